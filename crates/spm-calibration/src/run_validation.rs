//! The run's validation without an oracle (`[validation]`, issue 24): which share of the net's
//! nodes is held out of a validation fit, and the thresholds of the pass/warn verdicts. The
//! checks themselves (held-out prediction, repeat agreement, the corrected standard's lattice)
//! are computed after the run from the CDB and the backend, whatever the backend
//! (`spm_evaluation::validation`).

use serde::{Deserialize, Serialize};

/// The `[validation]` table of a plan; absent = the defaults, so old plans gain the checks.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunValidationConfig {
    /// Share of the net's nodes (all their repeats and LCSs) held out of the validation fit,
    /// in [0, 0.5]. Default 0.1. The surfaces written to `surfaces.json` still use every node:
    /// the held-out fit is a second fit that tests the procedure on places it has not seen.
    pub holdout_share: f64,
    /// Seed of the held-out draw (a seeded ChaCha permutation of the node indices). Default 1.
    pub holdout_seed: u64,
    /// Pass range of the RMS of (measured − predicted)/σ over the held-out records, σ the
    /// fit's eq. (14) scatter widened by the prediction's leverage (σ·√(1 + h)). Below the
    /// range the surfaces overstate their uncertainty, above it they predict unseen places
    /// worse than they claim. Default [0.7, 1.5].
    pub holdout_rms_sigma_range: [f64; 2],
    /// Largest pooled repeat-to-repeat scatter of a node's LCCs, in units of the records'
    /// stated standard uncertainty (the l repeats measure the same place). Default 2.
    pub repeat_scatter_over_stated_max: f64,
    /// Largest error of the lattice constant measured on the corrected image of the
    /// standard, % of the standard's lattice constant, at any place. Default 1.
    pub lattice_constant_error_pct_max: f64,
    /// Largest deviation of a lattice angle from the standard's, degrees, at any place.
    /// Default 0.5.
    pub lattice_angle_error_deg_max: f64,
    /// Places per side of the grid of corrected images of the standard taken after the run
    /// (0 = none). Default 3 (a 3 × 3 grid over the calibrated region).
    pub lattice_places_per_side: u32,
}

impl Default for RunValidationConfig {
    fn default() -> Self {
        Self {
            holdout_share: 0.1,
            holdout_seed: 1,
            holdout_rms_sigma_range: [0.7, 1.5],
            repeat_scatter_over_stated_max: 2.0,
            lattice_constant_error_pct_max: 1.0,
            lattice_angle_error_deg_max: 0.5,
            lattice_places_per_side: 3,
        }
    }
}

impl RunValidationConfig {
    /// Checks the values; the error names the field.
    ///
    /// # Errors
    /// `(field, reason)`.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if !(self.holdout_share.is_finite() && (0.0..=0.5).contains(&self.holdout_share)) {
            return Err((
                "validation.holdout_share",
                format!("must be in [0, 0.5], got {}", self.holdout_share),
            ));
        }
        let [lo, hi] = self.holdout_rms_sigma_range;
        if !(lo.is_finite() && hi.is_finite() && 0.0 <= lo && lo < hi) {
            return Err((
                "validation.holdout_rms_sigma_range",
                format!("must be [low, high] with 0 ≤ low < high, got [{lo}, {hi}]"),
            ));
        }
        let positive = |field: &'static str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err((field, format!("must be a finite number > 0, got {v}")))
            }
        };
        positive(
            "validation.repeat_scatter_over_stated_max",
            self.repeat_scatter_over_stated_max,
        )?;
        positive(
            "validation.lattice_constant_error_pct_max",
            self.lattice_constant_error_pct_max,
        )?;
        positive(
            "validation.lattice_angle_error_deg_max",
            self.lattice_angle_error_deg_max,
        )?;
        if self.lattice_places_per_side > 16 {
            return Err((
                "validation.lattice_places_per_side",
                format!("must be in [0, 16], got {}", self.lattice_places_per_side),
            ));
        }
        Ok(())
    }
}

/// The `[plan.targets]` table (issue 27): what a run promises. `spmcal calibrate` prints a
/// PASS or FAIL verdict for each declared target and exits with its own code (3) when one is
/// missed (`--no-targets` skips the check). Absent = nothing declared: the figures are
/// reported and the exit code does not depend on them.
///
/// Which targets a run is judged on depends on what can judge it: a backend with a ground
/// truth (the simulator) is judged against the truth (`distributed_over_lumped_rms_max`);
/// a backend without one (a controller, a stored image) by the oracle-free validation
/// (`validation_pass`). A target the backend cannot judge is reported as not judged.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunTargets {
    /// Largest distributed ÷ lumped RMS residual distortion over the calibrated region,
    /// dimensionless, judged against the ground truth (simulated backends). Absent = not
    /// declared. In (0, 10].
    #[serde(skip_serializing_if = "Option::is_none")]
    pub distributed_over_lumped_rms_max: Option<f64>,
    /// Backends without a ground truth: every check of `[plan.validation]` that reaches a
    /// verdict (held-out nodes, repeat agreement, the corrected standard) must pass; a
    /// `warn` is a missed target, a check without a verdict is not judged. Default false.
    pub validation_pass: bool,
}

impl RunTargets {
    /// True when the plan declares no target.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.distributed_over_lumped_rms_max.is_none() && !self.validation_pass
    }

    /// Checks the values; the error names the field.
    ///
    /// # Errors
    /// `(field, reason)`.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if let Some(v) = self.distributed_over_lumped_rms_max
            && !(v.is_finite() && v > 0.0 && v <= 10.0)
        {
            return Err((
                "targets.distributed_over_lumped_rms_max",
                format!("must be in (0, 10], got {v}"),
            ));
        }
        Ok(())
    }
}
