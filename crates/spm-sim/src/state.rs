//! The simulator's state: what the instrument is (its configuration, surface, static map
//! and Z characteristic) and where it stands (scanner, drift, clock, feedback, tip, fault log
//! and the last scan's truth). The physics (`sim`) advances it; the oracle (`oracle`,
//! `vertical::VerticalOracle`) reads it and nothing else. Layers: config → physics
//! (`scanner`, `drift`, `surface`, `vertical`) → state → oracle, and `sim` on top.

use crate::config::SimConfig;
use crate::drift::Drift;
use crate::fault::FaultEvent;
use crate::scanner::{Creep, PlayHysteresis, StaticMap};
use crate::surface::Surface;
use crate::vertical::ZMap;

/// The tip's imaging state (changed by tip-change faults).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct TipState {
    pub contrast: f64,
    pub ghost_offset: [f64; 2],
    pub ghost_amplitude: f64,
}

impl TipState {
    pub(crate) const PRISTINE: Self = Self {
        contrast: 1.0,
        ghost_offset: [0.0; 2],
        ghost_amplitude: 0.0,
    };
}

/// The scanner's dynamic state: hysteresis and creep of both lateral axes.
#[derive(Clone, Debug)]
pub(crate) struct ScannerState {
    pub hysteresis: [PlayHysteresis; 2],
    pub creep: [Creep; 2],
    /// DAC value applied now (after quantisation), counts.
    pub applied: [f64; 2],
    /// Post-hysteresis input x = u + h, counts.
    pub input: [f64; 2],
    /// Creep offsets, counts.
    pub creep_offset: [f64; 2],
}

impl ScannerState {
    #[inline]
    pub(crate) fn set(&mut self, u: [f64; 2]) {
        self.applied = u;
        self.input = [
            u[0] + self.hysteresis[0].update(u[0]),
            u[1] + self.hysteresis[1].update(u[1]),
        ];
    }

    pub(crate) fn advance(&mut self, dt_s: f64) {
        if dt_s > 0.0 {
            self.creep_offset = [
                self.creep[0].advance(self.input[0], dt_s),
                self.creep[1].advance(self.input[1], dt_s),
            ];
        }
    }

    #[inline]
    pub fn effective(&self) -> [f64; 2] {
        [
            self.input[0] + self.creep_offset[0],
            self.input[1] + self.creep_offset[1],
        ]
    }
}

/// The state the physics advances and the oracle reads.
#[derive(Clone, Debug)]
pub(crate) struct SimState {
    pub(crate) config: SimConfig,
    pub(crate) surface: Surface,
    pub(crate) map: StaticMap,
    /// The Z manipulator's characteristic (extension ⇄ Z counts).
    pub(crate) zmap: ZMap,
    pub(crate) scanner: ScannerState,
    pub(crate) drift: Drift,
    /// The instrument clock, s.
    pub(crate) time_s: f64,
    /// Feedback output: Z reading without noise, nm (Z counts × Kz).
    pub(crate) z_nm: f64,
    pub(crate) tip: TipState,
    /// Every fault that fired, in order.
    pub(crate) log: Vec<FaultEvent>,
    /// True tip positions (scanner frame, nm) of the last scan's forward
    /// pixels, when recording is on (oracle only).
    pub(crate) tip_trace: Option<Vec<[f64; 2]>>,
    /// Effective inputs (counts) of the same pixels, when recording is on.
    pub(crate) effective_trace: Option<Vec<[f64; 2]>>,
}

impl SimState {
    /// Tip position in the scanner frame now (nm).
    pub(crate) fn scanner_position_nm(&self) -> [f64; 2] {
        let ue = self.scanner.effective();
        self.map.position(ue[0], ue[1], self.z_counts_noiseless())
    }

    /// The static map's Z argument: the extension in nominal counts (extension / Kz₀).
    pub(crate) fn z_counts_noiseless(&self) -> f64 {
        self.z_nm / self.map.kz_nm_per_count()
    }

    /// The Z reading without noise (counts) through the Z characteristic.
    pub(crate) fn z_reading_noiseless(&self) -> f64 {
        self.zmap.counts_of(self.z_nm, self.scanner.effective())
    }
}
