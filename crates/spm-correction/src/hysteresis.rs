//! Rate-independent hysteresis of the scanner axes and the scanner dynamics model a
//! calibration file carries (issue 23).
//!
//! **Why Prandtl–Ishlinskii.** The raster's own hysteresis is what limits large images (the
//! error budget: 1.7–2.25 % of the side against a 0.21 % bound with the creep model alone).
//! A play-operator (Prandtl–Ishlinskii, PI) operator `h = Σ wᵢ·yᵢ`,
//! `yᵢ ← max(u − rᵢ, min(u + rᵢ, yᵢ))`, is
//! - linear in its weights, so it is identified by one (sign-constrained) least-squares fit
//!   from any sequence of commands, not only from symmetric loops ([`fit_dynamics`]);
//! - exact for any history with wiping-out memory (its state is the vector yᵢ);
//! - amplitude dependent and rate independent, which is what trace/retrace rasters at a
//!   ladder of sizes and two line rates separate from creep (rate dependent);
//! - symmetric, which is what a piezo tube's loops are to within the budget. Preisach
//!   would add asymmetric loops at the cost of a 2-D density the ladder cannot fix; Lapshin's
//!   parametric loop (RSI 91, 065106, 2020) describes one loop shape per amplitude but not
//!   arbitrary histories (a raster after a move), which the correction needs.
//!
//! The model of one axis in counts: effective input `uₑ = x + c`, `x = u + h(u-history)`,
//! `c` the creep of x ([`crate::dynamics::CreepLaw`]). Its large-signal gain on the
//! demagnetised midline is `(1 + W_h)·(1 + W_c)`, `W_h = Σwᵢ`.
//!
//! Pure: no IO, no clock.

use serde::{Deserialize, Serialize};

use crate::dynamics::{CommandHistory, CreepLaw};
use crate::error::CorrectionError;

/// Format name of a serialised [`ScannerDynamics`].
pub const DYNAMICS_FORMAT: &str = "spmcal-dynamics";
/// Format version of a serialised [`ScannerDynamics`].
pub const DYNAMICS_FORMAT_VERSION: u32 = 1;

/// A PI hysteresis operator of one axis: thresholds (counts) and weights (dimensionless).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlayHysteresis {
    /// Play thresholds rᵢ, counts, increasing, ≥ 0.
    pub thresholds_counts: Vec<f64>,
    /// Weights wᵢ ≥ 0 (dimensionless).
    pub weights: Vec<f64>,
}

impl PlayHysteresis {
    /// No hysteresis.
    #[must_use]
    pub fn none() -> Self {
        Self {
            thresholds_counts: Vec::new(),
            weights: Vec::new(),
        }
    }

    /// Checks the operator.
    ///
    /// # Errors
    /// [`CorrectionError::InvalidArgument`] naming the field.
    pub fn validate(&self, what: &str) -> Result<(), CorrectionError> {
        if self.thresholds_counts.len() != self.weights.len() {
            return Err(CorrectionError::InvalidArgument(format!(
                "{what}: {} thresholds but {} weights",
                self.thresholds_counts.len(),
                self.weights.len()
            )));
        }
        if self
            .thresholds_counts
            .iter()
            .any(|r| !(r.is_finite() && *r >= 0.0))
            || self.thresholds_counts.windows(2).any(|w| w[1] <= w[0])
        {
            return Err(CorrectionError::InvalidArgument(format!(
                "{what}.thresholds_counts must be finite, ≥ 0 and increasing"
            )));
        }
        if self.weights.iter().any(|w| !(w.is_finite() && *w >= 0.0)) {
            return Err(CorrectionError::InvalidArgument(format!(
                "{what}.weights must be finite and ≥ 0"
            )));
        }
        Ok(())
    }

    /// Large-signal weight W_h = Σwᵢ.
    #[must_use]
    pub fn total_weight(&self) -> f64 {
        self.weights.iter().sum()
    }

    /// Branch separation `h_down(u) − h_up(u)` of the periodic loop between `−amplitude` and
    /// `+amplitude` (about its centre) at `u`, counts: `Σ wᵢ·(min(u + rᵢ, A − rᵢ) −
    /// max(u − rᵢ, rᵢ − A))⁺` — the closed form of the operator on a symmetric cycle.
    #[must_use]
    pub fn loop_separation_counts(&self, amplitude_counts: f64, u_counts: f64) -> f64 {
        self.thresholds_counts
            .iter()
            .zip(&self.weights)
            .map(|(&r, &w)| {
                let down = (u_counts + r).min(amplitude_counts - r);
                let up = (u_counts - r).max(r - amplitude_counts);
                w * (down - up).max(0.0)
            })
            .sum()
    }
}

/// Play states of one axis (the operator outputs yᵢ, counts).
#[derive(Debug, Clone, PartialEq)]
struct PlayState {
    outputs: Vec<f64>,
}

impl PlayState {
    fn settled(thresholds: usize, u: f64) -> Self {
        Self {
            outputs: vec![u; thresholds],
        }
    }

    fn apply(&mut self, thresholds: &[f64], u: f64) {
        for (y, r) in self.outputs.iter_mut().zip(thresholds) {
            *y = (u - r).max((u + r).min(*y));
        }
    }

