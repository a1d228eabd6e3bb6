//! What the program writes for a person and what it keeps in its log (issue 27).
//!
//! - The **log** holds every event at `info` and above (`SPMCAL_LOG` overrides the filter):
//!   in `--log FILE`, or for `calibrate` in `OUT/calibrate.log`, which is opened only once the
//!   run's output folder exists (a refused command writes nothing); events before that are
//!   kept in memory and written first.
//! - The **console** (stderr) shows errors only when a log is kept, warnings too otherwise,
//!   with colour codes only on a terminal.
//! - Every warning is **counted by its message** ("transient failure", "feature lost", …), so
//!   that a run's summary gives one line per kind instead of one line per event.

use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::Path;
use std::sync::{Mutex, OnceLock};
use tracing::Level;
use tracing::field::{Field, Visit};
use tracing_subscriber::EnvFilter;
use tracing_subscriber::Layer as _;
use tracing_subscriber::layer::SubscriberExt as _;
use tracing_subscriber::util::SubscriberInitExt as _;

/// Largest log kept in memory before the log file is attached, bytes (beyond it the oldest
/// part is not kept, and the file says so).
const MAX_PENDING_BYTES: usize = 8 << 20;

/// The log's destination: lines in memory until a file is attached.
#[derive(Default)]
struct Sink {
    pending: Vec<u8>,
    dropped: bool,
    file: Option<std::fs::File>,
}

fn sink() -> &'static Mutex<Sink> {
    static SINK: OnceLock<Mutex<Sink>> = OnceLock::new();
    SINK.get_or_init(|| Mutex::new(Sink::default()))
}

fn counts() -> &'static Mutex<BTreeMap<String, usize>> {
    static COUNTS: OnceLock<Mutex<BTreeMap<String, usize>>> = OnceLock::new();
    COUNTS.get_or_init(|| Mutex::new(BTreeMap::new()))
}

/// A writer into the [`Sink`].
struct SinkWriter;

impl std::io::Write for SinkWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let Ok(mut sink) = sink().lock() else {
            return Ok(buf.len());
        };
        match sink.file.as_mut() {
            Some(file) => file.write_all(buf)?,
            None => {
                if sink.pending.len() + buf.len() > MAX_PENDING_BYTES {
                    sink.dropped = true;
                } else {
                    sink.pending.extend_from_slice(buf);
                }
            }
        }
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        match sink().lock() {
            Ok(mut sink) => sink.file.as_mut().map_or(Ok(()), std::io::Write::flush),
            Err(_) => Ok(()),
        }
    }
}

/// Counts warnings by their message.
struct WarningCounter;

struct MessageOf(Option<String>);

impl Visit for MessageOf {
    fn record_str(&mut self, field: &Field, value: &str) {
        if field.name() == "message" {
            self.0 = Some(value.to_owned());
        }
    }

    fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
        if field.name() == "message" {
            self.0 = Some(format!("{value:?}"));
        }
    }
}

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for WarningCounter {
    fn on_event(
        &self,
        event: &tracing::Event<'_>,
        _ctx: tracing_subscriber::layer::Context<'_, S>,
    ) {
        if *event.metadata().level() != Level::WARN {
            return;
        }
        let mut message = MessageOf(None);
        event.record(&mut message);
        let key = message
            .0
            .unwrap_or_else(|| event.metadata().target().to_owned());
        if let Ok(mut counts) = counts().lock() {
            *counts.entry(key).or_insert(0) += 1;
        }
    }
}

/// Where the log goes.
pub enum LogTo<'a> {
    /// A file the user named (`--log`), appended to.
    File(&'a Path),
    /// A file attached later ([`attach_log`]): `calibrate`'s `OUT/calibrate.log`.
    Deferred,
    /// No log: warnings to the console.
    Console,
}

/// Installs the subscriber: log, console and the warning counter.
pub fn install(log: LogTo<'_>) {
    use std::io::IsTerminal as _;
    let ansi = std::io::stderr().is_terminal();
    let file_filter =
        || EnvFilter::try_from_env("SPMCAL_LOG").unwrap_or_else(|_| EnvFilter::new("info"));
    let file_layer = match log {
        LogTo::File(path) => match std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
        {
            Ok(file) => {
                if let Ok(mut sink) = sink().lock() {
                    sink.file = Some(file);
                }
                true
            }
            Err(error) => {
                let _ = writeln!(
                    std::io::stderr(),
                    "spmcal: warning: cannot open the log file {}: {error}; logging to stderr",
                    path.display()
                );
                false
            }
        },
        LogTo::Deferred => true,
        LogTo::Console => false,
    };
    if file_layer {
        let _ = tracing_subscriber::registry()
            .with(
                tracing_subscriber::fmt::layer()
                    .with_ansi(false)
                    .with_writer(|| SinkWriter)
                    .with_filter(file_filter()),
            )
            .with(console_layer(ansi, "error"))
            .with(WarningCounter.with_filter(EnvFilter::new("warn")))
            .try_init();
    } else {
        let _ = tracing_subscriber::registry()
            .with(console_layer(ansi, "warn"))
            .with(WarningCounter.with_filter(EnvFilter::new("warn")))
            .try_init();
    }
}

/// The console's layer: events at `level` and above on stderr, without module paths.
fn console_layer<S>(ansi: bool, level: &str) -> impl tracing_subscriber::Layer<S>
where
    S: tracing::Subscriber + for<'a> tracing_subscriber::registry::LookupSpan<'a>,
{
    tracing_subscriber::fmt::layer()
        .with_ansi(ansi)
        .with_target(false)
        .with_writer(std::io::stderr)
        .with_filter(EnvFilter::new(level))
}

/// Attaches the deferred log to `path` (created or appended to) and writes what was kept in
/// memory so far. A log already going to a file (`--log`) is left where it is.
///
/// # Errors
/// The file cannot be opened or written.
pub fn attach_log(path: &Path) -> std::io::Result<()> {
    let Ok(mut sink) = sink().lock() else {
        return Ok(());
    };
    if sink.file.is_some() {
        return Ok(());
    }
    let mut file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)?;
    if sink.dropped {
        writeln!(
            file,
            "(the start of this log was not kept: more than {MAX_PENDING_BYTES} bytes before the \
             output folder existed)"
        )?;
    }
    file.write_all(&sink.pending)?;
    sink.pending = Vec::new();
    sink.file = Some(file);
    Ok(())
}

/// The warnings so far, one `(message, count)` per kind, most frequent first.
pub fn warning_counts() -> Vec<(String, usize)> {
    let mut v: Vec<(String, usize)> = counts()
        .lock()
        .map(|c| c.iter().map(|(k, n)| (k.clone(), *n)).collect())
        .unwrap_or_default();
    v.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warnings_are_counted_by_message() {
        let subscriber = tracing_subscriber::registry().with(WarningCounter);
        tracing::subscriber::with_default(subscriber, || {
            for t in 0..3 {
                tracing::warn!(t, "transient failure");
            }
            tracing::warn!(x = 1.5, "feature lost");
            tracing::info!("not a warning");
        });
        let counts = warning_counts();
        assert!(
            counts.contains(&("transient failure".to_owned(), 3)),
            "{counts:?}"
        );
        assert!(
            counts.contains(&("feature lost".to_owned(), 1)),
            "{counts:?}"
        );
        assert!(!counts.iter().any(|(k, _)| k == "not a warning"));
    }
}
