//! The embedded font, registered with plotters once per process.

use crate::PlotError;
use plotters::style::FontStyle;
use std::sync::OnceLock;

/// The family name every figure uses.
pub const FONT_FAMILY: &str = "sans-serif";

/// Registers DejaVu Sans (regular and bold, embedded by the `dejavu` crate; the Bitstream
/// Vera / DejaVu licence permits embedding) as plotters' `sans-serif`, once per process.
/// Every figure function calls it; callers drawing with plotters directly call it first.
///
/// # Errors
/// [`PlotError::Font`] when plotters rejects the font bytes.
pub fn register_fonts() -> Result<(), PlotError> {
    static REGISTERED: OnceLock<Result<(), String>> = OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            plotters::style::register_font(FONT_FAMILY, FontStyle::Normal, dejavu::sans::regular())
                .map_err(|_| "DejaVu Sans regular is not a valid font".to_owned())?;
            plotters::style::register_font(FONT_FAMILY, FontStyle::Bold, dejavu::sans::bold())
                .map_err(|_| "DejaVu Sans bold is not a valid font".to_owned())
        })
        .clone()
        .map_err(PlotError::Font)
}
