//! Closing the loop: the fitted model as spm-sim configuration values.
//!
//! This crate does not depend on spm-sim (algorithms never do); the mapping is
//! plain data — dotted TOML paths of spm-sim's `SimConfig` and their values —
//! and [`SimPatch::apply_to_toml`] merges it into a full spm-sim config text.

use crate::diagnose::Diagnosis;
use crate::types::{EffectKind, ModelCheckError};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// What the mapping needs to know about the instrument being simulated.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SimContext {
    /// Nominal calibration the commanded positions were expressed with, nm per count.
    pub nominal_nm_per_count: f64,
    /// The simulator's lateral half range, counts (field-relative nonlinearity
    /// coefficients are rescaled from the frame to the field with it).
    pub half_range_counts: f64,
    /// Simulator time at time 0 of the observations' time axis, s.
    pub time_offset_s: f64,
    /// Warm-up time constant used to express a drift acceleration, s.
    pub warmup_time_constant_s: f64,
    /// Pixel dwell of the simulated scan, s: spm-sim's feedback relaxes once
    /// per pixel, so a continuous lag τ (shift v·τ) becomes the time constant
    /// whose per-pixel decay d obeys d/(1 − d) = τ/dwell.
    pub pixel_dwell_s: Option<f64>,
    /// The move history of the simulated scan program, which drives spm-sim's
    /// creep; `None` = unknown (the creep finding then stays unmapped).
    #[serde(default)]
    pub move_history: Option<MoveHistory>,
}

/// The slowly varying scanner input of a scan program: what spm-sim's creep
/// (a chain of first-order relaxations of the input) follows. The fast axis
/// enters by its line centre (a raster sweeps about it faster than creep
/// follows), the slow axis by its line position.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MoveHistory {
    /// Knots of the piecewise-linear input, in time order, on the observations'
    /// time axis; the scanner rests (creep settled) at the first knot.
    pub knots: Vec<InputKnot>,
    /// Start and end of every frame of the diagnosis on the same axis, s.
    pub frames_s: Vec<[f64; 2]>,
    /// Duration of one scan line (trace and retrace), s: the fast axis sweeps
    /// its frame with this period.
    pub line_period_s: f64,
}

/// One knot of a [`MoveHistory`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct InputKnot {
    /// Time, s.
    pub time_s: f64,
    /// Fast-axis (x) input, nominal nm.
    pub x_nm: f64,
    /// Slow-axis (y) input, nominal nm.
    pub y_nm: f64,
}

/// spm-sim's creep chain as `sim_patch` sets it: time constants from 0.02 s to
/// 2000 s, three per decade (spm-sim's typical chain; one lg amplitude per frame
/// cannot resolve the chain, only its strength).
const CREEP_MIN_TAU_S: f64 = 0.02;
const CREEP_MAX_TAU_S: f64 = 2000.0;
const CREEP_PER_DECADE: u32 = 3;

/// A tip change to schedule in the simulator (a fault, not a config field).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TipChangeEvent {
    /// Simulator time, s.
    pub time_s: f64,
    /// Lateral jump, x, nm.
    pub jump_x_nm: f64,
    /// Lateral jump, y, nm.
    pub jump_y_nm: f64,
}

