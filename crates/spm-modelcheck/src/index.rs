//! Indexing features to lattice sites: integer (i, j) from the measured lattice vectors.
//!
//! The basis is measured once, from the largest group of features (one frame,
//! one direction), as the two most populated nearest-neighbour directions.
//! Every group is then indexed by a breadth-first walk from the feature nearest
//! the reference origin: a neighbour's index is the walker's index plus the
//! rounded local offset in basis units, so smooth distortion (nonlinearity,
//! drift) never accumulates into a wrong index.

use crate::types::{FeatureSet, LatticeSpec, LineDirection, ModelCheckError};
use std::collections::VecDeque;

/// The lattice found in the data.
#[derive(Clone, Debug, PartialEq)]
pub struct MeasuredBasis {
    /// First basis vector, nominal nm.
    pub b1_nm: [f64; 2],
    /// Second basis vector, nominal nm.
    pub b2_nm: [f64; 2],
    /// True first basis vector in the lattice frame, nm.
    pub a1_nm: [f64; 2],
    /// True second basis vector, nm (same handedness and angle class as b1, b2).
    pub a2_nm: [f64; 2],
}

/// The lattice site of every feature (`None` = not indexed), and the basis.
#[derive(Clone, Debug, PartialEq)]
pub struct Indexing {
    /// Integer (i, j) of every feature, `None` when it could not be indexed.
    pub sites: Vec<Option<[i64; 2]>>,
    /// The basis used.
    pub basis: MeasuredBasis,
    /// Warnings (e.g. frames whose lattice differs from the reference's).
    pub warnings: Vec<String>,
}

use spm_regression::median;

/// Nearest-neighbour lattice basis of a point set, or `None`.
fn measure_basis(points: &[[f64; 2]], a_expected_nm: Option<f64>) -> Option<([f64; 2], [f64; 2])> {
    if points.len() < 4 {
        return None;
    }
    let mut nn: Vec<f64> = points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            points
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, q)| (q[0] - p[0]).hypot(q[1] - p[1]))
                .fold(f64::INFINITY, f64::min)
        })
        .collect();
    let d_nn = median(&mut nn)?;
    let d_nn = match a_expected_nm {
        // Guard against duplicated detections: never below half the period.
        Some(a) if d_nn < 0.6 * a => a,
        _ => d_nn,
    };
    if !(d_nn.is_finite() && d_nn > 0.0) {
        return None;
    }
    // Cluster folded neighbour vectors by direction (angle mod π): spm-features' kernel, with
    // pairs within 30 % of the nearest-neighbour distance, directions within 14°.
    let pos: Vec<(f64, f64)> = points.iter().map(|p| (p[0], p[1])).collect();
    let mut clusters = spm_features::neighbour_vector_clusters(
        &pos,
        |len| len > 0.7 * d_nn && len < 1.3 * d_nn,
        |cos_abs| cos_abs > 0.97,
    );
    clusters.sort_by_key(|c| std::cmp::Reverse(c.n));
    let mean = |c: &spm_features::VectorCluster| {
        let (x, y) = c.mean();
        [x, y]
    };
    let first = clusters.first()?;
    let b1 = mean(first);
    // The second: the most populated direction clearly not parallel to b1.
    let b2 = clusters.iter().skip(1).map(mean).find(|v| {
        let cross = b1[0] * v[1] - b1[1] * v[0];
        (cross / (b1[0].hypot(b1[1]) * v[0].hypot(v[1]))).abs() > 0.5
    })?;
    Some((b1, b2))
}

/// The reference basis refined on a group's own neighbour vectors: for each
/// of b1, b2, the mean of the group's neighbour differences within 30 % of it
/// (sign-folded). `None` when either has fewer than three matches.
fn refine_basis(points: &[[f64; 2]], b1: [f64; 2], b2: [f64; 2]) -> Option<([f64; 2], [f64; 2])> {
    let mut out = [[0.0; 2]; 2];
    for (o, b) in out.iter_mut().zip([b1, b2]) {
        // Squared lengths compared (this loop over all pairs is hot; no hypot needed).
        let len2 = b[0] * b[0] + b[1] * b[1];
        let d2 = |v: [f64; 2], s: f64| (v[0] + s * b[0]).powi(2) + (v[1] + s * b[1]).powi(2);
        let (mut sum, mut n) = ([0.0, 0.0], 0usize);
        for (i, p) in points.iter().enumerate() {
            for q in points.iter().skip(i + 1) {
                let mut v = [q[0] - p[0], q[1] - p[1]];
                if d2(v, 1.0) < d2(v, -1.0) {
                    v = [-v[0], -v[1]];
                }
                if d2(v, -1.0) < 0.09 * len2 {
                    sum[0] += v[0];
                    sum[1] += v[1];
                    n += 1;
                }
            }
        }
        if n < 3 {
            return None;
        }
        *o = [sum[0] / n as f64, sum[1] / n as f64];
    }
    Some((out[0], out[1]))
}

