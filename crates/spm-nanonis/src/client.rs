//! A blocking client of the Nanonis TCP protocol.
//!
//! - **Exact frames.** A request is written whole (one `write_all` of header and body); a
//!   reply is read whole (`read_exact` of the 40-byte header, then of exactly the body size it
//!   announces, through a read-ahead: one `recv` usually brings both). A reply is accepted only for the command that was sent and only if its
//!   body decodes to exactly that command's return arguments and error section. After any
//!   I/O, timeout or framing failure the connection is dropped: its byte stream can no
//!   longer be trusted to be at a message boundary. It is reset, not closed, so that
//!   requests sent behind the failed one and not read yet are not executed later.
//! - **Timeouts per command.** Every command has the read timeout
//!   [`ClientConfig::command_timeout_s`]; wait-style commands (`Scan.WaitEndOfScan`, waited
//!   `FolMe.XYPosSet` and `Motor.StartMove`) get their expected duration plus
//!   [`ClientConfig::wait_margin_s`] ([`Client::call_waiting`]).
//!   The timeout is set on the socket only when it differs from the one last set there;
//!   writes have the ordinary timeout, set once per connection.
//! - **Reconnect with backoff.** A dropped connection is re-opened on the next command, up
//!   to [`ClientConfig::reconnect_attempts`] times (at most [`MAX_RECONNECT_ATTEMPTS`]) with
//!   exponential backoff from [`ClientConfig::reconnect_backoff_s`] (at most
//!   [`MAX_RECONNECT_BACKOFF_S`] per pause, so at most [`MAX_RECONNECT_BACKOFF_TOTAL_S`] of
//!   pauses in all); when every attempt fails the error is
//!   [`NanonisErrorKind::Unreachable`]. With a stop flag ([`Client::set_interrupt`]) the
//!   loop ends at the next attempt or within [`RECONNECT_POLL_S`] of a pause, as
//!   [`NanonisErrorKind::Aborted`] (issue 25 item 12: `reconnect_attempts = 4294967295` was
//!   accepted and still retrying 618 s after a SIGTERM). A request refused as busy is sent again, and so is
//!   one whose connection was lost when that is safe ([`Request::is_retry_safe`]: not the
//!   relative motor steps), up to [`RETRIES`] times; other failures are reported and the
//!   caller decides.
//! - **Schema by version.** On every (re)connection `Util.VersionGet` is asked and the
//!   [`Schema`] chosen from the host-application release.
//! - **Pipelines** ([`Client::call_pipelined`]): several requests in one write, their
//!   replies read in order, for a command and what follows it (one round trip where one
//!   call each takes one each: a move with its settle and clock read, a whole scan); nothing
//!   in a pipeline is sent again by the client. Every reply of a pipeline is read, so once
//!   the last is in the controller has executed them all.
//! - **A second connection for stop and abort** ([`Client::stop`]): the manual lets a client
//!   open up to four connections, each serialising its own commands, so a stop sent on a
//!   second connection is executed while the first one is blocked in a wait.

use crate::codec::{self, HEADER_LEN};
use crate::commands::{Reply, Request, Schema, Version};
use crate::error::{NanonisError, NanonisErrorKind};
use serde::{Deserialize, Serialize};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// Connection settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClientConfig {
    /// Controller host name or address.
    pub host: String,
    /// The TCP port of the controller's first programming-interface connection.
    pub port: u16,
    /// Timeout of one connection attempt, s.
    pub connect_timeout_s: f64,
    /// Read and write timeout of an ordinary command, s.
    pub command_timeout_s: f64,
    /// Added to the expected duration of wait-style commands, s.
    pub wait_margin_s: f64,
    /// Reconnect attempts after a dropped connection before giving up (at most
    /// [`MAX_RECONNECT_ATTEMPTS`]).
    pub reconnect_attempts: u32,
    /// First backoff between reconnect attempts, s (doubled each attempt, at most
    /// [`MAX_RECONNECT_BACKOFF_S`]).
    pub reconnect_backoff_s: f64,
}

