//! Input types: feature observations, frames, the lattice, options, errors.

use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Direction of the fast-axis motion while a feature was scanned.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LineDirection {
    /// The probe moved towards +x (trace).
    Forward,
    /// The probe moved towards −x (retrace).
    Backward,
}

impl LineDirection {
    /// +1 for forward, −1 for backward.
    pub fn sign(self) -> f64 {
        match self {
            Self::Forward => 1.0,
            Self::Backward => -1.0,
        }
    }
}

/// One scanned frame (one raster; its forward and backward halves share it).
///
/// Positions of its features are commanded scanner positions expressed in
/// *nominal* nanometres (the instrument's own calibration), relative to the
/// frame centre, x along the fast axis, y along the slow axis (y up).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameInfo {
    /// A label for reports (file name and channel).
    pub label: String,
    /// Half the frame width along x, nominal nm (> 0).
    pub half_width_x_nm: f64,
    /// Half the frame height along y, nominal nm (> 0).
    pub half_height_y_nm: f64,
    /// Start of the frame, s, on the common time axis of all frames.
    pub start_time_s: f64,
    /// Duration of the frame, s.
    pub duration_s: f64,
    /// Fast-axis scan speed, nominal nm/s (line length / line time).
    pub fast_speed_nm_per_s: f64,
    /// Number of lines.
    pub lines: usize,
    /// Pixel pitch (x, y), nominal nm, when the features come from a sampled
    /// image (positions are then `(column − (nx − 1)/2)·pitch`): the sub-pixel
    /// phase of every feature is known and the localiser's pixel-locking bias
    /// can be modelled. `None` for feature lists without a pixel grid.
    #[serde(default)]
    pub pixel_nm: Option<[f64; 2]>,
}

/// One localised feature (atom, corner hole) in one half of one frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FeatureObservation {
    /// Commanded x, nominal nm from the frame centre.
    pub x_nm: f64,
    /// Commanded y, nominal nm from the frame centre (y up).
    pub y_nm: f64,
    /// Acquisition time of the feature centre, s, common time axis.
    pub time_s: f64,
    /// Fast-axis direction of the line that scanned it.
    pub direction: LineDirection,
    /// Index of the frame in [`FeatureSet::frames`].
    pub frame_index: usize,
    /// Acquisition line index within the frame (0 = first line measured).
    pub line_index: usize,
    /// One-sigma localisation uncertainty (per axis), nominal nm, when known.
    pub sigma_nm: Option<f64>,
    /// Fitted Gaussian width σ of the feature, nominal nm, when known: the
    /// feature spans about ±σ of lines, so its position averages whatever
    /// moved during those lines (a vibration is seen attenuated).
    #[serde(default)]
    pub width_nm: Option<f64>,
    /// Radius of the localiser's fit window, nominal nm, when known.
    #[serde(default)]
    pub fit_radius_nm: Option<f64>,
    /// `time_s` minus the time the nearest scan line passed the feature's column, s: the
    /// feature's centre lies between lines, which are sampled only at their own times (a
    /// vibration of several cycles per line has no phase "between" them). `None` when
    /// unknown (taken as 0).
    #[serde(default)]
    pub line_time_offset_s: Option<f64>,
}

/// Features of one or more frames, ready for [`crate::diagnose_features`].
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FeatureSet {
    /// The frames.
    pub frames: Vec<FrameInfo>,
    /// The features, any order.
    pub features: Vec<FeatureObservation>,
    /// Warnings from extraction (e.g. frames that do not look like one scan
    /// series); carried into the diagnosis.
    #[serde(default)]
    pub warnings: Vec<String>,
}

/// The sample's lattice: the known geometry the baseline model uses.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum LatticeSpec {
    /// Triangular (hexagonal) lattice of period `a_nm`.
    Hex {
        /// Period, nm.
        a_nm: f64,
    },
    /// Square lattice of period `a_nm`.
    Square {
        /// Period, nm.
        a_nm: f64,
    },
}

/// HOPG surface lattice constant (β atoms seen by STM), nm.
pub const HOPG_A_NM: f64 = 0.2461;
/// Si(111)-7×7 surface cell (corner-hole period), nm.
pub const SI7X7_A_NM: f64 = 2.688;

