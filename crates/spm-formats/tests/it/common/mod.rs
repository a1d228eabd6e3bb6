//! Test helpers: a small FFT and an autocorrelation-based lattice period estimate.
//!
//! This is an independent sanity check of the readers' geometry (pixel size, orientation),
//! not the lattice measurement of spm-features.

#![allow(dead_code)]

use std::f64::consts::PI;

/// In-place radix-2 FFT of (re, im); `inverse` flips the sign of the exponent (no scaling).
fn fft(re: &mut [f64], im: &mut [f64], inverse: bool) {
    let n = re.len();
    assert!(n.is_power_of_two());
    let mut j = 0;
    for i in 1..n {
        let mut bit = n >> 1;
        while j & bit != 0 {
            j ^= bit;
            bit >>= 1;
        }
        j |= bit;
        if i < j {
            re.swap(i, j);
            im.swap(i, j);
        }
    }
    let sign = if inverse { 1.0 } else { -1.0 };
    let mut len = 2;
    while len <= n {
        let ang = sign * 2.0 * PI / len as f64;
        for start in (0..n).step_by(len) {
            for k in 0..len / 2 {
                let (wr, wi) = ((ang * k as f64).cos(), (ang * k as f64).sin());
                let (a, b) = (start + k, start + k + len / 2);
                let (xr, xi) = (re[b] * wr - im[b] * wi, re[b] * wi + im[b] * wr);
                re[b] = re[a] - xr;
                im[b] = im[a] - xi;
                re[a] += xr;
                im[a] += xi;
            }
        }
        len <<= 1;
    }
}

fn fft2(re: &mut [f64], im: &mut [f64], n: usize, inverse: bool) {
    let mut r = vec![0.0; n];
    let mut i = vec![0.0; n];
    for row in 0..n {
        fft(
            &mut re[row * n..(row + 1) * n],
            &mut im[row * n..(row + 1) * n],
            inverse,
        );
    }
    for col in 0..n {
        for k in 0..n {
            r[k] = re[k * n + col];
            i[k] = im[k * n + col];
        }
        fft(&mut r, &mut i, inverse);
        for k in 0..n {
            re[k * n + col] = r[k];
            im[k * n + col] = i[k];
        }
    }
}

/// Circular autocorrelation of a square power-of-two image after removing each line's mean
/// (which also suppresses fast-axis line noise). Index (dy, dx) with wrap-around.
pub fn autocorrelation(data: &[f64], n: usize) -> Vec<f64> {
    autocorrelation_high_pass(data, n, 0.0)
}

/// Like [`autocorrelation`], with spatial frequencies below `k_min` cycles per image removed.
pub fn autocorrelation_high_pass(data: &[f64], n: usize, k_min: f64) -> Vec<f64> {
    let mut re = vec![0.0; n * n];
    for row in 0..n {
        let line = &data[row * n..(row + 1) * n];
        let mean = line.iter().sum::<f64>() / n as f64;
        for c in 0..n {
            re[row * n + c] = line[c] - mean;
        }
    }
    let mut im = vec![0.0; n * n];
    fft2(&mut re, &mut im, n, false);
    for k in 0..n * n {
        let (ky, kx) = ((k / n) as f64, (k % n) as f64);
        let ky = ky.min(n as f64 - ky);
        let kx = kx.min(n as f64 - kx);
        let keep = (kx * kx + ky * ky).sqrt() >= k_min;
        re[k] = if keep {
            re[k] * re[k] + im[k] * im[k]
        } else {
            0.0
        };
        im[k] = 0.0;
    }
    fft2(&mut re, &mut im, n, true);
    re
}

/// Pearson correlation of two equally long slices.
pub fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let ma = a.iter().sum::<f64>() / n;
    let mb = b.iter().sum::<f64>() / n;
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    sab / (saa * sbb).sqrt()
}

