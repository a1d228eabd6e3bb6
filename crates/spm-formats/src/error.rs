//! The typed error every reader and writer returns.

use std::path::{Path, PathBuf};

use crate::Format;

/// What went wrong, without the details: the value callers match on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum ErrorKind {
    /// The operating system refused to read or write the file.
    Io,
    /// No reader recognises the file (neither by magic nor by extension).
    UnknownFormat,
    /// The file does not start with the magic bytes of the format it claims.
    BadMagic,
    /// The file ends before a header field or the data it announces.
    Truncated,
    /// A required header field is absent.
    MissingField,
    /// A header field is present but unparsable or out of its valid range.
    InvalidField,
    /// The header claims a size (pixels, bytes) beyond the reader's limits or the file length.
    TooLarge,
    /// The data block holds values the format forbids (NaN, infinity, trailing bytes).
    InvalidData,
    /// Text (a header, a string) is not valid in its declared encoding.
    Encoding,
    /// A valid file using a feature this crate does not implement.
    Unsupported,
    /// A caller passed an argument a writer or renderer cannot use.
    InvalidInput,
}

/// An error reading, writing or rendering an SPM file; it always names the file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FormatError {
    /// The operating system refused to read or write the file.
    #[error("{}: {action}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What was attempted ("cannot read", "cannot write").
        action: &'static str,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// No reader recognises the file.
    #[error("{}: unrecognised SPM file format (no known magic bytes or extension)", path.display())]
    UnknownFormat {
        /// The file.
        path: PathBuf,
    },
    /// The magic bytes of the expected format are missing.
    #[error("{}: not a {format} file: {detail}", path.display())]
    BadMagic {
        /// The file.
        path: PathBuf,
        /// The format that was expected.
        format: Format,
        /// What was found instead.
        detail: String,
    },
    /// The file ends before something it announces.
    #[error(
        "{}: truncated: {field} at byte offset {offset} needs {needed} bytes, only {available} left",
        path.display()
    )]
    Truncated {
        /// The file.
        path: PathBuf,
        /// The field or block being read.
        field: String,
        /// Byte offset where it starts.
        offset: u64,
        /// Bytes needed.
        needed: u64,
        /// Bytes present from `offset` to the end of the file.
        available: u64,
    },
    /// A required header field is absent.
    #[error("{}: missing header field {field}", path.display())]
    MissingField {
        /// The file.
        path: PathBuf,
        /// The field's name.
        field: String,
    },
    /// A header field cannot be parsed or is out of range.
    #[error("{}: header field {field}: {detail}", path.display())]
    InvalidField {
        /// The file.
        path: PathBuf,
        /// The field's name.
        field: String,
        /// What is wrong with it.
        detail: String,
    },
    /// A claimed size exceeds the limits.
    #[error("{}: {field} claims {claimed}, more than the limit {limit}", path.display())]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// The field or quantity.
        field: String,
        /// The claimed value.
        claimed: u64,
        /// The limit it exceeds.
        limit: u64,
    },
    /// The data block holds values the format forbids.
    #[error("{}: invalid data at byte offset {offset}: {detail}", path.display())]
    InvalidData {
        /// The file.
        path: PathBuf,
        /// Byte offset (or, for text formats, the line number noted in `detail`).
        offset: u64,
        /// What is wrong.
        detail: String,
    },
    /// Text in a wrong encoding.
    #[error("{}: {field} at byte offset {offset} is not valid {encoding}", path.display())]
    Encoding {
        /// The file.
        path: PathBuf,
        /// The header part or string.
        field: String,
        /// Byte offset of the first invalid byte (or of the string).
        offset: u64,
        /// The expected encoding ("UTF-8", "UTF-16LE").
        encoding: &'static str,
    },
    /// A valid file using an unimplemented feature.
    #[error("{}: unsupported: {detail}", path.display())]
    Unsupported {
        /// The file.
        path: PathBuf,
        /// The feature.
        detail: String,
    },
    /// An argument a writer or renderer cannot use.
    #[error("{}: invalid input: {detail}", path.display())]
    InvalidInput {
        /// The file being written (or a placeholder for in-memory encoding).
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
}

