//! The client-side watchdog of a PostgreSQL connection (issue 25 item 4): a server whose
//! backend is stopped (SIGSTOP, a hung host under a live kernel) still has its kernel
//! acknowledge every byte, so neither TCP keepalive nor `tcp_user_timeout` ever fires and a
//! blocked call of the `postgres` client would wait for ever. The client hides its socket,
//! so every connection runs through a relay this module owns: the client talks to a
//! loopback socket accepted here, and two pump threads copy the bytes to and from the
//! server. The relay follows the protocol's framing to know when the client waits for the
//! server (every StartupMessage, Query, Sync and FunctionCall is answered by one
//! ReadyForQuery; the Sync sent with a `COPY … FROM STDIN` is ignored by the server, so
//! its CopyInResponse closes it), and a watchdog thread shuts both sockets down when the
//! client has waited [`Link::reply_timeout`] with no byte from the server (the call then
//! fails at once as a closed connection, reported as
//! [`CdbError::Unanswered`](crate::CdbError::Unanswered)), or, once the run's stop flag is
//! set, after [`STOP_GRACE_S`] of such silence (reported as
//! [`CdbError::Interrupted`](crate::CdbError::Interrupted)). Time the client itself takes to
//! read what the server sent never counts as the server's silence.

use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU8, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

/// Once the stop flag is set, a wait for the server that has been silent this long is cut, s.
pub const STOP_GRACE_S: f64 = 1.0;
/// How often the watchdog looks, s.
const WATCH_PERIOD_S: f64 = 0.05;

/// Why a connection was cut.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Cut {
    /// The server did not answer within the reply timeout.
    Unanswered,
    /// The stop flag was set while the client waited for the server.
    Interrupted,
    /// A test asked to lose the server's reply to the next COMMIT.
    LostCommitReply,
}

const CUT_NONE: u8 = 0;

impl Cut {
    fn code(self) -> u8 {
        match self {
            Self::Unanswered => 1,
            Self::Interrupted => 2,
            Self::LostCommitReply => 3,
        }
    }
    fn from_code(code: u8) -> Option<Self> {
        match code {
            1 => Some(Self::Unanswered),
            2 => Some(Self::Interrupted),
            3 => Some(Self::LostCommitReply),
            _ => None,
        }
    }
}

/// The server side of the relay.
enum Upstream {
    Tcp(TcpStream),
    #[cfg(unix)]
    Unix(std::os::unix::net::UnixStream),
}

impl Upstream {
    fn try_clone(&self) -> std::io::Result<Self> {
        Ok(match self {
            Self::Tcp(s) => Self::Tcp(s.try_clone()?),
            #[cfg(unix)]
            Self::Unix(s) => Self::Unix(s.try_clone()?),
        })
    }
    fn shutdown(&self) {
        let _ = match self {
            Self::Tcp(s) => s.shutdown(Shutdown::Both),
            #[cfg(unix)]
            Self::Unix(s) => s.shutdown(Shutdown::Both),
        };
    }
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        match self {
            Self::Tcp(s) => s.read(buf),
            #[cfg(unix)]
            Self::Unix(s) => s.read(buf),
        }
    }
    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        match self {
            Self::Tcp(s) => s.write_all(buf),
            #[cfg(unix)]
            Self::Unix(s) => s.write_all(buf),
        }
    }
}

/// State shared by the pumps, the watchdog and the [`Link`].
struct Shared {
    base: Instant,
    /// Requests the server has not yet answered with ReadyForQuery.
    outstanding: AtomicI64,
    /// Last byte read from the server or written to it, ms after `base`.
    last_progress_ms: AtomicU64,
    /// True while a pump hands the server's bytes to a client that does not read them yet.
    delivering: AtomicBool,
    cut: AtomicU8,
    closed: AtomicBool,
    /// When the [`Link`] was dropped, ms after `base` plus one (0: it was not).
    owner_gone_ms: AtomicU64,
    reply_timeout: Duration,
    stop: OnceLock<Arc<AtomicBool>>,
    lose_commit_reply: AtomicBool,
    sockets: Mutex<Vec<Box<dyn Fn() + Send>>>,
}

