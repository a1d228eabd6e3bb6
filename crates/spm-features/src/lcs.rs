//! Recognition of local calibration structures (LCS): triangles A, B, C of
//! features whose true side lengths and angle are known.

use crate::detect::Feature;
use crate::error::{FeatureError, positive};
use serde::{Deserialize, Serialize};
use spm_hal::{CountPoint, CountVector, Counts, Nanometres, NmPerCount, NmPerCountMatrix, Radians};

/// HOPG β-atom lattice constant, nm.
pub const HOPG_LATTICE_NM: f64 = 0.2461;

/// A calibration standard's triangle: |AB|, |AC| and the angle BAC.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LcsStandard {
    /// True length of A→B.
    pub ab: Nanometres,
    /// True length of A→C.
    pub ac: Nanometres,
    /// True angle between A→B and A→C.
    pub angle_bac: Radians,
}

impl LcsStandard {
    /// Three neighbouring HOPG atoms: a = 0.2461 nm, 60°.
    pub fn hopg() -> Self {
        Self {
            ab: Nanometres(HOPG_LATTICE_NM),
            ac: Nanometres(HOPG_LATTICE_NM),
            angle_bac: Radians::from_degrees(60.0),
        }
    }
}

/// Settings of LCS recognition. Matching is done in counts, so the caller
/// gives an approximate nominal nm/count (the local coefficients are what is
/// being calibrated): tolerances must cover the scanner's nonlinearity and
/// nonorthogonality plus the drift distortion within one scan.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LcsConfig {
    /// The standard triangle.
    pub standard: LcsStandard,
    /// Approximate scanner sensitivity (same for x and y).
    pub nominal_sensitivity: NmPerCount,
    /// Accepted relative deviation of a side from its expected length in
    /// counts. Default 0.35.
    pub length_tolerance: f64,
    /// Accepted deviation of the angle BAC, rad. Default 0.35 (≈ 20°).
    pub angle_tolerance_rad: f64,
    /// The scanner's local calibration expected here, counts → nm up to a rotation, e.g.
    /// the last measured node's M = [[K̄x, K̄y·sin α], [0, K̄y·cos α]] (rows of nm/count).
    /// Candidates are then admitted through this map (the tolerances above apply to their
    /// sides and angle in nm) and still ranked through the nominal sensitivity, so the
    /// choice among the true LCSs (their orientation) does not depend on the prior. Where
    /// the local sensitivity is far from nominal (a scanner's edge), the true LCS fails the
    /// nominal tolerances while another triangle of features passes them; the neighbour's
    /// calibration tells them apart. `None` (default): admitted through the nominal
    /// sensitivity.
    #[serde(default)]
    pub prior: Option<NmPerCountMatrix>,
    /// The apparent lattice surveyed near here, as a map counts → nm up to a rotation
    /// (spm-calibration's survey: the nearest-neighbour vectors of a whole frame of the
    /// standard solved as an LCS). A candidate admitted above (through the prior or the
    /// nominal sensitivity) is accepted only when its sides and angle are also within the
    /// tolerances through this map: a triangle that is not a nearest-neighbour triangle of
    /// the lattice the image shows (a next-nearest neighbour √3 a away, a 120° pair, a
    /// triangle a wrong prior made look right) is refused. Without a prior, candidates are
    /// also admitted through this map instead of the nominal sensitivity (on the HOPG
    /// terrace, 11 % anisotropy and 5° obliquity put the true LCS outside a 10° tolerance
    /// around the nominal equilateral triangle). `None` (default): no gate.
    #[serde(default)]
    pub gate: Option<NmPerCountMatrix>,
}

impl LcsConfig {
    /// HOPG with the default tolerances and the given nominal nm/count.
    pub fn hopg(nominal_sensitivity: NmPerCount) -> Self {
        Self {
            standard: LcsStandard::hopg(),
            nominal_sensitivity,
            length_tolerance: 0.35,
            angle_tolerance_rad: 0.35,
            prior: None,
            gate: None,
        }
    }

    fn validate(&self) -> Result<(), FeatureError> {
        positive("nominal_sensitivity", self.nominal_sensitivity.value())?;
        positive("length_tolerance", self.length_tolerance)?;
        positive("angle_tolerance_rad", self.angle_tolerance_rad)?;
        positive("standard.ab", self.standard.ab.value())?;
        positive("standard.ac", self.standard.ac.value())?;
        positive("standard.angle_bac", self.standard.angle_bac.value())?;
        for (field, map) in [("prior", self.prior), ("gate", self.gate)] {
            if let Some(NmPerCountMatrix(m)) = map {
                let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
                if !(m.iter().flatten().all(|v| v.is_finite()) && det.is_finite() && det != 0.0) {
                    return Err(FeatureError::InvalidConfig {
                        field,
                        reason: "must be a finite, invertible 2×2 map",
                    });
                }
            }
        }
        Ok(())
    }

