//! Clean trace/retrace pairs whose lattice rows lie at any angle to the fast axis
//! (issue 29 item 2): no invented effect, and the features where the generator put the
//! sites (tests/it/common/image.rs: an image-level generator independent of the library).
#![allow(clippy::unwrap_used)]

use crate::common;

use common::image::{Hidden, Program, rotation_for_row_angle, true_site_position, write_frames};
use spm_modelcheck::{
    ExtractOptions, FeatureSet, LatticeSpec, LineDirection, Options, diagnose, extract_features,
};
use std::path::PathBuf;

/// The default program with its lattice rows at `angle_deg` from the fast axis and
/// `pixels` pixels per line (the same 4.8 nm frame).
fn program_at(angle_deg: f64, pixels: usize) -> Program {
    let base = Program {
        pixels,
        ..Program::default()
    };
    Program {
        rotation_rad: rotation_for_row_angle(&base, angle_deg.to_radians()),
        ..base
    }
}

fn cleanup(paths: &[PathBuf]) {
    if let Some(dir) = paths.first().and_then(|p| p.parent()) {
        let _ = std::fs::remove_dir_all(dir);
    }
}

fn features_of(paths: &[PathBuf], a_nm: f64) -> FeatureSet {
    let files: Vec<_> = paths
        .iter()
        .map(|p| (spm_formats::read_any(p).unwrap(), None))
        .collect();
    extract_features(
        &files,
        &LatticeSpec::Hex { a_nm },
        &ExtractOptions::default(),
    )
    .unwrap()
}

/// The localisation bias of a clean set against the generator's true site positions:
/// per feature, reported − true (nm); each frame and direction's mean removed (a constant
/// per group is a frame offset, not a bias that can imitate an effect). Returns the RMS
/// of the remaining bias per axis, pm, and the number of features.
fn localisation_bias_pm(program: &Program, seed: u64, set: &FeatureSet) -> ([f64; 2], usize) {
    type Group = ((usize, LineDirection), Vec<[f64; 2]>);
    let mut groups: Vec<Group> = Vec::new();
    for f in &set.features {
        let truth = true_site_position(program, seed, [f.x_nm, f.y_nm], f.time_s);
        let bias = [f.x_nm - truth[0], f.y_nm - truth[1]];
        let key = (f.frame_index, f.direction);
        match groups.iter_mut().find(|g| g.0 == key) {
            Some(g) => g.1.push(bias),
            None => groups.push((key, vec![bias])),
        }
    }
    let (mut sum, mut n) = ([0.0; 2], 0usize);
    for (_, biases) in &groups {
        let mean = [0, 1].map(|a| biases.iter().map(|b| b[a]).sum::<f64>() / biases.len() as f64);
        for b in biases {
            for a in 0..2 {
                sum[a] += (b[a] - mean[a]).powi(2);
            }
            n += 1;
        }
    }
    (sum.map(|s| 1000.0 * (s / n.max(1) as f64).sqrt()), n)
}

/// Row angles of the sweep, degrees from the fast axis.
const ANGLES_DEG: [f64; 9] = [0.0, 2.0, 4.0, 5.0, 6.0, 7.0, 10.0, 20.0, 30.0];

/// Prints the localisation bias against the truth over the sweep.
/// `cargo test --workspace --test it orientation::explore_bias -- --ignored --nocapture`
#[test]
#[ignore = "exploration: prints the localisation bias per orientation"]
fn explore_bias() {
    let only: Option<f64> = std::env::var("ANGLE").ok().map(|a| a.parse().unwrap());
    let pix: Option<usize> = std::env::var("PIXELS").ok().map(|a| a.parse().unwrap());
    for pixels in [96, 192] {
        if pix.is_some_and(|p| p != pixels) {
            continue;
        }
        for angle in ANGLES_DEG {
            if only.is_some_and(|o| o != angle) {
                continue;
            }
            for seed in [1u64, 2] {
                let program = program_at(angle, pixels);
                let paths = write_frames(&program, Hidden::None, seed, "explore-orientation");
                let set = features_of(&paths, program.a_nm);
                let (bias, n) = localisation_bias_pm(&program, seed, &set);
                cleanup(&paths);
                println!(
                    "{pixels} px, rows at {angle:>4.1}°, seed {seed}: bias RMS x {:.2} pm, y {:.2} pm ({n} features)",
                    bias[0], bias[1]
                );
            }
        }
    }
}

/// The features of clean sets sit where the generator put the sites, whatever the rows'
/// angle to the fast axis: the bias RMS (each frame and direction's mean removed) stays
/// within 1.5× that of rows at 30° (the localiser's noise, 1.9 pm at 96 px, 0.9 pm at
/// 192 px). Per-line levelling took the lattice's row into the lines' offsets at small
/// angles: 6 pm at 0°, 20 pm at 2°, 5–6 pm at 4–6°.
#[test]
fn features_sit_on_the_true_sites_at_every_row_angle() {
    let mut failures = Vec::new();
    for pixels in [96, 192] {
        let reference = {
            let program = program_at(30.0, pixels);
            let paths = write_frames(&program, Hidden::None, 1, "bias-reference");
            let set = features_of(&paths, program.a_nm);
            cleanup(&paths);
            localisation_bias_pm(&program, 1, &set).0
        };
        for angle in [0.0, 2.0, 5.0, 6.0] {
            let program = program_at(angle, pixels);
            let paths = write_frames(&program, Hidden::None, 1, "bias");
            let set = features_of(&paths, program.a_nm);
            cleanup(&paths);
            let (bias, n) = localisation_bias_pm(&program, 1, &set);
            println!(
                "{pixels} px, rows at {angle}°: bias {:.2} / {:.2} pm (30°: {:.2} / {:.2} pm)",
                bias[0], bias[1], reference[0], reference[1]
            );
            if n < 1000 || (0..2).any(|a| bias[a] > 1.5 * reference[a]) {
                failures.push(format!(
                    "{pixels} px, rows at {angle}°: {n} features, bias {bias:.2?} pm against {reference:.2?} pm at 30°"
                ));
            }
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

/// Clean trace/retrace pairs (down then up) with the rows at 0–30° from the fast axis,
/// two seeds, 96 and 192 pixels per line: no finding and nothing unexplained. Before the
/// lines were levelled jointly with the lattice, rows at 4–7° gave a structured y
/// residual along x and a "vibration" was named.
#[test]
fn clean_pairs_at_any_row_angle_give_no_finding() {
    let mut failures = Vec::new();
    for pixels in [96, 192] {
        for angle in ANGLES_DEG {
            for seed in [1u64, 2] {
                let program = program_at(angle, pixels);
                let paths = write_frames(&program, Hidden::None, 700 + seed, "orientation");
                let inputs = common::image::inputs(&paths);
                let d = diagnose(
                    &inputs,
                    &LatticeSpec::Hex { a_nm: program.a_nm },
                    &Options::default(),
                    &ExtractOptions::default(),
                );
                cleanup(&paths);
                let d = d.unwrap();
                println!(
                    "{pixels} px, rows at {angle}°, seed {seed}: baseline {:.2} pm, findings {:?}, unexplained {} {:?}",
                    d.baseline.rms_pm,
                    d.effects_found(),
                    d.unexplained,
                    d.residual_structure.reasons
                );
                if !d.findings.is_empty() || d.unexplained {
                    failures.push(format!(
                        "{pixels} px, rows at {angle}°, seed {seed}: findings {:?}, unexplained {:?}",
                        d.effects_found(),
                        d.residual_structure.reasons
                    ));
                }
            }
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}
