//! `Simulator::scan_sine_driven`: fast SPM's resonant scan program, the fast axis driven by a
//! sine over ±β of phase per line, the pixels equidistant in time.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_hal::{CountPoint, Counts, Microscope, ScanDirection, ScanRequest, Seconds};
use spm_sim::{SimConfig, Simulator, SineDrive};

const PIXELS: usize = 16;
const LINES: usize = 8;
const STEP_COUNTS: f64 = 2.0;
const DWELL_S: f64 = 1e-4;

fn request(direction: ScanDirection) -> ScanRequest {
    ScanRequest {
        origin: CountPoint::from_counts(-100.0, 250.0),
        pixel_step: Counts(STEP_COUNTS),
        pixels_per_line: PIXELS as u32,
        lines: LINES as u32,
        direction,
        pixel_dwell: Seconds(DWELL_S),
        record_backward: true,
    }
}

fn drive(beta_rad: f64) -> SineDrive {
    SineDrive {
        phase_at_line_end_rad: beta_rad,
    }
}

/// The closed form: column k at c + (W/sin β)·sin(β·ξ_k), ξ_k = (2k + 1 − N)/N, c the
/// raster's centre, W = N·step/2 its half-width.
fn sine_x_counts(column: usize, beta_rad: f64) -> f64 {
    let n = PIXELS as f64;
    let centre = -100.0 + 0.5 * (n - 1.0) * STEP_COUNTS;
    let half_width = 0.5 * n * STEP_COUNTS;
    let xi = (2.0 * column as f64 + 1.0 - n) / n;
    centre + half_width / beta_rad.sin() * (beta_rad * xi).sin()
}

#[test]
fn a_phase_of_zero_is_the_plain_scan_bit_for_bit() {
    let config = SimConfig::room_temperature_tube().without_random_faults();
    for direction in [ScanDirection::Direct, ScanDirection::Counter] {
        let mut a = Simulator::new(config.clone()).unwrap();
        let mut b = Simulator::new(config.clone()).unwrap();
        let mut r = request(direction);
        assert_eq!(
            a.scan(&r).unwrap(),
            b.scan_sine_driven(&r, drive(0.0)).unwrap()
        );
        // The unrecorded retrace (skipped in closed form on the plain raster) too.
        r.record_backward = false;
        assert_eq!(
            a.scan(&r).unwrap(),
            b.scan_sine_driven(&r, drive(0.0)).unwrap()
        );
        assert_eq!(a.now().unwrap(), b.now().unwrap());
    }
}

/// As β → 0 the sine tends to the linear raster: W·sin(βξ)/sin β − W·ξ = O(β²·W), so at
/// β = 1e-4 rad every pixel is commanded within 1e-7 counts of the raster's, and every
/// physics (hysteresis, creep, drift, noise, feedback, DAC rounding of the tube config) gives
/// the plain scan's heights within 1e-6 counts and its pixel times within 1e-12 s.
#[test]
fn a_small_phase_tends_to_the_linear_raster() {
    let beta = 1e-4;
    let r = request(ScanDirection::Direct);
    let mut ideal = Simulator::new(SimConfig::ideal()).unwrap();
    ideal.record_tip_positions(true);
    ideal.scan_sine_driven(&r, drive(beta)).unwrap();
    let inputs = ideal.oracle().last_scan_effective_inputs();
    assert_eq!(inputs.len(), PIXELS * LINES);
    for (k, p) in inputs.iter().enumerate() {
        let x = -100.0 + STEP_COUNTS * (k % PIXELS) as f64;
        assert!((p.x.value() - x).abs() < 1e-7, "pixel {k}: {p:?} vs {x}");
    }
    let config = SimConfig::room_temperature_tube().without_random_faults();
    let mut a = Simulator::new(config.clone()).unwrap();
    let mut b = Simulator::new(config).unwrap();
    let (fa, fb) = (
        a.scan(&r).unwrap(),
        b.scan_sine_driven(&r, drive(beta)).unwrap(),
    );
    let (ba, bb) = (fa.backward.unwrap(), fb.backward.unwrap());
    for (za, zb) in fa
        .forward
        .z_counts
        .iter()
        .zip(&fb.forward.z_counts)
        .chain(ba.z_counts.iter().zip(&bb.z_counts))
    {
        assert!((za - zb).abs() < 1e-6, "{za} vs {zb}");
    }
    // The approach to the first pixel is 1e-7 counts longer or shorter.
    for (ta, tb) in fa.forward.time_s.iter().zip(&fb.forward.time_s) {
        assert!((ta - tb).abs() < 1e-12, "{ta} vs {tb}");
    }
}

