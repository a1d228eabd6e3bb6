//! The node state machine of paper Fig. 2, as a pure step function.
//!
//! A [`NodeMachine`] measures one visit of one net node. Each call of [`NodeMachine::step`]
//! takes the [`Event`] that ended the previous [`Action`] and returns the next action:
//!
//! ```text
//! MoveAndPause → Attach → Aperture → Measure(vector 1) → … → Measure(vector n) → Finished
//!        ↑__________ restart (attempt + 1) on a failed stage ___________|
//!                                               GiveUp(reason) when the budgets run out
//! ```
//!
//! The cycle-level adaptivity of paper §2.6 (spoiled cycle → idle cycles → continue or
//! restart the skipping, or give up) is `spm_fos::DriftMonitor`'s, inside each measurement;
//! when it gives up (long-term instability) this machine returns the probe to the node and
//! redoes it (a new attempt), and after `max_attempts_per_node` attempts the node is given up
//! with a typed [`GiveUpReason`]. Transient backend errors restart the node as well, against
//! their own budget. The machine owns no microscope, clock, store or observer: the loop in
//! [`crate::runner`] executes the actions and owns termination, observers and checkpoints.

use crate::config::{AttachTarget, MeasurementMethod, NeighbourSet, PlanConfig};
use crate::lcc::{
    CountCovariance, LccEstimate, StandardVector, VectorObservation, solve_lcc, solve_lcc_rejecting,
};
use crate::plan::{GridNode, PlanVisit};
use serde::{Deserialize, Serialize};
use spm_hal::{CountPoint, CountVector, CountVelocity, Counts, ErrorKind, Radians, Seconds};

/// A node's vector (with every neighbour of A measured) is of another feature when its
/// length through the node's robust solution is this many robust standard deviations off
/// ([`crate::lcc::solve_lcc_rejecting`]).
pub const VECTOR_REJECTION_SIGMAS: f64 = 3.0;

/// Keeps the items of `items` whose indices are in `kept`, in order.
fn retain_indices<T>(items: &mut Vec<T>, kept: &[usize]) {
    let mut index = 0;
    items.retain(|_| {
        let keep = kept.contains(&index);
        index += 1;
        keep
    });
}

/// A feature position at a time (positions move with the drift).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Anchor {
    /// Position, counts.
    pub position: CountPoint,
    /// Instrument time of the sighting, seconds; `None` for a place that was never seen
    /// (the node itself, when the aperture around it stands in for the attachment).
    pub time: Option<Seconds>,
}

impl Anchor {
    /// The position expected at `t` with drift `v`.
    pub fn predict(&self, v: CountVelocity, t: Seconds) -> CountPoint {
        match self.time {
            Some(seen) => self.position + v.displacement(t - seen),
            None => self.position,
        }
    }
}

/// One vector to measure: from a feature (relative to A) to another.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct VectorTarget {
    /// Where the vector starts: at A, or (B↔C) at the end of another vector.
    pub start: VectorStart,
    /// Approximate vector from the start feature to the end feature, counts.
    pub estimate: CountVector,
    /// The true vector in the standard's frame, nm.
    pub standard: StandardVector,
}

/// Where a measured vector starts.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum VectorStart {
    /// At the feature A.
    AtA,
    /// At the end feature of the vector `index` of [`NodeMachine::targets`] (B↔C starts at
    /// B, the end of A→B): its measured value once known, else `estimate` from A.
    AtEndOf {
        /// Index of that vector.
        index: usize,
        /// Its approximate value, counts.
        estimate: CountVector,
    },
}

/// What the executor must do next.
#[derive(Clone, Debug, PartialEq)]
pub enum Action {
    /// Move to the node (and its coarse-stage level) and pause.
    MoveAndPause {
        /// The node.
        node: GridNode,
        /// The pause after the move.
        pause: Seconds,
    },
    /// Attach to the feature nearest `near` and wait for the drift to settle.
    Attach {
        /// Where to look, counts.
        near: CountPoint,
    },
    /// Scan the aperture around `centre` and recognise the LCS.
    Aperture {
        /// The aperture's centre (the captured feature, or the node for Fig. 3b).
        centre: Anchor,
    },
    /// Measure one vector drift-free by skipping.
    Skip {
        /// Index of the vector in [`NodeMachine::targets`].
        index: usize,
        /// The start feature.
        from: Anchor,
        /// Approximate vector to the end feature, counts.
        estimate: CountVector,
        /// Current drift estimate.
        drift: CountVelocity,
    },
    /// Measure all vectors at once by counter-scanning the aperture around `centre`.
    CounterScan {
        /// Centre of the aperture.
        centre: Anchor,
        /// Current drift estimate (prior for matching).
        drift: CountVelocity,
    },
    /// The node is measured: store the result (one transaction) and go on.
    Finished(Box<NodeMeasurement>),
    /// The node is given up.
    GiveUp(GiveUpReason),
}

