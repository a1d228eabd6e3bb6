//! Unit newtypes: scanner counts, nanometres, seconds, radians.
//!
//! Each wraps an `f64` whose unit is in the type's name. Arithmetic is defined
//! where it is dimensionally meaningful (sum and difference of like quantities,
//! scaling by a plain number); ratios and products go through [`value`](Counts::value)
//! and the explicit conversions in this module.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::ops::{Add, AddAssign, Div, Mul, Neg, Sub, SubAssign};

macro_rules! unit_newtype {
    ($(#[$meta:meta])* $name:ident, $suffix:literal) => {
        $(#[$meta])*
        #[derive(Clone, Copy, Debug, Default, PartialEq, PartialOrd, Serialize, Deserialize)]
        #[serde(transparent)]
        pub struct $name(pub f64);

        impl $name {
            /// Zero of this unit.
            pub const ZERO: Self = Self(0.0);

            /// The bare number in this unit.
            #[inline]
            pub const fn value(self) -> f64 {
                self.0
            }

            /// Absolute value.
            #[inline]
            pub fn abs(self) -> Self {
                Self(self.0.abs())
            }

            /// True when the value is neither NaN nor infinite.
            #[inline]
            pub fn is_finite(self) -> bool {
                self.0.is_finite()
            }

            /// The smaller of two values (NaN-propagating like `f64::min`).
            #[inline]
            pub fn min(self, other: Self) -> Self {
                Self(self.0.min(other.0))
            }

            /// The larger of two values.
            #[inline]
            pub fn max(self, other: Self) -> Self {
                Self(self.0.max(other.0))
            }
        }

        impl Add for $name {
            type Output = Self;
            #[inline]
            fn add(self, rhs: Self) -> Self {
                Self(self.0 + rhs.0)
            }
        }
        impl Sub for $name {
            type Output = Self;
            #[inline]
            fn sub(self, rhs: Self) -> Self {
                Self(self.0 - rhs.0)
            }
        }
        impl AddAssign for $name {
            #[inline]
            fn add_assign(&mut self, rhs: Self) {
                self.0 += rhs.0;
            }
        }
        impl SubAssign for $name {
            #[inline]
            fn sub_assign(&mut self, rhs: Self) {
                self.0 -= rhs.0;
            }
        }
        impl Neg for $name {
            type Output = Self;
            #[inline]
            fn neg(self) -> Self {
                Self(-self.0)
            }
        }
        impl Mul<f64> for $name {
            type Output = Self;
            #[inline]
            fn mul(self, rhs: f64) -> Self {
                Self(self.0 * rhs)
            }
        }
        impl Mul<$name> for f64 {
            type Output = $name;
            #[inline]
            fn mul(self, rhs: $name) -> $name {
                $name(self * rhs.0)
            }
        }
        impl Div<f64> for $name {
            type Output = Self;
            #[inline]
            fn div(self, rhs: f64) -> Self {
                Self(self.0 / rhs)
            }
        }
        /// The ratio of two like quantities is a plain number.
        impl Div for $name {
            type Output = f64;
            #[inline]
            fn div(self, rhs: Self) -> f64 {
                self.0 / rhs.0
            }
        }
        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                if let Some(precision) = f.precision() {
                    write!(f, "{:.*} {}", precision, self.0, $suffix)
                } else {
                    write!(f, "{} {}", self.0, $suffix)
                }
            }
        }
    };
}

unit_newtype!(
    /// A scanner coordinate or displacement in DAC counts (integer at the
    /// instrument, fractional once measured sub-count).
    Counts,
    "counts"
);
unit_newtype!(
    /// A physical length in nanometres.
    Nanometres,
    "nm"
);
unit_newtype!(
    /// A time or duration in seconds.
    Seconds,
    "s"
);
unit_newtype!(
    /// An angle in radians.
    Radians,
    "rad"
);

impl Radians {
    /// From degrees.
    #[inline]
    pub fn from_degrees(degrees: f64) -> Self {
        Self(degrees.to_radians())
    }
    /// In degrees.
    #[inline]
    pub fn to_degrees(self) -> f64 {
        self.0.to_degrees()
    }
}

