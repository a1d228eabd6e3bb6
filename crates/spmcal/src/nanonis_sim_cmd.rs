//! `spmcal nanonis-sim --port P --config SIM.toml`: the Nanonis TCP protocol over the
//! simulated microscope (see [`spm_nanonis_sim`]), for trying the whole pipeline over a
//! socket without hardware (`configs/calibrate-nanonis-sim.toml`).

use crate::error::CliError;
use spm_nanonis_sim::{Server, ServerConfig, SocketFaults};
use spm_sim::SimConfig;
use std::path::PathBuf;

/// `spmcal nanonis-sim`'s arguments.
#[derive(Debug, clap::Args)]
pub struct NanonisSimArgs {
    /// TCP port (0: any free port, printed).
    #[arg(long, default_value_t = 6501)]
    pub port: u16,
    /// Address to listen on.
    #[arg(long, default_value = "127.0.0.1")]
    pub host: String,
    /// The simulated microscope (spm-sim TOML).
    #[arg(long, value_name = "SIM.toml")]
    pub config: PathBuf,
    /// Host-application release to answer (decides the schema of Scan.PropsSet).
    #[arg(long)]
    pub release: Option<u32>,
    /// Probability per command of a socket fault (error reply, 1-byte writes, delay,
    /// stall, dropped connection, a scan left running).
    #[arg(long, default_value_t = 0.0)]
    pub fault_rate: f64,
    /// Seed of the fault generator.
    #[arg(long, default_value_t = 1)]
    pub fault_seed: u64,
    /// Delay of a delayed reply, s.
    #[arg(long, default_value_t = 0.05)]
    pub fault_delay_s: f64,
    /// Delay of a stalled reply, s.
    #[arg(long, default_value_t = 5.0)]
    pub fault_stall_s: f64,
    /// Connections served at once; one more is accepted and closed at once.
    #[arg(long, default_value_t = spm_nanonis_sim::ConnectionLimits::default().max_connections)]
    pub max_connections: usize,
    /// A request must arrive whole within this time of its first byte, s.
    #[arg(long, default_value_t = spm_nanonis_sim::ConnectionLimits::default().message_timeout_s)]
    pub message_timeout_s: f64,
    /// A connection idle this long between requests is closed, s.
    #[arg(long, default_value_t = spm_nanonis_sim::ConnectionLimits::default().idle_timeout_s)]
    pub idle_timeout_s: f64,
    /// The largest request body accepted, bytes (a larger one closes the connection).
    #[arg(long, default_value_t = spm_nanonis_sim::ConnectionLimits::default().max_request_body_bytes)]
    pub max_request_bytes: usize,
}

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

pub fn run(args: &NanonisSimArgs) -> Result<(), CliError> {
    let faults = &FaultOptions {
        rate: args.fault_rate,
        seed: args.fault_seed,
        delay_s: args.fault_delay_s,
        stall_s: args.fault_stall_s,
    };
    let limits = spm_nanonis_sim::ConnectionLimits {
        max_connections: args.max_connections,
        message_timeout_s: args.message_timeout_s,
        idle_timeout_s: args.idle_timeout_s,
        max_request_body_bytes: args.max_request_bytes,
    };
    let (host, port, config) = (&args.host, args.port, &args.config);
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
    if let Some(release) = args.release {
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
