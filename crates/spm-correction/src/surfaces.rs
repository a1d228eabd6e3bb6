//! The set of regression surfaces a calibration produces (`surfaces.json`).
//!
//! Per Z plane (eq. 2): K̄x^r, K̄y^r (nm/count), α^r (rad), Kz^r (nm/count), the product
//! surfaces K̄yx^r = K̄y sin α, K̄yy^r = K̄y cos α of eq. (11), and optionally the bowl (the Z
//! reading of a flat sample, X,Y⇒Z crosstalk); each a [`Polynomial2`] with its σ (eq. 14) and
//! degree. Plus provenance: scanner, fit time window, number of records.
//!
//! ## The calibration file (format version 2)
//! Version 2 is one self-describing calibration file: beside the surfaces it records the
//! calibrated region of every plane ([`CountRegion`], where the records lie — a correction
//! outside it extrapolates the polynomials), and in [`Provenance`] the counts convention
//! ([`CountsConvention`]) and nominal sensitivity the run used, the spmcal version and commit
//! that fitted it, when, and a SHA-256 digest of the records used. Every field added in version
//! 2 is optional on the way in, so a version-1 `surfaces.json` is still read (its calibrated
//! region is then the normalisation box of its K̄x polynomial, which is the records' extent by
//! construction of the fit).
//!
//! The stored LCC surfaces stay separate (DESIGN §9): the products are an *additional* pair,
//! used by eq. (12); [`Route::Exact`] ignores them.

use serde::{Deserialize, Serialize};
use spm_regression::Polynomial2;

use crate::CorrectionError;
use crate::field::{
    CorrectionField, FormCoefficients, LineAntiderivative, ProductField, SurfaceField,
};

/// Version of the `surfaces.json` layout written by this crate.
///
/// History: 1 the surfaces and a short provenance; 2 the calibrated region per plane and the
/// full provenance; 3 the scanner dynamics ([`crate::hysteresis::ScannerDynamics`]). Every
/// older version is read.
pub const SURFACES_FORMAT_VERSION: u32 = 3;

/// One regression surface with its statistics.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FittedSurface {
    /// The polynomial (eq. 6); its unit is that of the field holding it.
    pub surface: Polynomial2,
    /// σ of eq. (14): RMS deviation of the records from the surface, same unit.
    pub sigma: f64,
    /// Total degree (equal to `surface.degree()`; kept for readers of the JSON).
    pub degree: u32,
}

impl FittedSurface {
    /// A surface with its σ; the degree is taken from the polynomial.
    #[must_use]
    pub fn new(surface: Polynomial2, sigma: f64) -> Self {
        let degree = surface.degree();
        Self {
            surface,
            sigma,
            degree,
        }
    }

    /// A constant surface with σ = 0.
    ///
    /// # Errors
    /// [`CorrectionError::Regression`] for a non-finite value.
    pub fn constant(value: f64) -> Result<Self, CorrectionError> {
        Ok(Self::new(Polynomial2::constant(value)?, 0.0))
    }

    fn validate(&self, name: &str) -> Result<(), CorrectionError> {
        if self.degree != self.surface.degree() {
            return Err(CorrectionError::InvalidSurfaces(format!(
                "{name}: degree {} but the polynomial has degree {}",
                self.degree,
                self.surface.degree()
            )));
        }
        if !(self.sigma.is_finite() && self.sigma >= 0.0) {
            return Err(CorrectionError::InvalidSurfaces(format!(
                "{name}: sigma {} must be finite and >= 0",
                self.sigma
            )));
        }
        Ok(())
    }
}

