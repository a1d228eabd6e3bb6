//! Simulation versus measurement: baseline fit, residual diagnosis, effect library, model extension.
//!
//! Placeholder: this crate is filled in by its issue (see docs/ARCHITECTURE.md).