/// A simulator parameter the model check sets: a field of spm-sim's configuration, named by
/// its TOML path in one table ([`SimParam::path`]), which
/// `tests/it/sim.rs::every_simulator_parameter_the_model_check_sets_is_in_the_simulators_config`
/// checks against spm-sim's own config.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[non_exhaustive]
pub enum SimParam {
    /// K̄x of the scanner, nm per count (`scanner.sensitivity_x_nm_per_count`).
    SensitivityXNmPerCount,
    /// K̄y of the scanner, nm per count (`scanner.sensitivity_y_nm_per_count`).
    SensitivityYNmPerCount,
    /// The axes' non-orthogonality, degrees (`scanner.nonorthogonality_deg`).
    NonorthogonalityDeg,
    /// Linear crosstalk of x from y (`scanner.crosstalk_x_from_y`).
    CrosstalkXFromY,
    /// Linear crosstalk of y from x (`scanner.crosstalk_y_from_x`).
    CrosstalkYFromX,
    /// Bow of x from y (`scanner.bow_x_from_y`).
    BowXFromY,
    /// Bow of y from x (`scanner.bow_y_from_x`).
    BowYFromX,
    /// Shear gradient along x (`scanner.shear_gradient_x`).
    ShearGradientX,
    /// Shear gradient along y (`scanner.shear_gradient_y`).
    ShearGradientY,
    /// The x axis' quadratic nonlinearity (`scanner.nonlinearity_x.quadratic`).
    NonlinearityXQuadratic,
    /// The x axis' cubic nonlinearity (`scanner.nonlinearity_x.cubic`).
    NonlinearityXCubic,
    /// The y axis' quadratic nonlinearity (`scanner.nonlinearity_y.quadratic`).
    NonlinearityYQuadratic,
    /// The y axis' cubic nonlinearity (`scanner.nonlinearity_y.cubic`).
    NonlinearityYCubic,
    /// The x hysteresis loop's width, a fraction of the half range (`scanner.hysteresis_x.width_fraction`).
    HysteresisXWidthFraction,
    /// The x play operators' smallest threshold, counts (`scanner.hysteresis_x.min_threshold_counts`).
    HysteresisXMinThresholdCounts,
    /// The x play operators' largest threshold, counts (`scanner.hysteresis_x.max_threshold_counts`).
    HysteresisXMaxThresholdCounts,
    /// The number of x play operators (`scanner.hysteresis_x.operators`).
    HysteresisXOperators,
    /// Creep γ, per decade (`scanner.creep.log_slope_per_decade`).
    CreepLogSlopePerDecade,
    /// The creep chain's shortest time constant, s (`scanner.creep.min_time_constant_s`).
    CreepMinTimeConstantS,
    /// The creep chain's longest time constant, s (`scanner.creep.max_time_constant_s`).
    CreepMaxTimeConstantS,
    /// The creep chain's elements per decade (`scanner.creep.elements_per_decade`).
    CreepElementsPerDecade,
    /// The surface's rotation, degrees (whichever surface kind the config holds) (`surface.*.rotation_deg`).
    SurfaceRotationDeg,
    /// Constant drift, x, nm/s (`drift.velocity_x_nm_per_s`).
    DriftVelocityXNmPerS,
    /// Constant drift, y, nm/s (`drift.velocity_y_nm_per_s`).
    DriftVelocityYNmPerS,
    /// Warm-up drift amplitude, x, nm (`drift.warmup_amplitude_x_nm`).
    WarmupAmplitudeXNm,
    /// Warm-up drift amplitude, y, nm (`drift.warmup_amplitude_y_nm`).
    WarmupAmplitudeYNm,
    /// Warm-up drift time constant, s (`drift.warmup_time_constant_s`).
    WarmupTimeConstantS,
    /// Lateral vibration frequency, Hz (`drift.vibration_frequency_hz`).
    VibrationFrequencyHz,
    /// Lateral vibration amplitude, x, nm (`drift.vibration_amplitude_x_nm`).
    VibrationAmplitudeXNm,
    /// Lateral vibration amplitude, y, nm (`drift.vibration_amplitude_y_nm`).
    VibrationAmplitudeYNm,
    /// Lateral vibration phase, x, rad (`drift.vibration_phase_x_rad`).
    VibrationPhaseXRad,
    /// Lateral vibration phase, y, rad (`drift.vibration_phase_y_rad`).
    VibrationPhaseYRad,
    /// Interlace, stepped: the retrace's slow-axis advance, counts (`instrument.retrace_slow_axis_advance_counts`).
    RetraceSlowAxisAdvanceCounts,
    /// Interlace, ramped: the slow axis's advance through every line pair, counts
    /// (`instrument.slow_axis_ramp_counts`).
    SlowAxisRampCounts,
    /// The Z feedback's time constant, s (`measurement.feedback_time_constant_s`).
    FeedbackTimeConstantS,
}

impl SimParam {
    /// Every parameter.
    pub const ALL: &'static [Self] = &[
        Self::SensitivityXNmPerCount,
        Self::SensitivityYNmPerCount,
        Self::NonorthogonalityDeg,
        Self::CrosstalkXFromY,
        Self::CrosstalkYFromX,
        Self::BowXFromY,
        Self::BowYFromX,
        Self::ShearGradientX,
        Self::ShearGradientY,
        Self::NonlinearityXQuadratic,
        Self::NonlinearityXCubic,
        Self::NonlinearityYQuadratic,
        Self::NonlinearityYCubic,
        Self::HysteresisXWidthFraction,
        Self::HysteresisXMinThresholdCounts,
        Self::HysteresisXMaxThresholdCounts,
        Self::HysteresisXOperators,
        Self::CreepLogSlopePerDecade,
        Self::CreepMinTimeConstantS,
        Self::CreepMaxTimeConstantS,
        Self::CreepElementsPerDecade,
        Self::SurfaceRotationDeg,
        Self::DriftVelocityXNmPerS,
        Self::DriftVelocityYNmPerS,
        Self::WarmupAmplitudeXNm,
        Self::WarmupAmplitudeYNm,
        Self::WarmupTimeConstantS,
        Self::VibrationFrequencyHz,
        Self::VibrationAmplitudeXNm,
        Self::VibrationAmplitudeYNm,
        Self::VibrationPhaseXRad,
        Self::VibrationPhaseYRad,
        Self::RetraceSlowAxisAdvanceCounts,
        Self::SlowAxisRampCounts,
        Self::FeedbackTimeConstantS,
    ];

    /// Its dotted TOML path in spm-sim's config (`surface.*` is the single surface table).
    #[must_use]
    pub fn path(self) -> &'static str {
        match self {
            Self::SensitivityXNmPerCount => "scanner.sensitivity_x_nm_per_count",
            Self::SensitivityYNmPerCount => "scanner.sensitivity_y_nm_per_count",
            Self::NonorthogonalityDeg => "scanner.nonorthogonality_deg",
            Self::CrosstalkXFromY => "scanner.crosstalk_x_from_y",
            Self::CrosstalkYFromX => "scanner.crosstalk_y_from_x",
            Self::BowXFromY => "scanner.bow_x_from_y",
            Self::BowYFromX => "scanner.bow_y_from_x",
            Self::ShearGradientX => "scanner.shear_gradient_x",
            Self::ShearGradientY => "scanner.shear_gradient_y",
            Self::NonlinearityXQuadratic => "scanner.nonlinearity_x.quadratic",
            Self::NonlinearityXCubic => "scanner.nonlinearity_x.cubic",
            Self::NonlinearityYQuadratic => "scanner.nonlinearity_y.quadratic",
            Self::NonlinearityYCubic => "scanner.nonlinearity_y.cubic",
            Self::HysteresisXWidthFraction => "scanner.hysteresis_x.width_fraction",
            Self::HysteresisXMinThresholdCounts => "scanner.hysteresis_x.min_threshold_counts",
            Self::HysteresisXMaxThresholdCounts => "scanner.hysteresis_x.max_threshold_counts",
            Self::HysteresisXOperators => "scanner.hysteresis_x.operators",
            Self::CreepLogSlopePerDecade => "scanner.creep.log_slope_per_decade",
            Self::CreepMinTimeConstantS => "scanner.creep.min_time_constant_s",
            Self::CreepMaxTimeConstantS => "scanner.creep.max_time_constant_s",
            Self::CreepElementsPerDecade => "scanner.creep.elements_per_decade",
            Self::SurfaceRotationDeg => "surface.*.rotation_deg",
            Self::DriftVelocityXNmPerS => "drift.velocity_x_nm_per_s",
            Self::DriftVelocityYNmPerS => "drift.velocity_y_nm_per_s",
            Self::WarmupAmplitudeXNm => "drift.warmup_amplitude_x_nm",
            Self::WarmupAmplitudeYNm => "drift.warmup_amplitude_y_nm",
            Self::WarmupTimeConstantS => "drift.warmup_time_constant_s",
            Self::VibrationFrequencyHz => "drift.vibration_frequency_hz",
            Self::VibrationAmplitudeXNm => "drift.vibration_amplitude_x_nm",
            Self::VibrationAmplitudeYNm => "drift.vibration_amplitude_y_nm",
            Self::VibrationPhaseXRad => "drift.vibration_phase_x_rad",
            Self::VibrationPhaseYRad => "drift.vibration_phase_y_rad",
            Self::RetraceSlowAxisAdvanceCounts => "instrument.retrace_slow_axis_advance_counts",
            Self::SlowAxisRampCounts => "instrument.slow_axis_ramp_counts",
            Self::FeedbackTimeConstantS => "measurement.feedback_time_constant_s",
        }
    }

    /// The parameter at a dotted path.
    #[must_use]
    pub fn from_path(path: &str) -> Option<Self> {
        Self::ALL.iter().copied().find(|p| p.path() == path)
    }

    /// Whether it is one of the x hysteresis operator's.
    #[must_use]
    pub fn is_x_hysteresis(self) -> bool {
        matches!(
            self,
            Self::HysteresisXWidthFraction
                | Self::HysteresisXMinThresholdCounts
                | Self::HysteresisXMaxThresholdCounts
                | Self::HysteresisXOperators
        )
    }
}

