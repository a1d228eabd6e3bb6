//! The `Microscope` trait: the one I/O boundary between algorithms and an instrument.

use crate::scan::{Frame, ScanRequest};
use crate::units::{CountPoint, Counts, CountsPerSecond, Seconds};
use serde::{Deserialize, Serialize};

/// What went wrong, in terms every backend shares. Algorithms match on this,
/// never on a backend's own error type.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[non_exhaustive]
pub enum ErrorKind {
    /// The instrument did not answer in time.
    Timeout,
    /// The link to the controller failed or returned garbage.
    Communication,
    /// The Z feedback lost the surface (tip crash or lift-off).
    FeedbackLost,
    /// A requested position or region is outside what the instrument can reach.
    OutOfRange,
    /// The operation was aborted (by the user or the controller).
    Aborted,
    /// Anything else.
    Other,
}

impl ErrorKind {
    /// True for failures that may go away when the operation is retried.
    pub fn is_transient(self) -> bool {
        matches!(
            self,
            Self::Timeout | Self::Communication | Self::FeedbackLost
        )
    }
}

impl std::fmt::Display for ErrorKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let text = match self {
            Self::Timeout => "the instrument timed out",
            Self::Communication => "communication with the instrument failed",
            Self::FeedbackLost => "the Z feedback lost the surface",
            Self::OutOfRange => "the request is out of the instrument's range",
            Self::Aborted => "the operation was aborted",
            Self::Other => "instrument error",
        };
        f.write_str(text)
    }
}

/// A backend's error type: anything that can say which [`ErrorKind`] it is.
pub trait Error: std::error::Error + Send + Sync + 'static {
    /// The kind of failure.
    fn kind(&self) -> ErrorKind;
}

impl std::error::Error for ErrorKind {}

impl Error for ErrorKind {
    fn kind(&self) -> ErrorKind {
        *self
    }
}

/// Optional coarse-approach stage, found through [`Microscope::coarse_z`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CoarseZCapability {
    /// Smallest reachable stage position, in steps.
    pub min_steps: i64,
    /// Largest reachable stage position, in steps.
    pub max_steps: i64,
}

/// What a backend can do. Algorithms ask; they never try-and-fail.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Capabilities {
    /// Smallest lateral position, counts.
    pub field_min: CountPoint,
    /// Largest lateral position, counts.
    pub field_max: CountPoint,
    /// Smallest Z-manipulator position, counts.
    pub z_min: Counts,
    /// Largest Z-manipulator position, counts.
    pub z_max: Counts,
    /// Smallest commandable lateral increment (DAC resolution), counts.
    pub lateral_resolution: Counts,
    /// Largest pixels per line of one scan.
    pub max_pixels_per_line: u32,
    /// The controller's granularity of pixels per line: it acquires lines of a whole
    /// multiple of this many pixels (≥ 1; 1: any count). A Nanonis controller's is 16 (its
    /// real-time engine sends data in packets of 16 pixels). A backend with a granularity
    /// above 1 scans a request of `n` pixels per line with the same frame, pixel centres
    /// and line time when `n` divides the next multiple of the granularity (`n` a divisor
    /// or a multiple of it): the line oversampled and each requested pixel the mean of its
    /// samples ([`honours_pixels_per_line`](Self::honours_pixels_per_line)). Any other
    /// count costs the instrument the padding's pixels (the backend documents how). Absent
    /// in a serialised record of an older version: 1.
    #[serde(default = "one_pixel")]
    pub pixels_per_line_multiple: u32,
    /// Largest number of lines of one scan.
    pub max_lines: u32,
    /// Shortest pixel dwell, seconds.
    pub min_pixel_dwell: Seconds,
    /// Counter scans ([`ScanDirection::Counter`](crate::ScanDirection::Counter)) are supported.
    pub counter_scan: bool,
    /// The backward trace can be recorded.
    pub backward_trace: bool,
    /// The coarse approach stage, when there is one that software can drive.
    pub coarse_z: Option<CoarseZCapability>,
}

fn one_pixel() -> u32 {
    1
}

impl Capabilities {
    /// The pixels per line the controller acquires for a request of `pixels`: the next
    /// multiple of [`Self::pixels_per_line_multiple`] (a granularity of 0 taken as 1).
    #[must_use]
    pub fn acquired_pixels_per_line(&self, pixels: u32) -> u32 {
        let multiple = self.pixels_per_line_multiple.max(1);
        pixels.div_ceil(multiple).saturating_mul(multiple)
    }

