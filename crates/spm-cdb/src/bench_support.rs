//! Synthetic CDB content shared by spm-cdb's criterion bench and `cargo xtask bench`
//! (no I/O here): a 316-wide node grid whose LCCs lie on smooth surfaces with a small
//! deterministic wiggle, so that both measure the same workload.

use crate::LccRecord;

/// Scanner id of the synthetic records.
pub const SCANNER_ID: &str = "bench-scanner";
/// Acquisition time of the first record: 2024-01-01T00:00:00Z, Unix seconds.
pub const T0_UNIX_S: f64 = 1_704_067_200.0;

/// Record `i` of a net of `per_run` nodes (316 per row, 200 counts apart) repeated in
/// consecutive runs, one run a day, named by `run_ids` (the last id is reused past its end;
/// an empty list gives an empty id, a `per_run` of 0 counts as 1).
pub fn synthetic_record(i: u64, per_run: u64, run_ids: &[String]) -> LccRecord {
    let per_run = per_run.max(1);
    let (run, k) = (i / per_run, i % per_run);
    let (x, y) = ((k % 316) as i64 * 200, (k / 316) as i64 * 200);
    let (xf, yf) = (x as f64, y as f64);
    let wiggle = ((i as f64) * 12.9898).sin();
    LccRecord {
        scanner_id: SCANNER_ID.into(),
        run_id: usize::try_from(run)
            .ok()
            .and_then(|r| run_ids.get(r))
            .or(run_ids.last())
            .cloned()
            .unwrap_or_default(),
        acquired_unix_s: T0_UNIX_S + 86_400.0 * run as f64 + 3.0 * k as f64,
        repeat_index: 0,
        node_index: k as u32,
        lcs_index: 0,
        node_x_counts: x,
        node_y_counts: y,
        node_z_counts: 0,
        lcs_x_counts: xf + 0.3 * wiggle,
        lcs_y_counts: yf - 0.2 * wiggle,
        lcs_z_counts: 0.0,
        kx_nm_per_count: 0.02 + 1e-8 * xf - 2e-8 * yf + 1e-13 * xf * yf + 1e-5 * wiggle,
        ky_nm_per_count: 0.021 - 1e-8 * xf + 1e-5 * wiggle,
        alpha_rad: 0.001 + 1e-9 * yf,
        kz_nm_per_count: None,
        u_kx_nm_per_count: Some(1e-5),
        u_ky_nm_per_count: Some(1e-5),
        u_alpha_rad: Some(1e-4),
        u_kz_nm_per_count: None,
        drift_vx_nm_per_s: 0.01,
        drift_vy_nm_per_s: -0.01,
        cycles_kept: 8,
        cycles_discarded: 1,
        quality: 0.9,
        kz_x_counts: None,
        kz_y_counts: None,
    }
}
