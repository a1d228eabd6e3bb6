//! A calibration job: which backend, and which plan.
//!
//! A job file is TOML with a `[backend]` table and a `[plan]` table:
//!
//! ```toml
//! [backend]
//! kind = "sim"                 # which backend: one variant of [`BackendConfig`]
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
//!
//! The `[backend]` table is a typed, internally tagged enum ([`BackendConfig`]): adding a
//! backend is one crate plus one variant here and one arm in `run::run_job`.

use serde::Deserialize;
use spm_calibration::PlanConfig;
#[cfg(feature = "sim")]
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
    /// A job, plan or simulator config is not valid TOML, or a field of it is unknown,
    /// missing or wrong (the message names the file, line and field).
    #[error("{0}")]
    Config(#[from] spm_config::ConfigError),
    /// A field of the job is inconsistent with another (the message names file and line).
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
    /// A virtual calibration's image is refused (the message names the file and why).
    #[error("{0}")]
    Virtual(#[source] crate::virtual_mode::VirtualInputError),
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
pub const MAX_CONFIG_BYTES: u64 = spm_config::MAX_CONFIG_BYTES;

/// Largest number of visits (nodes × repeats) of one run: a week of instrument time at
/// well under a second per visit. A larger plan is almost surely a typo (`step_counts = 1`).
pub const MAX_TOTAL_VISITS: usize = 1_000_000;

/// The `[backend]` table of a job file: which instrument the job runs on.
#[derive(Debug, Clone, PartialEq, Deserialize, serde::Serialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
#[non_exhaustive]
pub enum BackendConfig {
    /// The simulated microscope (spm-sim).
    Sim {
        /// The simulator's config file, relative to the job file.
        sim_config: PathBuf,
    },
    /// A Nanonis controller over its TCP programming interface (spm-nanonis): host, port,
    /// timeouts, reconnects, the counts convention, the Z signal and the clock.
    Nanonis(spm_nanonis::NanonisConfig),
    /// The virtual calibration mode (spm-virtual): a stored image of the standard served as
    /// the surface: image file, channel, nominal sensitivity, optional counter frame.
    Virtual(crate::virtual_mode::VirtualBackendConfig),
}

/// The top level of a job file. `[plan]` is parsed by spm-calibration (its own diagnostics);
/// here it is only present or not.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct JobFile {
    backend: BackendConfig,
    #[serde(default)]
    plan: Option<toml::Table>,
    #[serde(default)]
    plan_file: Option<PathBuf>,
}

/// The top level of a plan file: a `[plan]` table and nothing else.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PlanFile {
    #[allow(dead_code)]
    plan: toml::Table,
}

/// The backend a job runs on, loaded.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub enum Backend {
    /// The simulated microscope with this configuration.
    #[cfg(feature = "sim")]
    Sim(Box<SimConfig>),
    /// A Nanonis controller (or `spmcal nanonis-sim`) over TCP.
    Nanonis(Box<spm_nanonis::NanonisConfig>),
    /// A stored image served as the surface (the virtual calibration mode).
    Virtual(Box<crate::virtual_mode::VirtualBackend>),
}

impl Backend {
    /// What the instrument offers, for checking a plan before anything is built.
    #[must_use]
    pub fn capabilities(&self) -> spm_hal::Capabilities {
        match self {
            #[cfg(feature = "sim")]
            Self::Sim(config) => config.capabilities(),
            Self::Nanonis(config) => config.capabilities(),
            Self::Virtual(backend) => backend.capabilities(),
        }
    }
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

/// The `[backend]` table of a generated job, for its provenance.
#[derive(serde::Serialize)]
struct BackendTable<'a> {
    backend: &'a BackendConfig,
}

