//! The calibration plan as typed configuration (TOML), its validation and typed errors.
//!
//! # Where the plan lives
//! A calibration job is one TOML document with a `[backend]` table (owned by the program that
//! builds the backend: `kind = "sim"` and the simulator's own table for the simulator) and a
//! `[plan]` table described here. [`PlanConfig::from_toml_str`] reads **only** the `[plan]`
//! table and ignores the others, which their owners parse and validate; inside `[plan]` every
//! table denies unknown fields. A plan can also stand alone in a `configs/plan-*.toml` file
//! holding just `[plan]` (e.g. `configs/plan-hopg-small.toml`), to be combined with a backend
//! by the caller.
//!
//! Every field has its unit in its name. There is no `Default`: a plan is always an explicit
//! choice, a file or [`PlanConfig::hopg_small_net`] (the named constructor used by tests).
//!
//! # Errors
//! [`ConfigError`] names the source (file), the 1-based line (and column for parse errors)
//! and the dotted field path, e.g. `plan.toml:14:1: field `plan.skipping.cycles`: must be ≥ 1`.

use crate::plan::{NetGeometry, PauseLaw, PlanError, ZLevel};
use serde::{Deserialize, Serialize};
use spm_hal::{Capabilities, Nanometres, Radians};
use std::path::Path;

/// Longest scanner id, bytes (it is stored with every record).
pub const MAX_SCANNER_ID_BYTES: usize = 128;
/// Most repeats of a plan.
pub const MAX_REPEATS: u32 = 10_000;
/// Most Z levels (or Y planes) of a net.
pub const MAX_LEVELS: usize = 10_000;
/// Largest coordinate, step, margin or size in counts (a 32-bit DAC).
pub const MAX_COUNTS: i64 = 1 << 31;
/// Largest coarse-stage position, steps.
pub const MAX_COARSE_STEPS: i64 = 100_000_000;
/// Most pixels per line or lines of one scan (instruments offer at most a few thousand).
pub const MAX_SCAN_PIXELS: u32 = 65_536;

/// The whole calibration plan (the `[plan]` table).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlanConfig {
    /// Identifier of the scanner being calibrated (stored with every CDB record).
    pub scanner_id: String,
    /// Number of repeated passes l over the net (paper Fig. 2 pos. 10), ≥ 1.
    pub repeats: u32,
    /// The calibration standard.
    pub standard: StandardConfig,
    /// The net of nodes.
    pub net: NetConfig,
    /// The pause after each node move.
    pub pause: PauseLaw,
    /// Scan and move parameters shared by all operations.
    pub motion: MotionConfig,
    /// Probe attachment.
    pub attach: AttachConfig,
    /// Aperture scan and LCS recognition.
    pub aperture: ApertureConfig,
    /// Skipping between LCS features (or counter-scanning, see `variant`).
    pub skipping: SkippingConfig,
    /// Drift tolerances (paper §2.6).
    pub drift: DriftConfig,
    /// Failure budgets.
    pub failures: FailureConfig,
    /// Which variant of the method (paper §6).
    pub variant: VariantConfig,
    /// Kz from monatomic steps searched near every node, and the LCS's level for the bowl
    /// (issue 15); absent = no vertical measurements (records carry no Kz).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub steps: Option<crate::vertical::StepSearchConfig>,
    /// The controller's tuning constants (fractions of the lattice or of a raster, counts of
    /// sightings). Optional in a plan file: absent, [`TuningConfig::RECOMMENDED`] is used and
    /// written back by [`PlanConfig::to_toml_string`], so a stored plan always states them.
    #[serde(default = "TuningConfig::recommended")]
    pub tuning: TuningConfig,
    /// The dynamics stage (`[dynamics]`, issue 23): absent = the defaults (on).
    #[serde(default)]
    pub dynamics: crate::dynamics::DynamicsConfig,
    /// The run's validation without an oracle (`[validation]`, issue 24): absent = the
    /// defaults (10 % of the nodes held out, the verdicts' thresholds).
    #[serde(default)]
    pub validation: crate::run_validation::RunValidationConfig,
    /// The lattice survey that gates LCS recognition (`[survey]`, issue 24): absent = the
    /// defaults (on, 3 × 3 places of 8 lattice constants).
    #[serde(default)]
    pub survey: crate::survey::SurveyConfig,
    /// What the run promises (`[targets]`, issue 27): absent = nothing declared, the exit
    /// code of `spmcal calibrate` does not depend on the figures.
    #[serde(
        default,
        skip_serializing_if = "crate::run_validation::RunTargets::is_empty"
    )]
    pub targets: crate::run_validation::RunTargets,
}

