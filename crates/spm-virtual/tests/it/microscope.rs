//! The virtual microscope against closed forms: where a pixel is looked up, which image
//! serves which half, the clock, and the refusals.
#![allow(clippy::unwrap_used)]

use spm_hal::{
    CountPoint, Counts, CountsPerSecond, Error as _, ErrorKind, Microscope, MoveRequest,
    ScanDirection, ScanRequest, Seconds, TraceHalf,
};
use spm_virtual::{
    ImageError, ImageTiming, StoredImage, VirtualMicroscope, VirtualParams, VirtualSurface,
};

/// A plane `offset + gx·column + gy·row` nm on a 40 × 30 grid of 0.2 × 0.25 nm pixels.
fn plane(offset: f64, gx: f64, gy: f64) -> StoredImage {
    let (nx, ny) = (40usize, 30usize);
    let h = (0..nx * ny)
        .map(|i| offset + gx * (i % nx) as f64 + gy * (i / nx) as f64)
        .collect();
    StoredImage::new(h, nx, ny, 0.2, 0.25, ImageTiming { line_time_s: 0.08 }).unwrap()
}

#[test]
fn counts_map_to_pixels_through_the_nominal_sensitivity() {
    // 0.05 nm per count: 4 counts per 0.2-nm column, 5 counts per 0.25-nm row; count 0 at
    // the centre pixel (19.5, 14.5).
    let mut m = VirtualMicroscope::new(
        VirtualSurface::single(plane(0.0, 0.01, 0.1)),
        VirtualParams::new(0.05),
    )
    .unwrap();
    let caps = m.capabilities();
    assert_eq!(
        caps.field_min,
        CountPoint::from_counts(-18.5 * 4.0, -13.5 * 5.0)
    );
    assert_eq!(
        caps.field_max,
        CountPoint::from_counts(18.5 * 4.0, 13.5 * 5.0)
    );
    // One pixel at (column 7.25, row 3.5) = ((7.25 − 19.5)·4, (3.5 − 14.5)·5) counts.
    let request = ScanRequest::centred_square(
        CountPoint::from_counts(-49.0, -55.0),
        Counts(1.0),
        1,
        Seconds(1e-3),
    );
    let frame = m.scan(&request).unwrap();
    let expected_nm = 0.01 * 7.25 + 0.1 * 3.5;
    assert!((frame.forward.z_counts[0] * 0.001 - expected_nm).abs() < 1e-12);
    // The position reading is the command.
    let target = CountPoint::from_counts(30.0, -20.0);
    m.move_to(MoveRequest {
        target,
        speed: CountsPerSecond(50.0),
        settle: Seconds(0.5),
    })
    .unwrap();
    assert_eq!(m.position().unwrap(), target);
}

#[test]
fn moves_scans_and_waits_advance_the_clock_at_the_files_speed() {
    let mut m = VirtualMicroscope::new(
        VirtualSurface::single(plane(0.0, 0.0, 0.0)),
        VirtualParams::new(0.05),
    )
    .unwrap();
    let start = m.position().unwrap();
    let target = CountPoint::from_counts(start.x.value() + 30.0, start.y.value() + 40.0);
    m.move_to(MoveRequest {
        target,
        speed: CountsPerSecond(10.0),
        settle: Seconds(0.25),
    })
    .unwrap();
    // 50 counts at 10 counts/s + 0.25 s.
    assert!((m.now().unwrap().value() - 5.25).abs() < 1e-12);
    m.wait(Seconds(1.0)).unwrap();
    // A 6 × 4 raster with a 2-count step: half a column, 2 ms per column (0.08 s / 40).
    let request = ScanRequest {
        origin: CountPoint::from_counts(-20.0, -20.0),
        pixel_step: Counts(2.0),
        pixels_per_line: 6,
        lines: 4,
        direction: ScanDirection::Direct,
        pixel_dwell: Seconds(1.0),
        record_backward: true,
    };
    let frame = m.scan(&request).unwrap();
    let dwell = 1e-3;
    assert!((frame.forward.time_s[0] - (6.25 + 0.5 * dwell)).abs() < 1e-12);
    let back = frame.backward.as_ref().unwrap();
    assert!((back.time_s[0] - (6.25 + 6.5 * dwell)).abs() < 1e-12);
    assert!((m.now().unwrap().value() - (6.25 + 48.0 * dwell)).abs() < 1e-12);
    // The probe ends at the start of the last line.
    assert_eq!(
        m.position().unwrap(),
        request.commanded_position(TraceHalf::Forward, 3, 0)
    );
}

