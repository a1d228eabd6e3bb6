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
        "um" | "µm" | "μm" => Some(1e3),
        "nm" => Some(1.0),
        "pm" => Some(1e-3),
        "A" | "\u{c5}" | "\u{212b}" | "Angstrom" => Some(0.1),
        _ => None,
    }
}

/// Converts a value in `unit` to SI when `unit` is a length with a prefix; returns the SI
/// unit and the factor. Other units are kept as they are.
pub(crate) fn to_si(unit: &str) -> (String, f64) {
    match length_unit_to_nm(unit) {
        // "A" is ambiguous (ampere or ångström); as a value unit it means ampere.
        Some(_) if unit.trim() == "A" => ("A".to_string(), 1.0),
        Some(nm) => ("m".to_string(), nm * 1e-9),
        None => (unit.trim().to_string(), 1.0),
    }
}

/// Placeholder path for in-memory encoders.
pub(crate) fn memory_path(what: &str) -> std::path::PathBuf {
    Path::new(&format!("<{what}>")).to_path_buf()
}
