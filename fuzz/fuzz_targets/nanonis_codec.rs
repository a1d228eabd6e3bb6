//! Fuzz target: the Nanonis TCP codec (spm-nanonis) on arbitrary bytes, both directions.
//! Byte 0 selects the schema (controller release before or after R5.1.14573); the next 40
//! bytes are a header, the rest a body. As a server: the request header is decoded and the
//! body decoded strictly for the command it names (or, when the header is invalid, for
//! every known command). As a client: the body is decoded as the reply of each request
//! this backend sends. Everything must return a value or a typed error, never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use spm_nanonis::codec::{HEADER_LEN, decode_request_header, decode_response_header};
use spm_nanonis::commands::{Request, ScanBuffer, ScanFrame, ScanProps, ScanSpeed, Schema};

const COMMANDS: [&str; 34] = [
    "Util.VersionGet",
    "Piezo.CalibrGet",
    "Piezo.RangeGet",
    "Piezo.DriftCompSet",
    "Piezo.DriftCompGet",
    "Piezo.TiltSet",
    "Piezo.TiltGet",
    "Piezo.HystOnOffSet",
    "Piezo.HystOnOffGet",
    "Scan.Action",
    "Scan.StatusGet",
    "Scan.WaitEndOfScan",
    "Scan.FrameSet",
    "Scan.FrameGet",
    "Scan.BufferSet",
    "Scan.BufferGet",
    "Scan.PropsSet",
    "Scan.PropsGet",
    "Scan.XYPosGet",
    "Scan.SpeedSet",
    "Scan.SpeedGet",
    "Scan.FrameDataGrab",
    "FolMe.XYPosSet",
    "FolMe.XYPosGet",
    "FolMe.SpeedSet",
    "FolMe.SpeedGet",
    "FolMe.Stop",
    "ZCtrl.ZPosGet",
    "ZCtrl.OnOffSet",
    "ZCtrl.OnOffGet",
    "Motor.StartMove",
    "Motor.StopMove",
    "Motor.FreqAmpGet",
    "Signals.ValsGet",
];

fn requests() -> Vec<Request> {
    let frame = ScanFrame {
        centre_x_m: 0.0,
        centre_y_m: 0.0,
        width_m: 1e-8,
        height_m: 1e-8,
        angle_deg: 0.0,
    };
    let speed = ScanSpeed {
        forward_speed_m_per_s: 1e-8,
        backward_speed_m_per_s: 1e-8,
        forward_line_s: 0.1,
        backward_line_s: 0.1,
        keep: 2,
        speed_ratio: 1.0,
    };
    vec![
        Request::UtilVersionGet,
        Request::PiezoCalibrGet,
        Request::PiezoDriftCompGet,
        Request::PiezoTiltGet,
        Request::PiezoHystOnOffGet,
        Request::ScanStatusGet,
        Request::ScanWaitEndOfScan { timeout_ms: 10 },
        Request::ScanFrameSet(frame),
        Request::ScanFrameGet,
        Request::ScanBufferSet(ScanBuffer {
            channels: vec![30],
            pixels: 16,
            lines: 16,
        }),
        Request::ScanBufferGet,
        Request::ScanPropsSet(ScanProps {
            continuous: 2,
            bouncy: 2,
            autosave: 3,
            series_name: String::new(),
            comment: String::new(),
            modules: Vec::new(),
            autopaste: None,
        }),
        Request::ScanSpeedSet(speed),
        Request::ScanSpeedGet,
        Request::ScanFrameDataGrab {
            channel: 30,
            forward: 1,
        },
        Request::FolMeXYPosGet { wait_newest: 0 },
        Request::ZCtrlZPosGet,
        Request::ScanPropsGet,
        Request::ScanXYPosGet { wait_newest: 1 },
        Request::FolMeSpeedGet,
        Request::MotorFreqAmpGet(3),
        Request::SignalsValsGet {
            indexes: vec![126, 127],
            wait_newest: 0,
        },
    ]
}

fuzz_target!(|data: &[u8]| {
    let Some((&selector, rest)) = data.split_first() else {
        return;
    };
    let schema = Schema::for_release(if selector & 1 == 0 { 14000 } else { 14718 });
    if rest.len() < HEADER_LEN {
        for name in COMMANDS {
            let _ = Request::decode(name, rest, schema);
        }
        return;
    }
    let mut header = [0u8; HEADER_LEN];
    header.copy_from_slice(&rest[..HEADER_LEN]);
    let body = &rest[HEADER_LEN..];
    match decode_request_header(&header) {
        Ok(h) => {
            if let Ok(request) = Request::decode(&h.command, body, schema) {
                // What decodes re-encodes to the same bytes (strings excepted: invalid
                // UTF-8 is replaced when decoded).
                let has_strings = matches!(request, Request::ScanPropsSet(_));
                if let (false, Ok(bytes)) = (has_strings, request.encode(schema)) {
                    assert_eq!(bytes, body, "{}", h.command);
                }
            }
        }
        Err(_) => {
            let name = COMMANDS[usize::from(selector >> 1) % COMMANDS.len()];
            let _ = Request::decode(name, body, schema);
        }
    }
    let _ = decode_response_header(&header);
    for request in requests() {
        let _ = request.decode_reply(body, schema);
    }
});
