//! A scripted mock backend for tests of code that is generic over [`Microscope`].
//!
//! After embedded-hal-mock: the test queues [`Expectation`]s; every call of
//! `wait`, `move_to`, `scan` or `z_position` takes the next one. A call that does
//! not match the queue returns a [`MockError`] of kind [`ErrorKind::Other`]
//! (it does not panic, so the code under test sees an ordinary failure) and is
//! remembered, and [`ScriptedMicroscope::done`] reports it. Faults are injected
//! with [`Expectation::fault`], or at a configurable rate with
//! [`ScriptedMicroscope::with_random_faults`] (a random fault fails the call without
//! consuming its expectation, so the retried call gets it). `now`, `position` and
//! `capabilities` are answered from the mock's state and never consume expectations.
//!
//! The mock has a clock: a scan takes [`Frame::nominal_duration`], a move
//! takes its length over its speed plus the settle time, a wait its duration.

use crate::microscope::{Capabilities, CoarseZStage, ErrorKind, Microscope, MoveRequest};
use crate::scan::{Frame, ScanRequest};
use crate::units::{CountPoint, Counts, Seconds};
use std::collections::VecDeque;
use std::fmt;

/// The operations of [`Microscope`] that consume expectations.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Operation {
    /// [`Microscope::wait`].
    Wait,
    /// [`Microscope::move_to`].
    MoveTo,
    /// [`Microscope::scan`].
    Scan,
    /// [`Microscope::z_position`].
    ZPosition,
}

/// The mock's error: a kind and a message.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{kind}: {message}")]
pub struct MockError {
    /// What kind of failure this is.
    pub kind: ErrorKind,
    /// What happened.
    pub message: String,
}

impl crate::microscope::Error for MockError {
    fn kind(&self) -> ErrorKind {
        self.kind
    }
}

/// A surface for a scripted scan: height in Z counts at a commanded position and time.
pub type ScanScript = Box<dyn FnMut(CountPoint, Seconds) -> Counts + Send>;

/// One expected call and how to answer it.
pub enum Expectation {
    /// A `wait`; `None` accepts any duration.
    Wait(Option<Seconds>),
    /// A `move_to`; `None` accepts any target, otherwise the target must lie
    /// within `tolerance` of it.
    MoveTo {
        /// The expected target.
        target: Option<CountPoint>,
        /// Accepted distance from the expected target.
        tolerance: Counts,
    },
    /// A `scan`, answered by evaluating the script at every pixel.
    Scan(ScanScript),
    /// A `z_position`, answered with this value.
    ZPosition(Counts),
    /// The named operation fails with this error.
    Fault {
        /// Which call fails.
        operation: Operation,
        /// The error it returns.
        error: MockError,
    },
}

impl Expectation {
    /// A scan answered by `surface(position, time)`.
    pub fn scan(surface: impl FnMut(CountPoint, Seconds) -> Counts + Send + 'static) -> Self {
        Self::Scan(Box::new(surface))
    }

    /// The next call of `operation` fails with `kind`.
    pub fn fault(operation: Operation, kind: ErrorKind) -> Self {
        Self::Fault {
            operation,
            error: MockError {
                kind,
                message: format!("injected {kind:?} fault on {operation:?}"),
            },
        }
    }

    fn operation(&self) -> Operation {
        match self {
            Self::Wait(_) => Operation::Wait,
            Self::MoveTo { .. } => Operation::MoveTo,
            Self::Scan(_) => Operation::Scan,
            Self::ZPosition(_) => Operation::ZPosition,
            Self::Fault { operation, .. } => *operation,
        }
    }
}

impl fmt::Debug for Expectation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Fault { operation, error } => write!(f, "Fault({operation:?}, {:?})", error.kind),
            other => write!(f, "{:?}", other.operation()),
        }
    }
}

/// Faults injected at random into the consuming calls (see
/// [`ScriptedMicroscope::with_random_faults`]).
#[derive(Clone, Debug, PartialEq)]
pub struct RandomFaults {
    /// Probability that a consuming call fails, in [0, 1].
    pub probability_per_call: f64,
    /// The kinds drawn from (uniformly); empty means none are injected.
    pub kinds: Vec<ErrorKind>,
    /// Seed of the deterministic generator.
    pub seed: u64,
}

