#![allow(clippy::unwrap_used)]
use super::*;
use crate::dynamics::creep_offsets;

/// The truth of these tests: play operators stepped command by command (written
/// independently of [`play_outputs`]), h = Σ wᵢ·yᵢ.
fn naive_h(thresholds: &[f64], weights: &[f64], commands: &[f64]) -> Vec<f64> {
    let mut y = vec![commands[0]; thresholds.len()];
    commands
        .iter()
        .map(|&u| {
            for (yi, r) in y.iter_mut().zip(thresholds) {
                if u - *yi > *r {
                    *yi = u - r;
                } else if *yi - u > *r {
                    *yi = u + r;
                }
            }
            y.iter().zip(weights).map(|(a, b)| a * b).sum()
        })
        .collect()
}

fn model() -> PlayHysteresis {
    PlayHysteresis {
        thresholds_counts: vec![300.0, 900.0, 2000.0],
        weights: vec![0.01, 0.02, 0.015],
    }
}

/// A symmetric periodic cycle ±A: the replayed branches differ by the closed-form separation.
#[test]
fn a_symmetric_cycle_has_the_closed_form_separation() {
    let m = model();
    let a = 2500.0;
    let mut h = CommandHistory::default();
    h.ramp_to(0.0, [0.0, 0.0]);
    h.ramp_to(1.0, [a, 0.0]);
    h.ramp_to(3.0, [-a, 0.0]);
    h.ramp_to(5.0, [a, 0.0]); // up branch from −A
    h.ramp_to(7.0, [-a, 0.0]); // down branch from +A
    for u in [-2000.0, -500.0, 0.0, 700.0, 2400.0] {
        let t_up = 3.0 + 2.0 * (u + a) / (2.0 * a);
        let t_down = 5.0 + 2.0 * (a - u) / (2.0 * a);
        let ys = play_outputs(&h, 0, &m.thresholds_counts, &[t_up, t_down]).unwrap();
        let hv = |y: &Vec<f64>| y.iter().zip(&m.weights).map(|(a, b)| a * b).sum::<f64>();
        let sep = hv(&ys[1]) - hv(&ys[0]);
        let closed = m.loop_separation_counts(a, u);
        assert!((sep - closed).abs() < 1e-9, "u {u}: {sep} vs {closed}");
        // The naive truth agrees.
        let commands: Vec<f64> = (0..=7000)
            .map(|k| {
                h.segments()
                    .iter()
                    .find(|s| s.end_s >= f64::from(k) * 1e-3)
                    .unwrap()
                    .at(f64::from(k) * 1e-3)[0]
            })
            .collect();
        let naive = naive_h(&m.thresholds_counts, &m.weights, &commands);
        let at = |t: f64| naive[(t * 1e3).round() as usize];
        assert!((at(t_down) - at(t_up) - closed).abs() < 0.05 * closed.abs() + 0.5);
    }
    // Closed form at the centre: Σ 2·wᵢ·min(rᵢ, A − rᵢ).
    let centre: f64 = m
        .thresholds_counts
        .iter()
        .zip(&m.weights)
        .map(|(r, w)| 2.0 * w * r.min(a - r))
        .sum();
    assert!((m.loop_separation_counts(a, 0.0) - centre).abs() < 1e-12);
}

