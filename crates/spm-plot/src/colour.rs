//! Colour maps from `colorous` (the d3-scale-chromatic ports of the matplotlib and
//! ColorBrewer schemes), so no colour table is written by hand.

use plotters::style::RGBColor;

/// Colour maps for surfaces and height images.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[non_exhaustive]
pub enum ColorMap {
    /// Black to white (colorous `GREYS`, reversed).
    Gray,
    /// Black – red – orange – yellow – white: the usual STM look (colorous `INFERNO`, the
    /// perceptually uniform member of the "hot" family; the previous hand-made "afmhot"
    /// ramps are gone).
    #[default]
    AfmHot,
    /// Dark blue – teal – green – yellow, perceptually uniform (colorous `VIRIDIS`).
    Viridis,
    /// Colour-vision-deficiency friendly blue – yellow (colorous `CIVIDIS`).
    Cividis,
    /// Diverging blue – white – red for signed quantities such as residuals (colorous
    /// `RED_BLUE`, reversed so that positive is red); 0.5 is white.
    Diverging,
}

impl ColorMap {
    /// The colour for `t` in [0, 1] (clamped; NaN gives the colour of 0).
    pub fn rgb(self, t: f64) -> [u8; 3] {
        let t = if t.is_finite() {
            t.clamp(0.0, 1.0)
        } else {
            0.0
        };
        let c = match self {
            ColorMap::Gray => colorous::GREYS.eval_continuous(1.0 - t),
            ColorMap::AfmHot => colorous::INFERNO.eval_continuous(t),
            ColorMap::Viridis => colorous::VIRIDIS.eval_continuous(t),
            ColorMap::Cividis => colorous::CIVIDIS.eval_continuous(t),
            ColorMap::Diverging => colorous::RED_BLUE.eval_continuous(1.0 - t),
        };
        [c.r, c.g, c.b]
    }

    /// [`ColorMap::rgb`] as a plotters colour.
    pub fn colour(self, t: f64) -> RGBColor {
        let [r, g, b] = self.rgb(t);
        RGBColor(r, g, b)
    }
}

/// The `k`-th colour of the categorical palette (colorous `TABLEAU10`, repeating).
pub fn category_colour(k: usize) -> RGBColor {
    let c = colorous::TABLEAU10[k % colorous::TABLEAU10.len()];
    RGBColor(c.r, c.g, c.b)
}
