//! Records the git commit spmcal is built from (`SPMCAL_GIT_COMMIT`), for the provenance of
//! the calibration files and reports it writes. Outside a git checkout (a packaged crate) the
//! variable is unset and the provenance says the commit is unknown.

use std::path::Path;
use std::process::Command;

fn main() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let git_dir = root.join(".git");
    if git_dir.join("HEAD").exists() {
        println!("cargo:rerun-if-changed={}", git_dir.join("HEAD").display());
        println!(
            "cargo:rerun-if-changed={}",
            git_dir.join("refs/heads").display()
        );
        println!(
            "cargo:rerun-if-changed={}",
            git_dir.join("packed-refs").display()
        );
    } else if git_dir.is_file() {
        // A worktree: .git is a file naming the real git directory.
        println!("cargo:rerun-if-changed={}", git_dir.display());
    }
    let output = Command::new("git")
        .args(["rev-parse", "HEAD"])
        .current_dir(&root)
        .output();
    if let Ok(output) = output
        && output.status.success()
        && let Ok(text) = String::from_utf8(output.stdout)
    {
        let commit = text.trim();
        if commit.len() == 40 && commit.chars().all(|c| c.is_ascii_hexdigit()) {
            println!("cargo:rustc-env=SPMCAL_GIT_COMMIT={commit}");
        }
    }
}
