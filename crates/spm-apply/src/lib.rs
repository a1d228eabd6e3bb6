//! # spm-apply: an spmcal calibration applied to SPM image files, as users take them
//!
//! What `spmcal correct` does, as a library (the CLI only reads, writes and reports):
//!
//! 1. **The file's own raster** ([`FileRaster`]): pixels, physical size and centre (the
//!    controller's scan offset), scan angle, slow-axis direction (up or down), forward and
//!    backward halves. Scanner counts come from the file when it records them (files spmcal
//!    writes: `spmcal_origin_x_counts`, `spmcal_origin_y_counts`, `spmcal_pixel_step_counts`),
//!    otherwise from its nm geometry through the controller's nominal sensitivity.
//! 2. **Guard rails** ([`check`]), each a typed [`ApplyError`] naming the file and the field:
//!    an already corrected file, a scanner or counts convention that does not match the
//!    calibration, a nominal sensitivity that disagrees with it, an image outside the
//!    calibrated region (unless extrapolation is allowed; the output is then marked).
//! 3. **One geometric map for every channel** ([`coordinate_map`]): eq. (5) integrated along
//!    the scanner's real path to every pixel — up (or down) the line-start column, then along
//!    the line — in the scanner's axes, then turned back into the frame's axes. A backward
//!    (retrace) half reaches each pixel along its own line after the forward trace; the static
//!    field's integrals along the trace and back cancel, so it shares the forward map.
//! 4. **Faithful output** ([`correct_file`] → [`Corrected`]): every pixel without data is NaN
//!    (never filled), the source header travels with the result, and the calibration's
//!    provenance, the dynamics used and the expected error of the correction are recorded.
//!
//! ## Scan angle
//! [`FileRaster::angle_ccw_rad`] is the rotation of the frame's axes in the scanner's plane,
//! counter-clockwise positive, as the scanner's axes are seen in an unrotated display.
//! Nanonis states its scan angle clockwise positive (`Scan.FrameSet`: "positive angle means
//! clockwise rotation"), so an `.sxm`'s `SCAN_ANGLE` enters with its sign reversed; other
//! formats' angles are taken as counter-clockwise ([`angle_ccw_deg`]).
//!
//! ## Dynamics
//! Only the static field is corrected here. The hysteresis and creep of the raster are not
//! (no hysteresis operator is identified yet); [`Corrected::dynamics`] says so, and the output
//! carries it in `spmcal_dynamics`.
#![doc = include_str!("../README.md")]
#![warn(missing_docs)]

use std::path::{Path, PathBuf};

pub mod counter;
pub mod crop;
pub mod dynamic;
pub mod history;
pub mod ruler;

use spm_correction::{
    CoordinateMap, CorrectionError, CorrectionField, CountRegion, CountsConvention, Integration,
    Interpolation, OutputGrid, Parallelism, PlaneSurfaces, Quadrature, RasterGeometry, Route,
    SurfaceSet, YCoordinates, correct_polyline, correct_raster, field_at_z, resample,
};
use spm_formats::{Channel, Direction, Format, ScanDir, SpmFile};
use spm_hal::{CountPoint, Counts, ScanDirection};

/// Header field a corrected file carries (its presence refuses a second correction).
pub const KEY_CORRECTED: &str = "spmcal_corrected";
/// Header field: the file's raster origin x in scanner counts (display bottom-left pixel).
pub const KEY_ORIGIN_X: &str = "spmcal_origin_x_counts";
/// Header field: the file's raster origin y in scanner counts.
pub const KEY_ORIGIN_Y: &str = "spmcal_origin_y_counts";
/// Header field: the pixel step in scanner counts.
pub const KEY_STEP: &str = "spmcal_pixel_step_counts";
/// Header field: the scanner the file was taken with.
pub const KEY_SCANNER: &str = "spmcal_scanner_id";
/// Header field: the counts convention of the recorded raster.
pub const KEY_CONVENTION: &str = "spmcal_counts_convention";
/// Header field: the controller's nominal sensitivity when the file was taken, nm/count.
pub const KEY_NOMINAL: &str = "spmcal_nominal_nm_per_count";

/// Header field: the path of the raster as spmcal's own files record it (`direct`: +x lines,
/// slow axis up; `counter`: −x lines from the far corner, slow axis down; `down`: +x lines,
/// slow axis down).
pub const KEY_SCAN_PATH: &str = "spmcal_scan_path";

/// Header field: the duration of one trace (one retrace), s, as spmcal's own files record it.
pub const KEY_LINE_TIME: &str = "spmcal_line_time_s";

/// A nominal sensitivity and the calibration's may differ by up to this factor either way
/// (a real scanner differs from its datasheet by tens of %; a unit slip is a factor 10³–10⁹).
pub const MAX_SENSITIVITY_RATIO: f64 = 2.0;

/// An image may reach this fraction of the calibrated region's larger side beyond it before
/// it counts as outside (the region is the records' extent; the net's outermost nodes stand
/// for a little beyond).
pub const REGION_TOLERANCE_FRACTION: f64 = 0.05;

/// Why a file could not be corrected.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ApplyError {
    /// A header field is missing or unusable for the raster.
    #[error("{}: header field `{field}`: {reason}", file.display())]
    Header {
        /// The image file.
        file: PathBuf,
        /// The field.
        field: String,
        /// What is wrong.
        reason: String,
    },
    /// An option is unusable.
    #[error("{option}: {reason}")]
    Option {
        /// The option, as the user wrote it.
        option: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// The file holds no channel to correct, or not the one asked for.
    #[error("{}: {reason}", file.display())]
    Channel {
        /// The image file.
        file: PathBuf,
        /// What is missing.
        reason: String,
    },
    /// The file was written by `spmcal correct` already.
    #[error(
        "{}: already corrected by spmcal (header field `{field}`); correcting it again would \
         apply the calibration twice — correct the raw file instead",
        file.display()
    )]
    AlreadyCorrected {
        /// The image file.
        file: PathBuf,
        /// The field that says so.
        field: &'static str,
    },
    /// The file names another scanner than the calibration's.
    #[error(
        "{}: header field `{KEY_SCANNER}` = {found:?}, but the calibration is of scanner {expected:?}",
        file.display()
    )]
    ScannerMismatch {
        /// The image file.
        file: PathBuf,
        /// The file's scanner.
        found: String,
        /// The calibration's scanner.
        expected: String,
    },
    /// The file's counts convention is not the calibration's.
    #[error(
        "{}: header field `{KEY_CONVENTION}` = {found:?}, but the calibration's counts are {expected:?}",
        file.display()
    )]
    ConventionMismatch {
        /// The image file.
        file: PathBuf,
        /// The file's convention.
        found: String,
        /// The calibration's convention.
        expected: String,
    },
    /// The nominal sensitivity that turns the file's nm into counts disagrees with the
    /// calibration.
    #[error(
        "{}: nominal sensitivity {given} nm/count (from {field}) disagrees with the calibration's \
         {expected} nm/count ({basis}) by a factor {ratio:.3e}; at most {MAX_SENSITIVITY_RATIO} is \
         accepted (a sensitivity given in m instead of nm is off by 10⁹)",
        file.display()
    )]
    SensitivityMismatch {
        /// The image file.
        file: PathBuf,
        /// Where the nominal sensitivity came from.
        field: String,
        /// The nominal sensitivity, nm/count.
        given: f64,
        /// The calibration's, nm/count.
        expected: f64,
        /// What the calibration's value is.
        basis: &'static str,
        /// max(given/expected, expected/given).
        ratio: f64,
    },
    /// The image lies (partly) outside the calibrated region.
    #[error(
        "{}: the image reaches {distance_counts:.0} counts ({percent:.0} % of the calibrated \
         region's side) beyond the calibrated region x {:.0}…{:.0}, y {:.0}…{:.0} counts of the \
         plane z = {z_counts} counts (image x {:.0}…{:.0}, y {:.0}…{:.0} counts); its surfaces \
         would be extrapolated. Check the file's size, offset and sensitivity, or pass \
         --allow-extrapolation to correct it anyway (the output is then marked)",
        file.display(),
        region.x_min_counts, region.x_max_counts, region.y_min_counts, region.y_max_counts,
        image.x_min_counts, image.x_max_counts, image.y_min_counts, image.y_max_counts
    )]
    OutsideRegion {
        /// The image file.
        file: PathBuf,
        /// The calibrated region.
        region: CountRegion,
        /// The image's bounding box, counts.
        image: CountRegion,
        /// Largest distance of an image corner outside, counts.
        distance_counts: f64,
        /// The same in % of the region's larger side.
        percent: f64,
        /// The plane.
        z_counts: f64,
    },
    /// The calibration's coefficients are implausible where the image lies.
    #[error(
        "the calibration's plane z = {z_counts}: field `{field}` = {value} at ({x_counts:.0}, \
         {y_counts:.0}) counts, under the image {}, {reason}",
        file.display()
    )]
    Calibration {
        /// The image file.
        file: PathBuf,
        /// The plane.
        z_counts: f64,
        /// The coefficient.
        field: &'static str,
        /// Its value.
        value: f64,
        /// Where, x.
        x_counts: f64,
        /// Where, y.
        y_counts: f64,
        /// The rule it breaks.
        reason: &'static str,
    },
    /// The correction math refused (invalid calibration, map or data).
    #[error("{}: channel {channel:?}: {source}", file.display())]
    Correction {
        /// The image file.
        file: PathBuf,
        /// The channel (or "map" for the shared geometric map).
        channel: String,
        /// The cause.
        source: CorrectionError,
    },
}

