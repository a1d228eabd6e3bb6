//! The cell-template localiser against an independent truth: a synthetic Si(111)-7×7-like
//! surface (a corner hole and six adatoms of two heights per cell, white noise, missing
//! cells and adsorbates) rendered through a known distortion (scales, rotation, shear and
//! a quadratic nonlinearity), written as Nanonis `.sxm` and read back like an instrument
//! file. Every located cell is compared with the true corner hole it belongs to.
#![allow(clippy::unwrap_used)]

use rand::{Rng, SeedableRng};
use spm_formats::{DateTime, ScanDir, SxmChannel, SxmScan, encode_sxm};
use spm_modelcheck::{ExtractOptions, LatticeSpec, Localiser, SI7X7_A_NM, extract_features};

const N: usize = 256;
const SIZE_NM: f64 = 40.0;

/// Nominal image position (nm from the frame centre, y up) → surface position (nm).
fn distortion(u: [f64; 2]) -> [f64; 2] {
    let (c, s) = (12f64.to_radians().cos(), 12f64.to_radians().sin());
    let m = [[1.04 * c, -1.04 * s + 0.03], [0.96 * s, 0.96 * c]];
    let q = 0.03 / (0.5 * SIZE_NM); // quadratic nonlinearity along x, 3 % at the edge
    let x = u[0] + q * u[0] * u[0];
    [
        m[0][0] * x + m[0][1] * u[1] + 0.7,
        m[1][0] * x + m[1][1] * u[1] - 0.4,
    ]
}

/// The nominal position whose surface position is `s` (Newton on the distortion).
fn inverse(s: [f64; 2]) -> [f64; 2] {
    let mut u = [0.0, 0.0];
    for _ in 0..30 {
        let f = distortion(u);
        let h = 1e-6;
        let fx = distortion([u[0] + h, u[1]]);
        let fy = distortion([u[0], u[1] + h]);
        let j = [
            [(fx[0] - f[0]) / h, (fy[0] - f[0]) / h],
            [(fx[1] - f[1]) / h, (fy[1] - f[1]) / h],
        ];
        let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
        let r = [s[0] - f[0], s[1] - f[1]];
        u[0] += (j[1][1] * r[0] - j[0][1] * r[1]) / det;
        u[1] += (-j[1][0] * r[0] + j[0][0] * r[1]) / det;
    }
    u
}

struct Surface {
    a1: [f64; 2],
    a2: [f64; 2],
    missing: Vec<[i64; 2]>,
    adsorbates: Vec<([i64; 2], [f64; 2])>,
}

impl Surface {
    fn fractional(&self, s: [f64; 2]) -> [f64; 2] {
        let det = self.a1[0] * self.a2[1] - self.a2[0] * self.a1[1];
        [
            (self.a2[1] * s[0] - self.a2[0] * s[1]) / det,
            (-self.a1[1] * s[0] + self.a1[0] * s[1]) / det,
        ]
    }

    fn site(&self, ij: [i64; 2]) -> [f64; 2] {
        let (i, j) = (ij[0] as f64, ij[1] as f64);
        [
            i * self.a1[0] + j * self.a2[0],
            i * self.a1[1] + j * self.a2[1],
        ]
    }

