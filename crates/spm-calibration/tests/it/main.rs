//! The integration tests of `spm-calibration`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spm-calibration --test it <module>::`.

mod end_to_end;
mod lcc;
mod machine;
mod mock;
mod plan;
mod survey;
mod vertical;