impl ApplyError {
    /// True when the input (file, calibration or option) is at fault, false for a failure of
    /// the machine (a thread pool that could not start).
    #[must_use]
    pub fn is_bad_input(&self) -> bool {
        !matches!(
            self,
            Self::Correction {
                source: CorrectionError::ThreadPool(_),
                ..
            }
        )
    }
}

/// Which channels to correct.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum ChannelSelection {
    /// Every image channel (forward and backward halves).
    #[default]
    All,
    /// The first forward channel in metres (the height), else the first channel.
    Height,
    /// The channels of this name (both halves), case-insensitive.
    Named(String),
}

/// How a file's raster is turned into counts and corrected.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ApplyOptions {
    /// Channels to correct.
    pub channels: ChannelSelection,
    /// The controller's nominal sensitivity, nm per count, for files that do not record their
    /// raster in counts (overrides the file's `spmcal_nominal_nm_per_count`).
    pub nominal_nm_per_count: Option<f64>,
    /// Z level of the image, counts (the lateral field is blended between the bracketing
    /// planes). Default: the plane nearest z = 0.
    pub z_counts: Option<f64>,
    /// Correct an image outside the calibrated region anyway (the output is marked).
    pub allow_extrapolation: bool,
    /// The scanner the user states the file was taken with (checked against the calibration
    /// when the file does not name its scanner).
    pub scanner_id: Option<String>,
    /// Override of the file's path: [`RasterPath::Counter`] for a counter-scanned frame.
    pub path: Option<RasterPath>,
    /// Apply the static field only, even when the calibration file holds dynamics.
    pub static_only: bool,
    /// The command history the image was taken with (`spmcal scan`'s sidecar): with the
    /// calibration's dynamics, the creep of the approach move is corrected too.
    pub history: Option<history::ScanHistory>,
    /// Interpolation of the resampling.
    pub interpolation: Interpolation,
    /// Measure the approach move's creep and the drift against the standard's lattice in the
    /// image itself ([`ruler`]), when the file is corrected along its own raster (no
    /// recorded history).
    pub ruler: Option<ruler::LatticeRuler>,
    /// The image's counter-scanned partner ([`counter`]): the drift and the part of the
    /// approach creep the two frames show, measured between them, when the file is corrected
    /// along its own raster (no recorded history).
    pub counter: Option<CounterPartner>,
}

/// A counter-scanned partner of the image (`spmcal correct --counter FILE`): the same place
/// scanned right before or after it with the slow axis the other way.
#[derive(Debug, Clone, PartialEq)]
pub struct CounterPartner {
    /// The partner file as read.
    pub file: SpmFile,
    /// Time from the image's first pixel to the partner's, s (negative: the partner came
    /// first). `None`: from the files' time stamps, and at least the earlier frame's duration
    /// (frames scanned back to back share their stamps' second).
    pub delay_s: Option<f64>,
    /// The feature scale the frames are matched at (the standard's lattice constant, or the
    /// sample's feature spacing).
    pub spacing: ruler::LatticeRuler,
}

/// The path the scanner takes to every pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RasterPath {
    /// Lines traced +x from the left edge; the slow axis steps as the file says.
    Trace(ScanDir),
    /// A counter scan: lines traced −x from the right edge, the slow axis stepping down from
    /// the far corner.
    Counter,
}

/// Where a raster's counts come from.
#[derive(Debug, Clone, PartialEq)]
pub enum CountsSource {
    /// The file records its raster in counts.
    Recorded,
    /// The file's nm geometry divided by a nominal sensitivity.
    Nominal {
        /// nm per count.
        nm_per_count: f64,
        /// Where it came from (an option or a header field).
        field: String,
    },
}

/// The raster of one channel in scanner counts, as the file states it.
#[derive(Debug, Clone, PartialEq)]
pub struct FileRaster {
    /// Pixels per line.
    pub columns: usize,
    /// Lines.
    pub rows: usize,
    /// Commanded frame centre, counts.
    pub centre: CountPoint,
    /// Pixel step along the fast axis, counts.
    pub step_x_counts: f64,
    /// Line step along the slow axis, counts.
    pub step_y_counts: f64,
    /// Rotation of the frame's axes, counter-clockwise, rad.
    pub angle_ccw_rad: f64,
    /// The path to every pixel.
    pub path: RasterPath,
    /// Where the counts come from.
    pub counts: CountsSource,
    /// Duration of one trace (or retrace), s, when the file says it (`.sxm` `SCAN_TIME`,
    /// `.sm4` line period, spmcal's own [`KEY_LINE_TIME`]): the raster's dynamics need it.
    pub line_time_s: Option<f64>,
}

/// The scan angle of a channel, counter-clockwise positive, degrees (see the crate docs):
/// a Nanonis `.sxm` states it clockwise positive.
#[must_use]
pub fn angle_ccw_deg(format: Format, channel: &Channel) -> f64 {
    let angle = channel.angle_deg().unwrap_or(0.0);
    match format {
        Format::NanonisSxm => -angle,
        _ => angle,
    }
}

fn header_number(file: &SpmFile, key: &str) -> Result<Option<f64>, ApplyError> {
    file.header_value(key)
        .map(|v| {
            v.trim()
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| ApplyError::Header {
                    file: file.source.clone(),
                    field: key.to_owned(),
                    reason: format!("{v:?} is not a finite number"),
                })
        })
        .transpose()
}

