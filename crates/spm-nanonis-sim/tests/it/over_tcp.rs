//! NanonisMicroscope against nanonis-sim, judged against the same simulator in process:
//! the same sequence of moves, waits, scans and Z reads gives the same clock, positions and
//! data within the wire format's precision, the pitfalls are handled, and faults are
//! survived.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_hal::{
    CountPoint, Counts, Error as _, ErrorKind, Frame, Microscope, MoveRequest, ScanDirection,
    ScanRequest, Seconds,
};
use spm_nanonis::{NanonisConfig, NanonisMicroscope};
use spm_nanonis_sim::{Server, ServerConfig, SocketFaults};
use spm_sim::{SimConfig, Simulator};
use std::path::Path;

fn sim_config() -> SimConfig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/sim-hopg.toml");
    let mut c = SimConfig::from_file(path).unwrap().without_random_faults();
    // DAC rounding of pixel positions that float32 frame geometry moves across a half
    // code would change whole pixels; without it the difference is continuous.
    c.measurement.quantise_lateral_dac = false;
    c
}

fn client_config(port: u16) -> NanonisConfig {
    NanonisConfig {
        command_timeout_s: 2.0,
        reconnect_attempts: 4,
        ..spm_nanonis_sim::loopback_config(port)
    }
}

fn start(faults: SocketFaults) -> spm_nanonis_sim::server::ServerHandle {
    Server::bind("127.0.0.1:0", sim_config(), ServerConfig::new(faults))
        .unwrap()
        .spawn()
        .unwrap()
}

fn request(direction: ScanDirection, pixels: u32, lines: u32) -> ScanRequest {
    ScanRequest {
        origin: CountPoint::from_counts(1234.25, -2345.5),
        pixel_step: Counts(0.75),
        pixels_per_line: pixels,
        lines,
        direction,
        pixel_dwell: Seconds(1e-4),
        record_backward: false,
    }
}

/// Relative float32 precision, with a floor for values near zero.
fn close(a: f64, b: f64, scale: f64) -> bool {
    (a - b).abs() <= 4.0 * f64::from(f32::EPSILON) * (a.abs().max(b.abs()) + scale)
}

fn check_frames(tcp: &Frame, local: &Frame, what: &str) {
    assert_eq!(tcp.request, local.request, "{what}");
    let halves = [
        (Some(&tcp.forward), Some(&local.forward)),
        (tcp.backward.as_ref(), local.backward.as_ref()),
    ];
    for (a, b) in halves {
        let (Some(a), Some(b)) = (a, b) else {
            assert_eq!(a.is_some(), b.is_some(), "{what}");
            continue;
        };
        assert_eq!(a.z_counts.len(), b.z_counts.len(), "{what}");
        // Z: float32 metres on the wire; pixel positions realised from float32 frame
        // geometry move the sample point by ≤ 0.002 counts, i.e. a fraction of a count of
        // topography at the steepest atomic slopes.
        let max_z = a
            .z_counts
            .iter()
            .zip(&b.z_counts)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max);
        let max_t = a
            .time_s
            .iter()
            .zip(&b.time_s)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max);
        eprintln!("{what}: max |Δz| {max_z:.2e} counts, max |Δt| {max_t:.2e} s");
        for (i, (za, zb)) in a.z_counts.iter().zip(&b.z_counts).enumerate() {
            assert!((za - zb).abs() <= 0.5, "{what}: z[{i}] {za} vs {zb}");
        }
        // Times: line times are float32 seconds, the clock two float32s.
        for (i, (ta, tb)) in a.time_s.iter().zip(&b.time_s).enumerate() {
            assert!(close(*ta, *tb, 1e-3), "{what}: t[{i}] {ta} vs {tb}");
        }
    }
}

