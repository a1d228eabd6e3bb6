//! Scanner input dynamics: what the commanded counts become before the static map sees them.
//!
//! A piezo tube does not follow its command statically. Its creep (and its hysteresis) act on
//! the *input*: the static map F — whose Jacobian the distributed calibration measures as
//! LCCs — sees the effective input `uₑ = u + h + c`, where `c` relaxes after every command
//! change: `ΔL(t) ≈ ΔL(0.1 s)·[1 + γ·lg(t / 0.1 s)]` (DESIGN §4). During an image the creep of
//! the move that brought the probe there, and of the raster itself, goes on, so the static
//! correction of eq. (9) misplaces the pixels of every image by a history-dependent amount.
//! This module
//!
//! - turns a backend's command log ([`spm_hal::recording::CommandEvent`]) into a piecewise-
//!   linear commanded trajectory ([`CommandHistory`]);
//! - models creep as a chain of first-order relaxations with log-spaced time constants and one
//!   weight (the form that gives the logarithmic law between its extreme time constants,
//!   [`CreepLaw`]) and replays any history through it exactly ([`creep_offsets`]);
//! - identifies the weight from the attachment sequences a calibration run makes anyway: after
//!   every node move the probe re-attaches to one atom until its apparent velocity dies out, and
//!   that motion is the creep of the move plus drift ([`fit_creep_law`]);
//! - corrects an image along its *effective* trajectory: eq. (5) integrated over the increments
//!   of `uₑ` pixel to pixel, the LCCs evaluated where the calibration saw that effective input
//!   ([`correct_effective_raster`]).
//!
//! Pure: no IO, no clock.

use crate::error::CorrectionError;
use crate::field::{CorrectionField, FormCoefficients};
use crate::parallel::{Parallelism, for_each_row};
use crate::raster::{CoordinateMap, YCoordinates};
use spm_hal::recording::CommandEvent;
use spm_hal::{ScanDirection, ScanRequest};

/// One piece of the commanded trajectory: a straight ramp (a hold when `from == to`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CommandSegment {
    /// Start, instrument time, s.
    pub start_s: f64,
    /// End, s (≥ start).
    pub end_s: f64,
    /// Commanded position at the start, counts.
    pub from_counts: [f64; 2],
    /// Commanded position at the end, counts.
    pub to_counts: [f64; 2],
}

impl CommandSegment {
    /// The command at time `t` (clamped to the segment).
    #[inline]
    pub fn at(&self, t_s: f64) -> [f64; 2] {
        let d = self.end_s - self.start_s;
        let f = if d > 0.0 {
            ((t_s - self.start_s) / d).clamp(0.0, 1.0)
        } else {
            1.0
        };
        [
            self.from_counts[0] + (self.to_counts[0] - self.from_counts[0]) * f,
            self.from_counts[1] + (self.to_counts[1] - self.from_counts[1]) * f,
        ]
    }
}

/// The commanded lateral trajectory, contiguous in time.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CommandHistory {
    segments: Vec<CommandSegment>,
}

impl CommandHistory {
    /// The segments, in time order.
    pub fn segments(&self) -> &[CommandSegment] {
        &self.segments
    }

    fn last(&self) -> Option<([f64; 2], f64)> {
        self.segments.last().map(|s| (s.to_counts, s.end_s))
    }

    /// Appends a ramp to `to` ending at `end_s`, starting where and when the history ends
    /// (or at `to` and `end_s` for the first segment). Segments that would go back in time
    /// are clamped to zero length.
    pub fn ramp_to(&mut self, end_s: f64, to: [f64; 2]) {
        let (from, start) = self.last().unwrap_or((to, end_s));
        if !(end_s.is_finite() && to[0].is_finite() && to[1].is_finite()) {
            return;
        }
        let end = end_s.max(start);
        self.segments.push(CommandSegment {
            start_s: start,
            end_s: end,
            from_counts: from,
            to_counts: to,
        });
    }

    /// Holds the last command until `end_s`.
    pub fn hold_until(&mut self, end_s: f64) {
        if let Some((p, _)) = self.last() {
            self.ramp_to(end_s, p);
        }
    }