/// Synthetic trace/retrace lines at a ladder of sizes and two rates, with creep, drift and a
/// signal lag: the fit recovers the loop the truth predicts at every ladder size.
/// A synthetic ladder (3 sizes × 2 line rates × 3 lines) through a scanner with the given
/// hysteresis and creep, a 2e-4 s signal lag and a drift: the history and the same-point
/// sightings of features every 37 counts in each line's trace and retrace.
fn synthetic_ladder(
    truth: &PlayHysteresis,
    creep_truth: &CreepParameters,
) -> (CommandHistory, Vec<SamePoint>) {
    let lag_s = 2e-4;
    let drift_counts_per_s = 3.0;
    let mut history = CommandHistory::default();
    history.ramp_to(0.0, [0.0, 0.0]);
    let mut t = 0.0;
    let mut lines: Vec<(f64, f64, f64, f64)> = Vec::new(); // (start, length, line time, x0)
    for &length in &[500.0, 2000.0, 8000.0] {
        for &half_line_s in &[0.05, 0.2] {
            let x0 = -0.5 * length;
            t += 0.5;
            history.ramp_to(t, [x0, 0.0]);
            for _ in 0..3 {
                lines.push((t, length, half_line_s, x0));
                history.ramp_to(t + half_line_s, [x0 + length, 0.0]);
                history.ramp_to(t + 2.0 * half_line_s, [x0, 0.0]);
                t += 2.0 * half_line_s;
            }
        }
    }
    history.hold_until(t + 1.0);
    // Truth on a dense timeline: e(t) = u + h + c(u + h) + drift; the recorded signal lags.
    let dt = 2e-4;
    let n = (t / dt) as usize;
    let times: Vec<f64> = (0..n).map(|k| k as f64 * dt).collect();
    let mut s = 0;
    let u: Vec<f64> = times
        .iter()
        .map(|&ti| {
            while history.segments()[s].end_s < ti {
                s += 1;
            }
            history.segments()[s].at(ti)[0]
        })
        .collect();
    let hv = naive_h(&truth.thresholds_counts, &truth.weights, &u);
    let mut xh = CommandHistory::default();
    for (k, &ti) in times.iter().enumerate() {
        xh.ramp_to(ti, [u[k] + hv[k], 0.0]);
    }
    let c = creep_offsets(&xh, &creep_truth.law().unwrap(), &times).unwrap();
    let e: Vec<f64> = (0..n)
        .map(|k| u[k] + hv[k] + c[k][0] + drift_counts_per_s * times[k])
        .collect();
    // Sightings: features every 37 counts; in each line's trace and retrace the command at
    // which the (lagged) signal shows e = feature.
    let mut sightings = Vec::new();
    let lag_k = (lag_s / dt).round() as usize;
    for (line, &(start, length, half_s, x0)) in lines.iter().enumerate() {
        let k0 = (start / dt).ceil() as usize + lag_k;
        let k1 = ((start + half_s) / dt) as usize;
        let k2 = ((start + 2.0 * half_s) / dt) as usize;
        let speed = length / half_s;
        let mut feature = x0 + 0.1 * length;
        while feature < x0 + 0.9 * length {
            let find = |from: usize, to: usize| -> Option<(f64, f64)> {
                (from..to.min(n - 1)).find_map(|k| {
                    let (a, b) = (e[k - lag_k] - feature, e[k + 1 - lag_k] - feature);
                    (a * b <= 0.0 && a != b).then(|| {
                        let f = a / (a - b);
                        (times[k] + f * dt, u[k] + f * (u[k + 1] - u[k]))
                    })
                })
            };
            if let (Some((t1, u1)), Some((t2, u2))) = (find(k0, k1), find(k1 + lag_k, k2)) {
                sightings.push(SamePoint {
                    axis: 0,
                    t_first_s: t1,
                    u_first_counts: u1,
                    v_first_counts_per_s: speed,
                    t_second_s: t2,
                    u_second_counts: u2,
                    v_second_counts_per_s: -speed,
                    group: line,
                });
            }
            feature += 37.0;
        }
    }
    (history, sightings)
}

