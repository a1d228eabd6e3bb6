//! Gwyddion native file (`.gwy`): the writer puts every channel and its metadata in one file;
//! the reader takes the image channels back out of ours and of Gwyddion's own.
//!
//! Layout (Gwyddion user guide, "Gwyddion Native File Format"): the magic `GWYP`, then one
//! serialised `GwyContainer`. A serialised object is its type name (NUL-terminated), a
//! little-endian u32 byte count of its components, then the components, each a name
//! (NUL-terminated), a one-byte type and the value: `i` i32, `d` f64, `s` NUL-terminated
//! UTF-8 string, `o` an object, `D` a u32 count followed by that many f64; all little-endian.
//!
//! Per channel `n` the container holds `/n/data` (a `GwyDataField`: `xres`, `yres`, `xreal`,
//! `yreal`, `xoff`, `yoff` in metres, `si_unit_xy`, `si_unit_z` as `GwySIUnit { unitstr }`, and
//! `data`, row 0 at the top), `/n/data/title`, `/n/meta` (a `GwyContainer` of strings), and
//! when the channel has pixels without data, `/n/mask` (1 where the value is NaN).
//!
//! Pixels without data: Gwyddion's data fields must be finite (a NaN makes its range and
//! histogram undefined and it draws nothing), and its own importers mark missing data with a
//! mask. So a `.gwy` carries them the Gwyddion way: the mask `/n/mask` is 1 there (Gwyddion
//! draws it over the image and its tools exclude masked pixels), and the data field holds the
//! mean of the valid pixels underneath, as Gwyddion's importers do. The `.gsf` writer keeps
//! NaN itself (Gwyddion masks it on import).

use std::path::Path;

use crate::error::{Ctx, FormatError, Result};
use crate::model::{Channel, Direction, Format, SpmFile};

/// Magic at the start of every `.gwy` file.
pub(crate) const MAGIC: &[u8] = b"GWYP";

/// Components of one serialised object.
#[derive(Default)]
struct Object {
    body: Vec<u8>,
}

impl Object {
    fn name(&mut self, name: &str, kind: u8) {
        self.body.extend_from_slice(name.as_bytes());
        self.body.push(0);
        self.body.push(kind);
    }

    fn int(&mut self, name: &str, value: i32) {
        self.name(name, b'i');
        self.body.extend_from_slice(&value.to_le_bytes());
    }

    fn double(&mut self, name: &str, value: f64) {
        self.name(name, b'd');
        self.body.extend_from_slice(&value.to_le_bytes());
    }

    fn string(&mut self, name: &str, value: &str) {
        self.name(name, b's');
        // A NUL would end the string early: strings are written without them.
        self.body.extend(value.bytes().filter(|&b| b != 0));
        self.body.push(0);
    }

    fn object(&mut self, name: &str, type_name: &str, object: &Object) -> Result<()> {
        self.name(name, b'o');
        object.serialise_into(type_name, &mut self.body)
    }

    fn doubles(&mut self, name: &str, values: &[f64]) -> Result<()> {
        self.name(name, b'D');
        let n = u32::try_from(values.len()).map_err(|_| too_large("array"))?;
        self.body.extend_from_slice(&n.to_le_bytes());
        for v in values {
            self.body.extend_from_slice(&v.to_le_bytes());
        }
        Ok(())
    }

    fn serialise_into(&self, type_name: &str, out: &mut Vec<u8>) -> Result<()> {
        out.extend_from_slice(type_name.as_bytes());
        out.push(0);
        let size = u32::try_from(self.body.len()).map_err(|_| too_large("object"))?;
        out.extend_from_slice(&size.to_le_bytes());
        out.extend_from_slice(&self.body);
        Ok(())
    }
}

fn too_large(what: &str) -> FormatError {
    Ctx::new(Path::new("<gwy>")).invalid_input(format!("{what} larger than 4 GiB"))
}

fn si_unit(unit: &str) -> Object {
    let mut o = Object::default();
    o.string("unitstr", unit);
    o
}

