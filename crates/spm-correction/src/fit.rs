//! Regression surfaces from calibration records (eqs. 2, 6, 11, 13, 14): one set of
//! surfaces per Z plane, the degree of each coefficient chosen by BIC, the correction 1-form
//! fitted coefficient by coefficient or as an exact form (the lower BIC), records a
//! misrecognised structure spoilt left out when asked, and the bowl of a plane whose LCS
//! levels were measured.
//!
//! Pure: records in, [`PlaneSurfaces`] and their statistics out. Selecting the records (a
//! CDB query, a time window, a scanner) is the caller's.

use crate::{CountRegion, FittedSurface, PlaneSurfaces, SurfaceForm};
use serde::Serialize;
use spm_records::{LccColumns, LccRecord};
use spm_regression::{Criterion, Field, Observations, SelectionOptions, delta_max, select_degree};

/// Why a plane's surfaces could not be fitted.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FitError {
    /// A plane holds too few valid records for a surface and its σ (eq. 14).
    #[error(
        "the plane z = {z_counts} counts holds {n} valid record(s); a surface with its σ needs \
         at least {MIN_RECORDS_PER_PLANE}"
    )]
    TooFewRecords {
        /// The plane.
        z_counts: i64,
        /// Valid records in it.
        n: usize,
    },
    /// A regression failed (too few points, ill-conditioned).
    #[error("fitting {coefficient} in the plane z = {z_counts} counts: {source}")]
    Regression {
        /// Which coefficient.
        coefficient: &'static str,
        /// The plane.
        z_counts: i64,
        /// The cause.
        source: spm_regression::RegressionError,
    },
}

/// Fewest valid records a plane needs: σ (eq. 14) has n − 1 degrees of freedom for the
/// lowest degree, so one record would report σ = 0.
pub const MIN_RECORDS_PER_PLANE: usize = 2;

/// What `cdb check` accepts of a record's regression inputs: finite centre, K̄x, K̄y > 0,
/// |α| < π/2, Kz > 0 where given.
fn usable(x: f64, y: f64, kx: f64, ky: f64, alpha: f64, kz: Option<f64>) -> bool {
    x.is_finite()
        && y.is_finite()
        && kx.is_finite()
        && kx > 0.0
        && ky.is_finite()
        && ky > 0.0
        && alpha.is_finite()
        && alpha.abs() < std::f64::consts::FRAC_PI_2
        && kz.is_none_or(|kz| kz.is_finite() && kz > 0.0)
}

/// Whether `cdb check` accepts a record's regression inputs (finite centre, K̄x, K̄y > 0,
/// |α| < π/2, Kz > 0 where given): the records a fit uses.
#[must_use]
pub fn record_is_usable(r: &LccRecord) -> bool {
    usable(
        r.lcs_x_counts,
        r.lcs_y_counts,
        r.kx_nm_per_count,
        r.ky_nm_per_count,
        r.alpha_rad,
        r.kz_nm_per_count,
    )
}

/// The surfaces of one Z plane fitted from `records` (all of that plane) by the procedure
/// that makes the calibration file ([`fit_plane`]): the validation's held-out fit.
///
/// # Errors
/// As [`fit_plane`]; [`FitError::TooFewRecords`] below [`MIN_RECORDS_PER_PLANE`].
pub fn fit_plane_of_records(
    z_counts: i64,
    records: &[&LccRecord],
    options: &SurfaceFitOptions,
) -> Result<PlaneSurfaces, FitError> {
    let columns: LccColumns = records.iter().copied().collect();
    if columns.len() < MIN_RECORDS_PER_PLANE {
        return Err(FitError::TooFewRecords {
            z_counts,
            n: columns.len(),
        });
    }
    fit_plane(z_counts, &columns, options).map(|(plane, _)| plane)
}

/// Keeps the records that `cdb check` accepts ([`record_is_usable`]); returns how many were
/// left out.
pub fn keep_valid(columns: &mut LccColumns) -> usize {
    let n = columns.len();
    let keep: Vec<bool> = (0..n)
        .map(|i| {
            usable(
                columns.lcs_x_counts[i],
                columns.lcs_y_counts[i],
                columns.kx_nm_per_count[i],
                columns.ky_nm_per_count[i],
                columns.alpha_rad[i],
                columns.kz_nm_per_count[i],
            )
        })
        .collect();
    let excluded = keep.iter().filter(|k| !**k).count();
    if excluded == 0 {
        return 0;
    }
    *columns = columns.selected(&keep);
    excluded
}

