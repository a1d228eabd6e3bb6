//! The calibration loop: executes the [`NodeMachine`]'s actions on a [`Microscope`] with
//! `spm-fos`, stores results through a [`ProgressStore`] (the CDB), reports to an
//! [`Observer`], and owns termination and checkpoints.
//!
//! # Resumability
//! The plan's visits are registered in the store under (repeat, node index) — stable for a
//! given plan and field. A visit's records and its "done" mark are committed in one
//! transaction ([`ProgressStore::commit_node`]); a given-up visit is marked with its reason.
//! A run killed at any moment therefore resumes ([`Calibrator::run`] with the same run id) at
//! the first visit, in execution order, that is neither done nor given up; a visit interrupted
//! half-way is measured again from its start. Only measurements whose every vector came from
//! kept (unspoiled) cycles reach the store.
//!
//! # Time
//! Record dates are `run_start_unix_s + (instrument clock − instrument clock at start)`: the
//! caller reads the wall clock once ([`RunOptions::start_unix_s`]), the library never.

use crate::config::PlanConfig;
use crate::machine::{
    Action, Anchor, ApertureResult, AttachResult, CycleCounts, Event, Failure, GiveUpReason,
    MachineParams, NodeMachine, NodeMeasurement, SkipResult,
};
use crate::plan::{GridNode, NetPlan, PlanError, PlanVisit};
use serde::{Deserialize, Serialize};
use spm_features::{DetectionConfig, LcsConfig, LcsStandard};
use spm_fos::{
    ApertureParams, AttachOutcome, AttachParams, CounterScanParams, Decision, FosError,
    MonitorParams, Motion, Raster, SkipOutcome, SkipParams, SpoilReason,
};
use spm_hal::{
    CountPoint, CountVector, CountVelocity, Error as _, ErrorKind, Microscope, Nanometres, Seconds,
};
use spm_records::{LccRecord, NodeDone, NodeState, PlanNode, RunInfo, RunStatus};
pub use spm_records::{MemoryStore, MemoryStoreError, ProgressStore};

/// Progress callbacks (all default to nothing). The CLI hangs a progress bar and plots here.
pub trait Observer {
    /// The run starts: visits in the plan and visits already finished (resume).
    fn run_started(&mut self, _total_visits: usize, _already_finished: usize) {}
    /// A visit starts (or restarts: attempt > 1).
    fn node_started(&mut self, _visit: &PlanVisit, _attempt: u32) {}
    /// A visit was measured and stored.
    fn node_finished(&mut self, _measurement: &NodeMeasurement) {}
    /// A visit was given up.
    fn node_given_up(&mut self, _visit: &PlanVisit, _reason: &GiveUpReason) {}
    /// A skipping cycle was spoiled and discarded.
    fn cycle_spoiled(&mut self, _visit: &PlanVisit, _reason: &SpoilReason) {}
    /// Every sighting of one attachment sequence (the feature re-found after a node move,
    /// position and time of each): the data of the creep law's identification.
    fn attach_sightings(&mut self, _visit: &PlanVisit, _sightings: &[spm_fos::Sighting]) {}
    /// A new drift velocity estimate at instrument time `at`.
    fn drift_estimate(&mut self, _visit: &PlanVisit, _velocity: CountVelocity, _at: Seconds) {}
    /// The vertical measurements at a visit (plans with `[plan.steps]`).
    fn kz_searched(&mut self, _visit: &PlanVisit, _search: &crate::vertical::KzSearch) {}
    /// Asked before every visit: `false` stops the run cleanly (it stays resumable).
    fn keep_going(&mut self) -> bool {
        true
    }
}

/// An observer that does nothing.
#[derive(Clone, Copy, Debug, Default)]
pub struct NoObserver;
impl Observer for NoObserver {}

/// Identity and clock of a run.
#[derive(Clone, Debug, PartialEq)]
pub struct RunOptions {
    /// Run id (the same id resumes the run).
    pub run_id: String,
    /// Wall-clock time of the start, UTC seconds since the Unix epoch.
    pub start_unix_s: f64,
    /// The configuration text stored with a new run (provenance).
    pub config_text: String,
}

/// A given-up visit in the report.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GivenUpVisit {
    /// Repeat index.
    pub repeat_index: u32,
    /// Node index.
    pub node_index: u32,
    /// The node, counts.
    pub node: [i64; 3],
    /// Why.
    pub reason: GiveUpReason,
}

