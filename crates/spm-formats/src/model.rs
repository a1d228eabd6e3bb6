//! The data model every reader produces.

use std::fmt;
use std::path::PathBuf;

use serde::Serialize;

use crate::error::{Ctx, Result};

/// The file formats this crate knows. Serialises as its [`Format::id`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Format {
    /// Nanonis `.sxm` scan file.
    NanonisSxm,
    /// RHK Technology `.sm4` file.
    RhkSm4,
    /// ISO 28600:2011 SPM data transfer format (text).
    Iso28600,
    /// Raw: two little-endian u32 (rows, cols), then rows·cols little-endian f64 metres.
    RawF64,
    /// Gwyddion Simple Field `.gsf`.
    Gsf,
    /// Gwyddion native file `.gwy`.
    Gwy,
}

impl Format {
    /// A short stable identifier (`"nanonis-sxm"`, `"rhk-sm4"`, `"iso28600"`, `"raw-f64"`, `"gsf"`,
    /// `"gwy"`).
    pub fn id(self) -> &'static str {
        match self {
            Format::NanonisSxm => "nanonis-sxm",
            Format::RhkSm4 => "rhk-sm4",
            Format::Iso28600 => "iso28600",
            Format::RawF64 => "raw-f64",
            Format::Gsf => "gsf",
            Format::Gwy => "gwy",
        }
    }
}

impl Serialize for Format {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(self.id())
    }
}

impl fmt::Display for Format {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.id())
    }
}

/// Fast-axis direction of a channel: trace (forward) or retrace (backward).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Direction {
    /// Trace: the probe moves towards +x (left to right in the display).
    Forward,
    /// Retrace: the probe moves towards −x (right to left in the display).
    Backward,
}

impl Direction {
    /// `"forward"` or `"backward"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Direction::Forward => "forward",
            Direction::Backward => "backward",
        }
    }
}

impl fmt::Display for Direction {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Slow-axis direction: where the first acquired line lies in the display.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ScanDir {
    /// The first line is the bottom line; the scan moves up.
    Up,
    /// The first line is the top line; the scan moves down.
    Down,
}

impl ScanDir {
    /// `"up"` or `"down"`.
    pub fn as_str(self) -> &'static str {
        match self {
            ScanDir::Up => "up",
            ScanDir::Down => "down",
        }
    }
}

impl fmt::Display for ScanDir {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A calendar date and wall-clock time as recorded by the instrument (no time zone).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct DateTime {
    /// Year, e.g. 2016.
    pub year: i32,
    /// Month 1–12.
    pub month: u8,
    /// Day of month 1–31.
    pub day: u8,
    /// Hour 0–23.
    pub hour: u8,
    /// Minute 0–59.
    pub minute: u8,
    /// Second 0–60.
    pub second: u8,
}

impl DateTime {
    /// Builds a date-time, checking the ranges (not the month lengths beyond 31).
    pub fn new(year: i32, month: u8, day: u8, hour: u8, minute: u8, second: u8) -> Option<Self> {
        let ok = (1..=12).contains(&month)
            && (1..=31).contains(&day)
            && hour < 24
            && minute < 60
            && second <= 60;
        ok.then_some(Self {
            year,
            month,
            day,
            hour,
            minute,
            second,
        })
    }

    /// The UTC date-time `seconds` after 1970-01-01T00:00:00 (proleptic Gregorian calendar,
    /// days to civil date after H. Hinnant's algorithm); `None` outside years ±2³¹.
    #[must_use]
    pub fn from_unix_seconds(seconds: i64) -> Option<Self> {
        let days = seconds.div_euclid(86_400);
        let of_day = seconds.rem_euclid(86_400);
        let z = days + 719_468;
        let era = z.div_euclid(146_097);
        let doe = z.rem_euclid(146_097);
        let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
        let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
        let mp = (5 * doy + 2) / 153;
        let day = doy - (153 * mp + 2) / 5 + 1;
        let month = if mp < 10 { mp + 3 } else { mp - 9 };
        let year = yoe + era * 400 + i64::from(month <= 2);
        Self::new(
            i32::try_from(year).ok()?,
            u8::try_from(month).ok()?,
            u8::try_from(day).ok()?,
            u8::try_from(of_day / 3600).ok()?,
            u8::try_from(of_day % 3600 / 60).ok()?,
            u8::try_from(of_day % 60).ok()?,
        )
    }

