//! The integration tests of `spm-sim`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spm-sim --test it <module>::`.

mod backward_aside;
mod config;
mod drift_and_determinism;
mod extended_physics;
mod faults;
mod lattice;
mod scanner;
mod sine_drive;
mod turned;
