//! `spm_apply::crop`: a part of a real file, written as `.gsf` and read back, keeps the whole
//! file's raster at its pixels (offset, scan angle, slow direction, pixel size), its values
//! and its pixels' times. The truth is the whole file's own raster (`FileRaster::of`), checked
//! against the headers by hand in `real_files`.
#![allow(clippy::unwrap_used)]

use spm_apply::FileRaster;
use spm_apply::crop::{KEY_CROP, crop_file};
use spm_formats::{SpmFile, encode_gsf, read_any, read_bytes};
use spmcal_tests::measured_file;
use std::ops::Range;

/// Crops `file` to `columns` × `rows`, round-trips every channel through `.gsf`, and checks
/// each against the whole file at nominal sensitivity `k` nm/count.
fn check(file: &SpmFile, k: f64, columns: Range<usize>, rows: Range<usize>) {
    let part = crop_file(file, columns.clone(), rows.clone()).unwrap();
    assert_eq!(part.channels.len(), file.channels.len());
    assert!(part.metadata.iter().any(|(key, _)| key == KEY_CROP));
    let extra: Vec<(&str, &str)> = part
        .metadata
        .iter()
        .map(|(a, b)| (a.as_str(), b.as_str()))
        .collect();
    for (whole, cut) in file.channels.iter().zip(&part.channels) {
        let what = format!("{} {}", whole.name(), whole.direction().as_str());
        let bytes = encode_gsf(cut, &extra).unwrap();
        let back = read_bytes(&bytes, std::path::Path::new("part.gsf")).unwrap();
        let r_whole = FileRaster::of(file, whole, Some(k), None).unwrap();
        let r_part = FileRaster::of(&back, &back.channels[0], Some(k), None).unwrap();
        assert_eq!(r_part.path, r_whole.path, "{what}: path");
        assert_eq!((r_part.columns, r_part.rows), (columns.len(), rows.len()));
        let step = r_whole.step_x_counts;
        for (i, j) in [
            (0, 0),
            (columns.len() - 1, 0),
            (0, rows.len() - 1),
            (columns.len() - 1, rows.len() - 1),
            (columns.len() / 3, rows.len() / 2),
        ] {
            let a = r_part.pixel_counts(i as f64, j as f64);
            let b = r_whole.pixel_counts((columns.start + i) as f64, (rows.start + j) as f64);
            let d = a.distance(b).value();
            assert!(
                d < 1e-6 * step.max(1.0),
                "{what}: part pixel ({i}, {j}) at ({}, {}) counts, the whole file's at ({}, {})",
                a.x.value(),
                a.y.value(),
                b.x.value(),
                b.y.value()
            );
        }
        if let (Some(t_whole), Some(t_part)) = (r_whole.line_time_s, r_part.line_time_s) {
            let want = t_whole * columns.len() as f64 / whole.nx() as f64;
            assert!((t_part - want).abs() < 1e-12 * want, "{what}: line time");
        }
        // Values (float32 in .gsf) and times (in memory: .gsf keeps only the line time).
        for (i, j) in [(0, 0), (columns.len() - 1, rows.len() - 1), (5, 7)] {
            let (a, b) = (
                back.channels[0].get(j, i).unwrap(),
                whole.get(rows.start + j, columns.start + i).unwrap(),
            );
            assert!(
                (a.is_nan() && b.is_nan()) || (a - b).abs() <= 1e-6 * b.abs(),
                "{what}: value at ({i}, {j})"
            );
        }
        if whole.timing().is_some() {
            for acq in [(0, 0), (rows.len() - 1, columns.len() - 1), (3, 2)] {
                let (row, col) = cut.display_index(acq.0, acq.1);
                let (whole_acq_row, whole_acq_col) =
                    acquisition_index(whole, rows.start + row, columns.start + col);
                let a = cut.pixel_time_s(acq.0, acq.1).unwrap();
                let b = whole.pixel_time_s(whole_acq_row, whole_acq_col).unwrap();
                assert!((a - b).abs() < 1e-9, "{what}: time of {acq:?}: {a} vs {b}");
            }
        }
    }
}

/// The acquisition `(line, pixel)` of display `(row, col)` (the inverse of
/// `Channel::display_index`, found by search: the channel's own mapping is the truth).
fn acquisition_index(c: &spm_formats::Channel, row: usize, col: usize) -> (usize, usize) {
    let line = (0..c.ny())
        .find(|&l| c.display_index(l, 0).0 == row)
        .unwrap();
    let pixel = (0..c.nx())
        .find(|&p| c.display_index(line, p).1 == col)
        .unwrap();
    (line, pixel)
}

/// The `.sm4`: 10° counter-clockwise, offset (−12.8, 16.3) nm, forward and backward halves.
#[test]
fn a_part_of_the_sm4_keeps_its_turned_and_offset_raster() {
    let file = read_any(measured_file(
        "graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4",
    ))
    .unwrap();
    check(&file, 0.001, 40..200, 17..131);
}

/// An `.sxm` scanned down, with backward halves, moved to (100, −40) nm and turned 30°
/// (clockwise in Nanonis's convention).
#[test]
fn a_part_of_a_turned_sxm_keeps_its_raster_and_times() {
    let file = super::real_files::patched_sxm(
        "SCAN_OFFSET",
        "             0.000000E+0         0.000000E+0",
        "             1.000000E-7        -4.000000E-8",
    );
    check(&file, 0.02, 128..256, 0..256);
    check(&file, 0.02, 10..90, 100..250);
    let file = super::real_files::patched_sxm(
        "SCAN_ANGLE",
        "            0.000E+0",
        "            3.000E+1",
    );
    check(&file, 0.02, 10..90, 100..250);
}

/// The ISO 28600 terrace: the left and the right half.
#[test]
fn the_halves_of_the_iso28600_terrace_tile_it() {
    let file = read_any(measured_file("hopg-terrace-iso28600/graphiteterrace.spm")).unwrap();
    check(&file, 0.01, 0..256, 0..512);
    check(&file, 0.01, 256..512, 0..512);
}

/// A part that leaves the image or is empty is refused, naming the option.
#[test]
fn a_part_outside_the_image_is_refused() {
    let file = read_any(measured_file("hopg-terrace-iso28600/graphiteterrace.spm")).unwrap();
    for (columns, rows, option) in [
        (0..513, 0..10, "--columns"),
        (5..5, 0..10, "--columns"),
        (0..10, 600..700, "--rows"),
    ] {
        let e = crop_file(&file, columns, rows).unwrap_err().to_string();
        assert!(e.starts_with(option), "{e}");
    }
}
