//! Rank-revealing linear least squares: the minimum-norm solution of a possibly rank-deficient
//! design, with its numerical rank, for the model check's effect columns (which may be
//! combinations of one another) and for normal systems a caller accumulates itself.
//!
//! [`least_squares`](crate::least_squares) refuses an undetermined column (a typed
//! `IllConditioned`); [`minimum_norm_least_squares`] instead gives such directions zero weight
//! and reports the rank, with the pseudo-inverse covariance σ̂²·(XᵀX)⁺. Two more things the
//! model check needs are here rather than in its crate:
//!
//! - a row mask (`included`): rows left out are not fitted, but get their residual;
//! - disjoint 0/1 indicator columns (one offset per frame, hundreds in a movie) eliminated
//!   exactly (Frisch–Waugh–Lovell) so that the cost grows with the data, not with frames³.
//!
//! The dense part factors the column-normalised design X = Q·R (CholeskyQR2, Householder QR
//! when that is not well conditioned) and takes the SVD of the small R; singular values below
//! [`MINIMUM_NORM_TOLERANCE`] of the largest are dropped.

use nalgebra::{DMatrix, DVector};

use crate::error::RegressionError;

/// Relative singular-value threshold of [`minimum_norm_least_squares`] (on unit-norm columns).
pub const MINIMUM_NORM_TOLERANCE: f64 = 1e-8;

/// The solution of [`minimum_norm_least_squares`].
#[derive(Debug, Clone, PartialEq)]
pub struct MinimumNormFit {
    /// The parameters, in column order (minimum norm over undetermined directions).
    pub coefficients: Vec<f64>,
    /// Covariance of the parameters, σ̂²·(XᵀX)⁺ with σ̂² = RSS / (equations − rank), row-major
    /// (n × n).
    pub covariance: Vec<Vec<f64>>,
    /// `rhs − model` for every row, those left out of the fit included.
    pub residuals: Vec<f64>,
    /// Residual sum of squares over the fitted rows.
    pub rss: f64,
    /// Fitted rows.
    pub equations: usize,
    /// Numerical rank of the design (columns that are combinations of others do not count).
    pub rank: usize,
}

/// Dense internal form of [`MinimumNormFit`].
struct DenseFit {
    coef: Vec<f64>,
    cov: DMatrix<f64>,
    residual: Vec<f64>,
    rss: f64,
    n_eq: usize,
    rank: usize,
}

/// Minimum-norm least squares `rhs ≈ Σⱼ coefficientⱼ·columns[j]` over the rows with
/// `included[r]` (see the module docs). Every column and the mask are as long as `rhs`.
///
/// # Errors
/// [`RegressionError::LengthMismatch`] for a column or mask of another length;
/// [`RegressionError::TooFewPoints`] (degree 0) unless there are more fitted rows than columns;
/// [`RegressionError::NonFinite`] for NaN/∞ in a fitted row (field "design" or "rhs");
/// [`RegressionError::InvalidArgument`] if the SVD does not converge.
pub fn minimum_norm_least_squares(
    columns: &[Vec<f64>],
    rhs: &[f64],
    included: &[bool],
) -> Result<MinimumNormFit, RegressionError> {
    if included.len() != rhs.len() {
        return Err(RegressionError::LengthMismatch {
            field: "row mask",
            expected: rhs.len(),
            got: included.len(),
        });
    }
    FactoredDesign::new(columns, included)?.fit(rhs)
}

/// A design of [`minimum_norm_least_squares`] factored once over its rows, for any number of
/// right-hand sides: [`FactoredDesign::fit`] gives what `minimum_norm_least_squares(columns,
/// rhs, included)` gives, bit for bit, without factoring the design again (the model check
/// asks how well one model explains each of many candidate columns).
pub struct FactoredDesign {
    columns: Vec<Vec<f64>>,
    included: Vec<bool>,
    n_eq: usize,
    /// The indicator columns eliminated, each row's group and each group's fitted rows.
    groups: Vec<usize>,
    member: Vec<Option<usize>>,
    counts: Vec<usize>,
    /// The other columns, their group means and their dense factor (`None`: no other
    /// column).
    others: Vec<usize>,
    means: Vec<Vec<f64>>,
    dense: Option<DenseFactor>,
}

