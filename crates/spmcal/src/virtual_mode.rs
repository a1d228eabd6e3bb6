//! The virtual calibration mode (issue 24): a stored image of a standard served as the
//! surface by `spm_virtual::VirtualMicroscope`, checked before anything runs, and the plan
//! a user's `spmcal calibrate --virtual IMAGE --standard hopg|si7x7` runs.
//!
//! Refusals ([`VirtualInputError`], exit 2, nothing written) name the file and the reason:
//! pixels without data, too few pixels per lattice constant (with the number needed), an
//! image that does not show the claimed standard (the lattice found versus the standard's),
//! and a net that does not fit in the image.

use serde::{Deserialize, Serialize};
use spm_calibration::{PlanConfig, StandardConfig, StandardName};
use spm_features::{DetectionConfig, LatticeConfig, Polarity, detect, lattice_vectors};
use spm_hal::{CountPoint, Counts, HeightMap};
use spm_virtual::{ChannelOptions, StoredImage, VirtualParams, VirtualSurface};
use std::path::{Path, PathBuf};

/// Fewest image pixels per lattice constant a virtual calibration accepts: the feature
/// detector fits a Gaussian over about half a lattice constant, which needs ≥ 3 pixels
/// across it.
pub const MIN_PIXELS_PER_LATTICE: f64 = 6.0;

/// The net's smallest margin from the image's usable edge, lattice constants: half the
/// aperture and a quarter lattice constant (an aperture centred on a feature up to a
/// lattice constant from its node may then leave the image: that visit is given up).
pub const MARGIN_LATTICE: f64 = 2.25;

/// The net's margin when the image is large enough ([`MARGIN_LATTICE`] otherwise): room for
/// an aperture centred on a feature 1.5 lattice constants from its node.
pub const ROOMY_MARGIN_LATTICE: f64 = 3.5;

/// Counts per image pixel of the default nominal sensitivity (pixel size / 10).
pub const DEFAULT_COUNTS_PER_PIXEL: f64 = 10.0;

/// The lattice found in an image must be within this factor of the standard's (either
/// way): a scanner distorting a lattice by more than 40 % is not calibrated against it.
pub const LATTICE_MATCH_FACTOR: f64 = 1.4;

/// The `[backend]` table of `kind = "virtual"`.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct VirtualBackendConfig {
    /// The stored image (any format spmcal reads), relative to the job file.
    pub image: PathBuf,
    /// The height channel's name (case-insensitive). Default: `Z`, else `Topography`, else
    /// the first channel in metres.
    #[serde(default)]
    pub channel: Option<String>,
    /// Nominal lateral sensitivity of the virtual scanner, nm per count (no default in a job
    /// file; `--virtual` uses the pixel size / 10).
    pub nominal_nm_per_count: f64,
    /// A consecutive frame scanned the other way, served for counter scans. Default: none
    /// (counter scans see the image itself).
    #[serde(default)]
    pub counter_image: Option<PathBuf>,
    /// Pixel size, nm, for files that state none (raw). Default: the file's.
    #[serde(default)]
    pub pixel_nm: Option<f64>,
    /// Line time, s, for files that state none. Default 0.1 s.
    #[serde(default)]
    pub fallback_line_time_s: Option<f64>,
    /// Remove the background (terraces, tilt, bow) at scales above this width, nm, before
    /// serving the image (`StoredImage::without_background`). Default: none in a job file;
    /// `--virtual` uses [`BACKGROUND_SIGMA_LATTICE`] lattice constants.
    #[serde(default)]
    pub background_sigma_nm: Option<f64>,
    /// Smooth the image with a Gaussian of this width, nm, before serving it
    /// (`StoredImage::smoothed`: pixel and line noise averaged). Default: none in a job
    /// file; `--virtual` uses [`default_smoothing_sigma_lattice`] lattice constants.
    #[serde(default)]
    pub smoothing_sigma_nm: Option<f64>,
    /// Filter the image by its own mean cell of this standard before serving it, after the
    /// background and the smoothing (`spm_features::cells::matched_filter`: the cell
    /// pattern fitted around every pixel, so a corner hole is found by its whole 7×7 cell,
    /// not by its few pixels). Default: none in a job file; `--virtual --standard si7x7`
    /// uses it.
    #[serde(default)]
    pub matched_cell: Option<StandardName>,
}

/// Width of the smoothing `--virtual` applies by default, lattice constants: for HOPG
/// 0.05 (the lattice keeps `exp(−2π²·0.05²)` ≈ 95 % of its corrugation; on the HOPG
/// terrace it lifts the share of tracking segments that recognise their atom from 57 % to
/// 71 %); for Si(111)-7×7 as well (wider, 0.15, widens the corner holes until the
/// detector takes them for defects on Si_7x7_051).
#[must_use]
pub fn default_smoothing_sigma_lattice(standard: StandardName) -> f64 {
    match standard {
        StandardName::Hopg | StandardName::Si7x7 => 0.05,
    }
}

