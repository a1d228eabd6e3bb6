//! After a run: regression surfaces, accuracy against the oracle (simulated
//! backends), `report.json`, `surfaces.json`, the PNG figures and `report.html` (the same
//! [`CalibrationReport`] with the figures embedded, see [`crate::html`]).

use crate::plots::{self, Coefficient, Region};
use crate::run::{DriftSample, NodeSample};
use crate::surfaces::{RegressionSummary, SurfaceFitOptions, fit_from_cdb};
use serde::Serialize;
use spm_calibration::{PlanConfig, RunReport};
use spm_cdb::RecordFilter;
use spm_correction::PlaneSurfaces;
use spm_correction::hysteresis::ScannerDynamics;
use spm_evaluation::accuracy::{
    Accuracy, EvaluationGrid, PolynomialImage, evaluate, polynomial_baseline,
};
use spm_hal::truth::{GroundTruth, SimulatedInstrument};
use std::path::Path;

/// Highest degree tried by BIC for every coefficient surface.
pub const MAX_SURFACE_DEGREE: u32 = 5;

/// Lines (and pixels per line) of the polynomial baseline's one image.
pub const POLYNOMIAL_LINES: usize = 1024;
/// Reference features per side of the polynomial baseline's image.
pub const POLYNOMIAL_CONTROL: usize = 12;

/// Why the post-run steps failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ReportError {
    /// Reading the CDB failed.
    #[error(transparent)]
    Cdb(#[from] spm_cdb::CdbError),
    /// Fitting surfaces failed.
    #[error(transparent)]
    Fit(#[from] crate::surfaces::SurfaceFitError),
    /// A correction step of the evaluation failed.
    #[error("accuracy evaluation: {0}")]
    Correction(#[from] spm_correction::CorrectionError),
    /// The image benchmark failed.
    #[error(transparent)]
    Images(#[from] spm_evaluation::images::ImageBenchmarkError),
    /// A figure could not be written.
    #[error(transparent)]
    Plot(#[from] plots::PlotError),
    /// A file could not be written.
    #[error("{path}: {message}")]
    Write {
        /// The file.
        path: String,
        /// Why.
        message: String,
    },
}

/// Accuracy of every method (report.json's `accuracy`).
#[derive(Debug, Clone, Serialize)]
pub struct AccuracyTable {
    /// The nominal sensitivity of the plan, orthogonal, no correction.
    pub uncorrected: Accuracy,
    /// K̄x, K̄y, α of the node nearest the field centre, applied everywhere.
    pub lumped: Accuracy,
    /// One affine map for the whole field: the mean LCCs of all nodes.
    pub affine: Accuracy,
    /// A per-image 3rd-order polynomial fitted to one slow image of the whole
    /// region over a reference grid (see `notes` and [`polynomial_baseline`]).
    pub polynomial: Option<Accuracy>,
    /// The distributed calibration: regression surfaces of every node.
    pub distributed: Accuracy,
    /// distributed RMS ÷ lumped RMS (the plan may declare a target for it:
    /// `[plan.targets] distributed_over_lumped_rms_max`).
    pub distributed_over_lumped_rms: f64,
}

/// One drift estimate in report.json.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DriftPoint {
    /// Instrument time, s.
    pub time_s: f64,
    /// Drift speed through the nominal sensitivity, nm/s.
    pub speed_nm_per_s: f64,
    /// The estimate of a spoiled (discarded) skipping cycle.
    pub spoiled: bool,
}

/// The drift history of the run (report.json `drift`, the HTML report's drift section).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DriftHistory {
    /// The nominal sensitivity the speeds are converted with, nm/count.
    pub nominal_nm_per_count: f64,
    /// Estimates made.
    pub estimates: usize,
    /// Of which spoiled cycles.
    pub spoiled: usize,
    /// Instrument time of the first and last estimate, s (None without estimates).
    pub time_span_s: Option<[f64; 2]>,
    /// Smallest, median and largest speed of the kept estimates, nm/s (None without any).
    pub speed_min_median_max_nm_per_s: Option<[f64; 3]>,
    /// Every estimate in time order.
    pub points: Vec<DriftPoint>,
}

impl DriftHistory {
    /// The history of `drift`, speeds through `nominal_nm_per_count`.
    pub fn of(drift: &[DriftSample], nominal_nm_per_count: f64) -> Self {
        let points: Vec<DriftPoint> = drift
            .iter()
            .map(|d| DriftPoint {
                time_s: d.time_s,
                speed_nm_per_s: d.vx_counts_per_s.hypot(d.vy_counts_per_s) * nominal_nm_per_count,
                spoiled: d.spoiled,
            })
            .collect();
        let mut kept: Vec<f64> = points
            .iter()
            .filter(|p| !p.spoiled && p.speed_nm_per_s.is_finite())
            .map(|p| p.speed_nm_per_s)
            .collect();
        kept.sort_by(f64::total_cmp);
        let speed_min_median_max_nm_per_s = match (kept.first(), kept.last()) {
            (Some(&lo), Some(&hi)) => Some([lo, kept[kept.len() / 2], hi]),
            _ => None,
        };
        let times = points.iter().map(|p| p.time_s).filter(|t| t.is_finite());
        let time_span_s = times
            .clone()
            .reduce(f64::min)
            .zip(times.reduce(f64::max))
            .map(|(a, b)| [a, b]);
        Self {
            nominal_nm_per_count,
            estimates: points.len(),
            spoiled: points.iter().filter(|p| p.spoiled).count(),
            time_span_s,
            speed_min_median_max_nm_per_s,
            points,
        }
    }
}

/// What report.json holds.
#[derive(Debug, Clone, Serialize)]
pub struct CalibrationReport {
    /// The scanner calibrated (the plan's `scanner_id`).
    pub scanner_id: String,
    /// Nodes per repeat.
    pub nodes: usize,
    /// Repeats l.
    pub repeats: u32,
    /// Records in the CDB for this run.
    pub records: u64,
    /// Instrument time of this invocation, s.
    pub instrument_time_s: f64,
    /// Wall time of the whole job, s.
    pub wall_time_s: f64,
    /// Wall time per measured node, ms.
    pub wall_time_per_node_ms: f64,
    /// Regression surfaces of the plane nearest z = 0.
    pub regression: RegressionSummary,
    /// Accuracy against the oracle (simulated backends only).
    pub accuracy: Option<AccuracyTable>,
    /// The image benchmark: test images taken after the run, as a user takes them, every
    /// method's position and lattice error on them (simulated backends only).
    pub images: Option<spm_evaluation::images::ImageBenchmark>,
    /// Every record's LCCs against the oracle's true LCCs (simulated backends only).
    pub node_lcc_error: Option<spm_evaluation::accuracy::NodeLccError>,
    /// The vertical axis against the oracle (simulated backends, runs that measured Kz).
    pub vertical: Option<spm_evaluation::vertical::VerticalReport>,
    /// The scanner dynamics identified in situ (issue 23), against the simulator's own where
    /// there is one.
    pub dynamics: Option<crate::dynamics::DynamicsReport>,
    /// What the run says of itself without an oracle (issue 24): held-out nodes, repeat
    /// agreement and the corrected standard's lattice, with pass/warn verdicts against the
    /// plan's `[validation]` thresholds. Every backend.
    pub validation: Validation,
    /// When, by which program, where, on which backend and from which inputs (absent when the
    /// caller gave none, e.g. tests that build a report directly).
    pub provenance: Option<RunProvenance>,
    /// The verdict on every target the plan declares (`[plan.targets]`, issue 27; empty when
    /// none is declared): see [`crate::targets`].
    pub targets: Vec<crate::targets::TargetVerdict>,
    /// The calibrator's own report (cycles, given-up nodes with reasons, …).
    pub run: RunReport,
    /// The drift estimates of the run.
    pub drift: DriftHistory,
    /// How the figures were measured, and what is not.
    pub notes: Vec<String>,
}

/// One input file of a run, with its SHA-256 digest.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct InputFile {
    /// The path as given.
    pub path: String,
    /// SHA-256 of its contents, hex (None: it could not be read).
    pub sha256: Option<String>,
}

impl InputFile {
    /// The file at `path` and its digest.
    #[must_use]
    pub fn of(path: &Path) -> Self {
        use sha2::Digest as _;
        Self {
            path: path.display().to_string(),
            sha256: std::fs::read(path).ok().map(|bytes| {
                sha2::Sha256::digest(&bytes)
                    .iter()
                    .map(|b| format!("{b:02x}"))
                    .collect()
            }),
        }
    }
}

/// Where a report comes from (issue 27): when, which program, which host, which backend, which
/// inputs. The caller supplies it (the library reads no clock).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunProvenance {
    /// Start of the invocation, UTC (RFC 3339).
    pub started_utc: String,
    /// End of the run, before the report, UTC (RFC 3339).
    pub finished_utc: String,
    /// spmcal's version.
    pub spmcal_version: String,
    /// The git commit spmcal was built from, when known.
    pub spmcal_commit: Option<String>,
    /// The host the run ran on, when known.
    pub host: Option<String>,
    /// The backend and its identity (simulator seed, controller address and state, image).
    pub backend: String,
    /// The simulator's seed (simulated backends).
    pub seed: Option<u64>,
    /// The job's files (config, plan, referenced files, images) with their digests.
    pub inputs: Vec<InputFile>,
}

