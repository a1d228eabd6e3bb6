//! The realistic grating polynomial: one image of the whole region over a pillar grating, the
//! pillars detected and indexed, a total-degree-3 polynomial per coordinate fitted from their
//! commanded counts to their certified grid positions.

use super::ImageBenchmarkError;
use super::take::CountRegion;
use crate::cubic::CubicMap;
use spm_features::{DetectionConfig, detect};
use spm_hal::truth::{GratingSample, SimulatedInstrument};
use spm_hal::{CountPoint, Counts, ScanRequest, Seconds, TraceHalf};

/// The grating of the realistic polynomial baseline.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GratingConfig {
    /// The certified pitch, nm (what the fit is told).
    pub nominal_pitch_nm: f64,
    /// The true pitch relative to the certificate (1.001 = at the edge of a 0.1 % certificate).
    pub true_over_nominal: f64,
    /// Pillar height, nm.
    pub height_nm: f64,
    /// Pillar Gaussian radius, nm.
    pub sigma_nm: f64,
    /// Mounting angle of the grating, degrees.
    pub rotation_deg: f64,
    /// Pixels per side of the one grating image.
    pub pixels: u32,
    /// Pixel dwell of the grating image, s.
    pub dwell_s: f64,
}

impl GratingConfig {
    /// A 40 nm pitch pillar grating (certificate ±0.1 %, true pitch at its edge), 5 nm high,
    /// one 513 × 513 image at `dwell_s`.
    pub fn standard(dwell_s: f64) -> Self {
        Self {
            nominal_pitch_nm: 40.0,
            true_over_nominal: 1.001,
            height_nm: 5.0,
            sigma_nm: 6.0,
            rotation_deg: 3.0,
            pixels: 513,
            dwell_s,
        }
    }
}

/// The realistic per-image polynomial: the same physics (scanner, hysteresis, creep, drift,
/// noise) over a pillar grating; one image of the whole region; pillars detected by
/// spm-features (real detection noise); indexed by a walk over nearest neighbours; a
/// total-degree-3 polynomial per coordinate fitted from the pillars' commanded counts to
/// their certified grid positions. Drift during the image stays in (one image, as a user
/// takes it).
///
/// # Errors
/// [`ImageBenchmarkError::Grating`] when the image cannot be taken, indexed or fitted.
pub fn grating_polynomial<S: SimulatedInstrument>(
    instrument: &S,
    nominal_nm_per_count: f64,
    region: &CountRegion,
    grating: &GratingConfig,
) -> Result<CubicMap, ImageBenchmarkError> {
    let mut sim = instrument
        .grating_twin(&GratingSample {
            pitch_nm: grating.nominal_pitch_nm * grating.true_over_nominal,
            height_nm: grating.height_nm,
            sigma_nm: grating.sigma_nm,
            rotation_deg: grating.rotation_deg,
        })
        .map_err(|e| ImageBenchmarkError::Grating(e.to_string()))?;
    let side =
        (region.x_max_counts - region.x_min_counts).max(region.y_max_counts - region.y_min_counts);
    let n = grating.pixels.max(16);
    let step = (side / f64::from(n - 1)).ceil();
    let centre = CountPoint::from_counts(
        (0.5 * (region.x_min_counts + region.x_max_counts)).round(),
        (0.5 * (region.y_min_counts + region.y_max_counts)).round(),
    );
    let request = ScanRequest::centred_square(centre, Counts(step), n, Seconds(grating.dwell_s));
    let frame = sim
        .scan(&request)
        .map_err(|e| ImageBenchmarkError::Grating(format!("grating image: {e}")))?;
    let map = frame
        .height_map(TraceHalf::Forward)
        .map_err(|e| ImageBenchmarkError::Grating(format!("grating image: {e}")))?;
    // Nominal period in pixels: the scanner's large-signal gain is unknown to the user, so
    // the detection is told only the order of magnitude.
    let period_px = grating.nominal_pitch_nm / (nominal_nm_per_count * step);
    let config = DetectionConfig {
        min_separation_px: 0.4 * period_px,
        max_fit_radius_px: (0.5 * period_px).max(3.0),
        ..DetectionConfig::default()
    };
    let features = detect(&map, &config)
        .map_err(|e| ImageBenchmarkError::Grating(format!("pillar detection: {e}")))?
        .features;
    let positions: Vec<[f64; 2]> = features
        .iter()
        .map(|f| [f.position.x.value(), f.position.y.value()])
        .collect();
    let indexed = index_grid(&positions, [centre.x.value(), centre.y.value()])
        .ok_or_else(|| ImageBenchmarkError::Grating("pillars could not be indexed".to_owned()))?;
    if indexed.len() < 50 {
        return Err(ImageBenchmarkError::Grating(format!(
            "only {} pillars indexed",
            indexed.len()
        )));
    }
    let points: Vec<[f64; 2]> = indexed.iter().map(|(k, _)| positions[*k]).collect();
    let targets: Vec<[f64; 2]> = indexed
        .iter()
        .map(|(_, (i, j))| {
            [
                f64::from(*i) * grating.nominal_pitch_nm,
                f64::from(*j) * grating.nominal_pitch_nm,
            ]
        })
        .collect();
    CubicMap::fit(&points, &targets)
        .map_err(|e| ImageBenchmarkError::Grating(format!("polynomial fit: {e}")))
}

