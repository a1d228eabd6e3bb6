//! Corrected coordinates of every pixel of a direct or counter raster (eqs. 7–9, 12).
//!
//! # Paths
//! Pixel (i, j) (column i, row j in scanner geometry, as in [`spm_hal::HeightMap`]) sits at the
//! commanded position (x_i, y_j) = (x₀ + i·h, y₀ + j·h). With retrace, the scanner reaches it
//!
//! - **direct image** (starts at the origin corner (x₀, y₀)): up the line-start column x = x₀
//!   from y₀ to y_j, then along the line +x from x₀ to x_i (eqs. 8, 9):
//!   ```text
//!   x̄_d(i,j) = ∫_{x₀}^{x_i} K̄x(s, y_j) ds + ∫_{y₀}^{y_j} K̄yx(x₀, t) dt
//!   ȳ_d(j)   = ∫_{y₀}^{y_j} K̄yy(x₀, t) dt
//!   ```
//! - **counter image** (starts at the far corner (X, Y) = (x₀ + x_max, y₀ + y_max)): down the
//!   line-start column x = X from Y to y_j, then along the line −x from X to x_i. Every step is
//!   negative, so each integral enters with its orientation:
//!   ```text
//!   x̄_c(i,j) = x̄_d(X,Y) − ∫_{x_i}^{X} K̄x(s, y_j) ds − ∫_{y_j}^{Y} K̄yx(X, t) dt
//!   ȳ_c(j)   = ȳ_d(Y)   − ∫_{y_j}^{Y} K̄yy(X, t) dt
//!   ```
//!
//! # Common frame
//! Both maps are in nm relative to the corrected origin corner of the direct image. The counter
//! path starts at the far corner, so the counter map is anchored there at the far corner's
//! direct-image value x̄_d(X, Y), ȳ_d(Y) (the point where the two rasters physically meet).
//! Then for the same pixel
//! ```text
//! (x̄_c − x̄_d)(i,j) = ∮ ω  around the rectangle [x₀, X] × [y_j, Y], clockwise
//!                   = −∬ (∂K̄yx/∂x − ∂K̄x/∂y) dA,    (ȳ_c − ȳ_d)(j) = −∬ ∂K̄yy/∂x dA
//! ```
//! (Green's theorem): zero for every pixel exactly when the 1-form is closed (path-independent
//! correction), independent of the column, and zero on the last row.

use spm_hal::{CountPoint, Counts, HeightMap, NmPoint, ScanDirection, ScanRequest};

use crate::error::check_finite_scalar;
use crate::field::CorrectionField;
use crate::parallel::{Parallelism, for_each_row};
use crate::{CorrectionError, Quadrature};

/// The commanded pixel grid of a raster in scanner counts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RasterGeometry {
    /// Commanded position of column 0, row 0 (the origin corner), counts.
    pub origin: CountPoint,
    /// Pixel spacing along both axes, counts (> 0).
    pub pixel_step: Counts,
    /// Pixels per line (x).
    pub columns: usize,
    /// Lines (y).
    pub rows: usize,
}

impl RasterGeometry {
    /// A validated geometry.
    ///
    /// # Errors
    /// [`CorrectionError::NonFinite`] for a non-finite origin or step,
    /// [`CorrectionError::InvalidArgument`] for a step ≤ 0, [`CorrectionError::Empty`] for zero
    /// columns or rows.
    pub fn new(
        origin: CountPoint,
        pixel_step: Counts,
        columns: usize,
        rows: usize,
    ) -> Result<Self, CorrectionError> {
        check_finite_scalar("origin x", origin.x.value())?;
        check_finite_scalar("origin y", origin.y.value())?;
        check_finite_scalar("pixel step", pixel_step.value())?;
        if pixel_step.value() <= 0.0 {
            return Err(CorrectionError::InvalidArgument(format!(
                "pixel step must be > 0 counts, got {}",
                pixel_step.value()
            )));
        }
        if columns == 0 || rows == 0 {
            return Err(CorrectionError::Empty("raster with zero columns or rows"));
        }
        Ok(Self {
            origin,
            pixel_step,
            columns,
            rows,
        })
    }

    /// The geometry of a height map.
    ///
    /// # Errors
    /// As [`RasterGeometry::new`].
    pub fn of_height_map(map: &HeightMap) -> Result<Self, CorrectionError> {
        Self::new(map.origin, map.pixel_step, map.columns, map.rows)
    }

