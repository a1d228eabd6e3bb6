//! Issue 25 item 15: a CDB overwritten while a reader runs crashed the reader with SIGBUS
//! (exit 135): the connections mapped up to 1 GiB of the file, and a mapped page past the
//! end of a file that shrank is a bus error. Now no connection maps the file.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_cdb::bench_support::{SCANNER_ID, T0_UNIX_S, synthetic_record};
use spm_cdb::{Cdb, CdbRead, RecordFilter, RunInfo, RunStatus};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

fn scratch(name: &str) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .join(format!("spm-cdb-mmap-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A CDB of `n` synthetic records in one run.
fn synthetic(path: &Path, n: u64) {
    let mut cdb = Cdb::open(path).unwrap();
    let run = RunInfo {
        run_id: "bulk".into(),
        scanner_id: SCANNER_ID.into(),
        config: String::new(),
        started_unix_s: T0_UNIX_S,
        finished_unix_s: None,
        status: RunStatus::Running,
    };
    cdb.create_run(&run).unwrap();
    let ids = vec![run.run_id];
    cdb.import_records((0..n).map(|i| synthetic_record(i, n, &ids)))
        .unwrap();
}

fn mmap_size(cdb: &Cdb) -> i64 {
    cdb.connection()
        .pragma_query_value(None, "mmap_size", |r| r.get(0))
        .unwrap()
}

#[test]
fn no_connection_maps_the_file() {
    let dir = scratch("pragma");
    let path = dir.join("c.sqlite");
    synthetic(&path, 10);
    assert_eq!(mmap_size(&Cdb::open(&path).unwrap()), 0, "read-write");
    let ro = Cdb::open_read_only(&path).unwrap();
    assert_eq!(mmap_size(&ro), 0, "read-only");
    // A snapshot reads through the same connection.
    let snapshot = ro.snapshot().unwrap();
    assert_eq!(
        snapshot.count_records(&RecordFilter::default()).unwrap(),
        10
    );
    assert_eq!(mmap_size(&ro), 0, "read-only, in a snapshot");
    drop(snapshot);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The child's part of [`a_file_truncated_under_a_reader_is_an_error_not_a_bus_error`]:
/// reads a CDB and truncates it (as `cp other.sqlite c.sqlite` does) at the first record.
#[test]
#[ignore = "run by a_file_truncated_under_a_reader_is_an_error_not_a_bus_error"]
fn truncated_under_a_reader_child() {
    let Some(path) = std::env::var_os("SPM_CDB_TRUNCATE_UNDER_READER") else {
        return;
    };
    let cdb = Cdb::open_read_only(&path).unwrap();
    // A scan in table order through the reader's connection: it reads the file page by
    // page while it steps (the library's queries may sort first and read everything).
    let mut stmt = cdb
        .connection()
        .prepare("SELECT lcs_x_counts FROM records")
        .unwrap();
    let mut rows = stmt.query([]).unwrap();
    let mut seen = 0_u64;
    let result = loop {
        match rows.next() {
            Ok(Some(_)) => {
                if seen == 0 {
                    std::fs::File::create(&path).unwrap();
                }
                seen += 1;
            }
            Ok(None) => break Ok(()),
            Err(e) => break Err(e),
        }
    };
    println!("reader ended after {seen} records: {result:?}");
}

#[test]
fn a_file_truncated_under_a_reader_is_an_error_not_a_bus_error() {
    let dir = scratch("truncate");
    let path = dir.join("c.sqlite");
    synthetic(&path, 40_000);
    let out = std::process::Command::new(std::env::current_exe().unwrap())
        .args([
            "--exact",
            // Its name in the one test binary of spm-cdb (tests/it/main.rs): module, then fn.
            "mmap::truncated_under_a_reader_child",
            "--ignored",
            "--nocapture",
        ])
        .env("SPM_CDB_TRUNCATE_UNDER_READER", &path)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && stdout.contains("reader ended after"),
        "the reader crashed ({:?}): {stdout}{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The read path's cost of no mmap: `columns` of 10⁶ records (one plane, the regression's
/// query) with the connection's `mmap_size` 0 and 1 GiB (what it was), best of 3 each.
/// `cargo test -p spm-cdb --test it -- --ignored --nocapture mmap::read_path_cost`
#[test]
#[ignore = "timing, 10^6 records"]
fn read_path_cost_of_no_mmap() {
    let dir = scratch("cost");
    let path = dir.join("c.sqlite");
    synthetic(&path, 1_000_000);
    let cdb = Cdb::open_read_only(&path).unwrap();
    let time = |size: i64| {
        cdb.connection()
            .pragma_update(None, "mmap_size", size)
            .unwrap();
        (0..3)
            .map(|_| {
                let start = Instant::now();
                let c = cdb.columns(&RecordFilter::default()).unwrap();
                assert_eq!(c.kx_nm_per_count.len(), 1_000_000);
                start.elapsed()
            })
            .min()
            .unwrap_or(Duration::ZERO)
    };
    for _ in 0..2 {
        let (without, with) = (time(0), time(1 << 30));
        println!(
            "columns of 10^6 records: mmap_size 0 {:.3} s, 1 GiB {:.3} s ({:+.0} %)",
            without.as_secs_f64(),
            with.as_secs_f64(),
            100.0 * (without.as_secs_f64() / with.as_secs_f64() - 1.0)
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
