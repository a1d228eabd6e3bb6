//! Peak memory and one-thread/all-threads time of corrected coordinates + bilinear resampling
//! of an N × N image (default 2048), in units of one image buffer (N² f64).
//!
//! Memory is the process's peak resident set (Linux `VmHWM` in `/proc/self/status`), reset
//! before each measurement by writing `5` to `/proc/self/clear_refs`; the input image is
//! built and touched before the reset, so "peak" = input + everything the call allocates and
//! touches. (The workspace forbids `unsafe`, so no counting global allocator; the resident
//! set counts pages touched, which for these buffers — every element is written — is their
//! size.) Times are wall clock, median of `--repeats` runs (default 5).
//!
//! ```text
//! cargo run --release -p spm-correction --example peak_memory -- [N] [--repeats R]
//! ```
#![allow(clippy::print_stdout)]

use std::time::Instant;

use spm_correction::{
    Integration, Interpolation, OutputGrid, Parallelism, ProductField, RasterGeometry,
    bench_support, correct_and_resample, correct_raster, resample,
};
use spm_hal::ScanDirection;

fn status_kib(key: &str) -> Option<u64> {
    let text = std::fs::read_to_string("/proc/self/status").ok()?;
    text.lines()
        .find(|l| l.starts_with(key))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
}

fn reset_peak() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

type Workload<'a> = Box<dyn Fn() -> Result<usize, spm_correction::CorrectionError> + 'a>;

fn two_step(
    field: &ProductField,
    geometry: &RasterGeometry,
    image: &[f64],
    parallelism: Parallelism,
) -> Result<usize, spm_correction::CorrectionError> {
    let map = correct_raster(
        field,
        geometry,
        ScanDirection::Direct,
        &Integration::default(),
        parallelism,
    )?;
    let grid = OutputGrid::covering(&map, None)?;
    let out = resample(image, &map, &grid, Interpolation::Bilinear, parallelism)?;
    Ok(std::hint::black_box(out).len())
}

fn fused(
    field: &ProductField,
    geometry: &RasterGeometry,
    image: &[f64],
    parallelism: Parallelism,
) -> Result<usize, spm_correction::CorrectionError> {
    let (_grid, out) = correct_and_resample(
        field,
        geometry,
        ScanDirection::Direct,
        &Integration::default(),
        image,
        None,
        Interpolation::Bilinear,
        parallelism,
    )?;
    Ok(std::hint::black_box(out).len())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut n = 2048usize;
    let mut repeats = 5usize;
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        if arg == "--repeats" {
            repeats = args.next().ok_or("--repeats needs a value")?.parse()?;
        } else {
            n = arg.parse()?;
        }
    }
    let field = bench_support::realistic_field()?;
    let geometry = bench_support::benchmark_geometry(n)?;
    let image = bench_support::benchmark_image(n);
    let buffer_kib = (n * n * std::mem::size_of::<f64>()) as f64 / 1024.0;
    let threads = rayon::current_num_threads();
    println!(
        "N = {n}: one image buffer = {:.1} MiB; rayon threads (all) = {threads}; repeats = {repeats}",
        buffer_kib / 1024.0
    );
    // Warm up rayon's pool and the allocator.
    fused(&field, &geometry, &image, Parallelism::AllCores)?;

    let cases: Vec<(&str, Workload<'_>)> = vec![
        (
            "correct_raster + resample, 1 thread",
            Box::new(|| two_step(&field, &geometry, &image, Parallelism::Sequential)),
        ),
        (
            "correct_raster + resample, all threads",
            Box::new(|| two_step(&field, &geometry, &image, Parallelism::AllCores)),
        ),
        (
            "fused correct_and_resample, 1 thread",
            Box::new(|| fused(&field, &geometry, &image, Parallelism::Sequential)),
        ),
        (
            "fused correct_and_resample, all threads",
            Box::new(|| fused(&field, &geometry, &image, Parallelism::AllCores)),
        ),
    ];
    let mut medians = Vec::new();
    println!(
        "| workload | peak RSS over the input (MiB) | peak, image buffers incl. input | output, image buffers | median time (ms) |"
    );
    println!("|---|---|---|---|---|");
    for (name, run) in &cases {
        if !reset_peak() {
            return Err("cannot reset the peak RSS (/proc/self/clear_refs)".into());
        }
        let base = status_kib("VmRSS:").ok_or("no VmRSS")?;
        let out_len = run()?;
        let peak = status_kib("VmHWM:").ok_or("no VmHWM")?;
        let extra_kib = peak.saturating_sub(base) as f64;
        let mut times = Vec::with_capacity(repeats);
        for _ in 0..repeats {
            let t0 = Instant::now();
            run()?;
            times.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        let median = times[times.len() / 2];
        medians.push(median);
        println!(
            "| {name} | {:.1} | {:.2} | {:.3} | {median:.1} |",
            extra_kib / 1024.0,
            1.0 + extra_kib / buffer_kib,
            out_len as f64 / (n * n) as f64
        );
    }
    println!(
        "one-thread / all-threads time: two-step {:.2}, fused {:.2}",
        medians[0] / medians[1],
        medians[2] / medians[3]
    );
    Ok(())
}