impl LatticeSpec {
    /// Parses `hopg`, `si7x7`, `hex:A_NM` or `square:A_NM`.
    pub fn parse(text: &str) -> Result<Self, ModelCheckError> {
        let bad = || ModelCheckError::BadLattice(text.to_owned());
        let t = text.trim().to_ascii_lowercase();
        let spec = match t.as_str() {
            "hopg" | "graphite" => Self::Hex { a_nm: HOPG_A_NM },
            "si7x7" | "si(111)-7x7" => Self::Hex { a_nm: SI7X7_A_NM },
            _ => {
                let (kind, value) = t.split_once(':').ok_or_else(bad)?;
                let a_nm: f64 = value.trim().parse().map_err(|_| bad())?;
                if !(a_nm.is_finite() && a_nm > 0.0) {
                    return Err(bad());
                }
                match kind.trim() {
                    "hex" => Self::Hex { a_nm },
                    "square" => Self::Square { a_nm },
                    _ => return Err(bad()),
                }
            }
        };
        Ok(spec)
    }

    /// The period, nm.
    pub fn a_nm(&self) -> f64 {
        match *self {
            Self::Hex { a_nm } | Self::Square { a_nm } => a_nm,
        }
    }

    /// Angle between the two basis vectors, rad (60° hexagonal, 90° square).
    pub fn basis_angle_rad(&self) -> f64 {
        match self {
            Self::Hex { .. } => PI / 3.0,
            Self::Square { .. } => PI / 2.0,
        }
    }
}

/// The eleven candidate effects of the library (DESIGN §13 vocabulary).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EffectKind {
    /// Drift velocity changing linearly in time (thermal warm-up, relaxation).
    DriftAcceleration,
    /// Logarithmic piezo creep after the move to the frame start.
    Creep,
    /// Piezo hysteresis: forward and backward lines follow different branches.
    Hysteresis,
    /// Static quadratic and cubic nonlinearity of each scanner axis.
    ScannerNonlinearity,
    /// Obliquity of the axes varying across the field.
    Nonorthogonality,
    /// Quadratic X⇔Y crosstalk (guidance bow).
    CrosstalkXy,
    /// Finite feedback bandwidth: features shift along the scan direction.
    FeedbackLag,
    /// Sinusoidal lateral vibration of tip against sample.
    PeriodicVibration,
    /// Sudden lateral jump of the image (tip apex change).
    TipChange,
    /// Backward lines displaced along the slow axis relative to forward ones: stepped
    /// (a constant offset) or ramped (the slow axis moving on through every line).
    Interlace,
    /// The fast axis driven by a sine in time (fast SPM, resonant scanning) while the
    /// pixels are equidistant in time.
    SinusoidalDrive,
}

impl EffectKind {
    /// All effects, in library order.
    pub const ALL: [EffectKind; 11] = [
        Self::DriftAcceleration,
        Self::Creep,
        Self::Hysteresis,
        Self::ScannerNonlinearity,
        Self::Nonorthogonality,
        Self::CrosstalkXy,
        Self::FeedbackLag,
        Self::PeriodicVibration,
        Self::TipChange,
        Self::Interlace,
        Self::SinusoidalDrive,
    ];

    /// The JSON name.
    pub fn name(self) -> &'static str {
        match self {
            Self::DriftAcceleration => "drift_acceleration",
            Self::Creep => "creep",
            Self::Hysteresis => "hysteresis",
            Self::ScannerNonlinearity => "scanner_nonlinearity",
            Self::Nonorthogonality => "nonorthogonality",
            Self::CrosstalkXy => "crosstalk_xy",
            Self::FeedbackLag => "feedback_lag",
            Self::PeriodicVibration => "periodic_vibration",
            Self::TipChange => "tip_change",
            Self::Interlace => "interlace",
            Self::SinusoidalDrive => "sinusoidal_drive",
        }
    }

    /// The effect with this JSON name.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|e| e.name() == name)
    }

    /// One sentence of physics, for reports.
    pub fn meaning(self) -> &'static str {
        match self {
            Self::DriftAcceleration => {
                "the tip-sample drift velocity changes in time (warm-up, thermal relaxation)"
            }
            Self::Creep => {
                "the piezo keeps moving logarithmically in time after the large move to the frame start"
            }
            Self::Hysteresis => {
                "the piezo follows different branches on trace and retrace; the separation vanishes at the line ends"
            }
            Self::ScannerNonlinearity => {
                "the piezo's displacement is not proportional to its voltage (quadratic and cubic terms per axis)"
            }
            Self::Nonorthogonality => {
                "the angle between the scanner axes changes across the field (obliquity gradient)"
            }
            Self::CrosstalkXy => {
                "motion of one axis bends the other quadratically (guidance bow, X⇔Y crosstalk)"
            }
            Self::FeedbackLag => {
                "the Z feedback lags, so features appear shifted along the scan direction by speed × time constant"
            }
            Self::PeriodicVibration => {
                "a sinusoidal lateral vibration of the tip against the sample"
            }
            Self::TipChange => {
                "the tip apex changed: the whole image jumps laterally at one moment"
            }
            Self::Interlace => {
                "backward lines sit at another slow-axis position than forward ones (slow-axis input stepped or ramped with the fast-axis direction, tube bending)"
            }
            Self::SinusoidalDrive => {
                "the fast axis follows a sine in time (resonant or fast-SPM drive) while the pixels are equidistant in time: features are stretched at the line centre and compressed towards the turnarounds"
            }
        }
    }
}

