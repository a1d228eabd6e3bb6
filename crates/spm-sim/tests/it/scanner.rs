//! Scanner truth: creep follows the configured log law, a full-range cycle
//! shows the configured hysteresis width (through the oracle's true
//! position), the oracle's LCCs equal a finite-difference Jacobian of the
//! static map, small frozen-state moves see exactly that Jacobian, and the
//! J = R(θ)·M decomposition round-trips (proptest).
#![allow(clippy::unwrap_used, clippy::needless_range_loop)]

use proptest::prelude::*;
use spm_hal::{CountPoint, Counts, Microscope, MoveRequest, NmPerCount, Radians, Seconds};
use spm_sim::{Lcc, SimConfig, Simulator};

fn move_fast(sim: &mut Simulator, x: f64, y: f64) {
    sim.move_to(MoveRequest {
        target: CountPoint::from_counts(x, y),
        speed: spm_hal::CountsPerSecond(1e8),
        settle: Seconds(0.0),
    })
    .unwrap();
}

#[test]
fn creep_after_a_step_follows_the_log_law() {
    let gamma = 0.015;
    let mut config = SimConfig::ideal();
    config.scanner.creep.log_slope_per_decade = gamma;
    config.scanner.creep.elements_per_decade = 3;
    let mut sim = Simulator::new(config).unwrap();
    let before = sim.oracle().tip_scanner_position_now().x.value();
    move_fast(&mut sim, 8000.0, 0.0);
    let t_step = sim.oracle().now().value();
    let dl_at = |sim: &mut Simulator, t: f64| {
        let now = sim.oracle().now().value();
        sim.wait(Seconds(t_step + t - now)).unwrap();
        sim.oracle().tip_scanner_position_now().x.value() - before
    };
    let dl01 = dl_at(&mut sim, 0.1);
    // Validity range 3·τ_min … τ_max/3 (τ_min = 0.02 s, τ_max = 2000 s).
    for t in [0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0] {
        let dl = dl_at(&mut sim, t);
        let law = 1.0 + gamma * (t / 0.1f64).log10();
        let ratio = dl / dl01;
        assert!(
            (ratio - law).abs() < 1e-3,
            "t = {t} s: ΔL/ΔL(0.1 s) = {ratio}, law {law}"
        );
    }
    // The oracle's step response agrees with the position it reports.
    let s01 = sim.oracle().creep_step_response(Seconds(0.1));
    assert!((dl01 - 8000.0 * 0.02 * (1.0 + s01)).abs() < 1e-3);
}

#[test]
fn a_full_range_cycle_shows_the_configured_hysteresis_width() {
    let width = 0.04;
    let mut config = SimConfig::ideal();
    config.scanner.hysteresis_x.width_fraction = width;
    config.scanner.hysteresis_x.operators = 16;
    let mut sim = Simulator::new(config).unwrap();
    let half = 32768.0;
    move_fast(&mut sim, half - 1.0, 0.0);
    move_fast(&mut sim, -half, 0.0);
    move_fast(&mut sim, 0.0, 0.0);
    let ascending = sim.oracle().tip_scanner_position_now().x.value();
    move_fast(&mut sim, half - 1.0, 0.0);
    move_fast(&mut sim, 0.0, 0.0);
    let descending = sim.oracle().tip_scanner_position_now().x.value();
    let measured = (descending - ascending) / (0.02 * 2.0 * half);
    assert!(
        (measured / width - 1.0).abs() < 1e-3,
        "width {measured} vs configured {width}"
    );
    // A loop of tens of counts after a reversal does not move the state.
    move_fast(&mut sim, 30.0, 0.0);
    let a = sim.oracle().tip_scanner_position_now().x.value();
    move_fast(&mut sim, 0.0, 0.0);
    let b = sim.oracle().tip_scanner_position_now().x.value();
    assert!((a - b - 30.0 * 0.02).abs() < 1e-9);
    assert_eq!(b, descending);
}

