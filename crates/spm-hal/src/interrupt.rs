//! A backend wrapper that honours a stop request between instrument operations (issue 25
//! item 12: a stop signal acted only between visits, and a long visit took minutes to end).
//!
//! Once the shared flag is set, every operation that takes instrument time — [`wait`],
//! [`move_to`], [`scan`] and a coarse step — is refused with [`Interrupted::Stopped`] (kind
//! [`ErrorKind::Aborted`]) *before* it reaches the backend; reads that take none (`now`,
//! `position`, `z_position`, the coarse position, the capabilities) still answer, so the
//! caller can date and mark what it stops. The caller's loop decides what an abort means
//! (spm-calibration's runner ends the run as aborted, the visit left undone). A backend that
//! can also cut a running operation short (a Nanonis scan, `set_interrupt`) is given the same
//! flag.
//!
//! [`wait`]: Microscope::wait
//! [`move_to`]: Microscope::move_to
//! [`scan`]: Microscope::scan

use crate::microscope::{Capabilities, CoarseZStage, ErrorKind, Microscope, MoveRequest};
use crate::scan::{Frame, ScanRequest};
use crate::units::{CountPoint, Counts, Seconds};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// An error of an [`Interruptible`] backend: the backend's own, or the stop request.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Interrupted<E> {
    /// The wrapped backend failed.
    #[error(transparent)]
    Backend(E),
    /// A stop was requested: the operation was not started.
    #[error(
        "interrupted: a stop was requested, so the instrument operation `{operation}` was not started"
    )]
    Stopped {
        /// The operation refused (`wait`, `move_to`, `scan`, `coarse_step`).
        operation: &'static str,
    },
}

impl<E: crate::microscope::Error> crate::microscope::Error for Interrupted<E> {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::Backend(e) => e.kind(),
            Self::Stopped { .. } => ErrorKind::Aborted,
        }
    }
}

/// A [`Microscope`] that refuses every operation taking instrument time once `stop` is set.
#[derive(Debug)]
pub struct Interruptible<M> {
    inner: M,
    stop: Arc<AtomicBool>,
    refused: u64,
}

impl<M: Microscope> Interruptible<M> {
    /// Wraps `inner` (also `&mut backend`); `stop` is set by whoever stops the run.
    pub fn new(inner: M, stop: Arc<AtomicBool>) -> Self {
        Self {
            inner,
            stop,
            refused: 0,
        }
    }

    /// The wrapped backend.
    pub fn into_inner(self) -> M {
        self.inner
    }

    /// Operations refused since the stop was requested.
    pub fn refused_operations(&self) -> u64 {
        self.refused
    }

    /// Refuses `operation` when a stop was requested.
    fn check(&mut self, operation: &'static str) -> Result<(), Interrupted<M::Error>> {
        if self.stop.load(Ordering::SeqCst) {
            self.refused += 1;
            return Err(Interrupted::Stopped { operation });
        }
        Ok(())
    }
}

impl<M: Microscope> Microscope for Interruptible<M> {
    type Error = Interrupted<M::Error>;

    fn capabilities(&self) -> Capabilities {
        self.inner.capabilities()
    }
    fn now(&mut self) -> Result<Seconds, Self::Error> {
        self.inner.now().map_err(Interrupted::Backend)
    }
    fn wait(&mut self, duration: Seconds) -> Result<(), Self::Error> {
        self.check("wait")?;
        self.inner.wait(duration).map_err(Interrupted::Backend)
    }
    fn position(&mut self) -> Result<CountPoint, Self::Error> {
        self.inner.position().map_err(Interrupted::Backend)
    }
    fn move_to(&mut self, request: MoveRequest) -> Result<(), Self::Error> {
        self.check("move_to")?;
        self.inner.move_to(request).map_err(Interrupted::Backend)
    }
    fn scan(&mut self, request: &ScanRequest) -> Result<Frame, Self::Error> {
        self.check("scan")?;
        self.inner.scan(request).map_err(Interrupted::Backend)
    }
    fn z_position(&mut self) -> Result<Counts, Self::Error> {
        self.inner.z_position().map_err(Interrupted::Backend)
    }
    fn coarse_z(&mut self) -> Option<&mut dyn CoarseZStage<Error = Self::Error>> {
        // The wrapper is its own coarse stage view (a borrowed view of the backend's stage
        // cannot be kept beside it).
        if self.inner.coarse_z().is_some() {
            Some(self)
        } else {
            None
        }
    }
}

impl<M: Microscope> CoarseZStage for Interruptible<M> {
    type Error = Interrupted<M::Error>;

    fn step(&mut self, steps: i64) -> Result<(), Self::Error> {
        self.check("coarse_step")?;
        match self.inner.coarse_z() {
            Some(stage) => stage.step(steps).map_err(Interrupted::Backend),
            None => Err(Interrupted::Stopped {
                operation: "coarse_step",
            }),
        }
    }
    fn position_steps(&mut self) -> Result<i64, Self::Error> {
        match self.inner.coarse_z() {
            Some(stage) => stage.position_steps().map_err(Interrupted::Backend),
            None => Err(Interrupted::Stopped {
                operation: "coarse_position",
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Error as _;
    use crate::mock::ScriptedMicroscope;

    #[test]
    fn after_a_stop_request_operations_are_refused_and_reads_answer() {
        let stop = Arc::new(AtomicBool::new(false));
        let mut mock = ScriptedMicroscope::new(ScriptedMicroscope::default_capabilities())
            .lenient_moves_and_waits(true);
        let mut m = Interruptible::new(&mut mock, Arc::clone(&stop));
        m.wait(Seconds(1.0))
            .expect("before the stop the backend waits");
        stop.store(true, Ordering::SeqCst);
        let err = m.wait(Seconds(1.0)).expect_err("a wait after the stop");
        assert_eq!(err.kind(), ErrorKind::Aborted);
        assert!(err.to_string().contains("`wait` was not started"), "{err}");
        let request = MoveRequest {
            target: CountPoint::from_counts(10.0, 0.0),
            speed: crate::CountsPerSecond(100.0),
            settle: Seconds(0.0),
        };
        let err = m.move_to(request).expect_err("a move after the stop");
        assert_eq!(err.kind(), ErrorKind::Aborted);
        assert!(m.now().is_ok(), "the clock still answers");
        assert!(m.position().is_ok(), "the position still answers");
        assert_eq!(m.refused_operations(), 2);
        drop(m);
        assert_eq!(
            mock.calls().len(),
            1,
            "only the wait before the stop reached the backend: {:?}",
            mock.calls()
        );
    }
}
