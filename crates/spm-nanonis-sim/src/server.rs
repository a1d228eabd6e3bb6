//! The server: listener, connection threads, command execution, fault injection.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use spm_hal::{
    CountPoint, Counts, Error as _, ErrorKind, Frame, Microscope, MoveRequest, ScanDirection,
    ScanRequest, Seconds,
};
use spm_nanonis::codec::{self, CodecError, ErrorSection, HEADER_LEN};
use spm_nanonis::commands::{
    DriftComp, FrameData, Reply, Request, ScanBuffer, ScanFrame, ScanPropsState, ScanSpeed, Schema,
    Version, motor_direction, scan_action,
};
use spm_nanonis::{PIXEL_PACKET, metres_per_count};
use spm_sim::{RasterTurn, SimConfig, Simulator};
use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Why the server cannot start or run.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ServerError {
    /// Binding or accepting failed.
    #[error("nanonis-sim: {0}")]
    Io(#[from] std::io::Error),
    /// The configuration cannot be served.
    #[error("nanonis-sim: {0}")]
    Config(String),
}

/// Faults injected at the socket level, each a probability per command (drawn from a
/// generator seeded with `seed`, in the order the commands arrive).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SocketFaults {
    /// Seed of the fault generator.
    pub seed: u64,
    /// An error reply ("busy") instead of executing the command.
    pub error_reply: f64,
    /// The connection is closed before the command is executed.
    pub drop_before: f64,
    /// The command is executed, then the connection is closed without a reply.
    pub drop_after: f64,
    /// The reply is written one byte per write.
    pub one_byte_writes: f64,
    /// The reply is delayed by `delay_s`.
    pub delay: f64,
    /// Delay of a delayed reply, s.
    pub delay_s: f64,
    /// The reply is delayed by `stall_s` (meant to exceed the client's timeout).
    pub stall: f64,
    /// Delay of a stalled reply, s.
    pub stall_s: f64,
    /// A scan is found running (as if started by someone else) at an idle moment
    /// (a clock or position read).
    pub scan_running: f64,
}

impl SocketFaults {
    /// No faults.
    pub fn none() -> Self {
        Self {
            seed: 0,
            error_reply: 0.0,
            drop_before: 0.0,
            drop_after: 0.0,
            one_byte_writes: 0.0,
            delay: 0.0,
            delay_s: 0.0,
            stall: 0.0,
            stall_s: 0.0,
            scan_running: 0.0,
        }
    }

    /// A total fault probability per command spread over the kinds: error replies 25 %,
    /// one-byte writes 25 %, delays (`delay_s`) 20 %, drops before 10 % and after 10 %,
    /// stalls (`stall_s`) 5 %, a scan left running 5 %.
    pub fn mixed(rate: f64, seed: u64, delay_s: f64, stall_s: f64) -> Self {
        Self {
            seed,
            error_reply: 0.25 * rate,
            one_byte_writes: 0.25 * rate,
            delay: 0.2 * rate,
            delay_s,
            drop_before: 0.1 * rate,
            drop_after: 0.1 * rate,
            stall: 0.05 * rate,
            stall_s,
            scan_running: 0.05 * rate,
        }
    }

    /// The total probability that a command meets a fault.
    pub fn total(&self) -> f64 {
        self.error_reply
            + self.drop_before
            + self.drop_after
            + self.one_byte_writes
            + self.delay
            + self.stall
            + self.scan_running
    }

    fn validate(&self) -> Result<(), ServerError> {
        let rates = [
            self.error_reply,
            self.drop_before,
            self.drop_after,
            self.one_byte_writes,
            self.delay,
            self.stall,
            self.scan_running,
        ];
        if rates.iter().any(|r| !(0.0..=1.0).contains(r)) || self.total() > 1.0 {
            return Err(ServerError::Config(format!(
                "fault probabilities must lie in [0, 1] and sum to at most 1: {self:?}"
            )));
        }
        for (name, d) in [("delay_s", self.delay_s), ("stall_s", self.stall_s)] {
            if !(d.is_finite() && (0.0..=3600.0).contains(&d)) {
                return Err(ServerError::Config(format!(
                    "{name} = {d} is not in [0, 3600] s"
                )));
            }
        }
        Ok(())
    }
}

/// What the server publishes and how.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServerConfig {
    /// Host-application release answered by `Util.VersionGet` (decides the schemas).
    pub host_release: u32,
    /// RT-engine release.
    pub rt_release: u32,
    /// Signal index of Z (topography), the only channel a scan buffer may record.
    pub z_channel: i32,
    /// Signal index publishing the whole seconds of the simulated time.
    pub time_whole_signal: i32,
    /// Signal index publishing the fraction of a second.
    pub time_fraction_signal: i32,
    /// The controller's nominal lateral calibration, nm per count (published through
    /// `Piezo.CalibrGet` by the counts convention of spm-nanonis).
    pub lateral_nm_per_count: f64,
    /// The nominal Z calibration, nm per count.
    pub z_nm_per_count: f64,
    /// Socket faults.
    pub faults: SocketFaults,
    /// Limits of the connections: a cap, timeouts, the largest request (issue 25 item 11);
    /// defaults [`ConnectionLimits::default`].
    #[serde(default)]
    pub limits: ConnectionLimits,
}

/// How many connections the server keeps and how long and how much it waits for a client
/// (issue 25 item 11: 20 clients each claiming an 80 MiB body took 1.6 GB, and a client
/// could hold a connection for ever). Defaults in [`ConnectionLimits::default`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ConnectionLimits {
    /// Connections served at once; one more is accepted and closed at once (default 8; a
    /// controller serves a handful of clients).
    pub max_connections: usize,
    /// Once a request's first byte has arrived, the whole request (header and body) must
    /// arrive within this time, s, or the connection is closed (default 10 s).
    pub message_timeout_s: f64,
    /// A connection that sends nothing for this long between requests is closed, s
    /// (default 600 s: longer than any pause of a calibration client between commands).
    pub idle_timeout_s: f64,
    /// The largest request body accepted, bytes (default 1 MiB; the protocol's own limit,
    /// [`codec::MAX_BODY_LEN`] = 80 MiB, is for replies carrying frames; no request the
    /// server implements needs more than a few KiB). A larger claim closes the connection.
    /// Bodies are read in chunks of at most [`BODY_CHUNK_BYTES`], the buffer growing only
    /// as data arrive.
    pub max_request_body_bytes: usize,
}

/// The piece a request body is read in: the most the server allocates ahead of the data.
pub const BODY_CHUNK_BYTES: usize = 64 << 10;

impl Default for ConnectionLimits {
    fn default() -> Self {
        Self {
            max_connections: 8,
            message_timeout_s: 10.0,
            idle_timeout_s: 600.0,
            max_request_body_bytes: 1 << 20,
        }
    }
}

impl ConnectionLimits {
    fn validate(&self) -> Result<(), ServerError> {
        let timeout_ok = |t: f64| t.is_finite() && (1e-3..=86_400.0).contains(&t);
        if !(1..=10_000).contains(&self.max_connections) {
            return Err(ServerError::Config(format!(
                "limits.max_connections = {} must lie in [1, 10000]",
                self.max_connections
            )));
        }
        for (name, t) in [
            ("message_timeout_s", self.message_timeout_s),
            ("idle_timeout_s", self.idle_timeout_s),
        ] {
            if !timeout_ok(t) {
                return Err(ServerError::Config(format!(
                    "limits.{name} = {t} must lie in [0.001, 86400] s"
                )));
            }
        }
        if !(HEADER_LEN..=codec::MAX_BODY_LEN).contains(&self.max_request_body_bytes) {
            return Err(ServerError::Config(format!(
                "limits.max_request_body_bytes = {} must lie in [{HEADER_LEN}, {}]",
                self.max_request_body_bytes,
                codec::MAX_BODY_LEN
            )));
        }
        Ok(())
    }
}

/// Host-application release the server answers by default (the manual's R5.1.14718).
pub const DEFAULT_HOST_RELEASE: u32 = 14718;

impl ServerConfig {
    /// The default server for a simulator: release 14718, Z on signal 30, time on signals
    /// 126 and 127, nominal calibration 0.02 nm/count lateral and 0.01 nm/count Z.
    pub fn new(faults: SocketFaults) -> Self {
        Self {
            host_release: DEFAULT_HOST_RELEASE,
            rt_release: 14_000,
            z_channel: 30,
            time_whole_signal: 126,
            time_fraction_signal: 127,
            lateral_nm_per_count: 0.02,
            z_nm_per_count: 0.01,
            faults,
            limits: ConnectionLimits::default(),
        }
    }
}

/// DAC width of a simulator's half range (`2^(bits−1)`), when it is a power of two.
fn bits_of(half_range_counts: f64, what: &str) -> Result<u32, ServerError> {
    let bits = (2.0 * half_range_counts).log2();
    if bits.fract() != 0.0 || !(8.0..=32.0).contains(&bits) {
        return Err(ServerError::Config(format!(
            "{what} = {half_range_counts} is not a power of two 2^(bits−1) with 8 ≤ bits ≤ 32"
        )));
    }
    Ok(bits as u32)
}

