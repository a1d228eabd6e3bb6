//! The two per-image competitors of the image benchmark (issue 23, item 5), implemented from
//! their papers' models and judged on the same images as the user's path:
//!
//! - [`yothers`]: the thermal-drift, hysteresis and creep transform (DHCT) after Yothers,
//!   Browder & Bumm, Rev. Sci. Instrum. 88, 013708 (2017): the sample's own known lattice is
//!   the ruler within one image, trace and retrace together; fast-axis hysteresis `A·t^b`
//!   (t since the line's reversal), drift and creep `c₀ + c₁t + c₂/(t + t₀)`.
//! - [`zhang`]: after Zhang et al., Rev. Sci. Instrum. (2019), doi 10.1063/1.5052281: a
//!   sinusoid-plus-linear map fitted from the features matched between trace and retrace.
//!
//! Both read what a file holds (the two halves in scanner geometry with their pixel times, the
//! nominal sensitivity) and nothing of the calibration. Each gives a map from the forward
//! trace's pixel (column, row) to corrected nm, as the benchmark's other methods do; an image
//! a method cannot correct (no retrace, lattice not resolved, too few atoms indexed or matched)
//! is refused with the reason, and the benchmark keeps the nominal map for it (what the user of
//! that method has). The papers' full texts were not at hand: the models are implemented as
//! the issue states them, each fitted with [`spm_regression::least_squares`] (nonlinear
//! parameters by a ladder, then golden-section refinement, each step a linear fit: no second
//! solver).

pub mod yothers;
pub mod zhang;

use spm_correction::{CoordinateMap, CorrectionError, YCoordinates};
use spm_features::Feature;
use spm_hal::HeightMap;

/// Why a competitor could not correct an image.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CompetitorError {
    /// The image does not carry what the method needs.
    #[error("{method}: refused: {reason}")]
    Refused {
        /// The method ("yothers", "zhang").
        method: &'static str,
        /// Why.
        reason: String,
    },
    /// A map could not be built.
    #[error("competitor map: {0}")]
    Correction(#[from] CorrectionError),
}

/// What a competitor needs to know of the images besides the images.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CompetitorConfig {
    /// Nominal sensitivity of the scanner, nm per count (the file's own scale).
    pub nominal_nm_per_count: f64,
    /// Lattice constant of the standard imaged, nm (HOPG 0.246; the DHCT's ruler).
    pub lattice_constant_nm: f64,
    /// Fewest pixels per lattice constant for atoms to be located (default 5, as the
    /// benchmark's lattice figure).
    pub min_pixels_per_lattice_constant: f64,
}

/// One half of a frame as a file holds it: the geometry and the line timing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HalfRaster {
    /// Pixels per line.
    pub columns: usize,
    /// Pixel dwell, s.
    pub dwell_s: f64,
    /// Whether this half runs towards +x (column 0 first).
    pub runs_plus_x: bool,
}

impl HalfRaster {
    /// The raster of one half from its pixel times (row 0: which end is first, and the dwell).
    ///
    /// # Errors
    /// [`CompetitorError::Refused`] for a map narrower than 2 pixels or without times.
    pub fn of(map: &HeightMap, method: &'static str) -> Result<Self, CompetitorError> {
        let refused = |reason: &str| CompetitorError::Refused {
            method,
            reason: reason.to_owned(),
        };
        if map.columns < 2 || map.time_s.len() != map.columns * map.rows {
            return Err(refused(
                "the map has no pixel times or fewer than 2 columns",
            ));
        }
        let dt = map.time_s[1] - map.time_s[0];
        if !(dt.is_finite() && dt != 0.0) {
            return Err(refused("the pixel times along a line do not advance"));
        }
        Ok(Self {
            columns: map.columns,
            dwell_s: dt.abs(),
            runs_plus_x: dt > 0.0,
        })
    }

    /// σ: +1 for a half that runs towards +x, −1 otherwise.
    pub fn sign(&self) -> f64 {
        if self.runs_plus_x { 1.0 } else { -1.0 }
    }