impl Shared {
    fn now_ms(&self) -> u64 {
        u64::try_from(self.base.elapsed().as_millis()).unwrap_or(u64::MAX)
    }
    fn progress(&self) {
        self.last_progress_ms.store(self.now_ms(), Ordering::SeqCst);
    }
    fn cut(&self, why: Cut) {
        let _ = self
            .cut
            .compare_exchange(CUT_NONE, why.code(), Ordering::SeqCst, Ordering::SeqCst);
        self.close();
    }
    fn close(&self) {
        self.closed.store(true, Ordering::SeqCst);
        if let Ok(sockets) = self.sockets.lock() {
            for shut in sockets.iter() {
                shut();
            }
        }
    }
    fn add_request(&self, n: i64) {
        if n != 0 {
            let _ = self
                .outstanding
                .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |v| Some((v + n).max(0)));
        }
    }
}

/// One relayed connection: where the client connects, and what its watchdog saw.
pub(crate) struct Link {
    shared: Arc<Shared>,
    port: u16,
}

impl std::fmt::Debug for Link {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Link").field("port", &self.port).finish()
    }
}

impl Drop for Link {
    /// The client is dropped first and closes its socket, which ends the pumps after its
    /// goodbye reached the server; a relay still open a moment later (a client given up
    /// while connecting) is closed by the watchdog.
    fn drop(&mut self) {
        self.shared
            .owner_gone_ms
            .store(self.shared.now_ms() + 1, Ordering::SeqCst);
    }
}

/// How long a relay may outlive its [`Link`] before the watchdog closes it, ms.
const ORPHAN_GRACE_MS: u64 = 1000;

/// Where the server is: `(host, port)` pairs tried in order, as the client would.
pub(crate) enum Target {
    Tcp(String, u16),
    Addr(std::net::IpAddr, u16),
    #[cfg(unix)]
    Socket(std::path::PathBuf),
}

fn open_upstream(targets: &[Target], timeout: Duration) -> std::io::Result<Upstream> {
    let mut last = std::io::Error::new(std::io::ErrorKind::NotFound, "no host to connect to");
    for target in targets {
        let addrs: Vec<SocketAddr> = match target {
            Target::Tcp(host, port) => match (host.as_str(), *port).to_socket_addrs() {
                Ok(a) => a.collect(),
                Err(e) => {
                    last = e;
                    continue;
                }
            },
            Target::Addr(ip, port) => vec![SocketAddr::new(*ip, *port)],
            #[cfg(unix)]
            Target::Socket(path) => match std::os::unix::net::UnixStream::connect(path) {
                Ok(s) => return Ok(Upstream::Unix(s)),
                Err(e) => {
                    last = std::io::Error::new(e.kind(), format!("{}: {e}", path.display()));
                    continue;
                }
            },
        };
        for addr in addrs {
            match TcpStream::connect_timeout(&addr, timeout) {
                Ok(s) => {
                    let _ = s.set_nodelay(true);
                    return Ok(Upstream::Tcp(s));
                }
                Err(e) => last = std::io::Error::new(e.kind(), format!("{addr}: {e}")),
            }
        }
    }
    Err(last)
}

