//! The one definition of the record columns: name, kind and order. Every store builds its
//! schema check, insert, select and export from [`LCC_RECORD_COLUMNS`].

use crate::model::LccRecord;

/// The storage kind of a record column.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ColumnKind {
    /// UTF-8 text, never empty.
    Text,
    /// A finite real number, always present.
    Real,
    /// A finite real number or absent (NULL).
    OptionalReal,
    /// A signed 64-bit integer, always present.
    Integer,
}

/// One column of the `records` table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct LccColumn {
    /// Column name, equal to the [`LccRecord`] field name (units in the name).
    pub name: &'static str,
    /// Storage kind.
    pub kind: ColumnKind,
}

const fn column(name: &'static str, kind: ColumnKind) -> LccColumn {
    LccColumn { name, kind }
}

/// The record columns in storage order (the [`LccRecord`] field order).
pub const LCC_RECORD_COLUMNS: [LccColumn; 27] = [
    column("scanner_id", ColumnKind::Text),
    column("run_id", ColumnKind::Text),
    column("acquired_unix_s", ColumnKind::Real),
    column("repeat_index", ColumnKind::Integer),
    column("node_index", ColumnKind::Integer),
    column("lcs_index", ColumnKind::Integer),
    column("node_x_counts", ColumnKind::Integer),
    column("node_y_counts", ColumnKind::Integer),
    column("node_z_counts", ColumnKind::Integer),
    column("lcs_x_counts", ColumnKind::Real),
    column("lcs_y_counts", ColumnKind::Real),
    column("lcs_z_counts", ColumnKind::Real),
    column("kx_nm_per_count", ColumnKind::Real),
    column("ky_nm_per_count", ColumnKind::Real),
    column("alpha_rad", ColumnKind::Real),
    column("kz_nm_per_count", ColumnKind::OptionalReal),
    column("u_kx_nm_per_count", ColumnKind::OptionalReal),
    column("u_ky_nm_per_count", ColumnKind::OptionalReal),
    column("u_alpha_rad", ColumnKind::OptionalReal),
    column("u_kz_nm_per_count", ColumnKind::OptionalReal),
    column("drift_vx_nm_per_s", ColumnKind::Real),
    column("drift_vy_nm_per_s", ColumnKind::Real),
    column("cycles_kept", ColumnKind::Integer),
    column("cycles_discarded", ColumnKind::Integer),
    column("quality", ColumnKind::Real),
    column("kz_x_counts", ColumnKind::OptionalReal),
    column("kz_y_counts", ColumnKind::OptionalReal),
];

/// Columns that hold a scale factor (nm per count) and must be > 0 when present.
pub const POSITIVE_COLUMNS: [&str; 3] = ["kx_nm_per_count", "ky_nm_per_count", "kz_nm_per_count"];

/// Columns that hold a standard uncertainty and must be ≥ 0 when present.
pub const UNCERTAINTY_COLUMNS: [&str; 4] = [
    "u_kx_nm_per_count",
    "u_ky_nm_per_count",
    "u_alpha_rad",
    "u_kz_nm_per_count",
];

/// A borrowed column value, in [`LCC_RECORD_COLUMNS`] order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ColumnValue<'a> {
    /// [`ColumnKind::Text`].
    Text(&'a str),
    /// [`ColumnKind::Real`].
    Real(f64),
    /// [`ColumnKind::OptionalReal`].
    OptionalReal(Option<f64>),
    /// [`ColumnKind::Integer`].
    Integer(i64),
}

/// An owned column value read back from a store, in [`LCC_RECORD_COLUMNS`] order.
#[derive(Debug, Clone, PartialEq)]
pub enum OwnedColumnValue {
    /// [`ColumnKind::Text`].
    Text(String),
    /// [`ColumnKind::Real`].
    Real(f64),
    /// [`ColumnKind::OptionalReal`].
    OptionalReal(Option<f64>),
    /// [`ColumnKind::Integer`].
    Integer(i64),
}

/// Why a record may not be stored, or why stored values do not make a record.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "record (run {run_id:?}, repeat {repeat_index}, node {node_index}, lcs {lcs_index}): {column}: {message}"
)]
pub struct RecordProblem {
    /// Run of the record.
    pub run_id: String,
    /// Repeat index.
    pub repeat_index: u32,
    /// Node index.
    pub node_index: u32,
    /// LCS index.
    pub lcs_index: u32,
    /// The offending column.
    pub column: &'static str,
    /// What is wrong.
    pub message: String,
}

