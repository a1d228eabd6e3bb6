//! From image files to feature observations with acquisition times.

use crate::diagnose::{Diagnosis, diagnose_features_with_pixels};
use crate::level::{Lines, lattice_harmonics, level_lines, refine_basis};
use crate::types::{
    FeatureObservation, FeatureSet, FrameInfo, LatticeSpec, LineDirection, ModelCheckError,
    Options, SI7X7_A_NM,
};
use crate::vibration::PixelImage;
use spm_features::cells::{self, Image, LatticeSearch, Peaks, Template};
use spm_features::{DetectionConfig, Polarity, detect};
use spm_formats::{Channel, DateTime, Direction, ScanDir, SpmFile};
use spm_hal::{CountPoint, Counts, HeightMap};
use std::path::{Path, PathBuf};

/// How features are extracted from images.
#[derive(Clone, Debug, PartialEq)]
pub struct ExtractOptions {
    /// Hills or pits; `None` = by lattice (pits, i.e. corner holes, for Si 7×7; hills otherwise).
    pub polarity: Option<Polarity>,
    /// Height channel name; `None` = the first channel in metres.
    pub channel: Option<String>,
    /// Line time assumed when a file records none, s (times are then in "line units").
    pub default_line_time_s: f64,
    /// Smallest signal-to-noise ratio of a feature (see spm-features). Default 4.
    pub min_snr: f64,
    /// Which localiser finds the features. Default: [`Localiser::Auto`].
    pub localiser: Localiser,
}

impl Default for ExtractOptions {
    fn default() -> Self {
        Self {
            polarity: None,
            channel: None,
            default_line_time_s: 1.0,
            min_snr: 4.0,
            localiser: Localiser::Auto,
        }
    }
}

/// Which localiser turns an image into features.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Localiser {
    /// By evidence, decided on the first image: the cell-template localiser when the
    /// image's power spectrum shows the claimed lattice and either its cell is a known
    /// pattern (Si(111)-7×7) or the plain detector puts fewer than a third of its
    /// features' nearest neighbours on lattice vectors (not the lattice by the diagnosis's
    /// own test); the plain detector otherwise.
    Auto,
    /// One feature per hill or pit (spm-features' Gaussian localiser).
    Features,
    /// One feature per unit cell: the mean cell folded from the image, fitted to every
    /// cell (see `cells.rs`).
    Cells,
}

/// Below this fraction of plain features with a lattice vector (of their own
/// nearest-neighbour basis) to their nearest neighbour — where the diagnosis would refuse
/// the plain features as not the lattice although the spectrum shows it —
/// [`Localiser::Auto`] takes the cell localiser (a clean atomic lattice gives 0.8–1; the
/// HOPG terrace with its step 0.56, and there the plain path with the structure-factor
/// registration is better: 44 pm baseline against 47–123 pm by cells, whose single
/// template phase does not follow the two terraces' registry).
const PLAIN_NN_FRACTION: f64 = 0.33;

/// One image input: a file and, optionally, its start time on a common axis.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageInput {
    /// The file.
    pub path: PathBuf,
    /// Frame start, s on the common axis; `None` = from the file's record date,
    /// or right after the previous frame when the file has none.
    pub start_time_s: Option<f64>,
}

/// A record time as seconds on the Unix axis (spm-formats' calendar).
fn seconds_of(dt: DateTime) -> f64 {
    dt.unix_seconds() as f64
}

/// Where a height map's features belong and how to find them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MapContext {
    /// Pixel pitch (x, y), nominal nm.
    pub pixel_nm: [f64; 2],
    /// Hills or pits.
    pub polarity: Polarity,
    /// Lattice period, nm (sets the detection scales).
    pub a_nm: f64,
    /// Smallest signal-to-noise ratio of a feature.
    pub min_snr: f64,
    /// Fast-axis direction of the map's lines.
    pub direction: LineDirection,
    /// Frame index of the features.
    pub frame_index: usize,
}

