//! The vibration on the images' pixels in the selection (issue 29 item 1; the pixel model
//! and its search are `vibration.rs`): searched before the feature-level selection and
//! named first when accepted, the features corrected by what they see of it.

use super::{
    Added, AliasFrequency, Finding, Model, PixelEvidence, Problem, Rejection, Selection, delta_bic,
    effect_params, implausible,
};
use crate::index::MeasuredBasis;
use crate::model::{Column, Ctx, Fit, build_obs, effect_columns, solve};
use crate::types::{EffectKind, FeatureSet, LineDirection, ModelCheckError};
use crate::vibration::{ImageMap, PixelFit, PixelImage, SearchSpace};
use nalgebra::{DMatrix, DVector};

/// A vibration found on the pixels: its frequency and the input displacement's x cos,
/// x sin, y cos, y sin (nominal nm) with time from `t_origin_s`.
#[derive(Clone, Copy, Debug)]
pub(super) struct FoundVibration {
    pub(super) frequency_hz: f64,
    coefficients_nm: [f64; 4],
    t_origin_s: f64,
}

/// The features moved back by what their footprints see of a vibration found on the
/// pixels (footprint averages over lines and along the line, `model.rs`): a feature seen
/// at u sits where the tip was at u + δu.
pub(super) fn corrected_for_vibration(set: &FeatureSet, v: &FoundVibration) -> FeatureSet {
    let mut out = set.clone();
    let all: Vec<Option<[i64; 2]>> = vec![Some([0, 0]); set.features.len()];
    let Ok((obs, source, t_mid)) = build_obs(set, &all, [1.0, 0.0], [0.0, 1.0]) else {
        return out;
    };
    let w = std::f64::consts::TAU * v.frequency_hz;
    let c = v.coefficients_nm;
    for (o, &k) in obs.iter().zip(&source) {
        let shift = t_mid - v.t_origin_s;
        let d = [0, 1].map(|a| {
            crate::model::along_line_attenuation(o, a, w)
                * crate::model::footprint_average(o, a, |t| {
                    let (sn, cs) = (w * (t + shift)).sin_cos();
                    c[2 * a] * cs + c[2 * a + 1] * sn
                })
        });
        out.features[k].x_nm += d[0];
        out.features[k].y_nm += d[1];
    }
    out
}

/// The least coherence of a vibration: what one sinusoid explains in all images over what
/// separate ones per image explain (beyond their noise). A vibration found on the
/// generator's images has 0.97–1.00; an unmodelled static distortion that some frequency's
/// pattern happens to match in each image (a large trace/retrace loop) has ≈ 0.5.
const MIN_COHERENCE: f64 = 0.8;

/// The most the feature positions may see of a vibration, as a fraction of the tip's
/// displacement at their times: their footprints average it (≤ 1, up to noise). More
/// means the features' fit at that frequency follows something else (the creep after a
/// frame's start, a trace/retrace loop): 1.4–4 there.
const MAX_SEEN: f64 = 1.25;

/// What the features see of a vibration at `f_hz`: the feature-level columns at this
/// frequency with their own coefficients (their footprints average the vibration over
/// lines and, at hundreds of Hz, within a line, in a way only they can tell), per
/// equation; and the model's columns with them.
fn features_seen(p: &Problem<'_>, m: &Model, f_hz: f64) -> (Vec<f64>, Vec<Column>) {
    let cols = effect_columns(EffectKind::PeriodicVibration, f_hz, &p.obs, &m.ctx);
    let mut with_vibration = m.cols.clone();
    with_vibration.extend(cols.iter().cloned());
    let seen: Vec<f64> = match solve(&with_vibration, &p.target, &m.mask) {
        Ok(f) => (0..p.target.len())
            .map(|i| (0..4).map(|j| f.coef[m.cols.len() + j] * cols[j][i]).sum())
            .collect(),
        Err(_) => vec![0.0; p.target.len()],
    };
    (seen, with_vibration)
}

/// The RMS of what the features see (`seen`) over the RMS of the tip's displacement at
/// their times (the image-axis coefficients of `image` at `f_hz`).
fn seen_fraction(p: &Problem<'_>, m: &Model, (image, f_hz): (&Fit, f64), seen: &[f64]) -> f64 {
    let w = std::f64::consts::TAU * f_hz;
    let (mut seen_ss, mut tip_ss) = (0.0, 0.0);
    for (k, o) in p.obs.iter().enumerate().filter(|(k, _)| m.mask[*k]) {
        let (sn, cs) = (w * o.t).sin_cos();
        let d = [
            image.coef[0] * cs + image.coef[1] * sn,
            image.coef[2] * cs + image.coef[3] * sn,
        ];
        tip_ss += d[0] * d[0] + d[1] * d[1];
        seen_ss += seen[2 * k].powi(2) + seen[2 * k + 1].powi(2);
    }
    (seen_ss / tip_ss.max(1e-300)).sqrt()
}

