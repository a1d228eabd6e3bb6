//! CDB tests: round trip, resume, queries, age dynamics, export, migration from v1, refusal of
//! a newer schema without modification, snapshot isolation across threads, integrity check.
//!
//! The bodies that hold for every back end run on both (`sqlite::*` and `postgres::*`, through
//! a store factory, [`common::Backend`]); the PostgreSQL tests start a private server once per
//! test binary. Tests of one back end's file or schema mechanics are named for it.
#![allow(clippy::unwrap_used)]

use crate::common;
use crate::on_both_backends; // #[macro_export]ed by common: at the crate root

use common::{Backend, T0, db_path, plan, record, run};
use rusqlite::Connection;
use spm_cdb::{
    Cdb, CdbRead, Coefficient, ErrorKind, LccRecord, NodeDone, NodeState, RecordFilter, RunStatus,
    SCHEMA_VERSION, TrendGrouping,
};

fn done(node_index: u32, t: f64) -> NodeDone {
    NodeDone {
        repeat_index: 0,
        node_index,
        attempts: 1,
        finished_unix_s: t,
    }
}

on_both_backends!(
    round_trip_queries_and_resume,
    commit_node_is_atomic_and_validated,
    age_dynamics_and_export,
    reader_snapshot_is_consistent_while_writer_commits,
    reads_always_see_whole_nodes,
    integrity_check_finds_corruption,
    concurrent_runs_of_four_scanners_lose_nothing,
    dynamics_are_stored_dated_per_scanner_and_validated,
    integrity_check_finds_bad_dynamics,
);

fn round_trip_queries_and_resume(b: &'static dyn Backend) {
    let path = b.fresh("round_trip");
    let r = run("run-1", "scanner-A", T0);
    let nodes = plan(3);
    let mut stored: Vec<LccRecord> = Vec::new();
    {
        let mut cdb = b.open(&path);
        assert_eq!(cdb.schema_version().unwrap(), SCHEMA_VERSION);
        cdb.create_run(&r).unwrap();
        assert_eq!(cdb.create_run(&r).unwrap_err().kind(), ErrorKind::Conflict);
        cdb.register_plan(&r.run_id, &nodes).unwrap();
        cdb.register_plan(&r.run_id, &nodes).unwrap(); // idempotent
        // nodes 0..4 measured (node 1 with two LCSs), node 4 given up, node 5 left pending
        for n in &nodes[..4] {
            let t = T0 + 60.0 * f64::from(n.node_index);
            let mut recs = vec![record(&r, n, 0, t)];
            if n.node_index == 1 {
                recs.push(record(&r, n, 1, t + 1.0));
            }
            cdb.commit_node(&r.run_id, &done(n.node_index, t + 2.0), &recs)
                .unwrap();
            stored.extend(recs);
        }
        cdb.give_up_node(
            &r.run_id,
            0,
            4,
            "no LCS found in 5 apertures",
            5,
            T0 + 400.0,
        )
        .unwrap();
        // simulated crash: dropped without finishing the run
    }
    let mut cdb = b.open(&path);
    let all = cdb.records(&RecordFilter::default()).unwrap();
    assert_eq!(all, stored);
    let next = cdb.next_pending(&r.run_id).unwrap().unwrap();
    assert_eq!(next, nodes[5]);
    let s = cdb.progress_summary(&r.run_id).unwrap();
    assert_eq!((s.pending, s.done, s.given_up), (1, 4, 1));
    let prog = cdb.progress(&r.run_id).unwrap();
    assert_eq!(
        prog[4].state,
        NodeState::GivenUp("no LCS found in 5 apertures".into())
    );
    assert_eq!(prog[4].attempts, 5);

    // queries: scanner, Z plane, time window, run
    let check = |filter: RecordFilter, expected: usize| {
        let got = cdb.records(&filter).unwrap();
        assert_eq!(got.len(), expected, "{filter:?}");
        assert_eq!(cdb.count_records(&filter).unwrap(), expected as u64);
        assert_eq!(cdb.columns(&filter).unwrap().len(), expected);
    };
    check(RecordFilter::scanner("scanner-A"), 5);
    check(RecordFilter::scanner("scanner-B"), 0);
    check(RecordFilter::scanner("scanner-A").with_z_plane(0), 4);
    check(RecordFilter::scanner("scanner-A").with_z_plane(500), 1);
    check(
        RecordFilter::default().with_window(Some(T0 + 60.0), Some(T0 + 120.0)),
        3,
    );
    check(
        RecordFilter::default().with_window(Some(T0 + 61.0), None),
        3,
    );
    check(
        RecordFilter::default().with_window(Some(T0 + 62.0), None),
        2,
    );
    check(RecordFilter::default().with_run("run-1"), 5);
    check(RecordFilter::default().with_run("nope"), 0);
    assert_eq!(cdb.z_planes("scanner-A").unwrap(), vec![0, 500]);
    assert_eq!(cdb.scanners().unwrap(), vec!["scanner-A".to_string()]);
    let bad = RecordFilter::default().with_window(Some(f64::NAN), None);
    assert_eq!(
        cdb.records(&bad).unwrap_err().kind(),
        ErrorKind::InvalidInput
    );

    // resume: finish the last node, close the run
    let last = nodes[5];
    cdb.commit_node(
        &r.run_id,
        &done(5, T0 + 500.0),
        &[record(&r, &last, 0, T0 + 499.0)],
    )
    .unwrap();
    assert_eq!(cdb.next_pending(&r.run_id).unwrap(), None);
    cdb.finish_run(&r.run_id, RunStatus::Finished, T0 + 600.0)
        .unwrap();
    let info = cdb.run(&r.run_id).unwrap().unwrap();
    assert_eq!(
        (info.status, info.finished_unix_s),
        (RunStatus::Finished, Some(T0 + 600.0))
    );
    assert_eq!(cdb.runs(Some("scanner-A")).unwrap().len(), 1);
    assert!(cdb.check().unwrap().is_ok(), "{:?}", cdb.check().unwrap());
}

fn commit_node_is_atomic_and_validated(b: &'static dyn Backend) {
    let path = b.fresh("atomic");
    let r = run("run-1", "S", T0);
    let nodes = plan(2);
    let mut cdb = b.open(&path);
    cdb.create_run(&r).unwrap();
    cdb.register_plan(&r.run_id, &nodes).unwrap();
    let n0 = nodes[0];
    // duplicate LCS index inside one node: the second insert fails, the first is rolled back
    let dup = [record(&r, &n0, 0, T0), record(&r, &n0, 0, T0)];
    assert_eq!(
        cdb.commit_node(&r.run_id, &done(0, T0), &dup)
            .unwrap_err()
            .kind(),
        ErrorKind::Conflict
    );
    assert_eq!(cdb.count_records(&RecordFilter::default()).unwrap(), 0);
    assert_eq!(cdb.next_pending(&r.run_id).unwrap(), Some(n0));
    // invalid values
    let shown = b.shown(&path);
    let check_invalid = |cdb: &mut Box<dyn common::Store>, edit: fn(&mut LccRecord)| {
        let mut rec = record(&r, &n0, 0, T0);
        edit(&mut rec);
        let e = cdb
            .commit_node(&r.run_id, &done(0, T0), &[rec])
            .unwrap_err();
        assert_eq!(e.kind(), ErrorKind::InvalidInput, "{e}");
        assert_eq!(e.path(), shown.as_path());
    };
    check_invalid(&mut cdb, |r| r.kx_nm_per_count = f64::NAN);
    check_invalid(&mut cdb, |r| r.ky_nm_per_count = -0.02);
    check_invalid(&mut cdb, |r| r.kz_nm_per_count = Some(0.0));
    check_invalid(&mut cdb, |r| r.alpha_rad = 2.0);
    check_invalid(&mut cdb, |r| r.u_alpha_rad = Some(-1.0));
    check_invalid(&mut cdb, |r| r.drift_vx_nm_per_s = f64::INFINITY);
    check_invalid(&mut cdb, |r| r.node_index = 1); // belongs to another node
    check_invalid(&mut cdb, |r| r.node_x_counts += 1); // not the plan node's coordinates
    check_invalid(&mut cdb, |r| r.scanner_id = "other".into());
    assert_eq!(
        cdb.commit_node(&r.run_id, &done(0, T0), &[])
            .unwrap_err()
            .kind(),
        ErrorKind::InvalidInput
    );
    assert_eq!(cdb.count_records(&RecordFilter::default()).unwrap(), 0);
    // unknown node / run, double commit, give up after done
    assert_eq!(
        cdb.commit_node(&r.run_id, &done(99, T0), &[record(&r, &n0, 0, T0)])
            .unwrap_err()
            .kind(),
        ErrorKind::NotFound
    );
    assert_eq!(
        cdb.commit_node("nope", &done(0, T0), &[record(&r, &n0, 0, T0)])
            .unwrap_err()
            .kind(),
        ErrorKind::NotFound
    );
    cdb.commit_node(&r.run_id, &done(0, T0), &[record(&r, &n0, 0, T0)])
        .unwrap();
    assert_eq!(
        cdb.commit_node(&r.run_id, &done(0, T0), &[record(&r, &n0, 1, T0)])
            .unwrap_err()
            .kind(),
        ErrorKind::Conflict
    );
    assert_eq!(
        cdb.give_up_node(&r.run_id, 0, 0, "x", 1, T0)
            .unwrap_err()
            .kind(),
        ErrorKind::Conflict
    );
    assert_eq!(
        cdb.give_up_node(&r.run_id, 0, 1, " ", 1, T0)
            .unwrap_err()
            .kind(),
        ErrorKind::InvalidInput
    );
    assert_eq!(
        cdb.finish_run("nope", RunStatus::Failed, T0)
            .unwrap_err()
            .kind(),
        ErrorKind::NotFound
    );
    // a plan re-registered with other coordinates is refused
    let mut moved = nodes.clone();
    moved[1].node_x_counts += 7;
    assert_eq!(
        cdb.register_plan(&r.run_id, &moved).unwrap_err().kind(),
        ErrorKind::Conflict
    );
    assert!(cdb.check().unwrap().is_ok());
}