    /// Seconds after 1970-01-01T00:00:00 UTC of this date-time taken as UTC (the inverse of
    /// [`Self::from_unix_seconds`]: civil date to days after H. Hinnant's algorithm).
    #[must_use]
    pub fn unix_seconds(&self) -> i64 {
        let (y, m, d) = (
            i64::from(self.year),
            i64::from(self.month),
            i64::from(self.day),
        );
        let y = if m <= 2 { y - 1 } else { y };
        let era = if y >= 0 { y } else { y - 399 } / 400;
        let yoe = y - era * 400;
        let mp = (m + 9) % 12;
        let doy = (153 * mp + 2) / 5 + d - 1;
        let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
        let days = era * 146_097 + doe - 719_468;
        days * 86_400
            + i64::from(self.hour) * 3600
            + i64::from(self.minute) * 60
            + i64::from(self.second)
    }
}

impl fmt::Display for DateTime {
    /// ISO 8601 without zone: `2016-01-07T12:54:04`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{:04}-{:02}-{:02}T{:02}:{:02}:{:02}",
            self.year, self.month, self.day, self.hour, self.minute, self.second
        )
    }
}

impl Serialize for DateTime {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

/// When the lines of one channel were acquired, relative to the start of the frame.
///
/// Line `i` in acquisition order starts at `first_line_start_s + i·line_period_s`; its pixel `j`
/// (in acquisition order along the line) is taken at `start + j·line_time_s / nx`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LineTiming {
    /// Duration of one line of this channel (one trace or one retrace), s.
    pub line_time_s: f64,
    /// Time between the starts of consecutive lines (trace + retrace when both are recorded), s.
    pub line_period_s: f64,
    /// Start of the first line relative to the frame start, s (the trace time for a retrace).
    pub first_line_start_s: f64,
}

/// Pixels in a row-major 2-D array.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Pixels per row.
    pub nx: usize,
    /// Rows.
    pub ny: usize,
    /// `nx·ny` values, row-major.
    pub data: Vec<f64>,
}

impl Image {
    /// The value at `row`, `col`, or `None` outside the image.
    pub fn get(&self, row: usize, col: usize) -> Option<f64> {
        if row < self.ny && col < self.nx {
            self.data.get(row * self.nx + col).copied()
        } else {
            None
        }
    }

    /// One row, or `None` outside the image.
    pub fn row(&self, row: usize) -> Option<&[f64]> {
        let start = row.checked_mul(self.nx)?;
        self.data.get(start..start.checked_add(self.nx)?)
    }
}

/// One image channel of a file: a named quantity, one scan direction, one pixel grid.
///
/// The data are stored in **display orientation**: row 0 is the top line, column 0 the left
/// edge, x increasing to the right, y increasing upwards. Values are in the SI unit named by
/// [`Channel::unit`] (metres for heights, amperes for currents). [`Channel::acquisition_image`]
/// gives the same pixels in the order they were measured.
#[derive(Debug, Clone, PartialEq)]
pub struct Channel {
    name: String,
    direction: Direction,
    unit: String,
    nx: usize,
    ny: usize,
    data: Vec<f64>,
    size_x_nm: Option<f64>,
    size_y_nm: Option<f64>,
    center_x_nm: Option<f64>,
    center_y_nm: Option<f64>,
    angle_deg: Option<f64>,
    scan_dir: Option<ScanDir>,
    timing: Option<LineTiming>,
}

