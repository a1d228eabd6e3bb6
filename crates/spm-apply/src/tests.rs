//! Unit tests against closed forms: linear fields, whose corrected coordinates are a linear
//! map of the commanded ones on any path.
#![allow(clippy::unwrap_used)]

use super::*;
use spm_correction::{FittedSurface, PlaneSurfaces, Provenance};
use spm_regression::{Polynomial2, n_terms};

/// A uniform field: K̄x, K̄y, α constant.
fn uniform(kx: f64, ky: f64, alpha: f64) -> SurfaceSet {
    let mut plane = PlaneSurfaces::constant(0.0, kx, ky, alpha).unwrap();
    plane.calibrated_region_counts = Some(CountRegion {
        x_min_counts: -30_000.0,
        x_max_counts: 30_000.0,
        y_min_counts: -30_000.0,
        y_max_counts: 30_000.0,
    });
    plane.n_records = 100;
    SurfaceSet::new(
        Provenance {
            scanner_id: "test-scanner".into(),
            n_records: 100,
            nominal_nm_per_count: Some(0.02),
            counts_convention: Some(CountsConvention::CentredSigned),
            ..Provenance::default()
        },
        vec![plane],
    )
    .unwrap()
}

/// A field whose coefficients vary over the plane (cubic surfaces).
fn curved() -> SurfaceSet {
    let surface = |base: f64, seed: f64| {
        let c = (0..n_terms(3))
            .map(|k| {
                if k == 0 {
                    base
                } else {
                    base * 0.04 * ((k as f64 + seed) * 1.3).sin()
                }
            })
            .collect();
        FittedSurface::new(
            Polynomial2::new(3, (0.0, 0.0), (30_000.0, 30_000.0), c).unwrap(),
            base * 0.001,
        )
    };
    let plane = PlaneSurfaces {
        z_counts: 0.0,
        n_records: 300,
        kx_nm_per_count: surface(0.020, 0.0),
        ky_nm_per_count: surface(0.019, 1.0),
        alpha_rad: surface(0.02, 2.0),
        kyx_nm_per_count: surface(0.0004, 3.0),
        kyy_nm_per_count: surface(0.019, 4.0),
        kz_nm_per_count: None,
        bowl_z_counts: None,
        calibrated_region_counts: CountRegion::bounding(
            &[-30_000.0, 30_000.0],
            &[-30_000.0, 30_000.0],
            0.0,
        ),
        form: spm_correction::SurfaceForm::Independent,
    };
    SurfaceSet::new(
        Provenance {
            scanner_id: "test-scanner".into(),
            n_records: 300,
            ..Provenance::default()
        },
        vec![plane],
    )
    .unwrap()
}

fn raster(columns: usize, rows: usize, angle_deg: f64, path: RasterPath) -> FileRaster {
    FileRaster {
        columns,
        rows,
        centre: CountPoint::from_counts(1200.0, -800.0),
        step_x_counts: 10.0,
        step_y_counts: 10.0,
        angle_ccw_rad: angle_deg.to_radians(),
        path,
        counts: CountsSource::Recorded,
        line_time_s: None,
    }
}

fn map_point(map: &CoordinateMap, column: usize, map_row: usize) -> [f64; 2] {
    let p = map.point(column, map_row).unwrap();
    [p.x.value(), p.y.value()]
}

