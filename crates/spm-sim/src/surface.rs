//! Sample surfaces: height z (nm) as a function of the sample position (nm),
//! and the true feature sites the oracle exposes.
//!
//! - **HOPG**: the β-atom triangular lattice (a = 0.2461 nm) as a sum of three
//!   cosines plus a three-sine term that makes the hollow sites deeper than the
//!   α-atom sites: `z = A·[Σ cos φⱼ + b·Σ sin φⱼ]`, `φⱼ = kⱼ·(r − r₀)`, `kⱼ` the
//!   three reciprocal vectors at 120° (`|k| = 4π/(a√3)`). Maxima (hills) are
//!   exactly at the β atoms `r₀ + n·a₁ + m·a₂`, the deepest minima (pits) exactly
//!   at the hollows `r₀ + 2(a₁ + a₂)/3`, the α atoms `r₀ + (a₁ + a₂)/3` are
//!   shallower minima. `A` is set so that atom-to-hollow is the configured
//!   corrugation. Monatomic steps are smooth straight edges (`step·½(1 +
//!   s/√(s² + w²))`, s the signed distance); every layer up shifts the lattice
//!   registry by `(a₁ + a₂)/3` (AB stacking). Vacancies remove a β atom
//!   (a Gaussian depression of the corrugation's depth, σ = 0.35·a) at sites
//!   picked by a hash of the site index; rotated circular domains have their
//!   own lattice orientation.
//! - **Si(111)-7×7**: Gaussian corner holes (pits) on a 2.688 nm triangular lattice.
//! - **Generic hex / square lattices** of Gaussian hills or pits.

use crate::config::{HopgConfig, LatticeConfig, Si7x7Config, SurfaceConfig};
use serde::{Deserialize, Serialize};
use spm_hal::NmPoint;
use std::f64::consts::PI;

/// What a feature site is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FeatureKind {
    /// A HOPG β atom (a hill).
    Atom,
    /// A HOPG hollow site (a pit).
    Hollow,
    /// A Si(111)-7×7 corner hole (a pit).
    CornerHole,
    /// A hill of a generic lattice.
    Hill,
    /// A pit of a generic lattice.
    Pit,
}

impl FeatureKind {
    /// True for hills (height maxima), false for pits.
    pub fn is_hill(self) -> bool {
        matches!(self, Self::Atom | Self::Hill)
    }
}

/// One true feature of the surface.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FeatureSite {
    /// Where it is in sample coordinates, nm.
    pub position: NmPoint,
    /// What it is.
    pub kind: FeatureKind,
    /// Terrace index (0 = reference layer, +1 one step up).
    pub terrace: i32,
    /// Index of the rotated domain holding it, `None` for the main lattice.
    pub domain: Option<usize>,
}

/// A 2-D Bravais lattice with its inverse and reciprocal vectors.
#[derive(Clone, Copy, Debug)]
struct Lattice {
    a1: [f64; 2],
    a2: [f64; 2],
    /// Rows of the inverse of [a1 a2]: fractional coordinates = inv · r.
    inv: [[f64; 2]; 2],
    /// Reciprocal vectors (a_i · b_j = 2π δ_ij).
    b1: [f64; 2],
    b2: [f64; 2],
    /// Origin (a lattice site), nm.
    origin: [f64; 2],
}

impl Lattice {
    fn new(a1: [f64; 2], a2: [f64; 2], origin: [f64; 2]) -> Self {
        let det = a1[0] * a2[1] - a1[1] * a2[0];
        let inv = [[a2[1] / det, -a2[0] / det], [-a1[1] / det, a1[0] / det]];
        let b1 = [2.0 * PI * inv[0][0], 2.0 * PI * inv[0][1]];
        let b2 = [2.0 * PI * inv[1][0], 2.0 * PI * inv[1][1]];
        Self {
            a1,
            a2,
            inv,
            b1,
            b2,
            origin,
        }
    }

    fn hexagonal(a: f64, rotation_rad: f64, origin: [f64; 2]) -> Self {
        let (s, c) = rotation_rad.sin_cos();
        let (s6, c6) = (rotation_rad + PI / 3.0).sin_cos();
        Self::new([a * c, a * s], [a * c6, a * s6], origin)
    }

