//! The integration tests of `spm-modelcheck`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spm-modelcheck --test it <module>::`.

mod common;

mod cells;
mod image;
mod measured;
mod orientation;
mod rules;
mod sim;
mod sine;
mod synthetic;
mod vibration;
