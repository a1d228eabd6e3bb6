//! Regression surfaces from CDB records (eq. 2, 6, 11, 13, 14): one set of
//! surfaces per Z plane, with the degree chosen per coefficient by BIC.

use serde::Serialize;
use spm_cdb::{CdbRead, LccColumns, RecordFilter};
use spm_correction::{
    CountRegion, CountsConvention, FittedSurface, PlaneSurfaces, Provenance, SurfaceForm,
    SurfaceSet,
};
use spm_regression::{Criterion, Field, Observations, SelectionOptions, delta_max, select_degree};

/// Why surfaces could not be fitted.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SurfaceFitError {
    /// Reading the CDB failed.
    #[error(transparent)]
    Cdb(#[from] spm_cdb::CdbError),
    /// The selection holds no record.
    #[error(
        "no record matches the selection ({})",
        describe_selection(scanner.as_deref(), since.as_deref(), until.as_deref())
    )]
    NoRecords {
        /// Scanner filter.
        scanner: Option<String>,
        /// Lower time bound.
        since: Option<String>,
        /// Upper time bound.
        until: Option<String>,
    },
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
    /// The CDB holds several scanners and none was chosen.
    #[error("the CDB holds several scanners ({0}); choose one with --scanner")]
    AmbiguousScanner(String),
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
    /// The assembled surfaces are invalid.
    #[error(transparent)]
    Correction(#[from] spm_correction::CorrectionError),
    /// The CDB's newest dynamics of the scanner cannot be read as a model.
    #[error("the dynamics stored by run {run_id} cannot be read: {message}")]
    Dynamics {
        /// The run that stored them.
        run_id: String,
        /// Why.
        message: String,
    },
}

/// Fewest valid records a plane needs: σ (eq. 14) has n − 1 degrees of freedom for the
/// lowest degree, so one record would report σ = 0.
pub const MIN_RECORDS_PER_PLANE: usize = 2;

/// The selection in words: `scanner "X", since 2026-…, until 2026-…`.
fn describe_selection(scanner: Option<&str>, since: Option<&str>, until: Option<&str>) -> String {
    let mut parts = Vec::new();
    match scanner {
        Some(s) => parts.push(format!("scanner {s:?}")),
        None => parts.push("any scanner".to_owned()),
    }
    if let Some(t) = since {
        parts.push(format!("since {t}"));
    }
    if let Some(t) = until {
        parts.push(format!("until {t}"));
    }
    parts.join(", ")
}

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

