//! PNG figures of a run, drawn with the workspace's plotting stack (`spm-plot`: plotters,
//! embedded font, colorous colour maps). Every figure has a title, axes with quantity and
//! unit, tick labels and, where colour carries a value, a colour bar with its unit.
//!
//! - `lcc-kx.png`, `lcc-ky.png`, `lcc-alpha.png`: the regression surface over the
//!   calibrated region (viridis) with every measured node as a disc filled with its
//!   measured value on the same scale (the passes over a node concentric, the first
//!   outermost); below it each node's residual, measured − surface,
//!   on a diverging scale. The title gives the degree, σ and Δmax of the fit.
//! - `drift.png`: the running median of the drift speed (nm/s through the nominal
//!   sensitivity) against instrument time (s) with its 16–84 % band, the spoiled skipping
//!   cycles marked with crosses.
//! - `trajectory.png`: the node centres joined in visiting order, one panel per pass.
//! - `lcc-uncertainty.png`: the standard uncertainty of each fitted surface over the region,
//!   σ·√h from the fit's design ([`spm_correction::fit::standard_uncertainty`]), with the records it
//!   was fitted from as dots.
//!
//! Positions are drawn in µm of field (nm for a map under a micrometre, `FieldAxes`)
//! through the plan's nominal sensitivity (a unit a
//! person can picture); the captions give the factor back to counts.

use crate::run::{DriftSample, NodeSample};
use crate::surfaces::SurfaceSummary;
use spm_plot::{
    ColorMap, FieldFigure, FieldPanel, ImagePairFigure, ImagePanel, MapFigure, MapNode,
    OrderFigure, OrderPanel, Series, SeriesStyle, XyFigure, cell_centres, field_maps, image_pair,
    order_map, running_quantiles, surface_map, xy_chart,
};

/// Why a figure could not be drawn.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {message}")]
pub struct PlotError {
    /// The figure.
    pub path: String,
    /// Why.
    pub message: String,
}

impl PlotError {
    fn of(file: &str) -> impl FnOnce(spm_plot::PlotError) -> Self + '_ {
        move |e| Self {
            path: file.to_owned(),
            message: e.to_string(),
        }
    }
}

/// One figure of the report: its file name, a caption and the PNG bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct Figure {
    /// File name in the report folder.
    pub file: String,
    /// What it shows (the HTML report's caption).
    pub caption: String,
    /// The PNG.
    pub png: Vec<u8>,
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
    /// The bounding box of the measured nodes when it has an area (a run that measured one
    /// row or column of the net spans none, and has no raster to judge or image).
    pub fn spanned(nodes: &[NodeSample]) -> Option<Self> {
        Self::around(nodes, 0.0)
            .filter(|r| r.x_max_counts > r.x_min_counts && r.y_max_counts > r.y_min_counts)
    }

    /// The same rectangle as the image benchmark's and the validation's region type.
    pub fn counts(&self) -> spm_evaluation::images::CountRegion {
        spm_evaluation::images::CountRegion {
            x_min_counts: self.x_min_counts,
            x_max_counts: self.x_max_counts,
            y_min_counts: self.y_min_counts,
            y_max_counts: self.y_max_counts,
        }
    }

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
}

/// Three significant digits, the display form of the HTML report's numbers.
fn significant(v: f64) -> String {
    match crate::html::Cell::significant(v) {
        crate::html::Cell::Number { text, .. } | crate::html::Cell::Text(text) => text,
    }
}

/// The axes of a map of the field: positions through the plan's nominal sensitivity in µm,
/// or in nm when the map spans less than a micrometre (a stored image of 50 nm in virtual
/// mode reads 0–50 nm, not 0.000–0.050 µm).
#[derive(Debug, Clone, PartialEq)]
struct FieldAxes {
    /// Nominal sensitivity, nm per count.
    nm_per_count: f64,
    /// The unit, nm.
    unit_nm: f64,
    /// The unit's symbol.
    unit: &'static str,
    /// Axis label of x.
    x_label: String,
    /// Axis label of y.
    y_label: String,
}

impl FieldAxes {
    /// The axes of a map spanning `span_counts` (its wider side) at `nm_per_count`.
    fn for_span(nm_per_count: f64, span_counts: f64) -> Self {
        let (unit_nm, unit) = if (span_counts * nm_per_count).abs() >= 1e3 {
            (1e3, "µm")
        } else {
            (1.0, "nm")
        };
        Self {
            nm_per_count,
            unit_nm,
            unit,
            x_label: format!("x on the field, {unit}"),
            y_label: format!("y on the field, {unit}"),
        }
    }

    /// The axes of a map of `region`.
    fn of_region(nm_per_count: f64, region: &Region) -> Self {
        Self::for_span(
            nm_per_count,
            (region.x_max_counts - region.x_min_counts)
                .max(region.y_max_counts - region.y_min_counts),
        )
    }