/// Summary of a run (of this invocation; `already_finished` counts visits of earlier ones).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RunReport {
    /// Run id.
    pub run_id: String,
    /// Visits in the plan (nodes × repeats).
    pub visits_planned: usize,
    /// Nodes per repeat.
    pub nodes: usize,
    /// Repeats.
    pub repeats: u32,
    /// Visits finished before this invocation (resume).
    pub already_finished: usize,
    /// Visits measured now.
    pub nodes_done: usize,
    /// Visits given up now, with reasons.
    pub given_up: Vec<GivenUpVisit>,
    /// Records stored now.
    pub records: usize,
    /// Skipping cycles kept / discarded / idle, restarts (measured visits and attempts).
    pub cycles: CycleCounts,
    /// Transient backend errors met.
    pub transient_errors: u32,
    /// Instrument time of this invocation, seconds.
    pub instrument_time_s: f64,
    /// True when stopped by the observer before the plan's end.
    pub interrupted: bool,
    /// Step searches for Kz (plans with `[plan.steps]`).
    #[serde(default)]
    pub kz: crate::vertical::KzTally,
    /// The lattice survey and how LCS candidates fared at its gate (`None` when the plan's
    /// `[survey]` is off or every visit was finished before this invocation).
    #[serde(default)]
    pub survey: Option<crate::survey::SurveyReport>,
}

/// Why a run failed as a whole.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RunError {
    /// The plan does not fit the instrument.
    #[error("plan: {0}")]
    Plan(#[from] PlanError),
    /// The store failed (nothing half-written: each node is one transaction).
    #[error("calibration database: {0}")]
    Store(Box<dyn std::error::Error + Send + Sync>),
    /// The instrument failed outside a node, or aborted.
    #[error("instrument ({kind:?}): {message}")]
    Instrument {
        /// The kind.
        kind: ErrorKind,
        /// Message.
        message: String,
    },
    /// A parameter derived from the plan was rejected by the FOS layer.
    #[error("invalid operation parameter `{field}`: {reason}")]
    Parameters {
        /// The parameter.
        field: &'static str,
        /// What is wrong with it.
        reason: &'static str,
    },
    /// The instrument cannot do what the plan asks.
    #[error("the instrument cannot do what the plan asks: {0}")]
    Unsupported(&'static str),
}

/// The FOS parameters derived from a plan (rasters in counts, tolerances in counts/s).
#[derive(Clone, Debug, PartialEq)]
pub struct FosParams {
    /// Attachment.
    pub attach: AttachParams,
    /// Aperture and LCS recognition.
    pub aperture: ApertureParams,
    /// Skipping.
    pub skip: SkipParams,
    /// Counter-scanning of the aperture.
    pub counter: CounterScanParams,
}

fn raster(size_counts: f64, pixels: u32, dwell_s: f64) -> Raster {
    Raster {
        pixels,
        pixel_step_counts: size_counts / f64::from(pixels.saturating_sub(1).max(1)),
        pixel_dwell_s: dwell_s,
    }
}

impl FosParams {
    /// Converts the plan: sizes to rasters, nm/s to counts/s with the nominal sensitivity,
    /// the attachment timeout from `max_attachments`, the monitor's speed limit from the
    /// segment (a feature must not drift more than `tuning.monitor_drift_segment_fraction`
    /// of the segment over one cycle).
    pub fn from_plan(plan: &PlanConfig) -> Self {
        let s = &plan.standard;
        let tuning = &plan.tuning;
        let dwell = plan.motion.pixel_dwell_s;
        let motion = Motion {
            speed_counts_per_s: plan.motion.move_speed_counts_per_s,
            settle_s: plan.motion.settle_s,
        };
        let spacing_counts = s.lattice_constant_nm / s.nominal_nm_per_count;
        let polarity = s.feature.polarity();
        let detection = |r: &Raster| DetectionConfig {
            polarity,
            min_separation_px: (tuning.detection_separation_fraction * spacing_counts
                / r.pixel_step_counts)
                .max(1.5),
            ..DetectionConfig::default()
        };
        let first = raster(
            plan.attach.first_size_counts,
            plan.attach.first_pixels,
            dwell,
        );
        let segment = raster(
            plan.attach.segment_size_counts,
            plan.attach.segment_pixels,
            dwell,
        );
        let aperture = raster(plan.aperture.size_counts, plan.aperture.pixels, dwell);
        let to_counts = |nm_per_s: f64| nm_per_s / s.nominal_nm_per_count;
        let speed_limit = to_counts(plan.drift.max_speed_nm_per_s);
        let hop_s = spacing_counts / motion.speed_counts_per_s + motion.settle_s;
        let track_s = segment.duration_s() + hop_s;
        let timeout_s =
            first.duration_s() + f64::from(plan.attach.max_attachments) * track_s + 1e-9;
        let attach = AttachParams {
            first,
            segment,
            first_detection: detection(&first),
            segment_detection: detection(&segment),
            motion,
            velocity_limit_counts_per_s: speed_limit,
            settle_count: tuning.attach_settle_sightings as usize,
            velocity_window: tuning.attach_velocity_window as usize,
            timeout_s,
            attachment_interval_s: 0.0,
            capture_radius_fraction: tuning.attach_capture_radius_fraction,
        };
        let cycle_s = 2.0 * track_s;
        let monitor = MonitorParams {
            velocity_tolerance_counts_per_s: to_counts(plan.drift.max_change_nm_per_s),
            max_speed_counts_per_s: (tuning.monitor_drift_segment_fraction * segment.side_counts()
                / cycle_s)
                .max(speed_limit),
            idle_cycles: plan.skipping.idle_cycles as usize,
            required_cycles: plan.skipping.cycles as usize,
            max_restarts: plan.skipping.max_restarts as usize,
        };
        let mut skip = SkipParams::new(segment, monitor);
        skip.detection = detection(&segment);
        skip.motion = motion;
        let lcs = LcsConfig {
            standard: LcsStandard {
                ab: Nanometres(s.lattice_constant_nm),
                ac: Nanometres(s.lattice_constant_nm),
                angle_bac: s.lcs_angle(),
            },
            nominal_sensitivity: spm_hal::NmPerCount(s.nominal_nm_per_count),
            length_tolerance: s.length_tolerance_fraction,
            angle_tolerance_rad: s.angle_tolerance_deg.to_radians(),
            prior: None,
            gate: None,
        };
        Self {
            attach,
            aperture: ApertureParams {
                raster: aperture,
                detection: detection(&aperture),
                lcs,
                motion,
            },
            skip,
            counter: CounterScanParams {
                raster: aperture,
                detection: detection(&aperture),
                motion,
                match_radius_counts: tuning.counter_match_radius_fraction * spacing_counts,
                drift_prior: CountVelocity::ZERO,
            },
        }
    }
}

/// Instrument time to UTC: the run's first instrument time and its wall-clock start.
#[derive(Clone, Copy, Debug)]
struct RunClock {
    clock0: Seconds,
    start_unix_s: f64,
}

impl RunClock {
    fn unix(self, t: Seconds) -> f64 {
        self.start_unix_s + (t - self.clock0).value()
    }
}

/// The calibration controller: a plan, a microscope, a store and an observer.
pub struct Calibrator<'a, M: Microscope, S: ProgressStore + ?Sized, O: Observer + ?Sized> {
    microscope: &'a mut M,
    store: &'a mut S,
    observer: &'a mut O,
    config: PlanConfig,
    plan: NetPlan,
    fos: FosParams,
    clock0: Option<Seconds>,
    survey: Option<crate::survey::SurveyReport>,
}

