//! The piezo scanner: the static map F, hysteresis (play operators), creep
//! (relaxation chain), and the decomposition of a Jacobian into LCCs.
//!
//! See the crate documentation for the model and what a small move's slope is.

use crate::config::{CreepConfig, HysteresisConfig, ScannerConfig};
use serde::{Deserialize, Serialize};
use spm_hal::{NmPerCount, Radians};

/// The static (frozen-state, small-signal) map from the *effective* input
/// counts `uₑ = u + h + c` and the Z extension (counts) to the tip position in
/// the scanner frame (nm):
///
/// ```text
/// vx = uₑx + γx·uₑx·uₑy/H,  vy = uₑy + γy·uₑx·uₑy/H    (shear gradient)
/// sx = vx / H,  gx = vx·(1 + qx·sx + cx·sx²)          (same for y)
/// k  = 1 + λ·z / Hz                                    (Z-dependent sensitivity)
/// X  = Kx·k·gx,  Y = Ky·k·gy
/// px = X + Y·(sin α₀ + cyx + byx·sy) + tx·Kz·z
/// py = Y·cos α₀ + X·(cxy + bxy·sx)    + ty·Kz·z
/// ```
#[derive(Clone, Debug, PartialEq)]
pub struct StaticMap {
    half_counts: f64,
    z_half_counts: f64,
    kx: f64,
    ky: f64,
    kz: f64,
    qx: f64,
    cx: f64,
    qy: f64,
    cy: f64,
    sin_a: f64,
    cos_a: f64,
    shear_x: f64,
    shear_y: f64,
    cyx: f64,
    cxy: f64,
    byx: f64,
    bxy: f64,
    tilt_x: f64,
    tilt_y: f64,
    z_coupling: f64,
    bowl_curvature_per_nm: f64,
}

/// A 2×2 Jacobian `[[∂px/∂ux, ∂px/∂uy], [∂py/∂ux, ∂py/∂uy]]`, nm/count.
pub type Jacobian = [[f64; 2]; 2];

impl StaticMap {
    /// The map of a validated scanner config; `half_counts` and `z_half_counts`
    /// are the instrument's half ranges.
    pub fn new(s: &ScannerConfig, half_counts: f64, z_half_counts: f64) -> Self {
        let (sin_a, cos_a) = s.nonorthogonality_deg.to_radians().sin_cos();
        Self {
            half_counts,
            z_half_counts,
            kx: s.sensitivity_x_nm_per_count,
            ky: s.sensitivity_y_nm_per_count,
            kz: s.sensitivity_z_nm_per_count,
            qx: s.nonlinearity_x.quadratic,
            cx: s.nonlinearity_x.cubic,
            qy: s.nonlinearity_y.quadratic,
            cy: s.nonlinearity_y.cubic,
            sin_a,
            cos_a,
            shear_x: s.shear_gradient_x,
            shear_y: s.shear_gradient_y,
            cyx: s.crosstalk_x_from_y,
            cxy: s.crosstalk_y_from_x,
            byx: s.bow_x_from_y,
            bxy: s.bow_y_from_x,
            tilt_x: s.tilt_x_from_z,
            tilt_y: s.tilt_y_from_z,
            z_coupling: s.lateral_sensitivity_change_per_z,
            bowl_curvature_per_nm: s.bowl_curvature_per_nm,
        }
    }

    /// Z sensitivity, nm/count.
    pub fn kz_nm_per_count(&self) -> f64 {
        self.kz
    }

    /// Tip position (nm, scanner frame) for effective input (counts) and Z extension (counts).
    #[inline]
    pub fn position(&self, ux: f64, uy: f64, z_counts: f64) -> [f64; 2] {
        let [ux, uy] = self.sheared(ux, uy);
        let sx = ux / self.half_counts;
        let sy = uy / self.half_counts;
        let k = 1.0 + self.z_coupling * z_counts / self.z_half_counts;
        let x = self.kx * k * ux * (1.0 + self.qx * sx + self.cx * sx * sx);
        let y = self.ky * k * uy * (1.0 + self.qy * sy + self.cy * sy * sy);
        let z_nm = self.kz * z_counts;
        [
            x + y * (self.sin_a + self.cyx + self.byx * sy) + self.tilt_x * z_nm,
            y * self.cos_a + x * (self.cxy + self.bxy * sx) + self.tilt_y * z_nm,
        ]
    }