    /// Appends a move from `from` at `speed` that ended its settle at `end_s`.
    fn push_move(
        &mut self,
        start_s: f64,
        end_s: f64,
        from: [f64; 2],
        to: [f64; 2],
        speed: f64,
        settle_s: f64,
    ) {
        if self.segments.is_empty() {
            self.ramp_to(start_s, from);
        }
        let length = (to[0] - from[0]).hypot(to[1] - from[1]);
        let travel_end = (end_s - settle_s.max(0.0)).max(start_s);
        let duration = if speed > 0.0 { length / speed } else { 0.0 };
        let travel_start = (travel_end - duration).max(start_s);
        self.ramp_to(travel_start, from);
        self.ramp_to(travel_end, to);
        self.hold_until(end_s);
    }

    /// Appends a raster as the HAL defines it: travel from `from` to the first pixel at the
    /// scan speed, then per line a trace and a retrace of `pixels · dwell` each; the raster
    /// ends at `end_s`. With `lines_descending` the lines were acquired last line first (a
    /// controller scanning its slow axis down).
    fn push_scan(
        &mut self,
        start_s: f64,
        end_s: f64,
        from: [f64; 2],
        request: &ScanRequest,
        lines_descending: bool,
    ) {
        if self.segments.is_empty() {
            self.ramp_to(start_s, from);
        }
        let nx = f64::from(request.pixels_per_line.max(1));
        let ny = request.lines.max(1);
        let dwell = request.pixel_dwell.value();
        let step = request.pixel_step.value();
        let (x0, y0) = (request.origin.x.value(), request.origin.y.value());
        let x1 = x0 + step * (nx - 1.0);
        // The y of the `k`-th line acquired.
        let y_of = |k: u32| {
            let line = if lines_descending { ny - 1 - k } else { k };
            match request.direction {
                ScanDirection::Direct => y0 + step * f64::from(line),
                ScanDirection::Counter => y0 + step * f64::from(ny - 1 - line),
            }
        };
        let (xa, xb) = match request.direction {
            ScanDirection::Direct => (x0, x1),
            ScanDirection::Counter => (x1, x0),
        };
        let line_s = 2.0 * nx * dwell;
        let raster_start = (end_s - line_s * f64::from(ny)).max(start_s);
        let first = [xa, y_of(0)];
        let travel = (first[0] - from[0]).hypot(first[1] - from[1]);
        let speed = if dwell > 0.0 { step / dwell } else { 0.0 };
        let travel_s = if speed > 0.0 { travel / speed } else { 0.0 };
        self.ramp_to((raster_start - travel_s).max(start_s), from);
        self.ramp_to(raster_start, first);
        for line in 0..ny {
            let base = raster_start + line_s * f64::from(line);
            let y = y_of(line);
            // Pixel k is held over [base + k·dwell, base + (k+1)·dwell]: a ramp through the
            // pixel centres is the zero-order hold to within half a pixel.
            self.ramp_to(base + 0.5 * dwell, [xa, y]);
            self.ramp_to(base + (nx - 0.5) * dwell, [xb, y]);
            self.ramp_to(base + (nx + 0.5) * dwell, [xb, y]);
            self.ramp_to(base + (2.0 * nx - 0.5) * dwell, [xa, y]);
        }
        self.hold_until(end_s);
    }

    /// Appends a backend's command log (events in time order).
    pub fn extend_with_events(&mut self, events: &[CommandEvent]) {
        for event in events {
            match event {
                CommandEvent::Move {
                    start_s,
                    end_s,
                    from,
                    request,
                } => self.push_move(
                    *start_s,
                    *end_s,
                    [from.x.value(), from.y.value()],
                    [request.target.x.value(), request.target.y.value()],
                    request.speed.value(),
                    request.settle.value(),
                ),
                CommandEvent::Wait { end_s, .. } => self.hold_until(*end_s),
                CommandEvent::Scan {
                    start_s,
                    end_s,
                    from,
                    request,
                    lines_descending,
                } => self.push_scan(
                    *start_s,
                    *end_s,
                    [from.x.value(), from.y.value()],
                    request,
                    *lines_descending,
                ),
                _ => {}
            }
        }
    }

    /// A history from a command log.
    pub fn from_events(events: &[CommandEvent]) -> Self {
        let mut h = Self::default();
        h.extend_with_events(events);
        h
    }
}

/// Creep as relaxations `ċₖ = (w·x − cₖ)/τₖ`, τₖ log-spaced, one weight w: after a step Δ from
/// rest the creep is `Δ·w·Σ(1 − e^{−t/τₖ})`, logarithmic in t between the extreme τ.
#[derive(Debug, Clone, PartialEq)]
pub struct CreepLaw {
    taus_s: Vec<f64>,
    weight: f64,
}