/// How an attachment ended (the executor's summary of `spm_fos::AttachReport`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum AttachResult {
    /// Held and settled.
    Settled {
        /// The feature's last sighting.
        feature: Anchor,
        /// Drift velocity, counts/s.
        drift: CountVelocity,
    },
    /// The drift did not settle in time.
    DriftNotSettled {
        /// Last drift velocity, counts/s.
        drift: CountVelocity,
    },
    /// No feature was found or it was lost.
    FeatureLost,
}

/// A recognised LCS with A's neighbours (the executor's summary of `spm_fos::ApertureReport`).
#[derive(Clone, Debug, PartialEq)]
pub struct ApertureResult {
    /// Feature A.
    pub a: Anchor,
    /// A→B and A→C as seen in the aperture, counts.
    pub lcs: Option<(CountVector, CountVector)>,
    /// A→neighbour for every neighbour forming an LCS with A, counts.
    pub neighbours: Vec<CountVector>,
    /// A→feature for every other feature recognised in the aperture, counts (for
    /// [`NeighbourSet::LatticeInAperture`]).
    pub features: Vec<CountVector>,
}

/// A measured vector (summary of `spm_fos::SkipReport`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SkipResult {
    /// The required cycles were kept.
    Completed {
        /// Mean drift-free vector over kept cycles, counts.
        vector: CountVector,
        /// Its covariance, counts².
        covariance: CountCovariance,
        /// A's last sighting.
        a: Anchor,
        /// Drift velocity, counts/s.
        drift: CountVelocity,
        /// Cycle statistics.
        cycles: CycleCounts,
    },
    /// The drift monitor gave up or the cycle budget ran out.
    Unstable {
        /// Cycle statistics.
        cycles: CycleCounts,
    },
}

/// Counts of skipping cycles.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CycleCounts {
    /// Kept measuring cycles.
    pub kept: u32,
    /// Spoiled and discarded cycles.
    pub discarded: u32,
    /// Idle cycles.
    pub idle: u32,
    /// Restarts of the skipping.
    pub restarts: u32,
}

impl CycleCounts {
    fn add(&mut self, other: CycleCounts) {
        self.kept += other.kept;
        self.discarded += other.discarded;
        self.idle += other.idle;
        self.restarts += other.restarts;
    }
}

/// Drift-free vectors from a counter-scan: A→feature for each matched neighbour.
#[derive(Clone, Debug, PartialEq)]
pub struct CounterResult {
    /// Drift-free A, counts.
    pub a: Anchor,
    /// Drift-free vectors A→neighbour with covariances.
    pub vectors: Vec<(CountVector, CountCovariance)>,
    /// Drift velocity, counts/s.
    pub drift: CountVelocity,
}

/// A failure of the last action, classified by the executor.
#[derive(Clone, Debug, PartialEq)]
pub enum Failure {
    /// A backend error of a transient kind (timeout, communication, feedback lost) or a
    /// feature lost while tracking: retried within the node's transient budget.
    Transient {
        /// The backend's kind (`None` for a lost feature).
        kind: Option<ErrorKind>,
        /// The message.
        message: String,
    },
    /// A measurement problem (recognition error, malformed frame): the node is redone.
    Measurement {
        /// The message.
        message: String,
    },
    /// A permanent backend error for this node (out of range, other): given up at once.
    Permanent {
        /// The backend's kind.
        kind: ErrorKind,
        /// The message.
        message: String,
    },
}

/// The outcome of the last action.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// Start of the visit (first call).
    Begin,
    /// The move and pause are done.
    Paused,
    /// The attachment ended.
    Attached(AttachResult),
    /// The aperture was scanned and recognised.
    ApertureScanned(ApertureResult),
    /// A vector was skipped.
    Skipped(SkipResult),
    /// A counter-scan was made.
    CounterScanned(CounterResult),
    /// The last action failed.
    Failed(Failure),
}

