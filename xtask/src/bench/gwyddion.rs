//! The peer side by side: Gwyddion's `gwy_data_field_sample_distorted`
//! (libprocess, one thread, bilinear and B-spline) against spm-correction on the
//! same image and the same coordinate map.
//!
//! The map is spm-correction's: the benchmark field's corrected raster, inverted
//! onto the output grid. Resampling the images "column index" and "row index"
//! bilinearly gives, for every output pixel, the exact fractional source pixel
//! that spm-correction interpolates at (bilinear interpolation reproduces linear
//! functions); shifted by ½ pixel (Gwyddion puts pixel centres at i + ½), that is
//! Gwyddion's coordinate array. The C harness (xtask/gwyddion/harness.c) reads
//! the image and the coordinates from raw float64 files, times the call and
//! writes its output; the outputs are compared pixel by pixel.

use super::Context;
use super::speed::{geometry, image};
use crate::XtaskError;
use serde::Serialize;
use spm_correction::{
    Integration, Interpolation, OutputGrid, Parallelism, correct_raster, resample,
};
use spm_hal::ScanDirection;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// One image size.
#[derive(Debug, Serialize)]
pub struct PeerRow {
    /// Source pixels per side.
    pub n: usize,
    /// Output pixels (columns × rows).
    pub output: [usize; 2],
    /// Gwyddion bilinear, best of the repeats, one thread, s.
    pub gwyddion_bilinear_s: f64,
    /// Gwyddion B-spline, one thread, s.
    pub gwyddion_bspline_s: f64,
    /// spm-correction resampling alone (given the corrected raster), bilinear, one thread, s.
    pub spmcal_resample_bilinear_s: f64,
    /// spm-correction resampling alone, Catmull-Rom cubic, one thread, s.
    pub spmcal_resample_cubic_s: f64,
    /// spm-correction correction + resampling (fused, bilinear), one thread, s.
    pub spmcal_fused_bilinear_s: f64,
    /// Gwyddion bilinear time ÷ spm-correction bilinear resampling time.
    pub gwyddion_over_spmcal_bilinear: f64,
    /// Gwyddion bilinear time ÷ spm-correction fused correction + resampling time.
    pub gwyddion_over_spmcal_fused: f64,
    /// Gwyddion B-spline time ÷ spm-correction Catmull-Rom time.
    pub gwyddion_bspline_over_spmcal_cubic: f64,
    /// Pixels compared (inside the data in both).
    pub compared: usize,
    /// max |Gwyddion bilinear − spm-correction bilinear| ÷ image range.
    pub bilinear_max_rel_diff: f64,
    /// max |Gwyddion B-spline − spm-correction Catmull-Rom| ÷ image range.
    pub cubic_max_rel_diff: f64,
    /// Outputs agree within interpolation tolerance (bilinear ≤ 1e-9, cubic ≤ 1e-3).
    pub agree: bool,
}

/// The Gwyddion section.
#[derive(Debug, Serialize)]
pub struct GwyddionResults {
    /// Gwyddion version (pkg-config or dpkg).
    pub version: String,
    /// How the harness was compiled.
    pub compile: String,
    /// Rows per image size.
    pub rows: Vec<PeerRow>,
}

fn sh(program: &str, args: &[&str]) -> Result<String, XtaskError> {
    let output = Command::new(program)
        .args(args)
        .env("DEBIAN_FRONTEND", "noninteractive")
        .output()
        .map_err(|e| XtaskError::step(format!("running {program}"), e))?;
    if output.status.success() {
        Ok(String::from_utf8_lossy(&output.stdout).trim().to_owned())
    } else {
        let err = String::from_utf8_lossy(&output.stderr);
        let tail: Vec<&str> = err.lines().rev().take(3).collect();
        Err(XtaskError::step(
            format!("{program} {}", args.join(" ")),
            format!("{} ({})", output.status, tail.join(" | ")),
        ))
    }
}

const HEADER: &str = "/usr/include/gwyddion/libprocess/correct.h";

fn ensure_installed() -> Result<(), XtaskError> {
    if Path::new(HEADER).exists() {
        return Ok(());
    }
    let uid = sh("id", &["-u"])?;
    if uid != "0" {
        return Err(XtaskError::step(
            "gwyddion",
            "libgwyddion20-dev is not installed and this is not root (apt-get needs root)",
        ));
    }
    println!("   gwyddion: apt-get install libgwyddion20-dev libglib2.0-dev");
    let install = [
        "install",
        "-y",
        "--no-install-recommends",
        "libgwyddion20-dev",
        "libglib2.0-dev",
    ];
    if sh("apt-get", &install).is_err() {
        sh("apt-get", &["update"])?;
        sh("apt-get", &install)?;
    }
    Ok(())
}