impl FactoredDesign {
    /// Factors `columns` over the rows with `included[r]`.
    ///
    /// # Errors
    /// [`RegressionError::LengthMismatch`] for a column of another length than the mask;
    /// [`RegressionError::TooFewPoints`] (degree 0) unless there are more fitted rows than
    /// columns; [`RegressionError::NonFinite`] for NaN/∞ in a fitted row of the design.
    pub fn new(columns: &[Vec<f64>], included: &[bool]) -> Result<Self, RegressionError> {
        let n_rows = included.len();
        if let Some(col) = columns.iter().find(|c| c.len() != n_rows) {
            return Err(RegressionError::LengthMismatch {
                field: "column",
                expected: n_rows,
                got: col.len(),
            });
        }
        let p = columns.len();
        let n_eq = included.iter().filter(|m| **m).count();
        if n_eq <= p {
            return Err(RegressionError::TooFewPoints {
                degree: 0,
                needed: p + 1,
                got: n_eq,
            });
        }
        let (groups, member) = indicator_groups(columns, n_rows);
        let mut counts = vec![0usize; groups.len()];
        for (m, &fitted) in member.iter().zip(included) {
            if let (Some(g), true) = (m, fitted) {
                counts[*g] += 1;
            }
        }
        let mut design = Self {
            columns: columns.to_vec(),
            included: included.to_vec(),
            n_eq,
            groups,
            member,
            counts,
            others: Vec::new(),
            means: Vec::new(),
            dense: None,
        };
        if design.groups.is_empty() {
            design.others = (0..p).collect();
            design.dense = Some(DenseFactor::new(columns, included)?);
            return Ok(design);
        }
        design.others = (0..p).filter(|j| !design.groups.contains(j)).collect();
        design.means = design
            .others
            .iter()
            .map(|&j| design.group_means(&columns[j]))
            .collect();
        let reduced: Vec<Vec<f64>> = design
            .others
            .iter()
            .zip(&design.means)
            .map(|(&j, m)| design.demeaned(&columns[j], m))
            .collect();
        if !reduced.is_empty() {
            design.dense = Some(DenseFactor::new(&reduced, included)?);
        }
        Ok(design)
    }

    /// Each group's mean of `v` over its fitted rows.
    fn group_means(&self, v: &[f64]) -> Vec<f64> {
        let mut sums = vec![0.0; self.groups.len()];
        for (r, m) in self.member.iter().enumerate() {
            if let (Some(g), true) = (m, self.included[r]) {
                sums[*g] += v[r];
            }
        }
        sums.iter()
            .zip(&self.counts)
            .map(|(s, n)| if *n > 0 { s / *n as f64 } else { 0.0 })
            .collect()
    }

    /// `v` less its group's mean on every row of a group.
    fn demeaned(&self, v: &[f64], means: &[f64]) -> Vec<f64> {
        v.iter()
            .zip(&self.member)
            .map(|(x, m)| m.map_or(*x, |g| x - means[g]))
            .collect()
    }

    /// The minimum-norm fit of `rhs` (as long as the mask).
    ///
    /// # Errors
    /// [`RegressionError::LengthMismatch`] for a `rhs` of another length than the mask;
    /// [`RegressionError::NonFinite`] for NaN/∞ in a fitted row of `rhs`;
    /// [`RegressionError::InvalidArgument`] if the SVD does not converge.
    pub fn fit(&self, rhs: &[f64]) -> Result<MinimumNormFit, RegressionError> {
        if rhs.len() != self.included.len() {
            return Err(RegressionError::LengthMismatch {
                field: "rhs",
                expected: self.included.len(),
                got: rhs.len(),
            });
        }
        // Checked here, not after the demeaning: a NaN spreads over its group there, and
        // the error would name the group's first row.
        if let Some(index) = (0..rhs.len()).find(|&r| self.included[r] && !rhs[r].is_finite()) {
            return Err(RegressionError::NonFinite {
                field: "rhs",
                index,
            });
        }
        let fit = self.solve(rhs)?;
        let p = fit.cov.nrows();
        Ok(MinimumNormFit {
            coefficients: fit.coef,
            covariance: (0..p)
                .map(|a| (0..p).map(|b| fit.cov[(a, b)]).collect())
                .collect(),
            residuals: fit.residual,
            rss: fit.rss,
            equations: fit.n_eq,
            rank: fit.rank,
        })
    }