fn data_field(channel: &Channel, values: &[f64], unit_z: &str, ctx: Ctx<'_>) -> Result<Object> {
    let (sx, sy) = match (channel.size_x_nm(), channel.size_y_nm()) {
        (Some(x), Some(y)) if x > 0.0 && y > 0.0 && x.is_finite() && y.is_finite() => (x, y),
        _ => return Err(ctx.invalid_input("the channel has no positive physical size")),
    };
    let xres = i32::try_from(channel.nx()).map_err(|_| ctx.invalid_input("too many columns"))?;
    let yres = i32::try_from(channel.ny()).map_err(|_| ctx.invalid_input("too many rows"))?;
    let mut f = Object::default();
    f.int("xres", xres);
    f.int("yres", yres);
    f.double("xreal", sx * 1e-9);
    f.double("yreal", sy * 1e-9);
    if let (Some(cx), Some(cy)) = (channel.center_x_nm(), channel.center_y_nm()) {
        f.double("xoff", (cx - sx / 2.0) * 1e-9);
        f.double("yoff", (cy - sy / 2.0) * 1e-9);
    }
    f.object("si_unit_xy", "GwySIUnit", &si_unit("m"))?;
    f.object("si_unit_z", "GwySIUnit", &si_unit(unit_z))?;
    f.doubles("data", values)?;
    Ok(f)
}

/// Encodes channels and their metadata as a `.gwy` file (see the module docs). `metadata` is
/// written for every channel (the source header and what was done to it). Infinite values are
/// refused; a NaN pixel (no data) is masked (see the module docs).
///
/// # Errors
/// [`crate::ErrorKind::InvalidInput`] for no channel, a channel without a positive physical
/// size, an infinite value, or a file over 4 GiB.
pub fn encode_gwy(channels: &[Channel], metadata: &[(String, String)]) -> Result<Vec<u8>> {
    let placeholder = crate::text::memory_path("gwy");
    encode_with_ctx(channels, metadata, Ctx::new(&placeholder))
}

fn encode_with_ctx(
    channels: &[Channel],
    metadata: &[(String, String)],
    ctx: Ctx<'_>,
) -> Result<Vec<u8>> {
    if channels.is_empty() {
        return Err(ctx.invalid_input("no channel to write"));
    }
    let mut container = Object::default();
    let mut meta = Object::default();
    for (k, v) in metadata {
        if k.is_empty() || k.contains('\0') {
            return Err(ctx.invalid_input(format!("metadata key {k:?} is empty or has a NUL")));
        }
        meta.string(k, v);
    }
    for (n, channel) in channels.iter().enumerate() {
        if let Some(i) = channel.data().iter().position(|v| v.is_infinite()) {
            return Err(ctx.invalid_input(format!(
                "channel {:?}: value {} at pixel {i} is infinite",
                channel.name(),
                channel.data()[i]
            )));
        }
        let title = match channel.direction() {
            Direction::Forward => channel.name().to_owned(),
            Direction::Backward => format!("{} (backward)", channel.name()),
        };
        let data = channel.data();
        let valid: Vec<f64> = data.iter().copied().filter(|v| v.is_finite()).collect();
        let mean = if valid.is_empty() {
            0.0
        } else {
            valid.iter().sum::<f64>() / valid.len() as f64
        };
        let values: Vec<f64> = data
            .iter()
            .map(|v| if v.is_nan() { mean } else { *v })
            .collect();
        let field = data_field(channel, &values, channel.unit(), ctx)?;
        container.object(&format!("/{n}/data"), "GwyDataField", &field)?;
        container.string(&format!("/{n}/data/title"), &title);
        container.object(&format!("/{n}/meta"), "GwyContainer", &meta)?;
        if valid.len() < data.len() {
            let mask: Vec<f64> = channel
                .data()
                .iter()
                .map(|v| if v.is_nan() { 1.0 } else { 0.0 })
                .collect();
            let mask_field = data_field(channel, &mask, "", ctx)?;
            container.object(&format!("/{n}/mask"), "GwyDataField", &mask_field)?;
        }
    }
    let mut out = MAGIC.to_vec();
    container.serialise_into("GwyContainer", &mut out)?;
    Ok(out)
}

