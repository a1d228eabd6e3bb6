//! Large fast-axis distortions (issue 29 item 3): a sinusoidally driven fast axis
//! (fast SPM) and cubic distortions of several lattice constants, hidden in images of
//! the image-level generator (tests/it/common/image.rs), must be indexed (≥ 95 % of the
//! features used by the final model) and the sine named as `sinusoidal_drive` with its
//! amplitude within 5 %.
#![allow(clippy::unwrap_used)]

use crate::common;

use common::image::{Hidden, Program, write_frames};
use spm_modelcheck::{
    Diagnosis, EffectKind, ExtractOptions, LatticeSpec, Options, diagnose, extract_features,
    index_features,
};

/// What one generated pair gives.
#[derive(Debug)]
struct Outcome {
    /// Features used by the final model over all features extracted.
    used_fraction: f64,
    /// Features the indexing alone puts on a site, over all features extracted (made for the
    /// exploration's print; the checks read the diagnosis).
    indexed_fraction: Option<f64>,
    /// Features the indexing left out, over all features extracted.
    unindexed_fraction: f64,
    /// The `sinusoidal_drive` finding's amplitude over the truth − 1 (`None`: not named).
    amplitude_error: Option<f64>,
    diagnosis: Diagnosis,
}

/// A program with a frame of `size_nm` at the default pixel pitch (0.05 nm, ≈ 5 px per
/// lattice constant), with `adsorbates_per_site` off-lattice blobs.
fn program(size_nm: f64, adsorbates_per_site: f64) -> Program {
    let base = Program::default();
    let pitch_nm = base.size_nm / base.pixels as f64;
    Program {
        pixels: (size_nm / pitch_nm).round() as usize,
        size_nm,
        adsorbates_per_site,
        ..base
    }
}

/// The true amplitude of the generator's drive, nm in the sample (lattice) frame: the
/// input x = W·sin(βξ)/sin β (nominal nm) through the fast axis's scale.
fn true_amplitude_nm(program: &Program, beta_rad: f64) -> f64 {
    program.scale[0] * 0.5 * program.size_nm / beta_rad.sin()
}

/// The fraction of the extracted features the indexing puts on a site, before any fit.
fn indexed_fraction(paths: &[std::path::PathBuf], a_nm: f64) -> f64 {
    let files: Vec<_> = paths
        .iter()
        .map(|p| (spm_formats::read_any(p).unwrap(), None))
        .collect();
    let lattice = LatticeSpec::Hex { a_nm };
    let set = extract_features(&files, &lattice, &ExtractOptions::default()).unwrap();
    let indexing = index_features(&set, &lattice).unwrap();
    indexing.sites.iter().filter(|s| s.is_some()).count() as f64
        / indexing.sites.len().max(1) as f64
}

/// Diagnoses one generated pair; `with_indexing` also indexes its features alone (a second
/// extraction and indexing, for the exploration's print; made on a refusal too).
fn measure(
    program: &Program,
    hidden: Hidden,
    seed: u64,
    tag: &str,
    with_indexing: bool,
) -> Result<Outcome, String> {
    let paths = write_frames(program, hidden, seed, tag);
    let d = diagnose(
        &common::image::inputs(&paths),
        &LatticeSpec::Hex { a_nm: program.a_nm },
        &Options::default(),
        &ExtractOptions::default(),
    );
    let indexed = (with_indexing || d.is_err()).then(|| indexed_fraction(&paths, program.a_nm));
    if let Some(dir) = paths.first().and_then(|p| p.parent()) {
        let _ = std::fs::remove_dir_all(dir);
    }
    let d = d.map_err(|e| format!("indexed {indexed:.3?}: {e}"))?;
    let total = (d.features_used + d.outliers + d.unindexed).max(1) as f64;
    let amplitude_error = match hidden {
        Hidden::SineDrive { beta_rad } => d
            .findings
            .iter()
            .find(|f| f.effect == "sinusoidal_drive")
            .and_then(|f| f.parameters.get("amplitude_nm"))
            .map(|a| a.value / true_amplitude_nm(program, beta_rad) - 1.0),
        _ => None,
    };
    Ok(Outcome {
        used_fraction: d.features_used as f64 / total,
        indexed_fraction: indexed,
        unindexed_fraction: d.unindexed as f64 / total,
        amplitude_error,
        diagnosis: d,
    })
}

