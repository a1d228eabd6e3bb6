//! The simulated microscope: explicit state, the `Microscope` implementation,
//! fault scheduling.

use crate::config::SimConfig;
use crate::drift::{Burst, Drift, Flicker, Jump};
use crate::fault::{FaultEvent, FaultEventKind, FaultKind, FaultTrigger, Operation, SimError};
use crate::oracle::Oracle;
use crate::scanner::{Creep, PlayHysteresis, StaticMap};
use crate::state::{ScannerState, SimState, TipState};
use crate::surface::Surface;
use crate::vertical::ZMap;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use spm_hal::{
    Capabilities, CoarseZCapability, CoarseZStage, CountPoint, Counts, Frame, Microscope,
    MoveRequest, NmPoint, NmVelocity, ScanDirection, ScanRequest, Seconds, TraceHalf, TraceImage,
};

/// Stream numbers of the independent random processes derived from the seed.
const STREAM_NOISE: u64 = 1;
const STREAM_FAULTS: u64 = 2;
/// The stream of the backward halves simulated aside ([`Simulator::record_backward_aside`]).
const STREAM_BACKWARD_ASIDE: u64 = 3;
const DRIFT_SEED_SALT: u64 = 0xD21F_7000_0000_0001;

/// Rounds to the nearest DAC/ADC code, ties towards +∞ (`floor(x + ½)`), so
/// that codes are uniform across zero: ties away from zero would map −½ and +½
/// to −1 and +1 and leave a two-code gap at code 0 (a pixel grid on half codes,
/// e.g. an even-sized raster centred on 0, would look 1/N too small there).
/// A truncating cast does the floor for |x| < 2⁵¹ (`f64::floor` is a libm call
/// on baseline x86-64); larger or non-finite values use `f64::floor`.
#[inline]
fn round_code(x: f64) -> f64 {
    let y = x + 0.5;
    if y.abs() < 2_251_799_813_685_248.0 {
        let t = (y as i64) as f64;
        if t > y { t - 1.0 } else { t }
    } else {
        y.floor()
    }
}

/// A physics-based simulated scanning tunnelling microscope.
///
/// Deterministic: all randomness comes from ChaCha8 streams seeded by
/// [`SimConfig::seed`]; there is no wall clock. Ground truth is reachable
/// only through [`Simulator::oracle`].
#[derive(Clone, Debug)]
pub struct Simulator {
    /// What the instrument is and where it stands: the state the oracle reads.
    pub(crate) state: SimState,
    flicker: Flicker,
    noise_rng: ChaCha8Rng,
    fault_rng: ChaCha8Rng,
    /// The commanded (requested) position, counts.
    command: [f64; 2],
    coarse_steps: i64,
    scheduled: Vec<(FaultTrigger, FaultKind)>,
    pending_jumps: Vec<Jump>,
    /// Tip position (scanner frame, nm) of the last simulated pixel.
    last_tip_nm: [f64; 2],
    /// Effective input (counts) of the last simulated pixel.
    last_effective: [f64; 2],
    /// While on: the random stream of the backward halves simulated aside.
    backward_aside: Option<ChaCha8Rng>,
}

/// Precomputed per-dwell factors of the pixel loop.
struct PixelFactors {
    creep_decays: Vec<f64>,
    feedback_decay: f64,
    fast_flicker: Vec<(usize, (f64, f64))>,
    /// 1/f processes slow on the pixel scale: one exact AR step per 8 pixels.
    medium_flicker: Vec<(usize, (f64, f64))>,
    slow_flicker: Vec<(usize, (f64, f64))>,
}

/// The geometry of one retrace simulated aside.
struct AsideLine {
    pixels: usize,
    runs_plus_x: bool,
    /// Where each column of the line is commanded.
    path: RasterPath,
    /// The slow-axis command at the half line's first pixel (in time), counts.
    y: f64,
    /// How far it moves on per pixel (a ramped slow axis), counts; 0 when stepped.
    y_per_pixel: f64,
    /// The field's edge the ramped command saturates at, counts.
    y_limit: f64,
    base_s: f64,
    dwell_s: f64,
}

impl AsideLine {
    /// The slow-axis command at the `pixel`-th pixel in time.
    fn y_at(&self, pixel: usize) -> f64 {
        if self.y_per_pixel == 0.0 {
            self.y
        } else {
            (self.y + self.y_per_pixel * pixel as f64).clamp(-self.y_limit, self.y_limit - 1.0)
        }
    }
}

/// Pixels per update of the medium 1/f processes.
const MEDIUM_FLICKER_PIXELS: usize = 8;

impl Simulator {
    /// A simulator in its initial state (t = 0, probe at the field centre,
    /// scanner demagnetised and settled), from a validated config.
    pub fn new(config: SimConfig) -> Result<Self, crate::ValidationError> {
        config.validate()?;
        let mut noise_rng = ChaCha8Rng::seed_from_u64(config.seed);
        noise_rng.set_stream(STREAM_NOISE);
        let mut fault_rng = ChaCha8Rng::seed_from_u64(config.seed);
        fault_rng.set_stream(STREAM_FAULTS);
        let surface = Surface::from_config(&config.surface, config.seed);
        let i = &config.instrument;
        let s = &config.scanner;
        let map = StaticMap::new(s, i.lateral_half_range_counts, i.z_half_range_counts);
        let zmap = ZMap::new(
            s.sensitivity_z_nm_per_count,
            i.z_half_range_counts,
            i.lateral_half_range_counts,
            s.z_manipulator.clone(),
        );
        let scanner = ScannerState {
            hysteresis: [
                PlayHysteresis::new(&s.hysteresis_x, i.lateral_half_range_counts, 0.0),
                PlayHysteresis::new(&s.hysteresis_y, i.lateral_half_range_counts, 0.0),
            ],
            creep: [Creep::new(&s.creep, 0.0), Creep::new(&s.creep, 0.0)],
            applied: [0.0; 2],
            input: [0.0; 2],
            creep_offset: [0.0; 2],
        };
        let drift = Drift::new(&config.drift, config.seed ^ DRIFT_SEED_SALT);
        let m = &config.measurement;
        let flicker = Flicker::new(
            m.z_flicker_noise_nm,
            m.flicker_min_frequency_hz,
            m.flicker_max_frequency_hz,
            &mut noise_rng,
        );
        let mut sim = Self {
            state: SimState {
                surface,
                map,
                zmap,
                scanner,
                drift,
                time_s: 0.0,
                z_nm: 0.0,
                tip: TipState::PRISTINE,
                log: Vec::new(),
                tip_trace: None,
                effective_trace: None,
                config,
            },
            flicker,
            noise_rng,
            fault_rng,
            command: [0.0; 2],
            coarse_steps: 0,
            scheduled: Vec::new(),
            pending_jumps: Vec::new(),
            last_tip_nm: [0.0; 2],
            last_effective: [0.0; 2],
            backward_aside: None,
        };
        sim.state.z_nm = sim.z_reference_nm();
        sim.state.z_nm = sim.feedback_target_nm(0.0, None);
        // Two passes settle the Z-dependent lateral position.
        sim.state.z_nm = sim.feedback_target_nm(0.0, None);
        tracing::debug!(seed = sim.state.config.seed, "spm-sim simulator created");
        Ok(sim)
    }

