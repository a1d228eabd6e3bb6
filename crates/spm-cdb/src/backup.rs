//! Online backup of a SQLite CDB (issue 25): [`Cdb::backup_to`].
//!
//! Copying the file with `cp` while a writer runs can catch the file and its `-wal` at
//! different moments, and copying it back later left a stale `-wal` to be replayed over it.
//! The backup goes through SQLite's online backup API instead: every page is copied in one
//! step, inside one read transaction of the source, so the copy is one committed state
//! whatever other connections commit meanwhile (in WAL mode a reader never blocks the
//! writer, nor the writer the reader).
//!
//! The copy is written to a hidden sibling of the destination (`.NAME.backup-PID`),
//! synced, checked with `PRAGMA integrity_check`, then hard-linked into place (a link never
//! replaces an existing file) and the sibling removed; the destination gets its own
//! identity file (`NAME-identity`, see [`crate::identity`]). A failure leaves neither the
//! destination nor the sibling behind; the siblings of a backup that was killed are removed
//! by the next backup to that destination once their process is gone.

use crate::error::{CdbError, Result};
use crate::{Cdb, identity};
use rusqlite::{Connection, OpenFlags};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// What [`Cdb::backup_to`] wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BackupSummary {
    /// Pages copied.
    pub pages: u64,
    /// Records in the copy.
    pub records: u64,
    /// Size of the copy, bytes.
    pub bytes: u64,
}

/// How long a backup step waits for a source that is locked (WAL recovery by another
/// connection) before giving up.
const LOCKED_WAIT: Duration = Duration::from_secs(10);

fn companion(path: &Path, suffix: &str) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(suffix);
    PathBuf::from(s)
}

/// The hidden sibling the copy is made in.
fn sibling(dest: &Path) -> PathBuf {
    let name = dest
        .file_name()
        .map_or_else(|| "cdb".into(), |n| n.to_string_lossy().into_owned());
    dest.with_file_name(format!(".{name}.backup-{}", std::process::id()))
}

/// Removes the hidden siblings (`.NAME.backup-PID` and companions) that backups to the same
/// destination killed mid-copy left, when their process is gone; best effort.
fn remove_stale_siblings(dest: &Path) {
    let Some(name) = dest.file_name().map(|n| n.to_string_lossy().into_owned()) else {
        return;
    };
    let dir = match dest.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let prefix = format!(".{name}.backup-");
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let file_name = entry.file_name().to_string_lossy().into_owned();
        let Some(rest) = file_name.strip_prefix(&prefix) else {
            continue;
        };
        let pid_text = ["-wal", "-shm", "-journal"]
            .iter()
            .find_map(|s| rest.strip_suffix(s))
            .unwrap_or(rest);
        let Ok(pid) = pid_text.parse::<u32>() else {
            continue;
        };
        if pid != std::process::id()
            && !crate::process_alive(pid)
            && entry.file_type().is_ok_and(|t| t.is_file())
        {
            match std::fs::remove_file(entry.path()) {
                Ok(()) => {
                    tracing::info!(file = %entry.path().display(), "removed the leftover of an interrupted backup")
                }
                Err(e) => {
                    tracing::debug!(file = %entry.path().display(), error = %e, "cannot remove a backup leftover")
                }
            }
        }
    }
}

fn remove_with_companions(path: &Path) {
    for suffix in ["", "-wal", "-shm", "-journal"] {
        let _ = std::fs::remove_file(companion(path, suffix));
    }
}

/// Refuses a destination that exists (also as a dangling symbolic link) or that has a
/// write-ahead log or journal beside it (SQLite would replay it over the copy).
fn check_destination(dest: &Path) -> Result<()> {
    for suffix in ["", "-wal", "-journal"] {
        let p = companion(dest, suffix);
        if std::fs::symlink_metadata(&p).is_ok() {
            let what = if suffix.is_empty() {
                "it exists".to_owned()
            } else {
                format!("{} lies beside it", p.display())
            };
            return Err(CdbError::Conflict {
                path: dest.to_path_buf(),
                reason: format!("backup destination: {what}; refusing to overwrite it"),
            });
        }
    }
    Ok(())
}

impl Cdb {
    /// Writes a consistent copy of the database to the new file `dest` through SQLite's
    /// online backup API: safe while other connections write (the copy is one committed
    /// state), `dest` appears complete or not at all, and its structure is checked
    /// (`PRAGMA integrity_check`) before it appears.
    ///
    /// # Errors
    /// [`crate::ErrorKind::Conflict`] if `dest` exists or a `-wal`/`-journal` lies beside
    /// it; [`crate::ErrorKind::Corrupt`] if the copy fails its integrity check;
    /// [`crate::ErrorKind::Io`] for file errors; SQLite errors (named by `dest` when they
    /// concern the copy).
    pub fn backup_to(&self, dest: &Path) -> Result<BackupSummary> {
        check_destination(dest)?;
        remove_stale_siblings(dest);
        let tmp = sibling(dest);
        remove_with_companions(&tmp);
        let result = self.copy_into(&tmp, dest).and_then(|summary| {
            link_into_place(&tmp, dest)?;
            Ok(summary)
        });
        remove_with_companions(&tmp);
        let summary = result?;
        // The copy is its own database file now: its identity file records where its
        // history stands, so a stale log laid beside it later is refused.
        if let Ok(conn) = open_copy(dest)
            && let Ok(Some(current)) = identity::read(&conn)
        {
            identity::write_sidecar(dest, &current);
        }
        tracing::info!(source = %self.path.display(), dest = %dest.display(), pages = summary.pages, "CDB backed up");
        Ok(summary)
    }