/// Grid indices of features on a distorted square lattice: a breadth-first walk from the
/// feature nearest `start`, each step predicted by the local lattice vectors of its parent.
fn index_grid(positions: &[[f64; 2]], start: [f64; 2]) -> Option<Vec<(usize, (i32, i32))>> {
    let dist = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]);
    let first = (0..positions.len())
        .min_by(|&a, &b| dist(positions[a], start).total_cmp(&dist(positions[b], start)))?;
    let p0 = positions[first];
    let mut near: Vec<usize> = (0..positions.len()).filter(|&k| k != first).collect();
    near.sort_by(|&a, &b| dist(positions[a], p0).total_cmp(&dist(positions[b], p0)));
    let near: Vec<[f64; 2]> = near
        .iter()
        .take(4)
        .map(|&k| [positions[k][0] - p0[0], positions[k][1] - p0[1]])
        .collect();
    if near.len() < 4 {
        return None;
    }
    let v1 = *near.iter().max_by(|a, b| a[0].total_cmp(&b[0]))?;
    let v2 = *near.iter().max_by(|a, b| a[1].total_cmp(&b[1]))?;
    let pitch = dist(v1, [0.0; 2]).min(dist(v2, [0.0; 2]));
    if !(pitch.is_finite() && pitch > 0.0) {
        return None;
    }
    // Cells of one pitch for the nearest-feature look-up.
    let grid = super::neighbours::Grid::new(positions, pitch);
    let nearest = |q: [f64; 2]| grid.nearest_within_a_cell(q, positions);
    let mut index_of: std::collections::HashMap<usize, (i32, i32)> =
        std::collections::HashMap::new();
    let mut taken: std::collections::HashSet<(i32, i32)> = std::collections::HashSet::new();
    let mut queue = std::collections::VecDeque::new();
    index_of.insert(first, (0, 0));
    taken.insert((0, 0));
    queue.push_back((first, (0_i32, 0_i32), v1, v2));
    while let Some((k, (i, j), a, b)) = queue.pop_front() {
        let p = positions[k];
        for (di, dj, sign, along_a) in [
            (1, 0, 1.0, true),
            (-1, 0, -1.0, true),
            (0, 1, 1.0, false),
            (0, -1, -1.0, false),
        ] {
            let v = if along_a { a } else { b };
            let q = [p[0] + sign * v[0], p[1] + sign * v[1]];
            let Some((m, d)) = nearest(q) else { continue };
            let cell = (i + di, j + dj);
            if d > 0.3 * pitch || index_of.contains_key(&m) || taken.contains(&cell) {
                continue;
            }
            let step = [
                sign * (positions[m][0] - p[0]),
                sign * (positions[m][1] - p[1]),
            ];
            let (na, nb) = if along_a { (step, b) } else { (a, step) };
            index_of.insert(m, cell);
            taken.insert(cell);
            queue.push_back((m, cell, na, nb));
        }
    }
    let mut out: Vec<(usize, (i32, i32))> = index_of.into_iter().collect();
    out.sort_unstable();
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sheared_square_lattice_is_indexed_from_its_centre() {
        // Pitch 10, a 2 % shear and a slight rotation: every feature gets its own (i, j).
        let (a, b) = ([10.0, 0.3], [0.2, 10.2]);
        let mut positions = Vec::new();
        let mut truth = Vec::new();
        for j in -4..=4_i32 {
            for i in -4..=4_i32 {
                let (fi, fj) = (f64::from(i), f64::from(j));
                positions.push([100.0 + fi * a[0] + fj * b[0], 50.0 + fi * a[1] + fj * b[1]]);
                truth.push((i, j));
            }
        }
        let indexed = index_grid(&positions, [100.0, 50.0]);
        let Some(indexed) = indexed else {
            panic!("not indexed");
        };
        assert_eq!(indexed.len(), positions.len());
        for (k, cell) in indexed {
            assert_eq!(cell, truth[k], "feature {k}");
        }
    }
}