#[test]
fn the_same_operations_give_the_same_instrument_over_tcp() {
    let server = start(SocketFaults::none());
    let mut tcp = NanonisMicroscope::connect(client_config(server.addr().port())).unwrap();
    let mut local = Simulator::new(sim_config()).unwrap();
    // The controller was found with every correction on and switched it off.
    let state = tcp.controller_state().clone();
    assert_eq!(state.drift_compensation_found.0, 1);
    assert_eq!(state.hysteresis_compensation_found, 1);
    assert_eq!(
        (
            state.drift_compensation_now,
            state.hysteresis_compensation_now
        ),
        (0, 0)
    );
    assert_eq!(state.tilt_now_deg, [0.0, 0.0]);
    assert_eq!(tcp.capabilities().field_min, local.capabilities().field_min);
    assert_eq!(tcp.capabilities().field_max, local.capabilities().field_max);

    let moves = [
        MoveRequest {
            target: CountPoint::from_counts(1200.0, -2300.0),
            speed: spm_hal::CountsPerSecond(20000.0),
            settle: Seconds(0.01),
        },
        MoveRequest {
            target: CountPoint::from_counts(-5000.5, 7000.25),
            speed: spm_hal::CountsPerSecond(5000.0),
            settle: Seconds(0.0),
        },
    ];
    let scans = [
        request(ScanDirection::Direct, 32, 8),
        request(ScanDirection::Counter, 16, 12),
        ScanRequest {
            record_backward: true,
            ..request(ScanDirection::Direct, 48, 6)
        },
    ];
    for (k, m) in moves.iter().enumerate() {
        tcp.move_to(*m).unwrap();
        local.move_to(*m).unwrap();
        assert!(close(
            tcp.now().unwrap().value(),
            local.now().unwrap().value(),
            1e-3
        ));
        let (a, b) = (tcp.position().unwrap(), local.position().unwrap());
        assert!(
            (a.x.value() - b.x.value()).abs() < 1e-6,
            "move {k}: {a:?} vs {b:?}"
        );
        assert!(
            (a.y.value() - b.y.value()).abs() < 1e-6,
            "move {k}: {a:?} vs {b:?}"
        );
        tcp.wait(Seconds(0.25)).unwrap();
        local.wait(Seconds(0.25)).unwrap();
        for s in &scans {
            let a = tcp.scan(s).unwrap();
            let b = local.scan(s).unwrap();
            check_frames(
                &a,
                &b,
                &format!("move {k}, {:?} {} px", s.direction, s.pixels_per_line),
            );
            let (za, zb) = (tcp.z_position().unwrap(), local.z_position().unwrap());
            assert!((za.value() - zb.value()).abs() <= 2e-3, "{za} vs {zb}");
        }
    }
    let (ta, tb) = (tcp.now().unwrap().value(), local.now().unwrap().value());
    assert!(close(ta, tb, 1e-3), "clock {ta} vs {tb}");
    assert!(ta > 1.0);
}

#[test]
fn pixel_counts_are_padded_to_16_and_cropped() {
    // 12 pixels are scanned as 16 with the same step and cropped: the data are those of an
    // in-process 16-pixel scan of the same origin, cropped, with 16-pixel line timing.
    let server = start(SocketFaults::none());
    let mut tcp = NanonisMicroscope::connect(client_config(server.addr().port())).unwrap();
    let mut local = Simulator::new(sim_config()).unwrap();
    for direction in [ScanDirection::Direct, ScanDirection::Counter] {
        let asked = ScanRequest {
            record_backward: true,
            ..request(direction, 12, 5)
        };
        let mut padded = asked.clone();
        padded.pixels_per_line = 16;
        if direction == ScanDirection::Counter {
            padded.origin.x -= Counts(4.0 * 0.75);
        }
        let a = tcp.scan(&asked).unwrap();
        let b = local.scan(&padded).unwrap();
        assert_eq!(a.request, asked);
        assert_eq!(a.forward.z_counts.len(), 12 * 5);
        let back_a = a.backward.as_ref().unwrap();
        let back_b = b.backward.as_ref().unwrap();
        for line in 0..5 {
            for pixel in 0..12 {
                // Forward: the first 12 pixels of each 16-pixel trace.
                let (i, j) = (line * 12 + pixel, line * 16 + pixel);
                assert!((a.forward.z_counts[i] - b.forward.z_counts[j]).abs() <= 2e-3);
                assert!(close(a.forward.time_s[i], b.forward.time_s[j], 1e-3));
                // Backward: the retrace reaches the requested pixels after the 4 padding ones.
                let j = line * 16 + 4 + pixel;
                assert!(
                    (back_a.z_counts[i] - back_b.z_counts[j]).abs() <= 2e-3,
                    "{direction:?}"
                );
                assert!(close(back_a.time_s[i], back_b.time_s[j], 1e-3));
            }
        }
    }
}

