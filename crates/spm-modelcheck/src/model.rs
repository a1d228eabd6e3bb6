//! The model: design columns of the baseline and of every effect, and the
//! linear least-squares solver.
//!
//! Every observation k gives two equations (x and y) in the lattice frame:
//!
//! ```text
//! R_k = J·u_k + v·(t_k − t̄) + c_frame + Σ_e J₀·Δu_e(k) + Σ_e Rot(θ₀)·d_e(k)
//! ```
//!
//! `R_k` is the true site (nm), `u_k` the commanded position (nominal nm), `J`
//! the lumped linear scanner (scales, obliquity, rotation: 4 numbers), `v` the
//! constant drift, `c` the per-frame offsets. Scanner effects add a
//! displacement `Δu_e` of the *input* (nominal nm, mapped by the baseline
//! `J₀`); tip–sample effects add a displacement `d_e` in the image axes
//! (mapped by the baseline rotation `θ₀`). All are linear in their
//! amplitudes; a few effects have one nonlinear hyper-parameter (a creep time
//! constant, a vibration frequency, a tip-change time) found by a search.

use crate::types::{EffectKind, FeatureSet, FrameInfo, LineDirection, ModelCheckError};
use nalgebra::DMatrix;

/// One indexed observation with everything the columns need.
#[derive(Clone, Debug)]
pub(crate) struct Obs {
    pub u: [f64; 2],
    pub site: [f64; 2],
    /// Time relative to the middle of the observation span, s.
    pub t: f64,
    /// Time since the start of its frame, s.
    pub t_frame: f64,
    /// +1 forward, −1 backward.
    pub s: f64,
    pub frame: usize,
    pub line: usize,
    pub direction: LineDirection,
    /// Position normalised by the frame half-size.
    pub xi: [f64; 2],
    /// Frame half-size, nominal nm.
    pub half: [f64; 2],
    /// Fast-axis speed, nominal nm/s.
    pub speed: f64,
    /// Sub-pixel phase (x, y) of the feature in its image, in [0, 1) (0 = on a
    /// pixel centre), and the pixel pitch, nominal nm; `None` without a grid.
    pub phase: Option<([f64; 2], [f64; 2])>,
    /// The feature's footprint over lines: (Gaussian width σ, fit-window
    /// radius) in lines, and the line period, s; `None` when unknown.
    pub footprint: Option<(f64, f64, f64)>,
    /// Time from the nearest line's pass at the feature's column to the feature's time, s.
    pub line_offset_s: f64,
}

/// The context effect columns need: baseline J₀ and rotation θ₀.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Ctx {
    pub j0: [[f64; 2]; 2],
    pub theta0: f64,
}

/// A column: the x and y contributions of one parameter for every observation,
/// interleaved `[x₀, y₀, x₁, y₁, …]`.
pub(crate) type Column = Vec<f64>;

pub(crate) fn baseline_columns(obs: &[Obs], n_frames: usize) -> Vec<Column> {
    let n = obs.len();
    let mut cols = vec![vec![0.0; 2 * n]; 6 + 2 * n_frames];
    for (k, o) in obs.iter().enumerate() {
        cols[0][2 * k] = o.u[0];
        cols[1][2 * k] = o.u[1];
        cols[2][2 * k + 1] = o.u[0];
        cols[3][2 * k + 1] = o.u[1];
        cols[4][2 * k] = o.t;
        cols[5][2 * k + 1] = o.t;
        cols[6 + 2 * o.frame][2 * k] = 1.0;
        cols[7 + 2 * o.frame][2 * k + 1] = 1.0;
    }
    cols
}

/// An input-space column: Δu along `axis` by `f(o)`, mapped by J₀.
fn input_col(obs: &[Obs], ctx: &Ctx, axis: usize, f: impl Fn(&Obs) -> f64) -> Column {
    let mut c = vec![0.0; 2 * obs.len()];
    for (k, o) in obs.iter().enumerate() {
        let v = f(o);
        c[2 * k] = ctx.j0[0][axis] * v;
        c[2 * k + 1] = ctx.j0[1][axis] * v;
    }
    c
}

/// A sample-space column: displacement along image `axis` by `f(o)`, rotated by θ₀.
fn sample_col(obs: &[Obs], ctx: &Ctx, axis: usize, f: impl Fn(&Obs) -> f64) -> Column {
    let (s, c0) = ctx.theta0.sin_cos();
    let dir = if axis == 0 { [c0, s] } else { [-s, c0] };
    let mut c = vec![0.0; 2 * obs.len()];
    for (k, o) in obs.iter().enumerate() {
        let v = f(o);
        c[2 * k] = dir[0] * v;
        c[2 * k + 1] = dir[1] * v;
    }
    c
}

