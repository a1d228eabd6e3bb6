//! Shared helpers of the CDB tests.
#![allow(clippy::unwrap_used, dead_code)]

use spm_cdb::{DynamicsRecord, LccRecord, PlanNode, RunInfo, RunStatus};
use std::path::PathBuf;

/// A fresh path for a test database (removed with its WAL/SHM files if left over).
pub fn db_path(name: &str) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("spm-cdb-tests");
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join(format!("{name}.sqlite"));
    for suffix in ["", "-wal", "-shm", "-journal", "-identity"] {
        let mut f = p.clone().into_os_string();
        f.push(suffix);
        let _ = std::fs::remove_file(PathBuf::from(f));
    }
    p
}

/// 2024-01-01T00:00:00Z.
pub const T0: f64 = 1_704_067_200.0;

pub fn run(run_id: &str, scanner_id: &str, started_unix_s: f64) -> RunInfo {
    RunInfo {
        run_id: run_id.into(),
        scanner_id: scanner_id.into(),
        config: "[plan]\nnodes = 3\n".into(),
        started_unix_s,
        finished_unix_s: None,
        status: RunStatus::Running,
    }
}

/// A plan of `n` nodes per plane on planes z = 0 and z = 500, one repeat.
pub fn plan(n: u32) -> Vec<PlanNode> {
    let mut v = Vec::new();
    for (p, z) in [0_i64, 500].into_iter().enumerate() {
        for k in 0..n {
            v.push(PlanNode {
                repeat_index: 0,
                node_index: p as u32 * n + k,
                node_x_counts: i64::from(k) * 1000,
                node_y_counts: i64::from(k % 2) * 1000,
                node_z_counts: z,
            });
        }
    }
    v
}

/// A plausible record at a plan node.
pub fn record(run: &RunInfo, node: &PlanNode, lcs_index: u32, t_unix_s: f64) -> LccRecord {
    let k = f64::from(node.node_index) + 0.1 * f64::from(lcs_index);
    LccRecord {
        scanner_id: run.scanner_id.clone(),
        run_id: run.run_id.clone(),
        acquired_unix_s: t_unix_s,
        repeat_index: node.repeat_index,
        node_index: node.node_index,
        lcs_index,
        node_x_counts: node.node_x_counts,
        node_y_counts: node.node_y_counts,
        node_z_counts: node.node_z_counts,
        lcs_x_counts: node.node_x_counts as f64 + 0.25,
        lcs_y_counts: node.node_y_counts as f64 - 0.5,
        lcs_z_counts: node.node_z_counts as f64 + 1.0 / 3.0,
        kx_nm_per_count: 0.02 + 1e-5 * k,
        ky_nm_per_count: 0.021 - 1e-5 * k,
        alpha_rad: 0.001 * k - 0.002,
        kz_nm_per_count: if node.node_index.is_multiple_of(2) {
            Some(0.003)
        } else {
            None
        },
        u_kx_nm_per_count: Some(1e-5),
        u_ky_nm_per_count: Some(2e-5),
        u_alpha_rad: Some(1e-3),
        u_kz_nm_per_count: None,
        drift_vx_nm_per_s: 0.01,
        drift_vy_nm_per_s: -0.02,
        cycles_kept: 8,
        cycles_discarded: 2,
        quality: 0.9,
        kz_x_counts: None,
        kz_y_counts: None,
    }
}

// ---------------------------------------------------------------------------------------
// Both back ends: the same test body runs on the embedded file and on a private PostgreSQL
// server, through a store factory.

use spm_cdb::postgres::PgCdb;
use spm_cdb::{Cdb, CdbRead, NodeDone, Result};
use std::path::Path;

