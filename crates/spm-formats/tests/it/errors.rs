//! Bad input gives a typed error naming the file, never a panic or a huge allocation.

#![allow(clippy::unwrap_used)]

use std::path::Path;

use spm_formats::{
    Channel, Direction, ErrorKind, Format, FormatError, encode_gsf, encode_raw_f64, read_any,
    read_as, read_bytes,
};
use spmcal_tests::measured_file;

fn bytes_of(rel: &str) -> Vec<u8> {
    std::fs::read(measured_file(rel)).unwrap()
}

fn err(bytes: &[u8], name: &str) -> FormatError {
    match read_bytes(bytes, Path::new(name)) {
        Ok(f) => panic!(
            "{name}: expected an error, read {} channels",
            f.channels.len()
        ),
        Err(e) => {
            let msg = e.to_string();
            assert!(msg.contains(name), "message does not name the file: {msg}");
            assert_eq!(e.path(), Path::new(name));
            e
        }
    }
}

fn replace(bytes: &[u8], from: &[u8], to: &[u8]) -> Vec<u8> {
    let pos = bytes.windows(from.len()).position(|w| w == from).unwrap();
    let mut out = bytes[..pos].to_vec();
    out.extend_from_slice(to);
    out.extend_from_slice(&bytes[pos + from.len()..]);
    out
}

const SXM: &str = "si7x7-nanonis/Si_7x7_051.sxm";
const SXM_DATA_OFFSET: usize = 789;

#[test]
fn sxm_truncated() {
    let b = bytes_of(SXM);
    let e = err(&b[..b.len() - 1000], "cut.sxm");
    assert_eq!(e.kind(), ErrorKind::Truncated, "{e}");
    let e = err(&b[..500], "header-cut.sxm");
    assert_eq!(e.kind(), ErrorKind::Truncated, "{e}");
    assert!(e.to_string().contains("SCANIT_END"), "{e}");
}

#[test]
fn sxm_wrong_magic() {
    let e = err(b"this is not a scan file at all", "junk.sxm");
    assert_eq!(e.kind(), ErrorKind::BadMagic);
    let e = read_as(b"GIF89a", Path::new("x"), Format::NanonisSxm).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::BadMagic);
}

#[test]
fn sxm_absurd_pixel_counts() {
    let b = bytes_of(SXM);
    let from = b"       256       256";
    for (claim, kind) in [
        (&b"1000000000 1"[..], ErrorKind::TooLarge),
        (b"31623 31623", ErrorKind::TooLarge), // 10^9 pixels
        (b"4096 4096", ErrorKind::Truncated),  // allowed size, but not in the file
        (b"-5 256", ErrorKind::InvalidField),
        (b"0 256", ErrorKind::InvalidField),
    ] {
        let e = err(&replace(&b, from, claim), "claims.sxm");
        assert_eq!(e.kind(), kind, "{}: {e}", String::from_utf8_lossy(claim));
    }
}

#[test]
fn sxm_nan_is_kept_and_reported_but_infinity_is_invalid() {
    let mut b = bytes_of(SXM);
    // First three values of the Z forward image (big-endian float32) become NaN.
    for k in 0..3 {
        let o = SXM_DATA_OFFSET + 4 * k;
        b[o..o + 4].copy_from_slice(&f32::NAN.to_be_bytes());
    }
    let f = read_bytes(&b, Path::new("nan.sxm")).unwrap();
    let z = f.channel("Z", Direction::Forward).unwrap();
    assert_eq!(z.nan_count(), 3);
    assert!(f.info().channels[0].nan_count == 3);
    assert_eq!(f.channel("Z", Direction::Backward).unwrap().nan_count(), 0);

    let o = SXM_DATA_OFFSET + 4 * 10;
    b[o..o + 4].copy_from_slice(&f32::INFINITY.to_be_bytes());
    let e = err(&b, "inf.sxm");
    assert_eq!(e.kind(), ErrorKind::InvalidData);
    assert!(matches!(e, FormatError::InvalidData { offset, .. } if offset == o as u64));
}

#[test]
fn sxm_non_utf8_header() {
    let b = bytes_of(SXM);
    let bad = replace(&b, b"C:\\Nanonis", b"C:\\Nan\xffnis");
    let e = err(&bad, "latin.sxm");
    assert_eq!(e.kind(), ErrorKind::Encoding, "{e}");
    assert!(matches!(e, FormatError::Encoding { offset, .. } if offset > 0));
}