/// How to fit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceFitOptions {
    /// Highest polynomial degree tried per coefficient (eq. 6).
    pub max_degree: u32,
    /// Degree-selection criterion.
    pub criterion: Criterion,
    /// Leave out of a plane's surfaces the records whose residual in K̄x, K̄y or α lies beyond
    /// this many robust standard deviations (`spm_regression::joint_outliers`), refitting
    /// until none does (at most [`MAX_OUTLIER_ROUNDS`] rounds, never below half the plane's
    /// records). For records a misrecognised structure spoilt (measured images: Si_7x7_028,
    /// 4 of 17 records with α 10°–19° off the others' median). Default `None`: every record is fitted.
    pub outlier_sigmas: Option<f64>,
    /// How K̄x, K̄yx and K̄yy are fitted ([`SurfaceForm`]); `None` (the default,
    /// [`Self::bic_up_to`]): per plane, the form with the lower BIC
    /// ([`spm_regression::information_criterion`] over the three coefficients' residuals, each
    /// in units of its independent fit's σ). Sparse or noisy records tend to get the exact
    /// form (Si_7x7_028's 17, the quick simulated job's 9); a dense net whose field's y scale
    /// does vary along x keeps the surfaces one by one (docs/RESULTS.md, stop 44).
    pub form: Option<SurfaceForm>,
}

/// Rounds of outlier rejection at most ([`SurfaceFitOptions::outlier_sigmas`]).
pub const MAX_OUTLIER_ROUNDS: usize = 5;

impl SurfaceFitOptions {
    /// Degrees 0…`max_degree` chosen by BIC, every record fitted, the form chosen by BIC.
    pub fn bic_up_to(max_degree: u32) -> Self {
        Self {
            max_degree,
            criterion: Criterion::Bic,
            outlier_sigmas: None,
            form: None,
        }
    }
}

/// Statistics of one fitted coefficient surface (report.json's `regression`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SurfaceSummary {
    /// Chosen degree.
    pub degree: u32,
    /// σ of eq. (14), the coefficient's unit.
    pub sigma: f64,
    /// Δmax of eq. (13) over the records' extent, reference at the field origin (0, 0).
    pub delta_max: f64,
}

/// Summary of the first plane's surfaces.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RegressionSummary {
    /// K̄x^r (nm/count).
    pub kx: SurfaceSummary,
    /// K̄y^r (nm/count).
    pub ky: SurfaceSummary,
    /// α^r (rad).
    pub alpha: SurfaceSummary,
    /// Kz^r (nm/count), when measured.
    pub kz: Option<SurfaceSummary>,
    /// The bowl (Z counts of the LCSs over the plane), when the plan measured the LCS levels.
    pub bowl: Option<SurfaceSummary>,
    /// Records left out as outliers ([`SurfaceFitOptions::outlier_sigmas`]).
    pub outliers_left_out: usize,
}