fn summary(o: &Outcome) -> String {
    let d = &o.diagnosis;
    format!(
        "indexed {:.3?}, used {:.3} (unindexed {:.3}, {} outliers of {}), amplitude error {:?}; baseline {:.1} pm → final {:.1} pm (σloc {:.1}); findings {:?}; unexplained {} {:?}; rejected {:?}",
        o.indexed_fraction,
        o.used_fraction,
        o.unindexed_fraction,
        d.outliers,
        d.features_used + d.outliers + d.unindexed,
        o.amplitude_error,
        d.baseline.rms_pm,
        d.final_report.rms_pm,
        d.localisation_sigma_pm,
        common::findings(d),
        d.unexplained,
        d.residual_structure.reasons,
        common::rejections(d),
    )
}

/// A case: its name, frame size (nm), adsorbates per site, and the hidden effect.
type Case = (&'static str, f64, f64, Hidden);

/// The sine drives: β = 1.2–1.5 rad of phase either side of the line centre (the edge
/// pixels 2.8–14× compressed), amplitudes 2.5–5.1 nm (≥ ±1 nm); on the 9.6 nm frame the
/// sine departs from the best straight line by 1.1 nm (4.4 lattice constants).
fn sine_cases() -> Vec<Case> {
    vec![
        ("sine_1.2", 4.8, 0.0, Hidden::SineDrive { beta_rad: 1.2 }),
        ("sine_1.4", 4.8, 0.0, Hidden::SineDrive { beta_rad: 1.4 }),
        ("sine_1.5", 4.8, 0.0, Hidden::SineDrive { beta_rad: 1.5 }),
        (
            "sine_1.3_large",
            9.6,
            0.0,
            Hidden::SineDrive { beta_rad: 1.3 },
        ),
    ]
}

/// Not passed yet (explore only): with 0.15 adsorbates per site the structure factor
/// registers some groups (most nearest-neighbour vectors are not lattice vectors), and the
/// indexing still slips in some seeds (docs/MODELCHECK.md).
fn adsorbate_cases() -> Vec<Case> {
    vec![(
        "sine_1.4_adsorbates",
        4.8,
        0.15,
        Hidden::SineDrive { beta_rad: 1.4 },
    )]
}

/// The cubic moves the frame edge by 0.96 nm (3.9 a) on 9.6 nm.
fn cubic_cases() -> Vec<Case> {
    vec![(
        "cubic_4a",
        9.6,
        0.0,
        Hidden::Nonlinearity {
            quadratic: 0.0,
            cubic: 0.2,
        },
    )]
}

/// `CASE=sine_1.4 SEEDS=5 cargo test -p spm-modelcheck --test it sine::explore_sine -- --ignored --nocapture`
#[test]
#[ignore = "exploration: prints every case"]
fn explore_sine() {
    let only = std::env::var("CASE").ok();
    let seeds: u64 = std::env::var("SEEDS").map_or(5, |s| s.parse().unwrap());
    let clean = ("clean", 4.8, 0.0, Hidden::None);
    for (name, size_nm, adsorbates, hidden) in sine_cases()
        .into_iter()
        .chain(cubic_cases())
        .chain(adsorbate_cases())
        .chain([clean])
    {
        if only.as_deref().is_some_and(|o| o != name) {
            continue;
        }
        let adsorbates = std::env::var("ADSORBATES").map_or(adsorbates, |a| a.parse().unwrap());
        for seed in 1..=seeds {
            let started = std::time::Instant::now();
            let o = measure(&program(size_nm, adsorbates), hidden, seed, name, true);
            println!(
                "{name} seed {seed} ({:.1} s): {}\n",
                started.elapsed().as_secs_f64(),
                o.as_ref().map_or_else(|e| format!("error: {e}"), summary)
            );
        }
    }
}

/// Seeds per case.
const SEEDS: u64 = 5;

/// Runs every seed of `case` and checks each with `check` (input, expected: the outcome,
/// the program and the hidden effect), collecting every failure. The seeds are independent
/// (each writes its own folder) and run on threads of their own.
fn check_case(
    case: Case,
    check: &(dyn Fn(&Outcome, &Program, Hidden) -> Result<(), String> + Sync),
) {
    let (name, size_nm, adsorbates, hidden) = case;
    let program = program(size_nm, adsorbates);
    let failures: Vec<String> = std::thread::scope(|scope| {
        let runs: Vec<_> = (1..=SEEDS)
            .map(|seed| {
                let program = &program;
                scope.spawn(move || {
                    let outcome = match measure(program, hidden, 40 + seed, name, false) {
                        Ok(o) => o,
                        Err(e) => return Some(format!("{name} seed {seed}: {e}")),
                    };
                    check(&outcome, program, hidden)
                        .err()
                        .map(|why| format!("{name} seed {seed}: {why}; {}", summary(&outcome)))
                })
            })
            .collect();
        runs.into_iter()
            .zip(1..=SEEDS)
            .filter_map(|(run, seed)| {
                run.join()
                    .unwrap_or_else(|_| Some(format!("{name} seed {seed}: panicked")))
            })
            .collect()
    });
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Indexed: at least 95 % of the extracted features in the final model (indexed and not
/// rejected as outliers).
fn indexed(o: &Outcome) -> Result<(), String> {
    if o.used_fraction >= 0.95 {
        Ok(())
    } else {
        Err(format!("only {:.1} % used", 100.0 * o.used_fraction))
    }
}

/// The sine named first, its amplitude within 5 % and its phase β within 5 %.
fn sine_named(o: &Outcome, hidden: Hidden) -> Result<(), String> {
    let Hidden::SineDrive { beta_rad } = hidden else {
        return Err("not a sine case".to_owned());
    };
    let d = &o.diagnosis;
    let first = d.findings.first().map(|f| f.effect.as_str());
    if first != Some("sinusoidal_drive") {
        return Err(format!("first finding {first:?}"));
    }
    let err = o.amplitude_error.ok_or("no amplitude")?;
    if err.abs() > 0.05 {
        return Err(format!("amplitude off by {:.1} %", 100.0 * err));
    }
    let phase = d.findings[0]
        .parameters
        .get("phase_at_line_end_rad")
        .ok_or("no phase")?
        .value;
    if (phase / beta_rad - 1.0).abs() > 0.05 {
        return Err(format!("phase {phase:.4} rad for {beta_rad} rad"));
    }
    Ok(())
}

/// A sine-driven fast axis (β 1.2–1.5 rad, amplitudes 2.5–5.1 nm, up to 1.1 nm = 4.4 a off
/// a straight line) is indexed (≥ 95 % of the features in the
/// final model), named first as `sinusoidal_drive` with its amplitude and phase within 5 %,
/// and leaves nothing the model lacks. Before issue 29's item 3, β ≥ 1.4 was refused
/// (`NotTheLattice`: the cubic beyond its 0.3 cap, the edges' features slipped by a site)
/// and β = 1.3 on 9.6 nm lost 6 % of the features as outliers.
#[test]
fn a_sine_driven_fast_axis_is_indexed_and_named_with_its_amplitude() {
    for case in sine_cases() {
        check_case(case, &|o, _, hidden| {
            indexed(o)?;
            sine_named(o, hidden)?;
            let d = &o.diagnosis;
            if d.unexplained {
                return Err(format!("unexplained: {:?}", d.residual_structure.reasons));
            }
            Ok(())
        });
    }
}

/// A cubic of several lattice constants (0.96 nm = 3.9 a at the frame edge) is indexed and
/// named as the polynomial it is — not as a sine, which cannot make a positive cubic — with
/// its cubic within 3σ + 10 %.
#[test]
fn a_cubic_of_several_lattice_constants_is_indexed_and_stays_a_polynomial() {
    for case in cubic_cases() {
        check_case(case, &|o, _, hidden| {
            indexed(o)?;
            let Hidden::Nonlinearity { cubic, .. } = hidden else {
                return Err("not a cubic case".to_owned());
            };
            let d = &o.diagnosis;
            let first = d.findings.first().map(|f| f.effect.as_str());
            if first != Some("scanner_nonlinearity") {
                return Err(format!("first finding {first:?}"));
            }
            if d.finding(EffectKind::SinusoidalDrive).is_some() {
                return Err("a sine named for a positive cubic".to_owned());
            }
            let c = d.findings[0]
                .parameters
                .get("cubic_x")
                .ok_or("no cubic_x")?;
            if (c.value - cubic).abs() > 3.0 * c.sigma + 0.1 * cubic {
                return Err(format!("cubic_x {} ± {} for {cubic}", c.value, c.sigma));
            }
            Ok(())
        });
    }
}

// ---------------------------------------------------------------------------------------
// spm-sim's own fast-SPM scan program (`Simulator::scan_sine_driven`)

/// spm-sim's frames with a sine-driven fast axis: the simulator's hexagonal lattice of
/// Gaussian hills, the frames turned into diagnose inputs as `tests/it/sim.rs` turns its
/// (features of the scanner-geometry height maps, placed on the nominal linear raster).
mod fast_spm {
    use super::Diagnosis;
    use crate::common::sim_frame::{SimFrame, add_sim_frame};
    use spm_hal::{CountPoint, Counts, Frame, ScanDirection, ScanRequest, Seconds};
    use spm_modelcheck::{
        FeatureSet, LatticeSpec, Options, SimContext, SimPatch, diagnose_features, sim_patch,
    };
    use spm_sim::{LatticeConfig, SimConfig, Simulator, SineDrive, SurfaceConfig};

    pub(super) const NOMINAL_NM_PER_COUNT: f64 = 0.02;
    /// The hills' Gaussian radius (σ) over the lattice constant.
    const SIGMA_OVER_A: f64 = 0.2;
    /// The true fast-axis scale, nm per count.
    pub(super) const KX_NM_PER_COUNT: f64 = 0.0205;
    const DWELL_S: f64 = 1e-4;

    /// A frame of `pixels` square pixels of `step_counts` over a lattice of `a_nm`.
    #[derive(Clone, Copy, Debug)]
    pub(super) struct Geometry {
        pub pixels: u32,
        pub step_counts: f64,
        /// The simulator's lattice constant, nm.
        pub a_nm: f64,
    }

    impl Geometry {
        /// The nominal pixel, nm.
        pub fn pixel_nm(&self) -> f64 {
            self.step_counts * NOMINAL_NM_PER_COUNT
        }

        /// The frame's nominal half-width W, nm.
        pub fn half_width_nm(&self) -> f64 {
            0.5 * f64::from(self.pixels) * self.pixel_nm()
        }

        /// The drive's true amplitude in the sample, nm: A = W/sin β (counts) through the
        /// fast axis's true scale.
        pub fn true_amplitude_nm(&self, beta_rad: f64) -> f64 {
            KX_NM_PER_COUNT * 0.5 * f64::from(self.pixels) * self.step_counts / beta_rad.sin()
        }
    }

    /// The instrument of `tests/it/sim.rs`'s baseline (off-nominal scales, 1° obliquity,
    /// constant drift, 3 pm white Z noise) over a hexagonal lattice of Gaussian hills.
    fn config(seed: u64, a_nm: f64) -> SimConfig {
        let mut c = SimConfig::ideal();
        c.seed = seed;
        c.surface = SurfaceConfig::HexLattice(LatticeConfig {
            lattice_constant_nm: a_nm,
            feature_height_nm: 0.1,
            feature_sigma_nm: SIGMA_OVER_A * a_nm,
            rotation_deg: 7.0,
        });
        c.scanner.sensitivity_x_nm_per_count = KX_NM_PER_COUNT;
        c.scanner.sensitivity_y_nm_per_count = 0.0196;
        c.scanner.nonorthogonality_deg = 1.0;
        c.drift.velocity_x_nm_per_s = 0.5;
        c.drift.velocity_y_nm_per_s = -0.3;
        c.measurement.z_white_noise_nm = 0.003;
        c
    }

    /// Two frames (direct, counter) of the field centre, both halves, the fast axis driven
    /// over ±`beta_rad` of phase per line: their features.
    pub(super) fn scan(geometry: Geometry, beta_rad: f64, seed: u64) -> FeatureSet {
        let mut sim = Simulator::new(config(seed, geometry.a_nm)).unwrap();
        let mut set = FeatureSet::default();
        for (f, direction) in [ScanDirection::Direct, ScanDirection::Counter]
            .into_iter()
            .enumerate()
        {
            let mut request = ScanRequest::centred_square(
                CountPoint::from_counts(0.0, 0.0),
                Counts(geometry.step_counts),
                geometry.pixels,
                Seconds(DWELL_S),
            )
            .with_direction(direction);
            request.record_backward = true;
            let drive = SineDrive {
                phase_at_line_end_rad: beta_rad,
            };
            let frame = sim.scan_sine_driven(&request, drive).unwrap();
            add_frame(&mut set, &frame, f, geometry);
        }
        set
    }

    /// The frame's features, as `tests/it/sim.rs`'s `add_frame` places them: the nominal
    /// (linear) raster of the request, each feature's time from its pixels' (equidistant).
    fn add_frame(set: &mut FeatureSet, frame: &Frame, frame_index: usize, g: Geometry) {
        let f = SimFrame {
            frame,
            index: frame_index,
            label: format!("sine-driven sim frame {frame_index}"),
            pixels: g.pixels as usize,
            pixel_nm: g.pixel_nm(),
            half_width_nm: g.half_width_nm(),
            dwell_s: DWELL_S,
            a_nm: g.a_nm,
        };
        add_sim_frame(set, None, &f);
    }

    pub(super) fn diagnose(set: &FeatureSet, a_nm: f64) -> Result<Diagnosis, String> {
        diagnose_features(set, &LatticeSpec::Hex { a_nm }, &Options::default())
            .map_err(|e| e.to_string())
    }

    /// The fitted model as spm-sim values (no move history: no creep to map).
    pub(super) fn patch(d: &Diagnosis) -> SimPatch {
        let ctx = SimContext {
            nominal_nm_per_count: NOMINAL_NM_PER_COUNT,
            half_range_counts: 32768.0,
            time_offset_s: 0.0,
            warmup_time_constant_s: 60.0,
            pixel_dwell_s: Some(DWELL_S),
            move_history: None,
        };
        sim_patch(d, &ctx, true)
    }
}

/// A spm-sim case: its name, frame geometry and phase β, rad.
type SimCase = (&'static str, fast_spm::Geometry, f64);

/// spm-sim's sine-driven frames: 96 px of 10 nm (16 lattice constants of 60 nm) at
/// β = 1.2–1.5 rad, amplitudes 490–530 nm (8–9 a; the line ends 2.8–14× compressed, the
/// positions 55–94 nm = 0.9–1.6 a off the best straight line), and 256 px of 5 nm over a
/// 30 nm lattice (43 a) at β = 1.4: amplitude 670 nm (22 a), 105 nm (3.5 a) off the best
/// straight line at the line ends.
fn sim_cases() -> Vec<SimCase> {
    let g = fast_spm::Geometry {
        pixels: 96,
        step_counts: 500.0,
        a_nm: 60.0,
    };
    let large = fast_spm::Geometry {
        pixels: 256,
        step_counts: 250.0,
        a_nm: 30.0,
    };
    vec![
        ("sim_sine_1.2", g, 1.2),
        ("sim_sine_1.4", g, 1.4),
        ("sim_sine_1.5", g, 1.5),
        ("sim_sine_1.4_large", large, 1.4),
    ]
}

/// What one spm-sim run gives.
fn measure_sim(case: SimCase, seed: u64) -> Result<Outcome, String> {
    let (_, geometry, beta_rad) = case;
    let set = fast_spm::scan(geometry, beta_rad, seed);
    let d = fast_spm::diagnose(&set, geometry.a_nm)?;
    let total = (d.features_used + d.outliers + d.unindexed).max(1) as f64;
    let amplitude_error = d
        .findings
        .iter()
        .find(|f| f.effect == "sinusoidal_drive")
        .and_then(|f| f.parameters.get("amplitude_nm"))
        .map(|a| a.value / geometry.true_amplitude_nm(beta_rad) - 1.0);
    Ok(Outcome {
        used_fraction: d.features_used as f64 / total,
        indexed_fraction: None,
        unindexed_fraction: d.unindexed as f64 / total,
        amplitude_error,
        diagnosis: d,
    })
}

/// `CASE=sim_sine_1.4 SEEDS=5 cargo test -p spm-modelcheck --test it sine::explore_sim_sine -- --ignored --nocapture`
#[test]
#[ignore = "exploration: prints every case"]
fn explore_sim_sine() {
    let only = std::env::var("CASE").ok();
    let seeds: u64 = std::env::var("SEEDS").map_or(5, |s| s.parse().unwrap());
    for case in sim_cases() {
        if only.as_deref().is_some_and(|o| o != case.0) {
            continue;
        }
        for seed in 1..=seeds {
            let started = std::time::Instant::now();
            let o = measure_sim(case, seed);
            let patch = o.as_ref().ok().map(|o| fast_spm::patch(&o.diagnosis));
            println!(
                "{} seed {seed} ({:.1} s): {}\n  patch {:?}\n",
                case.0,
                started.elapsed().as_secs_f64(),
                o.as_ref().map_or_else(|e| format!("error: {e}"), summary),
                patch.map(|p| (p.values, p.unmapped)),
            );
        }
    }
}

/// The true fast-axis sensitivity within 2 % and the phase within 5 % in `sim_patch`'s
/// values: the drive maps to spm-sim's scan program.
fn sim_patch_maps_the_drive(o: &Outcome, beta_rad: f64) -> Result<(), String> {
    let patch = fast_spm::patch(&o.diagnosis);
    let phase = patch
        .sine_drive_phase_at_line_end_rad
        .ok_or_else(|| format!("no scan program; unmapped {:?}", patch.unmapped))?;
    if (phase / beta_rad - 1.0).abs() > 0.05 {
        return Err(format!("patch phase {phase:.4} rad for {beta_rad} rad"));
    }
    let kx = patch
        .values
        .get(&spm_modelcheck::SimParam::SensitivityXNmPerCount)
        .copied()
        .ok_or("no sensitivity_x")?;
    if (kx / fast_spm::KX_NM_PER_COUNT - 1.0).abs() > 0.02 {
        return Err(format!(
            "patch sensitivity_x {kx:.5} nm/count for {}",
            fast_spm::KX_NM_PER_COUNT
        ));
    }
    Ok(())
}

/// spm-sim's fast-SPM scan program (`Simulator::scan_sine_driven`: the fast axis on a sine
/// over ±β of phase, the pixels equidistant in time) at β = 1.2–1.5 rad, amplitudes
/// 490–670 nm (8–22 lattice constants), seeds 41–45 (41–43 on 256 px): indexed (≥ 95 % of the features in
/// the final model), named first as `sinusoidal_drive` with its amplitude and phase within
/// 5 %, nothing left unexplained, and `sim_patch` maps it back to the scan program.
#[test]
fn spm_sims_sine_driven_fast_axis_is_indexed_and_named_with_its_amplitude() {
    let failures: Vec<String> = std::thread::scope(|scope| {
        let runs: Vec<_> = sim_cases()
            .into_iter()
            .flat_map(|case| {
                // The 256 px case takes ~3.5 s a seed (the 96 px ones 0.3–0.6 s): three seeds.
                let last = if case.1.pixels > 128 { 43 } else { 45 };
                (41..=last).map(move |seed| (case, seed))
            })
            .map(|(case, seed)| {
                let run = scope.spawn(move || {
                    let o = match measure_sim(case, seed) {
                        Ok(o) => o,
                        Err(e) => return Some(format!("{} seed {seed}: {e}", case.0)),
                    };
                    let hidden = Hidden::SineDrive { beta_rad: case.2 };
                    let check = || -> Result<(), String> {
                        indexed(&o)?;
                        sine_named(&o, hidden)?;
                        if o.diagnosis.unexplained {
                            return Err(format!(
                                "unexplained: {:?}",
                                o.diagnosis.residual_structure.reasons
                            ));
                        }
                        sim_patch_maps_the_drive(&o, case.2)
                    };
                    check()
                        .err()
                        .map(|why| format!("{} seed {seed}: {why}; {}", case.0, summary(&o)))
                });
                (case.0, seed, run)
            })
            .collect();
        runs.into_iter()
            .filter_map(|(name, seed, run)| {
                run.join()
                    .unwrap_or_else(|_| Some(format!("{name} seed {seed}: panicked")))
            })
            .collect()
    });
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// The control: the same frames on spm-sim's linear raster (β = 0) name no sine drive.
#[test]
fn spm_sims_linear_raster_names_no_sine_drive() {
    let (_, geometry, _) = sim_cases()[1];
    for seed in [41, 42] {
        let d = fast_spm::diagnose(&fast_spm::scan(geometry, 0.0, seed), geometry.a_nm).unwrap();
        assert!(
            d.finding(EffectKind::SinusoidalDrive).is_none(),
            "seed {seed}: {:?}",
            d.effects_found()
        );
        assert!(
            fast_spm::patch(&d)
                .sine_drive_phase_at_line_end_rad
                .is_none()
        );
    }
}
