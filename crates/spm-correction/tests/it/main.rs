//! The integration tests of `spm-correction`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spm-correction --test it <module>::`.

mod api;
mod fit;
mod properties;