/// The controller's tuning constants: how features are told apart, paired and captured, and
/// how fast a drift the skipping monitor accepts. Every value is dimensionless or a count;
/// the defaults ([`TuningConfig::RECOMMENDED`]) are the values the method was validated with
/// (`docs/results/calibration.md`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TuningConfig {
    /// Smallest separation of two detected features, as a fraction of the lattice constant
    /// (default 0.5: neighbouring atoms are a lattice constant apart; noise maxima closer
    /// than half of it are one feature). In (0, 1].
    pub detection_separation_fraction: f64,
    /// The fastest drift the skipping monitor accepts moves a feature by this fraction of
    /// the tracking segment's side over one cycle (default 0.4: the feature stays inside
    /// the segment it is searched in). In (0, 0.5].
    pub monitor_drift_segment_fraction: f64,
    /// Radius within which a counter-scan pairs a direct and a counter sighting, fraction of
    /// the lattice constant (default 0.35: nearer to one's own atom than to the neighbour).
    /// In (0, 0.5).
    pub counter_match_radius_fraction: f64,
    /// A measured vector farther than this fraction of its length from the expected one
    /// caught another feature (default 0.35). In (0, 0.5).
    pub vector_match_tolerance_fraction: f64,
    /// Consecutive sightings whose drift is below the limit before the attachment counts as
    /// settled (default 3). ≥ 1.
    pub attach_settle_sightings: u32,
    /// Sightings per drift-velocity fit during the attachment (default 4). ≥ 2.
    pub attach_velocity_window: u32,
    /// A sighting within this fraction of the lattice constant of the prediction is the
    /// same feature during the attachment (default 0.4). In (0, 0.5].
    pub attach_capture_radius_fraction: f64,
}

impl TuningConfig {
    /// The values the method was validated with.
    pub const RECOMMENDED: Self = Self {
        detection_separation_fraction: 0.5,
        monitor_drift_segment_fraction: 0.4,
        counter_match_radius_fraction: 0.35,
        vector_match_tolerance_fraction: 0.35,
        attach_settle_sightings: 3,
        attach_velocity_window: 4,
        attach_capture_radius_fraction: 0.4,
    };

    /// [`TuningConfig::RECOMMENDED`] (for serde).
    #[must_use]
    pub fn recommended() -> Self {
        Self::RECOMMENDED
    }

    fn validate(&self) -> Result<(), ValidationError> {
        let fraction = |field: &str, v: f64, max: f64, max_inclusive: bool| {
            let ok = v.is_finite() && v > 0.0 && if max_inclusive { v <= max } else { v < max };
            if ok {
                Ok(())
            } else {
                Err(ValidationError::new(
                    format!("plan.tuning.{field}"),
                    format!(
                        "must be in (0, {max}{}, got {v}",
                        if max_inclusive { "]" } else { ")" }
                    ),
                ))
            }
        };
        fraction(
            "detection_separation_fraction",
            self.detection_separation_fraction,
            1.0,
            true,
        )?;
        fraction(
            "monitor_drift_segment_fraction",
            self.monitor_drift_segment_fraction,
            0.5,
            true,
        )?;
        fraction(
            "counter_match_radius_fraction",
            self.counter_match_radius_fraction,
            0.5,
            false,
        )?;
        fraction(
            "vector_match_tolerance_fraction",
            self.vector_match_tolerance_fraction,
            0.5,
            false,
        )?;
        fraction(
            "attach_capture_radius_fraction",
            self.attach_capture_radius_fraction,
            0.5,
            true,
        )?;
        if self.attach_settle_sightings < 1 {
            return Err(ValidationError::new(
                "plan.tuning.attach_settle_sightings",
                "must be at least 1",
            ));
        }
        if self.attach_velocity_window < 2 {
            return Err(ValidationError::new(
                "plan.tuning.attach_velocity_window",
                "must be at least 2 (a velocity needs two sightings)",
            ));
        }
        Ok(())
    }
}

/// The calibration standard (a crystal lattice and its steps).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StandardConfig {
    /// Which named standard this is (`"hopg"` or `"si7x7"`), optional: when given, the
    /// lattice constant and the feature polarity must be the named standard's
    /// ([`StandardName`]); absent (older plans), the fields below alone define the standard.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<StandardName>,
    /// Distance A–B (and A–C) of the LCS: the lattice constant, nm (HOPG: 0.2461).
    pub lattice_constant_nm: f64,
    /// Angle BAC of the LCS, degrees (HOPG triangular lattice: 60).
    pub lcs_angle_deg: f64,
    /// Features are hills (atoms) or pits (hollows).
    pub feature: FeaturePolarity,
    /// Expected scanner sensitivity, nm per count, used to predict features' positions in
    /// counts for LCS matching and to convert drift tolerances; the calibration measures the
    /// true one.
    pub nominal_nm_per_count: f64,
    /// Accepted relative deviation of LCS side lengths from the lattice constant (after
    /// conversion with the nominal sensitivity), e.g. 0.25.
    pub length_tolerance_fraction: f64,
    /// Accepted deviation of the LCS angle, degrees.
    pub angle_tolerance_deg: f64,
    /// Height of a monatomic step, nm (HOPG: 0.3354), for Kz: with a `[plan.steps]` table the
    /// controller searches a step near every node ([`crate::vertical`]); without one records
    /// carry no Kz (`kz_nm_per_count = None`).
    pub step_height_nm: Option<f64>,
}