fn age_dynamics_and_export(b: &'static dyn Backend) {
    let path = b.fresh("trend");
    let mut cdb = b.open(&path);
    let nodes = plan(3);
    let day = 86_400.0;
    // three runs, 30 days apart; K̄x at the three nodes of plane 0 = base + (0, 1, 2)·1e-3
    let mut all = Vec::new();
    for (k, base) in [0.020, 0.0205, 0.021].into_iter().enumerate() {
        let r = run(&format!("run-{k}"), "S", T0 + 30.0 * day * k as f64);
        cdb.create_run(&r).unwrap();
        for (i, n) in nodes[..3].iter().enumerate() {
            let mut rec = record(&r, n, 0, r.started_unix_s + 10.0 * i as f64);
            rec.kx_nm_per_count = base + 1e-3 * i as f64;
            rec.kz_nm_per_count = None;
            all.push(rec);
        }
    }
    assert_eq!(cdb.import_records(&all).unwrap(), 9);
    let trend = cdb
        .age_dynamics(
            &RecordFilter::scanner("S"),
            Coefficient::KxNmPerCount,
            TrendGrouping::PerRun,
        )
        .unwrap();
    assert_eq!(trend.len(), 3);
    for (k, (p, base)) in trend.iter().zip([0.020, 0.0205, 0.021]).enumerate() {
        assert_eq!(p.key, format!("run-{k}"));
        let s = p.stat.unwrap();
        assert_eq!(s.n, 3);
        assert!((s.mean - (base + 1e-3)).abs() < 1e-15);
        assert!((s.std_dev - 1e-3).abs() < 1e-15); // sd of (0, 1, 2)·1e-3 with n − 1
        assert!((s.std_uncertainty - 1e-3 / 3.0_f64.sqrt()).abs() < 1e-15);
        assert!((p.mean_unix_s - (T0 + 30.0 * day * k as f64 + 10.0)).abs() < 1e-6);
    }
    let by_day = cdb
        .age_dynamics(
            &RecordFilter::default(),
            Coefficient::KzNmPerCount,
            TrendGrouping::PerDay,
        )
        .unwrap();
    assert_eq!(
        by_day.iter().map(|p| p.key.as_str()).collect::<Vec<_>>(),
        ["2024-01-01", "2024-01-31", "2024-03-01"]
    );
    assert!(by_day.iter().all(|p| p.stat.is_none())); // Kz not measured
    let per_node = cdb
        .age_dynamics(
            &RecordFilter::default(),
            Coefficient::AlphaRad,
            TrendGrouping::PerNodePerRun,
        )
        .unwrap();
    assert_eq!(per_node.len(), 9);
    assert_eq!(per_node[0].key, "0,0,0@run-0");

    // CSV: header + 9 lines; times as RFC 3339; values round-trip through text
    let mut csv = Vec::new();
    assert_eq!(
        cdb.export_csv(&RecordFilter::default(), &mut csv).unwrap(),
        9
    );
    let csv = String::from_utf8(csv).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines.len(), 10);
    assert_eq!(lines[0], spm_cdb::CSV_HEADER.as_str());
    let cols: Vec<&str> = lines[1].split(',').collect();
    assert_eq!(cols.len(), lines[0].split(',').count());
    assert_eq!(cols[0], "2024-01-01T00:00:00Z");
    assert_eq!(cols[13].parse::<f64>().unwrap(), all[0].kx_nm_per_count);
    // JSON: parses back into the same records
    let mut json = Vec::new();
    assert_eq!(
        cdb.export_json(&RecordFilter::scanner("S"), &mut json)
            .unwrap(),
        9
    );
    let v: serde_json::Value = serde_json::from_slice(&json).unwrap();
    assert_eq!(v["schema_version"], SCHEMA_VERSION);
    let back: Vec<LccRecord> = serde_json::from_value(v["records"].clone()).unwrap();
    // serde_json's default float parser may be 1 ulp off; the text itself is exact (ryu)
    assert_eq!(back.len(), all.len());
    for (b, a) in back.iter().zip(&all) {
        assert_eq!(
            (&b.run_id, b.node_index, b.cycles_kept),
            (&a.run_id, a.node_index, a.cycles_kept)
        );
        assert!((b.kx_nm_per_count - a.kx_nm_per_count).abs() <= 1e-15 * a.kx_nm_per_count);
        assert!((b.ky_nm_per_count - a.ky_nm_per_count).abs() <= 1e-15 * a.ky_nm_per_count);
        assert_eq!(b.u_kz_nm_per_count, a.u_kz_nm_per_count);
    }
}

/// Schema v1 as shipped: records without standard uncertainties.
const V1_DDL: &str = "
CREATE TABLE runs (run_id TEXT PRIMARY KEY NOT NULL, scanner_id TEXT NOT NULL, config TEXT NOT NULL,
  started_unix_s REAL NOT NULL, finished_unix_s REAL,
  status TEXT NOT NULL CHECK (status IN ('running', 'finished', 'failed', 'aborted')));
CREATE INDEX runs_scanner ON runs (scanner_id, started_unix_s);
CREATE TABLE progress (run_id TEXT NOT NULL REFERENCES runs (run_id), repeat_index INTEGER NOT NULL,
  node_index INTEGER NOT NULL, node_x_counts INTEGER NOT NULL, node_y_counts INTEGER NOT NULL,
  node_z_counts INTEGER NOT NULL, state TEXT NOT NULL CHECK (state IN ('pending', 'done', 'given_up')),
  reason TEXT, attempts INTEGER NOT NULL DEFAULT 0, updated_unix_s REAL,
  PRIMARY KEY (run_id, repeat_index, node_index)) WITHOUT ROWID;
CREATE TABLE records (id INTEGER PRIMARY KEY, scanner_id TEXT NOT NULL,
  run_id TEXT NOT NULL REFERENCES runs (run_id), acquired_unix_s REAL NOT NULL,
  repeat_index INTEGER NOT NULL, node_index INTEGER NOT NULL, lcs_index INTEGER NOT NULL DEFAULT 0,
  node_x_counts INTEGER NOT NULL, node_y_counts INTEGER NOT NULL, node_z_counts INTEGER NOT NULL,
  lcs_x_counts REAL NOT NULL, lcs_y_counts REAL NOT NULL, lcs_z_counts REAL NOT NULL,
  kx_nm_per_count REAL NOT NULL, ky_nm_per_count REAL NOT NULL, alpha_rad REAL NOT NULL,
  kz_nm_per_count REAL, drift_vx_nm_per_s REAL NOT NULL, drift_vy_nm_per_s REAL NOT NULL,
  cycles_kept INTEGER NOT NULL, cycles_discarded INTEGER NOT NULL, quality REAL NOT NULL);
CREATE UNIQUE INDEX records_node ON records (run_id, repeat_index, node_index, lcs_index);
CREATE INDEX records_plane ON records (scanner_id, node_z_counts, acquired_unix_s);
INSERT INTO runs VALUES ('old-run', 'S', '', 1600000000.0, 1600000900.0, 'finished');
INSERT INTO progress VALUES ('old-run', 0, 0, 0, 0, 0, 'done', NULL, 1, 1600000100.0);
INSERT INTO progress VALUES ('old-run', 0, 1, 1000, 0, 0, 'pending', NULL, 0, NULL);
INSERT INTO records (scanner_id, run_id, acquired_unix_s, repeat_index, node_index, lcs_index,
  node_x_counts, node_y_counts, node_z_counts, lcs_x_counts, lcs_y_counts, lcs_z_counts,
  kx_nm_per_count, ky_nm_per_count, alpha_rad, kz_nm_per_count, drift_vx_nm_per_s,
  drift_vy_nm_per_s, cycles_kept, cycles_discarded, quality)
  VALUES ('S', 'old-run', 1600000050.0, 0, 0, 0, 0, 0, 0, 0.5, -0.5, 0.0,
          0.0201, 0.0199, 0.0012, NULL, 0.01, 0.02, 6, 1, 0.8);
PRAGMA application_id = 1397771587;
PRAGMA user_version = 1;
";

#[test]
fn migrates_v1_file() {
    let path = db_path("migrate_v1");
    Connection::open(&path)
        .unwrap()
        .execute_batch(V1_DDL)
        .unwrap();
    // read-only cannot migrate: refused, file untouched
    let before = std::fs::read(&path).unwrap();
    let e = Cdb::open_read_only(&path).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::OutdatedSchema);
    assert_eq!(std::fs::read(&path).unwrap(), before);

    let mut cdb = Cdb::open(&path).unwrap();
    // v1 → v2 → v3 → v4 → v5 in one open; the stored values are untouched, the new columns
    // NULL.
    assert_eq!(cdb.schema_version().unwrap(), SCHEMA_VERSION);
    assert_eq!(SCHEMA_VERSION, 5);
    let old = cdb.records(&RecordFilter::default()).unwrap();
    assert_eq!(old.len(), 1);
    assert_eq!(old[0].kx_nm_per_count, 0.0201);
    assert_eq!((old[0].lcs_x_counts, old[0].quality), (0.5, 0.8));
    assert_eq!((old[0].u_kx_nm_per_count, old[0].u_alpha_rad), (None, None));
    assert_eq!((old[0].kz_x_counts, old[0].kz_y_counts), (None, None));
    assert!(cdb.check().unwrap().is_ok(), "{:?}", cdb.check().unwrap());
    // the migrated file takes v2 records and resumes the old plan
    let r = cdb.run("old-run").unwrap().unwrap();
    let next = cdb.next_pending("old-run").unwrap().unwrap();
    assert_eq!(next.node_x_counts, 1000);
    cdb.commit_node(
        "old-run",
        &done(1, 1600000200.0),
        &[record(&r, &next, 0, 1600000190.0)],
    )
    .unwrap();
    let all = cdb.records(&RecordFilter::default()).unwrap();
    assert_eq!(all[1].u_kx_nm_per_count, Some(1e-5));
    drop(cdb);
    // reopening is a no-op; read-only now works
    let ro = Cdb::open_read_only(&path).unwrap();
    assert_eq!(ro.count_records(&RecordFilter::default()).unwrap(), 2);
}

#[test]
fn refuses_newer_schema_without_touching_file() {
    let path = db_path("newer");
    Connection::open(&path)
        .unwrap()
        .execute_batch(
            "CREATE TABLE records (id INTEGER PRIMARY KEY, future TEXT);
             INSERT INTO records (future) VALUES ('from v99');
             PRAGMA application_id = 1397771587; PRAGMA user_version = 99;",
        )
        .unwrap();
    let before = std::fs::read(&path).unwrap();
    let mtime = std::fs::metadata(&path).unwrap().modified().unwrap();
    std::thread::sleep(std::time::Duration::from_millis(20));
    for e in [
        Cdb::open(&path).unwrap_err(),
        Cdb::open_read_only(&path).unwrap_err(),
    ] {
        assert_eq!(e.kind(), ErrorKind::NewerSchema);
        assert_eq!(e.path(), path.as_path());
        let msg = e.to_string();
        assert!(
            msg.contains("99") && msg.contains(&path.display().to_string()),
            "{msg}"
        );
    }
    assert_eq!(std::fs::read(&path).unwrap(), before);
    assert_eq!(std::fs::metadata(&path).unwrap().modified().unwrap(), mtime);
    let mut wal = path.clone().into_os_string();
    wal.push("-wal");
    assert!(!std::path::Path::new(&wal).exists());
}

#[test]
fn refuses_foreign_files() {
    let garbage = db_path("garbage");
    std::fs::write(&garbage, b"this is not a database, it is a text file of some length ...................................................................").unwrap();
    assert_eq!(Cdb::open(&garbage).unwrap_err().kind(), ErrorKind::NotACdb);
    let other = db_path("other_app");
    Connection::open(&other)
        .unwrap()
        .execute_batch("CREATE TABLE t (a);")
        .unwrap();
    assert_eq!(Cdb::open(&other).unwrap_err().kind(), ErrorKind::NotACdb);
    let missing = db_path("missing");
    assert_eq!(
        Cdb::open_read_only(&missing).unwrap_err().kind(),
        ErrorKind::NotFound
    );
    let opts = spm_cdb::OpenOptions {
        create: false,
        ..Default::default()
    };
    assert_eq!(
        Cdb::open_with(&missing, &opts).unwrap_err().kind(),
        ErrorKind::NotFound
    );
}

