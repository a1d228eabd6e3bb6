//! PNG rendering of a channel: colour map, robust value range, scale bar with a small label.
//!
//! The label is drawn with a built-in 3×5 pixel font (digits, '.', 'n', 'm', 'p', 'u'), so no
//! font dependency is needed.

use std::path::Path;

use crate::error::{Ctx, FormatError, Result};
use crate::model::Channel;

/// Colour maps for height images.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[non_exhaustive]
pub enum ColorMap {
    /// Black to white.
    Gray,
    /// Black – brown – orange – yellow – white, the usual STM "afmhot".
    #[default]
    AfmHot,
    /// Dark blue – teal – green – yellow (perceptually ordered, viridis-like).
    Viridis,
}

impl ColorMap {
    /// The colour for `t` in [0, 1].
    pub fn rgb(self, t: f64) -> [u8; 3] {
        let t = if t.is_finite() {
            t.clamp(0.0, 1.0)
        } else {
            0.0
        };
        let q = |v: f64| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
        match self {
            ColorMap::Gray => {
                let g = q(t);
                [g, g, g]
            }
            ColorMap::AfmHot => [q(2.0 * t), q(2.0 * t - 0.5), q(2.0 * t - 1.0)],
            ColorMap::Viridis => {
                const STOPS: [[f64; 3]; 5] = [
                    [0.267, 0.005, 0.329],
                    [0.229, 0.322, 0.546],
                    [0.128, 0.567, 0.551],
                    [0.369, 0.789, 0.383],
                    [0.993, 0.906, 0.144],
                ];
                let x = t * 4.0;
                let i = (x.floor() as usize).min(3);
                let f = x - i as f64;
                let c = |k: usize| STOPS[i][k] + (STOPS[i + 1][k] - STOPS[i][k]) * f;
                [q(c(0)), q(c(1)), q(c(2))]
            }
        }
    }
}

/// How to render a channel.
#[derive(Debug, Clone, PartialEq)]
pub struct PngOptions {
    /// The colour map.
    pub color_map: ColorMap,
    /// Value range mapped to the ends of the colour map; `None` = robust range from the
    /// `clip_fraction` and `1 − clip_fraction` quantiles.
    pub range: Option<(f64, f64)>,
    /// Fraction of pixels clipped at each end of the automatic range (default 0.005).
    pub clip_fraction: f64,
    /// Subtract a least-squares plane before colouring (default true).
    pub level_plane: bool,
    /// Draw a scale bar when the physical size is known (default true).
    pub scale_bar: bool,
    /// Integer magnification of every pixel (1 = one image pixel per PNG pixel).
    pub zoom: u32,
}

impl Default for PngOptions {
    fn default() -> Self {
        Self {
            color_map: ColorMap::AfmHot,
            range: None,
            clip_fraction: 0.005,
            level_plane: true,
            scale_bar: true,
            zoom: 1,
        }
    }
}

/// Colour shown for NaN pixels (unscanned parts of an incomplete frame).
const NAN_RGB: [u8; 3] = [40, 60, 110];

/// Subtracts the least-squares plane z = a + b·x + c·y over the finite pixels.
fn level(data: &[f64], nx: usize, ny: usize) -> Vec<f64> {
    let (mut n, mut sx, mut sy, mut sz) = (0.0, 0.0, 0.0, 0.0);
    let (mut sxx, mut syy, mut sxy, mut sxz, mut syz) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for r in 0..ny {
        for c in 0..nx {
            let z = data[r * nx + c];
            if !z.is_finite() {
                continue;
            }
            let (x, y) = (c as f64, r as f64);
            n += 1.0;
            sx += x;
            sy += y;
            sz += z;
            sxx += x * x;
            syy += y * y;
            sxy += x * y;
            sxz += x * z;
            syz += y * z;
        }
    }
    if n < 3.0 {
        return data.to_vec();
    }
    // Centred normal equations for b, c.
    let (mx, my, mz) = (sx / n, sy / n, sz / n);
    let cxx = sxx / n - mx * mx;
    let cyy = syy / n - my * my;
    let cxy = sxy / n - mx * my;
    let cxz = sxz / n - mx * mz;
    let cyz = syz / n - my * mz;
    let det = cxx * cyy - cxy * cxy;
    let (b, c) = if det.abs() > 1e-12 * (cxx * cyy).abs().max(f64::MIN_POSITIVE) {
        ((cxz * cyy - cyz * cxy) / det, (cyz * cxx - cxz * cxy) / det)
    } else {
        (0.0, 0.0)
    };
    data.iter()
        .enumerate()
        .map(|(i, &z)| {
            let (x, y) = ((i % nx) as f64, (i / nx) as f64);
            z - mz - b * (x - mx) - c * (y - my)
        })
        .collect()
}

fn quantile_range(values: &[f64], clip: f64) -> Option<(f64, f64)> {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let clip = if clip.is_finite() {
        clip.clamp(0.0, 0.49)
    } else {
        0.0
    };
    let last = v.len() - 1;
    let lo = v[((last as f64) * clip).round() as usize];
    let hi = v[((last as f64) * (1.0 - clip)).round() as usize];
    Some((lo, hi))
}

/// 3×5 glyphs, one row per u8 (3 low bits, MSB = left column).
fn glyph(c: char) -> Option<[u8; 5]> {
    Some(match c {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 1, 1],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '.' => [0, 0, 0, 0, 2],
        'n' => [0, 0, 6, 5, 5],
        'm' => [0, 0, 7, 7, 5],
        'p' => [0, 6, 5, 6, 4],
        'u' => [0, 0, 5, 5, 7],
        ' ' => [0, 0, 0, 0, 0],
        _ => return None,
    })
}

