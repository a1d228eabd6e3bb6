//! `spmcal simulate --like FILE --config SIM.toml --out OUT.sxm` (see
//! [`spmcal::simulate`]).

use crate::error::CliError;
use spm_formats::{encode_sxm, read_any};
use spm_sim::SimConfig;
use spmcal::simulate::{SimulateError, scan_program, simulate};
use std::path::Path;

fn cli(e: SimulateError) -> CliError {
    match e {
        SimulateError::BadInput(m) => CliError::BadInput(m),
        other => CliError::RunFailed(other.to_string()),
    }
}

pub fn run(
    like: &Path,
    config: &Path,
    out: &Path,
    nominal_nm_per_count: Option<f64>,
) -> Result<(), CliError> {
    crate::files::check_input(like, "--like")?;
    crate::files::check_input(config, "--config")?;
    crate::files::check_output(out, "--out", &[like, config])?;
    let file = read_any(like).map_err(|e| CliError::BadInput(e.to_string()))?;
    let program = scan_program(&file).map_err(cli)?;
    let text = std::fs::read_to_string(config).map_err(|source| CliError::Io {
        path: config.to_path_buf(),
        source,
    })?;
    let sim_config = SimConfig::from_toml_str(&text, &config.display().to_string())
        .map_err(|e| CliError::BadInput(e.to_string()))?;
    let scan = simulate(&program, sim_config, nominal_nm_per_count).map_err(cli)?;
    let bytes = encode_sxm(&scan, out).map_err(|e| CliError::RunFailed(e.to_string()))?;
    crate::write_atomically(out, &bytes)?;
    crate::outln!(
        "simulated {}×{} pixels, {:.3} nm, {} s per line, {} → {}",
        program.pixels[0],
        program.pixels[1],
        program.size_nm[0],
        program.line_time_s,
        program.scan_dir.as_str(),
        out.display()
    );
    Ok(())
}
