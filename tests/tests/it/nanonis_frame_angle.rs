//! Issue 26's target: a calibration through the Nanonis backend with a frame angle of 30° and
//! slow direction down gives LCCs within 2 σ of the unrotated run at the same places.
//!
//! Two calibrations over TCP (`NanonisMicroscope` against nanonis-sim on loopback, two fresh
//! servers of sim-hopg without its random faults): one unrotated and scanned up, one with
//! `frame_angle_deg = 30` and `slow_direction = "down"`, so every scan of the second — the
//! counter scans and the skipping cycles included — is a frame turned by 30° (counter frames by
//! 210°) started from its top line.
//!
//! - **The same places.** Each place is calibrated as a one-node net: the backend is wrapped in
//!   a test adapter that advertises a small field centred on the node, and the net (margin =
//!   that field's half width) is its one centre node. The unrotated run's node is the place in
//!   the controller's counts; the rotated run's is the same place in the turned counts (the
//!   inverse of the backend's turn, rounded to whole counts: ≤ 0.7 counts, 0.015 nm).
//! - **Compared physically.** The LCCs of the rotated run are in the turned counts frame, and
//!   sim-hopg's scanner is anisotropic (0.02 vs 0.0215 nm/count), so a 30° frame changes K̄x,
//!   K̄y and α. The unrotated run's local linear map (counts → nm, spm-hal's
//!   `NmPerCountMatrix::from_lcc`, eq. 3) is transformed into the 30° frame (composed with the
//!   turn of the counts), and its LCCs read back through the metric (spm-calibration's
//!   `Metric::coefficients`).
//! - **σ** of a comparison: the rotated record's stated standard uncertainty and the unrotated
//!   one's propagated through the transform (central differences, the three coefficients taken
//!   as uncorrelated: the records state no covariance), combined in quadrature.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_calibration::{Calibrator, MemoryStore, Metric, NoObserver, PlanConfig, RunOptions};
use spm_hal::{
    Capabilities, CoarseZStage, CountPoint, CountVector, Counts, Frame, Microscope, MoveRequest,
    NmPerCount, NmPerCountMatrix, Radians, ScanRequest, Seconds,
};
use spm_nanonis::{NanonisConfig, NanonisMicroscope, SlowDirection};
use spm_nanonis_sim::{Server, ServerConfig, ServerHandle, SocketFaults};
use spm_sim::SimConfig;
use std::path::Path;

const ANGLE_DEG: f64 = 30.0;

/// The places, the controller's counts (inside the 30° frame's smaller field, ±23 987 counts,
/// with room for the node's scans).
const PLACES: [(f64, f64); 4] = [
    (0.0, 0.0),
    (9000.0, 6000.0),
    (-8000.0, 9000.0),
    (6000.0, -9000.0),
];

/// Half width of the field the adapter advertises around a node, counts.
const HALF_FIELD_COUNTS: i64 = 2000;

/// A backend that advertises only a square field around `centre` (so that a net lays its one
/// node there); everything else goes to the backend unchanged.
struct AroundNode<M> {
    inner: M,
    centre: CountPoint,
}

impl<M: Microscope> Microscope for AroundNode<M> {
    type Error = M::Error;

    fn capabilities(&self) -> Capabilities {
        let mut c = self.inner.capabilities();
        let h = HALF_FIELD_COUNTS as f64;
        c.field_min = CountPoint::from_counts(self.centre.x.value() - h, self.centre.y.value() - h);
        c.field_max = CountPoint::from_counts(self.centre.x.value() + h, self.centre.y.value() + h);
        c
    }
    fn now(&mut self) -> Result<Seconds, Self::Error> {
        self.inner.now()
    }
    fn wait(&mut self, duration: Seconds) -> Result<(), Self::Error> {
        self.inner.wait(duration)
    }
    fn position(&mut self) -> Result<CountPoint, Self::Error> {
        self.inner.position()
    }
    fn move_to(&mut self, request: MoveRequest) -> Result<(), Self::Error> {
        self.inner.move_to(request)
    }
    fn scan(&mut self, request: &ScanRequest) -> Result<Frame, Self::Error> {
        self.inner.scan(request)
    }
    fn z_position(&mut self) -> Result<Counts, Self::Error> {
        self.inner.z_position()
    }
    fn coarse_z(&mut self) -> Option<&mut dyn CoarseZStage<Error = Self::Error>> {
        self.inner.coarse_z()
    }
}

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ lives in the workspace")
}