/// With a linear scanner (no hysteresis, no creep: the ideal config) the tip follows the
/// sine: every forward pixel's effective input is c + A·sin(β·ξ_k) and its tip position
/// 0.02 nm/count of it; the pixels stay equidistant in time (one dwell apart, a line every
/// 2N dwells), and the frame's request is the nominal raster.
#[test]
fn the_tip_follows_the_sine_at_pixels_equidistant_in_time() {
    let beta = 1.3;
    for direction in [ScanDirection::Direct, ScanDirection::Counter] {
        let mut sim = Simulator::new(SimConfig::ideal()).unwrap();
        sim.record_tip_positions(true);
        let r = request(direction);
        let frame = sim.scan_sine_driven(&r, drive(beta)).unwrap();
        assert_eq!(frame.request, r);
        let inputs = sim.oracle().last_scan_effective_inputs();
        let tips = sim.oracle().last_scan_tip_positions();
        assert_eq!(inputs.len(), PIXELS * LINES);
        for line in 0..LINES {
            for pixel in 0..PIXELS {
                let (column, row) = r.geometric_index(spm_hal::TraceHalf::Forward, line, pixel);
                let k = line * PIXELS + pixel;
                let x = sine_x_counts(column, beta);
                let y = 250.0 + STEP_COUNTS * row as f64;
                let p = inputs[k];
                assert!(
                    (p.x.value() - x).abs() < 1e-9 && (p.y.value() - y).abs() < 1e-9,
                    "line {line} pixel {pixel}: {p:?} vs ({x}, {y})"
                );
                assert!((tips[k].x.value() - 0.02 * x).abs() < 1e-9, "{:?}", tips[k]);
            }
        }
        let t = &frame.forward.time_s;
        for line in 0..LINES {
            for pixel in 1..PIXELS {
                let k = line * PIXELS + pixel;
                assert!((t[k] - t[k - 1] - DWELL_S).abs() < 1e-12);
            }
            if line > 0 {
                let dt = t[line * PIXELS] - t[(line - 1) * PIXELS];
                assert!((dt - 2.0 * PIXELS as f64 * DWELL_S).abs() < 1e-12);
            }
        }
    }
}

/// The line's ends meet the raster's ends: the sine passes c ± W at ξ = ±1, so the outer
/// pixels lie between the linear raster's and the frame edge (half a step further out).
#[test]
fn the_sine_compresses_the_line_ends_and_meets_the_frame_edge() {
    for beta in [0.5, 1.2, 1.5, std::f64::consts::FRAC_PI_2] {
        let n = PIXELS as f64;
        let centre = -100.0 + 0.5 * (n - 1.0) * STEP_COUNTS;
        let linear_end = centre + 0.5 * (n - 1.0) * STEP_COUNTS;
        let edge = centre + 0.5 * n * STEP_COUNTS;
        let end = sine_x_counts(PIXELS - 1, beta);
        assert!(linear_end < end && end < edge, "β {beta}: {end}");
        // Spacing shrinks from the centre to the ends as cos(β·ξ).
        let centre_step = sine_x_counts(PIXELS / 2, beta) - sine_x_counts(PIXELS / 2 - 1, beta);
        let end_step = end - sine_x_counts(PIXELS - 2, beta);
        assert!(end_step < centre_step);
    }
}

/// The retrace runs the other half-period with ξ reversed, the same map: with nothing
/// time-dependent (the ideal config: no drift, noise or feedback lag) each retrace reads the
/// trace's heights in reverse.
#[test]
fn the_retrace_runs_the_same_map_reversed() {
    let mut config = SimConfig::ideal();
    config.surface = spm_sim::SurfaceConfig::HexLattice(spm_sim::LatticeConfig {
        lattice_constant_nm: 0.2,
        feature_height_nm: 0.1,
        feature_sigma_nm: 0.04,
        rotation_deg: 7.0,
    });
    let mut sim = Simulator::new(config).unwrap();
    let frame = sim
        .scan_sine_driven(&request(ScanDirection::Direct), drive(1.4))
        .unwrap();
    let back = frame.backward.unwrap();
    for line in 0..LINES {
        for pixel in 0..PIXELS {
            let f = frame.forward.z_counts[line * PIXELS + pixel];
            let b = back.z_counts[line * PIXELS + PIXELS - 1 - pixel];
            assert!(
                (f - b).abs() < 1e-9,
                "line {line} pixel {pixel}: {f} vs {b}"
            );
        }
    }
    // Not flat: the heights vary along the line.
    let z = &frame.forward.z_counts[..PIXELS];
    let spread = z.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
        - z.iter().cloned().fold(f64::INFINITY, f64::min);
    assert!(spread > 1.0, "{spread}");
}

#[test]
fn a_phase_outside_zero_to_a_quarter_period_is_refused_and_the_sine_must_stay_inside() {
    let mut sim = Simulator::new(SimConfig::ideal()).unwrap();
    let r = request(ScanDirection::Direct);
    for beta in [-0.1, 1.6, f64::NAN, f64::INFINITY] {
        let e = sim.scan_sine_driven(&r, drive(beta)).unwrap_err();
        assert!(matches!(e, spm_sim::SimError::InvalidRequest { .. }), "{e}");
    }
    // The raster's last pixel at the field's edge: the sine's lies beyond it.
    let h = sim.capabilities().field_max.x.value();
    let mut edge = r.clone();
    edge.origin = CountPoint::from_counts(h - STEP_COUNTS * (PIXELS - 1) as f64, 0.0);
    sim.scan(&edge).unwrap();
    let e = sim.scan_sine_driven(&edge, drive(1.3)).unwrap_err();
    assert_eq!(
        spm_hal::Error::kind(&e),
        spm_hal::ErrorKind::OutOfRange,
        "{e}"
    );
}
