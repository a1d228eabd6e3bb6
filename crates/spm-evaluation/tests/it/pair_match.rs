//! The atoms of a counter-scanned pair are matched across it (`spm_evaluation::images::
//! match_features`), against the closed form that placed them, and on pairs of the image
//! benchmark that the matcher once left unmatched.
//!
//! A lattice shows the pair's offset only modulo a lattice vector, so a right match is one
//! branch: every atom paired with the second sighting of the atom one and the same lattice
//! vector from it, the pairs agreeing with one drift.
#![allow(clippy::unwrap_used)]

use spm_correction::{CoordinateMap, YCoordinates};
use spm_evaluation::images::match_features;
use spm_features::{Feature, FeatureQuality, Polarity, PositionUncertainty};
use spm_hal::{CountPoint, Counts, HeightMap, Seconds};

const PIXELS: usize = 129;
const STEP_NM: f64 = 0.04;
const LINE_S: f64 = 0.1;
const A_NM: f64 = 0.246;

/// The frame's pixel map: column and row times the step, nm.
fn frame() -> CoordinateMap {
    let n = PIXELS;
    CoordinateMap::new(
        n,
        n,
        (0..n * n).map(|i| (i % n) as f64 * STEP_NM).collect(),
        YCoordinates::PerPixel((0..n * n).map(|i| (i / n) as f64 * STEP_NM).collect()),
    )
    .unwrap()
}

/// A height map carrying only the pixel times of `time(row)` (the matcher reads times).
fn times(time: &dyn Fn(usize) -> f64) -> HeightMap {
    let n = PIXELS;
    HeightMap {
        origin: CountPoint::from_counts(0.0, 0.0),
        pixel_step: Counts(1.0),
        columns: n,
        rows: n,
        z_counts: vec![0.0; n * n],
        time_s: (0..n * n).map(|i| time(i / n)).collect(),
    }
}

fn feature(p: [f64; 2], t: f64) -> Feature {
    Feature {
        position: CountPoint::from_counts(p[0] / STEP_NM, p[1] / STEP_NM),
        column: p[0] / STEP_NM,
        row: p[1] / STEP_NM,
        time: Seconds(t),
        polarity: Polarity::Hill,
        amplitude_z_counts: 1.0,
        width: Counts(1.0),
        background_z_counts: 0.0,
        quality: FeatureQuality {
            snr: 50.0,
            shape_r2: 1.0,
            border_distance_px: 10.0,
            score: 1.0,
        },
        uncertainty: PositionUncertainty::default(),
    }
}

