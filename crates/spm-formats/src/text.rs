//! Small text helpers shared by the readers.

use std::path::Path;

use crate::error::{Ctx, Result};

/// `bytes` as UTF-8, or an `Encoding` error at the first bad byte (offset relative to `base`).
pub(crate) fn utf8<'b>(ctx: Ctx<'_>, bytes: &'b [u8], field: &str, base: usize) -> Result<&'b str> {
    std::str::from_utf8(bytes)
        .map_err(|e| ctx.encoding(field, base.saturating_add(e.valid_up_to()), "UTF-8"))
}

/// A finite float, or an `InvalidField` error naming `field`.
pub(crate) fn parse_f64(ctx: Ctx<'_>, field: &str, s: &str) -> Result<f64> {
    let t = s.trim();
    match t.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(ctx.invalid(field, format!("expected a finite number, found {t:?}"))),
    }
}

/// An unsigned integer, or an `InvalidField` error naming `field`.
pub(crate) fn parse_u64(ctx: Ctx<'_>, field: &str, s: &str) -> Result<u64> {
    let t = s.trim();
    t.parse::<u64>().map_err(|_| {
        ctx.invalid(
            field,
            format!("expected a non-negative integer, found {t:?}"),
        )
    })
}

/// Factor converting a length unit to nm, for the units SPM files use.
pub(crate) fn length_unit_to_nm(unit: &str) -> Option<f64> {
    match unit.trim() {
        "m" => Some(1e9),
        "mm" => Some(1e6),
        "um" | "\u{b5}m" | "\u{3bc}m" => Some(1e3),
        "nm" => Some(1.0),
        "pm" => Some(1e-3),
        "A" | "\u{c5}" | "\u{212b}" | "Angstrom" => Some(0.1),
        _ => None,
    }
}

/// For a prefixed length unit, the SI unit ("m") and the divisor taking a value to metres
/// (dividing by a power of ten rounds correctly where multiplying by 1e-9 would not).
/// Other units are kept as they are, with divisor 1.
pub(crate) fn to_si(unit: &str) -> (String, f64) {
    let divisor = match unit.trim() {
        "m" => Some(1.0),
        "mm" => Some(1e3),
        "um" | "\u{b5}m" | "\u{3bc}m" => Some(1e6),
        "nm" => Some(1e9),
        "pm" => Some(1e12),
        // "A" as a value unit means ampere; only the explicit spellings mean ångström.
        "\u{c5}" | "\u{212b}" | "Angstrom" => Some(1e10),
        _ => None,
    };
    match divisor {
        Some(d) => ("m".to_string(), d),
        None => (unit.trim().to_string(), 1.0),
    }
}

/// Placeholder path for in-memory encoders.
pub(crate) fn memory_path(what: &str) -> std::path::PathBuf {
    Path::new(&format!("<{what}>")).to_path_buf()
}
