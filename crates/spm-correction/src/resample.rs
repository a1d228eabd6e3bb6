//! Resampling a corrected image onto a uniform nm grid by inverse mapping.
//!
//! The forward map (pixel → corrected nm) is known at the pixel nodes; between them it is the
//! bilinear interpolant of the nodes. Every output node (X, Y) is pulled back to a fractional
//! source pixel (c, r) with F(c, r) = (X, Y), and the image is interpolated there.
//!
//! - **Raster maps** ([`YCoordinates::PerRow`], what [`crate::correct_raster`] gives): ȳ
//!   depends only on the row, so Y fixes the fractional source row r for the whole output row
//!   (binary search in the monotone ȳ of the rows); on that row x̄(·, r) is the blend of two
//!   source rows and is monotone in the column, so all X of the output row are inverted by one
//!   merge walk. O(1) per output pixel, no search, exact for the bilinear forward map.
//!   Memory: the input image, the map's x̄ (one buffer; ȳ is per row) and the output — three
//!   image-sized buffers.
//! - **General maps** ([`YCoordinates::PerPixel`], e.g. after drift correction): Newton's
//!   method on the bilinear forward map, started from the previous output pixel's solution
//!   (1–2 iterations for smooth maps). Four image-sized buffers (x̄ and ȳ both per pixel).
//!
//! Output nodes whose source lies outside [0, columns − 1] × [0, rows − 1] are NaN. NaN pixels
//! of the input (missing data) spread to the output nodes whose stencil touches them.

use spm_hal::{Nanometres, NmPoint};

use crate::CorrectionError;
use crate::field::CorrectionField;
use crate::parallel::{Parallelism, for_each_row};
use crate::raster::{CoordinateMap, Integration, RasterGeometry, RasterLines, YCoordinates};
use spm_hal::ScanDirection;

/// Largest output grid accepted (2²⁸ pixels = 2 GiB of f64).
pub const MAX_OUTPUT_PIXELS: usize = 1 << 28;

/// Interpolation of the source image at a fractional pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Interpolation {
    /// Bilinear (2×2 stencil).
    #[default]
    Bilinear,
    /// Catmull-Rom cubic convolution (4×4 stencil, indices clamped at the edges); reproduces
    /// quadratics exactly away from the edges.
    CatmullRom,
}

/// A uniform output grid in corrected coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutputGrid {
    /// Position of output column 0, row 0, nm.
    pub origin_nm: NmPoint,
    /// Spacing along both axes, nm (> 0).
    pub step_nm: Nanometres,
    /// Output columns.
    pub columns: usize,
    /// Output rows.
    pub rows: usize,
}

impl OutputGrid {
    /// A validated grid.
    ///
    /// # Errors
    /// [`CorrectionError::NonFinite`], [`CorrectionError::InvalidArgument`] (step ≤ 0),
    /// [`CorrectionError::Empty`], [`CorrectionError::GridTooLarge`].
    pub fn new(
        origin_nm: NmPoint,
        step_nm: Nanometres,
        columns: usize,
        rows: usize,
    ) -> Result<Self, CorrectionError> {
        crate::error::check_finite_scalar("grid origin x", origin_nm.x.value())?;
        crate::error::check_finite_scalar("grid origin y", origin_nm.y.value())?;
        crate::error::check_finite_scalar("grid step", step_nm.value())?;
        if step_nm.value() <= 0.0 {
            return Err(CorrectionError::InvalidArgument(format!(
                "grid step must be > 0 nm, got {}",
                step_nm.value()
            )));
        }
        if columns == 0 || rows == 0 {
            return Err(CorrectionError::Empty(
                "output grid with zero columns or rows",
            ));
        }
        if columns
            .checked_mul(rows)
            .is_none_or(|n| n > MAX_OUTPUT_PIXELS)
        {
            return Err(CorrectionError::GridTooLarge {
                columns,
                rows,
                limit: MAX_OUTPUT_PIXELS,
            });
        }
        Ok(Self {
            origin_nm,
            step_nm,
            columns,
            rows,
        })
    }