#[test]
fn the_fit_recovers_the_loops_of_a_ladder() {
    let truth = PlayHysteresis {
        thresholds_counts: vec![400.0, 1100.0, 1800.0, 2600.0, 3400.0],
        weights: vec![0.012, 0.009, 0.011, 0.008, 0.01],
    };
    let creep_truth = CreepParameters {
        weight: 0.004,
        min_time_constant_s: 0.01,
        max_time_constant_s: 1000.0,
        elements_per_decade: 3,
    };
    let lag_s = 2e-4;
    let (history, sightings) = synthetic_ladder(&truth, &creep_truth);
    assert!(sightings.len() > 300, "{}", sightings.len());
    let grid: Vec<f64> = (1..=40).map(|k| 100.0 * f64::from(k)).collect();
    let fit = fit_dynamics(
        &history,
        &sightings,
        &DynamicsFitSetup {
            thresholds_counts: [grid, Vec::new()],
            creep_shape: CreepParameters {
                weight: 0.0,
                ..creep_truth.clone()
            },
        },
    )
    .unwrap();
    for amplitude in [250.0, 1000.0, 4000.0] {
        for u in [-0.5 * amplitude, 0.0, 0.5 * amplitude] {
            let want = truth.loop_separation_counts(amplitude, u);
            let got = fit.hysteresis_x.loop_separation_counts(amplitude, u);
            assert!(
                (got - want).abs() <= 0.1 * want + 0.3,
                "A {amplitude} u {u}: {got} vs {want} ({fit:?})"
            );
        }
    }
    assert!(
        (fit.identification.signal_lag_s - lag_s).abs() < 0.3 * lag_s,
        "{fit:?}"
    );
}

/// The creep law's shortest time constant hidden in a ladder (0.05 s, between the candidates
/// 0.0464 and 0.1) is found: the nearest candidate wins, with a residual below the fixed
/// shape's (0.01 s), and the weight comes back.
#[test]
fn the_fast_end_of_the_creep_law_is_found_in_a_ladder() {
    let truth = PlayHysteresis {
        thresholds_counts: vec![400.0, 1100.0, 1800.0, 2600.0, 3400.0],
        weights: vec![0.012, 0.009, 0.011, 0.008, 0.01],
    };
    let creep_truth = CreepParameters {
        weight: 0.006,
        min_time_constant_s: 0.05,
        max_time_constant_s: 1000.0,
        elements_per_decade: 3,
    };
    let (history, sightings) = synthetic_ladder(&truth, &creep_truth);
    let grid: Vec<f64> = (1..=40).map(|k| 100.0 * f64::from(k)).collect();
    let setup = DynamicsFitSetup {
        thresholds_counts: [grid, Vec::new()],
        creep_shape: CreepParameters {
            weight: 0.0,
            min_time_constant_s: 0.01,
            max_time_constant_s: 1000.0,
            elements_per_decade: 3,
        },
    };
    let candidates: Vec<f64> = (0..=9)
        .map(|k| 1e-3 * 10f64.powf(f64::from(k) / 3.0))
        .collect();
    let fit = fit_dynamics_choosing_fast_end(&history, &sightings, &setup, &candidates).unwrap();
    let trials = &fit.identification.creep_fast_end_trials;
    // Every other candidate, and the best one's neighbours.
    assert!(
        trials.len() >= candidates.len() / 2 && trials.len() <= candidates.len(),
        "{trials:?}"
    );
    assert!(
        trials
            .windows(2)
            .all(|w| w[0].min_time_constant_s < w[1].min_time_constant_s)
    );
    let chosen = fit.creep.min_time_constant_s;
    assert!(
        (chosen / 0.0464 - 1.0).abs() < 0.01,
        "{chosen} ({trials:?})"
    );
    let fixed = fit_dynamics(&history, &sightings, &setup).unwrap();
    assert!(
        fit.identification.residual_rms_counts < 0.8 * fixed.identification.residual_rms_counts,
        "{} vs the fixed shape's {}",
        fit.identification.residual_rms_counts,
        fixed.identification.residual_rms_counts
    );
    // The law's weight per element depends on its element count; compare the settled gains
    // over the truth's own span of time constants (0.05 … 1000 s against 0.0464 … 1000 s).
    let gamma = fit.creep.law().unwrap().gamma_per_decade();
    let want = creep_truth.law().unwrap().gamma_per_decade();
    assert!((gamma / want - 1.0).abs() < 0.15, "γ {gamma} vs {want}");
    // No usable candidate is an error naming the range.
    let e = fit_dynamics_choosing_fast_end(&history, &sightings, &setup, &[-1.0, 5e3]).unwrap_err();
    assert!(
        e.to_string().contains("shortest creep time constant"),
        "{e}"
    );
}

