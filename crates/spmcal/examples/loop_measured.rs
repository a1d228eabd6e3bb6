//! Closing the loop on the measured datasets (DESIGN §10, issue 18): for each
//! file, the diagnosis's baseline configuration and its extended one
//! (`spm_modelcheck::sim_patch`) drive spm-sim through the file's own scan
//! program (`spmcal::simulate`), and both simulations are compared with the
//! measurement on feature positions (the diagnosis of the simulated file:
//! lumped scanner, trace/retrace shift) and image statistics (corrugation,
//! white-noise level, trace/retrace difference).
//!
//! `cargo run -p spmcal --example loop_measured` (prints a Markdown table).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_formats::{Channel, Direction, read_any};
use spm_modelcheck::{
    Diagnosis, ExtractOptions, ImageInput, LatticeSpec, LineDirection, Options, SimContext,
    diagnose, sim_patch,
};
use spm_sim::{HopgConfig, Si7x7Config, SimConfig, SurfaceConfig};
use spmcal::simulate::{move_history, scan_program, simulate};
use std::path::{Path, PathBuf};

/// Image statistics of the first height channel pair, pm.
#[derive(Clone, Copy, Debug, Default)]
struct Stats {
    corrugation_pm: f64,
    noise_pm: f64,
    trace_retrace_pm: f64,
}

fn levelled(c: &Channel) -> Vec<Vec<f64>> {
    let img = c.display_image();
    (0..img.ny)
        .map(|r| {
            let row: Vec<f64> = img.data[r * img.nx..(r + 1) * img.nx]
                .iter()
                .map(|v| if v.is_finite() { v * 1e12 } else { 0.0 })
                .collect();
            let n = row.len() as f64;
            let mx = (n - 1.0) / 2.0;
            let my = row.iter().sum::<f64>() / n;
            let sxx: f64 = (0..row.len()).map(|i| (i as f64 - mx).powi(2)).sum();
            let sxy: f64 = row
                .iter()
                .enumerate()
                .map(|(i, v)| (i as f64 - mx) * (v - my))
                .sum();
            let b = sxy / sxx.max(1e-300);
            row.iter()
                .enumerate()
                .map(|(i, v)| v - my - b * (i as f64 - mx))
                .collect()
        })
        .collect()
}

fn stats(path: &Path) -> Stats {
    let file = read_any(path).unwrap();
    let fwd = file
        .channels
        .iter()
        .find(|c| c.unit() == "m" && c.direction() == Direction::Forward)
        .unwrap();
    let bwd = file.channels.iter().find(|c| {
        c.unit() == "m" && c.direction() == Direction::Backward && c.name() == fwd.name()
    });
    let f = levelled(fwd);
    let rms = |rows: &[Vec<f64>]| {
        let (s, n) = rows
            .iter()
            .flatten()
            .fold((0.0, 0usize), |a, v| (a.0 + v * v, a.1 + 1));
        (s / n.max(1) as f64).sqrt()
    };
    // White noise from the second difference along the fast axis: var(Δ²) = 6σ².
    let d2: Vec<Vec<f64>> = f
        .iter()
        .map(|r| r.windows(3).map(|w| w[0] - 2.0 * w[1] + w[2]).collect())
        .collect();
    let tr = bwd.map_or(f64::NAN, |b| {
        let b = levelled(b);
        let diff: Vec<Vec<f64>> = f
            .iter()
            .zip(&b)
            .map(|(x, y)| x.iter().zip(y).map(|(p, q)| p - q).collect())
            .collect();
        rms(&diff)
    });
    Stats {
        corrugation_pm: rms(&f),
        noise_pm: rms(&d2) / 6f64.sqrt(),
        trace_retrace_pm: tr,
    }
}

/// Trace − retrace shift of the features along the fast axis in the
/// baseline fit (mean x residual forward − backward), pm.
fn feature_shift_pm(d: &Diagnosis) -> f64 {
    let mean = |dir| {
        let v: Vec<f64> = d
            .residuals
            .iter()
            .filter(|r| r.used && r.direction == dir)
            .map(|r| r.baseline_pm[0])
            .collect();
        v.iter().sum::<f64>() / v.len().max(1) as f64
    };
    mean(LineDirection::Forward) - mean(LineDirection::Backward)
}

