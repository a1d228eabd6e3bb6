//! Ground truth: what a *simulated* instrument knows about itself and a real one never does.
//!
//! The calibration never reads these traits: they exist so that a report can judge a
//! calibration against the truth when the backend has one (the simulator's oracle), without
//! naming the simulator. A real backend implements neither; `report.json` then has no
//! accuracy section.

use crate::{CountPoint, Counts, Microscope, NmPoint, NmVelocity, Seconds};

/// True local calibration coefficients at a point (DESIGN §4:
/// `J = R(θ)·[[K̄x, K̄y·sin α], [0, K̄y·cos α]]`; the rotation θ is unobservable).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrueLcc {
    /// K̄x, nm per count.
    pub kx_nm_per_count: f64,
    /// K̄y, nm per count.
    pub ky_nm_per_count: f64,
    /// Local obliquity α, rad.
    pub alpha_rad: f64,
}

/// The true state of an instrument whose physics is known (an oracle).
pub trait GroundTruth {
    /// The true static LCCs at a commanded point and Z level: the scanner's local map in
    /// its reference state (hysteresis on the major-loop midline, creep settled).
    fn true_lcc(&self, commanded: CountPoint, z: Counts) -> TrueLcc;
    /// The Z-manipulator position now, counts.
    fn z_now(&self) -> Counts;
    /// The instrument clock now.
    fn now(&self) -> Seconds;
    /// The sample drift velocity at instrument time `t`.
    fn drift_velocity(&self, t: Seconds) -> NmVelocity;
    /// Large-signal gain per axis from commanded to effective input in the reference state
    /// (dimensionless, ≈ 1 + the hysteresis and creep weights).
    fn reference_gain(&self) -> [f64; 2];
    /// The vertical axis' truth (Kz field, bowl), when the instrument models it.
    fn vertical(&self) -> Option<&dyn VerticalTruth> {
        None
    }
}

/// Which reference state lateral positions are taken in by [`VerticalTruth`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LateralState {
    /// Hysteresis on the major-loop midline, creep settled (as [`GroundTruth::true_lcc`]).
    CreepSettled,
    /// Right after a move: hysteresis midline, creep not yet reacted (a node is measured
    /// seconds after its move).
    JustMoved,
}

/// The true vertical axis of an instrument whose physics is known (issue 15).
pub trait VerticalTruth {
    /// True local Kz, nm per count, at a commanded point and Z reading.
    fn kz_at(&self, commanded: CountPoint, z: Counts, state: LateralState) -> f64;
    /// The Z reading (counts) of a flat, level sample at a commanded point with the coarse
    /// stage at `coarse_steps`: the bowl as the controller sees it.
    fn flat_sample_z_reading(
        &self,
        commanded: CountPoint,
        coarse_steps: i64,
        state: LateralState,
    ) -> Counts;
    /// True LCCs (creep-settled reference) at a commanded point for a Z *reading*.
    fn true_lcc_at_reading(&self, commanded: CountPoint, z: Counts) -> TrueLcc;
}

/// A square grating to image with the same instrument physics (the realistic per-image
/// polynomial baseline of the image benchmark).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GratingSample {
    /// True pitch, nm.
    pub pitch_nm: f64,
    /// Pillar height, nm.
    pub height_nm: f64,
    /// Pillar Gaussian width σ, nm.
    pub sigma_nm: f64,
    /// Rotation of the grating against the scanner's X axis, degrees.
    pub rotation_deg: f64,
}

/// A simulated instrument for judging corrections on images: it can be copied (the same
/// state and random stream going on after a run), it records the true tip position and true
/// effective input of every pixel of its last scan, and it can image a grating with the same
/// physics.
pub trait SimulatedInstrument: Microscope + GroundTruth + Clone {
    /// Switches the per-pixel truth recording of scans on or off.
    fn record_tip_positions(&mut self, on: bool);
    /// Switches on or off the backward halves recorded *aside*: while on, every scan returns
    /// its backward half (retrace) even when the request does not record it, and the forward
    /// data, the instrument's state and its random streams go on exactly as without it (the
    /// image benchmark's per-image trace/retrace methods read the retrace, the other methods'
    /// figures stay bit-identical).
    fn record_backward_aside(&mut self, on: bool);
    /// The true tip position (scanner frame, hysteresis and creep as they acted, no drift or
    /// jitter) of every pixel of the last scan, in acquisition order (empty when recording is
    /// off).
    fn last_scan_tip_positions(&self) -> Vec<NmPoint>;
    /// The true effective input of every pixel of the last scan, counts, in acquisition
    /// order (empty when recording is off).
    fn last_scan_effective_inputs(&self) -> Vec<CountPoint>;
    /// The sample's drift displacement at `t` (a past time: exact), nm: the sample point under
    /// the tip is the tip position plus it.
    fn drift_displacement(&self, t: Seconds) -> NmPoint;
    /// The same instrument physics over `grating` instead of the sample, in a session of its
    /// own (its own random stream; random faults off).
    ///
    /// # Errors
    /// The backend's error when the twin cannot be built.
    fn grating_twin(&self, grating: &GratingSample) -> Result<Self, Self::Error>;
}
