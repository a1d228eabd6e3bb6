//! Validation without an oracle (issue 24 item 6): what every run can say of its own
//! calibration, whatever the backend (simulated, virtual or a real controller).
//!
//! - [`held_out_check`]: a seeded share of the net's nodes is left out of a second fit; the
//!   surfaces fitted without them predict their LCCs. Each held-out record's error is divided
//!   by the prediction's standard deviation σ·√(1 + h): σ the fit's eq. (14) scatter (what
//!   the calibration file states), h the prediction's leverage
//!   ([`spm_regression::leverages`]). If the surfaces generalise as well as σ claims, the RMS
//!   of these ratios is 1.
//! - [`repeat_agreement`]: the l repeats of a node measure the same place; their pooled
//!   scatter is compared with the records' own stated standard uncertainty, and the mean
//!   change from the first to the last repeat shows a calibration that moved during the run.
//!
//! The corrected image of the standard is measured by the caller, which holds the instrument
//! (`spmcal`'s validation step), with [`crate::images::lattice`].
//!
//! No I/O and no clock; the draw of held-out nodes is a seeded ChaCha permutation.

use std::collections::{BTreeMap, BTreeSet};

use rand::SeedableRng as _;
use rand::seq::SliceRandom as _;
use serde::Serialize;
use spm_calibration::run_validation::RunValidationConfig;
use spm_correction::{FittedSurface, PlaneSurfaces};
use spm_records::LccRecord;
use spm_regression::{Observations, leverages};

/// The verdict of a check against the thresholds the plan states.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    /// Within the plan's thresholds.
    Pass,
    /// Outside them: the figure is reported, the run is not failed.
    Warn,
    /// The check could not be made (too few nodes or repeats); the reason is given.
    NotMeasured,
}

impl Verdict {
    /// `pass`, `warn` or `not measured`.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Pass => "pass",
            Self::Warn => "warn",
            Self::NotMeasured => "not measured",
        }
    }
}

/// The LCCs a check compares, with the unit its figures are reported in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Coefficient {
    Kx,
    Ky,
    Alpha,
}

impl Coefficient {
    const ALL: [Self; 3] = [Self::Kx, Self::Ky, Self::Alpha];

    fn name(self) -> &'static str {
        match self {
            Self::Kx => "kx",
            Self::Ky => "ky",
            Self::Alpha => "alpha",
        }
    }

    /// The display unit and the factor from the record's unit (nm/count, rad) to it.
    fn unit(self) -> (&'static str, f64) {
        match self {
            Self::Kx | Self::Ky => ("pm/count", 1e3),
            Self::Alpha => ("mrad", 1e3),
        }
    }

    fn value(self, r: &LccRecord) -> f64 {
        match self {
            Self::Kx => r.kx_nm_per_count,
            Self::Ky => r.ky_nm_per_count,
            Self::Alpha => r.alpha_rad,
        }
    }

    fn stated_u(self, r: &LccRecord) -> Option<f64> {
        match self {
            Self::Kx => r.u_kx_nm_per_count,
            Self::Ky => r.u_ky_nm_per_count,
            Self::Alpha => r.u_alpha_rad,
        }
        .filter(|u| u.is_finite() && *u > 0.0)
    }

    fn surface(self, plane: &PlaneSurfaces) -> &FittedSurface {
        match self {
            Self::Kx => &plane.kx_nm_per_count,
            Self::Ky => &plane.ky_nm_per_count,
            Self::Alpha => &plane.alpha_rad,
        }
    }
}

/// One coefficient of the held-out check.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HeldOutCoefficient {
    /// `kx`, `ky` or `alpha`.
    pub coefficient: &'static str,
    /// Held-out records compared.
    pub records: usize,
    /// RMS of (measured − predicted)/(σ·√(1 + h)).
    pub rms_z: f64,
    /// Largest |(measured − predicted)/(σ·√(1 + h))|.
    pub max_abs_z: f64,
    /// RMS of measured − predicted, in `unit`.
    pub rms_error: f64,
    /// RMS of the predictions' standard deviations σ·√(1 + h), in `unit`.
    pub rms_prediction_sd: f64,
    /// Unit of `rms_error` and `rms_prediction_sd`.
    pub unit: &'static str,
}

