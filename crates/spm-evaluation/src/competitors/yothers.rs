//! The DHCT after Yothers, Browder & Bumm, Rev. Sci. Instrum. 88, 013708 (2017): the sample's
//! own lattice is the ruler of one image, trace and retrace together.
//!
//! Every atom is seen at `p = O + R(δθ)·l + e`, `l = n₁b₁ + n₂b₂` its site on the known
//! hexagonal lattice (constant a, indexed by [`spm_apply::ruler::index_lattice`]; a retrace
//! atom takes the index of the trace atom it matches), and the distortion of a sighting at
//! time `t` (since the frame's start), `t_r` after its line's reversal, in a half running
//! along σ = ±1 is
//!
//! - fast axis: `e_x = k·(p_x − x̄) + σ·(h + A·t_r^b) + c₁ₓ·t + c₂ₓ/(t + t₀)`,
//! - slow axis: `e_y = c₁ᵧ·t + c₂ᵧ/(t + t₀)`
//!
//! (A·t_r^b the hysteresis since the reversal, mirrored between the halves; h the lag between
//! them; c₁ the drift; c₂/(t + t₀) the creep of the move before the frame, on both axes since
//! that move goes either way; c₀ is the origin O; k the fast axis's scale against the lattice,
//! which the ruler sets as it sets the slow axis's through c₁ᵧ). For fixed `(b, t₀)` the rest is
//! linear: one [`spm_regression::least_squares`] fit; `b` and `t₀` are found by a ladder, then
//! golden-section refinement, alternating. The corrected position of a pixel is `p − e`.

use super::{
    CompetitorConfig, CompetitorError, Sighting, detect_halves, feature_sighting, golden, map_of,
    pixel_sightings,
};
use spm_correction::CoordinateMap;
use spm_features::Feature;
use spm_hal::{CountPoint, HeightMap};

const METHOD: &str = "yothers";
/// Range of the hysteresis exponent b searched.
const EXPONENT_RANGE: [f64; 2] = [0.05, 3.0];
/// Range of the creep time offset t₀ searched, s.
const CREEP_OFFSET_RANGE_S: [f64; 2] = [1e-3, 1e4];

/// The fitted DHCT model of one image (see the module doc).
#[derive(Debug, Clone, PartialEq)]
pub struct YothersModel {
    /// A, nm.
    pub hysteresis_nm: f64,
    /// b.
    pub hysteresis_exponent: f64,
    /// h, nm.
    pub lag_nm: f64,
    /// k (dimensionless).
    pub fast_scale: f64,
    /// x̄, nm: the centre the scale acts about.
    pub centre_x_nm: f64,
    /// c₁ per axis, nm/s.
    pub drift_nm_per_s: [f64; 2],
    /// c₂ per axis, nm·s.
    pub creep_nm_s: [f64; 2],
    /// t₀, s.
    pub creep_offset_s: f64,
    /// O per axis, nm.
    pub origin_nm: [f64; 2],
    /// δθ, rad.
    pub rotation_rad: f64,
    /// Sightings fitted.
    pub sightings: usize,
    /// RMS residual of the fit, nm.
    pub residual_rms_nm: f64,
}

impl YothersModel {
    /// e of a sighting, nm.
    #[must_use]
    pub fn error_nm(&self, s: &Sighting) -> [f64; 2] {
        let g = 1.0 / (s.time_s + self.creep_offset_s);
        let h = self.lag_nm
            + self.hysteresis_nm * s.since_reversal_s.max(0.0).powf(self.hysteresis_exponent);
        [
            self.fast_scale * (s.position_nm[0] - self.centre_x_nm)
                + s.sign * h
                + self.drift_nm_per_s[0] * s.time_s
                + self.creep_nm_s[0] * g,
            self.drift_nm_per_s[1] * s.time_s + self.creep_nm_s[1] * g,
        ]
    }

    /// The corrected position `p − e` of a sighting, nm.
    #[must_use]
    pub fn corrected_nm(&self, s: &Sighting) -> [f64; 2] {
        let e = self.error_nm(s);
        [s.position_nm[0] - e[0], s.position_nm[1] - e[1]]
    }
}

/// One atom seen: the sighting and its site on the lattice, nm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LatticeSighting {
    /// The sighting.
    pub sighting: Sighting,
    /// Its lattice site `l`, nm (at the lattice's orientation up to a small δθ).
    pub site_nm: [f64; 2],
}