/// Structure factor |Σ e^{2πi k·r}|² / N of a point set at wave vector `k` (1/nm).
fn structure_factor(points: &[[f64; 2]], k: [f64; 2]) -> f64 {
    let (mut re, mut im) = (0.0, 0.0);
    for p in points {
        let (s, c) = (std::f64::consts::TAU * (k[0] * p[0] + k[1] * p[1])).sin_cos();
        re += c;
        im += s;
    }
    (re * re + im * im) / points.len().max(1) as f64
}

/// The strongest structure-factor peak within `|k|` ∈ [k_min, k_max] and
/// angle ∈ [θ_min, θ_max] (rad), refined on a finer grid.
fn peak(points: &[[f64; 2]], k_range: [f64; 2], theta_range: [f64; 2]) -> Option<([f64; 2], f64)> {
    let (nr, nt) = (48usize, 120usize);
    let mut best: Option<(f64, f64, f64)> = None; // (S, |k|, θ)
    let lk = [k_range[0].ln(), k_range[1].ln()];
    let dl = (lk[1] - lk[0]) / nr as f64;
    let dt = (theta_range[1] - theta_range[0]) / nt as f64;
    for i in 0..=nr {
        let kr = (lk[0] + i as f64 * dl).exp();
        for j in 0..=nt {
            let t = theta_range[0] + j as f64 * dt;
            let v = structure_factor(points, [kr * t.cos(), kr * t.sin()]);
            if best.is_none_or(|b| v > b.0) {
                best = Some((v, kr, t));
            }
        }
    }
    let (mut v, mut kr, mut t) = best?;
    // Refine: halve the steps three times around the best point.
    let (mut sl, mut st) = (dl, dt);
    for _ in 0..4 {
        let (v0, k0, t0) = (v, kr, t);
        for i in -2..=2 {
            for j in -2..=2 {
                let kk = k0 * (i as f64 * sl / 2.0).exp();
                let tt = t0 + j as f64 * st / 2.0;
                let w = structure_factor(points, [kk * tt.cos(), kk * tt.sin()]);
                if w > v {
                    (v, kr, t) = (w, kk, tt);
                }
            }
        }
        let _ = v0;
        sl /= 2.0;
        st /= 2.0;
    }
    Some(([kr * t.cos(), kr * t.sin()], v))
}

/// Lattice indices of points from two reciprocal vectors: n = round(k·r − φ),
/// φ the circular mean phase; `None` for points more than 0.3 off a site.
/// Returns the indices and the fraction of points on sites.
fn phase_index(points: &[[f64; 2]], k1: [f64; 2], k2: [f64; 2]) -> (Vec<Option<[i64; 2]>>, f64) {
    let phase0 = |k: [f64; 2]| {
        let (mut re, mut im) = (0.0, 0.0);
        for p in points {
            let (s, c) = (std::f64::consts::TAU * (k[0] * p[0] + k[1] * p[1])).sin_cos();
            re += c;
            im += s;
        }
        im.atan2(re) / std::f64::consts::TAU
    };
    let (f1, f2) = (phase0(k1), phase0(k2));
    let mut on = 0usize;
    let out: Vec<Option<[i64; 2]>> = points
        .iter()
        .map(|p| {
            let u = k1[0] * p[0] + k1[1] * p[1] - f1;
            let v = k2[0] * p[0] + k2[1] * p[1] - f2;
            let (nu, nv) = (u.round(), v.round());
            ((u - nu).abs() < 0.3 && (v - nv).abs() < 0.3).then(|| {
                on += 1;
                [nu as i64, nv as i64]
            })
        })
        .collect();
    let fraction = on as f64 / points.len().max(1) as f64;
    (out, fraction)
}

