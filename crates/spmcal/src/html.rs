//! `report.html`: one self-contained file (inline CSS, the PNG figures as base64 data URIs,
//! no script, no external resource) written from the same [`CalibrationReport`] that
//! `report.json` serialises.
//!
//! Every section and table has a stable `id`, every row a `data-key` and every number cell
//! its exact value in `data-value` (Rust's shortest round-trip form; `NaN` for a value
//! report.json writes as `null`), so that tests and scripts can read the page back and check
//! it against report.json. [`Page`] is the small builder; `cargo xtask bench` uses it too.

use crate::plots::Figure;
use crate::report::CalibrationReport;
use base64::Engine as _;
use std::fmt::Write as _;

/// Escapes text for HTML element content and attribute values.
pub fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            _ => out.push(c),
        }
    }
    out
}

/// One table cell.
#[derive(Debug, Clone, PartialEq)]
pub enum Cell {
    /// Text.
    Text(String),
    /// A number: the exact value (`data-value`) and its display text.
    Number {
        /// The value.
        value: f64,
        /// As shown.
        text: String,
    },
}

/// `value` with `digits` significant digits: fixed-point in [10⁻³, 10⁶) (at most six decimals),
/// scientific outside; `–` when not finite, `0` for zero. The one number format of what spmcal
/// shows a person (report cells, figure labels, `spmcal info`).
#[must_use]
pub fn significant_text(value: f64, digits: usize) -> String {
    if !value.is_finite() {
        return "–".to_owned();
    }
    if value == 0.0 {
        return "0".to_owned();
    }
    let a = value.abs();
    let digits = digits.max(1);
    if (1e-3..1e6).contains(&a) {
        let decimals = (digits as i64 - 1 - a.log10().floor() as i64).clamp(0, 6) as usize;
        format!("{value:.decimals$}")
    } else {
        format!("{value:.*e}", digits - 1)
    }
}

impl Cell {
    /// A text cell.
    pub fn text(text: impl Into<String>) -> Self {
        Self::Text(text.into())
    }

    /// A number shown with `decimals` decimals (`–` when not finite).
    pub fn number(value: f64, decimals: usize) -> Self {
        let text = if value.is_finite() {
            format!("{value:.decimals$}")
        } else {
            "–".to_owned()
        };
        Self::Number { value, text }
    }

    /// A number shown with three significant digits (`–` when not finite).
    pub fn significant(value: f64) -> Self {
        Self::Number {
            value,
            text: significant_text(value, 3),
        }
    }

    /// A count.
    pub fn count(value: usize) -> Self {
        Self::Number {
            value: value as f64,
            text: value.to_string(),
        }
    }
}

/// The exact form of a value in `data-value`.
pub fn data_value(value: f64) -> String {
    if value.is_nan() {
        "NaN".to_owned()
    } else {
        format!("{value:?}")
    }
}

/// One table row: its key (`data-key`) and cells (the first is the row's header).
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    /// Stable key of the row.
    pub key: String,
    /// The cells.
    pub cells: Vec<Cell>,
}

impl Row {
    /// A row.
    pub fn new(key: impl Into<String>, cells: Vec<Cell>) -> Self {
        Self {
            key: key.into(),
            cells,
        }
    }
}

const STYLE: &str = "\
body{font-family:'DejaVu Sans',Helvetica,Arial,sans-serif;margin:2em auto;max-width:1500px;\
padding:0 1em;color:#1b1b1b;background:#fff;line-height:1.4}\
h1{font-size:1.6em;border-bottom:2px solid #4e79a7;padding-bottom:.2em}\
h2{font-size:1.25em;margin-top:1.8em;color:#284b6e}\
table{border-collapse:collapse;margin:.6em 0;font-size:.92em}\
th,td{border:1px solid #c9ced6;padding:.25em .6em;text-align:right}\
th:first-child,td.text{text-align:left}thead th{background:#eef2f7}\
tbody tr:nth-child(even){background:#f8f9fb}\
div.table-box{overflow-x:auto;max-width:100%}div.table-box>table{margin:.3em 0}\
figure{margin:1em 0;max-width:100%}figure img{display:block;max-width:100%;height:auto;\
box-sizing:border-box;border:1px solid #dde}\
figcaption{font-size:.9em;color:#444}p.note{font-size:.9em;color:#444}\
details{margin:.5em 0}section{margin-bottom:1.5em}";

/// A self-contained HTML page built section by section; all text is escaped.
#[derive(Debug, Clone)]
pub struct Page {
    title: String,
    body: String,
    open_section: bool,
}

impl Page {
    /// A page with `title` (also the first heading).
    pub fn new(title: &str) -> Self {
        let mut body = String::new();
        let _ = writeln!(body, "<h1>{}</h1>", escape(title));
        Self {
            title: title.to_owned(),
            body,
            open_section: false,
        }
    }

    /// Starts a section `<section id=…>` with a heading (closing the previous one).
    pub fn section(&mut self, id: &str, heading: &str) {
        self.close_section();
        let _ = writeln!(
            self.body,
            "<section id=\"{}\">\n<h2>{}</h2>",
            escape(id),
            escape(heading)
        );
        self.open_section = true;
    }

    fn close_section(&mut self) {
        if self.open_section {
            self.body.push_str("</section>\n");
            self.open_section = false;
        }
    }

    /// A paragraph of text.
    pub fn paragraph(&mut self, text: &str) {
        let _ = writeln!(self.body, "<p>{}</p>", escape(text));
    }