    /// The whole problem: disjoint 0/1 indicator columns are eliminated exactly by demeaning
    /// every other column and the target within each indicator's rows (Frisch–Waugh–Lovell);
    /// the rest is solved densely ([`DenseFactor`]). Coefficients, residuals and covariances
    /// are those of the full problem: an offset is c_g = ȳ_g − m_gᵀ·β with m_g the group
    /// means of the other columns, var c_g = σ²/n_g + m_gᵀ·Cov β·m_g, cov(c_g, β) =
    /// −m_gᵀ·Cov β.
    fn solve(&self, target: &[f64]) -> Result<DenseFit, RegressionError> {
        let cols = &self.columns;
        let p = cols.len();
        if self.groups.is_empty() {
            let Some(dense) = &self.dense else {
                return Err(RegressionError::InvalidArgument(
                    "no dense factor".to_owned(),
                ));
            };
            let mut fit = dense.fit(target)?;
            fit.residual = residual_of(cols, &fit.coef, target);
            return Ok(fit);
        }
        let (groups, others, means) = (&self.groups, &self.others, &self.means);
        let y_means = self.group_means(target);
        let y_reduced = self.demeaned(target, &y_means);
        let (beta, cov_beta, rank_reduced) = match &self.dense {
            None => (Vec::new(), DMatrix::<f64>::zeros(0, 0), 0),
            Some(dense) => {
                let fit = dense.fit(&y_reduced)?;
                // Back to the residual variance of the full problem below.
                let dof = fit.n_eq.saturating_sub(fit.rank).max(1) as f64;
                let sigma2 = fit.rss / dof;
                let unit = if sigma2 > 0.0 {
                    fit.cov / sigma2
                } else {
                    DMatrix::zeros(others.len(), others.len())
                };
                (fit.coef, unit, fit.rank)
            }
        };
        let mut coef = vec![0.0; p];
        for (i, &j) in others.iter().enumerate() {
            coef[j] = beta[i];
        }
        for (g, &j) in groups.iter().enumerate() {
            coef[j] = y_means[g]
                - (0..others.len())
                    .map(|i| beta[i] * means[i][g])
                    .sum::<f64>();
        }
        let mut residual = target.to_vec();
        for &j in others {
            if coef[j] != 0.0 {
                for (r, c) in residual.iter_mut().zip(&cols[j]) {
                    *r -= coef[j] * c;
                }
            }
        }
        for (r, m) in residual.iter_mut().zip(&self.member) {
            if let Some(g) = m {
                *r -= coef[groups[*g]];
            }
        }
        let rss: f64 = (0..target.len())
            .filter(|&r| self.included[r])
            .map(|r| residual[r] * residual[r])
            .sum();
        let rank = rank_reduced + self.counts.iter().filter(|n| **n > 0).count();
        let sigma2 = rss / self.n_eq.saturating_sub(rank).max(1) as f64;
        let cov = offsets_covariance(p, others, groups, &self.counts, means, &cov_beta);
        Ok(DenseFit {
            coef,
            cov: cov * sigma2,
            residual,
            rss,
            n_eq: self.n_eq,
            rank,
        })
    }
}

