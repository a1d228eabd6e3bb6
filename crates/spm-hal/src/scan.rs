//! Raster scan requests, the frames a backend returns, and height maps in
//! scanner geometry.
//!
//! Conventions (DESIGN §2):
//! - A frame's data are stored in **acquisition order**: line 0 is the first
//!   line acquired, pixel 0 the first pixel acquired in that line.
//! - [`ScanDirection::Direct`]: forward traces run +x, lines step +y, starting
//!   at [`ScanRequest::origin`] (the corner with the smallest x and y).
//! - [`ScanDirection::Counter`]: forward traces run −x, lines step −y, starting
//!   at the far corner (Lapshin 2007, counter-scanning).
//! - Each line is a forward trace followed by a backward trace (retrace) over the
//!   same pixels in the opposite order; the backward half is recorded when
//!   [`ScanRequest::record_backward`] is set and the backend supports it.
//! - [`HeightMap`] re-orders one half into scanner geometry: row index grows
//!   with y, column index with x, whatever the acquisition order was.

use crate::units::{CountPoint, Counts, Seconds};
use serde::{Deserialize, Serialize};

/// The raster direction of a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScanDirection {
    /// +x forward traces, lines stepping +y, starting at the origin corner.
    Direct,
    /// −x forward traces, lines stepping −y, starting at the far corner.
    Counter,
}

/// Which half of a scan line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TraceHalf {
    /// The trace: the direction named by the frame's [`ScanDirection`].
    Forward,
    /// The retrace: the same line in the opposite direction.
    Backward,
}

/// A request for a raster scan of a square-pixel region.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScanRequest {
    /// The raster corner with the smallest x and y (pixel column 0, row 0 in
    /// scanner geometry), in counts.
    pub origin: CountPoint,
    /// Distance between neighbouring pixels along both axes, in counts (> 0).
    pub pixel_step: Counts,
    /// Pixels per line (along the fast axis x).
    pub pixels_per_line: u32,
    /// Number of lines (along the slow axis y).
    pub lines: u32,
    /// Direct or counter raster.
    pub direction: ScanDirection,
    /// Time spent on each pixel (sets the scan speed), in seconds (> 0).
    pub pixel_dwell: Seconds,
    /// Record the backward trace as well as the forward one.
    pub record_backward: bool,
}

/// Why a [`ScanRequest`] cannot be executed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ScanRequestError {
    /// A field of the request is not a finite positive number or count.
    #[error("scan request field `{field}` is invalid: {reason}")]
    InvalidField {
        /// The field's name.
        field: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// The raster leaves the scanner field.
    #[error("scan region [{min_x}, {max_x}] × [{min_y}, {max_y}] counts leaves the scanner field")]
    OutsideField {
        /// Smallest x of the raster, counts.
        min_x: f64,
        /// Largest x of the raster, counts.
        max_x: f64,
        /// Smallest y of the raster, counts.
        min_y: f64,
        /// Largest y of the raster, counts.
        max_y: f64,
    },
}

impl ScanRequest {
    /// A direct-scan request of `pixels`×`pixels` centred on `centre`.
    pub fn centred_square(
        centre: CountPoint,
        pixel_step: Counts,
        pixels: u32,
        pixel_dwell: Seconds,
    ) -> Self {
        let half_extent = pixel_step * (f64::from(pixels.saturating_sub(1)) / 2.0);
        Self {
            origin: CountPoint::new(centre.x - half_extent, centre.y - half_extent),
            pixel_step,
            pixels_per_line: pixels,
            lines: pixels,
            direction: ScanDirection::Direct,
            pixel_dwell,
            record_backward: false,
        }
    }

    /// The same region scanned in the other direction.
    pub fn with_direction(mut self, direction: ScanDirection) -> Self {
        self.direction = direction;
        self
    }

    /// Number of pixels in one half (forward or backward).
    pub fn pixel_count(&self) -> usize {
        self.pixels_per_line as usize * self.lines as usize
    }

