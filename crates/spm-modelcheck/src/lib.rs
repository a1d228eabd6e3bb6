//! # spm-modelcheck: simulation versus measurement
//!
//! Given measured images of a crystal lattice (or feature lists), fit the
//! baseline model — the known lattice seen through a lumped linear scanner
//! (scales, obliquity, rotation) with constant drift and per-frame offsets —
//! show what it gets wrong, name the physical cause from a library of eleven
//! effects by evidence, extend the model, and measure the gain on held-out
//! features (DESIGN §10, §13).
//!
//! - [`diagnose`]: files → [`Diagnosis`] (the `spmcal diagnose` entry point);
//! - [`diagnose_features`]: the same from a [`FeatureSet`] already extracted;
//! - [`extract_features`]: images → feature observations with times;
//! - [`survey_channel`]: an image's lattice, whole and in a grid of cells;
//! - [`write_png`]: the residual figure;
//! - [`sim_patch`]: the fitted model as spm-sim configuration values.
//!
//! The effect library ([`EffectKind`]) — each a model extension whose
//! parameters carry units in their names:
//!
//! | effect | extension | parameters |
//! |---|---|---|
//! | `drift_acceleration` | ½·a·t² tip–sample displacement | `acceleration_{x,y}_nm_per_s2` |
//! | `creep` | input displacement c_f·lg(1 + t′/τ) per frame f, t′ since the frame start | `creep_{x,y}_nm_per_decade_frame{f}`, `time_constant_s` |
//! | `hysteresis` | fast-axis input −s·W·(1 − ξx²)·(h + g·ξx²), s = ±1 trace/retrace | `branch_half_separation_fraction` (h), `loop_shape` (g), `branch_separation_nm` |
//! | `scanner_nonlinearity` | input W·(q·ξ² + c·ξ³ + …) per axis, degree raised by evidence | `quadratic_{x,y}`, `cubic_{x,y}`, `order{k}_{x,y}` (at the frame edge), `polynomial_degree` |
//! | `nonorthogonality` | input W·g·ξx·ξy per axis (obliquity varying over the field) | `shear_gradient_{x,y}` |
//! | `crosstalk_xy` | input x += b·H·ξy², y += b·W·ξx² (quadratic crosstalk, bow) | `bow_x_from_y`, `bow_y_from_x` |
//! | `feedback_lag` | fast-axis input −s·v·τ | `time_constant_s`, `shift_nm` |
//! | `periodic_vibration` | A·cos(2πft + φ) per axis; with images, fitted on their pixels (`vibration.rs`), its alias family reported | `amplitude_{x,y}_nm`, `frequency_hz`, `phase_{x,y}_rad`; `pixel_level` |
//! | `tip_change` | jump (jx, jy) from time t_c on | `jump_{x,y}_nm`, `time_s` |
//! | `interlace` | slow-axis displacement ±½·d of forward/backward lines (d: backward features relative to forward); ramped: the slow axis moving on through every line, displacement 2d × the time within the line pair | `separation_y_nm`, `slow_axis_ramped` (0 stepped, 1 ramped) |
//! | `sinusoidal_drive` | fast-axis input W·[ξ + κ·(sin βξ − βξ)/β]: the fast axis driven by a sine in time, pixels equidistant in time, ±β of phase over a line | `amplitude_nm`, `phase_at_line_end_rad` (β), `drive_frequency_hz`, `sine_weight` (κ), `sine_fraction` (1 for a pure sine) |
//!
//! ξ is the commanded position over the frame half-size (W along x, H along y).
//! Time-dependent tip–sample effects are seen through each feature's footprint
//! over lines (see `docs/MODELCHECK.md`). An effect is reported only when it is
//! supported (ΔBIC), relevant (against the localisation uncertainty and the
//! lattice constant), plausible (every parameter in its physical range), not
//! encompassed by another, and lowers the held-out RMS; features that are not
//! the claimed lattice are refused ([`ModelCheckError::NotTheLattice`]).
//! The constant parts of nonorthogonality and linear crosstalk are inside the
//! baseline's lumped linear scanner and cannot be told apart from it.
#![doc = include_str!("../README.md")]
#![warn(missing_docs)]

mod diagnose;
mod extract;
mod grow;
mod index;
mod level;
mod model;
mod plot;
mod simmap;
mod sine;
mod survey;
mod types;
mod vibration;

pub use diagnose::{
    AliasFrequency, BaselineReport, CandidateScore, Diagnosis, FinalReport, Finding, ParamValue,
    PixelEvidence, Rejection, ResidualPoint, ResidualStructure, diagnose_features,
    diagnose_features_with_pixels, diagnose_indexed,
};
pub use extract::{
    ExtractOptions, ImageInput, Localiser, MapContext, diagnose, diagnose_paths, extract_features,
    features_from_height_map, pixel_image_from_height_map,
};
pub use index::{Indexing, MeasuredBasis, index_features};
pub use plot::{register_system_font, write_png};
pub use simmap::{
    InputKnot, MoveHistory, SimContext, SimParam, SimPatch, TipChangeEvent, sim_patch,
};
pub use survey::{
    CellLattice, MIN_PART_FEATURES, PartLattice, ROBUST_CELL_RESIDUAL_FACTOR, SurveyError,
    survey_channel,
};
pub use types::{
    EffectKind, FeatureObservation, FeatureSet, FrameInfo, HOPG_A_NM, LatticeSpec, LineDirection,
    ModelCheckError, Options, SI7X7_A_NM,
};
pub use vibration::PixelImage;
