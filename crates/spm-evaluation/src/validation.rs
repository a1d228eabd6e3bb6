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
//! - [`lattice_check`]: counter-scanned pairs of the standard imaged over the calibrated
//!   region after the run (by the caller, which holds the instrument:
//!   [`crate::images::take_images_without_truth`]), corrected as `spmcal correct` does; the
//!   lattice constant and angles measured on each, before and after.
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

/// Fewest held-out records for a verdict: below it the RMS ratio is reported without one.
pub const MIN_RECORDS_FOR_VERDICT: usize = 10;

/// Where a node stands: its commanded (x, y, z), counts. The net's node index is in
/// trajectory order, which a serpentine plan reverses from one repeat to the next, so places,
/// not indices, identify a node across repeats.
pub type NodePlace = (i64, i64, i64);

/// The place of a record's node.
#[must_use]
pub fn node_place(r: &LccRecord) -> NodePlace {
    (r.node_x_counts, r.node_y_counts, r.node_z_counts)
}

/// The nodes to hold out: a seeded permutation of the distinct places, the first
/// `round(share · n)` of it, at most all but three (a fit needs the rest), and none when
/// `share` is 0.
#[must_use]
pub fn held_out_nodes(nodes: &BTreeSet<NodePlace>, share: f64, seed: u64) -> BTreeSet<NodePlace> {
    let mut all: Vec<NodePlace> = nodes.iter().copied().collect();
    let wanted = (share * all.len() as f64).round() as usize;
    let k = wanted.min(all.len().saturating_sub(3));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    all.shuffle(&mut rng);
    all.into_iter().take(k).collect()
}

