//! Developer probe of the lattice ruler (`spmcal correct --ruler`) on the benchmark's own test
//! images, taken on a freshly started simulator: per image, the file-alone error, what the
//! ruler found (or why it refused) and the error after it. Not a test:
//!
//! `cargo run --profile test -p spmcal --example ruler_probe -- JOB.toml CALIBRATION.json
//! [DWELL_FACTOR]`
//!
//! (`CALIBRATION.json` a calibration file with dynamics, e.g. the default job's
//! `surfaces.json`; only the images of the plan's dwell × `DWELL_FACTOR` are taken, default 4,
//! the slow class; the region is the calibration's own; `SIZES=1,2` keeps the sizes of those
//! pixel steps; `RUN=1` takes them after the job's own run, as the benchmark does.)
#![allow(clippy::unwrap_used, clippy::print_stdout, clippy::expect_used)]
use spm_evaluation::images::{
    CountRegion, ImageSetConfig, evaluate_images, ruler_outcome, take_test_images,
};
use spm_evaluation::images::{ImageCorrection, ImageMethod};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let job = spmcal::job::Job::from_file(std::path::Path::new(&args[0])).unwrap();
    let text = std::fs::read_to_string(&args[1]).unwrap();
    let set = spm_correction::SurfaceSet::from_json_str(&text).unwrap();
    let factor: f64 = args.get(2).map_or(4.0, |v| v.parse().unwrap());
    // RUN=1: the images are taken after the job's calibration run, on its simulator, as the
    // benchmark takes them; otherwise on a freshly started one.
    let sim = if std::env::var("RUN").is_ok() {
        let cdb = std::env::temp_dir().join(format!("ruler_probe_{}.sqlite", std::process::id()));
        let mut quiet = spm_calibration::NoObserver;
        let outcome = spmcal::run::run_job(
            &job,
            &cdb,
            spmcal::run::RunStart::New {
                run_id: "probe".to_owned(),
            },
            1_800_000_000.0,
            &mut quiet,
        )
        .unwrap();
        let _ = std::fs::remove_file(&cdb);
        outcome.instrument.simulator().unwrap().clone()
    } else {
        let spmcal::job::Backend::Sim(sim_config) = job.backend.clone() else {
            panic!("a simulated backend");
        };
        spm_sim::Simulator::new(*sim_config).unwrap()
    };
    let mut config = ImageSetConfig::standard(&job.plan, false);
    config.dwells_s = vec![job.plan.motion.pixel_dwell_s * factor];
    // BOTH=1: the plan's dwell and 4× it, as the benchmark takes them.
    if std::env::var("BOTH").is_ok() {
        config.dwells_s = vec![
            job.plan.motion.pixel_dwell_s,
            4.0 * job.plan.motion.pixel_dwell_s,
        ];
    }
    if let Ok(sizes) = std::env::var("SIZES") {
        let keep: Vec<u32> = sizes.split(',').map(|s| s.parse().unwrap()).collect();
        config
            .sizes
            .retain(|s| keep.contains(&(s.step_counts as u32)));
    }
    let plane = set.plane_nearest(0.0).unwrap();
    let r = plane.calibrated_region();
    let region = CountRegion {
        x_min_counts: r.x_min_counts,
        x_max_counts: r.x_max_counts,
        y_min_counts: r.y_min_counts,
        y_max_counts: r.y_max_counts,
    };
    let mut instrument = spm_hal::recording::CommandRecorder::new(sim, 10_000_000);
    let images = take_test_images(&mut instrument, &region, &config).unwrap();
    let ruler = spm_apply::ruler::LatticeRuler::hopg();
    let methods = [
        ImageMethod {
            name: "file".into(),
            correction: ImageCorrection::UserFile(Box::new(set.clone())),
        },
        ImageMethod {
            name: "ruler".into(),
            correction: ImageCorrection::UserFileRuler {
                set: Box::new(set.clone()),
                ruler,
            },
        },
    ];
    let bench = evaluate_images(&images, &methods, &config).unwrap();
    // DUMP=k writes image k's heights as a PGM (`/tmp/ruler_probe_k.pgm`, top row first).
    if let Some(k) = std::env::var("DUMP")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
    {
        let m = &images[k].map;
        let (lo, hi) = m
            .z_counts
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
        let mut out = format!("P2\n{} {}\n255\n", m.columns, m.rows).into_bytes();
        for row in (0..m.rows).rev() {
            for c in 0..m.columns {
                let v = (255.0 * (m.z_counts[row * m.columns + c] - lo) / (hi - lo)) as u8;
                out.extend(format!("{v} ").bytes());
            }
            out.push(b'\n');
        }
        std::fs::write(format!("/tmp/ruler_probe_{k}.pgm"), out).unwrap();
    }
    for (image, row) in images.iter().zip(&bench.images) {
        let outcome = ruler_outcome(&set, image, &ruler).unwrap();
        let said = match &outcome {
            Ok(e) => format!(
                "indexed {}/{} A {:.3?} tm {:.2} v {:.4?} res {:.4}",
                e.indexed,
                e.atoms,
                e.amplitude_nm,
                e.since_move_s,
                e.drift_nm_per_s,
                e.residual_rms_nm
            ),
            Err(e) => format!("REFUSED: {e}"),
        };
        println!(
            "{:>5} {:>7} {:<18} file {:7.3} % ruler {:7.3} % (sample {:6.3} / {:6.3})  {said}",
            image.size.side_counts(),
            format!("{:?}", image.direction),
            image.place,
            row.figures["file"].position_rms_pct_of_side,
            row.figures["ruler"].position_rms_pct_of_side,
            row.figures["file"].sample_position_rms_pct_of_side,
            row.figures["ruler"].sample_position_rms_pct_of_side,
        );
    }
    for (name, s) in &bench.methods {
        println!(
            "{name}: RMS {:.3} % of side (on the sample {:.3} %), lattice pairs {} failures {}",
            s.position_rms_pct_of_side,
            s.sample_position_rms_pct_of_side,
            s.lattice_pairs,
            s.lattice_failures
        );
    }
}
