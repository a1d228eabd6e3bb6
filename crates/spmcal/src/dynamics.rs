//! The scanner dynamics of a run (issue 23): the dynamics stage's ladder rasters and the
//! attachment tracks turned into same-point sightings, fitted by
//! `spm_correction::hysteresis::fit_dynamics`, and judged against the simulator's own
//! operator where there is one (the loop each predicts at every ladder size).
//!
//! Glue only: the shift tracking is `spm_features::trace_retrace_shifts`, the sightings and
//! the fit are `spm_correction::hysteresis`.

use serde::Serialize;
use spm_calibration::dynamics::LadderFrame;
use spm_correction::dynamics::{AttachTrack, CommandHistory};
use spm_correction::hysteresis::{
    CreepParameters, DynamicsFitSetup, PlayHysteresis, SamePoint, ScannerDynamics, fit_dynamics,
    fit_dynamics_choosing_fast_end, line_pair_sightings,
};
use spm_hal::TraceHalf;

/// Shifts with a smaller peak correlation are not used.
const MIN_SHIFT_CORRELATION: f64 = 0.5;
/// Fewest well-correlated windows a ladder frame must give to be used.
const MIN_WINDOWS: usize = 8;

/// The simulator's own dynamics, for the report's comparison.
#[derive(Debug, Clone, PartialEq)]
pub struct TrueDynamics {
    /// Per axis: the true operator.
    pub hysteresis: [PlayHysteresis; 2],
    /// γ of the true creep law, per decade.
    pub creep_gamma_per_decade: f64,
    /// The true creep law's shortest time constant, s.
    pub creep_min_time_constant_s: f64,
}

impl TrueDynamics {
    /// Of a simulator.
    #[cfg(feature = "sim")]
    #[must_use]
    pub fn of(sim: &spm_sim::Simulator) -> Self {
        let oracle = sim.oracle();
        let axis = |a: usize| {
            let (thresholds, weight) = oracle.hysteresis_operator(a);
            PlayHysteresis {
                weights: vec![weight; thresholds.len()],
                thresholds_counts: thresholds,
            }
        };
        Self {
            hysteresis: [axis(0), axis(1)],
            creep_gamma_per_decade: sim.config().scanner.creep.log_slope_per_decade,
            creep_min_time_constant_s: sim.config().scanner.creep.min_time_constant_s,
        }
    }
}

/// One ladder size's loop: identified against true.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LoopRow {
    /// Line length, counts.
    pub length_counts: f64,
    /// Branch separation at the loop's centre, identified, counts.
    pub separation_centre_counts: f64,
    /// The same from the simulator's operator (absent without a simulator).
    pub true_separation_centre_counts: Option<f64>,
    /// Identified / true (absent without a simulator).
    pub ratio: Option<f64>,
}

/// The dynamics section of report.json.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DynamicsReport {
    /// The identified model (absent when it could not be identified).
    pub model: Option<ScannerDynamics>,
    /// Ladder frames scanned, and those whose tracked shift closed.
    pub frames: usize,
    /// Frames used.
    pub frames_used: usize,
    /// Same-point sightings from the ladder.
    pub ladder_sightings: usize,
    /// Same-point sightings from the attachment tracks.
    pub track_sightings: usize,
    /// Counter-scanned pairs for the slow axis scanned, and those tracked.
    pub slow_pairs: usize,
    /// Pairs used.
    pub slow_pairs_used: usize,
    /// Same-point sightings along y from the pairs.
    pub slow_sightings: usize,
    /// The x loop at each ladder size.
    pub loops_x: Vec<LoopRow>,
    /// The y loop at each size of the counter-scanned pairs.
    pub loops_y: Vec<LoopRow>,
    /// Identified creep γ per decade (0.1 s … 10 s).
    pub creep_gamma_per_decade: Option<f64>,
    /// γ of the attachment tracks' creep fit alone (the cross-check).
    pub track_creep_gamma_per_decade: Option<f64>,
    /// The simulator's γ.
    pub true_creep_gamma_per_decade: Option<f64>,
    /// The creep law's shortest time constant the stage chose, s.
    pub creep_min_time_constant_s: Option<f64>,
    /// The simulator's shortest creep time constant, s.
    pub true_creep_min_time_constant_s: Option<f64>,
    /// What was not identified, and why.
    pub notes: Vec<String>,
}

/// The map without its first row (`None` with fewer than two rows).
fn without_first_line(map: &spm_hal::HeightMap) -> Option<spm_hal::HeightMap> {
    (map.rows >= 2).then(|| spm_hal::HeightMap {
        origin: spm_hal::CountPoint::new(map.origin.x, map.origin.y + map.pixel_step),
        pixel_step: map.pixel_step,
        columns: map.columns,
        rows: map.rows - 1,
        z_counts: map.z_counts[map.columns..].to_vec(),
        time_s: map.time_s[map.columns..].to_vec(),
    })
}

