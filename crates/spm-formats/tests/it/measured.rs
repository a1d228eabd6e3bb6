//! Every file in ../shared/data/measured/ reads with the pixels, sizes, directions and times
//! its header and the data README state.

#![allow(clippy::unwrap_used)]

use crate::common;

use spm_formats::{Direction, Format, ScanDir, SpmFile, read_any};
use spmcal_tests::measured_file;

fn read(rel: &str) -> SpmFile {
    read_any(measured_file(rel)).unwrap_or_else(|e| panic!("{rel}: {e}"))
}

fn close(a: f64, b: f64, rel: f64) -> bool {
    (a - b).abs() <= rel * b.abs().max(1e-300)
}

#[test]
fn si7x7_051_header_values() {
    let f = read("si7x7-nanonis/Si_7x7_051.sxm");
    assert_eq!(f.format, Format::NanonisSxm);
    assert_eq!(f.pixels(), Some([256, 256]));
    let [sx, sy] = f.size_nm().unwrap();
    assert!(
        close(sx, 20.0, 1e-12) && close(sy, 20.0, 1e-12),
        "{sx} {sy}"
    );
    assert_eq!(f.scan_dir, Some(ScanDir::Down));
    assert_eq!(f.line_time_s, Some(0.192));
    assert_eq!(f.recorded.unwrap().to_string(), "2016-01-07T12:54:04");
    let names: Vec<(String, Direction, String)> = f
        .channels
        .iter()
        .map(|c| (c.name().to_string(), c.direction(), c.unit().to_string()))
        .collect();
    assert_eq!(
        names,
        vec![
            ("Z".into(), Direction::Forward, "m".into()),
            ("Z".into(), Direction::Backward, "m".into()),
            ("Current".into(), Direction::Forward, "A".into()),
            ("Current".into(), Direction::Backward, "A".into()),
        ]
    );
    assert_eq!(f.header_value("SCAN_PIXELS"), Some("256       256"));
    assert_eq!(f.header_value("BIAS"), Some("-2.000E+0"));
    assert_eq!(
        f.header.first().map(|(k, _)| k.as_str()),
        Some("NANONIS_VERSION")
    );
    // A complete frame: no NaN; heights within a few nm.
    let z = f.channel("Z", Direction::Forward).unwrap();
    assert_eq!(z.nan_count(), 0);
    let (lo, hi) = z
        .data()
        .iter()
        .fold((f64::MAX, f64::MIN), |(l, h), &v| (l.min(v), h.max(v)));
    assert!(hi - lo > 1e-10 && hi - lo < 1e-8, "Z range {lo}..{hi} m");
    // Timing: backward lines start after the forward line.
    let zb = f.channel("Z", Direction::Backward).unwrap();
    assert_eq!(z.pixel_time_s(0, 0), Some(0.0));
    assert_eq!(zb.pixel_time_s(0, 0), Some(0.192));
    assert!(close(zb.pixel_time_s(1, 0).unwrap(), 0.192 + 0.384, 1e-12));
    let starts = z.line_start_times_s().unwrap();
    assert!(close(starts[255], 255.0 * 0.384, 1e-12));
    // ACQ_TIME 98.5 s ≈ 256 lines × (0.192 + 0.192) s.
    assert!(close(starts[255] + 0.384, 98.5, 0.01));
}

#[test]
fn all_nanonis_files_have_their_readme_sizes() {
    for (file, size_nm, rec) in [
        ("Si_7x7_012.sxm", 200.0, "2016-01-07T11:09:34"),
        ("Si_7x7_028.sxm", 50.0, "2016-01-07T12:10:04"),
        ("Si_7x7_032.sxm", 50.0, "2016-01-07T12:18:50"),
        ("Si_7x7_051.sxm", 20.0, "2016-01-07T12:54:04"),
    ] {
        let f = read(&format!("si7x7-nanonis/{file}"));
        assert_eq!(f.pixels(), Some([256, 256]), "{file}");
        let [sx, sy] = f.size_nm().unwrap();
        assert!(
            close(sx, size_nm, 1e-12) && close(sy, size_nm, 1e-12),
            "{file}: {sx}×{sy}"
        );
        assert_eq!(f.channels.len(), 4, "{file}");
        assert_eq!(f.scan_dir, Some(ScanDir::Down), "{file}");
        assert_eq!(f.recorded.unwrap().to_string(), rec, "{file}");
        for c in &f.channels {
            assert_eq!(c.nan_count(), 0, "{file} {}", c.name());
            assert_eq!((c.nx(), c.ny()), (256, 256));
        }
    }
}

