//! `cargo xtask bench`: one command, one run, every figure of DESIGN §11.
//!
//! Sections (each a module): calibration accuracy against the four baselines on
//! three simulated scanners, on the static field and on test images ([`accuracy`]), the
//! error budget of the images effect by effect ([`budget`]), drift insensitivity ([`drift`]),
//! productivity of the plan variants ([`productivity`]), localisation error ÷
//! Cramér–Rao bound ([`crb`]), speed ([`speed`]), the Gwyddion peer
//! ([`gwyddion`]) and virtual calibration on the measured images, held out ([`real`]). Everything is seeded; a section that fails is recorded with
//! its reason and the others still run. [`report`] writes `results.json`, the
//! PNG figures and `docs/RESULTS.md` (the hand-written `docs/results/*.md`
//! sections follow the measured tables).

mod accuracy;
mod budget;
mod crb;
mod drift;
mod gwyddion;
mod linalg;
mod nanonis;
mod postgres;
mod productivity;
mod real;
mod report;
mod speed;
mod vertical;

use crate::XtaskError;
use serde::Serialize;
use spm_calibration::NoObserver;
use spmcal::job::Job;
use spmcal::report::{CalibrationReport, RunRecord, finish_with};
use spmcal::run::{RecordingObserver, RunStart, run_job};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// A section's figures, or why they are missing.
#[derive(Debug, Serialize)]
#[serde(untagged)]
pub enum Section<T> {
    /// Measured.
    Measured(T),
    /// Not measured, with the reason.
    Missing {
        /// Why.
        missing: String,
    },
}

impl<T> Section<T> {
    fn from_result(result: Result<T, XtaskError>) -> Self {
        match result {
            Ok(value) => Self::Measured(value),
            Err(error) => Self::Missing {
                missing: error.to_string(),
            },
        }
    }

    /// The figures, when measured.
    pub fn measured(&self) -> Option<&T> {
        match self {
            Self::Measured(value) => Some(value),
            Self::Missing { .. } => None,
        }
    }
}

/// The machine of the run.
#[derive(Debug, Serialize)]
pub struct Machine {
    /// CPU model (/proc/cpuinfo).
    pub cpu: String,
    /// Logical cores available to this process.
    pub logical_cores: usize,
    /// Date of the run (UTC), YYYY-MM-DD HH:MM.
    pub date_utc: String,
    /// rustc version the workspace was built with, when known.
    pub rustc: String,
    /// /proc/loadavg (1, 5, 15 min) when the bench started: other work on the
    /// machine inflates the wall-clock figures.
    pub load_average_start: String,
    /// /proc/loadavg when the bench ended.
    pub load_average_end: String,
}

/// Everything `results.json` holds.
#[derive(Debug, Serialize)]
pub struct Results {
    /// The machine.
    pub machine: Machine,
    /// The command that produced the file.
    pub command: String,
    /// The source the bench was built from: `git rev-parse --short HEAD`.
    pub commit: String,
    /// Tracked files with uncommitted changes at that time (`git status`): the
    /// figures include them.
    pub uncommitted: Vec<String>,
    /// A reduced run (`--quick`).
    pub quick: bool,
    /// Wall time of the whole bench, s.
    pub bench_wall_time_s: f64,
    /// Calibration accuracy against the baselines, per scanner config.
    pub accuracy: Section<accuracy::AccuracyResults>,
    /// Error budget of the distributed calibration on test images, effect by effect.
    pub budget: Section<budget::BudgetResults>,
    /// LCC error against drift velocity.
    pub drift: Section<drift::DriftResults>,
    /// Error against repeats, cycles, instrument time and plan variants.
    pub productivity: Section<productivity::ProductivityResults>,
    /// Localisation error ÷ Cramér–Rao bound.
    pub crb: Section<crb::CrbResults>,
    /// Speed figures.
    pub speed: Section<speed::SpeedResults>,
    /// Gwyddion side by side.
    pub gwyddion: Section<gwyddion::GwyddionResults>,
    /// The vertical axis: Kz, the bowl, the z-dependence (issue 15).
    pub vertical: Section<vertical::VerticalResults>,
    /// Large least squares, nalgebra beside faer.
    pub linalg: Section<linalg::LinalgResults>,
    /// Nanonis TCP overhead: wall time per node over loopback ÷ in process.
    pub nanonis: Section<nanonis::NanonisResults>,
    /// The CDB on SQLite and on a shared PostgreSQL database.
    pub postgres: Section<postgres::PostgresResults>,
    /// Virtual calibration on the measured images, held out (issue 24).
    pub real: Section<real::RealResults>,
}

/// What `cargo xtask bench` was asked to do.
#[derive(Debug, Clone, Copy)]
pub struct Options {
    /// A reduced run.
    pub quick: bool,
    /// Also run the Gwyddion side-by-side comparison.
    pub with_gwyddion: bool,
    /// Regenerate the committed docs/ from this run.
    pub write_docs: bool,
}

