//! The frames SPECS' own Python client (`nanonis-spm` 1.0.9) exchanged with nanonis-sim in
//! the conformance session (`tests/data/vendor_session.txt`, written by
//! `examples/vendor_conformance.rs`), replayed against spm-nanonis:
//!
//! - every request the vendor client sent decodes strictly (the server's side), and
//!   spm-nanonis encodes the same request to the same bytes (the client's side);
//! - a server that answers with the captured replies serves spm-nanonis's blocking client
//!   the whole session: each reply decodes strictly to the value the captured bytes hold,
//!   with an error exactly where the vendor client saw one.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_nanonis::codec::{
    CodecError, HEADER_LEN, decode_request_header, decode_response_header, encode_request_header,
};
use spm_nanonis::commands::{Reply, Request, Schema};
use spm_nanonis::{Client, ClientConfig};
use std::io::{Read, Write};
use std::net::TcpListener;
use std::path::Path;

struct Exchange {
    request: Vec<u8>,
    reply: Vec<u8>,
}

fn hex(text: &str) -> Vec<u8> {
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&text[i..i + 2], 16).expect("hex"))
        .collect()
}

fn session() -> Vec<Exchange> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/vendor_session.txt");
    let text = std::fs::read_to_string(path).expect("the captured session");
    let mut out = Vec::new();
    let mut request = None;
    for line in text.lines() {
        if let Some(r) = line.strip_prefix("> ") {
            request = Some(hex(r));
        } else if let Some(r) = line.strip_prefix("< ") {
            out.push(Exchange {
                request: request.take().expect("a request before its reply"),
                reply: hex(r),
            });
        }
    }
    out
}

fn schema() -> Schema {
    Schema::for_release(spm_nanonis_sim::server::DEFAULT_HOST_RELEASE)
}

fn split(frame: &[u8]) -> ([u8; HEADER_LEN], &[u8]) {
    let mut header = [0u8; HEADER_LEN];
    header.copy_from_slice(&frame[..HEADER_LEN]);
    (header, &frame[HEADER_LEN..])
}

/// The request of an exchange, `None` for a command spm-nanonis does not know.
fn request_of(e: &Exchange) -> Option<Request> {
    let (header, body) = split(&e.request);
    let header = decode_request_header(&header).expect("the vendor's header is the manual's");
    assert_eq!(header.body_len, body.len());
    match Request::decode(&header.command, body, schema()) {
        Ok(r) => Some(r),
        Err(CodecError::UnknownCommand(_)) => None,
        Err(other) => panic!("{}: {other}", header.command),
    }
}

#[test]
fn the_vendor_clients_requests_are_spm_nanonis_requests_byte_for_byte() {
    let exchanges = session();
    assert!(exchanges.len() > 80, "{} exchanges", exchanges.len());
    let mut names = std::collections::BTreeSet::new();
    let mut unknown = 0;
    for e in &exchanges {
        let Some(request) = request_of(e) else {
            // Not implemented: the reply is an error the manual's layout decodes.
            let (header, body) = split(&e.reply);
            let header = decode_response_header(&header).expect("reply header");
            assert_eq!(header.body_len, body.len());
            let text = String::from_utf8_lossy(body);
            assert!(text.ends_with(&format!("does not implement {}", header.command)));
            unknown += 1;
            continue;
        };
        names.insert(request.name());
        let (header, body) = split(&e.request);
        assert_eq!(
            request.encode(schema()).expect("encodes"),
            body,
            "{}",
            request.name()
        );
        assert_eq!(
            encode_request_header(request.name(), body.len(), true).expect("header"),
            header,
            "{}",
            request.name()
        );
    }
    // Every command nanonis-sim implements is in the session, and a few it does not.
    assert_eq!(names.len(), 34, "{names:?}");
    assert!(unknown >= 4, "{unknown}");
}

#[test]
fn spm_nanonis_reads_every_captured_reply() {
    let exchanges: Vec<(Request, Exchange)> = session()
        .into_iter()
        .filter_map(|e| request_of(&e).map(|r| (r, e)))
        .collect();
    let replies: Vec<Vec<u8>> = exchanges.iter().map(|(_, e)| e.reply.clone()).collect();
    let requests: Vec<Vec<u8>> = exchanges.iter().map(|(_, e)| e.request.clone()).collect();
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    // The replaying server: each request must be the captured one; the captured reply goes
    // back.
    let replay = std::thread::spawn(move || {
        let (mut stream, _) = listener.accept().unwrap();
        for (request, reply) in requests.iter().zip(&replies) {
            let mut got = vec![0u8; request.len()];
            stream.read_exact(&mut got).unwrap();
            assert_eq!(&got, request);
            stream.write_all(reply).unwrap();
        }
    });
    // Connecting asks Util.VersionGet: the session's first exchange.
    assert_eq!(exchanges[0].0, Request::UtilVersionGet);
    let mut client = Client::connect(ClientConfig {
        host: "127.0.0.1".into(),
        port,
        connect_timeout_s: 2.0,
        command_timeout_s: 5.0,
        wait_margin_s: 1.0,
        reconnect_attempts: 0,
        reconnect_backoff_s: 0.01,
    })
    .unwrap();
    assert_eq!(
        client.version().map(|v| v.host_release),
        Some(spm_nanonis_sim::server::DEFAULT_HOST_RELEASE)
    );
    let mut errors = 0;
    for (request, e) in &exchanges[1..] {
        let (_, body) = split(&e.reply);
        let (expected, error) = request.decode_reply(body, schema()).expect("strict");
        match client.call(request) {
            Ok(reply) => {
                assert_eq!(error.status, 0, "{}", request.name());
                assert_eq!(reply, expected, "{}", request.name());
                if let Reply::FrameData(d) = &reply {
                    assert!(d.data.iter().all(|z| z.is_finite()));
                }
            }
            Err(err) => {
                assert_ne!(error.status, 0, "{}: {err}", request.name());
                assert!(err.to_string().contains(&error.description));
                errors += 1;
            }
        }
    }
    // The out-of-range Follow-Me target.
    assert_eq!(errors, 1);
    replay.join().unwrap();
}