    /// The grid covering the bounding box of `map`, at `step_nm` or, by default, the smaller
    /// of the mean corrected pixel spacings along x and y (no axis undersampled).
    ///
    /// # Errors
    /// As [`OutputGrid::new`]; [`CorrectionError::InvalidArgument`] for a map of one pixel
    /// without a step.
    pub fn covering(
        map: &CoordinateMap,
        step_nm: Option<Nanometres>,
    ) -> Result<Self, CorrectionError> {
        Self::from_bounds(map.bounds_nm_fast(), step_nm, map.columns(), map.rows())
    }

    /// The grid covering the box (min x, max x, min y, max y) nm of a `columns` × `rows` map.
    fn from_bounds(
        (x0, x1, y0, y1): (f64, f64, f64, f64),
        step_nm: Option<Nanometres>,
        columns: usize,
        rows: usize,
    ) -> Result<Self, CorrectionError> {
        let step = match step_nm {
            Some(s) => s.value(),
            None => {
                let sx = (columns > 1).then(|| (x1 - x0) / (columns - 1) as f64);
                let sy = (rows > 1).then(|| (y1 - y0) / (rows - 1) as f64);
                match (sx, sy) {
                    (Some(a), Some(b)) => a.min(b),
                    (Some(a), None) | (None, Some(a)) => a,
                    (None, None) => {
                        return Err(CorrectionError::InvalidArgument(
                            "a one-pixel map needs an explicit grid step".into(),
                        ));
                    }
                }
            }
        };
        if !(step.is_finite() && step > 0.0) {
            return Err(CorrectionError::InvalidArgument(format!(
                "grid step must be > 0 nm, got {step}"
            )));
        }
        // A hair of tolerance so the far edge survives rounding.
        let count = |extent: f64| -> Result<usize, CorrectionError> {
            let n = (extent / step * (1.0 + 1e-12)).floor() + 1.0;
            if n.is_finite() && n <= MAX_OUTPUT_PIXELS as f64 {
                Ok(n as usize)
            } else {
                Err(CorrectionError::GridTooLarge {
                    columns: usize::MAX,
                    rows: usize::MAX,
                    limit: MAX_OUTPUT_PIXELS,
                })
            }
        };
        Self::new(
            NmPoint::from_nm(x0, y0),
            Nanometres(step),
            count(x1 - x0)?,
            count(y1 - y0)?,
        )
    }

    /// x of output column `c`, nm.
    #[inline]
    #[must_use]
    pub fn x_nm(&self, column: usize) -> f64 {
        self.origin_nm.x.value() + self.step_nm.value() * column as f64
    }

    /// y of output row `r`, nm.
    #[inline]
    #[must_use]
    pub fn y_nm(&self, row: usize) -> f64 {
        self.origin_nm.y.value() + self.step_nm.value() * row as f64
    }
}

/// The source image as rows, with the interpolation kernel.
struct Source<'a> {
    image: &'a [f64],
    columns: usize,
    rows: usize,
    interpolation: Interpolation,
}

#[inline]
fn catmull_rom_weights(t: f64) -> [f64; 4] {
    let t2 = t * t;
    let t3 = t2 * t;
    [
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    ]
}

