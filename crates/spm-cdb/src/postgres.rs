//! The shared calibration database on PostgreSQL (feature `postgres`): the same schema,
//! versions and migrations as the embedded file, for a lab whose instruments calibrate into
//! one database at once.
//!
//! # Schema and versions
//! The SQLite schema with PostgreSQL types (`DOUBLE PRECISION`, `BIGINT`, `TEXT`); the record
//! columns are built from [`spm_records::LCC_RECORD_COLUMNS`]. A `schema_version` table holds
//! one row per applied version (the number, [`crate::APPLICATION_ID`] and what the step did).
//! A new database is created at v1 and brought to the current version by the migrations in
//! one transaction (readers see no schema or all of it); an older database is migrated one
//! transaction per step. Both run under a transaction-scoped advisory lock, so programs
//! opening one database at once do not race. A database of a *newer* schema is refused ([`ErrorKind::NewerSchema`]) after a look
//! that writes nothing.
//!
//! # Transactions and concurrency
//! Every write is one transaction (`READ COMMITTED`). [`PgCdb::commit_node`] locks its plan
//! row (`SELECT … FOR UPDATE`), inserts the node's records and marks the row done: commits of
//! different runs touch different rows and never wait for each other, two programs resuming
//! the same run serialise on the row and the second finds the node done
//! ([`ErrorKind::Conflict`]), and the unique (run, repeat, node, lcs) index makes a duplicate
//! record impossible. Readers never block writers: a [`PgSnapshot`] is a
//! `REPEATABLE READ READ ONLY` transaction.
//!
//! # Connection
//! `postgres://user[:password]@host[:port]/dbname` (or the libpq key-value form), plain TCP or
//! a Unix socket (`?host=/run/postgresql`). Errors name the URL without its password. A URL
//! without a password takes it, as libpq does, from `PGPASSWORD`, else from the password file
//! `PGPASSFILE` or `~/.pgpass` (mode 0600; see `pgpass.rs`).

use std::cell::{RefCell, RefMut};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::LazyLock;

use postgres::types::{ToSql, Type};
use postgres::{Client, NoTls, Row, Statement};

#[cfg(doc)]
use crate::ErrorKind;
use crate::constraints::{Found, Kind};
use crate::error::{CdbError, Result};
use crate::schema::{APPLICATION_ID, SCHEMA_VERSION};
use crate::sql::checks::{self, Checker};
use crate::sql::{self, Dialect};
use crate::{invalid, validate_record};
use spm_records::{
    ColumnKind, ColumnValue, IntegrityReport, LCC_RECORD_COLUMNS, LccRecord, UNCERTAINTY_COLUMNS,
};

/// True if `location` names a PostgreSQL database (`postgres://` or `postgresql://`) rather
/// than a file.
#[must_use]
pub fn is_postgres_url(location: &str) -> bool {
    let lower = location.trim_start().to_ascii_lowercase();
    lower.starts_with("postgres://") || lower.starts_with("postgresql://")
}

/// The URL for messages, errors and logs, rebuilt from the *parsed* configuration (the
/// same parser the connection uses) without the password: `scheme://user[:***]@host[:port]
/// /dbname`, with `:***` wherever a password was given (in the user info or as a
/// parameter, however spelled or percent-encoded). Only the user, hosts, ports (other than
/// 5432), Unix-socket folder, database and connect timeout are shown; a URL the parser
/// rejects is not shown at all (issue 25: redacting the text itself missed passwords
/// holding `/` or `?`).
#[must_use]
pub fn redact_url(url: &str) -> String {
    let trimmed = url.trim();
    let scheme = if trimmed.to_ascii_lowercase().starts_with("postgresql://") {
        "postgresql"
    } else if trimmed.to_ascii_lowercase().starts_with("postgres://") {
        "postgres"
    } else {
        return url.to_owned();
    };
    // The parser expects the scheme in lower case.
    let lowered = format!("{scheme}://{}", &trimmed[scheme.len() + 3..]);
    let Ok(config) = postgres::Config::from_str(&lowered) else {
        return format!("{scheme}://(a malformed URL, not shown)");
    };
    shown_config(scheme, &config)
}

/// `scheme://user[:***]@hosts/dbname[?host=…&connect_timeout=…]` of a parsed configuration.
fn shown_config(scheme: &str, config: &postgres::Config) -> String {
    use postgres::config::Host;
    let mut out = format!("{scheme}://");
    if let Some(user) = config.get_user() {
        out.push_str(&percent_encode(user));
        if config.get_password().is_some() {
            out.push_str(":***");
        }
        out.push('@');
    } else if config.get_password().is_some() {
        out.push_str(":***@");
    }
    let ports = config.get_ports();
    let port_of = |i: usize| ports.get(i).or_else(|| ports.first()).copied();
    let mut tcp = Vec::new();
    let mut sockets = Vec::new();
    for (i, host) in config.get_hosts().iter().enumerate() {
        match host {
            Host::Tcp(name) => {
                let mut h = if name.contains(':') {
                    format!("[{name}]")
                } else {
                    percent_encode(name)
                };
                if let Some(port) = port_of(i).filter(|&p| p != 5432) {
                    h.push_str(&format!(":{port}"));
                }
                tcp.push(h);
            }
            #[cfg(unix)]
            Host::Unix(path) => sockets.push(path.display().to_string()),
        }
    }
    if tcp.is_empty() && sockets.is_empty() {
        tcp = config
            .get_hostaddrs()
            .iter()
            .map(|a| match a {
                std::net::IpAddr::V6(v6) => format!("[{v6}]"),
                std::net::IpAddr::V4(v4) => v4.to_string(),
            })
            .collect();
    }
    out.push_str(&tcp.join(","));
    out.push('/');
    if let Some(db) = config.get_dbname() {
        out.push_str(&percent_encode(db));
    }
    let mut params: Vec<String> = sockets.iter().map(|s| format!("host={s}")).collect();
    if let Some(t) = config.get_connect_timeout() {
        params.push(format!("connect_timeout={}", t.as_secs()));
    }
    if !params.is_empty() {
        out.push('?');
        out.push_str(&params.join("&"));
    }
    out
}