#[test]
fn drift_pair_is_8_min_46_s_apart() {
    let a = read("si7x7-nanonis/Si_7x7_028.sxm").recorded.unwrap();
    let b = read("si7x7-nanonis/Si_7x7_032.sxm").recorded.unwrap();
    assert_eq!((a.year, a.month, a.day), (b.year, b.month, b.day));
    let secs = |d: spm_formats::DateTime| {
        i64::from(d.hour) * 3600 + i64::from(d.minute) * 60 + i64::from(d.second)
    };
    assert_eq!(secs(b) - secs(a), 8 * 60 + 46);
}

/// Forward and backward images of the same frame show the same surface in display
/// orientation: their correlation must beat the correlation with one of them mirrored.
fn assert_directions_aligned(f: &SpmFile, name: &str) -> (f64, f64) {
    let fw = f.channel(name, Direction::Forward).unwrap();
    let bw = f.channel(name, Direction::Backward).unwrap();
    let n = fw.nx();
    let mirrored: Vec<f64> = bw
        .data()
        .chunks(n)
        .flat_map(|row| row.iter().rev().copied())
        .collect();
    // Remove each line's mean (line offsets and drift dominate raw correlations).
    let demean = |d: &[f64]| -> Vec<f64> {
        d.chunks(n)
            .flat_map(|row| {
                let m = row.iter().sum::<f64>() / n as f64;
                row.iter().map(move |v| v - m)
            })
            .collect()
    };
    let direct = common::correlation(&demean(fw.data()), &demean(bw.data()));
    let flipped = common::correlation(&demean(fw.data()), &demean(&mirrored));
    assert!(
        direct > 0.3 && direct > flipped + 0.2,
        "{}: {name} forward/backward correlation {direct:.3}, with backward mirrored {flipped:.3}",
        f.source.display()
    );
    (direct, flipped)
}

#[test]
fn nanonis_backward_images_are_mirrored_into_display_orientation() {
    for file in ["Si_7x7_012.sxm", "Si_7x7_051.sxm"] {
        let f = read(&format!("si7x7-nanonis/{file}"));
        let (d, m) = assert_directions_aligned(&f, "Z");
        println!("{file}: Z fwd/bwd correlation {d:.3} (mirrored {m:.3})");
    }
}

#[test]
fn acquisition_order_reverses_backward_lines() {
    let f = read("si7x7-nanonis/Si_7x7_051.sxm");
    let bw = f.channel("Z", Direction::Backward).unwrap();
    let acq = bw.acquisition_image();
    // Scan down: acquisition row 0 is display row 0, read right to left.
    for c in 0..256 {
        assert_eq!(acq.get(0, c), bw.get(0, 255 - c));
        assert_eq!(acq.get(255, c), bw.get(255, 255 - c));
    }
    assert_eq!(bw.display_index(3, 0), (3, 255));
    let fw = f.channel("Z", Direction::Forward).unwrap();
    assert_eq!(fw.acquisition_image(), fw.display_image());
}

