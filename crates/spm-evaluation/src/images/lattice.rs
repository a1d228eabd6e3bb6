//! The lattice of a corrected counter-scanned pair: atoms detected on the raw images, matched
//! across the pair in the corrected frame, the drift between the sightings estimated, the
//! direct image moved to a common time, resampled onto a uniform nm grid, and its three
//! lattice vectors measured.

use super::neighbours::Grid;
use spm_correction::{
    CoordinateMap, FeatureMatch, FeatureSighting, Interpolation, OutputGrid, Parallelism,
    SightingPair, drift_corrected_map, resample,
};
use spm_features::{DetectionConfig, Feature, LatticeConfig, detect, lattice_vectors};
use spm_hal::{CountPoint, Counts, HeightMap, NmPoint, NmVelocity, Seconds};
use spm_regression::{least_squares, median};

/// The drift between the sightings of a pair: displacement `d(t) = v·(t − t₀) +
/// ½·α·(t − t₀)²` per axis (α = 0 unless asked for), so counter − direct position =
/// a + d(t_counter) − d(t_direct), least squares with the offset `a`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct PairDrift {
    /// v, nm/s.
    velocity: NmVelocity,
    /// α per axis, nm/s².
    acceleration_nm_per_s2: [f64; 2],
    /// t₀, s.
    t0_s: f64,
}

impl PairDrift {
    /// The acceleration's part of d(t) − d(t_ref) per axis, nm: ½·α·((t − t₀)² − (t_ref − t₀)²).
    fn accelerated_nm(&self, t_s: f64, t_ref_s: f64) -> [f64; 2] {
        let (u, r) = (t_s - self.t0_s, t_ref_s - self.t0_s);
        self.acceleration_nm_per_s2
            .map(|a| 0.5 * a * (u * u - r * r))
    }
}

/// [`PairDrift`] of the sightings and the RMS residual (nm).
fn drift_with_offset(pairs: &[SightingPair], accelerating: bool) -> Option<(PairDrift, f64)> {
    let unknowns = if accelerating { 3 } else { 2 };
    if pairs.len() < unknowns + 1 {
        return None;
    }
    let t0_s = pairs
        .iter()
        .map(|p| 0.5 * (p.counter.time.value() + p.direct.time.value()))
        .sum::<f64>()
        / pairs.len() as f64;
    let rows: Vec<Vec<f64>> = pairs
        .iter()
        .map(|p| {
            let (tc, td) = (p.counter.time.value() - t0_s, p.direct.time.value() - t0_s);
            let mut row = vec![1.0, tc - td];
            if accelerating {
                row.push(0.5 * (tc * tc - td * td));
            }
            row
        })
        .collect();
    let mut coefficients = [[0.0; 3]; 2];
    let mut ss = 0.0;
    for (k, c) in coefficients.iter_mut().enumerate() {
        let rhs: Vec<f64> = pairs
            .iter()
            .map(|p| {
                let (c, d) = (p.counter.position, p.direct.position);
                if k == 0 {
                    c.x.value() - d.x.value()
                } else {
                    c.y.value() - d.y.value()
                }
            })
            .collect();
        let fit = least_squares(&rows, &rhs, &vec![false; unknowns]).ok()?;
        c[..unknowns].copy_from_slice(&fit.coefficients);
        ss += fit.residual_rms * fit.residual_rms;
    }
    Some((
        PairDrift {
            velocity: NmVelocity {
                x_nm_per_s: coefficients[0][1],
                y_nm_per_s: coefficients[1][1],
            },
            acceleration_nm_per_s2: [coefficients[0][2], coefficients[1][2]],
            t0_s,
        },
        ss.sqrt(),
    ))
}

/// Atoms detected on a height map whose lattice period is `period_px` pixels (none when the
/// detection fails).
pub(crate) fn atoms(map: &HeightMap, period_px: f64) -> Vec<Feature> {
    let config = DetectionConfig {
        min_separation_px: 0.5 * period_px,
        ..DetectionConfig::default()
    };
    detect(map, &config).map(|d| d.features).unwrap_or_default()
}