/// Counters of what the server did.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct ServerStats {
    /// Requests received (complete headers and bodies).
    pub commands: u64,
    /// Requests received per command name (`Scan.Action`, …): where a client's round trips go.
    pub commands_by_name: std::collections::BTreeMap<String, u64>,
    /// Requests already received when the server turned to them, sent by the client before
    /// it had the previous reply (pipelined): `commands − pipelined` is the round trips.
    pub pipelined: u64,
    /// Error replies of the fault injector.
    pub injected_error_replies: u64,
    /// Connections dropped before executing.
    pub injected_drops_before: u64,
    /// Connections dropped after executing.
    pub injected_drops_after: u64,
    /// Replies written one byte at a time.
    pub injected_one_byte_writes: u64,
    /// Delayed replies.
    pub injected_delays: u64,
    /// Stalled replies.
    pub injected_stalls: u64,
    /// Scans found running.
    pub injected_scans_running: u64,
    /// Requests refused on demand ([`ServerHandle::refuse_next`]).
    pub injected_refusals: u64,
    /// Connections accepted.
    pub connections: u64,
    /// Requests refused as malformed (bad header closes, bad body gets an error reply).
    pub malformed: u64,
    /// Connections closed at once because [`ConnectionLimits::max_connections`] were open.
    pub refused_connections: u64,
    /// Connections closed by a timeout (a request not whole within
    /// [`ConnectionLimits::message_timeout_s`], or idle beyond
    /// [`ConnectionLimits::idle_timeout_s`]).
    pub timed_out_connections: u64,
    /// Connections closed for a request body above
    /// [`ConnectionLimits::max_request_body_bytes`].
    pub oversized_requests: u64,
    /// Failed `accept()` calls (each followed by a pause, [`accept_pause`]).
    pub accept_errors: u64,
    /// The most bytes of request bodies held at once, over all connections (the buffers'
    /// capacity: what was allocated, not what was claimed).
    pub request_buffer_bytes_peak: u64,
}

