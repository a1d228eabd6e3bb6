//! NanonisMicroscope interrupted (issue 26: pause and resume when the run is interrupted): once
//! the interrupt flag is set (spmcal sets it on SIGINT, SIGTERM, SIGHUP), a running scan is
//! paused on the controller and the backend answers `Aborted` at once; the controller holds the
//! paused frame; a backend opened again (a resumed run) stops it before anything moves and
//! scans as before. Judged by nanonis-sim, whose pause holds a frame at its start (running,
//! nothing acquired, the simulator's clock standing).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_hal::{CountPoint, Counts, ErrorKind, Microscope, ScanDirection, ScanRequest, Seconds};
use spm_nanonis::commands::{Reply, Request};
use spm_nanonis::{Client, ClockSource, NanonisConfig, NanonisMicroscope, SlowDirection};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

fn config(port: u16, clock: ClockSource) -> NanonisConfig {
    NanonisConfig {
        clock,
        frame_angle_deg: 30.0,
        slow_direction: SlowDirection::Down,
        ..spm_nanonis_sim::loopback_config(port)
    }
}

fn controller_clock() -> ClockSource {
    ClockSource::ControllerSignals {
        whole_s_signal: 126,
        fraction_s_signal: 127,
        virtual_time: true,
    }
}

fn request() -> ScanRequest {
    ScanRequest {
        origin: CountPoint::from_counts(-400.0, 250.0),
        pixel_step: Counts(2.0),
        pixels_per_line: 32,
        lines: 8,
        direction: ScanDirection::Counter,
        pixel_dwell: Seconds(1e-4),
        record_backward: true,
    }
}

fn status(user: &mut Client) -> u32 {
    match user.call(&Request::ScanStatusGet).unwrap() {
        Reply::U32(s) => s,
        other => panic!("Scan.StatusGet: {other:?}"),
    }
}

#[test]
fn an_interrupt_pauses_the_scan_and_a_resumed_backend_stops_it() {
    let server = crate::common::serve_ideal();
    let port = server.addr().port();
    let flag = Arc::new(AtomicBool::new(false));
    let mut tcp = NanonisMicroscope::connect(config(port, controller_clock())).unwrap();
    tcp.set_interrupt(Arc::clone(&flag));
    // Not interrupted: the scan is waited for in slices and comes whole.
    let whole = tcp.scan(&request()).unwrap();
    assert!(whole.forward.z_counts.iter().all(|z| z.is_finite()));
    let t_before = server.with_simulator(|s| s.oracle().now());
    // Interrupted while the scan runs.
    flag.store(true, Ordering::SeqCst);
    let error = tcp.scan(&request()).unwrap_err();
    assert_eq!(spm_hal::Error::kind(&error), ErrorKind::Aborted, "{error}");
    assert!(error.to_string().contains("paused"), "{error}");
    // The controller holds the frame paused: running poll after poll, nothing acquired, the
    // instrument's clock standing (a stopped frame would answer 0; a finished one would have
    // been simulated).
    let mut user = Client::connect(config(port, controller_clock()).client_config()).unwrap();
    for _ in 0..3 {
        assert_eq!(status(&mut user), 1);
    }
    match user
        .call(&Request::ScanFrameDataGrab {
            channel: 30,
            forward: 1,
        })
        .unwrap()
    {
        Reply::FrameData(d) => assert!(d.data.iter().all(|z| z.is_nan())),
        other => panic!("Scan.FrameDataGrab: {other:?}"),
    }
    assert_eq!(server.with_simulator(|s| s.oracle().now()), t_before);
    // The run stops; a resumed run opens the backend again: the paused frame is stopped
    // before anything moves, and scans are as before.
    drop(tcp);
    let mut resumed = NanonisMicroscope::connect(config(port, controller_clock())).unwrap();
    assert_eq!(status(&mut user), 0);
    let again = resumed.scan(&request()).unwrap();
    assert_eq!(again.forward.z_counts.len(), whole.forward.z_counts.len());
    // The same ideal, drift-free surface at the same places.
    for (a, b) in again.forward.z_counts.iter().zip(&whole.forward.z_counts) {
        assert!((a - b).abs() < 1e-3, "{a} vs {b}");
    }
    // A wait on the host clock is interrupted within the poll interval, not slept out.
    let mut host = NanonisMicroscope::connect(config(port, ClockSource::Host)).unwrap();
    host.set_interrupt(Arc::clone(&flag));
    let started = std::time::Instant::now();
    let error = host.wait(Seconds(30.0)).unwrap_err();
    assert_eq!(spm_hal::Error::kind(&error), ErrorKind::Aborted, "{error}");
    assert!(started.elapsed().as_secs_f64() < 5.0 * spm_nanonis::INTERRUPT_POLL_S);
}

