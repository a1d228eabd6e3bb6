//! Probe attachment (paper §2.1.1): capture the feature nearest a point and
//! hold it until the drift (creep after a node move) falls below a limit.

use crate::acquire::{Motion, Raster, Sighting, scan_and_recognise, track};
use crate::error::{FosError, positive};
use crate::velocity::fit_velocity;
use serde::{Deserialize, Serialize};
use spm_features::{DetectionConfig, Feature};
use spm_hal::{CountPoint, CountVelocity, Microscope, ScanDirection, Seconds};

/// Settings of [`attach`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AttachParams {
    /// The first attachment's raster: large enough to hold at least one
    /// feature wherever it lands on the surface.
    pub first: Raster,
    /// The segment raster of the following attachments (about one feature).
    pub segment: Raster,
    /// Recognition settings for the first raster.
    pub first_detection: DetectionConfig,
    /// Recognition settings for segments.
    pub segment_detection: DetectionConfig,
    /// Probe moves.
    pub motion: Motion,
    /// The attachment is settled when the drift speed is below this, counts per second.
    pub velocity_limit_counts_per_s: f64,
    /// Consecutive velocity estimates below the limit needed to settle.
    /// Default 3 (a single low estimate is as likely noise as settling).
    pub settle_count: usize,
    /// Attachments used for each velocity estimate (least-squares line over
    /// positions and times), at least 2. Default 4. A decaying creep makes a
    /// longer window overestimate the current speed: conservative.
    pub velocity_window: usize,
    /// Give up waiting after this long, seconds.
    pub timeout_s: f64,
    /// Pause before each segment attachment, seconds: a longer baseline
    /// makes each velocity estimate less noisy. Keep the drift over one
    /// interval well below half the feature spacing, or the tracker may lock
    /// onto a neighbouring feature (an aliased velocity). Default 0.
    pub attachment_interval_s: f64,
    /// A feature farther than this fraction of the segment's side from its
    /// predicted position is lost. Default 0.4.
    pub capture_radius_fraction: f64,
}

impl AttachParams {
    /// Defaults around the two rasters, the speed limit and the timeout.
    pub fn new(
        first: Raster,
        segment: Raster,
        velocity_limit_counts_per_s: f64,
        timeout_s: f64,
    ) -> Self {
        Self {
            first,
            segment,
            first_detection: DetectionConfig::default(),
            segment_detection: DetectionConfig::default(),
            motion: Motion::TYPICAL,
            velocity_limit_counts_per_s,
            settle_count: 3,
            velocity_window: 4,
            timeout_s,
            attachment_interval_s: 0.0,
            capture_radius_fraction: 0.4,
        }
    }

    fn validate<E: spm_hal::Error>(&self) -> Result<(), FosError<E>> {
        self.first.validate()?;
        self.segment.validate()?;
        self.motion.validate()?;
        positive(
            "velocity_limit_counts_per_s",
            self.velocity_limit_counts_per_s,
        )?;
        positive("timeout_s", self.timeout_s)?;
        positive("capture_radius_fraction", self.capture_radius_fraction)?;
        if !(self.attachment_interval_s.is_finite() && self.attachment_interval_s >= 0.0) {
            return Err(FosError::InvalidParameter {
                field: "attachment_interval_s",
                reason: "must be a finite time ≥ 0",
            });
        }
        if self.velocity_window < 2 {
            return Err(FosError::InvalidParameter {
                field: "velocity_window",
                reason: "at least 2 attachments are needed for a velocity",
            });
        }
        if self.settle_count == 0 {
            return Err(FosError::InvalidParameter {
                field: "settle_count",
                reason: "must be ≥ 1",
            });
        }
        Ok(())
    }
}

/// How an attachment ended.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AttachOutcome {
    /// The feature is held and the drift speed is below the limit.
    Settled {
        /// The last drift velocity estimate, counts per second.
        velocity: CountVelocity,
    },
    /// The drift did not fall below the limit before the timeout.
    TimedOut {
        /// The last drift velocity estimate (zero if there was none).
        velocity: CountVelocity,
    },
    /// No feature in the first raster, or the held feature vanished from its
    /// segment.
    FeatureLost {
        /// Where it was expected, counts.
        expected: CountPoint,
    },
}

/// The result of [`attach`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AttachReport {
    /// How it ended.
    pub outcome: AttachOutcome,
    /// The last sighting of the feature (None when none was captured).
    pub feature: Option<Feature>,
    /// Every sighting, first attachment included: position and time.
    pub history: Vec<Sighting>,
    /// Every velocity estimate, in order.
    pub velocities: Vec<CountVelocity>,
    /// Instrument time spent, seconds.
    pub elapsed_s: f64,
}