impl FileRaster {
    /// The raster of `channel` of `file`.
    ///
    /// # Errors
    /// [`ApplyError::Header`] for unusable geometry fields, [`ApplyError::Option`] for a bad
    /// nominal sensitivity.
    pub fn of(
        file: &SpmFile,
        channel: &Channel,
        nominal_nm_per_count: Option<f64>,
        path: Option<RasterPath>,
    ) -> Result<Self, ApplyError> {
        let (columns, rows) = (channel.nx(), channel.ny());
        let line_time_s = match header_number(file, KEY_LINE_TIME)? {
            Some(t) if t > 0.0 => Some(t),
            Some(t) => {
                return Err(ApplyError::Header {
                    file: file.source.clone(),
                    field: KEY_LINE_TIME.to_owned(),
                    reason: format!("{t} s: a line takes a positive time"),
                });
            }
            None => file.line_time_s.filter(|t| t.is_finite() && *t > 0.0),
        };
        let header = |field: &str, reason: String| ApplyError::Header {
            file: file.source.clone(),
            field: field.to_owned(),
            reason,
        };
        let slow = channel.scan_dir().or(file.scan_dir).unwrap_or(ScanDir::Up);
        let recorded_path = match file.header_value(KEY_SCAN_PATH).map(str::trim) {
            None => None,
            Some("direct") => Some(RasterPath::Trace(ScanDir::Up)),
            Some("down") => Some(RasterPath::Trace(ScanDir::Down)),
            Some("counter") => Some(RasterPath::Counter),
            Some(other) => {
                return Err(header(
                    KEY_SCAN_PATH,
                    format!("{other:?} is not one of direct, down, counter"),
                ));
            }
        };
        let path = path.or(recorded_path).unwrap_or(RasterPath::Trace(slow));
        let recorded = (
            header_number(file, KEY_ORIGIN_X)?,
            header_number(file, KEY_ORIGIN_Y)?,
            header_number(file, KEY_STEP)?,
        );
        if let (Some(x0), Some(y0), Some(step)) = recorded
            && nominal_nm_per_count.is_none()
        {
            if step.is_nan() || step <= 0.0 {
                return Err(header(KEY_STEP, format!("{step} must be > 0")));
            }
            let half = |n: usize| step * (n as f64 - 1.0) / 2.0;
            return Ok(Self {
                line_time_s,
                columns,
                rows,
                centre: CountPoint::from_counts(x0 + half(columns), y0 + half(rows)),
                step_x_counts: step,
                step_y_counts: step,
                angle_ccw_rad: angle_ccw_deg(file.format, channel).to_radians(),
                path,
                counts: CountsSource::Recorded,
            });
        }
        let (k, field) = match (nominal_nm_per_count, header_number(file, KEY_NOMINAL)?) {
            (Some(k), _) => (k, "--nominal-nm-per-count".to_owned()),
            (None, Some(k)) => (k, format!("header field `{KEY_NOMINAL}`")),
            (None, None) => {
                return Err(ApplyError::Option {
                    option: "--nominal-nm-per-count",
                    reason: format!(
                        "{}: the file does not record its raster in scanner counts; give the \
                         controller's nominal sensitivity (nm per count)",
                        file.source.display()
                    ),
                });
            }
        };
        let (lo, hi) = SENSITIVITY_RANGE_NM_PER_COUNT;
        if !(k.is_finite() && (lo..=hi).contains(&k)) {
            return Err(ApplyError::Option {
                option: "--nominal-nm-per-count",
                reason: format!(
                    "{}: {k:e} nm/count ({field}) must lie in [1e-9, 1e3] (a 1 µm field over 2¹⁶ \
                     counts is 0.015; a sensitivity in m instead of nm is 10⁹ too small)",
                    file.source.display()
                ),
            });
        }
        let (px, py) = match (channel.pixel_x_nm(), channel.pixel_y_nm()) {
            (Some(px), Some(py)) if px > 0.0 && py > 0.0 && px.is_finite() && py.is_finite() => {
                (px, py)
            }
            _ => {
                return Err(header(
                    "size",
                    "the file records no physical pixel size".to_owned(),
                ));
            }
        };
        let angle = angle_ccw_deg(file.format, channel);
        if !angle.is_finite() {
            return Err(header("scan angle", format!("{angle} is not finite")));
        }
        let (cx, cy) = (
            channel.center_x_nm().unwrap_or(0.0),
            channel.center_y_nm().unwrap_or(0.0),
        );
        if !(cx.is_finite() && cy.is_finite()) {
            return Err(header("offset", format!("({cx}, {cy}) nm is not finite")));
        }
        Ok(Self {
            line_time_s,
            columns,
            rows,
            centre: CountPoint::from_counts(cx / k, cy / k),
            step_x_counts: px / k,
            step_y_counts: py / k,
            angle_ccw_rad: angle.to_radians(),
            path,
            counts: CountsSource::Nominal {
                nm_per_count: k,
                field,
            },
        })
    }

    /// Commanded position (counts) of the pixel in display column `column`, display row `row`
    /// (row 0 = top).
    #[must_use]
    pub fn pixel_counts(&self, column: f64, row: f64) -> CountPoint {
        self.pixel_counts_rotated(column, row, self.angle_ccw_rad.sin_cos())
    }

    /// [`FileRaster::pixel_counts`] given `(sin, cos)` of the scan angle (computed once for
    /// every pixel of a frame).
    #[inline]
    fn pixel_counts_rotated(&self, column: f64, row: f64, (s, c): (f64, f64)) -> CountPoint {
        let u = (column - (self.columns as f64 - 1.0) / 2.0) * self.step_x_counts;
        let v = ((self.rows as f64 - 1.0) / 2.0 - row) * self.step_y_counts;
        CountPoint::from_counts(
            self.centre.x.value() + u * c - v * s,
            self.centre.y.value() + u * s + v * c,
        )
    }

    /// The bounding box of the raster's corners, counts.
    #[must_use]
    pub fn bounds(&self) -> CountRegion {
        let (w, h) = (self.columns as f64 - 1.0, self.rows as f64 - 1.0);
        let corners = [
            self.pixel_counts(0.0, 0.0),
            self.pixel_counts(w, 0.0),
            self.pixel_counts(0.0, h),
            self.pixel_counts(w, h),
        ];
        let xs: Vec<f64> = corners.iter().map(|p| p.x.value()).collect();
        let ys: Vec<f64> = corners.iter().map(|p| p.y.value()).collect();
        CountRegion::bounding(&xs, &ys, 0.0).unwrap_or(CountRegion {
            x_min_counts: f64::NAN,
            x_max_counts: f64::NAN,
            y_min_counts: f64::NAN,
            y_max_counts: f64::NAN,
        })
    }

    /// Display row of the `line`-th acquired line.
    fn display_row(&self, line: usize) -> usize {
        let down = match self.path {
            RasterPath::Trace(ScanDir::Down) | RasterPath::Counter => true,
            RasterPath::Trace(ScanDir::Up) => false,
        };
        if down { line } else { self.rows - 1 - line }
    }

    /// Display columns of a line in the order the scanner traces them.
    fn line_columns(&self) -> Box<dyn Iterator<Item = usize>> {
        match self.path {
            RasterPath::Counter => Box::new((0..self.columns).rev()),
            RasterPath::Trace(_) => Box::new(0..self.columns),
        }
    }
}

/// The checks a file must pass before it is corrected with `set` (see the crate docs).
/// Returns whether the image reaches beyond the calibrated region (allowed by the options).
///
/// # Errors
/// [`ApplyError::AlreadyCorrected`], [`ApplyError::ScannerMismatch`],
/// [`ApplyError::ConventionMismatch`], [`ApplyError::SensitivityMismatch`],
/// [`ApplyError::OutsideRegion`], [`ApplyError::Header`].
pub fn check(
    file: &SpmFile,
    set: &SurfaceSet,
    plane: &PlaneSurfaces,
    raster: &FileRaster,
    options: &ApplyOptions,
) -> Result<Option<f64>, ApplyError> {
    if file.header_value(KEY_CORRECTED).is_some() {
        return Err(ApplyError::AlreadyCorrected {
            file: file.source.clone(),
            field: KEY_CORRECTED,
        });
    }
    // Files written by the static `correct` of earlier versions.
    if file.header_value("spmcal_surfaces").is_some() {
        return Err(ApplyError::AlreadyCorrected {
            file: file.source.clone(),
            field: "spmcal_surfaces",
        });
    }
    let expected = &set.provenance.scanner_id;
    let stated = file
        .header_value(KEY_SCANNER)
        .map(str::trim)
        .map(str::to_owned)
        .or_else(|| options.scanner_id.clone());
    if let Some(found) = stated
        && !expected.is_empty()
        && found != *expected
    {
        return Err(ApplyError::ScannerMismatch {
            file: file.source.clone(),
            found,
            expected: expected.clone(),
        });
    }
    if raster.counts == CountsSource::Recorded
        && let Some(found) = file.header_value(KEY_CONVENTION)
    {
        let calibration = set
            .provenance
            .counts_convention
            .unwrap_or(CountsConvention::CentredSigned);
        if CountsConvention::parse(found) != Some(calibration) {
            return Err(ApplyError::ConventionMismatch {
                file: file.source.clone(),
                found: found.trim().to_owned(),
                expected: calibration.as_str().to_owned(),
            });
        }
    }
    if let CountsSource::Nominal {
        nm_per_count,
        field,
    } = &raster.counts
    {
        check_sensitivity(file, plane, set, raster, *nm_per_count, field)?;
    }
    let region = plane.calibrated_region();
    let image = raster.bounds();
    let side =
        (region.x_max_counts - region.x_min_counts).max(region.y_max_counts - region.y_min_counts);
    let w = raster.columns as f64 - 1.0;
    let h = raster.rows as f64 - 1.0;
    let distance = [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)]
        .iter()
        .map(|&(c, r)| {
            let p = raster.pixel_counts(c, r);
            region.distance_outside_counts(p.x.value(), p.y.value())
        })
        .fold(0.0_f64, f64::max);
    if !distance.is_finite() {
        return Err(ApplyError::Header {
            file: file.source.clone(),
            field: "geometry".to_owned(),
            reason: "the raster's corners are not finite".to_owned(),
        });
    }
    if distance > REGION_TOLERANCE_FRACTION * side.max(1.0) {
        if !options.allow_extrapolation {
            return Err(ApplyError::OutsideRegion {
                file: file.source.clone(),
                region,
                image,
                distance_counts: distance,
                percent: 100.0 * distance / side.max(1.0),
                z_counts: plane.z_counts,
            });
        }
        return Ok(Some(distance));
    }
    Ok(None)
}

