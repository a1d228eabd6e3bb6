//! The schema's keys, CHECK constraints and indexes, compared with what a CDB holds (issue 25
//! item 16).
//!
//! A column check alone let four tampered PostgreSQL schemas pass `cdb check`: a dropped
//! `progress` primary key (every `register_plan` then fails on its `ON CONFLICT`), a dropped
//! status CHECK, a dropped `records_node` unique index (the duplicate-record protection gone
//! without a sound) and an extra NOT NULL column (every insert fails). Each back end reads its
//! catalog into [`Found`] items (PostgreSQL: `pg_constraint` and `pg_index` in the one
//! resolved schema; SQLite: `pragma_table_info`, `pragma_foreign_key_list`,
//! `pragma_index_list`/`pragma_index_info` and the CHECKs of the stored DDL), and
//! [`compare`] reports every item of [`EXPECTED`] that none of them provides, by name.
//!
//! What "provides" means is structural, not textual, so that another server version's
//! spelling of the same definition is no finding: a key or an index by its table and ordered
//! columns (an index also by a longer one with those leading columns; the unique index also
//! by a primary key on them); a foreign key by its column and referenced table and column;
//! a CHECK by the columns it names, validated, and, for the status and state columns, by the
//! exact set of text literals it admits (a CHECK on `status` that lets `'x'` in too is a
//! finding). Constraints and indexes a CDB has beyond these are left alone, as are extra
//! columns, except a NOT NULL one without a default: every insert of the program would fail.

use spm_records::IntegrityProblem;

/// What kind of catalog item.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kind {
    /// A primary key.
    PrimaryKey,
    /// A foreign key.
    ForeignKey,
    /// A CHECK constraint.
    Check,
    /// A unique index (or a unique constraint's index).
    UniqueIndex,
    /// An index that need not be unique.
    Index,
}

impl Kind {
    fn label(self) -> &'static str {
        match self {
            Kind::PrimaryKey => "primary key",
            Kind::ForeignKey => "foreign key",
            Kind::Check => "CHECK constraint",
            Kind::UniqueIndex => "unique index",
            Kind::Index => "index",
        }
    }
}

/// An item of the schema every CDB must hold.
#[derive(Debug)]
pub(crate) struct Expected {
    /// Kind.
    pub kind: Kind,
    /// Table.
    pub table: &'static str,
    /// The name it has in a CDB this program made (PostgreSQL's default names).
    pub name: &'static str,
    /// Columns, in order.
    pub columns: &'static [&'static str],
    /// A foreign key's `table(column)`.
    pub references: Option<&'static str>,
    /// A CHECK's admitted text values, when it is a set of them.
    pub values: Option<&'static [&'static str]>,
    /// Only on PostgreSQL (SQLite keeps the version in a pragma).
    pub postgres_only: bool,
}

const fn item(
    kind: Kind,
    table: &'static str,
    name: &'static str,
    columns: &'static [&'static str],
) -> Expected {
    Expected {
        kind,
        table,
        name,
        columns,
        references: None,
        values: None,
        postgres_only: false,
    }
}

const fn foreign(table: &'static str, name: &'static str) -> Expected {
    Expected {
        references: Some("runs(run_id)"),
        ..item(Kind::ForeignKey, table, name, &["run_id"])
    }
}

/// The statuses `runs.status` admits.
pub(crate) const RUN_STATUSES: &[&str] = &["running", "finished", "failed", "aborted"];
/// The states `progress.state` admits.
pub(crate) const NODE_STATES: &[&str] = &["pending", "done", "given_up"];

