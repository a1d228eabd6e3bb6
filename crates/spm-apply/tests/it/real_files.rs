//! `correct` honours the geometry in the headers of the real files in
//! `../shared/data/measured/` (size, offset, angle, slow direction, backward halves), checked
//! against expectations computed by hand from the header values quoted in each test.
#![allow(clippy::unwrap_used)]

use spm_apply::{
    ApplyOptions, ChannelSelection, CountsSource, FileRaster, RasterPath, correct_file,
};
use spm_correction::{CountRegion, CountsConvention, PlaneSurfaces, Provenance, SurfaceSet};
use spm_formats::{Direction, ScanDir, SpmFile, read_any, read_bytes};
use spmcal_tests::measured_file;

/// A uniform calibration: K̄x = kx, K̄y = ky, α; calibrated over ±20 000 counts.
fn calibration(kx: f64, ky: f64, alpha: f64, nominal: f64) -> SurfaceSet {
    let mut plane = PlaneSurfaces::constant(0.0, kx, ky, alpha).unwrap();
    plane.n_records = 100;
    plane.calibrated_region_counts =
        CountRegion::bounding(&[-20_000.0, 20_000.0], &[-20_000.0, 20_000.0], 0.0);
    SurfaceSet::new(
        Provenance {
            scanner_id: "lab-stm".into(),
            n_records: 100,
            nominal_nm_per_count: Some(nominal),
            counts_convention: Some(CountsConvention::CentredSigned),
            ..Provenance::default()
        },
        vec![plane],
    )
    .unwrap()
}

fn with_k(k: f64) -> ApplyOptions {
    ApplyOptions {
        nominal_nm_per_count: Some(k),
        ..ApplyOptions::default()
    }
}

fn close(a: f64, b: f64, tol: f64, what: &str) {
    assert!((a - b).abs() <= tol, "{what}: {a} vs {b}");
}

/// Si_7x7_028.sxm: `SCAN_PIXELS 256 256`, `SCAN_RANGE 5E-8 5E-8`, `SCAN_OFFSET 0 0`,
/// `SCAN_ANGLE 0`, `SCAN_DIR down`, Z and Current, forward and backward.
#[test]
fn the_sxm_raster_is_read_from_its_header() {
    let file = read_any(measured_file("si7x7-nanonis/Si_7x7_028.sxm")).unwrap();
    let z = file.channel("Z", Direction::Forward).unwrap();
    let r = FileRaster::of(&file, z, Some(0.05), None).unwrap();
    // 50 nm / 256 px / 0.05 nm per count.
    close(r.step_x_counts, 3.906_25, 1e-9, "step");
    assert_eq!(r.path, RasterPath::Trace(ScanDir::Down));
    // The first acquired pixel of a downward scan is the top-left one: (−127.5, +127.5) steps.
    let first = r.pixel_counts(0.0, 0.0);
    close(first.x.value(), -498.046_875, 1e-9, "first pixel x");
    close(first.y.value(), 498.046_875, 1e-9, "first pixel y");
    assert_eq!(
        r.counts,
        CountsSource::Nominal {
            nm_per_count: 0.05,
            field: "--nominal-nm-per-count".into()
        }
    );
}

/// Rewrites a header value of an `.sxm` in place (same length), e.g. the offset or the angle.
pub(crate) fn patched_sxm(tag: &str, old: &str, new: &str) -> SpmFile {
    assert_eq!(old.len(), new.len());
    let path = measured_file("si7x7-nanonis/Si_7x7_051.sxm");
    let mut bytes = std::fs::read(&path).unwrap();
    let needle = format!(":{tag}:\n{old}");
    let at = bytes
        .windows(needle.len())
        .position(|w| w == needle.as_bytes())
        .unwrap_or_else(|| panic!("{tag} = {old:?} not in the header"));
    let start = at + tag.len() + 3;
    bytes[start..start + old.len()].copy_from_slice(new.as_bytes());
    read_bytes(&bytes, &path).unwrap()
}

