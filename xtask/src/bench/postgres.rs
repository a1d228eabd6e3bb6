//! The shared CDB on PostgreSQL beside the embedded SQLite file, measured the same way on
//! both back ends: bulk insert of 10⁶ records (one transaction; --quick: 10⁵), query + BIC
//! fit over them, and four calibrations of four scanners running at once into one database,
//! counting the records each calibration reported stored against the records the database
//! holds (lost or duplicated) and running the integrity check.
//!
//! PostgreSQL runs as a private server (`spm_cdb::pg_server`, installed from the
//! distribution's `postgresql` package) with its durable defaults (fsync at commit), as SQLite
//! runs with `synchronous = FULL`; client and server share the machine's cores.

use super::Context;
use crate::XtaskError;
use serde::Serialize;
use spm_calibration::NoObserver;
use spm_cdb::bench_support::{SCANNER_ID as SCANNER, T0_UNIX_S as T0, synthetic_record};
use spm_cdb::pg_server::TestServer;
use spm_cdb::postgres::PgCdb;
use spm_cdb::{Cdb, CdbRead, OpenOptions, RecordFilter, RunInfo, RunStatus};
use spmcal::cdb_handle::CdbHandle;
use spmcal::job::Job;
use spmcal::run::{RunStart, run_job};
use spmcal::surfaces::{SurfaceFitOptions, fit_from_cdb};
use std::path::Path;
use std::time::Instant;

/// Bulk figures of one back end.
#[derive(Debug, Serialize)]
pub struct BulkFigures {
    /// `sqlite` or `postgres`.
    pub backend: String,
    /// Records inserted.
    pub records: u64,
    /// Bulk insert in one transaction, s.
    pub insert_s: f64,
    /// Inserted records per second.
    pub insert_records_per_s: f64,
    /// Query of every record of the scanner, s.
    pub query_s: f64,
    /// Query + BIC fit of the regression surfaces (degree ≤ 3), s.
    pub query_and_fit_s: f64,
}

/// Four calibrations at once into one database.
#[derive(Debug, Serialize)]
pub struct ConcurrentFigures {
    /// `sqlite` or `postgres`.
    pub backend: String,
    /// Calibrations run at once (one scanner each).
    pub calibrations: usize,
    /// Wall time until the last one finished, s.
    pub wall_time_s: f64,
    /// Records the calibrations reported stored (sum of `RunReport::records`).
    pub records_reported: u64,
    /// Records the database holds for those runs.
    pub records_stored: u64,
    /// Reported but not stored.
    pub records_lost: u64,
    /// Stored more than once: stored records minus distinct (run, repeat, node, lcs).
    pub records_duplicated: u64,
    /// Visits left pending after every calibration finished.
    pub visits_pending: u64,
    /// The integrity check found nothing.
    pub check_clean: bool,
}

/// The section.
#[derive(Debug, Serialize)]
pub struct PostgresResults {
    /// `SHOW server_version` of the private server.
    pub server_version: String,
    /// Bulk insert, query, query + fit per back end.
    pub bulk: Vec<BulkFigures>,
    /// Four concurrent calibrations per back end.
    pub concurrent: Vec<ConcurrentFigures>,
}

fn step(what: &str) -> impl Fn(spm_cdb::CdbError) -> XtaskError + '_ {
    move |e| XtaskError::step(format!("CDB {what}"), e)
}

