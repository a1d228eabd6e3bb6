//! Least-squares fit of an isotropic Gaussian hill on a constant background
//! (Levenberg–Marquardt), the sub-pixel localiser behind [`crate::detect`].
//!
//! Model, in pixel units: `z(x, y) = b + A·exp(−((x−x0)² + (y−y0)²) / (2 s²))`,
//! parameters `[x0, y0, A, s, b]`. With white noise the least-squares fit is
//! the maximum-likelihood estimate, which reaches the Cramér–Rao bound of
//! [`crate::crb`] asymptotically.
//!
//! The Cholesky solve inside the loop is a damped Gauss–Newton step of this nonlinear fit,
//! (JᵀJ + λ·diag JᵀJ)·δ = Jᵀr on a fixed 5 × 5 matrix, not a linear least-squares solve: it
//! stays here, named in the repository test's allow-list of the numerics kernel.

use nalgebra::{SMatrix, SVector};

/// Number of model parameters.
pub(crate) const NPAR: usize = 5;
type Mat = SMatrix<f64, NPAR, NPAR>;
type Vector = SVector<f64, NPAR>;

/// One sample of the fit window: pixel coordinates relative to the window
/// centre (whole pixels) and the (sign-corrected) height.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Sample {
    pub dx: f64,
    pub dy: f64,
    pub z: f64,
}

/// Result of a Gaussian fit, pixel units relative to the window centre.
#[derive(Clone, Copy, Debug)]
pub(crate) struct GaussianFit {
    /// `[x0, y0, A, s, b]`.
    pub params: [f64; NPAR],
    /// Residual sum of squares.
    pub rss: f64,
    /// Total sum of squares about the window mean.
    pub tss: f64,
    /// Number of samples.
    pub n: usize,
    /// Covariance of the parameters per unit noise variance, `(JᵀJ)⁻¹`.
    pub unit_covariance: Mat,
}

/// Gaussian value and the gradient with respect to the parameters.
#[inline]
pub(crate) fn gaussian_gradient(p: &[f64; NPAR], dx: f64, dy: f64) -> (f64, [f64; NPAR]) {
    let [x0, y0, a, s, b] = *p;
    let ux = dx - x0;
    let uy = dy - y0;
    let r2 = ux * ux + uy * uy;
    let inv_s2 = 1.0 / (s * s);
    let e = (-0.5 * r2 * inv_s2).exp();
    let ae = a * e * inv_s2;
    (b + a * e, [ae * ux, ae * uy, e, ae * r2 / s, 1.0])
}

/// Integer grid indices of the samples (their offsets are whole pixels):
/// the Gaussian is separable, so each evaluation needs only one exponential
/// per grid column and per grid row, not one per sample.
struct Grid {
    /// Smallest offset along both axes.
    min: f64,
    /// Table length.
    len: usize,
    /// `(column, row)` table index of every sample.
    index: Vec<(usize, usize)>,
}

impl Grid {
    fn new(samples: &[Sample]) -> Self {
        let (mut min, mut max) = (f64::INFINITY, f64::NEG_INFINITY);
        for s in samples {
            min = min.min(s.dx).min(s.dy);
            max = max.max(s.dx).max(s.dy);
        }
        let min = min.floor();
        let len = if max >= min {
            (max - min) as usize + 1
        } else {
            0
        };
        let last = len.saturating_sub(1);
        // Offsets are whole pixels: truncation after adding ½ is exact rounding.
        let index = samples
            .iter()
            .map(|s| {
                (
                    ((s.dx - min + 0.5).max(0.0) as usize).min(last),
                    ((s.dy - min + 0.5).max(0.0) as usize).min(last),
                )
            })
            .collect();
        Self { min, len, index }
    }
}

/// Cost, JᵀJ and Jᵀr at `p` (hot loop: separable exponentials, plain arrays,
/// upper triangle only).
fn evaluate(samples: &[Sample], grid: &Grid, p: &[f64; NPAR]) -> (f64, Mat, Vector) {
    let [x0, y0, a, s, b] = *p;
    let inv_s2 = 1.0 / (s * s);
    let half_inv_s2 = -0.5 * inv_s2;
    let inv_s = 1.0 / s;
    let mut ex = [0.0f64; 64];
    let mut ey = [0.0f64; 64];
    let table = grid.len <= 64;
    if table {
        for k in 0..grid.len {
            let u = grid.min + k as f64;
            ex[k] = (half_inv_s2 * (u - x0) * (u - x0)).exp();
            ey[k] = (half_inv_s2 * (u - y0) * (u - y0)).exp();
        }
    }
    let mut h = [0.0f64; 15];
    let mut g = [0.0f64; NPAR];
    let mut cost = 0.0;
    for (sample, &(ci, ri)) in samples.iter().zip(&grid.index) {
        let ux = sample.dx - x0;
        let uy = sample.dy - y0;
        let r2 = ux * ux + uy * uy;
        let e = if table {
            ex[ci] * ey[ri]
        } else {
            (half_inv_s2 * r2).exp()
        };
        let ae = a * e * inv_s2;
        let j = [ae * ux, ae * uy, e, ae * r2 * inv_s, 1.0];
        let r = sample.z - (b + a * e);
        cost += r * r;
        let mut k = 0;
        for i in 0..NPAR {
            g[i] += j[i] * r;
            for jj in i..NPAR {
                h[k] += j[i] * j[jj];
                k += 1;
            }
        }
    }
    let mut jtj = Mat::zeros();
    let mut k = 0;
    for i in 0..NPAR {
        for jj in i..NPAR {
            jtj[(i, jj)] = h[k];
            jtj[(jj, i)] = h[k];
            k += 1;
        }
    }
    (cost, jtj, Vector::from(g))
}