/// Validation without an oracle (report.json's `validation`).
#[derive(Debug, Clone, Serialize)]
pub struct Validation {
    /// Predicted against measured LCCs at the nodes held out of a second fit.
    pub held_out: spm_evaluation::validation::HeldOutCheck,
    /// Repeat-to-repeat agreement at each node.
    pub repeats: spm_evaluation::validation::RepeatAgreement,
    /// The corrected standard's lattice over the calibrated region (`None`: no images were
    /// taken, e.g. `lattice_places_per_side = 0`).
    pub lattice: Option<spm_evaluation::validation::LatticeCheck>,
    /// Why the lattice check could not be made, when images were asked for.
    pub lattice_failure: Option<String>,
}

impl Validation {
    /// The checks over `records` (the scanner's records the surfaces were fitted from), and
    /// the lattice of the standard's `images` corrected with `set`.
    fn of(
        records: &[spm_cdb::LccRecord],
        plan: &PlanConfig,
        set: &spm_correction::SurfaceSet,
        images: Option<&Result<Vec<spm_evaluation::images::TestImage>, String>>,
        stored: Option<&crate::virtual_mode::StoredStandard>,
    ) -> Self {
        let usable: Vec<spm_cdb::LccRecord> = records
            .iter()
            .filter(|r| crate::surfaces::record_is_usable(r))
            .cloned()
            .collect();
        let options = SurfaceFitOptions::bic_up_to(MAX_SURFACE_DEGREE);
        let held_out =
            spm_evaluation::validation::held_out_check(&usable, &plan.validation, |z, records| {
                spm_correction::fit::fit_plane_of_records(z, records, &options)
            });
        let repeats = spm_evaluation::validation::repeat_agreement(&usable, &plan.validation);
        let (lattice, lattice_failure) = match (stored, images) {
            (Some(stored), _) => {
                match crate::virtual_mode::stored_lattice_check(stored, set, plan) {
                    Ok(check) => (Some(check), None),
                    Err(e) => (
                        None,
                        Some(format!("the stored image was not measured: {e}")),
                    ),
                }
            }
            (None, None) => (None, None),
            (None, Some(Err(e))) => (None, Some(format!("the images were not taken: {e}"))),
            (None, Some(Ok(images))) => match spm_evaluation::validation::lattice_check(
                images,
                set,
                &spm_evaluation::validation::lattice_image_set(plan),
                &plan.validation,
            ) {
                Ok(check) => (Some(check), None),
                Err(e) => (
                    None,
                    Some(format!("the images could not be corrected: {e}")),
                ),
            },
        };
        Self {
            held_out,
            repeats,
            lattice,
            lattice_failure,
        }
    }
}

/// Everything the post-run steps need.
pub struct RunRecord<'a> {
    /// The plan that ran.
    pub plan: &'a PlanConfig,
    /// The calibrator's report.
    pub run: &'a RunReport,
    /// The instrument's ground truth, when the backend has one (a simulator).
    pub truth: Option<&'a dyn TruthSource>,
    /// Drift estimates.
    pub drift: &'a [DriftSample],
    /// Measured nodes.
    pub nodes: &'a [NodeSample],
    /// Attachment sequences (for the creep law).
    pub attach_tracks: &'a [spm_correction::dynamics::AttachTrack],
    /// The run's lateral commands (for the creep law).
    pub commands: &'a [spm_hal::recording::CommandEvent],
    /// The dynamics stage's ladder rasters.
    pub ladder: &'a [spm_calibration::dynamics::LadderFrame],
    /// The simulator's own dynamics, when the backend is a simulator.
    pub true_dynamics: Option<crate::dynamics::TrueDynamics>,
    /// Wall time of the run, s.
    pub wall_time_s: f64,
    /// The standard imaged over the calibrated region after the run, for the validation's
    /// lattice check ([`crate::run::standard_images`]); `None` when not taken.
    pub standard_images: Option<&'a Result<Vec<spm_evaluation::images::TestImage>, String>>,
    /// The stored image a virtual run calibrated on: the validation's lattice check corrects
    /// it and measures it cell by cell instead of imaging pairs
    /// ([`crate::virtual_mode::stored_lattice_check`]).
    pub stored_standard: Option<&'a crate::virtual_mode::StoredStandard>,
    /// The run's provenance, for the report.
    pub provenance: Option<&'a RunProvenance>,
    /// Told the name of each phase of the report as it starts (a progress display).
    pub phase: Option<&'a dyn Fn(&str)>,
    /// A dynamics model stored with the run, used when the run's own frames identify none
    /// (a report regenerated from the CDB, [`crate::regenerate`]).
    pub stored_dynamics: Option<&'a ScannerDynamics>,
    /// Notes added to report.json's (what a regenerated report lacks).
    pub extra_notes: Vec<String>,
}

