//! One image of the standard before and after correction (issue 27's before/after figure):
//! the raw heights on the commanded raster through the nominal sensitivity, and the same
//! heights corrected as `spmcal correct` does (the calibration file alone, `user_file_map`)
//! and resampled onto a uniform nm grid of the same spacing.

use super::ImageBenchmarkError;
use super::take::TestImage;
use super::user_file::user_file_map;
use spm_correction::{Interpolation, OutputGrid, Parallelism, resample};
use spm_hal::Nanometres;

/// Heights on a uniform grid in nm.
#[derive(Debug, Clone, PartialEq)]
pub struct HeightsOnGrid {
    /// Columns (x).
    pub columns: usize,
    /// Rows (y), row 0 at the smallest y.
    pub rows: usize,
    /// Position of column 0, row 0, nm.
    pub origin_nm: [f64; 2],
    /// Spacing along both axes, nm.
    pub step_nm: f64,
    /// Heights, Z counts, relative to the raw image's median height (one reference for
    /// both images), `[row * columns + column]` (NaN where the corrected image has no data).
    pub z_counts: Vec<f64>,
}

/// The pair of [`before_after`].
#[derive(Debug, Clone, PartialEq)]
pub struct BeforeAfter {
    /// The image's place label.
    pub place: String,
    /// The raw image through the nominal sensitivity.
    pub before: HeightsOnGrid,
    /// The corrected image.
    pub after: HeightsOnGrid,
}

/// `image` before correction (its heights at the commanded pixel positions × the nominal
/// sensitivity `nominal_nm_per_count`) and after (mapped with the calibration file `set` as
/// `spmcal correct` does, resampled bilinearly onto a grid of the same spacing covering the
/// corrected image).
///
/// # Errors
/// [`ImageBenchmarkError`] when the image cannot be corrected or resampled (e.g. a map that
/// folds).
pub fn before_after(
    image: &TestImage,
    set: &spm_correction::SurfaceSet,
    nominal_nm_per_count: f64,
) -> Result<BeforeAfter, ImageBenchmarkError> {
    let m = &image.map;
    let step_nm = m.pixel_step.value() * nominal_nm_per_count;
    let mut finite: Vec<f64> = m
        .z_counts
        .iter()
        .copied()
        .filter(|z| z.is_finite())
        .collect();
    let reference = spm_regression::median(&mut finite).unwrap_or(0.0);
    let relative = |z: &[f64]| -> Vec<f64> { z.iter().map(|v| v - reference).collect() };
    let before = HeightsOnGrid {
        columns: m.columns,
        rows: m.rows,
        origin_nm: [
            m.origin.x.value() * nominal_nm_per_count,
            m.origin.y.value() * nominal_nm_per_count,
        ],
        step_nm,
        z_counts: relative(&m.z_counts),
    };
    let map = user_file_map(set, image, None, None)?;
    let grid = OutputGrid::covering(&map, Some(Nanometres(step_nm)))?;
    let z = resample(
        &m.z_counts,
        &map,
        &grid,
        Interpolation::Bilinear,
        Parallelism::Sequential,
    )?;
    let after = HeightsOnGrid {
        columns: grid.columns,
        rows: grid.rows,
        origin_nm: [grid.origin_nm.x.value(), grid.origin_nm.y.value()],
        step_nm: grid.step_nm.value(),
        z_counts: relative(&z),
    };
    Ok(BeforeAfter {
        place: image.place.clone(),
        before,
        after,
    })
}
