//! Nanonis TCP overhead (issue 14): the same calibration job (sim-hopg, the small HOPG plan)
//! run in process and over loopback TCP against `nanonis-sim` (spm-nanonis ↔
//! spm-nanonis-sim), wall time per node of each and their ratio (target ≤ 1.5×). Each side
//! is run `repeats` times and its fastest run kept (the machine is shared).

use super::Context;
use crate::XtaskError;
use serde::Serialize;
use spm_calibration::NoObserver;
use spm_nanonis::NanonisConfig;
use spm_nanonis_sim::{Server, ServerConfig, SocketFaults};
use spm_sim::SimConfig;
use spmcal::job::{Backend, Job};
use spmcal::run::{RecordingObserver, RunStart, run_job};
use std::path::Path;
use std::time::Instant;

/// The figures.
#[derive(Debug, Serialize)]
pub struct NanonisResults {
    /// Nodes of the net (visits of the one pass).
    pub nodes: usize,
    /// Runs per side (the fastest is kept).
    pub repeats: usize,
    /// In process: wall time per node, ms.
    pub in_process_ms_per_node: f64,
    /// Over loopback TCP: wall time per node, ms.
    pub tcp_ms_per_node: f64,
    /// TCP ÷ in process.
    pub ratio: f64,
    /// Protocol commands per node over TCP.
    pub commands_per_node: f64,
    /// Round trips per node over TCP: the commands less those the client pipelined behind
    /// another (`ServerStats::pipelined`).
    pub round_trips_per_node: f64,
    /// Protocol commands per node over TCP, per command name (where the round trips go).
    pub commands_per_node_by_name: std::collections::BTreeMap<String, f64>,
    /// Simulated instrument time per node, s (the same on both sides).
    pub instrument_s_per_node: f64,
    /// One protocol round trip alone: the median wall time of a `Scan.StatusGet` (a query
    /// that executes nothing) to an otherwise idle nanonis-sim, µs.
    pub round_trip_us: f64,
}

/// nanonis-sim on `sim`, no socket faults, on a free loopback port.
fn serve(sim: &SimConfig) -> Result<spm_nanonis_sim::server::ServerHandle, XtaskError> {
    Server::bind(
        "127.0.0.1:0",
        sim.clone(),
        ServerConfig::new(SocketFaults::none()),
    )
    .and_then(Server::spawn)
    .map_err(|e| XtaskError::step("starting nanonis-sim", e))
}

/// The median wall time of one `Scan.StatusGet` round trip, µs (2000 after 200 to warm up).
fn round_trip_us(sim: &SimConfig) -> Result<f64, XtaskError> {
    let server = serve(sim)?;
    let mut client =
        spm_nanonis::Client::connect(nanonis_config(server.addr().port()).client_config())
            .map_err(|e| XtaskError::step("connecting to nanonis-sim", e))?;
    let mut times_us = Vec::with_capacity(2000);
    for k in 0..2200 {
        let started = Instant::now();
        client
            .call(&spm_nanonis::commands::Request::ScanStatusGet)
            .map_err(|e| XtaskError::step("Scan.StatusGet", e))?;
        if k >= 200 {
            times_us.push(started.elapsed().as_secs_f64() * 1e6);
        }
    }
    server.kill();
    spm_regression::upper_median(&mut times_us)
        .ok_or_else(|| XtaskError::step("Scan.StatusGet", "no round trip timed"))
}

fn nanonis_config(port: u16) -> NanonisConfig {
    NanonisConfig {
        connect_timeout_s: 2.0,
        command_timeout_s: 10.0,
        wait_margin_s: 10.0,
        reconnect_attempts: 3,
        reconnect_backoff_s: 0.05,
        ..spm_nanonis_sim::loopback_config(port)
    }
}