/// What a report judges a calibration against: a ground truth that can also take the image
/// benchmark's test images (object-safe: the report never names the backend).
pub trait TruthSource: GroundTruth + Sync {
    /// Takes the image benchmark's test images on a copy of the instrument and judges every
    /// correction method on them.
    ///
    /// # Errors
    /// [`ReportError`] when the images cannot be taken or judged.
    fn image_benchmark(
        &self,
        record: &RunRecord<'_>,
        region: &Region,
        planes: &[(&str, &PlaneSurfaces)],
        dynamics: Option<&ScannerDynamics>,
        quick: bool,
    ) -> Result<spm_evaluation::images::ImageBenchmark, ReportError>;
}

impl<S: SimulatedInstrument + Sync> TruthSource for S {
    fn image_benchmark(
        &self,
        record: &RunRecord<'_>,
        region: &Region,
        planes: &[(&str, &PlaneSurfaces)],
        dynamics: Option<&ScannerDynamics>,
        quick: bool,
    ) -> Result<spm_evaluation::images::ImageBenchmark, ReportError> {
        image_benchmark(self, record, region, planes, dynamics, quick)
    }
}

impl<'a> RunRecord<'a> {
    /// The record of a [`crate::run::run_job`] outcome with what its recorder saw.
    pub fn of_job(
        plan: &'a PlanConfig,
        outcome: &'a crate::run::JobOutcome,
        samples: &'a crate::run::RunSamples,
        wall_time_s: f64,
    ) -> Self {
        Self {
            plan,
            run: &outcome.report,
            truth: outcome.instrument.truth(),
            drift: &samples.drift,
            nodes: &samples.nodes,
            attach_tracks: &samples.attach_tracks,
            commands: &outcome.commands,
            ladder: &outcome.ladder,
            true_dynamics: outcome.instrument.true_dynamics(),
            wall_time_s,
            standard_images: None,
            stored_standard: None,
            provenance: None,
            phase: None,
            stored_dynamics: None,
            extra_notes: Vec::new(),
        }
    }

    /// The record of a finished run as the CDB holds it (no instrument, drift, commands or
    /// frames): what [`crate::regenerate`] feeds the report with.
    #[must_use]
    pub fn of_stored(
        plan: &'a PlanConfig,
        run: &'a RunReport,
        nodes: &'a [NodeSample],
        provenance: &'a RunProvenance,
    ) -> Self {
        Self {
            plan,
            run,
            truth: None,
            drift: &[],
            nodes,
            attach_tracks: &[],
            commands: &[],
            ladder: &[],
            true_dynamics: None,
            wall_time_s: 0.0,
            standard_images: None,
            stored_standard: None,
            provenance: Some(provenance),
            phase: None,
            stored_dynamics: None,
            extra_notes: Vec::new(),
        }
    }

    /// The record with a progress display told each phase of the report.
    #[must_use]
    pub fn with_phase(self, phase: &'a dyn Fn(&str)) -> Self {
        Self {
            phase: Some(phase),
            ..self
        }
    }

    /// True when the run's backend has a ground truth: the instrument is a simulator, or (a
    /// report regenerated from the CDB) its provenance names a simulator's seed.
    fn simulated(&self) -> bool {
        self.truth.is_some() || self.provenance.is_some_and(|p| p.seed.is_some())
    }

    fn phase(&self, name: &str) {
        if let Some(phase) = self.phase {
            phase(name);
        }
    }

    /// The record with the run's provenance.
    #[must_use]
    pub fn with_provenance(self, provenance: &'a RunProvenance) -> Self {
        Self {
            provenance: Some(provenance),
            ..self
        }
    }

    /// The record with the standard's images for the validation's lattice check.
    #[must_use]
    pub fn with_standard_images(
        self,
        images: Option<&'a Result<Vec<spm_evaluation::images::TestImage>, String>>,
    ) -> Self {
        Self {
            standard_images: images,
            ..self
        }
    }

    /// The record with the stored image a virtual run calibrated on, for the validation's
    /// lattice check.
    #[must_use]
    pub fn with_stored_standard(
        self,
        stored: Option<&'a crate::virtual_mode::StoredStandard>,
    ) -> Self {
        Self {
            stored_standard: stored,
            ..self
        }
    }
}

impl CalibrationReport {
    /// The lattice survey's line of the summary: places with a lattice and the LCS gate's
    /// tally (issue 24); `None` when the run had no survey.
    fn survey_line(&self) -> Option<String> {
        let survey = self.run.survey.as_ref()?;
        let g = &survey.gate;
        Some(format!(
            "LCS gate (lattice surveyed at {} of {} places): {} of {} apertures' first choice \
             refused (misrecognition rate {}); candidates accepted {}, refused {}",
            survey.places.iter().filter(|p| p.lcc.is_some()).count(),
            survey.places.len(),
            g.misrecognitions,
            g.apertures_with_candidates,
            survey
                .misrecognition_rate
                .map_or_else(|| "-".to_owned(), |r| format!("{:.1} %", 100.0 * r)),
            g.candidates_accepted,
            g.candidates_refused
        ))
    }