fn compile(root: &Path, dir: &Path) -> Result<(PathBuf, String), XtaskError> {
    let source = root.join("xtask/gwyddion/harness.c");
    let binary = dir.join("harness");
    let (Some(src), Some(bin)) = (source.to_str(), binary.to_str()) else {
        return Err(XtaskError::step("gwyddion", "non-UTF-8 path"));
    };
    // pkg-config gwyddion also requires GTK and friends' .pc files; the
    // libprocess harness needs only glib, so fall back to explicit flags.
    let flags = match sh("pkg-config", &["--cflags", "--libs", "gwyddion"]) {
        Ok(flags) => flags,
        Err(_) => format!(
            "-I/usr/include/gwyddion -I/usr/lib/x86_64-linux-gnu/gwyddion/include {} -lgwyprocess2 -lgwyddion2 -lm",
            sh(
                "pkg-config",
                &["--cflags", "--libs", "glib-2.0", "gobject-2.0"]
            )?
        ),
    };
    let mut args = vec!["-O2", "-o", bin, src];
    args.extend(flags.split_whitespace());
    sh("gcc", &args)?;
    let root_prefix = format!("{}/", root.display());
    let line = format!("gcc {}", args.join(" ")).replace(&root_prefix, "");
    Ok((binary.clone(), line))
}

fn write_f64(path: &Path, values: impl Iterator<Item = f64>) -> Result<(), XtaskError> {
    let bytes: Vec<u8> = values.flat_map(f64::to_le_bytes).collect();
    std::fs::write(path, bytes)
        .map_err(|e| XtaskError::step(format!("writing {}", path.display()), e))
}

fn read_f64(path: &Path) -> Result<Vec<f64>, XtaskError> {
    let bytes = std::fs::read(path)
        .map_err(|e| XtaskError::step(format!("reading {}", path.display()), e))?;
    Ok(bytes
        .chunks_exact(8)
        .map(|c| {
            let mut b = [0u8; 8];
            b.copy_from_slice(c);
            f64::from_le_bytes(b)
        })
        .collect())
}

fn best_of<T>(
    repeats: usize,
    mut f: impl FnMut() -> Result<T, XtaskError>,
) -> Result<(f64, T), XtaskError> {
    let mut best = f64::INFINITY;
    let mut last = None;
    for _ in 0..repeats.max(1) {
        let started = Instant::now();
        let value = f()?;
        best = best.min(started.elapsed().as_secs_f64());
        last = Some(value);
    }
    last.map(|v| (best, v))
        .ok_or_else(|| XtaskError::step("timing", "no repeat"))
}

fn max_rel_diff(a: &[f64], b: &[f64], range: f64) -> (usize, f64) {
    let mut n = 0;
    let mut worst: f64 = 0.0;
    for (x, y) in a.iter().zip(b) {
        if x.is_finite() && y.is_finite() {
            n += 1;
            worst = worst.max((x - y).abs() / range);
        }
    }
    (n, worst)
}