#[test]
fn the_polyline_path_reproduces_the_analytic_direct_raster() {
    let set = curved();
    let field = set.planes[0].field(Route::Products);
    let r = raster(17, 13, 0.0, RasterPath::Trace(ScanDir::Up));
    let (fast, _) = coordinate_map(&field, &r).unwrap();
    let general = general_map(&field, &r, &Quadrature::default()).unwrap();
    for row in 0..13 {
        for column in 0..17 {
            let a = map_point(&fast, column, row);
            let b = map_point(&general, column, row);
            assert!(
                (a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9,
                "pixel ({column}, {row}): analytic {a:?}, polyline {b:?}"
            );
        }
    }
}

/// A uniform field is the linear map M = [[kx, ky sin α], [0, ky cos α]] on the scanner's
/// counts; in the frame's axes the corrected offset of a pixel from the first pixel is
/// R(−θ)·M·(p − p₀) whatever the path, rotation or direction.
#[test]
fn a_rotated_raster_in_a_uniform_oblique_field_matches_the_closed_form() {
    let (kx, ky, alpha) = (0.021, 0.018, 0.05);
    let set = uniform(kx, ky, alpha);
    let field = set.planes[0].field(Route::Products);
    for (angle, path) in [
        (30.0, RasterPath::Trace(ScanDir::Up)),
        (-10.0, RasterPath::Trace(ScanDir::Down)),
        (135.0, RasterPath::Counter),
        (0.0, RasterPath::Trace(ScanDir::Down)),
    ] {
        let r = raster(9, 7, angle, path);
        let (map, _) = coordinate_map(&field, &r).unwrap();
        let (s, c) = r.angle_ccw_rad.sin_cos();
        let expected = |column: usize, display_row: usize| {
            let p = r.pixel_counts(column as f64, display_row as f64);
            let (x, y) = (p.x.value(), p.y.value());
            let (mx, my) = (kx * x + ky * alpha.sin() * y, ky * alpha.cos() * y);
            [mx * c + my * s, -mx * s + my * c]
        };
        let e0 = expected(0, 0);
        let m0 = map_point(&map, 0, 6);
        for display_row in 0..7 {
            for column in 0..9 {
                let e = expected(column, display_row);
                let m = map_point(&map, column, 6 - display_row);
                let (dx, dy) = (
                    (m[0] - m0[0]) - (e[0] - e0[0]),
                    (m[1] - m0[1]) - (e[1] - e0[1]),
                );
                assert!(
                    dx.abs() < 1e-9 && dy.abs() < 1e-9,
                    "angle {angle}, {path:?}, pixel ({column}, {display_row}): off by ({dx:e}, {dy:e}) nm"
                );
            }
        }
    }
}

#[test]
fn the_pixel_positions_follow_the_frame_angle_counter_clockwise() {
    let r = raster(3, 3, 90.0, RasterPath::Trace(ScanDir::Up));
    // Rotated by 90° counter-clockwise, the frame's +x (right) is the scanner's +y.
    let right = r.pixel_counts(2.0, 1.0);
    assert!((right.x.value() - 1200.0).abs() < 1e-9);
    assert!((right.y.value() - (-800.0 + 10.0)).abs() < 1e-9);
    // And the frame's top is the scanner's −x.
    let top = r.pixel_counts(1.0, 0.0);
    assert!((top.x.value() - (1200.0 - 10.0)).abs() < 1e-9);
    assert!((top.y.value() - (-800.0)).abs() < 1e-9);
}

fn sim_file(nx: usize, ny: usize, headers: &[(&str, &str)]) -> SpmFile {
    let data: Vec<f64> = (0..nx * ny)
        .map(|i| ((i % nx) as f64 * 0.7).sin() * 1e-10)
        .collect();
    let channel = Channel::new("Z", Direction::Forward, "m", nx, ny, data)
        .unwrap()
        .with_size_nm(nx as f64 * 0.2, ny as f64 * 0.2)
        .with_center_nm(0.0, 0.0);
    SpmFile {
        source: PathBuf::from("test.gsf"),
        format: Format::Gsf,
        channels: vec![channel],
        header: headers
            .iter()
            .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
            .collect(),
        scan_dir: None,
        line_time_s: None,
        recorded: None,
    }
}

fn nominal(k: f64) -> ApplyOptions {
    ApplyOptions {
        nominal_nm_per_count: Some(k),
        ..ApplyOptions::default()
    }
}

#[test]
fn the_guard_rails_refuse_with_the_field_named() {
    let set = uniform(0.02, 0.02, 0.0);
    let check = |file: SpmFile, options: ApplyOptions, expect: &str| {
        let error = correct_file(&file, &set, &options).unwrap_err();
        let text = error.to_string();
        assert!(error.is_bad_input(), "{text}");
        assert!(text.contains(expect), "expected {expect:?} in: {text}");
    };
    check(
        sim_file(16, 16, &[(KEY_CORRECTED, "yes")]),
        nominal(0.02),
        "already corrected",
    );
    check(
        sim_file(16, 16, &[("spmcal_surfaces", "s.json")]),
        nominal(0.02),
        "already corrected",
    );
    check(
        sim_file(16, 16, &[(KEY_SCANNER, "other")]),
        nominal(0.02),
        "spmcal_scanner_id",
    );
    check(
        sim_file(16, 16, &[]),
        ApplyOptions {
            scanner_id: Some("other".into()),
            ..nominal(0.02)
        },
        "\"other\"",
    );
    // A sensitivity given in m instead of nm.
    check(
        sim_file(16, 16, &[]),
        nominal(0.02e-9),
        "--nominal-nm-per-count",
    );
    check(sim_file(16, 16, &[]), nominal(0.2), "factor");
    check(
        sim_file(
            16,
            16,
            &[
                (KEY_ORIGIN_X, "0"),
                (KEY_ORIGIN_Y, "0"),
                (KEY_STEP, "10"),
                (KEY_CONVENTION, "corner_unsigned"),
            ],
        ),
        ApplyOptions::default(),
        "spmcal_counts_convention",
    );
    // 3.2 nm over 16 px at 0.02 nm/count centred 3 µm away.
    let mut far = sim_file(16, 16, &[]);
    far.channels[0] = far.channels[0].clone().with_center_nm(3000.0, 0.0);
    check(far, nominal(0.02), "--allow-extrapolation");
    // 200 nm at 0.02 nm/count spans 10⁴ counts: inside; 2 µm spans 10⁵: outside.
    let mut large = sim_file(16, 16, &[]);
    large.channels[0] = large.channels[0].clone().with_size_nm(2000.0, 2000.0);
    check(large, nominal(0.02), "beyond the calibrated region");
    check(
        sim_file(16, 16, &[]),
        ApplyOptions::default(),
        "--nominal-nm-per-count",
    );
    check(
        sim_file(16, 16, &[]),
        ApplyOptions {
            channels: ChannelSelection::Named("Current".into()),
            ..nominal(0.02)
        },
        "Z (forward)",
    );
}

#[test]
fn extrapolation_when_allowed_is_marked_and_unknown_pixels_are_nan() {
    let set = uniform(0.02, 0.02, 0.01);
    let mut file = sim_file(32, 32, &[("Bias", "0.4 V")]);
    file.channels[0] = file.channels[0].clone().with_center_nm(700.0, 0.0);
    let options = ApplyOptions {
        allow_extrapolation: true,
        ..nominal(0.02)
    };
    let out = correct_file(&file, &set, &options).unwrap();
    assert!(out.extrapolated_counts.is_some());
    let get = |k: &str| {
        out.metadata
            .iter()
            .find(|(key, _)| key == k)
            .map(|(_, v)| v.as_str())
    };
    assert!(get("spmcal_extrapolated").unwrap().starts_with("yes"));
    assert_eq!(get("source_Bias"), Some("0.4 V"));
    assert_eq!(get(KEY_CORRECTED), Some("yes"));
    // The oblique field shears the raster: the output's corners hold no data, as NaN.
    let data = out.channels[0].data();
    assert!(out.unknown_pixels > 0);
    assert_eq!(
        data.iter().filter(|v| v.is_nan()).count(),
        out.unknown_pixels
    );
    assert!(data.iter().any(|v| v.is_finite()));
}

#[test]
fn an_identity_calibration_reproduces_the_image() {
    let set = uniform(0.02, 0.02, 0.0);
    let file = sim_file(24, 20, &[]);
    let out = correct_file(&file, &set, &nominal(0.02)).unwrap();
    let ch = &out.channels[0];
    assert_eq!((ch.nx(), ch.ny()), (24, 20));
    assert!((ch.size_x_nm().unwrap() - 24.0 * 0.2).abs() < 1e-9);
    for (a, b) in ch.data().iter().zip(file.channels[0].data()) {
        assert!((a - b).abs() < 1e-18, "{a} vs {b}");
    }
    assert_eq!(out.unknown_pixels, 0);
}

#[test]
fn output_names_name_what_spmcal_writes() {
    assert_eq!(
        OutputKind::of_path(Path::new("a/x.GSF")).unwrap(),
        OutputKind::Gsf
    );
    assert_eq!(
        OutputKind::of_path(Path::new("x.gwy")).unwrap(),
        OutputKind::Gwy
    );
    let error = OutputKind::of_path(Path::new("x.png"))
        .unwrap_err()
        .to_string();
    assert!(error.contains("--out") && error.contains(".png"), "{error}");
}

fn dynamics_of(
    hysteresis_x: spm_correction::hysteresis::PlayHysteresis,
    creep_weight: f64,
) -> spm_correction::hysteresis::ScannerDynamics {
    use spm_correction::hysteresis::*;
    ScannerDynamics {
        format: DYNAMICS_FORMAT.to_owned(),
        version: DYNAMICS_FORMAT_VERSION,
        hysteresis_x,
        hysteresis_y: PlayHysteresis::none(),
        creep: CreepParameters {
            weight: creep_weight,
            min_time_constant_s: 0.01,
            max_time_constant_s: 1e4,
            elements_per_decade: 3,
        },
        identification: DynamicsIdentification::default(),
    }
}

/// Dynamics that do nothing (no hysteresis, no creep) reproduce the static path, on a curved
/// field, a rotated raster and every path; the retrace half too.
#[test]
fn null_dynamics_reproduce_the_static_map() {
    let set = curved();
    let field = set.planes[0].field(Route::Products);
    let null = dynamics_of(spm_correction::hysteresis::PlayHysteresis::none(), 0.0);
    for (angle, path) in [
        (0.0, RasterPath::Trace(ScanDir::Up)),
        (25.0, RasterPath::Trace(ScanDir::Down)),
        (-40.0, RasterPath::Counter),
    ] {
        let mut r = raster(17, 13, angle, path);
        r.line_time_s = Some(0.05);
        let (stat, stat_first) = coordinate_map(&field, &r).unwrap();
        for half in [dynamic::Half::Trace, dynamic::Half::Retrace] {
            let (dynm, first) = dynamic::dynamic_map(&field, &r, &null, half).unwrap();
            // Both relative to their own first pixel: compare pixel differences.
            let origin_s = map_point(&stat, 0, 0);
            let origin_d = map_point(&dynm, 0, 0);
            for row in 0..13 {
                for column in 0..17 {
                    let a = map_point(&stat, column, row);
                    let b = map_point(&dynm, column, row);
                    let (da, db) = (
                        [a[0] - origin_s[0], a[1] - origin_s[1]],
                        [b[0] - origin_d[0], b[1] - origin_d[1]],
                    );
                    // The retrace chains its lines from the other end: on a curved field eq. (5)
                    // depends on the path, by well under a picometre here.
                    let tolerance = match half {
                        dynamic::Half::Trace => 2e-4,
                        dynamic::Half::Retrace => 1e-3,
                    };
                    assert!(
                        (da[0] - db[0]).abs() < tolerance && (da[1] - db[1]).abs() < tolerance,
                        "{path:?} {angle}° {half:?} ({column}, {row}): static {da:?}, dynamic {db:?}"
                    );
                }
            }
            assert!(first[0].is_finite() && stat_first[0].is_finite());
        }
    }
}

/// One play operator (threshold r, weight w) in a uniform field: along every trace after the
/// first, the effective input is u + w·max(u − r, u₀ + r) (the operator released at the
/// previous retrace's end u₀), so a pixel's x offset from the line's first pixel is
/// K·[(u − u₀) + w·(max(u − r, u₀ + r) − (u₀ + r))].
#[test]
fn one_play_operator_shifts_the_trace_by_its_closed_form() {
    let (k, r, w) = (0.02, 40.0, 0.05);
    let set = uniform(k, k, 0.0);
    let field = set.planes[0].field(Route::Products);
    let op = spm_correction::hysteresis::PlayHysteresis {
        thresholds_counts: vec![r],
        weights: vec![w],
    };
    let d = dynamics_of(op, 0.0);
    let mut rr = raster(33, 5, 0.0, RasterPath::Trace(ScanDir::Up));
    rr.line_time_s = Some(0.1);
    let (map, _) = dynamic::dynamic_map(&field, &rr, &d, dynamic::Half::Trace).unwrap();
    let step = rr.step_x_counts;
    // Map rows are bottom-up; every line but the first acquired (the bottom one, map row 0).
    for map_row in 1..5 {
        let x0 = map_point(&map, 0, map_row)[0];
        for column in 0..33 {
            let du = step * column as f64;
            let y = (du - r).max(r) - r; // relative to u₀
            let want = k * (du + w * y);
            let got = map_point(&map, column, map_row)[0] - x0;
            assert!(
                (got - want).abs() < 1e-9,
                "row {map_row} col {column}: {got} vs {want}"
            );
        }
    }
    // The static map lacks exactly the operator's part: K·w·(L − 2r) over the line.
    let (stat, _) = coordinate_map(&field, &rr).unwrap();
    let kink = map_point(&map, 32, 2)[0] - map_point(&map, 0, 2)[0];
    let flat = map_point(&stat, 32, 2)[0] - map_point(&stat, 0, 2)[0];
    let part = k * w * (32.0 * step - 2.0 * r);
    assert!(
        (kink - flat - part).abs() < 1e-9,
        "{kink} vs {flat} + {part}"
    );
}

/// `correct --ruler` on a file with both halves: each half's lines are bent along the line by
/// its own hysteresis, mirrored in the other half (`e = ±(0.06, 0.03)·u²` nm, u the place
/// along the line). Each half must come out on its own sample points (to a fifth of the bend,
/// a constant offset aside); the trace's estimate applied to the retrace would leave twice the
/// bend there.
#[test]
fn the_ruler_fits_each_half_on_its_own_atoms() {
    let (n, k) = (129, 0.002); // 10 counts per pixel: 0.02 nm, 12 pixels per lattice constant
    let mut set = uniform(k, k, 0.0);
    set.provenance.nominal_nm_per_count = Some(k);
    let dynamics = dynamics_of(spm_correction::hysteresis::PlayHysteresis::none(), 0.005);
    set.dynamics = Some(dynamics.clone());
    let field = set.planes[0].field(Route::Products);
    let mut r = raster(n, n, 0.0, RasterPath::Trace(ScanDir::Up));
    r.line_time_s = Some(0.1);
    let bend = |half: dynamic::Half, column: usize| -> [f64; 2] {
        let u = (column as f64 - 64.0) / 128.0;
        let sign = if half == dynamic::Half::Trace {
            1.0
        } else {
            -1.0
        };
        [sign * 0.06 * u * u, sign * 0.03 * u * u]
    };
    // Per half: the sample point of every pixel (map order) and the channel in display order.
    let mut truth = Vec::new();
    let mut channels = Vec::new();
    for (half, direction) in [
        (dynamic::Half::Trace, Direction::Forward),
        (dynamic::Half::Retrace, Direction::Backward),
    ] {
        let (map, _) = dynamic::dynamic_map(&field, &r, &dynamics, half).unwrap();
        let mut points = Vec::with_capacity(n * n);
        let mut display = vec![0.0; n * n];
        for row in 0..n {
            for column in 0..n {
                let p = map_point(&map, column, row);
                let e = bend(half, column);
                let q = [p[0] - e[0], p[1] - e[1]];
                display[(n - 1 - row) * n + column] = crate::ruler::tests::surface(q[0], q[1], 0.3);
                points.push(q);
            }
        }
        truth.push(points);
        channels.push(Channel::new("Z", direction, "m", n, n, display).unwrap());
    }
    let file = SpmFile {
        source: PathBuf::from("halves.gsf"),
        format: Format::Gsf,
        channels,
        header: Vec::new(),
        scan_dir: None,
        line_time_s: Some(0.1),
        recorded: None,
    };
    let options = ApplyOptions {
        ruler: Some(crate::ruler::LatticeRuler::hopg()),
        ..nominal(k)
    };
    let selected: Vec<&Channel> = file.channels.iter().collect();
    let maps = maps_for(&file, &set, &options, &field, &r, &selected).unwrap();
    let other = maps.other_half.as_ref().map(|o| &o.0).unwrap();
    // What is left of the bend, a constant offset removed, against the bend itself.
    let left = |map: &CoordinateMap, points: &[[f64; 2]]| -> f64 {
        let d: Vec<[f64; 2]> = points
            .iter()
            .enumerate()
            .map(|(i, q)| {
                let p = map_point(map, i % n, i / n);
                [p[0] - q[0], p[1] - q[1]]
            })
            .collect();
        crate::ruler::tests::spread_of(&d)
    };
    let bent: Vec<[f64; 2]> = (0..n * n)
        .map(|i| bend(dynamic::Half::Trace, i % n))
        .collect();
    let bend_rms = crate::ruler::tests::spread_of(&bent);
    for (name, map, points) in [
        ("trace", &maps.map, &truth[0]),
        ("retrace", other, &truth[1]),
    ] {
        let rms = left(map, points);
        assert!(
            rms < 0.2 * bend_rms,
            "{name}: {rms} nm RMS left, the bend is {bend_rms} nm RMS"
        );
    }
}