impl Source<'_> {
    /// The image at fractional (column, row) with row = j + fy; column in [0, columns − 1],
    /// 0 ≤ j ≤ rows − 2 (or 0 for one row) and fy ∈ [0, 1].
    #[inline(always)]
    fn sample(&self, column: f64, j: usize, fy: f64) -> f64 {
        let nx = self.columns;
        let i = (column as usize).min(nx.saturating_sub(2));
        let fx = column - i as f64;
        let i1 = (i + 1).min(nx - 1);
        let j1 = (j + 1).min(self.rows - 1);
        match self.interpolation {
            Interpolation::Bilinear => {
                let r0 = &self.image[j * nx..(j + 1) * nx];
                let r1 = &self.image[j1 * nx..(j1 + 1) * nx];
                let a = r0[i] + (r0[i1] - r0[i]) * fx;
                let b = r1[i] + (r1[i1] - r1[i]) * fx;
                a + (b - a) * fy
            }
            Interpolation::CatmullRom => {
                let wx = catmull_rom_weights(fx);
                let wy = catmull_rom_weights(fy);
                let clamp_c = |d: isize| (i as isize + d).clamp(0, nx as isize - 1) as usize;
                let clamp_r = |d: isize| (j as isize + d).clamp(0, self.rows as isize - 1) as usize;
                let mut total = 0.0;
                for (dy, wyv) in (-1..=2).zip(wy) {
                    let row = clamp_r(dy) * nx;
                    let mut s = 0.0;
                    for (dx, wxv) in (-1..=2).zip(wx) {
                        s += wxv * self.image[row + clamp_c(dx)];
                    }
                    total += wyv * s;
                }
                total
            }
        }
    }
}

/// Resamples `image` (values at the map's pixels, `[row * columns + column]`) onto `grid`.
///
/// # Errors
/// [`CorrectionError::SizeMismatch`]; [`CorrectionError::Empty`] for a map with fewer than two
/// columns or rows; [`CorrectionError::NonFinite`] for an infinite image value;
/// [`CorrectionError::NotMonotone`] when the map folds (x̄ not increasing along a line, or ȳ
/// not strictly monotone over the rows); [`CorrectionError::ThreadPool`].
pub fn resample(
    image: &[f64],
    map: &CoordinateMap,
    grid: &OutputGrid,
    interpolation: Interpolation,
    parallelism: Parallelism,
) -> Result<Vec<f64>, CorrectionError> {
    let grid = OutputGrid::new(grid.origin_nm, grid.step_nm, grid.columns, grid.rows)?;
    let mut out = vec![0.0; grid.columns * grid.rows];
    resample_into(image, map, &grid, interpolation, parallelism, &mut out)?;
    Ok(out)
}

/// [`resample`] into a caller's buffer of `grid.columns × grid.rows` values (every value is
/// overwritten; NaN outside the data).
///
/// # Errors
/// As [`resample`]; [`CorrectionError::SizeMismatch`] for a buffer of the wrong size.
pub fn resample_into(
    image: &[f64],
    map: &CoordinateMap,
    grid: &OutputGrid,
    interpolation: Interpolation,
    parallelism: Parallelism,
    out: &mut [f64],
) -> Result<(), CorrectionError> {
    let (nx, ny) = (map.columns(), map.rows());
    check_image(image, nx, ny)?;
    let grid = OutputGrid::new(grid.origin_nm, grid.step_nm, grid.columns, grid.rows)?;
    if out.len() != grid.columns * grid.rows {
        return Err(CorrectionError::SizeMismatch {
            what: "output buffer",
            expected: grid.columns * grid.rows,
            got: out.len(),
        });
    }
    let source = Source {
        image,
        columns: nx,
        rows: ny,
        interpolation,
    };
    match map.y_nm() {
        YCoordinates::PerRow(y_rows) => {
            resample_rows(&source, map.x_nm(), y_rows, &grid, parallelism, out)
        }
        YCoordinates::PerPixel(y_px) => {
            resample_newton(&source, map.x_nm(), y_px, &grid, parallelism, out)
        }
    }
}

