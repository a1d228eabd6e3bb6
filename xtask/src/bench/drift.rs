//! Drift insensitivity: the error of an A→B lattice vector (its relative
//! error is the LCC error it gives) against the drift velocity, for skipping
//! (spm-fos `skip`), counter-scanning (spm-fos `counter_scan`) and a single
//! aperture scan, judged by the simulator's oracle (true atom sites, true drift).
//!
//! Scanner: `SimConfig::ideal()` with white Z noise at SNR 10 and a constant
//! drift along the diagonal; the set-up of spm-fos's simulator tests (segments
//! 16×16 px at 0.2 ms/px, aperture 64×64 px at 0.3 ms/px, 4 kept skipping cycles).
//!
//! This module runs the scans and prints; the figures (relative errors, true sites, the
//! nearest-neighbour pairs, the RMS per velocity) are `spm_evaluation::drift`'s.

use super::Context;
use crate::XtaskError;
pub use spm_evaluation::drift::{DriftPoint, DriftResults};
use spm_evaluation::drift::{
    ideal_scanner_site, nearest_neighbour_errors_pct, relative_error_pct, site_vector_counts,
};
use spm_features::{DetectionConfig, Feature, LcsConfig};
use spm_fos::{
    ApertureParams, AttachParams, CounterScanParams, MonitorParams, Motion, Raster, SkipOutcome,
    SkipParams, aperture, attach, counter_scan, skip,
};
use spm_hal::{CountPoint, CountVector, CountVelocity, NmPoint};
use spm_sim::{FeatureKind, SimConfig, Simulator};

/// Nominal lateral sensitivity of the ideal scanner, nm/count.
const K: f64 = 0.02;
/// HOPG lattice constant in counts at `K`.
const A: f64 = 0.2461 / K;

fn simulator(seed: u64, v_nm_per_s: f64) -> Result<Simulator, XtaskError> {
    let mut config = SimConfig::ideal();
    config.seed = seed;
    config.measurement.z_white_noise_nm = 0.08 / 10.0;
    let c = v_nm_per_s / std::f64::consts::SQRT_2;
    config.drift.velocity_x_nm_per_s = c;
    config.drift.velocity_y_nm_per_s = c;
    Simulator::new(config).map_err(|e| XtaskError::step("simulator", e))
}

fn raster(pixels: u32, dwell_s: f64) -> Raster {
    Raster {
        pixels,
        pixel_step_counts: 1.0,
        pixel_dwell_s: dwell_s,
    }
}

fn detection() -> DetectionConfig {
    DetectionConfig {
        min_separation_px: 0.4 * A,
        ..DetectionConfig::default()
    }
}

/// The true atom site under a feature of the ideal scanner (F(u) = K·u).
fn site(sim: &Simulator, f: &Feature) -> Option<NmPoint> {
    let s = ideal_scanner_site(f.position, K, sim.oracle().drift_displacement(f.time));
    sim.oracle()
        .features_near(s, 0.15)
        .iter()
        .find(|f| f.kind == FeatureKind::Atom && f.position.distance(s).value() < 0.05)
        .map(|f| f.position)
}

fn true_vector(sim: &Simulator, a: &Feature, b: &Feature) -> Option<CountVector> {
    Some(site_vector_counts(site(sim, a)?, site(sim, b)?, K))
}