    /// The farthest a B or C can be from A, counts: the longer standard side stretched by
    /// the tolerance, through the nominal sensitivity or, with a prior, through its
    /// smallest singular value (the direction in which a nanometre takes the most counts).
    pub fn reach_counts(&self) -> f64 {
        let longest_nm = self.standard.ab.value().max(self.standard.ac.value());
        let nm_per_count = match self.prior {
            None => self.nominal_sensitivity.value(),
            Some(NmPerCountMatrix(m)) => {
                // σ_min² of M: the smaller eigenvalue of MᵀM.
                let (a, b, c, d) = (m[0][0], m[0][1], m[1][0], m[1][1]);
                let (p, q, r) = (a * a + c * c, a * b + c * d, b * b + d * d);
                let half_trace = 0.5 * (p + r);
                let root = (0.25 * (p - r).powi(2) + q * q).sqrt();
                (half_trace - root).max(0.0).sqrt()
            }
        };
        longest_nm * (1.0 + self.length_tolerance) / nm_per_count
    }

    /// Expected |AB| and |AC| in counts (through the nominal sensitivity).
    pub fn expected_counts(&self) -> (Counts, Counts) {
        (
            Counts(self.standard.ab.value() / self.nominal_sensitivity.value()),
            Counts(self.standard.ac.value() / self.nominal_sensitivity.value()),
        )
    }
}

/// A recognised LCS: indices into the feature list and its geometry in counts.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Lcs {
    /// Index of A.
    pub a: usize,
    /// Index of B.
    pub b: usize,
    /// Index of C.
    pub c: usize,
    /// A→B, counts (as seen in the frame: not drift-free).
    pub ab: CountVector,
    /// A→C, counts.
    pub ac: CountVector,
    /// The gravity centre of A, B, C, counts.
    pub centroid: CountPoint,
    /// Normalised mismatch to the standard through the nominal sensitivity (0 = exact at
    /// nominal nm/count; the ranking key).
    pub mismatch: f64,
}

/// Relative deviations of the sides and the angle deviation, rad, of the triangle A→B, A→C
/// from the standard once mapped through `m` (counts → nm).
fn deviations_through(
    NmPerCountMatrix(m): NmPerCountMatrix,
    ab: CountVector,
    ac: CountVector,
    standard: &LcsStandard,
) -> (f64, f64, f64) {
    let map = |v: CountVector| {
        let (x, y) = (v.x.value(), v.y.value());
        (m[0][0] * x + m[0][1] * y, m[1][0] * x + m[1][1] * y)
    };
    let (ab_nm, ac_nm) = (map(ab), map(ac));
    let cross_nm = ab_nm.0 * ac_nm.1 - ab_nm.1 * ac_nm.0;
    let angle_nm = cross_nm.abs().atan2(ab_nm.0 * ac_nm.0 + ab_nm.1 * ac_nm.1);
    (
        ab_nm.0.hypot(ab_nm.1) / standard.ab.value() - 1.0,
        ac_nm.0.hypot(ac_nm.1) / standard.ac.value() - 1.0,
        angle_nm - standard.angle_bac.value(),
    )
}

fn within_tolerances((dab, dac, dangle): (f64, f64, f64), config: &LcsConfig) -> bool {
    dab.abs() <= config.length_tolerance
        && dac.abs() <= config.length_tolerance
        && dangle.abs() <= config.angle_tolerance_rad
}

/// The triangle A, B, C when admitted (through the prior or the nominal sensitivity), with
/// whether it also passes the gate (true without one).
fn triangle(
    features: &[Feature],
    a: usize,
    b: usize,
    c: usize,
    config: &LcsConfig,
) -> Option<(Lcs, bool)> {
    let (pa, pb, pc) = (
        features.get(a)?.position,
        features.get(b)?.position,
        features.get(c)?.position,
    );
    let (ab, ac) = (pb - pa, pc - pa);
    let (lab, lac) = (ab.norm().value(), ac.norm().value());
    if lab <= 0.0 || lac <= 0.0 {
        return None;
    }
    // Against the standard through the nominal sensitivity: the ranking (and, without a
    // prior, the admission).
    let (eab, eac) = config.expected_counts();
    let cross = ab.x.value() * ac.y.value() - ab.y.value() * ac.x.value();
    let angle = cross.abs().atan2(ab.dot_counts_squared(ac));
    let nominal = (
        lab / eab.value() - 1.0,
        lac / eac.value() - 1.0,
        angle - config.standard.angle_bac.value(),
    );
    // The admission: through the prior when there is one, else through the gate's map (a
    // survey of the lattice is a better first guess than the nominal sensitivity).
    let admission = match config.prior.or(config.gate) {
        None => nominal,
        Some(m) => deviations_through(m, ab, ac, &config.standard),
    };
    if !within_tolerances(admission, config) {
        return None;
    }
    let gate_passed = config
        .gate
        .is_none_or(|m| within_tolerances(deviations_through(m, ab, ac, &config.standard), config));
    let mismatch = (nominal.0 / config.length_tolerance).powi(2)
        + (nominal.1 / config.length_tolerance).powi(2)
        + (nominal.2 / config.angle_tolerance_rad).powi(2);
    let lcs = Lcs {
        a,
        b,
        c,
        ab,
        ac,
        centroid: CountPoint::from_counts(
            (pa.x.value() + pb.x.value() + pc.x.value()) / 3.0,
            (pa.y.value() + pb.y.value() + pc.y.value()) / 3.0,
        ),
        mismatch,
    };
    Some((lcs, gate_passed))
}

