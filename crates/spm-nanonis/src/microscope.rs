//! [`NanonisMicroscope`]: spm-hal's [`Microscope`] over the Nanonis TCP protocol.
//!
//! See the crate documentation for the units convention and the pitfalls handled.

use crate::client::{Client, ClientConfig};
use crate::commands::{
    DriftComp, FrameData, Reply, Request, ScanBuffer, ScanFrame, ScanProps, ScanSpeed, Version,
    motor_direction, scan_action,
};
use crate::error::{NanonisError, NanonisErrorKind};
use serde::{Deserialize, Serialize};
use spm_hal::{
    Capabilities, CoarseZCapability, CoarseZStage, CountPoint, Counts, Frame, Microscope,
    MoveRequest, ScanDirection, ScanRequest, Seconds, TraceImage,
};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// The full span of the controller's low-voltage outputs, V (±10 V): `Piezo.CalibrGet`
/// gives metres per volt of these signals.
pub const LOW_VOLTAGE_SPAN_V: f64 = 20.0;

/// With an interrupt flag ([`NanonisMicroscope::set_interrupt`]), the longest the backend
/// waits on the controller (for the end of a scan) or sleeps (a wait on the host clock)
/// before it looks at the flag again, s.
pub const INTERRUPT_POLL_S: f64 = 0.2;

/// With a simulated controller ([`ClockSource::ControllerSignals`] with `virtual_time`), how
/// long each reply is polled for before the thread sleeps ([`Client::set_reply_poll`]).
pub const REPLY_POLL: std::time::Duration = std::time::Duration::from_micros(50);

/// Pixels per line travel from the real-time engine to the host in packets of this many:
/// the scan module coerces pixels per line to a multiple of it.
pub const PIXEL_PACKET: u32 = 16;

/// Where the instrument clock comes from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum ClockSource {
    /// The host's monotonic clock since the backend was opened; waits sleep on the host.
    /// The protocol has no clock command, so this is the choice for hardware.
    Host,
    /// The controller's own time, published as two signals read with `Signals.ValsGet`:
    /// whole seconds and the fraction (two `float32`s keep 0.1 µs resolution where one
    /// would lose it after a few minutes). Waits then run on the controller as
    /// `Scan.WaitEndOfScan` timeouts (whole milliseconds). `nanonis-sim` publishes its
    /// simulated time this way.
    ControllerSignals {
        /// Signal index of the whole seconds.
        whole_s_signal: i32,
        /// Signal index of the fraction of a second.
        fraction_s_signal: i32,
        /// The controller's time is virtual (a simulated controller such as `nanonis-sim`):
        /// it advances only while the controller executes a command, and reading the clock
        /// or the position (`FolMe.XYPosGet`) takes none of it. A reading of the clock then
        /// stays exact until the backend sends the controller anything else, and
        /// [`Microscope::now`] is answered from it (see the crate docs, "Round trips").
        /// `false` (the default): a clock that runs in real time, read at every `now`.
        #[serde(default)]
        virtual_time: bool,
    },
}

/// A software-drivable coarse Z motor.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CoarseZConfig {
    /// Smallest allowed position, steps from where the backend was opened.
    pub min_steps: i64,
    /// Largest allowed position, steps.
    pub max_steps: i64,
    /// `Motor.StartMove` direction that approaches the sample: "z+" or "z-".
    pub approach: String,
    /// Motor group (0 = group 1).
    pub group: u32,
    /// Upper bound of one step's duration, s (sets the command timeout).
    pub step_time_s: f64,
}

/// The slow-scan direction every frame is started in (`Scan.Action`'s direction).
///
/// Whichever it is, a [`Frame`] keeps spm-hal's geometry: the pixel of line `l`, pixel `k`
/// lies at [`ScanRequest::commanded_position`], and its time stamp is when the controller
/// acquired it. Scanned down, the lines of a direct frame are acquired from its last row
/// (the largest y in counts) to its first, so their time stamps decrease with `l`; a
/// counter frame (the frame turned by 180°) scanned down steps +y in counts instead of −y.
/// Direct and counter frames stay a counter pair: both the fast and the slow direction of
/// one are reversed in the other.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SlowDirection {
    /// From the frame's bottom line to its top (`Scan.Action` direction 1), the default.
    #[default]
    Up,
    /// From the frame's top line to its bottom (`Scan.Action` direction 0).
    Down,
}

impl<'de> Deserialize<'de> for SlowDirection {
    /// `"up"` or `"down"`; anything else is refused naming the field (a job's `[backend]` is
    /// read through an internally tagged enum, whose errors lose the field's path).
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let text = String::deserialize(deserializer)?;
        match text.as_str() {
            "up" => Ok(Self::Up),
            "down" => Ok(Self::Down),
            other => Err(serde::de::Error::custom(format!(
                "slow_direction {other:?} is neither \"up\" nor \"down\""
            ))),
        }
    }
}

impl SlowDirection {
    /// `Scan.Action`'s and `Scan.FrameDataGrab`'s direction flag: 1 = up, 0 = down.
    pub fn direction_up(self) -> u32 {
        match self {
            Self::Up => 1,
            Self::Down => 0,
        }
    }
}

/// Everything the backend needs to know about the controller and the job.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NanonisConfig {
    /// Controller host.
    pub host: String,
    /// Controller port (the first TCP programming-interface port).
    pub port: u16,
    /// Timeout of one connection attempt, s.
    pub connect_timeout_s: f64,
    /// Timeout of an ordinary command, s.
    pub command_timeout_s: f64,
    /// Margin added to wait-style commands' expected duration, s.
    pub wait_margin_s: f64,
    /// Reconnect attempts before the controller is declared unreachable.
    pub reconnect_attempts: u32,
    /// First backoff between reconnect attempts, s.
    pub reconnect_backoff_s: f64,
    /// Counts convention, lateral: one count is `20 V / 2^lateral_dac_bits` of the X/Y
    /// low-voltage outputs.
    pub lateral_dac_bits: u32,
    /// Counts convention, Z: one count is `20 V / 2^z_dac_bits` of the Z output.
    pub z_dac_bits: u32,
    /// Signal index (0–127) of the Z (topography) channel in the scan buffer.
    pub z_channel: i32,
    /// The instrument clock.
    pub clock: ClockSource,
    /// Largest pixels per line of one scan (rounded down to a multiple of 16).
    pub max_pixels_per_line: u32,
    /// Largest number of lines of one scan.
    pub max_lines: u32,
    /// Shortest pixel dwell, s.
    pub min_pixel_dwell_s: f64,
    /// The coarse Z motor, when software may drive it (its presence is still queried).
    pub coarse_z: Option<CoarseZConfig>,
    /// The frame angle of the counts convention, degrees, positive clockwise (the sense of
    /// `Scan.FrameSet`): the counts axes are the controller's X and Y turned by it, every
    /// scan frame is turned by it (counter scans by it + 180°), and the field is the
    /// largest square of the turned axes inside the controller's range. 0 by default.
    #[serde(default)]
    pub frame_angle_deg: f64,
    /// The slow-scan direction of every frame, `"up"` (the default) or `"down"`
    /// ([`SlowDirection`]): the order in time of the lines, never where the pixels lie.
    #[serde(default)]
    pub slow_direction: SlowDirection,
}

impl NanonisConfig {
    /// The connection part.
    pub fn client_config(&self) -> ClientConfig {
        ClientConfig {
            host: self.host.clone(),
            port: self.port,
            connect_timeout_s: self.connect_timeout_s,
            command_timeout_s: self.command_timeout_s,
            wait_margin_s: self.wait_margin_s,
            reconnect_attempts: self.reconnect_attempts,
            reconnect_backoff_s: self.reconnect_backoff_s,
        }
    }

    /// Checks every field; the message names it.
    pub fn validate(&self) -> Result<(), NanonisError> {
        let invalid = |field: &str, reason: String| {
            Err(NanonisError::new(
                NanonisErrorKind::Configuration,
                format!("backend.{field}: {reason}"),
            ))
        };
        self.client_config().validate()?;
        for (field, bits) in [
            ("lateral_dac_bits", self.lateral_dac_bits),
            ("z_dac_bits", self.z_dac_bits),
        ] {
            if !(8..=32).contains(&bits) {
                return invalid(field, format!("{bits} is outside [8, 32]"));
            }
        }
        if !(0..=127).contains(&self.z_channel) {
            return invalid(
                "z_channel",
                format!("{} is outside [0, 127]", self.z_channel),
            );
        }
        if let ClockSource::ControllerSignals {
            whole_s_signal,
            fraction_s_signal,
            ..
        } = self.clock
        {
            for s in [whole_s_signal, fraction_s_signal] {
                if !(0..=127).contains(&s) {
                    return invalid("clock", format!("signal {s} is outside [0, 127]"));
                }
            }
        }
        if self.max_pixels_per_line < PIXEL_PACKET || self.max_lines == 0 {
            return invalid(
                "max_pixels_per_line",
                "needs at least 16 pixels and 1 line".into(),
            );
        }
        if !(self.min_pixel_dwell_s.is_finite() && self.min_pixel_dwell_s > 0.0) {
            return invalid("min_pixel_dwell_s", "must be a finite time > 0".into());
        }
        if !(self.frame_angle_deg.is_finite() && self.frame_angle_deg.abs() <= 360.0) {
            return invalid(
                "frame_angle_deg",
                format!(
                    "{} is not an angle in [-360, 360] degrees",
                    self.frame_angle_deg
                ),
            );
        }
        if let Some(c) = &self.coarse_z {
            if c.min_steps > 0 || c.max_steps < 0 {
                return invalid("coarse_z", "[min_steps, max_steps] must contain 0".into());
            }
            if c.approach != "z+" && c.approach != "z-" {
                return invalid(
                    "coarse_z.approach",
                    format!("{:?} is not \"z+\" or \"z-\"", c.approach),
                );
            }
            if c.group > 5 {
                return invalid("coarse_z.group", format!("{} is outside [0, 5]", c.group));
            }
            if !(c.step_time_s.is_finite() && c.step_time_s > 0.0) {
                return invalid("coarse_z.step_time_s", "must be a finite time > 0".into());
            }
        }
        Ok(())
    }

    /// The capabilities this configuration gives (the coarse stage as configured; the
    /// backend drops it when the controller has no motor module).
    pub fn capabilities(&self) -> Capabilities {
        // A square of the turned axes inside the controller's square range: its half side
        // is the range's over |cos| + |sin| (1 for multiples of 90°).
        let (sin, cos) = self.frame_angle_deg.to_radians().sin_cos();
        let shrink = cos.abs() + sin.abs();
        let shrink = if (shrink - 1.0).abs() < 1e-12 {
            1.0
        } else {
            shrink
        };
        let half = (2f64.powi(self.lateral_dac_bits as i32 - 1) / shrink).floor();
        let z_half = 2f64.powi(self.z_dac_bits as i32 - 1);
        Capabilities {
            field_min: CountPoint::from_counts(-half, -half),
            field_max: CountPoint::from_counts(half - 1.0, half - 1.0),
            z_min: Counts(-z_half),
            z_max: Counts(z_half - 1.0),
            lateral_resolution: Counts(1.0),
            max_pixels_per_line: self.max_pixels_per_line / PIXEL_PACKET * PIXEL_PACKET,
            pixels_per_line_multiple: PIXEL_PACKET,
            max_lines: self.max_lines,
            min_pixel_dwell: Seconds(self.min_pixel_dwell_s),
            counter_scan: true,
            backward_trace: true,
            coarse_z: self.coarse_z.as_ref().map(|c| CoarseZCapability {
                min_steps: c.min_steps,
                max_steps: c.max_steps,
            }),
        }
    }
}

