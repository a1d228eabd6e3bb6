//! The `.gwy` reader: our own files come back as written, Gwyddion's own files of the real
//! measured images read as the originals do, and forged files are typed errors.

#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};

use spm_formats::{Channel, Direction, ErrorKind, Format, read_any, read_bytes, write_gwy};
use spmcal_tests::measured_file;

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("spm-formats-gwy-read-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// Two halves of one quantity and a second quantity, with holes (NaN) in one half and the
/// scan angle in the metadata: every value, hole, size, centre, name, direction and
/// metadata entry comes back.
#[test]
fn our_gwy_comes_back_as_written() {
    let (nx, ny) = (24, 16);
    let values = |seed: f64| -> Vec<f64> {
        (0..nx * ny)
            .map(|i| seed * 1e-10 * ((i % nx) as f64 - 0.37 * (i / nx) as f64).sin())
            .collect()
    };
    let mut holed = values(2.0);
    for i in [0, 1, nx, 5 * nx + 7, nx * ny - 1] {
        holed[i] = f64::NAN;
    }
    let channels = vec![
        Channel::new("Z", Direction::Forward, "m", nx, ny, values(1.0))
            .unwrap()
            .with_size_nm(12.0, 8.0)
            .with_center_nm(-3.5, 250.0),
        Channel::new("Z", Direction::Backward, "m", nx, ny, holed.clone())
            .unwrap()
            .with_size_nm(12.0, 8.0)
            .with_center_nm(-3.5, 250.0),
        Channel::new("Current", Direction::Forward, "A", nx, ny, values(0.3))
            .unwrap()
            .with_size_nm(12.0, 8.0)
            .with_center_nm(-3.5, 250.0),
    ];
    let meta = vec![
        ("spmcal_scan_angle_ccw_deg".to_owned(), "-12.5".to_owned()),
        ("Bias".to_owned(), "-0.4 V".to_owned()),
    ];
    let path = scratch("ours.gwy");
    write_gwy(&path, &channels, &meta).unwrap();
    let back = read_any(&path).unwrap();
    assert_eq!(back.format, Format::Gwy);
    assert_eq!(back.header, meta);
    assert_eq!(back.channels.len(), 3);
    for (written, read) in channels.iter().zip(&back.channels) {
        assert_eq!(
            (read.name(), read.direction(), read.unit()),
            (written.name(), written.direction(), written.unit())
        );
        assert_eq!((read.nx(), read.ny()), (nx, ny));
        for (a, b) in written.data().iter().zip(read.data()) {
            assert!(a == b || (a.is_nan() && b.is_nan()), "{a} came back as {b}");
        }
        let close = |a: Option<f64>, b: f64| (a.unwrap() - b).abs() < 1e-9 * b.abs().max(1.0);
        assert!(close(read.size_x_nm(), 12.0) && close(read.size_y_nm(), 8.0));
        assert!(close(read.center_x_nm(), -3.5) && close(read.center_y_nm(), 250.0));
        assert_eq!(read.angle_deg(), Some(-12.5));
    }
    assert_eq!(back.channels[1].nan_count(), 5);
    let _ = std::fs::remove_file(&path);
}

/// Gwyddion itself (`gwyddion --convert-to-gwy`; Debian's `gwyddion`, which `.ci/run`
/// installs) writes its own `.gwy` of a real file; read back, every channel is the one our
/// reader of the original gives: name, direction, unit, grid, size and every value.
fn gwyddion_converts(original: &Path, out: &Path) {
    let output = std::process::Command::new("gwyddion")
        .arg(format!("--convert-to-gwy={}", out.display()))
        .arg(original)
        .output()
        .unwrap_or_else(|e| {
            panic!(
                "gwyddion could not be run ({e}): install Debian's `gwyddion` package \
                 (apt-get install -y gwyddion); .ci/run does"
            )
        });
    assert!(
        output.status.success() && out.exists(),
        "gwyddion --convert-to-gwy {}: {}",
        original.display(),
        String::from_utf8_lossy(&output.stderr)
    );
}

#[test]
fn gwyddion_s_own_gwy_of_the_real_files_reads_as_the_originals() {
    for (relative, keeps_offset) in [
        ("si7x7-nanonis/Si_7x7_028.sxm", true),
        (
            "graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4",
            false,
        ),
    ] {
        let original_path = measured_file(relative);
        let original = read_any(&original_path).unwrap();
        let out = scratch(&format!(
            "{}.gwy",
            original_path.file_stem().unwrap().to_string_lossy()
        ));
        gwyddion_converts(&original_path, &out);
        let theirs = read_any(&out).unwrap();
        assert_eq!(theirs.format, Format::Gwy);
        assert_eq!(
            theirs.channels.len(),
            original.channels.len(),
            "{relative}: {:?}",
            theirs
                .channels
                .iter()
                .map(|c| (c.name(), c.direction()))
                .collect::<Vec<_>>()
        );
        for ours in &original.channels {
            let read = theirs
                .channel(ours.name(), ours.direction())
                .unwrap_or_else(|| {
                    panic!(
                        "{relative}: no {} {:?} in Gwyddion's file",
                        ours.name(),
                        ours.direction()
                    )
                });
            assert_eq!(
                (read.nx(), read.ny(), read.unit()),
                (ours.nx(), ours.ny(), ours.unit())
            );
            assert_eq!(
                read.data(),
                ours.data(),
                "{relative}: {} {:?}",
                ours.name(),
                ours.direction()
            );
            let rel = |a: Option<f64>, b: Option<f64>| (a.unwrap() / b.unwrap() - 1.0).abs() < 1e-6;
            assert!(
                rel(read.size_x_nm(), ours.size_x_nm()) && rel(read.size_y_nm(), ours.size_y_nm())
            );
            if keeps_offset {
                // The Nanonis frame is centred at (0, 0).
                assert!(read.center_x_nm().unwrap().abs() < 1e-9);
                assert!(read.center_y_nm().unwrap().abs() < 1e-9);
            }
        }
        let _ = std::fs::remove_file(&out);
    }
}

/// A minimal serialiser for forged files (the format of the module docs).
fn object(type_name: &str, components: &[Vec<u8>]) -> Vec<u8> {
    let body: Vec<u8> = components.concat();
    let mut out = type_name.as_bytes().to_vec();
    out.push(0);
    out.extend_from_slice(&(body.len() as u32).to_le_bytes());
    out.extend_from_slice(&body);
    out
}

fn component(name: &str, kind: u8, value: &[u8]) -> Vec<u8> {
    let mut out = name.as_bytes().to_vec();
    out.push(0);
    out.push(kind);
    out.extend_from_slice(value);
    out
}

fn int(name: &str, v: i32) -> Vec<u8> {
    component(name, b'i', &v.to_le_bytes())
}

fn double(name: &str, v: f64) -> Vec<u8> {
    component(name, b'd', &v.to_le_bytes())
}

fn doubles(name: &str, count: u32, values: &[f64]) -> Vec<u8> {
    let mut v = count.to_le_bytes().to_vec();
    for x in values {
        v.extend_from_slice(&x.to_le_bytes());
    }
    component(name, b'D', &v)
}

fn field(xres: i32, yres: i32, data: Vec<u8>) -> Vec<u8> {
    object(
        "GwyDataField",
        &[
            int("xres", xres),
            int("yres", yres),
            double("xreal", 1e-9),
            double("yreal", 1e-9),
            data,
        ],
    )
}

fn file(components: &[Vec<u8>]) -> Vec<u8> {
    let mut out = b"GWYP".to_vec();
    out.extend(object("GwyContainer", components));
    out
}

#[track_caller]
fn check(bytes: &[u8], kind: ErrorKind, mentions: &str) {
    let e = read_bytes(bytes, Path::new("forged.gwy")).unwrap_err();
    assert_eq!(e.kind(), kind, "{e}");
    let text = e.to_string();
    assert!(
        text.contains("forged.gwy") && text.contains(mentions),
        "{text}"
    );
}

#[test]
fn a_forged_gwy_is_a_typed_error_naming_the_field() {
    let good = file(&[component(
        "/0/data",
        b'o',
        &field(2, 1, doubles("data", 2, &[1.0, 2.0])),
    )]);
    let f = read_bytes(&good, Path::new("forged.gwy")).unwrap();
    assert_eq!(
        (f.channels[0].name(), f.channels[0].data()),
        ("Data", &[1.0, 2.0][..])
    );
    // An array claiming more items than the file holds: refused before allocating.
    check(
        &file(&[component(
            "/0/data",
            b'o',
            &field(2, 1, doubles("data", u32::MAX, &[1.0])),
        )]),
        ErrorKind::Truncated,
        "GwyDataField.data",
    );
    // Fewer values than pixels.
    check(
        &file(&[component(
            "/0/data",
            b'o',
            &field(3, 1, doubles("data", 2, &[1.0, 2.0])),
        )]),
        ErrorKind::Truncated,
        "/0/data.xres/yres",
    );
    check(
        &file(&[component(
            "/0/data",
            b'o',
            &field(2, 1, doubles("data", 2, &[1.0, f64::NAN])),
        )]),
        ErrorKind::InvalidField,
        "/0/data.data",
    );
    check(
        &file(&[component(
            "/0/data",
            b'o',
            &field(-2, 1, doubles("data", 2, &[1.0, 2.0])),
        )]),
        ErrorKind::InvalidField,
        "/0/data.xres",
    );
    check(
        &file(&[component(
            "/0/data",
            b'o',
            &field(2, 1, component("data", b'x', &[0])),
        )]),
        ErrorKind::InvalidData,
        "unknown type 'x'",
    );
    check(
        &file(&[int("/0/visible", 1)]),
        ErrorKind::MissingField,
        "no image channel",
    );
    // A mask of another grid.
    check(
        &file(&[
            component(
                "/0/data",
                b'o',
                &field(2, 1, doubles("data", 2, &[1.0, 2.0])),
            ),
            component(
                "/0/mask",
                b'o',
                &field(1, 2, doubles("data", 2, &[0.0, 1.0])),
            ),
        ]),
        ErrorKind::InvalidField,
        "/0/mask",
    );
    // Objects nested beyond any real file.
    let mut nested = object("GwyContainer", &[]);
    for _ in 0..40 {
        nested = object("GwyContainer", &[component("x", b'o', &nested)]);
    }
    let mut deep = b"GWYP".to_vec();
    deep.extend(nested);
    check(&deep, ErrorKind::InvalidData, "nested deeper");
    // An object whose size runs past its container.
    let mut long = good.clone();
    let at = 4 + "GwyContainer".len() + 1 + 4 + "/0/data".len() + 2 + "GwyDataField".len() + 1;
    long[at..at + 4].copy_from_slice(&10_000u32.to_le_bytes());
    check(&long, ErrorKind::Truncated, "GwyDataField components");
    check(b"GWYQ....", ErrorKind::BadMagic, "GWYP");
}