/// Every key, CHECK and index of the current schema (both back ends unless marked).
pub(crate) const EXPECTED: &[Expected] = &[
    Expected {
        postgres_only: true,
        ..item(
            Kind::PrimaryKey,
            "schema_version",
            "schema_version_pkey",
            &["version"],
        )
    },
    item(Kind::PrimaryKey, "runs", "runs_pkey", &["run_id"]),
    Expected {
        values: Some(RUN_STATUSES),
        ..item(Kind::Check, "runs", "runs_status_check", &["status"])
    },
    item(
        Kind::Index,
        "runs",
        "runs_scanner",
        &["scanner_id", "started_unix_s"],
    ),
    item(
        Kind::PrimaryKey,
        "progress",
        "progress_pkey",
        &["run_id", "repeat_index", "node_index"],
    ),
    foreign("progress", "progress_run_id_fkey"),
    Expected {
        values: Some(NODE_STATES),
        ..item(Kind::Check, "progress", "progress_state_check", &["state"])
    },
    item(Kind::PrimaryKey, "records", "records_pkey", &["id"]),
    foreign("records", "records_run_id_fkey"),
    item(
        Kind::UniqueIndex,
        "records",
        "records_node",
        &["run_id", "repeat_index", "node_index", "lcs_index"],
    ),
    item(
        Kind::Index,
        "records",
        "records_plane",
        &["scanner_id", "node_z_counts", "acquired_unix_s"],
    ),
    item(Kind::PrimaryKey, "dynamics", "dynamics_pkey", &["id"]),
    foreign("dynamics", "dynamics_run_id_fkey"),
    item(
        Kind::Check,
        "dynamics",
        "dynamics_scanner_id_text",
        &["scanner_id"],
    ),
    item(
        Kind::Check,
        "dynamics",
        "dynamics_time_finite",
        &["identified_unix_s"],
    ),
    item(
        Kind::Check,
        "dynamics",
        "dynamics_model_format_text",
        &["model_format"],
    ),
    item(
        Kind::Check,
        "dynamics",
        "dynamics_model_version_range",
        &["model_version"],
    ),
    item(
        Kind::Check,
        "dynamics",
        "dynamics_model_json_object",
        &["model_json"],
    ),
    item(
        Kind::Index,
        "dynamics",
        "dynamics_scanner",
        &["scanner_id", "identified_unix_s"],
    ),
];

/// The columns of every table of the current schema (`(table, column)`), for the extra-column
/// rule.
pub(crate) fn expected_column_names() -> Vec<(&'static str, &'static str)> {
    let mut v: Vec<(&str, &str)> = [
        ("schema_version", "version"),
        ("schema_version", "application_id"),
        ("schema_version", "description"),
        ("runs", "run_id"),
        ("runs", "scanner_id"),
        ("runs", "config"),
        ("runs", "started_unix_s"),
        ("runs", "finished_unix_s"),
        ("runs", "status"),
        ("runs", "cdb_id"),
        ("cdb_identity", "id"),
        ("cdb_identity", "generation"),
        ("records", "id"),
        ("dynamics", "id"),
    ]
    .into();
    for c in [
        "run_id",
        "repeat_index",
        "node_index",
        "node_x_counts",
        "node_y_counts",
        "node_z_counts",
        "state",
        "reason",
        "attempts",
        "updated_unix_s",
    ] {
        v.push(("progress", c));
    }
    v.extend(
        spm_records::LCC_RECORD_COLUMNS
            .iter()
            .map(|c| ("records", c.name)),
    );
    v.extend(
        spm_records::DYNAMICS_RECORD_COLUMNS
            .iter()
            .map(|c| ("dynamics", *c)),
    );
    v
}

/// A catalog item as a CDB holds it.
#[derive(Debug, Clone)]
pub(crate) struct Found {
    /// Kind.
    pub kind: Kind,
    /// Table.
    pub table: String,
    /// Columns, in order (a CHECK: the columns it names).
    pub columns: Vec<String>,
    /// A foreign key's `table(column)`.
    pub references: Option<String>,
    /// A CHECK's definition as stored.
    pub definition: String,
    /// Enforced on every row: a validated constraint, an index without predicate or
    /// expression.
    pub valid: bool,
}

/// The text literals of an SQL expression (`'…'`, `''` an escaped quote), in order.
pub(crate) fn text_literals(sql: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut chars = sql.chars().peekable();
    while let Some(c) = chars.next() {
        if c != '\'' {
            continue;
        }
        let mut lit = String::new();
        while let Some(c) = chars.next() {
            if c == '\'' {
                if chars.peek() == Some(&'\'') {
                    chars.next();
                    lit.push('\'');
                } else {
                    break;
                }
            } else {
                lit.push(c);
            }
        }
        out.push(lit);
    }
    out
}