    /// The outputs after applying `u` to a copy (a query inside a monotone segment).
    fn peek(&self, thresholds: &[f64], u: f64, out: &mut Vec<f64>) {
        out.clear();
        out.extend(
            self.outputs
                .iter()
                .zip(thresholds)
                .map(|(y, r)| (u - r).max((u + r).min(*y))),
        );
    }
}

/// The play outputs yᵢ (unit weight, counts) of `thresholds` on one axis at every query time,
/// replaying `history` from a demagnetised state at its first command. Queries in
/// non-decreasing time order. Exact: the command is monotone within each segment.
///
/// # Errors
/// [`CorrectionError::Empty`], [`CorrectionError::InvalidArgument`] for unsorted times.
pub fn play_outputs(
    history: &CommandHistory,
    axis: usize,
    thresholds_counts: &[f64],
    query_times_s: &[f64],
) -> Result<Vec<Vec<f64>>, CorrectionError> {
    let segments = history.segments();
    let first = crate::dynamics::first_of_replay(history, query_times_s)?;
    let axis = axis.min(1);
    let mut state = PlayState::settled(thresholds_counts.len(), first.from_counts[axis]);
    let mut out = Vec::with_capacity(query_times_s.len());
    let mut scratch = Vec::new();
    let mut q = 0;
    for seg in segments {
        while q < query_times_s.len() && query_times_s[q] <= seg.end_s {
            let u = seg.at(query_times_s[q])[axis];
            state.peek(thresholds_counts, u, &mut scratch);
            out.push(scratch.clone());
            q += 1;
        }
        state.apply(thresholds_counts, seg.to_counts[axis]);
    }
    while q < query_times_s.len() {
        out.push(state.outputs.clone());
        q += 1;
    }
    Ok(out)
}

/// Creep law parameters as stored (see [`CreepLaw::log_spaced`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreepParameters {
    /// Weight w of every relaxation element (dimensionless).
    pub weight: f64,
    /// Shortest time constant, s.
    pub min_time_constant_s: f64,
    /// Longest time constant, s.
    pub max_time_constant_s: f64,
    /// Elements per decade.
    pub elements_per_decade: u32,
}

impl CreepParameters {
    /// The law.
    ///
    /// # Errors
    /// As [`CreepLaw::log_spaced`].
    pub fn law(&self) -> Result<CreepLaw, CorrectionError> {
        CreepLaw::log_spaced(
            self.weight,
            self.min_time_constant_s,
            self.max_time_constant_s,
            self.elements_per_decade,
        )
    }

    /// Of a law.
    #[must_use]
    pub fn of(law: &CreepLaw, elements_per_decade: u32) -> Self {
        let taus = law.time_constants_s();
        Self {
            weight: law.weight(),
            min_time_constant_s: taus.first().copied().unwrap_or(1.0),
            max_time_constant_s: taus.last().copied().unwrap_or(1.0),
            elements_per_decade,
        }
    }
}

/// How the dynamics were identified.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DynamicsIdentification {
    /// Trace/retrace sightings used (both axes).
    pub sightings: usize,
    /// Ladder sizes (line lengths), counts.
    pub ladder_counts: Vec<f64>,
    /// Line rates used, lines per second.
    pub line_rates_hz: Vec<f64>,
    /// RMS residual of the fit, counts.
    pub residual_rms_counts: f64,
    /// Fitted signal lag (feedback), s.
    pub signal_lag_s: f64,
    /// Standard error of the creep weight.
    pub creep_weight_sigma: f64,
    /// What was not identified and why (empty = everything).
    #[serde(default)]
    pub notes: Vec<String>,
    /// The creep law's shortest time constants tried, each with the fit it gave (empty when
    /// the shape was fixed); the one with the least residual is the law's.
    #[serde(default)]
    pub creep_fast_end_trials: Vec<FastEndTrial>,
}

/// One shortest creep time constant tried by [`fit_dynamics_choosing_fast_end`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FastEndTrial {
    /// The creep law's shortest time constant, s.
    pub min_time_constant_s: f64,
    /// RMS residual of the joint fit with it (in the screening's passes), counts.
    pub residual_rms_counts: f64,
    /// The creep weight it fitted (per element).
    pub creep_weight: f64,
}

/// The scanner's dynamics: hysteresis per lateral axis and the creep law.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScannerDynamics {
    /// [`DYNAMICS_FORMAT`].
    pub format: String,
    /// [`DYNAMICS_FORMAT_VERSION`].
    pub version: u32,
    /// X hysteresis.
    pub hysteresis_x: PlayHysteresis,
    /// Y hysteresis.
    pub hysteresis_y: PlayHysteresis,
    /// Creep of both axes.
    pub creep: CreepParameters,
    /// How it was identified.
    #[serde(default)]
    pub identification: DynamicsIdentification,
}

impl ScannerDynamics {
    /// Checks every field.
    ///
    /// # Errors
    /// [`CorrectionError::InvalidArgument`] naming the field.
    pub fn validate(&self) -> Result<(), CorrectionError> {
        if self.format != DYNAMICS_FORMAT || self.version != DYNAMICS_FORMAT_VERSION {
            return Err(CorrectionError::InvalidArgument(format!(
                "dynamics format {:?} version {} (this build reads {DYNAMICS_FORMAT:?} version {DYNAMICS_FORMAT_VERSION})",
                self.format, self.version
            )));
        }
        self.hysteresis_x.validate("dynamics.hysteresis_x")?;
        self.hysteresis_y.validate("dynamics.hysteresis_y")?;
        self.creep.law().map(|_| ())
    }

