//! The scanner dynamics (schema v5): the checks of a record before it is stored and the
//! rules `cdb check` applies to every stored row, on both back ends (the SQL that stores and
//! reads them is in `crate::sql`).

use std::path::Path;

use crate::error::{CdbError, Result};
use spm_records::{DynamicsProblem, DynamicsRecord, IntegrityProblem};

/// Refuses a record that breaks [`DynamicsRecord::check`] (invalid input naming the field).
pub(crate) fn validate(path: &Path, d: &DynamicsRecord) -> Result<()> {
    d.check().map_err(|p| crate::invalid(path, p.to_string()))
}

/// Refuses a record whose scanner is not its run's.
pub(crate) fn check_run_scanner(path: &Path, d: &DynamicsRecord, run_scanner: &str) -> Result<()> {
    if d.scanner_id == run_scanner {
        return Ok(());
    }
    Err(crate::invalid(
        path,
        format!(
            "dynamics (run {:?}): scanner_id {:?} differs from the run's scanner {run_scanner:?}",
            d.run_id, d.scanner_id
        ),
    ))
}

/// The error for a record whose run is not stored.
pub(crate) fn unknown_run(path: &Path, d: &DynamicsRecord) -> CdbError {
    CdbError::NotFound {
        path: path.to_path_buf(),
        what: format!(
            "run {:?} (the run that identified the dynamics of scanner {:?})",
            d.run_id, d.scanner_id
        ),
    }
}

/// The finding `cdb check` makes of a stored row that breaks [`DynamicsRecord::check`]:
/// `non_finite` for a time that is not finite, `invalid_model_json` for a model that is not
/// a JSON object of bounded size, `invalid_dynamics` for the other rules.
pub(crate) fn problem(id: i64, d: &DynamicsRecord) -> Option<IntegrityProblem> {
    let p = d.check().err()?;
    let kind = match &p {
        DynamicsProblem::BadTime { .. } if !d.identified_unix_s.is_finite() => "non_finite",
        DynamicsProblem::TooLarge { .. } | DynamicsProblem::NotAnObject { .. } => {
            "invalid_model_json"
        }
        _ => "invalid_dynamics",
    };
    Some(IntegrityProblem {
        kind: kind.into(),
        detail: format!("dynamics id {id}: {p}"),
    })
}

/// Findings with at most `max` per kind, then one "… more" line.
pub(crate) struct Findings {
    max: usize,
    counts: std::collections::HashMap<String, usize>,
    problems: Vec<IntegrityProblem>,
}

impl Findings {
    pub(crate) fn new(max: usize) -> Self {
        Self {
            max,
            counts: std::collections::HashMap::new(),
            problems: Vec::new(),
        }
    }

    pub(crate) fn add(&mut self, p: Option<IntegrityProblem>) {
        let Some(p) = p else { return };
        let n = self.counts.entry(p.kind.clone()).or_insert(0);
        *n += 1;
        if *n <= self.max {
            self.problems.push(p);
        } else if *n == self.max + 1 {
            self.problems.push(IntegrityProblem {
                kind: p.kind,
                detail: format!("… more than {} rows", self.max),
            });
        }
    }

    pub(crate) fn into_problems(self) -> Vec<IntegrityProblem> {
        self.problems
    }
}
