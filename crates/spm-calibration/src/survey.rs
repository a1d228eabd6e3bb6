//! The lattice survey (issue 24): before the first node, frames of the standard are scanned
//! at a few places over the net (through the [`Microscope`] trait, like every other
//! operation), the apparent lattice of each is found (its nearest-neighbour vectors by
//! neighbour statistics over the whole frame, solved as an LCS), and their median becomes
//! the *gate* of LCS recognition at every node ([`spm_features::LcsConfig::gate`]): a
//! candidate triangle is accepted only when it is that lattice's nearest-neighbour triangle
//! within the plan's LCS tolerances.
//!
//! # Why
//! LCS recognition on its own admits a triangle through the last measured node's
//! calibration (the prior). On a measured HOPG image (about 11 pixels per lattice constant)
//! one wrong node passed its shape on: the chain locked onto another basis of the same
//! lattice, e.g. (a₁, a₁ + a₂), under which √3 a-long, 30°–40° triangles look like the
//! standard's equilateral one, and every later node repeated the error. A survey of the field
//! measures the lattice the image shows without inheriting anything from the nodes; a
//! frame of ~8 × 8 lattice constants averages the neighbour vectors of some 70 features, so
//! one noisy feature does not move it.
//!
//! # Where
//! `places_per_side`² frames on a grid spanning the net's lateral extent (its corners, edge
//! midpoints and centre for the default 3), each frame kept inside the field. Places whose
//! lattice is far from the others' are refused ([`refuse_outliers`]), and every node is
//! gated by the median over the rest ([`SurveyReport::gate`]); the gate's tolerances (the
//! LCS's) then cover the change of the scanner's sensitivity over the net. A place where no
//! lattice is found (a step, a defect, a scan error) does not count; with none found at
//! all, recognition runs ungated and the report says so.

use crate::config::PlanConfig;
use crate::lcc::{CountCovariance, LccEstimate, StandardVector, VectorObservation, solve_lcc};
use crate::plan::NetPlan;
use serde::{Deserialize, Serialize};
use spm_features::{DetectionConfig, Feature, Lattice, LatticeConfig, LatticeVector};
use spm_fos::{Raster, scan_and_recognise};
use spm_hal::{
    CountPoint, CountsPerSecond, Error as _, ErrorKind, Microscope, MoveRequest, NmPerCountMatrix,
    Radians, ScanDirection, Seconds,
};

/// The `[plan.survey]` table. Absent from a plan: the defaults (off), so older plans run as
/// they did; the plans `spmcal calibrate --virtual` builds for measured images turn it on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SurveyConfig {
    /// Survey the lattice and gate LCS recognition through it. Default false. On measured
    /// images a wrong LCS (a triangle of next-nearest neighbours, or one a wrong earlier node
    /// made look right) gives a wrong record that nothing downstream can tell from a right
    /// one, and the gate refuses it: virtual-mode plans turn it on, and a run on a real
    /// controller should (README). On the simulator's lattices the gate refused no candidate
    /// (quick job, 0 of 54; the 6 × 6 small net, 0 of 222), while the ~100 s of instrument
    /// time the survey adds change the drift and creep history every node sees, and so every
    /// simulated figure (`docs/results/virtual.md`): off by default, the simulated runs and
    /// their figures stay as they were.
    pub enabled: bool,
    /// Places per side of the survey grid over the net (1 = its centre only). Default 3.
    pub places_per_side: u32,
    /// Side of each survey frame, lattice constants (through the nominal sensitivity).
    /// Default 8: about 70 features of a triangular lattice.
    pub size_lattice: f64,
    /// A lattice direction counts when at least this many neighbour pairs lie along it.
    /// Default 4.
    pub min_pairs: u32,
    /// How a frame's lattice is found. Default `neighbours`.
    pub lattice_from: SurveyLattice,
}

/// How a survey frame's lattice is found (`[plan.survey] lattice_from`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SurveyLattice {
    /// The recognised features' neighbour vectors ([`neighbour_directions`]): for a lattice
    /// of single features (HOPG atoms). On the HOPG terrace's frames the spectrum's
    /// strongest peaks scatter by tens of per cent and degrees.
    #[default]
    Neighbours,
    /// The frame's power spectrum ([`spectrum_directions`]), the features' neighbours where
    /// it shows no lattice: for a cell pattern (Si(111)-7×7) whose features are barely
    /// above the noise, where every cell's pattern sharpens the peaks.
    Spectrum,
}