    /// The report's summary as a person reads it after a run: counts and times, the
    /// surfaces, the accuracy per method, the images section and the node LCCs against the
    /// oracle (the last three when the backend has one).
    #[must_use]
    pub fn summary_text(&self) -> String {
        use std::fmt::Write as _;
        let mut t = String::new();
        let _ = writeln!(
            t,
            "nodes {} × repeats {} → {} records; {} given up; cycles kept {} discarded {}",
            self.nodes,
            self.repeats,
            self.records,
            self.run.given_up.len(),
            self.run.cycles.kept,
            self.run.cycles.discarded
        );
        let _ = writeln!(
            t,
            "instrument time {:.0} s; wall time {:.1} s ({:.2} ms per node)",
            self.instrument_time_s, self.wall_time_s, self.wall_time_per_node_ms
        );
        if let Some(line) = self.survey_line() {
            let _ = writeln!(t, "{line}");
        }
        let r = &self.regression;
        let _ = writeln!(
            t,
            "surfaces: K̄x degree {} σ {:.2e}; K̄y degree {} σ {:.2e}; α degree {} σ {:.2e} rad",
            r.kx.degree, r.kx.sigma, r.ky.degree, r.ky.sigma, r.alpha.degree, r.alpha.sigma
        );
        if let Some(a) = &self.accuracy {
            let _ = writeln!(
                t,
                "{:<12} {:>12} {:>12} {:>16} {:>16}",
                "method", "RMS pm", "max pm", "mean lattice %", "max lattice %"
            );
            for (name, m) in [
                ("uncorrected", &a.uncorrected),
                ("lumped", &a.lumped),
                ("affine", &a.affine),
                ("distributed", &a.distributed),
            ]
            .into_iter()
            .chain(a.polynomial.as_ref().map(|p| ("polynomial", p)))
            {
                let _ = writeln!(
                    t,
                    "{:<12} {:>12.1} {:>12.1} {:>16.4} {:>16.4}",
                    name, m.rms_pm, m.max_pm, m.mean_lattice_error_pct, m.max_lattice_error_pct
                );
            }
            let _ = writeln!(
                t,
                "distributed / lumped RMS = {:.3}",
                a.distributed_over_lumped_rms
            );
        }
        if let Some(images) = &self.images {
            t.push_str(&images.summary_table());
        }
        if let Some(e) = &self.node_lcc_error {
            let _ = writeln!(
                t,
                "node LCCs vs oracle ({} records): K̄x {:+.3} ± {:.3} %, K̄y {:+.3} ± {:.3} %, α {:+.2} ± {:.2} mrad (mean, RMS)",
                e.n,
                e.kx_mean_pct,
                e.kx_rms_pct,
                e.ky_mean_pct,
                e.ky_rms_pct,
                e.alpha_mean_mrad,
                e.alpha_rms_mrad
            );
        }
        let h = &self.validation.held_out;
        let _ = writeln!(
            t,
            "validation, held-out nodes ({} of {}, {} records): RMS (measured − predicted)/σ = {:.2}, pass {}–{}: {}{}",
            h.nodes_held_out,
            h.nodes,
            h.records_held_out,
            h.rms_z,
            h.pass_range[0],
            h.pass_range[1],
            h.verdict.as_str().to_uppercase(),
            h.reason
                .as_deref()
                .map(|r| format!(" ({r})"))
                .unwrap_or_default()
        );
        let r = &self.validation.repeats;
        let ratios: Vec<String> = r
            .coefficients
            .iter()
            .map(|c| format!("{} {:.2}", c.coefficient, c.scatter_over_stated))
            .collect();
        let _ = writeln!(
            t,
            "validation, repeat agreement ({} places): scatter ÷ stated u = {}, pass ≤ {}: {}{}",
            r.places,
            if ratios.is_empty() {
                "-".to_owned()
            } else {
                ratios.join(", ")
            },
            r.scatter_over_stated_max,
            r.verdict.as_str().to_uppercase(),
            r.reason
                .as_deref()
                .map(|r| format!(" ({r})"))
                .unwrap_or_default()
        );
        match (&self.validation.lattice, &self.validation.lattice_failure) {
            (Some(l), _) => {
                let _ = writeln!(
                    t,
                    "validation, corrected standard ({} of {} places measured): lattice constant RMS {:.2} % (uncorrected {:.2} %{}), max {:.2} %, angles max {:.2}°, pass ≤ {} % and ≤ {}°: {}{}",
                    l.corrected_measured,
                    l.places.len(),
                    l.corrected_rms_error_pct,
                    l.uncorrected_rms_error_pct,
                    other_paths(l),
                    l.corrected_max_error_pct,
                    l.corrected_max_angle_error_deg,
                    l.thresholds[0],
                    l.thresholds[1],
                    l.verdict.as_str().to_uppercase(),
                    l.reason
                        .as_deref()
                        .map(|r| format!(" ({r})"))
                        .unwrap_or_default()
                );
            }
            (None, Some(why)) => {
                let _ = writeln!(t, "validation, corrected standard: NOT MEASURED ({why})");
            }
            (None, None) => {}
        }
        if self.targets.is_empty() {
            let _ = writeln!(t, "targets: none declared by the plan ([plan.targets])");
        }
        for v in &self.targets {
            let _ = writeln!(t, "{}", v.line());
        }
        t
    }
}

/// Fits, evaluates and writes `surfaces.json`, `report.json`, the figures and `report.html`
/// into `out`.
pub fn finish(
    cdb_path: &Path,
    out: &Path,
    record: &RunRecord<'_>,
    quick: bool,
) -> Result<CalibrationReport, ReportError> {
    finish_with(cdb_path, out, record, quick, true)
}

/// [`finish`], with the image benchmark (simulated backends) only when `with_images`: it takes
/// new images on a copy of the simulator, which sweeps of many calibrations can skip.
///
/// # Errors
/// As [`finish`].
pub fn finish_with(
    cdb_path: &Path,
    out: &Path,
    record: &RunRecord<'_>,
    quick: bool,
    with_images: bool,
) -> Result<CalibrationReport, ReportError> {
    // The dynamics first: stored (through its own handle, closed before the report reads) once
    // per run, and only when the dynamics stage gave frames (a run stopped before it, or with
    // the stage off, leaves the scanner's earlier dynamics the newest).
    // Without the stage's frames (stage off, or the run stopped before it) nothing is
    // identified.
    if !record.ladder.is_empty() {
        record.phase("identifying the scanner dynamics");
    }
    let dynamics = (!record.ladder.is_empty()).then(|| {
        crate::dynamics::identify(
            record.commands,
            record.attach_tracks,
            record.ladder,
            CREEP_LAW_SHAPE,
            record.true_dynamics.as_ref(),
        )
    });
    let identified = dynamics
        .as_ref()
        .and_then(|d| d.model.as_ref().filter(|_| d.frames_used > 0));
    if let Some(model) = identified {
        store_dynamics_once(cdb_path, record, model)?;
    }
    let identified = identified.or(record.stored_dynamics);
    let cdb = crate::cdb_handle::CdbHandle::open_read_only(cdb_path)?;
    let snapshot = cdb.snapshot()?;
    record.phase("fitting the regression surfaces");
    let mut fitted = fit_from_cdb(
        &*snapshot,
        Some(&record.plan.scanner_id),
        None,
        None,
        &SurfaceFitOptions::bic_up_to(MAX_SURFACE_DEGREE),
    )?;
    if let Some(model) = identified {
        fitted.set.dynamics = Some(model.clone());
    }
    if let Some(p) = record.provenance {
        fitted.set.provenance.written_utc = Some(p.finished_utc.clone());
    }
    let surfaces_json = fitted.set.to_json_string()?;
    write(&out.join("surfaces.json"), surfaces_json.as_bytes())?;
    let records = snapshot.count_records(&RecordFilter::default().with_run(&record.run.run_id))?;
    let all = snapshot.records(&RecordFilter::scanner(&record.plan.scanner_id))?;

    let mut notes = method_notes();
    notes.extend(record.extra_notes.iter().cloned());
    // A region of no area (the nodes of one row or column, e.g. a resume that measured only
    // those) has no raster to judge: no accuracy, said in the notes.
    let region = Region::spanned(record.nodes);
    let (accuracy, images, residual) = match (record.truth, region, fitted.set.planes.first()) {
        (Some(truth), Some(region), Some(plane)) => {
            record.phase(if with_images {
                "accuracy against the oracle, and the image benchmark (minutes)"
            } else {
                "accuracy against the oracle"
            });
            let (accuracy, images, residual) = accuracy_section(
                truth,
                record,
                &region,
                plane,
                &all,
                identified,
                quick,
                with_images,
            )?;
            (Some(accuracy), images, Some(residual))
        }
        _ => {
            notes.push(
                "accuracy: needs a simulated backend (the oracle) and measured nodes that span an area"
                    .to_owned(),
            );
            (None, None, None)
        }
    };

    let drift = DriftHistory::of(record.drift, record.plan.standard.nominal_nm_per_count);
    if drift.estimates == 0 {
        notes.push("drift: no drift estimate was made in this invocation (no figure)".to_owned());
    }
    record.phase("validating (held-out nodes, repeats, the corrected standard)");
    let validation = Validation::of(
        &all,
        record.plan,
        &fitted.set,
        record.standard_images,
        record.stored_standard,
    );
    record.phase("drawing the figures");
    let mut figures = figures(record, &fitted, &all, drift.estimates > 0)?;
    figures.extend(verdict_figures(
        record,
        (&fitted.set, &validation),
        residual.as_ref().zip(accuracy.as_ref()),
        &mut notes,
    )?);
    figures.extend(history_figure(&*snapshot, &record.plan.scanner_id)?);
    for figure in &figures {
        write(&out.join(&figure.file), &figure.png)?;
    }

    let node_lcc_error = record
        .truth
        .and_then(|truth| spm_evaluation::accuracy::node_lcc_error(truth, &all));
    let measured = record.run.nodes_done.max(1) as f64;
    let mut report = CalibrationReport {
        scanner_id: record.plan.scanner_id.clone(),
        nodes: record.run.nodes,
        repeats: record.run.repeats,
        records,
        instrument_time_s: record.run.instrument_time_s,
        wall_time_s: record.wall_time_s,
        wall_time_per_node_ms: record.wall_time_s / measured * 1e3,
        regression: fitted.summary,
        accuracy,
        images,
        node_lcc_error,
        vertical: record.truth.and_then(|truth| {
            if !fitted
                .set
                .planes
                .iter()
                .any(|p| p.kz_nm_per_count.is_some())
            {
                return None;
            }
            spm_evaluation::vertical::evaluate(truth, record.plan, &fitted.set, &all)
        }),
        dynamics,
        validation,
        provenance: record.provenance.cloned(),
        targets: Vec::new(),
        run: record.run.clone(),
        drift,
        notes,
    };
    report.targets = crate::targets::judge(&report, &record.plan.targets, record.simulated());
    write_report(out, &report, &figures)?;
    Ok(report)
}

