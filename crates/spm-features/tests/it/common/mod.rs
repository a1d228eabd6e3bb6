//! Synthetic HOPG surfaces for tests: three-cosine model with known atoms.
#![allow(dead_code, clippy::unwrap_used)] // as in the test files that included it

use rand::Rng;
use rand_distr::{Distribution, Normal};
use spm_hal::{CountPoint, Counts, Frame, HeightMap, ScanRequest, Seconds, TraceHalf};

/// A three-cosine HOPG surface in count coordinates (scanner = identity × nm/count).
pub struct Hopg {
    /// Lattice constant in counts.
    pub a_counts: f64,
    /// Peak-to-hollow corrugation in Z counts.
    pub corrugation_z: f64,
    k: [(f64, f64); 3],
    /// Lattice origin (an atom) in counts.
    pub origin: (f64, f64),
}

impl Hopg {
    /// `nm_per_count` lateral, corrugation in Z counts (given as nm at 0.001 nm/count → ×1000).
    pub fn new(nm_per_count: f64, corrugation_nm: f64) -> Self {
        let a = 0.2461 / nm_per_count;
        let g = 2.0 * std::f64::consts::PI / a;
        let b1 = (g, -g / 3f64.sqrt());
        let b2 = (0.0, 2.0 * g / 3f64.sqrt());
        let b3 = (-(b1.0 + b2.0), -(b1.1 + b2.1));
        Self {
            a_counts: a,
            corrugation_z: corrugation_nm * 100.0,
            k: [b1, b2, b3],
            origin: (0.0, 0.0),
        }
    }

    /// Position of atom (n, m) = origin + n·a1 + m·a2.
    pub fn atom(&self, n: i32, m: i32) -> CountPoint {
        let (n, m) = (f64::from(n), f64::from(m));
        CountPoint::from_counts(
            self.origin.0 + self.a_counts * (n + 0.5 * m),
            self.origin.1 + self.a_counts * (3f64.sqrt() / 2.0 * m),
        )
    }

    /// Height at (x, y) counts: corrugation/4.5 · (Σ cos(kᵢ·r) + 1.5), 0 at hollows.
    pub fn height(&self, x: f64, y: f64) -> f64 {
        let (x, y) = (x - self.origin.0, y - self.origin.1);
        let s: f64 = self.k.iter().map(|k| (k.0 * x + k.1 * y).cos()).sum();
        self.corrugation_z / 4.5 * (s + 1.5)
    }
}

/// A forward height map of `pixels`² centred on `centre`, white noise σ = `noise`.
pub fn segment_map(
    hopg: &Hopg,
    centre: CountPoint,
    step: Counts,
    pixels: u32,
    noise: f64,
    rng: &mut impl Rng,
) -> HeightMap {
    let request = ScanRequest::centred_square(centre, step, pixels, Seconds(1e-4));
    let normal = Normal::new(0.0, noise.max(1e-300)).unwrap();
    let frame = Frame::from_fn(request, Seconds(0.0), |p, _| {
        let n = if noise > 0.0 { normal.sample(rng) } else { 0.0 };
        Counts(hopg.height(p.x.value(), p.y.value()) + n)
    });
    frame.height_map(TraceHalf::Forward).unwrap()
}