/// Fits the surfaces of one Z plane from its records.
///
/// Implements eq. (2): the regression surfaces of one fixed Z position z_i.
pub fn fit_plane(
    z_counts: i64,
    columns: &LccColumns,
    options: &SurfaceFitOptions,
) -> Result<(PlaneSurfaces, RegressionSummary), FitError> {
    let Some(k) = options.outlier_sigmas else {
        return fit_plane_all(z_counts, columns, options);
    };
    let n = columns.len();
    let fewest = MIN_RECORDS_PER_PLANE.max(n.div_ceil(2));
    let mut keep = vec![true; n];
    for _ in 0..MAX_OUTLIER_ROUNDS {
        // The three measured coefficients' surfaces over the kept records, and every
        // record's residual from them (the product surfaces follow from these).
        let kept = columns.selected(&keep);
        let field = extent(&kept.lcs_x_counts, &kept.lcs_y_counts);
        let residual = |name: &'static str, values: &[f64], all: &[f64]| {
            let (surface, _) = fit_one(
                name,
                z_counts,
                &kept.lcs_x_counts,
                &kept.lcs_y_counts,
                values,
                &field,
                options,
            )?;
            Ok::<Vec<f64>, FitError>(
                all.iter()
                    .zip(columns.lcs_x_counts.iter().zip(&columns.lcs_y_counts))
                    .map(|(v, (x, y))| v - surface.surface.evaluate(*x, *y))
                    .collect(),
            )
        };
        let rk = residual(
            "kx_nm_per_count",
            &kept.kx_nm_per_count,
            &columns.kx_nm_per_count,
        )?;
        let ry = residual(
            "ky_nm_per_count",
            &kept.ky_nm_per_count,
            &columns.ky_nm_per_count,
        )?;
        let ra = residual("alpha_rad", &kept.alpha_rad, &columns.alpha_rad)?;
        let flagged = spm_regression::joint_outliers(&[&rk, &ry, &ra], &keep, k);
        let next: Vec<bool> = (0..n).map(|i| !flagged[i]).collect();
        if next == keep || next.iter().filter(|k| **k).count() < fewest {
            break;
        }
        keep = next;
    }
    let left_out = keep.iter().filter(|k| !**k).count();
    if left_out > 0 {
        tracing::info!(
            z_counts,
            left_out,
            n,
            "records left out of the surfaces as outliers"
        );
    }
    let (plane, mut summary) = fit_plane_all(z_counts, &columns.selected(&keep), options)?;
    summary.outliers_left_out = left_out;
    Ok((plane, summary))
}

/// [`fit_plane`] over every record of `columns`.
fn fit_plane_all(
    z_counts: i64,
    columns: &LccColumns,
    options: &SurfaceFitOptions,
) -> Result<(PlaneSurfaces, RegressionSummary), FitError> {
    let x = &columns.lcs_x_counts;
    let y = &columns.lcs_y_counts;
    let field = extent(x, y);
    let one = |name: &'static str, xs: &[f64], ys: &[f64], values: &[f64]| {
        fit_one(name, z_counts, xs, ys, values, &field, options)
    };
    let (kx, kx_summary) = one("kx_nm_per_count", x, y, &columns.kx_nm_per_count)?;
    let (ky, ky_summary) = one("ky_nm_per_count", x, y, &columns.ky_nm_per_count)?;
    let (alpha, alpha_summary) = one("alpha_rad", x, y, &columns.alpha_rad)?;
    // The values of the product surfaces of eq. (11), after K̄y and α have passed their own fits.
    let (kyx, kyy) = spm_regression::product_values(&columns.ky_nm_per_count, &columns.alpha_rad)
        .map_err(|source| FitError::Regression {
        coefficient: "kyx_nm_per_count",
        z_counts,
        source,
    })?;
    let (kyx_surface, _) = one("kyx_nm_per_count", x, y, &kyx)?;
    let (kyy_surface, _) = one("kyy_nm_per_count", x, y, &kyy)?;
    let independent = FormFit {
        form: SurfaceForm::Independent,
        kx,
        kx_summary,
        kyx: kyx_surface,
        kyy: kyy_surface,
    };
    let chosen = if options.form == Some(SurfaceForm::Independent) {
        independent
    } else {
        let records = PlaneRecords {
            z_counts,
            x,
            y,
            kx: &columns.kx_nm_per_count,
            kyx: &kyx,
            kyy: &kyy,
            field: &field,
        };
        let (exact, exact_params) = exact_form(&records, &independent, options.max_degree)?;
        match options.form {
            Some(_) => exact,
            None => choose_form(x.len(), independent, (exact, exact_params)),
        }
    };
    let FormFit {
        form,
        kx,
        kx_summary,
        kyx: kyx_surface,
        kyy: kyy_surface,
    } = chosen;
    let mut kz_x = Vec::new();
    let mut kz_y = Vec::new();
    let mut kz_v = Vec::new();
    for ((xi, yi), kz) in x.iter().zip(y).zip(&columns.kz_nm_per_count) {
        if let Some(kz) = kz {
            kz_x.push(*xi);
            kz_y.push(*yi);
            kz_v.push(*kz);
        }
    }
    let (kz, kz_summary) = if kz_v.len() >= 2 {
        let (surface, summary) = one("kz_nm_per_count", &kz_x, &kz_y, &kz_v)?;
        (Some(surface), Some(summary))
    } else {
        (None, None)
    };
    let plane = PlaneSurfaces {
        z_counts: z_counts as f64,
        n_records: columns.len(),
        kx_nm_per_count: kx,
        ky_nm_per_count: ky,
        alpha_rad: alpha,
        kyx_nm_per_count: kyx_surface,
        kyy_nm_per_count: kyy_surface,
        kz_nm_per_count: kz,
        bowl_z_counts: None,
        calibrated_region_counts: CountRegion::bounding(x, y, 0.0),
        form,
    };
    Ok((
        plane,
        RegressionSummary {
            kx: kx_summary,
            ky: ky_summary,
            alpha: alpha_summary,
            kz: kz_summary,
            bowl: None,
            outliers_left_out: 0,
        },
    ))
}

