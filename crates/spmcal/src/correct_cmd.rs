//! `spmcal correct IMAGE --surfaces surfaces.json --out OUT.gsf [--direction direct|counter]
//! [--nominal-nm-per-count K]`.
//!
//! The raster in scanner counts comes from the file when it records it (GSF
//! keys `spmcal_origin_x_counts`, `spmcal_origin_y_counts` and
//! `spmcal_pixel_step_counts`, for a simulated or controller-exported frame);
//! for any other file the controller's nominal
//! sensitivity (`--nominal-nm-per-count`) turns the file's nm geometry back into
//! the counts it commanded. The heights are kept in the file's unit. Pixels of
//! the output grid outside the scanned area are filled with the mean height
//! (GSF stores no NaN); their number is recorded in the header.

use crate::RasterDirection;
use crate::error::CliError;
use spm_correction::{
    Integration, Interpolation, Parallelism, RasterGeometry, Route, SurfaceSet,
    correct_and_resample,
};
use spm_formats::{Channel, Direction};
use spm_hal::{CountPoint, Counts, ScanDirection};
use std::path::Path;

fn bad(message: String) -> CliError {
    CliError::BadInput(message)
}

/// The raster of `channel` in counts.
fn geometry(
    file: &spm_formats::SpmFile,
    channel: &Channel,
    nominal_nm_per_count: Option<f64>,
    image: &Path,
) -> Result<RasterGeometry, CliError> {
    let key = |k: &str| -> Result<Option<f64>, CliError> {
        file.header_value(k)
            .map(|v| {
                v.trim().parse::<f64>().map_err(|_| {
                    bad(format!(
                        "{}: header {k} = {v:?} is not a number",
                        image.display()
                    ))
                })
            })
            .transpose()
    };
    let (nx, ny) = (channel.nx(), channel.ny());
    let stored = (
        key("spmcal_origin_x_counts")?,
        key("spmcal_origin_y_counts")?,
        key("spmcal_pixel_step_counts")?,
    );
    let (origin, step) = if let (Some(x), Some(y), Some(step)) = stored {
        (CountPoint::from_counts(x, y), step)
    } else {
        let k = nominal_nm_per_count.ok_or_else(|| {
            bad(format!(
                "{}: the file does not record its raster in scanner counts; give the controller's \
                 nominal sensitivity with --nominal-nm-per-count",
                image.display()
            ))
        })?;
        if !(k.is_finite() && k > 0.0) {
            return Err(bad(format!(
                "--nominal-nm-per-count {k}: must be a number > 0"
            )));
        }
        let pixel_nm = channel.pixel_x_nm().ok_or_else(|| {
            bad(format!(
                "{}: no physical pixel size in the file",
                image.display()
            ))
        })?;
        let step = pixel_nm / k;
        let cx = channel.center_x_nm().unwrap_or(0.0) / k;
        let cy = channel.center_y_nm().unwrap_or(0.0) / k;
        (
            CountPoint::from_counts(
                cx - step * (nx as f64 - 1.0) / 2.0,
                cy - step * (ny as f64 - 1.0) / 2.0,
            ),
            step,
        )
    };
    RasterGeometry::new(origin, Counts(step), nx, ny)
        .map_err(|e| bad(format!("{}: {e}", image.display())))
}

/// Largest surfaces file read, bytes.
const MAX_SURFACES_BYTES: u64 = 64 << 20;

/// Physical range of a sensitivity, nm per count (a 1 µm field over 2¹⁶ counts is 0.015).
const SENSITIVITY_RANGE_NM_PER_COUNT: (f64, f64) = (1e-9, 1e3);

/// Checks the plane's coefficients where the image lies: K̄x, K̄y and K̄yy = K̄y cos α
/// finite and in [`SENSITIVITY_RANGE_NM_PER_COUNT`], |α| < π/2 (a raster, not a mirror),
/// on a grid of up to 65 × 65 points over the raster including its corners.
fn check_plane(
    plane: &spm_correction::PlaneSurfaces,
    geometry: &RasterGeometry,
    surfaces: &Path,
) -> Result<(), CliError> {
    let (lo, hi) = SENSITIVITY_RANGE_NM_PER_COUNT;
    let samples = |n: usize| -> Vec<f64> {
        let k = n.clamp(1, 65);
        if k == 1 || n <= 1 {
            return vec![0.0];
        }
        (0..k)
            .map(|i| (n - 1) as f64 * i as f64 / (k - 1) as f64)
            .collect()
    };
    let (nx, ny) = (geometry.columns, geometry.rows);
    for row in samples(ny) {
        for column in samples(nx) {
            let (x, y) = (geometry.x_counts(column), geometry.y_counts(row));
            let kx = plane.kx_nm_per_count.surface.evaluate(x, y);
            let ky = plane.ky_nm_per_count.surface.evaluate(x, y);
            let alpha = plane.alpha_rad.surface.evaluate(x, y);
            let kyy = plane.kyy_nm_per_count.surface.evaluate(x, y);
            for (field, value) in [
                ("kx_nm_per_count", kx),
                ("ky_nm_per_count", ky),
                ("kyy_nm_per_count", kyy),
            ] {
                if !(value.is_finite() && (lo..=hi).contains(&value)) {
                    return Err(bad(format!(
                        "{}: plane z = {}: field `{field}` = {value} at ({x:.0}, {y:.0}) counts \
                         is outside [{lo}, {hi}] nm/count",
                        surfaces.display(),
                        plane.z_counts
                    )));
                }
            }
            if !(alpha.is_finite() && alpha.abs() < std::f64::consts::FRAC_PI_2) {
                return Err(bad(format!(
                    "{}: plane z = {}: field `alpha_rad` = {alpha} at ({x:.0}, {y:.0}) counts \
                     must lie in (−π/2, π/2)",
                    surfaces.display(),
                    plane.z_counts
                )));
            }
        }
    }
    Ok(())
}