impl CreepLaw {
    /// Time constants from `min_s` to `max_s`, `per_decade` of them per decade, weight `weight`.
    ///
    /// # Errors
    /// [`CorrectionError::InvalidArgument`] for non-positive or non-finite values.
    pub fn log_spaced(
        weight: f64,
        min_s: f64,
        max_s: f64,
        per_decade: u32,
    ) -> Result<Self, CorrectionError> {
        if !(min_s > 0.0
            && max_s >= min_s
            && max_s.is_finite()
            && per_decade > 0
            && weight.is_finite())
        {
            return Err(CorrectionError::InvalidArgument(format!(
                "creep law: time constants {min_s} … {max_s} s, {per_decade} per decade, weight {weight}"
            )));
        }
        let m = f64::from(per_decade);
        let n = ((max_s / min_s).log10() * m).round() as usize + 1;
        let taus_s = (0..n).map(|k| min_s * 10f64.powf(k as f64 / m)).collect();
        Ok(Self { taus_s, weight })
    }

    /// The same time constants with another weight.
    #[must_use]
    pub fn with_weight(&self, weight: f64) -> Self {
        Self {
            taus_s: self.taus_s.clone(),
            weight,
        }
    }

    /// Weight w of every element.
    pub fn weight(&self) -> f64 {
        self.weight
    }

    /// Time constants, s.
    pub fn time_constants_s(&self) -> &[f64] {
        &self.taus_s
    }

    /// Settled creep gain W = n·w.
    pub fn total_weight(&self) -> f64 {
        self.weight * self.taus_s.len() as f64
    }

    /// Log slope γ between 0.1 s and 10 s: `ΔL(10 s)/ΔL(0.1 s) = 1 + 2γ` (DESIGN §4's law).
    pub fn gamma_per_decade(&self) -> f64 {
        let (r01, r10) = (self.step_response(0.1), self.step_response(10.0));
        ((1.0 + r10) / (1.0 + r01) - 1.0) / 2.0
    }

    /// Fraction of a unit step still to creep t seconds after it (from rest): w·Σe^{−t/τₖ}
    /// (the settled gain minus [`CreepLaw::step_response`]; t < 0 counts as 0).
    pub fn still_to_come(&self, t_s: f64) -> f64 {
        self.weight
            * self
                .taus_s
                .iter()
                .map(|tau| (-t_s.max(0.0) / tau).exp())
                .sum::<f64>()
    }

    /// Fractional creep t seconds after a step from rest: w·Σ(1 − e^{−t/τₖ}).
    pub fn step_response(&self, t_s: f64) -> f64 {
        self.weight
            * self
                .taus_s
                .iter()
                .map(|tau| 1.0 - (-t_s / tau).exp())
                .sum::<f64>()
    }
}

/// Exact advance of one relaxation over a ramp input `x(s) = a + b·s`, s ∈ [0, T], target
/// weight `w`.
#[inline]
fn advance(c: f64, tau: f64, w: f64, a: f64, b: f64, t: f64) -> f64 {
    let e = (-t / tau).exp();
    let one_minus = -(-t / tau).exp_m1();
    e * c + w * (a * one_minus + b * (t - tau * one_minus))
}

/// The creep offset c (counts, per axis) at each query time, replaying `history` through
/// `law` from a state settled at the history's first command. Queries must be in
/// non-decreasing time order and inside the history (later ones hold its last command).
///
/// # Errors
/// [`CorrectionError::InvalidArgument`] for unsorted or non-finite query times, or an empty
/// history.
pub fn creep_offsets(
    history: &CommandHistory,
    law: &CreepLaw,
    query_times_s: &[f64],
) -> Result<Vec<[f64; 2]>, CorrectionError> {
    let segments = history.segments();
    let first = first_of_replay(history, query_times_s)?;
    let w = law.weight;
    let taus = &law.taus_s;
    let mut states: Vec<[f64; 2]> = taus
        .iter()
        .map(|_| [w * first.from_counts[0], w * first.from_counts[1]])
        .collect();
    let mut out = Vec::with_capacity(query_times_s.len());
    let mut q = 0;
    for seg in segments {
        let duration = seg.end_s - seg.start_s;
        let slope = |k: usize| {
            if duration > 0.0 {
                (seg.to_counts[k] - seg.from_counts[k]) / duration
            } else {
                0.0
            }
        };
        let b = [slope(0), slope(1)];
        // Queries inside this segment (or before its start, which means a gap: held).
        while q < query_times_s.len() && query_times_s[q] <= seg.end_s {
            let t = (query_times_s[q] - seg.start_s).clamp(0.0, duration.max(0.0));
            let mut c = [0.0; 2];
            for (s, &tau) in states.iter().zip(taus) {
                for k in 0..2 {
                    c[k] += advance(s[k], tau, w, seg.from_counts[k], b[k], t);
                }
            }
            out.push(c);
            q += 1;
        }
        if duration > 0.0 {
            for (s, &tau) in states.iter_mut().zip(taus) {
                for k in 0..2 {
                    s[k] = advance(s[k], tau, w, seg.from_counts[k], b[k], duration);
                }
            }
        } else {
            // A jump (zero-length segment): the states do not move.
        }
    }
    // Queries after the end: the last command held.
    if q < query_times_s.len() {
        let (last_t, last_u) = segments
            .last()
            .map_or((0.0, [0.0; 2]), |s| (s.end_s, s.to_counts));
        while q < query_times_s.len() {
            let t = (query_times_s[q] - last_t).max(0.0);
            let mut c = [0.0; 2];
            for (s, &tau) in states.iter().zip(taus) {
                for k in 0..2 {
                    c[k] += advance(s[k], tau, w, last_u[k], 0.0, t);
                }
            }
            out.push(c);
            q += 1;
        }
    }
    Ok(out)
}

