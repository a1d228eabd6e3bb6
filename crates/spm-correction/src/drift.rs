//! Counter-scanned pairs: drift from common features (Lapshin, Meas. Sci. Technol. 18 (2007)
//! 907), combined with the distributed correction.
//!
//! With a constant drift velocity v, a sample feature whose position at the reference time
//! t_ref is p appears at p + v·(t − t_ref) when the probe passes it at time t. After both
//! images are distortion-corrected into the common frame ([`crate::correct_raster`]), a feature
//! seen at p_d (time t_d) in the direct and p_c (t_c) in the counter image gives
//! v = (p_c − p_d)/(t_c − t_d); with several features v is their least-squares fit
//! v = Σ Δt·Δp / Σ Δt². Every pixel is then moved to the common time:
//! p(t_ref) = p − v·(t − t_ref).

use spm_hal::{HeightMap, NmPoint, NmVelocity, ScanDirection, Seconds};

use crate::CorrectionError;
use crate::field::CorrectionField;
use crate::parallel::Parallelism;
use crate::raster::{CoordinateMap, Integration, RasterGeometry, YCoordinates, correct_raster};

/// A feature seen once: its distortion-corrected position and the time the probe passed it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FeatureSighting {
    /// Corrected position, nm (common frame).
    pub position: NmPoint,
    /// Acquisition time, s.
    pub time: Seconds,
}

/// The same sample feature in the direct and the counter image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SightingPair {
    /// In the direct image.
    pub direct: FeatureSighting,
    /// In the counter image.
    pub counter: FeatureSighting,
}

/// A constant drift velocity fitted to sighting pairs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DriftEstimate {
    /// Drift velocity, nm/s.
    pub velocity: NmVelocity,
    /// RMS of the residuals Δp − v·Δt over the pairs (both components), nm; 0 for one pair.
    pub residual_rms_nm: f64,
    /// Number of pairs used.
    pub features: usize,
}

/// Least-squares constant drift from sighting pairs.
///
/// # Errors
/// [`CorrectionError::DriftUndetermined`] without pairs or when every pair has t_c = t_d;
/// [`CorrectionError::NonFinite`].
pub fn estimate_drift(pairs: &[SightingPair]) -> Result<DriftEstimate, CorrectionError> {
    if pairs.is_empty() {
        return Err(CorrectionError::DriftUndetermined(
            "no common feature between the direct and the counter image".into(),
        ));
    }
    let (mut stt, mut stx, mut sty) = (0.0, 0.0, 0.0);
    for (index, p) in pairs.iter().enumerate() {
        let values = [
            p.direct.position.x.value(),
            p.direct.position.y.value(),
            p.direct.time.value(),
            p.counter.position.x.value(),
            p.counter.position.y.value(),
            p.counter.time.value(),
        ];
        if values.iter().any(|v| !v.is_finite()) {
            return Err(CorrectionError::NonFinite {
                what: "feature sighting",
                index,
            });
        }
        let dt = p.counter.time.value() - p.direct.time.value();
        stt += dt * dt;
        stx += dt * (p.counter.position.x.value() - p.direct.position.x.value());
        sty += dt * (p.counter.position.y.value() - p.direct.position.y.value());
    }
    if stt.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
        return Err(CorrectionError::DriftUndetermined(
            "every feature was seen at the same time in both images".into(),
        ));
    }
    let velocity = NmVelocity {
        x_nm_per_s: stx / stt,
        y_nm_per_s: sty / stt,
    };
    let mut ss = 0.0;
    for p in pairs {
        let dt = p.counter.time.value() - p.direct.time.value();
        let rx =
            p.counter.position.x.value() - p.direct.position.x.value() - velocity.x_nm_per_s * dt;
        let ry =
            p.counter.position.y.value() - p.direct.position.y.value() - velocity.y_nm_per_s * dt;
        ss += rx * rx + ry * ry;
    }
    let residual_rms_nm = if pairs.len() > 1 {
        (ss / (2 * (pairs.len() - 1)) as f64).sqrt()
    } else {
        0.0
    };
    Ok(DriftEstimate {
        velocity,
        residual_rms_nm,
        features: pairs.len(),
    })
}

/// A position seen at `time` moved to the common time `t_ref`: p − v·(t − t_ref).
#[must_use]
pub fn to_common_time(
    position: NmPoint,
    time: Seconds,
    velocity: NmVelocity,
    t_ref: Seconds,
) -> NmPoint {
    let dt = time.value() - t_ref.value();
    NmPoint::from_nm(
        position.x.value() - velocity.x_nm_per_s * dt,
        position.y.value() - velocity.y_nm_per_s * dt,
    )
}

/// Every pixel of `map` moved to the common time `t_ref` (per-pixel times `time_s`, indexed
/// like the map). The result has per-pixel ȳ.
///
/// # Errors
/// [`CorrectionError::SizeMismatch`], [`CorrectionError::NonFinite`].
pub fn drift_corrected_map(
    map: &CoordinateMap,
    time_s: &[f64],
    velocity: NmVelocity,
    t_ref: Seconds,
) -> Result<CoordinateMap, CorrectionError> {
    let (nx, ny) = (map.columns(), map.rows());
    if time_s.len() != nx * ny {
        return Err(CorrectionError::SizeMismatch {
            what: "time_s",
            expected: nx * ny,
            got: time_s.len(),
        });
    }
    crate::error::check_finite("time_s", time_s)?;
    crate::error::check_finite_scalar("drift velocity x", velocity.x_nm_per_s)?;
    crate::error::check_finite_scalar("drift velocity y", velocity.y_nm_per_s)?;
    let mut x = Vec::with_capacity(nx * ny);
    let mut y = Vec::with_capacity(nx * ny);
    for (k, &t) in time_s.iter().enumerate() {
        let dt = t - t_ref.value();
        x.push(map.x_nm()[k] - velocity.x_nm_per_s * dt);
        y.push(map.y_at(k % nx, k / nx) - velocity.y_nm_per_s * dt);
    }
    CoordinateMap::new(nx, ny, x, YCoordinates::PerPixel(y))
}

