#![doc = include_str!("../README.md")]
//!
//! # spm-nanonis-sim: the Nanonis TCP protocol over the simulated microscope
//!
//! A TCP server that answers the commands [`spm_nanonis`] uses, byte for byte as the
//! manual describes them, by driving an [`spm_sim::Simulator`]: a user can run the whole
//! pipeline over a socket without hardware (`spmcal nanonis-sim`), and the backend is
//! tested against it.
//!
//! - **One thread per connection**; the simulated instrument is shared (a mutex), and the
//!   commands of one connection are executed in order, as on the controller.
//! - **Strict.** Headers must be exact (NUL padding, flags, unused bytes 0); bodies must be
//!   exactly the command's arguments under the server's release ([`ServerConfig::host_release`]
//!   decides the form of `Scan.PropsSet`); flags must be documented values. A malformed
//!   header closes the connection (its framing is lost); a malformed body, an unknown
//!   command or a setting the simulator does not model gets an error reply.
//! - **Like a controller left as a user had it**: drift, tilt and hysteresis compensation
//!   start on, continuous and bouncy scanning start on, and scans and moves are refused
//!   until they are off (the simulator does not model the controller's corrections, so
//!   it refuses to pretend); pixels per line are coerced to the closest multiple of 16.
//! - **Time** is the simulator's: published as two signals (whole seconds and fraction,
//!   [`ServerConfig::time_whole_signal`], [`ServerConfig::time_fraction_signal`]);
//!   `Scan.WaitEndOfScan` with no scan running waits its timeout in simulated time.
//! - **One simulator call per instrument operation**, so a run over TCP costs the same
//!   simulated time and random draws as in-process: a Follow-Me move is executed together
//!   with the settle wait that follows it (`FolMe.XYPosSet` then `Scan.WaitEndOfScan`),
//!   and a scan when its data are first needed (the first `Scan.FrameDataGrab` says
//!   whether the backward trace is wanted). Every command that observes the instrument
//!   first completes what is pending, so nothing of this is visible to a client except
//!   that errors of a scan are reported by the data grab.
//! - **Socket-level fault injection** ([`SocketFaults`], seeded): error replies, replies
//!   written one byte at a time, delays, stalls longer than the client's timeout,
//!   connections dropped before or after executing a command, and a scan left running.

pub mod server;

pub use server::{Server, ServerConfig, ServerError, ServerHandle, ServerStats, SocketFaults};