impl Channel {
    /// A channel from data in display orientation (row 0 = top, x increasing).
    ///
    /// Fails with [`crate::ErrorKind::InvalidInput`] when `data.len() != nx·ny` or the grid is
    /// empty. Geometry, scan direction and timing start unknown; set them with the `with_*`
    /// builders.
    pub fn new(
        name: impl Into<String>,
        direction: Direction,
        unit: impl Into<String>,
        nx: usize,
        ny: usize,
        data: Vec<f64>,
    ) -> Result<Self> {
        let name = name.into();
        if nx == 0 || ny == 0 || nx.checked_mul(ny) != Some(data.len()) {
            let placeholder = std::path::PathBuf::from(format!("<channel {name}>"));
            return Err(Ctx::new(&placeholder).invalid_input(format!(
                "{} values do not fill a {nx}×{ny} grid",
                data.len()
            )));
        }
        Ok(Self {
            name,
            direction,
            unit: unit.into(),
            nx,
            ny,
            data,
            size_x_nm: None,
            size_y_nm: None,
            center_x_nm: None,
            center_y_nm: None,
            angle_deg: None,
            scan_dir: None,
            timing: None,
        })
    }

    /// Sets the physical size of the frame, nm.
    pub fn with_size_nm(mut self, size_x_nm: f64, size_y_nm: f64) -> Self {
        self.size_x_nm = Some(size_x_nm);
        self.size_y_nm = Some(size_y_nm);
        self
    }

    /// Sets the frame centre in the instrument's coordinates, nm.
    pub fn with_center_nm(mut self, center_x_nm: f64, center_y_nm: f64) -> Self {
        self.center_x_nm = Some(center_x_nm);
        self.center_y_nm = Some(center_y_nm);
        self
    }

    /// Sets the scan rotation angle, degrees (as the instrument reports it).
    pub fn with_angle_deg(mut self, angle_deg: f64) -> Self {
        self.angle_deg = Some(angle_deg);
        self
    }

    /// Sets the slow-axis direction.
    pub fn with_scan_dir(mut self, scan_dir: ScanDir) -> Self {
        self.scan_dir = Some(scan_dir);
        self
    }

    /// Sets the line timing.
    pub fn with_timing(mut self, timing: LineTiming) -> Self {
        self.timing = Some(timing);
        self
    }

    /// The quantity's name as the file spells it ("Z", "Topography", "Current").
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Trace or retrace.
    pub fn direction(&self) -> Direction {
        self.direction
    }

    /// SI unit of the values ("m", "A", "V"), as the file names it.
    pub fn unit(&self) -> &str {
        &self.unit
    }

    /// Pixels per line.
    pub fn nx(&self) -> usize {
        self.nx
    }

    /// Lines.
    pub fn ny(&self) -> usize {
        self.ny
    }

    /// Physical width of the frame, nm (unknown for the raw format).
    pub fn size_x_nm(&self) -> Option<f64> {
        self.size_x_nm
    }

    /// Physical height of the frame, nm.
    pub fn size_y_nm(&self) -> Option<f64> {
        self.size_y_nm
    }

    /// Pixel pitch along x, nm.
    pub fn pixel_x_nm(&self) -> Option<f64> {
        self.size_x_nm.map(|s| s / self.nx as f64)
    }

    /// Pixel pitch along y, nm.
    pub fn pixel_y_nm(&self) -> Option<f64> {
        self.size_y_nm.map(|s| s / self.ny as f64)
    }

    /// Frame centre x in the instrument's coordinates, nm.
    pub fn center_x_nm(&self) -> Option<f64> {
        self.center_x_nm
    }

    /// Frame centre y in the instrument's coordinates, nm.
    pub fn center_y_nm(&self) -> Option<f64> {
        self.center_y_nm
    }

    /// Scan rotation angle, degrees.
    pub fn angle_deg(&self) -> Option<f64> {
        self.angle_deg
    }

    /// Slow-axis direction when the file says it.
    pub fn scan_dir(&self) -> Option<ScanDir> {
        self.scan_dir
    }

    /// Line timing when the file has it.
    pub fn timing(&self) -> Option<LineTiming> {
        self.timing
    }

    /// The values in display orientation, row-major (row 0 = top).
    pub fn data(&self) -> &[f64] {
        &self.data
    }

    /// Number of NaN values (Nanonis fills the unscanned part of an incomplete frame with NaN).
    pub fn nan_count(&self) -> usize {
        self.data.iter().filter(|v| v.is_nan()).count()
    }

