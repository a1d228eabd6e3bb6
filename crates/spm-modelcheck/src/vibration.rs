//! A lateral vibration modelled where it acts: on every pixel's height, not only on the
//! feature positions (issue 29 item 1; the selection's side is `diagnose/pixels.rs`).
//!
//! A feature's fitted position averages the tip's motion over the lines of its footprint,
//! and the features sample time once per line: a vibration whose phase advances about half
//! a cycle per line averages out inside each atom (the features only broaden), and any
//! other is seen at an alias modulo the line rate. Each pixel is sampled at its own time,
//! densely along its line. So, on the levelled images of both directions of every frame:
//!
//! 1. **Template.** Each image's lattice template is Σ_G a_G·cos 2πG·R(u) + b_G·sin 2πG·R(u)
//!    over the lattice's harmonics G (shells 1, √3, 2, below the pixel Nyquist frequency),
//!    R(u) a lattice map from the commanded position u to the lattice frame; the a, b
//!    are fitted to the image's heights modulo each line's offset and slope (the lines
//!    were levelled so; `detrend_lines`).
//! 2. **Model.** A tip displacement δu(t) (nominal nm, scan axes) shows as z = T(u + δu(t)):
//!    linearised, the residual e = z − T(u) is ∇T·δu, regressed on the template's
//!    gradient × cos/sin 2πf·t, t each pixel's own acquisition time.
//! 3. **Search** (`candidate`), against the baseline's rigid map R = J₀·u + v·(t − t₀)
//!    (affine within an image, so it absorbs none of a vibration): from two cycles per
//!    frame to half the pixel rate, first coherently within each image and summed over
//!    images (on a grid of a quarter of one image's resolution; the phase between frames
//!    tens of seconds apart would make a coherent grid miss the fringe), then coherently
//!    over all images around the five best peaks, then by exact least squares. Each line's
//!    sum Σ e·∇T·e^{iω(t − t_line)} is computed once on a sub-grid of 1/(8 line durations)
//!    (a frequency then costs one rotation per line, not one per pixel). Frequencies within
//!    2/span of a harmonic of the line rate are scan-synchronous (the same in every line)
//!    and left out, as at the feature level.
//! 4. **Fit** (`assess`), against each image's own polynomial lattice map (degree ≤ 5,
//!    fitted to its features' sites): the vibration's map from the features without what
//!    they see of it, the static model's from the features as they are (which follows a
//!    nonlinearity, a sine drive, a trace/retrace loop, a shear gradient). The frequency is
//!    re-chosen within the alias family and its amplitude fitted on the exact template
//!    (`exact_fit`: a displacement of 30 pm is g·δ ≈ 1 rad on graphite, where the linear
//!    response saturates and the template fitted to a vibrating image is washed out: +15 %
//!    in the amplitude otherwise).
//! 5. **Alias family**: the named frequency ± one and two line rates, and its mirrors about
//!    the pixel rate, each with its evidence gap N·ln(RSS_member/RSS_named). The line rate
//!    folds a frequency for the features, not for the pixels of a line (gaps of 10³–10⁵
//!    on the generator); the pixel clock folds it exactly when all pixels sit on one dwell
//!    grid (gap ≈ 0: the member within half the pixel rate is named).
//!
//! Its evidence (ΔBIC over the pixels against the static model, with the search's
//! look-elsewhere count), *coherence* (what one sinusoid explains in every image over
//! what separate ones per image explain beyond their noise) and two-fold held-out RMS of
//! the height residual (alternate lines) are judged in `diagnose/pixels.rs`.

use crate::types::LineDirection;

/// One pixel: its time, place and levelled height.
#[derive(Clone, Copy, Debug)]
struct Sample {
    /// Time from its line's centre, s.
    dt_s: f64,
    /// Commanded position (nominal nm from the frame centre, y up).
    u_nm: [f64; 2],
    /// The levelled height, in the image's height unit (pm for a file in m).
    height: f64,
}

/// One scan line of one image.
#[derive(Clone, Debug)]
struct Line {
    /// Its centre time on the features' time axis, s.
    t_centre_s: f64,
    /// Parity of its acquisition line (the held-out folds).
    parity: usize,
    samples: Vec<Sample>,
}

/// The pixels of one lattice image (one direction of one frame) for the pixel-level
/// vibration search: every scanned pixel's place, acquisition time and levelled height.
/// Built by the image reader ([`crate::diagnose`]) or from a height map
/// ([`crate::pixel_image_from_height_map`]).
#[derive(Clone, Debug)]
pub struct PixelImage {
    frame: usize,
    direction: LineDirection,
    lines: Vec<Line>,
    pixel_nm: [f64; 2],
}

/// The template's height and gradient (per nominal nm) at a commanded position u:
/// Σ_G a·cos 2πG·R(u) + b·sin 2πG·R(u), R the image's lattice map.
fn template_at(tpl: &ImageTemplate, coefficients: &[f64], u: [f64; 2]) -> (f64, [f64; 2]) {
    let tau = std::f64::consts::TAU;
    let r = [
        tpl.map[0].evaluate(u[0], u[1]),
        tpl.map[1].evaluate(u[0], u[1]),
    ];
    let (dx, dy) = (
        tpl.map[0].gradient(u[0], u[1]),
        tpl.map[1].gradient(u[0], u[1]),
    );
    let (mut t, mut g) = (0.0, [0.0, 0.0]);
    let mut phasors = Vec::with_capacity(tpl.harmonics.len());
    tpl.harmonics.phasors(r, &mut phasors);
    for (j, (h, &(s, co))) in tpl.harmonics.vectors.iter().zip(&phasors).enumerate() {
        let (a, b) = (coefficients[2 * j], coefficients[2 * j + 1]);
        t += a * co + b * s;
        let d = tau * (-a * s + b * co);
        g[0] += d * (h[0] * dx.0 + h[1] * dy.0);
        g[1] += d * (h[0] * dx.1 + h[1] * dy.1);
    }
    (t, g)
}

