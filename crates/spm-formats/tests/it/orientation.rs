//! Display orientation versus acquisition order, for every orientation flag the readers honour.

#![allow(clippy::unwrap_used)]

use std::path::Path;

use spm_formats::{Direction, ScanDir, read_bytes};
use spmcal_tests::measured_file;

fn replace(bytes: &[u8], from: &[u8], to: &[u8]) -> Vec<u8> {
    let pos = bytes.windows(from.len()).position(|w| w == from).unwrap();
    let mut out = bytes[..pos].to_vec();
    out.extend_from_slice(to);
    out.extend_from_slice(&bytes[pos + from.len()..]);
    out
}

/// The same stored data read with `SCAN_DIR up` instead of `down`: the display flips
/// vertically, the acquisition order (= stored order) does not change.
#[test]
fn sxm_scan_up_flips_the_display_not_the_acquisition_order() {
    let b = std::fs::read(measured_file("si7x7-nanonis/Si_7x7_051.sxm")).unwrap();
    let down = read_bytes(&b, Path::new("down.sxm")).unwrap();
    let up_bytes = replace(&b, b":SCAN_DIR:\ndown", b":SCAN_DIR:\nup\n\n");
    let up = read_bytes(&up_bytes, Path::new("up.sxm")).unwrap();
    assert_eq!(up.scan_dir, Some(ScanDir::Up));
    for (d, u) in down.channels.iter().zip(&up.channels) {
        assert_eq!(u.scan_dir(), Some(ScanDir::Up));
        assert_eq!(
            d.acquisition_image(),
            u.acquisition_image(),
            "{} {}",
            d.name(),
            d.direction()
        );
        for row in [0, 17, 255] {
            for col in [0, 100, 255] {
                assert_eq!(u.get(row, col), d.get(255 - row, col));
            }
        }
        // First acquired pixel of an upward backward line: bottom row, right edge.
        if u.direction() == Direction::Backward {
            assert_eq!(u.display_index(0, 0), (255, 255));
        } else {
            assert_eq!(u.display_index(0, 0), (255, 0));
        }
    }
}

/// Little-endian float data (`LSBFIRST`) decode to the same values.
#[test]
fn sxm_lsbfirst() {
    let b = std::fs::read(measured_file("si7x7-nanonis/Si_7x7_051.sxm")).unwrap();
    let be = read_bytes(&b, Path::new("be.sxm")).unwrap();
    let mut le = replace(&b, b"MSBFIRST", b"LSBFIRST");
    let start = 789;
    for c in le[start..].chunks_exact_mut(4) {
        c.reverse();
    }
    let le = read_bytes(&le, Path::new("le.sxm")).unwrap();
    assert_eq!(be.channels, le.channels);
}

fn iso_text(
    mode: &str,
    fast: &str,
    slow: &str,
    channels: &[(&str, &str)],
    rows: &[&str],
) -> Vec<u8> {
    let mut lines = vec![String::new(); 128];
    let set = |lines: &mut Vec<String>, n: usize, v: &str| lines[n - 1] = v.to_string();
    set(&mut lines, 1, "ISO/TC 201 SPM data transfer format");
    set(&mut lines, 2, "general information");
    set(&mut lines, 8, mode);
    for n in [9, 10, 11, 12, 13, 14, 15] {
        set(&mut lines, n, "-1");
    }
    set(&mut lines, 9, "2021");
    set(&mut lines, 10, "3");
    set(&mut lines, 11, "4");
    set(&mut lines, 12, "5");
    set(&mut lines, 13, "6");
    set(&mut lines, 14, "7");
    set(&mut lines, 16, "scan information");
    set(&mut lines, 17, "REGULAR MAPPING");
    set(&mut lines, 20, "X");
    set(&mut lines, 21, fast);
    set(&mut lines, 22, "Y");
    set(&mut lines, 23, slow);
    set(&mut lines, 24, "3");
    set(&mut lines, 25, "2");
    set(&mut lines, 26, "nm");
    set(&mut lines, 27, "nm");
    set(&mut lines, 28, "3.0");
    set(&mut lines, 29, "2.0");
    set(&mut lines, 37, "Hz");
    set(&mut lines, 38, "2.0");
    set(&mut lines, 69, channels[0].0);
    set(&mut lines, 70, channels[0].1);
    set(&mut lines, 94, &channels.len().to_string());
    for (k, (name, unit)) in channels.iter().enumerate() {
        set(&mut lines, 95 + 3 * k, name);
        set(&mut lines, 96 + 3 * k, unit);
    }
    set(&mut lines, 128, "end of header");
    let mut text = lines.join("\n");
    text.push('\n');
    for r in rows {
        text.push_str(r);
        text.push('\n');
    }
    text.push_str("end of experiment\n");
    text.into_bytes()
}