impl AttachReport {
    /// True when settled.
    pub fn is_settled(&self) -> bool {
        matches!(self.outcome, AttachOutcome::Settled { .. })
    }
    /// The last velocity estimate.
    pub fn velocity(&self) -> Option<CountVelocity> {
        self.velocities.last().copied()
    }
}

/// Attaches to the feature nearest `near`: a first raster around `near`,
/// then segment attachments re-centred on the feature (predicted with the
/// current drift estimate), a velocity from the last `velocity_window`
/// positions and times after each, until `settle_count` consecutive speeds
/// are below the limit or the timeout passes.
pub fn attach<M: Microscope>(
    microscope: &mut M,
    near: CountPoint,
    params: &AttachParams,
) -> Result<AttachReport, FosError<M::Error>> {
    params.validate()?;
    let start = microscope.now().map_err(FosError::instrument)?;
    microscope
        .move_to(params.motion.request(near))
        .map_err(FosError::instrument)?;
    let first = scan_and_recognise(
        microscope,
        &params.first,
        near,
        ScanDirection::Direct,
        &params.first_detection,
    )?;
    let mut report = AttachReport {
        outcome: AttachOutcome::FeatureLost { expected: near },
        feature: None,
        history: Vec::new(),
        velocities: Vec::new(),
        elapsed_s: 0.0,
    };
    let Some(feature) = first.detection.nearest(near).copied() else {
        tracing::warn!(
            x = near.x.value(),
            y = near.y.value(),
            "first attachment found no feature"
        );
        report.elapsed_s = (microscope.now().map_err(FosError::instrument)? - start).value();
        return Ok(report);
    };
    tracing::debug!(
        x = feature.position.x.value(),
        y = feature.position.y.value(),
        "feature captured"
    );
    report.feature = Some(feature);
    report.history.push(Sighting { feature });
    let capture = params.capture_radius_fraction * params.segment.side_counts();
    let mut drift = CountVelocity::ZERO;
    let mut below = 0;
    loop {
        let now = microscope.now().map_err(FosError::instrument)?;
        report.elapsed_s = (now - start).value();
        if report.elapsed_s > params.timeout_s {
            report.outcome = AttachOutcome::TimedOut { velocity: drift };
            tracing::info!(
                speed = drift.norm_counts_per_s(),
                elapsed_s = report.elapsed_s,
                "attachment timed out"
            );
            return Ok(report);
        }
        let Some(last) = report.history.last().copied() else {
            return Ok(report);
        };
        if params.attachment_interval_s > 0.0 {
            microscope
                .wait(Seconds(params.attachment_interval_s))
                .map_err(FosError::instrument)?;
        }
        let sighting = match track(
            microscope,
            last.position(),
            last.time(),
            drift,
            &params.segment,
            &params.motion,
            &params.segment_detection,
            capture,
        ) {
            Ok(s) => s,
            Err(FosError::FeatureLost { expected, .. }) => {
                report.outcome = AttachOutcome::FeatureLost { expected };
                report.elapsed_s =
                    (microscope.now().map_err(FosError::instrument)? - start).value();
                return Ok(report);
            }
            Err(e) => return Err(e),
        };
        report.feature = Some(sighting.feature);
        report.history.push(sighting);
        let window = params.velocity_window.min(report.history.len());
        let recent = &report.history[report.history.len() - window..];
        if let Some(v) = fit_velocity(recent.iter().map(|s| (s.time(), s.position()))) {
            drift = v;
            report.velocities.push(v);
            let speed = v.norm_counts_per_s();
            tracing::debug!(
                speed,
                attachments = report.history.len(),
                "attachment velocity"
            );
            if speed < params.velocity_limit_counts_per_s {
                below += 1;
            } else {
                below = 0;
            }
            if below >= params.settle_count {
                report.outcome = AttachOutcome::Settled { velocity: v };
                report.elapsed_s =
                    (microscope.now().map_err(FosError::instrument)? - start).value();
                tracing::info!(speed, elapsed_s = report.elapsed_s, "attachment settled");
                return Ok(report);
            }
        }
    }
}

/// The feature's expected position at time `t` from a sighting and a drift velocity.
pub fn predict(sighting: &Sighting, drift: CountVelocity, t: Seconds) -> CountPoint {
    sighting.position() + drift.displacement(t - sighting.time())
}