/// The effective hexagonal lattice constant (nm) of a channel from the area of the smallest
/// cell spanned by its strongest autocorrelation peaks: a = √(2·A/√3). The cell area is
/// insensitive to how a linear distortion (drift, shear) splits between the axes.
fn effective_lattice_nm(
    z: &spm_formats::Channel,
    a_guess_nm: f64,
    r_max_factor: f64,
) -> (f64, Vec<f64>) {
    let px_nm = z.pixel_x_nm().unwrap();
    assert!(
        close(px_nm, z.pixel_y_nm().unwrap(), 1e-12),
        "square pixels expected"
    );
    let a_px = a_guess_nm / px_nm;
    let v = common::nearest_neighbour_vectors_px(z.data(), z.nx(), 0.6 * a_px, r_max_factor * a_px);
    assert!(v.len() >= 2, "{}: no lattice found", z.name());
    let lengths: Vec<f64> = v.iter().map(|(x, y)| x.hypot(*y) * px_nm).collect();
    // Any two independent lattice vectors span a multiple of the primitive cell: take the
    // smallest area among the pairs.
    let cross = |i: usize, j: usize| (v[i].0 * v[j].1 - v[i].1 * v[j].0).abs();
    let pairs = [(0, 1), (0, 2), (1, 2)];
    let area_px2 = pairs
        .iter()
        .filter(|(i, j)| *i < v.len() && *j < v.len())
        .map(|&(i, j)| cross(i, j))
        .fold(f64::MAX, f64::min);
    let area_nm2 = area_px2 * px_nm * px_nm;
    ((2.0 * area_nm2 / 3f64.sqrt()).sqrt(), lengths)
}

/// Si(111)-7×7 corner holes. With the header's scan ranges the cell of all three 7×7 frames
/// (20 nm and 50 nm) comes out ≈ 1.3× the true 2.688 nm and sheared (neighbour vectors ≈ 3.0,
/// 3.5, 4.2 nm at ≈ 100°): the instrument's lateral calibration in these files is off — the
/// very thing spmcal calibrates. The reader is checked for consistency: both scan sizes give
/// the same cell within 8 % (drift differs between frames by a few %), i.e. pixel sizes are read right across scan ranges.
#[test]
fn si7x7_lattice_is_consistent_across_scan_sizes() {
    let mut effective = Vec::new();
    for file in ["Si_7x7_051.sxm", "Si_7x7_028.sxm", "Si_7x7_032.sxm"] {
        let f = read(&format!("si7x7-nanonis/{file}"));
        for dir in [Direction::Forward, Direction::Backward] {
            let z = f.channel("Z", dir).unwrap();
            let (a_nm, lengths) = effective_lattice_nm(z, 3.4, 1.35);
            println!(
                "{file} Z {dir}: neighbour distances {lengths:.3?} nm, effective a {a_nm:.3} nm \
                 ({:+.1} % vs 2.688 nm)",
                100.0 * (a_nm / 2.688 - 1.0)
            );
            effective.push(a_nm);
        }
    }
    let lo = effective.iter().copied().fold(f64::MAX, f64::min);
    let hi = effective.iter().copied().fold(f64::MIN, f64::max);
    assert!(hi / lo < 1.08, "effective lattice constants {effective:?}");
    // The header scale makes the cell 20–40 % too large (see above), not a factor 2 or 10.
    assert!(
        effective
            .iter()
            .all(|&a| a > 1.2 * 2.688 && a < 1.4 * 2.688),
        "{effective:?}"
    );
}

