//! [`VirtualMicroscope`]: the stored image served through [`Microscope`].

use crate::image::StoredImage;
use serde::{Deserialize, Serialize};
use spm_hal::{
    Capabilities, CoarseZStage, CountPoint, Counts, ErrorKind, Frame, Microscope, MoveRequest,
    ScanDirection, ScanRequest, Seconds, TraceHalf, TraceImage,
};

/// Largest pixels per line and lines of one virtual scan.
pub const MAX_SCAN_PIXELS: u32 = 4096;

/// The stated conversions of the virtual scanner.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VirtualParams {
    /// Nominal lateral sensitivity, nm per count (> 0; no default: it is the statement the
    /// calibration measures against). A count is `nominal_nm_per_count / pixel_nm` image
    /// pixels along either axis; the image's centre pixel is at the frame's offset (as a
    /// controller records it) over the sensitivity, so count 0 is the instrument's origin and
    /// a part of an image keeps the whole image's counts. The scan angle is not applied: the
    /// image's axes are the scanner's.
    pub nominal_nm_per_count: f64,
    /// Z sensitivity, nm per Z count (> 0). Default 0.001 (1 pm per count).
    #[serde(default = "VirtualParams::default_z_nm_per_count")]
    pub z_nm_per_count: f64,
}

impl VirtualParams {
    /// The default Z sensitivity, nm per count.
    pub const DEFAULT_Z_NM_PER_COUNT: f64 = 0.001;

    fn default_z_nm_per_count() -> f64 {
        Self::DEFAULT_Z_NM_PER_COUNT
    }

    /// Parameters with the default Z sensitivity.
    #[must_use]
    pub fn new(nominal_nm_per_count: f64) -> Self {
        Self {
            nominal_nm_per_count,
            z_nm_per_count: Self::DEFAULT_Z_NM_PER_COUNT,
        }
    }
}

/// The images a virtual microscope serves: the direct raster's forward half, and when the
/// file has them its backward half and a counter frame (a consecutive frame with the slow
/// direction reversed).
#[derive(Clone, Debug, PartialEq)]
pub struct VirtualSurface {
    /// Served for forward halves of direct scans (and of counter scans without a counter
    /// frame).
    pub forward: StoredImage,
    /// Served for backward halves; `None`: the forward image.
    pub backward: Option<StoredImage>,
    /// Served for forward halves of counter scans; `None`: the forward image.
    pub counter: Option<StoredImage>,
}

impl VirtualSurface {
    /// A surface of one image (every half and direction served from it).
    #[must_use]
    pub fn single(image: StoredImage) -> Self {
        Self {
            forward: image,
            backward: None,
            counter: None,
        }
    }
}

/// What a virtual microscope refuses.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum VirtualError {
    /// A move or scan leaves the stored image (its interpolation support).
    #[error("{what} leaves the stored image: {detail}")]
    OutOfRange {
        /// A move or a scan.
        what: &'static str,
        /// Where, in counts.
        detail: String,
    },
    /// The request is malformed.
    #[error("invalid request: {0}")]
    Invalid(String),
    /// The images of the surface do not share one grid and pixel size.
    #[error("the {0} image has another grid or pixel size than the forward image")]
    Mismatch(&'static str),
    /// A parameter is out of its range.
    #[error("{field}: {reason}")]
    Parameter {
        /// The parameter.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
}

impl spm_hal::Error for VirtualError {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::OutOfRange { .. } => ErrorKind::OutOfRange,
            Self::Invalid(_) | Self::Mismatch(_) | Self::Parameter { .. } => ErrorKind::Other,
        }
    }
}

/// A microscope whose surface is a stored image (the seed's virtual calibration mode).
///
/// - Counts map to image pixels through [`VirtualParams::nominal_nm_per_count`] and the
///   image's pixel size; the position reading is the command.
/// - A scan resamples the stored heights on the requested raster by Keys cubic convolution
///   ([`crate::interp`]); the backward half comes from the backward image, a counter scan's
///   forward half from the counter frame, when the surface has them.
/// - The clock advances by the original raster's speed: `pixel_time_s` of the stored image
///   per image pixel travelled (trace and retrace), moves at their requested speed plus
///   their settle, waits by their duration. The drift and creep that acted while the image
///   was recorded are frozen into it: a place is seen as the original raster saw it, at
///   any virtual time, so they act as a distortion of the surface, as in the seed's
///   virtual mode; repeated scans of a place agree exactly.
/// - The field is the part of the image the interpolation reaches: pixels 1 to n − 2.
#[derive(Clone, Debug)]
pub struct VirtualMicroscope {
    surface: VirtualSurface,
    params: VirtualParams,
    clock_s: f64,
    position: CountPoint,
}

