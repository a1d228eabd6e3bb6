//! Schema, version and migrations.
//!
//! The version lives in `PRAGMA user_version`; `PRAGMA application_id` marks the file as a
//! spmcal CDB. History:
//! - v1: runs, progress, records without standard uncertainties.
//! - v2: records gain `u_kx_nm_per_count`, `u_ky_nm_per_count`, `u_alpha_rad`,
//!   `u_kz_nm_per_count` (NULL = unknown for records migrated from v1).
//! - v3: records gain `kz_x_counts`, `kz_y_counts`, where Kz was measured (the step's edge
//!   point; NULL for records without Kz and for records migrated from v2, whose values are
//!   left untouched).
//! - v4: the CDB identity (issue 25): `cdb_identity` holds one row, a random id and a
//!   generation that every write transaction increments; every run row carries the id
//!   (`runs.cdb_id`; runs of a migrated file get the id the migration draws). See
//!   [`crate::identity`].
//! - v5: the scanner dynamics (issue 23): `dynamics` holds the hysteresis and creep models
//!   runs identified, one row per identification (run, scanner, time, format and version,
//!   the model as a JSON object), indexed by (scanner, time). The migration only adds the
//!   table and its index: runs, progress, records and the identity are left as they are.
//!
//! Indexes are kept to two on `records` (the unique (run, repeat, node, lcs) key and
//! (scanner, z plane, time), which also serves scanner + time-window queries) because each
//! index costs insert time.

use rusqlite::{Connection, TransactionBehavior};
use std::path::Path;

use crate::error::{CdbError, Result};

/// Schema version written by this library.
pub const SCHEMA_VERSION: i64 = 5;

/// The first schema version with the CDB identity ([`crate::identity`]).
pub(crate) const IDENTITY_VERSION: i64 = 4;

/// `PRAGMA application_id` of a spmcal CDB ("SPMC").
pub const APPLICATION_ID: i64 = 0x5350_4D43;

/// The schema of v4, used with [`DYNAMICS_V5`] for new files. The identity table comes
/// first, so that its root is page 2 in every new file.
const SCHEMA_V4: &str = "
CREATE TABLE cdb_identity (
    id         TEXT NOT NULL,
    generation INTEGER NOT NULL
);
INSERT INTO cdb_identity (id, generation) VALUES (lower(hex(randomblob(16))), 1);

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
";

/// The schema of new files, for tests that compare it with the dialect's types.
#[cfg(test)]
pub(crate) fn schema_text() -> &'static str {
    SCHEMA_V4
}

/// The `dynamics` table of v5 (new files and the v4 → v5 migration alike). The CHECKs
/// repeat the rules of [`spm_records::DynamicsRecord::check`] that SQL can state (the size
/// limit and the visible-text rule of the ids are left to it and to `cdb check`).
const DYNAMICS_V5: &str = "
CREATE TABLE dynamics (
    id                INTEGER PRIMARY KEY,
    run_id            TEXT NOT NULL REFERENCES runs (run_id),
    scanner_id        TEXT NOT NULL CHECK (length(scanner_id) > 0),
    identified_unix_s REAL NOT NULL CHECK (typeof(identified_unix_s) = 'real'
                          AND identified_unix_s > 0
                          AND identified_unix_s <= 1.7976931348623157e308),
    model_format      TEXT NOT NULL CHECK (length(model_format) > 0),
    model_version     INTEGER NOT NULL CHECK (typeof(model_version) = 'integer'
                          AND model_version BETWEEN 1 AND 4294967295),
    model_json        TEXT NOT NULL CHECK (json_valid(model_json)
                          AND json_type(model_json) = 'object')
);
CREATE INDEX dynamics_scanner ON dynamics (scanner_id, identified_unix_s);
";

/// v1 → v2: standard uncertainties.
const MIGRATE_V1_TO_V2: &str = "
ALTER TABLE records ADD COLUMN u_kx_nm_per_count REAL;
ALTER TABLE records ADD COLUMN u_ky_nm_per_count REAL;
ALTER TABLE records ADD COLUMN u_alpha_rad REAL;
ALTER TABLE records ADD COLUMN u_kz_nm_per_count REAL;
";

/// v2 → v3: where Kz was measured.
const MIGRATE_V2_TO_V3: &str = "
ALTER TABLE records ADD COLUMN kz_x_counts REAL;
ALTER TABLE records ADD COLUMN kz_y_counts REAL;
";