/// sim-hopg as shipped, without its random faults (a visit given up in one run and not the
/// other would leave a place uncompared).
fn serve() -> ServerHandle {
    let sim = SimConfig::from_file(root().join("configs/sim-hopg.toml"))
        .unwrap()
        .without_random_faults();
    Server::bind("127.0.0.1:0", sim, ServerConfig::new(SocketFaults::none()))
        .unwrap()
        .spawn()
        .unwrap()
}

/// The small HOPG plan as `nanonis_end_to_end` runs it over TCP (pixel counts multiples of
/// 16, pauses of whole milliseconds), as a one-node net.
fn plan() -> PlanConfig {
    let text = std::fs::read_to_string(root().join("configs/plan-hopg-small.toml")).unwrap();
    let text = text
        .replace("first_pixels = 24", "first_pixels = 32")
        .replace("segment_pixels = 12", "segment_pixels = 16")
        .replace("base_s = 0.5", "base_s = 10.0")
        .replace("per_count_s = 0.0005", "per_count_s = 0.0");
    let mut plan = PlanConfig::from_toml_str(&text, "plan-hopg-small (16-pixel)").unwrap();
    plan.net.margin_counts = HALF_FIELD_COUNTS;
    plan
}

fn config(port: u16, frame_angle_deg: f64, slow_direction: SlowDirection) -> NanonisConfig {
    NanonisConfig {
        reconnect_attempts: 3,
        frame_angle_deg,
        slow_direction,
        ..spm_nanonis_sim::loopback_config(port)
    }
}

/// The LCCs (K̄x, K̄y nm/count, α rad) and their standard uncertainties of the first LCS at
/// each place, calibrated through a backend with this frame angle and slow direction.
fn calibrate(frame_angle_deg: f64, slow: SlowDirection) -> Vec<([f64; 3], [f64; 3])> {
    let server = serve();
    let mut tcp =
        NanonisMicroscope::connect(config(server.addr().port(), frame_angle_deg, slow)).unwrap();
    let (s, c) = frame_angle_deg.to_radians().sin_cos();
    let mut out = Vec::new();
    for (k, (x, y)) in PLACES.into_iter().enumerate() {
        // The place in the turned counts: the inverse of the backend's turn
        // (controller x = c·x' + s·y', y = −s·x' + c·y').
        let node = CountPoint::from_counts((c * x - s * y).round(), (s * x + c * y).round());
        let mut around = AroundNode {
            inner: &mut tcp,
            centre: node,
        };
        let mut store = MemoryStore::default();
        let mut observer = NoObserver;
        let mut calibrator =
            Calibrator::new(&mut around, &mut store, &mut observer, plan()).unwrap();
        assert_eq!(calibrator.plan().nodes.len(), 1);
        let node_there = calibrator.plan().nodes[0].position();
        assert_eq!(node_there, node, "the net's one node is the place");
        let report = calibrator
            .run(&RunOptions {
                run_id: format!("place-{k}"),
                start_unix_s: 1.8e9,
                config_text: String::new(),
            })
            .unwrap();
        assert_eq!(
            report.nodes_done, 1,
            "{frame_angle_deg}° place {k}: {report:?}"
        );
        let r = store
            .records
            .iter()
            .find(|r| r.lcs_index == 0)
            .expect("a record at the place");
        out.push((
            [r.kx_nm_per_count, r.ky_nm_per_count, r.alpha_rad],
            [
                r.u_kx_nm_per_count.unwrap(),
                r.u_ky_nm_per_count.unwrap(),
                r.u_alpha_rad.unwrap(),
            ],
        ));
    }
    out
}

