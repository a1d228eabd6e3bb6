//! The ground-truth oracle: a borrowed, read-only view of the simulator's
//! hidden state. For tests, benchmarks and xtask — never for algorithms.

use crate::fault::FaultEvent;
use crate::scanner::{Jacobian, Lcc};
use crate::state::SimState;
use crate::surface::{FeatureSite, Surface};
use serde::{Deserialize, Serialize};
use spm_hal::{CountPoint, Counts, NmPerCount, NmPoint, NmVelocity, Seconds};

/// Read-only ground truth of a [`Simulator`](crate::Simulator).
///
/// Vocabulary (see the crate docs): `u` = commanded counts, `uₑ = u + h + c`
/// = *effective input* (after hysteresis h and creep c), `F(uₑ, z)` = the
/// static map (nm, scanner frame), `d(t)` = drift of the tip relative to the
/// sample. The sample point under the tip is `F(uₑ, z) + d(t)`.
#[derive(Clone, Copy, Debug)]
pub struct Oracle<'a> {
    state: &'a SimState,
}

fn point(p: [f64; 2]) -> CountPoint {
    CountPoint::from_counts(p[0], p[1])
}

impl<'a> Oracle<'a> {
    pub(crate) fn new(state: &'a SimState) -> Self {
        Self { state }
    }

    /// True tip positions (scanner frame, nm: hysteresis and creep as they
    /// acted, drift and jitter excluded) of the last scan's forward pixels in
    /// acquisition order, recorded while
    /// [`Simulator::record_tip_positions`](crate::Simulator::record_tip_positions)
    /// is on; empty otherwise.
    pub fn last_scan_tip_positions(&self) -> Vec<NmPoint> {
        self.state
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
        self.state
            .effective_trace
            .as_deref()
            .unwrap_or(&[])
            .iter()
            .map(|p| point(*p))
            .collect()
    }

    /// The instrument clock now.
    pub fn now(&self) -> Seconds {
        Seconds(self.state.time_s)
    }

    /// The static map F(uₑ, z): tip position in the scanner frame, nm.
    pub fn static_map(&self, effective: CountPoint, z: Counts) -> NmPoint {
        let p = self
            .state
            .map
            .position(effective.x.value(), effective.y.value(), z.value());
        NmPoint::from_nm(p[0], p[1])
    }

    /// ∂F/∂uₑ at (uₑ, z), nm/count (analytic).
    pub fn jacobian(&self, effective: CountPoint, z: Counts) -> Jacobian {
        self.state
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
    pub fn vertical(&self) -> VerticalOracle<'a> {
        VerticalOracle::new(self.state)
    }

    /// Nominal Kz (at z = 0, field centre), nm/count; see [`vertical`](Self::vertical) for
    /// the field of a nonlinear manipulator.
    pub fn kz(&self) -> NmPerCount {
        NmPerCount(self.state.map.kz_nm_per_count())
    }

    /// The Z reading now without noise (the feedback state), counts.
    pub fn z_now(&self) -> Counts {
        Counts(self.state.z_reading_noiseless())
    }

    /// The static map's Z argument now: the extension in nominal counts (extension / Kz₀);
    /// equals [`z_now`](Self::z_now) for a linear Z manipulator.
    pub fn z_map_argument_now(&self) -> Counts {
        Counts(self.state.z_counts_noiseless())
    }

    /// The effective input now: u + h + c, counts.
    pub fn effective_input_now(&self) -> CountPoint {
        point(self.state.scanner.effective())
    }

    /// The hysteresis offsets h (x, y) now, counts.
    pub fn hysteresis_offset_now(&self) -> CountPoint {
        let h = &self.state.scanner.hysteresis;
        CountPoint::from_counts(h[0].offset(), h[1].offset())
    }

    /// The creep offsets c (x, y) now, counts.
    pub fn creep_offset_now(&self) -> CountPoint {
        point(self.state.scanner.creep_offset)
    }

    /// The hysteresis operator of an axis (0 = x, 1 = y): its play thresholds (counts) and
    /// the one weight every operator has (h = w·Σyᵢ).
    pub fn hysteresis_operator(&self, axis: usize) -> (Vec<f64>, f64) {
        self.state.scanner.hysteresis[axis.min(1)].operator()
    }

    /// The dead band `[lo, hi]` of an axis (0 = x, 1 = y) in commanded counts:
    /// while the command stays inside it the hysteresis state is frozen.
    pub fn hysteresis_dead_band(&self, axis: usize) -> (Counts, Counts) {
        let (lo, hi) = self.state.scanner.hysteresis[axis.min(1)].dead_band();
        (Counts(lo), Counts(hi))
    }

    /// The effective input right after a fast move from the current state to
    /// commanded `u` (hysteresis applied along the way, creep not yet reacted).
    pub fn effective_input_for(&self, commanded: CountPoint) -> CountPoint {
        let mut h = self.state.scanner.hysteresis.clone();
        let c = self.state.scanner.creep_offset;
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
        let s = &self.state.scanner;
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
        let d = self.state.drift.displacement(t.value());
        NmPoint::from_nm(d[0], d[1])
    }