impl ServerStats {
    /// Faults injected, all kinds.
    pub fn injected(&self) -> u64 {
        self.injected_error_replies
            + self.injected_drops_before
            + self.injected_drops_after
            + self.injected_one_byte_writes
            + self.injected_delays
            + self.injected_stalls
            + self.injected_scans_running
            + self.injected_refusals
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Fault {
    None,
    ErrorReply,
    DropBefore,
    DropAfter,
    OneByte,
    Delay,
    Stall,
}

/// How a frame of the controller maps onto simulator scans.
#[derive(Clone, Debug, PartialEq)]
struct ScanPlan {
    /// 1 = up (the first line acquired is the frame's bottom row), 0 = down.
    direction_up: u32,
    /// Rows (lines) and columns (pixels per line) of the frame.
    rows: usize,
    columns: usize,
    /// Pixels per line of the simulator's (square-pixel) scan: `columns`, or for a frame
    /// with non-square pixels the line length over the line spacing.
    sim_columns: usize,
    /// The frame's turn about its centre, for angles other than 0° and 180°.
    turn: Option<RasterTurn>,
}

#[derive(Debug)]
struct PendingScan {
    /// The simulator's raster (origin at the smallest x and y).
    request: ScanRequest,
    plan: ScanPlan,
    /// Paused (`Scan.Action` 2) and not resumed yet.
    paused: bool,
    /// A `Scan.StatusGet` has seen it running.
    seen_running: bool,
    /// `Scan.WaitEndOfScan` has returned for it: it has ended, and is simulated when
    /// its data or the instrument are next observed.
    ended: bool,
}

#[derive(Debug)]
enum Pending {
    None,
    Move { target: CountPoint, speed: f64 },
    Scan(Box<PendingScan>),
}

/// Ground truth of the last frame's forward half as the simulator ran it, in acquisition
/// order (before the float32 wire and the row order of `Scan.FrameDataGrab`): for tests of a
/// client's pixel positions and times ([`ServerHandle::last_frame_truth`]).
#[derive(Clone, Debug, PartialEq)]
pub struct FrameTruth {
    /// The simulator's time of every forward pixel (its dwell's middle), s.
    pub time_s: Vec<f64>,
    /// The effective input `u + h + c` of every forward pixel, the simulator's counts
    /// (spm-sim's oracle); empty unless the simulator records them
    /// (`Simulator::record_tip_positions`). A downward frame is simulated line by line;
    /// these are the lines' records joined.
    pub effective_inputs: Vec<CountPoint>,
}

#[derive(Debug)]
struct LastScan {
    frame: Result<Frame, String>,
    /// The forward pixels' effective inputs as simulated (see [`FrameTruth`]).
    effective_inputs: Vec<CountPoint>,
    request: ScanRequest,
    plan: ScanPlan,
    /// The instrument as it was when the scan began, kept while the backward trace has
    /// not been recorded: a later backward grab simulates it there (see the crate docs).
    snapshot: Option<Box<Simulator>>,
}

/// Runs a frame on `sim`: one simulator scan for an upward frame; a downward frame line by
/// line from the frame's top (spm-sim's rasters step their lines upwards). With the frame,
/// the effective inputs of its forward pixels as the simulator recorded them, in
/// acquisition order (empty unless it records them).
fn run_scan(
    sim: &mut Simulator,
    request: &ScanRequest,
    plan: &ScanPlan,
    backward: bool,
) -> Result<(Frame, Vec<CountPoint>), String> {
    let mut request = request.clone();
    request.record_backward = backward;
    let scan = |sim: &mut Simulator, r: &ScanRequest| match plan.turn {
        None => sim.scan(r),
        Some(turn) => sim.scan_turned(r, turn),
    };
    if plan.direction_up == 1 {
        let frame = scan(sim, &request).map_err(|e| describe(&e))?;
        return Ok((frame, sim.oracle().last_scan_effective_inputs()));
    }
    let mut effective_inputs = Vec::new();
    let lines = request.lines;
    let mut frame = Frame {
        request: request.clone(),
        forward: spm_hal::TraceImage {
            z_counts: Vec::with_capacity(plan.rows * plan.sim_columns),
            time_s: Vec::with_capacity(plan.rows * plan.sim_columns),
        },
        backward: backward.then(|| spm_hal::TraceImage {
            z_counts: Vec::with_capacity(plan.rows * plan.sim_columns),
            time_s: Vec::with_capacity(plan.rows * plan.sim_columns),
        }),
    };
    for line in 0..lines {
        // The frame's top row: the largest y of a direct raster, the smallest of a
        // counter one (its frame is turned by 180°).
        let row = match request.direction {
            ScanDirection::Direct => lines - 1 - line,
            ScanDirection::Counter => line,
        };
        let one = ScanRequest {
            origin: CountPoint::from_counts(
                request.origin.x.value(),
                request.origin.y.value() + f64::from(row) * request.pixel_step.value(),
            ),
            lines: 1,
            ..request.clone()
        };
        let part = scan(sim, &one).map_err(|e| describe(&e))?;
        effective_inputs.extend(sim.oracle().last_scan_effective_inputs());
        frame.forward.z_counts.extend(part.forward.z_counts);
        frame.forward.time_s.extend(part.forward.time_s);
        if let (Some(all), Some(half)) = (frame.backward.as_mut(), part.backward) {
            all.z_counts.extend(half.z_counts);
            all.time_s.extend(half.time_s);
        }
    }
    Ok((frame, effective_inputs))
}

/// Line `values` (the simulator's `sim_columns` pixels, left to right in the frame)
/// resampled at the centres of the frame's `columns` pixels by linear interpolation; the
/// identity when the two agree.
fn resample(values: &[f64], columns: usize, out: &mut Vec<f64>) {
    let n = values.len();
    if n == columns || n == 0 {
        out.extend_from_slice(values);
        return;
    }
    // Both rasters span the same line, centred: pixel c of the frame at (c + ½)/columns of
    // it, simulator pixel j at (j + ½)/n.
    for c in 0..columns {
        let f = ((c as f64 + 0.5) / columns as f64 * n as f64 - 0.5).clamp(0.0, (n - 1) as f64);
        let j = (f.floor() as usize).min(n - 1);
        let k = (j + 1).min(n - 1);
        let w = f - j as f64;
        out.push(values[j] * (1.0 - w) + values[k] * w);
    }
}

struct State {
    sim: Simulator,
    config: ServerConfig,
    schema: Schema,
    calibration: [f32; 3],
    m_per_count: [f64; 3],
    drift: DriftComp,
    tilt: [f32; 2],
    hysteresis: u32,
    continuous: bool,
    bouncy: bool,
    buffer: ScanBuffer,
    frame: ScanFrame,
    speed: ScanSpeed,
    /// `FolMe.SpeedSet`: the custom speed, m/s, and whether it is used (else the scan
    /// speed is).
    folme_speed_m_per_s: f32,
    folme_custom: bool,
    /// `ZCtrl.OnOffSet`.
    z_on: bool,
    /// `Scan.PropsSet` values kept for `Scan.PropsGet` (autosave and autopaste in the
    /// coding of `Scan.PropsGet`: 0 = all, 1 = next, 2 = off).
    autosave: u32,
    autopaste: u32,
    series_name: String,
    comment: String,
    modules: Vec<String>,
    pending: Pending,
    last_scan: Option<LastScan>,
    /// A scan has ended (or been simulated) that no `Scan.WaitEndOfScan` returned for.
    end_unwaited: bool,
    leftover_running: bool,
    /// Requests to refuse, by command name: how many more, and the error description
    /// ([`ServerHandle::refuse_next`]).
    refusals: std::collections::BTreeMap<String, (u32, String)>,
    rng: ChaCha8Rng,
    stats: ServerStats,
}

/// A float32 argument read as the shortest decimal that rounds to it — the value a user
/// typing it into the controller would have meant. A pixel dwell of 1e-4 s sent as a
/// float32 time per line (0.0032 s for 32 pixels) is then exactly 1e-4 s again, not
/// 1.0000000067e-4 s: the simulator's pixel loop treats sub-ulp different dwells the same.
fn decimal(x: f32) -> f64 {
    format!("{x}").parse().unwrap_or(f64::from(x))
}

/// A sim error as a controller's error text, worded so that a client recognises its kind.
fn describe(e: &spm_sim::SimError) -> String {
    let kind = match e.kind() {
        ErrorKind::Timeout => "the real-time engine timed out",
        ErrorKind::Communication => "communication with the real-time engine failed",
        ErrorKind::FeedbackLost => "Z-Controller: feedback lost (safe tip)",
        ErrorKind::OutOfRange => "out of range",
        _ => "error",
    };
    format!("{kind}: {e}")
}

impl State {
    fn new(sim: Simulator, config: ServerConfig) -> Result<Self, ServerError> {
        config.faults.validate()?;
        config.limits.validate()?;
        let i = &sim.config().instrument;
        let bits = bits_of(
            i.lateral_half_range_counts,
            "instrument.lateral_half_range_counts",
        )?;
        let z_bits = bits_of(i.z_half_range_counts, "instrument.z_half_range_counts")?;
        let cal = |nm_per_count: f64, bits: u32| {
            (nm_per_count * 1e-9 * 2f64.powi(bits as i32) / spm_nanonis::LOW_VOLTAGE_SPAN_V) as f32
        };
        let calibration = [
            cal(config.lateral_nm_per_count, bits),
            cal(config.lateral_nm_per_count, bits),
            cal(config.z_nm_per_count, z_bits),
        ];
        if !calibration.iter().all(|c| c.is_finite() && *c > 0.0) {
            return Err(ServerError::Config(format!(
                "calibration {calibration:?} m/V is not positive"
            )));
        }
        let m_per_count = [
            metres_per_count(f64::from(calibration[0]), bits),
            metres_per_count(f64::from(calibration[1]), bits),
            metres_per_count(f64::from(calibration[2]), z_bits),
        ];
        let rng = ChaCha8Rng::seed_from_u64(config.faults.seed);
        Ok(Self {
            sim,
            schema: Schema::for_release(config.host_release),
            calibration,
            m_per_count,
            // As a user may have left it: every correction on, continuous bouncy scanning.
            drift: DriftComp {
                status: 1,
                v_m_per_s: [2e-12, -1e-12, 0.0],
                saturated: [0; 3],
                saturation_limit_percent: 10.0,
            },
            tilt: [0.4, -0.2],
            hysteresis: 1,
            continuous: true,
            bouncy: true,
            buffer: ScanBuffer {
                channels: vec![config.z_channel],
                pixels: 256,
                lines: 256,
            },
            frame: ScanFrame {
                centre_x_m: 0.0,
                centre_y_m: 0.0,
                width_m: 1e-7,
                height_m: 1e-7,
                angle_deg: 0.0,
            },
            speed: ScanSpeed {
                forward_speed_m_per_s: 1e-7,
                backward_speed_m_per_s: 1e-7,
                forward_line_s: 1.0,
                backward_line_s: 1.0,
                keep: 1,
                speed_ratio: 1.0,
            },
            folme_speed_m_per_s: 1e-7,
            folme_custom: false,
            z_on: true,
            autosave: 2,
            autopaste: 2,
            series_name: String::new(),
            comment: String::new(),
            modules: Vec::new(),
            pending: Pending::None,
            last_scan: None,
            end_unwaited: false,
            leftover_running: false,
            refusals: std::collections::BTreeMap::new(),
            rng,
            stats: ServerStats::default(),
            config,
        })
    }

    /// The error description when this request of `command` is one to refuse
    /// ([`ServerHandle::refuse_next`]); counted off.
    fn take_refusal(&mut self, command: &str) -> Option<String> {
        match self.refusals.get_mut(command) {
            Some((n, description)) if *n > 0 => {
                *n -= 1;
                self.stats.injected_refusals += 1;
                Some(description.clone())
            }
            _ => None,
        }
    }

    fn draw_fault(&mut self, command: &str) -> Fault {
        let f = &self.config.faults;
        if f.total() <= 0.0 {
            return Fault::None;
        }
        let u: f64 = self.rng.random();
        let mut edge = 0.0;
        let kinds = [
            (f.error_reply, Fault::ErrorReply),
            (f.drop_before, Fault::DropBefore),
            (f.drop_after, Fault::DropAfter),
            (f.one_byte_writes, Fault::OneByte),
            (f.delay, Fault::Delay),
            (f.stall, Fault::Stall),
        ];
        for (p, kind) in kinds {
            edge += p;
            if u < edge {
                return kind;
            }
        }
        edge += f.scan_running;
        if u < edge && matches!(command, "Signals.ValsGet" | "FolMe.XYPosGet") {
            self.leftover_running = true;
            self.stats.injected_scans_running += 1;
        }
        Fault::None
    }

    /// `Motor.StartMove` along X or Y: the steps take their time; spm-sim models no
    /// lateral stage, so the simulated sample stays where it is (documented in the crate).
    fn lateral_motor_steps(&mut self, steps: u16) -> Result<Reply, String> {
        let Some(c) = self.sim.config().instrument.coarse_z.as_ref() else {
            return Err("no motor module is configured".into());
        };
        let duration = f64::from(steps) * c.step_time_s;
        self.sim.wait(Seconds(duration)).map_err(|e| describe(&e))?;
        Ok(Reply::Empty)
    }

    /// A `Scan.WaitEndOfScan` that no end of scan ends: it waits its timeout.
    fn wait_out(&mut self, timeout_ms: i32) -> Result<Reply, String> {
        if timeout_ms < 0 {
            return Err("nanonis-sim: waiting forever with no scan running".into());
        }
        self.sim
            .wait(Seconds(f64::from(timeout_ms) * 1e-3))
            .map_err(|e| describe(&e))?;
        Ok(Reply::WaitEndOfScan {
            timed_out: 1,
            file_path: String::new(),
        })
    }

    fn counts_to_m(&self, p: CountPoint) -> (f64, f64) {
        (
            p.x.value() * self.m_per_count[0],
            p.y.value() * self.m_per_count[1],
        )
    }

    fn compensation_off(&self) -> Result<(), String> {
        if self.drift.status != 0 || self.tilt != [0.0, 0.0] || self.hysteresis != 0 {
            return Err(format!(
                "nanonis-sim does not model the controller's compensation: switch drift \
                 ({}), tilt ({:?}°) and hysteresis ({}) compensation off",
                self.drift.status, self.tilt, self.hysteresis
            ));
        }
        Ok(())
    }

    /// Refuses an operation the simulator cannot model with the feedback off.
    fn feedback_on(&self) -> Result<(), String> {
        if self.z_on {
            Ok(())
        } else {
            Err(
                "nanonis-sim does not model constant-height operation: the Z feedback is off \
                 (switch it on with ZCtrl.OnOffSet)"
                    .into(),
            )
        }
    }

    /// A Z reading in metres: the Z output saturates at the ends of its range (a reading
    /// beyond them is the feedback asking for more than the piezo gives).
    fn z_metres(&self, z_counts: f64) -> f32 {
        let h = self.sim.config().instrument.z_half_range_counts;
        (z_counts.clamp(-h, h - 1.0) * self.m_per_count[2]) as f32
    }

    /// Completes a pending move (with no settle) or scan (recording the backward trace
    /// when `backward` is set). A paused scan stays pending: the pause holds it at its
    /// start.
    fn flush(&mut self, backward: bool) -> Result<(), String> {
        match std::mem::replace(&mut self.pending, Pending::None) {
            Pending::None => Ok(()),
            Pending::Move { target, speed } => self.do_move(target, speed, 0.0),
            Pending::Scan(scan) if scan.paused => {
                self.pending = Pending::Scan(scan);
                Ok(())
            }
            Pending::Scan(scan) => {
                let PendingScan { request, plan, .. } = *scan;
                // The instrument before the scan, for a backward trace asked later.
                let snapshot = (!backward).then(|| Box::new(self.sim.clone()));
                let (frame, effective_inputs) =
                    match run_scan(&mut self.sim, &request, &plan, backward) {
                        Ok((frame, inputs)) => (Ok(frame), inputs),
                        Err(e) => (Err(e), Vec::new()),
                    };
                self.last_scan = Some(LastScan {
                    frame,
                    effective_inputs,
                    request,
                    plan,
                    snapshot,
                });
                Ok(())
            }
        }
    }

    fn do_move(&mut self, target: CountPoint, speed: f64, settle_s: f64) -> Result<(), String> {
        self.sim
            .move_to(MoveRequest {
                target,
                speed: spm_hal::CountsPerSecond(speed),
                settle: Seconds(settle_s),
            })
            .map_err(|e| describe(&e))
    }

    fn start_scan(&mut self, direction_up: u32) -> Result<(), String> {
        self.flush(false)?;
        if self.leftover_running {
            return Err("busy: a scan is already running".into());
        }
        self.compensation_off()?;
        self.feedback_on()?;
        if self.continuous || self.bouncy {
            return Err(
                "nanonis-sim scans one frame at a time: switch continuous and bouncy scanning off"
                    .into(),
            );
        }
        if self.buffer.channels != [self.config.z_channel] {
            return Err(format!(
                "nanonis-sim records only the Z channel (signal {})",
                self.config.z_channel
            ));
        }
        let f = self.frame;
        // 0° and 180° are the simulator's direct and counter rasters; any other angle turns
        // a direct raster about the frame's centre (the manual: positive = clockwise).
        let (direction, angle_rad) = if f.angle_deg == 0.0 {
            (ScanDirection::Direct, None)
        } else if f.angle_deg == 180.0 || f.angle_deg == -180.0 {
            (ScanDirection::Counter, None)
        } else {
            (
                ScanDirection::Direct,
                Some(-decimal(f.angle_deg).to_radians()),
            )
        };
        let pixels = self.buffer.pixels as u32;
        let lines = self.buffer.lines as u32;
        let width = decimal(f.width_m) / self.m_per_count[0];
        let step_x = width / f64::from(pixels);
        let step_y = decimal(f.height_m) / f64::from(lines) / self.m_per_count[1];
        if !(step_x.is_finite() && step_y.is_finite() && step_x > 0.0 && step_y > 0.0) {
            return Err(format!("invalid pixel size {step_x} × {step_y} counts"));
        }
        // Square pixels are scanned as they are; otherwise the simulator (square pixels
        // only) scans the frame's lines with the line spacing as its pixel step, and each
        // line is resampled to the frame's pixels.
        let (step, sim_columns) = if ((step_x - step_y) / step_x).abs() <= 1e-5 {
            (step_x, pixels)
        } else {
            let n = (width / step_y).round().max(1.0);
            let max = f64::from(self.sim.capabilities().max_pixels_per_line);
            if n > max {
                return Err(format!(
                    "out of range: the frame's lines need {n} pixels at the line spacing \
                     (at most {max})"
                ));
            }
            (step_y, n as u32)
        };
        let s = self.speed;
        if s.forward_line_s != s.backward_line_s
            || s.forward_line_s.is_nan()
            || s.forward_line_s <= 0.0
        {
            return Err(format!(
                "nanonis-sim retraces at the forward speed: time per line {} s / {} s",
                s.forward_line_s, s.backward_line_s
            ));
        }
        // The dwell a user meant: the shortest decimal at float32 precision of line time ÷
        // pixels (4.8 ms ÷ 48 is 9.999999999999999e-5 s in float64, 1e-4 s meant).
        let dwell = decimal((decimal(s.forward_line_s) / f64::from(sim_columns)) as f32);
        // Pixel i of a line at left + (i + ½)·width/pixels; the frame centre is the raster's.
        let centre = CountPoint::from_counts(
            decimal(f.centre_x_m) / self.m_per_count[0],
            decimal(f.centre_y_m) / self.m_per_count[1],
        );
        let origin = CountPoint::from_counts(
            centre.x.value() - 0.5 * f64::from(sim_columns - 1) * step,
            centre.y.value() - 0.5 * f64::from(lines - 1) * step,
        );
        self.pending = Pending::Scan(Box::new(PendingScan {
            request: ScanRequest {
                origin,
                pixel_step: Counts(step),
                pixels_per_line: sim_columns,
                lines,
                direction,
                pixel_dwell: Seconds(dwell),
                record_backward: false,
            },
            plan: ScanPlan {
                direction_up,
                rows: lines as usize,
                columns: pixels as usize,
                sim_columns: sim_columns as usize,
                turn: angle_rad.map(|angle_rad| RasterTurn { centre, angle_rad }),
            },
            paused: false,
            seen_running: false,
            ended: false,
        }));
        self.last_scan = None;
        self.end_unwaited = true;
        Ok(())
    }

    /// `Scan.StatusGet`. The simulator runs a frame in one piece, so a poll is a moment at
    /// which the scan either still runs or has ended: the first poll after the start sees
    /// it running, the next one (with nothing in between that observed the instrument)
    /// finds it ended, as simulated then. A paused scan runs until it is stopped.
    fn scan_status(&mut self) -> Result<u32, String> {
        if self.leftover_running {
            return Ok(1);
        }
        let Pending::Scan(scan) = &mut self.pending else {
            return Ok(0);
        };
        if scan.ended {
            return Ok(0);
        }
        if scan.paused || !scan.seen_running {
            scan.seen_running = true;
            return Ok(1);
        }
        self.flush(false)?;
        Ok(0)
    }

    /// The backward half of the last frame, simulated from the snapshot taken when the
    /// scan began if its first execution did not record it.
    fn record_backward_half(&mut self) -> Result<(), String> {
        let Some(last) = self.last_scan.as_mut() else {
            return Ok(());
        };
        let Ok(frame) = last.frame.as_mut() else {
            return Ok(());
        };
        if frame.backward.is_some() {
            return Ok(());
        }
        let Some(mut shadow) = last.snapshot.take() else {
            return Err("backward data were not recorded".into());
        };
        let (again, _) = run_scan(&mut shadow, &last.request, &last.plan, true)?;
        frame.backward = again.backward;
        Ok(())
    }

    fn grab(&mut self, channel: u32, forward: u32) -> Result<Reply, String> {
        if i64::from(channel) != i64::from(self.config.z_channel) {
            return Err(format!("channel {channel} is not recorded"));
        }
        if let Pending::Scan(scan) = &self.pending {
            if scan.paused {
                // Paused at its start: nothing acquired yet (NaN, as a controller's buffer).
                let plan = &scan.plan;
                return Ok(Reply::FrameData(FrameData {
                    channel_name: "Z (m)".into(),
                    rows: plan.rows,
                    columns: plan.columns,
                    data: vec![f32::NAN; plan.rows * plan.columns],
                    direction_up: plan.direction_up,
                }));
            }
            self.flush(forward == 0)?;
        }
        if forward == 0 {
            self.record_backward_half()?;
        }
        let Some(last) = &self.last_scan else {
            return Err("no scan data: no scan has run".into());
        };
        let frame = last.frame.as_ref().map_err(Clone::clone)?;
        let plan = &last.plan;
        let (rows, n) = (plan.rows, plan.sim_columns);
        let image = if forward == 1 {
            &frame.forward
        } else {
            frame
                .backward
                .as_ref()
                .ok_or_else(|| "backward data were not recorded".to_owned())?
        };
        if image.z_counts.len() != rows * n {
            return Err(format!(
                "the scan recorded {} pixels for {rows} × {n}",
                image.z_counts.len()
            ));
        }
        let mut data = Vec::with_capacity(rows * plan.columns);
        let mut line_values = Vec::with_capacity(n);
        let mut resampled = Vec::with_capacity(plan.columns);
        for row in 0..rows {
            // Rows top first: the last line acquired of an upward frame, the first of a
            // downward one.
            let line = if plan.direction_up == 1 {
                rows - 1 - row
            } else {
                row
            };
            let acquired = &image.z_counts[line * n..(line + 1) * n];
            line_values.clear();
            if forward == 1 {
                line_values.extend_from_slice(acquired);
            } else {
                line_values.extend(acquired.iter().rev());
            }
            resampled.clear();
            resample(&line_values, plan.columns, &mut resampled);
            data.extend(resampled.iter().map(|&z| self.z_metres(z)));
        }
        Ok(Reply::FrameData(FrameData {
            channel_name: "Z (m)".into(),
            rows,
            columns: plan.columns,
            data,
            direction_up: plan.direction_up,
        }))
    }

    /// Executes one request: dispatched by the command's module (the part of its name before
    /// the dot), each module's arms in its own function.
    fn execute(&mut self, request: &Request) -> Result<Reply, String> {
        match request.name().split('.').next().unwrap_or_default() {
            "Scan" => self.execute_scan(request),
            "FolMe" | "Motor" => self.execute_motion(request),
            "ZCtrl" | "Signals" => self.execute_readings(request),
            _ => self.execute_settings(request),
        }
    }

    /// `Util.*` and `Piezo.*`: the version, the calibration and the compensations.
    fn execute_settings(&mut self, request: &Request) -> Result<Reply, String> {
        match request {
            Request::UtilVersionGet => Ok(Reply::Version(Version {
                product_line: "Nanonis SPM Control Software".into(),
                version: "Generic 5 (spmcal nanonis-sim)".into(),
                host_release: self.config.host_release,
                rt_release: self.config.rt_release,
            })),
            Request::PiezoCalibrGet => Ok(Reply::F32x3(self.calibration)),
            Request::PiezoRangeGet => Ok(Reply::F32x3(
                self.calibration
                    .map(|c| c * spm_nanonis::LOW_VOLTAGE_SPAN_V as f32),
            )),
            Request::PiezoDriftCompSet {
                on_off,
                v_m_per_s,
                saturation_limit_percent,
            } => {
                match on_off {
                    1 => self.drift.status = 1,
                    2 => self.drift.status = 0,
                    _ => {}
                }
                self.drift.v_m_per_s = *v_m_per_s;
                self.drift.saturation_limit_percent = *saturation_limit_percent;
                Ok(Reply::Empty)
            }
            Request::PiezoDriftCompGet => Ok(Reply::DriftComp(self.drift)),
            Request::PiezoTiltSet { x_deg, y_deg } => {
                self.tilt = [*x_deg, *y_deg];
                Ok(Reply::Empty)
            }
            Request::PiezoTiltGet => Ok(Reply::F32x2(self.tilt)),
            Request::PiezoHystOnOffSet(v) => {
                self.hysteresis = *v;
                Ok(Reply::Empty)
            }
            Request::PiezoHystOnOffGet => Ok(Reply::U32(self.hysteresis)),
            other => Err(format!("nanonis-sim does not implement {}", other.name())),
        }
    }

    /// `Scan.*`: the scan itself (start, status, wait, data) or its set-up.
    fn execute_scan(&mut self, request: &Request) -> Result<Reply, String> {
        match request {
            Request::ScanAction { .. }
            | Request::ScanStatusGet
            | Request::ScanWaitEndOfScan { .. }
            | Request::ScanFrameDataGrab { .. } => self.execute_scan_run(request),
            _ => self.execute_scan_setup(request),
        }
    }

    /// `Scan.Action`, `Scan.StatusGet`, `Scan.WaitEndOfScan`, `Scan.FrameDataGrab`.
    fn execute_scan_run(&mut self, request: &Request) -> Result<Reply, String> {
        match request {
            Request::ScanAction {
                action,
                direction_up,
            } => match *action {
                scan_action::START => self.start_scan(*direction_up).map(|()| Reply::Empty),
                scan_action::STOP => {
                    self.leftover_running = false;
                    if matches!(self.pending, Pending::Scan(_)) {
                        self.pending = Pending::None;
                    }
                    self.end_unwaited = false;
                    Ok(Reply::Empty)
                }
                scan_action::PAUSE | scan_action::RESUME => {
                    // With no scan running there is nothing to pause or resume.
                    if let Pending::Scan(scan) = &mut self.pending
                        && !scan.ended
                    {
                        scan.paused = *action == scan_action::PAUSE;
                    }
                    Ok(Reply::Empty)
                }
                other => Err(format!("nanonis-sim does not model scan action {other}")),
            },
            Request::ScanStatusGet => self.scan_status().map(Reply::U32),
            Request::ScanWaitEndOfScan { timeout_ms } => {
                match std::mem::replace(&mut self.pending, Pending::None) {
                    Pending::Scan(mut scan) if !scan.paused && !scan.ended => {
                        // The scan ends; it is simulated when its data are needed.
                        scan.ended = true;
                        self.pending = Pending::Scan(scan);
                        self.end_unwaited = false;
                        Ok(Reply::WaitEndOfScan {
                            timed_out: 0,
                            file_path: String::new(),
                        })
                    }
                    Pending::Scan(scan) => {
                        // Paused (no end of scan comes) or already ended (the next end of
                        // scan is not coming): the wait times out, after the scan if it ran.
                        let paused = scan.paused;
                        self.pending = Pending::Scan(scan);
                        if !paused {
                            self.flush(false)?;
                        }
                        self.wait_out(*timeout_ms)
                    }
                    Pending::Move { target, speed } => {
                        let settle = f64::from((*timeout_ms).max(0)) * 1e-3;
                        self.do_move(target, speed, settle)?;
                        Ok(Reply::WaitEndOfScan {
                            timed_out: 1,
                            file_path: String::new(),
                        })
                    }
                    Pending::None if self.end_unwaited => {
                        // A scan ended (simulated because something observed it) before
                        // this wait: its end of scan is the one waited for.
                        self.end_unwaited = false;
                        Ok(Reply::WaitEndOfScan {
                            timed_out: 0,
                            file_path: String::new(),
                        })
                    }
                    Pending::None => self.wait_out(*timeout_ms),
                }
            }
            Request::ScanFrameDataGrab { channel, forward } => self.grab(*channel, *forward),
            other => Err(format!("nanonis-sim does not implement {}", other.name())),
        }
    }

    /// The scan's set-up: frame, buffer, properties, position and speed.
    fn execute_scan_setup(&mut self, request: &Request) -> Result<Reply, String> {
        match request {
            Request::ScanFrameSet(f) => {
                if ![
                    f.centre_x_m,
                    f.centre_y_m,
                    f.width_m,
                    f.height_m,
                    f.angle_deg,
                ]
                .iter()
                .all(|v| v.is_finite())
                    || f.width_m <= 0.0
                    || f.height_m <= 0.0
                {
                    return Err(format!("invalid frame {f:?}"));
                }
                self.frame = *f;
                Ok(Reply::Empty)
            }
            Request::ScanFrameGet => Ok(Reply::Frame(self.frame)),
            Request::ScanBufferSet(b) => {
                let max = self.sim.capabilities().max_pixels_per_line as i32;
                let max_lines = self.sim.capabilities().max_lines as i32;
                if b.pixels <= 0 || b.lines <= 0 || b.lines > max_lines {
                    return Err(format!("invalid buffer {} × {}", b.pixels, b.lines));
                }
                if b.channels.iter().any(|c| !(0..=127).contains(c)) {
                    return Err(format!("channel indexes {:?} outside [0, 127]", b.channels));
                }
                // Coerced to the closest multiple of 16 (at least 16), as the controller does.
                let packet = PIXEL_PACKET as i32;
                let pixels = ((b.pixels + packet / 2) / packet * packet).clamp(packet, max);
                self.buffer = ScanBuffer {
                    channels: b.channels.clone(),
                    pixels,
                    lines: b.lines,
                };
                Ok(Reply::Empty)
            }
            Request::ScanBufferGet => Ok(Reply::Buffer(self.buffer.clone())),
            Request::ScanPropsSet(p) => {
                match p.continuous {
                    1 => self.continuous = true,
                    2 => self.continuous = false,
                    _ => {}
                }
                match p.bouncy {
                    1 => self.bouncy = true,
                    2 => self.bouncy = false,
                    _ => {}
                }
                // Set: 0 = no change, 1 = all, 2 = next, 3 = off; Get: 0 = all, 1 = next,
                // 2 = off.
                if (1..=3).contains(&p.autosave) {
                    self.autosave = p.autosave - 1;
                }
                if let Some(a) = p.autopaste
                    && (1..=3).contains(&a)
                {
                    self.autopaste = a - 1;
                }
                // Empty strings and an empty module list are taken as set (the manual
                // documents no "no change" value for them).
                self.series_name.clone_from(&p.series_name);
                self.comment.clone_from(&p.comment);
                self.modules.clone_from(&p.modules);
                Ok(Reply::Empty)
            }
            Request::ScanPropsGet => Ok(Reply::Props(ScanPropsState {
                continuous: u32::from(self.continuous),
                bouncy: u32::from(self.bouncy),
                autosave: self.autosave,
                series_name: self.series_name.clone(),
                comment: self.comment.clone(),
                modules: self.modules.clone(),
                // The simulator has no module parameters to save.
                parameters_per_module: vec![0; self.modules.len()],
                parameter_rows: 0,
                parameter_columns: 0,
                parameters: Vec::new(),
                autopaste: self.schema.props_set_autopaste.then_some(self.autopaste),
            })),
            Request::ScanXYPosGet { .. } => {
                self.flush(false)?;
                let p = self.sim.position().map_err(|e| describe(&e))?;
                let (x_m, y_m) = self.counts_to_m(p);
                Ok(Reply::F32x2([x_m as f32, y_m as f32]))
            }
            Request::ScanSpeedSet(s) => {
                let width = f64::from(self.frame.width_m);
                let (tf, tb) = match s.keep {
                    1 => (
                        width / f64::from(s.forward_speed_m_per_s),
                        width / f64::from(s.backward_speed_m_per_s),
                    ),
                    2 => (f64::from(s.forward_line_s), f64::from(s.backward_line_s)),
                    _ => (
                        f64::from(self.speed.forward_line_s),
                        f64::from(self.speed.backward_line_s),
                    ),
                };
                if !(tf.is_finite() && tb.is_finite() && tf > 0.0 && tb > 0.0) {
                    return Err(format!("invalid speed {s:?}"));
                }
                self.speed = ScanSpeed {
                    forward_speed_m_per_s: (width / tf) as f32,
                    backward_speed_m_per_s: (width / tb) as f32,
                    forward_line_s: tf as f32,
                    backward_line_s: tb as f32,
                    keep: if s.keep == 1 { 0 } else { 1 },
                    speed_ratio: (tf / tb) as f32,
                };
                Ok(Reply::Empty)
            }
            Request::ScanSpeedGet => Ok(Reply::Speed(self.speed)),
            other => Err(format!("nanonis-sim does not implement {}", other.name())),
        }
    }

    /// `FolMe.*` and `Motor.*`: the tip's lateral moves and the coarse motor.
    fn execute_motion(&mut self, request: &Request) -> Result<Reply, String> {
        match request {
            Request::FolMeXYPosSet {
                x_m,
                y_m,
                wait_end_of_move,
            } => {
                self.flush(false)?;
                self.compensation_off()?;
                self.feedback_on()?;
                // Custom speed, or the scan's forward speed ("use scan speed").
                let speed_m = if self.folme_custom {
                    self.folme_speed_m_per_s
                } else {
                    self.speed.forward_speed_m_per_s
                };
                if !(speed_m.is_finite() && speed_m > 0.0) {
                    return Err(format!("the Follow-Me speed {speed_m} m/s is not positive"));
                }
                if !(x_m.is_finite() && y_m.is_finite()) {
                    return Err("target is not finite".into());
                }
                let mut target =
                    CountPoint::from_counts(x_m / self.m_per_count[0], y_m / self.m_per_count[1]);
                // Checked now, so that the error is this command's even when the move
                // itself is executed with the settle that follows it.
                let caps = self.sim.capabilities();
                if target.x < caps.field_min.x
                    || target.y < caps.field_min.y
                    || target.x > caps.field_max.x
                    || target.y > caps.field_max.y
                {
                    let (lo, hi) = (
                        self.counts_to_m(caps.field_min),
                        self.counts_to_m(caps.field_max),
                    );
                    return Err(format!(
                        "out of range: target ({x_m:.4e}, {y_m:.4e}) m is outside the scan \
                         range [{:.4e}, {:.4e}] × [{:.4e}, {:.4e}] m",
                        lo.0, hi.0, lo.1, hi.1
                    ));
                }
                // Metres → counts is exact only to ~1e-12 counts: a target that close to the
                // commanded position is the commanded position (a move of length 0, as the
                // client meant it, not one of 1e-12 counts).
                let here = self.sim.position().map_err(|e| describe(&e))?;
                if (target.x - here.x).abs().value() < 1e-9
                    && (target.y - here.y).abs().value() < 1e-9
                {
                    target = here;
                }
                let m_per_count = (self.m_per_count[0] * self.m_per_count[1]).sqrt();
                let speed = decimal(speed_m) / m_per_count;
                self.pending = Pending::Move { target, speed };
                if *wait_end_of_move == 0 {
                    self.flush(false)?;
                }
                Ok(Reply::Empty)
            }
            Request::FolMeXYPosGet { .. } => {
                self.flush(false)?;
                let p = self.sim.position().map_err(|e| describe(&e))?;
                let (x_m, y_m) = self.counts_to_m(p);
                Ok(Reply::XY { x_m, y_m })
            }
            Request::FolMeSpeedSet {
                speed_m_per_s,
                custom,
            } => {
                let valid = speed_m_per_s.is_finite() && *speed_m_per_s > 0.0;
                if *custom == 1 && !valid {
                    return Err(format!("speed {speed_m_per_s} m/s is not positive"));
                }
                // With "use scan speed" the value is kept only when it is a speed.
                if valid {
                    self.folme_speed_m_per_s = *speed_m_per_s;
                }
                self.folme_custom = *custom == 1;
                Ok(Reply::Empty)
            }
            Request::FolMeSpeedGet => Ok(Reply::FolMeSpeed {
                speed_m_per_s: self.folme_speed_m_per_s,
                custom: u32::from(self.folme_custom),
            }),
            Request::FolMeStop | Request::MotorStopMove => {
                if matches!(self.pending, Pending::Move { .. }) {
                    self.flush(false)?;
                }
                Ok(Reply::Empty)
            }
            Request::MotorStartMove {
                direction, steps, ..
            } => {
                self.flush(false)?;
                self.feedback_on()?;
                let signed = match *direction {
                    motor_direction::Z_MINUS => i64::from(*steps),
                    motor_direction::Z_PLUS => -i64::from(*steps),
                    _ => {
                        // X and Y: the sample slides under the tip by a distance no
                        // simulator state follows; the steps are taken (time passes)
                        // and the surface stays where it is.
                        return self.lateral_motor_steps(*steps);
                    }
                };
                let Some(stage) = self.sim.coarse_z() else {
                    return Err("no motor module is configured".into());
                };
                stage.step(signed).map_err(|e| describe(&e))?;
                Ok(Reply::Empty)
            }
            Request::MotorFreqAmpGet(_) => {
                if self.sim.config().instrument.coarse_z.is_some() {
                    Ok(Reply::F32x2([1000.0, 100.0]))
                } else {
                    Err("no motor module is configured".into())
                }
            }
            other => Err(format!("nanonis-sim does not implement {}", other.name())),
        }
    }

    /// `ZCtrl.*` and `Signals.*`: the Z controller and the published signals.
    fn execute_readings(&mut self, request: &Request) -> Result<Reply, String> {
        match request {
            Request::ZCtrlZPosGet => {
                self.flush(false)?;
                let z = self.sim.z_position().map_err(|e| describe(&e))?;
                Ok(Reply::F32(self.z_metres(z.value())))
            }
            Request::ZCtrlOnOffSet(on) => {
                self.z_on = *on == 1;
                Ok(Reply::Empty)
            }
            Request::ZCtrlOnOffGet => Ok(Reply::U32(u32::from(self.z_on))),
            Request::SignalsValsGet { indexes, .. } => {
                self.flush(false)?;
                let t = self.sim.now().map_err(|e| describe(&e))?.value();
                let whole = t.floor();
                let mut values = Vec::with_capacity(indexes.len());
                for &i in indexes {
                    if i == self.config.time_whole_signal {
                        values.push(whole as f32);
                    } else if i == self.config.time_fraction_signal {
                        values.push((t - whole) as f32);
                    } else if i == self.config.z_channel {
                        let z = self.sim.z_position().map_err(|e| describe(&e))?;
                        values.push(self.z_metres(z.value()));
                    } else {
                        return Err(format!("nanonis-sim does not publish signal {i}"));
                    }
                }
                Ok(Reply::Values(values))
            }
            other => Err(format!("nanonis-sim does not implement {}", other.name())),
        }
    }
}

type Shared = Arc<Mutex<State>>;

fn lock(shared: &Shared) -> MutexGuard<'_, State> {
    match shared.lock() {
        Ok(guard) => guard,
        // A connection thread that panicked leaves the state as it was between commands.
        Err(poisoned) => poisoned.into_inner(),
    }
}

/// Counters the connection threads keep outside the instrument's lock (a thread reading a
/// request must not wait for a scan another connection is running).
#[derive(Debug, Default)]
struct Counters {
    /// Connections being served.
    active: AtomicUsize,
    /// Bytes of request-body buffers held now, and the most held at once.
    buffered: AtomicUsize,
    buffered_peak: AtomicUsize,
    refused: AtomicU64,
    timed_out: AtomicU64,
    oversized: AtomicU64,
    accept_errors: AtomicU64,
}

impl Counters {
    fn add_to(&self, stats: &mut ServerStats) {
        stats.refused_connections = self.refused.load(Ordering::SeqCst);
        stats.timed_out_connections = self.timed_out.load(Ordering::SeqCst);
        stats.oversized_requests = self.oversized.load(Ordering::SeqCst);
        stats.accept_errors = self.accept_errors.load(Ordering::SeqCst);
        stats.request_buffer_bytes_peak = self.buffered_peak.load(Ordering::SeqCst) as u64;
    }
}

/// What every connection thread shares.
#[derive(Clone)]
struct Context {
    shared: Shared,
    counters: Arc<Counters>,
    stop: Arc<AtomicBool>,
    limits: ConnectionLimits,
}

/// A bound server, not yet serving.
pub struct Server {
    listener: TcpListener,
    shared: Shared,
}

/// A server running in the background.
pub struct ServerHandle {
    addr: SocketAddr,
    stop: Arc<AtomicBool>,
    connections: Arc<Mutex<Vec<TcpStream>>>,
    shared: Shared,
    counters: Arc<Counters>,
    thread: Option<JoinHandle<()>>,
}

impl Server {
    /// Binds `address` (e.g. `127.0.0.1:0` for any free port) over a simulator.
    pub fn bind(
        address: &str,
        sim_config: SimConfig,
        config: ServerConfig,
    ) -> Result<Self, ServerError> {
        let sim = Simulator::new(sim_config).map_err(|e| ServerError::Config(e.to_string()))?;
        let state = State::new(sim, config)?;
        let listener = TcpListener::bind(address)?;
        Ok(Self {
            listener,
            shared: Arc::new(Mutex::new(state)),
        })
    }

