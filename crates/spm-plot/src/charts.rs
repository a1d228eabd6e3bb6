//! Figures with a title, axes naming quantity and unit, tick labels and colour bars.

use crate::colour::{ColorMap, category_colour};
use crate::font::{FONT_FAMILY, register_fonts};
use crate::{PlotError, check_size, encode_png};
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

pub(crate) type Area<'a> = DrawingArea<BitMapBackend<'a>, Shift>;

pub(crate) const TITLE_PX: u32 = 22;
pub(crate) const LABEL_PX: u32 = 18;
pub(crate) const TICK_PX: u32 = 16;
/// The smallest text any chart of this crate draws, pixels of the PNG (the tick labels): at
/// a display width w of a figure W pixels wide it reads at `MIN_FONT_PX × w / W` px.
pub const MIN_FONT_PX: u32 = TICK_PX;

/// Draws with `draw` on a white `width`×`height` canvas and returns the PNG.
pub(crate) fn figure(
    title: &str,
    width: u32,
    height: u32,
    draw: impl FnOnce(&Area<'_>) -> Result<(), PlotError>,
) -> Result<Vec<u8>, PlotError> {
    register_fonts()?;
    let (w, h) = (width as usize, height as usize);
    check_size(title, w, h)?;
    let mut rgb = vec![255u8; w * h * 3];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| draw_error(title, e))?;
        draw(&root)?;
        root.present().map_err(|e| draw_error(title, e))?;
    }
    encode_png(title, w, h, &rgb)
}

pub(crate) fn draw_error(figure: &str, e: impl std::fmt::Display) -> PlotError {
    PlotError::Draw {
        figure: figure.to_owned(),
        message: e.to_string(),
    }
}

/// A tick label with as many decimals as the tick spacing needs (no `0.30000000000000004`).
pub(crate) fn tick_label(v: f64, step: f64) -> String {
    if !v.is_finite() {
        return String::new();
    }
    // A tick at a rounding error from 0 is 0.
    let v = if step > 0.0 && v.abs() < step * 1e-6 {
        0.0
    } else {
        v
    };
    let a = v.abs();
    if a != 0.0 && !(1e-3..1e5).contains(&a) {
        return format!("{v:.1e}");
    }
    let decimals = if step > 0.0 && step.is_finite() {
        (-step.log10().floor()).clamp(0.0, 6.0) as usize
    } else {
        3
    };
    let s = format!("{v:.decimals$}");
    if s.starts_with('-') && s[1..].chars().all(|c| c == '0' || c == '.') {
        s[1..].to_owned()
    } else {
        s
    }
}

/// A tick label of a logarithmic axis: the decimals its decade needs (1, 10, 0.5, 0.02).
pub(crate) fn log_tick_label(v: f64) -> String {
    if !(v.is_finite() && v > 0.0) {
        return String::new();
    }
    if !(1e-4..1e7).contains(&v) {
        return format!("{v:.0e}");
    }
    let decimals = (-v.log10().floor()).max(0.0) as usize;
    format!("{v:.decimals$}")
}

/// A logarithmic range around [lo, hi] with head-room at the top for a legend of `rows`
/// entries (the legend takes about 5.5 % of the plot's height per entry).
fn log_range_with_legend(lo: f64, hi: f64, rows: usize) -> (f64, f64) {
    let (lo, hi) = (lo / 1.3, hi * 1.3);
    let span = (hi / lo).log10().max(0.3);
    let f = (0.04 + 0.055 * rows as f64).min(0.6);
    (lo, hi * 10f64.powf(span * f / (1.0 - f)))
}

/// The finite (min, max) of `values`, widened when degenerate; `None` when none is finite.
pub(crate) fn finite_range(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if !(lo.is_finite() && hi.is_finite()) {
        return None;
    }
    if hi - lo <= 1e-12 * lo.abs().max(hi.abs()).max(1e-300) {
        let pad = if lo == 0.0 { 1.0 } else { lo.abs() * 1e-3 };
        return Some((lo - pad, hi + pad));
    }
    Some((lo, hi))
}

pub(crate) fn pad_range((lo, hi): (f64, f64), fraction: f64) -> (f64, f64) {
    let pad = (hi - lo) * fraction;
    (lo - pad, hi + pad)
}

/// Approximate tick step plotters uses for `n` ticks over `range` (for label decimals).
pub(crate) fn step_of((lo, hi): (f64, f64), n: usize) -> f64 {
    let raw = (hi - lo) / n.max(1) as f64;
    if !(raw > 0.0 && raw.is_finite()) {
        return 1.0;
    }
    let p = 10f64.powf(raw.log10().floor());
    let m = raw / p;
    let f = if m >= 5.0 {
        5.0
    } else if m >= 2.0 {
        2.0
    } else {
        1.0
    };
    f * p
}

/// Width of a colour bar's strip (bar, tick labels, rotated label), pixels.
const BAR_PX: u32 = 130;

