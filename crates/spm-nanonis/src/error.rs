//! The backend's error type and its mapping to spm-hal's shared [`ErrorKind`].

use crate::codec::CodecError;
use spm_hal::ErrorKind;

/// What went wrong, in this backend's terms.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum NanonisErrorKind {
    /// One connection attempt failed (refused, unreachable); retried with backoff.
    Connect,
    /// The controller stayed unreachable through every reconnect attempt: the run cannot
    /// go on (mapped to [`ErrorKind::Aborted`] so that a calibration stops and can be
    /// resumed, instead of giving up every remaining node one after another).
    Unreachable,
    /// Reading or writing the socket failed, or the peer closed it mid-message.
    Io,
    /// No complete reply within the command's timeout.
    Timeout,
    /// The bytes received are not a valid reply (framing, schema, wrong command).
    Protocol,
    /// The controller answered with its error section set; the description says why.
    Controller,
    /// The controller refused the command as busy (not executed): safe to send again.
    Busy,
    /// The controller reported that the Z feedback is off (a safe-tip event or a crash).
    FeedbackOff,
    /// The controller's data do not fit the request (a short or NaN-padded frame).
    IncompleteData,
    /// The request is outside what the controller or this backend can do.
    OutOfRange,
    /// The request is invalid (not finite, negative).
    InvalidRequest,
    /// The controller's configuration does not fit the job (calibration, compensation).
    Configuration,
    /// Stopped on request.
    Aborted,
}

/// An error of the Nanonis backend: a kind, the command it happened in, and a message.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("nanonis{}: {message}", command.as_ref().map(|c| format!(" {c}")).unwrap_or_default())]
pub struct NanonisError {
    /// What kind of failure.
    pub kind: NanonisErrorKind,
    /// The command being executed, when there was one.
    pub command: Option<String>,
    /// What happened.
    pub message: String,
}

impl NanonisError {
    /// An error of `kind` with a message.
    pub fn new(kind: NanonisErrorKind, message: impl Into<String>) -> Self {
        Self {
            kind,
            command: None,
            message: message.into(),
        }
    }

    /// The same error attributed to `command`.
    pub fn in_command(mut self, command: &str) -> Self {
        self.command = Some(command.to_owned());
        self
    }

    /// A codec error in `command`'s reply.
    pub fn protocol(command: &str, error: &CodecError) -> Self {
        Self::new(NanonisErrorKind::Protocol, error.to_string()).in_command(command)
    }

    /// Classifies an error reply's description: the controller reports conditions as text;
    /// a lost feedback, a timeout, a range error and a busy or communication condition are
    /// recognised by their words, everything else is [`NanonisErrorKind::Controller`].
    pub fn from_error_reply(command: &str, description: &str) -> Self {
        let lower = description.to_ascii_lowercase();
        let kind = if lower.contains("feedback") || lower.contains("safe tip") {
            NanonisErrorKind::FeedbackOff
        } else if lower.contains("timed out") || lower.contains("timeout") {
            NanonisErrorKind::Timeout
        } else if lower.contains("out of range") || lower.contains("outside") {
            NanonisErrorKind::OutOfRange
        } else if lower.starts_with("busy") {
            NanonisErrorKind::Busy
        } else if lower.contains("communication") {
            NanonisErrorKind::Io
        } else {
            NanonisErrorKind::Controller
        };
        Self::new(
            kind,
            format!("the controller answered with an error: {description}"),
        )
        .in_command(command)
    }
}

impl spm_hal::Error for NanonisError {
    fn kind(&self) -> ErrorKind {
        match self.kind {
            NanonisErrorKind::Connect
            | NanonisErrorKind::Io
            | NanonisErrorKind::Protocol
            | NanonisErrorKind::Busy => ErrorKind::Communication,
            NanonisErrorKind::Timeout => ErrorKind::Timeout,
            NanonisErrorKind::FeedbackOff => ErrorKind::FeedbackLost,
            NanonisErrorKind::OutOfRange => ErrorKind::OutOfRange,
            NanonisErrorKind::Unreachable | NanonisErrorKind::Aborted => ErrorKind::Aborted,
            NanonisErrorKind::IncompleteData => ErrorKind::Communication,
            NanonisErrorKind::Controller
            | NanonisErrorKind::InvalidRequest
            | NanonisErrorKind::Configuration => ErrorKind::Other,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use spm_hal::Error as _;

    fn check(description: &str, expected: ErrorKind) {
        let e = NanonisError::from_error_reply("Scan.Action", description);
        assert_eq!(e.kind(), expected, "{description}");
        assert!(e.to_string().contains("Scan.Action"));
        assert!(e.to_string().contains(description));
    }

    #[test]
    fn error_replies_map_to_shared_kinds() {
        check(
            "Z-Controller: feedback lost (Safe Tip)",
            ErrorKind::FeedbackLost,
        );
        check("the real-time engine timed out", ErrorKind::Timeout);
        check("target is out of range", ErrorKind::OutOfRange);
        check("busy", ErrorKind::Communication);
        check(
            "communication with the RT engine failed",
            ErrorKind::Communication,
        );
        check("Invalid channel index", ErrorKind::Other);
        assert!(ErrorKind::Communication.is_transient());
        assert!(
            !NanonisError::new(NanonisErrorKind::Unreachable, "x")
                .kind()
                .is_transient()
        );
    }
}