    fn square(a: f64, rotation_rad: f64, origin: [f64; 2]) -> Self {
        let (s, c) = rotation_rad.sin_cos();
        Self::new([a * c, a * s], [-a * s, a * c], origin)
    }

    #[inline]
    fn fractional(&self, x: f64, y: f64) -> (f64, f64) {
        let dx = x - self.origin[0];
        let dy = y - self.origin[1];
        (
            self.inv[0][0] * dx + self.inv[0][1] * dy,
            self.inv[1][0] * dx + self.inv[1][1] * dy,
        )
    }

    #[inline]
    fn site(&self, i: f64, j: f64) -> [f64; 2] {
        [
            self.origin[0] + i * self.a1[0] + j * self.a2[0],
            self.origin[1] + i * self.a1[1] + j * self.a2[1],
        ]
    }

    fn shifted(&self, fi: f64, fj: f64) -> Self {
        let o = self.site(fi, fj);
        Self { origin: o, ..*self }
    }

    /// Site indices whose sites may lie within `radius` of (x, y).
    fn index_box(&self, x: f64, y: f64, radius: f64) -> (i64, i64, i64, i64) {
        let (fi, fj) = self.fractional(x, y);
        // Generous bound: the lattice's shortest height limits the index range.
        let area = (self.a1[0] * self.a2[1] - self.a1[1] * self.a2[0]).abs();
        let l1 = self.a1[0].hypot(self.a1[1]);
        let l2 = self.a2[0].hypot(self.a2[1]);
        let h = area / l1.max(l2);
        let n = (radius / h).ceil() + 1.0;
        (
            (fi - n).floor() as i64,
            (fi + n).ceil() as i64,
            (fj - n).floor() as i64,
            (fj + n).ceil() as i64,
        )
    }
}

/// sin and cos together, accurate to ~1e-14 for |x| < 2²⁰ (phases of
/// sample positions up to ~30 µm): Cody–Waite reduction by π/2 with the
/// fdlibm 33-bit split, Taylor polynomials on [−π/4, π/4]. About twice as
/// fast as libm's `sincos` in the pixel loop.
#[inline]
fn fast_sin_cos(x: f64) -> (f64, f64) {
    const FRAC_2_PI: f64 = std::f64::consts::FRAC_2_PI;
    const PIO2_1: f64 = 1.570_796_326_734_125_6;
    const PIO2_1T: f64 = 6.077_100_506_506_192e-11;
    const MAGIC: f64 = 6_755_399_441_055_744.0; // 1.5·2⁵², rounds to nearest
    if x.is_nan() || x.abs() >= 1_048_576.0 {
        return x.sin_cos();
    }
    let k = (x * FRAC_2_PI + MAGIC) - MAGIC;
    let r = (x - k * PIO2_1) - k * PIO2_1T;
    let r2 = r * r;
    let s = r
        * (1.0
            + r2 * (-1.0 / 6.0
                + r2 * (1.0 / 120.0
                    + r2 * (-1.0 / 5040.0
                        + r2 * (1.0 / 362_880.0
                            + r2 * (-1.0 / 39_916_800.0 + r2 * (1.0 / 6_227_020_800.0)))))));
    let c = 1.0
        + r2 * (-0.5
            + r2 * (1.0 / 24.0
                + r2 * (-1.0 / 720.0
                    + r2 * (1.0 / 40_320.0
                        + r2 * (-1.0 / 3_628_800.0
                            + r2 * (1.0 / 479_001_600.0 - r2 / 87_178_291_200.0))))));
    match (k as i64) & 3 {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    }
}

/// `floor` via a truncating cast (libm call avoided) for |x| < 2⁵¹.
#[inline]
fn fast_floor(x: f64) -> f64 {
    if x.abs() < 2_251_799_813_685_248.0 {
        let t = (x as i64) as f64;
        if t > x { t - 1.0 } else { t }
    } else {
        x.floor()
    }
}

#[inline]
fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

#[derive(Clone, Debug)]
struct StepEdge {
    point: [f64; 2],
    /// Unit left normal of the edge direction.
    normal: [f64; 2],
    width_nm: f64,
}

