//! The image benchmark: the accuracy a user sees (issue 12, DESIGN §11 "first").
//!
//! After a calibration the same simulated instrument — every effect on, the same
//! seed stream going on — takes test images the way a user does: a move to the
//! image's place from wherever the previous image ended, the pause the plan's
//! pause law gives for that move (the wait a careful user makes for the creep), then
//! a direct raster and at once its counter raster (Lapshin 2007). Every method
//! corrects every image, and two figures are taken per image:
//!
//! - **position error**: the corrected coordinate of every pixel against the true
//!   tip position that pixel had in the simulator (scanner frame; hysteresis and
//!   creep as they acted during that image; drift and jitter excluded), after
//!   removing the best rigid motion. RMS and max, pm and % of the image side.
//! - **lattice error** (images that resolve the lattice): the counter-scanned pair
//!   is corrected with the method (drift from the atoms common to both images,
//!   `correct_counter_pair`), the direct image is resampled onto a uniform nm grid,
//!   spm-features detects the atoms and measures the three lattice vectors; their
//!   mean length against the standard's lattice constant, and the largest
//!   deviation of the angles between them from 60°.
//!
//! The methods are correction fields integrated along the image's raster (eq. 9),
//! or direct maps (polynomials evaluated at each pixel's commanded counts).

use crate::accuracy::{CUBIC_TERMS, cubic_basis, least_squares, rigid_residuals};
use serde::Serialize;
use spm_calibration::PauseLaw;
use spm_correction::dynamics::correct_effective_raster;
use spm_correction::{
    CoordinateMap, FeatureSighting, SightingPair, YCoordinates, drift_corrected_map, estimate_drift,
};
use spm_correction::{
    CorrectionError, CorrectionField, FeatureMatch, FormCoefficients, Integration, Interpolation,
    OutputGrid, Parallelism, RasterGeometry, correct_raster, resample,
};
use spm_features::{DetectionConfig, Feature, LatticeConfig, detect, lattice_vectors};
use spm_hal::recording::CommandRecorder;
use spm_hal::truth::{GratingSample, SimulatedInstrument};
use spm_hal::{
    CountPoint, Counts, HeightMap, Microscope, MoveRequest, NmPoint, ScanDirection, ScanRequest,
    Seconds, TraceHalf,
};
use std::collections::BTreeMap;

/// Why the image benchmark failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ImageBenchmarkError {
    /// The simulated instrument failed repeatedly on one image.
    #[error("test image {index} ({what}): the instrument failed {attempts} times, last: {message}")]
    Instrument {
        /// Index of the image in the set.
        index: usize,
        /// What was being done.
        what: &'static str,
        /// Attempts made.
        attempts: usize,
        /// The last error.
        message: String,
    },
    /// A correction step failed.
    #[error("test image correction: {0}")]
    Correction(#[from] CorrectionError),
    /// The configuration cannot produce an image set.
    #[error("image benchmark configuration: {0}")]
    Config(String),
    /// The grating calibration image could not be indexed or fitted.
    #[error("grating polynomial: {0}")]
    Grating(String),
}

/// One image size of the set.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ImageSize {
    /// Pixels per line and lines (odd, so that a raster centred on a whole count has every
    /// pixel on a whole count).
    pub pixels: u32,
    /// Pixel step, whole counts.
    pub step_counts: f64,
}

impl ImageSize {
    /// Side of the image, counts.
    pub fn side_counts(&self) -> f64 {
        self.step_counts * f64::from(self.pixels - 1)
    }
}

/// Which images are taken.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageSetConfig {
    /// Places per side of the calibrated region (corners, edge midpoints, centre: 3).
    pub places_per_side: usize,
    /// Image sizes.
    pub sizes: Vec<ImageSize>,
    /// Pixel dwells (scan speeds), s.
    pub dwells_s: Vec<f64>,
    /// The pause after the move to each image.
    pub pause: PauseLaw,
    /// Speed of the move to each image, counts/s.
    pub move_speed_counts_per_s: f64,
    /// Settle time of that move, s.
    pub settle_s: f64,
    /// Lattice constant of the standard imaged, nm.
    pub lattice_constant_nm: f64,
    /// Nominal sensitivity, nm/count (pixel periods for detection).
    pub nominal_nm_per_count: f64,
    /// Lattice figures only on images with at least this many pixels per lattice constant.
    pub min_pixels_per_lattice_constant: f64,
}

impl ImageSetConfig {
    /// The standard set: 3 × 3 places; a small atomic image (129 px × 1 count, about two
    /// apertures), a medium atomic image (257 px × 2 counts) and a large image (129 px × 128
    /// counts, ≈ 30 % of a 16-bit field's calibrated region); the plan's dwell and 4× slower.
    /// `quick` keeps the two atomic sizes and one dwell.
    pub fn standard(plan: &spm_calibration::PlanConfig, quick: bool) -> Self {
        let dwell = plan.motion.pixel_dwell_s;
        let mut sizes = vec![
            ImageSize {
                pixels: 129,
                step_counts: 1.0,
            },
            ImageSize {
                pixels: 257,
                step_counts: 2.0,
            },
        ];
        if !quick {
            sizes.push(ImageSize {
                pixels: 129,
                step_counts: 128.0,
            });
        }
        Self {
            places_per_side: 3,
            sizes,
            dwells_s: if quick {
                vec![dwell]
            } else {
                vec![dwell, 4.0 * dwell]
            },
            pause: plan.pause,
            move_speed_counts_per_s: plan.motion.move_speed_counts_per_s,
            settle_s: plan.motion.settle_s,
            lattice_constant_nm: plan.standard.lattice_constant_nm,
            nominal_nm_per_count: plan.standard.nominal_nm_per_count,
            min_pixels_per_lattice_constant: 5.0,
        }
    }
}

/// The calibrated region, counts.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CountRegion {
    /// Smallest x.
    pub x_min_counts: f64,
    /// Largest x.
    pub x_max_counts: f64,
    /// Smallest y.
    pub y_min_counts: f64,
    /// Largest y.
    pub y_max_counts: f64,
}

