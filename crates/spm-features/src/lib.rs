//! # spm-features: recognition of surface features (pure: no IO, no clock, no RNG)
//!
//! - [`detect`]: hills or pits in a [`HeightMap`](spm_hal::HeightMap), localised to
//!   sub-pixel precision by a Gaussian least-squares fit, each with its time
//!   of acquisition (needed for drift), amplitude, quality, and uncertainty;
//!   features cut by the border and defects are rejected with a reason.
//! - [`crb`]: Cramér–Rao bounds of the localisation for the same feature model,
//!   pixel pitch and noise, and DESIGN §5's closed form `√(2/π)·p·σn/A`.
//! - [`lattice_vectors`]: lattice directions of a frame from neighbour statistics.
//! - [`lcs_with_vertex`], [`lcs_neighbours`], [`find_lcs_nearest`]: local
//!   calibration structures (A, B, C triangles matching a standard) in counts,
//!   with tolerances wide enough for an uncalibrated scanner.
//!
//! ```
//! use spm_features::{detect, DetectionConfig};
//! use spm_hal::{CountPoint, Counts, Frame, ScanRequest, Seconds, TraceHalf};
//!
//! // A Gaussian hill at (103.3, 98.6) counts, scanned 21×21 with a 1-count step.
//! let request = ScanRequest::centred_square(
//!     CountPoint::from_counts(100.0, 100.0), Counts(1.0), 21, Seconds(1e-4));
//! let frame = Frame::from_fn(request, Seconds(0.0), |p, _| {
//!     let r2 = (p.x.value() - 103.3).powi(2) + (p.y.value() - 98.6).powi(2);
//!     Counts(5.0 * (-r2 / (2.0 * 2.0 * 2.0)).exp())
//! });
//! let map = frame.height_map(TraceHalf::Forward)?;
//! let found = detect(&map, &DetectionConfig::default())?;
//! assert_eq!(found.features.len(), 1);
//! let f = &found.features[0];
//! assert!((f.position.x.value() - 103.3).abs() < 1e-3);
//! assert!((f.position.y.value() - 98.6).abs() < 1e-3);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
#![doc = include_str!("../README.md")]
#![warn(missing_docs)]

pub mod cells;
pub mod crb;
mod detect;
mod error;
mod fit;
mod lattice;
mod lcs;
mod shift;
pub mod step;

pub use crb::{
    CramerRaoBound, GaussianFeatureModel, design_cramer_rao, gaussian_cramer_rao,
    profile_cramer_rao,
};
pub use detect::{
    Detection, DetectionConfig, Feature, FeatureQuality, MIN_MAP_SIDE, Polarity,
    PositionUncertainty, RejectReason, Rejection, detect, nearest_index,
};
pub use error::FeatureError;
pub use lattice::{
    Lattice, LatticeConfig, LatticeVector, VectorCluster, lattice_vectors,
    nearest_neighbour_distance, neighbour_vector_clusters, positions,
};
pub use lcs::{
    HOPG_LATTICE_NM, Lcs, LcsCandidates, LcsConfig, LcsStandard, find_lcs_at_nearest_vertex,
    find_lcs_nearest, lcs_candidates, lcs_neighbours, lcs_with_vertex,
};
pub use shift::{
    ColumnShift, ShiftConfig, counter_pair_shifts, trace_retrace_shifts, track_one_way,
};
pub use step::{StepConfig, StepMeasurement, StepRejection, measure_step, measure_step_pair};
