//! A calibration job: which backend, and which plan.
//!
//! A job file is TOML with a `[backend]` table and a `[plan]` table:
//!
//! ```toml
//! [backend]
//! kind = "sim"                 # the simulated microscope (the only backend built in so far)
//! sim_config = "sim-hopg.toml" # the simulator's config, relative to this file
//!
//! [plan]                       # spm-calibration's PlanConfig
//! scanner_id = "sim-hopg"
//! # ...
//! ```
//!
//! Instead of a `[plan]` table, a job may name a plan file at the top level:
//! `plan_file = "plan-hopg.toml"` (relative to the job file; its `[plan]` table is used).
//! `cargo xtask calibrate --config SIM.toml --plan PLAN.toml` builds the same
//! job from a simulator config and a plan file (see [`Job::from_parts`]).

use spm_calibration::PlanConfig;
use spm_sim::SimConfig;
use std::path::{Path, PathBuf};

/// Why a job file cannot be used; every variant names the file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum JobError {
    /// The file cannot be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The file is not TOML.
    #[error("{path}: not valid TOML: {message}")]
    Syntax {
        /// The file.
        path: PathBuf,
        /// toml's message (with line and column).
        message: String,
    },
    /// A field of the job table is missing or wrong.
    #[error("{path}{}: field `{field}`: {message}", line.map(|l| format!(":{l}")).unwrap_or_default())]
    Field {
        /// The file.
        path: PathBuf,
        /// 1-based line of the field (or of its table when the field is missing), when found.
        line: Option<usize>,
        /// Dotted field path.
        field: String,
        /// What is wrong.
        message: String,
    },
    /// The plan is invalid (the message names file, line and field).
    #[error("{0}")]
    Plan(#[from] spm_calibration::ConfigError),
    /// The simulator config is invalid (the message names file, line and field).
    #[error("{0}")]
    Sim(#[from] spm_sim::ConfigError),
}

/// The backend a job runs on.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub enum Backend {
    /// The simulated microscope with this configuration.
    Sim(Box<SimConfig>),
}

/// A loaded, validated job.
#[derive(Debug, Clone)]
pub struct Job {
    /// The backend.
    pub backend: Backend,
    /// The plan.
    pub plan: PlanConfig,
    /// The texts of the files the job came from (stored with the run as provenance).
    pub provenance_text: String,
}

impl Job {
    /// Loads a job file (`[backend]` + `[plan]`).
    pub fn from_file(path: &Path) -> Result<Self, JobError> {
        let text = read(path)?;
        let table: toml::Table = text
            .parse()
            .map_err(|e: toml::de::Error| JobError::Syntax {
                path: path.to_path_buf(),
                message: e.to_string(),
            })?;
        let field = |field: &str, message: &str| JobError::Field {
            path: path.to_path_buf(),
            line: line_of(&text, field),
            field: field.to_owned(),
            message: message.to_owned(),
        };
        let backend = table
            .get("backend")
            .and_then(toml::Value::as_table)
            .ok_or_else(|| field("backend", "a job file needs a [backend] table"))?;
        for key in backend.keys() {
            if !["kind", "sim_config"].contains(&key.as_str()) {
                return Err(field(
                    &format!("backend.{key}"),
                    "unknown field (expected `kind`, `sim_config`)",
                ));
            }
        }
        let kind = match backend.get("kind") {
            Some(toml::Value::String(kind)) => kind.as_str(),
            Some(other) => {
                return Err(field(
                    "backend.kind",
                    &format!("must be a string (\"sim\"), found {}", other.type_str()),
                ));
            }
            None => return Err(field("backend.kind", "missing (a string: \"sim\")")),
        };
        if kind != "sim" {
            return Err(field(
                "backend.kind",
                &format!("unknown backend {kind:?} (known: \"sim\")"),
            ));
        }
        let sim_path = match backend.get("sim_config") {
            Some(toml::Value::String(p)) => p.as_str(),
            Some(other) => {
                return Err(field(
                    "backend.sim_config",
                    &format!("must be a string (a file path), found {}", other.type_str()),
                ));
            }
            None => {
                return Err(field(
                    "backend.sim_config",
                    "missing (the simulator config file, relative to the job file)",
                ));
            }
        };
        let sim_path = path.parent().unwrap_or(Path::new(".")).join(sim_path);
        for key in table.keys() {
            if !["backend", "plan", "plan_file"].contains(&key.as_str()) {
                return Err(field(
                    key,
                    "unknown top-level field (expected [backend], [plan] or plan_file)",
                ));
            }
        }
        let (plan, plan_text) = match table.get("plan_file") {
            Some(toml::Value::String(plan_file)) => {
                if table.contains_key("plan") {
                    return Err(field(
                        "plan_file",
                        "give either plan_file or [plan], not both",
                    ));
                }
                Self::read_plan(&path.parent().unwrap_or(Path::new(".")).join(plan_file))?
            }
            Some(_) => return Err(field("plan_file", "must be a string (a file path)")),
            None => (
                PlanConfig::from_toml_str(&text, &path.display().to_string())?,
                text.clone(),
            ),
        };
        Self::from_parts(&sim_path, plan, format!("{text}\n{plan_text}"))
    }

    /// A job from a simulator config file and a plan (what `cargo xtask calibrate` uses).
    pub fn from_parts(
        sim_path: &Path,
        plan: PlanConfig,
        plan_text: String,
    ) -> Result<Self, JobError> {
        let sim_text = read(sim_path)?;
        let sim = SimConfig::from_toml_str(&sim_text, &sim_path.display().to_string())?;
        Ok(Self {
            backend: Backend::Sim(Box::new(sim)),
            plan,
            provenance_text: format!(
                "# simulator: {}\n{sim_text}\n# plan\n{plan_text}",
                sim_path.display()
            ),
        })
    }

    /// A plan file (a `[plan]` table, possibly among others).
    pub fn read_plan(path: &Path) -> Result<(PlanConfig, String), JobError> {
        let text = read(path)?;
        let plan = PlanConfig::from_toml_str(&text, &path.display().to_string())?;
        Ok((plan, text))
    }
}

/// 1-based line of a dotted field (`backend.kind`, `plan_file`) in a job file: the line
/// assigning its last key inside its table (top level before any table header), else the
/// line of its table header. A text search (jobs are small, hand-written files); `None` when
/// nothing matches.
fn line_of(text: &str, dotted: &str) -> Option<usize> {
    let (table, key) = dotted.rsplit_once('.').unwrap_or(("", dotted));
    let mut current = String::new();
    let mut header_line = None;
    for (i, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if let Some(name) = line.strip_prefix('[') {
            current = name
                .trim_start_matches('[')
                .split(']')
                .next()
                .unwrap_or("")
                .trim()
                .to_owned();
            if current == table {
                header_line = Some(i + 1);
            }
            continue;
        }
        let assigns = line
            .strip_prefix(key)
            .is_some_and(|rest| rest.trim_start().starts_with('='));
        if current == table && assigns {
            return Some(i + 1);
        }
    }
    header_line
}

fn read(path: &Path) -> Result<String, JobError> {
    std::fs::read_to_string(path).map_err(|source| JobError::Io {
        path: path.to_path_buf(),
        source,
    })
}