impl Serialize for SimParam {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_str(self.path())
    }
}

impl<'de> Deserialize<'de> for SimParam {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let path = String::deserialize(deserializer)?;
        Self::from_path(&path).ok_or_else(|| {
            serde::de::Error::custom(format!("{path} is not a simulator parameter spmcal sets"))
        })
    }
}

/// spm-sim configuration values of a fitted model.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SimPatch {
    /// The simulator parameters and their values.
    pub values: BTreeMap<SimParam, f64>,
    /// Tip changes to schedule.
    pub tip_changes: Vec<TipChangeEvent>,
    /// Findings spm-sim has no parameter for, with the reason.
    pub unmapped: Vec<String>,
    /// The scan program to run the frames with, as `tip_changes` is the faults to schedule
    /// (neither is a config value): `Some(β)` when the fast axis is driven by a sine
    /// (`sinusoidal_drive`): spm-sim's fast-SPM raster, `Simulator::scan_sine_driven` with
    /// `SineDrive { phase_at_line_end_rad: β }` (β in rad; its amplitude W/sin β in counts
    /// follows from the frame, so `scanner.sensitivity_x_nm_per_count` is the sine's scale,
    /// not the lumped slope at the line centre). `None`: the linear raster. Default: `None`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sine_drive_phase_at_line_end_rad: Option<f64>,
}

fn value(d: &BTreeMap<String, crate::ParamValue>, key: &str) -> f64 {
    d.get(key).map_or(0.0, |p| p.value)
}

