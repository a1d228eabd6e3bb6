//! The commands this backend uses, as typed requests and replies, with their argument
//! schemas from the manual (section *Functions*). The same definitions encode on one side
//! and decode (strictly: exact body sizes, documented flag values) on the other, so the
//! client and the simulator server cannot disagree silently.
//!
//! Where a command's arguments differ across controller releases the [`Schema`] says
//! which form to use; it is chosen from `Util.VersionGet`'s host-application release.

use crate::codec::{CodecError, ErrorSection, Reader, Writer};

/// First host-application release whose `Scan.PropsSet` takes the *Autopaste* argument
/// (manual, Change Log R5.1.14573).
pub const PROPS_AUTOPASTE_RELEASE: u32 = 14573;

/// Argument forms that depend on the controller's release.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Schema {
    /// `Scan.PropsSet` ends with *Autopaste* (`unsigned int32`).
    pub props_set_autopaste: bool,
}

impl Schema {
    /// The schema of a host-application release.
    pub fn for_release(host_release: u32) -> Self {
        Self {
            props_set_autopaste: host_release >= PROPS_AUTOPASTE_RELEASE,
        }
    }
}

/// `Scan.Action` actions (manual: 0 = Start, 1 = Stop, 2 = Pause, 3 = Resume, 4 = Freeze,
/// 5 = Unfreeze, 6 = Go to Center).
pub mod scan_action {
    /// Start.
    pub const START: u16 = 0;
    /// Stop.
    pub const STOP: u16 = 1;
    /// Pause.
    pub const PAUSE: u16 = 2;
    /// Resume.
    pub const RESUME: u16 = 3;
    /// Largest documented action.
    pub const MAX: u16 = 6;
}

/// `Motor.StartMove` directions (0 = X+, …, 4 = Z+, 5 = Z−).
pub mod motor_direction {
    /// X+.
    pub const X_PLUS: u32 = 0;
    /// X−.
    pub const X_MINUS: u32 = 1;
    /// Y+.
    pub const Y_PLUS: u32 = 2;
    /// Y−.
    pub const Y_MINUS: u32 = 3;
    /// Z+.
    pub const Z_PLUS: u32 = 4;
    /// Z−.
    pub const Z_MINUS: u32 = 5;
}

/// A request this backend sends.
#[derive(Clone, Debug, PartialEq)]
#[non_exhaustive]
pub enum Request {
    /// `Util.VersionGet`.
    UtilVersionGet,
    /// `Piezo.CalibrGet`: low-voltage calibration, m/V.
    PiezoCalibrGet,
    /// `Piezo.RangeGet`: ranges, m.
    PiezoRangeGet,
    /// `Piezo.DriftCompSet`.
    PiezoDriftCompSet {
        /// 0 = no change, 1 = on, 2 = off.
        on_off: i32,
        /// Compensation speeds, m/s.
        v_m_per_s: [f32; 3],
        /// Saturation limit, % of the range.
        saturation_limit_percent: f32,
    },
    /// `Piezo.DriftCompGet`.
    PiezoDriftCompGet,
    /// `Piezo.TiltSet`.
    PiezoTiltSet {
        /// Tilt X, degrees.
        x_deg: f32,
        /// Tilt Y, degrees.
        y_deg: f32,
    },
    /// `Piezo.TiltGet`.
    PiezoTiltGet,
    /// `Piezo.HystOnOffSet` (0 = off, 1 = on).
    PiezoHystOnOffSet(u32),
    /// `Piezo.HystOnOffGet`.
    PiezoHystOnOffGet,
    /// `Scan.Action`.
    ScanAction {
        /// See [`scan_action`].
        action: u16,
        /// 1 = up, 0 = down.
        direction_up: u32,
    },
    /// `Scan.StatusGet`.
    ScanStatusGet,
    /// `Scan.WaitEndOfScan`.
    ScanWaitEndOfScan {
        /// Timeout, ms (−1 = forever).
        timeout_ms: i32,
    },
    /// `Scan.FrameSet`.
    ScanFrameSet(ScanFrame),
    /// `Scan.FrameGet`.
    ScanFrameGet,
    /// `Scan.BufferSet`.
    ScanBufferSet(ScanBuffer),
    /// `Scan.BufferGet`.
    ScanBufferGet,
    /// `Scan.PropsSet` (the form is given by the [`Schema`]).
    ScanPropsSet(ScanProps),
    /// `Scan.PropsGet` (the reply's form is given by the [`Schema`]).
    ScanPropsGet,
    /// `Scan.XYPosGet`: the X and Y signals, m.
    ScanXYPosGet {
        /// 1 = wait for newest data.
        wait_newest: u32,
    },
    /// `Scan.SpeedSet`.
    ScanSpeedSet(ScanSpeed),
    /// `Scan.SpeedGet`.
    ScanSpeedGet,
    /// `Scan.FrameDataGrab`.
    ScanFrameDataGrab {
        /// Channel index (one of the buffer's channels).
        channel: u32,
        /// 1 = forward, 0 = backward.
        forward: u32,
    },
    /// `FolMe.XYPosSet`.
    FolMeXYPosSet {
        /// Target X, m.
        x_m: f64,
        /// Target Y, m.
        y_m: f64,
        /// 1 = return at the end of the move.
        wait_end_of_move: u32,
    },
    /// `FolMe.XYPosGet`.
    FolMeXYPosGet {
        /// 1 = wait for newest data.
        wait_newest: u32,
    },
    /// `FolMe.SpeedSet`.
    FolMeSpeedSet {
        /// Speed, m/s.
        speed_m_per_s: f32,
        /// 1 = custom speed, 0 = scan speed.
        custom: u32,
    },
    /// `FolMe.SpeedGet`.
    FolMeSpeedGet,
    /// `FolMe.Stop`.
    FolMeStop,
    /// `ZCtrl.ZPosGet`.
    ZCtrlZPosGet,
    /// `ZCtrl.OnOffSet` (0 = off, 1 = on).
    ZCtrlOnOffSet(u32),
    /// `ZCtrl.OnOffGet`.
    ZCtrlOnOffGet,
    /// `Motor.StartMove`.
    MotorStartMove {
        /// See [`motor_direction`].
        direction: u32,
        /// Steps.
        steps: u16,
        /// Group (0 = group 1).
        group: u32,
        /// 1 = return when finished.
        wait: u32,
    },
    /// `Motor.StopMove`.
    MotorStopMove,
    /// `Motor.FreqAmpGet` (axis: 0 = default, 1 = X, 2 = Y, 3 = Z).
    MotorFreqAmpGet(u16),
    /// `Signals.ValsGet`.
    SignalsValsGet {
        /// Signal indexes (0–127).
        indexes: Vec<i32>,
        /// 1 = wait for newest data.
        wait_newest: u32,
    },
}

