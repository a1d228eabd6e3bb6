//! `Simulator::scan_turned`: a raster turned about a point, as a controller's frame angle
//! turns its frame (nanonis-sim serves frame angles with it).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_hal::{CountPoint, Counts, Microscope, ScanDirection, ScanRequest, Seconds};
use spm_sim::{RasterTurn, SimConfig, Simulator};

fn request() -> ScanRequest {
    ScanRequest {
        origin: CountPoint::from_counts(-100.0, 250.0),
        pixel_step: Counts(2.0),
        pixels_per_line: 16,
        lines: 8,
        direction: ScanDirection::Direct,
        pixel_dwell: Seconds(1e-4),
        record_backward: true,
    }
}

#[test]
fn a_turn_by_zero_is_the_plain_scan_bit_for_bit() {
    let config = SimConfig::room_temperature_tube().without_random_faults();
    let mut a = Simulator::new(config.clone()).unwrap();
    let mut b = Simulator::new(config).unwrap();
    let turn = RasterTurn {
        centre: CountPoint::from_counts(7.0, -3.0),
        angle_rad: 0.0,
    };
    assert_eq!(
        a.scan(&request()).unwrap(),
        b.scan_turned(&request(), turn).unwrap()
    );
    assert_eq!(a.now().unwrap(), b.now().unwrap());
}

#[test]
fn every_pixel_is_commanded_at_its_turned_position() {
    let mut sim = Simulator::new(SimConfig::ideal()).unwrap();
    sim.record_tip_positions(true);
    let r = request();
    let centre = CountPoint::from_counts(-85.0, 257.0);
    let angle = 0.5f64;
    sim.scan_turned(
        &r,
        RasterTurn {
            centre,
            angle_rad: angle,
        },
    )
    .unwrap();
    let inputs = sim.oracle().last_scan_effective_inputs();
    assert_eq!(inputs.len(), 16 * 8);
    let (s, c) = angle.sin_cos();
    for line in 0..8 {
        for pixel in 0..16 {
            let (dx, dy) = (
                -100.0 + 2.0 * pixel as f64 - centre.x.value(),
                250.0 + 2.0 * line as f64 - centre.y.value(),
            );
            let (x, y) = (
                centre.x.value() + c * dx - s * dy,
                centre.y.value() + s * dx + c * dy,
            );
            let p = inputs[line * 16 + pixel];
            assert!(
                (p.x.value() - x).abs() < 1e-6 && (p.y.value() - y).abs() < 1e-6,
                "line {line} pixel {pixel}: {p:?} vs ({x}, {y})"
            );
        }
    }
}

#[test]
fn a_turned_raster_must_stay_inside_the_field() {
    let mut sim = Simulator::new(SimConfig::ideal()).unwrap();
    let h = sim.capabilities().field_max.x.value();
    // Inside unturned, its corner leaves the field when turned by 45° about the origin.
    let r = ScanRequest {
        origin: CountPoint::from_counts(h - 40.0, h - 40.0),
        pixel_step: Counts(2.0),
        pixels_per_line: 16,
        lines: 16,
        direction: ScanDirection::Direct,
        pixel_dwell: Seconds(1e-4),
        record_backward: false,
    };
    sim.scan(&r).unwrap();
    let turn = RasterTurn {
        centre: CountPoint::from_counts(0.0, 0.0),
        angle_rad: std::f64::consts::FRAC_PI_4,
    };
    let e = sim.scan_turned(&r, turn).unwrap_err();
    assert_eq!(
        spm_hal::Error::kind(&e),
        spm_hal::ErrorKind::OutOfRange,
        "{e}"
    );
}
