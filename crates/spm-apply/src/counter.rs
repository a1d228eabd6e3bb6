//! The drift between two frames of a counter-scanned pair (issue 23, `spmcal correct
//! --counter FILE`): the same place scanned twice, the second frame right after the first with
//! the slow axis the other way (Lapshin's counter-scanning), each corrected along its own raster
//! from the file alone ([`crate::dynamic`]: the second replayed after the first's raster).
//!
//! What the file-alone maps leave is a function of time only, the same for both frames: the
//! creep of the approach move before the first frame and the drift, `e(t)` (the corrected
//! position minus the true one, nm). A feature of the sample seen at `p₁` at time `t₁` in the
//! first frame and at `p₂` at `t₂` in the second obeys
//!
//! `p₁ − p₂ = e(t₁) − e(t₂) + c`
//!
//! (`c` what the two maps' frames differ by). In a counter pair every sample point is seen at
//! `t₁ + t₂ ≈ 2m` (`m` the pair's middle time: the first frame's last line is the second's
//! first), so the pair sees only the part of `e` that is odd about `m`:
//! `e(m + s) − e(m − s)`. The even part (a creep's curvature, symmetric about `m`) is the same
//! in both frames and cannot be seen by comparing them. The estimate is therefore the odd
//! polynomial `e(t) = v·(t − m) + w·(t − m)³`: `v` the drift over the pair (the classic
//! counter-scanning result) and `w` how it changes; they are fitted by linear least squares
//! with `c`.
//!
//! No lattice is assumed: any feature the detector finds in both frames serves (the spacing
//! given sets the detector's scale and the match radius). On a lattice the frames' offset is
//! known only up to a lattice vector, which does not matter since `c` is not applied. The
//! match is seeded where the two frames saw the sample at nearly the same time, with the
//! displacement most of those features share (a vote). It then grows to each feature from its
//! matched neighbours in the first frame, within 2.5 spacings, whose displacements, fitted by a
//! plane, predict its own. `e` changes little from one feature to the next, however much it
//! changes over the frames.
//!
//! Frames are refused, not guessed, when:
//! - fewer than 12 pairs match;
//! - fewer than 75 % of the first frame's features that have a feature near their predicted
//!   place in the other frame are matched;
//! - the matched features stay more than a quarter of the feature spacing RMS off the model.

use crate::ruler::{Atom, LatticeRuler, atoms};
use spm_correction::{CoordinateMap, CorrectionError};
use std::collections::HashMap;

/// Fewest matched features, as a fraction of the first frame's features that have a feature
/// near their predicted place in the second: features of two different places match by chance
/// at about half that rate.
const MIN_MATCHED_FRACTION: f64 = 0.75;
/// Largest RMS residual of the matched features, in feature spacings.
const MAX_RESIDUAL_FRACTION: f64 = 0.25;
/// Farthest a feature may lie from where it is predicted in the other frame, in feature
/// spacings.
const MATCH_RADIUS_FRACTION: f64 = 0.35;
/// Most passes of the match's growth from neighbour to neighbour.
const MAX_GROWTH_PASSES: usize = 200;
/// Neighbours that predict a feature's displacement, within this many spacings.
const NEIGHBOURHOOD_FRACTION: f64 = 2.5;

/// One frame of a counter-scanned pair: heights, the file-alone map and the pixel times, in the
/// map's order; the times on the pair's one clock (the later frame's offset by its delay).
#[derive(Debug, Clone, Copy)]
pub struct PairFrame<'a> {
    /// Heights (any unit; NaN where none).
    pub heights: &'a [f64],
    /// The frame's corrected coordinates.
    pub map: &'a CoordinateMap,
    /// Pixel times, s, on the pair's clock.
    pub times_s: &'a [f64],
}

