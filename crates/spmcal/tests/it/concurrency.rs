//! Readers during a run (issue 8): `spmcal cdb export` and `spmcal fit` run while
//! `spmcal calibrate` writes, and see transactionally consistent snapshots.
//!
//! Every export taken during the run must be exactly the first N rows (in acquisition order)
//! of the export taken after it — whole committed nodes, each row byte-identical to its
//! final version, no duplicate visit — and every fit must succeed on a record count between
//! the exports taken just before and just after it. Before the writer has created the schema,
//! an export is refused cleanly ("empty database", exit 2); that is tolerated only until the
//! first export succeeds.
//!
//! The same test runs on the embedded SQLite file and on a shared PostgreSQL database (a
//! private server started by `spm_cdb::pg_server`), whose schema is likewise created in one
//! transaction.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .ancestors()
        .nth(2)
        .expect("crates/spmcal lives in the workspace")
        .to_path_buf()
}

fn spmcal(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_spmcal"))
        .args(args)
        .env("NO_COLOR", "1")
        .output()
        .expect("spmcal runs")
}

/// Exports the CDB and returns its data rows (header checked and dropped). The CDB is
/// created atomically (spm-cdb builds it aside and links it into place), so a reader that
/// finds the file never sees it half made.
fn export(cdb: &str, csv: &Path) -> Vec<String> {
    let out = spmcal(&["cdb", "export", cdb, "--csv", csv.to_str().unwrap()]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "export: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = std::fs::read_to_string(csv).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some(spm_cdb::CSV_HEADER.as_str()));
    let rows: Vec<String> = lines.map(str::to_owned).collect();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.starts_with(&format!("{} records", rows.len())),
        "{stdout}"
    );
    rows
}

/// (repeat, node) of a CSV row.
fn visit(row: &str) -> (u32, u32) {
    let f: Vec<&str> = row.split(',').collect();
    (f[4].parse().unwrap(), f[5].parse().unwrap())
}

#[test]
fn export_and_fit_during_a_run_see_consistent_snapshots() {
    let dir = std::env::temp_dir().join(format!("spmcal-concurrency-{}", std::process::id()));
    let cdb = dir.join("cdb.sqlite");
    readers_during_a_run(&dir, cdb.to_str().unwrap(), &|| cdb.is_file());
}

#[test]
fn postgres_export_and_fit_during_a_run_see_consistent_snapshots() {
    let dir = std::env::temp_dir().join(format!("spmcal-concurrency-pg-{}", std::process::id()));
    let server = spm_cdb::pg_server::TestServer::start()
        .unwrap_or_else(|e| panic!("cannot start the private PostgreSQL server: {e}"));
    let url = server.create_database("concurrency").unwrap();
    let has_schema = || {
        let mut c = postgres::Client::connect(&url, postgres::NoTls).unwrap();
        c.query_one("SELECT to_regclass('schema_version') IS NOT NULL", &[])
            .unwrap()
            .get(0)
    };
    readers_during_a_run(&dir, &url, &has_schema);
}

/// Runs a calibration into `cdb` (a path or URL) and exports and fits while it writes;
/// `exists()` tells whether the writer has created the CDB yet.
fn readers_during_a_run(dir: &Path, cdb: &str, exists: &dyn Fn() -> bool) {
    let _ = std::fs::remove_dir_all(dir);
    std::fs::create_dir_all(dir).unwrap();
    let root = workspace_root();
    let plan = std::fs::read_to_string(root.join("configs/plan-hopg-small.toml"))
        .unwrap()
        .replace("step_counts = 20000", "step_counts = 3000")
        .replace("repeats = 1 ", "repeats = 2 ");
    // The dynamics stage off: it writes no record, and its frames and identification after
    // the last visit would only keep the readers polling a CDB that no longer changes.
    assert!(plan.contains("[plan.dynamics]\n"));
    let plan = plan.replacen("[plan.dynamics]\n", "[plan.dynamics]\nenabled = false\n", 1);
    std::fs::write(dir.join("plan.toml"), plan).unwrap();
    let job = dir.join("job.toml");
    std::fs::write(
        &job,
        format!(
            "plan_file = \"plan.toml\"\n[backend]\nkind = \"sim\"\nsim_config = {:?}\n",
            root.join("configs/sim-hopg.toml").display().to_string()
        ),
    )
    .unwrap();
    let mut writer = Command::new(env!("CARGO_BIN_EXE_spmcal"))
        .args([
            "calibrate",
            "--config",
            job.to_str().unwrap(),
            "--cdb",
            cdb,
            "--out",
            dir.join("out").to_str().unwrap(),
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();

    let mut snapshots: Vec<Vec<String>> = Vec::new();
    let mut fits: Vec<(usize, u64, usize)> = Vec::new();
    let mut i = 0;
    let status = loop {
        if let Some(status) = writer.try_wait().unwrap() {
            break status;
        }
        if !exists() {
            std::thread::sleep(std::time::Duration::from_millis(20));
            continue;
        }
        i += 1;
        let before = export(cdb, &dir.join(format!("export-{i}.csv")));
        let n_before = before.len();
        snapshots.push(before);
        if n_before >= 40 {
            let surfaces = dir.join(format!("surfaces-{i}.json"));
            let out = spmcal(&["fit", "--cdb", cdb, "--out", surfaces.to_str().unwrap()]);
            assert_eq!(
                out.status.code(),
                Some(0),
                "fit with {n_before} records: {}",
                String::from_utf8_lossy(&out.stderr)
            );
            let json: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&surfaces).unwrap()).unwrap();
            let used = json["provenance"]["n_records"]
                .as_u64()
                .expect("provenance.n_records");
            let after = export(cdb, &dir.join(format!("export-{i}b.csv")));
            fits.push((n_before, used, after.len()));
            snapshots.push(after);
        }
    };
    assert_eq!(status.code(), Some(0), "calibrate");

    let last = export(cdb, &dir.join("final.csv"));
    let final_count = last.len();
    let mut seen = HashSet::new();
    assert!(last.iter().all(|r| seen.insert(visit(r))), "a visit twice");
    let mut mid_run = 0;
    for (k, s) in snapshots.iter().enumerate() {
        assert!(s.len() <= final_count);
        assert_eq!(
            s.as_slice(),
            &last[..s.len()],
            "snapshot {k} ({} rows) is not a prefix of the final export",
            s.len()
        );
        if !s.is_empty() && s.len() < final_count {
            mid_run += 1;
        }
    }
    for (n_before, used, n_after) in &fits {
        assert!(
            (*n_before as u64..=*n_after as u64).contains(used),
            "fit used {used} records, exports saw {n_before} before and {n_after} after"
        );
    }
    let mid_run_fits = fits.iter().filter(|f| (f.1 as usize) < final_count).count();
    eprintln!(
        "{} exports ({mid_run} mid-run), {} fits ({mid_run_fits} mid-run), {final_count} records",
        snapshots.len(),
        fits.len()
    );
    assert!(mid_run >= 3, "only {mid_run} exports landed mid-run");
    assert!(mid_run_fits >= 2, "only {mid_run_fits} fits landed mid-run");
    let _ = std::fs::remove_dir_all(dir);
}
