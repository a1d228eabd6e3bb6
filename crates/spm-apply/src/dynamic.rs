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
/// position (from the field's origin, static reference state) of the half's first acquired
/// pixel, which the map's coordinates are relative to.
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
    let commanded: Vec<[f64; 2]> = pixels
        .iter()
        .map(|p| [p.3.x.value(), p.3.y.value()])
        .collect();
    let offsets = dynamics.offsets(&replay.history, &times)?;
    let gain = dynamics.gain()?;
    let reference = commanded[0];
    let along = correct_effective_raster(field, nx, ny, &commanded, &offsets, gain, reference)?;
    let zero = pixels[0].3;
    let to_zero = correct_polyline(
        field,
        &[
            CountPoint::from_counts(0.0, 0.0),
            CountPoint::from_counts(zero.x.value(), 0.0),
            zero,
        ],
        &Quadrature::default(),
    )?;
    let first_nm = to_zero
        .last()
        .map_or([0.0, 0.0], |p| [p.x.value(), p.y.value()]);
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
