//! The lattice survey and the LCS gate (issue 24), against the simulator's oracle: the
//! surveyed apparent lattice is the oracle's local calibration, and a decoy LCS — a
//! triangle that is not a nearest-neighbour triangle of the lattice, admitted through a
//! prior locked onto the wrong basis (a₁, a₁ + a₂), as happened on the measured HOPG
//! terrace — is accepted without the gate and refused with it.
#![allow(clippy::unwrap_used)]

use spm_calibration::survey::{
    apparent_lcc, neighbour_directions, spectrum_directions, survey_place,
};
use spm_calibration::{FosParams, PlanConfig};
use spm_features::{Feature, lcs_candidates};
use spm_fos::Raster;
use spm_hal::{
    CountPoint, CountVector, Microscope, NmPerCount, NmPerCountMatrix, Radians, Seconds,
};
use spm_sim::{SimConfig, Simulator};

fn map(m: NmPerCountMatrix, v: CountVector) -> (f64, f64) {
    let m = m.rows();
    (
        m[0][0] * v.x.value() + m[0][1] * v.y.value(),
        m[1][0] * v.x.value() + m[1][1] * v.y.value(),
    )
}

fn length_nm(m: NmPerCountMatrix, v: CountVector) -> f64 {
    let (x, y) = map(m, v);
    x.hypot(y)
}

/// The 2×2 map W with W·u = p and W·v = q.
fn map_taking(u: CountVector, v: CountVector, p: (f64, f64), q: (f64, f64)) -> NmPerCountMatrix {
    let (u0, u1, v0, v1) = (u.x.value(), u.y.value(), v.x.value(), v.y.value());
    let det = u0 * v1 - v0 * u1;
    // W = [p q]·[u v]⁻¹, [u v]⁻¹ = [[v1, −v0], [−u1, u0]] / det.
    let inv = [[v1 / det, -v0 / det], [-u1 / det, u0 / det]];
    NmPerCountMatrix([
        [
            p.0 * inv[0][0] + q.0 * inv[1][0],
            p.0 * inv[0][1] + q.0 * inv[1][1],
        ],
        [
            p.1 * inv[0][0] + q.1 * inv[1][0],
            p.1 * inv[0][1] + q.1 * inv[1][1],
        ],
    ])
}

/// The longer side of a triangle over a, through the oracle's map.
fn longest_side_over_a(truth: NmPerCountMatrix, t: &spm_features::Lcs, a_nm: f64) -> f64 {
    length_nm(truth, t.ab).max(length_nm(truth, t.ac)) / a_nm
}

#[test]
fn a_decoy_lcs_admitted_through_a_locked_prior_is_refused_by_the_survey_gate() {
    // The ideal scanner, where the survey must be the oracle's calibration, and the
    // room-temperature tube, whose survey frame (1.7 s, right after a move) carries the
    // creep and drift of its scan: there the survey is within the gate's tolerances of the
    // oracle, not within its uncertainty.
    for (config, relative, alpha_rad) in [
        (SimConfig::ideal(), 0.01, 0.01),
        (
            SimConfig::room_temperature_tube().without_random_faults(),
            0.1,
            0.2,
        ),
    ] {
        decoy_refused(Simulator::new(config).unwrap(), relative, alpha_rad);
    }
}