fn fos_failure<E: spm_hal::Error>(error: FosError<E>) -> Result<Failure, RunError> {
    match error {
        FosError::Instrument(e) => {
            let kind = e.kind();
            let message = e.to_string();
            if kind.is_transient() {
                Ok(Failure::Transient {
                    kind: Some(kind),
                    message,
                })
            } else if kind == ErrorKind::Aborted {
                Err(RunError::Instrument { kind, message })
            } else {
                Ok(Failure::Permanent { kind, message })
            }
        }
        FosError::FeatureLost { .. } => Ok(Failure::Transient {
            kind: None,
            message: error.to_string(),
        }),
        FosError::InvalidParameter { field, reason } => Err(RunError::Parameters { field, reason }),
        FosError::Unsupported(what) => Err(RunError::Unsupported(what)),
        other => Ok(Failure::Measurement {
            message: other.to_string(),
        }),
    }
}

/// A backend error of a move, pause, clock read or coarse step: like [`fos_failure`], an
/// `Aborted` instrument stops the run (it is not this node's failure).
fn instrument<E: spm_hal::Error>(e: E) -> Result<Failure, RunError> {
    let kind = e.kind();
    if kind == ErrorKind::Aborted {
        Err(RunError::Instrument {
            kind,
            message: e.to_string(),
        })
    } else if kind.is_transient() {
        Ok(Failure::Transient {
            kind: Some(kind),
            message: e.to_string(),
        })
    } else {
        Ok(Failure::Permanent {
            kind,
            message: e.to_string(),
        })
    }
}

impl<'a, M: Microscope, S: ProgressStore + ?Sized, O: Observer + ?Sized> Calibrator<'a, M, S, O> {
    /// A controller for `config` on `microscope` (the net is laid in its field).
    ///
    /// # Errors
    /// [`RunError::Plan`] when the net does not fit the field.
    pub fn new(
        microscope: &'a mut M,
        store: &'a mut S,
        observer: &'a mut O,
        config: PlanConfig,
    ) -> Result<Self, RunError> {
        let geometry = config.net.geometry(&microscope.capabilities())?;
        let plan = NetPlan::new(&geometry, config.repeats)?;
        let fos = FosParams::from_plan(&config);
        Ok(Self {
            microscope,
            store,
            observer,
            config,
            plan,
            fos,
            clock0: None,
            survey: None,
        })
    }

    /// The plan's visiting order.
    pub fn plan(&self) -> &NetPlan {
        &self.plan
    }