fn provides(e: &Expected, f: &Found) -> bool {
    if f.table != e.table || !f.valid {
        return false;
    }
    let same = |cols: &[String]| {
        cols.iter()
            .map(String::as_str)
            .eq(e.columns.iter().copied())
    };
    match e.kind {
        Kind::PrimaryKey => f.kind == Kind::PrimaryKey && same(&f.columns),
        Kind::ForeignKey => {
            f.kind == Kind::ForeignKey
                && same(&f.columns)
                && f.references.as_deref() == e.references
        }
        Kind::UniqueIndex => {
            matches!(f.kind, Kind::UniqueIndex | Kind::PrimaryKey) && same(&f.columns)
        }
        Kind::Index => {
            matches!(f.kind, Kind::Index | Kind::UniqueIndex | Kind::PrimaryKey)
                && f.columns.len() >= e.columns.len()
                && same(&f.columns[..e.columns.len()])
        }
        Kind::Check => {
            let mut cols: Vec<&str> = f.columns.iter().map(String::as_str).collect();
            cols.sort_unstable();
            let mut want: Vec<&str> = e.columns.to_vec();
            want.sort_unstable();
            f.kind == Kind::Check
                && cols == want
                && e.values.is_none_or(|values| {
                    let mut found = text_literals(&f.definition);
                    found.sort_unstable();
                    found.dedup();
                    let mut values: Vec<&str> = values.to_vec();
                    values.sort_unstable();
                    found.iter().map(String::as_str).eq(values)
                })
        }
    }
}

/// What an expected item looks like, for a finding.
fn describe(e: &Expected) -> String {
    let columns = e.columns.join(", ");
    match (e.references, e.values) {
        (Some(r), _) => format!("({columns}) REFERENCES {r}"),
        (_, Some(v)) => format!(
            "{columns} IN ({})",
            v.iter()
                .map(|s| format!("'{s}'"))
                .collect::<Vec<_>>()
                .join(", ")
        ),
        _ => format!("({columns})"),
    }
}

/// One finding (kind `missing_constraint` or `missing_index`) per item of [`EXPECTED`] that no
/// found item provides; `postgres` selects the PostgreSQL-only items too. A table that does
/// not exist is left to the column check.
pub(crate) fn compare(
    found: &[Found],
    postgres: bool,
    tables_present: &[String],
) -> Vec<IntegrityProblem> {
    let mut problems = Vec::new();
    for e in EXPECTED
        .iter()
        .filter(|e| postgres || !e.postgres_only)
        .filter(|e| tables_present.iter().any(|t| t == e.table))
    {
        if found.iter().any(|f| provides(e, f)) {
            continue;
        }
        let kind = match e.kind {
            Kind::UniqueIndex | Kind::Index => "missing_index",
            _ => "missing_constraint",
        };
        let altered: Vec<String> = found
            .iter()
            .filter(|f| f.table == e.table && f.kind == e.kind && e.kind == Kind::Check)
            .filter(|f| {
                let mut a: Vec<&str> = f.columns.iter().map(String::as_str).collect();
                a.sort_unstable();
                let mut b = e.columns.to_vec();
                b.sort_unstable();
                a == b
            })
            .map(|f| f.definition.clone())
            .collect();
        let how = if altered.is_empty() {
            "is missing".to_owned()
        } else {
            format!("is missing (found instead: {})", altered.join("; "))
        };
        problems.push(IntegrityProblem {
            kind: kind.into(),
            detail: format!(
                "table {}: {} {} {} {how}; recreate it as the schema defines it \
                 (docs/RELIABILITY.md)",
                e.table,
                e.kind.label(),
                e.name,
                describe(e)
            ),
        });
    }
    problems
}

/// One `extra_column` finding per stored column not in the schema that is NOT NULL without a
/// default (`stored`: `(table, column)` of such columns): every insert of the program fails
/// on it.
pub(crate) fn extra_not_null(stored: &[(String, String)]) -> Vec<IntegrityProblem> {
    let expected = expected_column_names();
    stored
        .iter()
        .filter(|(t, c)| !expected.iter().any(|(et, ec)| et == t && ec == c))
        .map(|(t, c)| IntegrityProblem {
            kind: "extra_column".into(),
            detail: format!(
                "table {t}: column {c} is not in the schema and is NOT NULL without a \
                 default, so every insert of this program fails; drop it or give it a default"
            ),
        })
        .collect()
}