/// The writes of a CDB, on either back end (the inherent methods of `Cdb` and `PgCdb`).
pub trait Store: CdbRead + Send {
    fn create_run(&mut self, run: &RunInfo) -> Result<()>;
    fn register_plan(&mut self, run_id: &str, nodes: &[PlanNode]) -> Result<()>;
    fn commit_node(&mut self, run_id: &str, done: &NodeDone, records: &[LccRecord]) -> Result<()>;
    fn give_up_node(
        &mut self,
        run_id: &str,
        repeat_index: u32,
        node_index: u32,
        reason: &str,
        attempts: u32,
        at_unix_s: f64,
    ) -> Result<()>;
    fn finish_run(&mut self, run_id: &str, status: RunStatus, at_unix_s: f64) -> Result<()>;
    fn reopen_run(&mut self, run_id: &str) -> Result<()>;
    fn import_records(&mut self, records: &[LccRecord]) -> Result<u64>;
    fn store_dynamics(&mut self, dynamics: &DynamicsRecord) -> Result<()>;
    fn snapshot(&self) -> Result<Box<dyn CdbRead + '_>>;
}

macro_rules! store {
    ($t:ty) => {
        impl Store for $t {
            fn create_run(&mut self, run: &RunInfo) -> Result<()> {
                <$t>::create_run(self, run)
            }
            fn register_plan(&mut self, run_id: &str, nodes: &[PlanNode]) -> Result<()> {
                <$t>::register_plan(self, run_id, nodes)
            }
            fn commit_node(
                &mut self,
                run_id: &str,
                done: &NodeDone,
                records: &[LccRecord],
            ) -> Result<()> {
                <$t>::commit_node(self, run_id, done, records)
            }
            fn give_up_node(
                &mut self,
                run_id: &str,
                repeat_index: u32,
                node_index: u32,
                reason: &str,
                attempts: u32,
                at_unix_s: f64,
            ) -> Result<()> {
                <$t>::give_up_node(
                    self,
                    run_id,
                    repeat_index,
                    node_index,
                    reason,
                    attempts,
                    at_unix_s,
                )
            }
            fn finish_run(
                &mut self,
                run_id: &str,
                status: RunStatus,
                at_unix_s: f64,
            ) -> Result<()> {
                <$t>::finish_run(self, run_id, status, at_unix_s)
            }
            fn reopen_run(&mut self, run_id: &str) -> Result<()> {
                <$t>::reopen_run(self, run_id)
            }
            fn import_records(&mut self, records: &[LccRecord]) -> Result<u64> {
                <$t>::import_records(self, records)
            }
            fn store_dynamics(&mut self, dynamics: &DynamicsRecord) -> Result<()> {
                <$t>::store_dynamics(self, dynamics)
            }
            fn snapshot(&self) -> Result<Box<dyn CdbRead + '_>> {
                Ok(Box::new(<$t>::snapshot(self)?))
            }
        }
    };
}

store!(Cdb);
store!(PgCdb);

/// A store factory: fresh databases by name, opened read-write.
pub trait Backend: Sync {
    /// An empty database for the test `name`; returns its location (path or URL).
    fn fresh(&self, name: &str) -> String;
    /// Opens a database read-write (creating the schema).
    fn open(&self, location: &str) -> Box<dyn Store>;
    /// Opens a database read-only.
    fn open_read_only(&self, location: &str) -> Result<Box<dyn CdbRead>>;
    /// Runs SQL on the database directly (to corrupt it behind the library's back).
    fn raw_sql(&self, location: &str, sql: &str);
    /// What errors name as the database's place.
    fn shown(&self, location: &str) -> std::path::PathBuf;
    /// An SQL literal for +∞ that the back end stores in a REAL / DOUBLE PRECISION column.
    fn infinity_literal(&self) -> &'static str;
    /// SQL that lets the statements after it (in the same `raw_sql` call) write `dynamics`
    /// rows the schema forbids: a missing run, a non-finite time, a model that is not a
    /// JSON object (damage behind the library's back).
    fn lift_dynamics_constraints(&self) -> &'static str;
}

