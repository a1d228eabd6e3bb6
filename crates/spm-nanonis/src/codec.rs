//! The wire format of the Nanonis TCP protocol ("Nanonis TCP Protocol — TCP Programming
//! Interface", the vendor's manual; sections *Data Types*, *Request message*, *Response
//! message*).
//!
//! - Every number is big-endian.
//! - A **request** is a 40-byte header — command name (32 bytes, ASCII, NUL-padded), body
//!   size (`int`), *send response back* (`unsigned int16`, 0 or 1), 2 unused bytes (0) —
//!   followed by the body (the arguments).
//! - A **response** is a 40-byte header — command name (32 bytes), body size (`int`), 4
//!   unused bytes (0) — followed by the body: the return arguments, then the **error
//!   section**: status (`unsigned int32`, non-zero = error), description size (`int`),
//!   description (bytes).
//! - Strings in a body are prefixed by their size in bytes (`int`); 1-D arrays are preceded
//!   by their element count as a separate argument; 2-D arrays by rows and columns;
//!   1-D string arrays by their size in bytes and their element count, each element
//!   prefixed by its own size.
//!
//! ## The size field of a string array
//! The manual calls the first field of a 1-D string array "the size in bytes of the
//! array", which read literally is what the elements occupy (each `4 +` its length). The
//! vendor's own client (`nanonis-spm` 1.0.9, `handleArrayString`) sends `4 × count`
//! instead, and decodes the arrays of a reply by element count and each element's prefix,
//! advancing by the size field; other public clients that send string arrays copy the
//! vendor's encoding. A controller therefore reads request arrays by count and prefixes:
//! the client sends the vendor's encoding ([`Writer::string_array_vendor`]), a reply
//! carries the exact byte total ([`Writer::string_array`], which the vendor client needs
//! to find what follows), and [`Reader::string_array`] accepts either value of the size
//! field and refuses any other (the array is still read by count and prefixes).
//!
//! Decoding never panics and never trusts a size: every read is bounds-checked, sizes
//! are checked against what is left of the body *before* anything is allocated, and a
//! body must be consumed exactly ([`Reader::finish`]).

/// Size of a request or response header, bytes.
pub const HEADER_LEN: usize = 40;
/// Size of the command-name field of a header, bytes.
pub const COMMAND_NAME_LEN: usize = 32;
/// Largest body accepted, bytes (a 4096 × 4096 float32 frame is 64 MiB; the limit leaves
/// room for its prefixes but refuses absurd sizes before anything is allocated).
pub const MAX_BODY_LEN: usize = 80 << 20;

/// Why bytes are not a valid message or argument list.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum CodecError {
    /// The body ends before an argument does.
    #[error("{what}: needs {needed} bytes at offset {offset}, the body has {available}")]
    Truncated {
        /// The argument being read.
        what: &'static str,
        /// Bytes the argument needs.
        needed: usize,
        /// Where it starts.
        offset: usize,
        /// Bytes left in the body.
        available: usize,
    },
    /// Bytes are left over after the last argument (the schema does not match).
    #[error("{left} bytes left over after the last argument of {command}")]
    TrailingBytes {
        /// The command whose body it is.
        command: String,
        /// Bytes not consumed.
        left: usize,
    },
    /// A size or count is negative or larger than what is left of the body.
    #[error("{what}: invalid size {size}")]
    InvalidSize {
        /// The argument.
        what: &'static str,
        /// The size read.
        size: i64,
    },
    /// A header field is invalid.
    #[error("header field `{field}`: {reason}")]
    Header {
        /// The field.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// A flag argument is outside its documented values.
    #[error("argument `{what}`: value {value} is not one of the documented values")]
    InvalidValue {
        /// The argument.
        what: &'static str,
        /// The value read.
        value: i64,
    },
    /// The command name is unknown to this implementation.
    #[error("unknown command {0:?}")]
    UnknownCommand(String),
    /// A value cannot be encoded (too long a name or string, too many elements).
    #[error("cannot encode {what}: {reason}")]
    Encode {
        /// What.
        what: &'static str,
        /// Why.
        reason: String,
    },
}

