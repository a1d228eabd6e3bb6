//! `results.json`, the PNG figures, `report.html` (self-contained, figures embedded) and
//! `docs/RESULTS.md`.
//!
//! The measured tables come first, then the hand-written sections of
//! `docs/results/*.md` (the crates' own benchmark write-ups), as before.
//! `results.json` and the figures are written to the output folder and copied
//! to `docs/results/bench/`, which RESULTS.md references.

use super::{Context, Results, Section};
use crate::XtaskError;
use std::fmt::Write as _;
use std::path::Path;

type Series = (String, Vec<(f64, f64)>);

/// A line/point chart with a logarithmic y axis (spm-plot), written to `path`.
fn chart(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series],
    lines: bool,
) -> Result<Vec<u8>, XtaskError> {
    let style = if lines {
        spm_plot::SeriesStyle::LineAndMarkers
    } else {
        spm_plot::SeriesStyle::Markers
    };
    let png = spm_plot::xy_chart(&spm_plot::XyFigure {
        title: title.to_owned(),
        x_label: x_label.to_owned(),
        y_label: y_label.to_owned(),
        series: series
            .iter()
            .map(|(name, points)| spm_plot::Series {
                name: name.clone(),
                points: points.clone(),
                style,
            })
            .collect(),
        log_y: true,
        y_from_zero: false,
        size: (1000, 560),
    })
    .map_err(|e| XtaskError::step(format!("drawing {}", path.display()), e))?;
    write_png(path, &png)?;
    Ok(png)
}

fn write_png(path: &Path, png: &[u8]) -> Result<(), XtaskError> {
    std::fs::write(path, png)
        .map_err(|e| XtaskError::step(format!("writing {}", path.display()), e))
}

/// A figure of the bench: file name, caption, PNG.
pub struct BenchFigure {
    /// File name in the output folder.
    pub file: String,
    /// Caption.
    pub caption: String,
    /// The PNG.
    pub png: Vec<u8>,
}

/// The category label of each accuracy config: its name, with the plan's distinguishing
/// suffix when the same scanner runs under several plans.
fn config_labels(configs: &[super::accuracy::ConfigAccuracy]) -> Vec<String> {
    configs
        .iter()
        .map(|c| {
            let repeated = configs.iter().filter(|o| o.config == c.config).count() > 1;
            let first_plan = configs
                .iter()
                .find(|o| o.config == c.config)
                .map(|o| o.plan.as_str());
            if repeated && first_plan != Some(c.plan.as_str()) {
                let stem = Path::new(&c.plan)
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_else(|| c.plan.clone());
                format!("{} + {}", c.config, stem.trim_start_matches("plan-hopg-"))
            } else {
                c.config.clone()
            }
        })
        .collect()
}