/// The first segment of a history to replay at `query_times_s`, which must be finite and in
/// time order.
///
/// # Errors
/// [`CorrectionError::Empty`] for an empty history, [`CorrectionError::InvalidArgument`] for
/// unsorted or non-finite query times.
pub(crate) fn first_of_replay<'h>(
    history: &'h CommandHistory,
    query_times_s: &[f64],
) -> Result<&'h CommandSegment, CorrectionError> {
    let first = history
        .segments()
        .first()
        .ok_or(CorrectionError::Empty("command history"))?;
    if query_times_s.iter().any(|t| !t.is_finite()) || query_times_s.windows(2).any(|w| w[1] < w[0])
    {
        return Err(CorrectionError::InvalidArgument(
            "query times must be finite and in time order".to_owned(),
        ));
    }
    Ok(first)
}

/// One attachment sequence: the same feature re-found again and again after a node move.
#[derive(Debug, Clone, PartialEq)]
pub struct AttachTrack {
    /// (instrument time s, feature x counts, feature y counts), in time order.
    pub sightings: Vec<(f64, f64, f64)>,
}

/// The identified creep law and how well the data fixed it.
#[derive(Debug, Clone, PartialEq)]
pub struct CreepFit {
    /// The law with the fitted weight.
    pub law: CreepLaw,
    /// Standard error of the weight.
    pub weight_sigma: f64,
    /// Sightings used.
    pub sightings: usize,
    /// Tracks used.
    pub tracks: usize,
    /// RMS residual of the feature positions, counts.
    pub residual_rms_counts: f64,
    /// RMS of the fitted creep motion within the tracks, counts (the signal).
    pub signal_rms_counts: f64,
    /// Log slope γ of the fitted law between 0.1 s and 10 s (ΔL(10 s)/ΔL(0.1 s) − 1, per decade).
    pub gamma_per_decade: f64,
}

/// One sighting in the creep fit: time (s), feature position and unit creep (counts), drift window.
type TrackPoint = (f64, [f64; 2], [f64; 2], usize);