/// The reference group's reciprocal vectors from the structure factor, when
/// they index clearly more features than the neighbour basis (≥ 100 features).
fn fourier_registration(
    points: &[[f64; 2]],
    b1: [f64; 2],
    b2: [f64; 2],
    lattice: &LatticeSpec,
) -> Option<([f64; 2], [f64; 2])> {
    // Only when the neighbour walk has poor material: most nearest-neighbour
    // vectors are not lattice vectors (a clean but strongly distorted
    // lattice is better walked — the walk follows smooth distortion, a
    // global phase does not).
    if points.len() < 100 || nn_fraction(points, b1, b2) >= 0.6 {
        return None;
    }
    let q_nn = reciprocal(b1, b2).map_or(0.0, |(r1, r2)| phase_index(points, r1, r2).1);
    let a = lattice.a_nm();
    let row = match lattice {
        LatticeSpec::Hex { .. } => a * 0.75f64.sqrt(),
        LatticeSpec::Square { .. } => a,
    };
    let kc = 1.0 / row;
    // Within ±35 %: instrument calibrations are not further off, and the
    // lattice's own harmonics (√3 × for a triangular lattice) stay outside.
    let range = [kc / 1.35, kc * 1.35];
    let (k1, _) = peak(points, range, [0.0, std::f64::consts::PI])?;
    let t1 = k1[1].atan2(k1[0]);
    let (k2, _) = peak(
        points,
        range,
        [t1 + 35f64.to_radians(), t1 + 145f64.to_radians()],
    )?;
    let (_, q_f) = phase_index(points, k1, k2);
    tracing::debug!(q_nn, q_f, "lattice registration by structure factor");
    (q_f > 0.5 && q_f > q_nn + 0.1).then_some((k1, k2))
}

/// The refusal test's measure on a point set: the fraction of points whose nearest
/// neighbour is a lattice vector of their own nearest-neighbour basis (0 when no basis).
pub(crate) fn own_nn_fraction(points: &[[f64; 2]]) -> f64 {
    measure_basis(points, None).map_or(0.0, |(b1, b2)| nn_fraction(points, b1, b2))
}

/// Fraction of points whose nearest neighbour is a lattice vector of (b1, b2)
/// within 0.2 in basis units.
fn nn_fraction(points: &[[f64; 2]], b1: [f64; 2], b2: [f64; 2]) -> f64 {
    let Some(inv) = inverse(b1, b2) else {
        return 0.0;
    };
    let mut good = 0usize;
    for (i, p) in points.iter().enumerate() {
        let nearest = points
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != i)
            .map(|(_, q)| [q[0] - p[0], q[1] - p[1]])
            .min_by(|u, v| (u[0] * u[0] + u[1] * u[1]).total_cmp(&(v[0] * v[0] + v[1] * v[1])));
        let Some(d) = nearest else { continue };
        let f = [
            inv[0][0] * d[0] + inv[0][1] * d[1],
            inv[1][0] * d[0] + inv[1][1] * d[1],
        ];
        let r = [f[0].round(), f[1].round()];
        if (f[0] - r[0]).abs() < 0.2 && (f[1] - r[1]).abs() < 0.2 && r != [0.0, 0.0] {
            good += 1;
        }
    }
    good as f64 / points.len().max(1) as f64
}

/// A group's own reciprocal vectors: the structure factor's local maxima reached by
/// climbing from the reference's (accepted within ±15 % in length and ±8° in direction).
/// Another frame or direction of one series is distorted differently, but by far less
/// than the distance to the pattern's other peaks; a free search of the window (as
/// before) could jump to one of them — a Si 7×7 pit set's fractional-order peaks gave
/// the forward and backward images of `Si_7x7_028` lattices 19 % apart.
fn refine_reciprocal(points: &[[f64; 2]], k1: [f64; 2], k2: [f64; 2]) -> ([f64; 2], [f64; 2]) {
    let near = |k: [f64; 2]| {
        let r = k[0].hypot(k[1]);
        let (q, _) = spm_features::cells::climb(&|q| structure_factor(points, q), k, 0.01 * r);
        let (rq, turn) = (
            q[0].hypot(q[1]),
            (k[0] * q[1] - k[1] * q[0]).atan2(k[0] * q[0] + k[1] * q[1]),
        );
        if (rq / r - 1.0).abs() <= 0.15 && turn.abs() <= 8f64.to_radians() {
            q
        } else {
            k
        }
    };
    (near(k1), near(k2))
}

/// Reciprocal vectors (rows of B⁻ᵀ) of a real-space basis.
fn reciprocal(b1: [f64; 2], b2: [f64; 2]) -> Option<([f64; 2], [f64; 2])> {
    let inv = inverse(b1, b2)?;
    // inv rows are the reciprocal vectors: inv·b_j = e_j.
    Some((inv[0], inv[1]))
}