/// One case: the frame's side (nm), the lattice's angle (rad), the pair's offset at Δt₀ in the
/// basis (b₁, b₂), and the direction (rad) of the drift.
fn check(side_nm: f64, angle: f64, offset: [f64; 2], drift_direction: f64) {
    let (s, c) = angle.sin_cos();
    let b1 = [A_NM * c, A_NM * s];
    let b2 = [
        A_NM * (0.5 * c - 0.75f64.sqrt() * s),
        A_NM * (0.5 * s + 0.75f64.sqrt() * c),
    ];
    let side = side_nm.min(STEP_NM * (PIXELS - 1) as f64);
    let direct_time = |row: usize| row as f64 * LINE_S;
    // Scanned the other way along the slow axis, right after the direct image.
    let counter_time = |row: usize| (2 * PIXELS - 1 - row) as f64 * LINE_S;
    let inside = |p: [f64; 2]| p[0] > 0.1 && p[0] < side - 0.1 && p[1] > 0.1 && p[1] < side - 0.1;
    let row_of = |p: [f64; 2]| (p[1] / STEP_NM).round().clamp(0.0, (PIXELS - 1) as f64) as usize;
    let dt_of = |p: [f64; 2]| counter_time(row_of(p)) - direct_time(row_of(p));
    let mut sites = Vec::new();
    for n1 in -40..40 {
        for n2 in -40..40 {
            let p = [
                f64::from(n1) * b1[0] + f64::from(n2) * b2[0],
                f64::from(n1) * b1[1] + f64::from(n2) * b2[1],
            ];
            if inside(p) {
                sites.push(([n1, n2], p));
            }
        }
    }
    // Δt₀: the median time apart of the 4 % of the atoms seen closest in time (the ones the
    // match starts from), so that they split between the two nearest counter atoms.
    let mut apart: Vec<f64> = sites.iter().map(|s| dt_of(s.1)).collect();
    apart.sort_by(f64::total_cmp);
    let early = &apart[..(apart.len() / 25).max(6)];
    let dt0 = early[early.len() / 2];
    // The drift: one and a half lattice constants across all the times apart.
    let w = 1.5 * A_NM / (apart[apart.len() - 1] - apart[0]).max(1e-9);
    let (ds, dc) = drift_direction.sin_cos();
    let shift = |dt: f64| -> [f64; 2] {
        let d = w * (dt - dt0);
        [
            offset[0] * b1[0] + offset[1] * b2[0] + d * dc,
            offset[0] * b1[1] + offset[1] * b2[1] + d * ds,
        ]
    };
    let mut direct = Vec::new();
    let mut counter = Vec::new();
    let mut index = Vec::new();
    // Both images see the same atoms; the counter's corrected frame is the direct's moved by
    // the offset, so the atoms seen first by the counter (the top rows) lie that far from
    // where the direct saw them, with no counter atom in between.
    for (n, p) in sites {
        let q = shift(dt_of(p));
        let q = [p[0] + q[0], p[1] + q[1]];
        let row = row_of(p);
        index.push(n);
        direct.push(feature(p, direct_time(row)));
        counter.push(feature(q, counter_time(row)));
    }
    let map = frame();
    let matches = match_features(
        &direct,
        &counter,
        &times(&direct_time),
        &times(&counter_time),
        0.3 * A_NM,
        (&map, &map),
    );
    // The matches are one branch (one lattice vector from each atom to the atom whose second
    // sighting it is paired with), and they cover nearly all atoms.
    let mut branches = std::collections::BTreeSet::new();
    for m in &matches {
        let d = direct
            .iter()
            .position(|f| f.column == m.direct_column && f.row == m.direct_row)
            .unwrap();
        let k = counter
            .iter()
            .position(|f| f.column == m.counter_column && f.row == m.counter_row)
            .unwrap();
        branches.insert([index[k][0] - index[d][0], index[k][1] - index[d][1]]);
    }
    let case = format!(
        "side {side_nm} nm, angle {angle}, offset {offset:?}, drift direction {drift_direction}"
    );
    assert_eq!(
        branches.len(),
        1,
        "{case}: matches in several branches: {branches:?}"
    );
    assert!(
        matches.len() as f64 >= 0.5 * direct.len() as f64,
        "{case}: {} of {} atoms matched",
        matches.len(),
        direct.len()
    );
}

/// Synthetic pairs: the counter sees the lattice moved by an offset (half a lattice vector,
/// the centre of a triangle, or several lattice constants, so that the atoms the counter sees
/// first lie far from where the direct saw them) and by a drift of 1.5 lattice constants over
/// the pair, in frames of 5.1 and 3 nm.
#[test]
fn offset_pairs_are_matched_on_one_branch() {
    let third = 1.0 / 3.0;
    for side in [5.12, 3.0] {
        for (angle, offset, drift_direction) in [
            (0.2, [0.5, 0.0], 0.2),
            (0.2, [third, third], 0.0),
            (0.2, [third, third], 1.2),
            (0.7, [third, third], 2.0),
            (1.1, [0.5, 0.5], 0.4),
            (0.0, [0.5, 0.0], 1.57),
            (0.2, [1.3, -2.2], 0.3),
            (0.5, [-0.6, -1.4], 1.0),
            (0.9, [2.5, -4.1], 2.5),
            (0.8, [1.2, -2.7], 0.1),
            (0.78, [0.3, -1.9], 3.0),
            (0.4, [-1.6, -0.4], 1.9),
        ] {
            check(side, angle, offset, drift_direction);
        }
    }
}

/// A pair read from `fixtures/NAME.txt`: the direct atoms' positions and times apart, the
/// counter atoms' positions.
fn fixture(name: &str) -> (Vec<[f64; 3]>, Vec<[f64; 2]>) {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/it/fixtures")
        .join(format!("{name}.txt"));
    let text = std::fs::read_to_string(&path).unwrap();
    let (mut direct, mut counter) = (Vec::new(), Vec::new());
    for line in text.lines().filter(|l| !l.starts_with('#')) {
        let mut words = line.split_whitespace();
        let kind = words.next().unwrap();
        let v: Vec<f64> = words.map(|w| w.parse().unwrap()).collect();
        match kind {
            "d" => direct.push([v[0], v[1], v[2]]),
            _ => counter.push([v[0], v[1]]),
        }
    }
    (direct, counter)
}