    /// Large-signal gain per axis on the demagnetised midline, settled creep:
    /// `(1 + W_h)·(1 + W_c)`.
    ///
    /// # Errors
    /// As [`CreepParameters::law`].
    pub fn gain(&self) -> Result<[f64; 2], CorrectionError> {
        let wc = self.creep.law()?.total_weight();
        Ok([
            (1.0 + self.hysteresis_x.total_weight()) * (1.0 + wc),
            (1.0 + self.hysteresis_y.total_weight()) * (1.0 + wc),
        ])
    }

    /// `uₑ − u` (counts, per axis) at every query time of `history`: the hysteresis h of the
    /// commands, then the creep of `x = u + h` (DESIGN §4's model). Queries in time order.
    /// One streaming pass per axis ([`replay_axis`]): memory is the output.
    ///
    /// # Errors
    /// As [`replay_axis`] and [`CreepParameters::law`].
    pub fn offsets(
        &self,
        history: &CommandHistory,
        query_times_s: &[f64],
    ) -> Result<Vec<[f64; 2]>, CorrectionError> {
        let [x, y] = self.offsets_per_axis(history, query_times_s)?;
        Ok(x.into_iter().zip(y).map(|(x, y)| [x, y]).collect())
    }

    /// [`ScannerDynamics::offsets`] of each axis, the two axes replayed on two threads (they
    /// are independent: the hysteresis and the creep elements act per axis).
    ///
    /// # Errors
    /// As [`ScannerDynamics::offsets`].
    pub fn offsets_per_axis(
        &self,
        history: &CommandHistory,
        query_times_s: &[f64],
    ) -> Result<[Vec<f64>; 2], CorrectionError> {
        let law = self.creep.law()?;
        let axis = |axis: usize, model: &PlayHysteresis| {
            let mut out = Vec::with_capacity(query_times_s.len());
            replay_axis(history, axis, model, &law, query_times_s, |h, c| {
                out.push(h + c);
            })
            .map(|()| out)
        };
        let (x, y) = rayon::join(
            || axis(0, &self.hysteresis_x),
            || axis(1, &self.hysteresis_y),
        );
        Ok([x?, y?])
    }
}

/// Exact advance of the relaxation elements over straight pieces of their input, with the
/// exponentials of the last few pieces' durations kept: a raster's pixels are evenly spaced,
/// so they are computed once per line rate, not once per pixel. A piece whose duration agrees
/// with a cached one to [`SAME_DURATION`] (times written as `base + k·dwell` differ in
/// their last bits) is advanced as lasting the cached duration, which moves the creep by far
/// less than a pico-count; otherwise the advance is [`crate::dynamics::creep_offsets`]'s.
///
/// Each element is kept as its lag `eₖ = cₖ − w·x` behind the equilibrium of the current
/// input x (every element has the weight w): over a ramp of x by Δx in T, `τₖċₖ = w·x − cₖ`
/// gives `eₖ ← e^{−T/τₖ}·eₖ − w·τₖ·(1 − e^{−T/τₖ})·Δx/T` — two products per element where
/// cₖ itself takes three — and the creep is `c = Σcₖ = Σeₖ + W·x` (W = n·w).
struct CreepStates<'l> {
    law: &'l CreepLaw,
    /// Per element: eₖ = cₖ − w·x (counts), in blocks of four (the last block padded with
    /// elements that stay 0: their decay and gain are 0).
    lags: Vec<[f64; 4]>,
    /// The number of elements n.
    elements: usize,
    /// W = n·w.
    total_weight: f64,
    /// The exponentials of the last few durations (a raster alternates a few: trace,
    /// retrace, the step to the next line), replaced round robin.
    tables: Vec<DecayTable>,
    /// The table to replace next.
    next: usize,
}

/// Tables kept by [`CreepStates`].
const DECAY_TABLES: usize = 4;

/// Per element, for one duration T: e^{−T/τ} and w·τ·(1 − e^{−T/τ})/T, so that a ramp of
/// the input by Δx over T advances the lag eₖ to `e·eₖ − L·Δx`; in blocks of four as
/// [`CreepStates`] keeps the lags (padded with 0), so the per-pixel update is one
/// vectorisable loop.
struct DecayTable {
    /// T, s.
    duration_s: f64,
    decay: Vec<[f64; 4]>,
    lag_gain: Vec<[f64; 4]>,
}

impl DecayTable {
    fn new(law: &CreepLaw, duration_s: f64) -> Self {
        let w = law.weight();
        let taus = law.time_constants_s();
        let blocks = taus.len().div_ceil(4);
        let mut table = Self {
            duration_s,
            decay: vec![[0.0; 4]; blocks],
            lag_gain: vec![[0.0; 4]; blocks],
        };
        for (k, &tau) in taus.iter().enumerate() {
            let one_minus = -(-duration_s / tau).exp_m1();
            table.decay[k / 4][k % 4] = (-duration_s / tau).exp();
            table.lag_gain[k / 4][k % 4] = w * tau * one_minus / duration_s;
        }
        table
    }

