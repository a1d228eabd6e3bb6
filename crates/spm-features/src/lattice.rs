//! Lattice vectors of a frame from neighbour statistics.

use crate::detect::Feature;
use crate::error::{FeatureError, positive};
use serde::{Deserialize, Serialize};
use spm_hal::{CountVector, Counts};

/// Settings of [`lattice_vectors`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LatticeConfig {
    /// Pairs longer than this factor times the median nearest-neighbour
    /// distance are ignored. Default 1.3 (first neighbour shell only).
    pub max_neighbour_factor: f64,
    /// Pair vectors within this angle of a cluster's direction join it, rad.
    /// Default 0.25 rad (≈ 14°).
    pub angle_tolerance_rad: f64,
    /// A direction needs this many pairs to count as a lattice vector. Default 2.
    pub min_pairs: usize,
}

impl Default for LatticeConfig {
    fn default() -> Self {
        Self {
            max_neighbour_factor: 1.3,
            angle_tolerance_rad: 0.25,
            min_pairs: 2,
        }
    }
}

/// One lattice direction: the mean neighbour vector and its uncertainty.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LatticeVector {
    /// Mean vector, counts (oriented with angle in (−π/2, π/2]).
    pub vector: CountVector,
    /// Standard error of the mean per component, counts.
    pub sigma: CountVector,
    /// Number of feature pairs averaged.
    pub pairs: usize,
}

/// The lattice of a frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Lattice {
    /// Lattice directions found, most populated first (three for a hexagonal
    /// lattice, two for a square one).
    pub vectors: Vec<LatticeVector>,
    /// Median nearest-neighbour distance, counts.
    pub nearest_neighbour: Counts,
}

impl Lattice {
    /// A basis: the two most populated directions, or `None` with fewer than two.
    pub fn basis(&self) -> Option<(LatticeVector, LatticeVector)> {
        match self.vectors.as_slice() {
            [a, b, ..] => Some((*a, *b)),
            _ => None,
        }
    }
}

/// Neighbour vectors of one direction ([`neighbour_vector_clusters`]): folded into one
/// half-plane and summed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VectorCluster {
    /// The first vector of the cluster (the direction the others are compared with).
    pub reference: (f64, f64),
    /// The sum of its vectors, each turned to point along `reference`.
    pub sum: (f64, f64),
    /// The sum of their squared components.
    pub sum_sq: (f64, f64),
    /// How many vectors.
    pub n: usize,
}

impl VectorCluster {
    /// The mean vector.
    #[must_use]
    pub fn mean(&self) -> (f64, f64) {
        (self.sum.0 / self.n as f64, self.sum.1 / self.n as f64)
    }
}

/// The lattice-basis estimator's one kernel (lattice vectors of detected features, the model
/// check's basis of a point set): the difference vector of every pair of `pos` whose length
/// `keep_length` accepts, folded so that v and −v coincide (into x > 0, or x = 0 and y > 0),
/// clustered by direction — a vector joins the first cluster whose reference it is parallel or
/// antiparallel to by `parallel(|cos|)`, else it starts one. Clusters in the order found.
pub fn neighbour_vector_clusters(
    pos: &[(f64, f64)],
    keep_length: impl Fn(f64) -> bool,
    parallel: impl Fn(f64) -> bool,
) -> Vec<VectorCluster> {
    let mut clusters: Vec<VectorCluster> = Vec::new();
    for i in 0..pos.len() {
        for j in i + 1..pos.len() {
            let mut v = (pos[j].0 - pos[i].0, pos[j].1 - pos[i].1);
            let len = v.0.hypot(v.1);
            if !keep_length(len) {
                continue;
            }
            // Fold into the half-plane x > 0 (or x = 0, y > 0).
            if v.0 < 0.0 || (v.0 == 0.0 && v.1 < 0.0) {
                v = (-v.0, -v.1);
            }
            let mut placed = false;
            for cluster in &mut clusters {
                let r = cluster.reference;
                let rl = r.0.hypot(r.1);
                let cos = (v.0 * r.0 + v.1 * r.1) / (len * rl);
                if parallel(cos.abs()) {
                    let w = if cos < 0.0 { (-v.0, -v.1) } else { v };
                    cluster.sum.0 += w.0;
                    cluster.sum.1 += w.1;
                    cluster.sum_sq.0 += w.0 * w.0;
                    cluster.sum_sq.1 += w.1 * w.1;
                    cluster.n += 1;
                    placed = true;
                    break;
                }
            }
            if !placed {
                clusters.push(VectorCluster {
                    reference: v,
                    sum: v,
                    sum_sq: (v.0 * v.0, v.1 * v.1),
                    n: 1,
                });
            }
        }
    }
    clusters
}

