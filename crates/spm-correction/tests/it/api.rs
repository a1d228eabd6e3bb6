//! The public API around the math: surface sets, fused resampling, Kz, counter pairs, errors.
#![allow(clippy::unwrap_used)]

use spm_correction::*;
use spm_hal::{
    CountPoint, Counts, Frame, Nanometres, NmPoint, NmVelocity, ScanDirection, ScanRequest,
    Seconds, TraceHalf,
};
use spm_regression::{Polynomial2, n_terms};

fn surface(base: f64, degree: u32, seed: f64) -> FittedSurface {
    let c = (0..n_terms(degree))
        .map(|k| {
            if k == 0 {
                base
            } else {
                base * 0.03 * ((k as f64 + seed) * 1.3).sin()
            }
        })
        .collect();
    FittedSurface::new(
        Polynomial2::new(degree, (10_000.0, 10_000.0), (10_000.0, 10_000.0), c).unwrap(),
        base * 0.001,
    )
}

fn plane(z_counts: f64) -> PlaneSurfaces {
    PlaneSurfaces {
        z_counts,
        n_records: 400,
        kx_nm_per_count: surface(0.0125, 3, 0.0),
        ky_nm_per_count: surface(0.0121, 2, 1.0),
        alpha_rad: surface(0.03, 2, 2.0),
        kyx_nm_per_count: surface(0.0004, 3, 3.0),
        kyy_nm_per_count: surface(0.0121, 3, 4.0),
        kz_nm_per_count: Some(surface(0.002, 1, 5.0)),
        bowl_z_counts: None,
        calibrated_region_counts: None,
        form: spm_correction::SurfaceForm::Independent,
    }
}

fn set() -> SurfaceSet {
    SurfaceSet::new(
        Provenance {
            scanner_id: "sim-hopg".into(),
            fit_since: Some("2026-11-01T00:00:00Z".into()),
            fit_until: None,
            n_records: 800,
            ..Provenance::default()
        },
        vec![plane(0.0), plane(50_000.0)],
    )
    .unwrap()
}

/// `result` is an error matching `expected`.
fn check<T: std::fmt::Debug>(
    result: Result<T, CorrectionError>,
    expected: fn(&CorrectionError) -> bool,
) {
    match result {
        Err(e) => assert!(expected(&e), "unexpected error {e:?}"),
        Ok(v) => panic!("expected an error, got {v:?}"),
    }
}

#[test]
fn surface_sets_round_trip_through_json_and_pick_the_nearest_plane() {
    let s = set();
    let text = s.to_json_string().unwrap();
    let back = SurfaceSet::from_json_str(&text).unwrap();
    assert_eq!(back, s);
    assert_eq!(s.plane_nearest(20_000.0).unwrap().z_counts, 0.0);
    assert_eq!(s.plane_nearest(30_000.0).unwrap().z_counts, 50_000.0);
    let (lo, hi, w) = s.bracketing_planes(12_500.0).unwrap();
    assert_eq!((lo.z_counts, hi.z_counts, w), (0.0, 50_000.0, 0.25));
    check(SurfaceSet::new(Provenance::default(), vec![]), |e| {
        matches!(e, CorrectionError::EmptySurfaces)
    });
    check(SurfaceSet::from_json_str("{"), |e| {
        matches!(e, CorrectionError::Json(_))
    });
    check(
        SurfaceSet::new(Provenance::default(), vec![plane(1.0), plane(1.0)]),
        |e| matches!(e, CorrectionError::InvalidSurfaces(_)),
    );
    check(s.plane_nearest(f64::NAN), |e| {
        matches!(e, CorrectionError::NonFinite { .. })
    });
    let mut bad = plane(0.0);
    bad.kx_nm_per_count.degree = 7;
    check(SurfaceSet::new(Provenance::default(), vec![bad]), |e| {
        matches!(e, CorrectionError::InvalidSurfaces(_))
    });
    // A blend of the two planes at w = 0 is the lower plane.
    let blend = BlendedField {
        lower: s.planes[0].field(Route::Products),
        upper: s.planes[1].field(Route::Products),
        weight_upper: 0.0,
    };
    let g = RasterGeometry::new(CountPoint::from_counts(100.0, 200.0), Counts(50.0), 6, 5).unwrap();
    let a = correct_raster(
        &blend,
        &g,
        ScanDirection::Direct,
        &Integration::default(),
        Parallelism::Sequential,
    )
    .unwrap();
    let b = correct_raster(
        &s.planes[0].field(Route::Products),
        &g,
        ScanDirection::Direct,
        &Integration::default(),
        Parallelism::Sequential,
    )
    .unwrap();
    for (u, v) in a.x_nm().iter().zip(b.x_nm()) {
        assert!((u - v).abs() < 1e-12);
    }
}