impl PixelImage {
    /// The pixels of a levelled image `z` (row-major, row index growing with y; `bad` not
    /// scanned); `pixel_nm` the pitch; `time_and_line` the time (s) and acquisition line of
    /// a (column, row). `None` when fewer than 4 lines have 8 pixels.
    pub(crate) fn new(
        (frame, direction): (usize, LineDirection),
        (z, bad, nx, ny): (&[f64], &[bool], usize, usize),
        pixel_nm: [f64; 2],
        time_and_line: &dyn Fn(f64, f64) -> (f64, usize),
    ) -> Option<Self> {
        if !(pixel_nm[0] > 0.0 && pixel_nm[1] > 0.0) {
            return None;
        }
        let mut lines = Vec::new();
        for r in 0..ny {
            let mut samples = Vec::with_capacity(nx);
            let mut parity = 0;
            for c in 0..nx {
                let k = r * nx + c;
                if bad.get(k).copied().unwrap_or(true) || !z.get(k).is_some_and(|v| v.is_finite()) {
                    continue;
                }
                let (time_s, line) = time_and_line(c as f64, r as f64);
                parity = line % 2;
                samples.push(Sample {
                    dt_s: time_s,
                    u_nm: [
                        (c as f64 - 0.5 * (nx as f64 - 1.0)) * pixel_nm[0],
                        (r as f64 - 0.5 * (ny as f64 - 1.0)) * pixel_nm[1],
                    ],
                    height: z[k],
                });
            }
            if samples.len() < 8 || samples.iter().any(|s| !s.dt_s.is_finite()) {
                continue;
            }
            let t_centre_s = samples.iter().map(|s| s.dt_s).sum::<f64>() / samples.len() as f64;
            for s in &mut samples {
                s.dt_s -= t_centre_s;
            }
            lines.push(Line {
                t_centre_s,
                parity,
                samples,
            });
        }
        (lines.len() >= 4).then_some(Self {
            frame,
            direction,
            lines,
            pixel_nm,
        })
    }

    /// The frame and line direction of the image.
    pub fn frame_and_direction(&self) -> (usize, LineDirection) {
        (self.frame, self.direction)
    }
}

/// The lattice's harmonics G = m·b₁ + n·b₂ (b the reciprocal basis, cycles per nm,
/// lattice frame), one of each ± pair, with their orders (m, n): e^{2πi·G·R} is then
/// formed from the two basis phasors' powers, not a `sin_cos` per harmonic (the templates
/// are evaluated at every pixel of every fit).
#[derive(Clone, Debug, Default)]
pub(crate) struct Harmonics {
    basis: [[f64; 2]; 2],
    orders: Vec<[i32; 2]>,
    vectors: Vec<[f64; 2]>,
}

/// The largest |m|, |n| of [`lattice_harmonics`].
const MAX_ORDER: i32 = 4;

impl Harmonics {
    fn len(&self) -> usize {
        self.orders.len()
    }

    fn is_empty(&self) -> bool {
        self.orders.is_empty()
    }

    /// (sin, cos) of 2π·G·R for each harmonic, into `out`.
    fn phasors(&self, r: [f64; 2], out: &mut Vec<(f64, f64)>) {
        let tau = std::f64::consts::TAU;
        let [b1, b2] = self.basis;
        let unit = |b: [f64; 2]| (tau * (b[0] * r[0] + b[1] * r[1])).sin_cos();
        // Powers −MAX … MAX of each basis phasor, as (sin, cos).
        let powers = |(s, c): (f64, f64)| {
            let mut p = [(0.0, 1.0); (2 * MAX_ORDER + 1) as usize];
            let mid = MAX_ORDER as usize;
            for k in 1..=mid {
                let (ps, pc) = p[mid + k - 1];
                p[mid + k] = (ps * c + pc * s, pc * c - ps * s);
                p[mid - k] = (-p[mid + k].0, p[mid + k].1);
            }
            p
        };
        let (p1, p2) = (powers(unit(b1)), powers(unit(b2)));
        out.clear();
        out.extend(self.orders.iter().map(|&[m, n]| {
            let (s1, c1) = p1[(m + MAX_ORDER) as usize];
            let (s2, c2) = p2[(n + MAX_ORDER) as usize];
            (s1 * c2 + c1 * s2, c1 * c2 - s1 * s2)
        }));
    }
}

/// The lattice's harmonics G = m·b₁ + n·b₂ (b the reciprocal basis of `basis_nm`, cycles
/// per nm) out to twice the longer of b₁, b₂ (a triangular lattice's shells 1, √3, 2), one
/// of each ± pair.
pub(crate) fn lattice_harmonics(basis_nm: [[f64; 2]; 2]) -> Harmonics {
    let [a1, a2] = basis_nm;
    let det = a1[0] * a2[1] - a1[1] * a2[0];
    if det.abs() < 1e-300 {
        return Harmonics::default();
    }
    let b1 = [a2[1] / det, -a2[0] / det];
    let b2 = [-a1[1] / det, a1[0] / det];
    let limit = 2.05 * b1[0].hypot(b1[1]).max(b2[0].hypot(b2[1]));
    let mut out = Harmonics {
        basis: [b1, b2],
        ..Harmonics::default()
    };
    for m in -MAX_ORDER..=MAX_ORDER {
        for n in -MAX_ORDER..=MAX_ORDER {
            let g = [
                f64::from(m) * b1[0] + f64::from(n) * b2[0],
                f64::from(m) * b1[1] + f64::from(n) * b2[1],
            ];
            let len = g[0].hypot(g[1]);
            let upper = g[1] > 0.0 || (g[1] == 0.0 && g[0] > 0.0);
            if len > 1e-12 && len <= limit && upper {
                out.orders.push([m, n]);
                out.vectors.push(g);
            }
        }
    }
    out
}