/// Why a node was given up (stored as its text in the CDB).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, thiserror::Error)]
#[serde(tag = "reason", rename_all = "snake_case")]
#[non_exhaustive]
pub enum GiveUpReason {
    /// No feature could be captured near the node.
    #[error("no feature captured near the node")]
    NoFeature,
    /// The drift did not fall below the limit during the attachments.
    #[error("drift did not settle below the limit ({speed_counts_per_s:.3} counts/s)")]
    DriftNotSettled {
        /// The last speed, counts/s.
        speed_counts_per_s: f64,
    },
    /// No LCS matching the standard was recognised in the aperture.
    #[error("no LCS matching the standard in the aperture")]
    NoLcs,
    /// Skipping (or counter-scanning) could not keep enough cycles: long-term drift
    /// instability.
    #[error("drift unstable: {discarded} cycles spoiled, {restarts} restarts")]
    DriftUnstable {
        /// Spoiled cycles over all attempts.
        discarded: u32,
        /// Skipping restarts over all attempts.
        restarts: u32,
    },
    /// A skipped vector disagrees with the same vector seen in the aperture by more than
    /// `tuning.vector_match_tolerance_fraction` of its length: an attachment caught a neighbouring
    /// feature (the probe landed more than half a lattice constant off), so the half-sum
    /// measured another vector of the lattice.
    #[error(
        "skipping caught another feature: the vector differs from the aperture's by {deviation_fraction:.2} of its length"
    )]
    WrongFeature {
        /// |measured − aperture estimate| ÷ |aperture estimate|.
        deviation_fraction: f64,
    },
    /// The measured vectors gave no valid LCCs.
    #[error("LCC solve failed: {message}")]
    Degenerate {
        /// The solver's message.
        message: String,
    },
    /// Recognition or frame errors on every attempt.
    #[error("measurement failed: {message}")]
    Measurement {
        /// The last message.
        message: String,
    },
    /// The transient-error budget ran out.
    #[error("{count} transient backend errors, last: {message}")]
    TransientErrors {
        /// Transient errors at this node.
        count: u32,
        /// The last kind (`None` for a lost feature).
        kind: Option<ErrorKind>,
        /// The last message.
        message: String,
    },
    /// A permanent backend error.
    #[error("backend error ({kind:?}): {message}")]
    Backend {
        /// The kind.
        kind: ErrorKind,
        /// The message.
        message: String,
    },
}

/// The result of a measured node.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NodeMeasurement {
    /// The visit.
    pub visit: PlanVisit,
    /// The LCCs.
    pub lcc: LccEstimate,
    /// Gravity centre of the features used (drift-free, at A's last sighting), counts.
    pub centre: CountPoint,
    /// Drift velocity at the end, counts/s.
    pub drift: CountVelocity,
    /// Cycle statistics over all attempts at this visit.
    pub cycles: CycleCounts,
    /// Attempts it took (1 = first time).
    pub attempts: u32,
    /// The vectors used.
    pub vectors: Vec<VectorObservation>,
}

impl NodeMeasurement {
    /// Quality score in (0, 1], higher is better: `1 / (1 + 100·r)` with r the combined
    /// relative standard uncertainty √((u(K̄x)/K̄x)² + (u(K̄y)/K̄y)²) (1 % → 0.5).
    pub fn quality(&self) -> f64 {
        let rx = self.lcc.u_kx().value() / self.lcc.kx.value();
        let ry = self.lcc.u_ky().value() / self.lcc.ky.value();
        let r = rx.hypot(ry);
        if r.is_finite() {
            1.0 / (1.0 + 100.0 * r)
        } else {
            0.0
        }
    }
}

/// The lattice a recognised LCS spans at a node: C = [A→B A→C] (columns, counts) and the
/// standard's S = [(a, 0) a(cos θ, ±sin θ)] (nm; the sign of C's orientation), so that the
/// site with lattice indices (i, j) lies at C·(i, j) in counts and at S·(i, j) in nm.
struct LcsFrame {
    /// C⁻¹, row by row.
    c_inverse: [[f64; 2]; 2],
    /// S, row by row.
    s: [[f64; 2]; 2],
}

impl LcsFrame {
    /// The frame of the LCS (A→B, A→C) for lattice constant `a_nm` and LCS angle
    /// `theta_rad`; `None` when A→B and A→C are parallel or not finite.
    fn new((ab, ac): (CountVector, CountVector), a_nm: f64, theta_rad: f64) -> Option<Self> {
        let (c11, c12, c21, c22) = (ab.x.value(), ac.x.value(), ab.y.value(), ac.y.value());
        let det = c11 * c22 - c12 * c21;
        if !(det.is_finite() && det != 0.0) {
            return None;
        }
        let sign = if det >= 0.0 { 1.0 } else { -1.0 };
        Some(Self {
            c_inverse: [[c22 / det, -c12 / det], [-c21 / det, c11 / det]],
            s: [
                [a_nm, a_nm * theta_rad.cos()],
                [0.0, sign * a_nm * theta_rad.sin()],
            ],
        })
    }

    /// Lattice coordinates (u, w) = C⁻¹·v of a vector from A, counts.
    fn lattice(&self, v: CountVector) -> (f64, f64) {
        let (x, y) = (v.x.value(), v.y.value());
        let m = &self.c_inverse;
        (m[0][0] * x + m[0][1] * y, m[1][0] * x + m[1][1] * y)
    }

