//! Line levelling of lattice images: each scan line's offset and slope (the feedback's
//! line-to-line offsets and tilts) removed without moving the lattice's features.
//!
//! Each line's offset and slope come from a least-squares line with Tukey weights
//! ([`taper`]). A line of a lattice image holds a non-integer number of periods: with
//! uniform weights the partial period at the ends leaks into the line's offset and
//! slope, which then change from line to line with the lattice phase of the row;
//! subtracting them moves every atom by a periodic function of its row (a fake slow
//! "vibration" of ~1 pm on graphite, since rows are time along the slow axis). The
//! taper suppresses that leakage.
//!
//! No taper helps when the lattice's rows lie nearly along the lines (issue 29): a line
//! then runs along one row for most of its length, so its mean and slope *are* the
//! lattice's height there, ≈ cos(g_y·y + φ) for a harmonic (g_x, g_y) with small g_x.
//! Subtracting them leaves a gradient along y under every atom that depends on the
//! atom's row phase, which changes slowly along the row: the features move along y by a
//! periodic function of x of period (row spacing)/sin θ. On the image-level generator
//! (tests/it/orientation.rs) the localisation bias against the true sites grew from
//! 1.9 pm RMS (rows at 20–30°, the localiser's noise) to 5–6 pm at 0–6° and 20 pm at 2°,
//! and a clean pair at 4–7° was diagnosed with a "vibration".
//!
//! So the offsets and slopes are fitted *jointly* with the lattice: a cos/sin pair per
//! harmonic of the lattice found in the image ([`lattice_harmonics`]), and only the
//! offsets and slopes are subtracted. The per-line parameters are eliminated line by
//! line (a Schur complement), so the cost is that of the harmonics' normal matrix. The
//! harmonics' wave vectors must be exact to a small fraction of a cycle over the image,
//! and the power-spectrum peaks of a line-levelled image are not, for the very
//! harmonics that matter (levelling suppresses what is nearly constant along lines,
//! which pulls their peaks): the reciprocal basis is refined by maximising the energy
//! the joint fit explains ([`refine_basis`], a variable projection over four numbers).
//! A harmonic exactly along the lines (g_x = 0) is itself a per-line offset: the
//! pseudo-inverse leaves it to the offsets, whose removal is then the same for every
//! atom of a row and moves none.

use nalgebra::{DMatrix, DVector};
use spm_features::cells::{Peaks, climb};

/// Tukey weight of column `c` of `nx`: flat in the middle, sin² tapers over the outer
/// 15 % of each end: enough to suppress the partial-period leakage (tests/it/image.rs,
/// clean cases), while the flat middle keeps the tilt estimate efficient on real lines
/// with strong feedback noise.
fn taper(c: usize, nx: usize) -> f64 {
    let alpha = 0.3;
    let x = (c as f64 + 0.5) / nx as f64;
    let edge = x.min(1.0 - x);
    if edge >= 0.5 * alpha {
        1.0
    } else {
        (0.5 * std::f64::consts::PI * edge / (0.5 * alpha))
            .sin()
            .powi(2)
    }
}

fn apply2(m: [[f64; 2]; 2], v: [f64; 2]) -> [f64; 2] {
    [
        m[0][0] * v[0] + m[0][1] * v[1],
        m[1][0] * v[0] + m[1][1] * v[1],
    ]
}

/// A map whose rows are its scan lines.
#[derive(Clone, Copy)]
pub(crate) struct Lines<'a> {
    /// Heights, row-major.
    pub z: &'a [f64],
    /// Unscanned pixels (not fitted, not changed).
    pub bad: &'a [bool],
    /// Columns.
    pub nx: usize,
    /// Rows (lines).
    pub ny: usize,
}

/// One line's least-squares pieces: G⁻¹ (G = PᵀWP over P = (1, x)), PᵀWz and PᵀWH.
type LinePieces = Option<([[f64; 2]; 2], [f64; 2], Vec<[f64; 2]>)>;

/// The joint fit: harmonic coefficients, each line's pieces, and the weighted energy
/// the harmonics explain beyond the lines' offsets and slopes.
struct JointFit {
    theta: DVector<f64>,
    lines: Vec<LinePieces>,
    explained: f64,
}

/// The lines' offsets and slopes carry a weak ridge, this fraction of their own
/// normal-matrix diagonal (they shrink by 0.1 %). It decides only what the lines cannot:
/// a harmonic (nearly) constant along the lines is, line by line, an offset, and
/// without the ridge it is undetermined (the pseudo-inverse left it to the offsets,
/// which then removed it from the image: at 0° on the generator the features kept a
/// 6 pm bias; a plain solve amplified the noise into 30–60 pm). With it, offsets that
/// form the lattice's own tone across the lines are the lattice's: line noise has no
/// tone at the lattice's row frequency, so at most that one component of it stays in
/// the image.
const LINE_RIDGE: f64 = 1e-3;