/// `report.json` and `report.html` of `report` with its `figures`, in `out`.
fn write_report(
    out: &Path,
    report: &CalibrationReport,
    figures: &[plots::Figure],
) -> Result<(), ReportError> {
    let json = serde_json::to_string_pretty(report).map_err(|e| ReportError::Write {
        path: "report.json".to_owned(),
        message: e.to_string(),
    })?;
    write(&out.join("report.json"), json.as_bytes())?;
    write(
        &out.join("report.html"),
        crate::html::calibration_page(report, figures).as_bytes(),
    )
}

/// How the accuracy figures are measured (report.json's first notes).
fn method_notes() -> Vec<String> {
    vec![
        "accuracy: residual distortion = corrected raster (eq. 9) with the method's surfaces minus \
         the same raster corrected with the oracle's true LCC field, best rigid motion removed; \
         lattice error = apparent change of the lattice constant on an aperture-sized corrected \
         image at each of a grid of places, from the exact local maps (no detection noise)"
            .to_owned(),
        format!(
            "polynomial (per-image 3rd-order) baseline: one {POLYNOMIAL_LINES}-line image of the whole \
             region (trace + retrace at the plan's pixel dwell) over a reference grid of \
             {POLYNOMIAL_CONTROL}×{POLYNOMIAL_CONTROL} features with exact positions; a total-degree-3 \
             polynomial per coordinate fitted by least squares; the drift (oracle velocity at the end \
             of the run) moves the features during the image. A best case for the baseline: it \
             assumes a standard resolvable over the whole field in one image (a grating, not an \
             atomic lattice) and no detection noise"
        ),
    ]
}

/// The accuracy table against the ground truth over the nodes' region, and the image
/// benchmark (when asked for) on the same methods.
#[allow(clippy::too_many_arguments)]
fn accuracy_section(
    truth: &dyn TruthSource,
    record: &RunRecord<'_>,
    region: &Region,
    plane: &PlaneSurfaces,
    all: &[spm_cdb::LccRecord],
    dynamics: Option<&ScannerDynamics>,
    quick: bool,
    with_images: bool,
) -> Result<
    (
        AccuracyTable,
        Option<spm_evaluation::images::ImageBenchmark>,
        spm_evaluation::ResidualField,
    ),
    ReportError,
> {
    let oracle = truth;
    let grid = EvaluationGrid {
        x_min_counts: region.x_min_counts,
        x_max_counts: region.x_max_counts,
        y_min_counts: region.y_min_counts,
        y_max_counts: region.y_max_counts,
        z_counts: oracle.z_now().value(),
        field_pixels: if quick { 33 } else { 65 },
        image_places: if quick { 5 } else { 9 },
        image_side_counts: record.plan.aperture.size_counts,
        lattice_constant_nm: record.plan.standard.lattice_constant_nm,
    };
    let z = plane.z_counts;
    let nominal = record.plan.standard.nominal_nm_per_count;
    let uncorrected = PlaneSurfaces::constant(z, nominal, nominal, 0.0)?;
    let centre = (
        0.5 * (region.x_min_counts + region.x_max_counts),
        0.5 * (region.y_min_counts + region.y_max_counts),
    );
    let nearest = all
        .iter()
        .min_by(|a, b| {
            let da = (a.lcs_x_counts - centre.0).hypot(a.lcs_y_counts - centre.1);
            let db = (b.lcs_x_counts - centre.0).hypot(b.lcs_y_counts - centre.1);
            da.total_cmp(&db)
        })
        .map(|r| (r.node_x_counts, r.node_y_counts));
    let mean_of = |records: &[&spm_cdb::LccRecord]| {
        let n = records.len().max(1) as f64;
        (
            records.iter().map(|r| r.kx_nm_per_count).sum::<f64>() / n,
            records.iter().map(|r| r.ky_nm_per_count).sum::<f64>() / n,
            records.iter().map(|r| r.alpha_rad).sum::<f64>() / n,
        )
    };
    let centre_records: Vec<&spm_cdb::LccRecord> = all
        .iter()
        .filter(|r| Some((r.node_x_counts, r.node_y_counts)) == nearest)
        .collect();
    let (kx, ky, alpha) = mean_of(&centre_records);
    let lumped = PlaneSurfaces::constant(z, kx, ky, alpha)?;
    let every: Vec<&spm_cdb::LccRecord> = all.iter().collect();
    let (kx, ky, alpha) = mean_of(&every);
    let affine = PlaneSurfaces::constant(z, kx, ky, alpha)?;
    let images = if with_images {
        Some(truth.image_benchmark(
            record,
            region,
            &[
                ("uncorrected", &uncorrected),
                ("lumped", &lumped),
                ("affine", &affine),
                ("distributed", plane),
            ],
            dynamics,
            quick,
        )?)
    } else {
        None
    };
    let uncorrected = evaluate(oracle, &uncorrected, &grid)?;
    let lumped = evaluate(oracle, &lumped, &grid)?;
    let affine = evaluate(oracle, &affine, &grid)?;
    let distributed = evaluate(oracle, plane, &grid)?;
    let v = oracle.drift_velocity(oracle.now());
    let lines = POLYNOMIAL_LINES as f64;
    let polynomial = polynomial_baseline(
        oracle,
        &grid,
        &PolynomialImage {
            control_points: POLYNOMIAL_CONTROL,
            image_time_s: lines * 2.0 * lines * record.plan.motion.pixel_dwell_s,
            drift_nm_per_s: (v.x_nm_per_s, v.y_nm_per_s),
        },
    )?;
    let accuracy = AccuracyTable {
        distributed_over_lumped_rms: distributed.rms_pm / lumped.rms_pm,
        uncorrected,
        lumped,
        affine,
        polynomial: Some(polynomial),
        distributed,
    };
    let residual =
        spm_evaluation::residual_field(oracle, &plane.field(spm_correction::Route::Exact), &grid)?;
    Ok((accuracy, images, residual))
}

