//! The vertical axis of a calibration against an instrument's ground truth (issue 15): the
//! `vertical` section of report.json — Kz surface error, bowl residual, the z-dependence of
//! K̄x and K̄y across the planes, and the trend of the Kz residuals with time. The surfaces
//! themselves (Kz, the bowl) are fitted by `spm_correction::fit`.

use serde::Serialize;
use spm_correction::SurfaceSet;
use spm_correction::fit::extent;
use spm_hal::truth::{GroundTruth, LateralState, VerticalTruth};
use spm_hal::{CountPoint, Counts};
use spm_records::LccRecord;

/// A z-slope measured across the Z planes against the oracle's.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SlopeComparison {
    /// Measured relative slope, per count of Z reading (from the planes' surfaces at the
    /// field centre).
    pub measured_per_count: f64,
    /// Its standard uncertainty.
    pub sigma_per_count: f64,
    /// The oracle's.
    pub true_per_count: f64,
    /// |measured − true| ≤ 2σ.
    pub within_2_sigma: bool,
}

/// One Z plane's vertical figures.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlaneVertical {
    /// Plane label (node z), counts.
    pub z_counts: f64,
    /// Mean Z reading of the plane's LCSs, counts.
    pub level_z_counts: f64,
    /// Records with Kz.
    pub kz_records: usize,
    /// Mean |Kz^r / Kz_true − 1| over the plane's nodes, %; the truth at the state right
    /// after a move (as the bowl's, [`PlaneVertical::bowl_residual_fraction`]).
    pub kz_mean_error_pct: Option<f64>,
    /// Largest of it, %.
    pub kz_max_error_pct: Option<f64>,
    /// RMS(bowl^r − bowl_true) / RMS(bowl_true) over the nodes, both relative to their means;
    /// the truth at the state right after a move (hysteresis midline, no creep yet).
    pub bowl_residual_fraction: Option<f64>,
    /// The same against the creep-settled reference state (the oracle's `true_lcc` state):
    /// the creep that has not happened by the time a node is measured (up to the settled
    /// total, ~8 % of the position on this scanner) scales the bowl's apparent curvature.
    pub bowl_residual_fraction_settled_creep: Option<f64>,
    /// χ² per degree of freedom of the Kz records about Kz^r with their own uncertainties:
    /// ≫ 1 means structure the surface does not model (or understated uncertainties).
    pub kz_chi2_per_dof: Option<f64>,
}

/// report.json's `vertical` (simulated backends only).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct VerticalReport {
    /// Mean over the planes' nodes of |Kz^r/Kz_true − 1|, %.
    pub kz_mean_error_pct: Option<f64>,
    /// Largest, %.
    pub kz_max_error_pct: Option<f64>,
    /// Worst plane's bowl residual fraction.
    pub bowl_residual_fraction: Option<f64>,
    /// The z-dependence of K̄x and K̄y recovered within 2σ (needs ≥ 3 planes).
    pub z_crosstalk_recovered: Option<bool>,
    /// The slopes behind it.
    pub z_crosstalk: Option<[SlopeComparison; 2]>,
    /// Trend of the Kz records' relative residuals (Kz / Kz^r − 1, all planes) with the
    /// acquisition time, % per hour: a Kz that changes while the calibration runs (a Z effect
    /// the static surfaces do not model) shows here.
    pub kz_residual_trend_pct_per_hour: Option<f64>,
    /// That trend over its standard error (the residuals' own scatter).
    pub kz_residual_trend_t: Option<f64>,
    /// The Kz residuals are structured: |trend t| > 5.
    pub kz_structured_residual: bool,
    /// Per plane.
    pub planes: Vec<PlaneVertical>,
}

/// Leverage `x₀ᵀ(XᵀX)⁻¹x₀` of the point (x₀, y₀) for `surface`'s polynomial fitted at the
/// points (x, y) ([`spm_regression::leverages`]): the variance of the surface's value there is
/// σ²·leverage. `None` when the design is singular.
fn leverage(
    surface: &spm_regression::Polynomial2,
    x: &[f64],
    y: &[f64],
    x0: f64,
    y0: f64,
) -> Option<f64> {
    let zeros = vec![0.0; x.len()];
    let observations = spm_regression::Observations::new(x, y, &zeros);
    spm_regression::leverages(&observations, surface, &[(x0, y0)])
        .ok()?
        .first()
        .copied()
}