/// LCCs of the controller's counts frame seen in the counts frame turned clockwise by
/// `angle_deg`: the local linear map (eq. 3) composed with the turn (a turned count vector
/// u' is the controller's u = (c·x' + s·y', −s·x' + c·y')), its LCCs read from its metric.
fn turned(lcc: [f64; 3], angle_deg: f64) -> [f64; 3] {
    let m = NmPerCountMatrix::from_lcc(NmPerCount(lcc[0]), NmPerCount(lcc[1]), Radians(lcc[2]));
    let (s, c) = angle_deg.to_radians().sin_cos();
    let image = |x: f64, y: f64| {
        let (a, b) = m.apply(CountVector::new(Counts(x), Counts(y)));
        [a.value(), b.value()]
    };
    let (e1, e2) = (image(c, -s), image(s, c));
    let dot = |a: [f64; 2], b: [f64; 2]| a[0] * b[0] + a[1] * b[1];
    let (kx, ky, alpha) = Metric {
        g11_nm2_per_count2: dot(e1, e1),
        g12_nm2_per_count2: dot(e1, e2),
        g22_nm2_per_count2: dot(e2, e2),
    }
    .coefficients()
    .unwrap();
    [kx.value(), ky.value(), alpha.value()]
}

/// The standard uncertainties of `turned(lcc)`, propagated by central differences from
/// uncorrelated uncertainties `u` of the three coefficients.
fn turned_uncertainty(lcc: [f64; 3], u: [f64; 3], angle_deg: f64) -> [f64; 3] {
    let mut variance = [0.0; 3];
    for i in 0..3 {
        let h = u[i] * 1e-3;
        let (mut plus, mut minus) = (lcc, lcc);
        plus[i] += h;
        minus[i] -= h;
        let (p, m) = (turned(plus, angle_deg), turned(minus, angle_deg));
        for j in 0..3 {
            let derivative = (p[j] - m[j]) / (2.0 * h);
            variance[j] += (derivative * u[i]).powi(2);
        }
    }
    variance.map(f64::sqrt)
}

#[test]
fn a_30_degree_frame_scanned_down_gives_the_unrotated_lccs_within_2_sigma() {
    let unrotated = calibrate(0.0, SlowDirection::Up);
    let rotated = calibrate(ANGLE_DEG, SlowDirection::Down);
    let names = ["K̄x", "K̄y", "α"];
    let mut worst = 0.0f64;
    let mut frame_shows = 0usize;
    for (k, ((lcc, u), (measured, u_measured))) in unrotated.iter().zip(&rotated).enumerate() {
        let expected = turned(*lcc, ANGLE_DEG);
        let u_expected = turned_uncertainty(*lcc, *u, ANGLE_DEG);
        for i in 0..3 {
            let sigma = u_expected[i].hypot(u_measured[i]);
            let off = (measured[i] - expected[i]).abs() / sigma;
            worst = worst.max(off);
            eprintln!(
                "place {k} {}: {:.6} at 30° down, {:.6} unrotated turned to 30° ({:.6} as \
                 measured), σ {sigma:.2e}: {off:.2} σ",
                names[i], measured[i], expected[i], lcc[i]
            );
            assert!(
                off <= 2.0,
                "place {k} {}: {} at 30° down vs {} expected ({off:.2} σ)",
                names[i],
                measured[i],
                expected[i]
            );
            // The frame matters: the unrotated value itself is further off than 2 σ.
            if (measured[i] - lcc[i]).abs() > 2.0 * sigma {
                frame_shows += 1;
            }
        }
    }
    eprintln!("largest difference {worst:.2} σ; {frame_shows} comparisons need the turn");
    assert!(
        frame_shows > 0,
        "the 30° frame changed no LCC beyond 2 σ: the comparison cannot tell the frames apart"
    );
}

