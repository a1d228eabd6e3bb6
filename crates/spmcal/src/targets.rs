//! The run's targets judged (issue 27): one PASS, FAIL or NOT JUDGED verdict per target the
//! plan declares in `[plan.targets]` ([`spm_calibration::run_validation::RunTargets`]).
//!
//! What judges a run is what can: a backend with a ground truth (the simulator) is judged
//! against the truth, a backend without one (a controller, a stored image) by the oracle-free
//! validation. So the distributed ÷ lumped ratio is not judged on a real run (no truth to
//! measure it against), and the validation target is not judged on a simulated run (the
//! truth measures the calibration itself, where the validation only estimates it). A check
//! that reaches no verdict (too few held-out records, a single repeat) is not judged either:
//! a run is failed only on a figure that was measured and missed.
//!
//! `spmcal calibrate` exits with code 3 when a verdict is FAIL, unless `--no-targets`.

use crate::report::{CalibrationReport, Validation};
use serde::Serialize;
use spm_calibration::run_validation::RunTargets;
use spm_evaluation::validation::Verdict;

/// The verdict on one target.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TargetOutcome {
    /// Measured and met.
    Pass,
    /// Measured and missed.
    Fail,
    /// Not measured on this backend or run (the reason is given).
    NotJudged,
}

impl TargetOutcome {
    /// `PASS`, `FAIL` or `NOT JUDGED`.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Pass => "PASS",
            Self::Fail => "FAIL",
            Self::NotJudged => "NOT JUDGED",
        }
    }
}

/// One declared target and its verdict (report.json's `targets`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TargetVerdict {
    /// What is judged, as a person reads it.
    pub target: String,
    /// The figure measured, as printed (None when not measured).
    pub measured: Option<String>,
    /// Pass, fail or not judged.
    pub outcome: TargetOutcome,
    /// Why not judged, or which part missed.
    pub note: Option<String>,
}

impl TargetVerdict {
    /// The summary's line: `target: …: measured → PASS (note)`.
    #[must_use]
    pub fn line(&self) -> String {
        format!(
            "target {}: {} → {}{}",
            self.target,
            self.measured.as_deref().unwrap_or("-"),
            self.outcome.as_str(),
            self.note
                .as_deref()
                .map(|n| format!(" ({n})"))
                .unwrap_or_default()
        )
    }
}

/// The verdicts on the `targets` of `report`'s plan (empty when none is declared);
/// `simulated`: the run's backend has a ground truth (see the module doc).
#[must_use]
pub fn judge(
    report: &CalibrationReport,
    targets: &RunTargets,
    simulated: bool,
) -> Vec<TargetVerdict> {
    judge_figures(
        report
            .accuracy
            .as_ref()
            .map(|a| a.distributed_over_lumped_rms),
        &report.validation,
        targets,
        simulated,
    )
}

/// [`judge`] on the figures it reads: the distributed ÷ lumped ratio (None: not measured)
/// and the validation.
#[must_use]
pub fn judge_figures(
    distributed_over_lumped_rms: Option<f64>,
    validation: &Validation,
    targets: &RunTargets,
    simulated: bool,
) -> Vec<TargetVerdict> {
    let mut verdicts = Vec::new();
    if let Some(max) = targets.distributed_over_lumped_rms_max {
        let target = format!("distributed ÷ lumped RMS residual distortion ≤ {max}");
        verdicts.push(match distributed_over_lumped_rms {
            Some(ratio) => TargetVerdict {
                target,
                measured: Some(format!("{ratio:.3}")),
                outcome: if ratio <= max {
                    TargetOutcome::Pass
                } else {
                    TargetOutcome::Fail
                },
                note: (!ratio.is_finite()).then(|| "not a finite number".to_owned()),
            },
            None => TargetVerdict {
                target,
                measured: None,
                outcome: TargetOutcome::NotJudged,
                note: Some(
                    "needs a ground truth (a simulated backend) and nodes spanning an area"
                        .to_owned(),
                ),
            },
        });
    }
    if targets.validation_pass {
        verdicts.extend(validation_verdicts(validation, simulated));
    }
    verdicts
}