/// The minimum-norm solution of the symmetric positive semi-definite system `matrix·x = rhs`
/// (a normal matrix the caller accumulated, e.g. streamed with other unknowns eliminated):
/// x = matrix⁺·rhs by SVD, singular values at or below `relative_tolerance` times the largest
/// diagonal entry dropped.
///
/// # Errors
/// [`RegressionError::LengthMismatch`] for a matrix that is not `rhs.len()` square;
/// [`RegressionError::NonFinite`] for NaN/∞; [`RegressionError::InvalidArgument`] if the SVD
/// does not converge.
pub fn minimum_norm_solve(
    matrix: &[Vec<f64>],
    rhs: &[f64],
    relative_tolerance: f64,
) -> Result<Vec<f64>, RegressionError> {
    let m = rhs.len();
    if matrix.len() != m {
        return Err(RegressionError::LengthMismatch {
            field: "matrix rows",
            expected: m,
            got: matrix.len(),
        });
    }
    if let Some(row) = matrix.iter().find(|r| r.len() != m) {
        return Err(RegressionError::LengthMismatch {
            field: "matrix row",
            expected: m,
            got: row.len(),
        });
    }
    if let Some(index) = matrix.iter().position(|r| r.iter().any(|v| !v.is_finite())) {
        return Err(RegressionError::NonFinite {
            field: "matrix row",
            index,
        });
    }
    if let Some(index) = rhs.iter().position(|v| !v.is_finite()) {
        return Err(RegressionError::NonFinite {
            field: "rhs",
            index,
        });
    }
    if m == 0 {
        return Ok(Vec::new());
    }
    let a = DMatrix::from_fn(m, m, |i, j| matrix[i][j]);
    let b = DVector::from_column_slice(rhs);
    let top = a.diagonal().iter().copied().fold(0.0_f64, f64::max);
    let x = a
        .svd(true, true)
        .solve(&b, relative_tolerance * top.max(1e-300))
        .map_err(|e| RegressionError::InvalidArgument(format!("SVD: {e}")))?;
    Ok(x.iter().copied().collect())
}

/// The disjoint 0/1 indicator columns, greedily in column order (an indicator joins when it
/// is disjoint from those already taken): their column indices and each row's group.
fn indicator_groups(cols: &[Vec<f64>], n_rows: usize) -> (Vec<usize>, Vec<Option<usize>>) {
    let mut member: Vec<Option<usize>> = vec![None; n_rows];
    let mut groups: Vec<usize> = Vec::new();
    for (j, col) in cols.iter().enumerate() {
        // One pass: 0/1 values only, disjoint from the groups taken so far.
        let mut ones = Vec::new();
        let mut usable = true;
        for (r, v) in col.iter().enumerate() {
            if *v == 1.0 {
                if member[r].is_some() {
                    usable = false;
                    break;
                }
                ones.push(r);
            } else if *v != 0.0 {
                usable = false;
                break;
            }
        }
        if usable && !ones.is_empty() {
            for r in ones {
                member[r] = Some(groups.len());
            }
            groups.push(j);
        }
    }
    (groups, member)
}

/// The unit covariance (per σ²) of all coefficients of [`FactoredDesign::solve`] from that of
/// the non-offset ones (`cov_beta`): var c_g = 1/n_g + m_gᵀ·C·m_g,
/// cov(c_g, β) = −m_gᵀ·C, cov(c_g, c_h) = m_gᵀ·C·m_h (g ≠ h).
fn offsets_covariance(
    p: usize,
    others: &[usize],
    groups: &[usize],
    counts: &[usize],
    means: &[Vec<f64>],
    cov_beta: &DMatrix<f64>,
) -> DMatrix<f64> {
    let mut cov = DMatrix::<f64>::zeros(p, p);
    let m_of = |g: usize| DVector::from_iterator(others.len(), means.iter().map(|m| m[g]));
    let cm: Vec<DVector<f64>> = (0..groups.len()).map(|g| cov_beta * m_of(g)).collect();
    for (a, &ja) in others.iter().enumerate() {
        for (b, &jb) in others.iter().enumerate() {
            cov[(ja, jb)] = cov_beta[(a, b)];
        }
        for (g, &jg) in groups.iter().enumerate() {
            cov[(ja, jg)] = -cm[g][a];
            cov[(jg, ja)] = -cm[g][a];
        }
    }
    for (g, &jg) in groups.iter().enumerate() {
        for (h, &jh) in groups.iter().enumerate() {
            let mut v = m_of(g).dot(&cm[h]);
            if g == h && counts[g] > 0 {
                v += 1.0 / counts[g] as f64;
            }
            cov[(jg, jh)] = v;
        }
    }
    cov
}

