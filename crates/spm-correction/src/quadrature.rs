//! Gauss–Legendre quadrature (nodes computed, no tables) for eq. (9) with non-polynomial
//! integrands and as a cross-check of the analytic integrals.

use crate::CorrectionError;

/// Largest supported number of Gauss–Legendre points per panel.
pub const MAX_GAUSS_POINTS: usize = 64;

/// A composite Gauss–Legendre rule: an interval is split into equal panels no longer than
/// `max_panel_counts`, each integrated with `points` nodes (exact for polynomials of degree
/// 2·points − 1 on each panel).
#[derive(Debug, Clone, PartialEq)]
pub struct Quadrature {
    /// Nodes on [−1, 1].
    nodes: Vec<f64>,
    /// Weights (sum 2).
    weights: Vec<f64>,
    /// Longest panel, counts.
    max_panel_counts: f64,
}

impl Quadrature {
    /// A rule with `points` nodes per panel and panels no longer than `max_panel_counts`.
    ///
    /// # Errors
    /// [`CorrectionError::InvalidArgument`] for 0 or more than [`MAX_GAUSS_POINTS`] points, or a
    /// panel length that is not finite and positive.
    pub fn new(points: usize, max_panel_counts: f64) -> Result<Self, CorrectionError> {
        if points == 0 || points > MAX_GAUSS_POINTS {
            return Err(CorrectionError::InvalidArgument(format!(
                "Gauss–Legendre points must be in 1..={MAX_GAUSS_POINTS}, got {points}"
            )));
        }
        if !(max_panel_counts.is_finite() && max_panel_counts > 0.0) {
            return Err(CorrectionError::InvalidArgument(format!(
                "quadrature panel length must be finite and > 0 counts, got {max_panel_counts}"
            )));
        }
        let (nodes, weights) = gauss_legendre(points);
        Ok(Self {
            nodes,
            weights,
            max_panel_counts,
        })
    }

    /// The default rule: 8 points, panels of at most 4096 counts (exact to rounding for the
    /// smooth LCC fields of a scanner).
    #[must_use]
    pub fn standard() -> Self {
        let (nodes, weights) = gauss_legendre(8);
        Self {
            nodes,
            weights,
            max_panel_counts: 4096.0,
        }
    }

    /// Number of nodes per panel.
    #[must_use]
    pub fn points(&self) -> usize {
        self.nodes.len()
    }

    /// Longest panel in counts.
    #[must_use]
    pub fn max_panel_counts(&self) -> f64 {
        self.max_panel_counts
    }

    /// Nodes on [−1, 1].
    #[must_use]
    pub fn nodes(&self) -> &[f64] {
        &self.nodes
    }

    /// Weights matching [`Quadrature::nodes`].
    #[must_use]
    pub fn weights(&self) -> &[f64] {
        &self.weights
    }

    /// ∫ f(t) dt from `a` to `b` (oriented: negative when b < a).
    pub fn integrate(&self, a: f64, b: f64, mut f: impl FnMut(f64) -> f64) -> f64 {
        let length = b - a;
        if length == 0.0 || !length.is_finite() {
            return if length == 0.0 { 0.0 } else { f64::NAN };
        }
        let panels = (length.abs() / self.max_panel_counts)
            .ceil()
            .clamp(1.0, 1e9) as usize;
        let h = length / panels as f64;
        let mut total = 0.0;
        for p in 0..panels {
            let lo = a + h * p as f64;
            let mid = lo + 0.5 * h;
            let mut s = 0.0;
            for (x, w) in self.nodes.iter().zip(&self.weights) {
                s += w * f(mid + 0.5 * h * x);
            }
            total += 0.5 * h * s;
        }
        total
    }
}

impl Default for Quadrature {
    fn default() -> Self {
        Self::standard()
    }
}

/// Nodes and weights of the n-point Gauss–Legendre rule on [−1, 1] (Newton on P_n).
fn gauss_legendre(n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut nodes = vec![0.0; n];
    let mut weights = vec![0.0; n];
    let nf = n as f64;
    for i in 0..n.div_ceil(2) {
        // Tricomi's initial guess.
        let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (nf + 0.5)).cos();
        let mut dp = 1.0;
        for _ in 0..100 {
            let (p, d) = legendre_and_derivative(n, x);
            dp = d;
            let dx = p / d;
            x -= dx;
            if dx.abs() < 1e-16 {
                break;
            }
        }
        let (_, d) = legendre_and_derivative(n, x);
        if d.is_finite() {
            dp = d;
        }
        let w = 2.0 / ((1.0 - x * x) * dp * dp);
        nodes[i] = -x;
        nodes[n - 1 - i] = x;
        weights[i] = w;
        weights[n - 1 - i] = w;
    }
    if n % 2 == 1 {
        nodes[n / 2] = 0.0;
    }
    (nodes, weights)
}

/// P_n(x) and P_n'(x) by the three-term recurrence.
fn legendre_and_derivative(n: usize, x: f64) -> (f64, f64) {
    let (mut p0, mut p1) = (1.0, x);
    if n == 0 {
        return (1.0, 0.0);
    }
    for k in 2..=n {
        let kf = k as f64;
        let p2 = ((2.0 * kf - 1.0) * x * p1 - (kf - 1.0) * p0) / kf;
        p0 = p1;
        p1 = p2;
    }
    let d = n as f64 * (x * p1 - p0) / (x * x - 1.0);
    (p1, d)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn check(points: usize, degree: i32, expected_exact: bool) {
        let q = Quadrature::new(points, 1e9).unwrap();
        let got = q.integrate(-0.3, 1.7, |t| t.powi(degree));
        let exact = (1.7f64.powi(degree + 1) - (-0.3f64).powi(degree + 1)) / f64::from(degree + 1);
        let err = (got - exact).abs() / exact.abs().max(1.0);
        assert_eq!(
            err < 1e-13,
            expected_exact,
            "{points} points degree {degree}: {err}"
        );
    }

    #[test]
    fn exact_up_to_degree_2n_minus_1() {
        for n in [1usize, 2, 3, 5, 8, 16, 33, 64] {
            let top = 2 * n as i32 - 1;
            check(n, top.min(60), true);
            if n <= 8 {
                check(n, top + 1, false);
            }
        }
        let q = Quadrature::new(12, 1e9).unwrap();
        assert!((q.weights().iter().sum::<f64>() - 2.0).abs() < 1e-14);
        assert!((q.integrate(0.0, std::f64::consts::PI, f64::sin) - 2.0).abs() < 1e-14);
        assert!((q.integrate(1.0, 1.0, f64::sin)).abs() == 0.0);
    }

    #[test]
    fn bad_rules_are_rejected() {
        assert!(Quadrature::new(0, 1.0).is_err());
        assert!(Quadrature::new(65, 1.0).is_err());
        assert!(Quadrature::new(4, 0.0).is_err());
        assert!(Quadrature::new(4, f64::NAN).is_err());
    }
}