/// Physical range of a sensitivity, nm per count (a 1 µm field over 2¹⁶ counts is 0.015).
pub const SENSITIVITY_RANGE_NM_PER_COUNT: (f64, f64) = (1e-9, 1e3);

/// Checks the plane's coefficients where the image lies: K̄x, K̄y and K̄yy = K̄y cos α finite
/// and in [`SENSITIVITY_RANGE_NM_PER_COUNT`], |α| < π/2 (a raster, not a mirror), on a grid of
/// up to 65 × 65 points over the raster including its corners.
///
/// # Errors
/// [`ApplyError::Calibration`].
pub fn check_coefficients(
    file: &SpmFile,
    plane: &PlaneSurfaces,
    raster: &FileRaster,
) -> Result<(), ApplyError> {
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
    for row in samples(raster.rows) {
        for column in samples(raster.columns) {
            let p = raster.pixel_counts(column, row);
            let (x, y) = (p.x.value(), p.y.value());
            let fail =
                |field: &'static str, value: f64, reason: &'static str| ApplyError::Calibration {
                    file: file.source.clone(),
                    z_counts: plane.z_counts,
                    field,
                    value,
                    x_counts: x,
                    y_counts: y,
                    reason,
                };
            for (field, value) in [
                (
                    "kx_nm_per_count",
                    plane.kx_nm_per_count.surface.evaluate(x, y),
                ),
                (
                    "ky_nm_per_count",
                    plane.ky_nm_per_count.surface.evaluate(x, y),
                ),
                (
                    "kyy_nm_per_count",
                    plane.kyy_nm_per_count.surface.evaluate(x, y),
                ),
            ] {
                if !(value.is_finite() && (lo..=hi).contains(&value)) {
                    return Err(fail(field, value, "is outside [1e-9, 1e3] nm/count"));
                }
            }
            let alpha = plane.alpha_rad.surface.evaluate(x, y);
            if !(alpha.is_finite() && alpha.abs() < std::f64::consts::FRAC_PI_2) {
                return Err(fail("alpha_rad", alpha, "must lie in (−π/2, π/2)"));
            }
        }
    }
    Ok(())
}

/// The nominal sensitivity against the calibration's: its provenance's nominal when recorded,
/// else the calibrated K̄x at the image centre.
fn check_sensitivity(
    file: &SpmFile,
    plane: &PlaneSurfaces,
    set: &SurfaceSet,
    raster: &FileRaster,
    given: f64,
    field: &str,
) -> Result<(), ApplyError> {
    let (expected, basis) = match set.provenance.nominal_nm_per_count {
        Some(k) => (k, "its runs' nominal"),
        None => {
            let region = plane.calibrated_region();
            let (x, y) = (
                raster
                    .centre
                    .x
                    .value()
                    .clamp(region.x_min_counts, region.x_max_counts),
                raster
                    .centre
                    .y
                    .value()
                    .clamp(region.y_min_counts, region.y_max_counts),
            );
            (
                plane.kx_nm_per_count.surface.evaluate(x, y),
                "its K̄x at the image centre",
            )
        }
    };
    if !(expected.is_finite() && expected > 0.0) {
        // An implausible calibration: check_coefficients names it.
        return Ok(());
    }
    let ratio = (given / expected).max(expected / given);
    if !(ratio.is_finite() && ratio <= MAX_SENSITIVITY_RATIO) {
        return Err(ApplyError::SensitivityMismatch {
            file: file.source.clone(),
            field: field.to_owned(),
            given,
            expected,
            basis,
            ratio,
        });
    }
    Ok(())
}

/// Corrected coordinates of every pixel of the raster, nm, in the frame's axes; indexed `[row * columns + column]` with row 0 the **bottom** display
/// row (scanner geometry), as [`resample`] expects. Returns the map and the corrected position
/// of the map's zero (the first acquired pixel, or eq. (7)'s origin corner on the analytic
/// path) from the field's origin (along x, then y), nm, scanner axes.
///
/// An unrotated raster traced from the left edge upward is eq. (7)'s direct raster (and a
/// counter scan its counter raster): those go through [`correct_raster`]'s analytic integrals.
/// Any other path (rotated frames, downward scans) integrates eq. (5) along the scanner's path
/// with [`correct_polyline`]: the line-start column, then each line.
///
/// # Errors
/// [`CorrectionError`] from the integration (non-finite field, invalid raster).
pub fn coordinate_map<F: CorrectionField + Sync>(
    field: &F,
    raster: &FileRaster,
) -> Result<(CoordinateMap, [f64; 2]), CorrectionError> {
    let quadrature = Quadrature::default();
    let axis_aligned = raster.angle_ccw_rad == 0.0 && raster.step_x_counts == raster.step_y_counts;
    let fast = match raster.path {
        RasterPath::Trace(ScanDir::Up) if axis_aligned => Some(ScanDirection::Direct),
        RasterPath::Counter if axis_aligned => Some(ScanDirection::Counter),
        _ => None,
    };
    let bottom_left = raster.pixel_counts(0.0, raster.rows as f64 - 1.0);
    // The map's zero: eq. (7)'s origin corner on the analytic path, else the first pixel.
    let zero = if fast.is_some() {
        bottom_left
    } else {
        raster.pixel_counts(
            match raster.path {
                RasterPath::Counter => raster.columns as f64 - 1.0,
                RasterPath::Trace(_) => 0.0,
            },
            raster.display_row(0) as f64,
        )
    };
    let to_zero = correct_polyline(
        field,
        &[
            CountPoint::from_counts(0.0, 0.0),
            CountPoint::from_counts(zero.x.value(), 0.0),
            zero,
        ],
        &quadrature,
    )?;
    let first_nm = to_zero
        .last()
        .map_or([0.0, 0.0], |p| [p.x.value(), p.y.value()]);
    if let Some(direction) = fast {
        let geometry = RasterGeometry::new(
            bottom_left,
            Counts(raster.step_x_counts),
            raster.columns,
            raster.rows,
        )?;
        let map = correct_raster(
            field,
            &geometry,
            direction,
            &Integration::default(),
            Parallelism::AllCores,
        )?;
        return Ok((map, first_nm));
    }
    general_map(field, raster, &quadrature).map(|map| (map, first_nm))
}

/// [`coordinate_map`] along the scanner's path for any raster, by [`correct_polyline`].
///
/// # Errors
/// As [`coordinate_map`].
pub fn general_map<F: CorrectionField + ?Sized>(
    field: &F,
    raster: &FileRaster,
    quadrature: &Quadrature,
) -> Result<CoordinateMap, CorrectionError> {
    let (nx, ny) = (raster.columns, raster.rows);
    let start_column = match raster.path {
        RasterPath::Counter => nx as f64 - 1.0,
        RasterPath::Trace(_) => 0.0,
    };
    let starts: Vec<CountPoint> = (0..ny)
        .map(|line| raster.pixel_counts(start_column, raster.display_row(line) as f64))
        .collect();
    let line_starts = correct_polyline(field, &starts, quadrature)?;
    let (s, c) = raster.angle_ccw_rad.sin_cos();
    let mut x_nm = vec![0.0; nx * ny];
    let mut y_nm = vec![0.0; nx * ny];
    let columns: Vec<usize> = raster.line_columns().collect();
    for (line, start) in line_starts.iter().enumerate() {
        let row = raster.display_row(line);
        let vertices: Vec<CountPoint> = columns
            .iter()
            .map(|&column| raster.pixel_counts(column as f64, row as f64))
            .collect();
        let along = correct_polyline(field, &vertices, quadrature)?;
        let map_row = ny - 1 - row;
        for (&column, offset) in columns.iter().zip(&along) {
            let x = start.x.value() + offset.x.value();
            let y = start.y.value() + offset.y.value();
            // Scanner axes → frame axes (rotation by −θ).
            let index = map_row * nx + column;
            x_nm[index] = x * c + y * s;
            y_nm[index] = -x * s + y * c;
        }
    }
    CoordinateMap::new(nx, ny, x_nm, YCoordinates::PerPixel(y_nm))
}

