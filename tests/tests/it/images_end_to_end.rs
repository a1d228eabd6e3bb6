//! Issue 12 end to end: the accuracy a user sees, with every simulated effect on.
//!
//! A 6 × 6 net is calibrated on the room-temperature tube scanner with hysteresis, creep,
//! drift, noise and feedback lag all on (random faults off), and the run's report carries the
//! image benchmark (`report.json` `images`): test images taken after the run as a user takes
//! them (a move, a pause, a direct and a counter raster), corrected by every method.
//!
//! The creep of the scanner is hidden from the algorithms: nothing tells them its law. The
//! run must *find* it (a creep weight well above its standard error, from the attachment
//! tracks the run makes anyway), *measure* it (its logarithmic slope against the simulator's
//! own, read through the oracle), and *correct* it (the images corrected along the effective
//! trajectory of the identified law beat the same surfaces corrected statically).
//!
//! Every target is relative to a reference the code under test cannot move, computed from the
//! oracle on the same images: `oracle_static_field` (the simulator's true small-signal LCC
//! field through the same correction — the best any static calibration can do) and
//! `bound_distributed_true_dynamics` (the calibrated surfaces along the simulator's true
//! effective inputs).

use crate::common;

use spm_hal::Seconds;

#[test]
fn with_every_effect_on_the_identified_creep_law_corrects_what_no_static_field_can() {
    let calibration = common::small_net(true, true);
    let report = &calibration.report;
    let images = report.images.as_ref().expect("the image benchmark ran");
    assert!(images.count >= 24, "{} test images", images.count);
    let get = |name: &str| {
        images
            .methods
            .get(name)
            .unwrap_or_else(|| panic!("method {name} missing: {:?}", images.methods.keys()))
    };
    for (name, m) in &images.methods {
        eprintln!(
            "{name:<34} position {:8.1} pm RMS {:7.3} % of side (on the sample {:7.3} %); lattice {:.3} / {:.3} % ({} pairs, {} failed)",
            m.position_rms_pm,
            m.position_rms_pct_of_side,
            m.sample_position_rms_pct_of_side,
            m.mean_lattice_error_pct,
            m.max_lattice_error_pct,
            m.lattice_pairs,
            m.lattice_failures
        );
    }

    // The lattice as the ruler of each image (`spmcal correct --ruler`): the creep of the move
    // that brought the probe there and the drift, which no file records, are hidden in every
    // image; measured against the lattice, they must go. Judged on the sample (where each
    // pixel was on it), which is what the ruler recovers: the file alone leaves them whole.
    let ruler = get("user_file_ruler");
    let file_alone = get("user_file_dynamics");
    assert!(
        ruler.sample_position_rms_pct_of_side <= 0.35 * file_alone.sample_position_rms_pct_of_side,
        "the ruler leaves {} % on the sample, the file alone {} %",
        ruler.sample_position_rms_pct_of_side,
        file_alone.sample_position_rms_pct_of_side
    );

    // The counter-scanned partner (`spmcal correct --counter`): the two frames of each pair see
    // the part of the approach creep and drift that is odd about the pair's middle, and only
    // that (the even part is the same in both frames). Measured between them feature by
    // feature, it must go: a quarter of what the file alone leaves on this net (0.76 when
    // written), so at most 0.85 of it.
    let counter = get("user_file_counter");
    assert!(
        counter.sample_position_rms_pct_of_side
            <= 0.85 * file_alone.sample_position_rms_pct_of_side,
        "the counter partner leaves {} % on the sample, the file alone {} %",
        counter.sample_position_rms_pct_of_side,
        file_alone.sample_position_rms_pct_of_side
    );

    // Found and measured: the creep law against the simulator's own.
    let dynamics = images.dynamics.as_ref().expect("dynamics summary");
    assert!(
        dynamics.note.is_none(),
        "creep law not identified: {dynamics:?}"
    );
    assert!(
        dynamics.creep_weight > 10.0 * dynamics.creep_weight_sigma,
        "creep not found above its noise: {dynamics:?}"
    );
    let oracle = calibration.simulator.oracle();
    let s = |t: f64| oracle.creep_step_response(Seconds(t));
    let true_gamma = ((1.0 + s(10.0)) / (1.0 + s(0.1)) - 1.0) / 2.0;
    eprintln!(
        "creep γ identified {:.4} per decade, simulator {:.4}",
        dynamics.gamma_per_decade, true_gamma
    );
    assert!(
        (dynamics.gamma_per_decade / true_gamma - 1.0).abs() < 0.25,
        "γ {} vs the simulator's {true_gamma}",
        dynamics.gamma_per_decade
    );

    // Corrected: what a static field cannot correct, the identified law removes for the most part.
    let static_truth = get("oracle_static_field");
    let distributed = get("distributed");
    let dynamic = get("distributed_creep_model");
    let bound = get("bound_distributed_true_dynamics");
    assert!(
        dynamic.position_rms_pct_of_side <= 0.35 * static_truth.position_rms_pct_of_side,
        "creep model {:.3} % vs the true static field {:.3} %",
        dynamic.position_rms_pct_of_side,
        static_truth.position_rms_pct_of_side
    );
    assert!(
        dynamic.position_rms_pct_of_side <= 0.35 * distributed.position_rms_pct_of_side,
        "creep model {:.3} % vs static distributed {:.3} %",
        dynamic.position_rms_pct_of_side,
        distributed.position_rms_pct_of_side
    );
    // The static calibration itself is not what limits the images: its surfaces do as well as
    // the simulator's true field through the same correction (within 30 %).
    assert!(
        distributed.position_rms_pct_of_side <= 1.3 * static_truth.position_rms_pct_of_side,
        "distributed {:.3} % vs true static field {:.3} %",
        distributed.position_rms_pct_of_side,
        static_truth.position_rms_pct_of_side
    );
    // And the rest is the dynamics the model leaves out (hysteresis): with the true effective
    // inputs the same surfaces do better still.
    assert!(
        bound.position_rms_pct_of_side < dynamic.position_rms_pct_of_side,
        "true-dynamics bound {:.3} % vs creep model {:.3} %",
        bound.position_rms_pct_of_side,
        dynamic.position_rms_pct_of_side
    );
    // The lattice seen on the corrected pairs. A pair counts only when its atoms can be matched
    // and a constant drift explains them; a static correction loses most pairs to the creep of
    // the approach, the creep model keeps them, and its error is within reach of what the same
    // surfaces give along the true effective trajectory (the oracle's bound).
    assert!(
        dynamic.lattice_pairs * 5 >= (dynamic.lattice_pairs + dynamic.lattice_failures) * 4,
        "creep model measured only {} of {} pairs",
        dynamic.lattice_pairs,
        dynamic.lattice_pairs + dynamic.lattice_failures
    );
    assert!(
        dynamic.lattice_pairs > distributed.lattice_pairs
            || dynamic.mean_lattice_error_pct < distributed.mean_lattice_error_pct,
        "lattice: creep model {dynamic:?} vs static {distributed:?}"
    );
    assert!(
        dynamic.mean_lattice_error_pct <= 2.0 * bound.mean_lattice_error_pct + 0.5,
        "lattice: creep model {:.3} % vs true-dynamics bound {:.3} %",
        dynamic.mean_lattice_error_pct,
        bound.mean_lattice_error_pct
    );
}

