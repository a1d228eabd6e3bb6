//! PNG figures of a run, drawn directly with the `png` crate (no font
//! dependency; the figures carry no text — their meaning is in the file name
//! and the report).
//!
//! - `lcc-kx.png`, `lcc-ky.png`, `lcc-alpha.png`: the regression surface over the
//!   calibrated region (colour, viridis) with every node's measured value as a
//!   square on the same colour scale, outlined in white: a node that stands out
//!   from the surface around it is a deviation from the fit.
//! - `drift.png`: drift speed against instrument time (white line; the grey
//!   line is zero, the axes span the run and 0…max speed).
//! - `trajectory.png`: the node centres joined in visiting order (colour from
//!   dark to bright along the run).

use crate::run::{DriftSample, NodeSample};
use spm_formats::ColorMap;
use spm_regression::Polynomial2;
use std::path::Path;

/// Why a figure could not be written.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {message}")]
pub struct PlotError {
    /// The figure.
    pub path: String,
    /// Why.
    pub message: String,
}

struct Canvas {
    width: usize,
    height: usize,
    rgb: Vec<u8>,
}

impl Canvas {
    fn new(width: usize, height: usize, background: [u8; 3]) -> Self {
        let mut rgb = Vec::with_capacity(width * height * 3);
        for _ in 0..width * height {
            rgb.extend_from_slice(&background);
        }
        Self { width, height, rgb }
    }

    fn set(&mut self, x: i64, y: i64, colour: [u8; 3]) {
        if x >= 0 && y >= 0 && (x as usize) < self.width && (y as usize) < self.height {
            let i = (y as usize * self.width + x as usize) * 3;
            self.rgb[i..i + 3].copy_from_slice(&colour);
        }
    }

    fn square(&mut self, cx: i64, cy: i64, half: i64, fill: [u8; 3], outline: [u8; 3]) {
        for y in cy - half - 1..=cy + half + 1 {
            for x in cx - half - 1..=cx + half + 1 {
                let edge = (x - cx).abs() == half + 1 || (y - cy).abs() == half + 1;
                self.set(x, y, if edge { outline } else { fill });
            }
        }
    }

    fn line(&mut self, from: (f64, f64), to: (f64, f64), colour: [u8; 3]) {
        let steps = ((to.0 - from.0).abs().max((to.1 - from.1).abs()).ceil() as usize).max(1);
        for k in 0..=steps {
            let t = k as f64 / steps as f64;
            let x = from.0 + (to.0 - from.0) * t;
            let y = from.1 + (to.1 - from.1) * t;
            self.set(x.round() as i64, y.round() as i64, colour);
        }
    }

    fn write(&self, path: &Path) -> Result<(), PlotError> {
        let error = |message: String| PlotError {
            path: path.display().to_string(),
            message,
        };
        let file = std::fs::File::create(path).map_err(|e| error(e.to_string()))?;
        let mut encoder = png::Encoder::new(
            std::io::BufWriter::new(file),
            self.width as u32,
            self.height as u32,
        );
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(|e| error(e.to_string()))?;
        writer
            .write_image_data(&self.rgb)
            .map_err(|e| error(e.to_string()))
    }
}

/// The region of the plots, counts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Region {
    /// Smallest x.
    pub x_min_counts: f64,
    /// Largest x.
    pub x_max_counts: f64,
    /// Smallest y.
    pub y_min_counts: f64,
    /// Largest y.
    pub y_max_counts: f64,
}

impl Region {
    /// The bounding box of the nodes, with a margin of `margin` of its size.
    pub fn around(nodes: &[NodeSample], margin: f64) -> Option<Self> {
        let first = nodes.first()?;
        let mut r = Self {
            x_min_counts: first.x_counts,
            x_max_counts: first.x_counts,
            y_min_counts: first.y_counts,
            y_max_counts: first.y_counts,
        };
        for n in nodes {
            r.x_min_counts = r.x_min_counts.min(n.x_counts);
            r.x_max_counts = r.x_max_counts.max(n.x_counts);
            r.y_min_counts = r.y_min_counts.min(n.y_counts);
            r.y_max_counts = r.y_max_counts.max(n.y_counts);
        }
        let mx = (r.x_max_counts - r.x_min_counts).max(1.0) * margin;
        let my = (r.y_max_counts - r.y_min_counts).max(1.0) * margin;
        r.x_min_counts -= mx;
        r.x_max_counts += mx;
        r.y_min_counts -= my;
        r.y_max_counts += my;
        Some(r)
    }