/// The lattice map of one image: its features' sites R (lattice frame, nm) as polynomials
/// of their commanded positions u (x and y of R).
pub(crate) type ImageMap = [spm_regression::Polynomial2; 2];

/// One image's lattice template: the harmonics below the pixel Nyquist frequency (at the
/// image's centre), the map, and the harmonics' cos/sin coefficients.
#[derive(Clone, Debug)]
struct ImageTemplate {
    map: ImageMap,
    harmonics: Harmonics,
    coefficients: Vec<f64>,
}

impl ImageTemplate {
    fn new(map: &ImageMap, harmonics: &Harmonics, pixel_nm: [f64; 2]) -> Self {
        let (dx, dy) = (map[0].gradient(0.0, 0.0), map[1].gradient(0.0, 0.0));
        let below_nyquist = |h: &[f64; 2]| {
            let k = [
                (h[0] * dx.0 + h[1] * dy.0) * pixel_nm[0],
                (h[0] * dx.1 + h[1] * dy.1) * pixel_nm[1],
            ];
            k[0].abs() < 0.5 && k[1].abs() < 0.5
        };
        let mut kept = Harmonics {
            basis: harmonics.basis,
            ..Harmonics::default()
        };
        for (order, h) in harmonics.orders.iter().zip(&harmonics.vectors) {
            if below_nyquist(h) {
                kept.orders.push(*order);
                kept.vectors.push(*h);
            }
        }
        Self {
            map: map.clone(),
            coefficients: vec![0.0; 2 * kept.len()],
            harmonics: kept,
        }
    }
}

/// What the search reads besides the images.
pub(crate) struct SearchSpace<'a> {
    /// Time 0 of the fit (the diagnosis's time origin), s on the features' axis.
    pub t_origin_s: f64,
    /// The longest frame, s (a vibration completes two cycles in it).
    pub longest_frame_s: f64,
    /// Line rates of the frames (lines per frame duration), Hz.
    pub line_frequencies_hz: &'a [f64],
    /// The lattice's harmonics (cycles per nm, lattice frame).
    pub harmonics: Harmonics,
}

/// One member of the named frequency's alias family.
#[derive(Clone, Copy, Debug)]
pub(crate) struct AliasMember {
    pub frequency_hz: f64,
    /// N·ln(RSS_member / RSS_named): how much less the member explains (≈ 0: not told apart).
    pub evidence_gap: f64,
}

/// The pixel-level vibration fit.
#[derive(Clone, Debug)]
pub(crate) struct PixelFit {
    pub frequency_hz: f64,
    /// x cos, x sin, y cos, y sin of the input displacement (nominal nm), t from the origin.
    pub coefficients_nm: [f64; 4],
    /// Their covariance (scaled by the residual variance), nm².
    pub covariance_nm2: [[f64; 4]; 4],
    /// RSS without and with the vibration (height unit²), and the pixels.
    pub rss: [f64; 2],
    pub pixels: usize,
    pub images: usize,
    /// Independent frequencies searched (the look-elsewhere count).
    pub trials: f64,
    pub aliases: Vec<AliasMember>,
    /// Joint explained sum of squares over the sum of the images' separate ones (beyond
    /// their noise).
    pub coherence: f64,
    /// Held-out RMS of the height residual without and with the vibration (height unit).
    pub heldout_rms: [f64; 2],
}

/// The samples flattened: time from the origin, place, height, residual against the
/// template, the template's gradients, image, line parity; and the images' templates.
struct Flat {
    t: Vec<f64>,
    u: Vec<[f64; 2]>,
    z: Vec<f64>,
    e: Vec<f64>,
    g: [Vec<f64>; 2],
    image: Vec<usize>,
    parity: Vec<usize>,
    /// Each line's samples (contiguous).
    lines: Vec<std::ops::Range<usize>>,
    /// Each image's samples and lines (contiguous).
    image_samples: Vec<std::ops::Range<usize>>,
    image_lines: Vec<std::ops::Range<usize>>,
    templates: Vec<ImageTemplate>,
}

impl Flat {
    /// The images' pixels, each image's template fitted at rest (its lines' offsets and
    /// slopes with it), the residuals and the gradients.
    fn new(images: &[(&PixelImage, &ImageMap)], t0: f64, harmonics: &Harmonics) -> Self {
        let mut f = Flat {
            lines: Vec::new(),
            image_samples: Vec::new(),
            image_lines: Vec::new(),
            t: Vec::new(),
            u: Vec::new(),
            z: Vec::new(),
            e: Vec::new(),
            g: [Vec::new(), Vec::new()],
            image: Vec::new(),
            parity: Vec::new(),
            templates: images
                .iter()
                .map(|(img, map)| ImageTemplate::new(map, harmonics, img.pixel_nm))
                .collect(),
        };
        for (i, (img, _)) in images.iter().enumerate() {
            let (first_sample, first_line) = (f.t.len(), f.lines.len());
            for line in &img.lines {
                f.lines.push(f.t.len()..f.t.len() + line.samples.len());
                for s in &line.samples {
                    f.t.push(line.t_centre_s + s.dt_s - t0);
                    f.u.push(s.u_nm);
                    f.z.push(s.height);
                    f.image.push(i);
                    f.parity.push(line.parity);
                }
            }
            f.image_samples.push(first_sample..f.t.len());
            f.image_lines.push(first_line..f.lines.len());
        }
        let n = f.t.len();
        let rest = (0.0, &[0.0; 4]);
        let mut target = f.z.clone();
        f.detrend_lines(&mut target);
        let coefficients = f.refit_templates(rest, &vec![true; n], &target);
        for (t, c) in f.templates.iter_mut().zip(coefficients) {
            t.coefficients = c;
        }
        let templates: Vec<Vec<f64>> = f.templates.iter().map(|t| t.coefficients.clone()).collect();
        f.e = f.exact_residual(&templates, rest);
        for k in 0..n {
            let g = f.displaced(&templates, rest, k).1;
            f.g[0].push(g[0]);
            f.g[1].push(g[1]);
        }
        f
    }