    /// The axes of a map of `points` (counts).
    fn of_points(nm_per_count: f64, points: impl Iterator<Item = (f64, f64)> + Clone) -> Self {
        let extent = |f: fn(&(f64, f64)) -> f64| {
            let (lo, hi) = points
                .clone()
                .map(|p| f(&p))
                .filter(|v| v.is_finite())
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
                    (a.min(v), b.max(v))
                });
            if hi >= lo { hi - lo } else { 0.0 }
        };
        Self::for_span(nm_per_count, extent(|p| p.0).max(extent(|p| p.1)))
    }

    /// A position in counts on the axes.
    fn at(&self, counts: f64) -> f64 {
        counts * self.nm_per_count / self.unit_nm
    }

    /// A position on the axes back in counts.
    fn counts(&self, value: f64) -> f64 {
        value * self.unit_nm / self.nm_per_count
    }

    /// The caption's sentence that takes the axes back to counts.
    fn note(&self) -> String {
        format!(
            "Axes in {} of field at the plan's nominal {} nm/count (1 {} = {} counts).",
            self.unit,
            significant(self.nm_per_count),
            self.unit,
            significant(self.unit_nm / self.nm_per_count)
        )
    }
}

/// Which lateral calibration coefficient a map shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coefficient {
    /// K̄x, nm/count (drawn in pm/count).
    Kx,
    /// K̄y, nm/count (drawn in pm/count).
    Ky,
    /// α, rad (drawn in mrad).
    Alpha,
}

impl Coefficient {
    /// File name of its map.
    pub fn file(self) -> &'static str {
        match self {
            Self::Kx => "lcc-kx.png",
            Self::Ky => "lcc-ky.png",
            Self::Alpha => "lcc-alpha.png",
        }
    }

    /// Name, what it is, display unit and factor from the stored unit to the display unit.
    fn describe(self) -> (&'static str, &'static str, &'static str, f64) {
        match self {
            Self::Kx => ("Kx", "x sensitivity", "pm/count", 1e3),
            Self::Ky => ("Ky", "y sensitivity", "pm/count", 1e3),
            Self::Alpha => ("α", "non-orthogonality", "mrad", 1e3),
        }
    }

    /// The measured value of a node, stored unit.
    pub fn of(self, node: &NodeSample) -> f64 {
        match self {
            Self::Kx => node.kx_nm_per_count,
            Self::Ky => node.ky_nm_per_count,
            Self::Alpha => node.alpha_rad,
        }
    }
}

/// The regression surface of `coefficient` over `region` with the measured node values on it
/// and their residuals below it, positions in µm (nm under a micrometre) through `nominal_nm_per_count`; the title
/// carries the fit's degree, σ and Δmax.
///
/// # Errors
/// [`PlotError`] when nothing finite can be drawn.
pub fn lcc_map(
    coefficient: Coefficient,
    fitted: &spm_correction::FittedSurface,
    summary: &SurfaceSummary,
    nodes: &[NodeSample],
    region: &Region,
    nominal_nm_per_count: f64,
) -> Result<Figure, PlotError> {
    let (name, what, unit, scale) = coefficient.describe();
    let title = format!(
        "{name} ({what}): degree {} surface, σ = {} {unit}, Δmax = {} {unit}",
        summary.degree,
        significant(summary.sigma * scale),
        significant(summary.delta_max * scale)
    );
    let axes = FieldAxes::of_region(nominal_nm_per_count, region);
    let surface = &fitted.surface;
    let value = |x: f64, y: f64| surface.evaluate(axes.counts(x), axes.counts(y)) * scale;
    let nodes: Vec<MapNode> = nodes
        .iter()
        .map(|n| MapNode {
            x: axes.at(n.x_counts),
            y: axes.at(n.y_counts),
            value: coefficient.of(n) * scale,
            visit: n.repeat_index,
        })
        .collect();
    let value_label = format!("{name}, {unit}");
    let residual_label = format!("measured − surface, {unit}");
    let png = surface_map(&MapFigure {
        title: &title,
        x_label: &axes.x_label,
        y_label: &axes.y_label,
        x_range: (axes.at(region.x_min_counts), axes.at(region.x_max_counts)),
        y_range: (axes.at(region.y_min_counts), axes.at(region.y_max_counts)),
        surface: &value,
        nodes: &nodes,
        value_label: &value_label,
        residual_label: &residual_label,
        map: ColorMap::Viridis,
    })
    .map_err(PlotError::of(coefficient.file()))?;
    Ok(Figure {
        file: coefficient.file().to_owned(),
        caption: format!(
            "{name} ({what}): fitted surface with the {} measured node values on the same \
             colour scale (top) and each node's residual, measured − surface (bottom); the \
             passes over a node are concentric discs, the first outermost. {}",
            nodes.len(),
            axes.note()
        ),
        png,
    })
}