/// Writes channels and metadata as a `.gwy` file (see [`encode_gwy`]).
///
/// # Errors
/// As [`encode_gwy`], and [`crate::ErrorKind::Io`] when the file cannot be written.
pub fn write_gwy(
    path: impl AsRef<Path>,
    channels: &[Channel],
    metadata: &[(String, String)],
) -> Result<()> {
    let path = path.as_ref();
    let bytes = encode_with_ctx(channels, metadata, Ctx::new(path))?;
    std::fs::write(path, bytes).map_err(|source| FormatError::Io {
        path: path.to_path_buf(),
        action: "cannot write",
        source,
    })
}

// ---------------------------------------------------------------------------------------
// Reading
// ---------------------------------------------------------------------------------------

/// Deepest nesting of objects a file may have (Gwyddion's own files nest 3–4 deep).
const MAX_DEPTH: usize = 32;

/// One component's value. Arrays of integers, characters, strings and objects are skipped
/// (checked, not kept): no channel needs them.
#[derive(Debug)]
enum Value {
    Int(i64),
    Double(f64),
    Str(String),
    Object(GwyObject),
    Doubles(Vec<f64>),
    Other,
}

/// A deserialised object: its type name and its components in file order.
#[derive(Debug)]
struct GwyObject {
    type_name: String,
    components: Vec<(String, Value)>,
}

impl GwyObject {
    fn get(&self, name: &str) -> Option<&Value> {
        self.components
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v)
    }

    fn int(&self, name: &str) -> Option<i64> {
        match self.get(name)? {
            Value::Int(v) => Some(*v),
            _ => None,
        }
    }

    fn double(&self, name: &str) -> Option<f64> {
        match self.get(name)? {
            Value::Double(v) => Some(*v),
            _ => None,
        }
    }

    fn string(&self, name: &str) -> Option<&str> {
        match self.get(name)? {
            Value::Str(v) => Some(v),
            _ => None,
        }
    }

    fn object(&self, name: &str) -> Option<&GwyObject> {
        match self.get(name)? {
            Value::Object(o) => Some(o),
            _ => None,
        }
    }

    /// The array of doubles `name`, moved out (an image's data need not be copied).
    fn take_doubles(&mut self, name: &str) -> Option<Vec<f64>> {
        self.components.iter_mut().find_map(|(n, v)| match v {
            Value::Doubles(d) if n == name => Some(std::mem::take(d)),
            _ => None,
        })
    }

    fn take_object(&mut self, name: &str) -> Option<GwyObject> {
        let i = self
            .components
            .iter()
            .position(|(n, v)| n == name && matches!(v, Value::Object(_)))?;
        match self.components.remove(i).1 {
            Value::Object(o) => Some(o),
            _ => None,
        }
    }
}

/// A cursor over the file's bytes, with the byte offset for errors.
struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
    ctx: Ctx<'a>,
}

