//! # spm-evaluation: a scanner calibration judged against a ground truth
//!
//! - [`accuracy`]: a correction field's residual distortion over the calibrated region and
//!   the lattice-constant error of small corrected images anywhere in it, against the true
//!   LCC field of the instrument's oracle (DESIGN §11); the per-image polynomial baseline.
//! - [`images`]: the image benchmark (issue 12): test images taken as a user takes them, every
//!   method's position and lattice error on them, the realistic grating polynomial.
//! - [`drift`]: the drift-insensitivity experiment's figures (relative vector errors against
//!   the truth, nearest-neighbour pairs, the RMS per drift velocity).
//! - [`cubic`]: the total-degree-3 polynomial map of the conventional corrections.
//! - [`competitors`]: the per-image trace/retrace corrections the benchmark compares with
//!   (after Yothers, Browder & Bumm 2017 and Zhang et al. 2019).
//! - [`rigid`]: residuals after the best rigid motion.
//! - [`validation`]: what a run says of itself without an oracle (held-out nodes, repeat
//!   agreement), on any backend.
//! - [`vertical`]: the vertical axis's surfaces (Kz, the bowl, the z-dependence of K̄x and
//!   K̄y) against the truth (report.json's `vertical`).
//!
//! The oracle is reached only through the `spm_hal::truth` traits; the simulator itself is
//! never named. No I/O, no command line, no clock: the caller takes the instrument and writes
//! the figures. Every fit is [`spm_regression::least_squares`] on the eq. (6) basis of
//! [`spm_regression::Polynomial2`].
#![doc = include_str!("../README.md")]

pub mod accuracy;
pub mod competitors;
pub mod cubic;
pub mod drift;
pub mod images;
pub mod rigid;
pub mod validation;
pub mod vertical;

pub use accuracy::{
    Accuracy, EvaluationGrid, PolynomialImage, ResidualField, evaluate, evaluate_field,
    polynomial_baseline, residual_field,
};
pub use cubic::CubicMap;
pub use images::ImageBenchmarkError;
pub use rigid::rigid_residuals;
