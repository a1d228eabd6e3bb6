//! Physics-based simulated scanning probe microscope implementing spm-hal's Microscope, with a ground-truth oracle.
//!
//! Placeholder: this crate is filled in by its issue (see docs/ARCHITECTURE.md).
