//! Calibration accuracy against a ground truth (the simulator's oracle, DESIGN §11).
//!
//! Two figures per correction method, both relative to the *true* local
//! calibration coefficients of the simulated scanner ([`spm_hal::truth::GroundTruth::true_lcc`],
//! the small-signal LCCs at the reference state):
//!
//! - **Residual distortion** over the calibrated region: a raster covering the
//!   region is corrected (eq. 9) once with the method's surfaces and once with
//!   the oracle's true LCC field; the difference of the two coordinate maps,
//!   after removing the best rigid motion (rotation and translation are
//!   unobservable), is the residual distortion. RMS and max in pm.
//! - **Lattice-constant error on corrected images anywhere in the field**: at
//!   every point of an evaluation grid, a small image (the size of a
//!   calibration aperture) is corrected with the method and with the truth; the
//!   local map between the two (finite differences at the image centre) is
//!   applied to the three lattice vectors of the standard; the relative change
//!   of their mean length is the lattice-constant error that image shows. This
//!   is exact (no detection noise), so it measures the calibration, not the
//!   recognition.
//!
//! Both compare like with like: the same raster trajectory, the same equations;
//! only the coefficient field differs.

use crate::cubic::CubicMap;
use crate::rigid::rigid_residuals;
use serde::Serialize;
use spm_correction::{
    CoordinateMap, CorrectionError, CorrectionField, FnField, FormCoefficients, Integration,
    Parallelism, PlaneSurfaces, RasterGeometry, Route, correct_raster,
};
use spm_hal::truth::GroundTruth;
use spm_hal::{CountPoint, Counts, ScanDirection};

/// The region and sampling of the evaluation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EvaluationGrid {
    /// Smallest x of the calibrated region, counts.
    pub x_min_counts: f64,
    /// Largest x, counts.
    pub x_max_counts: f64,
    /// Smallest y, counts.
    pub y_min_counts: f64,
    /// Largest y, counts.
    pub y_max_counts: f64,
    /// Z position of the plane, counts.
    pub z_counts: f64,
    /// Pixels per side of the field-wide raster (≥ 2).
    pub field_pixels: usize,
    /// Image places per side for the lattice-constant figure (≥ 1).
    pub image_places: usize,
    /// Side of each small image, counts.
    pub image_side_counts: f64,
    /// Lattice constant of the standard, nm.
    pub lattice_constant_nm: f64,
}

/// Accuracy of one method (report.json's `M`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Accuracy {
    /// RMS residual distortion over the region, pm.
    pub rms_pm: f64,
    /// Max residual distortion over the region, pm.
    pub max_pm: f64,
    /// RMS residual distortion as % of the lattice constant.
    pub rms_pct_of_lattice: f64,
    /// Mean |lattice-constant error| over the image places, %.
    pub mean_lattice_error_pct: f64,
    /// Max |lattice-constant error| over the image places, %.
    pub max_lattice_error_pct: f64,
}

/// The oracle's true LCC field as a correction field.
fn true_field<'a, T: GroundTruth + Sync + ?Sized>(
    oracle: &'a T,
    z_counts: f64,
) -> FnField<impl Fn(f64, f64) -> FormCoefficients + Sync + 'a> {
    FnField(move |x: f64, y: f64| {
        let lcc = oracle.true_lcc(CountPoint::from_counts(x, y), Counts(z_counts));
        FormCoefficients::from_lcc(lcc.kx_nm_per_count, lcc.ky_nm_per_count, lcc.alpha_rad)
    })
}

fn raster(
    field: &(impl CorrectionField + ?Sized),
    geometry: &RasterGeometry,
) -> Result<CoordinateMap, CorrectionError> {
    correct_raster(
        field,
        geometry,
        ScanDirection::Direct,
        &Integration::default(),
        Parallelism::Sequential,
    )
}

/// Evaluates one method's surfaces against the oracle.
pub fn evaluate<T: GroundTruth + Sync + ?Sized>(
    oracle: &T,
    plane: &PlaneSurfaces,
    grid: &EvaluationGrid,
) -> Result<Accuracy, CorrectionError> {
    evaluate_field(oracle, &plane.field(Route::Exact), grid)
}