/// The held-out check: the records of the held-out nodes ([`held_out_nodes`], by place)
/// against the
/// surfaces `fit` makes from the other records of their Z plane. `fit(z, records)` must be the
/// same procedure that makes the calibration file (degree selection included).
///
/// A plane whose fit fails leaves its held-out records out, and says so in `reason`.
pub fn held_out_check<E: std::fmt::Display>(
    records: &[LccRecord],
    config: &RunValidationConfig,
    fit: impl Fn(i64, &[&LccRecord]) -> Result<PlaneSurfaces, E>,
) -> HeldOutCheck {
    let nodes: BTreeSet<NodePlace> = records.iter().map(node_place).collect();
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
        if held.contains(&node_place(r)) {
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
    // Every vector here is non-empty (err, sd and z grow together; `all` is checked below).
    let rms = |v: &[f64]| spm_regression::rms(v).unwrap_or(f64::NAN);
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
    if check.records_held_out < MIN_RECORDS_FOR_VERDICT {
        check.reason = Some(format!(
            "{} held-out record(s): a verdict needs at least {MIN_RECORDS_FOR_VERDICT} (the RMS \
             of a few unit normals scatters by ±1/√(2n))",
            check.records_held_out
        ));
        return check;
    }
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
    /// Places (run, node place and LCS index) measured in at least two repeats.
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

/// The repeat agreement of `records`: each place (run, node place, LCS index) measured in
/// two or more repeats contributes its records' deviations from its mean.
#[must_use]
pub fn repeat_agreement(records: &[LccRecord], config: &RunValidationConfig) -> RepeatAgreement {
    let mut places: BTreeMap<(&str, NodePlace, u32), Vec<&LccRecord>> = BTreeMap::new();
    for r in records {
        places
            .entry((r.run_id.as_str(), node_place(r), r.lcs_index))
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

/// The lattice at one place of the corrected standard.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LatticePlace {
    /// Place label ("centre", "corner −x −y", …).
    pub place: String,
    /// The centre of the place's direct image, commanded counts.
    pub centre_counts: [f64; 2],
    /// Lattice-constant error of the uncorrected pair (nominal sensitivity, drift removed by
    /// the pair), % (None: not measured).
    pub uncorrected_error_pct: Option<f64>,
    /// Largest angle error of the uncorrected pair, degrees.
    pub uncorrected_angle_error_deg: Option<f64>,
    /// Lattice-constant error after `spmcal correct` with the run's calibration file, %.
    pub corrected_error_pct: Option<f64>,
    /// Largest angle error after it, degrees.
    pub corrected_angle_error_deg: Option<f64>,
    /// Lattice-constant error with the static surfaces alone (the file's dynamics not
    /// applied: `spmcal correct --static`), %.
    pub static_error_pct: Option<f64>,
    /// Largest angle error with the static surfaces alone, degrees.
    pub static_angle_error_deg: Option<f64>,
    /// Lattice-constant error with each image's counter-scanned partner (`spmcal correct
    /// --counter`: the drift between the pair's frames removed too), % (None: not measured, or
    /// the calibration holds no dynamics).
    pub counter_error_pct: Option<f64>,
    /// Largest angle error with the counter partner, degrees.
    pub counter_angle_error_deg: Option<f64>,
}

/// The lattice of the standard, imaged after the run over the calibrated region and
/// corrected as a user corrects (`spmcal correct`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LatticeCheck {
    /// What was measured: counter-scanned pairs imaged after the run, or the stored image a
    /// virtual run calibrated on, cell by cell.
    pub measured_on: LatticeSource,
    /// The standard's lattice constant, nm.
    pub lattice_constant_nm: f64,
    /// Pixels per line and lines of each image.
    pub pixels: u32,
    /// Pixel step, counts.
    pub step_counts: f64,
    /// Every place.
    pub places: Vec<LatticePlace>,
    /// Places measured after correction.
    pub corrected_measured: usize,
    /// Largest |lattice-constant error| after correction, % (NaN: none measured).
    pub corrected_max_error_pct: f64,
    /// RMS lattice-constant error after correction, % (its spread over the field).
    pub corrected_rms_error_pct: f64,
    /// Largest angle error after correction, degrees.
    pub corrected_max_angle_error_deg: f64,
    /// RMS lattice-constant error of the uncorrected pairs, %.
    pub uncorrected_rms_error_pct: f64,
    /// Places measured with the static surfaces alone.
    pub static_measured: usize,
    /// RMS lattice-constant error with the static surfaces alone, %.
    pub static_rms_error_pct: f64,
    /// Places measured with the counter partner (0 without dynamics).
    pub counter_measured: usize,
    /// RMS lattice-constant error with the counter partner, %.
    pub counter_rms_error_pct: f64,
    /// Whether the calibration file holds dynamics (then `spmcal correct` applies them, and
    /// the static column shows what the surfaces alone give).
    pub dynamics_applied: bool,
    /// The plan's thresholds: |error| %, angle degrees.
    pub thresholds: [f64; 2],
    /// Pass, warn or not measured.
    pub verdict: Verdict,
    /// Why not measured, or what is out of range.
    pub reason: Option<String>,
}

/// What a [`LatticeCheck`] measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LatticeSource {
    /// Counter-scanned pairs of the standard imaged after the run at places over the
    /// calibrated region ([`lattice_check`]).
    CounterPairs,
    /// The stored image a virtual run calibrated on, corrected whole and measured in the
    /// cells of a grid ([`lattice_check_of_cells`]).
    StoredImageCells,
}

/// The image set of the lattice check: `lattice_places_per_side`² places over the region, one
/// size with at least 6 pixels per lattice constant (129 pixels, ≈ 20 lattice constants),
/// the plan's dwell.
#[must_use]
pub fn lattice_image_set(plan: &spm_calibration::PlanConfig) -> crate::images::ImageSetConfig {
    let a_counts = plan.standard.lattice_constant_nm / plan.standard.nominal_nm_per_count;
    let step = (a_counts / 6.0).floor().max(1.0);
    crate::images::ImageSetConfig {
        places_per_side: plan.validation.lattice_places_per_side as usize,
        sizes: vec![crate::images::ImageSize {
            pixels: 129,
            step_counts: step,
        }],
        dwells_s: vec![plan.motion.pixel_dwell_s],
        pause: plan.pause,
        move_speed_counts_per_s: plan.motion.move_speed_counts_per_s,
        settle_s: plan.motion.settle_s,
        lattice_constant_nm: plan.standard.lattice_constant_nm,
        nominal_nm_per_count: plan.standard.nominal_nm_per_count,
        min_pixels_per_lattice_constant: 5.0,
    }
}

/// The lattice check on `images` (counter-scanned pairs taken with [`lattice_image_set`]):
/// each pair's lattice uncorrected (the nominal sensitivity), corrected with `set` as
/// `spmcal correct` does (the verdict's figure), and with the static surfaces alone
/// (`--static`, for comparison when the file holds dynamics).
///
/// # Errors
/// As the correction of an image.
pub fn lattice_check(
    images: &[crate::images::TestImage],
    set: &spm_correction::SurfaceSet,
    config: &crate::images::ImageSetConfig,
    thresholds: &RunValidationConfig,
) -> Result<LatticeCheck, crate::images::ImageBenchmarkError> {
    use crate::images::{ImageCorrection, ImageMethod, PairLattice, lattice_of_pairs};
    let a = config.lattice_constant_nm;
    let z = set.planes.first().map_or(0.0, |p| p.z_counts);
    let nominal = PlaneSurfaces::constant(
        z,
        config.nominal_nm_per_count,
        config.nominal_nm_per_count,
        0.0,
    )?;
    let uncorrected = lattice_of_pairs(
        images,
        &ImageMethod {
            name: "uncorrected".to_owned(),
            correction: ImageCorrection::Field(Box::new(
                nominal.field(spm_correction::Route::Products),
            )),
        },
        config,
    )?;
    let corrected = lattice_of_pairs(
        images,
        &ImageMethod {
            name: "user_file".to_owned(),
            correction: ImageCorrection::UserFile(Box::new(set.clone())),
        },
        config,
    )?;
    let mut surfaces_only = set.clone();
    surfaces_only.dynamics = None;
    let static_only = lattice_of_pairs(
        images,
        &ImageMethod {
            name: "user_file_static".to_owned(),
            correction: ImageCorrection::UserFile(Box::new(surfaces_only)),
        },
        config,
    )?;
    let with_partner = match set.dynamics {
        Some(_) => lattice_of_pairs(
            images,
            &ImageMethod {
                name: "user_file_counter".to_owned(),
                correction: ImageCorrection::UserFileCounter {
                    set: Box::new(set.clone()),
                    spacing: spm_apply::ruler::LatticeRuler {
                        constant_nm: a,
                        ..spm_apply::ruler::LatticeRuler::hopg()
                    },
                },
            },
            config,
        )?,
        None => Vec::new(),
    };
    let figures = |l: &PairLattice| match *l {
        PairLattice::Measured { a_nm, angle_deg } => {
            (Some(100.0 * (a_nm / a - 1.0)), Some(angle_deg))
        }
        _ => (None, None),
    };
    let places: Vec<LatticePlace> = uncorrected
        .iter()
        .zip(&corrected)
        .zip(&static_only)
        .enumerate()
        .map(|(k, (((pair, place, u), (_, _, c)), (_, _, st)))| {
            let (ue, ua) = figures(u);
            let (ce, ca) = figures(c);
            let (se, sa) = figures(st);
            let (pe, pa) = with_partner
                .get(k)
                .map_or((None, None), |(_, _, l)| figures(l));
            let centre_counts = images
                .iter()
                .find(|i| i.pair == *pair && i.direction == spm_hal::ScanDirection::Direct)
                .map_or([f64::NAN; 2], |i| {
                    let m = &i.map;
                    let half = |n: usize| 0.5 * (n.max(1) - 1) as f64 * m.pixel_step.value();
                    [
                        m.origin.x.value() + half(m.columns),
                        m.origin.y.value() + half(m.rows),
                    ]
                });
            LatticePlace {
                place: place.clone(),
                centre_counts,
                uncorrected_error_pct: ue,
                uncorrected_angle_error_deg: ua,
                corrected_error_pct: ce,
                corrected_angle_error_deg: ca,
                static_error_pct: se,
                static_angle_error_deg: sa,
                counter_error_pct: pe,
                counter_angle_error_deg: pa,
            }
        })
        .collect();
    Ok(summarise_places(
        LatticeSource::CounterPairs,
        places,
        a,
        (
            config.sizes.first().map_or(0, |s| s.pixels),
            config.sizes.first().map_or(0.0, |s| s.step_counts),
        ),
        set.dynamics.is_some(),
        thresholds,
    ))
}

/// A lattice check's figures over its places (RMS and largest errors of each column) and its
/// verdict against the plan's thresholds. `image` is the pixels per line and the pixel step
/// (counts) of the images measured.
fn summarise_places(
    measured_on: LatticeSource,
    places: Vec<LatticePlace>,
    lattice_constant_nm: f64,
    (pixels, step_counts): (u32, f64),
    dynamics_applied: bool,
    thresholds: &RunValidationConfig,
) -> LatticeCheck {
    let rms = |v: &[f64]| spm_regression::rms(v).unwrap_or(f64::NAN);
    let column =
        |f: fn(&LatticePlace) -> Option<f64>| -> Vec<f64> { places.iter().filter_map(f).collect() };
    let ce = column(|p| p.corrected_error_pct);
    let ca = column(|p| p.corrected_angle_error_deg);
    let ue = column(|p| p.uncorrected_error_pct);
    let se = column(|p| p.static_error_pct);
    let pe = column(|p| p.counter_error_pct);
    let max_abs = |v: &[f64]| {
        if v.is_empty() {
            f64::NAN
        } else {
            v.iter().fold(0.0_f64, |m, t| m.max(t.abs()))
        }
    };
    let mut check = LatticeCheck {
        measured_on,
        lattice_constant_nm,
        pixels,
        step_counts,
        corrected_measured: ce.len(),
        corrected_max_error_pct: max_abs(&ce),
        corrected_rms_error_pct: rms(&ce),
        corrected_max_angle_error_deg: max_abs(&ca),
        uncorrected_rms_error_pct: rms(&ue),
        static_measured: se.len(),
        static_rms_error_pct: rms(&se),
        counter_measured: pe.len(),
        counter_rms_error_pct: rms(&pe),
        dynamics_applied,
        places,
        thresholds: [
            thresholds.lattice_constant_error_pct_max,
            thresholds.lattice_angle_error_deg_max,
        ],
        verdict: Verdict::NotMeasured,
        reason: None,
    };
    judge_lattice(&mut check);
    check
}

/// A part of an image's lattice as a lattice fit over its features measures it
/// (`spm_modelcheck::survey`, what `spmcal lattice` reports).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PartFigures {
    /// True over apparent lattice length along x (1: right).
    pub scale_x: f64,
    /// The same along y.
    pub scale_y: f64,
    /// Obliquity of the axes, degrees (0: orthogonal).
    pub obliquity_deg: f64,
}

