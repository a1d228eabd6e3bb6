//! ISO 28600:2011 SPM data transfer format reader (text).
//!
//! The header is a fixed sequence of 128 lines whose meaning is given by their line number in
//! the norm (line 1 the magic `ISO/TC 201 SPM data transfer format`, line 8 the experiment
//! mode, 20–23 fast/slow axes and directions, 24–25 the pixel counts, 26–29 the lateral units
//! and fields of view, 69–70 the single channel's name and unit, 94–118 the channels of a
//! multi-channel map, 128 `end of header`). The data follow as decimal numbers, one point per
//! line (the channels of a multi-channel map comma-separated on the line), fast axis first,
//! then `end of experiment`. Only regular mappings (`MAP_SC`, `MAP_MC`) are read.

use std::path::Path;

use crate::error::{Ctx, Result};
use crate::model::{Channel, DateTime, Direction, Format, ScanDir, SpmFile};
use crate::text::{length_unit_to_nm, parse_f64, parse_u64, to_si, utf8};

/// The magic first line.
pub(crate) const MAGIC: &str = "ISO/TC 201 SPM data transfer format";
const END_HEADER: &str = "end of header";
const END_DATA: &str = "end of experiment";
const MAX_CHANNELS: usize = 8;

/// Names of the header lines this reader interprets (1-based line numbers of the norm).
const NAMED_LINES: &[(usize, &str)] = &[
    (3, "Institution identifier"),
    (4, "Instrument model identifier"),
    (5, "Operator identifier"),
    (6, "Experiment identifier"),
    (7, "Comment"),
    (8, "Experiment mode"),
    (9, "Year"),
    (10, "Month"),
    (11, "Day"),
    (12, "Hours"),
    (13, "Minutes"),
    (14, "Seconds"),
    (15, "Hours ahead of GMT"),
    (17, "Scan mode"),
    (18, "Scanning system"),
    (19, "Scanner type"),
    (20, "Fast scan axis"),
    (21, "Fast scan direction"),
    (22, "Slow scan axis"),
    (23, "Slow scan direction"),
    (24, "Number of X points"),
    (25, "Number of Y points"),
    (26, "X unit"),
    (27, "Y unit"),
    (28, "Field of view X"),
    (29, "Field of view Y"),
    (30, "X offset unit"),
    (31, "Y offset unit"),
    (32, "X offset"),
    (33, "Y offset"),
    (34, "Rotation angle"),
    (35, "Scan speed unit"),
    (36, "Scan speed"),
    (37, "Scan rate unit"),
    (38, "Scan rate"),
    (39, "SPM technique"),
    (40, "Bias voltage contact"),
    (41, "Bias voltage"),
    (50, "Sample temperature"),
    (51, "Surroundings pressure"),
    (52, "Environment humidity"),
    (65, "Sample identifier"),
    (69, "Z axis channel"),
    (70, "Z axis channel unit"),
    (88, "Data treatment"),
    (94, "Number of data channels"),
];

/// Reads an ISO 28600 file.
pub fn read_iso28600(path: impl AsRef<Path>) -> Result<SpmFile> {
    let path = path.as_ref();
    let bytes = crate::read_file(path)?;
    parse(&bytes, path)
}

fn line_name(n: usize) -> String {
    match NAMED_LINES.iter().find(|(k, _)| *k == n) {
        Some((_, name)) => format!("{n:03} {name}"),
        None => format!("{n:03}"),
    }
}

