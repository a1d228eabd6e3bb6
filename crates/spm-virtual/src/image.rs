//! The stored image a virtual microscope serves: heights in scanner geometry, the pixel
//! size, and the file's own pixel and line times.

use serde::{Deserialize, Serialize};

/// Smallest side of a stored image, pixels (the 4 × 4 support of the interpolation plus a
/// pixel to move in).
pub const MIN_SIDE_PX: usize = 5;

/// Why an image cannot be served.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ImageError {
    /// The image has pixels without data (NaN or infinite): an incomplete scan or a mask.
    #[error(
        "{count} pixels hold no finite height (the first at display row {first_row}, column \
         {first_column}); a virtual surface needs every pixel (crop the image to its measured part)"
    )]
    MissingData {
        /// Pixels without a finite value.
        count: usize,
        /// Display row of the first one (0 = top).
        first_row: usize,
        /// Column of the first one.
        first_column: usize,
    },
    /// Fewer pixels than the interpolation needs.
    #[error(
        "{columns} × {rows} pixels is too small: a virtual surface needs at least {MIN_SIDE_PX} × {MIN_SIDE_PX}"
    )]
    TooSmall {
        /// Columns.
        columns: usize,
        /// Rows.
        rows: usize,
    },
    /// The values do not fill the grid.
    #[error("{values} values do not fill a {columns} × {rows} grid")]
    WrongLength {
        /// Values given.
        values: usize,
        /// Columns.
        columns: usize,
        /// Rows.
        rows: usize,
    },
    /// The file states no physical size and none was given.
    #[error("the file states no physical size; give the pixel size (nm) explicitly")]
    NoPixelSize,
    /// The height unit is not a length.
    #[error("channel unit {unit:?} is not a length (metres or nanometres)")]
    NotAHeight {
        /// The unit the file names.
        unit: String,
    },
    /// A parameter is out of its range.
    #[error("{field}: {reason}")]
    Invalid {
        /// The parameter.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
}

/// How long the original raster spent per pixel and per line.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageTiming {
    /// Duration of one trace (one half of a line) of the original raster, s (> 0). The
    /// virtual scanner moves at the original speed: `line_time_s / columns` per pixel.
    pub line_time_s: f64,
}

/// What [`StoredImage::from_channel`] needs beyond the file.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChannelOptions {
    /// Pixel size, nm, for files that state no physical size (raw). Default `None`: the
    /// file's own size is used (and required).
    #[serde(default)]
    pub pixel_nm: Option<f64>,
    /// Line time, s, for files that state none (ISO 28600, raw). Default 0.1 s (a typical
    /// atomic-resolution raster).
    #[serde(default = "ChannelOptions::default_line_time_s")]
    pub fallback_line_time_s: f64,
}

impl ChannelOptions {
    /// The default fallback line time, s.
    pub const DEFAULT_LINE_TIME_S: f64 = 0.1;

    fn default_line_time_s() -> f64 {
        Self::DEFAULT_LINE_TIME_S
    }
}

impl Default for ChannelOptions {
    fn default() -> Self {
        Self {
            pixel_nm: None,
            fallback_line_time_s: Self::DEFAULT_LINE_TIME_S,
        }
    }
}

/// One stored image in scanner geometry: column index grows with x (to the right of the
/// display), row index with y (**upwards** in the display: row 0 is the display's bottom
/// line), heights in nm, every pixel finite.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredImage {
    heights_nm: Vec<f64>,
    columns: usize,
    rows: usize,
    pixel_x_nm: f64,
    pixel_y_nm: f64,
    timing: ImageTiming,
    centre_nm: [f64; 2],
}

