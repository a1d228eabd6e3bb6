//! Polynomial regression surfaces of Lapshin's distributed calibration: the 2-D polynomials of
//! eq. (6) (term order `1, y, x, xy, y², x², …`, see [`term_powers`]) fitted by weighted least
//! squares at a given degree ([`fit`]) or at a degree chosen by BIC or cross-validation
//! ([`select_degree`]); the statistics σ (eq. 14, [`sigma`]) and Δmax (eq. 13, [`delta_max`]);
//! the products of eq. (11) ([`product_values`]); and analytic x- and y-antiderivatives
//! ([`Polynomial2::integrate_x`], [`Polynomial2::integrate_y`]) for the image correction of
//! eqs. (9) and (12).
//!
//! It is the workspace's numerics kernel: [`least_squares`] (dense, with sign constraints,
//! leverage and covariance), [`generalised_least_squares`] (correlated blocks of observations
//! with their covariances), [`minimum_norm_least_squares`] (rank-revealing, with a row mask
//! and per-group offsets eliminated exactly) and [`minimum_norm_solve`] (a normal system a
//! caller accumulated) are its linear solvers, [`median`], [`upper_median`] and [`rms`] its
//! sample statistics; no other crate decomposes or inverts a matrix to fit
//! (`tests/tests/it/repository.rs`, `linear_algebra_solves_only_in_the_numerics_kernel`).
//!
//! Pure: no IO, no clock, no random numbers. Every failure is a typed [`RegressionError`];
//! no function returns NaN for finite input.
#![doc = include_str!("../README.md")]

#[cfg(feature = "test-support")]
pub mod bench_support;
mod error;
mod fit;
mod form;
mod gls;
mod lsq;
mod polynomial;
mod rank;
mod select;
mod stats;

pub use error::RegressionError;
pub use fit::{FitOptions, Observations, PolyFit, fit, leverages, standard_errors};
pub use form::{ExactForm, FormObservations, FormScatter, fit_exact_form};
pub use gls::{GeneralisedFit, SINGULAR_CORRELATION, generalised_least_squares};
pub use lsq::{LinearFit, least_squares};
pub use polynomial::{MAX_DEGREE, Polynomial2, n_terms, term_index, term_powers};
pub use rank::{
    FactoredDesign, MINIMUM_NORM_TOLERANCE, MinimumNormFit, minimum_norm_least_squares,
    minimum_norm_solve,
};
pub use select::{
    Criterion, DegreeScore, Selection, SelectionOptions, information_criterion, select_degree,
};
pub use stats::{
    DeltaMax, Field, degree_supported, delta_max, distinct_places, joint_outliers, median,
    product_values, rms, sigma, upper_median,
};