/// One feature located in both images of a counter-scanned pair, as fractional pixel
/// coordinates in scanner geometry (column grows with x, row with y, as in [`HeightMap`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FeatureMatch {
    /// Column in the direct image.
    pub direct_column: f64,
    /// Row in the direct image.
    pub direct_row: f64,
    /// Column in the counter image.
    pub counter_column: f64,
    /// Row in the counter image.
    pub counter_row: f64,
}

/// The result of [`correct_counter_pair`].
#[derive(Debug, Clone, PartialEq)]
pub struct CounterPairCorrection {
    /// The fitted drift.
    pub drift: DriftEstimate,
    /// Direct image: distortion- and drift-corrected coordinates at t_ref.
    pub direct: CoordinateMap,
    /// Counter image: distortion- and drift-corrected coordinates at t_ref.
    pub counter: CoordinateMap,
}

/// Bilinear interpolation of a per-pixel quantity.
fn interpolate_pixels(values: &[f64], columns: usize, rows: usize, c: f64, r: f64) -> f64 {
    let i = (c.floor().max(0.0) as usize).min(columns.saturating_sub(2));
    let j = (r.floor().max(0.0) as usize).min(rows.saturating_sub(2));
    let i1 = (i + 1).min(columns - 1);
    let j1 = (j + 1).min(rows - 1);
    let (fx, fy) = (c - i as f64, r - j as f64);
    let v = |a: usize, b: usize| values[b * columns + a];
    (v(i, j) * (1.0 - fx) + v(i1, j) * fx) * (1.0 - fy)
        + (v(i, j1) * (1.0 - fx) + v(i1, j1) * fx) * fy
}

/// Distributed correction of both images of a counter-scanned pair, drift from the matched
/// features, and both coordinate maps moved to `t_ref`.
///
/// The feature positions are corrected through the raster maps of their own image (direct or
/// counter path) and dated by the bilinear interpolation of the pixel times.
///
/// # Errors
/// [`CorrectionError::GeometryMismatch`] if the images do not share origin, step and size;
/// [`CorrectionError::InvalidArgument`] for a feature outside its image; as
/// [`correct_raster`] and [`estimate_drift`].
pub fn correct_counter_pair<F: CorrectionField + ?Sized>(
    field: &F,
    direct: &HeightMap,
    counter: &HeightMap,
    matches: &[FeatureMatch],
    t_ref: Seconds,
    integration: &Integration,
    parallelism: Parallelism,
) -> Result<CounterPairCorrection, CorrectionError> {
    let geometry = RasterGeometry::of_height_map(direct)?;
    let other = RasterGeometry::of_height_map(counter)?;
    if geometry != other {
        return Err(CorrectionError::GeometryMismatch(format!(
            "direct {geometry:?}, counter {other:?}"
        )));
    }
    for (what, m) in [("direct time_s", direct), ("counter time_s", counter)] {
        if m.time_s.len() != geometry.pixel_count() {
            return Err(CorrectionError::SizeMismatch {
                what,
                expected: geometry.pixel_count(),
                got: m.time_s.len(),
            });
        }
    }
    let d_map = correct_raster(
        field,
        &geometry,
        ScanDirection::Direct,
        integration,
        parallelism,
    )?;
    let c_map = correct_raster(
        field,
        &geometry,
        ScanDirection::Counter,
        integration,
        parallelism,
    )?;
    let (nx, ny) = (geometry.columns, geometry.rows);
    let mut pairs = Vec::with_capacity(matches.len());
    for (index, m) in matches.iter().enumerate() {
        let outside = || {
            CorrectionError::InvalidArgument(format!(
                "feature match {index} lies outside its image"
            ))
        };
        let pd = d_map
            .interpolate(m.direct_column, m.direct_row)
            .ok_or_else(outside)?;
        let pc = c_map
            .interpolate(m.counter_column, m.counter_row)
            .ok_or_else(outside)?;
        let td = interpolate_pixels(&direct.time_s, nx, ny, m.direct_column, m.direct_row);
        let tc = interpolate_pixels(&counter.time_s, nx, ny, m.counter_column, m.counter_row);
        pairs.push(SightingPair {
            direct: FeatureSighting {
                position: pd,
                time: Seconds(td),
            },
            counter: FeatureSighting {
                position: pc,
                time: Seconds(tc),
            },
        });
    }
    let drift = estimate_drift(&pairs)?;
    Ok(CounterPairCorrection {
        direct: drift_corrected_map(&d_map, &direct.time_s, drift.velocity, t_ref)?,
        counter: drift_corrected_map(&c_map, &counter.time_s, drift.velocity, t_ref)?,
        drift,
    })
}