impl Default for SurveyConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            places_per_side: 3,
            size_lattice: 8.0,
            min_pairs: 4,
            lattice_from: SurveyLattice::Neighbours,
        }
    }
}

impl SurveyConfig {
    /// Checks the ranges: places 1–10, size 3–64 lattice constants, pairs 2–1000.
    ///
    /// # Errors
    /// `(field, reason)` of the first value out of range (the field relative to `plan.`).
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if !(1..=10).contains(&self.places_per_side) {
            return Err((
                "survey.places_per_side",
                format!("must be in [1, 10], got {}", self.places_per_side),
            ));
        }
        if !(self.size_lattice.is_finite() && (3.0..=64.0).contains(&self.size_lattice)) {
            return Err((
                "survey.size_lattice",
                format!("must be in [3, 64], got {}", self.size_lattice),
            ));
        }
        if !(2..=1000).contains(&self.min_pairs) {
            return Err((
                "survey.min_pairs",
                format!("must be in [2, 1000], got {}", self.min_pairs),
            ));
        }
        Ok(())
    }
}

/// The apparent local calibration one survey frame found.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurveyLcc {
    /// K̄x, nm per count.
    pub kx_nm_per_count: f64,
    /// K̄y, nm per count.
    pub ky_nm_per_count: f64,
    /// α, rad.
    pub alpha_rad: f64,
    /// Lattice directions used.
    pub directions: usize,
    /// Neighbour pairs averaged over those directions.
    pub pairs: usize,
}

/// One survey place and what it found.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurveyPlace {
    /// Frame centre, counts.
    pub centre_counts: [f64; 2],
    /// Features recognised in the frame.
    pub features: usize,
    /// The lattice found, or `None`.
    pub lcc: Option<SurveyLcc>,
    /// Why no lattice was found.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refusal: Option<String>,
}

/// How LCS candidates fared at the gate over a run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GateTally {
    /// Apertures recognised with a gate.
    pub apertures: u32,
    /// Of those, apertures with at least one admitted candidate (accepted or refused).
    pub apertures_with_candidates: u32,
    /// Apertures where recognition without the gate would have chosen a candidate the gate
    /// refused (misrecognitions prevented).
    pub misrecognitions: u32,
    /// Candidates accepted (passing admission and gate), summed over apertures.
    pub candidates_accepted: u32,
    /// Candidates refused by the gate, summed over apertures.
    pub candidates_refused: u32,
}

impl GateTally {
    /// The misrecognition rate: `misrecognitions / apertures_with_candidates` (`None` when
    /// no aperture had a candidate).
    pub fn misrecognition_rate(&self) -> Option<f64> {
        (self.apertures_with_candidates > 0)
            .then(|| f64::from(self.misrecognitions) / f64::from(self.apertures_with_candidates))
    }

    /// Counts one aperture.
    pub fn count(&mut self, report: &spm_fos::ApertureReport) {
        let accepted = report.accepted_candidates;
        self.apertures += 1;
        if accepted + report.refused_by_gate > 0 {
            self.apertures_with_candidates += 1;
        }
        if report.best_refused_by_gate {
            self.misrecognitions += 1;
        }
        self.candidates_accepted += accepted as u32;
        self.candidates_refused += report.refused_by_gate as u32;
    }
}

/// The survey of a run and the gate's tally (in `RunReport::survey`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SurveyReport {
    /// The places surveyed, in scanning order.
    pub places: Vec<SurveyPlace>,
    /// LCS candidates at the gate.
    pub gate: GateTally,
    /// The misrecognition rate ([`GateTally::misrecognition_rate`]).
    pub misrecognition_rate: Option<f64>,
    /// The field's apparent lattice the gate used ([`SurveyReport::field_lcc`]).
    pub field: Option<SurveyLcc>,
}

