//! `cargo xtask calibrate`: until the calibration issue lands, a simulated
//! scan of HOPG (direct and counter frames) written as PNG images, with a
//! report of the scan and the oracle's true LCCs at its centre.

use crate::XtaskError;
use serde::Serialize;
use spm_hal::{
    CountPoint, Counts, HeightMap, Microscope, ScanDirection, ScanRequest, Seconds, TraceHalf,
};
use spm_sim::{SimConfig, Simulator};
use std::path::Path;
use std::time::Instant;

#[derive(Debug, Serialize)]
struct ScanReport {
    config: String,
    seed: u64,
    pixels: [u32; 2],
    pixel_step_counts: f64,
    pixel_dwell_s: f64,
    centre_counts: [f64; 2],
    instrument_time_s: f64,
    wall_time_s: f64,
    frames: Vec<String>,
    true_lcc_at_centre: TrueLcc,
    true_drift_velocity_nm_per_s: [f64; 2],
}

#[derive(Debug, Serialize)]
struct TrueLcc {
    kx_nm_per_count: f64,
    ky_nm_per_count: f64,
    alpha_rad: f64,
    kz_nm_per_count: f64,
}

pub fn run(config_path: &Path, out: &Path, quick: bool) -> Result<(), XtaskError> {
    let started = Instant::now();
    let config = SimConfig::from_file(config_path)
        .map_err(|e| XtaskError::step("reading the simulator config", e))?;
    let seed = config.seed;
    let mut sim =
        Simulator::new(config).map_err(|e| XtaskError::step("building the simulator", e))?;
    std::fs::create_dir_all(out)
        .map_err(|e| XtaskError::step(format!("creating {}", out.display()), e))?;

    let pixels: u32 = if quick { 64 } else { 256 };
    let centre = CountPoint::from_counts(0.0, 0.0);
    let pixel_dwell = Seconds(1e-4);
    let request = ScanRequest::centred_square(centre, Counts(1.0), pixels, pixel_dwell);
    let mut frames = Vec::new();
    for direction in [ScanDirection::Direct, ScanDirection::Counter] {
        let request = request.clone().with_direction(direction);
        let frame = sim
            .scan(&request)
            .map_err(|e| XtaskError::step(format!("{direction:?} scan"), e))?;
        let map = frame
            .height_map(TraceHalf::Forward)
            .map_err(|e| XtaskError::step("frame", e))?;
        let name = format!("hopg-{direction:?}.png").to_lowercase();
        let kx = sim
            .oracle()
            .true_lcc(centre, sim.oracle().z_now())
            .kx
            .value();
        write_png(&map, kx, &out.join(&name))?;
        frames.push(name);
    }
    let oracle = sim.oracle();
    let lcc = oracle.true_lcc(centre, oracle.z_now());
    let now = sim.now().map_err(|e| XtaskError::step("clock", e))?;
    let drift = sim.oracle().drift_velocity(now);
    let report = ScanReport {
        config: config_path.display().to_string(),
        seed,
        pixels: [pixels, pixels],
        pixel_step_counts: 1.0,
        pixel_dwell_s: pixel_dwell.value(),
        centre_counts: [0.0, 0.0],
        instrument_time_s: now.value(),
        wall_time_s: started.elapsed().as_secs_f64(),
        frames,
        true_lcc_at_centre: TrueLcc {
            kx_nm_per_count: lcc.kx.value(),
            ky_nm_per_count: lcc.ky.value(),
            alpha_rad: lcc.alpha.value(),
            kz_nm_per_count: sim.oracle().kz().value(),
        },
        true_drift_velocity_nm_per_s: [drift.x_nm_per_s, drift.y_nm_per_s],
    };
    let json = serde_json::to_string_pretty(&report).map_err(|e| XtaskError::step("report", e))?;
    let report_path = out.join("report.json");
    std::fs::write(&report_path, json)
        .map_err(|e| XtaskError::step(format!("writing {}", report_path.display()), e))?;
    println!(
        "simulated HOPG scan {pixels}×{pixels} (direct + counter) in {:.2} s wall, {:.2} s instrument time",
        report.wall_time_s, report.instrument_time_s
    );
    println!(
        "true LCCs at the centre: K̄x = {:.5} nm/count, K̄y = {:.5} nm/count, α = {:.4}°",
        lcc.kx.value(),
        lcc.ky.value(),
        lcc.alpha.to_degrees()
    );
    println!("report: {}", report_path.display());
    Ok(())
}

/// Writes a height map (scanner geometry, row 0 = smallest y) as a PNG in
/// display orientation (row 0 = top = largest y).
fn write_png(map: &HeightMap, nominal_nm_per_count: f64, path: &Path) -> Result<(), XtaskError> {
    let mut display = Vec::with_capacity(map.z_counts.len());
    for row in (0..map.rows).rev() {
        display.extend_from_slice(&map.z_counts[row * map.columns..(row + 1) * map.columns]);
    }
    let size_nm = map.pixel_step.value() * nominal_nm_per_count * map.columns as f64;
    let channel = spm_formats::Channel::new(
        "Z",
        spm_formats::Direction::Forward,
        "counts",
        map.columns,
        map.rows,
        display,
    )
    .map_err(|e| XtaskError::step("image", e))?
    .with_size_nm(size_nm, size_nm);
    let options = spm_formats::PngOptions {
        zoom: if map.columns < 128 { 4 } else { 2 },
        ..spm_formats::PngOptions::default()
    };
    spm_formats::write_png(path, &channel, &options)
        .map_err(|e| XtaskError::step(format!("writing {}", path.display()), e))
}