/// Feature positions as `(x, y)` counts.
pub fn positions(features: &[Feature]) -> Vec<(f64, f64)> {
    features
        .iter()
        .map(|f| (f.position.x.value(), f.position.y.value()))
        .collect()
}

/// The typical nearest-neighbour distance of a set of positions, counts: the upper median of
/// each position's distance to its nearest other one (NaN for fewer than two positions).
pub fn nearest_neighbour_distance(pos: &[(f64, f64)]) -> f64 {
    let mut nearest: Vec<f64> = pos
        .iter()
        .enumerate()
        .map(|(i, p)| {
            pos.iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, q)| (q.0 - p.0).hypot(q.1 - p.1))
                .fold(f64::INFINITY, f64::min)
        })
        .collect();
    spm_regression::upper_median(&mut nearest).unwrap_or(f64::NAN)
}

/// Lattice vectors from the statistics of neighbour pairs: every pair closer
/// than `max_neighbour_factor` × the median nearest-neighbour distance gives a
/// vector (folded so v and −v coincide); vectors are clustered by direction;
/// each cluster's mean is a lattice vector with its standard error.
///
/// Positions within one frame carry drift (features are scanned at different
/// times), so these vectors are approximate; skipping measures them drift-free.
pub fn lattice_vectors(
    features: &[Feature],
    config: &LatticeConfig,
) -> Result<Lattice, FeatureError> {
    positive("max_neighbour_factor", config.max_neighbour_factor)?;
    positive("angle_tolerance_rad", config.angle_tolerance_rad)?;
    if features.len() < 3 {
        return Err(FeatureError::TooFewFeatures {
            needed: 3,
            found: features.len(),
        });
    }
    let pos = positions(features);
    let d_nn = nearest_neighbour_distance(&pos);
    if !(d_nn.is_finite() && d_nn > 0.0) {
        return Err(FeatureError::TooFewFeatures {
            needed: 3,
            found: features.len(),
        });
    }
    let max_len = config.max_neighbour_factor * d_nn;
    let cos_tol = config.angle_tolerance_rad.cos();
    let clusters = neighbour_vector_clusters(
        &pos,
        |len| !(len > max_len || len <= 0.0),
        |cos_abs| cos_abs >= cos_tol,
    );
    let mut vectors: Vec<LatticeVector> = clusters
        .iter()
        .filter(|c| c.n >= config.min_pairs.max(1))
        .map(|c| {
            let n = c.n as f64;
            let mean = (c.sum.0 / n, c.sum.1 / n);
            let var = |sq: f64, m: f64| {
                if c.n > 1 {
                    ((sq - n * m * m) / (n - 1.0)).max(0.0) / n
                } else {
                    0.0
                }
            };
            LatticeVector {
                vector: CountVector::from_counts(mean.0, mean.1),
                sigma: CountVector::from_counts(
                    var(c.sum_sq.0, mean.0).sqrt(),
                    var(c.sum_sq.1, mean.1).sqrt(),
                ),
                pairs: c.n,
            }
        })
        .collect();
    vectors.sort_by_key(|v| std::cmp::Reverse(v.pairs));
    Ok(Lattice {
        vectors,
        nearest_neighbour: Counts(d_nn),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 4 × 3 triangular lattice with a = 2 (rows along x): the nearest-neighbour pairs fall
    /// into the three directions 0°, 60° and 120°, folded into the right half-plane, with the
    /// exact counts of a 4 × 3 patch; a window that keeps nothing gives no cluster.
    #[test]
    fn neighbour_vectors_of_a_triangular_patch_cluster_into_its_three_directions() {
        let a = 2.0;
        let h = a * 3f64.sqrt() / 2.0;
        let pos: Vec<(f64, f64)> = (0..3)
            .flat_map(|r| {
                (0..4).map(move |c| {
                    (
                        a * f64::from(c) + 0.5 * a * f64::from(r % 2),
                        h * f64::from(r),
                    )
                })
            })
            .collect();
        let clusters =
            neighbour_vector_clusters(&pos, |len| len > 0.9 * a && len < 1.1 * a, |c| c > 0.99);
        assert_eq!(clusters.len(), 3, "{clusters:?}");
        // Along x: 3 pairs per row × 3 rows; each oblique direction: 4 + 3 pairs between
        // two rows.
        let expect = [((a, 0.0), 9), ((0.5 * a, h), 7), ((0.5 * a, -h), 7)];
        for (mean, n) in expect {
            let hit = clusters.iter().find(|c| {
                let m = c.mean();
                (m.0 - mean.0).abs() < 1e-12 && (m.1 - mean.1).abs() < 1e-12
            });
            assert_eq!(hit.map(|c| c.n), Some(n), "{mean:?} in {clusters:?}");
        }
        assert!(neighbour_vector_clusters(&pos, |_| false, |_| true).is_empty());
    }
}
