//! The Z manipulator's characteristic: extension (nm) as a nonlinear function of the Z
//! counts, varying over the lateral field (issue 15).
//!
//! Without [`ZManipulatorConfig`] the extension is `E = Kz·z` (the linear map the simulator
//! always had). With it,
//!
//! ```text
//! ζ = z / Hz,  sx = uₑx / H,  sy = uₑy / H
//! L(s) = 1 + gx·sx + gy·sy + r·(sx² + sy²) + ρ·sin(2π·uₑx / P)
//! E(z, s) = Kz·Hz·ζ·(1 + q·ζ + c·ζ²)·L(s)                       (nm)
//! Kz(z, s) = ∂E/∂z = Kz·(1 + 2q·ζ + 3c·ζ²)·L(s)                   (nm/count)
//! ```
//!
//! (Hz the Z half range, H the lateral half range, uₑ the effective lateral input). The
//! feedback holds the *extension* that puts the tip on the surface; the controller reads the
//! Z counts `E⁻¹(extension, s)`. The ripple term (ρ, P) is a Z effect a calibration with
//! low-degree surfaces does not model: tests use it as the "hidden" effect whose residual
//! must show up as structure.

use serde::{Deserialize, Serialize};

/// Nonlinearity of the Z manipulator and its variation over the lateral field. Every field
/// is dimensionless (fractions); 0 everywhere = a linear manipulator with Kz everywhere.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZManipulatorConfig {
    /// Quadratic coefficient q of the characteristic `ζ(1 + q·ζ + c·ζ²)`, ζ = z / half range.
    /// Kz changes by `2q` at full extension. Typical: 0.04.
    pub quadratic: f64,
    /// Cubic coefficient c. Kz changes by `3c` at full extension. Typical: 0.02.
    pub cubic: f64,
    /// Fractional change of Kz at the +x field edge (linear in x), e.g. electrode asymmetry.
    /// Typical: 0.015.
    pub lateral_gradient_x: f64,
    /// Fractional change of Kz at the +y field edge (linear in y). Typical: -0.01.
    pub lateral_gradient_y: f64,
    /// Fractional change of Kz at normalised lateral radius 1 (quadratic in r; the tube's
    /// bending stiffens the Z response at the field edges). Typical: 0.02.
    pub lateral_radial: f64,
    /// Amplitude of a sinusoidal ripple of Kz along x (a "hidden" effect, not a polynomial),
    /// fraction. Typical: 0 (off).
    pub ripple_fraction: f64,
    /// Period of the ripple along x, lateral counts (> 0). Typical: 16384.
    pub ripple_period_counts: f64,
    /// Fractional change of Kz per hour of instrument time (aging, temperature): a Z effect
    /// a calibration that takes Kz as static does not model. Typical: 0 (off).
    pub kz_drift_per_hour: f64,
}

/// The Z characteristic of a validated config (see the module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct ZMap {
    kz: f64,
    z_half_counts: f64,
    half_counts: f64,
    nonlinear: Option<ZManipulatorConfig>,
    /// Instrument time the Kz drift is evaluated at, s (set by the simulator as time goes).
    time_s: f64,
}

impl ZMap {
    /// The map: Kz at the centre (nm/count), the Z and lateral half ranges (counts).
    pub fn new(
        kz_nm_per_count: f64,
        z_half_counts: f64,
        half_counts: f64,
        nonlinear: Option<ZManipulatorConfig>,
    ) -> Self {
        Self {
            kz: kz_nm_per_count,
            z_half_counts,
            half_counts,
            nonlinear,
            time_s: 0.0,
        }
    }

    /// Sets the instrument time (s) of the Kz drift.
    #[inline]
    pub fn set_time(&mut self, time_s: f64) {
        self.time_s = time_s;
    }

    /// True when the manipulator is linear and uniform (E = Kz·z).
    pub fn is_linear(&self) -> bool {
        self.nonlinear.is_none()
    }

    /// The nominal (centre, z = 0) Kz, nm/count.
    pub fn kz0_nm_per_count(&self) -> f64 {
        self.kz
    }

    #[inline]
    fn lateral(&self, c: &ZManipulatorConfig, ue: [f64; 2]) -> f64 {
        let sx = ue[0] / self.half_counts;
        let sy = ue[1] / self.half_counts;
        let ripple = if c.ripple_fraction != 0.0 {
            c.ripple_fraction * (std::f64::consts::TAU * ue[0] / c.ripple_period_counts).sin()
        } else {
            0.0
        };
        (1.0 + c.lateral_gradient_x * sx
            + c.lateral_gradient_y * sy
            + c.lateral_radial * (sx * sx + sy * sy)
            + ripple)
            * (1.0 + c.kz_drift_per_hour * self.time_s / 3600.0)
    }