/// The named calibration standards a plan can select.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StandardName {
    /// HOPG: the β atoms seen by STM, hills on a triangular lattice, a = 0.2461 nm.
    Hopg,
    /// Si(111)-7×7: the corner holes of the 7×7 cell, pits on a triangular lattice,
    /// a = 2.688 nm (7 × 0.384 nm).
    Si7x7,
}

impl StandardName {
    /// Every named standard.
    pub const ALL: [Self; 2] = [Self::Hopg, Self::Si7x7];

    /// The name as written in a plan (`hopg`, `si7x7`).
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Hopg => "hopg",
            Self::Si7x7 => "si7x7",
        }
    }

    /// The lattice constant, nm.
    #[must_use]
    pub fn lattice_constant_nm(self) -> f64 {
        match self {
            Self::Hopg => 0.2461,
            Self::Si7x7 => 2.688,
        }
    }

    /// Hills (HOPG atoms) or pits (7×7 corner holes).
    #[must_use]
    pub fn feature(self) -> FeaturePolarity {
        match self {
            Self::Hopg => FeaturePolarity::Hills,
            Self::Si7x7 => FeaturePolarity::Pits,
        }
    }

    /// Monatomic step height, nm (HOPG 0.3354, Si(111) 0.3135).
    #[must_use]
    pub fn step_height_nm(self) -> f64 {
        match self {
            Self::Hopg => 0.3354,
            Self::Si7x7 => 0.3135,
        }
    }

    /// The standard's `[plan.standard]` table with a nominal sensitivity (nm per count),
    /// the 60° LCS, and the given tolerances (`length_tolerance_fraction` in (0, 1),
    /// `angle_tolerance_deg` in degrees); no Kz (`step_height_nm` unset).
    #[must_use]
    pub fn standard(
        self,
        nominal_nm_per_count: f64,
        length_tolerance_fraction: f64,
        angle_tolerance_deg: f64,
    ) -> StandardConfig {
        StandardConfig {
            name: Some(self),
            lattice_constant_nm: self.lattice_constant_nm(),
            lcs_angle_deg: 60.0,
            feature: self.feature(),
            nominal_nm_per_count,
            length_tolerance_fraction,
            angle_tolerance_deg,
            step_height_nm: None,
        }
    }
}

impl std::str::FromStr for StandardName {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|n| n.as_str().eq_ignore_ascii_case(s))
            .ok_or_else(|| format!("unknown standard {s:?}: give hopg or si7x7"))
    }
}

impl StandardConfig {
    /// The lattice constant.
    pub fn lattice_constant(&self) -> Nanometres {
        Nanometres(self.lattice_constant_nm)
    }
    /// The LCS angle.
    pub fn lcs_angle(&self) -> Radians {
        Radians::from_degrees(self.lcs_angle_deg)
    }
}

/// Whether the standard's features are hills or pits.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FeaturePolarity {
    /// Features are local maxima (atoms).
    Hills,
    /// Features are local minima (hollows).
    Pits,
}

impl FeaturePolarity {
    /// The detector's polarity.
    #[must_use]
    pub fn polarity(self) -> spm_features::Polarity {
        match self {
            Self::Hills => spm_features::Polarity::Hill,
            Self::Pits => spm_features::Polarity::Pit,
        }
    }

    /// The name as written in a plan (`hills`, `pits`).
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Hills => "hills",
            Self::Pits => "pits",
        }
    }
}

/// How the net is laid out (paper Fig. 1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NetKind {
    /// Lateral x–y planes at fixed Z (Fig. 1a).
    LateralPlanes,
    /// Vertical x–z planes at fixed Y (Fig. 1b); needs `y_planes_counts`.
    VerticalPlanes,
}

/// The net of nodes. The nodes lie inside the scanner field shrunk by `margin_counts` on
/// every side, `step_counts` apart, the grid centred in that region.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetConfig {
    /// Lateral or vertical planes.
    pub kind: NetKind,
    /// Net step, counts (> 0).
    pub step_counts: i64,
    /// Distance kept from the field's edge, counts (≥ 0); must leave room for the first
    /// attachment and the aperture around every node.
    pub margin_counts: i64,
    /// The Z levels (one for a plain lateral calibration), in the first repeat's order.
    pub z_levels: Vec<ZLevel>,
    /// Fixed Y positions of vertical planes, counts (vertical planes only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y_planes_counts: Option<Vec<i64>>,
}

