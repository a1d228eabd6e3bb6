//! Net plans: the nodes of the calibration net and the order the probe visits them
//! (paper Fig. 1, DESIGN §7).
//!
//! - **Lateral planes** ([`NetGeometry::LateralPlanes`], Fig. 1a): at each Z plane (a
//!   coarse-stage position, the Z manipulator "fixed" by the feedback), the nodes of the x–y
//!   net are visited row by row; adjacent rows run in opposite x directions and adjacent
//!   planes in opposite y directions, so the trajectory is one continuous serpentine and every
//!   move is one net step (or a coarse-stage move).
//! - **Vertical planes** ([`NetGeometry::VerticalPlanes`], Fig. 1b): at each fixed Y, the
//!   x–z net is visited column by column: at a fixed x the Z levels (coarse-stage positions)
//!   are traversed, adjacent columns in opposite z directions, adjacent planes in opposite x
//!   directions.
//! - **Repeats** (Fig. 2 pos. 10): the plan is run `l` times; odd repeats traverse the
//!   trajectory backwards, starting where the previous repeat ended, so the scanner never
//!   jumps back across the field and the creep of successive passes alternates in sign.
//!
//! Every visit has a stable identity: [`PlanVisit::repeat_index`] and
//! [`PlanVisit::node_index`] (its position in the repeat's visiting order), both a
//! deterministic function of the plan, so progress stored in the CDB under them is valid
//! across runs of the same plan; [`PlanVisit::grid`] names the physical node.
//!
//! **Pause law** ([`PauseLaw`]): after a move of |Δu| counts laterally and |Δc| coarse
//! steps, the controller waits `base + per_count·|Δu| + per_coarse_step·|Δc|`, capped at
//! `max`. Creep after a step of the piezo decays roughly logarithmically with an amplitude
//! proportional to the step, so the time to fall below a fixed drift limit grows with the
//! step; the linear law with a cap is the simplest monotone rule of the paper's "the larger
//! the distance between the nodes, the longer the pause".

use serde::{Deserialize, Serialize};
use spm_hal::{CountPoint, Counts, Seconds};

/// Where the net lies and how it is traversed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum NetGeometry {
    /// Lateral x–y nets at fixed Z (Fig. 1a).
    LateralPlanes {
        /// Smallest x node coordinate, counts (the field's edge plus the margin).
        x_min_counts: i64,
        /// Largest x the net may reach, counts (nodes stop at or before it).
        x_max_counts: i64,
        /// Smallest y node coordinate, counts.
        y_min_counts: i64,
        /// Largest y the net may reach, counts.
        y_max_counts: i64,
        /// Net step along x and y, counts (> 0).
        step_counts: i64,
        /// The Z planes, in visiting order of the first repeat.
        z_planes: Vec<ZLevel>,
    },
    /// Vertical x–z nets at fixed Y (Fig. 1b).
    VerticalPlanes {
        /// Smallest x node coordinate, counts.
        x_min_counts: i64,
        /// Largest x the net may reach, counts.
        x_max_counts: i64,
        /// Net step along x, counts (> 0).
        step_counts: i64,
        /// The fixed Y positions of the planes, counts, in visiting order.
        y_planes_counts: Vec<i64>,
        /// The Z levels visited at each (x, y), in visiting order of the first column.
        z_levels: Vec<ZLevel>,
    },
}