impl LccRecord {
    /// The record's values in [`LCC_RECORD_COLUMNS`] order (integers widened to `i64`).
    #[must_use]
    pub fn column_values(&self) -> [ColumnValue<'_>; 27] {
        use ColumnValue::{Integer, OptionalReal, Real, Text};
        [
            Text(&self.scanner_id),
            Text(&self.run_id),
            Real(self.acquired_unix_s),
            Integer(i64::from(self.repeat_index)),
            Integer(i64::from(self.node_index)),
            Integer(i64::from(self.lcs_index)),
            Integer(self.node_x_counts),
            Integer(self.node_y_counts),
            Integer(self.node_z_counts),
            Real(self.lcs_x_counts),
            Real(self.lcs_y_counts),
            Real(self.lcs_z_counts),
            Real(self.kx_nm_per_count),
            Real(self.ky_nm_per_count),
            Real(self.alpha_rad),
            OptionalReal(self.kz_nm_per_count),
            OptionalReal(self.u_kx_nm_per_count),
            OptionalReal(self.u_ky_nm_per_count),
            OptionalReal(self.u_alpha_rad),
            OptionalReal(self.u_kz_nm_per_count),
            Real(self.drift_vx_nm_per_s),
            Real(self.drift_vy_nm_per_s),
            Integer(i64::from(self.cycles_kept)),
            Integer(i64::from(self.cycles_discarded)),
            Real(self.quality),
            OptionalReal(self.kz_x_counts),
            OptionalReal(self.kz_y_counts),
        ]
    }

    /// Rebuilds a record from values in [`LCC_RECORD_COLUMNS`] order, as a store reads them.
    ///
    /// # Errors
    /// A [`RecordProblem`] naming the first column whose value has the wrong kind or does not
    /// fit the field (a negative index, say). The values are not otherwise checked; use
    /// [`LccRecord::check`] for that.
    pub fn from_column_values(values: [OwnedColumnValue; 27]) -> Result<Self, RecordProblem> {
        let mut reader = ColumnReader {
            values: values.into_iter(),
            at: 0,
        };
        let scanner_id = reader.text()?;
        let run_id = reader.text()?;
        let acquired_unix_s = reader.real()?;
        let repeat_index = reader.index()?;
        let node_index = reader.index()?;
        let lcs_index = reader.index()?;
        Ok(Self {
            scanner_id,
            run_id,
            acquired_unix_s,
            repeat_index,
            node_index,
            lcs_index,
            node_x_counts: reader.integer()?,
            node_y_counts: reader.integer()?,
            node_z_counts: reader.integer()?,
            lcs_x_counts: reader.real()?,
            lcs_y_counts: reader.real()?,
            lcs_z_counts: reader.real()?,
            kx_nm_per_count: reader.real()?,
            ky_nm_per_count: reader.real()?,
            alpha_rad: reader.real()?,
            kz_nm_per_count: reader.optional_real()?,
            u_kx_nm_per_count: reader.optional_real()?,
            u_ky_nm_per_count: reader.optional_real()?,
            u_alpha_rad: reader.optional_real()?,
            u_kz_nm_per_count: reader.optional_real()?,
            drift_vx_nm_per_s: reader.real()?,
            drift_vy_nm_per_s: reader.real()?,
            cycles_kept: reader.index()?,
            cycles_discarded: reader.index()?,
            quality: reader.real()?,
            kz_x_counts: reader.optional_real()?,
            kz_y_counts: reader.optional_real()?,
        })
    }

    fn problem(&self, column: &'static str, message: String) -> RecordProblem {
        RecordProblem {
            run_id: self.run_id.clone(),
            repeat_index: self.repeat_index,
            node_index: self.node_index,
            lcs_index: self.lcs_index,
            column,
            message,
        }
    }

    /// Checks the record against the rules every store applies before writing: ids not
    /// empty, every real finite, K̄x, K̄y, Kz > 0, |α| < π/2, uncertainties ≥ 0.
    ///
    /// # Errors
    /// A [`RecordProblem`] naming the first offending column.
    pub fn check(&self) -> Result<(), RecordProblem> {
        for (col, value) in LCC_RECORD_COLUMNS.iter().zip(self.column_values()) {
            match value {
                ColumnValue::Text(t) => {
                    if let Some(why) = id_problem(t) {
                        return Err(self.problem(col.name, why));
                    }
                }
                ColumnValue::Real(v) | ColumnValue::OptionalReal(Some(v)) if !v.is_finite() => {
                    return Err(self.problem(col.name, format!("= {v} is not finite")));
                }
                ColumnValue::Real(v) | ColumnValue::OptionalReal(Some(v))
                    if POSITIVE_COLUMNS.contains(&col.name) && v <= 0.0 =>
                {
                    return Err(self.problem(col.name, format!("= {v} must be > 0")));
                }
                ColumnValue::OptionalReal(Some(v))
                    if UNCERTAINTY_COLUMNS.contains(&col.name) && v < 0.0 =>
                {
                    return Err(self.problem(col.name, format!("= {v} must be >= 0")));
                }
                _ => {}
            }
        }
        if self.alpha_rad.abs() >= std::f64::consts::FRAC_PI_2 {
            return Err(self.problem(
                "alpha_rad",
                format!("|alpha_rad| = {} must be < pi/2", self.alpha_rad.abs()),
            ));
        }
        Ok(())
    }
}

