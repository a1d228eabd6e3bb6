//! Baseline fit, forward selection of effects by evidence, held-out gain,
//! residual structure, and the report (DESIGN §13 `diagnose` JSON).

use crate::index::{MeasuredBasis, index_features};
use crate::model::{
    Column, Ctx, Fit, Obs, baseline_columns, build_obs, effect_columns, hyper_candidates,
    hyper_name, identifiable, param_names, solve,
};
use crate::types::{
    EffectKind, FeatureSet, FrameInfo, LatticeSpec, LineDirection, ModelCheckError, Options,
};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// A fitted parameter with its one-sigma uncertainty (the unit is in its name).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ParamValue {
    /// Best estimate.
    pub value: f64,
    /// One-sigma uncertainty (from the least-squares covariance scaled by the
    /// residual variance; for searched hyper-parameters, the search resolution).
    pub sigma: f64,
}

/// The baseline model's fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BaselineReport {
    /// RMS length of the residual vectors of all features used, pm.
    pub rms_pm: f64,
    /// Held-out RMS (two-fold over alternate lines), pm.
    pub heldout_rms_pm: f64,
    /// Whether constant drift could be told apart from the lumped scanner
    /// (false: one frame or frames scanned alike; the drift is then inside
    /// the scales and obliquity and `drift_*` are absent).
    pub drift_separable: bool,
    /// Lumped scanner (`scale_x`, `scale_y`: true nm per nominal nm;
    /// `obliquity_deg`; `rotation_deg`), constant drift in the image axes
    /// (`drift_x_nm_per_s`, `drift_y_nm_per_s`) and per-frame offsets.
    pub parameters: BTreeMap<String, ParamValue>,
}

/// One effect the data support, in the order it was added.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Finding {
    /// The effect's JSON name (DESIGN §13 vocabulary).
    pub effect: String,
    /// ΔBIC of adding the effect, after the look-elsewhere penalty of its search.
    pub evidence: f64,
    /// RMS before adding it (all features used), pm.
    pub rms_before_pm: f64,
    /// RMS after adding it, pm.
    pub rms_after_pm: f64,
    /// Held-out RMS before (fit on even lines, tested on odd, and vice versa), pm.
    pub heldout_rms_before_pm: f64,
    /// Held-out RMS after, pm.
    pub heldout_rms_after_pm: f64,
    /// The effect's parameters in the final model.
    pub parameters: BTreeMap<String, ParamValue>,
    /// Its physical meaning.
    pub meaning: String,
    /// Other effects whose evidence in the same round was within 6 of this one
    /// (the data cannot tell them apart well).
    pub confounded_with: Vec<String>,
}

/// The final model's fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FinalReport {
    /// RMS of the final model, pm.
    pub rms_pm: f64,
    /// Held-out RMS of the final model, pm.
    pub heldout_rms_pm: f64,
    /// The lumped scanner, drift and offsets in the final (extended) model
    /// (same keys as the baseline's).
    pub parameters: BTreeMap<String, ParamValue>,
}

/// Tests of structure left in the final residual.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResidualStructure {
    /// Lag-1 autocorrelation of time-ordered residuals (x), as ρ₁·√n.
    pub lag1_z_x: f64,
    /// Same for y.
    pub lag1_z_y: f64,
    /// Lag-1 autocorrelation of per-line mean residuals (x), as ρ₁·√n.
    pub line_lag1_z_x: f64,
    /// Same for y.
    pub line_lag1_z_y: f64,
    /// Threshold used.
    pub z_threshold: f64,
}

/// One candidate's evidence in one selection round.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CandidateScore {
    /// Effect name.
    pub effect: String,
    /// ΔBIC after the look-elsewhere penalty (negative = not supported).
    pub evidence: f64,
}

/// Residuals of one feature, for figures.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResidualPoint {
    /// Time from the middle of the observation span, s.
    pub time_s: f64,
    /// Commanded x, nominal nm from the frame centre.
    pub x_nm: f64,
    /// Commanded y, nominal nm.
    pub y_nm: f64,
    /// Frame index.
    pub frame: usize,
    /// Line index.
    pub line: usize,
    /// Forward or backward.
    pub direction: LineDirection,
    /// Baseline residual (lattice frame), pm.
    pub baseline_pm: [f64; 2],
    /// Final-model residual, pm.
    pub final_pm: [f64; 2],
    /// Whether it was used (false = outlier).
    pub used: bool,
}