/// Fits the plane's bowl (the LCSs' Z over x, y) when the plane's records come from a run that
/// measured the vertical axis (at least one record with Kz; without it `lcs_z_counts` is a
/// single Z reading on the corrugation and no bowl is fitted). With enough records for a
/// quadratic (≥ 12), records on another terrace (Z off the surface by more than 0.6 step)
/// are left out, iteratively.
///
/// `records` are the plane's records as the CDB holds them (the fit's selection).
///
/// # Errors
/// [`FitError`] from the regression.
pub fn with_bowl(
    records: &[LccRecord],
    mut plane: PlaneSurfaces,
    mut summary: RegressionSummary,
    options: &SurfaceFitOptions,
) -> Result<(PlaneSurfaces, RegressionSummary), FitError> {
    let levels: Vec<&LccRecord> = records
        .iter()
        .filter(|r| {
            r.lcs_x_counts.is_finite() && r.lcs_y_counts.is_finite() && r.lcs_z_counts.is_finite()
        })
        .collect();
    let kz: Vec<f64> = levels.iter().filter_map(|r| r.kz_nm_per_count).collect();
    // Kz^r at the places Kz was measured (the steps' edge points, schema v3; the LCS for
    // older records), not at the LCSs the steps were searched from.
    let with_kz: Vec<&&LccRecord> = levels
        .iter()
        .filter(|r| r.kz_nm_per_count.is_some_and(|k| k.is_finite() && k > 0.0))
        .collect();
    if with_kz.len() >= 2 {
        let x: Vec<f64> = with_kz
            .iter()
            .map(|r| r.kz_x_counts.unwrap_or(r.lcs_x_counts))
            .collect();
        let y: Vec<f64> = with_kz
            .iter()
            .map(|r| r.kz_y_counts.unwrap_or(r.lcs_y_counts))
            .collect();
        let v: Vec<f64> = with_kz.iter().filter_map(|r| r.kz_nm_per_count).collect();
        let field = extent(&x, &y);
        let (surface, s) = fit_one(
            "kz_nm_per_count",
            plane.z_counts as i64,
            &x,
            &y,
            &v,
            &field,
            options,
        )?;
        plane.kz_nm_per_count = Some(surface);
        summary.kz = Some(s);
    }
    if kz.is_empty() || levels.len() < 6 {
        return Ok((plane, summary));
    }
    // 0.6 monatomic step in counts (0.3354 nm over the mean Kz): a terrace offset. A plane
    // (fewer than 12 records) cannot follow the bowl, so nothing is left out then.
    let terrace = if levels.len() >= 12 {
        0.6 * 0.3354 / (kz.iter().sum::<f64>() / kz.len() as f64)
    } else {
        f64::INFINITY
    };
    let z_counts = plane.z_counts as i64;
    let mut keep = vec![true; levels.len()];
    let mut fitted = None;
    for _ in 0..4 {
        let pick = |f: fn(&LccRecord) -> f64| -> Vec<f64> {
            levels
                .iter()
                .zip(&keep)
                .filter(|(_, k)| **k)
                .map(|(r, _)| f(r))
                .collect()
        };
        let (x, y, z) = (
            pick(|r| r.lcs_x_counts),
            pick(|r| r.lcs_y_counts),
            pick(|r| r.lcs_z_counts),
        );
        if z.len() < 6 {
            break;
        }
        let field = extent(&x, &y);
        let (surface, s) = fit_one("bowl_z_counts", z_counts, &x, &y, &z, &field, options)?;
        let next: Vec<bool> = levels
            .iter()
            .map(|r| {
                (r.lcs_z_counts - surface.surface.evaluate(r.lcs_x_counts, r.lcs_y_counts)).abs()
                    < terrace
            })
            .collect();
        let stable = next == keep;
        keep = next;
        fitted = Some((surface, s));
        if stable {
            break;
        }
    }
    if let Some((surface, s)) = fitted {
        plane.bowl_z_counts = Some(surface);
        summary.bowl = Some(s);
    }
    Ok((plane, summary))
}