/// The example job states both frame fields; `slow_direction` takes "up" and "down" and a job
/// with anything else is refused naming the field.
#[test]
fn the_example_job_states_the_frame_angle_and_the_slow_direction() {
    use spmcal::job::{Backend, Job};
    let example = root().join("configs/calibrate-nanonis-sim.toml");
    let Backend::Nanonis(config) = Job::from_file(&example).unwrap().backend else {
        panic!("the example job is not a nanonis job");
    };
    assert_eq!(
        (config.frame_angle_deg, config.slow_direction),
        (0.0, SlowDirection::Up)
    );
    let text = std::fs::read_to_string(&example).unwrap();
    assert!(text.contains("slow_direction = \"up\""));
    let dir = std::env::temp_dir().join(format!("spmcal-slow-direction-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(
        root().join("configs/plan-hopg-small.toml"),
        dir.join("plan-hopg-small.toml"),
    )
    .unwrap();
    let job = dir.join("job.toml");
    std::fs::write(
        &job,
        text.replace("slow_direction = \"up\"", "slow_direction = \"down\""),
    )
    .unwrap();
    let Backend::Nanonis(config) = Job::from_file(&job).unwrap().backend else {
        panic!("not a nanonis job");
    };
    assert_eq!(config.slow_direction, SlowDirection::Down);
    std::fs::write(
        &job,
        text.replace("slow_direction = \"up\"", "slow_direction = \"left\""),
    )
    .unwrap();
    let error = match Job::from_file(&job) {
        Ok(_) => panic!("slow_direction = \"left\" was accepted"),
        Err(e) => e.to_string(),
    };
    assert!(error.contains("slow_direction"), "{error}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The command history of a scan taken downwards replays the lines in the order they were
/// taken. A direct request scanned down by the controller comes back in the request's line
/// order with each pixel's real time (line 0 last); the recorder notes the order from those
/// times, and the replay puts the commanded position of every pixel at that pixel's time. The
/// truth is the frame's own geometry (`ScanRequest::commanded_position`) and times; up and
/// down alike.
#[test]
fn a_recorded_downward_scan_replays_its_lines_in_the_order_they_were_taken() {
    use spm_correction::dynamics::CommandHistory;
    use spm_hal::TraceHalf;
    use spm_hal::recording::{CommandEvent, CommandRecorder};
    for slow in [SlowDirection::Up, SlowDirection::Down] {
        let server = serve();
        let tcp = NanonisMicroscope::connect(config(server.addr().port(), 0.0, slow)).unwrap();
        let mut recorder = CommandRecorder::new(tcp, 64);
        let request = ScanRequest::centred_square(
            CountPoint::from_counts(1000.0, -500.0),
            Counts(4.0),
            16,
            Seconds(2e-3),
        );
        let frame = recorder.scan(&request).unwrap();
        let (_, events) = recorder.into_parts();
        let descending = events.iter().any(|e| {
            matches!(
                e,
                CommandEvent::Scan {
                    lines_descending: true,
                    ..
                }
            )
        });
        assert_eq!(descending, slow == SlowDirection::Down, "{slow:?}");
        let history = CommandHistory::from_events(&events);
        let n = request.pixels_per_line as usize;
        for (k, &t) in frame.forward.time_s.iter().enumerate() {
            let (line, pixel) = (k / n, k % n);
            let want = request.commanded_position(TraceHalf::Forward, line, pixel);
            let segment = history
                .segments()
                .iter()
                .find(|s| s.start_s <= t && t <= s.end_s)
                .unwrap();
            let [x, y] = segment.at(t);
            let off = (x - want.x.value()).hypot(y - want.y.value());
            assert!(
                off < 0.5 * request.pixel_step.value(),
                "{slow:?}: line {line} pixel {pixel} at {t} s is replayed at ({x}, {y}), \
                 commanded ({}, {})",
                want.x.value(),
                want.y.value()
            );
        }
        server.kill();
    }
}