/// The diagnosis: DESIGN §13 `diagnose` JSON (plus diagnostic extras).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Diagnosis {
    /// The baseline fit.
    pub baseline: BaselineReport,
    /// Effects the data support, in the order added (empty = baseline suffices).
    pub findings: Vec<Finding>,
    /// The final model.
    #[serde(rename = "final")]
    pub final_report: FinalReport,
    /// Structured residual remains that no candidate explains.
    pub unexplained: bool,
    /// The structure tests behind `unexplained`.
    pub residual_structure: ResidualStructure,
    /// Evidence of every candidate in every round.
    pub rounds: Vec<Vec<CandidateScore>>,
    /// Features indexed and used.
    pub features_used: usize,
    /// Features dropped as outliers.
    pub outliers: usize,
    /// Features that could not be indexed.
    pub unindexed: usize,
    /// Frame labels.
    pub frames: Vec<String>,
    /// Time 0 of the model's time axis (the middle of the observation span) on
    /// the input's time axis, s.
    pub time_origin_s: f64,
    /// Half-size (x, y) of every frame, nominal nm.
    pub frame_half_nm: Vec<[f64; 2]>,
    /// Per-feature residuals (for the figure; not serialised).
    #[serde(skip)]
    pub residuals: Vec<ResidualPoint>,
}

impl Diagnosis {
    /// The finding for an effect, if made.
    pub fn finding(&self, effect: EffectKind) -> Option<&Finding> {
        self.findings.iter().find(|f| f.effect == effect.name())
    }

    /// The names of the effects found, in order.
    pub fn effects_found(&self) -> Vec<&str> {
        self.findings.iter().map(|f| f.effect.as_str()).collect()
    }
}

fn rms_pm(rss: f64, n_eq: usize) -> f64 {
    1000.0 * (rss / (n_eq as f64 / 2.0).max(1.0)).sqrt()
}

fn pv(value: f64, sigma: f64) -> ParamValue {
    ParamValue {
        value,
        sigma: if sigma.is_finite() { sigma } else { f64::MAX },
    }
}

struct Added {
    kind: EffectKind,
    hyper: f64,
    hyper_sigma: f64,
    range: std::ops::Range<usize>,
}

/// Fits the best hyper-parameter of `kind` on `mask`; returns (columns, fit, hyper, trials).
#[allow(clippy::too_many_arguments)] // all are the fit's state
fn best_extension(
    kind: EffectKind,
    obs: &[Obs],
    frames: &[FrameInfo],
    target: &[f64],
    cols: &[Column],
    current: &Fit,
    mask: &[bool],
    ctx: &Ctx,
) -> Option<(Vec<Column>, Fit, f64, f64)> {
    let (cands, trials) = hyper_candidates(kind, obs, frames, &current.residual, mask);
    let mut best: Option<(Vec<Column>, Fit, f64)> = None;
    for h in cands {
        let mut all = cols.to_vec();
        let extra = effect_columns(kind, h, obs, ctx);
        if nearly_collinear(&extra, cols, mask) {
            continue;
        }
        all.extend(extra.iter().cloned());
        let Ok(fit) = solve(&all, target, mask) else {
            continue;
        };
        if best.as_ref().is_none_or(|b| fit.rss < b.1.rss) {
            best = Some((extra, fit, h));
        }
    }
    best.map(|(c, f, h)| (c, f, h, trials))
}

/// Two-fold held-out RMS over alternate lines, pm, with optional extension.
fn heldout_rms(
    obs: &[Obs],
    frames: &[FrameInfo],
    target: &[f64],
    cols: &[Column],
    extra: Option<EffectKind>,
    mask: &[bool],
    ctx: &Ctx,
) -> f64 {
    let mut sum = 0.0;
    let mut n = 0usize;
    for fold in 0..2 {
        let train: Vec<bool> = (0..obs.len())
            .map(|k| mask[k] && obs[k].line % 2 == fold)
            .collect();
        let Ok(fit0) = solve(cols, target, &train) else {
            continue;
        };
        let fit = match extra {
            Some(kind) => match best_extension(kind, obs, frames, target, cols, &fit0, &train, ctx)
            {
                Some((_, fit, _, _)) => fit,
                None => fit0,
            },
            None => fit0,
        };
        for k in 0..obs.len() {
            if mask[k] && !train[k] {
                sum += fit.residual[2 * k].powi(2) + fit.residual[2 * k + 1].powi(2);
                n += 1;
            }
        }
    }
    if n == 0 {
        return f64::NAN;
    }
    1000.0 * (sum / n as f64).sqrt()
}

