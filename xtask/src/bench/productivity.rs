//! Productivity: calibration error against repeats l and kept skipping cycles
//! per vector, and against instrument time, for the plan variants (Fig. 3a:
//! attach to feature A; Fig. 3b: attach to the LCS centre; skipping to every
//! neighbour in the aperture; B↔C redundancy; counter-scanning instead of
//! skipping). A small net (configs/plan-hopg-small.toml with a 12000-count step:
//! 5 × 5 nodes) on the room-temperature tube scanner (configs/sim-hopg.toml).

use super::{Context, calibrate};
use crate::XtaskError;
use serde::Serialize;
use spm_calibration::{AttachTarget, MeasurementMethod, NeighbourSet, PlanConfig};
use spmcal::job::Job;

/// One calibration of the sweep.
#[derive(Debug, Serialize)]
pub struct ProductivityPoint {
    /// Variant name.
    pub variant: String,
    /// Repeats l.
    pub repeats: u32,
    /// Kept skipping cycles per vector.
    pub cycles: u32,
    /// Records.
    pub records: u64,
    /// Simulated instrument time, s.
    pub instrument_time_s: f64,
    /// RMS of (K̄x, K̄y measured / true − 1) over all records, %.
    pub node_k_rms_pct: f64,
    /// RMS over nodes of (K̄x, K̄y averaged over the node's repeats ÷ true − 1), %.
    pub node_mean_k_rms_pct: f64,
    /// RMS of α measured − true over all records, mrad.
    pub node_alpha_rms_mrad: f64,
    /// Residual distortion RMS of the distributed calibration, pm.
    pub distributed_rms_pm: f64,
    /// Mean lattice-constant error of the distributed calibration, %.
    pub distributed_mean_lattice_error_pct: f64,
}

/// The productivity section.
#[derive(Debug, Serialize)]
pub struct ProductivityResults {
    /// Net nodes per repeat.
    pub nodes: usize,
    /// Every calibration run.
    pub points: Vec<ProductivityPoint>,
}

fn variant(plan: &mut PlanConfig, name: &str) {
    match name {
        "fig3b-lcs-centre" => plan.variant.attach_to = AttachTarget::LcsCentre,
        "all-neighbours" => plan.variant.neighbours = NeighbourSet::AllInAperture,
        "bc-redundancy" => plan.variant.bc_redundancy = true,
        "counter-scan" => plan.variant.measurement = MeasurementMethod::CounterScan,
        _ => {}
    }
}

pub fn run(ctx: &Context) -> Result<ProductivityResults, XtaskError> {
    let plan_path = ctx.root.join("configs/plan-hopg-small.toml");
    let (base, plan_text) =
        Job::read_plan(&plan_path).map_err(|e| XtaskError::step("reading the plan", e))?;
    let sim_path = ctx.root.join("configs/sim-hopg.toml");
    let mut runs: Vec<(&str, u32, u32)> = Vec::new();
    let (repeats, cycles): (&[u32], &[u32]) = if ctx.quick {
        (&[1, 3], &[1, 4])
    } else {
        (&[1, 2, 3, 5], &[1, 2, 4, 8])
    };
    for &l in repeats {
        runs.push(("fig3a-feature-a", l, 2));
    }
    for &c in cycles {
        if c != 2 {
            runs.push(("fig3a-feature-a", 1, c));
        }
    }
    for name in [
        "fig3b-lcs-centre",
        "all-neighbours",
        "bc-redundancy",
        "counter-scan",
    ] {
        runs.push((name, 1, 2));
    }
    let mut points = Vec::new();
    let mut nodes = 0;
    for (name, l, c) in runs {
        let mut plan = base.clone();
        plan.net.step_counts = 12_000;
        plan.repeats = l;
        plan.skipping.cycles = c;
        variant(&mut plan, name);
        let job = Job::from_parts(&sim_path, plan, plan_text.clone())
            .map_err(|e| XtaskError::step("reading configs/sim-hopg.toml", e))?;
        let dir = ctx.scratch(&format!("productivity-{name}-l{l}-c{c}"))?;
        let calibrated = calibrate(&job, &dir, true, false)?;
        let report = calibrated.report;
        nodes = report.nodes;
        let (Some(e), Some(a)) = (report.node_lcc_error, report.accuracy.as_ref()) else {
            return Err(XtaskError::step(name, "no oracle figures"));
        };
        let point = ProductivityPoint {
            variant: name.to_owned(),
            repeats: l,
            cycles: c,
            records: report.records,
            instrument_time_s: report.instrument_time_s,
            node_k_rms_pct: super::rms(&[e.kx_rms_pct, e.ky_rms_pct]),
            node_mean_k_rms_pct: calibrated.node_mean_k_rms_pct.unwrap_or(f64::NAN),
            node_alpha_rms_mrad: e.alpha_rms_mrad,
            distributed_rms_pm: a.distributed.rms_pm,
            distributed_mean_lattice_error_pct: a.distributed.mean_lattice_error_pct,
        };
        println!(
            "   productivity {name} l={l} cycles={c}: {} records, {:.0} s instrument, K RMS {:.3} % per record, {:.3} % node mean, distributed {:.0} pm",
            point.records,
            point.instrument_time_s,
            point.node_k_rms_pct,
            point.node_mean_k_rms_pct,
            point.distributed_rms_pm
        );
        points.push(point);
    }
    Ok(ProductivityResults { nodes, points })
}
