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

use crate::config::{FeaturePolarity, PlanConfig};
use crate::lcc::CountCovariance;
use crate::machine::{
    Action, Anchor, ApertureResult, AttachResult, CounterResult, CycleCounts, Event, Failure,
    GiveUpReason, MachineParams, NodeMachine, NodeMeasurement, SkipResult, vector_covariance,
};
use crate::plan::{GridNode, NetPlan, PlanError, PlanVisit};
use serde::{Deserialize, Serialize};
use spm_features::{DetectionConfig, LcsConfig, LcsStandard, Polarity};
use spm_fos::{
    ApertureParams, AttachOutcome, AttachParams, CounterScanParams, Decision, FosError,
    MonitorParams, Motion, Raster, SkipOutcome, SkipParams, SpoilReason,
};
use spm_hal::{
    CountVector, CountVelocity, Counts, Error as _, ErrorKind, Microscope, Nanometres, Seconds,
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
    #[error("invalid operation parameters: {0}")]
    Parameters(String),
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
    /// segment (a feature must not drift more than 0.4 segment over one cycle).
    pub fn from_plan(plan: &PlanConfig) -> Self {
        let s = &plan.standard;
        let dwell = plan.motion.pixel_dwell_s;
        let motion = Motion {
            speed_counts_per_s: plan.motion.move_speed_counts_per_s,
            settle_s: plan.motion.settle_s,
        };
        let spacing_counts = s.lattice_constant_nm / s.nominal_nm_per_count;
        let polarity = match s.feature {
            FeaturePolarity::Hills => Polarity::Hill,
            FeaturePolarity::Pits => Polarity::Pit,
        };
        let detection = |r: &Raster| DetectionConfig {
            polarity,
            min_separation_px: (0.5 * spacing_counts / r.pixel_step_counts).max(1.5),
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
        let mut attach = AttachParams::new(first, segment, speed_limit, timeout_s);
        attach.first_detection = detection(&first);
        attach.segment_detection = detection(&segment);
        attach.motion = motion;
        let cycle_s = 2.0 * track_s;
        let monitor = MonitorParams {
            velocity_tolerance_counts_per_s: to_counts(plan.drift.max_change_nm_per_s),
            max_speed_counts_per_s: (0.4 * segment.side_counts() / cycle_s).max(speed_limit),
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
            nominal_nm_per_count: s.nominal_nm_per_count,
            length_tolerance: s.length_tolerance_fraction,
            angle_tolerance_rad: s.angle_tolerance_deg.to_radians(),
            prior_nm_per_count: None,
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
                match_radius_counts: 0.35 * spacing_counts,
                drift_prior: CountVelocity::ZERO,
            },
        }
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
        FosError::InvalidParameter { .. } | FosError::Unsupported(_) => {
            Err(RunError::Parameters(error.to_string()))
        }
        other => Ok(Failure::Measurement {
            message: other.to_string(),
        }),
    }
}

