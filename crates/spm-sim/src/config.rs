//! Typed simulator configuration (TOML), its validation and typed errors.
//!
//! Every field carries its unit in its name and documents its meaning and the
//! value used by [`SimConfig::room_temperature_tube`] ("typical") and by
//! [`SimConfig::ideal`]. There is no `Default`: a scenario is always an explicit
//! choice, either a shipped file (`configs/sim-hopg.toml`, `configs/sim-ideal.toml`)
//! or one of the named constructors, which equal those files.
//!
//! `SimConfig` is embeddable: a bigger configuration can hold it as a section
//! (e.g. `[backend.sim]`) and call [`SimConfig::validate_with_prefix`] with the
//! section's path so that errors name the full field path.

use serde::{Deserialize, Serialize};
use std::path::Path;

/// The whole simulated-microscope scenario.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimConfig {
    /// Master seed of every random process of the simulation (measurement
    /// noise, drift random walk and jumps, random faults each get their own
    /// stream derived from it). Same seed and config ⇒ bit-identical results.
    pub seed: u64,
    /// Ranges, limits and timing of the instrument.
    pub instrument: InstrumentConfig,
    /// The sample surface.
    pub surface: SurfaceConfig,
    /// The piezo scanner: static map, hysteresis, creep.
    pub scanner: ScannerConfig,
    /// Thermal drift of the tip relative to the sample.
    pub drift: DriftConfig,
    /// Measurement chain: noise, jitter, quantisation, feedback.
    pub measurement: MeasurementConfig,
    /// Randomly occurring faults (scheduled faults are added through the API).
    pub faults: FaultConfig,
}

/// Ranges, limits and timing of the instrument.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InstrumentConfig {
    /// Half range of the lateral DACs, counts; the field is
    /// `[-half, half - 1]` on both axes and the scanner polynomials are
    /// normalised by it. Typical (16-bit): 32768.
    pub lateral_half_range_counts: f64,
    /// Half range of the Z channel, counts; Z is `[-half, half - 1]`. Typical: 32768.
    pub z_half_range_counts: f64,
    /// Largest pixels per line of one scan. Typical: 4096.
    pub max_pixels_per_line: u32,
    /// Largest number of lines of one scan. Typical: 4096.
    pub max_lines: u32,
    /// Shortest pixel dwell, s. Typical: 1e-6.
    pub min_pixel_dwell_s: f64,
    /// Counter scans are supported. Typical: true.
    pub counter_scan: bool,
    /// Backward traces can be recorded. Typical: true.
    pub backward_trace: bool,
    /// Z-manipulator extension, nm, at which the feedback holds the tip on the
    /// surface's reference plane (z = 0) with the coarse stage at 0 steps.
    /// Typical: 40 (= 10000 counts at 0.004 nm/count).
    pub initial_z_extension_nm: f64,
    /// Instrument time consumed by every call (command round trip), s. Typical: 0.002; ideal: 0.
    pub call_overhead_s: f64,
    /// Interlace: how far the controller advances the slow-axis (y) command between the two
    /// halves of every scan line, counts, along the slow-scan direction (towards the next line:
    /// +y for direct rasters, −y for counter rasters). A controller that steps the slow axis in
    /// two parts per line (one at each turn-around) or ramps it through the line advances it by
    /// a fraction of the line pitch; the second half of every line then runs that far beyond
    /// the first, and its features appear displaced against the slow-scan direction. The command
    /// saturates at the field edge. Typical: 0; ideal: 0.
    pub retrace_slow_axis_advance_counts: f64,
    /// Interlace, ramped: how far the slow-axis (y) command moves on *through* every line
    /// pair (trace, then retrace), linearly in time, counts, along the slow-scan direction;
    /// each line pair starts where a stepped raster puts its line. A controller that ramps
    /// its slow axis continuously advances it by one line step per pair (the Nanonis Si 7×7
    /// files, docs/MODELCHECK.md): the features of the second half then sit half that
    /// further on, and each half's are sheared along the fast axis. Default 0: the slow axis
    /// stepped between lines.
    #[serde(default)]
    pub slow_axis_ramp_counts: f64,
    /// The coarse approach stage; absent = no software-driven stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coarse_z: Option<CoarseZConfig>,
}

/// A software-driven coarse approach stage.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CoarseZConfig {
    /// Smallest stage position, steps. Typical: -2000.
    pub min_steps: i64,
    /// Largest stage position, steps. Typical: 2000.
    pub max_steps: i64,
    /// Stage travel per step, nm (a step towards the sample shortens the Z
    /// extension the feedback needs by this much). Typical: 50.
    pub step_nm: f64,
    /// Time per step, s. Typical: 0.002.
    pub step_time_s: f64,
}

/// The sample surface (one TOML sub-table naming the kind, e.g. `[surface.hopg]`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SurfaceConfig {
    /// Highly oriented pyrolytic graphite.
    Hopg(HopgConfig),
    /// Si(111)-7×7 reconstruction, imaged by its corner holes.
    Si7x7(Si7x7Config),
    /// Generic hexagonal (triangular) lattice of Gaussian features.
    HexLattice(LatticeConfig),
    /// Generic square lattice of Gaussian features.
    SquareLattice(LatticeConfig),
}

