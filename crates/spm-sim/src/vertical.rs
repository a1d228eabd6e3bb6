//! The Z manipulator's characteristic: extension (nm) as a nonlinear function of the Z
//! counts, varying over the lateral field (issue 15).
//!
//! Without [`ZManipulatorConfig`] the extension is `E = Kz·z` (the linear map the simulator
//! always had). With it,
//!
//! ```text
//! ζ = z / Hz,  sx = uₑx / H,  sy = uₑy / H
//! L(s) = 1 + gx·sx + gy·sy + r·(sx² + sy²) + ρ·sin(2π·uₑx / P)
//! E(z, s) = Kz·Hz·ζ·(1 + q·ζ + c·ζ²)·L(s)                       (nm)
//! Kz(z, s) = ∂E/∂z = Kz·(1 + 2q·ζ + 3c·ζ²)·L(s)                   (nm/count)
//! ```
//!
//! (Hz the Z half range, H the lateral half range, uₑ the effective lateral input). The
//! feedback holds the *extension* that puts the tip on the surface; the controller reads the
//! Z counts `E⁻¹(extension, s)`. The ripple term (ρ, P) is a Z effect a calibration with
//! low-degree surfaces does not model: tests use it as the "hidden" effect whose residual
//! must show up as structure.

pub use crate::config::ZManipulatorConfig;

/// The Z characteristic of a validated config (see the module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct ZMap {
    kz: f64,
    z_half_counts: f64,
    half_counts: f64,
    nonlinear: Option<ZManipulatorConfig>,
    /// Instrument time the Kz drift is evaluated at, s (set by the simulator as time goes).
    time_s: f64,
}

impl ZMap {
    /// The map: Kz at the centre (nm/count), the Z and lateral half ranges (counts).
    pub fn new(
        kz_nm_per_count: f64,
        z_half_counts: f64,
        half_counts: f64,
        nonlinear: Option<ZManipulatorConfig>,
    ) -> Self {
        Self {
            kz: kz_nm_per_count,
            z_half_counts,
            half_counts,
            nonlinear,
            time_s: 0.0,
        }
    }

    /// Sets the instrument time (s) of the Kz drift.
    #[inline]
    pub fn set_time(&mut self, time_s: f64) {
        self.time_s = time_s;
    }

    /// True when the manipulator is linear and uniform (E = Kz·z).
    pub fn is_linear(&self) -> bool {
        self.nonlinear.is_none()
    }

    /// The nominal (centre, z = 0) Kz, nm/count.
    pub fn kz0_nm_per_count(&self) -> f64 {
        self.kz
    }

    #[inline]
    fn lateral(&self, c: &ZManipulatorConfig, ue: [f64; 2]) -> f64 {
        let sx = ue[0] / self.half_counts;
        let sy = ue[1] / self.half_counts;
        let ripple = if c.ripple_fraction != 0.0 {
            c.ripple_fraction * (std::f64::consts::TAU * ue[0] / c.ripple_period_counts).sin()
        } else {
            0.0
        };
        (1.0 + c.lateral_gradient_x * sx
            + c.lateral_gradient_y * sy
            + c.lateral_radial * (sx * sx + sy * sy)
            + ripple)
            * (1.0 + c.kz_drift_per_hour * self.time_s / 3600.0)
    }

    /// Extension (nm) at Z counts `z` and effective lateral input `ue` (counts).
    #[inline]
    pub fn extension_nm(&self, z_counts: f64, ue: [f64; 2]) -> f64 {
        match &self.nonlinear {
            None => self.kz * z_counts,
            Some(c) => {
                let zeta = z_counts / self.z_half_counts;
                self.kz
                    * z_counts
                    * (1.0 + c.quadratic * zeta + c.cubic * zeta * zeta)
                    * self.lateral(c, ue)
            }
        }
    }

    /// Local Kz = ∂E/∂z (nm/count) at Z counts `z` and effective lateral input `ue`.
    #[inline]
    pub fn kz_nm_per_count(&self, z_counts: f64, ue: [f64; 2]) -> f64 {
        match &self.nonlinear {
            None => self.kz,
            Some(c) => {
                let zeta = z_counts / self.z_half_counts;
                self.kz
                    * (1.0 + 2.0 * c.quadratic * zeta + 3.0 * c.cubic * zeta * zeta)
                    * self.lateral(c, ue)
            }
        }
    }

    /// Z counts whose extension is `extension_nm` at `ue` (Newton; the characteristic is
    /// monotone for validated configs).
    #[inline]
    pub fn counts_of(&self, extension_nm: f64, ue: [f64; 2]) -> f64 {
        let Some(c) = &self.nonlinear else {
            return extension_nm / self.kz;
        };
        let l = self.lateral(c, ue);
        let target = extension_nm / (self.kz * l);
        // Solve z·(1 + qζ + cζ²) = target.
        let h = self.z_half_counts;
        let mut z = target;
        for _ in 0..30 {
            let zeta = z / h;
            let f = z * (1.0 + c.quadratic * zeta + c.cubic * zeta * zeta) - target;
            let d = 1.0 + 2.0 * c.quadratic * zeta + 3.0 * c.cubic * zeta * zeta;
            let step = f / d;
            z -= step;
            if step.abs() < 1e-9 {
                break;
            }
        }
        z
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config() -> ZManipulatorConfig {
        ZManipulatorConfig {
            quadratic: 0.04,
            cubic: 0.02,
            lateral_gradient_x: 0.015,
            lateral_gradient_y: -0.01,
            lateral_radial: 0.02,
            ripple_fraction: 0.003,
            ripple_period_counts: 16384.0,
            kz_drift_per_hour: 0.0,
        }
    }

    #[test]
    fn counts_invert_the_extension_and_kz_is_its_slope() {
        let m = ZMap::new(0.004, 32768.0, 32768.0, Some(config()));
        for (z, ue) in [
            (0.0, [0.0, 0.0]),
            (10000.0, [20000.0, -15000.0]),
            (-25000.0, [-30000.0, 30000.0]),
        ] {
            let e = m.extension_nm(z, ue);
            assert!((m.counts_of(e, ue) - z).abs() < 1e-6);
            let h = 0.5;
            let slope = (m.extension_nm(z + h, ue) - m.extension_nm(z - h, ue)) / (2.0 * h);
            assert!((slope - m.kz_nm_per_count(z, ue)).abs() < 1e-12);
        }
        let linear = ZMap::new(0.004, 32768.0, 32768.0, None);
        assert_eq!(linear.counts_of(0.4, [1.0, 2.0]), 100.0);
        assert!(crate::config::check_z_manipulator(&config()).is_ok());
        let bad = ZManipulatorConfig {
            quadratic: 0.3,
            cubic: -0.3,
            ..config()
        };
        assert!(crate::config::check_z_manipulator(&bad).is_err());
    }
}