/// What the dynamics of the scanner contributed to a correction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DynamicsUsed {
    /// Static field only: the raster's hysteresis and the creep of the move that brought the
    /// probe there are not corrected.
    None,
    /// The calibration file holds dynamics, but the file states no line time.
    NoLineTime,
    /// The raster's hysteresis and creep along the file's own raster (trace or retrace per
    /// channel); of the approach move nothing is known (settled start assumed).
    Raster,
    /// The recorded command history (`spmcal scan`'s sidecar) through the dynamics: the
    /// raster and every command before it, the approach move's creep included.
    Recorded,
    /// [`DynamicsUsed::Raster`], and the approach move's creep and the drift measured against
    /// the standard's lattice in the image ([`ruler`]; the estimate in `spmcal_ruler_*`).
    RasterRuler,
    /// [`DynamicsUsed::Raster`] (the later frame replayed after the earlier one's raster), and
    /// the drift and the odd part of the approach creep measured between the image and its
    /// counter-scanned partner ([`counter`]; the estimate in `spmcal_counter_*`).
    RasterCounter,
}

impl DynamicsUsed {
    /// The text written into `spmcal_dynamics`.
    #[must_use]
    pub fn describe(self) -> &'static str {
        match self {
            Self::None => {
                "none: static distributed field only (eqs. 5-12); the raster's hysteresis and \
                 the creep of the approach move are not corrected"
            }
            Self::NoLineTime => {
                "none: the calibration holds the scanner's dynamics but the file states no line \
                 time; static distributed field only (eqs. 5-12)"
            }
            Self::Recorded => {
                "recorded: the scan's command history (the approach move and the raster) \
                 replayed through the calibration's hysteresis and creep"
            }
            Self::RasterRuler => {
                "raster + lattice ruler: the file's own raster replayed through the \
                 calibration's hysteresis and creep; the approach move's creep and the drift \
                 measured against the standard's lattice in the image (spmcal_ruler_*)"
            }
            Self::RasterCounter => {
                "raster + counter partner: the file's own raster replayed through the \
                 calibration's hysteresis and creep (after the partner's raster when the partner \
                 came first); the drift and the part of the approach move's creep odd about the \
                 pair's middle measured between the two frames (spmcal_counter_*); the even part \
                 is not seen by a pair"
            }
            Self::Raster => {
                "raster: the file's own raster (trace and retrace at its line time) replayed \
                 through the calibration's hysteresis and creep; the approach move's creep: \
                 none known (a settled start is assumed)"
            }
        }
    }
}

/// A corrected file: every selected channel on one uniform nm grid.
#[derive(Debug, Clone, PartialEq)]
pub struct Corrected {
    /// The corrected channels, display orientation, NaN where no data lies.
    pub channels: Vec<Channel>,
    /// Header fields for the output: the calibration's provenance, what was done, and the
    /// source header (keys prefixed `source_`, made identifiers).
    pub metadata: Vec<(String, String)>,
    /// The raster the file was corrected on.
    pub raster: FileRaster,
    /// Output pixels without data (NaN), per channel (the first channel's count).
    pub unknown_pixels: usize,
    /// How far the image reached beyond the calibrated region when extrapolation was allowed,
    /// counts.
    pub extrapolated_counts: Option<f64>,
    /// The dynamics used.
    pub dynamics: DynamicsUsed,
    /// The lattice ruler's estimate of the approach creep and drift, when it was used.
    pub ruler: Option<ruler::RulerEstimate>,
    /// The counter partner's estimate of the drift, when it was used.
    pub counter: Option<counter::PairEstimate>,
    /// Expected 1σ position error of the static correction over the image, nm (see
    /// [`expected_error_nm`]).
    pub expected_error_nm: f64,
    /// Output pixel, nm.
    pub step_nm: f64,
}

/// The expected 1σ position error of the static correction across the image, nm: each
/// surface's standard error σ·√(p/n) (σ of eq. 14, p terms of its degree, n records) carried
/// over the image's side in counts — K̄x over its width, K̄yy and α·K̄yy over its height —
/// combined in quadrature. It does not include the raster's dynamics.
#[must_use]
pub fn expected_error_nm(plane: &PlaneSurfaces, raster: &FileRaster) -> f64 {
    let n = plane.n_records.max(1) as f64;
    let se = |s: &spm_correction::FittedSurface| {
        let d = f64::from(s.degree);
        s.sigma * ((d + 1.0) * (d + 2.0) / 2.0 / n).sqrt()
    };
    let width = raster.step_x_counts * (raster.columns as f64 - 1.0);
    let height = raster.step_y_counts * (raster.rows as f64 - 1.0);
    let kyy = plane
        .kyy_nm_per_count
        .surface
        .evaluate(raster.centre.x.value(), raster.centre.y.value())
        .abs();
    let ex = se(&plane.kx_nm_per_count) * width;
    let ey = se(&plane.kyy_nm_per_count) * height;
    let ea = se(&plane.alpha_rad) * kyy * height;
    (ex * ex + ey * ey + ea * ea).sqrt()
}

fn selected<'f>(
    file: &'f SpmFile,
    selection: &ChannelSelection,
) -> Result<Vec<&'f Channel>, ApplyError> {
    let chosen: Vec<&Channel> = match selection {
        ChannelSelection::All => file.channels.iter().collect(),
        ChannelSelection::Height => file
            .channels
            .iter()
            .find(|c| c.direction() == Direction::Forward && c.unit() == "m")
            .or_else(|| file.channels.first())
            .into_iter()
            .collect(),
        ChannelSelection::Named(name) => file
            .channels
            .iter()
            .filter(|c| c.name().eq_ignore_ascii_case(name))
            .collect(),
    };
    if chosen.is_empty() {
        let available: Vec<String> = file
            .channels
            .iter()
            .map(|c| format!("{} ({})", c.name(), c.direction().as_str()))
            .collect();
        return Err(ApplyError::Channel {
            file: file.source.clone(),
            reason: match selection {
                ChannelSelection::Named(name) => format!(
                    "no channel named {name:?}; the file has: {}",
                    available.join(", ")
                ),
                _ => "the file holds no image channel".to_owned(),
            },
        });
    }
    Ok(chosen)
}

/// A header key as a GSF/GWY identifier: `source_` + the key with every other character `_`.
fn source_key(key: &str) -> String {
    let mut out = String::from("source_");
    out.extend(
        key.trim()
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' }),
    );
    out
}

/// The coordinate maps a file's channels are resampled with.
struct Maps {
    /// The first channel's half.
    map: CoordinateMap,
    /// Its frame's origin from the field's origin, nm.
    first_nm: [f64; 2],
    /// The other half's map and origin, when the dynamics make the halves differ and a channel
    /// of it is selected.
    other_half: Option<(CoordinateMap, [f64; 2])>,
    /// What the maps include.
    dynamics_used: DynamicsUsed,
    /// The lattice ruler's estimate, when it was applied.
    ruler: Option<ruler::RulerEstimate>,
    /// The counter partner's estimate, when it was applied.
    counter: Option<counter::PairEstimate>,
}

/// The half of the frame a channel holds. A channel's direction is that of its lines (forward
/// = +x, as Nanonis and Gwyddion name them): the trace of a +x raster, the retrace of a
/// counter raster (whose lines are traced −x first).
fn half_of(channel: &Channel, path: RasterPath) -> dynamic::Half {
    match (channel.direction(), path) {
        (Direction::Forward, RasterPath::Trace(_)) | (Direction::Backward, RasterPath::Counter) => {
            dynamic::Half::Trace
        }
        (Direction::Backward, RasterPath::Trace(_)) | (Direction::Forward, RasterPath::Counter) => {
            dynamic::Half::Retrace
        }
    }
}

