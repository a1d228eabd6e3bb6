//! Running a job: the backend, the CDB, the calibrator, and a recording observer.

use crate::cdb_handle::{CdbHandle, is_postgres};
use crate::job::{Backend, Job};
use spm_calibration::{
    Calibrator, GiveUpReason, NodeMeasurement, Observer, PlanVisit, RunError, RunOptions, RunReport,
};
use spm_cdb::{ProgressStore, RunInfo, RunStatus};
use spm_hal::{CountVelocity, Seconds};
#[cfg(feature = "sim")]
use spm_sim::Simulator;
use std::path::Path;
use std::sync::Arc;

/// Why a run could not be carried out.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum JobRunError {
    /// The CDB cannot be opened or read.
    #[error(transparent)]
    Cdb(#[from] spm_cdb::CdbError),
    /// The backend cannot be built from its config.
    #[error("backend: {0}")]
    Backend(#[source] Box<dyn std::error::Error + Send + Sync>),
    /// Every run id derived from the requested one is taken.
    #[error("no free run id: {0:?} and 10000 derived ids are all taken")]
    NoFreeRunId(String),
    /// The calibration failed as a whole.
    #[error(transparent)]
    Run(#[from] RunError),
    /// `--resume` found nothing to resume.
    #[error("no unfinished run of scanner {0:?} in the calibration database")]
    NothingToResume(String),
    /// `--resume` with a job whose plan or simulator config differs from the run's.
    #[error(
        "{path}: run {run_id:?} was started with another job (its plan or simulator config \
         differs); resume it with the config it was started with, or start a new run \
         without --resume"
    )]
    ConfigMismatch {
        /// The CDB.
        path: std::path::PathBuf,
        /// The unfinished run.
        run_id: String,
    },
    /// The CDB fails its integrity check: nothing is appended to it.
    #[error(
        "{path}: the calibration database fails its integrity check ({problems}); nothing \
         was written. See `spmcal cdb check {path}`",
        path = path.display()
    )]
    CdbRejected {
        /// The CDB.
        path: std::path::PathBuf,
        /// The first problems found.
        problems: String,
    },
}

impl JobRunError {
    /// True when a stop request cut a wait for the CDB (a PostgreSQL server that did not
    /// answer, or a reconnect loop): the run could not be marked 'aborted' then.
    pub fn is_cdb_wait_interrupted(&self) -> bool {
        let cdb = match self {
            Self::Cdb(e) => Some(e),
            Self::Run(RunError::Store(e)) => e.downcast_ref::<spm_cdb::CdbError>(),
            _ => None,
        };
        cdb.is_some_and(|e| e.kind() == spm_cdb::ErrorKind::Interrupted)
    }

    /// True when the error is the input's fault (a bad CDB, config or argument), false when
    /// the run itself failed.
    pub fn is_bad_input(&self) -> bool {
        match self {
            Self::NothingToResume(_) | Self::ConfigMismatch { .. } | Self::CdbRejected { .. } => {
                true
            }
            Self::Cdb(inner) => !matches!(
                inner.kind(),
                spm_cdb::ErrorKind::Sqlite
                    | spm_cdb::ErrorKind::Postgres
                    | spm_cdb::ErrorKind::Interrupted
                    | spm_cdb::ErrorKind::Io
            ),
            Self::Backend(_) | Self::Run(_) | Self::NoFreeRunId(_) => false,
        }
    }
}

/// The job's config text without the line naming where the simulator config was read from
/// (the same job resumed from another folder is the same job) and without the controller
/// state a Nanonis backend found (a resumed run finds its own compensation switched off).
fn comparable_config(text: &str) -> String {
    text.lines()
        .filter(|l| !l.starts_with("# simulator: ") && !l.starts_with("# controller: "))
        .collect::<Vec<_>>()
        .join("\n")
        .trim_end()
        .to_owned()
}