    /// A paragraph with a stable id.
    pub fn paragraph_with_id(&mut self, id: &str, text: &str) {
        let _ = writeln!(self.body, "<p id=\"{}\">{}</p>", escape(id), escape(text));
    }

    /// A table with a stable id, column headers and rows.
    pub fn table(&mut self, id: &str, header: &[&str], rows: &[Row]) {
        // Each table scrolls sideways inside its own box on a narrow window (800 px), so
        // the page itself never does.
        let _ = writeln!(
            self.body,
            "<div class=\"table-box\">\n<table id=\"{}\">\n<thead><tr>",
            escape(id)
        );
        for h in header {
            let _ = write!(self.body, "<th>{}</th>", escape(h));
        }
        self.body.push_str("</tr></thead>\n<tbody>\n");
        for row in rows {
            let _ = write!(self.body, "<tr data-key=\"{}\">", escape(&row.key));
            for (k, cell) in row.cells.iter().enumerate() {
                let tag = if k == 0 { "th" } else { "td" };
                match cell {
                    Cell::Text(t) => {
                        let _ = write!(self.body, "<{tag} class=\"text\">{}</{tag}>", escape(t));
                    }
                    Cell::Number { value, text } => {
                        let _ = write!(
                            self.body,
                            "<{tag} data-value=\"{}\">{}</{tag}>",
                            data_value(*value),
                            escape(text)
                        );
                    }
                }
            }
            self.body.push_str("</tr>\n");
        }
        self.body.push_str("</tbody>\n</table>\n</div>\n");
    }

    /// A bulleted list with a stable id.
    pub fn list(&mut self, id: &str, items: &[String]) {
        let _ = writeln!(self.body, "<ul id=\"{}\">", escape(id));
        for item in items {
            let _ = writeln!(self.body, "<li>{}</li>", escape(item));
        }
        self.body.push_str("</ul>\n");
    }

    /// A PNG figure embedded as a data URI, with a caption; `file` is its name in the
    /// report folder (the figure's `id` and `data-file`). Every figure is drawn by spm-plot,
    /// whose smallest text is declared in `data-min-font-px` (image pixels), for
    /// `cargo xtask check-report`'s legibility check at 800 px.
    pub fn figure(&mut self, file: &str, png: &[u8], caption: &str) {
        let id = format!("figure-{}", file.trim_end_matches(".png"));
        let _ = writeln!(
            self.body,
            "<figure id=\"{}\" data-file=\"{}\" data-min-font-px=\"{}\"><img alt=\"{}\" \
             src=\"data:image/png;base64,{}\"><figcaption>{}</figcaption></figure>",
            escape(&id),
            escape(file),
            spm_plot::MIN_FONT_PX,
            escape(caption),
            base64::engine::general_purpose::STANDARD.encode(png),
            escape(caption)
        );
    }

    /// Starts a collapsed block (`<details>`) with a summary line.
    pub fn details_start(&mut self, summary: &str) {
        let _ = writeln!(self.body, "<details><summary>{}</summary>", escape(summary));
    }

    /// Ends the block of [`Page::details_start`].
    pub fn details_end(&mut self) {
        self.body.push_str("</details>\n");
    }

    /// The whole document.
    pub fn finish(mut self) -> String {
        self.close_section();
        format!(
            "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
             <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n\
             <title>{}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n{}</body>\n</html>\n",
            escape(&self.title),
            self.body
        )
    }
}

/// The plan's targets with their verdicts (issue 27), or a sentence that it declares none.
fn targets_section(page: &mut Page, targets: &[crate::targets::TargetVerdict]) {
    page.section("targets", "Targets the plan declares");
    if targets.is_empty() {
        page.paragraph(
            "None: the plan has no [plan.targets] table, so the figures below are reported \
             without a verdict and the exit code does not depend on them.",
        );
        return;
    }
    page.paragraph(
        "Each target the plan declares, the figure measured and the verdict. A simulated run \
         is judged against the simulator's ground truth, a run on an instrument or a stored \
         image by the validation without an oracle; `spmcal calibrate` exits with code 3 when \
         a verdict is FAIL (unless --no-targets).",
    );
    let rows: Vec<Row> = targets
        .iter()
        .enumerate()
        .map(|(k, t)| {
            Row::new(
                k.to_string(),
                vec![
                    Cell::text(&t.target),
                    Cell::text(t.measured.as_deref().unwrap_or("–")),
                    Cell::text(t.outcome.as_str()),
                    Cell::text(t.note.as_deref().unwrap_or("")),
                ],
            )
        })
        .collect();
    page.table(
        "targets-table",
        &["target", "measured", "verdict", "note"],
        &rows,
    );
}