/// Fits the creep weight of `shape` (its time constants) to attachment tracks: a feature
/// re-found at commanded position `u_f(t)` obeys `u_f(t) = U − c(t) + v·t` (c the creep
/// offset of the command history, v the drift in counts/s). Per track an offset U; the drift
/// piecewise constant over windows of `drift_window_s`; one weight for both axes. Linear least
/// squares (c is linear in the weight).
///
/// # Errors
/// [`CorrectionError::Empty`] without usable tracks; [`CorrectionError::InvalidArgument`] when
/// the data do not determine the weight.
pub fn fit_creep_law(
    history: &CommandHistory,
    shape: &CreepLaw,
    tracks: &[AttachTrack],
    drift_window_s: f64,
) -> Result<CreepFit, CorrectionError> {
    let unit = shape.with_weight(1.0);
    // Every sighting, sorted by time, with its track.
    let mut points: Vec<(f64, usize, usize)> = Vec::new();
    for (k, track) in tracks.iter().enumerate() {
        if track.sightings.len() < 3 {
            continue;
        }
        for (i, s) in track.sightings.iter().enumerate() {
            if s.0.is_finite() && s.1.is_finite() && s.2.is_finite() {
                points.push((s.0, k, i));
            }
        }
    }
    if points.len() < 10 {
        return Err(CorrectionError::Empty(
            "attachment tracks for the creep fit",
        ));
    }
    points.sort_by(|a, b| a.0.total_cmp(&b.0));
    let times: Vec<f64> = points.iter().map(|p| p.0).collect();
    let creep = creep_offsets(history, &unit, &times)?;
    let window = drift_window_s.max(1.0);
    let t0 = times[0];
    // Group per track: (time, position, unit creep, window).
    let mut per_track: Vec<Vec<TrackPoint>> = vec![Vec::new(); tracks.len()];
    for (p, c) in points.iter().zip(&creep) {
        let s = tracks[p.1].sightings[p.2];
        let w = ((p.0 - t0) / window).floor().max(0.0) as usize;
        per_track[p.1].push((p.0, [s.1, s.2], *c, w));
    }
    let windows = per_track
        .iter()
        .flatten()
        .map(|r| r.3 + 1)
        .max()
        .unwrap_or(1);
    // Unknowns: [w, v_x(window 0..), v_y(window 0..)]; rows demeaned per track and axis.
    let n = 1 + 2 * windows;
    let mut rows = 0;
    let mut used_tracks = 0;
    let mut design: Vec<(Vec<(usize, f64)>, f64)> = Vec::new();
    for track in per_track.iter().filter(|t| t.len() >= 3) {
        used_tracks += 1;
        let m = track.len() as f64;
        for axis in 0..2 {
            let mean_y = track.iter().map(|r| r.1[axis]).sum::<f64>() / m;
            let mean_c = track.iter().map(|r| r.2[axis]).sum::<f64>() / m;
            // Mean of each drift column (time within its window) over the track.
            let mut mean_v = std::collections::BTreeMap::new();
            for r in track {
                *mean_v.entry(r.3).or_insert(0.0) += (r.0 - t0) / m;
            }
            for r in track {
                let mut row: Vec<(usize, f64)> = vec![(0, -(r.2[axis] - mean_c))];
                for (&win, &mean) in &mean_v {
                    let value = if win == r.3 { r.0 - t0 } else { 0.0 } - mean;
                    row.push((1 + axis * windows + win, value));
                }
                let y = r.1[axis] - mean_y;
                design.push((row, y));
                rows += 1;
            }
        }
    }
    let (solution, inverse_00) = solve_creep_design(&design, n)?;
    let w = solution[0];
    let mut ss = 0.0;
    let mut signal = 0.0;
    for (row, y) in &design {
        let fit: f64 = row.iter().map(|&(i, v)| v * solution[i]).sum();
        ss += (y - fit).powi(2);
        if let Some(&(_, v0)) = row.first() {
            signal += (v0 * w).powi(2);
        }
    }
    let dof = (rows as f64 - n as f64).max(1.0);
    let sigma2 = ss / dof;
    if !(w.is_finite() && inverse_00.is_finite()) {
        return Err(CorrectionError::InvalidArgument(
            "creep fit: no finite weight".to_owned(),
        ));
    }
    let law = shape.with_weight(w.max(0.0));
    Ok(CreepFit {
        gamma_per_decade: law.gamma_per_decade(),
        law,
        weight_sigma: (sigma2 * inverse_00).sqrt(),
        sightings: points.len(),
        tracks: used_tracks,
        residual_rms_counts: (ss / rows.max(1) as f64).sqrt(),
        signal_rms_counts: (signal / rows.max(1) as f64).sqrt(),
    })
}

/// The creep fit's least squares through the workspace's one solver,
/// [`spm_regression::least_squares`] (unconstrained): the sparse rows of `design` made dense
/// over `n` columns, the drift windows no row touches left out (their velocity is 0) and the
/// weight's column always kept. Returns the full solution and (AᵀA)⁻¹₀₀, the weight's unscaled
/// variance.
fn solve_creep_design(
    design: &[(Vec<(usize, f64)>, f64)],
    n: usize,
) -> Result<(Vec<f64>, f64), CorrectionError> {
    let mut used = vec![false; n];
    if let Some(first) = used.first_mut() {
        *first = true;
    }
    for (row, _) in design {
        for &(j, v) in row {
            if v != 0.0 {
                used[j] = true;
            }
        }
    }
    let keep: Vec<usize> = (0..n).filter(|&j| used[j]).collect();
    let mut position = vec![usize::MAX; n];
    for (c, &j) in keep.iter().enumerate() {
        position[j] = c;
    }
    let dense: Vec<Vec<f64>> = design
        .iter()
        .map(|(row, _)| {
            let mut d = vec![0.0; keep.len()];
            for &(j, v) in row {
                if let Some(cell) = d.get_mut(position[j]) {
                    *cell += v;
                }
            }
            d
        })
        .collect();
    let rhs: Vec<f64> = design.iter().map(|(_, y)| *y).collect();
    let fit = spm_regression::least_squares(&dense, &rhs, &vec![false; keep.len()])
        .map_err(|e| CorrectionError::InvalidArgument(format!("creep fit: {e}")))?;
    let mut solution = vec![0.0; n];
    for (c, &j) in keep.iter().enumerate() {
        solution[j] = fit.coefficients[c];
    }
    let inverse_00 = fit
        .unscaled_covariance
        .first()
        .and_then(|row| row.first())
        .copied()
        .unwrap_or(f64::NAN);
    Ok((solution, inverse_00))
}