fn reader_snapshot_is_consistent_while_writer_commits(b: &'static dyn Backend) {
    use std::sync::{Arc, Barrier};
    let path = b.fresh("snapshot");
    let r = run("run-1", "S", T0);
    let nodes = plan(50);
    {
        let mut cdb = b.open(&path);
        cdb.create_run(&r).unwrap();
        cdb.register_plan(&r.run_id, &nodes).unwrap();
        cdb.commit_node(&r.run_id, &done(0, T0), &[record(&r, &nodes[0], 0, T0)])
            .unwrap();
    }
    let barrier = Arc::new(Barrier::new(2));
    let writer = {
        let (path, barrier, r, nodes) = (path.clone(), barrier.clone(), r.clone(), nodes.clone());
        std::thread::spawn(move || {
            let mut cdb = b.open(&path);
            barrier.wait(); // reader holds its snapshot
            for n in &nodes[1..] {
                let recs = [record(&r, n, 0, T0 + 1.0), record(&r, n, 1, T0 + 2.0)];
                cdb.commit_node(&r.run_id, &done(n.node_index, T0 + 3.0), &recs)
                    .unwrap();
            }
            barrier.wait(); // all committed
        })
    };
    let reader = b.open(&path);
    {
        let snap = reader.snapshot().unwrap();
        let n0 = snap.count_records(&RecordFilter::default()).unwrap();
        let s0 = snap.progress_summary(&r.run_id).unwrap();
        assert_eq!((n0, s0.done), (1, 1));
        barrier.wait();
        // while the writer commits, and after it has finished, the snapshot does not move
        let mut seen = 0;
        loop {
            let n = snap.count_records(&RecordFilter::default()).unwrap();
            let s = snap.progress_summary(&r.run_id).unwrap();
            assert_eq!((n, s.done), (n0, s0.done));
            seen += 1;
            if writer.is_finished() || seen > 10_000 {
                break;
            }
            std::thread::yield_now();
        }
        barrier.wait();
        assert_eq!(snap.count_records(&RecordFilter::default()).unwrap(), n0);
    }
    writer.join().unwrap();
    // a new read sees everything; each read is consistent: 2 records per node after node 0
    let s = reader.progress_summary(&r.run_id).unwrap();
    assert_eq!(s.done, 100);
    assert_eq!(
        reader.count_records(&RecordFilter::default()).unwrap(),
        1 + 2 * 99
    );
    assert!(reader.check().unwrap().is_ok());
}

fn reads_always_see_whole_nodes(b: &'static dyn Backend) {
    // A reader polling without an explicit snapshot never sees a node half committed.
    let path = b.fresh("whole_nodes");
    let r = run("run-1", "S", T0);
    let nodes = plan(40);
    {
        let mut cdb = b.open(&path);
        cdb.create_run(&r).unwrap();
        cdb.register_plan(&r.run_id, &nodes).unwrap();
    }
    let writer = {
        let (path, r, nodes) = (path.clone(), r.clone(), nodes.clone());
        std::thread::spawn(move || {
            let mut cdb = b.open(&path);
            for n in &nodes {
                let recs: Vec<_> = (0..3).map(|k| record(&r, n, k, T0)).collect();
                cdb.commit_node(&r.run_id, &done(n.node_index, T0), &recs)
                    .unwrap();
            }
        })
    };
    let reader = b.open(&path);
    while !writer.is_finished() {
        let snap = reader.snapshot().unwrap();
        let done = snap.progress_summary(&r.run_id).unwrap().done;
        let n = snap.count_records(&RecordFilter::default()).unwrap();
        assert_eq!(n, 3 * done);
        assert!(snap.check().unwrap().problems.is_empty());
    }
    writer.join().unwrap();
    assert_eq!(reader.count_records(&RecordFilter::default()).unwrap(), 240);
}

fn integrity_check_finds_corruption(b: &'static dyn Backend) {
    let path = b.fresh("corrupt");
    let r = run("run-1", "S", T0);
    let nodes = plan(3);
    {
        let mut cdb = b.open(&path);
        cdb.create_run(&r).unwrap();
        cdb.register_plan(&r.run_id, &nodes).unwrap();
        cdb.commit_node(&r.run_id, &done(0, T0), &[record(&r, &nodes[0], 0, T0)])
            .unwrap();
        assert!(cdb.check().unwrap().is_ok());
    }
    let insert = |lcs: u32, kx: &str, alpha: &str| {
        b.raw_sql(
            &path,
            &format!(
                "INSERT INTO records (scanner_id, run_id, acquired_unix_s, repeat_index, node_index,
              lcs_index, node_x_counts, node_y_counts, node_z_counts, lcs_x_counts, lcs_y_counts,
              lcs_z_counts, kx_nm_per_count, ky_nm_per_count, alpha_rad, drift_vx_nm_per_s,
              drift_vy_nm_per_s, cycles_kept, cycles_discarded, quality)
             VALUES ('S', 'run-1', {T0}, 0, 0, {lcs}, 0, 0, 0, 0, 0, 0, {kx}, 0.02, {alpha},
                     0, 0, 1, 0, 1)"
            ),
        );
    };
    insert(1, "-0.02", "0.0"); // K̄x ≤ 0
    insert(2, b.infinity_literal(), "0.0"); // +∞
    insert(3, "0.02", "2.0"); // |α| ≥ π/2
    b.raw_sql(
        &path,
        "UPDATE progress SET state = 'done' WHERE node_index = 1;
         UPDATE progress SET state = 'given_up', reason = NULL WHERE node_index = 2;",
    );
    let cdb = b.open(&path);
    let report = cdb.check().unwrap();
    let kinds: Vec<&str> = report.problems.iter().map(|p| p.kind.as_str()).collect();
    for expected in [
        "nonpositive_lcc",
        "non_finite",
        "alpha_out_of_range",
        "done_without_records",
        "given_up_without_reason",
    ] {
        assert!(
            kinds.contains(&expected),
            "{expected} missing in {report:?}"
        );
    }
    assert!(!report.is_ok());
    assert!(
        report
            .problems
            .iter()
            .any(|p| p.detail.contains("kx_nm_per_count"))
    );
    // every problem was found once: 3 bad records, 1 done node without records, 1 given up
    // without a reason
    assert_eq!(report.problems.len(), 5, "{report:?}");
}

/// SQLite stores any value in any column: a text value where a number belongs is a typed
/// Corrupt error on read, not a panic. (PostgreSQL's column types refuse such a value.)
#[test]
fn sqlite_text_in_a_number_column_is_corrupt() {
    let path = db_path("corrupt_text");
    let r = run("run-1", "S", T0);
    let nodes = plan(3);
    {
        let mut cdb = Cdb::open(&path).unwrap();
        cdb.create_run(&r).unwrap();
        cdb.register_plan(&r.run_id, &nodes).unwrap();
        cdb.commit_node(&r.run_id, &done(0, T0), &[record(&r, &nodes[0], 0, T0)])
            .unwrap();
    }
    let raw = Connection::open(&path).unwrap();
    insert_text(&raw);
    drop(raw);
    let cdb = Cdb::open(&path).unwrap();
    let e = cdb.records(&RecordFilter::default()).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Corrupt, "{e}");
    assert!(
        cdb.check()
            .unwrap()
            .problems
            .iter()
            .any(|p| p.kind == "non_finite" && p.detail.contains("quality"))
    );
}

/// Four instruments calibrate into one database at once, each its own run and scanner, one
/// connection each: every node is committed exactly once with all its records, nothing is
/// lost or duplicated, and the check is clean.
fn concurrent_runs_of_four_scanners_lose_nothing(b: &'static dyn Backend) {
    let path = b.fresh("four_scanners");
    drop(b.open(&path)); // the schema exists before the writers race
    let nodes = plan(15);
    let writers: Vec<_> = (0..4)
        .map(|k| {
            let (path, nodes) = (path.clone(), nodes.clone());
            std::thread::spawn(move || {
                let mut cdb = b.open(&path);
                let r = run(&format!("run-{k}"), &format!("scanner-{k}"), T0);
                cdb.create_run(&r).unwrap();
                cdb.register_plan(&r.run_id, &nodes).unwrap();
                for n in &nodes {
                    let recs: Vec<_> = (0..2)
                        .map(|l| record(&r, n, l, T0 + f64::from(n.node_index)))
                        .collect();
                    // SQLite serialises writers with its lock (busy timeout); PostgreSQL
                    // commits different runs' nodes side by side.
                    cdb.commit_node(&r.run_id, &done(n.node_index, T0), &recs)
                        .unwrap();
                }
                cdb.finish_run(&r.run_id, RunStatus::Finished, T0 + 100.0)
                    .unwrap();
            })
        })
        .collect();
    for w in writers {
        w.join().unwrap();
    }
    let cdb = b.open(&path);
    assert_eq!(cdb.scanners().unwrap().len(), 4);
    for k in 0..4 {
        let filter = RecordFilter::scanner(&format!("scanner-{k}"));
        assert_eq!(cdb.count_records(&filter).unwrap(), 2 * nodes.len() as u64);
        let mut keys: Vec<(u32, u32)> = cdb
            .records(&filter)
            .unwrap()
            .iter()
            .map(|r| (r.node_index, r.lcs_index))
            .collect();
        keys.sort_unstable();
        keys.dedup();
        assert_eq!(keys.len(), 2 * nodes.len());
        let s = cdb.progress_summary(&format!("run-{k}")).unwrap();
        assert_eq!((s.pending, s.done), (0, nodes.len() as u64));
    }
    assert!(cdb.check().unwrap().is_ok(), "{:?}", cdb.check().unwrap());
}

fn insert_text(raw: &Connection) {
    raw.execute_batch(&format!(
        "INSERT INTO records (scanner_id, run_id, acquired_unix_s, repeat_index, node_index,
          lcs_index, node_x_counts, node_y_counts, node_z_counts, lcs_x_counts, lcs_y_counts,
          lcs_z_counts, kx_nm_per_count, ky_nm_per_count, alpha_rad, drift_vx_nm_per_s,
          drift_vy_nm_per_s, cycles_kept, cycles_discarded, quality)
         VALUES ('S', 'run-1', {T0}, 0, 0, 9, 0, 0, 0, 0, 0, 0, 0.02, 0.02, 0.0, 0, 0, 1, 0,
                 'excellent')"
    ))
    .unwrap();
}

