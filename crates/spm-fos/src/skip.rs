//! Skipping A↔B (paper §2.1.3): drift-insensitive measurement of the vector
//! between two neighbouring features, watched by the drift monitor (§2.6).

use crate::acquire::{Motion, Raster, Sighting, track};
use crate::error::{FosError, positive};
use crate::monitor::{CycleKind, Decision, DriftMonitor, MonitorParams};
use serde::{Deserialize, Serialize};
use spm_features::DetectionConfig;
use spm_hal::{CountPoint, CountVector, CountVelocity, Microscope, Seconds};

/// Settings of [`skip`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SkipParams {
    /// The segment raster (about one feature).
    pub segment: Raster,
    /// Recognition settings for segments.
    pub detection: DetectionConfig,
    /// Probe moves.
    pub motion: Motion,
    /// Drift monitor; `required_cycles` is the number n of kept cycles.
    pub monitor: MonitorParams,
    /// Largest number of cycles in all (kept, spoiled and idle).
    pub max_cycles: usize,
    /// A feature farther than this fraction of the segment's side from its
    /// predicted position is lost. Default 0.4.
    pub capture_radius_fraction: f64,
}

impl SkipParams {
    /// Defaults around a segment and a monitor.
    pub fn new(segment: Raster, monitor: MonitorParams) -> Self {
        Self {
            segment,
            detection: DetectionConfig::default(),
            motion: Motion::TYPICAL,
            max_cycles: 4 * monitor.required_cycles.max(1) + 8,
            monitor,
            capture_radius_fraction: 0.4,
        }
    }

    fn validate<E: spm_hal::Error>(&self) -> Result<(), FosError<E>> {
        self.segment.validate()?;
        self.motion.validate()?;
        positive("capture_radius_fraction", self.capture_radius_fraction)?;
        positive(
            "monitor.velocity_tolerance_counts_per_s",
            self.monitor.velocity_tolerance_counts_per_s,
        )?;
        positive(
            "monitor.max_speed_counts_per_s",
            self.monitor.max_speed_counts_per_s,
        )?;
        if self.monitor.required_cycles == 0 || self.max_cycles < self.monitor.required_cycles {
            return Err(FosError::InvalidParameter {
                field: "max_cycles",
                reason: "need required_cycles ≥ 1 and max_cycles ≥ required_cycles",
            });
        }
        Ok(())
    }

    fn capture_radius_counts(&self) -> f64 {
        self.capture_radius_fraction * self.segment.side_counts()
    }
}

/// The raw measurement of one cycle A → B → A.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SkipCycle {
    /// Measuring or idle.
    pub kind: CycleKind,
    /// A at the start of the cycle.
    pub a_start: Sighting,
    /// B.
    pub b: Sighting,
    /// A at the end of the cycle.
    pub a_end: Sighting,
    /// Forward difference B − A(start), counts.
    pub forward: CountVector,
    /// Backward difference B − A(end), counts.
    pub backward: CountVector,
    /// Half-sum of the forward and backward differences, counts.
    pub half_sum: CountVector,
    /// B − A interpolated to B's time from the two A sightings: the half-sum
    /// with weights from the actual feature times (equal to the half-sum when
    /// B is seen exactly midway between the A sightings). Cancels any constant
    /// drift. Counts.
    pub vector: CountVector,
    /// Drift velocity over the cycle from the two A sightings, counts per second.
    pub velocity: CountVelocity,
}

/// A cycle with the monitor's verdict.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct JudgedCycle {
    /// The measurement.
    pub cycle: SkipCycle,
    /// The monitor's decision on it.
    pub decision: Decision,
}

/// How a skipping run ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SkipOutcome {
    /// The required number of cycles was kept.
    Completed,
    /// The monitor gave up (long-term drift instability).
    GaveUp,
    /// The cycle budget ran out first.
    BudgetExhausted,
}

/// The result of [`skip`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SkipReport {
    /// How it ended.
    pub outcome: SkipOutcome,
    /// Mean drift-free A→B over the kept cycles (None when none was kept).
    pub vector: Option<CountVector>,
    /// Mean plain half-sum over the kept cycles.
    pub half_sum: Option<CountVector>,
    /// Standard error of `vector` per component (zero with one kept cycle).
    pub sigma: CountVector,
    /// Every cycle run, with its verdict.
    pub cycles: Vec<JudgedCycle>,
    /// Indices into `cycles` of the kept ones (after the last restart).
    pub kept: Vec<usize>,
    /// Spoiled cycles.
    pub discarded: usize,
    /// Idle cycles.
    pub idle: usize,
    /// Restarts.
    pub restarts: usize,
    /// The last sighting of A.
    pub a: Sighting,
    /// The last drift velocity estimate, counts per second.
    pub drift: CountVelocity,
}

/// The state carried from cycle to cycle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SkipState {
    /// The last sighting of A.
    pub a: Sighting,
    /// The current estimate of A→B, counts (aims the move to B).
    pub ab: CountVector,
    /// The current drift estimate, counts per second.
    pub drift: CountVelocity,
}