#[derive(Clone, Debug)]
struct Domain {
    centre: [f64; 2],
    radius_sq: f64,
    /// The domain's lattice (terrace 0 registry).
    lattice: Lattice,
}

#[derive(Clone, Debug)]
struct Hopg {
    lattice: Lattice,
    amplitude_nm: f64,
    asymmetry: f64,
    step_height_nm: f64,
    steps: Vec<StepEdge>,
    vacancy_threshold: u64,
    vacancy_depth_nm: f64,
    vacancy_inv_two_sigma_sq: f64,
    domains: Vec<Domain>,
    seed: u64,
}

#[derive(Clone, Debug)]
struct GaussianLattice {
    lattice: Lattice,
    height_nm: f64,
    inv_two_sigma_sq: f64,
    /// Half-width of the index window summed around a point.
    window: i64,
    kind: FeatureKind,
}

#[derive(Clone, Debug)]
enum Model {
    Hopg(Box<Hopg>),
    Gaussian(GaussianLattice),
}

/// A sample surface. Cheap to evaluate; immutable after construction.
#[derive(Clone, Debug)]
pub struct Surface {
    model: Model,
}

impl Surface {
    /// Builds the surface of a validated config; `seed` picks the vacancy sites.
    pub fn from_config(config: &SurfaceConfig, seed: u64) -> Self {
        let model = match config {
            SurfaceConfig::Hopg(h) => Model::Hopg(Box::new(Hopg::new(h, seed))),
            SurfaceConfig::Si7x7(s) => Model::Gaussian(GaussianLattice::si7x7(s)),
            SurfaceConfig::HexLattice(l) => Model::Gaussian(GaussianLattice::generic(l, true)),
            SurfaceConfig::SquareLattice(l) => Model::Gaussian(GaussianLattice::generic(l, false)),
        };
        Self { model }
    }

    /// Height of the surface at sample position (x, y), nm.
    #[inline]
    pub fn height_nm(&self, x_nm: f64, y_nm: f64) -> f64 {
        match &self.model {
            Model::Hopg(h) => h.height(x_nm, y_nm),
            Model::Gaussian(g) => g.height(x_nm, y_nm),
        }
    }

    /// The nominal lattice constant of the main lattice, nm.
    pub fn lattice_constant_nm(&self) -> f64 {
        let l = match &self.model {
            Model::Hopg(h) => &h.lattice,
            Model::Gaussian(g) => &g.lattice,
        };
        l.a1[0].hypot(l.a1[1])
    }

    /// The main lattice's primitive vectors a₁, a₂ in sample coordinates, nm.
    pub fn lattice_vectors_nm(&self) -> (NmPoint, NmPoint) {
        let l = match &self.model {
            Model::Hopg(h) => &h.lattice,
            Model::Gaussian(g) => &g.lattice,
        };
        (
            NmPoint::from_nm(l.a1[0], l.a1[1]),
            NmPoint::from_nm(l.a2[0], l.a2[1]),
        )
    }

    /// True feature sites (hills and pits; vacant atoms excluded) within
    /// `radius_nm` of `centre`, nearest first.
    pub fn features_near(&self, centre: NmPoint, radius_nm: f64) -> Vec<FeatureSite> {
        let (x, y) = (centre.x.value(), centre.y.value());
        let mut out = match &self.model {
            Model::Hopg(h) => h.features(x, y, radius_nm),
            Model::Gaussian(g) => g.features(x, y, radius_nm),
        };
        out.sort_by(|a, b| {
            let da = centre.distance(a.position).value();
            let db = centre.distance(b.position).value();
            da.total_cmp(&db)
        });
        out
    }
}

