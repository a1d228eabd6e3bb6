//! NanonisMicroscope scanning in both slow directions (issue 26): with
//! `slow_direction = "down"` every frame is started downwards, and the frame the backend returns
//! still places every pixel at spm-hal's `commanded_position` and stamps it with the time the
//! instrument acquired it — judged by the simulator behind nanonis-sim (the effective input and
//! the time of every pixel it scanned, [`spm_nanonis_sim::FrameTruth`]; an ideal instrument,
//! where the effective inputs are the commands), for direct and counter frames at 0°, 30° and
//! −115°.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_hal::{CountPoint, Counts, Frame, Microscope, ScanDirection, ScanRequest, Seconds};
use spm_nanonis::{NanonisConfig, NanonisMicroscope, SlowDirection};
use spm_nanonis_sim::{FrameTruth, ServerHandle};

const PIXELS: u32 = 16;
const LINES: u32 = 6;
const DWELL_S: f64 = 1e-4;
/// The controller's clock as the backend reads it: two float32 signals (whole seconds and the
/// fraction, whose float32 resolution is ≤ 6·10⁻⁸ s), and float32 line times: 1 µs, 1 % of a
/// dwell.
const CLOCK_S: f64 = 1e-6;

fn config(port: u16, frame_angle_deg: f64, slow_direction: SlowDirection) -> NanonisConfig {
    NanonisConfig {
        frame_angle_deg,
        slow_direction,
        ..spm_nanonis_sim::loopback_config(port)
    }
}

fn serve() -> ServerHandle {
    let server = crate::common::serve_ideal();
    server.with_simulator_mut(|s| s.record_tip_positions(true));
    server
}

/// The controller's (simulator's) counts of a point of the turned counts: turned clockwise
/// by the angle (the server's nominal calibration is the same along X and Y).
fn controller_counts(p: CountPoint, angle_deg: f64) -> CountPoint {
    let (s, c) = angle_deg.to_radians().sin_cos();
    let (x, y) = (p.x.value(), p.y.value());
    CountPoint::from_counts(c * x + s * y, -s * x + c * y)
}

fn request(direction: ScanDirection) -> ScanRequest {
    ScanRequest {
        origin: CountPoint::from_counts(1000.0, -900.0),
        pixel_step: Counts(1.5),
        pixels_per_line: PIXELS,
        lines: LINES,
        direction,
        pixel_dwell: Seconds(DWELL_S),
        record_backward: false,
    }
}

/// Every pixel of `frame` against the simulator's truth: the pixel the simulator scanned at
/// the pixel's commanded position (found by position, unique in a frame) was acquired at the
/// pixel's time stamp, and the frame's time stamps order the pixels as the simulator acquired
/// them.
///
/// Time tolerance: the clock's precision ([`CLOCK_S`]) for a frame scanned up; a frame scanned down is
/// simulated line by line (spm-sim's rasters step upwards), each line after the first
/// reached by a travel of one pixel step at scan speed (one dwell) that a controller does not
/// spend, so its early lines are stamped up to `(lines − 1)` dwells late — far less than the
/// 32 dwells of one line, which a line in the wrong place in time would be off by.
fn check(frame: &Frame, truth: &FrameTruth, angle: f64, slow: SlowDirection, what: &str) {
    let n = (PIXELS * LINES) as usize;
    assert_eq!(frame.forward.time_s.len(), n, "{what}");
    assert_eq!(truth.effective_inputs.len(), n, "{what}");
    assert_eq!(truth.time_s.len(), n, "{what}");
    let tolerance_s = match slow {
        SlowDirection::Up => CLOCK_S,
        SlowDirection::Down => f64::from(LINES - 1) * DWELL_S + CLOCK_S,
    };
    let mut matched = Vec::with_capacity(n);
    for line in 0..LINES as usize {
        for pixel in 0..PIXELS as usize {
            let wanted = controller_counts(
                frame
                    .request
                    .commanded_position(spm_hal::TraceHalf::Forward, line, pixel),
                angle,
            );
            let (j, distance) = truth
                .effective_inputs
                .iter()
                .map(|p| p.distance(wanted).value())
                .enumerate()
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap();
            // Float32 frame geometry: a few thousandths of a count.
            assert!(
                distance < 5e-3,
                "{what} line {line} pixel {pixel}: nothing scanned within {distance} counts"
            );
            let stamped = frame.forward.time_s[line * PIXELS as usize + pixel];
            assert!(
                (stamped - truth.time_s[j]).abs() <= tolerance_s,
                "{what} line {line} pixel {pixel}: stamped {stamped} s, scanned at {} s",
                truth.time_s[j]
            );
            matched.push((stamped, truth.time_s[j]));
        }
    }
    matched.sort_by(|a, b| a.0.total_cmp(&b.0));
    for pair in matched.windows(2) {
        assert!(
            pair[0].1 < pair[1].1,
            "{what}: the time stamps order two pixels the other way round than they were scanned"
        );
    }
}

/// The direction of the first line's trace and of the step between the first two lines
/// acquired, in the simulator's counts (unit vectors).
fn fast_and_slow(truth: &FrameTruth) -> (CountPoint, CountPoint) {
    let p = &truth.effective_inputs;
    let unit = |a: CountPoint, b: CountPoint| {
        let (dx, dy) = (b.x.value() - a.x.value(), b.y.value() - a.y.value());
        let l = dx.hypot(dy);
        CountPoint::from_counts(dx / l, dy / l)
    };
    (unit(p[0], p[1]), unit(p[0], p[PIXELS as usize]))
}

fn opposite(a: CountPoint, b: CountPoint) -> bool {
    (a.x.value() + b.x.value()).abs() < 1e-4 && (a.y.value() + b.y.value()).abs() < 1e-4
}

fn same(a: CountPoint, b: CountPoint) -> bool {
    (a.x.value() - b.x.value()).abs() < 1e-4 && (a.y.value() - b.y.value()).abs() < 1e-4
}

#[test]
fn both_slow_directions_place_and_time_every_pixel_at_any_angle() {
    for angle in [0.0, 30.0, -115.0] {
        let server = serve();
        let mut directions = Vec::new();
        for slow in [SlowDirection::Up, SlowDirection::Down] {
            let mut tcp =
                NanonisMicroscope::connect(config(server.addr().port(), angle, slow)).unwrap();
            for direction in [ScanDirection::Direct, ScanDirection::Counter] {
                let what = format!("{angle}° {slow:?} {direction:?}");
                let frame = tcp.scan(&request(direction)).unwrap();
                let truth = server.last_frame_truth().unwrap();
                check(&frame, &truth, angle, slow, &what);
                directions.push(((slow, direction), fast_and_slow(&truth)));
            }
        }
        let of = |slow, direction| {
            directions
                .iter()
                .find(|(key, _)| *key == (slow, direction))
                .unwrap()
                .1
        };
        use ScanDirection::{Counter, Direct};
        use SlowDirection::{Down, Up};
        for slow in [Up, Down] {
            // A counter frame reverses both the fast and the slow direction of the direct one,
            // scanned up or down.
            let (direct, counter) = (of(slow, Direct), of(slow, Counter));
            assert!(
                opposite(direct.0, counter.0) && opposite(direct.1, counter.1),
                "{angle}° {slow:?}: direct {direct:?}, counter {counter:?}"
            );
        }
        for direction in [Direct, Counter] {
            // Down reverses the slow direction only.
            let (up, down) = (of(Up, direction), of(Down, direction));
            assert!(
                same(up.0, down.0) && opposite(up.1, down.1),
                "{angle}° {direction:?}: up {up:?}, down {down:?}"
            );
        }
    }
}