/// The tracked windows whose correlation can be trusted, as (column, shift px).
fn well_correlated(shifts: &[spm_features::ColumnShift]) -> Vec<(f64, f64)> {
    shifts
        .iter()
        .filter(|s| s.correlation >= MIN_SHIFT_CORRELATION)
        .map(|s| (s.column, s.shift_px))
        .collect()
}

/// What the ladder frames gave.
struct LadderSightings {
    sightings: Vec<SamePoint>,
    frames_used: usize,
    windows_disagreeing: usize,
    lengths: Vec<f64>,
}

/// The same-point sightings of every ladder frame whose two-way shift tracking agrees.
fn ladder_sightings(ladder: &[LadderFrame]) -> LadderSightings {
    let mut out = LadderSightings {
        sightings: Vec::new(),
        frames_used: 0,
        windows_disagreeing: 0,
        lengths: Vec::new(),
    };
    for (index, frame) in ladder.iter().enumerate() {
        if frame.slow_axis.is_some() {
            continue;
        }
        let (Ok(forward), Ok(backward)) = (
            frame.frame.height_map(TraceHalf::Forward),
            frame.frame.height_map(TraceHalf::Backward),
        ) else {
            continue;
        };
        // The first line's trace follows the approach, not the previous retrace: its branch
        // differs from the periodic loop of the others, so it is left out.
        let (Some(forward), Some(backward)) =
            (without_first_line(&forward), without_first_line(&backward))
        else {
            continue;
        };
        let Ok((shifts, disagreeing)) = spm_features::trace_retrace_shifts(
            &forward.z_counts,
            &backward.z_counts,
            forward.columns,
            forward.rows,
            &spm_features::ShiftConfig::default(),
        ) else {
            continue;
        };
        let good = well_correlated(&shifts);
        // Where the two trackings disagree one of them slipped a lattice period, and the
        // agreeing windows of such a line may hold a slip of both: the frame is left out.
        out.windows_disagreeing += disagreeing;
        if good.len() < MIN_WINDOWS || disagreeing > 0 {
            continue;
        }
        out.frames_used += 1;
        if !out.lengths.contains(&frame.length_counts) {
            out.lengths.push(frame.length_counts);
        }
        out.sightings
            .extend(line_pair_sightings(&forward, &backward, &good, index));
    }
    out
}

/// What the slow-axis pairs gave.
struct SlowPairSightings {
    sightings: Vec<SamePoint>,
    pairs: usize,
    pairs_used: usize,
    lengths: Vec<f64>,
}

/// The same-point sightings along y of every counter-scanned pair (a frame stepping +y and
/// the next, stepping −y over the same region), from their +x halves (the same branch of the
/// fast axis's loop in both), tracked from the top where they meet. The group of a pair is
/// its first frame's index.
fn slow_pair_sightings(ladder: &[LadderFrame]) -> SlowPairSightings {
    use spm_hal::ScanDirection;
    let mut out = SlowPairSightings {
        sightings: Vec::new(),
        pairs: 0,
        pairs_used: 0,
        lengths: Vec::new(),
    };
    for (index, pair) in ladder.windows(2).enumerate() {
        let (up, down) = (&pair[0], &pair[1]);
        if up.slow_axis != Some(ScanDirection::Direct)
            || down.slow_axis != Some(ScanDirection::Counter)
            || up.place != down.place
            || up.length_counts != down.length_counts
        {
            continue;
        }
        out.pairs += 1;
        // The +x half: the trace of a direct frame, the retrace of a counter frame.
        let (Ok(up_map), Ok(down_map)) = (
            up.frame.height_map(TraceHalf::Forward),
            down.frame.height_map(TraceHalf::Backward),
        ) else {
            continue;
        };
        let Ok(shifts) = spm_features::counter_pair_shifts(
            &up_map.z_counts,
            &down_map.z_counts,
            up_map.columns,
            up_map.rows,
            &spm_features::ShiftConfig::default(),
        ) else {
            continue;
        };
        let good = well_correlated(&shifts);
        if good.len() < MIN_WINDOWS {
            continue;
        }
        out.pairs_used += 1;
        if !out.lengths.contains(&up.length_counts) {
            out.lengths.push(up.length_counts);
        }
        out.sightings
            .extend(spm_correction::hysteresis::counter_pair_sightings(
                &up_map, &down_map, &good, index,
            ));
    }
    out
}

