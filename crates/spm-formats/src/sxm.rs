//! Nanonis `.sxm` reader.
//!
//! Layout (Nanonis "SXM file format" description): an ASCII header of `:TAG:` lines, each
//! followed by value lines, ending with `:SCANIT_END:`; then the bytes `0x1A 0x04`; then, for
//! every row of the `DATA_INFO` table in order, the forward image and (Direction `both`) the
//! backward image, each `ny` lines of `nx` float32 values, big-endian when `SCANIT_TYPE` says
//! `MSBFIRST`. Lines are stored in acquisition order: with `SCAN_DIR down` the first stored
//! line is the top line. Backward lines are stored in time order (right to left). Incomplete
//! scans are NaN-filled; NaN is kept and reported by [`crate::Channel::nan_count`].

use std::path::Path;

use crate::error::{Ctx, Result};
use crate::model::{Channel, DateTime, Direction, Format, LineTiming, ScanDir, SpmFile};
use crate::text::{parse_f64, parse_u64, utf8};

const END_TAG: &[u8] = b":SCANIT_END:";
const DATA_MARK: [u8; 2] = [0x1A, 0x04];

/// Whether `bytes` start like a Nanonis scan file.
pub(crate) fn has_magic(bytes: &[u8]) -> bool {
    bytes.starts_with(b":NANONIS_VERSION:") || bytes.starts_with(b":SCANIT_TYPE:")
}

/// Reads a Nanonis `.sxm` file.
pub fn read_sxm(path: impl AsRef<Path>) -> Result<SpmFile> {
    let path = path.as_ref();
    let bytes = crate::read_file(path)?;
    parse(&bytes, path)
}

fn find(haystack: &[u8], needle: &[u8]) -> Option<usize> {
    if needle.is_empty() || haystack.len() < needle.len() {
        return None;
    }
    haystack.windows(needle.len()).position(|w| w == needle)
}

/// Splits the header text into `(tag, value)` pairs in file order.
fn parse_tags(ctx: Ctx<'_>, text: &str) -> Result<Vec<(String, String)>> {
    let mut out: Vec<(String, String)> = Vec::new();
    let mut current: Option<(String, Vec<&str>)> = None;
    for line in text.lines() {
        let t = line.trim_end_matches('\r');
        let trimmed = t.trim();
        let is_tag = trimmed.len() >= 2
            && trimmed.starts_with(':')
            && trimmed.ends_with(':')
            && !trimmed[1..trimmed.len() - 1].contains(':')
            && t.starts_with(':');
        if is_tag {
            if let Some((tag, lines)) = current.take() {
                ctx.check_header_entries(out.len())?;
                out.push((tag, join_value(&lines)));
            }
            current = Some((trimmed[1..trimmed.len() - 1].to_string(), Vec::new()));
        } else if let Some((_, lines)) = current.as_mut() {
            lines.push(t);
        }
    }
    if let Some((tag, lines)) = current {
        ctx.check_header_entries(out.len())?;
        out.push((tag, join_value(&lines)));
    }
    Ok(out)
}

fn join_value(lines: &[&str]) -> String {
    let mut v: Vec<&str> = lines.to_vec();
    while v.last().is_some_and(|l| l.trim().is_empty()) {
        v.pop();
    }
    while v.first().is_some_and(|l| l.trim().is_empty()) {
        v.remove(0);
    }
    if v.len() == 1 {
        v[0].trim().to_string()
    } else {
        v.join("\n")
    }
}

fn get<'h>(header: &'h [(String, String)], key: &str) -> Option<&'h str> {
    header
        .iter()
        .find(|(k, _)| k == key)
        .map(|(_, v)| v.as_str())
}

fn two_numbers(ctx: Ctx<'_>, field: &str, value: &str) -> Result<(f64, f64)> {
    let mut it = value.split_whitespace();
    match (it.next(), it.next()) {
        (Some(a), Some(b)) => Ok((parse_f64(ctx, field, a)?, parse_f64(ctx, field, b)?)),
        _ => Err(ctx.invalid(field, format!("expected two numbers, found {value:?}"))),
    }
}

struct ChannelSpec {
    name: String,
    unit: String,
    directions: Vec<Direction>,
}