impl VirtualMicroscope {
    /// A virtual microscope at the centre of its field, clock at 0 s.
    ///
    /// # Errors
    /// [`VirtualError::Parameter`] for a sensitivity that is not finite and positive,
    /// [`VirtualError::Mismatch`] when the backward or counter image has another grid.
    pub fn new(surface: VirtualSurface, params: VirtualParams) -> Result<Self, VirtualError> {
        for (field, v) in [
            ("nominal_nm_per_count", params.nominal_nm_per_count),
            ("z_nm_per_count", params.z_nm_per_count),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(VirtualError::Parameter {
                    field,
                    reason: format!("must be finite and > 0, got {v}"),
                });
            }
        }
        let same = |a: &StoredImage, b: &StoredImage| {
            a.columns() == b.columns()
                && a.rows() == b.rows()
                && a.pixel_x_nm() == b.pixel_x_nm()
                && a.pixel_y_nm() == b.pixel_y_nm()
        };
        if let Some(b) = &surface.backward
            && !same(&surface.forward, b)
        {
            return Err(VirtualError::Mismatch("backward"));
        }
        if let Some(c) = &surface.counter
            && !same(&surface.forward, c)
        {
            return Err(VirtualError::Mismatch("counter"));
        }
        let mut microscope = Self {
            surface,
            params,
            clock_s: 0.0,
            position: CountPoint::default(),
        };
        let caps = microscope.capabilities();
        microscope.position = CountPoint::new(
            (caps.field_min.x + caps.field_max.x) * 0.5,
            (caps.field_min.y + caps.field_max.y) * 0.5,
        );
        Ok(microscope)
    }

    /// The stated parameters.
    #[must_use]
    pub fn params(&self) -> VirtualParams {
        self.params
    }

    /// The served surface.
    #[must_use]
    pub fn surface(&self) -> &VirtualSurface {
        &self.surface
    }

    /// Counts per image pixel along x and y.
    #[must_use]
    pub fn counts_per_pixel(&self) -> (f64, f64) {
        let image = &self.surface.forward;
        (
            image.pixel_x_nm() / self.params.nominal_nm_per_count,
            image.pixel_y_nm() / self.params.nominal_nm_per_count,
        )
    }

    /// The image's centre pixel `(column, row)`: the frame's offset.
    fn centre_pixel(&self) -> (f64, f64) {
        let image = &self.surface.forward;
        (
            0.5 * (image.columns() as f64 - 1.0),
            0.5 * (image.rows() as f64 - 1.0),
        )
    }

    /// The counts of the image's centre: the frame's offset over the sensitivity.
    fn centre_counts(&self) -> (f64, f64) {
        let [x, y] = self.surface.forward.centre_nm();
        let k = self.params.nominal_nm_per_count;
        (x / k, y / k)
    }

    /// The fractional image pixel `(column, row)` of a commanded position.
    #[must_use]
    pub fn pixel_of(&self, point: CountPoint) -> (f64, f64) {
        let (cx, cy) = self.counts_per_pixel();
        let (c0, r0) = self.centre_pixel();
        let (x0, y0) = self.centre_counts();
        (
            (point.x.value() - x0) / cx + c0,
            (point.y.value() - y0) / cy + r0,
        )
    }

    /// The commanded position of a fractional image pixel.
    #[must_use]
    pub fn counts_of(&self, column: f64, row: f64) -> CountPoint {
        let (cx, cy) = self.counts_per_pixel();
        let (c0, r0) = self.centre_pixel();
        let (x0, y0) = self.centre_counts();
        CountPoint::from_counts(x0 + (column - c0) * cx, y0 + (row - r0) * cy)
    }

    fn inside(&self, point: CountPoint) -> bool {
        let caps = self.capabilities();
        point.is_finite()
            && point.x >= caps.field_min.x
            && point.y >= caps.field_min.y
            && point.x <= caps.field_max.x
            && point.y <= caps.field_max.y
    }

    fn image_for(&self, direction: ScanDirection, half: TraceHalf) -> &StoredImage {
        let s = &self.surface;
        match (half, direction) {
            (TraceHalf::Backward, _) => s.backward.as_ref().unwrap_or(&s.forward),
            (TraceHalf::Forward, ScanDirection::Counter) => {
                s.counter.as_ref().unwrap_or(&s.forward)
            }
            (TraceHalf::Forward, ScanDirection::Direct) => &s.forward,
        }
    }

    fn sample(
        &self,
        request: &ScanRequest,
        half: TraceHalf,
        line: usize,
        pixel: usize,
    ) -> Result<f64, VirtualError> {
        let point = request.commanded_position(half, line, pixel);
        let (column, row) = self.pixel_of(point);
        let image = self.image_for(request.direction, half);
        image
            .height_nm_at(column, row)
            .map(|h| h / self.params.z_nm_per_count)
            .ok_or_else(|| VirtualError::OutOfRange {
                what: "a scan",
                detail: format!("pixel at ({}, {}) counts", point.x.value(), point.y.value()),
            })
    }
}

