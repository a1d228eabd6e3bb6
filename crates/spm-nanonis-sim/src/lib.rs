#![doc = include_str!("../README.md")]
//!
//! # spm-nanonis-sim: the Nanonis TCP protocol over the simulated microscope
//!
//! A TCP server that answers the commands [`spm_nanonis`] uses, byte for byte as the
//! manual describes them, by driving an [`spm_sim::Simulator`]: a user can run the whole
//! pipeline over a socket without hardware (`spmcal nanonis-sim`), and the backend is
//! tested against it.
//!
//! - **One thread per connection**; the simulated instrument is shared (a mutex), and the
//!   commands of one connection are executed in order, as on the controller.
//! - **Strict.** Headers must be exact (NUL padding, flags, unused bytes 0); bodies must be
//!   exactly the command's arguments under the server's release ([`ServerConfig::host_release`]
//!   decides the form of `Scan.PropsSet`); flags must be documented values. A malformed
//!   header closes the connection (its framing is lost); a malformed body, an unknown
//!   command or a setting the simulator does not model gets an error reply.
//! - **Like a controller left as a user had it**: drift, tilt and hysteresis compensation
//!   start on, continuous and bouncy scanning start on, and scans and moves are refused
//!   until they are off (the simulator does not model the controller's corrections, so
//!   it refuses to pretend); pixels per line are coerced to the closest multiple of 16.
//! - **Time** is the simulator's: published as two signals (whole seconds and fraction,
//!   [`ServerConfig::time_whole_signal`], [`ServerConfig::time_fraction_signal`]);
//!   `Scan.WaitEndOfScan` with no scan running waits its timeout in simulated time.
//! - **One simulator call per instrument operation**, so a run over TCP costs the same
//!   simulated time and random draws as in-process: a Follow-Me move is executed together
//!   with the settle wait that follows it (`FolMe.XYPosSet` then `Scan.WaitEndOfScan`),
//!   and a scan when its data are first needed (the first `Scan.FrameDataGrab` says
//!   whether the backward trace is wanted). Every command that observes the instrument
//!   first completes what is pending, so nothing of this is visible to a client except
//!   that errors of a scan are reported by the data grab, and an instrument fault during
//!   a Follow-Me move (a simulated fault; a target out of range is refused by
//!   `FolMe.XYPosSet` itself) by the command that completes the move.
//! - **Where a controller's behaviour is uncertain**, the server follows the manual and the
//!   vendor's Python client (`nanonis-spm` 1.0.9), which `conformance/vendor_client.py`
//!   drives through a whole session (README):
//!   - *Both halves of the last frame* stay readable until the next scan starts, in any
//!     order and after any other command, from any connection. A frame whose first
//!     execution recorded only the forward trace keeps a copy of the instrument as it was
//!     when the scan began; a later backward grab simulates the frame there again with the
//!     retrace recorded and keeps its backward half. Its deterministic physics is that of
//!     the frame; its noise is drawn independently of the forward half's. The instrument
//!     itself is not touched, so a run stays identical to the same run in process.
//!   - *`Scan.StatusGet`*: 1 from `Scan.Action` start until the scan's end is observed —
//!     `Scan.WaitEndOfScan`, a data grab or any command that observes the instrument, or a
//!     second poll (the simulator runs a frame in one piece: the first poll after the
//!     start sees it running, the next one finds it ended and simulated). A
//!     `Scan.WaitEndOfScan` after such an end returns at once with that end of scan.
//!   - *Pause and resume* (`Scan.Action` 2 and 3) hold a frame at its start: while paused
//!     it runs (status 1), its data are NaN (nothing acquired) and no end of scan comes
//!     (waits time out); resumed, it runs whole.
//!   - *Scanning down* (`Scan.Action` with direction 0, as in the vendor's examples): the
//!     frame's top line first; simulated line by line (spm-sim's rasters step upwards), so
//!     a downward frame costs one simulator call overhead and one pixel step of travel
//!     more per line than an upward one. Frame data come top row first either way and the
//!     reply's direction says which way the frame was scanned.
//!   - *Frame angles*: 0° and 180° are spm-sim's direct and counter rasters; any other
//!     angle turns the direct raster about the frame's centre (clockwise for positive
//!     angles, as the manual has it; `spm_sim::Simulator::scan_turned`).
//!   - *Non-square pixels* (e.g. 100 pixels coerced to 96 on a square frame of 100 lines)
//!     are scanned: the simulator scans each line with square pixels at the line spacing,
//!     and each line is resampled (linear interpolation) at the frame's pixel centres.
//!   - *`FolMe.SpeedSet` with "use scan speed"* (custom 0) moves at the scan's forward
//!     speed; `FolMe.SpeedGet` answers the custom speed and the flag.
//!   - *A Follow-Me target outside the range* is refused by `FolMe.XYPosSet` itself, even
//!     when the move is executed with the settle that follows.
//!   - *`ZCtrl.OnOffSet`* switches the feedback; with it off, scans and moves are refused
//!     (the simulator does not model constant-height operation).
//!   - *Z saturates*: `ZCtrl.ZPosGet`, the Z signal and frame data never leave the Z
//!     range `Piezo.RangeGet` gives; beyond it the reading is the end of the range.
//!   - *X and Y coarse steps* take the motor's step time; spm-sim has no lateral stage, so
//!     the simulated sample stays where it is.
//!   - *`Scan.PropsSet`'s module list*: the size field of the string array is accepted
//!     both as the bytes the elements occupy (the manual's wording) and as `4 × count`
//!     (what the vendor client sends; see `spm_nanonis::codec`). `Scan.PropsGet` answers
//!     the exact byte total (the vendor client advances by it), no module parameters
//!     (a 0 × 0 array, which the vendor client decodes) and autosave/autopaste in the
//!     Get coding (0 = all, 1 = next, 2 = off).
//!   - *Commands it does not implement* get zeros for their documented return arguments
//!     (every count 0) followed by the error "nanonis-sim does not implement …", so that
//!     a client decoding the command's reply reads the error, not garbage.
//! - **Ground truth for clients' tests**: [`ServerHandle::last_frame_truth`] gives the last
//!   frame's forward pixels as the simulator scanned them, in acquisition order — their times
//!   and, while the simulator records them, their effective inputs (a downward frame's lines
//!   joined) — against which a client's pixel positions and time stamps are checked.
//! - **Socket-level fault injection** ([`SocketFaults`], seeded): error replies, replies
//!   written one byte at a time, delays, stalls longer than the client's timeout,
//!   connections dropped before or after executing a command, and a scan left running.
//!   And on demand, for a test: the next requests of a named command refused with an error
//!   section, not executed ([`ServerHandle::refuse_next`]), as a controller refuses an
//!   argument — wherever the command stands in a client's sequence or pipeline.
//! - **Bounded by the server, not by its clients** ([`ConnectionLimits`], issue 25 item 11):
//!   at most `max_connections` (default 8) are served, one more is accepted and closed at
//!   once; a request must arrive whole within `message_timeout_s` (10 s) of its first byte,
//!   and a connection idle for `idle_timeout_s` (600 s) is closed; a request body above
//!   `max_request_body_bytes` (1 MiB) closes the connection, and a body is read in chunks
//!   of [`BODY_CHUNK_BYTES`] (64 KiB), so a claimed 80 MiB body that never arrives costs
//!   one chunk, not 80 MiB (plus the connection's fixed read-ahead of [`READ_AHEAD_BYTES`],
//!   4 KiB, into which one `recv` usually brings a whole request: a request that arrives
//!   whole costs that `recv` and no other system call, the read timeout being set on the
//!   socket only when it changes). A failing `accept()` (out of file descriptors) is retried after
//!   a pause growing from 10 ms to 1 s ([`accept_pause`]), the first failure of a burst
//!   logged and the burst's size when accepting works again.

