//! Runs the diagnosis on the measured datasets of `../shared/data/measured/`
//! and writes `docs/modelcheck/<dataset>.json` and `.png`.
//!
//! `cargo run -p spm-modelcheck --example measured [DATASET…]`
//! (datasets: si7x7-drift-pair, si7x7-028, si7x7-032, si7x7-051, si7x7-012,
//! si7x7-raw-defects, si7x7-raw-step-edge, si7x7-raw-step-edge-atoms, graphite-sm4,
//! hopg-terrace; default all). A refused dataset gets `{"refused": REASON}` as its JSON:
//! the refusal is its verdict.
#![allow(clippy::unwrap_used)]

use spm_modelcheck::{ExtractOptions, ImageInput, LatticeSpec, Options, diagnose, write_png};
use std::path::PathBuf;

fn datasets() -> Vec<(&'static str, &'static str, Vec<&'static str>)> {
    vec![
        (
            "si7x7-drift-pair",
            "si7x7",
            vec![
                "si7x7-nanonis/Si_7x7_028.sxm",
                "si7x7-nanonis/Si_7x7_032.sxm",
            ],
        ),
        ("si7x7-028", "si7x7", vec!["si7x7-nanonis/Si_7x7_028.sxm"]),
        ("si7x7-032", "si7x7", vec!["si7x7-nanonis/Si_7x7_032.sxm"]),
        ("si7x7-051", "si7x7", vec!["si7x7-nanonis/Si_7x7_051.sxm"]),
        ("si7x7-012", "si7x7", vec!["si7x7-nanonis/Si_7x7_012.sxm"]),
        (
            "si7x7-raw-defects",
            "si7x7",
            vec!["si7x7-raw/image_with_defects.dat"],
        ),
        (
            "si7x7-raw-step-edge",
            "si7x7",
            vec!["si7x7-raw/image_with_step_edge.dat"],
        ),
        (
            "si7x7-raw-step-edge-atoms",
            "si7x7",
            vec!["si7x7-raw/image_with_step_edge_and_atoms.dat"],
        ),
        (
            "graphite-sm4",
            "hopg",
            vec!["graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4"],
        ),
        (
            "hopg-terrace",
            "hopg",
            vec!["hopg-terrace-iso28600/graphiteterrace.spm"],
        ),
    ]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let wanted: Vec<String> = std::env::args().skip(1).collect();
    let out = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../docs/modelcheck");
    std::fs::create_dir_all(&out)?;
    for (name, lattice, files) in datasets() {
        if !wanted.is_empty() && !wanted.iter().any(|w| w == name) {
            continue;
        }
        let inputs: Vec<ImageInput> = files
            .iter()
            .map(|f| ImageInput {
                path: spmcal_tests::measured_file(f),
                start_time_s: None,
            })
            .collect();
        let lattice = LatticeSpec::parse(lattice)?;
        let started = std::time::Instant::now();
        match diagnose(
            &inputs,
            &lattice,
            &Options::default(),
            &ExtractOptions::default(),
        ) {
            Ok(d) => {
                let json = serde_json::to_string_pretty(&d)?;
                std::fs::write(out.join(format!("{name}.json")), &json)?;
                write_png(&d, out.join(format!("{name}.png")), name)?;
                println!(
                    "== {name} ({:.1} s): {} features used, {} outliers, {} unindexed",
                    started.elapsed().as_secs_f64(),
                    d.features_used,
                    d.outliers,
                    d.unindexed
                );
                println!("{json}");
            }
            Err(e) => {
                let json = serde_json::to_string_pretty(&serde_json::json!({
                    "refused": e.to_string(),
                    "error": format!("{e:?}").split([' ', '{', '(']).next().unwrap_or(""),
                }))?;
                std::fs::write(out.join(format!("{name}.json")), &json)?;
                println!("== {name}: refused: {e}");
            }
        }
    }
    Ok(())
}