impl Microscope for VirtualMicroscope {
    type Error = VirtualError;

    fn capabilities(&self) -> Capabilities {
        let image = &self.surface.forward;
        let min = self.counts_of(1.0, 1.0);
        let max = self.counts_of(image.columns() as f64 - 2.0, image.rows() as f64 - 2.0);
        Capabilities {
            field_min: min,
            field_max: max,
            z_min: Counts(-1e9),
            z_max: Counts(1e9),
            lateral_resolution: Counts(1e-6),
            max_pixels_per_line: MAX_SCAN_PIXELS,
            pixels_per_line_multiple: 1,
            max_lines: MAX_SCAN_PIXELS,
            min_pixel_dwell: Seconds(1e-9),
            counter_scan: true,
            backward_trace: true,
            coarse_z: None,
        }
    }

    fn now(&mut self) -> Result<Seconds, Self::Error> {
        Ok(Seconds(self.clock_s))
    }

    fn wait(&mut self, duration: Seconds) -> Result<(), Self::Error> {
        let d = duration.value();
        if !(d.is_finite() && d >= 0.0) {
            return Err(VirtualError::Invalid(format!("wait of {d} s")));
        }
        self.clock_s += d;
        Ok(())
    }

    fn position(&mut self) -> Result<CountPoint, Self::Error> {
        Ok(self.position)
    }

    fn move_to(&mut self, request: MoveRequest) -> Result<(), Self::Error> {
        let speed = request.speed.value();
        let settle = request.settle.value();
        if !(speed.is_finite() && speed > 0.0 && settle.is_finite() && settle >= 0.0) {
            return Err(VirtualError::Invalid(format!(
                "move at {speed} counts/s with a settle of {settle} s"
            )));
        }
        if !self.inside(request.target) {
            return Err(VirtualError::OutOfRange {
                what: "a move",
                detail: format!(
                    "target ({}, {}) counts",
                    request.target.x.value(),
                    request.target.y.value()
                ),
            });
        }
        let distance = self.position.distance(request.target).value();
        self.clock_s += distance / speed + settle;
        self.position = request.target;
        Ok(())
    }

    fn scan(&mut self, request: &ScanRequest) -> Result<Frame, Self::Error> {
        request
            .validate()
            .map_err(|e| VirtualError::Invalid(e.to_string()))?;
        if request.pixels_per_line > MAX_SCAN_PIXELS || request.lines > MAX_SCAN_PIXELS {
            return Err(VirtualError::Invalid(format!(
                "{} × {} pixels: at most {MAX_SCAN_PIXELS} per side",
                request.pixels_per_line, request.lines
            )));
        }
        let caps = self.capabilities();
        request
            .check_inside(caps.field_min, caps.field_max)
            .map_err(|e| VirtualError::OutOfRange {
                what: "a scan",
                detail: e.to_string(),
            })?;
        let nx = request.pixels_per_line as usize;
        let ny = request.lines as usize;
        // The original raster's speed: pixel_time_s per image pixel along x.
        let (cx, _) = self.counts_per_pixel();
        let dwell_s = self.surface.forward.pixel_time_s() * request.pixel_step.value() / cx;
        let start_s = self.clock_s;
        let mut forward = TraceImage {
            z_counts: Vec::with_capacity(nx * ny),
            time_s: Vec::with_capacity(nx * ny),
        };
        let mut backward = request.record_backward.then(|| TraceImage {
            z_counts: Vec::with_capacity(nx * ny),
            time_s: Vec::with_capacity(nx * ny),
        });
        for line in 0..ny {
            let line_start_s = start_s + (2 * nx * line) as f64 * dwell_s;
            for pixel in 0..nx {
                forward
                    .z_counts
                    .push(self.sample(request, TraceHalf::Forward, line, pixel)?);
                forward
                    .time_s
                    .push(line_start_s + (pixel as f64 + 0.5) * dwell_s);
            }
            if let Some(back) = backward.as_mut() {
                for pixel in 0..nx {
                    back.z_counts
                        .push(self.sample(request, TraceHalf::Backward, line, pixel)?);
                    back.time_s
                        .push(line_start_s + ((nx + pixel) as f64 + 0.5) * dwell_s);
                }
            }
        }
        self.clock_s = start_s + (2 * nx * ny) as f64 * dwell_s;
        self.position = request.commanded_position(TraceHalf::Forward, ny - 1, 0);
        Ok(Frame {
            request: request.clone(),
            forward,
            backward,
        })
    }

    fn z_position(&mut self) -> Result<Counts, Self::Error> {
        Ok(Counts(0.0))
    }

    fn coarse_z(&mut self) -> Option<&mut dyn CoarseZStage<Error = Self::Error>> {
        None
    }
}