/// Metres per count from a low-voltage calibration (m/V) and a DAC width.
pub fn metres_per_count(calibration_m_per_v: f64, bits: u32) -> f64 {
    calibration_m_per_v * LOW_VOLTAGE_SPAN_V / 2f64.powi(bits as i32)
}

/// The controller's state as found and as set when the backend was opened: recorded with
/// the run, because a calibration on coordinates the controller already corrects is a
/// calibration of the correction.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ControllerState {
    /// Product line.
    pub product_line: String,
    /// Software version.
    pub version: String,
    /// Host-application release.
    pub host_release: u32,
    /// RT-engine release.
    pub rt_release: u32,
    /// `Piezo.CalibrGet`, m/V (X, Y, Z).
    pub calibration_m_per_v: [f64; 3],
    /// `Piezo.RangeGet`, m (X, Y, Z).
    pub range_m: [f64; 3],
    /// Metres per count (X, Y, Z) by the counts convention.
    pub metres_per_count: [f64; 3],
    /// Drift compensation found: on (1) / off (0) and its speeds, m/s.
    pub drift_compensation_found: (u32, [f64; 3]),
    /// Tilt correction found, degrees (X, Y).
    pub tilt_found_deg: [f64; 2],
    /// Hysteresis compensation found: 1 = on.
    pub hysteresis_compensation_found: u32,
    /// After setting: drift compensation status (0 = off).
    pub drift_compensation_now: u32,
    /// After setting: tilt, degrees.
    pub tilt_now_deg: [f64; 2],
    /// After setting: hysteresis compensation (0 = off).
    pub hysteresis_compensation_now: u32,
    /// Continuous and bouncy scanning were switched off, autosave and autopaste off.
    pub scan_props_set: bool,
    /// The Z controller was on.
    pub z_feedback_on: bool,
    /// A coarse Z motor answered the query.
    pub coarse_motor_present: bool,
}

/// Scan settings last sent, to skip unchanged ones (cleared on reconnection).
#[derive(Clone, Debug, Default, PartialEq)]
struct SentSettings {
    buffer: Option<(i32, i32)>,
    frame: Option<[u32; 5]>,
    speed: Option<ScanSpeed>,
    line_times_s: Option<(f64, f64)>,
    folme_speed: Option<u32>,
    reconnects: u64,
}

/// The Nanonis backend.
#[derive(Debug)]
pub struct NanonisMicroscope {
    client: Client,
    config: NanonisConfig,
    capabilities: Capabilities,
    /// Metres per count, X and Y.
    lateral_m_per_count: [f64; 2],
    /// Metres per Z count.
    z_m_per_count: f64,
    state: ControllerState,
    epoch: Instant,
    coarse_steps: i64,
    sent: SentSettings,
    /// What the whole-millisecond controller waits owe the requested ones, s.
    wait_carry_s: f64,
    /// The compensation as found when connecting, put back by
    /// [`NanonisMicroscope::restore_compensation`] (or on drop); `None` once restored.
    found_compensation: Option<FoundCompensation>,
    /// Set by whoever interrupts the run ([`NanonisMicroscope::set_interrupt`]).
    interrupt: Option<Arc<AtomicBool>>,
    /// The clock and position as last read or commanded, while the controller has received
    /// nothing else since.
    readings: Readings,
    /// No scan is running on the controller: known since `Scan.StatusGet` said so or a scan
    /// of the backend's ended normally, with nothing since that could have started or left
    /// one (no reconnection, no failed call, no interruption). `Some(reconnects)` holds the
    /// client's [`Client::reconnects`] when it became known; `None`: unknown, asked before
    /// the next scan (see the crate docs, "Round trips").
    scan_idle: Option<u64>,
    /// Where the tip may be after the backend's last scan, counts (x from, x to, y from, y
    /// to: the scanned raster with a margin), until the position is next read from the
    /// controller or the backend moves the tip: a reading outside it means another client
    /// moved the tip ([`NanonisMicroscope::check_tip_after_scan`]).
    after_scan: Option<[f64; 4]>,
}

/// What the backend knows of the controller without asking, valid while the client's
/// [`Client::sequence`] is the one recorded (the controller received nothing from the
/// backend since): see the crate docs, "Round trips".
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Readings {
    /// [`Client::sequence`] when they were taken or set.
    sequence: u64,
    /// The controller's virtual clock, s (kept only for [`ClockSource::ControllerSignals`]
    /// with `virtual_time`).
    clock_s: Option<f64>,
    /// The commanded position, counts: read (`FolMe.XYPosGet`) or the target of the move
    /// that put it there.
    position: Option<CountPoint>,
}

impl Readings {
    /// Nothing known, as of `sequence`.
    fn none(sequence: u64) -> Self {
        Self {
            sequence,
            clock_s: None,
            position: None,
        }
    }
}

/// The controller's own compensation as the backend found it.
#[derive(Debug, Clone, Copy)]
struct FoundCompensation {
    drift: DriftComp,
    tilt_deg: [f32; 2],
    hysteresis: u32,
}

fn f32_of(x: f64) -> f32 {
    x as f32
}

impl NanonisMicroscope {
    /// Puts the controller's own drift, tilt and hysteresis compensation back as they were
    /// found when connecting (they are switched off for the calibration, which must see
    /// uncorrected coordinates). Called when the run and its validation images are done;
    /// dropping the backend does it too, as a fallback. Scan properties (continuous and
    /// bouncy scanning, autosave) are not restored: the controller does not report them
    /// through the commands the backend uses.
    ///
    /// # Errors
    /// The controller's error; the compensation then stays off, which the error says.
    pub fn restore_compensation(&mut self) -> Result<(), NanonisError> {
        let Some(found) = self.found_compensation else {
            return Ok(());
        };
        self.client.call(&Request::PiezoDriftCompSet {
            on_off: if found.drift.status == 1 { 1 } else { 2 },
            v_m_per_s: found.drift.v_m_per_s,
            saturation_limit_percent: found.drift.saturation_limit_percent,
        })?;
        self.client.call(&Request::PiezoTiltSet {
            x_deg: found.tilt_deg[0],
            y_deg: found.tilt_deg[1],
        })?;
        self.client
            .call(&Request::PiezoHystOnOffSet(found.hysteresis))?;
        self.found_compensation = None;
        tracing::info!(
            drift = found.drift.status,
            tilt_deg = ?found.tilt_deg,
            hysteresis = found.hysteresis,
            "nanonis: the controller's compensation restored as found"
        );
        Ok(())
    }

    /// Connects, reads the calibration, puts the controller into a known state (drift,
    /// tilt and hysteresis compensation off; continuous and bouncy scanning, autosave and
    /// autopaste off), checks the Z feedback and queries the coarse motor.
    pub fn connect(config: NanonisConfig) -> Result<Self, NanonisError> {
        config.validate()?;
        let mut client = Client::connect(config.client_config())?;
        let version = client.version().cloned().unwrap_or(Version {
            product_line: String::new(),
            version: String::new(),
            host_release: 0,
            rt_release: 0,
        });
        let calibration = match client.call(&Request::PiezoCalibrGet)? {
            Reply::F32x3(v) => v.map(f64::from),
            other => return Err(unexpected("Piezo.CalibrGet", &other)),
        };
        if !calibration.iter().all(|c| c.is_finite() && *c > 0.0) {
            return Err(NanonisError::new(
                NanonisErrorKind::Configuration,
                format!("the piezo calibration {calibration:?} m/V is not positive and finite"),
            )
            .in_command("Piezo.CalibrGet"));
        }
        let range = match client.call(&Request::PiezoRangeGet)? {
            Reply::F32x3(v) => v.map(f64::from),
            other => return Err(unexpected("Piezo.RangeGet", &other)),
        };
        for (axis, (c, r)) in calibration.iter().zip(range).enumerate() {
            let expected = c * LOW_VOLTAGE_SPAN_V;
            if (r - expected).abs() > 0.01 * expected {
                tracing::warn!(
                    axis,
                    range_m = r,
                    calibration_times_20v_m = expected,
                    "nanonis: piezo range differs from calibration × 20 V (HV gain?)"
                );
            }
        }
        // Compensation to a known state.
        let found_drift = match client.call(&Request::PiezoDriftCompGet)? {
            Reply::DriftComp(d) => d,
            other => return Err(unexpected("Piezo.DriftCompGet", &other)),
        };
        let found_tilt = f32x2(&mut client, &Request::PiezoTiltGet)?;
        let found_hyst = u32_reply(&mut client, &Request::PiezoHystOnOffGet)?;
        client.call(&Request::PiezoDriftCompSet {
            on_off: 2,
            v_m_per_s: [0.0; 3],
            saturation_limit_percent: found_drift.saturation_limit_percent,
        })?;
        client.call(&Request::PiezoTiltSet {
            x_deg: 0.0,
            y_deg: 0.0,
        })?;
        client.call(&Request::PiezoHystOnOffSet(0))?;
        let now_drift: DriftComp = match client.call(&Request::PiezoDriftCompGet)? {
            Reply::DriftComp(d) => d,
            other => return Err(unexpected("Piezo.DriftCompGet", &other)),
        };
        let now_tilt = f32x2(&mut client, &Request::PiezoTiltGet)?;
        let now_hyst = u32_reply(&mut client, &Request::PiezoHystOnOffGet)?;
        if now_drift.status != 0 || now_tilt != [0.0, 0.0] || now_hyst != 0 {
            return Err(NanonisError::new(
                NanonisErrorKind::Configuration,
                format!(
                    "the controller's own compensation did not switch off (drift {}, tilt \
                     {now_tilt:?}°, hysteresis {now_hyst}): a calibration on corrected \
                     coordinates would calibrate the correction",
                    now_drift.status
                ),
            ));
        }
        let z_on = one_frame_at_a_time_with_feedback(&mut client)?;
        let coarse_motor_present = match &config.coarse_z {
            Some(_) => match client.call(&Request::MotorFreqAmpGet(3)) {
                Ok(_) => true,
                Err(e) if e.kind == NanonisErrorKind::Controller => {
                    tracing::info!(error = %e, "nanonis: no coarse motor answers; coarse Z off");
                    false
                }
                Err(e) => return Err(e),
            },
            None => false,
        };
        let mut capabilities = config.capabilities();
        if !coarse_motor_present {
            capabilities.coarse_z = None;
        }
        let lateral = [
            metres_per_count(calibration[0], config.lateral_dac_bits),
            metres_per_count(calibration[1], config.lateral_dac_bits),
        ];
        let z = metres_per_count(calibration[2], config.z_dac_bits);
        let state = ControllerState {
            product_line: version.product_line.clone(),
            version: version.version.clone(),
            host_release: version.host_release,
            rt_release: version.rt_release,
            calibration_m_per_v: calibration,
            range_m: range,
            metres_per_count: [lateral[0], lateral[1], z],
            drift_compensation_found: (found_drift.status, found_drift.v_m_per_s.map(f64::from)),
            tilt_found_deg: found_tilt.map(f64::from),
            hysteresis_compensation_found: found_hyst,
            drift_compensation_now: now_drift.status,
            tilt_now_deg: now_tilt.map(f64::from),
            hysteresis_compensation_now: now_hyst,
            scan_props_set: true,
            z_feedback_on: z_on,
            coarse_motor_present,
        };
        tracing::info!(?state, "nanonis: controller state recorded");
        let reconnects = client.reconnects();
        let mut opened = Self {
            client,
            capabilities,
            lateral_m_per_count: lateral,
            z_m_per_count: z,
            state,
            epoch: Instant::now(),
            coarse_steps: 0,
            wait_carry_s: 0.0,
            found_compensation: Some(FoundCompensation {
                drift: found_drift,
                tilt_deg: found_tilt,
                hysteresis: found_hyst,
            }),
            sent: SentSettings {
                reconnects,
                ..SentSettings::default()
            },
            config,
            interrupt: None,
            readings: Readings::default(),
            scan_idle: None,
            after_scan: None,
        };
        if opened.pipelining() {
            opened.client.set_reply_poll(REPLY_POLL);
        }
        // A scan left paused by an interrupted run (or running, by a user) is stopped before
        // anything moves the tip: its frame is not resumed (see the crate docs).
        opened.stop_running_scan()?;
        Ok(opened)
    }