/// Si_7x7_051.sxm (20 nm, 256 px, down) with `SCAN_OFFSET` set to (100 nm, −40 nm) and
/// `SCAN_ANGLE` to 30° (Nanonis: clockwise positive, so −30° counter-clockwise).
#[test]
fn the_sxm_offset_and_angle_move_and_turn_the_raster() {
    let file = patched_sxm(
        "SCAN_OFFSET",
        "             0.000000E+0         0.000000E+0",
        "             1.000000E-7        -4.000000E-8",
    );
    let z = file.channel("Z", Direction::Forward).unwrap();
    let r = FileRaster::of(&file, z, Some(0.02), None).unwrap();
    close(r.centre.x.value(), 5000.0, 1e-6, "centre x");
    close(r.centre.y.value(), -2000.0, 1e-6, "centre y");
    let file = patched_sxm("SCAN_ANGLE", "            0.000E+0", "            3.000E+1");
    let z = file.channel("Z", Direction::Forward).unwrap();
    let r = FileRaster::of(&file, z, Some(0.02), None).unwrap();
    close(r.angle_ccw_rad.to_degrees(), -30.0, 1e-9, "angle");
    // The right edge's middle is 127.5 steps of 20/256/0.02 = 3.90625 counts along the frame's
    // x, turned 30° clockwise: (+cos 30°, −sin 30°)·498.046875 counts (row 127.5 is the middle).
    let p = r.pixel_counts(255.0, 127.5);
    close(
        p.x.value(),
        498.046_875 * 30f64.to_radians().cos(),
        1e-6,
        "right x",
    );
    close(p.y.value(), -498.046_875 * 0.5, 1e-6, "right y");
}

/// With a calibration equal to the nominal sensitivity and no distortion, correcting
/// reproduces every channel of the real file, both halves, on its own grid and centre.
#[test]
fn an_identity_calibration_reproduces_every_channel_of_a_real_file() {
    let file = read_any(measured_file("si7x7-nanonis/Si_7x7_051.sxm")).unwrap();
    let set = calibration(0.02, 0.02, 0.0, 0.02);
    let out = correct_file(&file, &set, &with_k(0.02)).unwrap();
    assert_eq!(out.channels.len(), file.channels.len());
    for (a, b) in out.channels.iter().zip(&file.channels) {
        assert_eq!((a.name(), a.direction()), (b.name(), b.direction()));
        assert_eq!((a.nx(), a.ny()), (256, 256));
        close(a.size_x_nm().unwrap(), 20.0, 1e-9, "width");
        close(a.center_x_nm().unwrap(), 0.0, 1e-9, "centre x");
        close(a.center_y_nm().unwrap(), 0.0, 1e-9, "centre y");
        let mut differ = 0;
        for (x, y) in a.data().iter().zip(b.data()) {
            if x.is_nan() != y.is_nan()
                || (x.is_finite() && (x - y).abs() > 1e-6 * y.abs().max(1e-15))
            {
                differ += 1;
            }
        }
        assert_eq!(differ, 0, "{} {:?}", a.name(), a.direction());
    }
    let get = |k: &str| {
        out.metadata
            .iter()
            .find(|(key, _)| key == k)
            .map(|(_, v)| v.clone())
    };
    assert_eq!(get("source_BIAS").as_deref(), Some("-2.000E+0"));
    assert_eq!(
        get("spmcal_raster_path").as_deref(),
        Some("lines +x, slow axis down")
    );
    assert!(get("source_REC_DATE").is_some());
}

/// A calibration 10 % larger along x than the nominal: the corrected image is 22 nm wide
/// (20 nm · 1.1) and 20 nm tall, whichever half and however the frame is offset.
#[test]
fn a_scale_error_is_removed_on_both_halves() {
    let file = patched_sxm(
        "SCAN_OFFSET",
        "             0.000000E+0         0.000000E+0",
        "             1.000000E-7        -4.000000E-8",
    );
    let set = calibration(0.022, 0.02, 0.0, 0.02);
    let out = correct_file(
        &file,
        &set,
        &ApplyOptions {
            channels: ChannelSelection::Named("Z".into()),
            ..with_k(0.02)
        },
    )
    .unwrap();
    assert_eq!(out.channels.len(), 2);
    for c in &out.channels {
        // Width: 255 steps of 1.1·(20/256) nm, plus one pixel of the output grid.
        let step = c.size_x_nm().unwrap() / c.nx() as f64;
        close(
            (c.nx() - 1) as f64 * step,
            255.0 * 1.1 * 20.0 / 256.0,
            step,
            "width",
        );
        close(
            (c.ny() - 1) as f64 * step,
            255.0 * 20.0 / 256.0,
            step,
            "height",
        );
        // The centre: 5000 counts × 0.022 nm per count along x, −2000 × 0.02 along y.
        close(c.center_x_nm().unwrap(), 110.0, step, "centre x");
        close(c.center_y_nm().unwrap(), -40.0, step, "centre y");
    }
}

