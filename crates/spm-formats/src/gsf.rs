//! Gwyddion Simple Field (`.gsf`) reader and writer.
//!
//! Layout (Gwyddion user guide, "Simple Field Files"): the magic line
//! `Gwyddion Simple Field 1.0\n`; header lines `Name = value` (UTF-8); one to four NUL bytes
//! so the data start at a multiple of 4; then `XRes·YRes` little-endian IEEE float32 values,
//! row by row, the first row at the top. `XRes`, `YRes` are required; `XReal`, `YReal`
//! (physical size in base units, default 1), `XOffset`, `YOffset`, `XYUnits`, `ZUnits`,
//! `Title` are optional. Any other keys are free-form metadata. NaN values mark pixels without
//! data (Gwyddion masks them on import); infinite values are refused both ways.

use std::fmt::Write as _;
use std::path::Path;

use crate::error::{Ctx, FormatError, Result};
use crate::model::{Channel, Direction, Format, SpmFile};
use crate::text::{length_unit_to_nm, parse_f64, parse_u64, utf8};

/// The magic line, newline included.
pub(crate) const MAGIC: &[u8] = b"Gwyddion Simple Field 1.0\n";

/// Free-form header key (spmcal's, ignored by Gwyddion): the scan angle of the raster the
/// field was taken on, degrees counter-clockwise. GSF has no field for it; spmcal writes it
/// (`spmcal correct`, `spmcal crop`) and reads it back as the channel's angle.
pub const KEY_SCAN_ANGLE_CCW_DEG: &str = "spmcal_scan_angle_ccw_deg";

/// Suffix of the `Title` of a backward (retrace) channel.
const BACKWARD_SUFFIX: &str = " (backward)";

/// Reads a `.gsf` file.
pub fn read_gsf(path: impl AsRef<Path>) -> Result<SpmFile> {
    let path = path.as_ref();
    let bytes = crate::read_file(path)?;
    parse(&bytes, path)
}

/// Parses a `.gsf` file held in memory.
pub(crate) fn parse(bytes: &[u8], path: &Path) -> Result<SpmFile> {
    let ctx = Ctx::new(path);
    if !bytes.starts_with(MAGIC) {
        let shown = String::from_utf8_lossy(&bytes[..bytes.len().min(26)]).into_owned();
        return Err(ctx.bad_magic(
            Format::Gsf,
            format!("expected \"Gwyddion Simple Field 1.0\\n\", found {shown:?}"),
        ));
    }
    // The header ends at the first NUL; it is looked for only as far as a header may go.
    let limit = MAGIC.len() + crate::MAX_HEADER_BYTES as usize + 1;
    let nul = match bytes[..bytes.len().min(limit)].iter().position(|&b| b == 0) {
        Some(k) => k,
        None if bytes.len() > limit => {
            return Err(ctx.too_large(
                "header (bytes)",
                bytes.len() as u64,
                crate::MAX_HEADER_BYTES,
            ));
        }
        None => return Err(ctx.truncated("NUL padding after the header", bytes.len(), 1, 0)),
    };
    let data_start = (nul / 4 + 1) * 4;
    let pad = ctx.slice(bytes, nul, data_start - nul, "NUL padding")?;
    if let Some(k) = pad.iter().position(|&b| b != 0) {
        return Err(ctx.invalid_data(
            nul + k,
            "header padding must be NUL bytes up to a multiple of 4",
        ));
    }
    ctx.check_header_bytes(nul - MAGIC.len())?;
    let text = utf8(ctx, &bytes[MAGIC.len()..nul], "header", MAGIC.len())?;

    let mut header: Vec<(String, String)> = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        ctx.check_header_entries(header.len())?;
        let (k, v) = line.split_once('=').ok_or_else(|| {
            ctx.invalid(
                format!("header line {}", i + 2),
                format!("expected \"Name = value\", found {line:?}"),
            )
        })?;
        header.push((k.trim().to_string(), v.trim().to_string()));
    }
    let get = |key: &str| {
        header
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    };
    let nx = parse_u64(ctx, "XRes", get("XRes").ok_or_else(|| ctx.missing("XRes"))?)?;
    let ny = parse_u64(ctx, "YRes", get("YRes").ok_or_else(|| ctx.missing("YRes"))?)?;
    let available = bytes.len() - data_start;
    let (nx, ny) = ctx.check_grid("XRes/YRes", nx, ny, 1, 4, (data_start, available))?;
    let n = nx * ny;
    if available != 4 * n {
        return Err(ctx.invalid_data(
            data_start + 4 * n,
            format!(
                "{} bytes after the {}×{} float32 data",
                available - 4 * n,
                nx,
                ny
            ),
        ));
    }
    let real =
        |key: &str| -> Result<Option<f64>> { get(key).map(|v| parse_f64(ctx, key, v)).transpose() };
    let xy_units = get("XYUnits").unwrap_or("m");
    let to_nm = length_unit_to_nm(xy_units);
    let x_real = real("XReal")?.unwrap_or(1.0);
    let y_real = real("YReal")?.unwrap_or(1.0);
    if !(x_real > 0.0 && y_real > 0.0) {
        return Err(ctx.invalid("XReal/YReal", "physical size must be positive"));
    }
    let x_off = real("XOffset")?.unwrap_or(0.0);
    let y_off = real("YOffset")?.unwrap_or(0.0);

    let mut data = ctx.vec_with_capacity(n, "XRes×YRes data")?;
    for (k, c) in bytes[data_start..].chunks_exact(4).enumerate() {
        let v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        // NaN marks a pixel without data (Gwyddion reads it so, and masks it); an infinite
        // value is no measurement at all.
        if v.is_infinite() {
            return Err(ctx.invalid_data(data_start + 4 * k, format!("infinite value {v}")));
        }
        data.push(f64::from(v));
    }
    let title = get("Title").unwrap_or("Data");
    let (name, direction) = match title.strip_suffix(BACKWARD_SUFFIX) {
        Some(name) => (name, Direction::Backward),
        None => (title, Direction::Forward),
    };
    let unit = get("ZUnits").unwrap_or("").to_string();
    let mut ch = Channel::new(name, direction, unit, nx, ny, data)
        .map_err(|_| ctx.invalid("XRes/YRes", "grid does not match data"))?;
    if let Some(f) = to_nm {
        ch = ch
            .with_size_nm(x_real * f, y_real * f)
            .with_center_nm((x_off + x_real / 2.0) * f, (y_off + y_real / 2.0) * f);
    }
    if let Some(angle) = real(KEY_SCAN_ANGLE_CCW_DEG)? {
        ch = ch.with_angle_deg(angle);
    }
    Ok(SpmFile {
        source: path.to_path_buf(),
        format: Format::Gsf,
        channels: vec![ch],
        header,
        scan_dir: None,
        line_time_s: None,
        recorded: None,
    })
}

