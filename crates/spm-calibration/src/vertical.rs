//! The vertical axis at a node (issue 15): the Z level of the LCS for the bowl, and Kz from a
//! monatomic step searched near the node.
//!
//! After a node's LCCs are measured the controller (when the plan has a `[plan.steps]`
//! table, [`StepSearchConfig`])
//! 1. scans a small square at the LCS and takes its mean Z as the LCS's Z (the corrugation
//!    and the noise averaged; the run stores it as `lcs_z_counts`, from which the bowl
//!    surface of each Z plane is fitted);
//! 2. searches windows around the node, nearest first, out to `search_radius_counts`, scans
//!    each (trace and retrace) and measures a step in it ([`spm_features::measure_step_pair`]);
//!    the first clean monatomic step gives `Kz = h / H` with its uncertainty. A window with
//!    no edge moves the search on; a rejected step (double step, tip change, defects…) is
//!    remembered with its reason and the search moves on.
//!
//! Nothing is invented: without a clean step in reach the record carries no Kz and the search
//! outcome ([`KzSearch`]) says why (no edge in any window, or the rejections met).

use serde::{Deserialize, Serialize};
use spm_features::{StepConfig, StepRejection, measure_step, measure_step_pair};
use spm_hal::{
    CountPoint, Counts, Error as _, Microscope, MoveRequest, ScanRequest, Seconds, TraceHalf,
};

/// The step search of a plan (the `[plan.steps]` table). Units in the names.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StepSearchConfig {
    /// Expected Kz, nm per count: turns the standard's step height into the expected height
    /// in counts (steps whose height is off by more than `height_tolerance_fraction` are not
    /// monatomic). The measurement gives the true one.
    pub nominal_kz_nm_per_count: f64,
    /// Accepted relative deviation of a step's height from the nominal, e.g. 0.3.
    pub height_tolerance_fraction: f64,
    /// Side of a step window, counts (a few tens of nm).
    pub window_size_counts: f64,
    /// Pixels per line of a step window (≥ 32).
    pub window_pixels: u32,
    /// Lines of a step window (≥ 16).
    pub window_lines: u32,
    /// Half-width of the band around the edge left out of the terrace fits, nm (the edge's
    /// transition and the feedback lag; ≥ 1 nm for HOPG).
    pub edge_mask_nm: f64,
    /// Farthest window centre from the node, counts (0 = only the window at the node).
    pub search_radius_counts: f64,
    /// Side of the square scanned at the LCS for its mean Z (the bowl), counts; 0 = keep the
    /// single Z reading.
    pub level_size_counts: f64,
    /// Pixels per side of that square (≥ 4).
    pub level_pixels: u32,
}

impl StepSearchConfig {
    /// Checks the ranges; returns the offending field (under `steps.`) and the reason.
    pub fn check(&self) -> Result<(), (String, String)> {
        let bad = |f: &str, r: String| Err((format!("steps.{f}"), r));
        for (f, v, lo, hi) in [
            (
                "nominal_kz_nm_per_count",
                self.nominal_kz_nm_per_count,
                1e-6,
                10.0,
            ),
            (
                "height_tolerance_fraction",
                self.height_tolerance_fraction,
                0.01,
                0.45,
            ),
            ("window_size_counts", self.window_size_counts, 8.0, 1e9),
            ("edge_mask_nm", self.edge_mask_nm, 0.1, 1e4),
        ] {
            if !(v.is_finite() && (lo..=hi).contains(&v)) {
                return bad(
                    f,
                    format!("must be a finite number in [{lo}, {hi}], got {v}"),
                );
            }
        }
        for (f, v) in [
            ("search_radius_counts", self.search_radius_counts),
            ("level_size_counts", self.level_size_counts),
        ] {
            if !(v.is_finite() && (0.0..=1e9).contains(&v)) {
                return bad(f, format!("must be a finite number in [0, 1e9], got {v}"));
            }
        }
        for (f, v, lo) in [
            ("window_pixels", self.window_pixels, 32),
            ("window_lines", self.window_lines, 16),
            ("level_pixels", self.level_pixels, 4),
        ] {
            if !(lo..=4096).contains(&v) {
                return bad(f, format!("must be in [{lo}, 4096], got {v}"));
            }
        }
        if self.search_radius_counts / (0.5 * self.window_size_counts) > 20.0 {
            return bad(
                "search_radius_counts",
                "searches more than 40 × 40 windows; shrink it or enlarge the windows".into(),
            );
        }
        Ok(())
    }

