//! `spmcal scan`: one image through a job's backend (sim, nanonis), written with what a
//! controller records and the command history the backend was driven with
//! (`IMAGE.history.json`), so that `spmcal correct` applies the full dynamic correction to it.

use std::path::PathBuf;

use spm_apply::history::{HISTORY_FORMAT, HISTORY_VERSION, ScanHistory, sidecar_of};
use spm_apply::{
    KEY_CONVENTION, KEY_LINE_TIME, KEY_NOMINAL, KEY_ORIGIN_X, KEY_ORIGIN_Y, KEY_SCAN_PATH,
    KEY_SCANNER, KEY_STEP,
};
use spm_hal::{CountPoint, Counts, ScanDirection, ScanRequest, Seconds, TraceHalf};
use spmcal::job::Job;

use crate::error::CliError;

/// Take one image through a job's backend and keep the command history it was taken with
/// (IMAGE.gsf and IMAGE.gsf.history.json): `spmcal correct` then corrects the creep of the
/// approach move and the raster's dynamics with the calibration's dynamics.
#[derive(Debug, clap::Args)]
pub struct ScanArgs {
    /// The job file whose backend (and plan: scanner id, nominal sensitivity, dwell) is used.
    #[arg(long, value_name = "FILE")]
    pub config: PathBuf,
    /// The image to write (.gsf); the history goes to OUT.history.json beside it.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// Frame centre x, counts.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub x_counts: f64,
    /// Frame centre y, counts.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub y_counts: f64,
    /// Frame side, counts.
    #[arg(long)]
    pub size_counts: f64,
    /// Pixels per line (and lines).
    #[arg(long, default_value_t = 256)]
    pub pixels: u32,
    /// Pixel dwell, s (default: the plan's).
    #[arg(long)]
    pub dwell_s: Option<f64>,
    /// Scan as a counter raster (−x lines from the far corner, stepping −y).
    #[arg(long)]
    pub counter: bool,
    /// Wait at the frame's centre before the raster, s.
    #[arg(long, default_value_t = 10.0)]
    pub settle_s: f64,
}

pub fn run(args: &ScanArgs) -> Result<(), CliError> {
    let centre_counts = [args.x_counts, args.y_counts];
    if !args
        .out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("gsf"))
    {
        return Err(CliError::BadInput(format!(
            "--out {}: spmcal scan writes a Gwyddion .gsf image (and IMAGE.gsf.history.json)",
            args.out.display()
        )));
    }
    let bad = |what: &str| CliError::BadInput(what.to_owned());
    if !(args.size_counts.is_finite() && args.size_counts > 0.0) {
        return Err(bad("--size-counts must be a number > 0"));
    }
    if args.pixels < 2 {
        return Err(bad("--pixels must be at least 2"));
    }
    if !(args.settle_s.is_finite() && args.settle_s >= 0.0) {
        return Err(bad("--settle-s must be a number ≥ 0"));
    }
    if !centre_counts.iter().all(|v| v.is_finite()) {
        return Err(bad("--x-counts and --y-counts must be finite"));
    }
    crate::files::check_input(&args.config, "job")?;
    let job = Job::from_file(&args.config).map_err(|e| CliError::BadInput(e.to_string()))?;
    let dwell = args.dwell_s.unwrap_or(job.plan.motion.pixel_dwell_s);
    if !(dwell.is_finite() && dwell > 0.0) {
        return Err(bad("--dwell-s must be a number > 0"));
    }
    let sidecar = sidecar_of(&args.out);
    crate::files::check_output(&args.out, "--out", &[&args.config])?;
    crate::files::check_output(&sidecar, "--out", &[&args.config])?;
    let step = args.size_counts / f64::from(args.pixels - 1);
    let request = ScanRequest::centred_square(
        CountPoint::from_counts(centre_counts[0], centre_counts[1]),
        Counts(step),
        args.pixels,
        Seconds(dwell),
    )
    .with_direction(if args.counter {
        ScanDirection::Counter
    } else {
        ScanDirection::Direct
    });
    let scan = spmcal::run::scan_recorded(&job, &request, args.settle_s)
        .map_err(|e| CliError::RunFailed(e.to_string()))?;
    let map = scan
        .frame
        .height_map(TraceHalf::Forward)
        .map_err(|e| CliError::RunFailed(e.to_string()))?;
    // Display orientation: the top row first.
    let mut display = Vec::with_capacity(map.columns * map.rows);
    for row in (0..map.rows).rev() {
        display.extend_from_slice(&map.z_counts[row * map.columns..(row + 1) * map.columns]);
    }
    let k = job.plan.standard.nominal_nm_per_count;
    let side = |n: usize| map.pixel_step.value() * n as f64 * k;
    let channel = spm_formats::Channel::new(
        "Z",
        spm_formats::Direction::Forward,
        "counts",
        map.columns,
        map.rows,
        display,
    )
    .map_err(|e| CliError::RunFailed(e.to_string()))?
    .with_size_nm(side(map.columns), side(map.rows));
    let values = [
        map.origin.x.value().to_string(),
        map.origin.y.value().to_string(),
        map.pixel_step.value().to_string(),
        (dwell * f64::from(args.pixels)).to_string(),
        k.to_string(),
    ];
    let bytes = spm_formats::encode_gsf(
        &channel,
        &[
            (KEY_ORIGIN_X, values[0].as_str()),
            (KEY_ORIGIN_Y, values[1].as_str()),
            (KEY_STEP, values[2].as_str()),
            (
                KEY_SCAN_PATH,
                if args.counter { "counter" } else { "direct" },
            ),
            (KEY_SCANNER, job.plan.scanner_id.as_str()),
            (KEY_CONVENTION, "centred_signed"),
            (KEY_LINE_TIME, values[3].as_str()),
            (KEY_NOMINAL, values[4].as_str()),
        ],
    )
    .map_err(|e| CliError::RunFailed(e.to_string()))?;
    let history = ScanHistory {
        format: HISTORY_FORMAT.to_owned(),
        version: HISTORY_VERSION,
        scanner_id: job.plan.scanner_id.clone(),
        events: scan.events,
        forward_pixel_times_s: scan.frame.forward.time_s.clone(),
        backward_pixel_times_s: scan.frame.backward.as_ref().map(|b| b.time_s.clone()),
    };
    let json = history
        .to_json()
        .map_err(|e| CliError::RunFailed(e.to_string()))?;
    crate::files::write_atomically(&sidecar, json.as_bytes())?;
    crate::files::write_atomically(&args.out, &bytes)?;
    crate::outln!(
        "{} ({}×{} px, {:.4} nm per pixel at the nominal {k} nm/count) and its command history {} \
         ({} commands)",
        args.out.display(),
        map.columns,
        map.rows,
        map.pixel_step.value() * k,
        sidecar.display(),
        history.events.len()
    );
    Ok(())
}