    /// The four columns at frequency `f_hz`.
    fn columns(&self, f_hz: f64) -> Vec<Vec<f64>> {
        let w = std::f64::consts::TAU * f_hz;
        let n = self.t.len();
        let mut cols = vec![vec![0.0; n]; 4];
        for (k, t) in self.t.iter().enumerate() {
            let (s, c) = (w * t).sin_cos();
            cols[0][k] = self.g[0][k] * c;
            cols[1][k] = self.g[0][k] * s;
            cols[2][k] = self.g[1][k] * c;
            cols[3][k] = self.g[1][k] * s;
        }
        cols
    }

    /// The least-squares fit at `f_hz` over `included`: coefficients, covariance, RSS.
    fn fit(&self, f_hz: f64, included: &[bool]) -> Option<spm_regression::MinimumNormFit> {
        spm_regression::minimum_norm_least_squares(&self.columns(f_hz), &self.e, included)
            .ok()
            .filter(|f| f.rss.is_finite() && f.coefficients.len() == 4)
    }

    fn rss0(&self, included: &[bool]) -> f64 {
        self.e
            .iter()
            .zip(included)
            .filter(|(_, i)| **i)
            .map(|(e, _)| e * e)
            .sum()
    }
}

/// Gauss–Newton rounds of the exact fit.
const ROUNDS: usize = 3;

/// The vibration fitted on the exact template: a displacement of a few tens of pm is a
/// sizeable fraction of a lattice period (g·δ ≈ 1 rad for 35 pm on graphite), where the
/// linear response saturates (as 2·J₁(gδ)/g) and the template fitted to the vibrating
/// image is itself washed out (by J₀(gδ) per harmonic): together a bias of +15 % in the
/// amplitude. So, from the linear solution, `ROUNDS` times: each image's template
/// coefficients are refitted at the displaced places p + δ(t), then the displacement's
/// four coefficients take a Gauss–Newton step on the residual z − T(p + δ(t)).
struct Exact {
    coefficients: [f64; 4],
    covariance: [[f64; 4]; 4],
    /// RSS over the included samples.
    rss: f64,
    /// Each image's refitted template coefficients.
    templates: Vec<Vec<f64>>,
}

impl Flat {
    /// The displaced commanded position of sample `k` (nominal nm).
    fn displaced_u(&self, w: f64, c: &[f64; 4], k: usize) -> [f64; 2] {
        let (s, co) = (w * self.t[k]).sin_cos();
        [
            self.u[k][0] + c[0] * co + c[1] * s,
            self.u[k][1] + c[2] * co + c[3] * s,
        ]
    }

    /// The template of sample `k` (coefficients `templates`) at its displaced place: the
    /// height and the gradient per nm of input.
    fn displaced(
        &self,
        templates: &[Vec<f64>],
        (w, c): (f64, &[f64; 4]),
        k: usize,
    ) -> (f64, [f64; 2]) {
        let u = self.displaced_u(w, c, k);
        template_at(&self.templates[self.image[k]], &templates[self.image[k]], u)
    }

    /// Removes from `v` each line's least-squares offset and slope along the line: the
    /// lines were levelled jointly with the template, so every model of the heights is
    /// compared modulo a line's offset and slope (Frisch–Waugh: the same as fitting them).
    fn detrend_lines(&self, v: &mut [f64]) {
        for range in &self.lines {
            self.detrend_line(range.clone(), &mut v[range.clone()]);
        }
    }

    /// [`Self::detrend_lines`] over image `i`'s samples only (`v` indexed from its first).
    fn detrend_image(&self, i: usize, v: &mut [f64]) {
        let start = self.image_samples[i].start;
        for range in &self.lines[self.image_lines[i].clone()] {
            self.detrend_line(
                range.clone(),
                &mut v[range.start - start..range.end - start],
            );
        }
    }

    /// One line's (samples `range`) offset and slope removed from `v`.
    fn detrend_line(&self, range: std::ops::Range<usize>, v: &mut [f64]) {
        let m = range.len() as f64;
        if m < 3.0 {
            return;
        }
        let xs = &self.u[range];
        let mean_x = xs.iter().map(|p| p[0]).sum::<f64>() / m;
        let (mut sxx, mut sxv, mut sv) = (0.0, 0.0, 0.0);
        for (p, val) in xs.iter().zip(v.iter()) {
            let dx = p[0] - mean_x;
            sxx += dx * dx;
            sxv += dx * val;
            sv += val;
        }
        let (mean_v, slope) = (sv / m, if sxx > 0.0 { sxv / sxx } else { 0.0 });
        for (p, val) in xs.iter().zip(v.iter_mut()) {
            *val -= mean_v + slope * (p[0] - mean_x);
        }
    }

    /// The residual z − T(p + δ(t)) with each line's offset and slope removed.
    fn exact_residual(&self, templates: &[Vec<f64>], (w, c): (f64, &[f64; 4])) -> Vec<f64> {
        let mut r: Vec<f64> = (0..self.t.len())
            .map(|k| self.z[k] - self.displaced(templates, (w, c), k).0)
            .collect();
        self.detrend_lines(&mut r);
        r
    }

