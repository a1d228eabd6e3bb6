//! Faults on demand, the simulator's error type, and the fault log.

use serde::{Deserialize, Serialize};
use spm_hal::{ErrorKind, NmPoint, NmVelocity, Seconds};

/// The simulator's operations (trait calls), for fault triggers and errors.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Operation {
    /// `Microscope::now`.
    Now,
    /// `Microscope::wait`.
    Wait,
    /// `Microscope::position`.
    Position,
    /// `Microscope::move_to`.
    MoveTo,
    /// `Microscope::scan`.
    Scan,
    /// `Microscope::z_position`.
    ZPosition,
    /// The coarse stage (`CoarseZStage::step` / `position_steps`).
    CoarseZ,
}

/// What a fault does.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FaultKind {
    /// The call consumes `faults.timeout_duration_s` and fails with
    /// [`ErrorKind::Timeout`]; nothing else happens.
    Timeout,
    /// The call fails at once with [`ErrorKind::Communication`]; nothing else happens.
    Communication,
    /// The feedback loses the surface: a running scan or move stops there and
    /// fails with [`ErrorKind::FeedbackLost`] (time and position advance to the
    /// failure point); at an idle moment the next call fails. The feedback is
    /// re-established by the next call.
    FeedbackLost,
    /// The tip apex changes: the image shifts laterally by `jump` (a step in
    /// the apparent drift) and the contrast is multiplied by `contrast_factor`;
    /// with `ghost_amplitude > 0` a second apex at `ghost_offset` adds a ghost
    /// image of that relative amplitude (double tip). No error is returned.
    TipChange {
        /// Lateral jump of the image, nm.
        jump: NmPoint,
        /// Multiplier of the surface contrast (> 0).
        contrast_factor: f64,
        /// Offset of the second apex, nm.
        ghost_offset: NmPoint,
        /// Relative amplitude of the ghost image (0 = single tip).
        ghost_amplitude: f64,
    },
    /// The drift velocity jumps by `velocity` for `duration`. No error is returned.
    DriftBurst {
        /// Extra drift velocity, nm/s.
        velocity: NmVelocity,
        /// How long it lasts.
        duration: Seconds,
    },
}

/// When a scheduled fault fires.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FaultTrigger {
    /// At the next call of this operation (at its start).
    NextCall(Operation),
    /// At this instrument time (inside a running scan, move or wait, or, for
    /// call failures, at the first call starting afterwards).
    AtTime(Seconds),
}

/// What the log records.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FaultEventKind {
    /// A call timed out.
    Timeout,
    /// A call failed with a communication error.
    Communication,
    /// The feedback lost the surface.
    FeedbackLost,
    /// The tip changed.
    TipChange,
    /// A drift burst started (it lasts `duration_s`).
    DriftBurst,
    /// A spontaneous drift jump (part of the drift model).
    DriftJump,
}

/// One entry of the fault log.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FaultEvent {
    /// When it happened (instrument clock), s.
    pub time: Seconds,
    /// What happened.
    pub kind: FaultEventKind,
    /// How long its effect lasts (drift bursts), s; 0 for instantaneous events.
    pub duration: Seconds,
    /// The call during which it happened, if any.
    pub operation: Option<Operation>,
    /// True when scheduled through the API, false when drawn at random.
    pub scheduled: bool,
}

impl FaultEvent {
    /// True when the event's effect overlaps `[start, end]`.
    pub fn overlaps(&self, start: Seconds, end: Seconds) -> bool {
        self.time <= end && self.time + self.duration >= start
    }
}

/// The simulator's error; reports an [`ErrorKind`] through [`spm_hal::Error`].
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum SimError {
    /// The instrument did not answer in time.
    #[error("simulated instrument timed out during {operation:?} at t = {time}")]
    Timeout {
        /// The failed call.
        operation: Operation,
        /// When it failed.
        time: Seconds,
    },
    /// The link failed.
    #[error("simulated communication failure during {operation:?} at t = {time}")]
    Communication {
        /// The failed call.
        operation: Operation,
        /// When it failed.
        time: Seconds,
    },
    /// The feedback lost the surface.
    #[error("simulated feedback lost the surface during {operation:?} at t = {time}")]
    FeedbackLost {
        /// The failed call.
        operation: Operation,
        /// When it failed.
        time: Seconds,
    },
    /// The request is outside what the instrument can do.
    #[error("request out of range: {reason}")]
    OutOfRange {
        /// Why.
        reason: String,
    },
    /// The request is malformed (NaN, non-positive speed, …).
    #[error("invalid request: {reason}")]
    InvalidRequest {
        /// Why.
        reason: String,
    },
    /// A simulator could not be built from its configuration.
    #[error("invalid simulator configuration: {0}")]
    Config(#[from] crate::ValidationError),
}

impl spm_hal::Error for SimError {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::Timeout { .. } => ErrorKind::Timeout,
            Self::Communication { .. } => ErrorKind::Communication,
            Self::FeedbackLost { .. } => ErrorKind::FeedbackLost,
            Self::OutOfRange { .. } => ErrorKind::OutOfRange,
            Self::InvalidRequest { .. } | Self::Config(_) => ErrorKind::Other,
        }
    }
}