/// A vertical colour bar of `map` over `range` in `area`, its `label` drawn rotated at the
/// area's right edge, inside the area (plotters' `y_desc` of a right-hand axis lands outside
/// it, beside the next panel).
fn colour_bar(
    area: &Area<'_>,
    figure: &str,
    map: ColorMap,
    range: (f64, f64),
    label: &str,
) -> Result<(), PlotError> {
    let step = step_of(range, 8);
    let (w, h) = area.dim_in_pixel();
    let label_px = LABEL_PX + 6;
    let (bar_area, label_area) = area.split_horizontally(w.saturating_sub(label_px) as i32);
    label_area
        .draw(&Text::new(
            label.to_owned(),
            ((label_px / 2) as i32, (h / 2) as i32),
            (FONT_FAMILY, LABEL_PX)
                .into_font()
                .transform(FontTransform::Rotate270)
                .into_text_style(&label_area)
                .pos(Pos::new(HPos::Center, VPos::Center)),
        ))
        .map_err(|e| draw_error(figure, e))?;
    let mut chart = ChartBuilder::on(&bar_area)
        .margin_top(30)
        .margin_bottom(55)
        .margin_left(4)
        .margin_right(2)
        .right_y_label_area_size(62)
        .build_cartesian_2d(0.0..1.0, range.0..range.1)
        .map_err(|e| draw_error(figure, e))?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .disable_y_mesh()
        .disable_x_axis()
        .y_labels(8)
        .y_label_formatter(&|v| tick_label(*v, step))
        .label_style((FONT_FAMILY, TICK_PX))
        .draw()
        .map_err(|e| draw_error(figure, e))?;
    const STEPS: usize = 200;
    let span = range.1 - range.0;
    chart
        .draw_series((0..STEPS).map(|k| {
            let t0 = k as f64 / STEPS as f64;
            let t1 = (k + 1) as f64 / STEPS as f64;
            Rectangle::new(
                [(0.0, range.0 + t0 * span), (1.0, range.0 + t1 * span)],
                map.colour(0.5 * (t0 + t1)).filled(),
            )
        }))
        .map_err(|e| draw_error(figure, e))?;
    chart
        .draw_series(std::iter::once(Rectangle::new(
            [(0.0, range.0), (1.0, range.1)],
            BLACK.stroke_width(1),
        )))
        .map_err(|e| draw_error(figure, e))?;
    Ok(())
}

/// One measured node on a [`MapFigure`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapNode {
    /// x, the figure's x unit.
    pub x: f64,
    /// y, the figure's y unit.
    pub y: f64,
    /// The measured value, the figure's value unit.
    pub value: f64,
    /// Which visit of its place this is, 0-based (e.g. the pass over the net): visits of one
    /// place are drawn as concentric discs, the first outermost, so that none hides another.
    pub visit: u32,
}

/// A fitted surface over a rectangle with the measured node values on it (top panel:
/// surface as a colour map, nodes as discs filled with their measured value on the same
/// scale), and the residual of each node, measured − surface, on a diverging scale (bottom
/// panel).
pub struct MapFigure<'a> {
    /// Title (quantity, fit summary).
    pub title: &'a str,
    /// x axis: quantity, unit.
    pub x_label: &'a str,
    /// y axis: quantity, unit.
    pub y_label: &'a str,
    /// x range drawn.
    pub x_range: (f64, f64),
    /// y range drawn.
    pub y_range: (f64, f64),
    /// The surface, in the value unit.
    pub surface: &'a dyn Fn(f64, f64) -> f64,
    /// Measured nodes.
    pub nodes: &'a [MapNode],
    /// The value: quantity, unit (the colour bar's label).
    pub value_label: &'a str,
    /// The residual: quantity, unit.
    pub residual_label: &'a str,
    /// Colour map of the surface.
    pub map: ColorMap,
}

type MapChart<'a, 'b> =
    ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// A field panel's axes: labels and ranges.
struct FieldAxes<'a> {
    x_label: &'a str,
    y_label: &'a str,
    x_range: (f64, f64),
    y_range: (f64, f64),
}

fn map_panel<'a, 'b: 'a>(
    area: &'a Area<'b>,
    caption: &str,
    axes: &FieldAxes<'_>,
    title: &str,
) -> Result<MapChart<'a, 'b>, PlotError> {
    let (x0, x1) = axes.x_range;
    let (y0, y1) = axes.y_range;
    let mut chart = ChartBuilder::on(area)
        .caption(caption, (FONT_FAMILY, LABEL_PX))
        .margin(8)
        .x_label_area_size(50)
        .y_label_area_size(78)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(|e| draw_error(title, e))?;
    let (sx, sy) = (step_of((x0, x1), 6), step_of((y0, y1), 6));
    chart
        .configure_mesh()
        .x_labels(6)
        .y_labels(6)
        .x_label_formatter(&|v| tick_label(*v, sx))
        .y_label_formatter(&|v| tick_label(*v, sy))
        .x_desc(axes.x_label)
        .y_desc(axes.y_label)
        .label_style((FONT_FAMILY, TICK_PX))
        .axis_desc_style((FONT_FAMILY, LABEL_PX))
        .light_line_style(WHITE.mix(0.0))
        .draw()
        .map_err(|e| draw_error(title, e))?;
    Ok(chart)
}

/// Cells per side of the surface raster.
const MAP_CELLS: usize = 120;

/// Size of a [`surface_map`], pixels: two panels stacked, each the full width.
pub const MAP_WIDTH_PX: u32 = 960;
/// Height of a [`surface_map`], pixels.
pub const MAP_HEIGHT_PX: u32 = 1100;

