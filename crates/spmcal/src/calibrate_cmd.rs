//! `spmcal calibrate --config FILE [--cdb PATH] [--resume] [--out DIR]`.
//!
//! SIGINT, SIGTERM and SIGHUP stop the run at the next safe point (before the next instrument
//! operation, never inside a CDB transaction; a visit cut short stays undone): the run is
//! marked 'aborted' with a message and `--resume` continues it. A second signal of the same kind ends the program at once
//! (exit 1; the CDB stays consistent, as after a kill).

use crate::error::CliError;
use crate::files;
use spm_calibration::{GiveUpReason, NodeMeasurement, Observer, PlanVisit};
use spm_hal::{CountVelocity, Seconds};
use spmcal::job::Job;
use spmcal::progress::ProgressBarObserver;
use spmcal::report::{RunRecord, finish_with};
use spmcal::run::{RecordingObserver, RunStart, mark_aborted, run_job_interruptible};
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

/// The report folder when `--out` is not given.
pub const DEFAULT_OUT: &str = "spmcal-calibrate";

/// The files a run writes into its report folder.
pub const OUTPUT_FILES: [&str; 13] = [
    "report.json",
    "report.html",
    "surfaces.json",
    "lcc-kx.png",
    "lcc-ky.png",
    "lcc-alpha.png",
    spmcal::plots::UNCERTAINTY_FILE,
    spmcal::plots::RESIDUAL_FILE,
    spmcal::plots::BEFORE_AFTER_FILE,
    spmcal::plots::HISTORY_FILE,
    "trajectory.png",
    "drift.png",
    LOG_FILE,
];

/// The run's log in its report folder (every event at `info` and above; `--log` names
/// another file instead).
pub const LOG_FILE: &str = "calibrate.log";

/// The termination signals that stop a run at the next safe point.
#[cfg(unix)]
const STOP_SIGNALS: [(i32, &str); 3] = [
    (signal_hook::consts::SIGINT, "SIGINT"),
    (signal_hook::consts::SIGTERM, "SIGTERM"),
    (signal_hook::consts::SIGHUP, "SIGHUP"),
];

/// Set by a termination signal; read between visits.
struct StopRequest {
    requested: Arc<AtomicBool>,
    signal: Arc<AtomicUsize>,
}

impl StopRequest {
    /// Installs the handlers (they only set flags: async-signal-safe).
    fn install() -> Result<Self, CliError> {
        let requested = Arc::new(AtomicBool::new(false));
        let signal = Arc::new(AtomicUsize::new(0));
        #[cfg(unix)]
        for (number, _) in STOP_SIGNALS {
            let installed =
                signal_hook::flag::register_conditional_shutdown(number, 1, Arc::clone(&requested))
                    .and_then(|_| signal_hook::flag::register(number, Arc::clone(&requested)))
                    .and_then(|_| {
                        signal_hook::flag::register_usize(
                            number,
                            Arc::clone(&signal),
                            number as usize,
                        )
                    });
            installed.map_err(|e| {
                CliError::RunFailed(format!("cannot install the signal handlers: {e}"))
            })?;
        }
        Ok(Self { requested, signal })
    }

    fn requested(&self) -> bool {
        self.requested.load(Ordering::SeqCst)
    }

    /// From now on a stop request ends the program at once, with `message` (after the signal's
    /// name) and exit code 1: for the phase after the run, whose records are committed and
    /// whose files are written whole or not at all, so nothing is left to keep consistent
    /// (issue 25 item 12: a signal during the report was swallowed and the program exited 0).
    fn exit_on_request(&self, message: String) {
        let requested = Arc::clone(&self.requested);
        let signal = Arc::clone(&self.signal);
        let watcher = move || {
            loop {
                if requested.load(Ordering::SeqCst) {
                    let name = Self::name_of(signal.load(Ordering::SeqCst));
                    let _ = writeln!(
                        std::io::stderr(),
                        "spmcal: error: interrupted by {name} {message}"
                    );
                    std::process::exit(crate::error::EXIT_RUN_FAILED);
                }
                std::thread::sleep(std::time::Duration::from_millis(20));
            }
        };
        if let Err(e) = std::thread::Builder::new()
            .name("stop-watcher".to_owned())
            .spawn(watcher)
        {
            tracing::error!("cannot watch for stop signals during the report: {e}");
        }
    }

    /// The name of the signal received.
    fn name(&self) -> &'static str {
        Self::name_of(self.signal.load(Ordering::SeqCst))
    }

    /// The name of signal `number`.
    fn name_of(number: usize) -> &'static str {
        #[cfg(unix)]
        for (n, name) in STOP_SIGNALS {
            if n as usize == number {
                return name;
            }
        }
        "a termination signal"
    }
}

