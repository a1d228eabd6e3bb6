//! Vibration, interlace and shear gradient against their closed forms: the Z
//! reading of every pixel of an ideal instrument (linear scanner, no noise,
//! ideal feedback) is the surface height at the point the closed form puts the
//! tip on, and the oracle's positions follow the formulas.
#![allow(clippy::unwrap_used)]

use spm_hal::{
    CountPoint, Counts, Frame, Microscope, NmPoint, ScanDirection, ScanRequest, Seconds, TraceHalf,
};
use spm_sim::{LatticeConfig, SimConfig, Simulator, SurfaceConfig};

const K_NM_PER_COUNT: f64 = 0.02;
const KZ_NM_PER_COUNT: f64 = 0.004;

/// The ideal instrument over a smooth lattice whose height varies along x and y
/// on the scale of a few pixels (so a misplaced tip shows in Z).
fn ideal() -> SimConfig {
    let mut c = SimConfig::ideal();
    c.surface = SurfaceConfig::HexLattice(LatticeConfig {
        lattice_constant_nm: 6.0,
        feature_height_nm: 0.2,
        feature_sigma_nm: 1.2,
        rotation_deg: 11.0,
    });
    c
}

fn request(direction: ScanDirection) -> ScanRequest {
    let mut r = ScanRequest::centred_square(
        CountPoint::from_counts(0.0, 0.0),
        Counts(40.0),
        24,
        Seconds(1e-3),
    )
    .with_direction(direction);
    r.record_backward = true;
    r
}

/// Largest |measured − expected| (nm) over every pixel of one half, the expected
/// height being the surface at `tip(commanded, t)` (nm, scanner frame = sample).
fn worst_error_nm(
    sim: &Simulator,
    frame: &Frame,
    half: TraceHalf,
    tip: &dyn Fn(CountPoint, f64) -> [f64; 2],
) -> f64 {
    let map = frame.height_map(half).unwrap();
    let mut worst: f64 = 0.0;
    for row in 0..map.rows {
        for column in 0..map.columns {
            let u = CountPoint::from_counts(
                map.origin.x.value() + map.pixel_step.value() * column as f64,
                map.origin.y.value() + map.pixel_step.value() * row as f64,
            );
            let k = row * map.columns + column;
            let p = tip(u, map.time_s[k]);
            let expected = sim.oracle().surface_height(NmPoint::from_nm(p[0], p[1]));
            worst = worst.max((map.z_counts[k] * KZ_NM_PER_COUNT - expected).abs());
        }
    }
    worst
}

fn check_vibration(amplitude_nm: [f64; 2], frequency_hz: f64, phase_rad: [f64; 2]) {
    let mut c = ideal();
    c.drift.vibration_amplitude_x_nm = amplitude_nm[0];
    c.drift.vibration_amplitude_y_nm = amplitude_nm[1];
    c.drift.vibration_frequency_hz = frequency_hz;
    c.drift.vibration_phase_x_rad = phase_rad[0];
    c.drift.vibration_phase_y_rad = phase_rad[1];
    let mut sim = Simulator::new(c).unwrap();
    let w = std::f64::consts::TAU * frequency_hz;
    let vib = |t: f64| {
        [
            amplitude_nm[0] * (w * t + phase_rad[0]).cos(),
            amplitude_nm[1] * (w * t + phase_rad[1]).cos(),
        ]
    };
    for t in [0.0, 0.0123, 1.7, 33.3] {
        let d = sim.oracle().drift_displacement(Seconds(t));
        let v = vib(t);
        assert!((d.x.value() - v[0]).abs() < 1e-12 && (d.y.value() - v[1]).abs() < 1e-12);
    }
    for direction in [ScanDirection::Direct, ScanDirection::Counter] {
        let frame = sim.scan(&request(direction)).unwrap();
        for half in [TraceHalf::Forward, TraceHalf::Backward] {
            let tip = |u: CountPoint, t: f64| {
                let v = vib(t);
                [
                    K_NM_PER_COUNT * u.x.value() + v[0],
                    K_NM_PER_COUNT * u.y.value() + v[1],
                ]
            };
            let e = worst_error_nm(&sim, &frame, half, &tip);
            assert!(e < 1e-9, "{direction:?} {half:?}: {e} nm");
            // The same image without the vibration is far off: the test can fail.
            let still = |u: CountPoint, _t: f64| {
                [K_NM_PER_COUNT * u.x.value(), K_NM_PER_COUNT * u.y.value()]
            };
            assert!(worst_error_nm(&sim, &frame, half, &still) > 1e-3);
        }
    }
}

