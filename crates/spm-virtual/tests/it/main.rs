//! The integration tests of `spm-virtual`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spm-virtual --test it <module>::`.

mod microscope;
