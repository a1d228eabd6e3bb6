//! Errors of the FOS operations.

use spm_features::FeatureError;
use spm_hal::{CountPoint, ErrorKind, FrameError};

/// Why an FOS operation failed. Generic over the backend's error type `E`,
/// whose [`ErrorKind`] is exposed by [`FosError::instrument_kind`].
///
/// Outcomes that are part of normal operation (attachment timed out, a
/// skipping run gave up on unstable drift) are *not* errors: they are
/// reported in the operation's outcome type.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FosError<E: spm_hal::Error> {
    /// The instrument failed.
    #[error("instrument error ({kind}): {source}", kind = .0.kind(), source = .0)]
    Instrument(#[source] E),
    /// The instrument returned a frame that does not fit its request.
    #[error("malformed frame: {0}")]
    Frame(#[source] FrameError),
    /// Recognition could not process a frame.
    #[error("recognition failed: {0}")]
    Recognition(#[source] FeatureError),
    /// The tracked feature was not found where it was expected.
    #[error("feature lost: nothing recognised within {radius_counts} counts of ({}, {})", .expected.x, .expected.y)]
    FeatureLost {
        /// Where the feature was expected, counts.
        expected: CountPoint,
        /// The capture radius that was searched, counts.
        radius_counts: f64,
    },
    /// The direct and counter frames share no feature.
    #[error("counter-scan: no common feature ({direct} direct, {counter} counter features)")]
    NoCommonFeature {
        /// Features in the direct frame.
        direct: usize,
        /// Features in the counter frame.
        counter: usize,
    },
    /// The backend lacks a capability the operation needs.
    #[error("the instrument does not support {0}")]
    Unsupported(&'static str),
    /// A parameter is out of its valid range.
    #[error("parameter `{field}` is invalid: {reason}")]
    InvalidParameter {
        /// The parameter's name.
        field: &'static str,
        /// What is wrong with it.
        reason: &'static str,
    },
}

impl<E: spm_hal::Error> FosError<E> {
    /// The backend's error kind when the instrument failed.
    pub fn instrument_kind(&self) -> Option<ErrorKind> {
        match self {
            Self::Instrument(e) => Some(e.kind()),
            _ => None,
        }
    }

    /// True when retrying the operation may help (transient instrument
    /// failures and lost features).
    pub fn is_transient(&self) -> bool {
        match self {
            Self::Instrument(e) => e.kind().is_transient(),
            Self::FeatureLost { .. } => true,
            _ => false,
        }
    }

    pub(crate) fn instrument(error: E) -> Self {
        Self::Instrument(error)
    }
}

impl<E: spm_hal::Error> From<FrameError> for FosError<E> {
    fn from(error: FrameError) -> Self {
        Self::Frame(error)
    }
}

impl<E: spm_hal::Error> From<FeatureError> for FosError<E> {
    fn from(error: FeatureError) -> Self {
        Self::Recognition(error)
    }
}

/// Checks a parameter is finite and > 0.
pub(crate) fn positive<E: spm_hal::Error>(
    field: &'static str,
    value: f64,
) -> Result<(), FosError<E>> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(FosError::InvalidParameter {
            field,
            reason: "must be a finite number > 0",
        })
    }
}