/// Coarse-stage position of a plane label from the plan's Z levels.
fn coarse_of(plan: &spm_calibration::PlanConfig, z_counts: f64) -> i64 {
    plan.net
        .z_levels
        .iter()
        .find(|l| l.nominal_z_counts as f64 == z_counts)
        .and_then(|l| l.coarse_steps)
        .unwrap_or(0)
}

fn weighted_slope(points: &[(f64, f64, f64)]) -> Option<(f64, f64)> {
    // (x, y, σ) → slope and its σ from the stated σs: y = a + b·x weighted by 1/σ², the
    // rows scaled by 1/σ; var(b) is the unscaled covariance's (1, 1) element.
    if points.len() < 3 {
        return None;
    }
    let weight = |p: &(f64, f64, f64)| 1.0 / p.2.abs().max(1e-150);
    let rows: Vec<Vec<f64>> = points
        .iter()
        .map(|p| vec![weight(p), weight(p) * p.0])
        .collect();
    let rhs: Vec<f64> = points.iter().map(|p| weight(p) * p.1).collect();
    let fit = spm_regression::least_squares(&rows, &rhs, &[false, false]).ok()?;
    let slope = *fit.coefficients.get(1)?;
    let variance = *fit.unscaled_covariance.get(1)?.get(1)?;
    Some((slope, variance.max(0.0).sqrt()))
}

