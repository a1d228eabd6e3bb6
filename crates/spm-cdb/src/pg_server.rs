//! A private PostgreSQL server for tests and benchmarks (feature `postgres`): `initdb` into a
//! temporary directory, a free local port, the Unix socket in that directory, stopped and
//! removed at the end.
//!
//! The server binaries come from the distribution's package (`apt-get install postgresql`:
//! `/usr/lib/postgresql/<major>/bin`), or from the directory in `SPMCAL_PG_BIN`. PostgreSQL
//! refuses to run as root: as root, the server runs as the `postgres` system user (through
//! `setpriv`) and the directory is given to that user.
//!
//! Cleanup does not depend on the test process ending well: [`TestServer::start`] also
//! starts a watchdog that stops the server and removes its directory as soon as the starting
//! process is gone (after a panic, an abort or SIGKILL), so a server kept in a `static` for a
//! whole test binary is cleaned up too. Dropping the [`TestServer`] stops it at once.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Why a private server could not be started.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ServerError {
    /// The PostgreSQL server programs are not installed.
    #[error(
        "PostgreSQL server programs not found ({looked}); install them with \
         `apt-get install -y postgresql` or point SPMCAL_PG_BIN at the directory holding \
         initdb, postgres and pg_ctl"
    )]
    NotInstalled {
        /// Where they were looked for.
        looked: String,
    },
    /// Running as root, but there is no `postgres` user (or no `setpriv`) to run the server as.
    #[error(
        "running as root: PostgreSQL refuses to run as root and {0}; install the `postgresql` \
         package (it creates the postgres user) and util-linux (setpriv)"
    )]
    NoServerUser(String),
    /// A program failed.
    #[error("{program}: {detail}")]
    Failed {
        /// Program.
        program: String,
        /// Exit status and output.
        detail: String,
    },
    /// I/O on the temporary directory.
    #[error("{path}: {source}")]
    Io {
        /// Path.
        path: PathBuf,
        /// Error.
        source: std::io::Error,
    },
}

/// A running private PostgreSQL server; stopped and its directory removed when dropped.
#[derive(Debug)]
pub struct TestServer {
    dir: PathBuf,
    port: u16,
    bin: PathBuf,
    run_as: Option<(u32, u32)>,
    durable: bool,
    postmaster: Child,
    watchdog: Option<Child>,
}

/// The directory of the server programs: `SPMCAL_PG_BIN`, else the newest
/// `/usr/lib/postgresql/<major>/bin` holding `initdb`.
fn find_bin() -> Result<PathBuf, ServerError> {
    if let Some(dir) = std::env::var_os("SPMCAL_PG_BIN") {
        let dir = PathBuf::from(dir);
        if dir.join("initdb").is_file() {
            return Ok(dir);
        }
        return Err(ServerError::NotInstalled {
            looked: format!("SPMCAL_PG_BIN={} has no initdb", dir.display()),
        });
    }
    let root = Path::new("/usr/lib/postgresql");
    let mut found: Vec<(u32, PathBuf)> = std::fs::read_dir(root)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let major = e.file_name().to_string_lossy().parse::<u32>().ok()?;
            let bin = e.path().join("bin");
            bin.join("initdb").is_file().then_some((major, bin))
        })
        .collect();
    found.sort();
    found
        .pop()
        .map(|(_, bin)| bin)
        .ok_or_else(|| ServerError::NotInstalled {
            looked: "no /usr/lib/postgresql/*/bin/initdb, SPMCAL_PG_BIN not set".into(),
        })
}

/// Whether this process runs as root (uid 0), from `/proc/self/status`.
fn is_root() -> bool {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("Uid:"))
                .and_then(|l| l.split_whitespace().nth(1).map(|u| u == "0"))
        })
        .unwrap_or(false)
}

/// Uid and gid of the `postgres` user, from `/etc/passwd`.
fn postgres_user() -> Option<(u32, u32)> {
    let passwd = std::fs::read_to_string("/etc/passwd").ok()?;
    passwd.lines().find_map(|l| {
        let f: Vec<&str> = l.split(':').collect();
        (f.first() == Some(&"postgres"))
            .then(|| Some((f.get(2)?.parse().ok()?, f.get(3)?.parse().ok()?)))
            .flatten()
    })
}