/// How the per-image polynomial baseline's one image was taken.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolynomialImage {
    /// Reference features per side of the image (a grating pitch over the region, ≥ 4).
    pub control_points: usize,
    /// Time of the whole image (first line to last line), s.
    pub image_time_s: f64,
    /// Drift velocity during the image (x, y), nm/s: the sample moves by v·t under the tip.
    pub drift_nm_per_s: (f64, f64),
}

/// The per-image 3rd-order polynomial baseline of DESIGN §11: the conventional
/// correction of one image of the whole region taken over a reference standard
/// with known feature positions. The tip sees the feature at true position P
/// where the scanner's true map T(x, y) equals P + d(t), t = the time the slow
/// axis reaches y, d = drift; the polynomial P̂(x, y) (total degree 3 per
/// coordinate, least squares over `control_points`² features) is fitted to the
/// known positions P = T − d. Best case for the baseline: the feature positions
/// are exact (no detection noise); its errors are the polynomial's lack of fit
/// (hysteresis, creep, higher orders) and the drift during the one slow image.
/// The correction field is the polynomial's local shape: its Jacobian with the
/// local rotation removed, as (K̄x, K̄y sin α, K̄y cos α).
///
/// # Errors
/// As the correction of a raster; `CorrectionError::Empty` when the polynomial fit is
/// singular.
pub fn polynomial_baseline<T: GroundTruth + Sync + ?Sized>(
    oracle: &T,
    grid: &EvaluationGrid,
    image: &PolynomialImage,
) -> Result<Accuracy, CorrectionError> {
    let n = image.control_points.max(4);
    let truth = true_field(oracle, grid.z_counts);
    let (x0, y0) = (grid.x_min_counts, grid.y_min_counts);
    let side = (grid.x_max_counts - x0).max(grid.y_max_counts - y0);
    let step = side / (n - 1) as f64;
    let geometry = RasterGeometry::new(CountPoint::from_counts(x0, y0), Counts(step), n, n)?;
    let map = raster(&truth, &geometry)?;
    let mut points = Vec::with_capacity(n * n);
    let mut targets = Vec::with_capacity(n * n);
    for row in 0..n {
        let t_s = image.image_time_s * row as f64 / (n - 1) as f64;
        for column in 0..n {
            if let Some(p) = map.point(column, row) {
                points.push([x0 + column as f64 * step, y0 + row as f64 * step]);
                targets.push([
                    p.x.value() - image.drift_nm_per_s.0 * t_s,
                    p.y.value() - image.drift_nm_per_s.1 * t_s,
                ]);
            }
        }
    }
    let centre = [x0 + side / 2.0, y0 + side / 2.0];
    // The correction field is the polynomial's local shape (its Jacobian, rotation removed).
    let field = CubicMap::fit_normalised(&points, &targets, centre, side / 2.0)
        .map_err(|_| CorrectionError::Empty("polynomial baseline: singular fit"))?;
    evaluate_field(oracle, &field, grid)
}

/// The residual distortion at every pixel of the field-wide raster of the evaluation (the
/// figure [`Accuracy::rms_pm`] and [`Accuracy::max_pm`] summarise), for the report's map.
#[derive(Debug, Clone, PartialEq)]
pub struct ResidualField {
    /// Pixels per side of the raster.
    pub pixels: usize,
    /// Commanded position of pixel (0, 0), counts.
    pub origin_counts: [f64; 2],
    /// Spacing of the raster's pixels along both axes, counts.
    pub step_counts: f64,
    /// |method − truth| after the best rigid motion, nm, row by row from the smallest y
    /// (NaN where a pixel has no corrected position).
    pub residual_nm: Vec<f64>,
}