/// Percent-encodes the characters that would make a shown URL ambiguous.
fn percent_encode(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '%' | '@' | ':' | '/' | '?' | '&' | '=' | '#' | ',' | '[' | ']' => {
                out.push_str(&format!("%{:02X}", u32::from(c)));
            }
            c if c.is_control() => {
                let mut buf = [0; 4];
                for b in c.encode_utf8(&mut buf).bytes() {
                    out.push_str(&format!("%{b:02X}"));
                }
            }
            c => out.push(c),
        }
    }
    out
}

/// Versions of the PostgreSQL schema. History as in [`crate::SCHEMA_VERSION`]:
/// - v1: runs, progress, records without standard uncertainties.
/// - v2: records gain the standard uncertainties (NULL = unknown for records migrated from v1).
/// - v3: records gain `kz_x_counts`, `kz_y_counts`, where Kz was measured (NULL = no Kz).
/// - v4: the CDB identity: `cdb_identity` (a random id, a generation) and `runs.cdb_id`
///   (the database's id in every run row; the write-ahead-log checks of the file are the
///   server's business here).
/// - v5: the scanner dynamics: `dynamics` (run, scanner, time, model format and version,
///   the model as a JSON object in text, kept byte for byte), indexed by (scanner, time).
///   The migration only adds the table: runs, progress, records and the identity stay as
///   they are. Like the other writes here, storing dynamics leaves the identity's
///   generation alone (the log is the server's business).
const V1_DESCRIPTION: &str = "runs, progress, records";

/// Record columns added by later versions (absent from the v1 `records` table).
const ADDED_AFTER_V1: [&str; 6] = [
    UNCERTAINTY_COLUMNS[0],
    UNCERTAINTY_COLUMNS[1],
    UNCERTAINTY_COLUMNS[2],
    UNCERTAINTY_COLUMNS[3],
    "kz_x_counts",
    "kz_y_counts",
];

/// Migration steps: `MIGRATIONS[k]` takes version k+1 to k+2 (description, SQL).
const MIGRATIONS: &[(&str, &str)] = &[
    (
        "standard uncertainties",
        "ALTER TABLE records ADD COLUMN u_kx_nm_per_count DOUBLE PRECISION;
     ALTER TABLE records ADD COLUMN u_ky_nm_per_count DOUBLE PRECISION;
     ALTER TABLE records ADD COLUMN u_alpha_rad DOUBLE PRECISION;
     ALTER TABLE records ADD COLUMN u_kz_nm_per_count DOUBLE PRECISION;",
    ),
    (
        "where Kz was measured",
        "ALTER TABLE records ADD COLUMN kz_x_counts DOUBLE PRECISION;
     ALTER TABLE records ADD COLUMN kz_y_counts DOUBLE PRECISION;",
    ),
    (
        "the CDB identity",
        "CREATE TABLE cdb_identity (id TEXT NOT NULL, generation BIGINT NOT NULL);
     INSERT INTO cdb_identity (id, generation)
         VALUES (md5(random()::TEXT || clock_timestamp()::TEXT), 1);
     ALTER TABLE runs ADD COLUMN cdb_id TEXT;
     UPDATE runs SET cdb_id = (SELECT id FROM cdb_identity);",
    ),
    (
        "the scanner dynamics",
        "CREATE TABLE dynamics (
         id                BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
         run_id            TEXT NOT NULL REFERENCES runs (run_id),
         scanner_id        TEXT NOT NULL CONSTRAINT dynamics_scanner_id_text
                               CHECK (btrim(scanner_id) <> ''),
         identified_unix_s DOUBLE PRECISION NOT NULL CONSTRAINT dynamics_time_finite
                               CHECK (identified_unix_s > 0
                                      AND identified_unix_s < 'Infinity'::float8),
         model_format      TEXT NOT NULL CONSTRAINT dynamics_model_format_text
                               CHECK (btrim(model_format) <> ''),
         model_version     BIGINT NOT NULL CONSTRAINT dynamics_model_version_range
                               CHECK (model_version BETWEEN 1 AND 4294967295),
         model_json        TEXT NOT NULL CONSTRAINT dynamics_model_json_object
                               CHECK (json_typeof(model_json::json) = 'object')
     );
     CREATE INDEX dynamics_scanner ON dynamics (scanner_id, identified_unix_s);",
    ),
];