impl NetConfig {
    /// The net geometry inside the field of `capabilities`.
    ///
    /// # Errors
    /// [`PlanError::Invalid`] when the margins leave no room or the fields are inconsistent.
    pub fn geometry(&self, capabilities: &Capabilities) -> Result<NetGeometry, PlanError> {
        let invalid = |field: &'static str, reason: String| PlanError::Invalid { field, reason };
        if self.step_counts <= 0 {
            return Err(invalid(
                "step_counts",
                format!("must be > 0, got {}", self.step_counts),
            ));
        }
        if self.margin_counts < 0 {
            return Err(invalid("margin_counts", "must be >= 0".into()));
        }
        let span = |lo: f64, hi: f64| -> Result<(i64, i64), PlanError> {
            let lo = lo.ceil() as i64 + self.margin_counts;
            let hi = hi.floor() as i64 - self.margin_counts;
            if hi < lo {
                return Err(invalid(
                    "margin_counts",
                    format!(
                        "leaves no room in the field (margin {})",
                        self.margin_counts
                    ),
                ));
            }
            // Centre the grid: leftover space split evenly.
            let n = (hi - lo) / self.step_counts;
            let leftover = (hi - lo) - n * self.step_counts;
            let start = lo + leftover / 2;
            Ok((start, start + n * self.step_counts))
        };
        crate::vertical::check_coarse_levels(&self.z_levels, capabilities)?;
        let (x0, x1) = span(
            capabilities.field_min.x.value(),
            capabilities.field_max.x.value(),
        )?;
        match self.kind {
            NetKind::LateralPlanes => {
                if self.y_planes_counts.is_some() {
                    return Err(invalid(
                        "y_planes_counts",
                        "only for kind = \"vertical_planes\"".into(),
                    ));
                }
                let (y0, y1) = span(
                    capabilities.field_min.y.value(),
                    capabilities.field_max.y.value(),
                )?;
                Ok(NetGeometry::LateralPlanes {
                    x_min_counts: x0,
                    x_max_counts: x1,
                    y_min_counts: y0,
                    y_max_counts: y1,
                    step_counts: self.step_counts,
                    z_planes: self.z_levels.clone(),
                })
            }
            NetKind::VerticalPlanes => {
                let ys = self.y_planes_counts.clone().ok_or_else(|| {
                    invalid(
                        "y_planes_counts",
                        "is required for kind = \"vertical_planes\"".into(),
                    )
                })?;
                Ok(NetGeometry::VerticalPlanes {
                    x_min_counts: x0,
                    x_max_counts: x1,
                    step_counts: self.step_counts,
                    y_planes_counts: ys,
                    z_levels: self.z_levels.clone(),
                })
            }
        }
    }
}

/// Scan and move parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionConfig {
    /// Pixel dwell of every scan (attach, aperture, segments), seconds (> 0).
    pub pixel_dwell_s: f64,
    /// Speed of lateral moves, counts per second (> 0).
    pub move_speed_counts_per_s: f64,
    /// Settle time after a short move (feature to feature), seconds (≥ 0).
    pub settle_s: f64,
}

/// Probe attachment (paper §2.1.1).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AttachConfig {
    /// Side of the first attachment scan, counts: surely holds a feature wherever it lies
    /// (≥ ~2 lattice constants).
    pub first_size_counts: f64,
    /// Pixels per side of the first attachment scan (≥ 4).
    pub first_pixels: u32,
    /// Side of a segment (a scan enclosing one feature), counts.
    pub segment_size_counts: f64,
    /// Pixels per side of a segment (≥ 4).
    pub segment_pixels: u32,
    /// Attachments at most while waiting for the creep after a node move to die out.
    pub max_attachments: u32,
    /// Omit the pause and attachment (paper §2.1.3: possible when the net step is comparable
    /// with the skipping distance; the aperture then acts as the attachment).
    pub skip: bool,
}

/// The aperture scan (paper §2.1.2).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ApertureConfig {
    /// Side of the aperture, counts: encloses at least one LCS around the captured feature.
    pub size_counts: f64,
    /// Pixels per side (≥ 8).
    pub pixels: u32,
}

/// Skipping between the LCS features (paper §2.1.3).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SkippingConfig {
    /// Kept skipping cycles per vector (≥ 1; the paper advises against many).
    pub cycles: u32,
    /// Idle cycles inserted after a spoiled one (paper §2.6), ≥ 1.
    pub idle_cycles: u32,
    /// Restarts of a vector's skipping allowed before the node is redone.
    pub max_restarts: u32,
}

/// Drift tolerances (paper §2.1.1 and §2.6), in nm/s, converted to counts/s with the nominal
/// sensitivity.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriftConfig {
    /// Largest |drift velocity| at which measuring starts after the attachments (the
    /// microscope's typical post-warm-up drift), nm/s.
    pub max_speed_nm_per_s: f64,
    /// Largest change of the drift velocity within a skipping cycle (or between consecutive
    /// cycles) before the cycle is declared spoiled, nm/s.
    pub max_change_nm_per_s: f64,
}