/// The figures that show what the calibration achieves: the residual-distortion map (with a
/// ground truth), the validation map (the corrected standard's lattice over the field, on
/// every backend) and the before/after image of the standard (when it was imaged; a failure
/// to draw it is a note, not an error).
fn verdict_figures(
    record: &RunRecord<'_>,
    (set, validation): (&spm_correction::SurfaceSet, &Validation),
    residual: Option<(&spm_evaluation::ResidualField, &AccuracyTable)>,
    notes: &mut Vec<String>,
) -> Result<Vec<plots::Figure>, ReportError> {
    let mut figures = Vec::new();
    if let Some(check) = &validation.lattice {
        figures.extend(plots::validation_map(
            check,
            record.plan.standard.nominal_nm_per_count,
        )?);
    }
    if let Some((field, a)) = residual {
        figures.push(plots::residual_map(
            field,
            record.nodes,
            record.plan.standard.nominal_nm_per_count,
            (a.distributed.rms_pm, a.distributed.max_pm),
        )?);
    }
    match before_after(record, set) {
        Ok(Some(figure)) => figures.push(figure),
        Ok(None) => {}
        Err(why) => notes.push(format!("before/after figure: not drawn ({why})")),
    }
    Ok(figures)
}

/// The scanner's calibration history in the CDB (every run's mean K̄x and K̄y,
/// [`plots::cdb_trend_figure`]), as `spmcal cdb trend --png` draws it for every scanner.
fn history_figure(
    cdb: &dyn spm_cdb::CdbRead,
    scanner: &str,
) -> Result<Option<plots::Figure>, ReportError> {
    let filter = RecordFilter::scanner(scanner);
    let kx = cdb.age_dynamics(
        &filter,
        spm_cdb::Coefficient::KxNmPerCount,
        spm_cdb::TrendGrouping::PerRun,
    )?;
    let ky = cdb.age_dynamics(
        &filter,
        spm_cdb::Coefficient::KyNmPerCount,
        spm_cdb::TrendGrouping::PerRun,
    )?;
    let series = [
        plots::TrendSeries {
            scanner,
            coefficient: "K̄x",
            points: &kx,
        },
        plots::TrendSeries {
            scanner,
            coefficient: "K̄y",
            points: &ky,
        },
    ];
    let Ok(png) = plots::cdb_trend_figure(&series) else {
        return Ok(None);
    };
    Ok(Some(plots::Figure {
        file: plots::HISTORY_FILE.to_owned(),
        caption: format!(
            "the {} of scanner {scanner} in this CDB: each run's mean K̄x and K̄y as the \
             change from the first run, with ± its standard uncertainty (the band); a change \
             beyond the bands means the scanner moved between calibrations.",
            if kx.len() == 1 {
                "one run".to_owned()
            } else {
                format!("{} runs", kx.len())
            }
        ),
        png,
    }))
}

/// The before/after figure of the standard: the first direct image of the validation's
/// images at the centre place (else the first direct image), corrected with `set` as
/// `spmcal correct` does. `Ok(None)` when no image was taken.
fn before_after(
    record: &RunRecord<'_>,
    set: &spm_correction::SurfaceSet,
) -> Result<Option<plots::Figure>, String> {
    let Some(Ok(images)) = record.standard_images else {
        return Ok(None);
    };
    let direct = || {
        images
            .iter()
            .filter(|i| i.direction == spm_hal::ScanDirection::Direct)
    };
    let Some(image) = direct()
        .find(|i| i.place == "centre")
        .or_else(|| direct().next())
    else {
        return Ok(None);
    };
    let pair = spm_evaluation::images::before_after::before_after(
        image,
        set,
        record.plan.standard.nominal_nm_per_count,
    )
    .map_err(|e| e.to_string())?;
    plots::before_after_figure(&pair)
        .map(Some)
        .map_err(|e| e.to_string())
}

/// The report's figures: the LCC surfaces with the measured nodes, the trajectory, the
/// surfaces' uncertainty over the scanner's records `all` and (when there are drift
/// estimates) the drift history.
fn figures(
    record: &RunRecord<'_>,
    fitted: &crate::surfaces::FittedSurfaces,
    all: &[spm_cdb::LccRecord],
    with_drift: bool,
) -> Result<Vec<plots::Figure>, ReportError> {
    let mut figures = Vec::new();
    if let (Some(region), Some(plane)) = (
        Region::around(record.nodes, 0.08),
        fitted.set.planes.first(),
    ) {
        let summary = &fitted.summary;
        for (coefficient, surface, summary) in [
            (Coefficient::Kx, &plane.kx_nm_per_count, &summary.kx),
            (Coefficient::Ky, &plane.ky_nm_per_count, &summary.ky),
            (Coefficient::Alpha, &plane.alpha_rad, &summary.alpha),
        ] {
            figures.push(plots::lcc_map(
                coefficient,
                surface,
                summary,
                record.nodes,
                &region,
                record.plan.standard.nominal_nm_per_count,
            )?);
        }
        figures.push(plots::trajectory_plot(
            record.nodes,
            record.plan.standard.nominal_nm_per_count,
        )?);
        let records: Vec<(f64, f64)> = all
            .iter()
            .filter(|r| {
                crate::surfaces::record_is_usable(r) && r.node_z_counts as f64 == plane.z_counts
            })
            .map(|r| (r.lcs_x_counts, r.lcs_y_counts))
            .collect();
        figures.push(plots::uncertainty_map(
            plane,
            summary,
            &records,
            &region,
            record.plan.standard.nominal_nm_per_count,
        )?);
    }
    if with_drift {
        figures.push(plots::drift_plot(
            record.drift,
            record.plan.standard.nominal_nm_per_count,
        )?);
    }

    Ok(figures)
}

/// The corrected standard's other paths for the console: the static surfaces alone and each
/// pair's counter partner (when the file holds dynamics).
fn other_paths(l: &spm_evaluation::validation::LatticeCheck) -> String {
    if l.dynamics_applied {
        format!(
            "; static surfaces alone {:.2} % at {} places; with each pair's counter partner {:.2} % at {} places",
            l.static_rms_error_pct, l.static_measured, l.counter_rms_error_pct, l.counter_measured
        )
    } else {
        String::new()
    }
}

/// Shortest and longest time constant of the creep law's shape, s, and elements per decade:
/// the log law over the scales that matter to images (a line, 10 ms, to a session, hours).
/// The shortest is where the identification starts: the dynamics stage chooses it from
/// [`CREEP_FAST_END_RANGE_S`] by the data ([`creep_fast_end_candidates_s`]).
pub const CREEP_LAW_SHAPE: (f64, f64, u32) = (0.01, 1.0e4, 3);
/// The range, s, over which the dynamics stage looks for the creep law's shortest time
/// constant (a fast line's pixel-to-line times, 1 ms, to a slow line, 1 s).
pub const CREEP_FAST_END_RANGE_S: (f64, f64) = (1.0e-3, 1.0);

