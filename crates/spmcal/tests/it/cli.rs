//! The command-line contract of DESIGN §13: exit codes and JSON keys.

use std::path::Path;
use std::process::Command;

fn spmcal(args: &[&str]) -> (i32, String, String) {
    let output = Command::new(env!("CARGO_BIN_EXE_spmcal"))
        .args(args)
        .output()
        .expect("spmcal runs");
    (
        output.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&output.stdout).into_owned(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    )
}

fn check(args: &[&str], expected_code: i32, stderr_mentions: &str) {
    let (code, _, stderr) = spmcal(args);
    assert_eq!(code, expected_code, "spmcal {args:?}: stderr {stderr}");
    assert!(
        stderr.contains(stderr_mentions),
        "spmcal {args:?}: stderr {stderr:?} should mention {stderr_mentions:?}"
    );
}

#[test]
fn bad_usage_and_bad_input_exit_with_2_and_name_the_culprit() {
    let scratch = std::env::temp_dir().join(format!("spmcal-cli-{}", std::process::id()));
    std::fs::create_dir_all(&scratch).unwrap();
    let garbage = scratch.join("garbage.sxm");
    std::fs::write(&garbage, b"this is not an SPM file at all").unwrap();
    let bad_job = scratch.join("job.toml");
    std::fs::write(
        &bad_job,
        "[backend]\nkind = \"sim\"\nsim_config = \"x.toml\"\ncolour = 3\n",
    )
    .unwrap();
    let not_a_cdb = scratch.join("notes.sqlite");
    std::fs::write(&not_a_cdb, b"SQLite format 3\0 but not really").unwrap();
    let g = garbage.to_str().unwrap();
    check(&["frobnicate"], 2, "frobnicate");
    check(&["info"], 2, "FILE");
    check(&["info", "/no/such/file.sxm"], 2, "/no/such/file.sxm");
    check(&["info", g], 2, "garbage.sxm");
    check(
        &["calibrate", "--config", bad_job.to_str().unwrap()],
        2,
        "colour",
    );
    check(
        &["calibrate", "--config", "/no/such/job.toml"],
        2,
        "/no/such/job.toml",
    );
    check(&["cdb", "check", "/no/such.sqlite"], 2, "/no/such.sqlite");
    check(
        &["cdb", "check", not_a_cdb.to_str().unwrap()],
        2,
        "notes.sqlite",
    );
    check(
        &["fit", "--cdb", "/no/such.sqlite", "--out", "/tmp/s.json"],
        2,
        "/no/such.sqlite",
    );
    check(
        &["diagnose", g, "--lattice", "cubic", "--json", "/tmp/d.json"],
        2,
        "cubic",
    );
    let sxm = spmcal_tests::measured_file("si7x7-nanonis/Si_7x7_051.sxm");
    let sxm = sxm.to_str().unwrap();
    // A lattice the image does not resolve (the 200 nm Si 7×7 frame: 4 px per cell) is
    // refused with exit 2 and nothing written, not diagnosed (issue 29 item 4).
    let coarse = spmcal_tests::measured_file("si7x7-nanonis/Si_7x7_012.sxm");
    let diagnosis = scratch.join("d.json");
    check(
        &[
            "diagnose",
            coarse.to_str().unwrap(),
            "--lattice",
            "si7x7",
            "--json",
            diagnosis.to_str().unwrap(),
        ],
        2,
        "cannot be localised",
    );
    assert!(!diagnosis.exists());
    let out = scratch.join("out.gsf");
    let out = out.to_str().unwrap();
    check(
        &["correct", g, "--surfaces", "/no/such.json", "--out", out],
        2,
        "garbage.sxm",
    );
    check(
        &["correct", sxm, "--surfaces", "/no/such.json", "--out", out],
        2,
        "/no/such.json",
    );
    let surfaces = scratch.join("surfaces.json");
    std::fs::write(&surfaces, "{\"format_version\": 1}").unwrap();
    check(
        &[
            "correct",
            sxm,
            "--surfaces",
            surfaces.to_str().unwrap(),
            "--out",
            out,
        ],
        2,
        "surfaces.json",
    );
    let _ = std::fs::remove_dir_all(&scratch);
}

#[test]
fn info_json_has_the_contract_keys() {
    let file = spmcal_tests::measured_file("si7x7-nanonis/Si_7x7_051.sxm");
    let (code, stdout, stderr) = spmcal(&["info", file.to_str().unwrap(), "--json"]);
    assert_eq!(code, 0, "{stderr}");
    let json: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(json["format"], "nanonis-sxm");
    assert_eq!(json["pixels"], serde_json::json!([256, 256]));
    let size = json["size_nm"].as_array().unwrap();
    assert!((size[0].as_f64().unwrap() - 20.0).abs() < 1e-9);
    assert_eq!(json["scan_dir"], "down");
    assert!(json["line_time_s"].as_f64().unwrap() > 0.0);
    let channels = json["channels"].as_array().unwrap();
    assert!(
        channels
            .iter()
            .all(|c| c["name"].is_string() && c["direction"].is_string() && c["unit"].is_string())
    );
    assert!(Path::new(&file).is_file());
}