/// The mean-cell filter `--virtual` applies ([`VirtualBackendConfig::matched_cell`]): for
/// Si(111)-7×7, whose corner holes on Si_7x7_028/032 (13.8 pixels per cell) are barely
/// above the noise; none for HOPG (one atom per cell: the smoothing does it).
#[must_use]
pub fn default_matched_cell(standard: StandardName) -> Option<StandardName> {
    match standard {
        StandardName::Hopg => None,
        StandardName::Si7x7 => Some(StandardName::Si7x7),
    }
}

/// Width of the background `--virtual` removes, lattice constants: the lattice keeps more
/// than 99.9 % of its corrugation, terraces and tilt are gone.
pub const BACKGROUND_SIGMA_LATTICE: f64 = 1.5;

/// The virtual backend, loaded and checked.
#[derive(Debug, Clone)]
pub struct VirtualBackend {
    /// The image file (as given, resolved against the job file's folder).
    pub image: PathBuf,
    /// The height channel served (`None`: Z, Topography, or the first in metres).
    pub channel: Option<String>,
    /// The surface served.
    pub surface: VirtualSurface,
    /// The stated conversions.
    pub params: VirtualParams,
}

impl VirtualBackend {
    /// The instrument's capabilities.
    #[must_use]
    pub fn capabilities(&self) -> spm_hal::Capabilities {
        use spm_hal::Microscope;
        match self.microscope() {
            Ok(m) => m.capabilities(),
            // Unreachable for a loaded backend (its parameters were checked); an empty field
            // makes every plan refuse itself.
            Err(_) => spm_hal::mock::ScriptedMicroscope::default_capabilities(),
        }
    }

    /// A fresh microscope over the surface (clock at 0 s, probe at the centre).
    ///
    /// # Errors
    /// The parameters or images are inconsistent.
    pub fn microscope(&self) -> Result<spm_virtual::VirtualMicroscope, spm_virtual::VirtualError> {
        spm_virtual::VirtualMicroscope::new(self.surface.clone(), self.params)
    }
}

/// Why a virtual calibration refuses its input; every variant names the file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum VirtualInputError {
    /// The file cannot be read as an SPM image.
    #[error("{0}")]
    Read(#[from] spm_formats::FormatError),
    /// No height channel of that name.
    #[error("{path}: no height channel {wanted}; the file has {available}")]
    NoChannel {
        /// The file.
        path: PathBuf,
        /// The channel asked for.
        wanted: String,
        /// The channels present.
        available: String,
    },
    /// The channel cannot be served (pixels without data, no size, not a height).
    #[error("{path}: channel {channel}: {source}")]
    Image {
        /// The file.
        path: PathBuf,
        /// The channel.
        channel: String,
        /// Why.
        source: spm_virtual::ImageError,
    },
    /// The pixels are too coarse for the standard.
    #[error(
        "{path}: {pixels_per_lattice:.1} pixels per lattice constant of {standard} ({pixel_nm:.4} nm \
         pixels, a = {lattice_nm} nm); a virtual calibration needs at least {needed} \
         (pixels of at most {max_pixel_nm:.4} nm)"
    )]
    TooFewPixels {
        /// The file.
        path: PathBuf,
        /// The standard's name.
        standard: String,
        /// Pixels per lattice constant found.
        pixels_per_lattice: f64,
        /// Pixel size, nm (the larger of x and y).
        pixel_nm: f64,
        /// Lattice constant, nm.
        lattice_nm: f64,
        /// Pixels per lattice constant needed.
        needed: f64,
        /// Largest pixel size that would do, nm.
        max_pixel_nm: f64,
    },
    /// The image does not show the standard.
    #[error(
        "{path}: does not show {standard} ({polarity} on a lattice of {lattice_nm} nm): {finding}"
    )]
    NotTheStandard {
        /// The file.
        path: PathBuf,
        /// The standard's name.
        standard: String,
        /// Hills or pits.
        polarity: &'static str,
        /// Lattice constant, nm.
        lattice_nm: f64,
        /// What was found instead.
        finding: String,
    },
    /// The net (with its margins for attachment and aperture) does not fit in the image.
    #[error("{path}: {detail}")]
    NetTooLarge {
        /// The file.
        path: PathBuf,
        /// The sizes.
        detail: String,
    },
    /// A parameter is out of range.
    #[error("{path}: {detail}")]
    Parameter {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
}

/// The lattice measured on an image (the standard check and the before/after figures).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ImageLattice {
    /// Features found.
    pub features: usize,
    /// Median nearest-neighbour distance, nm (with the nominal pixel size).
    pub nearest_neighbour_nm: f64,
    /// Lengths of the two most populated lattice directions, nm.
    pub lengths_nm: [f64; 2],
    /// Angle between them, degrees (folded into (0°, 90°] ∪ its supplement as measured).
    pub angle_deg: f64,
}

/// The height channel and its backward half of a file.
fn pick_channels<'a>(
    file: &'a spm_formats::SpmFile,
    wanted: Option<&str>,
) -> Option<(&'a spm_formats::Channel, Option<&'a spm_formats::Channel>)> {
    use spm_formats::Direction;
    let forward = |name: &str| {
        file.channels
            .iter()
            .find(|c| c.direction() == Direction::Forward && c.name().eq_ignore_ascii_case(name))
    };
    let chosen = match wanted {
        Some(name) => forward(name)?,
        None => forward("Z").or_else(|| forward("Topography")).or_else(|| {
            file.channels
                .iter()
                .find(|c| c.direction() == Direction::Forward && c.unit() == "m")
        })?,
    };
    let backward = file
        .channels
        .iter()
        .find(|c| c.direction() == Direction::Backward && c.name() == chosen.name());
    Some((chosen, backward))
}