    /// Turns the recording of true tip positions on or off. While on, every
    /// scan keeps the scanner-frame tip position (nm; hysteresis and creep as
    /// they acted, no drift, no jitter) of each forward-trace pixel, in
    /// acquisition order, for [`Oracle::last_scan_tip_positions`]. Ground
    /// truth for benchmarks; it changes nothing the instrument measures.
    pub fn record_tip_positions(&mut self, on: bool) {
        self.state.tip_trace = on.then(Vec::new);
        self.state.effective_trace = on.then(Vec::new);
    }

    /// Turns the backward halves simulated aside on or off. While on, a scan whose request
    /// does not record the backward half still returns it: each retrace is simulated pixel by
    /// pixel from a copy of the instrument's state (its own random stream, no fault events),
    /// and the instrument then runs that retrace exactly as it would unrecorded. So the forward
    /// data, the state and every random stream go on bit for bit as without it (the image
    /// benchmark's per-image trace/retrace methods read the retrace; the other methods'
    /// figures do not move). Requests that record the backward half are simulated in line as
    /// always.
    pub fn record_backward_aside(&mut self, on: bool) {
        self.backward_aside = on.then(|| {
            let mut rng = ChaCha8Rng::seed_from_u64(self.state.config.seed);
            rng.set_stream(STREAM_BACKWARD_ASIDE);
            rng
        });
    }

    /// The configuration this simulator runs.
    pub fn config(&self) -> &SimConfig {
        &self.state.config
    }