#[test]
fn oracle_lccs_equal_a_finite_difference_jacobian_of_the_static_map() {
    let sim = Simulator::new(SimConfig::room_temperature_tube()).unwrap();
    let oracle = sim.oracle();
    let h = 0.5;
    for (x, y, z) in [
        (0.0, 0.0, 10000.0),
        (30000.0, -25000.0, 10000.0),
        (-31000.0, 31000.0, -20000.0),
        (12345.0, 6789.0, 0.0),
    ] {
        let f = |dx: f64, dy: f64| {
            oracle.static_map(CountPoint::from_counts(x + dx, y + dy), Counts(z))
        };
        let jx = [
            (f(h, 0.0).x.value() - f(-h, 0.0).x.value()) / (2.0 * h),
            (f(h, 0.0).y.value() - f(-h, 0.0).y.value()) / (2.0 * h),
        ];
        let jy = [
            (f(0.0, h).x.value() - f(0.0, -h).x.value()) / (2.0 * h),
            (f(0.0, h).y.value() - f(0.0, -h).y.value()) / (2.0 * h),
        ];
        let fd = [[jx[0], jy[0]], [jx[1], jy[1]]];
        let analytic = oracle.jacobian(CountPoint::from_counts(x, y), Counts(z));
        for i in 0..2 {
            for j in 0..2 {
                assert!(
                    (fd[i][j] - analytic[i][j]).abs() < 1e-9,
                    "{fd:?} vs {analytic:?}"
                );
            }
        }
        let from_fd = Lcc::from_jacobian(fd);
        let lcc = oracle.lcc(CountPoint::from_counts(x, y), Counts(z));
        assert!((from_fd.kx.value() / lcc.kx.value() - 1.0).abs() < 1e-8);
        assert!((from_fd.ky.value() / lcc.ky.value() - 1.0).abs() < 1e-8);
        assert!((from_fd.alpha.value() - lcc.alpha.value()).abs() < 1e-8);
        // K̄x, K̄y, α from the definitions of DESIGN §4.
        assert!((lcc.kx.value() - fd[0][0].hypot(fd[1][0])).abs() < 1e-9);
        assert!((lcc.ky.value() - fd[0][1].hypot(fd[1][1])).abs() < 1e-9);
    }
    // The shipped nonlinearity is 2–25 % at the field edges.
    let centre = oracle
        .lcc(CountPoint::from_counts(0.0, 0.0), Counts(0.0))
        .kx
        .value();
    let edge = oracle
        .lcc(CountPoint::from_counts(32767.0, 0.0), Counts(0.0))
        .kx
        .value();
    let change = edge / centre - 1.0;
    assert!((0.02..=0.25).contains(&change), "{change}");
}

#[test]
fn small_frozen_moves_see_exactly_the_oracle_jacobian() {
    let mut config = SimConfig::room_temperature_tube().without_random_faults();
    config.scanner.creep.log_slope_per_decade = 0.0;
    config.drift.velocity_x_nm_per_s = 0.0;
    config.drift.velocity_y_nm_per_s = 0.0;
    config.drift.warmup_amplitude_x_nm = 0.0;
    config.drift.warmup_amplitude_y_nm = 0.0;
    config.drift.velocity_random_walk_nm_per_s_per_sqrt_s = 0.0;
    config.drift.jump_rate_per_s = 0.0;
    config.measurement.feedback_time_constant_s = 0.0;
    config.measurement.z_white_noise_nm = 0.0;
    config.measurement.z_flicker_noise_nm = 0.0;
    config.measurement.lateral_jitter_nm = 0.0;
    config.scanner.tilt_x_from_z = 0.0;
    config.scanner.tilt_y_from_z = 0.0;
    config.scanner.lateral_sensitivity_change_per_z = 0.0;
    let mut sim = Simulator::new(config).unwrap();
    // Node approach with an overshoot so that both axes have reversed.
    move_fast(&mut sim, 21000.0, -15000.0);
    move_fast(&mut sim, 20000.0, -14000.0);
    let before = sim.oracle().tip_scanner_position_now();
    // Jacobian at the midpoint of the move: the comparison is exact to third order.
    let expected = sim
        .oracle()
        .lcc_now(CountPoint::from_counts(20010.0, -13992.5))
        .to_jacobian();
    move_fast(&mut sim, 20020.0, -13985.0);
    let after = sim.oracle().tip_scanner_position_now();
    let (du, dv) = (20.0, 15.0);
    let predicted = [
        expected[0][0] * du + expected[0][1] * dv,
        expected[1][0] * du + expected[1][1] * dv,
    ];
    let moved = [
        after.x.value() - before.x.value(),
        after.y.value() - before.y.value(),
    ];
    for a in 0..2 {
        // Midpoint rule: third-order error, ≪ 1e-5 relative.
        assert!(
            (moved[a] - predicted[a]).abs() < 1e-5 * predicted[0].abs().max(predicted[1].abs()),
            "{moved:?} vs {predicted:?}"
        );
    }
}