/// A new CDB appears complete or not at all: readers racing its creation never see an
/// empty file, and the creator leaves no temporary file behind.
#[test]
fn creation_is_atomic_for_racing_readers() {
    let path = db_path("atomic_creation");
    let dir = path.parent().unwrap().to_path_buf();
    let reader_path = path.clone();
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let stop_reader = stop.clone();
    let reader = std::thread::spawn(move || {
        let mut seen = 0u32;
        while !stop_reader.load(std::sync::atomic::Ordering::Relaxed) {
            if reader_path.exists() {
                match Cdb::open_read_only(&reader_path) {
                    Ok(cdb) => {
                        assert_eq!(cdb.schema_version().unwrap(), spm_cdb::SCHEMA_VERSION);
                        seen += 1;
                    }
                    Err(e) => panic!("reader saw a half-made CDB: {e}"),
                }
            }
        }
        seen
    });
    let cdb = Cdb::open(&path).unwrap();
    std::thread::sleep(std::time::Duration::from_millis(50));
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    assert!(reader.join().unwrap() > 0, "the reader never saw the CDB");
    drop(cdb);
    let leftovers: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains("atomic_creation") && n.contains(".creating-"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

/// The `records` table holds exactly the columns of `spm_records::LCC_RECORD_COLUMNS` (after
/// the surrogate key), with the SQL type and nullability of each column's kind: the schema text
/// and the one column list cannot diverge. (The physical order follows the migrations: the
/// uncertainties were appended by v2; every statement names its columns.)
#[test]
fn records_table_matches_the_one_column_list() {
    let path = db_path("column_list");
    drop(Cdb::open(&path).unwrap());
    let conn = Connection::open(&path).unwrap();
    let mut stmt = conn.prepare("PRAGMA table_info(records)").unwrap();
    let stored: std::collections::BTreeMap<String, (String, bool)> = stmt
        .query_map([], |r| {
            Ok((r.get(1)?, (r.get(2)?, r.get::<_, i64>(3)? != 0)))
        })
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    let expected: std::collections::BTreeMap<String, (String, bool)> =
        spm_records::LCC_RECORD_COLUMNS
            .iter()
            .map(|col| {
                let (sql_type, not_null) = match col.kind {
                    spm_records::ColumnKind::Text => ("TEXT", true),
                    spm_records::ColumnKind::Real => ("REAL", true),
                    spm_records::ColumnKind::OptionalReal => ("REAL", false),
                    spm_records::ColumnKind::Integer => ("INTEGER", true),
                };
                (col.name.to_owned(), (sql_type.to_owned(), not_null))
            })
            .chain([("id".to_owned(), ("INTEGER".to_owned(), false))])
            .collect();
    assert_eq!(stored, expected);
}

// ---------------------------------------------------------------------------------------
// PostgreSQL: schema versions, migration, refusals, column list, one node from two programs.

use spm_cdb::postgres::PgCdb;

/// v1 data as a v1 program stored it (no standard uncertainties).
const PG_V1_DATA: &str = "
INSERT INTO runs VALUES ('old-run', 'S', '', 1600000000.0, 1600000900.0, 'finished');
INSERT INTO progress VALUES ('old-run', 0, 0, 0, 0, 0, 'done', NULL, 1, 1600000100.0);
INSERT INTO progress VALUES ('old-run', 0, 1, 1000, 0, 0, 'pending', NULL, 0, NULL);
INSERT INTO records (scanner_id, run_id, acquired_unix_s, repeat_index, node_index, lcs_index,
  node_x_counts, node_y_counts, node_z_counts, lcs_x_counts, lcs_y_counts, lcs_z_counts,
  kx_nm_per_count, ky_nm_per_count, alpha_rad, kz_nm_per_count, drift_vx_nm_per_s,
  drift_vy_nm_per_s, cycles_kept, cycles_discarded, quality)
  VALUES ('S', 'old-run', 1600000050.0, 0, 0, 0, 0, 0, 0, 0.5, -0.5, 0.0,
          0.0201, 0.0199, 0.0012, NULL, 0.01, 0.02, 6, 1, 0.8);
";

fn pg_versions(url: &str) -> Vec<i64> {
    let mut c = ::postgres::Client::connect(url, ::postgres::NoTls).unwrap();
    c.query("SELECT version FROM schema_version ORDER BY version", &[])
        .unwrap()
        .iter()
        .map(|r| r.get(0))
        .collect()
}

#[test]
fn postgres_migrates_v1_database() {
    let pg = common::postgres();
    let url = pg.fresh("pg_migrate_v1");
    drop(PgCdb::open_at_version(&url, 1).unwrap());
    assert_eq!(pg_versions(&url), [1]);
    pg.raw_sql(&url, PG_V1_DATA);
    // read-only cannot migrate: refused, nothing written
    let e = PgCdb::open_read_only(&url).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::OutdatedSchema, "{e}");
    assert_eq!(pg_versions(&url), [1]);

    let mut cdb = PgCdb::open(&url).unwrap();
    assert_eq!(pg_versions(&url), [1, 2, 3, 4, 5]);
    assert_eq!(cdb.schema_version().unwrap(), SCHEMA_VERSION);
    let old = cdb.records(&RecordFilter::default()).unwrap();
    assert_eq!(old.len(), 1);
    assert_eq!(old[0].kx_nm_per_count, 0.0201);
    assert_eq!((old[0].u_kx_nm_per_count, old[0].u_alpha_rad), (None, None));
    assert!(cdb.check().unwrap().is_ok(), "{:?}", cdb.check().unwrap());
    let r = cdb.run("old-run").unwrap().unwrap();
    let next = cdb.next_pending("old-run").unwrap().unwrap();
    assert_eq!(next.node_x_counts, 1000);
    cdb.commit_node(
        "old-run",
        &done(1, 1600000200.0),
        &[record(&r, &next, 0, 1600000190.0)],
    )
    .unwrap();
    let all = cdb.records(&RecordFilter::default()).unwrap();
    assert_eq!(all[1].u_kx_nm_per_count, Some(1e-5));
    drop(cdb);
    drop(PgCdb::open(&url).unwrap()); // a no-op
    assert_eq!(pg_versions(&url), [1, 2, 3, 4, 5]);
    let ro = PgCdb::open_read_only(&url).unwrap();
    assert_eq!(ro.count_records(&RecordFilter::default()).unwrap(), 2);
}

#[test]
fn postgres_refuses_newer_schema_without_writing() {
    let pg = common::postgres();
    let url = pg.fresh("pg_newer");
    drop(PgCdb::open(&url).unwrap());
    pg.raw_sql(
        &url,
        &format!(
            "DROP TABLE records; CREATE TABLE records (id BIGINT PRIMARY KEY, future TEXT);
             INSERT INTO records VALUES (1, 'from v99');
             INSERT INTO schema_version VALUES (99, {}, 'the future');",
            spm_cdb::APPLICATION_ID
        ),
    );
    let state = |url: &str| -> (Vec<i64>, Vec<String>) {
        let mut c = ::postgres::Client::connect(url, ::postgres::NoTls).unwrap();
        let columns = c
            .query(
                "SELECT column_name::TEXT FROM information_schema.columns \
                 WHERE table_name = 'records' ORDER BY 1",
                &[],
            )
            .unwrap()
            .iter()
            .map(|r| r.get(0))
            .collect();
        (pg_versions(url), columns)
    };
    let before = state(&url);
    for e in [
        PgCdb::open(&url).unwrap_err(),
        PgCdb::open_read_only(&url).unwrap_err(),
    ] {
        assert_eq!(e.kind(), ErrorKind::NewerSchema);
        let msg = e.to_string();
        assert!(msg.contains("99") && msg.contains(&url), "{msg}");
    }
    assert_eq!(state(&url), before);
}

#[test]
fn postgres_refuses_foreign_databases() {
    let pg = common::postgres();
    let empty = pg.fresh("pg_empty");
    assert_eq!(
        PgCdb::open_read_only(&empty).unwrap_err().kind(),
        ErrorKind::NotACdb
    );
    let other = pg.fresh("pg_other_app");
    pg.raw_sql(&other, "CREATE TABLE runs (a INTEGER);");
    assert_eq!(PgCdb::open(&other).unwrap_err().kind(), ErrorKind::NotACdb);
    let foreign = pg.fresh("pg_foreign_version");
    pg.raw_sql(
        &foreign,
        "CREATE TABLE schema_version (version BIGINT PRIMARY KEY, application_id BIGINT NOT NULL,
           description TEXT NOT NULL);
         INSERT INTO schema_version VALUES (1, 42, 'another program');",
    );
    assert_eq!(
        PgCdb::open(&foreign).unwrap_err().kind(),
        ErrorKind::NotACdb
    );
    // a malformed URL is bad input; a server that is not there is a PostgreSQL error naming
    // the URL without its password
    assert_eq!(
        PgCdb::open("postgres://u@h:notaport/db")
            .unwrap_err()
            .kind(),
        ErrorKind::InvalidInput
    );
    let closed = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let e = PgCdb::open(&format!(
        "postgres://someone:secret@127.0.0.1:{closed}/nothing?connect_timeout=5"
    ))
    .unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Postgres, "{e}");
    assert!(!e.to_string().contains("secret"), "{e}");
    assert!(e.to_string().contains("someone:***@127.0.0.1"), "{e}");
}

/// The PostgreSQL `records` table holds exactly the columns of
/// `spm_records::LCC_RECORD_COLUMNS` (after the surrogate key) with the type and nullability
/// of each column's kind.
#[test]
fn postgres_records_table_matches_the_one_column_list() {
    let pg = common::postgres();
    let url = pg.fresh("pg_column_list");
    let cdb = PgCdb::open(&url).unwrap();
    let stored: std::collections::BTreeMap<String, (String, bool)> =
        spm_cdb::postgres::records_table_columns(&cdb)
            .unwrap()
            .into_iter()
            .collect();
    let expected: std::collections::BTreeMap<String, (String, bool)> =
        spm_records::LCC_RECORD_COLUMNS
            .iter()
            .map(|col| {
                let (sql_type, nullable) = match col.kind {
                    spm_records::ColumnKind::Text => ("text", false),
                    spm_records::ColumnKind::Real => ("double precision", false),
                    spm_records::ColumnKind::OptionalReal => ("double precision", true),
                    spm_records::ColumnKind::Integer => ("bigint", false),
                };
                (col.name.to_owned(), (sql_type.to_owned(), nullable))
            })
            .chain([("id".to_owned(), ("bigint".to_owned(), false))])
            .collect();
    assert_eq!(stored, expected);
}

/// Two programs resuming the same run commit the same node at once: the plan row's lock
/// serialises them, one stores the node and the other gets a Conflict; the node's records are
/// stored once.
#[test]
fn postgres_one_node_from_two_programs_is_stored_once() {
    let pg = common::postgres();
    let url = pg.fresh("pg_same_node");
    let r = run("run-1", "S", T0);
    let nodes = plan(20);
    {
        let mut cdb = PgCdb::open(&url).unwrap();
        cdb.create_run(&r).unwrap();
        cdb.register_plan(&r.run_id, &nodes).unwrap();
    }
    let racers: Vec<_> = (0..2)
        .map(|_| {
            let (url, r, nodes) = (url.clone(), r.clone(), nodes.clone());
            std::thread::spawn(move || {
                let mut cdb = PgCdb::open(&url).unwrap();
                let mut won = 0;
                for n in &nodes {
                    let recs: Vec<_> = (0..3).map(|k| record(&r, n, k, T0)).collect();
                    match cdb.commit_node(&r.run_id, &done(n.node_index, T0), &recs) {
                        Ok(()) => won += 1,
                        Err(e) => assert_eq!(e.kind(), ErrorKind::Conflict, "{e}"),
                    }
                }
                won
            })
        })
        .collect();
    let won: u32 = racers.into_iter().map(|t| t.join().unwrap()).sum();
    assert_eq!(won, 40);
    let cdb = PgCdb::open_read_only(&url).unwrap();
    assert_eq!(cdb.count_records(&RecordFilter::default()).unwrap(), 120);
    assert_eq!(cdb.progress_summary(&r.run_id).unwrap().done, 40);
    assert!(cdb.check().unwrap().is_ok());
}

/// Issue 25 item 5: `PRAGMA integrity_check` on a read-only connection skips CHECK
/// constraints, so a run status damaged to "finishe\0" and a plan state outside its set
/// passed `cdb check`. Each is now found by a query, as is a NULL in a NOT NULL column
/// (which integrity_check reports, but as structural damage that ended the check before
/// the other findings).
#[test]
fn sqlite_check_finds_check_and_not_null_violations() {
    let path = db_path("constraint_violations");
    let r = run("run-1", "S", T0);
    let nodes = plan(3);
    {
        let mut cdb = Cdb::open(&path).unwrap();
        cdb.create_run(&r).unwrap();
        cdb.register_plan(&r.run_id, &nodes).unwrap();
        cdb.commit_node(&r.run_id, &done(0, T0), &[record(&r, &nodes[0], 0, T0)])
            .unwrap();
    }
    let raw = Connection::open(&path).unwrap();
    raw.execute_batch(
        "PRAGMA ignore_check_constraints = ON;
         UPDATE runs SET status = CAST(X'66696E6973686500' AS TEXT);
         UPDATE progress SET state = 'dome' WHERE node_index = 1;",
    )
    .unwrap();
    drop(raw);
    let report = Cdb::open_read_only(&path).unwrap().check().unwrap();
    let kinds: Vec<&str> = report.problems.iter().map(|p| p.kind.as_str()).collect();
    assert!(!report.is_ok(), "damage not found: {report:?}");
    for expected in ["invalid_status", "invalid_state"] {
        assert!(
            kinds.contains(&expected),
            "{expected} missing in {report:?}"
        );
    }
    assert!(
        report
            .problems
            .iter()
            .any(|p| p.detail.contains("66696E6973686500")),
        "the damaged bytes are shown: {report:?}"
    );
    // A NULL where the schema says NOT NULL (only possible by editing the schema) is
    // found as well, with the CHECK violations.
    let raw = Connection::open(&path).unwrap();
    raw.execute_batch(
        "PRAGMA writable_schema = ON;
         UPDATE sqlite_master SET sql = replace(sql, 'config          TEXT NOT NULL', \
           'config          TEXT') WHERE name = 'runs';",
    )
    .unwrap();
    drop(raw);
    let raw = Connection::open(&path).unwrap();
    raw.execute_batch("UPDATE runs SET config = NULL;").unwrap();
    raw.execute_batch(
        "PRAGMA writable_schema = ON;
         UPDATE sqlite_master SET sql = replace(sql, 'config          TEXT,', \
           'config          TEXT NOT NULL,') WHERE name = 'runs';",
    )
    .unwrap();
    drop(raw);
    let report = Cdb::open_read_only(&path).unwrap().check().unwrap();
    let kinds: Vec<&str> = report.problems.iter().map(|p| p.kind.as_str()).collect();
    for expected in ["invalid_status", "invalid_state", "null_value"] {
        assert!(
            kinds.contains(&expected),
            "{expected} missing in {report:?}"
        );
    }
    assert!(
        report
            .problems
            .iter()
            .any(|p| p.detail.contains("runs.config") && p.detail.contains("run-1")),
        "{report:?}"
    );
}