#[test]
fn pixel_counts_dividing_16_are_scanned_in_their_own_frame_and_line_time() {
    // 4 pixels are scanned as 16 samples over the request's own frame in its line time (a
    // quarter of the dwell each) and each pixel is the mean of its 4 samples: the same
    // physics as the in-process 4-pixel scan (nanonis-sim runs exactly that scan, its
    // frame having non-square pixels, and resamples each line to 16 by linear
    // interpolation), the pixel times the same, the line time not 4 times longer.
    let server = start(SocketFaults::none());
    let mut tcp = NanonisMicroscope::connect(client_config(server.addr().port())).unwrap();
    let mut local = Simulator::new(sim_config()).unwrap();
    assert_eq!(tcp.capabilities().pixels_per_line_multiple, 16);
    assert_eq!(local.capabilities().pixels_per_line_multiple, 1);
    // Binned: the mean over samples 4k..4k+3 of the line resampled to 16 pixels.
    let binned = |line: &[f64], k: usize| -> f64 {
        let n = line.len();
        (4 * k..4 * k + 4)
            .map(|c| {
                let f = ((c as f64 + 0.5) / 16.0 * n as f64 - 0.5).clamp(0.0, (n - 1) as f64);
                let j = (f.floor() as usize).min(n - 1);
                let w = f - j as f64;
                line[j] * (1.0 - w) + line[(j + 1).min(n - 1)] * w
            })
            .sum::<f64>()
            / 4.0
    };
    for direction in [ScanDirection::Direct, ScanDirection::Counter] {
        let asked = ScanRequest {
            record_backward: true,
            ..request(direction, 4, 6)
        };
        let a = tcp.scan(&asked).unwrap();
        let b = local.scan(&asked).unwrap();
        assert_eq!(a.request, asked);
        // A line's trace and retrace: 4 pixels each at 1e-4 s, not 16.
        let period_s = a.forward.time_s[4] - a.forward.time_s[0];
        assert!(close(period_s, 8e-4, 1e-3), "{direction:?}: {period_s} s");
        let halves = [
            (&a.forward, &b.forward),
            (a.backward.as_ref().unwrap(), b.backward.as_ref().unwrap()),
        ];
        for (half, (got, truth)) in halves.into_iter().enumerate() {
            assert_eq!(got.z_counts.len(), 4 * 6);
            for line in 0..6 {
                let row = &truth.z_counts[line * 4..(line + 1) * 4];
                // The retrace's pixels are in scan order: left to right in the frame.
                let in_frame: Vec<f64> = if half == 0 {
                    row.to_vec()
                } else {
                    row.iter().rev().copied().collect()
                };
                for pixel in 0..4 {
                    let i = line * 4 + pixel;
                    let k = if half == 0 { pixel } else { 3 - pixel };
                    let e = binned(&in_frame, k);
                    assert!(
                        (got.z_counts[i] - e).abs() <= 2e-3,
                        "{direction:?} half {half} line {line} pixel {pixel}: {} vs {e}",
                        got.z_counts[i]
                    );
                    assert!(
                        close(got.time_s[i], truth.time_s[i], 1e-3),
                        "{direction:?} half {half}: {} vs {}",
                        got.time_s[i],
                        truth.time_s[i]
                    );
                }
            }
        }
    }
}

#[test]
fn socket_faults_are_survived_and_an_unreachable_controller_aborts() {
    let faults = SocketFaults::mixed(0.1, 7, 0.01, 0.0);
    let server = start(faults);
    let mut tcp = NanonisMicroscope::connect(client_config(server.addr().port()));
    // Opening may itself meet faults on non-repeatable commands; retry like a user would.
    for _ in 0..5 {
        if tcp.is_ok() {
            break;
        }
        tcp = NanonisMicroscope::connect(client_config(server.addr().port()));
    }
    let mut tcp = tcp.unwrap();
    let mut ok = 0;
    let mut transient = 0;
    for k in 0..40 {
        let s = request(ScanDirection::Direct, 16, 4);
        match tcp.scan(&s) {
            Ok(frame) => {
                frame.validate().unwrap();
                assert!(frame.forward.z_counts.iter().all(|z| z.is_finite()));
                ok += 1;
            }
            Err(e) => {
                assert!(e.kind().is_transient(), "scan {k}: {e}");
                transient += 1;
            }
        }
    }
    let stats = server.stats();
    eprintln!("ok {ok}, transient {transient}, {stats:?}");
    assert!(stats.injected() as f64 >= 0.05 * stats.commands as f64);
    assert!(ok >= 20, "{ok} of 40 scans succeeded");
    server.kill();
    let e = tcp
        .scan(&request(ScanDirection::Direct, 16, 4))
        .unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Aborted, "{e}");
    assert!(e.to_string().contains("unreachable"), "{e}");
}

