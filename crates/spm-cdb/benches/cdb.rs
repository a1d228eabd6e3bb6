//! CDB benchmarks (DESIGN §11): bulk insert of 10⁶ records in one transaction, the per-node
//! transaction rate of `commit_node` (synchronous FULL and NORMAL), and query + degree-3
//! regression fit over 10⁶ records.
#![allow(clippy::unwrap_used)]

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use spm_cdb::bench_support::{SCANNER_ID, T0_UNIX_S as T0};
use spm_cdb::{
    Cdb, CdbRead, LccRecord, NodeDone, OpenOptions, PlanNode, RecordFilter, RunInfo, RunStatus,
    Synchronous,
};
use spm_regression::{FitOptions, Observations, fit};
use std::path::PathBuf;
use std::time::{Duration, Instant};

const N_BIG: u64 = 1_000_000;
const RUNS: u64 = 10;

fn fresh(name: &str) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("spm-cdb-bench");
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join(format!("{name}.sqlite"));
    for suffix in ["", "-wal", "-shm"] {
        let mut f = p.clone().into_os_string();
        f.push(suffix);
        let _ = std::fs::remove_file(PathBuf::from(f));
    }
    p
}

fn run_info(k: u64) -> RunInfo {
    RunInfo {
        run_id: format!("run-{k:02}"),
        scanner_id: SCANNER_ID.into(),
        config: String::new(),
        started_unix_s: T0 + 86_400.0 * k as f64,
        finished_unix_s: None,
        status: RunStatus::Running,
    }
}

/// Record `i` of a 316×316-node net repeated over 10 runs, one Z plane; LCCs on a smooth field.
fn record(i: u64, run_ids: &[String]) -> LccRecord {
    spm_cdb::bench_support::synthetic_record(i, N_BIG / RUNS, run_ids)
}

/// A fresh CDB holding the 10 runs (no records yet).
fn with_runs(name: &str, sync: Synchronous) -> (Cdb, Vec<String>) {
    let options = OpenOptions {
        synchronous: sync,
        ..OpenOptions::default()
    };
    let mut cdb = Cdb::open_with(fresh(name), &options).unwrap();
    let mut ids = Vec::new();
    for k in 0..RUNS {
        let r = run_info(k);
        cdb.create_run(&r).unwrap();
        ids.push(r.run_id);
    }
    (cdb, ids)
}

fn bulk_insert(c: &mut Criterion) {
    let mut g = c.benchmark_group("cdb_insert");
    g.sample_size(10)
        .warm_up_time(Duration::from_millis(1))
        .measurement_time(Duration::from_secs(30))
        .throughput(Throughput::Elements(N_BIG));
    g.bench_function("bulk_1e6_one_transaction", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                let (mut cdb, ids) = with_runs("bulk", Synchronous::Full);
                let start = Instant::now();
                let n = cdb
                    .import_records((0..N_BIG).map(|i| record(i, &ids)))
                    .unwrap();
                total += start.elapsed();
                assert_eq!(n, N_BIG);
            }
            total
        });
    });
    g.bench_function("cpu_time/bulk_1e6_one_transaction", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                let (mut cdb, ids) = with_runs("bulk", Synchronous::Full);
                total += cpu_time_of(1, || {
                    cdb.import_records((0..N_BIG).map(|i| record(i, &ids)))
                        .unwrap()
                });
            }
            total
        });
    });
    g.finish();
}

