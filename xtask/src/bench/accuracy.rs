//! Calibration accuracy of the distributed calibration against the four
//! baselines of DESIGN §11 on three simulated scanners (configs/sim-mild.toml,
//! sim-typical.toml, sim-bad.toml), each with the plan of `cargo xtask
//! calibrate` (configs/plan-hopg.toml; --quick: plan-hopg-small.toml).

use super::{Context, calibrate};
use crate::XtaskError;
use serde::Serialize;
use spm_evaluation::accuracy::Accuracy;
use spmcal::job::Job;

/// The scanners, with their nonlinearity label.
/// (config, description, plan replacing the default one — full runs only).
pub const CONFIGS: [(&str, &str, Option<&str>); 4] = [
    ("sim-mild", "3 % nonlinearity", None),
    ("sim-typical", "10 % nonlinearity", None),
    (
        "sim-bad",
        "25 % nonlinearity, 5° obliquity, strong crosstalk and creep",
        None,
    ),
    (
        "sim-bad",
        "the same scanner, with pauses long enough for its creep",
        Some("configs/plan-hopg-slow-creep.toml"),
    ),
];

/// Accuracy of every method on one scanner.
#[derive(Debug, Serialize)]
pub struct ConfigAccuracy {
    /// Config name (configs/NAME.toml).
    pub config: String,
    /// What the config is.
    pub description: String,
    /// Plan file used.
    pub plan: String,
    /// Nodes per repeat × repeats → records.
    pub nodes: usize,
    /// Repeats l.
    pub repeats: u32,
    /// Records in the CDB.
    pub records: u64,
    /// Visits given up.
    pub given_up: usize,
    /// Visits given up, by reason.
    pub given_up_reasons: Vec<(String, usize)>,
    /// Simulated instrument time, s.
    pub instrument_time_s: f64,
    /// Wall time of the calibration, s.
    pub wall_time_s: f64,
    /// Wall time per measured node, ms.
    pub wall_time_per_node_ms: f64,
    /// Methods, in table order: uncorrected, lumped, affine, polynomial, distributed.
    pub methods: Vec<(String, Accuracy)>,
    /// distributed RMS ÷ lumped RMS.
    pub distributed_over_lumped_rms: f64,
    /// distributed RMS ÷ polynomial RMS.
    pub distributed_over_polynomial_rms: Option<f64>,
    /// spmcal's notes on how the figures were measured.
    pub notes: Vec<String>,
    /// The image benchmark: per method, the errors on test images taken as a user does.
    pub images: Option<spm_evaluation::images::ImageBenchmark>,
    /// The run's validation without an oracle (held-out nodes, repeat agreement, the
    /// corrected standard's lattice), as every run reports it.
    pub validation: spmcal::report::Validation,
}

/// The accuracy section.
#[derive(Debug, Serialize)]
pub struct AccuracyResults {
    /// One entry per scanner.
    pub configs: Vec<ConfigAccuracy>,
}

pub fn run(ctx: &Context) -> Result<AccuracyResults, XtaskError> {
    let plan_name = if ctx.quick {
        "configs/plan-hopg-small.toml"
    } else {
        "configs/plan-hopg.toml"
    };
    let (plan, plan_text) = Job::read_plan(&ctx.root.join(plan_name))
        .map_err(|e| XtaskError::step("reading the plan", e))?;
    let mut configs = Vec::new();
    for (index, (name, description, plan_override)) in CONFIGS.into_iter().enumerate() {
        let config_path = ctx.root.join("configs").join(format!("{name}.toml"));
        let (plan_name, plan, plan_text) = match plan_override {
            None => (plan_name, plan.clone(), plan_text.clone()),
            Some(_) if ctx.quick => continue,
            Some(other) => {
                let (p, t) = Job::read_plan(&ctx.root.join(other))
                    .map_err(|e| XtaskError::step("reading the plan", e))?;
                (other, p, t)
            }
        };
        let job = Job::from_parts(&config_path, plan, plan_text)
            .map_err(|e| XtaskError::step(format!("reading {}", config_path.display()), e))?;
        let dir = ctx.scratch(&format!("accuracy-{index}-{name}"))?;
        let report = calibrate(&job, &dir, ctx.quick, true)?.report;
        let mut given_up_reasons: Vec<(String, usize)> = Vec::new();
        for visit in &report.run.given_up {
            let reason = serde_json::to_value(&visit.reason)
                .ok()
                .and_then(|v| v.get("reason").and_then(|r| r.as_str()).map(str::to_owned))
                .unwrap_or_else(|| "unknown".to_owned());
            match given_up_reasons.iter_mut().find(|(r, _)| *r == reason) {
                Some(entry) => entry.1 += 1,
                None => given_up_reasons.push((reason, 1)),
            }
        }
        given_up_reasons.sort_by_key(|entry| std::cmp::Reverse(entry.1));
        let table = report
            .accuracy
            .ok_or_else(|| XtaskError::step(name, "no accuracy table (no oracle)"))?;
        let mut methods = vec![
            ("uncorrected".to_owned(), table.uncorrected),
            ("lumped".to_owned(), table.lumped),
            ("affine".to_owned(), table.affine),
        ];
        if let Some(p) = table.polynomial {
            methods.push(("polynomial".to_owned(), p));
        }
        methods.push(("distributed".to_owned(), table.distributed));
        println!(
            "   accuracy {name}: distributed {:.1} pm RMS, lumped {:.1}, polynomial {}",
            table.distributed.rms_pm,
            table.lumped.rms_pm,
            table
                .polynomial
                .map_or_else(|| "-".to_owned(), |p| format!("{:.1}", p.rms_pm))
        );
        configs.push(ConfigAccuracy {
            config: name.to_owned(),
            description: description.to_owned(),
            plan: plan_name.to_owned(),
            nodes: report.nodes,
            repeats: report.repeats,
            records: report.records,
            given_up: report.run.given_up.len(),
            given_up_reasons,
            instrument_time_s: report.instrument_time_s,
            wall_time_s: report.wall_time_s,
            wall_time_per_node_ms: report.wall_time_per_node_ms,
            distributed_over_lumped_rms: table.distributed_over_lumped_rms,
            distributed_over_polynomial_rms: table
                .polynomial
                .map(|p| table.distributed.rms_pm / p.rms_pm),
            methods,
            validation: report.validation,
            notes: report.notes,
            images: report.images.map(|mut i| {
                i.images.clear(); // per-image rows stay in the scratch report.json
                i
            }),
        });
    }
    Ok(AccuracyResults { configs })
}
