//! The correction methods of the benchmark and their figures: every method corrects every
//! image; position error against the true tip positions, lattice error on the corrected
//! counter-scanned pair; summaries per method.

use super::ImageBenchmarkError;
use super::lattice::{atoms, measure_lattice};
use super::take::{ImageSetConfig, ImageSize, TestImage};
use super::user_file::{user_file_map, user_file_pair_maps};
use crate::cubic::CubicMap;
use crate::rigid::rigid_residuals;
use serde::Serialize;
use spm_correction::dynamics::correct_effective_raster;
use spm_correction::{
    CoordinateMap, CorrectionError, CorrectionField, Integration, Parallelism, RasterGeometry,
    YCoordinates, correct_raster,
};
use spm_features::Feature;
use spm_hal::ScanDirection;
use std::collections::BTreeMap;

/// How a method turns an image into corrected coordinates.
pub enum ImageCorrection<'a> {
    /// A correction field integrated along the raster (eq. 9).
    Field(Box<dyn CorrectionField + 'a>),
    /// One polynomial map for every image (a grating calibration).
    Map(CubicMap),
    /// The bound: a cubic fitted to each image's own true positions (exact, per image).
    PerImageBound,
    /// What a user gets from `spmcal correct`: each image written as a file with what a
    /// controller records (its raster in counts, direction, scanner), read back, checked by the
    /// guard rails and mapped by `spm_apply` with the calibration file.
    UserFile(Box<spm_correction::SurfaceSet>),
    /// [`ImageCorrection::UserFile`] with the approach creep and drift measured against the
    /// lattice in each image (`spmcal correct --ruler`; images whose lattice is not resolved
    /// keep the file-alone map).
    UserFileRuler {
        /// The calibration file (with its dynamics).
        set: Box<spm_correction::SurfaceSet>,
        /// The lattice measured against.
        ruler: spm_apply::ruler::LatticeRuler,
    },
    /// [`ImageCorrection::UserFile`] with the approach creep and drift measured between the two
    /// frames of each counter-scanned pair (`spmcal correct --counter FILE`,
    /// [`spm_apply::counter`]; a pair whose features do not match keeps the file-alone maps).
    UserFileCounter {
        /// The calibration file (with its dynamics).
        set: Box<spm_correction::SurfaceSet>,
        /// The feature scale the frames are matched at.
        spacing: spm_apply::ruler::LatticeRuler,
    },
    /// [`ImageCorrection::UserFile`] with the command log recorded while the run and the
    /// images were taken (what `spmcal scan` keeps): the creep of the approach move is
    /// corrected too.
    UserFileRecorded {
        /// The calibration file (with its dynamics).
        set: Box<spm_correction::SurfaceSet>,
        /// The recorded commands: the run's and the images'.
        history: spm_correction::dynamics::CommandHistory,
    },
    /// A competitor fitted on each image's own trace and retrace (no calibration); an image
    /// it refuses keeps the nominal map (commanded counts × nominal sensitivity), as its user
    /// would.
    PerImageCompetitor {
        /// Which.
        method: Competitor,
        /// The standard and the nominal sensitivity.
        config: crate::competitors::CompetitorConfig,
    },
    /// A correction field integrated along each image's *effective* trajectory
    /// (`spm_correction::dynamics`): `offsets[image]` = uₑ − u per pixel in acquisition order,
    /// the field evaluated at uₑ / `gain`.
    EffectivePath {
        /// The LCC field.
        field: Box<dyn CorrectionField + 'a>,
        /// Per image (index in the set), per pixel: uₑ − u, counts.
        offsets: Vec<Vec<[f64; 2]>>,
        /// Large-signal gain per axis of the dynamics model.
        gain: [f64; 2],
    },
}

/// A per-image trace/retrace competitor ([`crate::competitors`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Competitor {
    /// The DHCT after Yothers, Browder & Bumm (2017).
    Yothers,
    /// The sinusoid-plus-linear map after Zhang et al. (2019).
    Zhang,
}

/// One correction method of the benchmark.
pub struct ImageMethod<'a> {
    /// Its name (report.json key).
    pub name: String,
    /// How it corrects.
    pub correction: ImageCorrection<'a>,
}