/// The v1 schema: `runs`, `progress`, and `records` with the columns of
/// [`LCC_RECORD_COLUMNS`] that v1 had.
static SCHEMA_V1: LazyLock<String> = LazyLock::new(|| {
    let record_columns: Vec<String> = LCC_RECORD_COLUMNS
        .iter()
        .filter(|c| !ADDED_AFTER_V1.contains(&c.name))
        .map(|c| {
            let extra = match c.name {
                "run_id" => " REFERENCES runs (run_id)",
                "lcs_index" => " DEFAULT 0",
                _ => "",
            };
            format!(
                "    {} {}{extra}",
                c.name,
                Dialect::Postgres.column_type(c.kind)
            )
        })
        .collect();
    format!(
        "CREATE TABLE schema_version (
    version        BIGINT PRIMARY KEY,
    application_id BIGINT NOT NULL,
    description    TEXT NOT NULL
);
CREATE TABLE runs (
    run_id          TEXT PRIMARY KEY,
    scanner_id      TEXT NOT NULL,
    config          TEXT NOT NULL,
    started_unix_s  DOUBLE PRECISION NOT NULL,
    finished_unix_s DOUBLE PRECISION,
    status          TEXT NOT NULL CHECK (status IN ('running', 'finished', 'failed', 'aborted'))
);
CREATE INDEX runs_scanner ON runs (scanner_id, started_unix_s);
CREATE TABLE progress (
    run_id         TEXT NOT NULL REFERENCES runs (run_id),
    repeat_index   BIGINT NOT NULL,
    node_index     BIGINT NOT NULL,
    node_x_counts  BIGINT NOT NULL,
    node_y_counts  BIGINT NOT NULL,
    node_z_counts  BIGINT NOT NULL,
    state          TEXT NOT NULL CHECK (state IN ('pending', 'done', 'given_up')),
    reason         TEXT,
    attempts       BIGINT NOT NULL DEFAULT 0,
    updated_unix_s DOUBLE PRECISION,
    PRIMARY KEY (run_id, repeat_index, node_index)
);
CREATE TABLE records (
    id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
{}
);
CREATE UNIQUE INDEX records_node ON records (run_id, repeat_index, node_index, lcs_index);
CREATE INDEX records_plane ON records (scanner_id, node_z_counts, acquired_unix_s);
",
        record_columns.join(",\n")
    )
});

/// A record value bound as a statement parameter.
#[derive(Debug)]
pub(crate) struct Bind<'a>(ColumnValue<'a>);

impl ToSql for Bind<'_> {
    fn to_sql(
        &self,
        ty: &Type,
        out: &mut postgres::types::private::BytesMut,
    ) -> std::result::Result<postgres::types::IsNull, Box<dyn std::error::Error + Sync + Send>>
    {
        match self.0 {
            ColumnValue::Text(t) => t.to_sql(ty, out),
            ColumnValue::Real(v) => v.to_sql(ty, out),
            ColumnValue::OptionalReal(v) => v.to_sql(ty, out),
            ColumnValue::Integer(v) => v.to_sql(ty, out),
        }
    }
    fn accepts(ty: &Type) -> bool {
        <&str as ToSql>::accepts(ty) || <f64 as ToSql>::accepts(ty) || <i64 as ToSql>::accepts(ty)
    }
    postgres::types::to_sql_checked!();
}

pub(crate) fn binds(r: &LccRecord) -> [Bind<'_>; LCC_RECORD_COLUMNS.len()] {
    r.column_values().map(Bind)
}

pub(crate) fn bind_refs<'a>(
    values: &'a [Bind<'a>; LCC_RECORD_COLUMNS.len()],
) -> Vec<&'a (dyn ToSql + Sync)> {
    values.iter().map(|b| b as &(dyn ToSql + Sync)).collect()
}

/// The PostgreSQL type of a column kind (for binary COPY).
fn copy_type(kind: ColumnKind) -> Type {
    match kind {
        ColumnKind::Text => Type::TEXT,
        ColumnKind::Real | ColumnKind::OptionalReal => Type::FLOAT8,
        ColumnKind::Integer => Type::INT8,
    }
}

/// What a look at a database found.
struct Probe {
    version: i64,
    application_ids: Vec<i64>,
    cdb_tables: i64,
}

fn probe(client: &mut impl postgres::GenericClient, path: &Path) -> Result<Probe> {
    let err = |e| CdbError::postgres(path, e);
    let row = client
        .query_one(
            "SELECT to_regclass('schema_version') IS NOT NULL, \
             (SELECT count(*) FROM pg_catalog.pg_tables WHERE schemaname = current_schema() \
              AND tablename IN ('runs', 'progress', 'records'))",
            &[],
        )
        .map_err(err)?;
    let has_version: bool = row.try_get(0).map_err(err)?;
    let cdb_tables: i64 = row.try_get(1).map_err(err)?;
    if !has_version {
        return Ok(Probe {
            version: 0,
            application_ids: Vec::new(),
            cdb_tables,
        });
    }
    let rows = client
        .query(
            "SELECT coalesce(max(version), 0), array_agg(DISTINCT application_id) \
             FROM schema_version",
            &[],
        )
        .map_err(err)?;
    let (version, application_ids) = match rows.first() {
        Some(r) => (
            r.try_get::<_, i64>(0).map_err(err)?,
            r.try_get::<_, Option<Vec<i64>>>(1)
                .map_err(err)?
                .unwrap_or_default(),
        ),
        None => (0, Vec::new()),
    };
    Ok(Probe {
        version,
        application_ids,
        cdb_tables,
    })
}

fn check_probe(path: &Path, p: &Probe) -> Result<()> {
    if let Some(other) = p.application_ids.iter().find(|&&a| a != APPLICATION_ID) {
        return Err(CdbError::NotACdb {
            path: path.to_path_buf(),
            reason: format!("schema_version has application_id {other:#x}"),
        });
    }
    crate::schema::check_version(
        path,
        p.version,
        p.cdb_tables > 0,
        "tables runs/progress/records present but no schema_version",
    )
}

/// Creates the schema in an empty database or migrates an older one up to `target`, one
/// transaction per step, each under the advisory lock keyed by [`APPLICATION_ID`].
fn initialise_or_migrate(client: &mut Client, path: &Path, target: i64) -> Result<()> {
    loop {
        let err = |e| CdbError::postgres(path, e);
        let mut tx = client.transaction().map_err(err)?;
        tx.execute("SELECT pg_advisory_xact_lock($1)", &[&APPLICATION_ID])
            .map_err(err)?;
        // Re-read under the lock: another program may have migrated meanwhile.
        let p = probe(&mut tx, path)?;
        check_probe(path, &p)?;
        let version = p.version;
        if version >= target {
            return Ok(());
        }
        let step = |e| CdbError::postgres(path, e);
        if version == 0 {
            // A new database is made at v1 and brought to the target by the migrations, all
            // in this one transaction: other programs see no schema or the whole of it.
            tracing::info!(path = %path.display(), version = target, "creating CDB schema");
            tx.batch_execute(&SCHEMA_V1).map_err(step)?;
            tx.execute(
                "INSERT INTO schema_version (version, application_id, description) \
                 VALUES (1, $1, $2)",
                &[&APPLICATION_ID, &V1_DESCRIPTION],
            )
            .map_err(step)?;
            for v in 1..target {
                migrate_step(&mut tx, path, v)?;
            }
        } else {
            tracing::info!(path = %path.display(), from = version, to = version + 1, "migrating CDB");
            migrate_step(&mut tx, path, version)?;
        }
        tx.commit().map_err(step)?;
    }
}