/// Cells per side of the uncertainty maps.
const UNCERTAINTY_CELLS: usize = 60;

/// The file of the surfaces' uncertainty map.
pub const UNCERTAINTY_FILE: &str = "lcc-uncertainty.png";

/// The standard uncertainty of the plane's Kx, Ky and α surfaces over `region`, σ·√h with h
/// the leverage of the fit's design over the records at `records_counts` (the LCS centres
/// the plane was fitted from, counts), σ each surface's eq. (14) σ; positions in µm (nm under a micrometre) through
/// `nominal_nm_per_count`.
///
/// # Errors
/// [`PlotError`] when the design cannot be evaluated or nothing finite can be drawn.
pub fn uncertainty_map(
    plane: &spm_correction::PlaneSurfaces,
    summary: &crate::surfaces::RegressionSummary,
    records_counts: &[(f64, f64)],
    region: &Region,
    nominal_nm_per_count: f64,
) -> Result<Figure, PlotError> {
    let file = UNCERTAINTY_FILE;
    let k = nominal_nm_per_count;
    let axes = FieldAxes::of_region(k, region);
    let grid = cell_centres(
        (region.x_min_counts, region.x_max_counts),
        (region.y_min_counts, region.y_max_counts),
        UNCERTAINTY_CELLS,
    );
    let xs: Vec<f64> = records_counts.iter().map(|p| p.0).collect();
    let ys: Vec<f64> = records_counts.iter().map(|p| p.1).collect();
    let mut values = Vec::new();
    for (coefficient, surface, sigma) in [
        (Coefficient::Kx, &plane.kx_nm_per_count, summary.kx.sigma),
        (Coefficient::Ky, &plane.ky_nm_per_count, summary.ky.sigma),
        (Coefficient::Alpha, &plane.alpha_rad, summary.alpha.sigma),
    ] {
        let (name, what, unit, scale) = coefficient.describe();
        let u = spm_correction::fit::standard_uncertainty(surface, &xs, &ys, sigma * scale, &grid)
            .map_err(|e| PlotError {
                path: file.to_owned(),
                message: format!("{name} surface's leverages: {e}"),
            })?;
        values.push((
            format!("{name} ({what}), degree {}", surface.surface.degree()),
            u,
            format!("u({name}), {unit}"),
        ));
    }
    let panels: Vec<FieldPanel<'_>> = values
        .iter()
        .map(|(caption, u, label)| FieldPanel {
            caption,
            values: u,
            value_label: label,
        })
        .collect();
    let points: Vec<(f64, f64)> = records_counts
        .iter()
        .map(|p| (axes.at(p.0), axes.at(p.1)))
        .collect();
    let png = field_maps(&FieldFigure {
        title: "Standard uncertainty of the fitted surfaces over the field",
        x_label: &axes.x_label,
        y_label: &axes.y_label,
        x_range: (axes.at(region.x_min_counts), axes.at(region.x_max_counts)),
        y_range: (axes.at(region.y_min_counts), axes.at(region.y_max_counts)),
        cells: UNCERTAINTY_CELLS,
        panels: &panels,
        points: &points,
        map: ColorMap::Cividis,
        shared_scale: false,
    })
    .map_err(PlotError::of(file))?;
    Ok(Figure {
        file: file.to_owned(),
        caption: format!(
            "how far each fitted surface may be off, one standard uncertainty σ·√h: σ the \
             scatter of one record about the surface, h the leverage of the fit's design at \
             that place (small inside the {} records, the dots; large at the edges and \
             corners, where the surface extrapolates). {}",
            records_counts.len(),
            axes.note()
        ),
        png,
    })
}

/// Bins of the drift figure's running median.
const DRIFT_BINS: usize = 60;
/// Fewest estimates in a bin of the running median.
const DRIFT_MIN_PER_BIN: usize = 5;