/// `Scan.StatusGet` requests the server has received so far.
fn status_gets(server: &spm_nanonis_sim::server::ServerHandle) -> u64 {
    let stats = server.stats();
    stats
        .commands_by_name
        .get("Scan.StatusGet")
        .copied()
        .unwrap_or(0)
}

/// Issue 26 (the TCP overhead): whether a scan runs is asked (`Scan.StatusGet`) before a scan
/// only when it is unknown — when the backend opens, after a failed call — not between scans
/// that ended normally with only moves, waits and reads in between (before: one round trip
/// per scan). The server's own count of the requests it received is the truth.
#[test]
fn scan_status_is_asked_only_when_unknown() {
    let server = start(SocketFaults::none());
    let port = server.addr().port();
    let mut tcp = NanonisMicroscope::connect(client_config(port)).unwrap();
    let opened = status_gets(&server);
    assert!(opened >= 1, "asked when the backend opens");
    let s = request(ScanDirection::Direct, 16, 4);
    for k in 0..3 {
        tcp.move_to(MoveRequest {
            target: CountPoint::from_counts(1000.0 + 10.0 * f64::from(k), -2000.0),
            speed: spm_hal::CountsPerSecond(1000.0),
            settle: Seconds(0.01),
        })
        .unwrap();
        tcp.wait(Seconds(0.1)).unwrap();
        tcp.now().unwrap();
        tcp.position().unwrap();
        tcp.scan(&s).unwrap();
        tcp.z_position().unwrap();
    }
    assert_eq!(
        status_gets(&server),
        opened,
        "no Scan.StatusGet between scans that ended normally"
    );
    // A scan the controller refuses (its Z feedback switched off by another client): the
    // backend no longer knows whether a scan runs.
    let mut other = spm_nanonis::Client::connect(client_config(port).client_config()).unwrap();
    other
        .call(&spm_nanonis::commands::Request::ZCtrlOnOffSet(0))
        .unwrap();
    tcp.scan(&s).unwrap_err();
    assert_eq!(status_gets(&server), opened);
    other
        .call(&spm_nanonis::commands::Request::ZCtrlOnOffSet(1))
        .unwrap();
    tcp.scan(&s).unwrap();
    assert_eq!(
        status_gets(&server),
        opened + 1,
        "asked after a failed scan"
    );
    tcp.scan(&s).unwrap();
    assert_eq!(status_gets(&server), opened + 1, "and known again after it");
}

/// A connection lost between two scans (here closed by the server after 0.3 s idle) may
/// come back to a controller running a scan (here started by another client meanwhile): the
/// backend asks `Scan.StatusGet` on the new connection, stops that scan, and only then
/// starts its own — the start is not sent again on the new connection by itself.
#[test]
fn after_a_reconnection_a_scan_left_running_is_stopped_first() {
    use spm_nanonis::commands::{Request, scan_action};
    let mut config = ServerConfig::new(SocketFaults::none());
    config.limits.idle_timeout_s = 0.3;
    let server = Server::bind("127.0.0.1:0", sim_config(), config)
        .unwrap()
        .spawn()
        .unwrap();
    let port = server.addr().port();
    let mut tcp = NanonisMicroscope::connect(client_config(port)).unwrap();
    let s = request(ScanDirection::Direct, 16, 4);
    tcp.scan(&s).unwrap();
    let before = server.stats();
    std::thread::sleep(std::time::Duration::from_millis(800));
    assert!(
        server.stats().timed_out_connections >= 1,
        "the idle connection is closed"
    );
    let mut other = spm_nanonis::Client::connect(client_config(port).client_config()).unwrap();
    other
        .call(&Request::ScanAction {
            action: scan_action::START,
            direction_up: 1,
        })
        .unwrap();
    let frame = tcp.scan(&s).unwrap();
    frame.validate().unwrap();
    assert!(tcp.client().reconnects() >= 1, "the backend reconnected");
    let after = server.stats();
    let sent = |name: &str| {
        after.commands_by_name.get(name).copied().unwrap_or(0)
            - before.commands_by_name.get(name).copied().unwrap_or(0)
    };
    assert!(sent("Scan.StatusGet") >= 1, "{after:?}");
    // The other client's start, the backend's stop of it and its own start.
    assert_eq!(sent("Scan.Action"), 3, "{after:?}");
}