    fn pixel_of(self, x: f64, y: f64, size: usize) -> (f64, f64) {
        let s = (size - 1) as f64;
        (
            (x - self.x_min_counts) / (self.x_max_counts - self.x_min_counts) * s,
            // Row 0 at the top: largest y.
            (self.y_max_counts - y) / (self.y_max_counts - self.y_min_counts) * s,
        )
    }
}

/// A regression surface over `region` with the measured node values on top.
pub fn lcc_map(
    path: &Path,
    surface: &Polynomial2,
    nodes: &[(f64, f64, f64)],
    region: &Region,
) -> Result<(), PlotError> {
    const SIZE: usize = 320;
    let mut values = Vec::with_capacity(SIZE * SIZE);
    for row in 0..SIZE {
        for column in 0..SIZE {
            let x = region.x_min_counts
                + (region.x_max_counts - region.x_min_counts) * column as f64 / (SIZE - 1) as f64;
            let y = region.y_max_counts
                - (region.y_max_counts - region.y_min_counts) * row as f64 / (SIZE - 1) as f64;
            values.push(surface.evaluate(x, y));
        }
    }
    let (mut lo, mut hi) = values
        .iter()
        .chain(nodes.iter().map(|n| &n.2))
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(*v), hi.max(*v))
        });
    if hi.partial_cmp(&lo) != Some(std::cmp::Ordering::Greater) {
        lo -= 1e-12;
        hi += 1e-12;
    }
    let colour = |v: f64| ColorMap::Viridis.rgb((v - lo) / (hi - lo));
    let mut canvas = Canvas::new(SIZE, SIZE, [0, 0, 0]);
    for (i, v) in values.iter().enumerate() {
        canvas.set((i % SIZE) as i64, (i / SIZE) as i64, colour(*v));
    }
    for (x, y, v) in nodes {
        let (px, py) = region.pixel_of(*x, *y, SIZE);
        canvas.square(
            px.round() as i64,
            py.round() as i64,
            3,
            colour(*v),
            [255, 255, 255],
        );
    }
    canvas.write(path)
}

/// Drift speed against time, in nm/s through `nominal_nm_per_count`.
pub fn drift_plot(
    path: &Path,
    drift: &[DriftSample],
    nominal_nm_per_count: f64,
) -> Result<(), PlotError> {
    const W: usize = 480;
    const H: usize = 240;
    let mut canvas = Canvas::new(W, H, [16, 16, 24]);
    let speeds: Vec<(f64, f64)> = drift
        .iter()
        .map(|d| {
            (
                d.time_s,
                d.vx_counts_per_s.hypot(d.vy_counts_per_s) * nominal_nm_per_count,
            )
        })
        .filter(|(t, v)| t.is_finite() && v.is_finite())
        .collect();
    let t0 = speeds.first().map_or(0.0, |s| s.0);
    let t1 = speeds.last().map_or(1.0, |s| s.0).max(t0 + 1e-9);
    let v_max = speeds.iter().fold(1e-12_f64, |m, s| m.max(s.1));
    let to_px = |t: f64, v: f64| {
        (
            8.0 + (t - t0) / (t1 - t0) * (W - 16) as f64,
            (H - 8) as f64 - v / v_max * (H - 16) as f64,
        )
    };
    canvas.line(to_px(t0, 0.0), to_px(t1, 0.0), [96, 96, 96]);
    canvas.line(to_px(t0, 0.0), to_px(t0, v_max), [96, 96, 96]);
    for pair in speeds.windows(2) {
        canvas.line(
            to_px(pair[0].0, pair[0].1),
            to_px(pair[1].0, pair[1].1),
            [240, 240, 240],
        );
    }
    canvas.write(path)
}

/// The node centres joined in visiting order.
pub fn trajectory_plot(
    path: &Path,
    nodes: &[NodeSample],
    region: &Region,
) -> Result<(), PlotError> {
    const SIZE: usize = 320;
    let mut canvas = Canvas::new(SIZE, SIZE, [16, 16, 24]);
    let n = nodes.len().max(2) as f64;
    for (k, pair) in nodes.windows(2).enumerate() {
        let c = ColorMap::Viridis.rgb(k as f64 / (n - 1.0));
        canvas.line(
            region.pixel_of(pair[0].x_counts, pair[0].y_counts, SIZE),
            region.pixel_of(pair[1].x_counts, pair[1].y_counts, SIZE),
            c,
        );
    }
    for (k, node) in nodes.iter().enumerate() {
        let (x, y) = region.pixel_of(node.x_counts, node.y_counts, SIZE);
        let c = ColorMap::Viridis.rgb(k as f64 / (n - 1.0));
        canvas.square(x.round() as i64, y.round() as i64, 2, c, [255, 255, 255]);
    }
    canvas.write(path)
}
