//! Errors of feature recognition.

/// Why recognition could not run on the given data or configuration.
///
/// "Nothing found" is not an error: detection returns an empty list and LCS
/// search returns `None`. Errors are for data that cannot be processed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum FeatureError {
    /// The map is smaller than recognition needs.
    #[error("height map of {columns}×{rows} pixels is too small (at least {min}×{min} needed)")]
    MapTooSmall {
        /// Columns of the map.
        columns: usize,
        /// Rows of the map.
        rows: usize,
        /// Smallest accepted side, pixels.
        min: usize,
    },
    /// The map's arrays do not match its size.
    #[error("height map of {columns}×{rows} pixels holds {z_len} heights and {time_len} times")]
    InconsistentMap {
        /// Columns of the map.
        columns: usize,
        /// Rows of the map.
        rows: usize,
        /// Length of `z_counts`.
        z_len: usize,
        /// Length of `time_s`.
        time_len: usize,
    },
    /// A height or time is NaN or infinite.
    #[error("height map has a non-finite {what} at column {column}, row {row}")]
    NonFinite {
        /// `height` or `time`.
        what: &'static str,
        /// Column of the first offending pixel.
        column: usize,
        /// Row of the first offending pixel.
        row: usize,
    },
    /// The map's origin or pixel step is not usable.
    #[error("height map geometry is invalid: {0}")]
    InvalidGeometry(&'static str),
    /// A configuration field is out of its valid range.
    #[error("configuration field `{field}` is invalid: {reason}")]
    InvalidConfig {
        /// The field's name.
        field: &'static str,
        /// What is wrong with it.
        reason: &'static str,
    },
    /// Too few features for a statistic (e.g. lattice vectors).
    #[error("{needed} features are needed, {found} were given")]
    TooFewFeatures {
        /// How many are needed.
        needed: usize,
        /// How many there were.
        found: usize,
    },
    /// A feature index is out of range.
    #[error("feature index {index} is out of range (there are {len})")]
    IndexOutOfRange {
        /// The index given.
        index: usize,
        /// Number of features.
        len: usize,
    },
}

/// Checks that `value` is finite and > 0.
pub(crate) fn positive(field: &'static str, value: f64) -> Result<(), FeatureError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(FeatureError::InvalidConfig {
            field,
            reason: "must be a finite number > 0",
        })
    }
}