    /// The value at display `row`, `col`.
    pub fn get(&self, row: usize, col: usize) -> Option<f64> {
        if row < self.ny && col < self.nx {
            self.data.get(row * self.nx + col).copied()
        } else {
            None
        }
    }

    /// A copy of the pixels in display orientation.
    pub fn display_image(&self) -> Image {
        Image {
            nx: self.nx,
            ny: self.ny,
            data: self.data.clone(),
        }
    }

    /// Whether acquisition order runs bottom-to-top in the display (scan up).
    fn rows_reversed(&self) -> bool {
        // Unknown slow direction: assume the first line is the top line.
        self.scan_dir == Some(ScanDir::Up)
    }

    /// The display position `(row, col)` of the pixel measured `acq_col`-th on the
    /// `acq_row`-th acquired line.
    pub fn display_index(&self, acq_row: usize, acq_col: usize) -> (usize, usize) {
        let row = if self.rows_reversed() {
            self.ny.saturating_sub(1 + acq_row)
        } else {
            acq_row
        };
        let col = match self.direction {
            Direction::Forward => acq_col,
            Direction::Backward => self.nx.saturating_sub(1 + acq_col),
        };
        (row, col)
    }

    /// The pixels in **acquisition order**: row 0 is the first line measured, and along each
    /// row the pixels are in time order (so a backward line runs from the right edge to the
    /// left edge of the display). Unknown slow direction is treated as scan down.
    pub fn acquisition_image(&self) -> Image {
        let mut data = Vec::with_capacity(self.data.len());
        for acq_row in 0..self.ny {
            let (row, _) = self.display_index(acq_row, 0);
            let line = &self.data[row * self.nx..(row + 1) * self.nx];
            match self.direction {
                Direction::Forward => data.extend_from_slice(line),
                Direction::Backward => data.extend(line.iter().rev()),
            }
        }
        Image {
            nx: self.nx,
            ny: self.ny,
            data,
        }
    }

    /// Start time of each line in acquisition order, s from the frame start (when known).
    pub fn line_start_times_s(&self) -> Option<Vec<f64>> {
        let t = self.timing?;
        Some(
            (0..self.ny)
                .map(|i| t.first_line_start_s + i as f64 * t.line_period_s)
                .collect(),
        )
    }

    /// Time of the pixel at acquisition position (`acq_row`, `acq_col`), s from the frame start.
    pub fn pixel_time_s(&self, acq_row: usize, acq_col: usize) -> Option<f64> {
        let t = self.timing?;
        Some(
            t.first_line_start_s
                + acq_row as f64 * t.line_period_s
                + acq_col as f64 * t.line_time_s / self.nx as f64,
        )
    }
}

/// One SPM file as read: its format, channels, timing and full header.
#[derive(Debug, Clone, PartialEq)]
pub struct SpmFile {
    /// Where it was read from (or the name given to an in-memory buffer).
    pub source: PathBuf,
    /// The detected format.
    pub format: Format,
    /// Image channels, in file order (for each quantity usually forward then backward).
    pub channels: Vec<Channel>,
    /// Every header entry, in file order, as text key/value pairs.
    pub header: Vec<(String, String)>,
    /// Slow-axis direction of the frame when the file says it.
    pub scan_dir: Option<ScanDir>,
    /// Duration of one forward line, s, when the file says it.
    pub line_time_s: Option<f64>,
    /// When the frame was recorded, when the file says it.
    pub recorded: Option<DateTime>,
}

impl SpmFile {
    /// The first channel with this name and direction.
    pub fn channel(&self, name: &str, direction: Direction) -> Option<&Channel> {
        self.channels
            .iter()
            .find(|c| c.name == name && c.direction == direction)
    }

    /// The first header value with this key.
    pub fn header_value(&self, key: &str) -> Option<&str> {
        self.header
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }

    /// `[nx, ny]` of the first channel.
    pub fn pixels(&self) -> Option<[usize; 2]> {
        self.channels.first().map(|c| [c.nx, c.ny])
    }

    /// `[x, y]` size in nm of the first channel, when known.
    pub fn size_nm(&self) -> Option<[f64; 2]> {
        let c = self.channels.first()?;
        Some([c.size_x_nm?, c.size_y_nm?])
    }

