//! Record types stored in the CDB.

use serde::{Deserialize, Serialize};

/// One local calibration measurement (an LCS measured at a net node), DESIGN §8.
///
/// Coordinates are scanner counts, LCCs nm per count, angles rad, velocities nm/s, times UTC
/// seconds since the Unix epoch (`acquired_unix_s`, supplied by the caller: the library reads
/// no clock).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LccRecord {
    /// Scanner the record belongs to.
    pub scanner_id: String,
    /// Calibration run that produced it.
    pub run_id: String,
    /// Acquisition time, UTC seconds since 1970-01-01T00:00:00Z.
    pub acquired_unix_s: f64,
    /// Repeat (pass over the net) index, 0-based.
    pub repeat_index: u32,
    /// Node index within the plan, 0-based.
    pub node_index: u32,
    /// Index of the LCS among those measured at this node (0 if one).
    pub lcs_index: u32,
    /// Commanded node x (counts).
    pub node_x_counts: i64,
    /// Commanded node y (counts).
    pub node_y_counts: i64,
    /// Node z: the Z-manipulator position of the lateral plane (counts).
    pub node_z_counts: i64,
    /// Gravity centre of the LCS, x (real counts).
    pub lcs_x_counts: f64,
    /// Gravity centre of the LCS, y (real counts).
    pub lcs_y_counts: f64,
    /// Gravity centre of the LCS, z (real counts).
    pub lcs_z_counts: f64,
    /// K̄x (nm per count), > 0.
    pub kx_nm_per_count: f64,
    /// K̄y (nm per count), > 0.
    pub ky_nm_per_count: f64,
    /// Local obliquity α (rad), |α| < π/2.
    pub alpha_rad: f64,
    /// Kz (nm per count), > 0, if measured at this node.
    pub kz_nm_per_count: Option<f64>,
    /// Standard uncertainty of K̄x (nm per count), if known.
    pub u_kx_nm_per_count: Option<f64>,
    /// Standard uncertainty of K̄y (nm per count), if known.
    pub u_ky_nm_per_count: Option<f64>,
    /// Standard uncertainty of α (rad), if known.
    pub u_alpha_rad: Option<f64>,
    /// Standard uncertainty of Kz (nm per count), if known.
    pub u_kz_nm_per_count: Option<f64>,
    /// Drift velocity x (nm/s) measured while skipping.
    pub drift_vx_nm_per_s: f64,
    /// Drift velocity y (nm/s).
    pub drift_vy_nm_per_s: f64,
    /// Skipping cycles kept.
    pub cycles_kept: u32,
    /// Skipping cycles discarded as spoiled.
    pub cycles_discarded: u32,
    /// Quality score (higher is better; the controller defines the scale).
    pub quality: f64,
    /// Where Kz was measured (the step's edge point), x, counts; `None` without Kz (and for
    /// records written before schema v3).
    pub kz_x_counts: Option<f64>,
    /// Where Kz was measured, y, counts.
    pub kz_y_counts: Option<f64>,
}

/// Status of a calibration run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RunStatus {
    /// In progress (or killed: resumable).
    Running,
    /// Completed.
    Finished,
    /// Stopped on an error.
    Failed,
    /// Stopped by the operator.
    Aborted,
}

impl RunStatus {
    /// The text stored in the `runs.status` column.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Running => "running",
            Self::Finished => "finished",
            Self::Failed => "failed",
            Self::Aborted => "aborted",
        }
    }

    /// Parses the stored text.
    #[must_use]
    pub fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "running" => Self::Running,
            "finished" => Self::Finished,
            "failed" => Self::Failed,
            "aborted" => Self::Aborted,
            _ => return None,
        })
    }
}

/// A calibration run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunInfo {
    /// Unique run id.
    pub run_id: String,
    /// Scanner calibrated.
    pub scanner_id: String,
    /// The configuration used (e.g. the TOML text), for provenance.
    pub config: String,
    /// Start time, UTC seconds since the epoch.
    pub started_unix_s: f64,
    /// End time, if finished.
    pub finished_unix_s: Option<f64>,
    /// Status.
    pub status: RunStatus,
}