/// Corrected coordinates of a raster along its effective trajectory: eq. (5) summed over the
/// increments of the effective input `uₑ = u + offset` from pixel to pixel along each line and
/// from line start to line start (eq. 8's route), with the form of `field` evaluated at
/// `uₑ / gain` — the commanded position at which the calibration's nodes had that effective
/// input (`gain` = the model's large-signal gain per axis, 1 + W).
///
/// `commanded` and `offsets` are per pixel in *acquisition order* (line by line as scanned).
/// The corrected frame has its origin where the settled effective input of
/// `reference_commanded` (`gain · reference`) is: images that share the reference (a direct
/// and a counter image of one place) share the frame, creep transients included.
///
/// # Errors
/// [`CorrectionError::SizeMismatch`], [`CorrectionError::NonFinite`], [`CorrectionError::Empty`].
pub fn correct_effective_raster(
    field: &(impl CorrectionField + ?Sized),
    columns: usize,
    rows: usize,
    commanded: &[[f64; 2]],
    offsets: &[[f64; 2]],
    gain: [f64; 2],
    reference_commanded: [f64; 2],
) -> Result<Vec<[f64; 2]>, CorrectionError> {
    let n = columns
        .checked_mul(rows)
        .ok_or(CorrectionError::Empty("raster size overflows"))?;
    if n == 0 {
        return Err(CorrectionError::Empty("raster with no pixel"));
    }
    for (what, v) in [("commanded", commanded), ("offsets", offsets)] {
        if v.len() != n {
            return Err(CorrectionError::SizeMismatch {
                what,
                expected: n,
                got: v.len(),
            });
        }
        if let Some(index) = v
            .iter()
            .position(|p| !(p[0].is_finite() && p[1].is_finite()))
        {
            return Err(CorrectionError::NonFinite { what, index });
        }
    }
    let ue: Vec<[f64; 2]> = commanded
        .iter()
        .zip(offsets)
        .map(|(u, o)| [u[0] + o[0], u[1] + o[1]])
        .collect();
    correct_effective_path(field, columns, rows, &ue, gain, reference_commanded)
}

/// [`correct_effective_raster`] given the effective input `uₑ = u + offsets` of every pixel
/// (acquisition order) directly.
///
/// # Errors
/// [`CorrectionError::SizeMismatch`], [`CorrectionError::NonFinite`], [`CorrectionError::Empty`],
/// [`CorrectionError::InvalidArgument`] for a gain that is not positive.
pub fn correct_effective_path(
    field: &(impl CorrectionField + ?Sized),
    columns: usize,
    rows: usize,
    ue: &[[f64; 2]],
    gain: [f64; 2],
    reference_commanded: [f64; 2],
) -> Result<Vec<[f64; 2]>, CorrectionError> {
    let n = path_pixels(columns, rows, ue.len())?;
    if let Some(index) = ue
        .iter()
        .position(|p| !(p[0].is_finite() && p[1].is_finite()))
    {
        return Err(CorrectionError::NonFinite {
            what: "effective input",
            index,
        });
    }
    effective_path(
        field,
        columns,
        rows,
        n,
        |i| ue[i],
        gain,
        reference_commanded,
    )
}