/// The CHECK constraints of an SQLite table's stored `CREATE TABLE` text: each `CHECK (…)`
/// outside quotes, with the table's columns it names.
pub(crate) fn sqlite_checks(table: &str, ddl: &str, columns: &[String]) -> Vec<Found> {
    let mut out = Vec::new();
    let bytes: Vec<char> = ddl.chars().collect();
    let mut i = 0;
    let mut quote: Option<char> = None;
    while i < bytes.len() {
        let c = bytes[i];
        if let Some(q) = quote {
            if c == q {
                quote = None;
            }
            i += 1;
            continue;
        }
        if c == '\'' || c == '"' || c == '`' {
            quote = Some(c);
            i += 1;
            continue;
        }
        let word_start = i == 0 || !(bytes[i - 1].is_alphanumeric() || bytes[i - 1] == '_');
        let is_check = word_start
            && bytes.len() >= i + 5
            && bytes[i..i + 5]
                .iter()
                .collect::<String>()
                .eq_ignore_ascii_case("check")
            && bytes
                .get(i + 5)
                .is_none_or(|n| !(n.is_alphanumeric() || *n == '_'));
        if !is_check {
            i += 1;
            continue;
        }
        let mut j = i + 5;
        while j < bytes.len() && bytes[j].is_whitespace() {
            j += 1;
        }
        if bytes.get(j) != Some(&'(') {
            i += 5;
            continue;
        }
        let (expr, end) = balanced(&bytes, j);
        out.push(Found {
            kind: Kind::Check,
            table: table.to_owned(),
            columns: named_columns(&expr, columns),
            references: None,
            definition: format!("CHECK {expr}"),
            valid: true,
        });
        i = end;
    }
    out
}

/// The parenthesised text starting at `open` (quotes respected) and the index after it.
fn balanced(chars: &[char], open: usize) -> (String, usize) {
    let mut depth = 0usize;
    let mut quote: Option<char> = None;
    for (k, &c) in chars.iter().enumerate().skip(open) {
        match (quote, c) {
            (Some(q), c) if c == q => quote = None,
            (Some(_), _) => {}
            (None, '\'' | '"' | '`') => quote = Some(c),
            (None, '(') => depth += 1,
            (None, ')') => {
                depth = depth.saturating_sub(1);
                if depth == 0 {
                    return (chars[open..=k].iter().collect(), k + 1);
                }
            }
            _ => {}
        }
    }
    (chars[open..].iter().collect(), chars.len())
}

/// The columns of `columns` that `expr` names (identifiers outside text literals, quoted
/// identifiers unquoted), each once, in `columns` order.
fn named_columns(expr: &str, columns: &[String]) -> Vec<String> {
    let mut words = Vec::new();
    let mut word = String::new();
    let mut in_text = false;
    for c in expr.chars() {
        if c == '\'' {
            in_text = !in_text;
        }
        if !in_text && (c.is_alphanumeric() || c == '_') {
            word.push(c);
        } else if !word.is_empty() {
            words.push(std::mem::take(&mut word).to_ascii_lowercase());
        }
    }
    if !word.is_empty() {
        words.push(word.to_ascii_lowercase());
    }
    columns
        .iter()
        .filter(|c| words.iter().any(|w| *w == c.to_ascii_lowercase()))
        .cloned()
        .collect()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn literals_and_checks_are_read_from_ddl() {
        assert_eq!(
            text_literals("CHECK ((status = ANY (ARRAY['a''b'::text, 'c'::text])))"),
            ["a'b", "c"]
        );
        let cols: Vec<String> = ["run_id", "status", "config"].map(String::from).into();
        let found = sqlite_checks(
            "runs",
            "CREATE TABLE runs (run_id TEXT, config TEXT DEFAULT 'check (config)', \
             status TEXT NOT NULL CHECK (status IN ('running', 'x)')))",
            &cols,
        );
        assert_eq!(found.len(), 1, "{found:?}");
        assert_eq!(found[0].columns, ["status"]);
        assert_eq!(text_literals(&found[0].definition), ["running", "x)"]);
    }
}