fn decoy_refused(mut sim: Simulator, relative: f64, alpha_rad: f64) {
    let plan = PlanConfig::hopg_small_net();
    let a_nm = plan.standard.lattice_constant_nm;
    let fos = FosParams::from_plan(&plan);
    let centre = CountPoint::from_counts(6000.0, -4000.0);
    // The survey frame: 8 lattice constants at the aperture's sampling (as the runner).
    let a_counts = a_nm / plan.standard.nominal_nm_per_count;
    let raster = Raster {
        pixels: (8.0 * a_counts / fos.aperture.raster.pixel_step_counts).ceil() as u32 + 1,
        ..fos.aperture.raster
    };
    let place = survey_place(&mut sim, centre, &raster, &fos.aperture.detection, &plan).unwrap();
    let surveyed = place.lcc.unwrap_or_else(|| panic!("no lattice: {place:?}"));
    // The oracle's local calibration at the place.
    let truth = sim.oracle().lcc_now(centre);
    println!("survey {surveyed:?}\noracle {truth:?}");
    assert!((surveyed.kx_nm_per_count / truth.kx.value() - 1.0).abs() < relative);
    assert!((surveyed.ky_nm_per_count / truth.ky.value() - 1.0).abs() < relative);
    assert!((surveyed.alpha_rad - truth.alpha.value()).abs() < alpha_rad);
    let truth_map = NmPerCountMatrix::from_lcc(truth.kx, truth.ky, truth.alpha);
    let gate = NmPerCountMatrix::from_lcc(
        NmPerCount(surveyed.kx_nm_per_count),
        NmPerCount(surveyed.ky_nm_per_count),
        Radians(surveyed.alpha_rad),
    );

    // An aperture at the place, and its features.
    sim.wait(Seconds(1.0)).unwrap();
    let report = spm_fos::aperture(&mut sim, centre, &fos.aperture).unwrap();
    let features: &[Feature] = &report.recognised.detection.features;
    let a = report.a.unwrap();
    // Two true nearest neighbours of A at 60° (through the oracle): a₁, a₂.
    let pa = features[a].position;
    let neighbours: Vec<CountVector> = features
        .iter()
        .map(|f| f.position - pa)
        .filter(|v| (length_nm(truth_map, *v) / a_nm - 1.0).abs() < 0.1)
        .collect();
    let angle = |u: CountVector, v: CountVector| {
        let (p, q) = (map(truth_map, u), map(truth_map, v));
        (p.0 * q.1 - p.1 * q.0).atan2(p.0 * q.0 + p.1 * q.1)
    };
    let (a1, a2) = neighbours
        .iter()
        .flat_map(|&u| neighbours.iter().map(move |&v| (u, v)))
        .find(|&(u, v)| (angle(u, v) - 60f64.to_radians()).abs() < 0.15)
        .unwrap_or_else(|| panic!("no two neighbours at 60° among {neighbours:?}"));
    // The prior a chain of wrong nodes locks onto: (a₁, a₁ + a₂), a √3 a-long vector 30°
    // from a₁, taken for two sides a of the standard's equilateral triangle.
    let standard = |deg: f64| {
        let r = f64::to_radians(deg);
        (a_nm * r.cos(), a_nm * r.sin())
    };
    let locked = map_taking(a1, a1 + a2, standard(0.0), standard(60.0));
    let without_gate = spm_features::LcsConfig {
        prior: Some(locked),
        ..fos.aperture.lcs.clone()
    };
    let ungated = lcs_candidates(features, a, &without_gate).unwrap();
    let decoys = |list: &[spm_features::Lcs]| {
        list.iter()
            .filter(|t| longest_side_over_a(truth_map, t, a_nm) > 1.5)
            .count()
    };
    // Without the gate the decoy is accepted and is what recognition chooses.
    let chosen = ungated.accepted.first().unwrap();
    assert!(
        longest_side_over_a(truth_map, chosen, a_nm) > 1.5,
        "{chosen:?}"
    );
    assert!(ungated.refused_by_gate.is_empty());

    // With the survey's gate: every decoy refused, nothing that is not a nearest-neighbour
    // triangle accepted, and the refusal counted as a misrecognition prevented.
    let with_gate = spm_features::LcsConfig {
        gate: Some(gate),
        ..without_gate
    };
    let gated = lcs_candidates(features, a, &with_gate).unwrap();
    assert_eq!(decoys(&gated.accepted), 0, "{gated:?}");
    assert_eq!(
        decoys(&gated.refused_by_gate),
        decoys(&ungated.accepted),
        "{gated:?}"
    );
    assert!(gated.best_refused_by_gate());

    // The gate alone (no prior) accepts the true nearest-neighbour triangles.
    let gate_only = spm_features::LcsConfig {
        prior: None,
        gate: Some(gate),
        ..fos.aperture.lcs.clone()
    };
    let true_ones = lcs_candidates(features, a, &gate_only).unwrap();
    assert!(!true_ones.accepted.is_empty());
    for t in &true_ones.accepted {
        assert!(
            (length_nm(truth_map, t.ab) / a_nm - 1.0).abs() < 0.1
                && (length_nm(truth_map, t.ac) / a_nm - 1.0).abs() < 0.1,
            "{t:?}"
        );
    }
}

