//! The simulator as a ground truth ([`spm_hal::truth`]): the oracle behind the traits a
//! report uses, so that reports never name the simulator.

use spm_hal::truth::{GratingSample, GroundTruth, SimulatedInstrument, TrueLcc};
use spm_hal::{CountPoint, Counts, NmPoint, NmVelocity, Seconds};

use crate::{LatticeConfig, SimError, Simulator, SurfaceConfig};

impl GroundTruth for Simulator {
    fn true_lcc(&self, commanded: CountPoint, z: Counts) -> TrueLcc {
        let lcc = self.oracle().true_lcc(commanded, z);
        TrueLcc {
            kx_nm_per_count: lcc.kx.value(),
            ky_nm_per_count: lcc.ky.value(),
            alpha_rad: lcc.alpha.value(),
        }
    }
    fn z_now(&self) -> Counts {
        self.oracle().z_now()
    }
    fn now(&self) -> Seconds {
        self.oracle().now()
    }
    fn drift_velocity(&self, t: Seconds) -> NmVelocity {
        self.oracle().drift_velocity(t)
    }
    fn reference_gain(&self) -> [f64; 2] {
        let (gx, gy) = self.oracle().reference_gain();
        [gx, gy]
    }
    fn vertical(&self) -> Option<&dyn spm_hal::truth::VerticalTruth> {
        Some(self)
    }
}

impl spm_hal::truth::VerticalTruth for Simulator {
    fn kz_at(&self, commanded: CountPoint, z: Counts, state: spm_hal::truth::LateralState) -> f64 {
        self.vertical_in(state).kz_at(commanded, z).value()
    }
    fn flat_sample_z_reading(
        &self,
        commanded: CountPoint,
        coarse_steps: i64,
        state: spm_hal::truth::LateralState,
    ) -> Counts {
        self.vertical_in(state)
            .flat_sample_z_reading(commanded, coarse_steps)
    }
    fn true_lcc_at_reading(&self, commanded: CountPoint, z: Counts) -> TrueLcc {
        let lcc = self.oracle().vertical().true_lcc_at_reading(commanded, z);
        TrueLcc {
            kx_nm_per_count: lcc.kx.value(),
            ky_nm_per_count: lcc.ky.value(),
            alpha_rad: lcc.alpha.value(),
        }
    }
}

impl Simulator {
    fn vertical_in(&self, state: spm_hal::truth::LateralState) -> crate::VerticalOracle<'_> {
        match state {
            spm_hal::truth::LateralState::CreepSettled => self.oracle().vertical(),
            spm_hal::truth::LateralState::JustMoved => self.oracle().vertical().just_moved(),
        }
    }
}

/// Salt of the grating twin's seed: its own session on its own sample.
const GRATING_SEED_SALT: u64 = 0x6772_6174_696e_6721;

impl SimulatedInstrument for Simulator {
    fn record_tip_positions(&mut self, on: bool) {
        Simulator::record_tip_positions(self, on);
    }
    fn record_backward_aside(&mut self, on: bool) {
        Simulator::record_backward_aside(self, on);
    }
    fn last_scan_tip_positions(&self) -> Vec<NmPoint> {
        self.oracle().last_scan_tip_positions()
    }
    fn last_scan_effective_inputs(&self) -> Vec<CountPoint> {
        self.oracle().last_scan_effective_inputs()
    }
    fn drift_displacement(&self, t: Seconds) -> NmPoint {
        self.oracle().drift_displacement(t)
    }
    fn grating_twin(&self, grating: &GratingSample) -> Result<Self, SimError> {
        let mut config = self.config().clone().without_random_faults();
        config.seed ^= GRATING_SEED_SALT;
        config.surface = SurfaceConfig::SquareLattice(LatticeConfig {
            lattice_constant_nm: grating.pitch_nm,
            feature_height_nm: grating.height_nm,
            feature_sigma_nm: grating.sigma_nm,
            rotation_deg: grating.rotation_deg,
        });
        Ok(Simulator::new(config)?)
    }
}
