//! `spmcal nanonis-sim --port P --config SIM.toml`: the Nanonis TCP protocol over the
//! simulated microscope (see [`spm_nanonis_sim`]), for trying the whole pipeline over a
//! socket without hardware (`configs/calibrate-nanonis-sim.toml`).

use crate::error::CliError;
use spm_nanonis_sim::{Server, ServerConfig, SocketFaults};
use spm_sim::SimConfig;
use std::path::Path;

/// Socket-fault options of the command line.
pub struct FaultOptions {
    /// Probability per command of a socket fault (0 = none).
    pub rate: f64,
    /// Seed of the fault generator.
    pub seed: u64,
    /// Delay of a delayed reply, s.
    pub delay_s: f64,
    /// Delay of a stalled reply, s (longer than the client's timeout to exercise it).
    pub stall_s: f64,
}

pub fn run(
    host: &str,
    port: u16,
    config: &Path,
    release: Option<u32>,
    faults: &FaultOptions,
    limits: spm_nanonis_sim::ConnectionLimits,
) -> Result<(), CliError> {
    crate::files::check_input(config, "--config")?;
    let sim = SimConfig::from_file(config).map_err(|e| CliError::BadInput(e.to_string()))?;
    if !(0.0..=1.0).contains(&faults.rate) {
        return Err(CliError::BadInput(format!(
            "--fault-rate {} must lie in [0, 1]",
            faults.rate
        )));
    }
    let mut server_config = ServerConfig::new(SocketFaults::mixed(
        faults.rate,
        faults.seed,
        faults.delay_s,
        faults.stall_s,
    ));
    if let Some(release) = release {
        server_config.host_release = release;
    }
    server_config.limits = limits;
    let server = Server::bind(&format!("{host}:{port}"), sim, server_config)
        .map_err(|e| CliError::BadInput(e.to_string()))?;
    let address = server
        .local_addr()
        .map_err(|e| CliError::RunFailed(e.to_string()))?;
    crate::outln!("nanonis-sim: listening on {address}");
    server
        .serve()
        .map_err(|e| CliError::RunFailed(e.to_string()))
}