#[test]
fn backward_halves_and_counter_scans_are_served_from_their_own_frames() {
    let surface = VirtualSurface {
        forward: plane(1.0, 0.0, 0.0),
        backward: Some(plane(2.0, 0.0, 0.0)),
        counter: Some(plane(3.0, 0.0, 0.0)),
    };
    let mut m = VirtualMicroscope::new(surface, VirtualParams::new(0.05)).unwrap();
    let mut request = ScanRequest::centred_square(
        CountPoint::from_counts(0.0, 0.0),
        Counts(4.0),
        5,
        Seconds(1e-3),
    );
    request.record_backward = true;
    let direct = m.scan(&request).unwrap();
    let counter = m
        .scan(&request.clone().with_direction(ScanDirection::Counter))
        .unwrap();
    let all = |z: &[f64], nm: f64| z.iter().all(|v| (v * 0.001 - nm).abs() < 1e-12);
    assert!(all(&direct.forward.z_counts, 1.0));
    assert!(all(&direct.backward.unwrap().z_counts, 2.0));
    assert!(all(&counter.forward.z_counts, 3.0));
    assert!(all(&counter.backward.unwrap().z_counts, 2.0));
}

#[test]
fn a_counter_scan_of_one_image_sees_the_same_heights_in_reverse_order() {
    let mut m = VirtualMicroscope::new(
        VirtualSurface::single(plane(0.0, 0.013, -0.021)),
        VirtualParams::new(0.05),
    )
    .unwrap();
    let request = ScanRequest::centred_square(
        CountPoint::from_counts(10.0, 10.0),
        Counts(3.0),
        7,
        Seconds(1e-3),
    );
    let direct = m
        .scan(&request)
        .unwrap()
        .height_map(TraceHalf::Forward)
        .unwrap();
    let counter = m
        .scan(&request.with_direction(ScanDirection::Counter))
        .unwrap()
        .height_map(TraceHalf::Forward)
        .unwrap();
    for (a, b) in direct.z_counts.iter().zip(&counter.z_counts) {
        assert!((a - b).abs() < 1e-9);
    }
}

#[test]
fn requests_leaving_the_image_are_out_of_range() {
    let mut m = VirtualMicroscope::new(
        VirtualSurface::single(plane(0.0, 0.0, 0.0)),
        VirtualParams::new(0.05),
    )
    .unwrap();
    let caps = m.capabilities();
    let e = m
        .move_to(MoveRequest {
            target: CountPoint::new(caps.field_max.x + Counts(0.5), caps.field_min.y),
            speed: CountsPerSecond(10.0),
            settle: Seconds(0.0),
        })
        .unwrap_err();
    assert_eq!(e.kind(), ErrorKind::OutOfRange);
    let request = ScanRequest::centred_square(caps.field_min, Counts(1.0), 3, Seconds(1e-3));
    assert_eq!(m.scan(&request).unwrap_err().kind(), ErrorKind::OutOfRange);
    // Nothing moved, nothing took time.
    assert_eq!(m.now().unwrap(), Seconds(0.0));
}

#[test]
fn images_with_missing_data_or_too_few_pixels_are_refused() {
    let mut h = vec![0.0; 6 * 6];
    h[2 * 6 + 4] = f64::NAN;
    h[5 * 6 + 1] = f64::NAN;
    let e = StoredImage::new(h, 6, 6, 0.1, 0.1, ImageTiming { line_time_s: 0.1 }).unwrap_err();
    // The first missing pixel in scanner row 2 is display row 6 − 1 − 2 = 3.
    assert_eq!(
        e,
        ImageError::MissingData {
            count: 2,
            first_row: 3,
            first_column: 4
        }
    );
    let e = StoredImage::new(
        vec![0.0; 16],
        4,
        4,
        0.1,
        0.1,
        ImageTiming { line_time_s: 0.1 },
    )
    .unwrap_err();
    assert!(matches!(e, ImageError::TooSmall { .. }));
    let mismatch = VirtualSurface {
        forward: plane(0.0, 0.0, 0.0),
        backward: Some(plane(0.0, 0.0, 0.0).crop(0, 0, 20, 20).unwrap()),
        counter: None,
    };
    assert!(VirtualMicroscope::new(mismatch, VirtualParams::new(0.05)).is_err());
}

