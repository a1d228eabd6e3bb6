//! Local calibration coefficients (LCCs) from drift-free count vectors (DESIGN §7).
//!
//! # The model
//! Near a net node the scanner is linear: a displacement of `d` counts moves the tip by
//! `R(θ)·M·d` nanometres, with
//!
//! ```text
//! M = [[K̄x, K̄y·sin α],
//!      [0,   K̄y·cos α]]
//! ```
//!
//! (K̄x, K̄y in nm per count, α the local obliquity; the rotation θ between the scanner and the
//! standard is unobservable and irrelevant). The metric `G = MᵀM` satisfies, for any two
//! measured vectors, `dᵢᵀ G dⱼ = Dᵢ·Dⱼ` where `Dᵢ` are the true vectors of the standard
//! (lengths L₁, L₂ and the angle γ between them for an LCS A, B, C). With
//! `g = (g₁₁, g₁₂, g₂₂)` = (K̄x², K̄x·K̄y·sin α, K̄y²) this is linear in `g`.
//!
//! # How it is solved
//! [`solve_metric_system`] builds and solves exactly that linear system (exactly for two
//! vectors, ordinary least squares for more); it is kept as the reference formulation.
//!
//! [`solve_lcc`], the estimator used by the controller, solves the *same relations* in an
//! equivalent linear parametrisation that is better for noisy data: the measured vectors are
//! `dᵢ = P·Dᵢ + εᵢ` with the 2×2 map `P = (R M)⁻¹` (4 unknowns: the 3 LCCs and θ) and the true
//! vectors `Dᵢ` written in any frame of the standard. This is linear in `P` with the noise
//! only in the regressand, so the generalised least-squares estimate of `P` (weights = the
//! inverse covariances of the measured vectors) is unbiased and its covariance is exact;
//! `G = P⁻ᵀ P⁻¹` then satisfies `dᵢᵀ G dⱼ = Dᵢ·Dⱼ` exactly for two vectors (the solutions
//! coincide) and in the least-squares sense for more. In the metric system the noise enters
//! the design matrix (products of measured components), which biases `g` by
//! `tr(G Σ)`-sized terms and correlates the pair equations (singular residual covariance
//! once four or more vectors are measured) — hence the reparametrisation.
//!
//! K̄x = √g₁₁, K̄y = √g₂₂, α = atan2(g₁₂, √det G) (i.e. sin α = g₁₂/(K̄x K̄y)); their
//! covariance is propagated from the vector covariances through the linear solve and the
//! Jacobian of the nonlinear map. The map's second-order bias ½·tr(∇²f·Σ) (of order
//! (σ/|d|)² relative, e.g. 5·10⁻⁴ at 1.3 % noise — small for one node but not averaged away
//! by the regression over many repeats) is subtracted, leaving a bias of order (σ/|d|)⁴.
//!
//! Kz comes from known heights ([`solve_kz`]): Kz = h / Δz for monatomic steps
//! (h = 0.3354 nm on HOPG), inverse-variance averaged over several steps.

use nalgebra::{DMatrix, Matrix2, Matrix3, Vector2, Vector3};
use serde::{Deserialize, Serialize};
use spm_hal::{CountVector, Counts, Nanometres, NmPerCount, Radians};

/// A true vector of the calibration standard, in nanometres, in any fixed frame of the
/// standard (only lengths and angles between vectors matter).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StandardVector {
    /// X component in the standard's frame.
    pub x: Nanometres,
    /// Y component in the standard's frame.
    pub y: Nanometres,
}

impl StandardVector {
    /// A vector from two bare numbers of nanometres.
    pub const fn from_nm(x_nm: f64, y_nm: f64) -> Self {
        Self {
            x: Nanometres(x_nm),
            y: Nanometres(y_nm),
        }
    }

    /// The vector of length `length` at angle `angle` from the frame's x axis.
    pub fn polar(length: Nanometres, angle: Radians) -> Self {
        Self::from_nm(
            length.value() * angle.value().cos(),
            length.value() * angle.value().sin(),
        )
    }

    /// Length.
    pub fn norm(self) -> Nanometres {
        Nanometres(self.x.value().hypot(self.y.value()))
    }

    /// Difference `self − other`.
    pub fn minus(self, other: Self) -> Self {
        Self::from_nm(
            self.x.value() - other.x.value(),
            self.y.value() - other.y.value(),
        )
    }

    fn v(self) -> Vector2<f64> {
        Vector2::new(self.x.value(), self.y.value())
    }
}

/// The covariance of a measured count vector, counts².
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CountCovariance {
    /// Variance of the x component, counts².
    pub xx_counts2: f64,
    /// Covariance of the x and y components, counts².
    pub xy_counts2: f64,
    /// Variance of the y component, counts².
    pub yy_counts2: f64,
}

impl CountCovariance {
    /// An exactly known vector (no uncertainty).
    pub const EXACT: Self = Self {
        xx_counts2: 0.0,
        xy_counts2: 0.0,
        yy_counts2: 0.0,
    };