/// Most reconnect attempts a configuration may ask for: with pauses of at most
/// [`MAX_RECONNECT_BACKOFF_S`], a controller gone for good is declared unreachable within
/// [`MAX_RECONNECT_BACKOFF_TOTAL_S`] of pauses (plus the connection attempts' own timeouts).
pub const MAX_RECONNECT_ATTEMPTS: u32 = 100;

/// Longest pause between two reconnect attempts, s (also the largest first backoff).
pub const MAX_RECONNECT_BACKOFF_S: f64 = 2.0;

/// The pauses of one reconnect loop add up to at most this, s
/// ([`MAX_RECONNECT_ATTEMPTS`] × [`MAX_RECONNECT_BACKOFF_S`]).
pub const MAX_RECONNECT_BACKOFF_TOTAL_S: f64 =
    MAX_RECONNECT_ATTEMPTS as f64 * MAX_RECONNECT_BACKOFF_S;

/// With a stop flag, the longest slice of a reconnect pause before the flag is looked at
/// again, s.
pub const RECONNECT_POLL_S: f64 = 0.1;

impl ClientConfig {
    /// Checks that every duration is finite and positive and that the reconnect loop is
    /// bounded ([`MAX_RECONNECT_ATTEMPTS`], [`MAX_RECONNECT_BACKOFF_S`]); the message names
    /// the field.
    pub fn validate(&self) -> Result<(), NanonisError> {
        if self.reconnect_attempts > MAX_RECONNECT_ATTEMPTS {
            return Err(NanonisError::new(
                NanonisErrorKind::Configuration,
                format!(
                    "reconnect_attempts = {} is more than {MAX_RECONNECT_ATTEMPTS} (a controller \
                     gone for good would be retried for hours)",
                    self.reconnect_attempts
                ),
            ));
        }
        if self.reconnect_backoff_s > MAX_RECONNECT_BACKOFF_S {
            return Err(NanonisError::new(
                NanonisErrorKind::Configuration,
                format!(
                    "reconnect_backoff_s = {} is more than {MAX_RECONNECT_BACKOFF_S} s",
                    self.reconnect_backoff_s
                ),
            ));
        }
        for (field, value) in [
            ("connect_timeout_s", self.connect_timeout_s),
            ("command_timeout_s", self.command_timeout_s),
            ("wait_margin_s", self.wait_margin_s),
            ("reconnect_backoff_s", self.reconnect_backoff_s),
        ] {
            if !(value.is_finite() && value > 0.0 && value < 1e6) {
                return Err(NanonisError::new(
                    NanonisErrorKind::Configuration,
                    format!("{field} = {value} must be a finite number of seconds in (0, 1e6)"),
                ));
            }
        }
        Ok(())
    }

    fn address(&self) -> Result<SocketAddr, NanonisError> {
        (self.host.as_str(), self.port)
            .to_socket_addrs()
            .map_err(|e| {
                NanonisError::new(
                    NanonisErrorKind::Connect,
                    format!("cannot resolve {}:{}: {e}", self.host, self.port),
                )
            })?
            .next()
            .ok_or_else(|| {
                NanonisError::new(
                    NanonisErrorKind::Connect,
                    format!("{}:{} resolves to no address", self.host, self.port),
                )
            })
    }
}

/// Times a request is sent again after a busy reply or a lost connection.
pub const RETRIES: u32 = 3;

fn seconds(s: f64) -> Duration {
    Duration::from_secs_f64(s.clamp(1e-3, 1e6))
}

/// A connection to the controller (see the module documentation).
#[derive(Debug)]
pub struct Client {
    config: ClientConfig,
    stream: Option<Connection>,
    stop_stream: Option<Connection>,
    version: Option<Version>,
    schema: Schema,
    /// Commands sent (including re-sent ones), for statistics.
    commands_sent: u64,
    /// Connections opened after the first one.
    reconnects: u64,
    /// Grows with every command sent on either connection and every connection opened
    /// ([`Client::sequence`]).
    sequence: u64,
    /// Set by whoever stops the run ([`Client::set_interrupt`]).
    interrupt: Option<Arc<AtomicBool>>,
    /// How long a reply is polled for before the thread sleeps ([`Client::set_reply_poll`]).
    reply_poll: Duration,
}