/// (skipping, single scan, counter-scan) relative errors of one run, or None
/// when a step did not complete (recorded as a missed run).
fn one_run(seed: u64, v: f64) -> Result<Option<(f64, f64, Vec<f64>)>, XtaskError> {
    let mut sim = simulator(seed, v)?;
    let start = CountPoint::from_counts(200.0, -150.0);
    let mut attach_params = AttachParams::new(raster(32, 2e-4), raster(16, 2e-4), 6.0, 10.0);
    attach_params.first_detection = detection();
    attach_params.segment_detection = detection();
    let attached =
        attach(&mut sim, start, &attach_params).map_err(|e| XtaskError::step("attach", e))?;
    let Some(a0) = attached.feature.filter(|_| attached.is_settled()) else {
        return Ok(None);
    };
    let ap_params = ApertureParams {
        raster: raster(64, 3e-4),
        detection: detection(),
        lcs: LcsConfig::hopg(spm_hal::NmPerCount(K)),
        motion: Motion::TYPICAL,
    };
    let ap =
        aperture(&mut sim, a0.position, &ap_params).map_err(|e| XtaskError::step("aperture", e))?;
    let Some(lcs) = ap.lcs else { return Ok(None) };
    let Some(a) = ap.feature(lcs.a).copied() else {
        return Ok(None);
    };
    // B: the LCS neighbour most separated in y (the vector a single scan distorts most).
    let (b_index, ab) = if lcs.ab.y.value().abs() >= lcs.ac.y.value().abs() {
        (lcs.b, lcs.ab)
    } else {
        (lcs.c, lcs.ac)
    };
    let Some(b) = ap.feature(b_index).copied() else {
        return Ok(None);
    };
    let Some(truth) = true_vector(&sim, &a, &b) else {
        return Ok(None);
    };
    let Some(single) = relative_error_pct(ab, truth) else {
        return Ok(None);
    };
    let drift = attached.velocity().unwrap_or(CountVelocity::ZERO);
    let mut skip_params = SkipParams::new(raster(16, 2e-4), MonitorParams::new(2.5, 20.0, 4));
    skip_params.detection = detection();
    let report = skip(&mut sim, a.position, a.time, ab, drift, &skip_params)
        .map_err(|e| XtaskError::step("skip", e))?;
    if report.outcome != SkipOutcome::Completed {
        return Ok(None);
    }
    let (Some(last), Some(vector)) = (
        report.kept.last().and_then(|&k| report.cycles.get(k)),
        report.vector,
    ) else {
        return Ok(None);
    };
    let Some(truth) = true_vector(&sim, &last.cycle.a_end.feature, &last.cycle.b.feature) else {
        return Ok(None);
    };
    let Some(skipping) = relative_error_pct(vector, truth) else {
        return Ok(None);
    };

    // Counter-scan on the same surface, a little away.
    let params = CounterScanParams {
        raster: raster(64, 3e-4),
        detection: detection(),
        motion: Motion::TYPICAL,
        match_radius_counts: 0.35 * A,
        drift_prior: drift,
    };
    let counter = counter_scan(&mut sim, CountPoint::from_counts(-300.0, 50.0), &params)
        .map_err(|e| XtaskError::step("counter_scan", e))?;
    let pairs: Vec<_> = counter.common.iter().map(|p| (p.drift_free, p)).collect();
    let errors = nearest_neighbour_errors_pct(&pairs, A, 0.3, |p, q| {
        true_vector(&sim, &p.direct, &q.direct)
    });
    Ok(Some((skipping, single, errors)))
}

pub fn run(ctx: &Context) -> Result<DriftResults, XtaskError> {
    let seeds: u64 = if ctx.quick { 3 } else { 20 };
    let velocities: &[f64] = if ctx.quick {
        &[0.0, 0.2, 0.4]
    } else {
        &[0.0, 0.1, 0.2, 0.3, 0.4]
    };
    let mut points = Vec::new();
    for &v_angstrom in velocities {
        let (mut skipping, mut single, mut counter) = (Vec::new(), Vec::new(), Vec::new());
        for seed in 0..seeds {
            if let Some((s, one, c)) = one_run(100 + seed, v_angstrom * 0.1)? {
                skipping.push(s);
                single.push(one);
                counter.extend(c);
            }
        }
        let point = DriftPoint::from_errors(v_angstrom, &skipping, &counter, &single);
        println!(
            "   drift {v_angstrom:.1} Å/s: skipping {:.3} %, counter-scan {:.3} %, single scan {:.3} % ({} runs)",
            point.skipping_pct, point.counter_scan_pct, point.single_scan_pct, point.runs
        );
        points.push(point);
    }
    DriftResults::from_points(seeds as usize, points)
        .ok_or_else(|| XtaskError::step("drift", "no velocities"))
}