/// Runs one cycle A → B → A from `state` and advances `state` (A's last
/// sighting and the drift). The A→B estimate is left to the caller.
pub fn skip_cycle<M: Microscope>(
    microscope: &mut M,
    state: &mut SkipState,
    kind: CycleKind,
    params: &SkipParams,
) -> Result<SkipCycle, FosError<M::Error>> {
    let radius = params.capture_radius_counts();
    let a_start = state.a;
    let b_expected: CountPoint = a_start.position() + state.ab;
    let b = track(
        microscope,
        b_expected,
        a_start.time(),
        state.drift,
        &params.segment,
        &params.motion,
        &params.detection,
        radius,
    )?;
    let a_end = track(
        microscope,
        a_start.position(),
        a_start.time(),
        state.drift,
        &params.segment,
        &params.motion,
        &params.detection,
        radius,
    )?;
    let forward = b.position() - a_start.position();
    let backward = b.position() - a_end.position();
    let half_sum = (forward + backward) * 0.5;
    let span: Seconds = a_end.time() - a_start.time();
    let a_move = a_end.position() - a_start.position();
    let (vector, velocity) = if span.value() > 0.0 {
        let w = (b.time() - a_start.time()) / span;
        (forward - a_move * w, a_move.per(span))
    } else {
        (
            half_sum,
            CountVelocity {
                x_counts_per_s: f64::NAN,
                y_counts_per_s: f64::NAN,
            },
        )
    };
    state.a = a_end;
    if velocity.norm_counts_per_s().is_finite() {
        state.drift = velocity;
    }
    tracing::debug!(
        ?kind,
        ab_x = vector.x.value(),
        ab_y = vector.y.value(),
        vx = velocity.x_counts_per_s,
        vy = velocity.y_counts_per_s,
        "skipping cycle"
    );
    Ok(SkipCycle {
        kind,
        a_start,
        b,
        a_end,
        forward,
        backward,
        half_sum,
        vector,
        velocity,
    })
}

fn mean(vectors: &[CountVector]) -> Option<CountVector> {
    if vectors.is_empty() {
        return None;
    }
    let n = vectors.len() as f64;
    let sum = vectors
        .iter()
        .fold(CountVector::default(), |acc, v| acc + *v);
    Some(sum * (1.0 / n))
}

/// Skips between A (seen at `a` at time `a_time`) and B ≈ A + `ab_estimate`
/// until the monitor has kept `required_cycles` cycles, gives up, or
/// `max_cycles` pass. A is first re-acquired in a segment (predicted with
/// `drift`). The drift estimate starts at `drift` (e.g. from the attachment)
/// and follows each cycle; the A→B estimate follows the kept cycles.
pub fn skip<M: Microscope>(
    microscope: &mut M,
    a: CountPoint,
    a_time: Seconds,
    ab_estimate: CountVector,
    drift: CountVelocity,
    params: &SkipParams,
) -> Result<SkipReport, FosError<M::Error>> {
    params.validate()?;
    let first_a = track(
        microscope,
        a,
        a_time,
        drift,
        &params.segment,
        &params.motion,
        &params.detection,
        params.capture_radius_counts(),
    )?;
    let mut state = SkipState {
        a: first_a,
        ab: ab_estimate,
        drift,
    };
    let mut monitor = DriftMonitor::new(params.monitor, Some(drift));
    let mut cycles: Vec<JudgedCycle> = Vec::new();
    let mut kept: Vec<usize> = Vec::new();
    let mut outcome = SkipOutcome::BudgetExhausted;
    for _ in 0..params.max_cycles {
        let kind = monitor.next_cycle();
        let cycle = skip_cycle(microscope, &mut state, kind, params)?;
        let decision = monitor.observe(cycle.velocity);
        match decision {
            Decision::Keep | Decision::Done => {
                kept.push(cycles.len());
                let vectors: Vec<CountVector> = kept
                    .iter()
                    .filter_map(|&i| cycles.get(i).map(|c| c.cycle.vector))
                    .chain(std::iter::once(cycle.vector))
                    .collect();
                if let Some(m) = mean(&vectors) {
                    state.ab = m;
                }
            }
            Decision::Restart => {
                tracing::info!("drift did not recover: skipping restarts");
                kept.clear();
            }
            Decision::Discard(reason) => {
                tracing::info!(?reason, "skipping cycle spoiled and discarded");
            }
            Decision::Idle { .. } | Decision::Resume | Decision::GiveUp => {}
        }
        cycles.push(JudgedCycle { cycle, decision });
        if decision == Decision::Done {
            outcome = SkipOutcome::Completed;
            break;
        }
        if decision == Decision::GiveUp {
            tracing::warn!("long-term drift instability: skipping gives up");
            outcome = SkipOutcome::GaveUp;
            kept.clear();
            break;
        }
    }
    let vectors: Vec<CountVector> = kept
        .iter()
        .filter_map(|&i| cycles.get(i).map(|c| c.cycle.vector))
        .collect();
    let half_sums: Vec<CountVector> = kept
        .iter()
        .filter_map(|&i| cycles.get(i).map(|c| c.cycle.half_sum))
        .collect();
    let vector = mean(&vectors);
    let sigma = match (vector, vectors.len()) {
        (Some(m), n) if n > 1 => {
            let nf = n as f64;
            let (sx, sy) = vectors.iter().fold((0.0, 0.0), |acc, v| {
                (
                    acc.0 + (v.x - m.x).value().powi(2),
                    acc.1 + (v.y - m.y).value().powi(2),
                )
            });
            CountVector::from_counts((sx / (nf - 1.0) / nf).sqrt(), (sy / (nf - 1.0) / nf).sqrt())
        }
        _ => CountVector::default(),
    };
    Ok(SkipReport {
        outcome,
        vector,
        half_sum: mean(&half_sums),
        sigma,
        cycles,
        kept,
        discarded: monitor.discarded(),
        idle: monitor.idle_cycles(),
        restarts: monitor.restarts(),
        a: state.a,
        drift: state.drift,
    })
}
