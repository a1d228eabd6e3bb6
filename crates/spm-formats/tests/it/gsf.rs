//! `.gsf` written by spmcal follows the Gwyddion spec and reads back identically.

#![allow(clippy::unwrap_used)]

use std::path::Path;

use spm_formats::{
    Channel, Direction, ErrorKind, Format, encode_gsf, read_any, read_bytes, write_gsf,
};
use spmcal_tests::measured_file;

fn si7x7_051() -> spm_formats::SpmFile {
    read_any(measured_file("si7x7-nanonis/Si_7x7_051.sxm")).unwrap()
}

/// Splits an encoded GSF into (header text after the magic line, padding length, data bytes).
fn split(bytes: &[u8]) -> (String, usize, &[u8]) {
    let nul = bytes.iter().position(|&b| b == 0).unwrap();
    // The padding brings the header to the next multiple of 4 (data may start with zeros).
    let data_start = (nul / 4 + 1) * 4;
    assert!(bytes[nul..data_start].iter().all(|&b| b == 0));
    let header = String::from_utf8(bytes[..nul].to_vec()).unwrap();
    (header, data_start - nul, &bytes[data_start..])
}

#[test]
fn encoded_gsf_follows_the_spec() {
    let f = si7x7_051();
    let z = f.channel("Z", Direction::Forward).unwrap();
    let bytes = encode_gsf(z, &[("Source", "Si_7x7_051.sxm")]).unwrap();
    assert!(bytes.starts_with(b"Gwyddion Simple Field 1.0\n"));
    let (header, pad, data) = split(&bytes);
    let lines: Vec<&str> = header.lines().collect();
    assert_eq!(lines[0], "Gwyddion Simple Field 1.0");
    let value = |key: &str| {
        lines.iter().find_map(|l| {
            let (k, v) = l.split_once('=')?;
            (k.trim() == key).then(|| v.trim().to_string())
        })
    };
    assert_eq!(value("XRes").as_deref(), Some("256"));
    assert_eq!(value("YRes").as_deref(), Some("256"));
    let x_real: f64 = value("XReal").unwrap().parse().unwrap();
    let y_real: f64 = value("YReal").unwrap().parse().unwrap();
    assert!((x_real - 2e-8).abs() < 1e-20 && (y_real - 2e-8).abs() < 1e-20);
    assert_eq!(value("XYUnits").as_deref(), Some("m"));
    assert_eq!(value("ZUnits").as_deref(), Some("m"));
    assert_eq!(value("Title").as_deref(), Some("Z"));
    assert_eq!(value("Source").as_deref(), Some("Si_7x7_051.sxm"));
    // One to four NULs, data start at a multiple of 4.
    assert!((1..=4).contains(&pad), "padding {pad}");
    assert!((header.len() + pad).is_multiple_of(4));
    assert_eq!(data.len(), 256 * 256 * 4);
    // Little-endian float32, row 0 = top, same values as the channel.
    for (k, c) in data.chunks_exact(4).enumerate() {
        let v = f32::from_le_bytes(c.try_into().unwrap());
        assert_eq!(f64::from(v), z.data()[k]);
    }
}