    /// Copies every page into `tmp` (synced), checks it and counts its records.
    fn copy_into(&self, tmp: &Path, dest: &Path) -> Result<BackupSummary> {
        let err = |e| CdbError::sqlite(dest, e);
        let mut out = Connection::open_with_flags(
            tmp,
            OpenFlags::SQLITE_OPEN_READ_WRITE
                | OpenFlags::SQLITE_OPEN_CREATE
                | OpenFlags::SQLITE_OPEN_NO_MUTEX,
        )
        .map_err(err)?;
        out.pragma_update(None, "synchronous", "FULL")
            .map_err(err)?;
        let pages = {
            let backup = rusqlite::backup::Backup::new(&self.conn, &mut out).map_err(err)?;
            let started = Instant::now();
            loop {
                use rusqlite::backup::StepResult;
                // -1: every page in one step, so in one read transaction of the source.
                match backup.step(-1).map_err(err)? {
                    StepResult::Done => break,
                    StepResult::More => {}
                    StepResult::Busy | StepResult::Locked => {
                        if started.elapsed() > LOCKED_WAIT {
                            return Err(CdbError::sqlite(
                                &self.path,
                                rusqlite::Error::SqliteFailure(
                                    rusqlite::ffi::Error::new(rusqlite::ffi::SQLITE_BUSY),
                                    Some("source locked during the backup".into()),
                                ),
                            ));
                        }
                        std::thread::sleep(Duration::from_millis(50));
                    }
                    _ => {}
                }
            }
            u64::try_from(backup.progress().pagecount).unwrap_or(0)
        };
        // A CDB is kept in WAL mode; closing the only connection checkpoints the log into
        // the file and deletes it.
        let _: String = out
            .pragma_update_and_check(None, "journal_mode", "WAL", |r| r.get(0))
            .map_err(err)?;
        out.close().map_err(|(_, e)| err(e))?;
        let io = |context: &str, e| CdbError::Io {
            path: dest.to_path_buf(),
            context: context.to_owned(),
            source: e,
        };
        std::fs::File::open(tmp)
            .and_then(|f| f.sync_all())
            .map_err(|e| io("syncing the backup", e))?;
        let conn = open_copy(tmp).map_err(err)?;
        let problems = integrity_problems(&conn).map_err(err)?;
        if !problems.is_empty() {
            return Err(CdbError::Corrupt {
                path: dest.to_path_buf(),
                reason: format!(
                    "the backup failed its integrity check: {}",
                    problems.join("; ")
                ),
            });
        }
        let records: i64 = conn
            .query_row("SELECT count(*) FROM records", [], |r| r.get(0))
            .map_err(err)?;
        drop(conn);
        let bytes = std::fs::metadata(tmp)
            .map_err(|e| io("reading the backup's size", e))?
            .len();
        Ok(BackupSummary {
            pages,
            records: u64::try_from(records).unwrap_or(0),
            bytes,
        })
    }
}

/// A read-only connection to a copy.
fn open_copy(path: &Path) -> rusqlite::Result<Connection> {
    Connection::open_with_flags(
        path,
        OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
    )
}

/// The lines of `PRAGMA integrity_check` other than "ok".
fn integrity_problems(conn: &Connection) -> rusqlite::Result<Vec<String>> {
    let mut stmt = conn.prepare("PRAGMA integrity_check")?;
    let lines = stmt
        .query_map([], |r| r.get::<_, String>(0))?
        .collect::<rusqlite::Result<Vec<_>>>()?;
    Ok(lines.into_iter().filter(|l| l != "ok").collect())
}

/// Puts the finished copy at `dest` without ever replacing a file: a hard link (refused
/// when `dest` appeared meanwhile), or where the file system has none, a rename after a
/// last look.
fn link_into_place(tmp: &Path, dest: &Path) -> Result<()> {
    let io = |e| CdbError::Io {
        path: dest.to_path_buf(),
        context: "putting the backup in place".into(),
        source: e,
    };
    match std::fs::hard_link(tmp, dest) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
            return Err(CdbError::Conflict {
                path: dest.to_path_buf(),
                reason: "backup destination: it appeared during the backup; refusing to \
                         overwrite it"
                    .into(),
            });
        }
        Err(e) => {
            tracing::debug!(dest = %dest.display(), error = %e, "no hard link: renaming the backup into place");
            check_destination(dest)?;
            std::fs::rename(tmp, dest).map_err(io)?;
        }
    }
    if let Some(dir) = dest.parent().filter(|d| !d.as_os_str().is_empty()) {
        // The new directory entry survives a power loss too (best effort where a folder
        // cannot be opened).
        if let Ok(d) = std::fs::File::open(dir) {
            let _ = d.sync_all();
        }
    }
    Ok(())
}
