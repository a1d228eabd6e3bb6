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
}

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

/// spm-sim configuration values of a fitted model.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SimPatch {
    /// Dotted `SimConfig` TOML paths and values. `surface.*.rotation_deg`
    /// means the rotation of whichever surface kind the config holds.
    pub values: BTreeMap<String, f64>,
    /// Tip changes to schedule.
    pub tip_changes: Vec<TipChangeEvent>,
    /// Findings spm-sim has no parameter for, with the reason.
    pub unmapped: Vec<String>,
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
/// to play operators whose thresholds all open within the frame.
pub fn sim_patch(d: &Diagnosis, ctx: &SimContext, with_findings: bool) -> SimPatch {
    // The linear part of the model the findings extend: the final fit's.
    let b = if with_findings {
        &d.final_report.parameters
    } else {
        &d.baseline.parameters
    };
    let n0 = ctx.nominal_nm_per_count;
    let mut p = SimPatch::default();
    let mut set = |k: &str, v: f64| {
        p.values.insert(k.to_owned(), v);
    };
    set(
        "scanner.sensitivity_x_nm_per_count",
        value(b, "scale_x") * n0,
    );
    set(
        "scanner.sensitivity_y_nm_per_count",
        value(b, "scale_y") * n0,
    );
    set("scanner.nonorthogonality_deg", value(b, "obliquity_deg"));
    set("scanner.crosstalk_x_from_y", 0.0);
    set("scanner.crosstalk_y_from_x", 0.0);
    set("surface.*.rotation_deg", -value(b, "rotation_deg"));
    let mut vx = value(b, "drift_x_nm_per_s");
    let mut vy = value(b, "drift_y_nm_per_s");
    let mut values = std::mem::take(&mut p.values);
    let mut unmapped = Vec::new();
    let mut tips = Vec::new();
    if with_findings {
        let frame_half = d.frame_half_nm.first().copied().unwrap_or([1.0, 1.0]);
        let field_half_nm = ctx.half_range_counts * n0;
        let rx = field_half_nm / frame_half[0].max(1e-12);
        let ry = field_half_nm / frame_half[1].max(1e-12);
        for f in &d.findings {
            let fp = &f.parameters;
            let Some(kind) = EffectKind::from_name(&f.effect) else {
                continue;
            };
            let mut put = |k: &str, v: f64| {
                values.insert(k.to_owned(), v);
            };
            match kind {
                EffectKind::DriftAcceleration => {
                    // d(t) = v·t + A·(1 − e^(−t/T)): acceleration −A/T²·e^(−t/T).
                    let tau = ctx.warmup_time_constant_s.max(1e-9);
                    let t_mid = d.time_origin_s + ctx.time_offset_s;
                    let e = (t_mid / tau).exp();
                    let ax = value(fp, "acceleration_x_nm_per_s2");
                    let ay = value(fp, "acceleration_y_nm_per_s2");
                    put("drift.warmup_time_constant_s", tau);
                    put("drift.warmup_amplitude_x_nm", -ax * tau * tau * e);
                    put("drift.warmup_amplitude_y_nm", -ay * tau * tau * e);
                    vx += ax * tau;
                    vy += ay * tau;
                }
                EffectKind::ScannerNonlinearity => {
                    put(
                        "scanner.nonlinearity_x.quadratic",
                        value(fp, "quadratic_x") * rx,
                    );
                    put(
                        "scanner.nonlinearity_x.cubic",
                        value(fp, "cubic_x") * rx * rx,
                    );
                    put(
                        "scanner.nonlinearity_y.quadratic",
                        value(fp, "quadratic_y") * ry,
                    );
                    put(
                        "scanner.nonlinearity_y.cubic",
                        value(fp, "cubic_y") * ry * ry,
                    );
                }
                EffectKind::CrosstalkXy => {
                    // px += Ky·uy·byx·uy/H ⇒ Δux = (Ky/Kx)·byx·uy²/H.
                    let k = value(b, "scale_y") / value(b, "scale_x").max(1e-12);
                    put(
                        "scanner.bow_x_from_y",
                        value(fp, "bow_x_from_y") * (frame_half[1] / frame_half[0]) * ry
                            / k.max(1e-12),
                    );
                    put(
                        "scanner.bow_y_from_x",
                        value(fp, "bow_y_from_x") * (frame_half[0] / frame_half[1]) * rx * k,
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
                    put("measurement.feedback_time_constant_s", tau_sim);
                }
                EffectKind::Hysteresis => {
                    let h = value(fp, "branch_half_separation_fraction");
                    let w_counts = frame_half[0] / n0;
                    put(
                        "scanner.hysteresis_x.width_fraction",
                        (h * w_counts / ctx.half_range_counts).max(0.0),
                    );
                    put("scanner.hysteresis_x.max_threshold_counts", 0.5 * w_counts);
                    put(
                        "scanner.hysteresis_x.min_threshold_counts",
                        0.5 * w_counts / 16.0,
                    );
                    put("scanner.hysteresis_x.operators", 16.0);
                }
                EffectKind::TipChange => tips.push(TipChangeEvent {
                    time_s: value(fp, "time_s") + ctx.time_offset_s,
                    jump_x_nm: value(fp, "jump_x_nm"),
                    jump_y_nm: value(fp, "jump_y_nm"),
                }),
                EffectKind::Creep => unmapped.push(
                    "creep: spm-sim's creep is a relaxation chain driven by the move history; \
                     the fitted lg-amplitude fixes γ only together with the approach move"
                        .to_owned(),
                ),
                EffectKind::Nonorthogonality => unmapped.push(
                    "nonorthogonality: spm-sim has a constant obliquity only (mapped from the \
                     baseline); its gradient over the field has no parameter"
                        .to_owned(),
                ),
                EffectKind::PeriodicVibration => unmapped
                    .push("periodic_vibration: spm-sim has no lateral vibration source".to_owned()),
                EffectKind::Interlace => unmapped.push(
                    "interlace: spm-sim has no direction-dependent slow-axis offset".to_owned(),
                ),
            }
        }
    }
    values.insert("drift.velocity_x_nm_per_s".to_owned(), vx);
    values.insert("drift.velocity_y_nm_per_s".to_owned(), vy);
    p.values = values;
    p.unmapped = unmapped;
    p.tip_changes = tips;
    p
}

impl SimPatch {
    /// Merges the values into a full spm-sim config (TOML text) and returns the new text.
    pub fn apply_to_toml(&self, base: &str) -> Result<String, ModelCheckError> {
        let bad = |e: String| ModelCheckError::InvalidInput(format!("spm-sim config: {e}"));
        let mut root: toml::Table = base
            .parse()
            .map_err(|e: toml::de::Error| bad(e.to_string()))?;
        for (path, v) in &self.values {
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
