//! Shared helpers of the CDB tests.
#![allow(clippy::unwrap_used, dead_code)]

use spm_cdb::{LccRecord, PlanNode, RunInfo, RunStatus};
use std::path::PathBuf;

/// A fresh path for a test database (removed with its WAL/SHM files if left over).
pub fn db_path(name: &str) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("spm-cdb-tests");
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join(format!("{name}.sqlite"));
    for suffix in ["", "-wal", "-shm", "-journal"] {
        let mut f = p.clone().into_os_string();
        f.push(suffix);
        let _ = std::fs::remove_file(PathBuf::from(f));
    }
    p
}

/// 2024-01-01T00:00:00Z.
pub const T0: f64 = 1_704_067_200.0;

pub fn run(run_id: &str, scanner_id: &str, started_unix_s: f64) -> RunInfo {
    RunInfo {
        run_id: run_id.into(),
        scanner_id: scanner_id.into(),
        config: "[plan]\nnodes = 3\n".into(),
        started_unix_s,
        finished_unix_s: None,
        status: RunStatus::Running,
    }
}

/// A plan of `n` nodes per plane on planes z = 0 and z = 500, one repeat.
pub fn plan(n: u32) -> Vec<PlanNode> {
    let mut v = Vec::new();
    for (p, z) in [0_i64, 500].into_iter().enumerate() {
        for k in 0..n {
            v.push(PlanNode {
                repeat_index: 0,
                node_index: p as u32 * n + k,
                node_x_counts: i64::from(k) * 1000,
                node_y_counts: i64::from(k % 2) * 1000,
                node_z_counts: z,
            });
        }
    }
    v
}

/// A plausible record at a plan node.
pub fn record(run: &RunInfo, node: &PlanNode, lcs_index: u32, t_unix_s: f64) -> LccRecord {
    let k = f64::from(node.node_index) + 0.1 * f64::from(lcs_index);
    LccRecord {
        scanner_id: run.scanner_id.clone(),
        run_id: run.run_id.clone(),
        acquired_unix_s: t_unix_s,
        repeat_index: node.repeat_index,
        node_index: node.node_index,
        lcs_index,
        node_x_counts: node.node_x_counts,
        node_y_counts: node.node_y_counts,
        node_z_counts: node.node_z_counts,
        lcs_x_counts: node.node_x_counts as f64 + 0.25,
        lcs_y_counts: node.node_y_counts as f64 - 0.5,
        lcs_z_counts: node.node_z_counts as f64 + 1.0 / 3.0,
        kx_nm_per_count: 0.02 + 1e-5 * k,
        ky_nm_per_count: 0.021 - 1e-5 * k,
        alpha_rad: 0.001 * k - 0.002,
        kz_nm_per_count: if node.node_index.is_multiple_of(2) {
            Some(0.003)
        } else {
            None
        },
        u_kx_nm_per_count: Some(1e-5),
        u_ky_nm_per_count: Some(2e-5),
        u_alpha_rad: Some(1e-3),
        u_kz_nm_per_count: None,
        drift_vx_nm_per_s: 0.01,
        drift_vy_nm_per_s: -0.02,
        cycles_kept: 8,
        cycles_discarded: 2,
        quality: 0.9,
        kz_x_counts: None,
        kz_y_counts: None,
    }
}
