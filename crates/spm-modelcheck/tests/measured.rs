//! The diagnosis on real measured images (../shared/data/measured): it runs,
//! serialises to the DESIGN §13 keys, and reports what docs/MODELCHECK.md says.
#![allow(clippy::unwrap_used)]

use spm_modelcheck::{ExtractOptions, ImageInput, LatticeSpec, Options, diagnose};

fn run(files: &[&str], lattice: &str) -> spm_modelcheck::Diagnosis {
    let inputs: Vec<ImageInput> = files
        .iter()
        .map(|f| ImageInput {
            path: spmcal_tests::measured_file(f),
            start_time_s: None,
        })
        .collect();
    diagnose(
        &inputs,
        &LatticeSpec::parse(lattice).unwrap(),
        &Options::default(),
        &ExtractOptions::default(),
    )
    .unwrap()
}

#[test]
fn si7x7_051_forward_backward_needs_more_than_the_baseline() {
    let d = run(&["si7x7-nanonis/Si_7x7_051.sxm"], "si7x7");
    assert!(d.features_used > 40);
    // Trace and retrace disagree: the baseline is not enough.
    assert!(!d.findings.is_empty());
    assert!(d.final_report.heldout_rms_pm < d.baseline.heldout_rms_pm);
    let json = serde_json::to_value(&d).unwrap();
    assert!(json["final"]["rms_pm"].is_number());
}

#[test]
fn the_si7x7_drift_pair_is_not_one_lattice_under_one_smooth_map() {
    let d = run(
        &[
            "si7x7-nanonis/Si_7x7_028.sxm",
            "si7x7-nanonis/Si_7x7_032.sxm",
        ],
        "si7x7",
    );
    assert_eq!(d.frames.len(), 2);
    // Frames 8 min 46 s apart: the record times put them on one time axis.
    assert!(d.features_used > 300);
    assert!(
        d.unexplained,
        "the residual stays far above the localisation noise"
    );
}

#[test]
fn the_graphite_sm4_pair_has_too_few_atoms_for_any_finding() {
    let d = run(
        &["graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4"],
        "hopg",
    );
    assert!(d.features_used >= 10);
    assert!(d.findings.is_empty());
}

#[test]
fn the_hopg_terrace_shows_distortion_beyond_the_lumped_scanner() {
    let d = run(&["hopg-terrace-iso28600/graphiteterrace.spm"], "hopg");
    assert!(d.features_used > 500);
    assert!(!d.findings.is_empty());
    // No timing in the file: constant drift cannot be told from the scanner.
    assert!(!d.baseline.drift_separable);
}