    /// Fraction of its line the half has run at (fractional) column `column`, 0…1.
    pub fn progress(&self, column: f64) -> f64 {
        let last = (self.columns - 1) as f64;
        if self.runs_plus_x {
            column / last
        } else {
            (last - column) / last
        }
    }

    /// Time since the line's reversal at (fractional) column `column`, s (pixel times are
    /// dwell midpoints: the first pixel is half a dwell after the reversal).
    pub fn since_reversal_s(&self, column: f64) -> f64 {
        let last = (self.columns - 1) as f64;
        let k = if self.runs_plus_x {
            column
        } else {
            last - column
        };
        (k + 0.5) * self.dwell_s
    }
}

/// One sighting of a point: where the file puts it and when it was seen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sighting {
    /// Nominal position (commanded counts × nominal sensitivity), nm.
    pub position_nm: [f64; 2],
    /// Time since the frame's start, s.
    pub time_s: f64,
    /// Time since its line's reversal, s.
    pub since_reversal_s: f64,
    /// Fraction of its line its half had run, 0…1.
    pub progress: f64,
    /// σ of its half: +1 towards +x, −1 towards −x.
    pub sign: f64,
}

/// The frame's start: half a dwell before the first pixel of either half.
pub(crate) fn frame_start_s(maps: &[&HeightMap], dwell_s: f64) -> f64 {
    let first = maps
        .iter()
        .flat_map(|m| m.time_s.iter().copied())
        .fold(f64::INFINITY, f64::min);
    first - 0.5 * dwell_s
}

/// The sighting of a feature detected on `map` (its position in commanded counts).
pub(crate) fn feature_sighting(
    f: &Feature,
    half: &HalfRaster,
    nm_per_count: f64,
    start_s: f64,
) -> Sighting {
    Sighting {
        position_nm: [
            f.position.x.value() * nm_per_count,
            f.position.y.value() * nm_per_count,
        ],
        time_s: f.time.value() - start_s,
        since_reversal_s: half.since_reversal_s(f.column),
        progress: half.progress(f.column),
        sign: half.sign(),
    }
}

/// The sightings of every pixel of `map`, geometry order.
pub(crate) fn pixel_sightings(
    map: &HeightMap,
    half: &HalfRaster,
    nm_per_count: f64,
    start_s: f64,
) -> Vec<Sighting> {
    let (x0, y0, s) = (
        map.origin.x.value(),
        map.origin.y.value(),
        map.pixel_step.value(),
    );
    let mut out = Vec::with_capacity(map.columns * map.rows);
    for row in 0..map.rows {
        for column in 0..map.columns {
            let c = column as f64;
            out.push(Sighting {
                position_nm: [
                    (x0 + s * c) * nm_per_count,
                    (y0 + s * row as f64) * nm_per_count,
                ],
                time_s: map.time_s[row * map.columns + column] - start_s,
                since_reversal_s: half.since_reversal_s(c),
                progress: half.progress(c),
                sign: half.sign(),
            });
        }
    }
    out
}

/// The nominal coordinate map of a height map (commanded counts × nominal sensitivity).
///
/// # Errors
/// As [`CoordinateMap::new`].
pub fn nominal_map(map: &HeightMap, nm_per_count: f64) -> Result<CoordinateMap, CorrectionError> {
    let (x0, y0, s) = (
        map.origin.x.value(),
        map.origin.y.value(),
        map.pixel_step.value(),
    );
    let n = map.columns * map.rows;
    let x = (0..n)
        .map(|i| (x0 + s * (i % map.columns) as f64) * nm_per_count)
        .collect();
    let y = (0..n)
        .map(|i| (y0 + s * (i / map.columns) as f64) * nm_per_count)
        .collect();
    CoordinateMap::new(map.columns, map.rows, x, YCoordinates::PerPixel(y))
}