impl Hopg {
    fn new(c: &HopgConfig, seed: u64) -> Self {
        let lattice = Lattice::hexagonal(
            c.lattice_constant_nm,
            c.rotation_deg.to_radians(),
            [0.0, 0.0],
        );
        let p2v = 4.5 + 1.5 * 3f64.sqrt() * c.hollow_asymmetry;
        let steps = c
            .steps
            .iter()
            .map(|s| {
                let (sn, cs) = s.direction_deg.to_radians().sin_cos();
                StepEdge {
                    point: [s.point_x_nm, s.point_y_nm],
                    normal: [-sn, cs],
                    width_nm: s.width_nm,
                }
            })
            .collect();
        let domains = c
            .domains
            .iter()
            .map(|d| Domain {
                centre: [d.centre_x_nm, d.centre_y_nm],
                radius_sq: d.radius_nm * d.radius_nm,
                lattice: Lattice::hexagonal(
                    c.lattice_constant_nm,
                    (c.rotation_deg + d.rotation_deg).to_radians(),
                    [d.centre_x_nm, d.centre_y_nm],
                ),
            })
            .collect();
        let sigma = 0.35 * c.lattice_constant_nm;
        Self {
            lattice,
            amplitude_nm: c.corrugation_nm / p2v,
            asymmetry: c.hollow_asymmetry,
            step_height_nm: c.step_height_nm,
            steps,
            vacancy_threshold: (c.vacancy_fraction.clamp(0.0, 1.0) * u64::MAX as f64) as u64,
            vacancy_depth_nm: c.corrugation_nm,
            vacancy_inv_two_sigma_sq: 1.0 / (2.0 * sigma * sigma),
            domains,
            seed: splitmix(seed ^ 0x0005_EED0_FA70),
        }
    }

    /// Terrace index (sharp) and smooth step height at (x, y).
    #[inline]
    fn terrace(&self, x: f64, y: f64) -> (i32, f64) {
        let mut index = 0;
        let mut height = 0.0;
        for s in &self.steps {
            let d = (x - s.point[0]) * s.normal[0] + (y - s.point[1]) * s.normal[1];
            if d >= 0.0 {
                index += 1;
            }
            height += 0.5 * (1.0 + d / (d * d + s.width_nm * s.width_nm).sqrt());
        }
        (index, height * self.step_height_nm)
    }

    #[inline]
    fn domain_at(&self, x: f64, y: f64) -> Option<usize> {
        self.domains.iter().position(|d| {
            let dx = x - d.centre[0];
            let dy = y - d.centre[1];
            dx * dx + dy * dy <= d.radius_sq
        })
    }

    /// The lattice of β atoms in force for a terrace and domain.
    #[inline]
    fn lattice_for(&self, terrace: i32, domain: Option<usize>) -> Lattice {
        let base = match domain.and_then(|d| self.domains.get(d)) {
            Some(d) => d.lattice,
            None => self.lattice,
        };
        if terrace.rem_euclid(2) == 1 {
            base.shifted(1.0 / 3.0, 1.0 / 3.0)
        } else {
            base
        }
    }

    #[inline]
    fn is_vacant(&self, i: i64, j: i64, terrace: i32, domain: Option<usize>) -> bool {
        if self.vacancy_threshold == 0 {
            return false;
        }
        let key = splitmix(
            self.seed
                ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
                ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
                ^ ((terrace as i64 as u64) << 40)
                ^ (domain.map_or(0, |d| d as u64 + 1) << 52),
        );
        key < self.vacancy_threshold
    }

