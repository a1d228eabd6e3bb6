//! Keys cubic convolution: the band-limited interpolation a virtual scan resamples with.
//!
//! The kernel (Keys 1981, a = −1/2) is
//!
//! ```text
//! w(s) = 3/2·|s|³ − 5/2·|s|² + 1            for |s| ≤ 1
//! w(s) = −1/2·|s|³ + 5/2·|s|² − 4·|s| + 2    for 1 < |s| < 2
//! w(s) = 0                                  otherwise
//! ```
//!
//! applied separably over the 4 × 4 samples around the point. It passes every sample
//! unchanged, reproduces polynomials up to degree 2 exactly (third-order accurate), and its
//! frequency response at a half-pixel offset is `9/8·cos(ω/2) − 1/8·cos(3ω/2)` for a sampled
//! sinusoid of ω radians per pixel (the tests check both closed forms).

/// The Keys cubic-convolution kernel with a = −1/2 at offset `s` (pixels).
#[must_use]
pub fn keys_kernel(s: f64) -> f64 {
    let s = s.abs();
    if s <= 1.0 {
        (1.5 * s - 2.5) * s * s + 1.0
    } else if s < 2.0 {
        ((-0.5 * s + 2.5) * s - 4.0) * s + 2.0
    } else {
        0.0
    }
}

/// A row-major grid of samples at integer coordinates `(column, row)`.
#[derive(Clone, Debug, PartialEq)]
pub struct Grid<'a> {
    /// Samples, `[row * columns + column]`.
    pub values: &'a [f64],
    /// Columns.
    pub columns: usize,
    /// Rows.
    pub rows: usize,
}

impl Grid<'_> {
    /// The interpolated value at the fractional coordinate `(column, row)`, or `None` when
    /// the 4 × 4 support leaves the grid (the point must lie in `[1, columns − 2]` ×
    /// `[1, rows − 2]`) or the coordinate is not finite.
    #[must_use]
    pub fn keys(&self, column: f64, row: f64) -> Option<f64> {
        if !(column.is_finite() && row.is_finite()) {
            return None;
        }
        let max_column = self.columns.checked_sub(2)? as f64;
        let max_row = self.rows.checked_sub(2)? as f64;
        if column < 1.0 || row < 1.0 || column > max_column || row > max_row {
            return None;
        }
        // floor(column) in [1, columns − 2]; the support is floor − 1 ..= floor + 2, clipped
        // at the upper edge where the weight of the clipped sample is exactly zero.
        let c0 = column.floor() as usize;
        let r0 = row.floor() as usize;
        let fc = column - c0 as f64;
        let fr = row - r0 as f64;
        let mut sum = 0.0;
        for dr in 0..4usize {
            let r = r0 + dr;
            let Some(r) = r.checked_sub(1) else { continue };
            let wr = keys_kernel(fr - (dr as f64 - 1.0));
            if wr == 0.0 {
                continue;
            }
            for dc in 0..4usize {
                let c = c0 + dc;
                let Some(c) = c.checked_sub(1) else { continue };
                let wc = keys_kernel(fc - (dc as f64 - 1.0));
                if wc == 0.0 {
                    continue;
                }
                if c >= self.columns || r >= self.rows {
                    return None;
                }
                sum += wr * wc * *self.values.get(r * self.columns + c)?;
            }
        }
        Some(sum)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn the_kernel_is_an_interpolating_partition_of_unity() {
        for k in -3..=3 {
            let expected = if k == 0 { 1.0 } else { 0.0 };
            assert_eq!(keys_kernel(f64::from(k)), expected);
        }
        for i in 0..100 {
            let f = f64::from(i) / 100.0;
            let sum: f64 = (-1..=2).map(|k| keys_kernel(f - f64::from(k))).sum();
            assert!((sum - 1.0).abs() < 1e-14, "f = {f}: sum {sum}");
        }
    }

    #[test]
    fn quadratic_surfaces_are_reproduced_exactly() {
        let (nx, ny) = (12usize, 9usize);
        let q =
            |x: f64, y: f64| 0.3 + 1.7 * x - 0.4 * y + 0.05 * x * x - 0.02 * x * y + 0.07 * y * y;
        let values: Vec<f64> = (0..ny)
            .flat_map(|r| (0..nx).map(move |c| (c as f64, r as f64)))
            .map(|(x, y)| q(x, y))
            .collect();
        let grid = Grid {
            values: &values,
            columns: nx,
            rows: ny,
        };
        for (x, y) in [
            (1.0, 1.0),
            (3.37, 2.91),
            (10.0, 7.0),
            (5.5, 6.25),
            (9.999, 1.001),
        ] {
            let v = grid.keys(x, y).unwrap();
            assert!(
                (v - q(x, y)).abs() < 1e-11,
                "({x}, {y}): {v} vs {}",
                q(x, y)
            );
        }
        assert_eq!(grid.keys(0.99, 3.0), None);
        assert_eq!(grid.keys(3.0, 7.01), None);
        assert_eq!(grid.keys(f64::NAN, 3.0), None);
    }

    #[test]
    fn a_sampled_sinusoid_at_half_pixels_follows_the_closed_form_response() {
        // cos(ω x) sampled at integers, read at k + 1/2: cos(ω (k + 1/2)) · H(ω) with
        // H(ω) = 2·(w(1/2)·cos(ω/2) + w(3/2)·cos(3ω/2)) = 9/8·cos(ω/2) − 1/8·cos(3ω/2).
        let n = 40usize;
        for period_px in [4.0, 6.0, 11.0, 25.0] {
            let omega = 2.0 * std::f64::consts::PI / period_px;
            let values: Vec<f64> = (0..4)
                .flat_map(|_| (0..n).map(|c| (omega * c as f64).cos()))
                .collect();
            let grid = Grid {
                values: &values,
                columns: n,
                rows: 4,
            };
            let h = 1.125 * (omega / 2.0).cos() - 0.125 * (1.5 * omega).cos();
            for k in 1..n - 3 {
                let x = k as f64 + 0.5;
                let v = grid.keys(x, 1.5).unwrap();
                let expected = (omega * x).cos() * h;
                assert!(
                    (v - expected).abs() < 1e-12,
                    "period {period_px}: {v} vs {expected}"
                );
            }
            // A band-limited interpolation: the response stays within 1 % of unity for the
            // ≥ 11-pixel periods a lattice constant is sampled with.
            if period_px >= 11.0 {
                assert!((h - 1.0).abs() < 0.01, "period {period_px}: H = {h}");
            }
        }
    }
}
