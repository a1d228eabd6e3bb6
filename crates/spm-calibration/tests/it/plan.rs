//! Net plans: serpentine order, alternating directions, node counts, stable indices.
#![allow(clippy::unwrap_used)]

use spm_calibration::{NetGeometry, NetPlan, PlanConfig, ZLevel};
use spm_hal::mock::ScriptedMicroscope;
use std::collections::HashSet;

fn level(z: i64, coarse: Option<i64>) -> ZLevel {
    ZLevel {
        nominal_z_counts: z,
        coarse_steps: coarse,
    }
}

fn lateral(nx: i64, ny: i64, planes: usize) -> NetGeometry {
    NetGeometry::LateralPlanes {
        x_min_counts: -1000,
        x_max_counts: -1000 + (nx - 1) * 500,
        y_min_counts: 0,
        y_max_counts: (ny - 1) * 500 + 499, // leftover < step: no extra node
        step_counts: 500,
        z_planes: (0..planes as i64)
            .map(|k| level(k * 100, Some(k * 10)))
            .collect(),
    }
}

#[test]
fn lateral_planes_are_a_continuous_serpentine() {
    let plan = NetPlan::new(&lateral(4, 3, 2), 1).unwrap();
    assert_eq!(plan.nodes_per_repeat(), 4 * 3 * 2);
    // Every move is one net step within a plane, or a pure Z move between planes.
    for w in plan.nodes.windows(2) {
        let (a, b) = (w[0], w[1]);
        let lateral = (a.x_counts - b.x_counts).abs() + (a.y_counts - b.y_counts).abs();
        if a.iz == b.iz {
            assert_eq!(lateral, 500, "{a:?} -> {b:?}");
        } else {
            assert_eq!(lateral, 0, "plane change must not move laterally");
        }
    }
    // Adjacent rows run in opposite x directions.
    let row_dir = |iz: u32, iy: u32| {
        let row: Vec<_> = plan
            .nodes
            .iter()
            .filter(|n| n.iz == iz && n.iy == iy)
            .collect();
        (row[row.len() - 1].x_counts - row[0].x_counts).signum()
    };
    assert_eq!(row_dir(0, 0), 1);
    assert_eq!(row_dir(0, 1), -1);
    assert_eq!(row_dir(0, 2), 1);
    // Adjacent planes run in opposite y directions.
    let plane_y = |iz: u32| {
        let ys: Vec<_> = plan
            .nodes
            .iter()
            .filter(|n| n.iz == iz)
            .map(|n| n.y_counts)
            .collect();
        (ys[ys.len() - 1] - ys[0]).signum()
    };
    assert_eq!(plane_y(0), 1);
    assert_eq!(plane_y(1), -1);
    // Each physical node exactly once.
    let unique: HashSet<_> = plan.nodes.iter().map(|n| (n.ix, n.iy, n.iz)).collect();
    assert_eq!(unique.len(), plan.nodes.len());
    assert_eq!(plan.nodes[0].coarse_steps, Some(0));
}

#[test]
fn vertical_planes_traverse_z_at_fixed_x_and_y() {
    let geometry = NetGeometry::VerticalPlanes {
        x_min_counts: 0,
        x_max_counts: 1000,
        step_counts: 500,
        y_planes_counts: vec![-2000, 2000],
        z_levels: vec![
            level(0, Some(0)),
            level(100, Some(50)),
            level(200, Some(100)),
        ],
    };
    let plan = NetPlan::new(&geometry, 1).unwrap();
    assert_eq!(plan.nodes_per_repeat(), 3 * 2 * 3);
    // The innermost loop is Z: the first three nodes share x and y.
    let first: Vec<_> = plan.nodes[..3]
        .iter()
        .map(|n| (n.x_counts, n.y_counts, n.z_counts))
        .collect();
    assert_eq!(first, vec![(0, -2000, 0), (0, -2000, 100), (0, -2000, 200)]);
    // The next column runs down in Z.
    let second: Vec<_> = plan.nodes[3..6]
        .iter()
        .map(|n| (n.x_counts, n.z_counts))
        .collect();
    assert_eq!(second, vec![(500, 200), (500, 100), (500, 0)]);
    // The second plane runs back in x.
    let plane2_x: Vec<_> = plan.nodes[9..].iter().map(|n| n.x_counts).collect();
    assert_eq!(plane2_x.first(), Some(&1000));
    assert_eq!(plane2_x.last(), Some(&0));
    assert!(plan.nodes[9..].iter().all(|n| n.y_counts == 2000));
}