fn parse_data_info(ctx: Ctx<'_>, value: &str) -> Result<Vec<ChannelSpec>> {
    let field = "DATA_INFO";
    let split = |line: &str| -> Vec<String> {
        let mut cells: Vec<String> = line.split('\t').map(|c| c.trim().to_string()).collect();
        if cells.first().is_some_and(|c| c.is_empty()) {
            cells.remove(0);
        }
        cells
    };
    let mut lines = value.lines().filter(|l| !l.trim().is_empty());
    let head = lines
        .next()
        .ok_or_else(|| ctx.invalid(field, "empty channel table"))?;
    let columns = split(head);
    let col = |name: &str, default: usize| {
        columns
            .iter()
            .position(|c| c.eq_ignore_ascii_case(name))
            .unwrap_or(default)
    };
    let (i_name, i_unit, i_dir) = (col("Name", 1), col("Unit", 2), col("Direction", 3));
    let mut specs = Vec::new();
    for (row, line) in lines.enumerate() {
        let cells = split(line);
        let cell = |i: usize| {
            cells.get(i).ok_or_else(|| {
                ctx.invalid(
                    field,
                    format!("row {} has {} columns, expected more", row + 1, cells.len()),
                )
            })
        };
        let directions = match cell(i_dir)?.to_ascii_lowercase().as_str() {
            "both" => vec![Direction::Forward, Direction::Backward],
            "forward" => vec![Direction::Forward],
            "backward" => vec![Direction::Backward],
            other => {
                return Err(ctx.invalid(
                    field,
                    format!("row {}: unknown direction {other:?}", row + 1),
                ));
            }
        };
        specs.push(ChannelSpec {
            name: cell(i_name)?.clone(),
            unit: cell(i_unit)?.clone(),
            directions,
        });
    }
    if specs.is_empty() {
        return Err(ctx.invalid(field, "no channels"));
    }
    Ok(specs)
}

fn parse_recorded(header: &[(String, String)]) -> Option<DateTime> {
    let date = get(header, "REC_DATE")?.trim();
    let time = get(header, "REC_TIME")?.trim();
    let d: Vec<&str> = date.split('.').collect();
    let t: Vec<&str> = time.split(':').collect();
    if d.len() != 3 || t.len() != 3 {
        return None;
    }
    DateTime::new(
        d[2].trim().parse().ok()?,
        d[1].trim().parse().ok()?,
        d[0].trim().parse().ok()?,
        t[0].trim().parse().ok()?,
        t[1].trim().parse().ok()?,
        t[2].trim().parse::<f64>().ok()?.floor() as u8,
    )
}

/// Scan geometry and line timing from the header, the same for every channel.
struct ScanGeometry {
    size_m: Option<(f64, f64)>,
    center_m: Option<(f64, f64)>,
    angle_deg: Option<f64>,
    scan_dir: Option<ScanDir>,
    /// Forward and backward line times, s.
    times: Option<(f64, f64)>,
}

impl ScanGeometry {
    fn read(ctx: Ctx<'_>, header: &[(String, String)]) -> Result<Self> {
        let size_m = match get(header, "SCAN_RANGE") {
            Some(v) => Some(two_numbers(ctx, "SCAN_RANGE", v)?),
            None => None,
        };
        let center_m = match get(header, "SCAN_OFFSET") {
            Some(v) => Some(two_numbers(ctx, "SCAN_OFFSET", v)?),
            None => None,
        };
        let angle_deg = match get(header, "SCAN_ANGLE") {
            Some(v) if !v.trim().is_empty() => Some(parse_f64(ctx, "SCAN_ANGLE", v)?),
            _ => None,
        };
        let scan_dir = match get(header, "SCAN_DIR").map(|s| s.trim().to_ascii_lowercase()) {
            Some(s) if s == "down" => Some(ScanDir::Down),
            Some(s) if s == "up" => Some(ScanDir::Up),
            Some(s) => {
                return Err(ctx.invalid("SCAN_DIR", format!("expected up or down, found {s:?}")));
            }
            None => None,
        };
        let times = match get(header, "SCAN_TIME") {
            Some(v) => {
                let (f, b) = two_numbers(ctx, "SCAN_TIME", v)?;
                if f <= 0.0 || b < 0.0 {
                    return Err(
                        ctx.invalid("SCAN_TIME", format!("non-positive line time in {v:?}"))
                    );
                }
                Some((f, b))
            }
            None => None,
        };
        Ok(Self {
            size_m,
            center_m,
            angle_deg,
            scan_dir,
            times,
        })
    }

    /// `ch` with this geometry and the timing of its trace direction.
    fn apply(&self, mut ch: Channel, direction: Direction) -> Channel {
        if let Some((sx, sy)) = self.size_m {
            ch = ch.with_size_nm(sx * 1e9, sy * 1e9);
        }
        if let Some((cx, cy)) = self.center_m {
            ch = ch.with_center_nm(cx * 1e9, cy * 1e9);
        }
        if let Some(a) = self.angle_deg {
            ch = ch.with_angle_deg(a);
        }
        if let Some(d) = self.scan_dir {
            ch = ch.with_scan_dir(d);
        }
        if let Some((tf, tb)) = self.times {
            let (line_time_s, first) = match direction {
                Direction::Forward => (tf, 0.0),
                Direction::Backward => (tb, tf),
            };
            ch = ch.with_timing(LineTiming {
                line_time_s,
                line_period_s: tf + tb,
                first_line_start_s: first,
            });
        }
        ch
    }
}

/// The f32 values of one image block starting at byte `offset`; infinite values are refused.
fn decode_f32(ctx: Ctx<'_>, block: &[u8], offset: usize, big_endian: bool) -> Result<Vec<f64>> {
    let mut stored = ctx.vec_with_capacity(block.len() / 4, "image data")?;
    for (k, c) in block.chunks_exact(4).enumerate() {
        let raw = [c[0], c[1], c[2], c[3]];
        let v = if big_endian {
            f32::from_be_bytes(raw)
        } else {
            f32::from_le_bytes(raw)
        };
        if v.is_infinite() {
            return Err(ctx.invalid_data(offset + 4 * k, "infinite value"));
        }
        stored.push(f64::from(v));
    }
    Ok(stored)
}

