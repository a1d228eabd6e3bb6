//! The integration tests of `spm-plot`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spm-plot --test it <module>::`.

mod figures;
mod render;