/// Issue 25 item 12: `reconnect_attempts = 4294967295` was accepted, and the client was still
/// retrying 618 s after a SIGTERM. A configuration beyond `MAX_RECONNECT_ATTEMPTS` (or a first
/// backoff beyond `MAX_RECONNECT_BACKOFF_S`) is refused naming the field, before any
/// connection.
#[test]
fn absurd_reconnect_settings_are_refused_naming_the_field() {
    use spm_nanonis::client::{MAX_RECONNECT_ATTEMPTS, MAX_RECONNECT_BACKOFF_S};
    for (field, config) in [
        (
            "reconnect_attempts",
            NanonisConfig {
                reconnect_attempts: u32::MAX,
                ..spm_nanonis_sim::loopback_config(9)
            },
        ),
        (
            "reconnect_attempts",
            NanonisConfig {
                reconnect_attempts: MAX_RECONNECT_ATTEMPTS + 1,
                ..spm_nanonis_sim::loopback_config(9)
            },
        ),
        (
            "reconnect_backoff_s",
            NanonisConfig {
                reconnect_backoff_s: 2.0 * MAX_RECONNECT_BACKOFF_S,
                ..spm_nanonis_sim::loopback_config(9)
            },
        ),
    ] {
        let e = config.validate().expect_err(field);
        assert_eq!(e.kind, spm_nanonis::NanonisErrorKind::Configuration, "{e}");
        assert!(e.to_string().contains(field), "{field}: {e}");
        let e = NanonisMicroscope::connect(config).expect_err(field);
        assert!(e.to_string().contains(field), "{field}: {e}");
    }
    let at_the_bound = NanonisConfig {
        reconnect_attempts: MAX_RECONNECT_ATTEMPTS,
        reconnect_backoff_s: MAX_RECONNECT_BACKOFF_S,
        ..spm_nanonis_sim::loopback_config(9)
    };
    at_the_bound.validate().unwrap();
}

/// Issue 25 item 12: a client whose controller is gone stops reconnecting at a stop request
/// instead of working through its attempts (here 100 with 2 s pauses: over 3 minutes).
#[test]
fn a_client_whose_server_is_gone_stops_reconnecting_at_a_stop_request() {
    let server = crate::common::serve_ideal();
    let config = NanonisConfig {
        reconnect_attempts: spm_nanonis::client::MAX_RECONNECT_ATTEMPTS,
        reconnect_backoff_s: spm_nanonis::client::MAX_RECONNECT_BACKOFF_S,
        ..spm_nanonis_sim::loopback_config(server.addr().port())
    };
    let mut client = Client::connect(config.client_config()).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    client.set_interrupt(Arc::clone(&stop));
    server.kill();
    // From another thread, while the client retries.
    let setter = {
        let stop = Arc::clone(&stop);
        std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(300));
            stop.store(true, Ordering::SeqCst);
        })
    };
    let started = std::time::Instant::now();
    let e = client.call(&Request::ScanStatusGet).unwrap_err();
    let waited = started.elapsed();
    setter.join().unwrap();
    assert_eq!(e.kind, spm_nanonis::NanonisErrorKind::Aborted, "{e}");
    assert!(
        e.to_string().contains("interrupted while reconnecting"),
        "{e}"
    );
    // One pause slice after the flag (0.1 s) and a refused connection at most; without the
    // flag the loop would pause 2 s at a time for over 3 minutes.
    assert!(
        waited < std::time::Duration::from_secs(30),
        "stopped only after {waited:?}"
    );
}