/// Bytes a connection reads ahead: one `recv` brings a reply's header with the body of any
/// reply but a frame's (whose rest is read straight into its own buffer).
const READ_AHEAD_BYTES: usize = 8 << 10;

/// An open connection, read through a read-ahead, and the read timeout last set on it (set
/// again only when a command needs another). The write timeout is the ordinary command
/// timeout, set once: a request is written at once whatever it asks the controller to do.
#[derive(Debug)]
struct Connection {
    stream: std::io::BufReader<TcpStream>,
    timeout: Option<Duration>,
    reply_poll: Duration,
}

impl Connection {
    fn new(
        stream: TcpStream,
        write_timeout: Duration,
        reply_poll: Duration,
    ) -> Result<Self, NanonisError> {
        stream
            .set_write_timeout(Some(write_timeout))
            .map_err(|e| io_error("set timeout", &e))?;
        Ok(Self {
            stream: std::io::BufReader::with_capacity(READ_AHEAD_BYTES, stream),
            timeout: None,
            reply_poll,
        })
    }

    /// Polls for the next reply's first bytes for up to `reply_poll` without sleeping (they
    /// are then in the read-ahead), yielding the CPU between two looks; after that the read
    /// sleeps until they come.
    fn poll_for_reply(&mut self) -> Result<(), NanonisError> {
        use std::io::BufRead;
        if self.reply_poll.is_zero() || !self.stream.buffer().is_empty() {
            return Ok(());
        }
        let set = |s: &TcpStream, on: bool| {
            s.set_nonblocking(on)
                .map_err(|e| io_error("set non-blocking", &e))
        };
        set(self.stream.get_ref(), true)?;
        let until = std::time::Instant::now() + self.reply_poll;
        let polled = loop {
            match self.stream.fill_buf() {
                Ok(_) => break Ok(()),
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::Interrupted
                    ) =>
                {
                    if std::time::Instant::now() >= until {
                        break Ok(());
                    }
                    // Yielded, not spun: the controller's thread may be waiting for this CPU.
                    std::thread::yield_now();
                }
                Err(e) => break Err(io_error("read reply header", &e)),
            }
        };
        set(self.stream.get_ref(), false)?;
        polled
    }

    fn set_timeout(&mut self, timeout: Duration) -> Result<(), NanonisError> {
        if self.timeout == Some(timeout) {
            return Ok(());
        }
        // Forgotten first: a failure half-way leaves it unknown.
        self.timeout = None;
        self.stream
            .get_ref()
            .set_read_timeout(Some(timeout))
            .map_err(|e| io_error("set timeout", &e))?;
        self.timeout = Some(timeout);
        Ok(())
    }
}

impl Client {
    /// Connects and asks the controller's version.
    pub fn connect(config: ClientConfig) -> Result<Self, NanonisError> {
        config.validate()?;
        let mut client = Self {
            config,
            stream: None,
            stop_stream: None,
            version: None,
            schema: Schema::for_release(0),
            commands_sent: 0,
            reconnects: 0,
            sequence: 0,
            interrupt: None,
            reply_poll: Duration::ZERO,
        };
        client.ensure_connected()?;
        client.reconnects = 0;
        Ok(client)
    }

    /// Ends the reconnect loop once `flag` is set: no further attempt is made and a pause is
    /// cut short within [`RECONNECT_POLL_S`]; the command fails as
    /// [`NanonisErrorKind::Aborted`].
    pub fn set_interrupt(&mut self, flag: Arc<AtomicBool>) {
        self.interrupt = Some(flag);
    }

    fn interrupted(&self) -> bool {
        self.interrupt
            .as_ref()
            .is_some_and(|flag| flag.load(Ordering::SeqCst))
    }