    /// The input after the field-dependent obliquity (shear gradient):
    /// `v = u + (γx, γy)·uₓ·u_y/H`, counts.
    #[inline]
    pub fn sheared(&self, ux: f64, uy: f64) -> [f64; 2] {
        if self.shear_x == 0.0 && self.shear_y == 0.0 {
            return [ux, uy];
        }
        let p = ux * uy / self.half_counts;
        [ux + self.shear_x * p, uy + self.shear_y * p]
    }

    /// Analytic Jacobian ∂p/∂uₑ (nm/count) at effective input and Z extension:
    /// the static map's ∂p/∂v times the shear's ∂v/∂uₑ.
    pub fn jacobian(&self, ux: f64, uy: f64, z_counts: f64) -> Jacobian {
        let h = self.half_counts;
        let [vx, vy] = self.sheared(ux, uy);
        let m = self.jacobian_of_sheared(vx, vy, z_counts);
        let s = [
            [1.0 + self.shear_x * uy / h, self.shear_x * ux / h],
            [self.shear_y * uy / h, 1.0 + self.shear_y * ux / h],
        ];
        [
            [
                m[0][0] * s[0][0] + m[0][1] * s[1][0],
                m[0][0] * s[0][1] + m[0][1] * s[1][1],
            ],
            [
                m[1][0] * s[0][0] + m[1][1] * s[1][0],
                m[1][0] * s[0][1] + m[1][1] * s[1][1],
            ],
        ]
    }

    /// ∂p/∂v of the map after the shear (v = sheared input, counts).
    fn jacobian_of_sheared(&self, ux: f64, uy: f64, z_counts: f64) -> Jacobian {
        let h = self.half_counts;
        let sx = ux / h;
        let sy = uy / h;
        let k = 1.0 + self.z_coupling * z_counts / self.z_half_counts;
        let x = self.kx * k * ux * (1.0 + self.qx * sx + self.cx * sx * sx);
        let y = self.ky * k * uy * (1.0 + self.qy * sy + self.cy * sy * sy);
        let dx = self.kx * k * (1.0 + 2.0 * self.qx * sx + 3.0 * self.cx * sx * sx);
        let dy = self.ky * k * (1.0 + 2.0 * self.qy * sy + 3.0 * self.cy * sy * sy);
        [
            [
                dx,
                dy * (self.sin_a + self.cyx + self.byx * sy) + y * self.byx / h,
            ],
            [
                dx * (self.cxy + self.bxy * sx) + x * self.bxy / h,
                dy * self.cos_a,
            ],
        ]
    }

    /// Height the tube's arc adds to the image at tip position `p` (nm): `c·r²/2`.
    #[inline]
    pub fn bowl_nm(&self, p: [f64; 2]) -> f64 {
        0.5 * self.bowl_curvature_per_nm * (p[0] * p[0] + p[1] * p[1])
    }

    /// Newton inverse: the effective input that puts the tip at `target` (nm)
    /// at Z extension `z_counts`, or `None` when it does not converge.
    pub fn inverse(&self, target: [f64; 2], z_counts: f64) -> Option<[f64; 2]> {
        let z_nm = self.kz * z_counts;
        let mut u = [
            (target[0] - self.tilt_x * z_nm) / self.kx,
            (target[1] - self.tilt_y * z_nm) / self.ky,
        ];
        for _ in 0..50 {
            let p = self.position(u[0], u[1], z_counts);
            let r = [target[0] - p[0], target[1] - p[1]];
            let j = self.jacobian(u[0], u[1], z_counts);
            let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
            if !det.is_finite() || det.abs() < 1e-300 {
                return None;
            }
            let du = [
                (j[1][1] * r[0] - j[0][1] * r[1]) / det,
                (-j[1][0] * r[0] + j[0][0] * r[1]) / det,
            ];
            u[0] += du[0];
            u[1] += du[1];
            if du[0].abs() < 1e-10 && du[1].abs() < 1e-10 {
                return Some(u);
            }
        }
        let p = self.position(u[0], u[1], z_counts);
        ((p[0] - target[0]).abs() < 1e-9 && (p[1] - target[1]).abs() < 1e-9).then_some(u)
    }
}