    /// Extension (nm) at Z counts `z` and effective lateral input `ue` (counts).
    #[inline]
    pub fn extension_nm(&self, z_counts: f64, ue: [f64; 2]) -> f64 {
        match &self.nonlinear {
            None => self.kz * z_counts,
            Some(c) => {
                let zeta = z_counts / self.z_half_counts;
                self.kz
                    * z_counts
                    * (1.0 + c.quadratic * zeta + c.cubic * zeta * zeta)
                    * self.lateral(c, ue)
            }
        }
    }

    /// Local Kz = ∂E/∂z (nm/count) at Z counts `z` and effective lateral input `ue`.
    #[inline]
    pub fn kz_nm_per_count(&self, z_counts: f64, ue: [f64; 2]) -> f64 {
        match &self.nonlinear {
            None => self.kz,
            Some(c) => {
                let zeta = z_counts / self.z_half_counts;
                self.kz
                    * (1.0 + 2.0 * c.quadratic * zeta + 3.0 * c.cubic * zeta * zeta)
                    * self.lateral(c, ue)
            }
        }
    }

    /// Z counts whose extension is `extension_nm` at `ue` (Newton; the characteristic is
    /// monotone for validated configs).
    #[inline]
    pub fn counts_of(&self, extension_nm: f64, ue: [f64; 2]) -> f64 {
        let Some(c) = &self.nonlinear else {
            return extension_nm / self.kz;
        };
        let l = self.lateral(c, ue);
        let target = extension_nm / (self.kz * l);
        // Solve z·(1 + qζ + cζ²) = target.
        let h = self.z_half_counts;
        let mut z = target;
        for _ in 0..30 {
            let zeta = z / h;
            let f = z * (1.0 + c.quadratic * zeta + c.cubic * zeta * zeta) - target;
            let d = 1.0 + 2.0 * c.quadratic * zeta + 3.0 * c.cubic * zeta * zeta;
            let step = f / d;
            z -= step;
            if step.abs() < 1e-9 {
                break;
            }
        }
        z
    }
}