/// HOPG: three-cosine β-atom model with monatomic steps, vacancies and rotated domains.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HopgConfig {
    /// Lattice constant of the β-atom triangular lattice, nm. Typical: 0.2461.
    pub lattice_constant_nm: f64,
    /// Peak-to-valley corrugation (β atom to hollow), nm; 0.02–0.2. Typical: 0.08.
    pub corrugation_nm: f64,
    /// Depth difference between hollow sites and α-atom sites relative to the
    /// three-cosine amplitude (0 = equal minima, dimensionless, 0–0.5). Typical: 0.3.
    pub hollow_asymmetry: f64,
    /// Orientation of the lattice in sample coordinates, degrees (a lattice
    /// vector points at this angle from +x). Typical: 12.
    pub rotation_deg: f64,
    /// Height of a monatomic step, nm. Typical: 0.3354.
    pub step_height_nm: f64,
    /// Straight step edges; crossing one in the direction of its left normal
    /// goes one layer up (and shifts the lattice registry, AB stacking).
    #[serde(default)]
    pub steps: Vec<StepEdgeConfig>,
    /// Fraction of β-atom sites that are vacant (0–0.2). Typical: 0.001.
    pub vacancy_fraction: f64,
    /// Circular grains whose lattice is rotated.
    #[serde(default)]
    pub domains: Vec<DomainConfig>,
}

/// A straight monatomic step edge.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StepEdgeConfig {
    /// A point of the edge, x, nm.
    pub point_x_nm: f64,
    /// A point of the edge, y, nm.
    pub point_y_nm: f64,
    /// Direction of the edge line, degrees from +x; the upper terrace is on its left.
    pub direction_deg: f64,
    /// Width of the edge's smooth transition, nm (> 0). Typical: 0.5.
    pub width_nm: f64,
}

/// A circular grain with a rotated lattice.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DomainConfig {
    /// Centre x, nm.
    pub centre_x_nm: f64,
    /// Centre y, nm.
    pub centre_y_nm: f64,
    /// Radius, nm (> 0).
    pub radius_nm: f64,
    /// Lattice rotation inside the grain relative to the surrounding lattice, degrees.
    pub rotation_deg: f64,
}

/// Si(111)-7×7: a triangular lattice of corner holes (pits).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Si7x7Config {
    /// Corner-hole lattice constant, nm. Typical: 2.688.
    pub lattice_constant_nm: f64,
    /// Corner-hole depth, nm (> 0). Typical: 0.1.
    pub corner_hole_depth_nm: f64,
    /// Corner-hole Gaussian radius (σ), nm (> 0). Typical: 0.35.
    pub corner_hole_sigma_nm: f64,
    /// Lattice orientation, degrees from +x. Typical: 0.
    pub rotation_deg: f64,
}

/// A generic lattice of Gaussian hills (height > 0) or pits (height < 0).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LatticeConfig {
    /// Lattice constant, nm (> 0).
    pub lattice_constant_nm: f64,
    /// Feature height, nm (≠ 0; negative = pits).
    pub feature_height_nm: f64,
    /// Feature Gaussian radius (σ), nm (> 0).
    pub feature_sigma_nm: f64,
    /// Lattice orientation, degrees from +x.
    pub rotation_deg: f64,
}

/// The piezo scanner. See the crate docs for the map and its physics.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScannerConfig {
    /// Small-signal X sensitivity at the field centre, nm/count. Typical: 0.02.
    pub sensitivity_x_nm_per_count: f64,
    /// Small-signal Y sensitivity at the field centre, nm/count. Typical: 0.0215.
    pub sensitivity_y_nm_per_count: f64,
    /// Z sensitivity, nm/count. Typical: 0.004.
    pub sensitivity_z_nm_per_count: f64,
    /// X static nonlinearity.
    pub nonlinearity_x: NonlinearityConfig,
    /// Y static nonlinearity.
    pub nonlinearity_y: NonlinearityConfig,
    /// Angle by which the Y axis leans towards +X from the perpendicular, degrees. Typical: 1.5.
    pub nonorthogonality_deg: f64,
    /// Field-dependent obliquity (shear gradient), x part: the X input gains
    /// `gₓ·uₓ·u_y/H` counts (H = lateral half range) before the static map, so the Y axis leans
    /// by an extra gₓ·uₓ/H rad (× Kx/Ky) that grows across the field — e.g. quadrant electrodes of
    /// unequal width. Dimensionless, |gₓ| ≤ 0.3. Typical: 0; ideal: 0.
    pub shear_gradient_x: f64,
    /// Field-dependent obliquity, y part: the Y input gains `g_y·uₓ·u_y/H` counts (the X axis
    /// tilts by g_y·u_y/H across the field). Dimensionless, |g_y| ≤ 0.3. Typical: 0; ideal: 0.
    pub shear_gradient_y: f64,
    /// Linear crosstalk: X displacement per Y displacement, nm/nm. Typical: 0.004.
    pub crosstalk_x_from_y: f64,
    /// Linear crosstalk: Y displacement per X displacement, nm/nm. Typical: -0.006.
    pub crosstalk_y_from_x: f64,
    /// Quadratic crosstalk (guidance bow): X displacement as a fraction of the
    /// Y displacement at the Y field edge, growing linearly with y/half. Typical: 0.008.
    pub bow_x_from_y: f64,
    /// Quadratic crosstalk: Y displacement as a fraction of the X displacement
    /// at the X field edge. Typical: 0.005.
    pub bow_y_from_x: f64,
    /// Tilted tube: X displacement per Z extension, nm/nm. Typical: 0.03.
    pub tilt_x_from_z: f64,
    /// Tilted tube: Y displacement per Z extension, nm/nm. Typical: -0.02.
    pub tilt_y_from_z: f64,
    /// Fractional change of both lateral sensitivities at full Z extension
    /// (Z counts = half range), linear in Z counts. Typical: 0.03.
    pub lateral_sensitivity_change_per_z: f64,
    /// Curvature of the tube's arc, 1/nm: the tip rises by c·r²/2 at lateral
    /// distance r (nm) from the field centre, which the feedback shows as a
    /// bowl (edges higher). 0 = off. Typical: 5e-7 (radius 2 mm).
    pub bowl_curvature_per_nm: f64,
    /// X hysteresis (Prandtl–Ishlinskii play operators).
    pub hysteresis_x: HysteresisConfig,
    /// Y hysteresis.
    pub hysteresis_y: HysteresisConfig,
    /// Creep (both lateral axes).
    pub creep: CreepConfig,
    /// Nonlinear Z manipulator whose Kz varies with z and over the field
    /// ([`crate::vertical`]); absent = linear, Kz = `sensitivity_z_nm_per_count` everywhere.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_manipulator: Option<ZManipulatorConfig>,
}

