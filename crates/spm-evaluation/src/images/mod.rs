//! The image benchmark: the accuracy a user sees (issue 12, DESIGN §11 "first").
//!
//! After a calibration the same simulated instrument — every effect on, the same
//! seed stream going on — takes test images the way a user does: a move to the
//! image's place from wherever the previous image ended, the pause the plan's
//! pause law gives for that move (the wait a careful user makes for the creep), then
//! a direct raster and at once its counter raster (Lapshin 2007). Every method
//! corrects every image, and two figures are taken per image:
//!
//! - **position error**: the corrected coordinate of every pixel against the true
//!   tip position that pixel had in the simulator (scanner frame; hysteresis and
//!   creep as they acted during that image; drift and jitter excluded), after
//!   removing the best rigid motion. RMS and max, pm and % of the image side.
//! - **lattice error** (images that resolve the lattice): the counter-scanned pair
//!   is corrected with the method (drift from the atoms common to both images,
//!   `correct_counter_pair`), the direct image is resampled onto a uniform nm grid,
//!   spm-features detects the atoms and measures the three lattice vectors; their
//!   mean length against the standard's lattice constant, and the largest
//!   deviation of the angles between them from 60°.
//!
//! The methods are correction fields integrated along the image's raster (eq. 9),
//! or direct maps (polynomials evaluated at each pixel's commanded counts).
//!
//! Modules: [`take`] (the image set and how it is taken), [`evaluate`] (the methods and
//! their figures), [`lattice`] (atoms matched across a counter-scanned pair, the lattice
//! measured on the corrected image), [`grating`] (the realistic grating polynomial).

use spm_correction::CorrectionError;

pub mod before_after;
pub mod evaluate;
pub mod grating;
pub mod lattice;
mod neighbours;
pub mod take;
mod user_file;

pub use crate::cubic::CubicMap;
pub use evaluate::{
    Competitor, DynamicsSummary, ImageBenchmark, ImageCorrection, ImageFigures, ImageMethod,
    ImageMethodSummary, ImageRow, PairLattice, evaluate_images, lattice_of_pairs,
};
pub use grating::{GratingConfig, grating_polynomial};
pub use lattice::{match_features, measure_lattice};
pub use take::{
    CountRegion, ImageSetConfig, ImageSize, TestImage, take_images_without_truth, take_test_images,
};
pub use user_file::ruler_outcome;

/// Why the image benchmark failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ImageBenchmarkError {
    /// The simulated instrument failed repeatedly on one image.
    #[error("test image {index} ({what}): the instrument failed {attempts} times, last: {message}")]
    Instrument {
        /// Index of the image in the set.
        index: usize,
        /// What was being done.
        what: &'static str,
        /// Attempts made.
        attempts: usize,
        /// The last error.
        message: String,
    },
    /// A correction step failed.
    #[error("test image correction: {0}")]
    Correction(#[from] CorrectionError),
    /// The configuration cannot produce an image set.
    #[error("image benchmark configuration: {0}")]
    Config(String),
    /// The grating calibration image could not be indexed or fitted.
    #[error("grating polynomial: {0}")]
    Grating(String),
}
