//! The integration tests of `spm-formats`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spm-formats --test it <module>::`.

mod common;

mod errors;
mod gsf;
mod gwy;
mod measured;
mod mutation;
mod orientation;
