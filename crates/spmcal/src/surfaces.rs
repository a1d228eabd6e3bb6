//! The calibration file's surfaces from the CDB: the records of a scanner and time window,
//! fitted plane by plane by `spm_correction::fit`, with the file's provenance (the runs, the
//! records' digest, the nominal sensitivity of their plans) and the scanner's newest
//! dynamics. Glue only: the fit is the library's.

use spm_cdb::{CdbRead, RecordFilter};
use spm_correction::fit::{FitError, MIN_RECORDS_PER_PLANE, fit_plane, keep_valid, with_bowl};
pub use spm_correction::fit::{
    RegressionSummary, SurfaceFitOptions, SurfaceSummary, record_is_usable,
};
use spm_correction::{CountsConvention, Provenance, SurfaceSet};

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
    /// The CDB holds several scanners and none was chosen.
    #[error("the CDB holds several scanners ({0}); choose one with --scanner")]
    AmbiguousScanner(String),
    /// A plane's surfaces could not be fitted (too few records, a failed regression).
    #[error(transparent)]
    Fit(#[from] FitError),
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
            return Err(FitError::TooFewRecords {
                z_counts: z,
                n: columns.len(),
            }
            .into());
        }
        let (plane, plane_summary) = fit_plane(z, &columns, options)?;
        n_records += plane.n_records;
        outlier_records += plane_summary.outliers_left_out;
        // The bowl from the LCSs' Z (issue 15; plans with `[plan.steps]`).
        let (plane, plane_summary) =
            with_bowl(&cdb.records(&filter)?, plane, plane_summary, options)?;
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
/// the selection that [`record_is_usable`] keeps, hashed as their JSON lines in acquisition order.
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