    /// Independent components with the same standard uncertainty `sigma`.
    pub fn isotropic(sigma: Counts) -> Self {
        let v = sigma.value() * sigma.value();
        Self {
            xx_counts2: v,
            xy_counts2: 0.0,
            yy_counts2: v,
        }
    }

    /// The covariance of the mean of `n` independent vectors with this covariance.
    pub fn of_mean(self, n: usize) -> Self {
        let k = 1.0 / (n.max(1) as f64);
        Self {
            xx_counts2: self.xx_counts2 * k,
            xy_counts2: self.xy_counts2 * k,
            yy_counts2: self.yy_counts2 * k,
        }
    }

    /// The covariance of a sum or difference of two independent vectors.
    pub fn plus(self, other: Self) -> Self {
        Self {
            xx_counts2: self.xx_counts2 + other.xx_counts2,
            xy_counts2: self.xy_counts2 + other.xy_counts2,
            yy_counts2: self.yy_counts2 + other.yy_counts2,
        }
    }

    fn m(self) -> Matrix2<f64> {
        Matrix2::new(
            self.xx_counts2,
            self.xy_counts2,
            self.xy_counts2,
            self.yy_counts2,
        )
    }

    fn is_valid(self) -> bool {
        let finite = self.xx_counts2.is_finite()
            && self.xy_counts2.is_finite()
            && self.yy_counts2.is_finite();
        finite
            && self.xx_counts2 >= 0.0
            && self.yy_counts2 >= 0.0
            && self.xy_counts2 * self.xy_counts2 <= self.xx_counts2 * self.yy_counts2 * (1.0 + 1e-9)
    }
}

/// One drift-free measured count vector between two features and its true counterpart.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct VectorObservation {
    /// Measured drift-free displacement (e.g. the half-sum of forward and backward
    /// differences of skipping), counts.
    pub measured: CountVector,
    /// Covariance of `measured`, counts².
    pub covariance: CountCovariance,
    /// The true vector of the standard between the same two features, nm.
    pub standard: StandardVector,
}

/// The metric `G = MᵀM`, nm² per count².
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Metric {
    /// g₁₁ = K̄x², nm²/count².
    pub g11_nm2_per_count2: f64,
    /// g₁₂ = K̄x·K̄y·sin α, nm²/count².
    pub g12_nm2_per_count2: f64,
    /// g₂₂ = K̄y², nm²/count².
    pub g22_nm2_per_count2: f64,
}

impl Metric {
    /// `uᵀ G v` in nm².
    pub fn inner_nm2(&self, u: CountVector, v: CountVector) -> f64 {
        let (ux, uy, vx, vy) = (u.x.value(), u.y.value(), v.x.value(), v.y.value());
        self.g11_nm2_per_count2 * ux * vx
            + self.g12_nm2_per_count2 * (ux * vy + uy * vx)
            + self.g22_nm2_per_count2 * uy * vy
    }

    /// K̄x, K̄y, α of this metric, or an error when it is not positive definite.
    pub fn coefficients(&self) -> Result<(NmPerCount, NmPerCount, Radians), LccError> {
        let (g11, g12, g22) = (
            self.g11_nm2_per_count2,
            self.g12_nm2_per_count2,
            self.g22_nm2_per_count2,
        );
        if !(g11.is_finite() && g12.is_finite() && g22.is_finite()) {
            return Err(LccError::NonFinite { what: "metric" });
        }
        let det = g11 * g22 - g12 * g12;
        if !(g11 > 0.0 && g22 > 0.0 && det > 1e-12 * g11 * g22) {
            return Err(LccError::NotPositiveDefinite {
                g11_nm2_per_count2: g11,
                g12_nm2_per_count2: g12,
                g22_nm2_per_count2: g22,
            });
        }
        Ok((
            NmPerCount(g11.sqrt()),
            NmPerCount(g22.sqrt()),
            Radians(g12.atan2(det.sqrt())),
        ))
    }
}