#[test]
fn sxm_missing_and_bad_fields() {
    let b = bytes_of(SXM);
    let e = err(&replace(&b, b":DATA_INFO:", b":DATA_INFX:"), "noinfo.sxm");
    assert_eq!(e.kind(), ErrorKind::MissingField);
    assert!(e.to_string().contains("DATA_INFO"));
    let e = err(
        &replace(
            &b,
            b"2.000000E-8           2.000000E-8",
            b"2.000000E-8           twenty",
        ),
        "range.sxm",
    );
    assert_eq!(e.kind(), ErrorKind::InvalidField);
    assert!(e.to_string().contains("SCAN_RANGE"));
    let e = err(&replace(&b, b"\x1a\x04", b"\x1a\x05"), "mark.sxm");
    assert_eq!(e.kind(), ErrorKind::Truncated);
}

fn gsf_bytes(header: &str, values: &[f32]) -> Vec<u8> {
    let mut b = format!("Gwyddion Simple Field 1.0\n{header}").into_bytes();
    let pad = 4 - b.len() % 4;
    b.extend(std::iter::repeat_n(0, pad));
    for v in values {
        b.extend_from_slice(&v.to_le_bytes());
    }
    b
}

#[test]
fn gsf_bad_inputs() {
    let good = gsf_bytes("XRes = 2\nYRes = 2\n", &[1.0, 2.0, 3.0, 4.0]);
    assert!(read_bytes(&good, Path::new("ok.gsf")).is_ok());
    assert_eq!(
        err(&good[..good.len() - 1], "cut.gsf").kind(),
        ErrorKind::Truncated
    );
    assert_eq!(err(&good[..30], "nopad.gsf").kind(), ErrorKind::Truncated);
    assert_eq!(
        err(b"Gwyddion Simple Field 2.0\n\0\0", "v2.gsf").kind(),
        ErrorKind::BadMagic
    );
    let huge = gsf_bytes("XRes = 1000000000\nYRes = 1\n", &[1.0]);
    assert_eq!(err(&huge, "huge.gsf").kind(), ErrorKind::TooLarge);
    let huge = gsf_bytes("XRes = 31623\nYRes = 31623\n", &[1.0]);
    assert_eq!(err(&huge, "huge2.gsf").kind(), ErrorKind::TooLarge);
    // NaN is a pixel without data; an infinite value is refused.
    let nan = gsf_bytes("XRes = 2\nYRes = 1\n", &[1.0, f32::NAN]);
    assert!(read_bytes(&nan, Path::new("nan.gsf")).is_ok());
    let inf = gsf_bytes("XRes = 2\nYRes = 1\n", &[1.0, f32::INFINITY]);
    let e = err(&inf, "inf.gsf");
    assert_eq!(e.kind(), ErrorKind::InvalidData);
    let missing = gsf_bytes("XRes = 2\n", &[1.0, 2.0]);
    assert_eq!(err(&missing, "missing.gsf").kind(), ErrorKind::MissingField);
    let latin = gsf_bytes("XRes = 2\nYRes = 1\nTitle = \u{fffd}\n", &[1.0, 2.0]);
    let latin: Vec<u8> = {
        let s = latin
            .windows(3)
            .position(|w| w == "\u{fffd}".as_bytes())
            .unwrap();
        let mut v = latin.clone();
        v[s..s + 3].copy_from_slice(b"\xe9\xe9\xe9");
        v
    };
    assert_eq!(err(&latin, "latin.gsf").kind(), ErrorKind::Encoding);
    let trailing = [good.clone(), vec![0, 0, 0, 0]].concat();
    assert_eq!(
        err(&trailing, "trailing.gsf").kind(),
        ErrorKind::InvalidData
    );
    let bad_real = gsf_bytes("XRes = 2\nYRes = 1\nXReal = -1\n", &[1.0, 2.0]);
    assert_eq!(err(&bad_real, "real.gsf").kind(), ErrorKind::InvalidField);
}

#[test]
fn raw_bad_inputs() {
    let ch = Channel::new("Z", Direction::Forward, "m", 3, 2, vec![0.0; 6]).unwrap();
    let good = encode_raw_f64(&ch);
    let f = read_bytes(&good, Path::new("ok.dat")).unwrap();
    assert_eq!(f.pixels(), Some([3, 2]));
    assert_eq!(
        err(&good[..good.len() - 3], "cut.dat").kind(),
        ErrorKind::Truncated
    );
    assert_eq!(err(&good[..5], "tiny.dat").kind(), ErrorKind::Truncated);
    let mut huge = good.clone();
    huge[0..4].copy_from_slice(&31623u32.to_le_bytes());
    huge[4..8].copy_from_slice(&31623u32.to_le_bytes());
    assert_eq!(err(&huge, "huge.dat").kind(), ErrorKind::TooLarge);
    let mut nan = good.clone();
    nan[8 + 8..8 + 16].copy_from_slice(&f64::NAN.to_le_bytes());
    let e = err(&nan, "nan.dat");
    assert!(
        matches!(e, FormatError::InvalidData { offset: 16, .. }),
        "{e}"
    );
    let trailing = [good.clone(), vec![1]].concat();
    assert_eq!(
        err(&trailing, "trailing.dat").kind(),
        ErrorKind::InvalidData
    );
    let mut zero = good;
    zero[0..4].copy_from_slice(&0u32.to_le_bytes());
    assert_eq!(err(&zero, "zero.dat").kind(), ErrorKind::InvalidField);
}

