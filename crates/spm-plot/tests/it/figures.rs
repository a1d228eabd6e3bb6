//! Every figure kind: PNG of the requested size, text drawn (title band not blank), the
//! colour bar spanning the colour map's ends, categories on their own ticks.
//! `SPM_PLOT_OUT=DIR` also writes the figures there, to look at.

#![allow(clippy::unwrap_used)]

use spm_plot::{
    CategoryFigure, CategorySeries, ColorMap, MAP_HEIGHT_PX, MAP_WIDTH_PX, MapFigure, MapNode,
    OrderFigure, OrderPanel, PanelGrid, Series, SeriesStyle, XyFigure, XyPanel, category_chart,
    category_colour, order_map, panel_grid, running_quantiles, surface_map, xy_chart,
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
                visit: 0,
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
    assert_eq!((img.w, img.h), (MAP_WIDTH_PX, MAP_HEIGHT_PX));
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

/// Pure-white pixels in rows `rows`.
fn white_pixels(img: &Image, rows: std::ops::Range<u32>) -> usize {
    rows.flat_map(|y| (0..img.w).map(move |x| (x, y)))
        .filter(|&(x, y)| img.px(x, y) == [255, 255, 255])
        .count()
}

/// The map figure of `surface` with `nodes` (value unit pm/count, position unit µm).
fn map_of(surface: &dyn Fn(f64, f64) -> f64, nodes: &[MapNode]) -> Image {
    let bytes = surface_map(&MapFigure {
        title: "Kx",
        x_label: "x on the field, µm",
        y_label: "y on the field, µm",
        x_range: (-1.0, 1.0),
        y_range: (-1.0, 1.0),
        surface,
        nodes,
        value_label: "Kx, pm/count",
        residual_label: "measured − surface, pm/count",
        map: ColorMap::Viridis,
    })
    .unwrap();
    save("surface-discs.png", &bytes);
    Image::decode(&bytes)
}

/// The nodes on the surface panel are discs filled with their value: drawing them over the
/// surface adds no white (the old markers were white rings around a small coloured dot,
/// which hid the value), and every node's fill colour appears.
#[test]
fn map_nodes_are_discs_filled_with_their_value() {
    let surface = |x: f64, y: f64| 20.0 + x - 0.5 * y;
    let mut nodes = Vec::new();
    for i in 0..4 {
        for j in 0..4 {
            let (x, y) = (-0.75 + 0.5 * f64::from(i), -0.75 + 0.5 * f64::from(j));
            nodes.push(MapNode {
                x,
                y,
                value: surface(x, y) + 0.2 * f64::from(i - j),
                visit: 0,
            });
        }
    }
    // The surface panel is the top half (title band included).
    let top = 0..MAP_HEIGHT_PX / 2;
    let bare = map_of(&surface, &[]);
    let with_nodes = map_of(&surface, &nodes);
    assert!(
        white_pixels(&with_nodes, top.clone()) <= white_pixels(&bare, top.clone()),
        "the node markers add white to the surface panel: {} > {}",
        white_pixels(&with_nodes, top.clone()),
        white_pixels(&bare, top)
    );
    // The value range is the nodes' extremes: both ends of the map fill a node.
    let lo = nodes.iter().map(|n| n.value).fold(f64::INFINITY, f64::min);
    let hi = nodes
        .iter()
        .map(|n| n.value)
        .fold(f64::NEG_INFINITY, f64::max);
    for n in &nodes {
        let t = (n.value - lo) / (hi - lo);
        assert!(
            with_nodes.has_colour(ColorMap::Viridis.rgb(t), 2),
            "node at ({}, {}) value {} not drawn in its colour",
            n.x,
            n.y,
            n.value
        );
    }
}

/// Two visits of one place are concentric discs: both values show (drawn at one radius, the
/// second visit hid the first).
#[test]
fn repeated_visits_of_a_place_are_concentric_and_both_show() {
    let surface = |_: f64, _: f64| 0.0;
    let nodes = [
        MapNode {
            x: 0.0,
            y: 0.0,
            value: -1.0,
            visit: 0,
        },
        MapNode {
            x: 0.0,
            y: 0.0,
            value: 1.0,
            visit: 1,
        },
    ];
    let img = map_of(&surface, &nodes);
    // Residuals ±1 are the diverging map's ends; the colour bar shows them too, so count
    // pixels against the bar alone (a figure without nodes has none of either end).
    let bare = map_of(&surface, &[]);
    for t in [0.0, 1.0] {
        let c = ColorMap::Diverging.rgb(t);
        assert!(
            count_colour(&img, c) > count_colour(&bare, c) + 20,
            "visit with residual {} hidden",
            2.0 * t - 1.0
        );
    }
}

/// Pixels exactly of `colour`.
fn count_colour(img: &Image, colour: [u8; 3]) -> usize {
    img.rgb
        .chunks_exact(3)
        .filter(|p| p[0] == colour[0] && p[1] == colour[1] && p[2] == colour[2])
        .count()
}

/// One panel per pass: three passes over the same nodes show three times the markers of
/// one pass (drawn into one panel, the last pass hid the two before it).
#[test]
fn order_map_draws_every_pass_in_its_own_panel() {
    let points: Vec<(f64, f64)> = (0..25)
        .map(|k| (f64::from(k % 5) * 100.0, f64::from(k / 5) * 100.0))
        .collect();
    let draw = |passes: usize| {
        let panels = (0..passes)
            .map(|p| OrderPanel {
                caption: format!("pass {}", p + 1),
                points: points.clone(),
            })
            .collect();
        let bytes = order_map(&OrderFigure {
            title: "Nodes in visiting order".to_owned(),
            x_label: "x, µm".to_owned(),
            y_label: "y, µm".to_owned(),
            panels,
            order_label: "visit number within the pass".to_owned(),
        })
        .unwrap();
        save(&format!("order-{passes}.png"), &bytes);
        Image::decode(&bytes)
    };
    let one = draw(1);
    let three = draw(3);
    assert_eq!((three.w, three.h), (2 * 430 + 130, 2 * 400 + 40));
    assert!(one.has_colour(ColorMap::Viridis.rgb(0.003), 6));
    assert!(one.has_colour(ColorMap::Viridis.rgb(0.997), 6));
    // The last visit's colour, exactly (the colour bar's steps are mid-step colours).
    let last = ColorMap::Viridis.rgb(1.0);
    let (n1, n3) = (count_colour(&one, last), count_colour(&three, last));
    assert!(n1 > 0);
    assert!(
        n3 >= 3 * n1 - 2 * n1 / 10,
        "three passes draw {n3} pixels of the last visit's colour, one pass {n1}"
    );
}

/// The running quantiles against a closed form: in every bin y runs over 0, 1, …, 99 once,
/// so (type 7) the median is 49.5 and the 16 % and 84 % quantiles are 0.16·99 and 0.84·99.
#[test]
fn running_quantiles_match_the_closed_form() {
    let points: Vec<(f64, f64)> = (0..1000)
        .map(|i| (f64::from(i), f64::from((i * 37) % 100)))
        .collect();
    let q = running_quantiles(&points, 10, 5, &[0.16, 0.5, 0.84]);
    assert_eq!(q.len(), 10);
    for (k, (x, v)) in q.iter().enumerate() {
        let centre = 999.0 / 10.0 * (k as f64 + 0.5);
        assert!((x - centre).abs() < 1e-9, "bin {k} centre {x} vs {centre}");
        for (got, want) in v.iter().zip([0.16 * 99.0, 49.5, 0.84 * 99.0]) {
            assert!((got - want).abs() < 1e-9, "bin {k}: {got} vs {want}");
        }
    }
    // A bin with fewer than `min_count` points is left out; non-finite points are skipped.
    let sparse = [(0.0, 1.0), (1.0, f64::NAN), (10.0, 2.0), (10.0, 4.0)];
    let q = running_quantiles(&sparse, 2, 2, &[0.5]);
    assert_eq!(q, vec![(7.5, vec![3.0])]);
    assert!(running_quantiles(&[], 4, 1, &[0.5]).is_empty());
}

/// A panel grid (the model check's residual figure): the requested size, the title and the
/// notes drawn in the header band, each panel's dots in its series' colour, and a panel with
/// nothing to draw saying so instead of failing the figure; no panel at all is an error.
#[test]
fn a_panel_grid_draws_its_header_and_every_panel() {
    let dots = |name: &str, k: f64| Series {
        name: name.to_owned(),
        points: (0..400)
            .map(|i| (f64::from(i), k * (f64::from(i) * 0.05).sin()))
            .collect(),
        style: SeriesStyle::Dots,
    };
    let panel = |title: &str, series: Vec<Series>| XyPanel {
        title: title.to_owned(),
        x_label: "time / s".to_owned(),
        y_label: "residual / pm".to_owned(),
        series,
        zero_line: true,
        y_from_zero: false,
    };
    let grid = PanelGrid {
        title: "residuals".to_owned(),
        notes: vec![
            "baseline 10 pm → final 2 pm".to_owned(),
            "found: none".to_owned(),
        ],
        columns: 2,
        panels: vec![
            panel("x and y", vec![dots("x", 100.0), dots("y", -50.0)]),
            panel("empty", vec![]),
            panel("only y", vec![dots("y", 20.0)]),
        ],
        size: (1000, 700),
    };
    let png = panel_grid(&grid).unwrap();
    save("panel-grid.png", &png);
    let image = Image::decode(&png);
    assert_eq!((image.w, image.h), (1000, 700));
    assert!(image.dark_pixels(0..30) > 100, "no title drawn");
    assert!(image.dark_pixels(40..90) > 200, "no notes drawn");
    let blue = category_colour(0);
    assert!(
        image.has_colour([blue.0, blue.1, blue.2], 40),
        "the first series is not drawn"
    );
    let empty = PanelGrid {
        panels: Vec::new(),
        ..grid
    };
    assert!(panel_grid(&empty).is_err());
}