/// One run: (wall time s, nodes, instrument time s).
fn timed_run(job: &Job, dir: &Path, name: &str) -> Result<(f64, usize, f64), XtaskError> {
    let cdb = dir.join(format!("{name}.sqlite"));
    let mut quiet = NoObserver;
    let mut recorder = RecordingObserver::new(&mut quiet);
    let started = Instant::now();
    let outcome = run_job(
        job,
        &cdb,
        RunStart::New {
            run_id: name.to_owned(),
        },
        1_800_000_000.0,
        &mut recorder,
    )
    .map_err(|e| XtaskError::step(format!("nanonis bench run {name}"), e))?;
    let wall_s = started.elapsed().as_secs_f64();
    Ok((
        wall_s,
        outcome.report.visits_planned,
        outcome.report.instrument_time_s,
    ))
}

/// Runs the comparison.
pub fn run(ctx: &Context) -> Result<NanonisResults, XtaskError> {
    let dir = ctx.scratch("nanonis")?;
    let sim_path = ctx.root.join("configs/sim-hopg.toml");
    let sim = SimConfig::from_file(&sim_path)
        .map_err(|e| XtaskError::step(format!("reading {}", sim_path.display()), e))?;
    let (plan, plan_text) = Job::read_plan(&ctx.root.join("configs/plan-hopg-small.toml"))
        .map_err(|e| XtaskError::step("reading plan-hopg-small.toml", e))?;
    let repeats = if ctx.quick { 1 } else { 3 };
    let local = Job {
        backend: Backend::Sim(Box::new(sim.clone())),
        plan: plan.clone(),
        provenance_text: plan_text.clone(),
    };
    let mut best_local = f64::INFINITY;
    let mut best_tcp = f64::INFINITY;
    let (mut nodes, mut instrument_s) = (0, 0.0);
    let mut stats = spm_nanonis_sim::ServerStats::default();
    for k in 0..repeats {
        let (wall, n, t) = timed_run(&local, &dir, &format!("local-{k}"))?;
        best_local = best_local.min(wall);
        (nodes, instrument_s) = (n, t);
        let server = serve(&sim)?;
        let tcp = Job {
            backend: Backend::Nanonis(Box::new(nanonis_config(server.addr().port()))),
            plan: plan.clone(),
            provenance_text: plan_text.clone(),
        };
        let (wall, _, _) = timed_run(&tcp, &dir, &format!("tcp-{k}"))?;
        best_tcp = best_tcp.min(wall);
        stats = server.stats();
        server.kill();
    }
    let per_node = |s: f64| 1e3 * s / nodes.max(1) as f64;
    let round_trip_us = round_trip_us(&sim)?;
    Ok(NanonisResults {
        nodes,
        repeats,
        in_process_ms_per_node: per_node(best_local),
        tcp_ms_per_node: per_node(best_tcp),
        ratio: best_tcp / best_local,
        commands_per_node: stats.commands as f64 / nodes.max(1) as f64,
        round_trips_per_node: (stats.commands - stats.pipelined) as f64 / nodes.max(1) as f64,
        commands_per_node_by_name: stats
            .commands_by_name
            .iter()
            .map(|(name, n)| (name.clone(), *n as f64 / nodes.max(1) as f64))
            .collect(),
        instrument_s_per_node: instrument_s / nodes.max(1) as f64,
        round_trip_us,
    })
}

#[cfg(test)]
mod tests {
    /// `cargo test -p xtask --release nanonis_overhead -- --ignored --nocapture`: the figure
    /// alone, without the whole bench.
    #[test]
    #[ignore = "a timing measurement, not a test; run on demand"]
    fn nanonis_overhead() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .parent()
            .map(std::path::Path::to_path_buf)
            .unwrap_or_default();
        let ctx = super::Context {
            out: root.join("target/bench-nanonis"),
            root,
            quick: false,
            write_docs: false,
        };
        match super::run(&ctx) {
            Ok(r) => println!("{r:#?}"),
            Err(e) => panic!("{e}"),
        }
    }
}