    /// The ground-truth view (tests, benchmarks, xtask; never algorithms).
    pub fn oracle(&self) -> Oracle<'_> {
        Oracle::new(&self.state)
    }

    /// Schedules a fault. See [`FaultKind`] and [`FaultTrigger`] for the semantics.
    pub fn schedule_fault(&mut self, trigger: FaultTrigger, kind: FaultKind) {
        tracing::debug!(?trigger, ?kind, "fault scheduled");
        self.scheduled.push((trigger, kind));
    }

    /// Scheduled faults not fired yet.
    pub fn pending_faults(&self) -> usize {
        self.scheduled.len()
    }

    /// Replaces the random fault rates (e.g. to switch random faults off mid-run).
    pub fn set_fault_rates(&mut self, faults: crate::config::FaultConfig) {
        self.state.config.faults = faults;
    }

    // ------------------------------------------------------------------
    // Physics helpers

    /// Z reading (nm) of the reference plane at the current coarse position.
    fn z_reference_nm(&self) -> f64 {
        let step = self
            .state
            .config
            .instrument
            .coarse_z
            .as_ref()
            .map_or(0.0, |c| c.step_nm);
        self.state.config.instrument.initial_z_extension_nm - self.coarse_steps as f64 * step
    }

    /// Image height of the surface under sample point `s` with the current tip.
    #[inline]
    fn topography_nm(&self, s: [f64; 2]) -> f64 {
        let z = self.state.surface.height_nm(s[0], s[1]);
        if self.state.tip == TipState::PRISTINE {
            z
        } else {
            let mut out = self.state.tip.contrast * z;
            if self.state.tip.ghost_amplitude > 0.0 {
                out += self.state.tip.ghost_amplitude
                    * self.state.tip.contrast
                    * self.state.surface.height_nm(
                        s[0] + self.state.tip.ghost_offset[0],
                        s[1] + self.state.tip.ghost_offset[1],
                    );
            }
            out
        }
    }

    /// The Z reading (nm) the feedback converges to at time t, with an
    /// optional lateral jitter.
    fn feedback_target_nm(&self, t_s: f64, jitter: Option<[f64; 2]>) -> f64 {
        let p = self.state.scanner_position_nm();
        let d = self.state.drift.displacement(t_s);
        let j = jitter.unwrap_or([0.0; 2]);
        let s = [p[0] + d[0] + j[0], p[1] + d[1] + j[1]];
        self.z_reference_nm() + self.topography_nm(s) + self.state.map.bowl_nm(p)
    }

    fn normal(&mut self) -> f64 {
        self.noise_rng.sample(StandardNormal)
    }

    fn quantise_lateral(&self, u: [f64; 2]) -> [f64; 2] {
        if self.state.config.measurement.quantise_lateral_dac {
            [round_code(u[0]), round_code(u[1])]
        } else {
            u
        }
    }

    /// A single noisy Z reading in counts from the current feedback state.
    fn read_z_counts(&mut self) -> f64 {
        let white = self.state.config.measurement.z_white_noise_nm;
        let n = if white > 0.0 {
            white * self.normal()
        } else {
            0.0
        };
        let z = self.state.zmap.counts_of(
            self.state.z_nm + n + self.flicker.value(),
            self.state.scanner.effective(),
        );
        if self.state.config.measurement.quantise_z_adc {
            round_code(z)
        } else {
            z
        }
    }

    /// Advances the clock by `dt` with the command held: creep, drift,
    /// flicker and the feedback evolve; events inside are handled.
    fn idle(&mut self, dt_s: f64, operation: Operation) -> Result<(), SimError> {
        if dt_s <= 0.0 {
            return Ok(());
        }
        let t0 = self.state.time_s;
        let t1 = t0 + dt_s;
        let events = self.events_in(t0, t1, true);
        let mut t = t0;
        for (te, kind, scheduled) in events {
            let te = te.clamp(t, t1);
            self.evolve_held(te - t);
            t = te;
            self.fire(te, kind, Some(operation), scheduled)?;
        }
        self.evolve_held(t1 - t);
        Ok(())
    }

    /// Evolves the state by dt with the command held, no events.
    fn evolve_held(&mut self, dt_s: f64) {
        if dt_s <= 0.0 {
            return;
        }
        self.state.scanner.advance(dt_s);
        self.state.time_s += dt_s;
        self.state.zmap.set_time(self.state.time_s);
        self.flush_drift(self.state.time_s);
        self.flicker.advance_all(dt_s, &mut self.noise_rng);
        let target = self.feedback_target_nm(self.state.time_s, None);
        let tau = self.state.config.measurement.feedback_time_constant_s;
        let decay = if tau > 0.0 { (-dt_s / tau).exp() } else { 0.0 };
        self.state.z_nm = target + (self.state.z_nm - target) * decay;
    }

    /// Generates drift knots up to t and logs the spontaneous jumps that are due.
    fn flush_drift(&mut self, t_s: f64) {
        let new = self.state.drift.ensure(t_s + 1.0);
        self.pending_jumps.extend(new);
        let mut k = 0;
        while k < self.pending_jumps.len() {
            if let Some(jump) = self.pending_jumps.get(k).copied()
                && jump.time_s <= t_s
            {
                self.pending_jumps.swap_remove(k);
                self.state.log.push(FaultEvent {
                    time: Seconds(jump.time_s),
                    kind: FaultEventKind::DriftJump,
                    duration: Seconds::ZERO,
                    operation: None,
                    scheduled: false,
                });
                continue;
            }
            k += 1;
        }
    }

    /// Moves the command along a straight line to `target` at `speed`.
    fn travel(
        &mut self,
        target: [f64; 2],
        speed_counts_per_s: f64,
        operation: Operation,
    ) -> Result<(), SimError> {
        let start = self.command;
        let length = (target[0] - start[0]).hypot(target[1] - start[1]);
        if length == 0.0 {
            self.command = target;
            let q = self.quantise_lateral(target);
            self.state.scanner.set(q);
            return Ok(());
        }
        let duration = length / speed_counts_per_s;
        let min_tau = self.state.scanner.creep[0]
            .time_constants_s()
            .first()
            .copied()
            .unwrap_or(f64::INFINITY)
            .min(
                self.state
                    .config
                    .measurement
                    .feedback_time_constant_s
                    .max(1e-6)
                    * 20.0,
            );
        let steps = ((duration / (0.5 * min_tau)).ceil())
            .max((length / 64.0).ceil())
            .clamp(1.0, 4000.0) as usize;
        let dt = duration / steps as f64;
        let t0 = self.state.time_s;
        let events = self.events_in(t0, t0 + duration, true);
        let mut next = 0;
        for k in 1..=steps {
            let f = k as f64 / steps as f64;
            let u = [
                start[0] + (target[0] - start[0]) * f,
                start[1] + (target[1] - start[1]) * f,
            ];
            self.command = u;
            let q = self.quantise_lateral(u);
            self.state.scanner.set(q);
            self.evolve_held(dt);
            while let Some((te, kind, scheduled)) = events.get(next).copied() {
                if te > self.state.time_s {
                    break;
                }
                next += 1;
                self.fire(te, kind, Some(operation), scheduled)?;
            }
        }
        self.command = target;
        Ok(())
    }

    // ------------------------------------------------------------------
    // Faults

    /// Random and scheduled events with times in `[t0, t1]`, sorted.
    fn events_in(&mut self, t0: f64, t1: f64, feedback: bool) -> Vec<(f64, FaultKind, bool)> {
        let mut out = Vec::new();
        let f = self.state.config.faults.clone();
        let draw = |rate: f64, rng: &mut ChaCha8Rng| -> Option<f64> {
            if rate <= 0.0 {
                return None;
            }
            let u: f64 = rng.random();
            let t = t0 - (1.0 - u).ln() / rate;
            (t <= t1).then_some(t)
        };
        if feedback && let Some(t) = draw(f.feedback_lost_rate_per_s, &mut self.fault_rng) {
            out.push((t, FaultKind::FeedbackLost, false));
        }
        if let Some(t) = draw(f.tip_change_rate_per_s, &mut self.fault_rng) {
            let kind = self.random_tip_change();
            out.push((t, kind, false));
        }
        if let Some(t) = draw(f.drift_burst_rate_per_s, &mut self.fault_rng) {
            let angle: f64 = self.fault_rng.random::<f64>() * std::f64::consts::TAU;
            out.push((
                t,
                FaultKind::DriftBurst {
                    velocity: NmVelocity {
                        x_nm_per_s: f.drift_burst_speed_nm_per_s * angle.cos(),
                        y_nm_per_s: f.drift_burst_speed_nm_per_s * angle.sin(),
                    },
                    duration: Seconds(f.drift_burst_duration_s),
                },
                false,
            ));
        }
        let mut k = 0;
        while k < self.scheduled.len() {
            let fire = match self.scheduled.get(k) {
                Some((FaultTrigger::AtTime(t), kind)) => {
                    let call_fault = matches!(kind, FaultKind::Timeout | FaultKind::Communication);
                    let feedback_ok = feedback || !matches!(kind, FaultKind::FeedbackLost);
                    !call_fault && feedback_ok && t.value() <= t1
                }
                _ => false,
            };
            if fire {
                let (trigger, kind) = self.scheduled.remove(k);
                if let FaultTrigger::AtTime(t) = trigger {
                    out.push((t.value().max(t0), kind, true));
                }
            } else {
                k += 1;
            }
        }
        out.sort_by(|a, b| a.0.total_cmp(&b.0));
        out
    }

    fn random_tip_change(&mut self) -> FaultKind {
        let sigma = self.state.config.faults.tip_change_jump_sigma_nm;
        let jx: f64 = self.fault_rng.sample(StandardNormal);
        let jy: f64 = self.fault_rng.sample(StandardNormal);
        let c: f64 = self.fault_rng.sample(StandardNormal);
        let ghost: f64 = self.fault_rng.random();
        let gx: f64 = self.fault_rng.sample(StandardNormal);
        let gy: f64 = self.fault_rng.sample(StandardNormal);
        let amplitude: f64 = self.fault_rng.random();
        FaultKind::TipChange {
            jump: NmPoint::from_nm(sigma * jx, sigma * jy),
            contrast_factor: (0.3 * c).exp().clamp(0.3, 3.0),
            ghost_offset: NmPoint::from_nm(0.3 * gx, 0.3 * gy),
            ghost_amplitude: if ghost < 0.3 {
                0.2 + 0.4 * amplitude
            } else {
                0.0
            },
        }
    }

    /// Applies an event at time t: logs it, changes the state, and returns
    /// the error for failing kinds.
    fn fire(
        &mut self,
        t_s: f64,
        kind: FaultKind,
        operation: Option<Operation>,
        scheduled: bool,
    ) -> Result<(), SimError> {
        let op = operation.unwrap_or(Operation::Now);
        let log = |sim: &mut Self, k: FaultEventKind, duration: f64| {
            tracing::debug!(time_s = t_s, kind = ?k, ?operation, scheduled, "simulated fault");
            sim.state.log.push(FaultEvent {
                time: Seconds(t_s),
                kind: k,
                duration: Seconds(duration),
                operation,
                scheduled,
            });
        };
        match kind {
            FaultKind::Timeout => {
                log(self, FaultEventKind::Timeout, 0.0);
                let d = self.state.config.faults.timeout_duration_s;
                self.evolve_held(d);
                Err(SimError::Timeout {
                    operation: op,
                    time: Seconds(self.state.time_s),
                })
            }
            FaultKind::Communication => {
                log(self, FaultEventKind::Communication, 0.0);
                Err(SimError::Communication {
                    operation: op,
                    time: Seconds(t_s),
                })
            }
            FaultKind::FeedbackLost => {
                log(self, FaultEventKind::FeedbackLost, 0.0);
                Err(SimError::FeedbackLost {
                    operation: op,
                    time: Seconds(t_s),
                })
            }
            FaultKind::TipChange {
                jump,
                contrast_factor,
                ghost_offset,
                ghost_amplitude,
            } => {
                log(self, FaultEventKind::TipChange, 0.0);
                self.state.drift.add_tip_jump(Jump {
                    time_s: t_s,
                    displacement_nm: [jump.x.value(), jump.y.value()],
                });
                self.state.tip = TipState {
                    contrast: if contrast_factor.is_finite() && contrast_factor > 0.0 {
                        self.state.tip.contrast * contrast_factor
                    } else {
                        self.state.tip.contrast
                    },
                    ghost_offset: [ghost_offset.x.value(), ghost_offset.y.value()],
                    ghost_amplitude: if ghost_amplitude.is_finite() {
                        ghost_amplitude.max(0.0)
                    } else {
                        0.0
                    },
                };
                Ok(())
            }
            FaultKind::DriftBurst { velocity, duration } => {
                let d = if duration.value().is_finite() {
                    duration.value().max(0.0)
                } else {
                    0.0
                };
                log(self, FaultEventKind::DriftBurst, d);
                let v = [velocity.x_nm_per_s, velocity.y_nm_per_s];
                if v.iter().all(|x| x.is_finite()) {
                    self.state.drift.add_burst(Burst {
                        start_s: t_s,
                        duration_s: d,
                        velocity_nm_per_s: v,
                    });
                }
                Ok(())
            }
        }
    }

    /// Start of every call: overhead, call-level faults (scheduled and random).
    fn begin_call(&mut self, operation: Operation, overhead: bool) -> Result<(), SimError> {
        if overhead {
            let d = self.state.config.instrument.call_overhead_s;
            self.idle(d, operation)?;
        }
        let now = self.state.time_s;
        // Scheduled faults for this call.
        let mut k = 0;
        while k < self.scheduled.len() {
            let due = match self.scheduled.get(k) {
                Some((FaultTrigger::NextCall(op), _)) => *op == operation,
                Some((FaultTrigger::AtTime(t), kind)) => {
                    t.value() <= now
                        && (matches!(kind, FaultKind::Timeout | FaultKind::Communication)
                            || matches!(kind, FaultKind::FeedbackLost))
                }
                None => false,
            };
            if due {
                let (_, kind) = self.scheduled.remove(k);
                self.fire(now, kind, Some(operation), true)?;
            } else {
                k += 1;
            }
        }
        if overhead {
            let p_timeout = self.state.config.faults.timeout_probability_per_call;
            let p_comm = self.state.config.faults.communication_probability_per_call;
            if p_timeout > 0.0 || p_comm > 0.0 {
                let u: f64 = self.fault_rng.random();
                if u < p_timeout {
                    return self.fire(now, FaultKind::Timeout, Some(operation), false);
                }
                if u < p_timeout + p_comm {
                    return self.fire(now, FaultKind::Communication, Some(operation), false);
                }
            }
        }
        Ok(())
    }

    fn check_point(&self, p: CountPoint, what: &str) -> Result<[f64; 2], SimError> {
        if !p.is_finite() {
            return Err(SimError::InvalidRequest {
                reason: format!("{what} is not finite"),
            });
        }
        let h = self.state.config.instrument.lateral_half_range_counts;
        let (x, y) = (p.x.value(), p.y.value());
        if x < -h || y < -h || x > h - 1.0 || y > h - 1.0 {
            return Err(SimError::OutOfRange {
                reason: format!("{what} ({x}, {y}) counts is outside [{}, {}]", -h, h - 1.0),
            });
        }
        Ok([x, y])
    }

    // ------------------------------------------------------------------
    // The scan

    fn pixel_factors(&self, dwell_s: f64, line_s: f64) -> PixelFactors {
        let tau = self.state.config.measurement.feedback_time_constant_s;
        let mut fast = Vec::new();
        let mut medium = Vec::new();
        let mut slow = Vec::new();
        for k in 0..self.flicker.len() {
            let f = self.flicker.corner_hz(k);
            let w = 2.0 * std::f64::consts::PI * f;
            if w * dwell_s >= 0.05 {
                fast.push((k, self.flicker.coefficients(k, dwell_s)));
            } else if w * line_s >= 0.1 {
                let block = MEDIUM_FLICKER_PIXELS as f64 * dwell_s;
                medium.push((k, self.flicker.coefficients(k, block)));
            } else {
                slow.push((k, self.flicker.coefficients(k, line_s)));
            }
        }
        PixelFactors {
            creep_decays: self.state.scanner.creep[0].decays(dwell_s),
            feedback_decay: if tau > 0.0 {
                (-dwell_s / tau).exp()
            } else {
                0.0
            },
            fast_flicker: fast,
            medium_flicker: medium,
            slow_flicker: slow,
        }
    }

    /// One pixel: command u over one dwell ending at `t_end`; returns the Z reading (counts).
    #[inline]
    fn pixel(&mut self, u: [f64; 2], t_mid: f64, f: &PixelFactors, record: bool) -> f64 {
        let q = self.quantise_lateral(u);
        self.state.scanner.set(q);
        self.state.zmap.set_time(t_mid);
        let x = self.state.scanner.input;
        self.state.scanner.creep_offset = [
            self.state.scanner.creep[0].advance_with(x[0], &f.creep_decays),
            self.state.scanner.creep[1].advance_with(x[1], &f.creep_decays),
        ];
        let ue = self.state.scanner.effective();
        let kz = self.state.map.kz_nm_per_count();
        let p = self.state.map.position(ue[0], ue[1], self.state.z_nm / kz);
        self.last_tip_nm = p;
        self.last_effective = ue;
        let d = self.state.drift.displacement(t_mid);
        let jitter = self.state.config.measurement.lateral_jitter_nm;
        let (jx, jy) = if jitter > 0.0 {
            (jitter * self.normal(), jitter * self.normal())
        } else {
            (0.0, 0.0)
        };
        let s = [p[0] + d[0] + jx, p[1] + d[1] + jy];
        let target = self.z_reference_nm() + self.topography_nm(s) + self.state.map.bowl_nm(p);
        self.state.z_nm = target + (self.state.z_nm - target) * f.feedback_decay;
        for &(k, c) in &f.fast_flicker {
            self.flicker.step(k, c, &mut self.noise_rng);
        }
        if !record {
            return 0.0;
        }
        let white = self.state.config.measurement.z_white_noise_nm;
        let n = if white > 0.0 {
            white * self.normal()
        } else {
            0.0
        };
        let z = self
            .state
            .zmap
            .counts_of(self.state.z_nm + n + self.flicker.value(), ue);
        if self.state.config.measurement.quantise_z_adc {
            round_code(z)
        } else {
            z
        }
    }

    /// One retrace simulated aside (see [`Simulator::record_backward_aside`]): pixel by pixel
    /// from a copy of the state, with the aside random stream and no fault events; the state
    /// and the instrument's own streams are put back as they were. Appends to `out`.
    fn retrace_aside(&mut self, line: &AsideLine, f: &PixelFactors, out: &mut TraceImage) {
        let Some(mut rng) = self.backward_aside.take() else {
            return;
        };
        let saved = (
            self.state.scanner.clone(),
            self.state.zmap.clone(),
            self.flicker.clone(),
            self.state.z_nm,
            self.state.time_s,
            self.command,
            self.last_tip_nm,
            self.last_effective,
        );
        std::mem::swap(&mut self.noise_rng, &mut rng);
        for pixel in 0..line.pixels {
            let t_mid = line.base_s + (pixel as f64 + 0.5) * line.dwell_s;
            if pixel % MEDIUM_FLICKER_PIXELS == 0 {
                for &(k, c) in &f.medium_flicker {
                    self.flicker.step(k, c, &mut self.noise_rng);
                }
            }
            let column = if line.runs_plus_x {
                pixel
            } else {
                line.pixels - 1 - pixel
            };
            let p = line.path.command(column, line.y_at(pixel));
            self.command = p;
            let z = self.pixel(p, t_mid, f, true);
            out.z_counts.push(z);
            out.time_s.push(t_mid);
        }
        std::mem::swap(&mut self.noise_rng, &mut rng);
        self.backward_aside = Some(rng);
        (
            self.state.scanner,
            self.state.zmap,
            self.flicker,
            self.state.z_nm,
            self.state.time_s,
            self.command,
            self.last_tip_nm,
            self.last_effective,
        ) = saved;
    }

    /// Refuses a scan request the instrument cannot take: invalid, beyond the pixel,
    /// dwell or counter-scan capabilities, or (along `path`, when it is not the plain
    /// raster) outside the field.
    fn check_scan(&self, request: &ScanRequest, path: &RasterPath) -> Result<(), SimError> {
        request.validate().map_err(|e| SimError::InvalidRequest {
            reason: e.to_string(),
        })?;
        let caps = self.capabilities();
        if request.pixels_per_line > caps.max_pixels_per_line || request.lines > caps.max_lines {
            return Err(SimError::OutOfRange {
                reason: format!(
                    "{}×{} pixels exceed the maximum {}×{}",
                    request.pixels_per_line,
                    request.lines,
                    caps.max_pixels_per_line,
                    caps.max_lines
                ),
            });
        }
        if request.pixel_dwell < caps.min_pixel_dwell {
            return Err(SimError::OutOfRange {
                reason: format!(
                    "pixel dwell {} is below the minimum {}",
                    request.pixel_dwell, caps.min_pixel_dwell
                ),
            });
        }
        if request.direction == ScanDirection::Counter && !caps.counter_scan {
            return Err(SimError::OutOfRange {
                reason: "counter scans are not supported by this configuration".to_owned(),
            });
        }
        if path.is_plain() {
            request.check_inside(caps.field_min, caps.field_max)
        } else {
            path.check_inside(request, caps.field_min, caps.field_max)
        }
        .map_err(|e| SimError::OutOfRange {
            reason: e.to_string(),
        })
    }

    /// The fast path for unrecorded retraces, when it applies: with the hysteresis
    /// frozen and the commanded x a linear ramp, creep is advanced in closed form
    /// (exact), fast 1/f processes by one exact AR step; only the last 12 feedback time
    /// constants are simulated pixel by pixel, because they set the feedback state at the
    /// next trace's start (the lag error left over is e^-12 ≈ 6e-6 of the step, far below
    /// an ADC count).
    fn lumped_retrace(
        &self,
        request: &ScanRequest,
        factors: &PixelFactors,
        (plain, record_backward): (bool, bool),
    ) -> Option<LumpedRetrace> {
        let nx = request.pixels_per_line as usize;
        let dwell = request.pixel_dwell.value();
        let step = request.pixel_step.value();
        let tau_fb = self.state.config.measurement.feedback_time_constant_s;
        let tail = if tau_fb > 0.0 {
            ((12.0 * tau_fb / dwell).ceil() as usize).clamp(2, nx)
        } else {
            2.min(nx)
        };
        let lumped_n = nx - tail;
        let quantise = self.state.config.measurement.quantise_lateral_dac;
        let ox = request.origin.x.value();
        let x_lo = ox;
        let x_hi = ox + step * (nx - 1) as f64;
        // With DAC rounding the ramp stays linear when the step is whole and
        // the rounded ends are exactly (nx − 1) steps apart.
        let linear_x = !quantise
            || (step.fract() == 0.0
                && round_code(x_hi) - round_code(x_lo) == step * (nx - 1) as f64);
        let (x_lo, x_hi) = if quantise {
            (round_code(x_lo), round_code(x_hi))
        } else {
            (x_lo, x_hi)
        };
        let advance = self
            .state
            .config
            .instrument
            .retrace_slow_axis_advance_counts;
        let ramp = self.state.config.instrument.slow_axis_ramp_counts;
        if !plain || record_backward || lumped_n < 8 || !linear_x || advance != 0.0 || ramp != 0.0 {
            return None;
        }
        let creep = self.state.scanner.creep[0].ramp_coefficients(&factors.creep_decays, lumped_n);
        // The medium processes miss the updates of the skipped pixels
        // 0, 8, 16, … < lumped_n: one AR step covers their blocks.
        let medium_blocks = lumped_n.div_ceil(MEDIUM_FLICKER_PIXELS);
        let medium_s = (medium_blocks * MEDIUM_FLICKER_PIXELS) as f64 * dwell;
        let flicker: Vec<(usize, (f64, f64))> = factors
            .fast_flicker
            .iter()
            .map(|&(k, _)| (k, self.flicker.coefficients(k, lumped_n as f64 * dwell)))
            .chain(
                factors
                    .medium_flicker
                    .iter()
                    .map(|&(k, _)| (k, self.flicker.coefficients(k, medium_s))),
            )
            .collect();
        Some(LumpedRetrace {
            pixels: lumped_n,
            x_range: (x_lo, x_hi),
            creep,
            flicker,
        })
    }

    /// Skips the first `plan.pixels` of an unrecorded retrace starting at `base_s` in
    /// closed form when the hysteresis is frozen over the ramp: the pixel the line goes
    /// on from (0 when it cannot).
    fn skip_retrace(&mut self, plan: &LumpedRetrace, line: &AsideLine, next_event_t: f64) -> usize {
        let (dwell, step, lumped_n) = (line.dwell_s, line.path.step_counts, plan.pixels);
        if next_event_t <= line.base_s + lumped_n as f64 * dwell {
            return 0;
        }
        let (x_lo, x_hi) = plan.x_range;
        let (lo, hi) = self.state.scanner.hysteresis[0].dead_band();
        if !(lo <= x_lo && x_hi <= hi) {
            return 0;
        }
        let (a, b) = if line.runs_plus_x {
            (x_lo, step)
        } else {
            (x_hi, -step)
        };
        let hx = self.state.scanner.hysteresis[0].offset();
        let y_in = self.state.scanner.input[1];
        self.state.scanner.creep_offset = [
            self.state.scanner.creep[0].advance_ramp(&plan.creep, a + hx, b),
            self.state.scanner.creep[1].advance_ramp(&plan.creep, y_in, 0.0),
        ];
        for &(k, c) in &plan.flicker {
            self.flicker.step(k, c, &mut self.noise_rng);
        }
        let x_last = a + b * (lumped_n - 1) as f64;
        self.command = [x_last, line.y];
        let q = self.quantise_lateral([x_last, line.y]);
        self.state.scanner.set(q);
        self.state.time_s = line.base_s + lumped_n as f64 * dwell;
        lumped_n
    }

    /// The pixels `first_pixel..` of one half line, with the events due on the way
    /// fired; each pixel's height into `out` (with the tip's and the effective
    /// position's traces on the forward half).
    fn scan_half_line(
        &mut self,
        line: &AsideLine,
        (half, first_pixel): (TraceHalf, usize),
        factors: &PixelFactors,
        events: &mut EventCursor,
        out: Option<&mut TraceImage>,
    ) -> Result<(), SimError> {
        let (nx, dwell) = (line.pixels, line.dwell_s);
        let record = out.is_some();
        let mut out = out;
        for pixel in first_pixel..nx {
            let t_mid = line.base_s + (pixel as f64 + 0.5) * dwell;
            if t_mid >= events.next_t {
                while let Some((te, kind, scheduled)) = events.list.get(events.next).copied() {
                    if te > t_mid {
                        break;
                    }
                    events.next += 1;
                    if let Err(e) = self.fire(te, kind, Some(Operation::Scan), scheduled) {
                        // The scan stops at this pixel.
                        self.state.time_s = te.max(t_mid - 0.5 * dwell);
                        return Err(e);
                    }
                }
                events.next_t = events.list.get(events.next).map_or(f64::INFINITY, |e| e.0);
            }
            if pixel % MEDIUM_FLICKER_PIXELS == 0 {
                for &(k, c) in &factors.medium_flicker {
                    self.flicker.step(k, c, &mut self.noise_rng);
                }
            }
            let column = if line.runs_plus_x {
                pixel
            } else {
                nx - 1 - pixel
            };
            let p = line.path.command(column, line.y_at(pixel));
            self.command = p;
            let z = self.pixel(p, t_mid, factors, record);
            if let Some(o) = out.as_mut() {
                o.z_counts.push(z);
                o.time_s.push(t_mid);
            }
            if half == TraceHalf::Forward {
                if let Some(trace) = self.state.tip_trace.as_mut() {
                    trace.push(self.last_tip_nm);
                }
                if let Some(trace) = self.state.effective_trace.as_mut() {
                    trace.push(self.last_effective);
                }
            }
            self.state.time_s = t_mid + 0.5 * dwell;
        }
        Ok(())
    }

    /// A raster's physics in acquisition order: the approach to the first pixel, then per
    /// line the slow flicker, the forward and backward halves (the retrace set aside or
    /// skipped in closed form when it is not recorded), the events due on the way.
    fn scan_impl(
        &mut self,
        request: &ScanRequest,
        turn: Option<RasterTurn>,
        drive: Option<SineDrive>,
    ) -> Result<Frame, SimError> {
        self.begin_call(Operation::Scan, true)?;
        let path = RasterPath::new(request, turn, drive)?;
        self.check_scan(request, &path)?;
        let caps = self.capabilities();
        let nx = request.pixels_per_line as usize;
        let ny = request.lines as usize;
        let dwell = request.pixel_dwell.value();
        let step = request.pixel_step.value();
        // Approach the first pixel at the scan speed.
        let (column, _) = request.geometric_index(TraceHalf::Forward, 0, 0);
        let first = request.commanded_position(TraceHalf::Forward, 0, 0);
        self.travel(
            path.command(column, first.y.value()),
            step / dwell,
            Operation::Scan,
        )?;
        for trace in [
            self.state.tip_trace.as_mut(),
            self.state.effective_trace.as_mut(),
        ]
        .into_iter()
        .flatten()
        {
            trace.clear();
            trace.reserve(nx * ny);
        }
        let start = self.state.time_s;
        let line_s = 2.0 * nx as f64 * dwell;
        let end = start + line_s * ny as f64;
        self.flush_drift(end);
        let list = self.events_in(start, end, true);
        let mut events = EventCursor {
            next_t: list.first().map_or(f64::INFINITY, |e| e.0),
            next: 0,
            list,
        };
        let factors = self.pixel_factors(dwell, line_s);
        let record_backward = request.record_backward && caps.backward_trace;
        let image = || TraceImage {
            z_counts: Vec::with_capacity(nx * ny),
            time_s: Vec::with_capacity(nx * ny),
        };
        let mut forward = image();
        let mut backward = record_backward.then(image);
        let mut aside = (!record_backward && self.backward_aside.is_some()).then(image);
        let oy = request.origin.y.value();
        // Interlace: the second half of every line runs `advance` counts further
        // along the slow-scan direction (the command saturates at the field edge).
        let advance = self
            .state
            .config
            .instrument
            .retrace_slow_axis_advance_counts
            * match request.direction {
                ScanDirection::Direct => 1.0,
                ScanDirection::Counter => -1.0,
            };
        // Ramped: the slow axis moves on through the line pair, along the slow direction.
        let ramp_per_pixel = self.state.config.instrument.slow_axis_ramp_counts
            * match request.direction {
                ScanDirection::Direct => 1.0,
                ScanDirection::Counter => -1.0,
            }
            / (2 * nx) as f64;
        let field_h = self.state.config.instrument.lateral_half_range_counts;
        let lumped = self.lumped_retrace(request, &factors, (path.is_plain(), backward.is_some()));
        for line in 0..ny {
            let row = match request.direction {
                ScanDirection::Direct => line,
                ScanDirection::Counter => ny - 1 - line,
            };
            let y = oy + step * row as f64;
            for &(k, c) in &factors.slow_flicker {
                self.flicker.step(k, c, &mut self.noise_rng);
            }
            for half in [TraceHalf::Forward, TraceHalf::Backward] {
                let runs_plus_x = matches!(
                    (request.direction, half),
                    (ScanDirection::Direct, TraceHalf::Forward)
                        | (ScanDirection::Counter, TraceHalf::Backward)
                );
                let half_index = if half == TraceHalf::Forward { 0 } else { 1 };
                let y = if half == TraceHalf::Backward && advance != 0.0 {
                    (y + advance).clamp(-field_h, field_h - 1.0)
                } else {
                    y
                };
                let y = y + ramp_per_pixel * (half_index * nx) as f64;
                let half_line = AsideLine {
                    pixels: nx,
                    runs_plus_x,
                    path,
                    y,
                    y_per_pixel: ramp_per_pixel,
                    y_limit: field_h,
                    base_s: start + ((2 * line + half_index) * nx) as f64 * dwell,
                    dwell_s: dwell,
                };
                if half == TraceHalf::Backward
                    && let Some(out) = aside.as_mut()
                {
                    self.retrace_aside(&half_line, &factors, out);
                }
                let first_pixel = match lumped.as_ref() {
                    Some(plan) if half == TraceHalf::Backward => {
                        self.skip_retrace(plan, &half_line, events.next_t)
                    }
                    _ => 0,
                };
                let out = match half {
                    TraceHalf::Forward => Some(&mut forward),
                    TraceHalf::Backward => backward.as_mut(),
                };
                self.scan_half_line(&half_line, (half, first_pixel), &factors, &mut events, out)?;
            }
        }
        self.state.time_s = end;
        self.flush_drift(end);
        Ok(Frame {
            request: request.clone(),
            forward,
            backward: backward.or(aside),
        })
    }
}

