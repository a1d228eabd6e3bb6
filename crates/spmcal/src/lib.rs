//! The library half of the `spmcal` program: the glue between the crates that
//! the command line, `cargo xtask` and the end-to-end tests share.
//!
//! - [`surfaces`]: CDB records → regression surfaces per Z plane (`surfaces.json`).
//! - [`accuracy`]: calibration accuracy against the simulator's oracle (DESIGN §11).
//!
//! The binary (`src/main.rs`) parses arguments, installs the tracing
//! subscriber and maps errors to exit codes; everything here returns typed
//! errors and prints nothing.

pub mod accuracy;
pub mod surfaces;
