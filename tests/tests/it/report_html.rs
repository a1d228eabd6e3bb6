//! `report.html` read back with an HTML parser and checked section by section against
//! `report.json` of the same run: metadata, accuracy per method, the image benchmark, the
//! regression surfaces with σ and Δmax, the given-up nodes with reasons, the drift history,
//! every figure (the embedded bytes are the PNG files) and the notes. A second page, from
//! the same report with a given-up node and markup in a note added, checks the given-up
//! rows and the escaping.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;
use base64::Engine as _;
use scraper::{ElementRef, Html, Selector};
use serde_json::Value;
use spm_calibration::{GiveUpReason, GivenUpVisit};
use spmcal::plots::Figure;

fn sel(s: &str) -> Selector {
    Selector::parse(s).unwrap()
}

/// The row `key` of table `table`: its cells (th and td).
fn row<'a>(doc: &'a Html, table: &str, key: &str) -> Vec<ElementRef<'a>> {
    let rows: Vec<ElementRef<'a>> = doc
        .select(&sel(&format!("table#{table} tbody tr[data-key=\"{key}\"]")))
        .collect();
    assert_eq!(rows.len(), 1, "table #{table}: one row {key}");
    rows[0].select(&sel("th, td")).collect()
}

fn rows<'a>(doc: &'a Html, table: &str) -> Vec<ElementRef<'a>> {
    doc.select(&sel(&format!("table#{table} tbody tr")))
        .collect()
}

fn text(cell: &ElementRef<'_>) -> String {
    cell.text().collect()
}

/// The cell's exact value against report.json's (JSON null = a non-finite value, NaN).
fn check_number(cell: &ElementRef<'_>, expected: &Value, what: &str) {
    let attr = cell
        .value()
        .attr("data-value")
        .unwrap_or_else(|| panic!("{what}: no data-value"));
    let got: f64 = attr.parse().unwrap_or_else(|_| panic!("{what}: {attr}"));
    match expected.as_f64() {
        Some(v) => assert_eq!(got, v, "{what}"),
        None => assert!(
            got.is_nan() && expected.is_null(),
            "{what}: {attr} vs {expected}"
        ),
    }
    assert!(!text(cell).trim().is_empty(), "{what}: shown");
}

fn scaled(v: &Value, factor: f64) -> Value {
    serde_json::json!(v.as_f64().unwrap() * factor)
}