    #[inline]
    fn holds(&self, duration_s: f64) -> bool {
        (duration_s - self.duration_s).abs() <= SAME_DURATION * duration_s
    }
}

impl<'l> CreepStates<'l> {
    /// Every element settled at the input (no lag).
    fn settled(law: &'l CreepLaw) -> Self {
        let n = law.time_constants_s().len();
        Self {
            law,
            lags: vec![[0.0; 4]; n.div_ceil(4)],
            elements: n,
            total_weight: law.total_weight(),
            tables: Vec::with_capacity(DECAY_TABLES),
            next: 0,
        }
    }

    /// The index of a duration's table: the first kept one that holds it, or a new one in the
    /// next slot.
    #[inline]
    fn table(&mut self, duration_s: f64) -> usize {
        if let Some(k) = self.tables.iter().position(|t| t.holds(duration_s)) {
            return k;
        }
        self.new_table(duration_s)
    }

    /// A new table in the next slot (the rare path of [`CreepStates::table`]).
    #[inline(never)]
    fn new_table(&mut self, duration_s: f64) -> usize {
        let table = DecayTable::new(self.law, duration_s);
        if self.tables.len() < DECAY_TABLES {
            self.tables.push(table);
            self.tables.len() - 1
        } else {
            let k = self.next;
            self.tables[k] = table;
            self.next = (k + 1) % DECAY_TABLES;
            k
        }
    }

    /// Advances over a straight piece from `from` to `to` lasting `duration_s` (≥ 0; a piece
    /// of no duration leaves every cₖ where it is); returns the creep c = Σcₖ at its end.
    ///
    /// Σeₖ is taken in four partial sums (one per place in the blocks), so the per-pixel sum
    /// is not one chain of dependent additions; the advance adds each element to its partial
    /// sum as it updates it (one pass).
    #[inline]
    fn advance(&mut self, from: f64, to: f64, duration_s: f64) -> f64 {
        let mut partial = [0.0; 4];
        if duration_s > 0.0 {
            let k = self.table(duration_s);
            let table = &self.tables[k];
            let rise = to - from;
            for ((e, d), g) in self.lags.iter_mut().zip(&table.decay).zip(&table.lag_gain) {
                let mut v = [0.0; 4];
                for m in 0..4 {
                    v[m] = d[m] * e[m] - g[m] * rise;
                }
                *e = v;
                for m in 0..4 {
                    partial[m] += v[m];
                }
            }
        } else {
            // cₖ unchanged while the equilibrium moves from `from` to `to`.
            let shift = self.law.weight() * (from - to);
            for e in &mut self.lags.as_flattened_mut()[..self.elements] {
                *e += shift;
            }
            for e in &self.lags {
                for m in 0..4 {
                    partial[m] += e[m];
                }
            }
        }
        (partial[0] + partial[1]) + (partial[2] + partial[3]) + self.total_weight * to
    }
}

/// The hysteresis of one axis along one monotone segment, swept: from the state `y⁰` at the
/// segment's start, a rising command gives `yᵢ = max(u − rᵢ, y⁰ᵢ)`, so
/// `h(u) = Σwᵢy⁰ᵢ + Σ_{eᵢ < u} wᵢ(u − eᵢ)` with the engagement points `eᵢ = y⁰ᵢ + rᵢ`
/// (falling: `yᵢ = min(u + rᵢ, y⁰ᵢ)`, `eᵢ = y⁰ᵢ − rᵢ`, engaged when `u < eᵢ`). The queries of a
/// segment come in command order, so each operator is engaged once: O(1) per query instead of
/// one operation per operator (a 2048-pixel line and 47 operators: 47× fewer).
#[derive(Debug, Default)]
struct PlaySweep {
    /// The segment the sweep is built for.
    segment: Option<usize>,
    /// +1 rising, −1 falling, 0 holding.
    sense: f64,
    /// (eᵢ, wᵢ) in engagement order.
    engagement: Vec<(f64, f64)>,
    /// Operators engaged so far.
    engaged: usize,
    /// Σwᵢy⁰ᵢ.
    h0: f64,
    /// Σ_engaged wᵢ.
    w: f64,
    /// Σ_engaged wᵢeᵢ.
    we: f64,
}

impl PlaySweep {
    fn start(
        &mut self,
        index: usize,
        seg: &crate::dynamics::CommandSegment,
        axis: usize,
        state: &PlayState,
        model: &PlayHysteresis,
    ) {
        let rise = seg.to_counts[axis] - seg.from_counts[axis];
        self.segment = Some(index);
        self.sense = if rise > 0.0 {
            1.0
        } else if rise < 0.0 {
            -1.0
        } else {
            0.0
        };
        self.h0 = state
            .outputs
            .iter()
            .zip(&model.weights)
            .map(|(y, w)| y * w)
            .sum();
        self.engagement.clear();
        self.engagement.extend(
            state
                .outputs
                .iter()
                .zip(&model.thresholds_counts)
                .zip(&model.weights)
                .map(|((y, r), w)| (y + self.sense * r, *w)),
        );
        let sense = self.sense;
        self.engagement
            .sort_by(|a, b| (sense * a.0).total_cmp(&(sense * b.0)));
        self.engaged = 0;
        self.w = 0.0;
        self.we = 0.0;
    }