fn lag1_z(series: &[Vec<f64>]) -> f64 {
    let mut num = 0.0;
    let mut den = 0.0;
    let mut pairs = 0usize;
    for s in series {
        if s.len() < 2 {
            continue;
        }
        let mean = s.iter().sum::<f64>() / s.len() as f64;
        for w in s.windows(2) {
            num += (w[0] - mean) * (w[1] - mean);
            pairs += 1;
        }
        den += s.iter().map(|v| (v - mean).powi(2)).sum::<f64>();
    }
    if den <= 0.0 || pairs < 8 {
        return 0.0;
    }
    num / den * (pairs as f64).sqrt()
}

fn structure(obs: &[Obs], residual: &[f64], mask: &[bool], threshold: f64) -> ResidualStructure {
    // Segments: (frame, direction), ordered by time.
    let mut keys: Vec<(usize, LineDirection)> = Vec::new();
    for o in obs {
        if !keys.contains(&(o.frame, o.direction)) {
            keys.push((o.frame, o.direction));
        }
    }
    let mut sx = Vec::new();
    let mut sy = Vec::new();
    let mut lx = Vec::new();
    let mut ly = Vec::new();
    for key in keys {
        let mut idx: Vec<usize> = (0..obs.len())
            .filter(|&k| mask[k] && (obs[k].frame, obs[k].direction) == key)
            .collect();
        idx.sort_by(|&a, &b| obs[a].t.total_cmp(&obs[b].t));
        sx.push(idx.iter().map(|&k| residual[2 * k]).collect::<Vec<_>>());
        sy.push(idx.iter().map(|&k| residual[2 * k + 1]).collect::<Vec<_>>());
        // Per-line means.
        let mut lines: BTreeMap<usize, (f64, f64, usize)> = BTreeMap::new();
        for &k in &idx {
            let e = lines.entry(obs[k].line).or_insert((0.0, 0.0, 0));
            e.0 += residual[2 * k];
            e.1 += residual[2 * k + 1];
            e.2 += 1;
        }
        lx.push(lines.values().map(|e| e.0 / e.2 as f64).collect::<Vec<_>>());
        ly.push(lines.values().map(|e| e.1 / e.2 as f64).collect::<Vec<_>>());
    }
    ResidualStructure {
        lag1_z_x: lag1_z(&sx),
        lag1_z_y: lag1_z(&sy),
        line_lag1_z_x: lag1_z(&lx),
        line_lag1_z_y: lag1_z(&ly),
        z_threshold: threshold,
    }
}