    /// Makes a run interruptible while the controller works: once `flag` is set (spmcal sets
    /// it on a termination signal), a running scan is paused on the controller
    /// (`Scan.Action` pause) and the scan, or a wait on the host clock, returns
    /// [`NanonisErrorKind::Aborted`] within [`INTERRUPT_POLL_S`], so the calibration stops at
    /// once (resumable) instead of at the end of the node. The paused frame is left on the
    /// controller for the user to look at or resume by hand; the next backend opened on the
    /// controller (`spmcal calibrate --resume`) stops it and the node is measured again.
    pub fn set_interrupt(&mut self, flag: Arc<AtomicBool>) {
        // The reconnect loop ends at the flag too (issue 25 item 12).
        self.client.set_interrupt(Arc::clone(&flag));
        self.interrupt = Some(flag);
    }

    fn interrupted(&self) -> bool {
        self.interrupt
            .as_ref()
            .is_some_and(|flag| flag.load(Ordering::SeqCst))
    }

    /// Pauses the scan running after an interrupt and says so as an `Aborted` error.
    fn pause_interrupted_scan(&mut self) -> NanonisError {
        let direction_up = self.config.slow_direction.direction_up();
        let paused = self.client.call(&Request::ScanAction {
            action: scan_action::PAUSE,
            direction_up,
        });
        let message = match paused {
            Ok(_) => {
                tracing::warn!("nanonis: interrupted; the scan is paused on the controller");
                "interrupted: the scan is paused on the controller (a resumed run stops it \
                 and measures the node again)"
                    .to_owned()
            }
            Err(e) => {
                tracing::error!(error = %e, "nanonis: interrupted; the scan could not be paused");
                format!("interrupted: the scan could not be paused ({e})")
            }
        };
        NanonisError::new(NanonisErrorKind::Aborted, message).in_command("Scan.Action")
    }

    /// Waits for the end of the scan just started, which takes `expected_s`: one
    /// `Scan.WaitEndOfScan` with the margin; with an interrupt flag, slices of at most
    /// [`INTERRUPT_POLL_S`] with the flag looked at between them (and `Scan.StatusGet`
    /// after a slice that timed out: an end of scan between two slices is not waited for
    /// again). Returns whether the scan ended within the margin.
    fn wait_end_of_scan(&mut self, expected_s: f64) -> Result<bool, NanonisError> {
        let total_ms = self.end_of_scan_timeout_ms(expected_s);
        if self.interrupt.is_none() {
            let request = Request::ScanWaitEndOfScan {
                timeout_ms: total_ms,
            };
            return match self.client.call_waiting(&request, expected_s)? {
                Reply::WaitEndOfScan { timed_out, .. } => Ok(timed_out != 1),
                other => Err(unexpected("Scan.WaitEndOfScan", &other)),
            };
        }
        self.sliced_wait_end_of_scan(total_ms, 0)
    }

    /// The interruptible wait for the end of a scan: slices of at most [`INTERRUPT_POLL_S`]
    /// up to `total_ms`, from `waited_ms` on (when > 0, slices that timed out have been
    /// waited already), with the flag looked at between them and `Scan.StatusGet` after each
    /// slice that timed out.
    fn sliced_wait_end_of_scan(
        &mut self,
        total_ms: i32,
        mut waited_ms: i32,
    ) -> Result<bool, NanonisError> {
        loop {
            if waited_ms > 0 {
                // After a slice that timed out: an end between two slices is not waited for.
                if self.interrupted() {
                    return Err(self.pause_interrupted_scan());
                }
                if u32_reply(&mut self.client, &Request::ScanStatusGet)? == 0 {
                    return Ok(true);
                }
            }
            if self.interrupted() {
                return Err(self.pause_interrupted_scan());
            }
            if waited_ms >= total_ms {
                return Ok(false);
            }
            let timeout_ms = slice_ms().min(total_ms - waited_ms);
            let request = Request::ScanWaitEndOfScan { timeout_ms };
            match self
                .client
                .call_waiting(&request, f64::from(timeout_ms) * 1e-3)?
            {
                Reply::WaitEndOfScan { timed_out, .. } if timed_out != 1 => return Ok(true),
                Reply::WaitEndOfScan { .. } => {}
                other => return Err(unexpected("Scan.WaitEndOfScan", &other)),
            }
            waited_ms = waited_ms.saturating_add(timeout_ms);
        }
    }

    /// `Scan.WaitEndOfScan`'s timeout for a scan that takes `expected_s`: that and the wait
    /// margin, whole milliseconds.
    fn end_of_scan_timeout_ms(&self, expected_s: f64) -> i32 {
        ((expected_s + self.config.wait_margin_s) * 1e3)
            .ceil()
            .min(f64::from(i32::MAX)) as i32
    }

    /// The controller's state found and set when the backend was opened.
    pub fn controller_state(&self) -> &ControllerState {
        &self.state
    }

    /// The client (statistics: commands sent, reconnects).
    pub fn client(&self) -> &Client {
        &self.client
    }

    /// Stops a running scan, a Follow-Me move and the coarse motor, on the second
    /// connection (so it works while the main one is blocked).
    pub fn abort(&mut self) -> Result<(), NanonisError> {
        self.scan_idle = None;
        self.client.stop(&Request::ScanAction {
            action: scan_action::STOP,
            direction_up: 1,
        })?;
        self.client.stop(&Request::FolMeStop)?;
        if self.state.coarse_motor_present {
            self.client.stop(&Request::MotorStopMove)?;
        }
        Ok(())
    }

    /// The controller's X and Y, m, of a point in counts: scaled by the counts convention,
    /// then turned clockwise by the frame angle.
    fn to_metres(&self, p: CountPoint) -> (f64, f64) {
        let (x, y) = (
            p.x.value() * self.lateral_m_per_count[0],
            p.y.value() * self.lateral_m_per_count[1],
        );
        if self.config.frame_angle_deg == 0.0 {
            return (x, y);
        }
        let (s, c) = self.config.frame_angle_deg.to_radians().sin_cos();
        (c * x + s * y, -s * x + c * y)
    }

    /// The point in counts of the controller's X and Y, m (the inverse of `to_metres`).
    fn counts_of_metres(&self, x_m: f64, y_m: f64) -> CountPoint {
        let (x, y) = if self.config.frame_angle_deg == 0.0 {
            (x_m, y_m)
        } else {
            let (s, c) = self.config.frame_angle_deg.to_radians().sin_cos();
            (c * x_m - s * y_m, s * x_m + c * y_m)
        };
        CountPoint::from_counts(
            x / self.lateral_m_per_count[0],
            y / self.lateral_m_per_count[1],
        )
    }

    fn invalidate_on_reconnect(&mut self) {
        if self.client.reconnects() != self.sent.reconnects {
            self.sent = SentSettings {
                reconnects: self.client.reconnects(),
                ..SentSettings::default()
            };
        }
    }

    /// A wait on the controller (controller clock) or on the host.
    fn pause(&mut self, duration_s: f64) -> Result<(), NanonisError> {
        match self.config.clock {
            ClockSource::Host => {
                // In slices when interruptible, so that an interrupt ends a long pause.
                let mut left_s = duration_s;
                while left_s > 0.0 {
                    if self.interrupted() {
                        return Err(NanonisError::new(
                            NanonisErrorKind::Aborted,
                            "interrupted during a wait",
                        ));
                    }
                    let slice_s = if self.interrupt.is_some() {
                        left_s.min(INTERRUPT_POLL_S)
                    } else {
                        left_s
                    };
                    std::thread::sleep(std::time::Duration::from_secs_f64(slice_s));
                    left_s -= slice_s;
                }
                Ok(())
            }
            ClockSource::ControllerSignals { .. } => {
                let request = self.controller_wait(duration_s)?;
                self.client.call_waiting(&request, duration_s)?;
                Ok(())
            }
        }
    }

    /// A wait on the controller: `Scan.WaitEndOfScan` with no scan to end, timing out after
    /// `duration_s` in whole milliseconds (the command's `int`), the remainder carried to the
    /// next wait: the controller's clock never runs more than ½ ms from the sum of the
    /// requested waits.
    fn controller_wait(&mut self, duration_s: f64) -> Result<Request, NanonisError> {
        let owed = duration_s + self.wait_carry_s;
        let ms = (owed * 1e3).round().max(0.0);
        if ms > f64::from(i32::MAX) {
            return Err(NanonisError::new(
                NanonisErrorKind::InvalidRequest,
                format!("a wait of {duration_s} s is longer than the protocol's timeout"),
            ));
        }
        self.wait_carry_s = owed - ms * 1e-3;
        Ok(Request::ScanWaitEndOfScan {
            timeout_ms: ms as i32,
        })
    }

    fn check_inside(&self, p: CountPoint, what: &str) -> Result<(), NanonisError> {
        let c = &self.capabilities;
        if !p.is_finite() {
            return Err(NanonisError::new(
                NanonisErrorKind::InvalidRequest,
                format!("{what} is not finite"),
            ));
        }
        if p.x < c.field_min.x || p.y < c.field_min.y || p.x > c.field_max.x || p.y > c.field_max.y
        {
            return Err(NanonisError::new(
                NanonisErrorKind::OutOfRange,
                format!(
                    "{what} ({}, {}) counts is outside the field",
                    p.x.value(),
                    p.y.value()
                ),
            ));
        }
        Ok(())
    }

