//! After Zhang et al., Rev. Sci. Instrum. (2019), doi 10.1063/1.5052281: a sinusoid-plus-linear
//! map fitted from the features matched between trace and retrace.
//!
//! Along the fast axis a half that runs along σ = ±1 and has run the fraction `u` of its line
//! (width W) puts a point at `p_x = x + σ·(h + β·W·sin(πu)) + vₓ·t`, and along the slow axis
//! at `p_y = y + vᵧ·t` (t since the frame's start): the hysteresis loop as a sinusoid that
//! closes at both reversals, mirrored between the halves, plus the linear part the two halves
//! can show — the lag h between them and the drift v, linear in time. A feature seen in both
//! halves at the same (x, y) gives, per matched pair (trace T, retrace R),
//!
//! `p_xT − p_xR = h·(σ_T − σ_R) + β·W·(σ_T·sin πu_T − σ_R·sin πu_R) + vₓ·(t_T − t_R)`,
//! `p_yT − p_yR = vᵧ·(t_T − t_R)`,
//!
//! linear in `(h, β, v)`: one [`spm_regression::least_squares`] fit. A scale along the line (or
//! any point-symmetric term of the loop other than the sinusoid) is the same in both halves
//! and invisible to the pair: it stays at the nominal sensitivity. The corrected position of a
//! pixel is `p − σ·(h + β·W·sin πu) − v·t`.

use super::{
    CompetitorConfig, CompetitorError, Sighting, detect_halves, feature_sighting, map_of,
    pixel_sightings,
};
use spm_correction::CoordinateMap;
use spm_hal::HeightMap;

const METHOD: &str = "zhang";

/// The fitted map of one image (see the module doc).
#[derive(Debug, Clone, PartialEq)]
pub struct ZhangModel {
    /// h, nm.
    pub lag_nm: f64,
    /// β (fraction of the line width).
    pub sinusoid: f64,
    /// W, nm.
    pub line_width_nm: f64,
    /// v per axis, nm/s.
    pub drift_nm_per_s: [f64; 2],
    /// Pairs fitted.
    pub pairs: usize,
    /// RMS residual of the fit (both axes), nm.
    pub residual_rms_nm: f64,
}

impl ZhangModel {
    /// The displacement of a sighting from where its point is, nm.
    #[must_use]
    pub fn error_nm(&self, s: &Sighting) -> [f64; 2] {
        let loop_nm = self.lag_nm
            + self.sinusoid * self.line_width_nm * (std::f64::consts::PI * s.progress).sin();
        [
            s.sign * loop_nm + self.drift_nm_per_s[0] * s.time_s,
            self.drift_nm_per_s[1] * s.time_s,
        ]
    }

    /// The corrected position of a sighting, nm.
    #[must_use]
    pub fn corrected_nm(&self, s: &Sighting) -> [f64; 2] {
        let e = self.error_nm(s);
        [s.position_nm[0] - e[0], s.position_nm[1] - e[1]]
    }
}

/// Fits the map to sightings matched between trace and retrace (`pairs`: trace, retrace), on
/// lines `line_width_nm` wide.
///
/// # Errors
/// [`CompetitorError::Refused`] with fewer than 12 pairs or an undetermined fit.
pub fn fit(
    pairs: &[(Sighting, Sighting)],
    line_width_nm: f64,
) -> Result<ZhangModel, CompetitorError> {
    let refused = |reason: String| CompetitorError::Refused {
        method: METHOD,
        reason,
    };
    if pairs.len() < 12 {
        return Err(refused(format!(
            "{} pairs matched (needs ≥ 12)",
            pairs.len()
        )));
    }
    let pi = std::f64::consts::PI;
    let mut rows_x = Vec::with_capacity(pairs.len());
    let mut rhs_x = Vec::with_capacity(pairs.len());
    let mut rows_y = Vec::with_capacity(pairs.len());
    let mut rhs_y = Vec::with_capacity(pairs.len());
    for (t, r) in pairs {
        let dt = t.time_s - r.time_s;
        rows_x.push(vec![
            t.sign - r.sign,
            line_width_nm * (t.sign * (pi * t.progress).sin() - r.sign * (pi * r.progress).sin()),
            dt,
        ]);
        rhs_x.push(t.position_nm[0] - r.position_nm[0]);
        rows_y.push(vec![dt]);
        rhs_y.push(t.position_nm[1] - r.position_nm[1]);
    }
    let fx = spm_regression::least_squares(&rows_x, &rhs_x, &[false; 3])
        .map_err(|e| refused(format!("fast-axis fit: {e}")))?;
    let fy = spm_regression::least_squares(&rows_y, &rhs_y, &[false])
        .map_err(|e| refused(format!("slow-axis fit: {e}")))?;
    Ok(ZhangModel {
        lag_nm: fx.coefficients[0],
        sinusoid: fx.coefficients[1],
        line_width_nm,
        drift_nm_per_s: [fx.coefficients[2], fy.coefficients[0]],
        pairs: pairs.len(),
        residual_rms_nm: (0.5
            * (fx.residual_rms * fx.residual_rms + fy.residual_rms * fy.residual_rms))
            .sqrt(),
    })
}

/// The map of one image: fitted on the features matched between its trace and retrace, and
/// the corrected coordinates of every pixel of the trace (scanner geometry).
///
/// # Errors
/// [`CompetitorError::Refused`] for an image without retrace, whose features are not resolved,
/// or matched on fewer than 12 features.
pub fn correct_image(
    trace: &HeightMap,
    retrace: Option<&HeightMap>,
    config: &CompetitorConfig,
) -> Result<(ZhangModel, CoordinateMap), CompetitorError> {
    let halves = detect_halves(trace, retrace, config, METHOD)?;
    let k = config.nominal_nm_per_count;
    let pairs: Vec<(Sighting, Sighting)> = halves
        .matches
        .iter()
        .filter_map(|&(i, j)| {
            Some((
                feature_sighting(
                    halves.trace.get(i)?,
                    &halves.trace_raster,
                    k,
                    halves.start_s,
                ),
                feature_sighting(
                    halves.retrace.get(j)?,
                    &halves.retrace_raster,
                    k,
                    halves.start_s,
                ),
            ))
        })
        .collect();
    let width = trace.pixel_step.value() * (trace.columns - 1) as f64 * k;
    let model = fit(&pairs, width)?;
    let corrected: Vec<[f64; 2]> = pixel_sightings(trace, &halves.trace_raster, k, halves.start_s)
        .iter()
        .map(|s| model.corrected_nm(s))
        .collect();
    Ok((model, map_of(trace.columns, trace.rows, &corrected)?))
}