    /// True when a request of `pixels` per line (≥ 1) is scanned exactly as asked (its
    /// frame, pixel centres and line time) at the controller's granularity: `pixels` divides
    /// the pixels the controller acquires for it ([`Self::acquired_pixels_per_line`]), each
    /// requested pixel then the mean of a whole number of samples.
    #[must_use]
    pub fn honours_pixels_per_line(&self, pixels: u32) -> bool {
        pixels > 0 && self.acquired_pixels_per_line(pixels).is_multiple_of(pixels)
    }
}

/// A lateral move with the feedback on.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MoveRequest {
    /// Target position, counts.
    pub target: CountPoint,
    /// Speed of the move (> 0).
    pub speed: CountsPerSecond,
    /// Time to wait at the target before returning, seconds (≥ 0).
    pub settle: Seconds,
}

/// The coarse approach stage (optional capability).
pub trait CoarseZStage {
    /// The backend's error type.
    type Error: Error;
    /// Moves the stage by `steps` (positive = towards the sample).
    fn step(&mut self, steps: i64) -> Result<(), Self::Error>;
    /// The stage's current position, steps.
    fn position_steps(&mut self) -> Result<i64, Self::Error>;
}

/// A scanning probe microscope, real or simulated.
///
/// The trait is small on purpose: the clock, a pause, lateral moves, raster
/// scans, the Z position, and capability queries. Everything else (feature
/// recognition, skipping, calibration) is built on top of it and is generic
/// over it.
///
/// # Example
/// A generic measurement that works with any backend:
/// ```
/// use spm_hal::{Microscope, ScanRequest, CountPoint, Counts, Seconds, TraceHalf};
///
/// fn mean_height<M: Microscope>(microscope: &mut M) -> Result<f64, M::Error> {
///     let caps = microscope.capabilities();
///     let centre = CountPoint::new(
///         (caps.field_min.x + caps.field_max.x) * 0.5,
///         (caps.field_min.y + caps.field_max.y) * 0.5,
///     );
///     let request = ScanRequest::centred_square(centre, Counts(1.0), 8, Seconds(1e-4));
///     let frame = microscope.scan(&request)?;
///     let z = &frame.forward.z_counts;
///     Ok(z.iter().sum::<f64>() / z.len() as f64)
/// }
///
/// // Drive it with the scripted mock: one scan of a flat surface at z = 7 counts.
/// use spm_hal::mock::{Expectation, ScriptedMicroscope};
/// let mut mock = ScriptedMicroscope::new(ScriptedMicroscope::default_capabilities());
/// mock.expect(Expectation::scan(|_point, _time| Counts(7.0)));
/// assert_eq!(mean_height(&mut mock).unwrap(), 7.0);
/// mock.done().unwrap();
/// ```
pub trait Microscope {
    /// The backend's error type.
    type Error: Error;

    /// What this backend can do.
    fn capabilities(&self) -> Capabilities;

    /// The instrument clock, seconds since an arbitrary epoch.
    fn now(&mut self) -> Result<Seconds, Self::Error>;

    /// Pauses for `duration` (the sample keeps drifting, the scanner keeps creeping).
    fn wait(&mut self, duration: Seconds) -> Result<(), Self::Error>;

    /// The commanded lateral position of the probe, counts.
    fn position(&mut self) -> Result<CountPoint, Self::Error>;

    /// Moves the probe laterally with the feedback on, then waits `settle`.
    fn move_to(&mut self, request: MoveRequest) -> Result<(), Self::Error>;

    /// Runs a raster scan and returns its frame. The probe ends where the last
    /// retrace ends (the start of the last line).
    fn scan(&mut self, request: &ScanRequest) -> Result<Frame, Self::Error>;

    /// The Z-manipulator position now, counts.
    fn z_position(&mut self) -> Result<Counts, Self::Error>;

    /// The coarse approach stage, when the backend has one software can drive.
    fn coarse_z(&mut self) -> Option<&mut dyn CoarseZStage<Error = Self::Error>>;
}

impl<T: Microscope + ?Sized> Microscope for &mut T {
    type Error = T::Error;

    fn capabilities(&self) -> Capabilities {
        T::capabilities(self)
    }
    fn now(&mut self) -> Result<Seconds, Self::Error> {
        T::now(self)
    }
    fn wait(&mut self, duration: Seconds) -> Result<(), Self::Error> {
        T::wait(self, duration)
    }
    fn position(&mut self) -> Result<CountPoint, Self::Error> {
        T::position(self)
    }
    fn move_to(&mut self, request: MoveRequest) -> Result<(), Self::Error> {
        T::move_to(self, request)
    }
    fn scan(&mut self, request: &ScanRequest) -> Result<Frame, Self::Error> {
        T::scan(self, request)
    }
    fn z_position(&mut self) -> Result<Counts, Self::Error> {
        T::z_position(self)
    }
    fn coarse_z(&mut self) -> Option<&mut dyn CoarseZStage<Error = Self::Error>> {
        T::coarse_z(self)
    }
}