/// K̄x and the product surfaces of one plane, fitted in one form.
struct FormFit {
    form: SurfaceForm,
    kx: FittedSurface,
    kx_summary: SurfaceSummary,
    kyx: FittedSurface,
    kyy: FittedSurface,
}

impl FormFit {
    /// Free coefficients of the three surfaces.
    fn n_params(&self, exact_params: usize) -> usize {
        match self.form {
            SurfaceForm::Independent => [&self.kx, &self.kyx, &self.kyy]
                .iter()
                .map(|s| spm_regression::n_terms(s.surface.degree()))
                .sum(),
            SurfaceForm::Exact => exact_params,
        }
    }
}

/// One plane's records: positions, counts; the form's three coefficients, nm per count; and
/// the records' extent (for Δmax).
struct PlaneRecords<'a> {
    z_counts: i64,
    x: &'a [f64],
    y: &'a [f64],
    kx: &'a [f64],
    kyx: &'a [f64],
    kyy: &'a [f64],
    field: &'a Field,
}

/// The exact form (`spm_regression::fit_exact_form`) through the plane's records, the x
/// potential's two kinds of observation weighted by the independent fits' σ; with the
/// potentials' number of free coefficients.
fn exact_form(
    r: &PlaneRecords<'_>,
    independent: &FormFit,
    max_degree: u32,
) -> Result<(FormFit, usize), FitError> {
    let form = spm_regression::fit_exact_form(
        &spm_regression::FormObservations {
            x: r.x,
            y: r.y,
            kx_nm_per_count: r.kx,
            kyx_nm_per_count: r.kyx,
            kyy_nm_per_count: r.kyy,
        },
        max_degree,
        spm_regression::FormScatter {
            kx_nm_per_count: independent.kx.sigma,
            kyx_nm_per_count: independent.kyx.sigma,
        },
    )
    .map_err(|source| FitError::Regression {
        coefficient: "exact form (kx, kyx, kyy)",
        z_counts: r.z_counts,
        source,
    })?;
    let n_params = form.n_params;
    let summary =
        |name, surface, values| summarise(name, r.z_counts, surface, r.x, r.y, values, r.field);
    let (kx, kx_summary) = summary("kx_nm_per_count", form.kx_nm_per_count, r.kx)?;
    let (kyx, _) = summary("kyx_nm_per_count", form.kyx_nm_per_count, r.kyx)?;
    let (kyy, _) = summary("kyy_nm_per_count", form.kyy_nm_per_count, r.kyy)?;
    Ok((
        FormFit {
            form: SurfaceForm::Exact,
            kx,
            kx_summary,
            kyx,
            kyy,
        },
        n_params,
    ))
}

/// The form with the lower BIC over the 3n residuals of K̄x, K̄yx and K̄yy, each in units of its
/// independent fit's σ (eq. 14); a tie keeps the independent surfaces.
fn choose_form(
    n_records: usize,
    independent: FormFit,
    (exact, exact_params): (FormFit, usize),
) -> FormFit {
    let scaled = |fit: &FormFit| {
        [
            (fit.kx.sigma, independent.kx.sigma),
            (fit.kyx.sigma, independent.kyx.sigma),
            (fit.kyy.sigma, independent.kyy.sigma),
        ]
        .iter()
        .map(|(s, unit)| if *unit > 0.0 { (s / unit).powi(2) } else { 1.0 })
        .sum::<f64>()
            * n_records.saturating_sub(1) as f64
    };
    let n = 3 * n_records;
    let bic = |fit: &FormFit| {
        spm_regression::information_criterion(n, fit.n_params(exact_params), scaled(fit))
    };
    let (b_independent, b_exact) = (bic(&independent), bic(&exact));
    tracing::info!(
        b_independent,
        b_exact,
        "BIC of the correction form, one by one against exact"
    );
    if b_exact < b_independent {
        exact
    } else {
        independent
    }
}