/// The closed-form skip of an unrecorded retrace's first pixels
/// ([`Simulator::lumped_retrace`]).
struct LumpedRetrace {
    /// Pixels skipped.
    pixels: usize,
    /// The commanded x of the line's ends (DAC-rounded when the DAC is), counts.
    x_range: (f64, f64),
    /// The creep elements' ramp coefficients over the skipped pixels.
    creep: Vec<[f64; 3]>,
    /// The fast and medium flicker processes' AR coefficients over them.
    flicker: Vec<(usize, (f64, f64))>,
}

/// The faults scheduled inside a scan, and the next to fire.
struct EventCursor {
    /// (time s, kind, scheduled) in time order.
    list: Vec<(f64, FaultKind, bool)>,
    /// The next to fire.
    next: usize,
    /// Its time, s (∞ when none is left).
    next_t: f64,
}

/// A raster turned about a point, as a controller's frame angle turns its frame: every
/// commanded position of the raster turned by `angle_rad` (counter-clockwise) about
/// `centre`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RasterTurn {
    /// The point turned about, counts.
    pub centre: CountPoint,
    /// The angle, radians, counter-clockwise.
    pub angle_rad: f64,
}

impl RasterTurn {
    fn apply(&self, x: f64, y: f64) -> [f64; 2] {
        let (s, c) = self.angle_rad.sin_cos();
        let (cx, cy) = (self.centre.x.value(), self.centre.y.value());
        let (dx, dy) = (x - cx, y - cy);
        [cx + c * dx - s * dy, cy + s * dx + c * dy]
    }
}