#[test]
fn repeats_alternate_direction_and_indices_are_stable() {
    let geometry = lateral(3, 3, 1);
    let plan = NetPlan::new(&geometry, 3).unwrap();
    assert_eq!(plan.total_visits(), 27);
    let visits: Vec<_> = plan.visits().collect();
    assert_eq!(visits.len(), 27);
    // Repeat 1 starts where repeat 0 ended and runs backwards.
    assert_eq!(visits[8].grid, visits[9].grid);
    assert_eq!(visits[9].grid, plan.nodes[8]);
    assert_eq!(visits[17].grid, plan.nodes[0]);
    assert_eq!(visits[18].grid, plan.nodes[0]);
    // Indices are (repeat, position in the repeat), in execution order.
    for (k, v) in visits.iter().enumerate() {
        assert_eq!(v.repeat_index as usize, k / 9);
        assert_eq!(v.node_index as usize, k % 9);
        assert_eq!(plan.visit(v.repeat_index, v.node_index), Some(*v));
    }
    // Building the plan again gives the same visits (stable across runs).
    let again: Vec<_> = NetPlan::new(&geometry, 3).unwrap().visits().collect();
    assert_eq!(visits, again);
    assert!(plan.visit(3, 0).is_none());
    assert!(plan.visit(0, 9).is_none());
}

#[test]
fn invalid_plans_are_typed_errors() {
    let NetGeometry::LateralPlanes { z_planes, .. } = lateral(2, 2, 1) else {
        unreachable!()
    };
    let zero_step = NetGeometry::LateralPlanes {
        x_min_counts: 0,
        x_max_counts: 10,
        y_min_counts: 0,
        y_max_counts: 10,
        step_counts: 0,
        z_planes: z_planes.clone(),
    };
    assert!(NetPlan::new(&zero_step, 1).is_err());
    assert!(NetPlan::new(&lateral(2, 2, 1), 0).is_err());
    let no_planes = NetGeometry::LateralPlanes {
        x_min_counts: 0,
        x_max_counts: 10,
        y_min_counts: 0,
        y_max_counts: 10,
        step_counts: 5,
        z_planes: vec![],
    };
    assert!(NetPlan::new(&no_planes, 1).is_err());
}

#[test]
fn the_small_hopg_plan_is_a_centred_3x3_net() {
    let config = PlanConfig::hopg_small_net();
    let caps = ScriptedMicroscope::default_capabilities();
    let geometry = config.net.geometry(&caps).unwrap();
    let plan = NetPlan::new(&geometry, config.repeats).unwrap();
    assert_eq!(plan.nodes_per_repeat(), 9);
    let xs: HashSet<_> = plan.nodes.iter().map(|n| n.x_counts).collect();
    let mut xs: Vec<_> = xs.into_iter().collect();
    xs.sort();
    assert_eq!(xs.len(), 3);
    // Centred: symmetric about the field centre (−0.5) within one count.
    assert!((xs[0] + xs[2] + 1).abs() <= 1, "{xs:?}");
    assert!(xs[0] >= -32768 + config.net.margin_counts);
}

#[test]
fn the_shipped_plan_file_parses() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../configs/plan-hopg-small.toml"
    );
    let plan = PlanConfig::from_file(path).unwrap();
    assert_eq!(plan, PlanConfig::hopg_small_net());
}

mod properties {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn any_lateral_net_is_a_unit_step_serpentine(
            nx in 1i64..8, ny in 1i64..8, planes in 1usize..4, repeats in 1u32..4,
            step in 1i64..5000, x0 in -30000i64..0, y0 in -30000i64..0,
        ) {
            let geometry = NetGeometry::LateralPlanes {
                x_min_counts: x0,
                x_max_counts: x0 + (nx - 1) * step,
                y_min_counts: y0,
                y_max_counts: y0 + (ny - 1) * step,
                step_counts: step,
                z_planes: (0..planes as i64).map(|k| level(k, None)).collect(),
            };
            let plan = NetPlan::new(&geometry, repeats).unwrap();
            prop_assert_eq!(plan.nodes_per_repeat(), (nx * ny) as usize * planes);
            let visits: Vec<_> = plan.visits().collect();
            prop_assert_eq!(visits.len(), plan.total_visits());
            for w in visits.windows(2) {
                let (a, b) = (w[0].grid, w[1].grid);
                let lateral = (a.x_counts - b.x_counts).abs() + (a.y_counts - b.y_counts).abs();
                // One net step, a plane change in place, or the turn between repeats.
                prop_assert!(lateral == step || (lateral == 0 && (a.iz != b.iz || a == b)));
            }
            let unique: HashSet<_> = plan.nodes.iter().map(|n| (n.ix, n.iy, n.iz)).collect();
            prop_assert_eq!(unique.len(), plan.nodes.len());
        }
    }
}