/// Features of one height map in scanner geometry (row index grows with y,
/// as [`HeightMap`] defines; one map unit = one pixel), placed with `ctx`;
/// `time_and_line` gives (time s, acquisition line) of a fractional
/// (column, row).
pub fn features_from_height_map(
    map: &HeightMap,
    ctx: &MapContext,
    time_and_line: &dyn Fn(f64, f64) -> (f64, usize),
) -> Result<Vec<FeatureObservation>, ModelCheckError> {
    let MapContext {
        pixel_nm,
        polarity,
        a_nm,
        min_snr,
        direction,
        frame_index,
    } = *ctx;
    let a_px = a_nm / pixel_nm[0].max(1e-12);
    let config = DetectionConfig {
        polarity,
        // Corner holes: the deepest minimum within 0.7 a (the shallower
        // half-cell minima lie at a/√3); atoms: the highest within a/2.
        min_separation_px: (if polarity == Polarity::Pit { 0.7 } else { 0.5 } * a_px).max(1.5),
        min_snr,
        max_fit_radius_px: (0.4 * a_px).clamp(2.0, 40.0),
        max_width_px: a_px.max(1.0),
        min_width_px: 0.4,
        ..DetectionConfig::default()
    };
    let found = detect(map, &config).map_err(|source| ModelCheckError::Features {
        label: format!("frame {frame_index} {direction:?}"),
        source,
    })?;
    let (nx, ny) = (map.columns as f64, map.rows as f64);
    Ok(found
        .features
        .iter()
        .map(|f| {
            let (column, row) = map.pixel_of(f.position);
            let (time_s, line_index) = time_and_line(column, row);
            let line_time_offset_s = Some(time_s - time_and_line(column, row.round()).0);
            let width_px = f.width.value() / map.pixel_step.value().max(1e-300);
            let sigma_px = f.uncertainty.radial().value()
                / std::f64::consts::SQRT_2
                / map.pixel_step.value().max(1e-300);
            FeatureObservation {
                x_nm: (column - 0.5 * (nx - 1.0)) * pixel_nm[0],
                y_nm: (row - 0.5 * (ny - 1.0)) * pixel_nm[1],
                time_s,
                direction,
                frame_index,
                line_index,
                sigma_nm: Some(sigma_px * pixel_nm[0]),
                width_nm: Some(width_px * pixel_nm[1]),
                // spm-features' window: fit_radius_sigmas·σ, at most 1.25 × the
                // separation and the configured maximum, at least the minimum.
                fit_radius_nm: Some(
                    (config.fit_radius_sigmas * width_px)
                        .min(1.25 * config.min_separation_px)
                        .clamp(config.min_fit_radius_px, config.max_fit_radius_px)
                        * pixel_nm[1],
                ),
                line_time_offset_s,
            }
        })
        .collect())
}

/// Scan settings that one scan series shares.
#[derive(Clone, Debug, PartialEq)]
struct FrameSettings {
    pixels: [usize; 2],
    size_nm: [f64; 2],
    line_time_s: Option<f64>,
    angle_deg: Option<f64>,
    bias: Option<String>,
    centre_nm: Option<[f64; 2]>,
}

impl FrameSettings {
    fn differs_from(&self, other: &Self) -> Vec<String> {
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-3 * a.abs().max(b.abs());
        let mut why = Vec::new();
        if self.pixels != other.pixels {
            why.push(format!("pixels {:?} vs {:?}", self.pixels, other.pixels));
        }
        if !(close(self.size_nm[0], other.size_nm[0]) && close(self.size_nm[1], other.size_nm[1])) {
            why.push(format!(
                "size {:?} nm vs {:?} nm",
                self.size_nm, other.size_nm
            ));
        }
        if let (Some(a), Some(b)) = (self.line_time_s, other.line_time_s)
            && !close(a, b)
        {
            why.push(format!("line time {a} s vs {b} s"));
        }
        if let (Some(a), Some(b)) = (self.angle_deg, other.angle_deg)
            && (a - b).abs() > 1e-3
        {
            why.push(format!("scan angle {a}° vs {b}°"));
        }
        if let (Some(a), Some(b)) = (&self.bias, &other.bias)
            && a != b
        {
            why.push(format!("bias {a} vs {b}"));
        }
        if let (Some(a), Some(b)) = (self.centre_nm, other.centre_nm)
            && (a[0] - b[0]).hypot(a[1] - b[1]) > 0.5 * self.size_nm[0].min(other.size_nm[0])
        {
            why.push(format!(
                "frame centre {a:?} nm vs {b:?} nm (different areas)"
            ));
        }
        why
    }
}

