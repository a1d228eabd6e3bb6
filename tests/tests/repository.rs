//! Repository checks as ordinary tests: the invariants of docs/ARCHITECTURE.md.

use std::path::{Path, PathBuf};

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the tests package lives inside the workspace")
        .to_path_buf()
}

fn crate_names() -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(workspace_root().join("crates"))
        .expect("crates/ exists")
        .filter_map(Result::ok)
        .filter(|entry| entry.path().join("Cargo.toml").is_file())
        .map(|entry| entry.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

fn normal_dependencies(crate_name: &str) -> Vec<String> {
    let path = workspace_root()
        .join("crates")
        .join(crate_name)
        .join("Cargo.toml");
    let text = std::fs::read_to_string(&path).expect("manifest readable");
    let manifest: toml::Table = text.parse().expect("manifest is TOML");
    manifest
        .get("dependencies")
        .and_then(toml::Value::as_table)
        .map(|table| table.keys().cloned().collect())
        .unwrap_or_default()
}

fn rust_sources(dir: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    let Ok(entries) = std::fs::read_dir(dir) else {
        return files;
    };
    for entry in entries.filter_map(Result::ok) {
        let path = entry.path();
        if path.is_dir() {
            files.extend(rust_sources(&path));
        } else if path.extension().is_some_and(|e| e == "rs") {
            files.push(path);
        }
    }
    files
}

#[test]
fn no_algorithm_crate_depends_on_the_simulator() {
    let allowed = ["spm-sim", "spmcal"];
    for name in crate_names() {
        if allowed.contains(&name.as_str()) {
            continue;
        }
        assert!(
            !normal_dependencies(&name).iter().any(|d| d == "spm-sim"),
            "crate {name} depends on spm-sim; algorithms must be generic over Microscope \
             (use spm-sim as a dev-dependency in tests only)"
        );
    }
}

#[test]
fn spm_hal_knows_no_other_workspace_crate() {
    let deps = normal_dependencies("spm-hal");
    for dep in deps {
        assert!(!dep.starts_with("spm"), "spm-hal depends on {dep}");
    }
}

#[test]
fn only_binaries_install_a_tracing_subscriber() {
    for name in crate_names() {
        if name == "spmcal" {
            continue;
        }
        assert!(
            !normal_dependencies(&name)
                .iter()
                .any(|d| d == "tracing-subscriber"),
            "library crate {name} depends on tracing-subscriber"
        );
    }
}

#[test]
fn the_correction_and_hal_crates_pull_in_neither_simulator_nor_sqlite() {
    for name in [
        "spm-hal",
        "spm-correction",
        "spm-regression",
        "spm-features",
    ] {
        for dep in normal_dependencies(name) {
            assert!(
                !["spm-sim", "spm-cdb", "rusqlite"].contains(&dep.as_str()),
                "{name} depends on {dep}"
            );
        }
    }
}

#[test]
fn pure_crates_read_no_clock_and_no_global_rng() {
    let forbidden = [
        "SystemTime::now",
        "Instant::now",
        "thread_rng",
        "rand::rng()",
        "from_entropy",
        "from_os_rng",
    ];
    for name in [
        "spm-features",
        "spm-regression",
        "spm-correction",
        "spm-sim",
    ] {
        for file in rust_sources(&workspace_root().join("crates").join(name).join("src")) {
            let text = std::fs::read_to_string(&file).expect("source readable");
            for needle in forbidden {
                assert!(
                    !text.contains(needle),
                    "{} uses {needle}: pure crates and the simulator's physics take time and \
                     randomness as inputs",
                    file.display()
                );
            }
        }
    }
}

#[test]
fn the_architecture_document_mentions_every_crate() {
    let text = std::fs::read_to_string(workspace_root().join("docs").join("ARCHITECTURE.md"))
        .expect("docs/ARCHITECTURE.md exists");
    for name in crate_names() {
        assert!(
            text.contains(&format!("crates/{name}")),
            "docs/ARCHITECTURE.md does not mention crates/{name}"
        );
    }
}

#[test]
fn the_readme_names_the_two_commands() {
    let text = std::fs::read_to_string(workspace_root().join("README.md")).expect("README.md");
    assert!(text.contains("cargo xtask calibrate"));
    assert!(text.contains("cargo test --workspace"));
}
