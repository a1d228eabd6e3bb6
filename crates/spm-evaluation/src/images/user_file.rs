//! The `user_file_*` methods: each test image written as a file with what a controller
//! records, read back and mapped by `spm_apply` with the calibration file, as `spmcal correct`
//! does (in memory: no file is written).

use super::ImageBenchmarkError;
use super::take::TestImage;
use spm_correction::CoordinateMap;
use spm_hal::ScanDirection;

/// [`ImageCorrection::UserFile`]: the image as a `.gsf` in memory (heights in display
/// orientation, the raster in counts, the scan path, the scanner and counts convention), read
/// back and mapped through `spm_apply` as `spmcal correct` does.
///
/// With `ruler` (and the calibration's dynamics, no recorded history), the approach creep and
/// drift are then measured against the lattice in the image as `spmcal correct --ruler` does;
/// an image whose lattice is not resolved (or not found) keeps the file-alone map, as a user
/// whose `--ruler` is refused corrects without it.
pub(super) fn user_file_map(
    set: &spm_correction::SurfaceSet,
    image: &TestImage,
    recorded: Option<&spm_correction::dynamics::CommandHistory>,
    ruler: Option<&spm_apply::ruler::LatticeRuler>,
) -> Result<CoordinateMap, ImageBenchmarkError> {
    let (map, raster) = file_map(set, image, recorded)?;
    if let (Some(ruler), Some(d), None) = (ruler, &set.dynamics, recorded) {
        let law = d.creep.law()?;
        let times = spm_apply::dynamic::pixel_times(&raster, spm_apply::dynamic::Half::Trace)?;
        // The heights in the map's order (scanner geometry, bottom row first).
        if let Ok(found) =
            spm_apply::ruler::estimate_from_lattice(&image.map.z_counts, &map, &times, &law, ruler)
        {
            return Ok(found.corrected(&map, &times)?);
        }
    }
    Ok(map)
}

/// [`ImageCorrection::UserFileCounter`]: the two images of a counter-scanned pair (the first
/// scanned first) each mapped from the file alone, then the approach creep and drift measured
/// between them ([`spm_apply::counter::estimate_from_pair`]) and removed from both, as
/// `spmcal correct --counter` does. The pair's clock: each file's pixel times from its line
/// time, the second file's shifted by the time between the two frames' first pixels (what a
/// controller's time stamps record). A pair whose features do not match, or a calibration
/// without dynamics, keeps the file-alone maps.
///
/// [`ImageCorrection::UserFileCounter`]: super::evaluate::ImageCorrection::UserFileCounter
pub(super) fn user_file_pair_maps(
    set: &spm_correction::SurfaceSet,
    first: &TestImage,
    second: &TestImage,
    spacing: &spm_apply::ruler::LatticeRuler,
) -> Result<(CoordinateMap, CoordinateMap), ImageBenchmarkError> {
    let (map1, raster1) = file_map(set, first, None)?;
    let raster2 = file_raster(set, second)?;
    let Some(d) = &set.dynamics else {
        return Ok((map1, file_map(set, second, None)?.0));
    };
    let start = |t: &[f64]| t.iter().copied().fold(f64::INFINITY, f64::min);
    let delay_s = start(&second.time_acquisition_s) - start(&first.time_acquisition_s);
    let field = set
        .plane_nearest(0.0)?
        .field(spm_correction::Route::Products);
    // The heights in the map's order (scanner geometry, bottom row first), the trace halves.
    let pair = spm_apply::counter::pair_maps(
        &field,
        d,
        (
            spm_apply::counter::PairFile {
                raster: &raster1,
                heights: &first.map.z_counts,
            },
            &map1,
        ),
        spm_apply::counter::PairFile {
            raster: &raster2,
            heights: &second.map.z_counts,
        },
        delay_s,
        spacing,
    );
    match pair {
        Ok((found, t1, (m2, t2))) => Ok((found.corrected(&map1, &t1)?, found.corrected(&m2, &t2)?)),
        // A pair whose features do not match keeps the file-alone maps, as a user whose
        // --counter is refused corrects without it.
        Err(_) => Ok((map1, file_map(set, second, None)?.0)),
    }
}