/// `Scan.FrameSet`/`FrameGet` arguments.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScanFrame {
    /// Centre X, m.
    pub centre_x_m: f32,
    /// Centre Y, m.
    pub centre_y_m: f32,
    /// Width, m.
    pub width_m: f32,
    /// Height, m.
    pub height_m: f32,
    /// Angle, degrees (positive = clockwise).
    pub angle_deg: f32,
}

/// `Scan.BufferSet`/`BufferGet` arguments.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanBuffer {
    /// Recorded channel indexes.
    pub channels: Vec<i32>,
    /// Pixels per line (the controller coerces to a multiple of 16).
    pub pixels: i32,
    /// Lines.
    pub lines: i32,
}

/// `Scan.PropsSet` arguments.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanProps {
    /// 0 = no change, 1 = on, 2 = off.
    pub continuous: u32,
    /// 0 = no change, 1 = on, 2 = off.
    pub bouncy: u32,
    /// 0 = no change, 1 = all, 2 = next, 3 = off.
    pub autosave: u32,
    /// Series name.
    pub series_name: String,
    /// Comment.
    pub comment: String,
    /// Modules whose parameters are saved in the file header.
    pub modules: Vec<String>,
    /// 0 = no change, 1 = all, 2 = next, 3 = off; `None` on releases without the argument.
    pub autopaste: Option<u32>,
}

/// `Scan.PropsGet` return arguments.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanPropsState {
    /// 0 = off, 1 = on.
    pub continuous: u32,
    /// 0 = off, 1 = on.
    pub bouncy: u32,
    /// 0 = all, 1 = next, 2 = off (not the coding of `Scan.PropsSet`).
    pub autosave: u32,
    /// Series name.
    pub series_name: String,
    /// Comment.
    pub comment: String,
    /// Modules whose parameters are saved in the file header.
    pub modules: Vec<String>,
    /// Number of parameters of each module.
    pub parameters_per_module: Vec<i32>,
    /// Rows of the parameters array (one per module with parameters).
    pub parameter_rows: usize,
    /// Columns of the parameters array.
    pub parameter_columns: usize,
    /// The parameters, row by row.
    pub parameters: Vec<String>,
    /// 0 = all, 1 = next, 2 = off (as autosave); `None` on releases without the argument.
    pub autopaste: Option<u32>,
}

/// `Scan.SpeedSet`/`SpeedGet` arguments.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScanSpeed {
    /// Forward linear speed, m/s.
    pub forward_speed_m_per_s: f32,
    /// Backward linear speed, m/s.
    pub backward_speed_m_per_s: f32,
    /// Forward time per line, s.
    pub forward_line_s: f32,
    /// Backward time per line, s.
    pub backward_line_s: f32,
    /// Set: 0 = no change, 1 = keep speed, 2 = keep time per line; Get: 0 = speed, 1 = time.
    pub keep: u16,
    /// Backward speed ÷ forward speed.
    pub speed_ratio: f32,
}

/// `Util.VersionGet` reply.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Version {
    /// "Nanonis SPM Control Software" or "Nanonis Tramea Software".
    pub product_line: String,
    /// e.g. "Generic 5".
    pub version: String,
    /// Host-application release.
    pub host_release: u32,
    /// RT-engine release.
    pub rt_release: u32,
}

/// `Piezo.DriftCompGet` reply.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriftComp {
    /// 1 = on.
    pub status: u32,
    /// Speeds, m/s.
    pub v_m_per_s: [f32; 3],
    /// Saturated X, Y, Z.
    pub saturated: [u32; 3],
    /// Saturation limit, %.
    pub saturation_limit_percent: f32,
}

/// `Scan.FrameDataGrab` reply.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameData {
    /// Channel name.
    pub channel_name: String,
    /// Rows (lines).
    pub rows: usize,
    /// Columns (pixels).
    pub columns: usize,
    /// Row-major data, in the channel's physical unit.
    pub data: Vec<f32>,
    /// 1 = up, 0 = down.
    pub direction_up: u32,
}

