//! Scanning and recognising one segment or aperture: the primitive every FOS
//! operation is built from.

use crate::error::{FosError, positive};
use serde::{Deserialize, Serialize};
use spm_features::{Detection, DetectionConfig, Feature, detect};
use spm_hal::{
    CountPoint, CountVelocity, Counts, Frame, HeightMap, Microscope, MoveRequest, ScanDirection,
    ScanRequest, Seconds, TraceHalf,
};

/// A square raster: pixels per side, pixel step and dwell.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Raster {
    /// Pixels per line and number of lines.
    pub pixels: u32,
    /// Pixel step, counts.
    pub pixel_step_counts: f64,
    /// Dwell per pixel, seconds.
    pub pixel_dwell_s: f64,
}

impl Raster {
    /// Checks the fields.
    pub fn validate<E: spm_hal::Error>(&self) -> Result<(), FosError<E>> {
        if self.pixels < spm_features::MIN_MAP_SIDE as u32 {
            return Err(FosError::InvalidParameter {
                field: "pixels",
                reason: "a raster needs at least 5 pixels per side",
            });
        }
        positive("pixel_step_counts", self.pixel_step_counts)?;
        positive("pixel_dwell_s", self.pixel_dwell_s)
    }

    /// The direct scan request centred on `centre`.
    pub fn request(&self, centre: CountPoint) -> ScanRequest {
        ScanRequest::centred_square(
            centre,
            Counts(self.pixel_step_counts),
            self.pixels,
            Seconds(self.pixel_dwell_s),
        )
    }

    /// Side length of the raster, counts.
    pub fn side_counts(&self) -> f64 {
        self.pixel_step_counts * f64::from(self.pixels.saturating_sub(1))
    }

    /// Nominal duration of one frame (trace and retrace), seconds.
    pub fn duration_s(&self) -> f64 {
        2.0 * f64::from(self.pixels) * f64::from(self.pixels) * self.pixel_dwell_s
    }
}

/// How the probe moves between features (a calibration plan sets it from `[plan.motion]`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Motion {
    /// Lateral speed, counts per second (> 0).
    pub speed_counts_per_s: f64,
    /// Settle time after each move, seconds (≥ 0).
    pub settle_s: f64,
}

impl Motion {
    /// A 16-bit tube scanner's usual hop between atoms: 2000 counts/s (≈ 40 nm/s at
    /// 0.02 nm/count) and 10 ms to settle. The parameter constructors start from it; a plan
    /// replaces it.
    pub const TYPICAL: Self = Self {
        speed_counts_per_s: 2000.0,
        settle_s: 0.01,
    };

    pub(crate) fn request(&self, target: CountPoint) -> MoveRequest {
        MoveRequest {
            target,
            speed: spm_hal::CountsPerSecond(self.speed_counts_per_s),
            settle: Seconds(self.settle_s.max(0.0)),
        }
    }

    pub(crate) fn validate<E: spm_hal::Error>(&self) -> Result<(), FosError<E>> {
        positive("speed_counts_per_s", self.speed_counts_per_s)?;
        if !(self.settle_s.is_finite() && self.settle_s >= 0.0) {
            return Err(FosError::InvalidParameter {
                field: "settle_s",
                reason: "must be a finite time ≥ 0",
            });
        }
        Ok(())
    }
}

/// One recognised frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Recognised {
    /// The frame's forward half in scanner geometry.
    pub map: HeightMap,
    /// What recognition found in it.
    pub detection: Detection,
}

/// Scans `raster` centred on `centre` in `direction` and recognises the forward half.
pub fn scan_and_recognise<M: Microscope>(
    microscope: &mut M,
    raster: &Raster,
    centre: CountPoint,
    direction: ScanDirection,
    detection: &DetectionConfig,
) -> Result<Recognised, FosError<M::Error>> {
    let request = raster.request(centre).with_direction(direction);
    let frame: Frame = microscope.scan(&request).map_err(FosError::instrument)?;
    let map = frame.height_map(TraceHalf::Forward)?;
    let detection = detect(&map, detection)?;
    Ok(Recognised { map, detection })
}

/// A feature measurement: where a feature was seen and when.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sighting {
    /// The recognised feature (position in counts, time, quality, uncertainty).
    pub feature: Feature,
}

impl Sighting {
    /// Position, counts.
    pub fn position(&self) -> CountPoint {
        self.feature.position
    }
    /// Time, seconds.
    pub fn time(&self) -> Seconds {
        self.feature.time
    }
}

/// Moves to a feature expected at `expected` (at time `expected_at`, moving
/// with `drift`), scans a segment centred on where it will be in the middle of
/// the scan, and returns the recognised feature nearest that prediction.
/// Fails with [`FosError::FeatureLost`] when none lies within `capture_radius_counts`.
#[allow(clippy::too_many_arguments)]
pub fn track<M: Microscope>(
    microscope: &mut M,
    expected: CountPoint,
    expected_at: Seconds,
    drift: CountVelocity,
    raster: &Raster,
    motion: &Motion,
    detection: &DetectionConfig,
    capture_radius_counts: f64,
) -> Result<Sighting, FosError<M::Error>> {
    let now = microscope.now().map_err(FosError::instrument)?;
    let from = microscope.position().map_err(FosError::instrument)?;
    // Predict the feature's position in the middle of the coming scan.
    let move_s = from.distance(expected).value() / motion.speed_counts_per_s + motion.settle_s;
    let mid = now + Seconds(move_s + 0.5 * raster.duration_s());
    let predicted = expected + drift.displacement(mid - expected_at);
    microscope
        .move_to(motion.request(predicted))
        .map_err(FosError::instrument)?;
    let recognised = scan_and_recognise(
        microscope,
        raster,
        predicted,
        ScanDirection::Direct,
        detection,
    )?;
    let found = recognised
        .detection
        .nearest(predicted)
        .filter(|f| f.position.distance(predicted).value() <= capture_radius_counts)
        .copied();
    match found {
        Some(feature) => {
            tracing::trace!(
                x = feature.position.x.value(),
                y = feature.position.y.value(),
                t = feature.time.value(),
                "feature tracked"
            );
            Ok(Sighting { feature })
        }
        None => {
            tracing::warn!(
                x = predicted.x.value(),
                y = predicted.y.value(),
                found = recognised.detection.features.len(),
                "feature lost"
            );
            Err(FosError::FeatureLost {
                expected: predicted,
                radius_counts: capture_radius_counts,
            })
        }
    }
}