/// Candidate play thresholds for ladder lines of `lengths` counts: from a quarter of the
/// shortest (at least 1 count) to half the longest.
fn threshold_grid(lengths: &mut [f64]) -> Vec<f64> {
    lengths.sort_by(f64::total_cmp);
    match (lengths.first(), lengths.last()) {
        (Some(&lo), Some(&hi)) => {
            let step = (0.25 * lo).max(1.0);
            let n = (0.5 * hi / step).floor() as usize;
            (1..=n).map(|k| step * k as f64).collect()
        }
        _ => Vec::new(),
    }
}

/// Same-point sightings of the attachment tracks: every later sighting against the first,
/// both axes (creep and drift), drift groups from `group0` on, one per drift window.
fn track_sightings(tracks: &[AttachTrack], group0: usize) -> Vec<SamePoint> {
    let mut out = Vec::new();
    for track in tracks {
        let Some(&(t0, x0, y0)) = track.sightings.first() else {
            continue;
        };
        for &(t, x, y) in track.sightings.iter().skip(1) {
            let window = (t / crate::report::CREEP_FIT_DRIFT_WINDOW_S)
                .floor()
                .max(0.0);
            let group = group0 + window as usize;
            for (axis, (a, b)) in [(x0, x), (y0, y)].into_iter().enumerate() {
                out.push(SamePoint {
                    axis,
                    t_first_s: t0,
                    u_first_counts: a,
                    v_first_counts_per_s: 0.0,
                    t_second_s: t,
                    u_second_counts: b,
                    v_second_counts_per_s: 0.0,
                    group,
                });
            }
        }
    }
    out
}

/// What the report says of the counter-scanned pairs, when not all of them served.
fn slow_pair_note(pairs: usize, pairs_used: usize, no_grid: bool) -> Option<String> {
    if pairs == 0 {
        Some(
            "y hysteresis not identified: the stage scanned no counter-scanned pairs \
             ([dynamics] slow_axis_pairs)"
                .to_owned(),
        )
    } else if no_grid {
        Some(format!(
            "y hysteresis not identified: none of the {pairs} counter-scanned pairs could be \
             tracked"
        ))
    } else if pairs_used < pairs {
        Some(format!(
            "{} of {pairs} counter-scanned pairs dropped (fewer than {MIN_WINDOWS} \
             well-correlated windows)",
            pairs - pairs_used
        ))
    } else {
        None
    }
}

/// The distinct line rates of the fast-axis ladder frames, lines per second.
fn line_rates_hz(ladder: &[LadderFrame]) -> Vec<f64> {
    ladder
        .iter()
        .filter(|f| f.slow_axis.is_none())
        .map(|f| {
            1.0 / (2.0
                * f64::from(f.frame.request.pixels_per_line)
                * f.frame.request.pixel_dwell.value())
        })
        .fold(Vec::new(), |mut v: Vec<f64>, r| {
            if !v.iter().any(|x| (x / r - 1.0).abs() < 1e-9) {
                v.push(r);
            }
            v
        })
}

/// The loop at each size on one axis (0 = x), identified against the simulator's.
fn loop_rows(
    model: Option<&ScannerDynamics>,
    truth: Option<&TrueDynamics>,
    axis: usize,
    lengths: &[f64],
) -> Vec<LoopRow> {
    lengths
        .iter()
        .map(|&length| {
            let a = 0.5 * length;
            let got = model.map_or(0.0, |m| {
                let h = if axis == 0 {
                    &m.hysteresis_x
                } else {
                    &m.hysteresis_y
                };
                h.loop_separation_counts(a, 0.0)
            });
            let want = truth.map(|t| t.hysteresis[axis.min(1)].loop_separation_counts(a, 0.0));
            LoopRow {
                length_counts: length,
                separation_centre_counts: got,
                true_separation_centre_counts: want,
                ratio: want.filter(|w| *w > 0.0).map(|w| got / w),
            }
        })
        .collect()
}