/// A reply's return arguments.
#[derive(Clone, Debug, PartialEq)]
#[non_exhaustive]
pub enum Reply {
    /// Only the error section.
    Empty,
    /// `Util.VersionGet`.
    Version(Version),
    /// Three `float32`s (`Piezo.CalibrGet`, `Piezo.RangeGet`).
    F32x3([f32; 3]),
    /// Two `float32`s (`Piezo.TiltGet`, `Motor.FreqAmpGet`).
    F32x2([f32; 2]),
    /// One `float32` (`ZCtrl.ZPosGet`).
    F32(f32),
    /// One `unsigned int32` (`*.OnOffGet`, `Scan.StatusGet`).
    U32(u32),
    /// `Piezo.DriftCompGet`.
    DriftComp(DriftComp),
    /// `Scan.WaitEndOfScan`.
    WaitEndOfScan {
        /// 1 = timed out.
        timed_out: u32,
        /// Auto-saved file path (empty when nothing was saved).
        file_path: String,
    },
    /// `Scan.FrameGet`.
    Frame(ScanFrame),
    /// `Scan.BufferGet`.
    Buffer(ScanBuffer),
    /// `Scan.SpeedGet`.
    Speed(ScanSpeed),
    /// `Scan.PropsGet`.
    Props(ScanPropsState),
    /// `FolMe.SpeedGet`.
    FolMeSpeed {
        /// Follow-Me speed, m/s.
        speed_m_per_s: f32,
        /// 1 = the custom speed is used, 0 = the scan speed.
        custom: u32,
    },
    /// `Scan.FrameDataGrab`.
    FrameData(FrameData),
    /// `FolMe.XYPosGet`.
    XY {
        /// X, m.
        x_m: f64,
        /// Y, m.
        y_m: f64,
    },
    /// `Signals.ValsGet`.
    Values(Vec<f32>),
}

fn flag(what: &'static str, v: u32, max: u32) -> Result<u32, CodecError> {
    if v > max {
        return Err(CodecError::InvalidValue {
            what,
            value: i64::from(v),
        });
    }
    Ok(v)
}

