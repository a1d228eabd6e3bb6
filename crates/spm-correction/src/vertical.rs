//! The vertical axis in corrections (issue 15): the lateral field for an image's Z level
//! (blending the calibrated Z planes, so the Z⇒X/Y change of the lateral sensitivities is
//! followed), and the bowl of a plane.

use crate::{BlendedField, CorrectionError, PlaneField, Route, SurfaceSet};

/// The lateral correction field at Z level `z_counts` (e.g. an image's mean Z reading):
/// the two calibrated planes bracketing it blended linearly in z (the nearest plane outside
/// their range). With one plane this is that plane's field.
///
/// # Errors
/// [`CorrectionError::EmptySurfaces`], [`CorrectionError::NonFinite`].
pub fn field_at_z(
    set: &SurfaceSet,
    z_counts: f64,
    route: Route,
) -> Result<BlendedField<PlaneField>, CorrectionError> {
    let (lower, upper, weight_upper) = set.bracketing_planes(z_counts)?;
    Ok(BlendedField {
        lower: lower.field(route),
        upper: upper.field(route),
        weight_upper,
    })
}

/// The bowl of the plane nearest `z_counts` at (x, y) relative to its value at the field
/// origin, Z counts: what a flat, level sample shows because of the tube's arc. `None` when
/// the plane has no bowl surface.
///
/// # Errors
/// [`CorrectionError::EmptySurfaces`], [`CorrectionError::NonFinite`].
pub fn bowl_counts(
    set: &SurfaceSet,
    z_counts: f64,
    x_counts: f64,
    y_counts: f64,
) -> Result<Option<f64>, CorrectionError> {
    let plane = set.plane_nearest(z_counts)?;
    Ok(plane
        .bowl_z_counts
        .as_ref()
        .map(|b| b.surface.evaluate(x_counts, y_counts) - b.surface.evaluate(0.0, 0.0)))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::{CorrectionField, PlaneSurfaces, Provenance};

    fn plane(z: f64, kx: f64) -> PlaneSurfaces {
        PlaneSurfaces::constant(z, kx, kx, 0.0).unwrap()
    }

    #[test]
    fn the_field_at_z_blends_the_bracketing_planes() {
        let provenance = Provenance {
            scanner_id: "s".into(),
            fit_since: None,
            fit_until: None,
            n_records: 2,
            ..Provenance::default()
        };
        let set =
            SurfaceSet::new(provenance, vec![plane(0.0, 0.020), plane(10000.0, 0.021)]).unwrap();
        for (z, expected) in [
            (0.0, 0.020),
            (2500.0, 0.02025),
            (10000.0, 0.021),
            (-5.0, 0.020),
        ] {
            let f = field_at_z(&set, z, Route::Exact).unwrap();
            let k = f.form(123.0, -456.0).kx_nm_per_count;
            assert!((k - expected).abs() < 1e-15, "z {z}: {k} vs {expected}");
        }
        assert_eq!(bowl_counts(&set, 0.0, 1.0, 2.0).unwrap(), None);
    }
}