    /// Makes sure no scan is running: a scan left running (by a user, an earlier client or
    /// a lost connection) is stopped on the second connection. Asks the controller
    /// (`Scan.StatusGet`) unless no scan is known to run ([`Self::scan_idle_known`]).
    fn stop_running_scan(&mut self) -> Result<(), NanonisError> {
        if self.scan_idle_known() {
            return Ok(());
        }
        for _ in 0..5 {
            if u32_reply(&mut self.client, &Request::ScanStatusGet)? == 0 {
                self.scan_idle = Some(self.client.reconnects());
                return Ok(());
            }
            tracing::warn!("nanonis: a scan is already running; stopping it");
            self.client.stop(&Request::ScanAction {
                action: scan_action::STOP,
                direction_up: 1,
            })?;
        }
        Err(NanonisError::new(
            NanonisErrorKind::Controller,
            "a scan keeps running after 5 stop requests",
        )
        .in_command("Scan.StatusGet"))
    }

    /// Whether no scan is known to run on the controller: one of the backend's scans ended
    /// normally (or `Scan.StatusGet` said so) and no connection has been opened since (a
    /// lost connection may have left a scan running); a failed call or an interruption
    /// forgets it ([`Self::noting_failure`]).
    fn scan_idle_known(&self) -> bool {
        self.client.is_connected() && self.scan_idle == Some(self.client.reconnects())
    }

    /// A call's result, with what a failure makes unknown forgotten: whether a scan runs
    /// (a scan may have been left running or paused, a stop may have failed).
    fn noting_failure<T>(&mut self, result: Result<T, NanonisError>) -> Result<T, NanonisError> {
        if result.is_err() {
            self.scan_idle = None;
        }
        result
    }

    /// Sends the scan buffer, frame and speed that differ from those last sent, with the
    /// read-backs of buffer and speed (pitfalls: pixels coerced to multiples of 16, speeds
    /// coerced by the controller).
    fn set_up_scan(
        &mut self,
        n16: i32,
        lines: i32,
        frame: ScanFrame,
        speed: ScanSpeed,
    ) -> Result<(), NanonisError> {
        if self.sent.buffer != Some((n16, lines)) {
            // Pitfall: read back what the controller made of it (pipelined).
            let set = Request::ScanBufferSet(ScanBuffer {
                channels: vec![self.config.z_channel],
                pixels: n16,
                lines,
            });
            let mut replies = self
                .call_then_read(&set, None, &[Request::ScanBufferGet])?
                .into_iter()
                .skip(1);
            if let Err(e) = checked_buffer(replies.next(), (n16, lines)) {
                self.sent.buffer = None;
                return Err(e);
            }
            self.sent.buffer = Some((n16, lines));
        }
        let frame_bits = frame_bits(&frame);
        if self.sent.frame != Some(frame_bits) {
            self.client.call(&Request::ScanFrameSet(frame))?;
            self.sent.frame = Some(frame_bits);
        }
        if self.sent.speed != Some(speed) {
            // Pitfall: the controller may coerce the speed; time the pixels by what it uses
            // (read back, pipelined).
            let mut replies = self
                .call_then_read(
                    &Request::ScanSpeedSet(speed),
                    None,
                    &[Request::ScanSpeedGet],
                )?
                .into_iter()
                .skip(1);
            let (tf, tb) = checked_line_times(replies.next())?;
            self.sent.speed = Some(speed);
            self.sent.line_times_s = Some((tf, tb));
        }
        Ok(())
    }

    /// Starts a scan on a controller running none, set up for it: the set-up again when a
    /// connection was opened during it (a lost one: the controller the new one meets may run
    /// a scan and hold other settings), and the start not sent again on a new connection
    /// before `Scan.StatusGet` has been asked there.
    fn start_scan(
        &mut self,
        n16: i32,
        lines: i32,
        frame: ScanFrame,
        speed: ScanSpeed,
        direction_up: u32,
    ) -> Result<(), NanonisError> {
        let mut last = None;
        for _ in 0..=crate::client::RETRIES {
            let reconnects = self.client.reconnects();
            self.invalidate_on_reconnect();
            self.stop_running_scan()?;
            self.set_up_scan(n16, lines, frame, speed)?;
            if self.client.reconnects() != reconnects {
                continue;
            }
            // From the start until its normal end a scan may be running.
            self.scan_idle = None;
            match self.client.call_on_one_connection(&Request::ScanAction {
                action: scan_action::START,
                direction_up,
            }) {
                Ok(_) => return Ok(()),
                Err(e) if !self.client.is_connected() && e.kind != NanonisErrorKind::Aborted => {
                    tracing::debug!(error = %e, "nanonis: connection lost at the scan's start");
                    last = Some(e);
                }
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| {
            NanonisError::new(
                NanonisErrorKind::Io,
                "the connection was reopened during every set-up of the scan",
            )
            .in_command("Scan.Action")
        }))
    }

    /// The controller's frame and speed for `request` (checked against the capabilities and
    /// the field): pixels per line coerced to a multiple of 16 (oversampled and binned, or
    /// padded and cropped: [`ScanPlan::bin`]), the frame turned for counter scans and by the
    /// counts convention's frame angle.
    fn plan_scan(&self, request: &ScanRequest) -> Result<ScanPlan, NanonisError> {
        request
            .validate()
            .map_err(|e| NanonisError::new(NanonisErrorKind::InvalidRequest, e.to_string()))?;
        let caps = &self.capabilities;
        let n = request.pixels_per_line;
        let lines = request.lines;
        // Pitfall: pixels per line are coerced to a multiple of 16.
        let n16 = caps.acquired_pixels_per_line(n);
        if n16 > caps.max_pixels_per_line || lines > caps.max_lines {
            return Err(NanonisError::new(
                NanonisErrorKind::OutOfRange,
                format!(
                    "{n} (scanned as {n16}) × {lines} pixels exceed the maximum {} × {}",
                    caps.max_pixels_per_line, caps.max_lines
                ),
            ));
        }
        if request.pixel_dwell < caps.min_pixel_dwell {
            return Err(NanonisError::new(
                NanonisErrorKind::OutOfRange,
                format!(
                    "pixel dwell {} is below the minimum {}",
                    request.pixel_dwell, caps.min_pixel_dwell
                ),
            ));
        }
        // A count dividing the multiple (4 of 16): the request's own frame and line time,
        // oversampled (`bin` samples per requested pixel, each a `bin`-th of its dwell) —
        // unless those samples would be shorter than the controller allows. Otherwise the
        // next multiple with the same pixel step, the extra pixels continuing the forward
        // trace past the requested ones, cropped (the lines longer by the padding).
        let bin = n16 / n;
        let bin = if caps.honours_pixels_per_line(n)
            && request.pixel_dwell.value() / f64::from(bin) >= caps.min_pixel_dwell.value()
        {
            bin
        } else {
            1
        };
        let step = request.pixel_step.value();
        let sample_step = step / f64::from(bin);
        let (far_x, _) = request.far_corner();
        // The raster's sample centres in counts: x range (the samples of a binned line fill
        // the requested pixels' cells; a padded one runs past the requested pixels).
        let pad = f64::from(n16 - n * bin) * sample_step;
        let inset = 0.5 * (step - sample_step);
        let (x_lo, x_hi) = match request.direction {
            ScanDirection::Direct => (
                request.origin.x.value() - inset,
                far_x.value() + inset + pad,
            ),
            ScanDirection::Counter => (
                request.origin.x.value() - inset - pad,
                far_x.value() + inset,
            ),
        };
        let (_, far_y) = request.far_corner();
        for (x, y) in [(x_lo, request.origin.y.value()), (x_hi, far_y.value())] {
            self.check_inside(
                CountPoint::from_counts(x, y),
                "the scan raster (its lines coerced to a multiple of 16 pixels)",
            )?;
        }
        // Frame: pixels are cell-centred, pixel i of a line at left + (i + ½)·width/pixels.
        let centre_counts = CountPoint::from_counts(
            0.5 * (x_lo + x_hi),
            0.5 * (request.origin.y.value() + far_y.value()),
        );
        let (cx, cy) = self.to_metres(centre_counts);
        let width_m = f64::from(n16) * sample_step * self.lateral_m_per_count[0];
        let height_m = f64::from(lines) * step * self.lateral_m_per_count[1];
        // Counter scans: the frame turned by 180°, so its +x runs along −x and its "up"
        // along −y.
        // Both turned further by the frame angle of the counts convention.
        let turned = self.config.frame_angle_deg
            + match request.direction {
                ScanDirection::Direct => 0.0,
                ScanDirection::Counter => 180.0,
            };
        // In (−180°, 180°].
        let angle_deg = if turned > 180.0 {
            turned - 360.0
        } else if turned <= -180.0 {
            turned + 360.0
        } else {
            turned
        } as f32;
        let line_s = f64::from(n16 / bin) * request.pixel_dwell.value();
        Ok(ScanPlan {
            raster_counts: [
                x_lo,
                x_hi,
                request.origin.y.value().min(far_y.value()),
                request.origin.y.value().max(far_y.value()),
            ],
            n16,
            bin,
            frame: ScanFrame {
                centre_x_m: f32_of(cx),
                centre_y_m: f32_of(cy),
                width_m: f32_of(width_m),
                height_m: f32_of(height_m),
                angle_deg,
            },
            speed: ScanSpeed {
                forward_speed_m_per_s: f32_of(width_m / line_s),
                backward_speed_m_per_s: f32_of(width_m / line_s),
                forward_line_s: f32_of(line_s),
                backward_line_s: f32_of(line_s),
                keep: 2,
                speed_ratio: 1.0,
            },
            line_s,
        })
    }

    /// The end of the scan started (`expected_s` long) and its data as
    /// [`Self::end_of_scan`] found them: a scan that failed or did not end is stopped (an
    /// interrupted one is left paused).
    fn finish_scan(
        &mut self,
        ended: Result<Option<ScanEnd>, NanonisError>,
        expected_s: f64,
    ) -> Result<ScanEnd, NanonisError> {
        let ended = match ended {
            Ok(ended) => ended,
            // Interrupted: the scan is paused, not stopped.
            Err(e) if e.kind == NanonisErrorKind::Aborted => return Err(e),
            Err(e) => {
                if let Err(stop) = self.abort() {
                    tracing::warn!(error = %stop, "nanonis: could not stop the scan");
                }
                return Err(e);
            }
        };
        ended.ok_or_else(|| {
            if let Err(stop) = self.abort() {
                tracing::warn!(error = %stop, "nanonis: could not stop the scan");
            }
            NanonisError::new(
                NanonisErrorKind::Timeout,
                format!(
                    "no end of scan within {:.0} ms",
                    (expected_s + self.config.wait_margin_s) * 1e3
                ),
            )
            .in_command("Scan.WaitEndOfScan")
        })
    }