impl Request {
    /// The command name on the wire.
    pub fn name(&self) -> &'static str {
        match self {
            Self::UtilVersionGet => "Util.VersionGet",
            Self::PiezoCalibrGet => "Piezo.CalibrGet",
            Self::PiezoRangeGet => "Piezo.RangeGet",
            Self::PiezoDriftCompSet { .. } => "Piezo.DriftCompSet",
            Self::PiezoDriftCompGet => "Piezo.DriftCompGet",
            Self::PiezoTiltSet { .. } => "Piezo.TiltSet",
            Self::PiezoTiltGet => "Piezo.TiltGet",
            Self::PiezoHystOnOffSet(_) => "Piezo.HystOnOffSet",
            Self::PiezoHystOnOffGet => "Piezo.HystOnOffGet",
            Self::ScanAction { .. } => "Scan.Action",
            Self::ScanStatusGet => "Scan.StatusGet",
            Self::ScanWaitEndOfScan { .. } => "Scan.WaitEndOfScan",
            Self::ScanFrameSet(_) => "Scan.FrameSet",
            Self::ScanFrameGet => "Scan.FrameGet",
            Self::ScanBufferSet(_) => "Scan.BufferSet",
            Self::ScanBufferGet => "Scan.BufferGet",
            Self::ScanPropsSet(_) => "Scan.PropsSet",
            Self::ScanPropsGet => "Scan.PropsGet",
            Self::ScanXYPosGet { .. } => "Scan.XYPosGet",
            Self::ScanSpeedSet(_) => "Scan.SpeedSet",
            Self::ScanSpeedGet => "Scan.SpeedGet",
            Self::ScanFrameDataGrab { .. } => "Scan.FrameDataGrab",
            Self::FolMeXYPosSet { .. } => "FolMe.XYPosSet",
            Self::FolMeXYPosGet { .. } => "FolMe.XYPosGet",
            Self::FolMeSpeedSet { .. } => "FolMe.SpeedSet",
            Self::FolMeSpeedGet => "FolMe.SpeedGet",
            Self::FolMeStop => "FolMe.Stop",
            Self::ZCtrlZPosGet => "ZCtrl.ZPosGet",
            Self::ZCtrlOnOffSet(_) => "ZCtrl.OnOffSet",
            Self::ZCtrlOnOffGet => "ZCtrl.OnOffGet",
            Self::MotorStartMove { .. } => "Motor.StartMove",
            Self::MotorStopMove => "Motor.StopMove",
            Self::MotorFreqAmpGet(_) => "Motor.FreqAmpGet",
            Self::SignalsValsGet { .. } => "Signals.ValsGet",
        }
    }

    /// True when sending the request twice has the same effect as once (a read, or a
    /// setting).
    pub fn is_idempotent(&self) -> bool {
        !matches!(
            self,
            Self::ScanAction { .. }
                | Self::ScanWaitEndOfScan { .. }
                | Self::FolMeXYPosSet { .. }
                | Self::MotorStartMove { .. }
        )
    }

    /// True when the request may be sent again after a connection lost before its reply
    /// (it may or may not have been executed): idempotent requests; `FolMe.XYPosSet` (an
    /// absolute target: a second move ends where the first did); `Scan.WaitEndOfScan` (a
    /// second wait lengthens a pause, or returns at once after a scan); `Scan.Action` (a
    /// start restarts the scan from its first line, a stop stops). Never `Motor.StartMove`:
    /// its steps are relative.
    pub fn is_retry_safe(&self) -> bool {
        !matches!(self, Self::MotorStartMove { .. })
    }

    /// The body.
    pub fn encode(&self, schema: Schema) -> Result<Vec<u8>, CodecError> {
        let mut w = Writer::new();
        match self {
            Self::UtilVersionGet
            | Self::PiezoCalibrGet
            | Self::PiezoRangeGet
            | Self::PiezoDriftCompGet
            | Self::PiezoTiltGet
            | Self::PiezoHystOnOffGet
            | Self::ScanStatusGet
            | Self::ScanFrameGet
            | Self::ScanBufferGet
            | Self::ScanSpeedGet
            | Self::ScanPropsGet
            | Self::FolMeSpeedGet
            | Self::FolMeStop
            | Self::ZCtrlZPosGet
            | Self::ZCtrlOnOffGet
            | Self::MotorStopMove => {}
            Self::PiezoDriftCompSet {
                on_off,
                v_m_per_s,
                saturation_limit_percent,
            } => {
                w.i32(*on_off);
                w.f32_array(v_m_per_s);
                w.f32(*saturation_limit_percent);
            }
            Self::PiezoTiltSet { x_deg, y_deg } => {
                w.f32(*x_deg);
                w.f32(*y_deg);
            }
            Self::PiezoHystOnOffSet(v) | Self::ZCtrlOnOffSet(v) => w.u32(*v),
            Self::ScanAction {
                action,
                direction_up,
            } => {
                w.u16(*action);
                w.u32(*direction_up);
            }
            Self::ScanWaitEndOfScan { timeout_ms } => w.i32(*timeout_ms),
            Self::ScanFrameSet(f) => encode_frame(&mut w, f),
            Self::ScanBufferSet(b) => encode_buffer(&mut w, b)?,
            Self::ScanPropsSet(p) => {
                w.u32(p.continuous);
                w.u32(p.bouncy);
                w.u32(p.autosave);
                w.string(&p.series_name)?;
                w.string(&p.comment)?;
                // The vendor client's encoding of the size field (see `codec`).
                w.string_array_vendor(&p.modules)?;
                match (schema.props_set_autopaste, p.autopaste) {
                    (true, Some(a)) => w.u32(a),
                    (false, None) => {}
                    (true, None) | (false, Some(_)) => {
                        return Err(CodecError::Encode {
                            what: "Scan.PropsSet",
                            reason:
                                "the Autopaste argument does not match the controller's release"
                                    .into(),
                        });
                    }
                }
            }
            Self::ScanSpeedSet(s) => encode_speed(&mut w, s),
            Self::ScanFrameDataGrab { channel, forward } => {
                w.u32(*channel);
                w.u32(*forward);
            }
            Self::FolMeXYPosSet {
                x_m,
                y_m,
                wait_end_of_move,
            } => {
                w.f64(*x_m);
                w.f64(*y_m);
                w.u32(*wait_end_of_move);
            }
            Self::FolMeXYPosGet { wait_newest } | Self::ScanXYPosGet { wait_newest } => {
                w.u32(*wait_newest)
            }
            Self::FolMeSpeedSet {
                speed_m_per_s,
                custom,
            } => {
                w.f32(*speed_m_per_s);
                w.u32(*custom);
            }
            Self::MotorStartMove {
                direction,
                steps,
                group,
                wait,
            } => {
                w.u32(*direction);
                w.u16(*steps);
                w.u32(*group);
                w.u32(*wait);
            }
            Self::MotorFreqAmpGet(axis) => w.u16(*axis),
            Self::SignalsValsGet {
                indexes,
                wait_newest,
            } => {
                w.i32(
                    i32::try_from(indexes.len()).map_err(|_| CodecError::Encode {
                        what: "signal indexes",
                        reason: "too many".into(),
                    })?,
                );
                w.i32_array(indexes);
                w.u32(*wait_newest);
            }
        }
        Ok(w.into_bytes())
    }

    /// Decodes a request body strictly (the server side): the body must be exactly the
    /// command's arguments under `schema`, flags within their documented values.
    pub fn decode(command: &str, body: &[u8], schema: Schema) -> Result<Self, CodecError> {
        let mut r = Reader::new(body);
        let request = match command {
            "Util.VersionGet" => Self::UtilVersionGet,
            "Piezo.CalibrGet" => Self::PiezoCalibrGet,
            "Piezo.RangeGet" => Self::PiezoRangeGet,
            "Piezo.DriftCompGet" => Self::PiezoDriftCompGet,
            "Piezo.TiltGet" => Self::PiezoTiltGet,
            "Piezo.HystOnOffGet" => Self::PiezoHystOnOffGet,
            "Scan.StatusGet" => Self::ScanStatusGet,
            "Scan.FrameGet" => Self::ScanFrameGet,
            "Scan.BufferGet" => Self::ScanBufferGet,
            "Scan.SpeedGet" => Self::ScanSpeedGet,
            "Scan.PropsGet" => Self::ScanPropsGet,
            "FolMe.SpeedGet" => Self::FolMeSpeedGet,
            "FolMe.Stop" => Self::FolMeStop,
            "ZCtrl.ZPosGet" => Self::ZCtrlZPosGet,
            "ZCtrl.OnOffGet" => Self::ZCtrlOnOffGet,
            "Motor.StopMove" => Self::MotorStopMove,
            "Piezo.DriftCompSet" => {
                let on_off = r.i32("compensation on/off")?;
                if !(0..=2).contains(&on_off) {
                    return Err(CodecError::InvalidValue {
                        what: "compensation on/off",
                        value: i64::from(on_off),
                    });
                }
                let v = [r.f32("vx")?, r.f32("vy")?, r.f32("vz")?];
                Self::PiezoDriftCompSet {
                    on_off,
                    v_m_per_s: v,
                    saturation_limit_percent: r.f32("saturation limit")?,
                }
            }
            "Piezo.TiltSet" => Self::PiezoTiltSet {
                x_deg: r.f32("tilt x")?,
                y_deg: r.f32("tilt y")?,
            },
            "Piezo.HystOnOffSet" => Self::PiezoHystOnOffSet(flag("on/off", r.u32("on/off")?, 1)?),
            "ZCtrl.OnOffSet" => Self::ZCtrlOnOffSet(flag("status", r.u32("status")?, 1)?),
            "Scan.Action" => {
                let action = r.u16("scan action")?;
                if action > scan_action::MAX {
                    return Err(CodecError::InvalidValue {
                        what: "scan action",
                        value: i64::from(action),
                    });
                }
                Self::ScanAction {
                    action,
                    direction_up: flag("scan direction", r.u32("scan direction")?, 1)?,
                }
            }
            "Scan.WaitEndOfScan" => Self::ScanWaitEndOfScan {
                timeout_ms: r.i32("timeout")?,
            },
            "Scan.FrameSet" => Self::ScanFrameSet(decode_frame(&mut r)?),
            "Scan.BufferSet" => Self::ScanBufferSet(decode_buffer(&mut r)?),
            "Scan.PropsSet" => {
                let continuous = flag("continuous scan", r.u32("continuous scan")?, 2)?;
                let bouncy = flag("bouncy scan", r.u32("bouncy scan")?, 2)?;
                let autosave = flag("autosave", r.u32("autosave")?, 3)?;
                let series_name = r.string("series name")?;
                let comment = r.string("comment")?;
                let modules = r.string_array("modules names")?;
                let autopaste = if schema.props_set_autopaste {
                    Some(flag("autopaste", r.u32("autopaste")?, 3)?)
                } else {
                    None
                };
                Self::ScanPropsSet(ScanProps {
                    continuous,
                    bouncy,
                    autosave,
                    series_name,
                    comment,
                    modules,
                    autopaste,
                })
            }
            "Scan.SpeedSet" => {
                let s = decode_speed(&mut r)?;
                if s.keep > 2 {
                    return Err(CodecError::InvalidValue {
                        what: "keep parameter constant",
                        value: i64::from(s.keep),
                    });
                }
                Self::ScanSpeedSet(s)
            }
            "Scan.FrameDataGrab" => Self::ScanFrameDataGrab {
                channel: r.u32("channel index")?,
                forward: flag("data direction", r.u32("data direction")?, 1)?,
            },
            "FolMe.XYPosSet" => Self::FolMeXYPosSet {
                x_m: r.f64("x")?,
                y_m: r.f64("y")?,
                wait_end_of_move: flag("wait end of move", r.u32("wait end of move")?, 1)?,
            },
            "Scan.XYPosGet" => Self::ScanXYPosGet {
                wait_newest: flag("wait for newest data", r.u32("wait for newest data")?, 1)?,
            },
            "FolMe.XYPosGet" => Self::FolMeXYPosGet {
                wait_newest: flag("wait for newest data", r.u32("wait for newest data")?, 1)?,
            },
            "FolMe.SpeedSet" => Self::FolMeSpeedSet {
                speed_m_per_s: r.f32("speed")?,
                custom: flag("custom speed", r.u32("custom speed")?, 1)?,
            },
            "Motor.StartMove" => Self::MotorStartMove {
                direction: flag("direction", r.u32("direction")?, 5)?,
                steps: r.u16("number of steps")?,
                group: flag("group", r.u32("group")?, 5)?,
                wait: flag("wait until finished", r.u32("wait until finished")?, 1)?,
            },
            "Motor.FreqAmpGet" => {
                let axis = r.u16("axis")?;
                if axis > 3 {
                    return Err(CodecError::InvalidValue {
                        what: "axis",
                        value: i64::from(axis),
                    });
                }
                Self::MotorFreqAmpGet(axis)
            }
            "Signals.ValsGet" => {
                let n = r.count("signals indexes size", 4)?;
                let indexes = r.i32_array("signals indexes", n)?;
                Self::SignalsValsGet {
                    indexes,
                    wait_newest: flag("wait for newest data", r.u32("wait for newest data")?, 1)?,
                }
            }
            other => return Err(CodecError::UnknownCommand(other.to_owned())),
        };
        r.finish(command)?;
        Ok(request)
    }

    /// Decodes the reply body to this request: its return arguments and the error section;
    /// the body must be consumed exactly.
    pub fn decode_reply(
        &self,
        body: &[u8],
        schema: Schema,
    ) -> Result<(Reply, ErrorSection), CodecError> {
        let mut r = Reader::new(body);
        let reply = match self {
            Self::UtilVersionGet => {
                let product_line = r.string("product line")?;
                let version = r.string("version")?;
                Reply::Version(Version {
                    product_line,
                    version,
                    host_release: r.u32("host release")?,
                    rt_release: r.u32("RT release")?,
                })
            }
            Self::PiezoCalibrGet | Self::PiezoRangeGet => {
                Reply::F32x3([r.f32("x")?, r.f32("y")?, r.f32("z")?])
            }
            Self::PiezoTiltGet | Self::MotorFreqAmpGet(_) | Self::ScanXYPosGet { .. } => {
                Reply::F32x2([r.f32("first")?, r.f32("second")?])
            }
            Self::FolMeSpeedGet => Reply::FolMeSpeed {
                speed_m_per_s: r.f32("speed")?,
                custom: r.u32("custom speed")?,
            },
            Self::ScanPropsGet => Reply::Props(decode_props(&mut r, schema)?),
            Self::ZCtrlZPosGet => Reply::F32(r.f32("z position")?),
            Self::PiezoHystOnOffGet | Self::ScanStatusGet | Self::ZCtrlOnOffGet => {
                Reply::U32(r.u32("status")?)
            }
            Self::PiezoDriftCompGet => Reply::DriftComp(DriftComp {
                status: r.u32("compensation status")?,
                v_m_per_s: [r.f32("vx")?, r.f32("vy")?, r.f32("vz")?],
                saturated: [
                    r.u32("x saturated")?,
                    r.u32("y saturated")?,
                    r.u32("z saturated")?,
                ],
                saturation_limit_percent: r.f32("saturation limit")?,
            }),
            Self::ScanWaitEndOfScan { .. } => Reply::WaitEndOfScan {
                timed_out: r.u32("timeout status")?,
                file_path: r.string_u32("file path")?,
            },
            Self::ScanFrameGet => Reply::Frame(decode_frame(&mut r)?),
            Self::ScanBufferGet => Reply::Buffer(decode_buffer(&mut r)?),
            Self::ScanSpeedGet => Reply::Speed(decode_speed(&mut r)?),
            Self::ScanFrameDataGrab { .. } => {
                let channel_name = r.string("channel name")?;
                let (rows, columns, data) = r.f32_2d("scan data")?;
                Reply::FrameData(FrameData {
                    channel_name,
                    rows,
                    columns,
                    data,
                    direction_up: r.u32("scan direction")?,
                })
            }
            Self::FolMeXYPosGet { .. } => Reply::XY {
                x_m: r.f64("x")?,
                y_m: r.f64("y")?,
            },
            Self::SignalsValsGet { .. } => {
                let n = r.count("signals values size", 4)?;
                Reply::Values(r.f32_array("signals values", n)?)
            }
            Self::PiezoDriftCompSet { .. }
            | Self::PiezoTiltSet { .. }
            | Self::PiezoHystOnOffSet(_)
            | Self::ScanAction { .. }
            | Self::ScanFrameSet(_)
            | Self::ScanBufferSet(_)
            | Self::ScanPropsSet(_)
            | Self::ScanSpeedSet(_)
            | Self::FolMeXYPosSet { .. }
            | Self::FolMeSpeedSet { .. }
            | Self::FolMeStop
            | Self::ZCtrlOnOffSet(_)
            | Self::MotorStartMove { .. }
            | Self::MotorStopMove => Reply::Empty,
        };
        let error = ErrorSection::decode(&mut r)?;
        r.finish(self.name())?;
        Ok((reply, error))
    }

    /// The reply a server sends with an error: the return arguments at their neutral
    /// values (the manual places the error section after them in every response).
    pub fn neutral_reply(&self, schema: Schema) -> Reply {
        match self {
            Self::UtilVersionGet => Reply::Version(Version {
                product_line: String::new(),
                version: String::new(),
                host_release: 0,
                rt_release: 0,
            }),
            Self::PiezoCalibrGet | Self::PiezoRangeGet => Reply::F32x3([0.0; 3]),
            Self::PiezoTiltGet | Self::MotorFreqAmpGet(_) | Self::ScanXYPosGet { .. } => {
                Reply::F32x2([0.0; 2])
            }
            Self::FolMeSpeedGet => Reply::FolMeSpeed {
                speed_m_per_s: 0.0,
                custom: 0,
            },
            Self::ScanPropsGet => Reply::Props(ScanPropsState {
                continuous: 0,
                bouncy: 0,
                autosave: 0,
                series_name: String::new(),
                comment: String::new(),
                modules: Vec::new(),
                parameters_per_module: Vec::new(),
                parameter_rows: 0,
                parameter_columns: 0,
                parameters: Vec::new(),
                autopaste: schema.props_set_autopaste.then_some(0),
            }),
            Self::ZCtrlZPosGet => Reply::F32(0.0),
            Self::PiezoHystOnOffGet | Self::ScanStatusGet | Self::ZCtrlOnOffGet => Reply::U32(0),
            Self::PiezoDriftCompGet => Reply::DriftComp(DriftComp {
                status: 0,
                v_m_per_s: [0.0; 3],
                saturated: [0; 3],
                saturation_limit_percent: 0.0,
            }),
            Self::ScanWaitEndOfScan { .. } => Reply::WaitEndOfScan {
                timed_out: 0,
                file_path: String::new(),
            },
            Self::ScanFrameGet => Reply::Frame(ScanFrame {
                centre_x_m: 0.0,
                centre_y_m: 0.0,
                width_m: 0.0,
                height_m: 0.0,
                angle_deg: 0.0,
            }),
            Self::ScanBufferGet => Reply::Buffer(ScanBuffer {
                channels: Vec::new(),
                pixels: 0,
                lines: 0,
            }),
            Self::ScanSpeedGet => Reply::Speed(ScanSpeed {
                forward_speed_m_per_s: 0.0,
                backward_speed_m_per_s: 0.0,
                forward_line_s: 0.0,
                backward_line_s: 0.0,
                keep: 0,
                speed_ratio: 0.0,
            }),
            Self::ScanFrameDataGrab { .. } => Reply::FrameData(FrameData {
                channel_name: String::new(),
                rows: 0,
                columns: 0,
                data: Vec::new(),
                direction_up: 0,
            }),
            Self::FolMeXYPosGet { .. } => Reply::XY { x_m: 0.0, y_m: 0.0 },
            Self::SignalsValsGet { .. } => Reply::Values(Vec::new()),
            _ => Reply::Empty,
        }
    }
}

