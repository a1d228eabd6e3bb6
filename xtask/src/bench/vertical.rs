//! The vertical axis (issue 15): `configs/calibrate-hopg-3d.toml` — the vertical-plane net of
//! Fig. 1b over 3 × 3 nodes × 3 coarse-Z levels, Kz from monatomic steps near the nodes, the
//! bowl from the LCS levels, the LCCs' z-dependence — run and judged against the oracle
//! (spmcal's report.json `vertical`), plus the hidden-effect check: the same job with a Kz
//! that drifts 3 %/h, which the static calibration must show as a structured residual.

use super::{Context, calibrate};
use crate::XtaskError;
use serde::Serialize;
use spmcal::job::{Backend, Job};

/// The job this section runs.
pub const JOB: &str = "configs/calibrate-hopg-3d.toml";

/// The vertical section.
#[derive(Debug, Serialize)]
pub struct VerticalResults {
    /// The job.
    pub job: String,
    /// Records stored.
    pub records: u64,
    /// Visits with a measured Kz / without a step in reach / with only rejected steps.
    pub kz_measured: usize,
    /// Visits without a step in reach.
    pub kz_no_step_in_reach: usize,
    /// report.json `regression.kz` (degree, σ, Δmax of the first plane).
    pub regression_kz: Option<spmcal::surfaces::SurfaceSummary>,
    /// report.json `vertical` with every effect on.
    pub vertical: Option<spm_evaluation::vertical::VerticalReport>,
    /// The Kz-residual trend (%/h) and its t with a hidden Kz drift of 3 %/h.
    pub hidden_kz_drift_trend_pct_per_hour: Option<f64>,
    /// Its t.
    pub hidden_kz_drift_trend_t: Option<f64>,
    /// The hidden drift was flagged as a structured residual.
    pub hidden_kz_drift_flagged: bool,
    /// Wall time of the calibration with every effect on, s.
    pub wall_time_s: f64,
}

pub fn run(ctx: &Context) -> Result<VerticalResults, XtaskError> {
    let path = ctx.root.join(JOB);
    let job = Job::from_file(&path).map_err(|e| XtaskError::step(format!("loading {JOB}"), e))?;
    let all = calibrate(&job, &ctx.scratch("vertical")?, true, false)?;
    let mut hidden = job.clone();
    let Backend::Sim(sim) = &mut hidden.backend else {
        return Err(XtaskError::step(
            JOB,
            "the vertical job must run on the simulator",
        ));
    };
    if let Some(z) = &mut sim.scanner.z_manipulator {
        z.kz_drift_per_hour = 0.03;
    }
    let drifting = calibrate(&hidden, &ctx.scratch("vertical-kz-drift")?, true, false)?;
    let hv = drifting.report.vertical.as_ref();
    let r = &all.report;
    Ok(VerticalResults {
        job: JOB.to_owned(),
        records: r.records,
        kz_measured: r.run.kz.measured,
        kz_no_step_in_reach: r.run.kz.no_step_in_reach,
        regression_kz: r.regression.kz,
        vertical: r.vertical.clone(),
        hidden_kz_drift_trend_pct_per_hour: hv.and_then(|v| v.kz_residual_trend_pct_per_hour),
        hidden_kz_drift_trend_t: hv.and_then(|v| v.kz_residual_trend_t),
        hidden_kz_drift_flagged: hv.is_some_and(|v| v.kz_structured_residual),
        wall_time_s: r.wall_time_s,
    })
}
