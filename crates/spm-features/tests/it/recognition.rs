//! Detection, rejection, lattice vectors and LCS on synthetic HOPG maps.
#![allow(clippy::unwrap_used)]

use crate::common;

use common::{Hopg, segment_map};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use spm_features::{
    DetectionConfig, FeatureError, LatticeConfig, LcsConfig, Polarity, RejectReason, detect,
    find_lcs_nearest, lattice_vectors, lcs_neighbours, lcs_with_vertex,
};
use spm_hal::{CountPoint, Counts, Frame, HeightMap, ScanRequest, Seconds, TraceHalf};

const NM_PER_COUNT: f64 = 0.005;

fn aperture(hopg: &Hopg, centre: CountPoint, noise: f64, seed: u64) -> (HeightMap, Counts) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let pixels = 64;
    let step = Counts(4.0 * hopg.a_counts / f64::from(pixels - 1));
    (
        segment_map(hopg, centre, step, pixels, noise, &mut rng),
        step,
    )
}

fn config_for(hopg: &Hopg, step: Counts) -> DetectionConfig {
    DetectionConfig {
        min_separation_px: 0.4 * hopg.a_counts / step.value(),
        ..DetectionConfig::default()
    }
}

#[test]
fn every_interior_atom_of_an_aperture_is_found_once_and_close_to_its_truth() {
    let hopg = Hopg::new(NM_PER_COUNT, 0.3);
    let centre = hopg.atom(2, 1);
    let (map, step) = aperture(&hopg, centre, hopg.corrugation_z / 10.0, 7);
    let found = detect(&map, &config_for(&hopg, step)).unwrap();
    // Every atom whose centre is at least 1.5 σ inside the map is found.
    let mut expected = 0;
    for n in -6..10 {
        for m in -6..10 {
            let atom = hopg.atom(n, m);
            let (c, r) = map.pixel_of(atom);
            let border = c.min(r).min(63.0 - c).min(63.0 - r);
            if border < 4.0 {
                continue;
            }
            expected += 1;
            let f = found.nearest(atom).unwrap();
            let error = f.position.distance(atom).value();
            assert!(error < 0.1 * hopg.a_counts, "atom ({n},{m}) error {error}");
            assert!(f.uncertainty.sigma_x.value() > 0.0 && f.uncertainty.sigma_x.value() < 2.0);
            // The time is interpolated between the four surrounding pixels.
            let (c0, r0) = (f.column.floor(), f.row.floor());
            let corners = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)]
                .map(|(dc, dr)| map.time_at(c0 + dc, r0 + dr).unwrap().value());
            let lo = corners.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = corners.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            assert!(f.time.value() >= lo && f.time.value() <= hi);
        }
    }
    assert!(expected >= 12);
    assert!(found.features.len() >= expected);
    assert!(
        found.features.len() <= expected + 12,
        "{}",
        found.features.len()
    );
    // No two features on one atom.
    for (i, a) in found.features.iter().enumerate() {
        for b in &found.features[i + 1..] {
            assert!(a.position.distance(b.position).value() > 0.5 * hopg.a_counts);
        }
    }
}

#[test]
fn hollows_are_found_as_pits() {
    let hopg = Hopg::new(NM_PER_COUNT, 0.3);
    // HOPG hollows of the three-cosine model sit at (a1 + a2)/3 from an atom.
    let a0 = hopg.atom(0, 0);
    let a1 = hopg.atom(1, 0);
    let a2 = hopg.atom(0, 1);
    let hollow = CountPoint::from_counts(
        (a0.x.value() + a1.x.value() + a2.x.value()) / 3.0,
        (a0.y.value() + a1.y.value() + a2.y.value()) / 3.0,
    );
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let step = Counts(hopg.a_counts / 15.0);
    let map = segment_map(&hopg, hollow, step, 16, hopg.corrugation_z / 20.0, &mut rng);
    let config = DetectionConfig {
        polarity: Polarity::Pit,
        ..config_for(&hopg, step)
    };
    let found = detect(&map, &config).unwrap();
    let f = found.nearest(hollow).unwrap();
    assert_eq!(f.polarity, Polarity::Pit);
    assert!(f.position.distance(hollow).value() < 0.05 * hopg.a_counts);
}

fn gaussian_map(hills: &[(f64, f64, f64, f64)], pixels: u32) -> HeightMap {
    let request = ScanRequest::centred_square(
        CountPoint::from_counts(0.0, 0.0),
        Counts(1.0),
        pixels,
        Seconds(1e-3),
    );
    Frame::from_fn(request, Seconds(0.0), |p, _| {
        let z: f64 = hills
            .iter()
            .map(|&(x, y, a, s)| {
                let r2 = (p.x.value() - x).powi(2) + (p.y.value() - y).powi(2);
                a * (-r2 / (2.0 * s * s)).exp()
            })
            .sum();
        Counts(z)
    })
    .height_map(TraceHalf::Forward)
    .unwrap()
}

/// One case: hills (x, y, amplitude, width) on a map centred on 0 with
/// 1-count pixels (35×35); expected (accepted count, rejection reasons sorted).
fn check(hills: &[(f64, f64, f64, f64)], expected: (usize, &[RejectReason])) {
    let map = gaussian_map(hills, 35);
    let config = DetectionConfig {
        min_separation_px: 4.0,
        ..DetectionConfig::default()
    };
    let found = detect(&map, &config).unwrap();
    let mut reasons: Vec<RejectReason> = found.rejected.iter().map(|r| r.reason).collect();
    reasons.sort_by_key(|r| format!("{r:?}"));
    assert_eq!(
        (found.features.len(), reasons.as_slice()),
        expected,
        "hills {hills:?}: {:?}",
        found.features
    );
}