    /// The window centres, nearest first: a square grid of pitch half a window around the
    /// node (an edge near one window's border is near the middle of the next), within the
    /// search radius.
    pub fn window_offsets(&self) -> Vec<(f64, f64)> {
        let pitch = 0.5 * self.window_size_counts;
        let n = (self.search_radius_counts / pitch).floor() as i64;
        let mut out: Vec<(f64, f64)> = (-n..=n)
            .flat_map(|i| (-n..=n).map(move |j| (i as f64 * pitch, j as f64 * pitch)))
            .filter(|(x, y)| x.hypot(*y) <= self.search_radius_counts + 1e-9)
            .collect();
        out.sort_by(|a, b| a.0.hypot(a.1).total_cmp(&b.0.hypot(b.1)));
        out
    }
}

/// The outcome of a node's step search.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "outcome", rename_all = "snake_case")]
pub enum KzOutcome {
    /// A clean monatomic step was measured.
    Measured {
        /// Kz = h / H, nm per count.
        kz_nm_per_count: f64,
        /// Its standard uncertainty, nm per count.
        u_kz_nm_per_count: f64,
        /// The step height, Z counts.
        height_counts: f64,
        /// The edge point, counts.
        edge_x_counts: f64,
        /// The edge point, counts.
        edge_y_counts: f64,
        /// Windows scanned.
        windows: usize,
    },
    /// No window within the search radius shows a clean monatomic step.
    NoStepInReach {
        /// Windows scanned.
        windows: usize,
        /// Rejected steps met on the way (kind and message), if any.
        rejected: Vec<String>,
    },
    /// The instrument failed during the search (the node's LCCs are kept; no Kz).
    Failed {
        /// The error.
        message: String,
    },
}

/// What the vertical measurements at a node gave.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct KzSearch {
    /// Mean Z of the level square at the LCS, counts (None: not measured).
    pub level_z_counts: Option<f64>,
    /// The step search.
    pub kz: KzOutcome,
}

impl KzSearch {
    /// Sets Kz (and the LCS's Z) of a record from this outcome; nothing when no step was
    /// measured.
    pub fn apply(&self, record: &mut spm_records::LccRecord) {
        if let Some(z) = self.level_z_counts {
            record.lcs_z_counts = z;
        }
        if let KzOutcome::Measured {
            kz_nm_per_count,
            u_kz_nm_per_count,
            edge_x_counts,
            edge_y_counts,
            ..
        } = self.kz
        {
            record.kz_nm_per_count = Some(kz_nm_per_count);
            record.u_kz_nm_per_count = Some(u_kz_nm_per_count);
            record.kz_x_counts = Some(edge_x_counts);
            record.kz_y_counts = Some(edge_y_counts);
        }
    }

    /// A one-line summary (logs and notes).
    pub fn summary(&self) -> String {
        match &self.kz {
            KzOutcome::Measured {
                kz_nm_per_count,
                u_kz_nm_per_count,
                windows,
                ..
            } => format!(
                "Kz {kz_nm_per_count:.6} ± {u_kz_nm_per_count:.6} nm/count ({windows} windows)"
            ),
            KzOutcome::NoStepInReach { windows, rejected } if rejected.is_empty() => {
                format!("no step in reach ({windows} windows, no edge)")
            }
            KzOutcome::NoStepInReach { windows, rejected } => format!(
                "no clean step in reach ({windows} windows; rejected: {})",
                rejected.join("; ")
            ),
            KzOutcome::Failed { message } => format!("step search failed: {message}"),
        }
    }
}

/// Scan parameters shared with the plan's motion settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScanMotion {
    /// Pixel dwell, s.
    pub pixel_dwell_s: f64,
    /// Move speed, counts/s.
    pub move_speed_counts_per_s: f64,
    /// Settle after a move, s.
    pub settle_s: f64,
}