/// Static nonlinearity of one axis: the axis displacement in "linear counts"
/// is `g(u) = u·(1 + quadratic·s + cubic·s²)`, `s = u / half_range`, so the
/// local slope at the field edges is `1 ± 2·quadratic + 3·cubic`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NonlinearityConfig {
    /// Quadratic coefficient (dimensionless). Typical: 0.03 (x), -0.025 (y).
    pub quadratic: f64,
    /// Cubic coefficient (dimensionless). Typical: 0.05 (x), 0.04 (y).
    pub cubic: f64,
}

/// Rate-independent hysteresis of one axis: `operators` play operators with
/// thresholds evenly spaced in `[min_threshold_counts, max_threshold_counts]`
/// and equal weights chosen so that the ±half-range major loop has the given width.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HysteresisConfig {
    /// Branch separation of the full-range major loop at u = 0 as a fraction
    /// of the full range (2·half); 0 = off. Typical: 0.04 (x), 0.05 (y).
    pub width_fraction: f64,
    /// Smallest play threshold, counts (> 0): moves that stay within
    /// ±this of their last reversal never change the hysteresis state. Typical: 512.
    pub min_threshold_counts: f64,
    /// Largest play threshold, counts (≤ half range / 2). Typical: 16384.
    pub max_threshold_counts: f64,
    /// Number of play operators (≥ 1). Typical: 16.
    pub operators: u32,
}

/// Creep: a chain of first-order relaxations with log-spaced time constants.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreepConfig {
    /// γ of ΔL(t) = ΔL(0.1 s)·[1 + γ·lg(t / 0.1 s)]; 0 = off. Typical: 0.015.
    pub log_slope_per_decade: f64,
    /// Shortest relaxation time constant, s (> 0). Typical: 0.02.
    pub min_time_constant_s: f64,
    /// Longest relaxation time constant, s (> min). Typical: 2000.
    pub max_time_constant_s: f64,
    /// Relaxation elements per decade of time constant (≥ 1). Typical: 3.
    pub elements_per_decade: u32,
}

/// Thermal drift and mechanical vibration of the tip relative to the sample.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriftConfig {
    /// Constant drift velocity, x, nm/s. Typical: 0.012 (0.12 Å/s).
    pub velocity_x_nm_per_s: f64,
    /// Constant drift velocity, y, nm/s. Typical: -0.007.
    pub velocity_y_nm_per_s: f64,
    /// Total displacement of the warm-up transient, x, nm. Typical: 1.5.
    pub warmup_amplitude_x_nm: f64,
    /// Total displacement of the warm-up transient, y, nm. Typical: -0.8.
    pub warmup_amplitude_y_nm: f64,
    /// Time constant of the warm-up exponential, s (> 0). Typical: 600.
    pub warmup_time_constant_s: f64,
    /// Random walk of the drift velocity (per axis), nm/s per √s. Typical: 2e-5.
    pub velocity_random_walk_nm_per_s_per_sqrt_s: f64,
    /// Knot interval of the random walk (and jump grid), s (> 0). Typical: 0.1.
    pub random_walk_interval_s: f64,
    /// Rate of sudden drift jumps (Poisson), 1/s. Typical: 2.8e-4 (one per hour).
    pub jump_rate_per_s: f64,
    /// Standard deviation of a jump per axis, nm. Typical: 0.05.
    pub jump_sigma_nm: f64,
    /// Lateral vibration of the tip relative to the sample (building, pump, cooling
    /// machinery): `Aₓ·cos(2πf·t + φₓ)` along x, nm (≥ 0). Typical: 0; ideal: 0.
    pub vibration_amplitude_x_nm: f64,
    /// Vibration amplitude along y, `A_y·cos(2πf·t + φ_y)`, nm (≥ 0). Typical: 0; ideal: 0.
    pub vibration_amplitude_y_nm: f64,
    /// Vibration frequency f, Hz (≥ 0; t is the instrument clock). Typical: 50; ideal: 50.
    pub vibration_frequency_hz: f64,
    /// Vibration phase φₓ at t = 0, rad, in [−2π, 2π]. Typical: 0; ideal: 0.
    pub vibration_phase_x_rad: f64,
    /// Vibration phase φ_y at t = 0, rad, in [−2π, 2π]. Typical: 0; ideal: 0.
    pub vibration_phase_y_rad: f64,
}

/// The measurement chain.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MeasurementConfig {
    /// White Z noise per pixel (standard deviation), nm. Typical: 0.003.
    pub z_white_noise_nm: f64,
    /// 1/f Z noise, standard deviation over its band, nm. Typical: 0.004.
    pub z_flicker_noise_nm: f64,
    /// Lower corner of the 1/f band, Hz (> 0). Typical: 0.01.
    pub flicker_min_frequency_hz: f64,
    /// Upper corner of the 1/f band, Hz (> min). Typical: 1000.
    pub flicker_max_frequency_hz: f64,
    /// Lateral position jitter per pixel and axis (standard deviation), nm. Typical: 0.002.
    pub lateral_jitter_nm: f64,
    /// Commanded lateral positions are rounded to whole DAC counts. Typical: true.
    pub quantise_lateral_dac: bool,
    /// Z readings are rounded to whole ADC counts. Typical: true.
    pub quantise_z_adc: bool,
    /// Time constant of the Z feedback (first-order lag), s; 0 = ideal. Typical: 5e-5.
    pub feedback_time_constant_s: f64,
}