    /// h at command `u` (the segment's queries in command order).
    fn at(&mut self, u: f64) -> f64 {
        if self.sense == 0.0 {
            return self.h0;
        }
        while let Some(&(e, w)) = self.engagement.get(self.engaged) {
            if self.sense * (u - e) > 0.0 {
                self.w += w;
                self.we += w * e;
                self.engaged += 1;
            } else {
                break;
            }
        }
        self.h0 + self.w * u - self.we
    }
}

/// Relative agreement under which [`CreepStates`] reuses its exponentials.
const SAME_DURATION: f64 = 1e-7;

/// Streams DESIGN §4's input model of one axis along `history`: at every query time (in time
/// order) it hands `sink` the hysteresis h (the play operators of `model` on the axis'
/// commands, exact: the command is monotone within each segment) and the creep c of `law`
/// driven by the post-hysteresis input x = u + h, taken as straight between consecutive
/// times of the history's vertices and the queries. The replay starts demagnetised and
/// settled at the history's first command. One pass; its memory is the operators' and
/// elements' states. The axes are independent.
///
/// # Errors
/// [`CorrectionError::Empty`] for an empty history, [`CorrectionError::InvalidArgument`] for
/// unsorted or non-finite query times.
pub fn replay_axis(
    history: &CommandHistory,
    axis: usize,
    model: &PlayHysteresis,
    law: &CreepLaw,
    query_times_s: &[f64],
    mut sink: impl FnMut(f64, f64),
) -> Result<(), CorrectionError> {
    let segments = history.segments();
    let first = crate::dynamics::first_of_replay(history, query_times_s)?;
    let axis = axis.min(1);
    let last_segment = segments.len() - 1;
    let mut play = PlayState::settled(model.thresholds_counts.len(), first.from_counts[axis]);
    // The play pointer: segments before `applied` have been applied at their ends.
    let mut applied = 0;
    let mut sweep = PlaySweep::default();
    // The merged times: every segment end and every query, each once, in order.
    let mut end = 0;
    let mut q = 0;
    let n = query_times_s.len();
    let mut previous: Option<(f64, f64)> = None;
    let mut creep: Option<CreepStates<'_>> = None;
    while q < n {
        let t = match segments.get(end) {
            Some(seg) if seg.end_s <= query_times_s[q] => seg.end_s,
            _ => query_times_s[q],
        };
        while end < segments.len() && segments[end].end_s <= t {
            end += 1;
        }
        // u and h at time t: the segment holding t swept, or, after the history, its end held.
        while applied < segments.len() && segments[applied].end_s < t {
            play.apply(&model.thresholds_counts, segments[applied].to_counts[axis]);
            applied += 1;
        }
        let seg = &segments[applied.min(last_segment)];
        let u = seg.at(t)[axis];
        let h = if applied < segments.len() {
            if sweep.segment != Some(applied) {
                sweep.start(applied, seg, axis, &play, model);
            }
            sweep.at(u)
        } else {
            play.outputs
                .iter()
                .zip(&model.weights)
                .map(|(y, w)| y * w)
                .sum::<f64>()
        };
        let x = u + h;
        let states = creep.get_or_insert_with(|| CreepStates::settled(law));
        let c = match previous {
            Some((t0, x0)) => states.advance(x0, x, (t - t0).max(0.0)),
            None => states.advance(x, x, 0.0),
        };
        let (mut t_last, mut x_last) = (t, x);
        while q < n && query_times_s[q] <= t {
            sink(h, c);
            q += 1;
        }
        // The queries strictly inside the segment being swept (no segment end among them, so
        // each is the next merged time, with the segment and its sweep as they are): the
        // steps above without their checks.
        if applied == end && applied < segments.len() {
            while q < n && query_times_s[q] < seg.end_s {
                let t = query_times_s[q];
                let u = seg.at(t)[axis];
                let h = sweep.at(u);
                let x = u + h;
                let c = states.advance(x_last, x, (t - t_last).max(0.0));
                (t_last, x_last) = (t, x);
                while q < n && query_times_s[q] <= t {
                    sink(h, c);
                    q += 1;
                }
            }
        }
        previous = Some((t_last, x_last));
    }
    Ok(())
}

/// Passes of [`fit_dynamics`]: the creep's input x = u + h needs the hysteresis of the
/// previous pass (the coupling is weak, W_h ≈ 0.1–0.2, so a few passes converge).
const FIT_PASSES: usize = 4;

/// Two sightings of one sample point along one axis: the command had `u_first_counts` at
/// `t_first_s` and `u_second_counts` at `t_second_s` when the probe saw it, moving at the given
/// command velocities (counts/s, signed) — a feature in a trace and in the retrace of the same
/// line (x), or in a direct and its counter-scanned frame (y).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SamePoint {
    /// 0 = x, 1 = y.
    pub axis: usize,
    /// First sighting time, s.
    pub t_first_s: f64,
    /// Command at the first sighting, counts.
    pub u_first_counts: f64,
    /// Command velocity at the first sighting, counts/s.
    pub v_first_counts_per_s: f64,
    /// Second sighting time, s (≥ first).
    pub t_second_s: f64,
    /// Command at the second sighting, counts.
    pub u_second_counts: f64,
    /// Command velocity at the second sighting, counts/s.
    pub v_second_counts_per_s: f64,
    /// Drift group: sightings of one group share one drift velocity.
    pub group: usize,
}