/// What [`estimate_from_pair`] found: the odd part of e about the pair's middle.
#[derive(Debug, Clone, PartialEq)]
pub struct PairEstimate {
    /// m: the pair's middle time (the mean of `t₁ + t₂` over the matches, halved), s.
    pub middle_s: f64,
    /// v: the drift over the pair, nm/s per axis.
    pub drift_nm_per_s: [f64; 2],
    /// w: its change, nm/s³ per axis (`e = v·(t − m) + w·(t − m)³`).
    pub cubic_nm_per_s3: [f64; 2],
    /// c: the second frame's map minus the first's for one sample point, beyond e (modulo a
    /// lattice vector on a lattice), nm.
    pub frame_offset_nm: [f64; 2],
    /// Features located in the first and the second frame.
    pub features: [usize; 2],
    /// Features matched between them and fitted.
    pub matched: usize,
    /// RMS of `p₁ − p₂` about its mean before the fit, nm.
    pub before_rms_nm: f64,
    /// RMS residual after it, nm.
    pub residual_rms_nm: f64,
}

impl PairEstimate {
    /// e at time `t_s`, nm.
    #[must_use]
    pub fn error_nm(&self, t_s: f64) -> [f64; 2] {
        let s = t_s - self.middle_s;
        let s3 = s * s * s;
        [
            self.drift_nm_per_s[0] * s + self.cubic_nm_per_s3[0] * s3,
            self.drift_nm_per_s[1] * s + self.cubic_nm_per_s3[1] * s3,
        ]
    }

    /// `map` with e(t) of every pixel removed (`times_s` per pixel, the map's order, on the
    /// pair's clock), less e at the frame's middle (median) time: the frame's middle stays
    /// where its map put it.
    ///
    /// # Errors
    /// [`CorrectionError::SizeMismatch`]; as [`CoordinateMap::new`].
    pub fn corrected(
        &self,
        map: &CoordinateMap,
        times_s: &[f64],
    ) -> Result<CoordinateMap, CorrectionError> {
        let mut sorted = times_s.to_vec();
        let reference = self.error_nm(spm_regression::median(&mut sorted).unwrap_or(0.0));
        crate::ruler::without_error(map, times_s, |t, _| {
            let e = self.error_nm(t);
            [e[0] - reference[0], e[1] - reference[1]]
        })
    }
}

/// Counter-frame features in cells of one feature spacing.
struct Cells {
    cell_nm: f64,
    cells: HashMap<(i64, i64), Vec<usize>>,
}

impl Cells {
    fn new(points: &[[f64; 2]], cell_nm: f64) -> Self {
        let mut cells: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
        for (k, p) in points.iter().enumerate() {
            cells.entry(Self::key(p, cell_nm)).or_default().push(k);
        }
        Self { cell_nm, cells }
    }

    fn key(p: &[f64; 2], cell_nm: f64) -> (i64, i64) {
        (
            (p[0] / cell_nm).floor() as i64,
            (p[1] / cell_nm).floor() as i64,
        )
    }

    /// The point nearest `q` within `radius_nm` (≤ one cell), when there is one.
    fn nearest(&self, points: &[[f64; 2]], q: [f64; 2], radius_nm: f64) -> Option<usize> {
        let (cx, cy) = Self::key(&q, self.cell_nm);
        let mut best: Option<(usize, f64)> = None;
        for dx in -1..=1 {
            for dy in -1..=1 {
                let Some(list) = self.cells.get(&(cx + dx, cy + dy)) else {
                    continue;
                };
                for &k in list {
                    let d2 = (points[k][0] - q[0]).powi(2) + (points[k][1] - q[1]).powi(2);
                    if d2 <= radius_nm * radius_nm && best.is_none_or(|b| d2 < b.1) {
                        best = Some((k, d2));
                    }
                }
            }
        }
        best.map(|b| b.0)
    }
}

