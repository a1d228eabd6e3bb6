//! The drift monitor of paper §2.6, as a pure state machine.
//!
//! Fed with one drift velocity per cycle (skipping or counter-scanning), it
//! says what to do with the cycle and what comes next: a cycle whose velocity
//! changed beyond the tolerance is *spoiled* and discarded; idle cycles follow;
//! if the drift recovered (the idle velocity is back within tolerance of the
//! velocity before the spoil) the interrupted measurement continues,
//! otherwise it restarts with the new velocity as reference; after too many
//! restarts (long-term instability) it gives up, and the caller returns to
//! the net node and redoes it. It owns no microscope and no loop: the loop
//! that runs cycles and stops on [`Decision::Done`] or [`Decision::GiveUp`]
//! is separate ([`crate::skip`]), so the policy is testable on its own.

use serde::{Deserialize, Serialize};
use spm_hal::CountVelocity;

/// Settings of the drift monitor.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MonitorParams {
    /// Largest accepted change of the drift velocity between a cycle and the
    /// reference (the mean of the kept cycles), counts per second.
    pub velocity_tolerance_counts_per_s: f64,
    /// Largest accepted drift speed in any cycle (beyond it the feature may
    /// leave its segment), counts per second.
    pub max_speed_counts_per_s: f64,
    /// Idle cycles after a spoiled one. Default 2.
    pub idle_cycles: usize,
    /// Measuring cycles to keep before the measurement is done.
    pub required_cycles: usize,
    /// Restarts allowed before giving up. Default 2.
    pub max_restarts: usize,
}

impl MonitorParams {
    /// Defaults for a given tolerance, speed limit and number of cycles.
    pub fn new(
        velocity_tolerance_counts_per_s: f64,
        max_speed_counts_per_s: f64,
        required_cycles: usize,
    ) -> Self {
        Self {
            velocity_tolerance_counts_per_s,
            max_speed_counts_per_s,
            idle_cycles: 2,
            required_cycles,
            max_restarts: 2,
        }
    }
}

/// Why a cycle was declared spoiled.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SpoilReason {
    /// The velocity differs from the reference by more than the tolerance.
    VelocityChange {
        /// |v − v_ref|, counts per second.
        change_counts_per_s: f64,
    },
    /// The drift speed exceeds the limit.
    TooFast {
        /// |v|, counts per second.
        speed_counts_per_s: f64,
    },
    /// The cycle could not be measured (e.g. velocity not finite).
    Invalid,
}

/// What the next cycle is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CycleKind {
    /// A measuring cycle: its result is kept if the monitor accepts it.
    Measuring,
    /// An idle cycle: run only to watch the drift; its result is not kept.
    Idle,
}

/// The monitor's verdict on one observed cycle.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Decision {
    /// Keep this measuring cycle; continue measuring.
    Keep,
    /// Keep this measuring cycle; the required number is reached.
    Done,
    /// This measuring cycle is spoiled: discard it; idle cycles follow.
    Discard(SpoilReason),
    /// An idle cycle; more idle cycles follow.
    Idle {
        /// Idle cycles still to run.
        remaining: usize,
    },
    /// Idle cycles are over and the drift recovered: continue the
    /// interrupted measurement (kept cycles stay).
    Resume,
    /// Idle cycles are over and the drift did not recover: drop the kept
    /// cycles and measure again with the new velocity as reference.
    Restart,
    /// Long-term instability: give up this measurement (return to the node).
    GiveUp,
}