/// Issue 25 item 17: a scanner id such as `=1+2+cmd|calc!A0` was exported unquoted, so a
/// spreadsheet opening the CSV ran it as a formula. Text fields are now quoted and a
/// leading `=`, `+`, `-`, `@` (or tab, CR) is neutralised with `'` (OWASP); ids with bidi
/// or other format characters are refused when stored.
#[test]
fn csv_export_neutralises_formulas_and_ids_refuse_format_characters() {
    let path = db_path("csv_injection");
    let mut cdb = Cdb::open(&path).unwrap();
    for (k, id) in ["=1+2+cmd|calc!A0", "@SUM(A1)", "-2+3", "+A1", "plain"]
        .into_iter()
        .enumerate()
    {
        let r = run(&format!("run-{k}"), id, T0 + k as f64);
        let nodes = plan(1);
        cdb.create_run(&r).unwrap();
        cdb.register_plan(&r.run_id, &nodes).unwrap();
        cdb.commit_node(&r.run_id, &done(0, T0), &[record(&r, &nodes[0], 0, T0)])
            .unwrap();
    }
    let mut out = Vec::new();
    cdb.export_csv(&RecordFilter::default(), &mut out).unwrap();
    let text = String::from_utf8(out).unwrap();
    for line in text.lines().skip(1) {
        let scanner = line.split(',').nth(1).unwrap();
        assert!(scanner.starts_with('"'), "unquoted text field in {line}");
        let inner = scanner.trim_matches('"');
        assert!(
            !inner.starts_with(['=', '+', '-', '@']),
            "formula left in {line}"
        );
    }
    assert!(text.contains("\"'=1+2+cmd|calc!A0\""), "{text}");
    assert!(text.contains("\"plain\""), "{text}");
    // Negative numbers stay numbers.
    assert!(
        text.contains(",-0.5,") || text.contains(",-0.02,"),
        "{text}"
    );
    for bad in [
        "scan\u{202E}ner",
        "a\u{200B}b",
        "tab\there",
        "x\u{2066}y",
        "nul\0",
    ] {
        let r = run(&format!("bad-{}", bad.len()), bad, T0);
        let e = cdb.create_run(&r).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::InvalidInput, "{bad:?}: {e}");
        assert!(e.to_string().contains("scanner id"), "{e}");
        let mut run_id_bad = run("ok", "S", T0);
        run_id_bad.run_id = bad.to_owned();
        assert_eq!(
            cdb.create_run(&run_id_bad).unwrap_err().kind(),
            ErrorKind::InvalidInput
        );
    }
    assert!(cdb.check().unwrap().is_ok());
}

/// The URL of `url`'s database for another role (trust authentication on the test server).
fn as_role(url: &str, role: &str) -> String {
    url.replacen("postgres://postgres@", &format!("postgres://{role}@"), 1)
}

/// Issue 25 item 8: an account whose own schema is on its `search_path` (the default
/// `"$user", public`) reads a CDB made in `public`; the schema lookups filtered on
/// `current_schema()` (the account's empty schema) while the queries found `public`'s
/// tables, so `check` reported every column missing.
#[test]
fn postgres_an_account_with_its_own_schema_reads_a_cdb_in_public() {
    let pg = common::postgres();
    let url = pg.fresh("pg_own_schema");
    let r = run("run-1", "S", T0);
    let nodes = plan(2);
    {
        let mut cdb = PgCdb::open(&url).unwrap();
        cdb.create_run(&r).unwrap();
        cdb.register_plan(&r.run_id, &nodes).unwrap();
        cdb.commit_node(&r.run_id, &done(0, T0), &[record(&r, &nodes[0], 0, T0)])
            .unwrap();
    }
    pg.raw_sql(
        &url,
        "DROP ROLE IF EXISTS alice; CREATE ROLE alice LOGIN;
         GRANT SELECT ON ALL TABLES IN SCHEMA public TO alice;
         CREATE SCHEMA alice AUTHORIZATION alice;",
    );
    let cdb = PgCdb::open_read_only(&as_role(&url, "alice")).unwrap();
    let report = cdb.check().unwrap();
    assert!(report.is_ok(), "{report:?}");
    assert_eq!(cdb.count_records(&RecordFilter::default()).unwrap(), 1);
    assert_eq!(cdb.runs(None).unwrap().len(), 1);
}

/// Issue 25 item 9: every server-side error read "PostgreSQL error: db error". The
/// server's message and SQLSTATE are shown, and a missing database or a missing privilege
/// is `AccessDenied` (bad input), not a run failure.
#[test]
fn postgres_server_errors_show_the_servers_message_and_access_errors_are_bad_input() {
    let pg = common::postgres();
    let url = pg.fresh("pg_messages");
    drop(PgCdb::open(&url).unwrap());
    let missing = url.replace("/pg_messages", "/pg_no_such_database");
    let e = PgCdb::open_read_only(&missing).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::AccessDenied, "{e}");
    let text = e.to_string();
    assert!(
        text.contains("pg_no_such_database") && text.contains("does not exist"),
        "{text}"
    );
    assert!(text.contains("3D000"), "{text}");
    assert!(!text.contains("db error"), "{text}");
    pg.raw_sql(&url, "DROP ROLE IF EXISTS bob; CREATE ROLE bob LOGIN;");
    let e = PgCdb::open_read_only(&as_role(&url, "bob")).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::AccessDenied, "{e}");
    assert!(e.to_string().contains("permission denied"), "{e}");
    assert!(e.to_string().contains("42501"), "{e}");
    // A server error of another kind names the server's words too.
    let mut cdb = PgCdb::open(&url).unwrap();
    let e = cdb
        .batch_execute_raw("SELECT * FROM no_such_table")
        .unwrap_err();
    assert!(
        e.to_string().contains("no_such_table") && e.to_string().contains("42P01"),
        "{e}"
    );
    // A URL without a host is bad input naming what is missing.
    let e = PgCdb::open_read_only("postgres://").unwrap_err();
    assert_eq!(e.kind(), ErrorKind::InvalidInput, "{e}");
    assert!(e.to_string().contains("no host"), "{e}");
}

/// A CDB with one run and `nodes` committed nodes, left open (its write-ahead log holds
/// the commits).
fn open_with_commits(path: &std::path::Path, scanner: &str, nodes: u32) -> Cdb {
    let r = run("run-1", scanner, T0);
    let plan_nodes = plan(3);
    let mut cdb = Cdb::open(path).unwrap();
    cdb.create_run(&r).unwrap();
    cdb.register_plan(&r.run_id, &plan_nodes).unwrap();
    for n in &plan_nodes[..nodes as usize] {
        let t = T0 + f64::from(n.node_index);
        cdb.commit_node(&r.run_id, &done(n.node_index, t), &[record(&r, n, 0, t)])
            .unwrap();
    }
    cdb
}

fn with_suffix(path: &std::path::Path, suffix: &str) -> std::path::PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(suffix);
    s.into()
}

/// Issue 25 item 2: SQLite replays a `-wal` beside a database without asking whether it
/// belongs: a log copied from another CDB, or left from before (older than the database),
/// was applied silently and the check said ok. Both are now refused before anything is
/// written, with the way out in the message; a database older than its identity file
/// (a restored backup) too.
#[test]
fn sqlite_a_foreign_or_stale_log_is_refused_before_anything_is_written() {
    // A foreign log: A's log beside B.
    let a = db_path("identity_a");
    let b = db_path("identity_b");
    let cdb_a = open_with_commits(&a, "A", 2);
    let log_of_a = std::fs::read(with_suffix(&a, "-wal")).unwrap();
    assert!(!log_of_a.is_empty());
    drop(cdb_a);
    drop(open_with_commits(&b, "B", 1));
    std::fs::write(with_suffix(&b, "-wal"), &log_of_a).unwrap();
    let before = (std::fs::read(&b).unwrap(), log_of_a.clone());
    for e in [
        Cdb::open_read_only(&b).unwrap_err(),
        Cdb::open(&b).unwrap_err(),
    ] {
        assert_eq!(e.kind(), ErrorKind::IdentityMismatch, "{e}");
        let text = e.to_string();
        assert!(
            text.contains("does not belong") && text.contains("mv "),
            "{text}"
        );
    }
    let after = (
        std::fs::read(&b).unwrap(),
        std::fs::read(with_suffix(&b, "-wal")).unwrap(),
    );
    assert!(
        after == before,
        "a refused open wrote to the database or its log"
    );
    // Moved aside as the message says, B opens as it was.
    std::fs::rename(with_suffix(&b, "-wal"), with_suffix(&b, "-wal.stale")).unwrap();
    let _ = std::fs::remove_file(with_suffix(&b, "-shm"));
    let cdb_b = Cdb::open_read_only(&b).unwrap();
    assert_eq!(cdb_b.scanners().unwrap(), vec!["B".to_owned()]);
    assert!(cdb_b.check().unwrap().is_ok());
    drop(cdb_b);

    // A stale log: the log of an earlier moment beside the database that went on.
    let c = db_path("identity_stale");
    let cdb_c = open_with_commits(&c, "C", 1);
    let early_log = std::fs::read(with_suffix(&c, "-wal")).unwrap();
    drop(cdb_c);
    let mut cdb_c = Cdb::open(&c).unwrap();
    let r = cdb_c.run("run-1").unwrap().unwrap();
    let nodes = plan(3);
    cdb_c
        .commit_node(
            "run-1",
            &done(1, T0 + 9.0),
            &[record(&r, &nodes[1], 0, T0 + 9.0)],
        )
        .unwrap();
    drop(cdb_c);
    std::fs::write(with_suffix(&c, "-wal"), &early_log).unwrap();
    let e = Cdb::open_read_only(&c).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::IdentityMismatch, "{e}");
    assert!(e.to_string().contains("older than the database"), "{e}");
    std::fs::remove_file(with_suffix(&c, "-wal")).unwrap();
    let _ = std::fs::remove_file(with_suffix(&c, "-shm"));
    assert_eq!(
        Cdb::open_read_only(&c)
            .unwrap()
            .count_records(&RecordFilter::default())
            .unwrap(),
        2
    );

    // A restored backup: the file is older than the generation its identity file records.
    let backup = std::fs::read(&c).unwrap();
    {
        let mut cdb_c = Cdb::open(&c).unwrap();
        cdb_c
            .finish_run("run-1", RunStatus::Finished, T0 + 99.0)
            .unwrap();
    }
    std::fs::write(&c, &backup).unwrap();
    let e = Cdb::open(&c).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::IdentityMismatch, "{e}");
    assert!(e.to_string().contains("-identity"), "{e}");
    std::fs::remove_file(with_suffix(&c, "-identity")).unwrap();
    assert!(Cdb::open(&c).unwrap().check().unwrap().is_ok());
}

