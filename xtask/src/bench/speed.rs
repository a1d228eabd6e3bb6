//! Speed: simulated calibration wall time per node (from the accuracy runs),
//! simulated pixels per second, correction + resampling of 2048² and 4096²
//! images (one thread and all threads, peak memory), and the CDB at 10⁶
//! records (insert, query, query + fit; --quick: 10⁵).

use super::Context;
use super::accuracy::AccuracyResults;
use crate::XtaskError;
use serde::Serialize;
use spm_cdb::bench_support::{SCANNER_ID as SCANNER, T0_UNIX_S as T0, synthetic_record};
use spm_cdb::{Cdb, CdbRead, OpenOptions, RecordFilter, RunInfo, RunStatus};
use spm_correction::{
    Integration, Interpolation, Parallelism, ProductField, RasterGeometry, bench_support,
    correct_and_resample,
};
use spm_hal::{CountPoint, Counts, Microscope, ScanDirection, ScanRequest, Seconds};
use spm_sim::{SimConfig, Simulator};
use spmcal::surfaces::{SurfaceFitOptions, fit_from_cdb};
use std::time::Instant;

/// Correction of one image size.
#[derive(Debug, Serialize)]
pub struct CorrectionSpeed {
    /// Pixels per side.
    pub n: usize,
    /// Best wall time on one thread, s.
    pub one_thread_s: f64,
    /// Pixels per second on one thread.
    pub one_thread_pixels_per_s: f64,
    /// Best CPU time of the calling thread on one thread (Linux
    /// /proc/thread-self/schedstat), s: the figure without the waits of a loaded machine.
    pub one_thread_cpu_s: Option<f64>,
    /// Best wall time on all threads, s.
    pub all_threads_s: f64,
    /// Pixels per second on all threads.
    pub all_threads_pixels_per_s: f64,
    /// Peak resident memory during one correction above the resident memory
    /// before it (VmHWM after resetting it through /proc/self/clear_refs), MiB.
    pub peak_extra_rss_mib: Option<f64>,
    /// The input image's size, MiB (n² f64).
    pub image_mib: f64,
}

/// The CDB figures.
#[derive(Debug, Serialize)]
pub struct CdbSpeed {
    /// Records inserted.
    pub records: u64,
    /// Bulk insert (one transaction, synchronous = full), s.
    pub insert_s: f64,
    /// Inserted records per second.
    pub insert_records_per_s: f64,
    /// Query of every record of the scanner, s.
    pub query_s: f64,
    /// Query + BIC fit of the regression surfaces (degree ≤ 3), s.
    pub query_and_fit_s: f64,
}

/// The speed section.
#[derive(Debug, Serialize)]
pub struct SpeedResults {
    /// Calibration wall time per node, ms, per accuracy config.
    pub calibration_ms_per_node: Vec<(String, f64)>,
    /// Simulated pixels per second (room-temperature tube, every effect on, one thread).
    pub simulated_pixels_per_s: f64,
    /// Correction + bilinear resampling (fused).
    pub correction: Vec<CorrectionSpeed>,
    /// The CDB.
    pub cdb: CdbSpeed,
    /// Threads of "all threads".
    pub threads: usize,
}

pub fn run(ctx: &Context, accuracy: Option<&AccuracyResults>) -> Result<SpeedResults, XtaskError> {
    let calibration_ms_per_node = accuracy
        .map(|a| {
            a.configs
                .iter()
                .map(|c| {
                    (
                        format!("{} ({})", c.config, c.plan),
                        c.wall_time_per_node_ms,
                    )
                })
                .collect()
        })
        .unwrap_or_default();
    let simulated_pixels_per_s = simulated_pixels(ctx.quick)?;
    println!(
        "   speed: simulator {:.2} M px/s",
        simulated_pixels_per_s / 1e6
    );
    let mut correction = Vec::new();
    for n in [2048usize, 4096] {
        let c = correction_speed(n, if ctx.quick { 1 } else { 3 })?;
        println!(
            "   speed: correction {n}²: {:.1} M px/s one thread, {:.1} M px/s all threads, peak +{:.0} MiB",
            c.one_thread_pixels_per_s / 1e6,
            c.all_threads_pixels_per_s / 1e6,
            c.peak_extra_rss_mib.unwrap_or(f64::NAN)
        );
        correction.push(c);
    }
    let cdb = cdb_speed(ctx, if ctx.quick { 100_000 } else { 1_000_000 })?;
    println!(
        "   speed: CDB {} records: insert {:.2} s, query {:.2} s, query + fit {:.2} s",
        cdb.records, cdb.insert_s, cdb.query_s, cdb.query_and_fit_s
    );
    Ok(SpeedResults {
        calibration_ms_per_node,
        simulated_pixels_per_s,
        correction,
        cdb,
        threads: std::thread::available_parallelism().map_or(1, usize::from),
    })
}

fn simulated_pixels(quick: bool) -> Result<f64, XtaskError> {
    let mut sim = Simulator::new(SimConfig::room_temperature_tube())
        .map_err(|e| XtaskError::step("simulator", e))?;
    let pixels = if quick { 256 } else { 512 };
    let request = ScanRequest::centred_square(
        CountPoint::from_counts(1000.0, -2000.0),
        Counts(1.0),
        pixels,
        Seconds(1e-4),
    );
    let started = Instant::now();
    let frame = sim
        .scan(&request)
        .map_err(|e| XtaskError::step("simulated scan", e))?;
    let seconds = started.elapsed().as_secs_f64();
    let halves = if frame.backward.is_some() { 2.0 } else { 1.0 };
    Ok(halves * f64::from(pixels) * f64::from(pixels) / seconds)
}

