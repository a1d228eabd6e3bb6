//! No panic reaches the user (issue 8, DESIGN §13: a 101 exit is always a bug).
//!
//! Every subcommand runs with every bad file in every file slot (the other slots valid) and
//! with bad arguments: missing, empty, garbage, truncated real file, a directory instead of a
//! file, NaN data (raw, GSF, surfaces), a truncated CDB, an unwritable output. Each must exit
//! 2 (bad input, DESIGN §13) with a message — never 0, 1 or 101 — and print no "panicked".
#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_cdb::CdbRead;
use std::path::{Path, PathBuf};
use std::process::Command;

fn spmcal(args: &[String]) -> (Option<i32>, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_spmcal"))
        .args(args)
        .env("NO_COLOR", "1")
        .output()
        .expect("spmcal runs");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

struct Fixture {
    dir: PathBuf,
    /// (label, path) of every bad file.
    bad: Vec<(&'static str, String)>,
    good_image: String,
    good_cdb: String,
    good_surfaces: String,
    good_job: String,
}

fn s(p: &Path) -> String {
    p.to_str().unwrap().to_owned()
}

fn fixture(name: &str) -> Fixture {
    let dir = std::env::temp_dir().join(format!("spmcal-no-panic-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("a-directory.sxm")).unwrap();
    let write = |name: &str, bytes: &[u8]| {
        let p = dir.join(name);
        std::fs::write(&p, bytes).unwrap();
        s(&p)
    };
    let sxm = spmcal_tests::measured_file("si7x7-nanonis/Si_7x7_051.sxm");
    let sxm_bytes = std::fs::read(&sxm).unwrap();

    // A real CDB and surfaces from a small calibration.
    let job = write(
        "job.toml",
        format!(
            "plan_file = {:?}\n[backend]\nkind = \"sim\"\nsim_config = {:?}\n",
            s(&root().join("configs/plan-hopg-small.toml")),
            s(&root().join("configs/sim-hopg.toml"))
        )
        .as_bytes(),
    );
    let out = dir.join("run");
    let (code, stderr) = spmcal(&[
        "calibrate".into(),
        "--config".into(),
        job.clone(),
        "--out".into(),
        s(&out),
    ]);
    assert_eq!(code, Some(0), "{stderr}");
    let cdb_bytes = std::fs::read(out.join("cdb.sqlite")).unwrap();
    let surfaces_text = std::fs::read_to_string(out.join("surfaces.json")).unwrap();

    let mut nan_raw = Vec::new();
    nan_raw.extend_from_slice(&16u32.to_le_bytes());
    nan_raw.extend_from_slice(&16u32.to_le_bytes());
    for _ in 0..256 {
        nan_raw.extend_from_slice(&f64::NAN.to_le_bytes());
    }
    let mut nan_gsf =
        b"Gwyddion Simple Field 1.0\nXRes = 16\nYRes = 16\nXReal = nan\nYReal = 1e-8\n".to_vec();
    nan_gsf.resize(nan_gsf.len().next_multiple_of(4) + 4, 0);
    for _ in 0..256 {
        nan_gsf.extend_from_slice(&f32::NAN.to_le_bytes());
    }
    // Surfaces with every number replaced by NaN-like nonsense the JSON parser accepts.
    let nan_surfaces = surfaces_text.replace("0.0", "1e999");

    let bad = vec![
        ("missing", s(&dir.join("no-such-file.sxm"))),
        ("empty", write("empty.sxm", b"")),
        (
            "garbage",
            write("garbage.sxm", b"\x00\xffnot an SPM file\x1a\x04\xde\xad"),
        ),
        ("truncated sxm", write("truncated.sxm", &sxm_bytes[..3000])),
        (
            "truncated sxm data",
            write("truncated-data.sxm", &sxm_bytes[..sxm_bytes.len() / 2]),
        ),
        ("directory", s(&dir.join("a-directory.sxm"))),
        ("NaN raw", write("nan.dat", &nan_raw)),
        ("NaN gsf", write("nan.gsf", &nan_gsf)),
        (
            "truncated cdb",
            write(
                "truncated.sqlite",
                &cdb_bytes[..cdb_bytes.len().min(8192) / 2],
            ),
        ),
        (
            "garbage json",
            write("garbage.json", b"{\"planes\": [1, 2,"),
        ),
        (
            "overflowing surfaces",
            write("overflow.json", nan_surfaces.as_bytes()),
        ),
        (
            "garbage toml",
            write("garbage.toml", b"[backend\nkind = \"sim"),
        ),
    ];
    Fixture {
        good_image: s(&sxm),
        good_cdb: s(&out.join("cdb.sqlite")),
        good_surfaces: s(&out.join("surfaces.json")),
        good_job: job,
        dir,
        bad,
    }
}

/// Runs one invocation and checks it failed cleanly as bad input.
fn expect_clean_failure(args: &[String], what: &str) {
    let (code, stderr) = spmcal(args);
    assert!(
        !stderr.contains("panicked"),
        "{what}: spmcal {args:?} panicked: {stderr}"
    );
    let code = code.unwrap_or_else(|| panic!("{what}: spmcal {args:?} died of a signal"));
    assert_ne!(code, 101, "{what}: spmcal {args:?}: {stderr}");
    assert_eq!(
        code, 2,
        "{what}: spmcal {args:?} exited {code} on bad input: {stderr}"
    );
    assert!(!stderr.trim().is_empty(), "{what}: no message");
}

#[test]
fn every_subcommand_fails_cleanly_on_bad_files_and_arguments() {
    let f = fixture("bad-input");
    let out = |name: &str| s(&f.dir.join(name));
    let v = |a: &[&str]| a.iter().map(|x| (*x).to_owned()).collect::<Vec<String>>();
    let mut tried = 0;
    let mut run = |args: Vec<String>, what: &str| {
        expect_clean_failure(&args, what);
        tried += 1;
    };
    for (label, bad) in &f.bad {
        let b = bad.as_str();
        let what = format!("bad file: {label}");
        // Image slots.
        run(v(&["info", b]), &what);
        run(v(&["info", b, "--json"]), &what);
        run(
            v(&[
                "diagnose",
                b,
                "--lattice",
                "si7x7",
                "--json",
                &out("d.json"),
            ]),
            &what,
        );
        run(
            v(&[
                "diagnose",
                &f.good_image,
                b,
                "--lattice",
                "si7x7",
                "--json",
                &out("d.json"),
            ]),
            &what,
        );
        run(
            v(&[
                "correct",
                b,
                "--surfaces",
                &f.good_surfaces,
                "--out",
                &out("c.gsf"),
            ]),
            &what,
        );
        // Surfaces slot.
        run(
            v(&[
                "correct",
                &f.good_image,
                "--surfaces",
                b,
                "--out",
                &out("c.gsf"),
            ]),
            &what,
        );
        // CDB slots.
        run(v(&["fit", "--cdb", b, "--out", &out("s.json")]), &what);
        run(v(&["cdb", "check", b]), &what);
        run(v(&["cdb", "export", b, "--csv", &out("x.csv")]), &what);
        run(v(&["cdb", "trend", b]), &what);
        run(
            v(&["report", "--cdb", b, "--run", "r", "--out", &out("rep")]),
            &what,
        );
        // Config slot.
        run(
            v(&["calibrate", "--config", b, "--out", &out("cal")]),
            &what,
        );
        run(
            v(&[
                "calibrate",
                "--config",
                b,
                "--resume",
                "--cdb",
                &f.good_cdb,
                "--out",
                &out("cal"),
            ]),
            &what,
        );
    }
    // A CDB slot that is a directory or garbage for calibrate.
    for (label, bad) in &f.bad {
        if matches!(*label, "missing" | "empty") {
            continue; // a missing or empty CDB file is created: not an error
        }
        run(
            v(&[
                "calibrate",
                "--config",
                &f.good_job,
                "--cdb",
                bad,
                "--out",
                &out("cal2"),
            ]),
            &format!("calibrate --cdb {label}"),
        );
    }
    // Bad arguments.
    let unwritable = "/proc/no-such-dir/out";
    for (what, args) in [
        ("no subcommand", v(&[])),
        (
            "unknown option",
            v(&["info", &f.good_image, "--frobnicate"]),
        ),
        ("info without file", v(&["info"])),
        (
            "diagnose bad lattice",
            v(&[
                "diagnose",
                &f.good_image,
                "--lattice",
                "hex:-1",
                "--json",
                &out("d.json"),
            ]),
        ),
        (
            "diagnose NaN lattice",
            v(&[
                "diagnose",
                &f.good_image,
                "--lattice",
                "square:nan",
                "--json",
                &out("d.json"),
            ]),
        ),
        (
            "diagnose no files",
            v(&["diagnose", "--lattice", "si7x7", "--json", &out("d.json")]),
        ),
        (
            "diagnose unwritable json",
            v(&[
                "diagnose",
                &f.good_image,
                "--lattice",
                "si7x7",
                "--json",
                unwritable,
            ]),
        ),
        (
            "correct bad direction",
            v(&[
                "correct",
                &f.good_image,
                "--surfaces",
                &f.good_surfaces,
                "--out",
                &out("c.gsf"),
                "--direction",
                "sideways",
            ]),
        ),
        (
            "correct unwritable out",
            v(&[
                "correct",
                &f.good_image,
                "--surfaces",
                &f.good_surfaces,
                "--out",
                unwritable,
            ]),
        ),
        (
            "fit bad date",
            v(&[
                "fit",
                "--cdb",
                &f.good_cdb,
                "--since",
                "yesterday",
                "--out",
                &out("s.json"),
            ]),
        ),
        (
            "fit inverted dates",
            v(&[
                "fit",
                "--cdb",
                &f.good_cdb,
                "--since",
                "2030-01-01",
                "--until",
                "2020-01-01",
                "--out",
                &out("s.json"),
            ]),
        ),
        (
            "fit unknown scanner",
            v(&[
                "fit",
                "--cdb",
                &f.good_cdb,
                "--scanner",
                "nope",
                "--out",
                &out("s.json"),
            ]),
        ),
        (
            "fit unwritable out",
            v(&["fit", "--cdb", &f.good_cdb, "--out", unwritable]),
        ),
        (
            "export unwritable csv",
            v(&["cdb", "export", &f.good_cdb, "--csv", unwritable]),
        ),
        ("cdb without action", v(&["cdb"])),
        ("cdb unknown action", v(&["cdb", "repair", &f.good_cdb])),
        (
            "calibrate unwritable out",
            v(&["calibrate", "--config", &f.good_job, "--out", unwritable]),
        ),
        (
            "calibrate resume with nothing to resume",
            v(&[
                "calibrate",
                "--config",
                &f.good_job,
                "--resume",
                "--cdb",
                &out("fresh.sqlite"),
                "--out",
                &out("cal3"),
            ]),
        ),
    ] {
        run(args, what);
    }
    eprintln!("{tried} bad invocations: all exited 2 with a message, none panicked");
    assert!(tried >= 150, "{tried}");
    let _ = std::fs::remove_dir_all(&f.dir);
}

// ---------------------------------------------------------------------------------------
// Issue 13: hostile environments — a closed stdout, a full disk, signals at random points.

/// A seeded generator (xorshift64*), so that the signal moments repeat from run to run.
struct Rng(u64);

impl Rng {
    fn below(&mut self, n: u64) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) % n.max(1)
    }
}

/// Runs `args` with stdout and stderr as given; returns (exit code, stderr).
fn spmcal_with(args: &[String], stdout: std::process::Stdio) -> (Option<i32>, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_spmcal"))
        .args(args)
        .env("NO_COLOR", "1")
        .stdin(std::process::Stdio::null())
        .stdout(stdout)
        .stderr(std::process::Stdio::piped())
        .output()
        .expect("spmcal runs");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn assert_no_panic(code: Option<i32>, stderr: &str, allowed: &[i32], what: &str) {
    assert!(!stderr.contains("panicked"), "{what}: {stderr}");
    let code = code.unwrap_or_else(|| panic!("{what}: died of a signal: {stderr}"));
    assert!(
        allowed.contains(&code),
        "{what}: exit {code} (allowed {allowed:?}): {stderr}"
    );
}

/// Every visit of every run stored exactly once or given up; nothing outside a plan.
fn assert_visits_consistent(cdb: &str, what: &str) {
    let db = spm_cdb::Cdb::open_read_only(cdb).unwrap();
    let bad: i64 = db
        .connection()
        .query_row(
            "SELECT count(*) FROM progress p WHERE \
             (SELECT count(*) FROM records r WHERE r.run_id = p.run_id \
                AND r.repeat_index = p.repeat_index AND r.node_index = p.node_index) \
             != (CASE p.state WHEN 'done' THEN 1 ELSE 0 END)",
            [],
            |r| r.get(0),
        )
        .unwrap();
    assert_eq!(bad, 0, "{what}: visits not stored exactly once");
    let (code, stderr) = spmcal(&["cdb".to_owned(), "check".to_owned(), cdb.to_owned()]);
    assert_eq!(code, Some(0), "{what}: cdb check: {stderr}");
}

/// A small full tmpfs on `dir` where the machine allows mounting; unmounted when dropped.
struct FullDisk(PathBuf);

impl FullDisk {
    fn mount(dir: &Path) -> Option<Self> {
        std::fs::create_dir_all(dir).ok()?;
        let mounted = Command::new("mount")
            .args(["-t", "tmpfs", "-o", "size=64k", "tmpfs"])
            .arg(dir)
            .stderr(std::process::Stdio::null())
            .status()
            .ok()?
            .success();
        if !mounted {
            return None;
        }
        let _ = std::fs::write(dir.join("filler"), vec![0u8; 1 << 20]);
        Some(Self(dir.to_path_buf()))
    }
}

impl Drop for FullDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).status();
    }
}