    /// spm-hal's frame from the grabbed data: the requested pixels of each line (the
    /// padding cropped, or each the mean of its `bin` samples: [`ScanPlan::bin`]), rows in
    /// spm-hal's geometry, each pixel timed from the scan's start `start_s` with the line
    /// times (forward, backward) `(tf, tb)`.
    fn assemble_frame(
        &self,
        request: &ScanRequest,
        (end, (n16, bin), direction_up, want_backward): (&ScanEnd, (u32, u32), u32, bool),
        (start_s, tf, tb): (f64, f64, f64),
    ) -> Result<Frame, NanonisError> {
        let (forward, backward) = (&end.forward, end.backward.as_ref());
        let n = request.pixels_per_line as usize;
        let n16u = n16 as usize;
        let bin = bin.max(1) as usize;
        let ny = request.lines as usize;
        let mut fwd = TraceImage {
            z_counts: Vec::with_capacity(n * ny),
            time_s: Vec::with_capacity(n * ny),
        };
        let mut bwd = want_backward.then(|| TraceImage {
            z_counts: Vec::with_capacity(n * ny),
            time_s: Vec::with_capacity(n * ny),
        });
        // A frame the controller scanned in the other slow direction (a bouncy scan left
        // on, a start by someone else) has its lines in the other order in time: not the
        // scan requested.
        for data in std::iter::once(forward).chain(backward) {
            if data.direction_up != direction_up {
                let (found, started) = match direction_up {
                    1 => ("downwards", "upwards"),
                    _ => ("upwards", "downwards"),
                };
                return Err(NanonisError::new(
                    NanonisErrorKind::Controller,
                    format!("the controller scanned the frame {found}; it was started {started}"),
                )
                .in_command("Scan.FrameDataGrab"));
            }
        }
        for line in 0..ny {
            // Rows come top line first whatever the slow direction (for an upward scan the
            // last line acquired, for a downward one the first): the frame's top is line
            // ny − 1 of spm-hal's geometry, for direct and counter (the frame turned by
            // 180°) requests alike.
            let row = ny - 1 - line;
            // Its place in time: upwards line `line` is acquired `line`-th, downwards
            // `(ny − 1 − line)`-th.
            let acquired = match self.config.slow_direction {
                SlowDirection::Up => line,
                SlowDirection::Down => ny - 1 - line,
            };
            let line_start = start_s + acquired as f64 * (tf + tb);
            let data_row = line_of(&forward.data, row, n16u)?;
            for pixel in 0..n {
                let samples = pixel * bin..(pixel + 1) * bin;
                let (z, index) = self.binned(data_row, samples)?;
                fwd.z_counts.push(z);
                fwd.time_s
                    .push(line_start + (index + 0.5) * tf / n16u as f64);
            }
            if let (Some(image), Some(data)) = (bwd.as_mut(), backward) {
                let data_row = line_of(&data.data, row, n16u)?;
                for pixel in 0..n {
                    let column = n - 1 - pixel;
                    let samples = column * bin..(column + 1) * bin;
                    let (z, index) = self.binned(data_row, samples)?;
                    image.z_counts.push(z);
                    // The retrace runs from the line's last sample back to its first.
                    let index = (n16u - 1) as f64 - index;
                    image
                        .time_s
                        .push(line_start + tf + (index + 0.5) * tb / n16u as f64);
                }
            }
        }
        Ok(Frame {
            request: request.clone(),
            forward: fwd,
            backward: bwd,
        })
    }

    /// One scan's command sequence in protocol order: the frame planned, the settings sent
    /// (and read back) and the scan started, its end waited for and its data grabbed, the
    /// frame assembled.
    fn scan_impl(&mut self, request: &ScanRequest) -> Result<Frame, NanonisError> {
        // A scan moves the tip: only this one's raster counts from here on.
        self.after_scan = None;
        let plan = self.plan_scan(request)?;
        let (n16, lines) = (plan.n16, request.lines);
        let direction_up = self.config.slow_direction.direction_up();
        // Backward first when wanted (a controller that records lazily learns it is needed).
        let want_backward = request.record_backward && self.capabilities.backward_trace;
        let how = (lines, direction_up, want_backward);
        let ScanDone {
            end,
            reconnects,
            line_times: (tf, tb),
        } = match self.scan_in_one_round_trip(&plan, how)? {
            Some(done) => done,
            None => self.scan_start_then_end(&plan, how)?,
        };
        // Ended normally on the connection it was started on: no scan runs until the next
        // start (a reconnection in between may have lost the end, or left another scan).
        if self.client.reconnects() == reconnects {
            self.scan_idle = Some(reconnects);
        }
        let start_s = end.end_s - f64::from(lines) * (tf + tb);
        // Where the tip may be now: on the raster, give or take two pixels and 2 % of the
        // frame (where a controller leaves the tip after a frame: its last pixel, or back
        // at its start).
        let [x0, x1, y0, y1] = plan.raster_counts;
        let margin = 2.0 * request.pixel_step.value() + 0.02 * (x1 - x0).max(y1 - y0);
        self.after_scan = Some([x0 - margin, x1 + margin, y0 - margin, y1 + margin]);
        // A position read with the scan's end (pipelined) is checked now.
        if self.readings.sequence == self.client.sequence()
            && let Some(p) = self.readings.position
        {
            self.check_tip_after_scan(p)?;
        }
        self.assemble_frame(
            request,
            (&end, (n16, plan.bin), direction_up, want_backward),
            (start_s, tf, tb),
        )
    }

    /// A scan started ([`Self::start_scan`]: the set-up and the start, then the end
    /// ([`Self::end_of_scan`]: the wait, the data, the clock and the position; one round
    /// trip with [`Self::pipelining`]).
    fn scan_start_then_end(
        &mut self,
        plan: &ScanPlan,
        (lines, direction_up, want_backward): (u32, u32, bool),
    ) -> Result<ScanDone, NanonisError> {
        self.start_scan(
            plan.n16 as i32,
            lines as i32,
            plan.frame,
            plan.speed,
            direction_up,
        )?;
        // The connection the scan was started on.
        let reconnects = self.client.reconnects();
        let line_times = self.sent.line_times_s.unwrap_or((plan.line_s, plan.line_s));
        let expected_s = f64::from(lines) * (line_times.0 + line_times.1);
        let ended = self.end_of_scan(expected_s, want_backward, plan.n16, lines);
        let end = self.finish_scan(ended, expected_s)?;
        Ok(ScanDone {
            end,
            reconnects,
            line_times,
        })
    }

    /// A whole scan in one round trip with a simulated controller ([`Self::pipelining`]):
    /// the settings that differ from those last sent (buffer and speed with their
    /// read-backs, the frame), the start, the wait for the end, the data, the clock and the
    /// position in one write, answered in order. `Ok(None)`: not done so, to be done by
    /// [`Self::scan_start_then_end`] — not pipelining, interrupted, or a failure before the
    /// start that the client would retry (busy, a lost connection).
    ///
    /// The controller executes the whole pipeline whatever it answers to each part. So a
    /// setting it refused (or read back otherwise than set) or a start it refused has run
    /// what followed all the same — a scan with the settings it had, or a wait for none
    /// (its timeout of controller time) — before the refusal is read: any scan started is
    /// then stopped (`Scan.Action` stop), every reply after the failure is discarded, the
    /// settings are sent again next time, and the error is the refusal, naming the
    /// refused command. Nothing after a failure is ever taken as the scan's data.
    fn scan_in_one_round_trip(
        &mut self,
        plan: &ScanPlan,
        (lines, direction_up, want_backward): (u32, u32, bool),
    ) -> Result<Option<ScanDone>, NanonisError> {
        let clock = match (self.pipelining(), self.clock_request()) {
            (true, Some(clock)) if !self.interrupted() => clock,
            _ => return Ok(None),
        };
        self.stop_running_scan()?;
        self.invalidate_on_reconnect();
        // Connected, on the connection `Scan.StatusGet` (now or before) found idle.
        if !self.scan_idle_known() {
            return Ok(None);
        }
        let buffer = (plan.n16 as i32, lines as i32);
        let bits = frame_bits(&plan.frame);
        let mut setup = Vec::with_capacity(6);
        if self.sent.buffer != Some(buffer) {
            setup.push(Request::ScanBufferSet(ScanBuffer {
                channels: vec![self.config.z_channel],
                pixels: buffer.0,
                lines: buffer.1,
            }));
            setup.push(Request::ScanBufferGet);
        }
        if self.sent.frame != Some(bits) {
            setup.push(Request::ScanFrameSet(plan.frame));
        }
        let speed_sent = self.sent.speed == Some(plan.speed);
        if !speed_sent {
            setup.push(Request::ScanSpeedSet(plan.speed));
            setup.push(Request::ScanSpeedGet);
        }
        setup.push(Request::ScanAction {
            action: scan_action::START,
            direction_up,
        });
        // The wait for the line times the controller uses, as read back before, else for
        // those requested (and the rest of it after, should the controller's be longer).
        let line_times = match (speed_sent, self.sent.line_times_s) {
            (true, Some(t)) => t,
            _ => (plan.line_s, plan.line_s),
        };
        let mut wait = self.end_of_scan_wait(f64::from(lines) * (line_times.0 + line_times.1));
        let reads = self.end_of_scan_reads(want_backward, clock);
        // From the start until its normal end a scan may be running.
        self.scan_idle = None;
        let reconnects = self.client.reconnects();
        let all: Vec<&Request> = setup
            .iter()
            .chain(std::iter::once(&wait.request))
            .chain(&reads)
            .collect();
        let timeout_s = self.client.waiting_timeout_s(wait.first_s);
        let mut results = self.client.call_pipelined(&all, timeout_s);
        let after_start = results.split_off(setup.len().min(results.len()));
        let answers = checked_setup(&setup, results, buffer);
        if let Some((e, other_settings)) = answers.failure {
            return self.after_a_failed_start(e, other_settings && answers.started);
        }
        // The controller holds the settings sent.
        self.sent.buffer = Some(buffer);
        self.sent.frame = Some(bits);
        if let Some(t) = answers.line_times {
            self.sent.speed = Some(plan.speed);
            self.sent.line_times_s = Some(t);
        }
        let line_times = self.sent.line_times_s.unwrap_or(line_times);
        let expected_s = f64::from(lines) * (line_times.0 + line_times.1);
        wait.total_ms = self.end_of_scan_timeout_ms(expected_s);
        let calls: Vec<(&Request, Option<f64>)> =
            std::iter::once((&wait.request, Some(wait.first_s)))
                .chain(reads.iter().map(|r| (r, None)))
                .collect();
        let ended = self
            .replies_in_order(&calls, after_start)
            .and_then(|replies| {
                self.end_of_scan_replies(replies, &wait, (want_backward, plan.n16, lines))
            });
        let end = self.finish_scan(ended, expected_s)?;
        Ok(Some(ScanDone {
            end,
            reconnects,
            line_times,
        }))
    }

