//! Trajectory and raster correction of SPM images, eqs. (5)-(12), resampling.
//!
//! Placeholder: this crate is filled in by its issue (see docs/ARCHITECTURE.md).