/// Drift speed (nm/s through `nominal_nm_per_count`) against instrument time: the running
/// median of the kept estimates with their 16–84 % band, the spoiled skipping cycles
/// marked.
///
/// # Errors
/// [`PlotError`] when no estimate is finite.
pub fn drift_plot(drift: &[DriftSample], nominal_nm_per_count: f64) -> Result<Figure, PlotError> {
    let speed = |d: &DriftSample| {
        (
            d.time_s,
            d.vx_counts_per_s.hypot(d.vy_counts_per_s) * nominal_nm_per_count,
        )
    };
    let kept: Vec<(f64, f64)> = drift.iter().filter(|d| !d.spoiled).map(speed).collect();
    let spoiled: Vec<(f64, f64)> = drift.iter().filter(|d| d.spoiled).map(speed).collect();
    let running = running_quantiles(&kept, DRIFT_BINS, DRIFT_MIN_PER_BIN, &[0.16, 0.5, 0.84]);
    // Too few estimates for bins: the points themselves.
    let (band, median) = if running.is_empty() {
        (Vec::new(), kept.clone())
    } else {
        let lower = running.iter().map(|(t, q)| (*t, q[0]));
        let upper = running.iter().rev().map(|(t, q)| (*t, q[2]));
        (
            lower.chain(upper).collect(),
            running.iter().map(|(t, q)| (*t, q[1])).collect(),
        )
    };
    let file = "drift.png";
    let png = xy_chart(&XyFigure {
        title: format!(
            "Drift speed during the run ({} estimates, {} spoiled cycles)",
            drift.len(),
            spoiled.len()
        ),
        x_label: "instrument time, s".to_owned(),
        y_label: "drift speed, nm/s".to_owned(),
        series: vec![
            Series {
                name: "16–84 % of the estimates".to_owned(),
                points: band,
                style: SeriesStyle::Band,
            },
            Series {
                name: "running median".to_owned(),
                points: median,
                style: SeriesStyle::Line,
            },
            spoiled_series(&spoiled),
        ],
        log_y: false,
        y_from_zero: true,
        size: (960, 500),
    })
    .map_err(PlotError::of(file))?;
    Ok(Figure {
        file: file.to_owned(),
        caption: format!(
            "drift speed against instrument time: the running median of the kept estimates \
             over {DRIFT_BINS} equal time bins, the band holding their middle 68 % \
             (16th to 84th percentile); the skipping cycles the monitor spoiled and \
             discarded are marked apart (a cross each when at most {MAX_SPOILED_CROSSES}, \
             else their running median). Speeds through the nominal {} nm/count.",
            significant(nominal_nm_per_count)
        ),
        png,
    })
}

/// More spoiled estimates than this are drawn as their running median, not one cross each.
const MAX_SPOILED_CROSSES: usize = 100;

/// The spoiled cycles' estimates: a cross each when few, their running median (over a third
/// of the kept estimates' bins) when many.
fn spoiled_series(spoiled: &[(f64, f64)]) -> Series {
    if spoiled.len() <= MAX_SPOILED_CROSSES {
        return Series {
            name: "spoiled cycle (discarded)".to_owned(),
            points: spoiled.to_vec(),
            style: SeriesStyle::Crosses,
        };
    }
    let running = running_quantiles(spoiled, DRIFT_BINS / 3, DRIFT_MIN_PER_BIN, &[0.5]);
    Series {
        name: "running median of the spoiled cycles (discarded)".to_owned(),
        points: running.iter().map(|(t, q)| (*t, q[0])).collect(),
        style: SeriesStyle::LineAndMarkers,
    }
}

/// The node centres joined in visiting order, one panel per pass (repeat), positions in µm (nm under a micrometre)
/// through `nominal_nm_per_count`.
///
/// # Errors
/// [`PlotError`] when no node is finite.
pub fn trajectory_plot(
    nodes: &[NodeSample],
    nominal_nm_per_count: f64,
) -> Result<Figure, PlotError> {
    let file = "trajectory.png";
    let axes = FieldAxes::of_points(
        nominal_nm_per_count,
        nodes.iter().map(|n| (n.x_counts, n.y_counts)),
    );
    let mut passes: Vec<u32> = nodes.iter().map(|n| n.repeat_index).collect();
    passes.sort_unstable();
    passes.dedup();
    let panels: Vec<OrderPanel> = passes
        .iter()
        .map(|&pass| {
            let points: Vec<(f64, f64)> = nodes
                .iter()
                .filter(|n| n.repeat_index == pass)
                .map(|n| (axes.at(n.x_counts), axes.at(n.y_counts)))
                .collect();
            OrderPanel {
                caption: format!("pass {}: {} visits", pass + 1, points.len()),
                points,
            }
        })
        .collect();
    let png = order_map(&OrderFigure {
        title: format!(
            "Measured nodes in visiting order ({} visits, {} {})",
            nodes.len(),
            panels.len(),
            if panels.len() == 1 { "pass" } else { "passes" }
        ),
        x_label: axes.x_label.clone(),
        y_label: axes.y_label.clone(),
        panels,
        order_label: "visit number within the pass".to_owned(),
    })
    .map_err(PlotError::of(file))?;
    Ok(Figure {
        file: file.to_owned(),
        caption: format!(
            "the measured nodes joined in the order they were visited, one panel per pass \
             over the net. {}",
            axes.note()
        ),
        png,
    })
}

