//! The approach move's creep and the drift from a counter-scanned partner (issue 23,
//! `spmcal correct --counter FILE`): two frames of the same place, one scanned after the other
//! with the slow axis the other way, each corrected along its own raster from the file alone
//! ([`crate::dynamic::dynamic_map`]).
//!
//! What the file-alone maps leave is a function of time only, the same for both frames (the
//! lattice ruler's model, [`crate::ruler`]):
//!
//! `e(t) = A·g(t + t_m) + v·t`, `g(t) = w·Σₖ e^{−t/τₖ}`
//!
//! (`e` the corrected position minus the true one, nm; `g` the creep still to come `t` after a
//! unit step, of the calibration's own law; `t_m` the time from the end of the approach move to
//! the first frame's first pixel; `A` the move's creep amplitude; `v` the drift). A feature of
//! the sample seen at `p₁` at time `t₁` in one frame and at `p₂` at `t₂` in the other obeys
//!
//! `p₁ − p₂ = e(t₁) − e(t₂)`
//!
//! (the two file-alone maps of one place share their frame: the raster's bottom-left pixel,
//! [`crate::dynamic`]). No lattice is assumed: any feature the detector
//! finds in both frames serves (the spacing given sets only the detector's scale and the match
//! radius). Sample points
//! seen at nearly the same time in both frames (the end of the first frame is where the
//! second begins) are matched first, nearest to nearest; the model fitted on them predicts where
//! each feature seen later lies in the other frame, and the match grows through larger and
//! larger shares of the features, ordered by `|t₂ − t₁|`. `A` and `v` follow by linear least squares for each
//! `t_m` of a log-spaced ladder, the least residual kept. With `g` almost straight over the
//! pair, `A` and `v` trade off along a valley on which `e` is the same over the frames.
//!
//! Frames whose features do not match (fewer than 12 pairs; under half of the first frame's
//! features with a feature near their predicted place in the other frame; or under 75 % of
//! those matched), or whose matched features stay more than a quarter of the feature spacing
//! RMS off the model, are refused, not guessed.

use crate::ruler::{LatticeRuler, RulerEstimate, atoms};
use spm_correction::dynamics::CreepLaw;
use spm_correction::{CoordinateMap, CorrectionError};
use std::collections::HashMap;

/// Fewest matched features, as a fraction of the first frame's features well inside the second
/// frame: features of two different places match by chance at about half that rate.
const MIN_MATCHED_FRACTION: f64 = 0.75;
/// Largest RMS residual of the matched features, in feature spacings.
const MAX_RESIDUAL_FRACTION: f64 = 0.25;
/// Farthest a feature may lie from where the model predicts it in the other frame, in feature
/// spacings.
const MATCH_RADIUS_FRACTION: f64 = 0.35;
/// Shares of the first frame's features, ordered by the time between their two sightings,
/// that the match grows through.
const GROWTH: [f64; 7] = [0.1, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0];

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

/// What [`estimate_from_pair`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct PairEstimate {
    /// The approach creep and drift, referenced to the middle of the *first* frame given
    /// ([`RulerEstimate::reference_to`] moves it to another frame's middle).
    pub estimate: RulerEstimate,
    /// Features located in the first and the second frame.
    pub features: [usize; 2],
    /// Features matched between them and fitted.
    pub matched: usize,
    /// RMS of `p₁ − p₂` about its mean before the fit, nm.
    pub before_rms_nm: f64,
    /// RMS residual after it, nm.
    pub residual_rms_nm: f64,
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

/// The fitted difference model: for a `t_m` the amplitude (zero while the match grows on pairs
/// too close in time to tell it) and the drift.
#[derive(Debug, Clone, Copy)]
struct Model {
    amplitude: [f64; 2],
    drift: [f64; 2],
    since_move_s: f64,
}

impl Model {
    /// e(t₁) − e(t₂).
    fn difference(&self, law: &CreepLaw, t1: f64, t2: f64) -> [f64; 2] {
        let dg =
            law.still_to_come(t1 + self.since_move_s) - law.still_to_come(t2 + self.since_move_s);
        let dt = t1 - t2;
        [
            self.amplitude[0] * dg + self.drift[0] * dt,
            self.amplitude[1] * dg + self.drift[1] * dt,
        ]
    }
}