/// The residual distortion of `method` against the oracle at every pixel of the evaluation's
/// field-wide raster (see the module doc): the raster corrected with the method and with the
/// true LCC field, the best rigid motion removed.
///
/// # Errors
/// As the correction of a raster.
pub fn residual_field<T: GroundTruth + Sync + ?Sized>(
    oracle: &T,
    method: &(impl CorrectionField + ?Sized),
    grid: &EvaluationGrid,
) -> Result<ResidualField, CorrectionError> {
    let truth = true_field(oracle, grid.z_counts);
    let n = grid.field_pixels.max(2);
    let step = ((grid.x_max_counts - grid.x_min_counts).max(grid.y_max_counts - grid.y_min_counts))
        / (n - 1) as f64;
    let geometry = RasterGeometry::new(
        CountPoint::from_counts(grid.x_min_counts, grid.y_min_counts),
        Counts(step),
        n,
        n,
    )?;
    let measured = raster(method, &geometry)?;
    let expected = raster(&truth, &geometry)?;
    let mut a = Vec::with_capacity(n * n);
    let mut b = Vec::with_capacity(n * n);
    let mut at = Vec::with_capacity(n * n);
    for row in 0..n {
        for column in 0..n {
            if let (Some(p), Some(q)) = (measured.point(column, row), expected.point(column, row)) {
                a.push([p.x.value(), p.y.value()]);
                b.push([q.x.value(), q.y.value()]);
                at.push(row * n + column);
            }
        }
    }
    let residuals = rigid_residuals(&a, &b);
    let mut residual_nm = vec![f64::NAN; n * n];
    for (k, r) in at.into_iter().zip(residuals) {
        residual_nm[k] = r;
    }
    Ok(ResidualField {
        pixels: n,
        origin_counts: [grid.x_min_counts, grid.y_min_counts],
        step_counts: step,
        residual_nm,
    })
}

/// Evaluates any correction field against the oracle (see the module doc).
pub fn evaluate_field<T: GroundTruth + Sync + ?Sized>(
    oracle: &T,
    method: &(impl CorrectionField + ?Sized),
    grid: &EvaluationGrid,
) -> Result<Accuracy, CorrectionError> {
    let truth = true_field(oracle, grid.z_counts);

    // Field-wide residual distortion.
    let residuals: Vec<f64> = residual_field(oracle, method, grid)?
        .residual_nm
        .into_iter()
        .filter(|r| !r.is_nan())
        .collect();
    let rms_nm = spm_regression::rms(&residuals).unwrap_or(0.0);
    let max_nm = residuals.iter().fold(0.0_f64, |m, r| m.max(*r));

    // Lattice-constant error on small corrected images across the field.
    let places = grid.image_places.max(1);
    let side = grid.image_side_counts;
    let image_pixels = 9usize;
    let image_step = side / (image_pixels - 1) as f64;
    let mut errors = Vec::with_capacity(places * places);
    for j in 0..places {
        for i in 0..places {
            let fraction = |k: usize| {
                if places == 1 {
                    0.5
                } else {
                    k as f64 / (places - 1) as f64
                }
            };
            let cx = grid.x_min_counts
                + side / 2.0
                + fraction(i) * (grid.x_max_counts - grid.x_min_counts - side).max(0.0);
            let cy = grid.y_min_counts
                + side / 2.0
                + fraction(j) * (grid.y_max_counts - grid.y_min_counts - side).max(0.0);
            let geometry = RasterGeometry::new(
                CountPoint::from_counts(cx - side / 2.0, cy - side / 2.0),
                Counts(image_step),
                image_pixels,
                image_pixels,
            )?;
            let c_method =
                local_jacobian(&raster(method, &geometry)?, image_pixels / 2, image_step);
            let c_true = local_jacobian(&raster(&truth, &geometry)?, image_pixels / 2, image_step);
            if let Some(error) = lattice_error(c_method, c_true) {
                errors.push(error * 100.0);
            }
        }
    }
    let mean_abs = errors.iter().map(|e| e.abs()).sum::<f64>() / errors.len().max(1) as f64;
    let max_abs = errors.iter().fold(0.0_f64, |m, e| m.max(e.abs()));
    Ok(Accuracy {
        rms_pm: rms_nm * 1e3,
        max_pm: max_nm * 1e3,
        rms_pct_of_lattice: rms_nm / grid.lattice_constant_nm * 100.0,
        mean_lattice_error_pct: mean_abs,
        max_lattice_error_pct: max_abs,
    })
}

/// ∂(x̄, ȳ)/∂(x, y) at pixel (c, c) by central differences, nm/count.
fn local_jacobian(map: &CoordinateMap, c: usize, step_counts: f64) -> [[f64; 2]; 2] {
    let p = |column: usize, row: usize| {
        map.point(column, row)
            .map_or([f64::NAN; 2], |q| [q.x.value(), q.y.value()])
    };
    let (xp, xm, yp, ym) = (p(c + 1, c), p(c - 1, c), p(c, c + 1), p(c, c - 1));
    let h = 2.0 * step_counts;
    [
        [(xp[0] - xm[0]) / h, (yp[0] - ym[0]) / h],
        [(xp[1] - xm[1]) / h, (yp[1] - ym[1]) / h],
    ]
}