/// Fractional row (j, f) of `y` in the strictly monotone `y_rows`, or None outside.
#[inline]
fn row_fraction(y_rows: &[f64], increasing: bool, y: f64) -> Option<(usize, f64)> {
    let n = y_rows.len();
    // Nodes within 1e-9 of a row spacing of the first/last row count as on it (rounding).
    let slack = 1e-9 * (y_rows[n - 1] - y_rows[0]).abs() / (n - 1) as f64;
    let (first, last) = if increasing {
        (y_rows[0] - slack, y_rows[n - 1] + slack)
    } else {
        (y_rows[0] + slack, y_rows[n - 1] - slack)
    };
    let inside = if increasing {
        y >= first && y <= last
    } else {
        y <= first && y >= last
    };
    if !inside {
        return None;
    }
    // First index k with y_rows[k] beyond y (partition point), then the gap k−1..k.
    let k = if increasing {
        y_rows.partition_point(|&v| v <= y)
    } else {
        y_rows.partition_point(|&v| v >= y)
    };
    let j = k.clamp(1, n - 1) - 1;
    let f = (y - y_rows[j]) / (y_rows[j + 1] - y_rows[j]);
    Some((j, f.clamp(0.0, 1.0)))
}

/// Inverts x̄(·, r) = a + (b − a)·f along one output row by a merge walk and writes
/// `kernel(i, t)` (source column i + t, 0 ≤ i ≤ columns − 2, t ∈ [0, 1]) at every output node
/// inside the row's extent. `Err(())` when the blended row is not strictly increasing.
#[inline]
fn walk_row(
    a: &[f64],
    b: &[f64],
    f: f64,
    grid: &OutputGrid,
    out_row: &mut [f64],
    kernel: impl Fn(usize, f64) -> f64,
) -> Result<(), ()> {
    let nx = a.len();
    let blend = |i: usize| a[i] + (b[i] - a[i]) * f;
    let (first, last) = (blend(0), blend(nx - 1));
    if last <= first {
        out_row.fill(f64::NAN);
        return Err(());
    }
    // Nodes within 1e-9 of a pixel of the first/last column count as on it (rounding).
    let slack = 1e-9 * (last - first) / (nx - 1) as f64;
    let (lo, hi) = (first - slack, last + slack);
    let (gx0, step) = (grid.origin_nm.x.value(), grid.step_nm.value());
    let c_start = ((lo - gx0) / step).ceil().max(0.0);
    if c_start >= out_row.len() as f64 {
        out_row.fill(f64::NAN);
        return Ok(());
    }
    let c_start = c_start as usize;
    out_row[..c_start].fill(f64::NAN);
    let mut c_end = out_row.len();
    let mut i = 0usize;
    let mut cur = first;
    let mut next = blend(1);
    if next <= cur {
        return Err(());
    }
    let mut inv = 1.0 / (next - cur);
    for (c, o) in out_row.iter_mut().enumerate().skip(c_start) {
        let x = gx0 + step * c as f64;
        if x > hi {
            c_end = c;
            break;
        }
        while next < x && i + 2 < nx {
            i += 1;
            cur = next;
            next = blend(i + 1);
            if next <= cur {
                return Err(());
            }
            inv = 1.0 / (next - cur);
        }
        let t = ((x - cur) * inv).clamp(0.0, 1.0);
        *o = kernel(i, t);
    }
    out_row[c_end..].fill(f64::NAN);
    Ok(())
}

/// One output row from the source rows j, j + 1 (x̄ lines `a`, `b`, blend `f`).
#[inline]
fn emit_row(
    source: &Source<'_>,
    a: &[f64],
    b: &[f64],
    j: usize,
    f: f64,
    grid: &OutputGrid,
    out_row: &mut [f64],
) -> Result<(), ()> {
    let nx = source.columns;
    match source.interpolation {
        Interpolation::Bilinear => {
            // Specialised kernel: the two source rows are fixed for the whole output row.
            let r0 = &source.image[j * nx..(j + 1) * nx];
            let r1 = &source.image[(j + 1) * nx..(j + 2) * nx];
            walk_row(a, b, f, grid, out_row, |i, t| {
                let (p0, p1) = (r0[i], r0[i + 1]);
                let (q0, q1) = (r1[i], r1[i + 1]);
                let lo = p0 + (p1 - p0) * t;
                let hi = q0 + (q1 - q0) * t;
                lo + (hi - lo) * f
            })
        }
        Interpolation::CatmullRom => walk_row(a, b, f, grid, out_row, |i, t| {
            source.sample(i as f64 + t, j, f)
        }),
    }
}