/// The value a feature's fitted position sees of a time-dependent tip–sample
/// displacement `f(t)` along image `axis` (0 = fast, 1 = slow).
///
/// A feature spans several lines, so its position averages whatever moved
/// during them. A Gaussian fit weighs line l (offset l lines from the centre,
/// within the fit window of radius R) by g(l)²·c(l) for the fast-axis
/// position and by l²·g(l)²·c(l) for the slow-axis position (g the profile of
/// width σ, c the window's chord): the seen displacement is
/// Σ w(l)·f(t + l·P) / Σ w(l), P the line period. For a vibration cos ωt
/// this attenuates the amplitude (strongly along the slow axis); a jump is
/// seen partly by the features scanned across it. Without a known footprint
/// (feature lists), f(t).
pub(crate) fn footprint_average(o: &Obs, axis: usize, f: impl Fn(f64) -> f64) -> f64 {
    let Some((sigma, radius, period)) = o.footprint else {
        return f(o.t);
    };
    // The lines are sampled at their own times: the nearest one passed the feature's
    // column `line_offset_s` before the feature's (fractional-row) time.
    let offset_lines = if period > 0.0 {
        o.line_offset_s / period
    } else {
        0.0
    };
    let t_nearest = o.t - o.line_offset_s;
    let n = radius.floor() as i64 + 1;
    let (mut sum, mut weight) = (0.0, 0.0);
    for m in -n..=n {
        let l = m as f64 - offset_lines;
        if l.abs() > radius {
            continue;
        }
        let chord = 2.0 * (radius * radius - l * l).max(0.0).sqrt() + 1.0;
        let g2 = (-(l * l) / (sigma * sigma).max(1e-12)).exp() * chord;
        let w = if axis == 0 { g2 } else { l * l * g2 };
        sum += w * f(t_nearest + m as f64 * period);
        weight += w;
    }
    if weight > 0.0 { sum / weight } else { f(o.t) }
}

/// The attenuation of a vibration of angular frequency `w_rad_per_s` (rad/s) within one
/// line of a feature's footprint, along image `axis` (0 = fast, 1 = slow).
///
/// Along its line the fit window spans a few pixels, scanned one dwell apart: a vibration
/// of several tens of cycles per line (hundreds of Hz) changes within it. A Gaussian fit
/// weighs column offset c (pixels) by c²·g(c)² for the fast-axis position and by g(c)²
/// for the slow-axis one (g(c)² = e^{−c²/σ²}); with a symmetric window the phase of the
/// line's centre is kept and the amplitude is multiplied by
/// Σ w(c)·cos(ω·c·τ) / Σ w(c), τ the dwell. 1 without a pixel grid or footprint, and for
/// vibrations slow against the dwell (the feature-level columns of [`footprint_average`]).
pub(crate) fn along_line_attenuation(o: &Obs, axis: usize, w_rad_per_s: f64) -> f64 {
    let (Some((sigma, radius, _)), Some((_, pitch))) = (o.footprint, o.phase) else {
        return 1.0;
    };
    if !(pitch[0] > 0.0 && o.speed > 0.0) {
        return 1.0;
    }
    let aspect = pitch[1] / pitch[0];
    let (sigma_px, radius_px) = (sigma * aspect, radius * aspect);
    let dwell_s = pitch[0] / o.speed;
    let n = radius_px.floor() as i64;
    let (mut sum, mut weight) = (0.0, 0.0);
    for c in -n..=n {
        let c = c as f64;
        let g2 = (-(c * c) / (sigma_px * sigma_px).max(1e-12)).exp();
        let wgt = if axis == 0 { c * c * g2 } else { g2 };
        sum += wgt * (w_rad_per_s * c * dwell_s).cos();
        weight += wgt;
    }
    if weight > 0.0 { sum / weight } else { 1.0 }
}

/// Names of the pixel-locking columns, in column order (nominal nm).
pub(crate) const PIXEL_LOCKING_NAMES: [&str; 4] = [
    "pixel_locking_x_sin1_nm",
    "pixel_locking_x_sin2_nm",
    "pixel_locking_y_sin1_nm",
    "pixel_locking_y_sin2_nm",
];

/// The localiser's pixel-locking bias: a fit of a peak sampled on a pixel
/// grid is pulled towards (or away from) pixel centres by an amount that is a
/// periodic, odd function of the sub-pixel phase φ (zero on a pixel centre and
/// half-way between two, by symmetry): b(φ) = s₁·sin 2πφ + s₂·sin 4πφ per
/// axis. On a lattice, φ of successive rows changes slowly (the beat of the
/// lattice period against the pixel pitch), and row is time along the slow
/// axis: the bias looks like a slow "vibration" unless modelled. `None` when
/// the features carry no pixel grid.
pub(crate) fn pixel_locking_columns(obs: &[Obs], ctx: &Ctx) -> Option<Vec<Column>> {
    if obs.iter().any(|o| o.phase.is_none()) {
        return None;
    }
    let tau = 2.0 * std::f64::consts::PI;
    let ph = |o: &Obs, axis: usize, k: f64| o.phase.map_or(0.0, |(p, _)| (k * tau * p[axis]).sin());
    Some(vec![
        input_col(obs, ctx, 0, |o| ph(o, 0, 1.0)),
        input_col(obs, ctx, 0, |o| ph(o, 0, 2.0)),
        input_col(obs, ctx, 1, |o| ph(o, 1, 1.0)),
        input_col(obs, ctx, 1, |o| ph(o, 1, 2.0)),
    ])
}