impl Nanometres {
    /// From ångströms (1 Å = 0.1 nm).
    #[inline]
    pub fn from_angstroms(angstroms: f64) -> Self {
        Self(angstroms * 0.1)
    }
    /// From picometres.
    #[inline]
    pub fn from_picometres(picometres: f64) -> Self {
        Self(picometres * 1e-3)
    }
    /// In picometres.
    #[inline]
    pub fn to_picometres(self) -> f64 {
        self.0 * 1e3
    }
}

impl Counts {
    /// The nearest integer DAC code, or `None` when it does not fit an `i64`
    /// or the value is not finite.
    pub fn to_dac_code(self) -> Option<i64> {
        let rounded = self.0.round();
        if rounded.is_finite() && rounded.abs() < 9.0e15 {
            Some(rounded as i64)
        } else {
            None
        }
    }
}

/// A local calibration coefficient: nanometres per count.
#[derive(Clone, Copy, Debug, Default, PartialEq, PartialOrd, Serialize, Deserialize)]
#[serde(transparent)]
pub struct NmPerCount(pub f64);

impl NmPerCount {
    /// The bare number in nm/count.
    #[inline]
    pub const fn value(self) -> f64 {
        self.0
    }
}

impl Mul<Counts> for NmPerCount {
    type Output = Nanometres;
    #[inline]
    fn mul(self, rhs: Counts) -> Nanometres {
        Nanometres(self.0 * rhs.0)
    }
}

/// A speed along a path, scanner counts per second (a move's speed).
#[derive(Clone, Copy, Debug, Default, PartialEq, PartialOrd, Serialize, Deserialize)]
#[serde(transparent)]
pub struct CountsPerSecond(pub f64);

impl CountsPerSecond {
    /// The bare number in counts per second.
    #[inline]
    pub const fn value(self) -> f64 {
        self.0
    }

    /// The time to travel `length` at this speed (infinite at a speed ≤ 0).
    #[must_use]
    pub fn time_for(self, length: Counts) -> Seconds {
        if self.0 > 0.0 {
            Seconds(length.0.abs() / self.0)
        } else {
            Seconds(f64::INFINITY)
        }
    }
}

/// A local metric of the scanner: the 2 × 2 matrix that maps a count vector to nanometres,
/// `[[K̄x, K̄y·sin α], [0, K̄y·cos α]]` in the scanner-aligned frame (DESIGN §4), row-major.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct NmPerCountMatrix(pub [[f64; 2]; 2]);

impl NmPerCountMatrix {
    /// From the local calibration coefficients K̄x, K̄y (nm/count) and α (rad): K̄y sin α and
    /// K̄y cos α, the summands of eq. (3), formed here for the whole workspace.
    ///
    /// Implements eq. (3): Kx = K̄x + K̄y sin α, Ky = K̄y cos α, kept as three terms.
    #[must_use]
    pub fn from_lcc(kx: NmPerCount, ky: NmPerCount, alpha: Radians) -> Self {
        let (s, c) = alpha.0.sin_cos();
        Self([[kx.0, ky.0 * s], [0.0, ky.0 * c]])
    }

    /// The rows.
    #[must_use]
    pub const fn rows(self) -> [[f64; 2]; 2] {
        self.0
    }

    /// The image of a count vector, nm.
    #[must_use]
    pub fn apply(self, v: CountVector) -> (Nanometres, Nanometres) {
        let m = self.0;
        (
            Nanometres(m[0][0] * v.x.0 + m[0][1] * v.y.0),
            Nanometres(m[1][0] * v.x.0 + m[1][1] * v.y.0),
        )
    }

    /// The count vector whose image is `(x, y)` nm; `None` for a singular matrix.
    #[must_use]
    pub fn solve(self, x: Nanometres, y: Nanometres) -> Option<CountVector> {
        let m = self.0;
        let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
        if !(det.is_finite() && det.abs() > f64::MIN_POSITIVE) {
            return None;
        }
        Some(CountVector::new(
            Counts((m[1][1] * x.0 - m[0][1] * y.0) / det),
            Counts((m[0][0] * y.0 - m[1][0] * x.0) / det),
        ))
    }
}