/// Local calibration coefficients from a Jacobian, DESIGN §4:
/// `J = R(θ)·[[K̄x, K̄y·sin α], [0, K̄y·cos α]]`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Lcc {
    /// K̄x = |J·e₁|, nm/count.
    pub kx: NmPerCount,
    /// K̄y = |J·e₂|, nm/count.
    pub ky: NmPerCount,
    /// Local obliquity α (angle of the Y axis from the perpendicular to X), rad.
    pub alpha: Radians,
    /// The unobservable rotation θ = atan2(J₂₁, J₁₁), rad.
    pub theta: Radians,
}

impl Lcc {
    /// Decomposes a Jacobian (nm/count).
    pub fn from_jacobian(j: Jacobian) -> Self {
        let kx = j[0][0].hypot(j[1][0]);
        let ky = j[0][1].hypot(j[1][1]);
        let theta = j[1][0].atan2(j[0][0]);
        let (s, c) = theta.sin_cos();
        // R(−θ)·J, second column.
        let m12 = c * j[0][1] + s * j[1][1];
        let m22 = -s * j[0][1] + c * j[1][1];
        let alpha = m12.atan2(m22);
        Self {
            kx: NmPerCount(kx),
            ky: NmPerCount(ky),
            alpha: Radians(alpha),
            theta: Radians(theta),
        }
    }

    /// Rebuilds `J = R(θ)·M`.
    pub fn to_jacobian(&self) -> Jacobian {
        let (s, c) = self.theta.value().sin_cos();
        let m = spm_hal::NmPerCountMatrix::from_lcc(self.kx, self.ky, self.alpha).rows();
        [
            [c * m[0][0] - s * m[1][0], c * m[0][1] - s * m[1][1]],
            [s * m[0][0] + c * m[1][0], s * m[0][1] + c * m[1][1]],
        ]
    }

    /// The metric `G = MᵀM = JᵀJ` as (g₁₁, g₁₂, g₂₂), nm²/count².
    pub fn metric(&self) -> (f64, f64, f64) {
        let kx = self.kx.value();
        let ky = self.ky.value();
        (kx * kx, kx * ky * self.alpha.value().sin(), ky * ky)
    }
}

/// Rate-independent hysteresis of one axis: Prandtl–Ishlinskii play operators.
///
/// Each operator `yᵢ ← max(u − rᵢ, min(u + rᵢ, yᵢ))`; the axis' hysteresis
/// offset is `h = w·Σ yᵢ`. While `u` stays inside `[max(yᵢ − rᵢ), min(yᵢ + rᵢ)]`
/// (the *dead band*) no operator moves and `h` is frozen.
#[derive(Clone, Debug, PartialEq)]
pub struct PlayHysteresis {
    thresholds: Vec<f64>,
    outputs: Vec<f64>,
    weight: f64,
    offset: f64,
    band_lo: f64,
    band_hi: f64,
}

impl PlayHysteresis {
    /// Operators of a validated config, all centred on `u0` (the demagnetised state).
    pub fn new(c: &HysteresisConfig, half_counts: f64, u0: f64) -> Self {
        let n = c.operators.max(1) as usize;
        let thresholds: Vec<f64> = if c.width_fraction > 0.0 {
            (0..n)
                .map(|i| {
                    if n == 1 {
                        c.min_threshold_counts
                    } else {
                        c.min_threshold_counts
                            + (c.max_threshold_counts - c.min_threshold_counts) * i as f64
                                / (n - 1) as f64
                    }
                })
                .collect()
        } else {
            Vec::new()
        };
        let sum_r: f64 = thresholds.iter().sum();
        let weight = if sum_r > 0.0 {
            c.width_fraction * half_counts / sum_r
        } else {
            0.0
        };
        let mut h = Self {
            outputs: vec![u0; thresholds.len()],
            thresholds,
            weight,
            offset: 0.0,
            band_lo: f64::NEG_INFINITY,
            band_hi: f64::INFINITY,
        };
        h.refresh();
        h
    }

