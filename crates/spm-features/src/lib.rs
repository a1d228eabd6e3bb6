//! Feature detection, sub-pixel localisation, lattice vectors and LCS recognition (pure, no IO).
//!
//! Placeholder: this crate is filled in by its issue (see docs/ARCHITECTURE.md).