/// The shortest creep time constants the dynamics stage tries: [`CREEP_FAST_END_RANGE_S`] at
/// the law's own spacing ([`CREEP_LAW_SHAPE`]'s elements per decade), s.
#[must_use]
pub fn creep_fast_end_candidates_s() -> Vec<f64> {
    let (lo, hi) = CREEP_FAST_END_RANGE_S;
    let per_decade = f64::from(CREEP_LAW_SHAPE.2);
    let n = ((hi / lo).log10() * per_decade).round() as usize;
    (0..=n)
        .map(|k| lo * 10f64.powf(k as f64 / per_decade))
        .collect()
}
/// Drift windows of the creep identification, s (the drift is taken constant within one).
pub const CREEP_FIT_DRIFT_WINDOW_S: f64 = 300.0;

/// The image benchmark on a copy of the simulator as the run left it (the same instrument and
/// seed stream going on): every surface-set method, the realistic grating polynomial, the
/// distributed calibration along the effective trajectory of the creep law identified from
/// the run, and two labelled bounds (the oracle's true dynamics; a per-image polynomial on
/// exact positions).
fn image_benchmark<S: SimulatedInstrument + Sync>(
    sim: &S,
    record: &RunRecord<'_>,
    region: &Region,
    planes: &[(&str, &PlaneSurfaces)],
    identified: Option<&ScannerDynamics>,
    quick: bool,
) -> Result<spm_evaluation::images::ImageBenchmark, ReportError> {
    use spm_correction::dynamics::{CommandHistory, CreepLaw, creep_offsets, fit_creep_law};
    use spm_evaluation::images::{
        GratingConfig, ImageCorrection, ImageMethod, ImageSetConfig, evaluate_images,
        grating_polynomial, take_test_images,
    };
    let plan = record.plan;
    let region = region.counts();
    let config = ImageSetConfig::standard(plan, quick);
    let grating = grating_polynomial(
        sim,
        plan.standard.nominal_nm_per_count,
        &region,
        &GratingConfig::standard(4.0 * plan.motion.pixel_dwell_s),
    )?;
    let mut instrument =
        spm_hal::recording::CommandRecorder::new(sim.clone(), crate::run::MAX_COMMANDS);
    let taken = take_test_images(&mut instrument, &region, &config)?;
    let (_, image_commands) = instrument.into_parts();

    // The creep law from the run's own attachment tracks and commands.
    let mut history = CommandHistory::from_events(record.commands);
    let (tau_min, tau_max, per_decade) = CREEP_LAW_SHAPE;
    // The shortest time constant the dynamics stage chose, when it ran.
    let tau_min = identified.map_or(tau_min, |d| d.creep.min_time_constant_s);
    let shape = CreepLaw::log_spaced(0.0, tau_min, tau_max, per_decade)?;
    let fit = fit_creep_law(
        &history,
        &shape,
        record.attach_tracks,
        CREEP_FIT_DRIFT_WINDOW_S,
    );
    history.extend_with_events(&image_commands);
    let dynamics = creep_summary(&fit);
    let split = |all: Vec<[f64; 2]>| -> Vec<Vec<[f64; 2]>> {
        let mut out = Vec::with_capacity(taken.len());
        let mut rest = all.as_slice();
        for image in &taken {
            let (head, tail) = rest.split_at(image.time_acquisition_s.len().min(rest.len()));
            out.push(head.to_vec());
            rest = tail;
        }
        out
    };
    let mut methods: Vec<ImageMethod<'_>> = planes
        .iter()
        .map(|(name, plane)| ImageMethod {
            name: (*name).to_owned(),
            correction: ImageCorrection::Field(Box::new(
                plane.field(spm_correction::Route::Products),
            )),
        })
        .collect();
    if let (Ok(f), Some((_, distributed))) =
        (&fit, planes.iter().find(|(name, _)| *name == "distributed"))
    {
        let times: Vec<f64> = taken
            .iter()
            .flat_map(|i| i.time_acquisition_s.iter().copied())
            .collect();
        let offsets = creep_offsets(&history, &f.law, &times)?;
        let gain = 1.0 + f.law.total_weight();
        methods.push(ImageMethod {
            name: "distributed_creep_model".to_owned(),
            correction: ImageCorrection::EffectivePath {
                field: Box::new(distributed.field(spm_correction::Route::Products)),
                offsets: split(offsets),
                gain: [gain, gain],
            },
        });
    }
    if let Some((_, distributed)) = planes.iter().find(|(name, _)| *name == "distributed") {
        push_user_file_methods(&mut methods, plan, distributed, identified, &history)?;
    }
    methods.push(ImageMethod {
        name: "polynomial".to_owned(),
        correction: ImageCorrection::Map(grating),
    });
    push_competitor_methods(&mut methods, plan, &config);
    push_reference_methods(&mut methods, sim, &taken, planes);
    let mut bench = evaluate_images(&taken, &methods, &config)?;
    bench.dynamics = Some(dynamics);
    Ok(bench)
}

/// The report's summary of the creep law identified from the run (or why it was not).
fn creep_summary(
    fit: &Result<spm_correction::dynamics::CreepFit, spm_correction::CorrectionError>,
) -> spm_evaluation::images::DynamicsSummary {
    use spm_evaluation::images::DynamicsSummary;
    let (tau_min, tau_max, per_decade) = CREEP_LAW_SHAPE;
    match fit {
        Ok(f) => DynamicsSummary {
            creep_weight: f.law.weight(),
            creep_weight_sigma: f.weight_sigma,
            time_constants_s: [
                f.law.time_constants_s().first().copied().unwrap_or(tau_min),
                f.law.time_constants_s().last().copied().unwrap_or(tau_max),
            ],
            elements_per_decade: per_decade,
            settled_gain: f.law.total_weight(),
            gamma_per_decade: f.gamma_per_decade,
            tracks: f.tracks,
            sightings: f.sightings,
            residual_rms_counts: f.residual_rms_counts,
            signal_rms_counts: f.signal_rms_counts,
            note: None,
        },
        Err(e) => DynamicsSummary {
            creep_weight: 0.0,
            creep_weight_sigma: f64::NAN,
            time_constants_s: [tau_min, tau_max],
            elements_per_decade: per_decade,
            settled_gain: 0.0,
            gamma_per_decade: 0.0,
            tracks: 0,
            sightings: 0,
            residual_rms_counts: f64::NAN,
            signal_rms_counts: f64::NAN,
            note: Some(format!("not identified: {e}")),
        },
    }
}