/// Mutual nearest neighbours between the direct features `subset` (positions shifted by
/// `offset(i)`) and every counter feature (binned in `counter_grid`, cells of `max`),
/// closer than `max`.
fn mutual_matches(
    direct: &[[f64; 2]],
    counter: &[[f64; 2]],
    counter_grid: &Grid,
    subset: &[usize],
    max: f64,
    offset: impl Fn(usize) -> [f64; 2],
) -> Vec<(usize, usize)> {
    let shifted: Vec<[f64; 2]> = subset
        .iter()
        .map(|&i| {
            let o = offset(i);
            [direct[i][0] + o[0], direct[i][1] + o[1]]
        })
        .collect();
    // Only neighbours within `max` count: a grid of `max`-sized cells finds them.
    let shifted_grid = Grid::new(&shifted, max);
    let mut out = Vec::new();
    for (k, p) in shifted.iter().enumerate() {
        let Some((j, distance)) = counter_grid.nearest_within_a_cell(*p, counter) else {
            continue;
        };
        if distance <= max
            && shifted_grid
                .nearest_within_a_cell(counter[j], &shifted)
                .map(|(m, _)| m)
                == Some(k)
        {
            out.push((subset[k], j));
        }
    }
    out
}

/// Atoms common to a counter-scanned pair. The two sightings of an atom are apart by the
/// drift (and creep) over the time between them, which runs from about zero (the last
/// direct line, the first counter line) to twice the image time: far more than a lattice
/// period in a slow image. So the match grows from the rows seen close in time: first the
/// few atoms with the shortest time apart, matched within `max`; their offsets give an
/// apparent offset and velocity; then ever more atoms matched at the positions those
/// predict, the fit renewed at every stage. Positions are the features' corrected
/// coordinates in the two images' common frame (`frame`: the direct and the counter map; nm,
/// `max` in nm too), where a good correction leaves only the drift between the sightings.
pub fn match_features(
    direct: &[Feature],
    counter: &[Feature],
    direct_map: &HeightMap,
    counter_map: &HeightMap,
    max: f64,
    frame: (&CoordinateMap, &CoordinateMap),
) -> Vec<FeatureMatch> {
    let (nx, ny) = (direct_map.columns, direct_map.rows);
    let position = |f: &Feature, map: &CoordinateMap| -> Option<[f64; 2]> {
        map.interpolate(f.column, f.row)
            .map(|p| [p.x.value(), p.y.value()])
    };
    // Features without a position in the frame are left out (kept indices).
    let keep_d: Vec<usize> = (0..direct.len())
        .filter(|&i| position(&direct[i], frame.0).is_some())
        .collect();
    let keep_c: Vec<usize> = (0..counter.len())
        .filter(|&j| position(&counter[j], frame.1).is_some())
        .collect();
    let pd: Vec<[f64; 2]> = keep_d
        .iter()
        .filter_map(|&i| position(&direct[i], frame.0))
        .collect();
    let pc: Vec<[f64; 2]> = keep_c
        .iter()
        .filter_map(|&j| position(&counter[j], frame.1))
        .collect();
    let time_apart = |i: usize| -> f64 {
        let f = &direct[keep_d[i]];
        let c = (f.column.round().max(0.0) as usize).min(nx.saturating_sub(1));
        let r = (f.row.round().max(0.0) as usize).min(ny.saturating_sub(1));
        let k = r * nx + c;
        match (counter_map.time_s.get(k), direct_map.time_s.get(k)) {
            (Some(tc), Some(td)) => tc - td,
            _ => f64::NAN,
        }
    };
    let mut order: Vec<usize> = (0..pd.len())
        .filter(|&i| time_apart(i).is_finite())
        .collect();
    order.sort_by(|&a, &b| time_apart(a).abs().total_cmp(&time_apart(b).abs()));
    // offset(Δt) = a + v·Δt per axis, least squares over the matched pairs; when their times
    // apart do not determine v (all alike), the mean offset.
    let fit = |pairs: &[(usize, usize)]| -> Option<[[f64; 2]; 2]> {
        if pairs.len() < 4 {
            return None;
        }
        let rows: Vec<Vec<f64>> = pairs
            .iter()
            .map(|&(i, _)| vec![1.0, time_apart(i)])
            .collect();
        let axis = |k: usize| -> [f64; 2] {
            let rhs: Vec<f64> = pairs.iter().map(|&(i, j)| pc[j][k] - pd[i][k]).collect();
            match least_squares(&rows, &rhs, &[false, false]).map(|f| f.coefficients) {
                Ok(c) if c.len() == 2 => [c[0], c[1]],
                _ => [rhs.iter().sum::<f64>() / rhs.len() as f64, 0.0],
            }
        };
        let ([ax, vx], [ay, vy]) = (axis(0), axis(1));
        Some([[ax, ay], [vx, vy]])
    };
    // The apparent offset to start from, by a vote: the displacement from each of the atoms
    // seen closest in time to its nearest counter atom is a candidate, and the shortest of
    // those that match nearly the most of these atoms wins (then the median of what it
    // matched). Two
    // corrections that each took out the drift from their own image's start (the lattice
    // ruler) leave the pair apart by up to several lattice constants; a periodic lattice shows
    // that offset only modulo a lattice vector, which is all the lattice measurement needs (a
    // constant offset moves no atom against another). The median of each atom's nearest
    // displacement alone fails when the offset lies near half a lattice vector: the nearest
    // atom is then one of two, and the medians of x and y mix them.
    let mut model = [[0.0_f64; 2]; 2];
    let counter_grid = Grid::new(&pc, max);
    {
        let take = (order.len() / 25).max(6).min(order.len());
        let early = &order[..take];
        let candidates: Vec<[f64; 2]> = early
            .iter()
            .filter_map(|&i| {
                counter_grid
                    .nearest(pd[i], &pc)
                    .map(|(j, _)| [pc[j][0] - pd[i][0], pc[j][1] - pd[i][1]])
            })
            .collect();
        let voted: Vec<(f64, Vec<(usize, usize)>)> = candidates
            .iter()
            .map(|c| {
                (
                    c[0].hypot(c[1]),
                    mutual_matches(&pd, &pc, &counter_grid, early, max, |_| *c),
                )
            })
            .collect();
        // Offsets a lattice vector apart match alike but for the atoms they push out of the
        // frame: of those matching at least 80 % as many as the best, the shortest.
        let most = voted.iter().map(|v| v.1.len()).max().unwrap_or(0);
        let best = voted
            .into_iter()
            .filter(|v| 5 * v.1.len() >= 4 * most)
            .min_by(|a, b| a.0.total_cmp(&b.0));
        if let Some((_, matched)) = best {
            let mut dx: Vec<f64> = matched.iter().map(|&(i, j)| pc[j][0] - pd[i][0]).collect();
            let mut dy: Vec<f64> = matched.iter().map(|&(i, j)| pc[j][1] - pd[i][1]).collect();
            if let (Some(mx), Some(my)) = (median(&mut dx), median(&mut dy)) {
                model[0] = [mx, my];
            }
        }
    }
    let mut pairs = Vec::new();
    // Stages of 4 %, 6 %, 9 %, … of the atoms (at least 6), then all of them, twice: each
    // stage's prediction errs by the velocity error times its longer time apart.
    let mut fraction = 0.04_f64;
    for _ in 0..12 {
        let take = ((order.len() as f64 * fraction.min(1.0)).ceil() as usize)
            .max(6)
            .min(order.len());
        fraction *= 1.5;
        pairs = mutual_matches(&pd, &pc, &counter_grid, &order[..take], max, |i| {
            let t = time_apart(i);
            [model[0][0] + model[1][0] * t, model[0][1] + model[1][1] * t]
        });
        if let Some(m) = fit(&pairs) {
            model = m;
        }
    }
    let pairs: Vec<(usize, usize)> = pairs
        .into_iter()
        .map(|(i, j)| (keep_d[i], keep_c[j]))
        .collect();
    pairs
        .into_iter()
        .map(|(i, j)| FeatureMatch {
            direct_column: direct[i].column,
            direct_row: direct[i].row,
            counter_column: counter[j].column,
            counter_row: counter[j].row,
        })
        .collect()
}