/// The validation without an oracle (every backend): held-out nodes and repeat agreement,
/// each with its verdict.
fn validation_section(page: &mut Page, v: &crate::report::Validation) {
    use spm_evaluation::validation::Verdict;
    page.section(
        "validation",
        "Validation without an oracle (every backend, issue 24)",
    );
    let verdict = |v: Verdict, reason: &Option<String>| match reason {
        Some(r) => format!("{}: {r}", v.as_str()),
        None => v.as_str().to_owned(),
    };
    let h = &v.held_out;
    page.paragraph_with_id(
        "validation-held-out",
        &format!(
            "Held-out nodes: {} of {} nodes (share {}, seed {}) left out of a second fit by the \
             same procedure; their {} records against its prediction. RMS of (measured − \
             predicted)/(σ·√(1 + h)) = {} (pass range {}–{}). Verdict: {}.",
            h.nodes_held_out,
            h.nodes,
            h.share,
            h.seed,
            h.records_held_out,
            if h.rms_z.is_nan() {
                "not measured".to_owned()
            } else {
                format!("{:.2}", h.rms_z)
            },
            h.pass_range[0],
            h.pass_range[1],
            verdict(h.verdict, &h.reason)
        ),
    );
    if !h.coefficients.is_empty() {
        let rows: Vec<Row> = h
            .coefficients
            .iter()
            .map(|c| {
                Row::new(
                    c.coefficient,
                    vec![
                        Cell::text(c.coefficient),
                        Cell::count(c.records),
                        Cell::number(c.rms_z, 2),
                        Cell::number(c.max_abs_z, 2),
                        Cell::significant(c.rms_error),
                        Cell::significant(c.rms_prediction_sd),
                        Cell::text(c.unit),
                    ],
                )
            })
            .collect();
        page.table(
            "validation-held-out-table",
            &[
                "coefficient",
                "records",
                "RMS ratio",
                "max |ratio|",
                "RMS error",
                "RMS predicted σ",
                "unit",
            ],
            &rows,
        );
    }
    let r = &v.repeats;
    page.paragraph_with_id(
        "validation-repeats",
        &format!(
            "Repeat agreement: {} place(s) measured {}. Pooled repeat scatter over \
             the records' stated uncertainty, at most {} to pass. Verdict: {}.",
            r.places,
            match r.repeats {
                0 | 1 => "in two repeats or more".to_owned(),
                2 => "in 2 repeats".to_owned(),
                n => format!("in 2–{n} repeats"),
            },
            r.scatter_over_stated_max,
            verdict(r.verdict, &r.reason)
        ),
    );
    if !r.coefficients.is_empty() {
        let rows: Vec<Row> = r
            .coefficients
            .iter()
            .map(|c| {
                Row::new(
                    c.coefficient,
                    vec![
                        Cell::text(c.coefficient),
                        Cell::significant(c.pooled_scatter),
                        Cell::significant(c.stated_u_rms),
                        Cell::number(c.scatter_over_stated, 2),
                        Cell::significant(c.first_to_last_mean),
                        Cell::significant(c.first_to_last_se),
                        Cell::text(c.unit),
                    ],
                )
            })
            .collect();
        page.table(
            "validation-repeats-table",
            &[
                "coefficient",
                "pooled scatter",
                "stated u (RMS)",
                "scatter ÷ stated",
                "last − first repeat (mean)",
                "its standard error",
                "unit",
            ],
            &rows,
        );
    }
    validation_lattice(page, v, &verdict);
}

/// What the corrected-standard check measured, in words.
fn lattice_source(l: &spm_evaluation::validation::LatticeCheck) -> String {
    match l.measured_on {
        spm_evaluation::validation::LatticeSource::CounterPairs => format!(
            "counter-scanned pairs of {} × {} pixels ({} counts per pixel) at {} places over \
             the calibrated region, taken after the run and corrected as spmcal correct does \
             (the drift removed by each pair)",
            l.pixels,
            l.pixels,
            l.step_counts,
            l.places.len()
        ),
        spm_evaluation::validation::LatticeSource::StoredImageCells => format!(
            "the stored image the run calibrated on ({} pixels per line, {:.3} counts per \
             pixel), corrected whole as spmcal correct does with the run's calibration (beyond \
             the calibrated region too) and its lattice measured in the {} cells of a grid \
             (spmcal lattice); a pair taken from a stored image would only resample its \
             frozen pixels",
            l.pixels,
            l.step_counts,
            l.places.len()
        ),
    }
}