/// `spmcal info` over every measured file: one line per file, values as read by hand from
/// the headers (and ../shared/data/measured/README.md): Nanonis `:SCAN_PIXELS:`,
/// `:SCAN_RANGE:` (m), `:SCAN_OFFSET:`, `:SCAN_ANGLE:`, `:SCAN_DIR:`, `:SCAN_TIME:` (s per
/// line), `:REC_DATE:`/`:REC_TIME:`, `:DATA_INFO:` (Z and Current, both directions); the
/// ISO 28600 file's 512 × 512 points of 1.14807e-08 m, top to bottom; the RHK file's
/// 256 × 256 points over 1.0 nm at 10°, 3 pages in 2 directions; the raw files' u32 rows
/// and columns. `--json` gives an array of as many entries.
#[test]
fn info_prints_one_line_per_real_file_with_the_header_values() {
    let files = [
        "si7x7-nanonis/Si_7x7_012.sxm",
        "si7x7-nanonis/Si_7x7_028.sxm",
        "si7x7-nanonis/Si_7x7_032.sxm",
        "si7x7-nanonis/Si_7x7_051.sxm",
        "hopg-terrace-iso28600/graphiteterrace.spm",
        "graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4",
        "si7x7-raw/image_with_defects.dat",
        "si7x7-raw/image_with_step_edge.dat",
    ];
    let paths: Vec<String> = files
        .iter()
        .map(|f| spmcal_tests::measured_file(f).to_str().unwrap().to_owned())
        .collect();
    let mut args = vec!["info"];
    args.extend(paths.iter().map(String::as_str));
    let (code, stdout, stderr) = spmcal(&args);
    assert_eq!(code, 0, "{stderr}");
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines.len(), 1 + files.len(), "{stdout}");
    // Columns are separated by at least two spaces; a cell holds at most single spaces.
    let cells = |line: &str| -> Vec<String> {
        line.split("  ")
            .map(str::trim)
            .filter(|c| !c.is_empty())
            .map(str::to_owned)
            .collect()
    };
    assert_eq!(
        cells(lines[0]),
        [
            "file",
            "format",
            "pixels",
            "size nm",
            "offset nm",
            "angle °",
            "dir",
            "line s",
            "recorded",
            "channels"
        ]
    );
    let expected: [[&str; 10]; 8] = [
        [
            "Si_7x7_012.sxm",
            "nanonis-sxm",
            "256×256",
            "200×200",
            "0, 0",
            "0",
            "down",
            "0.544",
            "2016-01-07T11:09:34",
            "4",
        ],
        [
            "Si_7x7_028.sxm",
            "nanonis-sxm",
            "256×256",
            "50×50",
            "0, 0",
            "0",
            "down",
            "0.256",
            "2016-01-07T12:10:04",
            "4",
        ],
        [
            "Si_7x7_032.sxm",
            "nanonis-sxm",
            "256×256",
            "50×50",
            "0, 0",
            "0",
            "down",
            "0.256",
            "2016-01-07T12:18:50",
            "4",
        ],
        [
            "Si_7x7_051.sxm",
            "nanonis-sxm",
            "256×256",
            "20×20",
            "0, 0",
            "0",
            "down",
            "0.192",
            "2016-01-07T12:54:04",
            "4",
        ],
        [
            "graphiteterrace.spm",
            "iso28600",
            "512×512",
            "11.4807×11.4807",
            "–",
            "–",
            "down",
            "–",
            "–",
            "1",
        ],
        [
            "dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4",
            "rhk-sm4",
            "256×256",
            "1×1",
            "*",
            "10",
            "–",
            "*",
            "*",
            "6",
        ],
        [
            "image_with_defects.dat",
            "raw-f64",
            "256×256",
            "–",
            "–",
            "–",
            "–",
            "–",
            "–",
            "1",
        ],
        [
            "image_with_step_edge.dat",
            "raw-f64",
            "512×512",
            "–",
            "–",
            "–",
            "–",
            "–",
            "–",
            "1",
        ],
    ];
    for (line, want) in lines[1..].iter().zip(&expected) {
        let got = cells(line);
        assert_eq!(got.len(), 10, "{line}");
        for (k, (g, w)) in got.iter().zip(want).enumerate() {
            // `*`: a value not checked here (read from the binary RHK page header).
            if *w != "*" {
                assert_eq!(g, w, "column {k} of {line}");
            }
        }
    }
    // No machine-precision noise anywhere (e.g. 0.9999999717180685).
    assert!(
        stdout
            .split(|c: char| !(c.is_ascii_digit() || c == '.'))
            .all(|n| n.len() <= 12),
        "{stdout}"
    );

    args.push("--json");
    let (code, stdout, stderr) = spmcal(&args);
    assert_eq!(code, 0, "{stderr}");
    let json: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let entries = json.as_array().expect("an array for many files");
    assert_eq!(entries.len(), files.len());
    for (entry, path) in entries.iter().zip(&paths) {
        assert_eq!(entry["file"].as_str(), Some(path.as_str()));
    }
    assert_eq!(entries[4]["pixels"], serde_json::json!([512, 512]));
    let size = entries[4]["size_nm"][0].as_f64().unwrap();
    assert!((size - 11.4807).abs() < 1e-9, "{size}");
}

/// Writes `name` into `dir` and returns its path as a string.
fn write(dir: &Path, name: &str, text: &str) -> String {
    let path = dir.join(name);
    std::fs::write(&path, text).expect("scratch file");
    path.to_str().expect("UTF-8 temp path").to_owned()
}

