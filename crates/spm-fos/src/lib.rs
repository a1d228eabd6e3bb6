//! Feature-oriented scanning operations over any Microscope: attach, aperture, skip, counter-scan, drift monitor.
//!
//! Placeholder: this crate is filled in by its issue (see docs/ARCHITECTURE.md).