/// Randomly occurring faults (all rates ≥ 0; 0 = never).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaultConfig {
    /// Probability that a call times out. Typical: 0.0005.
    pub timeout_probability_per_call: f64,
    /// Probability that a call fails with a communication error. Typical: 0.0005.
    pub communication_probability_per_call: f64,
    /// Rate at which the feedback loses the surface during scans and moves, 1/s. Typical: 1e-4.
    pub feedback_lost_rate_per_s: f64,
    /// Rate of spontaneous tip changes, 1/s. Typical: 2e-5.
    pub tip_change_rate_per_s: f64,
    /// Rate of drift bursts, 1/s. Typical: 1e-4.
    pub drift_burst_rate_per_s: f64,
    /// Time a timed-out call consumes before failing, s. Typical: 1.
    pub timeout_duration_s: f64,
    /// Speed of a random drift burst, nm/s. Typical: 0.2.
    pub drift_burst_speed_nm_per_s: f64,
    /// Duration of a random drift burst, s. Typical: 5.
    pub drift_burst_duration_s: f64,
    /// Standard deviation per axis of the lateral jump of a random tip change, nm. Typical: 0.3.
    pub tip_change_jump_sigma_nm: f64,
}

// ---------------------------------------------------------------------------
// Errors

pub use spm_config::{ConfigError, ValidationError};

impl spm_config::Validate for SimConfig {
    fn validate(&self) -> Result<(), ValidationError> {
        SimConfig::validate(self)
    }
}

// ---------------------------------------------------------------------------
// Loading

impl SimConfig {
    /// Parses and validates a TOML text; `source_name` labels errors (a file name).
    pub fn from_toml_str(text: &str, source_name: &str) -> Result<Self, ConfigError> {
        spm_config::parse_and_validate(text, source_name)
    }