#[test]
fn graphite_sm4_pages() {
    let f = read("graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4");
    assert_eq!(f.format, Format::RhkSm4);
    let got: Vec<(String, Direction, String)> = f
        .channels
        .iter()
        .map(|c| (c.name().to_string(), c.direction(), c.unit().to_string()))
        .collect();
    let want: Vec<(String, Direction, String)> = [
        ("LIA Current", Direction::Backward, "A"),
        ("LIA Current", Direction::Forward, "A"),
        ("Current", Direction::Backward, "A"),
        ("Current", Direction::Forward, "A"),
        ("Topography", Direction::Backward, "m"),
        ("Topography", Direction::Forward, "m"),
    ]
    .iter()
    .map(|(n, d, u)| (n.to_string(), *d, u.to_string()))
    .collect();
    assert_eq!(got, want);
    for c in &f.channels {
        assert_eq!((c.nx(), c.ny()), (256, 256));
        assert!(
            close(c.size_x_nm().unwrap(), 1.0, 1e-6),
            "{}",
            c.size_x_nm().unwrap()
        );
        assert!(close(c.size_y_nm().unwrap(), 1.0, 1e-6));
        assert!(close(c.pixel_x_nm().unwrap(), 0.00390625, 1e-6));
        assert_eq!(c.angle_deg(), Some(10.0));
    }
    assert_eq!(f.pixels(), Some([256, 256]));
    // Page header strings: date 07/02/20, time 07:44:02 (page 0; later pages say 07:44:03).
    assert_eq!(f.recorded.unwrap().to_string(), "2020-07-02T07:44:02");
    assert_eq!(f.header_value("Page4.Label"), Some("Topography"));
    assert_eq!(f.header_value("Page4.ScanDirection"), Some("SCAN_LEFT"));
    assert_eq!(f.header_value("Page5.ScanDirection"), Some("SCAN_RIGHT"));
    assert_eq!(f.header_value("Page6.DataType"), Some("1")); // spectroscopy, not a channel
    // The page header's `period` is the time per data point (RHK's SM4 description; spym
    // reads it as `time_per_point`), so 1.953125 ms per pixel → 0.5 s per 256-pixel line
    // (2 nm/s over this 1 nm frame). The data README's "line period 1.953 ms" is this pixel
    // period: a 0.5 s frame is implausible for atomic resolution at 9 K, and the file's own
    // spectroscopy pages (81 points per sweep, period 1e-4 s) only make sense per point.
    assert_eq!(f.header_value("Page4.Period"), Some("1.953125e-3"));
    assert_eq!(f.header_value("Page6.Period"), Some("1e-4"));
    assert!(close(f.line_time_s.unwrap(), 0.5, 1e-6));
    let t = topo_timing(&f);
    assert!(close(t.line_period_s, 1.0, 1e-6), "trace + retrace: {t:?}");
    let topo = f.channel("Topography", Direction::Forward).unwrap();
    let (lo, hi) = topo
        .data()
        .iter()
        .fold((f64::MAX, f64::MIN), |(l, h), &v| (l.min(v), h.max(v)));
    assert!(
        hi - lo > 1e-12 && hi - lo < 1e-9,
        "topography range {lo}..{hi} m"
    );
}

fn topo_timing(f: &SpmFile) -> spm_formats::LineTiming {
    f.channel("Topography", Direction::Forward)
        .and_then(|c| c.timing())
        .unwrap()
}

#[test]
fn graphite_sm4_left_and_right_pages_align() {
    let f = read("graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4");
    let (d, m) = assert_directions_aligned(&f, "Topography");
    println!("graphite topography right/left correlation {d:.3} (mirrored {m:.3})");
}

/// Graphite: three lattice row spacings from the power spectrum, a = d·2/√3.
#[test]
fn graphite_sm4_lattice_constant() {
    let f = read("graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4");
    let s3 = 3f64.sqrt() / 2.0;
    for dir in [Direction::Forward, Direction::Backward] {
        let z = f.channel("Topography", dir).unwrap();
        let px_nm = z.pixel_x_nm().unwrap();
        let d_px = 0.2461 * s3 / px_nm;
        let rows = common::row_spacings_px(z.data(), 256, 0.7 * d_px, 1.3 * d_px);
        let a_nm: Vec<f64> = rows.iter().map(|d| d * px_nm / s3).collect();
        let mean = a_nm.iter().sum::<f64>() / a_nm.len() as f64;
        println!("graphite Topography {dir}: a from row spacings {a_nm:.4?} nm, mean {mean:.4} nm");
        assert_eq!(a_nm.len(), 3);
        assert!(close(mean, 0.2461, 0.05), "{dir}: {a_nm:?} nm");
    }
}