/// A node of a run's plan (one visit: a repeat of a node).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct PlanNode {
    /// Repeat index, 0-based.
    pub repeat_index: u32,
    /// Node index in trajectory order, 0-based.
    pub node_index: u32,
    /// Node x (counts).
    pub node_x_counts: i64,
    /// Node y (counts).
    pub node_y_counts: i64,
    /// Node z (counts).
    pub node_z_counts: i64,
}

/// State of a plan node.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "state", content = "reason")]
pub enum NodeState {
    /// Not measured yet.
    Pending,
    /// Measured; its records are stored.
    Done,
    /// Abandoned after repeated failures, with the reason.
    GivenUp(String),
}

/// Progress of one plan node.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NodeProgress {
    /// The node.
    pub node: PlanNode,
    /// Its state.
    pub state: NodeState,
    /// Measurement attempts made.
    pub attempts: u32,
    /// Time of the last state change, UTC seconds since the epoch.
    pub updated_unix_s: Option<f64>,
}

/// Counts of plan nodes by state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct ProgressSummary {
    /// Pending nodes.
    pub pending: u64,
    /// Done nodes.
    pub done: u64,
    /// Given-up nodes.
    pub given_up: u64,
}

/// Completion of a node passed to [`crate::ProgressStore::commit_node`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NodeDone {
    /// Repeat index.
    pub repeat_index: u32,
    /// Node index.
    pub node_index: u32,
    /// Attempts it took.
    pub attempts: u32,
    /// Completion time, UTC seconds since the epoch.
    pub finished_unix_s: f64,
}

/// Selection of records; `None` fields do not filter. Time bounds are inclusive.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RecordFilter {
    /// Only this scanner.
    pub scanner_id: Option<String>,
    /// Only this run.
    pub run_id: Option<String>,
    /// Only this Z plane (node z, counts).
    pub node_z_counts: Option<i64>,
    /// Only records acquired at or after this time (UTC s).
    pub since_unix_s: Option<f64>,
    /// Only records acquired at or before this time (UTC s).
    pub until_unix_s: Option<f64>,
}

impl RecordFilter {
    /// All records of a scanner.
    #[must_use]
    pub fn scanner(scanner_id: &str) -> Self {
        Self {
            scanner_id: Some(scanner_id.to_owned()),
            ..Self::default()
        }
    }

    /// Restricts to one Z plane.
    #[must_use]
    pub fn with_z_plane(mut self, node_z_counts: i64) -> Self {
        self.node_z_counts = Some(node_z_counts);
        self
    }

    /// Restricts to one run.
    #[must_use]
    pub fn with_run(mut self, run_id: &str) -> Self {
        self.run_id = Some(run_id.to_owned());
        self
    }

    /// Restricts to a time window (inclusive).
    #[must_use]
    pub fn with_window(mut self, since_unix_s: Option<f64>, until_unix_s: Option<f64>) -> Self {
        self.since_unix_s = since_unix_s;
        self.until_unix_s = until_unix_s;
        self
    }
}

/// Selected records as columns, for regression (struct of arrays, no strings).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LccColumns {
    /// LCS gravity centre x (counts): the abscissa of the regression surfaces.
    pub lcs_x_counts: Vec<f64>,
    /// LCS gravity centre y (counts).
    pub lcs_y_counts: Vec<f64>,
    /// Node z (counts).
    pub node_z_counts: Vec<i64>,
    /// Acquisition time (UTC s).
    pub acquired_unix_s: Vec<f64>,
    /// K̄x (nm per count).
    pub kx_nm_per_count: Vec<f64>,
    /// K̄y (nm per count).
    pub ky_nm_per_count: Vec<f64>,
    /// α (rad).
    pub alpha_rad: Vec<f64>,
    /// Kz (nm per count) where measured.
    pub kz_nm_per_count: Vec<Option<f64>>,
}

impl LccColumns {
    /// Number of records.
    #[must_use]
    pub fn len(&self) -> usize {
        self.kx_nm_per_count.len()
    }