/// Encodes one channel as a `.gsf` file: its display-orientation data as float32, its size
/// in metres (`XReal`, `YReal`, `XYUnits = m`), `ZUnits` from the channel unit, `Title` from
/// the channel name and direction. `extra` adds free-form header lines (keys must be
/// identifiers; values one line).
///
/// Fails with [`crate::ErrorKind::InvalidInput`] when the channel size is unknown, a value is
/// not finite or does not fit in float32, or an extra key/value is malformed.
pub fn encode_gsf(channel: &Channel, extra: &[(&str, &str)]) -> Result<Vec<u8>> {
    let placeholder = crate::text::memory_path("gsf");
    encode_with_ctx(channel, extra, Ctx::new(&placeholder))
}

fn encode_with_ctx(channel: &Channel, extra: &[(&str, &str)], ctx: Ctx<'_>) -> Result<Vec<u8>> {
    let (sx, sy) = match (channel.size_x_nm(), channel.size_y_nm()) {
        (Some(x), Some(y)) if x > 0.0 && y > 0.0 && x.is_finite() && y.is_finite() => (x, y),
        _ => return Err(ctx.invalid_input("the channel has no positive physical size")),
    };
    let mut head = String::from_utf8_lossy(MAGIC).into_owned();
    let one_line = |s: &str| s.replace(['\n', '\r', '\0'], " ");
    let title = match channel.direction() {
        Direction::Forward => channel.name().to_string(),
        Direction::Backward => format!("{}{BACKWARD_SUFFIX}", channel.name()),
    };
    // Writing to a String cannot fail.
    let _ = writeln!(head, "XRes = {}", channel.nx());
    let _ = writeln!(head, "YRes = {}", channel.ny());
    let _ = writeln!(head, "XReal = {:e}", sx * 1e-9);
    let _ = writeln!(head, "YReal = {:e}", sy * 1e-9);
    if let (Some(cx), Some(cy)) = (channel.center_x_nm(), channel.center_y_nm()) {
        let _ = writeln!(head, "XOffset = {:e}", (cx - sx / 2.0) * 1e-9);
        let _ = writeln!(head, "YOffset = {:e}", (cy - sy / 2.0) * 1e-9);
    }
    let _ = writeln!(head, "XYUnits = m");
    let _ = writeln!(head, "ZUnits = {}", one_line(channel.unit()));
    let _ = writeln!(head, "Title = {}", one_line(&title));
    for (k, v) in extra {
        let valid_key = !k.is_empty()
            && k.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
            && !k.starts_with(|c: char| c.is_ascii_digit());
        if !valid_key {
            return Err(ctx.invalid_input(format!("GSF header key {k:?} is not an identifier")));
        }
        let _ = writeln!(head, "{k} = {}", one_line(v));
    }
    let mut out = head.into_bytes();
    let pad = 4 - out.len() % 4; // one to four NULs
    out.extend(std::iter::repeat_n(0u8, pad));
    out.reserve(4 * channel.data().len());
    for (i, &v) in channel.data().iter().enumerate() {
        let f = v as f32;
        if f.is_infinite() {
            return Err(ctx.invalid_input(format!(
                "value {v} at pixel {i} is not a finite float32 (GSF stores float32; NaN marks a \
                 pixel without data)"
            )));
        }
        out.extend_from_slice(&f.to_le_bytes());
    }
    Ok(out)
}

/// Writes one channel as a `.gsf` file (see [`encode_gsf`]).
pub fn write_gsf(path: impl AsRef<Path>, channel: &Channel, extra: &[(&str, &str)]) -> Result<()> {
    let path = path.as_ref();
    let bytes = encode_with_ctx(channel, extra, Ctx::new(path))?;
    std::fs::write(path, bytes).map_err(|source| FormatError::Io {
        path: path.to_path_buf(),
        action: "cannot write",
        source,
    })
}