mod neutral;
pub mod server;

pub use server::{
    BODY_CHUNK_BYTES, ConnectionLimits, FrameTruth, READ_AHEAD_BYTES, Server, ServerConfig,
    ServerError, ServerHandle, ServerStats, SocketFaults, accept_pause,
};

/// The backend configuration for talking to a `nanonis-sim` server on loopback `port` with the
/// server's own conventions: 16-bit X/Y and Z DACs, Z in signal 30, the controller's clock in
/// signals 126 (whole seconds) and 127 (fraction), 4096 × 4096 pixels at ≥ 1 µs, an upright
/// frame scanned up, 1 s to connect, 5 s per command (2 s wait margin), 2 reconnects 20 ms
/// apart. Tests, benches and examples change what they are about with struct-update syntax.
#[must_use]
pub fn loopback_config(port: u16) -> spm_nanonis::NanonisConfig {
    spm_nanonis::NanonisConfig {
        host: "127.0.0.1".into(),
        port,
        connect_timeout_s: 1.0,
        command_timeout_s: 5.0,
        wait_margin_s: 2.0,
        reconnect_attempts: 2,
        reconnect_backoff_s: 0.02,
        lateral_dac_bits: 16,
        z_dac_bits: 16,
        z_channel: 30,
        clock: spm_nanonis::ClockSource::ControllerSignals {
            whole_s_signal: 126,
            fraction_s_signal: 127,
            virtual_time: true,
        },
        max_pixels_per_line: 4096,
        max_lines: 4096,
        min_pixel_dwell_s: 1e-6,
        coarse_z: None,
        frame_angle_deg: 0.0,
        slow_direction: spm_nanonis::SlowDirection::Up,
    }
}