/// The records' bounding box (the calibrated region's one definition,
/// [`CountRegion::bounding`]); an empty or non-finite set has no extent (infinite bounds).
#[must_use]
pub fn extent(x: &[f64], y: &[f64]) -> Field {
    match CountRegion::bounding(x, y, 0.0) {
        Some(r) => Field {
            x_min: r.x_min_counts,
            x_max: r.x_max_counts,
            y_min: r.y_min_counts,
            y_max: r.y_max_counts,
        },
        None => Field {
            x_min: f64::INFINITY,
            x_max: f64::NEG_INFINITY,
            y_min: f64::INFINITY,
            y_max: f64::NEG_INFINITY,
        },
    }
}

/// A regression failure of `coefficient`'s surface on plane `z_counts`.
fn regression_error(
    coefficient: &'static str,
    z_counts: i64,
) -> impl Fn(spm_regression::RegressionError) -> FitError + Copy {
    move |source| FitError::Regression {
        coefficient,
        z_counts,
        source,
    }
}

/// One coefficient's surface through (x, y, values), its degree chosen by
/// `options.criterion` up to the highest the records support, with its σ and Δmax over
/// `field`.
fn fit_one(
    coefficient: &'static str,
    z_counts: i64,
    x: &[f64],
    y: &[f64],
    values: &[f64],
    field: &Field,
    options: &SurfaceFitOptions,
) -> Result<(FittedSurface, SurfaceSummary), FitError> {
    let regression = regression_error(coefficient, z_counts);
    let observations = Observations::new(x, y, values);
    // A handful of records or places cannot support a high degree: at least twice as many
    // records as terms, and more distinct places than terms (repeats of a node, or nodes
    // that attached to the same feature, are one place).
    let places = spm_regression::distinct_places(x, y);
    let mut max_degree = options.max_degree;
    while !spm_regression::degree_supported(max_degree, values.len(), places) {
        max_degree -= 1;
    }
    let selection = select_degree(
        &observations,
        &SelectionOptions {
            max_degree,
            criterion: options.criterion,
            fit: spm_regression::FitOptions::default(),
        },
    )
    .map_err(regression)?;
    summarise(
        coefficient,
        z_counts,
        selection.fit.surface,
        x,
        y,
        values,
        field,
    )
}

/// A fitted surface with its σ (eq. 14) over the records it was fitted to and its Δmax
/// (eq. 13) over `field`.
fn summarise(
    coefficient: &'static str,
    z_counts: i64,
    surface: spm_regression::Polynomial2,
    x: &[f64],
    y: &[f64],
    values: &[f64],
    field: &Field,
) -> Result<(FittedSurface, SurfaceSummary), FitError> {
    let regression = regression_error(coefficient, z_counts);
    let sigma = if values.len() >= 2 {
        spm_regression::sigma(&surface, &Observations::new(x, y, values)).map_err(regression)?
    } else {
        0.0
    };
    let delta = if field.x_min.is_finite() && field.x_max > field.x_min && field.y_max > field.y_min
    {
        delta_max(&surface, field, 33, 33, (0.0, 0.0))
            .map_err(regression)?
            .value
    } else {
        0.0
    };
    let degree = surface.degree();
    Ok((
        FittedSurface::new(surface, sigma),
        SurfaceSummary {
            degree,
            sigma,
            delta_max: delta,
        },
    ))
}

/// The standard uncertainty of a fitted surface's value at each point of `grid`: σ·√h, with
/// h the leverage of the point in the fit's design over the records at (`records_x`,
/// `records_y`) and σ = `sigma` (the surface's eq. (14) σ, in the unit wanted).
///
/// # Errors
/// [`spm_regression::RegressionError`] when the design is singular at the records.
pub fn standard_uncertainty(
    fitted: &FittedSurface,
    records_x: &[f64],
    records_y: &[f64],
    sigma: f64,
    grid: &[(f64, f64)],
) -> Result<Vec<f64>, spm_regression::RegressionError> {
    let zeros = vec![0.0; records_x.len()];
    let observations = Observations::new(records_x, records_y, &zeros);
    spm_regression::standard_errors(&observations, &fitted.surface, sigma, grid)
}