    /// The address bound.
    pub fn local_addr(&self) -> Result<SocketAddr, ServerError> {
        Ok(self.listener.local_addr()?)
    }

    fn context(&self) -> Context {
        let limits = lock(&self.shared).config.limits.clone();
        Context {
            shared: Arc::clone(&self.shared),
            counters: Arc::new(Counters::default()),
            stop: Arc::new(AtomicBool::new(false)),
            limits,
        }
    }

    /// Serves until the process ends.
    pub fn serve(self) -> Result<(), ServerError> {
        let context = self.context();
        let connections = Arc::new(Mutex::new(Vec::new()));
        accept_loop(&self.listener, &context, &connections);
        Ok(())
    }

    /// Serves on a background thread.
    pub fn spawn(self) -> Result<ServerHandle, ServerError> {
        let addr = self.listener.local_addr()?;
        let context = self.context();
        let connections = Arc::new(Mutex::new(Vec::new()));
        let handle_parts = (
            Arc::clone(&context.stop),
            Arc::clone(&connections),
            Arc::clone(&context.shared),
            Arc::clone(&context.counters),
        );
        let listener = self.listener;
        let thread = std::thread::Builder::new()
            .name("nanonis-sim-accept".into())
            .spawn(move || accept_loop(&listener, &context, &connections))?;
        let (stop, connections, shared, counters) = handle_parts;
        Ok(ServerHandle {
            addr,
            stop,
            connections,
            shared,
            counters,
            thread: Some(thread),
        })
    }
}

impl ServerHandle {
    /// The address served.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// What the server did so far.
    pub fn stats(&self) -> ServerStats {
        let mut stats = lock(&self.shared).stats.clone();
        self.counters.add_to(&mut stats);
        stats
    }

