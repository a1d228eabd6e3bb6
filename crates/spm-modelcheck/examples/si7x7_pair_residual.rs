//! What the Si(111)-7×7 drift pair's position-dependent residual is (issue 29 item 5): the
//! pair `Si_7x7_028.sxm` + `Si_7x7_032.sxm` (50 nm, the same area 8 min 46 s apart) is
//! diagnosed as `cargo run -p spm-modelcheck --example measured si7x7-drift-pair` does, and
//! the final model's per-cell residuals are taken apart:
//!
//! - the mean residual in N × N position cells of each frame and direction, with the noise
//!   each cell mean carries (the residuals' scatter within the cell over √n);
//! - the part the two frames share at the same commanded place and the part where they
//!   differ (a static cause — the sample, the scanner's field, the localiser — is shared;
//!   creep, drift changes and the tip differ between frames 8 min apart);
//! - the same for forward against backward within a frame (the same place seconds apart);
//! - how much of the shared part a smooth field of the commanded position (a polynomial of
//!   degree 3 … 7, as a scanner field beyond the model's would be) explains.
//!
//! `cargo run --release -p spm-modelcheck --example si7x7_pair_residual [CELLS]`
//! (default 4, as the diagnosis's spatial check). Prints; writes nothing.
#![allow(clippy::unwrap_used)]

use spm_modelcheck::{
    Diagnosis, ExtractOptions, ImageInput, LatticeSpec, LineDirection, Options, ResidualPoint,
    diagnose,
};

/// Per cell and axis: mean residual (pm), its standard error (pm) and the points.
type CellMap = Vec<Option<([f64; 2], [f64; 2], usize)>>;

fn cell_map(points: &[&ResidualPoint], half: [f64; 2], cells: usize) -> CellMap {
    let mut groups: Vec<Vec<[f64; 2]>> = vec![Vec::new(); cells * cells];
    for p in points {
        let u = ((p.x_nm / half[0] + 1.0) * 0.5 * cells as f64).floor();
        let v = ((p.y_nm / half[1] + 1.0) * 0.5 * cells as f64).floor();
        if u < 0.0 || v < 0.0 || u >= cells as f64 || v >= cells as f64 {
            continue;
        }
        groups[v as usize * cells + u as usize].push(p.final_pm);
    }
    groups
        .iter()
        .map(|g| {
            if g.len() < 4 {
                return None;
            }
            let n = g.len() as f64;
            let mean = [0, 1].map(|a| g.iter().map(|r| r[a]).sum::<f64>() / n);
            let se = [0, 1].map(|a| {
                let var = g.iter().map(|r| (r[a] - mean[a]).powi(2)).sum::<f64>() / (n - 1.0);
                (var / n).sqrt()
            });
            Some((mean, se, g.len()))
        })
        .collect()
}

/// Per axis (x, y): RMS over cells of (a + b)/2 and (a − b)/2 beyond the cell means' noise,
/// pm, and the noise's own RMS.
fn shared_and_differing(a: &CellMap, b: &CellMap) -> [[f64; 3]; 2] {
    let mut out = [[0.0; 3]; 2];
    for (axis, o) in out.iter_mut().enumerate() {
        let (mut sum, mut diff, mut noise, mut n) = (0.0, 0.0, 0.0, 0.0_f64);
        for (x, y) in a.iter().zip(b) {
            let (Some(x), Some(y)) = (x, y) else {
                continue;
            };
            let var = 0.25 * (x.1[axis].powi(2) + y.1[axis].powi(2));
            sum += (0.5 * (x.0[axis] + y.0[axis])).powi(2) - var;
            diff += (0.5 * (x.0[axis] - y.0[axis])).powi(2) - var;
            noise += var;
            n += 1.0;
        }
        let rms = |s: f64| (s / n.max(1.0)).max(0.0).sqrt();
        *o = [rms(sum), rms(diff), rms(noise)];
    }
    out
}

/// The half-difference (a − b)/2 of two cell maps, per axis: the RMS over cells of its
/// column means (a function of x alone) and of its row means (of y alone), pm.
fn along(a: &CellMap, b: &CellMap, cells: usize) -> [[f64; 2]; 2] {
    let mut out = [[0.0; 2]; 2];
    for (axis, o) in out.iter_mut().enumerate() {
        let d = |u: usize, v: usize| match (&a[v * cells + u], &b[v * cells + u]) {
            (Some(x), Some(y)) => Some(0.5 * (x.0[axis] - y.0[axis])),
            _ => None,
        };
        let mean = |vals: Vec<f64>| vals.iter().sum::<f64>() / vals.len().max(1) as f64;
        let cols: Vec<f64> = (0..cells)
            .map(|u| mean((0..cells).filter_map(|v| d(u, v)).collect()))
            .collect();
        let rows: Vec<f64> = (0..cells)
            .map(|v| mean((0..cells).filter_map(|u| d(u, v)).collect()))
            .collect();
        let rms = |v: &[f64]| {
            let m = mean(v.to_vec());
            (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len().max(1) as f64).sqrt()
        };
        *o = [rms(&cols), rms(&rows)];
    }
    out
}