/// Refuses a point set that is not the claimed lattice: the measured basis
/// must have the claimed period within a factor 1.6 (instrument calibrations
/// are never off by more) and the claimed angle class within 30°, and most
/// features' nearest-neighbour vectors must be lattice vectors (within 0.2 in
/// basis units). Random points (noise peaks, adsorbates) pass the last test
/// for ≈ 20 % of features, a lattice for nearly all.
fn check_lattice(
    points: &[[f64; 2]],
    b1: [f64; 2],
    b2: [f64; 2],
    lattice: &LatticeSpec,
    context: &str,
) -> Result<(usize, usize), ModelCheckError> {
    let refuse = |reason: String| {
        Err(ModelCheckError::NotTheLattice {
            context: context.to_owned(),
            reason,
        })
    };
    if points.len() < 6 {
        return refuse(format!("only {} features", points.len()));
    }
    let a = lattice.a_nm();
    for b in [b1, b2] {
        let r = b[0].hypot(b[1]) / a;
        if !(r > 1.0 / 1.6 && r < 1.6) {
            return refuse(format!(
                "the features' period is {:.4} nm, the claimed lattice's {a:.4} nm",
                b[0].hypot(b[1])
            ));
        }
    }
    let cos = (b1[0] * b2[0] + b1[1] * b2[1]) / (b1[0].hypot(b1[1]) * b2[0].hypot(b2[1]));
    let angle = cos.clamp(-1.0, 1.0).acos().to_degrees();
    let expected: &[f64] = match lattice {
        LatticeSpec::Hex { .. } => &[60.0, 120.0],
        LatticeSpec::Square { .. } => &[90.0],
    };
    if !expected.iter().any(|e| (angle - e).abs() < 30.0) {
        return refuse(format!("the features' lattice angle is {angle:.0}°"));
    }
    let Some(inv) = inverse(b1, b2) else {
        return refuse("degenerate basis".to_owned());
    };
    let mut good = 0usize;
    for (i, p) in points.iter().enumerate() {
        let nearest = points
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != i)
            .map(|(_, q)| [q[0] - p[0], q[1] - p[1]])
            .min_by(|u, v| (u[0] * u[0] + u[1] * u[1]).total_cmp(&(v[0] * v[0] + v[1] * v[1])));
        let Some(d) = nearest else { continue };
        let f = [
            inv[0][0] * d[0] + inv[0][1] * d[1],
            inv[1][0] * d[0] + inv[1][1] * d[1],
        ];
        let r = [f[0].round(), f[1].round()];
        if (f[0] - r[0]).abs() < 0.2 && (f[1] - r[1]).abs() < 0.2 && r != [0.0, 0.0] {
            good += 1;
        }
    }
    let fraction = good as f64 / points.len() as f64;
    // A clearly random group (enough features to tell) is refused alone.
    if points.len() >= 30 && fraction < RANDOM_NN_FRACTION {
        return refuse(format!(
            "only {:.0} % of the features have a lattice vector to their nearest neighbour",
            100.0 * fraction
        ));
    }
    Ok((good, points.len()))
}

/// Fraction of features whose nearest neighbour is a lattice vector (within
/// 0.2 in basis units) for random points (noise peaks, adsorbates) with the
/// detector's minimum separation: measured 0.18–0.28 on white-noise and blob
/// images (tests/it/image.rs); a lattice gives 0.8–1, a lattice with many
/// spurious detections (Si 7×7 with defects) 0.3–0.5.
const RANDOM_NN_FRACTION: f64 = 0.25;
/// Pooled over all frames and directions, at least this fraction is needed.
const LATTICE_NN_FRACTION: f64 = 0.33;

fn inverse(b1: [f64; 2], b2: [f64; 2]) -> Option<[[f64; 2]; 2]> {
    let det = b1[0] * b2[1] - b2[0] * b1[1];
    if !(det.is_finite() && det.abs() > 1e-300) {
        return None;
    }
    Some([[b2[1] / det, -b2[0] / det], [-b1[1] / det, b1[0] / det]])
}

/// A group of features: one frame's one scan direction, and the features' indices.
type Group = ((usize, LineDirection), Vec<usize>);

/// A reciprocal basis (k₁, k₂), cycles per nm.
type Reciprocal = ([f64; 2], [f64; 2]);

