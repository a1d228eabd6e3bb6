//! The vendor-client conformance harness (issue 26): starts `nanonis-sim` over
//! `configs/sim-hopg.toml` on a free port, runs `conformance/vendor_client.py` (the
//! vendor's own Python client through a scripted session) and answers its questions about
//! the truth — the simulator's clock, position and Z, the calibration, and every frame as
//! spm-nanonis's strict decoder reads it — one line at a time over the script's
//! stdin/stdout.
//!
//! ```text
//! cargo run -p spm-nanonis-sim --example vendor_conformance -- PYTHON [SCRIPT [CAPTURE]]
//! ```
//!
//! With `CAPTURE`, the script also writes the frames the vendor client exchanged (the
//! fixture `tests/data/vendor_session.txt` of `tests/it/vendor_frames.rs` was made so).
//!
//! `PYTHON` must have `nanonis-spm` and `numpy` (`.ci/run` makes a venv in
//! `target/venv`). Exit status: 0 when every command interoperates.

use spm_hal::Microscope;
use spm_nanonis::commands::{Reply, Request};
use spm_nanonis::{Client, ClientConfig, LOW_VOLTAGE_SPAN_V, metres_per_count};
use spm_nanonis_sim::server::ServerHandle;
use spm_nanonis_sim::{Server, ServerConfig, SocketFaults};
use spm_sim::SimConfig;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

struct Truth {
    server: ServerHandle,
    client: Client,
    calibration: [f32; 3],
    lateral_m_per_count: f64,
    z_m_per_count: f64,
    motor_step_s: f64,
}

impl Truth {
    fn answer(&mut self, question: &str) -> Result<String, String> {
        let words: Vec<&str> = question.split_whitespace().collect();
        match words.as_slice() {
            ["calibration"] => Ok(self
                .calibration
                .iter()
                .map(|c| format!("{c:e}"))
                .collect::<Vec<_>>()
                .join(" ")),
            ["now"] => Ok(format!(
                "{:e}",
                self.server.with_simulator(|s| s.oracle().now().value())
            )),
            ["position"] => {
                // The commanded position, read from a copy (a read changes nothing).
                let p = self
                    .server
                    .with_simulator(|s| s.clone().position())
                    .map_err(|e| e.to_string())?;
                Ok(format!(
                    "{:e} {:e}",
                    p.x.value() * self.lateral_m_per_count,
                    p.y.value() * self.lateral_m_per_count
                ))
            }
            ["z"] => Ok(format!(
                "{:e}",
                self.server.with_simulator(|s| s.oracle().z_now().value()) * self.z_m_per_count
            )),
            ["motor_step_time"] => Ok(format!("{:e}", self.motor_step_s)),
            ["grab", forward] => {
                let forward: u32 = forward.parse().map_err(|_| format!("{question:?}"))?;
                match self
                    .client
                    .call(&Request::ScanFrameDataGrab {
                        channel: 30,
                        forward,
                    })
                    .map_err(|e| e.to_string())?
                {
                    Reply::FrameData(d) => {
                        let mut line = format!("{} {} {}", d.rows, d.columns, d.direction_up);
                        for v in &d.data {
                            // Shortest round-trip float32 text: Python reads the same value.
                            line.push_str(&format!(" {v:?}"));
                        }
                        Ok(line)
                    }
                    other => Err(format!("unexpected reply {other:?}")),
                }
            }
            _ => Err(format!("unknown question {question:?}")),
        }
    }
}