proptest! {
    #[test]
    fn lcc_decomposition_reconstructs_the_jacobian(
        kx in 1e-3f64..0.1, ky in 1e-3f64..0.1,
        alpha in -0.6f64..0.6, theta in -3.1f64..3.1,
    ) {
        let lcc = Lcc { kx: NmPerCount(kx), ky: NmPerCount(ky), alpha: Radians(alpha), theta: Radians(theta) };
        let j = lcc.to_jacobian();
        let back = Lcc::from_jacobian(j);
        prop_assert!((back.kx.value() - kx).abs() < 1e-12);
        prop_assert!((back.ky.value() - ky).abs() < 1e-12);
        prop_assert!((back.alpha.value() - alpha).abs() < 1e-9);
        prop_assert!((back.theta.value() - theta).abs() < 1e-9);
        // The metric G = JᵀJ = MᵀM.
        let (g11, g12, g22) = back.metric();
        prop_assert!((g11 - (j[0][0] * j[0][0] + j[1][0] * j[1][0])).abs() < 1e-12);
        prop_assert!((g12 - (j[0][0] * j[0][1] + j[1][0] * j[1][1])).abs() < 1e-12);
        prop_assert!((g22 - (j[0][1] * j[0][1] + j[1][1] * j[1][1])).abs() < 1e-12);
    }

    #[test]
    fn any_orientation_preserving_jacobian_round_trips(
        a in -0.1f64..0.1, b in -0.1f64..0.1, c in -0.1f64..0.1, d in -0.1f64..0.1,
    ) {
        prop_assume!(a * d - b * c > 1e-6);
        let j = [[a, b], [c, d]];
        let back = Lcc::from_jacobian(j).to_jacobian();
        for i in 0..2 {
            for k in 0..2 {
                prop_assert!((back[i][k] - j[i][k]).abs() < 1e-12);
            }
        }
    }
}

#[test]
fn the_unrecorded_retrace_fast_path_matches_full_simulation() {
    let mut config = SimConfig::ideal();
    config.scanner.creep.log_slope_per_decade = 0.015;
    config.scanner.creep.elements_per_decade = 3;
    config.scanner.hysteresis_x.width_fraction = 0.04;
    config.scanner.hysteresis_x.operators = 16;
    config.scanner.nonlinearity_x.quadratic = 0.03;
    config.scanner.tilt_x_from_z = 0.03;
    config.measurement.feedback_time_constant_s = 2e-4;
    config.measurement.quantise_lateral_dac = true;
    let run = |record_backward: bool| {
        let mut sim = Simulator::new(config.clone()).unwrap();
        let mut request = spm_hal::ScanRequest::centred_square(
            CountPoint::from_counts(5000.0, -3000.0),
            Counts(1.0),
            96,
            Seconds(5e-5),
        );
        request.record_backward = record_backward;
        let a = sim.scan(&request).unwrap();
        let b = sim.scan(&request).unwrap();
        (
            a.forward.z_counts,
            b.forward.z_counts,
            sim.oracle().effective_input_now(),
        )
    };
    let (fast_a, fast_b, fast_u) = run(false);
    let (full_a, full_b, full_u) = run(true);
    for (x, y) in fast_a
        .iter()
        .chain(&fast_b)
        .zip(full_a.iter().chain(&full_b))
    {
        // The tail of 12 feedback time constants leaves e^-12 of the lag
        // error: ~1e-5 counts here, far below one ADC count.
        assert!((x - y).abs() < 1e-3, "{x} vs {y}");
    }
    assert!((fast_u.x.value() - full_u.x.value()).abs() < 1e-9);
    assert!((fast_u.y.value() - full_u.y.value()).abs() < 1e-9);
}

#[test]
fn the_oracle_inverse_finds_where_a_lattice_site_appears() {
    // The inverse holds Z at its current value, ignores DAC rounding and
    // answers for "now": switch off the Z⇒X/Y couplings, the rounding and the
    // call overhead (2 ms of creep ≈ 2 pm here) to test it exactly.
    let mut config = SimConfig::room_temperature_tube().without_random_faults();
    config.measurement.quantise_lateral_dac = false;
    config.scanner.tilt_x_from_z = 0.0;
    config.scanner.tilt_y_from_z = 0.0;
    config.scanner.lateral_sensitivity_change_per_z = 0.0;
    config.instrument.call_overhead_s = 0.0;
    let mut sim = Simulator::new(config).unwrap();
    move_fast(&mut sim, 12000.0, -9000.0);
    sim.wait(Seconds(2.0)).unwrap();
    let here = sim.oracle().tip_sample_position_now();
    let sites = sim.oracle().features_near(here, 0.6);
    let atom = sites.iter().find(|s| s.kind.is_hill()).unwrap();
    let target = sim
        .oracle()
        .commanded_for_sample_point(atom.position)
        .unwrap();
    sim.move_to(spm_hal::MoveRequest {
        target,
        speed: spm_hal::CountsPerSecond(1e9),
        settle: Seconds(0.0),
    })
    .unwrap();
    let reached = sim.oracle().tip_sample_position_now();
    assert!(
        reached.distance(atom.position).value() < 1e-6,
        "{reached:?} vs {:?}",
        atom.position
    );
}