/// Refuses a CDB that `cdb check` rejects, before anything is written to it. A file of an
/// older schema (migrated on the read-write open) is checked after its migration by the
/// next `cdb check`.
fn verify_existing_cdb(cdb_path: &Path) -> Result<(), JobRunError> {
    let postgres = is_postgres(cdb_path);
    if !postgres && !cdb_path.exists() {
        return Ok(());
    }
    let cdb = match CdbHandle::open_read_only(cdb_path) {
        Ok(cdb) => cdb,
        Err(e) if e.kind() == spm_cdb::ErrorKind::OutdatedSchema => return Ok(()),
        // A PostgreSQL database without the schema gets it on the read-write open (which
        // refuses another program's tables).
        Err(e) if postgres && e.kind() == spm_cdb::ErrorKind::NotACdb => return Ok(()),
        Err(e) => return Err(e.into()),
    };
    let report = cdb.read().check()?;
    if report.is_ok() {
        return Ok(());
    }
    let mut problems: Vec<String> = report.sqlite.iter().take(3).cloned().collect();
    problems.extend(
        report
            .problems
            .iter()
            .take(3)
            .map(|p| format!("{}: {}", p.kind, p.detail)),
    );
    Err(JobRunError::CdbRejected {
        path: crate::cdb_handle::shown(cdb_path).into(),
        problems: problems.join("; "),
    })
}

/// Registers a new run under `base` or, when that id is taken (another run started in the
/// same second), under `base-2`, `base-3`, …: a run id is never reused.
fn create_unique_run(
    cdb: &mut CdbHandle,
    base: &str,
    run: &RunInfo,
) -> Result<String, JobRunError> {
    let mut last = None;
    for n in 1..=10_000u32 {
        let run_id = if n == 1 {
            base.to_owned()
        } else {
            format!("{base}-{n}")
        };
        let info = RunInfo {
            run_id: run_id.clone(),
            ..run.clone()
        };
        match cdb.create_run(&info) {
            Ok(()) => return Ok(run_id),
            Err(e) if e.kind() == spm_cdb::ErrorKind::Conflict => last = Some(e),
            Err(e) => return Err(e.into()),
        }
    }
    Err(last.map_or_else(
        || JobRunError::NoFreeRunId(base.to_owned()),
        JobRunError::from,
    ))
}

/// One drift estimate during the run.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct DriftSample {
    /// Instrument time, s.
    pub time_s: f64,
    /// Drift velocity x, counts/s.
    pub vx_counts_per_s: f64,
    /// Drift velocity y, counts/s.
    pub vy_counts_per_s: f64,
    /// The estimate of a skipping cycle that the monitor spoiled and discarded.
    pub spoiled: bool,
}

/// One measured node, for plots.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct NodeSample {
    /// Repeat.
    pub repeat_index: u32,
    /// Node index in the repeat's order.
    pub node_index: u32,
    /// LCS gravity centre x, counts.
    pub x_counts: f64,
    /// LCS gravity centre y, counts.
    pub y_counts: f64,
    /// K̄x, nm/count.
    pub kx_nm_per_count: f64,
    /// K̄y, nm/count.
    pub ky_nm_per_count: f64,
    /// α, rad.
    pub alpha_rad: f64,
}

/// Records what a run did (drift, nodes, trajectory) and forwards to an inner observer.
pub struct RecordingObserver<'a> {
    inner: &'a mut dyn Observer,
    /// Drift estimates in time order.
    pub drift: Vec<DriftSample>,
    /// Measured nodes in order.
    pub nodes: Vec<NodeSample>,
    /// Visits given up, with reasons.
    pub given_up: Vec<(PlanVisit, String)>,
    /// Spoiled cycles seen.
    pub spoiled_cycles: usize,
    /// Attachment sequences (sightings of one feature after a node move), in order.
    pub attach_tracks: Vec<spm_correction::dynamics::AttachTrack>,
    /// A cycle was just spoiled: the runner reports its drift estimate next.
    spoil_pending: bool,
}

