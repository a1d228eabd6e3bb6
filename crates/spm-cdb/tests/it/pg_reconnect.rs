//! Issue 25 item 4 (rest): a PostgreSQL CDB whose connection is lost (the session ended by
//! the server, the server restarted, the reply to a COMMIT lost) opens it again and does the
//! interrupted transaction once — never twice, never half; a backend stopped in the middle
//! of a session (SIGSTOP: its kernel still acknowledges, so no keepalive fires) fails the
//! statement at the client-side reply timeout; a stop request ends a wait for it and a
//! reconnect loop. The truth is the server's own tables, read on a separate connection.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common::{self, Backend, T0, plan, record, run};
use spm_cdb::postgres::PgCdb;
use spm_cdb::{CdbRead, ErrorKind, NodeDone, RecordFilter};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

fn done(node_index: u32) -> NodeDone {
    NodeDone {
        repeat_index: 0,
        node_index,
        attempts: 1,
        finished_unix_s: T0 + f64::from(node_index),
    }
}

/// A CDB with a run of `nodes` pending nodes.
fn cdb_with_plan(url: &str, nodes: u32) -> PgCdb {
    let mut cdb = PgCdb::open(url).unwrap();
    let r = run("run-1", "S", T0);
    cdb.create_run(&r).unwrap();
    cdb.register_plan(&r.run_id, &plan(nodes)).unwrap();
    cdb
}

fn commit(cdb: &mut PgCdb, node: u32) -> spm_cdb::Result<()> {
    let r = run("run-1", "S", T0);
    let n = &plan(node + 1)[node as usize];
    let recs: Vec<_> = (0..3).map(|k| record(&r, n, k, T0)).collect();
    cdb.commit_node(&r.run_id, &done(node), &recs)
}

/// (state, records) of every node, read on a connection of its own.
fn stored(url: &str) -> Vec<(i64, String, i64)> {
    let mut c = postgres::Client::connect(url, postgres::NoTls).unwrap();
    c.query(
        "SELECT p.node_index, p.state, (SELECT count(*) FROM records r WHERE r.run_id = \
         p.run_id AND r.repeat_index = p.repeat_index AND r.node_index = p.node_index) \
         FROM progress p ORDER BY p.node_index",
        &[],
    )
    .unwrap()
    .iter()
    .map(|r| (r.get(0), r.get(1), r.get(2)))
    .collect()
}

/// What [`stored`] should read: the plan of `cdb_with_plan(url, n)` (2 n nodes) with the
/// nodes `done` stored, 3 records each.
fn expected(n: u32, done: &[i64]) -> Vec<(i64, String, i64)> {
    (0..i64::from(2 * n))
        .map(|k| {
            if done.contains(&k) {
                (k, "done".to_owned(), 3)
            } else {
                (k, "pending".to_owned(), 0)
            }
        })
        .collect()
}

fn admin(url: &str, sql: &str) {
    postgres::Client::connect(url, postgres::NoTls)
        .unwrap()
        .batch_execute(sql)
        .unwrap();
}

/// Sends a signal to a server process (`kill -SIG pid`).
fn signal(pid: i32, sig: &str) {
    let status = std::process::Command::new("kill")
        .args([format!("-{sig}"), pid.to_string()])
        .status()
        .unwrap();
    assert!(status.success(), "kill -{sig} {pid}");
}

/// A backend stopped with SIGSTOP, continued when dropped (also when a test fails).
struct Stopped(i32);
impl Stopped {
    fn new(pid: i32) -> Self {
        signal(pid, "STOP");
        Self(pid)
    }
}
impl Drop for Stopped {
    fn drop(&mut self) {
        signal(self.0, "CONT");
    }
}

/// Runs `f` on a thread; a call still blocked after `limit` is a hang (the test fails, the
/// thread is left behind).
fn within<T: Send + 'static>(limit: Duration, f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(limit)
        .unwrap_or_else(|_| panic!("still blocked after {limit:?}: a hang"))
}