/// The header lines up to "end of header" (without it) and the byte offset of the data.
fn header_lines<'a>(ctx: Ctx<'_>, bytes: &'a [u8]) -> Result<(Vec<&'a str>, usize)> {
    let mut lines: Vec<&str> = Vec::new();
    let mut pos = 0usize;
    let mut data_start = None;
    while pos < bytes.len() {
        let end = bytes[pos..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(bytes.len(), |k| pos + k);
        let line = utf8(
            ctx,
            &bytes[pos..end],
            &format!("header line {}", lines.len() + 1),
            pos,
        )?;
        let line = line.trim_end_matches('\r');
        pos = end.saturating_add(1).min(bytes.len());
        if line.trim() == END_HEADER {
            data_start = Some(pos);
            break;
        }
        lines.push(line);
        if lines.len() > 1000 {
            return Err(ctx.invalid("header", "no \"end of header\" line within 1000 lines"));
        }
    }
    let data_start =
        data_start.ok_or_else(|| ctx.truncated("header (\"end of header\")", 0, 0, bytes.len()))?;
    Ok((lines, data_start))
}

/// The data lines after the header: `n` points of `channels_n` comma-separated values each.
fn data_values(
    ctx: Ctx<'_>,
    bytes: &[u8],
    data_start: usize,
    header_lines: usize,
    n: usize,
    channels_n: usize,
) -> Result<Vec<Vec<f64>>> {
    let mut values: Vec<Vec<f64>> = vec![Vec::with_capacity(n); channels_n];
    let mut line_no = header_lines + 1;
    let mut point = 0usize;
    let text = utf8(ctx, &bytes[data_start..], "data", data_start)?;
    for line in text.lines() {
        line_no += 1;
        let t = line.trim();
        if t.is_empty() {
            continue;
        }
        if t == END_DATA {
            break;
        }
        if point >= n {
            return Err(ctx.invalid_data(
                data_start,
                format!("line {line_no}: more than {n} data points"),
            ));
        }
        let mut cells = t.split(',');
        for (c, ch_values) in values.iter_mut().enumerate() {
            let cell = cells.next().ok_or_else(|| {
                ctx.invalid_data(
                    data_start,
                    format!("line {line_no}: missing value of channel {}", c + 1),
                )
            })?;
            let v: f64 = cell.trim().parse().map_err(|_| {
                ctx.invalid_data(
                    data_start,
                    format!("line {line_no}: {cell:?} is not a number"),
                )
            })?;
            if !v.is_finite() {
                return Err(
                    ctx.invalid_data(data_start, format!("line {line_no}: non-finite value"))
                );
            }
            ch_values.push(v);
        }
        point += 1;
    }
    if point < n {
        return Err(ctx.truncated(
            format!("data ({point} of {n} points present)"),
            data_start,
            n,
            point,
        ));
    }

    Ok(values)
}

/// The date of the experiment (header lines 9 to 14), when the file gives one.
fn recorded(lines: &[&str]) -> Option<DateTime> {
    let num = |k: usize| lines.get(k - 1).and_then(|s| s.trim().parse::<i64>().ok());
    match (num(9), num(10), num(11), num(12), num(13), num(14)) {
        (Some(y), Some(mo), Some(d), Some(h), Some(mi), Some(s)) if y > 0 => DateTime::new(
            i32::try_from(y).unwrap_or(0),
            u8::try_from(mo).unwrap_or(0),
            u8::try_from(d).unwrap_or(0),
            u8::try_from(h).unwrap_or(0),
            u8::try_from(mi).unwrap_or(0),
            u8::try_from(s).unwrap_or(0),
        ),
        _ => None,
    }
}

/// Parses an ISO 28600 file held in memory.
pub(crate) fn parse(bytes: &[u8], path: &Path) -> Result<SpmFile> {
    let ctx = Ctx::new(path);
    if !bytes.starts_with(MAGIC.as_bytes()) {
        let shown = String::from_utf8_lossy(&bytes[..bytes.len().min(36)]).into_owned();
        return Err(ctx.bad_magic(
            Format::Iso28600,
            format!("expected {MAGIC:?}, found {shown:?}"),
        ));
    }
    let (lines, data_start) = header_lines(ctx, bytes)?;
    let field = |n: usize| -> Result<&str> {
        lines
            .get(n - 1)
            .map(|s| s.trim())
            .ok_or_else(|| ctx.missing(line_name(n)))
    };
    let header: Vec<(String, String)> = lines
        .iter()
        .enumerate()
        .skip(1)
        .map(|(i, v)| (line_name(i + 1), v.trim().to_string()))
        .collect();

    let mode = field(8)?;
    let channels_n = match mode {
        "MAP_SC" => 1,
        "MAP_MC" => {
            let n = parse_u64(ctx, &line_name(94), field(94)?)?;
            if n == 0 || n > MAX_CHANNELS as u64 {
                return Err(
                    ctx.invalid(line_name(94), format!("{n} channels (1 to {MAX_CHANNELS})"))
                );
            }
            n as usize
        }
        other => {
            return Err(ctx.unsupported(format!("experiment mode {other:?} (only MAP_SC, MAP_MC)")));
        }
    };
    let scan_mode = field(17)?;
    if scan_mode != "REGULAR MAPPING" {
        return Err(ctx.unsupported(format!("scan mode {scan_mode:?} (only REGULAR MAPPING)")));
    }
    if !field(20)?.eq_ignore_ascii_case("X") {
        return Err(ctx.unsupported(format!("fast scan axis {:?} (only X)", field(20)?)));
    }
    let reversed_x = match field(21)?.to_ascii_lowercase().as_str() {
        "left to right" => false,
        "right to left" => true,
        other => return Err(ctx.invalid(line_name(21), format!("unknown direction {other:?}"))),
    };
    let scan_dir = match field(23)?.to_ascii_lowercase().as_str() {
        "top to bottom" => ScanDir::Down,
        "bottom to top" => ScanDir::Up,
        other => return Err(ctx.invalid(line_name(23), format!("unknown direction {other:?}"))),
    };
    let nx = parse_u64(ctx, &line_name(24), field(24)?)?;
    let ny = parse_u64(ctx, &line_name(25), field(25)?)?;
    let available = bytes.len() - data_start;
    // Every value takes at least two bytes (a digit and a separator).
    let (nx, ny) = ctx.check_grid(
        "Number of X/Y points",
        nx,
        ny,
        channels_n as u64,
        2,
        (data_start, available),
    )?;
    let size = |unit_line: usize, value_line: usize| -> Result<f64> {
        let unit = field(unit_line)?;
        let f = length_unit_to_nm(unit).ok_or_else(|| {
            ctx.unsupported(format!("{}: lateral unit {unit:?}", line_name(unit_line)))
        })?;
        let v = parse_f64(ctx, &line_name(value_line), field(value_line)?)?.abs();
        if v == 0.0 {
            return Err(ctx.invalid(line_name(value_line), "field of view is zero"));
        }
        Ok(v * f)
    };
    let size_x_nm = size(26, 28)?;
    let size_y_nm = size(27, 29)?;

    let specs: Vec<(String, String)> = if channels_n == 1 {
        vec![(field(69)?.to_string(), field(70)?.to_string())]
    } else {
        (0..channels_n)
            .map(|c| {
                Ok((
                    field(95 + 3 * c)?.to_string(),
                    field(96 + 3 * c)?.to_string(),
                ))
            })
            .collect::<Result<_>>()?
    };

    // Data.
    let n = nx * ny;
    let values = data_values(ctx, bytes, data_start, lines.len(), n, channels_n)?;

    let recorded = recorded(&lines);
    let line_time_s = field(38)
        .ok()
        .and_then(|s| s.parse::<f64>().ok())
        .filter(|r| *r > 0.0 && r.is_finite())
        .map(|rate| 1.0 / rate);

    let direction = if reversed_x {
        Direction::Backward
    } else {
        Direction::Forward
    };
    let mut channels = Vec::with_capacity(channels_n);
    for ((name, unit), stored) in specs.into_iter().zip(values) {
        let (si_unit, divisor) = to_si(&unit);
        let mut data = Vec::with_capacity(n);
        for row in 0..ny {
            let src = if scan_dir == ScanDir::Up {
                ny - 1 - row
            } else {
                row
            };
            let line = &stored[src * nx..(src + 1) * nx];
            if reversed_x {
                data.extend(line.iter().rev().map(|v| v / divisor));
            } else {
                data.extend(line.iter().map(|v| v / divisor));
            }
        }
        let ch = Channel::new(name, direction, si_unit, nx, ny, data)
            .map_err(|_| ctx.invalid("Number of X/Y points", "grid does not match data"))?
            .with_size_nm(size_x_nm, size_y_nm)
            .with_scan_dir(scan_dir);
        channels.push(ch);
    }
    Ok(SpmFile {
        source: path.to_path_buf(),
        format: Format::Iso28600,
        channels,
        header,
        scan_dir: Some(scan_dir),
        line_time_s,
        recorded,
    })
}