fn centred(centre: CountPoint, size: f64, nx: u32, ny: u32, dwell: f64) -> ScanRequest {
    let step = size / f64::from(nx.saturating_sub(1).max(1));
    let mut r = ScanRequest::centred_square(centre, Counts(step), nx, Seconds(dwell));
    r.lines = ny;
    let half_y = step * f64::from(ny.saturating_sub(1)) / 2.0;
    r.origin = CountPoint::new(r.origin.x, centre.y - Counts(half_y));
    r
}

/// Measures the vertical quantities at a node: the LCS's level and Kz from a step near the
/// node (see the module docs). `lateral_nm_per_count` (the plan's nominal) converts the
/// edge mask to pixels. Instrument errors end the search with
/// [`KzOutcome::Failed`]; they never fail the node.
pub fn measure_node<M: Microscope + ?Sized>(
    mic: &mut M,
    node: CountPoint,
    lcs: CountPoint,
    config: &StepSearchConfig,
    step_height_nm: f64,
    lateral_nm_per_count: f64,
    motion: ScanMotion,
) -> KzSearch {
    let caps = mic.capabilities();
    let inside = |r: &ScanRequest| r.check_inside(caps.field_min, caps.field_max).is_ok();
    let mut level = None;
    if config.level_size_counts > 0.0 {
        let r = centred(
            lcs,
            config.level_size_counts,
            config.level_pixels,
            config.level_pixels,
            motion.pixel_dwell_s,
        );
        if inside(&r)
            && let Ok(frame) = mic.scan(&r)
        {
            let z = &frame.forward.z_counts;
            if !z.is_empty() && z.iter().all(|v| v.is_finite()) {
                level = Some(z.iter().sum::<f64>() / z.len() as f64);
            }
        }
    }
    // Box averages that locate the edge span ~1 nm (several atoms), whatever the pixel.
    let pixel_nm = lateral_nm_per_count * config.window_size_counts
        / f64::from(config.window_pixels.max(2) - 1);
    let step_config = StepConfig {
        height_tolerance_fraction: config.height_tolerance_fraction,
        smoothing_px: ((1.0 / pixel_nm).round() as usize).clamp(2, 64),
        min_terrace_px: ((2.0 / pixel_nm).round() as usize).clamp(6, 256),
        ..StepConfig::monatomic(
            step_height_nm / config.nominal_kz_nm_per_count,
            config.edge_mask_nm
                / (lateral_nm_per_count
                    * (config.window_size_counts / f64::from(config.window_pixels.max(2) - 1))),
        )
    };
    let mut windows = 0;
    let mut rejected = Vec::new();
    for (dx, dy) in config.window_offsets() {
        let centre = CountPoint::new(node.x + Counts(dx), node.y + Counts(dy));
        let mut request = centred(
            centre,
            config.window_size_counts,
            config.window_pixels,
            config.window_lines,
            motion.pixel_dwell_s,
        );
        request.record_backward = caps.backward_trace;
        if !inside(&request) {
            continue;
        }
        // Transient errors (timeouts, communication, feedback lost) are retried twice.
        let mut attempt = 0;
        let frame = loop {
            let moved = mic.move_to(MoveRequest {
                target: request.origin,
                speed: spm_hal::CountsPerSecond(motion.move_speed_counts_per_s),
                settle: Seconds(motion.settle_s),
            });
            match moved.and_then(|()| mic.scan(&request)) {
                Ok(f) => break f,
                Err(e) if e.kind().is_transient() && attempt < 2 => attempt += 1,
                Err(e) => {
                    return KzSearch {
                        level_z_counts: level,
                        kz: KzOutcome::Failed {
                            message: e.to_string(),
                        },
                    };
                }
            }
        };
        windows += 1;
        let forward = frame.height_map(TraceHalf::Forward);
        let backward = frame.height_map(TraceHalf::Backward);
        let result = match (forward, backward) {
            (Ok(f), Ok(b)) => measure_step_pair(&f, &b, &step_config),
            (Ok(f), Err(_)) => measure_step(&f, &step_config),
            (Err(e), _) => Err(StepRejection::Unusable(e.to_string())),
        };
        match result {
            Ok(m) => {
                let kz = step_height_nm / m.height_counts;
                tracing::debug!(kz, windows, "step measured");
                return KzSearch {
                    level_z_counts: level,
                    kz: KzOutcome::Measured {
                        kz_nm_per_count: kz,
                        u_kz_nm_per_count: kz * m.u_height_counts / m.height_counts,
                        height_counts: m.height_counts,
                        edge_x_counts: m.edge_point.x.value(),
                        edge_y_counts: m.edge_point.y.value(),
                        windows,
                    },
                };
            }
            Err(StepRejection::NoEdge { .. }) => {}
            Err(other) => {
                tracing::debug!(reason = %other, "step rejected");
                rejected.push(format!("{}: {other}", other.kind()));
            }
        }
    }
    KzSearch {
        level_z_counts: level,
        kz: KzOutcome::NoStepInReach { windows, rejected },
    }
}