/// What a [`RecordingObserver`] kept for the report: drift estimates and measured nodes.
#[derive(Debug, Default)]
pub struct RunSamples {
    /// Drift estimates in time order.
    pub drift: Vec<DriftSample>,
    /// Measured nodes in order.
    pub nodes: Vec<NodeSample>,
    /// Attachment sequences in order.
    pub attach_tracks: Vec<spm_correction::dynamics::AttachTrack>,
}

impl<'a> RecordingObserver<'a> {
    /// Ends the recording (releasing the inner observer) and keeps what the report needs.
    pub fn into_samples(self) -> RunSamples {
        RunSamples {
            drift: self.drift,
            nodes: self.nodes,
            attach_tracks: self.attach_tracks,
        }
    }

    /// A recorder forwarding to `inner`.
    pub fn new(inner: &'a mut dyn Observer) -> Self {
        Self {
            inner,
            drift: Vec::new(),
            nodes: Vec::new(),
            given_up: Vec::new(),
            spoiled_cycles: 0,
            attach_tracks: Vec::new(),
            spoil_pending: false,
        }
    }
}

impl Observer for RecordingObserver<'_> {
    fn run_started(&mut self, total_visits: usize, already_finished: usize) {
        self.inner.run_started(total_visits, already_finished);
    }
    fn node_started(&mut self, visit: &PlanVisit, attempt: u32) {
        self.inner.node_started(visit, attempt);
    }
    fn node_finished(&mut self, measurement: &NodeMeasurement) {
        self.nodes.push(NodeSample {
            repeat_index: measurement.visit.repeat_index,
            node_index: measurement.visit.node_index,
            x_counts: measurement.centre.x.value(),
            y_counts: measurement.centre.y.value(),
            kx_nm_per_count: measurement.lcc.kx.value(),
            ky_nm_per_count: measurement.lcc.ky.value(),
            alpha_rad: measurement.lcc.alpha.value(),
        });
        self.inner.node_finished(measurement);
    }
    fn attach_sightings(&mut self, visit: &PlanVisit, sightings: &[spm_fos::Sighting]) {
        self.attach_tracks
            .push(spm_correction::dynamics::AttachTrack {
                sightings: sightings
                    .iter()
                    .map(|s| {
                        (
                            s.time().value(),
                            s.position().x.value(),
                            s.position().y.value(),
                        )
                    })
                    .collect(),
            });
        self.inner.attach_sightings(visit, sightings);
    }
    fn node_given_up(&mut self, visit: &PlanVisit, reason: &GiveUpReason) {
        self.given_up.push((*visit, format!("{reason:?}")));
        self.inner.node_given_up(visit, reason);
    }
    fn cycle_spoiled(&mut self, visit: &PlanVisit, reason: &spm_fos::SpoilReason) {
        self.spoiled_cycles += 1;
        // The runner reports a spoiled cycle's drift estimate right after it, unless the
        // cycle had no finite velocity.
        self.spoil_pending = !matches!(reason, spm_fos::SpoilReason::Invalid);
        self.inner.cycle_spoiled(visit, reason);
    }
    fn drift_estimate(&mut self, visit: &PlanVisit, velocity: CountVelocity, at: Seconds) {
        self.drift.push(DriftSample {
            time_s: at.value(),
            vx_counts_per_s: velocity.x_counts_per_s,
            vy_counts_per_s: velocity.y_counts_per_s,
            spoiled: std::mem::take(&mut self.spoil_pending),
        });
        self.inner.drift_estimate(visit, velocity, at);
    }
    fn keep_going(&mut self) -> bool {
        self.inner.keep_going()
    }
}

/// Where a run starts.
#[derive(Debug, Clone, PartialEq)]
pub enum RunStart {
    /// A new run with this id.
    New {
        /// Run id.
        run_id: String,
    },
    /// The newest unfinished run of the plan's scanner.
    Resume,
}