    /// The geometry of a scan request.
    ///
    /// # Errors
    /// As [`RasterGeometry::new`].
    pub fn of_request(request: &ScanRequest) -> Result<Self, CorrectionError> {
        Self::new(
            request.origin,
            request.pixel_step,
            request.pixels_per_line as usize,
            request.lines as usize,
        )
    }

    /// Number of pixels.
    #[must_use]
    pub fn pixel_count(&self) -> usize {
        self.columns * self.rows
    }

    /// x of column `i`, counts.
    #[inline]
    #[must_use]
    pub fn x_counts(&self, column: f64) -> f64 {
        self.origin.x.value() + self.pixel_step.value() * column
    }

    /// y of row `j`, counts.
    #[inline]
    #[must_use]
    pub fn y_counts(&self, row: f64) -> f64 {
        self.origin.y.value() + self.pixel_step.value() * row
    }

    /// The far corner (X, Y) = (x₀ + x_max, y₀ + y_max), counts.
    #[must_use]
    pub fn far_corner(&self) -> CountPoint {
        CountPoint::from_counts(
            self.x_counts((self.columns - 1) as f64),
            self.y_counts((self.rows - 1) as f64),
        )
    }
}

/// How the path integrals are evaluated.
#[derive(Debug, Clone, PartialEq)]
pub enum Integration {
    /// Eq. (8): sums of the coefficients over unit (1-count) steps, each taken at the point
    /// the step arrives at (eq. 5). Needs an integer pixel step. Costs O(pixel step) per pixel.
    Sums,
    /// Eq. (9) by Gauss–Legendre quadrature over every pixel gap, ignoring analytic integrals
    /// (the cross-check, and the route for non-polynomial fields).
    Quadrature(Quadrature),
    /// Eq. (9) analytically where the field allows (eq. 12 for polynomials, eq. 10 for planes),
    /// the given quadrature elsewhere (e.g. K̄y^r sin α^r of non-planar surfaces).
    Analytic(Quadrature),
}

impl Default for Integration {
    fn default() -> Self {
        Self::Analytic(Quadrature::standard())
    }
}

/// ȳ of a coordinate map: one value per row (raster corrections, eq. 9: ȳ depends only on the
/// line) or one per pixel (after drift correction).
#[derive(Debug, Clone, PartialEq)]
pub enum YCoordinates {
    /// ȳ of every row, nm.
    PerRow(Vec<f64>),
    /// ȳ of every pixel, nm, `[row * columns + column]`.
    PerPixel(Vec<f64>),
}

/// Corrected coordinates (nm) of every pixel of a raster, in scanner geometry.
///
/// Memory: x̄ is stored per pixel; ȳ per row when it depends only on the row (raster
/// corrections), so a map costs one image-sized buffer.
#[derive(Debug, Clone, PartialEq)]
pub struct CoordinateMap {
    columns: usize,
    rows: usize,
    x_nm: Vec<f64>,
    y_nm: YCoordinates,
}

impl CoordinateMap {
    /// A map from its parts.
    ///
    /// # Errors
    /// [`CorrectionError::Empty`], [`CorrectionError::SizeMismatch`],
    /// [`CorrectionError::NonFinite`].
    pub fn new(
        columns: usize,
        rows: usize,
        x_nm: Vec<f64>,
        y_nm: YCoordinates,
    ) -> Result<Self, CorrectionError> {
        if columns == 0 || rows == 0 {
            return Err(CorrectionError::Empty(
                "coordinate map with zero columns or rows",
            ));
        }
        let n = columns
            .checked_mul(rows)
            .ok_or(CorrectionError::Empty("coordinate map size overflows"))?;
        if x_nm.len() != n {
            return Err(CorrectionError::SizeMismatch {
                what: "x_nm",
                expected: n,
                got: x_nm.len(),
            });
        }
        let (len, expected) = match &y_nm {
            YCoordinates::PerRow(v) => (v.len(), rows),
            YCoordinates::PerPixel(v) => (v.len(), n),
        };
        if len != expected {
            return Err(CorrectionError::SizeMismatch {
                what: "y_nm",
                expected,
                got: len,
            });
        }
        crate::error::check_finite("x_nm", &x_nm)?;
        match &y_nm {
            YCoordinates::PerRow(v) | YCoordinates::PerPixel(v) => {
                crate::error::check_finite("y_nm", v)?;
            }
        }
        Ok(Self {
            columns,
            rows,
            x_nm,
            y_nm,
        })
    }