    /// Connections being served now.
    pub fn active_connections(&self) -> usize {
        self.counters.active.load(Ordering::SeqCst)
    }

    /// Bytes of request-body buffers the server holds now, over all connections (their
    /// capacity: what is allocated).
    pub fn request_buffer_bytes(&self) -> usize {
        self.counters.buffered.load(Ordering::SeqCst)
    }

    /// Runs `f` on the simulator (tests: the oracle).
    pub fn with_simulator<T>(&self, f: impl FnOnce(&Simulator) -> T) -> T {
        f(&lock(&self.shared).sim)
    }

    /// The last frame's forward half as the simulator ran it ([`FrameTruth`]), once it has
    /// been simulated (its data grabbed or the instrument observed); `None` before, and for
    /// a frame that failed.
    pub fn last_frame_truth(&self) -> Option<FrameTruth> {
        let state = lock(&self.shared);
        let last = state.last_scan.as_ref()?;
        let frame = last.frame.as_ref().ok()?;
        Some(FrameTruth {
            time_s: frame.forward.time_s.clone(),
            effective_inputs: last.effective_inputs.clone(),
        })
    }

    /// The next `times` requests of `command` (`Scan.FrameSet`, …), on any connection, are
    /// answered with an error section and not executed, as a controller refuses an argument
    /// it does not accept (tests: a client's handling of a refusal, wherever the command
    /// stands in its sequence). `busy`: the description begins "busy" (a client sends such
    /// a request again), else it names the command and says it was refused, with none of
    /// the words that make an error transient. Replaces what was set for `command` before.
    pub fn refuse_next(&self, command: &str, times: u32, busy: bool) {
        let description = if busy {
            format!("busy: {command} not executed (injected: ServerHandle::refuse_next)")
        } else {
            format!("{command} refused (injected: ServerHandle::refuse_next); not executed")
        };
        lock(&self.shared)
            .refusals
            .insert(command.to_owned(), (times, description));
    }