#[test]
fn the_vibration_moves_the_tip_by_its_cosine() {
    check_vibration([0.8, 0.0], 7.3, [0.0, 0.0]);
    check_vibration([0.5, 1.1], 31.0, [1.2, -2.5]);
}

fn check_interlace(advance_counts: f64, direction: ScanDirection) {
    let mut c = ideal();
    c.instrument.retrace_slow_axis_advance_counts = advance_counts;
    let mut sim = Simulator::new(c).unwrap();
    let frame = sim.scan(&request(direction)).unwrap();
    // Along the slow-scan direction: +y for direct, −y for counter rasters.
    let along = match direction {
        ScanDirection::Direct => 1.0,
        ScanDirection::Counter => -1.0,
    };
    for (half, dy) in [
        (TraceHalf::Forward, 0.0),
        (TraceHalf::Backward, along * advance_counts),
    ] {
        let tip = |u: CountPoint, _t: f64| {
            [
                K_NM_PER_COUNT * u.x.value(),
                K_NM_PER_COUNT * (u.y.value() + dy),
            ]
        };
        let e = worst_error_nm(&sim, &frame, half, &tip);
        assert!(e < 1e-9, "{direction:?} {half:?}: {e} nm");
    }
    // The scan ends on the second half of its last line, commanded y + advance.
    let last_y = frame
        .request
        .commanded_position(TraceHalf::Backward, 23, 23)
        .y
        .value();
    let effective = sim.oracle().effective_input_now();
    assert!((effective.y.value() - (last_y + along * advance_counts)).abs() < 1e-9);
}

#[test]
fn the_interlace_advances_the_second_half_of_every_line_along_the_slow_scan() {
    for direction in [ScanDirection::Direct, ScanDirection::Counter] {
        check_interlace(20.0, direction);
        check_interlace(-7.5, direction);
    }
}

/// A ramped slow axis: the command moves on `ramp_counts` along the slow-scan direction
/// through every line pair, linearly in time (the first half's first pixel where a stepped
/// raster puts the line).
fn check_ramp(ramp_counts: f64, direction: ScanDirection) {
    let mut c = ideal();
    c.instrument.slow_axis_ramp_counts = ramp_counts;
    let mut sim = Simulator::new(c).unwrap();
    let r = request(direction);
    let frame = sim.scan(&r).unwrap();
    let along = match direction {
        ScanDirection::Direct => 1.0,
        ScanDirection::Counter => -1.0,
    };
    let (nx, dwell) = (r.pixels_per_line as f64, r.pixel_dwell.value());
    let start = frame.forward.time_s[0] - 0.5 * dwell;
    for half in [TraceHalf::Forward, TraceHalf::Backward] {
        // The pixel's place in time within its line pair, from its time.
        let tip = |u: CountPoint, t: f64| {
            let k = ((t - start) / dwell - 0.5).round().rem_euclid(2.0 * nx);
            let dy = along * ramp_counts * k / (2.0 * nx);
            [
                K_NM_PER_COUNT * u.x.value(),
                K_NM_PER_COUNT * (u.y.value() + dy),
            ]
        };
        let e = worst_error_nm(&sim, &frame, half, &tip);
        assert!(e < 1e-9, "{direction:?} {half:?}: {e} nm");
        // The stepped raster is far off: the test can fail.
        let stepped =
            |u: CountPoint, _t: f64| [K_NM_PER_COUNT * u.x.value(), K_NM_PER_COUNT * u.y.value()];
        assert!(
            worst_error_nm(&sim, &frame, half, &stepped) > 1e-3,
            "{half:?}"
        );
    }
}

#[test]
fn a_ramped_slow_axis_moves_on_through_every_line_pair() {
    for direction in [ScanDirection::Direct, ScanDirection::Counter] {
        check_ramp(40.0, direction);
        check_ramp(-15.0, direction);
    }
}

#[test]
fn the_interlace_is_visible_when_on() {
    // Without the closed form's shift the backward image does not match.
    let mut c = ideal();
    c.instrument.retrace_slow_axis_advance_counts = 20.0;
    let mut sim = Simulator::new(c).unwrap();
    let frame = sim.scan(&request(ScanDirection::Direct)).unwrap();
    let tip = |u: CountPoint, _t: f64| [K_NM_PER_COUNT * u.x.value(), K_NM_PER_COUNT * u.y.value()];
    assert!(worst_error_nm(&sim, &frame, TraceHalf::Backward, &tip) > 1e-3);
}