    /// Overrides derived FOS parameters (e.g. detection settings).
    pub fn fos_params_mut(&mut self) -> &mut FosParams {
        &mut self.fos
    }

    fn store_err(e: S::Error) -> RunError {
        RunError::Store(Box::new(e))
    }

    /// Runs (or resumes) the plan to its end, or until the observer says stop.
    ///
    /// # Errors
    /// [`RunError`] for store failures, an aborted instrument, or invalid parameters. Node
    /// failures are not errors: the node is given up and the run goes on.
    pub fn run(&mut self, options: &RunOptions) -> Result<RunReport, RunError> {
        let result = self.run_inner(options);
        if let Err(error) = &result {
            // Mark the run (best effort; it stays resumable: a later run with the same id
            // continues at the first unfinished visit and sets it finished).
            let status = match error {
                RunError::Instrument {
                    kind: ErrorKind::Aborted,
                    ..
                } => Some(RunStatus::Aborted),
                RunError::Instrument { .. }
                | RunError::Parameters { .. }
                | RunError::Unsupported(_) => Some(RunStatus::Failed),
                _ => None,
            };
            if let Some(status) = status {
                let at = match (self.clock0, self.microscope.now()) {
                    (Some(t0), Ok(now)) => options.start_unix_s + (now - t0).value(),
                    _ => options.start_unix_s,
                };
                if let Err(e) = self.store.finish_run(&options.run_id, status, at) {
                    tracing::warn!(error = %e, "could not mark the run");
                }
            }
        }
        result
    }

    fn run_inner(&mut self, options: &RunOptions) -> Result<RunReport, RunError> {
        let span = tracing::info_span!("calibration", run_id = %options.run_id);
        let _enter = span.enter();
        let clock0 = self.microscope.now().map_err(|e| RunError::Instrument {
            kind: e.kind(),
            message: e.to_string(),
        })?;
        self.clock0 = Some(clock0);
        let unix = |t: Seconds| options.start_unix_s + (t - clock0).value();
        let visits: Vec<PlanVisit> = self.plan.visits().collect();
        let nodes: Vec<PlanNode> = visits
            .iter()
            .map(|v| PlanNode {
                repeat_index: v.repeat_index,
                node_index: v.node_index,
                node_x_counts: v.grid.x_counts,
                node_y_counts: v.grid.y_counts,
                node_z_counts: v.grid.z_counts,
            })
            .collect();
        let run = RunInfo {
            run_id: options.run_id.clone(),
            scanner_id: self.config.scanner_id.clone(),
            config: options.config_text.clone(),
            started_unix_s: options.start_unix_s,
            finished_unix_s: None,
            status: RunStatus::Running,
        };
        self.store
            .begin_run(&run, &nodes)
            .map_err(Self::store_err)?;
        let states = self
            .store
            .states(&options.run_id)
            .map_err(Self::store_err)?;
        let finished = |v: &PlanVisit| {
            states
                .get(&(v.repeat_index, v.node_index))
                .is_some_and(|s| !matches!(s, NodeState::Pending))
        };
        let already = visits.iter().filter(|v| finished(v)).count();
        let mut report = RunReport {
            run_id: options.run_id.clone(),
            visits_planned: visits.len(),
            nodes: self.plan.nodes_per_repeat(),
            repeats: self.plan.repeats,
            already_finished: already,
            ..RunReport::default()
        };
        self.observer.run_started(visits.len(), already);
        tracing::info!(visits = visits.len(), already, "calibration run starts");
        if self.config.survey.enabled && already < visits.len() {
            self.survey = Some(self.survey_lattice()?);
        }
        let params = MachineParams::from_plan(&self.config);
        let mut previous: Option<GridNode> = None;
        let mut coarse_now: Option<i64> = None;
        for visit in visits.iter().filter(|v| !finished(v)) {
            if !self.observer.keep_going() {
                report.interrupted = true;
                tracing::info!("run interrupted by the observer");
                break;
            }
            let from = match previous {
                Some(p) => p.position(),
                None => self.read_retrying(|m| m.position())?,
            };
            let lateral = from.distance(visit.grid.position());
            let coarse_delta = match (coarse_now, visit.grid.coarse_steps) {
                (Some(a), Some(b)) => b - a,
                _ => 0,
            };
            let pause = self.config.pause.pause(lateral, coarse_delta);
            let clock = RunClock {
                clock0,
                start_unix_s: options.start_unix_s,
            };
            self.fos.aperture.lcs.gate = self.survey.as_ref().and_then(|s| s.gate());
            self.run_visit(
                visit,
                &params,
                pause,
                &mut coarse_now,
                &options.run_id,
                clock,
                &mut report,
            )?;
            previous = Some(visit.grid);
        }
        report.survey = self.survey.take().map(|mut s| {
            s.misrecognition_rate = s.gate.misrecognition_rate();
            s
        });
        let end = self.read_retrying(|m| m.now())?;
        report.instrument_time_s = (end - clock0).value();
        if !report.interrupted {
            self.store
                .finish_run(&options.run_id, RunStatus::Finished, unix(end))
                .map_err(Self::store_err)?;
        }
        tracing::info!(
            done = report.nodes_done,
            given_up = report.given_up.len(),
            instrument_time_s = report.instrument_time_s,
            "calibration run ends"
        );
        Ok(report)
    }