/// Failure budgets.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FailureConfig {
    /// Attempts at a node (a restart from the pause counts as one) before it is given up.
    pub max_attempts_per_node: u32,
    /// Transient backend errors (timeout, communication, feedback lost) retried per node
    /// before it is given up.
    pub transient_retries_per_node: u32,
}

/// The method's variant (paper §6).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VariantConfig {
    /// Attach to feature A (Fig. 3a) or to the LCS gravity centre (Fig. 3b).
    pub attach_to: AttachTarget,
    /// Skip to the LCS's B and C only, or to every neighbour of A in the aperture that forms
    /// an LCS with it (more vectors, least squares).
    pub neighbours: NeighbourSet,
    /// Additionally skip B↔C (redundant vector, least squares).
    pub bc_redundancy: bool,
    /// Measure the vectors by skipping, or by counter-scanning the aperture.
    pub measurement: MeasurementMethod,
}

/// Attachment target (paper Fig. 3).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AttachTarget {
    /// The feature nearest the node (Fig. 3a).
    FeatureA,
    /// The LCS nearest the node (Fig. 3b): no separate feature attachment; the aperture is
    /// scanned around the node itself, A is the feature nearest the node, and the LCCs are
    /// associated with the LCS's gravity centre. Faster (one scan fewer per node), for nets
    /// whose step is much larger than the LCS.
    LcsCentre,
}

/// Which neighbours of A are measured.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NeighbourSet {
    /// B and C of the LCS.
    Lcs,
    /// Every nearest neighbour of A found in the aperture.
    AllInAperture,
    /// Every feature of the aperture that sits on a site of A's lattice as the recognised
    /// LCS spans it (nearest neighbours and the farther shells, √3·a and 2·a in an aperture
    /// of 4 lattice constants), each named by its lattice indices through the LCS. A longer
    /// vector is measured to the same absolute precision, so its relative error is smaller;
    /// for stored images, whose noise is frozen (virtual mode).
    LatticeInAperture,
}

/// How drift-free vectors are measured.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MeasurementMethod {
    /// Skipping A↔B, A↔C with half-sums (drift-insensitive, the default of the paper).
    Skipping,
    /// Direct and counter scans of the aperture (paper §6; faster, less precise).
    CounterScan,
}

pub use spm_config::{ConfigError, ValidationError};

/// The document: only `[plan]` is read; other tables are ignored (their owners parse them).
#[derive(Deserialize)]
struct Document {
    plan: PlanConfig,
}

impl PlanConfig {
    /// Parses the `[plan]` table of a TOML document and validates it; `source_name` (a file
    /// name) labels errors.
    ///
    /// # Errors
    /// [`ConfigError::Parse`] or [`ConfigError::Invalid`] naming the line and field.
    pub fn from_toml_str(text: &str, source_name: &str) -> Result<Self, ConfigError> {
        let doc: Document = spm_config::parse_toml(text, source_name)?;
        doc.plan
            .validate()
            .map_err(|v| ConfigError::invalid(text, source_name, v))?;
        Ok(doc.plan)
    }