impl SurveyReport {
    /// The field's apparent lattice: the median K̄x, K̄y and α over the places with a
    /// lattice (`None` when no place found one).
    pub fn field_lcc(&self) -> Option<SurveyLcc> {
        let found: Vec<&SurveyLcc> = self.places.iter().filter_map(|p| p.lcc.as_ref()).collect();
        if found.is_empty() {
            return None;
        }
        let median = |f: fn(&SurveyLcc) -> f64| {
            let mut v: Vec<f64> = found.iter().map(|l| f(l)).collect();
            spm_regression::median(&mut v).unwrap_or(f64::NAN)
        };
        Some(SurveyLcc {
            kx_nm_per_count: median(|l| l.kx_nm_per_count),
            ky_nm_per_count: median(|l| l.ky_nm_per_count),
            alpha_rad: median(|l| l.alpha_rad),
            directions: found.iter().map(|l| l.directions).min().unwrap_or(0),
            pairs: found.iter().map(|l| l.pairs).sum(),
        })
    }

    /// The gate: the field's apparent lattice ([`Self::field_lcc`]) as a map counts → nm.
    ///
    /// One map for the whole net, not the nearest place's: on a measured image (HOPG
    /// terrace, ~40 features per frame) one frame's α scatters by ±5° around the lattice's
    /// and a gate at a 10° tolerance through the nearest frame refused the true LCS at
    /// most nodes; the median over the places is steady. The LCS tolerances must then
    /// cover the scanner's own change of sensitivity over the net (on the simulator's
    /// room-temperature tube, K̄x and K̄y within ±6 % of their mean).
    pub fn gate(&self) -> Option<NmPerCountMatrix> {
        self.field_lcc().map(|l| {
            NmPerCountMatrix::from_lcc(
                spm_hal::NmPerCount(l.kx_nm_per_count),
                spm_hal::NmPerCount(l.ky_nm_per_count),
                Radians(l.alpha_rad),
            )
        })
    }
}

/// The apparent local calibration of a frame's lattice: its most populated directions
/// (those with at least `min_pairs` pairs and a quarter of the most populated one's, at
/// most ⌊π / angle + ½⌋ of them: three for a triangular lattice, two for a square one),
/// each the standard's nearest-neighbour vector of length `lattice_constant_nm` at the
/// multiple of `lcs_angle` nearest its angle from the first, solved by [`solve_lcc`].
///
/// # Errors
/// A sentence saying why no lattice is taken: fewer than two directions, two directions at
/// the same multiple of the angle, or a degenerate solution.
pub fn apparent_lcc(
    lattice: &Lattice,
    lattice_constant_nm: f64,
    lcs_angle: Radians,
    min_pairs: usize,
) -> Result<(LccEstimate, SurveyLcc), String> {
    let step = lcs_angle.value();
    let most = lattice.vectors.first().map_or(0, |v| v.pairs);
    let max_directions = max_directions(lcs_angle);
    let directions: Vec<_> = lattice
        .vectors
        .iter()
        .filter(|v| v.pairs >= min_pairs.max(2) && 4 * v.pairs >= most)
        .take(max_directions)
        .collect();
    let [first, ..] = directions.as_slice() else {
        return Err("no lattice direction with enough neighbour pairs".into());
    };
    if directions.len() < 2 {
        return Err(format!(
            "one lattice direction with enough neighbour pairs ({} pairs), two needed",
            first.pairs
        ));
    }
    let f = first.vector;
    let mut multiples = Vec::with_capacity(directions.len());
    let mut observations = Vec::with_capacity(directions.len());
    for d in &directions {
        let v = d.vector;
        let angle =
            (f.x.value() * v.y.value() - f.y.value() * v.x.value()).atan2(f.dot_counts_squared(v));
        let k = (angle / step).round() as i64;
        if multiples.contains(&k) {
            return Err(format!(
                "two lattice directions at the same multiple of {:.0}° (apparent angle {:.1}°)",
                step.to_degrees(),
                angle.to_degrees()
            ));
        }
        multiples.push(k);
        let sigma = d.sigma.x.value().hypot(d.sigma.y.value()) / std::f64::consts::SQRT_2;
        observations.push(VectorObservation {
            measured: v,
            covariance: CountCovariance::isotropic(spm_hal::Counts(sigma)),
            standard: StandardVector::polar(
                spm_hal::Nanometres(lattice_constant_nm),
                Radians(k as f64 * step),
            ),
        });
    }
    let lcc = solve_lcc(&observations).map_err(|e| format!("no calibration from it: {e}"))?;
    Ok((
        lcc,
        SurveyLcc {
            kx_nm_per_count: lcc.kx.value(),
            ky_nm_per_count: lcc.ky.value(),
            alpha_rad: lcc.alpha.value(),
            directions: directions.len(),
            pairs: directions.iter().map(|d| d.pairs).sum(),
        },
    ))
}