/// The validation's corrected-standard part: the paragraph with its verdict and the table of
/// places.
fn validation_lattice(
    page: &mut Page,
    v: &crate::report::Validation,
    verdict: &dyn Fn(spm_evaluation::validation::Verdict, &Option<String>) -> String,
) {
    match (&v.lattice, &v.lattice_failure) {
        (Some(l), _) => {
            page.paragraph_with_id(
                "validation-lattice",
                &format!(
                    "Corrected standard: {}. Lattice \
                     constant measured at {} places: RMS error {:.2} % (uncorrected {:.2} %), \
                     max {:.2} %; angles max {:.2}°. Pass: ≤ {} % and ≤ {}° everywhere. \
                     Verdict: {}. {}",
                    lattice_source(l),
                    l.corrected_measured,
                    l.corrected_rms_error_pct,
                    l.uncorrected_rms_error_pct,
                    l.corrected_max_error_pct,
                    l.corrected_max_angle_error_deg,
                    l.thresholds[0],
                    l.thresholds[1],
                    verdict(l.verdict, &l.reason),
                    if l.dynamics_applied {
                        format!(
                            "The calibration file holds scanner dynamics, which spmcal correct \
                             applies; with the static surfaces alone (--static) the lattice is \
                             measured at {} places, RMS error {:.2} %; with each pair's \
                             counter-scanned partner (--counter) at {} places, RMS error {:.2} %.",
                            l.static_measured,
                            l.static_rms_error_pct,
                            l.counter_measured,
                            l.counter_rms_error_pct
                        )
                    } else {
                        String::new()
                    }
                ),
            );
            let opt = |v: Option<f64>, digits: usize| match v {
                Some(v) => Cell::number(v, digits),
                None => Cell::text("not measured"),
            };
            // The static and counter-partner columns only where something was measured in
            // them (a calibration with dynamics, measured on pairs).
            let others = l.static_measured > 0 || l.counter_measured > 0;
            let rows: Vec<Row> = l
                .places
                .iter()
                .map(|p| {
                    let mut cells = vec![
                        Cell::text(p.place.clone()),
                        opt(p.uncorrected_error_pct, 2),
                        opt(p.uncorrected_angle_error_deg, 2),
                        opt(p.corrected_error_pct, 2),
                        opt(p.corrected_angle_error_deg, 2),
                    ];
                    if others {
                        cells.extend([
                            opt(p.static_error_pct, 2),
                            opt(p.static_angle_error_deg, 2),
                            opt(p.counter_error_pct, 2),
                            opt(p.counter_angle_error_deg, 2),
                        ]);
                    }
                    Row::new(p.place.clone(), cells)
                })
                .collect();
            let header = [
                "place",
                "uncorrected: lattice constant error, %",
                "uncorrected: largest angle error, °",
                "corrected: lattice constant error, %",
                "corrected: largest angle error, °",
                "static surfaces only: lattice constant error, %",
                "static surfaces only: largest angle error, °",
                "with the counter partner: lattice constant error, %",
                "with the counter partner: largest angle error, °",
            ];
            page.table(
                "validation-lattice-table",
                &header[..if others { header.len() } else { 5 }],
                &rows,
            );
        }
        (None, Some(why)) => page.paragraph_with_id(
            "validation-lattice",
            &format!("Corrected standard: not measured ({why})."),
        ),
        (None, None) => page.paragraph_with_id(
            "validation-lattice",
            "Corrected standard: not asked for (validation.lattice_places_per_side = 0, or the \
             nodes span no area).",
        ),
    }
}

/// Columns of an accuracy table (report.json `accuracy.<method>`).
const ACCURACY_HEADER: [&str; 6] = [
    "method",
    "RMS residual, pm",
    "max residual, pm",
    "RMS, % of lattice constant",
    "mean |lattice error|, %",
    "max |lattice error|, %",
];

/// One accuracy row.
pub fn accuracy_row(method: &str, a: &spm_evaluation::accuracy::Accuracy) -> Row {
    Row::new(
        method,
        vec![
            Cell::text(method),
            Cell::number(a.rms_pm, 1),
            Cell::number(a.max_pm, 1),
            Cell::number(a.rms_pct_of_lattice, 2),
            Cell::number(a.mean_lattice_error_pct, 3),
            Cell::number(a.max_lattice_error_pct, 3),
        ],
    )
}

/// The accuracy table's header.
pub fn accuracy_header() -> &'static [&'static str] {
    &ACCURACY_HEADER
}

/// Columns of the image benchmark's per-method table (report.json `images.methods`).
const IMAGES_HEADER: [&str; 10] = [
    "method",
    "position RMS, pm",
    "position max, pm",
    "position RMS, % of side",
    "on the sample (drift included), % of side",
    "mean |lattice error|, %",
    "max |lattice error|, %",
    "max lattice-angle error, °",
    "lattice pairs",
    "lattice failures",
];

/// The competitors (per-image trace/retrace methods from their papers) keep the nominal map on
/// the images they refuse: a paragraph says how many (none when no competitor ran).
fn competitor_refusals(
    page: &mut Page,
    prefix: &str,
    images: &spm_evaluation::images::ImageBenchmark,
) {
    let refusals: Vec<String> = images
        .methods
        .iter()
        .filter_map(|(name, m)| {
            m.refused_images
                .map(|r| format!("{name}: {r} of {}", images.count))
        })
        .collect();
    if !refusals.is_empty() {
        page.paragraph_with_id(
            &format!("{prefix}images-competitors"),
            &format!(
                "competitors (corrections from each image's own trace and retrace, after their \
                 papers; shown with the real methods, an image a competitor refuses keeps the \
                 nominal map) — images refused: {}",
                refusals.join("; ")
            ),
        );
    }
}