/// The image written as a file with what a controller records, read back, checked by the
/// guard rails, and its raster read from the file.
fn file_raster(
    set: &spm_correction::SurfaceSet,
    image: &TestImage,
) -> Result<spm_apply::FileRaster, ImageBenchmarkError> {
    use spm_apply::{
        ApplyOptions, FileRaster, KEY_CONVENTION, KEY_LINE_TIME, KEY_ORIGIN_X, KEY_ORIGIN_Y,
        KEY_SCAN_PATH, KEY_SCANNER, KEY_STEP,
    };
    let m = &image.map;
    let fail = |what: String| ImageBenchmarkError::Config(format!("user file: {what}"));
    let mut display = Vec::with_capacity(m.columns * m.rows);
    for row in (0..m.rows).rev() {
        display.extend_from_slice(&m.z_counts[row * m.columns..(row + 1) * m.columns]);
    }
    let k = set.provenance.nominal_nm_per_count.unwrap_or(1.0);
    let side = |n: usize| m.pixel_step.value() * n as f64 * k;
    let channel = spm_formats::Channel::new(
        "Z",
        spm_formats::Direction::Forward,
        "counts",
        m.columns,
        m.rows,
        display,
    )
    .map_err(|e| fail(e.to_string()))?
    .with_size_nm(side(m.columns), side(m.rows));
    let (x0, y0, step) = (
        m.origin.x.value().to_string(),
        m.origin.y.value().to_string(),
        m.pixel_step.value().to_string(),
    );
    let path = match image.direction {
        ScanDirection::Direct => "direct",
        ScanDirection::Counter => "counter",
    };
    // What a controller records: the duration of one trace.
    let line_time = (image.dwell_s * m.columns as f64).to_string();
    let bytes = spm_formats::encode_gsf(
        &channel,
        &[
            (KEY_ORIGIN_X, x0.as_str()),
            (KEY_ORIGIN_Y, y0.as_str()),
            (KEY_STEP, step.as_str()),
            (KEY_SCAN_PATH, path),
            (KEY_SCANNER, set.provenance.scanner_id.as_str()),
            (KEY_CONVENTION, "centred_signed"),
            (KEY_LINE_TIME, line_time.as_str()),
        ],
    )
    .map_err(|e| fail(e.to_string()))?;
    let file = spm_formats::read_bytes(&bytes, std::path::Path::new("test-image.gsf"))
        .map_err(|e| fail(e.to_string()))?;
    let channel = file
        .channels
        .first()
        .ok_or_else(|| fail("no channel read back".to_owned()))?;
    let raster = FileRaster::of(&file, channel, None, None).map_err(|e| fail(e.to_string()))?;
    let plane = set.plane_nearest(0.0)?;
    // The benchmark's places reach the field's edge: extrapolation is allowed (and measured).
    let options = ApplyOptions {
        allow_extrapolation: true,
        ..ApplyOptions::default()
    };
    spm_apply::check(&file, set, plane, &raster, &options).map_err(|e| fail(e.to_string()))?;
    Ok(raster)
}

/// The image written as a file, read back and mapped (file alone, or with `recorded`), and
/// the raster read from the file.
fn file_map(
    set: &spm_correction::SurfaceSet,
    image: &TestImage,
    recorded: Option<&spm_correction::dynamics::CommandHistory>,
) -> Result<(CoordinateMap, spm_apply::FileRaster), ImageBenchmarkError> {
    let raster = file_raster(set, image)?;
    let field = set
        .plane_nearest(0.0)?
        .field(spm_correction::Route::Products);
    let half = spm_apply::dynamic::Half::Trace;
    let (map, _) = match (&set.dynamics, recorded) {
        (Some(d), Some(history)) => spm_apply::dynamic::recorded_map(
            &field,
            &raster,
            d,
            half,
            history,
            &image.time_acquisition_s,
        )?,
        (Some(d), None) => spm_apply::dynamic::dynamic_map(&field, &raster, d, half)?,
        (None, _) => spm_apply::coordinate_map(&field, &raster)?,
    };
    Ok((map, raster))
}

/// What `spmcal correct --ruler` finds on one test image (the file-alone map of
/// `user_file_map`, then [`spm_apply::ruler::estimate_from_lattice`]): the estimate, or why
/// the ruler refused the image. For developer probes of the ruler on the benchmark's images.
///
/// # Errors
/// As `user_file_map`; [`ImageBenchmarkError::Config`] when the calibration has no dynamics.
pub fn ruler_outcome(
    set: &spm_correction::SurfaceSet,
    image: &TestImage,
    ruler: &spm_apply::ruler::LatticeRuler,
) -> Result<Result<spm_apply::ruler::RulerEstimate, String>, ImageBenchmarkError> {
    let d = set.dynamics.as_ref().ok_or_else(|| {
        ImageBenchmarkError::Config("ruler: the calibration file has no dynamics".to_owned())
    })?;
    let (map, raster) = file_map(set, image, None)?;
    let law = d.creep.law()?;
    let times = spm_apply::dynamic::pixel_times(&raster, spm_apply::dynamic::Half::Trace)?;
    Ok(
        spm_apply::ruler::estimate_from_lattice(&image.map.z_counts, &map, &times, &law, ruler)
            .map_err(|e| e.to_string()),
    )
}