/// The spm-sim values of the diagnosis' model: the baseline alone
/// (`with_findings = false`) or extended by every finding.
///
/// Conventions (spm-sim's `StaticMap`, DESIGN §4): `J = R(θ)·[[Kx, Ky·sin α],
/// [0, Ky·cos α]]`; the surface rotation is −θ (modulo the lattice symmetry);
/// linear crosstalk is zero (it is inside J); frame-relative nonlinearity and
/// bow coefficients are rescaled to the field for a frame centred on the field
/// centre (`q_field = q_frame·H/W`, `c_field = c_frame·(H/W)²`); hysteresis maps
/// to play operators whose thresholds all open within the frame; the shear
/// gradient to `scanner.shear_gradient_{x,y}` (`γx = gx·H_field/H_frame`,
/// `γy = gy·H_field/W_frame`); a vibration to `drift.vibration_*` (phases moved to
/// the simulator's clock); an interlace to `instrument.retrace_slow_axis_advance_counts`
/// (`δ = −separation/(Ky·cos α)`), a ramped one to `instrument.slow_axis_ramp_counts`
/// (`ρ = −2·separation/(Ky·cos α)`); creep to the relaxation chain through the move
/// history ([`MoveHistory`]: its γ from the chain's closed-form response, and the
/// chain's gain, drift and loop that the linear fit and a hysteresis finding
/// already hold taken out of them). Tip changes become scheduled faults. A sinusoidal
/// drive becomes spm-sim's fast-SPM scan program ([`SimPatch::sine_drive_phase_at_line_end_rad`]):
/// the lumped scale's slope at the line centre is the sine's A·β/W (A = k·W/sin β), so the
/// fast axis's sensitivity is the lumped one × sin β/β.
pub fn sim_patch(d: &Diagnosis, ctx: &SimContext, with_findings: bool) -> SimPatch {
    // The linear part of the model the findings extend: the final fit's.
    let b = if with_findings {
        &d.final_report.parameters
    } else {
        &d.baseline.parameters
    };
    let n0 = ctx.nominal_nm_per_count;
    let mut p = SimPatch::default();
    let mut set = |k: SimParam, v: f64| {
        p.values.insert(k, v);
    };
    set(SimParam::SensitivityXNmPerCount, value(b, "scale_x") * n0);
    set(SimParam::SensitivityYNmPerCount, value(b, "scale_y") * n0);
    set(SimParam::NonorthogonalityDeg, value(b, "obliquity_deg"));
    set(SimParam::CrosstalkXFromY, 0.0);
    set(SimParam::CrosstalkYFromX, 0.0);
    set(SimParam::SurfaceRotationDeg, -value(b, "rotation_deg"));
    let mut m = Mapped {
        values: std::mem::take(&mut p.values),
        vx: value(b, "drift_x_nm_per_s"),
        vy: value(b, "drift_y_nm_per_s"),
        unmapped: Vec::new(),
        tips: Vec::new(),
        creep: None,
        sine_phase_rad: None,
    };
    if with_findings {
        let frame_half = d.frame_half_nm.first().copied().unwrap_or([1.0, 1.0]);
        let field_half_nm = ctx.half_range_counts * n0;
        let env = FrameScale {
            linear: b,
            frame_half,
            rx: field_half_nm / frame_half[0].max(1e-12),
            ry: field_half_nm / frame_half[1].max(1e-12),
            n0,
        };
        for f in &d.findings {
            let fp = &f.parameters;
            let Some(kind) = EffectKind::from_name(&f.effect) else {
                continue;
            };
            map_finding(&mut m, kind, fp, d, ctx, &env);
        }
    }
    let Mapped {
        mut values,
        vx,
        mut vy,
        unmapped,
        tips,
        creep,
        sine_phase_rad,
    } = m;
    if let (Some(beta), Some(v)) = (
        sine_phase_rad,
        values.get_mut(&SimParam::SensitivityXNmPerCount),
    ) {
        *v *= beta.sin() / beta;
    }
    if let (Some(chain), Some(h)) = (&creep, ctx.move_history.as_ref()) {
        // The lumped linear scanner of the fit has absorbed the chain's in-phase
        // response to the sweeps (a gain), and a trace/retrace loop found as
        // hysteresis may be the chain's quadrature response: spm-sim's chain adds
        // both again, so the scales and the loop are what remains without them.
        let gain = |period_s: f64| {
            chain
                .response(period_s)
                .map_or(0.0, |(in_phase, _)| in_phase)
        };
        // Fast axis: the sweep is periodic (line period), the in-phase response is
        // a gain. Slow axis: the move history's exact chain response, split like
        // the model splits it (scale, drift, frame offsets, creep columns).
        if let Some(v) = values.get_mut(&SimParam::SensitivityXNmPerCount) {
            *v /= 1.0 + gain(h.line_period_s);
        }
        if let Some([scale, drift]) = slow_axis_absorbed(h, &chain.taus_s, chain.tau_fit_s) {
            if let Some(v) = values.get_mut(&SimParam::SensitivityYNmPerCount) {
                *v /= 1.0 + chain.weight * scale;
            }
            vy -= value(b, "scale_y") * chain.weight * drift;
        }
        if let (Some((_, quadrature)), Some(wf)) = (
            chain.response(h.line_period_s),
            values.get(&SimParam::HysteresisXWidthFraction).copied(),
        ) {
            // A triangle sweep's fundamental is 8/π² of its amplitude: the chain's
            // branch half separation at the centre, as a fraction of the frame half-size.
            let h_chain = quadrature * 8.0 / (std::f64::consts::PI * std::f64::consts::PI);
            let frame_half = d.frame_half_nm.first().copied().unwrap_or([1.0, 1.0]);
            let w_counts = frame_half[0] / n0;
            let h_fit = wf * ctx.half_range_counts / w_counts.max(1e-12);
            let rest = h_fit - h_chain;
            if rest > 0.0 {
                values.insert(
                    SimParam::HysteresisXWidthFraction,
                    rest * w_counts / ctx.half_range_counts,
                );
            } else {
                values.retain(|k, _| !k.is_x_hysteresis());
            }
        }
    }
    values.insert(SimParam::DriftVelocityXNmPerS, vx);
    values.insert(SimParam::DriftVelocityYNmPerS, vy);
    p.values = values;
    p.unmapped = unmapped;
    p.tip_changes = tips;
    p.sine_drive_phase_at_line_end_rad = sine_phase_rad;
    p
}

/// What the findings map to, collected finding by finding.
struct Mapped {
    values: BTreeMap<SimParam, f64>,
    vx: f64,
    vy: f64,
    unmapped: Vec<String>,
    tips: Vec<TipChangeEvent>,
    creep: Option<CreepChain>,
    /// The sine drive's phase at the line end, rad (a scan program, not a config value).
    sine_phase_rad: Option<f64>,
}

impl Mapped {
    fn put(&mut self, key: SimParam, v: f64) {
        self.values.insert(key, v);
    }
}

/// The linear scanner the findings extend and the frame's place in the field.
struct FrameScale<'a> {
    /// The fit's linear parameters (scales, obliquity, rotation, drift).
    linear: &'a BTreeMap<String, crate::ParamValue>,
    /// Frame half-size (x, y), nominal nm.
    frame_half: [f64; 2],
    /// Field half-size over frame half-size along x and y.
    rx: f64,
    ry: f64,
    /// Nominal nm per count.
    n0: f64,
}

