//! Ideal config: a HOPG scan shows a triangular lattice with a = 0.2461 nm
//! (within 0.1 %) and 60° (within 0.1°). Measured from the image alone:
//! local maxima refined by a 5×5 least-squares paraboloid, then a
//! least-squares fit of a 2-D lattice (origin + n·a₁ + m·a₂) to all atoms;
//! counts are converted to nm with the ideal config's nominal 0.02 nm/count.
#![allow(clippy::unwrap_used, clippy::needless_range_loop)]

use spm_hal::{CountPoint, Counts, Microscope, ScanRequest, Seconds, TraceHalf};
use spm_sim::{HopgConfig, SimConfig, Simulator, SurfaceConfig};

/// Sub-pixel maxima (column, row) of a row-major image, away from the border.
fn refined_maxima(z: &[f64], nx: usize, ny: usize) -> Vec<(f64, f64)> {
    let at = |c: usize, r: usize| z[r * nx + c];
    let mut out = Vec::new();
    for r in 3..ny - 3 {
        for c in 3..nx - 3 {
            let v = at(c, r);
            let mut is_max = true;
            for dr in -2i64..=2 {
                for dc in -2i64..=2 {
                    if (dr, dc) != (0, 0)
                        && at((c as i64 + dc) as usize, (r as i64 + dr) as usize) >= v
                    {
                        is_max = false;
                    }
                }
            }
            if !is_max {
                continue;
            }
            // Least squares z = a + b x + c y + d x² + e xy + f y² over 5×5.
            let mut ata = [[0.0f64; 6]; 6];
            let mut atb = [0.0f64; 6];
            for dr in -2i64..=2 {
                for dc in -2i64..=2 {
                    let (x, y) = (dc as f64, dr as f64);
                    let row = [1.0, x, y, x * x, x * y, y * y];
                    let val = at((c as i64 + dc) as usize, (r as i64 + dr) as usize);
                    for i in 0..6 {
                        atb[i] += row[i] * val;
                        for j in 0..6 {
                            ata[i][j] += row[i] * row[j];
                        }
                    }
                }
            }
            let p = solve(ata, atb);
            let (b, cc, d, e, f) = (p[1], p[2], p[3], p[4], p[5]);
            let det = 4.0 * d * f - e * e;
            let dx = (-2.0 * f * b + e * cc) / det;
            let dy = (-2.0 * d * cc + e * b) / det;
            if dx.abs() < 1.0 && dy.abs() < 1.0 {
                out.push((c as f64 + dx, r as f64 + dy));
            }
        }
    }
    out
}

fn solve<const N: usize>(mut a: [[f64; N]; N], mut b: [f64; N]) -> [f64; N] {
    for k in 0..N {
        let p = (k..N)
            .max_by(|&i, &j| a[i][k].abs().total_cmp(&a[j][k].abs()))
            .unwrap();
        a.swap(k, p);
        b.swap(k, p);
        for i in k + 1..N {
            let f = a[i][k] / a[k][k];
            for j in k..N {
                a[i][j] -= f * a[k][j];
            }
            b[i] -= f * b[k];
        }
    }
    let mut x = [0.0; N];
    for k in (0..N).rev() {
        let s: f64 = (k + 1..N).map(|j| a[k][j] * x[j]).sum();
        x[k] = (b[k] - s) / a[k][k];
    }
    x
}

/// Least-squares lattice fit: returns (a₁, a₂) in the pixel units of `points`.
fn fit_lattice(points: &[(f64, f64)]) -> ((f64, f64), (f64, f64)) {
    let (cx, cy) = points
        .iter()
        .fold((0.0, 0.0), |s, p| (s.0 + p.0, s.1 + p.1));
    let (cx, cy) = (cx / points.len() as f64, cy / points.len() as f64);
    let origin = *points
        .iter()
        .min_by(|a, b| {
            let da = (a.0 - cx).hypot(a.1 - cy);
            let db = (b.0 - cx).hypot(b.1 - cy);
            da.total_cmp(&db)
        })
        .unwrap();
    let mut neighbours: Vec<(f64, f64)> = points
        .iter()
        .map(|p| (p.0 - origin.0, p.1 - origin.1))
        .filter(|d| d.0.hypot(d.1) > 1.0)
        .collect();
    neighbours.sort_by(|a, b| a.0.hypot(a.1).total_cmp(&b.0.hypot(b.1)));
    let a1 = neighbours[0];
    let a2 = *neighbours
        .iter()
        .find(|d| {
            let cos = (d.0 * a1.0 + d.1 * a1.1) / (d.0.hypot(d.1) * a1.0.hypot(a1.1));
            (cos - 0.5).abs() < 0.2
        })
        .unwrap();
    // Indices by rounding, then linear least squares for origin, a1, a2 (per coordinate).
    let det = a1.0 * a2.1 - a1.1 * a2.0;
    let mut ata = [[0.0f64; 3]; 3];
    let mut atx = [0.0f64; 3];
    let mut aty = [0.0f64; 3];
    for p in points {
        let (dx, dy) = (p.0 - origin.0, p.1 - origin.1);
        let n = ((a2.1 * dx - a2.0 * dy) / det).round();
        let m = ((-a1.1 * dx + a1.0 * dy) / det).round();
        let row = [1.0, n, m];
        for i in 0..3 {
            atx[i] += row[i] * p.0;
            aty[i] += row[i] * p.1;
            for j in 0..3 {
                ata[i][j] += row[i] * row[j];
            }
        }
    }
    let sx = solve(ata, atx);
    let sy = solve(ata, aty);
    ((sx[1], sy[1]), (sx[2], sy[2]))
}

fn check_lattice(rotation_deg: f64) {
    let mut config = SimConfig::ideal();
    if let SurfaceConfig::Hopg(HopgConfig {
        rotation_deg: r, ..
    }) = &mut config.surface
    {
        *r = rotation_deg;
    }
    let mut sim = Simulator::new(config).unwrap();
    let n = 128;
    let request = ScanRequest::centred_square(
        CountPoint::from_counts(300.0, -200.0),
        Counts(1.0),
        n,
        Seconds(1e-4),
    );
    let frame = sim.scan(&request).unwrap();
    let map = frame.height_map(TraceHalf::Forward).unwrap();
    let maxima = refined_maxima(&map.z_counts, map.columns, map.rows);
    assert!(maxima.len() > 60, "{} atoms", maxima.len());
    let (a1, a2) = fit_lattice(&maxima);
    let nm_per_count = 0.02;
    let l1 = a1.0.hypot(a1.1) * nm_per_count;
    let l2 = a2.0.hypot(a2.1) * nm_per_count;
    let angle = ((a1.0 * a2.0 + a1.1 * a2.1) / (a1.0.hypot(a1.1) * a2.0.hypot(a2.1)))
        .acos()
        .to_degrees();
    eprintln!(
        "rotation {rotation_deg}: a1 = {l1} nm, a2 = {l2} nm, angle {angle}°, {} atoms",
        maxima.len()
    );
    for l in [l1, l2] {
        assert!(
            (l / 0.2461 - 1.0).abs() < 1e-3,
            "a = {l} nm (rotation {rotation_deg}°)"
        );
    }
    assert!(
        (angle - 60.0).abs() < 0.1,
        "angle {angle}° (rotation {rotation_deg}°)"
    );
}

#[test]
fn ideal_hopg_scan_shows_the_triangular_lattice() {
    check_lattice(0.0);
    check_lattice(23.0);
}
