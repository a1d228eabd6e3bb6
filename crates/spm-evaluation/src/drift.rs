//! The drift-insensitivity experiment's figures (`cargo xtask bench`, section drift): the
//! relative error of a lattice vector measured by skipping, counter-scanning or a single scan
//! against the true vector, the true atom site under a feature of an ideal scanner, the
//! nearest-neighbour pairs of a counter-scanned frame, and the RMS summary per drift velocity.
//! xtask runs the scans and prints; the arithmetic is here.

use serde::Serialize;
use spm_hal::{CountPoint, CountVector, NmPoint};

/// One drift velocity of the sweep.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DriftPoint {
    /// Drift speed, Å/s (along the diagonal).
    pub velocity_angstrom_per_s: f64,
    /// RMS relative A→B vector error of skipping, %.
    pub skipping_pct: f64,
    /// RMS relative vector error of counter-scanning (drift-free positions of
    /// nearest-neighbour pairs seen in both frames), %.
    pub counter_scan_pct: f64,
    /// RMS relative A→B vector error of a single aperture scan, %.
    pub single_scan_pct: f64,
    /// Runs that completed (of the seeds tried).
    pub runs: usize,
}

impl DriftPoint {
    /// The RMS of each method's relative errors (%) at one velocity ([`spm_regression::rms`];
    /// NaN, a table cell without data, when a method has none); `runs` is the number of
    /// completed skipping runs.
    #[must_use]
    pub fn from_errors(
        velocity_angstrom_per_s: f64,
        skipping_pct: &[f64],
        counter_scan_pct: &[f64],
        single_scan_pct: &[f64],
    ) -> Self {
        let rms = |v: &[f64]| spm_regression::rms(v).unwrap_or(f64::NAN);
        Self {
            velocity_angstrom_per_s,
            skipping_pct: rms(skipping_pct),
            counter_scan_pct: rms(counter_scan_pct),
            single_scan_pct: rms(single_scan_pct),
            runs: skipping_pct.len(),
        }
    }
}

/// The drift section.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DriftResults {
    /// Seeds per velocity.
    pub seeds: usize,
    /// The sweep.
    pub points: Vec<DriftPoint>,
    /// single-scan error ÷ skipping error at the fastest drift.
    pub single_over_skipping_at_max: f64,
    /// skipping error at the fastest drift ÷ at rest.
    pub skipping_fast_over_rest: f64,
}

impl DriftResults {
    /// The sweep with its two ratios (the sweep's last point is the fastest drift, its first
    /// the slowest); `None` for an empty sweep.
    #[must_use]
    pub fn from_points(seeds: usize, points: Vec<DriftPoint>) -> Option<Self> {
        let (first, last) = (points.first()?, points.last()?);
        Some(Self {
            seeds,
            single_over_skipping_at_max: last.single_scan_pct / last.skipping_pct,
            skipping_fast_over_rest: last.skipping_pct / first.skipping_pct,
            points,
        })
    }
}

/// |measured − truth| / |truth| in %; `None` for a zero true vector.
#[must_use]
pub fn relative_error_pct(measured: CountVector, truth: CountVector) -> Option<f64> {
    let length = truth.norm().value();
    (length > 0.0).then(|| (measured - truth).norm().value() / length * 100.0)
}

/// Where an ideal scanner (F(u) = K·u, `sensitivity_nm_per_count` = K) sees a feature found
/// at `position` while the sample has drifted by `drift_displacement`: K·u + d.
#[must_use]
pub fn ideal_scanner_site(
    position: CountPoint,
    sensitivity_nm_per_count: f64,
    drift_displacement: NmPoint,
) -> NmPoint {
    NmPoint::from_nm(
        sensitivity_nm_per_count * position.x.value() + drift_displacement.x.value(),
        sensitivity_nm_per_count * position.y.value() + drift_displacement.y.value(),
    )
}

/// The vector between two true sites in counts of an ideal scanner of sensitivity
/// `sensitivity_nm_per_count`.
#[must_use]
pub fn site_vector_counts(a: NmPoint, b: NmPoint, sensitivity_nm_per_count: f64) -> CountVector {
    CountVector::from_counts(
        (b.x - a.x).value() / sensitivity_nm_per_count,
        (b.y - a.y).value() / sensitivity_nm_per_count,
    )
}