/// A fast axis driven by a sine, as a fast-SPM's resonant scanner drives it: each line's
/// fast-axis command follows x(t) = c + A·sin(β·ξ) with ξ = 2(t − t_mid)/T_line ∈ [−1, 1]
/// over the line's duration T_line (`pixels_per_line` dwells; t_mid its middle), while the
/// pixels are recorded equidistant in time as on the linear raster. The file's nominal
/// position stays linear in time, u = c + W·ξ (c the raster's centre column, W = N·step/2
/// its half-width, N the pixels per line): the amplitude A = W/sin β makes the line's ends
/// (ξ = ±1) meet the raster's ends, so the frame's request (its origin, step and pixel count)
/// is the nominal raster the file expects. Pixel k of a trace (its dwell's middle at
/// ξ_k = (2k + 1 − N)/N) is commanded at c + A·sin(β·ξ_k) and held over its dwell, as the
/// linear raster holds c + W·ξ_k; the retrace runs the other half-period with ξ reversed,
/// the same map. It is the convention of spm-modelcheck's `sinusoidal_drive` (its
/// `amplitude_nm` is A through the scanner's scale, its `phase_at_line_end_rad` β).
/// The physics (static map, hysteresis, creep, drift, noise, feedback, faults) act along
/// this path exactly as along the linear raster; as β → 0 it tends to the linear raster,
/// and β = 0 is exactly [`Microscope::scan`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SineDrive {
    /// The drive's phase at a line's ends, β, rad, in [0, π/2]: the line covers the phase
    /// ±β about the sine's zero crossing, so β = π·f_drive·T_line (f_drive the drive's
    /// frequency, Hz; π/2 when a line is a whole half-period). 0 is the linear raster.
    /// Typical (fast SPM): 1.2–1.5. Default: 0.
    pub phase_at_line_end_rad: f64,
}