fn decompose(fit: &Fit) -> (BTreeMap<String, ParamValue>, f64) {
    let c = &fit.coef;
    let j = [c[0], c[1], c[2], c[3]];
    let f = |j: [f64; 4]| -> [f64; 4] {
        let kx = j[0].hypot(j[2]);
        let theta = j[2].atan2(j[0]);
        let (s, co) = theta.sin_cos();
        let w = [co * j[1] + s * j[3], -s * j[1] + co * j[3]];
        let ky = w[0].hypot(w[1]);
        let alpha = w[0].atan2(w[1]);
        [kx, ky, alpha.to_degrees(), theta.to_degrees()]
    };
    let base = f(j);
    // Delta-method uncertainties.
    let mut grad = [[0.0; 4]; 4];
    for p in 0..4 {
        let h = 1e-7 * j[p].abs().max(1e-6);
        let mut jp = j;
        jp[p] += h;
        let v = f(jp);
        for q in 0..4 {
            grad[q][p] = (v[q] - base[q]) / h;
        }
    }
    let mut sig = [0.0; 4];
    for q in 0..4 {
        let mut var = 0.0;
        for a in 0..4 {
            for b in 0..4 {
                var += grad[q][a] * grad[q][b] * fit.cov[(a, b)];
            }
        }
        sig[q] = var.max(0.0).sqrt();
    }
    let theta = base[3].to_radians();
    let (s, co) = theta.sin_cos();
    // Drift in image axes: Rot(−θ)·v.
    let v = [c[4], c[5]];
    let d = [co * v[0] + s * v[1], -s * v[0] + co * v[1]];
    let dv = [
        fit.cov[(4, 4)].max(0.0).sqrt(),
        fit.cov[(5, 5)].max(0.0).sqrt(),
    ];
    let mut m = BTreeMap::new();
    m.insert("scale_x".to_owned(), pv(base[0], sig[0]));
    m.insert("scale_y".to_owned(), pv(base[1], sig[1]));
    m.insert("obliquity_deg".to_owned(), pv(base[2], sig[2]));
    m.insert("rotation_deg".to_owned(), pv(base[3], sig[3]));
    m.insert(
        "drift_x_nm_per_s".to_owned(),
        pv(d[0], (co * dv[0]).hypot(s * dv[1])),
    );
    m.insert(
        "drift_y_nm_per_s".to_owned(),
        pv(d[1], (s * dv[0]).hypot(co * dv[1])),
    );
    let n_frames = (c.len() - 6) / 2;
    for fr in 0..n_frames {
        let (ox, oy) = (c[6 + 2 * fr], c[7 + 2 * fr]);
        m.insert(
            format!("frame{fr}_offset_x_nm"),
            pv(ox, fit.cov[(6 + 2 * fr, 6 + 2 * fr)].max(0.0).sqrt()),
        );
        m.insert(
            format!("frame{fr}_offset_y_nm"),
            pv(oy, fit.cov[(7 + 2 * fr, 7 + 2 * fr)].max(0.0).sqrt()),
        );
    }
    (m, theta)
}

fn effect_params(added: &Added, fit: &Fit, frames: &[FrameInfo]) -> BTreeMap<String, ParamValue> {
    let mut m = BTreeMap::new();
    let names = param_names(added.kind);
    let vals: Vec<(f64, f64)> = added
        .range
        .clone()
        .map(|i| (fit.coef[i], fit.cov[(i, i)].max(0.0).sqrt()))
        .collect();
    if added.kind == EffectKind::Creep {
        for (i, (v, s)) in vals.iter().enumerate() {
            let axis = if i % 2 == 0 { "x" } else { "y" };
            m.insert(
                format!("creep_{axis}_nm_per_decade_frame{}", i / 2),
                pv(*v, *s),
            );
        }
    } else if added.kind != EffectKind::PeriodicVibration {
        for (name, (v, s)) in names.iter().zip(&vals) {
            m.insert((*name).to_owned(), pv(*v, *s));
        }
    }
    if let Some(h) = hyper_name(added.kind) {
        m.insert(h.to_owned(), pv(added.hyper, added.hyper_sigma));
    }
    let frame0 = frames.first();
    match added.kind {
        EffectKind::Hysteresis => {
            if let (Some(f), Some((v, s))) = (frame0, vals.first()) {
                m.insert(
                    "branch_separation_nm".to_owned(),
                    pv(2.0 * v * f.half_width_x_nm, 2.0 * s * f.half_width_x_nm),
                );
            }
        }
        EffectKind::FeedbackLag => {
            if let (Some(f), Some((v, s))) = (frame0, vals.first()) {
                m.insert(
                    "shift_nm".to_owned(),
                    pv(v * f.fast_speed_nm_per_s, s * f.fast_speed_nm_per_s),
                );
            }
        }
        EffectKind::PeriodicVibration => {
            if let [xc, xs, yc, ys] = vals.as_slice() {
                m.insert(
                    "amplitude_x_nm".to_owned(),
                    pv(
                        xc.0.hypot(xs.0),
                        (0.5 * (xc.1.powi(2) + xs.1.powi(2))).sqrt(),
                    ),
                );
                m.insert(
                    "amplitude_y_nm".to_owned(),
                    pv(
                        yc.0.hypot(ys.0),
                        (0.5 * (yc.1.powi(2) + ys.1.powi(2))).sqrt(),
                    ),
                );
                m.insert("phase_x_rad".to_owned(), pv(xs.0.atan2(xc.0), 0.0));
                m.insert("phase_y_rad".to_owned(), pv(ys.0.atan2(yc.0), 0.0));
            }
        }
        _ => {}
    }
    m
}