/// The benchmark's sample points (`TestImage::sample_truth_nm`: where on the sample each pixel
/// was) against a closed form. On an ideal scanner with a constant drift along y alone, the
/// exact per-image map of the tip positions (`PerImageBound`) leaves no error in the scanner
/// frame, and on the sample exactly the drift over the frame: each pixel `v·(t − t̄)` off
/// along y, so the RMS is `|v|·RMS(t)` of the pixel times (the best rigid motion removes the
/// mean; the tilt it could take out is 1/(2N) of it).
#[test]
fn the_sample_points_carry_the_drift_the_tip_positions_do_not() {
    use spm_evaluation::images::{ImageCorrection, ImageMethod, evaluate_images};
    let v_nm_per_s = DRIFT_Y_NM_PER_S;
    let (set, images) = ideal_drifting_images();
    let bench = evaluate_images(
        &images,
        &[ImageMethod {
            name: "exact".into(),
            correction: ImageCorrection::PerImageBound,
        }],
        &set,
    )
    .expect("benchmark");
    for (image, row) in images.iter().zip(&bench.images) {
        let f = row.figures["exact"];
        let t = &image.time_acquisition_s;
        let mean = t.iter().sum::<f64>() / t.len() as f64;
        let rms_t = (t.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / t.len() as f64).sqrt();
        let side_nm = image.size.side_counts() * 0.02;
        let expected = 100.0 * v_nm_per_s * rms_t / side_nm;
        assert!(
            f.position_rms_pct_of_side < 0.02 * expected,
            "{:?}: the tip positions, exactly mapped, are {} % off",
            image.direction,
            f.position_rms_pct_of_side
        );
        assert!(
            (f.sample_position_rms_pct_of_side / expected - 1.0).abs() < 0.03,
            "{:?}: on the sample {} % against the drift's {expected} %",
            image.direction,
            f.sample_position_rms_pct_of_side
        );
    }
}