impl PartFigures {
    /// The lattice-constant error of the part, %: of the two axes' apparent lattice
    /// constants (a / scale), the one farther from a.
    #[must_use]
    pub fn lattice_constant_error_pct(&self) -> f64 {
        let (ex, ey) = (
            100.0 * (1.0 / self.scale_x - 1.0),
            100.0 * (1.0 / self.scale_y - 1.0),
        );
        if ex.abs() >= ey.abs() { ex } else { ey }
    }
}

/// One cell of a grid over a stored image of the standard, its lattice before and after the
/// correction ([`lattice_check_of_cells`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SurveyCell {
    /// The cell's label ("cell (column, row)").
    pub place: String,
    /// Its centre, commanded counts.
    pub centre_counts: [f64; 2],
    /// The stored image's lattice there through the nominal sensitivity (`None`: too few
    /// features).
    pub uncorrected: Option<PartFigures>,
    /// The lattice there after `spmcal correct` with the run's calibration file.
    pub corrected: Option<PartFigures>,
}

/// The lattice check of a run on a stored image (the virtual backend), whose counter-scanned
/// pairs would only resample the same frozen pixels: the image itself, corrected as a user
/// corrects it, its lattice measured cell by cell (`cells`, e.g. a `lattice_places_per_side`²
/// grid), each cell's figures against the plan's thresholds as the pairs' are. `image` is the
/// image's pixels per line and pixel step in counts.
#[must_use]
pub fn lattice_check_of_cells(
    cells: &[SurveyCell],
    lattice_constant_nm: f64,
    image: (u32, f64),
    dynamics_applied: bool,
    thresholds: &RunValidationConfig,
) -> LatticeCheck {
    let error = |p: &Option<PartFigures>| p.map(|f| f.lattice_constant_error_pct());
    let angle = |p: &Option<PartFigures>| p.map(|f| f.obliquity_deg.abs());
    let places = cells
        .iter()
        .map(|c| LatticePlace {
            place: c.place.clone(),
            centre_counts: c.centre_counts,
            uncorrected_error_pct: error(&c.uncorrected),
            uncorrected_angle_error_deg: angle(&c.uncorrected),
            corrected_error_pct: error(&c.corrected),
            corrected_angle_error_deg: angle(&c.corrected),
            static_error_pct: None,
            static_angle_error_deg: None,
            counter_error_pct: None,
            counter_angle_error_deg: None,
        })
        .collect();
    summarise_places(
        LatticeSource::StoredImageCells,
        places,
        lattice_constant_nm,
        image,
        dynamics_applied,
        thresholds,
    )
}