/// The forward height channel of a file (or its backward one when the file holds only that
/// direction), and the backward channel of the same name when there is one.
fn height_channels<'f>(
    file: &'f SpmFile,
    ex: &ExtractOptions,
    path: &str,
) -> Result<(&'f Channel, Option<&'f Channel>), ModelCheckError> {
    let is_height = |c: &&Channel| match &ex.channel {
        Some(name) => c.name() == name,
        None => c.unit() == "m",
    };
    let heights: Vec<&Channel> = file.channels.iter().filter(is_height).collect();
    let Some(forward) = heights
        .iter()
        .find(|c| c.direction() == Direction::Forward)
        .or_else(|| heights.first())
        .copied()
    else {
        return Err(ModelCheckError::MissingMetadata {
            path: path.to_owned(),
            reason: match &ex.channel {
                Some(name) => format!("no channel named {name:?}"),
                None => format!(
                    "no height channel (unit m) among {} channel(s): {}",
                    file.channels.len(),
                    file.channels
                        .iter()
                        .map(|c| format!("{} [{}] {:?}", c.name(), c.unit(), c.direction()))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            },
        });
    };
    let backward = heights
        .iter()
        .find(|c| c.direction() == Direction::Backward && c.name() == forward.name())
        .copied()
        .filter(|b| !std::ptr::eq(*b, forward));
    Ok((forward, backward))
}

/// The levelled channel as a height map in scanner geometry (row index grows with y; display
/// row 0 is the top), one pixel per count, in pm when the channel is in metres, and which
/// pixels were not scanned (NaN; their height is 0).
///
/// The lines are levelled by [`level_lines`]; with `search`, the lattice's peaks are
/// looked for in the image so levelled, and, when found, the lines are levelled again
/// jointly with the lattice's harmonics.
fn geometric_map(channel: &Channel, search: Option<&LatticeSearch>) -> (HeightMap, Vec<bool>) {
    let (map, bad, _) = geometric_map_and_lattice(channel, search);
    (map, bad)
}

/// [`geometric_map`], and whether the lattice was found in it (its lines levelled jointly
/// with the lattice's harmonics).
fn geometric_map_and_lattice(
    channel: &Channel,
    search: Option<&LatticeSearch>,
) -> (HeightMap, Vec<bool>, bool) {
    let (nx, ny) = (channel.nx(), channel.ny());
    let scale = if channel.unit() == "m" { 1e12 } else { 1.0 };
    let data = channel.data();
    let mut raw = vec![0.0; nx * ny];
    let mut bad = vec![false; nx * ny];
    for r in 0..ny {
        for c in 0..nx {
            let v = data[r * nx + c];
            let k = (ny - 1 - r) * nx + c;
            if v.is_finite() {
                raw[k] = v * scale;
            } else {
                bad[k] = true;
            }
        }
    }
    // Heights beyond a metre are not a surface (a corrupt or hostile file): no lattice
    // model is fitted to them, the plain levelling only.
    let physical = channel.unit() != "m" || raw.iter().all(|v| v.abs() < 1e12);
    let (z, found) = level_with_lattice(raw, &bad, (nx, ny), search.filter(|_| physical));
    let map = HeightMap {
        origin: CountPoint::from_counts(0.0, 0.0),
        pixel_step: Counts(1.0),
        columns: nx,
        rows: ny,
        z_counts: z,
        time_s: vec![0.0; nx * ny],
    };
    (map, bad, found)
}

/// Levels the lines of `raw` (row-major, `bad` unscanned); with `search`, the lattice's
/// peaks are looked for in the image so levelled, and, when found, the lines are levelled
/// again jointly with the lattice's harmonics (then `true`).
fn level_with_lattice(
    raw: Vec<f64>,
    bad: &[bool],
    (nx, ny): (usize, usize),
    search: Option<&LatticeSearch>,
) -> (Vec<f64>, bool) {
    let mut z = raw.clone();
    level_lines(&mut z, bad, nx, ny, &[]);
    let mut found = false;
    if let Some(search) = search {
        let img = Image { z: &z, bad, nx, ny };
        if let Some(peaks) = cells::find_lattice(&img, search) {
            let lines = Lines {
                z: &raw,
                bad,
                nx,
                ny,
            };
            let basis = refine_basis(&lines, &peaks);
            let harmonics = lattice_harmonics(basis);
            tracing::debug!(
                spectrum = ?peaks.k,
                refined = ?basis,
                harmonics = harmonics.len(),
                "lines levelled jointly with the lattice's harmonics"
            );
            z = raw;
            level_lines(&mut z, bad, nx, ny, &harmonics);
            found = true;
        }
    }
    (z, found)
}

/// Whether an unscanned pixel lies within `a_px` pixels of the feature.
fn near_unscanned(
    f: &FeatureObservation,
    pixel_nm: [f64; 2],
    (nx, ny): (usize, usize),
    a_px: i64,
    bad: &[bool],
) -> bool {
    let c = (f.x_nm / pixel_nm[0] + 0.5 * (nx as f64 - 1.0)).round() as i64;
    let r = (f.y_nm / pixel_nm[1] + 0.5 * (ny as f64 - 1.0)).round() as i64;
    (-a_px..=a_px).any(|dr| {
        (-a_px..=a_px).any(|dc| {
            let (rr, cc) = (r + dr, c + dc);
            rr >= 0
                && cc >= 0
                && (rr as usize) < ny
                && (cc as usize) < nx
                && bad[rr as usize * nx + cc as usize]
        })
    })
}

/// The cell localiser's reference: the first image's lattice and template.
#[derive(Clone, Debug)]
struct CellReference {
    peaks: Peaks,
    template: Option<(Template, [f64; 2])>,
}

/// How the images of one extraction are localised (decided on the first image).
#[derive(Clone, Debug)]
enum Mode {
    Undecided,
    Plain,
    Cells(CellReference),
}

/// The claimed lattice's first peaks, cycles per nm ([`LatticeSearch::near_period`]).
fn lattice_search(lattice: &LatticeSpec, pixel_nm: [f64; 2]) -> LatticeSearch {
    LatticeSearch::near_period(
        pixel_nm,
        lattice.a_nm(),
        matches!(lattice, LatticeSpec::Hex { .. }),
    )
}

/// `Some(reason)` when the lattice's cell pattern is not resolved by the pixels: the
/// second shell of its reciprocal lattice (the first harmonics beyond the period itself)
/// must lie below the pixel Nyquist frequency, else a cell is one blurred, aliased
/// cosine and no point of it can be localised.
fn unresolved(peaks: &Peaks) -> Option<String> {
    let [k1, k2] = peaks.k;
    let first = k1[0].hypot(k1[1]).max(k2[0].hypot(k2[1]));
    let mut worst: f64 = 0.0;
    for m in -2i32..=2 {
        for n in -2i32..=2 {
            let k = [
                m as f64 * k1[0] + n as f64 * k2[0],
                m as f64 * k1[1] + n as f64 * k2[1],
            ];
            let len = k[0].hypot(k[1]);
            if len > 1.05 * first && len < 1.9 * first {
                worst = worst.max(k[0].abs()).max(k[1].abs());
            }
        }
    }
    let a_px = peaks.cell_area_px().sqrt();
    (worst >= 0.5).then(|| {
        format!(
            "the lattice is in the image (spectrum peaks {:.0}× and {:.0}× their ring), but a \
             cell spans only {a_px:.1} px: its pattern's second harmonics ({:.2} cycles/px) lie \
             beyond the pixel Nyquist limit (0.5), so a cell is one aliased cosine and no \
             point of it can be localised; image it with at least {:.0} px per cell",
            peaks.contrast[0],
            peaks.contrast[1],
            worst,
            (a_px * 2.0 * worst).ceil()
        )
    })
}

/// Pixel pitch of a file without a physical size, from the lattice's fundamental in
/// its image and the claimed lattice constant; `None` when no lattice is seen.
fn self_calibrate(channel: &Channel, lattice: &LatticeSpec) -> Option<(f64, Peaks)> {
    let (map, bad) = geometric_map(channel, None);
    let img = Image {
        z: &map.z_counts,
        bad: &bad,
        nx: map.columns,
        ny: map.rows,
    };
    let mut search = lattice_search(lattice, [1.0, 1.0]);
    search.k_range = [0.0, 0.5 * std::f64::consts::SQRT_2];
    let peaks = cells::find_lattice(&img, &search)?;
    let sin_gamma = lattice.basis_angle_rad().sin();
    let a_px = (peaks.cell_area_px() / sin_gamma).sqrt();
    Some((lattice.a_nm() / a_px, peaks))
}

/// Where the features of one channel go.
struct ChannelCtx<'c> {
    map_ctx: MapContext,
    time_and_line: &'c dyn Fn(f64, f64) -> (f64, usize),
    label: String,
}