/// Features at the points of a triangular lattice seen through a known map, with a
/// deterministic jitter of ±4 % of the lattice constant.
fn lattice_features(m_inverse: [[f64; 2]; 2], a_nm: f64, n: i32) -> Vec<Feature> {
    let template = spm_features::Feature {
        position: CountPoint::from_counts(0.0, 0.0),
        ..test_feature()
    };
    let mut out = Vec::new();
    let mut k = 0u32;
    for i in -n..=n {
        for j in -n..=n {
            let (x, y) = (
                a_nm * (f64::from(i) + 0.5 * f64::from(j)),
                a_nm * 3f64.sqrt() / 2.0 * f64::from(j),
            );
            k = k.wrapping_mul(1_103_515_245).wrapping_add(12_345);
            let jx = (f64::from(k >> 16 & 0xff) / 255.0 - 0.5) * 0.08 * a_nm;
            let jy = (f64::from(k >> 8 & 0xff) / 255.0 - 0.5) * 0.08 * a_nm;
            let (x, y) = (x + jx, y + jy);
            out.push(Feature {
                position: CountPoint::from_counts(
                    m_inverse[0][0] * x + m_inverse[0][1] * y,
                    m_inverse[1][0] * x + m_inverse[1][1] * y,
                ),
                ..template
            });
        }
    }
    out
}

fn test_feature() -> Feature {
    let map = spm_hal::HeightMap {
        origin: CountPoint::from_counts(0.0, 0.0),
        pixel_step: spm_hal::Counts(1.0),
        columns: 15,
        rows: 15,
        z_counts: (0..225)
            .map(|i| {
                let (c, r) = (f64::from(i % 15) - 7.0, f64::from(i / 15) - 7.0);
                100.0 * (-(c * c + r * r) / 8.0).exp()
            })
            .collect(),
        time_s: vec![0.0; 225],
    };
    spm_features::detect(&map, &spm_features::DetectionConfig::default())
        .unwrap()
        .features[0]
}

/// The inverse of the LCC map (counts per nm) turned by `rotation_deg` in the sample.
fn counts_per_nm(kx: f64, ky: f64, alpha: f64, rotation_deg: f64) -> [[f64; 2]; 2] {
    let m = NmPerCountMatrix::from_lcc(NmPerCount(kx), NmPerCount(ky), Radians(alpha)).rows();
    let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
    let inverse = [
        [m[1][1] / det, -m[0][1] / det],
        [-m[1][0] / det, m[0][0] / det],
    ];
    let r = rotation_deg.to_radians();
    [
        [
            inverse[0][0] * r.cos() + inverse[0][1] * r.sin(),
            -inverse[0][0] * r.sin() + inverse[0][1] * r.cos(),
        ],
        [
            inverse[1][0] * r.cos() + inverse[1][1] * r.sin(),
            -inverse[1][0] * r.sin() + inverse[1][1] * r.cos(),
        ],
    ]
}