pub fn run(ctx: &Context) -> Result<PostgresResults, XtaskError> {
    let server = TestServer::start_with(true)
        .map_err(|e| XtaskError::step("starting the private PostgreSQL server", e))?;
    let server_version = {
        let mut c = postgres::Client::connect(&server.url("postgres"), postgres::NoTls)
            .map_err(|e| XtaskError::step("PostgreSQL", e))?;
        c.query_one("SHOW server_version", &[])
            .and_then(|r| r.try_get::<_, String>(0))
            .map_err(|e| XtaskError::step("PostgreSQL", e))?
    };
    let records = if ctx.quick { 100_000 } else { 1_000_000 };
    let mut bulk = Vec::new();
    {
        let dir = ctx.scratch("cdb-backends")?;
        let mut cdb = Cdb::open_with(dir.join("cdb.sqlite"), &OpenOptions::default())
            .map_err(step("open"))?;
        let ids = create_runs(&mut |r| cdb.create_run(r))?;
        let started = Instant::now();
        let n = cdb
            .import_records((0..records).map(|i| synthetic_record(i, records / 10, &ids)))
            .map_err(step("insert"))?;
        let insert_s = started.elapsed().as_secs_f64();
        let snapshot = cdb.snapshot().map_err(step("snapshot"))?;
        bulk.push(query_and_fit("sqlite", &snapshot, n, insert_s)?);
    }
    {
        let url = server
            .create_database("bulk")
            .map_err(|e| XtaskError::step("PostgreSQL", e))?;
        let mut cdb = PgCdb::open(&url).map_err(step("open"))?;
        let ids = create_runs(&mut |r| cdb.create_run(r))?;
        let started = Instant::now();
        let n = cdb
            .import_records((0..records).map(|i| synthetic_record(i, records / 10, &ids)))
            .map_err(step("insert"))?;
        let insert_s = started.elapsed().as_secs_f64();
        let snapshot = cdb.snapshot().map_err(step("snapshot"))?;
        bulk.push(query_and_fit("postgres", &snapshot, n, insert_s)?);
    }
    for b in &bulk {
        println!(
            "   postgres: {} {} records: insert {:.2} s, query {:.2} s, query + fit {:.2} s",
            b.backend, b.records, b.insert_s, b.query_s, b.query_and_fit_s
        );
    }
    let mut concurrent = Vec::new();
    let dir = ctx.scratch("cdb-concurrent")?;
    let sqlite = dir.join("cdb.sqlite");
    concurrent.push(four_calibrations(ctx, "sqlite", &sqlite, &dir)?);
    let url = server
        .create_database("concurrent")
        .map_err(|e| XtaskError::step("PostgreSQL", e))?;
    concurrent.push(four_calibrations(ctx, "postgres", Path::new(&url), &dir)?);
    for c in &concurrent {
        println!(
            "   postgres: {} {} calibrations at once: {:.1} s, {} records reported, {} stored, \
             {} lost, {} duplicated, check {}",
            c.backend,
            c.calibrations,
            c.wall_time_s,
            c.records_reported,
            c.records_stored,
            c.records_lost,
            c.records_duplicated,
            if c.check_clean { "clean" } else { "FAILED" }
        );
    }
    Ok(PostgresResults {
        server_version,
        bulk,
        concurrent,
    })
}

/// Ten runs of the bench scanner, a day apart; returns their ids.
fn create_runs(
    create: &mut dyn FnMut(&RunInfo) -> Result<(), spm_cdb::CdbError>,
) -> Result<Vec<String>, XtaskError> {
    let mut ids = Vec::new();
    for k in 0..10u32 {
        let r = RunInfo {
            run_id: format!("run-{k:02}"),
            scanner_id: SCANNER.into(),
            config: String::new(),
            started_unix_s: T0 + 86_400.0 * f64::from(k),
            finished_unix_s: None,
            status: RunStatus::Running,
        };
        create(&r).map_err(step("create run"))?;
        ids.push(r.run_id);
    }
    Ok(ids)
}

fn query_and_fit(
    backend: &str,
    snapshot: &dyn CdbRead,
    n: u64,
    insert_s: f64,
) -> Result<BulkFigures, XtaskError> {
    let started = Instant::now();
    let all = snapshot
        .records(&RecordFilter::scanner(SCANNER))
        .map_err(step("query"))?;
    let query_s = started.elapsed().as_secs_f64();
    if all.len() as u64 != n {
        return Err(XtaskError::step(
            "CDB query",
            format!("{backend}: {} records read back of {n}", all.len()),
        ));
    }
    drop(all);
    let started = Instant::now();
    fit_from_cdb(
        snapshot,
        Some(SCANNER),
        None,
        None,
        &SurfaceFitOptions::bic_up_to(3),
    )
    .map_err(|e| XtaskError::step("CDB fit", e))?;
    Ok(BulkFigures {
        backend: backend.to_owned(),
        records: n,
        insert_s,
        insert_records_per_s: n as f64 / insert_s,
        query_s,
        query_and_fit_s: started.elapsed().as_secs_f64(),
    })
}