/// The surfaces of one fixed Z position of the scanner (eq. 2, one z_i).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlaneSurfaces {
    /// Z-manipulator position of the plane, counts.
    pub z_counts: f64,
    /// Number of CDB records the plane was fitted from.
    pub n_records: usize,
    /// K̄x^r, nm/count.
    pub kx_nm_per_count: FittedSurface,
    /// K̄y^r, nm/count.
    pub ky_nm_per_count: FittedSurface,
    /// α^r, rad.
    pub alpha_rad: FittedSurface,
    /// K̄yx^r ≈ K̄y sin α (eq. 11), nm/count.
    pub kyx_nm_per_count: FittedSurface,
    /// K̄yy^r ≈ K̄y cos α (eq. 11), nm/count.
    pub kyy_nm_per_count: FittedSurface,
    /// Kz^r, nm/count (absent when the calibration measured no vertical size).
    #[serde(default)]
    pub kz_nm_per_count: Option<FittedSurface>,
    /// The bowl: Z reading (counts) of a flat, level sample at (x, y) in this plane (X,Y⇒Z
    /// crosstalk). Heights are measured from it when present.
    #[serde(default)]
    pub bowl_z_counts: Option<FittedSurface>,
    /// Where the plane's records lie (LCS centres, counts), widened by half a net cell (the
    /// area the outermost nodes stand for). Absent in version-1 files: see
    /// [`PlaneSurfaces::calibrated_region`].
    #[serde(default)]
    pub calibrated_region_counts: Option<CountRegion>,
    /// How K̄x and the product surfaces were fitted (absent in older files: independently).
    #[serde(default)]
    pub form: SurfaceForm,
}

/// An axis-parallel rectangle of the scanner field, counts.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CountRegion {
    /// Lower x bound, counts.
    pub x_min_counts: f64,
    /// Upper x bound, counts.
    pub x_max_counts: f64,
    /// Lower y bound, counts.
    pub y_min_counts: f64,
    /// Upper y bound, counts.
    pub y_max_counts: f64,
}

impl CountRegion {
    /// The bounding box of points, widened by `margin_counts` on every side; `None` for no
    /// point or a non-finite one.
    #[must_use]
    pub fn bounding(x: &[f64], y: &[f64], margin_counts: f64) -> Option<Self> {
        if x.is_empty() || x.len() != y.len() || !margin_counts.is_finite() {
            return None;
        }
        let fold = |v: &[f64]| {
            v.iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &t| {
                    (lo.min(t), hi.max(t))
                })
        };
        let (x_min, x_max) = fold(x);
        let (y_min, y_max) = fold(y);
        let region = Self {
            x_min_counts: x_min - margin_counts,
            x_max_counts: x_max + margin_counts,
            y_min_counts: y_min - margin_counts,
            y_max_counts: y_max + margin_counts,
        };
        region.is_valid().then_some(region)
    }

    /// Finite bounds with min ≤ max on both axes.
    #[must_use]
    pub fn is_valid(&self) -> bool {
        [
            self.x_min_counts,
            self.x_max_counts,
            self.y_min_counts,
            self.y_max_counts,
        ]
        .iter()
        .all(|v| v.is_finite())
            && self.x_min_counts <= self.x_max_counts
            && self.y_min_counts <= self.y_max_counts
    }

    /// How far (counts) the point lies outside the region; 0 inside or on the border.
    #[must_use]
    pub fn distance_outside_counts(&self, x: f64, y: f64) -> f64 {
        let dx = (self.x_min_counts - x).max(x - self.x_max_counts).max(0.0);
        let dy = (self.y_min_counts - y).max(y - self.y_max_counts).max(0.0);
        dx.hypot(dy)
    }
}

/// How scanner counts relate to the field: what a file's raster in counts means.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CountsConvention {
    /// Signed counts, 0 at the field centre, +x along the fast axis of an unrotated frame and
    /// +y along its slow axis (away from the first line of an upward scan). spm-sim, the
    /// Nanonis backend and the files spmcal writes use it.
    CentredSigned,
}

impl CountsConvention {
    /// The name stored in files (`spmcal_counts_convention`).
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::CentredSigned => "centred_signed",
        }
    }

    /// Parses a stored name.
    #[must_use]
    pub fn parse(text: &str) -> Option<Self> {
        match text.trim() {
            "centred_signed" => Some(Self::CentredSigned),
            _ => None,
        }
    }
}

/// Which coefficients drive the correction.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Route {
    /// K̄x^r, K̄y^r, α^r as stored, products formed pointwise (eq. 9; eq. 10 for planes).
    Exact,
    /// K̄x^r with the product surfaces of eq. (11); fully analytic (eq. 12).
    #[default]
    Products,
}

/// The correction field of one plane, by route (implements [`CorrectionField`]).
#[derive(Debug, Clone, PartialEq)]
pub enum PlaneField {
    /// [`Route::Exact`].
    Exact(SurfaceField),
    /// [`Route::Products`].
    Products(ProductField),
}