/// Features of one channel by the cell localiser, or `None` when it finds too few cells.
fn cell_features(
    map: &HeightMap,
    bad: &[bool],
    ctx: &ChannelCtx<'_>,
    peaks: &Peaks,
    reference: Option<(&Template, [f64; 2])>,
) -> Option<(Vec<FeatureObservation>, cells::CellRun)> {
    let img = Image {
        z: &map.z_counts,
        bad,
        nx: map.columns,
        ny: map.rows,
    };
    let run = cells::locate_cells(&img, peaks, ctx.map_ctx.polarity, reference);
    if let Some(r) = &run {
        let mut c: Vec<f64> = r.cells.iter().map(|c| c.correlation).collect();
        tracing::debug!(
            label = %ctx.label,
            k = ?peaks.k,
            contrast = ?peaks.contrast,
            origin = ?r.origin,
            median_correlation = spm_regression::upper_median(&mut c).unwrap_or(0.0),
            "cell localiser"
        );
    }
    let run = run?;
    let (nx, ny) = (map.columns as f64, map.rows as f64);
    let px = ctx.map_ctx.pixel_nm;
    let feats = run
        .cells
        .iter()
        .map(|c| {
            let (time_s, line_index) = (ctx.time_and_line)(c.pos[0], c.pos[1]);
            let line_time_offset_s =
                Some(time_s - (ctx.time_and_line)(c.pos[0], c.pos[1].round()).0);
            FeatureObservation {
                x_nm: (c.pos[0] - 0.5 * (nx - 1.0)) * px[0],
                y_nm: (c.pos[1] - 0.5 * (ny - 1.0)) * px[1],
                time_s,
                direction: ctx.map_ctx.direction,
                frame_index: ctx.map_ctx.frame_index,
                line_index,
                sigma_nm: Some(c.sigma_px * px[0]),
                // The fit window (cos² of radius R ≈ a Gaussian of σ ≈ R/2.6) is the
                // footprint over lines.
                width_nm: Some(run.radius_px / 2.6 * px[1]),
                fit_radius_nm: Some(run.radius_px * px[1]),
                line_time_offset_s,
            }
        })
        .collect::<Vec<_>>();
    tracing::debug!(
        label = %ctx.label,
        cells = feats.len(),
        candidates = run.candidates,
        "cells located"
    );
    (feats.len() >= 6).then_some((feats, run))
}

