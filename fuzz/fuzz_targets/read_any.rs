//! Fuzz target: format detection plus whichever reader it picks (`read_bytes`, the in-memory
//! half of `read_any`). The first byte chooses the file name's extension so detection by
//! extension is exercised too. It must return a file or a typed error, never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use spm_formats::read_bytes;
use std::path::Path;

const NAMES: [&str; 7] = [
    "x.sxm",
    "x.sm4",
    "x.spm",
    "x.dat",
    "x.gsf",
    "x.raw",
    "x.unknown",
];

fuzz_target!(|data: &[u8]| {
    let Some((&selector, rest)) = data.split_first() else {
        return;
    };
    let name = NAMES[usize::from(selector) % NAMES.len()];
    let _ = read_bytes(rest, Path::new(name));
});
