//! The scanner's dynamics (hysteresis and creep) as identified by a run, stored beside the
//! LCCs as a versioned JSON document.
//!
//! The model itself (a Prandtl–Ishlinskii operator per axis and a creep law) belongs to
//! `spm-correction`; the CDB keeps it without depending on that crate: `model_format` and
//! `model_version` say what the document is, and [`DynamicsRecord::check`] makes sure it is
//! at least a JSON object of bounded size, so that whatever reads it back gets a document
//! its own parser can judge.

use serde::{Deserialize, Serialize};

use crate::columns::id_problem;

/// The columns every store keeps a [`DynamicsRecord`] in, in field order (the one list
/// their schemas, inserts and selects follow; the field names of the record).
pub const DYNAMICS_RECORD_COLUMNS: [&str; 6] = [
    "run_id",
    "scanner_id",
    "identified_unix_s",
    "model_format",
    "model_version",
    "model_json",
];

/// Largest `model_json` a store accepts, in bytes (1 MiB).
pub const DYNAMICS_MODEL_MAX_BYTES: usize = 1 << 20;

/// Largest `model_format` a store accepts, in bytes.
pub const DYNAMICS_FORMAT_MAX_BYTES: usize = 128;

/// The scanner dynamics a run identified, dated (DESIGN §8: the CDB keeps every
/// identification; the newest one of a scanner is the one in force).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DynamicsRecord {
    /// The run that identified it (a run of the same scanner, stored in the CDB).
    pub run_id: String,
    /// Scanner the model describes.
    pub scanner_id: String,
    /// When it was identified, UTC seconds since 1970-01-01T00:00:00Z (the time the run
    /// recorded; finite and > 0).
    pub identified_unix_s: f64,
    /// What kind of document `model_json` is, e.g. `"spmcal-dynamics"`.
    pub model_format: String,
    /// Version of that format (≥ 1).
    pub model_version: u32,
    /// The model: a JSON object of at most [`DYNAMICS_MODEL_MAX_BYTES`] bytes.
    pub model_json: String,
}

/// Why a [`DynamicsRecord`] may not be stored, naming the field.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum DynamicsProblem {
    /// `run_id`, `scanner_id` or `model_format` is blank or holds control or format
    /// characters ([`id_problem`]), or `model_format` is too long.
    #[error("dynamics (run {run_id:?}): {field} {why}")]
    BadText {
        /// Run of the record.
        run_id: String,
        /// The offending field.
        field: &'static str,
        /// What is wrong.
        why: String,
    },
    /// `identified_unix_s` is not finite or not > 0.
    #[error("dynamics (run {run_id:?}): identified_unix_s = {value} must be finite and > 0")]
    BadTime {
        /// Run of the record.
        run_id: String,
        /// The value, as text (NaN and infinities included).
        value: String,
    },
    /// `model_version` is 0.
    #[error("dynamics (run {run_id:?}): model_version must be >= 1, got 0")]
    BadVersion {
        /// Run of the record.
        run_id: String,
    },
    /// `model_json` is larger than [`DYNAMICS_MODEL_MAX_BYTES`].
    #[error("dynamics (run {run_id:?}): model_json is {bytes} bytes, more than the {max} allowed")]
    TooLarge {
        /// Run of the record.
        run_id: String,
        /// Its size.
        bytes: usize,
        /// The limit.
        max: usize,
    },
    /// `model_json` is not JSON, or not a JSON object.
    #[error("dynamics (run {run_id:?}): model_json {why}")]
    NotAnObject {
        /// Run of the record.
        run_id: String,
        /// What is wrong.
        why: String,
    },
}

impl DynamicsProblem {
    /// The field the problem is about.
    #[must_use]
    pub fn field(&self) -> &'static str {
        match self {
            Self::BadText { field, .. } => field,
            Self::BadTime { .. } => "identified_unix_s",
            Self::BadVersion { .. } => "model_version",
            Self::TooLarge { .. } | Self::NotAnObject { .. } => "model_json",
        }
    }
}