/// The survey's places: a `places_per_side`² grid over the lateral extent of the plan's
/// nodes, each moved inward so that a frame of `half_side` counts around it lies in the
/// field `[min, max]`.
pub fn places(
    plan: &NetPlan,
    places_per_side: u32,
    half_side: f64,
    field: (CountPoint, CountPoint),
) -> Vec<CountPoint> {
    let nodes: Vec<CountPoint> = plan.visits().map(|v| v.grid.position()).collect();
    let Some(first) = nodes.first() else {
        return Vec::new();
    };
    let (mut x0, mut x1, mut y0, mut y1) = (
        first.x.value(),
        first.x.value(),
        first.y.value(),
        first.y.value(),
    );
    for p in &nodes {
        x0 = x0.min(p.x.value());
        x1 = x1.max(p.x.value());
        y0 = y0.min(p.y.value());
        y1 = y1.max(p.y.value());
    }
    let n = places_per_side.max(1);
    let at = |lo: f64, hi: f64, i: u32| {
        if n == 1 {
            0.5 * (lo + hi)
        } else {
            lo + (hi - lo) * f64::from(i) / f64::from(n - 1)
        }
    };
    let clamp = |v: f64, lo: f64, hi: f64| {
        let (lo, hi) = (lo + half_side + 1.0, hi - half_side - 1.0);
        if lo <= hi {
            v.clamp(lo, hi)
        } else {
            0.5 * (lo + hi)
        }
    };
    let (min, max) = field;
    let mut out = Vec::with_capacity((n * n) as usize);
    for iy in 0..n {
        for k in 0..n {
            // Serpentine, as the net: each move is one grid step.
            let ix = if iy % 2 == 0 { k } else { n - 1 - k };
            out.push(CountPoint::from_counts(
                clamp(at(x0, x1, ix), min.x.value(), max.x.value()),
                clamp(at(y0, y1, iy), min.y.value(), max.y.value()),
            ));
        }
    }
    out
}

/// Scans one survey frame at `centre` (move, the plan's pause for the distance, scan) and
/// finds its lattice. A backend error other than `Aborted` is the place's refusal.
///
/// # Errors
/// The backend's `Aborted` error (the run stops).
pub fn survey_place<M: Microscope>(
    microscope: &mut M,
    centre: CountPoint,
    raster: &Raster,
    detection: &DetectionConfig,
    plan: &PlanConfig,
) -> Result<SurveyPlace, M::Error> {
    let mut place = SurveyPlace {
        centre_counts: [centre.x.value(), centre.y.value()],
        features: 0,
        lcc: None,
        refusal: None,
    };
    let recognised = match scan_at(microscope, centre, raster, detection, plan) {
        Err(spm_fos::FosError::Instrument(e)) if e.kind() == ErrorKind::Aborted => {
            return Err(e);
        }
        Err(e) => {
            place.refusal = Some(format!("the scan: {e}"));
            return Ok(place);
        }
        Ok(r) => r,
    };
    let features = &recognised.detection.features;
    place.features = features.len();
    let max_directions = max_directions(plan.standard.lcs_angle());
    let a_counts = plan.standard.lattice_constant_nm / plan.standard.nominal_nm_per_count;
    let spectrum = match plan.survey.lattice_from {
        SurveyLattice::Spectrum => spectrum_directions(&recognised.map, a_counts, max_directions),
        SurveyLattice::Neighbours => None,
    };
    let found = spectrum
        .map_or_else(
            || neighbour_directions(features, max_directions, plan.survey.min_pairs as usize),
            Ok,
        )
        .and_then(|lattice| {
            for v in &lattice.vectors {
                tracing::debug!(
                    x = v.vector.x.value(),
                    y = v.vector.y.value(),
                    pairs = v.pairs,
                    "survey lattice direction"
                );
            }
            apparent_lcc(
                &lattice,
                plan.standard.lattice_constant_nm,
                plan.standard.lcs_angle(),
                plan.survey.min_pairs as usize,
            )
        });
    match found {
        Ok((_, lcc)) => place.lcc = Some(lcc),
        Err(reason) => place.refusal = Some(reason),
    }
    Ok(place)
}