/// How Qᵀ·y is formed for the thin QR factorisation X = Q·R.
enum QFactor {
    /// CholeskyQR2 (Yamamoto et al. 2015): R₁ from the Cholesky factor of XᵀX, then again on
    /// X·R₁⁻¹, R = R₂·R₁ — as accurate as Householder for a column-scaled design with
    /// condition number below ~10⁸, and built from matrix products (fast). Holds Xᵀ:
    /// Qᵀ·y = R⁻ᵀ·Xᵀ·y.
    CholeskyQr2(DMatrix<f64>),
    /// Householder QR, when a Gram matrix is not positive definite (collinear or nearly
    /// collinear columns) or the CholeskyQR2 factor is not finite or not well conditioned.
    Householder(nalgebra::linalg::QR<f64, nalgebra::Dyn, nalgebra::Dyn>),
}

/// R of CholeskyQR2, when it is finite and well conditioned (diagonal ratio as a cheap
/// condition estimate); otherwise Householder decides the rank.
fn cholesky_qr2(x: &DMatrix<f64>) -> Option<(DMatrix<f64>, DMatrix<f64>)> {
    // Products through the blocked GEMM (a transposed copy is cheaper than dot-product loops
    // over the tall matrix).
    let xt = x.transpose();
    let r1 = (&xt * x).cholesky()?.l().transpose();
    let x1 = x * r1.clone().try_inverse()?;
    let r2 = (x1.transpose() * &x1).cholesky()?.l().transpose();
    let r = &r2 * &r1;
    let d: Vec<f64> = r.diagonal().iter().map(|v| v.abs()).collect();
    let dmax = d.iter().fold(0.0_f64, |m, v| m.max(*v));
    let dmin = d.iter().fold(f64::INFINITY, |m, v| m.min(*v));
    (r.iter().all(|v| v.is_finite()) && dmin > 1e-6 * dmax).then_some((xt, r))
}

/// The dense part's design, factored once for any number of targets: the fitted rows, the
/// column scales, the column-normalised design X = Q·R and the SVD of the small R, so that
/// X = (Q·U)·S·Vᵀ and (Q·U)ᵀ·y = Uᵀ·(Qᵀ·y). An SVD of the tall X itself (its n×p left factor
/// accumulated by Givens rotations) made a movie of 40 frames (28 000 equations, 170
/// columns) take minutes.
struct DenseFactor {
    rows: Vec<usize>,
    scale: Vec<f64>,
    x: DMatrix<f64>,
    q: QFactor,
    r: DMatrix<f64>,
    /// U, Vᵀ and the singular values of R; `None` when the SVD did not converge.
    svd: Option<(DMatrix<f64>, DMatrix<f64>, DVector<f64>)>,
}

impl DenseFactor {
    /// Factors `cols` over the rows `included`.
    fn new(cols: &[Vec<f64>], included: &[bool]) -> Result<Self, RegressionError> {
        let rows: Vec<usize> = (0..included.len()).filter(|&r| included[r]).collect();
        let p = cols.len();
        if rows.len() <= p {
            return Err(RegressionError::TooFewPoints {
                degree: 0,
                needed: p + 1,
                got: rows.len(),
            });
        }
        let mut scale = vec![1.0; p];
        let mut x = DMatrix::<f64>::zeros(rows.len(), p);
        for (j, col) in cols.iter().enumerate() {
            let norm = rows.iter().map(|&r| col[r] * col[r]).sum::<f64>().sqrt();
            scale[j] = if norm > 0.0 && norm.is_finite() {
                1.0 / norm
            } else {
                0.0
            };
            for (i, &r) in rows.iter().enumerate() {
                x[(i, j)] = col[r] * scale[j];
            }
        }
        if let Some(index) = (0..rows.len()).find(|&i| !x.row(i).iter().all(|v| v.is_finite())) {
            return Err(RegressionError::NonFinite {
                field: "design",
                index: rows[index],
            });
        }
        let (q, r) = match cholesky_qr2(&x) {
            Some((xt, r)) => (QFactor::CholeskyQr2(xt), r),
            None => {
                let qr = x.clone().qr();
                let r = qr.r();
                (QFactor::Householder(qr), r)
            }
        };
        Ok(Self::with_svd(rows, scale, x, q, r))
    }

    fn with_svd(
        rows: Vec<usize>,
        scale: Vec<f64>,
        x: DMatrix<f64>,
        q: QFactor,
        r: DMatrix<f64>,
    ) -> Self {
        let svd = r.clone().svd(true, true);
        let svd = match (svd.u, svd.v_t) {
            (Some(u), Some(v_t)) => Some((u, v_t, svd.singular_values)),
            _ => None,
        };
        Self {
            rows,
            scale,
            x,
            q,
            r,
            svd,
        }
    }