/// The displacement `p₁ − p₂` most of the first frame's features seen closest in time (the
/// first fifth of `ks`, at least 12) share with some feature of the second frame within 2.5
/// spacings: each candidate displacement is counted by the candidates within a tenth of a
/// spacing of it; ties go to the shortest.
fn vote_offset(one: &[Atom], points: &[[f64; 2]], cells: &Cells, ks: &[usize], a: f64) -> [f64; 2] {
    let take = (ks.len() / 5).max(12).min(ks.len());
    let reach = 2.5 * a;
    let mut candidates: Vec<[f64; 2]> = Vec::new();
    for &k in &ks[..take] {
        let p = one[k].p;
        let (cx, cy) = Cells::key(&p, cells.cell_nm);
        for dx in -3..=3 {
            for dy in -3..=3 {
                for &j in cells.cells.get(&(cx + dx, cy + dy)).into_iter().flatten() {
                    let d = [p[0] - points[j][0], p[1] - points[j][1]];
                    if d[0] * d[0] + d[1] * d[1] <= reach * reach {
                        candidates.push(d);
                    }
                }
            }
        }
    }
    // Each candidate's votes: the candidates within `close` of it, counted over the 3 × 3
    // buckets of side `close` around it (not over all pairs: thousands of candidates).
    let close = 0.1 * a;
    let bucket = |d: &[f64; 2]| ((d[0] / close).floor() as i64, (d[1] / close).floor() as i64);
    let mut buckets: std::collections::HashMap<(i64, i64), Vec<usize>> =
        std::collections::HashMap::new();
    for (i, d) in candidates.iter().enumerate() {
        buckets.entry(bucket(d)).or_default().push(i);
    }
    let mut best = ([0.0; 2], 0_usize, f64::INFINITY);
    for d in &candidates {
        let (bx, by) = bucket(d);
        let mut votes = 0;
        for dx in -1..=1 {
            for dy in -1..=1 {
                for &i in buckets.get(&(bx + dx, by + dy)).into_iter().flatten() {
                    let e = candidates[i];
                    if (e[0] - d[0]).powi(2) + (e[1] - d[1]).powi(2) <= close * close {
                        votes += 1;
                    }
                }
            }
        }
        let length = d[0] * d[0] + d[1] * d[1];
        if votes > best.1 || (votes == best.1 && length < best.2) {
            best = (*d, votes, length);
        }
    }
    best.0
}

/// A matched pair: `(p₁, t₁, p₂, t₂)`.
type Matched = ([f64; 2], f64, [f64; 2], f64);

/// Least squares of `p₁ − p₂ = c + v·(s₁ − s₂) + w·(s₁³ − s₂³)`, `s = t − m`, per axis.
/// Returns `(c, v, w)` per axis and the RMS residual (both axes), nm.
fn fit(pairs: &[Matched], middle_s: f64) -> Option<([[f64; 3]; 2], f64)> {
    let rows: Vec<Vec<f64>> = pairs
        .iter()
        .map(|(_, t1, _, t2)| {
            let (s1, s2) = (t1 - middle_s, t2 - middle_s);
            vec![1.0, s1 - s2, s1.powi(3) - s2.powi(3)]
        })
        .collect();
    let mut out = [[0.0; 3]; 2];
    let mut sum_sq = 0.0;
    for axis in 0..2 {
        let rhs: Vec<f64> = pairs
            .iter()
            .map(|(p1, _, p2, _)| p1[axis] - p2[axis])
            .collect();
        let f = spm_regression::least_squares(&rows, &rhs, &[false; 3]).ok()?;
        out[axis].copy_from_slice(&f.coefficients);
        sum_sq += f.residual_rms * f.residual_rms;
    }
    Some((out, (0.5 * sum_sq).sqrt()))
}