/// Figures of one image under one method.

#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ImageFigures {
    /// RMS position error after the best rigid motion, pm.
    pub position_rms_pm: f64,
    /// Max position error, pm.
    pub position_max_pm: f64,
    /// RMS position error, % of the image side.
    pub position_rms_pct_of_side: f64,
    /// RMS error against the sample points (tip plus drift), after the best rigid motion, %
    /// of the image side (see [`ImageMethodSummary::sample_position_rms_pct_of_side`]).
    pub sample_position_rms_pct_of_side: f64,
    /// Lattice-constant error on the corrected pair, % (None where not resolved or not found).
    pub lattice_error_pct: Option<f64>,
    /// Largest deviation of the lattice angles from 60°, degrees.
    pub lattice_angle_error_deg: Option<f64>,
}

/// A method's summary over the set (report.json `images.methods.<name>`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ImageMethodSummary {
    /// Mean |lattice error| over the pairs that resolve the lattice, %.
    pub mean_lattice_error_pct: f64,
    /// Max |lattice error|, %.
    pub max_lattice_error_pct: f64,
    /// Max lattice-angle error, degrees.
    pub max_lattice_angle_error_deg: f64,
    /// Pairs whose lattice was measured.
    pub lattice_pairs: usize,
    /// Pairs where the pipeline failed (counted as missing, not as zero).
    pub lattice_failures: usize,
    /// Root of the mean over images of the per-image mean-square position error, pm.
    pub position_rms_pm: f64,
    /// Largest position error in any image, pm.
    pub position_max_pm: f64,
    /// Mean over images of the per-image RMS position error, % of the image side.
    pub position_rms_pct_of_side: f64,
    /// Position RMS per image size (key: side in counts), pm.
    pub position_rms_pm_by_size: BTreeMap<String, f64>,
    /// Mean over images of the per-image RMS error against the sample points (the tip position
    /// plus the sample's drift: where on the sample each pixel was), % of the image side. A
    /// method that removes the drift is judged by this; `position_rms_pct_of_side` counts
    /// the drift it removed as an error.
    pub sample_position_rms_pct_of_side: f64,
    /// Images a per-image competitor refused (no retrace, lattice not resolved, too few atoms
    /// indexed or matched), which keep the nominal map in its figures; only for competitors.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub refused_images: Option<usize>,
}

/// The benchmark's result (report.json `images`).
#[derive(Debug, Clone, Serialize)]
pub struct ImageBenchmark {
    /// Images taken (direct and counter counted separately).
    pub count: usize,
    /// Counter-scanned pairs.
    pub pairs: usize,
    /// Sizes, dwells and places.
    pub sizes: Vec<ImageSize>,
    /// Pixel dwells, s.
    pub dwells_s: Vec<f64>,
    /// Per method.
    pub methods: BTreeMap<String, ImageMethodSummary>,
    /// The scanner-dynamics model the `*_creep_model` methods used, as identified from the
    /// run (None when it could not be identified).
    pub dynamics: Option<DynamicsSummary>,
    /// Per image: place, size, dwell, direction and every method's figures.
    pub images: Vec<ImageRow>,
}

/// The identified creep law (spm_correction::dynamics::fit_creep_law) in report.json.
#[derive(Debug, Clone, Serialize)]
pub struct DynamicsSummary {
    /// Weight w of every relaxation element.
    pub creep_weight: f64,
    /// Its standard error.
    pub creep_weight_sigma: f64,
    /// Time constants of the law's shape: shortest and longest, s, and per decade.
    pub time_constants_s: [f64; 2],
    /// Elements per decade.
    pub elements_per_decade: u32,
    /// Settled creep gain W = n·w.
    pub settled_gain: f64,
    /// Log slope γ of the law between 0.1 s and 10 s.
    pub gamma_per_decade: f64,
    /// Attachment tracks and sightings used.
    pub tracks: usize,
    /// Sightings used.
    pub sightings: usize,
    /// RMS residual of the tracks after the fit, counts.
    pub residual_rms_counts: f64,
    /// RMS of the fitted creep motion within the tracks, counts.
    pub signal_rms_counts: f64,
    /// Why it is missing, when it is.
    pub note: Option<String>,
}