impl Link {
    /// Connects to the first target that accepts (each within `timeout`) and listens on a
    /// loopback port for the client, which must connect within `timeout`.
    pub(crate) fn open(
        targets: &[Target],
        timeout: Duration,
        reply_timeout: Duration,
    ) -> std::io::Result<Self> {
        let upstream = open_upstream(targets, timeout)?;
        let listener = TcpListener::bind(("127.0.0.1", 0))?;
        let port = listener.local_addr()?.port();
        listener.set_nonblocking(true)?;
        let shared = Arc::new(Shared {
            base: Instant::now(),
            outstanding: AtomicI64::new(0),
            last_progress_ms: AtomicU64::new(0),
            delivering: AtomicBool::new(false),
            cut: AtomicU8::new(CUT_NONE),
            closed: AtomicBool::new(false),
            owner_gone_ms: AtomicU64::new(0),
            reply_timeout,
            stop: OnceLock::new(),
            lose_commit_reply: AtomicBool::new(false),
            sockets: Mutex::new(Vec::new()),
        });
        {
            let up = upstream.try_clone()?;
            if let Ok(mut sockets) = shared.sockets.lock() {
                sockets.push(Box::new(move || up.shutdown()));
            }
        }
        let accept_shared = Arc::clone(&shared);
        std::thread::Builder::new()
            .name("postgres-relay".to_owned())
            .spawn(move || accept_and_pump(&listener, upstream, &accept_shared, timeout))?;
        let watch_shared = Arc::clone(&shared);
        std::thread::Builder::new()
            .name("postgres-watchdog".to_owned())
            .spawn(move || watch(&watch_shared))?;
        Ok(Self { shared, port })
    }

    /// The loopback port the client connects to.
    pub(crate) fn port(&self) -> u16 {
        self.port
    }

    /// The reply timeout of this connection.
    pub(crate) fn reply_timeout(&self) -> Duration {
        self.shared.reply_timeout
    }

    /// Why the watchdog cut the connection, if it did.
    pub(crate) fn cut(&self) -> Option<Cut> {
        Cut::from_code(self.shared.cut.load(Ordering::SeqCst))
    }

    /// Watches `stop`: once set, a silent wait for the server is cut after [`STOP_GRACE_S`].
    pub(crate) fn set_stop(&self, stop: Arc<AtomicBool>) {
        let _ = self.shared.stop.set(stop);
    }

    /// Tests: the server's reply to the next COMMIT is dropped and the connection cut, as
    /// when a connection is lost after the server committed but before the client heard.
    pub(crate) fn lose_next_commit_reply(&self) {
        self.shared.lose_commit_reply.store(true, Ordering::SeqCst);
    }
}

/// Accepts the client (within `timeout`), then copies client → server here and server →
/// client on a second thread.
fn accept_and_pump(
    listener: &TcpListener,
    mut upstream: Upstream,
    shared: &Arc<Shared>,
    timeout: Duration,
) {
    let deadline = Instant::now() + timeout + Duration::from_secs(1);
    let client = loop {
        match listener.accept() {
            Ok((stream, peer)) if peer.ip().is_loopback() => break stream,
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                if Instant::now() > deadline || shared.closed.load(Ordering::SeqCst) {
                    shared.close();
                    return;
                }
                std::thread::sleep(Duration::from_millis(1));
            }
            Err(_) => {
                shared.close();
                return;
            }
        }
    };
    let setup = || -> std::io::Result<(TcpStream, Upstream)> {
        client.set_nonblocking(false)?;
        client.set_nodelay(true)?;
        let shut = client.try_clone()?;
        if let Ok(mut sockets) = shared.sockets.lock() {
            sockets.push(Box::new(move || {
                let _ = shut.shutdown(Shutdown::Both);
            }));
        }
        Ok((client.try_clone()?, upstream.try_clone()?))
    };
    let Ok((client_writer, upstream_reader)) = setup() else {
        shared.close();
        return;
    };
    let down_shared = Arc::clone(shared);
    if std::thread::Builder::new()
        .name("postgres-relay-down".to_owned())
        .spawn(move || pump_down(upstream_reader, client_writer, &down_shared))
        .is_err()
    {
        shared.close();
        return;
    }
    pump_up(client, &mut upstream, shared);
}

/// Client → server: counts the requests that await a ReadyForQuery.
fn pump_up(mut client: TcpStream, upstream: &mut Upstream, shared: &Shared) {
    let mut framer = Framer::new(true);
    let mut buf = vec![0u8; 64 * 1024];
    loop {
        let n = match client.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => n,
        };
        let mut requests = 0;
        framer.feed(&buf[..n], &mut |kind, _| {
            if matches!(kind, Kind::Startup | Kind::Typed(b'Q' | b'S' | b'F')) {
                requests += 1;
            }
        });
        shared.add_request(requests);
        if requests > 0 {
            shared.progress();
        }
        if upstream.write_all(&buf[..n]).is_err() {
            break;
        }
        shared.progress();
    }
    shared.close();
}