impl Reply {
    /// Encodes the return arguments followed by the error section.
    pub fn encode(&self, error: &ErrorSection) -> Result<Vec<u8>, CodecError> {
        let mut w = Writer::new();
        match self {
            Self::Empty => {}
            Self::Version(v) => {
                w.string(&v.product_line)?;
                w.string(&v.version)?;
                w.u32(v.host_release);
                w.u32(v.rt_release);
            }
            Self::F32x3(v) => w.f32_array(v),
            Self::F32x2(v) => w.f32_array(v),
            Self::F32(v) => w.f32(*v),
            Self::U32(v) => w.u32(*v),
            Self::DriftComp(d) => {
                w.u32(d.status);
                w.f32_array(&d.v_m_per_s);
                for s in d.saturated {
                    w.u32(s);
                }
                w.f32(d.saturation_limit_percent);
            }
            Self::WaitEndOfScan {
                timed_out,
                file_path,
            } => {
                w.u32(*timed_out);
                w.u32(
                    u32::try_from(file_path.len()).map_err(|_| CodecError::Encode {
                        what: "file path",
                        reason: "too long".into(),
                    })?,
                );
                w.raw_string(file_path);
            }
            Self::Frame(f) => encode_frame(&mut w, f),
            Self::Buffer(b) => encode_buffer(&mut w, b)?,
            Self::Speed(s) => encode_speed(&mut w, s),
            Self::Props(p) => {
                w.u32(p.continuous);
                w.u32(p.bouncy);
                w.u32(p.autosave);
                w.string(&p.series_name)?;
                w.string(&p.comment)?;
                w.string_array(&p.modules)?;
                w.i32(len_i32(
                    "parameters per module",
                    p.parameters_per_module.len(),
                )?);
                w.i32_array(&p.parameters_per_module);
                w.string_2d(p.parameter_rows, p.parameter_columns, &p.parameters)?;
                if let Some(a) = p.autopaste {
                    w.u32(a);
                }
            }
            Self::FolMeSpeed {
                speed_m_per_s,
                custom,
            } => {
                w.f32(*speed_m_per_s);
                w.u32(*custom);
            }
            Self::FrameData(d) => {
                w.string(&d.channel_name)?;
                w.f32_2d(d.rows, d.columns, &d.data)?;
                w.u32(d.direction_up);
            }
            Self::XY { x_m, y_m } => {
                w.f64(*x_m);
                w.f64(*y_m);
            }
            Self::Values(v) => {
                w.i32(i32::try_from(v.len()).map_err(|_| CodecError::Encode {
                    what: "signal values",
                    reason: "too many".into(),
                })?);
                w.f32_array(v);
            }
        }
        error.encode(&mut w)?;
        Ok(w.into_bytes())
    }
}

