//! Age dynamics of the coefficients (`CdbRead::age_dynamics`), computed from the records
//! a back end streams: the same on both (the SQL is in `crate::sql`).

use std::collections::BTreeMap;

use crate::error::Result;
use spm_records::{Coefficient, CoefficientStat, LccRecord, TrendGrouping, TrendPoint};

/// Welford accumulator.
#[derive(Default)]
struct Acc {
    n: u64,
    mean: f64,
    m2: f64,
}

impl Acc {
    fn push(&mut self, v: f64) {
        self.n += 1;
        let d = v - self.mean;
        self.mean += d / self.n as f64;
        self.m2 += d * (v - self.mean);
    }
    fn stat(&self) -> Option<CoefficientStat> {
        if self.n == 0 {
            return None;
        }
        let std_dev = if self.n > 1 {
            (self.m2 / (self.n - 1) as f64).max(0.0).sqrt()
        } else {
            0.0
        };
        Some(CoefficientStat {
            n: self.n,
            mean: self.mean,
            std_dev,
            std_uncertainty: std_dev / (self.n as f64).sqrt(),
        })
    }
}

struct Group {
    time: Acc,
    first: f64,
    last: f64,
    value: Acc,
}

/// UTC calendar day of a Unix time, `YYYY-MM-DD`.
pub(crate) fn utc_day(t_unix_s: f64) -> String {
    let days = (t_unix_s / 86_400.0).floor();
    let secs = days * 86_400.0;
    // Range-checked conversion: out-of-range times get a placeholder, never a panic.
    if !(secs.is_finite() && secs.abs() < 1e14) {
        return "invalid-date".into();
    }
    match time::OffsetDateTime::from_unix_timestamp(secs as i64) {
        Ok(t) => format!("{:04}-{:02}-{:02}", t.year(), u8::from(t.month()), t.day()),
        Err(_) => "invalid-date".into(),
    }
}

/// Streams the selected records of a back end into a callback (`CdbRead::for_each_record`
/// with its filter bound).
pub(crate) type RecordSource<'s> =
    dyn FnMut(&mut dyn FnMut(LccRecord) -> Result<()>) -> Result<()> + 's;

pub(crate) fn age_dynamics(
    source: &mut RecordSource<'_>,
    coefficient: Coefficient,
    grouping: TrendGrouping,
) -> Result<Vec<TrendPoint>> {
    let mut groups: BTreeMap<String, Group> = BTreeMap::new();
    let mut order: Vec<String> = Vec::new();
    source(&mut |r| {
        let key = match grouping {
            TrendGrouping::PerRun => r.run_id.clone(),
            TrendGrouping::PerDay => utc_day(r.acquired_unix_s),
            TrendGrouping::PerNodePerRun => format!(
                "{},{},{}@{}",
                r.node_x_counts, r.node_y_counts, r.node_z_counts, r.run_id
            ),
        };
        let value = match coefficient {
            Coefficient::KxNmPerCount => Some(r.kx_nm_per_count),
            Coefficient::KyNmPerCount => Some(r.ky_nm_per_count),
            Coefficient::AlphaRad => Some(r.alpha_rad),
            Coefficient::KzNmPerCount => r.kz_nm_per_count,
        };
        let g = groups.entry(key.clone()).or_insert_with(|| {
            order.push(key);
            Group {
                time: Acc::default(),
                first: r.acquired_unix_s,
                last: r.acquired_unix_s,
                value: Acc::default(),
            }
        });
        g.time.push(r.acquired_unix_s);
        g.first = g.first.min(r.acquired_unix_s);
        g.last = g.last.max(r.acquired_unix_s);
        if let Some(v) = value {
            g.value.push(v);
        }
        Ok(())
    })?;
    let mut out: Vec<TrendPoint> = order
        .into_iter()
        .filter_map(|k| {
            groups.remove(&k).map(|g| TrendPoint {
                key: k,
                mean_unix_s: g.time.mean,
                first_unix_s: g.first,
                last_unix_s: g.last,
                stat: g.value.stat(),
            })
        })
        .collect();
    out.sort_by(|a, b| {
        a.mean_unix_s
            .total_cmp(&b.mean_unix_s)
            .then_with(|| a.key.cmp(&b.key))
    });
    Ok(out)
}