impl Reader<'_> {
    fn take(&mut self, n: usize, field: &str) -> Result<&[u8]> {
        let s = self.ctx.slice(self.bytes, self.at, n, field)?;
        self.at += n;
        Ok(s)
    }

    /// A NUL-terminated UTF-8 string (its NUL consumed), no further than `end`.
    fn cstring(&mut self, end: usize, field: &str) -> Result<String> {
        let start = self.at;
        let rest = self.bytes.get(start..end).unwrap_or(&[]);
        let nul = rest.iter().position(|&b| b == 0).ok_or_else(|| {
            self.ctx.truncated(
                format!("{field} (NUL-terminated)"),
                start,
                rest.len() + 1,
                rest.len(),
            )
        })?;
        let text = std::str::from_utf8(&rest[..nul])
            .map_err(|_| self.ctx.encoding(field, start, "UTF-8"))?
            .to_owned();
        self.at = start + nul + 1;
        Ok(text)
    }

    fn u32(&mut self, field: &str) -> Result<u32> {
        let v = self.ctx.u32_le(self.bytes, self.at, field)?;
        self.at += 4;
        Ok(v)
    }

    /// An array's item count, checked against the bytes left before `end` (items of at least
    /// `item_bytes` each) before anything is allocated.
    fn count(&mut self, end: usize, item_bytes: usize, field: &str) -> Result<usize> {
        let n = self.u32(field)? as usize;
        let left = end.saturating_sub(self.at);
        if n.saturating_mul(item_bytes) > left {
            return Err(self.ctx.truncated(
                format!("{field} ({n} items)"),
                self.at,
                n.saturating_mul(item_bytes),
                left,
            ));
        }
        Ok(n)
    }

    /// One serialised object, which must end by `end`.
    fn object(&mut self, end: usize, depth: usize) -> Result<GwyObject> {
        if depth > MAX_DEPTH {
            return Err(self
                .ctx
                .invalid_data(self.at, format!("objects nested deeper than {MAX_DEPTH}")));
        }
        let type_name = self.cstring(end, "object type name")?;
        let size_at = self.at;
        let size = self.u32(&format!("{type_name} size"))? as usize;
        let body_end = self
            .at
            .checked_add(size)
            .filter(|&e| e <= end)
            .ok_or_else(|| {
                self.ctx.truncated(
                    format!("{type_name} components"),
                    size_at + 4,
                    size,
                    end.saturating_sub(size_at + 4),
                )
            })?;
        let mut components = Vec::new();
        while self.at < body_end {
            let name = self.cstring(body_end, &format!("{type_name} component name"))?;
            let kind_at = self.at;
            let kind = self.take(1, &format!("{type_name}.{name} type"))?[0];
            let field = format!("{type_name}.{name}");
            let value = match kind {
                b'b' | b'c' => {
                    self.take(1, &field)?;
                    Value::Other
                }
                b'i' => {
                    let s = self.take(4, &field)?;
                    Value::Int(i64::from(i32::from_le_bytes([s[0], s[1], s[2], s[3]])))
                }
                b'q' => {
                    let s = self.take(8, &field)?;
                    Value::Int(i64::from_le_bytes(s.try_into().unwrap_or([0; 8])))
                }
                b'd' => {
                    let s = self.take(8, &field)?;
                    Value::Double(f64::from_le_bytes(s.try_into().unwrap_or([0; 8])))
                }
                b's' => Value::Str(self.cstring(body_end, &field)?),
                b'o' => Value::Object(self.object(body_end, depth + 1)?),
                b'C' | b'I' | b'Q' => {
                    let item = match kind {
                        b'C' => 1,
                        b'I' => 4,
                        _ => 8,
                    };
                    let n = self.count(body_end, item, &field)?;
                    self.take(n * item, &field)?;
                    Value::Other
                }
                b'D' => {
                    let n = self.count(body_end, 8, &field)?;
                    let mut values = self.ctx.vec_with_capacity(n, &field)?;
                    let s = self.take(n * 8, &field)?;
                    values.extend(
                        s.chunks_exact(8)
                            .map(|c| f64::from_le_bytes(c.try_into().unwrap_or([0; 8]))),
                    );
                    Value::Doubles(values)
                }
                b'S' => {
                    let n = self.count(body_end, 1, &field)?;
                    for _ in 0..n {
                        self.cstring(body_end, &field)?;
                    }
                    Value::Other
                }
                b'O' => {
                    let n = self.count(body_end, 5, &field)?;
                    for _ in 0..n {
                        self.object(body_end, depth + 1)?;
                    }
                    Value::Other
                }
                other => {
                    return Err(self.ctx.invalid_data(
                        kind_at,
                        format!(
                            "component {field}: unknown type {:?} (Gwyddion's are b c i q d s o C I Q D S O)",
                            char::from(other)
                        ),
                    ));
                }
            };
            components.push((name, value));
        }
        Ok(GwyObject {
            type_name,
            components,
        })
    }
}

