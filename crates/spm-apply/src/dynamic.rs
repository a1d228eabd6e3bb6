//! The raster's own dynamics in a correction (issue 23): the file's raster is replayed as
//! commands — every line's trace and retrace at the file's line time, the slow axis stepping
//! between lines — through the calibration file's scanner dynamics (PI hysteresis per axis,
//! then the creep of its output), and eq. (5) is summed over the increments of the effective
//! input pixel to pixel (`spm_correction::dynamics::correct_effective_raster`).
//!
//! Of the probe's history before the frame nothing is known from a file alone: the replay
//! starts settled at the frame's first pixel (no creep of the approach move, the hysteresis
//! demagnetised there). What the image then still carries of the approach is named in the
//! output ([`crate::DynamicsUsed`]).

use spm_correction::CorrectionError;
use spm_correction::dynamics::{CommandHistory, correct_effective_raster};
use spm_correction::hysteresis::ScannerDynamics;
use spm_correction::{CoordinateMap, CorrectionField, Quadrature, YCoordinates, correct_polyline};
use spm_hal::CountPoint;

use crate::FileRaster;

/// Which half of the frame a channel holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Half {
    /// The traces (forward).
    Trace,
    /// The retraces (backward).
    Retrace,
}

/// Commanded position of every pixel of both halves and the instrument time at which it was
/// taken, in acquisition order, with the command history of the frame.
struct Replay {
    history: CommandHistory,
    /// Per half: (display column, display row, time s, commanded counts), acquisition order.
    pixels: [Vec<(usize, usize, f64, CountPoint)>; 2],
}

fn replay(raster: &FileRaster, line_time_s: f64) -> Replay {
    let (nx, ny) = (raster.columns, raster.rows);
    let dwell = line_time_s / nx as f64;
    let order: Vec<usize> = raster.line_columns().collect();
    let mut history = CommandHistory::default();
    let mut trace = Vec::with_capacity(nx * ny);
    let mut retrace = Vec::with_capacity(nx * ny);
    for line in 0..ny {
        let row = raster.display_row(line);
        let base = 2.0 * line_time_s * line as f64;
        let at = |column: usize| raster.pixel_counts(column as f64, row as f64);
        let (first, last) = (order[0], order[nx - 1]);
        let xy = |p: CountPoint| [p.x.value(), p.y.value()];
        history.ramp_to(base + 0.5 * dwell, xy(at(first)));
        history.ramp_to(base + (nx as f64 - 0.5) * dwell, xy(at(last)));
        history.ramp_to(base + line_time_s + 0.5 * dwell, xy(at(last)));
        history.ramp_to(
            base + line_time_s + (nx as f64 - 0.5) * dwell,
            xy(at(first)),
        );
        for (k, &column) in order.iter().enumerate() {
            trace.push((column, row, base + (k as f64 + 0.5) * dwell, at(column)));
        }
        for (k, &column) in order.iter().rev().enumerate() {
            retrace.push((
                column,
                row,
                base + line_time_s + (k as f64 + 0.5) * dwell,
                at(column),
            ));
        }
    }
    Replay {
        history,
        pixels: [trace, retrace],
    }
}

/// The coordinate map of one half of `raster` along its effective trajectory, and the nm
/// position (from the field's origin, static reference state) of the raster's bottom-left
/// pixel, which the map's coordinates are relative to (both halves, every path).
///
/// # Errors
/// [`CorrectionError::InvalidArgument`] without a line time; as the dynamics' replay and
/// [`correct_effective_raster`].
pub fn dynamic_map<F: CorrectionField + ?Sized>(
    field: &F,
    raster: &FileRaster,
    dynamics: &ScannerDynamics,
    half: Half,
) -> Result<(CoordinateMap, [f64; 2]), CorrectionError> {
    let line_time_s = raster
        .line_time_s
        .filter(|t| t.is_finite() && *t > 0.0)
        .ok_or_else(|| {
            CorrectionError::InvalidArgument(
                "the raster's dynamics need the file's line time".to_owned(),
            )
        })?;
    let (nx, ny) = (raster.columns, raster.rows);
    if nx < 2 || ny < 1 {
        return Err(CorrectionError::Empty("raster with fewer than 2 columns"));
    }
    let replay = replay(raster, line_time_s);
    let pixels = &replay.pixels[match half {
        Half::Trace => 0,
        Half::Retrace => 1,
    }];
    let times: Vec<f64> = pixels.iter().map(|p| p.2).collect();
    let offsets = dynamics.offsets(&replay.history, &times)?;
    map_along(field, raster, dynamics, pixels, &offsets)
}