/// Why LCCs cannot be computed from the given observations.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum LccError {
    /// Fewer than two vectors.
    #[error("at least two vectors are needed, got {got}")]
    TooFewVectors {
        /// Number of vectors given.
        got: usize,
    },
    /// An input is NaN or infinite.
    #[error("non-finite {what}")]
    NonFinite {
        /// Which input.
        what: &'static str,
    },
    /// A covariance is not a valid (finite, positive semi-definite) covariance.
    #[error("covariance of vector {index} is not finite positive semi-definite")]
    InvalidCovariance {
        /// Index of the observation.
        index: usize,
    },
    /// The measured vectors are (nearly) collinear: the metric is not determined.
    #[error("the measured vectors are collinear (largest |sin| between them {max_sin:e})")]
    Collinear {
        /// Largest |sine| of the angle between any two measured vectors.
        max_sin: f64,
    },
    /// The true vectors of the standard are (nearly) collinear.
    #[error("the standard's vectors are collinear (largest |sin| between them {max_sin:e})")]
    DegenerateStandard {
        /// Largest |sine| of the angle between any two standard vectors.
        max_sin: f64,
    },
    /// The solved metric is not positive definite (inconsistent data).
    #[error(
        "the metric is not positive definite (g11 = {g11_nm2_per_count2:e}, g12 = {g12_nm2_per_count2:e}, g22 = {g22_nm2_per_count2:e} nm²/count²)"
    )]
    NotPositiveDefinite {
        /// g₁₁.
        g11_nm2_per_count2: f64,
        /// g₁₂.
        g12_nm2_per_count2: f64,
        /// g₂₂.
        g22_nm2_per_count2: f64,
    },
    /// Kz: a step height in counts is zero, negative or its uncertainty invalid.
    #[error("step {index}: {reason}")]
    InvalidStep {
        /// Index of the step.
        index: usize,
        /// What is wrong.
        reason: &'static str,
    },
}

/// LCCs of one LCS with their uncertainties.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LccEstimate {
    /// K̄x, nm per count.
    pub kx: NmPerCount,
    /// K̄y, nm per count.
    pub ky: NmPerCount,
    /// Local obliquity α, rad.
    pub alpha: Radians,
    /// Covariance of (K̄x, K̄y, α) in (nm/count, nm/count, rad), row-major.
    pub covariance: [[f64; 3]; 3],
    /// The metric G.
    pub metric: Metric,
    /// Number of vectors used.
    pub vectors: usize,
    /// Redundancy: 2·vectors − 4 (0 for an exact two-vector solution).
    pub degrees_of_freedom: usize,
    /// χ² of the fit residuals with the given covariances (0 when exact or unweighted);
    /// χ²/dof ≫ 1 means the covariances understate the errors.
    pub chi_squared: f64,
}

impl LccEstimate {
    /// Standard uncertainty of K̄x, nm per count.
    pub fn u_kx(&self) -> NmPerCount {
        NmPerCount(self.covariance[0][0].max(0.0).sqrt())
    }
    /// Standard uncertainty of K̄y, nm per count.
    pub fn u_ky(&self) -> NmPerCount {
        NmPerCount(self.covariance[1][1].max(0.0).sqrt())
    }
    /// Standard uncertainty of α, rad.
    pub fn u_alpha(&self) -> Radians {
        Radians(self.covariance[2][2].max(0.0).sqrt())
    }

    /// The matrix M (nm per count) mapping a count vector to nanometres in the scanner-aligned
    /// frame (x along the scanner's X axis).
    pub fn matrix(&self) -> spm_hal::NmPerCountMatrix {
        spm_hal::NmPerCountMatrix::from_lcc(self.kx, self.ky, self.alpha)
    }

    /// A count vector in nanometres in the scanner-aligned frame.
    pub fn to_nm(&self, v: CountVector) -> (Nanometres, Nanometres) {
        let m = self.matrix().rows();
        (
            Nanometres(m[0][0] * v.x.value() + m[0][1] * v.y.value()),
            Nanometres(m[1][1] * v.y.value()),
        )
    }
}

fn cross(a: Vector2<f64>, b: Vector2<f64>) -> f64 {
    a.x * b.y - a.y * b.x
}

/// Largest |sin| of the angle between any two of the vectors (0 if any is zero).
fn max_sin(vectors: &[Vector2<f64>]) -> f64 {
    let mut best = 0.0_f64;
    for (i, a) in vectors.iter().enumerate() {
        for b in &vectors[i + 1..] {
            let n = a.norm() * b.norm();
            if n > 0.0 {
                best = best.max((cross(*a, *b) / n).abs());
            }
        }
    }
    best
}

/// Smallest |sin| accepted between the measured (or standard) vectors.
pub const MIN_SIN_BETWEEN_VECTORS: f64 = 1e-6;

fn validate(observations: &[VectorObservation]) -> Result<(), LccError> {
    if observations.len() < 2 {
        return Err(LccError::TooFewVectors {
            got: observations.len(),
        });
    }
    for (index, o) in observations.iter().enumerate() {
        if !(o.measured.x.is_finite() && o.measured.y.is_finite()) {
            return Err(LccError::NonFinite {
                what: "measured vector",
            });
        }
        if !(o.standard.x.is_finite() && o.standard.y.is_finite()) {
            return Err(LccError::NonFinite {
                what: "standard vector",
            });
        }
        if !o.covariance.is_valid() {
            return Err(LccError::InvalidCovariance { index });
        }
    }
    let standard: Vec<_> = observations.iter().map(|o| o.standard.v()).collect();
    let s = max_sin(&standard);
    if s < MIN_SIN_BETWEEN_VECTORS {
        return Err(LccError::DegenerateStandard { max_sin: s });
    }
    let measured: Vec<_> = observations
        .iter()
        .map(|o| Vector2::new(o.measured.x.value(), o.measured.y.value()))
        .collect();
    let s = max_sin(&measured);
    if s < MIN_SIN_BETWEEN_VECTORS {
        return Err(LccError::Collinear { max_sin: s });
    }
    Ok(())
}

