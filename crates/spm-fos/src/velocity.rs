//! Drift velocity from positions and times.

use spm_hal::{CountPoint, CountVelocity, Seconds};

/// Least-squares velocity (slope of position against time) of a track, or
/// `None` with fewer than two distinct times.
pub fn fit_velocity(
    track: impl IntoIterator<Item = (Seconds, CountPoint)>,
) -> Option<CountVelocity> {
    let points: Vec<(f64, f64, f64)> = track
        .into_iter()
        .map(|(t, p)| (t.value(), p.x.value(), p.y.value()))
        .collect();
    let n = points.len() as f64;
    if points.len() < 2 {
        return None;
    }
    let mean_t = points.iter().map(|p| p.0).sum::<f64>() / n;
    let mean_x = points.iter().map(|p| p.1).sum::<f64>() / n;
    let mean_y = points.iter().map(|p| p.2).sum::<f64>() / n;
    let stt: f64 = points.iter().map(|p| (p.0 - mean_t).powi(2)).sum();
    if !(stt > 0.0 && stt.is_finite()) {
        return None;
    }
    let stx: f64 = points.iter().map(|p| (p.0 - mean_t) * (p.1 - mean_x)).sum();
    let sty: f64 = points.iter().map(|p| (p.0 - mean_t) * (p.2 - mean_y)).sum();
    Some(CountVelocity {
        x_counts_per_s: stx / stt,
        y_counts_per_s: sty / stt,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn slope_of_a_straight_track() {
        let track = (0..4).map(|i| {
            let t = f64::from(i) * 0.5;
            (Seconds(t), CountPoint::from_counts(1.0 + 2.0 * t, -3.0 * t))
        });
        let v = fit_velocity(track).unwrap();
        assert!((v.x_counts_per_s - 2.0).abs() < 1e-12);
        assert!((v.y_counts_per_s + 3.0).abs() < 1e-12);
        assert!(fit_velocity([(Seconds(1.0), CountPoint::default())]).is_none());
        assert!(
            fit_velocity([
                (Seconds(1.0), CountPoint::default()),
                (Seconds(1.0), CountPoint::default())
            ])
            .is_none()
        );
    }
}