#[test]
fn a_file_channel_is_turned_into_scanner_geometry_in_nanometres() {
    // Display row 0 (top) holds 1 nm, the rest 0: in scanner geometry the top is the last row.
    let (nx, ny) = (8usize, 6usize);
    let mut data = vec![0.0; nx * ny];
    for v in &mut data[..nx] {
        *v = 1e-9;
    }
    let channel =
        spm_formats::Channel::new("Z", spm_formats::Direction::Forward, "m", nx, ny, data)
            .unwrap()
            .with_size_nm(4.0, 3.0);
    let image =
        StoredImage::from_channel(&channel, &spm_virtual::ChannelOptions::default()).unwrap();
    assert_eq!(image.pixel_x_nm(), 0.5);
    assert_eq!(image.pixel_y_nm(), 0.5);
    assert!((image.heights_nm()[(ny - 1) * nx] - 1.0).abs() < 1e-12);
    assert_eq!(image.heights_nm()[0], 0.0);
    // No timing in the channel: the documented fallback line time.
    assert_eq!(image.timing().line_time_s, 0.1);
    let current = spm_formats::Channel::new(
        "I",
        spm_formats::Direction::Forward,
        "A",
        nx,
        ny,
        vec![0.0; nx * ny],
    )
    .unwrap()
    .with_size_nm(4.0, 3.0);
    assert!(matches!(
        StoredImage::from_channel(&current, &spm_virtual::ChannelOptions::default()),
        Err(ImageError::NotAHeight { .. })
    ));
}

#[test]
fn background_removal_takes_planes_away_and_keeps_a_lattice_by_the_closed_form() {
    let (nx, ny) = (96usize, 80usize);
    let period_px = 7.0;
    let sigma_px = 6.0;
    let omega = 2.0 * std::f64::consts::PI / period_px;
    let h: Vec<f64> = (0..nx * ny)
        .map(|i| {
            let (x, y) = ((i % nx) as f64, (i / nx) as f64);
            3.0 + 0.2 * x - 0.15 * y + 0.01 * (omega * x).cos()
        })
        .collect();
    let image = StoredImage::new(h, nx, ny, 0.1, 0.1, ImageTiming { line_time_s: 0.1 }).unwrap();
    let flat = image.without_background(sigma_px).unwrap();
    // Gain of the high-pass at this period: 1 − exp(−2π²σ²/P²) (Gaussian's transform).
    let gain =
        1.0 - (-2.0 * std::f64::consts::PI.powi(2) * sigma_px.powi(2) / period_px.powi(2)).exp();
    let reach = 25; // beyond 4 σ from every edge the window is whole
    for row in reach..ny - reach {
        for column in reach..nx - reach {
            let expected = 0.01 * gain * (omega * column as f64).cos();
            let v = flat.heights_nm()[row * nx + column];
            assert!(
                (v - expected).abs() < 1e-6,
                "({column}, {row}): {v} vs {expected}"
            );
        }
    }
    // A plane alone is removed everywhere, edges included.
    let plane: Vec<f64> = (0..nx * ny)
        .map(|i| 1.0 + 0.3 * (i % nx) as f64 + 0.7 * (i / nx) as f64)
        .collect();
    let plane = StoredImage::new(plane, nx, ny, 0.1, 0.1, ImageTiming { line_time_s: 0.1 })
        .unwrap()
        .without_background(sigma_px)
        .unwrap();
    assert!(plane.heights_nm().iter().all(|v| v.abs() < 1e-8));
    assert!(image.without_background(0.0).is_err());
}

/// The background is the kernel's weighted least-squares plane, computed streaming from
/// Gaussian-smoothed moments: at pixels in the middle, at an edge and in a corner, the plane
/// fitted by `spm_regression::generalised_least_squares` (one 1 × 1 block per pixel of
/// variance 1/w, w the separable Gaussian window normalised inside the image) gives the same
/// heights to 1e-9.
#[test]
fn background_removal_is_the_kernel_weighted_plane_fit() {
    let (nx, ny) = (40usize, 31usize);
    let sigma_px = 2.5;
    let h: Vec<f64> = (0..nx * ny)
        .map(|i| {
            let (x, y) = ((i % nx) as f64, (i / nx) as f64);
            2.0 + 0.05 * x - 0.03 * y + 0.4 * (0.9 * x).sin() * (0.7 * y).cos() + 0.002 * x * y
        })
        .collect();
    let image = StoredImage::new(
        h.clone(),
        nx,
        ny,
        0.1,
        0.1,
        ImageTiming { line_time_s: 0.1 },
    )
    .unwrap();
    let flat = image.without_background(sigma_px).unwrap();
    let reach = (4.0 * sigma_px).ceil() as usize;
    let g = |d: usize| (-0.5 * (d as f64 / sigma_px).powi(2)).exp();
    for (column, row) in [(20_usize, 15_usize), (0, 12), (39, 30), (3, 0)] {
        let (x0, x1) = (column.saturating_sub(reach), (column + reach).min(nx - 1));
        let (y0, y1) = (row.saturating_sub(reach), (row + reach).min(ny - 1));
        let (mut rows, mut rhs, mut blocks) = (Vec::new(), Vec::new(), Vec::new());
        for y in y0..=y1 {
            for x in x0..=x1 {
                rows.push(vec![1.0, x as f64, y as f64]);
                rhs.push(h[y * nx + x]);
                blocks.push(vec![vec![
                    1.0 / (g(x.abs_diff(column)) * g(y.abs_diff(row))),
                ]]);
            }
        }
        let fit = spm_regression::generalised_least_squares(&rows, &rhs, &blocks).unwrap();
        let c = &fit.coefficients;
        let expected = h[row * nx + column] - (c[0] + c[1] * column as f64 + c[2] * row as f64);
        let got = flat.heights_nm()[row * nx + column];
        assert!(
            (got - expected).abs() < 1e-9,
            "({column}, {row}): {got} vs the kernel's {expected}"
        );
    }
}