/// What [`fit_dynamics`] fits.
#[derive(Debug, Clone, PartialEq)]
pub struct DynamicsFitSetup {
    /// Candidate play thresholds per axis, counts (increasing).
    pub thresholds_counts: [Vec<f64>; 2],
    /// Creep law shape (its weight is fitted).
    pub creep_shape: CreepParameters,
}

/// Identifies per axis the PI weights, jointly with one creep weight, a signal lag and one
/// drift velocity per group, from same-point sightings: `u₂ − u₁ = Σwᵢ(yᵢ(t₁) − yᵢ(t₂)) +
/// w_c(c̃(t₁) − c̃(t₂)) + v_g(t₂ − t₁) + δ(u̇₂ − u̇₁)` (c̃ the unit-weight creep of the
/// commands; δ the lag of the recorded signal behind the command). Weights ≥ 0.
///
/// # Errors
/// [`CorrectionError::Empty`] without sightings; [`CorrectionError::InvalidArgument`] when
/// the data do not determine the model.
pub fn fit_dynamics(
    history: &CommandHistory,
    sightings: &[SamePoint],
    setup: &DynamicsFitSetup,
) -> Result<ScannerDynamics, CorrectionError> {
    fit_dynamics_in_passes(history, sightings, setup, FIT_PASSES)
}

/// [`fit_dynamics`] with `passes` passes (≥ 1).
fn fit_dynamics_in_passes(
    history: &CommandHistory,
    sightings: &[SamePoint],
    setup: &DynamicsFitSetup,
    passes: usize,
) -> Result<ScannerDynamics, CorrectionError> {
    let usable: Vec<&SamePoint> = sightings
        .iter()
        .filter(|s| {
            s.t_first_s.is_finite()
                && s.t_second_s.is_finite()
                && s.u_first_counts.is_finite()
                && s.u_second_counts.is_finite()
                && s.v_first_counts_per_s.is_finite()
                && s.v_second_counts_per_s.is_finite()
        })
        .collect();
    if usable.is_empty() {
        return Err(CorrectionError::Empty("same-point sightings"));
    }
    let groups: Vec<usize> = {
        let mut g: Vec<usize> = usable.iter().map(|s| s.group * 2 + s.axis.min(1)).collect();
        g.sort_unstable();
        g.dedup();
        g
    };
    let unit_creep = CreepParameters {
        weight: 1.0,
        ..setup.creep_shape.clone()
    }
    .law()?;
    // Regressors: play outputs and unit creep at every sighting time, per axis.
    let mut times: Vec<f64> = usable
        .iter()
        .flat_map(|s| [s.t_first_s, s.t_second_s])
        .collect();
    times.sort_by(f64::total_cmp);
    times.dedup();
    let index_of = |t: f64| times.partition_point(|&v| v < t);
    let plays = [
        play_outputs(history, 0, &setup.thresholds_counts[0], &times)?,
        play_outputs(history, 1, &setup.thresholds_counts[1], &times)?,
    ];
    let (n0, n1) = (
        setup.thresholds_counts[0].len(),
        setup.thresholds_counts[1].len(),
    );
    // Pass 1 drives the creep by the commands; later passes by x = u + h of the previous pass.
    let mut hysteresis = [PlayHysteresis::none(), PlayHysteresis::none()];
    let mut result = None;
    for _ in 0..passes.max(1) {
        let mut creep = vec![[0.0; 2]; times.len()];
        for (axis, model) in hysteresis.iter().enumerate() {
            let mut k = 0;
            replay_axis(history, axis, model, &unit_creep, &times, |_, c| {
                if let Some(row) = creep.get_mut(k) {
                    row[axis] = c;
                }
                k += 1;
            })?;
        }
        let (full, sigma, fit) = solve_pass(&usable, &plays, &creep, &groups, (n0, n1), &index_of)?;
        hysteresis = [
            PlayHysteresis {
                thresholds_counts: setup.thresholds_counts[0].clone(),
                weights: full[..n0].to_vec(),
            },
            PlayHysteresis {
                thresholds_counts: setup.thresholds_counts[1].clone(),
                weights: full[n0..n0 + n1].to_vec(),
            },
        ];
        result = Some((full, sigma, fit));
    }
    let (full, sigma, fit) = result.ok_or(CorrectionError::Empty("dynamics fit passes"))?;
    Ok(ScannerDynamics {
        format: DYNAMICS_FORMAT.to_owned(),
        version: DYNAMICS_FORMAT_VERSION,
        hysteresis_x: hysteresis[0].clone(),
        hysteresis_y: hysteresis[1].clone(),
        creep: CreepParameters {
            weight: full[n0 + n1],
            ..setup.creep_shape.clone()
        },
        identification: DynamicsIdentification {
            sightings: usable.len(),
            residual_rms_counts: fit.residual_rms,
            signal_lag_s: full[n0 + n1 + 1],
            creep_weight_sigma: sigma[n0 + n1],
            ..DynamicsIdentification::default()
        },
    })
}