    /// Height (arbitrary units) at surface position `s`.
    fn height(&self, s: [f64; 2]) -> f64 {
        let f = self.fractional(s);
        let home = [f[0].round() as i64, f[1].round() as i64];
        // The nearest site's cell (for defects): the corner hole nearest in real space.
        let mut nearest = home;
        let mut best = f64::INFINITY;
        for di in -1..=1 {
            for dj in -1..=1 {
                let ij = [f[0].floor() as i64 + di, f[1].floor() as i64 + dj];
                let p = self.site(ij);
                let d = (p[0] - s[0]).hypot(p[1] - s[1]);
                if d < best {
                    (best, nearest) = (d, ij);
                }
            }
        }
        let _ = home;
        if self.missing.contains(&nearest) && best < 0.6 * SI7X7_A_NM {
            return 0.2;
        }
        let mut h = 0.0;
        let t = 0.13;
        let features: [([f64; 2], f64, f64); 7] = [
            ([0.0, 0.0], -1.0, 0.25),
            ([1.0 / 3.0 + t, 1.0 / 3.0], 0.6, 0.2),
            ([1.0 / 3.0, 1.0 / 3.0 + t], 0.6, 0.2),
            ([1.0 / 3.0 - t, 1.0 / 3.0 - t], 0.6, 0.2),
            ([2.0 / 3.0 - t, 2.0 / 3.0], 0.45, 0.2),
            ([2.0 / 3.0, 2.0 / 3.0 - t], 0.45, 0.2),
            ([2.0 / 3.0 + t, 2.0 / 3.0 + t], 0.45, 0.2),
        ];
        for (fp, amp, sigma) in features {
            let du = (f[0] - fp[0]) - (f[0] - fp[0]).round();
            let dv = (f[1] - fp[1]) - (f[1] - fp[1]).round();
            let d = [
                du * self.a1[0] + dv * self.a2[0],
                du * self.a1[1] + dv * self.a2[1],
            ];
            h += amp * (-(d[0] * d[0] + d[1] * d[1]) / (2.0 * sigma * sigma)).exp();
        }
        for (_, centre) in &self.adsorbates {
            let d = (s[0] - centre[0]).hypot(s[1] - centre[1]);
            h += 2.0 * (-(d * d) / (2.0 * 0.5f64.powi(2))).exp();
        }
        h
    }
}