/// A periodic vibration's finding as spm-sim's: the model's d = A·cos(ω·t − φ), t from the
/// observation span's middle at `t0_s` on the simulator's clock (φ = atan2(sin part, cos
/// part)); spm-sim's A·cos(ω·T + φ_sim), T its clock.
fn map_vibration(m: &mut Mapped, fp: &BTreeMap<String, crate::ParamValue>, t0_s: f64) {
    let f_hz = value(fp, "frequency_hz").max(0.0);
    let w = std::f64::consts::TAU * f_hz;
    m.put(SimParam::VibrationFrequencyHz, f_hz);
    for (axis, amplitude, phase) in [
        (
            "x",
            SimParam::VibrationAmplitudeXNm,
            SimParam::VibrationPhaseXRad,
        ),
        (
            "y",
            SimParam::VibrationAmplitudeYNm,
            SimParam::VibrationPhaseYRad,
        ),
    ] {
        m.put(amplitude, value(fp, &format!("amplitude_{axis}_nm")).abs());
        m.put(
            phase,
            wrap_rad(-value(fp, &format!("phase_{axis}_rad")) - w * t0_s),
        );
    }
}

/// One finding as spm-sim configuration values (see [`sim_patch`]).
fn map_finding(
    m: &mut Mapped,
    kind: EffectKind,
    fp: &BTreeMap<String, crate::ParamValue>,
    d: &Diagnosis,
    ctx: &SimContext,
    env: &FrameScale<'_>,
) {
    match kind {
        EffectKind::DriftAcceleration => {
            // d(t) = v·t + A·(1 − e^(−t/T)): acceleration −A/T²·e^(−t/T).
            let tau = ctx.warmup_time_constant_s.max(1e-9);
            let t_mid = d.time_origin_s + ctx.time_offset_s;
            let e = (t_mid / tau).exp();
            let ax = value(fp, "acceleration_x_nm_per_s2");
            let ay = value(fp, "acceleration_y_nm_per_s2");
            m.put(SimParam::WarmupTimeConstantS, tau);
            m.put(SimParam::WarmupAmplitudeXNm, -ax * tau * tau * e);
            m.put(SimParam::WarmupAmplitudeYNm, -ay * tau * tau * e);
            m.vx += ax * tau;
            m.vy += ay * tau;
        }
        EffectKind::ScannerNonlinearity => {
            m.put(
                SimParam::NonlinearityXQuadratic,
                value(fp, "quadratic_x") * env.rx,
            );
            m.put(
                SimParam::NonlinearityXCubic,
                value(fp, "cubic_x") * env.rx * env.rx,
            );
            m.put(
                SimParam::NonlinearityYQuadratic,
                value(fp, "quadratic_y") * env.ry,
            );
            m.put(
                SimParam::NonlinearityYCubic,
                value(fp, "cubic_y") * env.ry * env.ry,
            );
        }
        EffectKind::CrosstalkXy => {
            // px += Ky·uy·byx·uy/H ⇒ Δux = (Ky/Kx)·byx·uy²/H.
            let k = value(env.linear, "scale_y") / value(env.linear, "scale_x").max(1e-12);
            m.put(
                SimParam::BowXFromY,
                value(fp, "bow_x_from_y") * (env.frame_half[1] / env.frame_half[0]) * env.ry
                    / k.max(1e-12),
            );
            m.put(
                SimParam::BowYFromX,
                value(fp, "bow_y_from_x") * (env.frame_half[0] / env.frame_half[1]) * env.rx * k,
            );
        }
        EffectKind::FeedbackLag => {
            let tau = value(fp, "time_constant_s").max(0.0);
            let tau_sim = match ctx.pixel_dwell_s {
                Some(dwell) if dwell > 0.0 && tau > 0.0 => {
                    let d = tau / (dwell + tau);
                    -dwell / d.ln()
                }
                _ => tau,
            };
            m.put(SimParam::FeedbackTimeConstantS, tau_sim);
        }
        EffectKind::Hysteresis => {
            let h = value(fp, "branch_half_separation_fraction");
            let w_counts = env.frame_half[0] / env.n0;
            m.put(
                SimParam::HysteresisXWidthFraction,
                (h * w_counts / ctx.half_range_counts).max(0.0),
            );
            m.put(SimParam::HysteresisXMaxThresholdCounts, 0.5 * w_counts);
            m.put(
                SimParam::HysteresisXMinThresholdCounts,
                0.5 * w_counts / 16.0,
            );
            m.put(SimParam::HysteresisXOperators, 16.0);
        }
        EffectKind::TipChange => m.tips.push(TipChangeEvent {
            time_s: value(fp, "time_s") + ctx.time_offset_s,
            jump_x_nm: value(fp, "jump_x_nm"),
            jump_y_nm: value(fp, "jump_y_nm"),
        }),
        EffectKind::Creep => match creep_slope(fp, ctx.move_history.as_ref()) {
            Ok(chain) => {
                m.put(SimParam::CreepLogSlopePerDecade, chain.gamma);
                m.put(SimParam::CreepMinTimeConstantS, CREEP_MIN_TAU_S);
                m.put(SimParam::CreepMaxTimeConstantS, CREEP_MAX_TAU_S);
                m.put(
                    SimParam::CreepElementsPerDecade,
                    f64::from(CREEP_PER_DECADE),
                );
                m.creep = Some(chain);
            }
            Err(why) => m.unmapped.push(format!("creep: {why}")),
        },
        EffectKind::Nonorthogonality => {
            // Model: Δuₓ = gₓ·W·ξₓ·ξ_y = gₓ·uₓ·u_y/H_frame (and Δu_y = g_y·uₓ·u_y/W_frame);
            // spm-sim: Δuₓ = γₓ·uₓ·u_y/H_field ⇒ γₓ = gₓ·H_field/H_frame.
            m.put(
                SimParam::ShearGradientX,
                value(fp, "shear_gradient_x") * env.ry,
            );
            m.put(
                SimParam::ShearGradientY,
                value(fp, "shear_gradient_y") * env.rx,
            );
        }
        EffectKind::PeriodicVibration => map_vibration(m, fp, d.time_origin_s + ctx.time_offset_s),
        // spm-sim's fast-SPM scan program (`Simulator::scan_sine_driven`) takes the phase;
        // its amplitude W/sin β follows from the frame (the sensitivity is rescaled in
        // `sim_patch`).
        EffectKind::SinusoidalDrive => {
            let beta = value(fp, "phase_at_line_end_rad");
            if beta.is_finite() && beta > 0.0 && beta <= std::f64::consts::FRAC_PI_2 {
                m.sine_phase_rad = Some(beta);
            } else {
                m.unmapped.push(format!(
                    "sinusoidal_drive: phase at the line end {beta} rad outside (0, π/2]"
                ));
            }
        }
        EffectKind::Interlace => map_interlace(m, fp, env),
    }
}