/// The features of one channel: decides the mode on the first channel, then localises.
fn channel_features(
    mode: &mut Mode,
    map: &HeightMap,
    bad: &[bool],
    ctx: &ChannelCtx<'_>,
    lattice: &LatticeSpec,
    ex: &ExtractOptions,
) -> Result<Vec<FeatureObservation>, ModelCheckError> {
    let plain = || features_from_height_map(map, &ctx.map_ctx, ctx.time_and_line);
    let img = Image {
        z: &map.z_counts,
        bad,
        nx: map.columns,
        ny: map.rows,
    };
    if let Mode::Undecided = mode {
        let peaks = match ex.localiser {
            Localiser::Features => None,
            Localiser::Auto | Localiser::Cells => {
                cells::find_lattice(&img, &lattice_search(lattice, ctx.map_ctx.pixel_nm))
            }
        };
        let Some(peaks) = peaks else {
            tracing::debug!(label = %ctx.label, "no lattice peaks in the spectrum");
            *mode = Mode::Plain;
            return plain();
        };
        let pattern_cell = (lattice.a_nm() - SI7X7_A_NM).abs() < 1e-6;
        let mut plain_found = None;
        if ex.localiser == Localiser::Auto && !pattern_cell {
            let found = plain()?;
            let pts: Vec<[f64; 2]> = found.iter().map(|f| [f.x_nm, f.y_nm]).collect();
            let q = crate::index::own_nn_fraction(&pts);
            tracing::debug!(q, "plain detector: nearest neighbours on lattice vectors");
            if q >= PLAIN_NN_FRACTION {
                *mode = Mode::Plain;
                return Ok(found);
            }
            plain_found = Some(found);
        }
        if let Some(reason) = unresolved(&peaks) {
            return Err(ModelCheckError::Unresolved {
                context: ctx.label.clone(),
                reason,
            });
        }
        match cell_features(map, bad, ctx, &peaks, None) {
            Some((feats, run)) => {
                *mode = Mode::Cells(CellReference {
                    peaks,
                    template: Some((run.template, run.origin)),
                });
                return Ok(feats);
            }
            None => {
                *mode = Mode::Plain;
                return match plain_found {
                    Some(f) => Ok(f),
                    None => plain(),
                };
            }
        }
    }
    match mode {
        Mode::Cells(reference) => {
            let peaks = cells::follow_lattice(&img, &reference.peaks);
            let refd = reference.template.as_ref().map(|(t, o)| (t, *o));
            Ok(cell_features(map, bad, ctx, &peaks, refd).map_or_else(Vec::new, |r| r.0))
        }
        _ => plain(),
    }
}

/// The frame's physical size (x, y), nm: stored, or self-calibrated from the lattice in
/// the image when the file has none (a warning says so).
fn frame_size_nm(
    forward: &Channel,
    lattice: &LatticeSpec,
    (name, path): (&str, &str),
    warnings: &mut Vec<String>,
) -> Result<(f64, f64), ModelCheckError> {
    let (nx, ny) = (forward.nx(), forward.ny());
    if let (Some(sx), Some(sy)) = (forward.size_x_nm(), forward.size_y_nm()) {
        return Ok((sx, sy));
    }
    let Some((pixel, peaks)) = self_calibrate(forward, lattice) else {
        return Err(ModelCheckError::MissingMetadata {
            path: path.to_owned(),
            reason: "no physical size stored, and no lattice in the image's power \
                     spectrum to self-calibrate the pixel pitch from"
                .to_owned(),
        });
    };
    warnings.push(format!(
        "{name}: no physical size stored; pixel pitch {pixel:.5} nm self-calibrated \
         from the lattice in the image (cell of {:.1} px² set to the claimed {:.4} nm \
         lattice's): scales are relative to that, the lattice constant is not measured",
        peaks.cell_area_px(),
        lattice.a_nm()
    ));
    Ok((pixel * nx as f64, pixel * ny as f64))
}

/// Where the files' frames start on one time axis, s: given, else from the record
/// times, else where the previous frame ended.
struct FrameClock {
    /// The first file's record time, s.
    first_record_s: Option<f64>,
    /// Where the previous frame ended, s.
    next_start_s: f64,
}