/// The server ends the session (SQLSTATE 57P01, as at a shutdown): the next write opens the
/// connection again and is stored once.
#[test]
fn a_session_ended_by_the_server_is_opened_again_and_the_write_stored_once() {
    let url = common::postgres().fresh("pg_reconnect_terminated");
    let mut cdb = cdb_with_plan(&url, 3);
    commit(&mut cdb, 0).unwrap();
    let pid = cdb.backend_pid().unwrap();
    admin(&url, &format!("SELECT pg_terminate_backend({pid})"));
    commit(&mut cdb, 1).unwrap();
    assert_eq!(cdb.reconnects(), 1);
    assert_ne!(cdb.backend_pid().unwrap(), pid);
    // Reads reconnect too.
    admin(
        &url,
        &format!(
            "SELECT pg_terminate_backend({})",
            cdb.backend_pid().unwrap()
        ),
    );
    assert_eq!(cdb.count_records(&RecordFilter::default()).unwrap(), 6);
    assert_eq!(cdb.reconnects(), 2);
    assert_eq!(stored(&url), expected(3, &[0, 1]));
}

/// The connection is lost after the server committed but before the client heard: the
/// server is asked whether the transaction committed, and it is not done again (doing it
/// again would find the node done: a conflict, or with another writer, a duplicate).
#[test]
fn a_commit_whose_reply_was_lost_is_not_done_twice() {
    let url = common::postgres().fresh("pg_reconnect_lost_commit");
    let mut cdb = cdb_with_plan(&url, 2);
    cdb.lose_next_commit_reply();
    commit(&mut cdb, 0).unwrap();
    assert_eq!(cdb.reconnects(), 1);
    assert_eq!(stored(&url), expected(2, &[0]));
    let check = PgCdb::open_read_only(&url).unwrap().check().unwrap();
    assert!(check.is_ok(), "{check:?}");
}

/// A transaction cut in its middle (the session ended while it ran) is rolled back by the
/// server and done again whole on the new connection.
#[test]
fn a_transaction_cut_in_its_middle_is_done_again_whole() {
    let url = common::postgres().fresh("pg_reconnect_mid_tx");
    let mut cdb = cdb_with_plan(&url, 2);
    // A session holding the plan row makes the commit wait inside its transaction (after its
    // first statements); the commit's session is ended while it waits.
    let pid = cdb.backend_pid().unwrap();
    let killer = {
        let url = url.clone();
        std::thread::spawn(move || {
            let mut c = postgres::Client::connect(&url, postgres::NoTls).unwrap();
            let started = Instant::now();
            loop {
                let waiting: bool = c
                    .query_one(
                        "SELECT count(*) > 0 FROM pg_stat_activity WHERE pid = $1 AND \
                         wait_event_type = 'Lock'",
                        &[&pid],
                    )
                    .unwrap()
                    .get(0);
                if waiting {
                    break;
                }
                assert!(started.elapsed() < Duration::from_secs(20), "never waited");
                std::thread::sleep(Duration::from_millis(10));
            }
            c.batch_execute(&format!("SELECT pg_terminate_backend({pid})"))
                .unwrap();
        })
    };
    let (locked, holding) = std::sync::mpsc::channel();
    let releaser = {
        let url = url.clone();
        std::thread::spawn(move || {
            let mut holder = postgres::Client::connect(&url, postgres::NoTls).unwrap();
            let mut tx = holder.transaction().unwrap();
            tx.batch_execute("SELECT * FROM progress WHERE node_index = 0 FOR UPDATE")
                .unwrap();
            locked.send(()).unwrap();
            killer.join().unwrap();
            std::thread::sleep(Duration::from_millis(300));
            tx.rollback().unwrap();
        })
    };
    holding.recv().unwrap();
    commit(&mut cdb, 0).unwrap();
    releaser.join().unwrap();
    assert_eq!(cdb.reconnects(), 1);
    assert_eq!(stored(&url), expected(2, &[0]));
}

/// The server stopped and started again (same port and data) between two writes, and again
/// while a write waits in its reconnect pauses: both writes stored once.
#[test]
fn a_server_restart_is_survived() {
    let mut server = spm_cdb::pg_server::TestServer::start().unwrap();
    let url = server.create_database("restart").unwrap();
    let mut cdb = cdb_with_plan(&url, 3);
    commit(&mut cdb, 0).unwrap();
    server.restart().unwrap();
    commit(&mut cdb, 1).unwrap();
    assert_eq!(cdb.reconnects(), 1);
    // Down while the write starts, up again 1.5 s later: the write waits in its pauses.
    server.stop();
    let restarter = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(1500));
        server.restart().unwrap();
        server
    });
    commit(&mut cdb, 2).unwrap();
    let _server = restarter.join().unwrap();
    assert_eq!(cdb.reconnects(), 2);
    assert_eq!(stored(&url), expected(3, &[0, 1, 2]));
}