    /// Pixels per line.
    #[must_use]
    pub fn columns(&self) -> usize {
        self.columns
    }

    /// Lines.
    #[must_use]
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// x̄ of every pixel, nm, `[row * columns + column]`.
    #[must_use]
    pub fn x_nm(&self) -> &[f64] {
        &self.x_nm
    }

    /// ȳ, per row or per pixel.
    #[must_use]
    pub fn y_nm(&self) -> &YCoordinates {
        &self.y_nm
    }

    /// Consumes the map into its x̄ buffer and ȳ.
    #[must_use]
    pub fn into_parts(self) -> (Vec<f64>, YCoordinates) {
        (self.x_nm, self.y_nm)
    }

    /// ȳ of pixel (column, row) (no bounds check beyond the slice's).
    #[inline]
    pub(crate) fn y_at(&self, column: usize, row: usize) -> f64 {
        match &self.y_nm {
            YCoordinates::PerRow(v) => v[row],
            YCoordinates::PerPixel(v) => v[row * self.columns + column],
        }
    }

    /// Corrected position of pixel (column, row), or `None` outside the map.
    #[must_use]
    pub fn point(&self, column: usize, row: usize) -> Option<NmPoint> {
        (column < self.columns && row < self.rows).then(|| {
            NmPoint::from_nm(
                self.x_nm[row * self.columns + column],
                self.y_at(column, row),
            )
        })
    }

    /// Bilinear interpolation of the map at a fractional pixel (column, row), or `None` outside
    /// [0, columns − 1] × [0, rows − 1] or for a non-finite coordinate.
    #[must_use]
    pub fn interpolate(&self, column: f64, row: f64) -> Option<NmPoint> {
        let (cmax, rmax) = ((self.columns - 1) as f64, (self.rows - 1) as f64);
        if !(column >= 0.0 && row >= 0.0 && column <= cmax && row <= rmax) {
            return None;
        }
        let i = (column.floor() as usize).min(self.columns.saturating_sub(2));
        let j = (row.floor() as usize).min(self.rows.saturating_sub(2));
        let (fx, fy) = (column - i as f64, row - j as f64);
        let i1 = (i + 1).min(self.columns - 1);
        let j1 = (j + 1).min(self.rows - 1);
        let blend = |v00: f64, v10: f64, v01: f64, v11: f64| {
            (v00 * (1.0 - fx) + v10 * fx) * (1.0 - fy) + (v01 * (1.0 - fx) + v11 * fx) * fy
        };
        let x = |c: usize, r: usize| self.x_nm[r * self.columns + c];
        Some(NmPoint::from_nm(
            blend(x(i, j), x(i1, j), x(i, j1), x(i1, j1)),
            blend(
                self.y_at(i, j),
                self.y_at(i1, j),
                self.y_at(i, j1),
                self.y_at(i1, j1),
            ),
        ))
    }

    /// The bounding box, reading only the first and last column of x̄ when ȳ is per row
    /// (raster maps, whose lines are monotone in x̄ wherever they can be resampled); the full
    /// [`CoordinateMap::bounds_nm`] otherwise.
    pub(crate) fn bounds_nm_fast(&self) -> (f64, f64, f64, f64) {
        match &self.y_nm {
            YCoordinates::PerPixel(_) => self.bounds_nm(),
            YCoordinates::PerRow(y) => {
                let nx = self.columns;
                let edge = |offset: usize| {
                    self.x_nm
                        .iter()
                        .skip(offset)
                        .step_by(nx)
                        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &t| {
                            (lo.min(t), hi.max(t))
                        })
                };
                let (a_lo, a_hi) = edge(0);
                let (b_lo, b_hi) = edge(nx - 1);
                let (y_lo, y_hi) = y
                    .iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &t| {
                        (lo.min(t), hi.max(t))
                    });
                (a_lo.min(b_lo), a_hi.max(b_hi), y_lo, y_hi)
            }
        }
    }

    /// The bounding box (min x̄, max x̄, min ȳ, max ȳ), nm.
    #[must_use]
    pub fn bounds_nm(&self) -> (f64, f64, f64, f64) {
        let (x0, x1) = min_max(&self.x_nm);
        let (y0, y1) = match &self.y_nm {
            YCoordinates::PerRow(v) | YCoordinates::PerPixel(v) => min_max(v),
        };
        (x0, x1, y0, y1)
    }
}