#[test]
fn hopg_iso28600() {
    let f = read("hopg-terrace-iso28600/graphiteterrace.spm");
    assert_eq!(f.format, Format::Iso28600);
    assert_eq!(f.pixels(), Some([512, 512]));
    let [sx, sy] = f.size_nm().unwrap();
    assert!(
        close(sx, 11.4807, 1e-9) && close(sy, 11.4807, 1e-9),
        "{sx} {sy}"
    );
    assert_eq!(f.channels.len(), 1);
    let z = &f.channels[0];
    assert_eq!(
        (z.name(), z.direction(), z.unit()),
        ("Z (Forward)", Direction::Forward, "m")
    );
    assert_eq!(f.scan_dir, Some(ScanDir::Down));
    assert_eq!(f.line_time_s, None);
    assert_eq!(f.recorded, None);
    // First and last values of the data block: x left→right, y top→bottom.
    assert_eq!(z.get(0, 0), Some(1.5579461e-10));
    assert_eq!(z.get(0, 1), Some(1.8331518e-10));
    assert_eq!(z.get(511, 511), Some(9.3093692e-10));
    assert_eq!(f.header_value("008 Experiment mode"), Some("MAP_SC"));
    assert_eq!(
        f.header_value("088 Data treatment"),
        Some("post-treated data")
    );
}

/// HOPG: the dominant row spacing from the power spectrum (README: ≈ 0.22 nm against
/// 0.2131 nm ideal, a few % distortion).
#[test]
fn hopg_iso28600_lattice_constant() {
    let f = read("hopg-terrace-iso28600/graphiteterrace.spm");
    let z = &f.channels[0];
    let px_nm = z.pixel_x_nm().unwrap();
    let d_px = 0.2131 / px_nm;
    let rows = common::row_spacings_px(z.data(), 512, 0.7 * d_px, 1.3 * d_px);
    let rows_nm: Vec<f64> = rows.iter().map(|d| d * px_nm).collect();
    println!("HOPG ISO 28600: row spacings {rows_nm:.4?} nm (strongest first)");
    assert!(close(rows_nm[0], 0.2131, 0.06), "{rows_nm:?} nm");
}

#[test]
fn si7x7_raw_files() {
    for (file, n, first) in [
        ("image_with_defects.dat", 256, None),
        ("image_with_step_edge.dat", 512, None),
        ("image_with_step_edge_and_atoms.dat", 512, None::<f64>),
    ] {
        let path = measured_file(&format!("si7x7-raw/{file}"));
        let f = read_any(&path).unwrap();
        assert_eq!(f.format, Format::RawF64);
        assert_eq!(f.pixels(), Some([n, n]), "{file}");
        assert_eq!(f.size_nm(), None, "{file}: the raw format stores no size");
        let z = &f.channels[0];
        assert_eq!((z.name(), z.unit()), ("Z", "m"));
        // Independent decode of the first value.
        let bytes = std::fs::read(&path).unwrap();
        let v0 = f64::from_le_bytes(bytes[8..16].try_into().unwrap());
        assert_eq!(z.get(0, 0), Some(first.unwrap_or(v0)));
        let (lo, hi) = z
            .data()
            .iter()
            .fold((f64::MAX, f64::MIN), |(l, h), &v| (l.min(v), h.max(v)));
        assert!(
            hi - lo > 1e-11 && hi - lo < 1e-8,
            "{file}: range {lo}..{hi} m"
        );
    }
}

#[test]
fn info_json_has_the_design_keys() {
    let f = read("si7x7-nanonis/Si_7x7_051.sxm");
    let v = serde_json::to_value(f.info()).unwrap();
    assert_eq!(v["format"], "nanonis-sxm");
    assert_eq!(v["pixels"], serde_json::json!([256, 256]));
    assert_eq!(v["size_nm"], serde_json::json!([20.0, 20.0]));
    assert_eq!(v["scan_dir"], "down");
    assert_eq!(v["line_time_s"], 0.192);
    assert_eq!(v["recorded"], "2016-01-07T12:54:04");
    assert_eq!(v["channels"][0]["name"], "Z");
    assert_eq!(v["channels"][0]["direction"], "forward");
    assert_eq!(v["channels"][0]["unit"], "m");
    assert_eq!(v["channels"][1]["direction"], "backward");
    assert_eq!(v["header"][0], serde_json::json!(["NANONIS_VERSION", "2"]));

    let raw = read("si7x7-raw/image_with_defects.dat");
    let v = serde_json::to_value(raw.info()).unwrap();
    assert_eq!(v["size_nm"], serde_json::Value::Null);
    assert_eq!(v["scan_dir"], serde_json::Value::Null);
}

