//! `spmcal lattice FILE... --standard hopg|si7x7 [--grid N] [--json]`: the lattice of a
//! standard measured on images (the before and after of a correction, issue 24).

use crate::error::CliError;
use spm_calibration::StandardName;
use spmcal::virtual_mode::{PartLattice, survey_lattice};
use std::path::PathBuf;

fn text(lattice: Option<&PartLattice>) -> String {
    match lattice {
        Some(l) => format!(
            "scale x {:.3} ± {:.3}, scale y {:.3} ± {:.3}, obliquity {:+.2}° ± {:.2}°, {} features{}",
            l.scale_x,
            l.scale_x_sigma,
            l.scale_y,
            l.scale_y_sigma,
            l.obliquity_deg,
            l.obliquity_sigma_deg,
            l.features,
            if l.features_left_out > 0 {
                format!(" ({} left out: not lattice sites)", l.features_left_out)
            } else {
                String::new()
            }
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
        crate::outln!(
            "{}: {} (a = {} nm)",
            s.file.display(),
            s.standard,
            s.lattice_constant_nm
        );
        crate::outln!("  whole image: {}", text(s.whole.as_ref()));
        for c in &s.cells {
            crate::outln!(
                "  cell ({}, {}): {}",
                c.column,
                c.row,
                text(c.lattice.as_ref())
            );
        }
        let found: Vec<&PartLattice> = s.cells.iter().filter_map(|c| c.lattice.as_ref()).collect();
        if !found.is_empty() {
            let worst_scale = found
                .iter()
                .flat_map(|l| [l.scale_x, l.scale_y])
                .map(|v| (v - 1.0).abs())
                .fold(0.0, f64::max);
            let worst_obliquity = found
                .iter()
                .map(|l| l.obliquity_deg.abs())
                .fold(0.0, f64::max);
            crate::outln!(
                "  {} of {} cells: largest |scale − 1| {:.2} %, largest |obliquity| {:.2}°",
                found.len(),
                s.cells.len(),
                100.0 * worst_scale,
                worst_obliquity
            );
        }
    }
    Ok(())
}
