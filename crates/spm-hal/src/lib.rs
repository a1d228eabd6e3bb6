//! # spm-hal: the API boundary of spmcal
//!
//! Units ([`Counts`], [`Nanometres`], [`Seconds`], [`Radians`]), scan requests and
//! frames ([`ScanRequest`], [`Frame`], [`HeightMap`]), and the [`Microscope`]
//! trait through which every algorithm talks to an instrument, real or
//! simulated. This crate knows nothing of any backend: a real controller
//! implements [`Microscope`] with only this crate as a dependency.
//!
//! Errors follow embedded-hal: each backend has its own error type that reports
//! a shared, non-exhaustive [`ErrorKind`]. Optional hardware (the coarse Z
//! stage) is found by [`Microscope::coarse_z`] and [`Capabilities`], not by
//! "unsupported" errors. [`mock::ScriptedMicroscope`] is an expectation-queue
//! backend with fault injection for tests of generic code.
#![doc = include_str!("../README.md")]
#![warn(missing_docs)]

pub mod interrupt;
pub mod microscope;
pub mod mock;
pub mod recording;
pub mod scan;
#[cfg(feature = "truth")]
pub mod truth;
pub mod units;

pub use microscope::{
    Capabilities, CoarseZCapability, CoarseZStage, Error, ErrorKind, Microscope, MoveRequest,
};
pub use scan::{
    Frame, FrameError, HeightMap, ScanDirection, ScanRequest, ScanRequestError, TraceHalf,
    TraceImage,
};
pub use units::{
    CountPoint, CountVector, CountVelocity, Counts, CountsPerSecond, Nanometres, NmPerCount,
    NmPerCountMatrix, NmPoint, NmVelocity, Radians, Seconds,
};