    /// The reconnect loop's pause, in slices when a stop flag is set; `Err` once it is.
    fn backoff(&self, pause_s: f64) -> Result<(), NanonisError> {
        let interrupted = || {
            NanonisError::new(
                NanonisErrorKind::Aborted,
                format!(
                    "interrupted while reconnecting to the controller at {}:{}",
                    self.config.host, self.config.port
                ),
            )
        };
        let mut left_s = pause_s;
        loop {
            if self.interrupted() {
                return Err(interrupted());
            }
            if left_s <= 0.0 {
                return Ok(());
            }
            let slice_s = if self.interrupt.is_some() {
                left_s.min(RECONNECT_POLL_S)
            } else {
                left_s
            };
            std::thread::sleep(seconds(slice_s));
            left_s -= slice_s;
        }
    }

    /// Polls for each reply for up to `poll` before the thread sleeps waiting for it (zero,
    /// the default: no polling). Meant for a controller on the same host that answers in
    /// microseconds (`nanonis-sim`): a reply that comes while polling costs no wake-up of a
    /// sleeping thread, which on a virtual machine takes longer than the reply.
    pub fn set_reply_poll(&mut self, poll: Duration) {
        self.reply_poll = poll;
        if let Some(connection) = self.stream.as_mut() {
            connection.reply_poll = poll;
        }
    }

    /// The controller's version, from the last (re)connection.
    pub fn version(&self) -> Option<&Version> {
        self.version.as_ref()
    }

    /// The argument schema in use.
    pub fn schema(&self) -> Schema {
        self.schema
    }

    /// The connection settings.
    pub fn config(&self) -> &ClientConfig {
        &self.config
    }

    /// Commands sent so far (re-sent ones included).
    pub fn commands_sent(&self) -> u64 {
        self.commands_sent
    }

    /// Reconnections so far.
    pub fn reconnects(&self) -> u64 {
        self.reconnects
    }

    /// A number that grows with every command sent on either connection (stops included,
    /// whether or not they were answered) and with every connection opened. Two equal
    /// values bracket a span in which this client sent the controller nothing: what the
    /// client read of the controller before it is still what the controller would answer,
    /// as long as the client is the controller's only one. `NanonisMicroscope` keeps its
    /// clock and position readings on that ground.
    #[must_use]
    pub fn sequence(&self) -> u64 {
        self.sequence
    }

    fn open(&self) -> Result<TcpStream, NanonisError> {
        let address = self.config.address()?;
        let stream = TcpStream::connect_timeout(&address, seconds(self.config.connect_timeout_s))
            .map_err(|e| {
            NanonisError::new(
                NanonisErrorKind::Connect,
                format!("cannot connect to {address}: {e}"),
            )
        })?;
        stream
            .set_nodelay(true)
            .map_err(|e| NanonisError::new(NanonisErrorKind::Io, format!("set_nodelay: {e}")))?;
        Ok(stream)
    }

    /// Opens the main connection when there is none, with backoff, and asks the version.
    fn ensure_connected(&mut self) -> Result<(), NanonisError> {
        if self.stream.is_some() {
            return Ok(());
        }
        let mut backoff = self.config.reconnect_backoff_s;
        let mut last = None;
        for attempt in 0..=self.config.reconnect_attempts {
            if attempt > 0 {
                self.backoff(backoff)?;
                backoff = (backoff * 2.0).min(MAX_RECONNECT_BACKOFF_S);
            }
            match self.open() {
                Ok(stream) => {
                    self.stream = Some(Connection::new(
                        stream,
                        seconds(self.config.command_timeout_s),
                        self.reply_poll,
                    )?);
                    self.reconnects += 1;
                    self.sequence += 1;
                    match self.exchange(&Request::UtilVersionGet, self.config.command_timeout_s) {
                        Ok(Reply::Version(version)) => {
                            self.schema = Schema::for_release(version.host_release);
                            tracing::info!(
                                product = %version.product_line,
                                version = %version.version,
                                host_release = version.host_release,
                                rt_release = version.rt_release,
                                "nanonis: connected to {}:{}",
                                self.config.host,
                                self.config.port
                            );
                            self.version = Some(version);
                            return Ok(());
                        }
                        Ok(other) => {
                            self.drop_stream();
                            last = Some(NanonisError::new(
                                NanonisErrorKind::Protocol,
                                format!("unexpected reply {other:?}"),
                            ));
                        }
                        Err(e) => {
                            self.drop_stream();
                            last = Some(e);
                        }
                    }
                }
                Err(e) => last = Some(e),
            }
        }
        let cause = last.map(|e| e.to_string()).unwrap_or_default();
        Err(NanonisError::new(
            NanonisErrorKind::Unreachable,
            format!(
                "the controller at {}:{} is unreachable after {} reconnect attempts ({cause}); \
                 the run cannot continue: restart the controller (or its TCP interface) and \
                 resume",
                self.config.host, self.config.port, self.config.reconnect_attempts
            ),
        ))
    }