/// Largest RMS residual of a pair's matched atoms about their fitted drift, in lattice
/// constants, for a lattice to be measured.
const MATCH_RESIDUAL_LIMIT: f64 = 0.25;

/// The range of measured ÷ nominal lattice constant [`measure_lattice`] reports; outside it
/// the atom detection, tuned to the nominal period, has failed.
const MEASURABLE_PERIOD_RATIO: (f64, f64) = (2.0 / 3.0, 1.5);

/// Lattice constant (nm) and largest angle deviation from 60° (degrees) on the direct image of
/// a pair, given both images' corrected coordinate maps (scanner geometry): the atoms common
/// to both give the drift (`estimate_drift`), the direct map is moved to a common time, the
/// image resampled onto a uniform nm grid and the lattice measured on it. `None` when the
/// pipeline cannot measure.
pub fn measure_lattice(
    direct_coordinates: &CoordinateMap,
    counter_coordinates: &CoordinateMap,
    direct: &HeightMap,
    counter: &HeightMap,
    raw_atoms: (&[Feature], &[Feature]),
    lattice_constant_nm: f64,
) -> Option<(f64, f64)> {
    let matches = match_features(
        raw_atoms.0,
        raw_atoms.1,
        direct,
        counter,
        0.3 * lattice_constant_nm,
        (direct_coordinates, counter_coordinates),
    );
    if matches.len() < 6 {
        return None;
    }
    let (nx, ny) = (direct.columns, direct.rows);
    let time_at = |times: &[f64], c: f64, r: f64| -> f64 {
        let i = (c.round().max(0.0) as usize).min(nx - 1);
        let j = (r.round().max(0.0) as usize).min(ny - 1);
        times[j * nx + i]
    };
    let mut pairs = Vec::with_capacity(matches.len());
    for m in &matches {
        let pd = direct_coordinates.interpolate(m.direct_column, m.direct_row)?;
        let pc = counter_coordinates.interpolate(m.counter_column, m.counter_row)?;
        pairs.push(SightingPair {
            direct: FeatureSighting {
                position: pd,
                time: Seconds(time_at(&direct.time_s, m.direct_column, m.direct_row)),
            },
            counter: FeatureSighting {
                position: pc,
                time: Seconds(time_at(&counter.time_s, m.counter_column, m.counter_row)),
            },
        });
    }
    // The drift between the sightings, with a constant offset between the two images: two
    // corrections that each took out the drift from their own image's start (the lattice
    // ruler) are apart by the drift over the direct image; a constant offset moves no atom
    // against another, so it does not enter the lattice (the velocity alone moves the map).
    // Matched atoms that a drift cannot explain to a quarter of a lattice constant RMS are a
    // failed match (or an image too distorted to match), not a lattice measurement: the match
    // accepts atoms within 0.3 a, a wrong one is at least 0.7 a off, and a right match still
    // carries both corrections' own position errors (0.05 nm RMS on the default job's slow
    // 512-count pairs, whose bound a fifth, 0.049 nm, refused). A constant drift first; a
    // pair taken over tens of seconds (slow dwells) sees the drift's warm-up and the
    // approach's creep change it, and gets a constant acceleration too.
    let explained = |fit: Option<(PairDrift, f64)>| {
        fit.filter(|(_, rms)| !rms.is_nan() && *rms <= MATCH_RESIDUAL_LIMIT * lattice_constant_nm)
    };
    let (drift, _) = explained(drift_with_offset(&pairs, false))
        .or_else(|| explained(drift_with_offset(&pairs, true)))?;
    let t_ref = Seconds(direct.time_s[direct.time_s.len() / 2]);
    let moved =
        drift_corrected_map(direct_coordinates, &direct.time_s, drift.velocity, t_ref).ok()?;
    let moved = if drift.acceleration_nm_per_s2 == [0.0, 0.0] {
        moved
    } else {
        let (nc, nr) = (moved.columns(), moved.rows());
        let mut x = Vec::with_capacity(nc * nr);
        let mut y = Vec::with_capacity(nc * nr);
        for (k, &t) in direct.time_s.iter().enumerate() {
            // The velocity's part was moved already; the acceleration's is left.
            let q = drift.accelerated_nm(t, t_ref.value());
            let p = moved.point(k % nc, k / nc)?;
            x.push(p.x.value() - q[0]);
            y.push(p.y.value() - q[1]);
        }
        CoordinateMap::new(nc, nr, x, spm_correction::YCoordinates::PerPixel(y)).ok()?
    };
    // On the whole frame first; a slow frame's first lines can be smeared by the creep of the
    // approach (atoms merged into streaks the resampling cannot undo), so the frame from a
    // third of its lines on is tried next, then its last third: the lattice is the same
    // everywhere. (On the default job's slow 512-count pair 27, 53 s an image, the atoms from
    // a third on still gave one dominant row direction of 0.29 nm and no triangle.)
    lattice_in_frame(&moved, direct, lattice_constant_nm)
}

