//! `cargo xtask calibrate`: the main job. A full simulated distributed
//! calibration on the embedded defaults (`configs/sim-hopg.toml` with
//! `configs/plan-hopg.toml`), into a fresh CDB, then regression surfaces,
//! accuracy against the simulator's oracle and the four baselines, figures and
//! `report.json`.

use crate::XtaskError;
use spmcal::job::Job;
use spmcal::progress::ProgressBarObserver;
use spmcal::report::{RunRecord, finish};
use spmcal::run::{RecordingObserver, RunStart, run_job};
use std::path::Path;
use std::time::{Instant, SystemTime, UNIX_EPOCH};

pub fn run(
    config_path: &Path,
    plan_path: Option<&Path>,
    default_plan: &Path,
    out: &Path,
    quick: bool,
) -> Result<(), XtaskError> {
    let started = Instant::now();
    std::fs::create_dir_all(out)
        .map_err(|e| XtaskError::step(format!("creating {}", out.display()), e))?;
    install_log(&out.join("calibrate.log"));

    let text = std::fs::read_to_string(config_path)
        .map_err(|e| XtaskError::step(format!("reading {}", config_path.display()), e))?;
    let is_job = text
        .parse::<toml::Table>()
        .map(|t| t.contains_key("backend"))
        .unwrap_or(false);
    let job = if is_job {
        Job::from_file(config_path).map_err(|e| XtaskError::step("reading the job", e))?
    } else {
        let plan_path = plan_path.unwrap_or(default_plan);
        let (plan, plan_text) =
            Job::read_plan(plan_path).map_err(|e| XtaskError::step("reading the plan", e))?;
        Job::from_parts(config_path, plan, plan_text)
            .map_err(|e| XtaskError::step("reading the simulator config", e))?
    };

    // A fresh CDB for every job.
    let cdb_path = out.join("cdb.sqlite");
    for suffix in ["", "-wal", "-shm"] {
        let path = out.join(format!("cdb.sqlite{suffix}"));
        if path.exists() {
            std::fs::remove_file(&path)
                .map_err(|e| XtaskError::step(format!("removing {}", path.display()), e))?;
        }
    }
    let start_unix_s = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64());
    let run_id = format!("xtask-{}", start_unix_s as u64);
    let mut progress = ProgressBarObserver::new();
    let mut recorder = RecordingObserver::new(&mut progress);
    let run_started = Instant::now();
    let outcome = run_job(
        &job,
        &cdb_path,
        RunStart::New { run_id },
        start_unix_s,
        &mut recorder,
    )
    .map_err(|e| XtaskError::step("calibration", e))?;
    let run_wall_time_s = run_started.elapsed().as_secs_f64();
    let samples = recorder.into_samples();
    progress.finish();

    let record = RunRecord::of_job(&job.plan, &outcome, &samples, run_wall_time_s);
    let report =
        finish(&cdb_path, out, &record, quick).map_err(|e| XtaskError::step("report", e))?;

    println!();
    println!("== spmcal calibrate: summary ==");
    println!(
        "nodes {} × repeats {} → {} records; {} given up; cycles kept {} discarded {}",
        report.nodes,
        report.repeats,
        report.records,
        report.run.given_up.len(),
        report.run.cycles.kept,
        report.run.cycles.discarded
    );
    println!(
        "instrument time {:.0} s; wall time {:.1} s ({:.2} ms per node); job total {:.1} s",
        report.instrument_time_s,
        report.wall_time_s,
        report.wall_time_per_node_ms,
        started.elapsed().as_secs_f64()
    );
    let r = &report.regression;
    println!(
        "surfaces: K̄x degree {} σ {:.2e}; K̄y degree {} σ {:.2e}; α degree {} σ {:.2e} rad",
        r.kx.degree, r.kx.sigma, r.ky.degree, r.ky.sigma, r.alpha.degree, r.alpha.sigma
    );
    if let Some(a) = &report.accuracy {
        println!(
            "{:<12} {:>12} {:>12} {:>16} {:>16}",
            "method", "RMS pm", "max pm", "mean lattice %", "max lattice %"
        );
        for (name, m) in [
            ("uncorrected", &a.uncorrected),
            ("lumped", &a.lumped),
            ("affine", &a.affine),
            ("distributed", &a.distributed),
        ]
        .into_iter()
        .chain(a.polynomial.as_ref().map(|p| ("polynomial", p)))
        {
            println!(
                "{:<12} {:>12.1} {:>12.1} {:>16.4} {:>16.4}",
                name, m.rms_pm, m.max_pm, m.mean_lattice_error_pct, m.max_lattice_error_pct
            );
        }
        println!(
            "distributed / lumped RMS = {:.3} (target ≤ 0.1)",
            a.distributed_over_lumped_rms
        );
    }
    if let Some(images) = &report.images {
        print!("{}", images.summary_table());
    }
    if let Some(e) = &report.node_lcc_error {
        println!(
            "node LCCs vs oracle ({} records): K̄x {:+.3} ± {:.3} %, K̄y {:+.3} ± {:.3} %, α {:+.2} ± {:.2} mrad (mean, RMS)",
            e.n,
            e.kx_mean_pct,
            e.kx_rms_pct,
            e.ky_mean_pct,
            e.ky_rms_pct,
            e.alpha_mean_mrad,
            e.alpha_rms_mrad
        );
    }
    println!("output: {}", out.display());
    Ok(())
}

fn install_log(path: &Path) {
    if let Ok(file) = std::fs::File::create(path) {
        let _ = tracing_subscriber::fmt()
            .with_env_filter(
                tracing_subscriber::EnvFilter::try_from_env("SPMCAL_LOG")
                    .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
            )
            .with_ansi(false)
            .with_writer(std::sync::Mutex::new(file))
            .try_init();
    }
}