impl FrameClock {
    /// The start of a frame given `start` (the caller's) and `recorded` (the file's
    /// stamp), lasting `duration_s`; `first` says whether it is the first frame.
    fn start_s(
        &mut self,
        start: Option<f64>,
        recorded: Option<DateTime>,
        first: bool,
        duration_s: f64,
    ) -> f64 {
        let start_s = match (start, recorded, self.first_record_s) {
            (Some(s), _, _) => s,
            // A record time is stamped to the second: the true start lies in
            // [rec, rec + 1 s). Frames shorter than a second (a fast-SPM
            // movie) share stamps, so each starts where the previous ended
            // when that is within its second, not on top of it.
            (None, Some(rec), Some(first_s)) => {
                let rec_s = seconds_of(rec) - first_s;
                if first {
                    rec_s
                } else {
                    self.next_start_s.clamp(rec_s, rec_s + 1.0)
                }
            }
            _ => self.next_start_s,
        };
        self.next_start_s = start_s + duration_s;
        start_s
    }
}

/// One frame's timing and geometry, shared by its channels.
struct FrameGeometry {
    /// Pixels (columns, lines).
    pixels: (usize, usize),
    /// Pixel size (x, y), nm.
    pixel_nm: [f64; 2],
    /// The frame's start on the files' time axis, s.
    start_s: f64,
    /// One line's trace, s.
    line_time_s: f64,
    /// From one line's start to the next's, s.
    line_period_s: f64,
}

/// The feature observations of one channel of frame `frame_index` (features next to
/// unscanned pixels dropped), appended to `out`.
fn channel_observations(
    (channel, file, frame_index, name): (&Channel, &SpmFile, usize, &str),
    frame: &FrameGeometry,
    mode: &mut Mode,
    lattice: &LatticeSpec,
    polarity: Polarity,
    ex: &ExtractOptions,
    (out, pixels): (&mut Vec<FeatureObservation>, &mut Vec<PixelImage>),
) -> Result<(), ModelCheckError> {
    let (nx, ny) = frame.pixels;
    let pixel_nm = frame.pixel_nm;
    let line_time = frame.line_time_s;
    let pattern_cell = (lattice.a_nm() - SI7X7_A_NM).abs() < 1e-6;
    let direction = match channel.direction() {
        Direction::Forward => LineDirection::Forward,
        Direction::Backward => LineDirection::Backward,
    };
    let ch_timing = channel.timing();
    let first_line = ch_timing.map_or(
        if direction == LineDirection::Backward {
            line_time
        } else {
            0.0
        },
        |t| t.first_line_start_s,
    );
    // Atomic lattices (one hill per site, the plain localiser's) are levelled
    // jointly with their harmonics; a cell pattern (Si(111)-7×7) keeps the plain
    // per-line levelling: its cell localiser removes each line's mean inside its
    // own fit windows, and its many strong harmonics beyond the second shell are
    // not in the joint model (with them the 20 nm Si 7×7 frame lost its lattice).
    let search = (!pattern_cell).then(|| lattice_search(lattice, pixel_nm));
    let (map, bad, lattice_found) = geometric_map_and_lattice(channel, search.as_ref());
    let scan_up = channel.scan_dir().or(file.scan_dir) == Some(ScanDir::Up);
    let time_and_line = |column: f64, row: f64| {
        let display_row = (ny as f64 - 1.0) - row;
        let acq_row = if scan_up { row } else { display_row };
        let acq_col = match direction {
            LineDirection::Forward => column,
            LineDirection::Backward => nx as f64 - 1.0 - column,
        };
        let t = frame.start_s
            + first_line
            + acq_row * frame.line_period_s
            + (acq_col + 0.5) * line_time / nx as f64;
        (t, acq_row.round().max(0.0) as usize)
    };
    let ctx = ChannelCtx {
        map_ctx: MapContext {
            pixel_nm,
            polarity,
            a_nm: lattice.a_nm(),
            min_snr: ex.min_snr,
            direction,
            frame_index,
        },
        time_and_line: &time_and_line,
        label: format!("{name}, {}", format!("{direction:?}").to_lowercase()),
    };
    let feats = channel_features(mode, &map, &bad, &ctx, lattice, ex)?;
    if lattice_found && matches!(mode, Mode::Plain) {
        pixels.extend(PixelImage::new(
            (frame_index, direction),
            (&map.z_counts, &bad, nx, ny),
            pixel_nm,
            &time_and_line,
        ));
    }
    // Drop features next to unscanned (NaN) pixels.
    let a_px = (lattice.a_nm() / pixel_nm[0]).ceil() as i64;
    for f in feats {
        let near_nan = near_unscanned(&f, pixel_nm, (nx, ny), a_px, &bad);
        if !near_nan {
            out.push(f);
        }
    }
    Ok(())
}

/// Extracts feature observations from the height channels (forward and
/// backward) of each file. Frame `i` of the result is file `i`.
///
/// A file without a physical size (raw height arrays) is self-calibrated: its pixel
/// pitch makes the cell of the lattice's fundamental in the image the claimed
/// lattice's (a warning says so; its scales are then relative to that).
pub fn extract_features(
    files: &[(SpmFile, Option<f64>)],
    lattice: &LatticeSpec,
    ex: &ExtractOptions,
) -> Result<FeatureSet, ModelCheckError> {
    extract_features_and_pixels(files, lattice, ex).map(|(set, _)| set)
}

