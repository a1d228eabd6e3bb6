//! Typed errors of the calibration database.

use std::path::{Path, PathBuf};

/// What went wrong, for callers that branch on it (e.g. exit code 2 for bad input, 1 otherwise).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum ErrorKind {
    /// The file's schema is newer than this program supports; it was not modified.
    NewerSchema,
    /// The file's schema is older and the connection is read-only, so it cannot be migrated.
    OutdatedSchema,
    /// The file is not a SQLite database or not a spmcal CDB.
    NotACdb,
    /// A migration step failed (the file is left at the last complete version).
    Migration,
    /// The caller passed invalid data (non-finite value, K̄ ≤ 0, mismatched ids ...).
    InvalidInput,
    /// A run or plan node does not exist.
    NotFound,
    /// The operation conflicts with the stored state (node already done, duplicate record ...).
    Conflict,
    /// Stored data cannot be decoded (wrong type, out of range): the file was altered outside
    /// this library.
    Corrupt,
    /// Another connection holds the lock beyond the busy timeout.
    Busy,
    /// Reading or writing a file or stream failed.
    Io,
    /// Any other SQLite failure.
    Sqlite,
    /// Any other PostgreSQL failure (connection refused or lost, server error).
    Postgres,
    /// The PostgreSQL server refused the account: authentication failed, the database does
    /// not exist, or the account lacks a privilege (bad input: the URL or the account is
    /// wrong, not the run).
    AccessDenied,
    /// The database, its write-ahead log and its identity file do not belong together (a
    /// foreign or stale `-wal`, a replaced or restored file); nothing was written.
    IdentityMismatch,
    /// The run's stop flag ended a wait for the PostgreSQL server or a reconnect loop;
    /// nothing of the interrupted transaction was committed unless the message says so.
    Interrupted,
}