impl RandomFaults {
    /// The transient kinds (timeout, communication, feedback lost) at `probability_per_call`.
    pub fn transient(probability_per_call: f64, seed: u64) -> Self {
        Self {
            probability_per_call,
            kinds: vec![
                ErrorKind::Timeout,
                ErrorKind::Communication,
                ErrorKind::FeedbackLost,
            ],
            seed,
        }
    }
}

/// One injected random fault.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InjectedFault {
    /// The failed call.
    pub operation: Operation,
    /// Its error kind.
    pub kind: ErrorKind,
    /// The mock's clock when it failed.
    pub time: Seconds,
}

/// splitmix64: a tiny deterministic generator (no dependency).
fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A [`Microscope`] that answers from a queue of expectations.
pub struct ScriptedMicroscope {
    random_faults: Option<(RandomFaults, u64)>,
    injected: Vec<InjectedFault>,
    capabilities: Capabilities,
    expectations: VecDeque<Expectation>,
    clock: Seconds,
    position: CountPoint,
    lenient_moves_and_waits: bool,
    mismatches: Vec<String>,
    calls: Vec<Operation>,
}

impl ScriptedMicroscope {
    /// A mock with the given capabilities, its probe at the field's centre, clock at 0 s.
    pub fn new(capabilities: Capabilities) -> Self {
        let position = CountPoint::new(
            (capabilities.field_min.x + capabilities.field_max.x) * 0.5,
            (capabilities.field_min.y + capabilities.field_max.y) * 0.5,
        );
        Self {
            random_faults: None,
            injected: Vec::new(),
            capabilities,
            expectations: VecDeque::new(),
            clock: Seconds::ZERO,
            position,
            lenient_moves_and_waits: false,
            mismatches: Vec::new(),
            calls: Vec::new(),
        }
    }

    /// Capabilities of a generic 16-bit scanner (±32768 counts), with counter
    /// scans and backward traces, no coarse stage.
    pub fn default_capabilities() -> Capabilities {
        Capabilities {
            field_min: CountPoint::from_counts(-32768.0, -32768.0),
            field_max: CountPoint::from_counts(32767.0, 32767.0),
            z_min: Counts(-32768.0),
            z_max: Counts(32767.0),
            lateral_resolution: Counts(1.0),
            max_pixels_per_line: 4096,
            pixels_per_line_multiple: 1,
            max_lines: 4096,
            min_pixel_dwell: Seconds(1e-6),
            counter_scan: true,
            backward_trace: true,
            coarse_z: None,
        }
    }

    /// When set, `wait` and `move_to` succeed without an expectation unless the
    /// next expectation is for them (a fault or a checked target). Scripts then
    /// only list scans and faults.
    pub fn lenient_moves_and_waits(mut self, lenient: bool) -> Self {
        self.lenient_moves_and_waits = lenient;
        self
    }

    /// Fails consuming calls (`wait`, `move_to`, `scan`, `z_position`) at random with
    /// `faults.probability_per_call`, before they look at the queue: the expectation stays
    /// for the retry. Deterministic from `faults.seed`; see [`Self::injected_faults`].
    pub fn with_random_faults(mut self, faults: RandomFaults) -> Self {
        let state = faults.seed;
        self.random_faults = Some((faults, state));
        self
    }

    /// The random faults injected so far, in order.
    pub fn injected_faults(&self) -> &[InjectedFault] {
        &self.injected
    }

    /// Queues one expectation.
    pub fn expect(&mut self, expectation: Expectation) -> &mut Self {
        self.expectations.push_back(expectation);
        self
    }

    /// Queues several expectations.
    pub fn expect_all(&mut self, expectations: impl IntoIterator<Item = Expectation>) -> &mut Self {
        self.expectations.extend(expectations);
        self
    }

    /// Every consuming call made so far, in order.
    pub fn calls(&self) -> &[Operation] {
        &self.calls
    }

    /// Expectations not yet consumed.
    pub fn remaining(&self) -> usize {
        self.expectations.len()
    }

    /// Checks that every expectation was consumed and no call mismatched.
    pub fn done(&self) -> Result<(), String> {
        let mut problems = self.mismatches.clone();
        if !self.expectations.is_empty() {
            problems.push(format!("unconsumed expectations: {:?}", self.expectations));
        }
        if problems.is_empty() {
            Ok(())
        } else {
            Err(problems.join("; "))
        }
    }