    /// The vibration part of [`drift_displacement`](Self::drift_displacement) at `t`, nm.
    pub fn vibration_displacement(&self, t: Seconds) -> NmPoint {
        let v = self.state.drift.vibration(t.value());
        NmPoint::from_nm(v[0], v[1])
    }

    /// Drift velocity at `t`, nm/s (the vibration's included; jumps are steps and not included).
    pub fn drift_velocity(&self, t: Seconds) -> NmVelocity {
        let v = self.state.drift.velocity(t.value());
        NmVelocity {
            x_nm_per_s: v[0],
            y_nm_per_s: v[1],
        }
    }

    /// The tip position now in the scanner frame, F(uₑ, z), nm.
    pub fn tip_scanner_position_now(&self) -> NmPoint {
        let p = self.state.scanner_position_nm();
        NmPoint::from_nm(p[0], p[1])
    }

    /// The sample point under the tip now, F(uₑ, z) + d(now), nm.
    pub fn tip_sample_position_now(&self) -> NmPoint {
        let p = self.state.scanner_position_nm();
        let d = self.state.drift.displacement(self.state.time_s);
        NmPoint::from_nm(p[0] + d[0], p[1] + d[1])
    }

    /// The commanded position at which sample point `s` appears now: solves
    /// `F(u + h(u) + c, z) + d(now) = s` (Newton on F, fixed point on the
    /// hysteresis, current creep and Z). `None` if it does not converge.
    /// "Now" is literal: it ignores DAC rounding (≤ 0.5 count), the Z change
    /// at the target (through the Z⇒X/Y couplings, a few pm on HOPG), and
    /// the creep and drift during the call overhead and the move itself.
    pub fn commanded_for_sample_point(&self, sample: NmPoint) -> Option<CountPoint> {
        let d = self.state.drift.displacement(self.state.time_s);
        let target = [sample.x.value() - d[0], sample.y.value() - d[1]];
        let ue = self
            .state
            .map
            .inverse(target, self.state.z_counts_noiseless())?;
        let c = self.state.scanner.creep_offset;
        let mut u = [
            ue[0] - c[0] - self.state.scanner.hysteresis[0].offset(),
            ue[1] - c[1] - self.state.scanner.hysteresis[1].offset(),
        ];
        for _ in 0..100 {
            let mut h = self.state.scanner.hysteresis.clone();
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
        &self.state.surface
    }

    /// True height of the surface at a sample point (pristine tip), nm.
    pub fn surface_height(&self, sample: NmPoint) -> f64 {
        self.state
            .surface
            .height_nm(sample.x.value(), sample.y.value())
    }

    /// True feature sites within `radius_nm` of a sample point, nearest first.
    pub fn features_near(&self, sample: NmPoint, radius_nm: f64) -> Vec<FeatureSite> {
        self.state.surface.features_near(sample, radius_nm)
    }

    /// Every fault and drift jump so far, in the order they happened.
    pub fn fault_log(&self) -> &'a [FaultEvent] {
        &self.state.log
    }

    /// Fault-log entries whose effect overlaps `[start, end]`.
    pub fn faults_between(&self, start: Seconds, end: Seconds) -> Vec<FaultEvent> {
        self.state
            .log
            .iter()
            .filter(|e| e.overlaps(start, end))
            .cloned()
            .collect()
    }

    /// S(t): fractional extra displacement a step (from a settled state) has
    /// gained by creep `t` after it; ΔL(t) = ΔL(0)·(1 + S(t)).
    pub fn creep_step_response(&self, t: Seconds) -> f64 {
        self.state.scanner.creep[0].step_response_fraction(t.value())
    }

    /// Creep time constants (s) and the weight of every element.
    pub fn creep_elements(&self) -> (&'a [f64], f64) {
        let c = &self.state.scanner.creep[0];
        (c.time_constants_s(), c.weight())
    }

    /// The tip's current contrast multiplier (1 = pristine; tip changes alter it).
    pub fn tip_contrast(&self) -> f64 {
        self.state.tip.contrast
    }
}

/// Ground truth of the vertical axis (tests, benchmarks, xtask — never algorithms): the Kz
/// field, the bowl (X,Y⇒Z) and the Z⇒X/Y crosstalk.
///
/// Lateral positions are *commanded* counts taken in the reference state (see
/// [`crate::Oracle::reference_effective_input`]); Z is the controller's Z reading in counts.
#[derive(Clone, Copy, Debug)]
pub struct VerticalOracle<'a> {
    state: &'a SimState,
    creep_settled: bool,
}

/// The Z⇒X/Y crosstalk of the scanner.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ZCrosstalk {
    /// Tilted tube: X displacement per nm of extension, nm/nm.
    pub tilt_x_nm_per_nm: f64,
    /// Tilted tube: Y displacement per nm of extension, nm/nm.
    pub tilt_y_nm_per_nm: f64,
    /// Fractional change of both lateral sensitivities per count of the static map's Z
    /// argument (extension / Kz₀), 1/count.
    pub lateral_sensitivity_change_per_count: f64,
}