/// A server gone for good: the reconnect loop is bounded by its attempts, and a stop request
/// ends it at once (within a poll of its pause).
#[test]
fn reconnecting_is_bounded_and_ends_at_a_stop_request() {
    let mut server = spm_cdb::pg_server::TestServer::start().unwrap();
    let url = server.create_database("gone").unwrap();
    let bounded = format!("{url}?spmcal_reconnect_attempts=3&spmcal_reconnect_backoff_s=0.2");
    let mut cdb = cdb_with_plan(&bounded, 2);
    let mut stoppable = cdb_with_plan_on(&url, "run-2");
    let stop = Arc::new(AtomicBool::new(false));
    stoppable.set_interrupt(Arc::clone(&stop));
    server.stop();
    // 3 attempts, pauses 0.2 + 0.4 s.
    let started = Instant::now();
    let e = commit(&mut cdb, 0).unwrap_err();
    let took = started.elapsed();
    assert_eq!(e.kind(), ErrorKind::Postgres, "{e}");
    assert!(e.to_string().contains("3 reconnect attempt(s)"), "{e}");
    assert!(took < Duration::from_secs(10), "{took:?}");
    // Default settings (10 attempts, up to 2 s apart): the stop ends the loop.
    let setter = {
        let stop = Arc::clone(&stop);
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(800));
            stop.store(true, Ordering::SeqCst);
        })
    };
    let started = Instant::now();
    let e = within(Duration::from_secs(60), move || {
        let r = run("run-2", "S", T0);
        let n = &plan(1)[0];
        let recs = vec![record(&r, n, 0, T0)];
        stoppable
            .commit_node(&r.run_id, &done(0), &recs)
            .unwrap_err()
    });
    setter.join().unwrap();
    let took = started.elapsed();
    assert_eq!(e.kind(), ErrorKind::Interrupted, "{e}");
    assert!(took < Duration::from_secs(3), "{took:?}");
}

fn cdb_with_plan_on(url: &str, run_id: &str) -> PgCdb {
    let mut cdb = PgCdb::open(url).unwrap();
    let r = run(run_id, "S", T0);
    cdb.create_run(&r).unwrap();
    cdb.register_plan(&r.run_id, &plan(1)).unwrap();
    cdb
}

/// A backend stopped mid-session: a read (the integrity check) and a write fail at the
/// reply timeout (here 2 s) as unanswered, instead of waiting for ever.
#[test]
fn a_stopped_backend_fails_the_statement_at_the_reply_timeout() {
    let url = common::postgres().fresh("pg_stopped_backend");
    let quick = format!("{url}?spmcal_reply_timeout_s=2");
    drop(cdb_with_plan(&url, 2));
    let reader = PgCdb::open_read_only(&quick).unwrap();
    let _stopped = Stopped::new(reader.backend_pid().unwrap());
    let started = Instant::now();
    let e = within(Duration::from_secs(60), move || reader.check().unwrap_err());
    let took = started.elapsed();
    assert_eq!(e.kind(), ErrorKind::Postgres, "{e}");
    assert!(e.to_string().contains("did not answer within 2 s"), "{e}");
    assert!(took >= Duration::from_millis(1900), "{took:?}");
    assert!(took < Duration::from_secs(8), "{took:?}");

    let mut writer = PgCdb::open(&quick).unwrap();
    let _stopped = Stopped::new(writer.backend_pid().unwrap());
    let started = Instant::now();
    let e = within(Duration::from_secs(60), move || {
        commit(&mut writer, 0).unwrap_err()
    });
    assert!(e.to_string().contains("did not answer within 2 s"), "{e}");
    assert!(started.elapsed() < Duration::from_secs(8));
}

/// A stop request while the client waits for a stopped backend ends the wait within about
/// a second, long before the (default, 120 s) reply timeout; nothing of the write is stored.
#[test]
fn a_stop_request_ends_a_wait_for_a_stopped_backend() {
    let url = common::postgres().fresh("pg_stopped_backend_stop");
    let mut cdb = cdb_with_plan(&url, 2);
    let stop = Arc::new(AtomicBool::new(false));
    cdb.set_interrupt(Arc::clone(&stop));
    let stopped = Stopped::new(cdb.backend_pid().unwrap());
    let setter = {
        let stop = Arc::clone(&stop);
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(500));
            stop.store(true, Ordering::SeqCst);
        })
    };
    let started = Instant::now();
    let e = within(Duration::from_secs(60), move || {
        commit(&mut cdb, 0).unwrap_err()
    });
    setter.join().unwrap();
    let took = started.elapsed();
    assert_eq!(e.kind(), ErrorKind::Interrupted, "{e}");
    assert!(took < Duration::from_secs(4), "{took:?}");
    drop(stopped);
    assert_eq!(stored(&url), expected(2, &[]));
}