    /// Each image's template coefficients fitted to `target` (the heights, detrended per
    /// line) at the places displaced by the vibration (w, c), over `included`.
    fn refit_templates(
        &self,
        (w, c): (f64, &[f64; 4]),
        included: &[bool],
        target: &[f64],
    ) -> Vec<Vec<f64>> {
        self.templates
            .iter()
            .enumerate()
            .map(|(i, tpl)| {
                let range = self.image_samples[i].clone();
                let rows = &included[range.clone()];
                let m = tpl.harmonics.len();
                if m == 0 || rows.iter().filter(|r| **r).count() < 8 * m {
                    return tpl.coefficients.clone();
                }
                let mut cols = vec![vec![0.0; range.len()]; 2 * m];
                let mut phasors = Vec::with_capacity(m);
                for (row, k) in range.clone().enumerate() {
                    let u = self.displaced_u(w, c, k);
                    let r = [
                        tpl.map[0].evaluate(u[0], u[1]),
                        tpl.map[1].evaluate(u[0], u[1]),
                    ];
                    tpl.harmonics.phasors(r, &mut phasors);
                    for (j, &(sn, cs)) in phasors.iter().enumerate() {
                        cols[2 * j][row] = cs;
                        cols[2 * j + 1][row] = sn;
                    }
                }
                for col in &mut cols {
                    self.detrend_image(i, col);
                }
                spm_regression::minimum_norm_least_squares(&cols, &target[range], rows)
                    .map_or_else(|_| tpl.coefficients.clone(), |fit| fit.coefficients)
            })
            .collect()
    }

    fn exact_fit(&self, f_hz: f64, start: [f64; 4], included: &[bool]) -> Option<Exact> {
        let w = std::f64::consts::TAU * f_hz;
        let n = self.t.len();
        let mut c = start;
        let mut templates: Vec<Vec<f64>>;
        let mut target = self.z.clone();
        self.detrend_lines(&mut target);
        let mut last = None;
        for _ in 0..ROUNDS {
            templates = self.refit_templates((w, &c), included, &target);
            let mut cols = vec![vec![0.0; n]; 4];
            let mut r = vec![0.0; n];
            for k in (0..n).filter(|&k| included[k]) {
                let (t, g) = self.displaced(&templates, (w, &c), k);
                let (sn, cs) = (w * self.t[k]).sin_cos();
                r[k] = self.z[k] - t;
                cols[0][k] = g[0] * cs;
                cols[1][k] = g[0] * sn;
                cols[2][k] = g[1] * cs;
                cols[3][k] = g[1] * sn;
            }
            self.detrend_lines(&mut r);
            for col in &mut cols {
                self.detrend_lines(col);
            }
            let step = spm_regression::minimum_norm_least_squares(&cols, &r, included).ok()?;
            let mut covariance = [[0.0; 4]; 4];
            for (a, row) in covariance.iter_mut().enumerate() {
                c[a] += step.coefficients.get(a).copied().unwrap_or(0.0);
                for (b, v) in row.iter_mut().enumerate() {
                    *v = step
                        .covariance
                        .get(a)
                        .and_then(|r| r.get(b))
                        .copied()
                        .unwrap_or(f64::NAN);
                }
            }
            last = Some(covariance);
        }
        let covariance = last?;
        let templates = self.refit_templates((w, &c), included, &target);
        let r = self.exact_residual(&templates, (w, &c));
        let rss = (0..n).filter(|&k| included[k]).map(|k| r[k] * r[k]).sum();
        Some(Exact {
            coefficients: c,
            covariance,
            rss,
            templates,
        })
    }
}

/// Per line and axis, Σ e·g·e^{iω·dt} (dt from the line's centre) on the sub-grid
/// `f0 + j·step` (j < n), as (re, im) pairs: `[line][j][axis]` flattened (a sample's
/// frequencies contiguous).
fn line_sums(flat: &Flat, centres: &[f64], f0: f64, step: f64, n: usize) -> Vec<[f64; 2]> {
    const RESYNC: usize = 64;
    let tau = std::f64::consts::TAU;
    let nl = flat.lines.len();
    // Pixels LANES at a time: each pixel's phasor is a chain of rotations (one multiply-add
    // latency per frequency), and independent chains side by side keep the core busy. The
    // sums take the pixels' terms in the pixels' order, as one pixel at a time would.
    const LANES: usize = 4;
    let mut out = vec![[0.0; 2]; n * nl * 2];
    for (l, range) in flat.lines.iter().enumerate() {
        let pixels: Vec<usize> = range.clone().collect();
        for chunk in pixels.chunks(LANES) {
            let lanes = chunk.len();
            let (mut rot, mut w, mut dt) = ([(0.0, 0.0); LANES], [[0.0; 2]; LANES], [0.0; LANES]);
            for (p, &k) in chunk.iter().enumerate() {
                dt[p] = flat.t[k] - centres[l];
                rot[p] = (tau * step * dt[p]).sin_cos();
                w[p] = [flat.e[k] * flat.g[0][k], flat.e[k] * flat.g[1][k]];
            }
            for block in (0..n).step_by(RESYNC) {
                let f = f0 + block as f64 * step;
                let mut phasor = [(0.0, 0.0); LANES];
                for p in 0..lanes {
                    phasor[p] = (tau * f * dt[p]).sin_cos();
                }
                for j in block..(block + RESYNC).min(n) {
                    let base = (l * n + j) * 2;
                    for p in 0..lanes {
                        let (sn, cs) = phasor[p];
                        for a in 0..2 {
                            out[base + a][0] += w[p][a] * cs;
                            out[base + a][1] += w[p][a] * sn;
                        }
                        let (ds, dc) = rot[p];
                        phasor[p] = (sn * dc + cs * ds, cs * dc - sn * ds);
                    }
                }
            }
        }
    }
    out
}

