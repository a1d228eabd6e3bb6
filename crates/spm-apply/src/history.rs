//! The command history a scan keeps (`spmcal scan`), read back by `spmcal correct`: with it the
//! creep of the move that brought the probe to the frame, and every earlier command of the
//! session, is corrected too ([`crate::dynamic::recorded_map`]).
//!
//! A JSON sidecar beside the image, `IMAGE.history.json`:
//! `{"format": "spmcal-scan-history", "version": 1, "scanner_id": …, "events": [CommandEvent…],
//! "forward_pixel_times_s": […], "backward_pixel_times_s": […] | null}` — the backend's command
//! log (spm-hal's `CommandEvent`, instrument seconds) and the acquisition time of every pixel of
//! each recorded half in acquisition order, on the same clock.

use serde::{Deserialize, Serialize};
use spm_correction::dynamics::CommandHistory;
use spm_hal::recording::CommandEvent;

/// Format name of a history sidecar.
pub const HISTORY_FORMAT: &str = "spmcal-scan-history";
/// Format version of a history sidecar.
pub const HISTORY_VERSION: u32 = 1;
/// Largest sidecar read, bytes (a day of commands at 10 per second is well under it).
pub const MAX_HISTORY_BYTES: u64 = 512 * 1024 * 1024;

/// A scan's command history (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanHistory {
    /// [`HISTORY_FORMAT`].
    pub format: String,
    /// [`HISTORY_VERSION`].
    pub version: u32,
    /// The scanner the commands drove.
    pub scanner_id: String,
    /// The backend's command log, in time order.
    pub events: Vec<CommandEvent>,
    /// Acquisition time of every forward pixel, acquisition order, s.
    pub forward_pixel_times_s: Vec<f64>,
    /// Acquisition time of every backward pixel, when recorded.
    pub backward_pixel_times_s: Option<Vec<f64>>,
}

/// Why a history sidecar cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum HistoryError {
    /// The file cannot be read.
    #[error("{path}: {message}")]
    Read {
        /// The sidecar.
        path: String,
        /// Why.
        message: String,
    },
    /// The file is not a history of this format, or a field is unusable.
    #[error("{path}: field `{field}`: {reason}")]
    Field {
        /// The sidecar.
        path: String,
        /// The field.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
}

impl ScanHistory {
    /// Parses and checks a sidecar's text (`path` names it in errors).
    ///
    /// # Errors
    /// [`HistoryError::Read`] for text that is not such JSON, [`HistoryError::Field`] naming the
    /// field for a wrong format or version, non-finite or unsorted times, an empty log.
    pub fn from_json(text: &str, path: &str) -> Result<Self, HistoryError> {
        let h: Self = serde_json::from_str(text).map_err(|e| HistoryError::Read {
            path: path.to_owned(),
            message: e.to_string(),
        })?;
        let field = |field: &'static str, reason: String| HistoryError::Field {
            path: path.to_owned(),
            field,
            reason,
        };
        if h.format != HISTORY_FORMAT || h.version != HISTORY_VERSION {
            return Err(field(
                "format",
                format!(
                    "{:?} version {} (this build reads {HISTORY_FORMAT:?} version {HISTORY_VERSION})",
                    h.format, h.version
                ),
            ));
        }
        if h.events.is_empty() {
            return Err(field("events", "the command log is empty".to_owned()));
        }
        for (name, times) in [
            ("forward_pixel_times_s", Some(&h.forward_pixel_times_s)),
            ("backward_pixel_times_s", h.backward_pixel_times_s.as_ref()),
        ] {
            let Some(times) = times else { continue };
            if let Some(i) = times.iter().position(|t| !t.is_finite()) {
                return Err(field(name, format!("entry {i} is not a finite time")));
            }
            if let Some(i) = times.windows(2).position(|w| w[1] < w[0]) {
                return Err(field(name, format!("entry {} goes back in time", i + 1)));
            }
        }
        Ok(h)
    }

    /// The command log as a trajectory.
    #[must_use]
    pub fn command_history(&self) -> CommandHistory {
        CommandHistory::from_events(&self.events)
    }

    /// Pretty JSON.
    ///
    /// # Errors
    /// Serialisation errors (not expected).
    pub fn to_json(&self) -> Result<String, serde_json::Error> {
        serde_json::to_string(self)
    }
}

/// The sidecar path of an image: `IMAGE.history.json` beside it.
#[must_use]
pub fn sidecar_of(image: &std::path::Path) -> std::path::PathBuf {
    let mut name = image.file_name().unwrap_or_default().to_os_string();
    name.push(".history.json");
    image.with_file_name(name)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn sample() -> ScanHistory {
        ScanHistory {
            format: HISTORY_FORMAT.to_owned(),
            version: HISTORY_VERSION,
            scanner_id: "s".to_owned(),
            events: vec![CommandEvent::Wait {
                start_s: 0.0,
                end_s: 1.0,
            }],
            forward_pixel_times_s: vec![1.0, 1.1, 1.2],
            backward_pixel_times_s: None,
        }
    }

    #[test]
    fn a_history_round_trips_and_bad_fields_are_named() {
        let h = sample();
        let text = h.to_json().unwrap();
        assert_eq!(ScanHistory::from_json(&text, "x").unwrap(), h);
        let mut bad = sample();
        bad.version = 9;
        let e = ScanHistory::from_json(&bad.to_json().unwrap(), "x").unwrap_err();
        assert!(e.to_string().contains("`format`"), "{e}");
        let mut bad = sample();
        bad.forward_pixel_times_s = vec![2.0, 1.0];
        let e = ScanHistory::from_json(&bad.to_json().unwrap(), "x").unwrap_err();
        assert!(e.to_string().contains("forward_pixel_times_s"), "{e}");
        let mut bad = sample();
        bad.events.clear();
        assert!(ScanHistory::from_json(&bad.to_json().unwrap(), "x").is_err());
        assert!(ScanHistory::from_json("{", "x").is_err());
        assert_eq!(
            sidecar_of(std::path::Path::new("/d/img.gsf")),
            std::path::PathBuf::from("/d/img.gsf.history.json")
        );
    }
}
