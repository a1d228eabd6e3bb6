//! Typed errors of the regression crate.

/// Everything that can go wrong while building, fitting or evaluating a regression surface.
///
/// Every variant is data the caller can match on; no function of this crate returns NaN
/// instead of an error.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum RegressionError {
    /// Fewer usable points (positive weight) than polynomial terms (or than two for σ).
    #[error("too few points for degree {degree}: need at least {needed}, got {got}")]
    TooFewPoints {
        /// Requested degree.
        degree: u32,
        /// Minimum number of usable points.
        needed: usize,
        /// Number of usable points given.
        got: usize,
    },
    /// The least-squares problem is ill-conditioned (points too few, collinear or clustered).
    #[error(
        "ill-conditioned fit of degree {degree}: condition number {condition_number:e} exceeds {threshold:e}"
    )]
    IllConditioned {
        /// Requested degree.
        degree: u32,
        /// Condition number of the (normalised, weighted) design matrix; `inf` if singular.
        condition_number: f64,
        /// The threshold in force.
        threshold: f64,
    },
    /// An input value is NaN or infinite.
    #[error("non-finite {field} at index {index}")]
    NonFinite {
        /// Which input ("x", "y", "value", "coefficient", ...).
        field: &'static str,
        /// Index of the offending entry.
        index: usize,
    },
    /// Input slices of different lengths.
    #[error("length mismatch: {field} has {got} entries, expected {expected}")]
    LengthMismatch {
        /// Which input.
        field: &'static str,
        /// Expected length.
        expected: usize,
        /// Actual length.
        got: usize,
    },
    /// Degree above [`crate::MAX_DEGREE`].
    #[error("degree {degree} exceeds the supported maximum {max}")]
    DegreeTooHigh {
        /// Requested degree.
        degree: u32,
        /// Supported maximum.
        max: u32,
    },
    /// A weight is negative or non-finite.
    #[error("invalid weight {weight} at index {index}: weights must be finite and >= 0")]
    InvalidWeight {
        /// Index of the offending weight.
        index: usize,
        /// The weight.
        weight: f64,
    },
    /// A coefficient vector does not match the degree.
    #[error("coefficient vector has {got} entries, degree {degree} needs {expected}")]
    CoefficientCount {
        /// Degree.
        degree: u32,
        /// Expected number of coefficients.
        expected: usize,
        /// Given number.
        got: usize,
    },
    /// Any other invalid argument (bad normalisation scale, empty grid, zero folds ...).
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
}
