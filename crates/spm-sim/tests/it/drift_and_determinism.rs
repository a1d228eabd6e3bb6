//! A configured drift v moves a feature by v·Δt between repeated scans
//! (measured by sub-pixel cross-correlation); same seed ⇒ bit-identical
//! frames, different seed ⇒ different frames.
#![allow(clippy::unwrap_used, clippy::needless_range_loop)]

use spm_hal::{CountPoint, Counts, Microscope, ScanRequest, Seconds, TraceHalf};
use spm_sim::{SimConfig, Simulator};

/// Catmull-Rom bicubic interpolation of a row-major image (column x, row y).
fn bicubic(z: &[f64], nx: usize, x: f64, y: f64) -> (f64, f64, f64) {
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let w = |t: f64| {
        [
            0.5 * (-t * t * t + 2.0 * t * t - t),
            0.5 * (3.0 * t * t * t - 5.0 * t * t + 2.0),
            0.5 * (-3.0 * t * t * t + 4.0 * t * t + t),
            0.5 * (t * t * t - t * t),
        ]
    };
    let dw = |t: f64| {
        [
            0.5 * (-3.0 * t * t + 4.0 * t - 1.0),
            0.5 * (9.0 * t * t - 10.0 * t),
            0.5 * (-9.0 * t * t + 8.0 * t + 1.0),
            0.5 * (3.0 * t * t - 2.0 * t),
        ]
    };
    let (wx, wy, dwx, dwy) = (w(fx), w(fy), dw(fx), dw(fy));
    let (mut v, mut gx, mut gy) = (0.0, 0.0, 0.0);
    for j in 0..4 {
        for i in 0..4 {
            let c = (x0 as i64 - 1 + i as i64) as usize;
            let r = (y0 as i64 - 1 + j as i64) as usize;
            let s = z[r * nx + c];
            v += wx[i] * wy[j] * s;
            gx += dwx[i] * wy[j] * s;
            gy += wx[i] * dwy[j] * s;
        }
    }
    (v, gx, gy)
}

/// 5×5 binomial smoothing (shift-invariant, so it preserves the shift
/// between two images while suppressing the noise that biases
/// gradient-based registration); the border is left unsmoothed.
fn smooth(z: &[f64], n: usize) -> Vec<f64> {
    let w = [1.0, 4.0, 6.0, 4.0, 1.0];
    let mut out = z.to_vec();
    for r in 2..n - 2 {
        for c in 2..n - 2 {
            let mut s = 0.0;
            for (j, wj) in w.iter().enumerate() {
                for (i, wi) in w.iter().enumerate() {
                    s += wi * wj * z[(r + j - 2) * n + c + i - 2];
                }
            }
            out[r * n + c] = s / 256.0;
        }
    }
    out
}

/// Shift s (pixels) such that `b(x) ≈ a(x − s)`: integer cross-correlation
/// peak, then Gauss–Newton refinement of the same criterion with bicubic
/// interpolation (sub-pixel cross-correlation).
fn shift_between(a: &[f64], b: &[f64], n: usize) -> (f64, f64) {
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (ma, mb) = (mean(a), mean(b));
    let margin = 12usize;
    let mut best = (f64::NEG_INFINITY, 0i64, 0i64);
    for sy in -9i64..=9 {
        for sx in -9i64..=9 {
            let mut c = 0.0;
            for r in margin..n - margin {
                for col in margin..n - margin {
                    let ra = (r as i64 - sy) as usize;
                    let ca = (col as i64 - sx) as usize;
                    c += (b[r * n + col] - mb) * (a[ra * n + ca] - ma);
                }
            }
            if c > best.0 {
                best = (c, sx, sy);
            }
        }
    }
    let (mut sx, mut sy) = (best.1 as f64, best.2 as f64);
    for _ in 0..10 {
        let (mut h11, mut h12, mut h22, mut g1, mut g2) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for r in margin..n - margin {
            for col in margin..n - margin {
                let (v, gx, gy) = bicubic(a, n, col as f64 - sx, r as f64 - sy);
                let e = b[r * n + col] - mb - (v - ma);
                // d(a(x − s))/ds = −∇a.
                let (jx, jy) = (-gx, -gy);
                h11 += jx * jx;
                h12 += jx * jy;
                h22 += jy * jy;
                g1 += jx * e;
                g2 += jy * e;
            }
        }
        let det = h11 * h22 - h12 * h12;
        let dx = (h22 * g1 - h12 * g2) / det;
        let dy = (-h12 * g1 + h11 * g2) / det;
        sx += dx;
        sy += dy;
        if dx.abs() < 1e-7 && dy.abs() < 1e-7 {
            break;
        }
    }
    (sx, sy)
}

