//! Range and plausibility rules of a stored record against its run (issue 25: bit rot).
//!
//! [`LccRecord::check`] holds the rules a record obeys on its own (finite, K̄ > 0, |α| <
//! π/2). A record can obey them and still be impossible for the instrument that measured
//! it: an LCS y of −1.38·10⁹ counts on a ±32 768-count scanner, a K̄x a hundred times the
//! expected one. Those values come only from damage (bit rot, a hand edit), never from a
//! measurement, so `cdb check` reports them and the fit leaves them out.
//!
//! The limits come from the run's configuration text (`runs.config`, the job, plan and
//! simulator configs as `calibrate` stored them): the instrument's field
//! (`[instrument] lateral_half_range_counts`, `z_half_range_counts`), the aperture
//! (`[plan.aperture] size_counts`), the net's step (`[plan.net] step_counts`) and the
//! nominal sensitivity (`[plan.standard] nominal_nm_per_count`). A limit the text does not
//! give is not applied (a run of another program, a Nanonis job without a field).

use crate::model::LccRecord;

/// How many aperture sizes an LCS may lie from its node (attachments follow the feature
/// through creep and drift, so an LCS is not exactly at its node).
pub const APERTURES_FROM_NODE: f64 = 16.0;

/// How far K̄x, K̄y may lie from the nominal sensitivity, as a factor (LCS matching accepts
/// sides within a tolerance of typically ±30 % of the nominal, so a measured K̄ beyond a
/// factor of 2 cannot come from a measurement).
pub const NOMINAL_FACTOR: f64 = 2.0;

/// The limits a run's records must keep (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Plausibility {
    /// Half the lateral field (counts): |x|, |y| of nodes and LCSs at most this.
    pub lateral_half_range_counts: Option<f64>,
    /// Half the Z range (counts): |z| of nodes and LCSs at most this.
    pub z_half_range_counts: Option<f64>,
    /// Aperture size (counts).
    pub aperture_counts: Option<f64>,
    /// Step between the net's nodes (counts).
    pub step_counts: Option<f64>,
    /// Nominal sensitivity (nm per count).
    pub nominal_nm_per_count: Option<f64>,
}

impl Plausibility {
    /// The limits a run's configuration text gives (TOML as `calibrate` stores it: one or
    /// more documents one after the other; the first value of each key counts). Values
    /// that are not finite positive numbers are ignored.
    #[must_use]
    pub fn from_run_config(text: &str) -> Self {
        let mut p = Self::default();
        let mut table = String::new();
        for line in text.lines() {
            let line = line.split('#').next().unwrap_or("").trim();
            if let Some(name) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
                table = name.trim().to_owned();
                continue;
            }
            let Some((key, value)) = line.split_once('=') else {
                continue;
            };
            let Ok(value) = value.trim().replace('_', "").parse::<f64>() else {
                continue;
            };
            if !(value.is_finite() && value > 0.0) {
                continue;
            }
            let slot = match (table.as_str(), key.trim()) {
                ("instrument", "lateral_half_range_counts") => &mut p.lateral_half_range_counts,
                ("instrument", "z_half_range_counts") => &mut p.z_half_range_counts,
                ("plan.aperture", "size_counts") => &mut p.aperture_counts,
                ("plan.net", "step_counts") => &mut p.step_counts,
                ("plan.standard", "nominal_nm_per_count") => &mut p.nominal_nm_per_count,
                _ => continue,
            };
            slot.get_or_insert(value);
        }
        p
    }

    /// True when no limit is known.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }

    /// How far (counts, per axis) an LCS may lie from its node: [`APERTURES_FROM_NODE`]
    /// apertures, but at least half the net's step (an LCS nearer its own node than the
    /// next one is never implausible).
    #[must_use]
    pub fn max_offset_counts(&self) -> Option<f64> {
        let apertures = self.aperture_counts.map(|a| a * APERTURES_FROM_NODE);
        let half_step = self.step_counts.map(|s| s / 2.0);
        match (apertures, half_step) {
            (Some(a), Some(s)) => Some(a.max(s)),
            (a, s) => a.or(s),
        }
    }
}

impl LccRecord {
    /// Why the record is implausible for a run with these limits, or `None` when it keeps
    /// them all: node and LCS within the field, the LCS within
    /// [`Plausibility::max_offset_counts`] of its node, K̄x and K̄y within
    /// [`NOMINAL_FACTOR`] of the nominal sensitivity.
    #[must_use]
    pub fn implausibility(&self, limits: &Plausibility) -> Option<String> {
        let outside = |what: &str, v: f64, half: f64| {
            (v.abs() > half + 0.5)
                .then(|| format!("{what} = {v} counts lies outside the field ±{half} counts"))
        };
        if let Some(h) = limits.lateral_half_range_counts {
            let checks = [
                ("node_x_counts", self.node_x_counts as f64),
                ("node_y_counts", self.node_y_counts as f64),
                ("lcs_x_counts", self.lcs_x_counts),
                ("lcs_y_counts", self.lcs_y_counts),
            ];
            if let Some(why) = checks.iter().find_map(|&(w, v)| outside(w, v, h)) {
                return Some(why);
            }
        }
        if let Some(h) = limits.z_half_range_counts {
            let checks = [
                ("node_z_counts", self.node_z_counts as f64),
                ("lcs_z_counts", self.lcs_z_counts),
            ];
            if let Some(why) = checks.iter().find_map(|&(w, v)| outside(w, v, h)) {
                return Some(why);
            }
        }
        if let Some(max) = limits.max_offset_counts() {
            let dx = self.lcs_x_counts - self.node_x_counts as f64;
            let dy = self.lcs_y_counts - self.node_y_counts as f64;
            if dx.abs() > max || dy.abs() > max {
                return Some(format!(
                    "the LCS lies ({dx}, {dy}) counts from its node, more than {max} counts"
                ));
            }
        }
        if let Some(nominal) = limits.nominal_nm_per_count {
            for (what, k) in [
                ("kx_nm_per_count", self.kx_nm_per_count),
                ("ky_nm_per_count", self.ky_nm_per_count),
            ] {
                if !(k >= nominal / NOMINAL_FACTOR && k <= nominal * NOMINAL_FACTOR) {
                    return Some(format!(
                        "{what} = {k} is not within a factor {NOMINAL_FACTOR} of the nominal \
                         {nominal} nm/count"
                    ));
                }
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CONFIG: &str = "# simulator: sim.toml\nseed = 1\n[instrument]\n\
        lateral_half_range_counts = 32768.0\nz_half_range_counts = 32_768.0  # z\n\
        [plan]\nscanner_id = \"s\"\n[plan.standard]\nnominal_nm_per_count = 0.02\n\
        [plan.net]\nstep_counts = 20000\n[plan.aperture]\nsize_counts = 50.0\n\
        # plan\n[plan.aperture]\nsize_counts = 99.0\n";

    #[test]
    fn limits_come_from_the_run_config() {
        let p = Plausibility::from_run_config(CONFIG);
        assert_eq!(p.lateral_half_range_counts, Some(32768.0));
        assert_eq!(p.z_half_range_counts, Some(32768.0));
        assert_eq!(p.nominal_nm_per_count, Some(0.02));
        assert_eq!(p.aperture_counts, Some(50.0), "the first value counts");
        assert_eq!(p.max_offset_counts(), Some(10_000.0));
        assert!(Plausibility::from_run_config("[plan]\nnodes = 3\n").is_empty());
    }
}