/// The search's grids and the lines' sums.
struct Spectrum {
    /// Each line's centre time (from the origin) and image.
    centres: Vec<f64>,
    image_of: Vec<usize>,
    sums: Vec<[f64; 2]>,
    sub_f0: f64,
    sub_step: f64,
    sub_n: usize,
    /// Σ g_a²/2 over all samples, per axis.
    norm: [f64; 2],
}

impl Spectrum {
    /// The power at `f_hz`: Σ over axes of |Σ_lines e^{iωt_line}·S_line(f)|²/norm, summed
    /// over images when `per_image` (coherent within each image), else coherent over all.
    fn power(&self, f_hz: f64, per_image: bool, n_images: usize) -> f64 {
        let w = std::f64::consts::TAU * f_hz;
        let phasors: Vec<(f64, f64)> = self.centres.iter().map(|c| (w * c).sin_cos()).collect();
        self.power_with(f_hz, &phasors, per_image, n_images)
    }

    /// [`Self::power`] with each line's e^{iω·t_line} given as (sin, cos).
    fn power_with(
        &self,
        f_hz: f64,
        phasors: &[(f64, f64)],
        per_image: bool,
        n_images: usize,
    ) -> f64 {
        let j = ((f_hz - self.sub_f0) / self.sub_step).round();
        if !(j >= 0.0 && (j as usize) < self.sub_n) {
            return 0.0;
        }
        let j = j as usize;
        let groups = if per_image { n_images } else { 1 };
        let mut acc = vec![[[0.0; 2]; 2]; groups];
        for (l, &(s, c)) in phasors.iter().enumerate() {
            let g = if per_image { self.image_of[l] } else { 0 };
            for (a, sum) in acc[g].iter_mut().enumerate() {
                let v = self.sums[(l * self.sub_n + j) * 2 + a];
                sum[0] += v[0] * c - v[1] * s;
                sum[1] += v[0] * s + v[1] * c;
            }
        }
        acc.iter()
            .map(|g| {
                (0..2)
                    .map(|a| (g[a][0].powi(2) + g[a][1].powi(2)) / self.norm[a].max(1e-300))
                    .sum::<f64>()
            })
            .sum()
    }
}

/// Whether `f` is within `width` of a harmonic of a line rate (scan-synchronous).
fn synchronous(f: f64, line_frequencies_hz: &[f64], width: f64) -> bool {
    line_frequencies_hz.iter().any(|fl| {
        let k = (f / fl).round();
        k >= 1.0 && (f - k * fl).abs() < width
    })
}

/// The highest local maxima of `power` on a grid, best first.
fn top_peaks(grid: &[(f64, f64)], count: usize) -> Vec<f64> {
    let mut peaks: Vec<(f64, f64)> = (0..grid.len())
        .filter(|&i| {
            let p = grid[i].1;
            (i == 0 || grid[i - 1].1 <= p) && (i + 1 == grid.len() || grid[i + 1].1 <= p)
        })
        .map(|i| grid[i])
        .collect();
    peaks.sort_by(|a, b| b.1.total_cmp(&a.1));
    peaks.into_iter().take(count).map(|p| p.0).collect()
}

/// The coherent (all-image) power's maximum within ±`half` of `f`, on a step of `step`.
fn refine(spec: &Spectrum, f: f64, half: f64, step: f64) -> f64 {
    let n = (half / step).ceil() as i64;
    let mut best = (f, spec.power(f, false, 1));
    for i in -n..=n {
        let g = f + i as f64 * step;
        let p = spec.power(g, false, 1);
        if p > best.1 {
            best = (g, p);
        }
    }
    best.0
}

/// Most sub-grid line sums kept (memory) and most grid-point × line products (time).
const MAX_SUMS: usize = 40_000_000;
const MAX_GRID_WORK: usize = 200_000_000;

/// Searches the vibration over the images' pixels; `None` when there is nothing to
/// search (fewer than two images, or no frequency range).
/// The search's outcome on one set of templates: the best frequency, its alias family,
/// the trials it stands for, and the highest frequency searched.
#[derive(Clone, Debug)]
pub(crate) struct Candidate {
    pub frequency_hz: f64,
    /// The RSS without and with the linear fit at it, and the pixels.
    pub linear_rss: [f64; 2],
    pub pixels: usize,
    family: Vec<f64>,
    pub trials: f64,
    f_max: f64,
}

/// The affine lattice map of an image from the baseline: R = J₀·u + v·(t(u) − t₀), t(u)
/// the image's pixel times (affine in u within an image), as degree-1 polynomials.
pub(crate) fn affine_map(
    img: &PixelImage,
    j0: [[f64; 2]; 2],
    drift_nm_per_s: [f64; 2],
    t_origin_s: f64,
) -> Option<ImageMap> {
    let (mut x, mut y, mut rx, mut ry) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for line in &img.lines {
        for s in &line.samples {
            let t = line.t_centre_s + s.dt_s - t_origin_s;
            let u = s.u_nm;
            x.push(u[0]);
            y.push(u[1]);
            rx.push(j0[0][0] * u[0] + j0[0][1] * u[1] + drift_nm_per_s[0] * t);
            ry.push(j0[1][0] * u[0] + j0[1][1] * u[1] + drift_nm_per_s[1] * t);
        }
    }
    let options = spm_regression::FitOptions::default();
    let fx = spm_regression::fit(&spm_regression::Observations::new(&x, &y, &rx), 1, &options);
    let fy = spm_regression::fit(&spm_regression::Observations::new(&x, &y, &ry), 1, &options);
    Some([fx.ok()?.surface, fy.ok()?.surface])
}