fn len_i32(what: &'static str, n: usize) -> Result<i32, CodecError> {
    i32::try_from(n).map_err(|_| CodecError::Encode {
        what,
        reason: "too many".into(),
    })
}

fn decode_props(r: &mut Reader<'_>, schema: Schema) -> Result<ScanPropsState, CodecError> {
    let continuous = r.u32("continuous scan")?;
    let bouncy = r.u32("bouncy scan")?;
    let autosave = r.u32("autosave")?;
    let series_name = r.string("series name")?;
    let comment = r.string("comment")?;
    let modules = r.string_array("modules names")?;
    let n = r.count("parameters per module size", 4)?;
    let parameters_per_module = r.i32_array("parameters per module", n)?;
    let (parameter_rows, parameter_columns, parameters) = r.string_2d("parameters")?;
    let autopaste = if schema.props_set_autopaste {
        Some(r.u32("autopaste")?)
    } else {
        None
    };
    Ok(ScanPropsState {
        continuous,
        bouncy,
        autosave,
        series_name,
        comment,
        modules,
        parameters_per_module,
        parameter_rows,
        parameter_columns,
        parameters,
        autopaste,
    })
}

fn encode_frame(w: &mut Writer, f: &ScanFrame) {
    w.f32_array(&[
        f.centre_x_m,
        f.centre_y_m,
        f.width_m,
        f.height_m,
        f.angle_deg,
    ]);
}