fn scan_at<M: Microscope>(
    microscope: &mut M,
    centre: CountPoint,
    raster: &Raster,
    detection: &DetectionConfig,
    plan: &PlanConfig,
) -> Result<spm_fos::Recognised, spm_fos::FosError<M::Error>> {
    let instrument = spm_fos::FosError::Instrument;
    let from = microscope.position().map_err(instrument)?;
    microscope
        .move_to(MoveRequest {
            target: centre,
            speed: CountsPerSecond(plan.motion.move_speed_counts_per_s),
            settle: Seconds(plan.motion.settle_s),
        })
        .map_err(instrument)?;
    microscope
        .wait(plan.pause.pause(from.distance(centre), 0))
        .map_err(instrument)?;
    scan_and_recognise(microscope, raster, centre, ScanDirection::Direct, detection)
}

/// The lattice directions of a frame from its power spectrum (`spm_features::cells::
/// find_lattice`: the strongest pair of peaks near the nominal period, refined to sub-bin):
/// b₁, b₂ and, for a triangular lattice (`max_directions` 3), the shorter of b₁ ± b₂;
/// `None` when the spectrum shows no lattice (then the features' neighbour statistics are
/// used). Every cell of the frame contributes to the peaks, so a frame whose features are
/// barely above the noise (Si_7x7_028's corner holes: some features missed, some false)
/// still gives its lattice: the neighbour statistics of that frame put K̄y 50 % off.
/// `pairs` is the number of cells in the frame; `sigma` a tenth of a spectral bin.
pub fn spectrum_directions(
    map: &spm_hal::HeightMap,
    a_counts: f64,
    max_directions: usize,
) -> Option<Lattice> {
    use spm_features::cells;
    let step = map.pixel_step.value();
    let bad: Vec<bool> = map.z_counts.iter().map(|z| !z.is_finite()).collect();
    let img = cells::Image {
        z: &map.z_counts,
        bad: &bad,
        nx: map.columns,
        ny: map.rows,
    };
    let hex = max_directions == 3;
    let search = cells::LatticeSearch::near_period([step, step], a_counts, hex);
    let peaks = cells::find_lattice(&img, &search)?;
    let b = peaks.basis_px()?;
    let side = step * map.columns.min(map.rows) as f64;
    let cells_in_frame = (map.columns * map.rows) as f64 / peaks.cell_area_px();
    let vector = |v: [f64; 2]| {
        let (x, y) = (v[0] * step, v[1] * step);
        let sigma = (x * x + y * y) / (10.0 * side);
        LatticeVector {
            vector: spm_hal::CountVector::from_counts(x, y),
            sigma: spm_hal::CountVector::from_counts(sigma, sigma),
            pairs: cells_in_frame as usize,
        }
    };
    let mut vectors = vec![vector(b[0]), vector(b[1])];
    if hex {
        let (d, s) = (
            [b[0][0] - b[1][0], b[0][1] - b[1][1]],
            [b[0][0] + b[1][0], b[0][1] + b[1][1]],
        );
        vectors.push(vector(if d[0].hypot(d[1]) <= s[0].hypot(s[1]) {
            d
        } else {
            s
        }));
    }
    Some(Lattice {
        nearest_neighbour: spm_hal::Counts(
            step * b[0][0].hypot(b[0][1]).min(b[1][0].hypot(b[1][1])),
        ),
        vectors,
    })
}