/// The best vibration frequency over the images' pixels against their templates (`maps`);
/// `None` when there is nothing to search (fewer than two images, no frequency range).
pub(crate) fn candidate(
    images: &[(&PixelImage, &ImageMap)],
    space: &SearchSpace<'_>,
) -> Option<Candidate> {
    if images.len() < 2 {
        return None;
    }
    let flat = Flat::new(images, space.t_origin_s, &space.harmonics);
    let n = flat.t.len();
    if n < 64 || flat.templates.iter().any(|t| t.harmonics.is_empty()) {
        return None;
    }
    let t_min = flat.t.iter().copied().fold(f64::INFINITY, f64::min);
    let t_max = flat.t.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let span = t_max - t_min;
    let mut dwells: Vec<f64> = Vec::new();
    let mut line_duration: f64 = 0.0;
    let mut centres = Vec::with_capacity(flat.lines.len());
    let mut image_of = Vec::with_capacity(flat.lines.len());
    for range in &flat.lines {
        let ts = &flat.t[range.clone()];
        let lo = ts.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = ts.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        if ts.len() > 1 && hi > lo {
            dwells.push((hi - lo) / (ts.len() - 1) as f64);
            line_duration = line_duration.max(hi - lo);
        }
        centres.push(0.5 * (lo + hi));
        image_of.push(flat.image[range.start]);
    }
    let dwell = spm_regression::upper_median(&mut dwells)?;
    let line_duration = line_duration + dwell;
    let f_min = (1.5 / span).max(2.0 / space.longest_frame_s.max(1e-9));
    let f_max = 0.5 / dwell;
    if !(span > 0.0 && dwell > 0.0 && f_max > f_min) {
        return None;
    }
    let sub_step = 1.0 / (8.0 * line_duration);
    let sub_n = ((f_max - f_min) / sub_step).ceil() as usize + 3;
    if sub_n * flat.lines.len() * 2 > MAX_SUMS {
        tracing::debug!(
            sub_n,
            lines = flat.lines.len(),
            "pixel vibration search too large"
        );
        return None;
    }
    let sub_f0 = f_min - sub_step;
    let sums = line_sums(&flat, &centres, sub_f0, sub_step, sub_n);
    let norm = [0, 1].map(|a| 0.5 * flat.g[a].iter().map(|g| g * g).sum::<f64>());
    let spec = Spectrum {
        centres,
        image_of,
        sums,
        sub_f0,
        sub_step,
        sub_n,
        norm,
    };
    // Stage A: coherent within each image, summed over images.
    let mut image_span: f64 = 0.0;
    for i in 0..images.len() {
        let ts = spec
            .centres
            .iter()
            .zip(&spec.image_of)
            .filter(|(_, m)| **m == i)
            .map(|(c, _)| *c);
        let (lo, hi) = ts.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), t| {
            (lo.min(t), hi.max(t))
        });
        image_span = image_span.max(hi - lo + line_duration);
    }
    let mut step_a = 1.0 / (4.0 * image_span);
    let work = ((f_max - f_min) / step_a) as usize * spec.centres.len();
    if work > MAX_GRID_WORK {
        step_a *= work as f64 / MAX_GRID_WORK as f64;
    }
    let exclusion = 2.0 / span;
    // Each line's phasor advances by one rotation per grid step (restarted exactly every
    // 64 steps), not a sin_cos per line and frequency.
    let tau = std::f64::consts::TAU;
    let rotations: Vec<(f64, f64)> = spec
        .centres
        .iter()
        .map(|c| (tau * step_a * c).sin_cos())
        .collect();
    let mut phasors: Vec<(f64, f64)> = Vec::new();
    let mut grid: Vec<(f64, f64)> = Vec::new();
    for (g, f) in (0..)
        .map(|i| f_min + i as f64 * step_a)
        .take_while(|f| *f <= f_max)
        .enumerate()
    {
        if g % 64 == 0 {
            phasors = spec
                .centres
                .iter()
                .map(|c| (tau * f * c).sin_cos())
                .collect();
        } else {
            for (p, r) in phasors.iter_mut().zip(&rotations) {
                *p = (p.0 * r.1 + p.1 * r.0, p.1 * r.1 - p.0 * r.0);
            }
        }
        if !synchronous(f, space.line_frequencies_hz, exclusion) {
            grid.push((f, spec.power_with(f, &phasors, true, images.len())));
        }
    }
    // Stage B: coherent over all images around the best peaks, then exact fits.
    let step_b = 1.0 / (8.0 * span);
    let included = vec![true; n];
    let fit_rss = |f: f64| flat.fit(f, &included).map(|fit| fit.rss);
    let mut best: Option<(f64, f64)> = None;
    for f in top_peaks(&grid, 5) {
        let g = refine(&spec, f, step_a, step_b);
        if g < f_min || g > f_max || synchronous(g, space.line_frequencies_hz, exclusion) {
            continue;
        }
        if let Some(rss) = fit_rss(g)
            && best.is_none_or(|b| rss < b.1)
        {
            best = Some((g, rss));
        }
    }
    let (f_best, rss1) = best?;
    // The alias family.
    let line_rate = space.line_frequencies_hz.first().copied().unwrap_or(0.0);
    let mut family: Vec<f64> = Vec::new();
    if line_rate > 0.0 {
        for m in [-2.0, -1.0, 1.0, 2.0] {
            let g = f_best + m * line_rate;
            if g > 0.0 {
                family.push(refine(&spec, g, step_a, step_b));
            }
        }
    }
    family.push(1.0 / dwell - f_best);
    family.push(1.0 / dwell + f_best);
    Some(Candidate {
        frequency_hz: f_best,
        linear_rss: [flat.rss0(&included), rss1],
        pixels: n,
        family,
        trials: ((f_max - f_min) * span).max(1.0),
        f_max,
    })
}