/// Identifies the run's dynamics (module docs).
#[must_use]
pub fn identify(
    commands: &[spm_hal::recording::CommandEvent],
    tracks: &[AttachTrack],
    ladder: &[LadderFrame],
    creep_shape: (f64, f64, u32),
    truth: Option<&TrueDynamics>,
) -> DynamicsReport {
    let mut notes = Vec::new();
    let history = CommandHistory::from_events(commands);
    let LadderSightings {
        mut sightings,
        frames_used,
        windows_disagreeing,
        mut lengths,
    } = ladder_sightings(ladder);
    let ladder_sightings = sightings.len();
    if windows_disagreeing > 0 {
        notes.push(format!(
            "{windows_disagreeing} shift windows disagreed between the trackings from the two \
             ends of their line (one slipped a lattice period); their frames are left out"
        ));
    }
    let fast_frames = ladder.iter().filter(|f| f.slow_axis.is_none()).count();
    if frames_used < fast_frames {
        notes.push(format!(
            "{} of {fast_frames} ladder frames dropped (fewer than {MIN_WINDOWS} windows where the two trackings agreed and the lattice correlated)",
            fast_frames - frames_used,
        ));
    }
    // Creep and hysteresis jointly: the ladder's two line rates separate the rate-dependent
    // creep from the rate-independent hysteresis, and the attachment tracks (where creep and
    // drift alone move the features) add the creep of long moves. The tracks' own creep fit
    // (spm_correction::dynamics::fit_creep_law) is reported beside it as a cross-check.
    let (tau_min, tau_max, per_decade) = creep_shape;
    let track_creep = spm_correction::dynamics::CreepLaw::log_spaced(
        0.0, tau_min, tau_max, per_decade,
    )
    .and_then(|shape| {
        spm_correction::dynamics::fit_creep_law(
            &history,
            &shape,
            tracks,
            crate::report::CREEP_FIT_DRIFT_WINDOW_S,
        )
    });
    let track_creep_gamma_per_decade = track_creep.as_ref().ok().map(|f| f.gamma_per_decade);
    sightings.extend(track_sightings(tracks, ladder.len()));
    let track_sightings = sightings.len() - ladder_sightings;
    let grid_x = threshold_grid(&mut lengths);
    if grid_x.is_empty() {
        notes.push("x hysteresis not identified: no ladder frame could be used".to_owned());
    }
    let SlowPairSightings {
        sightings: slow,
        pairs,
        pairs_used,
        lengths: mut lengths_y,
    } = slow_pair_sightings(ladder);
    let slow_sightings = slow.len();
    let grid_y = threshold_grid(&mut lengths_y);
    notes.extend(slow_pair_note(pairs, pairs_used, grid_y.is_empty()));
    // Two stages. The fast-axis ladder and the tracks give the x hysteresis, the creep law
    // (its fast end chosen by the residual) and the lag; the counter-scanned pairs then give
    // the y hysteresis with all sightings. The pairs' sightings are dominated by the creep of
    // the move to the frame (tens of counts), which the creep law follows to a few per cent:
    // fitted jointly they pull the creep weight and with it the x loops (measured on
    // sim-hopg's quick job: x loops 1.06–1.15 of the simulator's jointly, 0.94–0.98 staged).
    let setup = DynamicsFitSetup {
        thresholds_counts: [grid_x.clone(), Vec::new()],
        creep_shape: CreepParameters {
            weight: 0.0,
            min_time_constant_s: tau_min,
            max_time_constant_s: tau_max,
            elements_per_decade: per_decade,
        },
    };
    let candidates = crate::report::creep_fast_end_candidates_s();
    let model = match fit_dynamics_choosing_fast_end(&history, &sightings, &setup, &candidates) {
        Ok(mut m) => {
            if !grid_y.is_empty() {
                let all: Vec<SamePoint> = sightings.iter().chain(&slow).copied().collect();
                let both = DynamicsFitSetup {
                    thresholds_counts: [grid_x, grid_y],
                    creep_shape: CreepParameters {
                        weight: 0.0,
                        ..m.creep.clone()
                    },
                };
                match fit_dynamics(&history, &all, &both) {
                    Ok(with_y) => m.hysteresis_y = with_y.hysteresis_y,
                    Err(e) => notes.push(format!("y hysteresis not identified: {e}")),
                }
            }
            m.identification.ladder_counts = lengths.clone();
            m.identification.line_rates_hz = line_rates_hz(ladder);
            m.identification.notes = notes.clone();
            Some(m)
        }
        Err(e) => {
            notes.push(format!("dynamics not identified: {e}"));
            None
        }
    };
    let loops_x = loop_rows(model.as_ref(), truth, 0, &lengths);
    let loops_y = loop_rows(model.as_ref(), truth, 1, &lengths_y);
    let creep_gamma_per_decade = model
        .as_ref()
        .and_then(|m| m.creep.law().ok())
        .map(|law| law.gamma_per_decade());
    DynamicsReport {
        creep_min_time_constant_s: model.as_ref().map(|m| m.creep.min_time_constant_s),
        model,
        frames: fast_frames,
        frames_used,
        ladder_sightings,
        track_sightings,
        slow_pairs: pairs,
        slow_pairs_used: pairs_used,
        slow_sightings,
        loops_x,
        loops_y,
        creep_gamma_per_decade,
        track_creep_gamma_per_decade,
        true_creep_gamma_per_decade: truth.map(|t| t.creep_gamma_per_decade),
        true_creep_min_time_constant_s: truth.map(|t| t.creep_min_time_constant_s),
        notes,
    }
}
