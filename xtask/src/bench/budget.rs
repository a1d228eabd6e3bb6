//! Error budget of the distributed calibration on the images users see (issue 12): the
//! default scanner (`configs/sim-hopg.toml`, every effect on) calibrated and imaged again with
//! one simulated effect switched off at a time — hysteresis, creep, drift, measurement noise,
//! feedback lag, the cubic order of the nonlinearity — and once more with every effect on but
//! another seed (statistical noise: the repeats' scatter). The part of an image error that an
//! effect causes is what disappears without it, in quadrature:
//! `√max(0, e_all² − e_without²)`.

use super::{Context, calibrate};
use crate::XtaskError;
use serde::Serialize;
use spm_evaluation::images::ImageMethodSummary;
use spm_sim::SimConfig;
use spmcal::job::{Backend, Job};
use std::collections::BTreeMap;

/// Methods the budget follows.
pub const METHODS: [&str; 4] = [
    "distributed",
    "distributed_creep_model",
    "oracle_static_field",
    "bound_distributed_true_dynamics",
];

/// One variant of the scanner.
#[derive(Debug, Serialize)]
pub struct BudgetRow {
    /// What was switched off.
    pub variant: String,
    /// Per method: the image figures.
    pub methods: BTreeMap<String, ImageMethodSummary>,
    /// Node LCC error against the oracle: K̄x RMS, K̄y RMS (%), α RMS (mrad).
    pub node_lcc_rms: Option<(f64, f64, f64)>,
}

/// The budget section.
#[derive(Debug, Serialize)]
pub struct BudgetResults {
    /// The plan used.
    pub plan: String,
    /// All on first, then one effect off per row, then the reseeded all-on run.
    pub rows: Vec<BudgetRow>,
}

fn variants(base: &SimConfig) -> Vec<(&'static str, SimConfig)> {
    let mut out = vec![("every effect on", base.clone())];
    let mut c = base.clone();
    c.scanner.hysteresis_x.width_fraction = 0.0;
    c.scanner.hysteresis_y.width_fraction = 0.0;
    out.push(("hysteresis off", c));
    let mut c = base.clone();
    c.scanner.creep.log_slope_per_decade = 0.0;
    out.push(("creep off", c));
    let mut c = base.clone();
    c.drift.velocity_x_nm_per_s = 0.0;
    c.drift.velocity_y_nm_per_s = 0.0;
    c.drift.warmup_amplitude_x_nm = 0.0;
    c.drift.warmup_amplitude_y_nm = 0.0;
    c.drift.velocity_random_walk_nm_per_s_per_sqrt_s = 0.0;
    c.drift.jump_rate_per_s = 0.0;
    out.push(("drift off", c));
    let mut c = base.clone();
    c.measurement.z_white_noise_nm = 0.0;
    c.measurement.z_flicker_noise_nm = 0.0;
    c.measurement.lateral_jitter_nm = 0.0;
    out.push(("noise off", c));
    let mut c = base.clone();
    c.measurement.feedback_time_constant_s = 0.0;
    out.push(("feedback lag off", c));
    let mut c = base.clone();
    c.scanner.nonlinearity_x.cubic = 0.0;
    c.scanner.nonlinearity_y.cubic = 0.0;
    out.push(("cubic nonlinearity off", c));
    let mut c = base.clone();
    c.seed = c.seed.wrapping_add(1);
    out.push(("every effect on, another seed", c));
    out
}

pub fn run(ctx: &Context) -> Result<BudgetResults, XtaskError> {
    let plan_name = if ctx.quick {
        "configs/plan-hopg-small.toml"
    } else {
        "configs/plan-hopg.toml"
    };
    let (plan, plan_text) = Job::read_plan(&ctx.root.join(plan_name))
        .map_err(|e| XtaskError::step("reading the plan", e))?;
    let base = SimConfig::room_temperature_tube().without_random_faults();
    let mut rows = Vec::new();
    let mut all = variants(&base);
    if ctx.quick {
        // The smoke run: every effect on and the two effects that dominate.
        all.retain(|(v, _)| matches!(*v, "every effect on" | "hysteresis off" | "creep off"));
    }
    for (index, (variant, sim)) in all.into_iter().enumerate() {
        let job = Job {
            backend: Backend::Sim(Box::new(sim)),
            plan: plan.clone(),
            provenance_text: plan_text.clone(),
        };
        let dir = ctx.scratch(&format!("budget-{index}"))?;
        let report = calibrate(&job, &dir, ctx.quick, true)?.report;
        let images = report
            .images
            .ok_or_else(|| XtaskError::step(variant, "no image benchmark (no oracle)"))?;
        let methods: BTreeMap<String, ImageMethodSummary> = images
            .methods
            .into_iter()
            .filter(|(name, _)| METHODS.contains(&name.as_str()))
            .collect();
        if let Some(d) = methods.get("distributed") {
            println!(
                "   budget {variant}: distributed {:.3} % of side, lattice {:.3} / {:.3} %",
                d.position_rms_pct_of_side, d.mean_lattice_error_pct, d.max_lattice_error_pct
            );
        }
        rows.push(BudgetRow {
            variant: variant.to_owned(),
            methods,
            node_lcc_rms: report
                .node_lcc_error
                .map(|e| (e.kx_rms_pct, e.ky_rms_pct, e.alpha_rms_mrad)),
        });
    }
    Ok(BudgetResults {
        plan: plan_name.to_owned(),
        rows,
    })
}
