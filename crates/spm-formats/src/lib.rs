//! SPM file formats: Nanonis `.sxm`, RHK `.sm4`, ISO 28600, raw f64, Gwyddion `.gsf` and `.gwy`.
//!
//! Every reader turns a file into one [`SpmFile`]: a list of image [`Channel`]s (name,
//! forward/backward, SI unit, pixel grid, physical size in nm, slow-axis direction, line
//! timing) plus the complete header as ordered key/value pairs. [`read_any`] detects the
//! format from the magic bytes (falling back to the extension); [`read_bytes`] does the same
//! for a buffer already in memory. [`write_gsf`] writes one channel as a Gwyddion Simple
//! Field, [`write_gwy`] any number of channels with their metadata as a Gwyddion native file. (Rendering a channel as a PNG is `spm_plot::render_png`: this crate reads and
//! writes files and draws nothing.)
//!
//! Orientation: a channel's data are in display orientation (row 0 = top, x to the right);
//! [`Channel::acquisition_image`] reorders them into acquisition order (row 0 = first line
//! measured, pixels along a row in time order), and [`Channel::pixel_time_s`] gives the time
//! of each pixel when the file records the line time.
//!
//! Robustness: readers never panic on data. Every size a header claims is checked against
//! the limits ([`MAX_PIXELS`], [`MAX_SIDE_PIXELS`]) and against the bytes actually present
//! before anything is allocated; failures are [`FormatError`]s naming the file and the field
//! or byte offset, with a [`FormatError::kind`] to match on.
#![doc = include_str!("../README.md")]

mod error;
mod gsf;
mod gwy;
mod iso28600;
mod model;
mod raw;
mod rhk_sm4;
mod sxm;
mod sxm_write;
mod text;

use std::path::Path;

pub use error::{
    ErrorKind, FormatError, MAX_HEADER_BYTES, MAX_HEADER_ENTRIES, MAX_PIXELS, MAX_SIDE_PIXELS,
    Result,
};
pub use gsf::{KEY_SCAN_ANGLE_CCW_DEG, encode_gsf, read_gsf, write_gsf};
pub use gwy::{encode_gwy, write_gwy};
pub use iso28600::read_iso28600;
pub use model::{
    Channel, ChannelInfo, DateTime, Direction, Format, Image, Info, LineTiming, ScanDir, SpmFile,
};
pub use raw::{encode_raw_f64, read_raw_f64};
pub use rhk_sm4::read_sm4;
pub use sxm::read_sxm;
pub use sxm_write::{SxmChannel, SxmScan, encode_sxm, write_sxm};

use error::Ctx;

/// Largest file [`read_any`] reads into memory (1 GiB).
pub const MAX_FILE_BYTES: u64 = 1 << 30;

/// Reads an SPM file of any supported format, detected by magic bytes or extension.
pub fn read_any(path: impl AsRef<Path>) -> Result<SpmFile> {
    let path = path.as_ref();
    let bytes = read_file(path)?;
    read_bytes(&bytes, path)
}

/// Files longer than this are read only when their blocks are on disk (see [`read_file`]).
const SPARSE_CHECK_BYTES: u64 = 64 << 20;

/// Reads a whole file with a size cap. The buffer is reserved with `try_reserve` (no
/// abort when memory is short), and a long file whose length is mostly holes (a sparse
/// file: fewer than 1/16 of its bytes allocated on disk) is refused before it is read: no
/// instrument writes one, and its zeros would make a claimed giant image look complete
/// (issue 25: a 4 KiB sparse GSF claiming 16383² pixels took 3.15 GB).
pub(crate) fn read_file(path: &Path) -> Result<Vec<u8>> {
    use std::io::Read;
    let io = |source| FormatError::Io {
        path: path.to_path_buf(),
        action: "cannot read",
        source,
    };
    let ctx = Ctx::new(path);
    let meta = std::fs::metadata(path).map_err(io)?;
    let len = meta.len();
    if len > MAX_FILE_BYTES {
        return Err(ctx.too_large("file length", len, MAX_FILE_BYTES));
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        let on_disk = meta.blocks().saturating_mul(512);
        if len > SPARSE_CHECK_BYTES && on_disk < len / 16 {
            return Err(ctx.invalid(
                "file",
                format!(
                    "a sparse file: {len} bytes long but only {on_disk} bytes on disk (the \
                     rest are holes); not a recorded image"
                ),
            ));
        }
    }
    let mut bytes: Vec<u8> =
        ctx.vec_with_capacity(usize::try_from(len).unwrap_or(usize::MAX), "file")?;
    std::fs::File::open(path)
        .map_err(io)?
        .take(MAX_FILE_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(io)?;
    if bytes.len() as u64 > MAX_FILE_BYTES {
        return Err(ctx.too_large("file length", bytes.len() as u64, MAX_FILE_BYTES));
    }
    Ok(bytes)
}

/// Detects the format of `bytes` from magic bytes, then from the extension of `name`.
pub fn detect_format(bytes: &[u8], name: &Path) -> Option<Format> {
    if bytes.starts_with(gsf::MAGIC) {
        return Some(Format::Gsf);
    }
    if bytes.starts_with(gwy::MAGIC) {
        return Some(Format::Gwy);
    }
    if bytes.starts_with(iso28600::MAGIC.as_bytes()) {
        return Some(Format::Iso28600);
    }
    if rhk_sm4::has_magic(bytes) {
        return Some(Format::RhkSm4);
    }
    if sxm::has_magic(bytes) {
        return Some(Format::NanonisSxm);
    }
    let ext = name
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match ext.as_deref() {
        Some("sxm") => Some(Format::NanonisSxm),
        Some("sm4") => Some(Format::RhkSm4),
        Some("gsf") => Some(Format::Gsf),
        Some("gwy") => Some(Format::Gwy),
        Some("spm") => Some(Format::Iso28600),
        Some("dat" | "raw") => Some(Format::RawF64),
        _ if raw::size_matches(bytes) => Some(Format::RawF64),
        _ => None,
    }
}

/// Parses a buffer already in memory; `name` is used for detection and in errors.
pub fn read_bytes(bytes: &[u8], name: &Path) -> Result<SpmFile> {
    match detect_format(bytes, name) {
        Some(format) => read_as(bytes, name, format),
        None => Err(FormatError::UnknownFormat {
            path: name.to_path_buf(),
        }),
    }
}

/// Parses a buffer as the given format.
pub fn read_as(bytes: &[u8], name: &Path, format: Format) -> Result<SpmFile> {
    match format {
        Format::NanonisSxm => sxm::parse(bytes, name),
        Format::RhkSm4 => rhk_sm4::parse(bytes, name),
        Format::Iso28600 => iso28600::parse(bytes, name),
        Format::RawF64 => raw::parse(bytes, name),
        Format::Gsf => gsf::parse(bytes, name),
        Format::Gwy => gwy::parse(bytes, name),
    }
}
