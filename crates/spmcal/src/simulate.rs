//! Closing the loop (DESIGN §10): the scan program of a measured file (size,
//! pixels, line time, directions, slow-axis direction, record date) run on the
//! simulated microscope of a configuration, returned as a Nanonis `.sxm` scan
//! (`spmcal simulate`; the model check's comparison of simulation and
//! measurement).

use spm_formats::{DateTime, Direction, ScanDir, SpmFile, SxmChannel, SxmScan};
use spm_hal::{CountPoint, Counts, Microscope, ScanDirection, ScanRequest, Seconds, TraceHalf};
use spm_sim::{SimConfig, Simulator};

/// Why a simulation could not be made.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SimulateError {
    /// The measured file or the configuration does not allow it (the message names which).
    #[error("{0}")]
    BadInput(String),
    /// The simulated scan failed.
    #[error("{0}")]
    Failed(String),
}

/// The scan program of a measured file.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanProgram {
    /// Pixels per line, lines.
    pub pixels: [usize; 2],
    /// Frame size, nm.
    pub size_nm: [f64; 2],
    /// Forward line time, s.
    pub line_time_s: f64,
    /// Trace and retrace recorded.
    pub both_directions: bool,
    /// Slow-axis direction.
    pub scan_dir: ScanDir,
    /// Record date.
    pub recorded: Option<DateTime>,
}

/// Reads the scan program of `file`: its first height channel (unit m).
pub fn scan_program(file: &SpmFile) -> Result<ScanProgram, SimulateError> {
    let path = file.source.display();
    let height: Vec<_> = file.channels.iter().filter(|c| c.unit() == "m").collect();
    let Some(first) = height.first() else {
        return Err(SimulateError::BadInput(format!(
            "{path}: no height channel (unit m) to copy the scan program from"
        )));
    };
    let (Some(sx), Some(sy)) = (first.size_x_nm(), first.size_y_nm()) else {
        return Err(SimulateError::BadInput(format!("{path}: no physical size")));
    };
    let both = height.iter().any(|c| c.direction() == Direction::Backward)
        && height.iter().any(|c| c.direction() == Direction::Forward);
    Ok(ScanProgram {
        pixels: [first.nx(), first.ny()],
        size_nm: [sx, sy],
        // Without timing: one second per line, as the diagnosis assumes.
        line_time_s: first.timing().map_or(1.0, |t| t.line_time_s),
        both_directions: both,
        scan_dir: first.scan_dir().or(file.scan_dir).unwrap_or(ScanDir::Up),
        recorded: file.recorded,
    })
}

/// The move history [`simulate`] puts the simulator through, for
/// `spm_modelcheck::SimContext` (the creep mapping): the scanner rests at the
/// field centre, approaches the first pixel at the scan speed, and sweeps one
/// frame, the fast axis about the centre, the slow axis from the first line to
/// the last (up scans from the bottom, down scans from the top). Times are on
/// the file's time axis (0 = the frame's start); the second value is the
/// simulator's clock at that instant (the `time_offset_s` of the context),
/// with `call_overhead_s` the simulator's time per call.
pub fn move_history(
    program: &ScanProgram,
    call_overhead_s: f64,
) -> (spm_modelcheck::MoveHistory, f64) {
    let [nx, ny] = program.pixels;
    let pixel_nm = program.size_nm[0] / nx.max(1) as f64;
    let half_y_nm = 0.5 * (ny.max(1) - 1) as f64 * pixel_nm;
    let half_x_nm = 0.5 * (nx.max(1) - 1) as f64 * pixel_nm;
    let dwell_s = program.line_time_s / nx.max(1) as f64;
    let approach_s = half_x_nm.hypot(half_y_nm) * dwell_s / pixel_nm.max(1e-300);
    let frame_s = 2.0 * program.line_time_s * ny as f64;
    let first_y = match program.scan_dir {
        ScanDir::Up => -half_y_nm,
        ScanDir::Down => half_y_nm,
    };
    let knot = |time_s: f64, y_nm: f64| spm_modelcheck::InputKnot {
        time_s,
        x_nm: 0.0,
        y_nm,
    };
    (
        spm_modelcheck::MoveHistory {
            knots: vec![
                knot(-approach_s, 0.0),
                knot(0.0, first_y),
                knot(frame_s, -first_y),
            ],
            frames_s: vec![[0.0, frame_s]],
            line_period_s: 2.0 * program.line_time_s,
        },
        call_overhead_s.max(0.0) + approach_s,
    )
}