/// An error of the calibration database; every variant names the database file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CdbError {
    /// See [`ErrorKind::NewerSchema`].
    #[error(
        "{}: schema version {found} is newer than this program supports ({supported}); the file was not modified",
        path.display()
    )]
    NewerSchema {
        /// Database file.
        path: PathBuf,
        /// Version in the file.
        found: i64,
        /// Highest version this program knows.
        supported: i64,
    },
    /// See [`ErrorKind::OutdatedSchema`].
    #[error(
        "{}: schema version {found} is older than {supported}; open it read-write once to migrate",
        path.display()
    )]
    OutdatedSchema {
        /// Database file.
        path: PathBuf,
        /// Version in the file.
        found: i64,
        /// Current version.
        supported: i64,
    },
    /// See [`ErrorKind::NotACdb`].
    #[error("{}: not a spmcal calibration database: {reason}", path.display())]
    NotACdb {
        /// Database file.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// See [`ErrorKind::Migration`].
    #[error("{}: migration from schema version {from} failed: {source}", path.display())]
    Migration {
        /// Database file.
        path: PathBuf,
        /// Version the failed step started from.
        from: i64,
        /// Underlying SQLite error.
        source: rusqlite::Error,
    },
    /// See [`ErrorKind::InvalidInput`].
    #[error("{}: invalid input: {reason}", path.display())]
    InvalidInput {
        /// Database file.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// See [`ErrorKind::NotFound`].
    #[error("{}: not found: {what}", path.display())]
    NotFound {
        /// Database file.
        path: PathBuf,
        /// What was looked for.
        what: String,
    },
    /// See [`ErrorKind::Conflict`].
    #[error("{}: conflict: {reason}", path.display())]
    Conflict {
        /// Database file.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// See [`ErrorKind::Corrupt`].
    #[error("{}: corrupt data: {reason}", path.display())]
    Corrupt {
        /// Database file.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// See [`ErrorKind::Busy`].
    #[error("{}: database busy: {source}", path.display())]
    Busy {
        /// Database file.
        path: PathBuf,
        /// Underlying SQLite error.
        source: rusqlite::Error,
    },
    /// See [`ErrorKind::Io`].
    #[error("{}: I/O error ({context}): {source}", path.display())]
    Io {
        /// Database file.
        path: PathBuf,
        /// What was being done.
        context: String,
        /// Underlying error.
        source: std::io::Error,
    },
    /// See [`ErrorKind::Sqlite`].
    #[error("{}: SQLite error: {source}", path.display())]
    Sqlite {
        /// Database file.
        path: PathBuf,
        /// Underlying SQLite error.
        source: rusqlite::Error,
    },
    /// See [`ErrorKind::IdentityMismatch`].
    #[error("{}: {reason}", path.display())]
    IdentityMismatch {
        /// Database file.
        path: PathBuf,
        /// What does not belong, and how to put it right.
        reason: String,
    },
    /// See [`ErrorKind::AccessDenied`].
    #[error("{}: access denied: {reason}", path.display())]
    AccessDenied {
        /// The database URL (without its password).
        path: PathBuf,
        /// The server's message.
        reason: String,
    },
    /// See [`ErrorKind::Postgres`].
    #[cfg(feature = "postgres")]
    #[error("{}: PostgreSQL error: {}", path.display(), postgres_message(source))]
    Postgres {
        /// The database URL (without its password).
        path: PathBuf,
        /// Underlying client error.
        source: postgres::Error,
    },
    /// See [`ErrorKind::Postgres`]: the server accepted the connection but did not complete
    /// it within the connect timeout (a server that never answers, a stopped backend).
    #[error("{}: the PostgreSQL server did not answer within {timeout_s} s ({what})", path.display())]
    Unanswered {
        /// The database URL (without its password).
        path: PathBuf,
        /// What was waited for.
        what: &'static str,
        /// The timeout, s.
        timeout_s: f64,
    },
    /// See [`ErrorKind::Postgres`]: the server cannot be reached (a connection refused, or
    /// lost and every reconnect attempt failed, or the outcome of a commit interrupted by a
    /// lost connection could not be learnt).
    #[error(
        "{}: PostgreSQL server unreachable ({attempts} reconnect attempt(s)): {last}",
        path.display()
    )]
    Unreachable {
        /// The database URL (without its password).
        path: PathBuf,
        /// Reconnect attempts made.
        attempts: u32,
        /// The last failure, in words.
        last: String,
    },
    /// See [`ErrorKind::Interrupted`].
    #[error("{}: stopped while {what} (a stop was requested)", path.display())]
    Interrupted {
        /// The database URL (without its password).
        path: PathBuf,
        /// What was under way.
        what: &'static str,
    },
}

impl CdbError {
    /// The kind of the error.
    #[must_use]
    pub fn kind(&self) -> ErrorKind {
        match self {
            Self::NewerSchema { .. } => ErrorKind::NewerSchema,
            Self::OutdatedSchema { .. } => ErrorKind::OutdatedSchema,
            Self::NotACdb { .. } => ErrorKind::NotACdb,
            Self::Migration { .. } => ErrorKind::Migration,
            Self::InvalidInput { .. } => ErrorKind::InvalidInput,
            Self::NotFound { .. } => ErrorKind::NotFound,
            Self::Conflict { .. } => ErrorKind::Conflict,
            Self::Corrupt { .. } => ErrorKind::Corrupt,
            Self::Busy { .. } => ErrorKind::Busy,
            Self::Io { .. } => ErrorKind::Io,
            Self::Sqlite { .. } => ErrorKind::Sqlite,
            Self::AccessDenied { .. } => ErrorKind::AccessDenied,
            Self::IdentityMismatch { .. } => ErrorKind::IdentityMismatch,
            #[cfg(feature = "postgres")]
            Self::Postgres { .. } => ErrorKind::Postgres,
            Self::Unanswered { .. } | Self::Unreachable { .. } => ErrorKind::Postgres,
            Self::Interrupted { .. } => ErrorKind::Interrupted,
        }
    }

    /// The database file the error concerns.
    #[must_use]
    pub fn path(&self) -> &Path {
        match self {
            Self::NewerSchema { path, .. }
            | Self::OutdatedSchema { path, .. }
            | Self::NotACdb { path, .. }
            | Self::Migration { path, .. }
            | Self::InvalidInput { path, .. }
            | Self::NotFound { path, .. }
            | Self::Conflict { path, .. }
            | Self::Corrupt { path, .. }
            | Self::Busy { path, .. }
            | Self::Io { path, .. }
            | Self::Sqlite { path, .. }
            | Self::AccessDenied { path, .. }
            | Self::IdentityMismatch { path, .. }
            | Self::Unanswered { path, .. }
            | Self::Unreachable { path, .. }
            | Self::Interrupted { path, .. } => path,
            #[cfg(feature = "postgres")]
            Self::Postgres { path, .. } => path,
        }
    }

    /// Classifies a rusqlite error.
    pub(crate) fn sqlite(path: &Path, source: rusqlite::Error) -> Self {
        use rusqlite::ErrorCode;
        let path = path.to_path_buf();
        match &source {
            rusqlite::Error::SqliteFailure(e, _) => match e.code {
                ErrorCode::DatabaseBusy | ErrorCode::DatabaseLocked => Self::Busy { path, source },
                ErrorCode::NotADatabase => Self::NotACdb {
                    path,
                    reason: source.to_string(),
                },
                ErrorCode::ConstraintViolation => Self::Conflict {
                    path,
                    reason: source.to_string(),
                },
                ErrorCode::DatabaseCorrupt => Self::Corrupt {
                    path,
                    reason: source.to_string(),
                },
                _ => Self::Sqlite { path, source },
            },
            rusqlite::Error::FromSqlConversionFailure(..)
            | rusqlite::Error::InvalidColumnType(..)
            | rusqlite::Error::IntegralValueOutOfRange(..) => Self::Corrupt {
                path,
                reason: source.to_string(),
            },
            _ => Self::Sqlite { path, source },
        }
    }
}

/// A PostgreSQL client error in words: for an error the server sent, its severity,
/// message, detail, hint and SQLSTATE (the client's own text is only "db error"); for
/// others the client's text and its cause ("error connecting to server: Connection
/// refused").
#[cfg(feature = "postgres")]
#[must_use]
pub fn postgres_message(error: &postgres::Error) -> String {
    if let Some(db) = error.as_db_error() {
        let mut text = format!(
            "{}: {} (SQLSTATE {})",
            db.severity(),
            db.message(),
            db.code().code()
        );
        if let Some(detail) = db.detail() {
            text.push_str(&format!("; detail: {detail}"));
        }
        if let Some(hint) = db.hint() {
            text.push_str(&format!("; hint: {hint}"));
        }
        return text;
    }
    let mut text = error.to_string();
    let mut cause = std::error::Error::source(error);
    while let Some(c) = cause {
        text.push_str(&format!(": {c}"));
        cause = c.source();
    }
    text
}

#[cfg(feature = "postgres")]
impl CdbError {
    /// Classifies a PostgreSQL client error by its SQLSTATE.
    pub(crate) fn postgres(path: &Path, source: postgres::Error) -> Self {
        use postgres::error::SqlState;
        let path = path.to_path_buf();
        let Some(code) = source.code().cloned() else {
            // The client's own "invalid configuration" when connecting: the server asked
            // for a password the URL does not give.
            if source.to_string().starts_with("invalid configuration") {
                return Self::AccessDenied {
                    path,
                    reason: postgres_message(&source),
                };
            }
            return Self::Postgres { path, source };
        };
        let message = postgres_message(&source);
        if code == SqlState::UNIQUE_VIOLATION
            || code == SqlState::FOREIGN_KEY_VIOLATION
            || code == SqlState::CHECK_VIOLATION
            || code == SqlState::NOT_NULL_VIOLATION
        {
            Self::Conflict {
                path,
                reason: message,
            }
        } else if code == SqlState::T_R_SERIALIZATION_FAILURE
            || code == SqlState::T_R_DEADLOCK_DETECTED
            || code == SqlState::LOCK_NOT_AVAILABLE
        {
            Self::Conflict {
                path,
                reason: format!("concurrent update: {message}"),
            }
        } else if code == SqlState::READ_ONLY_SQL_TRANSACTION {
            Self::InvalidInput {
                path,
                reason: format!("the database was opened read-only: {message}"),
            }
        } else if code == SqlState::INVALID_PASSWORD
            || code == SqlState::INVALID_AUTHORIZATION_SPECIFICATION
            || code == SqlState::INVALID_CATALOG_NAME
            || code == SqlState::INSUFFICIENT_PRIVILEGE
        {
            Self::AccessDenied {
                path,
                reason: message,
            }
        } else {
            Self::Postgres { path, source }
        }
    }
}

/// `Result` with [`CdbError`].
pub type Result<T, E = CdbError> = std::result::Result<T, E>;