/// The survey's LCC of a frame of a triangular lattice seen through (K̄x, K̄y, α), turned by
/// `rotation_deg` in the sample (the survey does not know the lattice's orientation), from
/// the features' neighbour statistics and from the frame's spectrum, against the closed form.
fn check_survey(kx: f64, ky: f64, alpha_deg: f64, rotation_deg: f64) {
    let (a_nm, alpha) = (0.2461, alpha_deg.to_radians());
    let inverse = counts_per_nm(kx, ky, alpha, rotation_deg);
    let case = format!("K̄x {kx}, K̄y {ky}, α {alpha_deg}°, turned {rotation_deg}°");
    let agree = |lattice: &spm_features::Lattice, how: &str| {
        assert_eq!(lattice.vectors.len(), 3, "{how}, {case}: {lattice:?}");
        let (lcc, _) = apparent_lcc(lattice, a_nm, Radians(60f64.to_radians()), 4).unwrap();
        assert!(
            (lcc.kx.value() / kx - 1.0).abs() < 0.01
                && (lcc.ky.value() / ky - 1.0).abs() < 0.01
                && (lcc.alpha.value() - alpha).abs() < 0.01,
            "{how}, {case}: {lcc:?}"
        );
    };
    let features = lattice_features(inverse, a_nm, 5);
    agree(
        &neighbour_directions(&features, 3, 4).unwrap(),
        "neighbours",
    );
    // A frame of Gaussian pits at the lattice's points, 1 count per pixel, 9 lattice
    // constants wide at the nominal sensitivity (the mean of K̄x and K̄y).
    let nominal = 0.5 * (kx + ky);
    let a_counts = a_nm / nominal;
    let n = (9.0 * a_counts).round() as usize;
    let centre = 0.5 * (n as f64 - 1.0);
    let m = NmPerCountMatrix::from_lcc(NmPerCount(kx), NmPerCount(ky), Radians(alpha)).rows();
    let r = rotation_deg.to_radians();
    let z_counts = (0..n * n)
        .map(|k| {
            let (c, row) = ((k % n) as f64 - centre, (k / n) as f64 - centre);
            // The pixel in the sample (nm), turned back into the lattice's frame.
            let (x, y) = (m[0][0] * c + m[0][1] * row, m[1][0] * c + m[1][1] * row);
            let (x, y) = (r.cos() * x + r.sin() * y, -r.sin() * x + r.cos() * y);
            let j = y / (a_nm * 0.75f64.sqrt());
            let i = x / a_nm - 0.5 * j;
            let mut h = 0.0;
            for (di, dj) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
                let (si, sj) = (i.floor() + di, j.floor() + dj);
                let (px, py) = (a_nm * (si + 0.5 * sj), a_nm * 0.75f64.sqrt() * sj);
                let d2 = (x - px).powi(2) + (y - py).powi(2);
                h -= (-d2 / (2.0 * (0.15 * a_nm).powi(2))).exp();
            }
            h
        })
        .collect();
    let map = spm_hal::HeightMap {
        origin: CountPoint::from_counts(-centre, -centre),
        pixel_step: spm_hal::Counts(1.0),
        columns: n,
        rows: n,
        z_counts,
        time_s: vec![0.0; n * n],
    };
    agree(
        &spectrum_directions(&map, a_counts, 3).expect("a lattice in the spectrum"),
        "spectrum",
    );
}

#[test]
fn the_survey_solves_a_known_oblique_lattice_as_its_local_calibration() {
    for (kx, ky, alpha_deg, rotation_deg) in [
        (0.022, 0.018, 6.0, 17.0),
        // Si_7x7_028's apparent lattice (the slow axis stretched by 1/0.68, −10°): its third
        // direction is 1.4 × the nearest-neighbour distance at these orientations.
        (0.0181, 0.0133, -10.0, 0.0),
        (0.0181, 0.0133, -10.0, 25.0),
        (0.0181, 0.0133, -10.0, 50.0),
    ] {
        check_survey(kx, ky, alpha_deg, rotation_deg);
    }
}

#[test]
fn old_plans_run_without_a_survey_unless_asked_and_the_survey_table_is_checked() {
    // A plan without `[plan.survey]` (the shipped small plan) gets the defaults: no survey.
    let text = include_str!("../../scenarios/plan-hopg-small.toml");
    assert!(!text.contains("survey"));
    let plan = PlanConfig::from_toml_str(text, "plan-hopg-small.toml").unwrap();
    assert!(!plan.survey.enabled);
    assert_eq!(plan.survey.places_per_side, 3);
    let on = format!("{text}\n[plan.survey]\nenabled = true\n");
    assert!(
        PlanConfig::from_toml_str(&on, "on.toml")
            .unwrap()
            .survey
            .enabled
    );
    // Unknown fields and out-of-range values are refused naming the field.
    let typo = format!("{text}\n[plan.survey]\nplaces = 3\n");
    let e = PlanConfig::from_toml_str(&typo, "typo.toml").unwrap_err();
    assert!(e.to_string().contains("places"), "{e}");
    let zero = format!("{text}\n[plan.survey]\nplaces_per_side = 0\n");
    let e = PlanConfig::from_toml_str(&zero, "zero.toml").unwrap_err();
    assert!(e.to_string().contains("survey.places_per_side"), "{e}");
}