/// Issue 26 (the TCP overhead): with a simulated controller (virtual clock) a move, its settle
/// and the clock read after them are one round trip, a scan setting and its read-back are one,
/// and so are a scan's end, its data, the clock and the position after it (pipelined: sent in
/// one write, answered in order). The
/// readings are the simulator's own (its clock and commanded position after the commands),
/// and the server's count of requests it found already received is the truth of the
/// round trips saved.
#[test]
fn a_wait_and_the_reads_after_it_are_one_round_trip() {
    a_wait_and_the_reads_after_it_are_one_round_trip_when(false);
    // As `spmcal calibrate` runs: interruptible (the wait for a scan's end in slices).
    a_wait_and_the_reads_after_it_are_one_round_trip_when(true);
}

fn a_wait_and_the_reads_after_it_are_one_round_trip_when(interruptible: bool) {
    let server = start(SocketFaults::none());
    let mut tcp = NanonisMicroscope::connect(client_config(server.addr().port())).unwrap();
    if interruptible {
        tcp.set_interrupt(std::sync::Arc::new(std::sync::atomic::AtomicBool::new(
            false,
        )));
    }
    let s = request(ScanDirection::Direct, 16, 4);
    let before = server.stats();
    tcp.move_to(MoveRequest {
        target: CountPoint::from_counts(1500.0, -2000.0),
        speed: spm_hal::CountsPerSecond(1000.0),
        settle: Seconds(0.0125),
    })
    .unwrap();
    let after_move = (tcp.now().unwrap(), tcp.position().unwrap());
    let truth_move = server.with_simulator_mut(|sim| (sim.now().unwrap(), sim.position().unwrap()));
    let frame = tcp.scan(&s).unwrap();
    frame.validate().unwrap();
    let after_scan = (tcp.now().unwrap(), tcp.position().unwrap());
    let truth_scan = server.with_simulator_mut(|sim| (sim.now().unwrap(), sim.position().unwrap()));
    let after = server.stats();
    let pipelined = after.pipelined - before.pipelined;
    eprintln!(
        "{} commands, {pipelined} pipelined",
        after.commands - before.commands
    );
    // The move's settle and clock read (2); the whole scan in one round trip (9 behind its
    // first request): its buffer and speed (set for the first time) with their read-backs,
    // its frame, its start, the wait for its end, its grab, the clock and the position.
    assert_eq!(pipelined, 11, "interruptible {interruptible}: {after:?}");
    let sent = |name: &str| {
        after.commands_by_name.get(name).copied().unwrap_or(0)
            - before.commands_by_name.get(name).copied().unwrap_or(0)
    };
    assert_eq!(
        after.commands - before.commands - pipelined,
        4,
        "the position read before the move, the Follow-Me speed, the move, the scan: {after:?}"
    );
    assert_eq!(sent("Scan.FrameSet"), 1);
    assert_eq!(sent("Scan.Action"), 1, "the start, nothing stopped");
    for ((t, p), (t_sim, p_sim), what) in [
        (after_move, truth_move, "after the move"),
        (after_scan, truth_scan, "after the scan"),
    ] {
        assert!(
            close(t.value(), t_sim.value(), 0.0),
            "{what}: {t} vs {t_sim}"
        );
        assert!(
            p.distance(p_sim).value() < 2e-3,
            "{what}: {p:?} vs {p_sim:?}"
        );
    }
}