/// [`fit_dynamics`] with the creep law's shortest time constant identified too: the fit is
/// made for each of `candidates_s` (the shape's other parameters as `setup` gives them) and
/// the one with the least residual kept (every other candidate first, then the best one's
/// neighbours). The number of fitted parameters is the same for every candidate (one creep
/// weight), so the residuals compare directly. What sees the fast
/// end: a line's trace and retrace at two line rates (elements of about a line time stretch
/// one rate's lines and not the other's) and the first seconds of the attachment tracks.
/// The trials are kept in the result's [`DynamicsIdentification::creep_fast_end_trials`].
///
/// # Errors
/// As [`fit_dynamics`] when no candidate gives a fit;
/// [`CorrectionError::InvalidArgument`] without a usable candidate (each must be positive
/// and not above the shape's longest time constant).
pub fn fit_dynamics_choosing_fast_end(
    history: &CommandHistory,
    sightings: &[SamePoint],
    setup: &DynamicsFitSetup,
    candidates_s: &[f64],
) -> Result<ScannerDynamics, CorrectionError> {
    let max_s = setup.creep_shape.max_time_constant_s;
    let mut usable: Vec<f64> = candidates_s
        .iter()
        .copied()
        .filter(|&t| t.is_finite() && t > 0.0 && t <= max_s)
        .collect();
    usable.sort_by(f64::total_cmp);
    usable.dedup();
    if usable.is_empty() {
        return Err(CorrectionError::InvalidArgument(format!(
            "no usable shortest creep time constant among {candidates_s:?} (each in (0, {max_s}] s)"
        )));
    }
    let setup_for = |min_time_constant_s: f64| {
        let mut trial = setup.clone();
        trial.creep_shape.min_time_constant_s = min_time_constant_s;
        trial
    };
    // Screening: every other candidate, then the neighbours of the best, each fitted in
    // SCREENING_PASSES passes (the passes refine the weak hysteresis–creep coupling and do not
    // reorder the candidates); the chosen one is then fitted in full.
    let mut trials: Vec<FastEndTrial> = Vec::with_capacity(usable.len());
    let mut last_error = None;
    let mut screen = |k: usize, trials: &mut Vec<FastEndTrial>| {
        if trials.iter().any(|t| t.min_time_constant_s == usable[k]) {
            return;
        }
        match fit_dynamics_in_passes(history, sightings, &setup_for(usable[k]), SCREENING_PASSES) {
            Ok(model) => trials.push(FastEndTrial {
                min_time_constant_s: usable[k],
                residual_rms_counts: model.identification.residual_rms_counts,
                creep_weight: model.creep.weight,
            }),
            Err(e) => last_error = Some(e),
        }
    };
    for k in (0..usable.len()).step_by(2) {
        screen(k, &mut trials);
    }
    let best_index = |trials: &[FastEndTrial]| {
        trials
            .iter()
            .filter(|t| t.residual_rms_counts.is_finite())
            .min_by(|a, b| a.residual_rms_counts.total_cmp(&b.residual_rms_counts))
            .and_then(|t| usable.iter().position(|&u| u == t.min_time_constant_s))
    };
    if let Some(k) = best_index(&trials) {
        for neighbour in [k.checked_sub(1), Some(k + 1)].into_iter().flatten() {
            if neighbour < usable.len() {
                screen(neighbour, &mut trials);
            }
        }
    }
    let Some(best) = best_index(&trials) else {
        return Err(last_error.unwrap_or(CorrectionError::Empty("creep fast-end trials")));
    };
    trials.sort_by(|a, b| a.min_time_constant_s.total_cmp(&b.min_time_constant_s));
    let mut model = fit_dynamics(history, sightings, &setup_for(usable[best]))?;
    model.identification.creep_fast_end_trials = trials;
    Ok(model)
}

/// Passes of each candidate's fit while [`fit_dynamics_choosing_fast_end`] screens them.
const SCREENING_PASSES: usize = 2;

/// One least-squares pass of [`fit_dynamics`]: (coefficients, standard errors, the fit).
fn solve_pass(
    usable: &[&SamePoint],
    plays: &[Vec<Vec<f64>>; 2],
    creep: &[[f64; 2]],
    groups: &[usize],
    (n0, n1): (usize, usize),
    index_of: &dyn Fn(f64) -> usize,
) -> Result<(Vec<f64>, Vec<f64>, spm_regression::LinearFit), CorrectionError> {
    let columns = n0 + n1 + 2 + groups.len();
    let mut rows = Vec::with_capacity(usable.len());
    let mut rhs = Vec::with_capacity(usable.len());
    for s in usable {
        let axis = s.axis.min(1);
        let (i1, i2) = (index_of(s.t_first_s), index_of(s.t_second_s));
        let mut row = vec![0.0; columns];
        let offset = if axis == 0 { 0 } else { n0 };
        for (k, (y1, y2)) in plays[axis][i1].iter().zip(&plays[axis][i2]).enumerate() {
            row[offset + k] = y1 - y2;
        }
        row[n0 + n1] = creep[i1][axis] - creep[i2][axis];
        row[n0 + n1 + 1] = s.v_second_counts_per_s - s.v_first_counts_per_s;
        let g = groups.partition_point(|&g| g < s.group * 2 + axis);
        row[n0 + n1 + 2 + g] = s.t_second_s - s.t_first_s;
        rows.push(row);
        rhs.push(s.u_second_counts - s.u_first_counts);
    }
    // Columns without any signal (an axis without sightings) are dropped.
    let keep: Vec<usize> = (0..columns)
        .filter(|&j| rows.iter().any(|r: &Vec<f64>| r[j] != 0.0))
        .collect();
    let reduced: Vec<Vec<f64>> = rows
        .iter()
        .map(|r| keep.iter().map(|&j| r[j]).collect())
        .collect();
    let non_negative: Vec<bool> = keep.iter().map(|&j| j <= n0 + n1).collect();
    let fit = spm_regression::least_squares(&reduced, &rhs, &non_negative)
        .map_err(|e| CorrectionError::InvalidArgument(format!("dynamics fit: {e}")))?;
    let mut full = vec![0.0; columns];
    let mut sigma = vec![0.0; columns];
    for (c, &j) in keep.iter().enumerate() {
        full[j] = fit.coefficients[c];
        sigma[j] = fit.standard_errors[c];
    }
    Ok((full, sigma, fit))
}

