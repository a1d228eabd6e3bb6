//! `results.json`, the PNG figures and `docs/RESULTS.md`.
//!
//! The measured tables come first, then the hand-written sections of
//! `docs/results/*.md` (the crates' own benchmark write-ups), as before.
//! `results.json` and the figures are written to the output folder and copied
//! to `docs/results/bench/`, which RESULTS.md references.

use super::{Context, Results, Section};
use crate::XtaskError;
use plotters::prelude::*;
use std::fmt::Write as _;
use std::path::Path;

type Series = (String, Vec<(f64, f64)>);

const COLOURS: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(23, 190, 207),
];

/// A line/point chart with a logarithmic y axis.
fn chart(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series],
    lines: bool,
) -> Result<(), XtaskError> {
    let fail =
        |e: &dyn std::fmt::Display| XtaskError::step(format!("drawing {}", path.display()), e);
    let points = series.iter().flat_map(|s| s.1.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for &(x, y) in points {
        if x.is_finite() && y.is_finite() && y > 0.0 {
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
    }
    if !(x0.is_finite() && y0.is_finite()) {
        return Err(fail(&"no finite points"));
    }
    let pad = (x1 - x0).max(1e-9) * 0.05;
    let (x0, x1) = (x0 - pad, x1 + pad);
    // Head-room above the data for the legend.
    let (y0, y1) = (y0 / 1.5, y1 * 6.0);
    let root = BitMapBackend::new(path, (800, 520)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| fail(&e))?;
    let text = spm_modelcheck::register_system_font();
    let mut builder = ChartBuilder::on(&root);
    builder.margin(15);
    if text {
        builder
            .caption(title, ("sans-serif", 20))
            .x_label_area_size(40)
            .y_label_area_size(70);
    }
    let mut ctx = builder
        .build_cartesian_2d(x0..x1, (y0..y1).log_scale())
        .map_err(|e| fail(&e))?;
    if text {
        ctx.configure_mesh()
            .x_desc(x_label)
            .y_desc(y_label)
            .draw()
            .map_err(|e| fail(&e))?;
    }
    for (k, (name, data)) in series.iter().enumerate() {
        let colour = COLOURS[k % COLOURS.len()];
        let data: Vec<(f64, f64)> = data
            .iter()
            .copied()
            .filter(|p| p.0.is_finite() && p.1.is_finite() && p.1 > 0.0)
            .collect();
        if lines {
            let drawn = ctx
                .draw_series(LineSeries::new(data.clone(), colour.stroke_width(2)))
                .map_err(|e| fail(&e))?;
            if text {
                drawn.label(name.as_str()).legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                });
            }
            ctx.draw_series(data.iter().map(|&p| Circle::new(p, 4, colour.filled())))
                .map_err(|e| fail(&e))?;
        } else {
            let drawn = ctx
                .draw_series(data.iter().map(|&p| Circle::new(p, 5, colour.filled())))
                .map_err(|e| fail(&e))?;
            if text {
                drawn
                    .label(name.as_str())
                    .legend(move |(x, y)| Circle::new((x + 10, y), 5, colour.filled()));
            }
        }
    }
    if text {
        ctx.configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .position(SeriesLabelPosition::UpperRight)
            .draw()
            .map_err(|e| fail(&e))?;
    }
    root.present().map_err(|e| fail(&e))
}