/// Issue 25 item 9, authentication: a wrong password and a missing one are `AccessDenied`
/// (bad input, exit 2) with the server's words, never showing the password.
#[test]
fn postgres_authentication_failures_are_access_denied() {
    let pg = common::postgres();
    let url = pg.fresh("pg_auth");
    drop(PgCdb::open(&url).unwrap());
    pg.raw_sql(
        &url,
        "DROP ROLE IF EXISTS mallory; CREATE ROLE mallory LOGIN PASSWORD 'right-one';",
    );
    // Password authentication for this role only, ahead of the test server's `trust`.
    let hba = pg.data_dir().join("pg_hba.conf");
    let rules = std::fs::read_to_string(&hba).unwrap();
    std::fs::write(
        &hba,
        format!("host all mallory 127.0.0.1/32 scram-sha-256\n{rules}"),
    )
    .unwrap();
    pg.raw_sql(&url, "SELECT pg_reload_conf();");
    std::thread::sleep(std::time::Duration::from_millis(300));
    let wrong = url.replacen("postgres://postgres@", "postgres://mallory:wrong-one@", 1);
    let e = PgCdb::open_read_only(&wrong).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::AccessDenied, "{e}");
    let text = e.to_string();
    assert!(
        text.contains("28P01") && text.contains("password authentication failed"),
        "{text}"
    );
    assert!(!text.contains("wrong-one"), "{text}");
    let none = url.replacen("postgres://postgres@", "postgres://mallory@", 1);
    let e = PgCdb::open_read_only(&none).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::AccessDenied, "{e}");
    assert!(e.to_string().contains("password missing"), "{e}");
    let right = url.replacen("postgres://postgres@", "postgres://mallory:right-one@", 1);
    let e = PgCdb::open_read_only(&right).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::AccessDenied, "no privilege yet: {e}");
}

// ---------------------------------------------------------------------------------------
// Scanner dynamics (schema v5, issue 23).

/// `store_dynamics` keeps every identification of every scanner; the queries give them
/// oldest first and the newest alone, whatever order they were stored in; invalid records,
/// unknown runs and another scanner's run are refused with typed errors and write
/// nothing; the JSON export carries them beside the records.
fn dynamics_are_stored_dated_per_scanner_and_validated(b: &'static dyn Backend) {
    let path = b.fresh("dynamics_store");
    let (r1, r2, r3) = (
        run("run-1", "S", T0),
        run("run-2", "S", T0 + 86_400.0),
        run("run-3", "T", T0),
    );
    let mut cdb = b.open(&path);
    for r in [&r1, &r2, &r3] {
        cdb.create_run(r).unwrap();
    }
    assert_eq!(cdb.dynamics_for_scanner("S").unwrap(), []);
    assert_eq!(cdb.latest_dynamics("S").unwrap(), None);
    // Stored newest first, and two of one time (the later stored is the newer).
    let d2 = common::dynamics(&r2, T0 + 90_000.0, 0.02);
    let d1 = common::dynamics(&r1, T0 + 3_600.0, 0.01);
    let d1b = common::dynamics(&r1, T0 + 3_600.0, 0.011);
    let t = common::dynamics(&r3, T0 + 100_000.0, 0.03);
    let t2 = common::dynamics(&r3, T0 + 100_000.0, 0.031);
    for d in [&d2, &d1, &d1b, &t, &t2] {
        cdb.store_dynamics(d).unwrap();
    }
    assert_eq!(
        cdb.dynamics_for_scanner("S").unwrap(),
        [d1.clone(), d1b.clone(), d2.clone()]
    );
    assert_eq!(cdb.latest_dynamics("S").unwrap(), Some(d2.clone()));
    // Of two at one time, the one stored later is the newer.
    assert_eq!(cdb.latest_dynamics("T").unwrap(), Some(t2.clone()));
    assert_eq!(cdb.latest_dynamics("U").unwrap(), None);
    assert_eq!(
        cdb.dynamics(None).unwrap(),
        [d1.clone(), d1b.clone(), d2.clone(), t.clone(), t2.clone()]
    );
    // The model text comes back byte for byte.
    assert_eq!(
        cdb.latest_dynamics("S").unwrap().unwrap().model_json,
        d2.model_json
    );

    // Refusals: each names its field or its run; nothing is written.
    let spoil = |f: &dyn Fn(&mut spm_cdb::DynamicsRecord)| {
        let mut d = common::dynamics(&r1, T0 + 7_200.0, 0.5);
        f(&mut d);
        d
    };
    for (d, kind, names) in [
        (
            spoil(&|d| d.model_json = "{\"creep\": ".into()),
            ErrorKind::InvalidInput,
            "model_json",
        ),
        (
            spoil(&|d| d.model_json = "[0.1, 0.2]".into()),
            ErrorKind::InvalidInput,
            "model_json",
        ),
        (
            spoil(&|d| d.identified_unix_s = f64::NAN),
            ErrorKind::InvalidInput,
            "identified_unix_s",
        ),
        (
            spoil(&|d| d.identified_unix_s = f64::INFINITY),
            ErrorKind::InvalidInput,
            "identified_unix_s",
        ),
        (
            spoil(&|d| d.scanner_id = String::new()),
            ErrorKind::InvalidInput,
            "scanner_id",
        ),
        (
            spoil(&|d| d.model_version = 0),
            ErrorKind::InvalidInput,
            "model_version",
        ),
        (
            spoil(&|d| d.run_id = "no-such-run".into()),
            ErrorKind::NotFound,
            "no-such-run",
        ),
        (
            spoil(&|d| d.scanner_id = "T".into()),
            ErrorKind::InvalidInput,
            "scanner",
        ),
    ] {
        let e = cdb.store_dynamics(&d).unwrap_err();
        assert_eq!(e.kind(), kind, "{e}");
        assert!(e.to_string().contains(names), "{names} not named: {e}");
    }
    assert_eq!(cdb.dynamics(None).unwrap().len(), 5);
    assert!(cdb.check().unwrap().is_ok(), "{:?}", cdb.check().unwrap());

    // A snapshot and a read-only open read them too.
    assert_eq!(
        cdb.snapshot().unwrap().latest_dynamics("S").unwrap(),
        Some(d2.clone())
    );
    let ro = b.open_read_only(&path).unwrap();
    assert_eq!(ro.dynamics_for_scanner("T").unwrap(), [t, t2]);

    // JSON export: "records" as before, "dynamics" selected like the records.
    let mut json = Vec::new();
    ro.export_json(&RecordFilter::scanner("S"), &mut json)
        .unwrap();
    let v: serde_json::Value = serde_json::from_slice(&json).unwrap();
    assert_eq!(v["schema_version"], 5);
    assert_eq!(v["records"], serde_json::json!([]));
    let back: Vec<spm_cdb::DynamicsRecord> = serde_json::from_value(v["dynamics"].clone()).unwrap();
    assert_eq!(back, [d1.clone(), d1b.clone(), d2.clone()]);
    let mut json = Vec::new();
    ro.export_json(
        &RecordFilter::scanner("S").with_window(Some(T0 + 86_400.0), None),
        &mut json,
    )
    .unwrap();
    let v: serde_json::Value = serde_json::from_slice(&json).unwrap();
    let back: Vec<spm_cdb::DynamicsRecord> = serde_json::from_value(v["dynamics"].clone()).unwrap();
    assert_eq!(back, [d2]);
}

/// `cdb check` finds dynamics rows that got past the schema (its constraints lifted
/// behind the library's back): a model that is not JSON or not an object, a non-finite
/// time, a missing run, another scanner than the run's, and names each row once.
fn integrity_check_finds_bad_dynamics(b: &'static dyn Backend) {
    let path = b.fresh("dynamics_check");
    let r = run("run-1", "S", T0);
    {
        let mut cdb = b.open(&path);
        cdb.create_run(&r).unwrap();
        cdb.store_dynamics(&common::dynamics(&r, T0 + 60.0, 0.01))
            .unwrap();
        assert!(cdb.check().unwrap().is_ok());
    }
    let row = |run_id: &str, scanner: &str, t: &str, json: &str| {
        format!(
            "INSERT INTO dynamics (run_id, scanner_id, identified_unix_s, model_format, \
             model_version, model_json) VALUES ('{run_id}', '{scanner}', {t}, \
             'spmcal-dynamics', 1, '{json}');"
        )
    };
    let sql = [
        b.lift_dynamics_constraints().to_owned(),
        row("run-1", "S", "1704067300.0", "{\"creep\": "),
        row("run-1", "S", "1704067301.0", "[1, 2]"),
        row("run-1", "S", b.infinity_literal(), "{}"),
        row("gone-run", "S", "1704067302.0", "{}"),
        row("run-1", "T", "1704067303.0", "{}"),
    ]
    .concat();
    b.raw_sql(&path, &sql);
    let cdb = b.open(&path);
    let report = cdb.check().unwrap();
    let found = |kind: &str| {
        report
            .problems
            .iter()
            .filter(|p| p.kind == kind)
            .map(|p| p.detail.clone())
            .collect::<Vec<_>>()
    };
    assert!(!report.is_ok());
    let json = found("invalid_model_json");
    assert_eq!(json.len(), 2, "{report:?}");
    assert!(
        json[0].contains("dynamics id 2") && json[0].contains("not JSON"),
        "{json:?}"
    );
    assert!(
        json[1].contains("dynamics id 3") && json[1].contains("JSON object"),
        "{json:?}"
    );
    let time = found("non_finite");
    assert_eq!(time.len(), 1, "{report:?}");
    assert!(time[0].contains("dynamics id 4") && time[0].contains("identified_unix_s"));
    let gone = found("dynamics_without_run");
    assert_eq!(gone.len(), 1, "{report:?}");
    assert!(gone[0].contains("gone-run"), "{gone:?}");
    let mismatch = found("scanner_mismatch");
    assert_eq!(mismatch.len(), 1, "{report:?}");
    assert!(mismatch[0].contains("dynamics id 6"), "{mismatch:?}");
    // the valid row (id 1) is not named anywhere
    assert!(
        report
            .problems
            .iter()
            .all(|p| !p.detail.contains("dynamics id 1:")),
        "{report:?}"
    );
    // On PostgreSQL the constraints dropped to let the rows in are findings too (item 16),
    // each by name; SQLite's were only switched off for the session.
    let lifted = found("missing_constraint");
    for name in [
        "dynamics_run_id_fkey",
        "dynamics_time_finite",
        "dynamics_model_json_object",
    ] {
        assert_eq!(
            lifted.iter().any(|d| d.contains(name)),
            b.lift_dynamics_constraints().contains(name),
            "{name}: {report:?}"
        );
    }
    assert_eq!(report.problems.len(), 5 + lifted.len(), "{report:?}");
}

/// Schema v4 as shipped (issue 25), with a fixed identity and rows of every table.
const V4_DDL: &str = "CREATE TABLE cdb_identity (
    id         TEXT NOT NULL,
    generation INTEGER NOT NULL
);
INSERT INTO cdb_identity (id, generation) VALUES ('0123456789abcdef0123456789abcdef', 7);

CREATE TABLE runs (
    run_id          TEXT PRIMARY KEY NOT NULL,
    scanner_id      TEXT NOT NULL,
    config          TEXT NOT NULL,
    started_unix_s  REAL NOT NULL,
    finished_unix_s REAL,
    status          TEXT NOT NULL CHECK (status IN ('running', 'finished', 'failed', 'aborted')),
    cdb_id          TEXT
);
CREATE INDEX runs_scanner ON runs (scanner_id, started_unix_s);

