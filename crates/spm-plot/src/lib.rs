//! The workspace's one plotting stack: [plotters] drawing into an RGB buffer, encoded as PNG.
//!
//! - [`register_fonts`]: DejaVu Sans, embedded (the `dejavu` crate), registered once with
//!   plotters, so every figure has text on every machine, with or without system fonts.
//! - [`ColorMap`]: sequential and diverging colour maps from `colorous` (the d3 /
//!   matplotlib schemes), plus the categorical palette [`category_colour`].
//! - Figures with a title, axes naming quantity and unit, tick labels and colour bars:
//!   [`surface_map`] (a fitted surface with the measured node values on it and their
//!   residuals below it), [`xy_chart`] (lines and markers, linear or logarithmic y),
//!   [`category_chart`] (one marker per series and category on a categorical axis) and
//!   [`field_maps`] (quantities over a field, stacked, e.g. a surface's uncertainty),
//!   [`order_map`] (small multiples of points joined in order, coloured by their index),
//!   and [`running_quantiles`] (a running median and spread of a cloud too dense to draw).
//! - [`render_png`] / [`write_png`]: an SPM [`spm_formats::Channel`] as a height image with
//!   a colour map and a labelled scale bar.
//!
//! Every function returns the PNG bytes (for files and for the HTML report's data URIs);
//! nothing panics on data: non-finite values are skipped, empty inputs are [`PlotError`]s.
#![doc = include_str!("../README.md")]

mod channel;
mod charts;
mod colour;
mod font;
mod panels;

pub use channel::{PngOptions, render_png, write_png};
pub use charts::{
    CategoryFigure, CategorySeries, FieldFigure, FieldPanel, IMAGE_PAIR_PX, ImagePairFigure,
    ImagePanel, MAP_HEIGHT_PX, MAP_WIDTH_PX, MIN_FONT_PX, MapFigure, MapNode, ORDER_COLUMNS,
    OrderFigure, OrderPanel, Series, SeriesStyle, XyFigure, category_chart, cell_centres,
    field_maps, image_pair, order_map, running_quantiles, surface_map, xy_chart,
};
pub use colour::{ColorMap, category_colour};
pub use font::{FONT_FAMILY, register_fonts};
pub use panels::{PanelGrid, XyPanel, panel_grid};

/// Why a figure could not be drawn or written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PlotError {
    /// The embedded font could not be registered with plotters.
    #[error("registering the embedded DejaVu Sans font: {0}")]
    Font(String),
    /// Drawing failed (plotters' backend).
    #[error("drawing {figure}: {message}")]
    Draw {
        /// The figure's title or file.
        figure: String,
        /// Why.
        message: String,
    },
    /// Nothing to draw (no finite value).
    #[error("{figure}: no finite values to draw")]
    Empty {
        /// The figure's title.
        figure: String,
    },
    /// The figure's size is not acceptable.
    #[error("{figure}: image {width}×{height} exceeds 32768 px per side or 2^26 pixels")]
    TooLarge {
        /// The figure.
        figure: String,
        /// Width, pixels.
        width: usize,
        /// Height, pixels.
        height: usize,
    },
    /// PNG encoding failed.
    #[error("{figure}: PNG encoding failed: {message}")]
    Encode {
        /// The figure.
        figure: String,
        /// Why.
        message: String,
    },
    /// Writing the file failed.
    #[error("{path}: cannot write: {source}")]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// Why.
        source: std::io::Error,
    },
}

/// Largest figure side, pixels.
const MAX_SIDE: usize = 1 << 15;
/// Largest figure, pixels.
const MAX_PIXELS: usize = 1 << 26;

/// Encodes an RGB buffer as PNG.
pub(crate) fn encode_png(
    figure: &str,
    width: usize,
    height: usize,
    rgb: &[u8],
) -> Result<Vec<u8>, PlotError> {
    let err = |e: png::EncodingError| PlotError::Encode {
        figure: figure.to_owned(),
        message: e.to_string(),
    };
    let mut out = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut out, width as u32, height as u32);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(err)?;
        writer.write_image_data(rgb).map_err(err)?;
        writer.finish().map_err(err)?;
    }
    Ok(out)
}

/// Checks a figure's size before allocating its buffer.
pub(crate) fn check_size(figure: &str, width: usize, height: usize) -> Result<(), PlotError> {
    if width == 0
        || height == 0
        || width > MAX_SIDE
        || height > MAX_SIDE
        || width.saturating_mul(height) > MAX_PIXELS
    {
        return Err(PlotError::TooLarge {
            figure: figure.to_owned(),
            width,
            height,
        });
    }
    Ok(())
}

/// Writes PNG bytes to `path`.
///
/// # Errors
/// [`PlotError::Io`] when the file cannot be written.
pub fn write_file(path: &std::path::Path, bytes: &[u8]) -> Result<(), PlotError> {
    std::fs::write(path, bytes).map_err(|source| PlotError::Io {
        path: path.to_path_buf(),
        source,
    })
}