/// The linear fit for fixed `(b, t₀)`: coefficients `[Oₓ, Oᵧ, δθ, k, h, A, c₁ₓ, c₁ᵧ, c₂ₓ,
/// c₂ᵧ]` and the RMS residual.
fn linear_fit(
    atoms: &[LatticeSighting],
    centre_x: f64,
    b: f64,
    t0: f64,
) -> Option<(Vec<f64>, f64)> {
    let mut rows = Vec::with_capacity(2 * atoms.len());
    let mut rhs = Vec::with_capacity(2 * atoms.len());
    for a in atoms {
        let s = &a.sighting;
        let l = a.site_nm;
        let g = 1.0 / (s.time_s + t0);
        let tb = s.since_reversal_s.max(0.0).powf(b);
        rows.push(vec![
            1.0,
            0.0,
            -l[1],
            s.position_nm[0] - centre_x,
            s.sign,
            s.sign * tb,
            s.time_s,
            0.0,
            g,
            0.0,
        ]);
        rhs.push(s.position_nm[0] - l[0]);
        rows.push(vec![0.0, 1.0, l[0], 0.0, 0.0, 0.0, 0.0, s.time_s, 0.0, g]);
        rhs.push(s.position_nm[1] - l[1]);
    }
    let fit = spm_regression::least_squares(&rows, &rhs, &[false; 10]).ok()?;
    fit.residual_rms
        .is_finite()
        .then_some((fit.coefficients, fit.residual_rms))
}

/// The model fitted at `(b, t₀)`.
fn model_at(atoms: &[LatticeSighting], centre_x: f64, b: f64, t0: f64) -> Option<YothersModel> {
    let (c, residual) = linear_fit(atoms, centre_x, b, t0)?;
    Some(YothersModel {
        hysteresis_nm: c[5],
        hysteresis_exponent: b,
        lag_nm: c[4],
        fast_scale: c[3],
        centre_x_nm: centre_x,
        drift_nm_per_s: [c[6], c[7]],
        creep_nm_s: [c[8], c[9]],
        creep_offset_s: t0,
        origin_nm: [c[0], c[1]],
        rotation_rad: c[2],
        sightings: atoms.len(),
        residual_rms_nm: residual,
    })
}

/// `(b, t₀)` of least residual: a ladder on each (unless `from` gives a start), then two
/// rounds of golden-section refinement, alternating (t₀ on a log scale).
fn search(atoms: &[LatticeSighting], centre_x: f64, from: Option<(f64, f64)>) -> (f64, f64) {
    let cost = |b: f64, t0: f64| linear_fit(atoms, centre_x, b, t0).map_or(f64::INFINITY, |f| f.1);
    let ladder = |lo: f64, hi: f64, n: usize| -> Vec<f64> {
        (0..=n)
            .map(|k| lo + (hi - lo) * k as f64 / n as f64)
            .collect()
    };
    let (mut b, mut t0) = from.unwrap_or((0.5, 1.0));
    let best = |values: &[f64], f: &mut dyn FnMut(f64) -> f64| -> f64 {
        values
            .iter()
            .map(|&v| (v, f(v)))
            .fold(
                (values[0], f64::INFINITY),
                |a, x| if x.1 < a.1 { x } else { a },
            )
            .0
    };
    // The ladders: b in steps of 0.1; log₁₀ t₀ in quarter decades.
    let bs = ladder(EXPONENT_RANGE[0], EXPONENT_RANGE[1], 29);
    let (l0, l1) = (
        CREEP_OFFSET_RANGE_S[0].log10(),
        CREEP_OFFSET_RANGE_S[1].log10(),
    );
    let ls = ladder(l0, l1, ((l1 - l0) * 4.0) as usize);
    if from.is_none() {
        b = best(&bs, &mut |v| cost(v, t0));
        t0 = 10f64.powf(best(&ls, &mut |v| cost(b, 10f64.powf(v))));
        b = best(&bs, &mut |v| cost(v, t0));
    }
    for _ in 0..2 {
        let db = 0.11;
        b = golden(
            (b - db).max(EXPONENT_RANGE[0]),
            (b + db).min(EXPONENT_RANGE[1]),
            24,
            &mut |v| cost(v, t0),
        );
        let l = t0.log10();
        t0 = 10f64.powf(golden((l - 0.3).max(l0), (l + 0.3).min(l1), 24, &mut |v| {
            cost(b, 10f64.powf(v))
        }));
    }
    (b, t0)
}

