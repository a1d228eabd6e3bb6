//! The residual figure (PNG): what the baseline gets wrong, at a glance.
//!
//! Six panels: baseline residual (x and y components, pm) against time,
//! against the fast-axis position, against the slow-axis position, and by
//! line direction/frame (a legend names each colour); the amplitude spectrum of the per-line
//! mean residual before and after the extension; and the final residual against time.
//! Drawn by spm-plot (`panel_grid`), like every figure of the workspace.

use crate::diagnose::Diagnosis;
use crate::types::{LineDirection, ModelCheckError};
use spm_plot::{PanelGrid, Series, SeriesStyle, XyPanel};
use std::path::Path;

/// Registers the workspace's embedded font (DejaVu Sans, `spm_plot::register_fonts`) with
/// plotters once, for every figure of the process; `false` only when plotters rejects it
/// (figures are then drawn without text).
pub fn register_system_font() -> bool {
    spm_plot::register_fonts().is_ok()
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

/// The four residual series of `used` (x and y, forward and backward lines) against `key`.
fn residual_series(
    used: &[&crate::ResidualPoint],
    key: &dyn Fn(&crate::ResidualPoint) -> f64,
    final_model: bool,
) -> Vec<Series> {
    let mut out = Vec::new();
    for (direction, half) in [
        (LineDirection::Forward, "forward"),
        (LineDirection::Backward, "backward"),
    ] {
        for (component, axis) in [(0usize, "x"), (1, "y")] {
            let points: Vec<(f64, f64)> = used
                .iter()
                .filter(|r| r.direction == direction)
                .map(|r| {
                    let v = if final_model {
                        r.final_pm
                    } else {
                        r.baseline_pm
                    };
                    (key(r), v[component])
                })
                .collect();
            if !points.is_empty() {
                out.push(Series {
                    name: format!("{axis}, {half} lines"),
                    points,
                    style: SeriesStyle::Dots,
                });
            }
        }
    }
    out
}

/// The residual figure of `d` as panels: the baseline residual against time, the fast and
/// slow axis and the frame's lines; the spectrum of the line-mean residual before and after
/// the extension; the final residual against time.
fn figure(d: &Diagnosis, title: &str) -> PanelGrid {
    let found = if d.findings.is_empty() {
        "none".to_owned()
    } else {
        d.findings
            .iter()
            .map(|f| format!("{} (evidence {:.0})", f.effect, f.evidence))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let used: Vec<&crate::ResidualPoint> = d.residuals.iter().filter(|r| r.used).collect();
    let max_line = used.iter().map(|q| q.line).max().unwrap_or(1).max(1) as f64;
    let panel = |title: &str, x_label: &str, series: Vec<Series>| XyPanel {
        title: title.to_owned(),
        x_label: x_label.to_owned(),
        y_label: "residual / pm".to_owned(),
        series,
        zero_line: true,
        y_from_zero: false,
    };
    let time_label = "time from the middle of the data / s";
    let panels = vec![
        panel(
            "baseline residual vs time",
            time_label,
            residual_series(&used, &|r| r.time_s, false),
        ),
        panel(
            "baseline residual vs fast axis x",
            "x / nm (nominal)",
            residual_series(&used, &|r| r.x_nm, false),
        ),
        panel(
            "baseline residual vs slow axis y",
            "y / nm (nominal)",
            residual_series(&used, &|r| r.y_nm, false),
        ),
        panel(
            "baseline residual by frame",
            "frame + line / lines of a frame",
            residual_series(
                &used,
                &|r| r.frame as f64 + 0.9 * r.line as f64 / max_line,
                false,
            ),
        ),
        XyPanel {
            title: "spectrum of line-mean residual".to_owned(),
            x_label: "cycles per line".to_owned(),
            y_label: "amplitude / pm".to_owned(),
            series: vec![
                Series {
                    name: "baseline".to_owned(),
                    points: line_spectrum(d, false),
                    style: SeriesStyle::Line,
                },
                Series {
                    name: "final model".to_owned(),
                    points: line_spectrum(d, true),
                    style: SeriesStyle::Line,
                },
            ],
            zero_line: false,
            y_from_zero: true,
        },
        panel(
            "final residual vs time",
            time_label,
            residual_series(&used, &|r| r.time_s, true),
        ),
    ];
    PanelGrid {
        title: title.to_owned(),
        notes: vec![
            format!(
                "baseline RMS {:.1} pm (held out {:.1} pm) → final {:.1} pm (held out {:.1} pm); \
                 structure left unexplained: {}",
                d.baseline.rms_pm,
                d.baseline.heldout_rms_pm,
                d.final_report.rms_pm,
                d.final_report.heldout_rms_pm,
                if d.unexplained { "yes" } else { "no" }
            ),
            format!("found: {found}"),
        ],
        columns: 3,
        panels,
        size: (1400, 900),
    }
}

/// Writes the residual figure of a diagnosis to `path` (PNG, 1400×900: its smallest text reads at 9 px when shown 800 px wide).
pub fn write_png(
    d: &Diagnosis,
    path: impl AsRef<Path>,
    title: &str,
) -> Result<(), ModelCheckError> {
    let path = path.as_ref();
    let plot_error = |reason: String| ModelCheckError::Plot {
        path: path.display().to_string(),
        reason,
    };
    let png = spm_plot::panel_grid(&figure(d, title)).map_err(|e| plot_error(e.to_string()))?;
    spm_plot::write_file(path, &png).map_err(|e| plot_error(e.to_string()))
}