    /// Reads, parses and validates a TOML file.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        spm_config::load_file(path.as_ref())
    }

    /// What the instrument of this config offers (as the simulator reports it), for
    /// checking a plan against it before any simulator is built.
    pub fn capabilities(&self) -> spm_hal::Capabilities {
        let i = &self.instrument;
        let h = i.lateral_half_range_counts;
        let hz = i.z_half_range_counts;
        spm_hal::Capabilities {
            field_min: spm_hal::CountPoint::from_counts(-h, -h),
            field_max: spm_hal::CountPoint::from_counts(h - 1.0, h - 1.0),
            z_min: spm_hal::Counts(-hz),
            z_max: spm_hal::Counts(hz - 1.0),
            lateral_resolution: spm_hal::Counts(1.0),
            max_pixels_per_line: i.max_pixels_per_line,
            pixels_per_line_multiple: 1,
            max_lines: i.max_lines,
            min_pixel_dwell: spm_hal::Seconds(i.min_pixel_dwell_s),
            counter_scan: i.counter_scan,
            backward_trace: i.backward_trace,
            coarse_z: i.coarse_z.as_ref().map(|c| spm_hal::CoarseZCapability {
                min_steps: c.min_steps,
                max_steps: c.max_steps,
            }),
        }
    }

    /// Semantic validation (finite numbers, positive where required, ranges).
    pub fn validate(&self) -> Result<(), ValidationError> {
        self.validate_with_prefix("")
    }

    /// Like [`validate`](Self::validate), with every field path prefixed by
    /// `prefix` (e.g. `"backend.sim."`) for configs embedded in bigger ones.
    pub fn validate_with_prefix(&self, prefix: &str) -> Result<(), ValidationError> {
        let v = spm_config::RangeChecker::new(prefix);
        self.validate_instrument(&v)?;
        self.validate_surface(&v)?;
        self.validate_scanner_geometry(&v)?;
        self.validate_scanner_dynamics(&v)?;
        self.validate_drift(&v)?;
        self.validate_measurement(&v)?;
        self.validate_faults(&v)?;
        Ok(())
    }

    /// The `[instrument]` table.
    fn validate_instrument(&self, v: &spm_config::RangeChecker<'_>) -> Result<(), ValidationError> {
        let i = &self.instrument;
        v.range_positive(
            "instrument.lateral_half_range_counts",
            i.lateral_half_range_counts,
            8.0,
            2147483648.0,
        )?;
        v.range_positive(
            "instrument.z_half_range_counts",
            i.z_half_range_counts,
            8.0,
            2147483648.0,
        )?;
        v.at_least_one("instrument.max_pixels_per_line", i.max_pixels_per_line)?;
        v.at_least_one("instrument.max_lines", i.max_lines)?;
        v.at_most(
            "instrument.max_pixels_per_line",
            i.max_pixels_per_line,
            65_536,
        )?;
        v.at_most("instrument.max_lines", i.max_lines, 65_536)?;
        v.range_positive(
            "instrument.min_pixel_dwell_s",
            i.min_pixel_dwell_s,
            1e-9,
            1.0,
        )?;
        v.range(
            "instrument.initial_z_extension_nm",
            i.initial_z_extension_nm,
            -1e6,
            1e6,
        )?;
        v.range("instrument.call_overhead_s", i.call_overhead_s, 0.0, 10.0)?;
        v.range(
            "instrument.retrace_slow_axis_advance_counts",
            i.retrace_slow_axis_advance_counts,
            -0.25 * i.lateral_half_range_counts,
            0.25 * i.lateral_half_range_counts,
        )?;
        v.range(
            "instrument.slow_axis_ramp_counts",
            i.slow_axis_ramp_counts,
            -0.25 * i.lateral_half_range_counts,
            0.25 * i.lateral_half_range_counts,
        )?;
        if let Some(c) = &i.coarse_z {
            if c.min_steps > c.max_steps {
                return v.fail("instrument.coarse_z.max_steps", "must be ≥ min_steps");
            }
            if c.min_steps > 0 || c.max_steps < 0 {
                return v.fail("instrument.coarse_z.min_steps", "the range must contain 0");
            }
            if c.min_steps < -100_000_000 {
                return v.fail("instrument.coarse_z.min_steps", "must be ≥ -100000000");
            }
            if c.max_steps > 100_000_000 {
                return v.fail("instrument.coarse_z.max_steps", "must be ≤ 100000000");
            }
            v.range_positive("instrument.coarse_z.step_nm", c.step_nm, 1e-3, 1e4)?;
            v.range("instrument.coarse_z.step_time_s", c.step_time_s, 0.0, 60.0)?;
        }
        Ok(())
    }

    /// The `[surface]` table (the lattice, the grating or the steps).
    fn validate_surface(&self, v: &spm_config::RangeChecker<'_>) -> Result<(), ValidationError> {
        match &self.surface {
            SurfaceConfig::Hopg(h) => {
                let p = "surface.hopg.";
                v.range_positive(
                    &format!("{p}lattice_constant_nm"),
                    h.lattice_constant_nm,
                    0.05,
                    1e4,
                )?;
                v.range_positive(&format!("{p}corrugation_nm"), h.corrugation_nm, 1e-6, 10.0)?;
                v.range(
                    &format!("{p}hollow_asymmetry"),
                    h.hollow_asymmetry,
                    0.0,
                    0.5,
                )?;
                v.range(&format!("{p}rotation_deg"), h.rotation_deg, -360.0, 360.0)?;
                v.range(&format!("{p}step_height_nm"), h.step_height_nm, 0.0, 100.0)?;
                v.range(
                    &format!("{p}vacancy_fraction"),
                    h.vacancy_fraction,
                    0.0,
                    0.2,
                )?;
                for (k, s) in h.steps.iter().enumerate() {
                    let q = format!("{p}steps[{k}].");
                    v.range(&format!("{q}point_x_nm"), s.point_x_nm, -1e7, 1e7)?;
                    v.range(&format!("{q}point_y_nm"), s.point_y_nm, -1e7, 1e7)?;
                    v.range(&format!("{q}direction_deg"), s.direction_deg, -360.0, 360.0)?;
                    v.range_positive(&format!("{q}width_nm"), s.width_nm, 1e-3, 1e6)?;
                }
                for (k, d) in h.domains.iter().enumerate() {
                    let q = format!("{p}domains[{k}].");
                    v.range(&format!("{q}centre_x_nm"), d.centre_x_nm, -1e7, 1e7)?;
                    v.range(&format!("{q}centre_y_nm"), d.centre_y_nm, -1e7, 1e7)?;
                    v.range_positive(&format!("{q}radius_nm"), d.radius_nm, 1e-3, 1e7)?;
                    v.range(&format!("{q}rotation_deg"), d.rotation_deg, -360.0, 360.0)?;
                }
            }
            SurfaceConfig::Si7x7(s) => {
                let p = "surface.si7x7.";
                v.range_positive(
                    &format!("{p}lattice_constant_nm"),
                    s.lattice_constant_nm,
                    0.05,
                    1e4,
                )?;
                v.range_positive(
                    &format!("{p}corner_hole_depth_nm"),
                    s.corner_hole_depth_nm,
                    1e-6,
                    10.0,
                )?;
                v.range_positive(
                    &format!("{p}corner_hole_sigma_nm"),
                    s.corner_hole_sigma_nm,
                    1e-3,
                    100.0,
                )?;
                v.range(&format!("{p}rotation_deg"), s.rotation_deg, -360.0, 360.0)?;
            }
            SurfaceConfig::HexLattice(l) | SurfaceConfig::SquareLattice(l) => {
                let p = if matches!(self.surface, SurfaceConfig::HexLattice(_)) {
                    "surface.hex_lattice."
                } else {
                    "surface.square_lattice."
                };
                v.range_positive(
                    &format!("{p}lattice_constant_nm"),
                    l.lattice_constant_nm,
                    0.05,
                    1e4,
                )?;
                v.range(
                    &format!("{p}feature_height_nm"),
                    l.feature_height_nm,
                    -100.0,
                    100.0,
                )?;
                if l.feature_height_nm == 0.0 {
                    return v.fail(&format!("{p}feature_height_nm"), "must not be 0");
                }
                v.range_positive(
                    &format!("{p}feature_sigma_nm"),
                    l.feature_sigma_nm,
                    1e-3,
                    1e3,
                )?;
                v.range(&format!("{p}rotation_deg"), l.rotation_deg, -360.0, 360.0)?;
            }
        }
        Ok(())
    }

    /// The `[scanner]` table's static field: sensitivities, nonlinearity, couplings.
    fn validate_scanner_geometry(
        &self,
        v: &spm_config::RangeChecker<'_>,
    ) -> Result<(), ValidationError> {
        let s = &self.scanner;
        v.range_positive(
            "scanner.sensitivity_x_nm_per_count",
            s.sensitivity_x_nm_per_count,
            1e-6,
            100.0,
        )?;
        v.range_positive(
            "scanner.sensitivity_y_nm_per_count",
            s.sensitivity_y_nm_per_count,
            1e-6,
            100.0,
        )?;
        v.range_positive(
            "scanner.sensitivity_z_nm_per_count",
            s.sensitivity_z_nm_per_count,
            1e-6,
            100.0,
        )?;
        for (name, n) in [
            ("scanner.nonlinearity_x", &s.nonlinearity_x),
            ("scanner.nonlinearity_y", &s.nonlinearity_y),
        ] {
            v.range(&format!("{name}.quadratic"), n.quadratic, -0.3, 0.3)?;
            v.range(&format!("{name}.cubic"), n.cubic, -0.3, 0.3)?;
            // The axis must stay monotonic over a generous margin of the field.
            let worst = (0..=40)
                .map(|k| -1.3 + 2.6 * f64::from(k) / 40.0)
                .map(|s| 1.0 + 2.0 * n.quadratic * s + 3.0 * n.cubic * s * s)
                .fold(f64::INFINITY, f64::min);
            if worst <= 0.2 {
                return v.fail(
                    &format!("{name}.cubic"),
                    "makes the axis non-monotonic (slope ≤ 0.2) within 1.3 × the half range",
                );
            }
        }
        v.range(
            "scanner.nonorthogonality_deg",
            s.nonorthogonality_deg,
            -20.0,
            20.0,
        )?;
        v.range("scanner.shear_gradient_x", s.shear_gradient_x, -0.3, 0.3)?;
        v.range("scanner.shear_gradient_y", s.shear_gradient_y, -0.3, 0.3)?;
        v.range(
            "scanner.crosstalk_x_from_y",
            s.crosstalk_x_from_y,
            -0.2,
            0.2,
        )?;
        v.range(
            "scanner.crosstalk_y_from_x",
            s.crosstalk_y_from_x,
            -0.2,
            0.2,
        )?;
        v.range("scanner.bow_x_from_y", s.bow_x_from_y, -0.2, 0.2)?;
        v.range("scanner.bow_y_from_x", s.bow_y_from_x, -0.2, 0.2)?;
        v.range("scanner.tilt_x_from_z", s.tilt_x_from_z, -1.0, 1.0)?;
        v.range("scanner.tilt_y_from_z", s.tilt_y_from_z, -1.0, 1.0)?;
        v.range(
            "scanner.lateral_sensitivity_change_per_z",
            s.lateral_sensitivity_change_per_z,
            -0.5,
            0.5,
        )?;
        v.range(
            "scanner.bowl_curvature_per_nm",
            s.bowl_curvature_per_nm,
            0.0,
            1.0,
        )?;
        if let Some(z) = &s.z_manipulator
            && let Err((field, reason)) = check_z_manipulator(z)
        {
            return v.fail(&format!("scanner.z_manipulator.{field}"), &reason);
        }
        Ok(())
    }

    /// The `[scanner]` table's hysteresis and creep.
    fn validate_scanner_dynamics(
        &self,
        v: &spm_config::RangeChecker<'_>,
    ) -> Result<(), ValidationError> {
        let s = &self.scanner;
        let i = &self.instrument;
        for (name, h) in [
            ("scanner.hysteresis_x", &s.hysteresis_x),
            ("scanner.hysteresis_y", &s.hysteresis_y),
        ] {
            v.range(
                &format!("{name}.width_fraction"),
                h.width_fraction,
                0.0,
                0.3,
            )?;
            v.range_positive(
                &format!("{name}.min_threshold_counts"),
                h.min_threshold_counts,
                1e-3,
                2147483648.0,
            )?;
            v.range_positive(
                &format!("{name}.max_threshold_counts"),
                h.max_threshold_counts,
                1e-3,
                2147483648.0,
            )?;
            if h.max_threshold_counts < h.min_threshold_counts {
                return v.fail(
                    &format!("{name}.max_threshold_counts"),
                    "must be ≥ min_threshold_counts",
                );
            }
            if h.max_threshold_counts > 0.5 * i.lateral_half_range_counts {
                return v.fail(
                    &format!("{name}.max_threshold_counts"),
                    "must be ≤ half of instrument.lateral_half_range_counts",
                );
            }
            v.at_least_one(&format!("{name}.operators"), h.operators)?;
            if h.operators > 256 {
                return v.fail(&format!("{name}.operators"), "must be ≤ 256");
            }
        }
        let c = &s.creep;
        v.range(
            "scanner.creep.log_slope_per_decade",
            c.log_slope_per_decade,
            0.0,
            0.1,
        )?;
        v.range_positive(
            "scanner.creep.min_time_constant_s",
            c.min_time_constant_s,
            1e-6,
            1e6,
        )?;
        v.range_positive(
            "scanner.creep.max_time_constant_s",
            c.max_time_constant_s,
            1e-6,
            1e9,
        )?;
        if c.max_time_constant_s <= c.min_time_constant_s {
            return v.fail(
                "scanner.creep.max_time_constant_s",
                "must be > min_time_constant_s",
            );
        }
        if c.max_time_constant_s / c.min_time_constant_s > 1e12 {
            return v.fail(
                "scanner.creep.max_time_constant_s",
                "spans more than 12 decades above min_time_constant_s",
            );
        }
        v.at_least_one("scanner.creep.elements_per_decade", c.elements_per_decade)?;
        if c.elements_per_decade > 20 {
            return v.fail("scanner.creep.elements_per_decade", "must be ≤ 20");
        }
        Ok(())
    }

    /// The `[drift]` table.
    fn validate_drift(&self, v: &spm_config::RangeChecker<'_>) -> Result<(), ValidationError> {
        let d = &self.drift;
        v.range(
            "drift.velocity_x_nm_per_s",
            d.velocity_x_nm_per_s,
            -1e3,
            1e3,
        )?;
        v.range(
            "drift.velocity_y_nm_per_s",
            d.velocity_y_nm_per_s,
            -1e3,
            1e3,
        )?;
        v.range(
            "drift.warmup_amplitude_x_nm",
            d.warmup_amplitude_x_nm,
            -1e4,
            1e4,
        )?;
        v.range(
            "drift.warmup_amplitude_y_nm",
            d.warmup_amplitude_y_nm,
            -1e4,
            1e4,
        )?;
        v.range_positive(
            "drift.warmup_time_constant_s",
            d.warmup_time_constant_s,
            1e-3,
            1e7,
        )?;
        v.range(
            "drift.velocity_random_walk_nm_per_s_per_sqrt_s",
            d.velocity_random_walk_nm_per_s_per_sqrt_s,
            0.0,
            100.0,
        )?;
        v.range_positive(
            "drift.random_walk_interval_s",
            d.random_walk_interval_s,
            0.01,
            1e4,
        )?;
        v.range("drift.jump_rate_per_s", d.jump_rate_per_s, 0.0, 10.0)?;
        if d.jump_rate_per_s * d.random_walk_interval_s > 0.1 {
            return v.fail(
                "drift.jump_rate_per_s",
                "must be < 0.1 / drift.random_walk_interval_s (at most one jump per knot)",
            );
        }
        v.range("drift.jump_sigma_nm", d.jump_sigma_nm, 0.0, 1e3)?;
        v.range(
            "drift.vibration_amplitude_x_nm",
            d.vibration_amplitude_x_nm,
            0.0,
            1e3,
        )?;
        v.range(
            "drift.vibration_amplitude_y_nm",
            d.vibration_amplitude_y_nm,
            0.0,
            1e3,
        )?;
        v.range(
            "drift.vibration_frequency_hz",
            d.vibration_frequency_hz,
            0.0,
            1e6,
        )?;
        let tau = std::f64::consts::TAU;
        v.range(
            "drift.vibration_phase_x_rad",
            d.vibration_phase_x_rad,
            -tau,
            tau,
        )?;
        v.range(
            "drift.vibration_phase_y_rad",
            d.vibration_phase_y_rad,
            -tau,
            tau,
        )?;
        Ok(())
    }

    /// The `[measurement]` table.
    fn validate_measurement(
        &self,
        v: &spm_config::RangeChecker<'_>,
    ) -> Result<(), ValidationError> {
        let m = &self.measurement;
        v.range(
            "measurement.z_white_noise_nm",
            m.z_white_noise_nm,
            0.0,
            100.0,
        )?;
        v.range(
            "measurement.z_flicker_noise_nm",
            m.z_flicker_noise_nm,
            0.0,
            100.0,
        )?;
        v.range_positive(
            "measurement.flicker_min_frequency_hz",
            m.flicker_min_frequency_hz,
            1e-6,
            1e7,
        )?;
        v.range_positive(
            "measurement.flicker_max_frequency_hz",
            m.flicker_max_frequency_hz,
            1e-6,
            1e7,
        )?;
        if m.flicker_max_frequency_hz <= m.flicker_min_frequency_hz {
            return v.fail(
                "measurement.flicker_max_frequency_hz",
                "must be > flicker_min_frequency_hz",
            );
        }
        v.range(
            "measurement.lateral_jitter_nm",
            m.lateral_jitter_nm,
            0.0,
            100.0,
        )?;
        v.range(
            "measurement.feedback_time_constant_s",
            m.feedback_time_constant_s,
            0.0,
            10.0,
        )?;
        Ok(())
    }

    /// The `[faults]` table.
    fn validate_faults(&self, v: &spm_config::RangeChecker<'_>) -> Result<(), ValidationError> {
        let f = &self.faults;
        v.range(
            "faults.timeout_probability_per_call",
            f.timeout_probability_per_call,
            0.0,
            1.0,
        )?;
        v.range(
            "faults.communication_probability_per_call",
            f.communication_probability_per_call,
            0.0,
            1.0,
        )?;
        v.range(
            "faults.feedback_lost_rate_per_s",
            f.feedback_lost_rate_per_s,
            0.0,
            100.0,
        )?;
        v.range(
            "faults.tip_change_rate_per_s",
            f.tip_change_rate_per_s,
            0.0,
            100.0,
        )?;
        v.range(
            "faults.drift_burst_rate_per_s",
            f.drift_burst_rate_per_s,
            0.0,
            100.0,
        )?;
        v.range(
            "faults.timeout_duration_s",
            f.timeout_duration_s,
            0.0,
            3600.0,
        )?;
        v.range(
            "faults.drift_burst_speed_nm_per_s",
            f.drift_burst_speed_nm_per_s,
            0.0,
            1e3,
        )?;
        v.range(
            "faults.drift_burst_duration_s",
            f.drift_burst_duration_s,
            0.0,
            3600.0,
        )?;
        v.range(
            "faults.tip_change_jump_sigma_nm",
            f.tip_change_jump_sigma_nm,
            0.0,
            1e3,
        )?;
        Ok(())
    }
}

