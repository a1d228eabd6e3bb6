//! No panic reaches the user (issue 8, DESIGN §13: a 101 exit is always a bug).
//!
//! Every subcommand runs with every bad file in every file slot (the other slots valid) and
//! with bad arguments: missing, empty, garbage, truncated real file, a directory instead of a
//! file, NaN data (raw, GSF, surfaces), a truncated CDB, an unwritable output. Each must exit
//! 2 (bad input, DESIGN §13) with a message — never 0, 1 or 101 — and print no "panicked".
#![allow(clippy::unwrap_used, clippy::expect_used)]

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

fn fixture() -> Fixture {
    let dir = std::env::temp_dir().join(format!("spmcal-no-panic-{}", std::process::id()));
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
    let f = fixture();
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