/// Predicted against measured LCCs at nodes left out of the fit.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HeldOutCheck {
    /// The plan's share of nodes held out.
    pub share: f64,
    /// The seed of the draw.
    pub seed: u64,
    /// Nodes with records.
    pub nodes: usize,
    /// Nodes held out.
    pub nodes_held_out: usize,
    /// Held-out records compared.
    pub records_held_out: usize,
    /// Per coefficient.
    pub coefficients: Vec<HeldOutCoefficient>,
    /// RMS of the ratios over the three coefficients (NaN when not measured).
    pub rms_z: f64,
    /// The plan's pass range of `rms_z`.
    pub pass_range: [f64; 2],
    /// Pass, warn or not measured.
    pub verdict: Verdict,
    /// Why not measured, or which coefficient is out of range.
    pub reason: Option<String>,
}

/// The node indices to hold out: a seeded permutation of the distinct indices, the first
/// `round(share · n)` of it, at most all but three (a fit needs the rest), and none when
/// `share` is 0.
#[must_use]
pub fn held_out_nodes(nodes: &BTreeSet<u32>, share: f64, seed: u64) -> BTreeSet<u32> {
    let mut all: Vec<u32> = nodes.iter().copied().collect();
    let wanted = (share * all.len() as f64).round() as usize;
    let k = wanted.min(all.len().saturating_sub(3));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    all.shuffle(&mut rng);
    all.into_iter().take(k).collect()
}