/// Same-point sightings of a trace/retrace frame (scanner geometry halves of a direct
/// raster) from tracked shifts `(trace column, shift px)`: the trace at column c and the
/// retrace at column c + shift saw the same sample point. One sighting per shift, timed on
/// the middle row; `group` is the drift group of the frame.
#[must_use]
pub fn line_pair_sightings(
    forward: &spm_hal::HeightMap,
    backward: &spm_hal::HeightMap,
    shifts: &[(f64, f64)],
    group: usize,
) -> Vec<SamePoint> {
    let (nx, ny) = (forward.columns, forward.rows);
    if nx < 2 || ny == 0 || backward.columns != nx || backward.rows != ny {
        return Vec::new();
    }
    let row = ny / 2;
    let time = |map: &spm_hal::HeightMap, column: f64| -> Option<(f64, f64)> {
        if !(column >= 0.0 && column <= (nx - 1) as f64) {
            return None;
        }
        let i = (column.floor() as usize).min(nx - 2);
        let f = column - i as f64;
        let t0 = *map.time_s.get(row * nx + i)?;
        let t1 = *map.time_s.get(row * nx + i + 1)?;
        // Command velocity: one pixel step per (t1 − t0).
        let dt = t1 - t0;
        (dt != 0.0).then(|| (t0 + f * dt, map.pixel_step.value() / dt))
    };
    shifts
        .iter()
        .filter_map(|&(column, shift)| {
            let (t1, v1) = time(forward, column)?;
            let (t2, v2) = time(backward, column + shift)?;
            let step = forward.pixel_step.value();
            Some(SamePoint {
                axis: 0,
                t_first_s: t1.min(t2),
                u_first_counts: forward.origin.x.value()
                    + step * if t1 <= t2 { column } else { column + shift },
                v_first_counts_per_s: if t1 <= t2 { v1 } else { v2 },
                t_second_s: t1.max(t2),
                u_second_counts: forward.origin.x.value()
                    + step * if t1 <= t2 { column + shift } else { column },
                v_second_counts_per_s: if t1 <= t2 { v2 } else { v1 },
                group,
            })
        })
        .collect()
}

/// Same-point sightings along the slow axis (y) of a counter-scanned pair: `up` (lines
/// stepping +y) saw at row `r` what `down` (the same region stepping −y) shows at row
/// `r + shift`, for each `(r, shift)` of `shifts` (rows, fractional; as
/// `spm_features::counter_pair_shifts` gives them). Times and the slow axis's command
/// velocities are read at the frames' middle column. Both frames must have the same size.
#[must_use]
pub fn counter_pair_sightings(
    up: &spm_hal::HeightMap,
    down: &spm_hal::HeightMap,
    shifts: &[(f64, f64)],
    group: usize,
) -> Vec<SamePoint> {
    let (nx, ny) = (up.columns, up.rows);
    if nx == 0 || ny < 2 || down.columns != nx || down.rows != ny {
        return Vec::new();
    }
    let column = nx / 2;
    let time = |map: &spm_hal::HeightMap, row: f64| -> Option<(f64, f64)> {
        if !(row >= 0.0 && row <= (ny - 1) as f64) {
            return None;
        }
        let j = (row.floor() as usize).min(ny - 2);
        let f = row - j as f64;
        let t0 = *map.time_s.get(j * nx + column)?;
        let t1 = *map.time_s.get((j + 1) * nx + column)?;
        // Command velocity: one pixel step per (t1 − t0), negative for a frame stepping −y.
        let dt = t1 - t0;
        (dt != 0.0).then(|| (t0 + f * dt, map.pixel_step.value() / dt))
    };
    let step = up.pixel_step.value();
    let y0 = up.origin.y.value();
    shifts
        .iter()
        .filter_map(|&(row, shift)| {
            let (t1, v1) = time(up, row)?;
            let (t2, v2) = time(down, row + shift)?;
            let (u1, u2) = (y0 + step * row, y0 + step * (row + shift));
            let up_first = t1 <= t2;
            Some(SamePoint {
                axis: 1,
                t_first_s: t1.min(t2),
                u_first_counts: if up_first { u1 } else { u2 },
                v_first_counts_per_s: if up_first { v1 } else { v2 },
                t_second_s: t1.max(t2),
                u_second_counts: if up_first { u2 } else { u1 },
                v_second_counts_per_s: if up_first { v2 } else { v1 },
                group,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests;