/// The maps of [`correct_file`]: the raster's dynamics (recorded or replayed) when the
/// calibration file has them and the file states its line time, else the static field
/// (eqs. 5-12).
fn maps_for<F: CorrectionField + Sync>(
    file: &SpmFile,
    set: &SurfaceSet,
    options: &ApplyOptions,
    field: &F,
    raster: &FileRaster,
    channels: &[&Channel],
) -> Result<Maps, ApplyError> {
    let correction = |source: CorrectionError| ApplyError::Correction {
        file: file.source.clone(),
        channel: "map".to_owned(),
        source,
    };
    let first = channels
        .first()
        .copied()
        .ok_or_else(|| ApplyError::Channel {
            file: file.source.clone(),
            reason: "the file holds no image channel".to_owned(),
        })?;
    let with_dynamics = if options.static_only {
        None
    } else {
        set.dynamics
            .as_ref()
            .filter(|_| raster.line_time_s.is_some())
    };
    let recorded = options.history.as_ref().filter(|_| with_dynamics.is_some());
    let recorded_history = recorded.map(history::ScanHistory::command_history);
    let dynamics_used = match (with_dynamics, &set.dynamics) {
        (Some(_), _) if recorded.is_some() => DynamicsUsed::Recorded,
        (Some(_), _) => DynamicsUsed::Raster,
        (None, Some(_)) if !options.static_only => DynamicsUsed::NoLineTime,
        _ => DynamicsUsed::None,
    };
    let map_of = |half: dynamic::Half| -> Result<(CoordinateMap, [f64; 2]), ApplyError> {
        match (with_dynamics, recorded, &recorded_history) {
            (Some(d), Some(h), Some(commands)) => {
                let times = match half {
                    dynamic::Half::Trace => Some(&h.forward_pixel_times_s),
                    dynamic::Half::Retrace => h.backward_pixel_times_s.as_ref(),
                }
                .ok_or_else(|| ApplyError::Option {
                    option: "--history",
                    reason: "the history holds no backward pixel times for a backward channel"
                        .to_owned(),
                })?;
                dynamic::recorded_map(field, raster, d, half, commands, times).map_err(correction)
            }
            (Some(d), _, _) => dynamic::dynamic_map(field, raster, d, half).map_err(correction),
            (None, _, _) => coordinate_map(field, raster).map_err(correction),
        }
    };
    let (mut map, first_nm) = map_of(half_of(first, raster.path))?;
    let other = match half_of(first, raster.path) {
        dynamic::Half::Trace => dynamic::Half::Retrace,
        dynamic::Half::Retrace => dynamic::Half::Trace,
    };
    let mut other_half =
        if with_dynamics.is_some() && channels.iter().any(|c| half_of(c, raster.path) == other) {
            Some(map_of(other)?)
        } else {
            None
        };
    // The lattice ruler: the approach creep, drift and fast-axis terms from the first channel's
    // atoms; the other half, whose lines run the other way (its hysteresis mirrored), from the
    // atoms of its own first channel. Each removed along its own pixel times and places.
    let mut estimate = None;
    let mut dynamics_used = dynamics_used;
    if let (Some(ruler), Some(d), DynamicsUsed::Raster) =
        (options.ruler.as_ref(), with_dynamics, dynamics_used)
    {
        let law = d.creep.law().map_err(correction)?;
        let measure = |channel: &Channel, map: &CoordinateMap, times: &[f64]| {
            let heights = geometry_heights(file, channel)?;
            ruler::estimate_from_lattice(&heights, map, times, &law, ruler).map_err(|source| {
                ApplyError::Option {
                    option: "--ruler",
                    reason: format!(
                        "{} (channel {}): {source}",
                        file.source.display(),
                        channel.name()
                    ),
                }
            })
        };
        let times =
            dynamic::pixel_times(raster, half_of(first, raster.path)).map_err(correction)?;
        let found = measure(first, &map, &times)?;
        map = found.corrected(&map, &times).map_err(correction)?;
        if let Some((other_map, other_first)) = other_half.take() {
            let times = dynamic::pixel_times(raster, other).map_err(correction)?;
            let channel = channels
                .iter()
                .find(|c| half_of(c, raster.path) == other)
                .ok_or_else(|| ApplyError::Channel {
                    file: file.source.clone(),
                    reason: "no channel of the other half".to_owned(),
                })?;
            let own = measure(channel, &other_map, &times)?;
            other_half = Some((
                own.corrected(&other_map, &times).map_err(correction)?,
                other_first,
            ));
        }
        dynamics_used = DynamicsUsed::RasterRuler;
        estimate = Some(found);
    }
    let mut pair = None;
    if options.counter.is_some() && !matches!(dynamics_used, DynamicsUsed::Raster) {
        return Err(ApplyError::Option {
            option: "--counter",
            reason: format!(
                "{}: a counter partner measures what the file-alone dynamics leave, but this \
                 correction is {}",
                file.source.display(),
                dynamics_used.describe()
            ),
        });
    }
    if let (Some(partner), Some(d), DynamicsUsed::Raster) =
        (options.counter.as_ref(), with_dynamics, dynamics_used)
    {
        let halves = [
            Some((half_of(first, raster.path), &mut map)),
            other_half.as_mut().map(|(m, _)| (other, m)),
        ];
        let found = with_counter_partner(file, options, field, raster, first, d, partner, halves)?;
        dynamics_used = DynamicsUsed::RasterCounter;
        pair = Some(found);
    }
    Ok(Maps {
        map,
        first_nm,
        other_half,
        dynamics_used,
        ruler: estimate,
        counter: pair,
    })
}

/// `spmcal correct --counter`: the drift and the odd part of the approach creep measured
/// between the image and its counter-scanned partner ([`counter`]) on the trace halves of the
/// first channel's name, and removed from each map of `halves` along its own pixel times. When
/// the partner came first, this image's maps are replayed after the partner's raster.
#[allow(clippy::too_many_arguments)]
fn with_counter_partner<F: CorrectionField + Sync>(
    file: &SpmFile,
    options: &ApplyOptions,
    field: &F,
    raster: &FileRaster,
    first: &Channel,
    dynamics: &spm_correction::hysteresis::ScannerDynamics,
    partner: &CounterPartner,
    halves: [Option<(dynamic::Half, &mut CoordinateMap)>; 2],
) -> Result<counter::PairEstimate, ApplyError> {
    let refuse = |reason: String| ApplyError::Option {
        option: "--counter",
        reason: format!("{}: {reason}", partner.file.source.display()),
    };
    let correction = |source: CorrectionError| ApplyError::Correction {
        file: file.source.clone(),
        channel: "map".to_owned(),
        source,
    };
    fn trace_channel<'f>(f: &'f SpmFile, name: &str, path: RasterPath) -> Option<&'f Channel> {
        f.channels
            .iter()
            .find(|c| c.name() == name && half_of(c, path) == dynamic::Half::Trace)
    }
    let own = trace_channel(file, first.name(), raster.path).ok_or_else(|| {
        refuse(format!(
            "{} has no trace channel {}",
            file.source.display(),
            first.name()
        ))
    })?;
    let probe = partner
        .file
        .channels
        .iter()
        .find(|c| c.name() == first.name())
        .ok_or_else(|| refuse(format!("no channel {}", first.name())))?;
    let partner_raster = FileRaster::of(&partner.file, probe, options.nominal_nm_per_count, None)?;
    let theirs = trace_channel(&partner.file, first.name(), partner_raster.path)
        .ok_or_else(|| refuse(format!("no trace channel {}", first.name())))?;
    if (partner_raster.columns, partner_raster.rows) != (raster.columns, raster.rows) {
        return Err(refuse(format!(
            "{} × {} pixels, the image {} × {}: not a counter-scanned partner",
            partner_raster.columns, partner_raster.rows, raster.columns, raster.rows
        )));
    }
    let frame_s = |r: &FileRaster| r.line_time_s.map(|t| 2.0 * t * r.rows as f64);
    let delay_s = match (partner.delay_s, file.recorded, partner.file.recorded) {
        (Some(d), _, _) => d,
        (None, Some(a), Some(b)) => {
            let d = (b.unix_seconds() - a.unix_seconds()) as f64;
            if d >= 0.0 {
                d.max(frame_s(raster).unwrap_or(0.0))
            } else {
                -(-d).max(frame_s(&partner_raster).unwrap_or(0.0))
            }
        }
        _ => {
            return Err(refuse(
                "the files carry no time stamps; give the time from the image's first line to \
                 the partner's (--counter-delay)"
                    .to_owned(),
            ));
        }
    };
    // The pair's clock starts at the earlier frame's first pixel; the later frame is replayed
    // after the earlier one's raster.
    let own_heights = geometry_heights(file, own)?;
    let partner_heights = geometry_heights(&partner.file, theirs)?;
    let own_file = counter::PairFile {
        raster,
        heights: &own_heights,
    };
    let partner_file = counter::PairFile {
        raster: &partner_raster,
        heights: &partner_heights,
    };
    let (own_start, (earlier, later)) = if delay_s >= 0.0 {
        (0.0, (own_file, partner_file))
    } else {
        (-delay_s, (partner_file, own_file))
    };
    // The earlier frame's trace map along its own raster: this image's own when it came first
    // and its first channel is the trace half (already made), else made here.
    let own_trace = halves
        .iter()
        .flatten()
        .find(|(half, _)| *half == dynamic::Half::Trace)
        .map(|(_, m)| &**m)
        .filter(|_| own_start == 0.0);
    let made;
    let earlier_map = match own_trace {
        Some(m) => m,
        None => {
            made = dynamic::dynamic_map(field, earlier.raster, dynamics, dynamic::Half::Trace)
                .map_err(correction)?
                .0;
            &made
        }
    };
    let (found, _, _) = counter::pair_maps(
        field,
        dynamics,
        (earlier, earlier_map),
        later,
        delay_s.abs(),
        &partner.spacing,
    )
    .map_err(|e| refuse(e.to_string()))?;
    let shifted = |half: dynamic::Half| -> Result<Vec<f64>, ApplyError> {
        Ok(dynamic::pixel_times(raster, half)
            .map_err(correction)?
            .iter()
            .map(|t| t + own_start)
            .collect())
    };
    for (half, map) in halves.into_iter().flatten() {
        if own_start > 0.0 {
            *map = dynamic::dynamic_map_after(
                field,
                raster,
                dynamics,
                half,
                &partner_raster,
                own_start,
            )
            .map_err(correction)?
            .0;
        }
        let times = shifted(half)?;
        *map = found.corrected(map, &times).map_err(correction)?;
    }
    Ok(found)
}