/// The vertical figures of a fitted surface set against an instrument's ground truth (the
/// simulator's oracle); `None` when it does not model the vertical axis. `records` are the
/// records the surfaces were fitted from.
pub fn evaluate(
    truth: &dyn GroundTruth,
    plan: &spm_calibration::PlanConfig,
    set: &SurfaceSet,
    records: &[LccRecord],
) -> Option<VerticalReport> {
    let vertical: &dyn VerticalTruth = truth.vertical()?;
    let mut planes = Vec::new();
    let mut kz_errors = Vec::new();
    // (time h, relative residual) of every Kz record.
    let mut residual_vs_time: Vec<(f64, f64)> = Vec::new();
    let t0 = records
        .iter()
        .map(|r| r.acquired_unix_s)
        .fold(f64::INFINITY, f64::min);
    let mut slopes_x = Vec::new();
    let mut slopes_y = Vec::new();
    let mut truth_x = Vec::new();
    let mut truth_y = Vec::new();
    for plane in &set.planes {
        let in_plane: Vec<&LccRecord> = records
            .iter()
            .filter(|r| r.node_z_counts as f64 == plane.z_counts)
            .collect();
        if in_plane.is_empty() {
            continue;
        }
        let level = in_plane.iter().map(|r| r.lcs_z_counts).sum::<f64>() / in_plane.len() as f64;
        let coarse = coarse_of(plan, plane.z_counts);
        // Kz^r at every node against the truth at the plane's level.
        let mut errors = Vec::new();
        let mut chi2 = 0.0;
        let mut n_kz = 0usize;
        if let Some(kz) = &plane.kz_nm_per_count {
            for r in &in_plane {
                let u = CountPoint::from_counts(r.lcs_x_counts, r.lcs_y_counts);
                let truth = vertical.kz_at(u, Counts(level), LateralState::JustMoved);
                let fitted = kz.surface.evaluate(r.lcs_x_counts, r.lcs_y_counts);
                errors.push(100.0 * (fitted / truth - 1.0).abs());
                if let (Some(k), Some(uk)) = (r.kz_nm_per_count, r.u_kz_nm_per_count)
                    && uk > 0.0
                {
                    let at = kz.surface.evaluate(
                        r.kz_x_counts.unwrap_or(r.lcs_x_counts),
                        r.kz_y_counts.unwrap_or(r.lcs_y_counts),
                    );
                    chi2 += ((k - at) / uk).powi(2);
                    residual_vs_time.push(((r.acquired_unix_s - t0) / 3600.0, k / at - 1.0));
                    n_kz += 1;
                }
            }
        }
        let kz_records = in_plane
            .iter()
            .filter(|r| r.kz_nm_per_count.is_some())
            .count();
        let dof = n_kz as f64
            - plane
                .kz_nm_per_count
                .as_ref()
                .map_or(0.0, |k| spm_regression::n_terms(k.surface.degree()) as f64);
        let kz_chi2_per_dof = (dof >= 1.0).then(|| chi2 / dof);
        // Bowl against the truth, both relative to their means over the nodes.
        let bowl_residual_fraction =
            bowl_fraction(plane, &in_plane, vertical, coarse, LateralState::JustMoved);
        let bowl_residual_fraction_settled_creep = bowl_fraction(
            plane,
            &in_plane,
            vertical,
            coarse,
            LateralState::CreepSettled,
        );
        // K̄x, K̄y at the field centre of the records (for the z-dependence).
        let xs: Vec<f64> = in_plane.iter().map(|r| r.lcs_x_counts).collect();
        let ys: Vec<f64> = in_plane.iter().map(|r| r.lcs_y_counts).collect();
        let f = extent(&xs, &ys);
        let (cx, cy) = (0.5 * (f.x_min + f.x_max), 0.5 * (f.y_min + f.y_max));
        let n = in_plane.len() as f64;
        let kx = plane.kx_nm_per_count.surface.evaluate(cx, cy);
        let ky = plane.ky_nm_per_count.surface.evaluate(cx, cy);
        // Standard errors of the surfaces' values at the centre (σ of eq. 14 × √leverage).
        let se = |f: &spm_correction::FittedSurface| {
            leverage(&f.surface, &xs, &ys, cx, cy)
                .map_or(f.sigma / n.sqrt(), |l| f.sigma * l.max(0.0).sqrt())
        };
        let sx = se(&plane.kx_nm_per_count);
        let sy = se(&plane.ky_nm_per_count);
        let t = vertical.true_lcc_at_reading(CountPoint::from_counts(cx, cy), Counts(level));
        slopes_x.push((level, kx, sx.max(1e-12)));
        slopes_y.push((level, ky, sy.max(1e-12)));
        truth_x.push((level, t.kx_nm_per_count, 1.0));
        truth_y.push((level, t.ky_nm_per_count, 1.0));
        kz_errors.extend(errors.iter().copied());
        planes.push(PlaneVertical {
            z_counts: plane.z_counts,
            level_z_counts: level,
            kz_records,
            kz_mean_error_pct: (!errors.is_empty())
                .then(|| errors.iter().sum::<f64>() / errors.len() as f64),
            kz_max_error_pct: errors.iter().copied().reduce(f64::max),
            bowl_residual_fraction,
            bowl_residual_fraction_settled_creep,
            kz_chi2_per_dof,
        });
    }
    if planes.is_empty() {
        return None;
    }
    let z_crosstalk = compare_slopes(&slopes_x, &truth_x).zip(compare_slopes(&slopes_y, &truth_y));
    let trend = residual_trend(&residual_vs_time);
    Some(VerticalReport {
        kz_mean_error_pct: (!kz_errors.is_empty())
            .then(|| kz_errors.iter().sum::<f64>() / kz_errors.len() as f64),
        kz_max_error_pct: kz_errors.iter().copied().reduce(f64::max),
        bowl_residual_fraction: planes
            .iter()
            .filter_map(|p| p.bowl_residual_fraction)
            .reduce(f64::max),
        z_crosstalk_recovered: z_crosstalk.map(|(x, y)| x.within_2_sigma && y.within_2_sigma),
        z_crosstalk: z_crosstalk.map(|(x, y)| [x, y]),
        kz_residual_trend_pct_per_hour: trend.map(|t| t.0),
        kz_residual_trend_t: trend.map(|t| t.1),
        kz_structured_residual: trend.is_some_and(|t| t.1.abs() > 5.0),
        planes,
    })
}

