//! `cargo xtask calibrate`: the main job. It runs `spmcal calibrate` itself (the same code
//! path a user runs) on the embedded defaults: `configs/calibrate-hopg.toml` (the simulated
//! room-temperature tube scanner over HOPG with `configs/plan-hopg.toml`), or with `--quick`
//! `configs/calibrate-hopg-quick.toml` (a 3 × 3 net), into a fresh CDB in the output folder,
//! with the image benchmark.
//!
//! `--config SIM.toml [--plan PLAN.toml]` (a simulator config rather than a job file) writes a
//! job file naming both into the output folder and runs that.

use crate::XtaskError;
use std::path::{Path, PathBuf};
use std::process::Command;

/// What to calibrate.
pub struct CalibrateArgs {
    /// A job file, or a simulator config (then `plan` or the default plan).
    pub config: Option<PathBuf>,
    /// The plan when `config` is a simulator config.
    pub plan: Option<PathBuf>,
    /// Output folder.
    pub out: PathBuf,
    /// Smoke run.
    pub quick: bool,
}

pub fn run(root: &Path, args: &CalibrateArgs) -> Result<(), XtaskError> {
    let out = &args.out;
    std::fs::create_dir_all(out)
        .map_err(|e| XtaskError::step(format!("creating {}", out.display()), e))?;
    let job = job_file(root, args)?;
    // A fresh CDB for every job.
    for suffix in ["", "-wal", "-shm"] {
        let path = out.join(format!("cdb.sqlite{suffix}"));
        if path.exists() {
            std::fs::remove_file(&path)
                .map_err(|e| XtaskError::step(format!("removing {}", path.display()), e))?;
        }
    }
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let mut command = Command::new(cargo);
    command
        .current_dir(root)
        .args(["run", "--release", "--quiet", "--package", "spmcal", "--"])
        .arg("calibrate")
        .arg("--config")
        .arg(&job)
        .arg("--out")
        .arg(out)
        .arg("--image-benchmark");
    if args.quick {
        command.arg("--quick");
    }
    println!(
        "== spmcal calibrate --config {} --out {}",
        job.display(),
        out.display()
    );
    let status = command
        .status()
        .map_err(|e| XtaskError::step("running spmcal calibrate", e))?;
    if status.success() {
        Ok(())
    } else {
        Err(XtaskError::step(
            "spmcal calibrate",
            format!("exited with {status}"),
        ))
    }
}

/// The job file to run: the one given, the default, or one written for a simulator config.
fn job_file(root: &Path, args: &CalibrateArgs) -> Result<PathBuf, XtaskError> {
    let default_job = root.join(if args.quick {
        "configs/calibrate-hopg-quick.toml"
    } else {
        "configs/calibrate-hopg.toml"
    });
    let Some(config) = &args.config else {
        return Ok(default_job);
    };
    let text = std::fs::read_to_string(config)
        .map_err(|e| XtaskError::step(format!("reading {}", config.display()), e))?;
    let is_job = text
        .parse::<toml::Table>()
        .is_ok_and(|t| t.contains_key("backend"));
    if is_job {
        return Ok(config.clone());
    }
    let plan = args.plan.clone().unwrap_or_else(|| {
        root.join(if args.quick {
            "configs/plan-hopg-small.toml"
        } else {
            "configs/plan-hopg.toml"
        })
    });
    let absolute = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    let job_text = format!(
        "# Written by cargo xtask calibrate for a simulator config and a plan.\n\
         plan_file = {:?}\n\n[backend]\nkind = \"sim\"\nsim_config = {:?}\n",
        absolute(&plan).display().to_string(),
        absolute(config).display().to_string(),
    );
    let path = args.out.join("job.toml");
    std::fs::write(&path, job_text)
        .map_err(|e| XtaskError::step(format!("writing {}", path.display()), e))?;
    Ok(path)
}