/// A velocity in scanner counts per second (drift measured in scanner coordinates).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CountVelocity {
    /// X component, counts per second.
    pub x_counts_per_s: f64,
    /// Y component, counts per second.
    pub y_counts_per_s: f64,
}

impl CountVelocity {
    /// Zero velocity.
    pub const ZERO: Self = Self {
        x_counts_per_s: 0.0,
        y_counts_per_s: 0.0,
    };

    /// Magnitude in counts per second.
    pub fn norm_counts_per_s(self) -> f64 {
        self.x_counts_per_s.hypot(self.y_counts_per_s)
    }

    /// The displacement after `duration` at this velocity.
    pub fn displacement(self, duration: Seconds) -> CountVector {
        CountVector::new(
            Counts(self.x_counts_per_s * duration.0),
            Counts(self.y_counts_per_s * duration.0),
        )
    }
}

/// A velocity in nanometres per second (e.g. the true drift of the sample).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NmVelocity {
    /// X component, nm per second.
    pub x_nm_per_s: f64,
    /// Y component, nm per second.
    pub y_nm_per_s: f64,
}

impl NmVelocity {
    /// Magnitude in nm per second.
    pub fn norm_nm_per_s(self) -> f64 {
        self.x_nm_per_s.hypot(self.y_nm_per_s)
    }
}

/// A point of the lateral scanner field in counts.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CountPoint {
    /// X coordinate.
    pub x: Counts,
    /// Y coordinate.
    pub y: Counts,
}

/// A displacement in the lateral scanner field in counts.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CountVector {
    /// X component.
    pub x: Counts,
    /// Y component.
    pub y: Counts,
}

impl CountPoint {
    /// A point from two count values.
    #[inline]
    pub const fn new(x: Counts, y: Counts) -> Self {
        Self { x, y }
    }
    /// A point from two bare numbers of counts.
    #[inline]
    pub const fn from_counts(x_counts: f64, y_counts: f64) -> Self {
        Self {
            x: Counts(x_counts),
            y: Counts(y_counts),
        }
    }
    /// Euclidean distance in counts.
    #[inline]
    pub fn distance(self, other: Self) -> Counts {
        (other - self).norm()
    }
    /// True when both coordinates are finite.
    #[inline]
    pub fn is_finite(self) -> bool {
        self.x.is_finite() && self.y.is_finite()
    }
}

impl CountVector {
    /// A vector from two count values.
    #[inline]
    pub const fn new(x: Counts, y: Counts) -> Self {
        Self { x, y }
    }
    /// A vector from two bare numbers of counts.
    #[inline]
    pub const fn from_counts(x_counts: f64, y_counts: f64) -> Self {
        Self {
            x: Counts(x_counts),
            y: Counts(y_counts),
        }
    }
    /// Length in counts.
    #[inline]
    pub fn norm(self) -> Counts {
        Counts(self.x.0.hypot(self.y.0))
    }
    /// Dot product in counts².
    #[inline]
    pub fn dot_counts_squared(self, other: Self) -> f64 {
        self.x.0 * other.x.0 + self.y.0 * other.y.0
    }
    /// The velocity that covers this vector in `duration`.
    #[inline]
    pub fn per(self, duration: Seconds) -> CountVelocity {
        CountVelocity {
            x_counts_per_s: self.x.0 / duration.0,
            y_counts_per_s: self.y.0 / duration.0,
        }
    }
}

impl Sub for CountPoint {
    type Output = CountVector;
    #[inline]
    fn sub(self, rhs: Self) -> CountVector {
        CountVector::new(self.x - rhs.x, self.y - rhs.y)
    }
}
impl Add<CountVector> for CountPoint {
    type Output = CountPoint;
    #[inline]
    fn add(self, rhs: CountVector) -> CountPoint {
        CountPoint::new(self.x + rhs.x, self.y + rhs.y)
    }
}
impl Sub<CountVector> for CountPoint {
    type Output = CountPoint;
    #[inline]
    fn sub(self, rhs: CountVector) -> CountPoint {
        CountPoint::new(self.x - rhs.x, self.y - rhs.y)
    }
}
impl Add for CountVector {
    type Output = CountVector;
    #[inline]
    fn add(self, rhs: Self) -> Self {
        CountVector::new(self.x + rhs.x, self.y + rhs.y)
    }
}
impl Sub for CountVector {
    type Output = CountVector;
    #[inline]
    fn sub(self, rhs: Self) -> Self {
        CountVector::new(self.x - rhs.x, self.y - rhs.y)
    }
}
impl Neg for CountVector {
    type Output = CountVector;
    #[inline]
    fn neg(self) -> Self {
        CountVector::new(-self.x, -self.y)
    }
}
impl Mul<f64> for CountVector {
    type Output = CountVector;
    #[inline]
    fn mul(self, rhs: f64) -> Self {
        CountVector::new(self.x * rhs, self.y * rhs)
    }
}