/// Why the vibration `fit` (evidence, RMS displacement nm, parameters, the fraction the
/// features see) may not be accepted; `None` when it may.
fn pixel_problem(
    p: &Problem<'_>,
    relevance_nm: f64,
    fit: &PixelFit,
    (evidence, displacement_nm, seen_by_features): (f64, f64, f64),
    parameters: &std::collections::BTreeMap<String, crate::ParamValue>,
) -> Option<String> {
    if evidence <= p.options.evidence_threshold {
        Some(format!("not supported on the pixels (ΔBIC {evidence:.1})"))
    } else if fit.coherence < MIN_COHERENCE {
        Some(format!(
            "not one vibration in every image (coherence {:.2})",
            fit.coherence
        ))
    } else if seen_by_features > MAX_SEEN {
        Some(format!(
            "the features move {seen_by_features:.2}× as much as the tip at this frequency: \
             something else than a vibration"
        ))
    } else if displacement_nm < relevance_nm {
        Some(format!(
            "irrelevant: explains {:.2} pm RMS, below {:.2} pm",
            1000.0 * displacement_nm,
            1000.0 * relevance_nm
        ))
    } else if let Some(r) = implausible(
        EffectKind::PeriodicVibration,
        parameters,
        p.frames,
        p.lattice_a_nm,
        p.span_s,
    ) {
        Some(format!("implausible: {r}"))
    } else if fit.heldout_rms[1] >= fit.heldout_rms[0] {
        Some(format!(
            "no held-out gain on the pixels ({:.3} → {:.3})",
            fit.heldout_rms[0], fit.heldout_rms[1]
        ))
    } else {
        None
    }
}

/// The finding of the vibration `fit` (its evidence, parameters and the fraction the
/// features see; the features' held-out RMS before and after, and whether they were
/// corrected).
fn pixel_finding(
    fit: &PixelFit,
    (evidence, parameters, seen_by_features): (
        f64,
        std::collections::BTreeMap<String, crate::ParamValue>,
        f64,
    ),
    (before, after, features_corrected): (f64, f64, bool),
) -> Finding {
    let kind = EffectKind::PeriodicVibration;
    let rms = |rss: f64| (rss / fit.pixels.max(1) as f64).sqrt();
    Finding {
        effect: kind.name().to_owned(),
        evidence,
        rms_before_pm: rms(fit.rss[0]),
        rms_after_pm: rms(fit.rss[1]),
        heldout_rms_before_pm: fit.heldout_rms[0],
        heldout_rms_after_pm: fit.heldout_rms[1],
        parameters,
        meaning: kind.meaning().to_owned(),
        confounded_with: Vec::new(),
        pixel_level: Some(PixelEvidence {
            images: fit.images,
            pixels: fit.pixels,
            aliases: fit
                .aliases
                .iter()
                .map(|a| AliasFrequency {
                    frequency_hz: a.frequency_hz,
                    evidence_gap: a.evidence_gap,
                })
                .collect(),
            coherence: fit.coherence,
            seen_by_features,
            feature_heldout_rms_before_pm: before,
            feature_heldout_rms_after_pm: if features_corrected { after } else { before },
            features_corrected,
        }),
    }
}

/// The images that have a map, with it.
fn paired<'a>(
    pixels: &'a [PixelImage],
    maps: &'a [Option<ImageMap>],
) -> Vec<(&'a PixelImage, &'a ImageMap)> {
    pixels
        .iter()
        .zip(maps)
        .filter_map(|(img, map)| map.as_ref().map(|m| (img, m)))
        .collect()
}

/// The highest degree of an image's lattice map.
const IMAGE_MAP_DEGREE: u32 = 5;