/// A request header.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RequestHeader {
    /// Command name, e.g. `Scan.Action`.
    pub command: String,
    /// Body size, bytes.
    pub body_len: usize,
    /// Whether the server must answer.
    pub send_response: bool,
}

/// A response header.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ResponseHeader {
    /// Command name of the request answered.
    pub command: String,
    /// Body size, bytes.
    pub body_len: usize,
}

fn encode_name(name: &str, out: &mut [u8; HEADER_LEN]) -> Result<(), CodecError> {
    let bytes = name.as_bytes();
    if bytes.is_empty() || bytes.len() > COMMAND_NAME_LEN {
        return Err(CodecError::Encode {
            what: "command name",
            reason: format!("{name:?} must have 1 to {COMMAND_NAME_LEN} bytes"),
        });
    }
    if !bytes.iter().all(|b| b.is_ascii_graphic()) {
        return Err(CodecError::Encode {
            what: "command name",
            reason: format!("{name:?} must be printable ASCII"),
        });
    }
    out[..bytes.len()].copy_from_slice(bytes);
    Ok(())
}

fn decode_name(header: &[u8; HEADER_LEN]) -> Result<String, CodecError> {
    let field = &header[..COMMAND_NAME_LEN];
    let end = field
        .iter()
        .position(|&b| b == 0)
        .unwrap_or(COMMAND_NAME_LEN);
    if end == 0 {
        return Err(CodecError::Header {
            field: "command name",
            reason: "empty".into(),
        });
    }
    if field[end..].iter().any(|&b| b != 0) {
        return Err(CodecError::Header {
            field: "command name",
            reason: "bytes after the NUL padding".into(),
        });
    }
    if !field[..end].iter().all(|b| b.is_ascii_graphic()) {
        return Err(CodecError::Header {
            field: "command name",
            reason: "not printable ASCII".into(),
        });
    }
    Ok(String::from_utf8_lossy(&field[..end]).into_owned())
}

fn body_len_field(header: &[u8; HEADER_LEN]) -> Result<usize, CodecError> {
    let size = i32::from_be_bytes([header[32], header[33], header[34], header[35]]);
    if size < 0 || size as usize > MAX_BODY_LEN {
        return Err(CodecError::Header {
            field: "body size",
            reason: format!("{size} is outside [0, {MAX_BODY_LEN}]"),
        });
    }
    Ok(size as usize)
}

fn encode_body_len(body_len: usize, out: &mut [u8; HEADER_LEN]) -> Result<(), CodecError> {
    if body_len > MAX_BODY_LEN {
        return Err(CodecError::Encode {
            what: "body size",
            reason: format!("{body_len} bytes is larger than {MAX_BODY_LEN}"),
        });
    }
    out[32..36].copy_from_slice(&(body_len as i32).to_be_bytes());
    Ok(())
}

/// Encodes a request header.
pub fn encode_request_header(
    command: &str,
    body_len: usize,
    send_response: bool,
) -> Result<[u8; HEADER_LEN], CodecError> {
    let mut out = [0u8; HEADER_LEN];
    encode_name(command, &mut out)?;
    encode_body_len(body_len, &mut out)?;
    out[36..38].copy_from_slice(&u16::from(send_response).to_be_bytes());
    Ok(out)
}

/// Decodes a request header (strictly: NUL padding, flag 0 or 1, unused bytes 0).
pub fn decode_request_header(header: &[u8; HEADER_LEN]) -> Result<RequestHeader, CodecError> {
    let command = decode_name(header)?;
    let body_len = body_len_field(header)?;
    let send_response = match u16::from_be_bytes([header[36], header[37]]) {
        0 => false,
        1 => true,
        other => {
            return Err(CodecError::Header {
                field: "send response back",
                reason: format!("{other} is neither 0 nor 1"),
            });
        }
    };
    if header[38..40] != [0, 0] {
        return Err(CodecError::Header {
            field: "not used",
            reason: "the last 2 bytes must be 0".into(),
        });
    }
    Ok(RequestHeader {
        command,
        body_len,
        send_response,
    })
}