impl NetGeometry {
    /// Number of nodes of one repeat, computed without building the plan (saturating, so
    /// an absurd net is measured before any memory is spent on it).
    pub fn node_count(&self) -> usize {
        let axis = |min: i64, max: i64, step: i64| -> usize {
            if step <= 0 || max < min {
                return 0;
            }
            usize::try_from((max.saturating_sub(min)) / step)
                .unwrap_or(usize::MAX)
                .saturating_add(1)
        };
        match self {
            Self::LateralPlanes {
                x_min_counts,
                x_max_counts,
                y_min_counts,
                y_max_counts,
                step_counts,
                z_planes,
            } => axis(*x_min_counts, *x_max_counts, *step_counts)
                .saturating_mul(axis(*y_min_counts, *y_max_counts, *step_counts))
                .saturating_mul(z_planes.len()),
            Self::VerticalPlanes {
                x_min_counts,
                x_max_counts,
                step_counts,
                y_planes_counts,
                z_levels,
            } => axis(*x_min_counts, *x_max_counts, *step_counts)
                .saturating_mul(y_planes_counts.len())
                .saturating_mul(z_levels.len()),
        }
    }
}

/// A Z level of the net: where the coarse approach stage is put, and the nominal Z
/// coordinate the level is stored under.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZLevel {
    /// Nominal Z-manipulator coordinate of the level, counts: the node z stored in the CDB
    /// (the Z plane of the regression surfaces). The measured Z at each LCS is stored
    /// separately.
    pub nominal_z_counts: i64,
    /// Coarse-stage position for this level, steps; `None` when the backend has no coarse
    /// stage that software drives (a single level).
    pub coarse_steps: Option<i64>,
}

/// The physical identity of a net node: its integer grid indices and coordinates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct GridNode {
    /// Column index along x, 0-based.
    pub ix: u32,
    /// Index along y (row for lateral planes, plane for vertical planes), 0-based.
    pub iy: u32,
    /// Index of the Z level, 0-based.
    pub iz: u32,
    /// Node x, counts.
    pub x_counts: i64,
    /// Node y, counts.
    pub y_counts: i64,
    /// Node z (the level's nominal Z), counts.
    pub z_counts: i64,
    /// Coarse-stage position of the node's level, steps.
    pub coarse_steps: Option<i64>,
}

impl GridNode {
    /// The lateral position of the node.
    pub fn position(&self) -> CountPoint {
        CountPoint::from_counts(self.x_counts as f64, self.y_counts as f64)
    }
}

/// One visit of a node: a repeat of a node at its place in the trajectory.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct PlanVisit {
    /// Repeat index, 0-based.
    pub repeat_index: u32,
    /// Position in this repeat's visiting order, 0-based (the CDB's node index).
    pub node_index: u32,
    /// The node visited.
    pub grid: GridNode,
}

/// The pause after a node move (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PauseLaw {
    /// Pause after any move, seconds (≥ 0).
    pub base_s: f64,
    /// Additional pause per count of lateral move length, seconds per count (≥ 0).
    pub per_count_s: f64,
    /// Additional pause per coarse-stage step, seconds per step (≥ 0).
    pub per_coarse_step_s: f64,
    /// Largest pause, seconds (≥ base).
    pub max_s: f64,
}

impl PauseLaw {
    /// The pause after a lateral move of `lateral` counts and `coarse_steps` coarse steps.
    pub fn pause(&self, lateral: Counts, coarse_steps: i64) -> Seconds {
        let raw = self.base_s
            + self.per_count_s * lateral.value().abs()
            + self.per_coarse_step_s * coarse_steps.unsigned_abs() as f64;
        Seconds(raw.min(self.max_s).max(0.0))
    }

    /// Checks that every field is finite and non-negative and `max ≥ base`.
    pub fn validate(&self) -> Result<(), PlanError> {
        for (field, v) in [
            ("base_s", self.base_s),
            ("per_count_s", self.per_count_s),
            ("per_coarse_step_s", self.per_coarse_step_s),
            ("max_s", self.max_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(PlanError::Invalid {
                    field,
                    reason: format!("must be finite and >= 0, got {v}"),
                });
            }
        }
        // A day is the longest pause that makes sense between two nodes; a count of lateral
        // move or a coarse step never needs more than a minute.
        for (field, v, max) in [
            ("base_s", self.base_s, 86_400.0),
            ("per_count_s", self.per_count_s, 60.0),
            ("per_coarse_step_s", self.per_coarse_step_s, 60.0),
            ("max_s", self.max_s, 86_400.0),
        ] {
            if v > max {
                return Err(PlanError::Invalid {
                    field,
                    reason: format!("must be <= {max} s, got {v}"),
                });
            }
        }
        if self.max_s < self.base_s {
            return Err(PlanError::Invalid {
                field: "max_s",
                reason: format!("must be >= base_s ({})", self.base_s),
            });
        }
        Ok(())
    }
}

