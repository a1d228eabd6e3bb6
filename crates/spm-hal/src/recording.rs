//! A backend wrapper that keeps the lateral command history: every move, wait and scan with
//! its instrument times. The creep and hysteresis of a piezo scanner depend on the whole
//! history of the commands, so a model of them (spm-correction's `dynamics`) replays this log.
//! Backend-agnostic: it only calls the wrapped [`Microscope`].

use crate::microscope::{Capabilities, CoarseZStage, Microscope, MoveRequest};
use crate::scan::{Frame, ScanRequest};
use crate::units::{CountPoint, Counts, Seconds};
use serde::{Deserialize, Serialize};

/// One lateral command and the instrument times around it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub enum CommandEvent {
    /// A move with feedback on.
    Move {
        /// Instrument time before the call, s.
        start_s: f64,
        /// Instrument time after it, s.
        end_s: f64,
        /// Commanded position before, counts.
        from: CountPoint,
        /// The request.
        request: MoveRequest,
    },
    /// A pause with the command held.
    Wait {
        /// Instrument time before, s.
        start_s: f64,
        /// Instrument time after, s.
        end_s: f64,
    },
    /// A raster scan (travel to its first pixel at the scan speed, then every line as trace
    /// and retrace at the pixel dwell, DESIGN §3).
    Scan {
        /// Instrument time before, s.
        start_s: f64,
        /// Instrument time after, s.
        end_s: f64,
        /// Commanded position before, counts.
        from: CountPoint,
        /// The request.
        request: ScanRequest,
        /// The lines were acquired last line first (the frame's times say so): a controller
        /// scanning its slow axis down delivers a direct request's lines in the request's
        /// order with their real times (spm-nanonis with `slow_direction = "down"`). False in
        /// histories written before this field.
        #[serde(default)]
        lines_descending: bool,
    },
}

/// Whether a frame's lines were acquired last line first: the forward trace's first pixel of
/// line 0 was taken after that of the last line (by the frame's own times).
#[must_use]
pub fn lines_descending(frame: &Frame) -> bool {
    let n = frame.request.pixels_per_line as usize;
    let lines = frame.request.lines as usize;
    let times = &frame.forward.time_s;
    match (times.first(), times.get((lines.max(1) - 1) * n)) {
        (Some(first), Some(last)) if lines > 1 => first > last,
        _ => false,
    }
}

/// Wraps a backend and records its lateral commands ([`CommandEvent`]). Failed commands are
/// recorded too when the clock and position can still be read after them (the probe may have
/// moved part of the way); otherwise they are left out.
#[derive(Debug)]
pub struct CommandRecorder<M> {
    inner: M,
    events: Vec<CommandEvent>,
    /// Largest number of events kept (the oldest are dropped beyond it).
    capacity: usize,
}

impl<M: Microscope> CommandRecorder<M> {
    /// Records the commands sent to `inner`, keeping at most `capacity` events.
    pub fn new(inner: M, capacity: usize) -> Self {
        Self {
            inner,
            events: Vec::new(),
            capacity: capacity.max(1),
        }
    }

    /// The events recorded so far, oldest first.
    pub fn events(&self) -> &[CommandEvent] {
        &self.events
    }

    /// The wrapped backend and the events.
    pub fn into_parts(self) -> (M, Vec<CommandEvent>) {
        (self.inner, self.events)
    }

    /// The wrapped backend.
    pub fn inner_mut(&mut self) -> &mut M {
        &mut self.inner
    }

    fn push(&mut self, event: CommandEvent) {
        if self.events.len() >= self.capacity {
            let drop = self.events.len() + 1 - self.capacity;
            self.events.drain(..drop);
        }
        self.events.push(event);
    }
}

impl<M: Microscope> Microscope for CommandRecorder<M> {
    type Error = M::Error;

    fn capabilities(&self) -> Capabilities {
        self.inner.capabilities()
    }
    fn now(&mut self) -> Result<Seconds, Self::Error> {
        self.inner.now()
    }
    fn wait(&mut self, duration: Seconds) -> Result<(), Self::Error> {
        let start = self.inner.now().ok();
        let result = self.inner.wait(duration);
        if let (Some(start), Ok(end)) = (start, self.inner.now()) {
            self.push(CommandEvent::Wait {
                start_s: start.value(),
                end_s: end.value(),
            });
        }
        result
    }
    fn position(&mut self) -> Result<CountPoint, Self::Error> {
        self.inner.position()
    }
    fn move_to(&mut self, request: MoveRequest) -> Result<(), Self::Error> {
        let start = self.inner.now().ok();
        let from = self.inner.position().ok();
        let result = self.inner.move_to(request);
        if result.is_ok()
            && let (Some(start), Some(from), Ok(end)) = (start, from, self.inner.now())
        {
            self.push(CommandEvent::Move {
                start_s: start.value(),
                end_s: end.value(),
                from,
                request,
            });
        }
        result
    }
    fn scan(&mut self, request: &ScanRequest) -> Result<Frame, Self::Error> {
        let start = self.inner.now().ok();
        let from = self.inner.position().ok();
        let result = self.inner.scan(request);
        if let Ok(frame) = &result
            && let (Some(start), Some(from), Ok(end)) = (start, from, self.inner.now())
        {
            self.push(CommandEvent::Scan {
                start_s: start.value(),
                end_s: end.value(),
                from,
                request: request.clone(),
                lines_descending: lines_descending(frame),
            });
        }
        result
    }
    fn z_position(&mut self) -> Result<Counts, Self::Error> {
        self.inner.z_position()
    }
    fn coarse_z(&mut self) -> Option<&mut dyn CoarseZStage<Error = Self::Error>> {
        self.inner.coarse_z()
    }
}
