//! Issue 25 item 11: the server bounds what its clients can make it hold. Over real sockets:
//! a connection beyond the cap is closed while the first ones are still served; a client
//! that sends half a header and stalls is dropped at the message timeout while others are
//! served, and an idle one at the idle timeout; a claimed huge body that never arrives
//! allocates one chunk per connection (the server's own count of its buffers' capacity); a
//! body above the limit closes the connection. On the binary (`spmcal`'s `hostile.rs`): the
//! same claims under a 1 GiB address-space limit (`issue25_11_claimed_huge_bodies_…`, where
//! the whole-body buffers of before exhausted it) and the accept-error backoff under
//! `ulimit -n` (`issue25_11_accept_errors_back_off_instead_of_spinning`).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_nanonis::codec::{self, HEADER_LEN};
use spm_nanonis_sim::{
    BODY_CHUNK_BYTES, ConnectionLimits, Server, ServerConfig, ServerHandle, SocketFaults,
    accept_pause,
};
use spm_sim::SimConfig;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::time::{Duration, Instant};

fn server(limits: ConnectionLimits) -> ServerHandle {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/sim-hopg.toml");
    let sim = SimConfig::from_file(path).unwrap().without_random_faults();
    let mut config = ServerConfig::new(SocketFaults::none());
    config.limits = limits;
    Server::bind("127.0.0.1:0", sim, config)
        .unwrap()
        .spawn()
        .unwrap()
}

fn connect(server: &ServerHandle) -> TcpStream {
    let s = TcpStream::connect(server.addr()).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    s
}

/// Sends `Util.VersionGet` and reads its reply: true when the server answered.
fn served(stream: &mut TcpStream) -> bool {
    let header = codec::encode_request_header("Util.VersionGet", 0, true).unwrap();
    if stream.write_all(&header).is_err() {
        return false;
    }
    let mut reply = [0u8; HEADER_LEN];
    if stream.read_exact(&mut reply).is_err() {
        return false;
    }
    let reply = codec::decode_response_header(&reply).unwrap();
    let mut body = vec![0u8; reply.body_len];
    stream.read_exact(&mut body).is_ok() && reply.command == "Util.VersionGet"
}

/// Waits until the server closes `stream` (EOF or reset); the time it took.
fn closed_after(stream: &mut TcpStream) -> Duration {
    let start = Instant::now();
    let mut byte = [0u8; 1];
    match stream.read(&mut byte) {
        Ok(0) => start.elapsed(),
        Ok(_) => panic!("the server sent data instead of closing"),
        Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => start.elapsed(),
        Err(e) => panic!("the connection was not closed: {e}"),
    }
}

fn wait_for(what: &str, mut done: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(10);
    while !done() {
        assert!(Instant::now() < deadline, "{what}: not within 10 s");
        std::thread::sleep(Duration::from_millis(5));
    }
}

#[test]
fn a_connection_beyond_the_cap_is_closed_and_the_first_ones_still_served() {
    let server = server(ConnectionLimits {
        max_connections: 3,
        ..ConnectionLimits::default()
    });
    let mut first: Vec<TcpStream> = (0..3).map(|_| connect(&server)).collect();
    for s in &mut first {
        assert!(served(s));
    }
    let mut extra = connect(&server);
    closed_after(&mut extra);
    assert!(
        !served(&mut extra),
        "the connection beyond the cap was served"
    );
    for s in &mut first {
        assert!(served(s), "a connection within the cap is no longer served");
    }
    let stats = server.stats();
    assert_eq!(stats.refused_connections, 1, "{stats:?}");
    assert_eq!(server.active_connections(), 3);
    // A closed connection frees its place.
    drop(first.pop());
    wait_for("the closed connection's place freed", || {
        server.active_connections() == 2
    });
    let mut next = connect(&server);
    assert!(served(&mut next));
}