/// The held-out check: the records of the held-out nodes ([`held_out_nodes`]) against the
/// surfaces `fit` makes from the other records of their Z plane. `fit(z, records)` must be the
/// same procedure that makes the calibration file (degree selection included).
///
/// A plane whose fit fails leaves its held-out records out, and says so in `reason`.
pub fn held_out_check<E: std::fmt::Display>(
    records: &[LccRecord],
    config: &RunValidationConfig,
    fit: impl Fn(i64, &[&LccRecord]) -> Result<PlaneSurfaces, E>,
) -> HeldOutCheck {
    let nodes: BTreeSet<u32> = records.iter().map(|r| r.node_index).collect();
    let held = held_out_nodes(&nodes, config.holdout_share, config.holdout_seed);
    let mut check = HeldOutCheck {
        share: config.holdout_share,
        seed: config.holdout_seed,
        nodes: nodes.len(),
        nodes_held_out: held.len(),
        records_held_out: 0,
        coefficients: Vec::new(),
        rms_z: f64::NAN,
        pass_range: config.holdout_rms_sigma_range,
        verdict: Verdict::NotMeasured,
        reason: None,
    };
    if held.is_empty() {
        check.reason = Some(format!(
            "no node held out ({} node(s), share {})",
            nodes.len(),
            config.holdout_share
        ));
        return check;
    }
    let mut planes: BTreeMap<i64, (Vec<&LccRecord>, Vec<&LccRecord>)> = BTreeMap::new();
    for r in records {
        let entry = planes.entry(r.node_z_counts).or_default();
        if held.contains(&r.node_index) {
            entry.1.push(r);
        } else {
            entry.0.push(r);
        }
    }
    // z-scores and errors per coefficient, in the coefficient's display unit.
    let mut z: [Vec<f64>; 3] = Default::default();
    let mut err: [Vec<f64>; 3] = Default::default();
    let mut sd: [Vec<f64>; 3] = Default::default();
    let mut failures = Vec::new();
    for (plane_z, (held_in, held_out)) in &planes {
        if held_out.is_empty() {
            continue;
        }
        let plane = match fit(*plane_z, held_in) {
            Ok(plane) => plane,
            Err(e) => {
                failures.push(format!("plane z = {plane_z}: {e}"));
                continue;
            }
        };
        let x: Vec<f64> = held_in.iter().map(|r| r.lcs_x_counts).collect();
        let y: Vec<f64> = held_in.iter().map(|r| r.lcs_y_counts).collect();
        let at: Vec<(f64, f64)> = held_out
            .iter()
            .map(|r| (r.lcs_x_counts, r.lcs_y_counts))
            .collect();
        for (k, c) in Coefficient::ALL.into_iter().enumerate() {
            let fitted = c.surface(&plane);
            let values: Vec<f64> = held_in.iter().map(|r| c.value(r)).collect();
            let h = match leverages(&Observations::new(&x, &y, &values), &fitted.surface, &at) {
                Ok(h) => h,
                Err(e) => {
                    failures.push(format!("plane z = {plane_z}, {}: {e}", c.name()));
                    continue;
                }
            };
            let (_, scale) = c.unit();
            for (r, h) in held_out.iter().zip(h) {
                let predicted = fitted.surface.evaluate(r.lcs_x_counts, r.lcs_y_counts);
                let s = fitted.sigma * (1.0 + h).sqrt();
                let e = c.value(r) - predicted;
                if s > 0.0 && e.is_finite() {
                    z[k].push(e / s);
                    err[k].push(e * scale);
                    sd[k].push(s * scale);
                }
            }
        }
        check.records_held_out += held_out.len();
    }
    let rms = |v: &[f64]| (v.iter().map(|t| t * t).sum::<f64>() / v.len() as f64).sqrt();
    for (k, c) in Coefficient::ALL.into_iter().enumerate() {
        if z[k].is_empty() {
            continue;
        }
        check.coefficients.push(HeldOutCoefficient {
            coefficient: c.name(),
            records: z[k].len(),
            rms_z: rms(&z[k]),
            max_abs_z: z[k].iter().fold(0.0_f64, |m, t| m.max(t.abs())),
            rms_error: rms(&err[k]),
            rms_prediction_sd: rms(&sd[k]),
            unit: c.unit().0,
        });
    }
    let all: Vec<f64> = z.iter().flatten().copied().collect();
    if all.is_empty() {
        check.reason = Some(if failures.is_empty() {
            "no held-out record could be compared".to_owned()
        } else {
            failures.join("; ")
        });
        return check;
    }
    check.rms_z = rms(&all);
    let [lo, hi] = config.holdout_rms_sigma_range;
    let out: Vec<String> = check
        .coefficients
        .iter()
        .filter(|c| !(lo..=hi).contains(&c.rms_z))
        .map(|c| format!("{} {:.2}", c.coefficient, c.rms_z))
        .collect();
    check.verdict = if (lo..=hi).contains(&check.rms_z) && out.is_empty() {
        Verdict::Pass
    } else {
        Verdict::Warn
    };
    let mut reasons = failures;
    if !out.is_empty() {
        reasons.push(format!(
            "outside [{lo}, {hi}]: {}{}",
            out.join(", "),
            if check.rms_z > hi {
                " (the surfaces predict unseen places worse than their σ states)"
            } else if check.rms_z < lo {
                " (the surfaces' σ overstates their error at unseen places)"
            } else {
                ""
            }
        ));
    }
    check.reason = (!reasons.is_empty()).then(|| reasons.join("; "));
    check
}

/// One coefficient of the repeat agreement.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RepeatCoefficient {
    /// `kx`, `ky` or `alpha`.
    pub coefficient: &'static str,
    /// Pooled standard deviation of a record about its node's mean over the repeats,
    /// √(Σ (v − v̄)² / Σ (nᵢ − 1)), in `unit`.
    pub pooled_scatter: f64,
    /// RMS of the records' stated standard uncertainty, in `unit` (NaN if none is stated).
    pub stated_u_rms: f64,
    /// `pooled_scatter / stated_u_rms`: 1 when the stated uncertainty is honest.
    pub scatter_over_stated: f64,
    /// Mean over nodes of (last repeat − first repeat), in `unit`: a calibration that moved
    /// during the run.
    pub first_to_last_mean: f64,
    /// Standard error of `first_to_last_mean`, in `unit`.
    pub first_to_last_se: f64,
    /// Unit of the figures.
    pub unit: &'static str,
}

/// Repeat-to-repeat agreement of the l repeats at each node.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RepeatAgreement {
    /// Largest number of repeats of a node.
    pub repeats: usize,
    /// Places (run, Z plane, node and LCS index) measured in at least two repeats.
    pub places: usize,
    /// Per coefficient.
    pub coefficients: Vec<RepeatCoefficient>,
    /// The plan's largest accepted `scatter_over_stated`.
    pub scatter_over_stated_max: f64,
    /// Pass, warn or not measured.
    pub verdict: Verdict,
    /// Why not measured, or which coefficient is out of range.
    pub reason: Option<String>,
}