fn run(python: &str, script: &Path, capture: Option<&Path>) -> Result<bool, String> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut sim = SimConfig::from_file(root.join("../../configs/sim-hopg.toml"))
        .map_err(|e| e.to_string())?
        .without_random_faults();
    sim.measurement.quantise_lateral_dac = false;
    let motor_step_s = sim
        .instrument
        .coarse_z
        .as_ref()
        .map_or(0.0, |c| c.step_time_s);
    let config = ServerConfig::new(SocketFaults::none());
    let bits = 16;
    let cal = |nm: f64| (nm * 1e-9 * 2f64.powi(bits) / LOW_VOLTAGE_SPAN_V) as f32;
    let calibration = [
        cal(config.lateral_nm_per_count),
        cal(config.lateral_nm_per_count),
        cal(config.z_nm_per_count),
    ];
    let server = Server::bind("127.0.0.1:0", sim, config)
        .and_then(Server::spawn)
        .map_err(|e| e.to_string())?;
    let port = server.addr().port();
    let client = Client::connect(ClientConfig {
        host: "127.0.0.1".into(),
        port,
        connect_timeout_s: 2.0,
        command_timeout_s: 30.0,
        wait_margin_s: 5.0,
        reconnect_attempts: 0,
        reconnect_backoff_s: 0.05,
    })
    .map_err(|e| e.to_string())?;
    let mut truth = Truth {
        server,
        client,
        calibration,
        lateral_m_per_count: metres_per_count(f64::from(calibration[0]), bits as u32),
        z_m_per_count: metres_per_count(f64::from(calibration[2]), bits as u32),
        motor_step_s,
    };
    eprintln!(
        "nanonis-sim on 127.0.0.1:{port}; running {}",
        script.display()
    );
    let mut command = Command::new(python);
    command.arg(script).arg("--port").arg(port.to_string());
    if let Some(capture) = capture {
        command.arg("--capture").arg(capture);
    }
    let mut child = command
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .map_err(|e| format!("cannot run {python}: {e}"))?;
    let (Some(mut to_script), Some(from_script)) = (child.stdin.take(), child.stdout.take()) else {
        return Err("no pipes to the script".into());
    };
    // A session takes seconds; one that hangs (the vendor client waits up to 1000 s for a
    // reply) is ended after two minutes, by its process id.
    let finished = Arc::new(AtomicBool::new(false));
    let watchdog = {
        let finished = Arc::clone(&finished);
        let pid = child.id();
        std::thread::spawn(move || {
            for _ in 0..1200 {
                std::thread::sleep(Duration::from_millis(100));
                if finished.load(Ordering::SeqCst) {
                    return;
                }
            }
            eprintln!("vendor_conformance: the session takes over 2 minutes; ending it");
            let _ = Command::new("kill").arg(pid.to_string()).status();
        })
    };
    let mut result = None;
    for line in BufReader::new(from_script).lines() {
        let line = line.map_err(|e| e.to_string())?;
        if let Some(question) = line.strip_prefix("truth ") {
            let answer = truth.answer(question).unwrap_or_else(|e| {
                eprintln!("harness: {e}");
                String::new()
            });
            writeln!(to_script, "{answer}").map_err(|e| e.to_string())?;
            to_script.flush().map_err(|e| e.to_string())?;
        } else if let Some(r) = line.strip_prefix("result ") {
            result = Some(r.to_owned());
        } else {
            println!("{line}");
        }
    }
    let status = child.wait().map_err(|e| e.to_string())?;
    finished.store(true, Ordering::SeqCst);
    let _ = watchdog.join();
    let stats = truth.server.stats();
    eprintln!(
        "server: {} commands, {} malformed; script: {status}; result {result:?}",
        stats.commands, stats.malformed
    );
    Ok(status.success() && result.is_some())
}

fn main() -> ExitCode {
    let mut args = std::env::args().skip(1);
    let Some(python) = args.next() else {
        eprintln!("usage: vendor_conformance PYTHON [SCRIPT]");
        return ExitCode::from(2);
    };
    let script = args.next().map_or_else(
        || Path::new(env!("CARGO_MANIFEST_DIR")).join("conformance/vendor_client.py"),
        PathBuf::from,
    );
    let capture = args.next().map(PathBuf::from);
    match run(&python, &script, capture.as_deref()) {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::FAILURE,
        Err(e) => {
            eprintln!("vendor_conformance: {e}");
            ExitCode::FAILURE
        }
    }
}
