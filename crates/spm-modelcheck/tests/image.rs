//! Hidden effects in pixel-sampled images written as Nanonis `.sxm` files and
//! read back (tests/common/image.rs): a generator independent of spm-sim and
//! of the feature-level one, so the localiser's pixel locking, the file
//! timing and the direction conventions are part of what is tested.
#![allow(clippy::unwrap_used)]

mod common;

use common::image::{Hidden, Program, write_frames, write_no_lattice};
use spm_modelcheck::{
    Diagnosis, EffectKind, ExtractOptions, ImageInput, LatticeSpec, ModelCheckError, Options,
    diagnose,
};
use std::path::PathBuf;

fn run_paths(paths: &[PathBuf], a_nm: f64) -> Result<Diagnosis, ModelCheckError> {
    let inputs: Vec<ImageInput> = paths
        .iter()
        .map(|p| ImageInput {
            path: p.clone(),
            start_time_s: None,
        })
        .collect();
    diagnose(
        &inputs,
        &LatticeSpec::Hex { a_nm },
        &Options::default(),
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
        "baseline {:.2} pm (sep {}) → final {:.2} pm; used {} ({} outliers, {} unindexed); findings {:?}; unexplained {} {:?}; rejected {:?}; round 0 {:?}; pl {:?}",
        d.baseline.rms_pm,
        d.baseline.drift_separable,
        d.final_report.rms_pm,
        d.features_used,
        d.outliers,
        d.unindexed,
        d.findings
            .iter()
            .map(|f| (
                f.effect.clone(),
                f.evidence.round(),
                f.parameters
                    .iter()
                    .map(|(k, v)| format!("{k}={:.4e}±{:.1e}", v.value, v.sigma))
                    .collect::<Vec<_>>()
            ))
            .collect::<Vec<_>>(),
        d.unexplained,
        d.residual_structure.reasons,
        d.rejected
            .iter()
            .map(|r| format!(
                "{} {:.0} {:.2}pm {}",
                r.effect, r.evidence, r.explained_rms_pm, r.reason
            ))
            .collect::<Vec<_>>(),
        d.rounds.first().map(|r| r
            .iter()
            .map(|c| (c.effect.clone(), c.evidence.round()))
            .collect::<Vec<_>>()),
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
