//! The pure arithmetic between a FOS report and the node machine's events: the covariance of
//! a skipped vector and the drift-free vectors of a counter-scan. No instrument, no state:
//! the runner calls these and only moves data.

use crate::lcc::CountCovariance;
use crate::machine::{Anchor, CounterResult, vector_covariance};
use spm_fos::{CounterScanReport, SkipReport};
use spm_hal::{CountPoint, CountVector, Counts};

/// Localisation variance of one feature sighting, per component, counts².
fn variance(f: &spm_features::Feature) -> (f64, f64) {
    (
        f.uncertainty.sigma_x.value().powi(2),
        f.uncertainty.sigma_y.value().powi(2),
    )
}

/// The covariance of a skipped vector (the mean over the kept cycles): the larger, per
/// component, of the cycles' scatter (`report.sigma`) and the localisation uncertainty of
/// one cycle's vector, σ_B² + ½(σ_A,start² + σ_A,end²), divided by the number of cycles.
#[must_use]
pub fn skip_vector_covariance(report: &SkipReport) -> CountCovariance {
    let (mut lx, mut ly, mut n) = (0.0, 0.0, 0usize);
    for c in report.kept.iter().filter_map(|&i| report.cycles.get(i)) {
        let (bx, by) = variance(&c.cycle.b.feature);
        let (sx, sy) = variance(&c.cycle.a_start.feature);
        let (ex, ey) = variance(&c.cycle.a_end.feature);
        lx += bx + 0.5 * (sx + ex);
        ly += by + 0.5 * (sy + ey);
        n += 1;
    }
    let n_f = n.max(1) as f64;
    let local = CountVector::new(Counts((lx / n_f).sqrt()), Counts((ly / n_f).sqrt()));
    vector_covariance(report.sigma, local, n)
}

/// The counter-scan's result for the node machine: A is the common feature nearest `target`
/// (drift-free), the vectors run from A to every other common feature, each with the
/// covariance ½(σ_A² + σ_N²) per component (the two direct sightings' localisation; the
/// drift is common to both ends). `None` when no feature is common to both frames.
#[must_use]
pub fn counter_scan_vectors(
    report: &CounterScanReport,
    target: CountPoint,
) -> Option<CounterResult> {
    let a = report.common.iter().min_by(|x, y| {
        x.drift_free
            .distance(target)
            .value()
            .total_cmp(&y.drift_free.distance(target).value())
    })?;
    let (ax, ay) = variance(&a.direct);
    let vectors = report
        .common
        .iter()
        .filter(|c| c.drift_free != a.drift_free)
        .map(|c| {
            let (nx, ny) = variance(&c.direct);
            (
                c.drift_free - a.drift_free,
                CountCovariance {
                    xx_counts2: 0.5 * (ax + nx),
                    xy_counts2: 0.0,
                    yy_counts2: 0.5 * (ay + ny),
                },
            )
        })
        .collect();
    Some(CounterResult {
        a: Anchor {
            position: a.drift_free,
            time: Some(report.reference_time),
        },
        vectors,
        drift: report.velocity,
    })
}