/// An interlace finding as spm-sim's stepped or ramped slow axis.
fn map_interlace(m: &mut Mapped, fp: &BTreeMap<String, crate::ParamValue>, env: &FrameScale<'_>) {
    // Model: backward-line features sit `separation_y_nm` further along image y
    // than forward ones (a tip–sample offset −sep/2·s). spm-sim: the second half
    // of every line runs δ counts further along the slow-scan direction, the tip
    // Ky·δ further, so its features appear Ky·δ back; for direct rasters (second
    // half = backward) and counter ones (second half = forward, stepping −y)
    // alike, sep = −Ky·cos α·δ. Ramped (`slow_axis_ramped`): spm-sim's slow axis
    // moves on ρ counts through each line pair, the second half's features sit ρ/2
    // further on the average, so sep = −Ky·cos α·ρ/2.
    let ky = value(env.linear, "scale_y")
        * env.n0
        * value(env.linear, "obliquity_deg").to_radians().cos();
    let sep = value(fp, "separation_y_nm");
    if ky <= 0.0 || !ky.is_finite() {
        m.unmapped
            .push(format!("interlace: slow-axis scale {ky} nm per count"));
    } else if value(fp, "slow_axis_ramped") >= 0.5 {
        m.put(SimParam::SlowAxisRampCounts, -2.0 * sep / ky);
    } else {
        m.put(SimParam::RetraceSlowAxisAdvanceCounts, -sep / ky);
    }
}

/// An angle in (−π, π], rad.
fn wrap_rad(a: f64) -> f64 {
    let tau = std::f64::consts::TAU;
    let r = a.rem_euclid(tau);
    if r > std::f64::consts::PI { r - tau } else { r }
}

/// The offset (nominal nm per unit element weight) of spm-sim's creep chain
/// driven by the piecewise-linear input of `knots` along `axis`, at `times`
/// (sorted): every element follows ṡ = (x − s)/τ exactly (closed form on each
/// linear piece), the offset is Σₖ sₖ.
fn chain_response(knots: &[InputKnot], axis: usize, taus: &[f64], times: &[f64]) -> Vec<f64> {
    let pos = |k: &InputKnot| if axis == 0 { k.x_nm } else { k.y_nm };
    let Some(first) = knots.first() else {
        return vec![0.0; times.len()];
    };
    let mut states = vec![pos(first); taus.len()];
    let mut now = first.time_s;
    let mut piece = 0;
    let mut out = Vec::with_capacity(times.len());
    // Advance the states from `now` to `t` along the current piece (x0 + b·(t − t0)).
    let advance = |states: &mut [f64], now: f64, t: f64, x0: f64, b: f64| {
        let h = t - now;
        if h <= 0.0 {
            return;
        }
        for (s, tau) in states.iter_mut().zip(taus) {
            let e = (-h / tau).exp();
            *s = x0 + b * (h - tau) + (*s - x0 + b * tau) * e;
        }
    };
    let piece_at = |i: usize, now: f64| -> (f64, f64) {
        // Input value at `now` and slope on piece i (held after the last knot).
        match (knots.get(i), knots.get(i + 1)) {
            (Some(a), Some(b)) if b.time_s > a.time_s => {
                let slope = (pos(b) - pos(a)) / (b.time_s - a.time_s);
                (pos(a) + slope * (now - a.time_s), slope)
            }
            (Some(_), Some(b)) => (pos(b), 0.0),
            (Some(a), None) => (pos(a), 0.0),
            _ => (0.0, 0.0),
        }
    };
    for &t in times {
        while let Some(next) = knots.get(piece + 1)
            && next.time_s <= t
        {
            let (x0, b) = piece_at(piece, now);
            advance(&mut states, now, next.time_s, x0, b);
            now = now.max(next.time_s);
            piece += 1;
        }
        let (x0, b) = piece_at(piece, now);
        advance(&mut states, now, t, x0, b);
        now = now.max(t);
        out.push(states.iter().sum());
    }
    out
}