/// Issue 25 item 19, a second client moving the tip during a run. The backend has the
/// controller to itself by assumption; what it can check without extra round trips is the
/// first position it reads from the controller after its scan: the tip must be on the
/// raster it scanned (with a margin), since the backend moved nothing since. Here with a
/// controller clock in real time (one command per round trip, as on hardware): a scan,
/// then another connection moves the tip 10 000 counts away, then the backend's position
/// read is an error naming another client, and the run would stop there. The control: the
/// same sequence with nobody else moving the tip reads the position (on the raster), and
/// the backend's own move after a scan is never mistaken for another client's.
#[test]
fn a_tip_moved_by_another_client_after_a_scan_is_an_error_naming_the_cause() {
    use spm_nanonis::commands::{Reply, Request};
    let server = start(SocketFaults::none());
    let port = server.addr().port();
    let mut config = client_config(port);
    config.clock = spm_nanonis::ClockSource::ControllerSignals {
        whole_s_signal: 126,
        fraction_s_signal: 127,
        virtual_time: false,
    };
    let mut tcp = NanonisMicroscope::connect(config.clone()).unwrap();
    let s = request(ScanDirection::Direct, 16, 4);
    let to_start = MoveRequest {
        target: s.origin,
        speed: spm_hal::CountsPerSecond(1000.0),
        settle: Seconds(0.01),
    };
    // Alone: the position after a scan is on its raster, and after the backend's own move
    // it is the move's target.
    tcp.move_to(to_start).unwrap();
    tcp.scan(&s).unwrap();
    let p = tcp.position().unwrap();
    assert!(
        (p.x.value() - s.origin.x.value()).abs() < 100.0
            && (p.y.value() - s.origin.y.value()).abs() < 100.0,
        "the tip after the scan: {p:?}"
    );
    tcp.scan(&s).unwrap();
    tcp.move_to(MoveRequest {
        target: CountPoint::from_counts(9000.0, 9000.0),
        ..to_start
    })
    .unwrap();
    tcp.position().unwrap();
    // Another client moves the tip after the backend's scan.
    tcp.move_to(to_start).unwrap();
    tcp.scan(&s).unwrap();
    let mut other = spm_nanonis::Client::connect(config.client_config()).unwrap();
    let Reply::XY { x_m, y_m } = other
        .call(&Request::FolMeXYPosGet { wait_newest: 0 })
        .unwrap()
    else {
        panic!("FolMe.XYPosGet");
    };
    other
        .call(&Request::FolMeXYPosSet {
            x_m: x_m + 10_000.0 * 0.02e-9,
            y_m,
            wait_end_of_move: 1,
        })
        .unwrap();
    let e = tcp.position().unwrap_err();
    assert!(
        e.to_string().contains("another client"),
        "the error names the cause: {e}"
    );
    assert_eq!(
        spm_hal::Error::kind(&e),
        spm_hal::ErrorKind::Aborted,
        "the run stops: {e}"
    );
}