/// Unicode format characters (category Cf: bidi controls, zero-width characters, …) and
/// the other invisible code points that make one id look like another or reorder the text
/// around it.
fn is_format_char(c: char) -> bool {
    matches!(
        u32::from(c),
        0x00AD
            | 0x0600..=0x0605
            | 0x061C
            | 0x06DD
            | 0x070F
            | 0x0890..=0x0891
            | 0x08E2
            | 0x180E
            | 0x200B..=0x200F
            | 0x2028..=0x202E
            | 0x2060..=0x206F
            | 0xFEFF
            | 0xFFF9..=0xFFFB
            | 0x110BD
            | 0x110CD
            | 0x13430..=0x1343F
            | 0x1BCA0..=0x1BCA3
            | 0x1D173..=0x1D17A
            | 0xE0001
            | 0xE0020..=0xE007F
    )
}

/// Why `id` (a scanner or run id) cannot be stored, or `None` when it can: an id is not
/// blank and holds no control character and no format character (bidi overrides and
/// isolates, zero-width characters: issue 25, they make ids look alike and reorder the
/// text around them in reports and exports).
#[must_use]
pub fn id_problem(id: &str) -> Option<String> {
    if id.trim().is_empty() {
        return Some("is empty".into());
    }
    let bad = id.chars().find(|&c| c.is_control() || is_format_char(c))?;
    Some(format!(
        "{id:?} holds the control or format character U+{:04X}; ids must be visible text",
        u32::from(bad)
    ))
}

struct ColumnReader {
    values: std::array::IntoIter<OwnedColumnValue, 27>,
    at: usize,
}