/// A map from corrected positions of every pixel (geometry order).
pub(crate) fn map_of(
    columns: usize,
    rows: usize,
    corrected: &[[f64; 2]],
) -> Result<CoordinateMap, CorrectionError> {
    CoordinateMap::new(
        columns,
        rows,
        corrected.iter().map(|p| p[0]).collect(),
        YCoordinates::PerPixel(corrected.iter().map(|p| p[1]).collect()),
    )
}

/// The atoms of both halves and their matches (trace index, retrace index), with the halves'
/// rasters and the frame's start; the matches grown from the sightings closest in time
/// ([`crate::images::match_features`] on the nominal maps).
pub(crate) struct Halves {
    pub trace: Vec<Feature>,
    pub retrace: Vec<Feature>,
    pub matches: Vec<(usize, usize)>,
    pub trace_raster: HalfRaster,
    pub retrace_raster: HalfRaster,
    pub start_s: f64,
}

/// Detects and matches the atoms of trace and retrace.
pub(crate) fn detect_halves(
    trace: &HeightMap,
    retrace: Option<&HeightMap>,
    config: &CompetitorConfig,
    method: &'static str,
) -> Result<Halves, CompetitorError> {
    let refused = |reason: String| CompetitorError::Refused { method, reason };
    let retrace = retrace.ok_or_else(|| refused("the image has no retrace".to_owned()))?;
    let step = trace.pixel_step.value() * config.nominal_nm_per_count;
    let period_px = config.lattice_constant_nm / step;
    if period_px.is_nan() || period_px < config.min_pixels_per_lattice_constant {
        return Err(refused(format!(
            "{period_px:.2} pixels per lattice constant (needs ≥ {})",
            config.min_pixels_per_lattice_constant
        )));
    }
    let trace_raster = HalfRaster::of(trace, method)?;
    let retrace_raster = HalfRaster::of(retrace, method)?;
    let start_s = frame_start_s(&[trace, retrace], trace_raster.dwell_s);
    let atoms_t = crate::images::lattice::atoms(trace, period_px);
    let atoms_r = crate::images::lattice::atoms(retrace, period_px);
    let frame_t = nominal_map(trace, config.nominal_nm_per_count)?;
    let frame_r = nominal_map(retrace, config.nominal_nm_per_count)?;
    let found = crate::images::match_features(
        &atoms_t,
        &atoms_r,
        trace,
        retrace,
        0.3 * config.lattice_constant_nm,
        (&frame_t, &frame_r),
    );
    // match_features names features by their pixel coordinates: back to indices.
    let index_of = |set: &[Feature], column: f64, row: f64| {
        set.iter().position(|f| f.column == column && f.row == row)
    };
    let matches: Vec<(usize, usize)> = found
        .iter()
        .filter_map(|m| {
            Some((
                index_of(&atoms_t, m.direct_column, m.direct_row)?,
                index_of(&atoms_r, m.counter_column, m.counter_row)?,
            ))
        })
        .collect();
    if matches.len() < 12 {
        return Err(refused(format!(
            "{} atoms matched between trace and retrace (needs ≥ 12; {} and {} located)",
            matches.len(),
            atoms_t.len(),
            atoms_r.len()
        )));
    }
    Ok(Halves {
        trace: atoms_t,
        retrace: atoms_r,
        matches,
        trace_raster,
        retrace_raster,
        start_s,
    })
}

/// Golden-section minimum of `f` on `[lo, hi]` (`iterations` steps): the abscissa.
pub(crate) fn golden(lo: f64, hi: f64, iterations: usize, f: &mut dyn FnMut(f64) -> f64) -> f64 {
    let r = 0.5 * (5f64.sqrt() - 1.0);
    let (mut a, mut b) = (lo, hi);
    let mut c = b - r * (b - a);
    let mut d = a + r * (b - a);
    let (mut fc, mut fd) = (f(c), f(d));
    for _ in 0..iterations {
        if fc < fd {
            b = d;
            d = c;
            fd = fc;
            c = b - r * (b - a);
            fc = f(c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + r * (b - a);
            fd = f(d);
        }
    }
    if fc < fd { c } else { d }
}