CREATE TABLE progress (
    run_id         TEXT NOT NULL REFERENCES runs (run_id),
    repeat_index   INTEGER NOT NULL,
    node_index     INTEGER NOT NULL,
    node_x_counts  INTEGER NOT NULL,
    node_y_counts  INTEGER NOT NULL,
    node_z_counts  INTEGER NOT NULL,
    state          TEXT NOT NULL CHECK (state IN ('pending', 'done', 'given_up')),
    reason         TEXT,
    attempts       INTEGER NOT NULL DEFAULT 0,
    updated_unix_s REAL,
    PRIMARY KEY (run_id, repeat_index, node_index)
) WITHOUT ROWID;

CREATE TABLE records (
    id                INTEGER PRIMARY KEY,
    scanner_id        TEXT NOT NULL,
    run_id            TEXT NOT NULL REFERENCES runs (run_id),
    acquired_unix_s   REAL NOT NULL,
    repeat_index      INTEGER NOT NULL,
    node_index        INTEGER NOT NULL,
    lcs_index         INTEGER NOT NULL DEFAULT 0,
    node_x_counts     INTEGER NOT NULL,
    node_y_counts     INTEGER NOT NULL,
    node_z_counts     INTEGER NOT NULL,
    lcs_x_counts      REAL NOT NULL,
    lcs_y_counts      REAL NOT NULL,
    lcs_z_counts      REAL NOT NULL,
    kx_nm_per_count   REAL NOT NULL,
    ky_nm_per_count   REAL NOT NULL,
    alpha_rad         REAL NOT NULL,
    kz_nm_per_count   REAL,
    drift_vx_nm_per_s REAL NOT NULL,
    drift_vy_nm_per_s REAL NOT NULL,
    cycles_kept       INTEGER NOT NULL,
    cycles_discarded  INTEGER NOT NULL,
    quality           REAL NOT NULL,
    u_kx_nm_per_count REAL,
    u_ky_nm_per_count REAL,
    u_alpha_rad       REAL,
    u_kz_nm_per_count REAL,
    kz_x_counts       REAL,
    kz_y_counts       REAL
);
CREATE UNIQUE INDEX records_node ON records (run_id, repeat_index, node_index, lcs_index);
CREATE INDEX records_plane ON records (scanner_id, node_z_counts, acquired_unix_s);

INSERT INTO runs VALUES ('old-run', 'S', '[plan]
nodes = 3
', 1600000000.0, NULL, 'running',
  '0123456789abcdef0123456789abcdef');
INSERT INTO runs VALUES ('done-run', 'S', '[plan]', 1600001000.0, 1600002000.0, 'finished',
  '0123456789abcdef0123456789abcdef');
INSERT INTO progress VALUES ('old-run', 0, 0, 0, 0, 0, 'done', NULL, 1, 1600000060.0);
INSERT INTO progress VALUES ('old-run', 0, 1, 1000, 0, 0, 'pending', NULL, 0, NULL);
INSERT INTO progress VALUES ('old-run', 0, 2, 2000, 0, 0, 'given_up', 'no feature', 3,
  1600000090.0);
INSERT INTO progress VALUES ('done-run', 0, 0, 0, 0, 500, 'done', NULL, 2, 1600001500.0);
INSERT INTO records (scanner_id, run_id, acquired_unix_s, repeat_index, node_index, lcs_index,
  node_x_counts, node_y_counts, node_z_counts, lcs_x_counts, lcs_y_counts, lcs_z_counts,
  kx_nm_per_count, ky_nm_per_count, alpha_rad, kz_nm_per_count, drift_vx_nm_per_s,
  drift_vy_nm_per_s, cycles_kept, cycles_discarded, quality, u_kx_nm_per_count,
  u_ky_nm_per_count, u_alpha_rad, u_kz_nm_per_count, kz_x_counts, kz_y_counts)
  VALUES ('S', 'old-run', 1600000050.0, 0, 0, 0, 0, 0, 0, 0.5, -0.5, 0.0,
          0.0201, 0.0199, 0.0012, NULL, 0.01, 0.02, 6, 1, 0.8, NULL, NULL, NULL, NULL, NULL, NULL),
         ('S', 'done-run', 1600001400.0, 0, 0, 0, 0, 0, 500, 0.25, 0.125, 500.5,
          0.0202, 0.0198, -0.0011, 0.003, -0.01, 0.03, 8, 0, 0.95, 1e-5, 2e-5, 1e-3, 1e-4,
          0.75, -0.25);
PRAGMA application_id = 1397771587;
PRAGMA user_version = 4;
";

/// Every row of the tables a v4 file has, with each value's stored type.
fn sqlite_rows(conn: &Connection) -> Vec<(String, Vec<Vec<rusqlite::types::Value>>)> {
    [
        ("cdb_identity", "rowid"),
        ("runs", "run_id"),
        ("progress", "run_id, repeat_index, node_index"),
        ("records", "id"),
    ]
    .iter()
    .map(|(table, order)| {
        let mut stmt = conn
            .prepare(&format!("SELECT * FROM {table} ORDER BY {order}"))
            .unwrap();
        let n = stmt.column_count();
        let rows = stmt
            .query_map([], |r| {
                (0..n)
                    .map(|k| r.get::<_, rusqlite::types::Value>(k))
                    .collect::<rusqlite::Result<Vec<_>>>()
            })
            .unwrap()
            .collect::<rusqlite::Result<Vec<_>>>()
            .unwrap();
        ((*table).to_owned(), rows)
    })
    .collect()
}

fn dynamics_schema(conn: &Connection) -> Vec<(String, String)> {
    conn.prepare("SELECT name, sql FROM sqlite_master WHERE tbl_name = 'dynamics' ORDER BY name")
        .unwrap()
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?)))
        .unwrap()
        .collect::<rusqlite::Result<_>>()
        .unwrap()
}

/// A v4 file migrates to v5 with every pre-existing row (runs, progress, records and the
/// identity, values and stored types) untouched and the `dynamics` table of a new file;
/// the migrated file takes dynamics, and storing them steps the identity's generation.
#[test]
fn sqlite_migrates_v4_file_leaving_every_row_untouched() {
    let path = db_path("migrate_v4");
    let before = {
        let raw = Connection::open(&path).unwrap();
        raw.execute_batch(V4_DDL).unwrap();
        sqlite_rows(&raw)
    };
    assert_eq!(before[0].1.len(), 1);
    assert_eq!(before[3].1.len(), 2);
    // read-only cannot migrate: refused, file untouched
    let bytes = std::fs::read(&path).unwrap();
    let e = Cdb::open_read_only(&path).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::OutdatedSchema);
    assert_eq!(std::fs::read(&path).unwrap(), bytes);

    let mut cdb = Cdb::open(&path).unwrap();
    assert_eq!(cdb.schema_version().unwrap(), 5);
    assert_eq!(sqlite_rows(cdb.connection()), before);
    assert!(cdb.check().unwrap().is_ok(), "{:?}", cdb.check().unwrap());
    assert_eq!(cdb.dynamics(None).unwrap(), []);
    // The migrated table is the one a new file gets.
    let fresh = Cdb::open(db_path("migrate_v4_fresh")).unwrap();
    assert_eq!(fresh.schema_version().unwrap(), 5);
    assert_eq!(dynamics_schema(cdb.connection()).len(), 2);
    assert_eq!(
        dynamics_schema(cdb.connection()),
        dynamics_schema(fresh.connection())
    );
    // The old run's records read as before, and the old run takes dynamics.
    let old = cdb.records(&RecordFilter::default()).unwrap();
    assert_eq!(old.len(), 2);
    assert_eq!(old[1].kz_x_counts, Some(0.75));
    let r = cdb.run("old-run").unwrap().unwrap();
    let d = common::dynamics(&r, 1_600_000_100.0, 0.01);
    cdb.store_dynamics(&d).unwrap();
    assert_eq!(cdb.latest_dynamics("S").unwrap(), Some(d));
    let after = sqlite_rows(cdb.connection());
    assert_eq!(
        after[1..],
        before[1..],
        "only the identity's generation moves"
    );
    let generation = |rows: &[(String, Vec<Vec<rusqlite::types::Value>>)]| rows[0].1[0][1].clone();
    assert_eq!(generation(&before), rusqlite::types::Value::Integer(7));
    assert_eq!(generation(&after), rusqlite::types::Value::Integer(8));
    drop(cdb);
    let sidecar = std::fs::read_to_string(with_suffix(&path, "-identity")).unwrap();
    assert!(sidecar.contains("generation=8"), "{sidecar}");
    assert!(Cdb::open_read_only(&path).unwrap().check().unwrap().is_ok());
}

/// Every row of the tables a v4 database has, as JSON text.
fn pg_rows(url: &str) -> Vec<String> {
    let mut c = ::postgres::Client::connect(url, ::postgres::NoTls).unwrap();
    let mut out = Vec::new();
    for (table, order) in [
        ("cdb_identity", "id"),
        ("runs", "run_id"),
        ("progress", "run_id, repeat_index, node_index"),
        ("records", "id"),
    ] {
        for r in c
            .query(
                &format!("SELECT row_to_json(t)::TEXT FROM {table} t ORDER BY {order}"),
                &[],
            )
            .unwrap()
        {
            out.push(format!("{table}: {}", r.get::<_, String>(0)));
        }
    }
    out
}

/// A v4 PostgreSQL database migrates to v5 with every pre-existing row untouched.
#[test]
fn postgres_migrates_v4_database_leaving_every_row_untouched() {
    let pg = common::postgres();
    let url = pg.fresh("pg_migrate_v4");
    let r = run("old-run", "S", T0);
    let nodes = plan(2);
    {
        let mut v4 = PgCdb::open_at_version(&url, 4).unwrap();
        v4.create_run(&r).unwrap();
        v4.register_plan(&r.run_id, &nodes).unwrap();
        v4.commit_node(
            &r.run_id,
            &done(0, T0 + 10.0),
            &[record(&r, &nodes[0], 0, T0)],
        )
        .unwrap();
        v4.give_up_node(&r.run_id, 0, 1, "no feature", 3, T0 + 20.0)
            .unwrap();
    }
    assert_eq!(pg_versions(&url), [1, 2, 3, 4]);
    let before = pg_rows(&url);
    assert_eq!(before.len(), 1 + 1 + 4 + 1, "{before:#?}");
    let e = PgCdb::open_read_only(&url).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::OutdatedSchema, "{e}");

    let mut cdb = PgCdb::open(&url).unwrap();
    assert_eq!(pg_versions(&url), [1, 2, 3, 4, 5]);
    assert_eq!(pg_rows(&url), before);
    assert!(cdb.check().unwrap().is_ok(), "{:?}", cdb.check().unwrap());
    assert_eq!(cdb.dynamics(None).unwrap(), []);
    let d = common::dynamics(&r, T0 + 30.0, 0.01);
    cdb.store_dynamics(&d).unwrap();
    assert_eq!(cdb.latest_dynamics("S").unwrap(), Some(d));
    assert_eq!(pg_rows(&url), before);
    drop(cdb);
    assert!(
        PgCdb::open_read_only(&url)
            .unwrap()
            .check()
            .unwrap()
            .is_ok()
    );
}