/// Draws a [`MapFigure`], [`MAP_WIDTH_PX`]×[`MAP_HEIGHT_PX`]: the surface with the nodes on
/// top, the residuals below.
///
/// # Errors
/// [`PlotError::Empty`] when the surface has no finite value over the range.
pub fn surface_map(f: &MapFigure<'_>) -> Result<Vec<u8>, PlotError> {
    let (x0, x1) = f.x_range;
    let (y0, y1) = f.y_range;
    if !(x1 > x0 && y1 > y0) {
        return Err(PlotError::Empty {
            figure: f.title.to_owned(),
        });
    }
    let cell = |i: usize, lo: f64, hi: f64| lo + (hi - lo) * (i as f64 + 0.5) / MAP_CELLS as f64;
    let mut grid = Vec::with_capacity(MAP_CELLS * MAP_CELLS);
    for j in 0..MAP_CELLS {
        for i in 0..MAP_CELLS {
            let (x, y) = (cell(i, x0, x1), cell(j, y0, y1));
            grid.push((i, j, (f.surface)(x, y)));
        }
    }
    let range = finite_range(
        grid.iter()
            .map(|g| g.2)
            .chain(f.nodes.iter().map(|n| n.value)),
    )
    .ok_or_else(|| PlotError::Empty {
        figure: f.title.to_owned(),
    })?;
    let residuals: Vec<(f64, f64, f64, u32)> = f
        .nodes
        .iter()
        .map(|n| (n.x, n.y, n.value - (f.surface)(n.x, n.y), n.visit))
        .filter(|r| r.0.is_finite() && r.1.is_finite() && r.2.is_finite())
        .collect();
    let r_max = residuals
        .iter()
        .fold(0.0f64, |m, r| m.max(r.2.abs()))
        .max(1e-12 * range.1.abs().max(range.0.abs()).max(1e-300));
    let r_range = (-r_max, r_max);
    let t = |v: f64| (v - range.0) / (range.1 - range.0);
    let tr = |v: f64| (v - r_range.0) / (r_range.1 - r_range.0);
    let title = f.title;
    figure(title, MAP_WIDTH_PX, MAP_HEIGHT_PX, |root| {
        let body = root
            .titled(
                title,
                (FONT_FAMILY, TITLE_PX).into_font().style(FontStyle::Bold),
            )
            .map_err(|e| draw_error(title, e))?;
        let (_, body_h) = body.dim_in_pixel();
        // Stacked, not side by side: each panel gets the figure's full width, so its text
        // stays readable when the page shrinks the figure.
        let (top, bottom) = body.split_vertically((body_h / 2) as i32);
        let bar_at = (MAP_WIDTH_PX - BAR_PX) as i32;
        let (map_area, bar_area) = top.split_horizontally(bar_at);
        let (res_area, res_bar_area) = bottom.split_horizontally(bar_at);

        let axes = FieldAxes {
            x_label: f.x_label,
            y_label: f.y_label,
            x_range: f.x_range,
            y_range: f.y_range,
        };
        let panel = |area, caption| map_panel(area, caption, &axes, title);

        // Top: the surface with the measured nodes on the same scale.
        let mut chart = panel(
            &map_area,
            "fitted surface; discs: measured node values, same scale",
        )?;
        let (dx, dy) = ((x1 - x0) / MAP_CELLS as f64, (y1 - y0) / MAP_CELLS as f64);
        chart
            .draw_series(grid.iter().filter(|g| g.2.is_finite()).map(|&(i, j, v)| {
                let (x, y) = (x0 + dx * i as f64, y0 + dy * j as f64);
                Rectangle::new([(x, y), (x + dx, y + dy)], f.map.colour(t(v)).filled())
            }))
            .map_err(|e| draw_error(title, e))?;
        let nodes = f
            .nodes
            .iter()
            .filter(|n| n.x.is_finite() && n.y.is_finite() && n.value.is_finite())
            .map(|n| (n.x, n.y, f.map.colour(t(n.value)), n.visit));
        draw_discs(&mut chart, title, nodes)?;
        colour_bar(&bar_area, title, f.map, range, f.value_label)?;

        // Bottom: the residuals on a diverging scale.
        let mut chart = panel(&res_area, "residual of each measured node")?;
        let discs = residuals
            .iter()
            .map(|r| (r.0, r.1, ColorMap::Diverging.colour(tr(r.2)), r.3));
        draw_discs(&mut chart, title, discs)?;
        colour_bar(
            &res_bar_area,
            title,
            ColorMap::Diverging,
            r_range,
            f.residual_label,
        )
    })
}

/// Radius of a place's first visit's disc, pixels; each later visit's is
/// [`DISC_STEP_PX`] smaller, down to [`DISC_MIN_PX`].
const DISC_PX: i32 = 12;
/// Radius step between the concentric discs of successive visits, pixels.
const DISC_STEP_PX: i32 = 4;
/// Smallest disc radius, pixels.
const DISC_MIN_PX: i32 = 3;

/// Discs filled with their colour, the outermost with a thin dark outline (no white ring:
/// the fill is the value); visit k of a place is drawn k·[`DISC_STEP_PX`] smaller, on top
/// of the earlier ones, so repeated visits show as concentric rings.
fn draw_discs<'a, 'b: 'a>(
    chart: &mut MapChart<'a, 'b>,
    title: &str,
    discs: impl Iterator<Item = (f64, f64, RGBColor, u32)> + Clone,
) -> Result<(), PlotError> {
    let mut visits: Vec<u32> = discs.clone().map(|d| d.3).collect();
    visits.sort_unstable();
    visits.dedup();
    let first = visits.first().copied();
    for visit in visits {
        let radius = (DISC_PX - DISC_STEP_PX * visit.min(16) as i32).max(DISC_MIN_PX);
        let these = discs.clone().filter(move |d| d.3 == visit);
        chart
            .draw_series(
                these
                    .clone()
                    .map(move |(x, y, c, _)| Circle::new((x, y), radius, c.filled())),
            )
            .map_err(|e| draw_error(title, e))?;
        if Some(visit) != first {
            continue;
        }
        chart
            .draw_series(these.map(move |(x, y, _, _)| {
                Circle::new((x, y), radius, RGBColor(40, 40, 40).stroke_width(1))
            }))
            .map_err(|e| draw_error(title, e))?;
    }
    Ok(())
}

/// The centres of `cells`×`cells` equal cells over a rectangle, row by row from the
/// smallest y, each row from the smallest x: where a [`FieldPanel`]'s values belong.
pub fn cell_centres(x_range: (f64, f64), y_range: (f64, f64), cells: usize) -> Vec<(f64, f64)> {
    let at = |i: usize, (lo, hi): (f64, f64)| lo + (hi - lo) * (i as f64 + 0.5) / cells as f64;
    (0..cells)
        .flat_map(|j| (0..cells).map(move |i| (at(i, x_range), at(j, y_range))))
        .collect()
}

/// One panel of a [`FieldFigure`]: a quantity over the field.
pub struct FieldPanel<'a> {
    /// The panel's caption.
    pub caption: &'a str,
    /// The value at each of the figure's [`cell_centres`], in order, the value unit.
    pub values: &'a [f64],
    /// The value: quantity, unit (the colour bar's label).
    pub value_label: &'a str,
}

