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
use spm_nanonis_sim::{Server, ServerConfig, SocketFaults};
use spm_sim::SimConfig;
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
    let server = Server::bind(
        "127.0.0.1:0",
        SimConfig::ideal(),
        ServerConfig::new(SocketFaults::none()),
    )
    .unwrap()
    .spawn()
    .unwrap();
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