/// Applies the migration from `version` to `version + 1` inside `tx` and records it.
fn migrate_step(tx: &mut postgres::Transaction<'_>, path: &Path, version: i64) -> Result<()> {
    let step = |e| CdbError::postgres(path, e);
    let Some((description, sql)) = usize::try_from(version - 1)
        .ok()
        .and_then(|k| MIGRATIONS.get(k))
    else {
        return Err(CdbError::NotACdb {
            path: path.to_path_buf(),
            reason: format!("no migration from schema version {version}"),
        });
    };
    tx.batch_execute(sql).map_err(step)?;
    tx.execute(
        "INSERT INTO schema_version (version, application_id, description) \
         VALUES ($1, $2, $3)",
        &[&(version + 1), &APPLICATION_ID, description],
    )
    .map_err(step)?;
    Ok(())
}

/// An open shared calibration database on PostgreSQL.
pub struct PgCdb {
    client: RefCell<Client>,
    path: PathBuf,
    insert: Option<Statement>,
}

impl std::fmt::Debug for PgCdb {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PgCdb").field("url", &self.path).finish()
    }
}

/// A read transaction (`REPEATABLE READ READ ONLY`) on a [`PgCdb`]: every query through it
/// sees the same committed state. Ends when dropped.
#[derive(Debug)]
pub struct PgSnapshot<'c> {
    db: &'c PgCdb,
}

impl Drop for PgSnapshot<'_> {
    fn drop(&mut self) {
        if let Ok(mut client) = self.db.client.try_borrow_mut()
            && let Err(e) = client.batch_execute("COMMIT")
        {
            tracing::debug!(error = %e, "ending a PostgreSQL snapshot");
        }
    }
}

/// How long a connection may take, TCP connect and start-up together, when the URL gives no
/// `connect_timeout` (libpq's parameter, seconds).
pub const DEFAULT_CONNECT_TIMEOUT_S: u64 = 10;
/// `lock_timeout` of every session, ms: a table lock held by another session fails the
/// statement after this, instead of waiting without end. A URL's `options=-c lock_timeout=…`
/// overrides it.
pub const DEFAULT_LOCK_TIMEOUT_MS: u64 = 30_000;
/// `statement_timeout` of every session, ms (the longest statement spmcal sends, an export
/// of a large CDB, takes seconds). A URL's `options=-c statement_timeout=…` overrides it.
pub const DEFAULT_STATEMENT_TIMEOUT_MS: u64 = 600_000;
/// TCP keepalive: first probe after this idle time, s (a host that went away is noticed
/// within about a minute instead of the kernel's two hours).
const KEEPALIVE_IDLE_S: u64 = 30;

fn connect(url: &str, path: &Path, read_only: bool) -> Result<Client> {
    let mut config =
        postgres::Config::from_str(url.trim()).map_err(|e| CdbError::InvalidInput {
            path: path.to_path_buf(),
            reason: format!(
                "not a PostgreSQL URL: {}",
                crate::error::postgres_message(&e)
            ),
        })?;
    check_config(path, &config)?;
    crate::pgpass::fill_in(&mut config);
    config.application_name("spmcal");
    // Session timeouts first, so that the URL's own `options` (later) override them.
    let mut options = format!(
        "-c lock_timeout={DEFAULT_LOCK_TIMEOUT_MS} -c statement_timeout={DEFAULT_STATEMENT_TIMEOUT_MS}"
    );
    if let Some(own) = config.get_options() {
        options.push(' ');
        options.push_str(own);
    }
    if read_only {
        options.push_str(" -c default_transaction_read_only=on");
    }
    config.options(&options);
    let timeout = config
        .get_connect_timeout()
        .copied()
        .unwrap_or(std::time::Duration::from_secs(DEFAULT_CONNECT_TIMEOUT_S));
    config.connect_timeout(timeout);
    config.keepalives(true);
    config.keepalives_idle(std::time::Duration::from_secs(KEEPALIVE_IDLE_S));
    // The client's connect timeout covers the TCP connect only: a server that accepts and
    // never answers would hold the start-up for ever. The whole connect runs on a thread
    // that is given up after the timeout (it ends with the process or when the socket does).
    let (sender, receiver) = std::sync::mpsc::channel();
    std::thread::Builder::new()
        .name("postgres-connect".to_owned())
        .spawn(move || {
            let _ = sender.send(config.connect(NoTls));
        })
        .map_err(|e| CdbError::Io {
            path: path.to_path_buf(),
            context: "starting the connection thread".to_owned(),
            source: e,
        })?;
    let unanswered = || CdbError::Unanswered {
        path: path.to_path_buf(),
        what: "connecting",
        timeout_s: timeout.as_secs_f64(),
    };
    let mut client = match receiver.recv_timeout(timeout + std::time::Duration::from_millis(500)) {
        Ok(connected) => connected.map_err(|e| CdbError::postgres(path, e))?,
        Err(_) => return Err(unanswered()),
    };
    pin_schema(&mut client, path)?;
    Ok(client)
}