/// Relative lattice-constant error of a corrected image: the true lattice
/// vectors (in the true corrected frame) mapped through C_method·C_true⁻¹,
/// mean length over the three directions of a triangular lattice, minus one.
/// The error is invariant to the lattice orientation only on average, so the
/// three orientations 0°, 60°, 120° and their rotations by 30° are averaged.
fn lattice_error(c_method: [[f64; 2]; 2], c_true: [[f64; 2]; 2]) -> Option<f64> {
    let det = c_true[0][0] * c_true[1][1] - c_true[0][1] * c_true[1][0];
    if !(det.is_finite() && det.abs() > 0.0) {
        return None;
    }
    let inv = [
        [c_true[1][1] / det, -c_true[0][1] / det],
        [-c_true[1][0] / det, c_true[0][0] / det],
    ];
    let t = [
        [
            c_method[0][0] * inv[0][0] + c_method[0][1] * inv[1][0],
            c_method[0][0] * inv[0][1] + c_method[0][1] * inv[1][1],
        ],
        [
            c_method[1][0] * inv[0][0] + c_method[1][1] * inv[1][0],
            c_method[1][0] * inv[0][1] + c_method[1][1] * inv[1][1],
        ],
    ];
    let mut worst: f64 = 0.0;
    for offset_deg in [0.0_f64, 30.0] {
        let mut sum = 0.0;
        for k in 0..3 {
            let angle = (offset_deg + 60.0 * k as f64).to_radians();
            let (s, c) = angle.sin_cos();
            let v = [t[0][0] * c + t[0][1] * s, t[1][0] * c + t[1][1] * s];
            sum += v[0].hypot(v[1]);
        }
        let error = sum / 3.0 - 1.0;
        if error.abs() > worst.abs() {
            worst = error;
        }
    }
    worst.is_finite().then_some(worst)
}

/// The RMS, in %, of the node-mean K̄x and K̄y errors: the records grouped by their node
/// (x, y, z), each group's mean K̄x and K̄y against the truth at the group's mean LCS centre
/// (at the instrument's present Z); `None` without records.
pub fn node_mean_k_rms_pct<T: GroundTruth + ?Sized>(
    records: &[spm_records::LccRecord],
    truth: &T,
) -> Option<f64> {
    let mut by_node: std::collections::BTreeMap<(i64, i64, i64), Vec<&spm_records::LccRecord>> =
        std::collections::BTreeMap::new();
    for r in records {
        by_node
            .entry((r.node_x_counts, r.node_y_counts, r.node_z_counts))
            .or_default()
            .push(r);
    }
    let z = truth.z_now();
    let mut errors = Vec::new();
    for group in by_node.values() {
        let n = group.len() as f64;
        let mean =
            |f: fn(&spm_records::LccRecord) -> f64| group.iter().map(|r| f(r)).sum::<f64>() / n;
        let lcc = truth.true_lcc(
            CountPoint::from_counts(mean(|r| r.lcs_x_counts), mean(|r| r.lcs_y_counts)),
            z,
        );
        errors.push((mean(|r| r.kx_nm_per_count) / lcc.kx_nm_per_count - 1.0) * 100.0);
        errors.push((mean(|r| r.ky_nm_per_count) / lcc.ky_nm_per_count - 1.0) * 100.0);
    }
    spm_regression::rms(&errors)
}

/// Measured node LCCs against the oracle's true LCCs at the LCS centres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct NodeLccError {
    /// Records compared.
    pub n: usize,
    /// Mean (K̄x measured / true − 1), % (bias).
    pub kx_mean_pct: f64,
    /// RMS (K̄x measured / true − 1), %.
    pub kx_rms_pct: f64,
    /// Mean (K̄y measured / true − 1), %.
    pub ky_mean_pct: f64,
    /// RMS (K̄y measured / true − 1), %.
    pub ky_rms_pct: f64,
    /// Mean (α measured − true), mrad.
    pub alpha_mean_mrad: f64,
    /// RMS (α measured − true), mrad.
    pub alpha_rms_mrad: f64,
}

