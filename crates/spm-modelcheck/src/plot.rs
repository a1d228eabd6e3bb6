//! The residual figure (PNG): what the baseline gets wrong, at a glance.
//!
//! Six panels: baseline residual (x and y components, pm) against time,
//! against the fast-axis position, against the slow-axis position, and by
//! line direction/frame (colours); the amplitude spectrum of the per-line mean
//! residual before and after the extension; and the final residual against time.

use crate::diagnose::Diagnosis;
use crate::types::{LineDirection, ModelCheckError};
use plotters::prelude::*;
use std::path::Path;

/// Registers the workspace's embedded font (DejaVu Sans, `spm_plot::register_fonts`) with
/// plotters once, for every figure of the process; `false` only when plotters rejects it
/// (figures are then drawn without text).
pub fn register_system_font() -> bool {
    spm_plot::register_fonts().is_ok()
}

fn range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if !(lo.is_finite() && hi.is_finite()) {
        return (-1.0, 1.0);
    }
    if hi - lo < 1e-12 {
        return (lo - 1.0, hi + 1.0);
    }
    let pad = 0.05 * (hi - lo);
    (lo - pad, hi + pad)
}

/// Amplitude spectrum of per-line mean residual magnitudes (x and y combined), by line frequency.
fn line_spectrum(d: &Diagnosis, final_model: bool) -> Vec<(f64, f64)> {
    use std::collections::BTreeMap;
    let mut lines: BTreeMap<(usize, usize), (f64, f64, usize)> = BTreeMap::new();
    for r in d.residuals.iter().filter(|r| r.used) {
        let v = if final_model {
            r.final_pm
        } else {
            r.baseline_pm
        };
        let e = lines.entry((r.frame, r.line)).or_insert((0.0, 0.0, 0));
        e.0 += v[0];
        e.1 += v[1];
        e.2 += 1;
    }
    let sx: Vec<f64> = lines.values().map(|e| e.0 / e.2 as f64).collect();
    let sy: Vec<f64> = lines.values().map(|e| e.1 / e.2 as f64).collect();
    let n = sx.len();
    if n < 4 {
        return Vec::new();
    }
    let mx = sx.iter().sum::<f64>() / n as f64;
    let my = sy.iter().sum::<f64>() / n as f64;
    (1..=n / 2)
        .map(|k| {
            let w = 2.0 * std::f64::consts::PI * k as f64 / n as f64;
            let (mut xc, mut xs, mut yc, mut ys) = (0.0, 0.0, 0.0, 0.0);
            for i in 0..n {
                let (s, c) = (w * i as f64).sin_cos();
                xc += (sx[i] - mx) * c;
                xs += (sx[i] - mx) * s;
                yc += (sy[i] - my) * c;
                ys += (sy[i] - my) * s;
            }
            let amp = 2.0 / n as f64 * (xc * xc + xs * xs + yc * yc + ys * ys).sqrt();
            (k as f64 / n as f64, amp)
        })
        .collect()
}

type Area<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;

/// A tick label without trailing zeros (−25, 2.5, 0.125), so five of them fit
/// a panel's width.
fn tick(v: &f64) -> String {
    let text = format!("{v:.3}");
    let text = text.trim_end_matches('0').trim_end_matches('.');
    if text == "-0" {
        "0".to_owned()
    } else {
        text.to_owned()
    }
}

fn scatter_panel(
    area: &Area<'_>,
    title: &str,
    x_label: &str,
    points: &[(f64, f64, RGBColor)],
    text: bool,
) -> Result<(), String> {
    let (x0, x1) = range(points.iter().map(|p| p.0));
    let (y0, y1) = range(points.iter().map(|p| p.1));
    let mut builder = ChartBuilder::on(area);
    builder
        .margin(8)
        .x_label_area_size(if text { 32 } else { 4 })
        .y_label_area_size(if text { 52 } else { 4 });
    if text {
        builder.caption(title, ("sans-serif", 15));
    }
    let mut chart = builder
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(|e| e.to_string())?;
    let mut mesh = chart.configure_mesh();
    mesh.light_line_style(WHITE.mix(0.0));
    if text {
        mesh.x_desc(x_label)
            .y_desc("residual / pm")
            .x_labels(5)
            .y_labels(6)
            .x_label_formatter(&tick)
            .y_label_formatter(&tick);
    } else {
        mesh.disable_x_axis().disable_y_axis();
    }
    mesh.draw().map_err(|e| e.to_string())?;
    chart
        .draw_series(
            points
                .iter()
                .map(|(x, y, c)| Circle::new((*x, *y), 2, c.mix(0.6).filled())),
        )
        .map_err(|e| e.to_string())?;
    chart
        .draw_series(LineSeries::new([(x0, 0.0), (x1, 0.0)], BLACK.mix(0.5)))
        .map_err(|e| e.to_string())?;
    Ok(())
}

const X_FWD: RGBColor = RGBColor(31, 119, 180);
const X_BWD: RGBColor = RGBColor(120, 180, 230);
const Y_FWD: RGBColor = RGBColor(214, 39, 40);
const Y_BWD: RGBColor = RGBColor(250, 150, 120);

fn colours(direction: LineDirection) -> (RGBColor, RGBColor) {
    match direction {
        LineDirection::Forward => (X_FWD, Y_FWD),
        LineDirection::Backward => (X_BWD, Y_BWD),
    }
}