/// The features grouped by (frame, direction), the largest group first.
fn feature_groups(set: &FeatureSet) -> Vec<Group> {
    let mut groups: Vec<Group> = Vec::new();
    for (k, f) in set.features.iter().enumerate() {
        let key = (f.frame_index, f.direction);
        match groups.iter_mut().find(|g| g.0 == key) {
            Some(g) => g.1.push(k),
            None => groups.push((key, vec![k])),
        }
    }
    groups.sort_by_key(|g| std::cmp::Reverse(g.1.len()));
    groups
}

/// The positions (nm) of the features `members`.
fn member_points(set: &FeatureSet, members: &[usize]) -> Vec<[f64; 2]> {
    members
        .iter()
        .map(|&k| [set.features[k].x_nm, set.features[k].y_nm])
        .collect()
}

/// The direct basis (b₁, b₂) of the reciprocal basis (k₁, k₂), when it is invertible.
fn direct_basis((k1, k2): Reciprocal) -> Option<([f64; 2], [f64; 2])> {
    inverse([k1[0], k2[0]], [k1[1], k2[1]])
        .map(|inv| ([inv[0][0], inv[1][0]], [inv[0][1], inv[1][1]]))
}

/// The measured basis with the true one of the same angle class and handedness.
fn measured_basis(b1: [f64; 2], b2: [f64; 2], lattice: &LatticeSpec) -> MeasuredBasis {
    let a = lattice.a_nm();
    let cos_measured = (b1[0] * b2[0] + b1[1] * b2[1]) / (b1[0].hypot(b1[1]) * b2[0].hypot(b2[1]));
    let gamma = match lattice {
        LatticeSpec::Hex { .. } if cos_measured < 0.0 => 2.0 * lattice.basis_angle_rad(),
        _ => lattice.basis_angle_rad(),
    };
    let handed = (b1[0] * b2[1] - b1[1] * b2[0]).signum();
    MeasuredBasis {
        b1_nm: b1,
        b2_nm: b2,
        a1_nm: [a, 0.0],
        a2_nm: [a * gamma.cos(), handed * a * gamma.sin()],
    }
}

/// What the reference group gives every other: its basis (b₁, b₂), nm, and the
/// structure-factor registration's reciprocal basis when it is used.
#[derive(Clone, Copy)]
struct Reference {
    b1: [f64; 2],
    b2: [f64; 2],
    phase_mode: Option<Reciprocal>,
}

impl Reference {
    /// A group's own basis, found the way it will be indexed: by the structure factor's
    /// peaks followed from the reference's (`None` when that registration is off or
    /// degenerate), else by its neighbour vectors from the reference's.
    fn group_basis(&self, pts: &[[f64; 2]]) -> ([f64; 2], [f64; 2]) {
        let from_k = self
            .phase_mode
            .and_then(|(k1, k2)| direct_basis(refine_reciprocal(pts, k1, k2)));
        from_k.unwrap_or_else(|| refine_basis(pts, self.b1, self.b2).unwrap_or((self.b1, self.b2)))
    }
}

/// Checks every group after the reference against the lattice, and warns where a group's
/// lattice differs from the reference's by more than drift could: (sites on the lattice,
/// features) over the groups, and the warnings.
fn check_other_groups(
    set: &FeatureSet,
    groups: &[Group],
    reference: &Reference,
    lattice: &LatticeSpec,
    label: &dyn Fn((usize, LineDirection)) -> String,
) -> Result<(usize, usize, Vec<String>), ModelCheckError> {
    let (b1, b2) = (reference.b1, reference.b2);
    let ref_len = [b1[0].hypot(b1[1]), b2[0].hypot(b2[1])];
    let (mut good_total, mut n_total) = (0, 0);
    let mut warnings = Vec::new();
    for (key, members) in groups.iter().skip(1) {
        let pts = member_points(set, members);
        if pts.len() < 6 {
            continue;
        }
        let (g1, g2) = reference.group_basis(&pts);
        let (g, n) = check_lattice(&pts, g1, g2, lattice, &label(*key))?;
        good_total += g;
        n_total += n;
        // One sample, one scan series: the lattice seen in every frame should
        // agree with the reference up to drift-sized distortion.
        let rot = |a: [f64; 2], b: [f64; 2]| {
            ((a[0] * b[1] - a[1] * b[0]).atan2(a[0] * b[0] + a[1] * b[1])).to_degrees()
        };
        let dr = rot(b1, g1).abs().max(rot(b2, g2).abs());
        let dl = ((g1[0].hypot(g1[1]) / ref_len[0]) - 1.0)
            .abs()
            .max(((g2[0].hypot(g2[1]) / ref_len[1]) - 1.0).abs());
        if dr > 5.0 || dl > 0.15 {
            warnings.push(format!(
                "{}: the lattice differs from {} by {dr:.1}° and {:.0} % in length: \
                 these frames may not be one scan series of one area",
                label(*key),
                label(groups[0].0),
                100.0 * dl
            ));
        }
    }
    Ok((good_total, n_total, warnings))
}