    #[inline]
    fn height(&self, x: f64, y: f64) -> f64 {
        let (terrace, step_height) = if self.steps.is_empty() {
            (0, 0.0)
        } else {
            self.terrace(x, y)
        };
        let domain = if self.domains.is_empty() {
            None
        } else {
            self.domain_at(x, y)
        };
        let lattice = if terrace == 0 && domain.is_none() {
            self.lattice
        } else {
            self.lattice_for(terrace, domain)
        };
        let dx = x - lattice.origin[0];
        let dy = y - lattice.origin[1];
        let p1 = lattice.b1[0] * dx + lattice.b1[1] * dy;
        let p2 = lattice.b2[0] * dx + lattice.b2[1] * dy;
        let (s1, c1) = fast_sin_cos(p1);
        let (s2, c2) = fast_sin_cos(p2);
        // φ3 = −φ1 − φ2.
        let c3 = c1 * c2 - s1 * s2;
        let s3 = -(s1 * c2 + c1 * s2);
        let mut z = self.amplitude_nm * ((c1 + c2 + c3) + self.asymmetry * (s1 + s2 + s3));
        if self.vacancy_threshold > 0 {
            let (fi, fj) = lattice.fractional(x, y);
            let (i0, j0) = (fast_floor(fi), fast_floor(fj));
            for (di, dj) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
                let (i, j) = (i0 + di, j0 + dj);
                if self.is_vacant(i as i64, j as i64, terrace, domain) {
                    let s = lattice.site(i, j);
                    let r2 = (x - s[0]).powi(2) + (y - s[1]).powi(2);
                    z -= self.vacancy_depth_nm * (-r2 * self.vacancy_inv_two_sigma_sq).exp();
                }
            }
        }
        z + step_height
    }

    fn features(&self, x: f64, y: f64, radius: f64) -> Vec<FeatureSite> {
        let mut out = Vec::new();
        let r2max = radius * radius;
        let mut domains: Vec<Option<usize>> = vec![None];
        domains.extend((0..self.domains.len()).map(Some));
        let max_terrace = self.steps.len() as i32;
        for domain in domains {
            for terrace in 0..=max_terrace {
                let lattice = self.lattice_for(terrace, domain);
                let (i0, i1, j0, j1) = lattice.index_box(x, y, radius);
                for i in i0..=i1 {
                    for j in j0..=j1 {
                        let (fi, fj) = (i as f64, j as f64);
                        for (kind, offset) in
                            [(FeatureKind::Atom, 0.0), (FeatureKind::Hollow, 2.0 / 3.0)]
                        {
                            let s = lattice.site(fi + offset, fj + offset);
                            let r2 = (s[0] - x).powi(2) + (s[1] - y).powi(2);
                            if r2 > r2max {
                                continue;
                            }
                            let here_terrace = if self.steps.is_empty() {
                                0
                            } else {
                                self.terrace(s[0], s[1]).0
                            };
                            let here_domain = self.domain_at(s[0], s[1]);
                            if here_terrace != terrace || here_domain != domain {
                                continue;
                            }
                            if kind == FeatureKind::Atom && self.is_vacant(i, j, terrace, domain) {
                                continue;
                            }
                            out.push(FeatureSite {
                                position: NmPoint::from_nm(s[0], s[1]),
                                kind,
                                terrace,
                                domain,
                            });
                        }
                    }
                }
            }
        }
        out
    }
}

impl GaussianLattice {
    fn si7x7(c: &Si7x7Config) -> Self {
        let lattice = Lattice::hexagonal(
            c.lattice_constant_nm,
            c.rotation_deg.to_radians(),
            [0.0, 0.0],
        );
        Self::build(
            lattice,
            -c.corner_hole_depth_nm,
            c.corner_hole_sigma_nm,
            FeatureKind::CornerHole,
        )
    }

    fn generic(c: &LatticeConfig, hexagonal: bool) -> Self {
        let rotation = c.rotation_deg.to_radians();
        let lattice = if hexagonal {
            Lattice::hexagonal(c.lattice_constant_nm, rotation, [0.0, 0.0])
        } else {
            Lattice::square(c.lattice_constant_nm, rotation, [0.0, 0.0])
        };
        let kind = if c.feature_height_nm > 0.0 {
            FeatureKind::Hill
        } else {
            FeatureKind::Pit
        };
        Self::build(lattice, c.feature_height_nm, c.feature_sigma_nm, kind)
    }

    fn build(lattice: Lattice, height_nm: f64, sigma_nm: f64, kind: FeatureKind) -> Self {
        let a = lattice.a1[0].hypot(lattice.a1[1]);
        // Sum sites within ~5σ: a window of ±ceil(5σ/h) cells beyond the own cell.
        let h = a * (3f64.sqrt() / 2.0);
        let window = ((5.0 * sigma_nm / h).ceil() as i64).clamp(0, 16);
        Self {
            lattice,
            height_nm,
            inv_two_sigma_sq: 1.0 / (2.0 * sigma_nm * sigma_nm),
            window,
            kind,
        }
    }

    #[inline]
    fn height(&self, x: f64, y: f64) -> f64 {
        let (fi, fj) = self.lattice.fractional(x, y);
        let (i0, j0) = (fast_floor(fi) as i64, fast_floor(fj) as i64);
        let mut z = 0.0;
        for i in (i0 - self.window)..=(i0 + 1 + self.window) {
            for j in (j0 - self.window)..=(j0 + 1 + self.window) {
                let s = self.lattice.site(i as f64, j as f64);
                let r2 = (x - s[0]).powi(2) + (y - s[1]).powi(2);
                z += (-r2 * self.inv_two_sigma_sq).exp();
            }
        }
        self.height_nm * z
    }