fn figures(dir: &Path, results: &Results) -> Result<Vec<BenchFigure>, XtaskError> {
    let mut made = Vec::new();
    if let Some(d) = results.drift.measured() {
        let pick = |f: fn(&super::drift::DriftPoint) -> f64| -> Vec<(f64, f64)> {
            d.points
                .iter()
                .map(|p| (p.velocity_angstrom_per_s, f(p)))
                .collect()
        };
        let png = chart(
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
        made.push(BenchFigure {
            file: "drift.png".to_owned(),
            caption: "LCC error against drift velocity".to_owned(),
            png,
        });
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
        let png = chart(
            &dir.join("productivity.png"),
            "Node LCC error against instrument time",
            "simulated instrument time, s",
            "RMS node K error (mean over repeats), %",
            &series,
            false,
        )?;
        made.push(BenchFigure {
            file: "productivity.png".to_owned(),
            caption: "node LCC error against instrument time, per plan variant".to_owned(),
            png,
        });
    }
    if let Some(a) = results.accuracy.measured() {
        let mut series: Vec<spm_plot::CategorySeries> = Vec::new();
        for (k, c) in a.configs.iter().enumerate() {
            for (name, m) in &c.methods {
                let index = match series.iter().position(|s| &s.name == name) {
                    Some(i) => i,
                    None => {
                        series.push(spm_plot::CategorySeries {
                            name: name.clone(),
                            values: vec![None; a.configs.len()],
                        });
                        series.len() - 1
                    }
                };
                series[index].values[k] = Some(m.rms_pm);
            }
        }
        let path = dir.join("accuracy.png");
        let png = spm_plot::category_chart(&spm_plot::CategoryFigure {
            title: "Residual distortion of the static field per method and scanner".to_owned(),
            x_label: "simulated scanner configuration".to_owned(),
            categories: config_labels(&a.configs),
            y_label: "RMS residual distortion, pm".to_owned(),
            series,
            log_y: true,
            size: (1200, 600),
        })
        .map_err(|e| XtaskError::step(format!("drawing {}", path.display()), e))?;
        write_png(&path, &png)?;
        made.push(BenchFigure {
            file: "accuracy.png".to_owned(),
            caption: "residual distortion per method on the three scanners (the bad one also with creep-length pauses)".to_owned(),
            png,
        });
    }
    Ok(made)
}

/// `report.html` of the bench: the run's metadata, the accuracy and image-benchmark tables
/// per scanner, the figures embedded, and which sections were not measured.
fn html(results: &Results, figures: &[BenchFigure]) -> String {
    use spmcal::html::{Cell, Page, Row, accuracy_header, accuracy_row, images_tables};
    let mut page = Page::new(&format!(
        "spmcal benchmark report{}",
        if results.quick { " (--quick)" } else { "" }
    ));
    page.section("metadata", "Run");
    let m = &results.machine;
    let text = |key: &str, label: &str, value: &str| {
        Row::new(key, vec![Cell::text(label), Cell::text(value)])
    };
    let rows = vec![
        text("command", "command", &results.command),
        text("commit", "commit", &results.commit),
        text(
            "uncommitted",
            "uncommitted files",
            &if results.uncommitted.is_empty() {
                "none".to_owned()
            } else {
                results.uncommitted.join(", ")
            },
        ),
        text(
            "quick",
            "reduced run (--quick)",
            if results.quick { "yes" } else { "no" },
        ),
        Row::new(
            "bench_wall_time_s",
            vec![
                Cell::text("bench wall time, s"),
                Cell::number(results.bench_wall_time_s, 1),
            ],
        ),
        text("cpu", "CPU", &m.cpu),
        Row::new(
            "logical_cores",
            vec![Cell::text("logical cores"), Cell::count(m.logical_cores)],
        ),
        text("date_utc", "date (UTC)", &m.date_utc),
        text("rustc", "rustc", &m.rustc),
        text(
            "load_average_start",
            "load average at start",
            &m.load_average_start,
        ),
        text(
            "load_average_end",
            "load average at end",
            &m.load_average_end,
        ),
    ];
    page.table("metadata-table", &["quantity", "value"], &rows);

    page.section("accuracy", "Accuracy per scanner and method");
    match &results.accuracy {
        Section::Measured(a) => {
            for (label, c) in config_labels(&a.configs).iter().zip(&a.configs) {
                let key = label.replace(' ', "");
                page.paragraph_with_id(
                    &format!("config-{key}"),
                    &format!(
                        "{label}: {} (plan {}, {} nodes × {} repeats, {} records, {} given up,                          instrument time {:.0} s)",
                        c.description,
                        c.plan,
                        c.nodes,
                        c.repeats,
                        c.records,
                        c.given_up,
                        c.instrument_time_s
                    ),
                );
                let rows: Vec<Row> = c.methods.iter().map(|(n, a)| accuracy_row(n, a)).collect();
                page.table(&format!("accuracy-{key}"), accuracy_header(), &rows);
                if let Some(images) = &c.images {
                    page.details_start(&format!("{label}: test images (image benchmark)"));
                    images_tables(&mut page, &format!("{key}-"), images);
                    page.details_end();
                }
            }
        }
        Section::Missing { missing } => page.paragraph(&format!("Not measured: {missing}")),
    }
    page.section("figures", "Figures");
    for f in figures {
        page.figure(&f.file, &f.png, &f.caption);
    }
    page.section("missing", "Sections not measured");
    let missing: Vec<String> = [
        ("accuracy", missing(&results.accuracy)),
        ("budget", missing(&results.budget)),
        ("drift", missing(&results.drift)),
        ("productivity", missing(&results.productivity)),
        ("crb", missing(&results.crb)),
        ("speed", missing(&results.speed)),
        ("gwyddion", missing(&results.gwyddion)),
    ]
    .into_iter()
    .filter_map(|(name, why)| why.map(|w| format!("{name}: {w}")))
    .collect();
    page.list("missing-list", &missing);
    page.paragraph(
        "The full tables (budget, CRB, speed, Gwyddion) are in RESULTS.md and results.json          beside this file.",
    );
    page.finish()
}

fn missing<T>(section: &Section<T>) -> Option<&str> {
    match section {
        Section::Measured(_) => None,
        Section::Missing { missing } => Some(missing),
    }
}

fn markdown(results: &Results, figures: &[(String, String)], fragments: &str) -> String {
    let mut md = String::new();
    header_section(&mut md, results);
    accuracy_section(&mut md, &results.accuracy);
    budget_section(&mut md, &results.budget);
    drift_section(&mut md, &results.drift);
    productivity_section(&mut md, &results.productivity);
    crb_section(&mut md, &results.crb);
    speed_section(&mut md, &results.speed);
    gwyddion_section(&mut md, &results.gwyddion);
    super::linalg::markdown(&mut md, &results.linalg);
    nanonis_section(&mut md, &results.nanonis);
    postgres_section(&mut md, &results.postgres);
    vertical_section(&mut md, &results.vertical);
    super::real::markdown(&mut md, &results.real);

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

/// The page's title, the machine and the source it was measured on.
fn header_section(md: &mut String, results: &Results) {
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
}

/// Calibration accuracy against the baselines, per scanner.
fn accuracy_section(md: &mut String, accuracy: &Section<super::accuracy::AccuracyResults>) {
    let _ = writeln!(
        md,
        "## Calibration accuracy against the baselines (DESIGN §11)\n"
    );
    if let Section::Measured(a) = accuracy {
        validation_markdown(md, &a.configs);
    }
    match accuracy {
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
                    images_table(md, images);
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
}

/// Drift insensitivity: skipping, counter-scanning and a single scan.
fn drift_section(md: &mut String, drift: &Section<super::drift::DriftResults>) {
    let _ = writeln!(md, "## Drift insensitivity\n");
    match drift {
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
}

/// Productivity: error against repeats, cycles, instrument time and variant.
fn productivity_section(
    md: &mut String,
    productivity: &Section<super::productivity::ProductivityResults>,
) {
    let _ = writeln!(
        md,
        "## Productivity: error against repeats, cycles, instrument time and variant\n"
    );
    match productivity {
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
}

/// Localisation error against the Cramér–Rao bound.
fn crb_section(md: &mut String, crb: &Section<super::crb::CrbResults>) {
    let _ = writeln!(md, "## Localisation error ÷ Cramér–Rao bound\n");
    match crb {
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
}

/// Speed: calibration, simulator, CDB and correction.
fn speed_section(md: &mut String, speed: &Section<super::speed::SpeedResults>) {
    let _ = writeln!(md, "## Speed\n");
    match speed {
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
}

/// Gwyddion side by side.
fn gwyddion_section(md: &mut String, gwyddion: &Section<super::gwyddion::GwyddionResults>) {
    let _ = writeln!(md, "## Gwyddion side by side\n");
    match gwyddion {
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
fn images_table(md: &mut String, images: &spm_evaluation::images::ImageBenchmark) {
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
/// The Nanonis backend's overhead over loopback TCP (issue 14).
fn nanonis_section(md: &mut String, section: &Section<super::nanonis::NanonisResults>) {
    let _ = writeln!(md, "## A Nanonis controller over TCP: overhead\n");
    match section {
        Section::Measured(r) => {
            let _ = writeln!(
                md,
                "The same calibration ({} nodes, one pass; fastest of {} runs per side) in process \
                 and through `spmcal nanonis-sim` over loopback TCP (`[backend] kind = \"nanonis\"`). \
                 Wall time only: the simulated instrument time per node is the same on both sides \
                 ({:.1} s).\n\n\
                 | in process, ms per node | over TCP, ms per node | TCP ÷ in process | protocol commands per node | one round trip, µs (median) |\n\
                 |---|---|---|---|---|\n\
                 | {:.2} | {:.2} | {:.2} | {:.0} | {:.0} |\n\n\
                 Target ≤ 1.5×. Every protocol command is a round trip on loopback; the ratio \
                 grows with machine load (other builds on these 2 cores).\n",
                r.nodes,
                r.repeats,
                r.instrument_s_per_node,
                r.in_process_ms_per_node,
                r.tcp_ms_per_node,
                r.ratio,
                r.commands_per_node,
                r.round_trip_us
            );
        }
        Section::Missing { missing } => {
            let _ = writeln!(md, "Not measured: {missing}\n");
        }
    }
}

/// The CDB on SQLite and on a shared PostgreSQL database (issue 16).
fn postgres_section(md: &mut String, section: &Section<super::postgres::PostgresResults>) {
    let _ = writeln!(
        md,
        "## The calibration database: SQLite and shared PostgreSQL\n"
    );
    match section {
        Section::Measured(r) => {
            let _ = writeln!(
                md,
                "PostgreSQL {} (a private server, fsync on) beside the SQLite file \
                 (`synchronous = FULL`).\n\n\
                 | back end | records | insert s (one transaction) | records/s | query s | query + fit s |\n\
                 |---|---|---|---|---|---|",
                r.server_version
            );
            for b in &r.bulk {
                let _ = writeln!(
                    md,
                    "| {} | {} | {:.2} | {:.0} | {:.2} | {:.2} |",
                    b.backend,
                    b.records,
                    b.insert_s,
                    b.insert_records_per_s,
                    b.query_s,
                    b.query_and_fit_s
                );
            }
            let _ = writeln!(
                md,
                "\nConcurrent calibrations into one database (one scanner each):\n\n\
                 | back end | calibrations | wall s | records reported | stored | lost | duplicated | visits pending | check |\n\
                 |---|---|---|---|---|---|---|---|---|"
            );
            for c in &r.concurrent {
                let _ = writeln!(
                    md,
                    "| {} | {} | {:.1} | {} | {} | {} | {} | {} | {} |",
                    c.backend,
                    c.calibrations,
                    c.wall_time_s,
                    c.records_reported,
                    c.records_stored,
                    c.records_lost,
                    c.records_duplicated,
                    c.visits_pending,
                    if c.check_clean {
                        "clean"
                    } else {
                        "**problems**"
                    }
                );
            }
            let _ = writeln!(
                md,
                "\nThe SIGKILL-and-resume test runs on both back ends \
                 (`cargo test -p spmcal --test it crash:: -- --nocapture` prints the kills survived).\n"
            );
        }
        Section::Missing { missing } => {
            let _ = writeln!(md, "Not measured: {missing}\n");
        }
    }
}

/// The vertical axis against the oracle (issue 15).
fn vertical_section(md: &mut String, section: &Section<super::vertical::VerticalResults>) {
    let _ = writeln!(md, "## The vertical axis: Kz, the bowl, Z levels\n");
    match section {
        Section::Measured(r) => {
            let opt = |v: Option<f64>, digits: usize| {
                v.map_or_else(|| "—".to_owned(), |v| format!("{v:.digits$}"))
            };
            let _ = writeln!(
                md,
                "`spmcal calibrate --config {}` with every effect on: {} records, Kz measured at {} \
                 visits ({} without a step in reach), {:.1} s wall time.\n",
                r.job, r.records, r.kz_measured, r.kz_no_step_in_reach, r.wall_time_s
            );
            if let Some(v) = &r.vertical {
                let _ = writeln!(
                    md,
                    "| Kz surface error mean % | max % | bowl residual (fraction of the bowl) | z-dependence of K̄x, K̄y within 2σ |\n\
                     |---|---|---|---|\n\
                     | {} | {} | {} | {} |\n",
                    opt(v.kz_mean_error_pct, 3),
                    opt(v.kz_max_error_pct, 3),
                    opt(v.bowl_residual_fraction, 3),
                    v.z_crosstalk_recovered
                        .map_or("—", |ok| if ok { "yes" } else { "**no**" })
                );
            }
            let _ = writeln!(
                md,
                "A Kz drifting 3 %/h, unknown to the calibration: residual trend {} %/h, t = {} \
                 ({}).\n",
                opt(r.hidden_kz_drift_trend_pct_per_hour, 2),
                opt(r.hidden_kz_drift_trend_t, 1),
                if r.hidden_kz_drift_flagged {
                    "flagged as a structured residual"
                } else {
                    "**not flagged**"
                }
            );
        }
        Section::Missing { missing } => {
            let _ = writeln!(md, "Not measured: {missing}\n");
        }
    }
}

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
    let html_path = ctx.out.join("report.html");
    std::fs::write(&html_path, html(results, &figures))
        .map_err(|e| XtaskError::step(format!("writing {}", html_path.display()), e))?;
    let figures: Vec<(String, String)> = figures.into_iter().map(|f| (f.file, f.caption)).collect();
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

/// The validation every run reports without an oracle (issue 24 item 6), per accuracy run:
/// the held-out prediction, the repeat agreement and the corrected standard's lattice.
fn validation_markdown(md: &mut String, configs: &[super::accuracy::ConfigAccuracy]) {
    use std::fmt::Write as _;
    let _ = writeln!(
        md,
        "### Validation without an oracle (every run, every backend)\n\n\
         Held out: RMS of (measured − predicted)/(σ·√(1 + h)) over the records of the nodes left \
         out of a second fit (target 0.8–1.5). Repeats: pooled repeat scatter ÷ the records' \
         stated uncertainty (K̄x, K̄y, α). Lattice: the standard imaged after the run at 3 × 3 \
         places and corrected as `spmcal correct` does; RMS lattice-constant error over the \
         places measured (uncorrected in brackets), largest angle error.\n\n\
         | scanner | held out (records) | verdict | repeats: scatter ÷ stated | verdict | lattice: RMS % (uncorrected) | max angle ° | places measured | verdict |\n\
         |---|---|---|---|---|---|---|---|---|"
    );
    for c in configs {
        let v = &c.validation;
        let h = &v.held_out;
        let ratios: Vec<String> = v
            .repeats
            .coefficients
            .iter()
            .map(|r| format!("{:.2}", r.scatter_over_stated))
            .collect();
        let (lattice, angle, places, verdict) = match &v.lattice {
            Some(l) => (
                format!(
                    "{:.2} ({:.2})",
                    l.corrected_rms_error_pct, l.uncorrected_rms_error_pct
                ),
                format!("{:.2}", l.corrected_max_angle_error_deg),
                format!("{}/{}", l.corrected_measured, l.places.len()),
                l.verdict.as_str().to_owned(),
            ),
            None => (
                "-".to_owned(),
                "-".to_owned(),
                "-".to_owned(),
                v.lattice_failure
                    .clone()
                    .unwrap_or_else(|| "not taken".to_owned()),
            ),
        };
        let _ = writeln!(
            md,
            "| {} ({}) | {:.2} ({}) | {} | {} | {} | {lattice} | {angle} | {places} | {verdict} |",
            c.config,
            c.plan,
            h.rms_z,
            h.records_held_out,
            h.verdict.as_str(),
            ratios.join(" / "),
            v.repeats.verdict.as_str(),
        );
    }
    let _ = writeln!(md);
}