/// Resolves the one schema the CDB lives in and pins the session's `search_path` to it, so
/// that every query and every catalogue lookup (the probe's table count, the check's
/// column list, both filtered on `current_schema()`) mean the same tables (issue 25: an
/// account with its own schema on its `search_path` had its lookups filtered on its own,
/// empty schema while the queries found the CDB in `public`). The schema is the one where
/// `schema_version` resolves through the account's `search_path`, else the first existing
/// schema of that path (where a new CDB is created).
fn pin_schema(client: &mut Client, path: &Path) -> Result<()> {
    let err = |e| CdbError::postgres(path, e);
    let row = client
        .query_one(
            "SELECT coalesce((SELECT n.nspname::TEXT FROM pg_catalog.pg_class c \
             JOIN pg_catalog.pg_namespace n ON n.oid = c.relnamespace \
             WHERE c.oid = to_regclass('schema_version')), current_schema()::TEXT)",
            &[],
        )
        .map_err(err)?;
    let schema: Option<String> = row.try_get(0).map_err(err)?;
    let Some(schema) = schema else {
        return Err(CdbError::InvalidInput {
            path: path.to_path_buf(),
            reason: "no schema of the account's search_path exists: create one or set \
                     search_path"
                .into(),
        });
    };
    client
        .execute(
            "SELECT pg_catalog.set_config('search_path', pg_catalog.quote_ident($1), false)",
            &[&schema],
        )
        .map_err(err)?;
    tracing::debug!(url = %path.display(), schema, "CDB schema resolved");
    Ok(())
}

/// The checks the client makes when connecting, made first so that a URL without a host
/// or user is bad input (exit 2) naming what is missing, not a connection failure
/// ("invalid configuration", issue 25). (A missing user or database is the server's
/// default, as with libpq.)
fn check_config(path: &Path, config: &postgres::Config) -> Result<()> {
    let bad = |reason: &str| {
        Err(CdbError::InvalidInput {
            path: path.to_path_buf(),
            reason: format!("the PostgreSQL URL {reason}"),
        })
    };
    let hosts = config.get_hosts().len().max(config.get_hostaddrs().len());
    if hosts == 0 {
        return bad("names no host: give postgres://user@host[:port]/database");
    }
    if !config.get_hosts().is_empty()
        && !config.get_hostaddrs().is_empty()
        && config.get_hosts().len() != config.get_hostaddrs().len()
    {
        return bad("names a different number of hosts and hostaddrs");
    }
    if config.get_ports().len() > 1 && config.get_ports().len() != hosts {
        return bad("names a different number of ports and hosts");
    }
    Ok(())
}

impl PgCdb {
    /// Connects read-write, creating the schema in an empty database and migrating an older
    /// one.
    ///
    /// # Errors
    /// [`ErrorKind::NewerSchema`] (nothing written), [`ErrorKind::NotACdb`],
    /// [`ErrorKind::Migration`], [`ErrorKind::InvalidInput`] for a malformed URL,
    /// [`ErrorKind::Postgres`] when the server cannot be reached.
    pub fn open(url: &str) -> Result<Self> {
        Self::open_at_version(url, SCHEMA_VERSION)
    }

    /// [`PgCdb::open`], creating or migrating only up to `version` (tests of the migrations).
    #[doc(hidden)]
    pub fn open_at_version(url: &str, version: i64) -> Result<Self> {
        let path = PathBuf::from(redact_url(url));
        let mut client = connect(url, &path, false)?;
        // Look first without the lock: a refused database must not be touched.
        let p = probe(&mut client, &path)?;
        check_probe(&path, &p)?;
        initialise_or_migrate(&mut client, &path, version)?;
        tracing::debug!(url = %path.display(), "CDB open");
        Ok(Self {
            client: RefCell::new(client),
            path,
            insert: None,
        })
    }

    /// Connects read-only (every transaction `READ ONLY`) to an existing CDB (for check,
    /// export, trend, fit). Never writes.
    ///
    /// # Errors
    /// [`ErrorKind::NewerSchema`], [`ErrorKind::OutdatedSchema`] (open read-write once to
    /// migrate), [`ErrorKind::NotACdb`] (also for a database without the schema), as
    /// [`PgCdb::open`].
    pub fn open_read_only(url: &str) -> Result<Self> {
        let path = PathBuf::from(redact_url(url));
        let mut client = connect(url, &path, true)?;
        let p = probe(&mut client, &path)?;
        check_probe(&path, &p)?;
        if p.version == 0 {
            return Err(CdbError::NotACdb {
                path,
                reason: "no CDB schema in this database".into(),
            });
        }
        if p.version < SCHEMA_VERSION {
            return Err(CdbError::OutdatedSchema {
                path,
                found: p.version,
                supported: SCHEMA_VERSION,
            });
        }
        Ok(Self {
            client: RefCell::new(client),
            path,
            insert: None,
        })
    }

