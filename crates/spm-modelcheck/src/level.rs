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

use nalgebra::{Complex, DMatrix, DVector};
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

/// One line's weighted sums over its pixels: G = PᵀWP (lower triangle used), PᵀWz,
/// PᵀWH, the lower triangle of HᵀWH (row-major, `m × m`) and HᵀWz.
struct LineSums {
    g: [[f64; 2]; 2],
    pz: [f64; 2],
    ph: Vec<[f64; 2]>,
    hh: Vec<f64>,
    hz: Vec<f64>,
}

impl LineSums {
    fn zeros(m: usize) -> Self {
        Self {
            g: [[0.0; 2]; 2],
            pz: [0.0; 2],
            ph: vec![[0.0; 2]; m],
            hh: vec![0.0; m * m],
            hz: vec![0.0; m],
        }
    }

    /// Adds `sign` × pixel (weight `w`, centred column `x`, design row `h`, height `v`,
    /// `None`: the height's terms are not touched).
    fn add_pixel(&mut self, sign: f64, w: f64, x: f64, h: &[f64], v: Option<f64>) {
        let w = sign * w;
        let m = h.len();
        self.g[0][0] += w;
        self.g[0][1] += w * x;
        self.g[1][1] += w * x * x;
        if let Some(v) = v {
            self.pz[0] += w * v;
            self.pz[1] += w * x * v;
        }
        for i in 0..m {
            let wh = w * h[i];
            self.ph[i][0] += wh;
            self.ph[i][1] += wh * x;
            if let Some(v) = v {
                self.hz[i] += wh * v;
            }
            let row = &mut self.hh[i * m..i * m + i + 1];
            for (acc, hj) in row.iter_mut().zip(h) {
                *acc += wh * hj;
            }
        }
    }
}

/// The harmonics' design row at pixel (column `c`, row `r`): (cos, sin) of
/// 2π(k_x·c + k_y·r) per harmonic.
fn design_row(k_px: &[[f64; 2]], c: usize, r: usize, h: &mut [f64]) {
    for (j, k) in k_px.iter().enumerate() {
        let (s, co) = (std::f64::consts::TAU * (k[0] * c as f64 + k[1] * r as f64)).sin_cos();
        h[2 * j] = co;
        h[2 * j + 1] = s;
    }
}

/// What every line shares: the sums of a *whole* line that do not depend on its heights
/// (they depend on the row only through each harmonic's phase e^{2πi·k_y·r}).
/// With E_j(c) = e^{2πi·k_x,j·c}: F_p(j) = Σ_c w·x^p·E_j, D±(i, j) = Σ_c w·E_i·E_j^{±1}.
struct WholeLine {
    g: [[f64; 2]; 2],
    /// E_j(c) at `c·harmonics + j` (a column's harmonics contiguous).
    by_column: Vec<Complex<f64>>,
    f: [Vec<Complex<f64>>; 2],
    /// `(i, j)`, j ≤ i, at `i·(i+1)/2 + j`.
    d_plus: Vec<Complex<f64>>,
    d_minus: Vec<Complex<f64>>,
}

impl WholeLine {
    fn new(k_px: &[[f64; 2]], weights: &[f64], centre: f64) -> Self {
        let nx = weights.len();
        let columns: Vec<Vec<Complex<f64>>> = k_px
            .iter()
            .map(|k| {
                (0..nx)
                    .map(|c| Complex::from_polar(1.0, std::f64::consts::TAU * k[0] * c as f64))
                    .collect()
            })
            .collect();
        let mut g = [[0.0; 2]; 2];
        for (c, &w) in weights.iter().enumerate() {
            let x = c as f64 - centre;
            g[0][0] += w;
            g[0][1] += w * x;
            g[1][1] += w * x * x;
        }
        let f = [0, 1].map(|p| {
            columns
                .iter()
                .map(|e| {
                    e.iter()
                        .zip(weights)
                        .enumerate()
                        .map(|(c, (e, w))| e * (w * if p == 0 { 1.0 } else { c as f64 - centre }))
                        .sum()
                })
                .collect()
        });
        let pairs = k_px.len() * (k_px.len() + 1) / 2;
        let (mut d_plus, mut d_minus) = (Vec::with_capacity(pairs), Vec::with_capacity(pairs));
        for i in 0..k_px.len() {
            for j in 0..=i {
                let (mut p, mut q) = (Complex::new(0.0, 0.0), Complex::new(0.0, 0.0));
                for ((a, b), w) in columns[i].iter().zip(&columns[j]).zip(weights) {
                    let wa = a * *w;
                    p += wa * b;
                    q += wa * b.conj();
                }
                d_plus.push(p);
                d_minus.push(q);
            }
        }
        let by_column = (0..nx)
            .flat_map(|c| columns.iter().map(move |e| e[c]))
            .collect();
        Self {
            g,
            by_column,
            f,
            d_plus,
            d_minus,
        }
    }