    /// Surveys the lattice at the plan's places (see [`crate::survey`]): frames of
    /// `survey.size_lattice` lattice constants at the aperture's sampling, recognised with
    /// the aperture's detection settings.
    fn survey_lattice(&mut self) -> Result<crate::survey::SurveyReport, RunError> {
        let _s = tracing::info_span!("survey").entered();
        let s = &self.config.standard;
        let a_counts = s.lattice_constant_nm / s.nominal_nm_per_count;
        let aperture = self.fos.aperture.raster;
        let side = self.config.survey.size_lattice * a_counts;
        let pixels = ((side / aperture.pixel_step_counts).ceil() as u32 + 1).clamp(16, 1024);
        let raster = Raster { pixels, ..aperture };
        let caps = self.microscope.capabilities();
        let places = crate::survey::places(
            &self.plan,
            self.config.survey.places_per_side,
            0.5 * raster.side_counts(),
            (caps.field_min, caps.field_max),
        );
        let mut report = crate::survey::SurveyReport::default();
        for centre in places {
            let place = crate::survey::survey_place(
                &mut *self.microscope,
                centre,
                &raster,
                &self.fos.aperture.detection,
                &self.config,
            )
            .map_err(|e| RunError::Instrument {
                kind: e.kind(),
                message: e.to_string(),
            })?;
            match (&place.lcc, &place.refusal) {
                (Some(l), _) => tracing::info!(
                    x = centre.x.value(),
                    y = centre.y.value(),
                    features = place.features,
                    kx = l.kx_nm_per_count,
                    ky = l.ky_nm_per_count,
                    alpha = l.alpha_rad,
                    "lattice surveyed"
                ),
                (None, reason) => tracing::warn!(
                    x = centre.x.value(),
                    y = centre.y.value(),
                    features = place.features,
                    reason = reason.as_deref().unwrap_or(""),
                    "survey found no lattice; the place gates nothing"
                ),
            }
            report.places.push(place);
        }
        crate::survey::refuse_outliers(
            &mut report.places,
            self.fos.aperture.lcs.length_tolerance,
            self.fos.aperture.lcs.angle_tolerance_rad,
        );
        for p in report.places.iter().filter(|p| p.lcc.is_none()) {
            if let Some(reason) = p.refusal.as_deref().filter(|r| r.starts_with("an outlier")) {
                tracing::warn!(
                    x = p.centre_counts[0],
                    y = p.centre_counts[1],
                    reason,
                    "survey place refused; it gates nothing"
                );
            }
        }
        report.field = report.field_lcc();
        if report.places.iter().all(|p| p.lcc.is_none()) {
            tracing::warn!("the survey found no lattice anywhere: LCS recognition runs ungated");
        }
        Ok(report)
    }

    /// A read of the instrument's state, retried on transient errors up to the plan's
    /// `failures.transient_retries_per_node`; a permanent error or too many transient ones
    /// fail the run (it stays resumable).
    fn read_retrying<T>(
        &mut self,
        mut read: impl FnMut(&mut M) -> Result<T, M::Error>,
    ) -> Result<T, RunError> {
        let mut attempts = 0;
        loop {
            match read(&mut *self.microscope) {
                Ok(v) => return Ok(v),
                Err(e)
                    if e.kind().is_transient()
                        && attempts < self.config.failures.transient_retries_per_node =>
                {
                    attempts += 1;
                    tracing::warn!(error = %e, attempts, "instrument read failed; retrying");
                }
                Err(e) => {
                    return Err(RunError::Instrument {
                        kind: e.kind(),
                        message: e.to_string(),
                    });
                }
            }
        }
    }