    /// Runs `f` on the simulator, mutably (tests: switch the oracle's recording on).
    pub fn with_simulator_mut<T>(&self, f: impl FnOnce(&mut Simulator) -> T) -> T {
        f(&mut lock(&self.shared).sim)
    }

    /// Stops at once, as a killed process would: the listener closes and every open
    /// connection is shut down.
    pub fn kill(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        // Wake the accept loop.
        let _ = TcpStream::connect_timeout(&self.addr, Duration::from_millis(200));
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
        let connections = match self.connections.lock() {
            Ok(mut c) => std::mem::take(&mut *c),
            Err(poisoned) => std::mem::take(&mut *poisoned.into_inner()),
        };
        for c in connections {
            let _ = c.shutdown(Shutdown::Both);
        }
    }
}

impl Drop for ServerHandle {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// The pause after the `failures`-th consecutive failed `accept()`: 10 ms, doubling, at most
/// 1 s. Out of file descriptors (EMFILE), `accept` fails at once for as long as the
/// condition lasts, and a loop retrying at once spun at 100 % CPU (issue 25 item 11).
#[must_use]
pub fn accept_pause(failures: u32) -> Duration {
    let ms = 10u64.saturating_mul(1 << failures.saturating_sub(1).min(7));
    Duration::from_millis(ms.min(1000))
}

/// Decrements the active-connection count when a connection ends (or its thread never
/// starts).
struct Active(Arc<Counters>);

impl Drop for Active {
    fn drop(&mut self) {
        self.0.active.fetch_sub(1, Ordering::SeqCst);
    }
}

fn accept_loop(
    listener: &TcpListener,
    context: &Context,
    connections: &Arc<Mutex<Vec<TcpStream>>>,
) {
    // Consecutive failures: the first of a burst is logged, the rest counted, and the
    // burst's size logged when accept works again.
    let mut failures = 0u32;
    let mut refused_in_a_row = 0u64;
    loop {
        let accepted = listener.accept();
        if context.stop.load(Ordering::SeqCst) {
            break;
        }
        let stream = match accepted {
            Ok((stream, _)) => stream,
            Err(e) => {
                context
                    .counters
                    .accept_errors
                    .fetch_add(1, Ordering::SeqCst);
                failures = failures.saturating_add(1);
                if failures == 1 {
                    tracing::warn!(error = %e, "nanonis-sim: accept failed; retrying with a growing pause (up to 1 s) until it works again");
                }
                std::thread::sleep(accept_pause(failures));
                continue;
            }
        };
        if failures > 0 {
            tracing::warn!(failures, "nanonis-sim: accept works again");
            failures = 0;
        }
        let counters = &context.counters;
        if counters.active.load(Ordering::SeqCst) >= context.limits.max_connections {
            counters.refused.fetch_add(1, Ordering::SeqCst);
            refused_in_a_row += 1;
            if refused_in_a_row == 1 {
                tracing::warn!(
                    max_connections = context.limits.max_connections,
                    "nanonis-sim: connection refused: the cap of connections is reached"
                );
            }
            let _ = stream.shutdown(Shutdown::Both);
            continue;
        }
        refused_in_a_row = 0;
        let _ = stream.set_nodelay(true);
        if let (Ok(clone), Ok(mut list)) = (stream.try_clone(), connections.lock()) {
            list.retain(|s| s.peer_addr().is_ok());
            list.push(clone);
        }
        lock(&context.shared).stats.connections += 1;
        counters.active.fetch_add(1, Ordering::SeqCst);
        let active = Active(Arc::clone(counters));
        let context = context.clone();
        let spawned = std::thread::Builder::new()
            .name("nanonis-sim-connection".into())
            .spawn(move || {
                let _active = active;
                serve_connection(stream, &context);
            });
        if let Err(e) = spawned {
            tracing::warn!(error = %e, "nanonis-sim: cannot start a connection thread");
        }
    }
}

fn encode_reply(command: &str, reply: &Reply, error: &ErrorSection) -> Option<Vec<u8>> {
    let body = reply.encode(error).ok()?;
    let header = codec::encode_response_header(command, body.len()).ok()?;
    let mut bytes = Vec::with_capacity(HEADER_LEN + body.len());
    bytes.extend_from_slice(&header);
    bytes.extend_from_slice(&body);
    Some(bytes)
}

fn encode_raw_reply(command: &str, zeros: usize, error: &ErrorSection) -> Option<Vec<u8>> {
    let mut body = vec![0u8; zeros];
    let mut tail = codec::Writer::new();
    error.encode(&mut tail).ok()?;
    body.extend_from_slice(&tail.into_bytes());
    let header = codec::encode_response_header(command, body.len()).ok()?;
    let mut bytes = header.to_vec();
    bytes.extend_from_slice(&body);
    Some(bytes)
}

fn serve_connection(mut stream: TcpStream, context: &Context) {
    serve_commands(&mut stream, context);
    // Shut the socket down whatever the reason (the accept loop keeps a clone for `kill`,
    // which would otherwise keep it open and leave the client waiting for its timeout).
    let _ = stream.shutdown(Shutdown::Both);
}

/// Why a read ended without its bytes.
enum ReadEnd {
    /// The peer closed the connection, or the socket failed.
    Closed,
    /// The deadline passed.
    TimedOut,
}

/// Bytes of a connection's read-ahead: a client writes a request's header and body in one
/// piece, so one `recv` into it usually brings a whole request (bodies longer than it are
/// read into their own buffer, [`BODY_CHUNK_BYTES`] at a time).
pub const READ_AHEAD_BYTES: usize = 4 << 10;

/// The read side of a connection: the bytes received ahead of what was asked for, and the
/// read timeout last set on the socket (set again only when another one is needed). A request
/// that arrives whole costs one `recv` and no other system call.
struct Incoming {
    ahead: Box<[u8]>,
    /// The unread bytes are `ahead[start..end]`.
    start: usize,
    end: usize,
    timeout: Option<Duration>,
}

impl Incoming {
    fn new() -> Self {
        Self {
            ahead: vec![0u8; READ_AHEAD_BYTES].into_boxed_slice(),
            start: 0,
            end: 0,
            timeout: None,
        }
    }