/// Why a plan cannot be built.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum PlanError {
    /// A field has an invalid value.
    #[error("plan field `{field}`: {reason}")]
    Invalid {
        /// The field.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
}

/// The complete visiting order of a calibration: every repeat of every node.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NetPlan {
    /// Nodes of one repeat in the first repeat's visiting order.
    pub nodes: Vec<GridNode>,
    /// Number of repeats l (≥ 1).
    pub repeats: u32,
}

fn axis(min: i64, max: i64, step: i64, field: &'static str) -> Result<Vec<i64>, PlanError> {
    if step <= 0 {
        return Err(PlanError::Invalid {
            field: "step_counts",
            reason: format!("must be > 0, got {step}"),
        });
    }
    if max < min {
        return Err(PlanError::Invalid {
            field,
            reason: format!("empty range [{min}, {max}]"),
        });
    }
    let n = (max - min) / step + 1;
    if n > 100_000 {
        return Err(PlanError::Invalid {
            field,
            reason: format!("{n} nodes along one axis is more than 100000"),
        });
    }
    Ok((0..n).map(|i| min + i * step).collect())
}

/// Visits `outer × middle × inner` boustrophedon-style: the inner direction reverses on
/// every line (globally, so a plane starts opposite to where the previous one's last line
/// ran), the middle direction reverses on every plane.
fn serpentine(outer: usize, middle: usize, inner: usize) -> Vec<(usize, usize, usize)> {
    let mut out = Vec::with_capacity(outer * middle * inner);
    let mut line = 0usize;
    for o in 0..outer {
        for m_step in 0..middle {
            let m = if o.is_multiple_of(2) {
                m_step
            } else {
                middle - 1 - m_step
            };
            for i_step in 0..inner {
                let i = if line.is_multiple_of(2) {
                    i_step
                } else {
                    inner - 1 - i_step
                };
                out.push((o, m, i));
            }
            line += 1;
        }
    }
    out
}

impl NetPlan {
    /// Builds the plan of `geometry` repeated `repeats` times.
    ///
    /// # Errors
    /// [`PlanError::Invalid`] for a non-positive step, an empty range or plane list, zero
    /// repeats, or more than 10⁷ nodes.
    pub fn new(geometry: &NetGeometry, repeats: u32) -> Result<Self, PlanError> {
        if repeats == 0 {
            return Err(PlanError::Invalid {
                field: "repeats",
                reason: "must be at least 1".into(),
            });
        }
        let nodes = match geometry {
            NetGeometry::LateralPlanes {
                x_min_counts,
                x_max_counts,
                y_min_counts,
                y_max_counts,
                step_counts,
                z_planes,
            } => {
                let xs = axis(*x_min_counts, *x_max_counts, *step_counts, "x_max_counts")?;
                let ys = axis(*y_min_counts, *y_max_counts, *step_counts, "y_max_counts")?;
                if z_planes.is_empty() {
                    return Err(PlanError::Invalid {
                        field: "z_planes",
                        reason: "at least one Z plane is needed".into(),
                    });
                }
                check_size(xs.len() * ys.len() * z_planes.len())?;
                serpentine(z_planes.len(), ys.len(), xs.len())
                    .into_iter()
                    .map(|(iz, iy, ix)| GridNode {
                        ix: ix as u32,
                        iy: iy as u32,
                        iz: iz as u32,
                        x_counts: xs[ix],
                        y_counts: ys[iy],
                        z_counts: z_planes[iz].nominal_z_counts,
                        coarse_steps: z_planes[iz].coarse_steps,
                    })
                    .collect()
            }
            NetGeometry::VerticalPlanes {
                x_min_counts,
                x_max_counts,
                step_counts,
                y_planes_counts,
                z_levels,
            } => {
                let xs = axis(*x_min_counts, *x_max_counts, *step_counts, "x_max_counts")?;
                if y_planes_counts.is_empty() {
                    return Err(PlanError::Invalid {
                        field: "y_planes_counts",
                        reason: "at least one Y plane is needed".into(),
                    });
                }
                if z_levels.is_empty() {
                    return Err(PlanError::Invalid {
                        field: "z_levels",
                        reason: "at least one Z level is needed".into(),
                    });
                }
                check_size(xs.len() * y_planes_counts.len() * z_levels.len())?;
                serpentine(y_planes_counts.len(), xs.len(), z_levels.len())
                    .into_iter()
                    .map(|(iy, ix, iz)| GridNode {
                        ix: ix as u32,
                        iy: iy as u32,
                        iz: iz as u32,
                        x_counts: xs[ix],
                        y_counts: y_planes_counts[iy],
                        z_counts: z_levels[iz].nominal_z_counts,
                        coarse_steps: z_levels[iz].coarse_steps,
                    })
                    .collect()
            }
        };
        Ok(Self { nodes, repeats })
    }