/// The sine's map of a line's columns: column k at c + A·sin(β·ξ_k) ([`SineDrive`]).
#[derive(Clone, Copy, Debug)]
struct SineLine {
    /// The raster's centre column's x, counts.
    centre_counts: f64,
    /// The sine's amplitude A = W/sin β, counts.
    amplitude_counts: f64,
    /// The phase at the line's ends β, rad.
    phase_at_line_end_rad: f64,
    /// Pixels per line, N.
    pixels: usize,
}

impl SineLine {
    /// The fast-axis command of `column`, counts.
    #[inline]
    fn x_counts(&self, column: usize) -> f64 {
        let n = self.pixels as f64;
        let xi = (2.0 * column as f64 + 1.0 - n) / n;
        self.centre_counts + self.amplitude_counts * (self.phase_at_line_end_rad * xi).sin()
    }
}

/// Where a raster's pixels are commanded: the linear raster of a [`ScanRequest`], its fast
/// axis driven by a sine ([`SineDrive`]) or not, turned ([`RasterTurn`]) or not.
#[derive(Clone, Copy, Debug)]
struct RasterPath {
    /// The raster's first column's x, counts.
    origin_x_counts: f64,
    /// The pixel step, counts.
    step_counts: f64,
    /// The sine's map of the columns (none: linear).
    sine: Option<SineLine>,
    /// The turn of every commanded position (none: unturned).
    turn: Option<RasterTurn>,
}

