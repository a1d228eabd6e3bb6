#![doc = include_str!("../README.md")]
//!
//! # spm-nanonis: a Nanonis (SPECS) controller behind spm-hal's `Microscope`
//!
//! Three layers, written from the vendor's manual "Nanonis TCP Protocol — TCP Programming
//! Interface" (it ships with the vendor's MIT-licensed Python client `nanonis-spm`):
//!
//! - [`codec`]: the wire format — 40-byte request and response headers, big-endian
//!   numbers, size-prefixed strings, 1-D and 2-D arrays, the error section. Tested on the
//!   manual's own hex examples and by round-trip properties; fuzzed (`fuzz/`).
//! - [`commands`] and [`client`]: the commands used, with their argument schemas (strict
//!   in both directions), and a blocking client: exact frames, per-command timeouts
//!   (longer for wait-style commands), reconnection with backoff, the schema chosen by
//!   `Util.VersionGet`, and a second connection for stop and abort.
//! - [`NanonisMicroscope`]: [`spm_hal::Microscope`] on top.
//!
//! ## Units: the counts convention
//! spm-hal speaks DAC counts; the controller speaks metres. `Piezo.CalibrGet` gives the
//! calibration of the ±10 V low-voltage outputs in m/V, and the job states the DAC width
//! (`lateral_dac_bits`, `z_dac_bits`). **One count is `20 V / 2^bits` of the output**, so
//! `metres = counts × calibration × 20 V / 2^bits`; count 0 is 0 m (the field centre) and
//! the field is `[−2^(bits−1), 2^(bits−1) − 1]` counts. A calibration in nm/count is then
//! a correction of the controller's own nominal calibration: with the controller's
//! calibration changed, the counts (and the calibration) change with it.
//!
//! ## The instrument clock
//! The protocol has no clock command. [`ClockSource::Host`] uses the host's monotonic
//! clock (hardware); [`ClockSource::ControllerSignals`] reads the controller's time from
//! two signals (whole seconds and fraction), which is how `nanonis-sim` publishes its
//! simulated time; waits then run on the controller as `Scan.WaitEndOfScan` timeouts,
//! quantised to whole milliseconds by that command's `int` argument (the remainder is
//! carried to the next wait, so the controller's clock stays within ½ ms of the sum of the
//! waits asked). A move's settle is always sent as such a wait, even of 0 ms, so that the
//! controller sees a move and its settle as one operation.
//!
//! ## Round trips
//! Every command is a round trip (13–14 µs to an idle `nanonis-sim` on loopback, more under
//! load, when each reply waits for a core), and a
//! calibration asks the clock and the position far more often than it changes them: spm-hal's command recorder reads both around every move, wait and scan,
//! and the feature tracking reads them again before each move. The backend answers these
//! without asking where the answer is known exactly, and nowhere else:
//! - **The position.** spm-hal's [`spm_hal::Microscope::position`] is the *commanded*
//!   position, not a measurement. After `FolMe.XYPosSet` with *wait end of move* (and its
//!   settle) it is the move's target, which the backend keeps, as it keeps it through a wait
//!   and a Z read (neither moves the tip); after anything else (a scan
//!   leaves the tip where the controller's scan module put it, a stop where it stopped, a
//!   failed move somewhere on its way) it is read with `FolMe.XYPosGet` (float64 metres),
//!   and that reading is kept. The target is the reading up to float64 rounding of the
//!   metres conversion (the controller's own DAC quantisation is not in either).
//! - **The clock**, with [`ClockSource::ControllerSignals`] and `virtual_time` (a simulated
//!   controller, `nanonis-sim`): a virtual clock advances only while the controller executes
//!   a command, and reading the clock or the position takes none of it (spm-sim's `now` and
//!   `position` cost no call overhead; its Z read does, so `ZCtrl.ZPosGet` ends a reading
//!   like any other command). The elapsed time since a reading is then known exactly — zero
//!   — until the backend sends anything else, and the reading is the answer. A controller
//!   clock that runs in real time (`virtual_time = false`) is read at every
//!   [`spm_hal::Microscope::now`]; [`ClockSource::Host`] costs no round trip at all.
//! - **What "anything else" is**: a kept reading holds while [`Client::sequence`] stands —
//!   it grows with every command sent on either connection (stops included) and every
//!   connection opened; a read of the clock or the position extends the readings when it
//!   was the only command sent since them. Like the scan settings left unsent when
//!   unchanged, this assumes that the backend is the controller's only client during a run.
//! - **Whether a scan runs.** `Scan.StatusGet` (and a stop of a scan found running) comes
//!   before a scan only when the backend does not know that none runs: when it opens, after
//!   any failed call (a scan may have been left running or paused, a stop may have failed),
//!   after an interruption, and on every new connection (a lost one may have left a scan
//!   running; a connection found lost at the scan's start is not reused for the start
//!   before the question is asked there, [`Client::call_on_one_connection`]). Between
//!   scans of its own that ended normally (`Scan.WaitEndOfScan` answered the end) nothing
//!   the backend sends starts one — moves, waits and reads do not — so the answer is known.
//!   This is the same assumption again: only another client could start a scan in between
//!   (were one to, the controller would meet the backend's start with its scan running).
//! - **Pipelined with a simulated controller** (`virtual_time`, `nanonis-sim`): a command
//!   and what follows it are sent in one write and answered in order
//!   ([`Client::call_pipelined`]): a move (`FolMe.XYPosSet`), its settle and the clock read
//!   after them (one round trip for three; a move the controller refuses is followed by its
//!   settle all the same: time passes, and the clock is read again after the failure); and
//!   a whole scan, one round trip for 5 to 11 commands: the settings that differ from those
//!   last sent on this connection (`Scan.BufferSet` and `Scan.SpeedSet` with their
//!   read-backs, `Scan.FrameSet`), the start (`Scan.Action`), the wait for its end
//!   (`Scan.WaitEndOfScan`), its frame data, the clock and the position. The readings are
//!   kept as if read one by one (reads take no virtual time). The controller executes a
//!   connection's commands one after another, so a pipeline is the same commands without
//!   the wait for each reply between them; from a failure in it that the client retries (a
//!   busy reply, a lost connection) on, the rest is sent one by one.
//!   **A refusal in a scan's pipeline.** The controller executes the whole pipeline
//!   whatever it answers to each part, so when a setting or the start is refused (or a
//!   read-back does not fit) it has run what followed by the time the refusal is read: a
//!   scan of the settings it had (the previous frame), or for a refused start a wait for
//!   no scan (the wait's timeout of virtual time: the scan's duration and the wait margin,
//!   with an interrupt flag one slice of [`INTERRUPT_POLL_S`]). The backend then stops any
//!   scan (`Scan.Action` stop, on the second connection, after every reply of the pipeline
//!   is in: the controller has executed them all), discards every reply after the refusal,
//!   forgets the settings sent (all sent again, and `Scan.StatusGet` asked, before the next
//!   scan) and returns the refusal as the error, naming the refused command: nothing after
//!   a failure is ever taken as data (`over_tcp::a_refused_setting_or_start_in_the_scan_pipeline_is_an_error_naming_it_and_no_frame`,
//!   each of `Scan.BufferSet`, `Scan.FrameSet`, `Scan.SpeedSet` and `Scan.Action` refused
//!   by nanonis-sim's `ServerHandle::refuse_next`). A scan that ran on other settings than
//!   those asked for — a setting refused, even as busy, before a start that was executed —
//!   is an error even when the refusal is one the client would otherwise send again (a busy
//!   one stays transient, and the calibration measures the node again from its move): the
//!   tip has scanned another frame since the run's move and settle. Retried in place, it
//!   spoiled a record (kx 7 % off) in `socket_faults_at_five_percent_of_commands_spoil_nothing`
//!   (`tests/`). What ran nothing unasked is retried, the scan done again one step after
//!   another (status, set-up, start, then its end) with the client's retries: a busy start
//!   (the wait after it waited for no scan), a busy read-back, a lost connection (nanonis-sim
//!   executes nothing after closing one, and a connection the client drops after a timeout
//!   is reset, so that the requests behind a stalled reply are not executed later: see
//!   [`client`]; `over_tcp::a_busy_start_in_the_scan_pipeline_is_retried_and_a_busy_frame_is_the_error`).
//!   What a refused setting made the controller do costs virtual time only, which is one
//!   reason this is done with a simulated controller alone.
//!   **Hardware** (a real-time or host clock) keeps one command per round trip, as the
//!   vendor's client sends them: the manual has each connection execute its commands one
//!   after another, but documents neither that a controller reads a request before it has
//!   answered the one before nor what it does with several under way, and no controller
//!   has been checked with them; and on hardware a scan on a refused frame would scan
//!   where the run did not ask for.
//! - **Replies polled for with a simulated controller**: the same `virtual_time` controller
//!   on the same host answers most commands within microseconds, and waking the thread
//!   that slept waiting for the reply takes longer (tens of µs on a virtual machine, where
//!   the sleeping CPU is idle), so each reply is polled for up to [`REPLY_POLL`] (50 µs)
//!   before the thread sleeps ([`Client::set_reply_poll`]). Hardware: no polling.
//!
//! On the small HOPG plan against `nanonis-sim` (`cargo test -p xtask --release
//! nanonis_overhead -- --ignored`): 472 commands per node, each a round trip, before the
//! three points above; 430 commands in 196 round trips with the move, the scan settings and
//! the scan's end pipelined; 430 in 95 round trips now (a move one, a scan one). A round
//! trip in a run costs far more than a bare one on an idle virtual machine (about 55 µs
//! against 13 µs: the other thread's idle virtual CPU has to be woken), so the round
//! trips, not the commands' work (under 2 % of either side's time), are the overhead. Time
//! per node over TCP ÷ in process, idle machine: 2.50–2.74 before, 1.47–1.51 with 196
//! round trips, 1.33–1.38 now (median 1.36), against 1.45–1.52 (median 1.48) for the build
//! before, alternated at load 1.8–2.0 (docs/RESULTS.md, "Nanonis").
//! - **Not done**, each for a reason:
//!   the clock after a move or a wait is not derived from the time asked (the controller
//!   adds its own overhead: nanonis-sim its simulator's call overhead), so it is read once
//!   after them; the end of a scan's position is not derived
//!   from the frame (where the controller leaves the tip after a frame is its scan module's
//!   choice, and the frame is realised in float32), so it is read once;
//!   the X and Y signals are not read in the clock's `Signals.ValsGet` (one round trip for
//!   both), because that command answers float32, 2·10⁻³ counts at the edge of a 16-bit
//!   field where `FolMe.XYPosGet` is exact; a move is not sent with the scan after it (spm-hal
//!   reads the clock after the move before it asks for the scan, and the backend does not
//!   know what comes next), so a move and a scan stay a round trip each, 86 of the 95 per
//!   node; a wait or a Z read and the clock read after it are still two (3 round trips per
//!   node).
//!
//! ## Failures
//! A reply "busy" (not executed) is sent again; a command whose connection was lost is sent
//! again when that is safe (everything but the relative `Motor.StartMove` steps), up to
//! [`client::RETRIES`] times over a fresh connection; timeouts, error replies and frames that
//! do not fit the request become [`NanonisError`]s whose [`spm_hal::ErrorKind`] tells the
//! calibration what to do (transient: retry the node; aborted: stop the run).
//!
//! ## Pitfalls handled
//! - **Pixels per line are coerced to a multiple of 16** (`Scan.BufferSet`: data travel
//!   from the real-time engine in packets of 16; `Capabilities::pixels_per_line_multiple`
//!   is 16). A request of `n` pixels that divides `m = ⌈n/16⌉·16` (2, 4, 8 of 16; any
//!   multiple of 16) is scanned in its own frame and line time as `m` samples, `m/n` in
//!   each requested pixel's cell at `n/m` of its dwell, each pixel their mean (centred on
//!   it, timed at its dwell's middle): the tip moves as the request says. Any other `n`
//!   (or a dwell whose `n/m` is below the shortest) is scanned as `m` pixels with the same
//!   pixel step, the extra pixels continuing the forward trace past the requested ones, and
//!   cropped; the pixel times account for the longer lines. The buffer is read back
//!   (`Scan.BufferGet`) and a mismatch is an error.
//! - **Continuous and bouncy scanning** (and autosave, autopaste) are switched off by
//!   `Scan.PropsSet` when the backend opens: left on, the controller starts the next frame
//!   (in the other direction, for bouncy) and the data grabbed are not the scan requested.
//!   `Scan.PropsSet` gained its *Autopaste* argument in release R5.1.14573: the argument is
//!   sent only to controllers of that release or later (`Util.VersionGet`).
//! - **The controller's own compensation** — drift (`Piezo.DriftCompSet`), tilt
//!   (`Piezo.TiltSet`) and hysteresis (`Piezo.HystOnOffSet`) — is switched off and read
//!   back when the backend opens, and what was found is kept in [`ControllerState`]
//!   (logged, and stored with the run by `spmcal calibrate`). Left on, the calibration is
//!   done on already-corrected coordinates: it measures the correction, not the scanner.
//! - **A scan already running** (started by a user or left by a lost connection) or paused
//!   (left by an interrupted run) is stopped on the second connection when the backend opens
//!   and before a new scan starts whenever a scan may be running (`Scan.StatusGet`; see
//!   "Round trips" for when it is known that none is).
//! - **Scan speed** is set with the time per line kept constant and read back
//!   (`Scan.SpeedGet`): the pixel times are reconstructed from the line times the
//!   controller actually uses: pixel `k` of line `l` at
//!   `start + l·(t_fwd + t_bwd) + (k + ½)·t_fwd/pixels`, backward pixels after `t_fwd`, and
//!   `start` = the controller time at the end of the scan − `lines·(t_fwd + t_bwd)`.
//! - **Counter scans** use the frame turned by 180°: its forward traces run along −x and
//!   its lines step along −y.
//! - **A frame angle** ([`NanonisConfig::frame_angle_deg`], positive clockwise as in
//!   `Scan.FrameSet`) turns the counts convention with it: counts are scaled to metres
//!   and turned by the angle, so moves, positions and every scan frame (counter scans at
//!   the angle + 180°) are on the turned axes, and the field is the largest square of the
//!   turned axes inside the controller's range.
//! - **The slow direction** ([`NanonisConfig::slow_direction`], [`SlowDirection`]): every
//!   frame is started up (`Scan.Action` direction 1, the default) or down (0). spm-hal's
//!   frame contract holds either way, so nothing above the backend knows: the pixel of line
//!   `l`, pixel `k` lies at `ScanRequest::commanded_position`, and its time stamp is when it
//!   was acquired — scanned down, line `l` of `n` is the `(n − 1 − l)`-th in time, so a
//!   direct frame's time stamps decrease with `l` (its lines step −y in time) and a counter
//!   frame's increase (+y). A counter frame scanned down is still the direct one's counter
//!   scan: both its fast and its slow direction are reversed. A frame whose
//!   `Scan.FrameDataGrab` direction is not the one started (a bouncy scan left on, a start by
//!   someone else) acquired its lines in the other order in time: not the scan requested,
//!   an error.
//! - **`Scan.PropsSet`'s module list** is sent as the vendor's client sends it (the string
//!   array's size field `4 × count`; see [`codec`] for the choice).
//! - **Frame data** (`Scan.FrameDataGrab`) come top line first whatever the slow direction
//!   (for an upward scan the last line acquired, for a downward one the first) and left to
//!   right in the frame for both trace directions; pixels not acquired are NaN, which is an
//!   error, never data. The row order of a *downward* frame is nanonis-sim's convention (the
//!   frame as displayed; the reply's direction flag says which way it was scanned): the
//!   vendor's client documents the flag, not the order, and it has not been checked on a
//!   controller. Were the rows in acquisition order there, every downward frame would come
//!   out mirrored in y; against nanonis-sim so mirrored, the calibration at 30° gave up its
//!   first node (no feature found; a mutation of this backend, not a test in the tree).
//! - **An interrupted run pauses the scan** ([`NanonisMicroscope::set_interrupt`]; spmcal
//!   sets the flag on SIGINT, SIGTERM and SIGHUP). A calibration otherwise stops between
//!   nodes, and a node takes minutes on hardware. With the flag set, the backend waits for
//!   the end of a scan in slices of [`INTERRUPT_POLL_S`] (after a slice that timed out,
//!   `Scan.StatusGet` tells an end between two slices from a scan still running) and, once
//!   the flag is up, sends `Scan.Action` *pause* and answers [`spm_hal::ErrorKind::Aborted`]:
//!   the run stops at once, marked aborted and resumable. Paused, not stopped: the tip stays
//!   engaged where it was, the feedback on, and the partial frame stays on the controller,
//!   where the user may look at it or resume it by hand. The frame is not resumed by the
//!   backend: its pixel times would straddle an unknown gap and the node's drift model would
//!   not hold across it. A backend opened on the controller — `spmcal calibrate --resume` —
//!   stops a paused (or running) frame before anything moves the tip, and the node is
//!   measured again. A wait on the host clock is cut short the same way.
//! - **The frame geometry is `float32` metres** on the wire (`Scan.FrameSet`), the move
//!   targets `float64`: a scan's pixel positions are realised to `float32` precision
//!   (relative 6·10⁻⁸, ≈ 0.002 counts at the edge of a 16-bit field).
//! - **A Z feedback that is off** when the backend opens is an error; an error reply naming
//!   the feedback maps to [`spm_hal::ErrorKind::FeedbackLost`] (transient).
//! - **A controller that stays unreachable** after the reconnect attempts is
//!   [`spm_hal::ErrorKind::Aborted`]: the calibration stops (and can be resumed) instead of
//!   giving up its remaining nodes one after another.
//! - **The coarse Z motor** is a capability found by query (`Motor.FreqAmpGet` on Z; the
//!   manual documents it for PD5, PMD4 and ANC150 controllers): with no motor module
//!   answering, [`spm_hal::Microscope::coarse_z`] is `None`. Positions are counted by the
//!   backend from where it was opened (`Motor.StepCounterGet` exists only for ANC150).
#![warn(missing_docs)]

pub mod client;
pub mod codec;
pub mod commands;
pub mod error;
pub mod microscope;

pub use client::{Client, ClientConfig};
pub use error::{NanonisError, NanonisErrorKind};
pub use microscope::{
    ClockSource, CoarseZConfig, ControllerState, INTERRUPT_POLL_S, LOW_VOLTAGE_SPAN_V,
    NanonisConfig, NanonisMicroscope, PIXEL_PACKET, REPLY_POLL, SlowDirection, metres_per_count,
};
