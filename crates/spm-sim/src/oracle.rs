//! The ground-truth oracle: a borrowed, read-only view of the simulator's
//! hidden state. For tests, benchmarks and xtask — never for algorithms.

use crate::fault::FaultEvent;
use crate::scanner::{Jacobian, Lcc};
use crate::sim::Simulator;
use crate::surface::{FeatureSite, Surface};
use spm_hal::{CountPoint, Counts, NmPerCount, NmPoint, NmVelocity, Seconds};

/// Read-only ground truth of a [`Simulator`].
///
/// Vocabulary (see the crate docs): `u` = commanded counts, `uₑ = u + h + c`
/// = *effective input* (after hysteresis h and creep c), `F(uₑ, z)` = the
/// static map (nm, scanner frame), `d(t)` = drift of the tip relative to the
/// sample. The sample point under the tip is `F(uₑ, z) + d(t)`.
#[derive(Clone, Copy, Debug)]
pub struct Oracle<'a> {
    sim: &'a Simulator,
}

fn point(p: [f64; 2]) -> CountPoint {
    CountPoint::from_counts(p[0], p[1])
}

impl<'a> Oracle<'a> {
    pub(crate) fn new(sim: &'a Simulator) -> Self {
        Self { sim }
    }

    /// True tip positions (scanner frame, nm: hysteresis and creep as they
    /// acted, drift and jitter excluded) of the last scan's forward pixels in
    /// acquisition order, recorded while [`Simulator::record_tip_positions`]
    /// is on; empty otherwise.
    pub fn last_scan_tip_positions(&self) -> Vec<NmPoint> {
        self.sim
            .tip_trace
            .as_deref()
            .unwrap_or(&[])
            .iter()
            .map(|p| NmPoint::from_nm(p[0], p[1]))
            .collect()
    }

    /// Effective inputs `uₑ = u + h + c` (counts) of the last scan's forward pixels, in
    /// acquisition order, recorded like [`last_scan_tip_positions`](Self::last_scan_tip_positions).
    pub fn last_scan_effective_inputs(&self) -> Vec<CountPoint> {
        self.sim
            .effective_trace
            .as_deref()
            .unwrap_or(&[])
            .iter()
            .map(|p| point(*p))
            .collect()
    }

    /// The instrument clock now.
    pub fn now(&self) -> Seconds {
        Seconds(self.sim.time_s)
    }

    /// The static map F(uₑ, z): tip position in the scanner frame, nm.
    pub fn static_map(&self, effective: CountPoint, z: Counts) -> NmPoint {
        let p = self
            .sim
            .map
            .position(effective.x.value(), effective.y.value(), z.value());
        NmPoint::from_nm(p[0], p[1])
    }

    /// ∂F/∂uₑ at (uₑ, z), nm/count (analytic).
    pub fn jacobian(&self, effective: CountPoint, z: Counts) -> Jacobian {
        self.sim
            .map
            .jacobian(effective.x.value(), effective.y.value(), z.value())
    }

    /// LCCs of the static map at effective input uₑ and Z extension z:
    /// the decomposition `J = R(θ)·[[K̄x, K̄y sin α], [0, K̄y cos α]]`.
    /// This is exactly the slope a small, fast move sees when the hysteresis
    /// state is frozen and the scanner is at uₑ (see the crate docs).
    pub fn lcc(&self, effective: CountPoint, z: Counts) -> Lcc {
        Lcc::from_jacobian(self.jacobian(effective, z))
    }