/// ∫ from a to b of g by eq. (8) sums over unit steps (value at the arrival point) or by
/// quadrature.
///
/// Implements eq. (8): the sums over unit steps.
fn gap_integral(
    integration: &Integration,
    a: f64,
    b: f64,
    g: impl Fn(f64) -> f64,
) -> Result<f64, CorrectionError> {
    match integration {
        Integration::Sums => {
            let steps = (b - a).abs().round();
            if steps > 1e9 {
                return Err(CorrectionError::InvalidArgument(format!(
                    "{steps} unit steps in one gap"
                )));
            }
            let sign = if b >= a { 1.0 } else { -1.0 };
            let mut s = 0.0;
            for k in 1..=(steps as u64) {
                s += g(a + sign * k as f64);
            }
            Ok(sign * s)
        }
        Integration::Quadrature(q) | Integration::Analytic(q) => Ok(q.integrate(a, b, g)),
    }
}

/// Which line-start column integral.
#[derive(Clone, Copy)]
enum Column {
    Kyx,
    Kyy,
}

/// ∫ from y(row_anchor) to y(j) of K̄yx or K̄yy along the column x, for every row j.
///
/// Implements eq. (9): the y integrals along the line-start column.
fn column_integrals<F: CorrectionField + ?Sized>(
    field: &F,
    geometry: &RasterGeometry,
    integration: &Integration,
    x_counts: f64,
    anchor_row: usize,
    which: Column,
) -> Result<Vec<f64>, CorrectionError> {
    let rows = geometry.rows;
    let mut out = vec![0.0; rows];
    let y = |j: usize| geometry.y_counts(j as f64);
    let pick = |t: f64| {
        let f = field.form(x_counts, t);
        match which {
            Column::Kyx => f.kyx_nm_per_count,
            Column::Kyy => f.kyy_nm_per_count,
        }
    };
    let analytic = |a: f64, b: f64| match (integration, which) {
        (Integration::Analytic(_), Column::Kyx) => field.integral_kyx_along_y(x_counts, a, b),
        (Integration::Analytic(_), Column::Kyy) => field.integral_kyy_along_y(x_counts, a, b),
        _ => None,
    };
    let y_anchor = y(anchor_row);
    // Analytic: each row directly from the anchor (no accumulation).
    if analytic(y_anchor, y_anchor).is_some() {
        for (j, o) in out.iter_mut().enumerate() {
            *o = analytic(y_anchor, y(j)).unwrap_or(0.0);
        }
        return Ok(out);
    }
    // Otherwise accumulate gap by gap outward from the anchor.
    for j in (anchor_row + 1)..rows {
        out[j] = out[j - 1] + gap_integral(integration, y(j - 1), y(j), pick)?;
    }
    for j in (0..anchor_row).rev() {
        out[j] = out[j + 1] + gap_integral(integration, y(j + 1), y(j), pick)?;
    }
    Ok(out)
}

/// ∫ from x(anchor_column) to x(i) of K̄x along the line y, for every column (into `out`).
///
/// Implements eq. (9): the x integral along a line.
fn line_integrals<F: CorrectionField + ?Sized>(
    field: &F,
    geometry: &RasterGeometry,
    integration: &Integration,
    y_counts: f64,
    anchor_column: usize,
    offset_nm: f64,
    out: &mut [f64],
) -> Result<(), CorrectionError> {
    let x = |i: usize| geometry.x_counts(i as f64);
    let x_anchor = x(anchor_column);
    if let Integration::Analytic(_) = integration {
        if let Some(line) = field.kx_line(y_counts) {
            let a0 = line.evaluate(x_anchor);
            let (x0, h) = (geometry.origin.x.value(), geometry.pixel_step.value());
            line.fill_uniform(x0, h, offset_nm - a0, out);
            return Ok(());
        }
        if field
            .integral_kx_along_x(x_anchor, x_anchor, y_counts)
            .is_some()
        {
            for (i, o) in out.iter_mut().enumerate() {
                *o = offset_nm
                    + field
                        .integral_kx_along_x(x_anchor, x(i), y_counts)
                        .unwrap_or(0.0);
            }
            return Ok(());
        }
    }
    let g = |s: f64| field.form(s, y_counts).kx_nm_per_count;
    out[anchor_column] = offset_nm;
    for i in (anchor_column + 1)..out.len() {
        out[i] = out[i - 1] + gap_integral(integration, x(i - 1), x(i), g)?;
    }
    for i in (0..anchor_column).rev() {
        out[i] = out[i + 1] + gap_integral(integration, x(i + 1), x(i), g)?;
    }
    Ok(())
}