impl CorrectionField for PlaneField {
    fn form(&self, x: f64, y: f64) -> FormCoefficients {
        match self {
            Self::Exact(f) => f.form(x, y),
            Self::Products(f) => f.form(x, y),
        }
    }
    fn forms(&self, x: &[f64], y: &[f64], out: &mut [FormCoefficients]) {
        match self {
            Self::Exact(f) => f.forms(x, y, out),
            Self::Products(f) => f.forms(x, y, out),
        }
    }
    fn integral_kx_along_x(&self, x_a: f64, x_b: f64, y: f64) -> Option<f64> {
        match self {
            Self::Exact(f) => f.integral_kx_along_x(x_a, x_b, y),
            Self::Products(f) => f.integral_kx_along_x(x_a, x_b, y),
        }
    }
    fn integral_kyx_along_y(&self, x: f64, y_a: f64, y_b: f64) -> Option<f64> {
        match self {
            Self::Exact(f) => f.integral_kyx_along_y(x, y_a, y_b),
            Self::Products(f) => f.integral_kyx_along_y(x, y_a, y_b),
        }
    }
    fn integral_kyy_along_y(&self, x: f64, y_a: f64, y_b: f64) -> Option<f64> {
        match self {
            Self::Exact(f) => f.integral_kyy_along_y(x, y_a, y_b),
            Self::Products(f) => f.integral_kyy_along_y(x, y_a, y_b),
        }
    }
    fn kx_line(&self, y: f64) -> Option<LineAntiderivative> {
        match self {
            Self::Exact(f) => f.kx_line(y),
            Self::Products(f) => f.kx_line(y),
        }
    }
}

impl PlaneSurfaces {
    /// The calibrated region: the stored one, or for a version-1 file the normalisation box
    /// (centre ± half-range) of the K̄x polynomial, which the fit sets to the records' extent.
    #[must_use]
    pub fn calibrated_region(&self) -> CountRegion {
        self.calibrated_region_counts.unwrap_or_else(|| {
            let (cx, cy) = self.kx_nm_per_count.surface.center();
            let (sx, sy) = self.kx_nm_per_count.surface.scale();
            CountRegion {
                x_min_counts: cx - sx,
                x_max_counts: cx + sx,
                y_min_counts: cy - sy,
                y_max_counts: cy + sy,
            }
        })
    }

    /// A plane with constant coefficients (a lumped calibration), products exact, no Kz/bowl.
    ///
    /// # Errors
    /// [`CorrectionError::Regression`] for non-finite values.
    pub fn constant(
        z_counts: f64,
        kx_nm_per_count: f64,
        ky_nm_per_count: f64,
        alpha_rad: f64,
    ) -> Result<Self, CorrectionError> {
        let form = crate::FormCoefficients::from_lcc(kx_nm_per_count, ky_nm_per_count, alpha_rad);
        Ok(Self {
            z_counts,
            n_records: 0,
            kx_nm_per_count: FittedSurface::constant(kx_nm_per_count)?,
            ky_nm_per_count: FittedSurface::constant(ky_nm_per_count)?,
            alpha_rad: FittedSurface::constant(alpha_rad)?,
            kyx_nm_per_count: FittedSurface::constant(form.kyx_nm_per_count)?,
            kyy_nm_per_count: FittedSurface::constant(form.kyy_nm_per_count)?,
            kz_nm_per_count: None,
            bowl_z_counts: None,
            calibrated_region_counts: None,
            form: SurfaceForm::Independent,
        })
    }

    /// The correction field of this plane by `route`.
    #[must_use]
    pub fn field(&self, route: Route) -> PlaneField {
        match route {
            Route::Exact => PlaneField::Exact(SurfaceField {
                kx_nm_per_count: self.kx_nm_per_count.surface.clone(),
                ky_nm_per_count: self.ky_nm_per_count.surface.clone(),
                alpha_rad: self.alpha_rad.surface.clone(),
            }),
            Route::Products => PlaneField::Products(ProductField {
                kx_nm_per_count: self.kx_nm_per_count.surface.clone(),
                kyx_nm_per_count: self.kyx_nm_per_count.surface.clone(),
                kyy_nm_per_count: self.kyy_nm_per_count.surface.clone(),
            }),
        }
    }