/// Least squares of the difference model on matched pairs `(p₁, t₁, p₂, t₂)`: with
/// `since_move_s` the full model, without it the drift alone. Returns the model and the RMS
/// residual, nm.
fn fit(
    pairs: &[([f64; 2], f64, [f64; 2], f64)],
    law: &CreepLaw,
    since_move_s: Option<f64>,
) -> Option<(Model, f64)> {
    let mut rows = Vec::with_capacity(2 * pairs.len());
    let mut rhs = Vec::with_capacity(2 * pairs.len());
    for (p1, t1, p2, t2) in pairs {
        let dt = t1 - t2;
        let (mut x, mut y) = (vec![dt, 0.0], vec![0.0, dt]);
        if let Some(tm) = since_move_s {
            let dg = law.still_to_come(t1 + tm) - law.still_to_come(t2 + tm);
            x.extend([dg, 0.0]);
            y.extend([0.0, dg]);
        }
        rows.push(x);
        rhs.push(p1[0] - p2[0]);
        rows.push(y);
        rhs.push(p1[1] - p2[1]);
    }
    let n = if since_move_s.is_some() { 4 } else { 2 };
    let f = spm_regression::least_squares(&rows, &rhs, &vec![false; n]).ok()?;
    let c = &f.coefficients;
    let amplitude = if n == 4 { [c[2], c[3]] } else { [0.0; 2] };
    Some((
        Model {
            drift: [c[0], c[1]],
            amplitude,
            since_move_s: since_move_s.unwrap_or(0.0),
        },
        f.residual_rms,
    ))
}