/// Reads one stored image (forward and, when present, backward half).
fn read_image(
    path: &Path,
    channel: Option<&str>,
    options: &ChannelOptions,
) -> Result<(StoredImage, Option<StoredImage>), VirtualInputError> {
    let file = spm_formats::read_any(path)?;
    let (forward, backward) =
        pick_channels(&file, channel).ok_or_else(|| VirtualInputError::NoChannel {
            path: path.to_path_buf(),
            wanted: channel
                .unwrap_or("Z (or Topography, or any in metres)")
                .to_owned(),
            available: file
                .channels
                .iter()
                .map(|c| format!("{} ({}, {})", c.name(), c.direction().as_str(), c.unit()))
                .collect::<Vec<_>>()
                .join(", "),
        })?;
    let image_error = |source| VirtualInputError::Image {
        path: path.to_path_buf(),
        channel: format!("{} ({})", forward.name(), forward.direction().as_str()),
        source,
    };
    let stored = StoredImage::from_channel(forward, options).map_err(image_error)?;
    // A backward half with pixels missing (an interrupted retrace) is left out rather than
    // refusing the forward image.
    let backward = backward.and_then(|b| StoredImage::from_channel(b, options).ok());
    Ok((stored, backward))
}

impl VirtualBackendConfig {
    /// Loads the images (paths relative to `dir`) and checks the parameters.
    ///
    /// # Errors
    /// [`VirtualInputError`] naming the file.
    pub fn load(&self, dir: &Path) -> Result<VirtualBackend, VirtualInputError> {
        let image_path = dir.join(&self.image);
        let options = ChannelOptions {
            pixel_nm: self.pixel_nm,
            fallback_line_time_s: self
                .fallback_line_time_s
                .unwrap_or(ChannelOptions::DEFAULT_LINE_TIME_S),
        };
        let (forward, backward) = read_image(&image_path, self.channel.as_deref(), &options)?;
        let counter = match &self.counter_image {
            Some(p) => Some(read_image(&dir.join(p), self.channel.as_deref(), &options)?.0),
            None => None,
        };
        let (forward, backward, counter) = match (
            self.background_sigma_nm,
            self.smoothing_sigma_nm,
            self.matched_cell,
        ) {
            (None, None, None) => (forward, backward, counter),
            (background, smoothing, matched) => {
                let level = |image: StoredImage| {
                    let pixel_nm = image.pixel_x_nm();
                    let image = match background {
                        Some(sigma_nm) => image.without_background(sigma_nm / pixel_nm),
                        None => Ok(image),
                    };
                    let image = match smoothing {
                        Some(sigma_nm) => image.and_then(|i| i.smoothed(sigma_nm / pixel_nm)),
                        None => image,
                    };
                    let image = image.map_err(|e| VirtualInputError::Parameter {
                        path: image_path.clone(),
                        detail: format!("background_sigma_nm / smoothing_sigma_nm: {e}"),
                    })?;
                    match matched {
                        Some(standard) => cell_matched(&image, standard).map_err(|finding| {
                            VirtualInputError::NotTheStandard {
                                path: image_path.clone(),
                                standard: standard.as_str().to_owned(),
                                polarity: standard.feature().as_str(),
                                lattice_nm: standard.lattice_constant_nm(),
                                finding,
                            }
                        }),
                        None => Ok(image),
                    }
                };
                (
                    level(forward)?,
                    backward.map(level).transpose()?,
                    counter.map(level).transpose()?,
                )
            }
        };
        let backend = VirtualBackend {
            image: image_path.clone(),
            channel: self.channel.clone(),
            surface: VirtualSurface {
                forward,
                backward,
                counter,
            },
            params: VirtualParams::new(self.nominal_nm_per_count),
        };
        backend
            .microscope()
            .map_err(|e| VirtualInputError::Parameter {
                path: image_path,
                detail: e.to_string(),
            })?;
        Ok(backend)
    }
}

/// `image` filtered by its own mean cell of `standard` (`spm_features::cells`: the lattice
/// from the spectrum, the mean cell folded over it, the matched filter), or why not.
fn cell_matched(image: &StoredImage, standard: StandardName) -> Result<StoredImage, String> {
    use spm_features::cells;
    let bad = vec![false; image.heights_nm().len()];
    let img = cells::Image {
        z: image.heights_nm(),
        bad: &bad,
        nx: image.columns(),
        ny: image.rows(),
    };
    let search = cells::LatticeSearch::near_period(
        [image.pixel_x_nm(), image.pixel_y_nm()],
        standard.lattice_constant_nm(),
        true,
    );
    let peaks = cells::find_lattice(&img, &search).ok_or_else(|| {
        "its spectrum shows no lattice near that period (the mean-cell filter \
         (`matched_cell`) needs one)"
            .to_owned()
    })?;
    let polarity = standard.feature().polarity();
    let matched = cells::matched_filter(&img, &peaks, polarity)
        .ok_or_else(|| "its cells cannot be located on the lattice of its spectrum".to_owned())?;
    tracing::info!(
        cells = matched.cells,
        radius_px = matched.radius_px,
        "image filtered by its own mean cell"
    );
    image
        .with_heights_nm(matched.z)
        .map_err(|e| format!("the filtered image: {e}"))
}

