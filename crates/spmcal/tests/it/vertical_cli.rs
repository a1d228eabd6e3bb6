//! The vertical-axis job on the command line (issue 15): a plan whose Z levels move a coarse
//! stage the backend does not have is refused with exit 2 naming the field, before anything
//! runs.

use std::path::Path;
use std::process::Command;

fn root() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
}

#[test]
fn a_plan_needing_a_missing_coarse_stage_is_refused_naming_the_field() {
    let scratch = std::env::temp_dir().join(format!("spmcal-vertical-cli-{}", std::process::id()));
    std::fs::create_dir_all(&scratch).expect("scratch");
    // The 3d scenario without its [instrument.coarse_z] table.
    let sim = std::fs::read_to_string(root().join("configs/sim-hopg-3d.toml")).expect("sim");
    let start = sim
        .find("[instrument.coarse_z]")
        .expect("a coarse stage table");
    let end = start + sim[start..].find("\n\n").expect("its end");
    std::fs::write(
        scratch.join("sim.toml"),
        format!("{}{}", &sim[..start], &sim[end..]),
    )
    .expect("write");
    std::fs::copy(
        root().join("configs/plan-hopg-3d.toml"),
        scratch.join("plan.toml"),
    )
    .expect("plan");
    let job = scratch.join("job.toml");
    std::fs::write(
        &job,
        "plan_file = \"plan.toml\"\n[backend]\nkind = \"sim\"\nsim_config = \"sim.toml\"\n",
    )
    .expect("job");
    let out = scratch.join("out");
    let output = Command::new(env!("CARGO_BIN_EXE_spmcal"))
        .args(["calibrate", "--config"])
        .arg(&job)
        .arg("--out")
        .arg(&out)
        .output()
        .expect("spmcal runs");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(2), "stderr: {stderr}");
    assert!(
        stderr.contains("plan.net.z_levels.coarse_steps") && stderr.contains("plan.toml"),
        "stderr should name the file and field: {stderr}"
    );
    assert!(!out.join("cdb.sqlite").exists(), "nothing ran");
    let _ = std::fs::remove_dir_all(&scratch);
}
