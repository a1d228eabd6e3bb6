//! The raster's own dynamics in a correction (issue 23): the file's raster is replayed as
//! commands — every line's trace and retrace at the file's line time, the slow axis stepping
//! between lines — through the calibration file's scanner dynamics (PI hysteresis per axis,
//! then the creep of its output), and eq. (5) is summed over the increments of the effective
//! input pixel to pixel (`spm_correction::dynamics::correct_effective_path_axes`).
//!
//! Of the probe's history before the frame nothing is known from a file alone: the replay
//! starts settled at the frame's first pixel (no creep of the approach move, the hysteresis
//! demagnetised there). What the image then still carries of the approach is named in the
//! output ([`crate::DynamicsUsed`]).

use rayon::prelude::*;
use spm_correction::CorrectionError;
use spm_correction::dynamics::{CommandHistory, correct_effective_path_axes};
use spm_correction::hysteresis::{PlayHysteresis, ScannerDynamics, replay_axis};
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

/// The command history of a file's raster replayed at `line_time_s` per line: per line a
/// trace and a retrace over the line's pixels, the slow axis stepping between lines.
fn raster_history(raster: &FileRaster, order: &[usize], line_time_s: f64) -> CommandHistory {
    let mut history = CommandHistory::default();
    append_raster(&mut history, raster, order, line_time_s, 0.0);
    history
}

/// Appends a file's raster replayed at `line_time_s` per line, its first pixel `start_s` after
/// the clock's origin, to `history`.
fn append_raster(
    history: &mut CommandHistory,
    raster: &FileRaster,
    order: &[usize],
    line_time_s: f64,
    start_s: f64,
) {
    let (nx, ny) = (raster.columns, raster.rows);
    let dwell = line_time_s / nx as f64;
    let (first, last) = (order[0], order[nx - 1]);
    for line in 0..ny {
        let row = raster.display_row(line);
        let base = start_s + 2.0 * line_time_s * line as f64;
        let at = |column: usize| {
            let p = raster.pixel_counts(column as f64, row as f64);
            [p.x.value(), p.y.value()]
        };
        history.ramp_to(base + 0.5 * dwell, at(first));
        history.ramp_to(base + (nx as f64 - 0.5) * dwell, at(last));
        history.ramp_to(base + line_time_s + 0.5 * dwell, at(last));
        history.ramp_to(base + line_time_s + (nx as f64 - 0.5) * dwell, at(first));
    }
}

/// The pixels of one half in acquisition order, computed on demand (a 2048² frame is 4 M
/// pixels: nothing per pixel is stored beyond the replay's output).
struct HalfPixels<'r> {
    raster: &'r FileRaster,
    /// Display columns in trace order.
    order: Vec<usize>,
    half: Half,
    /// (sin, cos) of the raster's scan angle.
    rotation: (f64, f64),
}

impl<'r> HalfPixels<'r> {
    fn new(raster: &'r FileRaster, half: Half) -> Self {
        Self {
            raster,
            order: raster.line_columns().collect(),
            half,
            rotation: raster.angle_ccw_rad.sin_cos(),
        }
    }

    fn len(&self) -> usize {
        self.raster.columns * self.raster.rows
    }

    /// (display column, display row) of the `i`-th acquired pixel.
    fn pixel(&self, i: usize) -> (usize, usize) {
        let nx = self.raster.columns;
        let (line, k) = (i / nx, i % nx);
        let column = match self.half {
            Half::Trace => self.order[k],
            Half::Retrace => self.order[nx - 1 - k],
        };
        (column, self.raster.display_row(line))
    }

    /// Commanded counts of the `i`-th acquired pixel.
    fn commanded(&self, i: usize) -> CountPoint {
        let (column, row) = self.pixel(i);
        self.raster
            .pixel_counts_rotated(column as f64, row as f64, self.rotation)
    }

    /// Display column of the `k`-th pixel of an acquired line.
    #[inline]
    fn column(&self, k: usize) -> usize {
        match self.half {
            Half::Trace => self.order[k],
            Half::Retrace => self.order[self.raster.columns - 1 - k],
        }
    }

    /// Instrument time of the `i`-th acquired pixel at `line_time_s` per line, s.
    fn time_s(&self, i: usize, line_time_s: f64) -> f64 {
        let nx = self.raster.columns;
        let dwell = line_time_s / nx as f64;
        let (line, k) = (i / nx, i % nx);
        let base = 2.0 * line_time_s * line as f64;
        let start = match self.half {
            Half::Trace => base,
            Half::Retrace => base + line_time_s,
        };
        start + (k as f64 + 0.5) * dwell
    }
}