impl FormatError {
    /// The kind of error, for matching.
    pub fn kind(&self) -> ErrorKind {
        match self {
            FormatError::Io { .. } => ErrorKind::Io,
            FormatError::UnknownFormat { .. } => ErrorKind::UnknownFormat,
            FormatError::BadMagic { .. } => ErrorKind::BadMagic,
            FormatError::Truncated { .. } => ErrorKind::Truncated,
            FormatError::MissingField { .. } => ErrorKind::MissingField,
            FormatError::InvalidField { .. } => ErrorKind::InvalidField,
            FormatError::TooLarge { .. } => ErrorKind::TooLarge,
            FormatError::InvalidData { .. } => ErrorKind::InvalidData,
            FormatError::Encoding { .. } => ErrorKind::Encoding,
            FormatError::Unsupported { .. } => ErrorKind::Unsupported,
            FormatError::InvalidInput { .. } => ErrorKind::InvalidInput,
        }
    }

    /// The file the error is about.
    pub fn path(&self) -> &Path {
        match self {
            FormatError::Io { path, .. }
            | FormatError::UnknownFormat { path }
            | FormatError::BadMagic { path, .. }
            | FormatError::Truncated { path, .. }
            | FormatError::MissingField { path, .. }
            | FormatError::InvalidField { path, .. }
            | FormatError::TooLarge { path, .. }
            | FormatError::InvalidData { path, .. }
            | FormatError::Encoding { path, .. }
            | FormatError::Unsupported { path, .. }
            | FormatError::InvalidInput { path, .. } => path,
        }
    }
}

/// Shorthand used throughout the crate.
pub type Result<T, E = FormatError> = std::result::Result<T, E>;

/// Error constructors bound to one file; keeps the readers short.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Ctx<'a> {
    pub path: &'a Path,
}

impl<'a> Ctx<'a> {
    pub fn new(path: &'a Path) -> Self {
        Self { path }
    }

    pub fn bad_magic(&self, format: Format, detail: impl Into<String>) -> FormatError {
        FormatError::BadMagic {
            path: self.path.to_path_buf(),
            format,
            detail: detail.into(),
        }
    }

    pub fn truncated(
        &self,
        field: impl Into<String>,
        offset: usize,
        needed: usize,
        available: usize,
    ) -> FormatError {
        FormatError::Truncated {
            path: self.path.to_path_buf(),
            field: field.into(),
            offset: offset as u64,
            needed: needed as u64,
            available: available as u64,
        }
    }

    pub fn missing(&self, field: impl Into<String>) -> FormatError {
        FormatError::MissingField {
            path: self.path.to_path_buf(),
            field: field.into(),
        }
    }

    pub fn invalid(&self, field: impl Into<String>, detail: impl Into<String>) -> FormatError {
        FormatError::InvalidField {
            path: self.path.to_path_buf(),
            field: field.into(),
            detail: detail.into(),
        }
    }

    pub fn too_large(&self, field: impl Into<String>, claimed: u64, limit: u64) -> FormatError {
        FormatError::TooLarge {
            path: self.path.to_path_buf(),
            field: field.into(),
            claimed,
            limit,
        }
    }

    pub fn invalid_data(&self, offset: usize, detail: impl Into<String>) -> FormatError {
        FormatError::InvalidData {
            path: self.path.to_path_buf(),
            offset: offset as u64,
            detail: detail.into(),
        }
    }

    pub fn encoding(
        &self,
        field: impl Into<String>,
        offset: usize,
        encoding: &'static str,
    ) -> FormatError {
        FormatError::Encoding {
            path: self.path.to_path_buf(),
            field: field.into(),
            offset: offset as u64,
            encoding,
        }
    }

    pub fn unsupported(&self, detail: impl Into<String>) -> FormatError {
        FormatError::Unsupported {
            path: self.path.to_path_buf(),
            detail: detail.into(),
        }
    }

    pub fn invalid_input(&self, detail: impl Into<String>) -> FormatError {
        FormatError::InvalidInput {
            path: self.path.to_path_buf(),
            detail: detail.into(),
        }
    }