/// v3 → v4: the CDB identity.
const MIGRATE_V3_TO_V4: &str = "
CREATE TABLE cdb_identity (id TEXT NOT NULL, generation INTEGER NOT NULL);
INSERT INTO cdb_identity (id, generation) VALUES (lower(hex(randomblob(16))), 1);
ALTER TABLE runs ADD COLUMN cdb_id TEXT;
UPDATE runs SET cdb_id = (SELECT id FROM cdb_identity);
";

/// Migration steps: `MIGRATIONS[k]` takes version k+1 to k+2 (v4 → v5 is [`DYNAMICS_V5`]).
const MIGRATIONS: &[&str] = &[
    MIGRATE_V1_TO_V2,
    MIGRATE_V2_TO_V3,
    MIGRATE_V3_TO_V4,
    DYNAMICS_V5,
];

/// What a read-only look at a file found.
pub(crate) struct Probe {
    pub user_version: i64,
    pub application_id: i64,
    pub n_tables: i64,
}

pub(crate) fn probe(conn: &Connection) -> rusqlite::Result<Probe> {
    let user_version = conn.pragma_query_value(None, "user_version", |r| r.get(0))?;
    let application_id = conn.pragma_query_value(None, "application_id", |r| r.get(0))?;
    let n_tables = conn.query_row(
        "SELECT count(*) FROM sqlite_master WHERE type = 'table'",
        [],
        |r| r.get(0),
    )?;
    Ok(Probe {
        user_version,
        application_id,
        n_tables,
    })
}

/// Checks a probe against what this library accepts (before anything is written).
pub(crate) fn check_probe(path: &Path, p: &Probe) -> Result<()> {
    if p.application_id != 0 && p.application_id != APPLICATION_ID {
        return Err(CdbError::NotACdb {
            path: path.to_path_buf(),
            reason: format!("application_id {:#x}", p.application_id),
        });
    }
    check_version(
        path,
        p.user_version,
        p.n_tables > 0,
        "tables present but no schema version",
    )
}

/// The checks of a found schema version both back ends make before writing anything: not
/// newer than this library's, not negative, and no version only in an empty database
/// (`unversioned` says what was found instead).
pub(crate) fn check_version(
    path: &Path,
    version: i64,
    has_tables: bool,
    unversioned: &str,
) -> Result<()> {
    if version > SCHEMA_VERSION {
        return Err(CdbError::NewerSchema {
            path: path.to_path_buf(),
            found: version,
            supported: SCHEMA_VERSION,
        });
    }
    if version == 0 && has_tables {
        return Err(CdbError::NotACdb {
            path: path.to_path_buf(),
            reason: unversioned.into(),
        });
    }
    if version < 0 {
        return Err(CdbError::NotACdb {
            path: path.to_path_buf(),
            reason: format!("negative schema version {version}"),
        });
    }
    Ok(())
}

/// Creates the schema in an empty database or migrates an older one, one transaction per step.
pub(crate) fn initialise_or_migrate(conn: &mut Connection, path: &Path) -> Result<()> {
    loop {
        let tx = conn
            .transaction_with_behavior(TransactionBehavior::Immediate)
            .map_err(|e| CdbError::sqlite(path, e))?;
        // Re-read inside the write lock: another process may have migrated meanwhile.
        let p = probe(&tx).map_err(|e| CdbError::sqlite(path, e))?;
        check_probe(path, &p)?;
        let version = p.user_version;
        if version == SCHEMA_VERSION {
            return Ok(());
        }
        let step = |e| CdbError::Migration {
            path: path.to_path_buf(),
            from: version,
            source: e,
        };
        if version == 0 {
            tracing::info!(path = %path.display(), version = SCHEMA_VERSION, "creating CDB schema");
            tx.execute_batch(SCHEMA_V4).map_err(step)?;
            tx.execute_batch(DYNAMICS_V5).map_err(step)?;
            tx.pragma_update(None, "application_id", APPLICATION_ID)
                .map_err(step)?;
            tx.pragma_update(None, "user_version", SCHEMA_VERSION)
                .map_err(step)?;
        } else {
            let Some(sql) = usize::try_from(version - 1)
                .ok()
                .and_then(|k| MIGRATIONS.get(k))
            else {
                return Err(CdbError::NotACdb {
                    path: path.to_path_buf(),
                    reason: format!("no migration from schema version {version}"),
                });
            };
            tracing::info!(path = %path.display(), from = version, to = version + 1, "migrating CDB");
            tx.execute_batch(sql).map_err(step)?;
            tx.pragma_update(None, "application_id", APPLICATION_ID)
                .map_err(step)?;
            tx.pragma_update(None, "user_version", version + 1)
                .map_err(step)?;
        }
        tx.commit().map_err(step)?;
    }
}
