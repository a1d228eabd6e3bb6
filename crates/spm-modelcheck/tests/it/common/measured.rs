//! The diagnoses of the measured files (../shared/data/measured, through the one data
//! helper), with the default options, made once per test binary and shared: the rule that
//! every accepted finding lowers the held-out RMS (`rules`) and the expectations file by file
//! (`measured`) read the same diagnoses. A diagnosis is deterministic, so a test that made
//! its own would get the same one.

use spm_modelcheck::{Diagnosis, ExtractOptions, LatticeSpec, ModelCheckError, Options};
use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

/// What `diagnose` gave on some measured files.
pub type Outcome = Arc<Result<Diagnosis, ModelCheckError>>;

/// The diagnosis of `files` (paths under ../shared/data/measured) against `lattice`
/// (`hopg`, `si7x7`, …) with the default options. The first test to ask makes it; the others
/// wait for it and share it.
pub fn diagnosis(files: &[&str], lattice: &str) -> Outcome {
    type Cells = HashMap<String, Arc<OnceLock<Outcome>>>;
    static CACHE: OnceLock<Mutex<Cells>> = OnceLock::new();
    let key = format!("{lattice}|{}", files.join("|"));
    let cell = {
        let mut cache = CACHE
            .get_or_init(|| Mutex::new(HashMap::new()))
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        Arc::clone(cache.entry(key).or_default())
    };
    Arc::clone(cell.get_or_init(|| {
        let paths: Vec<_> = files
            .iter()
            .map(|f| spmcal_tests::measured_file(f))
            .collect();
        let inputs = super::image::inputs(&paths);
        Arc::new(LatticeSpec::parse(lattice).and_then(|spec| {
            spm_modelcheck::diagnose(
                &inputs,
                &spec,
                &Options::default(),
                &ExtractOptions::default(),
            )
        }))
    }))
}