    /// Runs one visit's node machine to its end and stores the result.
    #[allow(clippy::too_many_arguments)]
    fn run_visit(
        &mut self,
        visit: &PlanVisit,
        params: &MachineParams,
        pause: Seconds,
        coarse_now: &mut Option<i64>,
        run_id: &str,
        clock: RunClock,
        report: &mut RunReport,
    ) -> Result<(), RunError> {
        let node_span = tracing::info_span!(
            "node",
            repeat = visit.repeat_index,
            node = visit.node_index,
            x = visit.grid.x_counts,
            y = visit.grid.y_counts,
            z = visit.grid.z_counts
        );
        let _node = node_span.enter();
        let mut machine = NodeMachine::new(*visit, params.clone(), pause);
        let mut event = Event::Begin;
        loop {
            event = match machine.step(event) {
                Action::Finished(measurement) => {
                    self.commit_measured(visit, &measurement, run_id, clock, report)?;
                    break;
                }
                Action::GiveUp(reason) => {
                    let attempts = machine.attempt();
                    report.cycles = add(report.cycles, machine.cycles());
                    self.commit_given_up(visit, reason, attempts, run_id, clock, report)?;
                    break;
                }
                other => {
                    if let Action::MoveAndPause { .. } = other {
                        self.observer.node_started(visit, machine.attempt());
                    }
                    self.execute(visit, other, coarse_now)?
                }
            };
        }
        report.transient_errors += machine.transient_errors();
        Ok(())
    }

    /// Stores a measured visit (one transaction) and lets the next node rank its LCS
    /// candidates through this node's calibration. The LCS level and the time are read from
    /// the instrument; when those reads fail past the transient retries, the visit is given
    /// up rather than stored with a guessed date.
    fn commit_measured(
        &mut self,
        visit: &PlanVisit,
        measurement: &NodeMeasurement,
        run_id: &str,
        clock: RunClock,
        report: &mut RunReport,
    ) -> Result<(), RunError> {
        let read = self
            .read_retrying(|m| m.z_position())
            .and_then(|z| Ok((z, self.read_retrying(|m| m.now())?)));
        let (z, now) = match read {
            Ok(read) => read,
            Err(RunError::Instrument { kind, message }) if kind.is_transient() => {
                let reason = GiveUpReason::TransientErrors {
                    count: self.config.failures.transient_retries_per_node + 1,
                    kind: Some(kind),
                    message: format!(
                        "reading the LCS level and time after the measurement: {message}"
                    ),
                };
                report.cycles = add(report.cycles, measurement.cycles);
                return self.commit_given_up(
                    visit,
                    reason,
                    measurement.attempts,
                    run_id,
                    clock,
                    report,
                );
            }
            Err(e) => return Err(e),
        };
        let at_unix_s = clock.unix(now);
        let mut record = self.record(run_id, measurement, z.value(), at_unix_s);
        // Vertical axis (issue 15): the LCS's level and Kz from a nearby step.
        if let Some(search) = crate::vertical::at_node(self.microscope, &self.config, &mut record) {
            report.kz.count(&search);
            self.observer.kz_searched(visit, &search);
        }
        let done = NodeDone {
            repeat_index: visit.repeat_index,
            node_index: visit.node_index,
            attempts: measurement.attempts,
            finished_unix_s: at_unix_s,
        };
        self.store
            .commit_node(run_id, &done, &[record])
            .map_err(Self::store_err)?;
        report.nodes_done += 1;
        report.records += 1;
        report.cycles = add(report.cycles, measurement.cycles);
        tracing::info!(
            kx = measurement.lcc.kx.value(),
            ky = measurement.lcc.ky.value(),
            alpha = measurement.lcc.alpha.value(),
            "node measured"
        );
        self.fos.aperture.lcs.prior = Some(measurement.lcc.matrix());
        self.observer.node_finished(measurement);
        Ok(())
    }

    /// Marks a visit given up with its reason.
    fn commit_given_up(
        &mut self,
        visit: &PlanVisit,
        reason: GiveUpReason,
        attempts: u32,
        run_id: &str,
        clock: RunClock,
        report: &mut RunReport,
    ) -> Result<(), RunError> {
        let now = self.read_retrying(|m| m.now())?;
        self.store
            .give_up_node(
                run_id,
                &NodeDone {
                    repeat_index: visit.repeat_index,
                    node_index: visit.node_index,
                    attempts,
                    finished_unix_s: clock.unix(now),
                },
                &reason.to_string(),
            )
            .map_err(Self::store_err)?;
        tracing::warn!(%reason, "node given up");
        self.observer.node_given_up(visit, &reason);
        report.given_up.push(GivenUpVisit {
            repeat_index: visit.repeat_index,
            node_index: visit.node_index,
            node: [
                visit.grid.x_counts,
                visit.grid.y_counts,
                visit.grid.z_counts,
            ],
            reason,
        });
        Ok(())
    }

