//! The integration tests of `spm-fos`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spm-fos --test it <module>::`.

mod mock;
mod sim;