/// Parses a Gwyddion native file (see the module docs) into its image channels: every
/// `/N/data` data field of the top container, in channel order, titled by `/N/data/title`
/// (a title ending in " (backward)" or " (Backward)" is the backward half of the name
/// before it; " (Forward)" is stripped). Pixels under the channel's mask `/N/mask` (1) are
/// NaN, as in the file spmcal wrote. The header is the entries of the first channel's
/// `/N/meta` container (strings) in file order; spmcal's own keys in it (the scan angle, the
/// raster) are read by spmcal as from a `.gsf`. Other objects (graphs, volume data,
/// selections) are checked for their structure and skipped.
pub(crate) fn parse(bytes: &[u8], path: &Path) -> Result<SpmFile> {
    let ctx = Ctx::new(path);
    if !bytes.starts_with(MAGIC) {
        let shown = String::from_utf8_lossy(&bytes[..bytes.len().min(4)]).into_owned();
        return Err(ctx.bad_magic(Format::Gwy, format!("expected \"GWYP\", found {shown:?}")));
    }
    let mut reader = Reader {
        bytes,
        at: MAGIC.len(),
        ctx,
    };
    let mut top = reader.object(bytes.len(), 0)?;
    if top.type_name != "GwyContainer" {
        return Err(ctx.invalid(
            "top-level object",
            format!("a GwyContainer expected, found {:?}", top.type_name),
        ));
    }
    if reader.at != bytes.len() {
        return Err(ctx.invalid_data(
            reader.at,
            format!("{} bytes after the container", bytes.len() - reader.at),
        ));
    }
    let mut numbers: Vec<u64> = top
        .components
        .iter()
        .filter_map(|(name, _)| {
            name.strip_prefix('/')?
                .strip_suffix("/data")?
                .parse::<u64>()
                .ok()
        })
        .collect();
    numbers.sort_unstable();
    numbers.dedup();
    let mut channels = Vec::with_capacity(numbers.len());
    let mut header: Vec<(String, String)> = Vec::new();
    for n in numbers {
        let key = format!("/{n}/data");
        let Some(field) = top.take_object(&key) else {
            continue;
        };
        if field.type_name != "GwyDataField" {
            continue;
        }
        let mut data = read_field(&ctx, field, &key)?;
        if let Some(mask) = top.take_object(&format!("/{n}/mask")) {
            let mask = read_field(&ctx, mask, &format!("/{n}/mask"))?;
            if (mask.nx, mask.ny) != (data.nx, data.ny) {
                return Err(ctx.invalid(
                    format!("/{n}/mask"),
                    format!(
                        "{}×{} pixels against the data's {}×{}",
                        mask.nx, mask.ny, data.nx, data.ny
                    ),
                ));
            }
            for (v, &m) in data.values.iter_mut().zip(&mask.values) {
                if m > 0.5 {
                    *v = f64::NAN;
                }
            }
        }
        let title = top
            .string(&format!("/{n}/data/title"))
            .unwrap_or("Data")
            .trim();
        let (name, direction) = split_title(title);
        let mut channel = Channel::new(name, direction, data.z_unit, data.nx, data.ny, data.values)
            .map_err(|_| ctx.invalid(format!("{key}.xres/yres"), "grid does not match data"))?;
        if let Some([sx, sy, cx, cy]) = data.geometry_nm {
            channel = channel.with_size_nm(sx, sy).with_center_nm(cx, cy);
        }
        if header.is_empty()
            && let Some(meta) = top.object(&format!("/{n}/meta"))
        {
            for (k, v) in &meta.components {
                if let Value::Str(text) = v {
                    ctx.check_header_entries(header.len())?;
                    header.push((k.clone(), text.clone()));
                }
            }
        }
        channels.push(channel);
    }
    if channels.is_empty() {
        return Err(ctx.missing("/0/data (a GwyDataField: the file holds no image channel)"));
    }
    let angle = header
        .iter()
        .find(|(k, _)| k == crate::gsf::KEY_SCAN_ANGLE_CCW_DEG)
        .map(|(_, v)| {
            v.trim()
                .parse::<f64>()
                .ok()
                .filter(|a| a.is_finite())
                .ok_or_else(|| {
                    ctx.invalid(
                        crate::gsf::KEY_SCAN_ANGLE_CCW_DEG,
                        format!("{v:?} is not a number"),
                    )
                })
        })
        .transpose()?;
    if let Some(angle) = angle {
        channels = channels
            .into_iter()
            .map(|c| c.with_angle_deg(angle))
            .collect();
    }
    Ok(SpmFile {
        source: path.to_path_buf(),
        format: Format::Gwy,
        channels,
        header,
        scan_dir: None,
        line_time_s: None,
        recorded: None,
    })
}

