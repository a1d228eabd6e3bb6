//! PNG rendering: size, colour map, scale bar.

#![allow(clippy::unwrap_used)]

use spm_formats::{Channel, Direction, read_any};
use spm_plot::{ColorMap, PngOptions, render_png};
use spmcal_tests::measured_file;

fn decode(bytes: &[u8]) -> (u32, u32, Vec<u8>) {
    let decoder = png::Decoder::new(bytes);
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgb);
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

#[test]
fn renders_a_measured_image_with_a_scale_bar() {
    let f = read_any(measured_file("si7x7-nanonis/Si_7x7_051.sxm")).unwrap();
    let z = f.channel("Z", Direction::Forward).unwrap();
    let opts = PngOptions {
        zoom: 2,
        ..PngOptions::default()
    };
    let png_bytes = render_png(z, &opts).unwrap();
    let (w, h, rgb) = decode(&png_bytes);
    assert_eq!((w, h), (512, 512));
    // 20 nm wide → a 5 nm bar = 128 px at zoom 2, white, near the bottom-left corner.
    let px = |x: u32, y: u32| {
        let i = 3 * (y * w + x) as usize;
        [rgb[i], rgb[i + 1], rgb[i + 2]]
    };
    let margin = 12;
    let bar_y = h - margin - 3; // top row of the 6-px-thick bar
    for x in [margin, margin + 64, margin + 127] {
        assert_eq!(px(x, bar_y + 1), [255, 255, 255], "bar pixel at x={x}");
    }
    assert_ne!(px(margin + 140, bar_y + 1), [255, 255, 255]);
    if let Ok(dir) = std::env::var("SPM_FORMATS_PNG_OUT") {
        std::fs::write(
            std::path::Path::new(&dir).join("Si_7x7_051_Z.png"),
            &png_bytes,
        )
        .unwrap();
    }
}

#[test]
fn colour_maps_span_dark_to_bright_and_nan_is_marked() {
    for map in [ColorMap::Gray, ColorMap::AfmHot, ColorMap::Viridis] {
        let lo = map.rgb(0.0).iter().map(|&c| u32::from(c)).sum::<u32>();
        let hi = map.rgb(1.0).iter().map(|&c| u32::from(c)).sum::<u32>();
        assert!(hi > lo + 300, "{map:?}");
        let _ = map.rgb(f64::NAN);
    }
    let data = vec![0.0, 1.0, f64::NAN, 3.0];
    let ch = Channel::new("z", Direction::Forward, "m", 2, 2, data).unwrap();
    let opts = PngOptions {
        color_map: ColorMap::Gray,
        level_plane: false,
        range: Some((0.0, 3.0)),
        ..PngOptions::default()
    };
    let (w, h, rgb) = decode(&render_png(&ch, &opts).unwrap());
    assert_eq!((w, h), (2, 2));
    assert_eq!(&rgb[0..3], &[0, 0, 0]);
    assert_eq!(&rgb[9..12], &[255, 255, 255]);
    assert_eq!(&rgb[6..9], &[40, 60, 110]); // NaN colour
}