/// The file of the residual-distortion map.
pub const RESIDUAL_FILE: &str = "residual-distortion.png";

/// The residual distortion the distributed correction leaves over the field, nm, against the
/// simulator's ground truth (`spm_evaluation::accuracy::residual_field`: the field-wide
/// raster corrected with the surfaces and with the true LCC field, the best rigid motion
/// removed; `rms_pm` and `max_pm` are the accuracy table's figures of the same raster);
/// positions in µm (nm under a micrometre) through `nominal_nm_per_count`, the measured nodes as dots.
///
/// # Errors
/// [`PlotError`] when no residual is finite.
pub fn residual_map(
    field: &spm_evaluation::ResidualField,
    nodes: &[NodeSample],
    nominal_nm_per_count: f64,
    (rms_pm, max_pm): (f64, f64),
) -> Result<Figure, PlotError> {
    let file = RESIDUAL_FILE;
    let k = nominal_nm_per_count;
    let (n, s) = (field.pixels, field.step_counts);
    let axes = FieldAxes::for_span(k, s * n as f64);
    let [x0, y0] = field.origin_counts;
    let range = |lo: f64| (axes.at(lo - 0.5 * s), axes.at(lo + s * (n as f64 - 0.5)));
    let points: Vec<(f64, f64)> = nodes
        .iter()
        .map(|p| (axes.at(p.x_counts), axes.at(p.y_counts)))
        .collect();
    let caption = format!(
        "distributed surfaces: RMS {} nm, max {} nm",
        significant(rms_pm * 1e-3),
        significant(max_pm * 1e-3)
    );
    let panels = [FieldPanel {
        caption: &caption,
        values: &field.residual_nm,
        value_label: "residual distortion, nm",
    }];
    let png = field_maps(&FieldFigure {
        title: "What the correction leaves: residual distortion over the field",
        x_label: &axes.x_label,
        y_label: &axes.y_label,
        x_range: range(x0),
        y_range: range(y0),
        cells: n,
        panels: &panels,
        points: &points,
        map: ColorMap::Viridis,
        shared_scale: false,
    })
    .map_err(PlotError::of(file))?;
    Ok(Figure {
        file: file.to_owned(),
        caption: format!(
            "how far each point of a {n} × {n} raster over the field still lies from where it \
             truly is after the distributed correction, nm: the raster corrected with the \
             surfaces minus the same raster corrected with the simulator's true coefficients, \
             the best rotation and shift removed (a simulated run's ground truth; dots: the \
             measured nodes). Dark is good; bright areas are where the surfaces miss the \
             scanner. {}",
            axes.note()
        ),
        png,
    })
}

/// The file of the validation map (the corrected standard's lattice over the field).
pub const VALIDATION_MAP_FILE: &str = "validation-map.png";

