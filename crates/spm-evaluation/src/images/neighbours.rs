//! Neighbour searches among points in the plane (nm): points binned in square cells, the
//! nearest within the 3 × 3 cells around a query, or at any distance by rings of cells. One
//! implementation for the image benchmark's matches (the lattice pair, the grating index).

/// Points binned in square cells of a fixed side (nm), for neighbour searches.
pub(crate) struct Grid {
    cell: f64,
    bins: std::collections::HashMap<(i64, i64), Vec<usize>>,
    /// Smallest and largest cell key along x and y (the searches stop beyond them).
    span: [(i64, i64); 2],
}

impl Grid {
    pub(crate) fn new(points: &[[f64; 2]], cell: f64) -> Self {
        let cell = cell.max(1e-12);
        let mut bins: std::collections::HashMap<(i64, i64), Vec<usize>> =
            std::collections::HashMap::new();
        let mut span = [(i64::MAX, i64::MIN); 2];
        for (i, p) in points.iter().enumerate() {
            let key = Self::key_of(cell, *p);
            span[0] = (span[0].0.min(key.0), span[0].1.max(key.0));
            span[1] = (span[1].0.min(key.1), span[1].1.max(key.1));
            bins.entry(key).or_default().push(i);
        }
        Self { cell, bins, span }
    }

    fn key_of(cell: f64, p: [f64; 2]) -> (i64, i64) {
        ((p[0] / cell).floor() as i64, (p[1] / cell).floor() as i64)
    }

    /// Folds the points of cell `key` into `best`, the nearest to `p` so far (ties to the
    /// lower index).
    fn visit(
        &self,
        key: (i64, i64),
        p: [f64; 2],
        points: &[[f64; 2]],
        best: &mut Option<(usize, f64)>,
    ) {
        for &i in self.bins.get(&key).into_iter().flatten() {
            let d = (points[i][0] - p[0]).hypot(points[i][1] - p[1]);
            if best.is_none_or(|b| d < b.1 || (d == b.1 && i < b.0)) {
                *best = Some((i, d));
            }
        }
    }

    /// The point of `points` (the grid's own) nearest to `p` among the 3 × 3 cells around it,
    /// ties to the lower index: `(index, distance)`.
    pub(crate) fn nearest_within_a_cell(
        &self,
        p: [f64; 2],
        points: &[[f64; 2]],
    ) -> Option<(usize, f64)> {
        let (cx, cy) = Self::key_of(self.cell, p);
        let mut best = None;
        for dx in -1..=1 {
            for dy in -1..=1 {
                self.visit((cx + dx, cy + dy), p, points, &mut best);
            }
        }
        best
    }

    /// The point of `points` nearest to `p` at any distance, ties to the lower index: rings of
    /// cells searched outwards until no closer point can lie beyond them.
    pub(crate) fn nearest(&self, p: [f64; 2], points: &[[f64; 2]]) -> Option<(usize, f64)> {
        if points.is_empty() {
            return None;
        }
        let (cx, cy) = Self::key_of(self.cell, p);
        let reach = [
            (cx - self.span[0].0).abs().max((self.span[0].1 - cx).abs()),
            (cy - self.span[1].0).abs().max((self.span[1].1 - cy).abs()),
        ];
        let last_ring = reach[0].max(reach[1]);
        let mut best: Option<(usize, f64)> = None;
        // Rings before the span's nearest cell, and the parts of a ring outside the span,
        // hold no point.
        let first_ring = (self.span[0].0 - cx)
            .max(cx - self.span[0].1)
            .max(self.span[1].0 - cy)
            .max(cy - self.span[1].1)
            .max(0);
        let (x_range, y_range) = (
            self.span[0].0..=self.span[0].1,
            self.span[1].0..=self.span[1].1,
        );
        for ring in first_ring..=last_ring {
            if ring == 0 {
                self.visit((cx, cy), p, points, &mut best);
            } else {
                let xs = (cx - ring).max(self.span[0].0)..=(cx + ring).min(self.span[0].1);
                for y in [cy - ring, cy + ring] {
                    if y_range.contains(&y) {
                        for x in xs.clone() {
                            self.visit((x, y), p, points, &mut best);
                        }
                    }
                }
                let ys = (cy - ring + 1).max(self.span[1].0)..=(cy + ring - 1).min(self.span[1].1);
                for x in [cx - ring, cx + ring] {
                    if x_range.contains(&x) {
                        for y in ys.clone() {
                            self.visit((x, y), p, points, &mut best);
                        }
                    }
                }
            }
            // Every point beyond this ring is at least `ring` cells away.
            if let Some((_, d)) = best
                && d < ring as f64 * self.cell
            {
                break;
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// The grid's nearest point, at any distance, is the brute-force nearest (ties to the
    /// lower index), for query points inside, beside and far outside the points' span, and
    /// on a lattice where ties are exact.
    #[test]
    fn the_grid_finds_the_same_nearest_point_as_a_full_search() {
        use rand::{Rng, SeedableRng};
        let brute = |p: [f64; 2], pts: &[[f64; 2]]| -> Option<(usize, f64)> {
            pts.iter()
                .enumerate()
                .map(|(i, q)| (i, (q[0] - p[0]).hypot(q[1] - p[1])))
                .min_by(|a, b| a.1.total_cmp(&b.1))
        };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let random: Vec<[f64; 2]> = (0..300)
            .map(|_| [rng.random_range(-5.0..5.0), rng.random_range(-3.0..3.0)])
            .collect();
        let lattice: Vec<[f64; 2]> = (0..100)
            .map(|i| [f64::from(i % 10) * 0.25, f64::from(i / 10) * 0.25])
            .collect();
        for (points, cell) in [(&random, 0.1), (&random, 2.0), (&lattice, 0.05)] {
            let grid = Grid::new(points, cell);
            for _ in 0..500 {
                let p = [rng.random_range(-40.0..40.0), rng.random_range(-40.0..40.0)];
                assert_eq!(grid.nearest(p, points), brute(p, points), "{p:?}");
                let near = [rng.random_range(-6.0..6.0), rng.random_range(-4.0..4.0)];
                assert_eq!(grid.nearest(near, points), brute(near, points), "{near:?}");
            }
            // Exactly between lattice points: the lower index.
            assert_eq!(
                grid.nearest([0.125, 0.0], points),
                brute([0.125, 0.0], points)
            );
        }
        assert_eq!(Grid::new(&[], 1.0).nearest([0.0, 0.0], &[]), None);
    }
}