/// The second frame's feature matched to each first-frame feature: seeded by the vote among
/// the first features of `ks` (closest in time), grown from neighbour to neighbour.
fn grow_match(
    one: &[Atom],
    points: &[[f64; 2]],
    cells: &Cells,
    ks: &[usize],
    a: f64,
) -> Vec<Option<usize>> {
    let radius = MATCH_RADIUS_FRACTION * a;
    let offset = vote_offset(one, points, cells, ks, a);
    let own_points: Vec<[f64; 2]> = one.iter().map(|x| x.p).collect();
    let own_cells = Cells::new(&own_points, a);
    let mut partner_of: Vec<Option<usize>> = vec![None; one.len()];
    let seeds = (ks.len() / 5).max(12).min(ks.len());
    for &k in &ks[..seeds] {
        let p = one[k].p;
        partner_of[k] = cells.nearest(points, [p[0] - offset[0], p[1] - offset[1]], radius);
    }
    let neighbourhood = NEIGHBOURHOOD_FRACTION * a;
    let reach = neighbourhood.div_euclid(a) as i64 + 1;
    for _pass in 0..MAX_GROWTH_PASSES {
        let mut grown = 0;
        for &k in ks {
            if partner_of[k].is_some() {
                continue;
            }
            let p = one[k].p;
            let (cx, cy) = Cells::key(&p, a);
            let (mut rows, mut rhs_x, mut rhs_y) = (Vec::new(), Vec::new(), Vec::new());
            for dx in -reach..=reach {
                for dy in -reach..=reach {
                    for &n in own_cells
                        .cells
                        .get(&(cx + dx, cy + dy))
                        .into_iter()
                        .flatten()
                    {
                        let (Some(j), q) = (partner_of[n], one[n].p) else {
                            continue;
                        };
                        if (q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2)
                            > neighbourhood * neighbourhood
                        {
                            continue;
                        }
                        rows.push(vec![1.0, q[0] - p[0], q[1] - p[1]]);
                        rhs_x.push(q[0] - points[j][0]);
                        rhs_y.push(q[1] - points[j][1]);
                    }
                }
            }
            let predicted = if rows.len() >= 6 {
                let fx = spm_regression::least_squares(&rows, &rhs_x, &[false; 3]);
                let fy = spm_regression::least_squares(&rows, &rhs_y, &[false; 3]);
                match (fx, fy) {
                    (Ok(fx), Ok(fy)) => [fx.coefficients[0], fy.coefficients[0]],
                    _ => continue,
                }
            } else if rows.len() >= 3 {
                let n = rows.len() as f64;
                [rhs_x.iter().sum::<f64>() / n, rhs_y.iter().sum::<f64>() / n]
            } else {
                continue;
            };
            if let Some(j) =
                cells.nearest(points, [p[0] - predicted[0], p[1] - predicted[1]], radius)
            {
                partner_of[k] = Some(j);
                grown += 1;
            }
        }
        if grown == 0 {
            break;
        }
    }
    partner_of
}