/// Settings out of range are refused before connecting, naming the parameter.
#[test]
fn absurd_settings_are_refused_naming_the_parameter() {
    for (query, named) in [
        (
            "spmcal_reconnect_attempts=4294967295",
            "spmcal_reconnect_attempts",
        ),
        ("spmcal_reconnect_attempts=101", "spmcal_reconnect_attempts"),
        ("spmcal_reconnect_backoff_s=5", "spmcal_reconnect_backoff_s"),
        (
            "spmcal_reconnect_backoff_s=NaN",
            "spmcal_reconnect_backoff_s",
        ),
        ("spmcal_reply_timeout_s=0", "spmcal_reply_timeout_s"),
        ("spmcal_reply_timeout_s=1e300", "spmcal_reply_timeout_s"),
        ("spmcal_retries=3", "spmcal_retries"),
    ] {
        let url = format!("postgres://u:hunter2@127.0.0.1:1/db?sslmode=disable&{query}");
        let e = PgCdb::open(&url).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::InvalidInput, "{query}: {e}");
        assert!(e.to_string().contains(named), "{query}: {e}");
        assert!(!e.to_string().contains("hunter2"), "{e}");
    }
    let (client_url, s) = spm_cdb::postgres::split_url(
        "postgres://u@h/db?spmcal_reconnect_attempts=100&sslmode=disable&spmcal_reply_timeout_s=5",
    )
    .unwrap();
    assert_eq!(client_url, "postgres://u@h/db?sslmode=disable");
    assert_eq!(s.reconnect_attempts, 100);
    assert_eq!(s.reply_timeout_s, 5.0);
    assert_eq!(
        s.reconnect_backoff_s,
        spm_cdb::postgres::DEFAULT_RECONNECT_BACKOFF_S
    );
}

/// The watchdog counts the requests awaiting the server by the protocol's framing; a count
/// left over by any kind of exchange (start-up, a write transaction, a COPY, a server-side
/// error, a snapshot, a streamed read) would cut an idle connection. With a reply timeout
/// of 0.5 s, every kind is done and the connection left idle for 1.5 s: it is still the
/// same, and answers.
#[test]
fn an_idle_connection_is_never_cut_whatever_it_did_before() {
    let url = common::postgres().fresh("pg_idle_not_cut");
    let quick = format!("{url}?spmcal_reply_timeout_s=0.5");
    let mut cdb = cdb_with_plan(&quick, 2);
    let idle = |cdb: &PgCdb, what: &str| {
        std::thread::sleep(Duration::from_millis(1500));
        let pid = cdb
            .backend_pid()
            .unwrap_or_else(|e| panic!("after {what}: {e}"));
        assert_eq!(cdb.reconnects(), 0, "after {what}");
        pid
    };
    let pid = idle(&cdb, "opening");
    commit(&mut cdb, 0).unwrap();
    idle(&cdb, "a commit");
    let e = commit(&mut cdb, 0).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Conflict, "{e}");
    idle(&cdb, "a refused commit");
    let r = run("run-1", "S", T0);
    let extra: Vec<_> = plan(2)
        .iter()
        .map(|n| {
            let mut rec = record(&r, n, 7, T0);
            rec.node_index = 3;
            rec
        })
        .take(1)
        .collect();
    assert_eq!(cdb.import_records(&extra).unwrap(), 1);
    idle(&cdb, "a COPY");
    {
        let snapshot = cdb.snapshot().unwrap();
        assert!(snapshot.count_records(&RecordFilter::default()).unwrap() >= 3);
        let report = snapshot.check().unwrap();
        drop(report);
    }
    idle(&cdb, "a snapshot and a check");
    let mut n = 0;
    cdb.for_each_record(&RecordFilter::default(), &mut |_| {
        n += 1;
        Ok(())
    })
    .unwrap();
    assert!(n >= 3);
    assert_eq!(idle(&cdb, "a streamed read"), pid);
}