/// The image as a height map in pixel units (1 count = 1 pixel), for recognition.
fn pixel_map(image: &StoredImage) -> HeightMap {
    HeightMap {
        origin: CountPoint::from_counts(0.0, 0.0),
        pixel_step: Counts(1.0),
        columns: image.columns(),
        rows: image.rows(),
        z_counts: image.heights_nm().iter().map(|h| h * 1000.0).collect(),
        time_s: vec![0.0; image.heights_nm().len()],
    }
}

/// The lattice of the standard's features over a whole image, with `pixel_nm` taken as the
/// pixel size: features by spm-features' detector (polarity of the standard, separation
/// half the lattice constant), directions by neighbour statistics.
///
/// # Errors
/// A message when no lattice is found.
pub fn measure_lattice(
    image: &StoredImage,
    polarity: Polarity,
    lattice_nm: f64,
) -> Result<ImageLattice, String> {
    let px = image.pixel_x_nm();
    let py = image.pixel_y_nm();
    let detection = DetectionConfig {
        polarity,
        min_separation_px: (0.5 * lattice_nm / px.max(py)).max(1.5),
        max_fit_radius_px: (0.5 * lattice_nm / px.max(py)).max(2.0),
        ..DetectionConfig::default()
    };
    let found = detect(&pixel_map(image), &detection).map_err(|e| e.to_string())?;
    let lattice =
        lattice_vectors(&found.features, &LatticeConfig::default()).map_err(|e| e.to_string())?;
    let (a, b) = lattice.basis().ok_or_else(|| {
        format!(
            "{} features but no two lattice directions",
            found.features.len()
        )
    })?;
    let nm = |v: spm_hal::CountVector| (v.x.value() * px, v.y.value() * py);
    let (ax, ay) = nm(a.vector);
    let (bx, by) = nm(b.vector);
    let la = ax.hypot(ay);
    let lb = bx.hypot(by);
    let angle_deg = ((ax * bx + ay * by) / (la * lb))
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees();
    Ok(ImageLattice {
        features: found.features.len(),
        nearest_neighbour_nm: lattice.nearest_neighbour.value() * px.max(py),
        lengths_nm: [la, lb],
        angle_deg,
    })
}

/// Checks an image against the standard it is claimed to show: enough pixels per lattice
/// constant, and a lattice of the standard's features within [`LATTICE_MATCH_FACTOR`] of
/// its lattice constant. Returns the lattice found.
///
/// # Errors
/// [`VirtualInputError::TooFewPixels`] or [`VirtualInputError::NotTheStandard`].
pub fn check_standard(
    path: &Path,
    image: &StoredImage,
    standard: &StandardConfig,
) -> Result<ImageLattice, VirtualInputError> {
    let a = standard.lattice_constant_nm;
    let pixel_nm = image.pixel_x_nm().max(image.pixel_y_nm());
    let name = standard.name.map_or_else(
        || "the plan's standard".to_owned(),
        |n| n.as_str().to_owned(),
    );
    let per_lattice = a / pixel_nm;
    if per_lattice < MIN_PIXELS_PER_LATTICE {
        return Err(VirtualInputError::TooFewPixels {
            path: path.to_path_buf(),
            standard: name,
            pixels_per_lattice: per_lattice,
            pixel_nm,
            lattice_nm: a,
            needed: MIN_PIXELS_PER_LATTICE,
            max_pixel_nm: a / MIN_PIXELS_PER_LATTICE,
        });
    }
    let polarity = standard.feature.polarity();
    let not_it = |finding: String| VirtualInputError::NotTheStandard {
        path: path.to_path_buf(),
        standard: name.clone(),
        polarity: standard.feature.as_str(),
        lattice_nm: a,
        finding,
    };
    let lattice = measure_lattice(image, polarity, a).map_err(&not_it)?;
    let cells = (image.columns() as f64 * image.pixel_x_nm() / a)
        * (image.rows() as f64 * image.pixel_y_nm() / a);
    let d = lattice.nearest_neighbour_nm;
    if !(d.is_finite() && d > a / LATTICE_MATCH_FACTOR && d < a * LATTICE_MATCH_FACTOR) {
        return Err(not_it(format!(
            "the {} features found are {d:.4} nm apart (median nearest neighbour), not within \
             a factor {LATTICE_MATCH_FACTOR} of {a} nm",
            lattice.features
        )));
    }
    if (lattice.features as f64) < 0.25 * cells {
        return Err(not_it(format!(
            "only {} features where a lattice of {a} nm holds about {cells:.0}",
            lattice.features
        )));
    }
    Ok(lattice)
}

