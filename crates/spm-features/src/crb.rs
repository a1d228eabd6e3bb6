//! Cramér–Rao bounds of sub-pixel localisation.
//!
//! For a feature `f(x − x0, y − y0)` sampled on pixels with white noise σn,
//! the Fisher information of the position is `F = Σ ∇f ∇fᵀ / σn²` over the
//! pixels used, and any unbiased estimator has `var(x0) ≥ (F⁻¹)ₓₓ`. When the
//! amplitude, background (and width) are unknown too, they enter `F` as
//! nuisance parameters; for a symmetric feature in a symmetric window they
//! decouple from the position and do not raise the bound.
//!
//! For a Gaussian hill of amplitude A sampled densely over the whole plane
//! with pitch p, `Σ (∂f/∂x)² → π A² / (2 p²)`, which gives DESIGN §5's
//! `σx ≥ √(2/π) · p · σn / A` ([`design_cramer_rao`]), independent of the width.

use crate::error::{FeatureError, positive};
use crate::fit::gaussian_gradient;
use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};
use spm_hal::Counts;

/// A lower bound on the standard deviation of a position estimate.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CramerRaoBound {
    /// Bound on σ along x, counts.
    pub sigma_x: Counts,
    /// Bound on σ along y, counts.
    pub sigma_y: Counts,
}

impl CramerRaoBound {
    /// The bound on the per-axis RMS, `√((σx² + σy²)/2)`, counts.
    pub fn per_axis_rms(self) -> Counts {
        Counts(((self.sigma_x.value().powi(2) + self.sigma_y.value().powi(2)) / 2.0).sqrt())
    }
}

/// A Gaussian feature model in pixel units (the model [`crate::detect`] fits).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GaussianFeatureModel {
    /// Amplitude over background, Z counts (> 0).
    pub amplitude_z_counts: f64,
    /// Gaussian width σ, pixels (> 0).
    pub width_px: f64,
}

/// DESIGN §5's closed form `√(2/π) · p · σn / A`: the bound for a Gaussian
/// feature over an unbounded, densely sampled window.
pub fn design_cramer_rao(
    pixel_step: Counts,
    noise_sigma_z_counts: f64,
    amplitude_z_counts: f64,
) -> Counts {
    Counts(
        (2.0 / std::f64::consts::PI).sqrt() * pixel_step.value() * noise_sigma_z_counts
            / amplitude_z_counts,
    )
}

/// Inverts a Fisher matrix and returns the position bounds (first two
/// parameters), scaled by the pixel step.
fn bound_from_fisher(
    fisher: DMatrix<f64>,
    pixel_step: Counts,
) -> Result<CramerRaoBound, FeatureError> {
    let inverse = fisher.try_inverse().ok_or(FeatureError::InvalidConfig {
        field: "window",
        reason: "the Fisher information is singular (window too small or feature flat)",
    })?;
    let (vx, vy) = (inverse[(0, 0)], inverse[(1, 1)]);
    if !(vx.is_finite() && vy.is_finite() && vx >= 0.0 && vy >= 0.0) {
        return Err(FeatureError::InvalidConfig {
            field: "window",
            reason: "the Fisher information is not positive definite",
        });
    }
    Ok(CramerRaoBound {
        sigma_x: pixel_step * vx.sqrt(),
        sigma_y: pixel_step * vy.sqrt(),
    })
}

/// The bound for a Gaussian feature whose centre sits `centre_offset_px`
/// from a pixel centre, fitted over the pixels within `window_radius_px` of
/// the feature centre. With `nuisance`, the amplitude, width and background
/// are estimated too (the full 5-parameter Fisher matrix of the fit used by
/// [`crate::detect`]).
pub fn gaussian_cramer_rao(
    model: GaussianFeatureModel,
    centre_offset_px: (f64, f64),
    window_radius_px: f64,
    pixel_step: Counts,
    noise_sigma_z_counts: f64,
    nuisance: bool,
) -> Result<CramerRaoBound, FeatureError> {
    positive("amplitude_z_counts", model.amplitude_z_counts)?;
    positive("width_px", model.width_px)?;
    positive("window_radius_px", window_radius_px)?;
    positive("pixel_step", pixel_step.value())?;
    positive("noise_sigma_z_counts", noise_sigma_z_counts)?;
    let n = if nuisance { 5 } else { 2 };
    let mut fisher = DMatrix::<f64>::zeros(n, n);
    let p = [
        centre_offset_px.0,
        centre_offset_px.1,
        model.amplitude_z_counts,
        model.width_px,
        0.0,
    ];
    let rad = window_radius_px.ceil() as i64 + 1;
    let r2 = window_radius_px * window_radius_px;
    for y in -rad..=rad {
        for x in -rad..=rad {
            let (dx, dy) = (x as f64, y as f64);
            if (dx - p[0]).powi(2) + (dy - p[1]).powi(2) > r2 {
                continue;
            }
            let (_, g) = gaussian_gradient(&p, dx, dy);
            for i in 0..n {
                for j in 0..n {
                    fisher[(i, j)] += g[i] * g[j];
                }
            }
        }
    }
    fisher /= noise_sigma_z_counts * noise_sigma_z_counts;
    bound_from_fisher(fisher, pixel_step)
}

