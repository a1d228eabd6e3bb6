//! The integration tests of `spmcal`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spmcal --test it <module>::`.

mod cdb_dynamics;
mod cli;
mod concurrency;
mod crash;
mod faults;
mod hostile;
mod no_panic;
mod postgres_cli;
mod surfaces;
mod vertical_cli;
mod virtual_mode;