    /// After a scan's set-up or start failed in its pipeline ([`Self::scan_in_one_round_trip`],
    /// whose later requests the controller has executed by now): any scan it started is
    /// stopped and the settings are forgotten (sent again). When a scan ran with other
    /// settings than those asked for (`scanned_otherwise`: a setting refused, even as busy,
    /// before a start that was not), the instrument is not where the run left it — the tip
    /// has scanned another frame — so the failure is the error whatever its kind (a busy
    /// one stays transient: the calibration measures the node again, from its move). Else
    /// a failure the client would retry (busy, a lost connection) gives `Ok(None)`: the
    /// scan is done again one step after another; any other is the error.
    fn after_a_failed_start(
        &mut self,
        e: NanonisError,
        scanned_otherwise: bool,
    ) -> Result<Option<ScanDone>, NanonisError> {
        tracing::debug!(error = %e, "nanonis: the scan's set-up or start failed; stopping");
        self.scan_idle = None;
        self.sent = SentSettings {
            reconnects: self.client.reconnects(),
            ..SentSettings::default()
        };
        if let Err(stop) = self.client.stop(&Request::ScanAction {
            action: scan_action::STOP,
            direction_up: 1,
        }) {
            tracing::warn!(error = %stop, "nanonis: could not stop the scan");
        }
        if scanned_otherwise {
            return Err(NanonisError {
                message: format!(
                    "{}; the controller scanned with its previous settings in its place \
                     (stopped): not the scan asked for",
                    e.message
                ),
                ..e
            });
        }
        let retried = e.kind == NanonisErrorKind::Busy
            || (!self.client.is_connected() && e.kind != NanonisErrorKind::Aborted);
        if retried { Ok(None) } else { Err(e) }
    }

    /// The mean height of a line's `samples` (columns of the frame), counts, and their mean
    /// column: one requested pixel ([`ScanPlan::bin`]).
    fn binned(
        &self,
        data_row: &[f32],
        samples: std::ops::Range<usize>,
    ) -> Result<(f64, f64), NanonisError> {
        let count = samples.len().max(1) as f64;
        let index = 0.5 * (samples.start + samples.end.saturating_sub(1)) as f64;
        let values = data_row.get(samples).ok_or_else(|| {
            NanonisError::new(
                NanonisErrorKind::IncompleteData,
                "the frame has fewer pixels per line than requested",
            )
            .in_command("Scan.FrameDataGrab")
        })?;
        let mut sum = 0.0;
        for &value in values {
            sum += self.z_counts(value)?;
        }
        Ok((sum / count, index))
    }

    fn z_counts(&self, value_m: f32) -> Result<f64, NanonisError> {
        if !value_m.is_finite() {
            // Pitfall: pixels not acquired yet are NaN in the buffer.
            return Err(NanonisError::new(
                NanonisErrorKind::IncompleteData,
                "the frame has pixels that were not acquired (NaN)",
            )
            .in_command("Scan.FrameDataGrab"));
        }
        Ok(f64::from(value_m) / self.z_m_per_count)
    }

    /// Whether a command and the reads after it are pipelined ([`Client::call_pipelined`]):
    /// with a simulated controller (a virtual clock: `nanonis-sim`, whose server reads a
    /// connection's requests one at a time from its stream, so several may be under way).
    /// A controller clock in real time, or the host's (hardware), sends one command per
    /// round trip, as the vendor's client does.
    fn pipelining(&self) -> bool {
        matches!(
            self.config.clock,
            ClockSource::ControllerSignals {
                virtual_time: true,
                ..
            }
        )
    }

    /// `first` (with `expected_s`, a wait-style command expected to take that long), then
    /// `reads` (commands that change nothing on the controller), in order
    /// ([`Self::call_in_order`]).
    fn call_then_read(
        &mut self,
        first: &Request,
        expected_s: Option<f64>,
        reads: &[Request],
    ) -> Result<Vec<Reply>, NanonisError> {
        let calls: Vec<(&Request, Option<f64>)> = std::iter::once((first, expected_s))
            .chain(reads.iter().map(|r| (r, None)))
            .collect();
        self.call_in_order(&calls)
    }

    /// Requests (each with `Some(expected_s)` when it is a wait-style command expected to take
    /// that long) executed in order: pipelined in one round trip when [`Self::pipelining`],
    /// else one call each; from a failure in the pipeline that the client retries (busy, or a
    /// lost connection with a retry-safe request) on, one call each (with the client's
    /// retries). Only for requests after which the later ones do no harm when an earlier
    /// one failed (reads, waits). The replies, in order.
    fn call_in_order(
        &mut self,
        calls: &[(&Request, Option<f64>)],
    ) -> Result<Vec<Reply>, NanonisError> {
        let results = if self.pipelining() {
            let all: Vec<&Request> = calls.iter().map(|(r, _)| *r).collect();
            let waits: Vec<f64> = calls.iter().filter_map(|(_, e)| *e).collect();
            let timeout_s = if waits.is_empty() {
                self.client.config().command_timeout_s
            } else {
                self.client.waiting_timeout_s(waits.iter().sum())
            };
            self.client.call_pipelined(&all, timeout_s)
        } else {
            Vec::new()
        };
        self.replies_in_order(calls, results)
    }

    /// The replies to `calls` from `results`, the answers to them sent in one pipeline (or
    /// fewer: none when not pipelined): taken in order up to the first failure the client
    /// would retry (busy, or a lost connection with a retry-safe request), from there one
    /// call each (with the client's retries). Any other failure is the error.
    fn replies_in_order(
        &mut self,
        calls: &[(&Request, Option<f64>)],
        results: Vec<Result<Reply, NanonisError>>,
    ) -> Result<Vec<Reply>, NanonisError> {
        let mut replies = Vec::with_capacity(calls.len());
        for ((request, _), result) in calls.iter().zip(results) {
            match result {
                Ok(reply) => replies.push(reply),
                Err(e)
                    if e.kind == NanonisErrorKind::Busy
                        || (!self.client.is_connected() && request.is_retry_safe()) =>
                {
                    tracing::debug!(error = %e, "nanonis: pipeline broken; one call each");
                    break;
                }
                Err(e) => return Err(e),
            }
        }
        for (request, expected_s) in calls.iter().skip(replies.len()) {
            replies.push(match expected_s {
                Some(expected_s) => self.client.call_waiting(request, *expected_s)?,
                None => self.client.call(request)?,
            });
        }
        Ok(replies)
    }

    /// The controller's clock read (`Signals.ValsGet` of the two time signals), with
    /// [`ClockSource::ControllerSignals`].
    fn clock_request(&self) -> Option<Request> {
        match self.config.clock {
            ClockSource::ControllerSignals {
                whole_s_signal,
                fraction_s_signal,
                ..
            } => Some(Request::SignalsValsGet {
                indexes: vec![whole_s_signal, fraction_s_signal],
                wait_newest: 0,
            }),
            ClockSource::Host => None,
        }
    }

    /// The end of the scan just started, which takes `expected_s`, and its data: `None` when
    /// it did not end within the margin. With [`Self::pipelining`] the wait (with an
    /// interrupt flag its first slice), the grabs, the clock and the position are one round
    /// trip (the readings kept as after reading them one by one; after a first slice that
    /// timed out, the rest of the wait and the reads again one call each), else the wait
    /// ([`Self::wait_end_of_scan`]), the grabs and the clock one call each.
    fn end_of_scan(
        &mut self,
        expected_s: f64,
        want_backward: bool,
        n16: u32,
        lines: u32,
    ) -> Result<Option<ScanEnd>, NanonisError> {
        let clock = self.clock_request();
        let (true, Some(clock)) = (self.pipelining(), clock) else {
            if !self.wait_end_of_scan(expected_s)? {
                return Ok(None);
            }
            return self.scan_data(want_backward, n16, lines).map(Some);
        };
        if self.interrupted() {
            return Err(self.pause_interrupted_scan());
        }
        let wait = self.end_of_scan_wait(expected_s);
        let reads = self.end_of_scan_reads(want_backward, clock);
        let replies = self.call_then_read(&wait.request, Some(wait.first_s), &reads)?;
        self.end_of_scan_replies(replies, &wait, (want_backward, n16, lines))
    }

    /// The wait for the end of a scan that takes `expected_s`, to be followed by
    /// [`Self::end_of_scan_reads`] in one pipeline: the whole wait, or with an interrupt
    /// flag its first slice.
    fn end_of_scan_wait(&self, expected_s: f64) -> EndOfScanWait {
        let total_ms = self.end_of_scan_timeout_ms(expected_s);
        let (first_ms, first_s) = if self.interrupt.is_some() {
            let ms = slice_ms().min(total_ms);
            (ms, f64::from(ms) * 1e-3)
        } else {
            (total_ms, expected_s)
        };
        EndOfScanWait {
            request: Request::ScanWaitEndOfScan {
                timeout_ms: first_ms,
            },
            first_ms,
            first_s,
            total_ms,
        }
    }

    /// What is read after the end of a scan, in order: its backward data when wanted (a
    /// controller that records lazily learns it is needed), its forward data, the clock
    /// (`clock`) and the position.
    fn end_of_scan_reads(&self, want_backward: bool, clock: Request) -> Vec<Request> {
        let grab_request = |forward| Request::ScanFrameDataGrab {
            channel: self.config.z_channel as u32,
            forward,
        };
        let mut reads: Vec<Request> = want_backward.then(|| grab_request(0)).into_iter().collect();
        reads.extend([
            grab_request(1),
            clock,
            Request::FolMeXYPosGet { wait_newest: 0 },
        ]);
        reads
    }

    /// The scan's end from the replies to `wait` and [`Self::end_of_scan_reads`] (`None`:
    /// it did not end within the margin); the clock and position read are kept. After a
    /// first part of the wait that timed out, the reads were of a scan still running: the
    /// rest of the wait (up to `wait.total_ms`), then the reads again, one call each.
    fn end_of_scan_replies(
        &mut self,
        replies: Vec<Reply>,
        wait: &EndOfScanWait,
        (want_backward, n16, lines): (bool, u32, u32),
    ) -> Result<Option<ScanEnd>, NanonisError> {
        let mut replies = replies.into_iter();
        match replies.next() {
            Some(Reply::WaitEndOfScan { timed_out, .. }) if timed_out != 1 => {}
            // The reads were of a scan still running: the rest of the wait, then again.
            Some(Reply::WaitEndOfScan { .. })
                if self.interrupt.is_some() || wait.first_ms < wait.total_ms =>
            {
                if !self.sliced_wait_end_of_scan(wait.total_ms, wait.first_ms)? {
                    return Ok(None);
                }
                return self.scan_data(want_backward, n16, lines).map(Some);
            }
            Some(Reply::WaitEndOfScan { .. }) => return Ok(None),
            other => return Err(unexpected_or_none("Scan.WaitEndOfScan", other)),
        }
        let backward = if want_backward {
            Some(checked_frame(replies.next(), n16, lines)?)
        } else {
            None
        };
        let forward = checked_frame(replies.next(), n16, lines)?;
        let end_s = clock_of(replies.next())?;
        let position = match replies.next() {
            Some(Reply::XY { x_m, y_m }) => self.counts_of_metres(x_m, y_m),
            other => return Err(unexpected_or_none("FolMe.XYPosGet", other)),
        };
        // Both read after everything else, and reads take no virtual time: kept.
        self.readings = Readings {
            sequence: self.client.sequence(),
            clock_s: Some(end_s),
            position: Some(position),
        };
        Ok(Some(ScanEnd {
            forward,
            backward,
            end_s,
        }))
    }