/// The residual distortion without a ground truth: the lattice-constant error of the standard
/// imaged after the run at the validation's places over the calibrated region
/// (`spm_evaluation::validation::LatticeCheck`), after `spmcal correct` with the run's
/// calibration and uncorrected (the nominal sensitivity), one cell per place, positions in µm (nm under a micrometre)
/// through `nominal_nm_per_count`. Every backend gets it: the standard is the ruler. `None`
/// when no place has a centre or no corrected lattice was measured.
///
/// # Errors
/// [`PlotError`] when the figure cannot be drawn.
pub fn validation_map(
    check: &spm_evaluation::validation::LatticeCheck,
    nominal_nm_per_count: f64,
) -> Result<Option<Figure>, PlotError> {
    let file = VALIDATION_MAP_FILE;
    let k = nominal_nm_per_count;
    let places: Vec<&spm_evaluation::validation::LatticePlace> = check
        .places
        .iter()
        .filter(|p| p.centre_counts.iter().all(|c| c.is_finite()))
        .collect();
    if check.corrected_measured == 0 || places.is_empty() {
        return Ok(None);
    }
    // The places' grid: their distinct centres along each axis (to a count).
    let distinct = |axis: usize| {
        let mut v: Vec<f64> = places
            .iter()
            .map(|p| p.centre_counts[axis].round())
            .collect();
        v.sort_by(f64::total_cmp);
        v.dedup();
        v
    };
    let (xs, ys) = (distinct(0), distinct(1));
    let cells = xs.len().max(ys.len());
    let spacing = |v: &[f64]| {
        if v.len() > 1 {
            (v[v.len() - 1] - v[0]) / (v.len() - 1) as f64
        } else {
            f64::from(check.pixels) * check.step_counts
        }
    };
    let d = spacing(&xs).max(spacing(&ys));
    let (x0, y0) = (xs[0] - 0.5 * d, ys[0] - 0.5 * d);
    let cell_of = |c: f64, lo: f64| ((c - lo) / d).floor().clamp(0.0, (cells - 1) as f64) as usize;
    let mut corrected = vec![f64::NAN; cells * cells];
    let mut uncorrected = vec![f64::NAN; cells * cells];
    for p in &places {
        let cell = cell_of(p.centre_counts[1], y0) * cells + cell_of(p.centre_counts[0], x0);
        // Places that share a cell (centres closer than the grid's spacing): a measured value
        // is not covered by a place that has none.
        if let Some(v) = p.corrected_error_pct.filter(|v| v.is_finite()) {
            corrected[cell] = v;
        }
        if let Some(v) = p.uncorrected_error_pct.filter(|v| v.is_finite()) {
            uncorrected[cell] = v;
        }
    }
    if !corrected.iter().any(|v| v.is_finite()) {
        return Ok(None);
    }
    let side = d * cells as f64;
    let axes = FieldAxes::for_span(k, side);
    let points: Vec<(f64, f64)> = places
        .iter()
        .map(|p| (axes.at(p.centre_counts[0]), axes.at(p.centre_counts[1])))
        .collect();
    let after = format!(
        "after spmcal correct with this calibration: RMS {} %, max |error| {} % ({} of {} places)",
        significant(check.corrected_rms_error_pct),
        significant(check.corrected_max_error_pct),
        check.corrected_measured,
        check.places.len()
    );
    let before = format!(
        "uncorrected (the nominal {} nm/count): RMS {} %",
        significant(k),
        significant(check.uncorrected_rms_error_pct)
    );
    let label = "lattice-constant error, %";
    let mut panels = vec![FieldPanel {
        caption: &after,
        values: &corrected,
        value_label: label,
    }];
    if uncorrected.iter().any(|v| v.is_finite()) {
        panels.push(FieldPanel {
            caption: &before,
            values: &uncorrected,
            value_label: label,
        });
    }
    let png = field_maps(&FieldFigure {
        title: "What the correction leaves, measured on the standard",
        x_label: &axes.x_label,
        y_label: &axes.y_label,
        x_range: (axes.at(x0), axes.at(x0 + side)),
        y_range: (axes.at(y0), axes.at(y0 + side)),
        cells,
        panels: &panels,
        points: &points,
        map: ColorMap::Viridis,
        shared_scale: true,
    })
    .map_err(PlotError::of(file))?;
    Ok(Some(Figure {
        file: file.to_owned(),
        caption: format!(
            "the standard imaged after the run at {} places over the calibrated region \
             (counter-scanned pairs; dots: the images' centres), its lattice constant measured \
             on each pair against the standard's {} nm: the error left after the correction a \
             user applies (top) and without it (bottom), on one colour scale, one cell per place, \
             blank where the lattice was not measured. No ground truth is needed, so a real controller's run \
             shows it too. {}",
            check.places.len(),
            significant(check.lattice_constant_nm),
            axes.note()
        ),
        png,
    }))
}

/// The file of the before/after image of the standard.
pub const BEFORE_AFTER_FILE: &str = "before-after.png";

/// One image of the standard before and after correction, on one colour scale
/// ([`spm_evaluation::images::before_after::before_after`]), nm axes.
///
/// # Errors
/// [`PlotError`] when an image has no finite height.
pub fn before_after_figure(
    pair: &spm_evaluation::images::before_after::BeforeAfter,
) -> Result<Figure, PlotError> {
    use spm_evaluation::images::before_after::HeightsOnGrid;
    fn panel<'a>(caption: &'a str, h: &'a HeightsOnGrid) -> ImagePanel<'a> {
        ImagePanel {
            caption,
            columns: h.columns,
            rows: h.rows,
            origin: (h.origin_nm[0], h.origin_nm[1]),
            step: h.step_nm,
            values: &h.z_counts,
        }
    }
    let file = BEFORE_AFTER_FILE;
    let png = image_pair(&ImagePairFigure {
        title: &format!(
            "The standard at the {} place, before and after correction",
            pair.place
        ),
        x_label: "x, nm",
        y_label: "y, nm",
        panels: [
            panel("raw (nominal sensitivity)", &pair.before),
            panel("corrected (as spmcal correct)", &pair.after),
        ],
        value_label: "height − median, Z counts",
        map: ColorMap::AfmHot,
    })
    .map_err(PlotError::of(file))?;
    Ok(Figure {
        file: file.to_owned(),
        caption: format!(
            "one image of the standard taken after the run ({}), left as the instrument gives \
             it (pixels placed through the nominal sensitivity) and right corrected with the \
             calibration file as spmcal correct does, on one colour scale: on the right the \
             atoms should sit on a regular lattice of the standard's constant, with equal \
             spacing in every direction.",
            pair.place
        ),
        png,
    })
}