    /// This design factored by Householder QR.
    fn householder(&self) -> Self {
        let qr = self.x.clone().qr();
        let r = qr.r();
        Self::with_svd(
            self.rows.clone(),
            self.scale.clone(),
            self.x.clone(),
            QFactor::Householder(qr),
            r,
        )
    }

    /// The minimum-norm fit of `target` (rows as long as the mask the design was factored
    /// over).
    fn fit(&self, target: &[f64]) -> Result<DenseFit, RegressionError> {
        let y = DVector::from_iterator(self.rows.len(), self.rows.iter().map(|&r| target[r]));
        if let Some(index) = y.iter().position(|v| !v.is_finite()) {
            return Err(RegressionError::NonFinite {
                field: "rhs",
                index: self.rows[index],
            });
        }
        let p = self.scale.len();
        let qty_head = match &self.q {
            QFactor::CholeskyQr2(xt) => {
                let qty = self.r.transpose().solve_lower_triangular(&(xt * &y));
                match qty {
                    Some(qty) if qty.iter().all(|v| v.is_finite()) => qty,
                    _ => return self.householder().fit(target),
                }
            }
            QFactor::Householder(qr) => {
                let mut qty = y.clone();
                qr.q_tr_mul(&mut qty);
                DVector::from_iterator(p, qty.iter().take(p).copied())
            }
        };
        let Some((uu, vt, singular_values)) = &self.svd else {
            return Err(RegressionError::InvalidArgument(
                "SVD did not converge".to_owned(),
            ));
        };
        let smax = singular_values.iter().fold(0.0_f64, |m, v| m.max(*v));
        let tol = smax * MINIMUM_NORM_TOLERANCE;
        let uty = uu.transpose() * &qty_head;
        let mut z = DVector::<f64>::zeros(p);
        let mut rank = 0usize;
        let mut inv_s2 = DVector::<f64>::zeros(p);
        for i in 0..singular_values.len() {
            let s = singular_values[i];
            if s > tol {
                z[i] = uty[i] / s;
                inv_s2[i] = 1.0 / (s * s);
                rank += 1;
            }
        }
        let beta_scaled = vt.transpose() * z;
        let coef: Vec<f64> = (0..p).map(|j| beta_scaled[j] * self.scale[j]).collect();
        let fitted = &self.x * &beta_scaled;
        let rss: f64 = (0..self.rows.len())
            .map(|i| (y[i] - fitted[i]).powi(2))
            .sum();
        let dof = self.rows.len().saturating_sub(rank).max(1) as f64;
        let sigma2 = rss / dof;
        let v = vt.transpose();
        let mut cov = DMatrix::<f64>::zeros(p, p);
        for a in 0..p {
            for b in 0..p {
                let mut sum = 0.0;
                for i in 0..singular_values.len() {
                    sum += v[(a, i)] * v[(b, i)] * inv_s2[i];
                }
                cov[(a, b)] = sum * sigma2 * self.scale[a] * self.scale[b];
            }
        }
        Ok(DenseFit {
            coef,
            cov,
            residual: Vec::new(),
            rss,
            n_eq: self.rows.len(),
            rank,
        })
    }
}

/// The dense solution without the indicator elimination (the reference the elimination is
/// tested against).
#[cfg(test)]
fn solve_dense(
    cols: &[Vec<f64>],
    target: &[f64],
    included: &[bool],
) -> Result<DenseFit, RegressionError> {
    let mut fit = DenseFactor::new(cols, included)?.fit(target)?;
    fit.residual = residual_of(cols, &fit.coef, target);
    Ok(fit)
}

/// `target − Σ coef_j·col_j` on every row.
fn residual_of(cols: &[Vec<f64>], coef: &[f64], target: &[f64]) -> Vec<f64> {
    let mut residual = target.to_vec();
    for (j, col) in cols.iter().enumerate() {
        if coef[j] != 0.0 {
            for (r, c) in residual.iter_mut().zip(col) {
                *r -= coef[j] * c;
            }
        }
    }
    residual
}

#[cfg(test)]
mod tests;