/// The polynomial degree of the nonlinearity for a hyper-parameter value (3 by default).
pub(crate) fn nonlinearity_degree(hyper: f64) -> usize {
    if hyper.is_finite() && hyper >= 3.0 {
        (hyper.round() as usize).min(15)
    } else {
        3
    }
}

/// Parameter names of the nonlinearity of a degree, in column order.
pub(crate) fn nonlinearity_names(degree: usize) -> Vec<String> {
    let mut names = Vec::new();
    for axis in ["x", "y"] {
        for k in 2..=degree {
            let order = match k {
                2 => "quadratic".to_owned(),
                3 => "cubic".to_owned(),
                k => format!("order{k}"),
            };
            names.push(format!("{order}_{axis}"));
        }
    }
    names
}

/// Names (with units) of an effect's linear parameters, in column order.
pub(crate) fn param_names(kind: EffectKind) -> &'static [&'static str] {
    match kind {
        EffectKind::DriftAcceleration => &["acceleration_x_nm_per_s2", "acceleration_y_nm_per_s2"],
        EffectKind::Creep => &["creep_x_nm_per_decade", "creep_y_nm_per_decade"],
        EffectKind::Hysteresis => &["branch_half_separation_fraction", "loop_shape"],
        EffectKind::ScannerNonlinearity => &["quadratic_x", "cubic_x", "quadratic_y", "cubic_y"],
        EffectKind::Nonorthogonality => &["shear_gradient_x", "shear_gradient_y"],
        EffectKind::CrosstalkXy => &["bow_x_from_y", "bow_y_from_x"],
        EffectKind::FeedbackLag => &["time_constant_s"],
        EffectKind::PeriodicVibration => &["x_cos_nm", "x_sin_nm", "y_cos_nm", "y_sin_nm"],
        EffectKind::TipChange => &["jump_x_nm", "jump_y_nm"],
        EffectKind::Interlace => &["separation_y_nm"],
        EffectKind::SinusoidalDrive => &["sine_weight"],
    }
}

/// Name (with unit) of an effect's hyper-parameter, if it has one.
pub(crate) fn hyper_name(kind: EffectKind) -> Option<&'static str> {
    match kind {
        EffectKind::Creep => Some("time_constant_s"),
        EffectKind::PeriodicVibration => Some("frequency_hz"),
        EffectKind::TipChange => Some("time_s"),
        EffectKind::SinusoidalDrive => Some("phase_at_line_end_rad"),
        EffectKind::Interlace => Some("slow_axis_ramped"),
        _ => None,
    }
}

/// Whether an effect can be told apart from the baseline with these data.
pub(crate) fn identifiable(kind: EffectKind, obs: &[Obs]) -> bool {
    let both = obs.iter().any(|o| o.s > 0.0) && obs.iter().any(|o| o.s < 0.0);
    match kind {
        EffectKind::Hysteresis | EffectKind::FeedbackLag | EffectKind::Interlace => both,
        // In one direction of one frame the time is a fixed function of the
        // position: a "vibration" is then any periodic function of position
        // (a localiser or levelling bias that follows the lattice, a
        // periodic distortion) and cannot be told from one. Only a second
        // pass over the same places at other times (the other direction,
        // another frame) makes it a function of time.
        EffectKind::PeriodicVibration => {
            let mut groups: Vec<(usize, LineDirection)> = Vec::new();
            for o in obs {
                if !groups.contains(&(o.frame, o.direction)) {
                    groups.push((o.frame, o.direction));
                }
            }
            groups.len() >= 2
        }
        _ => true,
    }
}