/// The file of the report's calibration-history figure.
pub const HISTORY_FILE: &str = "cdb-history.png";

/// One coefficient's history of one scanner in the CDB: per run, the mean acquisition time
/// (UTC s), the mean and its standard uncertainty, stored unit.
pub struct TrendSeries<'a> {
    /// The scanner.
    pub scanner: &'a str,
    /// `K̄x` or `K̄y`.
    pub coefficient: &'a str,
    /// The runs in time order.
    pub points: &'a [spm_cdb::TrendPoint],
}

/// The points of one series of [`cdb_trend_figure`]: per run with a value, [seconds since
/// `start_unix_s`, % change of the mean from the first run's, the same at mean − u and at
/// mean + u].
#[must_use]
pub fn trend_change(points: &[spm_cdb::TrendPoint], start_unix_s: f64) -> Vec<[f64; 4]> {
    let values: Vec<(f64, f64, f64)> = points
        .iter()
        .filter_map(|p| {
            p.stat
                .map(|st| (p.mean_unix_s, st.mean, st.std_uncertainty))
        })
        .filter(|(t, m, _)| t.is_finite() && m.is_finite() && *m != 0.0)
        .collect();
    let Some(&(_, first, _)) = values.first() else {
        return Vec::new();
    };
    let pct = |m: f64| (m / first - 1.0) * 100.0;
    values
        .iter()
        .map(|&(t, m, u)| [t - start_unix_s, pct(m), pct(m - u), pct(m + u)])
        .collect()
}

/// `spmcal cdb trend --png`: K̄x and K̄y of every scanner per run, as % change from the
/// scanner's first run, against the time since the CDB's first run (seconds, minutes, hours
/// or days, whichever suits the span), each mean with a band of ±
/// its standard uncertainty.
///
/// # Errors
/// [`PlotError`] when no run has a value.
pub fn cdb_trend_figure(series: &[TrendSeries<'_>]) -> Result<Vec<u8>, PlotError> {
    let file = "cdb trend";
    let start = series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.mean_unix_s))
        .filter(|t| t.is_finite())
        .fold(f64::INFINITY, f64::min);
    let all: Vec<Vec<[f64; 4]>> = series
        .iter()
        .map(|s| trend_change(s.points, start))
        .collect();
    // The time unit that suits the span: seconds, minutes, hours or days.
    let span_s = all.iter().flatten().map(|v| v[0]).fold(0.0_f64, f64::max);
    let (unit_s, unit) = [(86_400.0, "days"), (3600.0, "hours"), (60.0, "minutes")]
        .into_iter()
        .find(|(u, _)| span_s >= 3.0 * u)
        .unwrap_or((1.0, "seconds"));
    let mut out = Vec::new();
    for (s, values) in series.iter().zip(all) {
        let values: Vec<[f64; 4]> = values
            .into_iter()
            .map(|[t, m, lo, hi]| [t / unit_s, m, lo, hi])
            .collect();
        if values.is_empty() {
            continue;
        }
        let mut band: Vec<(f64, f64)> = values.iter().map(|v| (v[0], v[2])).collect();
        band.extend(values.iter().rev().map(|v| (v[0], v[3])));
        let name = format!("{} {}", s.scanner, s.coefficient);
        out.push(Series {
            name: format!("{name} ± u"),
            points: band,
            style: SeriesStyle::Band,
        });
        out.push(Series {
            name,
            points: values.iter().map(|v| (v[0], v[1])).collect(),
            style: SeriesStyle::LineAndMarkers,
        });
    }
    let first_utc = if start.is_finite() {
        // Whole seconds: the text carries no fraction.
        spm_cdb::rfc3339_utc(start.floor())
    } else {
        "–".to_owned()
    };
    xy_chart(&XyFigure {
        title: "Calibration history: K̄x and K̄y per run".to_owned(),
        x_label: format!("{unit} since the first run ({first_utc})"),
        y_label: "change from the scanner's first run, %".to_owned(),
        series: out,
        log_y: false,
        y_from_zero: false,
        size: (960, 540),
    })
    .map_err(PlotError::of(file))
}

#[cfg(test)]
mod tests {

    /// `check(span nm, unit, a position in counts → on the axes)`: a map of a micrometre or
    /// more in µm, of less in nm; positions go to the unit and back.
    #[test]
    fn a_map_under_a_micrometre_is_drawn_in_nm() {
        let check = |span_nm: f64, unit: &str, (counts, on_axes): (f64, f64)| {
            let k = 0.02;
            let axes = super::FieldAxes::for_span(k, span_nm / k);
            assert_eq!(axes.unit, unit, "{span_nm} nm");
            assert!((axes.at(counts) - on_axes).abs() < 1e-12, "{span_nm} nm");
            assert!((axes.counts(axes.at(counts)) - counts).abs() < 1e-9);
            assert!(axes.x_label.ends_with(unit) && axes.note().contains(unit));
        };
        check(50.0, "nm", (1000.0, 20.0));
        check(999.0, "nm", (-500.0, -10.0));
        check(1000.0, "µm", (1000.0, 0.02));
        check(1300.0, "µm", (32767.0, 0.65534));
        let points = [(0.0, 0.0), (2500.0, -100.0), (f64::NAN, 7.0)];
        assert_eq!(
            super::FieldAxes::of_points(0.02, points.iter().copied()).unit,
            "nm"
        );
    }
    use super::*;

