//! The scanner dynamics through spmcal's CDB handle (issue 23): `CdbHandle::store_dynamics`
//! and `CdbHandle::latest_dynamics` work the same on an SQLite file and on a PostgreSQL
//! database (a private server, as in `postgres_cli.rs`), and the handle's snapshots (the
//! filtered one `fit` and the report read through, and the unfiltered one) see them.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use spm_cdb::{DynamicsRecord, ErrorKind, RunInfo, RunStatus};
use spmcal::cdb_handle::CdbHandle;
use std::path::{Path, PathBuf};

const T0: f64 = 1_704_067_200.0;

fn run(run_id: &str, scanner_id: &str) -> RunInfo {
    RunInfo {
        run_id: run_id.into(),
        scanner_id: scanner_id.into(),
        config: "[plan]\n".into(),
        started_unix_s: T0,
        finished_unix_s: None,
        status: RunStatus::Running,
    }
}

fn dynamics(run_id: &str, scanner_id: &str, t: f64, gamma: f64) -> DynamicsRecord {
    DynamicsRecord {
        run_id: run_id.into(),
        scanner_id: scanner_id.into(),
        identified_unix_s: t,
        model_format: "spmcal-dynamics".into(),
        model_version: 1,
        model_json: format!(r#"{{"creep":{{"gamma":{gamma}}},"hysteresis":{{"x":[],"y":[]}}}}"#),
    }
}

fn exercise(location: &Path) {
    let mut handle = CdbHandle::open(location).unwrap();
    assert_eq!(handle.latest_dynamics("S").unwrap(), None);
    handle.create_run(&run("run-1", "S")).unwrap();
    handle.create_run(&run("run-2", "S")).unwrap();
    handle.create_run(&run("run-3", "T")).unwrap();
    let newer = dynamics("run-2", "S", T0 + 7200.0, 0.02);
    let older = dynamics("run-1", "S", T0 + 3600.0, 0.01);
    let other = dynamics("run-3", "T", T0 + 9000.0, 0.03);
    handle.store_dynamics(&newer).unwrap();
    handle.store_dynamics(&older).unwrap();
    handle.store_dynamics(&other).unwrap();

    assert_eq!(handle.latest_dynamics("S").unwrap(), Some(newer.clone()));
    assert_eq!(
        handle.dynamics_for_scanner("S").unwrap(),
        [older.clone(), newer.clone()]
    );
    assert_eq!(handle.latest_dynamics("T").unwrap(), Some(other));

    let mut bad = dynamics("run-1", "S", T0, 0.0);
    bad.model_json = "[1, 2, 3]".into();
    let e = handle.store_dynamics(&bad).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::InvalidInput, "{e}");
    assert!(e.to_string().contains("model_json"), "{e}");
    let e = handle
        .store_dynamics(&dynamics("run-9", "S", T0, 0.0))
        .unwrap_err();
    assert_eq!(e.kind(), ErrorKind::NotFound, "{e}");
    assert_eq!(handle.dynamics_for_scanner("S").unwrap().len(), 2);

    // Both snapshots see them, and `cdb check` is content.
    assert_eq!(
        handle.snapshot().unwrap().latest_dynamics("S").unwrap(),
        Some(newer.clone())
    );
    assert_eq!(
        handle
            .snapshot_unfiltered()
            .unwrap()
            .dynamics_for_scanner("S")
            .unwrap(),
        [older, newer.clone()]
    );
    assert!(handle.read().check().unwrap().is_ok());
    drop(handle);
    let ro = CdbHandle::open_read_only(location).unwrap();
    assert_eq!(ro.latest_dynamics("S").unwrap(), Some(newer));
}

#[test]
fn dynamics_through_the_handle_on_sqlite() {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("spmcal-cdb-dynamics");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("dynamics.sqlite");
    for suffix in ["", "-wal", "-shm", "-identity"] {
        let mut f = path.clone().into_os_string();
        f.push(suffix);
        let _ = std::fs::remove_file(PathBuf::from(f));
    }
    exercise(&path);
}

#[test]
fn dynamics_through_the_handle_on_postgres() {
    let server = spm_cdb::pg_server::TestServer::start()
        .unwrap_or_else(|e| panic!("cannot start the private PostgreSQL server: {e}"));
    let url = server.create_database("spmcal_dynamics").unwrap();
    exercise(Path::new(&url));
}