/// Stored order = acquisition order. Display: top line first, x increasing.
fn display_order(
    stored: &[f64],
    nx: usize,
    ny: usize,
    scan_dir: Option<ScanDir>,
    direction: Direction,
) -> Vec<f64> {
    let mut data = Vec::with_capacity(nx * ny);
    for row in 0..ny {
        let src_row = if scan_dir == Some(ScanDir::Up) {
            ny - 1 - row
        } else {
            row
        };
        let line = &stored[src_row * nx..(src_row + 1) * nx];
        match direction {
            Direction::Forward => data.extend_from_slice(line),
            Direction::Backward => data.extend(line.iter().rev()),
        }
    }
    data
}

/// Parses a Nanonis scan file held in memory.
pub(crate) fn parse(bytes: &[u8], path: &Path) -> Result<SpmFile> {
    let ctx = Ctx::new(path);
    if !has_magic(bytes) {
        let shown = String::from_utf8_lossy(&bytes[..bytes.len().min(20)]).into_owned();
        return Err(ctx.bad_magic(
            Format::NanonisSxm,
            format!("expected \":NANONIS_VERSION:\", found {shown:?}"),
        ));
    }
    // The end tag is looked for only as far as a header may go.
    let limit = crate::MAX_HEADER_BYTES as usize + END_TAG.len();
    let end = match find(&bytes[..bytes.len().min(limit)], END_TAG) {
        Some(end) => end,
        None if bytes.len() > limit => {
            return Err(ctx.too_large(
                "header (bytes)",
                bytes.len() as u64,
                crate::MAX_HEADER_BYTES,
            ));
        }
        None => return Err(ctx.truncated("header end tag :SCANIT_END:", 0, 0, bytes.len())),
    };
    let text = utf8(ctx, &bytes[..end], "header", 0)?;
    let after = end + END_TAG.len();
    let window = &bytes[after..bytes.len().min(after + 64)];
    let data_offset = find(window, &DATA_MARK)
        .map(|p| after + p + DATA_MARK.len())
        .ok_or_else(|| ctx.truncated("data start mark 0x1A 0x04", after, 2, bytes.len() - after))?;

    let header = parse_tags(ctx, text)?;

    let scanit = get(&header, "SCANIT_TYPE").ok_or_else(|| ctx.missing("SCANIT_TYPE"))?;
    let upper = scanit.to_ascii_uppercase();
    if !upper.contains("FLOAT") {
        return Err(ctx.unsupported(format!("SCANIT_TYPE {scanit:?} (only FLOAT data)")));
    }
    let big_endian = !upper.contains("LSBFIRST");

    let pixels = get(&header, "SCAN_PIXELS").ok_or_else(|| ctx.missing("SCAN_PIXELS"))?;
    let mut it = pixels.split_whitespace();
    let (nx_s, ny_s) = match (it.next(), it.next()) {
        (Some(a), Some(b)) => (a, b),
        _ => {
            return Err(ctx.invalid(
                "SCAN_PIXELS",
                format!("expected two integers, found {pixels:?}"),
            ));
        }
    };
    let nx = parse_u64(ctx, "SCAN_PIXELS", nx_s)?;
    let ny = parse_u64(ctx, "SCAN_PIXELS", ny_s)?;

    let specs = parse_data_info(
        ctx,
        get(&header, "DATA_INFO").ok_or_else(|| ctx.missing("DATA_INFO"))?,
    )?;
    let images: usize = specs.iter().map(|s| s.directions.len()).sum();
    let (nx, ny) = ctx.check_grid(
        "SCAN_PIXELS",
        nx,
        ny,
        images as u64,
        4,
        (data_offset, bytes.len() - data_offset),
    )?;

    let geometry = ScanGeometry::read(ctx, &header)?;
    let (scan_dir, times) = (geometry.scan_dir, geometry.times);

    let n = nx * ny;
    let mut channels = Vec::with_capacity(images);
    let mut offset = data_offset;
    for spec in &specs {
        for &direction in &spec.directions {
            let block = ctx.slice(
                bytes,
                offset,
                n * 4,
                &format!("{} {} image", spec.name, direction),
            )?;
            let stored = decode_f32(ctx, block, offset, big_endian)?;
            offset += n * 4;
            let data = display_order(&stored, nx, ny, scan_dir, direction);
            let ch = Channel::new(
                spec.name.clone(),
                direction,
                spec.unit.clone(),
                nx,
                ny,
                data,
            )
            .map_err(|_| ctx.invalid("SCAN_PIXELS", "grid does not match data"))?;
            let ch = geometry.apply(ch, direction);
            channels.push(ch);
        }
    }

    Ok(SpmFile {
        source: path.to_path_buf(),
        format: Format::NanonisSxm,
        channels,
        recorded: parse_recorded(&header),
        header,
        scan_dir,
        line_time_s: times.map(|(f, _)| f),
    })
}