/// The lattice map of one image (`frame`, line direction): its features' sites as
/// polynomials of their commanded positions, at degree 5 or the highest lower degree its
/// features support (three per term). It follows what the scanner does in that image
/// (drift, nonlinearity, a sine drive, a trace/retrace loop) and, of a vibration, only what
/// is smooth over the image.
fn image_map(
    p: &Problem<'_>,
    (mask, target): (&[bool], &[f64]),
    (frame, direction): (usize, LineDirection),
) -> Option<ImageMap> {
    let (mut x, mut y, mut rx, mut ry) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for (k, o) in p.obs.iter().enumerate() {
        if mask[k] && o.frame == frame && o.direction == direction {
            x.push(o.u[0]);
            y.push(o.u[1]);
            rx.push(target[2 * k]);
            ry.push(target[2 * k + 1]);
        }
    }
    let options = spm_regression::FitOptions::default();
    let fit = |x: &[f64], y: &[f64], rx: &[f64], ry: &[f64]| {
        (1..=IMAGE_MAP_DEGREE).rev().find_map(|d| {
            if x.len() < 3 * spm_regression::n_terms(d) {
                return None;
            }
            let fx = spm_regression::fit(&spm_regression::Observations::new(x, y, rx), d, &options);
            let fy = spm_regression::fit(&spm_regression::Observations::new(x, y, ry), d, &options);
            let (fx, fy) = (fx.ok()?, fy.ok()?);
            Some([fx.surface, fy.surface])
        })
    };
    // Features off their site by a quarter of the period (slipped in the indexing) are
    // left out, twice.
    let mut map: ImageMap = fit(&x, &y, &rx, &ry)?;
    for _ in 0..2 {
        let keep: Vec<bool> = (0..x.len())
            .map(|i| {
                let d = [
                    rx[i] - map[0].evaluate(x[i], y[i]),
                    ry[i] - map[1].evaluate(x[i], y[i]),
                ];
                d[0].hypot(d[1]) < 0.25 * p.lattice_a_nm
            })
            .collect();
        let pick = |v: &[f64]| -> Vec<f64> {
            v.iter()
                .zip(&keep)
                .filter(|(_, k)| **k)
                .map(|(v, _)| *v)
                .collect()
        };
        map = fit(&pick(&x), &pick(&y), &pick(&rx), &pick(&ry))?;
    }
    Some(map)
}

/// The vibration's coefficients (x cos, x sin, y cos, y sin) in the image axes, and their
/// covariance, from the pixels' input-axis ones: d = Rot(−θ₀)·J₀·δu.
fn image_axes(fit: &PixelFit, ctx: &Ctx) -> Fit {
    let (s, c) = ctx.theta0.sin_cos();
    let j = ctx.j0;
    let m = [
        [c * j[0][0] + s * j[1][0], c * j[0][1] + s * j[1][1]],
        [-s * j[0][0] + c * j[1][0], -s * j[0][1] + c * j[1][1]],
    ];
    let k = DMatrix::from_row_slice(
        4,
        4,
        &[
            m[0][0], 0.0, m[0][1], 0.0, //
            0.0, m[0][0], 0.0, m[0][1], //
            m[1][0], 0.0, m[1][1], 0.0, //
            0.0, m[1][0], 0.0, m[1][1],
        ],
    );
    let coef = &k * DVector::from_column_slice(&fit.coefficients_nm);
    let cov_in = DMatrix::from_fn(4, 4, |a, b| fit.covariance_nm2[a][b]);
    Fit {
        coef: coef.iter().copied().collect(),
        cov: &k * cov_in * k.transpose(),
        residual: Vec::new(),
        rss: fit.rss[1],
        n_eq: fit.pixels,
        rank: 4,
    }
}

