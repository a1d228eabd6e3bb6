//! Repository checks as ordinary tests: the invariants of docs/ARCHITECTURE.md.

use std::collections::{BTreeMap, BTreeSet};
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
    let allowed = ["spm-sim", "spm-nanonis-sim", "spmcal"];
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

/// The numerics kernel and linear-algebra crates the CLI crate must not name: its math lives
/// in the library crates (docs/ARCHITECTURE.md, `crates/spmcal`).
const CLI_FORBIDDEN_MATH: &[&str] = &["spm_regression::", "nalgebra::", "faer::"];

/// The forbidden names in a source text, outside comments.
fn math_in(text: &str) -> Vec<String> {
    text.lines()
        .enumerate()
        .filter(|(_, line)| !line.trim_start().starts_with("//"))
        .flat_map(|(i, line)| {
            CLI_FORBIDDEN_MATH
                .iter()
                .filter(move |name| line.contains(*name))
                .map(move |name| format!("line {}: {name}", i + 1))
        })
        .collect()
}

#[test]
fn the_cli_crate_holds_no_math() {
    let deps = normal_dependencies("spmcal");
    for kernel in ["spm-regression", "nalgebra", "faer"] {
        assert!(
            !deps.iter().any(|d| d == kernel),
            "crates/spmcal/Cargo.toml lists {kernel} as a dependency; the CLI's math belongs in \
             a library crate (a dev-dependency for its tests is fine)"
        );
    }
    let root = workspace_root();
    let mut found = Vec::new();
    for file in rust_sources(&root.join("crates/spmcal/src")) {
        let text = std::fs::read_to_string(&file).unwrap();
        found.extend(
            math_in(&text)
                .into_iter()
                .map(|m| format!("{}: {m}", file.display())),
        );
    }
    assert!(
        found.is_empty(),
        "math in the CLI crate:\n{}",
        found.join("\n")
    );
    // The check finds a call and passes over a comment.
    assert_eq!(
        math_in("// spm_regression::median\nlet m = spm_regression::median(&mut v);"),
        vec!["line 2: spm_regression::".to_owned()]
    );
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
        "spm-evaluation",
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

/// `cargo xtask bench --write-docs` writes docs/RESULTS.md from its measured tables and the
/// hand-written `docs/results/*.md` (headings demoted one level): a section edited in
/// RESULTS.md alone would be lost by the next regeneration.
#[test]
fn every_hand_written_results_fragment_is_in_results_md_as_it_stands() {
    let root = workspace_root();
    let results = std::fs::read_to_string(root.join("docs/RESULTS.md")).expect("RESULTS.md");
    let mut fragments: Vec<PathBuf> = std::fs::read_dir(root.join("docs/results"))
        .expect("docs/results")
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    fragments.sort();
    assert!(!fragments.is_empty());
    for path in fragments {
        let text = std::fs::read_to_string(&path).expect("fragment");
        let demoted: String = text
            .trim_end()
            .lines()
            .map(|line| {
                if line.starts_with('#') {
                    format!("#{line}\n")
                } else {
                    format!("{line}\n")
                }
            })
            .collect();
        assert!(
            results.contains(&demoted),
            "{} differs from its section of docs/RESULTS.md: edit the fragment, then the \
             section (or regenerate with `cargo xtask bench --write-docs`)",
            path.display()
        );
    }
}

#[test]
fn the_readme_names_the_two_commands() {
    let text = std::fs::read_to_string(workspace_root().join("README.md")).expect("README.md");
    assert!(text.contains("cargo xtask calibrate"));
    assert!(text.contains("cargo test --workspace"));
}

// ---------------------------------------------------------------------------------------------
// `cargo metadata`: the dependency graph as cargo resolves it.
// ---------------------------------------------------------------------------------------------

/// The cargo that runs the tests (`$CARGO`), else `cargo` on the path.
fn cargo() -> std::process::Command {
    let program = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    std::process::Command::new(program)
}

/// The host's target triple (`rustc -vV`), so that `cargo metadata` resolves (and needs) only
/// the packages of this platform.
fn host_triple() -> String {
    let rustc = std::env::var_os("RUSTC").unwrap_or_else(|| "rustc".into());
    let output = std::process::Command::new(rustc)
        .arg("-vV")
        .output()
        .expect("rustc runs");
    String::from_utf8_lossy(&output.stdout)
        .lines()
        .find_map(|l| l.strip_prefix("host: "))
        .expect("rustc -vV names the host")
        .trim()
        .to_owned()
}

/// `cargo metadata --format-version 1 --all-features --filter-platform <host>` of a manifest,
/// parsed. Offline first (everything a build of the workspace fetched is in cargo's cache); when
/// a package the build never needed is missing there (an optional feature's dependency), once
/// more with the registry reachable.
fn metadata_of(manifest: &Path) -> serde_json::Value {
    let host = host_triple();
    let run = |offline: bool| {
        let mut command = cargo();
        command
            .args(["metadata", "--format-version", "1", "--all-features"])
            .args(["--filter-platform", &host])
            .arg("--manifest-path")
            .arg(manifest);
        if offline {
            command.arg("--offline");
        }
        command.output().expect("cargo runs")
    };
    let mut output = run(true);
    if !output.status.success() {
        output = run(false);
    }
    assert!(
        output.status.success(),
        "cargo metadata --manifest-path {} failed:\n{}",
        manifest.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_slice(&output.stdout).expect("cargo metadata prints JSON")
}

fn workspace_metadata() -> serde_json::Value {
    metadata_of(&workspace_root().join("Cargo.toml"))
}

fn packages(metadata: &serde_json::Value) -> &[serde_json::Value] {
    metadata["packages"].as_array().map_or(&[], Vec::as_slice)
}

fn str_of<'a>(value: &'a serde_json::Value, key: &str) -> &'a str {
    value[key].as_str().unwrap_or_default()
}

/// Names of the workspace members.
fn member_names(metadata: &serde_json::Value) -> BTreeSet<String> {
    let ids: BTreeSet<&str> = metadata["workspace_members"]
        .as_array()
        .map(|a| a.iter().filter_map(serde_json::Value::as_str).collect())
        .unwrap_or_default();
    packages(metadata)
        .iter()
        .filter(|p| ids.contains(str_of(p, "id")))
        .map(|p| str_of(p, "name").to_owned())
        .collect()
}

fn package_named<'a>(metadata: &'a serde_json::Value, name: &str) -> &'a serde_json::Value {
    let members = member_names(metadata);
    packages(metadata)
        .iter()
        .find(|p| str_of(p, "name") == name && (members.contains(name) || p["source"].is_null()))
        .unwrap_or_else(|| panic!("cargo metadata has no package {name}"))
}

/// Every package name in the normal (non-dev) dependency tree of `root_name`, transitively,
/// as resolved by cargo (build dependencies included: they are linked into build scripts).
fn dependency_tree(metadata: &serde_json::Value, root_name: &str) -> BTreeSet<String> {
    let root_id = str_of(package_named(metadata, root_name), "id").to_owned();
    let nodes: BTreeMap<&str, &serde_json::Value> = metadata["resolve"]["nodes"]
        .as_array()
        .expect("cargo metadata has a resolve graph")
        .iter()
        .map(|n| (str_of(n, "id"), n))
        .collect();
    let name_of: BTreeMap<&str, &str> = packages(metadata)
        .iter()
        .map(|p| (str_of(p, "id"), str_of(p, "name")))
        .collect();
    let mut seen = BTreeSet::new();
    let mut stack = vec![root_id];
    let mut names = BTreeSet::new();
    while let Some(id) = stack.pop() {
        if !seen.insert(id.clone()) {
            continue;
        }
        let Some(node) = nodes.get(id.as_str()) else {
            continue;
        };
        for dep in node["deps"].as_array().map_or(&[][..], Vec::as_slice) {
            let not_dev_only = dep["dep_kinds"]
                .as_array()
                .is_some_and(|kinds| kinds.iter().any(|k| k["kind"].as_str() != Some("dev")));
            if not_dev_only {
                let pkg = str_of(dep, "pkg");
                names.insert(name_of.get(pkg).copied().unwrap_or(pkg).to_owned());
                stack.push(pkg.to_owned());
            }
        }
    }
    names
}

#[test]
fn spm_calibration_links_no_sqlite() {
    let tree = dependency_tree(&workspace_metadata(), "spm-calibration");
    for forbidden in ["rusqlite", "libsqlite3-sys", "spm-cdb"] {
        assert!(
            !tree.contains(forbidden),
            "spm-calibration's dependency tree holds {forbidden}: the controller talks to its \
             store through the ProgressStore trait and must not compile SQLite (issue 17, item 1)"
        );
    }
}