    /// Reads a file and parses its `[plan]` table.
    ///
    /// # Errors
    /// [`ConfigError::Io`] and as [`PlanConfig::from_toml_str`].
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        let path = path.as_ref();
        let text = spm_config::read_config_file(path)?;
        Self::from_toml_str(&text, &path.display().to_string())
    }

    /// The plan as a TOML document with a `[plan]` table.
    ///
    /// # Errors
    /// When serialisation fails (not expected for valid plans).
    pub fn to_toml_string(&self) -> Result<String, toml::ser::Error> {
        #[derive(Serialize)]
        struct Out<'a> {
            plan: &'a PlanConfig,
        }
        toml::to_string(&Out { plan: self })
    }

    /// Semantic validation: finite and positive numbers, sizes and counts in range.
    ///
    /// # Errors
    /// The first invalid field.
    pub fn validate(&self) -> Result<(), ValidationError> {
        self.tuning.validate()?;
        self.dynamics
            .validate()
            .map_err(|(field, reason)| ValidationError {
                field: format!("plan.{field}"),
                reason,
            })?;
        for check in [self.validation.validate(), self.survey.validate()] {
            check.map_err(|(field, reason)| ValidationError {
                field: format!("plan.{field}"),
                reason,
            })?;
        }
        self.targets
            .validate()
            .map_err(|(field, reason)| ValidationError {
                field: format!("plan.{field}"),
                reason,
            })?;
        let v = spm_config::RangeChecker::new("plan.");
        self.validate_identity_and_standard(&v)?;
        self.validate_net(&v)?;
        self.validate_scans(&v)?;
        Ok(())
    }

    /// The scanner id, the repeats, the standard and the step search.
    fn validate_identity_and_standard(
        &self,
        v: &spm_config::RangeChecker<'_>,
    ) -> Result<(), ValidationError> {
        if self.scanner_id.trim().is_empty() {
            return v.fail("scanner_id", "must not be empty");
        }
        if self.scanner_id.len() > MAX_SCANNER_ID_BYTES {
            return v.fail(
                "scanner_id",
                format!(
                    "is {} bytes long; at most {MAX_SCANNER_ID_BYTES}",
                    self.scanner_id.len()
                ),
            );
        }
        if self.scanner_id.chars().any(char::is_control) {
            return v.fail("scanner_id", "must not contain control characters");
        }
        v.count("repeats", self.repeats, 1, MAX_REPEATS)?;
        let s = &self.standard;
        v.range_positive(
            "standard.lattice_constant_nm",
            s.lattice_constant_nm,
            0.05,
            1e4,
        )?;
        if !(s.lcs_angle_deg.is_finite() && s.lcs_angle_deg > 0.0 && s.lcs_angle_deg < 180.0) {
            return v.fail(
                "standard.lcs_angle_deg",
                format!("must be in (0, 180), got {}", s.lcs_angle_deg),
            );
        }
        v.range_positive(
            "standard.nominal_nm_per_count",
            s.nominal_nm_per_count,
            1e-6,
            100.0,
        )?;
        if !(s.length_tolerance_fraction.is_finite()
            && s.length_tolerance_fraction > 0.0
            && s.length_tolerance_fraction < 1.0)
        {
            return v.fail(
                "standard.length_tolerance_fraction",
                format!("must be in (0, 1), got {}", s.length_tolerance_fraction),
            );
        }
        v.range_positive(
            "standard.angle_tolerance_deg",
            s.angle_tolerance_deg,
            1e-3,
            60.0,
        )?;
        if let Some(name) = s.name {
            let a = name.lattice_constant_nm();
            if (s.lattice_constant_nm - a).abs() > 1e-3 * a {
                return v.fail(
                    "standard.lattice_constant_nm",
                    format!(
                        "is {} nm, but the standard named {:?} has {a} nm",
                        s.lattice_constant_nm,
                        name.as_str()
                    ),
                );
            }
            if s.feature != name.feature() {
                return v.fail(
                    "standard.feature",
                    format!(
                        "the standard named {:?} has {:?} features",
                        name.as_str(),
                        name.feature()
                    ),
                );
            }
        }
        if let Some(steps) = &self.steps {
            if s.step_height_nm.is_none() {
                return v.fail(
                    "standard.step_height_nm",
                    "is required when [plan.steps] searches steps for Kz",
                );
            }
            if let Err((field, reason)) = steps.check() {
                return v.fail(&field, reason);
            }
        }
        if let Some(h) = s.step_height_nm {
            v.range_positive("standard.step_height_nm", h, 1e-3, 100.0)?;
        }
        Ok(())
    }

    /// The net of nodes and the pause law.
    fn validate_net(&self, v: &spm_config::RangeChecker<'_>) -> Result<(), ValidationError> {
        let n = &self.net;
        v.count("net.step_counts", n.step_counts, 1, MAX_COUNTS)?;
        v.count("net.margin_counts", n.margin_counts, 0, MAX_COUNTS)?;
        if n.z_levels.is_empty() {
            return v.fail("net.z_levels", "needs at least one level");
        }
        if n.z_levels.len() > MAX_LEVELS {
            return v.fail(
                "net.z_levels",
                format!("has {} levels; at most {MAX_LEVELS}", n.z_levels.len()),
            );
        }
        for level in &n.z_levels {
            v.count(
                "net.z_levels.nominal_z_counts",
                level.nominal_z_counts,
                -MAX_COUNTS,
                MAX_COUNTS,
            )?;
            if let Some(steps) = level.coarse_steps {
                v.count(
                    "net.z_levels.coarse_steps",
                    steps,
                    -MAX_COARSE_STEPS,
                    MAX_COARSE_STEPS,
                )?;
            }
        }
        match (n.kind, &n.y_planes_counts) {
            (NetKind::VerticalPlanes, None) => {
                return v.fail("net.y_planes_counts", "is required for vertical planes");
            }
            (NetKind::VerticalPlanes, Some(ys)) if ys.is_empty() => {
                return v.fail("net.y_planes_counts", "needs at least one plane");
            }
            (NetKind::VerticalPlanes, Some(ys)) if ys.len() > MAX_LEVELS => {
                return v.fail(
                    "net.y_planes_counts",
                    format!("has {} planes; at most {MAX_LEVELS}", ys.len()),
                );
            }
            (NetKind::LateralPlanes, Some(_)) => {
                return v.fail(
                    "net.y_planes_counts",
                    "is only for kind = \"vertical_planes\"",
                );
            }
            _ => {}
        }
        if let Some(ys) = &n.y_planes_counts {
            for y in ys {
                v.count("net.y_planes_counts", *y, -MAX_COUNTS, MAX_COUNTS)?;
            }
        }
        if let Err(PlanError::Invalid { field, reason }) = self.pause.validate() {
            return v.fail(&format!("pause.{field}"), reason);
        }
        Ok(())
    }

    /// Motion, attachment, aperture, skipping, drift limits and the failure budget.
    fn validate_scans(&self, v: &spm_config::RangeChecker<'_>) -> Result<(), ValidationError> {
        let s = &self.standard;
        let m = &self.motion;
        v.range_positive("motion.pixel_dwell_s", m.pixel_dwell_s, 1e-9, 10.0)?;
        v.range_positive(
            "motion.move_speed_counts_per_s",
            m.move_speed_counts_per_s,
            1e-3,
            1e9,
        )?;
        v.range("motion.settle_s", m.settle_s, 0.0, 3600.0)?;
        let a = &self.attach;
        v.range_positive(
            "attach.first_size_counts",
            a.first_size_counts,
            1e-3,
            MAX_COUNTS as f64,
        )?;
        v.count("attach.first_pixels", a.first_pixels, 4, MAX_SCAN_PIXELS)?;
        v.range_positive(
            "attach.segment_size_counts",
            a.segment_size_counts,
            1e-3,
            MAX_COUNTS as f64,
        )?;
        v.count(
            "attach.segment_pixels",
            a.segment_pixels,
            4,
            MAX_SCAN_PIXELS,
        )?;
        v.count("attach.max_attachments", a.max_attachments, 1, 100_000)?;
        v.range_positive(
            "aperture.size_counts",
            self.aperture.size_counts,
            1e-3,
            MAX_COUNTS as f64,
        )?;
        v.count("aperture.pixels", self.aperture.pixels, 8, MAX_SCAN_PIXELS)?;
        let nominal_lattice_counts = s.lattice_constant_nm / s.nominal_nm_per_count;
        if self.aperture.size_counts < 2.0 * nominal_lattice_counts {
            return v.fail(
                "aperture.size_counts",
                format!(
                    "must enclose an LCS: at least 2 lattice constants ({:.0} counts at the nominal sensitivity)",
                    2.0 * nominal_lattice_counts
                ),
            );
        }
        v.count("skipping.cycles", self.skipping.cycles, 1, 100_000)?;
        v.count(
            "skipping.idle_cycles",
            self.skipping.idle_cycles,
            1,
            100_000,
        )?;
        v.count(
            "skipping.max_restarts",
            self.skipping.max_restarts,
            0,
            10_000,
        )?;
        v.range_positive(
            "drift.max_speed_nm_per_s",
            self.drift.max_speed_nm_per_s,
            1e-9,
            1e3,
        )?;
        v.range_positive(
            "drift.max_change_nm_per_s",
            self.drift.max_change_nm_per_s,
            1e-9,
            1e3,
        )?;
        v.count(
            "failures.max_attempts_per_node",
            self.failures.max_attempts_per_node,
            1,
            1000,
        )?;
        v.count(
            "failures.transient_retries_per_node",
            self.failures.transient_retries_per_node,
            0,
            10_000,
        )?;
        Ok(())
    }

    /// A small HOPG plan for a 16-bit scanner of about 0.02 nm/count (the simulator's
    /// `room_temperature_tube` and `ideal` scenarios): a 3×3 lateral net (step 20000 counts,
    /// margin 8000), one Z level, 2 kept skipping cycles per vector, the skipping variant of
    /// Fig. 3a. Parsed from `scenarios/plan-hopg-small.toml` (`configs/plan-hopg-small.toml`).
    pub fn hopg_small_net() -> Self {
        // The text is part of the program; the crate's tests parse it.
        #[allow(clippy::expect_used)]
        Self::from_toml_str(
            include_str!("../scenarios/plan-hopg-small.toml"),
            "plan-hopg-small.toml",
        )
        .expect("the shipped plan parses and validates")
    }
}