/// The DHCT competitor (after Yothers et al. 2017) end to end on the simulator's images: on an
/// ideal scanner with a constant drift along y (a closed form: each pixel `v·t` off on the
/// sample), the images taken with their retraces aside are corrected from their own trace and
/// retrace with the lattice as the ruler; the corrected pixels land on the sample points the
/// simulator recorded to a fifth of the drift's error on every image, and the DHCT's drift
/// plus creep over the frame matches the drift's: e(t_start) − e(t_end) within 10 % of v·T
/// (an atom is seen v·t short of where it is).
#[test]
fn the_dhct_competitor_takes_out_a_constant_drift_from_trace_and_retrace() {
    use spm_evaluation::competitors::{CompetitorConfig, nominal_map, yothers};
    use spm_evaluation::images::TestImage;
    let v_nm_per_s = DRIFT_Y_NM_PER_S;
    let (_, images) = ideal_drifting_images();
    let competitor = CompetitorConfig {
        nominal_nm_per_count: 0.02,
        lattice_constant_nm: 0.2461,
        min_pixels_per_lattice_constant: 5.0,
    };
    let rms_on_sample = |image: &TestImage, map: &spm_correction::CoordinateMap| -> f64 {
        let mut points = Vec::new();
        for row in 0..map.rows() {
            for column in 0..map.columns() {
                let p = map.point(column, row).expect("pixel");
                points.push([p.x.value(), p.y.value()]);
            }
        }
        let r = spm_evaluation::rigid_residuals(&points, &image.sample_truth_nm);
        (r.iter().map(|v| v * v).sum::<f64>() / r.len() as f64).sqrt()
    };
    for image in &images {
        assert!(image.backward.is_some(), "no retrace aside");
        let nominal = nominal_map(&image.map, 0.02).expect("nominal map");
        let (model, map) = yothers::correct_image(&image.map, image.backward.as_ref(), &competitor)
            .expect("the DHCT corrects the image");
        let (before, after) = (rms_on_sample(image, &nominal), rms_on_sample(image, &map));
        assert!(
            after < 0.2 * before,
            "{:?}: on the sample {after} nm RMS, nominal {before} nm; {model:?}",
            image.direction
        );
        let times = &image.map.time_s;
        let (t0, t1) = (
            times.iter().copied().fold(f64::INFINITY, f64::min),
            times.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        );
        let e = |t: f64| {
            model.error_nm(&spm_evaluation::competitors::Sighting {
                position_nm: [model.centre_x_nm, 0.0],
                time_s: t - t0,
                since_reversal_s: 0.0,
                progress: 0.0,
                sign: 1.0,
            })[1]
        };
        let expected = v_nm_per_s * (t1 - t0);
        // The sample moves by +v·t: an atom is seen where the tip is, v·t short of it.
        let found = e(t0) - e(t1);
        assert!(
            (found / expected - 1.0).abs() < 0.1,
            "{:?}: the DHCT moves y by {found} nm over the frame, the drift {expected} nm; {model:?}",
            image.direction
        );
    }
}

