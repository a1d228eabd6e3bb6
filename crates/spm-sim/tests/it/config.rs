//! Shipped configs parse and equal the named constructors; bad configs give
//! typed errors naming the field (and the line where TOML gives it).
#![allow(clippy::unwrap_used)]

use spm_sim::{ConfigError, SimConfig};
use std::path::PathBuf;

fn config_path(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../configs")
        .join(name)
}

fn hopg_text() -> String {
    std::fs::read_to_string(config_path("sim-hopg.toml")).unwrap()
}

#[test]
fn shipped_files_parse_validate_and_equal_the_constructors() {
    let hopg = SimConfig::from_file(config_path("sim-hopg.toml")).unwrap();
    assert_eq!(hopg, SimConfig::room_temperature_tube());
    let ideal = SimConfig::from_file(config_path("sim-ideal.toml")).unwrap();
    assert_eq!(ideal, SimConfig::ideal());
    hopg.validate().unwrap();
    ideal.validate().unwrap();
}

#[test]
fn a_missing_file_names_the_file() {
    let e = SimConfig::from_file("/nonexistent/sim.toml").unwrap_err();
    assert!(matches!(e, ConfigError::Io { .. }));
    assert!(e.to_string().contains("/nonexistent/sim.toml"));
}

#[test]
fn an_unknown_field_is_named_with_its_line() {
    let text = hopg_text().replace(
        "corrugation_nm = 0.08",
        "corrugation_nm = 0.08\ncorugation_typo_nm = 0.1",
    );
    let e = SimConfig::from_toml_str(&text, "x.toml").unwrap_err();
    assert!(matches!(e, ConfigError::Parse { .. }), "{e}");
    assert_eq!(e.field(), Some("surface.hopg.corugation_typo_nm"), "{e}");
    let line = text
        .lines()
        .position(|l| l.starts_with("corugation_typo_nm"))
        .unwrap()
        + 1;
    assert_eq!(e.line(), Some(line), "{e}");
    assert!(e.to_string().contains("x.toml"), "{e}");
}

#[test]
fn a_wrong_type_is_named_with_its_line() {
    let text = hopg_text().replace("max_lines = 4096", "max_lines = \"many\"");
    let e = SimConfig::from_toml_str(&text, "x.toml").unwrap_err();
    assert!(matches!(e, ConfigError::Parse { .. }), "{e}");
    assert_eq!(e.field(), Some("instrument.max_lines"), "{e}");
    let line = text
        .lines()
        .position(|l| l.starts_with("max_lines"))
        .unwrap()
        + 1;
    assert_eq!(e.line(), Some(line), "{e}");
}

#[test]
fn a_negative_pixel_count_is_rejected_naming_the_field() {
    let text = hopg_text().replace("max_pixels_per_line = 4096", "max_pixels_per_line = -5");
    let e = SimConfig::from_toml_str(&text, "x.toml").unwrap_err();
    assert_eq!(e.field(), Some("instrument.max_pixels_per_line"), "{e}");
    assert!(e.line().is_some());
    let text = hopg_text().replace("max_pixels_per_line = 4096", "max_pixels_per_line = 0");
    let e = SimConfig::from_toml_str(&text, "x.toml").unwrap_err();
    assert!(matches!(e, ConfigError::Invalid { .. }), "{e}");
    assert_eq!(e.field(), Some("instrument.max_pixels_per_line"), "{e}");
}

#[test]
fn nan_and_infinities_are_rejected_naming_the_field_path_and_line() {
    let text = hopg_text().replace(
        "nonlinearity_x = { quadratic = 0.03, cubic = 0.05 }",
        "nonlinearity_x = { quadratic = 0.03, cubic = nan }",
    );
    let e = SimConfig::from_toml_str(&text, "x.toml").unwrap_err();
    assert!(matches!(e, ConfigError::Invalid { .. }), "{e}");
    assert_eq!(e.field(), Some("scanner.nonlinearity_x.cubic"), "{e}");
    let line = text
        .lines()
        .position(|l| l.starts_with("nonlinearity_x"))
        .unwrap()
        + 1;
    assert_eq!(e.line(), Some(line), "{e}");

    let text = hopg_text().replace("min_time_constant_s = 0.02", "min_time_constant_s = -inf");
    let e = SimConfig::from_toml_str(&text, "x.toml").unwrap_err();
    assert_eq!(e.field(), Some("scanner.creep.min_time_constant_s"), "{e}");

    let text = hopg_text().replace(
        "sensitivity_x_nm_per_count = 0.02",
        "sensitivity_x_nm_per_count = 0.0",
    );
    let e = SimConfig::from_toml_str(&text, "x.toml").unwrap_err();
    assert_eq!(e.field(), Some("scanner.sensitivity_x_nm_per_count"), "{e}");
    let line = text
        .lines()
        .position(|l| l.starts_with("sensitivity_x_nm_per_count"))
        .unwrap()
        + 1;
    assert_eq!(e.line(), Some(line), "{e}");

    let text = hopg_text().replace("width_nm = 0.5", "width_nm = -0.5");
    let e = SimConfig::from_toml_str(&text, "x.toml").unwrap_err();
    assert_eq!(e.field(), Some("surface.hopg.steps[0].width_nm"), "{e}");
    assert!(e.line().is_some(), "{e}");
}

#[test]
fn an_embedded_section_reports_the_full_path() {
    #[derive(serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Bigger {
        backend: Backend,
    }
    #[derive(serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Backend {
        kind: String,
        sim: SimConfig,
    }
    let inner = hopg_text();
    // Re-root every table of the simulator config under [backend.sim].
    let mut text = String::from("[backend]\nkind = \"sim\"\n[backend.sim]\n");
    for line in inner.lines() {
        if let Some(rest) = line.strip_prefix("[[") {
            text.push_str(&format!("[[backend.sim.{rest}\n"));
        } else if let Some(rest) = line.strip_prefix('[') {
            text.push_str(&format!("[backend.sim.{rest}\n"));
        } else {
            text.push_str(line);
            text.push('\n');
        }
    }
    let bigger: Bigger = toml::from_str(&text).unwrap();
    assert_eq!(bigger.backend.kind, "sim");
    assert_eq!(bigger.backend.sim, SimConfig::room_temperature_tube());
    let mut bad = bigger.backend.sim.clone();
    bad.drift.warmup_time_constant_s = f64::NAN;
    let e = bad.validate_with_prefix("backend.sim.").unwrap_err();
    assert_eq!(e.field, "backend.sim.drift.warmup_time_constant_s");
}