/// [`dynamic_map`] along a *recorded* command history (a command log that holds the probe's
/// moves before the frame and the frame's raster): `pixel_times_s` are the instrument times
/// of this half's pixels in acquisition order, on the history's clock. The creep of the
/// approach move is then corrected as well.
///
/// # Errors
/// [`CorrectionError::SizeMismatch`] when the times do not match the raster; as
/// [`dynamic_map`].
pub fn recorded_map<F: CorrectionField + ?Sized>(
    field: &F,
    raster: &FileRaster,
    dynamics: &ScannerDynamics,
    half: Half,
    history: &CommandHistory,
    pixel_times_s: &[f64],
) -> Result<(CoordinateMap, [f64; 2]), CorrectionError> {
    let (nx, ny) = (raster.columns, raster.rows);
    if pixel_times_s.len() != nx * ny {
        return Err(CorrectionError::SizeMismatch {
            what: "pixel times",
            expected: nx * ny,
            got: pixel_times_s.len(),
        });
    }
    // The file's geometry gives the commands; the record gives when.
    let replay = replay(raster, raster.line_time_s.unwrap_or(1.0));
    let pixels = &replay.pixels[match half {
        Half::Trace => 0,
        Half::Retrace => 1,
    }];
    let offsets = dynamics.offsets(history, pixel_times_s)?;
    map_along(field, raster, dynamics, pixels, &offsets)
}

/// The map of a half's pixels (display column, display row, time, commanded) with their
/// effective-input offsets (see [`dynamic_map`]).
fn map_along<F: CorrectionField + ?Sized>(
    field: &F,
    raster: &FileRaster,
    dynamics: &ScannerDynamics,
    pixels: &[(usize, usize, f64, CountPoint)],
    offsets: &[[f64; 2]],
) -> Result<(CoordinateMap, [f64; 2]), CorrectionError> {
    let (nx, ny) = (raster.columns, raster.rows);
    let commanded: Vec<[f64; 2]> = pixels
        .iter()
        .map(|p| [p.3.x.value(), p.3.y.value()])
        .collect();
    let gain = dynamics.gain()?;
    let reference = commanded
        .first()
        .copied()
        .ok_or(CorrectionError::Empty("raster with no pixel"))?;
    let along = correct_effective_raster(field, nx, ny, &commanded, offsets, gain, reference)?;
    // Every half and every path of one place shares the frame of the raster's bottom-left
    // pixel (as the static path does): the first acquired pixel is placed from it along the
    // static field.
    let corner = raster.pixel_counts(0.0, ny as f64 - 1.0);
    let quadrature = Quadrature::default();
    let last = |points: Vec<spm_hal::NmPoint>| {
        points
            .last()
            .map_or([0.0, 0.0], |p| [p.x.value(), p.y.value()])
    };
    let first_nm = last(correct_polyline(
        field,
        &[
            CountPoint::from_counts(0.0, 0.0),
            CountPoint::from_counts(corner.x.value(), 0.0),
            corner,
        ],
        &quadrature,
    )?);
    let to_first = last(correct_polyline(
        field,
        &[corner, pixels[0].3],
        &quadrature,
    )?);
    let along: Vec<[f64; 2]> = along
        .iter()
        .map(|p| [p[0] + to_first[0], p[1] + to_first[1]])
        .collect();
    let (s, c) = raster.angle_ccw_rad.sin_cos();
    let mut x_nm = vec![0.0; nx * ny];
    let mut y_nm = vec![0.0; nx * ny];
    for (p, xy) in pixels.iter().zip(&along) {
        let (column, row) = (p.0, p.1);
        let index = (ny - 1 - row) * nx + column;
        // Scanner axes → frame axes (rotation by −θ), as the static path does.
        x_nm[index] = xy[0] * c + xy[1] * s;
        y_nm[index] = -xy[0] * s + xy[1] * c;
    }
    let map = CoordinateMap::new(nx, ny, x_nm, YCoordinates::PerPixel(y_nm))?;
    Ok((map, first_nm))
}

/// `map` moved by (du, dv) nm.
///
/// # Errors
/// As [`CoordinateMap::new`].
pub fn translated(map: &CoordinateMap, du: f64, dv: f64) -> Result<CoordinateMap, CorrectionError> {
    let x: Vec<f64> = map.x_nm().iter().map(|v| v + du).collect();
    let y = match map.y_nm() {
        YCoordinates::PerRow(v) => YCoordinates::PerRow(v.iter().map(|y| y + dv).collect()),
        YCoordinates::PerPixel(v) => YCoordinates::PerPixel(v.iter().map(|y| y + dv).collect()),
    };
    CoordinateMap::new(map.columns(), map.rows(), x, y)
}