#[test]
fn a_stalled_half_header_or_an_idle_client_is_dropped_at_its_timeout() {
    let message_timeout = Duration::from_millis(300);
    let idle_timeout = Duration::from_millis(800);
    let server = server(ConnectionLimits {
        message_timeout_s: message_timeout.as_secs_f64(),
        idle_timeout_s: idle_timeout.as_secs_f64(),
        ..ConnectionLimits::default()
    });
    let mut stalled = connect(&server);
    let header = codec::encode_request_header("Util.VersionGet", 0, true).unwrap();
    stalled.write_all(&header[..HEADER_LEN / 2]).unwrap();
    let mut idle = connect(&server);
    let idle_since = Instant::now();
    let mut other = connect(&server);
    assert!(served(&mut other), "another client is served meanwhile");
    let waited = closed_after(&mut stalled);
    assert!(
        waited <= message_timeout + Duration::from_secs(2),
        "the stalled client was dropped after {waited:?}"
    );
    assert!(
        served(&mut other),
        "another client is served after the drop"
    );
    closed_after(&mut idle);
    let idle_for = idle_since.elapsed();
    assert!(
        idle_for >= idle_timeout && idle_for <= idle_timeout + Duration::from_secs(2),
        "the idle client was dropped after {idle_for:?}"
    );
    // `other` was used within the idle timeout: still served after it.
    assert!(served(&mut other));
    let stats = server.stats();
    assert_eq!(stats.timed_out_connections, 2, "{stats:?}");
}

#[test]
fn a_claimed_huge_body_that_never_arrives_allocates_one_chunk() {
    const CLIENTS: usize = 20;
    let claimed = codec::MAX_BODY_LEN; // 80 MiB, the protocol's limit
    let server = server(ConnectionLimits {
        max_connections: CLIENTS + 1,
        max_request_body_bytes: claimed,
        ..ConnectionLimits::default()
    });
    let clients: Vec<TcpStream> = (0..CLIENTS)
        .map(|_| {
            let mut s = connect(&server);
            let header = codec::encode_request_header("Scan.PropsSet", claimed, true).unwrap();
            s.write_all(&header).unwrap();
            s.write_all(&[0u8; 10]).unwrap();
            s
        })
        .collect();
    // Every connection has read its header and started its body.
    wait_for("every body started", || {
        server.request_buffer_bytes() >= CLIENTS * BODY_CHUNK_BYTES
    });
    std::thread::sleep(Duration::from_millis(100));
    let held = server.request_buffer_bytes();
    assert_eq!(
        held,
        CLIENTS * BODY_CHUNK_BYTES,
        "{CLIENTS} claims of {claimed} bytes hold {held} bytes"
    );
    drop(clients);
    wait_for("the buffers released", || {
        server.request_buffer_bytes() == 0
    });
    assert_eq!(
        server.stats().request_buffer_bytes_peak,
        (CLIENTS * BODY_CHUNK_BYTES) as u64
    );
    // A claim above the limit closes the connection at once; others are still served.
    let small = server_with_default_limits();
    let mut s = connect(&small);
    let header = codec::encode_request_header("Scan.PropsSet", 2 << 20, true).unwrap();
    s.write_all(&header).unwrap();
    closed_after(&mut s);
    assert_eq!(small.stats().oversized_requests, 1);
    assert_eq!(small.stats().request_buffer_bytes_peak, 0);
    assert!(served(&mut connect(&small)));
}

fn server_with_default_limits() -> ServerHandle {
    server(ConnectionLimits::default())
}

#[test]
fn accept_pauses_grow_from_10_ms_to_1_s() {
    let pauses: Vec<u64> = (1..=10)
        .map(|n| accept_pause(n).as_millis() as u64)
        .collect();
    assert_eq!(pauses, [10, 20, 40, 80, 160, 320, 640, 1000, 1000, 1000]);
    assert_eq!(accept_pause(u32::MAX), Duration::from_secs(1));
}

#[test]
fn limits_are_validated_and_optional_in_a_config() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/sim-hopg.toml");
    let sim = SimConfig::from_file(path).unwrap();
    for bad in [
        ConnectionLimits {
            max_connections: 0,
            ..ConnectionLimits::default()
        },
        ConnectionLimits {
            message_timeout_s: f64::NAN,
            ..ConnectionLimits::default()
        },
        ConnectionLimits {
            idle_timeout_s: 1e308,
            ..ConnectionLimits::default()
        },
        ConnectionLimits {
            max_request_body_bytes: codec::MAX_BODY_LEN + 1,
            ..ConnectionLimits::default()
        },
    ] {
        let mut config = ServerConfig::new(SocketFaults::none());
        config.limits = bad.clone();
        assert!(
            Server::bind("127.0.0.1:0", sim.clone(), config).is_err(),
            "{bad:?} accepted"
        );
    }
    // A config written before the limits existed still reads, with the defaults.
    let mut text = toml::to_string(&ServerConfig::new(SocketFaults::none())).unwrap();
    let at = text.find("[limits]").unwrap();
    text.truncate(at);
    let config: ServerConfig = toml::from_str(&text).unwrap();
    assert_eq!(config.limits, ConnectionLimits::default());
}
