//! The raw format of the `si7x7-raw` data (SPIEPy demo files).
//!
//! Two little-endian u32 (rows, cols), then rows·cols little-endian f64 heights in metres,
//! row-major, row 0 at the top. No physical size, direction or time is stored.

use std::path::Path;

use crate::error::{Ctx, Result};
use crate::model::{Channel, Direction, Format, SpmFile};

const HEADER_BYTES: usize = 8;

/// Whether the length of `bytes` is exactly what its two leading u32 announce.
pub(crate) fn size_matches(bytes: &[u8]) -> bool {
    if bytes.len() < HEADER_BYTES {
        return false;
    }
    let rows = u64::from(u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]));
    let cols = u64::from(u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]));
    rows > 0
        && cols > 0
        && rows
            .checked_mul(cols)
            .and_then(|n| n.checked_mul(8))
            .and_then(|n| n.checked_add(HEADER_BYTES as u64))
            == Some(bytes.len() as u64)
}

/// Reads a raw f64 height file.
pub fn read_raw_f64(path: impl AsRef<Path>) -> Result<SpmFile> {
    let path = path.as_ref();
    let bytes = crate::read_file(path)?;
    parse(&bytes, path)
}

/// Parses a raw f64 height file held in memory.
pub(crate) fn parse(bytes: &[u8], path: &Path) -> Result<SpmFile> {
    let ctx = Ctx::new(path);
    let rows = ctx.u32_le(bytes, 0, "rows")?;
    let cols = ctx.u32_le(bytes, 4, "cols")?;
    let available = bytes.len() - HEADER_BYTES;
    let (nx, ny) = ctx.check_grid(
        "rows/cols",
        u64::from(cols),
        u64::from(rows),
        1,
        8,
        (HEADER_BYTES, available),
    )?;
    let n = nx * ny;
    if available != 8 * n {
        return Err(ctx.invalid_data(
            HEADER_BYTES + 8 * n,
            format!(
                "{} bytes after the {rows}×{cols} f64 data",
                available - 8 * n
            ),
        ));
    }
    let mut data = ctx.vec_with_capacity(n, "data")?;
    for (k, c) in bytes[HEADER_BYTES..].chunks_exact(8).enumerate() {
        let v = f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]);
        if !v.is_finite() {
            return Err(ctx.invalid_data(HEADER_BYTES + 8 * k, format!("non-finite value {v}")));
        }
        data.push(v);
    }
    let ch = Channel::new("Z", Direction::Forward, "m", nx, ny, data)
        .map_err(|_| ctx.invalid("rows/cols", "grid does not match data"))?;
    Ok(SpmFile {
        source: path.to_path_buf(),
        format: Format::RawF64,
        channels: vec![ch],
        header: vec![
            ("rows".to_string(), rows.to_string()),
            ("cols".to_string(), cols.to_string()),
        ],
        scan_dir: None,
        line_time_s: None,
        recorded: None,
    })
}

/// Encodes a channel in the raw format (heights in its unit, assumed metres).
pub fn encode_raw_f64(channel: &Channel) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_BYTES + 8 * channel.data().len());
    // nx, ny are at most MAX_SIDE_PIXELS for read data; saturate for hand-made channels.
    let rows = u32::try_from(channel.ny()).unwrap_or(u32::MAX);
    let cols = u32::try_from(channel.nx()).unwrap_or(u32::MAX);
    out.extend_from_slice(&rows.to_le_bytes());
    out.extend_from_slice(&cols.to_le_bytes());
    for v in channel.data() {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}