/// Checks a Z-manipulator config: the characteristic must stay monotone over the Z range and
/// the lateral factor positive over the field. Returns the offending field and reason.
pub(crate) fn check(c: &ZManipulatorConfig) -> Result<(), (&'static str, String)> {
    for (field, v, lim) in [
        ("quadratic", c.quadratic, 0.3),
        ("cubic", c.cubic, 0.3),
        ("lateral_gradient_x", c.lateral_gradient_x, 0.3),
        ("lateral_gradient_y", c.lateral_gradient_y, 0.3),
        ("lateral_radial", c.lateral_radial, 0.3),
        ("ripple_fraction", c.ripple_fraction, 0.1),
        ("kz_drift_per_hour", c.kz_drift_per_hour, 0.2),
    ] {
        if !(v.is_finite() && v.abs() <= lim) {
            return Err((
                field,
                format!("must be a finite number in [-{lim}, {lim}], got {v}"),
            ));
        }
    }
    if !(c.ripple_period_counts.is_finite()
        && c.ripple_period_counts >= 16.0
        && c.ripple_period_counts <= 1e10)
    {
        return Err((
            "ripple_period_counts",
            format!(
                "must be a finite number in [16, 1e10], got {}",
                c.ripple_period_counts
            ),
        ));
    }
    // Monotone: dE/dz > 0 for |ζ| ≤ 1 (sampled), lateral factor > 0 on the field.
    for k in 0..=40 {
        let zeta = -1.0 + 0.05 * f64::from(k);
        if 1.0 + 2.0 * c.quadratic * zeta + 3.0 * c.cubic * zeta * zeta <= 0.1 {
            return Err((
                "quadratic",
                "with `cubic`, makes the Z characteristic non-monotone inside the Z range".into(),
            ));
        }
    }
    let worst = 1.0
        - c.lateral_gradient_x.abs()
        - c.lateral_gradient_y.abs()
        - 2.0 * c.lateral_radial.min(0.0).abs()
        - c.ripple_fraction.abs();
    if worst <= 0.1 {
        return Err((
            "lateral_gradient_x",
            "with the other lateral terms, makes Kz vanish somewhere in the field".into(),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config() -> ZManipulatorConfig {
        ZManipulatorConfig {
            quadratic: 0.04,
            cubic: 0.02,
            lateral_gradient_x: 0.015,
            lateral_gradient_y: -0.01,
            lateral_radial: 0.02,
            ripple_fraction: 0.003,
            ripple_period_counts: 16384.0,
            kz_drift_per_hour: 0.0,
        }
    }

    #[test]
    fn counts_invert_the_extension_and_kz_is_its_slope() {
        let m = ZMap::new(0.004, 32768.0, 32768.0, Some(config()));
        for (z, ue) in [
            (0.0, [0.0, 0.0]),
            (10000.0, [20000.0, -15000.0]),
            (-25000.0, [-30000.0, 30000.0]),
        ] {
            let e = m.extension_nm(z, ue);
            assert!((m.counts_of(e, ue) - z).abs() < 1e-6);
            let h = 0.5;
            let slope = (m.extension_nm(z + h, ue) - m.extension_nm(z - h, ue)) / (2.0 * h);
            assert!((slope - m.kz_nm_per_count(z, ue)).abs() < 1e-12);
        }
        let linear = ZMap::new(0.004, 32768.0, 32768.0, None);
        assert_eq!(linear.counts_of(0.4, [1.0, 2.0]), 100.0);
        assert!(check(&config()).is_ok());
        let bad = ZManipulatorConfig {
            quadratic: 0.3,
            cubic: -0.3,
            ..config()
        };
        assert!(check(&bad).is_err());
    }
}

/// Ground truth of the vertical axis (tests, benchmarks, xtask — never algorithms): the Kz
/// field, the bowl (X,Y⇒Z) and the Z⇒X/Y crosstalk.
///
/// Lateral positions are *commanded* counts taken in the reference state (see
/// [`crate::Oracle::reference_effective_input`]); Z is the controller's Z reading in counts.
#[derive(Clone, Copy, Debug)]
pub struct VerticalOracle<'a> {
    sim: &'a crate::Simulator,
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
    pub(crate) fn new(sim: &'a crate::Simulator) -> Self {
        Self {
            sim,
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
        let o = self.sim.oracle();
        let e = o.reference_effective_input(commanded);
        if self.creep_settled {
            [e.x.value(), e.y.value()]
        } else {
            let wc = 1.0 + self.sim.scanner.creep[0].total_weight();
            [e.x.value() / wc, e.y.value() / wc]
        }
    }

    /// True local Kz = ∂(extension)/∂(Z counts), nm/count, at commanded `u` and Z reading `z`.
    pub fn kz_at(&self, commanded: spm_hal::CountPoint, z: spm_hal::Counts) -> spm_hal::NmPerCount {
        let ue = self.reference_effective(commanded);
        spm_hal::NmPerCount(self.sim.zmap.kz_nm_per_count(z.value(), ue))
    }

    /// True local Kz (nm/count) a small scan around commanded `u` sees now: the current
    /// hysteresis and creep state (as [`crate::Oracle::effective_input_for`]) and Z reading.
    pub fn kz_now(&self, commanded: spm_hal::CountPoint) -> spm_hal::NmPerCount {
        let o = self.sim.oracle();
        let e = o.effective_input_for(commanded);
        let z = o.z_now();
        spm_hal::NmPerCount(
            self.sim
                .zmap
                .kz_nm_per_count(z.value(), [e.x.value(), e.y.value()]),
        )
    }

    /// Extension (nm) of Z reading `z` at commanded `u`.
    pub fn extension_nm(&self, commanded: spm_hal::CountPoint, z: spm_hal::Counts) -> f64 {
        let ue = self.reference_effective(commanded);
        self.sim.zmap.extension_nm(z.value(), ue)
    }

    /// Z reference (nm of extension) that holds the tip on the sample's reference plane with
    /// the coarse stage at `coarse_steps`.
    pub fn reference_extension_nm(&self, coarse_steps: i64) -> f64 {
        let i = &self.sim.config.instrument;
        let step = i.coarse_z.as_ref().map_or(0.0, |c| c.step_nm);
        i.initial_z_extension_nm - coarse_steps as f64 * step
    }

    /// Extension (nm) the bowl adds at commanded `u` with the stage at `coarse_steps` (the
    /// tube's arc over a flat, level sample; tilt and Z coupling included).
    pub fn bowl_nm(&self, commanded: spm_hal::CountPoint, coarse_steps: i64) -> f64 {
        let ue = self.reference_effective(commanded);
        let kz0 = self.sim.map.kz_nm_per_count();
        let base = self.reference_extension_nm(coarse_steps);
        let mut e = base;
        let mut bowl = 0.0;
        for _ in 0..4 {
            let p = self.sim.map.position(ue[0], ue[1], e / kz0);
            bowl = self.sim.map.bowl_nm(p);
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
        spm_hal::Counts(self.sim.zmap.counts_of(e, ue))
    }

    /// History-independent true LCCs at commanded `u` for Z reading `z` (the Z reading is
    /// turned into the static map's Z argument through the Z characteristic).
    pub fn true_lcc_at_reading(
        &self,
        commanded: spm_hal::CountPoint,
        z: spm_hal::Counts,
    ) -> crate::Lcc {
        let e = self.extension_nm(commanded, z);
        let arg = spm_hal::Counts(e / self.sim.map.kz_nm_per_count());
        self.sim.oracle().true_lcc(commanded, arg)
    }

    /// The Z⇒X/Y crosstalk parameters.
    pub fn z_crosstalk(&self) -> ZCrosstalk {
        let s = &self.sim.config.scanner;
        ZCrosstalk {
            tilt_x_nm_per_nm: s.tilt_x_from_z,
            tilt_y_nm_per_nm: s.tilt_y_from_z,
            lateral_sensitivity_change_per_count: s.lateral_sensitivity_change_per_z
                / self.sim.config.instrument.z_half_range_counts,
        }
    }

    /// True when the manipulator is linear and uniform.
    pub fn is_linear(&self) -> bool {
        self.sim.zmap.is_linear()
    }
}