/// A channel as an [`spm_hal::HeightMap`] for spm-features, in pixel units: column/row
/// positions are "counts" of one pixel each, heights in pm, each line's mean removed (the
/// usual line levelling of STM data: line offsets are feedback and drift, not topography).
fn height_map_px(z: &spm_formats::Channel) -> spm_hal::HeightMap {
    let n = z.nx();
    let z_pm: Vec<f64> = z
        .data()
        .chunks(n)
        .flat_map(|row| {
            let m = row.iter().sum::<f64>() / n as f64;
            row.iter().map(move |v| (v - m) * 1e12)
        })
        .collect();
    let time_s = (0..z_pm.len()).map(|k| k as f64).collect();
    spm_hal::HeightMap {
        origin: spm_hal::CountPoint::from_counts(0.0, 0.0),
        pixel_step: spm_hal::Counts(1.0),
        columns: n,
        rows: z.ny(),
        z_counts: z_pm,
        time_s,
    }
}

/// Features detected by spm-features and the lattice vectors of their nearest neighbours,
/// in nm (square pixels), most populated direction first. Returns (number of features,
/// vectors as (x, y, |v|) nm, pairs behind each vector).
fn feature_lattice_nm(
    z: &spm_formats::Channel,
    polarity: spm_features::Polarity,
    period_guess_px: f64,
) -> (usize, Vec<(f64, f64, f64)>, Vec<usize>) {
    let px_nm = z.pixel_x_nm().unwrap();
    assert!(close(px_nm, z.pixel_y_nm().unwrap(), 1e-12));
    let map = height_map_px(z);
    let config = spm_features::DetectionConfig {
        polarity,
        min_separation_px: 0.5 * period_guess_px,
        max_fit_radius_px: 0.6 * period_guess_px,
        max_width_px: 0.5 * period_guess_px,
        ..spm_features::DetectionConfig::default()
    };
    let found = spm_features::detect(&map, &config).unwrap();
    let lattice =
        spm_features::lattice_vectors(&found.features, &spm_features::LatticeConfig::default())
            .unwrap();
    let vectors = lattice
        .vectors
        .iter()
        .take(3)
        .map(|v| {
            let (x, y) = (v.vector.x.value() * px_nm, v.vector.y.value() * px_nm);
            (x, y, x.hypot(y))
        })
        .collect();
    let pairs = lattice.vectors.iter().take(3).map(|v| v.pairs).collect();
    (found.features.len(), vectors, pairs)
}

/// Graphite at 9 K (RHK .sm4, 1 nm, 256 px, a ≈ 63 px): atoms detected by spm-features, the
/// three nearest-neighbour directions of the triangular lattice, mean |a| within 5 % of
/// 0.2461 nm with the header's pixel size.
#[test]
fn graphite_sm4_lattice_with_spm_features() {
    let f = read("graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4");
    for dir in [Direction::Forward, Direction::Backward] {
        let z = f.channel("Topography", dir).unwrap();
        let a_px = 0.2461 / z.pixel_x_nm().unwrap();
        let (n, v, _) = feature_lattice_nm(z, spm_features::Polarity::Hill, a_px);
        let lengths: Vec<f64> = v.iter().map(|t| t.2).collect();
        let mean = lengths.iter().sum::<f64>() / lengths.len().max(1) as f64;
        println!(
            "graphite Topography {dir}: {n} atoms, lattice vectors {v:.4?} nm, mean |a| {mean:.4} nm \
             ({:+.1} % vs 0.2461)",
            100.0 * (mean / 0.2461 - 1.0)
        );
        assert!(n >= 8, "{dir}: only {n} atoms");
        assert_eq!(v.len(), 3, "{dir}: {v:?}");
        assert!(close(mean, 0.2461, 0.05), "{dir}: mean |a| {mean} nm");
    }
}