fn decode_frame(r: &mut Reader<'_>) -> Result<ScanFrame, CodecError> {
    Ok(ScanFrame {
        centre_x_m: r.f32("centre x")?,
        centre_y_m: r.f32("centre y")?,
        width_m: r.f32("width")?,
        height_m: r.f32("height")?,
        angle_deg: r.f32("angle")?,
    })
}

fn encode_buffer(w: &mut Writer, b: &ScanBuffer) -> Result<(), CodecError> {
    w.i32(
        i32::try_from(b.channels.len()).map_err(|_| CodecError::Encode {
            what: "channel indexes",
            reason: "too many".into(),
        })?,
    );
    w.i32_array(&b.channels);
    w.i32(b.pixels);
    w.i32(b.lines);
    Ok(())
}

fn decode_buffer(r: &mut Reader<'_>) -> Result<ScanBuffer, CodecError> {
    let n = r.count("number of channels", 4)?;
    Ok(ScanBuffer {
        channels: r.i32_array("channel indexes", n)?,
        pixels: r.i32("pixels")?,
        lines: r.i32("lines")?,
    })
}

fn encode_speed(w: &mut Writer, s: &ScanSpeed) {
    w.f32(s.forward_speed_m_per_s);
    w.f32(s.backward_speed_m_per_s);
    w.f32(s.forward_line_s);
    w.f32(s.backward_line_s);
    w.u16(s.keep);
    w.f32(s.speed_ratio);
}