    /// The standard's vector S·(u, w) of lattice coordinates, nm.
    fn standard(&self, (u, w): (f64, f64)) -> (f64, f64) {
        let m = &self.s;
        (m[0][0] * u + m[0][1] * w, m[1][0] * u + m[1][1] * w)
    }
}

/// The parts of the plan the machine needs.
#[derive(Clone, Debug, PartialEq)]
pub struct MachineParams {
    /// Attach target variant.
    pub attach_to: AttachTarget,
    /// Which neighbours.
    pub neighbours: NeighbourSet,
    /// B↔C redundancy.
    pub bc_redundancy: bool,
    /// Skipping or counter-scanning.
    pub measurement: MeasurementMethod,
    /// Omit the attachment.
    pub skip_attach: bool,
    /// Lattice constant (|AB| = |AC|), nm.
    pub lattice_constant_nm: f64,
    /// LCS angle.
    pub lcs_angle: Radians,
    /// Attempts per node.
    pub max_attempts: u32,
    /// Transient errors per node.
    pub transient_retries: u32,
    /// A measured vector farther than this fraction of its length from the expected one
    /// caught another feature (plan `tuning.vector_match_tolerance_fraction`).
    pub vector_match_tolerance: f64,
    /// Accepted relative deviation of a neighbour's length from the lattice constant
    /// (plan `standard.length_tolerance_fraction`), for [`NeighbourSet::AllInAperture`]; for
    /// [`NeighbourSet::LatticeInAperture`], the accepted distance of a feature from its
    /// lattice site, as a fraction of the lattice constant.
    pub length_tolerance: f64,
    /// Accepted deviation of a neighbour's direction from a lattice direction (plan
    /// `standard.angle_tolerance_deg`), for [`NeighbourSet::AllInAperture`].
    pub angle_tolerance: Radians,
}