    /// A scan's data and the clock at its end, one call each (backward first when wanted: a
    /// controller that records lazily learns it is needed).
    fn scan_data(
        &mut self,
        want_backward: bool,
        n16: u32,
        lines: u32,
    ) -> Result<ScanEnd, NanonisError> {
        let backward = if want_backward {
            Some(self.grab(0, n16, lines)?)
        } else {
            None
        };
        let forward = self.grab(1, n16, lines)?;
        let end_s = self.now_s()?;
        Ok(ScanEnd {
            forward,
            backward,
            end_s,
        })
    }

    fn grab(&mut self, forward: u32, columns: u32, rows: u32) -> Result<FrameData, NanonisError> {
        let request = Request::ScanFrameDataGrab {
            channel: self.config.z_channel as u32,
            forward,
        };
        checked_frame(Some(self.client.call(&request)?), columns, rows)
    }
}

/// A slice of the interruptible wait for the end of a scan, ms ([`INTERRUPT_POLL_S`]).
fn slice_ms() -> i32 {
    (INTERRUPT_POLL_S * 1e3) as i32
}

/// A scan's frame and speed as the controller is sent them ([`NanonisMicroscope::plan_scan`]).
struct ScanPlan {
    /// The scanned raster's sample centres, counts: x from, x to, y from, y to.
    raster_counts: [f64; 4],
    /// Pixels per line scanned (the request's, coerced to a multiple of 16).
    n16: u32,
    /// Samples per requested pixel. Above 1 (a request of a count dividing `n16`, such as 4
    /// of 16): the controller scans the request's frame in its line time, `bin` samples in
    /// each requested pixel's cell at a `bin`-th of its dwell, and each requested pixel is
    /// their mean (centred on the pixel, timed at its dwell's middle). 1: the line padded
    /// past the requested pixels at their step and dwell, and cropped.
    bin: u32,
    frame: ScanFrame,
    speed: ScanSpeed,
    /// One line's trace as requested, s.
    line_s: f64,
}

/// The wait for a scan's end as sent ([`NanonisMicroscope::end_of_scan_wait`]).
struct EndOfScanWait {
    /// `Scan.WaitEndOfScan` with `first_ms`.
    request: Request,
    /// Its timeout, ms, and as s the time it is expected to take (the scan's).
    first_ms: i32,
    first_s: f64,
    /// The whole wait's timeout, ms: more than `first_ms` for the first slice of an
    /// interruptible wait.
    total_ms: i32,
}

/// A scan done: its end, [`Client::reconnects`] when it was started, and the line times
/// (forward, backward) the controller used, s.
struct ScanDone {
    end: ScanEnd,
    reconnects: u64,
    line_times: (f64, f64),
}

/// A scan's end as [`NanonisMicroscope::end_of_scan`] found it.
struct ScanEnd {
    forward: FrameData,
    backward: Option<FrameData>,
    /// The controller's clock at the end, s.
    end_s: f64,
}

fn unexpected_or_none(command: &str, reply: Option<Reply>) -> NanonisError {
    match reply {
        Some(reply) => unexpected(command, &reply),
        None => NanonisError::new(NanonisErrorKind::Protocol, "no reply").in_command(command),
    }
}

/// The controller's time from the reply to the clock read, s.
fn clock_of(reply: Option<Reply>) -> Result<f64, NanonisError> {
    match reply {
        Some(Reply::Values(v)) if v.len() == 2 => Ok(f64::from(v[0]) + f64::from(v[1])),
        other => Err(unexpected_or_none("Signals.ValsGet", other)),
    }
}

/// A frame grab's reply, checked to hold `columns × rows` data.
fn checked_frame(reply: Option<Reply>, columns: u32, rows: u32) -> Result<FrameData, NanonisError> {
    match reply {
        Some(Reply::FrameData(d)) if d.rows == rows as usize && d.columns == columns as usize => {
            Ok(d)
        }
        Some(Reply::FrameData(d)) => Err(NanonisError::new(
            NanonisErrorKind::IncompleteData,
            format!(
                "{} × {} data for a {columns} × {rows} scan",
                d.columns, d.rows
            ),
        )
        .in_command("Scan.FrameDataGrab")),
        other => Err(unexpected_or_none("Scan.FrameDataGrab", other)),
    }
}

/// Row `row` of a grabbed frame of `columns` pixels per line.
fn line_of(data: &[f32], row: usize, columns: usize) -> Result<&[f32], NanonisError> {
    data.get(row * columns..(row + 1) * columns).ok_or_else(|| {
        NanonisError::new(
            NanonisErrorKind::IncompleteData,
            format!("the frame's data end before line {row} of {columns} pixels"),
        )
        .in_command("Scan.FrameDataGrab")
    })
}

/// The bits of a frame's geometry, to tell a frame from the one last sent.
fn frame_bits(frame: &ScanFrame) -> [u32; 5] {
    [
        frame.centre_x_m.to_bits(),
        frame.centre_y_m.to_bits(),
        frame.width_m.to_bits(),
        frame.height_m.to_bits(),
        frame.angle_deg.to_bits(),
    ]
}

/// The reply to `Scan.BufferGet` checked to hold the buffer set, `(pixels, lines)` (pitfall:
/// the controller coerces pixels per line to a multiple of 16).
fn checked_buffer(reply: Option<Reply>, (pixels, lines): (i32, i32)) -> Result<(), NanonisError> {
    match reply {
        Some(Reply::Buffer(b)) if b.pixels == pixels && b.lines == lines => Ok(()),
        Some(Reply::Buffer(b)) => Err(NanonisError::new(
            NanonisErrorKind::Controller,
            format!(
                "the controller set {} × {} pixels for the requested {pixels} × {lines}",
                b.pixels, b.lines
            ),
        )
        .in_command("Scan.BufferGet")),
        other => Err(unexpected_or_none("Scan.BufferGet", other)),
    }
}

/// The line times (forward, backward), s, of the reply to `Scan.SpeedGet`, checked positive
/// (pitfall: the controller may coerce the speed; the pixels are timed by what it uses).
fn checked_line_times(reply: Option<Reply>) -> Result<(f64, f64), NanonisError> {
    let (tf, tb) = match reply {
        Some(Reply::Speed(s)) => (f64::from(s.forward_line_s), f64::from(s.backward_line_s)),
        other => return Err(unexpected_or_none("Scan.SpeedGet", other)),
    };
    if !(tf.is_finite() && tb.is_finite() && tf > 0.0 && tb > 0.0) {
        return Err(NanonisError::new(
            NanonisErrorKind::Controller,
            format!("line times {tf} s / {tb} s are not positive"),
        )
        .in_command("Scan.SpeedGet"));
    }
    Ok((tf, tb))
}

/// A scan's set-up and start as the controller answered them in one pipeline
/// ([`checked_setup`]).
struct SetupAnswers {
    /// The line times read back, when the speed was set.
    line_times: Option<(f64, f64)>,
    /// The first failure, and whether it left the controller with other settings than
    /// those asked for (a setting refused, or read back otherwise than set).
    failure: Option<(NanonisError, bool)>,
    /// The start was answered without error: a scan ran.
    started: bool,
}

/// The replies to a scan's set-up and start sent in one pipeline (`setup`, the start last),
/// checked in order: the first error reply, failure or read-back that does not fit.
fn checked_setup(
    setup: &[Request],
    results: Vec<Result<Reply, NanonisError>>,
    buffer: (i32, i32),
) -> SetupAnswers {
    let mut answers = SetupAnswers {
        line_times: None,
        failure: None,
        started: false,
    };
    let mut results = results.into_iter();
    for request in setup {
        let reply = results.next().unwrap_or_else(|| {
            Err(NanonisError::new(NanonisErrorKind::Protocol, "no reply")
                .in_command(request.name()))
        });
        let setting = matches!(
            request,
            Request::ScanBufferSet(_) | Request::ScanFrameSet(_) | Request::ScanSpeedSet(_)
        );
        let checked = match (request, reply) {
            (_, Err(e)) => Err((e, setting)),
            (Request::ScanBufferGet, Ok(reply)) => checked_buffer(Some(reply), buffer)
                .map(|()| None)
                .map_err(|e| (e, true)),
            (Request::ScanSpeedGet, Ok(reply)) => checked_line_times(Some(reply))
                .map(Some)
                .map_err(|e| (e, true)),
            (_, Ok(_)) => Ok(None),
        };
        match checked {
            Ok(line_times) => {
                answers.line_times = line_times.or(answers.line_times);
                answers.started |= matches!(request, Request::ScanAction { .. });
            }
            Err(failure) => {
                answers.failure = answers.failure.or(Some(failure));
            }
        }
    }
    answers
}

impl NanonisMicroscope {
    fn now_s(&mut self) -> Result<f64, NanonisError> {
        let ClockSource::ControllerSignals {
            whole_s_signal,
            fraction_s_signal,
            virtual_time,
        } = self.config.clock
        else {
            return Ok(self.epoch.elapsed().as_secs_f64());
        };
        let before = self.client.sequence();
        if virtual_time
            && self.readings.sequence == before
            && let Some(t) = self.readings.clock_s
        {
            return Ok(t);
        }
        let request = Request::SignalsValsGet {
            indexes: vec![whole_s_signal, fraction_s_signal],
            wait_newest: 0,
        };
        let t = match self.client.call(&request)? {
            Reply::Values(v) if v.len() == 2 => f64::from(v[0]) + f64::from(v[1]),
            other => return Err(unexpected("Signals.ValsGet", &other)),
        };
        let readings = self.after_read(before);
        if virtual_time {
            readings.clock_s = Some(t);
        }
        Ok(t)
    }

    /// The commanded position: kept from the last reading or move while the controller has
    /// received nothing else, else read (`FolMe.XYPosGet`).
    fn position_counts(&mut self) -> Result<CountPoint, NanonisError> {
        let before = self.client.sequence();
        if self.readings.sequence == before
            && let Some(p) = self.readings.position
        {
            return Ok(p);
        }
        let p = match self
            .client
            .call(&Request::FolMeXYPosGet { wait_newest: 0 })?
        {
            Reply::XY { x_m, y_m } => self.counts_of_metres(x_m, y_m),
            other => return Err(unexpected("FolMe.XYPosGet", &other)),
        };
        self.after_read(before).position = Some(p);
        self.check_tip_after_scan(p)?;
        Ok(p)
    }