/// Encodes a response header.
pub fn encode_response_header(
    command: &str,
    body_len: usize,
) -> Result<[u8; HEADER_LEN], CodecError> {
    let mut out = [0u8; HEADER_LEN];
    encode_name(command, &mut out)?;
    encode_body_len(body_len, &mut out)?;
    Ok(out)
}

/// Decodes a response header (strictly: NUL padding, unused bytes 0).
pub fn decode_response_header(header: &[u8; HEADER_LEN]) -> Result<ResponseHeader, CodecError> {
    let command = decode_name(header)?;
    let body_len = body_len_field(header)?;
    if header[36..40] != [0, 0, 0, 0] {
        return Err(CodecError::Header {
            field: "not used",
            reason: "the last 4 bytes must be 0".into(),
        });
    }
    Ok(ResponseHeader { command, body_len })
}

/// The error section that ends every response body.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ErrorSection {
    /// Error status: 0 = no error.
    pub status: u32,
    /// The controller's description (empty when there is no error).
    pub description: String,
}

impl ErrorSection {
    /// No error.
    pub fn ok() -> Self {
        Self {
            status: 0,
            description: String::new(),
        }
    }

    /// An error with a description.
    pub fn error(description: impl Into<String>) -> Self {
        Self {
            status: 1,
            description: description.into(),
        }
    }

    /// Appends the section to a body.
    pub fn encode(&self, w: &mut Writer) -> Result<(), CodecError> {
        w.u32(self.status);
        w.string(&self.description)
    }

    /// Reads the section.
    pub fn decode(r: &mut Reader<'_>) -> Result<Self, CodecError> {
        let status = r.u32("error status")?;
        let description = r.string("error description")?;
        Ok(Self {
            status,
            description,
        })
    }
}

/// Builds a body, big-endian.
#[derive(Clone, Debug, Default)]
pub struct Writer {
    buf: Vec<u8>,
}

fn len_i32(what: &'static str, len: usize) -> Result<i32, CodecError> {
    i32::try_from(len).map_err(|_| CodecError::Encode {
        what,
        reason: format!("{len} does not fit an int"),
    })
}