/// The coordinate map of one half of `raster` along its effective trajectory, and the nm
/// position (from the field's origin, static reference state) of the raster's bottom-left
/// pixel, which the map's coordinates are relative to (both halves, every path).
///
/// # Errors
/// [`CorrectionError::InvalidArgument`] without a line time; as the dynamics' replay and
/// [`correct_effective_path_axes`].
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
    let pixels = HalfPixels::new(raster, half);
    let history = raster_history(raster, &pixels.order, line_time_s);
    let times: Vec<f64> = (0..pixels.len())
        .into_par_iter()
        .map(|i| pixels.time_s(i, line_time_s))
        .collect();
    let ue = effective_input(dynamics, &pixels, &history, &times)?;
    drop(times);
    map_along(field, raster, dynamics, &pixels, ue)
}

/// [`dynamic_map`] of the second frame of a pair scanned right after `earlier` (a
/// counter-scanned partner): the replay runs `earlier`'s raster first, settled at its first
/// pixel, then this raster, its first pixel `delay_s` after `earlier`'s (the commands between
/// them a straight move). The creep and hysteresis `earlier`'s raster left are then corrected
/// in this frame; what is still unknown is the approach move before `earlier`, the same
/// function of time in both frames ([`crate::counter`]).
///
/// # Errors
/// [`CorrectionError::InvalidArgument`] without a line time in either file, or a delay shorter
/// than `earlier`'s frame; as [`dynamic_map`].
pub fn dynamic_map_after<F: CorrectionField + ?Sized>(
    field: &F,
    raster: &FileRaster,
    dynamics: &ScannerDynamics,
    half: Half,
    earlier: &FileRaster,
    delay_s: f64,
) -> Result<(CoordinateMap, [f64; 2]), CorrectionError> {
    let line_time = |r: &FileRaster| {
        r.line_time_s
            .filter(|t| t.is_finite() && *t > 0.0)
            .ok_or_else(|| {
                CorrectionError::InvalidArgument(
                    "the raster's dynamics need the file's line time".to_owned(),
                )
            })
    };
    let (line_time_s, earlier_line_s) = (line_time(raster)?, line_time(earlier)?);
    let earlier_frame_s = 2.0 * earlier_line_s * earlier.rows as f64;
    if !(delay_s.is_finite() && delay_s >= earlier_frame_s) {
        return Err(CorrectionError::InvalidArgument(format!(
            "the partner's frame lasts {earlier_frame_s:.3} s, but this frame starts {delay_s:.3} s \
             after it"
        )));
    }
    let (nx, ny) = (raster.columns, raster.rows);
    if nx < 2 || ny < 1 || earlier.columns < 2 || earlier.rows < 1 {
        return Err(CorrectionError::Empty("raster with fewer than 2 columns"));
    }
    let pixels = HalfPixels::new(raster, half);
    let mut history = CommandHistory::default();
    let earlier_order: Vec<usize> = earlier.line_columns().collect();
    append_raster(&mut history, earlier, &earlier_order, earlier_line_s, 0.0);
    append_raster(&mut history, raster, &pixels.order, line_time_s, delay_s);
    let times: Vec<f64> = (0..pixels.len())
        .into_par_iter()
        .map(|i| delay_s + pixels.time_s(i, line_time_s))
        .collect();
    let ue = effective_input(dynamics, &pixels, &history, &times)?;
    drop(times);
    map_along(field, raster, dynamics, &pixels, ue)
}

/// The instrument time of every pixel of one half of `raster` as [`dynamic_map`] replays it
/// (s from the first trace pixel), in the map's order (bottom row first).
///
/// # Errors
/// [`CorrectionError::InvalidArgument`] without a line time, [`CorrectionError::Empty`] for a
/// raster of fewer than 2 columns.
pub fn pixel_times(raster: &FileRaster, half: Half) -> Result<Vec<f64>, CorrectionError> {
    let line_time_s = raster
        .line_time_s
        .filter(|t| t.is_finite() && *t > 0.0)
        .ok_or_else(|| {
            CorrectionError::InvalidArgument("pixel times need the file's line time".to_owned())
        })?;
    let (nx, ny) = (raster.columns, raster.rows);
    if nx < 2 || ny < 1 {
        return Err(CorrectionError::Empty("raster with fewer than 2 columns"));
    }
    let pixels = HalfPixels::new(raster, half);
    let mut times = vec![0.0; nx * ny];
    for i in 0..pixels.len() {
        let (column, row) = pixels.pixel(i);
        times[(ny - 1 - row) * nx + column] = pixels.time_s(i, line_time_s);
    }
    Ok(times)
}