    /// Checks finiteness and degrees.
    ///
    /// # Errors
    /// [`CorrectionError::InvalidSurfaces`].
    pub fn validate(&self) -> Result<(), CorrectionError> {
        if let Some(region) = &self.calibrated_region_counts
            && !region.is_valid()
        {
            return Err(CorrectionError::InvalidSurfaces(format!(
                "plane z = {}: calibrated_region_counts {region:?} must be finite with min <= max",
                self.z_counts
            )));
        }
        if !self.z_counts.is_finite() {
            return Err(CorrectionError::InvalidSurfaces(format!(
                "plane z {} is not finite",
                self.z_counts
            )));
        }
        self.kx_nm_per_count.validate("kx_nm_per_count")?;
        self.ky_nm_per_count.validate("ky_nm_per_count")?;
        self.alpha_rad.validate("alpha_rad")?;
        self.kyx_nm_per_count.validate("kyx_nm_per_count")?;
        self.kyy_nm_per_count.validate("kyy_nm_per_count")?;
        if let Some(kz) = &self.kz_nm_per_count {
            kz.validate("kz_nm_per_count")?;
        }
        if let Some(b) = &self.bowl_z_counts {
            b.validate("bowl_z_counts")?;
        }
        Ok(())
    }
}

/// Where the surfaces came from.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Provenance {
    /// Scanner the calibration belongs to.
    pub scanner_id: String,
    /// Earliest record used (RFC 3339 date-time), if the fit was restricted.
    #[serde(default)]
    pub fit_since: Option<String>,
    /// Latest record used (RFC 3339 date-time), if the fit was restricted.
    #[serde(default)]
    pub fit_until: Option<String>,
    /// Number of CDB records used over all planes.
    pub n_records: usize,
    /// How the calibration's counts relate to the field (version 2).
    #[serde(default)]
    pub counts_convention: Option<CountsConvention>,
    /// The nominal sensitivity the calibration runs assumed (their plans'
    /// `standard.nominal_nm_per_count`), nm per count (version 2).
    #[serde(default)]
    pub nominal_nm_per_count: Option<f64>,
    /// The runs whose records were used (version 2).
    #[serde(default)]
    pub run_ids: Vec<String>,
    /// SHA-256 (hex) of the records used, in the CDB's export order (version 2).
    #[serde(default)]
    pub records_sha256: Option<String>,
    /// When the file was written (RFC 3339 UTC; version 2).
    #[serde(default)]
    pub written_utc: Option<String>,
    /// The spmcal version that fitted it (version 2).
    #[serde(default)]
    pub spmcal_version: Option<String>,
    /// The git commit spmcal was built from, when known (version 2).
    #[serde(default)]
    pub spmcal_commit: Option<String>,
}

/// How a plane's K̄x and product surfaces K̄yx, K̄yy (the correction 1-form, eq. 5) are fitted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SurfaceForm {
    /// Each surface by itself (eqs. 2 and 11): the form is exact only as far as the records
    /// make it.
    #[default]
    Independent,
    /// The derivatives of two fitted potentials, x̄(x, y) and ȳ(y)
    /// (`spm_regression::fit_exact_form`): the form is exact, so the corrected position does
    /// not depend on the raster's path, and K̄yy has no x term for a raster to read at the
    /// start of its lines.
    Exact,
}

impl SurfaceForm {
    /// The name in files and on the command line.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Independent => "independent",
            Self::Exact => "exact",
        }
    }

    /// The form named `text` ([`Self::as_str`]).
    #[must_use]
    pub fn parse(text: &str) -> Option<Self> {
        [Self::Independent, Self::Exact]
            .into_iter()
            .find(|f| f.as_str() == text)
    }
}

/// All regression surfaces of one scanner: what `surfaces.json` holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SurfaceSet {
    /// Layout version ([`SURFACES_FORMAT_VERSION`]; every older one is read).
    pub format_version: u32,
    /// Scanner, time window, record count.
    pub provenance: Provenance,
    /// One entry per Z plane.
    pub planes: Vec<PlaneSurfaces>,
    /// The scanner's dynamics identified in situ (v3; absent = static correction only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dynamics: Option<crate::hysteresis::ScannerDynamics>,
}