    fn record(&self, run_id: &str, m: &NodeMeasurement, z: f64, at_unix_s: f64) -> LccRecord {
        let matrix = m.lcc.matrix().rows();
        let (vx, vy) = (m.drift.x_counts_per_s, m.drift.y_counts_per_s);
        let finite = |v: f64| if v.is_finite() { v } else { 0.0 };
        LccRecord {
            scanner_id: self.config.scanner_id.clone(),
            run_id: run_id.to_owned(),
            acquired_unix_s: at_unix_s,
            repeat_index: m.visit.repeat_index,
            node_index: m.visit.node_index,
            lcs_index: 0,
            node_x_counts: m.visit.grid.x_counts,
            node_y_counts: m.visit.grid.y_counts,
            node_z_counts: m.visit.grid.z_counts,
            lcs_x_counts: m.centre.x.value(),
            lcs_y_counts: m.centre.y.value(),
            lcs_z_counts: if z.is_finite() {
                z
            } else {
                m.visit.grid.z_counts as f64
            },
            kx_nm_per_count: m.lcc.kx.value(),
            ky_nm_per_count: m.lcc.ky.value(),
            alpha_rad: m.lcc.alpha.value(),
            kz_nm_per_count: None,
            u_kx_nm_per_count: Some(m.lcc.u_kx().value()),
            u_ky_nm_per_count: Some(m.lcc.u_ky().value()),
            u_alpha_rad: Some(m.lcc.u_alpha().value()),
            u_kz_nm_per_count: None,
            // Drift in nm/s through the local metric (scanner-aligned frame).
            drift_vx_nm_per_s: finite(matrix[0][0] * vx + matrix[0][1] * vy),
            drift_vy_nm_per_s: finite(matrix[1][1] * vy),
            cycles_kept: m.cycles.kept,
            cycles_discarded: m.cycles.discarded,
            quality: m.quality(),
            kz_x_counts: None,
            kz_y_counts: None,
        }
    }

    /// Executes one action and returns the event that ends it.
    fn execute(
        &mut self,
        visit: &PlanVisit,
        action: Action,
        coarse_now: &mut Option<i64>,
    ) -> Result<Event, RunError> {
        match action {
            Action::MoveAndPause { node, pause } => self.move_and_pause(node, pause, coarse_now),
            Action::Attach { near } => self.attach(visit, near),
            Action::Aperture { centre } => self.aperture(centre),
            Action::Skip {
                index,
                from,
                estimate,
                drift,
            } => self.skip(visit, index, from, estimate, drift),
            Action::CounterScan { centre, drift } => self.counter_scan(visit, centre, drift),
            Action::Finished(_) | Action::GiveUp(_) => Err(RunError::Unsupported(
                "a terminal step of the node machine as an instrument action",
            )),
        }
    }

    /// Moves the coarse stage (when the node sets a level) and the scanner to the node, and
    /// pauses.
    fn move_and_pause(
        &mut self,
        node: GridNode,
        pause: Seconds,
        coarse_now: &mut Option<i64>,
    ) -> Result<Event, RunError> {
        let _s = tracing::debug_span!("pause", pause_s = pause.value()).entered();
        let mic = &mut *self.microscope;
        if let Some(target) = node.coarse_steps {
            let Some(stage) = mic.coarse_z() else {
                return Err(RunError::Unsupported(
                    "coarse-stage positions (the instrument has no coarse stage)",
                ));
            };
            let from = match *coarse_now {
                Some(c) => c,
                None => match stage.position_steps() {
                    Ok(p) => p,
                    Err(e) => return instrument(e).map(Event::Failed),
                },
            };
            if target != from
                && let Err(e) = stage.step(target - from)
            {
                // Where the stage ended is unknown: read it again next time.
                *coarse_now = None;
                return instrument(e).map(Event::Failed);
            }
            *coarse_now = Some(target);
        }
        let request = spm_hal::MoveRequest {
            target: node.position(),
            speed: spm_hal::CountsPerSecond(self.config.motion.move_speed_counts_per_s),
            settle: Seconds(self.config.motion.settle_s),
        };
        if let Err(e) = mic.move_to(request) {
            return instrument(e).map(Event::Failed);
        }
        if let Err(e) = mic.wait(pause) {
            return instrument(e).map(Event::Failed);
        }
        Ok(Event::Paused)
    }

    /// Attaches to the feature nearest `near` and waits for the drift to settle.
    fn attach(&mut self, visit: &PlanVisit, near: CountPoint) -> Result<Event, RunError> {
        let _s = tracing::debug_span!("attach").entered();
        let r = match spm_fos::attach(&mut *self.microscope, near, &self.fos.attach) {
            Ok(r) => r,
            Err(e) => return Ok(Event::Failed(fos_failure(e)?)),
        };
        self.observer.attach_sightings(visit, &r.history);
        if let Some(last_t) = r.history.last().map(spm_fos::Sighting::time) {
            for v in &r.velocities {
                self.observer.drift_estimate(visit, *v, last_t);
            }
        }
        Ok(Event::Attached(match r.outcome {
            AttachOutcome::Settled { velocity } => match r.feature {
                Some(f) => AttachResult::Settled {
                    feature: Anchor {
                        position: f.position,
                        time: Some(f.time),
                    },
                    drift: velocity,
                },
                None => AttachResult::FeatureLost,
            },
            AttachOutcome::TimedOut { velocity } => {
                AttachResult::DriftNotSettled { drift: velocity }
            }
            AttachOutcome::FeatureLost { .. } => AttachResult::FeatureLost,
        }))
    }

