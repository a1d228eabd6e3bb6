//! Hidden effects in generated feature lists (fast, covers all eleven effects of
//! the library at five seeds each, whatever spm-sim can produce).
#![allow(clippy::unwrap_used)]

use crate::common;

use common::{Extra, Scan, generate, none};
use spm_modelcheck::{Diagnosis, EffectKind, LatticeSpec, Options, diagnose_features};

fn run(extra: &Extra, seed: u64, options: &Options) -> Diagnosis {
    let scan = Scan::default();
    let set = generate(&scan, seed, extra);
    diagnose_features(&set, &LatticeSpec::Hex { a_nm: scan.a_nm }, options).unwrap()
}

fn summary(d: &Diagnosis) -> String {
    format!(
        "baseline {:.1} pm → final {:.1} pm; findings {:?}; unexplained {} ({:?}); rounds[0] {:?}; rejected {:?}",
        d.baseline.rms_pm,
        d.final_report.rms_pm,
        d.findings
            .iter()
            .map(|f| (f.effect.clone(), f.evidence.round(), f.parameters.clone()))
            .collect::<Vec<_>>(),
        d.unexplained,
        d.residual_structure,
        d.rounds.first().map(|r| r
            .iter()
            .map(|c| (c.effect.clone(), c.evidence.round()))
            .collect::<Vec<_>>()),
        d.rejected
            .iter()
            .map(|r| format!("{} {:.0} {}", r.effect, r.evidence, r.reason))
            .collect::<Vec<_>>()
    )
}