    /// The raster's centre in counts.
    pub fn centre(&self) -> CountPoint {
        let (max_x, max_y) = self.far_corner();
        CountPoint::new((self.origin.x + max_x) * 0.5, (self.origin.y + max_y) * 0.5)
    }

    /// The corner opposite the origin (largest x and y), in counts.
    pub fn far_corner(&self) -> (Counts, Counts) {
        let nx = f64::from(self.pixels_per_line.saturating_sub(1));
        let ny = f64::from(self.lines.saturating_sub(1));
        (
            self.origin.x + self.pixel_step * nx,
            self.origin.y + self.pixel_step * ny,
        )
    }

    /// Checks that every field is finite and positive where it must be.
    pub fn validate(&self) -> Result<(), ScanRequestError> {
        let invalid = |field: &'static str, reason: &str| {
            Err(ScanRequestError::InvalidField {
                field,
                reason: reason.to_owned(),
            })
        };
        if !self.origin.is_finite() {
            return invalid("origin", "not finite");
        }
        if !(self.pixel_step.value().is_finite() && self.pixel_step.value() > 0.0) {
            return invalid("pixel_step", "must be a finite number of counts > 0");
        }
        if self.pixels_per_line == 0 {
            return invalid("pixels_per_line", "must be at least 1");
        }
        if self.lines == 0 {
            return invalid("lines", "must be at least 1");
        }
        if !(self.pixel_dwell.value().is_finite() && self.pixel_dwell.value() > 0.0) {
            return invalid("pixel_dwell", "must be a finite time > 0 s");
        }
        Ok(())
    }

    /// Checks the raster against a lateral field `[min, max]` (counts).
    pub fn check_inside(&self, min: CountPoint, max: CountPoint) -> Result<(), ScanRequestError> {
        let (far_x, far_y) = self.far_corner();
        if self.origin.x < min.x || self.origin.y < min.y || far_x > max.x || far_y > max.y {
            return Err(ScanRequestError::OutsideField {
                min_x: self.origin.x.value(),
                max_x: far_x.value(),
                min_y: self.origin.y.value(),
                max_y: far_y.value(),
            });
        }
        Ok(())
    }

    /// Scanner-geometry indices `(column, row)` of the pixel acquired as
    /// `pixel` of `line` in the given half.
    #[inline]
    pub fn geometric_index(&self, half: TraceHalf, line: usize, pixel: usize) -> (usize, usize) {
        let nx = self.pixels_per_line as usize;
        let ny = self.lines as usize;
        let runs_plus_x = matches!(
            (self.direction, half),
            (ScanDirection::Direct, TraceHalf::Forward)
                | (ScanDirection::Counter, TraceHalf::Backward)
        );
        let column = if runs_plus_x { pixel } else { nx - 1 - pixel };
        let row = match self.direction {
            ScanDirection::Direct => line,
            ScanDirection::Counter => ny - 1 - line,
        };
        (column, row)
    }

    /// The commanded position of the pixel acquired as `pixel` of `line` in
    /// the given half, in counts.
    #[inline]
    pub fn commanded_position(&self, half: TraceHalf, line: usize, pixel: usize) -> CountPoint {
        let (column, row) = self.geometric_index(half, line, pixel);
        CountPoint::new(
            self.origin.x + self.pixel_step * column as f64,
            self.origin.y + self.pixel_step * row as f64,
        )
    }
}

/// One recorded half (forward or backward traces) of a frame, in acquisition order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TraceImage {
    /// Z-manipulator position (the topography signal) of every pixel, in
    /// counts, indexed `[line * pixels_per_line + pixel]` in acquisition order.
    pub z_counts: Vec<f64>,
    /// Instrument time at which every pixel was acquired (its dwell's middle),
    /// in seconds of the backend's clock, indexed like `z_counts`.
    pub time_s: Vec<f64>,
}