/// Per-line offsets and slopes fitted jointly with a cos/sin pair per harmonic `k_px`
/// (cycles per pixel, (column, row)).
fn joint_fit(img: &Lines<'_>, k_px: &[[f64; 2]]) -> JointFit {
    let (nx, ny) = (img.nx, img.ny);
    let m = 2 * k_px.len();
    let centre = 0.5 * (nx as f64 - 1.0);
    let weights: Vec<f64> = (0..nx).map(|c| taper(c, nx)).collect();
    let mut h = vec![0.0; m];
    let mut a = DMatrix::<f64>::zeros(m, m);
    let mut b = DVector::<f64>::zeros(m);
    let mut lines = Vec::with_capacity(ny);
    // Lower triangle of HᵀWH, row-major; HᵀWz.
    let mut hh = vec![0.0; m * m];
    let mut hz = vec![0.0; m];
    // Each harmonic's phasor advances by e^{2πi·k_x} per column (a rotation, not a
    // sin_cos per pixel), restarted on every line.
    let step: Vec<(f64, f64)> = k_px
        .iter()
        .map(|k| (std::f64::consts::TAU * k[0]).sin_cos())
        .collect();
    let mut phasor = vec![(0.0, 0.0); k_px.len()];
    for r in 0..ny {
        let mut g = [[0.0; 2]; 2];
        let mut pz = [0.0; 2];
        let mut ph = vec![[0.0; 2]; m];
        hh.fill(0.0);
        hz.fill(0.0);
        for (p, k) in phasor.iter_mut().zip(k_px) {
            *p = (std::f64::consts::TAU * k[1] * r as f64).sin_cos();
        }
        for (c, &w) in weights.iter().enumerate() {
            if c > 0 {
                for (p, s) in phasor.iter_mut().zip(&step) {
                    *p = (p.0 * s.1 + p.1 * s.0, p.1 * s.1 - p.0 * s.0);
                }
            }
            let v = img.z[r * nx + c];
            if img.bad[r * nx + c] || !v.is_finite() {
                continue;
            }
            let x = c as f64 - centre;
            g[0][0] += w;
            g[0][1] += w * x;
            g[1][1] += w * x * x;
            pz[0] += w * v;
            pz[1] += w * x * v;
            for (j, p) in phasor.iter().enumerate() {
                h[2 * j] = p.1;
                h[2 * j + 1] = p.0;
            }
            for i in 0..m {
                let wh = w * h[i];
                ph[i][0] += wh;
                ph[i][1] += wh * x;
                hz[i] += wh * v;
                let row = &mut hh[i * m..i * m + i + 1];
                for (acc, hj) in row.iter_mut().zip(&h) {
                    *acc += wh * hj;
                }
            }
        }
        g[1][0] = g[0][1];
        g[0][0] *= 1.0 + LINE_RIDGE;
        g[1][1] *= 1.0 + LINE_RIDGE;
        let det = g[0][0] * g[1][1] - g[0][1] * g[1][0];
        let invertible = det > 1e-12 * (g[0][0] * g[1][1]).max(1e-300);
        if !invertible {
            lines.push(None);
            continue;
        }
        let gi = [
            [g[1][1] / det, -g[0][1] / det],
            [-g[1][0] / det, g[0][0] / det],
        ];
        // Reduced system: HᵀWH − (PᵀWH)ᵀG⁻¹(PᵀWH), HᵀWz − (PᵀWH)ᵀG⁻¹PᵀWz.
        let cz = apply2(gi, pz);
        for i in 0..m {
            let ci = apply2(gi, ph[i]);
            b[i] += hz[i] - (ph[i][0] * cz[0] + ph[i][1] * cz[1]);
            for j in 0..=i {
                a[(i, j)] += hh[i * m + j] - (ci[0] * ph[j][0] + ci[1] * ph[j][1]);
            }
        }
        lines.push(Some((gi, pz, ph)));
    }
    if m == 0 {
        return JointFit {
            theta: DVector::zeros(0),
            lines,
            explained: 0.0,
        };
    }
    for i in 0..m {
        for j in 0..i {
            a[(j, i)] = a[(i, j)];
        }
    }
    let normal: Vec<Vec<f64>> = (0..m)
        .map(|i| (0..m).map(|j| a[(i, j)]).collect())
        .collect();
    let theta = spm_regression::minimum_norm_solve(&normal, b.as_slice(), 1e-12)
        .map_or_else(|_| DVector::zeros(m), DVector::from_vec);
    let explained = b.dot(&theta);
    JointFit {
        theta,
        lines,
        explained: if explained.is_finite() {
            explained
        } else {
            0.0
        },
    }
}

