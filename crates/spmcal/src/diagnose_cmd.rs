//! `spmcal diagnose FILES... --lattice L --json OUT [--png OUT.png]`.

use crate::error::CliError;
use spm_modelcheck::{LatticeSpec, ModelCheckError, Options, diagnose_paths, write_png};
use std::path::{Path, PathBuf};

/// Physical range of a lattice constant, nm: from below the shortest interatomic distance
/// to a coarse calibration grating.
const LATTICE_RANGE_NM: (f64, f64) = (0.05, 1e4);

fn classify(error: ModelCheckError) -> CliError {
    match error {
        ModelCheckError::Numerical(_) | ModelCheckError::Plot { .. } => {
            CliError::RunFailed(error.to_string())
        }
        other => CliError::BadInput(other.to_string()),
    }
}

pub fn run(
    files: &[PathBuf],
    lattice: &str,
    json: &Path,
    png: Option<&Path>,
) -> Result<(), CliError> {
    let lattice =
        LatticeSpec::parse(lattice).map_err(|e| CliError::BadInput(format!("--lattice: {e}")))?;
    let a_nm = lattice.a_nm();
    if !(a_nm.is_finite() && (LATTICE_RANGE_NM.0..=LATTICE_RANGE_NM.1).contains(&a_nm)) {
        return Err(CliError::BadInput(format!(
            "--lattice: lattice constant {a_nm} nm is outside the physical range [{}, {}] nm",
            LATTICE_RANGE_NM.0, LATTICE_RANGE_NM.1
        )));
    }
    for file in files {
        crate::files::check_input(file, "image")?;
    }
    let inputs: Vec<&Path> = files.iter().map(PathBuf::as_path).collect();
    crate::files::check_output(json, "--json", &inputs)?;
    if let Some(png) = png {
        crate::files::check_output(png, "--png", &inputs)?;
        crate::files::check_distinct_outputs(&[("--json", json), ("--png", png)])?;
    }
    let diagnosis = diagnose_paths(files, &lattice, &Options::default()).map_err(classify)?;
    let text = serde_json::to_string_pretty(&diagnosis)
        .map_err(|e| CliError::RunFailed(format!("cannot encode the diagnosis: {e}")))?;
    crate::write_atomically(json, text.as_bytes())?;
    if let Some(png) = png {
        let title = files
            .iter()
            .filter_map(|f| f.file_name().map(|n| n.to_string_lossy().into_owned()))
            .collect::<Vec<_>>()
            .join(" + ");
        write_png(&diagnosis, png, &title).map_err(classify)?;
    }
    for w in &diagnosis.warnings {
        eprintln!("warning: {w}");
    }
    crate::outln!(
        "baseline {:.1} pm → final {:.1} pm; findings: {}; unexplained: {}{}",
        diagnosis.baseline.rms_pm,
        diagnosis.final_report.rms_pm,
        if diagnosis.findings.is_empty() {
            "none".to_owned()
        } else {
            diagnosis
                .findings
                .iter()
                .map(|f| format!("{} (evidence {:.1})", f.effect, f.evidence))
                .collect::<Vec<_>>()
                .join(", ")
        },
        diagnosis.unexplained,
        if diagnosis.residual_structure.reasons.is_empty() {
            String::new()
        } else {
            format!(" ({})", diagnosis.residual_structure.reasons.join("; "))
        }
    );
    Ok(())
}