/// The columns of an effect for a hyper-parameter value (ignored when it has none).
pub(crate) fn effect_columns(kind: EffectKind, hyper: f64, obs: &[Obs], ctx: &Ctx) -> Vec<Column> {
    match kind {
        EffectKind::DriftAcceleration => vec![
            sample_col(obs, ctx, 0, |o| 0.5 * o.t * o.t),
            sample_col(obs, ctx, 1, |o| 0.5 * o.t * o.t),
        ],
        EffectKind::Creep => {
            // Per frame: the amplitude depends on the move before the frame.
            let tau = hyper.max(1e-9);
            let n_frames = obs.iter().map(|o| o.frame + 1).max().unwrap_or(0);
            (0..n_frames)
                .flat_map(|f| {
                    let g = move |o: &Obs| {
                        if o.frame == f {
                            (1.0 + o.t_frame.max(0.0) / tau).log10()
                        } else {
                            0.0
                        }
                    };
                    [input_col(obs, ctx, 0, g), input_col(obs, ctx, 1, g)]
                })
                .collect()
        }
        EffectKind::Hysteresis => vec![
            input_col(obs, ctx, 0, |o| {
                -o.s * o.half[0] * (1.0 - o.xi[0] * o.xi[0])
            }),
            input_col(obs, ctx, 0, |o| {
                -o.s * o.half[0] * (1.0 - o.xi[0] * o.xi[0]) * o.xi[0] * o.xi[0]
            }),
        ],
        EffectKind::ScannerNonlinearity => {
            // Polynomial of degree `hyper` (3 unless raised): a strong map
            // that is not a cubic (a sinusoidal fast-axis drive with pixels
            // equidistant in time) needs higher orders to be followed.
            let degree = nonlinearity_degree(hyper);
            let mut cols = Vec::with_capacity(2 * (degree - 1));
            for axis in 0..2 {
                for k in 2..=degree {
                    cols.push(input_col(obs, ctx, axis, |o| {
                        o.half[axis] * o.xi[axis].powi(k as i32)
                    }));
                }
            }
            cols
        }
        EffectKind::Nonorthogonality => vec![
            input_col(obs, ctx, 0, |o| o.half[0] * o.xi[0] * o.xi[1]),
            input_col(obs, ctx, 1, |o| o.half[1] * o.xi[0] * o.xi[1]),
        ],
        EffectKind::CrosstalkXy => vec![
            input_col(obs, ctx, 0, |o| o.half[1] * o.xi[1] * o.xi[1]),
            input_col(obs, ctx, 1, |o| o.half[0] * o.xi[0] * o.xi[0]),
        ],
        EffectKind::FeedbackLag => vec![input_col(obs, ctx, 0, |o| -o.s * o.speed)],
        EffectKind::PeriodicVibration => {
            let w = 2.0 * std::f64::consts::PI * hyper;
            let seen = |o: &Obs, axis: usize, f: fn(f64) -> f64| {
                along_line_attenuation(o, axis, w) * footprint_average(o, axis, |t| f(w * t))
            };
            vec![
                sample_col(obs, ctx, 0, |o| seen(o, 0, f64::cos)),
                sample_col(obs, ctx, 0, |o| seen(o, 0, f64::sin)),
                sample_col(obs, ctx, 1, |o| seen(o, 1, f64::cos)),
                sample_col(obs, ctx, 1, |o| seen(o, 1, f64::sin)),
            ]
        }
        // Features of backward lines appear displaced along the slow axis by
        // `separation_y_nm` relative to forward ones: a feature at R is seen
        // where J·u + d = R, so the tip–sample displacement d is +s/2 times
        // the separation (forward +½, backward −½).
        //
        // Ramped (`hyper` ≥ ½): the slow axis moves on *through* every line, one line pitch
        // per trace + retrace, instead of stepping between lines (measured on the Si 7×7
        // pair, docs/MODELCHECK.md). A feature then sits further along the slow scan by
        // the advance times its time within its line pair: (1 + s·ξ)/4 in the half that
        // runs first, ½ + (1 − s·ξ)/4 in the second — less ½, s·(ξ − o)/4 with o = ±1 as
        // the forward or the backward half runs first, along the frame's slow direction.
        // Its forward − backward mean is −½·slow·o per unit advance; the column is scaled
        // so that its coefficient is, as for the stepped shape, `separation_y_nm` (the mean
        // separation in the first frame; the advance per line pair is twice its size).
        EffectKind::Interlace if hyper >= 0.5 => {
            let order = pair_order(obs);
            let (first0, slow0) = order.first().copied().unwrap_or((1.0, 1.0));
            vec![sample_col(obs, ctx, 1, |o| {
                let (first, slow) = order.get(o.frame).copied().unwrap_or((1.0, 1.0));
                -0.5 * first0 * slow0 * slow * o.s * (o.xi[0] - first)
            })]
        }
        EffectKind::Interlace => vec![sample_col(obs, ctx, 1, |o| 0.5 * o.s)],
        // The fast axis's input W·ξ becomes W·[ξ + κ·(sin βξ − βξ)/β]: a pure sine drive
        // (κ = 1) over ±β of phase about the line centre (see `sine_drive_departure`).
        EffectKind::SinusoidalDrive => vec![input_col(obs, ctx, 0, |o| {
            o.half[0] * sine_drive_departure(o.xi[0], hyper)
        })],
        EffectKind::TipChange => {
            let step = |t: f64| if t >= hyper { 1.0 } else { 0.0 };
            vec![
                sample_col(obs, ctx, 0, |o| footprint_average(o, 0, step)),
                sample_col(obs, ctx, 1, |o| footprint_average(o, 1, step)),
            ]
        }
    }
}

