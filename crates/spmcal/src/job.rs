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
    /// A config file is not a regular file (a FIFO, a device, a directory) or too large.
    #[error("{path}: {message}")]
    NotAConfigFile {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// Largest config file (job, plan or simulator) read, bytes: configs are small hand-written
/// files; anything larger is a mistake (e.g. a data file given as a config).
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// Largest number of visits (nodes × repeats) of one run: a week of instrument time at
/// well under a second per visit. A larger plan is almost surely a typo (`step_counts = 1`).
pub const MAX_TOTAL_VISITS: usize = 1_000_000;

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
        let plan = match table.get("plan_file") {
            Some(toml::Value::String(plan_file)) => {
                if table.contains_key("plan") {
                    return Err(field(
                        "plan_file",
                        "give either plan_file or [plan], not both",
                    ));
                }
                let plan_path = path.parent().unwrap_or(Path::new(".")).join(plan_file);
                let (plan, plan_text) = Self::read_plan(&plan_path)?;
                (plan, plan_text, plan_path.display().to_string())
            }
            Some(_) => return Err(field("plan_file", "must be a string (a file path)")),
            None => (
                PlanConfig::from_toml_str(&text, &path.display().to_string())?,
                text.clone(),
                path.display().to_string(),
            ),
        };
        let (plan, plan_text, plan_source) = plan;
        let job = Self::from_parts(&sim_path, plan, format!("{text}\n{plan_text}"))?;
        let Backend::Sim(sim) = &job.backend;
        Self::check_plan_on_backend(&job.plan, sim, &plan_source, &plan_text)?;
        Ok(job)
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

    /// A plan file: a `[plan]` table and nothing else at the top level.
    pub fn read_plan(path: &Path) -> Result<(PlanConfig, String), JobError> {
        let text = read(path)?;
        let plan = PlanConfig::from_toml_str(&text, &path.display().to_string())?;
        if let Ok(table) = text.parse::<toml::Table>() {
            for key in table.keys() {
                if key != "plan" {
                    return Err(JobError::Field {
                        path: path.to_path_buf(),
                        line: line_of(&text, key),
                        field: key.clone(),
                        message: "unknown top-level field of a plan file (expected only [plan])"
                            .to_owned(),
                    });
                }
            }
        }
        Ok((plan, text))
    }

    /// The other files a job file names (`backend.sim_config`, `plan_file`), resolved
    /// against its folder; best effort (nothing when the file cannot be read or parsed).
    pub fn referenced_files(path: &Path) -> Vec<PathBuf> {
        let Ok(text) = read(path) else {
            return Vec::new();
        };
        let Ok(table) = text.parse::<toml::Table>() else {
            return Vec::new();
        };
        let dir = path.parent().unwrap_or(Path::new("."));
        let mut files = Vec::new();
        if let Some(p) = table
            .get("backend")
            .and_then(|b| b.get("sim_config"))
            .and_then(toml::Value::as_str)
        {
            files.push(dir.join(p));
        }
        if let Some(p) = table.get("plan_file").and_then(toml::Value::as_str) {
            files.push(dir.join(p));
        }
        files
    }

    /// Checks the plan against the backend: the net laid in the instrument's field, its
    /// size, and scans within the instrument's limits. `plan_source` and `plan_text` locate
    /// the plan's fields.
    fn check_plan_on_backend(
        plan: &PlanConfig,
        sim: &SimConfig,
        plan_source: &str,
        plan_text: &str,
    ) -> Result<(), JobError> {
        let invalid = |field: &str, reason: String| {
            JobError::Plan(spm_calibration::ConfigError::Invalid {
                source_name: plan_source.to_owned(),
                line: spm_calibration::locate_field_line(plan_text, field),
                field: field.to_owned(),
                reason,
            })
        };
        let capabilities = sim.capabilities();
        let geometry = plan.net.geometry(&capabilities).map_err(|e| match e {
            spm_calibration::PlanError::Invalid { field, reason } => {
                invalid(&format!("plan.net.{field}"), reason)
            }
            other => invalid("plan.net", other.to_string()),
        })?;
        let nodes = geometry.node_count();
        let visits = nodes.saturating_mul(plan.repeats as usize);
        if nodes == 0 || visits > MAX_TOTAL_VISITS {
            return Err(invalid(
                "plan.net.step_counts",
                format!(
                    "gives {nodes} nodes × {} repeats = {visits} visits, more than the limit of \
                     {MAX_TOTAL_VISITS}",
                    plan.repeats
                ),
            ));
        }
        let max_pixels = capabilities.max_pixels_per_line.min(capabilities.max_lines);
        for (field, pixels) in [
            ("plan.aperture.pixels", plan.aperture.pixels),
            ("plan.attach.first_pixels", plan.attach.first_pixels),
            ("plan.attach.segment_pixels", plan.attach.segment_pixels),
        ] {
            if pixels > max_pixels {
                return Err(invalid(
                    field,
                    format!("must be ≤ {max_pixels}, the instrument's largest scan, got {pixels}"),
                ));
            }
        }
        if plan.motion.pixel_dwell_s < capabilities.min_pixel_dwell.value() {
            return Err(invalid(
                "plan.motion.pixel_dwell_s",
                format!(
                    "must be ≥ {} s, the instrument's shortest dwell, got {}",
                    capabilities.min_pixel_dwell.value(),
                    plan.motion.pixel_dwell_s
                ),
            ));
        }
        let width = capabilities.field_max.x.value() - capabilities.field_min.x.value();
        for (field, size) in [
            ("plan.aperture.size_counts", plan.aperture.size_counts),
            (
                "plan.attach.first_size_counts",
                plan.attach.first_size_counts,
            ),
            (
                "plan.attach.segment_size_counts",
                plan.attach.segment_size_counts,
            ),
        ] {
            if size > width {
                return Err(invalid(
                    field,
                    format!("must be ≤ {width} counts, the instrument's field, got {size}"),
                ));
            }
        }
        Ok(())
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

/// Reads a config file: a regular file (checked before opening: a FIFO would block, a
/// device never end) of at most [`MAX_CONFIG_BYTES`].
fn read(path: &Path) -> Result<String, JobError> {
    let io = |source| JobError::Io {
        path: path.to_path_buf(),
        source,
    };
    let not_config = |message: String| JobError::NotAConfigFile {
        path: path.to_path_buf(),
        message,
    };
    let meta = std::fs::metadata(path).map_err(io)?;
    if !meta.is_file() {
        return Err(not_config(
            "not a regular file (a directory, FIFO or device); a config must be a file".into(),
        ));
    }
    if meta.len() > MAX_CONFIG_BYTES {
        return Err(not_config(format!(
            "{} bytes is larger than the limit of {MAX_CONFIG_BYTES} bytes for a config",
            meta.len()
        )));
    }
    let file = std::fs::File::open(path).map_err(io)?;
    let mut bytes = Vec::new();
    use std::io::Read;
    file.take(MAX_CONFIG_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(io)?;
    if bytes.len() as u64 > MAX_CONFIG_BYTES {
        return Err(not_config(format!(
            "larger than the limit of {MAX_CONFIG_BYTES} bytes for a config"
        )));
    }
    String::from_utf8(bytes).map_err(|_| not_config("not UTF-8 text".into()))
}
