//! The integration tests of `spm-cdb`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spm-cdb --test it <module>::`.

// The CDB suite runs on both back ends: it needs the `postgres` feature, which
// `cargo test --workspace` enables (spmcal does); alone: `cargo test -p spm-cdb --features postgres`.
#[cfg(feature = "postgres")]
mod common;

#[cfg(feature = "postgres")]
mod cdb;
mod mmap;
#[cfg(feature = "postgres")]
mod pg_reconnect;
