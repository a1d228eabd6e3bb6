//! Read-only smoke test against a real Nanonis controller, `#[ignore]`d: it runs only when
//! `SPMCAL_NANONIS_ADDR=host:port` names the controller's first TCP programming-interface
//! port, and it sends only `*Get` commands (version, piezo calibration and range, the
//! compensation state, Z feedback status, tip position, Z, scan status, buffer, frame and
//! speed): it moves nothing, scans nothing and changes no setting.
//!
//! ```sh
//! SPMCAL_NANONIS_ADDR=192.168.1.10:6501 cargo test -p spmcal-tests --test it nanonis_smoke:: -- --ignored --nocapture
//! ```
#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_nanonis::commands::{Reply, Request};
use spm_nanonis::{Client, ClientConfig};

#[test]
#[ignore = "needs a controller: SPMCAL_NANONIS_ADDR=host:port"]
fn a_real_controller_answers_every_read_the_backend_relies_on() {
    let address = std::env::var("SPMCAL_NANONIS_ADDR")
        .expect("set SPMCAL_NANONIS_ADDR=host:port to run this test");
    let (host, port) = address
        .rsplit_once(':')
        .expect("SPMCAL_NANONIS_ADDR is host:port");
    let mut client = Client::connect(ClientConfig {
        host: host.to_owned(),
        port: port.parse().expect("the port is a number"),
        connect_timeout_s: 3.0,
        command_timeout_s: 5.0,
        wait_margin_s: 5.0,
        reconnect_attempts: 2,
        reconnect_backoff_s: 0.5,
    })
    .expect("the controller accepts the connection and answers Util.VersionGet");
    let version = client.version().cloned().expect("a version");
    eprintln!("{version:?}; schema {:?}", client.schema());
    assert!(version.host_release > 0);
    for request in [
        Request::PiezoCalibrGet,
        Request::PiezoRangeGet,
        Request::PiezoDriftCompGet,
        Request::PiezoTiltGet,
        Request::PiezoHystOnOffGet,
        Request::ZCtrlOnOffGet,
        Request::FolMeXYPosGet { wait_newest: 0 },
        Request::ZCtrlZPosGet,
        Request::ScanStatusGet,
        Request::ScanBufferGet,
        Request::ScanFrameGet,
        Request::ScanSpeedGet,
    ] {
        let reply = client
            .call(&request)
            .unwrap_or_else(|e| panic!("{}: {e}", request.name()));
        eprintln!("{}: {reply:?}", request.name());
        if let (Request::PiezoCalibrGet, Reply::F32x3(c)) = (&request, &reply) {
            assert!(c.iter().all(|v| v.is_finite() && *v > 0.0), "{c:?}");
        }
    }
    // The coarse motor is optional: report, do not require.
    match client.call(&Request::MotorFreqAmpGet(3)) {
        Ok(reply) => eprintln!("Motor.FreqAmpGet: {reply:?}"),
        Err(e) => eprintln!("no coarse motor answers: {e}"),
    }
}