impl SurfaceSet {
    /// A validated set.
    ///
    /// # Errors
    /// As [`SurfaceSet::validate`].
    pub fn new(
        provenance: Provenance,
        planes: Vec<PlaneSurfaces>,
    ) -> Result<Self, CorrectionError> {
        let set = Self {
            format_version: SURFACES_FORMAT_VERSION,
            provenance,
            planes,
            dynamics: None,
        };
        set.validate()?;
        Ok(set)
    }

    /// Checks: at least one plane, every plane valid, no two planes at the same z.
    ///
    /// # Errors
    /// [`CorrectionError::EmptySurfaces`], [`CorrectionError::InvalidSurfaces`].
    pub fn validate(&self) -> Result<(), CorrectionError> {
        if self.planes.is_empty() {
            return Err(CorrectionError::EmptySurfaces);
        }
        if self.format_version > SURFACES_FORMAT_VERSION {
            return Err(CorrectionError::InvalidSurfaces(format!(
                "format version {} is newer than {SURFACES_FORMAT_VERSION}",
                self.format_version
            )));
        }
        if let Some(k) = self.provenance.nominal_nm_per_count
            && !(k.is_finite() && k > 0.0)
        {
            return Err(CorrectionError::InvalidSurfaces(format!(
                "provenance.nominal_nm_per_count {k} must be finite and > 0"
            )));
        }
        for p in &self.planes {
            p.validate()?;
        }
        if let Some(d) = &self.dynamics {
            d.validate()
                .map_err(|e| CorrectionError::InvalidSurfaces(format!("dynamics: {e}")))?;
        }
        for (i, a) in self.planes.iter().enumerate() {
            if self.planes[i + 1..]
                .iter()
                .any(|b| b.z_counts == a.z_counts)
            {
                return Err(CorrectionError::InvalidSurfaces(format!(
                    "two planes at z = {} counts",
                    a.z_counts
                )));
            }
        }
        Ok(())
    }

    /// Parses and validates `surfaces.json` text.
    ///
    /// # Errors
    /// [`CorrectionError::Json`] (including invalid polynomials), and as
    /// [`SurfaceSet::validate`].
    pub fn from_json_str(text: &str) -> Result<Self, CorrectionError> {
        let set: Self =
            serde_json::from_str(text).map_err(|e| CorrectionError::Json(e.to_string()))?;
        set.validate()?;
        Ok(set)
    }

    /// Pretty JSON text of this set.
    ///
    /// # Errors
    /// [`CorrectionError::Json`] (not expected for a valid set).
    pub fn to_json_string(&self) -> Result<String, CorrectionError> {
        serde_json::to_string_pretty(self).map_err(|e| CorrectionError::Json(e.to_string()))
    }

    /// The plane whose z is nearest `z_counts` (ties: the lower plane).
    ///
    /// Planes are *not* interpolated in z: the surfaces of different planes are fitted
    /// independently (own degree and normalisation), the coarse Z stage sets them far apart, and
    /// an image is taken at one Z plane. Use [`SurfaceSet::bracketing_planes`] to blend the
    /// fields of two planes yourself ([`BlendedField`]).
    ///
    /// # Errors
    /// [`CorrectionError::EmptySurfaces`], [`CorrectionError::NonFinite`].
    pub fn plane_nearest(&self, z_counts: f64) -> Result<&PlaneSurfaces, CorrectionError> {
        crate::error::check_finite_scalar("z_counts", z_counts)?;
        self.planes
            .iter()
            .min_by(|a, b| {
                let da = (a.z_counts - z_counts).abs();
                let db = (b.z_counts - z_counts).abs();
                da.total_cmp(&db).then(a.z_counts.total_cmp(&b.z_counts))
            })
            .ok_or(CorrectionError::EmptySurfaces)
    }

