//! LCC solving, net plans and the adaptive distributed-calibration state machine.
//!
//! Placeholder: this crate is filled in by its issue (see docs/ARCHITECTURE.md).