/// The vibration at the candidate's frequency (re-chosen within its alias family) fitted
/// on the pixels against the templates of the maps `vibrating` (the features without what
/// they see of it), against the static model: the templates of the maps `still` (the
/// features as they are, which follow any static distortion of each image) and no
/// vibration. With its evidence, coherence and held-out RMS.
pub(crate) fn assess(
    images: &[(&PixelImage, &ImageMap, &ImageMap)],
    space: &SearchSpace<'_>,
    candidate: &Candidate,
) -> Option<PixelFit> {
    let with = |pick: fn(&(&PixelImage, &ImageMap, &ImageMap)) -> ImageMap| {
        let maps: Vec<ImageMap> = images.iter().map(pick).collect();
        let pairs: Vec<(&PixelImage, &ImageMap)> =
            images.iter().zip(&maps).map(|(i, m)| (i.0, m)).collect();
        Flat::new(&pairs, space.t_origin_s, &space.harmonics)
    };
    let flat = with(|i| i.2.clone());
    let still = with(|i| i.1.clone());
    let n = flat.t.len();
    let usable = |f: &Flat| f.templates.iter().all(|t| !t.harmonics.is_empty());
    if n < 64 || !usable(&flat) || !usable(&still) {
        return None;
    }
    let included = vec![true; n];
    let fit_rss = |f: f64| flat.fit(f, &included).map(|fit| fit.rss);
    let (f_max, family) = (candidate.f_max, &candidate.family);
    let (f_best, rss1) = std::iter::once(candidate.frequency_hz)
        .chain(family.iter().copied().filter(|g| *g <= f_max))
        .filter_map(|g| fit_rss(g).map(|r| (g, r)))
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    let fit = flat.fit(f_best, &included)?;
    let rss0 = still.rss0(&included);
    let family: Vec<f64> = std::iter::once(candidate.frequency_hz)
        .chain(family.iter().copied())
        .filter(|g| (g - f_best).abs() > 1e-9)
        .collect();
    let aliases: Vec<AliasMember> = family
        .iter()
        .filter_map(|&g| {
            fit_rss(g).map(|rss| AliasMember {
                frequency_hz: g,
                evidence_gap: n as f64 * (rss / rss1.max(1e-300)).ln(),
            })
        })
        .collect();
    // Coherence: the joint fit against separate fits per image.
    let mut separate = 0.0;
    for i in 0..images.len() {
        let mask: Vec<bool> = flat.image.iter().map(|&m| m == i).collect();
        if let Some(f) = flat.fit(f_best, &mask) {
            separate += flat.rss0(&mask) - f.rss;
        }
    }
    let sigma2 = rss1 / (n as f64 - 4.0).max(1.0);
    let noise_gain = 4.0 * (images.len() as f64 - 1.0) * sigma2;
    let joint = flat.rss0(&included) - rss1;
    let coherence = joint / (separate - noise_gain).max(joint).max(1e-300);
    // Held-out: two folds over alternate lines, the frequency re-chosen in its family.
    let mut members = vec![f_best];
    members.extend(family.iter().copied().filter(|g| *g <= f_max));
    let (mut before, mut after, mut count) = (0.0, 0.0, 0usize);
    for fold in 0..2 {
        let train: Vec<bool> = flat.parity.iter().map(|&p| p == fold).collect();
        let chosen = members
            .iter()
            .filter_map(|&g| flat.fit(g, &train).map(|f| (g, f)))
            .min_by(|a, b| a.1.rss.total_cmp(&b.1.rss));
        let Some((g, f)) = chosen else { continue };
        let start = [0, 1, 2, 3].map(|j| f.coefficients[j]);
        let Some(exact) = flat.exact_fit(g, start, &train) else {
            continue;
        };
        let w = std::f64::consts::TAU * g;
        let r = flat.exact_residual(&exact.templates, (w, &exact.coefficients));
        for k in (0..n).filter(|&k| !train[k]) {
            before += still.e[k] * still.e[k];
            after += r[k] * r[k];
            count += 1;
        }
    }
    let heldout_rms = [
        (before / count.max(1) as f64).sqrt(),
        (after / count.max(1) as f64).sqrt(),
    ];
    let start = [0, 1, 2, 3].map(|j| fit.coefficients[j]);
    let exact = flat.exact_fit(f_best, start, &included)?;
    Some(PixelFit {
        frequency_hz: f_best,
        coefficients_nm: exact.coefficients,
        covariance_nm2: exact.covariance,
        rss: [rss0, exact.rss.min(rss1)],
        pixels: n,
        images: images.len(),
        trials: candidate.trials,
        aliases,
        coherence,
        heldout_rms,
    })
}

#[cfg(test)]
mod harmonic_tests {
    use super::*;

    /// The harmonics' phasors from the basis phasors' powers are those of 2π·G·R.
    #[test]
    fn the_phasors_from_powers_are_the_direct_ones() {
        let h = lattice_harmonics([[0.2461, 0.0], [0.123_05, 0.213_13]]);
        assert!(h.len() >= 9, "{} harmonics", h.len());
        let mut out = Vec::new();
        for r in [[0.0, 0.0], [3.7, -2.2], [-41.3, 17.9], [250.0, 130.0]] {
            h.phasors(r, &mut out);
            for (g, &(s, c)) in h.vectors.iter().zip(&out) {
                let (ds, dc) = (std::f64::consts::TAU * (g[0] * r[0] + g[1] * r[1])).sin_cos();
                assert!(
                    (s - ds).abs() < 1e-9 && (c - dc).abs() < 1e-9,
                    "{g:?} at {r:?}"
                );
            }
        }
    }
}