    fn take(&mut self, operation: Operation) -> Result<Option<Expectation>, MockError> {
        self.calls.push(operation);
        if let Some((faults, state)) = &mut self.random_faults
            && !faults.kinds.is_empty()
        {
            let u = (splitmix64(state) >> 11) as f64 / (1u64 << 53) as f64;
            if u < faults.probability_per_call {
                let pick = splitmix64(state) % faults.kinds.len() as u64;
                let kind = faults
                    .kinds
                    .get(usize::try_from(pick).unwrap_or(0))
                    .copied()
                    .unwrap_or(ErrorKind::Other);
                self.injected.push(InjectedFault {
                    operation,
                    kind,
                    time: self.clock,
                });
                return Err(MockError {
                    kind,
                    message: format!("random {kind:?} fault on {operation:?}"),
                });
            }
        }
        let front_matches = self
            .expectations
            .front()
            .is_some_and(|e| e.operation() == operation);
        if front_matches {
            match self.expectations.pop_front() {
                Some(Expectation::Fault { error, .. }) => Err(error),
                other => Ok(other),
            }
        } else if self.lenient_moves_and_waits
            && matches!(operation, Operation::Wait | Operation::MoveTo)
        {
            Ok(None)
        } else {
            let message = format!(
                "unexpected {operation:?}; next expectation: {:?}",
                self.expectations.front()
            );
            self.mismatches.push(message.clone());
            Err(MockError {
                kind: ErrorKind::Other,
                message,
            })
        }
    }
}

impl Microscope for ScriptedMicroscope {
    type Error = MockError;

    fn capabilities(&self) -> Capabilities {
        self.capabilities.clone()
    }

    fn now(&mut self) -> Result<Seconds, MockError> {
        Ok(self.clock)
    }

    fn wait(&mut self, duration: Seconds) -> Result<(), MockError> {
        if let Some(Expectation::Wait(Some(expected))) = self.take(Operation::Wait)?
            && (expected - duration).abs().value() > 1e-9 * (1.0 + expected.value().abs())
        {
            let message = format!("wait of {duration} where {expected} was expected");
            self.mismatches.push(message.clone());
            return Err(MockError {
                kind: ErrorKind::Other,
                message,
            });
        }
        self.clock += duration.max(Seconds::ZERO);
        Ok(())
    }

    fn position(&mut self) -> Result<CountPoint, MockError> {
        Ok(self.position)
    }

    fn move_to(&mut self, request: MoveRequest) -> Result<(), MockError> {
        if let Some(Expectation::MoveTo {
            target: Some(expected),
            tolerance,
        }) = self.take(Operation::MoveTo)?
            && expected.distance(request.target) > tolerance
        {
            let message = format!(
                "move to ({}, {}) where ({}, {}) ± {} was expected",
                request.target.x, request.target.y, expected.x, expected.y, tolerance
            );
            self.mismatches.push(message.clone());
            return Err(MockError {
                kind: ErrorKind::Other,
                message,
            });
        }
        let length = self.position.distance(request.target);
        if request.speed.value() > 0.0 && request.speed.value().is_finite() {
            self.clock += Seconds(length.value() / request.speed.value());
        }
        self.clock += request.settle.max(Seconds::ZERO);
        self.position = request.target;
        Ok(())
    }

    fn scan(&mut self, request: &ScanRequest) -> Result<Frame, MockError> {
        let expectation = self.take(Operation::Scan)?;
        request.validate().map_err(|e| MockError {
            kind: ErrorKind::OutOfRange,
            message: e.to_string(),
        })?;
        let Some(Expectation::Scan(mut surface)) = expectation else {
            return Err(MockError {
                kind: ErrorKind::Other,
                message: "scan expectation without a script".to_owned(),
            });
        };
        let frame = Frame::from_fn(request.clone(), self.clock, &mut *surface);
        self.clock += Frame::nominal_duration(request);
        self.position = request.commanded_position(
            crate::scan::TraceHalf::Backward,
            (request.lines as usize).saturating_sub(1),
            (request.pixels_per_line as usize).saturating_sub(1),
        );
        Ok(frame)
    }

    fn z_position(&mut self) -> Result<Counts, MockError> {
        match self.take(Operation::ZPosition)? {
            Some(Expectation::ZPosition(z)) => Ok(z),
            _ => Ok(Counts::ZERO),
        }
    }