/// Removes each line's offset and slope, fitted jointly with the harmonics `k_px`
/// (cycles per pixel, (column, row); empty: a plain per-line fit), from `z` (whose
/// unscanned pixels, `bad`, are left as they are).
pub(crate) fn level_lines(z: &mut [f64], bad: &[bool], nx: usize, ny: usize, k_px: &[[f64; 2]]) {
    let fit = joint_fit(&Lines { z, bad, nx, ny }, k_px);
    let centre = 0.5 * (nx as f64 - 1.0);
    for (r, line) in fit.lines.into_iter().enumerate() {
        let Some((gi, mut rhs, ph)) = line else {
            continue;
        };
        for (i, p) in ph.iter().enumerate() {
            rhs[0] -= p[0] * fit.theta[i];
            rhs[1] -= p[1] * fit.theta[i];
        }
        let [offset, slope] = apply2(gi, rhs);
        for c in 0..nx {
            let k = r * nx + c;
            if !bad[k] {
                z[k] -= offset + slope * (c as f64 - centre);
            }
        }
    }
}

/// The reciprocal lattice points m·k₁ + n·k₂ out to `reach` × the longer basis vector,
/// one of each ± pair, folded into the pixel band (a harmonic beyond the Nyquist
/// frequency is sampled as its alias), cycles per pixel.
fn harmonics_of(k: [[f64; 2]; 2], reach: f64) -> Vec<[f64; 2]> {
    let [k1, k2] = k;
    let limit = reach * k1[0].hypot(k1[1]).max(k2[0].hypot(k2[1]));
    let half_plane = |k: [f64; 2]| {
        if k[1] < 0.0 || (k[1] == 0.0 && k[0] < 0.0) {
            [-k[0], -k[1]]
        } else {
            k
        }
    };
    let mut out: Vec<[f64; 2]> = Vec::new();
    for m in -4i32..=4 {
        for n in -4i32..=4 {
            let k = [
                m as f64 * k1[0] + n as f64 * k2[0],
                m as f64 * k1[1] + n as f64 * k2[1],
            ];
            let len = k[0].hypot(k[1]);
            if len < 1e-9 || len > limit {
                continue;
            }
            let k = half_plane([k[0] - k[0].round(), k[1] - k[1].round()]);
            if k[0].hypot(k[1]) < 1e-6
                || out.iter().any(|q| (q[0] - k[0]).hypot(q[1] - k[1]) < 1e-6)
            {
                continue;
            }
            out.push(k);
        }
    }
    out
}

/// The reciprocal basis of `peaks` refined on the image: the k₁, k₂ (cycles per pixel)
/// whose first-shell harmonics, fitted jointly with the lines' offsets and slopes,
/// explain the most energy; a compass search from the spectrum's peaks, over at most
/// ±2 cycles across the image.
pub(crate) fn refine_basis(img: &Lines<'_>, peaks: &Peaks) -> [[f64; 2]; 2] {
    let k0 = peaks.k;
    let n = img.nx.max(img.ny) as f64;
    let bound = 2.0 / n;
    // The compass search comes back to points it has evaluated (the way it came, each
    // climb's start): each energy, a fit over the whole image, is computed once.
    let seen = std::cell::RefCell::new(std::collections::HashMap::<[u64; 4], f64>::new());
    let energy = |p: [f64; 4]| {
        let k = [[p[0], p[1]], [p[2], p[3]]];
        if (0..4).any(|i| (p[i] - [k0[0][0], k0[0][1], k0[1][0], k0[1][1]][i]).abs() > bound) {
            return f64::NEG_INFINITY;
        }
        let key = p.map(f64::to_bits);
        if let Some(e) = seen.borrow().get(&key) {
            return *e;
        }
        let e = joint_fit(img, &harmonics_of(k, 1.05)).explained;
        seen.borrow_mut().insert(key, e);
        e
    };
    let mut p = [k0[0][0], k0[0][1], k0[1][0], k0[1][1]];
    let mut best = energy(p);
    // Two coordinates at a time (climb searches a plane), until neither pair moves.
    for _ in 0..6 {
        let before = p;
        for pair in [[0usize, 1], [2, 3]] {
            let f = |q: [f64; 2]| {
                let mut t = p;
                t[pair[0]] = q[0];
                t[pair[1]] = q[1];
                energy(t)
            };
            let (q, e) = climb(&f, [p[pair[0]], p[pair[1]]], 0.5 / n);
            if e > best {
                best = e;
                p[pair[0]] = q[0];
                p[pair[1]] = q[1];
            }
        }
        if p == before {
            break;
        }
    }
    [[p[0], p[1]], [p[2], p[3]]]
}

/// The lattice's harmonics for [`level_lines`]: the reciprocal lattice of the refined
/// basis out to twice its longer vector (a triangular lattice's first three shells: 1,
/// √3, 2), cycles per pixel.
pub(crate) fn lattice_harmonics(basis: [[f64; 2]; 2]) -> Vec<[f64; 2]> {
    harmonics_of(basis, 2.05)
}