/// Solves DESIGN §7's linear system `dᵢᵀ G dⱼ = Dᵢ·Dⱼ` (all pairs i ≤ j) for the metric by
/// ordinary least squares (exactly for two vectors), through the workspace's one solver
/// [`spm_regression::least_squares`]. Reference formulation; see the module docs for why
/// [`solve_lcc`] is preferred on noisy data.
///
/// # Errors
/// [`LccError`] for fewer than two vectors, non-finite input, collinear vectors or a
/// rank-deficient system.
pub fn solve_metric_system(observations: &[VectorObservation]) -> Result<Metric, LccError> {
    validate(observations)?;
    let n = observations.len();
    let scale = rms_norm(observations);
    let mut rows = Vec::with_capacity(n * (n + 1) / 2);
    let mut b = Vec::with_capacity(n * (n + 1) / 2);
    for i in 0..n {
        for j in i..n {
            let (di, dj) = (observations[i].measured, observations[j].measured);
            let (xi, yi) = (di.x.value() / scale, di.y.value() / scale);
            let (xj, yj) = (dj.x.value() / scale, dj.y.value() / scale);
            rows.push(vec![xi * xj, xi * yj + yi * xj, yi * yj]);
            b.push(
                observations[i]
                    .standard
                    .v()
                    .dot(&observations[j].standard.v()),
            );
        }
    }
    let g = spm_regression::least_squares(&rows, &b, &[false; 3])
        .map_err(|e| match e {
            // Rank deficiency: the measured vectors do not span the plane.
            spm_regression::RegressionError::IllConditioned {
                condition_number, ..
            } => LccError::Collinear {
                max_sin: 1.0 / condition_number,
            },
            _ => LccError::NonFinite { what: "metric" },
        })?
        .coefficients;
    let s2 = scale * scale;
    Ok(Metric {
        g11_nm2_per_count2: g[0] / s2,
        g12_nm2_per_count2: g[1] / s2,
        g22_nm2_per_count2: g[2] / s2,
    })
}

fn rms_norm(observations: &[VectorObservation]) -> f64 {
    let sum: f64 = observations
        .iter()
        .map(|o| o.measured.dot_counts_squared(o.measured))
        .sum();
    let rms = (sum / observations.len() as f64).sqrt();
    if rms > 0.0 { rms } else { 1.0 }
}

/// Computes the LCCs (K̄x, K̄y, α) and their covariance from two or more measured
/// drift-free count vectors and the standard's true vectors (see the module docs).
///
/// With exactly known vectors the result is exact; with covariances it is the generalised
/// least-squares estimate (ordinary least squares when some covariance is singular, with the
/// sandwich covariance), the covariance propagated to (K̄x, K̄y, α) by the Jacobian.
///
/// # Errors
/// [`LccError::TooFewVectors`], [`LccError::NonFinite`], [`LccError::InvalidCovariance`],
/// [`LccError::Collinear`] (measured vectors), [`LccError::DegenerateStandard`],
/// [`LccError::NotPositiveDefinite`].
pub fn solve_lcc(observations: &[VectorObservation]) -> Result<LccEstimate, LccError> {
    validate(observations)?;
    let n = observations.len();
    // Scale counts to O(1) for conditioning: P' = P / scale.
    let scale = rms_norm(observations);
    // Unknowns p = (p11, p12, p21, p22) of P (row-major); rows 2i, 2i+1 = x, y of vector i,
    // each pair with the vector's covariance: generalised least squares through the kernel
    // (ordinary least squares with the sandwich covariance when some covariance is singular).
    let mut rows = Vec::with_capacity(2 * n);
    let mut y = Vec::with_capacity(2 * n);
    let mut blocks = Vec::with_capacity(n);
    for o in observations {
        let d = o.standard.v();
        rows.push(vec![d.x, d.y, 0.0, 0.0]);
        rows.push(vec![0.0, 0.0, d.x, d.y]);
        y.push(o.measured.x.value() / scale);
        y.push(o.measured.y.value() / scale);
        let c = o.covariance.m() / (scale * scale);
        blocks.push(vec![vec![c[(0, 0)], c[(0, 1)]], vec![c[(1, 0)], c[(1, 1)]]]);
    }
    let fit =
        spm_regression::generalised_least_squares(&rows, &y, &blocks).map_err(|e| match e {
            spm_regression::RegressionError::NonFinite { .. } => {
                LccError::NonFinite { what: "covariance" }
            }
            _ => LccError::DegenerateStandard { max_sin: 0.0 },
        })?;
    let p = &fit.coefficients;
    let cov_p = DMatrix::from_fn(4, 4, |r, c| fit.covariance[r][c]);
    let chi_squared = fit.chi_squared.unwrap_or(0.0);
    let pm = Matrix2::new(p[0], p[1], p[2], p[3]);
    let det = pm.determinant();
    let measured: Vec<_> = observations
        .iter()
        .map(|o| Vector2::new(o.measured.x.value(), o.measured.y.value()))
        .collect();
    let frob2 = pm.norm_squared();
    if !(det.is_finite() && det.abs() > 1e-12 * frob2) {
        return Err(LccError::Collinear {
            max_sin: max_sin(&measured),
        });
    }
    let (params, jac) = coefficients_and_jacobian(&pm)?;
    // Back to counts: P = P' · scale, so B = P⁻¹ = B' / scale; K scales by 1/scale,
    // α is scale-free. Covariance of p' maps through the Jacobian (in primed units).
    let jm = DMatrix::from_fn(3, 4, |r, c| jac[(r, c)]);
    let cov_params = &jm * &cov_p * jm.transpose();
    let unscale = [1.0 / scale, 1.0 / scale, 1.0];
    let mut covariance = [[0.0; 3]; 3];
    for (r, row) in covariance.iter_mut().enumerate() {
        for (k, value) in row.iter_mut().enumerate() {
            *value = cov_params[(r, k)] * unscale[r] * unscale[k];
        }
    }
    // Second-order bias of the nonlinear map: E[f(p̂)] ≈ f(p) + ½ tr(∇²f · Σp). Subtract it
    // (Hessian by central differences of the analytic Jacobian), leaving O(σ⁴) bias.
    let bias = second_order_bias(&pm, &cov_p);
    let kx = (params[0] - bias[0]) / scale;
    let ky = (params[1] - bias[1]) / scale;
    let alpha = params[2] - bias[2];
    let metric = Metric {
        g11_nm2_per_count2: kx * kx,
        g12_nm2_per_count2: kx * ky * alpha.sin(),
        g22_nm2_per_count2: ky * ky,
    };
    if !(kx.is_finite() && ky.is_finite() && alpha.is_finite()) {
        return Err(LccError::NonFinite { what: "solution" });
    }
    Ok(LccEstimate {
        kx: NmPerCount(kx),
        ky: NmPerCount(ky),
        alpha: Radians(alpha),
        covariance,
        metric,
        vectors: n,
        degrees_of_freedom: 2 * n - 4,
        chi_squared,
    })
}