impl StoredImage {
    /// An image from heights in scanner geometry (`[row * columns + column]`, row 0 at the
    /// smallest y).
    ///
    /// # Errors
    /// [`ImageError`] for a grid too small or not filled, pixels without data, or a pixel
    /// size or time that is not finite and positive.
    pub fn new(
        heights_nm: Vec<f64>,
        columns: usize,
        rows: usize,
        pixel_x_nm: f64,
        pixel_y_nm: f64,
        timing: ImageTiming,
    ) -> Result<Self, ImageError> {
        if columns.checked_mul(rows) != Some(heights_nm.len()) {
            return Err(ImageError::WrongLength {
                values: heights_nm.len(),
                columns,
                rows,
            });
        }
        if columns < MIN_SIDE_PX || rows < MIN_SIDE_PX {
            return Err(ImageError::TooSmall { columns, rows });
        }
        let positive = |field: &'static str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(ImageError::Invalid {
                    field,
                    reason: format!("must be finite and > 0, got {v}"),
                })
            }
        };
        positive("pixel_x_nm", pixel_x_nm)?;
        positive("pixel_y_nm", pixel_y_nm)?;
        positive("line_time_s", timing.line_time_s)?;
        let missing = heights_nm.iter().filter(|v| !v.is_finite()).count();
        if let Some(first) = heights_nm.iter().position(|v| !v.is_finite()) {
            return Err(ImageError::MissingData {
                count: missing,
                first_row: rows - 1 - first / columns,
                first_column: first % columns,
            });
        }
        Ok(Self {
            heights_nm,
            columns,
            rows,
            pixel_x_nm,
            pixel_y_nm,
            timing,
            centre_nm: [0.0, 0.0],
        })
    }

    /// The same image with its frame centred at `centre_nm` in the instrument's
    /// coordinates (the file's scan offset; [`StoredImage::new`] puts it at 0).
    ///
    /// # Errors
    /// [`ImageError::Invalid`] for a centre that is not finite.
    pub fn with_centre_nm(mut self, centre_nm: [f64; 2]) -> Result<Self, ImageError> {
        if !centre_nm.iter().all(|v| v.is_finite()) {
            return Err(ImageError::Invalid {
                field: "centre_nm",
                reason: format!("must be finite, got {centre_nm:?}"),
            });
        }
        self.centre_nm = centre_nm;
        Ok(self)
    }

    /// The same frame (size, pixels, timing, centre) with other heights, nm, in the same
    /// order: an image filtered outside this crate.
    ///
    /// # Errors
    /// [`ImageError`] for a wrong number of heights or heights that are not finite.
    pub fn with_heights_nm(&self, heights_nm: Vec<f64>) -> Result<Self, ImageError> {
        Self::new(
            heights_nm,
            self.columns,
            self.rows,
            self.pixel_x_nm,
            self.pixel_y_nm,
            self.timing,
        )?
        .with_centre_nm(self.centre_nm)
    }

    /// The frame's centre in the instrument's coordinates, nm (the file's scan offset).
    #[must_use]
    pub fn centre_nm(&self) -> [f64; 2] {
        self.centre_nm
    }

    /// One channel of a file read by spm-formats: its display-oriented heights turned into
    /// scanner geometry (display row 0, the top, becomes the largest y), metres or
    /// nanometres turned into nm, the pixel size from the file (or `options.pixel_nm`), the
    /// line time from the file (or `options.fallback_line_time_s`).
    ///
    /// # Errors
    /// [`ImageError`]: not a height channel, no size, pixels without data, too small.
    pub fn from_channel(
        channel: &spm_formats::Channel,
        options: &ChannelOptions,
    ) -> Result<Self, ImageError> {
        let scale = match channel.unit() {
            "m" => 1e9,
            "nm" => 1.0,
            other => {
                return Err(ImageError::NotAHeight {
                    unit: other.to_owned(),
                });
            }
        };
        let (nx, ny) = (channel.nx(), channel.ny());
        let (pixel_x_nm, pixel_y_nm) =
            match (options.pixel_nm, channel.pixel_x_nm(), channel.pixel_y_nm()) {
                (Some(p), _, _) => (p, p),
                (None, Some(px), Some(py)) => (px, py),
                _ => return Err(ImageError::NoPixelSize),
            };
        let line_time_s = channel
            .timing()
            .map_or(options.fallback_line_time_s, |t| t.line_time_s);
        let data = channel.data();
        let mut heights_nm = Vec::with_capacity(data.len());
        for row in 0..ny {
            let display_row = ny - 1 - row;
            let start = display_row * nx;
            let line = data.get(start..start + nx).ok_or(ImageError::WrongLength {
                values: data.len(),
                columns: nx,
                rows: ny,
            })?;
            heights_nm.extend(line.iter().map(|v| v * scale));
        }
        Self::new(
            heights_nm,
            nx,
            ny,
            pixel_x_nm,
            pixel_y_nm,
            ImageTiming { line_time_s },
        )?
        .with_centre_nm([
            channel.center_x_nm().unwrap_or(0.0),
            channel.center_y_nm().unwrap_or(0.0),
        ])
    }

    /// Heights, nm, `[row * columns + column]` in scanner geometry.
    #[must_use]
    pub fn heights_nm(&self) -> &[f64] {
        &self.heights_nm
    }

    /// Columns (x).
    #[must_use]
    pub fn columns(&self) -> usize {
        self.columns
    }

    /// Rows (y).
    #[must_use]
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Pixel size along x, nm.
    #[must_use]
    pub fn pixel_x_nm(&self) -> f64 {
        self.pixel_x_nm
    }

    /// Pixel size along y, nm.
    #[must_use]
    pub fn pixel_y_nm(&self) -> f64 {
        self.pixel_y_nm
    }

    /// The original raster's timing.
    #[must_use]
    pub fn timing(&self) -> ImageTiming {
        self.timing
    }

    /// Time the original raster spent per pixel along a line, s.
    #[must_use]
    pub fn pixel_time_s(&self) -> f64 {
        self.timing.line_time_s / self.columns as f64
    }

    /// The height at a fractional pixel coordinate by Keys cubic convolution
    /// ([`crate::interp`]), or `None` outside `[1, columns − 2] × [1, rows − 2]`.
    #[must_use]
    pub fn height_nm_at(&self, column: f64, row: f64) -> Option<f64> {
        crate::interp::Grid {
            values: &self.heights_nm,
            columns: self.columns,
            rows: self.rows,
        }
        .keys(column, row)
    }

    /// The image minus its background: the heights less their local weighted
    /// least-squares plane under a Gaussian window of width `sigma_px` pixels (kernel cut at
    /// 4 σ, normalised over the part inside the image), so a plane is removed exactly
    /// everywhere and terraces, tilt and bow are removed at scales above σ. Far from the
    /// edges a sinusoid of period `P` pixels keeps the fraction `1 − exp(−2π²σ²/P²)` of its
    /// amplitude: with σ of 1.5 lattice constants a lattice keeps more than 99.9 % of its
    /// corrugation. The plane of every pixel is the weighted least squares of the numerics
    /// kernel computed streaming from smoothed moments (one pass for all pixels), not a second
    /// solver: `tests/it/microscope.rs` checks it against `spm_regression`'s fit.
    ///
    /// # Errors
    /// [`ImageError::Invalid`] for a width that is not finite and positive.
    pub fn without_background(&self, sigma_px: f64) -> Result<Self, ImageError> {
        let mean = |v: &[f64]| self.gaussian_mean(v, sigma_px);
        let n = self.heights_nm.len();
        let xs: Vec<f64> = (0..n).map(|i| (i % self.columns) as f64).collect();
        let ys: Vec<f64> = (0..n).map(|i| (i / self.columns) as f64).collect();
        let z = &self.heights_nm;
        let product =
            |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(p, q)| p * q).collect::<Vec<_>>();
        let mz = mean(z)?;
        let mx = mean(&xs)?;
        let my = mean(&ys)?;
        let mxx = mean(&product(&xs, &xs))?;
        let myy = mean(&product(&ys, &ys))?;
        let mxy = mean(&product(&xs, &ys))?;
        let mzx = mean(&product(z, &xs))?;
        let mzy = mean(&product(z, &ys))?;
        let heights_nm = (0..n)
            .map(|i| {
                // Local weighted plane z = mz + gx (x − mx) + gy (y − my).
                let sxx = mxx[i] - mx[i] * mx[i];
                let syy = myy[i] - my[i] * my[i];
                let sxy = mxy[i] - mx[i] * my[i];
                let szx = mzx[i] - mz[i] * mx[i];
                let szy = mzy[i] - mz[i] * my[i];
                let det = sxx * syy - sxy * sxy;
                let (gx, gy) = if det > 1e-12 * (sxx * syy).max(f64::MIN_POSITIVE) {
                    ((szx * syy - szy * sxy) / det, (szy * sxx - szx * sxy) / det)
                } else {
                    (0.0, 0.0)
                };
                z[i] - (mz[i] + gx * (xs[i] - mx[i]) + gy * (ys[i] - my[i]))
            })
            .collect();
        Ok(Self {
            heights_nm,
            ..self.clone_shape()
        })
    }

    /// The image smoothed by a Gaussian of width `sigma_px` pixels (kernel cut at 4 σ,
    /// normalised over the part inside the image): a low-pass that keeps the fraction
    /// `exp(−2π²σ²/P²)` of a sinusoid of period `P` pixels (far from the edges). With σ of
    /// a tenth of a lattice constant the lattice keeps about 82 % of its corrugation while
    /// pixel noise and line noise are averaged over the window.
    ///
    /// # Errors
    /// [`ImageError::Invalid`] for a width that is not finite and positive.
    pub fn smoothed(&self, sigma_px: f64) -> Result<Self, ImageError> {
        Ok(Self {
            heights_nm: self.gaussian_mean(&self.heights_nm, sigma_px)?,
            ..self.clone_shape()
        })
    }

    /// Gaussian-weighted local means (separable, cut at 4 σ, normalised over the image).
    fn gaussian_mean(&self, values: &[f64], sigma_px: f64) -> Result<Vec<f64>, ImageError> {
        if !(sigma_px.is_finite() && sigma_px > 0.0) {
            return Err(ImageError::Invalid {
                field: "sigma_px",
                reason: format!("must be finite and > 0, got {sigma_px}"),
            });
        }
        let reach = (4.0 * sigma_px).ceil() as usize;
        let kernel: Vec<f64> = (0..=reach)
            .map(|k| (-0.5 * (k as f64 / sigma_px).powi(2)).exp())
            .collect();
        let (nx, ny) = (self.columns, self.rows);
        // One pass along x then one along y, each normalised by the weights inside.
        let pass = |input: &[f64], along_x: bool| -> Vec<f64> {
            let (lines, along) = if along_x { (ny, nx) } else { (nx, ny) };
            let index = |line: usize, k: usize| {
                if along_x {
                    line * nx + k
                } else {
                    k * nx + line
                }
            };
            let mut out = vec![0.0; input.len()];
            for line in 0..lines {
                for k in 0..along {
                    let lo = k.saturating_sub(reach);
                    let hi = (k + reach).min(along - 1);
                    let (mut sum, mut weight) = (0.0, 0.0);
                    for j in lo..=hi {
                        let w = kernel[j.abs_diff(k)];
                        sum += w * input[index(line, j)];
                        weight += w;
                    }
                    out[index(line, k)] = sum / weight;
                }
            }
            out
        };
        Ok(pass(&pass(values, true), false))
    }

    fn clone_shape(&self) -> Self {
        Self {
            heights_nm: Vec::new(),
            ..*self
        }
    }

    /// A rectangular part of the image, columns `column0 .. column0 + columns` and rows
    /// `row0 .. row0 + rows` (scanner geometry), or `None` when it leaves the image or is
    /// smaller than [`MIN_SIDE_PX`].
    #[must_use]
    pub fn crop(&self, column0: usize, row0: usize, columns: usize, rows: usize) -> Option<Self> {
        if columns < MIN_SIDE_PX
            || rows < MIN_SIDE_PX
            || column0.checked_add(columns)? > self.columns
            || row0.checked_add(rows)? > self.rows
        {
            return None;
        }
        let mut heights_nm = Vec::with_capacity(columns * rows);
        for row in row0..row0 + rows {
            let start = row * self.columns + column0;
            heights_nm.extend_from_slice(self.heights_nm.get(start..start + columns)?);
        }
        // The part's centre from the whole's (row 0 at the smallest y).
        let centre_nm = [
            self.centre_nm[0]
                + (column0 as f64 + 0.5 * columns as f64 - 0.5 * self.columns as f64)
                    * self.pixel_x_nm,
            self.centre_nm[1]
                + (row0 as f64 + 0.5 * rows as f64 - 0.5 * self.rows as f64) * self.pixel_y_nm,
        ];
        Some(Self {
            heights_nm,
            columns,
            rows,
            centre_nm,
            ..*self
        })
    }
}