/// Whether some of `extra` is ≥ 99.9 % explained by `cols` (R² of its
/// variation about its mean, over the fitted equations): the effect is then
/// confounded with the model already there.
fn nearly_collinear(extra: &[Column], cols: &[Column], mask: &[bool]) -> bool {
    let n = mask.iter().filter(|m| **m).count().max(1) as f64;
    extra.iter().any(|c| {
        let mean = [0, 1].map(|a| {
            (0..mask.len())
                .filter(|&k| mask[k])
                .map(|k| c[2 * k + a])
                .sum::<f64>()
                / n
        });
        let total: f64 = (0..mask.len())
            .filter(|&k| mask[k])
            .map(|k| (c[2 * k] - mean[0]).powi(2) + (c[2 * k + 1] - mean[1]).powi(2))
            .sum();
        match solve(cols, c, mask) {
            Ok(f) => total <= 0.0 || f.rss < 1e-3 * total,
            Err(_) => true,
        }
    })
}

/// Least squares with robust outlier rejection (mis-indexed or defective features).
fn robust_fit(
    cols: &[Column],
    target: &[f64],
    mask: &mut Vec<bool>,
    outlier_sigmas: f64,
    needed: usize,
    floor_nm: f64,
) -> Result<Fit, ModelCheckError> {
    let n = mask.len();
    let mut fit = solve(cols, target, mask)?;
    for _ in 0..5 {
        let mut abs: Vec<f64> = (0..n)
            .filter(|&k| mask[k])
            .flat_map(|k| [fit.residual[2 * k].abs(), fit.residual[2 * k + 1].abs()])
            .collect();
        abs.sort_by(f64::total_cmp);
        let sigma = 1.4826 * abs.get(abs.len() / 2).copied().unwrap_or(0.0);
        // Never below a quarter period: a mis-indexed feature is off by a
        // lattice vector, a real effect (a tip jump) may be many σ.
        let limit = (outlier_sigmas * sigma).max(floor_nm);
        let new: Vec<bool> = (0..n)
            .map(|k| fit.residual[2 * k].abs() <= limit && fit.residual[2 * k + 1].abs() <= limit)
            .collect();
        if new == *mask || new.iter().filter(|m| **m).count() < needed {
            break;
        }
        *mask = new;
        fit = solve(cols, target, mask)?;
    }
    Ok(fit)
}

/// Diagnoses a set of indexed-able feature observations against a lattice.
///
/// Steps: index to lattice sites; baseline fit (lumped linear scanner,
/// constant drift, per-frame offsets) with robust outlier rejection; forward
/// selection of library effects by ΔBIC (with look-elsewhere penalty for
/// searched hyper-parameters), each accepted only when it also lowers the
/// two-fold held-out RMS over alternate lines; a lag-1 structure test of the
/// final residual.
pub fn diagnose_features(
    set: &FeatureSet,
    lattice: &LatticeSpec,
    options: &Options,
) -> Result<Diagnosis, ModelCheckError> {
    let indexing = index_features(set, lattice)?;
    diagnose_indexed(set, &indexing.sites, &indexing.basis, options)
}