pub fn run(
    image: &Path,
    surfaces: &Path,
    out: &Path,
    direction: RasterDirection,
    nominal_nm_per_count: Option<f64>,
    z_counts: Option<f64>,
) -> Result<(), CliError> {
    crate::files::check_input(image, "image")?;
    crate::files::check_output(out, "--out", &[image, surfaces])?;
    let file = spm_formats::read_any(image).map_err(|e| bad(e.to_string()))?;
    let channel = file
        .channels
        .iter()
        .find(|c| c.direction() == Direction::Forward && c.unit() == "m")
        .or_else(|| file.channels.first())
        .ok_or_else(|| bad(format!("{}: no image channel", image.display())))?;
    let bytes = crate::files::read_limited(surfaces, "surfaces file", MAX_SURFACES_BYTES)?;
    let text = String::from_utf8(bytes)
        .map_err(|_| bad(format!("{}: not UTF-8 text", surfaces.display())))?;
    let set = SurfaceSet::from_json_str(&text)
        .map_err(|e| bad(format!("{}: {e}", surfaces.display())))?;
    if let Some(z) = z_counts
        && !z.is_finite()
    {
        return Err(bad(format!("--z-counts {z} must be a finite number")));
    }
    let plane = set
        .plane_nearest(z_counts.unwrap_or(0.0))
        .map_err(|e| bad(format!("{}: {e}", surfaces.display())))?;
    // The lateral field at the image's Z level: the bracketing planes blended (issue 15).
    let field =
        spm_correction::field_at_z(&set, z_counts.unwrap_or(plane.z_counts), Route::Products)
            .map_err(|e| bad(format!("{}: {e}", surfaces.display())))?;
    let geometry = geometry(&file, channel, nominal_nm_per_count, image)?;
    check_plane(plane, &geometry, surfaces)?;
    if let Some(z) = z_counts {
        let (lower, upper, _) = set
            .bracketing_planes(z)
            .map_err(|e| bad(format!("{}: {e}", surfaces.display())))?;
        check_plane(lower, &geometry, surfaces)?;
        check_plane(upper, &geometry, surfaces)?;
    }
    if !channel.data().iter().any(|v| v.is_finite()) {
        return Err(bad(format!(
            "{}: channel {:?} holds no finite height (all NaN or infinite)",
            image.display(),
            channel.name()
        )));
    }
    // Display orientation (row 0 = top) → scanner geometry (row 0 = smallest y).
    let (nx, ny) = (channel.nx(), channel.ny());
    let mut heights = Vec::with_capacity(nx * ny);
    for row in (0..ny).rev() {
        heights.extend_from_slice(&channel.data()[row * nx..(row + 1) * nx]);
    }
    let scan_direction = match direction {
        RasterDirection::Direct => ScanDirection::Direct,
        RasterDirection::Counter => ScanDirection::Counter,
    };
    let (grid, resampled) = correct_and_resample(
        &field,
        &geometry,
        scan_direction,
        &Integration::default(),
        &heights,
        None,
        Interpolation::Bilinear,
        Parallelism::AllCores,
    )
    .map_err(|e| CliError::RunFailed(format!("correcting {}: {e}", image.display())))?;
    let valid: Vec<f64> = resampled
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    let fill = valid.iter().sum::<f64>() / valid.len().max(1) as f64;
    let filled = resampled.len() - valid.len();
    let mut display = Vec::with_capacity(resampled.len());
    for row in (0..grid.rows).rev() {
        display.extend(
            resampled[row * grid.columns..(row + 1) * grid.columns]
                .iter()
                .map(|v| if v.is_finite() { *v } else { fill }),
        );
    }
    let step_nm = grid.step_nm.value();
    let corrected = Channel::new(
        format!("{} (corrected)", channel.name()),
        Direction::Forward,
        channel.unit(),
        grid.columns,
        grid.rows,
        display,
    )
    .map_err(|e| CliError::RunFailed(e.to_string()))?
    .with_size_nm(step_nm * grid.columns as f64, step_nm * grid.rows as f64);
    let filled_text = filled.to_string();
    let source = image.display().to_string();
    let surfaces_text = surfaces.display().to_string();
    let partial = crate::files::temporary_beside(out);
    spm_formats::write_gsf(
        &partial,
        &corrected,
        &[
            ("spmcal_source", source.as_str()),
            ("spmcal_surfaces", surfaces_text.as_str()),
            ("spmcal_filled_outside_pixels", filled_text.as_str()),
        ],
    )
    .and_then(|()| {
        std::fs::rename(&partial, out).map_err(|source| spm_formats::FormatError::Io {
            path: out.to_path_buf(),
            action: "cannot write",
            source,
        })
    })
    .map_err(|e| {
        let _ = std::fs::remove_file(&partial);
        CliError::RunFailed(e.to_string())
    })?;
    crate::outln!(
        "{} → {} ({}×{} px of {:.4} nm; {} pixels outside the scan filled with the mean)",
        image.display(),
        out.display(),
        grid.columns,
        grid.rows,
        step_nm,
        filled
    );
    Ok(())
}
