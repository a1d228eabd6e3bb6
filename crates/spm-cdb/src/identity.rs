//! The CDB identity (schema v4, issue 25): which database a file and its write-ahead log
//! are, and how far its history goes.
//!
//! SQLite replays a `-wal` file beside a database on open without asking whether the log
//! belongs to it: a log left from before a restore, or copied from another CDB, was
//! applied silently and `cdb check` said ok on the wrong contents. Three things tie the
//! pieces together:
//!
//! - `cdb_identity`: one row, a random id drawn at creation and a *generation* that every
//!   write transaction increments, so every committed transaction in a log carries the
//!   identity page with its generation;
//! - `runs.cdb_id`: every run row carries the id (a run row from another CDB is seen);
//! - the sidecar `NAME-identity` beside the file, outside the log: the id and the last
//!   generation a writer committed (written after the commit, so it may lag, never lead).
//!
//! Every open of an existing v4 file (read-only or read-write, before anything is written)
//! reads the sidecar, then the main file alone (`immutable=1`, which SQLite reads without
//! the log) when a log is present, then the database with its log, and refuses
//! ([`crate::ErrorKind::IdentityMismatch`]) when the log changes the id (a log of another
//! database), lowers the generation (a log older than the database), when the database is
//! another one than the sidecar names, or older than the sidecar's generation (a restored
//! backup), or holds runs of another database. The message says how to put things right.
//!
//! Limits: a file without a sidecar (made before v4, or copied alone) is adopted as it is;
//! a log that is the newer half of the *same* database laid over an older copy of the file
//! is not recognised (its generations continue the file's).

use rusqlite::{Connection, OpenFlags, OptionalExtension};
use std::path::{Path, PathBuf};

use crate::error::{CdbError, Result};

/// A database's identity: its id and the generation of its last committed write.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Identity {
    pub id: String,
    pub generation: i64,
}

/// `NAME-identity` beside the database `NAME`.
pub(crate) fn sidecar_path(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push("-identity");
    PathBuf::from(s)
}

fn companion(path: &Path, suffix: &str) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(suffix);
    PathBuf::from(s)
}

/// True when a non-empty `-wal` lies beside the database.
pub(crate) fn has_log(path: &Path) -> bool {
    std::fs::metadata(companion(path, "-wal")).is_ok_and(|m| m.len() > 0)
}

/// The identity as the connection sees it (`None` before schema v4).
pub(crate) fn read(conn: &Connection) -> rusqlite::Result<Option<Identity>> {
    let exists: bool = conn.query_row(
        "SELECT count(*) > 0 FROM sqlite_master WHERE type = 'table' AND name = 'cdb_identity'",
        [],
        |r| r.get(0),
    )?;
    if !exists {
        return Ok(None);
    }
    conn.query_row(
        "SELECT id, generation FROM cdb_identity WHERE typeof(id) = 'text' \
         AND typeof(generation) = 'integer' ORDER BY rowid LIMIT 1",
        [],
        |r| {
            Ok(Identity {
                id: r.get(0)?,
                generation: r.get(1)?,
            })
        },
    )
    .optional()
}

/// Number of runs whose `cdb_id` is not the database's id.
fn foreign_runs(conn: &Connection, id: &str) -> rusqlite::Result<i64> {
    conn.query_row(
        "SELECT count(*) FROM runs WHERE coalesce(cdb_id, '') != ?1",
        [id],
        |r| r.get(0),
    )
}

/// Increments the generation inside a write transaction; returns the new identity.
pub(crate) fn bump(conn: &Connection) -> rusqlite::Result<Option<Identity>> {
    conn.query_row(
        "UPDATE cdb_identity SET generation = generation + 1 RETURNING id, generation",
        [],
        |r| {
            Ok(Identity {
                id: r.get(0)?,
                generation: r.get(1)?,
            })
        },
    )
    .optional()
}

/// The sidecar's identity, `None` when there is none (or it cannot be read: it is then
/// rewritten at the next read-write open).
pub(crate) fn read_sidecar(path: &Path) -> Option<Identity> {
    let text = std::fs::read_to_string(sidecar_path(path)).ok()?;
    let mut id = None;
    let mut generation = None;
    for line in text.lines() {
        match line.split_once('=') {
            Some(("id", v)) => id = Some(v.trim().to_owned()),
            Some(("generation", v)) => generation = v.trim().parse().ok(),
            _ => {}
        }
    }
    let parsed = id
        .zip(generation)
        .map(|(id, generation)| Identity { id, generation });
    if parsed.is_none() {
        tracing::warn!(file = %sidecar_path(path).display(), "unreadable CDB identity file ignored");
    }
    parsed
}

