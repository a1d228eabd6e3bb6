//! The sinusoidal fast-axis drive (`sinusoidal_drive`, issue 29 item 3): the phase β found
//! between the grid points, its uncertainty, the finding's physical parameters, and the
//! test that tells a sine from the cubic it starts as.
//!
//! The model (`model::sine_drive_departure`): the fast axis's input is
//! W·[ξ + κ·(sin βξ − βξ)/β], linear in the weight κ for a given phase β. A pure sine
//! drive has κ = 1 once the lumped scale is the sine's slope at the line centre; κ ≠ 1 is
//! a sine plus a linear ramp, which no resonant drive makes.

use crate::model::{Column, Ctx, Fit, Obs, effect_columns, solve};
use crate::types::{EffectKind, FrameInfo};
use std::collections::BTreeMap;
use std::f64::consts::FRAC_PI_2;

/// The largest phase at a line end, rad: at π/2 the line's last pixels stand still.
const MAX_PHASE_RAD: f64 = FRAC_PI_2;

/// The fit with the drive's column at phase `beta_rad` added to `cols`.
fn fit_at(
    beta_rad: f64,
    (obs, target, cols, mask, ctx): (&[Obs], &[f64], &[Column], &[bool], &Ctx),
) -> Option<(Vec<Column>, Fit)> {
    let extra = effect_columns(EffectKind::SinusoidalDrive, beta_rad, obs, ctx);
    let mut all = cols.to_vec();
    all.extend(extra.iter().cloned());
    solve(&all, target, mask).ok().map(|fit| (extra, fit))
}

/// The share of the fast axis's slope at the line centre that the sine carries in `fit`
/// (its last coefficient the weight κ of a column built with `ctx`'s J₀): κ·|J₀·e_x|/|J·e_x|,
/// 1 for a pure sine drive, and its standard error.
fn sine_fraction(fit: &Fit, ctx: &Ctx) -> (f64, f64) {
    let j0_x = ctx.j0[0][0].hypot(ctx.j0[1][0]);
    let j_x = match (fit.coef.first(), fit.coef.get(2)) {
        (Some(a), Some(c)) => a.hypot(*c),
        _ => f64::NAN,
    };
    let last = fit.coef.len().saturating_sub(1);
    let kappa = fit.coef.get(last).copied().unwrap_or(f64::NAN);
    let s_kappa = fit
        .cov
        .get((last, last))
        .map_or(f64::NAN, |v| v.max(0.0).sqrt());
    (kappa * j0_x / j_x, s_kappa * j0_x / j_x)
}