/// One image's row.
#[derive(Debug, Clone, Serialize)]
pub struct ImageRow {
    /// Pair index.
    pub pair: usize,
    /// Place label.
    pub place: String,
    /// Side, counts.
    pub side_counts: f64,
    /// Pixel dwell, s.
    pub dwell_s: f64,
    /// "direct" or "counter".
    pub direction: String,
    /// Figures per method.
    pub figures: BTreeMap<String, ImageFigures>,
}

fn geometry_of(image: &TestImage) -> Result<RasterGeometry, CorrectionError> {
    RasterGeometry::of_height_map(&image.map)
}

/// Commanded counts of every pixel (geometry order).
fn commanded(image: &TestImage) -> Vec<[f64; 2]> {
    let m = &image.map;
    let (x0, y0, s) = (m.origin.x.value(), m.origin.y.value(), m.pixel_step.value());
    let mut out = Vec::with_capacity(m.columns * m.rows);
    for row in 0..m.rows {
        for column in 0..m.columns {
            out.push([x0 + s * column as f64, y0 + s * row as f64]);
        }
    }
    out
}

fn flatten(map: &CoordinateMap) -> Result<Vec<[f64; 2]>, CorrectionError> {
    let mut out = Vec::with_capacity(map.columns() * map.rows());
    for row in 0..map.rows() {
        for column in 0..map.columns() {
            let p = map.point(column, row).ok_or(CorrectionError::Empty(
                "coordinate map smaller than its image",
            ))?;
            out.push([p.x.value(), p.y.value()]);
        }
    }
    Ok(out)
}

fn map_from_points(
    points: &[[f64; 2]],
    columns: usize,
    rows: usize,
) -> Result<CoordinateMap, CorrectionError> {
    CoordinateMap::new(
        columns,
        rows,
        points.iter().map(|p| p[0]).collect(),
        YCoordinates::PerPixel(points.iter().map(|p| p[1]).collect()),
    )
}

/// The method's corrected coordinates of every pixel of image `index`, in scanner geometry.
fn coordinate_map(
    method: &ImageMethod<'_>,
    image: &TestImage,
    index: usize,
) -> Result<CoordinateMap, ImageBenchmarkError> {
    Ok(coordinate_map_or_refusal(method, image, index)?.0)
}