/// The drift of [`ideal_drifting_images`], nm/s along y.
const DRIFT_Y_NM_PER_S: f64 = 0.02;

/// One 65-pixel image pair (direct and counter) at the centre of an ideal simulated scanner
/// whose sample drifts at [`DRIFT_Y_NM_PER_S`] along y, taken through the command recorder,
/// with the set's configuration.
fn ideal_drifting_images() -> (
    spm_evaluation::images::ImageSetConfig,
    Vec<spm_evaluation::images::TestImage>,
) {
    use spm_evaluation::images::{CountRegion, ImageSetConfig, ImageSize, take_test_images};
    let mut config = spm_sim::SimConfig::ideal();
    config.drift.velocity_y_nm_per_s = DRIFT_Y_NM_PER_S;
    let sim = spm_sim::Simulator::new(config).expect("simulator");
    let mut instrument = spm_hal::recording::CommandRecorder::new(sim, 100_000);
    let set = ImageSetConfig {
        places_per_side: 1,
        sizes: vec![ImageSize {
            pixels: 65,
            step_counts: 2.0,
        }],
        dwells_s: vec![2e-3],
        pause: spm_calibration::PauseLaw {
            base_s: 0.0,
            per_count_s: 0.0,
            per_coarse_step_s: 0.0,
            max_s: 0.0,
        },
        move_speed_counts_per_s: 20_000.0,
        settle_s: 0.0,
        lattice_constant_nm: 0.2461,
        nominal_nm_per_count: 0.02,
        min_pixels_per_lattice_constant: 5.0,
    };
    let region = CountRegion {
        x_min_counts: -100.0,
        x_max_counts: 100.0,
        y_min_counts: -100.0,
        y_max_counts: 100.0,
    };
    let images = take_test_images(&mut instrument, &region, &set).expect("images");
    (set, images)
}

