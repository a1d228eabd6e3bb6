//! Several xy panels in one figure, under a title and lines of notes (the model check's
//! residual figure).

use crate::PlotError;
use crate::charts::{
    Area, LABEL_PX, Series, TICK_PX, TITLE_PX, draw_error, draw_xy_series, figure, finite_range,
    pad_range, step_of, tick_label,
};
use crate::font::FONT_FAMILY;
use plotters::prelude::*;

/// One panel of a [`PanelGrid`]: series against a numeric x axis, each with its legend entry.
#[derive(Debug, Clone, PartialEq)]
pub struct XyPanel {
    /// The panel's title.
    pub title: String,
    /// x axis: quantity, unit.
    pub x_label: String,
    /// y axis: quantity, unit.
    pub y_label: String,
    /// The series (colours by position, as in [`crate::xy_chart`]).
    pub series: Vec<Series>,
    /// A thin line at y = 0 (residuals).
    pub zero_line: bool,
    /// y starts at 0 (magnitudes).
    pub y_from_zero: bool,
}

/// Panels in a grid of `columns`, row by row, under a title and notes.
#[derive(Debug, Clone, PartialEq)]
pub struct PanelGrid {
    /// Title.
    pub title: String,
    /// Lines of text under the title (what the figure says, in words).
    pub notes: Vec<String>,
    /// Panels per row.
    pub columns: usize,
    /// The panels.
    pub panels: Vec<XyPanel>,
    /// Size, pixels.
    pub size: (u32, u32),
}

/// Height of a line of notes, pixels.
const NOTE_LINE_PX: u32 = 24;

/// Draws a [`PanelGrid`]. A panel without a drawable point says so in its place.
///
/// # Errors
/// [`PlotError::Empty`] when there is no panel; a drawing error.
pub fn panel_grid(f: &PanelGrid) -> Result<Vec<u8>, PlotError> {
    let title = f.title.as_str();
    if f.panels.is_empty() || f.columns == 0 {
        return Err(PlotError::Empty {
            figure: f.title.clone(),
        });
    }
    let rows = f.panels.len().div_ceil(f.columns);
    figure(title, f.size.0, f.size.1, |root| {
        let header_px = TITLE_PX + 18 + NOTE_LINE_PX * f.notes.len() as u32;
        let (header, body) = root.split_vertically(header_px);
        header
            .draw_text(
                title,
                &(FONT_FAMILY, TITLE_PX)
                    .into_font()
                    .style(FontStyle::Bold)
                    .color(&BLACK),
                (12, 8),
            )
            .map_err(|e| draw_error(title, e))?;
        for (k, note) in f.notes.iter().enumerate() {
            header
                .draw_text(
                    note,
                    &(FONT_FAMILY, TICK_PX).into_font().color(&BLACK),
                    (12, (TITLE_PX + 16 + NOTE_LINE_PX * k as u32) as i32),
                )
                .map_err(|e| draw_error(title, e))?;
        }
        let areas = body.split_evenly((rows, f.columns));
        for (panel, area) in f.panels.iter().zip(&areas) {
            draw_panel(title, panel, area)?;
        }
        Ok(())
    })
}

fn draw_panel(figure_title: &str, p: &XyPanel, area: &Area<'_>) -> Result<(), PlotError> {
    let err = |e: &dyn std::fmt::Display| draw_error(figure_title, e);
    let series: Vec<(&Series, Vec<(f64, f64)>)> = p
        .series
        .iter()
        .map(|s| {
            let points = s
                .points
                .iter()
                .copied()
                .filter(|q| q.0.is_finite() && q.1.is_finite())
                .collect();
            (s, points)
        })
        .collect();
    let all = || series.iter().flat_map(|s| s.1.iter());
    let (Some(xr), Some(yr)) = (
        finite_range(all().map(|q| q.0)),
        finite_range(all().map(|q| q.1)),
    ) else {
        area.draw_text(
            &format!("{}: nothing to draw", p.title),
            &(FONT_FAMILY, TICK_PX).into_font().color(&BLACK),
            (12, 12),
        )
        .map_err(|e| err(&e))?;
        return Ok(());
    };
    let xr = pad_range(xr, 0.03);
    let (lo, hi) = if p.y_from_zero {
        (0.0f64.min(yr.0), yr.1)
    } else {
        pad_range(yr, 0.05)
    };
    // Head-room for the legend (one row per series).
    let yr = (lo, hi + (hi - lo) * 0.09 * series.len().max(1) as f64);
    let (sx, sy) = (step_of(xr, 5), step_of(yr, 6));
    let mut chart = ChartBuilder::on(area)
        .caption(p.title.as_str(), (FONT_FAMILY, LABEL_PX))
        .margin(10)
        .x_label_area_size(48)
        .y_label_area_size(76)
        .build_cartesian_2d(xr.0..xr.1, yr.0..yr.1)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .light_line_style(WHITE.mix(0.0))
        .x_labels(5)
        .y_labels(6)
        .x_label_formatter(&|v| tick_label(*v, sx))
        .y_label_formatter(&|v| tick_label(*v, sy))
        .x_desc(p.x_label.as_str())
        .y_desc(p.y_label.as_str())
        .label_style((FONT_FAMILY, TICK_PX))
        .axis_desc_style((FONT_FAMILY, TICK_PX))
        .draw()
        .map_err(|e| err(&e))?;
    if p.zero_line {
        chart
            .draw_series(LineSeries::new([(xr.0, 0.0), (xr.1, 0.0)], BLACK.mix(0.5)))
            .map_err(|e| err(&e))?;
    }
    draw_xy_series(&mut chart, figure_title, &series)
}
