//! The storage trait a calibration run writes through, and an in-memory implementation.

use std::collections::HashMap;

use crate::columns::RecordProblem;
use crate::model::{LccRecord, NodeDone, NodeState, PlanNode, RunInfo, RunStatus};

/// Where a calibration run's plan progress and records go.
///
/// Implemented by `spm_cdb::Cdb` (embedded SQLite), by the shared PostgreSQL store, and by
/// [`MemoryStore`] (dry runs and tests). Every method is one transaction: a run killed at any
/// moment leaves each visit either pending, done with all its records, or given up.
pub trait ProgressStore {
    /// The store's error.
    type Error: std::error::Error + Send + Sync + 'static;
    /// Creates the run if it does not exist (else leaves it) and registers the plan's
    /// visits (idempotent).
    ///
    /// # Errors
    /// The store's error (I/O, a conflicting plan already registered under this run id).
    fn begin_run(&mut self, run: &RunInfo, visits: &[PlanNode]) -> Result<(), Self::Error>;
    /// The state of every registered visit, by (repeat, node index).
    ///
    /// # Errors
    /// The store's error.
    fn states(&mut self, run_id: &str) -> Result<HashMap<(u32, u32), NodeState>, Self::Error>;
    /// Stores a measured visit's records and marks it done, in one transaction.
    ///
    /// # Errors
    /// The store's error; an invalid record ([`LccRecord::check`]) or a visit that is not
    /// pending stores nothing.
    fn commit_node(
        &mut self,
        run_id: &str,
        done: &NodeDone,
        records: &[LccRecord],
    ) -> Result<(), Self::Error>;
    /// Marks a visit as given up with its reason.
    ///
    /// # Errors
    /// The store's error; a visit that is not pending is left as it is.
    fn give_up_node(
        &mut self,
        run_id: &str,
        visit: &NodeDone,
        reason: &str,
    ) -> Result<(), Self::Error>;
    /// Sets the run's final status.
    ///
    /// # Errors
    /// The store's error (an unknown run).
    fn finish_run(
        &mut self,
        run_id: &str,
        status: RunStatus,
        at_unix_s: f64,
    ) -> Result<(), Self::Error>;
}

impl<S: ProgressStore + ?Sized> ProgressStore for &mut S {
    type Error = S::Error;
    fn begin_run(&mut self, run: &RunInfo, visits: &[PlanNode]) -> Result<(), Self::Error> {
        (**self).begin_run(run, visits)
    }
    fn states(&mut self, run_id: &str) -> Result<HashMap<(u32, u32), NodeState>, Self::Error> {
        (**self).states(run_id)
    }
    fn commit_node(
        &mut self,
        run_id: &str,
        done: &NodeDone,
        records: &[LccRecord],
    ) -> Result<(), Self::Error> {
        (**self).commit_node(run_id, done, records)
    }
    fn give_up_node(
        &mut self,
        run_id: &str,
        visit: &NodeDone,
        reason: &str,
    ) -> Result<(), Self::Error> {
        (**self).give_up_node(run_id, visit, reason)
    }
    fn finish_run(
        &mut self,
        run_id: &str,
        status: RunStatus,
        at_unix_s: f64,
    ) -> Result<(), Self::Error> {
        (**self).finish_run(run_id, status, at_unix_s)
    }
}

/// An in-memory [`ProgressStore`] (dry runs and tests): the same semantics as the CDB's plan
/// progress, without persistence.
#[derive(Clone, Debug, Default)]
pub struct MemoryStore {
    /// Runs by id.
    pub runs: HashMap<String, RunInfo>,
    /// Visit states by (run, repeat, node).
    pub states: HashMap<(String, u32, u32), NodeState>,
    /// Stored records in commit order.
    pub records: Vec<LccRecord>,
}

/// Errors of [`MemoryStore`].
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum MemoryStoreError {
    /// The visit is not registered or not pending.
    #[error(
        "memory store: visit (run {run_id:?}, repeat {repeat_index}, node {node_index}) is {state:?}, not pending"
    )]
    NotPending {
        /// Run.
        run_id: String,
        /// Repeat index.
        repeat_index: u32,
        /// Node index.
        node_index: u32,
        /// Its state, `None` if it is not registered.
        state: Option<NodeState>,
    },
    /// No such run.
    #[error("memory store: no run {run_id:?}")]
    NoRun {
        /// Run.
        run_id: String,
    },
    /// A record failed [`LccRecord::check`].
    #[error("memory store: {0}")]
    InvalidRecord(#[from] RecordProblem),
}

impl MemoryStore {
    fn pending(&self, run_id: &str, visit: &NodeDone) -> Result<(), MemoryStoreError> {
        let key = (run_id.to_owned(), visit.repeat_index, visit.node_index);
        match self.states.get(&key) {
            Some(NodeState::Pending) => Ok(()),
            other => Err(MemoryStoreError::NotPending {
                run_id: run_id.to_owned(),
                repeat_index: visit.repeat_index,
                node_index: visit.node_index,
                state: other.cloned(),
            }),
        }
    }
}

impl ProgressStore for MemoryStore {
    type Error = MemoryStoreError;
    fn begin_run(&mut self, run: &RunInfo, visits: &[PlanNode]) -> Result<(), Self::Error> {
        self.runs
            .entry(run.run_id.clone())
            .or_insert_with(|| run.clone());
        for v in visits {
            self.states
                .entry((run.run_id.clone(), v.repeat_index, v.node_index))
                .or_insert(NodeState::Pending);
        }
        Ok(())
    }
    fn states(&mut self, run_id: &str) -> Result<HashMap<(u32, u32), NodeState>, Self::Error> {
        Ok(self
            .states
            .iter()
            .filter(|((r, _, _), _)| r == run_id)
            .map(|((_, rep, node), s)| ((*rep, *node), s.clone()))
            .collect())
    }
    fn commit_node(
        &mut self,
        run_id: &str,
        done: &NodeDone,
        records: &[LccRecord],
    ) -> Result<(), Self::Error> {
        self.pending(run_id, done)?;
        for r in records {
            r.check()?;
        }
        self.records.extend_from_slice(records);
        self.states.insert(
            (run_id.to_owned(), done.repeat_index, done.node_index),
            NodeState::Done,
        );
        Ok(())
    }
    fn give_up_node(
        &mut self,
        run_id: &str,
        visit: &NodeDone,
        reason: &str,
    ) -> Result<(), Self::Error> {
        self.pending(run_id, visit)?;
        self.states.insert(
            (run_id.to_owned(), visit.repeat_index, visit.node_index),
            NodeState::GivenUp(reason.to_owned()),
        );
        Ok(())
    }
    fn finish_run(
        &mut self,
        run_id: &str,
        status: RunStatus,
        at_unix_s: f64,
    ) -> Result<(), Self::Error> {
        let run = self
            .runs
            .get_mut(run_id)
            .ok_or_else(|| MemoryStoreError::NoRun {
                run_id: run_id.to_owned(),
            })?;
        run.status = status;
        run.finished_unix_s = Some(at_unix_s);
        Ok(())
    }
}