/// The effective input `uₑ = u + h + c` of every pixel of a half (acquisition order), counts,
/// one vector per axis: each axis replayed on its own thread
/// ([`ScannerDynamics::offsets_per_axis`]'s replay), its command added as the offsets come.
fn effective_input(
    dynamics: &ScannerDynamics,
    pixels: &HalfPixels<'_>,
    history: &CommandHistory,
    pixel_times_s: &[f64],
) -> Result<[Vec<f64>; 2], CorrectionError> {
    let law = dynamics.creep.law()?;
    let nx = pixels.raster.columns;
    let axis = |axis: usize, model: &PlayHysteresis| {
        let mut out = Vec::with_capacity(pixel_times_s.len());
        // The pixel the next offset belongs to: line and position in the line.
        let (mut line, mut k) = (0, 0);
        let mut row = pixels.raster.display_row(0) as f64;
        replay_axis(history, axis, model, &law, pixel_times_s, |h, c| {
            let u =
                pixels
                    .raster
                    .pixel_counts_rotated(pixels.column(k) as f64, row, pixels.rotation);
            let u = if axis == 0 { u.x.value() } else { u.y.value() };
            out.push(u + (h + c));
            k += 1;
            if k == nx {
                k = 0;
                line += 1;
                if line < pixels.raster.rows {
                    row = pixels.raster.display_row(line) as f64;
                }
            }
        })
        .map(|()| out)
    };
    let (x, y) = rayon::join(
        || axis(0, &dynamics.hysteresis_x),
        || axis(1, &dynamics.hysteresis_y),
    );
    Ok([x?, y?])
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
    if nx < 2 || ny < 1 {
        return Err(CorrectionError::Empty("raster with fewer than 2 columns"));
    }
    // The file's geometry gives the commands; the record gives when.
    let pixels = HalfPixels::new(raster, half);
    let ue = effective_input(dynamics, &pixels, history, pixel_times_s)?;
    map_along(field, raster, dynamics, &pixels, ue)
}

/// The map of a half's pixels given their effective input `[ue_x, ue_y]` (see
/// [`dynamic_map`]); the input's buffers become the map's.
fn map_along<F: CorrectionField + ?Sized>(
    field: &F,
    raster: &FileRaster,
    dynamics: &ScannerDynamics,
    pixels: &HalfPixels<'_>,
    ue: [Vec<f64>; 2],
) -> Result<(CoordinateMap, [f64; 2]), CorrectionError> {
    let (nx, ny) = (raster.columns, raster.rows);
    let gain = dynamics.gain()?;
    let reference = pixels.commanded(0);
    let along = correct_effective_path_axes(
        field,
        nx,
        ny,
        &ue[0],
        &ue[1],
        gain,
        [reference.x.value(), reference.y.value()],
    )?;
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
        &[corner, pixels.commanded(0)],
        &quadrature,
    )?);
    let (s, c) = raster.angle_ccw_rad.sin_cos();
    // The effective input is spent: its buffers (one value per pixel each) take the map,
    // every value of which is written below.
    let [mut x_nm, mut y_nm] = ue;
    // Map row m holds display row ny − 1 − m, which one acquired line holds (`display_row`
    // is its own inverse: the identity or the reversal of the rows); the map's rows are
    // filled on every core.
    x_nm.par_chunks_mut(nx)
        .zip(y_nm.par_chunks_mut(nx))
        .enumerate()
        .for_each(|(m, (x_row, y_row))| {
            let line = raster.display_row(ny - 1 - m);
            for (k, xy) in along[line * nx..(line + 1) * nx].iter().enumerate() {
                let p = [xy[0] + to_first[0], xy[1] + to_first[1]];
                let column = pixels.column(k);
                // Scanner axes → frame axes (rotation by −θ), as the static path does.
                x_row[column] = p[0] * c + p[1] * s;
                y_row[column] = -p[0] * s + p[1] * c;
            }
        });
    drop(along);
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