/// ½ tr(∇²f Σp) for f = (K̄x, K̄y, α) of P, Hessians by central differences of the Jacobian.
/// Zero when the Hessian cannot be evaluated (too close to degenerate).
fn second_order_bias(p: &Matrix2<f64>, cov_p: &DMatrix<f64>) -> Vector3<f64> {
    if cov_p.iter().all(|v: &f64| *v == 0.0) {
        return Vector3::zeros();
    }
    let h = 1e-6 * p.norm();
    let mut bias = Vector3::zeros();
    for j in 0..4 {
        let mut plus = *p;
        let mut minus = *p;
        plus[(j / 2, j % 2)] += h;
        minus[(j / 2, j % 2)] -= h;
        let (Ok((_, jp)), Ok((_, jm))) = (
            coefficients_and_jacobian(&plus),
            coefficients_and_jacobian(&minus),
        ) else {
            return Vector3::zeros();
        };
        // Column j of each Hessian: ∂J[k, i]/∂p_j.
        for k in 0..3 {
            for i in 0..4 {
                let hess_kij = (jp[(k, i)] - jm[(k, i)]) / (2.0 * h);
                bias[k] += 0.5 * hess_kij * cov_p[(i, j)];
            }
        }
    }
    if bias.iter().all(|b: &f64| b.is_finite()) {
        bias
    } else {
        Vector3::zeros()
    }
}