/// A raster scan as returned by a backend.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Frame {
    /// The request that produced this frame.
    pub request: ScanRequest,
    /// The forward traces.
    pub forward: TraceImage,
    /// The backward traces, when requested and supported.
    pub backward: Option<TraceImage>,
}

/// Why a frame's data do not fit its request.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum FrameError {
    /// The number of samples does not match the request.
    #[error("frame {half:?} half has {found} {what} samples, the request needs {expected}")]
    WrongLength {
        /// Which half.
        half: TraceHalf,
        /// `z` or `time`.
        what: &'static str,
        /// Samples found.
        found: usize,
        /// Samples needed.
        expected: usize,
    },
    /// The requested half was not recorded.
    #[error("the {0:?} half of this frame was not recorded")]
    MissingHalf(TraceHalf),
    /// The request itself is invalid.
    #[error(transparent)]
    Request(#[from] ScanRequestError),
}

impl Frame {
    /// Builds a frame by evaluating `sample(position, time)` at every commanded
    /// pixel, in acquisition order. Each line takes `2 · pixels_per_line ·
    /// pixel_dwell` (trace and retrace); times are pixel-dwell midpoints from
    /// `start`. Useful for scripted backends and tests.
    pub fn from_fn(
        request: ScanRequest,
        start: Seconds,
        mut sample: impl FnMut(CountPoint, Seconds) -> Counts,
    ) -> Self {
        let nx = request.pixels_per_line as usize;
        let ny = request.lines as usize;
        let dwell = request.pixel_dwell.value();
        let mut forward = TraceImage {
            z_counts: Vec::with_capacity(nx * ny),
            time_s: Vec::with_capacity(nx * ny),
        };
        let mut backward = request.record_backward.then(|| TraceImage {
            z_counts: Vec::with_capacity(nx * ny),
            time_s: Vec::with_capacity(nx * ny),
        });
        for line in 0..ny {
            let line_start = start.value() + (line * 2 * nx) as f64 * dwell;
            for pixel in 0..nx {
                let t = Seconds(line_start + (pixel as f64 + 0.5) * dwell);
                let p = request.commanded_position(TraceHalf::Forward, line, pixel);
                forward.z_counts.push(sample(p, t).value());
                forward.time_s.push(t.value());
            }
            for pixel in 0..nx {
                let t = Seconds(line_start + ((nx + pixel) as f64 + 0.5) * dwell);
                let p = request.commanded_position(TraceHalf::Backward, line, pixel);
                let z = sample(p, t);
                if let Some(back) = backward.as_mut() {
                    back.z_counts.push(z.value());
                    back.time_s.push(t.value());
                }
            }
        }
        Self {
            request,
            forward,
            backward,
        }
    }

    /// The duration such a frame takes on an instrument that retraces every
    /// line at the same speed: `2 · pixels · dwell`.
    pub fn nominal_duration(request: &ScanRequest) -> Seconds {
        request.pixel_dwell * (2.0 * request.pixel_count() as f64)
    }

    /// One half of the frame, or an error when it was not recorded.
    pub fn half(&self, half: TraceHalf) -> Result<&TraceImage, FrameError> {
        match half {
            TraceHalf::Forward => Ok(&self.forward),
            TraceHalf::Backward => self.backward.as_ref().ok_or(FrameError::MissingHalf(half)),
        }
    }

    /// Checks that the recorded data fit the request.
    pub fn validate(&self) -> Result<(), FrameError> {
        self.request.validate()?;
        let expected = self.request.pixel_count();
        let halves = [
            (TraceHalf::Forward, Some(&self.forward)),
            (TraceHalf::Backward, self.backward.as_ref()),
        ];
        for (half, image) in halves {
            let Some(image) = image else { continue };
            for (what, found) in [("z", image.z_counts.len()), ("time", image.time_s.len())] {
                if found != expected {
                    return Err(FrameError::WrongLength {
                        half,
                        what,
                        found,
                        expected,
                    });
                }
            }
        }
        Ok(())
    }