/// The 1-based line of a dotted field (`plan.skipping.cycles`) in a TOML text: the key's
/// line, else the line of the deepest table of the path that is written.
#[must_use]
pub fn locate_field_line(text: &str, field: &str) -> Option<usize> {
    spm_config::TomlLocator::new(text).line_of(field)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn the_named_constructor_round_trips_through_toml() {
        let plan = PlanConfig::hopg_small_net();
        plan.validate().unwrap();
        let text = plan.to_toml_string().unwrap();
        let back = PlanConfig::from_toml_str(&text, "mem.toml").unwrap();
        assert_eq!(plan, back);
    }

    #[test]
    fn a_named_standard_is_selectable_and_checked_and_old_plans_stay_valid() {
        let old = PlanConfig::hopg_small_net();
        assert_eq!(old.standard.name, None);
        let text = old.to_toml_string().unwrap();
        assert!(!text.contains("name ="), "{text}");
        let si = text
            .replace(
                "lattice_constant_nm = 0.2461",
                "name = \"si7x7\"\nlattice_constant_nm = 2.688",
            )
            .replace("feature = \"hills\"", "feature = \"pits\"")
            // The same lattice in counts: ten times the lattice, ten times the nm per count.
            .replace(
                "nominal_nm_per_count = 0.02",
                "nominal_nm_per_count = 0.2184",
            );
        let plan = PlanConfig::from_toml_str(&si, "si.toml").unwrap();
        assert_eq!(plan.standard.name, Some(StandardName::Si7x7));
        assert_eq!(
            plan.standard,
            StandardName::Si7x7.standard(
                plan.standard.nominal_nm_per_count,
                plan.standard.length_tolerance_fraction,
                plan.standard.angle_tolerance_deg
            )
        );
        // A name contradicting the lattice or the polarity is refused with its line.
        let wrong = si.replace("feature = \"pits\"", "feature = \"hills\"");
        let message = PlanConfig::from_toml_str(&wrong, "si.toml")
            .unwrap_err()
            .to_string();
        assert!(message.contains("plan.standard.feature"), "{message}");
        let wrong = si.replace(
            "lattice_constant_nm = 2.688",
            "lattice_constant_nm = 0.2461",
        );
        let message = PlanConfig::from_toml_str(&wrong, "si.toml")
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("plan.standard.lattice_constant_nm"),
            "{message}"
        );
        assert_eq!("SI7x7".parse::<StandardName>(), Ok(StandardName::Si7x7));
        assert!("gold".parse::<StandardName>().is_err());
    }

    #[test]
    fn other_tables_are_ignored_and_unknown_plan_fields_are_named_with_their_line() {
        let mut text = "[backend]\nkind = \"sim\"\nanything = 3\n\n".to_owned();
        text.push_str(&PlanConfig::hopg_small_net().to_toml_string().unwrap());
        PlanConfig::from_toml_str(&text, "job.toml").unwrap();
        let bad = text.replace("idle_cycles = 1", "idle_cycles = 1\nidel = 2");
        let e = PlanConfig::from_toml_str(&bad, "job.toml").unwrap_err();
        let message = e.to_string();
        assert!(message.starts_with("job.toml:"), "{message}");
        assert_eq!(e.field(), Some("plan.skipping.idel"), "{message}");
        let line = bad.lines().position(|l| l.starts_with("idel")).unwrap() + 1;
        assert_eq!(e.line(), Some(line), "{message}");
    }

    #[test]
    fn invalid_values_name_field_and_line() {
        let text = PlanConfig::hopg_small_net()
            .to_toml_string()
            .unwrap()
            .replace("cycles = 2", "cycles = 0");
        let e = PlanConfig::from_toml_str(&text, "p.toml").unwrap_err();
        assert_eq!(e.field(), Some("plan.skipping.cycles"));
        let line = text.lines().position(|l| l == "cycles = 0").unwrap() + 1;
        assert_eq!(e.line(), Some(line));
        assert!(e.to_string().contains("p.toml:"));
        let wrong_type = PlanConfig::hopg_small_net()
            .to_toml_string()
            .unwrap()
            .replace("repeats = 1", "repeats = \"two\"");
        let e = PlanConfig::from_toml_str(&wrong_type, "p.toml").unwrap_err();
        assert_eq!(e.field(), Some("plan.repeats"), "{e}");
    }

    /// Issue 27: `[plan.targets]` is read, round-trips through the written plan, names a bad
    /// value's field and line, and refuses unknown fields; absent, nothing is declared.
    #[test]
    fn targets_are_declared_checked_and_written_back() {
        let plain = PlanConfig::hopg_small_net();
        assert!(plain.targets.is_empty());
        assert!(!plain.to_toml_string().unwrap().contains("targets"));
        let text = format!(
            "{}\n[plan.targets]\ndistributed_over_lumped_rms_max = 0.1\nvalidation_pass = true\n",
            plain.to_toml_string().unwrap()
        );
        let plan = PlanConfig::from_toml_str(&text, "p.toml").unwrap();
        assert_eq!(plan.targets.distributed_over_lumped_rms_max, Some(0.1));
        assert!(plan.targets.validation_pass);
        let again = PlanConfig::from_toml_str(&plan.to_toml_string().unwrap(), "q.toml").unwrap();
        assert_eq!(again, plan);
        let bad = text.replace("rms_max = 0.1", "rms_max = -1.0");
        let e = PlanConfig::from_toml_str(&bad, "p.toml").unwrap_err();
        assert_eq!(
            e.field(),
            Some("plan.targets.distributed_over_lumped_rms_max"),
            "{e}"
        );
        let line = bad.lines().position(|l| l.ends_with("= -1.0")).unwrap() + 1;
        assert_eq!(e.line(), Some(line), "{e}");
        let unknown = text.replace("validation_pass", "validation_passes");
        let e = PlanConfig::from_toml_str(&unknown, "p.toml").unwrap_err();
        assert_eq!(e.field(), Some("plan.targets.validation_passes"), "{e}");
    }
}
