//! The library half of the `spmcal` program: the glue between the crates that
//! the command line, `cargo xtask` and the end-to-end tests share.
//!
//! - [`cdb_handle`]: the CDB a command names, an SQLite file or a PostgreSQL URL.
//! - [`surfaces`]: CDB records → regression surfaces per Z plane (`surfaces.json`).
//! - [`job`]: the job file (`[backend]` + `[plan]`).
//! - [`run`]: running a job on its backend into the CDB, recording drift and nodes.
//! - [`progress`]: the terminal progress bar of a run.
//! - [`plots`]: PNG figures of a run (drawn with `spm-plot`).
//! - [`report`]: after a run: surfaces.json, accuracy, report.json, figures, report.html.
//! - [`regenerate`]: the report of a finished run, regenerated from the CDB (`spmcal report`).
//! - [`html`]: the self-contained `report.html` (also used by `cargo xtask bench`).
//! - [`simulate`]: a measured file's scan program on the simulated microscope (`spmcal simulate`).
//!
//! The binary (`src/main.rs`) parses arguments, installs the tracing
//! subscriber and maps errors to exit codes; everything here returns typed
//! errors and prints nothing.
#![doc = include_str!("../README.md")]

pub mod cdb_handle;
pub mod dynamics;
pub mod html;
pub mod job;
pub mod plots;
pub mod progress;
pub mod regenerate;
pub mod report;
pub mod run;
#[cfg(feature = "sim")]
pub mod simulate;
pub mod surfaces;
pub mod targets;
pub mod virtual_mode;