    fn refresh(&mut self) {
        self.offset = self.weight * self.outputs.iter().sum::<f64>();
        self.band_lo = f64::NEG_INFINITY;
        self.band_hi = f64::INFINITY;
        for (y, r) in self.outputs.iter().zip(&self.thresholds) {
            self.band_lo = self.band_lo.max(y - r);
            self.band_hi = self.band_hi.min(y + r);
        }
    }

    /// Applies input `u` (counts); returns the offset h (counts).
    #[inline]
    pub fn update(&mut self, u: f64) -> f64 {
        if u < self.band_lo || u > self.band_hi {
            for (y, r) in self.outputs.iter_mut().zip(&self.thresholds) {
                *y = (u - r).max((u + r).min(*y));
            }
            self.refresh();
        }
        self.offset
    }

    /// The current offset h = w·Σyᵢ, counts.
    pub fn offset(&self) -> f64 {
        self.offset
    }

    /// Total weight W = n·w (the large-signal gain excess of the major loop).
    pub fn total_weight(&self) -> f64 {
        self.weight * self.thresholds.len() as f64
    }

    /// Thresholds (counts) and the common weight.
    pub fn operator(&self) -> (Vec<f64>, f64) {
        (self.thresholds.clone(), self.weight)
    }

    /// The dead band `[lo, hi]` (counts) inside which the state is frozen.
    pub fn dead_band(&self) -> (f64, f64) {
        (self.band_lo, self.band_hi)
    }
}

/// Creep of one axis: relaxations `cₖ → w·x` with time constants τₖ
/// log-spaced from τ_min to τ_max, driven by the post-hysteresis input x.
#[derive(Clone, Debug, PartialEq)]
pub struct Creep {
    taus_s: Vec<f64>,
    weight: f64,
    states: Vec<f64>,
}

impl Creep {
    /// The chain of a validated config, settled at input `x0`.
    pub fn new(c: &CreepConfig, x0: f64) -> Self {
        let (taus_s, weight) = creep_elements(c);
        Self {
            states: vec![weight * x0; taus_s.len()],
            taus_s,
            weight,
        }
    }

    /// Time constants τₖ, s.
    pub fn time_constants_s(&self) -> &[f64] {
        &self.taus_s
    }

    /// Weight w of every element.
    pub fn weight(&self) -> f64 {
        self.weight
    }

    /// Decay factors `exp(−dt/τₖ)` for a time step.
    pub fn decays(&self, dt_s: f64) -> Vec<f64> {
        self.taus_s.iter().map(|t| (-dt_s / t).exp()).collect()
    }

    /// Advances by a step whose decay factors are `decays`, input `x` held constant.
    #[inline]
    pub fn advance_with(&mut self, x: f64, decays: &[f64]) -> f64 {
        let target = self.weight * x;
        let n = self.states.len().min(decays.len());
        let (states, decays) = (&mut self.states[..n], &decays[..n]);
        for (c, d) in states.iter_mut().zip(decays) {
            *c = target + (*c - target) * d;
        }
        // Four partial sums let the compiler vectorise the reduction.
        let mut acc = [0.0f64; 4];
        let chunks = states.chunks_exact(4);
        let rest: f64 = chunks.remainder().iter().sum();
        for c in chunks {
            acc[0] += c[0];
            acc[1] += c[1];
            acc[2] += c[2];
            acc[3] += c[3];
        }
        (acc[0] + acc[1]) + (acc[2] + acc[3]) + rest
    }