fn figures(dir: &Path, results: &Results) -> Result<Vec<(String, String)>, XtaskError> {
    let mut made = Vec::new();
    if let Some(d) = results.drift.measured() {
        let pick = |f: fn(&super::drift::DriftPoint) -> f64| -> Vec<(f64, f64)> {
            d.points
                .iter()
                .map(|p| (p.velocity_angstrom_per_s, f(p)))
                .collect()
        };
        chart(
            &dir.join("drift.png"),
            "LCC error against drift velocity",
            "drift velocity, Å/s",
            "RMS vector (LCC) error, %",
            &[
                ("skipping".to_owned(), pick(|p| p.skipping_pct)),
                ("counter-scanning".to_owned(), pick(|p| p.counter_scan_pct)),
                (
                    "single aperture scan".to_owned(),
                    pick(|p| p.single_scan_pct),
                ),
            ],
            true,
        )?;
        made.push((
            "drift.png".to_owned(),
            "LCC error against drift velocity".to_owned(),
        ));
    }
    if let Some(p) = results.productivity.measured() {
        let mut series: Vec<Series> = Vec::new();
        for point in &p.points {
            let name = if point.variant == "fig3a-feature-a" {
                format!("Fig. 3a, l = {}, cycles = {}", point.repeats, point.cycles)
            } else {
                point.variant.clone()
            };
            let key = if point.variant == "fig3a-feature-a" {
                if point.cycles == 2 {
                    "Fig. 3a: repeats l (2 cycles)"
                } else {
                    "Fig. 3a: cycles (l = 1)"
                }
                .to_owned()
            } else {
                name
            };
            match series.iter_mut().find(|s| s.0 == key) {
                Some(s) => {
                    s.1.push((point.instrument_time_s, point.node_mean_k_rms_pct))
                }
                None => series.push((
                    key,
                    vec![(point.instrument_time_s, point.node_mean_k_rms_pct)],
                )),
            }
        }
        chart(
            &dir.join("productivity.png"),
            "Node LCC error against instrument time",
            "simulated instrument time, s",
            "RMS node K error (mean over repeats), %",
            &series,
            false,
        )?;
        made.push((
            "productivity.png".to_owned(),
            "node LCC error against instrument time, per plan variant".to_owned(),
        ));
    }
    if let Some(a) = results.accuracy.measured() {
        let mut series: Vec<Series> = Vec::new();
        for (k, c) in a.configs.iter().enumerate() {
            for (name, m) in &c.methods {
                let point = (k as f64, m.rms_pm);
                match series.iter_mut().find(|s| &s.0 == name) {
                    Some(s) => s.1.push(point),
                    None => series.push((name.clone(), vec![point])),
                }
            }
        }
        chart(
            &dir.join("accuracy.png"),
            "Residual distortion: 0 = mild, 1 = typical, 2 = bad, 3 = bad with creep-length pauses",
            "scanner config",
            "RMS residual distortion, pm",
            &series,
            true,
        )?;
        made.push((
            "accuracy.png".to_owned(),
            "residual distortion per method on the three scanners (the bad one also with creep-length pauses)".to_owned(),
        ));
    }
    Ok(made)
}

fn missing<T>(section: &Section<T>) -> Option<&str> {
    match section {
        Section::Measured(_) => None,
        Section::Missing { missing } => Some(missing),
    }
}

