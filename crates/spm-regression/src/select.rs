//! Automatic choice of the polynomial degree.
//!
//! Two criteria:
//! - [`Criterion::Bic`] (default): BIC = n ln(RSS_w/n) + p ln n over degrees 0 … max, p the number
//!   of terms; the smallest BIC wins. BIC is consistent (it picks the true degree with
//!   probability → 1 as n grows), cheap (one fit per degree) and needs no random split. RSS_w is
//!   floored at n·(10⁻¹² · rms(z))² so that exact data do not send ln to −∞ and let rounding
//!   noise choose among the degrees that all fit exactly; the floor then makes the smallest such
//!   degree win through the penalty term.
//! - [`Criterion::CrossValidation`]: k-fold cross-validation with deterministic folds (point i
//!   goes to fold i mod k, so no random numbers are needed and results are reproducible) and
//!   the one-standard-error rule: the smallest degree whose mean held-out squared error is within
//!   one standard error of the best degree's. Use it when the noise is not Gaussian/homoscedastic.
//!
//! Degrees that cannot be fitted (too few points, ill-conditioned) end the search; the best of
//! those fitted so far is returned.

use crate::RegressionError;
use crate::fit::{FitOptions, Observations, PolyFit, fit};

/// The degree-selection criterion.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Criterion {
    /// Bayesian information criterion (default).
    #[default]
    Bic,
    /// k-fold cross-validation with the one-standard-error rule.
    CrossValidation {
        /// Number of folds (≥ 2).
        folds: usize,
    },
}

/// Options of [`select_degree`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SelectionOptions {
    /// Highest degree tried (0 … max_degree).
    pub max_degree: u32,
    /// Criterion.
    pub criterion: Criterion,
    /// Options of every fit.
    pub fit: FitOptions,
}

impl Default for SelectionOptions {
    fn default() -> Self {
        Self {
            max_degree: 6,
            criterion: Criterion::Bic,
            fit: FitOptions::default(),
        }
    }
}

/// Score of one candidate degree (lower is better).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DegreeScore {
    /// Degree.
    pub degree: u32,
    /// BIC, or mean held-out squared error for cross-validation.
    pub score: f64,
    /// Standard error of the cross-validation score (0 for BIC).
    pub standard_error: f64,
}

/// Result of [`select_degree`].
#[derive(Debug, Clone, PartialEq)]
pub struct Selection {
    /// Fit of the chosen degree on all points.
    pub fit: PolyFit,
    /// Scores of every degree that could be fitted, ascending degree.
    pub scores: Vec<DegreeScore>,
}

impl Selection {
    /// The chosen degree.
    #[must_use]
    pub fn degree(&self) -> u32 {
        self.fit.surface.degree()
    }
}

fn bic(fit: &PolyFit, obs: &Observations<'_>) -> f64 {
    bic_score(
        fit.n_points,
        fit.surface.coefficients().len(),
        fit.weighted_rss,
        obs.value,
    )
}

/// [`information_criterion`] with the RSS floored at 10⁻¹² of the `values`' RMS per point, so
/// an exact fit does not score −∞.
pub(crate) fn bic_score(
    n_points: usize,
    n_params: usize,
    weighted_rss: f64,
    values: &[f64],
) -> f64 {
    let mean_sq = values.iter().map(|v| v * v).sum::<f64>() / values.len().max(1) as f64;
    let floor = n_points as f64 * (1e-12 * mean_sq.sqrt()).powi(2);
    information_criterion(n_points, n_params, weighted_rss.max(floor))
}

/// The Bayesian information criterion BIC = n·ln(RSS/n) + p·ln n of a least-squares fit of
/// `n_params` parameters to `n_points` observations with the weighted residual sum of squares
/// `weighted_rss` (lower is better; the RSS is floored at the smallest positive number). The
/// one criterion [`select_degree`] and every other model choice use.
#[must_use]
pub fn information_criterion(n_points: usize, n_params: usize, weighted_rss: f64) -> f64 {
    let n = n_points as f64;
    let rss = weighted_rss.max(f64::MIN_POSITIVE);
    n * (rss / n).ln() + n_params as f64 * n.ln()
}

