//! CSV and JSON export.

use rusqlite::Connection;
use std::io::Write;
use std::path::Path;

use crate::error::{CdbError, Result};
use crate::model::{LccRecord, RecordFilter};
use crate::query::for_each_record;
use crate::schema::SCHEMA_VERSION;

/// CSV header: `acquired_utc` (RFC 3339) then the record fields in declaration order.
pub const CSV_HEADER: &str = "acquired_utc,scanner_id,run_id,acquired_unix_s,repeat_index,\
node_index,lcs_index,node_x_counts,node_y_counts,node_z_counts,lcs_x_counts,lcs_y_counts,\
lcs_z_counts,kx_nm_per_count,ky_nm_per_count,alpha_rad,kz_nm_per_count,u_kx_nm_per_count,\
u_ky_nm_per_count,u_alpha_rad,u_kz_nm_per_count,drift_vx_nm_per_s,drift_vy_nm_per_s,\
cycles_kept,cycles_discarded,quality";

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

fn csv_text(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_owned()
    }
}

fn opt(v: Option<f64>) -> String {
    v.map(|v| v.to_string()).unwrap_or_default()
}

fn csv_line(r: &LccRecord) -> String {
    format!(
        "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
        rfc3339_utc(r.acquired_unix_s),
        csv_text(&r.scanner_id),
        csv_text(&r.run_id),
        r.acquired_unix_s,
        r.repeat_index,
        r.node_index,
        r.lcs_index,
        r.node_x_counts,
        r.node_y_counts,
        r.node_z_counts,
        r.lcs_x_counts,
        r.lcs_y_counts,
        r.lcs_z_counts,
        r.kx_nm_per_count,
        r.ky_nm_per_count,
        r.alpha_rad,
        opt(r.kz_nm_per_count),
        opt(r.u_kx_nm_per_count),
        opt(r.u_ky_nm_per_count),
        opt(r.u_alpha_rad),
        opt(r.u_kz_nm_per_count),
        r.drift_vx_nm_per_s,
        r.drift_vy_nm_per_s,
        r.cycles_kept,
        r.cycles_discarded,
        r.quality
    )
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

pub(crate) fn csv(
    conn: &Connection,
    path: &Path,
    filter: &RecordFilter,
    out: &mut dyn Write,
) -> Result<u64> {
    let e = io(path, "writing CSV export");
    out.write_all(CSV_HEADER.as_bytes()).map_err(&e)?;
    out.write_all(b"\n").map_err(&e)?;
    let mut n = 0;
    for_each_record(conn, path, filter, |r| {
        n += 1;
        out.write_all(csv_line(&r).as_bytes()).map_err(&e)
    })?;
    out.flush().map_err(&e)?;
    Ok(n)
}

pub(crate) fn json(
    conn: &Connection,
    path: &Path,
    filter: &RecordFilter,
    out: &mut dyn Write,
) -> Result<u64> {
    let e = io(path, "writing JSON export");
    write!(out, "{{\"schema_version\":{SCHEMA_VERSION},\"records\":[").map_err(&e)?;
    let mut n = 0u64;
    for_each_record(conn, path, filter, |r| {
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
    out.write_all(b"\n]}\n").map_err(&e)?;
    out.flush().map_err(&e)?;
    Ok(n)
}
