//! Localisation error ÷ Cramér–Rao bound at several SNRs: the measurement of
//! docs/results/features.md (`spm-features` example `crb_ratio`) with the
//! library's `detect` and `profile_cramer_rao`: synthetic three-cosine HOPG,
//! 16×16 segments over 1.2 a, the atom at a uniformly random sub-pixel offset.

use super::Context;
use crate::XtaskError;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;
use spm_features::{DetectionConfig, design_cramer_rao, detect, profile_cramer_rao};
use spm_hal::{CountPoint, Counts, Frame, ScanRequest, Seconds, TraceHalf};

/// One SNR.
#[derive(Debug, Serialize)]
pub struct CrbPoint {
    /// Corrugation ÷ white-noise σ.
    pub snr: f64,
    /// Segments fitted.
    pub trials: usize,
    /// RMS error per axis, counts.
    pub rms_counts: f64,
    /// Window Cramér–Rao bound per axis, counts.
    pub crb_counts: f64,
    /// rms ÷ crb.
    pub ratio: f64,
    /// DESIGN §5's closed form √(2/π)·p·σn/A, counts.
    pub design_bound_counts: f64,
    /// Atoms not found.
    pub missed: usize,
}

/// The CRB section.
#[derive(Debug, Serialize)]
pub struct CrbResults {
    /// One row per SNR.
    pub points: Vec<CrbPoint>,
}

/// Three-cosine HOPG in counts (0.005 nm/count, corrugation 0.3 nm).
struct Hopg {
    a: f64,
    corrugation: f64,
    k: [(f64, f64); 3],
}

impl Hopg {
    fn new() -> Self {
        let a = 0.2461 / 0.005;
        let g = 2.0 * std::f64::consts::PI / a;
        let b1 = (g, -g / 3f64.sqrt());
        let b2 = (0.0, 2.0 * g / 3f64.sqrt());
        let b3 = (-(b1.0 + b2.0), -(b1.1 + b2.1));
        Self {
            a,
            corrugation: 30.0,
            k: [b1, b2, b3],
        }
    }
    fn atom(&self, n: f64, m: f64) -> CountPoint {
        CountPoint::from_counts(self.a * (n + 0.5 * m), self.a * (3f64.sqrt() / 2.0 * m))
    }
    fn height(&self, x: f64, y: f64) -> f64 {
        let s: f64 = self.k.iter().map(|k| (k.0 * x + k.1 * y).cos()).sum();
        self.corrugation / 4.5 * (s + 1.5)
    }
}

pub fn run(ctx: &Context) -> Result<CrbResults, XtaskError> {
    let trials = if ctx.quick { 200 } else { 2000 };
    let hopg = Hopg::new();
    let step = Counts(1.2 * hopg.a / 15.0);
    let config = DetectionConfig {
        min_separation_px: 0.4 * hopg.a / step.value(),
        ..DetectionConfig::default()
    };
    let mut points = Vec::new();
    for snr in [5.0_f64, 10.0, 20.0] {
        let mut rng = ChaCha8Rng::seed_from_u64(snr as u64);
        let noise = hopg.corrugation / snr;
        let normal = Normal::new(0.0, noise).map_err(|e| XtaskError::step("crb", e))?;
        let (mut errors, mut bounds) = (Vec::new(), Vec::new());
        let (mut amp, mut n, mut missed) = (0.0, 0usize, 0usize);
        for _ in 0..trials {
            let atom = hopg.atom(3.0, 2.0);
            let off = (rng.random::<f64>() - 0.5, rng.random::<f64>() - 0.5);
            let centre = CountPoint::from_counts(
                atom.x.value() + off.0 * step.value(),
                atom.y.value() + off.1 * step.value(),
            );
            let request = ScanRequest::centred_square(centre, step, 16, Seconds(1e-4));
            let frame = Frame::from_fn(request, Seconds(0.0), |p, _| {
                Counts(hopg.height(p.x.value(), p.y.value()) + normal.sample(&mut rng))
            });
            let map = frame
                .height_map(TraceHalf::Forward)
                .map_err(|e| XtaskError::step("crb: height map", e))?;
            let found = detect(&map, &config).map_err(|e| XtaskError::step("crb: detect", e))?;
            let Some(f) = found
                .nearest(atom)
                .filter(|f| f.position.distance(atom).value() < 0.3 * hopg.a)
            else {
                missed += 1;
                continue;
            };
            let (col, row) = map.pixel_of(atom);
            let radius = config.fit_radius_sigmas * f.width.value() / step.value();
            let Ok(bound) = profile_cramer_rao(
                |dx, dy| {
                    hopg.height(
                        atom.x.value() + dx * step.value(),
                        atom.y.value() + dy * step.value(),
                    )
                },
                (col, row),
                map.columns,
                map.rows,
                radius.min(1.25 * config.min_separation_px),
                step,
                noise,
                true,
            ) else {
                missed += 1;
                continue;
            };
            errors.extend([
                (f.position.x - atom.x).value(),
                (f.position.y - atom.y).value(),
            ]);
            bounds.extend([bound.sigma_x.value(), bound.sigma_y.value()]);
            amp += f.amplitude_z_counts;
            n += 1;
        }
        if n == 0 {
            return Err(XtaskError::step(
                "crb",
                format!("no atom found at SNR {snr}"),
            ));
        }
        // Per coordinate: the RMS of the x and y errors, and of the x and y bounds.
        let (rms, crb) = (super::rms(&errors), super::rms(&bounds));
        let design = design_cramer_rao(step, noise, amp / n as f64);
        println!(
            "   crb SNR {snr}: RMS {rms:.4} counts, CRB {crb:.4}, ratio {:.3}",
            rms / crb
        );
        points.push(CrbPoint {
            snr,
            trials: n,
            rms_counts: rms,
            crb_counts: crb,
            ratio: rms / crb,
            design_bound_counts: design.value(),
            missed,
        });
    }
    Ok(CrbResults { points })
}