/// Mean and standard error of the held-out weighted squared error over `folds` folds.
fn cross_validate(
    obs: &Observations<'_>,
    degree: u32,
    folds: usize,
    options: &FitOptions,
) -> Result<(f64, f64), RegressionError> {
    let mut fold_mse = Vec::with_capacity(folds);
    for f in 0..folds {
        let (mut x, mut y, mut z, mut w) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for i in (0..obs.len()).filter(|i| i % folds != f) {
            x.push(obs.x[i]);
            y.push(obs.y[i]);
            z.push(obs.value[i]);
            w.push(obs.weight_of(i));
        }
        let train = Observations::new(&x, &y, &z).with_weights(&w);
        let model = fit(&train, degree, options)?;
        let (mut se, mut sw) = (0.0, 0.0);
        for i in (0..obs.len()).filter(|i| i % folds == f) {
            let wi = obs.weight_of(i);
            let e = obs.value[i] - model.surface.evaluate(obs.x[i], obs.y[i]);
            se += wi * e * e;
            sw += wi;
        }
        if sw > 0.0 {
            fold_mse.push(se / sw);
        }
    }
    let k = fold_mse.len() as f64;
    if k < 1.0 {
        return Err(RegressionError::InvalidArgument(
            "no fold has held-out points with positive weight".into(),
        ));
    }
    let mean = fold_mse.iter().sum::<f64>() / k;
    let var = if k > 1.0 {
        fold_mse.iter().map(|m| (m - mean).powi(2)).sum::<f64>() / (k - 1.0)
    } else {
        0.0
    };
    Ok((mean, (var / k).sqrt()))
}

/// Fits degrees 0 … `options.max_degree` and returns the one the criterion prefers.
///
/// # Errors
/// Input errors of [`Observations::validate`]; the error of degree 0 if not even a constant
/// can be fitted; [`RegressionError::InvalidArgument`] for fewer than 2 folds.
pub fn select_degree(
    obs: &Observations<'_>,
    options: &SelectionOptions,
) -> Result<Selection, RegressionError> {
    obs.validate()?;
    if let Criterion::CrossValidation { folds } = options.criterion
        && folds < 2
    {
        return Err(RegressionError::InvalidArgument(format!(
            "cross-validation needs at least 2 folds, got {folds}"
        )));
    }
    let mut fits: Vec<PolyFit> = Vec::new();
    let mut scores: Vec<DegreeScore> = Vec::new();
    for degree in 0..=options.max_degree {
        let full = match fit(obs, degree, &options.fit) {
            Ok(f) => f,
            Err(e) if degree == 0 => return Err(e),
            Err(e) => {
                tracing::debug!(degree, error = %e, "degree search stops");
                break;
            }
        };
        let score = match options.criterion {
            Criterion::Bic => DegreeScore {
                degree,
                score: bic(&full, obs),
                standard_error: 0.0,
            },
            Criterion::CrossValidation { folds } => {
                match cross_validate(obs, degree, folds, &options.fit) {
                    Ok((score, standard_error)) => DegreeScore {
                        degree,
                        score,
                        standard_error,
                    },
                    Err(e) if degree == 0 => return Err(e),
                    Err(e) => {
                        tracing::debug!(degree, error = %e, "cross-validation stops");
                        break;
                    }
                }
            }
        };
        fits.push(full);
        scores.push(score);
    }
    let best = scores
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.score.total_cmp(&b.1.score))
        .map_or(0, |(i, _)| i);
    let chosen = match options.criterion {
        Criterion::Bic => best,
        Criterion::CrossValidation { .. } => {
            let limit = scores[best].score + scores[best].standard_error;
            scores.iter().position(|s| s.score <= limit).unwrap_or(best)
        }
    };
    let fit = fits.swap_remove(chosen);
    tracing::debug!(degree = fit.surface.degree(), "selected degree");
    Ok(Selection { fit, scores })
}