/// The coefficient of `g` in the least-squares fit of `y` by (1, t, g) — the
/// frame offset and the linear drift/scale the model absorbs, and its creep column.
fn lg_coefficient(t: &[f64], g: &[f64], y: &[f64]) -> f64 {
    // Through the kernel's rank-revealing solver, as the model check fits that column: a
    // creep column nearly proportional to t (τ far above the frame) is not an error.
    let columns = [vec![1.0; t.len()], t.to_vec(), g.to_vec()];
    spm_regression::minimum_norm_least_squares(&columns, y, &vec![true; y.len()])
        .map_or(0.0, |fit| fit.coefficients[2])
}

/// spm-sim's creep slope γ (per decade) of the fitted per-frame creep amplitudes
/// (`creep_{x,y}_nm_per_decade_frame{f}`, nominal nm per decade, column
/// lg(1 + t′/τ)): the chain of spm-sim's shape with element weight w answers the
/// move history with an offset whose lg amplitude per frame and axis is w·r_f
/// (r_f: [`chain_response`] projected like the model sees it, [`lg_coefficient`]);
/// w = Σ c·r / Σ r², and γ from spm-sim's w = γ/(m − γ·A).
/// What the model's linear part absorbs of the chain's slow-axis response
/// (unit element weight) to the move history: the least-squares coefficients
/// of the slow-axis input (a scale gain) and of time (a drift, nominal nm/s),
/// next to per-frame offsets and creep columns lg(1 + t′/τ_fit).
fn slow_axis_absorbed(h: &MoveHistory, taus: &[f64], tau_fit_s: f64) -> Option<[f64; 2]> {
    let frames: Vec<[f64; 2]> = h.frames_s.iter().copied().filter(|f| f[1] > f[0]).collect();
    if frames.is_empty() || h.knots.len() < 2 {
        return None;
    }
    let per = 200;
    let mut times = Vec::with_capacity(per * frames.len());
    let mut frame_of = Vec::with_capacity(per * frames.len());
    for (f, [t0, t1]) in frames.iter().enumerate() {
        for i in 0..per {
            times.push(t0 + (t1 - t0) * (i as f64 + 0.5) / per as f64);
            frame_of.push(f);
        }
    }
    let response = chain_response(&h.knots, 1, taus, &times);
    let input = |t: f64| {
        let k = &h.knots;
        let i = k.iter().rposition(|q| q.time_s <= t).unwrap_or(0);
        match (k.get(i), k.get(i + 1)) {
            (Some(a), Some(b)) if b.time_s > a.time_s => {
                a.y_nm + (b.y_nm - a.y_nm) * (t - a.time_s) / (b.time_s - a.time_s)
            }
            (Some(a), _) => a.y_nm,
            _ => 0.0,
        }
    };
    let t_mid = 0.5 * (frames[0][0] + frames[frames.len() - 1][1]);
    let n_cols = 2 + 2 * frames.len();
    let columns: Vec<Vec<f64>> = (0..n_cols)
        .map(|c| {
            times
                .iter()
                .zip(&frame_of)
                .map(|(&t, &f)| match c {
                    0 => input(t),
                    1 => t - t_mid,
                    c if c - 2 < frames.len() => f64::from(u8::from(c - 2 == f)),
                    c => {
                        if c - 2 - frames.len() == f {
                            (1.0 + (t - frames[f][0]) / tau_fit_s).log10()
                        } else {
                            0.0
                        }
                    }
                })
                .collect()
        })
        .collect();
    let coef = spm_regression::minimum_norm_least_squares(
        &columns,
        &response,
        &vec![true; response.len()],
    )
    .ok()?
    .coefficients;
    let (a, b) = (coef[0], coef[1]);
    (a.is_finite() && b.is_finite()).then_some([a, b])
}

/// The creep chain `sim_patch` sets: spm-sim's γ, its element weight w, time constants.
struct CreepChain {
    gamma: f64,
    weight: f64,
    taus_s: Vec<f64>,
    /// The fitted creep column's time constant, s.
    tau_fit_s: f64,
}

impl CreepChain {
    /// (in-phase, quadrature) response of the chain's offset to a sinusoidal
    /// input of period `period_s`, per unit input: Σ w/(1 + (ωτ)²), Σ w·ωτ/(1 + (ωτ)²).
    fn response(&self, period_s: f64) -> Option<(f64, f64)> {
        if !(period_s > 0.0 && period_s.is_finite()) {
            return None;
        }
        let w = std::f64::consts::TAU / period_s;
        Some(self.taus_s.iter().fold((0.0, 0.0), |(p, q), tau| {
            let x = w * tau;
            let d = 1.0 + x * x;
            (p + self.weight / d, q + self.weight * x / d)
        }))
    }
}

