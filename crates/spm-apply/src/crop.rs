//! A rectangular part of an image file, every channel, with its geometry carried over: the
//! frame centre moved to the part's centre (along the scan angle), the size and the line
//! timing of the part, the slow direction and the source header kept.
//!
//! What it is for: a held-out part of one image (calibrate in virtual mode on the left half,
//! correct the right half and measure its lattice), or leaving out a step or a defect. The
//! part is written by `spmcal crop` as `.gsf` or `.gwy`, whose readers take the scan angle
//! counter-clockwise ([`crate::angle_ccw_deg`]); the part's angle is written that way, so a
//! cropped `.sxm` keeps its raster.

use crate::{ApplyError, angle_ccw_deg};
use spm_formats::{Channel, Direction, LineTiming, ScanDir, SpmFile};
use std::ops::Range;

/// Header key: which part of which file this is.
pub const KEY_CROP: &str = "spmcal_crop";

/// The part of a file: its channels (display orientation) and the header for its output.
#[derive(Debug, Clone)]
pub struct Cropped {
    /// Every channel of the file, cut to the part.
    pub channels: Vec<Channel>,
    /// The source header (keys prefixed `source_`, made identifiers) and what was cut.
    pub metadata: Vec<(String, String)>,
}

/// Display columns `columns` (0 = left) and display rows `rows` (0 = top) of every channel of
/// `file`.
///
/// # Errors
/// [`ApplyError::Option`] for an empty part or one leaving the image (naming `--columns` or
/// `--rows`), [`ApplyError::Channel`] for a file without channels or with channels of
/// different sizes.
pub fn crop_file(
    file: &SpmFile,
    columns: Range<usize>,
    rows: Range<usize>,
) -> Result<Cropped, ApplyError> {
    let Some(first) = file.channels.first() else {
        return Err(ApplyError::Channel {
            file: file.source.clone(),
            reason: "the file holds no image channel".to_owned(),
        });
    };
    let (nx, ny) = (first.nx(), first.ny());
    check_range("--columns", &columns, nx, file)?;
    check_range("--rows", &rows, ny, file)?;
    let mut channels = Vec::with_capacity(file.channels.len());
    for channel in &file.channels {
        if (channel.nx(), channel.ny()) != (nx, ny) {
            return Err(ApplyError::Channel {
                file: file.source.clone(),
                reason: format!(
                    "channel {:?} has {}×{} pixels, channel {:?} {nx}×{ny}: one part cannot cut both",
                    channel.name(),
                    channel.nx(),
                    channel.ny(),
                    first.name()
                ),
            });
        }
        channels.push(crop_channel(file, channel, &columns, &rows)?);
    }
    let mut metadata = vec![(
        KEY_CROP.to_owned(),
        format!(
            "display columns {}..{} and rows {}..{} (row 0 at the top) of the {nx}×{ny} image {}",
            columns.start,
            columns.end,
            rows.start,
            rows.end,
            file.source.display()
        ),
    )];
    if let Some(t) = first.timing() {
        metadata.push((
            crate::KEY_LINE_TIME.to_owned(),
            format!("{}", t.line_time_s * columns.len() as f64 / nx as f64),
        ));
    }
    if first.angle_deg().is_some() {
        metadata.push((
            spm_formats::KEY_SCAN_ANGLE_CCW_DEG.to_owned(),
            format!("{}", angle_ccw_deg(file.format, first)),
        ));
    }
    if let Some(dir) = first.scan_dir().or(file.scan_dir) {
        let path = match dir {
            ScanDir::Down => "down",
            ScanDir::Up => "direct",
        };
        metadata.push((crate::KEY_SCAN_PATH.to_owned(), path.to_owned()));
    }
    // What spmcal's own files say of their raster and calibration holds for the part too (a
    // corrected file's part is still corrected); the recorded counts move with the part.
    for key in [
        crate::KEY_CORRECTED,
        crate::KEY_SCANNER,
        crate::KEY_CONVENTION,
        crate::KEY_NOMINAL,
        crate::KEY_STEP,
    ] {
        if let Some(value) = file.header_value(key) {
            metadata.push((key.to_owned(), value.trim().to_owned()));
        }
    }
    let number = |key: &str| {
        file.header_value(key)
            .and_then(|v| v.trim().parse::<f64>().ok())
    };
    if let (Some(x0), Some(y0), Some(step)) = (
        number(crate::KEY_ORIGIN_X),
        number(crate::KEY_ORIGIN_Y),
        number(crate::KEY_STEP),
    ) {
        // The origin is the bottom-left pixel's count; the part's bottom row is display row
        // `rows.end − 1`, `ny − rows.end` rows above the frame's.
        metadata.push((
            crate::KEY_ORIGIN_X.to_owned(),
            format!("{}", x0 + columns.start as f64 * step),
        ));
        metadata.push((
            crate::KEY_ORIGIN_Y.to_owned(),
            format!("{}", y0 + (ny - rows.end) as f64 * step),
        ));
    }
    metadata.extend(crate::source_header(file));
    Ok(Cropped { channels, metadata })
}

