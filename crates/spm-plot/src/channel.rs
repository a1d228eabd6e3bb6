//! PNG rendering of an SPM channel: colour map, robust value range, labelled scale bar.
//! (Moved here from `spm-formats`, a file-format crate, so that the workspace has one
//! plotting stack.)

use crate::colour::ColorMap;
use crate::font::{FONT_FAMILY, register_fonts};
use crate::{PlotError, check_size, encode_png};
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use spm_formats::Channel;
use std::path::Path;

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
pub const NAN_RGB: [u8; 3] = [40, 60, 110];

/// Subtracts the least-squares plane z = a + b·x + c·y over the finite pixels.
/// The kernel's least squares (`spm_regression::least_squares` on rows 1, x, y) computed
/// streaming from nine sums, so a large image needs no n × 3 design; the test
/// `level_is_the_kernel_plane_fit` checks the two agree to 1e-9.
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
        fmt(len_nm / 1000.0, "µm")
    } else if len_nm < 1.0 {
        fmt(len_nm * 1000.0, "pm")
    } else {
        fmt(len_nm, "nm")
    }
}

/// Renders a channel (display orientation) to PNG bytes.
///
/// # Errors
/// [`PlotError::TooLarge`] for an image over 32768 px per side or 2^26 pixels after zoom;
/// [`PlotError::Font`], [`PlotError::Draw`] or [`PlotError::Encode`] otherwise.
pub fn render_png(channel: &Channel, options: &PngOptions) -> Result<Vec<u8>, PlotError> {
    let figure = format!("channel {}", channel.name());
    let (nx, ny) = (channel.nx(), channel.ny());
    let zoom = options.zoom.max(1) as usize;
    let (w, h) = (nx.saturating_mul(zoom), ny.saturating_mul(zoom));
    check_size(&figure, w, h)?;
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
    let mut rgb = vec![0u8; 3 * w * h];
    for r in 0..ny {
        for c in 0..nx {
            let v = values[r * nx + c];
            let colour = if v.is_nan() {
                NAN_RGB
            } else {
                options.color_map.rgb((v - lo) / span)
            };
            for y in r * zoom..(r + 1) * zoom {
                for x in c * zoom..(c + 1) * zoom {
                    let i = 3 * (y * w + x);
                    rgb[i..i + 3].copy_from_slice(&colour);
                }
            }
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
        let text_px = (7 * s + 4) as u32;
        if bar_px >= 4 && w > 2 * margin + bar_px && h > 4 * margin + text_px as usize + 2 {
            register_fonts()?;
            let err = |e: &dyn std::fmt::Display| PlotError::Draw {
                figure: figure.clone(),
                message: e.to_string(),
            };
            let root =
                BitMapBackend::with_buffer(&mut rgb, (w as u32, h as u32)).into_drawing_area();
            let y = (h - margin - thick) as i32;
            let (m, b, t) = (margin as i32, bar_px as i32, thick as i32);
            root.draw(&Rectangle::new(
                [(m - 1, y - 1), (m + b + 1, y + t + 1)],
                BLACK.filled(),
            ))
            .map_err(|e| err(&e))?;
            root.draw(&Rectangle::new([(m, y), (m + b, y + t)], WHITE.filled()))
                .map_err(|e| err(&e))?;
            let label = label_for(len_nm);
            let at = (m, y - 3);
            let style = |colour: &RGBColor| {
                (FONT_FAMILY, text_px)
                    .into_font()
                    .color(colour)
                    .pos(Pos::new(HPos::Left, VPos::Bottom))
            };
            // A black halo, then the white text.
            for (dx, dy) in [(-1, 0), (1, 0), (0, -1), (0, 1)] {
                root.draw(&Text::new(
                    label.clone(),
                    (at.0 + dx, at.1 + dy),
                    style(&BLACK),
                ))
                .map_err(|e| err(&e))?;
            }
            root.draw(&Text::new(label, at, style(&WHITE)))
                .map_err(|e| err(&e))?;
            root.present().map_err(|e| err(&e))?;
        }
    }
    encode_png(&figure, w, h, &rgb)
}

/// Renders a channel and writes the PNG file.
///
/// # Errors
/// As [`render_png`], and [`PlotError::Io`] when the file cannot be written.
pub fn write_png(
    path: impl AsRef<Path>,
    channel: &Channel,
    options: &PngOptions,
) -> Result<(), PlotError> {
    let bytes = render_png(channel, options)?;
    crate::write_file(path.as_ref(), &bytes)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// The streamed plane equals the kernel's least-squares plane on pseudo-random data with
    /// unscanned (NaN) pixels, to 1e-9.
    #[test]
    fn level_is_the_kernel_plane_fit() {
        let (nx, ny) = (37, 23);
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let data: Vec<f64> = (0..nx * ny)
            .map(|k| {
                let (x, y) = ((k % nx) as f64, (k / nx) as f64);
                if k % 17 == 3 {
                    f64::NAN
                } else {
                    40.0 + 0.3 * x - 0.7 * y + 5.0 * next()
                }
            })
            .collect();
        let finite: Vec<usize> = (0..data.len()).filter(|&k| data[k].is_finite()).collect();
        let rows: Vec<Vec<f64>> = finite
            .iter()
            .map(|&k| vec![1.0, (k % nx) as f64, (k / nx) as f64])
            .collect();
        let rhs: Vec<f64> = finite.iter().map(|&k| data[k]).collect();
        let fit = spm_regression::least_squares(&rows, &rhs, &[false; 3]).unwrap();
        let levelled = level(&data, nx, ny);
        for (k, (&z, l)) in data.iter().zip(&levelled).enumerate() {
            let (x, y) = ((k % nx) as f64, (k / nx) as f64);
            let c = &fit.coefficients;
            let expected = z - (c[0] + c[1] * x + c[2] * y);
            if z.is_finite() {
                assert!((l - expected).abs() < 1e-9, "pixel {k}: {l} vs {expected}");
            } else {
                assert!(l.is_nan());
            }
        }
    }
}