/// Output rows per work item of [`correct_and_resample`] (each caches two source lines).
const FUSED_CHUNK_ROWS: usize = 32;

/// Fused raster correction and resampling: the corrected coordinates of each source line are
/// computed when an output row first needs them (two lines cached per work item) instead of
/// being stored for the whole image. Same result as [`crate::correct_raster`] followed by
/// [`OutputGrid::covering`] and [`resample`], with two image-sized buffers (input and output)
/// instead of three and a third of the memory traffic.
///
/// Returns the output grid (covering the corrected image at `step_nm`, by default the smaller
/// mean pixel spacing) and the resampled image.
///
/// # Errors
/// As [`crate::correct_raster`] and [`resample`].
#[allow(clippy::too_many_arguments)]
pub fn correct_and_resample<F: CorrectionField + ?Sized>(
    field: &F,
    geometry: &RasterGeometry,
    direction: ScanDirection,
    integration: &Integration,
    image: &[f64],
    step_nm: Option<Nanometres>,
    interpolation: Interpolation,
    parallelism: Parallelism,
) -> Result<(OutputGrid, Vec<f64>), CorrectionError> {
    let mut out = Vec::new();
    let grid = correct_and_resample_into(
        field,
        geometry,
        direction,
        integration,
        image,
        step_nm,
        interpolation,
        parallelism,
        &mut out,
    )?;
    Ok((grid, out))
}

/// [`correct_and_resample`] into a caller's buffer (resized to the output grid, which is
/// returned), so image after image reuses one allocation.
///
/// # Errors
/// As [`correct_and_resample`].
#[allow(clippy::too_many_arguments)]
pub fn correct_and_resample_into<F: CorrectionField + ?Sized>(
    field: &F,
    geometry: &RasterGeometry,
    direction: ScanDirection,
    integration: &Integration,
    image: &[f64],
    step_nm: Option<Nanometres>,
    interpolation: Interpolation,
    parallelism: Parallelism,
    out: &mut Vec<f64>,
) -> Result<OutputGrid, CorrectionError> {
    let lines = RasterLines::new(field, geometry, direction, integration)?;
    let (nx, ny) = (lines.geometry.columns, lines.geometry.rows);
    check_image(image, nx, ny)?;
    let edges = lines.edges()?;
    let (x0, x1) = edges
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &(a, b)| {
            (lo.min(a).min(b), hi.max(a).max(b))
        });
    let y_rows = &lines.y_per_row;
    let (y0, y1) = y_rows
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &t| {
            (lo.min(t), hi.max(t))
        });
    let grid = OutputGrid::from_bounds((x0, x1, y0, y1), step_nm, nx, ny)?;
    let increasing = check_rows_monotone(y_rows)?;
    let source = Source {
        image,
        columns: nx,
        rows: ny,
        interpolation,
    };
    out.resize(grid.columns * grid.rows, 0.0);
    let folded = std::sync::atomic::AtomicUsize::new(usize::MAX);
    let failure = std::sync::Mutex::new(None::<CorrectionError>);
    for_each_row(
        parallelism,
        out,
        grid.columns * FUSED_CHUNK_ROWS,
        |chunk_index, chunk| {
            let mut lines_cache = [(usize::MAX, vec![0.0; nx]), (usize::MAX, vec![0.0; nx])];
            for (k, out_row) in chunk.chunks_mut(grid.columns).enumerate() {
                let r = chunk_index * FUSED_CHUNK_ROWS + k;
                let Some((j, f)) = row_fraction(y_rows, increasing, grid.y_nm(r)) else {
                    out_row.fill(f64::NAN);
                    continue;
                };
                if lines_cache[0].0 != j {
                    if lines_cache[1].0 == j {
                        lines_cache.swap(0, 1);
                    } else {
                        lines_cache[0].0 = usize::MAX;
                        if let Err(e) = lines.fill_row(j, &mut lines_cache[0].1) {
                            if let Ok(mut slot) = failure.lock() {
                                *slot = Some(e);
                            }
                            return;
                        }
                        lines_cache[0].0 = j;
                    }
                }
                if lines_cache[1].0 != j + 1 {
                    lines_cache[1].0 = usize::MAX;
                    if let Err(e) = lines.fill_row(j + 1, &mut lines_cache[1].1) {
                        if let Ok(mut slot) = failure.lock() {
                            *slot = Some(e);
                        }
                        return;
                    }
                    lines_cache[1].0 = j + 1;
                }
                let (a, b) = (&lines_cache[0].1, &lines_cache[1].1);
                if emit_row(&source, a, b, j, f, &grid, out_row).is_err() {
                    folded.fetch_min(j, std::sync::atomic::Ordering::Relaxed);
                }
            }
        },
    )?;
    if let Some(e) = failure.into_inner().ok().flatten() {
        return Err(e);
    }
    let j = folded.into_inner();
    if j != usize::MAX {
        return Err(CorrectionError::NotMonotone {
            axis: "x",
            index: j,
        });
    }
    Ok(grid)
}