impl RasterPath {
    /// The path of `request`, turned by `turn` and driven by `drive`. A turn by 0 is no turn
    /// and a phase of 0 no sine (every position's bits as the plain raster's); a phase that
    /// is not finite or outside [0, π/2] is refused.
    fn new(
        request: &ScanRequest,
        turn: Option<RasterTurn>,
        drive: Option<SineDrive>,
    ) -> Result<Self, SimError> {
        let step = request.pixel_step.value();
        let pixels = request.pixels_per_line as usize;
        let sine = match drive {
            Some(d) if d.phase_at_line_end_rad != 0.0 => {
                let beta = d.phase_at_line_end_rad;
                if !(beta.is_finite() && beta > 0.0 && beta <= std::f64::consts::FRAC_PI_2) {
                    return Err(SimError::InvalidRequest {
                        reason: format!(
                            "sine drive phase at the line end {beta} rad must be in [0, π/2]"
                        ),
                    });
                }
                let half_width_counts = 0.5 * pixels as f64 * step;
                Some(SineLine {
                    centre_counts: request.origin.x.value()
                        + 0.5 * pixels.saturating_sub(1) as f64 * step,
                    amplitude_counts: half_width_counts / beta.sin(),
                    phase_at_line_end_rad: beta,
                    pixels,
                })
            }
            _ => None,
        };
        Ok(Self {
            origin_x_counts: request.origin.x.value(),
            step_counts: step,
            sine,
            turn: turn.filter(|t| t.angle_rad != 0.0),
        })
    }

    /// The plain linear raster (no sine, no turn).
    fn is_plain(&self) -> bool {
        self.sine.is_none() && self.turn.is_none()
    }

    /// The command of `column` on the line at `y` (counts).
    #[inline]
    fn command(&self, column: usize, y: f64) -> [f64; 2] {
        let x = match &self.sine {
            None => self.origin_x_counts + self.step_counts * column as f64,
            Some(s) => s.x_counts(column),
        };
        match self.turn {
            None => [x, y],
            Some(t) => t.apply(x, y),
        }
    }

    /// Refuses a path that leaves the field [`min`, `max`]: the bounding box of its corners
    /// (its lines' first and last columns, the first and last lines; the sine's columns are
    /// monotone in the column) after the turn.
    fn check_inside(
        &self,
        request: &ScanRequest,
        min: CountPoint,
        max: CountPoint,
    ) -> Result<(), spm_hal::ScanRequestError> {
        let (_, far_y) = request.far_corner();
        let (y0, y1) = (request.origin.y.value(), far_y.value());
        let last = (request.pixels_per_line as usize).saturating_sub(1);
        let corners = [(0, y0), (last, y0), (0, y1), (last, y1)].map(|(c, y)| self.command(c, y));
        let lo = corners
            .iter()
            .fold([f64::INFINITY; 2], |m, p| [m[0].min(p[0]), m[1].min(p[1])]);
        let hi = corners.iter().fold([f64::NEG_INFINITY; 2], |m, p| {
            [m[0].max(p[0]), m[1].max(p[1])]
        });
        if lo[0] < min.x.value()
            || lo[1] < min.y.value()
            || hi[0] > max.x.value()
            || hi[1] > max.y.value()
        {
            return Err(spm_hal::ScanRequestError::OutsideField {
                min_x: lo[0],
                max_x: hi[0],
                min_y: lo[1],
                max_y: hi[1],
            });
        }
        Ok(())
    }
}