/// Every record's LCCs against the truth at its LCS centre (at the instrument's present Z):
/// mean and RMS per coefficient; `None` without records.
#[must_use]
pub fn node_lcc_error(
    oracle: &dyn GroundTruth,
    all: &[spm_records::LccRecord],
) -> Option<NodeLccError> {
    let z = oracle.z_now();
    let mut e = Vec::with_capacity(all.len());
    for r in all {
        let truth = oracle.true_lcc(CountPoint::from_counts(r.lcs_x_counts, r.lcs_y_counts), z);
        e.push((
            (r.kx_nm_per_count / truth.kx_nm_per_count - 1.0) * 100.0,
            (r.ky_nm_per_count / truth.ky_nm_per_count - 1.0) * 100.0,
            (r.alpha_rad - truth.alpha_rad) * 1e3,
        ));
    }
    if e.is_empty() {
        return None;
    }
    let n = e.len() as f64;
    let mean = |f: fn(&(f64, f64, f64)) -> f64| e.iter().map(f).sum::<f64>() / n;
    let rms = |f: fn(&(f64, f64, f64)) -> f64| {
        spm_regression::rms(&e.iter().map(f).collect::<Vec<_>>()).unwrap_or(0.0)
    };
    Some(NodeLccError {
        n: e.len(),
        kx_mean_pct: mean(|v| v.0),
        kx_rms_pct: rms(|v| v.0),
        ky_mean_pct: mean(|v| v.1),
        ky_rms_pct: rms(|v| v.1),
        alpha_mean_mrad: mean(|v| v.2),
        alpha_rms_mrad: rms(|v| v.2),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use spm_hal::truth::TrueLcc;
    use spm_hal::{NmVelocity, Seconds};

    #[test]
    fn a_one_percent_isotropic_scale_error_is_a_one_percent_lattice_error() {
        let truth = [[0.02, 0.001], [0.0, 0.021]];
        let method = [[0.0202, 0.00101], [0.0, 0.02121]];
        let error = lattice_error(method, truth);
        assert!(error.is_some_and(|e| (e - 0.01).abs() < 1e-9), "{error:?}");
        assert_eq!(lattice_error(truth, truth), Some(0.0));
    }

    /// An oracle whose true LCCs are linear in x (K̄x = 0.02·(1 + gx·x)) and y
    /// (K̄y = 0.021·(1 + gy·y)), α = 0: the true map is a quadratic, inside the polynomial
    /// baseline's cubic basis (a constant one with both slopes 0).
    struct LinearLcc {
        gx_per_count: f64,
        gy_per_count: f64,
        ky_nm_per_count: f64,
    }

    /// K̄x linear in x, K̄y linear in y.
    const SLOPED: LinearLcc = LinearLcc {
        gx_per_count: 1e-5,
        gy_per_count: -2e-5,
        ky_nm_per_count: 0.021,
    };

    /// A scanner of one constant sensitivity everywhere, orthogonal.
    const CONSTANT: LinearLcc = LinearLcc {
        gx_per_count: 0.0,
        gy_per_count: 0.0,
        ky_nm_per_count: 0.02,
    };

    impl GroundTruth for LinearLcc {
        fn true_lcc(&self, commanded: CountPoint, _z: Counts) -> TrueLcc {
            TrueLcc {
                kx_nm_per_count: 0.02 * (1.0 + self.gx_per_count * commanded.x.value()),
                ky_nm_per_count: self.ky_nm_per_count
                    * (1.0 + self.gy_per_count * commanded.y.value()),
                alpha_rad: 0.0,
            }
        }
        fn z_now(&self) -> Counts {
            Counts(0.0)
        }
        fn now(&self) -> Seconds {
            Seconds(0.0)
        }
        fn drift_velocity(&self, _t: Seconds) -> NmVelocity {
            NmVelocity::default()
        }
        fn reference_gain(&self) -> [f64; 2] {
            [1.0, 1.0]
        }
    }

    #[test]
    fn the_polynomial_baseline_recovers_a_field_inside_its_basis() -> Result<(), CorrectionError> {
        let grid = EvaluationGrid {
            x_min_counts: -2000.0,
            x_max_counts: 2000.0,
            y_min_counts: -2000.0,
            y_max_counts: 2000.0,
            z_counts: 0.0,
            field_pixels: 21,
            image_places: 3,
            image_side_counts: 200.0,
            lattice_constant_nm: 0.246,
        };
        let image = PolynomialImage {
            control_points: 12,
            image_time_s: 100.0,
            drift_nm_per_s: (0.0, 0.0),
        };
        let accuracy = polynomial_baseline(&SLOPED, &grid, &image)?;
        // Solver round-off only: far below a picometre and 1e-9 % of the lattice constant.
        assert!(accuracy.max_pm < 1e-6, "{accuracy:?}");
        assert!(accuracy.max_lattice_error_pct < 1e-9, "{accuracy:?}");
        Ok(())
    }

    /// Issue 27's residual map: a method 1 % too sensitive everywhere maps every pixel 1 %
    /// too far from the others; after the best rigid motion (the centroids matched, no
    /// rotation by symmetry) each pixel is off by 1 % of its true distance from the raster's
    /// centre — a closed form per pixel. The summary figures are the map's RMS and max.
    #[test]
    fn the_residual_map_of_a_scale_error_grows_with_the_distance_from_the_centre()
    -> Result<(), CorrectionError> {
        let grid = EvaluationGrid {
            x_min_counts: -1000.0,
            x_max_counts: 1000.0,
            y_min_counts: -1000.0,
            y_max_counts: 1000.0,
            z_counts: 0.0,
            field_pixels: 11,
            image_places: 1,
            image_side_counts: 100.0,
            lattice_constant_nm: 0.246,
        };
        let method = PlaneSurfaces::constant(0.0, 0.0202, 0.0202, 0.0)?;
        let field = residual_field(&CONSTANT, &method.field(Route::Exact), &grid)?;
        assert_eq!((field.pixels, field.residual_nm.len()), (11, 121));
        assert_eq!(field.step_counts, 200.0);
        let mut squares = 0.0;
        for row in 0..11 {
            for column in 0..11 {
                let (dx, dy) = (column as f64 - 5.0, row as f64 - 5.0);
                let expected = 0.01 * 0.02 * 200.0 * dx.hypot(dy);
                let got = field.residual_nm[row * 11 + column];
                assert!(
                    (got - expected).abs() < 1e-9,
                    "({column}, {row}): {got} vs {expected}"
                );
                squares += expected * expected;
            }
        }
        let accuracy = evaluate(&CONSTANT, &method, &grid)?;
        assert!((accuracy.rms_pm - 1e3 * (squares / 121.0).sqrt()).abs() < 1e-6);
        assert!((accuracy.max_pm - 1e3 * 0.01 * 0.02 * 200.0 * 50f64.sqrt()).abs() < 1e-6);
        Ok(())
    }

    /// Two nodes against a constant 0.02 / 0.02 nm/count truth: node A's two records average
    /// to +1 % and −1 %, node B's one record is +2 % and 0 %: RMS of (1, −1, 2, 0) = √1.5.
    #[test]
    fn node_mean_errors_average_each_node_first() {
        let record = |node_x: i64, kx: f64, ky: f64| spm_records::LccRecord {
            scanner_id: "s".into(),
            run_id: "r".into(),
            acquired_unix_s: 0.0,
            repeat_index: 0,
            node_index: 0,
            lcs_index: 0,
            node_x_counts: node_x,
            node_y_counts: 0,
            node_z_counts: 0,
            lcs_x_counts: node_x as f64,
            lcs_y_counts: 0.0,
            lcs_z_counts: 0.0,
            kx_nm_per_count: kx,
            ky_nm_per_count: ky,
            alpha_rad: 0.0,
            kz_nm_per_count: None,
            u_kx_nm_per_count: None,
            u_ky_nm_per_count: None,
            u_alpha_rad: None,
            u_kz_nm_per_count: None,
            drift_vx_nm_per_s: 0.0,
            drift_vy_nm_per_s: 0.0,
            cycles_kept: 4,
            cycles_discarded: 0,
            quality: 1.0,
            kz_x_counts: None,
            kz_y_counts: None,
        };
        let records = [
            record(0, 0.0200, 0.0196),
            record(0, 0.0204, 0.0200),
            record(100, 0.0204, 0.0200),
        ];
        let rms = node_mean_k_rms_pct(&records, &CONSTANT).unwrap();
        assert!((rms - 1.5_f64.sqrt()).abs() < 1e-9, "{rms}");
        assert_eq!(node_mean_k_rms_pct(&[], &CONSTANT), None);
    }
}
