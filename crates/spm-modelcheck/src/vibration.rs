//! A lateral vibration modelled where it acts: on every pixel's height, not only on the
//! feature positions (issue 29 item 1).
//!
//! A feature's fitted position averages the tip's motion over the lines of its footprint,
//! and its times are sampled once per line: a vibration whose phase advances about half
//! a cycle per line averages out inside each atom (the features only broaden), and any
//! other is seen at its alias modulo the line rate. Each pixel, though, is sampled at
//! its own time, densely along the line. So, per image (one direction of one frame):
//!
//! 1. the lattice *template* T(c, r) is the image's own sum of lattice harmonics, fitted
//!    jointly with the lines' offsets and slopes when the lines are levelled
//!    (`level.rs`; its reciprocal basis refined on the image, so the image's mean affine
//!    distortion — including constant drift, affine in (column, row) within one
//!    image — is inside the template);
//! 2. a displacement δu of the tip (nominal nm of input, image axes) changes the height
//!    by ∇T·δu: the height residual e = z − T is regressed on the template's gradient
//!    times cos/sin of 2πf·t, t each pixel's own acquisition time;
//! 3. the frequency is searched from two cycles per frame to half the pixel rate: first
//!    coherently within each image and summed over images (a grid of a quarter of one
//!    image's resolution: the phase between frames tens of seconds apart would make a
//!    coherent grid miss the fringe), then coherently over all images around the best
//!    peaks. Each line's sum is computed once per frequency of a sub-grid of 1/(8 line
//!    durations) about the line's centre time, so a frequency costs one rotation per
//!    line, not per pixel. Frequencies within 2/span of a harmonic of the line rate are
//!    scan-synchronous (a static distortion of every line) and left out, as at the
//!    feature level;
//! 4. the alias family — the named frequency ± one and two line rates, and its mirrors
//!    about the pixel rate — is fitted exactly and reported with each member's evidence
//!    gap: the line rate folds a frequency for the features, not for the pixels of a line
//!    (the gap is large), while the pixel clock folds it exactly when the pixels sit on
//!    one dwell grid (the gap is then ≈ 0: the lower member, within half the pixel rate,
//!    is named).
//!
//! The vibration is accepted when its evidence (ΔBIC over the pixels, with the search's
//! look-elsewhere count) exceeds the threshold, the same sinusoid explains every image
//! (its *coherence*: the joint fit explains at least half of what separate fits per image
//! explain beyond their noise — a tip change or a frame-specific artefact does not), its
//! displacement is relevant and plausible as at the feature level, and it lowers the
//! two-fold held-out RMS of the height residual over alternate lines (fitted on the even
//! lines, tested on the odd, and vice versa; the frequency re-chosen within its alias
//! family on each fold).

use crate::types::LineDirection;

/// One pixel: its time, its height residual against its image's lattice template, and
/// the template's gradient.
#[derive(Clone, Copy, Debug)]
struct Sample {
    /// Time from its line's centre, s.
    dt_s: f64,
    /// Height minus the lattice template, in the image's height unit (pm for a file in m).
    residual: f64,
    /// ∂T/∂u along x and y per nominal nm of input (height unit per nm).
    gradient_per_nm: [f64; 2],
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
/// vibration search: every scanned pixel's acquisition time, height residual against the
/// image's lattice template (its sum of lattice harmonics) and the template's gradient.
/// Built by the image reader ([`crate::diagnose`]) or from a height map
/// ([`crate::pixel_image_from_height_map`]).
#[derive(Clone, Debug)]
pub struct PixelImage {
    frame: usize,
    direction: LineDirection,
    lines: Vec<Line>,
}

/// A lattice template: the harmonics (cycles per pixel, (column, row)) and their cos/sin
/// coefficients, as `level::level_lines` fits them.
pub(crate) struct Template<'a> {
    pub k_px: &'a [[f64; 2]],
    pub coefficients: &'a [f64],
}