/// Forwards to the progress observer and says stop once a signal has arrived.
struct Stoppable<'a> {
    inner: &'a mut dyn Observer,
    stop: &'a StopRequest,
}

impl Observer for Stoppable<'_> {
    fn run_started(&mut self, total_visits: usize, already_finished: usize) {
        self.inner.run_started(total_visits, already_finished);
    }
    fn node_started(&mut self, visit: &PlanVisit, attempt: u32) {
        self.inner.node_started(visit, attempt);
    }
    fn node_finished(&mut self, measurement: &NodeMeasurement) {
        self.inner.node_finished(measurement);
    }
    fn node_given_up(&mut self, visit: &PlanVisit, reason: &GiveUpReason) {
        self.inner.node_given_up(visit, reason);
    }
    fn cycle_spoiled(&mut self, visit: &PlanVisit, reason: &spm_fos::SpoilReason) {
        self.inner.cycle_spoiled(visit, reason);
    }
    fn drift_estimate(&mut self, visit: &PlanVisit, velocity: CountVelocity, at: Seconds) {
        self.inner.drift_estimate(visit, velocity, at);
    }
    fn attach_sightings(&mut self, visit: &PlanVisit, sightings: &[spm_fos::Sighting]) {
        self.inner.attach_sightings(visit, sightings);
    }
    fn keep_going(&mut self) -> bool {
        !self.stop.requested() && self.inner.keep_going()
    }
}

fn now_unix_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// What the report after the run holds.
#[derive(Debug, Clone, Copy)]
pub struct ReportOptions {
    /// Take the image benchmark's test images (simulated backends).
    pub image_benchmark: bool,
    /// A reduced report (smoke runs).
    pub quick: bool,
    /// Exit with [`crate::error::EXIT_TARGET_MISSED`] when a target of the plan is missed
    /// (false: `--no-targets`).
    pub enforce_targets: bool,
}

/// Refuses a CDB file (or one of its `-wal`/`-shm`/`-journal`/`-identity` companions) that is where
/// the run writes a report file or that file's temporary `NAME.partial`: compared by
/// location, so also when neither exists yet (issue 25: a new CDB named
/// `OUT/report.json` was replaced by the report, every record lost, exit 0).
fn check_cdb_is_no_report_file(cdb: &Path, out: &Path) -> Result<(), CliError> {
    let cdb_files: Vec<PathBuf> = ["", "-wal", "-shm", "-journal", "-identity"]
        .iter()
        .map(|suffix| {
            let mut s = cdb.as_os_str().to_owned();
            s.push(suffix);
            files::location(Path::new(&s))
        })
        .collect();
    for name in OUTPUT_FILES {
        let target = out.join(name);
        for written in [target.clone(), spmcal::report::partial_path(&target)] {
            if cdb_files.contains(&files::location(&written)) {
                return Err(CliError::BadInput(format!(
                    "--cdb {}: is where the run writes its report file {} (--out {}); \
                     give the calibration database another name or folder",
                    cdb.display(),
                    written.display(),
                    out.display()
                )));
            }
        }
    }
    Ok(())
}

/// The CLI error of a run that did not end: bad input, or a failure (one the stop request
/// caused, as a paused Nanonis scan, says so).
fn run_error(e: &spmcal::run::JobRunError, stop: &StopRequest) -> CliError {
    if e.is_bad_input() {
        CliError::BadInput(e.to_string())
    } else if stop.requested() && e.is_cdb_wait_interrupted() {
        CliError::RunFailed(format!(
            "interrupted by {} while waiting for the calibration database ({e}); nothing of \
             the visit under way is stored, and the run could not be marked 'aborted' (it \
             stays 'running'); continue it with --resume",
            stop.name()
        ))
    } else if stop.requested() {
        CliError::RunFailed(format!(
            "interrupted by {}: the run stopped inside a visit ({e}); nothing of that visit is \
             stored, the run is marked 'aborted' in the CDB; continue it with --resume",
            stop.name()
        ))
    } else {
        CliError::RunFailed(e.to_string())
    }
}

/// Where the job comes from.
#[derive(Debug, Clone)]
pub enum JobSource {
    /// A job file.
    Config(PathBuf),
    /// `--virtual IMAGE --standard NAME`: a stored image and the plan built for it.
    Virtual(PathBuf, spmcal::virtual_mode::VirtualRunOptions),
}