// ---------------------------------------------------------------------------
// Named scenarios

impl SimConfig {
    /// A scenario shipped with the crate (`scenarios/*.toml`, also `configs/*.toml` of the
    /// workspace). The texts are part of the program, parsed by the same loader as any user
    /// file; the crate's tests parse each of them, so this cannot fail in a released build.
    #[allow(clippy::expect_used)]
    fn embedded(text: &str, name: &str) -> Self {
        Self::from_toml_str(text, name).expect("a shipped scenario parses and validates")
    }

    /// All effects off: a linear orthogonal scanner (0.02 nm/count on both
    /// axes, 0.004 nm/count in Z), no hysteresis, creep, drift, noise,
    /// quantisation or faults, a perfect HOPG lattice (a = 0.2461 nm,
    /// rotation 0). Parsed from `scenarios/sim-ideal.toml` (`configs/sim-ideal.toml`).
    pub fn ideal() -> Self {
        Self::embedded(
            include_str!("../scenarios/sim-ideal.toml"),
            "sim-ideal.toml",
        )
    }

    /// A room-temperature tube scanner over HOPG with every effect on at
    /// realistic magnitudes. Parsed from `scenarios/sim-hopg.toml` (`configs/sim-hopg.toml`).
    pub fn room_temperature_tube() -> Self {
        Self::embedded(include_str!("../scenarios/sim-hopg.toml"), "sim-hopg.toml")
    }