    /// Whether the main connection is open (a lost one is reopened by the next request).
    #[must_use]
    pub fn is_connected(&self) -> bool {
        self.stream.is_some()
    }

    /// Sends a request with the ordinary command timeout and returns its reply.
    pub fn call(&mut self, request: &Request) -> Result<Reply, NanonisError> {
        self.call_with_timeout(request, self.config.command_timeout_s)
    }

    /// Sends a wait-style request expected to take `expected_s`: its timeout is that plus
    /// the wait margin.
    pub fn call_waiting(
        &mut self,
        request: &Request,
        expected_s: f64,
    ) -> Result<Reply, NanonisError> {
        self.call_with_timeout(request, self.waiting_timeout_s(expected_s))
    }

    /// The timeout of a wait-style request expected to take `expected_s`: that, the wait
    /// margin and the ordinary command timeout, s.
    #[must_use]
    pub fn waiting_timeout_s(&self, expected_s: f64) -> f64 {
        expected_s.max(0.0) + self.config.wait_margin_s + self.config.command_timeout_s
    }

    /// Sends a request with an explicit timeout (s). A request the controller refused as
    /// busy (not executed) is sent again; so is a request whose connection was lost before
    /// the reply when that is safe ([`Request::is_retry_safe`]); at most [`RETRIES`] times.
    pub fn call_with_timeout(
        &mut self,
        request: &Request,
        timeout_s: f64,
    ) -> Result<Reply, NanonisError> {
        self.call_resending(request, timeout_s, request.is_retry_safe())
    }

    /// Sends a request with the ordinary command timeout, again after a busy reply, but not
    /// on a new connection when its own was lost before the reply: the error is returned
    /// (and [`Client::is_connected`] is `false`), so that the caller looks at what the
    /// controller on a new connection is doing first. `NanonisMicroscope` starts its scans
    /// this way: a scan may be running on a controller it reconnects to.
    pub fn call_on_one_connection(&mut self, request: &Request) -> Result<Reply, NanonisError> {
        self.call_resending(request, self.config.command_timeout_s, false)
    }

    fn call_resending(
        &mut self,
        request: &Request,
        timeout_s: f64,
        resend_on_loss: bool,
    ) -> Result<Reply, NanonisError> {
        let mut last = None;
        for _ in 0..=RETRIES {
            self.ensure_connected()?;
            match self.exchange(request, timeout_s) {
                Ok(reply) => return Ok(reply),
                Err(e) if e.kind == NanonisErrorKind::Busy => {
                    tracing::debug!(error = %e, "nanonis: busy; sending again");
                    last = Some(e);
                }
                Err(e) if self.stream.is_none() && resend_on_loss => {
                    tracing::debug!(error = %e, "nanonis: connection dropped; sending again");
                    last = Some(e);
                }
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| {
            NanonisError::new(NanonisErrorKind::Io, "no attempt was made")
                .in_command(request.name())
        }))
    }