impl MachineParams {
    /// From a plan.
    pub fn from_plan(plan: &PlanConfig) -> Self {
        Self {
            attach_to: plan.variant.attach_to,
            neighbours: plan.variant.neighbours,
            bc_redundancy: plan.variant.bc_redundancy,
            measurement: plan.variant.measurement,
            skip_attach: plan.attach.skip,
            lattice_constant_nm: plan.standard.lattice_constant_nm,
            lcs_angle: plan.standard.lcs_angle(),
            max_attempts: plan.failures.max_attempts_per_node.max(1),
            transient_retries: plan.failures.transient_retries_per_node,
            vector_match_tolerance: plan.tuning.vector_match_tolerance_fraction,
            length_tolerance: plan.standard.length_tolerance_fraction,
            angle_tolerance: Radians(plan.standard.angle_tolerance_deg.to_radians()),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Stage {
    Start,
    Pausing,
    Attaching,
    Aperture,
    Measuring(usize),
    CounterScanning,
    Over,
}

/// The state machine of one visit (see the module docs).
#[derive(Clone, Debug)]
pub struct NodeMachine {
    visit: PlanVisit,
    params: MachineParams,
    pause: Seconds,
    stage: Stage,
    attempt: u32,
    transient: u32,
    a: Option<Anchor>,
    drift: CountVelocity,
    targets: Vec<VectorTarget>,
    measured: Vec<VectorObservation>,
    cycles: CycleCounts,
    last_failure: Option<GiveUpReason>,
}

impl NodeMachine {
    /// A machine for `visit`; `pause` is the pause after the move to it (pause law).
    pub fn new(visit: PlanVisit, params: MachineParams, pause: Seconds) -> Self {
        Self {
            visit,
            params,
            pause,
            stage: Stage::Start,
            attempt: 0,
            transient: 0,
            a: None,
            drift: CountVelocity::ZERO,
            targets: Vec::new(),
            measured: Vec::new(),
            cycles: CycleCounts::default(),
            last_failure: None,
        }
    }

    /// The visit.
    pub fn visit(&self) -> &PlanVisit {
        &self.visit
    }
    /// The current attempt (1-based once started).
    pub fn attempt(&self) -> u32 {
        self.attempt
    }
    /// Transient errors so far.
    pub fn transient_errors(&self) -> u32 {
        self.transient
    }
    /// The vectors to measure at this attempt.
    pub fn targets(&self) -> &[VectorTarget] {
        &self.targets
    }
    /// Cycle statistics so far.
    pub fn cycles(&self) -> CycleCounts {
        self.cycles
    }
    /// The current drift estimate.
    pub fn drift(&self) -> CountVelocity {
        self.drift
    }
    /// True once [`Action::Finished`] or [`Action::GiveUp`] was returned.
    pub fn is_over(&self) -> bool {
        self.stage == Stage::Over
    }

    /// Restart the node (a new attempt) after `reason`, or give up when attempts ran out.
    fn redo(&mut self, reason: GiveUpReason) -> Action {
        tracing::info!(
            repeat = self.visit.repeat_index,
            node = self.visit.node_index,
            attempt = self.attempt,
            %reason,
            "node attempt failed"
        );
        self.last_failure = Some(reason.clone());
        if self.attempt >= self.params.max_attempts {
            self.stage = Stage::Over;
            return Action::GiveUp(reason);
        }
        self.start_attempt(self.params_pause_on_redo())
    }

    fn params_pause_on_redo(&self) -> Seconds {
        // Back to a node the probe is already near: the pause of a short move.
        self.pause
    }

    fn start_attempt(&mut self, pause: Seconds) -> Action {
        self.attempt += 1;
        self.a = None;
        self.targets.clear();
        self.measured.clear();
        self.stage = Stage::Pausing;
        Action::MoveAndPause {
            node: self.visit.grid,
            pause,
        }
    }

    fn after_pause(&mut self) -> Action {
        let node = self.visit.grid.position();
        if self.params.skip_attach || self.params.attach_to == AttachTarget::LcsCentre {
            // Fig. 3b / §2.1.3: the aperture around the node acts as the attachment.
            self.stage = Stage::Aperture;
            Action::Aperture {
                centre: Anchor {
                    position: node,
                    time: None,
                },
            }
        } else {
            self.stage = Stage::Attaching;
            Action::Attach { near: node }
        }
    }

    /// True angle of a measured vector: its angle from the first vector rounded to a
    /// multiple of the LCS angle (lattice directions), length the lattice constant.
    fn standard_for(&self, first: CountVector, v: CountVector) -> StandardVector {
        let angle = (first.x.value() * v.y.value() - first.y.value() * v.x.value())
            .atan2(first.dot_counts_squared(v));
        let step = self.params.lcs_angle.value();
        let k = (angle / step).round();
        StandardVector::polar(
            spm_hal::Nanometres(self.params.lattice_constant_nm),
            Radians(k * step),
        )
    }

    /// Every neighbour of A named by the lattice direction it lies along, through the
    /// recognised LCS: the LCS maps the standard's frame to counts here (P·(a, 0) = A→B,
    /// P·a(cos θ, ±sin θ) = A→C), each neighbour is taken back through P⁻¹ and given the
    /// standard vector of its nearest lattice direction (its angle rounded to a multiple of
    /// the LCS angle θ). A neighbour that is not a nearest neighbour there (its length or
    /// angle through P⁻¹ beyond the standard's tolerances) is not measured. Naming the
    /// directions in counts instead (the angle from the first neighbour) names one wrongly
    /// where the scanner's local distortion turns a direction by more than half of θ, and
    /// one such vector spoils the node's solution (a Si 7×7 image at 0.68 y-scale and −10°
    /// obliquity: a record with K̄x 21 % and α 27° off).
    fn neighbours_through_lcs(
        &self,
        lcs: (CountVector, CountVector),
        neighbours: &[CountVector],
    ) -> Vec<VectorTarget> {
        let a = self.params.lattice_constant_nm;
        let theta = self.params.lcs_angle.value();
        let Some(frame) = LcsFrame::new(lcs, a, theta) else {
            return Vec::new();
        };
        neighbours
            .iter()
            .filter_map(|&n| {
                let (x, y) = frame.standard(frame.lattice(n));
                let angle = y.atan2(x);
                let k = (angle / theta).round();
                let off_angle = (angle - k * theta).abs();
                let off_length = (x.hypot(y) / a - 1.0).abs();
                (off_angle <= self.params.angle_tolerance.value()
                    && off_length <= self.params.length_tolerance)
                    .then(|| VectorTarget {
                        start: VectorStart::AtA,
                        estimate: n,
                        standard: StandardVector::polar(spm_hal::Nanometres(a), Radians(k * theta)),
                    })
            })
            .collect()
    }

    /// Every feature of the aperture on a site of A's lattice, named by its lattice indices
    /// through the recognised LCS: a feature at v sits at lattice coordinates (u, w) = C⁻¹·v
    /// ([`LcsFrame`]); it is kept when its nearest site (i, j) is not A's own and it lies
    /// within `length_tolerance` lattice constants of that site in the standard's frame
    /// (|S·(u − i, w − j)|), and its true vector is S·(i, j).
    fn sites_through_lcs(
        &self,
        lcs: (CountVector, CountVector),
        features: &[CountVector],
    ) -> Vec<VectorTarget> {
        let a = self.params.lattice_constant_nm;
        let Some(frame) = LcsFrame::new(lcs, a, self.params.lcs_angle.value()) else {
            return Vec::new();
        };
        features
            .iter()
            .filter_map(|&v| {
                let (u, w) = frame.lattice(v);
                let (i, j) = (u.round(), w.round());
                let (ex, ey) = frame.standard((u - i, w - j));
                let (sx, sy) = frame.standard((i, j));
                ((i, j) != (0.0, 0.0) && ex.hypot(ey) <= self.params.length_tolerance * a).then(
                    || VectorTarget {
                        start: VectorStart::AtA,
                        estimate: v,
                        standard: StandardVector::from_nm(sx, sy),
                    },
                )
            })
            .collect()
    }

    fn plan_targets(&mut self, aperture: &ApertureResult) -> bool {
        let a = self.params.lattice_constant_nm;
        let mut targets = Vec::new();
        match (self.params.neighbours, aperture.lcs) {
            (NeighbourSet::LatticeInAperture, Some(lcs)) => {
                targets = self.sites_through_lcs(lcs, &aperture.features);
                if targets.len() < 2 {
                    return false;
                }
            }
            (NeighbourSet::AllInAperture, Some(lcs)) if aperture.neighbours.len() >= 2 => {
                targets = self.neighbours_through_lcs(lcs, &aperture.neighbours);
                if targets.len() < 2 {
                    return false;
                }
            }
            (NeighbourSet::AllInAperture, _) if aperture.neighbours.len() >= 2 => {
                let first = aperture.neighbours[0];
                for &n in &aperture.neighbours {
                    targets.push(VectorTarget {
                        start: VectorStart::AtA,
                        estimate: n,
                        standard: self.standard_for(first, n),
                    });
                }
            }
            (_, Some((ab, ac))) => {
                let sign = if ab.x.value() * ac.y.value() - ab.y.value() * ac.x.value() >= 0.0 {
                    1.0
                } else {
                    -1.0
                };
                targets.push(VectorTarget {
                    start: VectorStart::AtA,
                    estimate: ab,
                    standard: StandardVector::from_nm(a, 0.0),
                });
                targets.push(VectorTarget {
                    start: VectorStart::AtA,
                    estimate: ac,
                    standard: StandardVector::polar(
                        spm_hal::Nanometres(a),
                        Radians(sign * self.params.lcs_angle.value()),
                    ),
                });
            }
            _ => return false,
        }
        if self.params.bc_redundancy && targets.len() >= 2 {
            let (b, c) = (targets[0], targets[1]);
            targets.push(VectorTarget {
                start: VectorStart::AtEndOf {
                    index: 0,
                    estimate: b.estimate,
                },
                estimate: c.estimate - b.estimate,
                standard: c.standard.minus(b.standard),
            });
        }
        self.targets = targets;
        true
    }

    /// The machine's step on a skipping's result (stage `Measuring(index)`): the vector is
    /// kept and the next one measured, or a vector that caught another feature redoes the
    /// node (or, with every lattice site measured, costs its vector only), or an unstable
    /// drift redoes the node.
    fn skipped(&mut self, index: usize, result: SkipResult) -> Action {
        match result {
            SkipResult::Completed {
                vector,
                covariance,
                a,
                drift,
                cycles,
            } => {
                self.cycles.add(cycles);
                self.drift = drift;
                if let Some(target) = self.targets.get(index) {
                    let length = target.estimate.norm().value();
                    let deviation_fraction =
                        (vector - target.estimate).norm().value() / length.max(f64::MIN_POSITIVE);
                    if deviation_fraction.is_nan()
                        || deviation_fraction > self.params.vector_match_tolerance
                    {
                        // With every site of A measured, a skipping that caught another
                        // feature costs its vector only, while three or more targets
                        // remain: the node keeps its redundancy.
                        if self.drops_wrong_vectors() && self.targets.len() > 3 {
                            return self.drop_target(index, "caught another feature");
                        }
                        return self.redo(GiveUpReason::WrongFeature { deviation_fraction });
                    }
                }
                // Keep A's latest sighting when the vector started at A.
                if self
                    .targets
                    .get(index)
                    .is_some_and(|t| t.start == VectorStart::AtA)
                {
                    self.a = Some(a);
                }
                let standard = self.targets[index].standard;
                self.measured.push(VectorObservation {
                    measured: vector,
                    covariance,
                    standard,
                });
                self.next_measurement(index + 1)
            }
            SkipResult::Unstable { cycles } => {
                self.cycles.add(cycles);
                self.redo(GiveUpReason::DriftUnstable {
                    discarded: self.cycles.discarded,
                    restarts: self.cycles.restarts,
                })
            }
        }
    }

    /// Whether a vector whose skipping caught another feature (or would leave the
    /// instrument's range) is dropped from the node rather than the node redone: for
    /// [`NeighbourSet::LatticeInAperture`], whose farther sites lie near the aperture's edge,
    /// where a skipping's window reaches beyond a small image or meets a feature between
    /// sites (Si_7x7_051: 1 record of 25 nodes when such a vector redid its node, 16 when it
    /// is dropped). A nearest neighbour that catches another feature says that the node's
    /// attachment or LCS is wrong, and the other variants redo the node.
    fn drops_wrong_vectors(&self) -> bool {
        self.params.neighbours == NeighbourSet::LatticeInAperture
    }

    /// Leaves target `index` out of the node (its skipping `why`) and measures the next one,
    /// now at the same index.
    fn drop_target(&mut self, index: usize, why: &str) -> Action {
        self.targets.remove(index);
        tracing::debug!(
            why,
            left = self.targets.len(),
            "a vector is left out of the node"
        );
        self.next_measurement(index)
    }

    fn next_measurement(&mut self, index: usize) -> Action {
        let Some(a) = self.a else {
            return self.redo(GiveUpReason::NoFeature);
        };
        if index >= self.targets.len() {
            return self.solve();
        }
        let target = self.targets[index];
        // The start feature: A, or (B↔C) A plus the measured A→B when available.
        let from_offset = match target.start {
            VectorStart::AtA => CountVector::default(),
            VectorStart::AtEndOf { index, estimate } => {
                self.measured.get(index).map_or(estimate, |m| m.measured)
            }
        };
        self.stage = Stage::Measuring(index);
        Action::Skip {
            index,
            from: Anchor {
                position: a.position + from_offset,
                time: a.time,
            },
            estimate: target.estimate,
            drift: self.drift,
        }
    }

    fn solve(&mut self) -> Action {
        let Some(a) = self.a else {
            return self.redo(GiveUpReason::NoFeature);
        };
        // Every neighbour of A measured: a vector of another feature (a defect, a feature
        // the aperture misplaced) is left out by the node's own redundancy.
        let solved = match self.params.neighbours {
            NeighbourSet::AllInAperture | NeighbourSet::LatticeInAperture
                if self.measured.len() > 3 =>
            {
                solve_lcc_rejecting(&self.measured, VECTOR_REJECTION_SIGMAS).map(|(lcc, kept)| {
                    retain_indices(&mut self.measured, &kept);
                    retain_indices(&mut self.targets, &kept);
                    lcc
                })
            }
            _ => solve_lcc(&self.measured),
        };
        match solved {
            Ok(lcc) => {
                // Gravity centre of A and the end features of the vectors from A.
                let ends: Vec<CountVector> = self
                    .measured
                    .iter()
                    .zip(self.targets.iter())
                    .filter(|(_, t)| t.start == VectorStart::AtA)
                    .map(|(m, _)| m.measured)
                    .collect();
                let n = (ends.len() + 1) as f64;
                let sum = ends.iter().fold(CountVector::default(), |s, v| s + *v);
                let centre = a.position + sum * (1.0 / n);
                self.stage = Stage::Over;
                Action::Finished(Box::new(NodeMeasurement {
                    visit: self.visit,
                    lcc,
                    centre,
                    drift: self.drift,
                    cycles: self.cycles,
                    attempts: self.attempt,
                    vectors: self.measured.clone(),
                }))
            }
            Err(e) => self.redo(GiveUpReason::Degenerate {
                message: e.to_string(),
            }),
        }
    }

    /// One transition: the outcome of the last action in, the next action out.
    pub fn step(&mut self, event: Event) -> Action {
        if self.stage == Stage::Over {
            return Action::GiveUp(self.last_failure.clone().unwrap_or(
                GiveUpReason::Measurement {
                    message: "step after the end of the visit".into(),
                },
            ));
        }
        match (self.stage, event) {
            (Stage::Start, Event::Begin) => self.start_attempt(self.pause),
            // With every site of A measured, a vector whose skipping would leave the
            // instrument's range (a site near the field's edge) is left out of the node while
            // three or more targets remain.
            (
                Stage::Measuring(index),
                Event::Failed(Failure::Permanent {
                    kind: ErrorKind::OutOfRange,
                    ..
                }),
            ) if self.drops_wrong_vectors() && self.targets.len() > 3 => {
                self.drop_target(index, "out of the instrument's range")
            }
            (_, Event::Failed(failure)) => self.fail(failure),
            (Stage::Pausing, Event::Paused) => self.after_pause(),
            (Stage::Attaching, Event::Attached(result)) => match result {
                AttachResult::Settled { feature, drift } => {
                    self.drift = drift;
                    self.stage = Stage::Aperture;
                    Action::Aperture { centre: feature }
                }
                AttachResult::DriftNotSettled { drift } => {
                    self.drift = drift;
                    self.redo(GiveUpReason::DriftNotSettled {
                        speed_counts_per_s: drift.norm_counts_per_s(),
                    })
                }
                AttachResult::FeatureLost => self.redo(GiveUpReason::NoFeature),
            },
            (Stage::Aperture, Event::ApertureScanned(result)) => {
                self.a = Some(result.a);
                if !self.plan_targets(&result) {
                    return self.redo(GiveUpReason::NoLcs);
                }
                match self.params.measurement {
                    MeasurementMethod::Skipping => self.next_measurement(0),
                    MeasurementMethod::CounterScan => {
                        self.stage = Stage::CounterScanning;
                        Action::CounterScan {
                            centre: result.a,
                            drift: self.drift,
                        }
                    }
                }
            }
            (Stage::Measuring(index), Event::Skipped(result)) => self.skipped(index, result),
            (Stage::CounterScanning, Event::CounterScanned(result)) => {
                self.drift = result.drift;
                self.a = Some(result.a);
                // Match each drift-free vector to the nearest planned target.
                self.measured.clear();
                let mut used = Vec::new();
                for t in self.targets.clone() {
                    if t.start != VectorStart::AtA {
                        // B↔C is implied by the same scan: no independent information.
                        continue;
                    }
                    let best = result
                        .vectors
                        .iter()
                        .enumerate()
                        .filter(|(i, _)| !used.contains(i))
                        .map(|(i, (v, c))| (i, *v, *c, (*v - t.estimate).norm().value()))
                        .min_by(|x, y| x.3.total_cmp(&y.3));
                    if let Some((i, v, c, d)) = best
                        && d < self.params.vector_match_tolerance * t.estimate.norm().value()
                    {
                        used.push(i);
                        self.measured.push(VectorObservation {
                            measured: v,
                            covariance: c,
                            standard: t.standard,
                        });
                    }
                }
                self.targets.retain(|t| t.start == VectorStart::AtA);
                if self.measured.len() < 2 {
                    return self.redo(GiveUpReason::NoLcs);
                }
                self.cycles.kept += 1;
                // Only the matched targets are kept, in measured order.
                self.targets = self
                    .measured
                    .iter()
                    .map(|m| VectorTarget {
                        start: VectorStart::AtA,
                        estimate: m.measured,
                        standard: m.standard,
                    })
                    .collect();
                self.solve()
            }
            (stage, event) => {
                tracing::error!(?stage, ?event, "unexpected event");
                self.fail(Failure::Measurement {
                    message: format!("unexpected event {event:?} in stage {stage:?}"),
                })
            }
        }
    }

    fn fail(&mut self, failure: Failure) -> Action {
        match failure {
            Failure::Transient { kind, message } => {
                self.transient += 1;
                tracing::warn!(?kind, error = %message, count = self.transient, "transient failure");
                if self.transient > self.params.transient_retries {
                    self.stage = Stage::Over;
                    let reason = GiveUpReason::TransientErrors {
                        count: self.transient,
                        kind,
                        message,
                    };
                    self.last_failure = Some(reason.clone());
                    Action::GiveUp(reason)
                } else {
                    // A retry does not use up an attempt.
                    self.attempt = self.attempt.saturating_sub(1);
                    let pause = self.pause;
                    self.start_attempt(pause)
                }
            }
            Failure::Measurement { message } => self.redo(GiveUpReason::Measurement { message }),
            Failure::Permanent { kind, message } => {
                self.stage = Stage::Over;
                let reason = GiveUpReason::Backend { kind, message };
                self.last_failure = Some(reason.clone());
                Action::GiveUp(reason)
            }
        }
    }
}

/// The covariance of a mean vector from the scatter of `n` kept cycles (its standard
/// error `sigma`) and the localisation uncertainties (`localisation`, per-cycle standard
/// deviation): the larger of the two per component.
pub fn vector_covariance(
    sigma_of_mean: CountVector,
    localisation_per_cycle: CountVector,
    n: usize,
) -> CountCovariance {
    let n = n.max(1) as f64;
    let var = |s: Counts, l: Counts| (s.value() * s.value()).max(l.value() * l.value() / n);
    CountCovariance {
        xx_counts2: var(sigma_of_mean.x, localisation_per_cycle.x),
        xy_counts2: 0.0,
        yy_counts2: var(sigma_of_mean.y, localisation_per_cycle.y),
    }
}