impl Writer {
    /// An empty body.
    pub fn new() -> Self {
        Self::default()
    }
    /// The bytes.
    pub fn into_bytes(self) -> Vec<u8> {
        self.buf
    }
    /// Bytes written so far.
    pub fn len(&self) -> usize {
        self.buf.len()
    }
    /// True when nothing is written.
    pub fn is_empty(&self) -> bool {
        self.buf.is_empty()
    }
    /// `int`.
    pub fn i32(&mut self, v: i32) {
        self.buf.extend_from_slice(&v.to_be_bytes());
    }
    /// `unsigned int16`.
    pub fn u16(&mut self, v: u16) {
        self.buf.extend_from_slice(&v.to_be_bytes());
    }
    /// `unsigned int32`.
    pub fn u32(&mut self, v: u32) {
        self.buf.extend_from_slice(&v.to_be_bytes());
    }
    /// `float32`.
    pub fn f32(&mut self, v: f32) {
        self.buf.extend_from_slice(&v.to_be_bytes());
    }
    /// `float64`.
    pub fn f64(&mut self, v: f64) {
        self.buf.extend_from_slice(&v.to_be_bytes());
    }
    /// A string prefixed by its size in bytes (`int`).
    pub fn string(&mut self, s: &str) -> Result<(), CodecError> {
        self.i32(len_i32("string size", s.len())?);
        self.buf.extend_from_slice(s.as_bytes());
        Ok(())
    }
    /// A string whose size was sent as an earlier argument (no prefix).
    pub fn raw_string(&mut self, s: &str) {
        self.buf.extend_from_slice(s.as_bytes());
    }
    /// A 1-D `int` array without its count (sent as an earlier argument).
    pub fn i32_array(&mut self, values: &[i32]) {
        for &v in values {
            self.i32(v);
        }
    }
    /// A 1-D `float32` array without its count.
    pub fn f32_array(&mut self, values: &[f32]) {
        for &v in values {
            self.f32(v);
        }
    }
    /// A 1-D string array with its size in bytes (the exact total the elements occupy)
    /// and element count in front, each element prefixed by its size: the form of a reply.
    pub fn string_array(&mut self, values: &[String]) -> Result<(), CodecError> {
        let bytes: usize = values.iter().map(|s| 4 + s.len()).sum();
        self.i32(len_i32("string array size", bytes)?);
        self.string_array_elements(values)
    }
    /// A 1-D string array as the vendor's client sends it in a request: the size field is
    /// `4 × count` (see the module documentation), then the count and the elements.
    pub fn string_array_vendor(&mut self, values: &[String]) -> Result<(), CodecError> {
        let bytes = values.len().checked_mul(4).ok_or(CodecError::Encode {
            what: "string array size",
            reason: "too many elements".into(),
        })?;
        self.i32(len_i32("string array size", bytes)?);
        self.string_array_elements(values)
    }
    fn string_array_elements(&mut self, values: &[String]) -> Result<(), CodecError> {
        self.i32(len_i32("string array count", values.len())?);
        for s in values {
            self.string(s)?;
        }
        Ok(())
    }
    /// A 2-D string array: rows and columns in front, then `rows × columns` strings row
    /// by row, each prefixed by its size.
    pub fn string_2d(
        &mut self,
        rows: usize,
        columns: usize,
        values: &[String],
    ) -> Result<(), CodecError> {
        if rows.checked_mul(columns) != Some(values.len()) {
            return Err(CodecError::Encode {
                what: "2-D string array",
                reason: format!("{rows} × {columns} ≠ {} values", values.len()),
            });
        }
        self.i32(len_i32("rows", rows)?);
        self.i32(len_i32("columns", columns)?);
        for s in values {
            self.string(s)?;
        }
        Ok(())
    }
    /// A 2-D `float32` array with rows and columns in front, row-major.
    pub fn f32_2d(
        &mut self,
        rows: usize,
        columns: usize,
        values: &[f32],
    ) -> Result<(), CodecError> {
        if rows.checked_mul(columns) != Some(values.len()) {
            return Err(CodecError::Encode {
                what: "2-D array",
                reason: format!("{rows} × {columns} ≠ {} values", values.len()),
            });
        }
        self.i32(len_i32("rows", rows)?);
        self.i32(len_i32("columns", columns)?);
        self.f32_array(values);
        Ok(())
    }
}