/// [`coordinate_map`], and whether a per-image competitor refused the image (the map is then
/// the nominal one).
fn coordinate_map_or_refusal(
    method: &ImageMethod<'_>,
    image: &TestImage,
    index: usize,
) -> Result<(CoordinateMap, bool), ImageBenchmarkError> {
    let (nx, ny) = (image.map.columns, image.map.rows);
    if let ImageCorrection::PerImageCompetitor { method, config } = &method.correction {
        return competitor_map(*method, config, image);
    }
    Ok((
        match &method.correction {
            ImageCorrection::Field(field) => correct_raster(
                field.as_ref(),
                &geometry_of(image)?,
                image.direction,
                &Integration::default(),
                Parallelism::Sequential,
            )?,
            ImageCorrection::Map(map) => {
                let points: Vec<[f64; 2]> = commanded(image)
                    .iter()
                    .map(|u| map.eval(u[0], u[1]))
                    .collect();
                map_from_points(&points, nx, ny)?
            }
            ImageCorrection::PerImageBound => {
                let u = commanded(image);
                let fit = CubicMap::fit(&u, &image.truth_nm).map_err(|e| {
                    ImageBenchmarkError::Grating(format!("per-image bound: polynomial fit: {e}"))
                })?;
                let points: Vec<[f64; 2]> = u.iter().map(|p| fit.eval(p[0], p[1])).collect();
                map_from_points(&points, nx, ny)?
            }
            ImageCorrection::UserFile(set) => user_file_map(set, image, None, None)?,
            ImageCorrection::UserFileRuler { set, ruler } => {
                user_file_map(set, image, None, Some(ruler))?
            }
            ImageCorrection::UserFileCounter { set, .. } => user_file_map(set, image, None, None)?,
            ImageCorrection::UserFileRecorded { set, history } => {
                user_file_map(set, image, Some(history), None)?
            }
            ImageCorrection::PerImageCompetitor { method, config } => {
                competitor_map(*method, config, image)?.0
            }
            ImageCorrection::EffectivePath {
                field,
                offsets,
                gain,
            } => {
                let offsets = offsets.get(index).ok_or_else(|| {
                    ImageBenchmarkError::Config(format!(
                        "no effective-input offsets for image {index}"
                    ))
                })?;
                let n = image.commanded_acquisition.len().max(1) as f64;
                let centre = image
                    .commanded_acquisition
                    .iter()
                    .fold([0.0, 0.0], |s, u| [s[0] + u[0] / n, s[1] + u[1] / n]);
                let acquisition = correct_effective_raster(
                    field.as_ref(),
                    nx,
                    ny,
                    &image.commanded_acquisition,
                    offsets,
                    *gain,
                    centre,
                )?;
                spm_correction::dynamics::to_geometry_map(&acquisition, nx, ny, image.direction)?
            }
        },
        false,
    ))
}
/// A competitor's map of one image, or the nominal map where it refuses the image (`true`).
fn competitor_map(
    method: Competitor,
    config: &crate::competitors::CompetitorConfig,
    image: &TestImage,
) -> Result<(CoordinateMap, bool), ImageBenchmarkError> {
    use crate::competitors::{CompetitorError, nominal_map, yothers, zhang};
    let found = match method {
        Competitor::Yothers => {
            yothers::correct_image(&image.map, image.backward.as_ref(), config).map(|f| f.1)
        }
        Competitor::Zhang => {
            zhang::correct_image(&image.map, image.backward.as_ref(), config).map(|f| f.1)
        }
    };
    match found {
        Ok(map) => Ok((map, false)),
        Err(CompetitorError::Refused { .. }) => {
            Ok((nominal_map(&image.map, config.nominal_nm_per_count)?, true))
        }
        Err(CompetitorError::Correction(e)) => Err(e.into()),
    }
}

fn position_figures(
    corrected: &[[f64; 2]],
    truth_nm: &[[f64; 2]],
    image: &TestImage,
    nominal: f64,
) -> (f64, f64, f64) {
    let r = rigid_residuals(corrected, truth_nm);
    if r.is_empty() {
        // No truth recorded: no figure, not a zero.
        return (f64::NAN, f64::NAN, f64::NAN);
    }
    let n = r.len() as f64;
    let ms = r.iter().map(|v| v * v).sum::<f64>() / n;
    let max = r.iter().copied().fold(0.0_f64, f64::max);
    let side_nm = image.size.side_counts() * nominal;
    (ms.sqrt() * 1e3, max * 1e3, 100.0 * ms.sqrt() / side_nm)
}

/// The lattice of one counter-scanned pair, corrected by a method.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PairLattice {
    /// Not the direct image of a pair that resolves the lattice.
    NotApplicable,
    /// The measurement failed (too few atoms matched, a drift that does not explain them).
    Failed,
    /// Measured on the corrected direct image.
    Measured {
        /// Mean length of the three lattice vectors, nm.
        a_nm: f64,
        /// Largest deviation of the angles between them from 60°, degrees.
        angle_deg: f64,
    },
}

/// The lattice of the pair whose direct image is `images[k]` (`map`: its corrected
/// coordinates by `method`), measured once per pair on its direct image; the raw images'
/// atoms are detected once per pair (`raw_atoms`, keyed by `k`), whatever the method.
fn pair_lattice(
    method: &ImageMethod<'_>,
    images: &[TestImage],
    k: usize,
    map: &CoordinateMap,
    config: &ImageSetConfig,
    raw_atoms: &mut BTreeMap<usize, (Vec<Feature>, Vec<Feature>)>,
) -> Result<PairLattice, ImageBenchmarkError> {
    let Some(counter) = lattice_partner(images, k, config) else {
        return Ok(PairLattice::NotApplicable);
    };
    let counter_map = coordinate_map(method, counter, k + 1)?;
    let raw = raw_atoms
        .entry(k)
        .or_insert_with(|| raw_pair_atoms(&images[k], counter, config));
    Ok(lattice_of_maps(
        &images[k],
        counter,
        map,
        &counter_map,
        raw,
        config,
    ))
}