/// A point in physical (sample) coordinates in nanometres.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NmPoint {
    /// X coordinate.
    pub x: Nanometres,
    /// Y coordinate.
    pub y: Nanometres,
}

impl NmPoint {
    /// A point from two bare numbers of nanometres.
    #[inline]
    pub const fn from_nm(x_nm: f64, y_nm: f64) -> Self {
        Self {
            x: Nanometres(x_nm),
            y: Nanometres(y_nm),
        }
    }
    /// Euclidean distance.
    #[inline]
    pub fn distance(self, other: Self) -> Nanometres {
        Nanometres((other.x.0 - self.x.0).hypot(other.y.0 - self.y.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn count_point_minus_vector_round_trips(ax in -1e6f64..1e6, ay in -1e6f64..1e6,
                                               vx in -1e6f64..1e6, vy in -1e6f64..1e6) {
            let a = CountPoint::from_counts(ax, ay);
            let v = CountVector::from_counts(vx, vy);
            let b = a + v;
            let back = b - a;
            prop_assert!((back.x.0 - vx).abs() <= 1e-9 * (1.0 + vx.abs() + ax.abs()));
            prop_assert!((back.y.0 - vy).abs() <= 1e-9 * (1.0 + vy.abs() + ay.abs()));
            prop_assert!(((b - v).x.0 - ax).abs() <= 1e-9 * (1.0 + vx.abs() + ax.abs()));
        }

        #[test]
        fn unit_arithmetic_is_linear(a in -1e9f64..1e9, b in -1e9f64..1e9, k in -1e3f64..1e3) {
            let (x, y) = (Nanometres(a), Nanometres(b));
            prop_assert_eq!((x + y) - y, Nanometres((a + b) - b));
            prop_assert_eq!(x * k, k * x);
            prop_assert_eq!(-(-x), x);
            prop_assert!(((x + y) * k).0 - (x * k + y * k).0 <= 1e-6 * (1.0 + (a.abs() + b.abs()) * k.abs()));
        }

        #[test]
        fn degrees_round_trip(d in -720.0f64..720.0) {
            prop_assert!((Radians::from_degrees(d).to_degrees() - d).abs() < 1e-9);
        }

        #[test]
        fn velocity_times_duration_is_displacement(vx in -1e3f64..1e3, vy in -1e3f64..1e3, t in 1e-3f64..1e3) {
            let v = CountVelocity { x_counts_per_s: vx, y_counts_per_s: vy };
            let d = v.displacement(Seconds(t));
            let back = d.per(Seconds(t));
            prop_assert!((back.x_counts_per_s - vx).abs() <= 1e-9 * (1.0 + vx.abs()));
            prop_assert!((back.y_counts_per_s - vy).abs() <= 1e-9 * (1.0 + vy.abs()));
        }
    }

    #[test]
    fn ratio_of_like_units_is_a_number() {
        assert_eq!(Counts(10.0) / Counts(4.0), 2.5);
        assert_eq!(NmPerCount(0.5) * Counts(4.0), Nanometres(2.0));
        assert_eq!(Nanometres::from_angstroms(4.0), Nanometres(0.4));
        assert_eq!(format!("{:.2}", Seconds(1.0 / 3.0)), "0.33 s");
        assert_eq!(Counts(2.5).to_dac_code(), Some(3));
        assert_eq!(Counts(f64::NAN).to_dac_code(), None);
    }
}