/// Eq. (5) along the effective trajectory (`correct_effective_raster`, what every dynamic
/// path of `spmcal correct` and the benchmark composes) with the oracle's true LCCs and the
/// true effective input reproduces the tip's true displacements along the lines and across
/// them, on the full room-temperature scanner (hysteresis and creep on). The composition
/// with the commanded input instead (the static correction) misses the slow axis's creep,
/// which the test requires it to show: the dynamics hidden in the images are there to find.
#[test]
fn the_true_lccs_along_the_true_effective_path_give_the_tip_positions() {
    use spm_evaluation::images::{CountRegion, ImageSetConfig, ImageSize, take_test_images};
    use spm_hal::truth::GroundTruth;
    let text = std::fs::read_to_string(common::workspace_root().join("configs/sim-hopg.toml"))
        .expect("configs/sim-hopg.toml");
    let config = spm_sim::SimConfig::from_toml_str(&text, "configs/sim-hopg.toml")
        .expect("the shipped simulator config")
        .without_random_faults();
    let sim = spm_sim::Simulator::new(config).expect("simulator");
    let mut instrument = spm_hal::recording::CommandRecorder::new(sim, 1_000_000);
    let set = ImageSetConfig {
        places_per_side: 3,
        sizes: vec![
            ImageSize {
                pixels: 128,
                step_counts: 4.0,
            },
            ImageSize {
                pixels: 64,
                step_counts: 128.0,
            },
        ],
        dwells_s: vec![1e-4],
        pause: spm_calibration::PauseLaw {
            base_s: 1.0,
            per_count_s: 1e-4,
            per_coarse_step_s: 0.0,
            max_s: 5.0,
        },
        move_speed_counts_per_s: 20_000.0,
        settle_s: 0.0,
        lattice_constant_nm: 0.2461,
        nominal_nm_per_count: 0.0022424,
        min_pixels_per_lattice_constant: 5.0,
    };
    let region = CountRegion {
        x_min_counts: -25_000.0,
        x_max_counts: 25_000.0,
        y_min_counts: -25_000.0,
        y_max_counts: 25_000.0,
    };
    let images = take_test_images(&mut instrument, &region, &set).expect("images");
    let sim = instrument.inner_mut();
    let gain = sim.reference_gain();
    let z = sim.z_now();
    let oracle = spm_correction::FnField(|x: f64, y: f64| {
        let l = sim.true_lcc(spm_hal::CountPoint::from_counts(x, y), z);
        spm_correction::FormCoefficients::from_lcc(
            l.kx_nm_per_count,
            l.ky_nm_per_count,
            l.alpha_rad,
        )
    });
    let (mut worst_fast, mut worst_slow, mut worst_commanded_slow) = (0.0f64, 0.0f64, 0.0f64);
    let mut direct = 0;
    for im in images
        .iter()
        .filter(|i| i.direction == spm_hal::ScanDirection::Direct)
    {
        // A direct image: acquisition order is the geometry's (truth_nm's order).
        direct += 1;
        let (n, rows) = (im.map.columns, im.map.rows);
        let offsets: Vec<[f64; 2]> = im
            .true_effective_acquisition
            .iter()
            .zip(&im.commanded_acquisition)
            .map(|(e, u)| [e[0] - u[0], e[1] - u[1]])
            .collect();
        let zero = vec![[0.0; 2]; offsets.len()];
        let centre = im.commanded_acquisition[(rows / 2) * n + n / 2];
        let path = |offsets: &[[f64; 2]], gain: [f64; 2]| {
            spm_correction::dynamics::correct_effective_raster(
                &oracle,
                n,
                rows,
                &im.commanded_acquisition,
                offsets,
                gain,
                centre,
            )
            .expect("a valid raster")
        };
        let effective = path(&offsets, gain);
        let commanded = path(&zero, [1.0, 1.0]);
        // Along the middle line (x) and the middle column (y), against the truth.
        let (a, b) = ((rows / 2) * n, (rows / 2) * n + n - 1);
        let (c, d) = (n / 2, (rows - 1) * n + n / 2);
        let along = |p: &[[f64; 2]], i: usize, j: usize, k: usize| p[j][k] - p[i][k];
        let truth_x = along(&im.truth_nm, a, b, 0);
        let truth_y = along(&im.truth_nm, c, d, 1);
        let x_error = along(&effective, a, b, 0) / truth_x - 1.0;
        let y_error = along(&effective, c, d, 1) / truth_y - 1.0;
        let y_commanded = along(&commanded, c, d, 1) / truth_y - 1.0;
        eprintln!(
            "{:>14} {:>4} counts: along x {:+.4} %, along y {:+.4} %; commanded input along y {:+.3} %",
            im.place,
            im.size.side_counts(),
            100.0 * x_error,
            100.0 * y_error,
            100.0 * y_commanded
        );
        worst_fast = worst_fast.max(x_error.abs());
        worst_slow = worst_slow.max(y_error.abs());
        worst_commanded_slow = worst_commanded_slow.max(y_commanded.abs());
    }
    assert_eq!(direct, 18, "9 places × 2 sizes of direct images");
    // Along the lines within 0.05 % (measured: 0.041 %); across them within 0.3 % (0.244 %:
    // on a 508-count frame the approach move's creep is up to a fifth of the frame, summed
    // over 127 line starts).
    assert!(
        worst_fast < 5e-4 && worst_slow < 3e-3,
        "the true LCCs along the true effective path miss by {:.3} % along x, {:.3} % along y",
        100.0 * worst_fast,
        100.0 * worst_slow
    );
    assert!(
        worst_commanded_slow > 1e-2,
        "the slow axis's creep should show on the commanded input ({:.3} %)",
        100.0 * worst_commanded_slow
    );
}