/// `spmcal correct`'s library paths with the calibration file: the recorded history, the
/// lattice ruler and the file's dynamics (when the run identified them), and the file alone.
fn push_user_file_methods(
    methods: &mut Vec<spm_evaluation::images::ImageMethod<'_>>,
    plan: &PlanConfig,
    distributed: &PlaneSurfaces,
    identified: Option<&ScannerDynamics>,
    history: &spm_correction::dynamics::CommandHistory,
) -> Result<(), ReportError> {
    use spm_evaluation::images::{ImageCorrection, ImageMethod};
    // `spmcal correct`'s library path with the calibration file (static field: no
    // recorded history is applied yet).
    let set = spm_correction::SurfaceSet::new(
        spm_correction::Provenance {
            scanner_id: plan.scanner_id.clone(),
            n_records: distributed.n_records,
            nominal_nm_per_count: Some(plan.standard.nominal_nm_per_count),
            counts_convention: Some(spm_correction::CountsConvention::CentredSigned),
            ..spm_correction::Provenance::default()
        },
        vec![(*distributed).clone()],
    )?;
    if let Some(d) = identified {
        let mut with = set.clone();
        with.dynamics = Some(d.clone());
        methods.push(ImageMethod {
            name: "user_file_recorded_history".to_owned(),
            correction: ImageCorrection::UserFileRecorded {
                set: Box::new(with.clone()),
                history: history.clone(),
            },
        });
        methods.push(ImageMethod {
            name: "user_file_ruler".to_owned(),
            correction: ImageCorrection::UserFileRuler {
                set: Box::new(with.clone()),
                ruler: spm_apply::ruler::LatticeRuler {
                    constant_nm: plan.standard.lattice_constant_nm,
                    ..spm_apply::ruler::LatticeRuler::hopg()
                },
            },
        });
        methods.push(ImageMethod {
            name: "user_file_counter".to_owned(),
            correction: ImageCorrection::UserFileCounter {
                set: Box::new(with.clone()),
                spacing: spm_apply::ruler::LatticeRuler {
                    constant_nm: plan.standard.lattice_constant_nm,
                    ..spm_apply::ruler::LatticeRuler::hopg()
                },
            },
        });
        methods.push(ImageMethod {
            name: "user_file_dynamics".to_owned(),
            correction: ImageCorrection::UserFile(Box::new(with)),
        });
    }
    methods.push(ImageMethod {
        name: "user_file_alone".to_owned(),
        correction: ImageCorrection::UserFile(Box::new(set)),
    });
    Ok(())
}

/// The competitors (issue 23 item 5), with no calibration.
fn push_competitor_methods(
    methods: &mut Vec<spm_evaluation::images::ImageMethod<'_>>,
    plan: &PlanConfig,
    config: &spm_evaluation::images::ImageSetConfig,
) {
    use spm_evaluation::images::{ImageCorrection, ImageMethod};
    // The competitors (issue 23 item 5): per-image trace/retrace corrections from their
    // papers, with no calibration; shown with the real methods.
    let competitor = spm_evaluation::competitors::CompetitorConfig {
        nominal_nm_per_count: plan.standard.nominal_nm_per_count,
        lattice_constant_nm: plan.standard.lattice_constant_nm,
        min_pixels_per_lattice_constant: config.min_pixels_per_lattice_constant,
    };
    for (name, method) in [
        (
            "competitor_yothers_2017",
            spm_evaluation::images::Competitor::Yothers,
        ),
        (
            "competitor_zhang_2019",
            spm_evaluation::images::Competitor::Zhang,
        ),
    ] {
        methods.push(ImageMethod {
            name: name.to_owned(),
            correction: ImageCorrection::PerImageCompetitor {
                method,
                config: competitor,
            },
        });
    }
}

/// The labelled references (bounds, not competitors).
fn push_reference_methods<'a, S: SimulatedInstrument + Sync>(
    methods: &mut Vec<spm_evaluation::images::ImageMethod<'a>>,
    sim: &'a S,
    taken: &[spm_evaluation::images::TestImage],
    planes: &[(&str, &'a PlaneSurfaces)],
) {
    use spm_evaluation::images::{ImageCorrection, ImageMethod};
    // References (labelled bounds, not competitors): the oracle's true static LCC field, the
    // distributed surfaces along the oracle's true effective trajectory, and a per-image cubic
    // on exact positions.
    let oracle = sim;
    let z = oracle.z_now();
    methods.push(ImageMethod {
        name: "oracle_static_field".to_owned(),
        correction: ImageCorrection::Field(Box::new(spm_correction::FnField(
            move |x: f64, y: f64| {
                let lcc = oracle.true_lcc(spm_hal::CountPoint::from_counts(x, y), z);
                spm_correction::FormCoefficients::from_lcc(
                    lcc.kx_nm_per_count,
                    lcc.ky_nm_per_count,
                    lcc.alpha_rad,
                )
            },
        ))),
    });
    if let Some((_, distributed)) = planes.iter().find(|(name, _)| *name == "distributed") {
        let offsets: Vec<Vec<[f64; 2]>> = taken
            .iter()
            .map(|i| {
                i.true_effective_acquisition
                    .iter()
                    .zip(&i.commanded_acquisition)
                    .map(|(e, u)| [e[0] - u[0], e[1] - u[1]])
                    .collect()
            })
            .collect();
        let [gx, gy] = oracle.reference_gain();
        methods.push(ImageMethod {
            name: "bound_distributed_true_dynamics".to_owned(),
            correction: ImageCorrection::EffectivePath {
                field: Box::new(distributed.field(spm_correction::Route::Products)),
                offsets,
                gain: [gx, gy],
            },
        });
    }
    methods.push(ImageMethod {
        name: "bound_polynomial_per_image".to_owned(),
        correction: ImageCorrection::PerImageBound,
    });
}

/// Stores a run's identified dynamics in the CDB, dated by when the run finished, unless the
/// run stored them already (a regenerated report).
fn store_dynamics_once(
    cdb_path: &Path,
    record: &RunRecord<'_>,
    model: &ScannerDynamics,
) -> Result<(), ReportError> {
    let mut handle = crate::cdb_handle::CdbHandle::open(cdb_path)?;
    let (run, already) = {
        let read = handle.read();
        let run = read
            .runs(Some(&record.plan.scanner_id))?
            .into_iter()
            .find(|r| r.run_id == record.run.run_id);
        let already = read
            .dynamics(Some(&record.plan.scanner_id))?
            .iter()
            .any(|d| d.run_id == record.run.run_id);
        (run, already)
    };
    let Some(run) = run.filter(|_| !already) else {
        return Ok(());
    };
    let stored = spm_records::DynamicsRecord {
        run_id: run.run_id.clone(),
        scanner_id: run.scanner_id.clone(),
        identified_unix_s: run.finished_unix_s.unwrap_or(run.started_unix_s),
        model_format: spm_correction::hysteresis::DYNAMICS_FORMAT.to_owned(),
        model_version: spm_correction::hysteresis::DYNAMICS_FORMAT_VERSION,
        model_json: serde_json::to_string(model).map_err(|e| ReportError::Write {
            path: "dynamics".to_owned(),
            message: e.to_string(),
        })?,
    };
    handle.store_dynamics(&stored)?;
    Ok(())
}

/// The hidden temporary name a report file is written under before it is renamed into place:
/// `.NAME.partial` beside it.
#[must_use]
pub fn partial_path(path: &Path) -> std::path::PathBuf {
    let name = path
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    path.with_file_name(format!(".{name}.partial"))
}

/// Writes a report file whole or not at all: into [`partial_path`], then renamed; the
/// temporary file is removed when either step fails (issue 25 item 13: a visible
/// `report.partial` was left behind).
fn write(path: &Path, bytes: &[u8]) -> Result<(), ReportError> {
    let partial = partial_path(path);
    std::fs::write(&partial, bytes)
        .and_then(|()| std::fs::rename(&partial, path))
        .map_err(|e| {
            let _ = std::fs::remove_file(&partial);
            ReportError::Write {
                path: path.display().to_string(),
                message: e.to_string(),
            }
        })
}