impl DynamicsRecord {
    /// The rules every store applies before writing (and `cdb check` to what is stored):
    /// ids and the format name are visible text, the time is finite and > 0, the version is
    /// ≥ 1, and `model_json` is a JSON object of at most [`DYNAMICS_MODEL_MAX_BYTES`].
    ///
    /// # Errors
    /// The first [`DynamicsProblem`] found, naming the field.
    pub fn check(&self) -> Result<(), DynamicsProblem> {
        let run_id = || self.run_id.clone();
        for (field, text) in [
            ("run_id", &self.run_id),
            ("scanner_id", &self.scanner_id),
            ("model_format", &self.model_format),
        ] {
            if let Some(why) = id_problem(text) {
                return Err(DynamicsProblem::BadText {
                    run_id: run_id(),
                    field,
                    why,
                });
            }
        }
        if self.model_format.len() > DYNAMICS_FORMAT_MAX_BYTES {
            return Err(DynamicsProblem::BadText {
                run_id: run_id(),
                field: "model_format",
                why: format!(
                    "is {} bytes, more than the {DYNAMICS_FORMAT_MAX_BYTES} allowed",
                    self.model_format.len()
                ),
            });
        }
        if !(self.identified_unix_s.is_finite() && self.identified_unix_s > 0.0) {
            return Err(DynamicsProblem::BadTime {
                run_id: run_id(),
                value: self.identified_unix_s.to_string(),
            });
        }
        if self.model_version == 0 {
            return Err(DynamicsProblem::BadVersion { run_id: run_id() });
        }
        if self.model_json.len() > DYNAMICS_MODEL_MAX_BYTES {
            return Err(DynamicsProblem::TooLarge {
                run_id: run_id(),
                bytes: self.model_json.len(),
                max: DYNAMICS_MODEL_MAX_BYTES,
            });
        }
        match serde_json::from_str::<serde_json::Value>(&self.model_json) {
            Ok(serde_json::Value::Object(_)) => Ok(()),
            Ok(other) => Err(DynamicsProblem::NotAnObject {
                run_id: run_id(),
                why: format!("must be a JSON object, found {}", json_kind(&other)),
            }),
            Err(e) => Err(DynamicsProblem::NotAnObject {
                run_id: run_id(),
                why: format!("is not JSON: {e}"),
            }),
        }
    }
}

fn json_kind(v: &serde_json::Value) -> &'static str {
    match v {
        serde_json::Value::Null => "null",
        serde_json::Value::Bool(_) => "a boolean",
        serde_json::Value::Number(_) => "a number",
        serde_json::Value::String(_) => "a string",
        serde_json::Value::Array(_) => "an array",
        serde_json::Value::Object(_) => "an object",
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn good() -> DynamicsRecord {
        DynamicsRecord {
            run_id: "run-1".into(),
            scanner_id: "scanner-A".into(),
            identified_unix_s: 1.7e9,
            model_format: "spmcal-dynamics".into(),
            model_version: 1,
            model_json: r#"{"creep":{"gamma":0.01},"hysteresis":[]}"#.into(),
        }
    }

    #[test]
    fn a_valid_record_passes() {
        good().check().unwrap();
    }

    #[test]
    fn the_column_list_is_the_records_fields_in_order() {
        let text = serde_json::to_string(&good()).unwrap();
        let mut at = 0;
        for column in DYNAMICS_RECORD_COLUMNS {
            let found = text[at..]
                .find(&format!("\"{column}\":"))
                .unwrap_or_else(|| panic!("{column} missing or out of order in {text}"));
            at += found;
        }
        let value: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(
            value.as_object().unwrap().len(),
            DYNAMICS_RECORD_COLUMNS.len()
        );
    }

    type Spoil = Box<dyn Fn(&mut DynamicsRecord)>;

    #[test]
    fn every_rule_names_its_field() {
        let cases: Vec<(&str, Spoil)> = vec![
            ("run_id", Box::new(|r| r.run_id = " ".into())),
            (
                "scanner_id",
                Box::new(|r| r.scanner_id = "a\u{202E}b".into()),
            ),
            ("model_format", Box::new(|r| r.model_format = String::new())),
            (
                "model_format",
                Box::new(|r| r.model_format = "f".repeat(129)),
            ),
            (
                "identified_unix_s",
                Box::new(|r| r.identified_unix_s = f64::NAN),
            ),
            (
                "identified_unix_s",
                Box::new(|r| r.identified_unix_s = f64::INFINITY),
            ),
            ("identified_unix_s", Box::new(|r| r.identified_unix_s = 0.0)),
            (
                "identified_unix_s",
                Box::new(|r| r.identified_unix_s = -1.0),
            ),
            ("model_version", Box::new(|r| r.model_version = 0)),
            ("model_json", Box::new(|r| r.model_json = "{".into())),
            ("model_json", Box::new(|r| r.model_json = "[1, 2]".into())),
            ("model_json", Box::new(|r| r.model_json = "null".into())),
            ("model_json", Box::new(|r| r.model_json = String::new())),
            (
                "model_json",
                Box::new(|r| {
                    r.model_json = format!("{{\"pad\":\"{}\"}}", "x".repeat(1 << 20));
                }),
            ),
        ];
        for (field, spoil) in cases {
            let mut r = good();
            spoil(&mut r);
            let e = r.check().unwrap_err();
            assert_eq!(e.field(), field, "{e}");
            assert!(e.to_string().contains(field), "{e}");
            assert!(e.to_string().contains("run-1") || field == "run_id", "{e}");
        }
    }

    #[test]
    fn the_size_limit_is_inclusive_and_deep_nesting_is_an_error_not_a_crash() {
        let mut r = good();
        let pad = DYNAMICS_MODEL_MAX_BYTES - "{\"p\":\"\"}".len();
        r.model_json = format!("{{\"p\":\"{}\"}}", "x".repeat(pad));
        assert_eq!(r.model_json.len(), DYNAMICS_MODEL_MAX_BYTES);
        r.check().unwrap();
        r.model_json = format!("{}1{}", "{\"a\":".repeat(100_000), "}".repeat(100_000));
        assert_eq!(r.check().unwrap_err().field(), "model_json");
    }
}