/// Per frame: which half of a line pair runs first (+1 forward, −1 backward) and which
/// way the slow axis runs (+1 towards +y, −1 towards −y), from the features' times: within
/// a line the half that runs first is earlier, and the lines advance in time along the
/// slow direction. A frame with one direction only gets (+1, sign).
pub(crate) fn pair_order(obs: &[Obs]) -> Vec<(f64, f64)> {
    let n_frames = obs.iter().map(|o| o.frame + 1).max().unwrap_or(0);
    (0..n_frames)
        .map(|f| {
            let of: Vec<&Obs> = obs.iter().filter(|o| o.frame == f).collect();
            // t = a + b·line + c·s over the frame (lines are numbered in acquisition
            // order): c < 0 when the forward half is the earlier; and t = a′ + b′·y, b′ < 0
            // when the lines run towards −y.
            let fit = |columns: Vec<Vec<f64>>| {
                let t: Vec<f64> = of.iter().map(|o| o.t_frame).collect();
                spm_regression::minimum_norm_least_squares(&columns, &t, &vec![true; t.len()])
                    .ok()
                    .and_then(|fit| fit.coefficients.get(1).copied())
            };
            let ones = vec![1.0; of.len()];
            let both = of.iter().any(|o| o.s > 0.0) && of.iter().any(|o| o.s < 0.0);
            let first = if !both {
                1.0
            } else {
                fit(vec![
                    ones.clone(),
                    of.iter().map(|o| o.s).collect(),
                    of.iter().map(|o| o.line as f64).collect(),
                ])
                .map_or(1.0, |c| if c <= 0.0 { 1.0 } else { -1.0 })
            };
            let slow = fit(vec![ones, of.iter().map(|o| o.u[1]).collect()])
                .map_or(1.0, |b| if b < 0.0 { -1.0 } else { 1.0 });
            (first, slow)
        })
        .collect()
}

/// Hyper-parameter candidates for an effect from the current residuals, and the
/// number of independent trials they stand for (the look-elsewhere count).
pub(crate) fn hyper_candidates(
    kind: EffectKind,
    obs: &[Obs],
    frames: &[FrameInfo],
    residual: &[f64],
    mask: &[bool],
) -> (Vec<f64>, f64) {
    match kind {
        EffectKind::Creep => {
            let t_frame = frames
                .iter()
                .map(|f| f.duration_s)
                .fold(0.0_f64, f64::max)
                .max(1e-6);
            let grid: Vec<f64> = [0.001, 0.003, 0.01, 0.03, 0.1, 0.3]
                .iter()
                .map(|r| r * t_frame)
                .collect();
            let m = grid.len() as f64;
            (grid, m)
        }
        EffectKind::PeriodicVibration => vibration_candidates(
            obs,
            residual,
            mask,
            frames.iter().map(|f| f.duration_s).fold(0.0, f64::max),
            &frames
                .iter()
                .filter(|f| f.duration_s > 0.0 && f.lines > 0)
                .map(|f| f.lines as f64 / f.duration_s)
                .collect::<Vec<_>>(),
        ),
        EffectKind::TipChange => tip_change_candidates(obs, frames, residual, mask),
        // β on a grid; `refine_sine_phase` then finds the best β between grid points.
        // The look-elsewhere count: β is one smooth parameter whose effect is told apart
        // from a cubic only through its higher orders, a few independent trials.
        EffectKind::SinusoidalDrive => (
            (0..SINE_GRID_POINTS)
                .map(|i| SINE_PHASE_MIN_RAD + i as f64 * SINE_PHASE_STEP_RAD)
                .collect(),
            4.0,
        ),
        // Stepped (0) or ramped (1) slow axis: two shapes, one trial each.
        EffectKind::Interlace => (vec![0.0, 1.0], 2.0),
        _ => (vec![0.0], 1.0),
    }
}

/// The sinusoidal drive's phase grid: β from 0.1 rad (a drive indistinguishable from a
/// small cubic) to 1.55 rad (just short of the turnaround at π/2, where the pixels at the
/// line ends stop moving and no feature there can be localised), in 0.05 rad steps.
pub(crate) const SINE_PHASE_MIN_RAD: f64 = 0.1;
/// Step of the β grid, rad.
pub(crate) const SINE_PHASE_STEP_RAD: f64 = 0.05;
/// Points of the β grid.
pub(crate) const SINE_GRID_POINTS: usize = 30;

/// The departure from a straight line of a sinusoidally driven fast axis, in units of the
/// frame's half-width W, at the normalised commanded position ξ = u/W.
///
/// Physics. A fast-SPM (resonant) scanner drives the fast axis by x(t) = A·sin(ω(t − t₀)),
/// ω = 2π·f_drive, and records the pixels equidistant in time; a line of duration T_line
/// centred on the zero crossing t₀ covers the phase ω(t − t₀) ∈ [−β, β] with
/// β = π·f_drive·T_line (β = π/2 when a line is a whole half-period, as in pyfastspm's
/// movies). The file's nominal position is linear in time, u = W·ξ with
/// ξ = 2(t − t₀)/T_line ∈ [−1, 1] (trace; the retrace runs the second half-period,
/// x = −A·sin(ω(t − t₀′)) with ξ = −2(t − t₀′)/T_line, the same map), so the true position
/// is x = A·sin(βξ). Written about the linear scanner, whose lumped scale J absorbs the
/// slope at the centre, x = (A·β/W)·W·[ξ + (sin βξ − βξ)/β]: the input departs from
/// the nominal W·ξ by W·(sin βξ − βξ)/β, which this returns divided by W. Its Taylor
/// series is −β²ξ³/6 + β⁴ξ⁵/120 − …: the cubic of spmcal's polynomial (−β²/6 at the
/// frame edge) with every higher order fixed by the one phase β. The amplitude in the
/// sample is A = |J·e_x|·W/β (nm), the drive frequency f = β/(π·T_line) (Hz).
pub(crate) fn sine_drive_departure(xi: f64, beta_rad: f64) -> f64 {
    if beta_rad.abs() < 1e-6 {
        return 0.0;
    }
    ((beta_rad * xi).sin() - beta_rad * xi) / beta_rad
}