pub fn run(
    source: &JobSource,
    cdb: Option<&Path>,
    resume: bool,
    out: Option<&Path>,
    report_options: ReportOptions,
) -> Result<(), CliError> {
    let stop = StopRequest::install()?;
    let job = match source {
        JobSource::Config(config) => Job::from_file(config),
        JobSource::Virtual(image, options) => Job::virtual_image(image, options),
    }
    .map_err(|e| CliError::BadInput(e.to_string()))?;
    let out: PathBuf = out.map_or_else(|| PathBuf::from(DEFAULT_OUT), Path::to_path_buf);
    let cdb_path = cdb.map_or_else(|| out.join("cdb.sqlite"), Path::to_path_buf);
    let inputs = guard_files(source, &cdb_path, &out)?;
    std::fs::create_dir_all(&out).map_err(|e| CliError::io(&out, e))?;
    if stop.requested() {
        return Err(CliError::RunFailed(format!(
            "interrupted by {} before the run started; nothing was written",
            stop.name()
        )));
    }
    // The log goes into the report folder from here on (with what was logged before).
    if let Err(e) = crate::console::attach_log(&out.join(LOG_FILE)) {
        tracing::error!("cannot write the log {}: {e}", out.join(LOG_FILE).display());
    }
    let start_unix_s = now_unix_s();
    let start = if resume {
        RunStart::Resume
    } else {
        RunStart::New {
            run_id: format!("{}-{}", job.plan.scanner_id, start_unix_s as u64),
        }
    };
    let mut progress = ProgressBarObserver::new();
    let mut stoppable = Stoppable {
        inner: &mut progress,
        stop: &stop,
    };
    let mut recorder = RecordingObserver::new(&mut stoppable);
    let started = Instant::now();
    // A Nanonis controller's running scan is paused at a signal (not finished first).
    let interrupt = Some(Arc::clone(&stop.requested));
    let mut outcome = run_job_interruptible(
        &job,
        &cdb_path,
        start,
        start_unix_s,
        &mut recorder,
        interrupt,
    )
    .map_err(|e| run_error(&e, &stop))?;
    let wall_time_s = started.elapsed().as_secs_f64();
    let samples = recorder.into_samples();
    progress.finish();
    let run_id = outcome.report.run_id.clone();
    if outcome.report.interrupted {
        let signal = stop.name();
        let marked = mark_aborted(&cdb_path, &run_id, start_unix_s + wall_time_s.max(0.0));
        return Err(CliError::RunFailed(match marked {
            Ok(()) => format!(
                "interrupted by {signal}: run {run_id} stopped after {} visits measured now \
                 ({} before) and was marked 'aborted'; continue it with --resume",
                outcome.report.nodes_done, outcome.report.already_finished
            ),
            Err(e) => format!(
                "interrupted by {signal}: run {run_id} stopped after {} visits measured now; \
                 it could not be marked 'aborted' ({e}); continue it with --resume",
                outcome.report.nodes_done
            ),
        }));
    }
    stop.exit_on_request(format!(
        "after the run: run {run_id}'s {} visits are stored in the CDB {} and it is marked \
         finished; the report in {} is incomplete",
        outcome.report.nodes_done,
        spmcal::cdb_handle::shown(&cdb_path),
        out.display()
    ));
    let spinner = ProgressBarObserver::phases();
    let phase = |name: &str| spinner.phase(name);
    phase("imaging the standard over the calibrated region (validation)");
    // The standard imaged over the calibrated region, for the validation's lattice check; a
    // virtual run's stored image is itself corrected and measured instead.
    let stored = spmcal::run::stored_standard(&job);
    let standard = spmcal::run::standard_images(&mut outcome.instrument, &job.plan, &samples.nodes);
    if let Err(e) = outcome.instrument.release() {
        tracing::error!("the controller's own compensation could not be switched back on: {e}");
    }
    let provenance = run_provenance(
        &job,
        &outcome.instrument,
        (start_unix_s, wall_time_s),
        &inputs,
    );
    let record = RunRecord::of_job(&job.plan, &outcome, &samples, wall_time_s)
        .with_standard_images(standard.as_ref())
        .with_stored_standard(stored.as_ref())
        .with_provenance(&provenance)
        .with_phase(&phase);
    let report = finish_with(
        &cdb_path,
        &out,
        &record,
        report_options.quick,
        report_options.image_benchmark,
    )
    .map_err(|e| CliError::RunFailed(e.to_string()))?;
    spinner.finish();
    crate::outln!(
        "run {}: {} visits measured now ({} before), {} given up, {} records; CDB {}; report {}",
        run_id,
        outcome.report.nodes_done,
        outcome.report.already_finished,
        outcome.report.given_up.len(),
        report.records,
        spmcal::cdb_handle::shown(&cdb_path),
        out.join("report.json").display()
    );
    for line in report.summary_text().lines() {
        crate::outln!("{line}");
    }
    let warnings = crate::console::warning_counts();
    if !warnings.is_empty() {
        let kinds: Vec<String> = warnings
            .iter()
            .map(|(message, n)| format!("{n} × {message}"))
            .collect();
        crate::outln!(
            "recovered or noted during the run (details in {}): {}",
            crate::files::log_path()
                .unwrap_or_else(|| out.join(LOG_FILE))
                .display(),
            kinds.join("; ")
        );
    }
    crate::outln!("report: {}", out.join("report.html").display());
    targets_verdict(&report, source, &run_id, report_options.enforce_targets)
}