    fn coarse_z(&mut self) -> Option<&mut dyn CoarseZStage<Error = MockError>> {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::units::Counts;

    fn mock() -> ScriptedMicroscope {
        ScriptedMicroscope::new(ScriptedMicroscope::default_capabilities())
    }

    #[test]
    fn random_faults_hit_at_their_rate_deterministically_and_keep_the_script() {
        let run = |seed: u64| {
            let mut m = mock()
                .lenient_moves_and_waits(true)
                .with_random_faults(RandomFaults::transient(0.05, seed));
            m.expect(Expectation::Wait(Some(Seconds(1.0))));
            let mut failures = Vec::new();
            // The one scripted wait is retried until it succeeds; then lenient waits.
            for _ in 0..20_000 {
                if let Err(e) = m.wait(Seconds(1.0)) {
                    failures.push(e.kind);
                }
            }
            assert_eq!(m.remaining(), 0, "the scripted wait was consumed once");
            assert!(m.done().is_ok());
            assert_eq!(m.injected_faults().len(), failures.len());
            assert!(failures.iter().all(|k| k.is_transient()));
            failures
        };
        let a = run(7);
        let rate = a.len() as f64 / 20_000.0;
        assert!((0.045..0.055).contains(&rate), "rate {rate}");
        assert_eq!(a, run(7), "same seed, same faults");
        assert_ne!(a, run(8));
        for kind in [
            ErrorKind::Timeout,
            ErrorKind::Communication,
            ErrorKind::FeedbackLost,
        ] {
            assert!(a.contains(&kind));
        }
        let mut quiet = mock().with_random_faults(RandomFaults::transient(0.0, 1));
        quiet.expect(Expectation::Wait(None));
        assert!(quiet.wait(Seconds(1.0)).is_ok());
    }

    #[test]
    fn scripted_scan_returns_the_scripted_surface_and_advances_the_clock() {
        let mut m = mock();
        m.expect(Expectation::scan(|p, _| Counts(p.x.value() * 2.0)));
        let request = ScanRequest::centred_square(
            CountPoint::from_counts(10.0, 10.0),
            Counts(1.0),
            4,
            Seconds(0.01),
        );
        let frame = m.scan(&request).unwrap();
        assert_eq!(frame.forward.z_counts[1], 2.0 * (8.5 + 1.0));
        assert!((m.now().unwrap().value() - 0.32).abs() < 1e-12);
        m.done().unwrap();
    }

    #[test]
    fn injected_faults_are_returned_as_typed_errors() {
        let mut m = mock();
        m.expect(Expectation::fault(Operation::MoveTo, ErrorKind::Timeout));
        let error = m
            .move_to(MoveRequest {
                target: CountPoint::from_counts(1.0, 1.0),
                speed: crate::CountsPerSecond(100.0),
                settle: Seconds(0.0),
            })
            .unwrap_err();
        assert_eq!(crate::microscope::Error::kind(&error), ErrorKind::Timeout);
        m.done().unwrap();
    }

    #[test]
    fn an_unexpected_call_is_an_error_and_is_reported_by_done() {
        let mut m = mock();
        m.expect(Expectation::ZPosition(Counts(3.0)));
        assert!(m.wait(Seconds(1.0)).is_err());
        assert!(m.done().is_err());
    }

    #[test]
    fn lenient_mode_lets_moves_and_waits_through_and_still_checks_targets() {
        let mut m = mock().lenient_moves_and_waits(true);
        m.wait(Seconds(2.0)).unwrap();
        m.expect(Expectation::MoveTo {
            target: Some(CountPoint::from_counts(5.0, 5.0)),
            tolerance: Counts(0.5),
        });
        let far = MoveRequest {
            target: CountPoint::from_counts(50.0, 5.0),
            speed: crate::CountsPerSecond(10.0),
            settle: Seconds(0.0),
        };
        assert!(m.move_to(far).is_err());
        assert!(m.done().is_err());
    }

    #[test]
    fn the_blanket_impl_forwards_through_a_mutable_reference() {
        fn generic<M: Microscope>(mut m: M) -> Result<Seconds, M::Error> {
            m.wait(Seconds(1.5))?;
            m.now()
        }
        let mut m = mock().lenient_moves_and_waits(true);
        assert_eq!(generic(&mut m).unwrap(), Seconds(1.5));
    }
}