fn creep_slope(
    fp: &BTreeMap<String, crate::ParamValue>,
    history: Option<&MoveHistory>,
) -> Result<CreepChain, String> {
    let Some(h) = history else {
        return Err("spm-sim's creep is driven by the move history, and none \
             (SimContext::move_history) was given"
            .to_owned());
    };
    let tau_fit = value(fp, "time_constant_s").max(1e-9);
    let m = f64::from(CREEP_PER_DECADE);
    let decades = (CREEP_MAX_TAU_S / CREEP_MIN_TAU_S).log10();
    let n = (decades * m).round() as usize + 1;
    let taus: Vec<f64> = (0..n)
        .map(|k| CREEP_MIN_TAU_S * 10f64.powf(k as f64 / m))
        .collect();
    let (mut num, mut den) = (0.0, 0.0);
    for (f, &[t0, t1]) in h.frames_s.iter().enumerate() {
        if t1.partial_cmp(&t0) != Some(std::cmp::Ordering::Greater) {
            continue;
        }
        let times: Vec<f64> = (0..400)
            .map(|i| t0 + (t1 - t0) * (i as f64 + 0.5) / 400.0)
            .collect();
        let rel: Vec<f64> = times.iter().map(|t| t - t0).collect();
        let g: Vec<f64> = rel.iter().map(|t| (1.0 + t / tau_fit).log10()).collect();
        for (a, axis) in ["x", "y"].iter().enumerate() {
            let Some(c) = fp.get(&format!("creep_{axis}_nm_per_decade_frame{f}")) else {
                continue;
            };
            let y = chain_response(&h.knots, a, &taus, &times);
            let r = lg_coefficient(&rel, &g, &y);
            num += c.value * r;
            den += r * r;
        }
    }
    if den.is_nan() || den <= 0.0 {
        return Err("the move history does not drive creep in the frames".to_owned());
    }
    let w = num / den;
    let a: f64 = taus.iter().map(|t| 1.0 - (-0.1 / t).exp()).sum();
    let gamma = w * m / (1.0 + w * a);
    if !(gamma.is_finite() && gamma > 0.0) {
        return Err(format!(
            "the fitted creep runs against the move history (γ = {gamma:.4} per decade)"
        ));
    }
    let gamma = gamma.min(0.1);
    Ok(CreepChain {
        gamma,
        weight: gamma / (m - gamma * a),
        taus_s: taus,
        tau_fit_s: tau_fit,
    })
}

impl SimPatch {
    /// Merges the values into a full spm-sim config (TOML text) and returns the new text.
    pub fn apply_to_toml(&self, base: &str) -> Result<String, ModelCheckError> {
        let bad = |e: String| ModelCheckError::InvalidInput(format!("spm-sim config: {e}"));
        let mut root: toml::Table = base
            .parse()
            .map_err(|e: toml::de::Error| bad(e.to_string()))?;
        for (param, v) in &self.values {
            let path = param.path();
            let parts: Vec<&str> = path.split('.').collect();
            let Some((last, dirs)) = parts.split_last() else {
                continue;
            };
            let mut table = &mut root;
            for part in dirs {
                let key = if *part == "*" {
                    // The single sub-table (e.g. the surface kind).
                    match table.keys().next() {
                        Some(k) => k.clone(),
                        None => return Err(bad(format!("{path}: no table for *"))),
                    }
                } else {
                    (*part).to_owned()
                };
                table = table
                    .entry(key)
                    .or_insert_with(|| toml::Value::Table(toml::Table::new()))
                    .as_table_mut()
                    .ok_or_else(|| bad(format!("{path}: {part} is not a table")))?;
            }
            let value = match table.get(*last) {
                Some(toml::Value::Integer(_)) => toml::Value::Integer(v.round() as i64),
                _ => toml::Value::Float(*v),
            };
            table.insert((*last).to_owned(), value);
        }
        toml::to_string(&root).map_err(|e| bad(e.to_string()))
    }

    /// The values as TOML text (nested tables), for reports.
    pub fn to_toml(&self) -> String {
        self.apply_to_toml("").unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn knot(time_s: f64, x_nm: f64, y_nm: f64) -> InputKnot {
        InputKnot { time_s, x_nm, y_nm }
    }

    #[test]
    fn the_chain_follows_a_step_and_a_ramp_in_closed_form() {
        let taus = [0.1, 1.0, 10.0];
        // A step of 5 nm at t = 0 (a zero-length piece), then held.
        let step = [
            knot(-1.0, 0.0, 0.0),
            knot(0.0, 0.0, 0.0),
            knot(0.0, 5.0, 0.0),
        ];
        let times = [0.05, 0.5, 3.0, 30.0];
        let got = chain_response(&step, 0, &taus, &times);
        for (t, g) in times.iter().zip(&got) {
            let expected: f64 = taus.iter().map(|tau| 5.0 * (1.0 - (-t / tau).exp())).sum();
            assert!((g - expected).abs() < 1e-12, "t {t}: {g} vs {expected}");
        }
        // A ramp y = 2·t from rest: s(t) = 2·(t − τ·(1 − e^(−t/τ))).
        let ramp = [knot(0.0, 0.0, 0.0), knot(100.0, 0.0, 200.0)];
        let got = chain_response(&ramp, 1, &taus, &times);
        for (t, g) in times.iter().zip(&got) {
            let expected: f64 = taus
                .iter()
                .map(|tau| 2.0 * (t - tau * (1.0 - (-t / tau).exp())))
                .sum();
            assert!((g - expected).abs() < 1e-9, "t {t}: {g} vs {expected}");
        }
    }

    #[test]
    fn the_lg_coefficient_recovers_a_synthetic_amplitude() {
        let t: Vec<f64> = (0..300).map(|i| 0.1 * f64::from(i)).collect();
        let g: Vec<f64> = t.iter().map(|t| (1.0 + t / 0.5).log10()).collect();
        let y: Vec<f64> = t
            .iter()
            .zip(&g)
            .map(|(t, g)| 3.0 - 0.2 * t + 1.7 * g)
            .collect();
        assert!((lg_coefficient(&t, &g, &y) - 1.7).abs() < 1e-9);
    }

    #[test]
    fn angles_wrap_into_minus_pi_to_pi() {
        for (a, w) in [
            (0.5, 0.5),
            (7.0, 7.0 - std::f64::consts::TAU),
            (-4.0, -4.0 + std::f64::consts::TAU),
        ] {
            assert!((wrap_rad(a) - w).abs() < 1e-12);
        }
    }
}