/// Maps of quantities over one rectangle, stacked, each with its colour bar, and the
/// points the quantities were derived from as small dots (e.g. the records a surface was
/// fitted from).
pub struct FieldFigure<'a> {
    /// Title.
    pub title: &'a str,
    /// x axis: quantity, unit.
    pub x_label: &'a str,
    /// y axis: quantity, unit.
    pub y_label: &'a str,
    /// x range drawn.
    pub x_range: (f64, f64),
    /// y range drawn.
    pub y_range: (f64, f64),
    /// Cells per side of every panel's values.
    pub cells: usize,
    /// The panels, top to bottom.
    pub panels: &'a [FieldPanel<'a>],
    /// Points drawn as dots on every panel.
    pub points: &'a [(f64, f64)],
    /// Colour map.
    pub map: ColorMap,
    /// Every panel on one colour scale (the union of their ranges: panels of one quantity to
    /// compare, e.g. before and after a correction); else each panel on its own.
    pub shared_scale: bool,
}

/// Height of one panel of a [`field_maps`] figure, pixels.
const FIELD_PANEL_PX: u32 = 420;

/// Draws a [`FieldFigure`], [`MAP_WIDTH_PX`] wide, 420 pixels high per panel.
///
/// # Errors
/// [`PlotError::Empty`] when there is no panel, a panel has no finite value or not one value
/// per cell, or the rectangle has no area.
pub fn field_maps(f: &FieldFigure<'_>) -> Result<Vec<u8>, PlotError> {
    let title = f.title;
    let empty = || PlotError::Empty {
        figure: title.to_owned(),
    };
    let (x0, x1) = f.x_range;
    let (y0, y1) = f.y_range;
    if f.panels.is_empty() || f.cells == 0 || !(x1 > x0 && y1 > y0) {
        return Err(empty());
    }
    let ranges = f
        .panels
        .iter()
        .map(|p| {
            if p.values.len() != f.cells * f.cells {
                return None;
            }
            finite_range(p.values.iter().copied())
        })
        .collect::<Option<Vec<_>>>()
        .ok_or_else(empty)?;
    let ranges = if f.shared_scale {
        let union = ranges
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), r| {
                (lo.min(r.0), hi.max(r.1))
            });
        vec![union; ranges.len()]
    } else {
        ranges
    };
    let height = 40 + FIELD_PANEL_PX * f.panels.len() as u32;
    figure(title, MAP_WIDTH_PX, height, |root| {
        let body = root
            .titled(
                title,
                (FONT_FAMILY, TITLE_PX).into_font().style(FontStyle::Bold),
            )
            .map_err(|e| draw_error(title, e))?;
        let rows = body.split_evenly((f.panels.len(), 1));
        let axes = FieldAxes {
            x_label: f.x_label,
            y_label: f.y_label,
            x_range: f.x_range,
            y_range: f.y_range,
        };
        let (dx, dy) = ((x1 - x0) / f.cells as f64, (y1 - y0) / f.cells as f64);
        for ((panel, range), row) in f.panels.iter().zip(&ranges).zip(&rows) {
            let (map_area, bar_area) = row.split_horizontally((MAP_WIDTH_PX - BAR_PX) as i32);
            let mut chart = map_panel(&map_area, panel.caption, &axes, title)?;
            let t = |v: f64| (v - range.0) / (range.1 - range.0);
            chart
                .draw_series(
                    panel
                        .values
                        .iter()
                        .enumerate()
                        .filter(|(_, v)| v.is_finite())
                        .map(|(k, &v)| {
                            let (i, j) = (k % f.cells, k / f.cells);
                            let (x, y) = (x0 + dx * i as f64, y0 + dy * j as f64);
                            Rectangle::new([(x, y), (x + dx, y + dy)], f.map.colour(t(v)).filled())
                        }),
                )
                .map_err(|e| draw_error(title, e))?;
            chart
                .draw_series(
                    f.points
                        .iter()
                        .filter(|p| p.0.is_finite() && p.1.is_finite())
                        .map(|&p| Circle::new(p, 2, RGBColor(30, 30, 30).filled())),
                )
                .map_err(|e| draw_error(title, e))?;
            colour_bar(&bar_area, title, f.map, *range, panel.value_label)?;
        }
        Ok(())
    })
}

/// One image of an [`ImagePairFigure`]: values on a uniform grid.
pub struct ImagePanel<'a> {
    /// The panel's caption.
    pub caption: &'a str,
    /// Columns (x).
    pub columns: usize,
    /// Rows (y), row 0 at the smallest y.
    pub rows: usize,
    /// Position of column 0, row 0 (the pixel's centre), axis unit.
    pub origin: (f64, f64),
    /// Pixel spacing along both axes, axis unit.
    pub step: f64,
    /// Values, `[row * columns + column]`; NaN pixels are left white.
    pub values: &'a [f64],
}

/// Two images side by side on one colour scale with one colour bar (e.g. an image before
/// and after a correction), each panel square in its axis unit.
pub struct ImagePairFigure<'a> {
    /// Title.
    pub title: &'a str,
    /// x axis: quantity, unit.
    pub x_label: &'a str,
    /// y axis: quantity, unit.
    pub y_label: &'a str,
    /// The two images, left then right.
    pub panels: [ImagePanel<'a>; 2],
    /// The value: quantity, unit (the colour bar's label).
    pub value_label: &'a str,
    /// Colour map.
    pub map: ColorMap,
}

/// Size of an [`image_pair`], pixels.
pub const IMAGE_PAIR_PX: (u32, u32) = (960, 460);

