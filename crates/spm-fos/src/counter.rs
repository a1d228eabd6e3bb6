//! Counter-scanning (Lapshin 2007): a direct and a counter scan of the same
//! region; every feature common to both gives the drift, and the drift gives
//! drift-free positions.

use crate::acquire::{Motion, Raster, scan_and_recognise};
use crate::error::{FosError, positive};
use serde::{Deserialize, Serialize};
use spm_features::{DetectionConfig, Feature};
use spm_hal::{CountPoint, CountVelocity, Microscope, ScanDirection, Seconds};

/// Settings of [`counter_scan`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CounterScanParams {
    /// The raster of both scans.
    pub raster: Raster,
    /// Recognition settings.
    pub detection: DetectionConfig,
    /// Probe moves.
    pub motion: Motion,
    /// A direct and a counter feature are the same when, after shifting by
    /// the prior drift, they are closer than this, counts. Set it below half
    /// the feature spacing.
    pub match_radius_counts: f64,
    /// The drift known beforehand (e.g. from the attachment), used to pair
    /// features; zero when unknown.
    pub drift_prior: CountVelocity,
}

/// One feature seen in both frames.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CommonFeature {
    /// Its sighting in the direct frame.
    pub direct: Feature,
    /// Its sighting in the counter frame.
    pub counter: Feature,
    /// Its drift-free position at the report's reference time, counts.
    pub drift_free: CountPoint,
}

/// The result of a counter-scan.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CounterScanReport {
    /// The drift velocity (apparent motion of the surface in scanner
    /// counts), counts per second.
    pub velocity: CountVelocity,
    /// Its one-sigma uncertainty per component, counts per second.
    pub velocity_sigma: CountVelocity,
    /// The time to which drift-free positions refer (the earliest direct sighting).
    pub reference_time: Seconds,
    /// The common features.
    pub common: Vec<CommonFeature>,
}

/// Pairs direct and counter features and solves for a common drift velocity
/// (least squares over all pairs: `p_counter − p_direct = v·(t_counter − t_direct)`)
/// and the drift-free positions. `None` without a common feature.
pub fn solve_counter_scan(
    direct: &[Feature],
    counter: &[Feature],
    drift_prior: CountVelocity,
    match_radius_counts: f64,
) -> Option<CounterScanReport> {
    let mut pairs: Vec<(Feature, Feature)> = Vec::new();
    for d in direct {
        let best = counter
            .iter()
            .map(|c| {
                let expected = d.position + drift_prior.displacement(c.time - d.time);
                (c, c.position.distance(expected).value())
            })
            .filter(|(_, dist)| *dist <= match_radius_counts)
            .min_by(|a, b| a.1.total_cmp(&b.1));
        if let Some((c, _)) = best {
            pairs.push((*d, *c));
        }
    }
    let (mut stt, mut stx, mut sty) = (0.0, 0.0, 0.0);
    for (d, c) in &pairs {
        let dt = (c.time - d.time).value();
        stt += dt * dt;
        stx += dt * (c.position.x - d.position.x).value();
        sty += dt * (c.position.y - d.position.y).value();
    }
    if stt.is_nan() || stt <= 0.0 {
        return None;
    }
    let velocity = CountVelocity {
        x_counts_per_s: stx / stt,
        y_counts_per_s: sty / stt,
    };
    // Uncertainty: from the residual scatter with several pairs, from the
    // localisation uncertainties otherwise (the larger of the two).
    let (mut rx, mut ry, mut ux, mut uy) = (0.0, 0.0, 0.0, 0.0);
    for (d, c) in &pairs {
        let dt = (c.time - d.time).value();
        rx += ((c.position.x - d.position.x).value() - velocity.x_counts_per_s * dt).powi(2);
        ry += ((c.position.y - d.position.y).value() - velocity.y_counts_per_s * dt).powi(2);
        ux += (d.uncertainty.sigma_x.value().powi(2) + c.uncertainty.sigma_x.value().powi(2))
            * dt
            * dt;
        uy += (d.uncertainty.sigma_y.value().powi(2) + c.uncertainty.sigma_y.value().powi(2))
            * dt
            * dt;
    }
    let n = pairs.len() as f64;
    let scatter = |r: f64| {
        if pairs.len() > 1 {
            (r / (n - 1.0) / stt).sqrt()
        } else {
            0.0
        }
    };
    let velocity_sigma = CountVelocity {
        x_counts_per_s: scatter(rx).max(ux.sqrt() / stt),
        y_counts_per_s: scatter(ry).max(uy.sqrt() / stt),
    };
    let reference_time = pairs
        .iter()
        .map(|(d, _)| d.time)
        .fold(Seconds(f64::INFINITY), Seconds::min);
    let common = pairs
        .iter()
        .map(|(d, c)| {
            let from_direct = d.position - velocity.displacement(d.time - reference_time);
            let from_counter = c.position - velocity.displacement(c.time - reference_time);
            CommonFeature {
                direct: *d,
                counter: *c,
                drift_free: CountPoint::from_counts(
                    0.5 * (from_direct.x + from_counter.x).value(),
                    0.5 * (from_direct.y + from_counter.y).value(),
                ),
            }
        })
        .collect();
    Some(CounterScanReport {
        velocity,
        velocity_sigma,
        reference_time,
        common,
    })
}

/// Counter-scans the region of `params.raster` centred on `centre`: a direct
/// scan, then a counter scan (−x lines stepping −y from the far corner).
/// Fails with [`FosError::NoCommonFeature`] when the frames share no feature
/// and with [`FosError::Unsupported`] when the backend cannot counter-scan.
pub fn counter_scan<M: Microscope>(
    microscope: &mut M,
    centre: CountPoint,
    params: &CounterScanParams,
) -> Result<CounterScanReport, FosError<M::Error>> {
    params.raster.validate()?;
    params.motion.validate()?;
    positive("match_radius_counts", params.match_radius_counts)?;
    if !microscope.capabilities().counter_scan {
        return Err(FosError::Unsupported("counter scans"));
    }
    microscope
        .move_to(params.motion.request(centre))
        .map_err(FosError::instrument)?;
    let direct = scan_and_recognise(
        microscope,
        &params.raster,
        centre,
        ScanDirection::Direct,
        &params.detection,
    )?;
    let counter = scan_and_recognise(
        microscope,
        &params.raster,
        centre,
        ScanDirection::Counter,
        &params.detection,
    )?;
    let report = solve_counter_scan(
        &direct.detection.features,
        &counter.detection.features,
        params.drift_prior,
        params.match_radius_counts,
    )
    .ok_or(FosError::NoCommonFeature {
        direct: direct.detection.features.len(),
        counter: counter.detection.features.len(),
    })?;
    tracing::debug!(
        common = report.common.len(),
        vx = report.velocity.x_counts_per_s,
        vy = report.velocity.y_counts_per_s,
        "counter-scan"
    );
    Ok(report)
}
