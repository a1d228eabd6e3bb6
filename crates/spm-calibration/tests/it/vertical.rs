//! The vertical axis in the controller (issue 15), on the simulated microscope: where no
//! step is in reach the record carries no Kz and the run's tally says why (nothing is
//! invented); where a step is, the record carries Kz (and where it was measured) within the
//! step measurement's accuracy of the oracle's true Kz.
#![allow(clippy::unwrap_used)]

use spm_calibration::{
    Calibrator, KzOutcome, MemoryStore, NoObserver, PlanConfig, RunOptions, StepSearchConfig,
};
use spm_hal::{CountPoint, Microscope, MoveRequest, Seconds};
use spm_sim::{SimConfig, Simulator, StepEdgeConfig, SurfaceConfig};

fn steps() -> StepSearchConfig {
    StepSearchConfig {
        nominal_kz_nm_per_count: 0.004,
        height_tolerance_fraction: 0.3,
        window_size_counts: 1500.0,
        window_pixels: 96,
        window_lines: 32,
        edge_mask_nm: 3.0,
        search_radius_counts: 1500.0,
        level_size_counts: 400.0,
        level_pixels: 16,
    }
}

fn plan() -> PlanConfig {
    let mut plan = PlanConfig::hopg_small_net();
    plan.standard.step_height_nm = Some(0.3354);
    plan.steps = Some(steps());
    plan.validate().unwrap();
    plan
}

#[test]
fn no_step_in_reach_leaves_kz_unset_and_says_so() {
    // A terrace without steps: nothing within any node's search windows.
    let mut config = SimConfig::room_temperature_tube().without_random_faults();
    if let SurfaceConfig::Hopg(h) = &mut config.surface {
        h.steps.clear();
    }
    let mut sim = Simulator::new(config).unwrap();
    let mut store = MemoryStore::default();
    let mut observer = NoObserver;
    let report = Calibrator::new(&mut sim, &mut store, &mut observer, plan())
        .unwrap()
        .run(&RunOptions {
            run_id: "no-step".into(),
            start_unix_s: 1.8e9,
            config_text: String::new(),
        })
        .unwrap();
    assert!(report.nodes_done >= 8, "{report:?}");
    assert_eq!(report.kz.measured, 0, "{:?}", report.kz);
    assert_eq!(
        report.kz.no_step_in_reach + report.kz.only_rejected_steps + report.kz.failed,
        report.nodes_done,
        "{:?}",
        report.kz
    );
    for r in &store.records {
        assert_eq!(
            (r.kz_nm_per_count, r.u_kz_nm_per_count, r.kz_x_counts),
            (None, None, None),
            "nothing invented: {r:?}"
        );
    }
}

#[test]
fn a_step_beside_the_node_gives_kz_and_a_double_step_is_rejected_with_its_reason() {
    let mut config = SimConfig::room_temperature_tube().without_random_faults();
    if let SurfaceConfig::Hopg(h) = &mut config.surface {
        h.domains.clear();
        h.steps = vec![
            // A monatomic edge near x = +15 nm, a double step (two edges 0.8 nm apart) near
            // x = -600 nm.
            StepEdgeConfig {
                point_x_nm: 15.0,
                point_y_nm: 0.0,
                direction_deg: 90.0,
                width_nm: 0.2,
            },
            StepEdgeConfig {
                point_x_nm: -600.0,
                point_y_nm: 0.0,
                direction_deg: 90.0,
                width_nm: 0.2,
            },
            StepEdgeConfig {
                point_x_nm: -599.2,
                point_y_nm: 0.0,
                direction_deg: 90.0,
                width_nm: 0.2,
            },
        ];
    }
    let mut sim = Simulator::new(config).unwrap();
    let motion = spm_calibration::vertical::ScanMotion {
        pixel_dwell_s: 1e-4,
        move_speed_counts_per_s: 20000.0,
        settle_s: 0.01,
    };
    for (target_nm, expect_measured) in [(15.0, true), (-600.0, false)] {
        // Put the node 10 nm beside the edge.
        let at = spm_hal::NmPoint::from_nm(target_nm - 10.0, 0.0);
        for _ in 0..2 {
            let node = sim.oracle().commanded_for_sample_point(at).unwrap();
            sim.move_to(MoveRequest {
                target: node,
                speed: spm_hal::CountsPerSecond(20000.0),
                settle: Seconds(0.5),
            })
            .unwrap();
        }
        let node: CountPoint = sim.position().unwrap();
        let search = spm_calibration::vertical::measure_node(
            &mut sim,
            node,
            node,
            &steps(),
            0.3354,
            0.02,
            motion,
        );
        match (&search.kz, expect_measured) {
            (
                KzOutcome::Measured {
                    kz_nm_per_count,
                    edge_x_counts,
                    edge_y_counts,
                    ..
                },
                true,
            ) => {
                let edge = CountPoint::from_counts(*edge_x_counts, *edge_y_counts);
                let truth = sim.oracle().vertical().kz_now(edge).value();
                assert!(
                    (kz_nm_per_count / truth - 1.0).abs() < 0.005,
                    "Kz {kz_nm_per_count} vs {truth}"
                );
            }
            (KzOutcome::NoStepInReach { rejected, .. }, false) => {
                assert!(
                    rejected.iter().any(|r| r.starts_with("double_step")),
                    "{rejected:?}"
                );
            }
            (other, _) => panic!("at {target_nm} nm: {other:?}"),
        }
    }
}