    /// The summary `spmcal info` prints (DESIGN §13).
    pub fn info(&self) -> Info {
        Info {
            file: self.source.display().to_string(),
            format: self.format.id().to_string(),
            channels: self
                .channels
                .iter()
                .map(|c| ChannelInfo {
                    name: c.name.clone(),
                    direction: c.direction.as_str().to_string(),
                    unit: c.unit.clone(),
                    nan_count: c.nan_count(),
                })
                .collect(),
            pixels: self.pixels(),
            size_nm: self.size_nm(),
            scan_dir: self.scan_dir.map(|d| d.as_str().to_string()),
            line_time_s: self.line_time_s,
            recorded: self.recorded.map(|d| d.to_string()),
            header: self.header.clone(),
        }
    }
}

/// One channel in [`Info`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ChannelInfo {
    /// Quantity name.
    pub name: String,
    /// `"forward"` or `"backward"`.
    pub direction: String,
    /// SI unit of the values.
    pub unit: String,
    /// NaN pixels (unscanned part of an incomplete frame).
    pub nan_count: usize,
}

/// What `spmcal info FILE --json` prints; the keys follow DESIGN §13.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Info {
    /// The file.
    pub file: String,
    /// Format identifier, see [`Format::id`].
    pub format: String,
    /// Channels with name, direction, unit.
    pub channels: Vec<ChannelInfo>,
    /// `[nx, ny]`.
    pub pixels: Option<[usize; 2]>,
    /// `[x, y]` in nm (null when the file does not store it).
    pub size_nm: Option<[f64; 2]>,
    /// `"up"` / `"down"` when known.
    pub scan_dir: Option<String>,
    /// Seconds per forward line when known.
    pub line_time_s: Option<f64>,
    /// ISO 8601 record date-time when known.
    pub recorded: Option<String>,
    /// The full header as `[key, value]` pairs in file order.
    pub header: Vec<(String, String)>,
}

#[cfg(test)]
mod tests {
    use super::DateTime;

    /// Unix seconds against dates computed by hand (`date -u -d @N`).
    #[test]
    fn unix_seconds_become_civil_dates() {
        let check = |secs: i64, want: (i32, u8, u8, u8, u8, u8)| {
            let d = DateTime::from_unix_seconds(secs)
                .map(|d| (d.year, d.month, d.day, d.hour, d.minute, d.second));
            assert_eq!(d, Some(want), "{secs}");
        };
        check(0, (1970, 1, 1, 0, 0, 0));
        check(951_782_400, (2000, 2, 29, 0, 0, 0)); // a leap day of a 400-year leap year
        check(1_795_000_000, (2026, 11, 18, 11, 6, 40));
        check(-1, (1969, 12, 31, 23, 59, 59));
        check(4_107_542_399, (2100, 2, 28, 23, 59, 59)); // 2100 is no leap year
        check(4_107_542_400, (2100, 3, 1, 0, 0, 0));
    }

    /// The inverse: the same hand-computed instants back to Unix seconds, and a round trip
    /// over every day of four centuries (leap years and the century rule).
    #[test]
    fn civil_dates_become_unix_seconds() {
        for (secs, (y, mo, d, h, mi, s)) in [
            (0, (1970, 1, 1, 0, 0, 0)),
            (951_782_400, (2000, 2, 29, 0, 0, 0)),
            (1_795_000_000, (2026, 11, 18, 11, 6, 40)),
            (-1, (1969, 12, 31, 23, 59, 59)),
            (4_107_542_399, (2100, 2, 28, 23, 59, 59)),
            (4_107_542_400, (2100, 3, 1, 0, 0, 0)),
        ] {
            let date = DateTime::new(y, mo, d, h, mi, s).expect("valid");
            assert_eq!(date.unix_seconds(), secs, "{date}");
        }
        for day in -73_000..73_000_i64 {
            let secs = day * 86_400 + 3_723;
            let date = DateTime::from_unix_seconds(secs).expect("in range");
            assert_eq!(date.unix_seconds(), secs, "{date}");
        }
    }
}