    /// One half re-ordered into scanner geometry (see [`HeightMap`]).
    pub fn height_map(&self, half: TraceHalf) -> Result<HeightMap, FrameError> {
        self.validate()?;
        let image = self.half(half)?;
        let nx = self.request.pixels_per_line as usize;
        let ny = self.request.lines as usize;
        let mut z_counts = vec![0.0; nx * ny];
        let mut time_s = vec![0.0; nx * ny];
        for line in 0..ny {
            for pixel in 0..nx {
                let (column, row) = self.request.geometric_index(half, line, pixel);
                let source = line * nx + pixel;
                z_counts[row * nx + column] = image.z_counts[source];
                time_s[row * nx + column] = image.time_s[source];
            }
        }
        Ok(HeightMap {
            origin: self.request.origin,
            pixel_step: self.request.pixel_step,
            columns: nx,
            rows: ny,
            z_counts,
            time_s,
        })
    }
}

/// One image in scanner geometry: row index grows with y, column index with x.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HeightMap {
    /// Commanded position of column 0, row 0, in counts.
    pub origin: CountPoint,
    /// Pixel spacing along both axes, in counts.
    pub pixel_step: Counts,
    /// Number of columns (x).
    pub columns: usize,
    /// Number of rows (y).
    pub rows: usize,
    /// Height of every pixel in Z counts, `[row * columns + column]`.
    pub z_counts: Vec<f64>,
    /// Acquisition time of every pixel in seconds, indexed like `z_counts`.
    pub time_s: Vec<f64>,
}

impl HeightMap {
    /// Height at `(column, row)`, or `None` outside the map.
    #[inline]
    pub fn z(&self, column: usize, row: usize) -> Option<f64> {
        if column < self.columns && row < self.rows {
            self.z_counts.get(row * self.columns + column).copied()
        } else {
            None
        }
    }

    /// Commanded position of a (possibly fractional) pixel coordinate.
    #[inline]
    pub fn position(&self, column: f64, row: f64) -> CountPoint {
        CountPoint::new(
            self.origin.x + self.pixel_step * column,
            self.origin.y + self.pixel_step * row,
        )
    }

    /// Fractional pixel coordinate `(column, row)` of a commanded position.
    #[inline]
    pub fn pixel_of(&self, point: CountPoint) -> (f64, f64) {
        (
            (point.x - self.origin.x) / self.pixel_step,
            (point.y - self.origin.y) / self.pixel_step,
        )
    }