/// What `spmcal calibrate --virtual` chooses; every field has a default.
#[derive(Debug, Clone, PartialEq)]
pub struct VirtualRunOptions {
    /// The standard the image shows.
    pub standard: StandardName,
    /// Height channel (default: see [`VirtualBackendConfig::channel`]).
    pub channel: Option<String>,
    /// Nominal sensitivity, nm per count (default: pixel size / [`DEFAULT_COUNTS_PER_PIXEL`]).
    pub nominal_nm_per_count: Option<f64>,
    /// Nodes per side of the net (default 5, at least 2).
    pub nodes_per_side: u32,
    /// Repeats l (default 1: a stored image does not change between repeats, so each
    /// repeat returns the same coefficients at a node).
    pub repeats: u32,
    /// Pixel size, nm, for files without one.
    pub pixel_nm: Option<f64>,
    /// A counter frame (a consecutive frame scanned the other way).
    pub counter_image: Option<PathBuf>,
    /// Width of the smoothing, lattice constants (default
    /// [`default_smoothing_sigma_lattice`]).
    pub smoothing_sigma_lattice: Option<f64>,
    /// Accepted LCS angle deviation, degrees (default 20).
    pub angle_tolerance_deg: f64,
    /// Accepted relative LCS side deviation (default 0.35).
    pub length_tolerance_fraction: f64,
}

impl VirtualRunOptions {
    /// The defaults for a standard.
    #[must_use]
    pub fn new(standard: StandardName) -> Self {
        Self {
            standard,
            channel: None,
            nominal_nm_per_count: None,
            nodes_per_side: 5,
            repeats: 1,
            pixel_nm: None,
            counter_image: None,
            smoothing_sigma_lattice: None,
            angle_tolerance_deg: 20.0,
            length_tolerance_fraction: 0.35,
        }
    }
}

/// The backend config and the plan of a virtual calibration of `image`: the standard's
/// lattice, rasters sized in lattice constants (first attachment 3, segment 2, aperture 4;
/// about 8 to 12 samples per lattice constant), the net of `nodes_per_side`² nodes spread
/// over the image inside a margin that keeps every aperture and attachment on it.
///
/// # Errors
/// [`VirtualInputError`] for an image that cannot be read, does not show the standard, is
/// sampled too coarsely, or cannot hold the net.
pub fn virtual_job(
    image: &Path,
    options: &VirtualRunOptions,
) -> Result<(VirtualBackendConfig, VirtualBackend, PlanConfig), VirtualInputError> {
    let parameter = |detail: String| VirtualInputError::Parameter {
        path: image.to_path_buf(),
        detail,
    };
    if options.nodes_per_side < 2 || options.repeats < 1 {
        return Err(parameter(format!(
            "a net needs at least 2 nodes per side and 1 repeat, got {} and {}",
            options.nodes_per_side, options.repeats
        )));
    }
    let probe = VirtualBackendConfig {
        image: image.to_path_buf(),
        channel: options.channel.clone(),
        nominal_nm_per_count: 1.0,
        counter_image: options.counter_image.clone(),
        pixel_nm: options.pixel_nm,
        fallback_line_time_s: None,
        background_sigma_nm: Some(
            BACKGROUND_SIGMA_LATTICE * options.standard.lattice_constant_nm(),
        ),
        smoothing_sigma_nm: Some(
            options
                .smoothing_sigma_lattice
                .unwrap_or_else(|| default_smoothing_sigma_lattice(options.standard))
                * options.standard.lattice_constant_nm(),
        ),
        matched_cell: default_matched_cell(options.standard),
    };
    let loaded = probe.load(Path::new(""))?;
    let pixel_nm = loaded.surface.forward.pixel_x_nm();
    let nominal = options
        .nominal_nm_per_count
        .unwrap_or(pixel_nm / DEFAULT_COUNTS_PER_PIXEL);
    if !(nominal.is_finite() && nominal > 0.0) {
        return Err(parameter(format!(
            "nominal sensitivity {nominal} nm per count"
        )));
    }
    let config = VirtualBackendConfig {
        nominal_nm_per_count: nominal,
        ..probe
    };
    let backend = VirtualBackend {
        params: VirtualParams::new(nominal),
        ..loaded
    };
    let standard = options.standard.standard(
        nominal,
        options.length_tolerance_fraction,
        options.angle_tolerance_deg,
    );
    check_standard(image, &backend.surface.forward, &standard)?;
    let plan = virtual_plan(image, &backend, standard, options)?;
    Ok((config, backend, plan))
}