fn vibration_candidates(
    obs: &[Obs],
    residual: &[f64],
    mask: &[bool],
    longest_frame_s: f64,
    line_frequencies_hz: &[f64],
) -> (Vec<f64>, f64) {
    let idx: Vec<usize> = (0..obs.len()).filter(|&k| mask[k]).collect();
    if idx.len() < 10 {
        return (Vec::new(), 1.0);
    }
    let mut times: Vec<f64> = idx.iter().map(|&k| obs[k].t).collect();
    times.sort_by(f64::total_cmp);
    let span = times[times.len() - 1] - times[0];
    let mut gaps: Vec<f64> = times
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|d| *d > 0.0)
        .collect();
    let Some(gap) = spm_regression::upper_median(&mut gaps) else {
        return (Vec::new(), 1.0);
    };
    if !(span > 0.0 && gap > 0.0) {
        return (Vec::new(), 1.0);
    }
    // A "vibration" must complete two cycles within a frame; slower motion is
    // drift variation (drift_acceleration, creep), not vibration.
    let f_min = (1.5 / span).max(2.0 / longest_frame_s.max(1e-9));
    let f_max = 0.5 / gap;
    if f_max <= f_min {
        return (Vec::new(), 1.0);
    }
    let trials = ((f_max - f_min) * span).max(1.0);
    let n_grid_min = 16;
    let n_grid = ((4.0 * trials) as usize).clamp(n_grid_min, 6000);
    let df = (f_max - f_min) / n_grid as f64;
    // The periodogram of the residual's x and y on the grid f_min + g·df. Each
    // observation's phasor e^{iωt} advances from one grid frequency to the next by one
    // rotation e^{i·2π·df·t}, restarted exactly (a sin_cos) every `RESYNC` points: the
    // rounding of the rotations stays below 64 ulp, and the sums cost four products and
    // one rotation per point instead of a sin_cos (the search took 39 % of a diagnosis).
    const RESYNC: usize = 64;
    let points = n_grid + 1;
    let (mut xc, mut xs, mut yc, mut ys) = (
        vec![0.0; points],
        vec![0.0; points],
        vec![0.0; points],
        vec![0.0; points],
    );
    for &k in &idx {
        let t = obs[k].t;
        let (rx, ry) = (residual[2 * k], residual[2 * k + 1]);
        let (ds, dc) = (2.0 * std::f64::consts::PI * df * t).sin_cos();
        for block in (0..points).step_by(RESYNC) {
            let f = f_min + block as f64 * df;
            let (mut s, mut c) = (2.0 * std::f64::consts::PI * f * t).sin_cos();
            for g in block..(block + RESYNC).min(points) {
                xc[g] += rx * c;
                xs[g] += rx * s;
                yc[g] += ry * c;
                ys[g] += ry * s;
                (s, c) = (s * dc + c * ds, c * dc - s * ds);
            }
        }
    }
    let mut power: Vec<(f64, f64)> = Vec::with_capacity(points);
    for g in 0..points {
        let f = f_min + g as f64 * df;
        // Harmonics of the line frequency are scan-synchronous: a "vibration"
        // there cannot be told from trace/retrace effects (hysteresis, lag).
        let synchronous = line_frequencies_hz.iter().any(|fl| {
            let k = (f / fl).round();
            k >= 1.0 && (f - k * fl).abs() < 2.0 / span
        });
        if synchronous {
            continue;
        }
        power.push((
            f,
            xc[g] * xc[g] + xs[g] * xs[g] + yc[g] * yc[g] + ys[g] * ys[g],
        ));
    }
    // The three highest local maxima.
    let mut peaks: Vec<(f64, f64)> = (0..power.len())
        .filter(|&i| {
            let p = power[i].1;
            (i == 0 || power[i - 1].1 <= p) && (i + 1 == power.len() || power[i + 1].1 <= p)
        })
        .map(|i| power[i])
        .collect();
    peaks.sort_by(|a, b| b.1.total_cmp(&a.1));
    // Each of the three highest peaks refined on a sub-grid of ±1 grid step.
    let cands = peaks
        .iter()
        .take(3)
        .flat_map(|p| (-4..=4).map(move |i| p.0 + i as f64 * df / 4.0))
        .filter(|f| *f > 0.0)
        .collect();
    (cands, trials)
}

