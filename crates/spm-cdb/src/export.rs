//! CSV and JSON export.

use std::io::Write;
use std::path::Path;

use crate::error::{CdbError, Result};
use crate::query::RecordSource;
use crate::schema::SCHEMA_VERSION;
use spm_records::{DynamicsRecord, LccRecord, RecordFilter};

/// CSV header: `acquired_utc` (RFC 3339) then the record columns
/// ([`spm_records::LCC_RECORD_COLUMNS`]) in order.
pub static CSV_HEADER: std::sync::LazyLock<String> = std::sync::LazyLock::new(|| {
    let mut h = String::from("acquired_utc");
    for c in spm_records::LCC_RECORD_COLUMNS {
        h.push(',');
        h.push_str(c.name);
    }
    h
});

/// RFC 3339 UTC text of a Unix time (millisecond precision is kept as given by `time`).
#[must_use]
pub fn rfc3339_utc(t_unix_s: f64) -> String {
    let nanos = (t_unix_s * 1e9).round();
    if !(nanos.is_finite() && nanos.abs() < 1e27) {
        return String::new();
    }
    time::OffsetDateTime::from_unix_timestamp_nanos(nanos as i128)
        .ok()
        .and_then(|t| {
            t.format(&time::format_description::well_known::Rfc3339)
                .ok()
        })
        .unwrap_or_default()
}

/// A text field: always quoted, and a leading `=`, `+`, `-`, `@`, tab or carriage return
/// (what a spreadsheet reads as a formula) neutralised with a leading `'` (OWASP CSV
/// injection; issue 25). Numbers are written as numbers and never start a formula.
fn csv_text(s: &str) -> String {
    let neutral = if s.starts_with(['=', '+', '-', '@', '\t', '\r']) {
        "'"
    } else {
        ""
    };
    format!("\"{neutral}{}\"", s.replace('"', "\"\""))
}

fn csv_line(r: &LccRecord) -> String {
    use spm_records::ColumnValue;
    let mut line = rfc3339_utc(r.acquired_unix_s);
    for v in r.column_values() {
        line.push(',');
        match v {
            ColumnValue::Text(t) => line.push_str(&csv_text(t)),
            ColumnValue::Real(v) | ColumnValue::OptionalReal(Some(v)) => {
                line.push_str(&v.to_string());
            }
            ColumnValue::OptionalReal(None) => {}
            ColumnValue::Integer(v) => line.push_str(&v.to_string()),
        }
    }
    line.push('\n');
    line
}

fn io(path: &Path, context: &str) -> impl Fn(std::io::Error) -> CdbError {
    let path = path.to_path_buf();
    let context = context.to_owned();
    move |source| CdbError::Io {
        path: path.clone(),
        context: context.clone(),
        source,
    }
}

pub(crate) fn csv(path: &Path, source: &mut RecordSource<'_>, out: &mut dyn Write) -> Result<u64> {
    let e = io(path, "writing CSV export");
    out.write_all(CSV_HEADER.as_bytes()).map_err(&e)?;
    out.write_all(b"\n").map_err(&e)?;
    let mut n = 0;
    source(&mut |r| {
        n += 1;
        out.write_all(csv_line(&r).as_bytes()).map_err(&e)
    })?;
    out.flush().map_err(&e)?;
    Ok(n)
}

/// The dynamics a record filter selects: its scanner (already applied by the query), run
/// and time window (on `identified_unix_s`); the Z plane does not apply.
pub(crate) fn select_dynamics(
    mut dynamics: Vec<DynamicsRecord>,
    filter: &RecordFilter,
) -> Vec<DynamicsRecord> {
    dynamics.retain(|d| {
        filter
            .scanner_id
            .as_ref()
            .is_none_or(|s| *s == d.scanner_id)
            && filter.run_id.as_ref().is_none_or(|r| *r == d.run_id)
            && filter.since_unix_s.is_none_or(|t| d.identified_unix_s >= t)
            && filter.until_unix_s.is_none_or(|t| d.identified_unix_s <= t)
    });
    dynamics
}

pub(crate) fn json(
    path: &Path,
    source: &mut RecordSource<'_>,
    dynamics: &[DynamicsRecord],
    out: &mut dyn Write,
) -> Result<u64> {
    let e = io(path, "writing JSON export");
    write!(out, "{{\"schema_version\":{SCHEMA_VERSION},\"records\":[").map_err(&e)?;
    let mut n = 0u64;
    source(&mut |r| {
        if n > 0 {
            out.write_all(b",\n").map_err(&e)?;
        } else {
            out.write_all(b"\n").map_err(&e)?;
        }
        n += 1;
        serde_json::to_writer(&mut *out, &r).map_err(|err| CdbError::Io {
            path: path.to_path_buf(),
            context: "writing JSON export".into(),
            source: std::io::Error::other(err),
        })
    })?;
    out.write_all(b"\n],\"dynamics\":[").map_err(&e)?;
    for (k, d) in dynamics.iter().enumerate() {
        out.write_all(if k > 0 { b",\n" } else { b"\n" })
            .map_err(&e)?;
        serde_json::to_writer(&mut *out, d).map_err(|err| CdbError::Io {
            path: path.to_path_buf(),
            context: "writing JSON export".into(),
            source: std::io::Error::other(err),
        })?;
    }
    out.write_all(b"\n]}\n").map_err(&e)?;
    out.flush().map_err(&e)?;
    Ok(n)
}