    /// Number of nodes in one repeat.
    pub fn nodes_per_repeat(&self) -> usize {
        self.nodes.len()
    }

    /// Number of visits over all repeats.
    pub fn total_visits(&self) -> usize {
        self.nodes.len() * self.repeats as usize
    }

    /// The visit at `(repeat_index, node_index)`, if it exists. Odd repeats run backwards.
    pub fn visit(&self, repeat_index: u32, node_index: u32) -> Option<PlanVisit> {
        if repeat_index >= self.repeats {
            return None;
        }
        let n = self.nodes.len();
        let i = node_index as usize;
        if i >= n {
            return None;
        }
        let physical = if repeat_index.is_multiple_of(2) {
            i
        } else {
            n - 1 - i
        };
        Some(PlanVisit {
            repeat_index,
            node_index,
            grid: self.nodes[physical],
        })
    }

    /// Every visit in execution order.
    pub fn visits(&self) -> impl Iterator<Item = PlanVisit> + '_ {
        let n = self.nodes.len() as u32;
        (0..self.repeats).flat_map(move |r| (0..n).filter_map(move |i| self.visit(r, i)))
    }
}

fn check_size(n: usize) -> Result<(), PlanError> {
    if n > 10_000_000 {
        Err(PlanError::Invalid {
            field: "step_counts",
            reason: format!("{n} nodes per repeat is more than 10^7"),
        })
    } else {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn serpentine_reverses_lines_and_planes() {
        let s = serpentine(2, 2, 3);
        assert_eq!(
            s,
            vec![
                (0, 0, 0),
                (0, 0, 1),
                (0, 0, 2),
                (0, 1, 2),
                (0, 1, 1),
                (0, 1, 0),
                (1, 1, 0),
                (1, 1, 1),
                (1, 1, 2),
                (1, 0, 2),
                (1, 0, 1),
                (1, 0, 0),
            ]
        );
    }

    #[test]
    fn pause_law_is_linear_and_capped() {
        let law = PauseLaw {
            base_s: 1.0,
            per_count_s: 0.01,
            per_coarse_step_s: 0.5,
            max_s: 20.0,
        };
        assert_eq!(law.pause(Counts(100.0), 0), Seconds(2.0));
        assert_eq!(law.pause(Counts(-100.0), 2), Seconds(3.0));
        assert_eq!(law.pause(Counts(1e6), 0), Seconds(20.0));
        law.validate().unwrap();
        let bad = PauseLaw { max_s: 0.5, ..law };
        assert!(bad.validate().is_err());
    }
}