/// Settings of the diagnosis.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Options {
    /// Candidate effects searched (default: all eleven).
    pub effects: Vec<EffectKind>,
    /// ΔBIC (after the look-elsewhere penalty) an effect needs to be accepted.
    /// Default 10 ("very strong" evidence); calibrated by the null tests.
    pub evidence_threshold: f64,
    /// Most effects added. Default 4.
    pub max_findings: usize,
    /// Lag-1 autocorrelation z-score (ρ₁·√n of time-ordered residuals) above
    /// which the final residual is called structured. Default 4.
    pub structure_z_threshold: f64,
    /// Residuals beyond this many robust σ are outliers (mis-indexed or
    /// defective features) and are dropped before the search. Default 5.
    pub outlier_sigmas: f64,
    /// Relevance against the localisation uncertainty: an effect is reported
    /// only when the RMS displacement it explains is at least this fraction of
    /// the per-feature localisation uncertainty (robust σ of the residual,
    /// vector length). Default 0.5.
    pub relevance_sigma_fraction: f64,
    /// Relevance against the scale a user cares about: the RMS displacement an
    /// effect explains must also be at least this fraction of the lattice
    /// constant. Default 0.005 (half of the 1 % lattice-constant accuracy a
    /// scanner calibration aims at).
    pub relevance_lattice_fraction: f64,
}

impl Default for Options {
    fn default() -> Self {
        Self {
            effects: EffectKind::ALL.to_vec(),
            evidence_threshold: 10.0,
            max_findings: 4,
            structure_z_threshold: 4.0,
            outlier_sigmas: 5.0,
            relevance_sigma_fraction: 0.5,
            relevance_lattice_fraction: 0.005,
        }
    }
}

impl Options {
    /// These options without one effect in the search.
    pub fn without(mut self, effect: EffectKind) -> Self {
        self.effects.retain(|e| *e != effect);
        self
    }
}

/// Why a diagnosis could not be made.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ModelCheckError {
    /// The lattice text is not `hopg`, `si7x7`, `hex:A_NM` or `square:A_NM`.
    #[error("unknown lattice {0:?}: use hopg, si7x7, hex:A_NM or square:A_NM")]
    BadLattice(String),
    /// A file could not be read.
    #[error(transparent)]
    Format(#[from] spm_formats::FormatError),
    /// A file lacks what the diagnosis needs (size, timing, a height channel).
    #[error("{path}: {reason}")]
    MissingMetadata {
        /// The file.
        path: String,
        /// What is missing.
        reason: String,
    },
    /// Too few features to fit the model.
    #[error("too few usable features: {found} found, at least {needed} needed ({context})")]
    TooFewFeatures {
        /// Features found.
        found: usize,
        /// Features needed.
        needed: usize,
        /// Where.
        context: String,
    },
    /// Feature recognition failed.
    #[error("feature recognition failed on {label}: {source}")]
    Features {
        /// Which image.
        label: String,
        /// The error.
        source: spm_features::FeatureError,
    },
    /// The lattice could not be indexed (no two lattice directions).
    #[error("cannot index the lattice in {0}: fewer than two lattice directions found")]
    NoLattice(String),
    /// The features do not form the claimed lattice (white noise, adsorbates,
    /// a different lattice constant): the diagnosis refuses rather than
    /// reporting effects of a model that does not describe the data.
    #[error("the claimed lattice is not in these images ({context}): {reason}")]
    NotTheLattice {
        /// Which frame / direction.
        context: String,
        /// What failed.
        reason: String,
    },
    /// The claimed lattice is in the images, but its features cannot be localised
    /// (e.g. a cell pattern sampled too coarsely): the diagnosis refuses rather than
    /// fitting features that are not the lattice's.
    #[error("the lattice cannot be localised in {context}: {reason}")]
    Unresolved {
        /// Which image.
        context: String,
        /// Why.
        reason: String,
    },
    /// The input is inconsistent (bad frame index, non-finite values, …).
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// The least-squares problem has no solution.
    #[error("numerical failure: {0}")]
    Numerical(String),
    /// Writing the figure failed.
    #[error("cannot write the figure {path}: {reason}")]
    Plot {
        /// The PNG path.
        path: String,
        /// Why.
        reason: String,
    },
}