pub fn run(root: &Path, out: &Path, options: Options) -> Result<(), XtaskError> {
    let Options {
        quick,
        with_gwyddion,
        write_docs,
    } = options;
    let started = Instant::now();
    std::fs::create_dir_all(out)
        .map_err(|e| XtaskError::step(format!("creating {}", out.display()), e))?;
    let machine = machine();
    println!(
        "== cargo xtask bench{}{}: {} ({} logical cores), {}",
        if quick { " --quick" } else { "" },
        if with_gwyddion { " --gwyddion" } else { "" },
        machine.cpu,
        machine.logical_cores,
        machine.date_utc
    );
    let ctx = Context {
        root: root.to_path_buf(),
        out: out.to_path_buf(),
        quick,
        write_docs,
    };
    let accuracy = timed("accuracy", || accuracy::run(&ctx));
    let budget = timed("budget", || budget::run(&ctx));
    let drift = timed("drift", || drift::run(&ctx));
    let productivity = timed("productivity", || productivity::run(&ctx));
    let crb = timed("crb", || crb::run(&ctx));
    let speed = timed("speed", || speed::run(&ctx, accuracy.measured()));
    let nanonis = timed("nanonis", || nanonis::run(&ctx));
    let postgres = timed("postgres", || postgres::run(&ctx));
    let vertical = timed("vertical", || vertical::run(&ctx));
    let real = timed("real", || real::run(&ctx));
    let gwyddion = timed("gwyddion", || {
        if with_gwyddion {
            gwyddion::run(&ctx)
        } else {
            Err(XtaskError::step(
                "gwyddion",
                "not run: pass --gwyddion (installs libgwyddion20-dev with apt-get when root)",
            ))
        }
    });
    let linalg = timed("linalg", || linalg::run(&ctx));
    let mut machine = machine;
    machine.load_average_end = load_average();
    let mut command = String::from("cargo xtask bench");
    if quick {
        command.push_str(" --quick");
    }
    if with_gwyddion {
        command.push_str(" --gwyddion");
    }
    if write_docs {
        command.push_str(" --write-docs");
    }
    let (commit, uncommitted) = source_state(root);
    let results = Results {
        machine,
        command,
        commit,
        uncommitted,
        quick,
        bench_wall_time_s: started.elapsed().as_secs_f64(),
        accuracy,
        budget,
        drift,
        productivity,
        crb,
        speed,
        gwyddion,
        vertical,
        linalg,
        nanonis,
        postgres,
        real,
    };
    report::write(&ctx, &results)
}

/// What every section needs.
pub struct Context {
    /// Workspace root.
    pub root: PathBuf,
    /// Output folder (results.json, figures, scratch).
    pub out: PathBuf,
    /// Reduced run.
    pub quick: bool,
    /// Regenerate the committed docs/ (`--write-docs`).
    pub write_docs: bool,
}

impl Context {
    /// A fresh scratch folder under the output folder.
    pub fn scratch(&self, name: &str) -> Result<PathBuf, XtaskError> {
        let dir = self.out.join("scratch").join(name);
        if dir.exists() {
            std::fs::remove_dir_all(&dir)
                .map_err(|e| XtaskError::step(format!("removing {}", dir.display()), e))?;
        }
        std::fs::create_dir_all(&dir)
            .map_err(|e| XtaskError::step(format!("creating {}", dir.display()), e))?;
        Ok(dir)
    }
}

fn timed<T>(name: &str, f: impl FnOnce() -> Result<T, XtaskError>) -> Section<T> {
    let started = Instant::now();
    let result = f();
    match &result {
        Ok(_) => println!(
            "   {name}: done in {:.1} s",
            started.elapsed().as_secs_f64()
        ),
        Err(e) => println!("   {name}: missing ({e})"),
    }
    Section::from_result(result)
}

/// A calibration with its figures.
pub struct Calibrated {
    /// spmcal's report (report.json).
    pub report: CalibrationReport,
    /// RMS over nodes of (K̄x, K̄y averaged over the node's repeats ÷ the
    /// oracle's true value − 1), %: the error the net's repeats leave.
    pub node_mean_k_rms_pct: Option<f64>,
}