/// The per-row data of a raster correction: x̄ of any line can be computed on demand
/// ([`RasterLines::fill_row`]), so a fused correction + resampling never stores the whole map.
pub(crate) struct RasterLines<'f, F: ?Sized> {
    field: &'f F,
    pub(crate) geometry: RasterGeometry,
    integration: Integration,
    anchor_column: usize,
    /// x̄ at the anchor column of every row (anchor + line-start column integral), nm.
    offsets_nm: Vec<f64>,
    /// ȳ of every row, nm.
    pub(crate) y_per_row: Vec<f64>,
}

impl<'f, F: CorrectionField + ?Sized> RasterLines<'f, F> {
    pub(crate) fn new(
        field: &'f F,
        geometry: &RasterGeometry,
        direction: ScanDirection,
        integration: &Integration,
    ) -> Result<Self, CorrectionError> {
        let geometry = RasterGeometry::new(
            geometry.origin,
            geometry.pixel_step,
            geometry.columns,
            geometry.rows,
        )?;
        let h = geometry.pixel_step.value();
        if matches!(integration, Integration::Sums) && h.fract() != 0.0 {
            return Err(CorrectionError::NonIntegerStep {
                pixel_step_counts: h,
            });
        }
        let (nx, ny) = (geometry.columns, geometry.rows);
        let far = geometry.far_corner();
        // Direct-image column integrals at x₀ from row 0.
        let x0 = geometry.origin.x.value();
        let d_yx = column_integrals(field, &geometry, integration, x0, 0, Column::Kyx)?;
        let d_yy = column_integrals(field, &geometry, integration, x0, 0, Column::Kyy)?;
        let (col_yx, col_yy, anchor_column, anchor_x, anchor_y) = match direction {
            ScanDirection::Direct => (d_yx, d_yy, 0, 0.0, 0.0),
            ScanDirection::Counter => {
                // The far corner's direct-image value anchors the counter path.
                let mut top = vec![0.0; nx];
                line_integrals(
                    field,
                    &geometry,
                    integration,
                    far.y.value(),
                    0,
                    d_yx[ny - 1],
                    &mut top,
                )?;
                let anchor_x = top[nx - 1];
                let anchor_y = d_yy[ny - 1];
                let c_yx = column_integrals(
                    field,
                    &geometry,
                    integration,
                    far.x.value(),
                    ny - 1,
                    Column::Kyx,
                )?;
                let c_yy = column_integrals(
                    field,
                    &geometry,
                    integration,
                    far.x.value(),
                    ny - 1,
                    Column::Kyy,
                )?;
                (c_yx, c_yy, nx - 1, anchor_x, anchor_y)
            }
        };
        crate::error::check_finite("line-start column integral", &col_yx)?;
        crate::error::check_finite("line-start column integral", &col_yy)?;
        let y_per_row: Vec<f64> = col_yy.iter().map(|v| anchor_y + v).collect();
        crate::error::check_finite("y_nm", &y_per_row)?;
        let offsets_nm = col_yx.iter().map(|v| anchor_x + v).collect();
        Ok(Self {
            field,
            geometry,
            integration: integration.clone(),
            anchor_column,
            offsets_nm,
            y_per_row,
        })
    }

    /// x̄ of every pixel of row `j` into `out` (length `columns`), checked finite.
    pub(crate) fn fill_row(&self, j: usize, out: &mut [f64]) -> Result<(), CorrectionError> {
        let y = self.geometry.y_counts(j as f64);
        line_integrals(
            self.field,
            &self.geometry,
            &self.integration,
            y,
            self.anchor_column,
            self.offsets_nm[j],
            out,
        )?;
        crate::error::check_finite("x_nm", out)
    }

    /// (x̄ of column 0, x̄ of the last column) of every row: the line integral over the whole
    /// line, O(rows) (a two-column raster with the same ends).
    pub(crate) fn edges(&self) -> Result<Vec<(f64, f64)>, CorrectionError> {
        let g = &self.geometry;
        let nx = g.columns;
        if nx == 1 {
            return Ok(self.offsets_nm.iter().map(|&v| (v, v)).collect());
        }
        let wide = RasterGeometry::new(
            g.origin,
            Counts(g.pixel_step.value() * (nx - 1) as f64),
            2,
            g.rows,
        )?;
        let anchor = if self.anchor_column == 0 { 0 } else { 1 };
        let mut pair = [0.0; 2];
        let mut out = Vec::with_capacity(g.rows);
        for j in 0..g.rows {
            line_integrals(
                self.field,
                &wide,
                &self.integration,
                g.y_counts(j as f64),
                anchor,
                self.offsets_nm[j],
                &mut pair,
            )?;
            out.push((pair[0], pair[1]));
        }
        Ok(out)
    }
}