/// A free local TCP port (bound and released; the server binds it right after).
fn free_port(dir: &Path) -> Result<u16, ServerError> {
    let listener =
        std::net::TcpListener::bind("127.0.0.1:0").map_err(|source| ServerError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
    listener
        .local_addr()
        .map(|a| a.port())
        .map_err(|source| ServerError::Io {
            path: dir.to_path_buf(),
            source,
        })
}

/// A server program `path`, run as the account `run_as` (uid, gid) when given (`setpriv`:
/// PostgreSQL refuses to run as root).
fn server_program(path: &Path, run_as: Option<(u32, u32)>) -> Command {
    match run_as {
        Some((uid, gid)) => {
            let mut c = Command::new("setpriv");
            c.args([
                format!("--reuid={uid}"),
                format!("--regid={gid}"),
                "--clear-groups".into(),
                "--".into(),
            ])
            .arg(path);
            c
        }
        None => Command::new(path),
    }
}

/// Starts the postmaster on `port` with the test settings, its output in `server.log`.
fn spawn_postmaster(
    dir: &Path,
    bin: &Path,
    run_as: Option<(u32, u32)>,
    port: u16,
    durable: bool,
) -> Result<Child, ServerError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| ServerError::Io { path, source }
    };
    let data = dir.join("data");
    let path = bin.join("postgres");
    let mut c = server_program(&path, run_as);
    c.arg("-D")
        .arg(&data)
        .args(["-p", &port.to_string(), "-h", "127.0.0.1", "-k"])
        .arg(dir)
        .args(["-c", "max_connections=60", "-c", "shared_buffers=64MB"]);
    if !durable {
        c.args([
            "-c",
            "fsync=off",
            "-c",
            "synchronous_commit=off",
            "-c",
            "full_page_writes=off",
        ]);
    }
    let log_path = dir.join("server.log");
    let log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log_path)
        .map_err(io(dir))?;
    if let Some((uid, gid)) = run_as {
        std::os::unix::fs::chown(&log_path, Some(uid), Some(gid)).map_err(io(dir))?;
    }
    let log_err = log.try_clone().map_err(io(dir))?;
    c.stdin(Stdio::null())
        .stdout(log)
        .stderr(log_err)
        .spawn()
        .map_err(io(&path))
}

impl TestServer {
    /// Starts a server with settings for tests (no fsync: a test's data need not survive a
    /// power cut; commits, isolation and locking are unchanged).
    ///
    /// # Errors
    /// [`ServerError::NotInstalled`] naming what is missing; failures of initdb or the server.
    pub fn start() -> Result<Self, ServerError> {
        Self::start_with(false)
    }