/// Pairs of the image benchmark that the matcher left without a match (fewer than 6) when it
/// started from the per-axis median of the earliest atoms' nearest displacements: their
/// earliest atoms lie at the frame's edge with no counter atom near, and their nearest
/// displacements fall on two or three lattice branches. Replayed with each atom on its own
/// pixel of maps that hold the recorded positions and times: most atoms must be matched, and
/// the matches must agree with one drift (a + v·Δt) to a tenth of a lattice constant.
#[test]
fn pairs_the_benchmark_left_unmatched_are_matched() {
    for name in ["pair-a", "pair-b", "pair-c"] {
        let (direct, counter) = fixture(name);
        let n = ((direct.len().max(counter.len()) as f64).sqrt().ceil() as usize).max(2) + 1;
        let map_of = |points: &[[f64; 2]]| {
            let mut x = vec![0.0; n * n];
            let mut y = vec![0.0; n * n];
            for (k, p) in points.iter().enumerate() {
                x[k] = p[0];
                y[k] = p[1];
            }
            CoordinateMap::new(n, n, x, YCoordinates::PerPixel(y)).unwrap()
        };
        let on_pixel = |k: usize, p: [f64; 2], t: f64| Feature {
            column: (k % n) as f64,
            row: (k / n) as f64,
            ..feature(p, t)
        };
        let direct_points: Vec<[f64; 2]> = direct.iter().map(|d| [d[0], d[1]]).collect();
        let direct_features: Vec<Feature> = direct
            .iter()
            .enumerate()
            .map(|(k, d)| on_pixel(k, [d[0], d[1]], 0.0))
            .collect();
        let counter_features: Vec<Feature> = counter
            .iter()
            .enumerate()
            .map(|(k, c)| on_pixel(k, *c, 0.0))
            .collect();
        // The direct atoms' pixels carry time 0 in the direct map, their time apart in the
        // counter's.
        let times_on = |time_s: Vec<f64>| HeightMap {
            origin: CountPoint::from_counts(0.0, 0.0),
            pixel_step: Counts(1.0),
            columns: n,
            rows: n,
            z_counts: vec![0.0; n * n],
            time_s,
        };
        let times_direct = times_on(vec![0.0; n * n]);
        let mut apart = vec![0.0; n * n];
        for (k, d) in direct.iter().enumerate() {
            apart[k] = d[2];
        }
        let times_counter = times_on(apart);
        let matches = match_features(
            &direct_features,
            &counter_features,
            &times_direct,
            &times_counter,
            0.3 * A_NM,
            (&map_of(&direct_points), &map_of(&counter)),
        );
        let least = direct.len().min(counter.len());
        assert!(
            matches.len() as f64 >= 0.6 * least as f64,
            "{name}: {} matched of {} and {} atoms",
            matches.len(),
            direct.len(),
            counter.len()
        );
        // One drift: counter − direct = a + v·Δt per axis, residuals under a tenth of a.
        let pixel = |c: f64, r: f64| c as usize + n * r as usize;
        let seen: Vec<([f64; 2], f64)> = matches
            .iter()
            .map(|m| {
                let (d, c) = (
                    direct[pixel(m.direct_column, m.direct_row)],
                    counter[pixel(m.counter_column, m.counter_row)],
                );
                ([c[0] - d[0], c[1] - d[1]], d[2])
            })
            .collect();
        let rows: Vec<Vec<f64>> = seen.iter().map(|s| vec![1.0, s.1]).collect();
        for axis in 0..2 {
            let rhs: Vec<f64> = seen.iter().map(|s| s.0[axis]).collect();
            let fit = spm_regression::least_squares(&rows, &rhs, &[false, false]).unwrap();
            assert!(
                fit.residual_rms < 0.1 * A_NM,
                "{name}: axis {axis}: the matches leave {} nm RMS about one drift",
                fit.residual_rms
            );
        }
    }
}