/// The outcome of [`run_job`].
pub struct JobOutcome {
    /// The calibrator's report.
    pub report: RunReport,
    /// The instrument after the run (its ground truth, when it has one).
    pub instrument: FinishedInstrument,
    /// The lateral commands of the run with their instrument times (the creep model's input).
    pub commands: Vec<spm_hal::recording::CommandEvent>,
    /// The dynamics stage's ladder rasters (empty when the stage was off or failed).
    pub ladder: Vec<spm_calibration::dynamics::LadderFrame>,
}

/// Most lateral commands a run keeps for the creep model (the oldest are dropped beyond it;
/// a 16 × 16 × 3 run sends about 10⁵).
pub const MAX_COMMANDS: usize = 4_000_000;

/// Runs a job's plan on its backend, appending to the CDB at `cdb_path`.
///
/// `start_unix_s` is the wall-clock start (the library reads no clock).
pub fn run_job<O: Observer>(
    job: &Job,
    cdb_path: &Path,
    start: RunStart,
    start_unix_s: f64,
    observer: &mut O,
) -> Result<JobOutcome, JobRunError> {
    run_job_interruptible(job, cdb_path, start, start_unix_s, observer, None)
}

/// [`run_job`], interruptible while the instrument works: once `interrupt` is set, no
/// further instrument operation (move, wait, scan, coarse step) is started on any backend
/// (`spm_hal::interrupt::Interruptible`), so the run stops inside its visit as aborted, the
/// visit left undone for `--resume` (issue 25 item 12); a Nanonis controller's running scan
/// is also paused at once (`NanonisMicroscope::set_interrupt`). Between visits the observer's
/// `keep_going` stops the run cleanly (`RunReport::interrupted`).
pub fn run_job_interruptible<O: Observer>(
    job: &Job,
    cdb_path: &Path,
    start: RunStart,
    start_unix_s: f64,
    observer: &mut O,
    interrupt: Option<std::sync::Arc<std::sync::atomic::AtomicBool>>,
) -> Result<JobOutcome, JobRunError> {
    verify_existing_cdb(cdb_path)?;
    // The instrument is opened before the CDB is touched: a backend that cannot be built
    // leaves no run behind.
    let mut instrument = open_backend(&job.backend)?;
    // Every backend stops before its next instrument operation once the flag is set (the
    // runner then ends the run as aborted, the visit undone); a Nanonis controller also cuts
    // a running scan or wait short.
    let stop = interrupt.unwrap_or_default();
    if let Instrument::Nanonis(nanonis) = &mut instrument {
        nanonis.set_interrupt(std::sync::Arc::clone(&stop));
    }
    // A controller's state as found when it was opened (its own compensation, switched
    // off) is part of the run's provenance (ignored when comparing jobs for --resume).
    let provenance = match &instrument {
        Instrument::Nanonis(nanonis) => format!(
            "{}\n# controller: {}\n",
            job.provenance_text.trim_end(),
            serde_json::to_string(nanonis.controller_state()).unwrap_or_default()
        ),
        #[cfg(feature = "sim")]
        Instrument::Sim(_) => job.provenance_text.clone(),
        Instrument::Virtual(_) => job.provenance_text.clone(),
    };
    let mut cdb = CdbHandle::open(cdb_path)?;
    // A PostgreSQL CDB stops reconnecting, and stops waiting for a silent server, at a stop.
    cdb.set_interrupt(std::sync::Arc::clone(&stop));
    let run_id = match start {
        RunStart::New { run_id } => {
            let run = RunInfo {
                run_id: run_id.clone(),
                scanner_id: job.plan.scanner_id.clone(),
                config: provenance.clone(),
                started_unix_s: start_unix_s,
                finished_unix_s: None,
                status: RunStatus::Running,
            };
            create_unique_run(&mut cdb, &run_id, &run)?
        }
        RunStart::Resume => {
            // The newest run that did not finish: killed ('running'), stopped by a signal
            // ('aborted') or by an instrument failure ('failed'). A finished run is never
            // reused.
            let runs = cdb.read().runs(Some(&job.plan.scanner_id))?;
            let run = runs
                .iter()
                .rev()
                .find(|r| r.status != RunStatus::Finished)
                .ok_or_else(|| JobRunError::NothingToResume(job.plan.scanner_id.clone()))?;
            if comparable_config(&run.config) != comparable_config(&job.provenance_text) {
                return Err(JobRunError::ConfigMismatch {
                    path: crate::cdb_handle::shown(cdb_path).into(),
                    run_id: run.run_id.clone(),
                });
            }
            cdb.reopen_run(&run.run_id)?;
            run.run_id.clone()
        }
    };
    let options = RunOptions {
        run_id,
        start_unix_s,
        config_text: provenance,
    };
    match instrument {
        #[cfg(feature = "sim")]
        Instrument::Sim(mut sim) => {
            let (result, commands, ladder) =
                calibrate_on(&mut *sim, &mut cdb, observer, job, &options, &stop);
            let report = settle(result, &mut cdb, &options, start_unix_s)?;
            Ok(JobOutcome {
                report,
                instrument: FinishedInstrument::Sim(sim),
                commands,
                ladder,
            })
        }
        Instrument::Nanonis(mut nanonis) => {
            let (result, commands, ladder) =
                calibrate_on(&mut *nanonis, &mut cdb, observer, job, &options, &stop);
            let report = settle(result, &mut cdb, &options, start_unix_s)?;
            Ok(JobOutcome {
                report,
                instrument: FinishedInstrument::Nanonis(nanonis),
                commands,
                ladder,
            })
        }
        Instrument::Virtual(mut virt) => {
            let (result, commands, ladder) =
                calibrate_on(&mut *virt, &mut cdb, observer, job, &options, &stop);
            let report = settle(result, &mut cdb, &options, start_unix_s)?;
            Ok(JobOutcome {
                report,
                instrument: FinishedInstrument::Virtual(virt),
                commands,
                ladder,
            })
        }
    }
}