#[test]
fn border_cuts_and_defects_are_rejected() {
    let lattice: Vec<(f64, f64, f64, f64)> = (-1..=1)
        .flat_map(|i| (-1..=1).map(move |j| (f64::from(i) * 9.0, f64::from(j) * 9.0, 5.0, 2.0)))
        .collect();
    check(&lattice, (9, &[]));
    // A hill centred on the edge is cut by the border.
    let mut cut = lattice.clone();
    cut.push((16.0, 4.5, 5.0, 2.0));
    check(&cut, (9, &[RejectReason::CutByBorder]));
    // A sharp spike (tip artefact) and a tall adatom are defects.
    let mut defects = lattice.clone();
    defects[0].3 = 0.9;
    defects[8].2 = 20.0;
    check(&defects, (7, &[RejectReason::Defect, RejectReason::Defect]));
    // A flat map holds nothing.
    check(&[], (0, &[]));
}

#[test]
fn bad_maps_and_configs_are_typed_errors() {
    let mut map = gaussian_map(&[(0.0, 0.0, 5.0, 2.0)], 11);
    map.z_counts[13] = f64::NAN;
    assert!(matches!(
        detect(&map, &DetectionConfig::default()),
        Err(FeatureError::NonFinite {
            what: "height",
            column: 2,
            row: 1
        })
    ));
    map.z_counts.pop();
    assert!(matches!(
        detect(&map, &DetectionConfig::default()),
        Err(FeatureError::InconsistentMap { .. })
    ));
    let small = gaussian_map(&[], 3);
    assert!(matches!(
        detect(&small, &DetectionConfig::default()),
        Err(FeatureError::MapTooSmall { .. })
    ));
    let map = gaussian_map(&[], 11);
    let config = DetectionConfig {
        min_snr: f64::NAN,
        ..DetectionConfig::default()
    };
    assert!(matches!(
        detect(&map, &config),
        Err(FeatureError::InvalidConfig {
            field: "min_snr",
            ..
        })
    ));
}

#[test]
fn lattice_vectors_and_lcs_of_an_aperture() {
    let hopg = Hopg::new(NM_PER_COUNT, 0.3);
    let centre = hopg.atom(2, 1);
    let (map, step) = aperture(&hopg, centre, hopg.corrugation_z / 10.0, 11);
    let found = detect(&map, &config_for(&hopg, step)).unwrap();
    let lattice = lattice_vectors(&found.features, &LatticeConfig::default()).unwrap();
    assert_eq!(lattice.vectors.len(), 3, "{lattice:?}");
    assert!((lattice.nearest_neighbour.value() / hopg.a_counts - 1.0).abs() < 0.02);
    for v in &lattice.vectors {
        assert!(
            (v.vector.norm().value() / hopg.a_counts - 1.0).abs() < 0.02,
            "{v:?}"
        );
        assert!(v.sigma.x.value() < 0.02 * hopg.a_counts);
        assert!(v.pairs >= 5);
    }

    // LCS at the atom nearest the centre: six neighbours, each forming an LCS.
    let config = LcsConfig::hopg(spm_hal::NmPerCount(NM_PER_COUNT * 1.15)); // a 15 % wrong nominal sensitivity
    let a = found.nearest_index(centre).unwrap();
    let triangles = lcs_with_vertex(&found.features, a, &config).unwrap();
    assert_eq!(triangles.len(), 6, "{triangles:?}");
    for t in &triangles {
        let cross = t.ab.x.value() * t.ac.y.value() - t.ab.y.value() * t.ac.x.value();
        assert!(cross > 0.0, "counter-clockwise ordering");
    }
    assert_eq!(
        lcs_neighbours(&found.features, a, &config).unwrap().len(),
        6
    );
    // The structure whose gravity centre is nearest a point between three atoms.
    let target = CountPoint::from_counts(
        (hopg.atom(2, 1).x.value() + hopg.atom(3, 1).x.value() + hopg.atom(2, 2).x.value()) / 3.0,
        (hopg.atom(2, 1).y.value() + hopg.atom(3, 1).y.value() + hopg.atom(2, 2).y.value()) / 3.0,
    );
    let lcs = find_lcs_nearest(&found.features, target, &config)
        .unwrap()
        .unwrap();
    assert!(lcs.centroid.distance(target).value() < 0.05 * hopg.a_counts);
    // Far-off nominal sensitivity: nothing matches.
    let wrong = LcsConfig::hopg(spm_hal::NmPerCount(NM_PER_COUNT * 2.0));
    assert!(
        find_lcs_nearest(&found.features, target, &wrong)
            .unwrap()
            .is_none()
    );
    // A neighbour's calibration as the prior overrides the nominal sensitivity: with the
    // true map the far-off nominal finds all six again; with a prior twice off, none.
    let k = NM_PER_COUNT;
    let prior_true = LcsConfig {
        prior: Some(spm_hal::NmPerCountMatrix([[k, 0.0], [0.0, k]])),
        ..wrong.clone()
    };
    assert_eq!(
        lcs_with_vertex(&found.features, a, &prior_true)
            .unwrap()
            .len(),
        6
    );
    let prior_wrong = LcsConfig {
        prior: Some(spm_hal::NmPerCountMatrix([[2.0 * k, 0.0], [0.0, 2.0 * k]])),
        ..config.clone()
    };
    assert!(
        lcs_with_vertex(&found.features, a, &prior_wrong)
            .unwrap()
            .is_empty()
    );
    let singular = LcsConfig {
        prior: Some(spm_hal::NmPerCountMatrix([[k, k], [k, k]])),
        ..config.clone()
    };
    assert!(lcs_with_vertex(&found.features, a, &singular).is_err());
    assert!(lcs_with_vertex(&found.features, 10_000, &config).is_err());
}
