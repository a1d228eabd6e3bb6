//! `spmcal fit --cdb PATH [--scanner ID] [--since DATE] [--until DATE] --out calibration.json`:
//! the calibration file (format version 2: surfaces, calibrated region, provenance).

use crate::cdb_cmd::cdb_error;
use crate::dates::parse_window;
use crate::error::CliError;
use spmcal::surfaces::{SurfaceFitError, SurfaceFitOptions, fit_from_cdb};
use std::path::Path;

/// Highest degree tried by BIC for every coefficient surface.
pub use spmcal::report::MAX_SURFACE_DEGREE;

pub fn run(
    cdb_path: &Path,
    scanner: Option<&str>,
    since: Option<&str>,
    until: Option<&str>,
    out: &Path,
    reject_outliers: Option<f64>,
    form: Option<spm_correction::SurfaceForm>,
) -> Result<(), CliError> {
    let (since, until) = parse_window(since, until)?;
    if let Some(k) = reject_outliers
        && !(k.is_finite() && k >= 1.0)
    {
        return Err(CliError::BadInput(format!(
            "--reject-outliers {k}: give a number of standard deviations ≥ 1"
        )));
    }
    crate::files::check_output(out, "--out", &[cdb_path])?;
    let cdb = crate::cdb_cmd::open_read_only(cdb_path)?;
    let snapshot = cdb.snapshot().map_err(cdb_error)?;
    let fitted = fit_from_cdb(
        &*snapshot,
        scanner,
        since,
        until,
        &SurfaceFitOptions {
            outlier_sigmas: reject_outliers,
            form,
            ..SurfaceFitOptions::bic_up_to(MAX_SURFACE_DEGREE)
        },
    )
    .map_err(|e| match e {
        SurfaceFitError::Cdb(e) => cdb_error(e),
        SurfaceFitError::NoRecords { .. }
        | SurfaceFitError::AmbiguousScanner(_)
        | SurfaceFitError::Fit(spm_correction::fit::FitError::TooFewRecords { .. }) => {
            CliError::BadInput(format!("{}: {e}", spmcal::cdb_handle::shown(cdb_path)))
        }
        other => CliError::RunFailed(other.to_string()),
    })?;
    if fitted.excluded_records > 0 {
        use std::io::Write;
        let _ = writeln!(
            std::io::stderr(),
            "spmcal: warning: {}: {} records with invalid coefficients (as `spmcal cdb check` \
             reports them) were left out of the fit",
            spmcal::cdb_handle::shown(cdb_path),
            fitted.excluded_records
        );
    }
    if fitted.outlier_records > 0 {
        crate::outln!(
            "{} records left out as outliers (beyond {} robust σ of their plane's surfaces)",
            fitted.outlier_records,
            reject_outliers.unwrap_or(f64::NAN)
        );
    }
    let mut set = fitted.set;
    set.provenance.written_utc = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .ok()
        .map(|d| spm_cdb::rfc3339_utc(d.as_secs_f64()));
    let json = set
        .to_json_string()
        .map_err(|e| CliError::RunFailed(e.to_string()))?;
    crate::write_atomically(out, json.as_bytes())?;
    let s = fitted.summary;
    crate::outln!(
        "{} planes, {} records → {}",
        set.planes.len(),
        set.provenance.n_records,
        out.display()
    );
    crate::outln!(
        "K̄x: degree {} σ {:.2e} nm/count; K̄y: degree {} σ {:.2e} nm/count; α: degree {} σ {:.2e} rad",
        s.kx.degree,
        s.kx.sigma,
        s.ky.degree,
        s.ky.sigma,
        s.alpha.degree,
        s.alpha.sigma
    );
    let forms: Vec<String> = set
        .planes
        .iter()
        .map(|p| format!("z = {}: {}", p.z_counts, p.form.as_str()))
        .collect();
    crate::outln!("form of K̄x, K̄yx, K̄yy (eq. 5): {}", forms.join("; "));
    Ok(())
}