fn tip_change_candidates(
    obs: &[Obs],
    frames: &[FrameInfo],
    residual: &[f64],
    mask: &[bool],
) -> (Vec<f64>, f64) {
    let mut scored: Vec<(f64, f64)> = Vec::new();
    let mut trials: f64 = 0.0;
    for (f, frame) in frames.iter().enumerate() {
        let mut in_frame: Vec<usize> = (0..obs.len())
            .filter(|&k| mask[k] && obs[k].frame == f)
            .collect();
        if in_frame.len() < 8 {
            continue;
        }
        in_frame.sort_by(|&a, &b| obs[a].t.total_cmp(&obs[b].t));
        let total = in_frame.iter().fold([0.0, 0.0], |acc, &k| {
            [acc[0] + residual[2 * k], acc[1] + residual[2 * k + 1]]
        });
        let n = in_frame.len() as f64;
        let mut left = [0.0, 0.0];
        let min_lines = 3.max(frame.lines / 20);
        for (m, &k) in in_frame.iter().enumerate() {
            left[0] += residual[2 * k];
            left[1] += residual[2 * k + 1];
            let Some(&next) = in_frame.get(m + 1) else {
                break;
            };
            // Only between lines, away from the frame's first and last lines.
            if obs[next].line == obs[k].line
                || obs[next].line < min_lines
                || obs[next].line + min_lines > frame.lines
            {
                continue;
            }
            trials += 1.0;
            let n1 = (m + 1) as f64;
            let n2 = n - n1;
            let d = [
                left[0] / n1 - (total[0] - left[0]) / n2,
                left[1] / n1 - (total[1] - left[1]) / n2,
            ];
            let score = n1 * n2 / n * (d[0] * d[0] + d[1] * d[1]);
            scored.push((0.5 * (obs[k].t + obs[next].t), score));
        }
    }
    scored.sort_by(|a, b| b.1.total_cmp(&a.1));
    (
        scored.iter().take(3).map(|s| s.0).collect(),
        trials.max(1.0),
    )
}

/// A least-squares solution.
#[derive(Clone, Debug)]
pub(crate) struct Fit {
    pub coef: Vec<f64>,
    /// Covariance of the coefficients (σ² (XᵀX)⁺).
    pub cov: DMatrix<f64>,
    /// Residual `R − model` for every observation (also those not fitted).
    pub residual: Vec<f64>,
    /// Residual sum of squares over the fitted equations.
    pub rss: f64,
    /// Fitted equations.
    pub n_eq: usize,
    /// Numerical rank of the design (columns that are combinations of others do not count).
    pub rank: usize,
}

/// Solves `target ≈ Σ coef_j·col_j` over the observations in `mask` (each observation two
/// rows, x then y) through the numerics kernel's rank-revealing solver
/// [`spm_regression::minimum_norm_least_squares`]: effect columns that are combinations of
/// others get zero weight and do not count in the rank, and the per-frame offsets (disjoint
/// 0/1 indicator columns, hundreds in a movie) are eliminated exactly, so that the cost grows
/// with the data, not with frames³.
/// The design `cols` factored over the features of `mask` (both axes' rows), for many
/// right-hand sides; `None` when it cannot be (too few features, a non-finite value).
pub(crate) fn factor(cols: &[Column], mask: &[bool]) -> Option<spm_regression::FactoredDesign> {
    let rows = cols.first().map_or(2 * mask.len(), Vec::len);
    let included: Vec<bool> = (0..rows)
        .map(|r| mask.get(r / 2).copied().unwrap_or(false))
        .collect();
    spm_regression::FactoredDesign::new(cols, &included).ok()
}

pub(crate) fn solve(
    cols: &[Column],
    target: &[f64],
    mask: &[bool],
) -> Result<Fit, ModelCheckError> {
    let p = cols.len();
    let included: Vec<bool> = (0..target.len())
        .map(|r| mask.get(r / 2).copied().unwrap_or(false))
        .collect();
    let fit =
        spm_regression::minimum_norm_least_squares(cols, target, &included).map_err(
            |e| match e {
                spm_regression::RegressionError::TooFewPoints { got, .. } => {
                    ModelCheckError::TooFewFeatures {
                        found: got / 2,
                        needed: p / 2 + 1,
                        context: "least-squares fit".to_owned(),
                    }
                }
                spm_regression::RegressionError::NonFinite { .. } => {
                    ModelCheckError::InvalidInput("non-finite value in the design".to_owned())
                }
                other => ModelCheckError::Numerical(other.to_string()),
            },
        )?;
    Ok(Fit {
        coef: fit.coefficients,
        cov: DMatrix::from_fn(p, p, |a, b| fit.covariance[a][b]),
        residual: fit.residuals,
        rss: fit.rss,
        n_eq: fit.equations,
        rank: fit.rank,
    })
}