/// The bowl surface of `plane` against the truth's flat-sample Z reading at its records, both
/// relative to their means over the nodes: RMS of the difference over RMS of the truth.
fn bowl_fraction(
    plane: &spm_correction::PlaneSurfaces,
    in_plane: &[&LccRecord],
    vertical: &dyn VerticalTruth,
    coarse: i64,
    state: LateralState,
) -> Option<f64> {
    plane.bowl_z_counts.as_ref().and_then(|b| {
        let pairs: Vec<(f64, f64)> = in_plane
            .iter()
            .map(|r| {
                let u = CountPoint::from_counts(r.lcs_x_counts, r.lcs_y_counts);
                (
                    b.surface.evaluate(r.lcs_x_counts, r.lcs_y_counts),
                    vertical.flat_sample_z_reading(u, coarse, state).value(),
                )
            })
            .collect();
        let n = pairs.len() as f64;
        let mb = pairs.iter().map(|p| p.0).sum::<f64>() / n;
        let mt = pairs.iter().map(|p| p.1).sum::<f64>() / n;
        let rms_t = (pairs.iter().map(|p| (p.1 - mt).powi(2)).sum::<f64>() / n).sqrt();
        let rms_r = (pairs
            .iter()
            .map(|p| ((p.0 - mb) - (p.1 - mt)).powi(2))
            .sum::<f64>()
            / n)
            .sqrt();
        (rms_t > 0.0).then(|| rms_r / rms_t)
    })
}

/// The measured relative slope of a coefficient against Z (per count, normalised by its mean)
/// against the truth's, and whether they agree within 2 σ.
fn compare_slopes(m: &[(f64, f64, f64)], t: &[(f64, f64, f64)]) -> Option<SlopeComparison> {
    let (sm, ss) = weighted_slope(m)?;
    let (st, _) = weighted_slope(t)?;
    // Relative slopes (per count), normalised by the mean coefficient.
    let mean_m = m.iter().map(|p| p.1).sum::<f64>() / m.len() as f64;
    let mean_t = t.iter().map(|p| p.1).sum::<f64>() / t.len() as f64;
    let (measured, sigma, truth) = (sm / mean_m, ss / mean_m, st / mean_t);
    Some(SlopeComparison {
        measured_per_count: measured,
        sigma_per_count: sigma,
        true_per_count: truth,
        within_2_sigma: (measured - truth).abs() <= 2.0 * sigma,
    })
}

/// The linear trend of the Kz records' relative residuals against time (% per hour) and its
/// t value; `None` under 4 records.
fn residual_trend(residual_vs_time: &[(f64, f64)]) -> Option<(f64, f64)> {
    (residual_vs_time.len() >= 4).then(|| {
        let n = residual_vs_time.len() as f64;
        let mt = residual_vs_time.iter().map(|p| p.0).sum::<f64>() / n;
        let mr = residual_vs_time.iter().map(|p| p.1).sum::<f64>() / n;
        let stt: f64 = residual_vs_time.iter().map(|p| (p.0 - mt).powi(2)).sum();
        let str_: f64 = residual_vs_time
            .iter()
            .map(|p| (p.0 - mt) * (p.1 - mr))
            .sum();
        let b = if stt > 0.0 { str_ / stt } else { 0.0 };
        let ss: f64 = residual_vs_time
            .iter()
            .map(|p| (p.1 - mr - b * (p.0 - mt)).powi(2))
            .sum();
        let se = (ss / (n - 2.0) / stt.max(1e-300)).sqrt();
        (100.0 * b, if se > 0.0 { b / se } else { 0.0 })
    })
}

#[cfg(test)]
mod tests {
    use super::leverage;

    /// The leverage of a plane fitted at the four corners (±1, ±1) and the centre, against
    /// its closed form 1/n + x₀²/Σx² + y₀²/Σy² (the design's columns are orthogonal there).
    #[test]
    fn a_plane_s_leverage_is_its_closed_form() -> Result<(), spm_regression::RegressionError> {
        let x = [-1.0, 1.0, -1.0, 1.0, 0.0];
        let y = [-1.0, -1.0, 1.0, 1.0, 0.0];
        let plane = spm_regression::Polynomial2::new(1, (0.0, 0.0), (1.0, 1.0), vec![0.0; 3])?;
        for (x0, y0) in [(0.0, 0.0), (0.5, -0.25), (2.0, 3.0)] {
            let expected = 1.0 / 5.0 + x0 * x0 / 4.0 + y0 * y0 / 4.0;
            let h = leverage(&plane, &x, &y, x0, y0);
            assert!(
                h.is_some_and(|h| (h - expected).abs() < 1e-12),
                "({x0}, {y0}): {h:?} against {expected}"
            );
        }
        // Three collinear records cannot carry a plane.
        assert_eq!(
            leverage(&plane, &[0.0, 1.0, 2.0], &[0.0, 1.0, 2.0], 0.0, 0.0),
            None
        );
        Ok(())
    }
}