/// The counter image of the pair whose direct image is `images[k]`, when that pair resolves
/// the lattice (at least [`ImageSetConfig::min_pixels_per_lattice_constant`]).
fn lattice_partner<'i>(
    images: &'i [TestImage],
    k: usize,
    config: &ImageSetConfig,
) -> Option<&'i TestImage> {
    let image = images.get(k)?;
    let counter = images
        .get(k + 1)
        .filter(|c| c.pair == image.pair && c.direction == ScanDirection::Counter)?;
    (image.direction == ScanDirection::Direct
        && period_px(image, config) >= config.min_pixels_per_lattice_constant)
        .then_some(counter)
}

/// The lattice constant in pixels of `image`.
fn period_px(image: &TestImage, config: &ImageSetConfig) -> f64 {
    config.lattice_constant_nm / config.nominal_nm_per_count / image.size.step_counts.max(1e-9)
}

/// The atoms of a pair's raw images (they do not depend on the method).
fn raw_pair_atoms(
    direct: &TestImage,
    counter: &TestImage,
    config: &ImageSetConfig,
) -> (Vec<Feature>, Vec<Feature>) {
    let period = period_px(direct, config);
    (atoms(&direct.map, period), atoms(&counter.map, period))
}

/// The lattice measured on a pair corrected into `map` (direct) and `counter_map`.
fn lattice_of_maps(
    direct: &TestImage,
    counter: &TestImage,
    map: &CoordinateMap,
    counter_map: &CoordinateMap,
    raw: &(Vec<Feature>, Vec<Feature>),
    config: &ImageSetConfig,
) -> PairLattice {
    match measure_lattice(
        map,
        counter_map,
        &direct.map,
        &counter.map,
        (&raw.0, &raw.1),
        config.lattice_constant_nm,
    ) {
        Some((a_nm, angle_deg)) => PairLattice::Measured { a_nm, angle_deg },
        None => PairLattice::Failed,
    }
}

/// The maps of a method that corrects the two images of a counter-scanned pair together
/// ([`ImageCorrection::UserFileCounter`]), direct image first; `None` for a method that maps
/// each image alone.
fn pair_method_maps(
    method: &ImageMethod<'_>,
    direct: &TestImage,
    counter: &TestImage,
) -> Result<Option<(CoordinateMap, CoordinateMap)>, ImageBenchmarkError> {
    match &method.correction {
        ImageCorrection::UserFileCounter { set, spacing } => {
            user_file_pair_maps(set, direct, counter, spacing).map(Some)
        }
        _ => Ok(None),
    }
}

/// The lattice of every counter-scanned pair of `images` corrected by `method`, with no
/// ground truth (the run's validation): `(pair, place, lattice)` per pair.
///
/// # Errors
/// As the correction of an image.
pub fn lattice_of_pairs(
    images: &[TestImage],
    method: &ImageMethod<'_>,
    config: &ImageSetConfig,
) -> Result<Vec<(usize, String, PairLattice)>, ImageBenchmarkError> {
    let mut raw_atoms = BTreeMap::new();
    let mut out = Vec::new();
    for (k, image) in images.iter().enumerate() {
        if image.direction != ScanDirection::Direct {
            continue;
        }
        // A pair method maps both images together.
        if let Some(counter) = lattice_partner(images, k, config)
            && let Some((map, counter_map)) = pair_method_maps(method, image, counter)?
        {
            let raw = raw_atoms
                .entry(k)
                .or_insert_with(|| raw_pair_atoms(image, counter, config));
            let lattice = lattice_of_maps(image, counter, &map, &counter_map, raw, config);
            out.push((image.pair, image.place.clone(), lattice));
            continue;
        }
        let map = coordinate_map(method, image, k)?;
        let lattice = pair_lattice(method, images, k, &map, config, &mut raw_atoms)?;
        out.push((image.pair, image.place.clone(), lattice));
    }
    Ok(out)
}

/// What one method gives on one image: whether a competitor refused it, its figures, and
/// (the direct image of a pair) the pair's lattice.
struct ImageOutcome {
    refused: bool,
    rms_pm: f64,
    max_pm: f64,
    pct: f64,
    sample_pct: f64,
    lattice: PairLattice,
}