/// Like [`diagnose_features`] with the lattice sites given (e.g. from a simulator's oracle).
pub fn diagnose_indexed(
    set: &FeatureSet,
    sites: &[Option<[i64; 2]>],
    basis: &MeasuredBasis,
    options: &Options,
) -> Result<Diagnosis, ModelCheckError> {
    if sites.len() != set.features.len() {
        return Err(ModelCheckError::InvalidInput(format!(
            "{} sites for {} features",
            sites.len(),
            set.features.len()
        )));
    }
    let (obs, source, t_mid) = build_obs(set, sites, basis.a1_nm, basis.a2_nm)?;
    let lattice_a_nm = basis.a1_nm[0].hypot(basis.a1_nm[1]);
    let n_frames = set.frames.len();
    let needed = 8 + n_frames * 2;
    if obs.len() < needed {
        return Err(ModelCheckError::TooFewFeatures {
            found: obs.len(),
            needed,
            context: "indexed features".to_owned(),
        });
    }
    let target: Vec<f64> = obs.iter().flat_map(|o| o.site).collect();
    let mut base_cols = baseline_columns(&obs, n_frames);
    let mut mask = vec![true; obs.len()];
    let mut fit = robust_fit(
        &base_cols,
        &target,
        &mut mask,
        options.outlier_sigmas,
        needed,
        0.25 * lattice_a_nm,
    )?;
    // Constant drift and the lumped scanner are inseparable when the times
    // follow the positions (one frame, or frames scanned the same way): then
    // the drift is absorbed into the lumped scanner (Lapshin's point for
    // counter-scanning) and not reported.
    let (trial, _) = decompose(&fit);
    let relative = |k: &str| {
        trial
            .get(k)
            .map_or(f64::INFINITY, |p| p.sigma / p.value.abs().max(1e-12))
    };
    let without_drift: Vec<Column> = base_cols
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != 4 && *i != 5)
        .map(|(_, c)| c.clone())
        .collect();
    let drift_separable = !nearly_collinear(&base_cols[4..6], &without_drift, &mask)
        && relative("scale_x") < 0.05
        && relative("scale_y") < 0.05
        && trial.get("obliquity_deg").is_some_and(|p| p.sigma < 3.0);
    if !drift_separable {
        for c in &mut base_cols[4..6] {
            c.iter_mut().for_each(|v| *v = 0.0);
        }
        mask = vec![true; obs.len()];
        fit = robust_fit(
            &base_cols,
            &target,
            &mut mask,
            options.outlier_sigmas,
            needed,
            0.25 * lattice_a_nm,
        )?;
    }
    let (mut baseline_params, theta0) = decompose(&fit);
    if !drift_separable {
        baseline_params.remove("drift_x_nm_per_s");
        baseline_params.remove("drift_y_nm_per_s");
    }
    let mut ctx = Ctx {
        j0: [[fit.coef[0], fit.coef[1]], [fit.coef[2], fit.coef[3]]],
        theta0,
    };
    let frames = &set.frames;
    let baseline_fit = fit.clone();
    let baseline_heldout = heldout_rms(&obs, frames, &target, &base_cols, None, &mask, &ctx);
    let baseline = BaselineReport {
        rms_pm: rms_pm(fit.rss, fit.n_eq),
        heldout_rms_pm: baseline_heldout,
        drift_separable,
        parameters: baseline_params,
    };
    let mut cols = base_cols;
    let mut added: Vec<Added> = Vec::new();
    let mut findings: Vec<Finding> = Vec::new();
    let mut rounds = Vec::new();
    let mut heldout_now = baseline_heldout;
    let n_eq = fit.n_eq as f64;
    for _ in 0..options.max_findings {
        let mut scores: Vec<(EffectKind, f64, Vec<Column>, Fit, f64)> = Vec::new();
        for &kind in &options.effects {
            if added.iter().any(|a| a.kind == kind) || !identifiable(kind, &obs) {
                continue;
            }
            let Some((extra, fit1, h, trials)) =
                best_extension(kind, &obs, frames, &target, &cols, &fit, &mask, &ctx)
            else {
                continue;
            };
            if fit1.rank < fit.rank + extra.len() {
                // Some of its columns are combinations of the model's: with these
                // data the effect cannot be told apart from what is already there.
                continue;
            }
            let k = extra.len() as f64 + if hyper_name(kind).is_some() { 1.0 } else { 0.0 };
            let evidence = if fit1.rss > 0.0 && fit.rss > 0.0 {
                n_eq * (fit.rss / fit1.rss).ln() - k * n_eq.ln() - 2.0 * trials.max(1.0).ln()
            } else {
                f64::NEG_INFINITY
            };
            scores.push((kind, evidence, extra, fit1, h));
        }
        scores.sort_by(|a, b| b.1.total_cmp(&a.1));
        rounds.push(
            scores
                .iter()
                .map(|s| CandidateScore {
                    effect: s.0.name().to_owned(),
                    evidence: if s.1.is_finite() { s.1 } else { -1e300 },
                })
                .collect::<Vec<_>>(),
        );
        let mut accepted = None;
        for (pos, s) in scores.iter().enumerate() {
            if s.1 <= options.evidence_threshold {
                break;
            }
            let after = heldout_rms(&obs, frames, &target, &cols, Some(s.0), &mask, &ctx);
            if after < heldout_now {
                accepted = Some((pos, after));
                break;
            }
        }
        let Some((pos, after)) = accepted else { break };
        let (kind, evidence, extra, fit1, h) = scores.swap_remove(pos);
        let confounded_with = scores
            .iter()
            .filter(|s| s.1 > options.evidence_threshold && s.1 >= evidence - 6.0)
            .map(|s| s.0.name().to_owned())
            .collect();
        let start = cols.len();
        cols.extend(extra);
        let hyper_sigma = match kind {
            EffectKind::Creep => h,
            EffectKind::PeriodicVibration => {
                let span = obs.iter().map(|o| o.t).fold(f64::NEG_INFINITY, f64::max)
                    - obs.iter().map(|o| o.t).fold(f64::INFINITY, f64::min);
                0.25 / span.max(1e-9)
            }
            EffectKind::TipChange => frames
                .iter()
                .map(|f| 0.5 * f.duration_s / f.lines.max(1) as f64)
                .fold(0.0, f64::max),
            _ => 0.0,
        };
        added.push(Added {
            kind,
            hyper: h,
            hyper_sigma,
            range: start..cols.len(),
        });
        findings.push(Finding {
            effect: kind.name().to_owned(),
            evidence,
            rms_before_pm: rms_pm(fit.rss, fit.n_eq),
            rms_after_pm: rms_pm(fit1.rss, fit1.n_eq),
            heldout_rms_before_pm: heldout_now,
            heldout_rms_after_pm: after,
            parameters: BTreeMap::new(),
            meaning: kind.meaning().to_owned(),
            confounded_with,
        });
        heldout_now = after;
        fit = fit1;
        // Refresh J₀ and θ₀ from the extended fit and rebuild the effect columns.
        let (_, theta) = decompose(&fit);
        ctx = Ctx {
            j0: [[fit.coef[0], fit.coef[1]], [fit.coef[2], fit.coef[3]]],
            theta0: theta,
        };
        cols.truncate(6 + 2 * n_frames);
        for a in &mut added {
            let start = cols.len();
            cols.extend(effect_columns(a.kind, a.hyper, &obs, &ctx));
            a.range = start..cols.len();
        }
        fit = solve(&cols, &target, &mask)?;
        tracing::debug!(effect = kind.name(), evidence, "effect accepted");
    }
    for (finding, a) in findings.iter_mut().zip(&added) {
        finding.parameters = effect_params(a, &fit, frames);
        if a.kind == EffectKind::TipChange
            && let Some(t) = finding.parameters.get_mut("time_s")
        {
            t.value += t_mid;
        }
    }
    let (mut final_params, _) = decompose(&fit);
    if !drift_separable {
        final_params.remove("drift_x_nm_per_s");
        final_params.remove("drift_y_nm_per_s");
    }
    let residual_structure = structure(&obs, &fit.residual, &mask, options.structure_z_threshold);
    let unexplained = [
        residual_structure.lag1_z_x,
        residual_structure.lag1_z_y,
        residual_structure.line_lag1_z_x,
        residual_structure.line_lag1_z_y,
    ]
    .iter()
    .any(|z| *z > options.structure_z_threshold)
        // A residual beyond 25 % of the period is not a small distortion of
        // the lattice model at all (mis-indexing, several domains, or a
        // distortion far outside the library).
        || rms_pm(fit.rss, fit.n_eq) > 250.0 * lattice_a_nm;
    let residuals = obs
        .iter()
        .enumerate()
        .map(|(k, o)| ResidualPoint {
            time_s: o.t,
            x_nm: o.u[0],
            y_nm: o.u[1],
            frame: o.frame,
            line: o.line,
            direction: o.direction,
            baseline_pm: [
                1000.0 * baseline_fit.residual[2 * k],
                1000.0 * baseline_fit.residual[2 * k + 1],
            ],
            final_pm: [
                1000.0 * fit.residual[2 * k],
                1000.0 * fit.residual[2 * k + 1],
            ],
            used: mask[k],
        })
        .collect();
    let used = mask.iter().filter(|m| **m).count();
    Ok(Diagnosis {
        baseline,
        findings,
        final_report: FinalReport {
            rms_pm: rms_pm(fit.rss, fit.n_eq),
            heldout_rms_pm: heldout_now,
            parameters: final_params,
        },
        unexplained,
        residual_structure,
        rounds,
        features_used: used,
        outliers: obs.len() - used,
        unindexed: set.features.len() - source.len(),
        frames: set.frames.iter().map(|f| f.label.clone()).collect(),
        time_origin_s: t_mid,
        frame_half_nm: set
            .frames
            .iter()
            .map(|f| [f.half_width_x_nm, f.half_height_y_nm])
            .collect(),
        residuals,
    })
}