    /// Coefficients of `n` steps with decay factors `decays` and a ramp input
    /// `x_j = a + j·b` (j = 0 … n−1): after them `cₖ = Aₖ·cₖ + Pₖ·a + Qₖ·b`.
    pub fn ramp_coefficients(&self, decays: &[f64], n: usize) -> Vec<[f64; 3]> {
        decays
            .iter()
            .map(|&d| {
                let (mut a, mut p, mut q) = (1.0, 0.0, 0.0);
                let g = (1.0 - d) * self.weight;
                for j in 0..n {
                    a *= d;
                    p = d * p + g;
                    q = d * q + g * j as f64;
                }
                [a, p, q]
            })
            .collect()
    }

    /// Applies [`ramp_coefficients`](Self::ramp_coefficients); returns the offset.
    pub fn advance_ramp(&mut self, coefficients: &[[f64; 3]], a: f64, b: f64) -> f64 {
        for (c, k) in self.states.iter_mut().zip(coefficients) {
            *c = k[0] * *c + k[1] * a + k[2] * b;
        }
        self.offset()
    }

    /// Advances by `dt_s` with input `x` held constant; returns the offset.
    pub fn advance(&mut self, x: f64, dt_s: f64) -> f64 {
        let target = self.weight * x;
        for (c, t) in self.states.iter_mut().zip(&self.taus_s) {
            *c = target + (*c - target) * (-dt_s / t).exp();
        }
        self.offset()
    }

    /// The creep offset Σcₖ, counts.
    pub fn offset(&self) -> f64 {
        self.states.iter().sum()
    }

    /// W = Σ weights: the settled creep gain.
    pub fn total_weight(&self) -> f64 {
        self.weight * self.taus_s.len() as f64
    }

    /// S(t) = w·Σ(1 − exp(−t/τₖ)): the fractional extra displacement a step
    /// from a settled state has gained `t` seconds after it.
    pub fn step_response_fraction(&self, t_s: f64) -> f64 {
        step_fraction(&self.taus_s, self.weight, t_s)
    }
}

fn step_fraction(taus: &[f64], weight: f64, t_s: f64) -> f64 {
    weight * taus.iter().map(|tau| 1.0 - (-t_s / tau).exp()).sum::<f64>()
}

/// Time constants and weight of a creep chain: τ log-spaced with
/// `elements_per_decade`, weight `w = γ / (m − γ·A)`, `A = Σ(1 − e^{−0.1 s/τₖ})`,
/// so that `d ΔL / d lg t = γ·ΔL(0.1 s)` between the extreme time constants.
pub fn creep_elements(c: &CreepConfig) -> (Vec<f64>, f64) {
    if c.log_slope_per_decade <= 0.0 {
        return (Vec::new(), 0.0);
    }
    let m = f64::from(c.elements_per_decade.max(1));
    let decades = (c.max_time_constant_s / c.min_time_constant_s).log10();
    let n = (decades * m).round() as usize + 1;
    let taus: Vec<f64> = (0..n)
        .map(|k| c.min_time_constant_s * 10f64.powf(k as f64 / m))
        .collect();
    let a: f64 = taus.iter().map(|t| 1.0 - (-0.1 / t).exp()).sum();
    let gamma = c.log_slope_per_decade;
    let weight = gamma / (m - gamma * a);
    (taus, weight)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::config::SimConfig;

    #[test]
    fn inverse_round_trips() {
        let c = SimConfig::room_temperature_tube();
        let m = StaticMap::new(&c.scanner, 32768.0, 32768.0);
        for (x, y) in [(0.0, 0.0), (30000.0, -31000.0), (-20000.0, 12345.0)] {
            let p = m.position(x, y, 5000.0);
            let u = m.inverse(p, 5000.0).unwrap();
            assert!((u[0] - x).abs() < 1e-6 && (u[1] - y).abs() < 1e-6);
        }
    }

    #[test]
    fn play_operators_freeze_inside_the_dead_band() {
        let c = SimConfig::room_temperature_tube();
        let mut h = PlayHysteresis::new(&c.scanner.hysteresis_x, 32768.0, 0.0);
        h.update(5000.0);
        let after_rise = h.update(4000.0);
        for u in [4100.0, 4990.0, 4300.0, 3980.0] {
            assert_eq!(h.update(u), after_rise);
        }
    }
}