/// `args` with the last one (an output path) on a full disk: a full tmpfs where possible,
/// else a file-size limit of 1 KiB (SIGXFSZ ignored: writes fail with EFBIG).
fn on_full_disk(dir: &Path, args: &[String], name: &str) -> (Option<i32>, String) {
    let mount = dir.join(format!("full-{name}"));
    if let Some(_disk) = FullDisk::mount(&mount) {
        let mut args = args.to_vec();
        args.push(s(&mount.join(name)));
        return spmcal_with(&args, std::process::Stdio::null());
    }
    let mut script = String::from("trap '' XFSZ; ulimit -f 1; exec \"$0\"");
    for k in 0..=args.len() {
        script.push_str(&format!(" \"${}\"", k + 1));
    }
    let out = Command::new("sh")
        .arg("-c")
        .arg(script)
        .arg(env!("CARGO_BIN_EXE_spmcal"))
        .args(args)
        .arg(s(&dir.join(name)))
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .output()
        .unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn closed_stdout_full_disk_and_signals_never_panic_nor_lose_a_visit() {
    let f = fixture("hostile");
    let dir = f.dir.join("hostile");
    std::fs::create_dir_all(&dir).unwrap();
    let v = |a: &[&str]| a.iter().map(|x| (*x).to_owned()).collect::<Vec<String>>();
    let out = |name: &str| s(&dir.join(name));
    let reading: Vec<Vec<String>> = vec![
        v(&["info", &f.good_image]),
        v(&["info", &f.good_image, "--json"]),
        v(&["cdb", "check", &f.good_cdb]),
        v(&["cdb", "trend", &f.good_cdb]),
        v(&["cdb", "export", &f.good_cdb, "--csv", &out("e.csv")]),
        v(&["fit", "--cdb", &f.good_cdb, "--out", &out("s.json")]),
        v(&[
            "calibrate",
            "--config",
            &f.good_job,
            "--cdb",
            &out("closed.sqlite"),
            "--out",
            &out("cal"),
        ]),
    ];
    // 1. A closed stdout: exit 0 or 1, quietly.
    for args in &reading {
        let (reader, writer) = std::io::pipe().unwrap();
        drop(reader);
        let (code, stderr) = spmcal_with(args, writer.into());
        assert_no_panic(code, &stderr, &[0, 1], &format!("closed stdout {args:?}"));
    }
    assert_visits_consistent(&out("closed.sqlite"), "closed stdout");
    assert_visits_consistent(&f.good_cdb, "readers with a closed stdout");
    // 2. A full disk under every output: exit 1 (or 2 where the output cannot be made), and
    //    every CDB that exists passes its check.
    let full: Vec<(Vec<String>, &str)> = vec![
        (v(&["cdb", "export", &f.good_cdb, "--csv"]), "e.csv"),
        (v(&["fit", "--cdb", &f.good_cdb, "--out"]), "s.json"),
        (v(&["cdb", "check", &f.good_cdb, "--log"]), "l.txt"),
        (
            v(&[
                "calibrate",
                "--config",
                &f.good_job,
                "--out",
                &out("cal-full"),
                "--cdb",
            ]),
            "c.sqlite",
        ),
        (
            v(&[
                "calibrate",
                "--config",
                &f.good_job,
                "--cdb",
                &out("c2.sqlite"),
                "--out",
            ]),
            "report",
        ),
    ];
    let mut full_disk = 0;
    for (args, name) in &full {
        let (code, stderr) = on_full_disk(&dir, args, name);
        assert_no_panic(code, &stderr, &[0, 1, 2], &format!("full disk {args:?}"));
        full_disk += 1;
    }
    if Path::new(&out("c2.sqlite")).exists() {
        assert_visits_consistent(&out("c2.sqlite"), "report on a full disk");
    }
    // 3. SIGINT and SIGTERM at seeded random points of a 13 × 13 run (169 visits): each
    //    stops at a safe point; the run is 'aborted' (or finished), nothing is lost, and
    //    the last resume completes the plan.
    let plan = std::fs::read_to_string(root().join("configs/plan-hopg-small.toml"))
        .unwrap()
        .replacen("step_counts = 20000", "step_counts = 4000", 1)
        // The dynamics stage off: the signals land among the visits, and the stage's frames
        // and identification would only lengthen the last resume.
        .replacen("[plan.dynamics]\n", "[plan.dynamics]\nenabled = false\n", 1);
    assert!(plan.contains("enabled = false"));
    std::fs::write(dir.join("plan13.toml"), plan).unwrap();
    std::fs::write(
        dir.join("job13.toml"),
        format!(
            "plan_file = \"plan13.toml\"\n[backend]\nkind = \"sim\"\nsim_config = {:?}\n",
            s(&root().join("configs/sim-ideal.toml"))
        ),
    )
    .unwrap();
    let cdb = out("signals.sqlite");
    let mut rng = Rng(0x5EED_0013);
    let mut signals = 0;
    for trial in 0..6 {
        let signal = if trial % 2 == 0 { "INT" } else { "TERM" };
        let mut args = v(&[
            "calibrate",
            "--config",
            &out("job13.toml"),
            "--cdb",
            &cdb,
            "--out",
            &out("cal13"),
        ]);
        if trial > 0 {
            args.push("--resume".to_owned());
        }
        let stored = |cdb: &str| {
            spm_cdb::Cdb::open_read_only(cdb)
                .ok()
                .and_then(|db| db.count_records(&spm_cdb::RecordFilter::default()).ok())
                .unwrap_or(0)
        };
        let target = stored(&cdb) + 1 + rng.below(12);
        let child = Command::new(env!("CARGO_BIN_EXE_spmcal"))
            .args(&args)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let started = std::time::Instant::now();
        let mut child = child;
        while stored(&cdb) < target
            && child.try_wait().unwrap().is_none()
            && started.elapsed() < std::time::Duration::from_secs(120)
        {
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        let _ = Command::new("kill")
            .args([format!("-{signal}"), child.id().to_string()])
            .status();
        signals += 1;
        let output = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
        let what = format!("SIG{signal} after {target} records");
        assert_no_panic(output.status.code(), &stderr, &[0, 1], &what);
        assert_visits_consistent(&cdb, &what);
        let db = spm_cdb::Cdb::open_read_only(&cdb).unwrap();
        let run = db.runs(None).unwrap().pop().unwrap();
        assert!(
            matches!(run.status.as_str(), "aborted" | "finished"),
            "{what}: run is {}",
            run.status.as_str()
        );
        if run.status.as_str() == "finished" {
            break;
        }
    }
    let (code, stderr) = spmcal(&v(&[
        "calibrate",
        "--config",
        &out("job13.toml"),
        "--cdb",
        &cdb,
        "--out",
        &out("cal13"),
        "--resume",
    ]));
    // Nothing left to resume (finished during the trials) is exit 2; else the resume ends it.
    assert!(matches!(code, Some(0 | 2)), "last resume: {stderr}");
    assert_visits_consistent(&cdb, "after the last resume");
    let db = spm_cdb::Cdb::open_read_only(&cdb).unwrap();
    assert_eq!(
        db.count_records(&spm_cdb::RecordFilter::default()).unwrap(),
        169,
        "every planned visit stored once"
    );
    eprintln!(
        "{} closed-stdout runs, {full_disk} full-disk runs, {signals} signals: no panic, no visit lost",
        reading.len()
    );
    let _ = std::fs::remove_dir_all(&f.dir);
}