/// The dynamics of a file: serialised and read back unchanged; a wrong version is refused.
#[test]
fn dynamics_round_trip_and_refuse_other_versions() {
    let d = ScannerDynamics {
        format: DYNAMICS_FORMAT.to_owned(),
        version: DYNAMICS_FORMAT_VERSION,
        hysteresis_x: model(),
        hysteresis_y: PlayHysteresis::none(),
        creep: CreepParameters {
            weight: 0.004,
            min_time_constant_s: 0.01,
            max_time_constant_s: 1e4,
            elements_per_decade: 3,
        },
        identification: DynamicsIdentification::default(),
    };
    d.validate().unwrap();
    let text = serde_json::to_string(&d).unwrap();
    let back: ScannerDynamics = serde_json::from_str(&text).unwrap();
    assert_eq!(back, d);
    let mut bad = d.clone();
    bad.version = 99;
    assert!(bad.validate().is_err());
    let mut bad = d;
    bad.hysteresis_x.weights[0] = -0.1;
    assert!(bad.validate().is_err());
}

/// The swept hysteresis of [`replay_axis`] equals the weighted operator outputs, on a history
/// with reversals inside segments' queries and after its end.
#[test]
fn streamed_hysteresis_equals_the_weighted_outputs() {
    let m = model();
    let mut h = CommandHistory::default();
    h.ramp_to(0.0, [0.0, 0.0]);
    h.ramp_to(1.0, [3000.0, -200.0]);
    h.ramp_to(1.5, [-1000.0, 400.0]);
    h.ramp_to(2.5, [2500.0, 0.0]);
    let times: Vec<f64> = (0..=60).map(|k| 0.05 * f64::from(k)).collect();
    for axis in 0..2 {
        let ys = play_outputs(&h, axis, &m.thresholds_counts, &times).unwrap();
        let law = CreepParameters {
            weight: 0.0,
            min_time_constant_s: 1.0,
            max_time_constant_s: 1.0,
            elements_per_decade: 1,
        }
        .law()
        .unwrap();
        let mut streamed = Vec::new();
        replay_axis(&h, axis, &m, &law, &times, |h, _| streamed.push(h)).unwrap();
        assert_eq!(streamed.len(), times.len());
        for (y, s) in ys.iter().zip(&streamed) {
            let want: f64 = y.iter().zip(&m.weights).map(|(a, b)| a * b).sum();
            assert!((want - s).abs() < 1e-12, "{want} vs {s}");
        }
    }
}

