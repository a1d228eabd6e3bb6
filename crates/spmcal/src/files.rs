//! Guards on the files the command line reads and writes (issue 13).
//!
//! - Inputs must be regular files, checked *before* opening (a FIFO would block the open,
//!   a device such as `/dev/zero` would be read until memory runs out).
//! - Outputs must be regular files or new, and never the same file as an input, the CDB
//!   (or its `-wal`/`-shm` companions) or the log: compared by location (the resolved
//!   parent plus the name, so also for files that do not exist yet, issue 25) and, for
//!   existing files, by identity (device + inode, so also through hard links).
//! - Standard output that is closed or full ends the program with a typed error (exit 1,
//!   no panic).

use crate::error::CliError;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// The `--log` file, once it is known: every output is checked against it.
static LOG: OnceLock<PathBuf> = OnceLock::new();

/// Remembers the log file so that no output replaces it.
pub fn set_log(path: &Path) {
    let _ = LOG.set(path.to_path_buf());
}

/// The `--log` file, when one was given.
pub fn log_path() -> Option<PathBuf> {
    LOG.get().cloned()
}

/// A file's identity: device and inode (following symbolic links).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FileId {
    dev: u64,
    ino: u64,
}

/// The identity of an existing file, `None` when it does not exist.
pub fn identity(path: &Path) -> Option<FileId> {
    let meta = std::fs::metadata(path).ok()?;
    id_of(&meta)
}

#[cfg(unix)]
fn id_of(meta: &std::fs::Metadata) -> Option<FileId> {
    use std::os::unix::fs::MetadataExt;
    Some(FileId {
        dev: meta.dev(),
        ino: meta.ino(),
    })
}

#[cfg(not(unix))]
fn id_of(_meta: &std::fs::Metadata) -> Option<FileId> {
    None
}

/// What kind of non-regular file `meta` describes, for messages.
fn kind_of(meta: &std::fs::Metadata) -> &'static str {
    let t = meta.file_type();
    if t.is_dir() {
        return "a directory";
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_fifo() {
            return "a FIFO";
        }
        if t.is_char_device() {
            return "a character device";
        }
        if t.is_block_device() {
            return "a block device";
        }
        if t.is_socket() {
            return "a socket";
        }
    }
    "not a regular file"
}

/// Checks that an input exists and is a regular file (without opening it); `what` names
/// its role ("image", "config", "calibration database").
pub fn check_input(path: &Path, what: &str) -> Result<std::fs::Metadata, CliError> {
    let meta = std::fs::metadata(path).map_err(|e| CliError::io(path, e))?;
    if meta.is_file() {
        Ok(meta)
    } else {
        Err(CliError::BadInput(format!(
            "{}: {} is {}, expected a regular file",
            path.display(),
            what,
            kind_of(&meta)
        )))
    }
}

/// Where `path` is, whether or not the file exists: absolute, its longest existing
/// ancestor resolved (symbolic links, `..`) and the rest appended lexically. Two spellings
/// of one place give the same location, so a file that does not exist yet (a new CDB, a
/// report not written yet) is compared by where it will be, not by an identity it does
/// not have.
pub fn location(path: &Path) -> PathBuf {
    let absolute = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    for ancestor in absolute.ancestors() {
        let Ok(resolved) = std::fs::canonicalize(ancestor) else {
            continue;
        };
        let Ok(rest) = absolute.strip_prefix(ancestor) else {
            break;
        };
        let mut out = resolved;
        for component in rest.components() {
            match component {
                std::path::Component::CurDir => {}
                std::path::Component::ParentDir => {
                    out.pop();
                }
                other => out.push(other.as_os_str()),
            }
        }
        return out;
    }
    absolute
}

/// A file an output must never be: its name, its location and, when it exists, its
/// identity.
struct Protected {
    path: PathBuf,
    location: PathBuf,
    id: Option<FileId>,
}

/// The files that an output must never be: `inputs`, their CDB companions (`-wal`,
/// `-shm`, `-journal`, `-identity`) and the log, whether they exist or not.
fn protected(inputs: &[&Path]) -> Vec<Protected> {
    let mut paths: Vec<PathBuf> = Vec::new();
    for p in inputs
        .iter()
        .copied()
        .chain(LOG.get().map(PathBuf::as_path))
    {
        paths.push(p.to_path_buf());
        for suffix in ["-wal", "-shm", "-journal", "-identity"] {
            let mut s = p.as_os_str().to_owned();
            s.push(suffix);
            paths.push(PathBuf::from(s));
        }
    }
    paths
        .into_iter()
        .map(|path| Protected {
            location: location(&path),
            id: identity(&path),
            path,
        })
        .collect()
}

