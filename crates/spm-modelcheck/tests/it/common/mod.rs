//! A feature-level generator: lattice sites seen through a linear scanner with
//! constant drift, plus hidden extras, with per-feature times of a raster.
#![allow(dead_code, clippy::unwrap_used)]

pub mod image;
pub mod measured;
pub mod sim_frame;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use spm_modelcheck::{Diagnosis, FeatureObservation, FeatureSet, FrameInfo, LineDirection};

/// The diagnosis's findings for a failure message: each effect, its evidence, held-out RMS
/// before → after (pm) and parameters.
pub fn findings(d: &Diagnosis) -> Vec<String> {
    d.findings
        .iter()
        .map(|f| {
            let parameters: Vec<String> = f
                .parameters
                .iter()
                .map(|(k, v)| format!("{k}={:.4e}±{:.1e}", v.value, v.sigma))
                .collect();
            format!(
                "{} ev {:.0} held-out {:.1}→{:.1} pm {parameters:?}",
                f.effect, f.evidence, f.heldout_rms_before_pm, f.heldout_rms_after_pm
            )
        })
        .collect()
}

/// The diagnosis's rejected candidates for a failure message.
pub fn rejections(d: &Diagnosis) -> Vec<String> {
    d.rejected
        .iter()
        .map(|r| {
            format!(
                "{} {:.0} {:.2}pm {}",
                r.effect, r.evidence, r.explained_rms_pm, r.reason
            )
        })
        .collect()
}

/// The first round's candidates and their evidence.
pub fn first_round(d: &Diagnosis) -> Option<Vec<(String, f64)>> {
    d.rounds.first().map(|r| {
        r.iter()
            .map(|c| (c.effect.clone(), c.evidence.round()))
            .collect()
    })
}

/// Scan geometry of the generated frames.
#[derive(Clone, Debug)]
pub struct Scan {
    pub a_nm: f64,
    pub half_nm: f64,
    pub lines: usize,
    pub line_time_s: f64,
    /// Slow axis of each frame: true = lines step +y (up), false = −y (down).
    pub frames_up: Vec<bool>,
    pub gap_s: f64,
    pub noise_nm: f64,
    pub scale: [f64; 2],
    pub obliquity_rad: f64,
    pub rotation_rad: f64,
    pub drift_nm_per_s: [f64; 2],
}

impl Default for Scan {
    fn default() -> Self {
        Self {
            a_nm: 1.0,
            half_nm: 10.0,
            lines: 128,
            line_time_s: 0.25,
            frames_up: vec![true, false, true],
            gap_s: 20.0,
            noise_nm: 0.01,
            scale: [1.04, 0.97],
            obliquity_rad: 0.02,
            rotation_rad: 0.3,
            drift_nm_per_s: [0.004, -0.003],
        }
    }
}

/// Hidden extras: (input displacement nm, sample displacement nm) of a feature
/// at commanded u, time t (s, absolute), line sign s, time since frame start.
pub type Extra = dyn Fn([f64; 2], f64, f64, f64) -> ([f64; 2], [f64; 2]);