/// The phase β at which the drive is a pure sine (`sine_fraction` = 1), with its columns and
/// fit. With the weight κ free, κ and β trade along a valley (both make the cubic κ·β²/6),
/// and a minimum of the RSS along it follows whatever else bends the positions (the
/// localiser's bias on a profile stretched unevenly along the line: β 10 % high, the
/// amplitude 20 % low on the image-level generator). A resonant drive is a sine, so the
/// phase is the root of sine_fraction(β) − 1, which falls with β: bracketed on the grid,
/// bisected (30 steps). Without a root (a positive cubic, a drive that is no sine) the
/// grid's best `best` is kept, and the plausibility test rejects it.
pub(crate) fn pure_sine_phase(
    obs: &[Obs],
    target: &[f64],
    cols: &[Column],
    mask: &[bool],
    ctx: &Ctx,
    best: (Vec<Column>, Fit, f64),
) -> (Vec<Column>, Fit, f64) {
    let data = (obs, target, cols, mask, ctx);
    let excess = |b: f64| fit_at(b, data).map_or(f64::NAN, |(_, f)| sine_fraction(&f, ctx).0 - 1.0);
    let grid: Vec<f64> = (0..crate::model::SINE_GRID_POINTS)
        .map(|i| crate::model::SINE_PHASE_MIN_RAD + i as f64 * crate::model::SINE_PHASE_STEP_RAD)
        .chain([MAX_PHASE_RAD - 1e-3])
        .collect();
    let values: Vec<f64> = grid.iter().map(|&b| excess(b)).collect();
    let bracket = (1..grid.len()).find(|&i| values[i - 1] > 0.0 && values[i] <= 0.0);
    let Some(i) = bracket else {
        return best;
    };
    let (mut lo, mut hi) = (grid[i - 1], grid[i]);
    for _ in 0..30 {
        let mid = 0.5 * (lo + hi);
        if excess(mid) > 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let beta = 0.5 * (lo + hi);
    match fit_at(beta, data) {
        Some((extra, fit)) => (extra, fit, beta),
        None => best,
    }
}

/// The phase's standard error, rad, from the sine fraction's: σ_β = σ_f/|∂f/∂β| at the
/// pure-sine phase `beta_rad` (f = 1 defines β).
pub(crate) fn phase_sigma(
    obs: &[Obs],
    target: &[f64],
    cols: &[Column],
    mask: &[bool],
    ctx: &Ctx,
    beta_rad: f64,
) -> f64 {
    let data = (obs, target, cols, mask, ctx);
    let h = 1e-3;
    let at = |b: f64| fit_at(b, data).map(|(_, f)| sine_fraction(&f, ctx));
    match (at(beta_rad - h), at(beta_rad), at(beta_rad + h)) {
        (Some(lo), Some(mid), Some(hi)) => {
            let slope = (hi.0 - lo.0) / (2.0 * h);
            if slope != 0.0 && slope.is_finite() {
                (mid.1 / slope).abs()
            } else {
                f64::NAN
            }
        }
        _ => f64::NAN,
    }
}

/// The finding's parameters from the weight κ (`weight`: value, σ), the phase β (value,
/// σ), the context the column was built with (`ctx`, its J₀ maps the input), and the fit
/// (its lumped J): `amplitude_nm` = κ·|J₀·e_x|·W/β, the sine's amplitude in the sample;
/// `sine_fraction` = κ·|J₀·e_x|/|J·e_x|, the share of the fast axis's slope at the line
/// centre the sine carries (1 for a pure drive); `drive_frequency_hz` = β/(π·T_line) with
/// T_line = 2W/v the line's duration (W the half-width, v the fast speed); the phase
/// `phase_at_line_end_rad` = β is inserted by the caller. W and v of the first frame.
pub(crate) fn parameters(
    weight: (f64, f64),
    beta: (f64, f64),
    ctx: &Ctx,
    fit: &Fit,
    frames: &[FrameInfo],
) -> BTreeMap<String, (f64, f64)> {
    let mut m = BTreeMap::new();
    let Some(frame) = frames.first() else {
        return m;
    };
    let (kappa, s_kappa) = weight;
    let (b, s_b) = beta;
    let j0_x = ctx.j0[0][0].hypot(ctx.j0[1][0]);
    let j_x = match (fit.coef.first(), fit.coef.get(2)) {
        (Some(a), Some(c)) => a.hypot(*c),
        _ => f64::NAN,
    };
    let half_nm = frame.half_width_x_nm;
    let amplitude = kappa * j0_x * half_nm / b;
    let rel = |a: f64, s: f64| if a != 0.0 { s / a } else { 0.0 };
    let rel_b = if s_b.is_finite() { rel(b, s_b) } else { 0.0 };
    // β is pinned by the pure-sine condition, so the weight's uncertainty is in β's; for a
    // given drive the fitted slope |J·e_x| = A·β/W follows β as β/sin β, so A ∝ 1/sin β
    // and σ_A = A·|cot β|·σ_β.
    let s_amplitude = if s_b.is_finite() {
        amplitude.abs() * s_b / b.tan().abs()
    } else {
        amplitude.abs() * rel(kappa, s_kappa)
    };
    m.insert("amplitude_nm".to_owned(), (amplitude, s_amplitude));
    let fraction = kappa * j0_x / j_x;
    m.insert(
        "sine_fraction".to_owned(),
        (fraction, (s_kappa * j0_x / j_x).abs()),
    );
    if frame.fast_speed_nm_per_s > 0.0 && half_nm > 0.0 {
        let line_s = 2.0 * half_nm / frame.fast_speed_nm_per_s;
        let f = b / (std::f64::consts::PI * line_s);
        m.insert("drive_frequency_hz".to_owned(), (f, f * rel_b));
    }
    m
}

/// Why the drive's parameters are not physical: a resonant drive is a pure sine, so the
/// sine must carry the fast axis's slope at the line centre (`sine_fraction` within 0.25
/// of 1, or 3σ); a negative weight is a positive cubic, which no sine makes.
pub(crate) fn implausible(fraction: (f64, f64)) -> Option<String> {
    let (v, s) = fraction;
    ((v - 1.0).abs() > 0.25 + 3.0 * s).then(|| {
        format!(
            "sine fraction {v:.3} ± {s:.1e}: a drive that is not a sine \
             (1 = the sine carries the fast axis)"
        )
    })
}

/// Evidence (ΔBIC) that the drive's shape is seen beyond the cubic it starts as: the drive
/// added to the model *with* a free quadratic and cubic on both axes (the polynomial
/// nonlinearity at degree 3), on the features that model keeps. Below the threshold the data do not tell the sine from a
/// polynomial, and the polynomial (which also takes positive cubics) is the honest name.
pub(crate) fn beyond_cubic_evidence(
    obs: &[Obs],
    target: &[f64],
    cols: &[Column],
    mask: &[bool],
    ctx: &Ctx,
    (extra, trials): (&[Column], f64),
    evidence: &dyn Fn(f64, f64, f64, f64, f64) -> f64,
) -> f64 {
    let mut with_cubic = cols.to_vec();
    with_cubic.extend(effect_columns(
        EffectKind::ScannerNonlinearity,
        3.0,
        obs,
        ctx,
    ));
    let n_cubic = with_cubic.len();
    with_cubic.extend(extra.iter().cloned());
    // On the features the extended model describes: the baseline's outliers include the
    // frame edges, where a drive departs most from a straight line and from a cubic
    // (re-admitted after an acceptance, as `readmit` does), within 5 RMS of its residual.
    let Ok(f1) = solve(&with_cubic, target, mask) else {
        return f64::NEG_INFINITY;
    };
    let rms = (f1.rss / f1.n_eq.max(1) as f64).sqrt();
    let wide: Vec<bool> = (0..mask.len())
        .map(|k| {
            let r = f1.residual[2 * k].hypot(f1.residual[2 * k + 1]);
            mask[k] || (r.is_finite() && r < 5.0 * std::f64::consts::SQRT_2 * rms)
        })
        .collect();
    let (Ok(f0), Ok(f1)) = (
        solve(&with_cubic[..n_cubic], target, &wide),
        solve(&with_cubic, target, &wide),
    ) else {
        return f64::NEG_INFINITY;
    };
    evidence(f0.n_eq as f64, f0.rss, f1.rss, 2.0, trials)
}