#[test]
fn gsf_reads_back_identically() {
    let f = si7x7_051();
    let dir = std::env::temp_dir().join(format!("spm-formats-gsf-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for ch in &f.channels {
        let path = dir.join(format!("{}-{}.gsf", ch.name(), ch.direction()));
        write_gsf(&path, ch, &[]).unwrap();
        let back = read_any(&path).unwrap();
        assert_eq!(back.format, Format::Gsf);
        assert_eq!(back.channels.len(), 1);
        let b = &back.channels[0];
        assert_eq!(
            (b.name(), b.direction(), b.unit()),
            (ch.name(), ch.direction(), ch.unit())
        );
        assert_eq!((b.nx(), b.ny()), (ch.nx(), ch.ny()));
        assert!((b.size_x_nm().unwrap() - 20.0).abs() < 1e-9);
        assert!((b.size_y_nm().unwrap() - 20.0).abs() < 1e-9);
        assert!((b.center_x_nm().unwrap() - ch.center_x_nm().unwrap()).abs() < 1e-9);
        // Nanonis data are float32 already: the values come back bit for bit.
        assert_eq!(b.data(), ch.data());
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn header_padding_is_never_empty() {
    // Header lengths of every residue mod 4 get 1–4 NULs and read back.
    for title_len in 0..8 {
        let ch = Channel::new(
            "t".repeat(title_len + 1),
            Direction::Forward,
            "m",
            3,
            2,
            vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
        )
        .unwrap()
        .with_size_nm(3.0, 2.0);
        let bytes = encode_gsf(&ch, &[]).unwrap();
        let nul = bytes.iter().position(|&b| b == 0).unwrap();
        let data_start = bytes.len() - 6 * 4;
        assert!(data_start > nul && data_start - nul <= 4 && data_start.is_multiple_of(4));
        assert!(bytes[nul..data_start].iter().all(|&b| b == 0));
        let back = read_bytes(&bytes, Path::new("mem.gsf")).unwrap();
        assert_eq!(back.channels[0].data(), ch.data());
        assert_eq!(back.channels[0].name(), ch.name());
    }
}

#[test]
fn nan_marks_pixels_without_data_both_ways() {
    let ch = Channel::new("z", Direction::Forward, "m", 2, 1, vec![0.5, f64::NAN])
        .unwrap()
        .with_size_nm(1.0, 1.0);
    let bytes = encode_gsf(&ch, &[]).unwrap();
    let back = read_bytes(&bytes, Path::new("mem.gsf")).unwrap();
    assert_eq!(back.channels[0].data()[0], 0.5);
    assert!(back.channels[0].data()[1].is_nan());
    assert_eq!(back.channels[0].nan_count(), 1);
}

#[test]
fn writer_rejects_what_gsf_cannot_hold() {
    let ch = Channel::new("z", Direction::Forward, "m", 2, 1, vec![0.0, f64::INFINITY])
        .unwrap()
        .with_size_nm(1.0, 1.0);
    assert_eq!(
        encode_gsf(&ch, &[]).unwrap_err().kind(),
        ErrorKind::InvalidInput
    );
    let ch = Channel::new("z", Direction::Forward, "m", 2, 1, vec![0.0, 1e300])
        .unwrap()
        .with_size_nm(1.0, 1.0);
    assert_eq!(
        encode_gsf(&ch, &[]).unwrap_err().kind(),
        ErrorKind::InvalidInput
    );
    let no_size = Channel::new("z", Direction::Forward, "m", 2, 1, vec![0.0, 1.0]).unwrap();
    assert_eq!(
        encode_gsf(&no_size, &[]).unwrap_err().kind(),
        ErrorKind::InvalidInput
    );
    let ok = Channel::new("z", Direction::Forward, "m", 2, 1, vec![0.0, 1.0])
        .unwrap()
        .with_size_nm(1.0, 1.0);
    assert_eq!(
        encode_gsf(&ok, &[("bad key", "v")]).unwrap_err().kind(),
        ErrorKind::InvalidInput
    );
    assert_eq!(
        Channel::new("z", Direction::Forward, "m", 2, 2, vec![0.0])
            .unwrap_err()
            .kind(),
        ErrorKind::InvalidInput
    );
}

#[test]
fn gsf_defaults_follow_the_spec() {
    // Only XRes/YRes: XReal = YReal = 1 (metres), title defaults.
    let mut bytes = b"Gwyddion Simple Field 1.0\nXRes = 2\nYRes = 1\n".to_vec();
    let pad = 4 - bytes.len() % 4;
    bytes.extend(std::iter::repeat_n(0, pad));
    bytes.extend_from_slice(&1.5f32.to_le_bytes());
    bytes.extend_from_slice(&(-2.0f32).to_le_bytes());
    let f = read_bytes(&bytes, Path::new("defaults.gsf")).unwrap();
    let c = &f.channels[0];
    assert_eq!(c.data(), &[1.5, -2.0]);
    assert_eq!(c.size_x_nm(), Some(1e9));
    assert_eq!(f.header_value("XRes"), Some("2"));
}

/// Gwyddion itself (Debian's `gwyddion`; `.ci/run` installs it) renders a file we wrote: the
/// thumbnail of channel `channel` as rows of luminance, with its width and height.
fn gwyddion_renders(file: &Path, channel: usize) -> (usize, usize, Vec<f64>) {
    let png_path = file.with_extension(format!("{channel}.png"));
    let output = std::process::Command::new("gwyddion-thumbnailer")
        .args(["-c", &channel.to_string(), "gnome2", "128"])
        .arg(file)
        .arg(&png_path)
        .output()
        .unwrap_or_else(|e| {
            panic!(
                "gwyddion-thumbnailer could not be run ({e}): install Debian's `gwyddion` \
                 package (apt-get install -y gwyddion); .ci/run does"
            )
        });
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success() && !stderr.contains("CRITICAL"),
        "Gwyddion could not open {} cleanly: {stderr}",
        file.display()
    );
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(&png_path).unwrap(),
    ));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    let channels = info.color_type.samples();
    let (w, h) = (info.width as usize, info.height as usize);
    let luma = (0..w * h)
        .map(|i| {
            let p = &buf[i * channels..];
            if channels >= 3 {
                0.299 * f64::from(p[0]) + 0.587 * f64::from(p[1]) + 0.114 * f64::from(p[2])
            } else {
                f64::from(p[0])
            }
        })
        .collect();
    (w, h, luma)
}

