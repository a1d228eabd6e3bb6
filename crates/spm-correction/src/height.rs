//! Heights through Kz (eq. 2, Kz^r): Z counts → nm.

use crate::raster::RasterGeometry;
use crate::{CorrectionError, PlaneSurfaces};

/// Heights in nm of a raster's Z values (counts, `[row * columns + column]` in scanner
/// geometry): `z_nm = Kz^r(x, y) · (z − z_ref(x, y))`, where z_ref is the bowl surface of the
/// plane when present (so the X,Y⇒Z crosstalk of a flat sample is removed) and the plane's
/// z otherwise. NaN pixels (missing data) stay NaN.
///
/// Implements eq. (1), its z̄ line: z̄ = Kz^r(x, y)·Δz.
///
/// # Errors
/// [`CorrectionError::MissingSurface`] without Kz; [`CorrectionError::SizeMismatch`];
/// [`CorrectionError::NonFinite`] for an infinite height or a non-finite Kz/bowl value.
pub fn heights_nm(
    plane: &PlaneSurfaces,
    geometry: &RasterGeometry,
    z_counts: &[f64],
) -> Result<Vec<f64>, CorrectionError> {
    let kz = plane
        .kz_nm_per_count
        .as_ref()
        .ok_or(CorrectionError::MissingSurface("kz_nm_per_count"))?;
    let n = geometry.pixel_count();
    if z_counts.len() != n {
        return Err(CorrectionError::SizeMismatch {
            what: "z_counts",
            expected: n,
            got: z_counts.len(),
        });
    }
    let mut out = Vec::with_capacity(n);
    for (index, &z) in z_counts.iter().enumerate() {
        if z.is_infinite() {
            return Err(CorrectionError::NonFinite {
                what: "z_counts",
                index,
            });
        }
        let (i, j) = (index % geometry.columns, index / geometry.columns);
        let (x, y) = (geometry.x_counts(i as f64), geometry.y_counts(j as f64));
        let k = kz.surface.evaluate(x, y);
        let reference = plane
            .bowl_z_counts
            .as_ref()
            .map_or(plane.z_counts, |b| b.surface.evaluate(x, y));
        if !(k.is_finite() && reference.is_finite()) {
            return Err(CorrectionError::NonFinite {
                what: "Kz or bowl on the raster",
                index,
            });
        }
        out.push(k * (z - reference));
    }
    Ok(out)
}