    /// Acquisition time at a fractional pixel coordinate: the time of the
    /// nearest pixel, or `None` outside the map.
    pub fn time_at(&self, column: f64, row: f64) -> Option<Seconds> {
        let c = column.round();
        let r = row.round();
        if !(c >= 0.0 && r >= 0.0) {
            return None;
        }
        let (c, r) = (c as usize, r as usize);
        if c < self.columns && r < self.rows {
            self.time_s.get(r * self.columns + c).copied().map(Seconds)
        } else {
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(direction: ScanDirection) -> ScanRequest {
        ScanRequest {
            origin: CountPoint::from_counts(100.0, 200.0),
            pixel_step: Counts(2.0),
            pixels_per_line: 3,
            lines: 2,
            direction,
            pixel_dwell: Seconds(0.001),
            record_backward: true,
        }
    }

    fn check(
        direction: ScanDirection,
        half: TraceHalf,
        line: usize,
        pixel: usize,
        expected: (f64, f64),
    ) {
        let p = request(direction).commanded_position(half, line, pixel);
        assert_eq!(
            (p.x.value(), p.y.value()),
            expected,
            "{direction:?} {half:?} line {line} pixel {pixel}"
        );
    }

    #[test]
    fn commanded_positions_follow_the_raster_conventions() {
        check(
            ScanDirection::Direct,
            TraceHalf::Forward,
            0,
            0,
            (100.0, 200.0),
        );
        check(
            ScanDirection::Direct,
            TraceHalf::Forward,
            0,
            2,
            (104.0, 200.0),
        );
        check(
            ScanDirection::Direct,
            TraceHalf::Backward,
            0,
            0,
            (104.0, 200.0),
        );
        check(
            ScanDirection::Direct,
            TraceHalf::Forward,
            1,
            1,
            (102.0, 202.0),
        );
        check(
            ScanDirection::Counter,
            TraceHalf::Forward,
            0,
            0,
            (104.0, 202.0),
        );
        check(
            ScanDirection::Counter,
            TraceHalf::Forward,
            1,
            2,
            (100.0, 200.0),
        );
        check(
            ScanDirection::Counter,
            TraceHalf::Backward,
            0,
            0,
            (100.0, 202.0),
        );
    }

    #[test]
    fn height_map_reorders_every_direction_to_scanner_geometry() {
        // The sample is a plane z = x + 10·y: in geometry order it must be
        // identical whatever the acquisition order was.
        for direction in [ScanDirection::Direct, ScanDirection::Counter] {
            let frame = Frame::from_fn(request(direction), Seconds(5.0), |p, _| {
                Counts(p.x.value() + 10.0 * p.y.value())
            });
            for half in [TraceHalf::Forward, TraceHalf::Backward] {
                let map = frame.height_map(half).unwrap();
                for row in 0..2 {
                    for column in 0..3 {
                        let p = map.position(column as f64, row as f64);
                        assert_eq!(map.z(column, row), Some(p.x.value() + 10.0 * p.y.value()));
                    }
                }
            }
        }
    }

    #[test]
    fn times_grow_in_acquisition_order_and_include_the_retrace() {
        let frame = Frame::from_fn(request(ScanDirection::Direct), Seconds(0.0), |_, _| {
            Counts(0.0)
        });
        let t = &frame.forward.time_s;
        assert!(t.windows(2).all(|w| w[1] > w[0]));
        // Line 1 starts after 3 forward + 3 backward pixels.
        assert!((t[3] - 0.0065).abs() < 1e-12);
        let back = frame.backward.as_ref().unwrap();
        assert!((back.time_s[0] - 0.0035).abs() < 1e-12);
        assert!((Frame::nominal_duration(&frame.request).value() - 0.012).abs() < 1e-12);
    }

    #[test]
    fn invalid_requests_name_the_field() {
        let mut r = request(ScanDirection::Direct);
        r.pixel_step = Counts(f64::NAN);
        assert!(matches!(
            r.validate(),
            Err(ScanRequestError::InvalidField {
                field: "pixel_step",
                ..
            })
        ));
        let mut r = request(ScanDirection::Direct);
        r.lines = 0;
        assert!(matches!(
            r.validate(),
            Err(ScanRequestError::InvalidField { field: "lines", .. })
        ));
        let r = request(ScanDirection::Direct);
        assert!(
            r.check_inside(
                CountPoint::from_counts(0.0, 0.0),
                CountPoint::from_counts(103.0, 1000.0)
            )
            .is_err()
        );
        assert!(
            r.check_inside(
                CountPoint::from_counts(0.0, 0.0),
                CountPoint::from_counts(104.0, 1000.0)
            )
            .is_ok()
        );
    }

    #[test]
    fn a_frame_with_missing_samples_is_rejected() {
        let mut frame = Frame::from_fn(request(ScanDirection::Direct), Seconds(0.0), |_, _| {
            Counts(0.0)
        });
        frame.forward.z_counts.pop();
        assert!(matches!(
            frame.height_map(TraceHalf::Forward),
            Err(FrameError::WrongLength { .. })
        ));
        frame.backward = None;
        assert!(matches!(
            frame.half(TraceHalf::Backward),
            Err(FrameError::MissingHalf(_))
        ));
    }
}