/// The instrument a job ran on, kept after the run for the report.
#[non_exhaustive]
pub enum FinishedInstrument {
    /// The simulated microscope (its oracle is the ground truth).
    #[cfg(feature = "sim")]
    Sim(Box<Simulator>),
    /// A Nanonis controller (no ground truth).
    Nanonis(Box<spm_nanonis::NanonisMicroscope>),
    /// A stored image served as the surface (no ground truth).
    Virtual(Box<spm_virtual::VirtualMicroscope>),
}

impl FinishedInstrument {
    /// The ground truth the report judges the calibration against, when the backend has one.
    #[must_use]
    pub fn truth(&self) -> Option<&dyn crate::report::TruthSource> {
        match self {
            #[cfg(feature = "sim")]
            Self::Sim(sim) => Some(&**sim),
            Self::Nanonis(_) | Self::Virtual(_) => None,
        }
    }

    /// The true scanner dynamics, when the backend has them (the simulator's).
    #[must_use]
    pub fn true_dynamics(&self) -> Option<crate::dynamics::TrueDynamics> {
        match self {
            #[cfg(feature = "sim")]
            Self::Sim(sim) => Some(crate::dynamics::TrueDynamics::of(sim)),
            Self::Nanonis(_) | Self::Virtual(_) => None,
        }
    }

    /// The simulator, when the backend is simulated (tests and benchmarks that read its
    /// oracle directly).
    #[cfg(feature = "sim")]
    #[must_use]
    pub fn simulator(&self) -> Option<&Simulator> {
        match self {
            Self::Sim(sim) => Some(sim),
            Self::Nanonis(_) | Self::Virtual(_) => None,
        }
    }