fn draw(d: &Diagnosis, path: &Path, title: &str) -> Result<(), String> {
    let text = register_system_font();
    let root = BitMapBackend::new(path, (1000, 600)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| e.to_string())?;
    let (header, body) = root.split_vertically(if text { 84 } else { 4 });
    if text {
        let found = if d.findings.is_empty() {
            "none".to_owned()
        } else {
            d.findings
                .iter()
                .map(|f| format!("{} (ΔBIC {:.0})", f.effect, f.evidence))
                .collect::<Vec<_>>()
                .join(", ")
        };
        header
            .draw_text(title, &("sans-serif", 22).into_text_style(&header), (10, 6))
            .map_err(|e| e.to_string())?;
        let line = format!(
            "baseline RMS {:.1} pm (held-out {:.1}) → final {:.1} pm (held-out {:.1});  unexplained: {}.   blue = x, red = y; light = backward",
            d.baseline.rms_pm,
            d.baseline.heldout_rms_pm,
            d.final_report.rms_pm,
            d.final_report.heldout_rms_pm,
            d.unexplained
        );
        let style = ("sans-serif", 13).into_text_style(&header);
        header
            .draw_text(&line, &style, (10, 36))
            .map_err(|e| e.to_string())?;
        header
            .draw_text(&format!("found: {found}"), &style, (10, 56))
            .map_err(|e| e.to_string())?;
    }
    let panels = body.split_evenly((2, 3));
    let used: Vec<_> = d.residuals.iter().filter(|r| r.used).collect();
    let series = |key: &dyn Fn(&crate::ResidualPoint) -> f64, final_model: bool| {
        used.iter()
            .flat_map(|r| {
                let (cx, cy) = colours(r.direction);
                let v = if final_model {
                    r.final_pm
                } else {
                    r.baseline_pm
                };
                let k = key(r);
                [(k, v[0], cx), (k, v[1], cy)]
            })
            .collect::<Vec<_>>()
    };
    scatter_panel(
        &panels[0],
        "baseline residual vs time",
        "time / s",
        &series(&|r| r.time_s, false),
        text,
    )?;
    scatter_panel(
        &panels[1],
        "baseline residual vs fast axis x",
        "x / nm (nominal)",
        &series(&|r| r.x_nm, false),
        text,
    )?;
    scatter_panel(
        &panels[2],
        "baseline residual vs slow axis y",
        "y / nm (nominal)",
        &series(&|r| r.y_nm, false),
        text,
    )?;
    scatter_panel(
        &panels[3],
        "baseline residual by frame",
        "frame + line / lines",
        &used
            .iter()
            .flat_map(|r| {
                let (cx, cy) = colours(r.direction);
                let max_line = used.iter().map(|q| q.line).max().unwrap_or(1).max(1) as f64;
                let k = r.frame as f64 + 0.9 * r.line as f64 / max_line;
                [(k, r.baseline_pm[0], cx), (k, r.baseline_pm[1], cy)]
            })
            .collect::<Vec<_>>(),
        text,
    )?;
    // Spectrum panel.
    {
        let before = line_spectrum(d, false);
        let after = line_spectrum(d, true);
        let (x0, x1) = range(before.iter().chain(&after).map(|p| p.0));
        let (_, y1) = range(before.iter().chain(&after).map(|p| p.1));
        let mut builder = ChartBuilder::on(&panels[4]);
        builder
            .margin(8)
            .x_label_area_size(if text { 32 } else { 4 })
            .y_label_area_size(if text { 52 } else { 4 });
        if text {
            builder.caption("spectrum of line-mean residual", ("sans-serif", 15));
        }
        let mut chart = builder
            .build_cartesian_2d(x0.max(0.0)..x1, 0.0..y1.max(1e-9))
            .map_err(|e| e.to_string())?;
        let mut mesh = chart.configure_mesh();
        mesh.light_line_style(WHITE.mix(0.0));
        if text {
            mesh.x_desc("cycles per line")
                .y_desc("amplitude / pm")
                .x_labels(6)
                .y_labels(6)
                .x_label_formatter(&tick)
                .y_label_formatter(&tick);
        } else {
            mesh.disable_x_axis().disable_y_axis();
        }
        mesh.draw().map_err(|e| e.to_string())?;
        chart
            .draw_series(LineSeries::new(before, RGBColor(80, 80, 80)))
            .map_err(|e| e.to_string())?;
        chart
            .draw_series(LineSeries::new(after, RGBColor(44, 160, 44)))
            .map_err(|e| e.to_string())?;
    }
    scatter_panel(
        &panels[5],
        "final residual vs time",
        "time / s",
        &series(&|r| r.time_s, true),
        text,
    )?;
    root.present().map_err(|e| e.to_string())?;
    Ok(())
}

/// Writes the residual figure of a diagnosis to `path` (PNG, 1000×600).
pub fn write_png(
    d: &Diagnosis,
    path: impl AsRef<Path>,
    title: &str,
) -> Result<(), ModelCheckError> {
    let path = path.as_ref();
    draw(d, path, title).map_err(|reason| ModelCheckError::Plot {
        path: path.display().to_string(),
        reason,
    })
}