/// The plan of [`virtual_job`] for a loaded backend (`image` names the run and the errors).
///
/// # Errors
/// [`VirtualInputError::NetTooLarge`] when the net and its margins do not fit.
pub fn virtual_plan(
    image: &Path,
    backend: &VirtualBackend,
    standard: StandardConfig,
    options: &VirtualRunOptions,
) -> Result<PlanConfig, VirtualInputError> {
    let a_counts = standard.lattice_constant_nm / standard.nominal_nm_per_count;
    let forward = &backend.surface.forward;
    let counts_per_px = forward.pixel_x_nm() / standard.nominal_nm_per_count;
    // Samples no finer than half an image pixel, and 12 per lattice constant at most.
    let step = (a_counts / 12.0).max(0.5 * counts_per_px);
    let pixels = |size: f64| ((size / step).round() as u32).clamp(8, 256);
    let mut plan = PlanConfig::hopg_small_net();
    plan.scanner_id = format!(
        "virtual-{}",
        image
            .file_stem()
            .map_or_else(|| "image".to_owned(), |s| s.to_string_lossy().into_owned())
    );
    plan.repeats = options.repeats;
    // A stored image has no scanner dynamics of its own to identify (its trace and retrace
    // are fixed): the dynamics stage is off in virtual mode.
    plan.dynamics.enabled = false;
    // Measured images hold decoys (next-nearest-neighbour triangles, a chain of nodes locked
    // onto another basis of the lattice): recognition is gated by the image's own lattice,
    // surveyed first (`spm_calibration::survey`, docs/results/virtual.md).
    plan.survey.enabled = true;
    // Every neighbour of A is measured, not B and C alone: a stored image freezes its noise,
    // so the repeats that average it on an instrument return the same vectors here, while
    // A's other neighbours are independent sightings. On Si_7x7_028 the records' K̄y then
    // follows the lattice tool's row by row with a sd of 1.4 % (one triangle: 1.5–5 %, and
    // up to 1.7 % high on average), and a vector of another feature is left out by the node's own
    // redundancy (`spm_calibration::solve_lcc_rejecting`; docs/results/virtual.md).
    // For Si(111)-7×7 every corner hole of the aperture on a site of A's lattice is measured
    // (the shells at √3·a and 2·a too): the records' K̄x scatter halves (Si_7x7_028 1.9 →
    // 1.0 %, 032 1.1 → 0.7 %). On the HOPG terrace the farther atoms are worse sightings (the
    // noise's false atoms within the site tolerance; the left half's mean α moved by 2°), so
    // HOPG keeps the nearest neighbours.
    plan.variant.neighbours = match options.standard {
        StandardName::Si7x7 => spm_calibration::NeighbourSet::LatticeInAperture,
        StandardName::Hopg => spm_calibration::NeighbourSet::AllInAperture,
    };
    // A cell pattern's frames give their lattice by their spectrum (Si_7x7_028: the
    // features' neighbours put K̄y 50 % off); single atoms by their neighbours.
    plan.survey.lattice_from = match options.standard {
        StandardName::Hopg => spm_calibration::SurveyLattice::Neighbours,
        StandardName::Si7x7 => spm_calibration::SurveyLattice::Spectrum,
    };
    plan.attach.first_size_counts = 3.0 * a_counts;
    plan.attach.first_pixels = pixels(3.0 * a_counts);
    // A tracking segment of two lattice constants: on measured images one of a lattice
    // constant recognises its feature in a quarter of the places only (HOPG terrace).
    plan.attach.segment_size_counts = 2.0 * a_counts;
    plan.attach.segment_pixels = pixels(2.0 * a_counts);
    plan.aperture.size_counts = 4.0 * a_counts;
    plan.aperture.pixels = pixels(4.0 * a_counts);
    plan.motion.pixel_dwell_s = forward.pixel_time_s() * step / counts_per_px;
    plan.motion.move_speed_counts_per_s = 20.0 * a_counts;
    plan.motion.settle_s = 0.0;
    plan.pause.base_s = 0.0;
    plan.pause.per_count_s = 0.0;
    plan.pause.max_s = 1.0;
    plan.standard = standard;
    // Margin: half the aperture (2 a) and a quarter lattice constant for the attachment's
    // wandering (the first attachment's window, 1.5 a, lies inside).
    let caps = backend.capabilities();
    let width = (caps.field_max.x - caps.field_min.x).value();
    let height = (caps.field_max.y - caps.field_min.y).value();
    let n = f64::from(options.nodes_per_side - 1);
    // The roomy margin when the nodes stay at least a lattice constant apart with it.
    let roomy = width.min(height) - 2.0 * ROOMY_MARGIN_LATTICE * a_counts >= n * a_counts;
    let margin_lattice = if roomy {
        ROOMY_MARGIN_LATTICE
    } else {
        MARGIN_LATTICE
    };
    let margin = (margin_lattice * a_counts).ceil();
    let span = width.min(height) - 2.0 * margin;
    let step_counts = (span / n).floor();
    if step_counts.is_nan() || step_counts < 1.0 {
        let a_nm = plan.standard.lattice_constant_nm;
        return Err(VirtualInputError::NetTooLarge {
            path: image.to_path_buf(),
            detail: format!(
                "a net of {0} × {0} nodes with its margins of {MARGIN_LATTICE} lattice constants \
                 needs an image of more than {1:.1} nm ({2:.1} lattice constants of {a_nm} nm) \
                 on its shorter side; this one is {3:.1} nm",
                options.nodes_per_side,
                2.0 * MARGIN_LATTICE * a_nm,
                2.0 * MARGIN_LATTICE,
                width.min(height) * plan.standard.nominal_nm_per_count
            ),
        });
    }
    plan.net.margin_counts = margin as i64;
    plan.net.step_counts = step_counts as i64;
    plan.validate().map_err(|e| VirtualInputError::Parameter {
        path: image.to_path_buf(),
        detail: format!("the plan built for this image is invalid: {e}"),
    })?;
    Ok(plan)
}