    /// The two planes bracketing `z_counts` and the weight of the upper one (0 at the lower
    /// plane, 1 at the upper); outside the planes' range the nearest plane twice with weight 0.
    ///
    /// # Errors
    /// [`CorrectionError::EmptySurfaces`], [`CorrectionError::NonFinite`].
    pub fn bracketing_planes(
        &self,
        z_counts: f64,
    ) -> Result<(&PlaneSurfaces, &PlaneSurfaces, f64), CorrectionError> {
        crate::error::check_finite_scalar("z_counts", z_counts)?;
        let below = self
            .planes
            .iter()
            .filter(|p| p.z_counts <= z_counts)
            .max_by(|a, b| a.z_counts.total_cmp(&b.z_counts));
        let above = self
            .planes
            .iter()
            .filter(|p| p.z_counts > z_counts)
            .min_by(|a, b| a.z_counts.total_cmp(&b.z_counts));
        match (below, above) {
            (Some(lo), Some(hi)) => Ok((
                lo,
                hi,
                (z_counts - lo.z_counts) / (hi.z_counts - lo.z_counts),
            )),
            (Some(p), None) | (None, Some(p)) => Ok((p, p, 0.0)),
            (None, None) => Err(CorrectionError::EmptySurfaces),
        }
    }
}

/// Linear blend (1 − w)·lower + w·upper of two fields' 1-form coefficients (interpolation
/// between Z planes). Integrals are linear in the integrand, so analytic integrals blend too.
#[derive(Debug, Clone, PartialEq)]
pub struct BlendedField<F> {
    /// Field at the lower plane.
    pub lower: F,
    /// Field at the upper plane.
    pub upper: F,
    /// Weight of the upper field, in [0, 1].
    pub weight_upper: f64,
}

impl<F: CorrectionField> BlendedField<F> {
    /// The one plane that carries the whole weight (w = 0 or 1: an image on a plane, or a
    /// set of one plane), which is then evaluated alone — the same value as the blend for
    /// finite coefficients, at half the cost.
    fn single(&self) -> Option<&F> {
        if self.weight_upper == 0.0 {
            Some(&self.lower)
        } else if self.weight_upper == 1.0 {
            Some(&self.upper)
        } else {
            None
        }
    }
}

impl<F: CorrectionField> CorrectionField for BlendedField<F> {
    fn forms(&self, x: &[f64], y: &[f64], out: &mut [FormCoefficients]) {
        if let Some(f) = self.single() {
            return f.forms(x, y, out);
        }
        for (o, (&x, &y)) in out.iter_mut().zip(x.iter().zip(y)) {
            *o = self.form(x, y);
        }
    }
    fn form(&self, x: f64, y: f64) -> FormCoefficients {
        if let Some(f) = self.single() {
            return f.form(x, y);
        }
        let (a, b, w) = (
            self.lower.form(x, y),
            self.upper.form(x, y),
            self.weight_upper,
        );
        FormCoefficients {
            kx_nm_per_count: (1.0 - w) * a.kx_nm_per_count + w * b.kx_nm_per_count,
            kyx_nm_per_count: (1.0 - w) * a.kyx_nm_per_count + w * b.kyx_nm_per_count,
            kyy_nm_per_count: (1.0 - w) * a.kyy_nm_per_count + w * b.kyy_nm_per_count,
        }
    }
    fn integral_kx_along_x(&self, x_a: f64, x_b: f64, y: f64) -> Option<f64> {
        if let Some(f) = self.single() {
            return f.integral_kx_along_x(x_a, x_b, y);
        }
        let w = self.weight_upper;
        Some(
            (1.0 - w) * self.lower.integral_kx_along_x(x_a, x_b, y)?
                + w * self.upper.integral_kx_along_x(x_a, x_b, y)?,
        )
    }
    fn integral_kyx_along_y(&self, x: f64, y_a: f64, y_b: f64) -> Option<f64> {
        if let Some(f) = self.single() {
            return f.integral_kyx_along_y(x, y_a, y_b);
        }
        let w = self.weight_upper;
        Some(
            (1.0 - w) * self.lower.integral_kyx_along_y(x, y_a, y_b)?
                + w * self.upper.integral_kyx_along_y(x, y_a, y_b)?,
        )
    }
    fn integral_kyy_along_y(&self, x: f64, y_a: f64, y_b: f64) -> Option<f64> {
        if let Some(f) = self.single() {
            return f.integral_kyy_along_y(x, y_a, y_b);
        }
        let w = self.weight_upper;
        Some(
            (1.0 - w) * self.lower.integral_kyy_along_y(x, y_a, y_b)?
                + w * self.upper.integral_kyy_along_y(x, y_a, y_b)?,
        )
    }
}