    /// The client, for reads through `&self` (one query at a time).
    pub(crate) fn client(&self) -> Result<RefMut<'_, Client>> {
        self.client.try_borrow_mut().map_err(|_| {
            invalid(
                &self.path,
                "a query was started from inside another query's callback".into(),
            )
        })
    }

    fn err(&self) -> impl Fn(postgres::Error) -> CdbError + '_ {
        |e| CdbError::postgres(&self.path, e)
    }

    /// Runs SQL as the database owner sees it (tests that alter the database directly).
    ///
    /// # Errors
    /// PostgreSQL errors.
    #[doc(hidden)]
    pub fn batch_execute_raw(&mut self, sql: &str) -> Result<()> {
        let path = self.path.clone();
        self.client
            .get_mut()
            .batch_execute(sql)
            .map_err(|e| CdbError::postgres(&path, e))
    }

    /// Starts a read transaction: all queries through the snapshot see one committed state.
    ///
    /// # Errors
    /// PostgreSQL errors.
    pub fn snapshot(&self) -> Result<PgSnapshot<'_>> {
        self.client()?
            .batch_execute("BEGIN ISOLATION LEVEL REPEATABLE READ READ ONLY")
            .map_err(self.err())?;
        Ok(PgSnapshot { db: self })
    }

    sql::write::write_methods!();

    /// Bulk import: inserts records (of existing runs, outside any plan) in one transaction
    /// with a binary `COPY`. Returns the number inserted.
    ///
    /// # Errors
    /// [`ErrorKind::InvalidInput`] for an invalid record; [`ErrorKind::Conflict`] for a
    /// duplicate (run, repeat, node, lcs) or a record of an unknown run. Nothing is written on
    /// error.
    pub fn import_records<I>(&mut self, records: I) -> Result<u64>
    where
        I: IntoIterator,
        I::Item: std::borrow::Borrow<LccRecord>,
    {
        let path = self.path.clone();
        let err = |e| CdbError::postgres(&path, e);
        let mut tx = self.client.get_mut().transaction().map_err(err)?;
        let types: Vec<Type> = LCC_RECORD_COLUMNS
            .iter()
            .map(|c| copy_type(c.kind))
            .collect();
        let sink = tx
            .copy_in(&format!(
                "COPY records ({}) FROM STDIN (FORMAT binary)",
                sql::record_columns()
            ))
            .map_err(err)?;
        let mut writer = postgres::binary_copy::BinaryCopyInWriter::new(sink, &types);
        let mut n = 0;
        for r in records {
            let r = std::borrow::Borrow::borrow(&r);
            validate_record(&path, r)?;
            let values = binds(r);
            writer.write(&bind_refs(&values)).map_err(err)?;
            n += 1;
        }
        writer.finish().map_err(err)?;
        tx.commit().map_err(err)?;
        tracing::info!(records = n, "records imported");
        Ok(n)
    }

    fn query_rows(&self, sql: &str, params: &[&(dyn ToSql + Sync)]) -> Result<Vec<Row>> {
        self.client()?.query(sql, params).map_err(self.err())
    }
}

sql::read::sql_read!(
    PgCdb,
    |s| sql: *s,
    path: &s.path,
    version: schema_version(s),
    check: integrity_check(s),
);
sql::read::sql_read!(
    PgSnapshot<'_>,
    |s| sql: *s.db,
    path: &s.db.path,
    version: schema_version(s.db),
    check: integrity_check(s.db),
);
sql::write::progress_store!(PgCdb);

impl sql::write::SqlStore for PgCdb {
    fn write<T>(&mut self, f: impl FnOnce(&mut dyn sql::write::SqlTx) -> Result<T>) -> Result<T> {
        let path = self.path.clone();
        let err = |e| CdbError::postgres(&path, e);
        let client = self.client.get_mut();
        let insert = match &self.insert {
            Some(s) => s.clone(),
            None => {
                let s = client
                    .prepare(sql::insert_record(Dialect::Postgres))
                    .map_err(err)?;
                self.insert = Some(s.clone());
                s
            }
        };
        let mut tx = sql::pg::Tx::new(client.transaction().map_err(err)?, &path, insert);
        let out = f(&mut tx)?;
        tx.commit()?;
        Ok(out)
    }
}

/// The newest version in `schema_version`.
fn schema_version(db: &PgCdb) -> Result<i64> {
    let rows = db.query_rows("SELECT max(version) FROM schema_version", &[])?;
    let v: Option<i64> = rows
        .first()
        .map(|r| r.try_get(0))
        .transpose()
        .map_err(db.err())?
        .flatten();
    Ok(v.unwrap_or(0))
}

/// The tables and columns the current schema defines, as `(table, column, data type,
/// nullable)`.
fn expected_columns() -> Vec<(&'static str, &'static str, &'static str, bool)> {
    let mut v = vec![
        ("schema_version", "version", "bigint", false),
        ("schema_version", "application_id", "bigint", false),
        ("schema_version", "description", "text", false),
        ("runs", "run_id", "text", false),
        ("runs", "scanner_id", "text", false),
        ("runs", "config", "text", false),
        ("runs", "started_unix_s", "double precision", false),
        ("runs", "finished_unix_s", "double precision", true),
        ("runs", "status", "text", false),
        ("runs", "cdb_id", "text", true),
        ("cdb_identity", "id", "text", false),
        ("cdb_identity", "generation", "bigint", false),
        ("records", "id", "bigint", false),
    ];
    for c in [
        "repeat_index",
        "node_index",
        "node_x_counts",
        "node_y_counts",
        "node_z_counts",
    ] {
        v.push(("progress", c, "bigint", false));
    }
    v.extend([
        ("progress", "run_id", "text", false),
        ("progress", "state", "text", false),
        ("progress", "reason", "text", true),
        ("progress", "attempts", "bigint", false),
        ("progress", "updated_unix_s", "double precision", true),
    ]);
    for c in LCC_RECORD_COLUMNS {
        let (ty, nullable) = match c.kind {
            ColumnKind::Text => ("text", false),
            ColumnKind::Real => ("double precision", false),
            ColumnKind::OptionalReal => ("double precision", true),
            ColumnKind::Integer => ("bigint", false),
        };
        v.push(("records", c.name, ty, nullable));
    }
    v.extend([
        ("dynamics", "id", "bigint", false),
        ("dynamics", "run_id", "text", false),
        ("dynamics", "scanner_id", "text", false),
        ("dynamics", "identified_unix_s", "double precision", false),
        ("dynamics", "model_format", "text", false),
        ("dynamics", "model_version", "bigint", false),
        ("dynamics", "model_json", "text", false),
    ]);
    v
}

