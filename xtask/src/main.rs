//! Project automation for spmcal: `cargo xtask calibrate | bench`.
//!
//! `cargo xtask` is an alias (see `.cargo/config.toml`) for
//! `cargo run --package xtask --release --`.

mod bench;
mod calibrate;

use clap::{Parser, Subcommand};
use std::path::PathBuf;

#[derive(Debug, Parser)]
#[command(name = "xtask", about = "spmcal project automation")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// The main job: a full simulated calibration with a report.
    Calibrate {
        /// A job file, or a simulated-microscope config (TOML); default
        /// configs/calibrate-hopg.toml (--quick: configs/calibrate-hopg-quick.toml).
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// Output folder.
        #[arg(long, value_name = "DIR", default_value = "target/spmcal/calibrate")]
        out: PathBuf,
        /// The calibration plan, when --config is a simulator config
        /// (default configs/plan-hopg.toml; --quick: configs/plan-hopg-small.toml).
        #[arg(long, value_name = "FILE")]
        plan: Option<PathBuf>,
        /// A reduced run that takes seconds.
        #[arg(long)]
        quick: bool,
    },
    /// Benchmarks: writes results.json and figures into --out (and docs/ with --write-docs).
    Bench {
        /// A reduced run.
        #[arg(long)]
        quick: bool,
        /// Also run the Gwyddion side-by-side comparison.
        #[arg(long)]
        gwyddion: bool,
        /// Output folder for results.json.
        #[arg(long, value_name = "DIR", default_value = "target/bench")]
        out: PathBuf,
        /// Regenerate the committed docs/RESULTS.md and docs/results/bench/ from this run
        /// (never with --quick; without this flag nothing under docs/ is touched).
        #[arg(long, conflicts_with = "quick")]
        write_docs: bool,
    },
}

fn main() {
    let cli = Cli::parse();
    let workspace_root = workspace_root();
    let result = match cli.command {
        Command::Calibrate {
            config,
            plan,
            out,
            quick,
        } => calibrate::run(
            &workspace_root,
            &calibrate::CalibrateArgs {
                config: config.map(|c| workspace_root.join(c)),
                plan: plan.map(|p| workspace_root.join(p)),
                out: workspace_root.join(out),
                quick,
            },
        ),
        Command::Bench {
            quick,
            gwyddion,
            out,
            write_docs,
        } => bench::run(
            &workspace_root,
            &workspace_root.join(out),
            bench::Options {
                quick,
                with_gwyddion: gwyddion,
                write_docs,
            },
        ),
    };
    if let Err(error) = result {
        eprintln!("xtask: error: {error}");
        std::process::exit(1);
    }
}

/// The workspace root (the parent of this crate's folder), so relative paths
/// work from any current directory.
fn workspace_root() -> PathBuf {
    let manifest = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    manifest.parent().map(PathBuf::from).unwrap_or(manifest)
}

/// An error of an xtask job, with what it was doing.
#[derive(Debug, thiserror::Error)]
pub enum XtaskError {
    /// A step failed.
    #[error("{step}: {message}")]
    Step {
        /// What was being done.
        step: String,
        /// Why it failed.
        message: String,
    },
}

impl XtaskError {
    /// A failed step.
    pub fn step(step: impl Into<String>, message: impl std::fmt::Display) -> Self {
        Self::Step {
            step: step.into(),
            message: message.to_string(),
        }
    }
}