pub fn generate(scan: &Scan, seed: u64, extra: &Extra) -> FeatureSet {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let noise = Normal::new(0.0, scan.noise_nm).unwrap();
    let (so, co) = scan.obliquity_rad.sin_cos();
    let (sr, cr) = scan.rotation_rad.sin_cos();
    // J = R(θ)·[[kx, ky sin α],[0, ky cos α]] maps input (nm) to lattice frame.
    let u_mat = [
        [scan.scale[0], scan.scale[1] * so],
        [0.0, scan.scale[1] * co],
    ];
    let j = [
        [
            cr * u_mat[0][0] - sr * u_mat[1][0],
            cr * u_mat[0][1] - sr * u_mat[1][1],
        ],
        [
            sr * u_mat[0][0] + cr * u_mat[1][0],
            sr * u_mat[0][1] + cr * u_mat[1][1],
        ],
    ];
    let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
    let jinv = [
        [j[1][1] / det, -j[0][1] / det],
        [-j[1][0] / det, j[0][0] / det],
    ];
    let period = 2.0 * scan.line_time_s;
    let duration = period * scan.lines as f64;
    let h = scan.half_nm;
    let mut set = FeatureSet::default();
    let a1 = [scan.a_nm, 0.0];
    let a2 = [0.5 * scan.a_nm, 0.75f64.sqrt() * scan.a_nm];
    let reach = (2.0 * h / scan.a_nm) as i64 + 4;
    for (f, &up) in scan.frames_up.iter().enumerate() {
        let start = f as f64 * (duration + scan.gap_s);
        set.frames.push(FrameInfo {
            label: format!("synthetic {f}"),
            half_width_x_nm: h,
            half_height_y_nm: h,
            start_time_s: start,
            duration_s: duration,
            fast_speed_nm_per_s: 2.0 * h / scan.line_time_s,
            lines: scan.lines,
            pixel_nm: None,
        });
        let offset = [0.37 * f as f64, -0.21 * f as f64];
        for dir in [LineDirection::Forward, LineDirection::Backward] {
            let s = dir.sign();
            for i in -reach..=reach {
                for jj in -reach..=reach {
                    let r = [
                        i as f64 * a1[0] + jj as f64 * a2[0] + offset[0],
                        i as f64 * a1[1] + jj as f64 * a2[1] + offset[1],
                    ];
                    let mut u = [
                        jinv[0][0] * r[0] + jinv[0][1] * r[1],
                        jinv[1][0] * r[0] + jinv[1][1] * r[1],
                    ];
                    if u[0].abs() > 1.5 * h || u[1].abs() > 1.5 * h {
                        continue;
                    }
                    let mut t = 0.0;
                    let mut line = 0.0;
                    for _ in 0..8 {
                        let frac_y = (u[1] + h) / (2.0 * h);
                        line = if up { frac_y } else { 1.0 - frac_y } * (scan.lines as f64 - 1.0);
                        let frac_x = (u[0] + h) / (2.0 * h);
                        let along = if s > 0.0 { frac_x } else { 1.0 - frac_x };
                        let t_frame = line.round() * period
                            + if s > 0.0 { 0.0 } else { scan.line_time_s }
                            + along * scan.line_time_s;
                        t = start + t_frame;
                        let (du, dsamp) = extra(u, t, s, t_frame);
                        let d = [
                            scan.drift_nm_per_s[0] * t + dsamp[0],
                            scan.drift_nm_per_s[1] * t + dsamp[1],
                        ];
                        // R = Rot(θ)(U(u + du) + d)  ⇒  u = J⁻¹(R − Rot(θ)d) − du
                        let rd = [cr * d[0] - sr * d[1], sr * d[0] + cr * d[1]];
                        let q = [r[0] - rd[0], r[1] - rd[1]];
                        u = [
                            jinv[0][0] * q[0] + jinv[0][1] * q[1] - du[0],
                            jinv[1][0] * q[0] + jinv[1][1] * q[1] - du[1],
                        ];
                    }
                    if u[0].abs() > 0.95 * h || u[1].abs() > 0.95 * h {
                        continue;
                    }
                    set.features.push(FeatureObservation {
                        x_nm: u[0] + noise.sample(&mut rng),
                        y_nm: u[1] + noise.sample(&mut rng),
                        time_s: t,
                        direction: dir,
                        frame_index: f,
                        line_index: line.round() as usize,
                        sigma_nm: Some(scan.noise_nm),
                        width_nm: None,
                        fit_radius_nm: None,
                        line_time_offset_s: None,
                    });
                }
            }
        }
    }
    set
}

pub fn none() -> Box<Extra> {
    Box::new(|_, _, _, _| ([0.0, 0.0], [0.0, 0.0]))
}
