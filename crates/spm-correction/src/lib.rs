//! # spm-correction: image correction by distributed calibration (Lapshin, eqs. 5–12)
//!
//! Pure math: no IO, no clock. Given the regression surfaces of a calibration
//! ([`SurfaceSet`], what `surfaces.json` holds) this crate computes
//!
//! - corrected coordinates along **any trajectory** (eq. 5): unit steps
//!   ([`correct_unit_steps`]) or a piecewise-linear path by quadrature ([`correct_polyline`]);
//! - corrected coordinates of every pixel of a **direct or counter raster** (eqs. 7–9, 12) in a
//!   common frame ([`correct_raster`] → [`CoordinateMap`]), analytic for polynomial surfaces
//!   (eq. 12 with the product surfaces of eq. 11, the integrals of eq. 10 for planes), by
//!   Gauss–Legendre quadrature otherwise or as a cross-check ([`Integration`]); the paper's
//!   closed forms literally in [`closed_form`];
//! - the image **resampled** onto a uniform nm grid by inverse mapping ([`resample`],
//!   bilinear or Catmull-Rom, NaN outside the data), heights through Kz ([`heights_nm`]);
//! - **scanner input dynamics** ([`dynamics`]): creep replayed along a command log, its law
//!   identified from attachment tracks, and images corrected along their effective trajectory;
//! - the **regression surfaces fitted** from a plane's calibration records ([`fit`]: eqs. 2,
//!   6, 11, 13, 14, the degree by BIC, the 1-form as an exact form, outliers, the bowl);
//! - **counter-scanned pairs**: drift from common features and drift-corrected coordinate maps
//!   ([`estimate_drift`], [`correct_counter_pair`]).
//!
//! ## The end-to-end call (what `spmcal correct` does)
//! ```no_run
//! # use spm_correction::*;
//! # fn run(json: &str, map: &spm_hal::HeightMap) -> Result<(), CorrectionError> {
//! let set = SurfaceSet::from_json_str(json)?;
//! let plane = set.plane_nearest(0.0)?;                     // the image's Z plane
//! let field = plane.field(Route::Products);                 // eq. 12 (or Route::Exact, eq. 9)
//! let geometry = RasterGeometry::of_height_map(map)?;
//! let coords = correct_raster(&field, &geometry, spm_hal::ScanDirection::Direct,
//!                             &Integration::default(), Parallelism::AllCores)?;
//! let heights = heights_nm(plane, &geometry, &map.z_counts)?;  // or keep counts
//! let grid = OutputGrid::covering(&coords, None)?;
//! let image_nm = resample(&heights, &coords, &grid, Interpolation::Bilinear,
//!                         Parallelism::AllCores)?;
//! # let _ = image_nm; Ok(()) }
//! ```
#![doc = include_str!("../README.md")]
#![warn(missing_docs)]

pub mod bench_support;
pub mod closed_form;
mod drift;
pub mod dynamics;
mod error;
mod field;
pub mod fit;
mod height;
pub mod hysteresis;
mod parallel;
mod quadrature;
mod raster;
mod resample;
mod surfaces;
mod trajectory;
mod vertical;

pub use drift::{
    CounterPairCorrection, DriftEstimate, FeatureMatch, FeatureSighting, SightingPair,
    correct_counter_pair, drift_corrected_map, estimate_drift, to_common_time,
};
pub use error::CorrectionError;
pub use field::{
    CorrectionField, FnField, FormCoefficients, LineAntiderivative, ProductField, SurfaceField,
    linear_times_cos, linear_times_sin,
};
pub use height::heights_nm;
pub use parallel::Parallelism;
pub use quadrature::{MAX_GAUSS_POINTS, Quadrature};
pub use raster::{
    CoordinateMap, Integration, RasterGeometry, YCoordinates, correct_raster,
    correct_raster_reusing,
};
pub use resample::{
    Interpolation, MAX_OUTPUT_PIXELS, OutputGrid, correct_and_resample, correct_and_resample_into,
    resample, resample_into,
};
pub use surfaces::{
    BlendedField, CountRegion, CountsConvention, FittedSurface, PlaneField, PlaneSurfaces,
    Provenance, Route, SURFACES_FORMAT_VERSION, SurfaceForm, SurfaceSet,
};
pub use trajectory::{correct_polyline, correct_unit_steps};
pub use vertical::{bowl_counts, field_at_z};