    /// The Z-manipulator view: true Kz field, bowl, Z⇒X/Y crosstalk ([`crate::vertical`]).
    pub fn vertical(&self) -> crate::vertical::VerticalOracle<'a> {
        crate::vertical::VerticalOracle::new(self.sim)
    }

    /// Nominal Kz (at z = 0, field centre), nm/count; see [`vertical`](Self::vertical) for
    /// the field of a nonlinear manipulator.
    pub fn kz(&self) -> NmPerCount {
        NmPerCount(self.sim.map.kz_nm_per_count())
    }

    /// The Z reading now without noise (the feedback state), counts.
    pub fn z_now(&self) -> Counts {
        Counts(self.sim.z_reading_noiseless())
    }

    /// The static map's Z argument now: the extension in nominal counts (extension / Kz₀);
    /// equals [`z_now`](Self::z_now) for a linear Z manipulator.
    pub fn z_map_argument_now(&self) -> Counts {
        Counts(self.sim.z_counts_noiseless())
    }

    /// The effective input now: u + h + c, counts.
    pub fn effective_input_now(&self) -> CountPoint {
        point(self.sim.scanner.effective())
    }

    /// The hysteresis offsets h (x, y) now, counts.
    pub fn hysteresis_offset_now(&self) -> CountPoint {
        let h = &self.sim.scanner.hysteresis;
        CountPoint::from_counts(h[0].offset(), h[1].offset())
    }

    /// The creep offsets c (x, y) now, counts.
    pub fn creep_offset_now(&self) -> CountPoint {
        point(self.sim.scanner.creep_offset)
    }

    /// The hysteresis operator of an axis (0 = x, 1 = y): its play thresholds (counts) and
    /// the one weight every operator has (h = w·Σyᵢ).
    pub fn hysteresis_operator(&self, axis: usize) -> (Vec<f64>, f64) {
        self.sim.scanner.hysteresis[axis.min(1)].operator()
    }

    /// The dead band `[lo, hi]` of an axis (0 = x, 1 = y) in commanded counts:
    /// while the command stays inside it the hysteresis state is frozen.
    pub fn hysteresis_dead_band(&self, axis: usize) -> (Counts, Counts) {
        let (lo, hi) = self.sim.scanner.hysteresis[axis.min(1)].dead_band();
        (Counts(lo), Counts(hi))
    }

    /// The effective input right after a fast move from the current state to
    /// commanded `u` (hysteresis applied along the way, creep not yet reacted).
    pub fn effective_input_for(&self, commanded: CountPoint) -> CountPoint {
        let mut h = self.sim.scanner.hysteresis.clone();
        let c = self.sim.scanner.creep_offset;
        let (ux, uy) = (commanded.x.value(), commanded.y.value());
        point([ux + h[0].update(ux) + c[0], uy + h[1].update(uy) + c[1]])
    }

    /// LCCs a small fast move around commanded `u` sees given the current
    /// hysteresis and creep state and Z: `lcc(effective_input_for(u), z_now)`.
    /// Compare measured LCCs with this (taken right after the measurement)
    /// for the 0.1 %-level check.
    pub fn lcc_now(&self, commanded: CountPoint) -> Lcc {
        self.lcc(
            self.effective_input_for(commanded),
            self.z_map_argument_now(),
        )
    }

    /// Large-signal gain of each axis from commanded to effective input in the
    /// demagnetised, creep-settled reference state: `(1 + W_h)(1 + W_c)`.
    pub fn reference_gain(&self) -> (f64, f64) {
        let s = &self.sim.scanner;
        let wc = s.creep[0].total_weight();
        (
            (1.0 + s.hysteresis[0].total_weight()) * (1.0 + wc),
            (1.0 + s.hysteresis[1].total_weight()) * (1.0 + wc),
        )
    }

    /// The effective input of commanded `u` in the reference state (major-loop
    /// midline, creep settled): `uₑ = (1 + W_h)(1 + W_c)·u` per axis.
    pub fn reference_effective_input(&self, commanded: CountPoint) -> CountPoint {
        let (gx, gy) = self.reference_gain();
        CountPoint::from_counts(commanded.x.value() * gx, commanded.y.value() * gy)
    }

    /// History-independent true LCCs at commanded `u` and Z extension `z`:
    /// the small-signal LCCs at the reference state,
    /// `lcc(reference_effective_input(u), z)`. A real measurement at `u` differs
    /// from it by the history-dependent hysteresis/creep offset (see
    /// [`lcc_now`](Self::lcc_now) and the crate docs).
    pub fn true_lcc(&self, commanded: CountPoint, z: Counts) -> Lcc {
        self.lcc(self.reference_effective_input(commanded), z)
    }

    /// Drift displacement of the tip relative to the sample at `t`, nm, the
    /// configured vibration included (exact for t up to now; later times hold
    /// the random walk's last velocity).
    pub fn drift_displacement(&self, t: Seconds) -> NmPoint {
        let d = self.sim.drift.displacement(t.value());
        NmPoint::from_nm(d[0], d[1])
    }

    /// The vibration part of [`drift_displacement`](Self::drift_displacement) at `t`, nm.
    pub fn vibration_displacement(&self, t: Seconds) -> NmPoint {
        let v = self.sim.drift.vibration(t.value());
        NmPoint::from_nm(v[0], v[1])
    }

    /// Drift velocity at `t`, nm/s (the vibration's included; jumps are steps and not included).
    pub fn drift_velocity(&self, t: Seconds) -> NmVelocity {
        let v = self.sim.drift.velocity(t.value());
        NmVelocity {
            x_nm_per_s: v[0],
            y_nm_per_s: v[1],
        }
    }

    /// The tip position now in the scanner frame, F(uₑ, z), nm.
    pub fn tip_scanner_position_now(&self) -> NmPoint {
        let p = self.sim.scanner_position_nm();
        NmPoint::from_nm(p[0], p[1])
    }

    /// The sample point under the tip now, F(uₑ, z) + d(now), nm.
    pub fn tip_sample_position_now(&self) -> NmPoint {
        let p = self.sim.scanner_position_nm();
        let d = self.sim.drift.displacement(self.sim.time_s);
        NmPoint::from_nm(p[0] + d[0], p[1] + d[1])
    }

    /// The commanded position at which sample point `s` appears now: solves
    /// `F(u + h(u) + c, z) + d(now) = s` (Newton on F, fixed point on the
    /// hysteresis, current creep and Z). `None` if it does not converge.
    /// "Now" is literal: it ignores DAC rounding (≤ 0.5 count), the Z change
    /// at the target (through the Z⇒X/Y couplings, a few pm on HOPG), and
    /// the creep and drift during the call overhead and the move itself.
    pub fn commanded_for_sample_point(&self, sample: NmPoint) -> Option<CountPoint> {
        let d = self.sim.drift.displacement(self.sim.time_s);
        let target = [sample.x.value() - d[0], sample.y.value() - d[1]];
        let ue = self
            .sim
            .map
            .inverse(target, self.sim.z_counts_noiseless())?;
        let c = self.sim.scanner.creep_offset;
        let mut u = [
            ue[0] - c[0] - self.sim.scanner.hysteresis[0].offset(),
            ue[1] - c[1] - self.sim.scanner.hysteresis[1].offset(),
        ];
        for _ in 0..100 {
            let mut h = self.sim.scanner.hysteresis.clone();
            let next = [
                ue[0] - c[0] - h[0].update(u[0]),
                ue[1] - c[1] - h[1].update(u[1]),
            ];
            let done = (next[0] - u[0]).abs() < 1e-9 && (next[1] - u[1]).abs() < 1e-9;
            u = next;
            if done {
                return Some(point(u));
            }
        }
        None
    }

    /// The surface model.
    pub fn surface(&self) -> &'a Surface {
        &self.sim.surface
    }

    /// True height of the surface at a sample point (pristine tip), nm.
    pub fn surface_height(&self, sample: NmPoint) -> f64 {
        self.sim
            .surface
            .height_nm(sample.x.value(), sample.y.value())
    }

    /// True feature sites within `radius_nm` of a sample point, nearest first.
    pub fn features_near(&self, sample: NmPoint, radius_nm: f64) -> Vec<FeatureSite> {
        self.sim.surface.features_near(sample, radius_nm)
    }

    /// Every fault and drift jump so far, in the order they happened.
    pub fn fault_log(&self) -> &'a [FaultEvent] {
        &self.sim.log
    }

    /// Fault-log entries whose effect overlaps `[start, end]`.
    pub fn faults_between(&self, start: Seconds, end: Seconds) -> Vec<FaultEvent> {
        self.sim
            .log
            .iter()
            .filter(|e| e.overlaps(start, end))
            .cloned()
            .collect()
    }

    /// S(t): fractional extra displacement a step (from a settled state) has
    /// gained by creep `t` after it; ΔL(t) = ΔL(0)·(1 + S(t)).
    pub fn creep_step_response(&self, t: Seconds) -> f64 {
        self.sim.scanner.creep[0].step_response_fraction(t.value())
    }

    /// Creep time constants (s) and the weight of every element.
    pub fn creep_elements(&self) -> (&'a [f64], f64) {
        let c = &self.sim.scanner.creep[0];
        (c.time_constants_s(), c.weight())
    }

    /// The tip's current contrast multiplier (1 = pristine; tip changes alter it).
    pub fn tip_contrast(&self) -> f64 {
        self.sim.tip.contrast
    }
}