/// A v4 file (it has the identity) with another database's log beside it is refused
/// read-only as an identity mismatch, as before v5 — not passed over as merely outdated —
/// and the files stay as they were.
#[test]
fn sqlite_a_v4_file_with_a_foreign_log_is_still_an_identity_mismatch() {
    let make = |name: &str, id: &str| {
        let path = db_path(name);
        let raw = Connection::open(&path).unwrap();
        raw.execute_batch(&V4_DDL.replace("0123456789abcdef0123456789abcdef", id))
            .unwrap();
        let _: String = raw
            .query_row("PRAGMA journal_mode = WAL", [], |r| r.get(0))
            .unwrap();
        (path, raw)
    };
    let (a, raw_a) = make("v4_identity_a", "aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa");
    drop(raw_a);
    let (b, raw_b) = make("v4_identity_b", "bbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbb");
    raw_b
        .execute_batch("PRAGMA wal_autocheckpoint = 0; UPDATE cdb_identity SET generation = 8;")
        .unwrap();
    let log_of_b = std::fs::read(with_suffix(&b, "-wal")).unwrap();
    assert!(!log_of_b.is_empty());
    std::fs::write(with_suffix(&a, "-wal"), &log_of_b).unwrap();
    let before = std::fs::read(&a).unwrap();
    let e = Cdb::open_read_only(&a).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::IdentityMismatch, "{e}");
    assert_eq!(std::fs::read(&a).unwrap(), before);
    assert_eq!(std::fs::read(with_suffix(&a, "-wal")).unwrap(), log_of_b);
    drop(raw_b);
}

/// A CDB with one run, its plan and one stored node (both back ends share the body).
fn one_stored_node(cdb: &mut dyn common::Store) {
    let r = run("run-1", "S", T0);
    let nodes = plan(2);
    cdb.create_run(&r).unwrap();
    cdb.register_plan(&r.run_id, &nodes).unwrap();
    cdb.commit_node(&r.run_id, &done(0, T0), &[record(&r, &nodes[0], 0, T0)])
        .unwrap();
}

/// How many findings of `report` are about the schema's keys, CHECKs, indexes and columns.
fn schema_findings(report: &spm_cdb::IntegrityReport) -> usize {
    report
        .problems
        .iter()
        .filter(|p| {
            ["missing_constraint", "missing_index", "extra_column"].contains(&p.kind.as_str())
        })
        .count()
}

/// What is wrong with `report` of the case `case` (tampered to give one finding of `kind`
/// naming `named`, or untampered when `kind` is empty): `None` when it is right.
fn tampering_missed(
    case: &str,
    report: &spm_cdb::IntegrityReport,
    kind: &str,
    named: &str,
) -> Option<String> {
    if kind.is_empty() {
        return (!report.is_ok()).then(|| format!("{case}: untampered, but {report:?}"));
    }
    if report.is_ok() {
        return Some(format!("{case}: the tampering passes the check"));
    }
    if !names_finding(report, kind, named) || schema_findings(report) != 1 {
        return Some(format!("{case}: not one {kind} naming {named}: {report:?}"));
    }
    None
}

/// The findings of `report` of `kind` whose detail names `name`.
fn names_finding(report: &spm_cdb::IntegrityReport, kind: &str, name: &str) -> bool {
    report
        .problems
        .iter()
        .any(|p| p.kind == kind && p.detail.contains(name))
}

/// Issue 25 item 16: four tampered PostgreSQL schemas passed `cdb check` — a dropped
/// `progress` primary key (`register_plan` then fails on its `ON CONFLICT`), a dropped status
/// CHECK, a dropped `records_node` unique index (duplicate records accepted) and an extra
/// NOT NULL column (every insert fails). Each is now a finding naming the constraint, index
/// or column, as is a status CHECK loosened to admit another value; the untampered CDB
/// passes.
#[test]
fn postgres_check_finds_tampered_keys_checks_and_indexes() {
    let pg = common::postgres();
    let cases = [
        ("pg_tamper_none", "SELECT 1", "", ""),
        (
            "pg_tamper_pkey",
            "ALTER TABLE progress DROP CONSTRAINT progress_pkey",
            "missing_constraint",
            "progress_pkey",
        ),
        (
            "pg_tamper_status",
            "ALTER TABLE runs DROP CONSTRAINT runs_status_check",
            "missing_constraint",
            "runs_status_check",
        ),
        (
            "pg_tamper_loose_status",
            "ALTER TABLE runs DROP CONSTRAINT runs_status_check;
             ALTER TABLE runs ADD CONSTRAINT runs_status_check CHECK
                 (status IN ('running', 'finished', 'failed', 'aborted', 'x'))",
            "missing_constraint",
            "runs_status_check",
        ),
        (
            "pg_tamper_unique",
            "DROP INDEX records_node",
            "missing_index",
            "records_node",
        ),
        (
            "pg_tamper_column",
            "ALTER TABLE records ADD COLUMN operator TEXT NOT NULL DEFAULT 'x';
             ALTER TABLE records ALTER COLUMN operator DROP DEFAULT",
            "extra_column",
            "operator",
        ),
    ];
    let mut missed = Vec::new();
    for (name, tamper, kind, named) in cases {
        let url = pg.fresh(name);
        {
            let mut cdb = common::Backend::open(pg, &url);
            one_stored_node(cdb.as_mut());
            let before = cdb.check().unwrap();
            assert!(before.is_ok(), "{name}: untampered CDB: {before:?}");
        }
        pg.raw_sql(&url, tamper);
        let report = PgCdb::open_read_only(&url).unwrap().check().unwrap();
        missed.extend(tampering_missed(name, &report, kind, named));
    }
    assert!(missed.is_empty(), "{missed:#?}");
    // A row stored while the status CHECK was gone is found too.
    let url = pg.fresh("pg_tamper_status_row");
    let mut cdb = common::Backend::open(pg, &url);
    one_stored_node(cdb.as_mut());
    pg.raw_sql(
        &url,
        "ALTER TABLE runs DROP CONSTRAINT runs_status_check;
         UPDATE runs SET status = 'finishe'",
    );
    let report = cdb.check().unwrap();
    assert!(
        names_finding(&report, "invalid_status", "finishe"),
        "{report:?}"
    );
}

/// Issue 25 item 16 on SQLite: the same comparison of keys, CHECKs (from the stored DDL) and
/// indexes. A dropped unique index, a status CHECK edited out of the stored schema, a
/// `progress` table rebuilt without its primary key and an extra NOT NULL column without a
/// default are each found by name; the untampered file passes.
#[test]
fn sqlite_check_finds_tampered_keys_checks_and_indexes() {
    let cases = [
        ("sq_tamper_none", "SELECT 1", "", ""),
        (
            "sq_tamper_unique",
            "DROP INDEX records_node",
            "missing_index",
            "records_node",
        ),
        (
            "sq_tamper_status",
            "PRAGMA writable_schema = ON;
             UPDATE sqlite_master SET sql = replace(sql,
                 'CHECK (status IN (''running'', ''finished'', ''failed'', ''aborted''))', '')
                 WHERE name = 'runs';",
            "missing_constraint",
            "runs_status_check",
        ),
        (
            "sq_tamper_loose_status",
            "PRAGMA writable_schema = ON;
             UPDATE sqlite_master SET sql = replace(sql, '''aborted''', '''aborted'', ''x''')
                 WHERE name = 'runs';",
            "missing_constraint",
            "runs_status_check",
        ),
        (
            "sq_tamper_pkey",
            "PRAGMA foreign_keys = OFF;
             CREATE TABLE progress_copy (run_id TEXT NOT NULL REFERENCES runs (run_id),
                 repeat_index INTEGER NOT NULL, node_index INTEGER NOT NULL,
                 node_x_counts INTEGER NOT NULL, node_y_counts INTEGER NOT NULL,
                 node_z_counts INTEGER NOT NULL,
                 state TEXT NOT NULL CHECK (state IN ('pending', 'done', 'given_up')),
                 reason TEXT, attempts INTEGER NOT NULL DEFAULT 0, updated_unix_s REAL);
             INSERT INTO progress_copy SELECT * FROM progress;
             DROP TABLE progress;
             ALTER TABLE progress_copy RENAME TO progress;",
            "missing_constraint",
            "progress_pkey",
        ),
        (
            "sq_tamper_column",
            "ALTER TABLE records ADD COLUMN operator TEXT NOT NULL DEFAULT 'x';
             PRAGMA writable_schema = ON;
             UPDATE sqlite_master SET sql = replace(sql, 'operator TEXT NOT NULL DEFAULT ''x''',
                 'operator TEXT NOT NULL') WHERE name = 'records';",
            "extra_column",
            "operator",
        ),
    ];
    let mut missed = Vec::new();
    for (name, tamper, kind, named) in cases {
        let path = db_path(name);
        {
            let mut cdb = Cdb::open(&path).unwrap();
            one_stored_node(&mut cdb);
            let before = cdb.check().unwrap();
            assert!(before.is_ok(), "{name}: untampered CDB: {before:?}");
        }
        Connection::open(&path)
            .unwrap()
            .execute_batch(tamper)
            .unwrap();
        let report = Cdb::open_read_only(&path).unwrap().check().unwrap();
        missed.extend(tampering_missed(name, &report, kind, named));
    }
    assert!(missed.is_empty(), "{missed:#?}");
}

/// One tampered CDB, made the same way on a back end: a committed node, then rows written
/// past the library (a blank scanner id, an LCS index beyond `u32`, K̄x ≤ 0, a given-up node
/// whose reason is white space).
fn tampered_report(b: &dyn Backend, name: &str) -> spm_cdb::IntegrityReport {
    let path = b.fresh(name);
    let r = run("run-1", "S", T0);
    let nodes = plan(3);
    {
        let mut cdb = b.open(&path);
        cdb.create_run(&r).unwrap();
        cdb.register_plan(&r.run_id, &nodes).unwrap();
        cdb.commit_node(&r.run_id, &done(0, T0), &[record(&r, &nodes[0], 0, T0)])
            .unwrap();
        assert!(cdb.check().unwrap().is_ok());
    }
    let insert = |scanner: &str, lcs: i64, kx: &str| {
        b.raw_sql(
            &path,
            &format!(
                "INSERT INTO records (scanner_id, run_id, acquired_unix_s, repeat_index, node_index,
              lcs_index, node_x_counts, node_y_counts, node_z_counts, lcs_x_counts, lcs_y_counts,
              lcs_z_counts, kx_nm_per_count, ky_nm_per_count, alpha_rad, drift_vx_nm_per_s,
              drift_vy_nm_per_s, cycles_kept, cycles_discarded, quality)
             VALUES ('{scanner}', 'run-1', {T0}, 0, 0, {lcs}, 0, 0, 0, 0, 0, 0, {kx}, 0.02, 0.0,
                     0, 0, 1, 0, 1)"
            ),
        );
    };
    insert("  ", 1, "0.02");
    insert("S", 4_294_967_296, "0.02");
    insert("S", 2, "-0.02");
    b.raw_sql(
        &path,
        "UPDATE progress SET state = 'given_up', reason = '   ' WHERE node_index = 2;",
    );
    b.open_read_only(&path).unwrap().check().unwrap()
}

/// The semantic rules of `cdb check` are one set of SQL predicates in two dialects
/// (`spm_cdb`'s `sql::checks`): the same tampering gives the same findings, word for word, on
/// both back ends — including the rules PostgreSQL had alone before they were shared (a blank
/// id, a white-space reason, an index beyond `u32`).
#[test]
fn both_back_ends_find_the_same_problems_in_the_same_words() {
    let sqlite = tampered_report(&common::Sqlite, "same_problems_sqlite");
    let postgres = tampered_report(common::postgres(), "same_problems");
    let kinds = |r: &spm_cdb::IntegrityReport| {
        r.problems
            .iter()
            .map(|p| p.kind.clone())
            .collect::<Vec<_>>()
    };
    let mut expected = vec![
        "nonpositive_lcc",
        "empty_text",
        "negative_count",
        "given_up_without_reason",
        "scanner_mismatch",
    ];
    expected.sort_unstable();
    for report in [&sqlite, &postgres] {
        let mut found = kinds(report);
        found.sort_unstable();
        assert_eq!(found, expected, "{report:?}");
        assert!(report.sqlite.is_empty(), "{report:?}");
    }
    assert_eq!(sqlite.problems, postgres.problems);
}