impl Simulator {
    /// A raster whose fast axis is driven by a sine ([`SineDrive`]): fast SPM's resonant
    /// scan program, the physics of [`Microscope::scan`] along the sine's path (the pixels
    /// equidistant in time, each commanded at its dwell's middle on the sine). The frame's
    /// request is the nominal (linear) raster; a phase of 0 is exactly [`Microscope::scan`].
    /// Refused (`InvalidRequest`) for a phase outside [0, π/2], (`OutOfRange`) when the
    /// sine's end pixels (up to half a step beyond the raster's) leave the field.
    pub fn scan_sine_driven(
        &mut self,
        request: &ScanRequest,
        drive: SineDrive,
    ) -> Result<Frame, SimError> {
        let result = self.scan_impl(request, None, Some(drive));
        if let Err(e) = &result {
            tracing::debug!(error = %e, "simulated sine-driven scan failed");
        }
        result
    }
}

impl Simulator {
    /// A raster scan turned about a point ([`RasterTurn`]): the physics of
    /// [`Microscope::scan`] along the turned path. The frame's request is the raster before
    /// the turn; a turn by 0 is exactly [`Microscope::scan`].
    pub fn scan_turned(
        &mut self,
        request: &ScanRequest,
        turn: RasterTurn,
    ) -> Result<Frame, SimError> {
        let result = self.scan_impl(request, Some(turn), None);
        if let Err(e) = &result {
            tracing::debug!(error = %e, "simulated turned scan failed");
        }
        result
    }
}

impl Microscope for Simulator {
    type Error = SimError;

    fn capabilities(&self) -> Capabilities {
        let i = &self.state.config.instrument;
        let h = i.lateral_half_range_counts;
        let hz = i.z_half_range_counts;
        Capabilities {
            field_min: CountPoint::from_counts(-h, -h),
            field_max: CountPoint::from_counts(h - 1.0, h - 1.0),
            z_min: Counts(-hz),
            z_max: Counts(hz - 1.0),
            // One count is the DAC step by definition; with
            // `quantise_lateral_dac = false` the simulator additionally honours
            // sub-count commands exactly (an ideal DAC), but still advertises 1.
            lateral_resolution: Counts(1.0),
            max_pixels_per_line: i.max_pixels_per_line,
            pixels_per_line_multiple: 1,
            max_lines: i.max_lines,
            min_pixel_dwell: Seconds(i.min_pixel_dwell_s),
            counter_scan: i.counter_scan,
            backward_trace: i.backward_trace,
            coarse_z: i.coarse_z.as_ref().map(|c| CoarseZCapability {
                min_steps: c.min_steps,
                max_steps: c.max_steps,
            }),
        }
    }

    fn now(&mut self) -> Result<Seconds, SimError> {
        self.begin_call(Operation::Now, false)?;
        Ok(Seconds(self.state.time_s))
    }

    fn wait(&mut self, duration: Seconds) -> Result<(), SimError> {
        self.begin_call(Operation::Wait, true)?;
        let d = duration.value();
        if !d.is_finite() || d < 0.0 {
            return Err(SimError::InvalidRequest {
                reason: format!("wait duration {duration} must be finite and ≥ 0"),
            });
        }
        self.idle(d, Operation::Wait)
    }

    fn position(&mut self) -> Result<CountPoint, SimError> {
        self.begin_call(Operation::Position, false)?;
        Ok(CountPoint::from_counts(self.command[0], self.command[1]))
    }

    fn move_to(&mut self, request: MoveRequest) -> Result<(), SimError> {
        self.begin_call(Operation::MoveTo, true)?;
        let target = self.check_point(request.target, "move target")?;
        let speed = request.speed.value();
        if !(speed.is_finite() && speed > 0.0) {
            return Err(SimError::InvalidRequest {
                reason: format!("move speed {speed} counts/s must be finite and > 0"),
            });
        }
        let settle = request.settle.value();
        if !(settle.is_finite() && settle >= 0.0) {
            return Err(SimError::InvalidRequest {
                reason: format!("settle time {} must be finite and ≥ 0", request.settle),
            });
        }
        self.travel(target, speed, Operation::MoveTo)?;
        self.idle(settle, Operation::MoveTo)
    }

    fn scan(&mut self, request: &ScanRequest) -> Result<Frame, SimError> {
        let result = self.scan_impl(request, None, None);
        if let Err(e) = &result {
            tracing::debug!(error = %e, "simulated scan failed");
        }
        result
    }

    fn z_position(&mut self) -> Result<Counts, SimError> {
        self.begin_call(Operation::ZPosition, true)?;
        Ok(Counts(self.read_z_counts()))
    }

    fn coarse_z(&mut self) -> Option<&mut dyn CoarseZStage<Error = SimError>> {
        if self.state.config.instrument.coarse_z.is_some() {
            Some(self)
        } else {
            None
        }
    }
}

impl CoarseZStage for Simulator {
    type Error = SimError;

    fn step(&mut self, steps: i64) -> Result<(), SimError> {
        self.begin_call(Operation::CoarseZ, true)?;
        let Some(c) = self.state.config.instrument.coarse_z.clone() else {
            return Err(SimError::OutOfRange {
                reason: "this configuration has no coarse stage".to_owned(),
            });
        };
        let target = self.coarse_steps.saturating_add(steps);
        if target < c.min_steps || target > c.max_steps {
            return Err(SimError::OutOfRange {
                reason: format!(
                    "coarse position {target} steps is outside [{}, {}]",
                    c.min_steps, c.max_steps
                ),
            });
        }
        let duration = steps.unsigned_abs() as f64 * c.step_time_s;
        self.idle(duration, Operation::CoarseZ)?;
        self.coarse_steps = target;
        // The feedback re-establishes the gap at the new stage position.
        self.state.z_nm = self.feedback_target_nm(self.state.time_s, None);
        Ok(())
    }

    fn position_steps(&mut self) -> Result<i64, SimError> {
        self.begin_call(Operation::CoarseZ, false)?;
        Ok(self.coarse_steps)
    }
}

#[cfg(test)]
mod round_code_tests {
    use super::round_code;

    #[test]
    fn half_code_grids_stay_uniform_across_zero() {
        let grid: Vec<f64> = (-4..4).map(|i| f64::from(i) + 0.5).collect();
        let codes: Vec<f64> = grid.iter().map(|&x| round_code(x)).collect();
        assert_eq!(codes, vec![-3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0]);
        assert_eq!(round_code(-0.49), 0.0);
        assert_eq!(round_code(-0.51), -1.0);
        assert_eq!(round_code(2.4999), 2.0);
        assert_eq!(round_code(-7.0), -7.0);
        assert_eq!(round_code(1e300), 1e300);
    }
}