#[test]
fn fused_correction_and_resampling_equals_the_two_steps_on_every_thread_count() {
    let s = set();
    let g = RasterGeometry::new(
        CountPoint::from_counts(2000.0, 3000.0),
        Counts(40.0),
        70,
        50,
    )
    .unwrap();
    let image: Vec<f64> = (0..70 * 50)
        .map(|k| ((k % 70) as f64 * 0.3).sin() + (k / 70) as f64 * 0.1)
        .collect();
    for route in [Route::Exact, Route::Products] {
        let field = s.planes[0].field(route);
        for direction in [ScanDirection::Direct, ScanDirection::Counter] {
            for interpolation in [Interpolation::Bilinear, Interpolation::CatmullRom] {
                let map = correct_raster(
                    &field,
                    &g,
                    direction,
                    &Integration::default(),
                    Parallelism::Sequential,
                )
                .unwrap();
                let grid = OutputGrid::covering(&map, None).unwrap();
                let two_step =
                    resample(&image, &map, &grid, interpolation, Parallelism::Sequential).unwrap();
                for par in [
                    Parallelism::Sequential,
                    Parallelism::Threads(2),
                    Parallelism::AllCores,
                ] {
                    let (fgrid, fused) = correct_and_resample(
                        &field,
                        &g,
                        direction,
                        &Integration::default(),
                        &image,
                        None,
                        interpolation,
                        par,
                    )
                    .unwrap();
                    assert_eq!(fgrid.columns, grid.columns);
                    assert_eq!(fgrid.rows, grid.rows);
                    let nan = fused.iter().filter(|v| v.is_nan()).count();
                    assert!(nan < fused.len() / 2, "{nan} NaN of {}", fused.len());
                    for (a, b) in fused.iter().zip(&two_step) {
                        assert!(a.is_nan() == b.is_nan() && (a.is_nan() || (a - b).abs() < 1e-9));
                    }
                }
            }
        }
    }
}

#[test]
fn heights_go_through_kz_and_the_bowl() {
    let mut p = PlaneSurfaces::constant(1000.0, 0.01, 0.01, 0.0).unwrap();
    let g = RasterGeometry::new(CountPoint::from_counts(0.0, 0.0), Counts(10.0), 3, 2).unwrap();
    let z = vec![1000.0, 1010.0, 1020.0, 990.0, f64::NAN, 1000.0];
    check(heights_nm(&p, &g, &z), |e| {
        matches!(e, CorrectionError::MissingSurface("kz_nm_per_count"))
    });
    p.kz_nm_per_count = Some(FittedSurface::constant(0.05).unwrap());
    let h = heights_nm(&p, &g, &z).unwrap();
    assert_eq!(h[..4], [0.0, 0.5, 1.0, -0.5]);
    assert!(h[4].is_nan());
    // A bowl z = 1000 + x/10 counts: heights relative to it.
    p.bowl_z_counts = Some(FittedSurface::new(
        Polynomial2::from_raw_coefficients(1, vec![1000.0, 0.0, 0.1]).unwrap(),
        0.0,
    ));
    let h = heights_nm(&p, &g, &z).unwrap();
    assert!((h[1] - 0.45).abs() < 1e-12 && (h[2] - 0.9).abs() < 1e-12);
    check(heights_nm(&p, &g, &z[..5]), |e| {
        matches!(e, CorrectionError::SizeMismatch { .. })
    });
    check(heights_nm(&p, &g, &[f64::INFINITY; 6]), |e| {
        matches!(e, CorrectionError::NonFinite { .. })
    });
}