fn instrument<E: spm_hal::Error>(e: E) -> Failure {
    let kind = e.kind();
    if kind.is_transient() {
        Failure::Transient {
            kind: Some(kind),
            message: e.to_string(),
        }
    } else {
        Failure::Permanent {
            kind,
            message: e.to_string(),
        }
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
                RunError::Instrument { .. } | RunError::Parameters(_) => Some(RunStatus::Failed),
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
        let params = MachineParams::from_plan(&self.config);
        let mut previous: Option<GridNode> = None;
        let mut coarse_now: Option<i64> = None;
        for visit in visits.iter().filter(|v| !finished(v)) {
            if !self.observer.keep_going() {
                report.interrupted = true;
                tracing::info!("run interrupted by the observer");
                break;
            }
            let here = self.microscope.position().unwrap_or(visit.grid.position());
            let lateral = previous.map_or_else(
                || here.distance(visit.grid.position()),
                |p| p.position().distance(visit.grid.position()),
            );
            let coarse_delta = match (coarse_now, visit.grid.coarse_steps) {
                (Some(a), Some(b)) => b - a,
                _ => 0,
            };
            let pause = self.config.pause.pause(lateral, coarse_delta);
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
                let action = machine.step(event);
                event = match action {
                    Action::Finished(measurement) => {
                        let z = self.microscope.z_position().map_or(f64::NAN, |z| z.value());
                        let now = self.microscope.now().unwrap_or(clock0);
                        let mut record = self.record(&options.run_id, &measurement, z, unix(now));
                        // Vertical axis (issue 15): the LCS's level and Kz from a nearby step.
                        if let Some(search) =
                            crate::vertical::at_node(self.microscope, &self.config, &mut record)
                        {
                            report.kz.count(&search);
                            self.observer.kz_searched(visit, &search);
                        }
                        let done = NodeDone {
                            repeat_index: visit.repeat_index,
                            node_index: visit.node_index,
                            attempts: measurement.attempts,
                            finished_unix_s: unix(now),
                        };
                        self.store
                            .commit_node(&options.run_id, &done, &[record])
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
                        // The next node (a net step away) ranks its LCS candidates through
                        // this node's calibration rather than the nominal sensitivity.
                        let (sin, cos) = measurement.lcc.alpha.value().sin_cos();
                        let (kx, ky) = (measurement.lcc.kx.value(), measurement.lcc.ky.value());
                        self.fos.aperture.lcs.prior_nm_per_count =
                            Some([[kx, ky * sin], [0.0, ky * cos]]);
                        self.observer.node_finished(&measurement);
                        break;
                    }
                    Action::GiveUp(reason) => {
                        let now = self.microscope.now().unwrap_or(clock0);
                        self.store
                            .give_up_node(
                                &options.run_id,
                                &NodeDone {
                                    repeat_index: visit.repeat_index,
                                    node_index: visit.node_index,
                                    attempts: machine.attempt(),
                                    finished_unix_s: unix(now),
                                },
                                &reason.to_string(),
                            )
                            .map_err(Self::store_err)?;
                        report.cycles = add(report.cycles, machine.cycles());
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
                        break;
                    }
                    other => {
                        if let Action::MoveAndPause { .. } = other {
                            self.observer.node_started(visit, machine.attempt());
                        }
                        self.execute(visit, other, &mut coarse_now)?
                    }
                };
            }
            report.transient_errors += machine.transient_errors();
            previous = Some(visit.grid);
        }
        let end = self.microscope.now().unwrap_or(clock0);
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

    fn record(&self, run_id: &str, m: &NodeMeasurement, z: f64, at_unix_s: f64) -> LccRecord {
        let matrix = m.lcc.matrix();
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
        let mic = &mut *self.microscope;
        match action {
            Action::MoveAndPause { node, pause } => {
                let _s = tracing::debug_span!("pause", pause_s = pause.value()).entered();
                if let Some(target) = node.coarse_steps {
                    let current = *coarse_now;
                    let Some(stage) = mic.coarse_z() else {
                        return Err(RunError::Parameters(
                            "the plan sets coarse-stage positions but the instrument has no coarse stage".into(),
                        ));
                    };
                    let from = match current {
                        Some(c) => c,
                        None => match stage.position_steps() {
                            Ok(p) => p,
                            Err(e) => return Ok(Event::Failed(instrument(e))),
                        },
                    };
                    if target != from
                        && let Err(e) = stage.step(target - from)
                    {
                        return Ok(Event::Failed(instrument(e)));
                    }
                    *coarse_now = Some(target);
                }
                let request = spm_hal::MoveRequest {
                    target: node.position(),
                    speed_counts_per_s: self.config.motion.move_speed_counts_per_s,
                    settle: Seconds(self.config.motion.settle_s),
                };
                if let Err(e) = mic.move_to(request) {
                    return Ok(Event::Failed(instrument(e)));
                }
                if let Err(e) = mic.wait(pause) {
                    return Ok(Event::Failed(instrument(e)));
                }
                Ok(Event::Paused)
            }
            Action::Attach { near } => {
                let _s = tracing::debug_span!("attach").entered();
                match spm_fos::attach(mic, near, &self.fos.attach) {
                    Ok(r) => {
                        self.observer.attach_sightings(visit, &r.history);
                        let last_t = r.history.last().map(|s| s.time());
                        for v in &r.velocities {
                            self.observer.drift_estimate(
                                visit,
                                *v,
                                last_t.unwrap_or(Seconds::ZERO),
                            );
                        }
                        Ok(Event::Attached(match r.outcome {
                            AttachOutcome::Settled { velocity } => match r.feature {
                                Some(f) => AttachResult::Settled {
                                    feature: Anchor {
                                        position: f.position,
                                        time: f.time,
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
                    Err(e) => Ok(Event::Failed(fos_failure(e)?)),
                }
            }
            Action::Aperture { centre } => {
                let _s = tracing::debug_span!("aperture").entered();
                // The captured feature (just attached: its drift is below the limit), or the
                // node for Fig. 3b.
                let target = centre.position;
                match spm_fos::aperture(mic, target, &self.fos.aperture) {
                    Ok(r) => {
                        let Some(a) = r.a.and_then(|i| r.feature(i)).copied() else {
                            return Ok(Event::ApertureScanned(ApertureResult {
                                a: centre,
                                lcs: None,
                                neighbours: Vec::new(),
                            }));
                        };
                        let neighbours = r
                            .neighbours
                            .iter()
                            .filter_map(|&i| r.feature(i))
                            .map(|f| f.position - a.position)
                            .collect();
                        Ok(Event::ApertureScanned(ApertureResult {
                            a: Anchor {
                                position: a.position,
                                time: a.time,
                            },
                            lcs: r.lcs.map(|l| (l.ab, l.ac)),
                            neighbours,
                        }))
                    }
                    Err(e) => Ok(Event::Failed(fos_failure(e)?)),
                }
            }
            Action::Skip {
                index,
                from,
                estimate,
                drift,
            } => {
                let _s = tracing::debug_span!("skip", vector = index).entered();
                // fos predicts A at its next scan from the sighting time and the drift.
                match spm_fos::skip(
                    mic,
                    from.position,
                    from.time,
                    estimate,
                    drift,
                    &self.fos.skip,
                ) {
                    Ok(r) => {
                        for c in &r.cycles {
                            if let Decision::Discard(reason) = c.decision {
                                self.observer.cycle_spoiled(visit, &reason);
                            }
                            if c.cycle.velocity.norm_counts_per_s().is_finite() {
                                self.observer.drift_estimate(
                                    visit,
                                    c.cycle.velocity,
                                    c.cycle.a_end.time(),
                                );
                            }
                        }
                        let cycles = CycleCounts {
                            kept: r.kept.len() as u32,
                            discarded: r.discarded as u32,
                            idle: r.idle as u32,
                            restarts: r.restarts as u32,
                        };
                        match (r.outcome, r.vector) {
                            (SkipOutcome::Completed, Some(vector)) => {
                                // Localisation uncertainty of one cycle's vector:
                                // σ_B² + ½(σ_A,start² + σ_A,end²) per component.
                                let (mut lx, mut ly, mut n) = (0.0, 0.0, 0usize);
                                for &i in &r.kept {
                                    if let Some(c) = r.cycles.get(i) {
                                        let u = |f: &spm_features::Feature| {
                                            (
                                                f.uncertainty.sigma_x.value().powi(2),
                                                f.uncertainty.sigma_y.value().powi(2),
                                            )
                                        };
                                        let (bx, by) = u(&c.cycle.b.feature);
                                        let (sx, sy) = u(&c.cycle.a_start.feature);
                                        let (ex, ey) = u(&c.cycle.a_end.feature);
                                        lx += bx + 0.5 * (sx + ex);
                                        ly += by + 0.5 * (sy + ey);
                                        n += 1;
                                    }
                                }
                                let n_f = n.max(1) as f64;
                                let local = CountVector::new(
                                    Counts((lx / n_f).sqrt()),
                                    Counts((ly / n_f).sqrt()),
                                );
                                let covariance: CountCovariance =
                                    vector_covariance(r.sigma, local, n);
                                Ok(Event::Skipped(SkipResult::Completed {
                                    vector,
                                    covariance,
                                    a: Anchor {
                                        position: r.a.position(),
                                        time: r.a.time(),
                                    },
                                    drift: r.drift,
                                    cycles,
                                }))
                            }
                            _ => Ok(Event::Skipped(SkipResult::Unstable { cycles })),
                        }
                    }
                    Err(e) => Ok(Event::Failed(fos_failure(e)?)),
                }
            }
            Action::CounterScan { centre, drift } => {
                let _s = tracing::debug_span!("counter_scan").entered();
                let mut params = self.fos.counter.clone();
                params.drift_prior = drift;
                let now = mic.now().unwrap_or(centre.time);
                let target = if centre.time.is_finite() {
                    centre.predict(drift, now)
                } else {
                    centre.position
                };
                match spm_fos::counter_scan(mic, target, &params) {
                    Ok(r) => {
                        self.observer
                            .drift_estimate(visit, r.velocity, r.reference_time);
                        let Some(a) = r.common.iter().min_by(|x, y| {
                            x.drift_free
                                .distance(target)
                                .value()
                                .total_cmp(&y.drift_free.distance(target).value())
                        }) else {
                            return Ok(Event::Failed(Failure::Measurement {
                                message: "counter-scan found no common feature".into(),
                            }));
                        };
                        let ua = a.direct.uncertainty;
                        let vectors = r
                            .common
                            .iter()
                            .filter(|c| c.drift_free != a.drift_free)
                            .map(|c| {
                                let u = c.direct.uncertainty;
                                (
                                    c.drift_free - a.drift_free,
                                    CountCovariance {
                                        xx_counts2: 0.5
                                            * (ua.sigma_x.value().powi(2)
                                                + u.sigma_x.value().powi(2)),
                                        xy_counts2: 0.0,
                                        yy_counts2: 0.5
                                            * (ua.sigma_y.value().powi(2)
                                                + u.sigma_y.value().powi(2)),
                                    },
                                )
                            })
                            .collect();
                        Ok(Event::CounterScanned(CounterResult {
                            a: Anchor {
                                position: a.drift_free,
                                time: r.reference_time,
                            },
                            vectors,
                            drift: r.velocity,
                        }))
                    }
                    Err(e) => Ok(Event::Failed(fos_failure(e)?)),
                }
            }
            Action::Finished(_) | Action::GiveUp(_) => Ok(Event::Failed(Failure::Measurement {
                message: "terminal action executed".into(),
            })),
        }
    }
}

fn add(mut a: CycleCounts, b: CycleCounts) -> CycleCounts {
    a.kept += b.kept;
    a.discarded += b.discarded;
    a.idle += b.idle;
    a.restarts += b.restarts;
    a
}