/// Corrected coordinates of every pixel of a direct or counter raster, in the common frame
/// (nm from the corrected origin corner of the direct image; a counter map is anchored at the
/// far corner's direct-image value, where the two rasters physically meet).
///
/// Implements eq. (7): every pixel of a direct or counter raster.
///
/// # Errors
/// [`CorrectionError::NonIntegerStep`] for [`Integration::Sums`] with a fractional pixel step;
/// [`CorrectionError::NonFinite`] if the field gives non-finite coefficients on the raster;
/// [`CorrectionError::ThreadPool`].
pub fn correct_raster<F: CorrectionField + ?Sized>(
    field: &F,
    geometry: &RasterGeometry,
    direction: ScanDirection,
    integration: &Integration,
    parallelism: Parallelism,
) -> Result<CoordinateMap, CorrectionError> {
    correct_raster_reusing(
        field,
        geometry,
        direction,
        integration,
        parallelism,
        Vec::new(),
    )
}

/// [`correct_raster`] writing x̄ into `buffer` (resized to the image), so a caller correcting
/// image after image reuses one allocation (e.g. the x̄ of the previous map, from
/// [`CoordinateMap::into_parts`]).
///
/// # Errors
/// As [`correct_raster`].
pub fn correct_raster_reusing<F: CorrectionField + ?Sized>(
    field: &F,
    geometry: &RasterGeometry,
    direction: ScanDirection,
    integration: &Integration,
    parallelism: Parallelism,
    buffer: Vec<f64>,
) -> Result<CoordinateMap, CorrectionError> {
    let lines = RasterLines::new(field, geometry, direction, integration)?;
    let (nx, ny) = (lines.geometry.columns, lines.geometry.rows);
    let n = nx
        .checked_mul(ny)
        .ok_or(CorrectionError::Empty("raster size overflows"))?;
    let mut x_nm = buffer;
    x_nm.clear();
    x_nm.resize(n, 0.0);
    let failure = std::sync::Mutex::new(None::<CorrectionError>);
    for_each_row(parallelism, &mut x_nm, nx, |j, row| {
        if let Err(e) = lines.fill_row(j, row)
            && let Ok(mut slot) = failure.lock()
        {
            *slot = Some(e);
        }
    })?;
    if let Some(e) = failure.into_inner().ok().flatten() {
        return Err(e);
    }
    // Sizes and finiteness checked above (x̄ row by row while hot in cache).
    Ok(CoordinateMap {
        columns: nx,
        rows: ny,
        x_nm,
        y_nm: YCoordinates::PerRow(lines.y_per_row),
    })
}

/// (min, max) of `values` (±∞ reversed when empty): blocks on every core, each folded in
/// eight independent lanes (a min/max of finite values is exact in any order).
fn min_max(values: &[f64]) -> (f64, f64) {
    use rayon::prelude::*;
    const BLOCK: usize = 1 << 16;
    let fold = |block: &[f64]| {
        let mut lo = [f64::INFINITY; 8];
        let mut hi = [f64::NEG_INFINITY; 8];
        let mut chunks = block.chunks_exact(8);
        for chunk in &mut chunks {
            for k in 0..8 {
                lo[k] = lo[k].min(chunk[k]);
                hi[k] = hi[k].max(chunk[k]);
            }
        }
        let (lo, hi) = chunks.remainder().iter().fold(
            (
                lo.iter().copied().fold(f64::INFINITY, f64::min),
                hi.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            ),
            |(lo, hi), &t| (lo.min(t), hi.max(t)),
        );
        (lo, hi)
    };
    let join = |(a, b): (f64, f64), (c, d): (f64, f64)| (a.min(c), b.max(d));
    if values.len() <= BLOCK {
        return fold(values);
    }
    values
        .par_chunks(BLOCK)
        .map(fold)
        .reduce(|| (f64::INFINITY, f64::NEG_INFINITY), join)
}
