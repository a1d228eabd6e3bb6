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
#![warn(missing_docs)]

pub mod config;
pub mod lcc;
pub mod plan;

pub use config::{
    ApertureConfig, AttachConfig, AttachTarget, ConfigError, DriftConfig, FailureConfig,
    FeaturePolarity, MeasurementMethod, MotionConfig, NeighbourSet, NetConfig, NetKind, PlanConfig,
    SkippingConfig, StandardConfig, ValidationError, VariantConfig,
};
pub use lcc::{
    CountCovariance, KzEstimate, LccError, LccEstimate, Metric, StandardVector, StepObservation,
    VectorObservation, solve_kz, solve_lcc, solve_metric_system,
};
pub use plan::{GridNode, NetGeometry, NetPlan, PauseLaw, PlanError, PlanVisit, ZLevel};
