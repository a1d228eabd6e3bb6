//! The integration tests of `spm-evaluation`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test --workspace --test it <module>::`.

mod competitors;
mod pair_match;