impl Job {
    /// Loads a job file (`[backend]` + `[plan]` or `plan_file`).
    ///
    /// # Errors
    /// A [`JobError`] naming the file, line and field.
    pub fn from_file(path: &Path) -> Result<Self, JobError> {
        let text = read(path)?;
        let source_name = path.display().to_string();
        let file: JobFile = spm_config::parse_toml(&text, &source_name)?;
        let dir = path.parent().unwrap_or(Path::new("."));
        let (plan, plan_text, plan_source) = match (&file.plan_file, &file.plan) {
            (Some(_), Some(_)) => {
                return Err(JobError::Field {
                    path: path.to_path_buf(),
                    line: spm_config::TomlLocator::new(&text).line_of("plan_file"),
                    field: "plan_file".to_owned(),
                    message: "give either plan_file or [plan], not both".to_owned(),
                });
            }
            (Some(plan_file), None) => {
                let plan_path = dir.join(plan_file);
                let (plan, plan_text) = Self::read_plan(&plan_path)?;
                (plan, plan_text, plan_path.display().to_string())
            }
            (None, _) => (
                PlanConfig::from_toml_str(&text, &source_name)?,
                text.clone(),
                source_name.clone(),
            ),
        };
        let job = match &file.backend {
            #[cfg(feature = "sim")]
            BackendConfig::Sim { sim_config } => {
                Self::from_parts(&dir.join(sim_config), plan, format!("{text}\n{plan_text}"))?
            }
            #[cfg(not(feature = "sim"))]
            BackendConfig::Sim { .. } => {
                return Err(JobError::Field {
                    path: path.to_path_buf(),
                    line: spm_config::TomlLocator::new(&text).line_of("backend"),
                    field: "backend.kind".to_owned(),
                    message: "this spmcal was built without the simulator (its `sim` feature \
                              is off): it drives kind = \"nanonis\" and kind = \"virtual\" only"
                        .to_owned(),
                });
            }
            BackendConfig::Nanonis(config) => {
                config.validate().map_err(|e| JobError::Field {
                    path: path.to_path_buf(),
                    line: spm_config::TomlLocator::new(&text).line_of("backend"),
                    field: "backend".to_owned(),
                    message: e.message,
                })?;
                Self {
                    backend: Backend::Nanonis(Box::new(config.clone())),
                    plan,
                    provenance_text: format!("# job\n{text}\n# plan\n{plan_text}"),
                }
            }
            BackendConfig::Virtual(config) => {
                let backend = config.load(dir).map_err(JobError::Virtual)?;
                crate::virtual_mode::check_standard(
                    &backend.image,
                    &backend.surface.forward,
                    &plan.standard,
                )
                .map_err(JobError::Virtual)?;
                Self {
                    backend: Backend::Virtual(Box::new(backend)),
                    plan,
                    provenance_text: format!("# job\n{text}\n# plan\n{plan_text}"),
                }
            }
        };
        Self::check_plan_on_backend(&job.plan, &job.backend, &plan_source, &plan_text)?;
        Ok(job)
    }

    /// The job `spmcal calibrate --virtual IMAGE --standard NAME` runs: the image checked
    /// against the standard and a plan built for it ([`crate::virtual_mode::virtual_job`]).
    ///
    /// # Errors
    /// [`JobError::Virtual`] naming the image and the reason.
    pub fn virtual_image(
        image: &Path,
        options: &crate::virtual_mode::VirtualRunOptions,
    ) -> Result<Self, JobError> {
        let (config, backend, plan) =
            crate::virtual_mode::virtual_job(image, options).map_err(JobError::Virtual)?;
        let config = BackendConfig::Virtual(config);
        let backend_text = toml::to_string(&BackendTable { backend: &config }).unwrap_or_default();
        let plan_text = plan.to_toml_string().unwrap_or_default();
        let job = Self {
            backend: Backend::Virtual(Box::new(backend)),
            plan,
            provenance_text: format!("# job (--virtual)\n{backend_text}\n# plan\n{plan_text}"),
        };
        let source = format!("the plan built for {}", image.display());
        Self::check_plan_on_backend(&job.plan, &job.backend, &source, &plan_text)?;
        Ok(job)
    }

    /// A job from a simulator config file and a plan (what `cargo xtask calibrate` uses).
    ///
    /// # Errors
    /// A [`JobError`] naming the simulator's file, line and field.
    #[cfg(feature = "sim")]
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
    ///
    /// # Errors
    /// A [`JobError`] naming the file, line and field.
    pub fn read_plan(path: &Path) -> Result<(PlanConfig, String), JobError> {
        let text = read(path)?;
        let source_name = path.display().to_string();
        let plan = PlanConfig::from_toml_str(&text, &source_name)?;
        spm_config::parse_toml::<PlanFile>(&text, &source_name)?;
        Ok((plan, text))
    }

    /// The other files a job file names (`backend.sim_config`, `plan_file`), resolved
    /// against its folder; best effort (nothing when the file cannot be read or parsed).
    pub fn referenced_files(path: &Path) -> Vec<PathBuf> {
        let Ok(text) = read(path) else {
            return Vec::new();
        };
        let Ok(file) = toml::from_str::<JobFile>(&text) else {
            return Vec::new();
        };
        let dir = path.parent().unwrap_or(Path::new("."));
        let mut files = Vec::new();
        match &file.backend {
            BackendConfig::Sim { sim_config } => files.push(dir.join(sim_config)),
            BackendConfig::Nanonis(_) => {}
            BackendConfig::Virtual(config) => {
                files.push(dir.join(&config.image));
                files.extend(config.counter_image.iter().map(|p| dir.join(p)));
            }
        }
        if let Some(p) = &file.plan_file {
            files.push(dir.join(p));
        }
        files
    }

    /// Checks the plan against the backend: the net laid in the instrument's field, its
    /// size, and scans within the instrument's limits. `plan_source` and `plan_text` locate
    /// the plan's fields.
    fn check_plan_on_backend(
        plan: &PlanConfig,
        backend: &Backend,
        plan_source: &str,
        plan_text: &str,
    ) -> Result<(), JobError> {
        let invalid = |field: &str, reason: String| {
            JobError::Config(spm_config::ConfigError::Invalid {
                source_name: plan_source.to_owned(),
                line: spm_calibration::locate_field_line(plan_text, field),
                field: field.to_owned(),
                reason,
            })
        };
        let capabilities = backend.capabilities();
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