    /// Scans the aperture around `centre` (the captured feature, or the node for Fig. 3b)
    /// and recognises the LCS.
    fn aperture(&mut self, centre: Anchor) -> Result<Event, RunError> {
        let _s = tracing::debug_span!("aperture").entered();
        let r = match spm_fos::aperture(&mut *self.microscope, centre.position, &self.fos.aperture)
        {
            Ok(r) => r,
            Err(e) => return Ok(Event::Failed(fos_failure(e)?)),
        };
        if self.fos.aperture.lcs.gate.is_some()
            && let Some(survey) = self.survey.as_mut()
        {
            survey.gate.count(&r);
        }
        let Some(a) = r.a.and_then(|i| r.feature(i)).copied() else {
            return Ok(Event::ApertureScanned(ApertureResult {
                a: centre,
                lcs: None,
                neighbours: Vec::new(),
                features: Vec::new(),
            }));
        };
        let neighbours = r
            .neighbours
            .iter()
            .filter_map(|&i| r.feature(i))
            .map(|f| f.position - a.position)
            .collect();
        let features = r
            .recognised
            .detection
            .features
            .iter()
            .enumerate()
            .filter(|(i, _)| Some(*i) != r.a)
            .map(|(_, f)| f.position - a.position)
            .collect();
        Ok(Event::ApertureScanned(ApertureResult {
            a: Anchor {
                position: a.position,
                time: Some(a.time),
            },
            lcs: r.lcs.map(|l| (l.ab, l.ac)),
            neighbours,
            features,
        }))
    }

    /// Measures one vector drift-free by skipping from `from` to the feature `estimate`
    /// away and back.
    fn skip(
        &mut self,
        visit: &PlanVisit,
        index: usize,
        from: Anchor,
        estimate: CountVector,
        drift: CountVelocity,
    ) -> Result<Event, RunError> {
        let _s = tracing::debug_span!("skip", vector = index).entered();
        // fos predicts the start feature at its next scan from its sighting and the drift;
        // a place never seen is taken as seen now.
        let seen = match from.time {
            Some(t) => t,
            None => match self.microscope.now() {
                Ok(t) => t,
                Err(e) => return instrument(e).map(Event::Failed),
            },
        };
        let r = match spm_fos::skip(
            &mut *self.microscope,
            from.position,
            seen,
            estimate,
            drift,
            &self.fos.skip,
        ) {
            Ok(r) => r,
            Err(e) => return Ok(Event::Failed(fos_failure(e)?)),
        };
        for c in &r.cycles {
            if let Decision::Discard(reason) = c.decision {
                self.observer.cycle_spoiled(visit, &reason);
            }
            if c.cycle.velocity.norm_counts_per_s().is_finite() {
                self.observer
                    .drift_estimate(visit, c.cycle.velocity, c.cycle.a_end.time());
            }
        }
        let cycles = CycleCounts {
            kept: r.kept.len() as u32,
            discarded: r.discarded as u32,
            idle: r.idle as u32,
            restarts: r.restarts as u32,
        };
        Ok(Event::Skipped(match (r.outcome, r.vector) {
            (SkipOutcome::Completed, Some(vector)) => SkipResult::Completed {
                vector,
                covariance: crate::measure::skip_vector_covariance(&r),
                a: Anchor {
                    position: r.a.position(),
                    time: Some(r.a.time()),
                },
                drift: r.drift,
                cycles,
            },
            _ => SkipResult::Unstable { cycles },
        }))
    }

    /// Measures all vectors at once by counter-scanning the aperture around `centre`.
    fn counter_scan(
        &mut self,
        visit: &PlanVisit,
        centre: Anchor,
        drift: CountVelocity,
    ) -> Result<Event, RunError> {
        let _s = tracing::debug_span!("counter_scan").entered();
        let mut params = self.fos.counter.clone();
        params.drift_prior = drift;
        let now = match self.microscope.now() {
            Ok(t) => t,
            Err(e) => return instrument(e).map(Event::Failed),
        };
        let target = centre.predict(drift, now);
        let r = match spm_fos::counter_scan(&mut *self.microscope, target, &params) {
            Ok(r) => r,
            Err(e) => return Ok(Event::Failed(fos_failure(e)?)),
        };
        self.observer
            .drift_estimate(visit, r.velocity, r.reference_time);
        Ok(match crate::measure::counter_scan_vectors(&r, target) {
            Some(result) => Event::CounterScanned(result),
            None => Event::Failed(Failure::Measurement {
                message: "counter-scan found no common feature".into(),
            }),
        })
    }
}

fn add(mut a: CycleCounts, b: CycleCounts) -> CycleCounts {
    a.kept += b.kept;
    a.discarded += b.discarded;
    a.idle += b.idle;
    a.restarts += b.restarts;
    a
}
