//! Drift insensitivity: the error of an A→B lattice vector (its relative
//! error is the LCC error it gives) against the drift velocity, for skipping
//! (spm-fos `skip`), counter-scanning (spm-fos `counter_scan`) and a single
//! aperture scan, judged by the simulator's oracle (true atom sites, true drift).
//!
//! Scanner: `SimConfig::ideal()` with white Z noise at SNR 10 and a constant
//! drift along the diagonal; the set-up of spm-fos's simulator tests (segments
//! 16×16 px at 0.2 ms/px, aperture 64×64 px at 0.3 ms/px, 4 kept skipping cycles).

use super::{Context, rms};
use crate::XtaskError;
use serde::Serialize;
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

/// One drift velocity.
#[derive(Debug, Serialize)]
pub struct DriftPoint {
    /// Drift speed, Å/s (along the diagonal).
    pub velocity_angstrom_per_s: f64,
    /// RMS relative A→B vector error of skipping, %.
    pub skipping_pct: f64,
    /// RMS relative vector error of counter-scanning (drift-free positions of
    /// nearest-neighbour pairs seen in both frames), %.
    pub counter_scan_pct: f64,
    /// RMS relative A→B vector error of a single aperture scan, %.
    pub single_scan_pct: f64,
    /// Runs that completed (of the seeds tried).
    pub runs: usize,
}

/// The drift section.
#[derive(Debug, Serialize)]
pub struct DriftResults {
    /// Seeds per velocity.
    pub seeds: usize,
    /// The sweep.
    pub points: Vec<DriftPoint>,
    /// single-scan error ÷ skipping error at the fastest drift.
    pub single_over_skipping_at_max: f64,
    /// skipping error at the fastest drift ÷ at rest.
    pub skipping_fast_over_rest: f64,
}

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
    let d = sim.oracle().drift_displacement(f.time);
    let s = NmPoint::from_nm(
        K * f.position.x.value() + d.x.value(),
        K * f.position.y.value() + d.y.value(),
    );
    sim.oracle()
        .features_near(s, 0.15)
        .iter()
        .find(|f| f.kind == FeatureKind::Atom && f.position.distance(s).value() < 0.05)
        .map(|f| f.position)
}

fn true_vector(sim: &Simulator, a: &Feature, b: &Feature) -> Option<CountVector> {
    let (sa, sb) = (site(sim, a)?, site(sim, b)?);
    Some(CountVector::from_counts(
        (sb.x - sa.x).value() / K,
        (sb.y - sa.y).value() / K,
    ))
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
    let single = (ab - truth).norm().value() / truth.norm().value() * 100.0;
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
    let skipping = (vector - truth).norm().value() / truth.norm().value() * 100.0;

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
    let mut errors = Vec::new();
    for (i, p) in counter.common.iter().enumerate() {
        for q in &counter.common[i + 1..] {
            let measured = q.drift_free - p.drift_free;
            if (measured.norm().value() - A).abs() > 0.3 * A {
                continue;
            }
            if let Some(truth) = true_vector(&sim, &p.direct, &q.direct) {
                errors.push((measured - truth).norm().value() / truth.norm().value() * 100.0);
            }
        }
    }
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
        let point = DriftPoint {
            velocity_angstrom_per_s: v_angstrom,
            skipping_pct: rms(&skipping),
            counter_scan_pct: rms(&counter),
            single_scan_pct: rms(&single),
            runs: skipping.len(),
        };
        println!(
            "   drift {v_angstrom:.1} Å/s: skipping {:.3} %, counter-scan {:.3} %, single scan {:.3} % ({} runs)",
            point.skipping_pct, point.counter_scan_pct, point.single_scan_pct, point.runs
        );
        points.push(point);
    }
    let (Some(first), Some(last)) = (points.first(), points.last()) else {
        return Err(XtaskError::step("drift", "no velocities"));
    };
    Ok(DriftResults {
        seeds: seeds as usize,
        single_over_skipping_at_max: last.single_scan_pct / last.skipping_pct,
        skipping_fast_over_rest: last.skipping_pct / first.skipping_pct,
        points,
    })
}
