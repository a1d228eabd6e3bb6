//! The integration tests of `spm-apply`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spm-apply --test it <module>::`.

mod crop;
mod real_files;