    /// The simulator, owned.
    #[cfg(feature = "sim")]
    #[must_use]
    pub fn into_simulator(self) -> Option<Simulator> {
        match self {
            Self::Sim(sim) => Some(*sim),
            Self::Nanonis(_) | Self::Virtual(_) => None,
        }
    }
}

/// The standard imaged over the region of the measured `nodes` after the run, for the
/// validation's lattice check (counter-scanned pairs at the plan's
/// `validation.lattice_places_per_side`² places): on the controller, and on a copy of a simulator (so that the image benchmark, which takes its own
/// images on another copy, sees the instrument as the run left it). `None` when the plan asks
/// for no places, the nodes span no area, or the backend is a stored image.
pub fn standard_images(
    instrument: &mut FinishedInstrument,
    plan: &spm_calibration::PlanConfig,
    nodes: &[NodeSample],
) -> Option<Result<Vec<spm_evaluation::images::TestImage>, String>> {
    use spm_evaluation::images::take_images_without_truth;
    if plan.validation.lattice_places_per_side == 0 {
        return None;
    }
    let region = crate::plots::Region::spanned(nodes)?.counts();
    let config = spm_evaluation::validation::lattice_image_set(plan);
    let taken = match instrument {
        #[cfg(feature = "sim")]
        FinishedInstrument::Sim(sim) => {
            let mut copy = (**sim).clone();
            take_images_without_truth(&mut copy, &region, &config)
        }
        FinishedInstrument::Nanonis(nanonis) => {
            take_images_without_truth(&mut **nanonis, &region, &config)
        }
        // A pair taken from a stored image would only resample its frozen pixels: the image
        // itself is corrected and measured instead ([`stored_standard`]).
        FinishedInstrument::Virtual(_) => return None,
    };
    Some(taken.map_err(|e| e.to_string()))
}

/// The stored image of a virtual job, for the validation's lattice check
/// ([`crate::virtual_mode::stored_lattice_check`]); `None` for other backends, when the plan
/// asks for no places, or when the plan does not name its standard.
#[must_use]
pub fn stored_standard(job: &crate::job::Job) -> Option<crate::virtual_mode::StoredStandard> {
    if job.plan.validation.lattice_places_per_side == 0 {
        return None;
    }
    match &job.backend {
        Backend::Virtual(virt) => crate::virtual_mode::StoredStandard::of_job(virt, &job.plan),
        _ => None,
    }
}

impl FinishedInstrument {
    /// Gives the instrument back as it was found: a Nanonis controller's own compensation,
    /// switched off for the calibration, is switched back on as found (dropping the backend
    /// does it too, as a fallback).
    ///
    /// # Errors
    /// The controller's message; the compensation then stays off.
    pub fn release(&mut self) -> Result<(), String> {
        match self {
            Self::Nanonis(nanonis) => nanonis.restore_compensation().map_err(|e| e.to_string()),
            #[cfg(feature = "sim")]
            Self::Sim(_) => Ok(()),
            Self::Virtual(_) => Ok(()),
        }
    }

    /// The backend and its identity, for the provenance: the simulator's seed, the
    /// controller's address and the state it was found in, the stored image.
    #[must_use]
    pub fn identity(&self, backend: &Backend) -> String {
        match (self, backend) {
            (Self::Nanonis(nanonis), Backend::Nanonis(config)) => format!(
                "nanonis {}:{}; controller {}",
                config.host,
                config.port,
                serde_json::to_string(nanonis.controller_state()).unwrap_or_default()
            ),
            #[cfg(feature = "sim")]
            (Self::Sim(_), Backend::Sim(config)) => format!("sim (seed {})", config.seed),
            (Self::Virtual(_), Backend::Virtual(v)) => format!("virtual ({})", v.image.display()),
            _ => "unknown".to_owned(),
        }
    }
}