/// The lattice check's verdict against its thresholds, with the reasons.
fn judge_lattice(check: &mut LatticeCheck) {
    let [e_max, a_max] = check.thresholds;
    let failed = check.places.len() - check.corrected_measured;
    if check.corrected_measured == 0 {
        check.reason = Some(format!(
            "the lattice was measured at none of {} places after correction",
            check.places.len()
        ));
        return;
    }
    let mut problems = Vec::new();
    if check.corrected_max_error_pct > e_max {
        problems.push(format!(
            "lattice constant off by up to {:.2} % (pass ≤ {e_max} %)",
            check.corrected_max_error_pct
        ));
    }
    if check.corrected_max_angle_error_deg > a_max {
        problems.push(format!(
            "angles off by up to {:.2}° (pass ≤ {a_max}°)",
            check.corrected_max_angle_error_deg
        ));
    }
    if failed > 0 {
        problems.push(format!(
            "not measured at {failed} of {} places",
            check.places.len()
        ));
    }
    check.verdict = if problems.is_empty() {
        Verdict::Pass
    } else {
        Verdict::Warn
    };
    check.reason = (!problems.is_empty()).then(|| problems.join("; "));
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
    fn records(
        n: u32,
        repeats: u32,
        noise: f64,
        stated_factor: f64,
        per_repeat: f64,
    ) -> Vec<LccRecord> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let normal = Normal::new(0.0, 1.0).expect("normal");
        let mut out = Vec::new();
        for repeat in 0..repeats {
            for j in 0..n {
                for i in 0..n {
                    let node_x = -8000.0 + 16000.0 * f64::from(i) / f64::from(n - 1);
                    let y = -8000.0 + 16000.0 * f64::from(j) / f64::from(n - 1);
                    // The LCS lies near its node; the trajectory is serpentine, so the node
                    // index runs backwards in odd repeats.
                    let x = node_x + rng.random_range(-50.0..50.0);
                    let index = j * n + i;
                    let [kx, ky, alpha] = truth(x, y);
                    let e = |rng: &mut rand_chacha::ChaCha8Rng| normal.sample(rng) * noise;
                    out.push(LccRecord {
                        scanner_id: "s".into(),
                        run_id: "r".into(),
                        acquired_unix_s: 0.0,
                        repeat_index: repeat,
                        node_index: if repeat % 2 == 1 {
                            n * n - 1 - index
                        } else {
                            index
                        },
                        lcs_index: 0,
                        node_x_counts: node_x as i64,
                        node_y_counts: y as i64,
                        node_z_counts: 0,
                        lcs_x_counts: x,
                        lcs_y_counts: y,
                        lcs_z_counts: 0.0,
                        kx_nm_per_count: kx * (1.0 + e(&mut rng)) + per_repeat * f64::from(repeat),
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
            form: spm_correction::SurfaceForm::Independent,
        })
    }

    #[test]
    fn the_draw_is_seeded_and_holds_the_share() {
        let nodes: BTreeSet<NodePlace> = (0..256).map(|i| (i % 16, i / 16, 0)).collect();
        let a = held_out_nodes(&nodes, 0.1, 1);
        assert_eq!(a.len(), 26);
        assert_eq!(a, held_out_nodes(&nodes, 0.1, 1));
        assert_ne!(a, held_out_nodes(&nodes, 0.1, 2));
        assert!(held_out_nodes(&nodes, 0.0, 1).is_empty());
        // A fit keeps at least three nodes.
        let few: BTreeSet<NodePlace> = (0..4).map(|i| (i, 0, 0)).collect();
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
            &recs.iter().map(node_place).collect(),
            config.holdout_share,
            config.holdout_seed,
        );
        // The held-out places see a K̄x 0.4 % off the field (a local defect the net's other
        // nodes cannot show): 4 σ.
        for r in recs.iter_mut().filter(|r| held.contains(&node_place(r))) {
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
            assert!(
                c.first_to_last_mean.abs() < 3.0 * c.first_to_last_se,
                "{c:?}"
            );
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
