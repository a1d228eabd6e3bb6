//! Every figure kind: PNG of the requested size, text drawn (title band not blank), the
//! colour bar spanning the colour map's ends, categories on their own ticks.
//! `SPM_PLOT_OUT=DIR` also writes the figures there, to look at.

#![allow(clippy::unwrap_used)]

use spm_plot::{
    CategoryFigure, CategorySeries, ColorMap, MapFigure, MapNode, OrderFigure, Series, SeriesStyle,
    XyFigure, category_chart, order_map, surface_map, xy_chart,
};

struct Image {
    w: u32,
    h: u32,
    rgb: Vec<u8>,
}

impl Image {
    fn decode(bytes: &[u8]) -> Self {
        let decoder = png::Decoder::new(bytes);
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!(info.color_type, png::ColorType::Rgb);
        buf.truncate(info.buffer_size());
        Self {
            w: info.width,
            h: info.height,
            rgb: buf,
        }
    }

    fn px(&self, x: u32, y: u32) -> [u8; 3] {
        let i = 3 * (y * self.w + x) as usize;
        [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
    }

    /// Pixels in rows `rows` darker than mid-grey (text).
    fn dark_pixels(&self, rows: std::ops::Range<u32>) -> usize {
        rows.flat_map(|y| (0..self.w).map(move |x| (x, y)))
            .filter(|&(x, y)| self.px(x, y).iter().map(|&c| u32::from(c)).sum::<u32>() < 300)
            .count()
    }

    /// Whether some pixel is within `tol` of `colour` in every channel.
    fn has_colour(&self, colour: [u8; 3], tol: u8) -> bool {
        self.rgb
            .chunks_exact(3)
            .any(|p| (0..3).all(|k| p[k].abs_diff(colour[k]) <= tol))
    }
}

fn save(name: &str, bytes: &[u8]) {
    if let Ok(dir) = std::env::var("SPM_PLOT_OUT") {
        std::fs::write(std::path::Path::new(&dir).join(name), bytes).unwrap();
    }
}

#[test]
fn surface_map_has_title_colour_bars_and_nodes() {
    let surface = |x: f64, y: f64| 20.0 + 0.002 * x - 0.001 * y + 1e-6 * x * y;
    let mut nodes = Vec::new();
    for i in 0..5 {
        for j in 0..5 {
            let (x, y) = (-400.0 + 200.0 * f64::from(i), -400.0 + 200.0 * f64::from(j));
            // Measured = surface + a known residual pattern.
            nodes.push(MapNode {
                x,
                y,
                value: surface(x, y) + 0.05 * f64::from(i - j),
            });
        }
    }
    let bytes = surface_map(&MapFigure {
        title: "Kx regression surface (degree 2, σ = 0.05 pm/count, Δmax = 1.2 pm/count)",
        x_label: "x, counts",
        y_label: "y, counts",
        x_range: (-450.0, 450.0),
        y_range: (-450.0, 450.0),
        surface: &surface,
        nodes: &nodes,
        value_label: "Kx, pm/count",
        residual_label: "measured − surface, pm/count",
        map: ColorMap::Viridis,
    })
    .unwrap();
    save("surface.png", &bytes);
    let img = Image::decode(&bytes);
    assert_eq!((img.w, img.h), (1440, 600));
    assert!(img.dark_pixels(0..30) > 200, "title drawn");
    // Both ends of both colour maps appear (colour bars).
    for map in [ColorMap::Viridis, ColorMap::Diverging] {
        for t in [0.003, 0.997] {
            assert!(img.has_colour(map.rgb(t), 6), "{map:?} at {t}");
        }
    }
}

#[test]
fn xy_chart_draws_lines_markers_and_legend() {
    let line: Vec<(f64, f64)> = (0..100)
        .map(|k| (f64::from(k) * 10.0, 1.0 + (f64::from(k) * 0.1).sin().abs()))
        .collect();
    let spoiled = vec![(150.0, 1.9), (620.0, 0.4)];
    let bytes = xy_chart(&XyFigure {
        title: "Drift speed against instrument time".to_owned(),
        x_label: "instrument time, s".to_owned(),
        y_label: "drift speed, nm/s".to_owned(),
        series: vec![
            Series {
                name: "drift estimate".to_owned(),
                points: line,
                style: SeriesStyle::LineAndMarkers,
            },
            Series {
                name: "spoiled cycle".to_owned(),
                points: spoiled,
                style: SeriesStyle::Crosses,
            },
        ],
        log_y: false,
        y_from_zero: true,
        size: (900, 480),
    })
    .unwrap();
    save("xy.png", &bytes);
    let img = Image::decode(&bytes);
    assert_eq!((img.w, img.h), (900, 480));
    assert!(img.dark_pixels(0..34) > 200, "title drawn");
    let c0 = spm_plot::category_colour(0);
    let c1 = spm_plot::category_colour(1);
    assert!(img.has_colour([c0.0, c0.1, c0.2], 0));
    assert!(img.has_colour([c1.0, c1.1, c1.2], 0));
}

#[test]
fn log_xy_chart_keeps_a_narrow_range_readable() {
    // Six series between 0.9 % and 2.6 %: the legend's head-room must not squash them.
    let series: Vec<Series> = (0..6)
        .map(|k| Series {
            name: format!("variant {k}"),
            points: vec![
                (360.0 + 20.0 * f64::from(k), 0.9 + 0.3 * f64::from(k)),
                (1130.0, 0.88),
            ],
            style: SeriesStyle::Markers,
        })
        .collect();
    let bytes = xy_chart(&XyFigure {
        title: "Node LCC error against instrument time".to_owned(),
        x_label: "simulated instrument time, s".to_owned(),
        y_label: "RMS node K error, %".to_owned(),
        series,
        log_y: true,
        y_from_zero: false,
        size: (1000, 560),
    })
    .unwrap();
    save("xy-log.png", &bytes);
    let img = Image::decode(&bytes);
    // The markers (left half: the legend is on the right) spread over more than a fifth of
    // the figure's height.
    let rows_of = |k: usize| -> Vec<u32> {
        let c = spm_plot::category_colour(k);
        (0..img.h)
            .filter(|&y| (0..img.w / 2).any(|x| img.px(x, y) == [c.0, c.1, c.2]))
            .collect()
    };
    let (rows, rows5) = (rows_of(0), rows_of(5));
    let low = rows.iter().max().unwrap();
    let high = rows5.iter().min().unwrap();
    assert!(low - high > img.h / 5, "{low} {high}");
}

#[test]
fn category_chart_puts_categories_on_ticks_and_rejects_empty() {
    let categories: Vec<String> = ["sim-mild", "sim-typical", "sim-bad", "sim-bad + pauses"]
        .iter()
        .map(|s| (*s).to_owned())
        .collect();
    let bytes = category_chart(&CategoryFigure {
        title: "Residual distortion per method and scanner".to_owned(),
        x_label: "scanner configuration".to_owned(),
        categories: categories.clone(),
        y_label: "RMS residual distortion, pm".to_owned(),
        series: vec![
            CategorySeries {
                name: "uncorrected".to_owned(),
                values: vec![Some(900.0), Some(3000.0), Some(9000.0), Some(9100.0)],
            },
            CategorySeries {
                name: "distributed".to_owned(),
                values: vec![Some(3.0), Some(5.0), None, Some(40.0)],
            },
        ],
        log_y: true,
        size: (1000, 520),
    })
    .unwrap();
    save("category.png", &bytes);
    let img = Image::decode(&bytes);
    assert_eq!((img.w, img.h), (1000, 520));
    // Category labels below the plot: text in the bottom band.
    assert!(img.dark_pixels(img.h - 64..img.h - 20) > 300);
    let empty = category_chart(&CategoryFigure {
        title: "empty".to_owned(),
        x_label: "x".to_owned(),
        categories,
        y_label: "y".to_owned(),
        series: vec![CategorySeries {
            name: "nothing".to_owned(),
            values: vec![None, Some(f64::NAN), Some(-1.0), None],
        }],
        log_y: true,
        size: (400, 300),
    });
    assert!(matches!(empty, Err(spm_plot::PlotError::Empty { .. })));
}

#[test]
fn order_map_colours_by_order() {
    let points: Vec<(f64, f64)> = (0..25)
        .map(|k| (f64::from(k % 5) * 100.0, f64::from(k / 5) * 100.0))
        .collect();
    let bytes = order_map(&OrderFigure {
        title: "Nodes in visiting order".to_owned(),
        x_label: "x, counts".to_owned(),
        y_label: "y, counts".to_owned(),
        points,
        order_label: "visit number".to_owned(),
    })
    .unwrap();
    save("order.png", &bytes);
    let img = Image::decode(&bytes);
    assert_eq!((img.w, img.h), (860, 700));
    assert!(img.has_colour(ColorMap::Viridis.rgb(0.003), 6));
    assert!(img.has_colour(ColorMap::Viridis.rgb(0.997), 6));
}