/// Estimates the odd part of e about the pair's middle (see the module doc). `spacing` sets the
/// feature scale (the detector's separation and the match radius follow from its constant).
///
/// # Errors
/// [`CorrectionError::InvalidArgument`] for frames whose features are not resolved, do not
/// match, or stay more than a quarter spacing RMS off the fitted model; as the detection.
pub fn estimate_from_pair(
    first: PairFrame<'_>,
    second: PairFrame<'_>,
    spacing: &LatticeRuler,
) -> Result<PairEstimate, CorrectionError> {
    for f in [&first, &second] {
        let n_px = f.map.columns() * f.map.rows();
        for (what, len) in [
            ("heights", f.heights.len()),
            ("pixel times", f.times_s.len()),
        ] {
            if len != n_px {
                return Err(CorrectionError::SizeMismatch {
                    what,
                    expected: n_px,
                    got: len,
                });
            }
        }
    }
    for f in [&first, &second] {
        let (x0, x1, _, _) = f.map.bounds_nm();
        let nm_per_px = (x1 - x0) / (f.map.columns().max(2) - 1) as f64;
        let per_feature = spacing.constant_nm / nm_per_px;
        if per_feature.is_nan() || per_feature < spacing.min_pixels_per_constant {
            return Err(CorrectionError::InvalidArgument(format!(
                "counter partner: matching features {} nm apart needs ≥ {} pixels between \
                 them; this image has {per_feature:.2} ({nm_per_px:.4} nm per pixel)",
                spacing.constant_nm, spacing.min_pixels_per_constant
            )));
        }
    }
    let one = atoms(first.heights, first.map, first.times_s, spacing)?;
    let two = atoms(second.heights, second.map, second.times_s, spacing)?;
    let a = spacing.constant_nm;
    let points: Vec<[f64; 2]> = two.iter().map(|x| x.p).collect();
    let cells = Cells::new(&points, a);
    // The first frame's features in the order of how far in time their place was seen in the
    // other frame (its nearest feature, before any match).
    let mut order: Vec<(usize, f64)> = (0..one.len())
        .filter_map(|k| {
            let j = cells.nearest(&points, one[k].p, a)?;
            Some((k, (two[j].t - one[k].t).abs()))
        })
        .collect();
    order.sort_by(|x, y| x.1.total_cmp(&y.1));
    let ks: Vec<usize> = order.iter().map(|o| o.0).collect();
    let partner_of = grow_match(&one, &points, &cells, &ks, a);
    let pairs: Vec<Matched> = partner_of
        .iter()
        .enumerate()
        .filter_map(|(k, j)| j.map(|j| (one[k].p, one[k].t, two[j].p, two[j].t)))
        .collect();
    let refuse =
        |reason: String| CorrectionError::InvalidArgument(format!("counter partner: {reason}"));
    if pairs.len() < 12 {
        return Err(refuse(format!(
            "the frames' features do not match (fewer than 12 of {} and {})",
            one.len(),
            two.len()
        )));
    }
    let middle_s =
        0.5 * pairs.iter().map(|(_, t1, _, t2)| t1 + t2).sum::<f64>() / pairs.len() as f64;
    let (coef, residual_rms_nm) = fit(&pairs, middle_s)
        .ok_or_else(|| refuse("the matched features do not determine the drift".to_owned()))?;
    // Features whose place in the other frame (where the fit puts it) has no feature within a
    // spacing lie outside that frame or were not detected there: not counted against the match.
    let predicted = |k: usize, t2: f64| -> [f64; 2] {
        let (p, s1, s2) = (one[k].p, one[k].t - middle_s, t2 - middle_s);
        let d = |axis: usize| {
            let c = coef[axis];
            c[0] + c[1] * (s1 - s2) + c[2] * (s1.powi(3) - s2.powi(3))
        };
        [p[0] - d(0), p[1] - d(1)]
    };
    let inside = ks
        .iter()
        .filter(|&&k| {
            let Some(mut j) = cells.nearest(&points, one[k].p, 2.0 * a) else {
                return false;
            };
            for _ in 0..2 {
                match cells.nearest(&points, predicted(k, two[j].t), a) {
                    Some(next) => j = next,
                    None => return false,
                }
            }
            true
        })
        .count();
    let matched = pairs.len();
    if (matched as f64) < MIN_MATCHED_FRACTION * inside as f64 {
        return Err(refuse(format!(
            "only {matched} features matched between the frames, of {inside} with a feature \
             near their place in the other frame (not the same place, or moved by more than the \
             model holds)"
        )));
    }
    if residual_rms_nm > MAX_RESIDUAL_FRACTION * a {
        return Err(refuse(format!(
            "the matched features stay {residual_rms_nm:.3} nm RMS off the model (more than \
             {MAX_RESIDUAL_FRACTION} of the {a} nm spacing): the frames' difference is not a \
             function of time alone"
        )));
    }
    let n = matched as f64;
    let mean = pairs.iter().fold([0.0; 2], |m, (p1, _, p2, _)| {
        [m[0] + (p1[0] - p2[0]) / n, m[1] + (p1[1] - p2[1]) / n]
    });
    let before_rms_nm = (pairs
        .iter()
        .map(|(p1, _, p2, _)| (p1[0] - p2[0] - mean[0]).powi(2) + (p1[1] - p2[1] - mean[1]).powi(2))
        .sum::<f64>()
        / n)
        .sqrt();
    Ok(PairEstimate {
        middle_s,
        drift_nm_per_s: [coef[0][1], coef[1][1]],
        cubic_nm_per_s3: [coef[0][2], coef[1][2]],
        frame_offset_nm: [-coef[0][0], -coef[1][0]],
        features: [one.len(), two.len()],
        matched,
        before_rms_nm,
        residual_rms_nm,
    })
}

/// A frame's file-alone map and its pixel times on the pair's clock (the map's order).
pub type MappedFrame = (CoordinateMap, Vec<f64>);

/// One file of a counter-scanned pair as [`pair_maps`] reads it: its raster and the heights of
/// its trace half (scanner geometry, bottom row first).
#[derive(Debug, Clone, Copy)]
pub struct PairFile<'a> {
    /// The file's raster (with its line time).
    pub raster: &'a crate::FileRaster,
    /// Heights of the trace half, bottom row first.
    pub heights: &'a [f64],
}

