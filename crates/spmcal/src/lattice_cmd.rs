//! `spmcal lattice FILE... --standard hopg|si7x7 [--grid N] [--json]`: the lattice of a
//! standard measured on images (the before and after of a correction, issue 24).

use crate::error::CliError;
use spm_calibration::StandardName;
use spmcal::virtual_mode::{ImageLattice, survey_lattice};
use std::path::PathBuf;

fn text(lattice: Option<&ImageLattice>, a: f64) -> String {
    match lattice {
        Some(l) => format!(
            "a {:.4} nm ({:+.2} %), sides {:.4} / {:.4} nm, angle {:.2}°, {} features",
            l.mean_length_nm(),
            100.0 * (l.mean_length_nm() / a - 1.0),
            l.lengths_nm[0],
            l.lengths_nm[1],
            l.acute_angle_deg(),
            l.features
        ),
        None => "no lattice found".to_owned(),
    }
}

pub fn run(
    files: &[PathBuf],
    standard: StandardName,
    grid: usize,
    channel: Option<&str>,
    json: bool,
) -> Result<(), CliError> {
    if !(1..=16).contains(&grid) {
        return Err(CliError::BadInput(format!(
            "--grid {grid}: give 1 to 16 cells per side"
        )));
    }
    let mut surveys = Vec::with_capacity(files.len());
    for file in files {
        crate::files::check_input(file, "image")?;
        surveys.push(
            survey_lattice(file, standard, channel, grid)
                .map_err(|e| CliError::BadInput(e.to_string()))?,
        );
    }
    if json {
        let text = serde_json::to_string_pretty(&surveys)
            .map_err(|e| CliError::RunFailed(e.to_string()))?;
        crate::outln!("{text}");
        return Ok(());
    }
    for s in &surveys {
        let a = s.lattice_constant_nm;
        crate::outln!("{}: {} (a = {a} nm)", s.file.display(), s.standard);
        crate::outln!("  whole image: {}", text(s.whole.as_ref(), a));
        for c in &s.cells {
            crate::outln!(
                "  cell ({}, {}): {}",
                c.column,
                c.row,
                text(c.lattice.as_ref(), a)
            );
        }
        let found: Vec<&ImageLattice> = s.cells.iter().filter_map(|c| c.lattice.as_ref()).collect();
        if !found.is_empty() {
            let worst_a = found
                .iter()
                .map(|l| (l.mean_length_nm() / a - 1.0).abs())
                .fold(0.0, f64::max);
            let worst_angle = found
                .iter()
                .map(|l| (l.acute_angle_deg() - 60.0).abs())
                .fold(0.0, f64::max);
            crate::outln!(
                "  {} of {} cells: largest |a error| {:.2} %, largest |angle − 60°| {:.2}°",
                found.len(),
                s.cells.len(),
                100.0 * worst_a,
                worst_angle
            );
        }
    }
    Ok(())
}
