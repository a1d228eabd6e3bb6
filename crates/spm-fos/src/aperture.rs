//! Aperture scanning and LCS recognition (paper §2.1.2).

use crate::acquire::{Motion, Raster, Recognised, scan_and_recognise};
use crate::error::FosError;
use serde::{Deserialize, Serialize};
use spm_features::{DetectionConfig, Feature, Lcs, LcsConfig, lcs_candidates};
use spm_hal::{CountPoint, Microscope, ScanDirection};

/// Settings of [`aperture`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ApertureParams {
    /// The aperture raster (encloses A and its neighbours).
    pub raster: Raster,
    /// Recognition settings.
    pub detection: DetectionConfig,
    /// The LCS standard and tolerances.
    pub lcs: LcsConfig,
    /// Probe moves.
    pub motion: Motion,
}

/// The result of [`aperture`].
#[derive(Clone, Debug, PartialEq)]
pub struct ApertureReport {
    /// The recognised aperture.
    pub recognised: Recognised,
    /// Index of A (the feature nearest the aperture's centre), if any.
    pub a: Option<usize>,
    /// The best LCS with vertex A, if any.
    pub lcs: Option<Lcs>,
    /// Every neighbour of A that forms an LCS with it.
    pub neighbours: Vec<usize>,
    /// Candidates with vertex A accepted (admitted and through the gate).
    pub accepted_candidates: usize,
    /// Candidates with vertex A that the LCS gate ([`LcsConfig::gate`]) refused.
    pub refused_by_gate: usize,
    /// True when, without the gate, recognition would have chosen a candidate the gate
    /// refused (a misrecognition prevented).
    pub best_refused_by_gate: bool,
}

impl ApertureReport {
    /// The feature with index `i`.
    pub fn feature(&self, i: usize) -> Option<&Feature> {
        self.recognised.detection.features.get(i)
    }
}

/// Scans an aperture centred on `centre` (the captured feature A) and
/// recognises the LCS with vertex A. Positions within one aperture carry the
/// drift of the scan: they are approximate and serve to aim the skipping.
pub fn aperture<M: Microscope>(
    microscope: &mut M,
    centre: CountPoint,
    params: &ApertureParams,
) -> Result<ApertureReport, FosError<M::Error>> {
    params.raster.validate()?;
    params.motion.validate()?;
    microscope
        .move_to(params.motion.request(centre))
        .map_err(FosError::instrument)?;
    let recognised = scan_and_recognise(
        microscope,
        &params.raster,
        centre,
        ScanDirection::Direct,
        &params.detection,
    )?;
    let features = &recognised.detection.features;
    let a = recognised.detection.nearest_index(centre);
    let candidates = match a {
        Some(a) => lcs_candidates(features, a, &params.lcs)?,
        None => spm_features::LcsCandidates::default(),
    };
    let mut neighbours: Vec<usize> = candidates
        .accepted
        .iter()
        .flat_map(|t| [t.b, t.c])
        .collect();
    neighbours.sort_unstable();
    neighbours.dedup();
    let lcs = candidates.accepted.first().copied();
    tracing::debug!(
        features = features.len(),
        lcs = lcs.is_some(),
        neighbours = neighbours.len(),
        refused_by_gate = candidates.refused_by_gate.len(),
        "aperture recognised"
    );
    Ok(ApertureReport {
        recognised,
        a,
        lcs,
        neighbours,
        accepted_candidates: candidates.accepted.len(),
        refused_by_gate: candidates.refused_by_gate.len(),
        best_refused_by_gate: candidates.best_refused_by_gate(),
    })
}