    fn place(x: f64, y: f64, corrected: Option<f64>) -> spm_evaluation::validation::LatticePlace {
        spm_evaluation::validation::LatticePlace {
            place: format!("({x}, {y})"),
            centre_counts: [x, y],
            uncorrected_error_pct: Some(9.0),
            uncorrected_angle_error_deg: Some(5.0),
            corrected_error_pct: corrected,
            corrected_angle_error_deg: corrected.map(|_| 0.2),
            static_error_pct: None,
            static_angle_error_deg: None,
            counter_error_pct: None,
            counter_angle_error_deg: None,
        }
    }

    fn check(
        places: Vec<spm_evaluation::validation::LatticePlace>,
    ) -> spm_evaluation::validation::LatticeCheck {
        let measured = places
            .iter()
            .filter(|p| p.corrected_error_pct.is_some())
            .count();
        spm_evaluation::validation::LatticeCheck {
            measured_on: spm_evaluation::validation::LatticeSource::CounterPairs,
            lattice_constant_nm: 0.2461,
            pixels: 64,
            step_counts: 3.0,
            places,
            corrected_measured: measured,
            corrected_max_error_pct: 1.0,
            corrected_rms_error_pct: 1.0,
            corrected_max_angle_error_deg: 0.2,
            uncorrected_rms_error_pct: 9.0,
            static_measured: 0,
            static_rms_error_pct: f64::NAN,
            counter_measured: 0,
            counter_rms_error_pct: f64::NAN,
            dynamics_applied: false,
            thresholds: [1.0, 0.5],
            verdict: spm_evaluation::validation::Verdict::Pass,
            reason: None,
        }
    }

    /// A virtual run's places can share a cell of the map (nodes that attached to the same
    /// feature): a measured place is drawn whatever the order, and a map with nothing measured
    /// is no figure rather than an error (the HOPG terrace's right half, stop 44).
    #[test]
    fn places_sharing_a_cell_keep_the_measured_value() {
        let shared = check(vec![
            place(0.0, 0.0, Some(1.0)),
            place(10.0, 5.0, None),
            place(5000.0, 0.0, None),
        ]);
        assert!(validation_map(&shared, 0.02).unwrap().is_some());
        let none = check(vec![place(0.0, 0.0, None), place(5000.0, 0.0, None)]);
        assert!(validation_map(&none, 0.02).unwrap().is_none());
    }

    fn point(t: f64, mean: f64, u: f64) -> spm_cdb::TrendPoint {
        spm_cdb::TrendPoint {
            key: format!("run-{t}"),
            mean_unix_s: t,
            first_unix_s: t,
            last_unix_s: t,
            stat: Some(spm_cdb::CoefficientStat {
                n: 4,
                mean,
                std_dev: 2.0 * u,
                std_uncertainty: u,
            }),
        }
    }

    /// Issue 27's history figure: a sensitivity 0.0200 then 0.0202 nm/count a day later is a
    /// change of +1 % at 86 400 s, its ± 0.0001 band ±0.5 %; a run without a value is left
    /// out.
    #[test]
    fn the_trend_is_the_change_from_the_first_run_in_percent_against_time() {
        let mut points = vec![
            point(1000.0, 0.02, 1e-4),
            point(1000.0 + 86_400.0, 0.0202, 1e-4),
        ];
        points.push(spm_cdb::TrendPoint {
            stat: None,
            ..point(1000.0 + 2.0 * 86_400.0, 0.0, 0.0)
        });
        let v = trend_change(&points, 1000.0);
        assert_eq!(v.len(), 2);
        let expected = [[0.0, 0.0, -0.5, 0.5], [86_400.0, 1.0, 0.5, 1.5]];
        for (got, want) in v.iter().zip(expected) {
            for (g, w) in got.iter().zip(want) {
                assert!((g - w).abs() < 1e-9, "{got:?} vs {want:?}");
            }
        }
        let png = cdb_trend_figure(&[TrendSeries {
            scanner: "s",
            coefficient: "K̄x",
            points: &points,
        }])
        .unwrap();
        assert!(png.starts_with(&[0x89, b'P', b'N', b'G']));
    }
}