/// Lattice directions of a standard whose LCS angle is `lcs_angle`: ⌊π / angle + ½⌋, at
/// least 2 (3 for 60°, 2 for 90°).
fn max_directions(lcs_angle: Radians) -> usize {
    ((std::f64::consts::PI / lcs_angle.value()).round() as usize).max(2)
}

/// The lattice directions of a frame's features by mode seeking: every pair closer than
/// [`LatticeConfig`]'s default factor (1.3) × the median nearest-neighbour distance gives a
/// vector, folded so that v and −v coincide; the vector with the most others within the
/// default angle tolerance (0.25 rad) of it seeds a direction, whose mean is refined three
/// times over the vectors within that tolerance of it; those vectors are removed and the
/// next direction sought, up to `max_directions` directions of at least `min_pairs` pairs.
///
/// `spm_features::lattice_vectors` clusters greedily around the first vector of each
/// cluster, which on a measured frame (HOPG terrace, ~11 pixels per lattice constant) split
/// one lattice direction into two clusters 10° apart and let a split half outrank a true
/// direction; seeking the densest direction first does not.
///
/// # Errors
/// A sentence when the frame has fewer than three features.
pub fn neighbour_directions(
    features: &[Feature],
    max_directions: usize,
    min_pairs: usize,
) -> Result<Lattice, String> {
    let config = LatticeConfig::default();
    let pos = spm_features::positions(features);
    let d_nn = spm_features::nearest_neighbour_distance(&pos);
    if pos.len() < 3 || !(d_nn.is_finite() && d_nn > 0.0) {
        return Err(format!("{} features: too few for a lattice", pos.len()));
    }
    // Every pair up to `limit` apart, folded so that v and −v coincide.
    let pairs_within = |limit: f64| {
        let mut out: Vec<(f64, f64)> = Vec::new();
        for (i, p) in pos.iter().enumerate() {
            for q in &pos[i + 1..] {
                let v = (q.0 - p.0, q.1 - p.1);
                let len = v.0.hypot(v.1);
                if len > 0.0 && len <= limit {
                    out.push(if v.0 < 0.0 || (v.0 == 0.0 && v.1 < 0.0) {
                        (-v.0, -v.1)
                    } else {
                        v
                    });
                }
            }
        }
        out
    };
    let mut remaining = pairs_within(config.max_neighbour_factor * d_nn);
    let cos_tol = config.angle_tolerance_rad.cos();
    // The members of the direction `m` (sign-aligned with it) and the rest.
    let split = |m: (f64, f64), from: &[(f64, f64)]| {
        let ml = m.0.hypot(m.1);
        let (mut members, mut rest) = (Vec::new(), Vec::new());
        for &w in from {
            let cos = (w.0 * m.0 + w.1 * m.1) / (ml * w.0.hypot(w.1));
            if cos.abs() >= cos_tol {
                members.push(if cos < 0.0 { (-w.0, -w.1) } else { w });
            } else {
                rest.push(w);
            }
        }
        (members, rest)
    };
    let mut vectors = Vec::new();
    while vectors.len() < max_directions {
        let Some(seed) = remaining
            .iter()
            .copied()
            .max_by_key(|&u| split(u, &remaining).0.len())
        else {
            break;
        };
        let mut mean = seed;
        for _ in 0..3 {
            let (members, _) = split(mean, &remaining);
            let n = members.len().max(1) as f64;
            mean = (
                members.iter().map(|w| w.0).sum::<f64>() / n,
                members.iter().map(|w| w.1).sum::<f64>() / n,
            );
        }
        let (members, rest) = split(mean, &remaining);
        if members.len() < min_pairs.max(2) {
            break;
        }
        vectors.push(mean_vector(&members));
        remaining = rest;
    }
    // A triangular lattice's third direction is the first two's difference (or sum), which
    // a strongly anisotropic image can make longer than the neighbour limit: Si_7x7_028's
    // slow axis stretches it to 1.42 × the nearest-neighbour distance, its pairs were
    // left out, and a sparse direction of stray pairs took its place (K̄y 50 % off). It is
    // measured where the first two predict it, over pairs up to twice that far.
    if max_directions == 3
        && let [v1, v2, ..] = vectors.as_slice()
    {
        let (a, b) = (v1.vector, v2.vector);
        let (ax, ay, bx, by) = (a.x.value(), a.y.value(), b.x.value(), b.y.value());
        let third = if ax * bx + ay * by > 0.0 {
            (ax - bx, ay - by)
        } else {
            (ax + bx, ay + by)
        };
        let length = third.0.hypot(third.1);
        let near: Vec<(f64, f64)> = pairs_within(2.0 * length)
            .into_iter()
            .filter(|w| {
                let l = w.0.hypot(w.1);
                (l / length - 1.0).abs() <= THIRD_LENGTH_TOLERANCE
            })
            .collect();
        let (members, _) = split(third, &near);
        if members.len() >= min_pairs.max(2) {
            let third = mean_vector(&members);
            vectors.truncate(2);
            vectors.push(third);
            vectors.sort_by_key(|v| std::cmp::Reverse(v.pairs));
        }
    }
    Ok(Lattice {
        vectors,
        nearest_neighbour: spm_hal::Counts(d_nn),
    })
}