/// One test image as taken.
#[derive(Debug, Clone)]
pub struct TestImage {
    /// Index of the counter-scanned pair it belongs to.
    pub pair: usize,
    /// Place label ("centre", "corner −x −y", …).
    pub place: String,
    /// Its size.
    pub size: ImageSize,
    /// Pixel dwell, s.
    pub dwell_s: f64,
    /// Direct or counter.
    pub direction: ScanDirection,
    /// The forward trace in scanner geometry (row with y, column with x).
    pub map: HeightMap,
    /// True tip position of every pixel, scanner frame, nm, in the same geometry.
    pub truth_nm: Vec<[f64; 2]>,
    /// Commanded counts of every pixel in acquisition order.
    pub commanded_acquisition: Vec<[f64; 2]>,
    /// Time of every pixel in acquisition order, s.
    pub time_acquisition_s: Vec<f64>,
    /// True effective input (u + h + c, counts) of every pixel in acquisition order (oracle:
    /// only the true-dynamics bound uses it).
    pub true_effective_acquisition: Vec<[f64; 2]>,
}

/// Places of the set: corners, edges and centre of the region, inset by half an image.
fn places(region: &CountRegion, n: usize, half: f64) -> Vec<(String, [f64; 2])> {
    let axis = |lo: f64, hi: f64| -> Vec<f64> {
        let (a, b) = (lo + half, hi - half);
        if n <= 1 || b <= a {
            return vec![(0.5 * (lo + hi)).round()];
        }
        (0..n)
            .map(|k| (a + (b - a) * k as f64 / (n - 1) as f64).round())
            .collect()
    };
    let xs = axis(region.x_min_counts, region.x_max_counts);
    let ys = axis(region.y_min_counts, region.y_max_counts);
    let label = |k: usize, len: usize, minus: &str, plus: &str| -> String {
        if len == 1 || (k * 2 + 1 == len) {
            String::new()
        } else if k == 0 {
            minus.to_owned()
        } else if k + 1 == len {
            plus.to_owned()
        } else {
            format!("{k}")
        }
    };
    let mut out = Vec::new();
    for (j, &y) in ys.iter().enumerate() {
        for (i, &x) in xs.iter().enumerate() {
            let lx = label(i, xs.len(), "−x", "+x");
            let ly = label(j, ys.len(), "−y", "+y");
            let name = match (lx.is_empty(), ly.is_empty()) {
                (true, true) => "centre".to_owned(),
                (false, true) => format!("edge {lx}"),
                (true, false) => format!("edge {ly}"),
                (false, false) => format!("corner {lx} {ly}"),
            };
            out.push((name, [x, y]));
        }
    }
    out
}

/// Geometry-ordered copy of a forward trace's per-pixel values (acquisition order in).
fn to_geometry<T: Copy>(values: &[T], nx: usize, ny: usize, direction: ScanDirection) -> Vec<T> {
    match direction {
        ScanDirection::Direct => values.to_vec(),
        ScanDirection::Counter => {
            let mut out = Vec::with_capacity(values.len());
            for row in 0..ny {
                for column in 0..nx {
                    let (line, pixel) = (ny - 1 - row, nx - 1 - column);
                    out.push(values[line * nx + pixel]);
                }
            }
            out
        }
    }
}

const ATTEMPTS: usize = 4;

/// Takes the image set on `sim` (truth recording is switched on for it and off after).
///
/// # Errors
/// [`ImageBenchmarkError::Instrument`] when an image fails [`ATTEMPTS`] times.
pub fn take_test_images<S: SimulatedInstrument>(
    instrument: &mut CommandRecorder<S>,
    region: &CountRegion,
    config: &ImageSetConfig,
) -> Result<Vec<TestImage>, ImageBenchmarkError> {
    if config.sizes.is_empty() || config.dwells_s.is_empty() || config.places_per_side == 0 {
        return Err(ImageBenchmarkError::Config(
            "no sizes, dwells or places".to_owned(),
        ));
    }
    instrument.inner_mut().record_tip_positions(true);
    let sim = &mut *instrument;
    let mut images = Vec::new();
    let mut pair = 0;
    let result = (|| {
        for size in &config.sizes {
            let half = 0.5 * size.side_counts();
            let spots = places(region, config.places_per_side, half);
            for &dwell in &config.dwells_s {
                for (name, centre) in &spots {
                    let from = sim
                        .position()
                        .map_err(|e| ImageBenchmarkError::Instrument {
                            index: images.len(),
                            what: "position",
                            attempts: 1,
                            message: e.to_string(),
                        })?;
                    let distance = (centre[0] - from.x.value()).hypot(centre[1] - from.y.value());
                    let centre_point = CountPoint::from_counts(centre[0], centre[1]);
                    retry(images.len(), "move", || {
                        sim.move_to(MoveRequest {
                            target: centre_point,
                            speed: spm_hal::CountsPerSecond(config.move_speed_counts_per_s),
                            settle: Seconds(config.settle_s),
                        })
                    })?;
                    let pause = config.pause.pause(Counts(distance), 0);
                    retry(images.len(), "pause", || sim.wait(pause))?;
                    let request = ScanRequest::centred_square(
                        centre_point,
                        Counts(size.step_counts),
                        size.pixels,
                        Seconds(dwell),
                    );
                    for direction in [ScanDirection::Direct, ScanDirection::Counter] {
                        let request = request.clone().with_direction(direction);
                        let frame = retry(images.len(), "scan", || sim.scan(&request))?;
                        let truth = sim.inner_mut().last_scan_tip_positions();
                        let effective: Vec<[f64; 2]> = sim
                            .inner_mut()
                            .last_scan_effective_inputs()
                            .iter()
                            .map(|p| [p.x.value(), p.y.value()])
                            .collect();
                        let map = frame
                            .height_map(TraceHalf::Forward)
                            .map_err(|e| ImageBenchmarkError::Config(format!("height map: {e}")))?;
                        let n = size.pixels as usize;
                        let truth: Vec<[f64; 2]> =
                            truth.iter().map(|p| [p.x.value(), p.y.value()]).collect();
                        if truth.len() != n * n {
                            return Err(ImageBenchmarkError::Config(format!(
                                "truth recording holds {} of {} pixels",
                                truth.len(),
                                n * n
                            )));
                        }
                        let mut commanded = Vec::with_capacity(n * n);
                        for line in 0..n {
                            for pixel in 0..n {
                                let u = request.commanded_position(TraceHalf::Forward, line, pixel);
                                commanded.push([u.x.value(), u.y.value()]);
                            }
                        }
                        images.push(TestImage {
                            pair,
                            place: name.clone(),
                            size: *size,
                            dwell_s: dwell,
                            direction,
                            map,
                            truth_nm: to_geometry(&truth, n, n, direction),
                            commanded_acquisition: commanded,
                            time_acquisition_s: frame.forward.time_s.clone(),
                            true_effective_acquisition: effective,
                        });
                    }
                    pair += 1;
                }
            }
        }
        Ok(())
    })();
    instrument.inner_mut().record_tip_positions(false);
    result.map(|()| images)
}

