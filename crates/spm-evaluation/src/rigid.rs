//! The residual of a point set after the best rigid motion: rotation and translation are
//! unobservable in a calibration, so every position figure is taken after removing them.

/// Distances |R·aᵢ + t − bᵢ| after the least-squares rigid motion (R, t) taking a to b.
pub fn rigid_residuals(a: &[[f64; 2]], b: &[[f64; 2]]) -> Vec<f64> {
    let n = a.len().min(b.len());
    if n == 0 {
        return Vec::new();
    }
    let mean = |v: &[[f64; 2]]| {
        let s = v[..n]
            .iter()
            .fold([0.0, 0.0], |s, p| [s[0] + p[0], s[1] + p[1]]);
        [s[0] / n as f64, s[1] / n as f64]
    };
    let (ma, mb) = (mean(a), mean(b));
    // Optimal rotation angle (2-D Procrustes).
    let (mut sxx, mut sxy) = (0.0, 0.0);
    for i in 0..n {
        let p = [a[i][0] - ma[0], a[i][1] - ma[1]];
        let q = [b[i][0] - mb[0], b[i][1] - mb[1]];
        sxx += p[0] * q[0] + p[1] * q[1];
        sxy += p[0] * q[1] - p[1] * q[0];
    }
    let theta = sxy.atan2(sxx);
    let (s, c) = theta.sin_cos();
    (0..n)
        .map(|i| {
            let p = [a[i][0] - ma[0], a[i][1] - ma[1]];
            let r = [c * p[0] - s * p[1], s * p[0] + c * p[1]];
            (r[0] - (b[i][0] - mb[0])).hypot(r[1] - (b[i][1] - mb[1]))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rotated_and_shifted_copy_has_no_residual() {
        let a: Vec<[f64; 2]> = (0..20).map(|i| [i as f64, (i * i) as f64 * 0.1]).collect();
        let (s, c) = 0.3_f64.sin_cos();
        let b: Vec<[f64; 2]> = a
            .iter()
            .map(|p| [c * p[0] - s * p[1] + 5.0, s * p[0] + c * p[1] - 2.0])
            .collect();
        assert!(rigid_residuals(&a, &b).iter().all(|r| *r < 1e-9));
    }
}