    fn features(&self, x: f64, y: f64, radius: f64) -> Vec<FeatureSite> {
        let (i0, i1, j0, j1) = self.lattice.index_box(x, y, radius);
        let mut out = Vec::new();
        for i in i0..=i1 {
            for j in j0..=j1 {
                let s = self.lattice.site(i as f64, j as f64);
                if (s[0] - x).powi(2) + (s[1] - y).powi(2) <= radius * radius {
                    out.push(FeatureSite {
                        position: NmPoint::from_nm(s[0], s[1]),
                        kind: self.kind,
                        terrace: 0,
                        domain: None,
                    });
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::config::SimConfig;

    #[test]
    fn si7x7_corner_holes_and_generic_features_are_extrema() {
        use crate::config::{LatticeConfig, Si7x7Config};
        let surfaces = [
            SurfaceConfig::Si7x7(Si7x7Config {
                lattice_constant_nm: 2.688,
                corner_hole_depth_nm: 0.1,
                corner_hole_sigma_nm: 0.35,
                rotation_deg: 10.0,
            }),
            SurfaceConfig::SquareLattice(LatticeConfig {
                lattice_constant_nm: 0.5,
                feature_height_nm: 0.05,
                feature_sigma_nm: 0.08,
                rotation_deg: 0.0,
            }),
            SurfaceConfig::HexLattice(LatticeConfig {
                lattice_constant_nm: 0.4,
                feature_height_nm: -0.03,
                feature_sigma_nm: 0.1,
                rotation_deg: 30.0,
            }),
        ];
        for config in surfaces {
            let s = Surface::from_config(&config, 3);
            let sites = s.features_near(NmPoint::from_nm(1.0, -2.0), 6.0);
            assert!(sites.len() >= 4, "{config:?}");
            for site in sites {
                let (x, y) = (site.position.x.value(), site.position.y.value());
                let z0 = s.height_nm(x, y);
                for k in 0..8 {
                    let a = f64::from(k) * PI / 4.0;
                    let z = s.height_nm(x + 0.02 * a.cos(), y + 0.02 * a.sin());
                    assert_eq!(z < z0, site.kind.is_hill(), "{site:?}");
                }
            }
        }
    }

    #[test]
    fn fast_sin_cos_matches_libm() {
        let mut x = -30000.0;
        while x < 30000.0 {
            let (s, c) = fast_sin_cos(x);
            let (es, ec) = x.sin_cos();
            assert!((s - es).abs() < 1e-13 && (c - ec).abs() < 1e-13, "{x}");
            x += 0.3779;
        }
        assert!(fast_sin_cos(f64::NAN).0.is_nan());
    }

    #[test]
    fn hopg_atoms_are_maxima_and_hollows_minima() {
        let config = SimConfig::ideal();
        let s = Surface::from_config(&config.surface, 1);
        let sites = s.features_near(NmPoint::from_nm(0.3, 0.2), 1.0);
        assert!(sites.len() > 20);
        let eps = 0.01;
        for site in sites {
            let (x, y) = (site.position.x.value(), site.position.y.value());
            let z0 = s.height_nm(x, y);
            for k in 0..8 {
                let a = f64::from(k) * PI / 4.0;
                let z = s.height_nm(x + eps * a.cos(), y + eps * a.sin());
                if site.kind.is_hill() {
                    assert!(z < z0, "{site:?}");
                } else {
                    assert!(z > z0, "{site:?}");
                }
            }
        }
        // Corrugation is atom-to-hollow.
        let atom = s.height_nm(0.0, 0.0);
        let (a1, a2) = s.lattice_vectors_nm();
        let hollow = s.height_nm(
            2.0 / 3.0 * (a1.x.value() + a2.x.value()),
            2.0 / 3.0 * (a1.y.value() + a2.y.value()),
        );
        assert!((atom - hollow - 0.08).abs() < 1e-12);
    }
}