    /// This config with every random fault rate set to zero (scheduled faults
    /// still work). Handy for accuracy runs.
    pub fn without_random_faults(mut self) -> Self {
        self.faults = FaultConfig {
            timeout_duration_s: self.faults.timeout_duration_s,
            ..FaultConfig::none()
        };
        self
    }
}

impl FaultConfig {
    /// No random faults (timeouts of scheduled faults last 1 s).
    pub fn none() -> Self {
        Self {
            timeout_probability_per_call: 0.0,
            communication_probability_per_call: 0.0,
            feedback_lost_rate_per_s: 0.0,
            tip_change_rate_per_s: 0.0,
            drift_burst_rate_per_s: 0.0,
            timeout_duration_s: 1.0,
            drift_burst_speed_nm_per_s: 0.2,
            drift_burst_duration_s: 5.0,
            tip_change_jump_sigma_nm: 0.3,
        }
    }
}

/// Nonlinearity of the Z manipulator and its variation over the lateral field. Every field
/// is dimensionless (fractions); 0 everywhere = a linear manipulator with Kz everywhere.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZManipulatorConfig {
    /// Quadratic coefficient q of the characteristic `ζ(1 + q·ζ + c·ζ²)`, ζ = z / half range.
    /// Kz changes by `2q` at full extension. Typical: 0.04.
    pub quadratic: f64,
    /// Cubic coefficient c. Kz changes by `3c` at full extension. Typical: 0.02.
    pub cubic: f64,
    /// Fractional change of Kz at the +x field edge (linear in x), e.g. electrode asymmetry.
    /// Typical: 0.015.
    pub lateral_gradient_x: f64,
    /// Fractional change of Kz at the +y field edge (linear in y). Typical: -0.01.
    pub lateral_gradient_y: f64,
    /// Fractional change of Kz at normalised lateral radius 1 (quadratic in r; the tube's
    /// bending stiffens the Z response at the field edges). Typical: 0.02.
    pub lateral_radial: f64,
    /// Amplitude of a sinusoidal ripple of Kz along x (a "hidden" effect, not a polynomial),
    /// fraction. Typical: 0 (off).
    pub ripple_fraction: f64,
    /// Period of the ripple along x, lateral counts (> 0). Typical: 16384.
    pub ripple_period_counts: f64,
    /// Fractional change of Kz per hour of instrument time (aging, temperature): a Z effect
    /// a calibration that takes Kz as static does not model. Typical: 0 (off).
    pub kz_drift_per_hour: f64,
}