/// Builds the observations from a feature set and the lattice sites.
pub(crate) fn build_obs(
    set: &FeatureSet,
    sites: &[Option<[i64; 2]>],
    a1: [f64; 2],
    a2: [f64; 2],
) -> Result<(Vec<Obs>, Vec<usize>, f64), ModelCheckError> {
    let mut obs = Vec::new();
    let mut source = Vec::new();
    let times: Vec<f64> = set
        .features
        .iter()
        .zip(sites)
        .filter(|(_, s)| s.is_some())
        .map(|(f, _)| f.time_s)
        .collect();
    let t_min = times.iter().copied().fold(f64::INFINITY, f64::min);
    let t_max = times.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let t_mid = 0.5 * (t_min + t_max);
    for (k, (f, site)) in set.features.iter().zip(sites).enumerate() {
        let Some([i, j]) = *site else { continue };
        let frame = set.frames.get(f.frame_index).ok_or_else(|| {
            ModelCheckError::InvalidInput(format!(
                "feature {k} names frame {} of {}",
                f.frame_index,
                set.frames.len()
            ))
        })?;
        if !(f.x_nm.is_finite() && f.y_nm.is_finite() && f.time_s.is_finite()) {
            continue;
        }
        let half = [
            frame.half_width_x_nm.max(1e-12),
            frame.half_height_y_nm.max(1e-12),
        ];
        let (i, j) = (i as f64, j as f64);
        let phase = frame.pixel_nm.and_then(|p| {
            if !(p[0] > 0.0 && p[1] > 0.0 && p[0].is_finite() && p[1].is_finite()) {
                return None;
            }
            let nx = (2.0 * half[0] / p[0]).round();
            let ny = (2.0 * half[1] / p[1]).round();
            let fx = f.x_nm / p[0] + 0.5 * (nx - 1.0);
            let fy = f.y_nm / p[1] + 0.5 * (ny - 1.0);
            Some(([fx - fx.floor(), fy - fy.floor()], p))
        });
        obs.push(Obs {
            u: [f.x_nm, f.y_nm],
            site: [i * a1[0] + j * a2[0], i * a1[1] + j * a2[1]],
            t: f.time_s - t_mid,
            t_frame: f.time_s - frame.start_time_s,
            s: f.direction.sign(),
            frame: f.frame_index,
            line: f.line_index,
            direction: f.direction,
            xi: [f.x_nm / half[0], f.y_nm / half[1]],
            half,
            speed: frame.fast_speed_nm_per_s,
            phase,
            footprint: match (f.width_nm, f.fit_radius_nm, frame.pixel_nm) {
                (Some(w), Some(r), Some(p))
                    if w.is_finite() && w > 0.0 && r.is_finite() && r > 0.0 && p[1] > 0.0 =>
                {
                    Some((
                        w / p[1],
                        (r / p[1]).min(64.0),
                        frame.duration_s / frame.lines.max(1) as f64,
                    ))
                }
                _ => None,
            },
            line_offset_s: f
                .line_time_offset_s
                .filter(|s| s.is_finite() && s.abs() <= frame.duration_s)
                .unwrap_or(0.0),
        });
        source.push(k);
    }
    Ok((obs, source, t_mid))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The adapter over the kernel's solver: an observation's mask covers its two rows,
    /// exact data come back with their rank, and too few observations are a typed error.
    /// (The solver itself, its rank, its indicator elimination and its covariance against
    /// closed forms: `spm-regression`'s `rank` tests.)
    #[test]
    fn solve_masks_observations_and_recovers_exact_coefficients_and_the_rank() {
        let n = 200;
        let t: Vec<f64> = (0..2 * n)
            .map(|i| i as f64 / (2 * n) as f64 - 0.5)
            .collect();
        let cols: Vec<Column> = vec![
            vec![1.0; 2 * n],
            t.clone(),
            t.iter().map(|v| v * v * v).collect(),
        ];
        let truth = [0.3, -2.0, 5.0];
        let mut target: Vec<f64> = (0..2 * n)
            .map(|i| (0..3).map(|j| truth[j] * cols[j][i]).sum())
            .collect();
        // Observation 7 is an outlier in y, left out by the mask.
        target[15] += 1.0;
        let mut mask = vec![true; n];
        mask[7] = false;
        let fit = solve(&cols, &target, &mask).unwrap();
        for (c, t) in fit.coef.iter().zip(truth) {
            assert!((c - t).abs() < 1e-10, "{c} vs {t}");
        }
        assert!(fit.rss < 1e-20 && fit.rank == 3 && fit.n_eq == 2 * (n - 1));
        assert!((fit.residual[15] - 1.0).abs() < 1e-10 && fit.residual[14].abs() < 1e-10);
        let mut few = vec![false; n];
        few[0] = true;
        assert!(matches!(
            solve(&cols, &target, &few),
            Err(ModelCheckError::TooFewFeatures {
                found: 1,
                needed: 2,
                ..
            })
        ));
    }
}