    /// Line `r`'s height-independent sums over all its pixels, into `out` (its `pz` and
    /// `hz` zeroed); the phases A_j = e^{2πi·k_y,j·r} given.
    fn fill(&self, phase: &[Complex<f64>], out: &mut LineSums) {
        let m = 2 * phase.len();
        out.g = self.g;
        out.pz = [0.0; 2];
        out.hz.fill(0.0);
        for (j, a) in phase.iter().enumerate() {
            for p in 0..2 {
                let v = a * self.f[p][j];
                out.ph[2 * j][p] = v.re;
                out.ph[2 * j + 1][p] = v.im;
            }
        }
        // cos·cos = ½Re(S₋ + S₊), sin·sin = ½Re(S₋ − S₊), sin_i·cos_j = ½Im(S₊ + S₋),
        // cos_i·sin_j = ½Im(S₊ − S₋); S± = Σ w·e^{i(φ_i ± φ_j)} = A_i·A_j^{±1}·D±.
        let mut at = 0;
        for i in 0..phase.len() {
            for j in 0..=i {
                let sp = phase[i] * phase[j] * self.d_plus[at];
                let sm = phase[i] * phase[j].conj() * self.d_minus[at];
                at += 1;
                let (ci, si) = (2 * i, 2 * i + 1);
                let (cj, sj) = (2 * j, 2 * j + 1);
                out.hh[ci * m + cj] = 0.5 * (sm.re + sp.re);
                out.hh[si * m + sj] = 0.5 * (sm.re - sp.re);
                out.hh[si * m + cj] = 0.5 * (sp.im + sm.im);
                if i != j {
                    out.hh[ci * m + sj] = 0.5 * (sp.im - sm.im);
                }
            }
        }
    }
}

/// Line `r`'s sums over its scanned pixels: the whole line's closed-form sums less its
/// unscanned pixels, or the scanned pixels summed directly — when most of the line is
/// unscanned (where that difference would lose precision) or without `whole` (the
/// reference the closed form is tested against).
fn line_sums(
    img: &Lines<'_>,
    k_px: &[[f64; 2]],
    weights: &[f64],
    whole: Option<&WholeLine>,
    r: usize,
    out: &mut LineSums,
) {
    let (nx, centre) = (img.nx, 0.5 * (img.nx as f64 - 1.0));
    let m = 2 * k_px.len();
    let row = &img.z[r * nx..(r + 1) * nx];
    let bad_row = &img.bad[r * nx..(r + 1) * nx];
    let good = |c: usize| !bad_row[c] && row[c].is_finite();
    let unscanned = (0..nx).filter(|&c| !good(c)).count();
    let mut h = vec![0.0; m];
    let whole = match whole {
        Some(whole) if 2 * unscanned <= nx => whole,
        _ => {
            *out = LineSums::zeros(m);
            for (c, &w) in weights.iter().enumerate() {
                if good(c) {
                    design_row(k_px, c, r, &mut h);
                    out.add_pixel(1.0, w, c as f64 - centre, &h, Some(row[c]));
                }
            }
            return;
        }
    };
    let phase: Vec<Complex<f64>> = k_px
        .iter()
        .map(|k| Complex::from_polar(1.0, std::f64::consts::TAU * k[1] * r as f64))
        .collect();
    whole.fill(&phase, out);
    for (c, &w) in weights.iter().enumerate() {
        if !good(c) {
            design_row(k_px, c, r, &mut h);
            out.add_pixel(-1.0, w, c as f64 - centre, &h, None);
        }
    }
    // The heights' sums: Σ w·v·(1, x) and Σ w·v·e^{iφ_j} = A_j·Σ w·v·E_j(c).
    let nh = k_px.len();
    let mut t = vec![Complex::new(0.0, 0.0); nh];
    for (c, &w) in weights.iter().enumerate() {
        if !good(c) {
            continue;
        }
        let e = &whole.by_column[c * nh..(c + 1) * nh];
        let wv = w * row[c];
        out.pz[0] += wv;
        out.pz[1] += wv * (c as f64 - centre);
        for (tj, e) in t.iter_mut().zip(e) {
            *tj += e * wv;
        }
    }
    for (j, (tj, a)) in t.iter().zip(&phase).enumerate() {
        let v = a * tj;
        out.hz[2 * j] = v.re;
        out.hz[2 * j + 1] = v.im;
    }
}

/// Per-line offsets and slopes fitted jointly with a cos/sin pair per harmonic `k_px`
/// (cycles per pixel, (column, row)).
///
/// The sums over a line that do not involve its heights are the same for every line up
/// to each harmonic's phase along the rows, so they are formed once ([`WholeLine`]):
/// the cost per line is that of the heights' sums and the m × m reduction, not m²
/// per pixel (issue 28: this fit inside the basis refinement was 38 % of a diagnosis).
fn joint_fit(img: &Lines<'_>, k_px: &[[f64; 2]]) -> JointFit {
    joint_fit_with(img, k_px, false)
}

