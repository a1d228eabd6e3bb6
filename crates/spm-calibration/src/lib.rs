//! # spm-calibration: LCC solving, net plans and the adaptive distributed-calibration controller
//!
//! Lapshin's distributed calibration (DESIGN §7): the scanner field is covered by a net of
//! nodes; at every node the probe attaches to a feature of a crystal standard, recognises a
//! local calibration structure (LCS), measures its vectors drift-free by skipping (or
//! counter-scanning), and turns them into local calibration coefficients (K̄x, K̄y, α, Kz)
//! stored in the CDB.
//!
//! - [`lcc`]: the LCCs from measured vectors, with propagated uncertainties; Kz from steps.
//! - [`plan`]: net geometries (Fig. 1a/1b), serpentine visiting order, repeats, pause law.
//! - [`config`]: the plan as typed TOML (`[plan]` table; see the module docs for the job file).
//! - [`machine`]: the node state machine of Fig. 2 as a pure step function.
//! - [`runner`]: the loop over a [`spm_hal::Microscope`]: executes the machine's actions with
//!   `spm-fos`, commits each node in one transaction to a [`ProgressStore`] (the CDB),
//!   reports to an [`Observer`], resumes where a killed run stopped.
#![warn(missing_docs)]

pub mod config;
pub mod lcc;
pub mod machine;
pub mod plan;
pub mod runner;

pub use config::{
    ApertureConfig, AttachConfig, AttachTarget, ConfigError, DriftConfig, FailureConfig,
    FeaturePolarity, MeasurementMethod, MotionConfig, NeighbourSet, NetConfig, NetKind, PlanConfig,
    SkippingConfig, StandardConfig, ValidationError, VariantConfig,
};
pub use lcc::{
    CountCovariance, KzEstimate, LccError, LccEstimate, Metric, StandardVector, StepObservation,
    VectorObservation, solve_kz, solve_lcc, solve_metric_system,
};
pub use machine::{
    Action, Anchor, ApertureResult, AttachResult, CounterResult, CycleCounts, Event, Failure,
    GiveUpReason, MachineParams, NodeMachine, NodeMeasurement, SkipResult, VectorTarget,
};
pub use plan::{GridNode, NetGeometry, NetPlan, PauseLaw, PlanError, PlanVisit, ZLevel};
pub use runner::{
    Calibrator, FosParams, GivenUpVisit, MemoryStore, MemoryStoreError, NoObserver, Observer,
    ProgressStore, RunError, RunOptions, RunReport,
};