pub fn run(ctx: &Context) -> Result<GwyddionResults, XtaskError> {
    ensure_installed()?;
    let dir = ctx.scratch("gwyddion")?;
    let (harness, compile_line) = compile(&ctx.root, &dir)?;
    let version = sh("dpkg-query", &["-W", "-f=${Version}", "libgwyddion20-dev"])
        .unwrap_or_else(|_| "unknown".to_owned());
    let repeats = if ctx.quick { 1 } else { 3 };
    let sizes: &[usize] = if ctx.quick { &[2048] } else { &[2048, 4096] };
    let field = super::speed::field()?;
    let mut rows = Vec::new();
    for &n in sizes {
        let img = image(n);
        let geometry = geometry(n)?;
        let map = correct_raster(
            &field,
            &geometry,
            ScanDirection::Direct,
            &Integration::default(),
            Parallelism::Sequential,
        )
        .map_err(|e| XtaskError::step("correction", e))?;
        let grid = OutputGrid::covering(&map, None).map_err(|e| XtaskError::step("grid", e))?;
        let resample_with = |values: &[f64], interpolation| {
            resample(values, &map, &grid, interpolation, Parallelism::Sequential)
                .map_err(|e| XtaskError::step("resample", e))
        };
        let (ours_bilinear_s, ours) =
            best_of(repeats, || resample_with(&img, Interpolation::Bilinear))?;
        let (ours_cubic_s, ours_cubic) =
            best_of(repeats, || resample_with(&img, Interpolation::CatmullRom))?;
        let (fused_s, _) = best_of(repeats, || {
            super::speed::correct(n, &img, Interpolation::Bilinear, Parallelism::Sequential)
        })?;
        let columns: Vec<f64> = (0..n * n).map(|k| (k % n) as f64).collect();
        let lines: Vec<f64> = (0..n * n).map(|k| (k / n) as f64).collect();
        let cc = resample_with(&columns, Interpolation::Bilinear)?;
        let rr = resample_with(&lines, Interpolation::Bilinear)?;
        let image_path = dir.join(format!("image-{n}.f64"));
        let coords_path = dir.join(format!("coords-{n}.f64"));
        write_f64(&image_path, img.iter().copied())?;
        write_f64(
            &coords_path,
            cc.iter().zip(&rr).flat_map(|(c, r)| {
                if c.is_finite() && r.is_finite() {
                    [c + 0.5, r + 0.5]
                } else {
                    [-1e6, -1e6]
                }
            }),
        )?;
        let mut gwy = Vec::new();
        for kind in ["linear", "bspline"] {
            let out_path = dir.join(format!("gwyddion-{kind}-{n}.f64"));
            let args: Vec<String> = vec![
                image_path.display().to_string(),
                n.to_string(),
                n.to_string(),
                coords_path.display().to_string(),
                grid.columns.to_string(),
                grid.rows.to_string(),
                kind.to_owned(),
                repeats.to_string(),
                out_path.display().to_string(),
            ];
            let args: Vec<&str> = args.iter().map(String::as_str).collect();
            let harness_path = harness.display().to_string();
            let seconds: f64 = sh(&harness_path, &args)?
                .parse()
                .map_err(|e| XtaskError::step("harness output", e))?;
            let mut values = read_f64(&out_path)?;
            // Outside spm-correction's data the comparison is skipped.
            for (v, o) in values.iter_mut().zip(&ours) {
                if !o.is_finite() {
                    *v = f64::NAN;
                }
            }
            gwy.push((seconds, values));
        }
        let range = 4.0; // the image spans [−2, 2]
        let (compared, bilinear_diff) = max_rel_diff(&gwy[0].1, &ours, range);
        let (_, cubic_diff) = max_rel_diff(&gwy[1].1, &ours_cubic, range);
        let row = PeerRow {
            n,
            output: [grid.columns, grid.rows],
            gwyddion_bilinear_s: gwy[0].0,
            gwyddion_bspline_s: gwy[1].0,
            spmcal_resample_bilinear_s: ours_bilinear_s,
            spmcal_resample_cubic_s: ours_cubic_s,
            spmcal_fused_bilinear_s: fused_s,
            gwyddion_over_spmcal_bilinear: gwy[0].0 / ours_bilinear_s,
            gwyddion_over_spmcal_fused: gwy[0].0 / fused_s,
            gwyddion_bspline_over_spmcal_cubic: gwy[1].0 / ours_cubic_s,
            compared,
            bilinear_max_rel_diff: bilinear_diff,
            cubic_max_rel_diff: cubic_diff,
            agree: compared > 0 && bilinear_diff <= 1e-9 && cubic_diff <= 1e-3,
        };
        println!(
            "   gwyddion {n}²: bilinear {:.3} s vs spm-correction {:.3} s (×{:.2}), fused {:.3} s; B-spline {:.3} s vs Catmull-Rom {:.3} s; max diff {:.1e} / {:.1e}",
            row.gwyddion_bilinear_s,
            row.spmcal_resample_bilinear_s,
            row.gwyddion_over_spmcal_bilinear,
            row.spmcal_fused_bilinear_s,
            row.gwyddion_bspline_s,
            row.spmcal_resample_cubic_s,
            row.bilinear_max_rel_diff,
            row.cubic_max_rel_diff
        );
        rows.push(row);
    }
    Ok(GwyddionResults {
        version,
        compile: compile_line,
        rows,
    })
}