/// Writes the sidecar (a temporary file renamed into place; best effort: a sidecar that
/// lags behind the database is accepted, so a failure here only weakens the next check).
pub(crate) fn write_sidecar(path: &Path, identity: &Identity) {
    let target = sidecar_path(path);
    let name = target
        .file_name()
        .map_or_else(|| "identity".into(), |n| n.to_string_lossy().into_owned());
    let tmp = target.with_file_name(format!(".{name}.tmp-{}", std::process::id()));
    let text = format!(
        "# spmcal calibration database identity (outside the write-ahead log; see \
         docs/RELIABILITY.md)\nid={}\ngeneration={}\n",
        identity.id, identity.generation
    );
    let written = std::fs::write(&tmp, text).and_then(|()| std::fs::rename(&tmp, &target));
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        tracing::debug!(file = %target.display(), error = %e, "cannot write the CDB identity file");
    }
}

/// Removes a sidecar left by a database that no longer exists (before creating a new one).
pub(crate) fn remove_stale_sidecar(path: &Path) {
    let _ = std::fs::remove_file(sidecar_path(path));
}

/// The identity in the main file alone (`immutable=1`: SQLite ignores the log), or `None`
/// when it cannot be read (a writer checkpointing at this moment; then the log check is
/// left to the other rules).
pub(crate) fn main_file(path: &Path) -> Option<Identity> {
    let conn = Connection::open_with_flags(
        crate::immutable_uri(path),
        OpenFlags::SQLITE_OPEN_READ_ONLY
            | OpenFlags::SQLITE_OPEN_NO_MUTEX
            | OpenFlags::SQLITE_OPEN_URI,
    )
    .ok()?;
    read(&conn).ok().flatten()
}

/// What an open found, read in this order: sidecar, main file alone, database with log.
pub(crate) struct Looked {
    pub sidecar: Option<Identity>,
    pub main_file: Option<Identity>,
}

impl Looked {
    /// Reads the sidecar and, when a log is present, the main file alone. Call before the
    /// connection reads the database (so that its generation is at least theirs).
    pub(crate) fn before_open(path: &Path) -> Self {
        let sidecar = read_sidecar(path);
        let main_file = if has_log(path) { main_file(path) } else { None };
        Self { sidecar, main_file }
    }

    /// Checks the database as `conn` sees it against what was looked at before.
    pub(crate) fn verify(&self, path: &Path, conn: &Connection) -> Result<()> {
        let err = |e| CdbError::sqlite(path, e);
        let Some(seen) = read(conn).map_err(err)? else {
            return Ok(());
        };
        let log = companion(path, "-wal");
        let shm = companion(path, "-shm");
        let side = sidecar_path(path);
        let move_log_aside = format!(
            "To open the database as its main file holds it, move the log aside: `mv {} {}.stale; \
             rm -f {}`. If the log belongs with another copy of the database file, put that \
             copy back instead",
            log.display(),
            log.display(),
            shm.display()
        );
        if let Some(main) = &self.main_file {
            if main.id != seen.id {
                return Err(mismatch(
                    path,
                    format!(
                        "the write-ahead log {} does not belong to this database (it turns \
                         database {} into {}): SQLite would replay it over the file. Nothing \
                         was written. {move_log_aside}.",
                        log.display(),
                        main.id,
                        seen.id
                    ),
                ));
            }
            if seen.generation < main.generation {
                return Err(mismatch(
                    path,
                    format!(
                        "the write-ahead log {} is older than the database (it takes the \
                         database from generation {} back to {}): SQLite would replay stale \
                         pages over newer ones. Nothing was written. {move_log_aside}.",
                        log.display(),
                        main.generation,
                        seen.generation
                    ),
                ));
            }
        }
        if let Some(recorded) = &self.sidecar {
            let restore = format!(
                "If the database was replaced or restored from a backup on purpose, remove {} \
                 and open it again",
                side.display()
            );
            let log_note = if has_log(path) {
                format!(
                    " (with the write-ahead log {}: if that log is the stale part, move it \
                     aside: `mv {} {}.stale; rm -f {}`)",
                    log.display(),
                    log.display(),
                    log.display(),
                    shm.display()
                )
            } else {
                String::new()
            };
            if recorded.id != seen.id {
                return Err(mismatch(
                    path,
                    format!(
                        "this is database {}, but {} records database {} here{log_note}. \
                         Nothing was written. {restore}.",
                        seen.id,
                        side.display(),
                        recorded.id
                    ),
                ));
            }
            if seen.generation < recorded.generation {
                return Err(mismatch(
                    path,
                    format!(
                        "the database is at generation {}, older than generation {} that {} \
                         records as committed{log_note}. Nothing was written. {restore}.",
                        seen.generation,
                        recorded.generation,
                        side.display()
                    ),
                ));
            }
        }
        let foreign = foreign_runs(conn, &seen.id).map_err(err)?;
        if foreign > 0 {
            return Err(mismatch(
                path,
                format!(
                    "{foreign} run(s) carry another database's id than {}: pages of another \
                     database (a foreign write-ahead log {}?) are in this one. Nothing was \
                     written. {move_log_aside}.",
                    seen.id,
                    log.display()
                ),
            ));
        }
        Ok(())
    }
}

fn mismatch(path: &Path, reason: String) -> CdbError {
    CdbError::IdentityMismatch {
        path: path.to_path_buf(),
        reason,
    }
}