fn per_node(c: &mut Criterion) {
    const NODES: u64 = 200;
    let mut g = c.benchmark_group("cdb_commit_node");
    g.sample_size(10)
        .warm_up_time(Duration::from_millis(1))
        .measurement_time(Duration::from_secs(5))
        .throughput(Throughput::Elements(NODES));
    for (label, sync) in [("full", Synchronous::Full), ("normal", Synchronous::Normal)] {
        g.bench_function(format!("200_nodes_sync_{label}"), |b| {
            b.iter_custom(|iters| {
                let mut total = Duration::ZERO;
                for _ in 0..iters {
                    let (mut cdb, ids) = with_runs(&format!("per_node_{label}"), sync);
                    let plan: Vec<PlanNode> = (0..NODES)
                        .map(|i| {
                            let r = record(i, &ids);
                            PlanNode {
                                repeat_index: 0,
                                node_index: r.node_index,
                                node_x_counts: r.node_x_counts,
                                node_y_counts: r.node_y_counts,
                                node_z_counts: 0,
                            }
                        })
                        .collect();
                    cdb.register_plan(&ids[0], &plan).unwrap();
                    let start = Instant::now();
                    for i in 0..NODES {
                        let r = record(i, &ids);
                        let done = NodeDone {
                            repeat_index: 0,
                            node_index: r.node_index,
                            attempts: 1,
                            finished_unix_s: r.acquired_unix_s,
                        };
                        cdb.commit_node(&ids[0], &done, &[r]).unwrap();
                    }
                    total += start.elapsed();
                }
                total
            });
        });
    }
    g.finish();
}

/// On-CPU time of the calling thread (ns, from /proc/thread-self/schedstat; Linux only).
/// SQLite and the fit run on this thread, so this is robust to other processes sharing the
/// cores, unlike wall time.
fn thread_cpu() -> Option<Duration> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    let ns: u64 = s.split_whitespace().next()?.parse().ok()?;
    Some(Duration::from_nanos(ns))
}

/// Runs `f` `iters` times and returns the thread CPU time it used (wall time if unavailable).
fn cpu_time_of<T>(iters: u64, mut f: impl FnMut() -> T) -> Duration {
    let wall = Instant::now();
    let start = thread_cpu();
    for _ in 0..iters {
        std::hint::black_box(f());
    }
    match (start, thread_cpu()) {
        (Some(a), Some(b)) => b.saturating_sub(a),
        _ => wall.elapsed(),
    }
}

fn query_and_fit(c: &mut Criterion) {
    let (mut cdb, ids) = with_runs("query", Synchronous::Normal);
    cdb.import_records((0..N_BIG).map(|i| record(i, &ids)))
        .unwrap();
    let filter = RecordFilter::scanner(SCANNER_ID).with_z_plane(0);
    let mut g = c.benchmark_group("cdb_query_fit");
    g.sample_size(10)
        .warm_up_time(Duration::from_millis(1))
        .measurement_time(Duration::from_secs(10))
        .throughput(Throughput::Elements(N_BIG));
    g.bench_function("query_1e6", |b| {
        b.iter(|| {
            let cols = cdb.columns(&filter).unwrap();
            assert_eq!(cols.len() as u64, N_BIG);
            cols
        });
    });
    g.bench_function("query_and_fit_degree3_1e6", |b| {
        b.iter(|| {
            let cols = cdb.columns(&filter).unwrap();
            let obs = Observations::new(
                &cols.lcs_x_counts,
                &cols.lcs_y_counts,
                &cols.kx_nm_per_count,
            );
            fit(&obs, 3, &FitOptions::default()).unwrap()
        });
    });
    // The same two measurements in thread CPU time instead of wall time.
    g.bench_function("cpu_time/query_1e6", |b| {
        b.iter_custom(|iters| cpu_time_of(iters, || cdb.columns(&filter).unwrap()));
    });
    g.bench_function("cpu_time/query_and_fit_degree3_1e6", |b| {
        b.iter_custom(|iters| {
            cpu_time_of(iters, || {
                let cols = cdb.columns(&filter).unwrap();
                let obs = Observations::new(
                    &cols.lcs_x_counts,
                    &cols.lcs_y_counts,
                    &cols.kx_nm_per_count,
                );
                fit(&obs, 3, &FitOptions::default()).unwrap()
            })
        });
    });
    g.finish();
}

criterion_group!(benches, bulk_insert, per_node, query_and_fit);
criterion_main!(benches);