#[test]
fn iso_single_channel_units_and_date() {
    let rows = ["1", "2", "3", "4", "5", "6"];
    let b = iso_text(
        "MAP_SC",
        "left to right",
        "top to bottom",
        &[("Z", "nm")],
        &rows,
    );
    let f = read_bytes(&b, Path::new("sc.spm")).unwrap();
    let z = &f.channels[0];
    assert_eq!(z.unit(), "m");
    assert_eq!(z.data(), &[1e-9, 2e-9, 3e-9, 4e-9, 5e-9, 6e-9]);
    assert_eq!((z.size_x_nm(), z.size_y_nm()), (Some(3.0), Some(2.0)));
    assert_eq!(f.recorded.unwrap().to_string(), "2021-03-04T05:06:07");
    assert_eq!(f.line_time_s, Some(0.5));
}

/// Two channels, stored right to left and bottom to top.
#[test]
fn iso_multi_channel_reversed_axes() {
    // Stored points (fast x right→left, slow y bottom→top): value = 10·stored_row + stored_col.
    let rows = [
        "0, 100", "1, 101", "2, 102", "10, 110", "11, 111", "12, 112",
    ];
    let b = iso_text(
        "MAP_MC",
        "right to left",
        "bottom to top",
        &[("Z", "m"), ("I", "A")],
        &rows,
    );
    let f = read_bytes(&b, Path::new("mc.spm")).unwrap();
    assert_eq!(f.channels.len(), 2);
    assert_eq!(f.scan_dir, Some(ScanDir::Up));
    let z = &f.channels[0];
    let i = &f.channels[1];
    assert_eq!(
        (z.name(), z.unit(), i.name(), i.unit()),
        ("Z", "m", "I", "A")
    );
    assert_eq!(z.direction(), Direction::Backward);
    // Display: top row = last stored row, left column = last stored column.
    assert_eq!(z.data(), &[12.0, 11.0, 10.0, 2.0, 1.0, 0.0]);
    assert_eq!(i.get(1, 2), Some(100.0));
    // Acquisition order is the stored order.
    assert_eq!(
        z.acquisition_image().data,
        vec![0.0, 1.0, 2.0, 10.0, 11.0, 12.0]
    );
}

/// A positive y scale in an RHK page means the stored lines run bottom to top: the display
/// flips and the acquisition order stays the stored order.
#[test]
fn sm4_positive_y_scale_flips_the_display() {
    let b = std::fs::read(measured_file(
        "graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4",
    ))
    .unwrap();
    let orig = read_bytes(&b, Path::new("orig.sm4")).unwrap();
    // Page 5 (Topography, SCAN_RIGHT) header at 1655786; y_scale at +60.
    let mut flipped = b.clone();
    let o = 1_655_786 + 60;
    let y = f32::from_le_bytes(flipped[o..o + 4].try_into().unwrap());
    flipped[o..o + 4].copy_from_slice(&(-y).to_le_bytes());
    let f = read_bytes(&flipped, Path::new("flipped.sm4")).unwrap();
    let a = orig.channel("Topography", Direction::Forward).unwrap();
    let c = f.channel("Topography", Direction::Forward).unwrap();
    assert_eq!(c.scan_dir(), Some(ScanDir::Up));
    assert_eq!(a.scan_dir(), None);
    assert_eq!(c.acquisition_image(), a.acquisition_image());
    assert_eq!(c.get(0, 7), a.get(255, 7));
    assert_eq!(c.size_y_nm(), a.size_y_nm());
}