/// Draws an [`ImagePairFigure`], [`IMAGE_PAIR_PX`]: the colour range is the 0.5–99.5 %
/// range of both images' finite values together, so the two read on one scale.
///
/// # Errors
/// [`PlotError::Empty`] when an image has no finite value or not one value per pixel.
pub fn image_pair(f: &ImagePairFigure<'_>) -> Result<Vec<u8>, PlotError> {
    let title = f.title;
    let empty = || PlotError::Empty {
        figure: title.to_owned(),
    };
    let mut all: Vec<f64> = Vec::new();
    for p in &f.panels {
        if p.columns == 0
            || p.rows == 0
            || p.values.len() != p.columns * p.rows
            || p.step.is_nan()
            || p.step <= 0.0
        {
            return Err(empty());
        }
        all.extend(p.values.iter().copied().filter(|v| v.is_finite()));
    }
    if all.is_empty() {
        return Err(empty());
    }
    all.sort_by(f64::total_cmp);
    let at = |q: f64| all[((all.len() - 1) as f64 * q).round() as usize];
    let range = finite_range([at(0.005), at(0.995)].into_iter()).ok_or_else(empty)?;
    let (width, height) = IMAGE_PAIR_PX;
    figure(title, width, height, |root| {
        let body = root
            .titled(
                title,
                (FONT_FAMILY, TITLE_PX).into_font().style(FontStyle::Bold),
            )
            .map_err(|e| draw_error(title, e))?;
        let (images, bar_area) = body.split_horizontally((width - BAR_PX) as i32);
        let halves = images.split_evenly((1, 2));
        for (panel, area) in f.panels.iter().zip(&halves) {
            // A square extent around the image, so that angles read true.
            let half_side = 0.5 * panel.step * panel.columns.max(panel.rows) as f64;
            let centre = (
                panel.origin.0 + 0.5 * panel.step * (panel.columns as f64 - 1.0),
                panel.origin.1 + 0.5 * panel.step * (panel.rows as f64 - 1.0),
            );
            let axes = FieldAxes {
                x_label: f.x_label,
                y_label: f.y_label,
                x_range: (centre.0 - half_side, centre.0 + half_side),
                y_range: (centre.1 - half_side, centre.1 + half_side),
            };
            let mut chart = map_panel(area, panel.caption, &axes, title)?;
            let t = |v: f64| ((v - range.0) / (range.1 - range.0)).clamp(0.0, 1.0);
            let (h, (x0, y0)) = (0.5 * panel.step, panel.origin);
            chart
                .draw_series(
                    panel
                        .values
                        .iter()
                        .enumerate()
                        .filter(|(_, v)| v.is_finite())
                        .map(|(k, &v)| {
                            let (i, j) = (k % panel.columns, k / panel.columns);
                            let (x, y) = (x0 + panel.step * i as f64, y0 + panel.step * j as f64);
                            Rectangle::new(
                                [(x - h, y - h), (x + h, y + h)],
                                f.map.colour(t(v)).filled(),
                            )
                        }),
                )
                .map_err(|e| draw_error(title, e))?;
        }
        colour_bar(&bar_area, title, f.map, range, f.value_label)
    })
}

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SeriesStyle {
    /// A line through the points.
    Line,
    /// A line with a dot on every point.
    LineAndMarkers,
    /// Dots only.
    Markers,
    /// Crosses only (e.g. rejected or spoiled samples).
    Crosses,
    /// Small translucent dots (thousands of points, e.g. residuals of every feature).
    Dots,
    /// A shaded band: the points are the band's outline, its lower edge left to right then
    /// its upper edge right to left (e.g. a 16–84 % spread around a running median); shaded
    /// in the colour of the series that follows it (the median it surrounds).
    Band,
}

/// One series of an [`XyFigure`].
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend entry.
    pub name: String,
    /// Points (x, y); non-finite points (and y ≤ 0 on a logarithmic axis) are skipped.
    pub points: Vec<(f64, f64)>,
    /// How it is drawn.
    pub style: SeriesStyle,
}

/// Lines and markers against a numeric x axis.
#[derive(Debug, Clone, PartialEq)]
pub struct XyFigure {
    /// Title.
    pub title: String,
    /// x axis: quantity, unit.
    pub x_label: String,
    /// y axis: quantity, unit.
    pub y_label: String,
    /// The series.
    pub series: Vec<Series>,
    /// Logarithmic y axis.
    pub log_y: bool,
    /// y starts at 0 (linear axes of magnitudes).
    pub y_from_zero: bool,
    /// Size, pixels.
    pub size: (u32, u32),
}

/// Draws an [`XyFigure`].
///
/// # Errors
/// [`PlotError::Empty`] when no series has a drawable point.
pub fn xy_chart(f: &XyFigure) -> Result<Vec<u8>, PlotError> {
    let keep = |p: &(f64, f64)| p.0.is_finite() && p.1.is_finite() && (!f.log_y || p.1 > 0.0);
    let series: Vec<(&Series, Vec<(f64, f64)>)> = f
        .series
        .iter()
        .map(|s| (s, s.points.iter().copied().filter(keep).collect()))
        .collect();
    let all = || series.iter().flat_map(|s| s.1.iter());
    let empty = || PlotError::Empty {
        figure: f.title.clone(),
    };
    let xr = pad_range(finite_range(all().map(|p| p.0)).ok_or_else(empty)?, 0.03);
    let (ylo, yhi) = finite_range(all().map(|p| p.1)).ok_or_else(empty)?;
    let legend_rows = series.len() as f64;
    let title = f.title.as_str();
    figure(title, f.size.0, f.size.1, |root| {
        let mut builder = ChartBuilder::on(root);
        builder
            .caption(
                title,
                (FONT_FAMILY, TITLE_PX).into_font().style(FontStyle::Bold),
            )
            .margin(14)
            .x_label_area_size(52)
            .y_label_area_size(84);
        let sx = step_of(xr, 8);
        if f.log_y {
            let yr = log_range_with_legend(ylo, yhi, series.len());
            let mut chart = builder
                .build_cartesian_2d(xr.0..xr.1, (yr.0..yr.1).log_scale())
                .map_err(|e| draw_error(title, e))?;
            chart
                .configure_mesh()
                .x_labels(8)
                .x_label_formatter(&|v| tick_label(*v, sx))
                .y_label_formatter(&|v| log_tick_label(*v))
                .x_desc(f.x_label.as_str())
                .y_desc(f.y_label.as_str())
                .label_style((FONT_FAMILY, TICK_PX))
                .axis_desc_style((FONT_FAMILY, LABEL_PX))
                .draw()
                .map_err(|e| draw_error(title, e))?;
            draw_xy_series(&mut chart, title, &series)
        } else {
            let yr = if f.y_from_zero {
                (
                    0.0f64.min(ylo),
                    yhi + (yhi - 0.0f64.min(ylo)) * 0.08 * legend_rows.max(2.0),
                )
            } else {
                let (a, b) = pad_range((ylo, yhi), 0.05);
                (a, b + (b - a) * 0.08 * legend_rows.max(2.0))
            };
            let sy = step_of(yr, 8);
            let mut chart = builder
                .build_cartesian_2d(xr.0..xr.1, yr.0..yr.1)
                .map_err(|e| draw_error(title, e))?;
            chart
                .configure_mesh()
                .x_labels(8)
                .y_labels(8)
                .x_label_formatter(&|v| tick_label(*v, sx))
                .y_label_formatter(&|v| tick_label(*v, sy))
                .x_desc(f.x_label.as_str())
                .y_desc(f.y_label.as_str())
                .label_style((FONT_FAMILY, TICK_PX))
                .axis_desc_style((FONT_FAMILY, LABEL_PX))
                .draw()
                .map_err(|e| draw_error(title, e))?;
            draw_xy_series(&mut chart, title, &series)
        }
    })
}