impl ColumnReader {
    fn next(&mut self) -> (&'static str, Option<OwnedColumnValue>) {
        let name = LCC_RECORD_COLUMNS.get(self.at).map_or("?", |c| c.name);
        self.at += 1;
        (name, self.values.next())
    }
    fn wrong(name: &'static str, want: &str, got: Option<OwnedColumnValue>) -> RecordProblem {
        RecordProblem {
            run_id: String::new(),
            repeat_index: 0,
            node_index: 0,
            lcs_index: 0,
            column: name,
            message: format!("expected {want}, found {got:?}"),
        }
    }
    fn text(&mut self) -> Result<String, RecordProblem> {
        match self.next() {
            (_, Some(OwnedColumnValue::Text(t))) => Ok(t),
            (name, got) => Err(Self::wrong(name, "text", got)),
        }
    }
    fn real(&mut self) -> Result<f64, RecordProblem> {
        match self.next() {
            (_, Some(OwnedColumnValue::Real(v) | OwnedColumnValue::OptionalReal(Some(v)))) => Ok(v),
            (name, got) => Err(Self::wrong(name, "a real number", got)),
        }
    }
    fn optional_real(&mut self) -> Result<Option<f64>, RecordProblem> {
        match self.next() {
            (_, Some(OwnedColumnValue::OptionalReal(v))) => Ok(v),
            (_, Some(OwnedColumnValue::Real(v))) => Ok(Some(v)),
            (name, got) => Err(Self::wrong(name, "a real number or NULL", got)),
        }
    }
    fn integer(&mut self) -> Result<i64, RecordProblem> {
        match self.next() {
            (_, Some(OwnedColumnValue::Integer(v))) => Ok(v),
            (name, got) => Err(Self::wrong(name, "an integer", got)),
        }
    }
    fn index(&mut self) -> Result<u32, RecordProblem> {
        match self.next() {
            (name, Some(OwnedColumnValue::Integer(v))) => u32::try_from(v).map_err(|_| {
                Self::wrong(
                    name,
                    "an integer in 0..=4294967295",
                    Some(OwnedColumnValue::Integer(v)),
                )
            }),
            (name, got) => Err(Self::wrong(name, "an integer", got)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn record(kx: f64, alpha: f64, kz: Option<f64>, u_kx: Option<f64>) -> LccRecord {
        LccRecord {
            scanner_id: "s".into(),
            run_id: "r".into(),
            acquired_unix_s: 1.7e9,
            repeat_index: 1,
            node_index: 2,
            lcs_index: 0,
            node_x_counts: -5,
            node_y_counts: 7,
            node_z_counts: 0,
            lcs_x_counts: -4.5,
            lcs_y_counts: 7.25,
            lcs_z_counts: 0.5,
            kx_nm_per_count: kx,
            ky_nm_per_count: 0.02,
            alpha_rad: alpha,
            kz_nm_per_count: kz,
            u_kx_nm_per_count: u_kx,
            u_ky_nm_per_count: None,
            u_alpha_rad: None,
            u_kz_nm_per_count: None,
            drift_vx_nm_per_s: 0.01,
            drift_vy_nm_per_s: -0.02,
            cycles_kept: 5,
            cycles_discarded: 1,
            quality: 0.9,
            kz_x_counts: None,
            kz_y_counts: None,
        }
    }

    fn owned(r: &LccRecord) -> [OwnedColumnValue; 27] {
        r.column_values().map(|v| match v {
            ColumnValue::Text(t) => OwnedColumnValue::Text(t.to_owned()),
            ColumnValue::Real(v) => OwnedColumnValue::Real(v),
            ColumnValue::OptionalReal(v) => OwnedColumnValue::OptionalReal(v),
            ColumnValue::Integer(v) => OwnedColumnValue::Integer(v),
        })
    }

    /// The column list names every field of the record exactly once, in declaration order:
    /// the serde field order of `LccRecord` is the independent truth.
    #[test]
    fn columns_are_the_record_fields_in_order() {
        let r = record(0.02, 0.01, Some(0.1), Some(1e-5));
        let json = serde_json_like_field_order(&r);
        let names: Vec<&str> = LCC_RECORD_COLUMNS.iter().map(|c| c.name).collect();
        assert_eq!(names, json);
        for (c, v) in LCC_RECORD_COLUMNS.iter().zip(r.column_values()) {
            let kind = match v {
                ColumnValue::Text(_) => ColumnKind::Text,
                ColumnValue::Real(_) => ColumnKind::Real,
                ColumnValue::OptionalReal(_) => ColumnKind::OptionalReal,
                ColumnValue::Integer(_) => ColumnKind::Integer,
            };
            assert_eq!(c.kind, kind, "{}", c.name);
        }
    }

    /// Field names in declaration order, from the derived `Serialize` (serde_json writes the
    /// fields in declaration order).
    fn serde_json_like_field_order(r: &LccRecord) -> Vec<&'static str> {
        let text = serde_json::to_string(r).expect("LccRecord serializes");
        let mut found: Vec<(usize, &'static str)> = LCC_RECORD_COLUMNS
            .iter()
            .filter_map(|c| {
                text.find(&format!("\"{}\":", c.name))
                    .map(|at| (at, c.name))
            })
            .collect();
        found.sort_unstable();
        let keys = text.matches("\":").count();
        assert_eq!(
            keys,
            found.len(),
            "every serialized field is a column: {text}"
        );
        found.into_iter().map(|(_, n)| n).collect()
    }

    fn check(r: LccRecord, expected_column: Option<&str>) {
        match (r.check(), expected_column) {
            (Ok(()), None) => {}
            (Err(p), Some(col)) => assert_eq!(p.column, col, "{p}"),
            (got, want) => panic!("check() = {got:?}, expected problem in {want:?}"),
        }
    }

    #[test]
    fn check_names_the_offending_column() {
        check(record(0.02, 0.01, None, None), None);
        check(record(0.0, 0.01, None, None), Some("kx_nm_per_count"));
        check(record(f64::NAN, 0.01, None, None), Some("kx_nm_per_count"));
        check(record(0.02, 1.6, None, None), Some("alpha_rad"));
        check(record(0.02, 0.0, Some(-1.0), None), Some("kz_nm_per_count"));
        check(
            record(0.02, 0.0, None, Some(-1e-6)),
            Some("u_kx_nm_per_count"),
        );
        check(
            record(0.02, 0.0, None, Some(f64::INFINITY)),
            Some("u_kx_nm_per_count"),
        );
        let mut r = record(0.02, 0.0, None, None);
        r.scanner_id = " ".into();
        check(r, Some("scanner_id"));
    }

    #[test]
    fn wrong_kinds_are_named() {
        let r = record(0.02, 0.01, None, None);
        let mut v = owned(&r);
        v[4] = OwnedColumnValue::Integer(-1);
        let p = LccRecord::from_column_values(v).expect_err("negative node index");
        assert_eq!(p.column, "node_index");
        let mut v = owned(&r);
        v[12] = OwnedColumnValue::Text("x".into());
        let p = LccRecord::from_column_values(v).expect_err("text for a real");
        assert_eq!(p.column, "kx_nm_per_count");
    }

    proptest! {
        #[test]
        fn column_values_round_trip(
            kx in 1e-6f64..1.0, alpha in -1.5f64..1.5,
            kz in proptest::option::of(1e-6f64..1.0), u in proptest::option::of(0.0f64..1.0),
            node in 0u32..u32::MAX, x in i64::MIN..i64::MAX,
        ) {
            let mut r = record(kx, alpha, kz, u);
            r.node_index = node;
            r.node_x_counts = x;
            let back = LccRecord::from_column_values(owned(&r)).expect("own values read back");
            prop_assert_eq!(back, r);
        }
    }
}