/// Checks the image against the map size and for infinities (NaN = missing data is allowed).
fn check_image(image: &[f64], nx: usize, ny: usize) -> Result<(), CorrectionError> {
    if image.len() != nx * ny {
        return Err(CorrectionError::SizeMismatch {
            what: "image",
            expected: nx * ny,
            got: image.len(),
        });
    }
    if nx < 2 || ny < 2 {
        return Err(CorrectionError::Empty(
            "resampling needs at least two columns and two rows",
        ));
    }
    if let Some(index) = image.iter().position(|v| v.is_infinite()) {
        return Err(CorrectionError::NonFinite {
            what: "image",
            index,
        });
    }
    Ok(())
}

/// Strict monotonicity of ȳ over the rows; returns whether it increases.
fn check_rows_monotone(y_rows: &[f64]) -> Result<bool, CorrectionError> {
    let increasing = y_rows.len() > 1 && y_rows[1] > y_rows[0];
    for (k, w) in y_rows.windows(2).enumerate() {
        if !((increasing && w[1] > w[0]) || (!increasing && w[1] < w[0])) {
            return Err(CorrectionError::NotMonotone {
                axis: "y",
                index: k,
            });
        }
    }
    Ok(increasing)
}

fn resample_rows(
    source: &Source<'_>,
    x_nm: &[f64],
    y_rows: &[f64],
    grid: &OutputGrid,
    parallelism: Parallelism,
    out: &mut [f64],
) -> Result<(), CorrectionError> {
    let nx = source.columns;
    let increasing = check_rows_monotone(y_rows)?;
    let folded = std::sync::atomic::AtomicUsize::new(usize::MAX);
    let mark_folded = |j: usize| {
        folded.fetch_min(j, std::sync::atomic::Ordering::Relaxed);
    };
    for_each_row(parallelism, out, grid.columns, |r, out_row| {
        let Some((j, f)) = row_fraction(y_rows, increasing, grid.y_nm(r)) else {
            out_row.fill(f64::NAN);
            return;
        };
        let a = &x_nm[j * nx..(j + 1) * nx];
        let b = &x_nm[(j + 1) * nx..(j + 2) * nx];
        let result = emit_row(source, a, b, j, f, grid, out_row);
        if result.is_err() {
            mark_folded(j);
        }
    })?;
    let j = folded.into_inner();
    if j != usize::MAX {
        return Err(CorrectionError::NotMonotone {
            axis: "x",
            index: j,
        });
    }
    Ok(())
}