/// The RMS (pm, both axes) of what a polynomial of the commanded position of `degree`
/// explains of the residuals, fitted per axis over `points`, and its share of their variance.
fn smooth_part(points: &[&ResidualPoint], degree: u32) -> (f64, f64) {
    let terms: Vec<(u32, u32)> = spm_regression::term_powers(degree).collect();
    let scale = points
        .iter()
        .map(|p| p.x_nm.abs().max(p.y_nm.abs()))
        .fold(1e-9, f64::max);
    let rows: Vec<Vec<f64>> = points
        .iter()
        .map(|p| {
            let (x, y) = (p.x_nm / scale, p.y_nm / scale);
            terms
                .iter()
                .map(|&(i, j)| x.powi(i as i32) * y.powi(j as i32))
                .collect()
        })
        .collect();
    let columns: Vec<Vec<f64>> = (0..terms.len())
        .map(|k| rows.iter().map(|r| r[k]).collect())
        .collect();
    let included = vec![true; points.len()];
    let (mut total, mut left) = (0.0, 0.0);
    for axis in 0..2 {
        let target: Vec<f64> = points.iter().map(|p| p.final_pm[axis]).collect();
        let mean = target.iter().sum::<f64>() / target.len() as f64;
        total += target.iter().map(|t| (t - mean).powi(2)).sum::<f64>();
        left += spm_regression::minimum_norm_least_squares(&columns, &target, &included)
            .map_or(f64::NAN, |f| f.rss);
    }
    (
        ((total - left) / (2.0 * points.len() as f64))
            .max(0.0)
            .sqrt(),
        1.0 - left / total,
    )
}