/// [`joint_fit`]; `direct`: every line summed pixel by pixel (the reference the closed
/// form is tested against).
fn joint_fit_with(img: &Lines<'_>, k_px: &[[f64; 2]], direct: bool) -> JointFit {
    let (nx, ny) = (img.nx, img.ny);
    let m = 2 * k_px.len();
    let centre = 0.5 * (nx as f64 - 1.0);
    let weights: Vec<f64> = (0..nx).map(|c| taper(c, nx)).collect();
    let mut a = DMatrix::<f64>::zeros(m, m);
    let mut b = DVector::<f64>::zeros(m);
    let mut lines = Vec::with_capacity(ny);
    let whole = (!direct).then(|| WholeLine::new(k_px, &weights, centre));
    let mut sums = LineSums::zeros(m);
    for r in 0..ny {
        line_sums(img, k_px, &weights, whole.as_ref(), r, &mut sums);
        let LineSums {
            mut g,
            pz,
            ref ph,
            ref hh,
            ref hz,
        } = sums;
        g[1][0] = g[0][1];
        g[0][0] *= 1.0 + LINE_RIDGE;
        g[1][1] *= 1.0 + LINE_RIDGE;
        let det = g[0][0] * g[1][1] - g[0][1] * g[1][0];
        let invertible = g[0][0] > 0.0 && det > 1e-12 * (g[0][0] * g[1][1]).max(1e-300);
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
        lines.push(Some((gi, pz, ph.clone())));
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The closed-form line sums give the pixel-by-pixel fit: a lattice with line
    /// offsets, a few unscanned pixels on some lines and most of one line unscanned.
    #[test]
    fn the_closed_form_sums_are_the_pixel_sums() {
        let (nx, ny) = (53, 41);
        let basis = [[0.137, 0.021], [-0.052, 0.128]];
        let k_px = harmonics_of(basis, 2.05);
        assert!(k_px.len() >= 6, "{} harmonics", k_px.len());
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let mut noise = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1);
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let mut z = vec![0.0; nx * ny];
        let mut bad = vec![false; nx * ny];
        for r in 0..ny {
            let offset = noise();
            for c in 0..nx {
                let (x, y) = (c as f64, r as f64);
                let phase = |k: [f64; 2]| std::f64::consts::TAU * (k[0] * x + k[1] * y);
                z[r * nx + c] =
                    phase(basis[0]).cos() + 0.5 * phase(basis[1]).sin() + offset + 0.1 * noise();
                bad[r * nx + c] = (r % 7 == 3 && c % 11 == 2) || (r == 20 && c > 10);
            }
        }
        z[5 * nx + 9] = f64::NAN;
        let img = Lines {
            z: &z,
            bad: &bad,
            nx,
            ny,
        };
        let fast = joint_fit(&img, &k_px);
        let direct = joint_fit_with(&img, &k_px, true);
        let scale = direct.theta.amax().max(1.0);
        assert!(
            (&fast.theta - &direct.theta).amax() < 1e-9 * scale,
            "θ {} against {}",
            fast.theta,
            direct.theta
        );
        assert!((fast.explained - direct.explained).abs() < 1e-9 * direct.explained.abs());
        assert!(
            direct.explained > 1.0,
            "the lattice explains {}",
            direct.explained
        );
        for (r, (a, b)) in fast.lines.iter().zip(&direct.lines).enumerate() {
            let (Some(a), Some(b)) = (a, b) else {
                panic!("line {r}: {} against {}", a.is_some(), b.is_some());
            };
            for (p, q) in a.2.iter().zip(&b.2) {
                assert!(
                    (p[0] - q[0]).abs() + (p[1] - q[1]).abs() < 1e-9 * nx as f64,
                    "line {r}"
                );
            }
            assert!((a.1[0] - b.1[0]).abs() + (a.1[1] - b.1[1]).abs() < 1e-9 * nx as f64);
        }
        // No harmonics: the plain per-line fit, the same lines' sums.
        let (fast, direct) = (joint_fit(&img, &[]), joint_fit_with(&img, &[], true));
        assert_eq!(fast.theta.len(), 0);
        for (a, b) in fast.lines.iter().zip(&direct.lines) {
            let (Some(a), Some(b)) = (a, b) else {
                panic!("{} against {}", a.is_some(), b.is_some());
            };
            assert!((a.1[0] - b.1[0]).abs() + (a.1[1] - b.1[1]).abs() < 1e-9 * nx as f64);
            assert!(b.1[0].abs() > 0.0);
        }
    }
}