/// The streaming replay of [`ScannerDynamics::offsets`] equals (to 1e-9 counts) its definition
/// composed from the separate pieces: h from [`play_outputs`] at every vertex and query, the
/// post-hysteresis input x = u + h as a straight-piece history through them, its creep by
/// [`crate::dynamics::creep_offsets`]; on a raster-like history with evenly spaced queries
/// (where the replay reuses its exponentials across last-bit differences), reversals, a hold, and queries after the end.
#[test]
fn the_streaming_replay_equals_the_composed_definition() {
    let d = ScannerDynamics {
        format: DYNAMICS_FORMAT.to_owned(),
        version: DYNAMICS_FORMAT_VERSION,
        hysteresis_x: model(),
        hysteresis_y: PlayHysteresis {
            thresholds_counts: vec![100.0, 700.0],
            weights: vec![0.03, 0.01],
        },
        creep: CreepParameters {
            weight: 0.004,
            min_time_constant_s: 0.01,
            max_time_constant_s: 1e4,
            elements_per_decade: 3,
        },
        identification: DynamicsIdentification::default(),
    };
    let mut h = CommandHistory::default();
    h.ramp_to(0.0, [-4000.0, -3000.0]);
    h.ramp_to(2.0, [0.0, 0.0]);
    h.hold_until(5.0);
    let mut times = Vec::new();
    for line in 0..6 {
        let base = 5.0 + 0.2 * f64::from(line);
        let y = 40.0 * f64::from(line);
        h.ramp_to(base + 0.1, [3000.0, y]);
        h.ramp_to(base + 0.2, [0.0, y + 40.0]);
        times.extend((0..64).map(|k| base + (f64::from(k) + 0.5) * 0.1 / 64.0));
    }
    times.extend([7.0, 9.5]);
    let got = d.offsets(&h, &times).unwrap();

    let mut merged: Vec<f64> = h.segments().iter().map(|s| s.end_s).collect();
    merged.extend(&times);
    merged.sort_by(f64::total_cmp);
    merged.dedup();
    let models = [&d.hysteresis_x, &d.hysteresis_y];
    let hs: Vec<Vec<f64>> = (0..2)
        .map(|axis| {
            play_outputs(&h, axis, &models[axis].thresholds_counts, &merged)
                .unwrap()
                .iter()
                .map(|y| {
                    y.iter()
                        .zip(&models[axis].weights)
                        .map(|(y, w)| y * w)
                        .sum()
                })
                .collect()
        })
        .collect();
    let mut x = CommandHistory::default();
    for (k, &t) in merged.iter().enumerate() {
        let seg = h
            .segments()
            .iter()
            .find(|s| s.end_s >= t)
            .unwrap_or_else(|| h.segments().last().unwrap());
        let u = seg.at(t);
        x.ramp_to(t, [u[0] + hs[0][k], u[1] + hs[1][k]]);
    }
    let c = creep_offsets(&x, &d.creep.law().unwrap(), &times).unwrap();
    for (i, &t) in times.iter().enumerate() {
        let k = merged.partition_point(|&v| v < t);
        let want = [hs[0][k] + c[i][0], hs[1][k] + c[i][1]];
        for axis in 0..2 {
            let e = (got[i][axis] - want[axis]).abs();
            assert!(
                e < 1e-9,
                "query {i} at {t} s axis {axis}: {got:?} vs {want:?}",
                got = got[i]
            );
        }
    }
}

/// A counter-scanned pair's sightings: `up` saw at row r what `down` shows at row r + s;
/// each sighting carries the two rows' commands, their times (the middle column's, in time
/// order) and the slow axis's signed command velocities.
#[test]
fn counter_pair_sightings_carry_rows_times_and_slow_velocities() {
    use spm_hal::{CountPoint, Counts, HeightMap};
    let (nx, ny) = (4, 10);
    let line_s = 0.004;
    let map = |up: bool| HeightMap {
        origin: CountPoint::from_counts(100.0, -500.0),
        pixel_step: Counts(3.0),
        columns: nx,
        rows: ny,
        z_counts: vec![0.0; nx * ny],
        time_s: (0..ny)
            .flat_map(|r| {
                let line = if up { r } else { 2 * ny - 1 - r };
                (0..nx).map(move |c| line as f64 * line_s + c as f64 * 1e-4)
            })
            .collect(),
    };
    let (up, down) = (map(true), map(false));
    let s = counter_pair_sightings(&up, &down, &[(2.0, 1.5), (8.0, -0.5), (9.5, 1.0)], 7);
    // The last shift points outside the frame: dropped.
    assert_eq!(s.len(), 2);
    let first = &s[0];
    assert_eq!((first.axis, first.group), (1, 7));
    assert!((first.u_first_counts - (-500.0 + 6.0)).abs() < 1e-12);
    assert!((first.u_second_counts - (-500.0 + 10.5)).abs() < 1e-12);
    assert!((first.t_first_s - (2.0 * line_s + 2e-4)).abs() < 1e-12);
    assert!((first.t_second_s - ((19.0 - 3.5) * line_s + 2e-4)).abs() < 1e-12);
    assert!((first.v_first_counts_per_s - 3.0 / line_s).abs() < 1e-9);
    assert!((first.v_second_counts_per_s + 3.0 / line_s).abs() < 1e-9);
    assert!(s[1].t_first_s < s[1].t_second_s);
}
