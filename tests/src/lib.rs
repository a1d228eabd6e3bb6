//! Shared helpers for tests across the workspace.
//!
//! The only way a test reaches the measured data in `../shared/data/` is
//! [`shared_data_dir`]: it finds the folder beside the project's root (or the
//! path in `SPMCAL_SHARED_DATA`) and fails with a message that says where it
//! looked when the folder is missing.

use std::path::{Path, PathBuf};

/// The `shared/data` folder beside the project's root.
///
/// Looks at `$SPMCAL_SHARED_DATA` first, then at `../shared/data` relative to
/// the workspace root (the folder holding this crate's parent).
///
/// # Panics
/// Panics with a clear message when the folder cannot be found: this is a test
/// helper, and a missing data folder is a broken test environment.
pub fn shared_data_dir() -> PathBuf {
    match find_shared_data_dir() {
        Ok(path) => path,
        Err(looked) => panic!(
            "the shared data folder is missing: looked in {looked}. \
             Clone the project with ../shared/ beside it, or set SPMCAL_SHARED_DATA \
             to the path of shared/data."
        ),
    }
}

/// A file under `shared/data/measured/`, checked to exist.
///
/// # Panics
/// Panics naming the full path when the file is missing.
pub fn measured_file(relative: &str) -> PathBuf {
    let path = shared_data_dir().join("measured").join(relative);
    assert!(
        path.is_file(),
        "measured data file {} is missing from the shared data folder",
        path.display()
    );
    path
}

/// Like [`shared_data_dir`] but returns the places it looked instead of panicking.
pub fn find_shared_data_dir() -> Result<PathBuf, String> {
    let mut looked = Vec::new();
    if let Some(env) = std::env::var_os("SPMCAL_SHARED_DATA") {
        let candidate = PathBuf::from(env);
        if candidate.is_dir() {
            return Ok(candidate);
        }
        looked.push(candidate);
    }
    let workspace_root = Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_default();
    let candidate = workspace_root.join("..").join("shared").join("data");
    if candidate.is_dir() {
        return Ok(candidate);
    }
    looked.push(candidate);
    Err(looked
        .iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(", "))
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_shared_data_folder_holds_the_measured_readme() {
        let readme = super::shared_data_dir().join("measured").join("README.md");
        assert!(readme.is_file(), "{} missing", readme.display());
    }
}