/// Four calibrations (scanners `shared-0` … `shared-3`, the small HOPG plan — a 13 × 13 net,
/// --quick: 3 × 3 — on the room-temperature HOPG simulator) in four threads into the CDB at `location`.
fn four_calibrations(
    ctx: &Context,
    backend: &str,
    location: &Path,
    dir: &Path,
) -> Result<ConcurrentFigures, XtaskError> {
    let (mut plan, plan_text) = Job::read_plan(&ctx.root.join("configs/plan-hopg-small.toml"))
        .map_err(|e| XtaskError::step("reading the plan", e))?;
    if !ctx.quick {
        // A 13 × 13 net (169 visits per scanner) instead of the small plan's 3 × 3.
        plan.net.step_counts = 4000;
    }
    let sim_path = ctx.root.join("configs/sim-hopg.toml");
    let mut jobs = Vec::new();
    for k in 0..4 {
        let mut plan = plan.clone();
        plan.scanner_id = format!("shared-{k}");
        jobs.push(
            Job::from_parts(&sim_path, plan, plan_text.clone())
                .map_err(|e| XtaskError::step("building the job", e))?,
        );
    }
    // The schema exists before the calibrations start (as in a lab's shared database).
    drop(CdbHandle::open(location).map_err(step("open"))?);
    let started = Instant::now();
    let reports: Vec<Result<(String, usize), XtaskError>> = std::thread::scope(|scope| {
        let handles: Vec<_> = jobs
            .iter()
            .enumerate()
            .map(|(k, job)| {
                scope.spawn(move || {
                    let outcome = run_job(
                        job,
                        location,
                        RunStart::New {
                            run_id: format!("{backend}-shared-{k}"),
                        },
                        1_800_000_000.0,
                        &mut NoObserver,
                    )
                    .map_err(|e| {
                        XtaskError::step(
                            format!("{backend} calibration {k} in {}", dir.display()),
                            e,
                        )
                    })?;
                    Ok((outcome.report.run_id, outcome.report.records))
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join().unwrap_or_else(|_| {
                    Err(XtaskError::step(
                        "concurrent calibration",
                        "thread panicked",
                    ))
                })
            })
            .collect()
    });
    let wall_time_s = started.elapsed().as_secs_f64();
    let reports = reports.into_iter().collect::<Result<Vec<_>, _>>()?;
    let cdb = CdbHandle::open_read_only(location).map_err(step("open"))?;
    let snapshot = cdb.snapshot().map_err(step("snapshot"))?;
    let (mut reported, mut stored, mut distinct, mut pending) = (0u64, 0u64, 0u64, 0u64);
    for (run_id, records) in &reports {
        reported += *records as u64;
        let all = snapshot
            .records(&RecordFilter::default().with_run(run_id))
            .map_err(step("query"))?;
        stored += all.len() as u64;
        let keys: std::collections::HashSet<(u32, u32, u32)> = all
            .iter()
            .map(|r| (r.repeat_index, r.node_index, r.lcs_index))
            .collect();
        distinct += keys.len() as u64;
        pending += snapshot
            .progress_summary(run_id)
            .map_err(step("progress"))?
            .pending;
    }
    let report = snapshot.check().map_err(step("check"))?;
    Ok(ConcurrentFigures {
        backend: backend.to_owned(),
        calibrations: reports.len(),
        wall_time_s,
        records_reported: reported,
        records_stored: stored,
        records_lost: reported.saturating_sub(distinct),
        records_duplicated: stored - distinct,
        visits_pending: pending,
        check_clean: report.is_ok(),
    })
}

#[cfg(test)]
mod tests {
    /// The section alone, at full size (10⁶ records): `cargo test -p xtask --release --
    /// --ignored shared_cdb_figures --nocapture` prints the figures as JSON.
    #[test]
    #[ignore = "minutes: the figures for docs/RESULTS.md"]
    #[allow(clippy::unwrap_used)]
    fn shared_cdb_figures() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .parent()
            .unwrap()
            .to_path_buf();
        let quick = std::env::var_os("SPMCAL_BENCH_QUICK").is_some();
        let ctx = super::Context {
            out: root.join("target/bench-postgres"),
            root,
            quick,
            // The figures are printed for the lead; docs/ is never rewritten here.
            write_docs: false,
        };
        let results = super::run(&ctx).unwrap();
        println!("{}", serde_json::to_string_pretty(&results).unwrap());
    }
}