    /// One request and its reply on the main connection. Any failure that leaves the
    /// stream at an unknown position drops the connection.
    fn exchange(&mut self, request: &Request, timeout_s: f64) -> Result<Reply, NanonisError> {
        let name = request.name();
        let Some(connection) = self.stream.as_mut() else {
            return Err(NanonisError::new(NanonisErrorKind::Io, "not connected").in_command(name));
        };
        self.commands_sent += 1;
        self.sequence += 1;
        let result = transact(connection, request, self.schema, timeout_s);
        match result {
            Ok((reply, error)) => {
                if error.status != 0 {
                    Err(NanonisError::from_error_reply(name, &error.description))
                } else {
                    Ok(reply)
                }
            }
            Err(e) => {
                self.drop_stream();
                Err(e.in_command(name))
            }
        }
    }

    /// Sends `requests` on the main connection in one write, then reads their replies in
    /// order: one round trip where calls one after another take one each. The controller
    /// executes a connection's commands one after another, so they run as the same calls
    /// would. No request is sent again here (nor is the connection reopened once lost): the
    /// result of each is its reply, its error reply, or the error that ended the exchange (the
    /// connection is then dropped and the requests after it fail too; they may have been
    /// executed). An error reply does not stop the controller from executing what follows
    /// it: the caller decides what a failure means for the requests after it
    /// (`NanonisMicroscope` sends reads and waits again one by one from the first failure on,
    /// [`Request::is_retry_safe`], and stops the scan a pipeline started after a refused
    /// setting). `timeout_s` is the read timeout of each reply.
    pub fn call_pipelined(
        &mut self,
        requests: &[&Request],
        timeout_s: f64,
    ) -> Vec<Result<Reply, NanonisError>> {
        let failed_all = |e: NanonisError| {
            requests
                .iter()
                .map(|r| Err(e.clone().in_command(r.name())))
                .collect()
        };
        if let Err(e) = self.ensure_connected() {
            return failed_all(e);
        }
        let mut message = Vec::new();
        for request in requests {
            if let Err(e) = encode_request(request, self.schema, &mut message) {
                return failed_all(e);
            }
        }
        let Some(connection) = self.stream.as_mut() else {
            return failed_all(NanonisError::new(NanonisErrorKind::Io, "not connected"));
        };
        self.commands_sent += requests.len() as u64;
        self.sequence += requests.len() as u64;
        let written = connection.set_timeout(seconds(timeout_s)).and_then(|()| {
            connection
                .stream
                .get_mut()
                .write_all(&message)
                .map_err(|e| io_error("write requests", &e))
        });
        if let Err(e) = written {
            self.drop_stream();
            return failed_all(e);
        }
        let mut results = Vec::with_capacity(requests.len());
        for request in requests {
            let Some(connection) = self.stream.as_mut() else {
                results.push(Err(NanonisError::new(
                    NanonisErrorKind::Io,
                    "not read: the connection was dropped at an earlier reply",
                )
                .in_command(request.name())));
                continue;
            };
            results.push(match read_reply(connection, request, self.schema) {
                Ok((reply, error)) if error.status == 0 => Ok(reply),
                Ok((_, error)) => Err(NanonisError::from_error_reply(
                    request.name(),
                    &error.description,
                )),
                Err(e) => {
                    self.drop_stream();
                    Err(e.in_command(request.name()))
                }
            });
        }
        results
    }

    /// Sends a stop request (`Scan.Action` stop, `FolMe.Stop`, `Motor.StopMove`) on the
    /// second connection, opened on first use and re-opened once if it was dropped.
    pub fn stop(&mut self, request: &Request) -> Result<(), NanonisError> {
        let mut last = None;
        for _ in 0..2 {
            if self.stop_stream.is_none() {
                self.stop_stream = Some(Connection::new(
                    self.open()?,
                    seconds(self.config.command_timeout_s),
                    Duration::ZERO,
                )?);
            }
            let Some(connection) = self.stop_stream.as_mut() else {
                continue;
            };
            self.sequence += 1;
            match transact(
                connection,
                request,
                self.schema,
                self.config.command_timeout_s,
            ) {
                Ok((_, error)) if error.status != 0 => {
                    return Err(NanonisError::from_error_reply(
                        request.name(),
                        &error.description,
                    ));
                }
                Ok(_) => return Ok(()),
                Err(e) => {
                    self.stop_stream = None;
                    last = Some(e.in_command(request.name()));
                }
            }
        }
        Err(last.unwrap_or_else(|| NanonisError::new(NanonisErrorKind::Io, "stop failed")))
    }