fn check_page(html: &str, json: &Value, figures: &[Figure]) {
    let doc = Html::parse_document(html);
    // Self-contained: no script, no external resource.
    for forbidden in ["script", "link", "iframe", "object", "[href]"] {
        assert_eq!(doc.select(&sel(forbidden)).count(), 0, "{forbidden}");
    }
    for img in doc.select(&sel("img")) {
        assert!(
            img.value()
                .attr("src")
                .unwrap()
                .starts_with("data:image/png;base64,")
        );
    }
    for id in [
        "metadata",
        "targets",
        "accuracy",
        "images",
        "regression",
        "given-up",
        "drift",
        "notes",
    ] {
        assert_eq!(
            doc.select(&sel(&format!("section#{id}"))).count(),
            1,
            "{id}"
        );
    }

    // Metadata.
    let run = &json["run"];
    assert_eq!(
        text(&row(&doc, "metadata-table", "run_id")[1]),
        run["run_id"]
    );
    assert_eq!(
        text(&row(&doc, "metadata-table", "scanner_id")[1]),
        json["scanner_id"]
    );
    for (key, value) in [
        ("nodes", &json["nodes"]),
        ("repeats", &json["repeats"]),
        ("records", &json["records"]),
        ("visits_planned", &run["visits_planned"]),
        ("already_finished", &run["already_finished"]),
        ("nodes_done", &run["nodes_done"]),
        ("cycles_kept", &run["cycles"]["kept"]),
        ("cycles_discarded", &run["cycles"]["discarded"]),
        ("cycles_idle", &run["cycles"]["idle"]),
        ("cycles_restarts", &run["cycles"]["restarts"]),
        ("transient_errors", &run["transient_errors"]),
        ("instrument_time_s", &json["instrument_time_s"]),
        ("wall_time_s", &json["wall_time_s"]),
        ("wall_time_per_node_ms", &json["wall_time_per_node_ms"]),
    ] {
        check_number(&row(&doc, "metadata-table", key)[1], value, key);
    }
    let given_up = run["given_up"].as_array().unwrap();
    check_number(
        &row(&doc, "metadata-table", "given_up")[1],
        &serde_json::json!(given_up.len()),
        "given_up",
    );

    // The plan's targets, each verdict as report.json has it.
    let targets = json["targets"].as_array().unwrap();
    if targets.is_empty() {
        assert_eq!(doc.select(&sel("table#targets-table")).count(), 0);
    }
    for (k, t) in targets.iter().enumerate() {
        let cells = row(&doc, "targets-table", &k.to_string());
        assert_eq!(text(&cells[0]), t["target"]);
        assert_eq!(text(&cells[1]), t["measured"].as_str().unwrap_or("–"));
        let verdict = text(&cells[2]);
        assert_eq!(
            verdict.to_lowercase().replace(' ', "_"),
            t["outcome"].as_str().unwrap(),
            "target {k}"
        );
    }

    // Accuracy per method.
    let accuracy = json["accuracy"].as_object().expect("simulated: accuracy");
    let methods = [
        "uncorrected",
        "lumped",
        "affine",
        "polynomial",
        "distributed",
    ];
    assert_eq!(rows(&doc, "accuracy-table").len(), methods.len());
    for method in methods {
        let cells = row(&doc, "accuracy-table", method);
        for (k, field) in [
            "rms_pm",
            "max_pm",
            "rms_pct_of_lattice",
            "mean_lattice_error_pct",
            "max_lattice_error_pct",
        ]
        .iter()
        .enumerate()
        {
            check_number(
                &cells[k + 1],
                &accuracy[method][field],
                &format!("{method} {field}"),
            );
        }
    }

    // The image benchmark.
    let images = json["images"]["methods"].as_object().expect("images");
    assert_eq!(rows(&doc, "images-methods").len(), images.len());
    for (method, m) in images {
        let cells = row(&doc, "images-methods", method);
        for (k, field) in [
            "position_rms_pm",
            "position_max_pm",
            "position_rms_pct_of_side",
            "sample_position_rms_pct_of_side",
            "mean_lattice_error_pct",
            "max_lattice_error_pct",
            "max_lattice_angle_error_deg",
            "lattice_pairs",
            "lattice_failures",
        ]
        .iter()
        .enumerate()
        {
            check_number(
                &cells[k + 1],
                &m[field],
                &format!("images {method} {field}"),
            );
        }
    }
    let per_image = json["images"]["images"].as_array().unwrap();
    assert_eq!(rows(&doc, "images-per-image").len(), per_image.len());
    let method_names: Vec<&String> = images.keys().collect();
    for (k, image) in per_image.iter().enumerate() {
        let cells = row(&doc, "images-per-image", &k.to_string());
        assert_eq!(text(&cells[1]), image["place"]);
        check_number(&cells[2], &image["side_counts"], "image side");
        check_number(&cells[3], &image["dwell_s"], "image dwell");
        assert_eq!(text(&cells[4]), image["direction"]);
        for (m, name) in method_names.iter().enumerate() {
            check_number(
                &cells[5 + m],
                &image["figures"][name.as_str()]["position_rms_pm"],
                &format!("image {k} {name}"),
            );
        }
    }
    let summary = doc
        .select(&sel("p#images-summary"))
        .next()
        .map(|p| text(&p))
        .unwrap();
    assert!(
        summary.starts_with(&format!("{} test images", json["images"]["count"])),
        "{summary}"
    );

    // Regression surfaces: degree, σ and Δmax (pm/count and mrad: × 1000).
    for key in ["kx", "ky", "alpha"] {
        let cells = row(&doc, "regression-table", key);
        let s = &json["regression"][key];
        check_number(&cells[1], &s["degree"], &format!("{key} degree"));
        check_number(&cells[2], &scaled(&s["sigma"], 1e3), &format!("{key} σ"));
        check_number(
            &cells[3],
            &scaled(&s["delta_max"], 1e3),
            &format!("{key} Δmax"),
        );
    }

    // Given-up nodes with reasons.
    assert_eq!(rows(&doc, "given-up-table").len(), given_up.len());
    for (k, g) in given_up.iter().enumerate() {
        let cells = row(&doc, "given-up-table", &k.to_string());
        check_number(&cells[0], &g["repeat_index"], "given-up repeat");
        check_number(&cells[1], &g["node_index"], "given-up node");
        assert_eq!(text(&cells[3]), g["reason"]["reason"], "given-up reason");
        assert!(!text(&cells[4]).is_empty());
    }

    // Drift history.
    let drift = &json["drift"];
    check_number(
        &row(&doc, "drift-table", "estimates")[1],
        &drift["estimates"],
        "estimates",
    );
    check_number(
        &row(&doc, "drift-table", "spoiled")[1],
        &drift["spoiled"],
        "spoiled",
    );
    let points = drift["points"].as_array().unwrap();
    assert_eq!(points.len() as u64, drift["estimates"].as_u64().unwrap());
    assert_eq!(
        points.iter().filter(|p| p["spoiled"] == true).count() as u64,
        drift["spoiled"].as_u64().unwrap()
    );
    // Every marked estimate is a cycle the run counted as spoiled (a cycle without a finite
    // velocity has no estimate to mark).
    assert!(drift["spoiled"].as_u64().unwrap() <= run["cycles"]["discarded"].as_u64().unwrap());
    let speeds = &drift["speed_min_median_max_nm_per_s"];
    for (k, key) in ["speed_min", "speed_median", "speed_max"]
        .iter()
        .enumerate()
    {
        check_number(&row(&doc, "drift-table", key)[1], &speeds[k], key);
    }

    // Every figure, byte for byte.
    assert_eq!(doc.select(&sel("figure")).count(), figures.len());
    for f in figures {
        let figure = doc
            .select(&sel(&format!("figure[data-file=\"{}\"]", f.file)))
            .next()
            .unwrap_or_else(|| panic!("{} embedded", f.file));
        let src = figure
            .select(&sel("img"))
            .next()
            .unwrap()
            .value()
            .attr("src")
            .unwrap();
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(src.trim_start_matches("data:image/png;base64,"))
            .unwrap();
        assert!(bytes == f.png, "{}: embedded bytes are the file", f.file);
    }

    // Notes, verbatim (escaping undone by the parser).
    let notes: Vec<String> = doc
        .select(&sel("ul#notes-list li"))
        .map(|li| text(&li))
        .collect();
    let expected: Vec<String> = json["notes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n.as_str().unwrap().to_owned())
        .collect();
    assert_eq!(notes, expected);
}

#[test]
fn report_html_matches_report_json() {
    // The shared small net with its image benchmark (`common::small_net`): the page and
    // report.json it wrote, and the figures beside them.
    let calibration = common::small_net(true, true);
    let file = |name: &str| -> Vec<u8> {
        calibration
            .files
            .get(name)
            .unwrap_or_else(|| panic!("{name} written"))
            .clone()
    };
    let figures: Vec<Figure> = [
        "lcc-kx.png",
        "lcc-ky.png",
        "lcc-alpha.png",
        "lcc-uncertainty.png",
        "trajectory.png",
        "drift.png",
        "residual-distortion.png",
        "cdb-history.png",
    ]
    .iter()
    .map(|name| Figure {
        file: (*name).to_owned(),
        caption: String::new(),
        png: file(name),
    })
    .collect();
    let html = String::from_utf8(file("report.html")).unwrap();
    let json: Value = serde_json::from_slice(&file("report.json")).unwrap();
    check_page(&html, &json, &figures);
    let mut report = calibration.report.clone();

    // The same report with a given-up node and markup in a note: rows and escaping.
    report.run.given_up.push(GivenUpVisit {
        repeat_index: 0,
        node_index: 7,
        node: [100, -200, 0],
        reason: GiveUpReason::NoLcs,
    });
    report
        .notes
        .push("<script>alert('x')</script> & \"quoted\"".to_owned());
    // Declared targets: a missed ratio and the validation (not judged on a simulator).
    report.targets = spmcal::targets::judge_figures(
        Some(2.0),
        &report.validation,
        &spm_calibration::run_validation::RunTargets {
            distributed_over_lumped_rms_max: Some(0.1),
            validation_pass: true,
        },
        true,
    );
    assert_eq!(report.targets.len(), 4);
    let html = spmcal::html::calibration_page(&report, &figures);
    let json = serde_json::to_value(&report).unwrap();
    check_page(&html, &json, &figures);
    assert!(
        html.contains("&lt;script&gt;alert(&#39;x&#39;)&lt;/script&gt; &amp; &quot;quoted&quot;")
    );
}