/// The columns of the CDB's tables as stored: `(table, column) → (data type, nullable)`.
fn stored_columns(db: &PgCdb) -> Result<HashMap<(String, String), (String, bool)>> {
    db.query_rows(
        "SELECT table_name::TEXT, column_name::TEXT, data_type::TEXT, is_nullable = 'YES' \
         FROM information_schema.columns WHERE table_schema = current_schema() \
         AND table_name IN ('schema_version', 'runs', 'progress', 'records', \
         'cdb_identity', 'dynamics')",
        &[],
    )?
    .iter()
    .map(|r| {
        Ok((
            (r.try_get(0)?, r.try_get(1)?),
            (r.try_get(2)?, r.try_get(3)?),
        ))
    })
    .collect::<std::result::Result<_, postgres::Error>>()
    .map_err(db.err())
}

/// The keys, CHECKs and indexes of the CDB's tables in the resolved schema, as
/// [`crate::constraints::Found`] items, and the tables present.
fn stored_constraints(db: &PgCdb) -> Result<(Vec<Found>, Vec<String>)> {
    let tables = "('schema_version', 'runs', 'progress', 'records', 'cdb_identity', 'dynamics')";
    let names = |array: &str, of: &str| {
        format!(
            "ARRAY(SELECT a.attname::TEXT FROM unnest({array}) WITH ORDINALITY AS k(n, o) \
             JOIN pg_catalog.pg_attribute a ON a.attrelid = {of} AND a.attnum = k.n \
             ORDER BY k.o)"
        )
    };
    let constraints = db.query_rows(
        &format!(
            "SELECT t.relname::TEXT, c.contype::TEXT, {}, \
             CASE WHEN c.contype = 'f' THEN r.relname::TEXT || '(' || \
             array_to_string({}, ', ') || ')' END, pg_catalog.pg_get_constraintdef(c.oid), \
             c.convalidated FROM pg_catalog.pg_constraint c \
             JOIN pg_catalog.pg_class t ON t.oid = c.conrelid \
             JOIN pg_catalog.pg_namespace n ON n.oid = t.relnamespace \
             LEFT JOIN pg_catalog.pg_class r ON r.oid = c.confrelid \
             WHERE n.nspname = current_schema() AND t.relname IN {tables} \
             AND c.contype IN ('p', 'f', 'c')",
            names("c.conkey", "c.conrelid"),
            names("c.confkey", "c.confrelid"),
        ),
        &[],
    )?;
    let indexes = db.query_rows(
        &format!(
            "SELECT t.relname::TEXT, x.indisunique, {}, \
             x.indisvalid AND x.indpred IS NULL AND x.indexprs IS NULL \
             FROM pg_catalog.pg_index x JOIN pg_catalog.pg_class t ON t.oid = x.indrelid \
             JOIN pg_catalog.pg_namespace n ON n.oid = t.relnamespace \
             WHERE n.nspname = current_schema() AND t.relname IN {tables}",
            names("x.indkey::int2[]", "x.indrelid"),
        ),
        &[],
    )?;
    let present = db.query_rows(
        &format!(
            "SELECT t.relname::TEXT FROM pg_catalog.pg_class t \
             JOIN pg_catalog.pg_namespace n ON n.oid = t.relnamespace \
             WHERE n.nspname = current_schema() AND t.relkind IN ('r', 'p') \
             AND t.relname IN {tables}"
        ),
        &[],
    )?;
    let read = || -> std::result::Result<_, postgres::Error> {
        let mut found = Vec::new();
        for r in &constraints {
            let kind = match r.try_get::<_, String>(1)?.as_str() {
                "p" => Kind::PrimaryKey,
                "f" => Kind::ForeignKey,
                _ => Kind::Check,
            };
            found.push(Found {
                kind,
                table: r.try_get(0)?,
                columns: r.try_get(2)?,
                references: r.try_get(3)?,
                definition: r.try_get(4)?,
                valid: r.try_get(5)?,
            });
        }
        for r in &indexes {
            found.push(Found {
                kind: if r.try_get(1)? {
                    Kind::UniqueIndex
                } else {
                    Kind::Index
                },
                table: r.try_get(0)?,
                columns: r.try_get(2)?,
                references: None,
                definition: String::new(),
                valid: r.try_get(3)?,
            });
        }
        let present = present
            .iter()
            .map(|r| r.try_get(0))
            .collect::<std::result::Result<Vec<String>, _>>()?;
        Ok((found, present))
    };
    read().map_err(db.err())
}

/// Columns of the CDB's tables that are NOT NULL without a default (nor an identity or a
/// generated value): `(table, column)`.
fn stored_required_columns(db: &PgCdb) -> Result<Vec<(String, String)>> {
    db.query_rows(
        "SELECT table_name::TEXT, column_name::TEXT FROM information_schema.columns \
         WHERE table_schema = current_schema() AND table_name IN ('schema_version', 'runs', \
         'progress', 'records', 'cdb_identity', 'dynamics') AND is_nullable = 'NO' \
         AND column_default IS NULL AND is_identity = 'NO' AND is_generated = 'NEVER'",
        &[],
    )?
    .iter()
    .map(|r| Ok((r.try_get(0)?, r.try_get(1)?)))
    .collect::<std::result::Result<_, postgres::Error>>()
    .map_err(db.err())
}

/// The schema's keys, CHECKs and indexes (issue 25 item 16, [`crate::constraints`]) and
/// extra NOT NULL columns.
fn constraint_check(c: &mut PgChecker<'_>) -> Result<()> {
    let (found, present) = stored_constraints(c.db)?;
    c.report
        .problems
        .extend(crate::constraints::compare(&found, true, &present));
    let required = stored_required_columns(c.db)?;
    c.report
        .problems
        .extend(crate::constraints::extra_not_null(&required));
    Ok(())
}