/// Server → client: counts the ReadyForQuery (and CopyInResponse) messages.
fn pump_down(mut upstream: Upstream, mut client: TcpStream, shared: &Shared) {
    let mut framer = Framer::new(false);
    let mut buf = vec![0u8; 64 * 1024];
    loop {
        let n = match upstream.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => n,
        };
        shared.progress();
        let mut answered = 0;
        let mut commit_reply = false;
        framer.feed(&buf[..n], &mut |kind, body| match kind {
            Kind::Typed(b'Z' | b'G') => answered += 1,
            Kind::Typed(b'C') if body.starts_with(b"COMMIT") => commit_reply = true,
            _ => {}
        });
        if commit_reply && shared.lose_commit_reply.swap(false, Ordering::SeqCst) {
            shared.cut(Cut::LostCommitReply);
            break;
        }
        shared.delivering.store(true, Ordering::SeqCst);
        let written = client.write_all(&buf[..n]);
        shared.delivering.store(false, Ordering::SeqCst);
        shared.progress();
        shared.add_request(-answered);
        if written.is_err() {
            break;
        }
    }
    shared.close();
}

/// Cuts a wait for the server at the reply timeout, or soon after a stop request.
fn watch(shared: &Shared) {
    let period = Duration::from_secs_f64(WATCH_PERIOD_S);
    let reply_ms = u64::try_from(shared.reply_timeout.as_millis()).unwrap_or(u64::MAX);
    let grace_ms = (STOP_GRACE_S * 1000.0) as u64;
    while !shared.closed.load(Ordering::SeqCst) {
        std::thread::sleep(period);
        let gone = shared.owner_gone_ms.load(Ordering::SeqCst);
        if gone > 0 && shared.now_ms().saturating_sub(gone) > ORPHAN_GRACE_MS {
            shared.close();
            break;
        }
        if shared.outstanding.load(Ordering::SeqCst) <= 0
            || shared.delivering.load(Ordering::SeqCst)
        {
            continue;
        }
        let silent_ms = shared
            .now_ms()
            .saturating_sub(shared.last_progress_ms.load(Ordering::SeqCst));
        if silent_ms > reply_ms {
            tracing::warn!(
                silent_s = silent_ms as f64 / 1000.0,
                "PostgreSQL: no reply within the reply timeout; connection cut"
            );
            shared.cut(Cut::Unanswered);
        } else if silent_ms > grace_ms
            && shared.stop.get().is_some_and(|s| s.load(Ordering::SeqCst))
        {
            tracing::warn!(
                "PostgreSQL: stop requested while waiting for the server; connection cut"
            );
            shared.cut(Cut::Interrupted);
        }
    }
}

/// A protocol message seen by a [`Framer`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    /// An untyped start-up packet (StartupMessage, SSLRequest, …).
    Startup,
    /// A typed message.
    Typed(u8),
}

/// SSLRequest and GSSENCRequest codes: the server answers with one untyped byte.
const ENCRYPTION_REQUESTS: [u32; 2] = [80_877_103, 80_877_104];

/// Splits a byte stream into protocol messages as the bytes arrive, handing each message's
/// kind and the first bytes of its body (up to 16) to a callback once its header is read.
struct Framer {
    /// The client's side sends untyped packets first (an encryption request, which the
    /// client here never sends, then the StartupMessage); the server's are all typed.
    untyped_next: bool,
    header: Vec<u8>,
    /// Bytes of the current message's body still to skip.
    remaining: usize,
    kind: Option<Kind>,
    prefix: Vec<u8>,
}

impl Framer {
    fn new(client: bool) -> Self {
        Self {
            untyped_next: client,
            header: Vec::with_capacity(8),
            remaining: 0,
            kind: None,
            prefix: Vec::new(),
        }
    }