    /// True if empty.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.kx_nm_per_count.is_empty()
    }

    /// The records whose `keep` is true (a record beyond `keep`'s length is dropped).
    #[must_use]
    pub fn selected(&self, keep: &[bool]) -> Self {
        fn pick<T: Clone>(values: &[T], keep: &[bool]) -> Vec<T> {
            values
                .iter()
                .zip(keep)
                .filter(|(_, k)| **k)
                .map(|(v, _)| v.clone())
                .collect()
        }
        Self {
            lcs_x_counts: pick(&self.lcs_x_counts, keep),
            lcs_y_counts: pick(&self.lcs_y_counts, keep),
            node_z_counts: pick(&self.node_z_counts, keep),
            acquired_unix_s: pick(&self.acquired_unix_s, keep),
            kx_nm_per_count: pick(&self.kx_nm_per_count, keep),
            ky_nm_per_count: pick(&self.ky_nm_per_count, keep),
            alpha_rad: pick(&self.alpha_rad, keep),
            kz_nm_per_count: pick(&self.kz_nm_per_count, keep),
        }
    }

    /// Appends one record's regression inputs.
    pub fn push(&mut self, r: &LccRecord) {
        self.lcs_x_counts.push(r.lcs_x_counts);
        self.lcs_y_counts.push(r.lcs_y_counts);
        self.node_z_counts.push(r.node_z_counts);
        self.acquired_unix_s.push(r.acquired_unix_s);
        self.kx_nm_per_count.push(r.kx_nm_per_count);
        self.ky_nm_per_count.push(r.ky_nm_per_count);
        self.alpha_rad.push(r.alpha_rad);
        self.kz_nm_per_count.push(r.kz_nm_per_count);
    }
}

impl<'a> FromIterator<&'a LccRecord> for LccColumns {
    fn from_iter<I: IntoIterator<Item = &'a LccRecord>>(records: I) -> Self {
        let mut columns = Self::default();
        for r in records {
            columns.push(r);
        }
        columns
    }
}

/// A calibration coefficient tracked by a store's age-dynamics query.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Coefficient {
    /// K̄x (nm per count).
    KxNmPerCount,
    /// K̄y (nm per count).
    KyNmPerCount,
    /// α (rad).
    AlphaRad,
    /// Kz (nm per count).
    KzNmPerCount,
}

/// How a store's age-dynamics query groups records.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrendGrouping {
    /// One point per run (the whole field aggregated).
    PerRun,
    /// One point per UTC calendar day.
    PerDay,
    /// One point per node (x, y, z) and run: the history of each node.
    PerNodePerRun,
}

/// Mean and spread of one coefficient in one group.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CoefficientStat {
    /// Number of values.
    pub n: u64,
    /// Mean.
    pub mean: f64,
    /// Sample standard deviation (n − 1 denominator; 0 if n = 1).
    pub std_dev: f64,
    /// Standard uncertainty of the mean, std_dev/√n.
    pub std_uncertainty: f64,
}

/// One point of an age-dynamics trend.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrendPoint {
    /// Group key: run id, `YYYY-MM-DD`, or `x,y,z@run`.
    pub key: String,
    /// Mean acquisition time of the group (UTC s).
    pub mean_unix_s: f64,
    /// First acquisition time of the group (UTC s).
    pub first_unix_s: f64,
    /// Last acquisition time of the group (UTC s).
    pub last_unix_s: f64,
    /// Statistics of the coefficient (absent if no value, e.g. Kz not measured).
    pub stat: Option<CoefficientStat>,
}

/// One finding of a store's integrity check.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct IntegrityProblem {
    /// Short machine-readable class, e.g. `non_finite`, `nonpositive_lcc`, `done_without_records`.
    pub kind: String,
    /// Human-readable detail naming the row.
    pub detail: String,
}

/// Result of a store's integrity check.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct IntegrityReport {
    /// Problems the database engine itself reports (SQLite: lines of `PRAGMA integrity_check`
    /// other than `ok`, and `PRAGMA foreign_key_check` rows).
    pub sqlite: Vec<String>,
    /// Semantic problems.
    pub problems: Vec<IntegrityProblem>,
}

impl IntegrityReport {
    /// True if no problem was found.
    #[must_use]
    pub fn is_ok(&self) -> bool {
        self.sqlite.is_empty() && self.problems.is_empty()
    }
}