/// The lattice of a corrected frame: on the whole frame, else from a third of its lines on,
/// else on its last third (see [`measure_lattice`]).
fn lattice_in_frame(
    moved: &CoordinateMap,
    direct: &HeightMap,
    lattice_constant_nm: f64,
) -> Option<(f64, f64)> {
    lattice_in_rows(moved, direct, lattice_constant_nm, 0)
        .or_else(|| lattice_in_rows(moved, direct, lattice_constant_nm, moved.rows() / 3))
        .or_else(|| lattice_in_rows(moved, direct, lattice_constant_nm, 2 * moved.rows() / 3))
}

/// [`measure_lattice`]'s measurement on the drift-moved direct map `moved`, inside its rows
/// from `first_row` (acquisition order of a direct raster) on.
fn lattice_in_rows(
    moved: &CoordinateMap,
    direct: &HeightMap,
    lattice_constant_nm: f64,
    first_row: usize,
) -> Option<(f64, f64)> {
    // The largest axis-aligned rectangle inside the corrected (sheared, drift-moved) image:
    // inside its left and right columns and its first and last rows.
    let m = moved;
    let (nc, nr) = (m.columns(), m.rows());
    let (mut x0, mut x1, mut y0, mut y1) = (
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
    );
    if first_row + 2 > nr {
        return None;
    }
    for r in first_row..nr {
        x0 = x0.max(m.point(0, r)?.x.value());
        x1 = x1.min(m.point(nc - 1, r)?.x.value());
    }
    for c in 0..nc {
        y0 = y0.max(m.point(c, first_row)?.y.value());
        y1 = y1.min(m.point(c, nr - 1)?.y.value());
    }
    if !(x1 > x0 && y1 > y0) {
        return None;
    }
    let (bx0, bx1, by0, by1) = m.bounds_nm();
    let pixels = (direct.columns.max(2) - 1) as f64;
    let step = ((bx1 - bx0) + (by1 - by0)) / 2.0 / pixels;
    let margin = 0.03 * (x1 - x0).min(y1 - y0);
    let side = (x1 - x0).min(y1 - y0) - 2.0 * margin;
    let n = (side / step).floor() as usize;
    if n < 8 {
        return None;
    }
    let grid = OutputGrid::new(
        NmPoint::from_nm(x0 + margin, y0 + margin),
        spm_hal::Nanometres(step),
        n,
        n,
    )
    .ok()?;
    let image = resample(
        &direct.z_counts,
        moved,
        &grid,
        Interpolation::Bilinear,
        Parallelism::Sequential,
    )
    .ok()?;
    if !image.iter().all(|v| v.is_finite()) {
        return None;
    }
    let map = HeightMap {
        origin: CountPoint::from_counts(0.0, 0.0),
        pixel_step: Counts(1.0),
        columns: n,
        rows: n,
        z_counts: image,
        time_s: vec![0.0; n * n],
    };
    let found = atoms(&map, lattice_constant_nm / step);
    let lattice = lattice_vectors(&found, &LatticeConfig::default()).ok()?;
    if lattice.vectors.len() < 3 {
        return None;
    }
    let v: Vec<[f64; 2]> = lattice
        .vectors
        .iter()
        .take(3)
        .map(|l| [l.vector.x.value() * step, l.vector.y.value() * step])
        .collect();
    let a = v.iter().map(|p| p[0].hypot(p[1])).sum::<f64>() / 3.0;
    // Three directions of one triangular lattice: lengths within a quarter of their mean.
    // Anything else is a second-neighbour or spurious vector, not a measurement.
    if v.iter().any(|p| (p[0].hypot(p[1]) / a - 1.0).abs() > 0.25) {
        return None;
    }
    // The atoms were located for the standard's period: a lattice outside ⅔ … 3/2 of it is
    // outside what that detection can measure (a superlattice of the atoms it kept, as in one
    // slow pair of the default job that read +256 % where its positions were 0.4 % off).
    if !(a > MEASURABLE_PERIOD_RATIO.0 * lattice_constant_nm
        && a < MEASURABLE_PERIOD_RATIO.1 * lattice_constant_nm)
    {
        return None;
    }
    let mut worst: f64 = 0.0;
    for i in 0..3 {
        for j in (i + 1)..3 {
            let cos = (v[i][0] * v[j][0] + v[i][1] * v[j][1])
                / (v[i][0].hypot(v[i][1]) * v[j][0].hypot(v[j][1]));
            let angle = cos.clamp(-1.0, 1.0).acos().to_degrees();
            // Directions are unoriented: 60° and 120° are the same pair of lines.
            let dev = (angle - 60.0).abs().min((angle - 120.0).abs());
            worst = worst.max(dev);
        }
    }
    // A triangular lattice's three directions are 60° apart; one further off than 15° is a
    // spurious vector (a failed resampling or match), not a distorted lattice.
    (worst <= 15.0).then_some((a, worst))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// Sightings of a pair taken while the drift warms up (d = v·t + ½·α·t², hidden): the
    /// constant-velocity model leaves them more than a quarter of a lattice constant off, the
    /// accelerating one recovers v and α and explains them exactly.
    #[test]
    fn a_warming_drift_is_explained_with_an_acceleration() {
        let (v, alpha) = ([0.012, -0.008], [0.015, 0.01]);
        let d = |t: f64| [0, 1].map(|k| v[k] * t + 0.5 * alpha[k] * t * t);
        let pairs: Vec<SightingPair> = (0..40)
            .map(|i| {
                let (x, y) = (f64::from(i % 8) * 0.25, f64::from(i / 8) * 0.22);
                let td = f64::from(i) * 0.3;
                let tc = 40.0 - 0.6 * td;
                let at = |t: f64| {
                    let s = d(t);
                    FeatureSighting {
                        position: NmPoint::from_nm(x + s[0] + 0.7, y + s[1] - 0.3),
                        time: Seconds(t),
                    }
                };
                SightingPair {
                    direct: at(td),
                    counter: at(tc),
                }
            })
            .collect();
        let (_, constant_rms) = drift_with_offset(&pairs, false).unwrap();
        assert!(
            constant_rms > MATCH_RESIDUAL_LIMIT * 0.246,
            "{constant_rms}"
        );
        let (drift, rms) = drift_with_offset(&pairs, true).unwrap();
        assert!(rms < 1e-9, "{rms}");
        for (k, want_alpha) in alpha.iter().enumerate() {
            assert!((drift.acceleration_nm_per_s2[k] - want_alpha).abs() < 1e-9);
            let want = d(17.0)[k] - d(4.0)[k];
            let v = [drift.velocity.x_nm_per_s, drift.velocity.y_nm_per_s][k];
            let got = v * (17.0 - 4.0) + drift.accelerated_nm(17.0, 4.0)[k];
            assert!((got - want).abs() < 1e-9);
        }
    }
}