    /// `len` bytes starting at `offset`, or a `Truncated` error naming `field`.
    pub fn slice<'b>(
        &self,
        bytes: &'b [u8],
        offset: usize,
        len: usize,
        field: &str,
    ) -> Result<&'b [u8]> {
        let available = bytes.len().saturating_sub(offset);
        match offset.checked_add(len) {
            Some(end) if end <= bytes.len() => Ok(&bytes[offset..end]),
            _ => Err(self.truncated(field, offset, len, available)),
        }
    }

    pub fn u16_le(&self, bytes: &[u8], offset: usize, field: &str) -> Result<u16> {
        let s = self.slice(bytes, offset, 2, field)?;
        Ok(u16::from_le_bytes([s[0], s[1]]))
    }

    pub fn u32_le(&self, bytes: &[u8], offset: usize, field: &str) -> Result<u32> {
        let s = self.slice(bytes, offset, 4, field)?;
        Ok(u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
    }

    pub fn f32_le(&self, bytes: &[u8], offset: usize, field: &str) -> Result<f32> {
        let s = self.slice(bytes, offset, 4, field)?;
        Ok(f32::from_le_bytes([s[0], s[1], s[2], s[3]]))
    }

    /// Checks a claimed pixel grid against the limits and against the bytes present.
    ///
    /// `bytes_per_pixel` times `count` images must fit in the `available` bytes from `offset`
    /// (the last argument); this runs before
    /// any allocation so a forged header cannot make a reader allocate more than the file holds.
    pub fn check_grid(
        &self,
        field: &str,
        nx: u64,
        ny: u64,
        count: u64,
        bytes_per_pixel: u64,
        (offset, available): (usize, usize),
    ) -> Result<(usize, usize)> {
        if nx == 0 || ny == 0 {
            return Err(self.invalid(field, format!("pixel grid {nx}×{ny} is empty")));
        }
        if nx > MAX_SIDE_PIXELS {
            return Err(self.too_large(format!("{field} (x pixels)"), nx, MAX_SIDE_PIXELS));
        }
        if ny > MAX_SIDE_PIXELS {
            return Err(self.too_large(format!("{field} (y pixels)"), ny, MAX_SIDE_PIXELS));
        }
        let pixels = nx.saturating_mul(ny);
        if pixels > MAX_PIXELS {
            return Err(self.too_large(format!("{field} (pixels)"), pixels, MAX_PIXELS));
        }
        let needed = pixels.saturating_mul(count).saturating_mul(bytes_per_pixel);
        if needed > available as u64 {
            return Err(FormatError::Truncated {
                path: self.path.to_path_buf(),
                field: format!("data of {count} image(s) of {nx}×{ny} announced by {field}"),
                offset: offset as u64,
                needed,
                available: available as u64,
            });
        }
        // Both fit in usize: they are at most MAX_SIDE_PIXELS.
        Ok((nx as usize, ny as usize))
    }
}

/// Largest accepted header (bytes of header text): real headers are below 100 KB.
pub const MAX_HEADER_BYTES: u64 = 1 << 20;
/// Largest accepted number of header entries: real headers hold a few hundred.
pub const MAX_HEADER_ENTRIES: u64 = 10_000;

impl Ctx<'_> {
    /// Refuses a header of more than [`MAX_HEADER_BYTES`] bytes, before it is parsed.
    pub fn check_header_bytes(&self, bytes: usize) -> Result<()> {
        if bytes as u64 > MAX_HEADER_BYTES {
            return Err(self.too_large("header (bytes)", bytes as u64, MAX_HEADER_BYTES));
        }
        Ok(())
    }

    /// Refuses a header of more than [`MAX_HEADER_ENTRIES`] entries, before the next one is
    /// stored.
    pub fn check_header_entries(&self, entries: usize) -> Result<()> {
        if entries as u64 >= MAX_HEADER_ENTRIES {
            return Err(self.too_large("header (entries)", entries as u64 + 1, MAX_HEADER_ENTRIES));
        }
        Ok(())
    }

    /// An empty vector with room for `n` elements, or a `TooLarge` error naming `field`
    /// when the memory cannot be had (instead of aborting the process).
    pub fn vec_with_capacity<T>(&self, n: usize, field: &str) -> Result<Vec<T>> {
        let mut v = Vec::new();
        v.try_reserve_exact(n).map_err(|_| {
            self.too_large(
                format!("{field} (bytes of memory; not available)"),
                (n as u64).saturating_mul(std::mem::size_of::<T>() as u64),
                0,
            )
        })?;
        Ok(v)
    }
}

/// Largest accepted number of pixels along one side of an image.
pub const MAX_SIDE_PIXELS: u64 = 1 << 16;
/// Largest accepted number of pixels in one image (16384 × 16384).
pub const MAX_PIXELS: u64 = 1 << 28;