/// The statuses and states the schema's CHECKs admit, queried: rows stored while a CHECK
/// was missing (the columns are known to exist).
fn status_check(c: &mut PgChecker<'_>) -> Result<()> {
    c.rows(
        "invalid_status",
        "SELECT 'run ' || quote_literal(run_id) || ': status ' || quote_literal(status) || \
         ' is not running, finished, failed or aborted' FROM runs WHERE status NOT IN \
         ('running', 'finished', 'failed', 'aborted') ORDER BY run_id",
    )?;
    c.rows(
        "invalid_state",
        "SELECT 'run ' || quote_literal(run_id) || ', repeat ' || repeat_index || \
         ', node ' || node_index || ': state ' || quote_literal(state) || \
         ' is not pending, done or given_up' FROM progress WHERE state NOT IN \
         ('pending', 'done', 'given_up') ORDER BY run_id, repeat_index, node_index",
    )
}

/// The records table's columns as stored (`column → (data type, nullable)`), for tests that
/// compare the schema with [`LCC_RECORD_COLUMNS`].
///
/// # Errors
/// PostgreSQL errors.
#[doc(hidden)]
pub fn records_table_columns(db: &PgCdb) -> Result<HashMap<String, (String, bool)>> {
    Ok(stored_columns(db)?
        .into_iter()
        .filter(|((t, _), _)| t == "records")
        .map(|((_, c), v)| (c, v))
        .collect())
}

type PgChecker<'a> = Checker<'a, PgCdb>;

fn integrity_check(db: &PgCdb) -> Result<IntegrityReport> {
    let mut c = Checker::new(db);
    // Structure: every column of the current schema with its type and nullability, and
    // every key, CHECK and index (the server enforces them only while they exist).
    let stored = stored_columns(db)?;
    constraint_check(&mut c)?;
    for (table, column, ty, nullable) in expected_columns() {
        match stored.get(&(table.to_owned(), column.to_owned())) {
            None => c
                .report
                .sqlite
                .push(format!("table {table}: column {column} missing")),
            Some((t, n)) if t != ty || *n != nullable => c.report.sqlite.push(format!(
                "table {table}: column {column} is {t}{}, expected {ty}{}",
                if *n { "" } else { " NOT NULL" },
                if nullable { "" } else { " NOT NULL" }
            )),
            Some(_) => {}
        }
    }
    if !c.report.sqlite.is_empty() {
        return Ok(c.report);
    }
    status_check(&mut c)?;
    checks::value_checks(&mut c)?;
    checks::relation_checks(&mut c)?;
    checks::dynamics_checks(&mut c)?;
    checks::plausibility_checks(&mut c)?;
    if !c.report.problems.is_empty() {
        tracing::warn!(
            url = %db.path.display(),
            problems = c.report.problems.len(),
            "CDB integrity problems"
        );
    }
    Ok(c.report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recognises_and_redacts_urls() {
        for (url, is_pg, shown) in [
            ("postgres://u@h:5432/db", true, "postgres://u@h/db"),
            ("postgres://u@h:5433/db", true, "postgres://u@h:5433/db"),
            (
                "postgresql://u:secret@h/db",
                true,
                "postgresql://u:***@h/db",
            ),
            (
                "postgres://u@h/db?password=x&sslmode=disable",
                true,
                "postgres://u:***@h/db",
            ),
            ("cdb.sqlite", false, "cdb.sqlite"),
            ("./postgres/cdb.sqlite", false, "./postgres/cdb.sqlite"),
        ] {
            assert_eq!(is_postgres_url(url), is_pg, "{url}");
            assert_eq!(redact_url(url), shown, "{url}");
        }
    }

    /// Issue 25 item 3: the client's parser takes everything before the first `@` as the
    /// credentials, so a password holding `/` or `?` (or given as a percent-encoded
    /// `?password=`) was printed in clear by a redaction that parsed the string itself.
    #[test]
    fn passwords_never_survive_redaction_however_they_are_spelled() {
        for (url, secret) in [
            ("postgres://u:pa/ss@h:5432/db", "pa/ss"),
            ("postgres://u:pa?ss@h/db", "pa?ss"),
            ("postgres://u:p@ss@h/db", "ss@h"),
            ("postgres://u@h/db?password=hunter2", "hunter2"),
            ("postgres://u@h/db?pass%77ord=hunter2", "hunter2"),
            (
                "postgres://u@h/db?sslmode=disable&password=hunter2",
                "hunter2",
            ),
            ("postgres://u:se%2Fcret@h/db", "se%2Fcret"),
            ("postgres://u:hunter2@h:notaport/db", "hunter2"),
            ("postgres://u:hunter2@%2Ftmp%2Fsock/db", "hunter2"),
        ] {
            let shown = redact_url(url);
            assert!(!shown.contains(secret), "{url} shown as {shown}");
            assert!(!shown.contains("hunter2"), "{shown}");
            assert!(shown.starts_with("postgres://"), "{shown}");
        }
        assert_eq!(
            redact_url("postgres://u:pa/ss@h/db"),
            "postgres://u:***@h/db"
        );
        assert_eq!(
            redact_url("postgres://u@%2Ftmp%2Fsock/db"),
            "postgres://u@/db?host=/tmp/sock"
        );
    }

    #[test]
    fn v1_records_table_lacks_exactly_the_later_columns() {
        for c in LCC_RECORD_COLUMNS {
            let present = SCHEMA_V1.contains(&format!("    {} ", c.name));
            assert_eq!(present, !ADDED_AFTER_V1.contains(&c.name), "{}", c.name);
        }
        // Every later column is added by exactly one migration step.
        for name in ADDED_AFTER_V1 {
            let adding = MIGRATIONS
                .iter()
                .filter(|(_, sql)| sql.contains(&format!("ADD COLUMN {name} ")))
                .count();
            assert_eq!(adding, 1, "{name}");
        }
    }
}
