//! Developer probe of the dynamics stage on the simulator: ladder frames given as
//! `LENGTH:DWELL` arguments, the fit, and the loops it predicts against the simulator's own.
//! Not a test: `cargo run --profile test -p spmcal --example ladder_probe -- 2048:1e-4 8192:4e-4`.
#![allow(clippy::unwrap_used, clippy::print_stdout)]
use spm_correction::hysteresis::{
    CreepParameters, DynamicsFitSetup, PlayHysteresis, fit_dynamics, line_pair_sightings,
};
use spm_hal::{CountPoint, Counts, Microscope, ScanDirection, ScanRequest, Seconds, TraceHalf};

fn env(name: &str, default: f64) -> f64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() {
    if let Ok(path) = std::env::var("LOAD") {
        let text = std::fs::read_to_string(path).unwrap();
        let parse = |l: &str| -> Vec<f64> {
            l.trim_matches(|c| c == '[' || c == ']')
                .split(',')
                .map(|v| v.trim().parse().unwrap())
                .collect()
        };
        let mut lines = text.lines();
        let a = parse(lines.next().unwrap());
        let b = parse(lines.next().unwrap());
        let rows: usize = lines
            .next()
            .and_then(|l| l.trim().parse().ok())
            .unwrap_or(4);
        let columns = a.len() / rows;
        let skip = env("SKIP", 0.0) as usize;
        let (shifts, dis) = spm_features::trace_retrace_shifts(
            &a[skip * columns..],
            &b[skip * columns..],
            columns,
            rows - skip,
            &spm_features::ShiftConfig::default(),
        )
        .unwrap();
        println!("{} windows {dis} disagreeing", shifts.len());
        let cfg = spm_features::ShiftConfig::default();
        let fwd = spm_features::track_one_way(
            &a[skip * columns..],
            &b[skip * columns..],
            columns,
            rows - skip,
            &cfg,
        )
        .unwrap();
        let mirror = |img: &[f64]| -> Vec<f64> {
            img.chunks(columns)
                .flat_map(|r| r.iter().rev().copied())
                .collect()
        };
        let bwd = spm_features::track_one_way(
            &mirror(&a[skip * columns..]),
            &mirror(&b[skip * columns..]),
            columns,
            rows - skip,
            &cfg,
        )
        .unwrap();
        let n = fwd.len();
        for (i, f) in fwd.iter().enumerate().step_by((n / 40).max(1)) {
            let bk = &bwd[n - 1 - i.min(n - 1)];
            println!(
                "{:7.1} fwd {:7.2} ({:.2})   bwd@{:7.1} {:7.2} ({:.2})",
                f.column,
                f.shift_px,
                f.correlation,
                (columns - 1) as f64 - bk.column,
                -bk.shift_px,
                bk.correlation
            );
        }
        return;
    }
    let frames: Vec<(f64, f64)> = std::env::args()
        .skip(1)
        .filter_map(|a| {
            let (l, d) = a.split_once(':')?;
            Some((l.parse().ok()?, d.parse().ok()?))
        })
        .collect();
    let config = spm_sim::SimConfig::from_file(
        std::env::var("PROBE_SIM").unwrap_or_else(|_| "configs/sim-hopg.toml".to_owned()),
    )
    .unwrap();
    let mut sim = spm_sim::Simulator::new(config).unwrap();
    let (thresholds, w) = sim.oracle().hysteresis_operator(0);
    let truth = PlayHysteresis {
        weights: vec![w; thresholds.len()],
        thresholds_counts: thresholds,
    };
    let step = env("STEP", 4.0);
    let pre_move = env("PRE_MOVE", 0.0);
    if pre_move != 0.0 {
        for target in [[-pre_move, pre_move], [pre_move, -pre_move], [0.0, 0.0]] {
            sim.move_to(spm_hal::MoveRequest {
                target: CountPoint::from_counts(target[0], target[1]),
                speed: spm_hal::CountsPerSecond(20_000.0),
                settle: Seconds(10.0),
            })
            .unwrap();
        }
    }
    let pre_wait = env("PRE_WAIT", 0.0);
    if pre_wait > 0.0 {
        sim.wait(Seconds(pre_wait)).unwrap();
    }
    let mut rec = spm_hal::recording::CommandRecorder::new(&mut sim, 1_000_000);
    let mut points = Vec::new();
    for (group, &(length, dwell)) in frames.iter().enumerate() {
        let pixels = (length / step) as u32 + 1;
        let request = ScanRequest {
            origin: CountPoint::from_counts(-0.5 * length, 0.0),
            pixel_step: Counts(step),
            pixels_per_line: pixels.min(4096),
            lines: env("LINES", 4.0) as u32,
            direction: ScanDirection::Direct,
            pixel_dwell: Seconds(dwell),
            record_backward: true,
        };
        let settle = env("SETTLE", 0.0);
        if settle > 0.0 {
            rec.move_to(spm_hal::MoveRequest {
                target: CountPoint::from_counts(0.0, 0.0),
                speed: spm_hal::CountsPerSecond(20_000.0),
                settle: Seconds(settle),
            })
            .unwrap();
        }
        let frame = rec.scan(&request).unwrap();
        let skip_lines = env("SKIP_LINES", 0.0) as usize;
        let strip = |mut m: spm_hal::HeightMap| {
            m.z_counts.drain(..skip_lines * m.columns);
            m.time_s.drain(..skip_lines * m.columns);
            m.rows -= skip_lines;
            m
        };
        let f = strip(frame.height_map(TraceHalf::Forward).unwrap());
        let b = strip(frame.height_map(TraceHalf::Backward).unwrap());
        if group == env("DUMP_GROUP", 99.0) as usize {
            let _ = std::fs::write(
                "/tmp/probe.txt",
                format!("{:?}\n{:?}\n{}", f.z_counts, b.z_counts, f.rows),
            );
        }
        let (shifts, disagreeing) = spm_features::trace_retrace_shifts(
            &f.z_counts,
            &b.z_counts,
            f.columns,
            f.rows,
            &spm_features::ShiftConfig {
                window_px: env("SHIFT_WIN", 24.0) as usize,
                step_px: env("SHIFT_STEP", 8.0) as usize,
                ..spm_features::ShiftConfig::default()
            },
        )
        .unwrap();
        let good: Vec<(f64, f64)> = shifts
            .iter()
            .filter(|s| s.correlation > 0.5)
            .map(|s| (s.column, s.shift_px))
            .collect();
        let p = line_pair_sightings(&f, &b, &good, group);
        println!(
            "frame {length}:{dwell}: {} windows, {disagreeing} disagreeing, {} sightings",
            shifts.len(),
            p.len()
        );
        if disagreeing > 0 && std::env::var("KEEP").is_err() {
            continue;
        }
        points.extend(p);
    }
    let (_, events) = rec.into_parts();
    let (taus, wc) = sim.oracle().creep_elements();
    println!(
        "sim creep: {} elements {:?}..{:?} w {wc}",
        taus.len(),
        taus.first(),
        taus.last()
    );
    let history = spm_correction::dynamics::CommandHistory::from_events(&events);
    {
        let law = spm_correction::dynamics::CreepLaw::log_spaced(wc, 0.02, 2000.0, 3).unwrap();
        let mut times: Vec<f64> = points
            .iter()
            .flat_map(|p| [p.t_first_s, p.t_second_s])
            .collect();
        times.sort_by(f64::total_cmp);
        let c = spm_correction::dynamics::creep_offsets(&history, &law, &times).unwrap();
        let at = |t: f64| c[times.partition_point(|&v| v < t)][0];
        for p in points.iter().step_by((points.len() / 16).max(1)) {
            println!(
                "g{} u1 {:8.1} du {:7.2} creep pred {:7.2}  t1 {:.3} t2 {:.3}",
                p.group,
                p.u_first_counts,
                p.u_second_counts - p.u_first_counts,
                at(p.t_first_s) - at(p.t_second_s),
                p.t_first_s,
                p.t_second_s
            );
        }
    }
    let longest = frames.iter().fold(0.0_f64, |a, f| a.max(f.0));
    let n_grid: u32 = std::env::var("NGRID")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(64);
    let grid: Vec<f64> = (1..=n_grid)
        .map(|k| longest / 128.0 * f64::from(k))
        .collect();
    let fit = fit_dynamics(
        &history,
        &points,
        &DynamicsFitSetup {
            thresholds_counts: [grid, Vec::new()],
            creep_shape: CreepParameters {
                weight: 0.0,
                min_time_constant_s: std::env::var("TMIN")
                    .ok()
                    .and_then(|v| v.parse().ok())
                    .unwrap_or(0.01),
                max_time_constant_s: std::env::var("TMAX")
                    .ok()
                    .and_then(|v| v.parse().ok())
                    .unwrap_or(1e4),
                elements_per_decade: 3,
            },
        },
    )
    .unwrap();
    println!(
        "creep w {:.5} lag {:.2e} s resid {:.2} counts; W_h {:.4} (true {:.4})",
        fit.creep.weight,
        fit.identification.signal_lag_s,
        fit.identification.residual_rms_counts,
        fit.hysteresis_x.total_weight(),
        truth.total_weight()
    );
    for &(length, _) in &frames {
        let a = 0.5 * length;
        println!(
            "A {a:6}: sep centre {:7.1} true {:7.1}; at A/2 {:7.1} true {:7.1}",
            fit.hysteresis_x.loop_separation_counts(a, 0.0),
            truth.loop_separation_counts(a, 0.0),
            fit.hysteresis_x.loop_separation_counts(a, 0.5 * a),
            truth.loop_separation_counts(a, 0.5 * a)
        );
    }
}