/// Relative errors (%) of the nearest-neighbour vectors of a counter-scanned frame: every pair
/// of drift-free positions whose distance is within `tolerance_fraction` of the lattice
/// constant `lattice_counts`, against `truth` of the pair (pairs without a truth are skipped).
pub fn nearest_neighbour_errors_pct<T>(
    points: &[(CountPoint, T)],
    lattice_counts: f64,
    tolerance_fraction: f64,
    truth: impl Fn(&T, &T) -> Option<CountVector>,
) -> Vec<f64> {
    let mut errors = Vec::new();
    for (i, (p, p_id)) in points.iter().enumerate() {
        for (q, q_id) in &points[i + 1..] {
            let measured = *q - *p;
            if (measured.norm().value() - lattice_counts).abs()
                > tolerance_fraction * lattice_counts
            {
                continue;
            }
            if let Some(error) = truth(p_id, q_id).and_then(|t| relative_error_pct(measured, t)) {
                errors.push(error);
            }
        }
    }
    errors
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// A 3-4-5 triangle: an error of (3, 4) counts on a true vector of 50 counts is 10 %.
    #[test]
    fn relative_errors_are_in_percent_of_the_true_length() {
        let truth = CountVector::from_counts(30.0, 40.0);
        let measured = CountVector::from_counts(33.0, 44.0);
        assert!((relative_error_pct(measured, truth).unwrap() - 10.0).abs() < 1e-12);
        assert_eq!(
            relative_error_pct(measured, CountVector::from_counts(0.0, 0.0)),
            None
        );
    }

    /// K·u + d, and back: the vector between two sites in counts is their difference / K.
    #[test]
    fn the_ideal_scanner_maps_counts_to_sites_and_back() {
        let site = ideal_scanner_site(
            CountPoint::from_counts(100.0, -50.0),
            0.02,
            NmPoint::from_nm(0.5, 0.25),
        );
        assert!((site.x.value() - 2.5).abs() < 1e-12 && (site.y.value() + 0.75).abs() < 1e-12);
        let v = site_vector_counts(NmPoint::from_nm(0.0, 0.0), site, 0.02);
        assert!((v.x.value() - 125.0).abs() < 1e-9 && (v.y.value() + 37.5).abs() < 1e-9);
    }

    /// Three points: only the pair at the lattice constant counts; its error against a truth
    /// 1 % longer is 1/1.01 %.
    #[test]
    fn only_nearest_neighbour_pairs_are_judged() {
        let points = vec![
            (CountPoint::from_counts(0.0, 0.0), 0),
            (CountPoint::from_counts(10.0, 0.0), 1),
            (CountPoint::from_counts(30.0, 0.0), 2),
        ];
        let errors = nearest_neighbour_errors_pct(&points, 10.0, 0.3, |a, b| {
            Some(CountVector::from_counts(10.1 * f64::from(b - a), 0.0))
        });
        assert_eq!(errors.len(), 1);
        assert!((errors[0] - 0.1 / 10.1 * 100.0).abs() < 1e-9);
    }

    /// RMS per method (NaN without data) and the sweep's two ratios.
    #[test]
    fn the_sweep_summary_is_rms_and_ratios() {
        let slow = DriftPoint::from_errors(0.0, &[3.0, 4.0], &[], &[1.0]);
        assert!((slow.skipping_pct - 12.5_f64.sqrt()).abs() < 1e-12);
        assert!(slow.counter_scan_pct.is_nan() && slow.runs == 2);
        let fast = DriftPoint::from_errors(0.4, &[2.0 * 12.5_f64.sqrt()], &[1.0], &[10.0]);
        let results = DriftResults::from_points(3, vec![slow, fast]).unwrap();
        assert!((results.skipping_fast_over_rest - 2.0).abs() < 1e-12);
        assert!(
            (results.single_over_skipping_at_max - 10.0 / (2.0 * 12.5_f64.sqrt())).abs() < 1e-12
        );
        assert_eq!(DriftResults::from_points(3, Vec::new()), None);
    }
}