/// Estimates the approach creep and drift shared by the two frames of a counter-scanned pair
/// (see the module doc). `law` is the calibration's creep law; `spacing` the feature scale
/// (the detector's separation and the match radius follow from its constant).
///
/// # Errors
/// [`CorrectionError::InvalidArgument`] for frames whose features are not resolved, do not
/// match (fewer than 12, or under 75 % of the first frame's features well inside the second), or stay more than a quarter
/// spacing RMS off the fitted model; as the detection.
pub fn estimate_from_pair(
    first: PairFrame<'_>,
    second: PairFrame<'_>,
    law: &CreepLaw,
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
    let one = atoms(first.heights, first.map, first.times_s, spacing)?;
    let two = atoms(second.heights, second.map, second.times_s, spacing)?;
    let a = spacing.constant_nm;
    let radius = MATCH_RADIUS_FRACTION * a;
    let points: Vec<[f64; 2]> = two.iter().map(|x| x.p).collect();
    let cells = Cells::new(&points, a);
    // Each first-frame feature's partner with the model `m` (two passes: the partner's time
    // enters the prediction).
    let partner = |m: &Model, k: usize| -> Option<usize> {
        let (p, t) = (one[k].p, one[k].t);
        let mut j = cells.nearest(&points, p, a)?;
        for _ in 0..2 {
            let d = m.difference(law, t, two[j].t);
            j = cells.nearest(&points, [p[0] - d[0], p[1] - d[1]], radius)?;
        }
        Some(j)
    };
    let pairs_of = |m: &Model, ks: &[usize]| -> Vec<([f64; 2], f64, [f64; 2], f64)> {
        ks.iter()
            .filter_map(|&k| partner(m, k).map(|j| (one[k].p, one[k].t, two[j].p, two[j].t)))
            .collect()
    };
    // Order the first frame's features by how far in time their place was seen in the other
    // frame (its nearest feature, before any model).
    let zero = Model {
        amplitude: [0.0; 2],
        drift: [0.0; 2],
        since_move_s: 0.0,
    };
    let mut order: Vec<(usize, f64)> = (0..one.len())
        .filter_map(|k| {
            let j = cells.nearest(&points, one[k].p, a)?;
            Some((k, (two[j].t - one[k].t).abs()))
        })
        .collect();
    order.sort_by(|x, y| x.1.total_cmp(&y.1));
    let ks: Vec<usize> = order.iter().map(|o| o.0).collect();
    // The full model on a log ladder of t_m: the fit of least residual.
    let (from, to, per_decade) = (0.1_f64, 1e4_f64, 8_u32);
    let steps = ((to / from).log10() * f64::from(per_decade)).ceil() as usize;
    let ladder = |pairs: &[([f64; 2], f64, [f64; 2], f64)]| -> Option<(Model, f64)> {
        let mut best: Option<(Model, f64)> = None;
        for k in 0..=steps {
            let tm = from * 10f64.powf(k as f64 / f64::from(per_decade));
            if let Some((m, rms)) = fit(pairs, law, Some(tm))
                && best.is_none_or(|b| rms < b.1)
            {
                best = Some((m, rms));
            }
        }
        best
    };
    // The match grows from the pairs seen closest in time; each stage's model predicts the
    // next stage's partners. The drift alone until the pairs span enough time for the creep.
    let mut model = zero;
    for share in GROWTH {
        let upto = ((ks.len() as f64 * share).ceil() as usize).min(ks.len());
        let pairs = pairs_of(&model, &ks[..upto]);
        let next = if pairs.len() >= 24 {
            ladder(&pairs)
        } else if pairs.len() >= 6 {
            fit(&pairs, law, None)
        } else {
            None
        };
        if let Some((m, _)) = next {
            model = m;
        }
    }
    let mut best: Option<(Model, f64, usize)> = None;
    for _ in 0..2 {
        let base = best.map_or(model, |b| b.0);
        let pairs = pairs_of(&base, &ks);
        if pairs.len() < 12 {
            break;
        }
        best = ladder(&pairs)
            .map(|(m, rms)| (m, rms, pairs.len()))
            .or(best);
    }
    let (model, residual_rms_nm, matched) = best.ok_or_else(|| {
        CorrectionError::InvalidArgument(format!(
            "counter partner: the frames' features do not match (fewer than 12 of {} and {})",
            one.len(),
            two.len()
        ))
    })?;
    // Features whose predicted place in the other frame has no feature within a spacing (it
    // lies outside that frame, or the feature was not detected there) are not counted
    // against the match.
    let inside = ks
        .iter()
        .filter(|&&k| {
            let (p, t) = (one[k].p, one[k].t);
            let Some(mut j) = cells.nearest(&points, p, a) else {
                return false;
            };
            for _ in 0..2 {
                let d = model.difference(law, t, two[j].t);
                match cells.nearest(&points, [p[0] - d[0], p[1] - d[1]], a) {
                    Some(next) => j = next,
                    None => return false,
                }
            }
            true
        })
        .count();
    if (matched as f64) < MIN_MATCHED_FRACTION * inside as f64 {
        return Err(CorrectionError::InvalidArgument(format!(
            "counter partner: only {matched} features matched between the frames, of {inside} \
             the first frame shows well inside the second (not the same place, or moved by more \
             than the model holds)"
        )));
    }
    if residual_rms_nm > MAX_RESIDUAL_FRACTION * a {
        return Err(CorrectionError::InvalidArgument(format!(
            "counter partner: the matched features stay {residual_rms_nm:.3} nm RMS off the \
             model (more than {MAX_RESIDUAL_FRACTION} of the {a} nm spacing): the frames' \
             difference is not a function of time alone"
        )));
    }
    let before_rms_nm = {
        let pairs = pairs_of(&model, &ks);
        let n = pairs.len().max(1) as f64;
        let mean = pairs.iter().fold([0.0; 2], |m, (p1, _, p2, _)| {
            [m[0] + (p1[0] - p2[0]) / n, m[1] + (p1[1] - p2[1]) / n]
        });
        (pairs
            .iter()
            .map(|(p1, _, p2, _)| {
                (p1[0] - p2[0] - mean[0]).powi(2) + (p1[1] - p2[1] - mean[1]).powi(2)
            })
            .sum::<f64>()
            / n)
            .sqrt()
    };
    Ok(PairEstimate {
        estimate: RulerEstimate::of_time_terms(
            law,
            model.amplitude,
            model.since_move_s,
            model.drift,
            first.times_s,
        ),
        features: [one.len(), two.len()],
        matched,
        before_rms_nm,
        residual_rms_nm,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::ruler::tests::surface;
    use spm_correction::YCoordinates;

    const N: usize = 129;
    const STEP_NM: f64 = 0.02;

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

    /// One frame of a pair: `counter` scans −x lines from the top, after the direct frame
    /// (`start_s`); every pixel sees the sample displaced by `hidden`'s e(t). Heights, the
    /// file-alone map (the commanded grid, bottom row first) and the pixel times.
    fn frame(
        hidden: &RulerEstimate,
        start_s: f64,
        counter: bool,
        sample: &dyn Fn(f64, f64) -> f64,
    ) -> (Vec<f64>, CoordinateMap, Vec<f64>) {
        let line_s = 0.05;
        let dwell = line_s / N as f64;
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
                t[i] = start_s + 2.0 * line_s * line as f64 + (place as f64 + 0.5) * dwell;
                let p = [col as f64 * STEP_NM, row as f64 * STEP_NM];
                let e = hidden.error_nm(t[i]);
                x[i] = p[0];
                y[i] = p[1];
                h[i] = sample(p[0] - e[0], p[1] - e[1]);
            }
        }
        let map = CoordinateMap::new(N, N, x, YCoordinates::PerPixel(y)).unwrap();
        (h, map, t)
    }

    /// RMS over a frame's pixels of what is left of e after removing `found`'s estimate, both
    /// referenced to the frame's middle (a rigid offset is not corrected).
    fn left(times: &[f64], hidden: &RulerEstimate, found: &RulerEstimate) -> (f64, f64) {
        let mut h = hidden.clone();
        h.reference_to(times);
        let mut f = found.clone();
        f.reference_to(times);
        let n = times.len() as f64;
        let (mut before, mut after) = (0.0, 0.0);
        for &t in times {
            let (a, b) = (h.error_at_nm(t, 0.0), f.error_at_nm(t, 0.0));
            before += a[0] * a[0] + a[1] * a[1];
            after += (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2);
        }
        ((before / n).sqrt(), (after / n).sqrt())
    }

    /// A pair (direct, then counter) of a sample displaced by a hidden approach creep (2 s
    /// after the move) and drift, a tenth of the side over the pair: on a hexagonal lattice
    /// and on random blobs, the estimate must take out 90 % of e in both frames, and frames of
    /// two different places must be refused.
    #[test]
    fn a_counter_partner_finds_the_approach_creep_and_drift() {
        let law = CreepLaw::log_spaced(0.0055, 0.01, 1e4, 3).unwrap();
        let hidden = RulerEstimate::of_time_terms(&law, [-15.0, 10.0], 1.0, [0.02, -0.012], &[0.0]);
        let pair_delay_s = 2.0 * 0.05 * N as f64;
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
        for (name, sample) in [
            ("lattice", &lattice as &dyn Fn(f64, f64) -> f64),
            ("blobs", &blob_surface),
        ] {
            let (h1, m1, t1) = frame(&hidden, 0.0, false, sample);
            let (h2, m2, t2) = frame(&hidden, pair_delay_s, true, sample);
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
                &law,
                &LatticeRuler::hopg(),
            )
            .unwrap();
            for times in [&t1, &t2] {
                let (before, after) = left(times, &hidden, &found.estimate);
                assert!(before > 0.1, "{name}: the hidden e is {before} nm RMS");
                assert!(
                    after < 0.1 * before,
                    "{name}: left of e {before} → {after} nm; {found:?}"
                );
            }
            assert!(found.residual_rms_nm < 0.005, "{name}: {found:?}");
        }
        // The second frame of another place (the blobs against the lattice): refused.
        let (h1, m1, t1) = frame(&hidden, 0.0, false, &lattice);
        let (h2, m2, t2) = frame(&hidden, pair_delay_s, true, &blob_surface);
        let refused = estimate_from_pair(
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
            &law,
            &LatticeRuler::hopg(),
        );
        assert!(refused.is_err(), "{refused:?}");
    }
}