/// Fits the model from `init`. Returns `None` when the fit does not converge
/// to a finite hill (A > 0, s within `[s_min, s_max]`). With `fix_width` the
/// width stays at `init[3]` (a 4-parameter fit).
pub(crate) fn fit_gaussian(
    samples: &[Sample],
    init: [f64; NPAR],
    s_min: f64,
    s_max: f64,
    max_iterations: usize,
    fix_width: bool,
) -> Option<GaussianFit> {
    if samples.len() <= NPAR {
        return None;
    }
    let grid = Grid::new(samples);
    let evaluate = |p: &[f64; NPAR]| {
        let (cost, mut jtj, mut jtr) = evaluate(samples, &grid, p);
        if fix_width {
            for i in 0..NPAR {
                jtj[(3, i)] = 0.0;
                jtj[(i, 3)] = 0.0;
            }
            jtj[(3, 3)] = 1.0;
            jtr[3] = 0.0;
        }
        (cost, jtj, jtr)
    };
    let mut p = init;
    let (mut cost, mut jtj, mut jtr) = evaluate(&p);
    let mut lambda = 1e-4;
    let mut converged = false;
    let mut last_step_px = f64::INFINITY;
    for _ in 0..max_iterations {
        let mut a = jtj;
        for i in 0..NPAR {
            a[(i, i)] *= 1.0 + lambda;
            a[(i, i)] += 1e-12;
        }
        let Some(chol) = a.cholesky() else {
            lambda *= 10.0;
            continue;
        };
        let delta = chol.solve(&jtr);
        let mut trial = p;
        for i in 0..NPAR {
            trial[i] += delta[i];
        }
        // Keep the width positive and bounded; a step that leaves the box is damped.
        let plausible = trial[3] > 0.25 * s_min
            && trial[3] < 4.0 * s_max
            && trial.iter().all(|v| v.is_finite());
        if !plausible {
            lambda *= 10.0;
            if lambda > 1e8 {
                break;
            }
            continue;
        }
        let (trial_cost, trial_jtj, trial_jtr) = evaluate(&trial);
        if trial_cost.is_finite() && trial_cost <= cost {
            // Near the minimum the steps shrink about quadratically: after a
            // step below 0.01 px the remaining error is far below any
            // achievable localisation precision.
            let small_step = delta[0].abs() < 1e-2
                && delta[1].abs() < 1e-2
                && delta[3].abs() < 1e-2 * trial[3].abs();
            let small_gain = cost - trial_cost <= 1e-10 * cost.max(f64::MIN_POSITIVE);
            last_step_px = delta[0].hypot(delta[1]);
            p = trial;
            cost = trial_cost;
            jtj = trial_jtj;
            jtr = trial_jtr;
            lambda = (lambda * 0.1).max(1e-9);
            if small_step || small_gain {
                converged = true;
                break;
            }
        } else {
            lambda *= 10.0;
            if lambda > 1e8 {
                // No descent direction left: at a minimum to numerical precision.
                converged = true;
                break;
            }
        }
    }
    // An iteration limit reached while the position no longer moves is convergence too.
    converged |= last_step_px < 1e-2;
    let [_, _, amplitude, width, _] = p;
    let acceptable = converged
        && amplitude > 0.0
        && width >= s_min
        && width <= s_max
        && p.iter().all(|v| v.is_finite());
    if !acceptable {
        return None;
    }
    let unit_covariance = jtj.try_inverse()?;
    let n = samples.len();
    let mean = samples.iter().map(|s| s.z).sum::<f64>() / n as f64;
    let tss = samples.iter().map(|s| (s.z - mean).powi(2)).sum::<f64>();
    Some(GaussianFit {
        params: p,
        rss: cost,
        tss,
        n,
        unit_covariance,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn recovers_a_noiseless_gaussian() {
        let truth = [0.3, -0.2, 2.0, 1.7, 0.5];
        let mut samples = Vec::new();
        for y in -5..=5 {
            for x in -5..=5 {
                let (z, _) = gaussian_gradient(&truth, f64::from(x), f64::from(y));
                samples.push(Sample {
                    dx: f64::from(x),
                    dy: f64::from(y),
                    z,
                });
            }
        }
        let fit = fit_gaussian(&samples, [0.0, 0.0, 1.5, 1.2, 0.4], 0.3, 10.0, 50, false).unwrap();
        for (p, t) in fit.params.iter().zip(truth) {
            assert!((p - t).abs() < 1e-6, "{:?}", fit.params);
        }
    }
}