    /// Whether bytes are waiting in the read-ahead.
    fn has_bytes(&self) -> bool {
        self.start < self.end
    }

    /// One `recv` of at least one byte into `buf` (into the read-ahead when `buf` is `None`)
    /// by `deadline`: the first attempt with the timeout `first` (the whole allowance, set on
    /// the socket only when it is not set already), another after a timeout or an
    /// interruption that left time.
    fn recv_by(
        &mut self,
        stream: &mut TcpStream,
        mut buf: Option<&mut [u8]>,
        deadline: Instant,
        first: Duration,
    ) -> Result<usize, ReadEnd> {
        let mut timeout = first;
        loop {
            if timeout.is_zero() {
                return Err(ReadEnd::TimedOut);
            }
            if self.timeout != Some(timeout) {
                self.timeout = None;
                if stream.set_read_timeout(Some(timeout)).is_err() {
                    return Err(ReadEnd::Closed);
                }
                self.timeout = Some(timeout);
            }
            let read = match buf.as_deref_mut() {
                Some(buf) => stream.read(buf),
                None => stream.read(&mut self.ahead),
            };
            match read {
                Ok(0) => return Err(ReadEnd::Closed),
                Ok(n) => return Ok(n),
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock
                            | std::io::ErrorKind::TimedOut
                            | std::io::ErrorKind::Interrupted
                    ) => {}
                Err(_) => return Err(ReadEnd::Closed),
            }
            timeout = deadline.saturating_duration_since(Instant::now());
        }
    }