/// [`correct_effective_path`] with the effective input of each axis in its own slice
/// (`ue_x[i]`, `ue_y[i]` of pixel i, acquisition order), as a replay per axis gives it: the
/// same sums, bit for bit, without the pairs' buffer.
///
/// # Errors
/// As [`correct_effective_path`]; [`CorrectionError::SizeMismatch`] when the slices differ in
/// length.
pub fn correct_effective_path_axes(
    field: &(impl CorrectionField + ?Sized),
    columns: usize,
    rows: usize,
    ue_x: &[f64],
    ue_y: &[f64],
    gain: [f64; 2],
    reference_commanded: [f64; 2],
) -> Result<Vec<[f64; 2]>, CorrectionError> {
    let n = path_pixels(columns, rows, ue_x.len())?;
    if ue_y.len() != n {
        return Err(CorrectionError::SizeMismatch {
            what: "effective input",
            expected: n,
            got: ue_y.len(),
        });
    }
    if let Some(index) = ue_x
        .iter()
        .zip(ue_y)
        .position(|(x, y)| !(x.is_finite() && y.is_finite()))
    {
        return Err(CorrectionError::NonFinite {
            what: "effective input",
            index,
        });
    }
    effective_path(
        field,
        columns,
        rows,
        n,
        |i| [ue_x[i], ue_y[i]],
        gain,
        reference_commanded,
    )
}

/// The pixels of a `columns` × `rows` path whose effective input holds `len` pixels.
fn path_pixels(columns: usize, rows: usize, len: usize) -> Result<usize, CorrectionError> {
    let n = columns
        .checked_mul(rows)
        .ok_or(CorrectionError::Empty("raster size overflows"))?;
    if n == 0 {
        return Err(CorrectionError::Empty("raster with no pixel"));
    }
    if len != n {
        return Err(CorrectionError::SizeMismatch {
            what: "effective input",
            expected: n,
            got: len,
        });
    }
    Ok(n)
}

/// The sums of [`correct_effective_path`] over the `n` = `columns` × `rows` pixels whose
/// (checked, finite) effective input `ue(i)` gives.
fn effective_path(
    field: &(impl CorrectionField + ?Sized),
    columns: usize,
    rows: usize,
    n: usize,
    ue: impl Fn(usize) -> [f64; 2] + Sync,
    gain: [f64; 2],
    reference_commanded: [f64; 2],
) -> Result<Vec<[f64; 2]>, CorrectionError> {
    if !(gain[0] > 0.0 && gain[1] > 0.0) {
        return Err(CorrectionError::InvalidArgument(format!("gain {gain:?}")));
    }
    let step = |from: [f64; 2], to: [f64; 2]| -> [f64; 2] {
        let mid = [
            0.5 * (from[0] + to[0]) / gain[0],
            0.5 * (from[1] + to[1]) / gain[1],
        ];
        field
            .form(mid[0], mid[1])
            .increment(to[0] - from[0], to[1] - from[1])
    };
    let mut out = vec![[0.0; 2]; n];
    let reference = [
        reference_commanded[0] * gain[0],
        reference_commanded[1] * gain[1],
    ];
    // The line starts chain line to line; each line then sums its own increments (the lines
    // are independent given their starts, so they run on every core, bit-identically).
    let mut line_starts = Vec::with_capacity(rows);
    let mut line_start = step(reference, ue(0));
    for line in 0..rows {
        let base = line * columns;
        if line > 0 {
            let d = step(ue(base - columns), ue(base));
            line_start = [line_start[0] + d[0], line_start[1] + d[1]];
        }
        line_starts.push(line_start);
    }
    // Along a line, the forms at the increments' midpoints are evaluated in one call (the
    // same values as `step`'s, bit for bit).
    for_each_row(Parallelism::AllCores, &mut out, columns, |line, row| {
        let base = line * columns;
        let mut mid_x = Vec::with_capacity(columns);
        let mut mid_y = Vec::with_capacity(columns);
        for k in 1..columns {
            let (from, to) = (ue(base + k - 1), ue(base + k));
            mid_x.push(0.5 * (from[0] + to[0]) / gain[0]);
            mid_y.push(0.5 * (from[1] + to[1]) / gain[1]);
        }
        let zero = FormCoefficients {
            kx_nm_per_count: 0.0,
            kyx_nm_per_count: 0.0,
            kyy_nm_per_count: 0.0,
        };
        let mut forms = vec![zero; columns - 1];
        field.forms(&mid_x, &mid_y, &mut forms);
        row[0] = line_starts[line];
        let mut previous = ue(base);
        for k in 1..columns {
            let next = ue(base + k);
            let d = forms[k - 1].increment(next[0] - previous[0], next[1] - previous[1]);
            row[k] = [row[k - 1][0] + d[0], row[k - 1][1] + d[1]];
            previous = next;
        }
    })?;
    Ok(out)
}

