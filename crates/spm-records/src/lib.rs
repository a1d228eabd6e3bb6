//! The records of Lapshin's distributed calibration (DESIGN §8) and the storage trait a
//! calibration run writes through.
//!
//! This crate is the seam between the calibration controller (`spm-calibration`) and the
//! databases that keep its results (`spm-cdb`: embedded SQLite, shared PostgreSQL). It holds
//! no I/O and links no database: a program that runs calibrations into its own store depends
//! on this crate and `spm-calibration` only.
//!
//! - [`LccRecord`] and the run/plan types ([`RunInfo`], [`PlanNode`], [`NodeState`], …).
//! - [`LCC_RECORD_COLUMNS`]: the one definition of the record columns (name, kind, order)
//!   that every store's schema, insert, select and export are built from;
//!   [`LccRecord::column_values`] and [`LccRecord::from_column_values`] convert.
//! - [`LccRecord::check`]: the validity rules every store applies before writing;
//!   [`LccRecord::implausibility`]: the range rules against the run's [`Plausibility`]
//!   limits (field, aperture, nominal sensitivity) that `cdb check` and the fit apply.
//! - [`DynamicsRecord`]: the scanner dynamics (hysteresis, creep) a run identified, as a
//!   versioned JSON object the stores keep beside the LCCs; [`DynamicsRecord::check`].
//! - [`ProgressStore`]: begin a run, read the plan's states, commit a node in one
//!   transaction, give a node up, finish the run.
#![doc = include_str!("../README.md")]

mod columns;
mod dynamics;
mod model;
mod plausibility;
mod store;

pub use columns::{
    ColumnKind, ColumnValue, LCC_RECORD_COLUMNS, LccColumn, OwnedColumnValue, POSITIVE_COLUMNS,
    RecordProblem, UNCERTAINTY_COLUMNS, id_problem,
};
pub use dynamics::{
    DYNAMICS_FORMAT_MAX_BYTES, DYNAMICS_MODEL_MAX_BYTES, DYNAMICS_RECORD_COLUMNS, DynamicsProblem,
    DynamicsRecord,
};
pub use model::{
    Coefficient, CoefficientStat, IntegrityProblem, IntegrityReport, LccColumns, LccRecord,
    NodeDone, NodeProgress, NodeState, PlanNode, ProgressSummary, RecordFilter, RunInfo, RunStatus,
    TrendGrouping, TrendPoint,
};
pub use plausibility::{APERTURES_FROM_NODE, NOMINAL_FACTOR, Plausibility};
pub use store::{MemoryStore, MemoryStoreError, ProgressStore};