/// A triangular lattice seen through x' = x + s·y, y' = k·y (the fast axis x keeps its
/// scale; the slow axis y carries the drift and creep of the frame time: stretch k, shear s).
/// From two measured nearest-neighbour vectors m1, m2 and the third, m3 (the shorter of
/// m2 ∓ m1), the quadratic form |A⁻¹m|² = mx² − 2α·mx·my + β·my² (α = s/k, β = (s² + 1)/k²)
/// must give equal lengths: two linear equations in (α, β). Returns (a, k, s), a in the
/// units of m — the lattice constant on the fast-axis scale.
fn fast_axis_lattice(m1: (f64, f64), m2: (f64, f64)) -> Option<(f64, f64, f64)> {
    let minus = (m2.0 - m1.0, m2.1 - m1.1);
    let plus = (m2.0 + m1.0, m2.1 + m1.1);
    let m3 = if minus.0.hypot(minus.1) < plus.0.hypot(plus.1) {
        minus
    } else {
        plus
    };
    // Q(m1) = Q(mi): (2·mxi·myi − 2·mx1·my1)·α + (my1² − myi²)·β = mxi² − mx1².
    let row = |m: (f64, f64)| {
        (
            2.0 * m.0 * m.1 - 2.0 * m1.0 * m1.1,
            m1.1 * m1.1 - m.1 * m.1,
            m.0 * m.0 - m1.0 * m1.0,
        )
    };
    let (p, q) = (row(m2), row(m3));
    let det = p.0 * q.1 - p.1 * q.0;
    if det.abs() < 1e-12 {
        return None;
    }
    let alpha = (p.2 * q.1 - p.1 * q.2) / det;
    let beta = (p.0 * q.2 - p.2 * q.0) / det;
    let w2 = beta - alpha * alpha;
    let a2 = m1.0 * m1.0 - 2.0 * alpha * m1.0 * m1.1 + beta * m1.1 * m1.1;
    (w2 > 0.0 && a2 > 0.0).then(|| {
        let k = 1.0 / w2.sqrt();
        (a2.sqrt(), k, alpha * k)
    })
}

#[test]
fn the_fast_axis_lattice_solution_inverts_a_known_distortion() {
    // a = 2, rotated 20°, seen with k = 1.4, s = −0.2.
    let (a, k, s) = (2.0_f64, 1.4, -0.2);
    let v = |deg: f64| {
        let (sn, cs) = deg.to_radians().sin_cos();
        (a * cs + s * a * sn, k * a * sn)
    };
    let (got_a, got_k, got_s) = fast_axis_lattice(v(20.0), v(80.0)).unwrap();
    assert!((got_a - a).abs() < 1e-9 && (got_k - k).abs() < 1e-9 && (got_s - s).abs() < 1e-9);
}