/// The validation target: one verdict per check, judged only without a ground truth.
fn validation_verdicts(v: &Validation, simulated: bool) -> Vec<TargetVerdict> {
    let lattice = v.lattice.as_ref().map_or(
        (
            Verdict::NotMeasured,
            None,
            v.lattice_failure
                .clone()
                .or_else(|| Some("no images of the standard were taken".to_owned())),
        ),
        |l| {
            (
                l.verdict,
                Some(format!(
                    "lattice constant max {:.2} %, angles max {:.2}°",
                    l.corrected_max_error_pct, l.corrected_max_angle_error_deg
                )),
                l.reason.clone(),
            )
        },
    );
    let checks = [
        (
            format!(
                "held-out nodes: RMS (measured − predicted)/σ in {}–{}",
                v.held_out.pass_range[0], v.held_out.pass_range[1]
            ),
            v.held_out.verdict,
            v.held_out
                .rms_z
                .is_finite()
                .then(|| format!("{:.2}", v.held_out.rms_z)),
            v.held_out.reason.clone(),
        ),
        (
            format!(
                "repeat agreement: scatter ÷ stated u ≤ {}",
                v.repeats.scatter_over_stated_max
            ),
            v.repeats.verdict,
            (!v.repeats.coefficients.is_empty()).then(|| {
                v.repeats
                    .coefficients
                    .iter()
                    .map(|c| format!("{} {:.2}", c.coefficient, c.scatter_over_stated))
                    .collect::<Vec<_>>()
                    .join(", ")
            }),
            v.repeats.reason.clone(),
        ),
        (
            "corrected standard within the plan's lattice thresholds".to_owned(),
            lattice.0,
            lattice.1,
            lattice.2,
        ),
    ];
    checks
        .into_iter()
        .map(|(target, verdict, measured, reason)| {
            let (outcome, note) = if simulated {
                (
                    TargetOutcome::NotJudged,
                    Some(
                        "judged against the ground truth on a simulated backend, not by the \
                         validation"
                            .to_owned(),
                    ),
                )
            } else {
                match verdict {
                    Verdict::Pass => (TargetOutcome::Pass, None),
                    Verdict::Warn => (TargetOutcome::Fail, reason),
                    Verdict::NotMeasured => (TargetOutcome::NotJudged, reason),
                }
            };
            TargetVerdict {
                target: format!("validation, {target}"),
                measured,
                outcome,
                note,
            }
        })
        .collect()
}

/// True when a verdict is FAIL.
#[must_use]
pub fn any_missed(verdicts: &[TargetVerdict]) -> bool {
    verdicts.iter().any(|v| v.outcome == TargetOutcome::Fail)
}

#[cfg(test)]
mod tests {
    use super::*;
    use spm_calibration::run_validation::RunValidationConfig;

    /// A validation of no records (every check not measured), then verdicts set by hand.
    fn validation(held_out: Verdict, repeats: Verdict) -> Validation {
        let config = RunValidationConfig::default();
        let mut held = spm_evaluation::validation::held_out_check(&[], &config, |_, _| {
            Err::<spm_correction::PlaneSurfaces, _>("no fit")
        });
        held.verdict = held_out;
        held.reason = Some("K̄x out of range".to_owned());
        let mut agreement = spm_evaluation::validation::repeat_agreement(&[], &config);
        agreement.verdict = repeats;
        Validation {
            held_out: held,
            repeats: agreement,
            lattice: None,
            lattice_failure: None,
        }
    }

    fn outcomes(v: &[TargetVerdict]) -> Vec<TargetOutcome> {
        v.iter().map(|t| t.outcome).collect()
    }

    #[test]
    fn the_ratio_is_judged_against_the_declared_bound_and_only_when_measured() {
        use TargetOutcome::{Fail, NotJudged, Pass};
        let targets = RunTargets {
            distributed_over_lumped_rms_max: Some(0.1),
            validation_pass: false,
        };
        let v = validation(Verdict::Pass, Verdict::Pass);
        assert_eq!(
            outcomes(&judge_figures(Some(0.2), &v, &targets, true)),
            [Fail]
        );
        assert_eq!(
            outcomes(&judge_figures(Some(0.1), &v, &targets, true)),
            [Pass]
        );
        assert_eq!(
            outcomes(&judge_figures(Some(f64::NAN), &v, &targets, true)),
            [Fail]
        );
        assert_eq!(
            outcomes(&judge_figures(None, &v, &targets, false)),
            [NotJudged]
        );
        assert!(judge_figures(Some(9.0), &v, &RunTargets::default(), true).is_empty());
    }

    #[test]
    fn a_real_run_is_judged_by_its_validation_and_a_simulated_one_is_not() {
        use TargetOutcome::{Fail, NotJudged, Pass};
        let targets = RunTargets {
            distributed_over_lumped_rms_max: None,
            validation_pass: true,
        };
        let v = validation(Verdict::Warn, Verdict::Pass);
        let real = judge_figures(None, &v, &targets, false);
        // Held out warns (FAIL, its reason kept), repeats pass, no lattice images: not judged.
        assert_eq!(outcomes(&real), [Fail, Pass, NotJudged]);
        assert_eq!(real[0].note.as_deref(), Some("K̄x out of range"));
        assert!(any_missed(&real));
        let simulated = judge_figures(Some(0.05), &v, &targets, true);
        assert_eq!(outcomes(&simulated), [NotJudged, NotJudged, NotJudged]);
        assert!(!any_missed(&simulated));
        let not_measured = validation(Verdict::NotMeasured, Verdict::NotMeasured);
        assert!(!any_missed(&judge_figures(
            None,
            &not_measured,
            &targets,
            false
        )));
    }
}