/// What `cargo test --workspace` compiles is the workspace's resolve with default features
/// (`cargo metadata` without `--all-features`): faer is not in it. The library's least squares
/// run on nalgebra; faer is compiled only for the `linalg` comparison (spm-regression's and
/// xtask's `faer` features, turned on by the `cargo xtask` alias), and in the test build it
/// cost minutes of CPU for nothing a test runs (issue 28, item 7).
#[test]
fn the_test_build_leaves_faer_out() {
    let output = cargo()
        .args(["metadata", "--format-version", "1", "--offline"])
        .args(["--filter-platform", &host_triple()])
        .arg("--manifest-path")
        .arg(workspace_root().join("Cargo.toml"))
        .output()
        .expect("cargo runs");
    assert!(
        output.status.success(),
        "cargo metadata failed:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let metadata: serde_json::Value =
        serde_json::from_slice(&output.stdout).expect("cargo metadata prints JSON");
    let name_of: BTreeMap<&str, &str> = packages(&metadata)
        .iter()
        .map(|p| (str_of(p, "id"), str_of(p, "name")))
        .collect();
    for node in metadata["resolve"]["nodes"]
        .as_array()
        .expect("cargo metadata has a resolve graph")
    {
        let name = name_of.get(str_of(node, "id")).copied().unwrap_or_default();
        assert_ne!(
            name, "faer",
            "faer is in the workspace's default-feature resolve, so `cargo test --workspace` \
             compiles it: keep spm-regression's `faer` feature off in every member's manifest \
             (xtask's own `faer` feature, which the `cargo xtask` alias turns on, turns it on)"
        );
        let features = node["features"].as_array().map_or(&[][..], Vec::as_slice);
        assert!(
            !features.iter().any(|f| f.as_str() == Some("faer")),
            "{name} has its `faer` feature on in the workspace's default-feature resolve"
        );
    }
}

/// The features of every package `cargo tree -p spmcal` resolves over the dependency
/// edges `edges` (`{package} [{features}]` lines).
fn spmcal_tree_features(edges: &str) -> String {
    package_tree_features("spmcal", edges, &[])
}

/// `cargo tree` of `package` with `extra` arguments (feature flags), one `name version
/// [features]` line per package.
fn package_tree_features(package: &str, edges: &str, extra: &[&str]) -> String {
    let output = cargo()
        .args(["tree", "--offline", "-p", package, "-e", edges])
        .args(extra)
        .args(["--prefix", "none", "--format", "{p} [{f}]"])
        .args(["--target", &host_triple()])
        .arg("--manifest-path")
        .arg(workspace_root().join("Cargo.toml"))
        .output()
        .expect("cargo runs");
    assert!(
        output.status.success(),
        "cargo tree failed:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

/// A program's build compiles no test support (issue 28, item 3): `cargo build -p spmcal`
/// resolves spm-cdb and spm-regression without their `test-support` feature, so the private
/// PostgreSQL server (`spm_cdb::pg_server`) and the benchmark helpers
/// (`spm_cdb::bench_support`, `spm_regression::bench_support`) are not in it. The tests
/// (dev-dependencies) and xtask turn the feature on; the check is not vacuous: the test
/// build of spmcal has it.
#[test]
fn a_program_build_leaves_the_test_support_out() {
    let program = spmcal_tree_features("normal,build");
    assert!(
        program.lines().any(|l| l.starts_with("spm-cdb ")),
        "spm-cdb is in spmcal's tree:\n{program}"
    );
    let with_support: Vec<&str> = program
        .lines()
        .filter(|l| l.contains("test-support"))
        .collect();
    assert!(
        with_support.is_empty(),
        "`cargo build -p spmcal` turns on a test-support feature: {with_support:?} (enable it \
         only in [dev-dependencies] and in xtask)"
    );
    let tests = spmcal_tree_features("normal,build,dev");
    assert!(
        tests
            .lines()
            .any(|l| l.starts_with("spm-cdb ") && l.contains("test-support")),
        "spmcal's tests no longer turn on spm-cdb's test-support:\n{tests}"
    );
}

/// The Nanonis-only program (issue 28 item 4): `cargo build -p spmcal --no-default-features`
/// links neither the simulator nor the Nanonis protocol's simulated server, and spm-hal's
/// ground-truth traits are there only because the evaluation (which judges a run's
/// validation images) reads them; the default build has all three. A crate using spm-hal
/// alone gets no ground truth. `.ci/run` builds that program.
#[test]
fn the_nanonis_only_program_links_no_simulator_and_the_hal_alone_no_ground_truth() {
    let has = |tree: &str, name: &str| tree.lines().any(|l| l.starts_with(&format!("{name} ")));
    let default = package_tree_features("spmcal", "normal,build", &[]);
    for name in ["spm-sim", "spm-nanonis-sim", "spm-nanonis", "spm-virtual"] {
        assert!(
            has(&default, name),
            "the default spmcal has {name}:\n{default}"
        );
    }
    let nanonis_only = package_tree_features("spmcal", "normal,build", &["--no-default-features"]);
    for name in ["spm-sim", "spm-nanonis-sim"] {
        assert!(
            !has(&nanonis_only, name),
            "spmcal --no-default-features links {name}:\n{nanonis_only}"
        );
    }
    for name in ["spm-nanonis", "spm-virtual", "spm-calibration", "spm-cdb"] {
        assert!(
            has(&nanonis_only, name),
            "spmcal --no-default-features lacks {name}:\n{nanonis_only}"
        );
    }
    let hal = package_tree_features("spm-hal", "normal,build", &[]);
    let hal_line = hal
        .lines()
        .find(|l| l.starts_with("spm-hal "))
        .unwrap_or_default();
    assert!(
        !hal_line.contains("truth"),
        "spm-hal alone turns on its ground truth: {hal_line}"
    );
    let sim = package_tree_features("spm-sim", "normal,build", &[]);
    assert!(
        sim.lines()
            .any(|l| l.starts_with("spm-hal ") && l.contains("truth")),
        "spm-sim implements the ground truth, so it turns the feature on:\n{sim}"
    );
}

/// A scratch crate outside the workspace that depends on `spm-correction` alone, by path, as a
/// user's program would: its resolved dependency tree holds neither the simulator nor SQLite.
#[test]
fn a_crate_using_spm_correction_alone_pulls_in_neither_simulator_nor_sqlite() {
    let dir =
        std::env::temp_dir().join(format!("spmcal-scratch-correction-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("src")).expect("temporary folder");
    let correction = workspace_root().join("crates").join("spm-correction");
    let manifest = format!(
        "[package]\nname = \"scratch-user\"\nversion = \"0.0.0\"\nedition = \"2024\"\n\
         publish = false\n\n[dependencies]\nspm-correction = {{ path = {path} }}\n\n\
         [workspace]\n",
        path = toml::Value::String(correction.display().to_string())
    );
    std::fs::write(dir.join("Cargo.toml"), manifest).expect("scratch manifest");
    std::fs::write(
        dir.join("src").join("main.rs"),
        "fn main() { let _ = spm_correction::Parallelism::AllCores; }\n",
    )
    .expect("scratch main.rs");
    // The workspace's lock file, so that resolution is offline and picks the tested versions.
    std::fs::copy(workspace_root().join("Cargo.lock"), dir.join("Cargo.lock"))
        .expect("Cargo.lock copied");
    let metadata = metadata_of(&dir.join("Cargo.toml"));
    let tree = dependency_tree(&metadata, "scratch-user");
    let _ = std::fs::remove_dir_all(&dir);
    assert!(
        tree.contains("spm-correction") && tree.contains("spm-hal"),
        "the scratch crate's tree misses spm-correction or spm-hal: {tree:?}"
    );
    for forbidden in ["spm-sim", "spm-cdb", "rusqlite", "libsqlite3-sys"] {
        assert!(
            !tree.contains(forbidden),
            "a crate depending on spm-correction alone pulls in {forbidden}: {tree:?}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// The codemap of docs/ARCHITECTURE.md against the manifests.
// ---------------------------------------------------------------------------------------------

fn architecture_text() -> String {
    std::fs::read_to_string(workspace_root().join("docs").join("ARCHITECTURE.md"))
        .expect("docs/ARCHITECTURE.md exists")
}

/// The lines of the first fenced block opened with ```` ```<tag> ````.
fn fenced_block(text: &str, tag: &str) -> Vec<String> {
    let opening = format!("```{tag}");
    text.lines()
        .skip_while(|line| line.trim() != opening)
        .skip(1)
        .take_while(|line| line.trim() != "```")
        .map(str::to_owned)
        .collect()
}

/// One line of the codemap: `crate -> dep dep? ... ; never: pkg pkg`.
#[derive(Debug, Clone, PartialEq, Eq)]
struct CodemapLine {
    name: String,
    /// Workspace dependencies, `true` when optional (written `name?`).
    depends_on: BTreeMap<String, bool>,
    /// Packages that must be absent from the crate's whole dependency tree.
    never: BTreeSet<String>,
}

impl CodemapLine {
    fn parse(line: &str) -> Option<Self> {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            return None;
        }
        let (edges, never) = match line.split_once(';') {
            Some((edges, rest)) => (edges, rest.trim().strip_prefix("never:").unwrap_or(rest)),
            None => (line, ""),
        };
        let (name, deps) = edges.split_once("->").unwrap_or((edges, ""));
        let words = |s: &str| -> Vec<String> {
            s.split([' ', ','])
                .filter(|w| !w.is_empty())
                .map(str::to_owned)
                .collect()
        };
        Some(Self {
            name: name.trim().to_owned(),
            depends_on: words(deps)
                .into_iter()
                .map(|d| match d.strip_suffix('?') {
                    Some(optional) => (optional.to_owned(), true),
                    None => (d, false),
                })
                .collect(),
            never: words(never).into_iter().collect(),
        })
    }

    fn render(&self) -> String {
        let deps: Vec<String> = self
            .depends_on
            .iter()
            .map(|(d, optional)| {
                if *optional {
                    format!("{d}?")
                } else {
                    d.clone()
                }
            })
            .collect();
        let mut line = format!("{} -> {}", self.name, deps.join(" "));
        if !self.never.is_empty() {
            let never: Vec<&str> = self.never.iter().map(String::as_str).collect();
            line = format!("{}  ; never: {}", line.trim_end(), never.join(" "));
        }
        line.trim_end().to_owned()
    }
}

fn codemap() -> Vec<CodemapLine> {
    let lines: Vec<CodemapLine> = fenced_block(&architecture_text(), "codemap")
        .iter()
        .filter_map(|l| CodemapLine::parse(l))
        .collect();
    assert!(
        !lines.is_empty(),
        "docs/ARCHITECTURE.md has no ```codemap block (one line per crate: \
         `crate -> workspace deps ; never: packages`)"
    );
    lines
}

/// The workspace dependencies of `name` in its manifest (normal and build, not dev), with
/// whether each is optional.
fn manifest_workspace_deps(
    metadata: &serde_json::Value,
    name: &str,
    members: &BTreeSet<String>,
) -> BTreeMap<String, bool> {
    let mut deps = BTreeMap::new();
    for dep in package_named(metadata, name)["dependencies"]
        .as_array()
        .map_or(&[][..], Vec::as_slice)
    {
        let dep_name = str_of(dep, "name");
        if dep["kind"].as_str() == Some("dev") || !members.contains(dep_name) {
            continue;
        }
        let optional = dep["optional"].as_bool().unwrap_or(false);
        let entry = deps.entry(dep_name.to_owned()).or_insert(optional);
        *entry = *entry && optional;
    }
    deps
}

#[test]
fn the_codemap_matches_the_manifests() {
    let metadata = workspace_metadata();
    let members = member_names(&metadata);
    let map = codemap();
    let mut problems = Vec::new();
    let mut listed = BTreeSet::new();
    for line in &map {
        if !listed.insert(line.name.clone()) {
            problems.push(format!("`{}` has two lines; keep one", line.name));
        }
        if !members.contains(&line.name) {
            problems.push(format!(
                "`{}` is no workspace crate: remove its line `{}`",
                line.name,
                line.render()
            ));
            continue;
        }
        let actual = manifest_workspace_deps(&metadata, &line.name, &members);
        if actual != line.depends_on {
            let fixed = CodemapLine {
                depends_on: actual,
                ..line.clone()
            };
            problems.push(format!(
                "the manifest of `{}` says otherwise: replace `{}` with `{}`",
                line.name,
                line.render(),
                fixed.render()
            ));
        }
        let tree = dependency_tree(&metadata, &line.name);
        for absent in &line.never {
            if tree.contains(absent) {
                problems.push(format!(
                    "`{}` must never link `{absent}` (codemap), but its dependency tree holds it",
                    line.name
                ));
            }
        }
    }
    for name in members.difference(&listed) {
        let line = CodemapLine {
            name: name.clone(),
            depends_on: manifest_workspace_deps(&metadata, name, &members),
            never: BTreeSet::new(),
        };
        problems.push(format!(
            "crate `{name}` is missing from the codemap: add the line `{}` (and its \
             `; never:` list and its invariants)",
            line.render()
        ));
    }
    assert!(
        problems.is_empty(),
        "docs/ARCHITECTURE.md ```codemap block:\n  - {}",
        problems.join("\n  - ")
    );
}

// ---------------------------------------------------------------------------------------------
// Crates importable one by one: metadata, README with an example, `cargo package`.
// ---------------------------------------------------------------------------------------------

/// Workspace members that may be published (`publish` not set to `false`).
fn publishable_members(metadata: &serde_json::Value) -> Vec<&serde_json::Value> {
    let members = member_names(metadata);
    packages(metadata)
        .iter()
        .filter(|p| members.contains(str_of(p, "name")) && p["source"].is_null())
        .filter(|p| {
            p["publish"]
                .as_array()
                .is_none_or(|registries| !registries.is_empty())
        })
        .collect()
}

#[test]
fn every_publishable_crate_has_metadata_and_a_readme_with_an_example() {
    let metadata = workspace_metadata();
    let mut problems = Vec::new();
    for package in publishable_members(&metadata) {
        let name = str_of(package, "name");
        let dir = Path::new(str_of(package, "manifest_path"))
            .parent()
            .expect("a manifest lives in a folder")
            .to_path_buf();
        for field in ["description", "license", "readme"] {
            if str_of(package, field).trim().is_empty() {
                problems.push(format!("{name}: Cargo.toml [package] has no `{field}`"));
            }
        }
        if package["keywords"].as_array().is_none_or(Vec::is_empty) {
            problems.push(format!("{name}: Cargo.toml [package] has no `keywords`"));
        }
        let repository = str_of(package, "repository");
        if repository.contains("example") || repository.contains("invalid") {
            problems.push(format!(
                "{name}: placeholder repository URL `{repository}`; name a real one or none"
            ));
        }
        let readme = dir.join("README.md");
        let Ok(text) = std::fs::read_to_string(&readme) else {
            problems.push(format!("{name}: {} is missing", readme.display()));
            continue;
        };
        if !text.contains("```rust") && !text.contains("```sh") {
            problems.push(format!(
                "{name}: README.md has no usage example (a ```rust block, run as a doctest)"
            ));
        }
        let is_lib = package["targets"].as_array().is_some_and(|targets| {
            targets.iter().any(|t| {
                t["kind"]
                    .as_array()
                    .is_some_and(|k| k.iter().any(|k| k.as_str() == Some("lib")))
            })
        });
        if is_lib {
            let lib_rs =
                std::fs::read_to_string(dir.join("src").join("lib.rs")).unwrap_or_default();
            if !lib_rs.contains("#![doc = include_str!(\"../README.md\")]") {
                problems.push(format!(
                    "{name}: src/lib.rs lacks `#![doc = include_str!(\"../README.md\")]`, so the \
                     README's example is not compiled and run as a doctest"
                ));
            }
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

/// `cargo package --workspace --exclude <unpublishable> --no-verify --offline`: every
/// publishable crate packages, its workspace dependencies resolved against the other packaged
/// crates (cargo's local overlay). `cargo package -p X --no-verify` alone would look the
/// unpublished `spm-*` dependencies up on crates.io; `-p X --no-verify --exclude-lockfile`
/// is the single-crate form.
#[test]
fn every_publishable_crate_packages() {
    let metadata = workspace_metadata();
    let publishable: BTreeSet<&str> = publishable_members(&metadata)
        .iter()
        .map(|p| str_of(p, "name"))
        .collect();
    let target = std::env::temp_dir().join(format!("spmcal-package-{}", std::process::id()));
    let mut command = cargo();
    command
        .current_dir(workspace_root())
        .env("CARGO_TARGET_DIR", &target)
        .args([
            "package",
            "--workspace",
            "--no-verify",
            "--offline",
            "--allow-dirty",
        ]);
    for name in member_names(&metadata) {
        if !publishable.contains(name.as_str()) {
            command.args(["--exclude", &name]);
        }
    }
    let output = command.output().expect("cargo runs");
    let _ = std::fs::remove_dir_all(&target);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "cargo package failed:\n{stderr}");
    for name in publishable {
        assert!(
            stderr.contains(&format!("Packaging {name} v")),
            "cargo package did not package {name}:\n{stderr}"
        );
    }
}

/// Test targets of a workspace member as cargo sees them (`cargo metadata`: the files it
/// discovers in `tests/` and the manifest's `[[test]]` entries), paths relative to the package.
fn integration_test_targets(package: &serde_json::Value) -> Vec<PathBuf> {
    let dir = Path::new(str_of(package, "manifest_path"))
        .parent()
        .expect("a manifest lives in its package's folder")
        .to_path_buf();
    package["targets"]
        .as_array()
        .map_or(&[][..], Vec::as_slice)
        .iter()
        .filter(|t| {
            t["kind"]
                .as_array()
                .is_some_and(|kinds| kinds.iter().any(|k| k == "test"))
        })
        .map(|t| {
            let path = PathBuf::from(str_of(t, "src_path"));
            path.strip_prefix(&dir)
                .map(Path::to_path_buf)
                .unwrap_or(path)
        })
        .collect()
}

/// Issue 28 item 7: every package's integration tests are one binary, `tests/it/main.rs`, with a
/// module per topic (docs/ARCHITECTURE.md, "Tests"). Each further file directly in `tests/`
/// (or `[[test]]` entry) would be a binary of its own that links the workspace once more.
#[test]
fn every_package_has_at_most_one_integration_test_binary_tests_it_main_rs() {
    let metadata = workspace_metadata();
    let members = member_names(&metadata);
    let one_binary = Path::new("tests").join("it").join("main.rs");
    let mut problems = Vec::new();
    for name in &members {
        let targets = integration_test_targets(package_named(&metadata, name));
        if targets.len() > 1 || targets.iter().any(|t| *t != one_binary) {
            problems.push(format!("{name}: test binaries {targets:?}"));
        }
    }
    assert_eq!(
        members.len(),
        crate_names().len() + 2,
        "members: crates/*, xtask and tests"
    );
    // The files themselves, so that a file cargo would not pick up (`autotests = false`) cannot
    // hide either: no Rust file directly in a package's `tests/`.
    let mut packages: Vec<PathBuf> = crate_names()
        .iter()
        .map(|n| workspace_root().join("crates").join(n))
        .collect();
    packages.extend(["tests", "xtask"].map(|d| workspace_root().join(d)));
    for package in packages {
        let Ok(entries) = std::fs::read_dir(package.join("tests")) else {
            continue;
        };
        for path in entries.filter_map(Result::ok).map(|e| e.path()) {
            if path.extension().is_some_and(|e| e == "rs") {
                problems.push(format!("{}: move it to tests/it/", path.display()));
            }
        }
    }
    assert!(
        problems.is_empty(),
        "one integration-test binary per package, tests/it/main.rs with a `mod` per former \
         test file:\n  {}",
        problems.join("\n  ")
    );
}

// ---------------------------------------------------------------------------------------------
// Functions of library code, parsed with syn: lengths and the equation index.
// ---------------------------------------------------------------------------------------------

/// A function with a body in a source file.
#[derive(Debug, Clone)]
struct FnInfo {
    /// The type of its `impl` block (last path segment), `None` for free functions.
    owner: Option<String>,
    name: String,
    /// Its doc comment, lines joined.
    doc: String,
    /// First line of the item (its first attribute or doc line, else the `fn` line), 1-based.
    item_line: usize,
    /// Line of the `fn` keyword.
    fn_line: usize,
    /// Line of the closing brace of the body.
    end_line: usize,
    /// Inside `#[cfg(test)]` code or a `#[test]` function.
    test_code: bool,
}

impl FnInfo {
    fn lines(&self) -> usize {
        self.end_line + 1 - self.fn_line
    }
}

fn is_test_attr(attr: &syn::Attribute) -> bool {
    attr.path().is_ident("test")
        || (attr.path().is_ident("cfg")
            && attr
                .parse_args::<syn::Ident>()
                .is_ok_and(|ident| ident == "test"))
}

fn doc_of(attrs: &[syn::Attribute]) -> String {
    attrs
        .iter()
        .filter(|a| a.path().is_ident("doc"))
        .filter_map(|a| match &a.meta {
            syn::Meta::NameValue(nv) => match &nv.value {
                syn::Expr::Lit(syn::ExprLit {
                    lit: syn::Lit::Str(s),
                    ..
                }) => Some(s.value()),
                _ => None,
            },
            _ => None,
        })
        .collect::<Vec<_>>()
        .join("\n")
}

#[derive(Default)]
struct FnCollector {
    owner: Vec<Option<String>>,
    test_depth: usize,
    found: Vec<FnInfo>,
}

impl FnCollector {
    fn push(&mut self, attrs: &[syn::Attribute], sig: &syn::Signature, block: &syn::Block) {
        let fn_line = sig.fn_token.span.start().line;
        let item_line = attrs
            .iter()
            .map(|a| a.pound_token.span.start().line)
            .chain([fn_line])
            .min()
            .unwrap_or(fn_line);
        self.found.push(FnInfo {
            owner: self.owner.last().cloned().flatten(),
            name: sig.ident.to_string(),
            doc: doc_of(attrs),
            item_line,
            fn_line,
            end_line: block.brace_token.span.close().start().line,
            test_code: self.test_depth > 0 || attrs.iter().any(is_test_attr),
        });
    }
}

impl<'ast> syn::visit::Visit<'ast> for FnCollector {
    fn visit_item_mod(&mut self, module: &'ast syn::ItemMod) {
        let test = module.attrs.iter().any(is_test_attr);
        self.test_depth += usize::from(test);
        syn::visit::visit_item_mod(self, module);
        self.test_depth -= usize::from(test);
    }

    fn visit_item_fn(&mut self, item: &'ast syn::ItemFn) {
        self.push(&item.attrs, &item.sig, &item.block);
        self.owner.push(None);
        syn::visit::visit_item_fn(self, item);
        self.owner.pop();
    }

    fn visit_item_impl(&mut self, item: &'ast syn::ItemImpl) {
        self.owner.push(impl_owner(item));
        syn::visit::visit_item_impl(self, item);
        self.owner.pop();
    }

    fn visit_item_trait(&mut self, item: &'ast syn::ItemTrait) {
        self.owner.push(Some(item.ident.to_string()));
        syn::visit::visit_item_trait(self, item);
        self.owner.pop();
    }

    fn visit_impl_item_fn(&mut self, item: &'ast syn::ImplItemFn) {
        self.push(&item.attrs, &item.sig, &item.block);
        self.owner.push(None);
        syn::visit::visit_impl_item_fn(self, item);
        self.owner.pop();
    }

    fn visit_trait_item_fn(&mut self, item: &'ast syn::TraitItemFn) {
        if let Some(block) = &item.default {
            self.push(&item.attrs, &item.sig, block);
        }
        self.owner.push(None);
        syn::visit::visit_trait_item_fn(self, item);
        self.owner.pop();
    }
}

/// The type an `impl` block is for (its last path segment), for naming its methods.
fn impl_owner(item: &syn::ItemImpl) -> Option<String> {
    match item.self_ty.as_ref() {
        syn::Type::Path(p) => p.path.segments.last().map(|s| s.ident.to_string()),
        _ => None,
    }
}

/// Every function with a body in a Rust source file.
fn functions_in(path: &Path) -> Vec<FnInfo> {
    let text = std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("{} is unreadable: {e}", path.display()));
    let file =
        syn::parse_file(&text).unwrap_or_else(|e| panic!("{} does not parse: {e}", path.display()));
    let mut collector = FnCollector::default();
    syn::visit::Visit::visit_file(&mut collector, &file);
    collector.found
}

/// The longest a library function may be without a `// long-function: <reason>` comment.
const MAX_FUNCTION_LINES: usize = 150;

/// The reason written in a `// long-function: <reason>` comment in the lines just above the
/// function (the comment block above its attributes, or among its attributes and doc lines).
fn long_function_reason(source_lines: &[&str], function: &FnInfo) -> Option<String> {
    let marker = "// long-function:";
    let reason_in = |line: &str| {
        line.trim()
            .strip_prefix(marker)
            .map(str::trim)
            .filter(|reason| !reason.is_empty())
            .map(str::to_owned)
    };
    // Lines are 1-based; index i holds line i + 1.
    let attrs = (function.item_line - 1)..(function.fn_line - 1);
    if let Some(reason) = attrs
        .filter_map(|i| source_lines.get(i))
        .find_map(|l| reason_in(l))
    {
        return Some(reason);
    }
    source_lines[..function.item_line - 1]
        .iter()
        .rev()
        .take_while(|l| l.trim_start().starts_with("//") && !l.trim_start().starts_with("///"))
        .find_map(|l| reason_in(l))
}

#[test]
fn no_library_function_is_longer_than_150_lines_without_a_reason() {
    let mut offenders = Vec::new();
    // Every crate's library and binary sources, and xtask's (issue 28 item 6).
    let folders = crate_names()
        .into_iter()
        .map(|name| workspace_root().join("crates").join(name).join("src"))
        .chain([workspace_root().join("xtask").join("src")]);
    for folder in folders {
        for file in rust_sources(&folder) {
            let text = std::fs::read_to_string(&file).expect("source readable");
            let lines: Vec<&str> = text.lines().collect();
            for function in functions_in(&file) {
                if function.test_code || function.lines() <= MAX_FUNCTION_LINES {
                    continue;
                }
                if long_function_reason(&lines, &function).is_none() {
                    let relative = file.strip_prefix(workspace_root()).unwrap_or(&file);
                    offenders.push(format!(
                        "{}:{} fn {}{} is {} lines",
                        relative.display(),
                        function.fn_line,
                        function
                            .owner
                            .as_ref()
                            .map(|o| format!("{o}::"))
                            .unwrap_or_default(),
                        function.name,
                        function.lines()
                    ));
                }
            }
        }
    }
    assert!(
        offenders.is_empty(),
        "library functions over {MAX_FUNCTION_LINES} lines: split them, or write \
         `// long-function: <reason>` just above the fn:\n  {}",
        offenders.join("\n  ")
    );
}

#[test]
fn the_length_check_measures_functions_and_reads_reasons() {
    let dir = std::env::temp_dir().join(format!("spmcal-fnlen-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temporary folder");
    let file = dir.join("sample.rs");
    let body = "    let _ = 1;\n".repeat(3);
    let text = format!(
        "/// Doc.\n// long-function: a table\n#[inline]\npub fn a() {{\n{body}}}\n\n\
         struct S;\nimpl S {{\n    fn b(&self) {{}}\n}}\n\n#[cfg(test)]\nmod tests {{\n    \
         #[test]\n    fn c() {{}}\n}}\n"
    );
    std::fs::write(&file, &text).expect("sample written");
    let found = functions_in(&file);
    let _ = std::fs::remove_dir_all(&dir);
    let lines: Vec<&str> = text.lines().collect();
    let a = &found[0];
    assert_eq!(
        (a.name.as_str(), a.item_line, a.fn_line, a.lines()),
        ("a", 1, 4, 5)
    );
    assert_eq!(long_function_reason(&lines, a).as_deref(), Some("a table"));
    assert_eq!(a.doc.trim(), "Doc.");
    let b = &found[1];
    assert_eq!(
        (b.owner.as_deref(), b.name.as_str(), b.lines()),
        (Some("S"), "b", 1)
    );
    assert_eq!(long_function_reason(&lines, b), None);
    assert!(!a.test_code && !b.test_code && found[2].test_code);
}

/// One row of the equation index: `| (N) | … | `path::function`, … |`.
fn equation_index() -> BTreeMap<u32, Vec<String>> {
    let text = architecture_text();
    let section: Vec<&str> = text
        .lines()
        .skip_while(|l| !l.starts_with("## Equation index"))
        .skip(1)
        .take_while(|l| !l.starts_with("## "))
        .collect();
    let mut index = BTreeMap::new();
    for row in section.iter().filter(|l| l.trim_start().starts_with('|')) {
        let cells: Vec<&str> = row.trim().trim_matches('|').split('|').collect();
        let Some(number) = cells
            .first()
            .map(|c| c.trim().trim_start_matches("eq.").trim())
            .and_then(|c| c.strip_prefix('(')?.strip_suffix(')')?.parse::<u32>().ok())
        else {
            continue;
        };
        let functions: Vec<String> = cells
            .last()
            .map(|c| c.split('`').skip(1).step_by(2).map(str::to_owned).collect())
            .unwrap_or_default();
        index.insert(number, functions);
    }
    index
}

#[test]
fn every_equation_of_the_paper_resolves_to_a_function_that_says_so() {
    let index = equation_index();
    let mut problems = Vec::new();
    for n in 1..=14 {
        match index.get(&n) {
            None => problems.push(format!("eq. ({n}) has no row in the equation index")),
            Some(functions) if functions.is_empty() => {
                problems.push(format!("eq. ({n}) names no function (write `path.rs::fn`)"));
            }
            Some(_) => {}
        }
    }
    for (n, functions) in &index {
        if !(1..=14).contains(n) {
            problems.push(format!(
                "eq. ({n}) is not an equation of the paper, (1)-(14)"
            ));
        }
        for entry in functions {
            let Some((path, item)) = entry.split_once(".rs::") else {
                problems.push(format!("eq. ({n}): `{entry}` is not `path.rs::function`"));
                continue;
            };
            let file = workspace_root().join(format!("{path}.rs"));
            if !file.is_file() {
                problems.push(format!("eq. ({n}): {}.rs does not exist", path));
                continue;
            }
            let (owner, name) = match item.rsplit_once("::") {
                Some((owner, name)) => (Some(owner), name),
                None => (None, item),
            };
            let candidates: Vec<FnInfo> = functions_in(&file)
                .into_iter()
                .filter(|f| !f.test_code && f.name == name && f.owner.as_deref() == owner)
                .collect();
            if candidates.is_empty() {
                problems.push(format!("eq. ({n}): {path}.rs has no `fn {item}`"));
                continue;
            }
            let says = |f: &FnInfo| {
                f.doc.lines().any(|line| {
                    line.trim().starts_with("Implements eq") && line.contains(&format!("({n})"))
                })
            };
            if !candidates.iter().any(says) {
                problems.push(format!(
                    "eq. ({n}): `{entry}` lacks the doc line `/// Implements eq. ({n}).`"
                ));
            }
        }
    }
    assert!(
        problems.is_empty(),
        "docs/ARCHITECTURE.md, equation index:\n  {}",
        problems.join("\n  ")
    );
}

/// Where production code names a function: every path expression (a call `a::f(…)`, or `f`
/// passed as a value) by its last segment and the segment before it (`Self` resolved to the
/// impl's type), and every method call by its name. A name-level call graph: a method call
/// `.form(…)` counts for every `form`, since types are not resolved without the compiler.
#[derive(Debug, Clone)]
struct Reference {
    name: String,
    /// The segment before the name in a path (`Type` in `Type::f`), `None` for a bare name.
    qualifier: Option<String>,
    /// A method call (`x.f(…)`), reached through any owner.
    method: bool,
    /// The function the reference is in: (impl type, name).
    caller: (Option<String>, String),
}

/// A spot that computes an indexed equation's formula outside the functions the index names.
#[derive(Debug, Clone)]
struct ShapeHit {
    /// The equations whose indexed functions may compute it.
    equations: &'static [u32],
    line: usize,
    caller: (Option<String>, String),
    what: &'static str,
}

/// The identifiers of an expression, lower-cased.
fn idents_of(expr: &syn::Expr) -> Vec<String> {
    #[derive(Default)]
    struct Idents(Vec<String>);
    impl<'ast> syn::visit::Visit<'ast> for Idents {
        fn visit_ident(&mut self, ident: &'ast proc_macro2::Ident) {
            self.0.push(ident.to_string().to_lowercase());
        }
    }
    let mut idents = Idents::default();
    syn::visit::Visit::visit_expr(&mut idents, expr);
    idents.0
}

/// The last identifier of a plain path or field expression (`ky`, `self.ky_nm_per_count`,
/// `l.ky.0`), lower-cased; `None` for anything else.
fn plain_name(expr: &syn::Expr) -> Option<String> {
    match expr {
        syn::Expr::Path(p) => p
            .path
            .segments
            .last()
            .map(|s| s.ident.to_string().to_lowercase()),
        syn::Expr::Field(f) => match &f.member {
            syn::Member::Named(ident) => Some(ident.to_string().to_lowercase()),
            syn::Member::Unnamed(_) => plain_name(&f.base),
        },
        syn::Expr::Paren(p) => plain_name(&p.expr),
        syn::Expr::Reference(r) => plain_name(&r.expr),
        syn::Expr::Unary(u) => plain_name(&u.expr),
        _ => None,
    }
}

/// Whether `expr` is a call of the method `sin` or `cos`.
fn is_sin_or_cos(expr: &syn::Expr) -> bool {
    match expr {
        syn::Expr::MethodCall(m) => m.method == "sin" || m.method == "cos",
        syn::Expr::Paren(p) => is_sin_or_cos(&p.expr),
        _ => false,
    }
}

/// The formulas of eqs. (3), (5) and (11) by their shape:
/// - eq. (3)/(11): a K̄y (a plain name containing `ky`) times the sine or cosine of anything,
///   or `sin_cos()` of an α (a receiver naming `alpha`);
/// - eq. (5): a sum of a product naming `kx_nm_per_count` and one naming `kyx_nm_per_count`
///   (K̄x·Δx + K̄yx·Δy).
fn formula_shape(expr: &syn::Expr) -> Option<(&'static [u32], &'static str)> {
    match expr {
        syn::Expr::Binary(b) if matches!(b.op, syn::BinOp::Mul(_)) => {
            let ky_times_trig = |k: &syn::Expr, t: &syn::Expr| {
                is_sin_or_cos(t) && plain_name(k).is_some_and(|n| n.contains("ky"))
            };
            (ky_times_trig(&b.left, &b.right) || ky_times_trig(&b.right, &b.left))
                .then_some((&[3, 11], "K̄y times sin/cos (eqs. 3, 11)"))
        }
        syn::Expr::MethodCall(m) if m.method == "sin_cos" => idents_of(&m.receiver)
            .iter()
            .any(|i| i.contains("alpha"))
            .then_some((&[3, 11], "sin_cos() of α (eqs. 3, 11)")),
        syn::Expr::Binary(b) if matches!(b.op, syn::BinOp::Add(_)) => {
            let product_naming = |e: &syn::Expr, name: &str| {
                let mut inner = e;
                while let syn::Expr::Paren(p) = inner {
                    inner = &p.expr;
                }
                matches!(inner, syn::Expr::Binary(p) if matches!(p.op, syn::BinOp::Mul(_)))
                    && idents_of(e).iter().any(|i| i == name)
            };
            let (l, r) = (&b.left, &b.right);
            ((product_naming(l, "kx_nm_per_count") && product_naming(r, "kyx_nm_per_count"))
                || (product_naming(r, "kx_nm_per_count") && product_naming(l, "kyx_nm_per_count")))
            .then_some((&[1, 5], "K̄x·Δx + K̄yx·Δy (eqs. 1, 5)"))
        }
        _ => None,
    }
}

/// The references and formula shapes of one file's non-test code, and the names of the
/// out-of-line modules it declares under `#[cfg(test)]` (their files are test code).
#[derive(Default)]
struct CallCollector {
    owner: Vec<Option<String>>,
    function: Vec<(Option<String>, String)>,
    test_depth: usize,
    references: Vec<Reference>,
    shapes: Vec<ShapeHit>,
    /// Linear-algebra solves written outside the numerics kernel ([`solver_shape`]).
    solvers: Vec<SolverHit>,
    test_modules: Vec<String>,
}

impl CallCollector {
    fn caller(&self) -> Option<(Option<String>, String)> {
        (self.test_depth == 0).then(|| self.function.last().cloned())?
    }

    fn enter_fn(&mut self, attrs: &[syn::Attribute], name: &syn::Ident) -> bool {
        let test = attrs.iter().any(is_test_attr);
        self.test_depth += usize::from(test);
        let owner = self.owner.last().cloned().flatten();
        self.function.push((owner, name.to_string()));
        self.owner.push(None);
        test
    }

    fn leave_fn(&mut self, test: bool) {
        self.owner.pop();
        self.function.pop();
        self.test_depth -= usize::from(test);
    }
}

impl<'ast> syn::visit::Visit<'ast> for CallCollector {
    fn visit_item_mod(&mut self, module: &'ast syn::ItemMod) {
        let test = module.attrs.iter().any(is_test_attr);
        if test && module.content.is_none() {
            self.test_modules.push(module.ident.to_string());
        }
        self.test_depth += usize::from(test);
        syn::visit::visit_item_mod(self, module);
        self.test_depth -= usize::from(test);
    }

    fn visit_item_impl(&mut self, item: &'ast syn::ItemImpl) {
        self.owner.push(impl_owner(item));
        syn::visit::visit_item_impl(self, item);
        self.owner.pop();
    }

    fn visit_item_fn(&mut self, item: &'ast syn::ItemFn) {
        let test = self.enter_fn(&item.attrs, &item.sig.ident);
        syn::visit::visit_item_fn(self, item);
        self.leave_fn(test);
    }

    fn visit_impl_item_fn(&mut self, item: &'ast syn::ImplItemFn) {
        let test = self.enter_fn(&item.attrs, &item.sig.ident);
        syn::visit::visit_impl_item_fn(self, item);
        self.leave_fn(test);
    }

    fn visit_trait_item_fn(&mut self, item: &'ast syn::TraitItemFn) {
        let test = self.enter_fn(&item.attrs, &item.sig.ident);
        syn::visit::visit_trait_item_fn(self, item);
        self.leave_fn(test);
    }

    fn visit_expr_path(&mut self, expr: &'ast syn::ExprPath) {
        if let (Some(caller), Some(last)) = (self.caller(), expr.path.segments.last()) {
            let n = expr.path.segments.len();
            let qualifier = (n >= 2).then(|| expr.path.segments[n - 2].ident.to_string());
            let qualifier = match qualifier.as_deref() {
                Some("Self") => caller.0.clone(),
                _ => qualifier,
            };
            self.references.push(Reference {
                name: last.ident.to_string(),
                qualifier,
                method: false,
                caller,
            });
        }
        syn::visit::visit_expr_path(self, expr);
    }

    fn visit_expr_method_call(&mut self, expr: &'ast syn::ExprMethodCall) {
        if let Some(caller) = self.caller() {
            self.references.push(Reference {
                name: expr.method.to_string(),
                qualifier: None,
                method: true,
                caller,
            });
        }
        syn::visit::visit_expr_method_call(self, expr);
    }

    fn visit_expr(&mut self, expr: &'ast syn::Expr) {
        if let (Some(caller), Some((line, what))) = (self.caller(), solver_shape(expr)) {
            self.solvers.push(SolverHit { line, caller, what });
        }
        if let (Some(caller), Some((equations, what))) = (self.caller(), formula_shape(expr)) {
            let line = match expr {
                syn::Expr::Binary(b) => match &b.op {
                    syn::BinOp::Mul(t) => t.spans[0].start().line,
                    syn::BinOp::Add(t) => t.spans[0].start().line,
                    _ => 0,
                },
                syn::Expr::MethodCall(m) => m.method.span().start().line,
                _ => 0,
            };
            self.shapes.push(ShapeHit {
                equations,
                line,
                caller,
                what,
            });
        }
        syn::visit::visit_expr(self, expr);
    }
}

fn calls_in_text(text: &str) -> CallCollector {
    let file = syn::parse_file(text).unwrap_or_else(|e| panic!("does not parse: {e}"));
    let mut collector = CallCollector::default();
    syn::visit::Visit::visit_file(&mut collector, &file);
    collector
}

/// The production sources of the library crates and their references and shapes: every
/// `crates/*/src` file except those of `#[cfg(test)]` modules, `tests.rs` files and
/// `bench_support.rs` (bench helpers).
fn production_calls() -> Vec<(PathBuf, CallCollector)> {
    production_calls_in(
        crate_names()
            .into_iter()
            .map(|name| workspace_root().join("crates").join(name).join("src"))
            .collect(),
    )
}

/// [`production_calls`] of the given source folders (each one package's `src`).
fn production_calls_in(src_dirs: Vec<PathBuf>) -> Vec<(PathBuf, CallCollector)> {
    let mut out = Vec::new();
    for src in src_dirs {
        let files: Vec<(PathBuf, CallCollector)> = rust_sources(&src)
            .into_iter()
            .map(|file| {
                let text = std::fs::read_to_string(&file).expect("source readable");
                let calls = calls_in_text(&text);
                (file, calls)
            })
            .collect();
        let test_modules: BTreeSet<String> = files
            .iter()
            .flat_map(|(_, c)| c.test_modules.iter().cloned())
            .chain(["tests".to_owned(), "bench_support".to_owned()])
            .collect();
        out.extend(files.into_iter().filter(|(file, _)| {
            let stem = file.file_stem().map(|s| s.to_string_lossy().into_owned());
            let module = if stem.as_deref() == Some("mod") {
                file.parent()
                    .and_then(Path::file_name)
                    .map(|s| s.to_string_lossy().into_owned())
            } else {
                stem
            };
            !module.is_some_and(|m| test_modules.contains(&m))
        }));
    }
    out
}

/// Whether `reference` reaches the indexed function `(owner, name)` from another function.
fn reaches(reference: &Reference, owner: Option<&str>, name: &str) -> bool {
    if reference.name != name
        || (reference.caller.0.as_deref() == owner && reference.caller.1 == name)
    {
        return false;
    }
    match (owner, reference.method) {
        (_, true) => owner.is_some(),
        (Some(owner), false) => reference.qualifier.as_deref().is_none_or(|q| q == owner),
        (None, false) => true,
    }
}

/// The indexed functions no production code reaches, and the formulas of eqs. (3), (5) and
/// (11) computed outside the functions the index names for them.
fn equation_call_graph_problems(
    index: &BTreeMap<u32, Vec<String>>,
    calls: &[(PathBuf, CallCollector)],
) -> Vec<String> {
    let mut problems = Vec::new();
    // The equations each indexed function is listed for.
    let mut indexed: BTreeMap<(Option<String>, String), BTreeSet<u32>> = BTreeMap::new();
    for (n, functions) in index {
        for entry in functions {
            let Some((_, item)) = entry.split_once(".rs::") else {
                continue;
            };
            let (owner, name) = match item.rsplit_once("::") {
                Some((owner, name)) => (Some(owner), name),
                None => (None, item),
            };
            indexed
                .entry((owner.map(str::to_owned), name.to_owned()))
                .or_default()
                .insert(*n);
            let reached = calls
                .iter()
                .flat_map(|(_, c)| &c.references)
                .any(|r| reaches(r, owner, name));
            if !reached {
                problems.push(format!(
                    "eq. ({n}): `{entry}` is reached from tests only (no production caller)"
                ));
            }
        }
    }
    for (file, collector) in calls {
        for hit in &collector.shapes {
            let allowed = indexed
                .get(&hit.caller)
                .is_some_and(|listed| hit.equations.iter().any(|e| listed.contains(e)));
            if allowed {
                continue;
            }
            let relative = file.strip_prefix(workspace_root()).unwrap_or(file);
            problems.push(format!(
                "eq. ({}): {}:{} in fn {}{} computes {} itself; call the indexed function",
                hit.equations[0],
                relative.display(),
                hit.line,
                hit.caller
                    .0
                    .as_ref()
                    .map(|o| format!("{o}::"))
                    .unwrap_or_default(),
                hit.caller.1,
                hit.what
            ));
        }
    }
    problems
}

#[test]
fn every_indexed_function_is_reached_from_production_and_its_formula_is_written_once() {
    let problems = equation_call_graph_problems(&equation_index(), &production_calls());
    assert!(
        problems.is_empty(),
        "docs/ARCHITECTURE.md, equation index (a name-level call graph of crates/*/src \
         without test code):\n  {}",
        problems.join("\n  ")
    );
}

#[test]
fn the_equation_call_graph_finds_test_only_functions_and_second_formulas() {
    let text = "
        pub struct F;
        impl F {
            /// Implements eq. (3).
            pub fn from_lcc(ky: f64, alpha: f64) -> f64 { ky * alpha.sin() }
        }
        /// Implements eq. (5).
        pub fn step(k: &K, dx: f64, dy: f64) -> f64 { k.kx_nm_per_count * dx + k.kyx_nm_per_count * dy }
        pub fn used() -> f64 { F::from_lcc(1.0, 0.5) }
        pub fn second(l: &L) -> f64 { l.ky_nm_per_count * l.alpha_rad.cos() }
        pub fn third(a: f64) -> (f64, f64) { a.alpha.sin_cos() }
        pub fn fourth(k: &K) -> f64 { (k.kx_nm_per_count * 2.0) + k.kyx_nm_per_count * 3.0 }
        /// Implements eq. (2).
        pub fn fit_plane(ky: &[f64], a: &[f64]) -> Vec<f64> {
            ky.iter().zip(a).map(|(ky, a)| ky * a.sin()).collect()
        }
        #[cfg(test)]
        mod tests {
            #[test]
            fn t() { let _ = super::step(&K, 1.0, 0.0); }
        }
    ";
    let mut index = BTreeMap::new();
    index.insert(3, vec!["a.rs::F::from_lcc".to_owned()]);
    index.insert(5, vec!["a.rs::step".to_owned()]);
    index.insert(2, vec!["a.rs::fit_plane".to_owned()]);
    let problems =
        equation_call_graph_problems(&index, &[(PathBuf::from("a.rs"), calls_in_text(text))]);
    let has = |needle: &str| problems.iter().any(|p| p.contains(needle));
    assert!(
        has("`a.rs::step` is reached from tests only"),
        "{problems:#?}"
    );
    assert!(!has("from_lcc` is reached"), "{problems:#?}");
    assert!(
        has("in fn second computes K̄y times sin/cos"),
        "{problems:#?}"
    );
    assert!(has("in fn third computes sin_cos() of α"), "{problems:#?}");
    assert!(has("in fn fourth computes K̄x·Δx + K̄yx·Δy"), "{problems:#?}");
    assert!(
        has("`a.rs::fit_plane` is reached from tests only"),
        "{problems:#?}"
    );
    assert!(
        has("in fn fit_plane computes K̄y times sin/cos"),
        "{problems:#?}"
    );
    assert!(
        !has("in fn step") && !has("F::from_lcc computes"),
        "{problems:#?}"
    );
    assert_eq!(problems.len(), 6, "{problems:#?}");
}

/// spm-sim is layered (issue 28 item 4): the configuration; the physics of each part
/// (`scanner`, `drift`, `surface`, `vertical`, `fault`); the state they make up (`state`); the
/// oracle that reads that state and nothing else (`oracle`); the simulator that advances it
/// (`sim`) and its ground-truth traits (`truth`). A module names (`crate::…`, in code, not in
/// comments) only modules of a lower layer; a name re-exported at the crate root counts as its
/// module's. No cycle is then possible (the oracle read 13 fields of the simulator, and
/// config, sim, oracle and vertical named each other, before).
#[test]
fn the_simulator_is_layered_config_physics_state_oracle_simulator() {
    let layer_of = |module: &str| -> Option<usize> {
        Some(match module {
            "config" => 0,
            "fault" | "scanner" | "drift" | "surface" | "vertical" => 1,
            "state" => 2,
            "oracle" => 3,
            "sim" => 4,
            "truth" => 5,
            _ => return None,
        })
    };
    let src = workspace_root().join("crates/spm-sim/src");
    let lib = std::fs::read_to_string(src.join("lib.rs")).expect("spm-sim's lib.rs");
    // Root re-exports: `pub use module::{A, B};` (possibly over several lines).
    let mut root_names: BTreeMap<String, String> = BTreeMap::new();
    for statement in lib.split(';') {
        let statement = statement.trim();
        let Some(rest) = statement
            .rsplit("pub use ")
            .next()
            .filter(|_| statement.contains("pub use "))
        else {
            continue;
        };
        let Some((module, names)) = rest.split_once("::") else {
            continue;
        };
        for name in names
            .trim_matches(|c| c == '{' || c == '}' || char::is_whitespace(c))
            .split(',')
        {
            let name = name.trim();
            if !name.is_empty() {
                root_names.insert(name.to_owned(), module.trim().to_owned());
            }
        }
    }
    assert!(
        root_names.get("Oracle").map(String::as_str) == Some("oracle"),
        "the re-export parser found {root_names:?}"
    );
    let mut offences = Vec::new();
    let mut checked = 0;
    for file in rust_sources(&src) {
        let module = file
            .file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or_default()
            .to_owned();
        let Some(own) = layer_of(&module) else {
            continue;
        };
        let text = std::fs::read_to_string(&file).expect("source readable");
        for (n, line) in text.lines().enumerate() {
            let code = line.split("//").next().unwrap_or_default();
            for piece in code.split("crate::").skip(1) {
                let name: String = piece
                    .chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_')
                    .collect();
                let target = root_names.get(&name).cloned().unwrap_or(name);
                let Some(theirs) = layer_of(&target) else {
                    continue;
                };
                checked += 1;
                if target != module && theirs >= own {
                    offences.push(format!(
                        "crates/spm-sim/src/{module}.rs:{}: `{module}` (layer {own}) names \
                         `{target}` (layer {theirs})",
                        n + 1
                    ));
                }
            }
        }
    }
    assert!(
        checked >= 20,
        "only {checked} crate paths found: the scan is broken"
    );
    assert!(
        offences.is_empty(),
        "spm-sim's layers are crossed:\n  {}",
        offences.join("\n  ")
    );
}

/// One drawing stack (issue 28 item 5): spm-plot is the only crate whose manifest names
/// plotters; the model check, the CLI and xtask draw through it.
#[test]
fn only_spm_plot_depends_on_plotters() {
    let mut users = Vec::new();
    let manifests = crate_names()
        .into_iter()
        .map(|name| {
            workspace_root()
                .join("crates")
                .join(name)
                .join("Cargo.toml")
        })
        .chain([workspace_root().join("xtask/Cargo.toml")]);
    for manifest in manifests {
        let text = std::fs::read_to_string(&manifest).expect("manifest readable");
        let table: toml::Table = text.parse().expect("manifest is TOML");
        let names = |key: &str| {
            table
                .get(key)
                .and_then(toml::Value::as_table)
                .is_some_and(|deps| deps.contains_key("plotters"))
        };
        if names("dependencies") || names("dev-dependencies") || names("build-dependencies") {
            users.push(
                manifest
                    .strip_prefix(workspace_root())
                    .unwrap_or(&manifest)
                    .display()
                    .to_string(),
            );
        }
    }
    assert_eq!(users, vec!["crates/spm-plot/Cargo.toml".to_owned()]);
}

// ---------------------------------------------------------------------------------------------
// One numerics kernel (issue 28 item 1): linear algebra solves only in spm-regression.
// ---------------------------------------------------------------------------------------------

/// A linear-algebra solve found in production code.
#[derive(Debug)]
struct SolverHit {
    line: usize,
    caller: (Option<String>, String),
    what: String,
}

/// The matrix decompositions and inverses only the numerics kernel (`crates/spm-regression`)
/// calls: anything else solves through `least_squares`, `minimum_norm_least_squares` or
/// `minimum_norm_solve`.
const KERNEL_ONLY_METHODS: &[&str] = &[
    "svd",
    "try_svd",
    "cholesky",
    "lu",
    "full_piv_lu",
    "qr",
    "col_piv_qr",
    "udu",
    "bunch_kaufman",
    "symmetric_eigen",
    "try_inverse",
    "try_inverse_mut",
    "pseudo_inverse",
    "solve_lower_triangular",
    "solve_upper_triangular",
];

/// Parentheses and references around an expression removed.
fn peeled(expr: &syn::Expr) -> &syn::Expr {
    match expr {
        syn::Expr::Paren(p) => peeled(&p.expr),
        syn::Expr::Reference(r) => peeled(&r.expr),
        other => other,
    }
}

/// A plain operand (a name, a field, an index by a name or a literal) as text, to compare two
/// operands; `None` for anything else.
fn operand_key(expr: &syn::Expr) -> Option<String> {
    Some(match peeled(expr) {
        syn::Expr::Path(p) => p
            .path
            .segments
            .iter()
            .map(|s| s.ident.to_string())
            .collect::<Vec<_>>()
            .join("::"),
        syn::Expr::Field(f) => {
            let member = match &f.member {
                syn::Member::Named(ident) => ident.to_string(),
                syn::Member::Unnamed(index) => index.index.to_string(),
            };
            format!("{}.{member}", operand_key(&f.base)?)
        }
        syn::Expr::Index(i) => format!("{}[{}]", operand_key(&i.expr)?, operand_key(&i.index)?),
        syn::Expr::Lit(syn::ExprLit {
            lit: syn::Lit::Int(n),
            ..
        }) => n.base10_digits().to_owned(),
        _ => return None,
    })
}

/// `a * d − b * b`: the determinant of a symmetric 2 × 2 matrix, the shape of a Gram (normal)
/// matrix's determinant in a hand-written least-squares solve. (A general 2 × 2 inverse,
/// `a * d − b * c` of a basis or a Jacobian, is not a fit and is not matched.)
fn is_symmetric_determinant(expr: &syn::Expr) -> bool {
    let product = |e: &syn::Expr| match peeled(e) {
        syn::Expr::Binary(b) if matches!(b.op, syn::BinOp::Mul(_)) => {
            Some((operand_key(&b.left)?, operand_key(&b.right)?))
        }
        _ => None,
    };
    match peeled(expr) {
        syn::Expr::Binary(b) if matches!(b.op, syn::BinOp::Sub(_)) => {
            matches!((product(&b.left), product(&b.right)),
                (Some((a, d)), Some((b1, b2))) if a != d && b1 == b2)
        }
        _ => false,
    }
}

/// Whether an expression is a solve that belongs in the kernel: a decomposition or inverse
/// ([`KERNEL_ONLY_METHODS`]); a product with a transpose on its left (XᵀX, Xᵀy: normal
/// equations formed by hand); the determinant of a symmetric 2 × 2 matrix (a normal matrix solved by hand); or
/// Cramer's rule with a `det…(…)` function. Its line and what it is.
fn solver_shape(expr: &syn::Expr) -> Option<(usize, String)> {
    match expr {
        syn::Expr::MethodCall(m) => {
            let name = m.method.to_string();
            KERNEL_ONLY_METHODS
                .contains(&name.as_str())
                .then(|| (m.method.span().start().line, format!("calls .{name}()")))
        }
        syn::Expr::Binary(b) => match &b.op {
            syn::BinOp::Mul(t) => {
                let transposed = |e: &syn::Expr| matches!(peeled(e), syn::Expr::MethodCall(m) if m.method == "transpose");
                // Xᵀ on the left: XᵀX, Xᵀy, XᵀWX (a propagation J·C·Jᵀ has it on the right).
                transposed(&b.left).then(|| {
                    (
                        t.spans[0].start().line,
                        "multiplies by a transpose (normal equations XᵀX, Xᵀy by hand)".to_owned(),
                    )
                })
            }
            syn::BinOp::Sub(t) if is_symmetric_determinant(expr) => Some((
                t.spans[0].start().line,
                "forms the determinant a·d − b² of a symmetric 2 × 2 (normal) matrix".to_owned(),
            )),
            syn::BinOp::Div(t) => {
                let det_call = matches!(peeled(&b.left), syn::Expr::Call(c)
                    if matches!(peeled(&c.func), syn::Expr::Path(p)
                        if p.path.segments.last().is_some_and(|s| s.ident.to_string().starts_with("det"))));
                det_call.then(|| {
                    (
                        t.spans[0].start().line,
                        "divides a determinant by a determinant (Cramer's rule)".to_owned(),
                    )
                })
            }
            _ => None,
        },
        _ => None,
    }
}

/// The justified exceptions: `(file, function, why it is not the kernel's business)`. Each
/// entry must still match something (a stale entry fails the test too).
const SOLVER_ALLOW_LIST: &[(&str, &str, &str)] = &[
    // Newton steps of nonlinear fits: a damped Gauss–Newton step solves a small fixed-size
    // normal matrix of the linearisation, one per iteration; not a linear least-squares fit.
    (
        "crates/spm-features/src/fit.rs",
        "fit_gaussian",
        "Levenberg–Marquardt step (5 × 5) and its covariance",
    ),
    (
        "crates/spm-features/src/cells.rs",
        "fit_cell",
        "Gauss–Newton step (3 × 3) of a cell's template fit",
    ),
    (
        "crates/spm-features/src/cells.rs",
        "locate_one",
        "the cell fit's covariance (3 × 3 inverse of its Newton normal matrix)",
    ),
    // The Cramér–Rao bound is the inverse Fisher information itself, not a fit.
    (
        "crates/spm-features/src/crb.rs",
        "bound_from_fisher",
        "inverse Fisher information (the bound)",
    ),
    // Not solves: the inverse of the 2 × 2 map P (M = P⁻¹ up to a rotation), and det G of the
    // metric, whose sign and size decide that the metric is positive definite (α from it).
    (
        "crates/spm-calibration/src/lcc.rs",
        "coefficients",
        "det G of the metric, a positive-definiteness test",
    ),
    (
        "crates/spm-calibration/src/lcc.rs",
        "coefficients_and_jacobian",
        "inverse of the 2 × 2 map P",
    ),
    // Streamed closed forms of the kernel's least squares (moments summed over an image, no
    // design kept), each checked against the kernel's fit to 1e-9 by the test it names.
    (
        "crates/spm-features/src/step.rs",
        "solve_lines",
        "streamed; test solve_lines_is_the_kernel_least_squares",
    ),
    (
        "crates/spm-plot/src/channel.rs",
        "level",
        "streamed; test level_is_the_kernel_plane_fit",
    ),
    (
        "crates/spm-features/src/cells.rs",
        "window_fit",
        "the template's weighted line per pixel from streamed moments; test \
         window_fit_is_the_kernel_weighted_least_squares",
    ),
    (
        "crates/spm-virtual/src/image.rs",
        "without_background",
        "a weighted plane per pixel from smoothed moments; test \
         background_removal_is_the_kernel_weighted_plane_fit",
    ),
];

/// The solves outside the kernel that the allow-list does not name, and the allow-list
/// entries that name nothing.
fn solver_problems(
    calls: &[(PathBuf, CallCollector)],
    allow: &[(&str, &str, &str)],
) -> Vec<String> {
    let mut problems = Vec::new();
    let mut used = vec![false; allow.len()];
    for (file, collector) in calls {
        let relative = file.strip_prefix(workspace_root()).unwrap_or(file);
        let path = relative.to_string_lossy().replace('\\', "/");
        if path.starts_with("crates/spm-regression/") {
            continue;
        }
        for hit in &collector.solvers {
            if let Some(k) = allow
                .iter()
                .position(|(p, f, _)| *p == path && *f == hit.caller.1)
            {
                used[k] = true;
                continue;
            }
            problems.push(format!(
                "{path}:{} in fn {}{} {}: solve through spm_regression (least_squares, \
                 minimum_norm_least_squares, minimum_norm_solve) or add a commented \
                 SOLVER_ALLOW_LIST entry",
                hit.line,
                hit.caller
                    .0
                    .as_ref()
                    .map(|o| format!("{o}::"))
                    .unwrap_or_default(),
                hit.caller.1,
                hit.what
            ));
        }
    }
    for ((path, function, _), used) in allow.iter().zip(used) {
        if !used {
            problems.push(format!(
                "SOLVER_ALLOW_LIST names {path}::{function}, which solves nothing any more: \
                 remove the entry"
            ));
        }
    }
    problems
}

#[test]
fn linear_algebra_solves_only_in_the_numerics_kernel() {
    let mut dirs: Vec<PathBuf> = crate_names()
        .into_iter()
        .map(|name| workspace_root().join("crates").join(name).join("src"))
        .collect();
    dirs.push(workspace_root().join("xtask/src"));
    let calls = production_calls_in(dirs);
    let kernel_hits = calls
        .iter()
        .filter(|(f, _)| f.starts_with(workspace_root().join("crates/spm-regression")))
        .map(|(_, c)| c.solvers.len())
        .sum::<usize>();
    assert!(
        kernel_hits >= 3,
        "the kernel's own solves are not found: the scan is broken"
    );
    let problems = solver_problems(&calls, SOLVER_ALLOW_LIST);
    assert!(
        problems.is_empty(),
        "one numerics kernel (docs/ARCHITECTURE.md, spm-regression):\n  {}",
        problems.join("\n  ")
    );
}

#[test]
fn the_solver_check_finds_decompositions_normal_equations_and_cramer() {
    let text = "
        pub fn svd_solve(a: M, b: V) -> V { a.svd(true, true).solve(&b, 1e-12).unwrap() }
        pub fn normal(x: M, y: V) -> V { let n = x.transpose() * &x; n.cholesky().unwrap().solve(&(x.transpose() * y)) }
        pub fn cramer(sxx: f64, sxy: f64, syy: f64, sxz: f64, syz: f64) -> f64 {
            let det = sxx * syy - sxy * sxy;
            (sxz * syy - syz * sxy) / det
        }
        pub fn cramer3(a: &M, c: &M) -> f64 { det3(c) / det3(a) }
        pub fn propagate(j: M, c: M) -> M { &j * &c * j.transpose() }
        pub fn fine(j: [[f64; 2]; 2], v: [f64; 2]) -> f64 {
            let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
            (j[1][1] * v[0]) / det
        }
        pub fn allowed(m: M) -> M { m.try_inverse().unwrap() }
        #[cfg(test)]
        mod tests {
            fn reference(a: M) -> M { a.svd(true, true).pseudo_inverse(0.0).unwrap() }
        }
    ";
    let calls = [(
        workspace_root().join("crates/x/src/a.rs"),
        calls_in_text(text),
    )];
    let allow = [
        ("crates/x/src/a.rs", "allowed", "a reason"),
        ("crates/x/src/a.rs", "gone", "a stale entry"),
    ];
    let problems = solver_problems(&calls, &allow);
    let has = |needle: &str| problems.iter().any(|p| p.contains(needle));
    assert!(has("fn svd_solve calls .svd()"), "{problems:#?}");
    assert!(has("fn normal multiplies by a transpose"), "{problems:#?}");
    assert!(has("fn normal calls .cholesky()"), "{problems:#?}");
    assert!(
        has("fn cramer forms the determinant a·d − b²"),
        "{problems:#?}"
    );
    assert!(has("fn cramer3 divides a determinant"), "{problems:#?}");
    assert!(has("names crates/x/src/a.rs::gone"), "{problems:#?}");
    assert!(
        !has("fn fine") && !has("fn allowed") && !has("fn reference") && !has("fn propagate"),
        "{problems:#?}"
    );
    assert_eq!(problems.len(), 7, "{problems:#?}");
}