fn diag(path: &Path, lattice: &LatticeSpec) -> Result<Diagnosis, String> {
    diagnose(
        &[ImageInput {
            path: path.to_path_buf(),
            start_time_s: None,
        }],
        lattice,
        &Options::default(),
        &ExtractOptions::default(),
    )
    .map_err(|e| e.to_string())
}

fn base_config(lattice: &LatticeSpec, nominal: f64, corr_nm: f64, noise_nm: f64) -> SimConfig {
    let mut c = SimConfig::ideal();
    c.seed = 7;
    c.scanner.sensitivity_x_nm_per_count = nominal;
    c.scanner.sensitivity_y_nm_per_count = nominal;
    c.measurement.z_white_noise_nm = noise_nm;
    c.surface = if (lattice.a_nm() - spm_modelcheck::SI7X7_A_NM).abs() < 1e-6 {
        SurfaceConfig::Si7x7(Si7x7Config {
            lattice_constant_nm: lattice.a_nm(),
            corner_hole_depth_nm: corr_nm,
            corner_hole_sigma_nm: 0.35,
            rotation_deg: 0.0,
        })
    } else {
        let SurfaceConfig::Hopg(h) = &c.surface else {
            unreachable!()
        };
        SurfaceConfig::Hopg(HopgConfig {
            corrugation_nm: corr_nm,
            ..h.clone()
        })
    };
    c
}

fn run_sim(like: &Path, config: SimConfig, nominal: f64, out: &Path) {
    let file = read_any(like).unwrap();
    let program = scan_program(&file).unwrap();
    let scan = simulate(&program, config, Some(nominal)).unwrap();
    spm_formats::write_sxm(out, &scan).unwrap();
}