/// Whether `cdb check` accepts a record's regression inputs ([`usable`]): the records a fit
/// uses.
#[must_use]
pub fn record_is_usable(r: &spm_cdb::LccRecord) -> bool {
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
/// As [`fit_plane`]; [`SurfaceFitError::TooFewRecords`] below [`MIN_RECORDS_PER_PLANE`].
pub fn fit_plane_of_records(
    z_counts: i64,
    records: &[&spm_cdb::LccRecord],
    options: &SurfaceFitOptions,
) -> Result<PlaneSurfaces, SurfaceFitError> {
    let columns: LccColumns = records.iter().copied().collect();
    if columns.len() < MIN_RECORDS_PER_PLANE {
        return Err(SurfaceFitError::TooFewRecords {
            z_counts,
            n: columns.len(),
        });
    }
    fit_plane(z_counts, &columns, options).map(|(plane, _)| plane)
}

/// Keeps the records that `cdb check` accepts ([`usable`]); returns how many were left out.
fn keep_valid(columns: &mut LccColumns) -> usize {
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
    fn retain<T>(v: &mut Vec<T>, keep: &[bool]) {
        let mut i = 0;
        v.retain(|_| {
            let k = keep.get(i).copied().unwrap_or(false);
            i += 1;
            k
        });
    }
    retain(&mut columns.lcs_x_counts, &keep);
    retain(&mut columns.lcs_y_counts, &keep);
    retain(&mut columns.node_z_counts, &keep);
    retain(&mut columns.acquired_unix_s, &keep);
    retain(&mut columns.kx_nm_per_count, &keep);
    retain(&mut columns.ky_nm_per_count, &keep);
    retain(&mut columns.alpha_rad, &keep);
    retain(&mut columns.kz_nm_per_count, &keep);
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

/// Surfaces and their summary.
#[derive(Debug, Clone)]
pub struct FittedSurfaces {
    /// What `surfaces.json` holds.
    pub set: SurfaceSet,
    /// Degree, σ, Δmax of each coefficient in the plane nearest z = 0.
    pub summary: RegressionSummary,
    /// Records left out because `cdb check` would flag their coefficients.
    pub excluded_records: usize,
    /// Records left out as outliers of their plane's surfaces, over all planes
    /// ([`SurfaceFitOptions::outlier_sigmas`]).
    pub outlier_records: usize,
}

/// Selects records from the CDB and fits surfaces per Z plane.
pub fn fit_from_cdb(
    cdb: &dyn CdbRead,
    scanner: Option<&str>,
    since_unix_s: Option<f64>,
    until_unix_s: Option<f64>,
    options: &SurfaceFitOptions,
) -> Result<FittedSurfaces, SurfaceFitError> {
    let scanner_id = match scanner {
        Some(id) => id.to_owned(),
        None => {
            let scanners = cdb.scanners()?;
            match scanners.as_slice() {
                [] => {
                    return Err(SurfaceFitError::NoRecords {
                        scanner: None,
                        since: since_unix_s.map(spm_cdb::rfc3339_utc),
                        until: until_unix_s.map(spm_cdb::rfc3339_utc),
                    });
                }
                [one] => one.clone(),
                many => return Err(SurfaceFitError::AmbiguousScanner(many.join(", "))),
            }
        }
    };
    let mut planes = Vec::new();
    let mut summary = None;
    let mut n_records = 0;
    let mut excluded_records = 0;
    let mut outlier_records = 0;
    for z in cdb.z_planes(&scanner_id)? {
        let filter = RecordFilter::scanner(&scanner_id)
            .with_z_plane(z)
            .with_window(since_unix_s, until_unix_s);
        let mut columns = cdb.columns(&filter)?;
        let excluded = keep_valid(&mut columns);
        excluded_records += excluded;
        if excluded > 0 {
            tracing::warn!(
                z,
                excluded,
                "records with invalid coefficients left out of the fit"
            );
        }
        if columns.is_empty() {
            continue;
        }
        if columns.len() < MIN_RECORDS_PER_PLANE {
            return Err(SurfaceFitError::TooFewRecords {
                z_counts: z,
                n: columns.len(),
            });
        }
        let (plane, plane_summary) = fit_plane(z, &columns, options)?;
        n_records += plane.n_records;
        outlier_records += plane_summary.outliers_left_out;
        // The bowl from the LCSs' Z (issue 15; plans with `[plan.steps]`).
        let (plane, plane_summary) =
            crate::vertical::with_bowl(cdb, &filter, plane, plane_summary, options)?;
        if summary.is_none() || z == 0 {
            summary = Some(plane_summary);
        }
        planes.push(plane);
    }
    let Some(summary) = summary else {
        return Err(SurfaceFitError::NoRecords {
            scanner: Some(scanner_id),
            since: since_unix_s.map(spm_cdb::rfc3339_utc),
            until: until_unix_s.map(spm_cdb::rfc3339_utc),
        });
    };
    let used = records_used(cdb, &scanner_id, since_unix_s, until_unix_s)?;
    let provenance = Provenance {
        scanner_id: scanner_id.clone(),
        fit_since: since_unix_s.map(spm_cdb::rfc3339_utc),
        fit_until: until_unix_s.map(spm_cdb::rfc3339_utc),
        n_records,
        counts_convention: Some(CountsConvention::CentredSigned),
        nominal_nm_per_count: used.nominal_nm_per_count,
        run_ids: used.run_ids,
        records_sha256: Some(used.sha256),
        written_utc: None,
        spmcal_version: Some(env!("CARGO_PKG_VERSION").to_owned()),
        spmcal_commit: option_env!("SPMCAL_GIT_COMMIT").map(str::to_owned),
    };
    let mut set = SurfaceSet::new(provenance, planes)?;
    set.dynamics = newest_dynamics(cdb, &scanner_id, until_unix_s)?;
    set.validate()?;
    Ok(FittedSurfaces {
        set,
        summary,
        excluded_records,
        outlier_records,
    })
}

/// The scanner's newest dynamics identified no later than `until_unix_s` (if given).
fn newest_dynamics(
    cdb: &dyn CdbRead,
    scanner_id: &str,
    until_unix_s: Option<f64>,
) -> Result<Option<spm_correction::hysteresis::ScannerDynamics>, SurfaceFitError> {
    let Some(stored) = cdb
        .dynamics(Some(scanner_id))?
        .into_iter()
        .rfind(|d| until_unix_s.is_none_or(|u| d.identified_unix_s <= u))
    else {
        return Ok(None);
    };
    let model: spm_correction::hysteresis::ScannerDynamics =
        serde_json::from_str(&stored.model_json).map_err(|e| SurfaceFitError::Dynamics {
            run_id: stored.run_id.clone(),
            message: e.to_string(),
        })?;
    model.validate().map_err(|e| SurfaceFitError::Dynamics {
        run_id: stored.run_id.clone(),
        message: e.to_string(),
    })?;
    Ok(Some(model))
}

/// What the provenance of a calibration file says of the records it was fitted from.
struct RecordsUsed {
    run_ids: Vec<String>,
    sha256: String,
    nominal_nm_per_count: Option<f64>,
}

/// The runs, the SHA-256 (hex) and the nominal sensitivity of the records a fit uses: those of
/// the selection that [`usable`] keeps, hashed as their JSON lines in acquisition order.
fn records_used(
    cdb: &dyn CdbRead,
    scanner_id: &str,
    since_unix_s: Option<f64>,
    until_unix_s: Option<f64>,
) -> Result<RecordsUsed, SurfaceFitError> {
    use sha2::Digest as _;
    let filter = RecordFilter::scanner(scanner_id).with_window(since_unix_s, until_unix_s);
    let mut hasher = sha2::Sha256::new();
    let mut run_ids: Vec<String> = Vec::new();
    cdb.for_each_record(&filter, &mut |record| {
        if record_is_usable(&record) {
            // Serialising a plain record cannot fail; an empty line would still be hashed.
            let line = serde_json::to_vec(&record).unwrap_or_default();
            hasher.update(&line);
            hasher.update(b"\n");
            if !run_ids.contains(&record.run_id) {
                run_ids.push(record.run_id);
            }
        }
        Ok(())
    })?;
    let sha256 = hasher
        .finalize()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect::<String>();
    // The runs' plans state the nominal sensitivity; it is recorded when they agree.
    let mut nominal: Option<f64> = None;
    let mut agree = true;
    for id in &run_ids {
        let Some(run) = cdb.run(id)? else { continue };
        match plan_nominal_nm_per_count(&run.config) {
            Some(k) => match nominal {
                None => nominal = Some(k),
                Some(n) if (n - k).abs() <= 1e-9 * n.abs() => {}
                Some(_) => agree = false,
            },
            None => agree = false,
        }
    }
    Ok(RecordsUsed {
        run_ids,
        sha256,
        nominal_nm_per_count: if agree { nominal } else { None },
    })
}

/// `plan.standard.nominal_nm_per_count` of a run's stored job text (TOML), if it parses.
fn plan_nominal_nm_per_count(config: &str) -> Option<f64> {
    let value: toml::Value = toml::from_str(config).ok()?;
    let k = value
        .get("plan")?
        .get("standard")?
        .get("nominal_nm_per_count")?;
    k.as_float()
        .or_else(|| k.as_integer().map(|i| i as f64))
        .filter(|k| k.is_finite() && *k > 0.0)
}

/// Fits the surfaces of one Z plane from its records.
///
/// Implements eq. (2): the regression surfaces of one fixed Z position z_i.
pub fn fit_plane(
    z_counts: i64,
    columns: &LccColumns,
    options: &SurfaceFitOptions,
) -> Result<(PlaneSurfaces, RegressionSummary), SurfaceFitError> {
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
            Ok::<Vec<f64>, SurfaceFitError>(
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
) -> Result<(PlaneSurfaces, RegressionSummary), SurfaceFitError> {
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
        .map_err(|source| SurfaceFitError::Regression {
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
) -> Result<(FormFit, usize), SurfaceFitError> {
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
    .map_err(|source| SurfaceFitError::Regression {
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
pub(crate) fn extent(x: &[f64], y: &[f64]) -> Field {
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
) -> impl Fn(spm_regression::RegressionError) -> SurfaceFitError + Copy {
    move |source| SurfaceFitError::Regression {
        coefficient,
        z_counts,
        source,
    }
}

pub(crate) fn fit_one(
    coefficient: &'static str,
    z_counts: i64,
    x: &[f64],
    y: &[f64],
    values: &[f64],
    field: &Field,
    options: &SurfaceFitOptions,
) -> Result<(FittedSurface, SurfaceSummary), SurfaceFitError> {
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
) -> Result<(FittedSurface, SurfaceSummary), SurfaceFitError> {
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