/// Relative length window around the predicted third direction of a triangular lattice
/// ([`neighbour_directions`]): wide enough for a frame's scatter, narrow enough to leave the
/// next shell (√3 times longer in an undistorted lattice) out.
const THIRD_LENGTH_TOLERANCE: f64 = 0.25;

/// The mean of a direction's pair vectors (sign-aligned) and its standard error.
fn mean_vector(members: &[(f64, f64)]) -> LatticeVector {
    let n = members.len() as f64;
    let mean = (
        members.iter().map(|w| w.0).sum::<f64>() / n,
        members.iter().map(|w| w.1).sum::<f64>() / n,
    );
    let var = |c: fn(&(f64, f64)) -> f64, m: f64| {
        members.iter().map(|w| (c(w) - m).powi(2)).sum::<f64>() / (n - 1.0).max(1.0) / n
    };
    LatticeVector {
        vector: spm_hal::CountVector::from_counts(mean.0, mean.1),
        sigma: spm_hal::CountVector::from_counts(
            var(|w| w.0, mean.0).sqrt(),
            var(|w| w.1, mean.1).sqrt(),
        ),
        pairs: members.len(),
    }
}

/// Refuses the places whose lattice is far from the others': K̄x or K̄y off the median over
/// the places with a lattice by more than `length_tolerance` (relative), or α by more than
/// `angle_tolerance_rad`. A survey frame that mis-indexed its lattice (a direction lost
/// between clusters, features missed on one side of a step) gives a map tens of per cent
/// off and would drag the median (the HOPG terrace's right half: one place at K̄x/K 1.48
/// and α 31° beside others at 1.0 ± 0.1 and 3°–9°). With fewer than three places there is no median to judge by.
pub fn refuse_outliers(
    places: &mut [SurveyPlace],
    length_tolerance: f64,
    angle_tolerance_rad: f64,
) {
    let median = |f: fn(&SurveyLcc) -> f64| {
        let mut v: Vec<f64> = places
            .iter()
            .filter_map(|p| p.lcc.as_ref().map(f))
            .collect();
        spm_regression::median(&mut v).unwrap_or(f64::NAN)
    };
    if places.iter().filter(|p| p.lcc.is_some()).count() < 3 {
        return;
    }
    let kx = median(|l| l.kx_nm_per_count);
    let ky = median(|l| l.ky_nm_per_count);
    let alpha = median(|l| l.alpha_rad);
    for place in places.iter_mut() {
        let Some(l) = place.lcc else { continue };
        let (dx, dy) = (l.kx_nm_per_count / kx - 1.0, l.ky_nm_per_count / ky - 1.0);
        let da = l.alpha_rad - alpha;
        if dx.abs() > length_tolerance
            || dy.abs() > length_tolerance
            || da.abs() > angle_tolerance_rad
        {
            place.refusal = Some(format!(
                "an outlier: K̄x {:+.1} %, K̄y {:+.1} %, α {:+.1}° from the median of the places \
                 (tolerances {:.0} %, {:.1}°)",
                100.0 * dx,
                100.0 * dy,
                da.to_degrees(),
                100.0 * length_tolerance,
                angle_tolerance_rad.to_degrees()
            ));
            place.lcc = None;
        }
    }
}
