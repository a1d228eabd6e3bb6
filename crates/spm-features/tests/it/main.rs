//! The integration tests of `spm-features`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spm-features --test it <module>::`.

mod common;

mod recognition;
mod sim_oracle;
mod step_sim;
mod synthetic;