#[test]
fn drift_of_a_counter_scanned_pair_is_recovered_from_common_features() {
    // Identity scanner (1 nm per count), drift 0.08 nm/s along x and −0.03 nm/s along y.
    let v = NmVelocity {
        x_nm_per_s: 0.08,
        y_nm_per_s: -0.03,
    };
    let request = ScanRequest {
        origin: CountPoint::from_counts(0.0, 0.0),
        pixel_step: Counts(1.0),
        pixels_per_line: 40,
        lines: 30,
        direction: ScanDirection::Direct,
        pixel_dwell: Seconds(0.01),
        record_backward: false,
    };
    let direct = Frame::from_fn(request.clone(), Seconds(0.0), |_, _| Counts(0.0))
        .height_map(TraceHalf::Forward)
        .unwrap();
    let counter = Frame::from_fn(
        request.with_direction(ScanDirection::Counter),
        Seconds(30.0),
        |_, _| Counts(0.0),
    )
    .height_map(TraceHalf::Forward)
    .unwrap();
    let field = PlaneSurfaces::constant(0.0, 1.0, 1.0, 0.0)
        .unwrap()
        .field(Route::Exact);
    let t_ref = Seconds(10.0);
    let time_at = |m: &spm_hal::HeightMap, c: f64, r: f64| {
        // Bilinear in the pixel times, as correct_counter_pair dates features.
        let (i, j) = ((c.floor() as usize).min(38), (r.floor() as usize).min(28));
        let (fx, fy) = (c - i as f64, r - j as f64);
        let t = |a: usize, b: usize| m.time_s[b * 40 + a];
        (t(i, j) * (1.0 - fx) + t(i + 1, j) * fx) * (1.0 - fy)
            + (t(i, j + 1) * (1.0 - fx) + t(i + 1, j + 1) * fx) * fy
    };
    // Features at true positions (nm at t_ref); find where each image shows them.
    let truth = [(8.3, 6.1), (30.2, 9.7), (12.6, 22.4)];
    let locate = |m: &spm_hal::HeightMap, p: (f64, f64)| {
        let (mut c, mut r) = p;
        for _ in 0..50 {
            let t = time_at(m, c, r) - t_ref.value();
            c = p.0 + v.x_nm_per_s * t;
            r = p.1 + v.y_nm_per_s * t;
        }
        (c, r)
    };
    let matches: Vec<FeatureMatch> = truth
        .iter()
        .map(|&p| {
            let (dc, dr) = locate(&direct, p);
            let (cc, cr) = locate(&counter, p);
            FeatureMatch {
                direct_column: dc,
                direct_row: dr,
                counter_column: cc,
                counter_row: cr,
            }
        })
        .collect();
    let pair = correct_counter_pair(
        &field,
        &direct,
        &counter,
        &matches,
        t_ref,
        &Integration::default(),
        Parallelism::Sequential,
    )
    .unwrap();
    assert!((pair.drift.velocity.x_nm_per_s - 0.08).abs() < 1e-9);
    assert!((pair.drift.velocity.y_nm_per_s + 0.03).abs() < 1e-9);
    assert!(pair.drift.residual_rms_nm < 1e-9);
    for (m, p) in matches.iter().zip(truth) {
        for (map, c, r) in [
            (&pair.direct, m.direct_column, m.direct_row),
            (&pair.counter, m.counter_column, m.counter_row),
        ] {
            let q = map.interpolate(c, r).unwrap();
            assert!((q.x.value() - p.0).abs() < 1e-6 && (q.y.value() - p.1).abs() < 1e-6);
        }
    }
    // The drift-corrected direct image resamples through the general (Newton) path.
    let grid = OutputGrid::new(NmPoint::from_nm(2.0, 2.0), Nanometres(1.0), 30, 20).unwrap();
    let image: Vec<f64> = (0..1200).map(|k| (k % 40) as f64).collect();
    let out = resample(
        &image,
        &pair.direct,
        &grid,
        Interpolation::Bilinear,
        Parallelism::Sequential,
    )
    .unwrap();
    assert!(out.iter().filter(|v| v.is_finite()).count() > 300);
    check(estimate_drift(&[]), |e| {
        matches!(e, CorrectionError::DriftUndetermined(_))
    });
}

