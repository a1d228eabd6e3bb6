//! Corrected coordinates along an arbitrary trajectory (eq. 5).

use spm_hal::{CountPoint, NmPoint};

use crate::field::CorrectionField;
use crate::{CorrectionError, Quadrature};

fn check_path(path: &[CountPoint]) -> Result<(), CorrectionError> {
    if path.is_empty() {
        return Err(CorrectionError::Empty("trajectory without points"));
    }
    for (i, p) in path.iter().enumerate() {
        if !p.is_finite() {
            return Err(CorrectionError::NonFinite {
                what: "trajectory point",
                index: i,
            });
        }
    }
    Ok(())
}

/// Eq. (5) literally: the trajectory moves in unit steps (Δx, Δy ∈ {−1, 0, +1} counts); each
/// step adds K̄x·Δx + K̄yx·Δy to x̄ and K̄yy·Δy to ȳ, with the coefficients taken at the point the
/// step arrives at. Returns the corrected position of every point, nm, the first at (0, 0).
///
/// Eqs. (1) and (5) literally, x̄, ȳ as sums of the local unit steps (each a
/// [`crate::FormCoefficients::increment`]): the reference the tests check the integral route
/// against; not in the equation index, which names what production runs.
///
/// # Errors
/// [`CorrectionError::Empty`], [`CorrectionError::NonFinite`],
/// [`CorrectionError::NotAUnitStep`].
pub fn correct_unit_steps<F: CorrectionField + ?Sized>(
    field: &F,
    path: &[CountPoint],
) -> Result<Vec<NmPoint>, CorrectionError> {
    check_path(path)?;
    let mut out = Vec::with_capacity(path.len());
    let (mut x, mut y) = (0.0, 0.0);
    out.push(NmPoint::from_nm(0.0, 0.0));
    for (index, w) in path.windows(2).enumerate() {
        let dx = w[1].x.value() - w[0].x.value();
        let dy = w[1].y.value() - w[0].y.value();
        let unit = |d: f64| d == 0.0 || d == 1.0 || d == -1.0;
        if !(unit(dx) && unit(dy)) {
            return Err(CorrectionError::NotAUnitStep {
                index,
                dx_counts: dx,
                dy_counts: dy,
            });
        }
        let [ix, iy] = field.form(w[1].x.value(), w[1].y.value()).increment(dx, dy);
        x += ix;
        y += iy;
        out.push(NmPoint::from_nm(x, y));
    }
    Ok(out)
}

/// Eq. (5) as an integral along a piecewise-linear trajectory through `vertices`: on each
/// straight segment p(τ) = a + τ(b − a), τ ∈ [0, 1],
/// `Δx̄ = ∫ [K̄x(p)·(b−a)_x + K̄yx(p)·(b−a)_y] dτ`, `Δȳ = ∫ K̄yy(p)·(b−a)_y dτ`.
/// Axis-parallel segments use the field's analytic integrals when it has them (so a polyline
/// along a raster path reproduces [`crate::correct_raster`]); other segments use `quadrature`
/// (panels no longer than its `max_panel_counts` along the segment). Returns the corrected
/// position of every vertex, nm, the first at (0, 0).
///
/// Implements eqs. (1) and (5) along a piecewise-linear path, by quadrature.
///
/// # Errors
/// [`CorrectionError::Empty`], [`CorrectionError::NonFinite`].
pub fn correct_polyline<F: CorrectionField + ?Sized>(
    field: &F,
    vertices: &[CountPoint],
    quadrature: &Quadrature,
) -> Result<Vec<NmPoint>, CorrectionError> {
    check_path(vertices)?;
    let mut out = Vec::with_capacity(vertices.len());
    let (mut x, mut y) = (0.0, 0.0);
    out.push(NmPoint::from_nm(0.0, 0.0));
    for w in vertices.windows(2) {
        let (ax, ay) = (w[0].x.value(), w[0].y.value());
        let (bx, by) = (w[1].x.value(), w[1].y.value());
        let (dx, dy) = (bx - ax, by - ay);
        let (sx, sy) = segment(field, quadrature, (ax, ay), (dx, dy));
        x += sx;
        y += sy;
        out.push(NmPoint::from_nm(x, y));
    }
    Ok(out)
}

/// (Δx̄, Δȳ) of one straight segment from `a` by `d` counts.
fn segment<F: CorrectionField + ?Sized>(
    field: &F,
    quadrature: &Quadrature,
    a: (f64, f64),
    d: (f64, f64),
) -> (f64, f64) {
    let (ax, ay) = a;
    let (dx, dy) = d;
    if dx == 0.0 && dy == 0.0 {
        return (0.0, 0.0);
    }
    if dy == 0.0
        && let Some(v) = field.integral_kx_along_x(ax, ax + dx, ay)
    {
        return (v, 0.0);
    }
    if dx == 0.0
        && let (Some(p), Some(q)) = (
            field.integral_kyx_along_y(ax, ay, ay + dy),
            field.integral_kyy_along_y(ax, ay, ay + dy),
        )
    {
        return (p, q);
    }
    // τ-integral with panels scaled to the segment length in counts.
    let length = dx.hypot(dy);
    let (mut sx, mut sy) = (0.0, 0.0);
    let panels = (length / quadrature.max_panel_counts())
        .ceil()
        .clamp(1.0, 1e9) as usize;
    let h = 1.0 / panels as f64;
    for p in 0..panels {
        let mid = (p as f64 + 0.5) * h;
        for (node, weight) in quadrature.nodes().iter().zip(quadrature.weights()) {
            let tau = mid + 0.5 * h * node;
            let [ix, iy] = field.form(ax + tau * dx, ay + tau * dy).increment(dx, dy);
            let w = 0.5 * h * weight;
            sx += w * ix;
            sy += w * iy;
        }
    }
    (sx, sy)
}
