//! # spm-sim: a physics-based simulated STM with a ground-truth oracle
//!
//! [`Simulator`] implements [`spm_hal::Microscope`]: a deterministic model of a
//! room-temperature tube scanner over a crystal standard (HOPG, Si(111)-7×7,
//! generic lattices) with static nonlinearity, nonorthogonality (constant and
//! field-dependent), crosstalk, Z couplings, rate-independent hysteresis,
//! logarithmic creep, thermal drift, lateral vibration, interlace, measurement
//! noise, feedback lag, quantisation and faults on demand. The
//! ground truth is reachable only through [`Simulator::oracle`] ([`Oracle`]).
//!
//! ```
//! use spm_hal::{Microscope, ScanRequest, CountPoint, Counts, Seconds};
//! use spm_sim::{SimConfig, Simulator};
//!
//! let mut sim = Simulator::new(SimConfig::ideal()).unwrap();
//! let request = ScanRequest::centred_square(CountPoint::from_counts(0.0, 0.0), Counts(1.0), 16, Seconds(1e-4));
//! let frame = sim.scan(&request).unwrap();
//! assert_eq!(frame.forward.z_counts.len(), 256);
//! let lcc = sim.oracle().true_lcc(CountPoint::from_counts(0.0, 0.0), sim.oracle().z_now());
//! assert!((lcc.kx.value() - 0.02).abs() < 1e-12);
//! ```
//!
//! ## Determinism
//! All randomness comes from ChaCha8 streams derived from [`SimConfig::seed`]
//! (measurement noise, random faults, and the drift random walk whose every
//! knot has its own stream so the drift is a function of time only). There is
//! no global RNG and no wall clock: same seed, config and call sequence ⇒
//! bit-identical frames.
//!
//! ## Time
//! Every call may cost `instrument.call_overhead_s` (wait, move, scan, Z read,
//! coarse steps; `now` and `position` are free). A move takes length/speed
//! plus settle; a scan first travels from the current position to its first
//! pixel at the scan speed (`pixel_step / pixel_dwell`), then takes exactly
//! `2·pixels·dwell`: every line is a trace and a retrace at the same dwell,
//! times are dwell midpoints as in [`spm_hal::Frame::from_fn`], and the
//! retrace is simulated (creep, feedback, drift, noise) whether or not it is
//! recorded (an unrecorded retrace whose hysteresis is frozen is advanced in
//! closed form — exact for creep, an exact AR step for the 1/f processes —
//! and only its last ~20 feedback time constants pixel by pixel). The probe
//! ends at the last retrace's last pixel.
//!
//! ## Scan programs beyond the raster
//! Simulator extensions (not on the `Microscope` trait), the raster's physics along
//! another path: [`Simulator::scan_turned`] turns every commanded position about a
//! point ([`RasterTurn`], a controller's frame angle); [`Simulator::scan_sine_driven`]
//! drives the fast axis by a sine over ±β of phase per line with the pixels
//! equidistant in time ([`SineDrive`], fast SPM's resonant scanner: column k at
//! c + (W/sin β)·sin(β·ξ_k), ξ_k = (2k + 1 − N)/N, so the line's ends meet the
//! nominal raster's). The frame's request stays the nominal raster.
//!
//! ## The scanner model
//! Per lateral axis, commanded counts `u` (DAC-quantised if configured) pass
//! through **hysteresis** and **creep** to the *effective input*
//! `uₑ = u + h + c`, and the **static map** F gives the tip position in the
//! scanner frame: `p = F(uₑ, z)` (see [`StaticMap`] for F: per-axis cubic
//! nonlinearity normalised to the half range, a shear gradient (field-dependent
//! obliquity: the input gains `(γx, γy)·uₓ·u_y/H` before the map), nonorthogonality α₀, linear and
//! quadratic ("bow") X⇔Y crosstalk, Z⇒X/Y tilt, Z-dependent lateral
//! sensitivity; the tube arc adds a bowl `c·r²/2` to the image). The sample
//! point under the tip is `p + d(t)` (drift) + lateral jitter.
//!
//! - **Hysteresis** ([`PlayHysteresis`]): Prandtl–Ishlinskii play operators,
//!   `yᵢ ← max(u − rᵢ, min(u + rᵢ, yᵢ))`, thresholds rᵢ evenly spaced in
//!   `[min_threshold_counts, max_threshold_counts]` (≤ half/2), offset
//!   `h = w·Σyᵢ` with equal weights chosen so that a full-range (±half) cycle
//!   has branch separation `2·width_fraction·half` at u = 0 (i.e. the
//!   configured width as a fraction of the full commanded range). Valid for any
//!   history (it is a rate-independent operator with wiping-out memory).
//! - **Creep** ([`Creep`]): per axis, relaxations `ċₖ = (w·x − cₖ)/τₖ` driven by
//!   the post-hysteresis input `x = u + h`, τₖ log-spaced from
//!   `min_time_constant_s` to `max_time_constant_s` with `elements_per_decade`,
//!   and `w = γ/(m − γ·Σ(1 − e^{−0.1 s/τₖ}))`. After a step Δ from a settled
//!   state, `ΔL(t) = Δ·(1 + S(t))`, `S(t) = w·Σ(1 − e^{−t/τₖ})`, which obeys
//!   `ΔL(t) ≈ ΔL(0.1 s)·[1 + γ·lg(t / 0.1 s)]` for `3·τ_min ≲ t ≲ τ_max/3`
//!   (ripple below ~0.1 % of ΔL with 3 elements per decade); beyond τ_max
//!   the creep saturates at the settled gain `1 + W_c`, `W_c = n·w`. It is a
//!   linear time-invariant system, so superposition makes it valid for any
//!   move history. Integration is exact for a held input (zero-order hold
//!   per pixel in scans, sub-steps ≤ τ_min/2 during moves).
//!
//! ### What a small move's slope is (read this before judging a calibration)
//! - **Fast, small moves with the hysteresis frozen see exactly `J_F(uₑ)`**,
//!   the Jacobian of the static map at the current effective input. The
//!   hysteresis is frozen while the command stays inside the dead band
//!   ([`Oracle::hysteresis_dead_band`]); after any reversal of an axis the band
//!   is at least `2·min_threshold_counts` wide (1024 counts in
//!   `sim-hopg.toml`), so skipping between atoms (10–30 counts), segment and
//!   aperture scans never move it — *except* a monotonic continuation of the
//!   last large move (e.g. the first scan lines right after a node move in
//!   the same direction), where the slope is `(1 + Σ active wᵢ)·J_F`. Approach
//!   a node with an overshoot (or scan once) to reverse both axes first.
//! - **Creep adds `S(t)`**: a move observed t seconds later has travelled
//!   `(1 + S(t))·J_F·Δu`. With the shipped creep (γ = 0.015, τ_min = 20 ms)
//!   `S(0.1 s) ≈ 1.7 %`, `S(0.3 s) ≈ 2.4 %`, `S(1 s) ≈ 3.2 %`, `S(10 s) ≈ 4.8 %`; alternating skips with period P see
//!   roughly `1 + S(P/2)` for the elements faster than P and a common-mode
//!   offset (cancelled like drift) for the slower ones. [`Oracle::creep_step_response`]
//!   gives S(t) to compute what a protocol should measure; set
//!   `scanner.creep.log_slope_per_decade = 0` to remove it.
//! - **Large-signal vs small-signal**: the major loop's midline has gain
//!   `1 + W_h` (`W_h` = total play weight) and settled creep a further
//!   `1 + W_c`, so the reference (demagnetised, settled) effective input of
//!   commanded u is `(1 + W_h)(1 + W_c)·u` ([`Oracle::reference_effective_input`]);
//!   [`Oracle::true_lcc`] evaluates `J_F` there. In `sim-hopg.toml`
//!   W_h = 0.155 (x) / 0.194 (y) and W_c = 0.081, i.e. reference gains 1.249 / 1.290:
//!   the large-signal field is ~25 % wider in nm than the small-signal
//!   sensitivity × counts, as for real PZT tubes. A node's actual `uₑ` departs
//!   from it by the history-dependent offset (up to `width·half·(1 + W_c)`
//!   plus unsettled creep), which changes the local LCCs by `F″·δuₑ`
//!   (≈ 0.2–1.5 % at the shipped nonlinearity). For 0.1 %-level checks compare
//!   a measured LCC with [`Oracle::lcc_now`] taken right after the
//!   measurement; for field-wide accuracy use [`Oracle::true_lcc`] and expect
//!   that hysteresis-induced spread.
//!
//! ## Drift and measurement
//! Drift ([`DriftConfig`]): constant velocity, warm-up exponential, velocity
//! random walk, Poisson jumps, a lateral vibration `A·cos(2πf·t + φ)` per axis
//! (building, pumps), plus drift bursts and tip-change jumps (faults).
//! Interlace (`instrument.retrace_slow_axis_advance_counts`): the controller
//! advances the slow-axis command between the two halves of every line, so the
//! second half runs that far along the slow-scan direction. Ramped
//! (`instrument.slow_axis_ramp_counts`): the slow-axis command moves on through every
//! line pair, linearly in time, as a controller that ramps its slow axis does.
//! Z: the feedback output follows `reference + topography(sample point) +
//! bowl` through a first-order lag (time constant `feedback_time_constant_s`,
//! acting along the fast axis in both trace directions); the reading adds white
//! and 1/f noise (a bank of AR(1) processes one per decade) and is rounded to
//! ADC counts if configured. Z has no hysteresis or creep in this model.
//!
//! ## Faults
//! [`Simulator::schedule_fault`] with a [`FaultTrigger`] (next call of an
//! operation, or a time) and a [`FaultKind`]; random faults at the rates of
//! [`FaultConfig`]. Timeouts, communication errors and lost feedback return a
//! [`SimError`] of the matching [`spm_hal::ErrorKind`]; tip changes and drift
//! bursts change the data only. Everything is logged with its time
//! ([`Oracle::fault_log`]), including spontaneous drift jumps.
#![doc = include_str!("../README.md")]
#![warn(missing_docs)]

pub mod config;
mod drift;
pub mod fault;
pub mod oracle;
pub mod scanner;
pub mod sim;
mod state;
pub mod surface;
pub mod vertical;

pub use config::{
    CoarseZConfig, ConfigError, CreepConfig, DomainConfig, DriftConfig, FaultConfig, HopgConfig,
    HysteresisConfig, InstrumentConfig, LatticeConfig, MeasurementConfig, NonlinearityConfig,
    ScannerConfig, Si7x7Config, SimConfig, StepEdgeConfig, SurfaceConfig, ValidationError,
};
pub use fault::{FaultEvent, FaultEventKind, FaultKind, FaultTrigger, Operation, SimError};
pub use oracle::Oracle;
pub use scanner::{Creep, Jacobian, Lcc, PlayHysteresis, StaticMap, creep_elements};
pub use sim::{RasterTurn, Simulator, SineDrive};

mod truth;
pub use oracle::{VerticalOracle, ZCrosstalk};
pub use surface::{FeatureKind, FeatureSite, Surface};
pub use vertical::{ZManipulatorConfig, ZMap};