const ISO: &str = "hopg-terrace-iso28600/graphiteterrace.spm";

#[test]
fn iso_bad_inputs() {
    let b = bytes_of(ISO);
    let e = err(&b[..b.len() / 2], "cut.spm");
    assert_eq!(e.kind(), ErrorKind::Truncated, "{e}");
    let e = err(&b[..300], "header-cut.spm");
    assert_eq!(e.kind(), ErrorKind::Truncated, "{e}");
    let huge = replace(
        &b,
        b"top to bottom\n512\n512\n",
        b"top to bottom\n1000000000\n1\n",
    );
    assert_eq!(err(&huge, "huge.spm").kind(), ErrorKind::TooLarge);
    let nan = replace(&b, b"1.8331518e-10\n", b"nan\n");
    let e = err(&nan, "nan.spm");
    assert_eq!(e.kind(), ErrorKind::InvalidData, "{e}");
    assert!(e.to_string().contains("line 130"), "{e}");
    let word = replace(&b, b"1.8331518e-10\n", b"abc\n");
    assert_eq!(err(&word, "word.spm").kind(), ErrorKind::InvalidData);
    let latin = replace(&b, b"Bogus", b"B\xf6gus");
    assert_eq!(err(&latin, "latin.spm").kind(), ErrorKind::Encoding);
    let spec = replace(&b, b"MAP_SC", b"SPEC_SC");
    assert_eq!(err(&spec, "spec.spm").kind(), ErrorKind::Unsupported);
    assert_eq!(
        err(b"ISO/TC 201 SPM data transfer format\n", "empty.spm").kind(),
        ErrorKind::Truncated
    );
    assert_eq!(err(b"ISO/TC 999", "magic.spm").kind(), ErrorKind::BadMagic);
}

const SM4: &str = "graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4";
const SM4_PAGE0_HEADER: usize = 5242;

#[test]
fn sm4_bad_inputs() {
    let b = bytes_of(SM4);
    let e = err(&b[..b.len() / 2], "cut.sm4");
    assert_eq!(e.kind(), ErrorKind::Truncated, "{e}");
    let e = err(&b[..40], "tiny.sm4");
    assert_eq!(e.kind(), ErrorKind::Truncated, "{e}");
    let mut huge = b.clone();
    let o = SM4_PAGE0_HEADER + 24;
    huge[o..o + 4].copy_from_slice(&1_000_000_000u32.to_le_bytes());
    assert_eq!(err(&huge, "huge.sm4").kind(), ErrorKind::TooLarge);
    let mut big = b.clone();
    big[o..o + 4].copy_from_slice(&4096u32.to_le_bytes());
    assert_eq!(err(&big, "big.sm4").kind(), ErrorKind::Truncated);
    let mut pages = b.clone();
    pages[94..98].copy_from_slice(&u32::MAX.to_le_bytes());
    assert_eq!(err(&pages, "pages.sm4").kind(), ErrorKind::TooLarge);
    let mut scale = b.clone();
    scale[SM4_PAGE0_HEADER + 56..SM4_PAGE0_HEADER + 60].copy_from_slice(&f32::NAN.to_le_bytes());
    assert_eq!(err(&scale, "scale.sm4").kind(), ErrorKind::InvalidField);
    let mut magic = b;
    magic[2] = b'X';
    assert_eq!(err(&magic, "magic.sm4").kind(), ErrorKind::BadMagic);
}

#[test]
fn unknown_and_missing_files() {
    let e = err(b"\x89PNG\r\n\x1a\n", "picture.xyz");
    assert_eq!(e.kind(), ErrorKind::UnknownFormat);
    let e = read_any("/nonexistent/dir/file.sxm").unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Io);
    assert!(e.to_string().contains("/nonexistent/dir/file.sxm"));
}

#[test]
fn errors_are_std_errors() {
    let ch = Channel::new("Z", Direction::Forward, "m", 1, 1, vec![0.0]).unwrap();
    let e: Box<dyn std::error::Error> = Box::new(encode_gsf(&ch, &[]).unwrap_err());
    assert!(e.to_string().contains("invalid input"));
}