/// The bound for an arbitrary feature profile: `profile(dx_px, dy_px)` is the
/// noiseless height (Z counts) at offset `(dx, dy)` pixels from the feature
/// centre. The pixels are those of a `columns`×`rows` map within
/// `window_radius_px` of `centre_px` (fractional column, row). With
/// `nuisance`, an unknown height scale and background are estimated too.
/// Derivatives are central differences.
#[allow(clippy::too_many_arguments)]
pub fn profile_cramer_rao(
    profile: impl Fn(f64, f64) -> f64,
    centre_px: (f64, f64),
    columns: usize,
    rows: usize,
    window_radius_px: f64,
    pixel_step: Counts,
    noise_sigma_z_counts: f64,
    nuisance: bool,
) -> Result<CramerRaoBound, FeatureError> {
    positive("window_radius_px", window_radius_px)?;
    positive("pixel_step", pixel_step.value())?;
    positive("noise_sigma_z_counts", noise_sigma_z_counts)?;
    let n = if nuisance { 4 } else { 2 };
    let mut fisher = DMatrix::<f64>::zeros(n, n);
    let h = 1e-4;
    let r2 = window_radius_px * window_radius_px;
    for row in 0..rows {
        for column in 0..columns {
            let dx = column as f64 - centre_px.0;
            let dy = row as f64 - centre_px.1;
            if dx * dx + dy * dy > r2 {
                continue;
            }
            // d/dx0 f(x − x0) = −f'(x − x0).
            let gx = -(profile(dx + h, dy) - profile(dx - h, dy)) / (2.0 * h);
            let gy = -(profile(dx, dy + h) - profile(dx, dy - h)) / (2.0 * h);
            let g = [gx, gy, profile(dx, dy), 1.0];
            if !g.iter().all(|v| v.is_finite()) {
                return Err(FeatureError::InvalidConfig {
                    field: "profile",
                    reason: "the profile is not finite in the window",
                });
            }
            for i in 0..n {
                for j in 0..n {
                    fisher[(i, j)] += g[i] * g[j];
                }
            }
        }
    }
    fisher /= noise_sigma_z_counts * noise_sigma_z_counts;
    bound_from_fisher(fisher, pixel_step)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn check(width_px: f64, radius_px: f64, nuisance: bool, expected_ratio: (f64, f64)) {
        let model = GaussianFeatureModel {
            amplitude_z_counts: 10.0,
            width_px,
        };
        let bound =
            gaussian_cramer_rao(model, (0.0, 0.0), radius_px, Counts(2.0), 1.0, nuisance).unwrap();
        let closed = design_cramer_rao(Counts(2.0), 1.0, 10.0);
        let ratio = bound.sigma_x / closed;
        assert!(
            ratio >= expected_ratio.0 && ratio <= expected_ratio.1,
            "width {width_px} radius {radius_px}: ratio {ratio}"
        );
        assert!((bound.sigma_x - bound.sigma_y).abs().value() < 1e-9);
    }

    #[test]
    fn gaussian_bound_tends_to_the_design_closed_form() {
        // Dense sampling, big window: the closed form.
        check(4.0, 30.0, false, (0.999, 1.001));
        check(4.0, 30.0, true, (0.999, 1.01));
        // A 2.2σ window keeps most of the information.
        check(3.0, 6.6, false, (1.0, 1.08));
        // Coarse sampling (σ = 0.8 px) still close; truncation raises the bound.
        check(0.8, 10.0, false, (0.95, 1.05));
        check(3.0, 3.0, false, (1.2, 2.0));
    }

    #[test]
    fn profile_bound_matches_the_gaussian_bound() {
        let s: f64 = 2.5;
        let gauss = |dx: f64, dy: f64| 7.0 * (-(dx * dx + dy * dy) / (2.0 * s * s)).exp();
        let a =
            profile_cramer_rao(gauss, (10.3, 9.8), 21, 21, 6.0, Counts(1.5), 0.7, false).unwrap();
        let b = gaussian_cramer_rao(
            GaussianFeatureModel {
                amplitude_z_counts: 7.0,
                width_px: s,
            },
            (0.3, -0.2),
            6.0,
            Counts(1.5),
            0.7,
            false,
        )
        .unwrap();
        assert!((a.sigma_x / b.sigma_x - 1.0).abs() < 1e-5);
        assert!((a.sigma_y / b.sigma_y - 1.0).abs() < 1e-5);
    }

    #[test]
    fn invalid_inputs_are_errors() {
        let model = GaussianFeatureModel {
            amplitude_z_counts: 1.0,
            width_px: 1.0,
        };
        assert!(gaussian_cramer_rao(model, (0.0, 0.0), 3.0, Counts(1.0), 0.0, false).is_err());
        assert!(gaussian_cramer_rao(model, (0.0, 0.0), f64::NAN, Counts(1.0), 1.0, false).is_err());
    }
}