pub(crate) fn draw_xy_series<'a, 'b: 'a, X, Y>(
    chart: &mut ChartContext<'a, BitMapBackend<'b>, Cartesian2d<X, Y>>,
    title: &str,
    series: &[(&Series, Vec<(f64, f64)>)],
) -> Result<(), PlotError>
where
    X: Ranged<ValueType = f64>,
    Y: Ranged<ValueType = f64>,
{
    for (k, (s, points)) in series.iter().enumerate() {
        let colour = category_colour(if s.style == SeriesStyle::Band {
            k + 1
        } else {
            k
        });
        let style = s.style;
        let mut legend_drawn = false;
        if matches!(style, SeriesStyle::Line | SeriesStyle::LineAndMarkers) {
            chart
                .draw_series(LineSeries::new(points.clone(), colour.stroke_width(2)))
                .map_err(|e| draw_error(title, e))?
                .label(s.name.as_str())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                });
            legend_drawn = true;
        }
        if style == SeriesStyle::Band {
            let shade = colour.mix(0.25);
            chart
                .draw_series(std::iter::once(Polygon::new(
                    points.clone(),
                    shade.filled(),
                )))
                .map_err(|e| draw_error(title, e))?
                .label(s.name.as_str())
                .legend(move |(x, y)| {
                    Rectangle::new([(x, y - 5), (x + 20, y + 5)], shade.filled())
                });
        } else if style == SeriesStyle::Crosses {
            let drawn = chart
                .draw_series(
                    points
                        .iter()
                        .map(|&p| Cross::new(p, 6, colour.stroke_width(2))),
                )
                .map_err(|e| draw_error(title, e))?;
            drawn
                .label(s.name.as_str())
                .legend(move |(x, y)| Cross::new((x + 10, y), 6, colour.stroke_width(2)));
        } else if style == SeriesStyle::Dots {
            let dot = colour.mix(0.55);
            chart
                .draw_series(points.iter().map(|&p| Circle::new(p, 2, dot.filled())))
                .map_err(|e| draw_error(title, e))?
                .label(s.name.as_str())
                .legend(move |(x, y)| Circle::new((x + 10, y), 4, colour.filled()));
        } else if style != SeriesStyle::Line {
            let drawn = chart
                .draw_series(points.iter().map(|&p| Circle::new(p, 4, colour.filled())))
                .map_err(|e| draw_error(title, e))?;
            if !legend_drawn {
                drawn
                    .label(s.name.as_str())
                    .legend(move |(x, y)| Circle::new((x + 10, y), 4, colour.filled()));
            }
        }
    }
    chart
        .configure_series_labels()
        .label_font((FONT_FAMILY, TICK_PX))
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(|e| draw_error(title, e))
}

/// One series of a [`CategoryFigure`]: a value per category (`None`: not measured).
#[derive(Debug, Clone, PartialEq)]
pub struct CategorySeries {
    /// Legend entry.
    pub name: String,
    /// One value per category.
    pub values: Vec<Option<f64>>,
}

/// Values per category and series: a categorical x axis (one tick per category, the
/// series side by side within it), no line joining categories.
#[derive(Debug, Clone, PartialEq)]
pub struct CategoryFigure {
    /// Title.
    pub title: String,
    /// x axis: what the categories are.
    pub x_label: String,
    /// Category names, in order.
    pub categories: Vec<String>,
    /// y axis: quantity, unit.
    pub y_label: String,
    /// The series.
    pub series: Vec<CategorySeries>,
    /// Logarithmic y axis.
    pub log_y: bool,
    /// Size, pixels.
    pub size: (u32, u32),
}

/// Draws a [`CategoryFigure`].
///
/// # Errors
/// [`PlotError::Empty`] when there is no category or no drawable value.
pub fn category_chart(f: &CategoryFigure) -> Result<Vec<u8>, PlotError> {
    let title = f.title.as_str();
    let n = f.categories.len();
    let ok = |v: f64| v.is_finite() && (!f.log_y || v > 0.0);
    let values = f
        .series
        .iter()
        .flat_map(|s| s.values.iter().flatten().copied())
        .filter(|v| ok(*v));
    let (ylo, yhi) = finite_range(values).ok_or_else(|| PlotError::Empty {
        figure: title.to_owned(),
    })?;
    if n == 0 {
        return Err(PlotError::Empty {
            figure: title.to_owned(),
        });
    }
    let m = f.series.len().max(1) as f64;
    // Within a category the series sit side by side over 70 % of its width.
    let x_of = |category: usize, k: usize| category as f64 - 0.35 + 0.7 * (k as f64 + 0.5) / m;
    let points: Vec<Vec<(f64, f64)>> = f
        .series
        .iter()
        .enumerate()
        .map(|(k, s)| {
            s.values
                .iter()
                .enumerate()
                .filter_map(|(c, v)| v.filter(|v| ok(*v)).map(|v| (x_of(c, k), v)))
                .collect()
        })
        .collect();
    figure(title, f.size.0, f.size.1, |root| {
        let mut builder = ChartBuilder::on(root);
        builder
            .caption(
                title,
                (FONT_FAMILY, TITLE_PX).into_font().style(FontStyle::Bold),
            )
            .margin(14)
            .x_label_area_size(64)
            .y_label_area_size(84);
        let x_range = -0.5..(n as f64 - 0.5);
        if f.log_y {
            let yr = log_range_with_legend(ylo, yhi, f.series.len());
            let chart = builder
                .build_cartesian_2d(x_range, (yr.0..yr.1).log_scale())
                .map_err(|e| draw_error(title, e))?;
            category_body(chart, root, f, &points, (yr.0, yr.1))
        } else {
            let (a, b) = pad_range((0.0f64.min(ylo), yhi), 0.06);
            let b = b + (b - a) * 0.08 * f.series.len().max(2) as f64;
            let chart = builder
                .build_cartesian_2d(x_range, a..b)
                .map_err(|e| draw_error(title, e))?;
            category_body(chart, root, f, &points, (a, b))
        }
    })
}