/// The scan's set-up and start, sent in one write with the wait for its end and the reads
/// after it (a simulated controller): a setting or the start the controller refuses (here
/// `ServerHandle::refuse_next`) has let it run the rest — a scan with the settings it had,
/// or a wait for none — before the refusal is read. The backend then stops whatever scan
/// runs, discards every reply after the refusal, and returns the error naming the refused
/// command: no frame. The next scan sends its settings again, asks whether a scan runs
/// first, and gets the frame asked for (the controller then holds exactly the settings of
/// a controller that never refused anything).
#[test]
fn a_refused_setting_or_start_in_the_scan_pipeline_is_an_error_naming_it_and_no_frame() {
    use spm_nanonis::commands::{Reply, Request};
    let first = request(ScanDirection::Direct, 16, 4);
    // Another frame, buffer and speed: all three are sent before its start.
    let second = ScanRequest {
        origin: CountPoint::from_counts(-3000.0, 2500.0),
        pixel_dwell: Seconds(2e-4),
        ..request(ScanDirection::Counter, 32, 8)
    };
    let settings = |port: u16| {
        let mut c = spm_nanonis::Client::connect(client_config(port).client_config()).unwrap();
        [
            Request::ScanFrameGet,
            Request::ScanBufferGet,
            Request::ScanSpeedGet,
            Request::ScanStatusGet,
        ]
        .map(|r| c.call(&r).unwrap())
    };
    // The reference: the same scans, nothing refused.
    let reference = start(SocketFaults::none());
    let mut tcp = NanonisMicroscope::connect(client_config(reference.addr().port())).unwrap();
    tcp.scan(&first).unwrap();
    tcp.scan(&second).unwrap();
    let expected = settings(reference.addr().port());
    for refused in [
        "Scan.BufferSet",
        "Scan.FrameSet",
        "Scan.SpeedSet",
        "Scan.Action",
    ] {
        let server = start(SocketFaults::none());
        let port = server.addr().port();
        let mut tcp = NanonisMicroscope::connect(client_config(port)).unwrap();
        tcp.scan(&first).unwrap();
        let before = server.stats();
        server.refuse_next(refused, 1, false);
        let e = tcp.scan(&second).unwrap_err();
        assert_eq!(e.command.as_deref(), Some(refused), "{e}");
        assert_eq!(e.kind, spm_nanonis::NanonisErrorKind::Controller, "{e}");
        assert!(e.to_string().contains("refused"), "{e}");
        let after = server.stats();
        assert_eq!(after.injected_refusals, 1);
        let sent = |name: &str| {
            after.commands_by_name.get(name).copied().unwrap_or(0)
                - before.commands_by_name.get(name).copied().unwrap_or(0)
        };
        // One round trip for the scan, then the stop (on the second connection).
        let round_trips = (after.commands - after.pipelined) - (before.commands - before.pipelined);
        assert_eq!(round_trips, 2, "{refused}: {after:?}");
        assert_eq!(sent("Scan.Action"), 2, "{refused}: the start and the stop");
        assert_eq!(sent("Scan.WaitEndOfScan"), 1, "{refused}");
        // Nothing runs on the controller.
        let mut other = spm_nanonis::Client::connect(client_config(port).client_config()).unwrap();
        assert_eq!(
            other.call(&Request::ScanStatusGet).unwrap(),
            Reply::U32(0),
            "{refused}: the scan is stopped"
        );
        drop(other);
        // The next scan: whether a scan runs is asked, every setting is sent again, and the
        // frame is the one asked for.
        let before = server.stats();
        let frame = tcp.scan(&second).unwrap();
        frame.validate().unwrap();
        assert_eq!(frame.request, second);
        let after = server.stats();
        let sent = |name: &str| {
            after.commands_by_name.get(name).copied().unwrap_or(0)
                - before.commands_by_name.get(name).copied().unwrap_or(0)
        };
        for name in [
            "Scan.StatusGet",
            "Scan.BufferSet",
            "Scan.FrameSet",
            "Scan.SpeedSet",
            "Scan.Action",
        ] {
            assert_eq!(sent(name), 1, "{refused}: {name} after the failure");
        }
        assert_eq!(settings(port), expected, "{refused}");
    }
}

/// The same pipeline, a setting or the start answered "busy" (not executed), which the client
/// otherwise sends again. A busy start ran nothing (the wait after it waited for no scan):
/// the scan is done again one step after another, with the frame asked for. A busy frame
/// before a start that ran has let the controller scan its previous frame: the tip is not
/// where the run left it, so that is the scan's error, transient (the calibration measures
/// the node again from its move), naming `Scan.FrameSet` — not a frame.
#[test]
fn a_busy_start_in_the_scan_pipeline_is_retried_and_a_busy_frame_is_the_error() {
    let first = request(ScanDirection::Direct, 16, 4);
    let second = ScanRequest {
        origin: CountPoint::from_counts(-3000.0, 2500.0),
        ..first.clone()
    };
    let server = start(SocketFaults::none());
    let mut tcp = NanonisMicroscope::connect(client_config(server.addr().port())).unwrap();
    tcp.scan(&first).unwrap();
    server.refuse_next("Scan.Action", 1, true);
    let frame = tcp.scan(&second).unwrap();
    frame.validate().unwrap();
    assert_eq!(frame.request, second);
    let truth = server.last_frame_truth().unwrap();
    assert_eq!(truth.time_s.len(), frame.forward.time_s.len());
    for (t, t_sim) in frame.forward.time_s.iter().zip(&truth.time_s) {
        assert!(close(*t, *t_sim, 1e-3), "{t} vs {t_sim}");
    }
    server.refuse_next("Scan.FrameSet", 1, true);
    let e = tcp.scan(&first).unwrap_err();
    assert_eq!(e.command.as_deref(), Some("Scan.FrameSet"), "{e}");
    assert_eq!(e.kind, spm_nanonis::NanonisErrorKind::Busy, "{e}");
    assert!(e.kind().is_transient(), "{e}");
    assert!(e.to_string().contains("previous settings"), "{e}");
    let frame = tcp.scan(&first).unwrap();
    frame.validate().unwrap();
    assert_eq!(server.stats().injected_refusals, 2);
}