/// The three strongest autocorrelation peaks in directions at least 30° apart (modulo 180°)
/// with distance in [r_min, r_max] pixels: for a hexagonal lattice, the nearest-neighbour
/// vectors. Returns them as (x, y) in pixels, strongest first (sub-pixel by parabolas along
/// x and y). Wavelengths longer than `2·r_max` are filtered out first.
pub fn nearest_neighbour_vectors_px(
    data: &[f64],
    n: usize,
    r_min: f64,
    r_max: f64,
) -> Vec<(f64, f64)> {
    let acf = autocorrelation_high_pass(data, n, n as f64 / (2.0 * r_max));
    let at = |dy: i64, dx: i64| {
        let y = dy.rem_euclid(n as i64) as usize;
        let x = dx.rem_euclid(n as i64) as usize;
        acf[y * n + x]
    };
    let r = r_max.ceil() as i64;
    let mut peaks = Vec::new();
    // Half plane is enough: the ACF is centrally symmetric.
    for dy in 0..=r {
        for dx in -r..=r {
            if dy == 0 && dx <= 0 {
                continue;
            }
            let d = ((dx * dx + dy * dy) as f64).sqrt();
            if d < r_min || d > r_max {
                continue;
            }
            let v = at(dy, dx);
            let local_max = (-1..=1)
                .flat_map(|a| (-1..=1).map(move |b| (a, b)))
                .filter(|&(a, b)| (a, b) != (0, 0))
                .all(|(a, b)| at(dy + a, dx + b) <= v);
            if local_max {
                peaks.push((v, dy, dx));
            }
        }
    }
    peaks.sort_by(|a, b| b.0.total_cmp(&a.0));
    let refine = |m: f64, c: f64, p: f64| {
        let den = m - 2.0 * c + p;
        if den.abs() > 0.0 {
            (0.5 * (m - p) / den).clamp(-0.5, 0.5)
        } else {
            0.0
        }
    };
    let mut chosen: Vec<(f64, f64)> = Vec::new();
    for (_, dy, dx) in peaks {
        let c = at(dy, dx);
        let fx = dx as f64 + refine(at(dy, dx - 1), c, at(dy, dx + 1));
        let fy = dy as f64 + refine(at(dy - 1, dx), c, at(dy + 1, dx));
        let angle = fy.atan2(fx).rem_euclid(PI);
        let far = chosen.iter().all(|&(x, y)| {
            let d = (y.atan2(x).rem_euclid(PI) - angle).abs();
            d.min(PI - d) > PI / 6.0
        });
        if far {
            chosen.push((fx, fy));
        }
        if chosen.len() == 3 {
            break;
        }
    }
    chosen
}

/// Lattice row spacings from the power spectrum: the three strongest spectral peaks (at
/// least 30° apart) whose row spacing lies in [d_min, d_max] pixels. The image is levelled
/// line by line, Hann-windowed and zero-padded to twice its size (n must be a power of two).
/// Returns the row spacings in pixels.
pub fn row_spacings_px(data: &[f64], n: usize, d_min: f64, d_max: f64) -> Vec<f64> {
    let m = 2 * n;
    let mut re = vec![0.0; m * m];
    let mut im = vec![0.0; m * m];
    let hann = |i: usize| 0.5 - 0.5 * (2.0 * PI * (i as f64 + 0.5) / n as f64).cos();
    for row in 0..n {
        let line = &data[row * n..(row + 1) * n];
        let mean = line.iter().sum::<f64>() / n as f64;
        for c in 0..n {
            re[row * m + c] = (line[c] - mean) * hann(row) * hann(c);
        }
    }
    fft2(&mut re, &mut im, m, false);
    let power: Vec<f64> = re.iter().zip(&im).map(|(r, i)| r * r + i * i).collect();
    let at = |ky: i64, kx: i64| {
        let y = ky.rem_euclid(m as i64) as usize;
        let x = kx.rem_euclid(m as i64) as usize;
        power[y * m + x]
    };
    // Row spacing d (pixels) ↔ frequency |k| = m / d (in padded bins).
    let (k_min, k_max) = (m as f64 / d_max, m as f64 / d_min);
    let r = k_max.ceil() as i64;
    let mut peaks = Vec::new();
    for ky in 0..=r {
        for kx in -r..=r {
            if ky == 0 && kx <= 0 {
                continue;
            }
            let k = ((kx * kx + ky * ky) as f64).sqrt();
            if k < k_min || k > k_max {
                continue;
            }
            let v = at(ky, kx);
            let local_max = (-1..=1)
                .flat_map(|a| (-1..=1).map(move |b| (a, b)))
                .filter(|&(a, b)| (a, b) != (0, 0))
                .all(|(a, b)| at(ky + a, kx + b) <= v);
            if local_max {
                peaks.push((v, ky, kx));
            }
        }
    }
    peaks.sort_by(|a, b| b.0.total_cmp(&a.0));
    let refine = |a: f64, c: f64, b: f64| {
        let den = a - 2.0 * c + b;
        if den.abs() > 0.0 {
            (0.5 * (a - b) / den).clamp(-0.5, 0.5)
        } else {
            0.0
        }
    };
    let mut chosen: Vec<(f64, f64)> = Vec::new();
    for (_, ky, kx) in peaks {
        let c = at(ky, kx);
        let fx = kx as f64 + refine(at(ky, kx - 1), c, at(ky, kx + 1));
        let fy = ky as f64 + refine(at(ky - 1, kx), c, at(ky + 1, kx));
        let angle = fy.atan2(fx).rem_euclid(PI);
        let far = chosen.iter().all(|&(a, _)| {
            let d = (a - angle).abs();
            d.min(PI - d) > PI / 6.0
        });
        if far {
            chosen.push((angle, m as f64 / (fx * fx + fy * fy).sqrt()));
        }
        if chosen.len() == 3 {
            break;
        }
    }
    chosen.into_iter().map(|(_, d)| d).collect()
}