impl Decision {
    /// True when the observed cycle's data are to be kept.
    pub fn keeps_cycle(self) -> bool {
        matches!(self, Self::Keep | Self::Done)
    }
    /// True when the measurement is over (done or given up).
    pub fn is_terminal(self) -> bool {
        matches!(self, Self::Done | Self::GiveUp)
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum State {
    Measuring,
    Idle { remaining: usize },
    Finished,
}

/// The state machine. See the module documentation.
#[derive(Clone, Debug, PartialEq)]
pub struct DriftMonitor {
    params: MonitorParams,
    reference: Option<CountVelocity>,
    sum: (f64, f64),
    kept: usize,
    restarts: usize,
    state: State,
    discarded: usize,
    idle: usize,
}

impl DriftMonitor {
    /// A monitor; `reference` is the drift velocity known beforehand (e.g.
    /// from the attachment), if any.
    pub fn new(params: MonitorParams, reference: Option<CountVelocity>) -> Self {
        Self {
            params,
            reference,
            sum: (0.0, 0.0),
            kept: 0,
            restarts: 0,
            state: State::Measuring,
            discarded: 0,
            idle: 0,
        }
    }

    /// What the next cycle is for.
    pub fn next_cycle(&self) -> CycleKind {
        match self.state {
            State::Idle { .. } => CycleKind::Idle,
            State::Measuring | State::Finished => CycleKind::Measuring,
        }
    }

    /// The current reference velocity.
    pub fn reference(&self) -> Option<CountVelocity> {
        self.reference
    }

    /// Measuring cycles kept since the last restart.
    pub fn kept(&self) -> usize {
        self.kept
    }

    /// Spoiled cycles so far.
    pub fn discarded(&self) -> usize {
        self.discarded
    }

    /// Idle cycles run so far.
    pub fn idle_cycles(&self) -> usize {
        self.idle
    }

    /// Restarts so far.
    pub fn restarts(&self) -> usize {
        self.restarts
    }

    fn spoil(&self, v: CountVelocity) -> Option<SpoilReason> {
        let speed = v.norm_counts_per_s();
        if !speed.is_finite() {
            return Some(SpoilReason::Invalid);
        }
        if speed > self.params.max_speed_counts_per_s {
            return Some(SpoilReason::TooFast {
                speed_counts_per_s: speed,
            });
        }
        let reference = self.reference?;
        let change = (v.x_counts_per_s - reference.x_counts_per_s)
            .hypot(v.y_counts_per_s - reference.y_counts_per_s);
        (change > self.params.velocity_tolerance_counts_per_s).then_some(
            SpoilReason::VelocityChange {
                change_counts_per_s: change,
            },
        )
    }

    fn keep(&mut self, v: CountVelocity) -> Decision {
        self.kept += 1;
        self.sum.0 += v.x_counts_per_s;
        self.sum.1 += v.y_counts_per_s;
        let n = self.kept as f64;
        self.reference = Some(CountVelocity {
            x_counts_per_s: self.sum.0 / n,
            y_counts_per_s: self.sum.1 / n,
        });
        if self.kept >= self.params.required_cycles {
            self.state = State::Finished;
            Decision::Done
        } else {
            Decision::Keep
        }
    }

    /// Feeds the drift velocity measured in the cycle just run and returns
    /// the verdict. After a terminal decision further calls return it again.
    pub fn observe(&mut self, velocity: CountVelocity) -> Decision {
        match self.state {
            State::Finished => {
                if self.kept >= self.params.required_cycles {
                    Decision::Done
                } else {
                    Decision::GiveUp
                }
            }
            State::Measuring => match self.spoil(velocity) {
                None => self.keep(velocity),
                Some(reason) => {
                    self.discarded += 1;
                    if self.params.idle_cycles == 0 {
                        self.after_idle(velocity)
                    } else {
                        self.state = State::Idle {
                            remaining: self.params.idle_cycles,
                        };
                        Decision::Discard(reason)
                    }
                }
            },
            State::Idle { remaining } => {
                self.idle += 1;
                if remaining > 1 {
                    self.state = State::Idle {
                        remaining: remaining - 1,
                    };
                    Decision::Idle {
                        remaining: remaining - 1,
                    }
                } else {
                    self.after_idle(velocity)
                }
            }
        }
    }

    fn after_idle(&mut self, velocity: CountVelocity) -> Decision {
        if self.spoil(velocity).is_none() {
            self.state = State::Measuring;
            return Decision::Resume;
        }
        if self.restarts >= self.params.max_restarts {
            self.state = State::Finished;
            self.kept = 0;
            return Decision::GiveUp;
        }
        self.restarts += 1;
        self.kept = 0;
        self.sum = (0.0, 0.0);
        let speed = velocity.norm_counts_per_s();
        self.reference =
            (speed.is_finite() && speed <= self.params.max_speed_counts_per_s).then_some(velocity);
        self.state = State::Measuring;
        Decision::Restart
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn v(x: f64) -> CountVelocity {
        CountVelocity {
            x_counts_per_s: x,
            y_counts_per_s: 0.0,
        }
    }

    /// Feeds velocities (counts/s along x) and compares the decisions.
    fn check(reference: Option<f64>, velocities: &[f64], expected: &[Decision]) {
        let params = MonitorParams::new(1.0, 50.0, 3);
        let mut monitor = DriftMonitor::new(params, reference.map(v));
        let got: Vec<Decision> = velocities.iter().map(|&x| monitor.observe(v(x))).collect();
        assert_eq!(got, expected, "velocities {velocities:?}");
    }

    const CHANGE: fn(f64) -> Decision = |c| {
        Decision::Discard(SpoilReason::VelocityChange {
            change_counts_per_s: c,
        })
    };

    #[test]
    fn decisions_follow_paper_section_2_6() {
        use Decision::*;
        // Steady drift: three kept cycles, done.
        check(Some(5.0), &[5.2, 4.9, 5.1], &[Keep, Keep, Done]);
        // No prior reference: the first cycle sets it.
        check(None, &[3.0, 3.5, 2.8], &[Keep, Keep, Done]);
        // A burst spoils a cycle; two idle cycles; drift recovered: resume.
        check(
            Some(5.0),
            &[5.0, 9.0, 9.0, 5.2, 5.1, 4.9],
            &[Keep, CHANGE(4.0), Idle { remaining: 1 }, Resume, Keep, Done],
        );
        // The drift settles at a new value: restart with it as reference.
        check(
            Some(5.0),
            &[5.0, 9.0, 9.0, 9.0, 9.0, 9.1, 8.9],
            &[
                Keep,
                CHANGE(4.0),
                Idle { remaining: 1 },
                Restart,
                Keep,
                Keep,
                Done,
            ],
        );
        // Long-term instability: give up after two restarts.
        check(
            Some(0.0),
            &[3.0, 0.0, 6.0, 9.0, 0.0, 12.0, 15.0, 0.0, 18.0, 0.0],
            &[
                CHANGE(3.0),
                Idle { remaining: 1 },
                Restart,
                CHANGE(3.0),
                Idle { remaining: 1 },
                Restart,
                CHANGE(3.0),
                Idle { remaining: 1 },
                GiveUp,
                GiveUp,
            ],
        );
        // Too fast is spoiled whatever the reference.
        check(
            None,
            &[60.0],
            &[Discard(SpoilReason::TooFast {
                speed_counts_per_s: 60.0,
            })],
        );
        check(None, &[f64::NAN], &[Discard(SpoilReason::Invalid)]);
    }

    #[test]
    fn next_cycle_kind_follows_the_state() {
        let mut m = DriftMonitor::new(MonitorParams::new(1.0, 50.0, 2), Some(v(0.0)));
        assert_eq!(m.next_cycle(), CycleKind::Measuring);
        assert!(!m.observe(v(5.0)).keeps_cycle());
        assert_eq!(m.next_cycle(), CycleKind::Idle);
        m.observe(v(0.0));
        m.observe(v(0.0));
        assert_eq!(m.next_cycle(), CycleKind::Measuring);
        assert_eq!((m.discarded(), m.idle_cycles(), m.restarts()), (1, 2, 0));
        assert!(m.observe(v(0.1)).keeps_cycle());
        assert!(m.observe(v(0.1)).is_terminal());
    }
}