/// [`extract_features`], and the pixels of every atomic-lattice image levelled with its
/// lattice template (for the pixel-level vibration search).
fn extract_features_and_pixels(
    files: &[(SpmFile, Option<f64>)],
    lattice: &LatticeSpec,
    ex: &ExtractOptions,
) -> Result<(FeatureSet, Vec<PixelImage>), ModelCheckError> {
    let mut pixels = Vec::new();
    let polarity = ex
        .polarity
        .unwrap_or(if (lattice.a_nm() - SI7X7_A_NM).abs() < 1e-6 {
            Polarity::Pit
        } else {
            Polarity::Hill
        });
    let mut set = FeatureSet::default();
    let mut clock = FrameClock {
        first_record_s: files.iter().find_map(|(f, _)| f.recorded).map(seconds_of),
        next_start_s: 0.0,
    };
    let mut first_settings: Option<(String, FrameSettings)> = None;
    let mut mode = match ex.localiser {
        Localiser::Features => Mode::Plain,
        _ => Mode::Undecided,
    };
    for (frame_index, (file, start)) in files.iter().enumerate() {
        let path = file.source.display().to_string();
        let name = file
            .source
            .file_name()
            .map_or_else(|| path.clone(), |n| n.to_string_lossy().into_owned());
        let (forward, backward) = height_channels(file, ex, &path)?;
        let (nx, ny) = (forward.nx(), forward.ny());
        let (sx, sy) = frame_size_nm(forward, lattice, (&name, &path), &mut set.warnings)?;
        let timing = forward.timing();
        let line_time = timing.map_or(ex.default_line_time_s, |t| t.line_time_s);
        let settings = FrameSettings {
            pixels: [nx, ny],
            size_nm: [sx, sy],
            line_time_s: timing.map(|t| t.line_time_s),
            angle_deg: forward.angle_deg(),
            bias: file.header_value("BIAS").map(|b| b.trim().to_owned()),
            centre_nm: forward
                .center_x_nm()
                .zip(forward.center_y_nm())
                .map(|(x, y)| [x, y]),
        };
        if let Some((first_label, first)) = &first_settings {
            let why = settings.differs_from(first);
            if !why.is_empty() {
                set.warnings.push(format!(
                    "{path} differs from {first_label} in {}: frames of different scan \
                     series are diagnosed as one",
                    why.join(", ")
                ));
            }
        } else {
            first_settings = Some((path.clone(), settings));
        }
        let line_period = timing.map_or(
            line_time * if backward.is_some() { 2.0 } else { 1.0 },
            |t| t.line_period_s,
        );
        let start_s = clock.start_s(
            *start,
            file.recorded,
            set.frames.is_empty(),
            line_period * ny as f64,
        );
        set.frames.push(FrameInfo {
            label: format!(
                "{} ({})",
                file.source
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default(),
                forward.name()
            ),
            half_width_x_nm: 0.5 * sx,
            half_height_y_nm: 0.5 * sy,
            start_time_s: start_s,
            duration_s: line_period * ny as f64,
            fast_speed_nm_per_s: sx / line_time.max(1e-12),
            lines: ny,
            pixel_nm: Some([sx / nx as f64, sy / ny as f64]),
        });
        let frame = FrameGeometry {
            pixels: (nx, ny),
            pixel_nm: [sx / nx as f64, sy / ny as f64],
            start_s,
            line_time_s: line_time,
            line_period_s: line_period,
        };
        for channel in [Some(forward), backward].into_iter().flatten() {
            channel_observations(
                (channel, file, frame_index, &name),
                &frame,
                &mut mode,
                lattice,
                polarity,
                ex,
                (&mut set.features, &mut pixels),
            )?;
        }
    }
    Ok((set, pixels))
}

/// The `spmcal diagnose` entry point: reads the files, extracts features,
/// and diagnoses them against the lattice.
pub fn diagnose(
    inputs: &[ImageInput],
    lattice: &LatticeSpec,
    options: &Options,
    ex: &ExtractOptions,
) -> Result<Diagnosis, ModelCheckError> {
    let mut files = Vec::with_capacity(inputs.len());
    for input in inputs {
        files.push((spm_formats::read_any(&input.path)?, input.start_time_s));
    }
    let (set, pixels) = extract_features_and_pixels(&files, lattice, ex)?;
    if set.features.is_empty() {
        // Say why in the user's terms: a lattice sampled too coarsely to
        // localise features, or no feature of that period at all.
        let finest_px = set
            .frames
            .iter()
            .filter_map(|f| f.pixel_nm)
            .map(|p| lattice.a_nm() / p[0].max(p[1]))
            .fold(f64::NAN, f64::max);
        return Err(ModelCheckError::NotTheLattice {
            context: format!("{} frame(s)", set.frames.len()),
            reason: if finest_px.is_finite() {
                format!(
                    "no features found; the claimed lattice constant spans {finest_px:.1} px \
                     (atoms need about 4 px or more to be localised)"
                )
            } else {
                "no features found".to_owned()
            },
        });
    }
    tracing::info!(
        features = set.features.len(),
        frames = set.frames.len(),
        "features extracted"
    );
    diagnose_features_with_pixels(&set, lattice, options, &pixels)
}