    /// Waits up to `idle` for the first byte of a request (none when the read-ahead holds
    /// one already).
    fn wait_for_request(&mut self, stream: &mut TcpStream, idle: Duration) -> Result<(), ReadEnd> {
        if self.has_bytes() {
            return Ok(());
        }
        let n = self.recv_by(stream, None, Instant::now() + idle, idle)?;
        (self.start, self.end) = (0, n);
        Ok(())
    }

    /// Fills `buf` exactly, all by `deadline`: from the read-ahead first, then from the
    /// socket (a part at least as long as the read-ahead straight into `buf`).
    fn read_by(
        &mut self,
        stream: &mut TcpStream,
        buf: &mut [u8],
        deadline: Instant,
    ) -> Result<(), ReadEnd> {
        let mut at = 0;
        while at < buf.len() {
            if self.has_bytes() {
                let n = (self.end - self.start).min(buf.len() - at);
                buf[at..at + n].copy_from_slice(&self.ahead[self.start..self.start + n]);
                self.start += n;
                at += n;
                continue;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if buf.len() - at >= self.ahead.len() {
                at += self.recv_by(stream, Some(&mut buf[at..]), deadline, left)?;
            } else {
                let n = self.recv_by(stream, None, deadline, left)?;
                (self.start, self.end) = (0, n);
            }
        }
        Ok(())
    }
}

/// A request body's buffer, counted in [`Counters::buffered`] while it lives.
struct BodyBuffer<'a> {
    bytes: Vec<u8>,
    counted: usize,
    counters: &'a Counters,
}

impl BodyBuffer<'_> {
    /// Makes room for `n` more bytes (exactly: the buffer never holds more than what arrived
    /// plus one chunk) and counts the allocation.
    fn grow(&mut self, n: usize) {
        self.bytes.reserve_exact(n);
        let capacity = self.bytes.capacity();
        let added = capacity.saturating_sub(self.counted);
        self.counted = capacity;
        let now = self.counters.buffered.fetch_add(added, Ordering::SeqCst) + added;
        self.counters.buffered_peak.fetch_max(now, Ordering::SeqCst);
    }
}

impl Drop for BodyBuffer<'_> {
    fn drop(&mut self) {
        self.counters
            .buffered
            .fetch_sub(self.counted, Ordering::SeqCst);
    }
}

/// Reads one request: the first byte within the idle timeout, the rest of the header and
/// the body within the message timeout, the body in chunks as it arrives. `None` ends the
/// connection (closed, timed out, malformed or oversized; counted).
fn read_request(
    stream: &mut TcpStream,
    incoming: &mut Incoming,
    context: &Context,
) -> Option<(codec::RequestHeader, Vec<u8>)> {
    let limits = &context.limits;
    let counters = &context.counters;
    let timed_out = |end: ReadEnd, what: &str| {
        if matches!(end, ReadEnd::TimedOut) {
            counters.timed_out.fetch_add(1, Ordering::SeqCst);
            tracing::debug!("nanonis-sim: {what}; closing the connection");
        }
    };
    let mut header = [0u8; HEADER_LEN];
    let idle = Duration::from_secs_f64(limits.idle_timeout_s);
    if let Err(end) = incoming.wait_for_request(stream, idle) {
        timed_out(end, "idle beyond the idle timeout");
        return None;
    }
    let deadline = Instant::now() + Duration::from_secs_f64(limits.message_timeout_s);
    if let Err(end) = incoming.read_by(stream, &mut header, deadline) {
        timed_out(
            end,
            "a request's header not whole within the message timeout",
        );
        return None;
    }
    let header = match codec::decode_request_header(&header) {
        Ok(h) => h,
        Err(e) => {
            tracing::warn!(error = %e, "nanonis-sim: malformed header; closing the connection");
            lock(&context.shared).stats.malformed += 1;
            return None;
        }
    };
    if header.body_len > limits.max_request_body_bytes {
        counters.oversized.fetch_add(1, Ordering::SeqCst);
        tracing::warn!(
            command = %header.command,
            body_bytes = header.body_len,
            max = limits.max_request_body_bytes,
            "nanonis-sim: request body larger than the limit; closing the connection"
        );
        return None;
    }
    let mut body = BodyBuffer {
        bytes: Vec::new(),
        counted: 0,
        counters,
    };
    while body.bytes.len() < header.body_len {
        let at = body.bytes.len();
        let n = BODY_CHUNK_BYTES.min(header.body_len - at);
        body.grow(n);
        body.bytes.resize(at + n, 0);
        if let Err(end) = incoming.read_by(stream, &mut body.bytes[at..], deadline) {
            timed_out(end, "a request's body not whole within the message timeout");
            return None;
        }
    }
    Some((header, std::mem::take(&mut body.bytes)))
}

fn serve_commands(stream: &mut TcpStream, context: &Context) {
    let (shared, stop) = (&context.shared, &context.stop);
    let mut incoming = Incoming::new();
    loop {
        if stop.load(Ordering::SeqCst) {
            return;
        }
        let pipelined = incoming.has_bytes();
        let Some((header, body)) = read_request(stream, &mut incoming, context) else {
            return;
        };
        let (fault, bytes) = {
            let mut state = lock(shared);
            if stop.load(Ordering::SeqCst) {
                return;
            }
            state.stats.commands += 1;
            state.stats.pipelined += u64::from(pipelined);
            // The name is copied once, on its first request.
            match state.stats.commands_by_name.get_mut(&header.command) {
                Some(n) => *n += 1,
                None => {
                    state
                        .stats
                        .commands_by_name
                        .insert(header.command.clone(), 1);
                }
            }
            let fault = state.draw_fault(&header.command);
            let refused = state.take_refusal(&header.command);
            let request = Request::decode(&header.command, &body, state.schema);
            let bytes = match (fault, request) {
                (Fault::DropBefore, _) => {
                    state.stats.injected_drops_before += 1;
                    return;
                }
                (_, Err(CodecError::UnknownCommand(name))) => {
                    // Zeros for its return arguments (every count 0), then the error: a
                    // client decoding the command's documented reply reads the error.
                    tracing::debug!(command = %name, "nanonis-sim: command not implemented");
                    encode_raw_reply(
                        &header.command,
                        crate::neutral::neutral_len(&name),
                        &ErrorSection::error(format!("nanonis-sim does not implement {name}")),
                    )
                }
                (_, Err(e)) => {
                    state.stats.malformed += 1;
                    tracing::debug!(error = %e, command = %header.command, "nanonis-sim: invalid request");
                    encode_reply(
                        &header.command,
                        &Reply::Empty,
                        &ErrorSection::error(format!("invalid request: {e}")),
                    )
                }
                (_, Ok(request)) if refused.is_some() => encode_reply(
                    &header.command,
                    &request.neutral_reply(state.schema),
                    &ErrorSection::error(refused.unwrap_or_default()),
                ),
                (Fault::ErrorReply, Ok(request)) => {
                    state.stats.injected_error_replies += 1;
                    encode_reply(
                        &header.command,
                        &request.neutral_reply(state.schema),
                        &ErrorSection::error("busy: injected fault (error reply)"),
                    )
                }
                (_, Ok(request)) => match state.execute(&request) {
                    Ok(reply) => encode_reply(&header.command, &reply, &ErrorSection::ok()),
                    Err(description) => encode_reply(
                        &header.command,
                        &request.neutral_reply(state.schema),
                        &ErrorSection::error(description),
                    ),
                },
            };
            match fault {
                Fault::DropAfter => state.stats.injected_drops_after += 1,
                Fault::OneByte => state.stats.injected_one_byte_writes += 1,
                Fault::Delay => state.stats.injected_delays += 1,
                Fault::Stall => state.stats.injected_stalls += 1,
                _ => {}
            }
            let delays = (state.config.faults.delay_s, state.config.faults.stall_s);
            (
                match fault {
                    Fault::Delay => Some(delays.0),
                    Fault::Stall => Some(delays.1),
                    Fault::DropAfter => None,
                    _ => Some(0.0),
                },
                (fault, bytes),
            )
        };
        let (fault_kind, bytes) = bytes;
        let Some(delay_s) = fault else {
            return; // dropped after executing
        };
        if delay_s > 0.0 {
            std::thread::sleep(Duration::from_secs_f64(delay_s));
        }
        if !header.send_response {
            continue;
        }
        let Some(bytes) = bytes else {
            tracing::warn!(command = %header.command, "nanonis-sim: cannot encode the reply");
            return;
        };
        let written = if fault_kind == Fault::OneByte {
            bytes
                .iter()
                .try_for_each(|b| stream.write_all(std::slice::from_ref(b)))
        } else {
            stream.write_all(&bytes)
        };
        if written.is_err() {
            return;
        }
    }
}