/// A channel title's name and direction: "Z (backward)" (spmcal's), "Z (Backward)"
/// (Gwyddion's Nanonis importer) and "Topography [Left]" (its RHK importer: lines right to
/// left) are backward halves; "Z (Forward)" and "Topography [Right]" forward ones.
fn split_title(title: &str) -> (&str, Direction) {
    for (suffix, direction) in [
        (" (backward)", Direction::Backward),
        (" (Backward)", Direction::Backward),
        (" [Left]", Direction::Backward),
        (" (forward)", Direction::Forward),
        (" (Forward)", Direction::Forward),
        (" [Right]", Direction::Forward),
    ] {
        if let Some(name) = title.strip_suffix(suffix) {
            return (name, direction);
        }
    }
    (title, Direction::Forward)
}

/// What a `GwyDataField` holds.
struct Field {
    nx: usize,
    ny: usize,
    /// Row 0 at the top.
    values: Vec<f64>,
    z_unit: String,
    /// Size x, y and centre x, y in nm, when the lateral unit is a length.
    geometry_nm: Option<[f64; 4]>,
}

/// A `GwyDataField`: its grid, data (row 0 at the top), physical size and centre (lateral
/// unit metres, or a prefixed metre), and z unit.
fn read_field(ctx: &Ctx<'_>, mut field: GwyObject, key: &str) -> Result<Field> {
    let res = |name: &str| -> Result<u64> {
        let v = field
            .int(name)
            .ok_or_else(|| ctx.missing(format!("{key}.{name}")))?;
        u64::try_from(v)
            .map_err(|_| ctx.invalid(format!("{key}.{name}"), format!("{v} is negative")))
    };
    let (xres, yres) = (res("xres")?, res("yres")?);
    let Some(values) = field.take_doubles("data") else {
        return Err(ctx.missing(format!("{key}.data (an array of doubles)")));
    };
    let (nx, ny) = ctx.check_grid(
        &format!("{key}.xres/yres"),
        xres,
        yres,
        1,
        8,
        (0, values.len().saturating_mul(8)),
    )?;
    if values.len() != nx * ny {
        return Err(ctx.invalid(
            format!("{key}.data"),
            format!("{} values for {nx}×{ny} pixels", values.len()),
        ));
    }
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(ctx.invalid(
            format!("{key}.data"),
            format!(
                "value {} at pixel {i} is not finite (Gwyddion's data fields are finite; \
                 missing data is masked)",
                values[i]
            ),
        ));
    }
    let unit = |name: &str| {
        field
            .object(name)
            .and_then(|u| u.string("unitstr"))
            .unwrap_or("")
            .to_owned()
    };
    let real = |name: &str| -> Result<Option<f64>> {
        match field.double(name) {
            Some(v) if v.is_finite() => Ok(Some(v)),
            Some(v) => Err(ctx.invalid(format!("{key}.{name}"), format!("{v} is not finite"))),
            None => Ok(None),
        }
    };
    let (xreal, yreal) = (real("xreal")?.unwrap_or(1.0), real("yreal")?.unwrap_or(1.0));
    if !(xreal > 0.0 && yreal > 0.0) {
        return Err(ctx.invalid(
            format!("{key}.xreal/yreal"),
            format!("physical size {xreal} × {yreal} must be positive"),
        ));
    }
    let (xoff, yoff) = (real("xoff")?.unwrap_or(0.0), real("yoff")?.unwrap_or(0.0));
    let geometry_nm = crate::text::length_unit_to_nm(&unit("si_unit_xy")).map(|f| {
        [
            xreal * f,
            yreal * f,
            (xoff + xreal / 2.0) * f,
            (yoff + yreal / 2.0) * f,
        ]
    });
    Ok(Field {
        nx,
        ny,
        values,
        z_unit: unit("si_unit_z"),
        geometry_nm,
    })
}