/// (effect, generator, true parameters) for every library effect.
fn hidden(effect: EffectKind, k: f64) -> (Box<Extra>, Vec<(&'static str, f64)>) {
    let h = Scan::default().half_nm;
    match effect {
        EffectKind::DriftAcceleration => (
            Box::new(move |_, t, _, _| {
                (
                    [0.0, 0.0],
                    [0.5 * 2e-5 * k * t * t, -0.5 * 1.5e-5 * k * t * t],
                )
            }),
            vec![
                ("acceleration_x_nm_per_s2", 2e-5 * k),
                ("acceleration_y_nm_per_s2", -1.5e-5 * k),
            ],
        ),
        EffectKind::Creep => (
            Box::new(move |_, _, _, tf| {
                let g = (1.0 + tf / 0.64).log10();
                ([0.15 * k * g, -0.1 * k * g], [0.0, 0.0])
            }),
            vec![
                ("creep_x_nm_per_decade_frame0", 0.15 * k),
                ("creep_y_nm_per_decade_frame0", -0.1 * k),
                ("creep_x_nm_per_decade_frame2", 0.15 * k),
            ],
        ),
        EffectKind::Hysteresis => (
            Box::new(move |u, _, s, _| {
                (
                    [-s * 0.01 * k * h * (1.0 - (u[0] / h).powi(2)), 0.0],
                    [0.0, 0.0],
                )
            }),
            vec![("branch_half_separation_fraction", 0.01 * k)],
        ),
        EffectKind::ScannerNonlinearity => (
            Box::new(move |u, _, _, _| {
                let (x, y) = (u[0] / h, u[1] / h);
                (
                    [
                        k * h * (0.01 * x * x + 0.008 * x.powi(3)),
                        k * h * (-0.008 * y * y + 0.006 * y.powi(3)),
                    ],
                    [0.0, 0.0],
                )
            }),
            vec![
                ("quadratic_x", 0.01 * k),
                ("cubic_x", 0.008 * k),
                ("quadratic_y", -0.008 * k),
                ("cubic_y", 0.006 * k),
            ],
        ),
        EffectKind::Nonorthogonality => (
            Box::new(move |u, _, _, _| {
                let (x, y) = (u[0] / h, u[1] / h);
                ([k * h * 0.01 * x * y, k * h * -0.008 * x * y], [0.0, 0.0])
            }),
            vec![
                ("shear_gradient_x", 0.01 * k),
                ("shear_gradient_y", -0.008 * k),
            ],
        ),
        EffectKind::CrosstalkXy => (
            Box::new(move |u, _, _, _| {
                let (x, y) = (u[0] / h, u[1] / h);
                ([k * h * 0.01 * y * y, k * h * 0.008 * x * x], [0.0, 0.0])
            }),
            vec![("bow_x_from_y", 0.01 * k), ("bow_y_from_x", 0.008 * k)],
        ),
        EffectKind::FeedbackLag => {
            let v = 2.0 * h / Scan::default().line_time_s;
            (
                Box::new(move |_, _, s, _| ([-s * v * 2e-4 * k, 0.0], [0.0, 0.0])),
                vec![("time_constant_s", 2e-4 * k)],
            )
        }
        EffectKind::PeriodicVibration => (
            Box::new(move |_, t, _, _| {
                let w = 2.0 * std::f64::consts::PI * 0.37;
                (
                    [0.0, 0.0],
                    [0.03 * k * (w * t).cos(), 0.02 * k * (w * t + 1.0).sin()],
                )
            }),
            vec![
                ("amplitude_x_nm", 0.03 * k),
                ("amplitude_y_nm", 0.02 * k),
                ("frequency_hz", 0.37),
            ],
        ),
        EffectKind::TipChange => (
            Box::new(move |_, t, _, _| {
                if t > 20.0 {
                    ([0.0, 0.0], [0.12 * k, -0.08 * k])
                } else {
                    ([0.0, 0.0], [0.0, 0.0])
                }
            }),
            vec![
                ("jump_x_nm", 0.12 * k),
                ("jump_y_nm", -0.08 * k),
                ("time_s", 20.0),
            ],
        ),
        // Backward-line features 40 pm further along the slow axis than
        // forward ones: the tip sits ±20 pm off.
        EffectKind::Interlace => (
            Box::new(move |_, _, s, _| ([0.0, 0.0], [0.0, 0.5 * s * 0.04 * k])),
            vec![("separation_y_nm", 0.04 * k), ("slow_axis_ramped", 0.0)],
        ),
        // The fast axis driven by a sine over ±β of phase, β = 0.8 + 0.5·k rad (1.1–1.5: a
        // fast-SPM drive; at β ≈ 1.04 the sine departs from its best cubic by 4 pm RMS, and
        // the polynomial is named), the nominal frame edge at the sine's value there: input
        // x = W·sin(βξ)/sin β.
        EffectKind::SinusoidalDrive => {
            let scale_x = Scan::default().scale[0];
            let beta = 0.8 + 0.5 * k;
            (
                Box::new(move |u, _, _, _| {
                    let xi = u[0] / h;
                    ([h * ((beta * xi).sin() / beta.sin() - xi), 0.0], [0.0, 0.0])
                }),
                vec![
                    ("amplitude_nm", scale_x * h / beta.sin()),
                    ("phase_at_line_end_rad", beta),
                ],
            )
        }
    }
}

#[test]
#[ignore = "exploration: prints every case"]
fn explore() {
    let d = run(&*none(), 1, &Options::default());
    println!("none: {}", summary(&d));
    for effect in EffectKind::ALL {
        let (extra, _) = hidden(effect, 1.0);
        let d = run(&*extra, 7, &Options::default());
        println!("{}: {}\n", effect.name(), summary(&d));
    }
}

fn check_recovered(d: &Diagnosis, effect: EffectKind, truth: &[(&str, f64)]) {
    let f = d
        .finding(effect)
        .unwrap_or_else(|| panic!("{} not found: {}", effect.name(), summary(d)));
    for (name, value) in truth {
        let p = *f
            .parameters
            .get(*name)
            .unwrap_or_else(|| panic!("{}: no {name}: {}", effect.name(), summary(d)));
        // Within 3σ of the stated uncertainty (plus 1 % for model discretisation).
        assert!(
            (p.value - value).abs() <= 3.0 * p.sigma + 0.01 * value.abs(),
            "{}: {name} = {} ± {} but {value} was hidden; {}",
            effect.name(),
            p.value,
            p.sigma,
            summary(d)
        );
    }
    assert!(
        f.heldout_rms_after_pm < 0.97 * f.heldout_rms_before_pm,
        "{}: no held-out gain {} → {}",
        effect.name(),
        f.heldout_rms_before_pm,
        f.heldout_rms_after_pm
    );
}

/// Seeds per hidden effect.
const SEEDS_PER_EFFECT: u64 = 5;

/// The hidden effect named first and alone at every seed, its parameters
/// recovered, a held-out gain, nothing left unexplained.
fn check_named_at_every_seed(effect: EffectKind) {
    let n = EffectKind::ALL
        .iter()
        .position(|e| *e == effect)
        .unwrap_or_default();
    for r in 0..SEEDS_PER_EFFECT {
        let seed = 100 + 10 * n as u64 + r;
        // Random realistic amplitude: 0.6–1.4 × the nominal.
        let k = 0.6 + 0.8 * ((seed * 2_654_435_761) % 1000) as f64 / 1000.0;
        let (extra, truth) = hidden(effect, k);
        let d = run(&*extra, seed, &Options::default());
        assert_eq!(
            d.findings.first().map(|f| f.effect.as_str()),
            Some(effect.name()),
            "seed {seed}: {}",
            summary(&d)
        );
        assert_eq!(d.findings.len(), 1, "seed {seed}: {}", summary(&d));
        check_recovered(&d, effect, &truth);
        assert!(!d.unexplained, "seed {seed}: {}", summary(&d));
    }
}

#[test]
fn hidden_drift_acceleration_is_named() {
    check_named_at_every_seed(EffectKind::DriftAcceleration);
}

#[test]
fn hidden_creep_is_named() {
    check_named_at_every_seed(EffectKind::Creep);
}

#[test]
fn hidden_hysteresis_is_named() {
    check_named_at_every_seed(EffectKind::Hysteresis);
}

#[test]
fn hidden_scanner_nonlinearity_is_named() {
    check_named_at_every_seed(EffectKind::ScannerNonlinearity);
}

#[test]
fn hidden_nonorthogonality_is_named() {
    check_named_at_every_seed(EffectKind::Nonorthogonality);
}

#[test]
fn hidden_crosstalk_is_named() {
    check_named_at_every_seed(EffectKind::CrosstalkXy);
}

#[test]
fn hidden_feedback_lag_is_named() {
    check_named_at_every_seed(EffectKind::FeedbackLag);
}

#[test]
fn hidden_periodic_vibration_is_named() {
    check_named_at_every_seed(EffectKind::PeriodicVibration);
}

#[test]
fn hidden_tip_change_is_named() {
    check_named_at_every_seed(EffectKind::TipChange);
}

#[test]
fn hidden_interlace_is_named() {
    check_named_at_every_seed(EffectKind::Interlace);
}

/// A slow axis that ramps through every line instead of stepping between lines (as the
/// Si 7×7 pair's Nanonis scans do, docs/MODELCHECK.md): the tip moves on along the slow
/// scan, `advance` per trace + retrace, in every frame whichever way it runs. It is named
/// `interlace`, ramped, at every seed, with the mean separation of the directions it
/// implies; the stepped shape fits it worse.
#[test]
fn a_slow_axis_ramped_through_the_lines_is_named_as_a_ramped_interlace() {
    let scan = Scan::default();
    let period = 2.0 * scan.line_time_s;
    let frame_span = period * scan.lines as f64 + scan.gap_s;
    let ups = scan.frames_up.clone();
    for seed in 300..300 + SEEDS_PER_EFFECT {
        let k = 0.6 + 0.8 * ((seed * 2_654_435_761) % 1000) as f64 / 1000.0;
        let advance = 0.06 * k;
        let ups = ups.clone();
        let extra: Box<Extra> = Box::new(move |_, t, _, t_frame| {
            let frame = ((t / frame_span).floor().max(0.0) as usize).min(ups.len() - 1);
            let slow = if ups[frame] { 1.0 } else { -1.0 };
            let within = (t_frame / period).fract();
            ([0.0, 0.0], [0.0, slow * advance * (within - 0.5)])
        });
        let d = run(&*extra, seed, &Options::default());
        assert_eq!(
            d.findings.first().map(|f| f.effect.as_str()),
            Some("interlace"),
            "seed {seed}: {}",
            summary(&d)
        );
        // Frame 0 runs up with the forward half first: forward − backward = −advance/2.
        check_recovered(
            &d,
            EffectKind::Interlace,
            &[
                ("separation_y_nm", -0.5 * advance),
                ("slow_axis_ramped", 1.0),
            ],
        );
        assert!(!d.unexplained, "seed {seed}: {}", summary(&d));
    }
}

#[test]
fn hidden_sinusoidal_drive_is_named() {
    check_named_at_every_seed(EffectKind::SinusoidalDrive);
}

/// Every effect of the library has a test above.
#[test]
fn every_library_effect_is_hidden_here() {
    for effect in EffectKind::ALL {
        let (_, truth) = hidden(effect, 1.0);
        assert!(!truth.is_empty(), "{}", effect.name());
    }
    assert_eq!(EffectKind::ALL.len(), 11, "add a hidden_*_is_named test");
}

#[test]
fn no_hidden_effect_gives_no_finding_in_at_least_19_of_20_seeds() {
    let clean = (0..20)
        .filter(|seed| {
            run(&*none(), 1000 + seed, &Options::default())
                .findings
                .is_empty()
        })
        .count();
    assert!(clean >= 19, "only {clean} of 20 clean");
}

#[test]
fn two_hidden_effects_are_both_named() {
    let (a, _) = hidden(EffectKind::Hysteresis, 0.8);
    let (b, _) = hidden(EffectKind::DriftAcceleration, 1.2);
    let extra = move |u, t, s, tf| {
        let (da, sa) = a(u, t, s, tf);
        let (db, sb) = b(u, t, s, tf);
        (
            [da[0] + db[0], da[1] + db[1]],
            [sa[0] + sb[0], sa[1] + sb[1]],
        )
    };
    let d = run(&extra, 77, &Options::default());
    let found = d.effects_found();
    assert!(
        found.contains(&"hysteresis") && found.contains(&"drift_acceleration"),
        "{}",
        summary(&d)
    );
}

#[test]
fn a_jump_outside_the_search_is_unexplained() {
    let (extra, _) = hidden(EffectKind::TipChange, 1.0);
    let options = Options::default().without(EffectKind::TipChange);
    let d = run(&*extra, 5, &options);
    assert!(d.unexplained, "{}", summary(&d));
    // With tip_change in the search, it is named and nothing remains.
    let d = run(&*extra, 5, &Options::default());
    assert_eq!(d.effects_found(), ["tip_change"], "{}", summary(&d));
    assert!(!d.unexplained, "{}", summary(&d));
}

#[test]
fn the_json_has_the_design_keys() {
    let (extra, _) = hidden(EffectKind::FeedbackLag, 1.0);
    let d = run(&*extra, 3, &Options::default());
    let v: serde_json::Value = serde_json::to_value(&d).unwrap();
    for key in ["baseline", "findings", "final", "unexplained"] {
        assert!(v.get(key).is_some(), "{key} missing");
    }
    assert!(v["baseline"]["rms_pm"].is_number());
    assert!(v["baseline"]["parameters"].is_object());
    assert!(v["final"]["rms_pm"].is_number());
    let f = &v["findings"][0];
    for key in [
        "effect",
        "evidence",
        "rms_before_pm",
        "rms_after_pm",
        "heldout_rms_before_pm",
        "heldout_rms_after_pm",
        "parameters",
    ] {
        assert!(f.get(key).is_some(), "finding key {key} missing");
    }
    assert_eq!(f["effect"], "feedback_lag");
}

/// Absurd parameters are not findings: trace and retrace shifted *against*
/// the scan direction (a negative feedback lag, a reversed hysteresis loop)
/// is not named, and the structure is reported as unexplained.
#[test]
fn a_negative_lag_is_implausible_and_unexplained() {
    let v = 2.0 * Scan::default().half_nm / Scan::default().line_time_s;
    let extra = move |_: [f64; 2], _: f64, s: f64, _: f64| ([s * v * 3e-4, 0.0], [0.0, 0.0]);
    let d = run(&extra, 12, &Options::default());
    assert!(
        !d.effects_found().contains(&"feedback_lag"),
        "{}",
        summary(&d)
    );
    assert!(d.unexplained, "{}", summary(&d));
    assert!(
        d.rejected
            .iter()
            .any(|r| r.effect == "feedback_lag" && r.reason.starts_with("implausible")),
        "{:?}",
        d.rejected
    );
}