/// Checks that `out` may be written: new, or an existing regular file that is none of
/// `inputs` (nor the CDB's companions, nor the log). `flag` names the option.
pub fn check_output(out: &Path, flag: &str, inputs: &[&Path]) -> Result<(), CliError> {
    let out_location = location(out);
    let clash = |id: Option<FileId>| {
        protected(inputs)
            .into_iter()
            .find(|p| p.location == out_location || (id.is_some() && p.id == id))
    };
    let meta = match std::fs::metadata(out) {
        Ok(meta) => meta,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            // A dangling symbolic link would be followed to create its target: refuse.
            if std::fs::symlink_metadata(out).is_ok() {
                return Err(CliError::BadInput(format!(
                    "{flag} {}: a dangling symbolic link; give a regular file",
                    out.display()
                )));
            }
            if let Some(p) = clash(None) {
                return Err(same_file(flag, out, &p.path));
            }
            return Ok(());
        }
        Err(e) => return Err(CliError::io(out, e)),
    };
    if !meta.is_file() {
        return Err(CliError::BadInput(format!(
            "{flag} {}: is {}; an output must be a regular file or new",
            out.display(),
            kind_of(&meta)
        )));
    }
    if let Some(p) = clash(id_of(&meta)) {
        return Err(same_file(flag, out, &p.path));
    }
    Ok(())
}

fn same_file(flag: &str, out: &Path, other: &Path) -> CliError {
    CliError::BadInput(format!(
        "{flag} {}: is the same file as {}; refusing to overwrite it",
        out.display(),
        other.display()
    ))
}

/// Checks that no two of `outputs` are the same file (by name or identity).
pub fn check_distinct_outputs(outputs: &[(&str, &Path)]) -> Result<(), CliError> {
    for (i, (flag_a, a)) in outputs.iter().enumerate() {
        for (flag_b, b) in outputs.iter().skip(i + 1) {
            let same_id = matches!((identity(a), identity(b)), (Some(x), Some(y)) if x == y);
            if a == b || same_id || location(a) == location(b) {
                return Err(CliError::BadInput(format!(
                    "{flag_a} and {flag_b} name the same file {}",
                    a.display()
                )));
            }
        }
    }
    Ok(())
}

/// A hidden temporary name beside `path`, unique to this process (`.NAME.partial-PID`).
///
/// Every writer asks for it before writing, so it first removes the temporaries of the same
/// target that processes no longer alive left behind (an export or fit killed mid-write
/// left 46–54 MB that nothing removed, issue 25): see [`remove_stale_partials`].
pub fn temporary_beside(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map_or_else(|| "out".into(), |n| n.to_string_lossy().into_owned());
    remove_stale_partials(path, &name);
    path.with_file_name(format!(".{name}.partial-{}", std::process::id()))
}

/// Removes `.NAME.partial-PID` files beside `path` whose process is gone (Linux: no
/// `/proc/PID`; elsewhere nothing is removed). A live writer's partial, another target's and
/// anything that is not a regular file are left alone; best effort.
fn remove_stale_partials(path: &Path, name: &str) {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let prefix = format!(".{name}.partial-");
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let file_name = entry.file_name();
        let Some(pid) = file_name
            .to_str()
            .and_then(|n| n.strip_prefix(&prefix))
            .and_then(|p| p.parse::<u32>().ok())
        else {
            continue;
        };
        if pid == std::process::id()
            || process_alive(pid)
            || !entry.file_type().is_ok_and(|t| t.is_file())
        {
            continue;
        }
        match std::fs::remove_file(entry.path()) {
            Ok(()) => tracing::info!(
                file = %entry.path().display(),
                "removed the temporary file of an interrupted writer (process {pid} is gone)"
            ),
            Err(e) => tracing::debug!(
                file = %entry.path().display(),
                error = %e,
                "cannot remove a stale temporary file"
            ),
        }
    }
}

/// Whether a process with this id exists (Linux: `/proc/PID`; elsewhere assumed alive, so
/// nothing of a live writer is ever removed).
fn process_alive(pid: u32) -> bool {
    let proc_root = Path::new("/proc");
    if proc_root.join("self").exists() {
        proc_root.join(pid.to_string()).exists()
    } else {
        true
    }
}

/// Writes `bytes` to a temporary file beside `path`, then renames it into place: readers
/// never see a half-written file, and a failure leaves no temporary file behind.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), CliError> {
    let partial = temporary_beside(path);
    let result = std::fs::write(&partial, bytes)
        .map_err(|e| CliError::io(path, e))
        .and_then(|()| std::fs::rename(&partial, path).map_err(|e| CliError::io(path, e)));
    if result.is_err() {
        let _ = std::fs::remove_file(&partial);
    }
    result
}

/// Reads a whole input file of at most `limit` bytes (checked to be a regular file first).
pub fn read_limited(path: &Path, what: &str, limit: u64) -> Result<Vec<u8>, CliError> {
    let meta = check_input(path, what)?;
    if meta.len() > limit {
        return Err(CliError::BadInput(format!(
            "{}: {what} of {} bytes is larger than the limit of {limit} bytes",
            path.display(),
            meta.len()
        )));
    }
    let file = std::fs::File::open(path).map_err(|e| CliError::io(path, e))?;
    let mut bytes = Vec::new();
    use std::io::Read;
    file.take(limit + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| CliError::io(path, e))?;
    if bytes.len() as u64 > limit {
        return Err(CliError::BadInput(format!(
            "{}: {what} is larger than the limit of {limit} bytes",
            path.display()
        )));
    }
    Ok(bytes)
}

/// Writes one line to standard output; a closed or full stdout is an error (exit 1), not a
/// panic.
pub fn stdout_line(args: std::fmt::Arguments<'_>) -> Result<(), CliError> {
    let mut out = std::io::stdout().lock();
    out.write_fmt(args)
        .and_then(|()| out.write_all(b"\n"))
        .and_then(|()| out.flush())
        .map_err(CliError::Stdout)
}