fn markdown(results: &Results, figures: &[(String, String)], fragments: &str) -> String {
    let mut md = String::new();
    let m = &results.machine;
    let _ = writeln!(md, "# Results\n");
    let _ = writeln!(
        md,
        "Generated by `{}` on {} (UTC): {}, {} logical cores, {}. Every figure below was \
         measured in that one run (bench wall time {:.0} s); ratios compare figures of the same \
         run. Load average (1/5/15 min) {} at the start, {} at the end: other work on this \
         shared machine inflates wall-clock times, all-threads figures most. Machine-readable: \
         [`results/bench/results.json`](results/bench/results.json).\n",
        results.command,
        m.date_utc,
        m.cpu,
        m.logical_cores,
        m.rustc,
        results.bench_wall_time_s,
        m.load_average_start,
        m.load_average_end
    );
    let _ = writeln!(
        md,
        "Source: commit `{}`{}.\n",
        results.commit,
        if results.uncommitted.is_empty() {
            String::new()
        } else {
            format!(
                " plus uncommitted changes (another engineer's work in progress) in {}",
                results
                    .uncommitted
                    .iter()
                    .map(|p| format!("`{p}`"))
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        }
    );
    if results.quick {
        let _ = writeln!(
            md,
            "**This is a `--quick` run**: small plans (3 × 3 nodes), fewer seeds, trials and \
             repeats, CDB at 10⁵ records instead of 10⁶. Run `cargo xtask bench --gwyddion` for \
             the full figures.\n"
        );
    }

    let _ = writeln!(
        md,
        "## Calibration accuracy against the baselines (DESIGN §11)\n"
    );
    match &results.accuracy {
        Section::Measured(a) => {
            if let Some(c) = a.configs.first() {
                let _ = writeln!(
                    md,
                    "Each scanner: one simulated distributed calibration with `{}` ({} nodes × {} \
                     repeats), judged against the simulator's oracle. Methods: **uncorrected** = \
                     nominal sensitivity; **lumped** = K̄x, K̄y, α of the node nearest the centre \
                     everywhere; **affine** = the mean LCCs of all nodes; **polynomial** = per-image \
                     3rd-order polynomial from one slow image of the whole region over a reference \
                     grid with exact positions (drift moves the features during the image — see \
                     the note); **distributed** = the regression surfaces.\n",
                    c.plan, c.nodes, c.repeats
                );
            }
            for c in &a.configs {
                let _ = writeln!(
                    md,
                    "### `configs/{}.toml` with `{}` — {}\n\n{} records{}, instrument time {:.0} s, wall time {:.1} s \
                     ({:.1} ms per node). distributed ÷ lumped RMS = **{:.3}**{}.\n",
                    c.config,
                    c.plan,
                    c.description,
                    c.records,
                    if c.given_up == 0 {
                        String::new()
                    } else {
                        let reasons: Vec<String> = c
                            .given_up_reasons
                            .iter()
                            .map(|(r, n)| format!("{n} {r}"))
                            .collect();
                        format!(" ({} visits given up: {})", c.given_up, reasons.join(", "))
                    },
                    c.instrument_time_s,
                    c.wall_time_s,
                    c.wall_time_per_node_ms,
                    c.distributed_over_lumped_rms,
                    c.distributed_over_polynomial_rms
                        .map_or_else(String::new, |r| format!(
                            "; distributed ÷ polynomial RMS = **{r:.3}**"
                        ))
                );
                let _ = writeln!(
                    md,
                    "| method | RMS pm | max pm | RMS % of a | mean lattice error % | max lattice error % |\n|---|---|---|---|---|---|"
                );
                for (name, m) in &c.methods {
                    let _ = writeln!(
                        md,
                        "| {name} | {:.1} | {:.1} | {:.3} | {:.4} | {:.4} |",
                        m.rms_pm,
                        m.max_pm,
                        m.rms_pct_of_lattice,
                        m.mean_lattice_error_pct,
                        m.max_lattice_error_pct
                    );
                }
                md.push('\n');
                if let Some(images) = &c.images {
                    images_table(&mut md, images);
                }
            }
            if let Some(c) = a.configs.first() {
                for note in &c.notes {
                    let _ = writeln!(md, "- {note}");
                }
                md.push('\n');
            }
        }
        Section::Missing { missing } => {
            let _ = writeln!(md, "Not measured: {missing}\n");
        }
    }

    budget_section(&mut md, &results.budget);
    let _ = writeln!(md, "## Drift insensitivity\n");
    match &results.drift {
        Section::Measured(d) => {
            let _ = writeln!(
                md,
                "Relative error of a lattice vector (= the LCC error it gives) against the drift \
                 speed (along the diagonal), ideal scanner at SNR 10, judged by the oracle's true \
                 atom sites; RMS over {} seeds per speed. Skipping: 4 kept A→B→A cycles \
                 (16×16 px segments, 0.2 ms/px); single aperture scan: the same A→B vector in \
                 one 64×64 px frame at 0.3 ms/px; counter-scanning: drift-free positions of \
                 nearest-neighbour pairs from a direct and a counter 64×64 frame.\n",
                d.seeds
            );
            let _ = writeln!(
                md,
                "| drift Å/s | skipping % | counter-scanning % | single scan % | runs |\n|---|---|---|---|---|"
            );
            for p in &d.points {
                let _ = writeln!(
                    md,
                    "| {:.1} | {:.3} | {:.3} | {:.3} | {} |",
                    p.velocity_angstrom_per_s,
                    p.skipping_pct,
                    p.counter_scan_pct,
                    p.single_scan_pct,
                    p.runs
                );
            }
            let _ = writeln!(
                md,
                "\nAt the fastest drift the single scan's error is **{:.1} ×** skipping's; skipping \
                 at the fastest drift ÷ at rest = **{:.2}**.\n",
                d.single_over_skipping_at_max, d.skipping_fast_over_rest
            );
        }
        Section::Missing { missing } => {
            let _ = writeln!(md, "Not measured: {missing}\n");
        }
    }

    let _ = writeln!(
        md,
        "## Productivity: error against repeats, cycles, instrument time and variant\n"
    );
    match &results.productivity {
        Section::Measured(p) => {
            let _ = writeln!(
                md,
                "`configs/sim-hopg.toml` (room-temperature tube, every effect on) with \
                 `configs/plan-hopg-small.toml` at a 12000-count step ({} nodes per repeat). \
                 K error per record = RMS over records of (K̄x, K̄y measured ÷ oracle − 1); node \
                 K error = the same with each node's K̄x, K̄y averaged over its repeats (what \
                 repeats buy); distributed = \
                 the residual distortion of the fitted surfaces (few nodes, so dominated by the \
                 surface degree the net supports).\n",
                p.nodes
            );
            let _ = writeln!(
                md,
                "| variant | l | cycles | records | instrument time s | K error per record % | node K error % | α error mrad | distributed RMS pm | distributed mean lattice % |\n|---|---|---|---|---|---|---|---|---|---|"
            );
            for q in &p.points {
                let _ = writeln!(
                    md,
                    "| {} | {} | {} | {} | {:.0} | {:.3} | {:.3} | {:.2} | {:.0} | {:.3} |",
                    q.variant,
                    q.repeats,
                    q.cycles,
                    q.records,
                    q.instrument_time_s,
                    q.node_k_rms_pct,
                    q.node_mean_k_rms_pct,
                    q.node_alpha_rms_mrad,
                    q.distributed_rms_pm,
                    q.distributed_mean_lattice_error_pct
                );
            }
            md.push('\n');
        }
        Section::Missing { missing } => {
            let _ = writeln!(md, "Not measured: {missing}\n");
        }
    }

    let _ = writeln!(md, "## Localisation error ÷ Cramér–Rao bound\n");
    match &results.crb {
        Section::Measured(c) => {
            let _ = writeln!(
                md,
                "Synthetic three-cosine HOPG, 16×16 segments over 1.2 a, random sub-pixel offset; \
                 `spm_features::detect` against `profile_cramer_rao` (see the Recognition section below).\n"
            );
            let _ = writeln!(
                md,
                "| SNR | trials | RMS error (counts) | CRB (counts) | ratio | √(2/π)·p·σn/A (counts) | missed |\n|---|---|---|---|---|---|---|"
            );
            for p in &c.points {
                let _ = writeln!(
                    md,
                    "| {} | {} | {:.4} | {:.4} | **{:.3}** | {:.4} | {} |",
                    p.snr,
                    p.trials,
                    p.rms_counts,
                    p.crb_counts,
                    p.ratio,
                    p.design_bound_counts,
                    p.missed
                );
            }
            md.push('\n');
        }
        Section::Missing { missing } => {
            let _ = writeln!(md, "Not measured: {missing}\n");
        }
    }

    let _ = writeln!(md, "## Speed\n");
    match &results.speed {
        Section::Measured(s) => {
            let per_node: Vec<String> = s
                .calibration_ms_per_node
                .iter()
                .map(|(c, ms)| format!("{c} {ms:.1} ms"))
                .collect();
            let _ = writeln!(
                md,
                "- Simulated calibration wall time per node (accuracy runs): {}.",
                if per_node.is_empty() {
                    "not measured".to_owned()
                } else {
                    per_node.join(", ")
                }
            );
            let _ = writeln!(
                md,
                "- Simulator: **{:.2} M pixels/s** (room-temperature tube, every effect on, one thread, trace + retrace).",
                s.simulated_pixels_per_s / 1e6
            );
            let _ = writeln!(
                md,
                "- CDB, {} records: bulk insert {:.2} s ({:.0} records/s); query of all records {:.2} s; query + BIC fit of the surfaces {:.2} s.\n",
                s.cdb.records,
                s.cdb.insert_s,
                s.cdb.insert_records_per_s,
                s.cdb.query_s,
                s.cdb.query_and_fit_s
            );
            let _ = writeln!(
                md,
                "Correction + bilinear resampling (fused), degree-3 surfaces, best of the repeats; \
                 peak memory = resident-set high-water mark above the level before the call \
                 (one thread):\n"
            );
            let _ = writeln!(
                md,
                "| image | 1 thread s | 1 thread M px/s | 1 thread CPU-time M px/s | {} threads s | {} threads M px/s | speed-up | peak +MiB (image MiB) |\n|---|---|---|---|---|---|---|---|",
                s.threads, s.threads
            );
            for c in &s.correction {
                let _ = writeln!(
                    md,
                    "| {}² | {:.3} | {:.1} | {} | {:.3} | {:.1} | {:.2} | {} ({:.0}) |",
                    c.n,
                    c.one_thread_s,
                    c.one_thread_pixels_per_s / 1e6,
                    c.one_thread_cpu_s.map_or_else(
                        || "n/a".to_owned(),
                        |cpu| format!("{:.1}", (c.n * c.n) as f64 / cpu / 1e6)
                    ),
                    c.all_threads_s,
                    c.all_threads_pixels_per_s / 1e6,
                    c.one_thread_s / c.all_threads_s,
                    c.peak_extra_rss_mib
                        .map_or_else(|| "n/a".to_owned(), |m| format!("{m:.0}")),
                    c.image_mib
                );
            }
            md.push('\n');
        }
        Section::Missing { missing } => {
            let _ = writeln!(md, "Not measured: {missing}\n");
        }
    }

    let _ = writeln!(md, "## Gwyddion side by side\n");
    match &results.gwyddion {
        Section::Measured(g) => {
            let _ = writeln!(
                md,
                "Gwyddion {} `gwy_data_field_sample_distorted` (threads off) via \
                 `xtask/gwyddion/harness.c`, on spm-correction's image and coordinate map \
                 (the inverse map of the corrected raster, as source-pixel coordinates). \
                 spm-correction's resampling inverts the forward map itself; Gwyddion is given \
                 the inverse map. Cubic rows compare Gwyddion's B-spline with spm-correction's \
                 Catmull-Rom (different kernels: agreement is to interpolation tolerance only).\n",
                g.version
            );
            let _ = writeln!(
                md,
                "| image → output | Gwyddion bilinear s | spm-correction bilinear s | Gwyddion ÷ spm-correction | spm-correction fused (correction + resampling) s | Gwyddion ÷ fused | Gwyddion B-spline s | spm-correction Catmull-Rom s | ratio | max diff bilinear / cubic (÷ range) | agree |\n|---|---|---|---|---|---|---|---|---|---|---|"
            );
            for r in &g.rows {
                let _ = writeln!(
                    md,
                    "| {}² → {}×{} | {:.3} | {:.3} | **{:.2}** | {:.3} | **{:.2}** | {:.3} | {:.3} | **{:.2}** | {:.1e} / {:.1e} | {} |",
                    r.n,
                    r.output[0],
                    r.output[1],
                    r.gwyddion_bilinear_s,
                    r.spmcal_resample_bilinear_s,
                    r.gwyddion_over_spmcal_bilinear,
                    r.spmcal_fused_bilinear_s,
                    r.gwyddion_over_spmcal_fused,
                    r.gwyddion_bspline_s,
                    r.spmcal_resample_cubic_s,
                    r.gwyddion_bspline_over_spmcal_cubic,
                    r.bilinear_max_rel_diff,
                    r.cubic_max_rel_diff,
                    if r.agree { "yes" } else { "**no**" }
                );
            }
            let _ = writeln!(md, "\nHarness built with `{}`.\n", g.compile);
        }
        Section::Missing { missing } => {
            let _ = writeln!(md, "Peer rows missing: {missing}\n");
        }
    }
    super::linalg::markdown(&mut md, &results.linalg);

    if !figures.is_empty() {
        let _ = writeln!(md, "## Figures\n");
        for (file, caption) in figures {
            let _ = writeln!(md, "![{caption}](results/bench/{file})\n");
        }
    }
    let absent: Vec<&str> = [
        missing(&results.accuracy),
        missing(&results.drift),
        missing(&results.productivity),
        missing(&results.crb),
        missing(&results.speed),
    ]
    .into_iter()
    .flatten()
    .collect();
    if !absent.is_empty() {
        let _ = writeln!(
            md,
            "Sections that failed in this run: {}\n",
            absent.join("; ")
        );
    }
    let _ = writeln!(
        md,
        "---\n\n# Component benchmarks (hand-written, `docs/results/*.md`)\n\n\
         Measured by each crate's own benchmarks and tests; each section names its command and date.\n"
    );
    md.push_str(fragments);
    md
}

fn fragments(root: &Path) -> Result<String, XtaskError> {
    let dir = root.join("docs").join("results");
    let mut paths: Vec<_> = std::fs::read_dir(&dir)
        .map_err(|e| XtaskError::step(format!("reading {}", dir.display()), e))?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    paths.sort();
    let mut text = String::new();
    for path in &paths {
        let fragment = std::fs::read_to_string(path)
            .map_err(|e| XtaskError::step(format!("reading {}", path.display()), e))?;
        // Demote the fragment's headings one level under this part.
        for line in fragment.trim_end().lines() {
            if line.starts_with('#') {
                text.push('#');
            }
            text.push_str(line);
            text.push('\n');
        }
        text.push('\n');
    }
    Ok(text)
}

/// The image benchmark's table of one calibration.
fn images_table(md: &mut String, images: &spmcal::images::ImageBenchmark) {
    let _ = writeln!(
        md,
        "**On test images** ({} images = {} counter-scanned pairs; sides {} counts; dwells {} s; \
         position error against the true tip positions, drift excluded, best rigid motion \
         removed; lattice error on the drift-corrected pairs that resolve atoms). Methods \
         named `bound_*` and `oracle_*` are labelled references, not competitors.\n",
        images.count,
        images.pairs,
        images
            .sizes
            .iter()
            .map(|s| format!("{:.0}", s.side_counts()))
            .collect::<Vec<_>>()
            .join(", "),
        images
            .dwells_s
            .iter()
            .map(|d| format!("{d:.0e}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let _ = writeln!(
        md,
        "| method | position RMS pm | position max pm | position RMS % of side | mean lattice error % | max lattice error % | lattice pairs (failed) |\n|---|---|---|---|---|---|---|"
    );
    for (name, m) in &images.methods {
        let (mean, max) = if m.lattice_pairs == 0 {
            ("—".to_owned(), "—".to_owned())
        } else {
            (
                format!("{:.3}", m.mean_lattice_error_pct),
                format!("{:.3}", m.max_lattice_error_pct),
            )
        };
        let _ = writeln!(
            md,
            "| {name} | {:.1} | {:.1} | {:.3} | {mean} | {max} | {} ({}) |",
            m.position_rms_pm,
            m.position_max_pm,
            m.position_rms_pct_of_side,
            m.lattice_pairs,
            m.lattice_failures
        );
    }
    if let Some(d) = &images.dynamics {
        let _ = writeln!(
            md,
            "\nCreep law identified from the run's {} attachment tracks ({} sightings): weight \
             {:.5} ± {:.5} per element ({} per decade, τ {} … {} s), settled gain {:.3}, γ = {:.4} per \
             decade; track residual {:.3} counts RMS against a fitted creep motion of {:.3} counts RMS.{}",
            d.tracks,
            d.sightings,
            d.creep_weight,
            d.creep_weight_sigma,
            d.elements_per_decade,
            d.time_constants_s[0],
            d.time_constants_s[1],
            d.settled_gain,
            d.gamma_per_decade,
            d.residual_rms_counts,
            d.signal_rms_counts,
            d.note
                .as_ref()
                .map_or_else(String::new, |n| format!(" ({n})"))
        );
    }
    md.push('\n');
}

/// The error budget section.
fn budget_section(md: &mut String, budget: &Section<super::budget::BudgetResults>) {
    let _ = writeln!(md, "## Error budget of the images (issue 12)\n");
    match budget {
        Section::Measured(b) => {
            let _ = writeln!(
                md,
                "`configs/sim-hopg.toml` (random faults off) with `{}`, calibrated and imaged again \
                 with one effect off at a time. Figures: position RMS in % of the image side (mean \
                 over the images) and mean / max lattice error %, per method; the share of an \
                 effect is √(e_all² − e_without²) of the position figure.\n",
                b.plan
            );
            let all = b.rows.first();
            let _ = writeln!(
                md,
                "| variant | distributed pos % side | distributed lattice mean / max % | share of distributed pos % | creep model pos % side | creep model lattice mean / max % | share of creep-model pos % | oracle static field pos % | true-dynamics bound pos % | node K̄x / K̄y RMS %, α mrad |\n|---|---|---|---|---|---|---|---|---|---|"
            );
            let share = |row: &super::budget::BudgetRow, method: &str| -> String {
                match (
                    all.and_then(|a| a.methods.get(method)),
                    row.methods.get(method),
                ) {
                    (Some(a), Some(r)) if row.variant != "every effect on" => {
                        let e = a.position_rms_pct_of_side;
                        let w = r.position_rms_pct_of_side;
                        format!("{:.3}", (e * e - w * w).max(0.0).sqrt())
                    }
                    _ => "—".to_owned(),
                }
            };
            let pos = |row: &super::budget::BudgetRow, method: &str| -> String {
                row.methods.get(method).map_or_else(
                    || "—".to_owned(),
                    |m| format!("{:.3}", m.position_rms_pct_of_side),
                )
            };
            let lat = |row: &super::budget::BudgetRow, method: &str| -> String {
                match row.methods.get(method) {
                    Some(m) if m.lattice_pairs > 0 => format!(
                        "{:.3} / {:.3} ({} pairs)",
                        m.mean_lattice_error_pct, m.max_lattice_error_pct, m.lattice_pairs
                    ),
                    _ => "—".to_owned(),
                }
            };
            for row in &b.rows {
                let _ = writeln!(
                    md,
                    "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
                    row.variant,
                    pos(row, "distributed"),
                    lat(row, "distributed"),
                    share(row, "distributed"),
                    pos(row, "distributed_creep_model"),
                    lat(row, "distributed_creep_model"),
                    share(row, "distributed_creep_model"),
                    pos(row, "oracle_static_field"),
                    pos(row, "bound_distributed_true_dynamics"),
                    row.node_lcc_rms.map_or_else(
                        || "—".to_owned(),
                        |(x, y, a)| format!("{x:.2} / {y:.2}, {a:.1}")
                    ),
                );
            }
            md.push('\n');
        }
        Section::Missing { missing } => {
            let _ = writeln!(md, "Not measured: {missing}\n");
        }
    }
}

pub fn write(ctx: &Context, results: &Results) -> Result<(), XtaskError> {
    let json = serde_json::to_string_pretty(results).map_err(|e| XtaskError::step("json", e))?;
    let results_path = ctx.out.join("results.json");
    std::fs::write(&results_path, &json)
        .map_err(|e| XtaskError::step(format!("writing {}", results_path.display()), e))?;
    let figures = figures(&ctx.out, results)?;
    let md = markdown(results, &figures, &fragments(&ctx.root)?);
    let out_md = ctx.out.join("RESULTS.md");
    std::fs::write(&out_md, &md)
        .map_err(|e| XtaskError::step(format!("writing {}", out_md.display()), e))?;
    if !ctx.write_docs || ctx.quick {
        // Only an explicit `cargo xtask bench --write-docs` rewrites committed files; a smoke
        // run or a run into another folder leaves docs/ as committed.
        println!(
            "wrote {} and {} (docs/ left as committed; --write-docs regenerates it)",
            results_path.display(),
            out_md.display()
        );
        return Ok(());
    }
    let docs = ctx.root.join("docs").join("results").join("bench");
    std::fs::create_dir_all(&docs)
        .map_err(|e| XtaskError::step(format!("creating {}", docs.display()), e))?;
    std::fs::write(docs.join("results.json"), &json)
        .map_err(|e| XtaskError::step("writing docs/results/bench/results.json", e))?;
    for (file, _) in &figures {
        std::fs::copy(ctx.out.join(file), docs.join(file))
            .map_err(|e| XtaskError::step(format!("copying {file}"), e))?;
    }
    let results_md = ctx.root.join("docs").join("RESULTS.md");
    std::fs::write(&results_md, md)
        .map_err(|e| XtaskError::step(format!("writing {}", results_md.display()), e))?;
    println!(
        "wrote {}, {} and docs/results/bench/",
        results_path.display(),
        results_md.display()
    );
    Ok(())
}