fn retry<T, E: std::fmt::Display>(
    index: usize,
    what: &'static str,
    mut f: impl FnMut() -> Result<T, E>,
) -> Result<T, ImageBenchmarkError> {
    let mut last = String::new();
    for _ in 0..ATTEMPTS {
        match f() {
            Ok(v) => return Ok(v),
            Err(e) => last = e.to_string(),
        }
    }
    Err(ImageBenchmarkError::Instrument {
        index,
        what,
        attempts: ATTEMPTS,
        message: last,
    })
}

/// A total-degree-3 polynomial map counts → nm (per coordinate), normalised coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CubicMap {
    centre: [f64; 2],
    half: f64,
    ax: [f64; 10],
    ay: [f64; 10],
}

impl CubicMap {
    /// The map of given coefficients (total-degree-3 monomials of [`CUBIC_TERMS`] in the
    /// normalised coordinates `(x − centre) / half`).
    pub(crate) fn from_coefficients(
        centre: [f64; 2],
        half: f64,
        ax: [f64; 10],
        ay: [f64; 10],
    ) -> Self {
        Self {
            centre,
            half,
            ax,
            ay,
        }
    }

    /// Least-squares fit of `points` (counts) to `targets` (nm); `None` when singular.
    pub fn fit(points: &[[f64; 2]], targets: &[[f64; 2]]) -> Option<Self> {
        let n = points.len().min(targets.len());
        if n < 10 {
            return None;
        }
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in &points[..n] {
            for k in 0..2 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        let centre = [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])];
        let half = (0.5 * (hi[0] - lo[0])).max(0.5 * (hi[1] - lo[1])).max(1e-9);
        let rows: Vec<([f64; 10], [f64; 2])> = points[..n]
            .iter()
            .zip(&targets[..n])
            .map(|(p, t)| {
                (
                    cubic_basis((p[0] - centre[0]) / half, (p[1] - centre[1]) / half),
                    *t,
                )
            })
            .collect();
        let ax = least_squares(&rows, |r| r.1[0])?;
        let ay = least_squares(&rows, |r| r.1[1])?;
        Some(Self {
            centre,
            half,
            ax,
            ay,
        })
    }

    /// The map at (x, y) counts, nm.
    pub fn eval(&self, x: f64, y: f64) -> [f64; 2] {
        let b = cubic_basis(
            (x - self.centre[0]) / self.half,
            (y - self.centre[1]) / self.half,
        );
        let dot = |a: &[f64; 10]| a.iter().zip(&b).map(|(p, q)| p * q).sum::<f64>();
        [dot(&self.ax), dot(&self.ay)]
    }

    /// Jacobian [[∂X/∂x, ∂X/∂y], [∂Y/∂x, ∂Y/∂y]], nm/count.
    pub fn jacobian(&self, x: f64, y: f64) -> [[f64; 2]; 2] {
        let (u, v) = (
            (x - self.centre[0]) / self.half,
            (y - self.centre[1]) / self.half,
        );
        let mut j = [[0.0; 2]; 2];
        for (k, &(p, q)) in CUBIC_TERMS.iter().enumerate() {
            let du = if p > 0 {
                f64::from(p) * u.powi(p - 1) * v.powi(q)
            } else {
                0.0
            };
            let dv = if q > 0 {
                f64::from(q) * u.powi(p) * v.powi(q - 1)
            } else {
                0.0
            };
            j[0][0] += self.ax[k] * du / self.half;
            j[1][0] += self.ay[k] * du / self.half;
            j[0][1] += self.ax[k] * dv / self.half;
            j[1][1] += self.ay[k] * dv / self.half;
        }
        j
    }
}

