//! Hidden effects in pixel-sampled images written as Nanonis `.sxm` files and
//! read back (tests/it/common/image.rs): a generator independent of spm-sim and
//! of the feature-level one, so the localiser's pixel locking, the file
//! timing and the direction conventions are part of what is tested.
#![allow(clippy::unwrap_used)]

use crate::common;

use common::image::{Hidden, Program, vibration_image_amplitudes, write_frames, write_no_lattice};
use spm_modelcheck::{
    Diagnosis, EffectKind, ExtractOptions, LatticeSpec, ModelCheckError, Options, diagnose,
};
use std::path::PathBuf;

fn run_paths(paths: &[PathBuf], a_nm: f64) -> Result<Diagnosis, ModelCheckError> {
    run_paths_with(paths, a_nm, &Options::default())
}

fn run_paths_with(
    paths: &[PathBuf],
    a_nm: f64,
    options: &Options,
) -> Result<Diagnosis, ModelCheckError> {
    let inputs = common::image::inputs(paths);
    diagnose(
        &inputs,
        &LatticeSpec::Hex { a_nm },
        options,
        &ExtractOptions::default(),
    )
}

fn run(program: &Program, hidden: Hidden, seed: u64, tag: &str) -> Diagnosis {
    let paths = write_frames(program, hidden, seed, tag);
    let d = run_paths(&paths, program.a_nm);
    if let Some(dir) = paths.first().and_then(|p| p.parent()) {
        let _ = std::fs::remove_dir_all(dir);
    }
    d.unwrap()
}

fn summary(d: &Diagnosis) -> String {
    format!(
        "σloc {:.2} pm, baseline {:.2} pm (sep {}) → final {:.2} pm; used {} ({} outliers, {} unindexed); findings {:?}; unexplained {} {:?}; rejected {:?}; round 0 {:?}; pl {:?}",
        d.localisation_sigma_pm,
        d.baseline.rms_pm,
        d.baseline.drift_separable,
        d.final_report.rms_pm,
        d.features_used,
        d.outliers,
        d.unindexed,
        common::findings(d),
        d.unexplained,
        d.residual_structure.reasons,
        common::rejections(d),
        common::first_round(d),
        d.localiser_bias
    )
}

fn cases() -> Vec<(&'static str, Hidden)> {
    vec![
        ("none", Hidden::None),
        (
            "hysteresis",
            Hidden::Hysteresis {
                half_separation_nm: 0.03,
            },
        ),
        (
            "drift_acceleration",
            Hidden::DriftAcceleration {
                a_nm_per_s2: [1.2e-4, -0.8e-4],
            },
        ),
        (
            "tip_change",
            Hidden::TipChange {
                time_s: 10.0,
                jump_nm: [0.04, -0.03],
            },
        ),
        (
            "periodic_vibration",
            Hidden::Vibration {
                amplitude_nm: [0.012, 0.008],
                frequency_hz: 0.83,
            },
        ),
        ("feedback_lag", Hidden::FeedbackFilter { decay: 0.5 }),
        (
            "scanner_nonlinearity",
            Hidden::Nonlinearity {
                quadratic: 0.02,
                cubic: 0.015,
            },
        ),
        ("interlace", Hidden::Interlace { dy_nm: 0.03 }),
        ("sine_drive", Hidden::SineDrive { beta_rad: 1.2 }),
        ("sine_drive_full", Hidden::SineDrive { beta_rad: 1.5 }),
        (
            "hysteresis_large",
            Hidden::Hysteresis {
                half_separation_nm: 0.085,
            },
        ),
    ]
}

#[test]
#[ignore = "exploration: prints every case"]
fn explore_image() {
    let program = Program::default();
    let only = std::env::var("CASE").ok();
    for (name, hidden) in cases() {
        if only.as_deref().is_some_and(|o| o != name) {
            continue;
        }
        for seed in 1..=std::env::var("SEEDS").map_or(2, |s| s.parse().unwrap()) {
            let started = std::time::Instant::now();
            let d = run(&program, hidden, seed, name);
            if let Ok(png) = std::env::var("PNG") {
                spm_modelcheck::write_png(&d, format!("{png}-{name}-{seed}.png"), name).unwrap();
            }
            println!(
                "{name} seed {seed} ({:.1} s): {}\n",
                started.elapsed().as_secs_f64(),
                summary(&d)
            );
        }
    }
}