/// An opened instrument of one of the [`Backend`]s.
enum Instrument {
    /// The simulated microscope.
    #[cfg(feature = "sim")]
    Sim(Box<Simulator>),
    /// A Nanonis controller over TCP.
    Nanonis(Box<spm_nanonis::NanonisMicroscope>),
    /// A stored image served as the surface.
    Virtual(Box<spm_virtual::VirtualMicroscope>),
}

/// Builds the job's instrument.
fn open_backend(backend: &Backend) -> Result<Instrument, JobRunError> {
    match backend {
        #[cfg(feature = "sim")]
        Backend::Sim(config) => Simulator::new((**config).clone())
            .map(|sim| Instrument::Sim(Box::new(sim)))
            .map_err(|e| JobRunError::Backend(Box::new(e))),
        Backend::Nanonis(config) => {
            let nanonis = spm_nanonis::NanonisMicroscope::connect((**config).clone())
                .map_err(|e| JobRunError::Backend(Box::new(e)))?;
            // The controller's state as found and as set (compensation off) goes into the
            // run's log: a calibration is only meaningful on uncorrected coordinates.
            tracing::info!(
                state = %serde_json::to_string(nanonis.controller_state()).unwrap_or_default(),
                "nanonis controller state"
            );
            Ok(Instrument::Nanonis(Box::new(nanonis)))
        }
        Backend::Virtual(backend) => backend
            .microscope()
            .map(|m| Instrument::Virtual(Box::new(m)))
            .map_err(|e| JobRunError::Backend(Box::new(e))),
    }
}

