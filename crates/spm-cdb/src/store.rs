//! [`ProgressStore`] for the embedded CDB: the calibration controller writes through it.

use std::collections::HashMap;

use spm_records::{LccRecord, NodeDone, NodeState, PlanNode, ProgressStore, RunInfo, RunStatus};

use crate::{Cdb, CdbError, CdbRead};

impl ProgressStore for Cdb {
    type Error = CdbError;
    fn begin_run(&mut self, run: &RunInfo, visits: &[PlanNode]) -> Result<(), Self::Error> {
        if self.run(&run.run_id)?.is_none() {
            self.create_run(run)?;
        }
        self.register_plan(&run.run_id, visits)
    }
    fn states(&mut self, run_id: &str) -> Result<HashMap<(u32, u32), NodeState>, Self::Error> {
        Ok(self
            .progress(run_id)?
            .into_iter()
            .map(|p| ((p.node.repeat_index, p.node.node_index), p.state))
            .collect())
    }
    fn commit_node(
        &mut self,
        run_id: &str,
        done: &NodeDone,
        records: &[LccRecord],
    ) -> Result<(), Self::Error> {
        Cdb::commit_node(self, run_id, done, records)
    }
    fn give_up_node(
        &mut self,
        run_id: &str,
        visit: &NodeDone,
        reason: &str,
    ) -> Result<(), Self::Error> {
        Cdb::give_up_node(
            self,
            run_id,
            visit.repeat_index,
            visit.node_index,
            reason,
            visit.attempts,
            visit.finished_unix_s,
        )
    }
    fn finish_run(
        &mut self,
        run_id: &str,
        status: RunStatus,
        at_unix_s: f64,
    ) -> Result<(), Self::Error> {
        Cdb::finish_run(self, run_id, status, at_unix_s)
    }
}
