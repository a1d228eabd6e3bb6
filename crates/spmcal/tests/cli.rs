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