/// The estimate between the trace halves of a counter-scanned pair: the earlier frame's map
/// along its own raster (`earlier_map`, [`crate::dynamic::dynamic_map`], which the caller
/// usually has already), the later frame's replayed after the earlier one's raster,
/// `delay_s` after it ([`crate::dynamic::dynamic_map_after`]). Returns the estimate, the
/// earlier frame's pixel times and the later frame's map and times, on the pair's clock: the
/// maps before the estimate is removed ([`PairEstimate::corrected`]).
///
/// # Errors
/// As [`crate::dynamic::dynamic_map_after`], [`crate::dynamic::pixel_times`] and
/// [`estimate_from_pair`].
pub fn pair_maps<F: spm_correction::CorrectionField + ?Sized>(
    field: &F,
    dynamics: &spm_correction::hysteresis::ScannerDynamics,
    (earlier, earlier_map): (PairFile<'_>, &CoordinateMap),
    later: PairFile<'_>,
    delay_s: f64,
    spacing: &LatticeRuler,
) -> Result<(PairEstimate, Vec<f64>, MappedFrame), CorrectionError> {
    use crate::dynamic::{Half, dynamic_map_after, pixel_times};
    let (second_map, _) = dynamic_map_after(
        field,
        later.raster,
        dynamics,
        Half::Trace,
        earlier.raster,
        delay_s,
    )?;
    let first_times = pixel_times(earlier.raster, Half::Trace)?;
    let second_times: Vec<f64> = pixel_times(later.raster, Half::Trace)?
        .iter()
        .map(|t| t + delay_s)
        .collect();
    let found = estimate_from_pair(
        PairFrame {
            heights: earlier.heights,
            map: earlier_map,
            times_s: &first_times,
        },
        PairFrame {
            heights: later.heights,
            map: &second_map,
            times_s: &second_times,
        },
        spacing,
    )?;
    Ok((found, first_times, (second_map, second_times)))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::ruler::tests::surface;
    use spm_correction::YCoordinates;
    use spm_correction::dynamics::CreepLaw;

    const N: usize = 129;
    const STEP_NM: f64 = 0.02;
    const LINE_S: f64 = 0.05;

    /// Random Gaussian blobs (no lattice), 150 over 3.4 × 3.4 nm, from a fixed stream.
    fn blobs() -> Vec<[f64; 2]> {
        let mut s = 0x9E37_79B9_7F4A_7C15_u64;
        let mut next = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut out: Vec<[f64; 2]> = Vec::new();
        while out.len() < 150 {
            let p = [-0.4 + 3.4 * next(), -0.4 + 3.4 * next()];
            if out.iter().all(|q| (q[0] - p[0]).hypot(q[1] - p[1]) > 0.2) {
                out.push(p);
            }
        }
        out
    }

    /// One frame of a pair: `counter` scans −x lines from the top, right after the direct frame
    /// (`start_s`); every pixel sees the sample displaced by `e(t)`. Heights, the file-alone map
    /// (the commanded grid, bottom row first) and the pixel times.
    fn frame(
        e: &dyn Fn(f64) -> [f64; 2],
        start_s: f64,
        counter: bool,
        sample: &dyn Fn(f64, f64) -> f64,
    ) -> (Vec<f64>, CoordinateMap, Vec<f64>) {
        let dwell = LINE_S / N as f64;
        let (mut h, mut t, mut x, mut y) = (
            vec![0.0; N * N],
            vec![0.0; N * N],
            vec![0.0; N * N],
            vec![0.0; N * N],
        );
        for row in 0..N {
            for col in 0..N {
                let i = row * N + col;
                let (line, place) = if counter {
                    (N - 1 - row, N - 1 - col)
                } else {
                    (row, col)
                };
                t[i] = start_s + 2.0 * LINE_S * line as f64 + (place as f64 + 0.5) * dwell;
                let p = [col as f64 * STEP_NM, row as f64 * STEP_NM];
                let d = e(t[i]);
                x[i] = p[0];
                y[i] = p[1];
                h[i] = sample(p[0] - d[0], p[1] - d[1]);
            }
        }
        let map = CoordinateMap::new(N, N, x, YCoordinates::PerPixel(y)).unwrap();
        (h, map, t)
    }

    /// RMS over a frame's pixels of `truth` and of what the estimate leaves of it, both taken
    /// relative to the frame's middle time.
    fn left(times: &[f64], truth: &dyn Fn(f64) -> [f64; 2], found: &PairEstimate) -> (f64, f64) {
        let mut sorted = times.to_vec();
        let mid = spm_regression::median(&mut sorted).unwrap();
        let (t0, f0) = (truth(mid), found.error_nm(mid));
        let n = times.len() as f64;
        let (mut before, mut after) = (0.0, 0.0);
        for &t in times {
            let (a, b) = (truth(t), found.error_nm(t));
            let a = [a[0] - t0[0], a[1] - t0[1]];
            let b = [b[0] - f0[0], b[1] - f0[1]];
            before += a[0] * a[0] + a[1] * a[1];
            after += (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2);
        }
        ((before / n).sqrt(), (after / n).sqrt())
    }

    /// A pair (direct, then counter) of a sample displaced by a hidden approach creep (1 s after
    /// the move) and drift, a tenth of the side over the pair, on a hexagonal lattice and on
    /// random blobs. The pair sees only the part of e odd about its middle: the estimate must
    /// leave under 10 % of that part in both frames, and recover a pure drift to 1 %. Frames of
    /// two different places are refused.
    #[test]
    fn a_counter_partner_finds_the_odd_part_of_the_approach_creep_and_drift() {
        let law = CreepLaw::log_spaced(0.0055, 0.01, 1e4, 3).unwrap();
        let (amplitude, since_move_s, drift) = ([-15.0, 10.0], 1.0, [0.02, -0.012]);
        let hidden = |t: f64| -> [f64; 2] {
            let g = law.still_to_come(t + since_move_s);
            [
                amplitude[0] * g + drift[0] * t,
                amplitude[1] * g + drift[1] * t,
            ]
        };
        let delay_s = 2.0 * LINE_S * N as f64;
        // The pair's middle: the first frame's end, the second's start.
        let odd = |t: f64| -> [f64; 2] {
            let (a, b) = (hidden(t), hidden(2.0 * delay_s - t));
            [0.5 * (a[0] - b[0]), 0.5 * (a[1] - b[1])]
        };
        let spots = blobs();
        let blob_surface = |x: f64, y: f64| -> f64 {
            spots
                .iter()
                .map(|p| {
                    (-((x - p[0]).powi(2) + (y - p[1]).powi(2)) / (2.0 * 0.045f64.powi(2))).exp()
                })
                .sum()
        };
        let lattice = |x: f64, y: f64| surface(x, y, 0.3);
        let estimate = |e: &dyn Fn(f64) -> [f64; 2],
                        one: &dyn Fn(f64, f64) -> f64,
                        two: &dyn Fn(f64, f64) -> f64| {
            let (h1, m1, t1) = frame(e, 0.0, false, one);
            let (h2, m2, t2) = frame(e, delay_s, true, two);
            let found = estimate_from_pair(
                PairFrame {
                    heights: &h1,
                    map: &m1,
                    times_s: &t1,
                },
                PairFrame {
                    heights: &h2,
                    map: &m2,
                    times_s: &t2,
                },
                &LatticeRuler::hopg(),
            );
            (found, t1, t2)
        };
        for (name, sample) in [
            ("lattice", &lattice as &dyn Fn(f64, f64) -> f64),
            ("blobs", &blob_surface),
        ] {
            let (found, t1, t2) = estimate(&hidden, sample, sample);
            let found = found.unwrap();
            assert!(found.residual_rms_nm < 0.005, "{name}: {found:?}");
            for times in [&t1, &t2] {
                let (before, after) = left(times, &odd, &found);
                assert!(before > 0.1, "{name}: the odd part of e is {before} nm RMS");
                assert!(
                    after < 0.1 * before,
                    "{name}: left of the odd part {before} → {after} nm; {found:?}"
                );
            }
            // A drift alone is odd about any time: recovered to 1 %.
            let pure = |t: f64| [drift[0] * t, drift[1] * t];
            let (found, _, _) = estimate(&pure, sample, sample);
            let v = found.unwrap().drift_nm_per_s;
            for axis in 0..2 {
                assert!(
                    (v[axis] / drift[axis] - 1.0).abs() < 0.01,
                    "{name}: drift {v:?}, hidden {drift:?}"
                );
            }
        }
        // The second frame of another place (the blobs against the lattice): refused.
        let (refused, _, _) = estimate(&hidden, &lattice, &blob_surface);
        assert!(refused.is_err(), "{refused:?}");
    }
}