#[test]
fn every_located_cell_sits_on_its_true_corner_hole() {
    let a = SI7X7_A_NM;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(18);
    let mut surface = Surface {
        a1: [a, 0.0],
        a2: [0.5 * a, 0.75f64.sqrt() * a],
        missing: Vec::new(),
        adsorbates: Vec::new(),
    };
    // Sites whose corner hole is in the field (nominal), and defects among them.
    let px = SIZE_NM / N as f64;
    let half = 0.5 * SIZE_NM;
    let mut sites = Vec::new();
    for i in -20i64..=20 {
        for j in -20i64..=20 {
            let u = inverse(surface.site([i, j]));
            if u[0].abs() < half && u[1].abs() < half {
                sites.push(([i, j], u));
            }
        }
    }
    for (ij, _) in &sites {
        let r: f64 = rng.random();
        if r < 0.06 {
            surface.missing.push(*ij);
        } else if r < 0.10 {
            let p = surface.site(*ij);
            let off = [rng.random::<f64>() - 0.5, rng.random::<f64>() - 0.5];
            surface
                .adsorbates
                .push((*ij, [p[0] + 0.4 * a * off[0], p[1] + 0.4 * a * off[1]]));
        }
    }
    // Render (display rows: row 0 at the top; scan down: acquisition order = display).
    let scale_m = 50e-12;
    let mut data = vec![0.0; N * N];
    for r in 0..N {
        for c in 0..N {
            let u = [
                (c as f64 - 0.5 * (N as f64 - 1.0)) * px,
                (0.5 * (N as f64 - 1.0) - r as f64) * px,
            ];
            let noise: f64 = rng.random::<f64>() + rng.random::<f64>() + rng.random::<f64>() - 1.5;
            data[r * N + c] = scale_m * (surface.height(distortion(u)) + 0.15 * noise);
        }
    }
    let scan = SxmScan {
        pixels: [N, N],
        size_nm: [SIZE_NM, SIZE_NM],
        centre_nm: [0.0, 0.0],
        angle_deg: 0.0,
        line_time_s: [0.1, 0.1],
        scan_dir: ScanDir::Down,
        recorded: DateTime::new(2024, 3, 5, 12, 0, 0).unwrap(),
        bias_v: 1.5,
        comment: "synthetic 7x7-like cells".into(),
        extra_header: Vec::new(),
        channels: vec![SxmChannel {
            name: "Z".into(),
            unit: "m".into(),
            forward: data,
            backward: None,
        }],
    };
    let dir = std::env::temp_dir().join(format!("spm-modelcheck-cells-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("cells.sxm");
    std::fs::write(&path, encode_sxm(&scan, &path).unwrap()).unwrap();
    let file = spm_formats::read_any(&path).unwrap();
    let ex = ExtractOptions {
        localiser: Localiser::Cells,
        ..ExtractOptions::default()
    };
    let set =
        extract_features(&[(file, None)], &LatticeSpec::parse("si7x7").unwrap(), &ex).unwrap();
    std::fs::remove_dir_all(&dir).ok();

    // Match every feature to the nearest true corner hole.
    let mut errors = Vec::new();
    let mut located = std::collections::HashSet::new();
    let mut on_defects = 0usize;
    for f in &set.features {
        let (ij, u) = sites
            .iter()
            .min_by(|p, q| {
                (p.1[0] - f.x_nm)
                    .hypot(p.1[1] - f.y_nm)
                    .total_cmp(&(q.1[0] - f.x_nm).hypot(q.1[1] - f.y_nm))
            })
            .unwrap();
        let d = [f.x_nm - u[0], f.y_nm - u[1]];
        assert!(
            d[0].hypot(d[1]) < 0.25 * a,
            "feature at ({:.3}, {:.3}) nm is not on a corner hole",
            f.x_nm,
            f.y_nm
        );
        if surface.missing.contains(ij) || surface.adsorbates.iter().any(|(s, _)| s == ij) {
            on_defects += 1;
            continue;
        }
        located.insert(*ij);
        errors.push((d, f.sigma_nm.unwrap()));
    }
    // A common offset (the template's extremum against the pit centre) is allowed, small.
    let mut dx: Vec<f64> = errors.iter().map(|e| e.0[0]).collect();
    let mut dy: Vec<f64> = errors.iter().map(|e| e.0[1]).collect();
    dx.sort_by(f64::total_cmp);
    dy.sort_by(f64::total_cmp);
    let offset = [dx[dx.len() / 2], dy[dy.len() / 2]];
    assert!(
        offset[0].hypot(offset[1]) < 0.02 * a,
        "common offset {offset:?} nm"
    );
    let mut worst: f64 = 0.0;
    let mut sq = 0.0;
    let mut sig: Vec<f64> = Vec::new();
    for (d, s) in &errors {
        let e = (d[0] - offset[0]).hypot(d[1] - offset[1]);
        worst = worst.max(e);
        sq += e * e;
        sig.push(*s);
    }
    let rms = (sq / errors.len() as f64).sqrt();
    sig.sort_by(f64::total_cmp);
    let sigma = sig[sig.len() / 2];
    println!(
        "{} features, {} intact cells located of {} in the field, {} on defects; \
         offset {offset:?} nm, error RMS {:.1} pm, worst {:.1} pm, median σ {:.1} pm",
        set.features.len(),
        located.len(),
        sites.len(),
        on_defects,
        1000.0 * rms,
        1000.0 * worst,
        1000.0 * sigma
    );
    // Every located cell within 1.5 % of the cell (40 pm, a quarter pixel) of its corner
    // hole; the RMS error within a factor 3 of the reported per-axis uncertainty·√2.
    assert!(worst < 0.015 * a, "worst error {worst} nm");
    assert!(
        rms < 3.0 * std::f64::consts::SQRT_2 * sigma + 0.002,
        "rms {rms} vs σ {sigma}"
    );
    // Most intact cells whose window lies in the field are found.
    let intact_inside: Vec<_> = sites
        .iter()
        .filter(|(ij, u)| {
            u[0].abs() < half - 0.75 * a
                && u[1].abs() < half - 0.75 * a
                && !surface.missing.contains(ij)
                && !surface.adsorbates.iter().any(|(s, _)| s == ij)
        })
        .collect();
    let interior = intact_inside
        .iter()
        .filter(|(ij, _)| located.contains(ij))
        .count();
    let interior_total = intact_inside.len();
    assert!(
        interior * 10 >= interior_total * 9,
        "{interior} of {interior_total} intact interior cells located"
    );
    // Missing cells (flat) are not reported.
    let missing_reported = set
        .features
        .iter()
        .filter(|f| {
            surface.missing.iter().any(|ij| {
                let u = inverse(surface.site(*ij));
                (u[0] - f.x_nm).hypot(u[1] - f.y_nm) < 0.25 * a
            })
        })
        .count();
    assert_eq!(missing_reported, 0, "features on missing cells");
}
