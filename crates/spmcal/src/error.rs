//! The CLI's error type and its mapping to exit codes (DESIGN §13).

use std::path::PathBuf;

/// Exit code: success.
pub const EXIT_SUCCESS: i32 = 0;
/// Exit code: a run failed (instrument, numerical).
pub const EXIT_RUN_FAILED: i32 = 1;
/// Exit code: bad usage or bad input.
pub const EXIT_BAD_INPUT: i32 = 2;
/// Exit code: `calibrate` ran and wrote its report, but missed a target its plan declares
/// (`[plan.targets]`, issue 27; not 1, which says the run itself failed, nor 2, bad input).
pub const EXIT_TARGET_MISSED: i32 = 3;

/// Everything a subcommand can fail with.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// An input file, config or argument is wrong; the message names it.
    #[error("{0}")]
    BadInput(String),
    /// The run itself failed (instrument fault, numerical failure).
    #[error("{0}")]
    RunFailed(String),
    /// The run finished and its report is written, but it missed a declared target.
    #[error("{0}")]
    TargetMissed(String),
    /// Standard output is closed or full (exit 1, no message when the reader went away).
    #[error("cannot write to standard output: {0}")]
    Stdout(std::io::Error),
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
}

impl CliError {
    /// The process exit code for this error.
    pub fn exit_code(&self) -> i32 {
        match self {
            Self::BadInput(_) => EXIT_BAD_INPUT,
            Self::TargetMissed(_) => EXIT_TARGET_MISSED,
            Self::RunFailed(_) | Self::Stdout(_) => EXIT_RUN_FAILED,
            Self::Io { source, .. } => match source.kind() {
                std::io::ErrorKind::NotFound
                | std::io::ErrorKind::IsADirectory
                | std::io::ErrorKind::NotADirectory
                | std::io::ErrorKind::PermissionDenied
                | std::io::ErrorKind::InvalidData
                | std::io::ErrorKind::InvalidInput => EXIT_BAD_INPUT,
                _ => EXIT_RUN_FAILED,
            },
        }
    }

    /// True when the error is a closed standard output (the reader went away): the
    /// program ends quietly.
    pub fn is_closed_stdout(&self) -> bool {
        matches!(self, Self::Stdout(e) if e.kind() == std::io::ErrorKind::BrokenPipe)
    }

    /// An I/O error on `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io {
            path: path.into(),
            source,
        }
    }
}
