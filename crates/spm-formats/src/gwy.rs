//! Gwyddion native file (`.gwy`) writer: every channel and its metadata in one file.
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
use crate::model::{Channel, Direction};

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