fn check_shear(gx: f64, gy: f64) {
    let mut c = ideal();
    c.scanner.shear_gradient_x = gx;
    c.scanner.shear_gradient_y = gy;
    let h = c.instrument.lateral_half_range_counts;
    let mut sim = Simulator::new(c).unwrap();
    let sheared = |u: [f64; 2]| {
        let p = u[0] * u[1] / h;
        [
            K_NM_PER_COUNT * (u[0] + gx * p),
            K_NM_PER_COUNT * (u[1] + gy * p),
        ]
    };
    // The static map and its Jacobian against the closed form.
    for u in [[0.0, 0.0], [20000.0, -15000.0], [-31000.0, -30000.0]] {
        let p = sim
            .oracle()
            .static_map(CountPoint::from_counts(u[0], u[1]), Counts(0.0));
        let e = sheared(u);
        assert!((p.x.value() - e[0]).abs() < 1e-9 && (p.y.value() - e[1]).abs() < 1e-9);
        let j = sim
            .oracle()
            .jacobian(CountPoint::from_counts(u[0], u[1]), Counts(0.0));
        let expected = [
            [
                K_NM_PER_COUNT * (1.0 + gx * u[1] / h),
                K_NM_PER_COUNT * gx * u[0] / h,
            ],
            [
                K_NM_PER_COUNT * gy * u[1] / h,
                K_NM_PER_COUNT * (1.0 + gy * u[0] / h),
            ],
        ];
        for a in 0..2 {
            for b in 0..2 {
                assert!((j[a][b] - expected[a][b]).abs() < 1e-15, "J[{a}][{b}]");
            }
        }
        // The oracle's inverse finds the command back.
        let back = sim
            .oracle()
            .commanded_for_sample_point(NmPoint::from_nm(e[0], e[1]))
            .unwrap();
        assert!((back.x.value() - u[0]).abs() < 1e-6 && (back.y.value() - u[1]).abs() < 1e-6);
    }
    // A scan off the field centre, where ux·uy is large.
    let mut r = request(ScanDirection::Direct);
    r.origin = CountPoint::from_counts(15000.0, -20000.0);
    let frame = sim.scan(&r).unwrap();
    let tip = |u: CountPoint, _t: f64| sheared([u.x.value(), u.y.value()]);
    for half in [TraceHalf::Forward, TraceHalf::Backward] {
        let e = worst_error_nm(&sim, &frame, half, &tip);
        assert!(e < 1e-9, "{half:?}: {e} nm");
    }
    let plain =
        |u: CountPoint, _t: f64| [K_NM_PER_COUNT * u.x.value(), K_NM_PER_COUNT * u.y.value()];
    assert!(worst_error_nm(&sim, &frame, TraceHalf::Forward, &plain) > 1e-3);
}

#[test]
fn the_shear_gradient_adds_g_ux_uy_over_h_to_the_input() {
    check_shear(0.05, 0.0);
    check_shear(-0.03, 0.08);
}

#[test]
fn the_new_fields_are_validated_with_their_paths() {
    type Edit = fn(&mut SimConfig);
    let cases: [(&str, Edit); 7] = [
        ("drift.vibration_amplitude_x_nm", |c| {
            c.drift.vibration_amplitude_x_nm = -1.0
        }),
        ("drift.vibration_frequency_hz", |c| {
            c.drift.vibration_frequency_hz = f64::NAN
        }),
        ("drift.vibration_phase_y_rad", |c| {
            c.drift.vibration_phase_y_rad = 7.0
        }),
        ("scanner.shear_gradient_y", |c| {
            c.scanner.shear_gradient_y = 0.5
        }),
        ("instrument.retrace_slow_axis_advance_counts", |c| {
            c.instrument.retrace_slow_axis_advance_counts = 9000.0
        }),
        ("instrument.slow_axis_ramp_counts", |c| {
            c.instrument.slow_axis_ramp_counts = 9000.0
        }),
        ("instrument.slow_axis_ramp_counts", |c| {
            c.instrument.slow_axis_ramp_counts = f64::NAN
        }),
    ];
    for (field, edit) in cases {
        let mut c = SimConfig::ideal();
        edit(&mut c);
        let e = c.validate_with_prefix("backend.sim.").unwrap_err();
        assert_eq!(e.field, format!("backend.sim.{field}"));
    }
}
