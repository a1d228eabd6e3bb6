//! The integration tests of `spm-nanonis-sim`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spm-nanonis-sim --test it <module>::`.

mod backend_angles;
mod backend_directions;
mod backend_interrupt;
mod common;
mod issue26;
mod limits;
mod over_tcp;
mod vendor_frames;