/// Fits the DHCT model to atoms seen on a known lattice (see the module doc).
///
/// # Errors
/// [`CompetitorError::Refused`] with fewer than 12 atoms, or when no `(b, t₀)` gives a fit.
pub fn fit(atoms: &[LatticeSighting]) -> Result<YothersModel, CompetitorError> {
    if atoms.len() < 12 {
        return Err(CompetitorError::Refused {
            method: METHOD,
            reason: format!("{} atoms indexed (needs ≥ 12)", atoms.len()),
        });
    }
    let centre_x =
        atoms.iter().map(|a| a.sighting.position_nm[0]).sum::<f64>() / atoms.len() as f64;
    let (b, t0) = search(atoms, centre_x, None);
    let first = model_at(atoms, centre_x, b, t0);
    // The sites turned by the fitted δθ (the linearised rotation's error is second order), and
    // the search once more.
    let turned: Vec<LatticeSighting> = match &first {
        Some(m) => {
            let (s, c) = m.rotation_rad.sin_cos();
            atoms
                .iter()
                .map(|a| LatticeSighting {
                    site_nm: [
                        c * a.site_nm[0] - s * a.site_nm[1],
                        s * a.site_nm[0] + c * a.site_nm[1],
                    ],
                    ..*a
                })
                .collect()
        }
        None => atoms.to_vec(),
    };
    let (b, t0) = search(&turned, centre_x, Some((b, t0)));
    model_at(&turned, centre_x, b, t0).ok_or(CompetitorError::Refused {
        method: METHOD,
        reason: "no hysteresis exponent and creep offset give a determined fit".to_owned(),
    })
}

/// The atoms of both halves on the lattice: the trace's indexed from one another, the
/// retrace's by the trace atom each matches.
fn lattice_sightings(
    trace: &HeightMap,
    retrace: Option<&HeightMap>,
    config: &CompetitorConfig,
) -> Result<(Vec<LatticeSighting>, super::Halves), CompetitorError> {
    let halves = detect_halves(trace, retrace, config, METHOD)?;
    let k = config.nominal_nm_per_count;
    let in_nm: Vec<Feature> = halves
        .trace
        .iter()
        .map(|f| Feature {
            position: CountPoint::from_counts(f.position.x.value() * k, f.position.y.value() * k),
            ..*f
        })
        .collect();
    let (index, apparent) =
        spm_apply::ruler::index_lattice(&in_nm).map_err(|e| CompetitorError::Refused {
            method: METHOD,
            reason: e.to_string(),
        })?;
    let reached = index.iter().flatten().count();
    if (reached as f64) < 0.7 * halves.trace.len() as f64 {
        return Err(CompetitorError::Refused {
            method: METHOD,
            reason: format!(
                "only {reached} of {} trace atoms could be indexed",
                halves.trace.len()
            ),
        });
    }
    let basis = spm_apply::ruler::hexagonal_basis(&apparent, config.lattice_constant_nm);
    let site = |n: [i64; 2]| {
        let (a, b) = (n[0] as f64, n[1] as f64);
        [
            a * basis[0][0] + b * basis[1][0],
            a * basis[0][1] + b * basis[1][1],
        ]
    };
    let mut out = Vec::new();
    for (f, n) in halves.trace.iter().zip(&index) {
        if let Some(n) = n {
            out.push(LatticeSighting {
                sighting: feature_sighting(f, &halves.trace_raster, k, halves.start_s),
                site_nm: site(*n),
            });
        }
    }
    for &(i, j) in &halves.matches {
        if let (Some(Some(n)), Some(f)) = (index.get(i), halves.retrace.get(j)) {
            out.push(LatticeSighting {
                sighting: feature_sighting(f, &halves.retrace_raster, k, halves.start_s),
                site_nm: site(*n),
            });
        }
    }
    Ok((out, halves))
}

/// The DHCT of one image: the model fitted on its trace and retrace, and the corrected
/// coordinates of every pixel of the trace (scanner geometry).
///
/// # Errors
/// [`CompetitorError::Refused`] for an image without retrace, whose lattice is not resolved,
/// indexed on less than 70 % of its trace atoms, or matched on fewer than 12 atoms.
pub fn correct_image(
    trace: &HeightMap,
    retrace: Option<&HeightMap>,
    config: &CompetitorConfig,
) -> Result<(YothersModel, CoordinateMap), CompetitorError> {
    let (atoms, halves) = lattice_sightings(trace, retrace, config)?;
    let model = fit(&atoms)?;
    let corrected: Vec<[f64; 2]> = pixel_sightings(
        trace,
        &halves.trace_raster,
        config.nominal_nm_per_count,
        halves.start_s,
    )
    .iter()
    .map(|s| model.corrected_nm(s))
    .collect();
    Ok((model, map_of(trace.columns, trace.rows, &corrected)?))
}