/// The RHK `.sm4` (graphite, 9 K): pages with `XOffset = -1.2814023e-8`,
/// `YOffset = 1.6329706e-8` m, `Angle = 1e1` (10°), 256 px over 1.0 nm, `SCAN_RIGHT` and
/// `SCAN_LEFT` halves of topography, current and lock-in.
#[test]
fn the_sm4_offset_angle_and_halves_are_honoured() {
    let file = read_any(measured_file(
        "graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4",
    ))
    .unwrap();
    let topo = file.channel("Topography", Direction::Forward).unwrap();
    let r = FileRaster::of(&file, topo, Some(0.001), None).unwrap();
    close(r.centre.x.value(), -12_814.023, 1e-2, "centre x");
    close(r.centre.y.value(), 16_329.706, 1e-2, "centre y");
    close(r.angle_ccw_rad.to_degrees(), 10.0, 1e-9, "angle");
    // The middle of the right edge: 127.5 steps of 3.90625 counts along the frame's x,
    // turned 10° counter-clockwise.
    let half = 127.5 * topo.pixel_x_nm().unwrap() / 0.001;
    let p = r.pixel_counts(255.0, 127.5);
    close(
        p.x.value(),
        -12_814.023 + half * 10f64.to_radians().cos(),
        1e-2,
        "right x",
    );
    close(
        p.y.value(),
        16_329.706 + half * 10f64.to_radians().sin(),
        1e-2,
        "right y",
    );
    // Both halves of every channel, one map, the frame's centre and angle kept.
    let set = calibration(0.001, 0.001, 0.0, 0.001);
    let out = correct_file(&file, &set, &with_k(0.001)).unwrap();
    assert_eq!(out.channels.len(), 6);
    let backward = out
        .channels
        .iter()
        .filter(|c| c.direction() == Direction::Backward)
        .count();
    assert_eq!(backward, 3);
    for c in &out.channels {
        close(
            c.center_x_nm().unwrap(),
            -12.814_023,
            1e-5,
            "output centre x",
        );
        close(
            c.center_y_nm().unwrap(),
            16.329_706,
            1e-5,
            "output centre y",
        );
        close(c.angle_deg().unwrap(), 10.0, 1e-9, "output angle");
        // The identity calibration keeps every pixel: no NaN appears where the file had data.
        assert_eq!(c.nan_count(), 0, "{} {:?}", c.name(), c.direction());
    }
}

/// The ISO 28600 HOPG terrace: 512 × 512 over 11.4807 nm, `Slow scan direction = top to
/// bottom`, offsets 0, forward only.
#[test]
fn the_iso28600_raster_is_downward_and_centred() {
    let file = read_any(measured_file("hopg-terrace-iso28600/graphiteterrace.spm")).unwrap();
    let z = &file.channels[0];
    let r = FileRaster::of(&file, z, Some(0.01), None).unwrap();
    assert_eq!(r.path, RasterPath::Trace(ScanDir::Down));
    close(r.step_x_counts, 11.4807 / 512.0 / 0.01, 1e-9, "step");
    close(r.centre.x.value(), 0.0, 1e-9, "centre x");
    let first = r.pixel_counts(0.0, 0.0);
    close(
        first.y.value(),
        255.5 * 11.4807 / 512.0 / 0.01,
        1e-9,
        "top line y",
    );
    // A calibration of another scanner is refused; so is a sensitivity in m.
    let set = calibration(0.01, 0.01, 0.0, 0.01);
    let other = ApplyOptions {
        scanner_id: Some("afm-2".into()),
        ..with_k(0.01)
    };
    let e = correct_file(&file, &set, &other).unwrap_err().to_string();
    assert!(
        e.contains("graphiteterrace.spm") && e.contains("lab-stm"),
        "{e}"
    );
    let e = correct_file(&file, &set, &with_k(1e-11))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("graphiteterrace.spm") && e.contains("1e-11"),
        "{e}"
    );
}