#[test]
#[ignore = "exploration: prints the no-lattice cases"]
fn explore_no_lattice() {
    let program = Program::default();
    for blobs in [false, true] {
        for seed in 1..=3 {
            let path = write_no_lattice(&program, blobs, seed, "explore-nolattice");
            let r = run_paths(std::slice::from_ref(&path), program.a_nm);
            println!("blobs {blobs} seed {seed}: {:?}", r.map(|d| summary(&d)));
        }
    }
}

/// Rotates a lattice-frame vector into the image axes (the library reports
/// tip–sample displacements along the scan axes).
fn to_image(program: &Program, v: [f64; 2]) -> [f64; 2] {
    let (s, c) = program.rotation_rad.sin_cos();
    [c * v[0] + s * v[1], -s * v[0] + c * v[1]]
}

/// (effect expected first, hidden, true parameters).
type HiddenCase = (EffectKind, Hidden, Vec<(&'static str, f64)>);

/// The hidden cases with amplitude factor k.
fn hidden_effects(program: &Program, k: f64) -> Vec<HiddenCase> {
    let acc = [5e-4 * k, -3.5e-4 * k];
    let acc_img = to_image(program, acc);
    let jump = [0.04 * k, -0.03 * k];
    let jump_img = to_image(program, jump);
    let vib = [0.012 * k, 0.008 * k];
    let vib_img = vibration_image_amplitudes(program, vib);
    vec![
        (
            EffectKind::Hysteresis,
            Hidden::Hysteresis {
                half_separation_nm: 0.03 * k,
            },
            vec![("branch_separation_nm", 0.06 * k)],
        ),
        (
            EffectKind::DriftAcceleration,
            Hidden::DriftAcceleration { a_nm_per_s2: acc },
            vec![
                ("acceleration_x_nm_per_s2", acc_img[0]),
                ("acceleration_y_nm_per_s2", acc_img[1]),
            ],
        ),
        (
            EffectKind::TipChange,
            Hidden::TipChange {
                time_s: 10.0,
                jump_nm: jump,
            },
            vec![
                ("jump_x_nm", jump_img[0]),
                ("jump_y_nm", jump_img[1]),
                ("time_s", 10.0),
            ],
        ),
        (
            EffectKind::PeriodicVibration,
            Hidden::Vibration {
                amplitude_nm: vib,
                frequency_hz: 0.83,
            },
            vec![
                ("amplitude_x_nm", vib_img[0]),
                ("amplitude_y_nm", vib_img[1]),
                ("frequency_hz", 0.83),
            ],
        ),
        (
            EffectKind::ScannerNonlinearity,
            Hidden::Nonlinearity {
                quadratic: 0.02 * k,
                cubic: 0.015 * k,
            },
            vec![("quadratic_x", 0.02 * k), ("cubic_x", 0.015 * k)],
        ),
        // Creep after the move to each frame (both frames, same move size).
        (
            EffectKind::Creep,
            Hidden::Creep {
                nm_per_decade: [0.05 * k, -0.035 * k],
                time_constant_s: 0.5,
            },
            vec![
                ("creep_x_nm_per_decade_frame0", 0.05 * k),
                ("creep_y_nm_per_decade_frame0", -0.035 * k),
                ("creep_x_nm_per_decade_frame1", 0.05 * k),
            ],
        ),
        (
            EffectKind::CrosstalkXy,
            Hidden::Bow {
                x_from_y: 0.012 * k,
                y_from_x: -0.009 * k,
            },
            vec![("bow_x_from_y", 0.012 * k), ("bow_y_from_x", -0.009 * k)],
        ),
        (
            EffectKind::Nonorthogonality,
            Hidden::ShearGradient {
                x: 0.012 * k,
                y: -0.01 * k,
            },
            vec![
                ("shear_gradient_x", 0.012 * k),
                ("shear_gradient_y", -0.01 * k),
            ],
        ),
        // Backward lines 25–45 pm along the slow axis (input): their features
        // appear displaced by minus the tip's displacement, in the image axes.
        (
            EffectKind::Interlace,
            Hidden::Interlace { dy_nm: 0.035 * k },
            vec![(
                "separation_y_nm",
                -program.scale[1] * program.obliquity_rad.cos() * 0.035 * k,
            )],
        ),
        // The library's lag is the localiser's apparent shift of a filtered
        // profile (less than the filter's centroid shift): named, and its
        // parameter bounded below (see docs/MODELCHECK.md).
        (
            EffectKind::FeedbackLag,
            Hidden::FeedbackFilter {
                decay: 0.3 + 0.2 * k,
            },
            vec![],
        ),
    ]
}

/// The hidden effects in groups of two, one test each (they run in parallel: the ten
/// effects × 5 seeds in one test took 50 s of the binary's critical path).
const EFFECT_GROUPS: [[EffectKind; 2]; 5] = [
    [EffectKind::Hysteresis, EffectKind::DriftAcceleration],
    [EffectKind::TipChange, EffectKind::PeriodicVibration],
    [EffectKind::ScannerNonlinearity, EffectKind::Creep],
    [EffectKind::CrosstalkXy, EffectKind::Nonorthogonality],
    [EffectKind::Interlace, EffectKind::FeedbackLag],
];

#[test]
fn the_effect_groups_cover_every_hidden_effect_once() {
    let all: Vec<EffectKind> = hidden_effects(&Program::default(), 1.0)
        .iter()
        .map(|c| c.0)
        .collect();
    let grouped: Vec<EffectKind> = EFFECT_GROUPS.iter().flatten().copied().collect();
    assert_eq!(grouped, all);
}

/// Each hidden effect of `group`, 5 seeds each at a random 0.7–1.3 × amplitude (the seeds
/// and amplitudes of its place in [`hidden_effects`]): the effect named first in at least
/// 5 of 6 cases over the group (and 4 of 5 per effect), its parameters within 3σ + 10 %
/// where the truth maps one to one.
fn check_hidden_effects_named_first(group: &[EffectKind]) {
    let program = Program::default();
    let mut named_first = 0;
    let mut total = 0;
    let mut failures = Vec::new();
    for (e, effect) in hidden_effects(&program, 1.0)
        .iter()
        .map(|c| c.0)
        .enumerate()
        .filter(|(_, effect)| group.contains(effect))
    {
        let mut first_here = 0;
        for seed in 0..5u64 {
            let s = 40 + 10 * e as u64 + seed;
            let k = 0.7 + 0.6 * ((s * 2_654_435_761) % 1000) as f64 / 1000.0;
            let cases = hidden_effects(&program, k);
            let (_, hidden, truth) = &cases[e];
            let d = run(&program, *hidden, s, effect.name());
            total += 1;
            let first = d.findings.first().map(|f| f.effect.as_str());
            if first == Some(effect.name()) {
                named_first += 1;
                first_here += 1;
            } else {
                failures.push(format!(
                    "{} seed {s}: named {first:?}: {}",
                    effect.name(),
                    summary(&d)
                ));
                continue;
            }
            // final.parameters: the baseline's keys only, never effect
            // values under frame-offset names.
            for key in d.final_report.parameters.keys() {
                assert!(
                    d.baseline.parameters.contains_key(key),
                    "{key}: {}",
                    summary(&d)
                );
            }
            let f = &d.findings[0];
            for (name, value) in truth {
                let Some(p) = f.parameters.get(*name) else {
                    failures.push(format!("{}: no {name}", effect.name()));
                    continue;
                };
                if (p.value - value).abs() > 3.0 * p.sigma + 0.1 * value.abs() {
                    failures.push(format!(
                        "{} seed {s}: {name} = {:.4e} ± {:.1e}, hidden {value:.4e}",
                        effect.name(),
                        p.value,
                        p.sigma
                    ));
                }
            }
            if effect == EffectKind::FeedbackLag {
                let tau = f.parameters["time_constant_s"].value;
                let d_true = 0.3 + 0.2 * k;
                let dwell = program.line_time_s / program.pixels as f64;
                let centroid = dwell * d_true / (1.0 - d_true);
                if !(tau > 0.3 * centroid && tau < 1.1 * centroid) {
                    failures.push(format!(
                        "feedback_lag seed {s}: τ {tau:.3e} vs centroid lag {centroid:.3e}"
                    ));
                }
            }
        }
        assert!(
            first_here >= 4,
            "{}: named first in {first_here} of 5: {failures:#?}",
            effect.name()
        );
    }
    println!("named first in {named_first} of {total}; parameter misses: {failures:?}");
    assert!(
        6 * named_first >= 5 * total,
        "named first in {named_first} of {total}: {failures:#?}"
    );
    assert!(failures.iter().all(|f| !f.contains('=')), "{failures:#?}");
}

#[test]
fn hidden_hysteresis_and_drift_acceleration_in_images_are_named_first_with_their_parameters() {
    check_hidden_effects_named_first(&EFFECT_GROUPS[0]);
}

#[test]
fn a_hidden_tip_change_and_vibration_in_images_are_named_first_with_their_parameters() {
    check_hidden_effects_named_first(&EFFECT_GROUPS[1]);
}

#[test]
fn hidden_nonlinearity_and_creep_in_images_are_named_first_with_their_parameters() {
    check_hidden_effects_named_first(&EFFECT_GROUPS[2]);
}

#[test]
fn hidden_crosstalk_and_nonorthogonality_in_images_are_named_first_with_their_parameters() {
    check_hidden_effects_named_first(&EFFECT_GROUPS[3]);
}

#[test]
fn hidden_interlace_and_feedback_lag_in_images_are_named_first_with_their_parameters() {
    check_hidden_effects_named_first(&EFFECT_GROUPS[4]);
}

/// Clean two-frame sets (down then up, trace and retrace): no finding, no
/// "unexplained", in every one of 5 seeds.
#[test]
fn clean_images_give_no_finding() {
    let program = Program::default();
    for seed in 0..5 {
        let d = run(&program, Hidden::None, 900 + seed, "clean");
        assert!(d.findings.is_empty(), "seed {seed}: {}", summary(&d));
        assert!(!d.unexplained, "seed {seed}: {}", summary(&d));
        assert!(
            d.baseline.drift_separable,
            "down + up frames 28 s apart: {}",
            summary(&d)
        );
        // The JSON's final parameters hold the baseline's keys only.
        for key in d.final_report.parameters.keys() {
            assert!(
                d.baseline.parameters.contains_key(key) || key.starts_with("drift_"),
                "{key}"
            );
        }
    }
}

/// A trace/retrace y offset the library cannot follow (beyond its plausible
/// range, or with `interlace` left out of the search) is called unexplained
/// by the direction check, not absorbed by another effect.
#[test]
fn an_interlace_offset_outside_the_search_is_unexplained() {
    let program = Program::default();
    let paths = write_frames(&program, Hidden::Interlace { dy_nm: 0.03 }, 77, "interlace");
    let d = run_paths_with(
        &paths,
        program.a_nm,
        &Options::default().without(EffectKind::Interlace),
    )
    .unwrap();
    assert!(d.unexplained, "{}", summary(&d));
    assert!(
        d.residual_structure.direction_offset_pm[0]
            .hypot(d.residual_structure.direction_offset_pm[1])
            > 20.0,
        "{}",
        summary(&d)
    );
}

/// Trace and retrace made with a peer's drift + hysteresis + creep model
/// (Yothers, Browder & Bumm 2017): hysteresis and creep are named, no
/// feedback lag is invented, and the final residual comes down to the
/// localisation noise of a clean set (the peer's own fit ends at 6 pm on
/// its data; a clean set here ends at ≈ 2–3 pm).
#[test]
fn a_peer_drift_hysteresis_creep_model_is_explained() {
    let program = Program::default();
    let clean = run(&program, Hidden::None, 600, "peer-clean");
    // Mid-line trace/retrace separations ≈ 0.04, 0.08, 0.13, 0.17 nm (the
    // issue's sweep: up to 0.7 a on graphite).
    for (i, exponent) in [0.012, 0.025, 0.04, 0.055].into_iter().enumerate() {
        let hidden = Hidden::PeerDriftHysteresisCreep {
            acceleration_nm_per_s2: [2e-4, -1.5e-4],
            creep_nm: [0.03, -0.04],
            creep_time_constant_s: 0.5,
            hysteresis_exponent: exponent,
        };
        let d = run(&program, hidden, 600 + i as u64, "peer");
        println!("exponent {exponent}: {}", summary(&d));
        let found = d.effects_found();
        assert!(found.contains(&"hysteresis"), "{}", summary(&d));
        assert!(found.contains(&"creep"), "{}", summary(&d));
        assert!(!found.contains(&"feedback_lag"), "{}", summary(&d));
        assert!(!d.unexplained, "{}", summary(&d));
        assert!(
            d.final_report.rms_pm < 1.5 * clean.final_report.rms_pm + 1.0,
            "final {} pm against clean {} pm: {}",
            d.final_report.rms_pm,
            clean.final_report.rms_pm,
            summary(&d)
        );
    }
}

/// Trace/retrace separations up to 1.2 a mid-line (0.09–0.30 nm on graphite):
/// the other half of each frame is registered at the line ends, so the
/// separation is measured, not mistaken for a neighbouring site.
#[test]
fn large_hysteresis_does_not_misindex_the_other_half() {
    let program = Program::default();
    for (i, half) in [0.045, 0.067, 0.085, 0.125, 0.15].into_iter().enumerate() {
        let d = run(
            &program,
            Hidden::Hysteresis {
                half_separation_nm: half,
            },
            300 + i as u64,
            "large-hysteresis",
        );
        assert_eq!(
            d.findings.first().map(|f| f.effect.as_str()),
            Some("hysteresis"),
            "{}",
            summary(&d)
        );
        let sep = d.findings[0].parameters["branch_separation_nm"];
        assert!(
            (sep.value - 2.0 * half).abs() < 3.0 * sep.sigma + 0.1 * 2.0 * half,
            "{half}: {}",
            summary(&d)
        );
        assert!(d.final_report.rms_pm < 6.0, "{}", summary(&d));
        assert!(
            d.findings.iter().all(|f| f.effect != "feedback_lag"),
            "{}",
            summary(&d)
        );
    }
}

/// Images without the lattice (white noise, random adsorbate blobs) are
/// refused, not diagnosed.
#[test]
fn images_without_the_lattice_are_refused() {
    let program = Program::default();
    for (blobs, seed) in [(false, 1), (false, 2), (true, 3), (true, 4)] {
        let path = write_no_lattice(&program, blobs, seed, "refuse");
        let r = run_paths(std::slice::from_ref(&path), program.a_nm);
        let _ = std::fs::remove_dir_all(path.parent().unwrap());
        assert!(
            matches!(r, Err(ModelCheckError::NotTheLattice { .. })),
            "blobs {blobs}: {:?}",
            r.map(|d| summary(&d))
        );
    }
    // And a lattice of another period (claimed hopg, scanned 2× larger).
    let paths = write_frames(
        &Program {
            a_nm: 0.5,
            ..Program::default()
        },
        Hidden::None,
        5,
        "other-period",
    );
    let r = run_paths(&paths, 0.2461);
    let _ = std::fs::remove_dir_all(paths[0].parent().unwrap());
    assert!(
        matches!(r, Err(ModelCheckError::NotTheLattice { .. })),
        "{:?}",
        r.map(|d| summary(&d))
    );
}

/// A fast axis driven sinusoidally in time (pixels equidistant in time, not
/// space): a strong map that is not a cubic. Named as the sinusoidal drive,
/// with the features at the frame edges kept (re-admitted under the extended
/// model) and nothing relevant left.
#[test]
fn a_sinusoidal_fast_axis_drive_is_followed() {
    let program = Program::default();
    let d = run(&program, Hidden::SineDrive { beta_rad: 1.2 }, 11, "sine");
    // Named with its shape (issue 29 item 3; before: `scanner_nonlinearity`, a cubic
    // within 15 % of −β²/6): the sine drive, its amplitude W·k_x/sin β (nm in the sample)
    // and its phase β within 5 %.
    assert_eq!(
        d.effects_found().first(),
        Some(&"sinusoidal_drive"),
        "{}",
        summary(&d)
    );
    assert!(d.outliers * 50 < d.features_used, "{}", summary(&d));
    assert!(
        d.final_report.rms_pm < 1.5 * d.localisation_sigma_pm,
        "{}",
        summary(&d)
    );
    assert!(!d.unexplained, "{}", summary(&d));
    let k = 1.2_f64;
    let f = &d.findings[0].parameters;
    let amplitude = f["amplitude_nm"].value;
    let truth = program.scale[0] * 0.5 * program.size_nm / k.sin();
    assert!(
        (amplitude / truth - 1.0).abs() < 0.05,
        "amplitude {amplitude} for {truth}: {}",
        summary(&d)
    );
    let beta = f["phase_at_line_end_rad"].value;
    assert!((beta / k - 1.0).abs() < 0.05, "β {beta}: {}", summary(&d));
}

/// Slow-axis directions of a movie scanned down, up, down, … (no flyback).
fn alternating_frames(frames: usize) -> Vec<spm_formats::ScanDir> {
    (0..frames)
        .map(|f| {
            if f % 2 == 0 {
                spm_formats::ScanDir::Down
            } else {
                spm_formats::ScanDir::Up
            }
        })
        .collect()
}

/// A fast-SPM-like movie: many frames shorter than the record time's one
/// second resolution, fast drift, a vibration. The frames are placed one
/// after another within their stamped seconds (not on top of each other), so
/// the vibration (4.5 cycles per frame) keeps its phase from frame to frame
/// and is named with its frequency, and the drift comes out.
#[test]
fn a_fast_movie_with_second_resolution_stamps_is_timed_and_followed() {
    let program = Program {
        pixels: 48,
        size_nm: 2.4,
        line_time_s: 0.002,
        frames: alternating_frames(12),
        gap_s: 0.0,
        drift_nm_per_s: [0.4, -0.3],
        ..Program::default()
    };
    let d = run(
        &program,
        Hidden::Vibration {
            amplitude_nm: [0.012, 0.008],
            frequency_hz: 23.7,
        },
        12,
        "movie",
    );
    assert_eq!(
        d.effects_found().first(),
        Some(&"periodic_vibration"),
        "{}",
        summary(&d)
    );
    let f = d.findings[0].parameters["frequency_hz"].value;
    assert!((f - 23.7).abs() < 0.1, "{f} Hz: {}", summary(&d));
    assert!(d.baseline.drift_separable, "{}", summary(&d));
    let v = |k: &str| d.baseline.parameters[k].value;
    let speed = v("drift_x_nm_per_s").hypot(v("drift_y_nm_per_s"));
    let truth = 0.4_f64.hypot(0.3);
    assert!(
        (speed - truth).abs() < 0.1 * truth,
        "drift {speed} nm/s against {truth}: {}",
        summary(&d)
    );
    let amplitude = d.findings[0].parameters["amplitude_x_nm"];
    let truth_x = vibration_image_amplitudes(&program, [0.012, 0.008])[0];
    assert!(
        (amplitude.value - truth_x).abs() < 3.0 * amplitude.sigma + 0.1 * truth_x,
        "x amplitude {amplitude:?} against {truth_x}: {}",
        summary(&d)
    );
}

/// Frames of different scan series (another size) are diagnosed with a
/// warning naming the difference.
#[test]
fn frames_of_different_series_are_flagged() {
    let a = write_frames(
        &Program {
            frames: vec![spm_formats::ScanDir::Down],
            ..Program::default()
        },
        Hidden::None,
        21,
        "series-a",
    );
    let b = write_frames(
        &Program {
            frames: vec![spm_formats::ScanDir::Up],
            size_nm: 6.0,
            ..Program::default()
        },
        Hidden::None,
        22,
        "series-b",
    );
    let d = run_paths(&[a[0].clone(), b[0].clone()], 0.2461);
    for p in [&a[0], &b[0]] {
        let _ = std::fs::remove_dir_all(p.parent().unwrap());
    }
    let d = d.unwrap();
    assert!(
        d.warnings.iter().any(|w| w.contains("size")),
        "{:?}",
        d.warnings
    );
}

/// A file holding only the backward (retrace) image is diagnosed from it.
#[test]
fn a_backward_only_file_is_diagnosed() {
    let program = Program {
        frames: vec![spm_formats::ScanDir::Up],
        ..Program::default()
    };
    let paths = write_frames(&program, Hidden::None, 31, "backward-only");
    let file = spm_formats::read_any(&paths[0]).unwrap();
    let backward = file
        .channels
        .iter()
        .find(|c| c.direction() == spm_formats::Direction::Backward)
        .unwrap();
    let gsf = paths[0].with_extension("gsf");
    spm_formats::write_gsf(&gsf, backward, &[]).unwrap();
    let d = run_paths(std::slice::from_ref(&gsf), program.a_nm);
    let _ = std::fs::remove_dir_all(paths[0].parent().unwrap());
    let d = d.unwrap();
    assert!(d.features_used > 300, "{}", summary(&d));
    assert!(d.findings.is_empty(), "{}", summary(&d));
}

/// Writes one `.sxm` frame with the given forward image (backward the same)
/// and scan settings, the header's line times replaced by `line_time_text`
/// when given (the writer refuses what a hostile file may hold); returns its
/// path.
fn write_raw_frame(
    tag: &str,
    pixels: [usize; 2],
    size_nm: [f64; 2],
    line_time_text: Option<&str>,
    image: Vec<f64>,
) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "spm-modelcheck-degenerate-{}-{tag}",
        std::process::id()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    let scan = spm_formats::SxmScan {
        pixels,
        size_nm,
        centre_nm: [0.0, 0.0],
        angle_deg: 0.0,
        line_time_s: [0.08, 0.08],
        scan_dir: spm_formats::ScanDir::Down,
        recorded: spm_formats::DateTime::new(2024, 3, 5, 12, 0, 0).unwrap(),
        bias_v: 0.1,
        comment: String::new(),
        extra_header: Vec::new(),
        channels: vec![spm_formats::SxmChannel {
            name: "Z".into(),
            unit: "m".into(),
            forward: image.clone(),
            backward: Some(image),
        }],
    };
    let path = dir.join("frame.sxm");
    let mut bytes = spm_formats::encode_sxm(&scan, &path).unwrap();
    if let Some(text) = line_time_text {
        let end = bytes.windows(2).position(|w| w == [0x1A, 0x04]).unwrap();
        let header = String::from_utf8(bytes[..end].to_vec()).unwrap();
        let header = header.replace("8.000000E-2", text);
        bytes.splice(..end, header.into_bytes());
    }
    std::fs::write(&path, bytes).unwrap();
    path
}

/// Degenerate and hostile inputs end in a typed error (or, where the data
/// allow, a diagnosis), never a panic or a hang: NaN-filled and constant
/// frames, a 4×4 and a one-line frame, infinite and enormous heights,
/// absurd scan sizes and line times, truncated, empty and random files.
#[test]
fn degenerate_inputs_give_errors_not_panics() {
    let program = Program::default();
    let good = write_frames(&program, Hidden::None, 5, "degenerate-good");
    let lattice = write_frames(&program, Hidden::None, 6, "degenerate-lattice");
    let n = 96;
    let lattice_image = std::fs::read(&lattice[0]).unwrap();
    let mut cases: Vec<(&str, PathBuf)> = vec![
        (
            "nan",
            write_raw_frame("nan", [n, n], [4.8, 4.8], None, vec![f64::NAN; n * n]),
        ),
        (
            "constant",
            write_raw_frame("constant", [n, n], [4.8, 4.8], None, vec![1e-9; n * n]),
        ),
        (
            "4x4",
            write_raw_frame("4x4", [4, 4], [0.2, 0.2], None, vec![0.0; 16]),
        ),
        (
            "one-line",
            write_raw_frame("one-line", [n, 1], [4.8, 0.05], None, vec![0.0; n]),
        ),
        (
            "infinite",
            write_raw_frame(
                "infinite",
                [n, n],
                [4.8, 4.8],
                None,
                (0..n * n)
                    .map(|k| if k % 7 == 0 { f64::INFINITY } else { 1e-10 })
                    .collect(),
            ),
        ),
        (
            "enormous",
            write_raw_frame(
                "enormous",
                [n, n],
                [4.8, 4.8],
                None,
                (0..n * n).map(|k| 1e30 * (k % 3) as f64).collect(),
            ),
        ),
        (
            "tiny-size",
            write_raw_frame(
                "tiny-size",
                [n, n],
                [1e-9, 1e-9],
                None,
                (0..n * n).map(|k| ((k % 5) as f64) * 1e-11).collect(),
            ),
        ),
        (
            "nan-line-time",
            write_raw_frame(
                "nan-line-time",
                [n, n],
                [4.8, 4.8],
                Some("NaN"),
                (0..n * n).map(|k| ((k % 5) as f64) * 1e-11).collect(),
            ),
        ),
        (
            "zero-line-time",
            write_raw_frame(
                "zero-line-time",
                [n, n],
                [4.8, 4.8],
                Some("0.000000E0"),
                (0..n * n).map(|k| ((k % 5) as f64) * 1e-11).collect(),
            ),
        ),
    ];
    let dir = std::env::temp_dir().join(format!(
        "spm-modelcheck-degenerate-{}-files",
        std::process::id()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    for (name, bytes) in [
        (
            "truncated.sxm",
            lattice_image[..lattice_image.len() / 2].to_vec(),
        ),
        ("empty.sxm", Vec::new()),
        (
            "random.sxm",
            (0..5000u32)
                .map(|k| (k.wrapping_mul(2_654_435_761) >> 13) as u8)
                .collect(),
        ),
        ("header-only.sxm", lattice_image[..2000].to_vec()),
    ] {
        let path = dir.join(name);
        std::fs::write(&path, bytes).unwrap();
        cases.push((name, path));
    }
    for (name, path) in &cases {
        // Alone, and beside a good frame (a bad file must not be skipped
        // silently, nor poison the good one into a panic).
        for paths in [vec![path.clone()], vec![good[0].clone(), path.clone()]] {
            let result = run_paths(&paths, program.a_nm);
            if let Ok(d) = &result {
                assert!(
                    d.final_report.rms_pm.is_finite() && d.baseline.rms_pm.is_finite(),
                    "{name}: {}",
                    summary(d)
                );
                // A frame that gave nothing is named, not dropped silently.
                assert!(
                    d.warnings.iter().any(|w| w.contains("frame 1")),
                    "{name}: {:?}",
                    d.warnings
                );
            }
            println!(
                "{name} ({} files): {:?}",
                paths.len(),
                result.map(|d| summary(&d))
            );
            // The same files claimed as Si(111)-7×7 (the cell localiser's path).
            if let Ok(d) = run_paths(&paths, spm_modelcheck::SI7X7_A_NM) {
                assert!(d.final_report.rms_pm.is_finite(), "{name}: {}", summary(&d));
            }
        }
    }
    // The frames with no lattice at all are refused, not diagnosed.
    for name in [
        "nan",
        "constant",
        "random.sxm",
        "empty.sxm",
        "truncated.sxm",
    ] {
        let path = &cases.iter().find(|c| c.0 == name).unwrap().1;
        assert!(
            run_paths(std::slice::from_ref(path), program.a_nm).is_err(),
            "{name} was diagnosed"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
    // A lattice sampled too coarsely to localise atoms (2.5 px per lattice
    // constant) is refused as unresolved, with the reason in pixels.
    let coarse = Program {
        pixels: 64,
        size_nm: 6.4,
        ..Program::default()
    };
    let paths = write_frames(&coarse, Hidden::None, 7, "degenerate-coarse");
    match run_paths(&paths, coarse.a_nm) {
        Err(
            ModelCheckError::NotTheLattice { reason, .. }
            | ModelCheckError::Unresolved { reason, .. },
        ) => assert!(reason.contains(" px"), "{reason}"),
        other => panic!("{:?}", other.map(|d| summary(&d))),
    }
}

/// A fast-SPM-like movie: many short frames, fast axis driven sinusoidally.
/// `FRAMES=40 cargo test -p spm-modelcheck --test it image::explore_movie -- --ignored --nocapture`
#[test]
#[ignore = "exploration: a long movie"]
fn explore_movie() {
    let frames: usize = std::env::var("FRAMES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(20);
    let program = Program {
        pixels: 64,
        size_nm: 3.2,
        line_time_s: 0.002,
        frames: alternating_frames(frames),
        gap_s: 0.0,
        ..Program::default()
    };
    let started = std::time::Instant::now();
    let d = run(&program, Hidden::SineDrive { beta_rad: 1.2 }, 1, "movie");
    println!(
        "{frames} frames in {:?}: {}",
        started.elapsed(),
        summary(&d)
    );
}

/// Clean sets over a sweep of scan programs (pixels, size, noise,
/// corrugation, rotation, line time): any finding is printed.
/// `cargo test -p spm-modelcheck --test it image::explore_clean_sweep -- --ignored --nocapture`
#[test]
#[ignore = "exploration: clean sets over many scan programs"]
fn explore_clean_sweep() {
    let mut case = 0u64;
    for pixels in [64usize, 128, 200] {
        for (size_nm, noise_nm, corrugation_nm) in
            [(3.0, 0.001, 0.02), (6.0, 0.003, 0.05), (10.0, 0.002, 0.03)]
        {
            case += 1;
            let program = Program {
                pixels,
                size_nm,
                z_noise_nm: noise_nm,
                corrugation_nm,
                rotation_rad: 0.37 * case as f64,
                line_time_s: 0.02 * (1 + case % 4) as f64,
                ..Program::default()
            };
            let paths = write_frames(&program, Hidden::None, 2000 + case, "clean-sweep");
            let d = match run_paths(&paths, program.a_nm) {
                Ok(d) => d,
                Err(e) => {
                    println!("px {pixels} size {size_nm}: {e}");
                    continue;
                }
            };
            println!(
                "px {pixels} size {size_nm} noise {noise_nm} corr {corrugation_nm}: findings {:?} unexplained {} {:?}; baseline {:.2} pm σloc {:.2}",
                d.effects_found(),
                d.unexplained,
                d.residual_structure.reasons,
                d.baseline.rms_pm,
                d.localisation_sigma_pm
            );
        }
    }
}