/// A channel's values in scanner geometry (bottom row first), refused when none is finite.
fn geometry_heights(file: &SpmFile, channel: &Channel) -> Result<Vec<f64>, ApplyError> {
    let (nx, ny) = (channel.nx(), channel.ny());
    let mut heights = Vec::with_capacity(nx * ny);
    for row in (0..ny).rev() {
        heights.extend_from_slice(&channel.data()[row * nx..(row + 1) * nx]);
    }
    if !heights.iter().any(|v| v.is_finite()) {
        return Err(ApplyError::Channel {
            file: file.source.clone(),
            reason: format!(
                "channel {:?} ({}) holds no finite height or value (every pixel NaN or \
                 infinite)",
                channel.name(),
                channel.direction().as_str()
            ),
        });
    }
    Ok(heights)
}

/// The corrected channel on the output grid (display orientation), with its geometry.
fn output_channel(
    file: &SpmFile,
    channel: &Channel,
    grid: &OutputGrid,
    display: Vec<f64>,
    centre: [f64; 2],
    angle_ccw_rad: f64,
) -> Result<Channel, ApplyError> {
    let step_nm = grid.step_nm.value();
    let mut corrected = Channel::new(
        channel.name(),
        channel.direction(),
        channel.unit(),
        grid.columns,
        grid.rows,
        display,
    )
    .map_err(|e| ApplyError::Channel {
        file: file.source.clone(),
        reason: e.to_string(),
    })?
    .with_size_nm(step_nm * grid.columns as f64, step_nm * grid.rows as f64)
    .with_center_nm(centre[0], centre[1])
    .with_angle_deg(angle_ccw_rad.to_degrees());
    if let Some(dir) = channel.scan_dir().or(file.scan_dir) {
        corrected = corrected.with_scan_dir(dir);
    }
    Ok(corrected)
}

/// Corrects the selected channels of `file` with the calibration `set` (see the crate docs).
///
/// # Errors
/// Every [`ApplyError`]: the guard rails of [`check`], unusable geometry, and the correction's
/// own refusals.
pub fn correct_file(
    file: &SpmFile,
    set: &SurfaceSet,
    options: &ApplyOptions,
) -> Result<Corrected, ApplyError> {
    let channels = selected(file, &options.channels)?;
    let Some(first) = channels.first() else {
        return Err(ApplyError::Channel {
            file: file.source.clone(),
            reason: "the file holds no image channel".to_owned(),
        });
    };
    let (nx, ny) = (first.nx(), first.ny());
    if let Some(other) = channels.iter().find(|c| c.nx() != nx || c.ny() != ny) {
        return Err(ApplyError::Channel {
            file: file.source.clone(),
            reason: format!(
                "channel {:?} has {}×{} pixels, channel {:?} {nx}×{ny}: one map cannot correct both; \
                 choose one with --channel",
                other.name(),
                other.nx(),
                other.ny(),
                first.name()
            ),
        });
    }
    if nx < 2 || ny < 2 {
        return Err(ApplyError::Channel {
            file: file.source.clone(),
            reason: format!("{nx}×{ny} pixels: a raster to correct needs at least 2×2"),
        });
    }
    if let Some(z) = options.z_counts
        && !z.is_finite()
    {
        return Err(ApplyError::Option {
            option: "--z-counts",
            reason: format!("{z} must be a finite number"),
        });
    }
    let correction = |channel: &str, source: CorrectionError| ApplyError::Correction {
        file: file.source.clone(),
        channel: channel.to_owned(),
        source,
    };
    let raster = FileRaster::of(file, first, options.nominal_nm_per_count, options.path)?;
    let z = options.z_counts.unwrap_or(0.0);
    let plane = set.plane_nearest(z).map_err(|e| correction("map", e))?;
    let extrapolated_counts = check(file, set, plane, &raster, options)?;
    check_coefficients(file, plane, &raster)?;
    if options.z_counts.is_some() {
        let z = options.z_counts.unwrap_or(plane.z_counts);
        let (lower, upper, _) = set.bracketing_planes(z).map_err(|e| correction("map", e))?;
        check_coefficients(file, lower, &raster)?;
        check_coefficients(file, upper, &raster)?;
    }
    let field = field_at_z(
        set,
        options.z_counts.unwrap_or(plane.z_counts),
        Route::Products,
    )
    .map_err(|e| correction("map", e))?;
    let Maps {
        map,
        first_nm,
        other_half,
        dynamics_used,
        ruler,
        counter,
    } = maps_for(file, set, options, &field, &raster, &channels)?;
    let grid = OutputGrid::covering(&map, None).map_err(|e| correction("map", e))?;
    let step_nm = grid.step_nm.value();
    // The output grid's centre in the scanner's axes, from the field's origin.
    let (s, c) = raster.angle_ccw_rad.sin_cos();
    let gu = grid.origin_nm.x.value() + step_nm * (grid.columns as f64 - 1.0) / 2.0;
    let gv = grid.origin_nm.y.value() + step_nm * (grid.rows as f64 - 1.0) / 2.0;
    let centre = [first_nm[0] + gu * c - gv * s, first_nm[1] + gu * s + gv * c];
    let mut out = Vec::with_capacity(channels.len());
    let mut unknown_pixels = 0;
    for (i, channel) in channels.iter().enumerate() {
        let heights = geometry_heights(file, channel)?;
        // The other half's map, expressed in this one's frame (both from the field's origin).
        let shifted;
        let channel_map = match &other_half {
            Some((other, other_first))
                if half_of(channel, raster.path) != half_of(first, raster.path) =>
            {
                let (dx, dy) = (other_first[0] - first_nm[0], other_first[1] - first_nm[1]);
                let (du, dv) = (dx * c + dy * s, -dx * s + dy * c);
                shifted = dynamic::translated(other, du, dv)
                    .map_err(|e| correction(channel.name(), e))?;
                &shifted
            }
            _ => &map,
        };
        let resampled = resample(
            &heights,
            channel_map,
            &grid,
            options.interpolation,
            Parallelism::AllCores,
        )
        .map_err(|e| correction(channel.name(), e))?;
        let mut display = Vec::with_capacity(resampled.len());
        for row in (0..grid.rows).rev() {
            display.extend_from_slice(&resampled[row * grid.columns..(row + 1) * grid.columns]);
        }
        if i == 0 {
            unknown_pixels = display.iter().filter(|v| !v.is_finite()).count();
        }
        out.push(output_channel(
            file,
            channel,
            &grid,
            display,
            centre,
            raster.angle_ccw_rad,
        )?);
    }
    let expected = expected_error_nm(plane, &raster);
    let metadata = metadata(
        file,
        set,
        plane,
        &raster,
        &Facts {
            expected_error_nm: expected,
            extrapolated_counts,
            unknown_pixels,
            dynamics: dynamics_used,
            ruler: ruler.clone(),
            counter: counter.clone(),
        },
    );
    Ok(Corrected {
        channels: out,
        metadata,
        raster,
        unknown_pixels,
        extrapolated_counts,
        dynamics: dynamics_used,
        ruler,
        counter,
        expected_error_nm: expected,
        step_nm,
    })
}

