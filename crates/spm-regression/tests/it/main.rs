//! The integration tests of `spm-regression`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spm-regression --test it <module>::`.

mod properties;
mod regression;