/// Indexes one group by the neighbour walk: from its seed (given `seed_site`), retried
/// from the next features nearest it while the walk stays small (an isolated or spurious
/// seed), then across defects and missing atoms from the nearest indexed feature within
/// three basis lengths.
fn walk_group(
    pts: &[[f64; 2]],
    (seed, seed_site): (usize, [i64; 2]),
    frac: &dyn Fn([f64; 2]) -> [f64; 2],
    b_len: f64,
) -> Vec<Option<[i64; 2]>> {
    let mut order: Vec<usize> = (0..pts.len()).collect();
    order.sort_by(|&p, &q| {
        let dp = (pts[p][0] - pts[seed][0]).hypot(pts[p][1] - pts[seed][1]);
        let dq = (pts[q][0] - pts[seed][0]).hypot(pts[q][1] - pts[seed][1]);
        dp.total_cmp(&dq)
    });
    let mut local: Vec<Option<[i64; 2]>> = vec![None; pts.len()];
    let mut best_count = 0usize;
    for &start in order.iter().take(12) {
        let site0 = if start == seed {
            seed_site
        } else {
            let f = frac([pts[start][0] - pts[seed][0], pts[start][1] - pts[seed][1]]);
            [
                seed_site[0] + f[0].round() as i64,
                seed_site[1] + f[1].round() as i64,
            ]
        };
        let walk = walk_lattice(pts, start, site0, frac, b_len);
        let count = walk.iter().filter(|s| s.is_some()).count();
        if count > best_count {
            best_count = count;
            local = walk;
        }
        if 2 * best_count > pts.len() {
            break;
        }
    }
    loop {
        let mut best: Option<(f64, usize, usize)> = None;
        for q in 0..pts.len() {
            if local[q].is_some() {
                continue;
            }
            for p in 0..pts.len() {
                if local[p].is_none() {
                    continue;
                }
                let d = (pts[q][0] - pts[p][0]).hypot(pts[q][1] - pts[p][1]);
                if d < 3.0 * b_len && best.is_none_or(|b| d < b.0) {
                    best = Some((d, q, p));
                }
            }
        }
        let Some((_, q, p)) = best else { break };
        let Some(ip) = local[p] else { break };
        let f = frac([pts[q][0] - pts[p][0], pts[q][1] - pts[p][1]]);
        let site0 = [ip[0] + f[0].round() as i64, ip[1] + f[1].round() as i64];
        let walk = walk_lattice(pts, q, site0, frac, b_len);
        for (l, w) in local.iter_mut().zip(walk) {
            if l.is_none() {
                *l = w;
            }
        }
    }
    local
}