/// Runs the plan on any instrument, recording its lateral commands (the creep model's input).
fn calibrate_on<M: spm_hal::Microscope, O: Observer>(
    microscope: &mut M,
    cdb: &mut CdbHandle,
    observer: &mut O,
    job: &Job,
    options: &RunOptions,
    stop: &std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> (
    Result<RunReport, RunError>,
    Vec<spm_hal::recording::CommandEvent>,
    Vec<spm_calibration::dynamics::LadderFrame>,
) {
    let recorder = spm_hal::recording::CommandRecorder::new(microscope, MAX_COMMANDS);
    // Outside the recorder: an operation refused after a stop request is not in the log.
    let mut interruptible = spm_hal::interrupt::Interruptible::new(recorder, Arc::clone(stop));
    let result = Calibrator::new(&mut interruptible, &mut *cdb, observer, job.plan.clone())
        .and_then(|mut calibrator| calibrator.run(options));
    let ladder = match &result {
        Ok(report) if job.plan.dynamics.enabled && !report.interrupted => {
            dynamics_stage(&mut interruptible, &job.plan)
        }
        _ => Vec::new(),
    };
    let (_, commands) = interruptible.into_inner().into_parts();
    (result, commands, ladder)
}

/// The dynamics stage after the net (issue 23): the ladder rasters around the field's centre,
/// inside the net's margin. A failed stage is logged and leaves the run without dynamics.
fn dynamics_stage<M: spm_hal::Microscope>(
    microscope: &mut M,
    plan: &spm_calibration::PlanConfig,
) -> Vec<spm_calibration::dynamics::LadderFrame> {
    let caps = microscope.capabilities();
    let centre = spm_hal::CountPoint::from_counts(
        (0.5 * (caps.field_min.x.value() + caps.field_max.x.value())).round(),
        (0.5 * (caps.field_min.y.value() + caps.field_max.y.value())).round(),
    );
    let longest = plan
        .dynamics
        .ladder_counts
        .iter()
        .fold(0.0_f64, |a, &b| a.max(b));
    let margin = plan.net.margin_counts as f64 + 0.5 * longest;
    let half = [
        (0.5 * (caps.field_max.x.value() - caps.field_min.x.value()) - margin).max(0.0),
        (0.5 * (caps.field_max.y.value() - caps.field_min.y.value()) - margin).max(0.0),
    ];
    let scan = spm_calibration::dynamics::scan_ladder(
        microscope,
        &plan.dynamics,
        &plan.standard,
        centre,
        half,
    );
    for failure in &scan.failures {
        tracing::warn!("dynamics stage: a ladder frame was not taken: {failure}");
    }
    scan.frames
}

/// The run's result; a plan the instrument cannot carry out marks the run failed.
fn settle(
    result: Result<RunReport, RunError>,
    cdb: &mut CdbHandle,
    options: &RunOptions,
    start_unix_s: f64,
) -> Result<RunReport, JobRunError> {
    match result {
        Ok(report) => Ok(report),
        Err(error) => {
            // Never leave a run 'running' that nothing will continue on its own: a plan the
            // instrument cannot carry out is marked failed (the runner marks instrument
            // failures itself; a CDB failure leaves the run resumable as it is).
            if let RunError::Plan(_) = error
                && let Ok(Some(run)) = cdb.read().run(&options.run_id)
                && run.status == RunStatus::Running
                && let Err(e) = ProgressStore::finish_run(
                    &mut *cdb,
                    &options.run_id,
                    RunStatus::Failed,
                    start_unix_s,
                )
            {
                tracing::warn!(error = %e, "could not mark the run failed");
            }
            Err(error.into())
        }
    }
}

/// Marks an interrupted run 'aborted' (a signal stopped it at a safe point); `--resume`
/// continues it.
///
/// # Errors
/// CDB errors.
pub fn mark_aborted(cdb_path: &Path, run_id: &str, at_unix_s: f64) -> Result<(), JobRunError> {
    let mut cdb = CdbHandle::open(cdb_path)?;
    ProgressStore::finish_run(&mut cdb, run_id, RunStatus::Aborted, at_unix_s)?;
    Ok(())
}

/// One image taken on a job's backend with the backend's command log (`spmcal scan`): the
/// probe moves to the frame's centre, settles, then rasters.
pub struct RecordedScan {
    /// The frame.
    pub frame: spm_hal::Frame,
    /// Every lateral command of the session, with instrument times.
    pub events: Vec<spm_hal::recording::CommandEvent>,
}

/// Takes `request` on the job's backend (see [`RecordedScan`]).
///
/// # Errors
/// [`JobRunError::Backend`] when the backend cannot be opened or refuses the move or scan.
pub fn scan_recorded(
    job: &Job,
    request: &spm_hal::ScanRequest,
    settle_s: f64,
) -> Result<RecordedScan, JobRunError> {
    fn on<M: spm_hal::Microscope>(
        microscope: &mut M,
        request: &spm_hal::ScanRequest,
        settle_s: f64,
    ) -> Result<RecordedScan, JobRunError>
    where
        M::Error: Send + Sync + 'static,
    {
        use spm_hal::Microscope as _;
        let mut recorder = spm_hal::recording::CommandRecorder::new(microscope, MAX_COMMANDS);
        let backend = |e: M::Error| JobRunError::Backend(Box::new(e));
        let speed = request.pixel_step.value() / request.pixel_dwell.value();
        recorder
            .move_to(spm_hal::MoveRequest {
                target: request.centre(),
                speed: spm_hal::CountsPerSecond(speed),
                settle: spm_hal::Seconds(settle_s),
            })
            .map_err(backend)?;
        let frame = recorder.scan(request).map_err(backend)?;
        let (_, events) = recorder.into_parts();
        Ok(RecordedScan { frame, events })
    }
    match open_backend(&job.backend)? {
        #[cfg(feature = "sim")]
        Instrument::Sim(mut sim) => on(&mut *sim, request, settle_s),
        Instrument::Nanonis(mut nanonis) => on(&mut *nanonis, request, settle_s),
        Instrument::Virtual(mut virt) => on(&mut *virt, request, settle_s),
    }
}