fn rms_of(map: &CellMap) -> f64 {
    let (mut s, mut n) = (0.0, 0.0_f64);
    for (m, se, _) in map.iter().flatten() {
        for axis in 0..2 {
            s += m[axis].powi(2) - se[axis].powi(2);
            n += 1.0;
        }
    }
    (s / n.max(1.0)).max(0.0).sqrt()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let cells: usize = std::env::args()
        .nth(1)
        .map_or(Ok(4), |a| a.parse())
        .unwrap_or(4);
    let inputs: Vec<ImageInput> = ["Si_7x7_028.sxm", "Si_7x7_032.sxm"]
        .iter()
        .map(|f| ImageInput {
            path: spmcal_tests::measured_file(&format!("si7x7-nanonis/{f}")),
            start_time_s: None,
        })
        .collect();
    let d: Diagnosis = diagnose(
        &inputs,
        &LatticeSpec::parse("si7x7")?,
        &Options::default(),
        &ExtractOptions::default(),
    )?;
    println!(
        "pair: {} features used, final RMS {:.1} pm, σloc {:.1} pm, spatial {:.1} pm (z {:.1}); findings {:?}",
        d.features_used,
        d.final_report.rms_pm,
        d.localisation_sigma_pm,
        d.residual_structure.spatial_rms_pm,
        d.residual_structure.spatial_z,
        d.effects_found()
    );
    let used: Vec<&ResidualPoint> = d.residuals.iter().filter(|p| p.used).collect();
    let pick = |frame: usize, dir: Option<LineDirection>| -> Vec<&ResidualPoint> {
        used.iter()
            .copied()
            .filter(|p| p.frame == frame && dir.is_none_or(|d| p.direction == d))
            .collect()
    };
    let half = |frame: usize| d.frame_half_nm.get(frame).copied().unwrap_or([25.0, 25.0]);
    println!("cells {cells} × {cells}, RMS over cells and axes beyond the cell means' noise, pm:");
    let mut maps = Vec::new();
    for frame in 0..2 {
        for dir in [LineDirection::Forward, LineDirection::Backward] {
            let m = cell_map(&pick(frame, Some(dir)), half(frame), cells);
            println!("  frame {frame} {dir:?}: cell means {:.1} pm", rms_of(&m));
            maps.push(m);
        }
    }
    let show = |what: &str, r: [[f64; 3]; 2]| {
        println!(
            "  {what}: x shared {:.1}, differing {:.1} (noise {:.1}); y shared {:.1}, differing {:.1} (noise {:.1})",
            r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2]
        );
    };
    show(
        "028 forward vs backward",
        shared_and_differing(&maps[0], &maps[1]),
    );
    show(
        "032 forward vs backward",
        shared_and_differing(&maps[2], &maps[3]),
    );
    show(
        "forward 028 vs 032",
        shared_and_differing(&maps[0], &maps[2]),
    );
    show(
        "backward 028 vs 032",
        shared_and_differing(&maps[1], &maps[3]),
    );
    for (frame, (f, b)) in [(0, (&maps[0], &maps[1])), (1, (&maps[2], &maps[3]))] {
        let a = along(f, b, cells);
        println!(
            "  frame {frame} (forward − backward)/2 by column (x) / by row (y): x axis {:.1} / {:.1} pm, y axis {:.1} / {:.1} pm",
            a[0][0], a[0][1], a[1][0], a[1][1]
        );
    }
    for (frame, (f, b)) in [(0, (&maps[0], &maps[1])), (1, (&maps[2], &maps[3]))] {
        let profile: Vec<String> = (0..cells)
            .map(|u| {
                let v: Vec<f64> = (0..cells)
                    .filter_map(|v| match (&f[v * cells + u], &b[v * cells + u]) {
                        (Some(x), Some(y)) => Some(0.5 * (x.0[1] - y.0[1])),
                        _ => None,
                    })
                    .collect();
                format!("{:+.1}", v.iter().sum::<f64>() / v.len().max(1) as f64)
            })
            .collect();
        println!(
            "  frame {frame} y residual (forward − backward)/2 by column, −x → +x: {} pm",
            profile.join(" ")
        );
    }
    let whole: Vec<CellMap> = (0..2)
        .map(|f| cell_map(&pick(f, None), half(f), cells))
        .collect();
    show(
        "028 vs 032, directions pooled (8 min 46 s apart)",
        shared_and_differing(&whole[0], &whole[1]),
    );
    // The y residual against ½·s·x (s = +1 forward, −1 backward), with a constant per
    // frame and direction: the slope a slow axis ramping through each line would leave.
    let groups: Vec<(usize, LineDirection)> = (0..2)
        .flat_map(|f| [(f, LineDirection::Forward), (f, LineDirection::Backward)])
        .collect();
    let mut columns: Vec<Vec<f64>> = vec![
        used.iter()
            .map(|p| {
                let s = if p.direction == LineDirection::Forward {
                    1.0
                } else {
                    -1.0
                };
                0.5 * s * p.x_nm
            })
            .collect(),
    ];
    for g in &groups {
        columns.push(
            used.iter()
                .map(|p| f64::from(u8::from((p.frame, p.direction) == *g)))
                .collect(),
        );
    }
    let target: Vec<f64> = used.iter().map(|p| p.final_pm[1]).collect();
    let fit =
        spm_regression::minimum_norm_least_squares(&columns, &target, &vec![true; used.len()])?;
    // A slow axis that ramps through every line (one line pitch p per trace + retrace)
    // moves the tip p/2 in y while a line's 2W are traversed, seen scaled by scale_y:
    // k = p·scale_y/(2W).
    let lines = d.residuals.iter().map(|p| p.line + 1).max().unwrap_or(1) as f64;
    let w = half(0)[0];
    let scale_y = d
        .baseline
        .parameters
        .get("scale_y")
        .map_or(f64::NAN, |p| p.value);
    let pitch = 2.0 * half(0)[1] / lines;
    println!(
        "  y residual = k·½·s·x + a constant per frame and direction: k = {:.3e} ± {:.1e}; a continuous slow-axis ramp (pitch {:.4} nm over {lines} lines, scale_y {scale_y:.4}, W {w:.2} nm) gives {:.3e}; the RSS falls {:.0} → {:.0} pm²",
        fit.coefficients[0] * 1e-3,
        fit.covariance[0][0].sqrt() * 1e-3,
        pitch,
        pitch * scale_y / (2.0 * w),
        target.iter().map(|t| t * t).sum::<f64>(),
        fit.rss
    );
    for degree in [3, 4, 5, 6, 7] {
        let (rms, share) = smooth_part(&used, degree);
        println!(
            "  a degree-{degree} field of the commanded place explains {rms:.1} pm RMS ({:.1} % of the final residual's variance)",
            100.0 * share
        );
    }
    Ok(())
}