    /// The first position read from the controller after the backend's last scan must lie
    /// on that scan's raster (with its margin): the backend has moved nothing since, so a
    /// tip elsewhere was moved by another client — a program or a person at the controller
    /// — and what the run measures next is not what it commanded (issue 25 item 19). That is
    /// an error naming the cause; the run stops there (`--resume` continues it once the
    /// controller is the run's alone). Checked once per scan.
    fn check_tip_after_scan(&mut self, p: CountPoint) -> Result<(), NanonisError> {
        let Some([x0, x1, y0, y1]) = self.after_scan.take() else {
            return Ok(());
        };
        let (x, y) = (p.x.value(), p.y.value());
        if (x0..=x1).contains(&x) && (y0..=y1).contains(&y) {
            return Ok(());
        }
        // Aborted, as by the user: not this node's failure, so the run stops (a visit given
        // up and the run going on would leave the tip to the other client).
        Err(NanonisError::new(
            NanonisErrorKind::Aborted,
            format!(
                "after the backend's scan of x {x0:.0} … {x1:.0}, y {y0:.0} … {y1:.0} counts the \
                 tip is at ({x:.0}, {y:.0}) counts, and the backend moved nothing since: \
                 another client (a program or the controller's own software) moved the tip; \
                 a calibration needs the controller to itself"
            ),
        )
        .in_command("FolMe.XYPosGet"))
    }

    /// Runs one command that does not move the tip (a wait, a Z read) and keeps the
    /// position known before it: what it takes is controller time, so the clock is read
    /// again after it.
    fn keeping_position<T>(
        &mut self,
        command: impl FnOnce(&mut Self) -> Result<T, NanonisError>,
    ) -> Result<T, NanonisError> {
        let before = self.client.sequence();
        let position = (self.readings.sequence == before)
            .then_some(self.readings.position)
            .flatten();
        let result = command(self)?;
        let after = self.client.sequence();
        if after == before + 1 {
            self.readings = Readings {
                position,
                ..Readings::none(after)
            };
        }
        Ok(result)
    }

    /// The readings after a read of the clock or the position begun at `before`: a read
    /// moves nothing and takes no virtual time, so what held before it still holds when it
    /// was the only command sent since (a re-sent read or a reconnection forgets the rest).
    fn after_read(&mut self, before: u64) -> &mut Readings {
        let after = self.client.sequence();
        if self.readings.sequence == before && after == before + 1 {
            self.readings.sequence = after;
        } else {
            self.readings = Readings::none(after);
        }
        &mut self.readings
    }
}

/// Continuous and bouncy scanning, autosave and autopaste off (`Scan.PropsSet`), then the Z
/// feedback checked: on (`true`), or an error.
fn one_frame_at_a_time_with_feedback(client: &mut Client) -> Result<bool, NanonisError> {
    let autopaste = client.schema().props_set_autopaste.then_some(3);
    client.call(&Request::ScanPropsSet(ScanProps {
        continuous: 2,
        bouncy: 2,
        autosave: 3,
        series_name: String::new(),
        comment: String::new(),
        modules: Vec::new(),
        autopaste,
    }))?;
    if u32_reply(client, &Request::ZCtrlOnOffGet)? != 1 {
        return Err(NanonisError::new(
            NanonisErrorKind::FeedbackOff,
            "the Z controller is off: approach the tip and switch the feedback on first",
        )
        .in_command("ZCtrl.OnOffGet"));
    }
    Ok(true)
}

fn unexpected(command: &str, reply: &Reply) -> NanonisError {
    NanonisError::new(
        NanonisErrorKind::Protocol,
        format!("unexpected reply {reply:?}"),
    )
    .in_command(command)
}

fn f32x2(client: &mut Client, request: &Request) -> Result<[f32; 2], NanonisError> {
    match client.call(request)? {
        Reply::F32x2(v) => Ok(v),
        other => Err(unexpected(request.name(), &other)),
    }
}

fn u32_reply(client: &mut Client, request: &Request) -> Result<u32, NanonisError> {
    match client.call(request)? {
        Reply::U32(v) => Ok(v),
        other => Err(unexpected(request.name(), &other)),
    }
}

impl Microscope for NanonisMicroscope {
    type Error = NanonisError;

    fn capabilities(&self) -> Capabilities {
        self.capabilities.clone()
    }

    fn now(&mut self) -> Result<Seconds, NanonisError> {
        let result = self.now_s().map(Seconds);
        self.noting_failure(result)
    }

    fn wait(&mut self, duration: Seconds) -> Result<(), NanonisError> {
        let d = duration.value();
        if !(d.is_finite() && d >= 0.0) {
            return Err(NanonisError::new(
                NanonisErrorKind::InvalidRequest,
                format!("wait duration {duration} must be finite and ≥ 0"),
            ));
        }
        let result = self.keeping_position(|m| m.pause(d));
        self.noting_failure(result)
    }

    fn position(&mut self) -> Result<CountPoint, NanonisError> {
        let result = self.position_counts();
        self.noting_failure(result)
    }

    fn move_to(&mut self, request: MoveRequest) -> Result<(), NanonisError> {
        // The backend's own move: wherever the tip was, it is commanded elsewhere now.
        self.after_scan = None;
        let result = self.move_impl(request);
        self.noting_failure(result)
    }

    fn scan(&mut self, request: &ScanRequest) -> Result<Frame, NanonisError> {
        let result = self.scan_impl(request);
        if let Err(e) = &result {
            tracing::debug!(error = %e, "nanonis: scan failed");
        }
        self.noting_failure(result)
    }

    fn z_position(&mut self) -> Result<Counts, NanonisError> {
        let result = self.keeping_position(|m| match m.client.call(&Request::ZCtrlZPosGet)? {
            Reply::F32(z) if z.is_finite() => Ok(Counts(f64::from(z) / m.z_m_per_count)),
            other => Err(unexpected("ZCtrl.ZPosGet", &other)),
        });
        self.noting_failure(result)
    }

    fn coarse_z(&mut self) -> Option<&mut dyn CoarseZStage<Error = NanonisError>> {
        if self.capabilities.coarse_z.is_some() {
            Some(self)
        } else {
            None
        }
    }
}

impl NanonisMicroscope {
    /// [`Microscope::move_to`] (a failure is noted by the caller).
    fn move_impl(&mut self, request: MoveRequest) -> Result<(), NanonisError> {
        self.check_inside(request.target, "move target")?;
        let speed = request.speed.value();
        if !(speed.is_finite() && speed > 0.0) {
            return Err(NanonisError::new(
                NanonisErrorKind::InvalidRequest,
                format!("move speed {speed} counts/s must be finite and > 0"),
            ));
        }
        let settle = request.settle.value();
        if !(settle.is_finite() && settle >= 0.0) {
            return Err(NanonisError::new(
                NanonisErrorKind::InvalidRequest,
                format!("settle time {} must be finite and ≥ 0", request.settle),
            ));
        }
        // Where the move starts (for its timeout), before any setting is sent: a kept
        // position stays valid only until the controller receives something else.
        let here = self.position_counts()?;
        self.invalidate_on_reconnect();
        // Speed in m/s along the path: counts/s × the geometric mean of the X and Y
        // metres per count (exact when they are equal, as in the counts convention of a
        // square field).
        let m_per_count = (self.lateral_m_per_count[0] * self.lateral_m_per_count[1]).sqrt();
        let speed_m = f32_of(speed * m_per_count);
        if self.sent.folme_speed != Some(speed_m.to_bits()) {
            self.client.call(&Request::FolMeSpeedSet {
                speed_m_per_s: speed_m,
                custom: 1,
            })?;
            self.sent.folme_speed = Some(speed_m.to_bits());
        }
        let (x_m, y_m) = self.to_metres(request.target);
        let expected_s = here.distance(request.target).value() / speed;
        let set = Request::FolMeXYPosSet {
            x_m,
            y_m,
            wait_end_of_move: 1,
        };
        // The settle always goes to the controller (even 0 s) so that a controller-side
        // clock sees move and settle as one operation.
        let clock_s = match (self.pipelining(), self.clock_request()) {
            (true, Some(clock)) => {
                // The move, its settle and the clock read after them in one round trip (a
                // move the controller refuses is followed by the settle all the same: time
                // passes, and the clock is read again after the failure).
                let wait = self.controller_wait(settle)?;
                let mut replies = self
                    .call_in_order(&[
                        (&set, Some(expected_s)),
                        (&wait, Some(settle)),
                        (&clock, None),
                    ])?
                    .into_iter()
                    .skip(2);
                Some(clock_of(replies.next())?)
            }
            _ => {
                self.client.call_waiting(&set, expected_s)?;
                self.pause(settle)?;
                None
            }
        };
        // The move waited for its end: the commanded position is its target (spm-hal's
        // `position` is the commanded one), known without asking until the next command.
        self.readings = Readings {
            position: Some(request.target),
            clock_s,
            ..Readings::none(self.client.sequence())
        };
        Ok(())
    }
}

impl CoarseZStage for NanonisMicroscope {
    type Error = NanonisError;

    fn step(&mut self, steps: i64) -> Result<(), NanonisError> {
        let result = self.coarse_step(steps);
        self.noting_failure(result)
    }

    fn position_steps(&mut self) -> Result<i64, NanonisError> {
        Ok(self.coarse_steps)
    }
}

impl NanonisMicroscope {
    /// [`CoarseZStage::step`] (a failure is noted by the caller).
    fn coarse_step(&mut self, steps: i64) -> Result<(), NanonisError> {
        let Some(c) = self.config.coarse_z.clone() else {
            return Err(NanonisError::new(
                NanonisErrorKind::OutOfRange,
                "no coarse Z motor is configured",
            ));
        };
        let target = self.coarse_steps.saturating_add(steps);
        if target < c.min_steps || target > c.max_steps {
            return Err(NanonisError::new(
                NanonisErrorKind::OutOfRange,
                format!(
                    "coarse position {target} steps is outside [{}, {}]",
                    c.min_steps, c.max_steps
                ),
            ));
        }
        let approach = if c.approach == "z+" {
            motor_direction::Z_PLUS
        } else {
            motor_direction::Z_MINUS
        };
        let retract = if approach == motor_direction::Z_PLUS {
            motor_direction::Z_MINUS
        } else {
            motor_direction::Z_PLUS
        };
        let direction = if steps >= 0 { approach } else { retract };
        let mut left = steps.unsigned_abs();
        while left > 0 {
            let chunk = left.min(u64::from(u16::MAX)) as u16;
            self.client.call_waiting(
                &Request::MotorStartMove {
                    direction,
                    steps: chunk,
                    group: c.group,
                    wait: 1,
                },
                f64::from(chunk) * c.step_time_s,
            )?;
            left -= u64::from(chunk);
            let signed = if steps >= 0 {
                i64::from(chunk)
            } else {
                -i64::from(chunk)
            };
            self.coarse_steps += signed;
        }
        Ok(())
    }
}

impl Drop for NanonisMicroscope {
    /// Puts the controller's compensation back if the run did not (an error or an early
    /// stop): best effort on an open connection (a lost one is not reopened here, so that
    /// dropping never waits out the reconnect attempts), a failure is logged.
    fn drop(&mut self) {
        if self.found_compensation.is_none() {
            return;
        }
        if !self.client.is_connected() {
            tracing::error!(
                "nanonis: the connection is lost; the controller's compensation stays off"
            );
            return;
        }
        if let Err(e) = self.restore_compensation() {
            tracing::error!(
                error = %e,
                "nanonis: the controller's compensation could not be restored; it stays off"
            );
        }
    }
}
