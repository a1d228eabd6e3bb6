//! Typed errors of the correction crate.

use spm_regression::RegressionError;

/// Everything that can go wrong while correcting coordinates or resampling an image.
///
/// Every variant is data the caller can match on; no function of this crate panics on data.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum CorrectionError {
    /// Two inputs that must have the same size do not.
    #[error("size mismatch: {what} has {got} entries, expected {expected}")]
    SizeMismatch {
        /// Which input.
        what: &'static str,
        /// Expected number of entries.
        expected: usize,
        /// Actual number.
        got: usize,
    },
    /// An input number is NaN or infinite where a finite value is required.
    #[error("non-finite {what} at index {index}")]
    NonFinite {
        /// Which input.
        what: &'static str,
        /// Index of the offending entry (0 for scalars).
        index: usize,
    },
    /// The surface set has no Z plane.
    #[error("the surface set has no Z plane")]
    EmptySurfaces,
    /// A surface set or plane is inconsistent (degree mismatch, duplicate plane, bad σ ...).
    #[error("invalid surface set: {0}")]
    InvalidSurfaces(String),
    /// A required optional surface is absent (e.g. product surfaces for eq. 12, or Kz).
    #[error("surface `{0}` is missing from the plane")]
    MissingSurface(&'static str),
    /// An empty image, path or grid, or a zero-sized dimension.
    #[error("empty input: {0}")]
    Empty(&'static str),
    /// An argument out of its domain (non-positive step, too many quadrature points ...).
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// A unit-step trajectory (eq. 5) has a step that is not 0 or ±1 count per axis.
    #[error(
        "step {index} of the trajectory is ({dx_counts}, {dy_counts}) counts; eq. (5) needs 0 or ±1"
    )]
    NotAUnitStep {
        /// Index of the step (between points index and index + 1).
        index: usize,
        /// x difference in counts.
        dx_counts: f64,
        /// y difference in counts.
        dy_counts: f64,
    },
    /// The sums of eq. (8) need an integer pixel step in counts.
    #[error("eq. (8) sums need an integer pixel step, got {pixel_step_counts} counts")]
    NonIntegerStep {
        /// The pixel step.
        pixel_step_counts: f64,
    },
    /// The corrected coordinates are not monotone where the inverse mapping needs them to be.
    #[error("corrected {axis} coordinates are not strictly monotone at {index} (folded map)")]
    NotMonotone {
        /// "x" (along a line) or "y" (across lines).
        axis: &'static str,
        /// Row (for x) or pixel index where monotonicity fails.
        index: usize,
    },
    /// A requested output grid is larger than allowed.
    #[error("output grid of {columns}×{rows} pixels exceeds the limit of {limit} pixels")]
    GridTooLarge {
        /// Columns requested.
        columns: usize,
        /// Rows requested.
        rows: usize,
        /// Maximum number of pixels.
        limit: usize,
    },
    /// The drift of a counter-scanned pair cannot be determined (no features, equal times).
    #[error("drift undetermined: {0}")]
    DriftUndetermined(String),
    /// The two images of a counter-scanned pair do not share their raster.
    #[error("the direct and counter images do not share a raster: {0}")]
    GeometryMismatch(String),
    /// A thread pool could not be built.
    #[error("thread pool: {0}")]
    ThreadPool(String),
    /// JSON (de)serialisation of a surface set failed.
    #[error("surface set JSON: {0}")]
    Json(String),
    /// An error from the regression crate (e.g. an invalid polynomial).
    #[error(transparent)]
    Regression(#[from] RegressionError),
}

/// Checks that every value of a slice is finite.
pub(crate) fn check_finite(what: &'static str, values: &[f64]) -> Result<(), CorrectionError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(CorrectionError::NonFinite { what, index }),
        None => Ok(()),
    }
}

/// Checks that a scalar is finite.
pub(crate) fn check_finite_scalar(what: &'static str, value: f64) -> Result<(), CorrectionError> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(CorrectionError::NonFinite { what, index: 0 })
    }
}