impl<'a> VerticalOracle<'a> {
    pub(crate) fn new(state: &'a SimState) -> Self {
        Self {
            state,
            creep_settled: true,
        }
    }

    /// The same view, with lateral positions taken right after a move instead of with the
    /// creep settled: the effective input `(1 + W_h)·u` (hysteresis midline, creep not yet
    /// reacted). A node is measured seconds after its move, far from the settled state of
    /// creep time constants up to hours; the two references bracket the state it had.
    pub fn just_moved(mut self) -> Self {
        self.creep_settled = false;
        self
    }

    fn reference_effective(&self, commanded: spm_hal::CountPoint) -> [f64; 2] {
        let o = Oracle::new(self.state);
        let e = o.reference_effective_input(commanded);
        if self.creep_settled {
            [e.x.value(), e.y.value()]
        } else {
            let wc = 1.0 + self.state.scanner.creep[0].total_weight();
            [e.x.value() / wc, e.y.value() / wc]
        }
    }

    /// True local Kz = ∂(extension)/∂(Z counts), nm/count, at commanded `u` and Z reading `z`.
    pub fn kz_at(&self, commanded: spm_hal::CountPoint, z: spm_hal::Counts) -> spm_hal::NmPerCount {
        let ue = self.reference_effective(commanded);
        spm_hal::NmPerCount(self.state.zmap.kz_nm_per_count(z.value(), ue))
    }

    /// True local Kz (nm/count) a small scan around commanded `u` sees now: the current
    /// hysteresis and creep state (as [`crate::Oracle::effective_input_for`]) and Z reading.
    pub fn kz_now(&self, commanded: spm_hal::CountPoint) -> spm_hal::NmPerCount {
        let o = Oracle::new(self.state);
        let e = o.effective_input_for(commanded);
        let z = o.z_now();
        spm_hal::NmPerCount(
            self.state
                .zmap
                .kz_nm_per_count(z.value(), [e.x.value(), e.y.value()]),
        )
    }

    /// Extension (nm) of Z reading `z` at commanded `u`.
    pub fn extension_nm(&self, commanded: spm_hal::CountPoint, z: spm_hal::Counts) -> f64 {
        let ue = self.reference_effective(commanded);
        self.state.zmap.extension_nm(z.value(), ue)
    }

    /// Z reference (nm of extension) that holds the tip on the sample's reference plane with
    /// the coarse stage at `coarse_steps`.
    pub fn reference_extension_nm(&self, coarse_steps: i64) -> f64 {
        let i = &self.state.config.instrument;
        let step = i.coarse_z.as_ref().map_or(0.0, |c| c.step_nm);
        i.initial_z_extension_nm - coarse_steps as f64 * step
    }

    /// Extension (nm) the bowl adds at commanded `u` with the stage at `coarse_steps` (the
    /// tube's arc over a flat, level sample; tilt and Z coupling included).
    pub fn bowl_nm(&self, commanded: spm_hal::CountPoint, coarse_steps: i64) -> f64 {
        let ue = self.reference_effective(commanded);
        let kz0 = self.state.map.kz_nm_per_count();
        let base = self.reference_extension_nm(coarse_steps);
        let mut e = base;
        let mut bowl = 0.0;
        for _ in 0..4 {
            let p = self.state.map.position(ue[0], ue[1], e / kz0);
            bowl = self.state.map.bowl_nm(p);
            e = base + bowl;
        }
        bowl
    }

    /// The Z reading (counts, noiseless) of a flat, level sample on the reference plane at
    /// commanded `u` with the stage at `coarse_steps`: the bowl as the controller sees it.
    pub fn flat_sample_z_reading(
        &self,
        commanded: spm_hal::CountPoint,
        coarse_steps: i64,
    ) -> spm_hal::Counts {
        let ue = self.reference_effective(commanded);
        let e = self.reference_extension_nm(coarse_steps) + self.bowl_nm(commanded, coarse_steps);
        spm_hal::Counts(self.state.zmap.counts_of(e, ue))
    }

    /// History-independent true LCCs at commanded `u` for Z reading `z` (the Z reading is
    /// turned into the static map's Z argument through the Z characteristic).
    pub fn true_lcc_at_reading(
        &self,
        commanded: spm_hal::CountPoint,
        z: spm_hal::Counts,
    ) -> crate::Lcc {
        let e = self.extension_nm(commanded, z);
        let arg = spm_hal::Counts(e / self.state.map.kz_nm_per_count());
        Oracle::new(self.state).true_lcc(commanded, arg)
    }

    /// The Z⇒X/Y crosstalk parameters.
    pub fn z_crosstalk(&self) -> ZCrosstalk {
        let s = &self.state.config.scanner;
        ZCrosstalk {
            tilt_x_nm_per_nm: s.tilt_x_from_z,
            tilt_y_nm_per_nm: s.tilt_y_from_z,
            lateral_sensitivity_change_per_count: s.lateral_sensitivity_change_per_z
                / self.state.config.instrument.z_half_range_counts,
        }
    }

    /// True when the manipulator is linear and uniform.
    pub fn is_linear(&self) -> bool {
        self.state.zmap.is_linear()
    }
}