/// The pixels of a height map in scanner geometry (as [`features_from_height_map`] reads
/// it) for the pixel-level vibration search: its lines levelled (jointly with the claimed
/// lattice's harmonics found in its spectrum); `None` when the lattice is not found in
/// the map. Heights are in the map's unit (the search is scale-free).
pub fn pixel_image_from_height_map(
    map: &HeightMap,
    ctx: &MapContext,
    lattice: &LatticeSpec,
    time_and_line: &dyn Fn(f64, f64) -> (f64, usize),
) -> Option<PixelImage> {
    let (nx, ny) = (map.columns, map.rows);
    let bad: Vec<bool> = map.z_counts.iter().map(|v| !v.is_finite()).collect();
    let raw: Vec<f64> = map
        .z_counts
        .iter()
        .map(|v| if v.is_finite() { *v } else { 0.0 })
        .collect();
    let search = lattice_search(lattice, ctx.pixel_nm);
    let (z, found) = level_with_lattice(raw, &bad, (nx, ny), Some(&search));
    if !found {
        return None;
    }
    PixelImage::new(
        (ctx.frame_index, ctx.direction),
        (&z, &bad, nx, ny),
        ctx.pixel_nm,
        time_and_line,
    )
}

/// Convenience: [`diagnose`] for plain paths with default extraction.
pub fn diagnose_paths(
    paths: &[impl AsRef<Path>],
    lattice: &LatticeSpec,
    options: &Options,
) -> Result<Diagnosis, ModelCheckError> {
    let inputs: Vec<ImageInput> = paths
        .iter()
        .map(|p| ImageInput {
            path: p.as_ref().to_path_buf(),
            start_time_s: None,
        })
        .collect();
    diagnose(&inputs, lattice, options, &ExtractOptions::default())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex_peaks(k: f64) -> Peaks {
        let k1 = [k, 0.0];
        let k2 = [0.5 * k, 0.75f64.sqrt() * k];
        Peaks {
            k: [k1, k2],
            contrast: [100.0, 100.0],
            harmonics: vec![([1, 0], k1, 100.0), ([0, 1], k2, 100.0)],
        }
    }

    #[test]
    fn a_cell_is_resolved_when_its_second_shell_is_below_nyquist() {
        // Second shell of a triangular reciprocal lattice: √3·|k| (here along y).
        for (k, resolved) in [(0.2, true), (0.28, true), (0.3, false), (0.4, false)] {
            let r = unresolved(&hex_peaks(k));
            assert_eq!(r.is_none(), resolved, "|k| = {k}: {r:?}");
        }
    }

    #[test]
    fn a_file_without_size_is_calibrated_from_its_lattice() {
        // Corner-hole-like pits on a triangular lattice of 12 px (rotated 7°), with a
        // second, weaker feature per cell: pixel pitch = a / 12 px.
        let (n, a_px) = (128usize, 12.0);
        let (c, s) = (7f64.to_radians().cos(), 7f64.to_radians().sin());
        let b1 = [a_px * c, a_px * s];
        let b2 = [
            a_px * (0.5 * c - 0.75f64.sqrt() * s),
            a_px * (0.5 * s + 0.75f64.sqrt() * c),
        ];
        let det = b1[0] * b2[1] - b2[0] * b1[1];
        let mut data = Vec::with_capacity(n * n);
        for r in 0..n {
            for col in 0..n {
                let (x, y) = (col as f64, r as f64);
                let u = (b2[1] * x - b2[0] * y) / det;
                let v = (-b1[1] * x + b1[0] * y) / det;
                let mut h = 0.0;
                for (fu, fv, amp) in [(0.0, 0.0, -1.0), (1.0 / 3.0, 1.0 / 3.0, 0.5)] {
                    let du = (u - fu) - (u - fu).round();
                    let dv = (v - fv) - (v - fv).round();
                    let p = [du * b1[0] + dv * b2[0], du * b1[1] + dv * b2[1]];
                    h += amp * (-(p[0] * p[0] + p[1] * p[1]) / 4.0).exp();
                }
                data.push(1e-11 * h);
            }
        }
        let channel = Channel::new("Z", Direction::Forward, "m", n, n, data).expect("channel");
        assert!(channel.size_x_nm().is_none());
        let lattice = LatticeSpec::parse("si7x7").expect("lattice");
        let (pixel, _) = self_calibrate(&channel, &lattice).expect("calibrated");
        let truth = SI7X7_A_NM / a_px;
        assert!((pixel / truth - 1.0).abs() < 0.01, "{pixel} vs {truth}");
    }
}