/// (K̄x, K̄y, α) from P (counts per nm, scaled) and the 3×4 Jacobian ∂(K̄x, K̄y, α)/∂vec(P)
/// (row-major vec), in the scaled units.
fn coefficients_and_jacobian(
    p: &Matrix2<f64>,
) -> Result<(Vector3<f64>, nalgebra::SMatrix<f64, 3, 4>), LccError> {
    let b = p
        .try_inverse()
        .ok_or(LccError::NonFinite { what: "inverse" })?;
    let g = |b: &Matrix2<f64>| {
        let c1 = b.column(0);
        let c2 = b.column(1);
        Vector3::new(c1.dot(&c1), c1.dot(&c2), c2.dot(&c2))
    };
    let gv = g(&b);
    let metric = Metric {
        g11_nm2_per_count2: gv[0],
        g12_nm2_per_count2: gv[1],
        g22_nm2_per_count2: gv[2],
    };
    let (kx, ky, alpha) = metric.coefficients()?;
    let (kx, ky, alpha) = (kx.value(), ky.value(), alpha.value());
    // ∂(K̄x, K̄y, α)/∂(g11, g12, g22).
    let (g11, g12, g22) = (gv[0], gv[1], gv[2]);
    let det = g11 * g22 - g12 * g12;
    let sq = det.sqrt();
    // α = atan2(g12, √det): dα = (√det·dg12 − g12·d√det)/(g12² + det), g12² + det = g11 g22.
    let denom = g11 * g22;
    let dsq = |dd: f64| dd / (2.0 * sq);
    let j_gk = Matrix3::new(
        1.0 / (2.0 * kx),
        0.0,
        0.0,
        0.0,
        0.0,
        1.0 / (2.0 * ky),
        (-g12 * dsq(g22)) / denom,
        (sq - g12 * dsq(-2.0 * g12)) / denom,
        (-g12 * dsq(g11)) / denom,
    );
    // ∂g/∂vec(P) via dB = −B dP B.
    let mut j_pg = nalgebra::SMatrix::<f64, 3, 4>::zeros();
    for k in 0..4 {
        let mut e = Matrix2::zeros();
        e[(k / 2, k % 2)] = 1.0;
        let db = -(b * e * b);
        let c1 = b.column(0);
        let c2 = b.column(1);
        let d1 = db.column(0);
        let d2 = db.column(1);
        j_pg[(0, k)] = 2.0 * c1.dot(&d1);
        j_pg[(1, k)] = c1.dot(&d2) + c2.dot(&d1);
        j_pg[(2, k)] = 2.0 * c2.dot(&d2);
    }
    Ok((Vector3::new(kx, ky, alpha), j_gk * j_pg))
}

/// One measured step (or other known vertical size) for Kz.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepObservation {
    /// Measured height of the step in Z counts (sign ignored: up or down steps).
    pub height: Counts,
    /// Standard uncertainty of `height`, counts.
    pub u_height: Counts,
    /// The true height, nm (e.g. 0.3354 nm for a monatomic HOPG step, n·0.3354 for n layers).
    pub true_height: Nanometres,
}

/// Kz with its standard uncertainty.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct KzEstimate {
    /// Kz, nm per count.
    pub kz: NmPerCount,
    /// Standard uncertainty of Kz, nm per count.
    pub u_kz: NmPerCount,
    /// Steps used.
    pub steps: usize,
}

/// Kz = h / Δz from known step heights; several steps are combined by the inverse-variance
/// weighted mean of their ratios (unweighted mean when some uncertainty is zero). The
/// uncertainty of each ratio is Kz·u(Δz)/Δz (first-order propagation).
///
/// # Errors
/// [`LccError::TooFewVectors`] for no step, [`LccError::InvalidStep`] for a non-finite or
/// zero height or an invalid uncertainty.
pub fn solve_kz(steps: &[StepObservation]) -> Result<KzEstimate, LccError> {
    if steps.is_empty() {
        return Err(LccError::TooFewVectors { got: 0 });
    }
    let mut ratios = Vec::with_capacity(steps.len());
    for (index, s) in steps.iter().enumerate() {
        let dz = s.height.value().abs();
        let h = s.true_height.value().abs();
        if !(dz.is_finite() && dz > 0.0) {
            return Err(LccError::InvalidStep {
                index,
                reason: "measured height must be finite and non-zero",
            });
        }
        if !(h.is_finite() && h > 0.0) {
            return Err(LccError::InvalidStep {
                index,
                reason: "true height must be finite and non-zero",
            });
        }
        let u = s.u_height.value();
        if !(u.is_finite() && u >= 0.0) {
            return Err(LccError::InvalidStep {
                index,
                reason: "uncertainty must be finite and >= 0",
            });
        }
        let k = h / dz;
        ratios.push((k, k * u / dz));
    }
    let weighted = ratios.iter().all(|&(_, u)| u > 0.0);
    let (kz, u_kz) = if weighted {
        let sw: f64 = ratios.iter().map(|&(_, u)| 1.0 / (u * u)).sum();
        let kz = ratios.iter().map(|&(k, u)| k / (u * u)).sum::<f64>() / sw;
        (kz, (1.0 / sw).sqrt())
    } else {
        let n = ratios.len() as f64;
        let kz = ratios.iter().map(|&(k, _)| k).sum::<f64>() / n;
        let var = ratios.iter().map(|&(_, u)| u * u).sum::<f64>() / (n * n);
        (kz, var.sqrt())
    };
    Ok(KzEstimate {
        kz: NmPerCount(kz),
        u_kz: NmPerCount(u_kz),
        steps: steps.len(),
    })
}

/// Smallest robust scale of the vectors' length residuals in [`solve_lcc_rejecting`]: a
/// nearest-neighbour vector is not expected to agree with its node's lattice better than
/// 1 % (localisation noise over one lattice constant), so agreement below that does not
/// make a 3 % vector an outlier.
pub const MIN_VECTOR_RESIDUAL_SCALE: f64 = 0.01;