#[test]
fn bad_input_gives_typed_errors() {
    let field = PlaneSurfaces::constant(0.0, 1.0, 1.0, 0.0)
        .unwrap()
        .field(Route::Exact);
    check(
        RasterGeometry::new(CountPoint::from_counts(f64::NAN, 0.0), Counts(1.0), 2, 2),
        |e| matches!(e, CorrectionError::NonFinite { .. }),
    );
    check(
        RasterGeometry::new(CountPoint::from_counts(0.0, 0.0), Counts(0.0), 2, 2),
        |e| matches!(e, CorrectionError::InvalidArgument(_)),
    );
    check(
        RasterGeometry::new(CountPoint::from_counts(0.0, 0.0), Counts(1.0), 0, 2),
        |e| matches!(e, CorrectionError::Empty(_)),
    );
    let g = RasterGeometry::new(CountPoint::from_counts(0.0, 0.0), Counts(1.5), 4, 3).unwrap();
    check(
        correct_raster(
            &field,
            &g,
            ScanDirection::Direct,
            &Integration::Sums,
            Parallelism::Sequential,
        ),
        |e| matches!(e, CorrectionError::NonIntegerStep { .. }),
    );
    let path = [
        CountPoint::from_counts(0.0, 0.0),
        CountPoint::from_counts(2.0, 0.0),
    ];
    check(correct_unit_steps(&field, &path), |e| {
        matches!(e, CorrectionError::NotAUnitStep { index: 0, .. })
    });
    check(correct_unit_steps(&field, &[]), |e| {
        matches!(e, CorrectionError::Empty(_))
    });
    let nan_field = FnField(|_: f64, _: f64| FormCoefficients::from_lcc(f64::NAN, 1.0, 0.0));
    check(
        correct_raster(
            &nan_field,
            &g,
            ScanDirection::Direct,
            &Integration::default(),
            Parallelism::Sequential,
        ),
        |e| matches!(e, CorrectionError::NonFinite { .. }),
    );
    let map = correct_raster(
        &field,
        &g,
        ScanDirection::Direct,
        &Integration::default(),
        Parallelism::Sequential,
    )
    .unwrap();
    let grid = OutputGrid::covering(&map, None).unwrap();
    check(
        resample(
            &[0.0; 5],
            &map,
            &grid,
            Interpolation::Bilinear,
            Parallelism::Sequential,
        ),
        |e| matches!(e, CorrectionError::SizeMismatch { .. }),
    );
    check(
        resample(
            &[f64::INFINITY; 12],
            &map,
            &grid,
            Interpolation::Bilinear,
            Parallelism::Sequential,
        ),
        |e| matches!(e, CorrectionError::NonFinite { .. }),
    );
    check(
        OutputGrid::new(
            NmPoint::from_nm(0.0, 0.0),
            Nanometres(1.0),
            1 << 20,
            1 << 20,
        ),
        |e| matches!(e, CorrectionError::GridTooLarge { .. }),
    );
    // A folded map (x̄ decreasing along the line) is refused, not resampled into garbage.
    let folded = FnField(|_: f64, _: f64| FormCoefficients::from_lcc(-1.0, 1.0, 0.0));
    let map = correct_raster(
        &folded,
        &g,
        ScanDirection::Direct,
        &Integration::default(),
        Parallelism::Sequential,
    )
    .unwrap();
    let grid = OutputGrid::covering(&map, Some(Nanometres(1.0))).unwrap();
    check(
        resample(
            &[0.0; 12],
            &map,
            &grid,
            Interpolation::Bilinear,
            Parallelism::Sequential,
        ),
        |e| matches!(e, CorrectionError::NotMonotone { axis: "x", .. }),
    );
    // NaN pixels stay local: missing data, not an error.
    let map = correct_raster(
        &field,
        &g,
        ScanDirection::Direct,
        &Integration::default(),
        Parallelism::Sequential,
    )
    .unwrap();
    let grid = OutputGrid::covering(&map, None).unwrap();
    let mut img = vec![1.0; 12];
    img[0] = f64::NAN;
    let out = resample(
        &img,
        &map,
        &grid,
        Interpolation::Bilinear,
        Parallelism::Sequential,
    )
    .unwrap();
    assert!(out[0].is_nan() && out[out.len() - 1] == 1.0);
}

#[test]
fn sums_converge_to_the_integrals_and_polylines_follow_the_raster_path() {
    let s = set();
    let field = s.planes[0].field(Route::Exact);
    let g =
        RasterGeometry::new(CountPoint::from_counts(1000.0, 2000.0), Counts(200.0), 5, 4).unwrap();
    let integral = correct_raster(
        &field,
        &g,
        ScanDirection::Direct,
        &Integration::default(),
        Parallelism::Sequential,
    )
    .unwrap();
    let sums = correct_raster(
        &field,
        &g,
        ScanDirection::Direct,
        &Integration::Sums,
        Parallelism::Sequential,
    )
    .unwrap();
    // Eq. (8) vs eq. (9): the right-endpoint sum differs by ~½·Σ ∂K per unit step, tiny.
    for (a, b) in integral.x_nm().iter().zip(sums.x_nm()) {
        assert!((a - b).abs() < 1e-5 * (1.0 + a.abs()), "{a} {b}");
    }
    // The raster path as a polyline: up the line-start column, then along the line.
    let (i, j) = (4usize, 3usize);
    let path = [
        CountPoint::from_counts(1000.0, 2000.0),
        CountPoint::from_counts(1000.0, 2000.0 + 200.0 * j as f64),
        CountPoint::from_counts(1000.0 + 200.0 * i as f64, 2000.0 + 200.0 * j as f64),
    ];
    let p = correct_polyline(&field, &path, &Quadrature::standard()).unwrap();
    let q = integral.point(i, j).unwrap();
    assert!((p[2].x.value() - q.x.value()).abs() < 1e-10);
    assert!((p[2].y.value() - q.y.value()).abs() < 1e-10);
}
