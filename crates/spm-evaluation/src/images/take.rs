//! The image set and how it is taken: places over the calibrated region, sizes, dwells, the
//! move and pause before each image, a direct raster and at once its counter raster, with the
//! simulator's true tip positions and effective inputs recorded for every pixel.

use super::ImageBenchmarkError;
use serde::Serialize;
use spm_calibration::PauseLaw;
use spm_hal::recording::CommandRecorder;
use spm_hal::truth::SimulatedInstrument;
use spm_hal::{
    CountPoint, Counts, HeightMap, Microscope, MoveRequest, ScanDirection, ScanRequest, Seconds,
    TraceHalf,
};

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
    /// The backward trace (retrace) in the same geometry, with its own pixel times, when the
    /// instrument recorded it (the per-image trace/retrace methods, `crate::competitors`).
    pub backward: Option<HeightMap>,
    /// True tip position of every pixel, scanner frame, nm, in the same geometry.
    pub truth_nm: Vec<[f64; 2]>,
    /// The sample point under the tip at every pixel (the tip position plus the sample's drift
    /// displacement at the pixel's time), nm, in the same geometry: where on the sample each
    /// pixel was, which a corrected image should show.
    pub sample_truth_nm: Vec<[f64; 2]>,
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
    if values.len() != nx * ny {
        // No truth recorded (or a short recording): nothing to reorder.
        return Vec::new();
    }
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
/// [`ImageBenchmarkError::Instrument`] when an image fails 4 times (`ATTEMPTS`).
pub fn take_test_images<S: SimulatedInstrument>(
    instrument: &mut CommandRecorder<S>,
    region: &CountRegion,
    config: &ImageSetConfig,
) -> Result<Vec<TestImage>, ImageBenchmarkError> {
    instrument.inner_mut().record_tip_positions(true);
    // The retraces aside: the forward data and the random streams go on as without them.
    instrument.inner_mut().record_backward_aside(true);
    let result = take_images(instrument, region, config, |sim, n| {
        let truth: Vec<[f64; 2]> = sim
            .inner_mut()
            .last_scan_tip_positions()
            .iter()
            .map(|p| [p.x.value(), p.y.value()])
            .collect();
        let effective: Vec<[f64; 2]> = sim
            .inner_mut()
            .last_scan_effective_inputs()
            .iter()
            .map(|p| [p.x.value(), p.y.value()])
            .collect();
        if truth.len() != n {
            return Err(ImageBenchmarkError::Config(format!(
                "truth recording holds {} of {n} pixels",
                truth.len(),
            )));
        }
        Ok((truth, effective))
    });
    instrument.inner_mut().record_tip_positions(false);
    instrument.inner_mut().record_backward_aside(false);
    let mut images = result?;
    // The sample points: the drift at each pixel's (past) time is exact now.
    for image in &mut images {
        let n = image.map.columns;
        let times = to_geometry(
            &image.time_acquisition_s,
            n,
            image.map.rows,
            image.direction,
        );
        image.sample_truth_nm = image
            .truth_nm
            .iter()
            .zip(&times)
            .map(|(p, &t)| {
                let d = instrument.inner_mut().drift_displacement(Seconds(t));
                [p[0] + d.x.value(), p[1] + d.y.value()]
            })
            .collect();
    }
    Ok(images)
}

/// Takes the image set on any instrument, with no ground truth: the images' `truth_nm` and
/// `true_effective_acquisition` are empty (the run's validation on a real controller or a
/// stored image).
///
/// # Errors
/// [`ImageBenchmarkError::Instrument`] when an image fails 4 times (`ATTEMPTS`).
pub fn take_images_without_truth<M: Microscope>(
    instrument: &mut M,
    region: &CountRegion,
    config: &ImageSetConfig,
) -> Result<Vec<TestImage>, ImageBenchmarkError> {
    take_images(instrument, region, config, |_, _| {
        Ok((Vec::new(), Vec::new()))
    })
}

/// The image set: at each size, dwell and place, a move, the pause, a direct raster and at
/// once its counter raster. `truth(instrument, pixels)` gives the true tip positions and
/// effective inputs of the scan just taken (acquisition order), when there are any.
fn take_images<M: Microscope>(
    sim: &mut M,
    region: &CountRegion,
    config: &ImageSetConfig,
    mut truth: impl FnMut(&mut M, usize) -> TruthOfScan,
) -> Result<Vec<TestImage>, ImageBenchmarkError> {
    if config.sizes.is_empty() || config.dwells_s.is_empty() || config.places_per_side == 0 {
        return Err(ImageBenchmarkError::Config(
            "no sizes, dwells or places".to_owned(),
        ));
    }
    let mut images = Vec::new();
    let mut pair = 0;
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
                    let n = size.pixels as usize;
                    let (truth, effective) = truth(sim, n * n)?;
                    let map = frame
                        .height_map(TraceHalf::Forward)
                        .map_err(|e| ImageBenchmarkError::Config(format!("height map: {e}")))?;
                    let backward = frame.backward.is_some().then(|| {
                        frame.height_map(TraceHalf::Backward).map_err(|e| {
                            ImageBenchmarkError::Config(format!("backward height map: {e}"))
                        })
                    });
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
                        backward: backward.transpose()?,
                        truth_nm: to_geometry(&truth, n, n, direction),
                        sample_truth_nm: Vec::new(),
                        commanded_acquisition: commanded,
                        time_acquisition_s: frame.forward.time_s.clone(),
                        true_effective_acquisition: effective,
                    });
                }
                pair += 1;
            }
        }
    }
    Ok(images)
}

/// The true tip positions (nm) and effective inputs (counts) of a scan, acquisition order.
type TruthOfScan = Result<(Vec<[f64; 2]>, Vec<[f64; 2]>), ImageBenchmarkError>;

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