/// The repeat agreement of `records`: each place (run, Z plane, node, LCS index) measured in
/// two or more repeats contributes its records' deviations from its mean.
#[must_use]
pub fn repeat_agreement(records: &[LccRecord], config: &RunValidationConfig) -> RepeatAgreement {
    let mut places: BTreeMap<(&str, i64, u32, u32), Vec<&LccRecord>> = BTreeMap::new();
    for r in records {
        places
            .entry((r.run_id.as_str(), r.node_z_counts, r.node_index, r.lcs_index))
            .or_default()
            .push(r);
    }
    let repeats = places.values().map(Vec::len).max().unwrap_or(0);
    let groups: Vec<Vec<&LccRecord>> = places
        .into_values()
        .filter(|g| g.len() >= 2)
        .map(|mut g| {
            g.sort_by_key(|r| r.repeat_index);
            g
        })
        .collect();
    let mut agreement = RepeatAgreement {
        repeats,
        places: groups.len(),
        coefficients: Vec::new(),
        scatter_over_stated_max: config.repeat_scatter_over_stated_max,
        verdict: Verdict::NotMeasured,
        reason: None,
    };
    if groups.is_empty() {
        agreement.reason = Some(format!(
            "no place was measured in two repeats (largest number of repeats: {repeats})"
        ));
        return agreement;
    }
    let mut out = Vec::new();
    for c in Coefficient::ALL {
        let (unit, scale) = c.unit();
        let (mut ss, mut dof) = (0.0, 0usize);
        let (mut u2, mut nu) = (0.0, 0usize);
        let mut changes = Vec::with_capacity(groups.len());
        for g in &groups {
            let n = g.len() as f64;
            let mean = g.iter().map(|r| c.value(r)).sum::<f64>() / n;
            ss += g.iter().map(|r| (c.value(r) - mean).powi(2)).sum::<f64>();
            dof += g.len() - 1;
            for u in g.iter().filter_map(|r| c.stated_u(r)) {
                u2 += u * u;
                nu += 1;
            }
            if let (Some(first), Some(last)) = (g.first(), g.last()) {
                changes.push(c.value(last) - c.value(first));
            }
        }
        let pooled = (ss / dof as f64).sqrt() * scale;
        let stated = if nu > 0 {
            (u2 / nu as f64).sqrt() * scale
        } else {
            f64::NAN
        };
        let m = changes.len() as f64;
        let mean_change = changes.iter().sum::<f64>() / m;
        let se = if changes.len() >= 2 {
            (changes
                .iter()
                .map(|d| (d - mean_change).powi(2))
                .sum::<f64>()
                / (m - 1.0)
                / m)
                .sqrt()
        } else {
            f64::NAN
        };
        let ratio = pooled / stated;
        if ratio.is_finite() && ratio > config.repeat_scatter_over_stated_max {
            out.push(format!("{} {:.2}", c.name(), ratio));
        }
        agreement.coefficients.push(RepeatCoefficient {
            coefficient: c.name(),
            pooled_scatter: pooled,
            stated_u_rms: stated,
            scatter_over_stated: ratio,
            first_to_last_mean: mean_change * scale,
            first_to_last_se: se * scale,
            unit,
        });
    }
    if agreement
        .coefficients
        .iter()
        .all(|c| c.scatter_over_stated.is_nan())
    {
        agreement.reason = Some("the records state no uncertainty to compare with".to_owned());
        return agreement;
    }
    agreement.verdict = if out.is_empty() {
        Verdict::Pass
    } else {
        Verdict::Warn
    };
    if !out.is_empty() {
        agreement.reason = Some(format!(
            "repeat scatter over stated uncertainty above {}: {}",
            config.repeat_scatter_over_stated_max,
            out.join(", ")
        ));
    }
    agreement
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng as _;
    use rand_distr::{Distribution as _, Normal};
    use spm_regression::{FitOptions, fit};

    /// The true field: a tilted K̄x, a curved K̄y, a sloped α (nm/count, rad).
    fn truth(x: f64, y: f64) -> [f64; 3] {
        [
            0.05 * (1.0 + 1e-5 * x),
            0.05 * (1.0 - 2e-5 * y + 1e-9 * x * y),
            0.01 + 1e-6 * x,
        ]
    }

    /// Records on an `n`×`n` net, `repeats` passes, each LCC with Gaussian noise of standard
    /// deviation `noise` (relative for K, absolute rad for α) and a stated u of
    /// `stated_factor · noise`, plus `per_repeat` added to K̄x per repeat index.
    fn records(n: u32, repeats: u32, noise: f64, stated_factor: f64, per_repeat: f64) -> Vec<LccRecord> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let normal = Normal::new(0.0, 1.0).expect("normal");
        let mut out = Vec::new();
        for repeat in 0..repeats {
            for j in 0..n {
                for i in 0..n {
                    let x = -8000.0 + 16000.0 * f64::from(i) / f64::from(n - 1)
                        + rng.random_range(-50.0..50.0);
                    let y = -8000.0 + 16000.0 * f64::from(j) / f64::from(n - 1);
                    let [kx, ky, alpha] = truth(x, y);
                    let e = |rng: &mut rand_chacha::ChaCha8Rng| normal.sample(rng) * noise;
                    out.push(LccRecord {
                        scanner_id: "s".into(),
                        run_id: "r".into(),
                        acquired_unix_s: 0.0,
                        repeat_index: repeat,
                        node_index: j * n + i,
                        lcs_index: 0,
                        node_x_counts: x as i64,
                        node_y_counts: y as i64,
                        node_z_counts: 0,
                        lcs_x_counts: x,
                        lcs_y_counts: y,
                        lcs_z_counts: 0.0,
                        kx_nm_per_count: kx * (1.0 + e(&mut rng))
                            + per_repeat * f64::from(repeat),
                        ky_nm_per_count: ky * (1.0 + e(&mut rng)),
                        alpha_rad: alpha + e(&mut rng),
                        kz_nm_per_count: None,
                        u_kx_nm_per_count: Some(kx * noise * stated_factor),
                        u_ky_nm_per_count: Some(ky * noise * stated_factor),
                        u_alpha_rad: Some(noise * stated_factor),
                        u_kz_nm_per_count: None,
                        drift_vx_nm_per_s: 0.0,
                        drift_vy_nm_per_s: 0.0,
                        cycles_kept: 4,
                        cycles_discarded: 0,
                        quality: 1.0,
                        kz_x_counts: None,
                        kz_y_counts: None,
                    });
                }
            }
        }
        out
    }

    /// A degree-2 fit of each coefficient (the truth is at most degree 2).
    fn fit_plane(z: i64, records: &[&LccRecord]) -> Result<PlaneSurfaces, String> {
        let x: Vec<f64> = records.iter().map(|r| r.lcs_x_counts).collect();
        let y: Vec<f64> = records.iter().map(|r| r.lcs_y_counts).collect();
        let one = |v: Vec<f64>| -> Result<FittedSurface, String> {
            let obs = Observations::new(&x, &y, &v);
            let f = fit(&obs, 2, &FitOptions::default()).map_err(|e| e.to_string())?;
            Ok(FittedSurface::new(f.surface, f.sigma))
        };
        let kx = one(records.iter().map(|r| r.kx_nm_per_count).collect())?;
        let ky = one(records.iter().map(|r| r.ky_nm_per_count).collect())?;
        let alpha = one(records.iter().map(|r| r.alpha_rad).collect())?;
        Ok(PlaneSurfaces {
            z_counts: z as f64,
            n_records: records.len(),
            kyx_nm_per_count: ky.clone(),
            kyy_nm_per_count: ky.clone(),
            kx_nm_per_count: kx,
            ky_nm_per_count: ky,
            alpha_rad: alpha,
            kz_nm_per_count: None,
            bowl_z_counts: None,
            calibrated_region_counts: None,
        })
    }

    #[test]
    fn the_draw_is_seeded_and_holds_the_share() {
        let nodes: BTreeSet<u32> = (0..256).collect();
        let a = held_out_nodes(&nodes, 0.1, 1);
        assert_eq!(a.len(), 26);
        assert_eq!(a, held_out_nodes(&nodes, 0.1, 1));
        assert_ne!(a, held_out_nodes(&nodes, 0.1, 2));
        assert!(held_out_nodes(&nodes, 0.0, 1).is_empty());
        // A fit keeps at least three nodes.
        let few: BTreeSet<u32> = (0..4).collect();
        assert_eq!(held_out_nodes(&few, 0.5, 1).len(), 1);
    }

    #[test]
    fn an_honest_fit_predicts_held_out_nodes_at_one_sigma() {
        let recs = records(20, 1, 1e-3, 1.0, 0.0);
        let config = RunValidationConfig {
            holdout_share: 0.25,
            ..RunValidationConfig::default()
        };
        let check = held_out_check(&recs, &config, fit_plane);
        assert_eq!(check.nodes, 400);
        assert_eq!(check.nodes_held_out, 100);
        assert_eq!(check.records_held_out, 100);
        assert_eq!(check.verdict, Verdict::Pass, "{check:?}");
        // 300 ratios: the RMS of unit normals is 1 ± 0.04.
        assert!((0.88..1.12).contains(&check.rms_z), "{check:?}");
    }

    #[test]
    fn a_defect_at_held_out_nodes_is_found() {
        let mut recs = records(20, 1, 1e-3, 1.0, 0.0);
        let config = RunValidationConfig {
            holdout_share: 0.25,
            ..RunValidationConfig::default()
        };
        let held = held_out_nodes(
            &recs.iter().map(|r| r.node_index).collect(),
            config.holdout_share,
            config.holdout_seed,
        );
        // The held-out places see a K̄x 0.4 % off the field (a local defect the net's other
        // nodes cannot show): 4 σ.
        for r in recs.iter_mut().filter(|r| held.contains(&r.node_index)) {
            r.kx_nm_per_count *= 1.004;
        }
        let check = held_out_check(&recs, &config, fit_plane);
        assert_eq!(check.verdict, Verdict::Warn, "{check:?}");
        let kx = &check.coefficients[0];
        assert_eq!(kx.coefficient, "kx");
        assert!(kx.rms_z > 3.5 && kx.rms_z < 4.5, "{kx:?}");
        // K̄y and α are untouched: their ratios stay near 1 (100 ratios each: ± 0.07).
        assert!(check.coefficients[1].rms_z < 1.4, "{check:?}");
        assert!(check.coefficients[2].rms_z < 1.4, "{check:?}");
    }

    #[test]
    fn repeats_agree_with_an_honest_stated_uncertainty() {
        let recs = records(10, 3, 1e-3, 1.0, 0.0);
        let a = repeat_agreement(&recs, &RunValidationConfig::default());
        assert_eq!((a.repeats, a.places), (3, 100));
        assert_eq!(a.verdict, Verdict::Pass, "{a:?}");
        for c in &a.coefficients {
            assert!((0.85..1.15).contains(&c.scatter_over_stated), "{c:?}");
            assert!(c.first_to_last_mean.abs() < 3.0 * c.first_to_last_se, "{c:?}");
        }
    }

    #[test]
    fn an_understated_uncertainty_and_a_moving_calibration_are_found() {
        // u stated 3× too small, and K̄x grows by 2e-4 nm/count per repeat.
        let recs = records(10, 3, 1e-3, 1.0 / 3.0, 2e-4);
        let a = repeat_agreement(&recs, &RunValidationConfig::default());
        assert_eq!(a.verdict, Verdict::Warn, "{a:?}");
        let ky = &a.coefficients[1];
        assert!((2.5..3.5).contains(&ky.scatter_over_stated), "{ky:?}");
        // First to last repeat: 2 × 2e-4 nm/count = 0.4 pm/count.
        let kx = &a.coefficients[0];
        assert!(
            (kx.first_to_last_mean - 0.4).abs() < 3.0 * kx.first_to_last_se,
            "{kx:?}"
        );
        assert!(kx.first_to_last_mean / kx.first_to_last_se > 5.0, "{kx:?}");
    }

    #[test]
    fn one_repeat_is_not_measured() {
        let recs = records(5, 1, 1e-3, 1.0, 0.0);
        let a = repeat_agreement(&recs, &RunValidationConfig::default());
        assert_eq!(a.verdict, Verdict::NotMeasured);
        assert!(a.reason.is_some());
    }
}