pub use spm_modelcheck::{
    CellLattice, MIN_PART_FEATURES, PartLattice, ROBUST_CELL_RESIDUAL_FACTOR,
};

/// The lattice of the standard measured on an image file, whole and in a `grid` × `grid`
/// partition.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LatticeSurvey {
    /// The file.
    pub file: PathBuf,
    /// The standard.
    pub standard: &'static str,
    /// Its lattice constant, nm.
    pub lattice_constant_nm: f64,
    /// The whole image.
    pub whole: Option<PartLattice>,
    /// The cells.
    pub cells: Vec<CellLattice>,
}

/// The narrowest cell of the validation's grid over a stored image, lattice constants
/// ([`stored_lattice_check`]): about 29 sites of a triangular lattice. The lattice fit needs
/// [`MIN_PART_FEATURES`], and the features within a lattice constant of the data's edge are
/// not extracted: Si_7x7_051 (7.4 lattice constants) corrected finds no lattice in any cell of
/// 2 × 2 (23 features over the whole image), so it is measured whole.
pub const MIN_CELL_SIDE_LATTICE: f64 = 5.0;

/// The stored image a virtual run calibrated on, for the validation's lattice check
/// ([`stored_lattice_check`]).
#[derive(Debug, Clone, PartialEq)]
pub struct StoredStandard {
    /// The image file.
    pub image: PathBuf,
    /// Its height channel (`None`: Z, Topography, or the first in metres).
    pub channel: Option<String>,
    /// The standard it shows.
    pub standard: StandardName,
}

impl StoredStandard {
    /// The stored image of a job's virtual backend, when the plan's standard is one the
    /// survey knows: named (`[plan.standard] name`), or, in a plan that predates the name,
    /// recognised by its lattice constant.
    #[must_use]
    pub fn of_job(backend: &VirtualBackend, plan: &PlanConfig) -> Option<Self> {
        let a = plan.standard.lattice_constant_nm;
        let standard = plan.standard.name.or_else(|| {
            StandardName::ALL
                .into_iter()
                .find(|s| (s.lattice_constant_nm() - a).abs() <= 1e-6 * a)
        })?;
        Some(Self {
            image: backend.image.clone(),
            channel: backend.channel.clone(),
            standard,
        })
    }
}

/// The validation's lattice check of a run on a stored image: a counter-scanned pair taken
/// from it would resample the same frozen pixels, so the image itself is corrected as
/// `spmcal correct` corrects it with the run's calibration `set` (the nominal sensitivity of
/// the plan; beyond the calibrated region too, since the net keeps a margin) and its lattice
/// measured in each cell of a `lattice_places_per_side`² grid before and after
/// ([`spm_modelcheck::survey_channel`], what `spmcal lattice` reports), judged against the
/// plan's thresholds ([`spm_evaluation::validation::lattice_check_of_cells`]).
///
/// # Errors
/// [`VirtualInputError`] when the image cannot be read or corrected.
pub fn stored_lattice_check(
    stored: &StoredStandard,
    set: &spm_correction::SurfaceSet,
    plan: &PlanConfig,
) -> Result<spm_evaluation::validation::LatticeCheck, VirtualInputError> {
    use spm_evaluation::validation::{PartFigures, SurveyCell};
    let path = stored.image.as_path();
    let nominal = plan.standard.nominal_nm_per_count;
    let file = spm_formats::read_any(path)?;
    let forward = height_channel(&file, path, stored.channel.as_deref())?;
    let (Some(pixel_x_nm), Some(pixel_y_nm)) = (forward.pixel_x_nm(), forward.pixel_y_nm()) else {
        return Err(VirtualInputError::Image {
            path: path.to_path_buf(),
            channel: forward.name().to_owned(),
            source: spm_virtual::ImageError::NoPixelSize,
        });
    };
    let size_nm = [
        forward.nx() as f64 * pixel_x_nm,
        forward.ny() as f64 * pixel_y_nm,
    ];
    // The plan's places per side, fewer on a small image: a cell at least
    // [`MIN_CELL_SIDE_LATTICE`] lattice constants wide, so that it holds the features a fit
    // needs (Si_7x7_051, 7.4 lattice constants: the whole image).
    let side_lattice = size_nm[0].min(size_nm[1]) / stored.standard.lattice_constant_nm();
    let grid = (plan.validation.lattice_places_per_side as usize)
        .min((side_lattice / MIN_CELL_SIDE_LATTICE).floor() as usize)
        .max(1);
    let spec = lattice_spec(stored.standard, path)?;
    let before = survey_of(&file, forward, &spec, grid, path)?;
    let options = spm_apply::ApplyOptions {
        nominal_nm_per_count: Some(nominal),
        allow_extrapolation: true,
        // The channel surveyed before, both its halves; its forward half is surveyed after.
        channels: spm_apply::ChannelSelection::Named(forward.name().to_owned()),
        ..spm_apply::ApplyOptions::default()
    };
    let corrected = spm_apply::correct_file(&file, set, &options).map_err(|e| {
        VirtualInputError::Parameter {
            path: path.to_path_buf(),
            detail: format!("correcting the stored image with the run's calibration: {e}"),
        }
    })?;
    // As `spmcal lattice` reads `spmcal correct`'s output: the corrected channel encoded as
    // the .gsf it writes, with its metadata, and read back (not under the raw file's header,
    // whose line time and scan direction describe the raw raster).
    let corrected_forward = corrected
        .channels
        .iter()
        .find(|c| c.direction() == spm_formats::Direction::Forward);
    let after = match corrected_forward {
        Some(channel) => {
            let extra: Vec<(&str, &str)> = corrected
                .metadata
                .iter()
                .map(|(k, v)| (k.as_str(), v.as_str()))
                .collect();
            let bytes = spm_formats::encode_gsf(channel, &extra)?;
            let written = spm_formats::read_bytes(&bytes, &path.with_extension("corrected.gsf"))?;
            match written.channels.first() {
                Some(channel) => survey_of(&written, channel, &spec, grid, path)?,
                None => (None, Vec::new()),
            }
        }
        None => (None, Vec::new()),
    };
    let figures = |c: Option<&spm_modelcheck::CellLattice>| {
        c.and_then(|c| c.lattice).map(|l| PartFigures {
            scale_x: l.scale_x,
            scale_y: l.scale_y,
            obliquity_deg: l.obliquity_deg,
        })
    };
    let (width, height) = (size_nm[0] / nominal, size_nm[1] / nominal);
    let cells: Vec<SurveyCell> = before
        .1
        .iter()
        .map(|b| {
            let centre = |k: usize, n: f64| ((k as f64 + 0.5) / grid as f64 - 0.5) * n;
            SurveyCell {
                place: format!("cell ({}, {})", b.column, b.row),
                // Row 0 is the display's top, +y.
                centre_counts: [centre(b.column, width), -centre(b.row, height)],
                uncorrected: figures(Some(b)),
                corrected: figures(
                    after
                        .1
                        .iter()
                        .find(|a| (a.column, a.row) == (b.column, b.row)),
                ),
            }
        })
        .collect();
    Ok(spm_evaluation::validation::lattice_check_of_cells(
        &cells,
        stored.standard.lattice_constant_nm(),
        (
            u32::try_from(forward.nx()).unwrap_or(u32::MAX),
            pixel_x_nm / nominal,
        ),
        set.dynamics.is_some(),
        &plan.validation,
    ))
}