/// Bilinear forward map at (c, r) (cell clamped, so extrapolated outside) and its Jacobian.
#[inline(always)]
fn forward(
    x_nm: &[f64],
    y_nm: &[f64],
    nx: usize,
    ny: usize,
    c: f64,
    r: f64,
) -> ((f64, f64), [[f64; 2]; 2]) {
    // `as usize` truncates, which is the floor for c, r ≥ 0 (and 0 for NaN or negatives, the
    // clamp); `floor` itself is a libm call on the baseline x86-64 target.
    let i = (c.max(0.0) as usize).min(nx - 2);
    let j = (r.max(0.0) as usize).min(ny - 2);
    let (fx, fy) = (c - i as f64, r - j as f64);
    let k = j * nx + i;
    let corners = |v: &[f64]| (v[k], v[k + 1], v[k + nx], v[k + nx + 1]);
    let (x00, x10, x01, x11) = corners(x_nm);
    let (y00, y10, y01, y11) = corners(y_nm);
    let bil = |a: f64, b: f64, cc: f64, d: f64| {
        (a * (1.0 - fx) + b * fx) * (1.0 - fy) + (cc * (1.0 - fx) + d * fx) * fy
    };
    let value = (bil(x00, x10, x01, x11), bil(y00, y10, y01, y11));
    let jac = [
        [
            (x10 - x00) * (1.0 - fy) + (x11 - x01) * fy,
            (x01 - x00) * (1.0 - fx) + (x11 - x10) * fx,
        ],
        [
            (y10 - y00) * (1.0 - fy) + (y11 - y01) * fy,
            (y01 - y00) * (1.0 - fx) + (y11 - y10) * fx,
        ],
    ];
    (value, jac)
}

/// The Newton step (pixels, |dc| + |dr|) after which [`invert`] stops.
const NEWTON_STEP_DONE_PX: f64 = 1e-7;

/// Newton's method for F(c, r) = target from `guess`; None if it does not converge.
#[inline(always)]
fn invert(
    x_nm: &[f64],
    y_nm: &[f64],
    nx: usize,
    ny: usize,
    target: (f64, f64),
    guess: (f64, f64),
) -> Option<(f64, f64)> {
    let (mut c, mut r) = guess;
    if !(c.is_finite() && r.is_finite()) {
        return None;
    }
    let longest_side = nx.max(ny) as f64;
    for _ in 0..40 {
        let ((fx, fy), j) = forward(x_nm, y_nm, nx, ny, c, r);
        let (ex, ey) = (fx - target.0, fy - target.1);
        let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
        if det.abs() < 1e-300 || !det.is_finite() {
            return None;
        }
        let inverse_det = 1.0 / det;
        let dc = (ex * j[1][1] - ey * j[0][1]) * inverse_det;
        let dr = (ey * j[0][0] - ex * j[1][0]) * inverse_det;
        // Damp huge steps so a far guess cannot jump across the map's folds.
        let size = dc.abs() + dr.abs();
        let scale = if size > longest_side {
            longest_side / size
        } else {
            1.0
        };
        c -= dc * scale;
        r -= dr * scale;
        // Newton converges quadratically: after a step of s pixels the error left is about
        // s² times the cell's twist over its Jacobian (≪ 1), so a step under 1e-7 leaves
        // under 1e-13 pixel and needs no second evaluation to confirm it.
        if dc.abs() + dr.abs() < NEWTON_STEP_DONE_PX {
            return Some((c, r));
        }
    }
    None
}