#[test]
fn smoothing_attenuates_a_sinusoid_by_the_gaussians_transform() {
    let (nx, ny) = (90usize, 40usize);
    let (period_px, sigma_px) = (9.0, 1.2);
    let omega = 2.0 * std::f64::consts::PI / period_px;
    let h: Vec<f64> = (0..nx * ny)
        .map(|i| (omega * (i % nx) as f64).sin())
        .collect();
    let image = StoredImage::new(h, nx, ny, 0.1, 0.1, ImageTiming { line_time_s: 0.1 }).unwrap();
    let smooth = image.smoothed(sigma_px).unwrap();
    // The sampled Gaussian's transform: Σ w_k cos(ω k) / Σ w_k over the cut kernel.
    let reach = (4.0 * sigma_px).ceil() as i32;
    let w = |k: i32| (-0.5 * (f64::from(k) / sigma_px).powi(2)).exp();
    let gain = (-reach..=reach)
        .map(|k| w(k) * (omega * f64::from(k)).cos())
        .sum::<f64>()
        / (-reach..=reach).map(w).sum::<f64>();
    // Close to the continuous exp(−2π²σ²/P²).
    let continuous =
        (-2.0 * std::f64::consts::PI.powi(2) * sigma_px.powi(2) / period_px.powi(2)).exp();
    assert!((gain - continuous).abs() < 1e-3, "{gain} vs {continuous}");
    for row in 0..ny {
        for column in 6..nx - 6 {
            let expected = gain * (omega * column as f64).sin();
            let v = smooth.heights_nm()[row * nx + column];
            assert!(
                (v - expected).abs() < 1e-9,
                "({column}, {row}): {v} vs {expected}"
            );
        }
    }
}

/// The frame's offset places the image in the instrument's counts: a part of an image (its
/// centre moved with it) serves the same heights at the same counts as the whole, so a
/// calibration on one part is in the counts `spmcal correct` gives the other.
#[test]
fn an_offset_frame_and_its_parts_share_the_instruments_counts() {
    let params = VirtualParams::new(0.05);
    // The whole frame centred at (3, −2) nm: its centre pixel (19.5, 14.5) at (60, −40) counts.
    let whole = plane(0.0, 0.01, 0.1).with_centre_nm([3.0, -2.0]).unwrap();
    let m_whole = VirtualMicroscope::new(VirtualSurface::single(whole.clone()), params).unwrap();
    assert_eq!(
        m_whole.pixel_of(CountPoint::from_counts(60.0, -40.0)),
        (19.5, 14.5)
    );
    // Columns 20..40, rows 5..25: the centre moves by +10 columns (2 nm) and 0 rows.
    let part = whole.crop(20, 5, 20, 20).unwrap();
    let [cx, cy] = part.centre_nm();
    assert!((cx - (3.0 + 10.0 * 0.2)).abs() < 1e-12, "{cx}");
    assert!((cy - (-2.0 + 0.0 * 0.25)).abs() < 1e-12, "{cy}");
    let mut m_part = VirtualMicroscope::new(VirtualSurface::single(part), params).unwrap();
    let mut m_whole = m_whole;
    let caps = m_part.capabilities();
    assert!(caps.field_min.x.value() > 0.0, "the right half lies at +x");
    for (x, y) in [(100.0, -50.0), (120.0, -10.0)] {
        let request = ScanRequest::centred_square(
            CountPoint::from_counts(x, y),
            Counts(2.0),
            5,
            Seconds(1e-3),
        );
        let a = m_part.scan(&request).unwrap();
        let b = m_whole.scan(&request).unwrap();
        for (p, q) in a.forward.z_counts.iter().zip(&b.forward.z_counts) {
            assert!((p - q).abs() < 1e-9, "at ({x}, {y}): {p} vs {q}");
        }
    }
}