fn check_range(
    option: &'static str,
    range: &Range<usize>,
    n: usize,
    file: &SpmFile,
) -> Result<(), ApplyError> {
    if range.end > n || range.len() < 2 {
        return Err(ApplyError::Option {
            option,
            reason: format!(
                "{}..{} is not a part of at least 2 of the {n} pixels of {} (0..{n} is the whole)",
                range.start,
                range.end,
                file.source.display()
            ),
        });
    }
    Ok(())
}

fn crop_channel(
    file: &SpmFile,
    channel: &Channel,
    columns: &Range<usize>,
    rows: &Range<usize>,
) -> Result<Channel, ApplyError> {
    let (nx, ny) = (channel.nx(), channel.ny());
    let (w, h) = (columns.len(), rows.len());
    let mut data = Vec::with_capacity(w * h);
    for row in rows.clone() {
        data.extend_from_slice(&channel.data()[row * nx + columns.start..row * nx + columns.end]);
    }
    let mut part = Channel::new(
        channel.name(),
        channel.direction(),
        channel.unit(),
        w,
        h,
        data,
    )
    .map_err(|e| ApplyError::Channel {
        file: file.source.clone(),
        reason: e.to_string(),
    })?;
    let angle_ccw_deg = angle_ccw_deg(file.format, channel);
    if let (Some(px), Some(py)) = (channel.pixel_x_nm(), channel.pixel_y_nm()) {
        part = part.with_size_nm(px * w as f64, py * h as f64);
        // The part's centre from the frame's, in the frame's axes (u right, v up), then
        // turned by the scan angle into the instrument's.
        let u = (columns.start as f64 + 0.5 * w as f64 - 0.5 * nx as f64) * px;
        let v = (0.5 * ny as f64 - rows.start as f64 - 0.5 * h as f64) * py;
        let (s, c) = angle_ccw_deg.to_radians().sin_cos();
        let (cx, cy) = (
            channel.center_x_nm().unwrap_or(0.0),
            channel.center_y_nm().unwrap_or(0.0),
        );
        part = part.with_center_nm(cx + u * c - v * s, cy + u * s + v * c);
    }
    if channel.angle_deg().is_some() {
        part = part.with_angle_deg(angle_ccw_deg);
    }
    let dir = channel.scan_dir().or(file.scan_dir);
    if let Some(dir) = dir {
        part = part.with_scan_dir(dir);
    }
    if let Some(t) = channel.timing() {
        // The part's first pixel in time: its first line in acquisition order (the top one
        // scanning down, the bottom one scanning up), its first pixel along that line (the
        // left one forward, the right one backward).
        let first_line = match dir {
            Some(ScanDir::Up) => ny - rows.end,
            _ => rows.start,
        };
        let first_pixel = match channel.direction() {
            Direction::Forward => columns.start,
            Direction::Backward => nx - columns.end,
        };
        part = part.with_timing(LineTiming {
            line_time_s: t.line_time_s * w as f64 / nx as f64,
            line_period_s: t.line_period_s,
            first_line_start_s: t.first_line_start_s
                + first_line as f64 * t.line_period_s
                + first_pixel as f64 * t.line_time_s / nx as f64,
        });
    }
    Ok(part)
}