/// The vibration searched on the images' pixels (`vibration.rs`), when they are given:
/// its finding, named first, or its rejection. With pixels the feature-level candidate is
/// not searched (the line rate aliases its frequency, and where the phase advances about
/// half a cycle per line the features do not see it). The feature positions are corrected
/// by what their footprints see of it when that lowers their held-out RMS.
pub(super) fn pixel_vibration(
    p: &mut Problem<'_>,
    m: &mut Model,
    sel: &mut Selection,
    (pixels, basis): (&[PixelImage], &MeasuredBasis),
) -> Result<Option<FoundVibration>, ModelCheckError> {
    let kind = EffectKind::PeriodicVibration;
    if pixels.len() < 2 || !p.options.effects.contains(&kind) {
        return Ok(None);
    }
    sel.excluded.push(kind);
    let line_frequencies_hz: Vec<f64> = p
        .frames
        .iter()
        .filter(|f| f.duration_s > 0.0 && f.lines > 0)
        .map(|f| f.lines as f64 / f.duration_s)
        .collect();
    let space = SearchSpace {
        t_origin_s: p.t_mid,
        longest_frame_s: p.frames.iter().map(|f| f.duration_s).fold(0.0, f64::max),
        line_frequencies_hz: &line_frequencies_hz,
        harmonics: crate::vibration::lattice_harmonics([basis.a1_nm, basis.a2_nm]),
    };
    // The frequency against each image's affine map from the baseline (a template that
    // cannot absorb any of the vibration) ...
    let drift = [m.fit.coef[4], m.fit.coef[5]];
    let affine: Vec<Option<ImageMap>> = pixels
        .iter()
        .map(|img| crate::vibration::affine_map(img, m.ctx.j0, drift, p.t_mid))
        .collect();
    let Some(candidate) = crate::vibration::candidate(&paired(pixels, &affine), &space) else {
        return Ok(None);
    };
    let [rss0, rss1] = candidate.linear_rss;
    if delta_bic(candidate.pixels as f64, rss0, rss1, 5.0, candidate.trials)
        <= p.options.evidence_threshold
    {
        // Nothing there even against the rigid template: no vibration (and no need to
        // fit one on the images' own maps).
        return Ok(None);
    }
    // ... what the features see of it (`features_seen`) ...
    let seen_at = |f_hz: f64| features_seen(p, m, f_hz);
    // ... and the vibration fitted against each image's own lattice map from its features
    // without what they see of it, against the static model, each image's map from its
    // features as they are (which follows the scanner's static distortions — a
    // nonlinearity, a sine drive, a trace/retrace loop, a shear gradient — and absorbs of
    // a vibration only what is smooth over an image): a static distortion that some
    // frequency's pattern mimics is better explained by the static model.
    let without: Vec<f64> = p
        .target
        .iter()
        .zip(&seen_at(candidate.frequency_hz).0)
        .map(|(t, s)| t - s)
        .collect();
    let triples: Vec<(&PixelImage, ImageMap, ImageMap)> = pixels
        .iter()
        .filter_map(|img| {
            let fd = img.frame_and_direction();
            let still = image_map(p, (&m.mask, &p.target), fd)?;
            let vibrating = image_map(p, (&m.mask, &without), fd)?;
            Some((img, still, vibrating))
        })
        .collect();
    let triples: Vec<(&PixelImage, &ImageMap, &ImageMap)> =
        triples.iter().map(|(i, s, v)| (*i, s, v)).collect();
    let Some(fit) = crate::vibration::assess(&triples, &space, &candidate) else {
        return Ok(None);
    };
    let image = image_axes(&fit, &m.ctx);
    let added = Added {
        kind,
        hyper: fit.frequency_hz,
        hyper_sigma: 0.25 / p.span_s.max(1e-9),
        range: 0..4,
    };
    let parameters = effect_params(&added, &image, p.frames, &m.ctx);
    let evidence = delta_bic(fit.pixels as f64, fit.rss[0], fit.rss[1], 5.0, fit.trials);
    let amplitude = |k: &str| parameters.get(k).map_or(0.0, |v| v.value);
    let displacement_nm =
        (0.5 * (amplitude("amplitude_x_nm").powi(2) + amplitude("amplitude_y_nm").powi(2))).sqrt();
    let (seen, with_vibration) = seen_at(fit.frequency_hz);
    let seen_by_features = seen_fraction(p, m, (&image, fit.frequency_hz), &seen);
    let relevance_nm = p.relevance_nm(&m.fit, &m.mask);
    let problem = pixel_problem(
        p,
        relevance_nm,
        &fit,
        (evidence, displacement_nm, seen_by_features),
        &parameters,
    );
    tracing::debug!(
        frequency_hz = fit.frequency_hz,
        evidence,
        coherence = fit.coherence,
        heldout = ?fit.heldout_rms,
        ?parameters,
        ?problem,
        "pixel-level vibration"
    );
    if let Some(reason) = problem {
        if evidence > p.options.evidence_threshold {
            sel.rejected.push(Rejection {
                effect: kind.name().to_owned(),
                evidence,
                explained_rms_pm: 1000.0 * displacement_nm,
                reason,
            });
        }
        return Ok(None);
    }
    let before = m.heldout_now;
    let after = p.heldout_pm(&with_vibration, &m.mask);
    let features_corrected = after < before;
    if features_corrected {
        p.target = p.target.iter().zip(&seen).map(|(t, s)| t - s).collect();
        m.fit = solve(&m.cols, &p.target, &m.mask)?;
        m.heldout_now = after;
    }
    sel.pixel = Some(pixel_finding(
        &fit,
        (evidence, parameters, seen_by_features),
        (before, after, features_corrected),
    ));
    Ok(Some(FoundVibration {
        frequency_hz: fit.frequency_hz,
        coefficients_nm: fit.coefficients_nm,
        t_origin_s: p.t_mid,
    }))
}