fn main() {
    let sets: [(&str, &str, &str); 9] = [
        ("si7x7-051", "si7x7", "si7x7-nanonis/Si_7x7_051.sxm"),
        ("si7x7-028", "si7x7", "si7x7-nanonis/Si_7x7_028.sxm"),
        ("si7x7-032", "si7x7", "si7x7-nanonis/Si_7x7_032.sxm"),
        ("si7x7-012", "si7x7", "si7x7-nanonis/Si_7x7_012.sxm"),
        (
            "si7x7-raw-defects",
            "si7x7",
            "si7x7-raw/image_with_defects.dat",
        ),
        (
            "si7x7-raw-step-edge",
            "si7x7",
            "si7x7-raw/image_with_step_edge.dat",
        ),
        (
            "si7x7-raw-step-edge-atoms",
            "si7x7",
            "si7x7-raw/image_with_step_edge_and_atoms.dat",
        ),
        (
            "graphite-sm4",
            "hopg",
            "graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4",
        ),
        (
            "hopg-terrace",
            "hopg",
            "hopg-terrace-iso28600/graphiteterrace.spm",
        ),
    ];
    let tmp: PathBuf = std::env::temp_dir().join(format!("spmcal-loop-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    println!("| dataset | what | measured | baseline sim | extended sim | gain |");
    println!("|---|---|---|---|---|---|");
    for (name, lat, rel) in sets {
        let path = spmcal_tests::measured_file(rel);
        let lattice = LatticeSpec::parse(lat).unwrap();
        let d = match diag(&path, &lattice) {
            Ok(d) => d,
            Err(e) => {
                println!("| {name} | diagnosis refused | {e} | | | |");
                continue;
            }
        };
        let file = read_any(&path).unwrap();
        // A file without a scan program (no size or line time stored: the
        // raw Si 7×7 files) has nothing to re-run on the simulator.
        let program = match scan_program(&file) {
            Ok(program) => program,
            Err(e) => {
                println!("| {name} | no scan program to simulate | {e} | | | |");
                continue;
            }
        };
        let pixel_nm = program.size_nm[0] / program.pixels[0] as f64;
        let nominal = pixel_nm / 8.0;
        let meas = stats(&path);
        // The baseline's image statistics: the white noise as measured, the
        // corrugation scaled so the noise-free simulation matches the signal.
        let noise_nm = meas.noise_pm * 1e-3;
        let probe = tmp.join(format!("{name}-probe.sxm"));
        run_sim(
            &path,
            base_config(&lattice, nominal, 0.1, 0.0),
            nominal,
            &probe,
        );
        let s0 = stats(&probe);
        let signal = (meas.corrugation_pm.powi(2) - meas.noise_pm.powi(2))
            .max(0.0)
            .sqrt();
        let corr_nm = 0.1 * signal / s0.corrugation_pm.max(1e-9);
        let mut base = base_config(&lattice, nominal, corr_nm, noise_nm);
        // The scanner field holds the frame twice over: the diagnosis's
        // frame-relative nonlinearity maps to modest field coefficients.
        base.instrument.lateral_half_range_counts = program.pixels[0] as f64 * 8.0;
        for h in [
            &mut base.scanner.hysteresis_x,
            &mut base.scanner.hysteresis_y,
        ] {
            h.max_threshold_counts = h
                .max_threshold_counts
                .min(0.25 * program.pixels[0] as f64 * 8.0);
            h.min_threshold_counts = h.min_threshold_counts.min(0.5 * h.max_threshold_counts);
        }
        let (history, frame_start_s) = move_history(&program, base.instrument.call_overhead_s);
        let ctx = SimContext {
            nominal_nm_per_count: nominal,
            half_range_counts: base.instrument.lateral_half_range_counts,
            time_offset_s: frame_start_s,
            warmup_time_constant_s: 60.0,
            pixel_dwell_s: Some(program.line_time_s / program.pixels[0] as f64),
            move_history: Some(history),
        };
        let text = toml::to_string(&base).unwrap();
        let mut results = Vec::new();
        for extended in [false, true] {
            let patch = sim_patch(&d, &ctx, extended);
            let patched = patch.apply_to_toml(&text).unwrap();
            let config = SimConfig::from_toml_str(&patched, name).unwrap();
            let out = tmp.join(format!(
                "{name}-{}.sxm",
                if extended { "ext" } else { "base" }
            ));
            run_sim(&path, config, nominal, &out);
            let ds = diag(&out, &lattice).ok();
            results.push((stats(&out), ds, patch.unmapped.clone()));
        }
        let row = |what: &str, m: f64, b: f64, e: f64| {
            let gain = (b - m).abs() / (e - m).abs().max(1e-9);
            let p = if m.abs() < 5.0 { 3 } else { 1 };
            println!(
                "| {name} | {what} | {m:.p$} | {b:.p$} | {e:.p$} | {} |",
                if gain.is_finite() {
                    format!("{gain:.2}×")
                } else {
                    "—".into()
                }
            );
        };
        let (sb, db, _) = &results[0];
        let (se, de, unmapped) = &results[1];
        row(
            "corrugation, pm",
            meas.corrugation_pm,
            sb.corrugation_pm,
            se.corrugation_pm,
        );
        row("white noise, pm", meas.noise_pm, sb.noise_pm, se.noise_pm);
        row(
            "trace − retrace image RMS, pm",
            meas.trace_retrace_pm,
            sb.trace_retrace_pm,
            se.trace_retrace_pm,
        );
        let fs = |d: &Option<Diagnosis>| d.as_ref().map_or(f64::NAN, feature_shift_pm);
        row(
            "feature shift trace − retrace, pm",
            feature_shift_pm(&d),
            fs(db),
            fs(de),
        );
        let p = |d: &Diagnosis, k: &str| d.baseline.parameters.get(k).map_or(f64::NAN, |p| p.value);
        for k in ["scale_x", "scale_y", "obliquity_deg"] {
            let g = |x: &Option<Diagnosis>| x.as_ref().map_or(f64::NAN, |x| p(x, k));
            row(k, p(&d, k), g(db), g(de));
        }
        println!(
            "| {name} | findings; unmapped | {:?} | | | {:?} |",
            d.effects_found(),
            unmapped
        );
    }
    let _ = std::fs::remove_dir_all(&tmp);
}