#[test]
fn a_configured_drift_moves_the_image_by_v_dt() {
    let (vx, vy) = (0.02, -0.012); // nm/s
    let mut config = SimConfig::ideal();
    config.drift.velocity_x_nm_per_s = vx;
    config.drift.velocity_y_nm_per_s = vy;
    config.measurement.z_white_noise_nm = 0.002;
    config.seed = 99;
    let mut sim = Simulator::new(config).unwrap();
    let n = 64;
    let request = ScanRequest::centred_square(
        CountPoint::from_counts(-500.0, 700.0),
        Counts(0.5),
        n as u32,
        Seconds(1e-4),
    );
    let first = sim.scan(&request).unwrap();
    sim.wait(Seconds(3.0)).unwrap();
    let second = sim.scan(&request).unwrap();
    let dt = second.forward.time_s[0] - first.forward.time_s[0];
    let a = first.height_map(TraceHalf::Forward).unwrap().z_counts;
    let b = second.height_map(TraceHalf::Forward).unwrap().z_counts;
    let (sx, sy) = shift_between(&smooth(&a, n), &smooth(&b, n), n);
    // The sample moves by −d relative to the tip, so pixel x of the second
    // image shows what pixel x − s showed in the first, with
    // K·p·s = −v·(Δt + s_x·dwell + s_y·line_time): the shift is v·Δt plus the
    // drift during the raster-time difference between x and x − s
    // (K = 0.02 nm/count, p = 0.5 count/px).
    let (kp, dwell, line) = (0.02 * 0.5, 1e-4, 2.0 * n as f64 * 1e-4);
    let m = [[kp + vx * dwell, vx * line], [vy * dwell, kp + vy * line]];
    let rhs = [-vx * dt, -vy * dt];
    let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
    let ex = (rhs[0] * m[1][1] - m[0][1] * rhs[1]) / det;
    let ey = (m[0][0] * rhs[1] - m[1][0] * rhs[0]) / det;
    eprintln!("shift ({sx}, {sy}) px, expected ({ex}, {ey}) px");
    assert!(
        (sx - ex).abs() < 0.02 && (sy - ey).abs() < 0.02,
        "shift ({sx}, {sy}) px, expected ({ex}, {ey}) px over {dt} s"
    );
    // The oracle's true drift agrees.
    let d = sim.oracle().drift_displacement(Seconds(dt));
    assert!((d.x.value() - vx * dt).abs() < 1e-12 && (d.y.value() - vy * dt).abs() < 1e-12);
}

fn session(seed: u64) -> Vec<Result<spm_hal::Frame, spm_sim::SimError>> {
    let mut config = SimConfig::room_temperature_tube();
    config.seed = seed;
    let mut sim = Simulator::new(config).unwrap();
    let request = ScanRequest::centred_square(
        CountPoint::from_counts(2000.0, -3000.0),
        Counts(1.0),
        24,
        Seconds(1e-4),
    );
    let mut out = Vec::new();
    for k in 0..3 {
        let mut r = request.clone();
        r.record_backward = k == 1;
        out.push(sim.scan(&r));
        let _ = sim.wait(Seconds(0.5));
    }
    out
}

#[test]
fn same_seed_gives_bit_identical_frames_and_another_seed_differs() {
    let a = session(7);
    let b = session(7);
    assert_eq!(a, b);
    for (x, y) in a.iter().zip(&b) {
        if let (Ok(x), Ok(y)) = (x, y) {
            let bits = |f: &spm_hal::Frame| {
                f.forward
                    .z_counts
                    .iter()
                    .map(|v| v.to_bits())
                    .collect::<Vec<_>>()
            };
            assert_eq!(bits(x), bits(y));
        }
    }
    let c = session(8);
    assert_ne!(a, c);
}