impl PixelImage {
    /// The pixels of a levelled image `z` (row-major, row index growing with y; `bad` not
    /// scanned) against `template`; `pixel_nm` the pitch; `time_and_line` the time (s) and
    /// acquisition line of a (column, row). `None` when fewer than 4 lines have 8 pixels.
    pub(crate) fn new(
        (frame, direction): (usize, LineDirection),
        (z, bad, nx, ny): (&[f64], &[bool], usize, usize),
        template: &Template<'_>,
        pixel_nm: [f64; 2],
        time_and_line: &dyn Fn(f64, f64) -> (f64, usize),
    ) -> Option<Self> {
        let tau = std::f64::consts::TAU;
        if template.coefficients.len() != 2 * template.k_px.len()
            || !(pixel_nm[0] > 0.0 && pixel_nm[1] > 0.0)
        {
            return None;
        }
        let mut lines = Vec::new();
        for r in 0..ny {
            let mut samples = Vec::with_capacity(nx);
            let mut times = Vec::with_capacity(nx);
            let mut parity = 0;
            for c in 0..nx {
                let k = r * nx + c;
                if bad.get(k).copied().unwrap_or(true) || !z[k].is_finite() {
                    continue;
                }
                let (mut t, mut g) = (0.0, [0.0, 0.0]);
                for (j, kv) in template.k_px.iter().enumerate() {
                    let (s, co) = (tau * (kv[0] * c as f64 + kv[1] * r as f64)).sin_cos();
                    let (a, b) = (template.coefficients[2 * j], template.coefficients[2 * j + 1]);
                    t += a * co + b * s;
                    let d = -a * s + b * co;
                    g[0] += tau * kv[0] * d;
                    g[1] += tau * kv[1] * d;
                }
                let (time_s, line) = time_and_line(c as f64, r as f64);
                parity = line % 2;
                times.push(time_s);
                samples.push(Sample {
                    dt_s: time_s,
                    residual: z[k] - t,
                    gradient_per_nm: [g[0] / pixel_nm[0], g[1] / pixel_nm[1]],
                });
            }
            if samples.len() < 8 || times.iter().any(|t| !t.is_finite()) {
                continue;
            }
            let t_centre_s = times.iter().sum::<f64>() / times.len() as f64;
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
        })
    }

    /// The frame and line direction of the image.
    pub fn frame_and_direction(&self) -> (usize, LineDirection) {
        (self.frame, self.direction)
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

/// The samples flattened: time from the origin, residual, gradients, image, line parity.
struct Flat {
    t: Vec<f64>,
    e: Vec<f64>,
    g: [Vec<f64>; 2],
    image: Vec<usize>,
    parity: Vec<usize>,
}

impl Flat {
    fn new(images: &[PixelImage], t0: f64) -> Self {
        let mut f = Flat {
            t: Vec::new(),
            e: Vec::new(),
            g: [Vec::new(), Vec::new()],
            image: Vec::new(),
            parity: Vec::new(),
        };
        for (i, img) in images.iter().enumerate() {
            for line in &img.lines {
                for s in &line.samples {
                    f.t.push(line.t_centre_s + s.dt_s - t0);
                    f.e.push(s.residual);
                    f.g[0].push(s.gradient_per_nm[0]);
                    f.g[1].push(s.gradient_per_nm[1]);
                    f.image.push(i);
                    f.parity.push(line.parity);
                }
            }
        }
        f
    }

    /// The four columns at frequency `f_hz`.
    fn columns(&self, f_hz: f64) -> Vec<Vec<f64>> {
        let w = std::f64::consts::TAU * f_hz;
        let n = self.t.len();
        let mut cols = vec![vec![0.0; n]; 4];
        for k in 0..n {
            let (s, c) = (w * self.t[k]).sin_cos();
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

/// Per line and axis, Σ e·g·e^{iω·dt} on the sub-grid `f0 + j·step` (j < n), as
/// (re, im) pairs: `[j][line][axis]` flattened.
fn line_sums(lines: &[&Line], f0: f64, step: f64, n: usize) -> Vec<[f64; 2]> {
    const RESYNC: usize = 64;
    let tau = std::f64::consts::TAU;
    let nl = lines.len();
    let mut out = vec![[0.0; 2]; n * nl * 2];
    for (l, line) in lines.iter().enumerate() {
        for s in &line.samples {
            let (ds, dc) = (tau * step * s.dt_s).sin_cos();
            let w = [
                s.residual * s.gradient_per_nm[0],
                s.residual * s.gradient_per_nm[1],
            ];
            for block in (0..n).step_by(RESYNC) {
                let f = f0 + block as f64 * step;
                let (mut sn, mut cs) = (tau * f * s.dt_s).sin_cos();
                for j in block..(block + RESYNC).min(n) {
                    let base = (j * nl + l) * 2;
                    for a in 0..2 {
                        out[base + a][0] += w[a] * cs;
                        out[base + a][1] += w[a] * sn;
                    }
                    (sn, cs) = (sn * dc + cs * ds, cs * dc - sn * ds);
                }
            }
        }
    }
    out
}

/// The search's grids and the lines' sums.
struct Spectrum<'a> {
    lines: Vec<&'a Line>,
    /// Image of each line.
    image_of: Vec<usize>,
    sums: Vec<[f64; 2]>,
    sub_f0: f64,
    sub_step: f64,
    sub_n: usize,
    /// Σ g_a²/2 over all samples, per axis.
    norm: [f64; 2],
}

impl Spectrum<'_> {
    /// The power at `f_hz`: Σ over axes of |Σ_lines e^{iωt_line}·S_line(f)|²/norm, summed
    /// over images when `per_image` (coherent within each image), else coherent over all.
    fn power(&self, f_hz: f64, per_image: bool, n_images: usize, lines: &[bool]) -> f64 {
        let j = ((f_hz - self.sub_f0) / self.sub_step).round();
        if !(j >= 0.0 && (j as usize) < self.sub_n) {
            return 0.0;
        }
        let j = j as usize;
        let nl = self.lines.len();
        let groups = if per_image { n_images } else { 1 };
        let mut acc = vec![[[0.0; 2]; 2]; groups];
        let w = std::f64::consts::TAU * f_hz;
        for (l, line) in self.lines.iter().enumerate() {
            if !lines[l] {
                continue;
            }
            let (s, c) = (w * line.t_centre_s).sin_cos();
            let g = if per_image { self.image_of[l] } else { 0 };
            for a in 0..2 {
                let v = self.sums[(j * nl + l) * 2 + a];
                acc[g][a][0] += v[0] * c - v[1] * s;
                acc[g][a][1] += v[0] * s + v[1] * c;
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
fn refine(spec: &Spectrum<'_>, f: f64, half: f64, step: f64, lines: &[bool]) -> f64 {
    let n = (half / step).ceil() as i64;
    let mut best = (f, spec.power(f, false, 1, lines));
    for i in -n..=n {
        let g = f + i as f64 * step;
        let p = spec.power(g, false, 1, lines);
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
pub(crate) fn search(images: &[PixelImage], space: &SearchSpace<'_>) -> Option<PixelFit> {
    if images.len() < 2 {
        return None;
    }
    let flat = Flat::new(images, space.t_origin_s);
    let n = flat.t.len();
    if n < 64 {
        return None;
    }
    let t_min = flat.t.iter().copied().fold(f64::INFINITY, f64::min);
    let t_max = flat.t.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let span = t_max - t_min;
    let mut line_durations: Vec<f64> = Vec::new();
    let mut dwells: Vec<f64> = Vec::new();
    for img in images {
        for line in &img.lines {
            let lo = line.samples.iter().map(|s| s.dt_s).fold(f64::INFINITY, f64::min);
            let hi = line.samples.iter().map(|s| s.dt_s).fold(f64::NEG_INFINITY, f64::max);
            let m = line.samples.len();
            if m > 1 && hi > lo {
                dwells.push((hi - lo) / (m - 1) as f64);
                line_durations.push(hi - lo);
            }
        }
    }
    let dwell = spm_regression::upper_median(&mut dwells)?;
    let line_duration = line_durations.iter().copied().fold(0.0, f64::max) + dwell;
    let f_min = (1.5 / span).max(2.0 / space.longest_frame_s.max(1e-9));
    let f_max = 0.5 / dwell;
    if !(span > 0.0 && dwell > 0.0 && f_max > f_min) {
        return None;
    }
    let lines: Vec<&Line> = images.iter().flat_map(|i| i.lines.iter()).collect();
    let image_of: Vec<usize> = images
        .iter()
        .enumerate()
        .flat_map(|(i, img)| std::iter::repeat_n(i, img.lines.len()))
        .collect();
    let sub_step = 1.0 / (8.0 * line_duration);
    let sub_n = ((f_max - f_min) / sub_step).ceil() as usize + 2;
    if sub_n * lines.len() * 2 > MAX_SUMS {
        tracing::debug!(sub_n, lines = lines.len(), "pixel vibration search too large");
        return None;
    }
    let sub_f0 = f_min - sub_step;
    let sums = line_sums(&lines, sub_f0, sub_step, sub_n + 1);
    let norm = [0, 1].map(|a| 0.5 * flat.g[a].iter().map(|g| g * g).sum::<f64>());
    let spec = Spectrum {
        lines,
        image_of,
        sums,
        sub_f0,
        sub_step,
        sub_n: sub_n + 1,
        norm,
    };
    let all_lines = vec![true; spec.lines.len()];
    // Stage A: coherent within each image, summed over images.
    let image_span = images
        .iter()
        .map(|img| {
            let lo = img.lines.iter().map(|l| l.t_centre_s).fold(f64::INFINITY, f64::min);
            let hi = img
                .lines
                .iter()
                .map(|l| l.t_centre_s)
                .fold(f64::NEG_INFINITY, f64::max);
            hi - lo + line_duration
        })
        .fold(0.0, f64::max);
    let mut step_a = 1.0 / (4.0 * image_span);
    let work = ((f_max - f_min) / step_a) as usize * spec.lines.len();
    if work > MAX_GRID_WORK {
        step_a *= work as f64 / MAX_GRID_WORK as f64;
    }
    let exclusion = 2.0 / span;
    let grid: Vec<(f64, f64)> = (0..)
        .map(|i| f_min + i as f64 * step_a)
        .take_while(|f| *f <= f_max)
        .filter(|f| !synchronous(*f, space.line_frequencies_hz, exclusion))
        .map(|f| (f, spec.power(f, true, images.len(), &all_lines)))
        .collect();
    // Stage B: coherent over all images around the best peaks, then exact fits.
    let step_b = 1.0 / (8.0 * span);
    let included = vec![true; n];
    let fit_rss = |f: f64| flat.fit(f, &included).map(|fit| fit.rss);
    let mut best: Option<(f64, f64)> = None;
    for f in top_peaks(&grid, 5) {
        let g = refine(&spec, f, step_a, step_b, &all_lines);
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
    let fit = flat.fit(f_best, &included)?;
    let rss0 = flat.rss0(&included);
    // The alias family.
    let line_rate = space.line_frequencies_hz.first().copied().unwrap_or(0.0);
    let mut family: Vec<f64> = Vec::new();
    if line_rate > 0.0 {
        for m in [-2.0, -1.0, 1.0, 2.0] {
            let g = f_best + m * line_rate;
            if g > 0.0 {
                family.push(refine(&spec, g, step_a, step_b, &all_lines));
            }
        }
    }
    family.push(1.0 / dwell - f_best);
    family.push(1.0 / dwell + f_best);
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
    let joint = rss0 - rss1;
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
        let cols = flat.columns(g);
        for k in 0..n {
            if train[k] {
                continue;
            }
            let pred: f64 = (0..4).map(|j| f.coefficients[j] * cols[j][k]).sum();
            before += flat.e[k] * flat.e[k];
            after += (flat.e[k] - pred).powi(2);
            count += 1;
        }
    }
    let heldout_rms = [
        (before / count.max(1) as f64).sqrt(),
        (after / count.max(1) as f64).sqrt(),
    ];
    let mut coefficients_nm = [0.0; 4];
    let mut covariance_nm2 = [[0.0; 4]; 4];
    for a in 0..4 {
        coefficients_nm[a] = fit.coefficients[a];
        for b in 0..4 {
            covariance_nm2[a][b] = fit.covariance[a][b];
        }
    }
    Some(PixelFit {
        frequency_hz: f_best,
        coefficients_nm,
        covariance_nm2,
        rss: [rss0, rss1],
        pixels: n,
        images: images.len(),
        trials: ((f_max - f_min) * span).max(1.0),
        aliases,
        coherence,
        heldout_rms,
    })
}