/// The image benchmark: the summary line, per-method table and the identified dynamics;
/// `prefix` makes the ids unique when a page holds several.
pub fn images_tables(
    page: &mut Page,
    prefix: &str,
    images: &spm_evaluation::images::ImageBenchmark,
) {
    page.paragraph_with_id(
        &format!("{prefix}images-summary"),
        &format!(
            "{} test images ({} counter-scanned pairs), sizes {}, pixel dwells {} s",
            images.count,
            images.pairs,
            images
                .sizes
                .iter()
                .map(|s| format!("{} px × {} counts", s.pixels, s.step_counts))
                .collect::<Vec<_>>()
                .join(", "),
            images
                .dwells_s
                .iter()
                .map(|d| format!("{d}"))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    );
    let rows: Vec<Row> = images
        .methods
        .iter()
        .map(|(name, m)| {
            Row::new(
                name,
                vec![
                    Cell::text(name),
                    Cell::number(m.position_rms_pm, 1),
                    Cell::number(m.position_max_pm, 1),
                    Cell::number(m.position_rms_pct_of_side, 3),
                    Cell::number(m.sample_position_rms_pct_of_side, 3),
                    Cell::number(m.mean_lattice_error_pct, 3),
                    Cell::number(m.max_lattice_error_pct, 3),
                    Cell::number(m.max_lattice_angle_error_deg, 3),
                    Cell::count(m.lattice_pairs),
                    Cell::count(m.lattice_failures),
                ],
            )
        })
        .collect();
    page.table(&format!("{prefix}images-methods"), &IMAGES_HEADER, &rows);
    competitor_refusals(page, prefix, images);
    if !images.images.is_empty() {
        // Per image: every method's position RMS (report.json `images.images`).
        let methods: Vec<&String> = images.methods.keys().collect();
        let mut header: Vec<String> = [
            "image",
            "place",
            "side, counts",
            "pixel dwell, s",
            "direction",
        ]
        .iter()
        .map(|h| (*h).to_owned())
        .collect();
        header.extend(methods.iter().map(|m| format!("{m}: position RMS, pm")));
        let header: Vec<&str> = header.iter().map(String::as_str).collect();
        let rows: Vec<Row> = images
            .images
            .iter()
            .enumerate()
            .map(|(k, image)| {
                let mut cells = vec![
                    Cell::text(format!("pair {} {}", image.pair, image.direction)),
                    Cell::text(&image.place),
                    Cell::significant(image.side_counts),
                    Cell::significant(image.dwell_s),
                    Cell::text(&image.direction),
                ];
                cells.extend(methods.iter().map(|m| {
                    image
                        .figures
                        .get(*m)
                        .map_or(Cell::text("–"), |f| Cell::number(f.position_rms_pm, 1))
                }));
                Row::new(k.to_string(), cells)
            })
            .collect();
        page.details_start(&format!("every image ({})", images.images.len()));
        page.table(&format!("{prefix}images-per-image"), &header, &rows);
        page.details_end();
    }
    if let Some(d) = &images.dynamics {
        let rows = vec![
            Row::new(
                "creep_weight",
                vec![
                    Cell::text("creep weight w"),
                    Cell::significant(d.creep_weight),
                ],
            ),
            Row::new(
                "creep_weight_sigma",
                vec![
                    Cell::text("its standard error"),
                    Cell::significant(d.creep_weight_sigma),
                ],
            ),
            Row::new(
                "settled_gain",
                vec![
                    Cell::text("settled creep gain W"),
                    Cell::significant(d.settled_gain),
                ],
            ),
            Row::new(
                "gamma_per_decade",
                vec![
                    Cell::text("log slope γ per decade"),
                    Cell::significant(d.gamma_per_decade),
                ],
            ),
            Row::new(
                "tracks",
                vec![Cell::text("attachment tracks used"), Cell::count(d.tracks)],
            ),
            Row::new(
                "sightings",
                vec![Cell::text("sightings used"), Cell::count(d.sightings)],
            ),
            Row::new(
                "residual_rms_counts",
                vec![
                    Cell::text("track residual RMS, counts"),
                    Cell::significant(d.residual_rms_counts),
                ],
            ),
        ];
        page.table(
            &format!("{prefix}images-dynamics"),
            &["creep law identified from the run", "value"],
            &rows,
        );
        if let Some(note) = &d.note {
            page.paragraph(note);
        }
    }
}

/// The scanner dynamics the run identified: the loop at each ladder size (against the
/// simulator's own where there is one), the creep's log slope and what was not identified.
fn dynamics_section(page: &mut Page, report: &CalibrationReport) {
    let Some(d) = &report.dynamics else {
        return;
    };
    page.section("dynamics", "Scanner dynamics identified in situ");
    page.paragraph(&format!(
        "{} of {} ladder frames used ({} same-point sightings, {} from the attachment tracks). \
         The fast axis's hysteresis loop (branch separation at its centre, counts) at each \
         ladder line:",
        d.frames_used, d.frames, d.ladder_sightings, d.track_sightings
    ));
    let optional = |v: Option<f64>| v.map_or_else(|| Cell::text("—"), Cell::significant);
    let loop_rows = |prefix: &str, loops: &[crate::dynamics::LoopRow]| -> Vec<Row> {
        loops
            .iter()
            .map(|l| {
                Row::new(
                    format!("{prefix}-{}", l.length_counts),
                    vec![
                        Cell::significant(l.length_counts),
                        Cell::significant(l.separation_centre_counts),
                        optional(l.true_separation_centre_counts),
                        optional(l.ratio),
                    ],
                )
            })
            .collect()
    };
    page.table(
        "dynamics-loops",
        &[
            "line (counts)",
            "identified (counts)",
            "simulator's (counts)",
            "identified / simulator's",
        ],
        &loop_rows("loop", &d.loops_x),
    );
    if !d.loops_y.is_empty() {
        page.paragraph(&format!(
            "The slow axis's loop, from {} of {} counter-scanned pairs ({} same-point \
             sightings along y):",
            d.slow_pairs_used, d.slow_pairs, d.slow_sightings
        ));
        page.table(
            "dynamics-loops-y",
            &[
                "frame height (counts)",
                "identified (counts)",
                "simulator's (counts)",
                "identified / simulator's",
            ],
            &loop_rows("loop-y", &d.loops_y),
        );
    }
    let gamma = |v: Option<f64>| v.map_or_else(|| "—".to_owned(), |g| significant_text(g, 3));
    page.paragraph(&format!(
        "Creep log slope γ per decade: {} (joint fit), {} (attachment tracks alone), {} (the \
         simulator's).",
        gamma(d.creep_gamma_per_decade),
        gamma(d.track_creep_gamma_per_decade),
        gamma(d.true_creep_gamma_per_decade)
    ));
    let trials = d
        .model
        .as_ref()
        .map_or(&[][..], |m| &m.identification.creep_fast_end_trials[..]);
    if !trials.is_empty() {
        page.paragraph(&format!(
            "The creep law's shortest time constant, chosen by the joint fit's residual: {} s \
             (the simulator's: {} s). Each candidate's fit:",
            gamma(d.creep_min_time_constant_s),
            gamma(d.true_creep_min_time_constant_s)
        ));
        let rows: Vec<Row> = trials
            .iter()
            .map(|t| {
                Row::new(
                    format!("fast-end-{}", t.min_time_constant_s),
                    vec![
                        Cell::significant(t.min_time_constant_s),
                        Cell::significant(t.residual_rms_counts),
                        Cell::significant(t.creep_weight),
                    ],
                )
            })
            .collect();
        page.table(
            "dynamics-fast-end",
            &[
                "shortest time constant (s)",
                "residual RMS (counts)",
                "creep weight per element",
            ],
            &rows,
        );
    }
    if !d.notes.is_empty() {
        page.list("dynamics-notes", &d.notes);
    }
}

/// The calibration report page: metadata, accuracy per method, the image benchmark, the
/// regression surfaces with σ and Δmax, given-up nodes with reasons, the drift history,
/// the figures and the notes: one section after another, in reading order.
pub fn calibration_page(report: &CalibrationReport, figures: &[Figure]) -> String {
    let run = &report.run;
    let mut page = Page::new(&format!(
        "spmcal calibration report: run {} of scanner {}",
        run.run_id, report.scanner_id
    ));
    run_section(&mut page, report, figures);
    accuracy_section(&mut page, report, figures);
    images_section(&mut page, report);
    regression_section(&mut page, report, figures);
    given_up_section(&mut page, report);
    drift_section(&mut page, report, figures);
    trajectory_and_notes_section(&mut page, report, figures);
    page.finish()
}

/// Adds the figure `file` to the page when it was drawn.
fn figure(page: &mut Page, figures: &[Figure], file: &str) {
    if let Some(f) = figures.iter().find(|f| f.file == file) {
        page.figure(&f.file, &f.png, &f.caption);
    }
}

/// The run: ids, counts, times, provenance, targets, validation and the before/after image.
fn run_section(page: &mut Page, report: &CalibrationReport, figures: &[Figure]) {
    let run = &report.run;
    page.section("metadata", "Run");
    let text_row = |key: &str, label: &str, value: &str| {
        Row::new(key, vec![Cell::text(label), Cell::text(value)])
    };
    let num_row = |key: &str, label: &str, cell: Cell| Row::new(key, vec![Cell::text(label), cell]);
    let rows = vec![
        text_row("run_id", "run id", &run.run_id),
        text_row("scanner_id", "scanner id", &report.scanner_id),
        num_row("nodes", "nodes per repeat", Cell::count(report.nodes)),
        num_row("repeats", "repeats l", Cell::count(report.repeats as usize)),
        num_row(
            "visits_planned",
            "visits planned",
            Cell::count(run.visits_planned),
        ),
        num_row(
            "already_finished",
            "visits finished before this invocation",
            Cell::count(run.already_finished),
        ),
        num_row(
            "nodes_done",
            "visits measured now",
            Cell::count(run.nodes_done),
        ),
        num_row(
            "given_up",
            "visits given up",
            Cell::count(run.given_up.len()),
        ),
        num_row(
            "records",
            "records in the CDB",
            Cell::number(report.records as f64, 0),
        ),
        num_row(
            "cycles_kept",
            "skipping cycles kept",
            Cell::count(run.cycles.kept as usize),
        ),
        num_row(
            "cycles_discarded",
            "skipping cycles spoiled (discarded)",
            Cell::count(run.cycles.discarded as usize),
        ),
        num_row(
            "cycles_idle",
            "idle cycles",
            Cell::count(run.cycles.idle as usize),
        ),
        num_row(
            "cycles_restarts",
            "skipping restarts",
            Cell::count(run.cycles.restarts as usize),
        ),
        num_row(
            "transient_errors",
            "transient backend errors",
            Cell::count(run.transient_errors as usize),
        ),
        num_row(
            "instrument_time_s",
            "instrument time, s",
            Cell::number(report.instrument_time_s, 1),
        ),
        num_row(
            "wall_time_s",
            "wall time, s",
            Cell::number(report.wall_time_s, 2),
        ),
        num_row(
            "wall_time_per_node_ms",
            "wall time per measured node, ms",
            Cell::number(report.wall_time_per_node_ms, 1),
        ),
        text_row(
            "interrupted",
            "interrupted",
            if run.interrupted { "yes" } else { "no" },
        ),
    ];
    page.table("metadata-table", &["quantity", "value"], &rows);
    match &report.provenance {
        Some(p) => {
            let mut rows = vec![
                text_row("started_utc", "started (UTC)", &p.started_utc),
                text_row("finished_utc", "run finished (UTC)", &p.finished_utc),
                text_row("spmcal_version", "spmcal version", &p.spmcal_version),
                text_row(
                    "spmcal_commit",
                    "spmcal commit",
                    p.spmcal_commit.as_deref().unwrap_or("unknown"),
                ),
                text_row("host", "host", p.host.as_deref().unwrap_or("unknown")),
                text_row("backend", "backend", &p.backend),
            ];
            if let Some(seed) = p.seed {
                rows.push(num_row(
                    "seed",
                    "simulator seed",
                    Cell::count(seed as usize),
                ));
            }
            for (k, f) in p.inputs.iter().enumerate() {
                rows.push(text_row(
                    &format!("input-{k}"),
                    &format!("input: {}", f.path),
                    f.sha256
                        .as_deref()
                        .map_or("unreadable".to_owned(), |d| format!("SHA-256 {d}"))
                        .as_str(),
                ));
            }
            page.table("provenance-table", &["provenance", "value"], &rows);
        }
        None => page.paragraph("Provenance: not recorded by the caller."),
    }

    targets_section(page, &report.targets);
    validation_section(page, &report.validation);
    figure(page, figures, crate::plots::VALIDATION_MAP_FILE);
    if figures
        .iter()
        .any(|f| f.file == crate::plots::BEFORE_AFTER_FILE)
    {
        page.paragraph(
            "The next figure shows one of these images of the standard before and after the \
             correction on one colour scale: compare the spacing of the atoms across the image \
             and in each direction; after a good correction it is the same everywhere.",
        );
        figure(page, figures, crate::plots::BEFORE_AFTER_FILE);
    }
}

/// Accuracy against the oracle: per method, the residual map, the node LCCs.
fn accuracy_section(page: &mut Page, report: &CalibrationReport, figures: &[Figure]) {
    page.section("accuracy", "Accuracy against the simulator's ground truth");
    match &report.accuracy {
        Some(a) => {
            let mut rows = vec![
                accuracy_row("uncorrected", &a.uncorrected),
                accuracy_row("lumped", &a.lumped),
                accuracy_row("affine", &a.affine),
            ];
            if let Some(p) = &a.polynomial {
                rows.push(accuracy_row("polynomial", p));
            }
            rows.push(accuracy_row("distributed", &a.distributed));
            page.table("accuracy-table", accuracy_header(), &rows);
            page.paragraph_with_id(
                "accuracy-ratio",
                &format!(
                    "distributed RMS ÷ lumped RMS = {:.3} (the plan's target, if it declares \
                     one, is judged in the Targets section)",
                    a.distributed_over_lumped_rms
                ),
            );
        }
        None => page.paragraph("Not measured: needs a simulated backend (the oracle)."),
    }
    if figures
        .iter()
        .any(|f| f.file == crate::plots::RESIDUAL_FILE)
    {
        page.paragraph(
            "The next figure maps the distributed row of this table over the field: at each \
             point, how many nm a corrected position still lies from the truth. Read it for \
             where the calibration is weakest (bright), not only how good it is on average.",
        );
        figure(page, figures, crate::plots::RESIDUAL_FILE);
    }
    if let Some(e) = &report.node_lcc_error {
        page.paragraph(&format!(
            "Measured node LCCs against the true LCCs at the LCS centres ({} records):",
            e.n
        ));
        let rows = vec![
            Row::new(
                "kx",
                vec![
                    Cell::text("Kx, %"),
                    Cell::number(e.kx_mean_pct, 4),
                    Cell::number(e.kx_rms_pct, 4),
                ],
            ),
            Row::new(
                "ky",
                vec![
                    Cell::text("Ky, %"),
                    Cell::number(e.ky_mean_pct, 4),
                    Cell::number(e.ky_rms_pct, 4),
                ],
            ),
            Row::new(
                "alpha",
                vec![
                    Cell::text("α, mrad"),
                    Cell::number(e.alpha_mean_mrad, 4),
                    Cell::number(e.alpha_rms_mrad, 4),
                ],
            ),
        ];
        page.table(
            "node-lcc-error",
            &["coefficient", "mean error", "RMS error"],
            &rows,
        );
    }
}

/// The image benchmark.
fn images_section(page: &mut Page, report: &CalibrationReport) {
    page.section(
        "images",
        "Test images taken after the run (image benchmark)",
    );
    match &report.images {
        Some(images) => images_tables(page, "", images),
        None => page.paragraph(
            "Not measured: needs a simulated backend (and is skipped when the image benchmark \
             is off).",
        ),
    }
}

/// The regression surfaces with σ and Δmax, their figures.
fn regression_section(page: &mut Page, report: &CalibrationReport, figures: &[Figure]) {
    page.section("regression", "Regression surfaces (plane nearest z = 0)");
    let r = &report.regression;
    let surface_row =
        |key: &str, label: &str, unit: &str, scale: f64, s: &crate::surfaces::SurfaceSummary| {
            Row::new(
                key,
                vec![
                    Cell::text(label),
                    Cell::count(s.degree as usize),
                    Cell::significant(s.sigma * scale),
                    Cell::significant(s.delta_max * scale),
                    Cell::text(unit),
                ],
            )
        };
    let mut rows = vec![
        surface_row("kx", "Kx (x sensitivity)", "pm/count", 1e3, &r.kx),
        surface_row("ky", "Ky (y sensitivity)", "pm/count", 1e3, &r.ky),
        surface_row("alpha", "α (non-orthogonality)", "mrad", 1e3, &r.alpha),
    ];
    if let Some(kz) = &r.kz {
        rows.push(surface_row("kz", "Kz (z sensitivity)", "pm/count", 1e3, kz));
    }
    page.table(
        "regression-table",
        &["coefficient", "degree", "σ", "Δmax", "unit"],
        &rows,
    );
    page.paragraph(
        "σ: the residual standard deviation of the fit (eq. 14); Δmax: the largest deviation of \
         the surface from its value at the field origin over the records' extent (eq. 13). \
         Values shown in the unit of the last column (report.json holds nm/count and rad).",
    );
    for file in ["lcc-kx.png", "lcc-ky.png", "lcc-alpha.png"] {
        figure(page, figures, file);
    }
    page.paragraph(
        "The next figure shows how far each fitted surface itself may be off over the field \
         (one standard uncertainty, from the fit's design and σ): small where the records are \
         dense, growing towards the corners, where the surface extrapolates.",
    );
    figure(page, figures, crate::plots::UNCERTAINTY_FILE);

    dynamics_section(page, report);
}

/// Given-up nodes with their reasons.
fn given_up_section(page: &mut Page, report: &CalibrationReport) {
    let run = &report.run;
    page.section("given-up", "Given-up nodes");
    if run.given_up.is_empty() {
        page.paragraph("None: every visit of this invocation was measured.");
    }
    let rows: Vec<Row> = run
        .given_up
        .iter()
        .enumerate()
        .map(|(k, g)| {
            let code = serde_json::to_value(&g.reason)
                .ok()
                .and_then(|v| v.get("reason").and_then(|r| r.as_str()).map(str::to_owned))
                .unwrap_or_default();
            Row::new(
                k.to_string(),
                vec![
                    Cell::count(g.repeat_index as usize),
                    Cell::count(g.node_index as usize),
                    Cell::text(format!("({}, {}, {})", g.node[0], g.node[1], g.node[2])),
                    Cell::text(code),
                    Cell::text(g.reason.to_string()),
                ],
            )
        })
        .collect();
    page.table(
        "given-up-table",
        &[
            "repeat",
            "node",
            "node position, counts",
            "reason",
            "explanation",
        ],
        &rows,
    );
}

/// The drift history and the CDB history of the scanner.
fn drift_section(page: &mut Page, report: &CalibrationReport, figures: &[Figure]) {
    page.section("drift", "Drift history");
    let d = &report.drift;
    let mut rows = vec![
        Row::new(
            "estimates",
            vec![Cell::text("drift estimates"), Cell::count(d.estimates)],
        ),
        Row::new(
            "spoiled",
            vec![
                Cell::text("of which spoiled cycles (discarded)"),
                Cell::count(d.spoiled),
            ],
        ),
        Row::new(
            "nominal_nm_per_count",
            vec![
                Cell::text("nominal sensitivity used for nm, nm/count"),
                Cell::significant(d.nominal_nm_per_count),
            ],
        ),
    ];
    if let Some([t0, t1]) = d.time_span_s {
        rows.push(Row::new(
            "time_first_s",
            vec![
                Cell::text("first estimate, instrument time, s"),
                Cell::number(t0, 1),
            ],
        ));
        rows.push(Row::new(
            "time_last_s",
            vec![
                Cell::text("last estimate, instrument time, s"),
                Cell::number(t1, 1),
            ],
        ));
    }
    if let Some([lo, median, hi]) = d.speed_min_median_max_nm_per_s {
        for (key, label, v) in [
            ("speed_min", "smallest kept speed, nm/s", lo),
            ("speed_median", "median kept speed, nm/s", median),
            ("speed_max", "largest kept speed, nm/s", hi),
        ] {
            rows.push(Row::new(key, vec![Cell::text(label), Cell::significant(v)]));
        }
    }
    page.table("drift-table", &["quantity", "value"], &rows);
    figure(page, figures, "drift.png");

    if figures.iter().any(|f| f.file == crate::plots::HISTORY_FILE) {
        page.section("history", "Calibration history of the scanner (the CDB)");
        page.paragraph(
            "Every run of this scanner in the calibration database: read the line against its \
             band; a step larger than the bands between two runs means the scanner changed \
             (or was handled) between them, and the newest calibration is the one to use.",
        );
        figure(page, figures, crate::plots::HISTORY_FILE);
    }
}

/// The nodes in visiting order and how the figures were measured.
fn trajectory_and_notes_section(page: &mut Page, report: &CalibrationReport, figures: &[Figure]) {
    page.section("trajectory", "Nodes in visiting order");
    figure(page, figures, "trajectory.png");

    page.section("notes", "How the figures were measured");
    page.list("notes-list", &report.notes);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check(input: &str, expected: &str) {
        assert_eq!(escape(input), expected, "escape({input:?})");
    }

    #[test]
    fn escapes_markup_and_quotes() {
        check("a<b>&\"c'", "a&lt;b&gt;&amp;&quot;c&#39;");
        check("σ = 0.1 µm", "σ = 0.1 µm");
        check("</table><script>", "&lt;/table&gt;&lt;script&gt;");
    }

    #[test]
    fn numbers_keep_their_exact_value() {
        assert_eq!(data_value(0.1 + 0.2), "0.30000000000000004");
        assert_eq!(data_value(f64::NAN), "NaN");
        assert_eq!(data_value(3.0), "3.0");
        match Cell::significant(0.012345) {
            Cell::Number { text, .. } => assert_eq!(text, "0.0123"),
            Cell::Text(_) => panic!("a number cell"),
        }
        match Cell::number(f64::INFINITY, 2) {
            Cell::Number { text, .. } => assert_eq!(text, "–"),
            Cell::Text(_) => panic!("a number cell"),
        }
    }
}
