//! Fuzz target: the gsf reader on arbitrary bytes (forced format, no detection).
//! It must return a file or a typed error, never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use spm_formats::{Format, read_as};
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let _ = read_as(data, Path::new("fuzz/field.gsf"), Format::Gsf);
});