/// A frame's other half (backward vs forward) sees the same atoms, but trace and retrace
/// can be shifted by up to a lattice constant mid-line (hysteresis, lag): shifts the
/// group's sites `local` by a vote over its features near the line ends, where hysteresis
/// vanishes (the loop closes at the turnaround), against the half of `frame` already
/// indexed in `sites`.
fn register_with_other_half(
    set: &FeatureSet,
    frame: usize,
    sites: &[Option<[i64; 2]>],
    pts: &[[f64; 2]],
    local: &mut [Option<[i64; 2]>],
    frac: &dyn Fn([f64; 2]) -> [f64; 2],
    b_len: f64,
) {
    let half_x = set
        .frames
        .get(frame)
        .map_or(f64::INFINITY, |f| f.half_width_x_nm.max(1e-12));
    let other: Vec<(usize, [i64; 2])> = sites
        .iter()
        .enumerate()
        .filter_map(|(k, s)| s.map(|s| (k, s)))
        .filter(|(k, _)| set.features[*k].frame_index == frame)
        .collect();
    if other.is_empty() {
        return;
    }
    let mut votes: std::collections::HashMap<[i64; 2], f64> = std::collections::HashMap::new();
    for edge_limit in [0.8, 0.6, 0.0] {
        for (m, l) in local.iter().enumerate() {
            let Some(l) = l else { continue };
            let xi = (pts[m][0] / half_x).abs();
            if xi < edge_limit {
                continue;
            }
            let nearest = other
                .iter()
                .map(|&(k, s)| {
                    let f = &set.features[k];
                    ([pts[m][0] - f.x_nm, pts[m][1] - f.y_nm], s)
                })
                .min_by(|a, b| a.0[0].hypot(a.0[1]).total_cmp(&b.0[0].hypot(b.0[1])));
            let Some((d, s)) = nearest else { continue };
            if d[0].hypot(d[1]) > 0.75 * b_len {
                continue;
            }
            let f = frac(d);
            let implied = [s[0] + f[0].round() as i64, s[1] + f[1].round() as i64];
            // Features nearest the turnaround count most.
            *votes
                .entry([implied[0] - l[0], implied[1] - l[1]])
                .or_insert(0.0) += xi * xi + 0.05;
        }
        if votes.values().sum::<f64>() >= 3.0 {
            break;
        }
    }
    if let Some((shift, _)) = votes
        .into_iter()
        .max_by(|a, b| a.1.total_cmp(&b.1).then(b.0.cmp(&a.0)))
    {
        for l in local.iter_mut().flatten() {
            l[0] += shift[0];
            l[1] += shift[1];
        }
    }
}

