//! NanonisMicroscope with a frame angle (issue 26): the counts axes are the controller's X
//! and Y turned by it, so every move and every scan pixel lands where the turned counts
//! say — judged by the simulator behind nanonis-sim (its commanded positions, the
//! effective inputs it records; an ideal instrument, where they are the commands).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_hal::{CountPoint, Counts, Microscope, MoveRequest, ScanDirection, ScanRequest, Seconds};
use spm_nanonis::{NanonisConfig, NanonisMicroscope};

fn config(port: u16, frame_angle_deg: f64) -> NanonisConfig {
    NanonisConfig {
        frame_angle_deg,
        ..spm_nanonis_sim::loopback_config(port)
    }
}

/// The controller's (simulator's) counts of a point of the turned counts: turned clockwise
/// by the angle (the server's nominal calibration is the same along X and Y).
fn controller_counts(p: CountPoint, angle_deg: f64) -> (f64, f64) {
    let (s, c) = angle_deg.to_radians().sin_cos();
    let (x, y) = (p.x.value(), p.y.value());
    (c * x + s * y, -s * x + c * y)
}

#[test]
fn moves_and_scans_land_on_the_turned_axes() {
    for angle in [30.0, -115.0, 90.0] {
        let server = crate::common::serve_ideal();
        let mut tcp = NanonisMicroscope::connect(config(server.addr().port(), angle)).unwrap();
        // The field is the largest turned square inside the controller's range.
        let caps = tcp.capabilities();
        let shrink = angle.to_radians().cos().abs() + angle.to_radians().sin().abs();
        let h = caps.field_max.x.value() + 1.0;
        assert!(h * shrink <= 32768.0 + 1e-6 && (h + 1.0) * shrink > 32768.0 - 1e-6);
        let target = CountPoint::from_counts(1500.0, -700.0);
        tcp.move_to(MoveRequest {
            target,
            speed: spm_hal::CountsPerSecond(20_000.0),
            settle: Seconds(0.0),
        })
        .unwrap();
        let there = server.with_simulator(|s| s.clone().position()).unwrap();
        let (x, y) = controller_counts(target, angle);
        assert!(
            (there.x.value() - x).abs() < 1e-6 && (there.y.value() - y).abs() < 1e-6,
            "{angle}°: {there:?} vs ({x}, {y})"
        );
        let back = tcp.position().unwrap();
        assert!(back.distance(target).value() < 1e-6, "{back:?}");
        server.with_simulator_mut(|s| s.record_tip_positions(true));
        for direction in [ScanDirection::Direct, ScanDirection::Counter] {
            let request = ScanRequest {
                origin: CountPoint::from_counts(1000.0, -900.0),
                pixel_step: Counts(1.5),
                pixels_per_line: 16,
                lines: 6,
                direction,
                pixel_dwell: Seconds(1e-4),
                record_backward: false,
            };
            let frame = tcp.scan(&request).unwrap();
            assert_eq!(frame.forward.z_counts.len(), 16 * 6);
            let inputs = server.with_simulator(|s| s.oracle().last_scan_effective_inputs());
            assert_eq!(inputs.len(), 16 * 6);
            for line in 0..6 {
                for pixel in 0..16 {
                    let wanted =
                        request.commanded_position(spm_hal::TraceHalf::Forward, line, pixel);
                    let (x, y) = controller_counts(wanted, angle);
                    let got = inputs[line * 16 + pixel];
                    // Float32 frame geometry: a few thousandths of a count.
                    assert!(
                        (got.x.value() - x).abs() < 5e-3 && (got.y.value() - y).abs() < 5e-3,
                        "{angle}° {direction:?} line {line} pixel {pixel}: {got:?} vs ({x}, {y})"
                    );
                }
            }
        }
    }
}
