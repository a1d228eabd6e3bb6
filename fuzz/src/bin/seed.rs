//! Builds the fuzz corpus at run time from the measured files (the data are not committed).
//!
//! `cargo run --release --bin seed -- [MEASURED_DIR] [CORPUS_DIR]` (defaults
//! `../../shared/data/measured` relative to `fuzz/`, and `corpus`). For every target it writes:
//! the first 64 KiB of each real file of that format (a complete header, truncated data); a
//! shrunk but valid 16 × 16 version where the format makes that easy (sxm, ISO 28600, raw,
//! GSF re-encoded from a real channel); the `read_any` corpus gets all of them with a
//! leading selector byte (see `fuzz_targets/read_any.rs`).

use spm_formats::{SpmFile, encode_gsf, encode_raw_f64, read_any};
use std::error::Error;
use std::fs;
use std::path::PathBuf;

const PREFIX: usize = 64 * 1024;
const SMALL: usize = 16;

fn main() -> Result<(), Box<dyn Error>> {
    let mut args = std::env::args().skip(1);
    let measured = args.next().map_or_else(
        || PathBuf::from("../../shared/data/measured"),
        PathBuf::from,
    );
    let corpus = args
        .next()
        .map_or_else(|| PathBuf::from("corpus"), PathBuf::from);
    let mut seeds: Vec<(&str, String, Vec<u8>)> = Vec::new();
    let mut files: Vec<PathBuf> = Vec::new();
    for dir in fs::read_dir(&measured)? {
        let dir = dir?.path();
        if dir.is_dir() {
            for f in fs::read_dir(&dir)? {
                files.push(f?.path());
            }
        }
    }
    files.sort();
    let mut gsf_done = false;
    for path in &files {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let target = match path.extension().and_then(|e| e.to_str()) {
            Some("sxm") => "sxm",
            Some("sm4") => "sm4",
            Some("spm") => "iso28600",
            Some("dat") => "raw",
            _ => continue,
        };
        let bytes = fs::read(path)?;
        seeds.push((
            target,
            format!("{name}.prefix"),
            bytes[..bytes.len().min(PREFIX)].to_vec(),
        ));
        let small = match target {
            "sxm" => shrink_sxm(&bytes),
            "iso28600" => shrink_iso(&bytes),
            _ => None,
        };
        if let Some(small) = small {
            seeds.push((target, format!("{name}.small"), small));
        }
        if let Some(channel) = read_any(path).ok().as_ref().and_then(small_channel) {
            if target == "raw" {
                seeds.push(("raw", format!("{name}.small"), encode_raw_f64(&channel)));
            }
            if !gsf_done {
                seeds.push((
                    "gsf",
                    format!("{name}.small.gsf"),
                    encode_gsf(&channel, &[("Source", "seed")])?,
                ));
                gsf_done = true;
            }
        }
    }
    let targets = ["sxm", "sm4", "iso28600", "raw", "gsf"];
    for (i, (target, name, bytes)) in seeds.iter().enumerate() {
        let dir = corpus.join(target);
        fs::create_dir_all(&dir)?;
        fs::write(dir.join(name), bytes)?;
        // read_any: selector byte = index of the matching extension in its NAMES table.
        let selector = targets.iter().position(|t| t == target).unwrap_or(6) as u8;
        let any = corpus.join("read_any");
        fs::create_dir_all(&any)?;
        let mut tagged = vec![selector];
        tagged.extend_from_slice(bytes);
        fs::write(any.join(format!("{i:02}-{name}")), tagged)?;
    }
    println!("{} seeds written under {}", seeds.len(), corpus.display());
    Ok(())
}

/// The top-left SMALL × SMALL crop of the first channel.
fn small_channel(file: &SpmFile) -> Option<spm_formats::Channel> {
    let c = file.channels.first()?;
    let (nx, ny) = (c.nx(), c.ny());
    if nx < SMALL || ny < SMALL {
        return None;
    }
    let data: Vec<f64> = (0..SMALL)
        .flat_map(|r| c.data()[r * nx..r * nx + SMALL].iter().copied())
        .collect();
    let ch =
        spm_formats::Channel::new(c.name(), c.direction(), c.unit(), SMALL, SMALL, data).ok()?;
    Some(ch.with_size_nm(1.0, 1.0))
}

fn find(haystack: &[u8], needle: &[u8]) -> Option<usize> {
    haystack.windows(needle.len()).position(|w| w == needle)
}

/// A Nanonis file whose header says 16 × 16 pixels, cut after enough data for every
/// channel and direction at that size (the reader only needs the bytes it reads).
fn shrink_sxm(bytes: &[u8]) -> Option<Vec<u8>> {
    let key = b":SCAN_PIXELS:\n";
    let at = find(bytes, key)? + key.len();
    let eol = at + bytes[at..].iter().position(|&b| b == b'\n')?;
    let end = find(bytes, b":SCANIT_END:")?;
    let mut out = bytes[..at].to_vec();
    out.extend_from_slice(format!("{SMALL:>10}{SMALL:>10}").as_bytes());
    out.extend_from_slice(&bytes[eol..end]);
    let data_start = end + find(&bytes[end..], b"\x1a\x04")? + 2;
    out.extend_from_slice(&bytes[end..data_start]);
    // At most 16 channels × 2 directions of 16 × 16 f32.
    let need = 16 * 2 * SMALL * SMALL * 4;
    out.extend_from_slice(&bytes[data_start..(data_start + need).min(bytes.len())]);
    Some(out)
}

/// An ISO 28600 file whose header says 16 × 16 points, with that many data lines.
fn shrink_iso(bytes: &[u8]) -> Option<Vec<u8>> {
    let text = std::str::from_utf8(bytes).ok()?;
    let header_end = text.find("end of header\n")? + "end of header\n".len();
    let header = text[..header_end].replacen("\n512\n512\n", &format!("\n{SMALL}\n{SMALL}\n"), 1);
    let mut out = header;
    for line in text[header_end..].lines().take(SMALL * SMALL) {
        out.push_str(line);
        out.push('\n');
    }
    out.push_str("end of experiment\n");
    Some(out.into_bytes())
}
