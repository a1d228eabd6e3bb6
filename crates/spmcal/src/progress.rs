//! The terminal progress bar of a calibration run (an [`Observer`]).

use indicatif::{ProgressBar, ProgressStyle};
use spm_calibration::{GiveUpReason, NodeMeasurement, Observer, PlanVisit};

/// Shows visits done out of the plan, the last node's LCCs, and given-up nodes.
pub struct ProgressBarObserver {
    bar: ProgressBar,
}

impl ProgressBarObserver {
    /// A bar on stderr (hidden when stderr is not a terminal).
    pub fn new() -> Self {
        let bar = ProgressBar::new(0);
        if let Ok(style) = ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40}] {pos}/{len} visits, ETA {eta} {msg}",
        ) {
            bar.set_style(style);
        }
        Self { bar }
    }

    /// Leaves the bar at its final state.
    pub fn finish(&self) {
        self.bar.finish();
    }

    /// A spinner for the phases after the run (hidden when stderr is not a terminal): each
    /// [`PhaseSpinner::phase`] replaces its message.
    pub fn phases() -> PhaseSpinner {
        let spinner = ProgressBar::new_spinner();
        if let Ok(style) = ProgressStyle::with_template("{elapsed_precise} {spinner} {msg}") {
            spinner.set_style(style);
        }
        spinner.enable_steady_tick(std::time::Duration::from_millis(200));
        PhaseSpinner { spinner }
    }
}

/// The phases after the run, on one spinner line.
pub struct PhaseSpinner {
    spinner: ProgressBar,
}

impl PhaseSpinner {
    /// Shows the phase that starts.
    pub fn phase(&self, name: &str) {
        self.spinner.set_message(name.to_owned());
    }

    /// Removes the spinner line.
    pub fn finish(&self) {
        self.spinner.finish_and_clear();
    }
}

impl Default for ProgressBarObserver {
    fn default() -> Self {
        Self::new()
    }
}

impl Observer for ProgressBarObserver {
    fn run_started(&mut self, total_visits: usize, already_finished: usize) {
        self.bar.set_length(total_visits as u64);
        self.bar.set_position(already_finished as u64);
    }
    fn node_finished(&mut self, measurement: &NodeMeasurement) {
        self.bar.inc(1);
        self.bar.set_message(format!(
            "K̄x {:.5} K̄y {:.5} nm/count α {:+.3}°",
            measurement.lcc.kx.value(),
            measurement.lcc.ky.value(),
            measurement.lcc.alpha.to_degrees()
        ));
    }
    fn node_given_up(&mut self, visit: &PlanVisit, reason: &GiveUpReason) {
        self.bar.inc(1);
        self.bar.println(format!(
            "node {} (repeat {}) given up: {reason}",
            visit.node_index, visit.repeat_index
        ));
    }
}
