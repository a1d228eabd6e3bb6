//! # spm-fos: feature-oriented scanning operations over any [`Microscope`](spm_hal::Microscope)
//!
//! The measurement operations of Lapshin's distributed calibration (paper §2):
//! - [`attach`]: capture the feature nearest a point with a first, larger
//!   raster, then hold it with segment attachments, estimating the drift
//!   velocity from successive positions and times until it is below a limit
//!   ([`AttachOutcome`]);
//! - [`aperture`]: scan around the captured feature A and recognise the LCS;
//! - [`skip`]: A → B → A cycles; forward and backward differences, their
//!   (time-weighted) half-sum cancels constant drift; watched by the
//!   [`DriftMonitor`] of §2.6, a pure state machine deciding keep / discard /
//!   idle / resume / restart / give up;
//! - [`counter_scan`]: direct and counter frames; common features give the
//!   drift velocity and drift-free positions (Lapshin 2007).
//!
//! Everything is generic over the backend; nothing here knows whether it
//! drives a simulator or an instrument. Velocities are the apparent motion
//! of the surface in scanner counts per second.
#![doc = include_str!("../README.md")]
#![warn(missing_docs)]

mod acquire;
mod aperture;
mod attach;
mod counter;
mod error;
pub mod monitor;
mod skip;
mod velocity;

pub use acquire::{Motion, Raster, Recognised, Sighting, scan_and_recognise, track};
pub use aperture::{ApertureParams, ApertureReport, aperture};
pub use attach::{AttachOutcome, AttachParams, AttachReport, attach, predict};
pub use counter::{
    CommonFeature, CounterScanParams, CounterScanReport, counter_scan, solve_counter_scan,
};
pub use error::FosError;
pub use monitor::{CycleKind, Decision, DriftMonitor, MonitorParams, SpoilReason};
pub use skip::{
    JudgedCycle, SkipCycle, SkipOutcome, SkipParams, SkipReport, SkipState, skip, skip_cycle,
};
pub use velocity::fit_velocity;