fn category_body<'a, 'b: 'a, Y>(
    mut chart: ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, Y>>,
    root: &Area<'b>,
    f: &CategoryFigure,
    points: &[Vec<(f64, f64)>],
    (y_bottom, y_top): (f64, f64),
) -> Result<(), PlotError>
where
    Y: Ranged<ValueType = f64> + plotters::coord::ranged1d::ValueFormatter<f64>,
{
    let title = f.title.as_str();
    let n = f.categories.len();
    let linear_step = step_of((y_bottom, y_top), 10);
    chart
        .configure_mesh()
        .disable_x_mesh()
        .x_labels(0)
        .x_label_formatter(&|_| String::new())
        .y_label_formatter(&|v| {
            if f.log_y {
                log_tick_label(*v)
            } else {
                tick_label(*v, linear_step)
            }
        })
        .x_desc(f.x_label.as_str())
        .y_desc(f.y_label.as_str())
        .label_style((FONT_FAMILY, TICK_PX))
        .axis_desc_style((FONT_FAMILY, LABEL_PX))
        .draw()
        .map_err(|e| draw_error(title, e))?;
    // Category names under the axis and separators between categories.
    for (c, name) in f.categories.iter().enumerate() {
        let (px, py) = chart.backend_coord(&(c as f64, y_bottom));
        root.draw(&Text::new(
            name.clone(),
            (px, py + 8),
            (FONT_FAMILY, LABEL_PX)
                .into_font()
                .into_text_style(root)
                .pos(Pos::new(HPos::Center, VPos::Top)),
        ))
        .map_err(|e| draw_error(title, e))?;
    }
    chart
        .draw_series((1..n).map(|c| {
            let x = c as f64 - 0.5;
            PathElement::new(
                vec![(x, y_bottom), (x, y_top)],
                BLACK.mix(0.25).stroke_width(1),
            )
        }))
        .map_err(|e| draw_error(title, e))?;
    for (k, (s, p)) in f.series.iter().zip(points).enumerate() {
        let colour = category_colour(k);
        chart
            .draw_series(p.iter().map(|&q| Circle::new(q, 6, colour.filled())))
            .map_err(|e| draw_error(title, e))?
            .label(s.name.as_str())
            .legend(move |(x, y)| Circle::new((x + 8, y), 6, colour.filled()));
    }
    chart
        .configure_series_labels()
        .label_font((FONT_FAMILY, LABEL_PX))
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(|e| draw_error(title, e))
}

/// One panel of an [`OrderFigure`]: points joined in order (e.g. one pass over the net).
#[derive(Debug, Clone, PartialEq)]
pub struct OrderPanel {
    /// The panel's caption (e.g. "pass 2, 25 visits").
    pub caption: String,
    /// The points in order, the figure's x and y units.
    pub points: Vec<(f64, f64)>,
}

/// Small multiples of points joined in order and coloured by their index within their
/// panel (e.g. the nodes in visiting order, one panel per pass), on shared axes, so that no
/// panel hides another.
#[derive(Debug, Clone, PartialEq)]
pub struct OrderFigure {
    /// Title.
    pub title: String,
    /// x axis: quantity, unit.
    pub x_label: String,
    /// y axis: quantity, unit.
    pub y_label: String,
    /// The panels, drawn left to right, top to bottom, [`ORDER_COLUMNS`] per row.
    pub panels: Vec<OrderPanel>,
    /// What the order is (the colour bar's label).
    pub order_label: String,
}

/// Panels per row of an [`order_map`].
pub const ORDER_COLUMNS: usize = 2;
/// Size of one panel of an [`order_map`], pixels.
const ORDER_PANEL_PX: (u32, u32) = (430, 400);

/// Draws an [`OrderFigure`]: [`ORDER_COLUMNS`] panels per row (fewer when there are fewer
/// panels), each 430 pixels wide and 400 high, and one colour bar.
///
/// # Errors
/// [`PlotError::Empty`] when no point is finite.
pub fn order_map(f: &OrderFigure) -> Result<Vec<u8>, PlotError> {
    let title = f.title.as_str();
    let empty = || PlotError::Empty {
        figure: title.to_owned(),
    };
    let all = || f.panels.iter().flat_map(|p| p.points.iter());
    let xr = pad_range(finite_range(all().map(|p| p.0)).ok_or_else(empty)?, 0.06);
    let yr = pad_range(finite_range(all().map(|p| p.1)).ok_or_else(empty)?, 0.06);
    let longest = f.panels.iter().map(|p| p.points.len()).max().unwrap_or(1);
    let last = longest.saturating_sub(1).max(1) as f64;
    let order_range = (1.0, last + 1.0);
    let map = ColorMap::Viridis;
    let columns = f.panels.len().clamp(1, ORDER_COLUMNS);
    let rows = f.panels.len().div_ceil(columns).max(1);
    let width = columns as u32 * ORDER_PANEL_PX.0 + BAR_PX;
    let height = rows as u32 * ORDER_PANEL_PX.1 + 40;
    figure(title, width, height, |root| {
        let body = root
            .titled(
                title,
                (FONT_FAMILY, TITLE_PX).into_font().style(FontStyle::Bold),
            )
            .map_err(|e| draw_error(title, e))?;
        let (grid, bar) = body.split_horizontally((width - BAR_PX) as i32);
        let cells = grid.split_evenly((rows, columns));
        for (panel, area) in f.panels.iter().zip(&cells) {
            order_panel(area, title, f, panel, (xr, yr), |k| {
                map.colour(k as f64 / last)
            })?;
        }
        colour_bar(&bar, title, map, order_range, f.order_label.as_str())
    })
}