/// Exit code 3 ([`CliError::TargetMissed`]) when the report missed a target of its plan,
/// unless `enforce` is off (`--no-targets`: a line says so).
fn targets_verdict(
    report: &spmcal::report::CalibrationReport,
    source: &JobSource,
    run_id: &str,
    enforce: bool,
) -> Result<(), CliError> {
    let missed: Vec<&str> = report
        .targets
        .iter()
        .filter(|t| t.outcome == spmcal::targets::TargetOutcome::Fail)
        .map(|t| t.target.as_str())
        .collect();
    if missed.is_empty() {
        return Ok(());
    }
    if !enforce {
        crate::outln!(
            "missed {} of the plan's targets; not failing the run (--no-targets)",
            missed.len()
        );
        return Ok(());
    }
    Err(CliError::TargetMissed(format!(
        "run {run_id} missed {} of the targets its plan declares ([plan.targets] of the job {}): {}; the records \
         and the report are complete (exit 3; --no-targets exits 0)",
        missed.len(),
        match source {
            JobSource::Config(config) => config.display().to_string(),
            JobSource::Virtual(image, _) => format!("the plan built for {}", image.display()),
        },
        missed.join("; ")
    )))
}

/// The job's input files, after checking that the run replaces none of them: the CDB is none
/// of the inputs, and no report file is an input or the CDB (bad input otherwise, nothing
/// written).
fn guard_files(source: &JobSource, cdb_path: &Path, out: &Path) -> Result<Vec<PathBuf>, CliError> {
    // Every file the run reads must stay as it is: the CDB is none of the configs, and no
    // report file is a config or the CDB.
    let mut inputs: Vec<PathBuf> = Vec::new();
    match source {
        JobSource::Config(config) => {
            inputs.push(config.clone());
            inputs.extend(Job::referenced_files(config));
        }
        JobSource::Virtual(image, options) => {
            inputs.push(image.clone());
            inputs.extend(options.counter_image.iter().cloned());
        }
    }
    let input_refs: Vec<&Path> = inputs.iter().map(PathBuf::as_path).collect();
    // A PostgreSQL URL names no file: the file guards apply to a CDB file only.
    let cdb_is_file = !spmcal::cdb_handle::is_postgres(cdb_path);
    if cdb_is_file && cdb_path.exists() {
        files::check_input(cdb_path, "calibration database")?;
    }
    if cdb_is_file {
        check_cdb_is_no_report_file(cdb_path, out)?;
        files::check_output(cdb_path, "--cdb", &input_refs)?;
    }
    let mut protected = input_refs.clone();
    protected.push(cdb_path);
    for name in OUTPUT_FILES {
        files::check_output(&out.join(name), "--out", &protected)?;
    }
    if out.exists() && !out.is_dir() {
        return Err(CliError::BadInput(format!(
            "--out {}: not a directory",
            out.display()
        )));
    }
    Ok(inputs)
}

/// The run's provenance for its report: the times, the program, the host, the backend and
/// the input files (with their digests).
fn run_provenance(
    job: &spmcal::job::Job,
    instrument: &spmcal::run::FinishedInstrument,
    (start_unix_s, wall_time_s): (f64, f64),
    inputs: &[PathBuf],
) -> spmcal::report::RunProvenance {
    spmcal::report::RunProvenance {
        started_utc: spm_cdb::rfc3339_utc(start_unix_s),
        finished_utc: spm_cdb::rfc3339_utc(start_unix_s + wall_time_s),
        spmcal_version: env!("CARGO_PKG_VERSION").to_owned(),
        spmcal_commit: option_env!("SPMCAL_GIT_COMMIT").map(str::to_owned),
        host: host_name(),
        backend: instrument.identity(&job.backend),
        seed: match &job.backend {
            #[cfg(feature = "sim")]
            spmcal::job::Backend::Sim(config) => Some(config.seed),
            _ => None,
        },
        inputs: inputs
            .iter()
            .map(|p| spmcal::report::InputFile::of(p))
            .collect(),
    }
}

/// The machine's host name (Linux: the kernel's; else `HOSTNAME`), for the provenance.
fn host_name() -> Option<String> {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|h| h.trim().to_owned())
        .filter(|h| !h.is_empty())
}