/// Runs one calibration job into a fresh CDB in `dir` and evaluates it
/// (spmcal's `run_job` + `finish`, as `cargo xtask calibrate` does).
pub fn calibrate(
    job: &Job,
    dir: &Path,
    quick: bool,
    with_images: bool,
) -> Result<Calibrated, XtaskError> {
    let cdb_path = dir.join("cdb.sqlite");
    let mut quiet = NoObserver;
    let mut recorder = RecordingObserver::new(&mut quiet);
    let started = Instant::now();
    let mut outcome = run_job(
        job,
        &cdb_path,
        RunStart::New {
            run_id: "bench".to_owned(),
        },
        // A fixed start time: the CDB contents do not depend on the clock.
        1_800_000_000.0,
        &mut recorder,
    )
    .map_err(|e| XtaskError::step(format!("calibration in {}", dir.display()), e))?;
    let wall_time_s = started.elapsed().as_secs_f64();
    let samples = recorder.into_samples();
    // The validation's corrected standard, imaged as `spmcal calibrate` images it.
    let standard = spmcal::run::standard_images(&mut outcome.instrument, &job.plan, &samples.nodes);
    let stored = spmcal::run::stored_standard(job);
    let record = RunRecord::of_job(&job.plan, &outcome, &samples, wall_time_s)
        .with_standard_images(standard.as_ref())
        .with_stored_standard(stored.as_ref());
    let report = finish_with(&cdb_path, dir, &record, quick, with_images)
        .map_err(|e| XtaskError::step(format!("report in {}", dir.display()), e))?;
    let node_mean_k_rms_pct = match outcome.instrument.simulator() {
        Some(sim) => node_mean_error(&cdb_path, sim)?,
        None => None,
    };
    Ok(Calibrated {
        report,
        node_mean_k_rms_pct,
    })
}

fn node_mean_error(cdb_path: &Path, sim: &spm_sim::Simulator) -> Result<Option<f64>, XtaskError> {
    let fail = |e: spm_cdb::CdbError| XtaskError::step("reading the bench CDB", e);
    let cdb = spm_cdb::Cdb::open_read_only(cdb_path).map_err(fail)?;
    let snapshot = cdb.snapshot().map_err(fail)?;
    let records =
        spm_cdb::CdbRead::records(&snapshot, &spm_cdb::RecordFilter::default()).map_err(fail)?;
    Ok(spm_evaluation::accuracy::node_mean_k_rms_pct(&records, sim))
}

fn machine() -> Machine {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|text| {
            text.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_owned())
        })
        .unwrap_or_else(|| "unknown".to_owned());
    let rustc = std::process::Command::new("rustc")
        .arg("--version")
        .output()
        .ok()
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .map_or_else(|| "unknown".to_owned(), |s| s.trim().to_owned());
    Machine {
        cpu,
        logical_cores: std::thread::available_parallelism().map_or(1, usize::from),
        date_utc: date_utc(),
        rustc,
        load_average_start: load_average(),
        load_average_end: String::new(),
    }
}

fn source_state(root: &Path) -> (String, Vec<String>) {
    let git = |args: &[&str]| {
        std::process::Command::new("git")
            .arg("-C")
            .arg(root)
            .args(args)
            .output()
            .ok()
            .filter(|o| o.status.success())
            .and_then(|o| String::from_utf8(o.stdout).ok())
    };
    let commit = git(&["rev-parse", "--short", "HEAD"])
        .map_or_else(|| "unknown".to_owned(), |s| s.trim().to_owned());
    let uncommitted = git(&["status", "--porcelain", "--untracked-files=no"])
        .map(|s| {
            s.lines()
                .filter_map(|l| l.get(3..))
                .filter(|p| !p.starts_with("docs/"))
                .map(str::to_owned)
                .collect()
        })
        .unwrap_or_default();
    (commit, uncommitted)
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "unknown".to_owned())
}

/// The current UTC date and time, YYYY-MM-DD HH:MM.
fn date_utc() -> String {
    civil_date(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs()),
    )
}

/// Seconds since the Unix epoch as YYYY-MM-DD HH:MM (UTC; the calendar of
/// `spm_formats::DateTime::from_unix_seconds`).
fn civil_date(secs: u64) -> String {
    i64::try_from(secs)
        .ok()
        .and_then(spm_formats::DateTime::from_unix_seconds)
        .map_or_else(
            || format!("{secs} s after 1970"),
            |d| {
                format!(
                    "{:04}-{:02}-{:02} {:02}:{:02}",
                    d.year, d.month, d.day, d.hour, d.minute
                )
            },
        )
}

/// Root mean square ([`spm_regression::rms`]); NaN when empty (a table cell without data).
pub fn rms(values: &[f64]) -> f64 {
    spm_regression::rms(values).unwrap_or(f64::NAN)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn civil_dates() {
        assert_eq!(civil_date(0), "1970-01-01 00:00");
        assert_eq!(civil_date(951_782_400), "2000-02-29 00:00");
        assert_eq!(civil_date(1_704_067_200 + 3_661), "2024-01-01 01:01");
    }

    #[test]
    fn rms_of_nothing_is_nan() {
        assert!(rms(&[]).is_nan());
        assert!((rms(&[3.0, 4.0]) - 12.5_f64.sqrt()).abs() < 1e-12);
    }
}