/// Every method on the images `group` (consecutive indices of one pair): each image's map is
/// made once per method and serves both its own figures and its pair's lattice; the raw
/// atoms once per pair. `result[method][image in group]`.
fn evaluate_group(
    images: &[TestImage],
    group: std::ops::Range<usize>,
    methods: &[ImageMethod<'_>],
    config: &ImageSetConfig,
) -> Result<Vec<Vec<ImageOutcome>>, ImageBenchmarkError> {
    let nominal = config.nominal_nm_per_count;
    let mut raw: Option<(Vec<Feature>, Vec<Feature>)> = None;
    let mut out = Vec::with_capacity(methods.len());
    for method in methods {
        let pair = match group.len() {
            2 => pair_method_maps(method, &images[group.start], &images[group.start + 1])?,
            _ => None,
        };
        let maps = match pair {
            Some((a, b)) => vec![(a, false), (b, false)],
            None => group
                .clone()
                .map(|k| coordinate_map_or_refusal(method, &images[k], k))
                .collect::<Result<Vec<_>, _>>()?,
        };
        let mut outcomes = Vec::with_capacity(maps.len());
        for (g, k) in group.clone().enumerate() {
            let image = &images[k];
            let (map, refused) = &maps[g];
            let corrected = flatten(map)?;
            let (rms_pm, max_pm, pct) =
                position_figures(&corrected, &image.truth_nm, image, nominal);
            let (_, _, sample_pct) =
                position_figures(&corrected, &image.sample_truth_nm, image, nominal);
            let lattice = match (lattice_partner(images, k, config), maps.get(g + 1)) {
                (Some(counter), Some((counter_map, _))) => {
                    let raw = raw.get_or_insert_with(|| raw_pair_atoms(image, counter, config));
                    lattice_of_maps(image, counter, map, counter_map, raw, config)
                }
                _ => PairLattice::NotApplicable,
            };
            outcomes.push(ImageOutcome {
                refused: *refused,
                rms_pm,
                max_pm,
                pct,
                sample_pct,
                lattice,
            });
        }
        out.push(outcomes);
    }
    Ok(out)
}

/// Corrects every image with every method and summarises. The pairs are independent and
/// are evaluated in parallel (rayon); the figures are gathered in image order, so the result
/// does not depend on the number of threads.
///
/// # Errors
/// As the correction of an image.
pub fn evaluate_images(
    images: &[TestImage],
    methods: &[ImageMethod<'_>],
    config: &ImageSetConfig,
) -> Result<ImageBenchmark, ImageBenchmarkError> {
    use rayon::prelude::*;
    let mut rows: Vec<ImageRow> = images
        .iter()
        .map(|image| ImageRow {
            pair: image.pair,
            place: image.place.clone(),
            side_counts: image.size.side_counts(),
            dwell_s: image.dwell_s,
            direction: match image.direction {
                ScanDirection::Direct => "direct".to_owned(),
                ScanDirection::Counter => "counter".to_owned(),
            },
            figures: BTreeMap::new(),
        })
        .collect();
    // Consecutive images of one pair form a group.
    let mut groups: Vec<std::ops::Range<usize>> = Vec::new();
    for (k, image) in images.iter().enumerate() {
        match groups.last_mut() {
            Some(g) if images[g.start].pair == image.pair => g.end = k + 1,
            _ => groups.push(k..k + 1),
        }
    }
    let evaluated = groups
        .par_iter()
        .map(|g| evaluate_group(images, g.clone(), methods, config))
        .collect::<Result<Vec<_>, _>>()?;
    let mut summaries = BTreeMap::new();
    for (m, method) in methods.iter().enumerate() {
        let mut ms_sum = 0.0;
        let mut max_pm: f64 = 0.0;
        let mut pct_sum = 0.0;
        let mut sample_pct_sum = 0.0;
        let mut by_size: BTreeMap<String, (f64, usize)> = BTreeMap::new();
        let mut lattice: Vec<f64> = Vec::new();
        let mut angle_max: f64 = 0.0;
        let mut failures = 0;
        let mut refused = 0;
        for (group, outcomes) in groups.iter().zip(&evaluated) {
            for (k, o) in group.clone().zip(&outcomes[m]) {
                let image = &images[k];
                refused += usize::from(o.refused);
                let rms = o.rms_pm;
                sample_pct_sum += o.sample_pct;
                ms_sum += rms * rms;
                max_pm = max_pm.max(o.max_pm);
                pct_sum += o.pct;
                let key = format!("{}", image.size.side_counts());
                let e = by_size.entry(key).or_insert((0.0, 0));
                e.0 += rms * rms;
                e.1 += 1;
                let mut figures = ImageFigures {
                    position_rms_pm: rms,
                    position_max_pm: o.max_pm,
                    position_rms_pct_of_side: o.pct,
                    sample_position_rms_pct_of_side: o.sample_pct,
                    lattice_error_pct: None,
                    lattice_angle_error_deg: None,
                };
                // The lattice figure once per pair, on its direct image.
                match o.lattice {
                    PairLattice::Measured { a_nm, angle_deg } => {
                        let e = 100.0 * (a_nm / config.lattice_constant_nm - 1.0);
                        lattice.push(e.abs());
                        angle_max = angle_max.max(angle_deg);
                        figures.lattice_error_pct = Some(e);
                        figures.lattice_angle_error_deg = Some(angle_deg);
                    }
                    PairLattice::Failed => failures += 1,
                    PairLattice::NotApplicable => {}
                }
                rows[k].figures.insert(method.name.clone(), figures);
            }
        }
        let n = images.len().max(1) as f64;
        let nl = lattice.len().max(1) as f64;
        summaries.insert(
            method.name.clone(),
            ImageMethodSummary {
                mean_lattice_error_pct: lattice.iter().sum::<f64>() / nl,
                max_lattice_error_pct: lattice.iter().copied().fold(0.0, f64::max),
                max_lattice_angle_error_deg: angle_max,
                lattice_pairs: lattice.len(),
                lattice_failures: failures,
                position_rms_pm: (ms_sum / n).sqrt(),
                position_max_pm: max_pm,
                position_rms_pct_of_side: pct_sum / n,
                position_rms_pm_by_size: by_size
                    .into_iter()
                    .map(|(k, (s, c))| (k, (s / c.max(1) as f64).sqrt()))
                    .collect(),
                sample_position_rms_pct_of_side: sample_pct_sum / n,
                refused_images: matches!(
                    method.correction,
                    ImageCorrection::PerImageCompetitor { .. }
                )
                .then_some(refused),
            },
        );
    }
    Ok(ImageBenchmark {
        count: images.len(),
        pairs: images.last().map_or(0, |i| i.pair + 1),
        sizes: config.sizes.clone(),
        dwells_s: config.dwells_s.clone(),
        methods: summaries,
        dynamics: None,
        images: rows,
    })
}

impl ImageBenchmark {
    /// The table the calibrate summary prints: one line per method.
    pub fn summary_table(&self) -> String {
        let mut out = format!(
            "test images ({} images, {} counter-scanned pairs; position: true tip positions, drift excluded; lattice: corrected pairs, over the pairs measured)\n{:<33} {:>15} {:>15} {:>10} {:>14} {:>13} {:>14}\n",
            self.count,
            self.pairs,
            "method",
            "position RMS pm",
            "position max pm",
            "RMS % side",
            "mean lattice %",
            "max lattice %",
            "pairs measured"
        );
        for (name, m) in &self.methods {
            let (mean, max) = if m.lattice_pairs == 0 {
                ("—".to_owned(), "—".to_owned())
            } else {
                (
                    format!("{:.4}", m.mean_lattice_error_pct),
                    format!("{:.4}", m.max_lattice_error_pct),
                )
            };
            out.push_str(&format!(
                "{:<33} {:>15.1} {:>15.1} {:>10.3} {:>14} {:>13} {:>8}/{:<5}\n",
                name,
                m.position_rms_pm,
                m.position_max_pm,
                m.position_rms_pct_of_side,
                mean,
                max,
                m.lattice_pairs,
                m.lattice_pairs + m.lattice_failures
            ));
        }
        out
    }
}