#[test]
fn config_errors_exit_2_naming_file_line_and_field() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let plan = std::fs::read_to_string(root.join("configs/plan-hopg-small.toml")).unwrap();
    let sim = std::fs::read_to_string(root.join("configs/sim-hopg.toml")).unwrap();
    let dir = std::env::temp_dir().join(format!("spmcal-config-errors-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let line_of = |text: &str, needle: &str| {
        text.lines()
            .position(|l| l.starts_with(needle))
            .map(|i| i + 1)
            .unwrap_or_else(|| panic!("{needle} not in the config"))
    };
    let step = line_of(&plan, "step_counts = 20000");
    let dwell = line_of(&plan, "pixel_dwell_s =");
    let overhead = line_of(&sim, "call_overhead_s =");
    write(&dir, "sim.toml", &sim);
    write(&dir, "plan.toml", &plan);
    let job = |plan_file: &str, sim_file: &str| {
        format!(
            "plan_file = \"{plan_file}\"\n[backend]\nkind = \"sim\"\nsim_config = \"{sim_file}\"\n"
        )
    };
    // (what, file to write, its text, job text, file named in the message, line, field)
    let mut cases: Vec<(&str, &str, String, String, &str, usize, &str)> = Vec::new();
    let plan_with = |from: &str, to: &str| plan.replacen(from, to, 1);
    let sim_with = |from: &str, to: &str| {
        let at = sim.find(from).expect("in sim config");
        format!("{}{to}{}", &sim[..at], &sim[at + from.len()..])
    };
    for (what, text, line, field) in [
        (
            "plan: unknown field",
            plan_with("step_counts = 20000", "step_counts = 20000\ncolour = 3"),
            step + 1,
            "plan.net.colour",
        ),
        (
            "plan: wrong type",
            plan_with("step_counts = 20000", "step_counts = \"many\""),
            step,
            "plan.net.step_counts",
        ),
        (
            "plan: out of range",
            plan_with("step_counts = 20000", "step_counts = -5"),
            step,
            "plan.net.step_counts",
        ),
        (
            "plan: NaN",
            plan_with("pixel_dwell_s = 0.0001", "pixel_dwell_s = nan"),
            dwell,
            "plan.motion.pixel_dwell_s",
        ),
    ] {
        cases.push((
            what,
            "bad-plan.toml",
            text,
            job("bad-plan.toml", "sim.toml"),
            "bad-plan.toml",
            line,
            field,
        ));
    }
    let seed = line_of(&sim, "seed =");
    for (what, text, line, field) in [
        (
            "sim: unknown field",
            sim_with("seed = 20261121", "seed = 20261121\nbogus = 1"),
            seed + 1,
            "bogus",
        ),
        (
            "sim: wrong type",
            sim_with("call_overhead_s = 0.002", "call_overhead_s = \"fast\""),
            overhead,
            "instrument.call_overhead_s",
        ),
        (
            "sim: out of range",
            sim_with("call_overhead_s = 0.002", "call_overhead_s = -1.0"),
            overhead,
            "instrument.call_overhead_s",
        ),
    ] {
        cases.push((
            what,
            "bad-sim.toml",
            text,
            job("plan.toml", "bad-sim.toml"),
            "bad-sim.toml",
            line,
            field,
        ));
    }
    for (what, job_text, line, field) in [
        (
            "job: unknown top-level field",
            job("plan.toml", "sim.toml").replacen("[backend]", "extra_table = 2\n[backend]", 1),
            2,
            "extra_table",
        ),
        (
            "job: unknown backend field",
            format!("{}colour = 3\n", job("plan.toml", "sim.toml")),
            5,
            "backend.colour",
        ),
        (
            "job: wrong type",
            job("plan.toml", "sim.toml").replace("kind = \"sim\"", "kind = 5"),
            3,
            "backend.kind",
        ),
    ] {
        cases.push((
            what,
            "unused.toml",
            String::new(),
            job_text,
            "job.toml",
            line,
            field,
        ));
    }
    for (what, file, text, job_text, named, line, field) in &cases {
        write(&dir, file, text);
        let job_path = write(&dir, "job.toml", job_text);
        let (code, _, stderr) = spmcal(&[
            "calibrate",
            "--config",
            &job_path,
            "--out",
            dir.join("out").to_str().unwrap(),
        ]);
        assert_eq!(code, 2, "{what}: {stderr}");
        assert!(
            stderr.contains(&format!("{named}:{line}")),
            "{what}: stderr {stderr:?} should name {named}:{line}"
        );
        assert!(
            stderr.contains(&format!("`{field}`")),
            "{what}: stderr {stderr:?} should name field {field}"
        );
        assert!(!stderr.contains("panicked"), "{what}: {stderr}");
    }
    assert!(
        !dir.join("out").join("cdb.sqlite").exists(),
        "a bad config must not create a CDB"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_cdb_with_a_newer_schema_is_refused_and_left_byte_identical() {
    let dir = std::env::temp_dir().join(format!("spmcal-newer-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cdb_path = dir.join("newer.sqlite");
    {
        let cdb = spm_cdb::Cdb::open(&cdb_path).unwrap();
        let newer = spm_cdb::SCHEMA_VERSION + 1;
        cdb.connection()
            .pragma_update(None, "user_version", newer)
            .unwrap();
    }
    let before = std::fs::read(&cdb_path).unwrap();
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let job = write(
        &dir,
        "job.toml",
        &format!(
            "plan_file = {:?}\n[backend]\nkind = \"sim\"\nsim_config = {:?}\n",
            root.join("configs/plan-hopg-small.toml")
                .display()
                .to_string(),
            root.join("configs/sim-hopg.toml").display().to_string()
        ),
    );
    let db = cdb_path.to_str().unwrap();
    let out = dir.join("out");
    let csv = dir.join("x.csv");
    let surfaces = dir.join("s.json");
    for args in [
        vec![
            "calibrate",
            "--config",
            &job,
            "--cdb",
            db,
            "--out",
            out.to_str().unwrap(),
        ],
        vec![
            "calibrate",
            "--config",
            &job,
            "--cdb",
            db,
            "--resume",
            "--out",
            out.to_str().unwrap(),
        ],
        vec!["cdb", "check", db],
        vec!["cdb", "export", db, "--csv", csv.to_str().unwrap()],
        vec!["cdb", "trend", db],
        vec!["fit", "--cdb", db, "--out", surfaces.to_str().unwrap()],
    ] {
        let (code, _, stderr) = spmcal(&args);
        assert_eq!(code, 2, "{args:?}: {stderr}");
        assert!(
            stderr.contains("newer.sqlite") && stderr.contains("newer than this program"),
            "{args:?}: {stderr}"
        );
        assert_eq!(
            std::fs::read(&cdb_path).unwrap(),
            before,
            "{args:?} changed the file"
        );
    }
    assert!(!csv.exists() && !surfaces.exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// `spmcal simulate --like FILE --config SIM.toml --out OUT.sxm`: the measured
/// file's scan program on the simulator, written as a Nanonis file that the
/// readers (and `spmcal info`) take like the original; the nominal calibration
/// sets the commanded pixels.
#[test]
fn simulate_copies_the_scan_program_of_a_measured_file() {
    let scratch = std::env::temp_dir().join(format!("spmcal-sim-{}", std::process::id()));
    std::fs::create_dir_all(&scratch).unwrap();
    let like = spmcal_tests::measured_file("si7x7-nanonis/Si_7x7_051.sxm");
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/sim-hopg.toml");
    let out = scratch.join("sim.sxm");
    let (code, _, stderr) = spmcal(&[
        "simulate",
        "--like",
        like.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--nominal-nm-per-count",
        "0.02",
    ]);
    assert_eq!(code, 0, "{stderr}");
    let original = spm_formats::read_any(&like).unwrap();
    let simulated = spm_formats::read_any(&out).unwrap();
    assert_eq!(simulated.pixels(), original.pixels());
    assert_eq!(simulated.size_nm(), original.size_nm());
    assert_eq!(simulated.scan_dir, original.scan_dir);
    assert_eq!(simulated.line_time_s, original.line_time_s);
    assert_eq!(simulated.recorded, original.recorded);
    assert_eq!(simulated.channels.len(), 2, "forward and backward Z");
    // A missing config is bad input naming the flag's file.
    check(
        &[
            "simulate",
            "--like",
            like.to_str().unwrap(),
            "--config",
            scratch.join("missing.toml").to_str().unwrap(),
            "--out",
            scratch.join("x.sxm").to_str().unwrap(),
        ],
        2,
        "missing.toml",
    );
    let _ = std::fs::remove_dir_all(&scratch);
}

/// `spmcal scan` keeps the command history beside the image; `correct` applies the
/// calibration's dynamics along it (and says so), `--static` does not, and a damaged history is
/// refused with exit 2 naming the sidecar and the field.
#[test]
fn a_scanned_image_is_corrected_along_its_recorded_history() {
    let dir = std::env::temp_dir().join(format!("spmcal-scan-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let job = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/calibrate-hopg-quick.toml");
    let image = dir.join("img.gsf");
    let (code, _, stderr) = spmcal(&[
        "scan",
        "--config",
        job.to_str().unwrap(),
        "--out",
        image.to_str().unwrap(),
        "--size-counts",
        "1024",
        "--pixels",
        "48",
        "--x-counts",
        "-3000",
        "--settle-s",
        "1",
    ]);
    assert_eq!(code, 0, "{stderr}");
    let sidecar = dir.join("img.gsf.history.json");
    assert!(sidecar.is_file());
    // A calibration with dynamics: a uniform field, one play operator, creep.
    let calibration = dynamics_calibration(&dir);
    let correct = |out: &str, extra: &[&str]| {
        let out = dir.join(out);
        let mut args = vec![
            "correct",
            image.to_str().unwrap(),
            "--calibration",
            calibration.to_str().unwrap(),
            "--out",
        ];
        let out_text = out.to_str().unwrap().to_owned();
        args.push(&out_text);
        args.extend_from_slice(extra);
        spmcal(&args)
    };
    let (code, stdout, stderr) = correct("recorded.gsf", &[]);
    assert_eq!(code, 0, "{stderr}");
    assert!(stdout.contains("recorded history"), "{stdout}");
    let (code, stdout, stderr) = correct("static.gsf", &["--static"]);
    assert_eq!(code, 0, "{stderr}");
    assert!(stdout.contains("none (static field)"), "{stdout}");
    let recorded = std::fs::read(dir.join("recorded.gsf")).unwrap();
    let fixed = std::fs::read(dir.join("static.gsf")).unwrap();
    assert_ne!(recorded, fixed, "the dynamics changed nothing");
    // A damaged history: exit 2, the sidecar and the field named, nothing written.
    let text = std::fs::read_to_string(&sidecar).unwrap();
    std::fs::write(&sidecar, text.replacen("\"version\":1", "\"version\":7", 1)).unwrap();
    let (code, _, stderr) = correct("damaged.gsf", &[]);
    assert_eq!(code, 2, "{stderr}");
    assert!(
        stderr.contains("history.json") && stderr.contains("`format`"),
        "{stderr}"
    );
    assert!(!dir.join("damaged.gsf").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// `spmcal correct --counter FILE`: a direct image and its counter-scanned partner of one
/// place (HOPG atoms resolved, no history sidecar), corrected with the drift measured between
/// them: exit 0, the dynamics used named, the estimate in the output's metadata. Refused with
/// exit 2, naming the option, nothing written: no feature spacing, a partner of another size,
/// `--counter-delay` without `--counter`.
#[test]
fn an_image_is_corrected_with_its_counter_scanned_partner() {
    let dir = std::env::temp_dir().join(format!("spmcal-counter-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let job = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/calibrate-hopg-quick.toml");
    let scan = |name: &str, pixels: &str, counter: bool| {
        let out = dir.join(name);
        let mut args = vec![
            "scan",
            "--config",
            job.to_str().unwrap(),
            "--size-counts",
            "128",
            "--pixels",
            pixels,
            "--x-counts",
            "-3000",
            "--settle-s",
            "1",
            "--out",
        ];
        let out_text = out.to_str().unwrap().to_owned();
        args.push(&out_text);
        if counter {
            args.push("--counter");
        }
        let (code, _, stderr) = spmcal(&args);
        assert_eq!(code, 0, "{stderr}");
        // A file alone: no recorded history.
        std::fs::remove_file(dir.join(format!("{name}.history.json"))).unwrap();
        out
    };
    let direct = scan("direct.gsf", "96", false);
    let counter = scan("counter.gsf", "96", true);
    let small = scan("small.gsf", "64", true);
    let calibration = dynamics_calibration(&dir);
    let correct = |out: &str, extra: &[&str]| {
        let mut args = vec![
            "correct",
            direct.to_str().unwrap(),
            "--calibration",
            calibration.to_str().unwrap(),
            "--out",
        ];
        let out_text = dir.join(out).to_str().unwrap().to_owned();
        args.push(&out_text);
        args.extend_from_slice(extra);
        spmcal(&args)
    };
    let partner = counter.to_str().unwrap();
    let (code, stdout, stderr) = correct(
        "paired.gsf",
        &[
            "--counter",
            partner,
            "--feature-nm",
            "0.246",
            "--counter-delay",
            "10",
        ],
    );
    assert_eq!(code, 0, "{stderr}");
    assert!(stdout.contains("counter-scanned partner"), "{stdout}");
    let out = spm_formats::read_any(dir.join("paired.gsf")).unwrap();
    let drift = out.header_value("spmcal_counter_drift_nm_per_s").unwrap();
    assert_eq!(drift.split_whitespace().count(), 2, "{drift}");
    assert!(
        out.header_value("spmcal_dynamics")
            .is_some_and(|d| d.contains("counter partner")),
        "{:?}",
        out.header_value("spmcal_dynamics")
    );
    for (name, extra, needle) in [
        ("no-spacing.gsf", vec!["--counter", partner], "--feature-nm"),
        (
            "small.gsf.out.gsf",
            vec![
                "--counter",
                small.to_str().unwrap(),
                "--feature-nm",
                "0.246",
                "--counter-delay",
                "10",
            ],
            "not a counter-scanned partner",
        ),
        ("no-partner.gsf", vec!["--counter-delay", "10"], "--counter"),
    ] {
        let (code, _, stderr) = correct(name, &extra);
        assert_eq!(code, 2, "{name}: {stderr}");
        assert!(stderr.contains(needle), "{name}: {stderr}");
        assert!(!dir.join(name).exists(), "{name} was written");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `spmcal scan --out IMAGE.sxm` writes what a Nanonis controller writes: both halves named
/// by the direction of their lines (forward = +x), the slow direction, the line time and
/// spmcal's raster in counts. Independent truth for a counter raster (−x lines first,
/// stepping down): the same scan written as `.gsf` (its trace only, labelled backward) must
/// look like the `.sxm`'s backward half in display orientation, and less like its forward
/// half (the retrace, displaced by the raster's hysteresis); `correct` then corrects both
/// halves along the recorded history.
#[test]
fn a_scanned_sxm_names_its_halves_as_nanonis_does() {
    let dir = std::env::temp_dir().join(format!("spmcal-scan-sxm-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let job = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/calibrate-hopg-quick.toml");
    let scan = |out: &Path| {
        let (code, _, stderr) = spmcal(&[
            "scan",
            "--config",
            job.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--size-counts",
            "1024",
            "--pixels",
            "48",
            "--x-counts",
            "-3000",
            "--settle-s",
            "1",
            "--counter",
        ]);
        assert_eq!(code, 0, "{stderr}");
    };
    let sxm = dir.join("counter.sxm");
    let gsf = dir.join("counter.gsf");
    scan(&sxm);
    scan(&gsf);
    assert!(dir.join("counter.sxm.history.json").is_file());
    let file = spm_formats::read_any(&sxm).unwrap();
    assert_eq!(file.format, spm_formats::Format::NanonisSxm);
    assert_eq!(file.scan_dir, Some(spm_formats::ScanDir::Down));
    assert_eq!(file.header_value("spmcal_scan_path"), Some("counter"));
    let line_time = file.line_time_s.unwrap();
    let dwell = line_time / 48.0;
    assert!(dwell > 0.0 && (line_time - 48.0 * dwell).abs() < 1e-12);
    let half = |d: spm_formats::Direction| {
        file.channels
            .iter()
            .find(|c| c.direction() == d)
            .unwrap()
            .data()
            .to_vec()
    };
    let (forward, backward) = (
        half(spm_formats::Direction::Forward),
        half(spm_formats::Direction::Backward),
    );
    let trace = spm_formats::read_any(&gsf).unwrap();
    assert_eq!(
        trace.channels[0].direction(),
        spm_formats::Direction::Backward
    );
    let trace = trace.channels[0].data().to_vec();
    let correlation = |a: &[f64], b: &[f64]| {
        let n = a.len() as f64;
        let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
        let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
        for (x, y) in a.iter().zip(b) {
            ab += (x - ma) * (y - mb);
            aa += (x - ma) * (x - ma);
            bb += (y - mb) * (y - mb);
        }
        ab / (aa * bb).sqrt()
    };
    let flipped: Vec<f64> = backward
        .chunks(48)
        .rev()
        .flat_map(|r| r.iter().copied())
        .collect();
    let (same, other, upside_down) = (
        correlation(&backward, &trace),
        correlation(&forward, &trace),
        correlation(&flipped, &trace),
    );
    assert!(
        same > 0.9 && same > other + 0.02 && upside_down < 0.5,
        "correlation with the trace: backward {same}, forward {other}, backward upside down \
         {upside_down}"
    );
    // Both halves corrected along the recorded history (a calibration with dynamics).
    let calibration = dynamics_calibration(&dir);
    let out = dir.join("counter.corrected.gwy");
    let (code, stdout, stderr) = spmcal(&[
        "correct",
        sxm.to_str().unwrap(),
        "--calibration",
        calibration.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    assert!(
        stdout.contains("2 channel(s)") && stdout.contains("recorded history"),
        "{stdout}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `DIR/calibration.json`: a uniform field of scanner `sim-hopg` (0.02 nm/count, ±30 000
/// counts) with dynamics (one fast-axis play operator pair, creep).
#[allow(clippy::unwrap_used)] // test set-up: a failure here is the test failing
fn dynamics_calibration(dir: &Path) -> std::path::PathBuf {
    use spm_correction::hysteresis::{
        CreepParameters, DYNAMICS_FORMAT, DYNAMICS_FORMAT_VERSION, DynamicsIdentification,
        PlayHysteresis, ScannerDynamics,
    };
    let mut plane = spm_correction::PlaneSurfaces::constant(0.0, 0.02, 0.02, 0.0).unwrap();
    plane.calibrated_region_counts = Some(spm_correction::CountRegion {
        x_min_counts: -30_000.0,
        x_max_counts: 30_000.0,
        y_min_counts: -30_000.0,
        y_max_counts: 30_000.0,
    });
    let mut set = spm_correction::SurfaceSet::new(
        spm_correction::Provenance {
            scanner_id: "sim-hopg".into(),
            n_records: 100,
            nominal_nm_per_count: Some(0.02),
            counts_convention: Some(spm_correction::CountsConvention::CentredSigned),
            ..spm_correction::Provenance::default()
        },
        vec![plane],
    )
    .unwrap();
    set.dynamics = Some(ScannerDynamics {
        format: DYNAMICS_FORMAT.to_owned(),
        version: DYNAMICS_FORMAT_VERSION,
        hysteresis_x: PlayHysteresis {
            thresholds_counts: vec![100.0, 300.0],
            weights: vec![0.02, 0.03],
        },
        hysteresis_y: PlayHysteresis::none(),
        creep: CreepParameters {
            weight: 0.005,
            min_time_constant_s: 0.01,
            max_time_constant_s: 1e4,
            elements_per_decade: 3,
        },
        identification: DynamicsIdentification::default(),
    });
    let calibration = dir.join("calibration.json");
    std::fs::write(&calibration, set.to_json_string().unwrap()).unwrap();
    calibration
}

/// Issue 27: a successful run keeps the console quiet (no warnings, no colour codes: the
/// details go to `OUT/calibrate.log`), names `report.html`, and records its provenance — the
/// job's files with their SHA-256, checked here against an independent digest, and the
/// simulator's seed as the config states it.
#[test]
fn a_run_logs_to_its_folder_keeps_the_console_quiet_and_records_its_provenance() {
    use sha2::Digest as _;
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let dir = std::env::temp_dir().join(format!("spmcal-provenance-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let config = root.join("configs/calibrate-hopg-quick.toml");
    let (code, stdout, stderr) = spmcal(&[
        "calibrate",
        "--config",
        config.to_str().unwrap(),
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    assert!(
        !stderr.contains("WARN"),
        "warnings on the console: {stderr}"
    );
    assert!(
        !stderr.contains('\u{1b}'),
        "colour codes into a pipe: {stderr:?}"
    );
    assert!(
        stdout.contains(&format!("report: {}", dir.join("report.html").display())),
        "{stdout}"
    );
    let log = std::fs::read_to_string(dir.join("calibrate.log")).expect("calibrate.log");
    assert!(log.contains("calibration run starts"), "{log}");
    assert!(!log.contains('\u{1b}'));
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
    let p = &report["provenance"];
    let digest: String = sha2::Sha256::digest(std::fs::read(&config).unwrap())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    assert_eq!(p["inputs"][0]["path"], config.to_str().unwrap());
    assert_eq!(p["inputs"][0]["sha256"], digest.as_str());
    let sim: toml::Value =
        toml::from_str(&std::fs::read_to_string(root.join("configs/sim-hopg.toml")).unwrap())
            .unwrap();
    assert_eq!(
        p["seed"].as_i64(),
        sim["seed"].as_integer(),
        "the seed of configs/sim-hopg.toml"
    );
    let (started, finished) = (
        p["started_utc"].as_str().unwrap(),
        p["finished_utc"].as_str().unwrap(),
    );
    assert!(
        started.ends_with('Z') && started <= finished,
        "{started} {finished}"
    );
    assert_eq!(p["spmcal_version"], env!("CARGO_PKG_VERSION"));
    assert!(report["validation"]["held_out"]["nodes"].as_u64() > Some(0));
    let _ = std::fs::remove_dir_all(&dir);
}

/// Issue 23: the dynamics stage of the quick job identifies what the simulated scanner hides
/// (`configs/sim-hopg.toml`, read here as the truth): the fast axis's hysteresis loop at every
/// ladder line outside its dead band within 10 % of the simulator's operator, the slow
/// axis's from the counter-scanned pairs likewise at the two largest sizes, the creep law's
/// log slope within 10 %, and its shortest time constant — chosen from the data, not fixed —
/// within a fifth of a decade of the simulator's (the fixed 0.01 s of before was 0.3 off).
#[test]
fn the_dynamics_stage_finds_the_simulators_hysteresis_and_creep() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let dir = std::env::temp_dir().join(format!("spmcal-dynamics-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let config = root.join("configs/calibrate-hopg-quick.toml");
    let (code, _, stderr) = spmcal(&[
        "calibrate",
        "--config",
        config.to_str().unwrap(),
        "--quick",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
    let d = &report["dynamics"];
    let sim: toml::Value =
        toml::from_str(&std::fs::read_to_string(root.join("configs/sim-hopg.toml")).unwrap())
            .unwrap();
    let creep = &sim["scanner"]["creep"];
    let true_tau = creep["min_time_constant_s"].as_float().unwrap();
    let true_gamma = creep["log_slope_per_decade"].as_float().unwrap();
    let tau = d["creep_min_time_constant_s"].as_f64().unwrap();
    assert!(
        (tau / true_tau).log10().abs() < 0.2,
        "shortest creep time constant {tau} s against the simulator's {true_tau} s"
    );
    let gamma = d["creep_gamma_per_decade"].as_f64().unwrap();
    assert!(
        (gamma / true_gamma - 1.0).abs() < 0.1,
        "creep γ {gamma} against {true_gamma}"
    );
    let trials = d["model"]["identification"]["creep_fast_end_trials"]
        .as_array()
        .unwrap();
    assert!(trials.len() >= 5, "{trials:?}");
    let mut loops = 0;
    for row in d["loops_x"].as_array().unwrap() {
        let want = row["true_separation_centre_counts"].as_f64().unwrap();
        if want < 1.0 {
            continue; // inside the dead band
        }
        let got = row["separation_centre_counts"].as_f64().unwrap();
        assert!(
            (got / want - 1.0).abs() < 0.1,
            "loop at {} counts: {got} against {want}",
            row["length_counts"]
        );
        loops += 1;
    }
    assert!(loops >= 3, "{d}");
    // The slow axis, from the counter-scanned pairs: every pair tracked, and the loop of the
    // two largest within 10 % of the simulator's (the 2049-count loop, 12 counts, is 4
    // pixels: there the tracking's precision shows, and it is not asserted).
    assert_eq!(d["slow_pairs_used"], d["slow_pairs"], "{d}");
    let loops_y = d["loops_y"].as_array().unwrap();
    assert!(loops_y.len() >= 3, "{d}");
    for row in loops_y
        .iter()
        .filter(|r| r["length_counts"].as_f64() > Some(8000.0))
    {
        let want = row["true_separation_centre_counts"].as_f64().unwrap();
        let got = row["separation_centre_counts"].as_f64().unwrap();
        assert!(
            (got / want - 1.0).abs() < 0.1,
            "y loop at {} counts: {got} against {want}",
            row["length_counts"]
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `spmcal crop`: the two halves of a real `.sxm` (both halves of Z and Current: 4 channels)
/// come out as `.gsf` per channel and as one `.gwy`; the `.gsf` halves tile the frame (their
/// offsets ∓ a quarter of the 20 nm side); a part leaving the image, a bad range or an
/// output it cannot write is exit 2 naming the option, and writes nothing.
#[test]
fn crop_writes_the_halves_of_a_real_file_and_refuses_bad_parts() {
    let scratch = std::env::temp_dir().join(format!("spmcal-crop-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&scratch);
    std::fs::create_dir_all(&scratch).unwrap();
    let sxm = spmcal_tests::measured_file("si7x7-nanonis/Si_7x7_051.sxm");
    let sxm = sxm.to_str().unwrap();
    for (columns, centre_nm) in [("0..128", -5.0), ("128..256", 5.0)] {
        let out = scratch.join(format!("half-{columns}.gsf"));
        let (code, stdout, stderr) = spmcal(&[
            "crop",
            sxm,
            "--columns",
            columns,
            "--out",
            out.to_str().unwrap(),
        ]);
        assert_eq!(code, 0, "{stderr}");
        assert_eq!(stdout.lines().count(), 4, "{stdout}");
        let z = stdout.lines().find(|l| l.contains(".Z.forward.")).unwrap();
        let part = spm_formats::read_any(z).unwrap();
        assert_eq!(part.pixels(), Some([128, 256]));
        let c = &part.channels[0];
        assert!((c.center_x_nm().unwrap() - centre_nm).abs() < 1e-9);
        assert!(c.center_y_nm().unwrap().abs() < 1e-9);
        assert!((c.size_x_nm().unwrap() - 10.0).abs() < 1e-9);
    }
    let gwy = scratch.join("half.gwy");
    let (code, _, stderr) = spmcal(&[
        "crop",
        sxm,
        "--rows",
        "0..100",
        "--out",
        gwy.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    assert!(std::fs::metadata(&gwy).unwrap().len() > 4 * 256 * 100 * 4);
    let bad = scratch.join("bad.gsf");
    for (args, named) in [
        (vec!["--columns", "0..300"], "--columns"),
        (vec!["--rows", "10..10"], "--rows"),
        (vec!["--columns", "left"], "--columns"),
    ] {
        let mut all = vec!["crop", sxm, "--out", bad.to_str().unwrap()];
        all.extend(args);
        let (code, _, stderr) = spmcal(&all);
        assert_eq!(code, 2, "{stderr}");
        assert!(stderr.contains(named), "{stderr}");
        assert!(!bad.exists());
    }
    let png = scratch.join("half.png");
    let (code, _, stderr) = spmcal(&["crop", sxm, "--out", png.to_str().unwrap()]);
    assert_eq!(code, 2, "{stderr}");
    assert!(stderr.contains(".png"), "{stderr}");
    assert!(!png.exists());
    let _ = std::fs::remove_dir_all(&scratch);
}

/// Issue 27 item 2: a run that misses a target its plan declares exits with code 3 after
/// writing its report, and prints the verdict; `--no-targets` prints it and exits 0; a met
/// target passes. The plan: the quick 3 × 3 job with `distributed_over_lumped_rms_max` first
/// at 0.1 (a 3 × 3 net cannot reach it), then at 10. The verdict is checked against the
/// figures report.json holds (the ratio of the two RMS residuals of its accuracy table,
/// measured against the simulator's oracle), not against the program's own verdict. The
/// last run's CDB then gives `cdb trend --png` its history figure.
#[test]
fn a_missed_target_exits_3_with_its_verdict_and_no_targets_exits_0() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let dir = std::env::temp_dir().join(format!("spmcal-targets-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let plan_text = std::fs::read_to_string(root.join("configs/plan-hopg-small.toml")).unwrap();
    let job_with = |name: &str, max: f64| {
        let plan = write(
            &dir,
            &format!("plan-{name}.toml"),
            &format!("{plan_text}\n[plan.targets]\ndistributed_over_lumped_rms_max = {max}\n"),
        );
        write(
            &dir,
            &format!("job-{name}.toml"),
            &format!(
                "plan_file = {plan:?}\n[backend]\nkind = \"sim\"\nsim_config = {:?}\n",
                root.join("configs/sim-hopg.toml").display().to_string()
            ),
        )
    };
    let ratio_of = |out: &Path| {
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap())
                .unwrap();
        let a = &report["accuracy"];
        (
            a["distributed"]["rms_pm"].as_f64().unwrap() / a["lumped"]["rms_pm"].as_f64().unwrap(),
            report["targets"][0]["outcome"].as_str().unwrap().to_owned(),
        )
    };
    let missed = job_with("missed", 0.1);
    for (flag, expected_code) in [(None, 3), (Some("--no-targets"), 0)] {
        let out = dir.join(format!("out-{expected_code}"));
        let mut args = vec![
            "calibrate",
            "--config",
            &missed,
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend(flag);
        let (code, stdout, stderr) = spmcal(&args);
        let (ratio, outcome) = ratio_of(&out);
        assert!(
            ratio > 0.1,
            "the 3 × 3 net reaches {ratio}: pick another target"
        );
        assert_eq!(code, expected_code, "{flag:?}: {stdout}\n{stderr}");
        assert_eq!(outcome, "fail");
        assert!(
            stdout.contains(&format!(
                "target distributed ÷ lumped RMS residual distortion ≤ 0.1: {ratio:.3} → FAIL"
            )),
            "{stdout}"
        );
        assert!(out.join("report.html").exists(), "the report is written");
        if expected_code == 3 {
            assert!(
                stderr.contains("missed 1 of the targets") && stderr.contains("job-missed.toml"),
                "{stderr}"
            );
        } else {
            assert!(stdout.contains("--no-targets"), "{stdout}");
        }
    }
    let met = job_with("met", 10.0);
    let out = dir.join("out-met");
    let (code, stdout, stderr) = spmcal(&[
        "calibrate",
        "--config",
        &met,
        "--out",
        out.to_str().unwrap(),
    ]);
    let (ratio, outcome) = ratio_of(&out);
    assert!(ratio <= 10.0, "{ratio}");
    assert_eq!((code, outcome.as_str()), (0, "pass"), "{stdout}\n{stderr}");
    assert!(stdout.contains("→ PASS"), "{stdout}");
    // The CDB's history as a figure (`cdb trend --png`); never written over the CDB.
    let db = out.join("cdb.sqlite");
    let png = dir.join("trend.png");
    let args = [
        "cdb",
        "trend",
        db.to_str().unwrap(),
        "--png",
        png.to_str().unwrap(),
    ];
    let (code, stdout, stderr) = spmcal(&args);
    assert_eq!(code, 0, "{stderr}");
    assert!(
        stdout.contains("K̄x") && stdout.contains("figure: "),
        "{stdout}"
    );
    let bytes = std::fs::read(&png).unwrap();
    assert!(bytes.starts_with(&[0x89, b'P', b'N', b'G']));
    let before = std::fs::read(&db).unwrap();
    let (code, _, stderr) = spmcal(&[
        "cdb",
        "trend",
        db.to_str().unwrap(),
        "--png",
        db.to_str().unwrap(),
    ]);
    assert_eq!(code, 2, "the CDB is not replaced by its figure: {stderr}");
    assert_eq!(std::fs::read(&db).unwrap(), before);
    let _ = std::fs::remove_dir_all(&dir);
}