/// Splits `out` (acquisition order) into a [`CoordinateMap`] in scanner geometry.
///
/// # Errors
/// As [`CoordinateMap::new`].
pub fn to_geometry_map(
    acquisition: &[[f64; 2]],
    columns: usize,
    rows: usize,
    direction: ScanDirection,
) -> Result<CoordinateMap, CorrectionError> {
    let n = columns * rows;
    if acquisition.len() != n {
        return Err(CorrectionError::SizeMismatch {
            what: "coordinates",
            expected: n,
            got: acquisition.len(),
        });
    }
    let mut x = Vec::with_capacity(n);
    let mut y = Vec::with_capacity(n);
    for row in 0..rows {
        for column in 0..columns {
            let k = match direction {
                ScanDirection::Direct => row * columns + column,
                ScanDirection::Counter => (rows - 1 - row) * columns + (columns - 1 - column),
            };
            x.push(acquisition[k][0]);
            y.push(acquisition[k][1]);
        }
    }
    CoordinateMap::new(columns, rows, x, YCoordinates::PerPixel(y))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// A step from rest: the replay equals the closed-form step response.
    #[test]
    fn a_step_creeps_by_the_step_response() {
        let law = CreepLaw::log_spaced(0.005, 0.02, 2000.0, 3).unwrap();
        let mut h = CommandHistory::default();
        h.ramp_to(0.0, [0.0, 0.0]);
        h.ramp_to(1.0, [0.0, 0.0]);
        h.ramp_to(1.0, [1000.0, -500.0]); // an instantaneous step at t = 1 s
        h.hold_until(200.0);
        let times = [1.0, 1.1, 2.0, 11.0, 101.0];
        let c = creep_offsets(&h, &law, &times).unwrap();
        for (t, c) in times.iter().zip(&c) {
            let s = law.step_response(t - 1.0);
            // Settled at 0 before the step: c = Δ·S(t − 1).
            assert!(
                (c[0] - 1000.0 * s).abs() < 1e-9,
                "t {t}: {} vs {}",
                c[0],
                1000.0 * s
            );
            assert!((c[1] + 500.0 * s).abs() < 1e-9);
        }
    }

    /// A slow ramp: the creep follows with the settled gain once τ ≪ the ramp time.
    #[test]
    fn a_slow_ramp_is_followed_by_its_fast_elements() {
        let law = CreepLaw::log_spaced(0.01, 0.01, 0.1, 1).unwrap(); // τ = 0.01, 0.1 s
        let mut h = CommandHistory::default();
        h.ramp_to(0.0, [0.0, 0.0]);
        h.ramp_to(100.0, [100.0, 0.0]); // 1 count/s
        let c = creep_offsets(&h, &law, &[100.0]).unwrap();
        // Each element lags its target w·x by w·b·τ: c = Σ w (x − b τ).
        let expected = 0.01 * (100.0 - 0.01) + 0.01 * (100.0 - 0.1);
        assert!(
            (c[0][0] - expected).abs() < 1e-9,
            "{} vs {expected}",
            c[0][0]
        );
    }

    /// The fit recovers the weight that generated synthetic tracks (with drift).
    #[test]
    fn the_fit_recovers_the_weight_of_synthetic_tracks() {
        let truth = CreepLaw::log_spaced(0.004, 0.02, 2000.0, 3).unwrap();
        let mut h = CommandHistory::default();
        h.ramp_to(0.0, [0.0, 0.0]);
        let mut tracks = Vec::new();
        let mut t = 0.0;
        let mut x = 0.0;
        for node in 0..20 {
            let to = [x + 3000.0, if node % 2 == 0 { 0.0 } else { 2000.0 }];
            h.ramp_to(t + 0.2, to);
            t += 0.2;
            x = to[0];
            let times: Vec<f64> = (1..8).map(|k| t + 0.5 * f64::from(k)).collect();
            h.hold_until(t + 5.0);
            let c = creep_offsets(&h, &truth, &times).unwrap();
            tracks.push(AttachTrack {
                sightings: times
                    .iter()
                    .zip(&c)
                    .map(|(ti, ci)| (*ti, to[0] - ci[0] + 0.01 * ti, to[1] - ci[1] - 0.02 * ti))
                    .collect(),
            });
            t += 5.0;
        }
        let fit = fit_creep_law(&h, &truth.with_weight(0.0), &tracks, 50.0).unwrap();
        assert!((fit.law.weight() - 0.004).abs() < 1e-6, "{fit:?}");
    }
}