/// What a correction found, for its output's metadata.
struct Facts {
    expected_error_nm: f64,
    extrapolated_counts: Option<f64>,
    unknown_pixels: usize,
    dynamics: DynamicsUsed,
    ruler: Option<ruler::RulerEstimate>,
    counter: Option<counter::PairEstimate>,
}

fn metadata(
    file: &SpmFile,
    set: &SurfaceSet,
    plane: &PlaneSurfaces,
    raster: &FileRaster,
    facts: &Facts,
) -> Vec<(String, String)> {
    let Facts {
        expected_error_nm,
        extrapolated_counts,
        unknown_pixels,
        dynamics,
        ref ruler,
        ref counter,
    } = *facts;
    let p = &set.provenance;
    let region = plane.calibrated_region();
    let mut m: Vec<(String, String)> = vec![
        (KEY_CORRECTED.into(), "yes".into()),
        (
            "spmcal_corrector_version".into(),
            env!("CARGO_PKG_VERSION").into(),
        ),
        (
            "spmcal_source_file".into(),
            file.source.display().to_string(),
        ),
        ("spmcal_source_format".into(), file.format.id().into()),
        ("spmcal_calibration_scanner_id".into(), p.scanner_id.clone()),
        (
            "spmcal_calibration_format_version".into(),
            set.format_version.to_string(),
        ),
        ("spmcal_calibration_records".into(), p.n_records.to_string()),
        (
            "spmcal_calibration_records_sha256".into(),
            p.records_sha256.clone().unwrap_or_else(|| "unknown".into()),
        ),
        (
            "spmcal_calibration_written_utc".into(),
            p.written_utc.clone().unwrap_or_else(|| "unknown".into()),
        ),
        (
            "spmcal_calibration_fit_window".into(),
            format!(
                "{} .. {}",
                p.fit_since.as_deref().unwrap_or("first record"),
                p.fit_until.as_deref().unwrap_or("last record")
            ),
        ),
        (
            "spmcal_calibration_spmcal".into(),
            format!(
                "{} ({})",
                p.spmcal_version.as_deref().unwrap_or("unknown version"),
                p.spmcal_commit.as_deref().unwrap_or("unknown commit")
            ),
        ),
        ("spmcal_plane_z_counts".into(), plane.z_counts.to_string()),
        (
            "spmcal_calibrated_region_counts".into(),
            format!(
                "x {} .. {}, y {} .. {}",
                region.x_min_counts, region.x_max_counts, region.y_min_counts, region.y_max_counts
            ),
        ),
        (
            "spmcal_counts_source".into(),
            match &raster.counts {
                CountsSource::Recorded => "recorded in the file".into(),
                CountsSource::Nominal {
                    nm_per_count,
                    field,
                } => format!("nominal {nm_per_count} nm/count ({field})"),
            },
        ),
        (
            "spmcal_raster_centre_counts".into(),
            format!("{} {}", raster.centre.x.value(), raster.centre.y.value()),
        ),
        (
            "spmcal_raster_step_counts".into(),
            format!("{} {}", raster.step_x_counts, raster.step_y_counts),
        ),
        (
            spm_formats::KEY_SCAN_ANGLE_CCW_DEG.into(),
            raster.angle_ccw_rad.to_degrees().to_string(),
        ),
        (
            "spmcal_raster_path".into(),
            match raster.path {
                RasterPath::Trace(ScanDir::Up) => "lines +x, slow axis up".into(),
                RasterPath::Trace(ScanDir::Down) => "lines +x, slow axis down".into(),
                RasterPath::Counter => "counter scan: lines -x, slow axis down".into(),
            },
        ),
        ("spmcal_dynamics".into(), dynamics.describe().into()),
        (
            "spmcal_expected_error_nm".into(),
            format!("{expected_error_nm:.6}"),
        ),
    ];
    if let Some(r) = ruler {
        m.extend(ruler_fields(r));
    }
    if let Some(c) = counter {
        m.extend(counter_fields(c));
    }
    m.extend(vec![
        (
            "spmcal_expected_error_basis".into(),
            "1 sigma of the static surfaces (standard errors of K̄x, K̄yy, α over the image side); \
             dynamics excluded"
                .into(),
        ),
        (
            "spmcal_unknown_pixels".into(),
            format!("{unknown_pixels} (NaN: outside the scanned area or without data)"),
        ),
        (
            "spmcal_extrapolated".into(),
            match extrapolated_counts {
                Some(d) => format!(
                    "yes: the image reaches {d:.0} counts beyond the calibrated region \
                     (--allow-extrapolation)"
                ),
                None => "no".into(),
            },
        ),
    ]);
    m.extend(source_header(file));
    m
}

/// The source's date and header as output fields (keys prefixed `source_`, made identifiers):
/// kept, but no longer read as the output's own.
pub(crate) fn source_header(file: &SpmFile) -> Vec<(String, String)> {
    let mut m = Vec::with_capacity(file.header.len() + 1);
    if let Some(date) = file.recorded {
        m.push(("spmcal_source_recorded".into(), date.to_string()));
    }
    for (key, value) in &file.header {
        m.push((source_key(key), value.replace(['\n', '\r', '\0'], " ")));
    }
    m
}

/// The counter partner's estimate as output metadata.
fn counter_fields(c: &counter::PairEstimate) -> [(String, String); 4] {
    [
        (
            "spmcal_counter_drift_nm_per_s".to_owned(),
            format!("{:.6} {:.6}", c.drift_nm_per_s[0], c.drift_nm_per_s[1]),
        ),
        (
            "spmcal_counter_cubic_nm_per_s3".to_owned(),
            format!("{:.3e} {:.3e}", c.cubic_nm_per_s3[0], c.cubic_nm_per_s3[1]),
        ),
        (
            "spmcal_counter_matched".to_owned(),
            format!("{} of {} and {}", c.matched, c.features[0], c.features[1]),
        ),
        (
            "spmcal_counter_residual_nm".to_owned(),
            format!("{:.4}", c.residual_rms_nm),
        ),
    ]
}

/// The lattice ruler's estimate as output metadata.
fn ruler_fields(r: &ruler::RulerEstimate) -> [(String, String); 6] {
    [
        (
            "spmcal_ruler_approach_amplitude_nm".to_owned(),
            format!("{:.6} {:.6}", r.amplitude_nm[0], r.amplitude_nm[1]),
        ),
        (
            "spmcal_ruler_since_move_s".to_owned(),
            format!("{:.4}", r.since_move_s),
        ),
        (
            "spmcal_ruler_drift_nm_per_s".to_owned(),
            format!("{:.6e} {:.6e}", r.drift_nm_per_s[0], r.drift_nm_per_s[1]),
        ),
        (
            "spmcal_ruler_fast_axis_nm".to_owned(),
            format!(
                "x·u {:.6} x·u² {:.6} x·u³ {:.6} y·u² {:.6} y·u³ {:.6} (u along the line, -1/2..1/2)",
                r.fast_axis_nm[0],
                r.fast_axis_nm[1],
                r.fast_axis_nm[2],
                r.fast_axis_nm[3],
                r.fast_axis_nm[4]
            ),
        ),
        (
            "spmcal_ruler_atoms".to_owned(),
            format!("{} located, {} indexed", r.atoms, r.indexed),
        ),
        (
            "spmcal_ruler_lattice_rms_nm".to_owned(),
            format!(
                "{:.6} before, {:.6} after",
                r.before_rms_nm, r.residual_rms_nm
            ),
        ),
    ]
}

/// The output file kinds spmcal writes, from an output name's extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutputKind {
    /// Gwyddion Simple Field: one channel per file.
    Gsf,
    /// Gwyddion native: every channel and the metadata in one file.
    Gwy,
}

impl OutputKind {
    /// The kind an output path names by its extension.
    ///
    /// # Errors
    /// [`ApplyError::Option`] naming the extension and the ones spmcal writes.
    pub fn of_path(path: &Path) -> Result<Self, ApplyError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match ext.as_deref() {
            Some("gsf") => Ok(Self::Gsf),
            Some("gwy") => Ok(Self::Gwy),
            other => Err(ApplyError::Option {
                option: "--out",
                reason: format!(
                    "{}: spmcal cannot write {} files; name the output .gsf (one channel per \
                     file) or .gwy (every channel and the metadata)",
                    path.display(),
                    match other {
                        Some(e) => format!(".{e}"),
                        None => "extension-less".to_owned(),
                    }
                ),
            }),
        }
    }
}

#[cfg(test)]
mod tests;