/// Checks a Z-manipulator config: the characteristic must stay monotone over the Z range and
/// the lateral factor positive over the field. Returns the offending field and reason.
pub(crate) fn check_z_manipulator(c: &ZManipulatorConfig) -> Result<(), (&'static str, String)> {
    for (field, v, lim) in [
        ("quadratic", c.quadratic, 0.3),
        ("cubic", c.cubic, 0.3),
        ("lateral_gradient_x", c.lateral_gradient_x, 0.3),
        ("lateral_gradient_y", c.lateral_gradient_y, 0.3),
        ("lateral_radial", c.lateral_radial, 0.3),
        ("ripple_fraction", c.ripple_fraction, 0.1),
        ("kz_drift_per_hour", c.kz_drift_per_hour, 0.2),
    ] {
        if !(v.is_finite() && v.abs() <= lim) {
            return Err((
                field,
                format!("must be a finite number in [-{lim}, {lim}], got {v}"),
            ));
        }
    }
    if !(c.ripple_period_counts.is_finite()
        && c.ripple_period_counts >= 16.0
        && c.ripple_period_counts <= 1e10)
    {
        return Err((
            "ripple_period_counts",
            format!(
                "must be a finite number in [16, 1e10], got {}",
                c.ripple_period_counts
            ),
        ));
    }
    // Monotone: dE/dz > 0 for |ζ| ≤ 1 (sampled), lateral factor > 0 on the field.
    for k in 0..=40 {
        let zeta = -1.0 + 0.05 * f64::from(k);
        if 1.0 + 2.0 * c.quadratic * zeta + 3.0 * c.cubic * zeta * zeta <= 0.1 {
            return Err((
                "quadratic",
                "with `cubic`, makes the Z characteristic non-monotone inside the Z range".into(),
            ));
        }
    }
    let worst = 1.0
        - c.lateral_gradient_x.abs()
        - c.lateral_gradient_y.abs()
        - 2.0 * c.lateral_radial.min(0.0).abs()
        - c.ripple_fraction.abs();
    if worst <= 0.1 {
        return Err((
            "lateral_gradient_x",
            "with the other lateral terms, makes Kz vanish somewhere in the field".into(),
        ));
    }
    Ok(())
}