fn decode_speed(r: &mut Reader<'_>) -> Result<ScanSpeed, CodecError> {
    Ok(ScanSpeed {
        forward_speed_m_per_s: r.f32("forward speed")?,
        backward_speed_m_per_s: r.f32("backward speed")?,
        forward_line_s: r.f32("forward time per line")?,
        backward_line_s: r.f32("backward time per line")?,
        keep: r.u16("keep parameter constant")?,
        speed_ratio: r.f32("speed ratio")?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn schemas() -> [Schema; 2] {
        [Schema::for_release(14000), Schema::for_release(14718)]
    }

    fn check_round_trip(request: Request, schema: Schema) {
        let body = request.encode(schema).expect("encodes");
        let back = Request::decode(request.name(), &body, schema).expect("decodes");
        assert_eq!(back, request);
        let reply = request.neutral_reply(schema);
        let bytes = reply.encode(&ErrorSection::error("x")).expect("encodes");
        let (decoded, error) = request.decode_reply(&bytes, schema).expect("reply decodes");
        assert_eq!(decoded, reply, "{}", request.name());
        assert_eq!(error, ErrorSection::error("x"));
    }

    #[test]
    fn every_request_round_trips_under_both_schemas() {
        for schema in schemas() {
            let props = ScanProps {
                continuous: 2,
                bouncy: 2,
                autosave: 3,
                series_name: "s".into(),
                comment: "".into(),
                modules: vec!["Z-Controller".into(), "Bias".into()],
                autopaste: schema.props_set_autopaste.then_some(3),
            };
            for request in [
                Request::UtilVersionGet,
                Request::PiezoCalibrGet,
                Request::PiezoDriftCompSet {
                    on_off: 2,
                    v_m_per_s: [0.0; 3],
                    saturation_limit_percent: 10.0,
                },
                Request::ScanAction {
                    action: scan_action::START,
                    direction_up: 1,
                },
                Request::ScanWaitEndOfScan { timeout_ms: 1500 },
                Request::ScanBufferSet(ScanBuffer {
                    channels: vec![30],
                    pixels: 64,
                    lines: 12,
                }),
                Request::ScanPropsSet(props),
                Request::ScanFrameDataGrab {
                    channel: 30,
                    forward: 1,
                },
                Request::FolMeXYPosSet {
                    x_m: 1e-8,
                    y_m: -2e-8,
                    wait_end_of_move: 1,
                },
                Request::MotorStartMove {
                    direction: motor_direction::Z_MINUS,
                    steps: 10,
                    group: 0,
                    wait: 1,
                },
                Request::SignalsValsGet {
                    indexes: vec![126, 127],
                    wait_newest: 0,
                },
                Request::ScanPropsGet,
                Request::ScanXYPosGet { wait_newest: 1 },
                Request::FolMeSpeedGet,
            ] {
                check_round_trip(request, schema);
            }
        }
    }

    /// The body of `Scan.PropsSet` as the vendor's Python client (`nanonis-spm` 1.0.9)
    /// builds it: `handleArrayString` writes `4 × count` as the modules' size field.
    fn vendor_props_set(modules: &[&str], size_field: i32) -> Vec<u8> {
        let mut body = Vec::new();
        for v in [2u32, 2, 3] {
            body.extend_from_slice(&v.to_be_bytes());
        }
        for s in ["series", ""] {
            body.extend_from_slice(&(s.len() as i32).to_be_bytes());
            body.extend_from_slice(s.as_bytes());
        }
        body.extend_from_slice(&size_field.to_be_bytes());
        body.extend_from_slice(&(modules.len() as i32).to_be_bytes());
        for m in modules {
            body.extend_from_slice(&(m.len() as i32).to_be_bytes());
            body.extend_from_slice(m.as_bytes());
        }
        body.extend_from_slice(&3u32.to_be_bytes());
        body
    }

    #[test]
    fn props_set_module_lists_use_the_vendor_clients_size_field() {
        let schema = Schema::for_release(14718);
        let modules = ["Z-Controller", "Bias"];
        let expected = Request::ScanPropsSet(ScanProps {
            continuous: 2,
            bouncy: 2,
            autosave: 3,
            series_name: "series".into(),
            comment: String::new(),
            modules: modules.iter().map(|m| (*m).to_owned()).collect(),
            autopaste: Some(3),
        });
        // What the vendor sends, byte for byte, is what this client sends.
        let vendor = vendor_props_set(&modules, 4 * 2);
        assert_eq!(expected.encode(schema).expect("encodes"), vendor);
        assert_eq!(
            Request::decode("Scan.PropsSet", &vendor, schema).expect("vendor form"),
            expected
        );
        // The manual's literal reading (the bytes the elements occupy) is accepted too.
        let exact = (4 + 12) + (4 + 4);
        assert_eq!(
            Request::decode("Scan.PropsSet", &vendor_props_set(&modules, exact), schema)
                .expect("exact form"),
            expected
        );
        // Any other size is refused, by name.
        for bad in [0, 7, exact + 4, -8] {
            assert!(
                matches!(
                    Request::decode("Scan.PropsSet", &vendor_props_set(&modules, bad), schema),
                    Err(CodecError::InvalidSize {
                        what: "modules names",
                        ..
                    })
                ),
                "size field {bad}"
            );
        }
    }

    #[test]
    fn props_get_replies_carry_the_exact_byte_total_the_vendor_client_advances_by() {
        let schema = Schema::for_release(14718);
        let reply = Reply::Props(ScanPropsState {
            continuous: 0,
            bouncy: 1,
            autosave: 2,
            series_name: "img".into(),
            comment: "c".into(),
            modules: vec!["Z-Controller".into(), "Bias".into()],
            parameters_per_module: vec![0, 0],
            parameter_rows: 0,
            parameter_columns: 0,
            parameters: Vec::new(),
            autopaste: Some(2),
        });
        let bytes = reply.encode(&ErrorSection::ok()).expect("encodes");
        // continuous, bouncy, autosave, "img", "c", then the modules' size field.
        let at = 12 + 4 + 3 + 4 + 1;
        let size = i32::from_be_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]);
        assert_eq!(size, (4 + 12) + (4 + 4));
        let (decoded, error) = Request::ScanPropsGet
            .decode_reply(&bytes, schema)
            .expect("decodes");
        assert_eq!(decoded, reply);
        assert_eq!(error, ErrorSection::ok());
    }

    #[test]
    fn a_props_set_of_the_wrong_release_is_refused_by_size() {
        let old = Schema::for_release(14000);
        let new = Schema::for_release(14573);
        let request = Request::ScanPropsSet(ScanProps {
            continuous: 2,
            bouncy: 2,
            autosave: 3,
            series_name: String::new(),
            comment: String::new(),
            modules: Vec::new(),
            autopaste: None,
        });
        let body = request.encode(old).expect("encodes for the old release");
        assert!(matches!(
            Request::decode("Scan.PropsSet", &body, new),
            Err(CodecError::Truncated { .. })
        ));
        assert!(request.encode(new).is_err());
    }

    #[test]
    fn flags_outside_their_documented_values_are_refused() {
        let mut w = Writer::new();
        w.u16(7);
        w.u32(1);
        assert!(matches!(
            Request::decode("Scan.Action", &w.into_bytes(), Schema::for_release(14718)),
            Err(CodecError::InvalidValue { .. })
        ));
        assert!(matches!(
            Request::decode("Bias.Set", &[], Schema::for_release(14718)),
            Err(CodecError::UnknownCommand(_))
        ));
    }
}