/// [`solve_lcc`] over a node's many vectors (every neighbour of A) that leaves out the
/// vectors of other features. Each vector's length through a solution is compared with its
/// standard's, `e = |M·v| / |s| − 1` (independent of the frame's rotation). Every three of
/// the vectors are solved, and the solution whose median |e| over all vectors is least is
/// the reference (least median of squares: up to half the vectors may be another feature's
/// without moving it). Vectors with |e| beyond `k` robust standard deviations of that
/// solution's residuals (1.4826 × their median |e|, at least
/// [`MIN_VECTOR_RESIDUAL_SCALE`]) are left out, and the rest solved by [`solve_lcc`].
/// Returns the estimate and the indices of the vectors kept, in order. With three vectors or
/// fewer it is [`solve_lcc`] of all (a triangle has no redundancy to judge a vector by).
///
/// # Errors
/// As [`solve_lcc`].
pub fn solve_lcc_rejecting(
    observations: &[VectorObservation],
    k: f64,
) -> Result<(LccEstimate, Vec<usize>), LccError> {
    let n = observations.len();
    let all: Vec<usize> = (0..n).collect();
    if n <= 3 {
        return solve_lcc(observations).map(|e| (e, all));
    }
    let residuals = |estimate: &LccEstimate| -> Vec<f64> {
        observations
            .iter()
            .map(|o| {
                let (x, y) = estimate.to_nm(o.measured);
                (x.value().hypot(y.value()) / o.standard.norm().value() - 1.0).abs()
            })
            .collect()
    };
    let mut best: Option<(f64, Vec<f64>)> = None;
    for i in 0..n {
        for j in i + 1..n {
            for l in j + 1..n {
                let Ok(estimate) = solve_lcc(&[observations[i], observations[j], observations[l]])
                else {
                    continue;
                };
                let e = residuals(&estimate);
                let mut sorted = e.clone();
                let Some(median) = spm_regression::median(&mut sorted) else {
                    continue;
                };
                if median.is_finite() && best.as_ref().is_none_or(|(m, _)| median < *m) {
                    best = Some((median, e));
                }
            }
        }
    }
    let Some((median, e)) = best else {
        return solve_lcc(observations).map(|e| (e, all));
    };
    let limit = k * (1.4826 * median).max(MIN_VECTOR_RESIDUAL_SCALE);
    let kept: Vec<usize> = all.into_iter().filter(|&i| e[i] <= limit).collect();
    if kept.len() < 3 {
        return solve_lcc(observations).map(|e| (e, (0..n).collect()));
    }
    if kept.len() < n {
        tracing::debug!(
            kept = kept.len(),
            of = n,
            limit,
            "vectors of other features left out"
        );
    }
    let subset: Vec<VectorObservation> = kept.iter().map(|&i| observations[i]).collect();
    solve_lcc(&subset).map(|estimate| (estimate, kept))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn obs(m: [[f64; 2]; 2], theta: f64, d: StandardVector, sigma: f64) -> VectorObservation {
        // counts = M⁻¹ R(−θ) D
        let (s, c) = theta.sin_cos();
        let rd = Vector2::new(
            c * d.x.value() + s * d.y.value(),
            -s * d.x.value() + c * d.y.value(),
        );
        let mm = Matrix2::new(m[0][0], m[0][1], m[1][0], m[1][1]);
        let u = mm.try_inverse().unwrap() * rd;
        VectorObservation {
            measured: CountVector::from_counts(u.x, u.y),
            covariance: CountCovariance::isotropic(Counts(sigma)),
            standard: d,
        }
    }

    #[test]
    fn hopg_triangle_is_solved_exactly() {
        let kx = 0.0021;
        let ky = 0.0019;
        let alpha = 0.03_f64;
        let m = [[kx, ky * alpha.sin()], [0.0, ky * alpha.cos()]];
        let a = 0.2461;
        let d1 = StandardVector::from_nm(a, 0.0);
        let d2 = StandardVector::polar(Nanometres(a), Radians::from_degrees(60.0));
        let o = [obs(m, 0.4, d1, 0.0), obs(m, 0.4, d2, 0.0)];
        let e = solve_lcc(&o).unwrap();
        assert!((e.kx.value() - kx).abs() < 1e-14);
        assert!((e.ky.value() - ky).abs() < 1e-14);
        assert!((e.alpha.value() - alpha).abs() < 1e-10);
        assert!(e.u_kx().value() == 0.0);
        let g = solve_metric_system(&o).unwrap();
        let (gkx, gky, galpha) = g.coefficients().unwrap();
        assert!((gkx.value() - kx).abs() < 1e-12);
        assert!((gky.value() - ky).abs() < 1e-12);
        assert!((galpha.value() - alpha).abs() < 1e-8);
        for i in 0..2 {
            for j in 0..2 {
                let lhs = e.metric.inner_nm2(o[i].measured, o[j].measured);
                let rhs = o[i].standard.v().dot(&o[j].standard.v());
                assert!((lhs - rhs).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn degenerate_geometry_is_a_typed_error() {
        let v = |x: f64, y: f64, sx: f64, sy: f64| VectorObservation {
            measured: CountVector::from_counts(x, y),
            covariance: CountCovariance::EXACT,
            standard: StandardVector::from_nm(sx, sy),
        };
        assert!(matches!(
            solve_lcc(&[v(100.0, 0.0, 0.25, 0.0), v(200.0, 0.0, 0.1, 0.2)]),
            Err(LccError::Collinear { .. })
        ));
        assert!(matches!(
            solve_lcc(&[v(100.0, 0.0, 0.25, 0.0), v(0.0, 100.0, 0.5, 0.0)]),
            Err(LccError::DegenerateStandard { .. })
        ));
        assert!(matches!(
            solve_lcc(&[v(f64::NAN, 0.0, 0.25, 0.0), v(0.0, 100.0, 0.0, 0.25)]),
            Err(LccError::NonFinite { .. })
        ));
        assert!(matches!(
            solve_lcc(&[v(100.0, 0.0, 0.25, 0.0)]),
            Err(LccError::TooFewVectors { got: 1 })
        ));
        let mut bad = v(100.0, 0.0, 0.25, 0.0);
        bad.covariance.xx_counts2 = -1.0;
        assert!(matches!(
            solve_lcc(&[bad, v(0.0, 100.0, 0.0, 0.25)]),
            Err(LccError::InvalidCovariance { index: 0 })
        ));
        let m = Metric {
            g11_nm2_per_count2: 1.0,
            g12_nm2_per_count2: 2.0,
            g22_nm2_per_count2: 1.0,
        };
        assert!(matches!(
            m.coefficients(),
            Err(LccError::NotPositiveDefinite { .. })
        ));
    }

    #[test]
    fn kz_from_steps() {
        let steps = [
            StepObservation {
                height: Counts(100.0),
                u_height: Counts(2.0),
                true_height: Nanometres(0.3354),
            },
            StepObservation {
                height: Counts(-200.0),
                u_height: Counts(2.0),
                true_height: Nanometres(0.6708),
            },
        ];
        let k = solve_kz(&steps).unwrap();
        assert!((k.kz.value() - 0.003354).abs() < 1e-12);
        // u = Kz·u/Δz = 0.003354·0.02 and 0.003354·0.01, combined.
        let (u1, u2): (f64, f64) = (0.003354 * 0.02, 0.003354 * 0.01);
        let expected = 1.0 / (1.0 / (u1 * u1) + 1.0 / (u2 * u2)).sqrt();
        assert!((k.u_kz.value() - expected).abs() < 1e-15);
        assert!(solve_kz(&[]).is_err());
        let mut zero = steps[0];
        zero.height = Counts(0.0);
        assert!(matches!(
            solve_kz(&[zero]),
            Err(LccError::InvalidStep { index: 0, .. })
        ));
    }

    /// `check(lengths' errors, expected kept)`: six neighbours of A on a distorted lattice,
    /// the i-th one's measured vector stretched by `errors[i]`; the node's solution leaves out
    /// exactly the vectors of another feature and is then the lattice's.
    #[track_caller]
    fn check_rejection(errors: [f64; 6], kept: &[usize]) {
        let (kx, ky, alpha) = (0.0180, 0.0133, -0.17_f64);
        let m = [[kx, ky * alpha.sin()], [0.0, ky * alpha.cos()]];
        let a = 2.688;
        let o: Vec<VectorObservation> = (0..6)
            .map(|i| {
                let d =
                    StandardVector::polar(Nanometres(a), Radians::from_degrees(60.0 * i as f64));
                let mut v = obs(m, 0.2, d, 0.0);
                v.measured = v.measured * (1.0 + errors[i]);
                v
            })
            .collect();
        let (e, k) = solve_lcc_rejecting(&o, 3.0).unwrap();
        assert_eq!(k, kept, "errors {errors:?}");
        let clean = errors
            .iter()
            .enumerate()
            .all(|(i, &x)| x == 0.0 || !kept.contains(&i));
        if clean {
            assert!((e.kx.value() / kx - 1.0).abs() < 1e-9, "{}", e.kx.value());
            assert!((e.ky.value() / ky - 1.0).abs() < 1e-9);
            assert!((e.alpha.value() - alpha).abs() < 1e-9);
        }
    }

    #[test]
    fn a_vector_of_another_feature_is_left_out_of_the_node() {
        check_rejection([0.0; 6], &[0, 1, 2, 3, 4, 5]);
        check_rejection([0.0, 0.0, 0.30, 0.0, 0.0, 0.0], &[0, 1, 3, 4, 5]);
        check_rejection([0.0, -0.25, 0.0, 0.0, 0.20, 0.0], &[0, 2, 3, 5]);
        // Within the noise floor (1 %): nothing is left out.
        check_rejection(
            [0.01, -0.01, 0.005, 0.0, -0.008, 0.012],
            &[0, 1, 2, 3, 4, 5],
        );
    }
}