/// Runs `program` on the simulator of `config` at the field centre and
/// returns the `.sxm` scan. `nominal_nm_per_count` is the calibration the
/// instrument's software believes (pixels are commanded with it and the file
/// states sizes in it); `None` = the config's x sensitivity. Up scans are
/// direct rasters (+x trace, lines stepping +y); down scans are counter
/// rasters (lines stepping −y), whose −x half comes first in each line.
pub fn simulate(
    program: &ScanProgram,
    config: SimConfig,
    nominal_nm_per_count: Option<f64>,
) -> Result<SxmScan, SimulateError> {
    let nominal = nominal_nm_per_count.unwrap_or(config.scanner.sensitivity_x_nm_per_count);
    if !(nominal.is_finite() && nominal > 0.0) {
        return Err(SimulateError::BadInput(format!(
            "nominal calibration {nominal} nm per count is not a positive number"
        )));
    }
    let z_nm_per_count = config.scanner.sensitivity_z_nm_per_count;
    let [nx, ny] = program.pixels;
    if nx != ny || (program.size_nm[0] - program.size_nm[1]).abs() > 1e-9 * program.size_nm[0] {
        return Err(SimulateError::BadInput(format!(
            "--like: the simulator scans square rasters with square pixels; the file has \
             {nx}×{ny} pixels over {:?} nm",
            program.size_nm
        )));
    }
    let step = program.size_nm[0] / nx as f64 / nominal;
    let dwell = program.line_time_s / nx as f64;
    let mut sim =
        Simulator::new(config).map_err(|e| SimulateError::BadInput(format!("--config: {e}")))?;
    let direction = match program.scan_dir {
        ScanDir::Up => ScanDirection::Direct,
        ScanDir::Down => ScanDirection::Counter,
    };
    let mut request = ScanRequest::centred_square(
        CountPoint::from_counts(0.0, 0.0),
        Counts(step),
        nx as u32,
        Seconds(dwell),
    )
    .with_direction(direction);
    // Both halves always: a counter raster's +x half is its backward half.
    request.record_backward = true;
    let frame = sim
        .scan(&request)
        .map_err(|e| SimulateError::Failed(format!("simulated scan failed: {e}")))?;
    // Acquisition order of an image with +x (`plus_x`) lines.
    let acquisition = |half: TraceHalf, plus_x: bool| -> Result<Vec<f64>, SimulateError> {
        let map = frame
            .height_map(half)
            .map_err(|e| SimulateError::Failed(format!("simulated frame: {e}")))?;
        let mut out = vec![0.0; nx * ny];
        for r in 0..ny {
            let row = match program.scan_dir {
                ScanDir::Up => r,
                ScanDir::Down => ny - 1 - r,
            };
            for k in 0..nx {
                let col = if plus_x { k } else { nx - 1 - k };
                out[r * nx + k] = map.z_counts[row * nx + col] * z_nm_per_count * 1e-9;
            }
        }
        Ok(out)
    };
    // Direct: forward = +x; counter: backward = +x.
    let (plus, minus) = match direction {
        ScanDirection::Counter => (TraceHalf::Backward, TraceHalf::Forward),
        _ => (TraceHalf::Forward, TraceHalf::Backward),
    };
    let forward = acquisition(plus, true)?;
    let backward = if program.both_directions {
        Some(acquisition(minus, false)?)
    } else {
        None
    };
    Ok(SxmScan {
        pixels: [nx, ny],
        size_nm: program.size_nm,
        centre_nm: [0.0, 0.0],
        angle_deg: 0.0,
        line_time_s: [program.line_time_s, program.line_time_s],
        scan_dir: program.scan_dir,
        recorded: program
            .recorded
            .or_else(|| DateTime::new(2000, 1, 1, 0, 0, 0))
            .ok_or_else(|| SimulateError::Failed("no date".into()))?,
        bias_v: 0.0,
        comment: "spmcal simulate".to_owned(),
        extra_header: Vec::new(),
        channels: vec![SxmChannel {
            name: "Z".to_owned(),
            unit: "m".to_owned(),
            forward,
            backward,
        }],
    })
}