/// Checks the Z levels against the backend: a level that sets a coarse-stage position needs a
/// coarse stage, and the position must be inside the stage's range.
///
/// # Errors
/// [`crate::PlanError::Invalid`] naming `z_levels.coarse_steps`.
pub fn check_coarse_levels(
    levels: &[crate::ZLevel],
    capabilities: &spm_hal::Capabilities,
) -> Result<(), crate::PlanError> {
    for (k, level) in levels.iter().enumerate() {
        let Some(steps) = level.coarse_steps else {
            continue;
        };
        let Some(stage) = &capabilities.coarse_z else {
            return Err(crate::PlanError::Invalid {
                field: "z_levels.coarse_steps",
                reason: format!(
                    "level {k} sets the coarse stage to {steps} steps, but the instrument has \
                     no coarse Z stage"
                ),
            });
        };
        if steps < stage.min_steps || steps > stage.max_steps {
            return Err(crate::PlanError::Invalid {
                field: "z_levels.coarse_steps",
                reason: format!(
                    "level {k}: {steps} steps is outside the stage's range [{}, {}]",
                    stage.min_steps, stage.max_steps
                ),
            });
        }
    }
    Ok(())
}

/// How the step searches of a run ended.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct KzTally {
    /// Visits with a measured Kz.
    pub measured: usize,
    /// Visits without a step in reach (no edge in any window).
    pub no_step_in_reach: usize,
    /// Visits whose only steps were rejected (double steps, tip changes, defects…).
    pub only_rejected_steps: usize,
    /// Visits whose search failed on an instrument error.
    pub failed: usize,
    /// Rejections met, by kind.
    pub rejections: std::collections::BTreeMap<String, usize>,
}

impl KzTally {
    /// Counts one search.
    pub fn count(&mut self, search: &KzSearch) {
        match &search.kz {
            KzOutcome::Measured { .. } => self.measured += 1,
            KzOutcome::NoStepInReach { rejected, .. } => {
                if rejected.is_empty() {
                    self.no_step_in_reach += 1;
                } else {
                    self.only_rejected_steps += 1;
                }
                for r in rejected {
                    let kind = r.split(':').next().unwrap_or("unknown").to_owned();
                    *self.rejections.entry(kind).or_insert(0) += 1;
                }
            }
            KzOutcome::Failed { .. } => self.failed += 1,
        }
    }
}

/// The runner's hook after a node's LCCs: with `[plan.steps]`, measures the vertical
/// quantities at the node and applies them to the record; `None` without the table.
pub fn at_node<M: Microscope + ?Sized>(
    mic: &mut M,
    plan: &crate::PlanConfig,
    record: &mut spm_records::LccRecord,
) -> Option<KzSearch> {
    let steps = plan.steps.as_ref()?;
    let height = plan.standard.step_height_nm?;
    let node = CountPoint::from_counts(record.node_x_counts as f64, record.node_y_counts as f64);
    let lcs = CountPoint::from_counts(record.lcs_x_counts, record.lcs_y_counts);
    let motion = ScanMotion {
        pixel_dwell_s: plan.motion.pixel_dwell_s,
        move_speed_counts_per_s: plan.motion.move_speed_counts_per_s,
        settle_s: plan.motion.settle_s,
    };
    let search = measure_node(
        mic,
        node,
        lcs,
        steps,
        height,
        plan.standard.nominal_nm_per_count,
        motion,
    );
    tracing::info!(summary = %search.summary(), "vertical measurements at the node");
    search.apply(record);
    Some(search)
}