/// Reads a body, big-endian, bounds-checked.
#[derive(Clone, Debug)]
pub struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    /// A reader at the start of `buf`.
    pub fn new(buf: &'a [u8]) -> Self {
        Self { buf, pos: 0 }
    }

    /// Bytes not read yet.
    pub fn remaining(&self) -> usize {
        self.buf.len() - self.pos
    }

    fn take(&mut self, what: &'static str, n: usize) -> Result<&'a [u8], CodecError> {
        if n > self.remaining() {
            return Err(CodecError::Truncated {
                what,
                needed: n,
                offset: self.pos,
                available: self.remaining(),
            });
        }
        let slice = &self.buf[self.pos..self.pos + n];
        self.pos += n;
        Ok(slice)
    }

    fn array<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], CodecError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(what, N)?);
        Ok(out)
    }

    /// `int`.
    pub fn i32(&mut self, what: &'static str) -> Result<i32, CodecError> {
        Ok(i32::from_be_bytes(self.array(what)?))
    }
    /// `unsigned int16`.
    pub fn u16(&mut self, what: &'static str) -> Result<u16, CodecError> {
        Ok(u16::from_be_bytes(self.array(what)?))
    }
    /// `unsigned int32`.
    pub fn u32(&mut self, what: &'static str) -> Result<u32, CodecError> {
        Ok(u32::from_be_bytes(self.array(what)?))
    }
    /// `float32`.
    pub fn f32(&mut self, what: &'static str) -> Result<f32, CodecError> {
        Ok(f32::from_be_bytes(self.array(what)?))
    }
    /// `float64`.
    pub fn f64(&mut self, what: &'static str) -> Result<f64, CodecError> {
        Ok(f64::from_be_bytes(self.array(what)?))
    }

    /// A count or size (`int`), checked ≥ 0 and `count × element_size` ≤ the bytes left.
    pub fn count(&mut self, what: &'static str, element_size: usize) -> Result<usize, CodecError> {
        let n = self.i32(what)?;
        self.check_count(what, i64::from(n), element_size)
    }

    fn check_count(
        &self,
        what: &'static str,
        n: i64,
        element_size: usize,
    ) -> Result<usize, CodecError> {
        let fits = usize::try_from(n)
            .ok()
            .and_then(|n| n.checked_mul(element_size).map(|bytes| (n, bytes)))
            .filter(|&(_, bytes)| bytes <= self.remaining());
        match fits {
            Some((n, _)) => Ok(n),
            None => Err(CodecError::InvalidSize { what, size: n }),
        }
    }

    /// A string whose size in bytes was read before (`len`).
    pub fn raw_string(&mut self, what: &'static str, len: usize) -> Result<String, CodecError> {
        Ok(String::from_utf8_lossy(self.take(what, len)?).into_owned())
    }
    /// A string prefixed by its size (`int`). Invalid UTF-8 is replaced (the controller's
    /// texts are informative; nothing is decided on their bytes).
    pub fn string(&mut self, what: &'static str) -> Result<String, CodecError> {
        let len = self.count(what, 1)?;
        self.raw_string(what, len)
    }
    /// A string prefixed by its size as `unsigned int32`.
    pub fn string_u32(&mut self, what: &'static str) -> Result<String, CodecError> {
        let n = self.u32(what)?;
        let len = self.check_count(what, i64::from(n), 1)?;
        self.raw_string(what, len)
    }
    /// `n` `int`s.
    pub fn i32_array(&mut self, what: &'static str, n: usize) -> Result<Vec<i32>, CodecError> {
        let n = self.check_count(what, n as i64, 4)?;
        (0..n).map(|_| self.i32(what)).collect()
    }
    /// `n` `float32`s.
    pub fn f32_array(&mut self, what: &'static str, n: usize) -> Result<Vec<f32>, CodecError> {
        let n = self.check_count(what, n as i64, 4)?;
        (0..n).map(|_| self.f32(what)).collect()
    }
    /// A 1-D string array: size field, count, then each element prefixed by its size. The
    /// size field must be either what the elements occupy (the manual's reading) or
    /// `4 × count` (the vendor client's encoding); see the module documentation.
    pub fn string_array(&mut self, what: &'static str) -> Result<Vec<String>, CodecError> {
        let size = self.i32(what)?;
        let start = self.pos;
        let n = self.count(what, 4)?;
        let mut out = Vec::with_capacity(n);
        for _ in 0..n {
            out.push(self.string(what)?);
        }
        let used = self.pos - start - 4;
        let vendor = n.checked_mul(4);
        if usize::try_from(size)
            .ok()
            .is_none_or(|size| size != used && Some(size) != vendor)
        {
            return Err(CodecError::InvalidSize {
                what,
                size: i64::from(size),
            });
        }
        Ok(out)
    }
    /// A 2-D string array: rows, columns, then `rows × columns` strings, each prefixed by
    /// its size (row by row).
    pub fn string_2d(
        &mut self,
        what: &'static str,
    ) -> Result<(usize, usize, Vec<String>), CodecError> {
        let rows = self.i32(what)?;
        let columns = self.i32(what)?;
        if rows < 0 || columns < 0 {
            return Err(CodecError::InvalidSize {
                what,
                size: i64::from(rows.min(columns)),
            });
        }
        // Every element has at least its 4-byte prefix.
        let n = self.check_count(what, i64::from(rows) * i64::from(columns), 4)?;
        let mut values = Vec::with_capacity(n);
        for _ in 0..n {
            values.push(self.string(what)?);
        }
        Ok((rows as usize, columns as usize, values))
    }
    /// A 2-D `float32` array: rows, columns, then `rows × columns` values row-major.
    pub fn f32_2d(&mut self, what: &'static str) -> Result<(usize, usize, Vec<f32>), CodecError> {
        let rows = self.i32(what)?;
        let columns = self.i32(what)?;
        if rows < 0 || columns < 0 {
            return Err(CodecError::InvalidSize {
                what,
                size: i64::from(rows.min(columns)),
            });
        }
        let n = i64::from(rows) * i64::from(columns);
        let n = self.check_count(what, n, 4)?;
        let values = self.f32_array(what, n)?;
        Ok((rows as usize, columns as usize, values))
    }

    /// Checks that the whole body was read.
    pub fn finish(&self, command: &str) -> Result<(), CodecError> {
        if self.remaining() != 0 {
            return Err(CodecError::TrailingBytes {
                command: command.to_owned(),
                left: self.remaining(),
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Bytes from the manual's hex notation (groups of 4 hex digits, spaces ignored).
    fn hex(text: &str) -> Vec<u8> {
        let digits: Vec<u8> = text.bytes().filter(|b| !b.is_ascii_whitespace()).collect();
        digits
            .chunks(2)
            .map(|pair| {
                let s = std::str::from_utf8(pair).expect("hex digits are ASCII");
                u8::from_str_radix(s, 16).expect("valid hex in the test vector")
            })
            .collect()
    }

    fn header(bytes: &[u8]) -> [u8; HEADER_LEN] {
        let mut h = [0u8; HEADER_LEN];
        h.copy_from_slice(&bytes[..HEADER_LEN]);
        h
    }

    const FOLME_XYPOSGET_NAME: &str =
        "466F 6C4D 652E 5859 506F 7347 6574 0000 0000 0000 0000 0000 0000 0000 0000 0000";
    const FOLME_XYPOSSET_NAME: &str =
        "466F 6C4D 652E 5859 506F 7353 6574 0000 0000 0000 0000 0000 0000 0000 0000 0000";

    #[test]
    fn manual_example_return_the_tip_position_request() {
        // Manual, Examples > Return the tip position: FolMe.XYPosGet, body = Wait for newest
        // data (unsigned int32) = 1.
        let bytes = hex(&format!(
            "{FOLME_XYPOSGET_NAME} 0000 0004 0001 0000 0000 0001"
        ));
        let mut w = Writer::new();
        w.u32(1);
        let body = w.into_bytes();
        let mut encoded = encode_request_header("FolMe.XYPosGet", body.len(), true)
            .expect("valid header")
            .to_vec();
        encoded.extend_from_slice(&body);
        assert_eq!(encoded, bytes);
        let decoded = decode_request_header(&header(&bytes)).expect("valid header");
        assert_eq!(
            decoded,
            RequestHeader {
                command: "FolMe.XYPosGet".into(),
                body_len: 4,
                send_response: true
            }
        );
    }

    #[test]
    fn manual_example_return_the_tip_position_response() {
        // X = 5 nm, Y = −5 nm (float64), error status 0, error size 0.
        let bytes = hex(&format!(
            "{FOLME_XYPOSGET_NAME} 0000 0018 0000 0000 3E35 798E E230 8C3A BE35 798E E230 8C3A \
             0000 0000 0000 0000"
        ));
        let h = decode_response_header(&header(&bytes)).expect("valid header");
        assert_eq!(h.command, "FolMe.XYPosGet");
        assert_eq!(h.body_len, 24);
        let mut r = Reader::new(&bytes[HEADER_LEN..]);
        assert_eq!(r.f64("x").expect("x"), 5e-9);
        assert_eq!(r.f64("y").expect("y"), -5e-9);
        assert_eq!(
            ErrorSection::decode(&mut r).expect("error"),
            ErrorSection::ok()
        );
        r.finish("FolMe.XYPosGet").expect("consumed");
        // And the other way round.
        let mut w = Writer::new();
        w.f64(5e-9);
        w.f64(-5e-9);
        ErrorSection::ok().encode(&mut w).expect("encodes");
        let body = w.into_bytes();
        let mut encoded = encode_response_header("FolMe.XYPosGet", body.len())
            .expect("valid")
            .to_vec();
        encoded.extend_from_slice(&body);
        assert_eq!(encoded, bytes);
    }

    #[test]
    fn manual_example_change_the_tip_position() {
        // FolMe.XYPosSet X = 10 nm, Y = 15 nm, wait = 1; response: error section only.
        let request = hex(&format!(
            "{FOLME_XYPOSSET_NAME} 0000 0014 0001 0000 3E45 798E E230 8C3A 3E50 1B2B 29A4 692B 0000 0001"
        ));
        let mut w = Writer::new();
        w.f64(10e-9);
        w.f64(15e-9);
        w.u32(1);
        let body = w.into_bytes();
        let mut encoded = encode_request_header("FolMe.XYPosSet", body.len(), true)
            .expect("valid")
            .to_vec();
        encoded.extend_from_slice(&body);
        assert_eq!(encoded, request);
        let response = hex(&format!(
            "{FOLME_XYPOSSET_NAME} 0000 0008 0000 0000 0000 0000 0000 0000"
        ));
        let h = decode_response_header(&header(&response)).expect("valid");
        assert_eq!(h.body_len, 8);
        let mut r = Reader::new(&response[HEADER_LEN..]);
        assert_eq!(
            ErrorSection::decode(&mut r).expect("error"),
            ErrorSection::ok()
        );
        r.finish("FolMe.XYPosSet").expect("consumed");
    }

    fn check_header_rejected(mutate: impl Fn(&mut [u8; HEADER_LEN]), field: &str) {
        let mut h = encode_request_header("Scan.Action", 6, true).expect("valid");
        mutate(&mut h);
        match decode_request_header(&h) {
            Err(CodecError::Header { field: f, .. }) => assert_eq!(f, field),
            other => panic!("expected a header error on {field}, got {other:?}"),
        }
    }

    #[test]
    fn malformed_headers_are_rejected_with_the_field() {
        check_header_rejected(|h| h[0] = 0, "command name");
        check_header_rejected(|h| h[20] = b'x', "command name");
        check_header_rejected(|h| h[3] = 0x07, "command name");
        check_header_rejected(|h| h[32] = 0x80, "body size");
        check_header_rejected(|h| h[37] = 2, "send response back");
        check_header_rejected(|h| h[39] = 1, "not used");
        assert!(encode_request_header("", 0, true).is_err());
        assert!(encode_request_header(&"x".repeat(33), 0, true).is_err());
    }

    #[test]
    fn sizes_are_checked_before_allocating() {
        // A count of 2^31−1 floats in an 8-byte body.
        let mut w = Writer::new();
        w.i32(i32::MAX);
        w.i32(0);
        let bytes = w.into_bytes();
        let mut r = Reader::new(&bytes);
        assert!(matches!(
            r.count("values", 4),
            Err(CodecError::InvalidSize { .. })
        ));
        let mut r = Reader::new(&bytes);
        // i32::MAX rows × 0 columns is an empty array, and valid.
        assert_eq!(r.f32_2d("data").map(|(_, _, v)| v.len()), Ok(0));
        let mut w = Writer::new();
        w.i32(i32::MAX);
        w.i32(2);
        let bytes = w.into_bytes();
        let mut r = Reader::new(&bytes);
        assert!(matches!(
            r.f32_2d("data"),
            Err(CodecError::InvalidSize { .. })
        ));
        let mut r = Reader::new(&[0xFF, 0xFF, 0xFF, 0xFF]);
        assert!(r.string("name").is_err());
    }

    proptest! {
        #[test]
        fn scalars_strings_and_arrays_round_trip(
            a in any::<i32>(), b in any::<u16>(), c in any::<u32>(),
            d in any::<f32>().prop_filter("not NaN", |v| !v.is_nan()), e in any::<f64>().prop_filter("not NaN", |v| !v.is_nan()),
            s in ".{0,40}",
            ints in proptest::collection::vec(any::<i32>(), 0..20),
            strings in proptest::collection::vec(".{0,10}", 0..6),
            rows in 0usize..6, columns in 0usize..6,
        ) {
            let grid: Vec<f32> = (0..rows * columns).map(|i| i as f32 * 0.5 - 3.0).collect();
            let mut w = Writer::new();
            w.i32(a); w.u16(b); w.u32(c); w.f32(d); w.f64(e);
            w.string(&s).expect("encodes");
            w.i32(ints.len() as i32); w.i32_array(&ints);
            w.string_array(&strings).expect("encodes");
            w.f32_2d(rows, columns, &grid).expect("encodes");
            ErrorSection::error("boom").encode(&mut w).expect("encodes");
            let bytes = w.into_bytes();
            let mut r = Reader::new(&bytes);
            prop_assert_eq!(r.i32("a").expect("a"), a);
            prop_assert_eq!(r.u16("b").expect("b"), b);
            prop_assert_eq!(r.u32("c").expect("c"), c);
            prop_assert_eq!(r.f32("d").expect("d"), d);
            prop_assert_eq!(r.f64("e").expect("e"), e);
            prop_assert_eq!(r.string("s").expect("s"), s);
            let n = r.count("n", 4).expect("n");
            prop_assert_eq!(r.i32_array("ints", n).expect("ints"), ints);
            prop_assert_eq!(r.string_array("strings").expect("strings"), strings);
            let (rr, cc, values) = r.f32_2d("grid").expect("grid");
            prop_assert_eq!((rr, cc), (rows, columns));
            prop_assert_eq!(values, grid);
            prop_assert_eq!(ErrorSection::decode(&mut r).expect("err"), ErrorSection::error("boom"));
            prop_assert!(r.finish("t").is_ok());
        }

        #[test]
        fn headers_round_trip(name in "[A-Za-z][A-Za-z0-9.]{0,31}", len in 0usize..MAX_BODY_LEN, flag in any::<bool>()) {
            let h = encode_request_header(&name, len, flag).expect("valid");
            let d = decode_request_header(&h).expect("decodes");
            prop_assert_eq!(d, RequestHeader { command: name.clone(), body_len: len, send_response: flag });
            let h = encode_response_header(&name, len).expect("valid");
            let d = decode_response_header(&h).expect("decodes");
            prop_assert_eq!(d, ResponseHeader { command: name, body_len: len });
        }

        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..200)) {
            let mut r = Reader::new(&bytes);
            let _ = r.string_array("a");
            let mut r = Reader::new(&bytes);
            let _ = r.f32_2d("b");
            if bytes.len() >= HEADER_LEN {
                let _ = decode_request_header(&header(&bytes));
                let _ = decode_response_header(&header(&bytes));
            }
        }
    }
}