fn resample_newton(
    source: &Source<'_>,
    x_nm: &[f64],
    y_nm: &[f64],
    grid: &OutputGrid,
    parallelism: Parallelism,
    out: &mut [f64],
) -> Result<(), CorrectionError> {
    let (nx, ny) = (source.columns, source.rows);
    // Affine first guess for the first node of every row: from three corners of the map.
    let p00 = (x_nm[0], y_nm[0]);
    let p10 = (x_nm[nx - 1], y_nm[nx - 1]);
    let p01 = (x_nm[(ny - 1) * nx], y_nm[(ny - 1) * nx]);
    let a = [
        [
            (p10.0 - p00.0) / (nx - 1) as f64,
            (p01.0 - p00.0) / (ny - 1) as f64,
        ],
        [
            (p10.1 - p00.1) / (nx - 1) as f64,
            (p01.1 - p00.1) / (ny - 1) as f64,
        ],
    ];
    let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
    if !(det.is_finite() && det.abs() > 0.0) {
        out.fill(f64::NAN);
        return Err(CorrectionError::NotMonotone {
            axis: "x",
            index: 0,
        });
    }
    let affine_guess = |x: f64, y: f64| {
        let (dx, dy) = (x - p00.0, y - p00.1);
        (
            (dx * a[1][1] - dy * a[0][1]) / det,
            (dy * a[0][0] - dx * a[1][0]) / det,
        )
    };
    let (cmax, rmax) = ((nx - 1) as f64, (ny - 1) as f64);
    let tol = 1e-9;
    // One output node of a row: Newton from the row's guess, the guess then moved on. The
    // value at the node, or None outside the data.
    let node = |walk: &mut RowWalk, c: usize| -> Option<f64> {
        let (x, y) = (grid.x_nm(c), walk.y);
        let solution = invert(x_nm, y_nm, nx, ny, (x, y), walk.guess)
            .or_else(|| invert(x_nm, y_nm, nx, ny, (x, y), affine_guess(x, y)));
        let Some((sc, sr)) = solution else {
            walk.guess = affine_guess(grid.x_nm(c + 1), y);
            walk.previous = None;
            walk.before_previous = None;
            return None;
        };
        walk.guess = match (walk.previous, walk.before_previous) {
            (Some((pc, pr)), Some((qc, qr))) => (3.0 * (sc - pc) + qc, 3.0 * (sr - pr) + qr),
            (Some((pc, pr)), None) => (2.0 * sc - pc, 2.0 * sr - pr),
            _ => (sc, sr),
        };
        walk.before_previous = walk.previous;
        walk.previous = Some((sc, sr));
        if sc < -tol || sr < -tol || sc > cmax + tol || sr > rmax + tol {
            return None;
        }
        let (sc, sr) = (sc.clamp(0.0, cmax), sr.clamp(0.0, rmax));
        let j = (sr as usize).min(ny - 2);
        Some(source.sample(sc, j, sr - j as f64))
    };
    let columns = grid.columns;
    // NEWTON_ROWS output rows per work item, walked side by side: each row's nodes depend on
    // the row's previous ones (the guess), so one row is a chain of dependent Newton steps;
    // rows side by side give the processor independent chains to overlap. Each row's
    // arithmetic is the same as walked alone.
    for_each_row(parallelism, out, NEWTON_ROWS * columns, |item, rows| {
        // NaN where no node is written (outside the data), filled here so that each worker
        // first touches its own rows.
        rows.fill(f64::NAN);
        let first_row = item * NEWTON_ROWS;
        let mut walks = [RowWalk::default(); NEWTON_ROWS];
        let count = rows.len() / columns;
        for (k, walk) in walks.iter_mut().enumerate().take(count) {
            let y = grid.y_nm(first_row + k);
            *walk = RowWalk {
                y,
                guess: affine_guess(grid.x_nm(0), y),
                previous: None,
                before_previous: None,
            };
        }
        for c in 0..columns {
            for (k, walk) in walks.iter_mut().enumerate().take(count) {
                if let Some(v) = node(walk, c) {
                    rows[k * columns + c] = v;
                }
            }
        }
    })
}

/// Output rows [`resample_newton`] walks side by side.
const NEWTON_ROWS: usize = 4;

/// The walk of [`resample_newton`] along one output row: its y, the next node's guess and
/// the last two nodes' solutions (the guess extrapolates the last three quadratically, the
/// map being smooth, so that one Newton step ends it; the last two linearly after a restart).
#[derive(Debug, Clone, Copy, Default)]
struct RowWalk {
    /// y of the row, nm.
    y: f64,
    /// (column, row) guess of the next node.
    guess: (f64, f64),
    /// The last node's solution.
    previous: Option<(f64, f64)>,
    /// The solution before it.
    before_previous: Option<(f64, f64)>,
}