/// Si(111)-7×7 corner holes (dark: detected as pits) and adatoms (hills) by spm-features on
/// Si_7x7_051 (20 nm, 256 px, both directions).
///
/// What the data say. With the header's pixel size (20 nm / 256) the corner holes form a
/// lattice whose two clean nearest-neighbour directions are ≈ 3.0 nm (−13°, nearly along the
/// fast axis) and ≈ 3.6 nm (67°), the third side ≈ 4.3 nm: the cell is ≈ 1.3× the true
/// 2.688 nm in area and strongly sheared, so the "2.688 nm within 3 %" does not hold
/// for this file. That it is the instrument and not the reader:
/// - identity, scale-free: along the hole direction nearest the fast axis the adatom spacing
///   is exactly 1/3.5 of the corner-hole spacing (2a₀ = 0.768 nm against 7a₀ = 2.688 nm), a
///   ratio any linear distortion — header scale, drift, shear — leaves unchanged;
/// - the distortion is anisotropic (a shear and a slow-axis stretch), which no pixel-size
///   reading can produce (a reader error would be one isotropic factor);
/// - assuming only that the fast axis is undistorted (a line takes 0.192 s, drift cannot act
///   on it) and solving for a triangular lattice seen through a slow-axis stretch and shear,
///   the cell comes out 2.87 nm forward and 2.92 nm backward (+7 % and +8 %) with the slow
///   axis stretched ≈ 1.48× and sheared ≈ −0.19: the file's fast-axis calibration reads
///   ≈ 7–8 % long and the slow axis carries ≈ 0.1 nm/s of drift or creep over the 98 s frame
///   (room temperature).
///
/// The test asserts these statements, not fitted numbers: the ratio 3.5 within 3 %, the cell
/// area 20–40 % too large, the fast-axis lattice constant 3–15 % long and the slow axis
/// stretched by more than 20 %, forward and backward agreeing within 2 %.
#[test]
fn si7x7_051_corner_holes_and_adatoms_with_spm_features() {
    let f = read("si7x7-nanonis/Si_7x7_051.sxm");
    let mut fast = Vec::new();
    for dir in [Direction::Forward, Direction::Backward] {
        let z = f.channel("Z", dir).unwrap();
        let px = z.pixel_x_nm().unwrap();
        let (holes, hv, hp) = feature_lattice_nm(z, spm_features::Polarity::Pit, 2.688 / px);
        let (adatoms, av, _) = feature_lattice_nm(z, spm_features::Polarity::Hill, 0.768 / px);
        println!(
            "Si_7x7_051 Z {dir}: {holes} corner holes, vectors {hv:.3?} nm ({hp:?} pairs); \
             {adatoms} adatoms, vectors {av:.3?} nm"
        );
        assert!(holes >= 25, "{dir}: {holes} corner holes");
        assert!(hv.len() >= 2 && hp[1] >= 10, "{dir}: {hv:?} {hp:?}");
        let (m1, m2) = ((hv[0].0, hv[0].1), (hv[1].0, hv[1].1));
        // Identity: the adatom spacing along the first hole direction.
        let angle = |v: (f64, f64)| v.1.atan2(v.0);
        let along = av
            .iter()
            .find(|a| {
                let d = (angle((a.0, a.1)) - angle(m1)).rem_euclid(std::f64::consts::PI);
                d.min(std::f64::consts::PI - d) < 6f64.to_radians()
            })
            .unwrap_or_else(|| panic!("{dir}: no adatom direction along {m1:?}: {av:?}"));
        let ratio = hv[0].2 / along.2;
        // Header scale: the cell area.
        let area = (m1.0 * m2.1 - m1.1 * m2.0).abs();
        let a_area = (2.0 * area / 3f64.sqrt()).sqrt();
        // The fast-axis scale only.
        let (a_fast, k, s) = fast_axis_lattice(m1, m2).unwrap();
        println!(
            "Si_7x7_051 Z {dir}: hole/adatom spacing ratio {ratio:.3} (7×7: 3.5); header scale: \
             cell from area {a_area:.3} nm ({:+.1} %); fast-axis scale: a = {a_fast:.3} nm \
             ({:+.1} % vs 2.688), slow-axis stretch {k:.3}, shear {s:+.3}",
            100.0 * (a_area / 2.688 - 1.0),
            100.0 * (a_fast / 2.688 - 1.0)
        );
        assert!(close(ratio, 3.5, 0.03), "{dir}: ratio {ratio}");
        assert!(
            a_area > 1.2 * 2.688 && a_area < 1.4 * 2.688,
            "{dir}: {a_area}"
        );
        assert!(
            a_fast > 1.03 * 2.688 && a_fast < 1.15 * 2.688,
            "{dir}: {a_fast}"
        );
        assert!(k > 1.2, "{dir}: slow-axis stretch {k}");
        fast.push(a_fast);
    }
    assert!(close(fast[0], fast[1], 0.02), "forward/backward {fast:?}");
}
