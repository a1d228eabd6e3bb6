//! spm-sim frames as the model check's input: each frame's `FrameInfo` and each half's
//! features (and, when asked, its pixels), placed on the request's nominal linear raster,
//! each feature's time from its pixels' (equidistant along a line).

use spm_features::Polarity;
use spm_hal::{Frame, HeightMap, ScanDirection, TraceHalf};
use spm_modelcheck::{
    FeatureSet, FrameInfo, LatticeSpec, LineDirection, MapContext, PixelImage,
    features_from_height_map, pixel_image_from_height_map,
};

/// One simulated frame and how it was scanned.
pub struct SimFrame<'a> {
    pub frame: &'a Frame,
    /// Its index among the set's frames.
    pub index: usize,
    pub label: String,
    /// Pixels per side (square frames).
    pub pixels: usize,
    /// The nominal pixel, nm.
    pub pixel_nm: f64,
    /// The frame's nominal half-width, nm.
    pub half_width_nm: f64,
    pub dwell_s: f64,
    /// The lattice constant, nm.
    pub a_nm: f64,
}

/// Adds `f`'s frame and its halves' features to `set` (and their pixels to `pixels`);
/// returns each half's direction and height map.
pub fn add_sim_frame(
    set: &mut FeatureSet,
    mut pixels: Option<&mut Vec<PixelImage>>,
    f: &SimFrame<'_>,
) -> Vec<(LineDirection, HeightMap)> {
    let (n, pixel_nm, dwell_s) = (f.pixels, f.pixel_nm, f.dwell_s);
    set.frames.push(FrameInfo {
        label: f.label.clone(),
        half_width_x_nm: f.half_width_nm,
        half_height_y_nm: f.half_width_nm,
        start_time_s: f.frame.forward.time_s[0] - 0.5 * dwell_s,
        duration_s: 2.0 * (n * n) as f64 * dwell_s,
        fast_speed_nm_per_s: pixel_nm / dwell_s,
        lines: n,
        pixel_nm: Some([pixel_nm, pixel_nm]),
    });
    let counter = f.frame.request.direction == ScanDirection::Counter;
    let mut maps = Vec::new();
    for half in [TraceHalf::Forward, TraceHalf::Backward] {
        let map = f.frame.height_map(half).unwrap();
        // Fast-axis motion: direct forward and counter backward run +x.
        let plus_x = matches!(
            (counter, half),
            (false, TraceHalf::Forward) | (true, TraceHalf::Backward)
        );
        let direction = if plus_x {
            LineDirection::Forward
        } else {
            LineDirection::Backward
        };
        let times = map.time_s.clone();
        let time_and_line = move |column: f64, row: f64| {
            let r = (row.round().max(0.0) as usize).min(n - 1);
            let c = (column.round().max(0.0) as usize).min(n - 1);
            let dt = (column - c as f64) * dwell_s * if plus_x { 1.0 } else { -1.0 };
            let line = if counter { n - 1 - r } else { r };
            (times[r * n + c] + dt, line)
        };
        let ctx = MapContext {
            pixel_nm: [pixel_nm, pixel_nm],
            polarity: Polarity::Hill,
            a_nm: f.a_nm,
            min_snr: 4.0,
            direction,
            frame_index: f.index,
        };
        set.features
            .extend(features_from_height_map(&map, &ctx, &time_and_line).unwrap());
        if let Some(pixels) = pixels.as_deref_mut() {
            let lattice = LatticeSpec::Hex { a_nm: f.a_nm };
            pixels.extend(pixel_image_from_height_map(
                &map,
                &ctx,
                &lattice,
                &time_and_line,
            ));
        }
        maps.push((direction, map));
    }
    maps
}