/// One panel of an [`order_map`]: the points joined in order, coloured by `colour(index)`.
fn order_panel(
    area: &Area<'_>,
    title: &str,
    f: &OrderFigure,
    panel: &OrderPanel,
    (xr, yr): ((f64, f64), (f64, f64)),
    colour: impl Fn(usize) -> RGBColor,
) -> Result<(), PlotError> {
    let (sx, sy) = (step_of(xr, 5), step_of(yr, 5));
    let mut chart = ChartBuilder::on(area)
        .caption(panel.caption.as_str(), (FONT_FAMILY, LABEL_PX))
        .margin(8)
        .x_label_area_size(48)
        .y_label_area_size(70)
        .build_cartesian_2d(xr.0..xr.1, yr.0..yr.1)
        .map_err(|e| draw_error(title, e))?;
    chart
        .configure_mesh()
        .x_labels(5)
        .y_labels(5)
        .x_label_formatter(&|v| tick_label(*v, sx))
        .y_label_formatter(&|v| tick_label(*v, sy))
        .x_desc(f.x_label.as_str())
        .y_desc(f.y_label.as_str())
        .label_style((FONT_FAMILY, TICK_PX))
        .axis_desc_style((FONT_FAMILY, LABEL_PX))
        .draw()
        .map_err(|e| draw_error(title, e))?;
    let points = &panel.points;
    chart
        .draw_series(
            points
                .windows(2)
                .enumerate()
                .map(|(k, w)| PathElement::new(vec![w[0], w[1]], colour(k).stroke_width(2))),
        )
        .map_err(|e| draw_error(title, e))?;
    chart
        .draw_series(
            points
                .iter()
                .enumerate()
                .map(|(k, &p)| Circle::new(p, 5, colour(k).filled())),
        )
        .map_err(|e| draw_error(title, e))?;
    chart
        .draw_series(
            points
                .iter()
                .map(|&p| Circle::new(p, 5, BLACK.stroke_width(1))),
        )
        .map_err(|e| draw_error(title, e))?;
    Ok(())
}

/// The running quantiles of `points` (x, y): the x range split into `bins` equal bins, and
/// for each bin holding at least `min_count` finite points, (the bin's centre, the
/// `quantiles` of its y values), linearly interpolated between order statistics (the
/// "type 7" definition of R and NumPy). A summary of a cloud too dense to draw point by
/// point (e.g. a run's ~30 000 drift estimates).
pub fn running_quantiles(
    points: &[(f64, f64)],
    bins: usize,
    min_count: usize,
    quantiles: &[f64],
) -> Vec<(f64, Vec<f64>)> {
    let finite: Vec<(f64, f64)> = points
        .iter()
        .copied()
        .filter(|p| p.0.is_finite() && p.1.is_finite())
        .collect();
    let Some((x0, x1)) = finite_range(finite.iter().map(|p| p.0)) else {
        return Vec::new();
    };
    let bins = bins.max(1);
    let width = (x1 - x0) / bins as f64;
    let mut per_bin: Vec<Vec<f64>> = vec![Vec::new(); bins];
    for &(x, y) in &finite {
        let k = (((x - x0) / width) as usize).min(bins - 1);
        per_bin[k].push(y);
    }
    per_bin
        .into_iter()
        .enumerate()
        .filter(|(_, ys)| ys.len() >= min_count.max(1))
        .map(|(k, mut ys)| {
            ys.sort_by(f64::total_cmp);
            let q = quantiles.iter().map(|&q| quantile_sorted(&ys, q)).collect();
            (x0 + width * (k as f64 + 0.5), q)
        })
        .collect()
}

/// The `q` quantile of sorted, non-empty `ys` (type 7).
fn quantile_sorted(ys: &[f64], q: f64) -> f64 {
    let h = (ys.len() - 1) as f64 * q.clamp(0.0, 1.0);
    let (lo, hi) = (h.floor() as usize, h.ceil() as usize);
    ys[lo] + (h - lo as f64) * (ys[hi] - ys[lo])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check(v: f64, step: f64, expected: &str) {
        assert_eq!(tick_label(v, step), expected, "tick_label({v}, {step})");
    }

    #[test]
    fn tick_labels_have_the_decimals_the_step_needs() {
        check(0.30000000000000004, 0.1, "0.3");
        check(20.0, 5.0, "20");
        check(20.25, 0.05, "20.25");
        check(-0.0, 0.1, "0.0");
        check(1.5e-5, 1e-6, "1.5e-5");
        check(250_000.0, 50_000.0, "2.5e5");
    }

    #[test]
    fn log_tick_labels_show_the_decade() {
        for (v, expected) in [
            (1.0, "1"),
            (10.0, "10"),
            (0.5, "0.5"),
            (0.02, "0.02"),
            (1e6, "1000000"),
            (1e8, "1e8"),
        ] {
            assert_eq!(log_tick_label(v), expected, "log_tick_label({v})");
        }
    }

    #[test]
    fn the_legend_gets_head_room_on_a_log_axis() {
        let (lo, hi) = log_range_with_legend(1.0, 10.0, 4);
        assert!(lo < 1.0 && hi > 13.0 && hi < 100.0, "{lo} {hi}");
    }
}