    /// Drops the main connection after a failure: reset (`SO_LINGER` 0) rather than closed,
    /// so that requests the controller has received but not read yet — the rest of a
    /// pipeline behind a reply that timed out — go with it instead of being executed later,
    /// while the caller has gone on (a scan's start behind a stalled `Scan.FrameSet` would
    /// start a scan in the middle of whatever comes next). The kernel discards the unread
    /// bytes of a reset connection, and nanonis-sim, which may have read them already,
    /// stops at its next write, that of the stalled reply.
    fn drop_stream(&mut self) {
        if let Some(connection) = self.stream.take()
            && let Err(e) =
                socket2::SockRef::from(connection.stream.get_ref()).set_linger(Some(Duration::ZERO))
        {
            tracing::debug!(error = %e, "nanonis: cannot reset the connection; closing it");
        }
    }

    /// Closes both connections (the next command reconnects).
    pub fn disconnect(&mut self) {
        self.stream = None;
        self.stop_stream = None;
    }
}

fn io_error(what: &str, e: &std::io::Error) -> NanonisError {
    let kind = match e.kind() {
        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut => NanonisErrorKind::Timeout,
        _ => NanonisErrorKind::Io,
    };
    NanonisError::new(kind, format!("{what}: {e}"))
}

/// The bytes of one request: header and body.
fn encode_request(
    request: &Request,
    schema: Schema,
    out: &mut Vec<u8>,
) -> Result<(), NanonisError> {
    let body = request
        .encode(schema)
        .map_err(|e| NanonisError::new(NanonisErrorKind::InvalidRequest, e.to_string()))?;
    let header = codec::encode_request_header(request.name(), body.len(), true)
        .map_err(|e| NanonisError::new(NanonisErrorKind::InvalidRequest, e.to_string()))?;
    out.reserve(HEADER_LEN + body.len());
    out.extend_from_slice(&header);
    out.extend_from_slice(&body);
    Ok(())
}

/// Writes one request and reads its reply on `connection`.
fn transact(
    connection: &mut Connection,
    request: &Request,
    schema: Schema,
    timeout_s: f64,
) -> Result<(Reply, codec::ErrorSection), NanonisError> {
    let mut message = Vec::new();
    encode_request(request, schema, &mut message)?;
    connection.set_timeout(seconds(timeout_s))?;
    connection
        .stream
        .get_mut()
        .write_all(&message)
        .map_err(|e| io_error("write request", &e))?;
    read_reply(connection, request, schema)
}

/// Reads the reply to `request` on `connection`.
fn read_reply(
    connection: &mut Connection,
    request: &Request,
    schema: Schema,
) -> Result<(Reply, codec::ErrorSection), NanonisError> {
    let name = request.name();
    connection.poll_for_reply()?;
    let stream = &mut connection.stream;
    let mut reply_header = [0u8; HEADER_LEN];
    stream
        .read_exact(&mut reply_header)
        .map_err(|e| io_error("read reply header", &e))?;
    let header = codec::decode_response_header(&reply_header)
        .map_err(|e| NanonisError::protocol(name, &e))?;
    if header.command != name {
        return Err(NanonisError::new(
            NanonisErrorKind::Protocol,
            format!(
                "reply is for {:?}, not for the request sent",
                header.command
            ),
        ));
    }
    let mut reply_body = vec![0u8; header.body_len];
    stream
        .read_exact(&mut reply_body)
        .map_err(|e| io_error("read reply body", &e))?;
    request
        .decode_reply(&reply_body, schema)
        .map_err(|e| NanonisError::protocol(name, &e))
}