    /// Starts a server; `durable` keeps PostgreSQL's default fsync-at-commit (benchmarks that
    /// compare with SQLite's `synchronous = FULL`).
    ///
    /// # Errors
    /// As [`TestServer::start`].
    pub fn start_with(durable: bool) -> Result<Self, ServerError> {
        let bin = find_bin()?;
        let run_as = if is_root() {
            let user = postgres_user()
                .ok_or_else(|| ServerError::NoServerUser("there is no postgres user".into()))?;
            if Command::new("setpriv")
                .arg("--version")
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .status()
                .is_err()
            {
                return Err(ServerError::NoServerUser("setpriv is missing".into()));
            }
            Some(user)
        } else {
            None
        };
        let dir = std::env::temp_dir().join(format!(
            "spmcal-pg-{}-{}",
            std::process::id(),
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos())
        ));
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| ServerError::Io { path, source }
        };
        std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        if let Some((uid, gid)) = run_as {
            std::os::unix::fs::chown(&dir, Some(uid), Some(gid)).map_err(io(&dir))?;
        }
        let data = dir.join("data");
        let command = |program: &str| server_program(&bin.join(program), run_as);
        // `--no-sync`: initdb's flush of the files it created (1.7 of its 2.3 s here) buys a
        // throw-away cluster nothing; `durable` concerns the commits, which keep their fsync.
        let output = command("initdb")
            .args([
                "--no-sync",
                "-A",
                "trust",
                "-U",
                "postgres",
                "-E",
                "UTF8",
                "--no-locale",
                "-D",
            ])
            .arg(&data)
            .stdin(Stdio::null())
            .output()
            .map_err(io(&bin.join("initdb")))?;
        if !output.status.success() {
            let _ = std::fs::remove_dir_all(&dir);
            return Err(ServerError::Failed {
                program: "initdb".into(),
                detail: format!(
                    "{}: {}",
                    output.status,
                    String::from_utf8_lossy(&output.stderr)
                ),
            });
        }
        let mut last_error = String::new();
        for _attempt in 0..5 {
            let port = free_port(&dir)?;
            let postmaster = spawn_postmaster(&dir, &bin, run_as, port, durable)?;
            let mut server = Self {
                dir: dir.clone(),
                port,
                bin: bin.clone(),
                run_as,
                durable,
                postmaster,
                watchdog: None,
            };
            match server.wait_ready(Duration::from_secs(60)) {
                Ok(()) => {
                    server.watchdog = server.spawn_watchdog();
                    return Ok(server);
                }
                Err(e) => {
                    last_error = e;
                    server.stop_server();
                    // Keep the directory for the next attempt; dropping would remove it.
                    std::mem::forget(server);
                }
            }
        }
        let _ = std::fs::remove_dir_all(&dir);
        Err(ServerError::Failed {
            program: "postgres".into(),
            detail: last_error,
        })
    }

    /// Stops the server (a fast shutdown: every session is ended with SQLSTATE 57P01) and
    /// starts it again on the same port and data directory, as an administrator's restart
    /// does. Returns when it accepts connections again.
    ///
    /// # Errors
    /// As [`TestServer::start`].
    pub fn restart(&mut self) -> Result<(), ServerError> {
        self.stop_server();
        if let Some(mut w) = self.watchdog.take() {
            let _ = w.kill();
            let _ = w.wait();
        }
        self.postmaster =
            spawn_postmaster(&self.dir, &self.bin, self.run_as, self.port, self.durable)?;
        self.wait_ready(Duration::from_secs(60))
            .map_err(|detail| ServerError::Failed {
                program: "postgres (restart)".into(),
                detail,
            })?;
        self.watchdog = self.spawn_watchdog();
        Ok(())
    }

    /// Stops the server without starting it again (tests of a server gone for good); dropping
    /// the value still removes the directory.
    pub fn stop(&mut self) {
        self.stop_server();
    }

    fn wait_ready(&mut self, limit: Duration) -> Result<(), String> {
        let started = Instant::now();
        loop {
            if let Ok(Some(status)) = self.postmaster.try_wait() {
                return Err(format!(
                    "exited with {status}: {}",
                    std::fs::read_to_string(self.dir.join("server.log")).unwrap_or_default()
                ));
            }
            let ok = postgres::Client::connect(&self.url("postgres"), postgres::NoTls).is_ok();
            if ok {
                return Ok(());
            }
            if started.elapsed() > limit {
                return Err(format!(
                    "not ready after {limit:?}: {}",
                    std::fs::read_to_string(self.dir.join("server.log")).unwrap_or_default()
                ));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// A detached shell that waits for this process to end, then stops the server (SIGINT to
    /// the postmaster: fast shutdown) and removes the directory.
    fn spawn_watchdog(&self) -> Option<Child> {
        let script = "while kill -0 \"$1\" 2>/dev/null; do sleep 0.5; done; \
                      kill -INT \"$2\" 2>/dev/null; \
                      i=0; while kill -0 \"$2\" 2>/dev/null && [ $i -lt 100 ]; do \
                      sleep 0.1; i=$((i+1)); done; \
                      kill -KILL \"$2\" 2>/dev/null; rm -rf \"$3\"";
        Command::new("setsid")
            .args(["sh", "-c", script, "spmcal-pg-watchdog"])
            .arg(std::process::id().to_string())
            .arg(self.postmaster.id().to_string())
            .arg(&self.dir)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .ok()
    }

    /// The TCP port the server listens on (127.0.0.1).
    #[must_use]
    pub fn port(&self) -> u16 {
        self.port
    }

    /// `postgres://postgres@127.0.0.1:PORT/DB`.
    #[must_use]
    pub fn url(&self, database: &str) -> String {
        format!("postgres://postgres@127.0.0.1:{}/{database}", self.port)
    }

    /// Creates an empty database (dropping one of that name first) and returns its URL.
    ///
    /// # Errors
    /// [`ServerError::Failed`] with the server's message.
    pub fn create_database(&self, name: &str) -> Result<String, ServerError> {
        let failed = |e: postgres::Error| ServerError::Failed {
            program: format!("CREATE DATABASE {name}"),
            detail: e.to_string(),
        };
        let mut admin =
            postgres::Client::connect(&self.url("postgres"), postgres::NoTls).map_err(failed)?;
        let quoted = format!("\"{}\"", name.replace('"', "\"\""));
        admin
            .batch_execute(&format!("DROP DATABASE IF EXISTS {quoted} WITH (FORCE)"))
            .map_err(failed)?;
        admin
            .batch_execute(&format!("CREATE DATABASE {quoted}"))
            .map_err(failed)?;
        Ok(self.url(name))
    }

    /// The server's directory (data, socket, log).
    #[must_use]
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn stop_server(&mut self) {
        let data = self.dir.join("data");
        let mut c = server_program(&self.bin.join("pg_ctl"), self.run_as);
        let stopped = c
            .args(["stop", "-m", "fast", "-w", "-t", "30", "-D"])
            .arg(&data)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        if !stopped {
            let _ = self.postmaster.kill();
        }
        let _ = self.postmaster.wait();
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        self.stop_server();
        if let Some(mut w) = self.watchdog.take() {
            let _ = w.kill();
            let _ = w.wait();
        }
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}