    fn feed(&mut self, mut bytes: &[u8], each: &mut dyn FnMut(Kind, &[u8])) {
        while !bytes.is_empty() {
            if self.remaining > 0 {
                let take = self.remaining.min(bytes.len());
                if let Some(kind) = self.kind {
                    let want = 16usize.saturating_sub(self.prefix.len()).min(take);
                    self.prefix.extend_from_slice(&bytes[..want]);
                    if self.prefix.len() >= 16 || take == self.remaining {
                        each(kind, &self.prefix);
                        self.kind = None;
                    }
                }
                self.remaining -= take;
                bytes = &bytes[take..];
                continue;
            }
            let header_len = if self.untyped_next { 4 } else { 5 };
            let take = (header_len - self.header.len()).min(bytes.len());
            self.header.extend_from_slice(&bytes[..take]);
            bytes = &bytes[take..];
            if self.header.len() < header_len {
                continue;
            }
            let (kind, len_bytes) = if self.untyped_next {
                (Kind::Startup, &self.header[..4])
            } else {
                (Kind::Typed(self.header[0]), &self.header[1..5])
            };
            let length =
                u32::from_be_bytes([len_bytes[0], len_bytes[1], len_bytes[2], len_bytes[3]]);
            let body = (length as usize).saturating_sub(4);
            self.header.clear();
            self.prefix.clear();
            if kind == Kind::Startup {
                // An encryption request (8 bytes: length and code) is answered by one raw
                // byte, then the StartupMessage follows; it awaits no ReadyForQuery.
                let code_wanted = body == 4;
                if code_wanted && bytes.len() >= 4 {
                    let code = u32::from_be_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]);
                    if ENCRYPTION_REQUESTS.contains(&code) {
                        self.remaining = 4;
                        self.kind = None;
                        continue;
                    }
                }
                self.untyped_next = false;
            }
            if body == 0 {
                each(kind, &[]);
            } else {
                self.remaining = body;
                self.kind = Some(kind);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kinds(client: bool, chunks: &[&[u8]]) -> Vec<(Kind, Vec<u8>)> {
        let mut f = Framer::new(client);
        let mut out = Vec::new();
        for c in chunks {
            f.feed(c, &mut |k, b| out.push((k, b.to_vec())));
        }
        out
    }

    fn typed(t: u8, body: &[u8]) -> Vec<u8> {
        let mut v = vec![t];
        v.extend_from_slice(&(u32::try_from(body.len() + 4).unwrap_or(0)).to_be_bytes());
        v.extend_from_slice(body);
        v
    }

    #[test]
    fn frames_are_found_across_any_split() {
        let mut startup = 12u32.to_be_bytes().to_vec();
        startup.extend_from_slice(&[0, 3, 0, 0, 0, 0, 0, 0]);
        let mut stream = startup;
        stream.extend(typed(b'Q', b"SELECT 1\0"));
        stream.extend(typed(b'S', b""));
        stream.extend(typed(b'X', b""));
        let want = vec![
            (Kind::Startup, vec![0, 3, 0, 0, 0, 0, 0, 0]),
            (Kind::Typed(b'Q'), b"SELECT 1\0".to_vec()),
            (Kind::Typed(b'S'), vec![]),
            (Kind::Typed(b'X'), vec![]),
        ];
        assert_eq!(kinds(true, &[&stream]), want);
        for split in 1..stream.len() {
            let (a, b) = stream.split_at(split);
            assert_eq!(kinds(true, &[a, b]), want, "split at {split}");
        }
        let bytes: Vec<&[u8]> = stream.chunks(1).collect();
        assert_eq!(kinds(true, &bytes), want);
    }

    #[test]
    fn a_commit_reply_is_seen_by_its_tag() {
        let mut stream = typed(b'C', b"COMMIT\0");
        stream.extend(typed(b'Z', b"I"));
        let got = kinds(false, &[&stream]);
        assert_eq!(got[0], (Kind::Typed(b'C'), b"COMMIT\0".to_vec()));
        assert_eq!(got[1], (Kind::Typed(b'Z'), b"I".to_vec()));
    }
}