impl CorrectionField for CubicMap {
    fn form(&self, x: f64, y: f64) -> FormCoefficients {
        let j = self.jacobian(x, y);
        let kx = j[0][0].hypot(j[1][0]);
        let (ex, ey) = (j[0][0] / kx, j[1][0] / kx);
        FormCoefficients {
            kx_nm_per_count: kx,
            kyx_nm_per_count: j[0][1] * ex + j[1][1] * ey,
            kyy_nm_per_count: (j[0][0] * j[1][1] - j[0][1] * j[1][0]) / kx,
        }
    }
}

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
    /// [`ImageCorrection::UserFile`] with the command log recorded while the run and the
    /// images were taken (what `spmcal scan` keeps): the creep of the approach move is
    /// corrected too.
    UserFileRecorded {
        /// The calibration file (with its dynamics).
        set: Box<spm_correction::SurfaceSet>,
        /// The recorded commands: the run's and the images'.
        history: spm_correction::dynamics::CommandHistory,
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
    let (nx, ny) = (image.map.columns, image.map.rows);
    Ok(match &method.correction {
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
            let fit = CubicMap::fit(&u, &image.truth_nm).ok_or_else(|| {
                ImageBenchmarkError::Grating("per-image bound: singular fit".to_owned())
            })?;
            let points: Vec<[f64; 2]> = u.iter().map(|p| fit.eval(p[0], p[1])).collect();
            map_from_points(&points, nx, ny)?
        }
        ImageCorrection::UserFile(set) => user_file_map(set, image, None)?,
        ImageCorrection::UserFileRecorded { set, history } => {
            user_file_map(set, image, Some(history))?
        }
        ImageCorrection::EffectivePath {
            field,
            offsets,
            gain,
        } => {
            let offsets = offsets.get(index).ok_or_else(|| {
                ImageBenchmarkError::Config(format!("no effective-input offsets for image {index}"))
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
    })
}

/// [`ImageCorrection::UserFile`]: the image as a `.gsf` in memory (heights in display
/// orientation, the raster in counts, the scan path, the scanner and counts convention), read
/// back and mapped through `spm_apply` as `spmcal correct` does.
fn user_file_map(
    set: &spm_correction::SurfaceSet,
    image: &TestImage,
    recorded: Option<&spm_correction::dynamics::CommandHistory>,
) -> Result<CoordinateMap, ImageBenchmarkError> {
    use spm_apply::{
        ApplyOptions, FileRaster, KEY_CONVENTION, KEY_LINE_TIME, KEY_ORIGIN_X, KEY_ORIGIN_Y,
        KEY_SCAN_PATH, KEY_SCANNER, KEY_STEP,
    };
    let m = &image.map;
    let fail = |what: String| ImageBenchmarkError::Config(format!("user file: {what}"));
    let mut display = Vec::with_capacity(m.columns * m.rows);
    for row in (0..m.rows).rev() {
        display.extend_from_slice(&m.z_counts[row * m.columns..(row + 1) * m.columns]);
    }
    let k = set.provenance.nominal_nm_per_count.unwrap_or(1.0);
    let side = |n: usize| m.pixel_step.value() * n as f64 * k;
    let channel = spm_formats::Channel::new(
        "Z",
        spm_formats::Direction::Forward,
        "counts",
        m.columns,
        m.rows,
        display,
    )
    .map_err(|e| fail(e.to_string()))?
    .with_size_nm(side(m.columns), side(m.rows));
    let (x0, y0, step) = (
        m.origin.x.value().to_string(),
        m.origin.y.value().to_string(),
        m.pixel_step.value().to_string(),
    );
    let path = match image.direction {
        ScanDirection::Direct => "direct",
        ScanDirection::Counter => "counter",
    };
    // What a controller records: the duration of one trace.
    let line_time = (image.dwell_s * m.columns as f64).to_string();
    let bytes = spm_formats::encode_gsf(
        &channel,
        &[
            (KEY_ORIGIN_X, x0.as_str()),
            (KEY_ORIGIN_Y, y0.as_str()),
            (KEY_STEP, step.as_str()),
            (KEY_SCAN_PATH, path),
            (KEY_SCANNER, set.provenance.scanner_id.as_str()),
            (KEY_CONVENTION, "centred_signed"),
            (KEY_LINE_TIME, line_time.as_str()),
        ],
    )
    .map_err(|e| fail(e.to_string()))?;
    let file = spm_formats::read_bytes(&bytes, std::path::Path::new("test-image.gsf"))
        .map_err(|e| fail(e.to_string()))?;
    let channel = file
        .channels
        .first()
        .ok_or_else(|| fail("no channel read back".to_owned()))?;
    let raster = FileRaster::of(&file, channel, None, None).map_err(|e| fail(e.to_string()))?;
    let plane = set.plane_nearest(0.0)?;
    // The benchmark's places reach the field's edge: extrapolation is allowed (and measured).
    let options = ApplyOptions {
        allow_extrapolation: true,
        ..ApplyOptions::default()
    };
    spm_apply::check(&file, set, plane, &raster, &options).map_err(|e| fail(e.to_string()))?;
    let field = plane.field(spm_correction::Route::Products);
    let half = spm_apply::dynamic::Half::Trace;
    let (map, _) = match (&set.dynamics, recorded) {
        (Some(d), Some(history)) => spm_apply::dynamic::recorded_map(
            &field,
            &raster,
            d,
            half,
            history,
            &image.time_acquisition_s,
        )?,
        (Some(d), None) => spm_apply::dynamic::dynamic_map(&field, &raster, d, half)?,
        (None, _) => spm_apply::coordinate_map(&field, &raster)?,
    };
    Ok(map)
}

fn position_figures(corrected: &[[f64; 2]], image: &TestImage, nominal: f64) -> (f64, f64, f64) {
    let r = rigid_residuals(corrected, &image.truth_nm);
    let n = r.len().max(1) as f64;
    let ms = r.iter().map(|v| v * v).sum::<f64>() / n;
    let max = r.iter().copied().fold(0.0_f64, f64::max);
    let side_nm = image.size.side_counts() * nominal;
    (ms.sqrt() * 1e3, max * 1e3, 100.0 * ms.sqrt() / side_nm)
}

fn atoms(map: &HeightMap, period_px: f64) -> Vec<Feature> {
    let config = DetectionConfig {
        min_separation_px: 0.5 * period_px,
        ..DetectionConfig::default()
    };
    detect(map, &config).map(|d| d.features).unwrap_or_default()
}

/// Mutual nearest neighbours between the direct features `subset` (positions shifted by
/// `offset(i)`) and every counter feature, closer than `max`.
fn mutual_matches(
    direct: &[[f64; 2]],
    counter: &[[f64; 2]],
    subset: &[usize],
    max: f64,
    offset: impl Fn(usize) -> [f64; 2],
) -> Vec<(usize, usize)> {
    let shifted: Vec<[f64; 2]> = subset
        .iter()
        .map(|&i| {
            let o = offset(i);
            [direct[i][0] + o[0], direct[i][1] + o[1]]
        })
        .collect();
    // Only neighbours within `max` count: a grid of `max`-sized cells finds them.
    let cell = max.max(1e-12);
    let key = |p: [f64; 2]| ((p[0] / cell).floor() as i64, (p[1] / cell).floor() as i64);
    let grid = |set: &[[f64; 2]]| {
        let mut g: std::collections::HashMap<(i64, i64), Vec<usize>> =
            std::collections::HashMap::new();
        for (i, p) in set.iter().enumerate() {
            g.entry(key(*p)).or_default().push(i);
        }
        g
    };
    let counter_grid = grid(counter);
    let shifted_grid = grid(&shifted);
    let nearest = |p: [f64; 2],
                   set: &[[f64; 2]],
                   g: &std::collections::HashMap<(i64, i64), Vec<usize>>|
     -> Option<(usize, f64)> {
        let (cx, cy) = key(p);
        let mut best: Option<(usize, f64)> = None;
        for dx in -1..=1 {
            for dy in -1..=1 {
                for &i in g.get(&(cx + dx, cy + dy)).into_iter().flatten() {
                    let d = (set[i][0] - p[0]).hypot(set[i][1] - p[1]);
                    if best.is_none_or(|b| d < b.1 || (d == b.1 && i < b.0)) {
                        best = Some((i, d));
                    }
                }
            }
        }
        best
    };
    let mut out = Vec::new();
    for (k, p) in shifted.iter().enumerate() {
        let Some((j, distance)) = nearest(*p, counter, &counter_grid) else {
            continue;
        };
        if distance <= max
            && nearest(counter[j], &shifted, &shifted_grid).map(|(m, _)| m) == Some(k)
        {
            out.push((subset[k], j));
        }
    }
    out
}

/// Atoms common to a counter-scanned pair. The two sightings of an atom are apart by the
/// drift (and creep) over the time between them, which runs from about zero (the last
/// direct line, the first counter line) to twice the image time: far more than a lattice
/// period in a slow image. So the match grows from the rows seen close in time: first the
/// few atoms with the shortest time apart, matched within `max`; their offsets give an
/// apparent offset and velocity; then ever more atoms matched at the positions those
/// predict, the fit renewed at every stage. Positions are the features' corrected
/// coordinates in the two images' common frame (`frame`: the direct and the counter map; nm,
/// `max` in nm too), where a good correction leaves only the drift between the sightings.
pub fn match_features(
    direct: &[Feature],
    counter: &[Feature],
    direct_map: &HeightMap,
    counter_map: &HeightMap,
    max: f64,
    frame: (&CoordinateMap, &CoordinateMap),
) -> Vec<FeatureMatch> {
    let (nx, ny) = (direct_map.columns, direct_map.rows);
    let position = |f: &Feature, map: &CoordinateMap| -> Option<[f64; 2]> {
        map.interpolate(f.column, f.row)
            .map(|p| [p.x.value(), p.y.value()])
    };
    // Features without a position in the frame are left out (kept indices).
    let keep_d: Vec<usize> = (0..direct.len())
        .filter(|&i| position(&direct[i], frame.0).is_some())
        .collect();
    let keep_c: Vec<usize> = (0..counter.len())
        .filter(|&j| position(&counter[j], frame.1).is_some())
        .collect();
    let pd: Vec<[f64; 2]> = keep_d
        .iter()
        .filter_map(|&i| position(&direct[i], frame.0))
        .collect();
    let pc: Vec<[f64; 2]> = keep_c
        .iter()
        .filter_map(|&j| position(&counter[j], frame.1))
        .collect();
    let time_apart = |i: usize| -> f64 {
        let f = &direct[keep_d[i]];
        let c = (f.column.round().max(0.0) as usize).min(nx.saturating_sub(1));
        let r = (f.row.round().max(0.0) as usize).min(ny.saturating_sub(1));
        let k = r * nx + c;
        match (counter_map.time_s.get(k), direct_map.time_s.get(k)) {
            (Some(tc), Some(td)) => tc - td,
            _ => f64::NAN,
        }
    };
    let mut order: Vec<usize> = (0..pd.len())
        .filter(|&i| time_apart(i).is_finite())
        .collect();
    order.sort_by(|&a, &b| time_apart(a).abs().total_cmp(&time_apart(b).abs()));
    // offset(Δt) = a + v·Δt per axis, least squares over the matched pairs.
    let fit = |pairs: &[(usize, usize)]| -> Option<[[f64; 2]; 2]> {
        if pairs.len() < 4 {
            return None;
        }
        let n = pairs.len() as f64;
        let (mut st, mut stt) = (0.0, 0.0);
        let (mut sx, mut sy, mut stx, mut sty) = (0.0, 0.0, 0.0, 0.0);
        for &(i, j) in pairs {
            let t = time_apart(i);
            let (dx, dy) = (pc[j][0] - pd[i][0], pc[j][1] - pd[i][1]);
            st += t;
            stt += t * t;
            sx += dx;
            sy += dy;
            stx += t * dx;
            sty += t * dy;
        }
        let det = n * stt - st * st;
        if det.abs() <= 1e-12 || det.is_nan() {
            return Some([[sx / n, sy / n], [0.0, 0.0]]);
        }
        let v = [(n * stx - st * sx) / det, (n * sty - st * sy) / det];
        Some([[(sx - v[0] * st) / n, (sy - v[1] * st) / n], v])
    };
    let mut model = [[0.0_f64; 2]; 2];
    let mut pairs = Vec::new();
    // Stages of 4 %, 6 %, 9 %, … of the atoms (at least 6), then all of them, twice: each
    // stage's prediction errs by the velocity error times its longer time apart.
    let mut fraction = 0.04_f64;
    for _ in 0..12 {
        let take = ((order.len() as f64 * fraction.min(1.0)).ceil() as usize)
            .max(6)
            .min(order.len());
        fraction *= 1.5;
        pairs = mutual_matches(&pd, &pc, &order[..take], max, |i| {
            let t = time_apart(i);
            [model[0][0] + model[1][0] * t, model[0][1] + model[1][1] * t]
        });
        if let Some(m) = fit(&pairs) {
            model = m;
        }
    }
    let pairs: Vec<(usize, usize)> = pairs
        .into_iter()
        .map(|(i, j)| (keep_d[i], keep_c[j]))
        .collect();
    pairs
        .into_iter()
        .map(|(i, j)| FeatureMatch {
            direct_column: direct[i].column,
            direct_row: direct[i].row,
            counter_column: counter[j].column,
            counter_row: counter[j].row,
        })
        .collect()
}

/// Lattice constant (nm) and largest angle deviation from 60° (degrees) on the direct image of
/// a pair, given both images' corrected coordinate maps (scanner geometry): the atoms common
/// to both give the drift (`estimate_drift`), the direct map is moved to a common time, the
/// image resampled onto a uniform nm grid and the lattice measured on it. `None` when the
/// pipeline cannot measure.
pub fn measure_lattice(
    direct_coordinates: &CoordinateMap,
    counter_coordinates: &CoordinateMap,
    direct: &HeightMap,
    counter: &HeightMap,
    raw_atoms: (&[Feature], &[Feature]),
    lattice_constant_nm: f64,
) -> Option<(f64, f64)> {
    let matches = match_features(
        raw_atoms.0,
        raw_atoms.1,
        direct,
        counter,
        0.3 * lattice_constant_nm,
        (direct_coordinates, counter_coordinates),
    );
    if matches.len() < 6 {
        return None;
    }
    let (nx, ny) = (direct.columns, direct.rows);
    let time_at = |times: &[f64], c: f64, r: f64| -> f64 {
        let i = (c.round().max(0.0) as usize).min(nx - 1);
        let j = (r.round().max(0.0) as usize).min(ny - 1);
        times[j * nx + i]
    };
    let mut pairs = Vec::with_capacity(matches.len());
    for m in &matches {
        let pd = direct_coordinates.interpolate(m.direct_column, m.direct_row)?;
        let pc = counter_coordinates.interpolate(m.counter_column, m.counter_row)?;
        pairs.push(SightingPair {
            direct: FeatureSighting {
                position: pd,
                time: Seconds(time_at(&direct.time_s, m.direct_column, m.direct_row)),
            },
            counter: FeatureSighting {
                position: pc,
                time: Seconds(time_at(&counter.time_s, m.counter_column, m.counter_row)),
            },
        });
    }
    let drift = estimate_drift(&pairs).ok()?;
    // Matched atoms that a constant drift cannot explain to a fifth of a lattice constant are
    // a failed match (or an image too distorted to match), not a lattice measurement.
    if drift.residual_rms_nm.is_nan() || drift.residual_rms_nm > 0.2 * lattice_constant_nm {
        return None;
    }
    let t_ref = Seconds(direct.time_s[direct.time_s.len() / 2]);
    let moved =
        drift_corrected_map(direct_coordinates, &direct.time_s, drift.velocity, t_ref).ok()?;
    // The largest axis-aligned rectangle inside the corrected (sheared, drift-moved) image:
    // inside its left and right columns and its first and last rows.
    let m = &moved;
    let (nc, nr) = (m.columns(), m.rows());
    let (mut x0, mut x1, mut y0, mut y1) = (
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
    );
    for r in 0..nr {
        x0 = x0.max(m.point(0, r)?.x.value());
        x1 = x1.min(m.point(nc - 1, r)?.x.value());
    }
    for c in 0..nc {
        y0 = y0.max(m.point(c, 0)?.y.value());
        y1 = y1.min(m.point(c, nr - 1)?.y.value());
    }
    if !(x1 > x0 && y1 > y0) {
        return None;
    }
    let (bx0, bx1, by0, by1) = m.bounds_nm();
    let pixels = (direct.columns.max(2) - 1) as f64;
    let step = ((bx1 - bx0) + (by1 - by0)) / 2.0 / pixels;
    let margin = 0.03 * (x1 - x0).min(y1 - y0);
    let side = (x1 - x0).min(y1 - y0) - 2.0 * margin;
    let n = (side / step).floor() as usize;
    if n < 8 {
        return None;
    }
    let grid = OutputGrid::new(
        NmPoint::from_nm(x0 + margin, y0 + margin),
        spm_hal::Nanometres(step),
        n,
        n,
    )
    .ok()?;
    let image = resample(
        &direct.z_counts,
        &moved,
        &grid,
        Interpolation::Bilinear,
        Parallelism::Sequential,
    )
    .ok()?;
    if !image.iter().all(|v| v.is_finite()) {
        return None;
    }
    let map = HeightMap {
        origin: CountPoint::from_counts(0.0, 0.0),
        pixel_step: Counts(1.0),
        columns: n,
        rows: n,
        z_counts: image,
        time_s: vec![0.0; n * n],
    };
    let found = atoms(&map, lattice_constant_nm / step);
    let lattice = lattice_vectors(&found, &LatticeConfig::default()).ok()?;
    if lattice.vectors.len() < 3 {
        return None;
    }
    let v: Vec<[f64; 2]> = lattice
        .vectors
        .iter()
        .take(3)
        .map(|l| [l.vector.x.value() * step, l.vector.y.value() * step])
        .collect();
    let a = v.iter().map(|p| p[0].hypot(p[1])).sum::<f64>() / 3.0;
    // Three directions of one triangular lattice: lengths within a quarter of their mean.
    // Anything else is a second-neighbour or spurious vector, not a measurement.
    if v.iter().any(|p| (p[0].hypot(p[1]) / a - 1.0).abs() > 0.25) {
        return None;
    }
    let mut worst: f64 = 0.0;
    for i in 0..3 {
        for j in (i + 1)..3 {
            let cos = (v[i][0] * v[j][0] + v[i][1] * v[j][1])
                / (v[i][0].hypot(v[i][1]) * v[j][0].hypot(v[j][1]));
            let angle = cos.clamp(-1.0, 1.0).acos().to_degrees();
            // Directions are unoriented: 60° and 120° are the same pair of lines.
            let dev = (angle - 60.0).abs().min((angle - 120.0).abs());
            worst = worst.max(dev);
        }
    }
    // A triangular lattice's three directions are 60° apart; one further off than 15° is a
    // spurious vector (a failed resampling or match), not a distorted lattice.
    (worst <= 15.0).then_some((a, worst))
}

/// Corrects every image with every method and summarises.
///
/// # Errors
/// As the correction of an image.
pub fn evaluate_images(
    images: &[TestImage],
    methods: &[ImageMethod<'_>],
    config: &ImageSetConfig,
) -> Result<ImageBenchmark, ImageBenchmarkError> {
    let nominal = config.nominal_nm_per_count;
    let a_true = config.lattice_constant_nm;
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
    let mut summaries = BTreeMap::new();
    // The atoms of the raw images do not depend on the method: detected once per pair.
    let mut raw_atoms: BTreeMap<usize, (Vec<Feature>, Vec<Feature>)> = BTreeMap::new();
    for method in methods {
        let mut ms_sum = 0.0;
        let mut max_pm: f64 = 0.0;
        let mut pct_sum = 0.0;
        let mut by_size: BTreeMap<String, (f64, usize)> = BTreeMap::new();
        let mut lattice: Vec<f64> = Vec::new();
        let mut angle_max: f64 = 0.0;
        let mut failures = 0;
        for (k, image) in images.iter().enumerate() {
            let map = coordinate_map(method, image, k)?;
            let corrected = flatten(&map)?;
            let (rms, max, pct) = position_figures(&corrected, image, nominal);
            ms_sum += rms * rms;
            max_pm = max_pm.max(max);
            pct_sum += pct;
            let key = format!("{}", image.size.side_counts());
            let e = by_size.entry(key).or_insert((0.0, 0));
            e.0 += rms * rms;
            e.1 += 1;
            let mut figures = ImageFigures {
                position_rms_pm: rms,
                position_max_pm: max,
                position_rms_pct_of_side: pct,
                lattice_error_pct: None,
                lattice_angle_error_deg: None,
            };
            // The lattice figure once per pair, on its direct image.
            let period_px = config.lattice_constant_nm / nominal / image.size.step_counts.max(1e-9);
            if image.direction == ScanDirection::Direct
                && period_px >= config.min_pixels_per_lattice_constant
                && let Some(counter) = images
                    .get(k + 1)
                    .filter(|c| c.pair == image.pair && c.direction == ScanDirection::Counter)
            {
                let counter_map = coordinate_map(method, counter, k + 1)?;
                let raw = raw_atoms.entry(k).or_insert_with(|| {
                    (atoms(&image.map, period_px), atoms(&counter.map, period_px))
                });
                let measured = measure_lattice(
                    &map,
                    &counter_map,
                    &image.map,
                    &counter.map,
                    (&raw.0, &raw.1),
                    a_true,
                );
                match measured {
                    Some((a_nm, angle)) => {
                        let e = 100.0 * (a_nm / config.lattice_constant_nm - 1.0);
                        lattice.push(e.abs());
                        angle_max = angle_max.max(angle);
                        figures.lattice_error_pct = Some(e);
                        figures.lattice_angle_error_deg = Some(angle);
                    }
                    None => failures += 1,
                }
            }
            rows[k].figures.insert(method.name.clone(), figures);
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

/// The grating of the realistic polynomial baseline.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GratingConfig {
    /// The certified pitch, nm (what the fit is told).
    pub nominal_pitch_nm: f64,
    /// The true pitch relative to the certificate (1.001 = at the edge of a 0.1 % certificate).
    pub true_over_nominal: f64,
    /// Pillar height, nm.
    pub height_nm: f64,
    /// Pillar Gaussian radius, nm.
    pub sigma_nm: f64,
    /// Mounting angle of the grating, degrees.
    pub rotation_deg: f64,
    /// Pixels per side of the one grating image.
    pub pixels: u32,
    /// Pixel dwell of the grating image, s.
    pub dwell_s: f64,
}

impl GratingConfig {
    /// A 40 nm pitch pillar grating (certificate ±0.1 %, true pitch at its edge), 5 nm high,
    /// one 513 × 513 image at `dwell_s`.
    pub fn standard(dwell_s: f64) -> Self {
        Self {
            nominal_pitch_nm: 40.0,
            true_over_nominal: 1.001,
            height_nm: 5.0,
            sigma_nm: 6.0,
            rotation_deg: 3.0,
            pixels: 513,
            dwell_s,
        }
    }
}

/// The realistic per-image polynomial: the same physics (scanner, hysteresis, creep, drift,
/// noise) over a pillar grating; one image of the whole region; pillars detected by
/// spm-features (real detection noise); indexed by a walk over nearest neighbours; a
/// total-degree-3 polynomial per coordinate fitted from the pillars' commanded counts to
/// their certified grid positions. Drift during the image stays in (one image, as a user
/// takes it).
///
/// # Errors
/// [`ImageBenchmarkError::Grating`] when the image cannot be taken, indexed or fitted.
pub fn grating_polynomial<S: SimulatedInstrument>(
    instrument: &S,
    nominal_nm_per_count: f64,
    region: &CountRegion,
    grating: &GratingConfig,
) -> Result<CubicMap, ImageBenchmarkError> {
    let mut sim = instrument
        .grating_twin(&GratingSample {
            pitch_nm: grating.nominal_pitch_nm * grating.true_over_nominal,
            height_nm: grating.height_nm,
            sigma_nm: grating.sigma_nm,
            rotation_deg: grating.rotation_deg,
        })
        .map_err(|e| ImageBenchmarkError::Grating(e.to_string()))?;
    let side =
        (region.x_max_counts - region.x_min_counts).max(region.y_max_counts - region.y_min_counts);
    let n = grating.pixels.max(16);
    let step = (side / f64::from(n - 1)).ceil();
    let centre = CountPoint::from_counts(
        (0.5 * (region.x_min_counts + region.x_max_counts)).round(),
        (0.5 * (region.y_min_counts + region.y_max_counts)).round(),
    );
    let request = ScanRequest::centred_square(centre, Counts(step), n, Seconds(grating.dwell_s));
    let frame = sim
        .scan(&request)
        .map_err(|e| ImageBenchmarkError::Grating(format!("grating image: {e}")))?;
    let map = frame
        .height_map(TraceHalf::Forward)
        .map_err(|e| ImageBenchmarkError::Grating(format!("grating image: {e}")))?;
    // Nominal period in pixels: the scanner's large-signal gain is unknown to the user, so
    // the detection is told only the order of magnitude.
    let period_px = grating.nominal_pitch_nm / (nominal_nm_per_count * step);
    let config = DetectionConfig {
        min_separation_px: 0.4 * period_px,
        max_fit_radius_px: (0.5 * period_px).max(3.0),
        ..DetectionConfig::default()
    };
    let features = detect(&map, &config)
        .map_err(|e| ImageBenchmarkError::Grating(format!("pillar detection: {e}")))?
        .features;
    let positions: Vec<[f64; 2]> = features
        .iter()
        .map(|f| [f.position.x.value(), f.position.y.value()])
        .collect();
    let indexed = index_grid(&positions, [centre.x.value(), centre.y.value()])
        .ok_or_else(|| ImageBenchmarkError::Grating("pillars could not be indexed".to_owned()))?;
    if indexed.len() < 50 {
        return Err(ImageBenchmarkError::Grating(format!(
            "only {} pillars indexed",
            indexed.len()
        )));
    }
    let points: Vec<[f64; 2]> = indexed.iter().map(|(k, _)| positions[*k]).collect();
    let targets: Vec<[f64; 2]> = indexed
        .iter()
        .map(|(_, (i, j))| {
            [
                f64::from(*i) * grating.nominal_pitch_nm,
                f64::from(*j) * grating.nominal_pitch_nm,
            ]
        })
        .collect();
    CubicMap::fit(&points, &targets)
        .ok_or_else(|| ImageBenchmarkError::Grating("singular polynomial fit".to_owned()))
}

/// Grid indices of features on a distorted square lattice: a breadth-first walk from the
/// feature nearest `start`, each step predicted by the local lattice vectors of its parent.
fn index_grid(positions: &[[f64; 2]], start: [f64; 2]) -> Option<Vec<(usize, (i32, i32))>> {
    let dist = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]);
    let first = (0..positions.len())
        .min_by(|&a, &b| dist(positions[a], start).total_cmp(&dist(positions[b], start)))?;
    let p0 = positions[first];
    let mut near: Vec<usize> = (0..positions.len()).filter(|&k| k != first).collect();
    near.sort_by(|&a, &b| dist(positions[a], p0).total_cmp(&dist(positions[b], p0)));
    let near: Vec<[f64; 2]> = near
        .iter()
        .take(4)
        .map(|&k| [positions[k][0] - p0[0], positions[k][1] - p0[1]])
        .collect();
    if near.len() < 4 {
        return None;
    }
    let v1 = *near.iter().max_by(|a, b| a[0].total_cmp(&b[0]))?;
    let v2 = *near.iter().max_by(|a, b| a[1].total_cmp(&b[1]))?;
    let pitch = dist(v1, [0.0; 2]).min(dist(v2, [0.0; 2]));
    if !(pitch.is_finite() && pitch > 0.0) {
        return None;
    }
    // Buckets of one pitch for the nearest-feature look-up.
    let key = |p: [f64; 2]| ((p[0] / pitch).floor() as i64, (p[1] / pitch).floor() as i64);
    let mut buckets: std::collections::HashMap<(i64, i64), Vec<usize>> =
        std::collections::HashMap::new();
    for (k, p) in positions.iter().enumerate() {
        buckets.entry(key(*p)).or_default().push(k);
    }
    let nearest = |q: [f64; 2]| -> Option<(usize, f64)> {
        let (bx, by) = key(q);
        let mut best: Option<(usize, f64)> = None;
        for dx in -1..=1 {
            for dy in -1..=1 {
                for &k in buckets.get(&(bx + dx, by + dy)).into_iter().flatten() {
                    let d = dist(positions[k], q);
                    if best.is_none_or(|b| d < b.1) {
                        best = Some((k, d));
                    }
                }
            }
        }
        best
    };
    let mut index_of: std::collections::HashMap<usize, (i32, i32)> =
        std::collections::HashMap::new();
    let mut taken: std::collections::HashSet<(i32, i32)> = std::collections::HashSet::new();
    let mut queue = std::collections::VecDeque::new();
    index_of.insert(first, (0, 0));
    taken.insert((0, 0));
    queue.push_back((first, (0_i32, 0_i32), v1, v2));
    while let Some((k, (i, j), a, b)) = queue.pop_front() {
        let p = positions[k];
        for (di, dj, sign, along_a) in [
            (1, 0, 1.0, true),
            (-1, 0, -1.0, true),
            (0, 1, 1.0, false),
            (0, -1, -1.0, false),
        ] {
            let v = if along_a { a } else { b };
            let q = [p[0] + sign * v[0], p[1] + sign * v[1]];
            let Some((m, d)) = nearest(q) else { continue };
            let cell = (i + di, j + dj);
            if d > 0.3 * pitch || index_of.contains_key(&m) || taken.contains(&cell) {
                continue;
            }
            let step = [
                sign * (positions[m][0] - p[0]),
                sign * (positions[m][1] - p[1]),
            ];
            let (na, nb) = if along_a { (step, b) } else { (a, step) };
            index_of.insert(m, cell);
            taken.insert(cell);
            queue.push_back((m, cell, na, nb));
        }
    }
    let mut out: Vec<(usize, (i32, i32))> = index_of.into_iter().collect();
    out.sort_unstable();
    Some(out)
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