/// The workload of spm-correction's benchmarks (`spm_correction::bench_support`):
/// degree-3 surfaces over a 20000-count scanner, 1–5 % nonlinearity.
pub fn field() -> Result<ProductField, XtaskError> {
    bench_support::realistic_field().map_err(|e| XtaskError::step("correction field", e))
}

/// The smooth test image of spm-correction's benchmarks (values in [−2, 2]).
pub fn image(n: usize) -> Vec<f64> {
    bench_support::benchmark_image(n)
}

/// The raster of spm-correction's benchmarks: 16384 counts wide from (2000, 3000).
pub fn geometry(n: usize) -> Result<RasterGeometry, XtaskError> {
    bench_support::benchmark_geometry(n).map_err(|e| XtaskError::step("raster geometry", e))
}

/// Correction + resampling of the benchmark image with the benchmark field.
pub fn correct(
    n: usize,
    image: &[f64],
    interpolation: Interpolation,
    parallelism: Parallelism,
) -> Result<(spm_correction::OutputGrid, Vec<f64>), XtaskError> {
    correct_and_resample(
        &field()?,
        &geometry(n)?,
        ScanDirection::Direct,
        &Integration::default(),
        image,
        None,
        interpolation,
        parallelism,
    )
    .map_err(|e| XtaskError::step("correction", e))
}

/// CPU time of the calling thread, s (Linux /proc/thread-self/schedstat, first field, ns).
fn thread_cpu_s() -> Option<f64> {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()?
        .split_whitespace()
        .next()?
        .parse::<f64>()
        .ok()
        .map(|ns| ns * 1e-9)
}

fn status_kib(key: &str) -> Option<f64> {
    std::fs::read_to_string("/proc/self/status")
        .ok()?
        .lines()
        .find(|l| l.starts_with(key))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

fn correction_speed(n: usize, repeats: usize) -> Result<CorrectionSpeed, XtaskError> {
    let img = image(n);
    let pixels = (n * n) as f64;
    let mut best = [f64::INFINITY; 2];
    let mut best_cpu: Option<f64> = None;
    let mut peak = None;
    for (k, par) in [Parallelism::Sequential, Parallelism::AllCores]
        .into_iter()
        .enumerate()
    {
        for _ in 0..repeats {
            // Reset the peak RSS to the current RSS (Linux ≥ 4.0), then measure.
            let reset = std::fs::write("/proc/self/clear_refs", "5").is_ok();
            let before = status_kib("VmRSS:");
            let cpu0 = thread_cpu_s();
            let started = Instant::now();
            let out = correct(n, &img, Interpolation::Bilinear, par)?;
            best[k] = best[k].min(started.elapsed().as_secs_f64());
            if let (0, Some(a), Some(b)) = (k, cpu0, thread_cpu_s()) {
                best_cpu = Some(best_cpu.map_or(b - a, |c: f64| c.min(b - a)));
            }
            let hwm = status_kib("VmHWM:");
            drop(out);
            if let (true, 0, Some(b), Some(h)) = (reset, k, before, hwm) {
                peak = Some(((h - b) / 1024.0).max(0.0));
            }
        }
    }
    Ok(CorrectionSpeed {
        n,
        one_thread_s: best[0],
        one_thread_pixels_per_s: pixels / best[0],
        one_thread_cpu_s: best_cpu,
        all_threads_s: best[1],
        all_threads_pixels_per_s: pixels / best[1],
        peak_extra_rss_mib: peak,
        image_mib: pixels * 8.0 / (1024.0 * 1024.0),
    })
}

fn cdb_speed(ctx: &Context, records: u64) -> Result<CdbSpeed, XtaskError> {
    let dir = ctx.scratch("cdb")?;
    let path = dir.join("cdb.sqlite");
    let step = |what: &str| {
        let what = what.to_owned();
        move |e: spm_cdb::CdbError| XtaskError::step(format!("CDB {what}"), e)
    };
    let mut cdb = Cdb::open_with(&path, &OpenOptions::default()).map_err(step("open"))?;
    let runs = 10u64;
    let mut ids = Vec::new();
    for k in 0..runs {
        let r = RunInfo {
            run_id: format!("run-{k:02}"),
            scanner_id: SCANNER.into(),
            config: String::new(),
            started_unix_s: T0 + 86_400.0 * k as f64,
            finished_unix_s: None,
            status: RunStatus::Running,
        };
        cdb.create_run(&r).map_err(step("create run"))?;
        ids.push(r.run_id);
    }
    let per_run = records / runs;
    let started = Instant::now();
    let n = cdb
        .import_records((0..records).map(|i| synthetic_record(i, per_run, &ids)))
        .map_err(step("insert"))?;
    let insert_s = started.elapsed().as_secs_f64();
    let snapshot = cdb.snapshot().map_err(step("snapshot"))?;
    let started = Instant::now();
    let all = snapshot
        .records(&RecordFilter::scanner(SCANNER))
        .map_err(step("query"))?;
    let query_s = started.elapsed().as_secs_f64();
    if all.len() as u64 != n {
        return Err(XtaskError::step(
            "CDB query",
            format!("{} records read back of {n}", all.len()),
        ));
    }
    drop(all);
    let started = Instant::now();
    fit_from_cdb(
        &snapshot,
        Some(SCANNER),
        None,
        None,
        &SurfaceFitOptions::bic_up_to(3),
    )
    .map_err(|e| XtaskError::step("CDB fit", e))?;
    let query_and_fit_s = started.elapsed().as_secs_f64();
    Ok(CdbSpeed {
        records: n,
        insert_s,
        insert_records_per_s: n as f64 / insert_s,
        query_s,
        query_and_fit_s,
    })
}