struct Canvas {
    w: usize,
    h: usize,
    rgb: Vec<u8>,
}

impl Canvas {
    fn put(&mut self, x: usize, y: usize, c: [u8; 3]) {
        if x < self.w && y < self.h {
            let i = 3 * (y * self.w + x);
            self.rgb[i..i + 3].copy_from_slice(&c);
        }
    }

    fn rect(&mut self, x0: usize, y0: usize, w: usize, h: usize, c: [u8; 3]) {
        for y in y0..y0 + h {
            for x in x0..x0 + w {
                self.put(x, y, c);
            }
        }
    }

    /// Draws `text` with its top-left corner at (x, y), each font pixel `s`×`s`, outlined.
    fn text(&mut self, x: usize, y: usize, s: usize, text: &str) {
        for pass in 0..2 {
            for (k, ch) in text.chars().enumerate() {
                let Some(g) = glyph(ch) else { continue };
                for (row, bits) in g.iter().enumerate() {
                    for col in 0..3 {
                        if bits & (4 >> col) == 0 {
                            continue;
                        }
                        let px = x + (4 * k + col) * s;
                        let py = y + row * s;
                        if pass == 0 {
                            // black outline
                            self.rect(
                                px.saturating_sub(1),
                                py.saturating_sub(1),
                                s + 2,
                                s + 2,
                                [0, 0, 0],
                            );
                        } else {
                            self.rect(px, py, s, s, [255, 255, 255]);
                        }
                    }
                }
            }
        }
    }
}

/// A "nice" bar length (1, 2 or 5 × 10^k nm) close to a quarter of the width.
fn nice_length_nm(width_nm: f64) -> f64 {
    let target = width_nm / 4.0;
    let p = 10f64.powf(target.log10().floor());
    let m = target / p;
    let f = if m >= 5.0 {
        5.0
    } else if m >= 2.0 {
        2.0
    } else {
        1.0
    };
    f * p
}

fn label_for(len_nm: f64) -> String {
    let fmt = |v: f64, unit: &str| {
        if (v - v.round()).abs() < 1e-9 {
            format!("{} {unit}", v.round() as i64)
        } else {
            format!("{v} {unit}")
        }
    };
    if len_nm >= 1000.0 {
        fmt(len_nm / 1000.0, "um")
    } else if len_nm < 1.0 {
        fmt(len_nm * 1000.0, "pm")
    } else {
        fmt(len_nm, "nm")
    }
}

/// Renders a channel (display orientation) to PNG bytes.
pub fn render_png(channel: &Channel, options: &PngOptions) -> Result<Vec<u8>> {
    let placeholder = crate::text::memory_path("png");
    render_with_ctx(channel, options, Ctx::new(&placeholder))
}

fn render_with_ctx(channel: &Channel, options: &PngOptions, ctx: Ctx<'_>) -> Result<Vec<u8>> {
    let (nx, ny) = (channel.nx(), channel.ny());
    let zoom = options.zoom.max(1) as usize;
    let (w, h) = (nx.saturating_mul(zoom), ny.saturating_mul(zoom));
    if w > 1 << 15 || h > 1 << 15 || w.saturating_mul(h) > 1 << 26 {
        return Err(ctx.invalid_input(format!(
            "rendered image {w}×{h} exceeds 32768 px per side or 2^26 pixels"
        )));
    }
    let values = if options.level_plane {
        level(channel.data(), nx, ny)
    } else {
        channel.data().to_vec()
    };
    let (lo, hi) = match options.range {
        Some(r) => r,
        None => quantile_range(&values, options.clip_fraction).unwrap_or((0.0, 1.0)),
    };
    let span = if (hi - lo).abs() > 0.0 && (hi - lo).is_finite() {
        hi - lo
    } else {
        1.0
    };
    let mut canvas = Canvas {
        w,
        h,
        rgb: vec![0; 3 * w * h],
    };
    for r in 0..ny {
        for c in 0..nx {
            let v = values[r * nx + c];
            let rgb = if v.is_nan() {
                NAN_RGB
            } else {
                options.color_map.rgb((v - lo) / span)
            };
            canvas.rect(c * zoom, r * zoom, zoom, zoom, rgb);
        }
    }
    if options.scale_bar
        && let Some(width_nm) = channel.size_x_nm().filter(|s| *s > 0.0 && s.is_finite())
    {
        let len_nm = nice_length_nm(width_nm);
        let bar_px = ((len_nm / width_nm) * w as f64).round() as usize;
        let s = (w / 256).max(1);
        let thick = 3 * s;
        let margin = 6 * s;
        if bar_px >= 4 && w > 2 * margin + bar_px && h > 4 * margin + 8 * s {
            let y = h - margin - thick;
            canvas.rect(margin - 1, y - 1, bar_px + 2, thick + 2, [0, 0, 0]);
            canvas.rect(margin, y, bar_px, thick, [255, 255, 255]);
            canvas.text(margin, y - 7 * s, s, &label_for(len_nm));
        }
    }
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, w as u32, h as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let err = |e: png::EncodingError| ctx.invalid_input(format!("PNG encoding failed: {e}"));
        let mut writer = enc.write_header().map_err(err)?;
        writer.write_image_data(&canvas.rgb).map_err(err)?;
        writer.finish().map_err(err)?;
    }
    Ok(out)
}

/// Renders a channel and writes the PNG file.
pub fn write_png(path: impl AsRef<Path>, channel: &Channel, options: &PngOptions) -> Result<()> {
    let path = path.as_ref();
    let bytes = render_with_ctx(channel, options, Ctx::new(path))?;
    std::fs::write(path, bytes).map_err(|source| FormatError::Io {
        path: path.to_path_buf(),
        action: "cannot write",
        source,
    })
}