/// The LCS candidates with one vertex: those accepted, and those admitted through the
/// prior or the nominal sensitivity but refused by the gate ([`LcsConfig::gate`]). Each
/// list is sorted by mismatch.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LcsCandidates {
    /// Accepted LCSs, best first.
    pub accepted: Vec<Lcs>,
    /// Candidates the gate refused, best first (empty without a gate).
    pub refused_by_gate: Vec<Lcs>,
}

impl LcsCandidates {
    /// True when the candidate recognition would have chosen without the gate (the best
    /// mismatch of both lists) is one the gate refused: a misrecognition prevented.
    pub fn best_refused_by_gate(&self) -> bool {
        match (self.accepted.first(), self.refused_by_gate.first()) {
            (_, None) => false,
            (None, Some(_)) => true,
            (Some(a), Some(r)) => r.mismatch < a.mismatch,
        }
    }
}

/// Every LCS candidate with vertex `a`, split by the gate (see [`lcs_with_vertex`]).
pub fn lcs_candidates(
    features: &[Feature],
    a: usize,
    config: &LcsConfig,
) -> Result<LcsCandidates, FeatureError> {
    config.validate()?;
    let Some(pa) = features.get(a).map(|f| f.position) else {
        return Err(FeatureError::IndexOutOfRange {
            index: a,
            len: features.len(),
        });
    };
    let reach = config.reach_counts();
    let near: Vec<usize> = (0..features.len())
        .filter(|&j| j != a && features[j].position.distance(pa).value() <= reach)
        .collect();
    let mut out = LcsCandidates::default();
    for &b in &near {
        for &c in &near {
            if b == c {
                continue;
            }
            let Some((t, gate_passed)) = triangle(features, a, b, c, config) else {
                continue;
            };
            let cross = t.ab.x.value() * t.ac.y.value() - t.ab.y.value() * t.ac.x.value();
            if cross < 0.0 && triangle(features, a, c, b, config).is_some() {
                continue; // the counter-clockwise ordering is kept instead
            }
            if gate_passed {
                out.accepted.push(t);
            } else {
                out.refused_by_gate.push(t);
            }
        }
    }
    out.accepted
        .sort_by(|x, y| x.mismatch.total_cmp(&y.mismatch));
    out.refused_by_gate
        .sort_by(|x, y| x.mismatch.total_cmp(&y.mismatch));
    Ok(out)
}

/// Every LCS with vertex `a` (B, C among the other features) that passes the admission and
/// the gate. When both orderings (B, C) and (C, B) match (equal sides), the one turning
/// counter-clockwise from A→B to A→C is kept. Sorted by mismatch.
pub fn lcs_with_vertex(
    features: &[Feature],
    a: usize,
    config: &LcsConfig,
) -> Result<Vec<Lcs>, FeatureError> {
    Ok(lcs_candidates(features, a, config)?.accepted)
}

/// Every neighbour of `a` that forms an LCS with it (as B or C), sorted by index.
pub fn lcs_neighbours(
    features: &[Feature],
    a: usize,
    config: &LcsConfig,
) -> Result<Vec<usize>, FeatureError> {
    let mut out: Vec<usize> = lcs_with_vertex(features, a, config)?
        .iter()
        .flat_map(|t| [t.b, t.c])
        .collect();
    out.sort_unstable();
    out.dedup();
    Ok(out)
}

/// The LCS whose gravity centre is nearest `point` (paper §2.1.2: among
/// several structures near the node, the closest is used); ties go to the
/// smaller mismatch. `None` when no triangle matches.
pub fn find_lcs_nearest(
    features: &[Feature],
    point: CountPoint,
    config: &LcsConfig,
) -> Result<Option<Lcs>, FeatureError> {
    config.validate()?;
    let mut best: Option<(f64, Lcs)> = None;
    for a in 0..features.len() {
        for t in lcs_with_vertex(features, a, config)? {
            let d = t.centroid.distance(point).value();
            let better = match &best {
                None => true,
                Some((bd, bt)) => {
                    d < bd - 1e-9 || ((d - bd).abs() <= 1e-9 && t.mismatch < bt.mismatch)
                }
            };
            if better {
                best = Some((d, t));
            }
        }
    }
    Ok(best.map(|(_, t)| t))
}

/// The LCS with vertex A = the feature nearest `point` (the captured
/// feature), best mismatch first. `None` when there are no features or no
/// triangle at that vertex.
pub fn find_lcs_at_nearest_vertex(
    features: &[Feature],
    point: CountPoint,
    config: &LcsConfig,
) -> Result<Option<Lcs>, FeatureError> {
    let Some(a) = crate::detect::nearest_index(features, point) else {
        return Ok(None);
    };
    Ok(lcs_with_vertex(features, a, config)?.into_iter().next())
}