/// The height channel of `file` (`wanted`, or Z, Topography, the first in metres), forward.
fn height_channel<'a>(
    file: &'a spm_formats::SpmFile,
    path: &Path,
    wanted: Option<&str>,
) -> Result<&'a spm_formats::Channel, VirtualInputError> {
    pick_channels(file, wanted)
        .map(|(forward, _)| forward)
        .ok_or_else(|| VirtualInputError::NoChannel {
            path: path.to_path_buf(),
            wanted: wanted
                .unwrap_or("Z (or Topography, or any in metres)")
                .to_owned(),
            available: file
                .channels
                .iter()
                .map(|c| c.name().to_owned())
                .collect::<Vec<_>>()
                .join(", "),
        })
}

/// The lattice model check's specification of a standard.
fn lattice_spec(
    standard: StandardName,
    path: &Path,
) -> Result<spm_modelcheck::LatticeSpec, VirtualInputError> {
    spm_modelcheck::LatticeSpec::parse(standard.as_str()).map_err(|e| {
        VirtualInputError::Parameter {
            path: path.to_path_buf(),
            detail: e.to_string(),
        }
    })
}

/// [`spm_modelcheck::survey_channel`] with its error named by the file.
fn survey_of(
    file: &spm_formats::SpmFile,
    channel: &spm_formats::Channel,
    spec: &spm_modelcheck::LatticeSpec,
    grid: usize,
    path: &Path,
) -> Result<(Option<PartLattice>, Vec<CellLattice>), VirtualInputError> {
    spm_modelcheck::survey_channel(file, channel, spec, grid).map_err(|e| match e {
        spm_modelcheck::SurveyError::NoPixelSize => VirtualInputError::Image {
            path: path.to_path_buf(),
            channel: channel.name().to_owned(),
            source: spm_virtual::ImageError::NoPixelSize,
        },
    })
}

/// Measures the lattice of `standard` on an image file, whole and in a `grid` × `grid`
/// partition, by spm-modelcheck's extraction and baseline fit (what `spmcal diagnose`
/// reports), on the height channel; pixels without data (a corrected image's corners) are
/// left out by the extraction ([`spm_modelcheck::survey_channel`]).
///
/// # Errors
/// [`VirtualInputError`] when the file cannot be read or has no height channel.
pub fn survey_lattice(
    path: &Path,
    standard: StandardName,
    channel: Option<&str>,
    grid: usize,
) -> Result<LatticeSurvey, VirtualInputError> {
    let a = standard.lattice_constant_nm();
    let file = spm_formats::read_any(path)?;
    let forward = height_channel(&file, path, channel)?;
    let spec = lattice_spec(standard, path)?;
    let (whole, cells) = survey_of(&file, forward, &spec, grid, path)?;
    Ok(LatticeSurvey {
        file: path.to_path_buf(),
        standard: standard.as_str(),
        lattice_constant_nm: a,
        whole,
        cells,
    })
}