/// Mean luminance over a fraction box (x0, x1, y0, y1) of the picture (y from the top).
fn mean_box(w: usize, h: usize, luma: &[f64], b: (f64, f64, f64, f64)) -> f64 {
    let (x0, x1) = ((b.0 * w as f64) as usize, (b.1 * w as f64) as usize);
    let (y0, y1) = ((b.2 * h as f64) as usize, (b.3 * h as f64) as usize);
    let mut sum = 0.0;
    let mut n = 0.0;
    for y in y0..y1 {
        for x in x0..x1 {
            sum += luma[y * w + x];
            n += 1.0;
        }
    }
    sum / n
}

/// A forward channel rising to the right and a backward one rising to the top, each with a
/// corner without data (NaN): Gwyddion must open the `.gwy` (both channels) and the `.gsf`,
/// and draw them the right way round.
#[test]
fn gwyddion_reads_our_gwy_and_gsf_with_nan() {
    let dir = std::env::temp_dir().join(format!("spm-formats-gwy-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (nx, ny) = (64, 48);
    let ramp = |f: &dyn Fn(usize, usize) -> f64| -> Vec<f64> {
        (0..nx * ny)
            .map(|i| {
                let (row, col) = (i / nx, i % nx);
                let hole =
                    (row < 8 && col < 8) || ((20..24).contains(&row) && (30..34).contains(&col));
                if hole { f64::NAN } else { f(row, col) }
            })
            .collect()
    };
    let right = Channel::new(
        "Z",
        Direction::Forward,
        "m",
        nx,
        ny,
        ramp(&|_, c| c as f64 * 1e-11),
    )
    .unwrap()
    .with_size_nm(6.4, 4.8)
    .with_center_nm(10.0, -5.0);
    let up = Channel::new(
        "Z",
        Direction::Backward,
        "m",
        nx,
        ny,
        ramp(&|r, _| (ny - r) as f64 * 1e-11),
    )
    .unwrap()
    .with_size_nm(6.4, 4.8);
    let gwy = dir.join("two.gwy");
    let meta = vec![("spmcal_corrected".to_owned(), "yes".to_owned())];
    spm_formats::write_gwy(&gwy, &[right.clone(), up], &meta).unwrap();
    let (w, h, luma) = gwyddion_renders(&gwy, 0);
    assert!(w > h, "the 64 × 48 channel drawn {w} × {h}");
    let (left, rightside) = (
        mean_box(w, h, &luma, (0.0, 0.3, 0.5, 1.0)),
        mean_box(w, h, &luma, (0.7, 1.0, 0.5, 1.0)),
    );
    assert!(
        rightside > left + 60.0,
        "channel 0: left {left}, right {rightside}"
    );
    let (w, h, luma) = gwyddion_renders(&gwy, 1);
    let (top, bottom) = (
        mean_box(w, h, &luma, (0.3, 1.0, 0.0, 0.3)),
        mean_box(w, h, &luma, (0.3, 1.0, 0.7, 1.0)),
    );
    assert!(top > bottom + 60.0, "channel 1: top {top}, bottom {bottom}");
    let gsf = dir.join("right.gsf");
    write_gsf(&gsf, &right, &[]).unwrap();
    let (w, h, luma) = gwyddion_renders(&gsf, 0);
    let (left, rightside) = (
        mean_box(w, h, &luma, (0.0, 0.3, 0.5, 1.0)),
        mean_box(w, h, &luma, (0.7, 1.0, 0.5, 1.0)),
    );
    assert!(
        rightside > left + 60.0,
        "gsf: left {left}, right {rightside}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Our `.sxm` writer as Gwyddion reads it: a frame whose sample rises to the top, written in
/// acquisition order for a slow axis stepping up and for one stepping down (the first line
/// acquired is then the top one), both halves (backward lines stored right to left). Gwyddion
/// must draw every channel with the top bright, and the extra header tags must come back
/// through our reader.
#[test]
fn gwyddion_reads_our_sxm_the_right_way_round() {
    use spm_formats::{DateTime, ScanDir, SxmChannel, SxmScan, encode_sxm, read_any};
    let dir = std::env::temp_dir().join(format!("spm-formats-sxm-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (nx, ny) = (64, 48);
    // Height of the sample at display row r (0 = top) and column c: bright at the top, a
    // small ramp to the right.
    let z = |r: usize, c: usize| ((ny - r) as f64 * 1e-11) + c as f64 * 1e-13;
    for scan_dir in [ScanDir::Up, ScanDir::Down] {
        let acquisition = |plus_x: bool| -> Vec<f64> {
            let mut out = Vec::with_capacity(nx * ny);
            for line in 0..ny {
                // Display row of the line acquired `line`-th.
                let r = match scan_dir {
                    ScanDir::Up => ny - 1 - line,
                    ScanDir::Down => line,
                };
                for k in 0..nx {
                    out.push(z(r, if plus_x { k } else { nx - 1 - k }));
                }
            }
            out
        };
        let scan = SxmScan {
            pixels: [nx, ny],
            size_nm: [6.4, 4.8],
            centre_nm: [10.0, -5.0],
            angle_deg: 0.0,
            line_time_s: [0.1, 0.1],
            scan_dir,
            recorded: DateTime::new(2026, 11, 26, 12, 0, 0).unwrap(),
            bias_v: 0.5,
            comment: "orientation test".to_owned(),
            channels: vec![SxmChannel {
                name: "Z".to_owned(),
                unit: "m".to_owned(),
                forward: acquisition(true),
                backward: Some(acquisition(false)),
            }],
            extra_header: vec![("spmcal_scan_path".to_owned(), "counter".to_owned())],
        };
        let path = dir.join(format!("{}.sxm", scan_dir.as_str()));
        std::fs::write(&path, encode_sxm(&scan, &path).unwrap()).unwrap();
        for channel in [0, 1] {
            let (w, h, luma) = gwyddion_renders(&path, channel);
            assert!(w > h, "{path:?} channel {channel}: drawn {w} × {h}");
            let (top, bottom) = (
                mean_box(w, h, &luma, (0.0, 1.0, 0.0, 0.3)),
                mean_box(w, h, &luma, (0.0, 1.0, 0.7, 1.0)),
            );
            assert!(
                top > bottom + 60.0,
                "{path:?} channel {channel}: top {top}, bottom {bottom}"
            );
        }
        // Our reader: display order (top row first), both halves equal to the sample.
        let file = read_any(&path).unwrap();
        assert_eq!(file.channels.len(), 2);
        assert_eq!(file.scan_dir, Some(scan_dir));
        assert_eq!(file.header_value("spmcal_scan_path"), Some("counter"));
        for ch in &file.channels {
            for (i, v) in ch.data().iter().enumerate() {
                let want = z(i / nx, i % nx);
                assert!(
                    (v - want).abs() < 1e-6 * want.abs(),
                    "{path:?} pixel {i}: {v} vs {want}"
                );
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
