//! `spmcal scan`: one image through a job's backend (sim, nanonis), written with what a
//! controller records and the command history the backend was driven with
//! (`IMAGE.history.json`), so that `spmcal correct` applies the full dynamic correction to it.

use std::path::PathBuf;

use spm_apply::history::{HISTORY_FORMAT, HISTORY_VERSION, ScanHistory, sidecar_of};
use spm_apply::{
    KEY_CONVENTION, KEY_LINE_TIME, KEY_NOMINAL, KEY_ORIGIN_X, KEY_ORIGIN_Y, KEY_SCAN_PATH,
    KEY_SCANNER, KEY_STEP,
};
use spm_formats::{DateTime, ScanDir, SxmChannel, SxmScan, encode_sxm};
use spm_hal::{CountPoint, Counts, HeightMap, ScanDirection, ScanRequest, Seconds, TraceHalf};
use spmcal::job::Job;

use crate::error::CliError;

/// Take one image through a job's backend and keep the command history it was taken with
/// (IMAGE.sxm or IMAGE.gsf, and IMAGE.….history.json): `spmcal correct` then corrects the
/// creep of the approach move and the raster's dynamics with the calibration's dynamics.
#[derive(Debug, clap::Args)]
pub struct ScanArgs {
    /// The job file whose backend (and plan: scanner id, nominal sensitivity, dwell) is used.
    #[arg(long, value_name = "FILE")]
    pub config: PathBuf,
    /// The image to write: .sxm (Nanonis: both halves, +x lines as `forward`, the raster's
    /// line time, direction and date, spmcal's raster in counts as extra tags) or .gsf (the
    /// trace only); the history goes to OUT.history.json beside it.
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
    let sxm = match args
        .out
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .as_deref()
    {
        Some("sxm") => true,
        Some("gsf") => false,
        _ => {
            return Err(CliError::BadInput(format!(
                "--out {}: spmcal scan writes a Nanonis .sxm or a Gwyddion .gsf image (and \
                 IMAGE.history.json beside it)",
                args.out.display()
            )));
        }
    };
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
    let mut request = ScanRequest::centred_square(
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
    request.record_backward = sxm;
    let scan = spmcal::run::scan_recorded(&job, &request, args.settle_s)
        .map_err(|e| CliError::RunFailed(e.to_string()))?;
    let k = job.plan.standard.nominal_nm_per_count;
    let (bytes, map) = if sxm {
        encode_sxm_image(&scan, &job, args, dwell)?
    } else {
        encode_gsf_image(&scan, &job, args, dwell)?
    };
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

/// spmcal's raster in counts, as header fields `correct` reads (`spm_apply::KEY_*`).
fn raster_fields(
    map: &HeightMap,
    job: &Job,
    args: &ScanArgs,
    dwell_s: f64,
) -> Vec<(&'static str, String)> {
    vec![
        (KEY_ORIGIN_X, map.origin.x.value().to_string()),
        (KEY_ORIGIN_Y, map.origin.y.value().to_string()),
        (KEY_STEP, map.pixel_step.value().to_string()),
        (
            KEY_SCAN_PATH,
            if args.counter { "counter" } else { "direct" }.to_owned(),
        ),
        (KEY_SCANNER, job.plan.scanner_id.clone()),
        (KEY_CONVENTION, "centred_signed".to_owned()),
        (KEY_LINE_TIME, (dwell_s * map.columns as f64).to_string()),
        (
            KEY_NOMINAL,
            job.plan.standard.nominal_nm_per_count.to_string(),
        ),
    ]
}

/// The trace as a one-channel .gsf (display orientation, top row first), labelled by the
/// direction of its lines: `Forward` for +x (a direct raster), `Backward` for −x (a counter
/// raster), as Nanonis and Gwyddion do.
fn encode_gsf_image(
    scan: &spmcal::run::RecordedScan,
    job: &Job,
    args: &ScanArgs,
    dwell_s: f64,
) -> Result<(Vec<u8>, HeightMap), CliError> {
    let failed = |e: &dyn std::fmt::Display| CliError::RunFailed(e.to_string());
    let map = scan
        .frame
        .height_map(TraceHalf::Forward)
        .map_err(|e| failed(&e))?;
    let mut display = Vec::with_capacity(map.columns * map.rows);
    for row in (0..map.rows).rev() {
        display.extend_from_slice(&map.z_counts[row * map.columns..(row + 1) * map.columns]);
    }
    let k = job.plan.standard.nominal_nm_per_count;
    let side = |n: usize| map.pixel_step.value() * n as f64 * k;
    let direction = if args.counter {
        spm_formats::Direction::Backward
    } else {
        spm_formats::Direction::Forward
    };
    let channel =
        spm_formats::Channel::new("Z", direction, "counts", map.columns, map.rows, display)
            .map_err(|e| failed(&e))?
            .with_size_nm(side(map.columns), side(map.rows));
    let fields = raster_fields(&map, job, args, dwell_s);
    let pairs: Vec<(&str, &str)> = fields.iter().map(|(k, v)| (*k, v.as_str())).collect();
    let bytes = spm_formats::encode_gsf(&channel, &pairs).map_err(|e| failed(&e))?;
    Ok((bytes, map))
}

/// Both halves as a Nanonis .sxm: `forward` holds the +x lines and `backward` the −x lines,
/// each in acquisition order (a direct raster's trace is +x and steps up; a counter raster's
/// trace is −x and steps down, `SCAN_DIR down`). Z in counts (the backend's unit), the frame
/// centre and size at the plan's nominal sensitivity, the record date from the system clock
/// (UTC), spmcal's raster in counts as extra tags.
fn encode_sxm_image(
    scan: &spmcal::run::RecordedScan,
    job: &Job,
    args: &ScanArgs,
    dwell_s: f64,
) -> Result<(Vec<u8>, HeightMap), CliError> {
    let failed = |e: &dyn std::fmt::Display| CliError::RunFailed(e.to_string());
    let trace = scan
        .frame
        .height_map(TraceHalf::Forward)
        .map_err(|e| failed(&e))?;
    let retrace = scan
        .frame
        .height_map(TraceHalf::Backward)
        .map_err(|e| failed(&e))?;
    let (nx, ny) = (trace.columns, trace.rows);
    let scan_dir = if args.counter {
        ScanDir::Down
    } else {
        ScanDir::Up
    };
    // Acquisition order of one half whose lines run +x (`plus_x`) or −x.
    let acquisition = |map: &HeightMap, plus_x: bool| -> Vec<f64> {
        let mut out = Vec::with_capacity(nx * ny);
        for line in 0..ny {
            let row = match scan_dir {
                ScanDir::Up => line,
                ScanDir::Down => ny - 1 - line,
            };
            for k in 0..nx {
                let column = if plus_x { k } else { nx - 1 - k };
                out.push(map.z_counts[row * nx + column]);
            }
        }
        out
    };
    let (plus, minus) = if args.counter {
        (&retrace, &trace)
    } else {
        (&trace, &retrace)
    };
    let k = job.plan.standard.nominal_nm_per_count;
    let step_nm = trace.pixel_step.value() * k;
    let recorded = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .ok()
        .and_then(|d| i64::try_from(d.as_secs()).ok())
        .and_then(DateTime::from_unix_seconds)
        .or_else(|| DateTime::new(1970, 1, 1, 0, 0, 0))
        .ok_or_else(|| CliError::RunFailed("no record date".to_owned()))?;
    let sxm = SxmScan {
        pixels: [nx, ny],
        size_nm: [step_nm * nx as f64, step_nm * ny as f64],
        centre_nm: [args.x_counts * k, args.y_counts * k],
        angle_deg: 0.0,
        line_time_s: [dwell_s * nx as f64, dwell_s * nx as f64],
        scan_dir,
        recorded,
        bias_v: 0.0,
        comment: format!(
            "spmcal scan of scanner {} through the job {}",
            job.plan.scanner_id,
            args.config.display()
        ),
        channels: vec![SxmChannel {
            name: "Z".to_owned(),
            unit: "counts".to_owned(),
            forward: acquisition(plus, true),
            backward: Some(acquisition(minus, false)),
        }],
        extra_header: raster_fields(&trace, job, args, dwell_s)
            .into_iter()
            .map(|(k, v)| (k.to_owned(), v))
            .collect(),
    };
    let bytes = encode_sxm(&sxm, &args.out).map_err(|e| failed(&e))?;
    Ok((bytes, trace))
}