/// Indexes every feature of `set` to a lattice site.
pub fn index_features(
    set: &FeatureSet,
    lattice: &LatticeSpec,
) -> Result<Indexing, ModelCheckError> {
    let groups = feature_groups(set);
    let reference = groups
        .first()
        .ok_or_else(|| ModelCheckError::NoLattice("an empty feature set".to_owned()))?;
    let ref_points = member_points(set, &reference.1);
    let label = |key: (usize, LineDirection)| {
        let name = set
            .frames
            .get(key.0)
            .map_or_else(|| format!("frame {}", key.0), |f| f.label.clone());
        format!("{name}, {:?}", key.1).to_lowercase()
    };
    let (mut b1, mut b2) =
        measure_basis(&ref_points, None).ok_or_else(|| ModelCheckError::NotTheLattice {
            context: label(reference.0),
            reason: "no two lattice directions among the features".to_owned(),
        })?;
    // Lattice-level registration: when many features are not on the lattice
    // (defects, half-cell minima, noise peaks), neighbour vectors mislead; the
    // structure factor of the whole point set still peaks at the lattice's
    // reciprocal vectors (an affine drift distortion only moves the peaks).
    // Use it when it puts clearly more features on sites.
    let phase_mode = fourier_registration(&ref_points, b1, b2, lattice);
    if let Some((g1, g2)) = phase_mode.and_then(direct_basis) {
        (b1, b2) = (g1, g2);
    }
    let binv =
        inverse(b1, b2).ok_or_else(|| ModelCheckError::NoLattice("degenerate basis".into()))?;
    let basis = measured_basis(b1, b2, lattice);
    let (good_ref, n_ref) = check_lattice(&ref_points, b1, b2, lattice, &label(reference.0))?;
    let reference_basis = Reference { b1, b2, phase_mode };
    let (good_other, n_other, warnings) =
        check_other_groups(set, &groups, &reference_basis, lattice, &label)?;
    let (good_total, n_total) = (good_ref + good_other, n_ref + n_other);
    let pooled = good_total as f64 / n_total.max(1) as f64;
    // (With the structure-factor registration the reference group has
    // already shown more than half its features on lattice sites.)
    if phase_mode.is_none() && pooled < LATTICE_NN_FRACTION {
        return Err(ModelCheckError::NotTheLattice {
            context: format!("{} features in {} group(s)", n_total, groups.len()),
            reason: format!(
                "only {:.0} % of the features have a lattice vector to their nearest \
                 neighbour (random points: about 20 %, a lattice: 80–100 %)",
                100.0 * pooled
            ),
        });
    }
    // Reference origin: the reference-group feature nearest the frame centre.
    let origin_k = reference
        .1
        .iter()
        .copied()
        .min_by(|&p, &q| {
            let fp = &set.features[p];
            let fq = &set.features[q];
            fp.x_nm.hypot(fp.y_nm).total_cmp(&fq.x_nm.hypot(fq.y_nm))
        })
        .ok_or_else(|| ModelCheckError::NoLattice("no origin".into()))?;
    let origin = [set.features[origin_k].x_nm, set.features[origin_k].y_nm];
    let frac = |d: [f64; 2]| {
        [
            binv[0][0] * d[0] + binv[0][1] * d[1],
            binv[1][0] * d[0] + binv[1][1] * d[1],
        ]
    };
    let b_len = b1[0].hypot(b1[1]).max(b2[0].hypot(b2[1]));
    let mut sites: Vec<Option<[i64; 2]>> = vec![None; set.features.len()];
    for (_, members) in &groups {
        let pts = member_points(set, members);
        // Seed: nearest to the reference origin (same frame as the reference ⇒
        // same site; another frame ⇒ the per-frame offset absorbs the choice).
        let Some(seed) = (0..pts.len()).min_by(|&p, &q| {
            let dp = (pts[p][0] - origin[0]).hypot(pts[p][1] - origin[1]);
            let dq = (pts[q][0] - origin[0]).hypot(pts[q][1] - origin[1]);
            dp.total_cmp(&dq)
        }) else {
            continue;
        };
        let frame = set.features[members[seed]].frame_index;
        let f0 = frac([pts[seed][0] - origin[0], pts[seed][1] - origin[1]]);
        let seed_site = [f0[0].round() as i64, f0[1].round() as i64];
        // The group's own metric: the reference basis refined on this group's
        // neighbour vectors (another frame may be distorted differently by
        // its drift); its index directions stay those of the reference.
        let group_k = phase_mode.map(|(k1, k2)| refine_reciprocal(&pts, k1, k2));
        let (g1, g2) = match group_k {
            Some(k) => direct_basis(k).unwrap_or((b1, b2)),
            None => refine_basis(&pts, b1, b2).unwrap_or((b1, b2)),
        };
        let ginv = inverse(g1, g2).unwrap_or(binv);
        let gfrac = |d: [f64; 2]| {
            [
                ginv[0][0] * d[0] + ginv[0][1] * d[1],
                ginv[1][0] * d[0] + ginv[1][1] * d[1],
            ]
        };
        let mut local = match group_k {
            // Indexed by phase: the whole group at once, off-site features left out.
            Some((k1, k2)) => phase_index(&pts, k1, k2).0,
            None => walk_group(&pts, (seed, seed_site), &gfrac, b_len),
        };
        // Large distortions: regrown from the group's centre with the site map iterated
        // (`grow`), where one basis or one phase would slip by a site.
        if let Some(grown) = set.frames.get(frame).and_then(|f| {
            crate::grow::grow_from_centre(&pts, &local, [f.half_width_x_nm, f.half_height_y_nm])
        }) {
            local = grown;
        }
        register_with_other_half(set, frame, &sites, &pts, &mut local, &gfrac, b_len);
        // Duplicate sites in one group: keep none of them (ambiguous).
        let mut seen = std::collections::HashMap::new();
        for s in local.iter().flatten() {
            *seen.entry(*s).or_insert(0usize) += 1;
        }
        for (m, &k) in members.iter().enumerate() {
            sites[k] = local[m].filter(|s| seen.get(s).copied() == Some(1));
        }
    }
    Ok(Indexing {
        sites,
        basis,
        warnings,
    })
}

/// Breadth-first indexing from `start` (given `site0`): a neighbour within
/// 1.6 basis lengths gets the walker's index plus its rounded offset when the
/// offset is within 0.35 of a lattice vector.
fn walk_lattice(
    pts: &[[f64; 2]],
    start: usize,
    site0: [i64; 2],
    frac: &dyn Fn([f64; 2]) -> [f64; 2],
    b_len: f64,
) -> Vec<Option<[i64; 2]>> {
    let mut local: Vec<Option<[i64; 2]>> = vec![None; pts.len()];
    local[start] = Some(site0);
    let mut queue = VecDeque::from([start]);
    while let Some(p) = queue.pop_front() {
        let Some(ip) = local[p] else { continue };
        for q in 0..pts.len() {
            if local[q].is_some() {
                continue;
            }
            let d = [pts[q][0] - pts[p][0], pts[q][1] - pts[p][1]];
            if d[0].hypot(d[1]) > 1.6 * b_len {
                continue;
            }
            let f = frac(d);
            let r = [f[0].round(), f[1].round()];
            if (f[0] - r[0]).abs() < 0.35 && (f[1] - r[1]).abs() < 0.35 {
                local[q] = Some([ip[0] + r[0] as i64, ip[1] + r[1] as i64]);
                queue.push_back(q);
            }
        }
    }
    local
}