/// Scanner dynamics identified by `run` at `t` (a small valid model).
pub fn dynamics(run: &RunInfo, t_unix_s: f64, gamma: f64) -> DynamicsRecord {
    DynamicsRecord {
        run_id: run.run_id.clone(),
        scanner_id: run.scanner_id.clone(),
        identified_unix_s: t_unix_s,
        model_format: "spmcal-dynamics".into(),
        model_version: 1,
        model_json: format!(
            r#"{{"creep":{{"gamma":{gamma},"tau_s":1.0}},"hysteresis":{{"x":[0.1,0.2],"y":[]}}}}"#
        ),
    }
}

/// The embedded SQLite file.
pub struct Sqlite;

impl Backend for Sqlite {
    fn fresh(&self, name: &str) -> String {
        db_path(name).to_string_lossy().into_owned()
    }
    fn open(&self, location: &str) -> Box<dyn Store> {
        Box::new(Cdb::open(location).unwrap())
    }
    fn open_read_only(&self, location: &str) -> Result<Box<dyn CdbRead>> {
        Ok(Box::new(Cdb::open_read_only(location)?))
    }
    fn raw_sql(&self, location: &str, sql: &str) {
        rusqlite::Connection::open(location)
            .unwrap()
            .execute_batch(sql)
            .unwrap();
    }
    fn shown(&self, location: &str) -> std::path::PathBuf {
        Path::new(location).to_path_buf()
    }
    fn infinity_literal(&self) -> &'static str {
        "9e999"
    }
    fn lift_dynamics_constraints(&self) -> &'static str {
        "PRAGMA foreign_keys = OFF; PRAGMA ignore_check_constraints = ON;"
    }
}

/// A private PostgreSQL server, one per test binary (stopped by its watchdog when the binary
/// exits), one database per test.
pub struct Postgres {
    server: spm_cdb::pg_server::TestServer,
}

impl Postgres {
    /// The server's data folder (its `pg_hba.conf`).
    pub fn data_dir(&self) -> std::path::PathBuf {
        self.server.dir().join("data")
    }
}

/// The test binary's PostgreSQL server, started on first use. Panics with the harness's
/// message (naming what is missing) if PostgreSQL is not installed.
pub fn postgres() -> &'static Postgres {
    static SERVER: std::sync::OnceLock<Postgres> = std::sync::OnceLock::new();
    SERVER.get_or_init(|| Postgres {
        server: spm_cdb::pg_server::TestServer::start()
            .unwrap_or_else(|e| panic!("cannot start the private PostgreSQL server: {e}")),
    })
}

impl Backend for Postgres {
    fn fresh(&self, name: &str) -> String {
        self.server.create_database(name).unwrap()
    }
    fn open(&self, location: &str) -> Box<dyn Store> {
        Box::new(PgCdb::open(location).unwrap())
    }
    fn open_read_only(&self, location: &str) -> Result<Box<dyn CdbRead>> {
        Ok(Box::new(PgCdb::open_read_only(location)?))
    }
    fn raw_sql(&self, location: &str, sql: &str) {
        postgres::Client::connect(location, postgres::NoTls)
            .unwrap()
            .batch_execute(sql)
            .unwrap();
    }
    fn shown(&self, location: &str) -> std::path::PathBuf {
        std::path::PathBuf::from(location)
    }
    fn infinity_literal(&self) -> &'static str {
        "'Infinity'"
    }
    fn lift_dynamics_constraints(&self) -> &'static str {
        "ALTER TABLE dynamics DROP CONSTRAINT dynamics_run_id_fkey, \
         DROP CONSTRAINT dynamics_time_finite, DROP CONSTRAINT dynamics_model_json_object;"
    }
}

/// `#[test]`s running each named body (`fn name(b: &'static dyn Backend)`) on both back ends:
/// `sqlite::name` and `postgres::name`.
#[macro_export]
macro_rules! on_both_backends {
    ($($name:ident),* $(,)?) => {
        mod sqlite {
            $(#[test]
            fn $name() {
                super::$name(&super::common::Sqlite);
            })*
        }
        mod postgres {
            $(#[test]
            fn $name() {
                super::$name(super::common::postgres());
            })*
        }
    };
}
