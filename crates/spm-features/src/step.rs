//! Monatomic steps: find a step edge in a scan and measure its height by fitting the two
//! terraces, drift-insensitively, with an uncertainty; reject what is not one clean step
//! (issue 15).
//!
//! # Model
//! Every scan line `j` crossing the edge is fitted as `z = c_j + g·i + H·u(i, j)`, where `i`
//! is the pixel along the line, `c_j` a per-line offset, `g` an in-line slope shared by all
//! lines (the bowl and the sample tilt over the window), `u` = 1 on the upper terrace and
//! 0 on the lower, and `H` the step height (Z counts). Pixels within `edge_mask_px` of the
//! edge are left out (the edge's transition and the feedback's lag). The per-line offsets
//! absorb everything slow — Z drift, 1/f noise, the slow-axis tilt — because both terraces
//! of a line are measured within one line time; the lateral drift only moves the edge, which
//! is located line by line. With the retrace (or a counter scan) measured too, the mean of the
//! two directions also cancels a linear Z drift within the line and the feedback lag's
//! asymmetry ([`measure_step_pair`]).
//!
//! The height is the mean of the per-line heights `H_j` (with the common slope); its
//! uncertainty their standard error, so the atomic corrugation, the noise and whatever
//! differs from line to line are in it.
//!
//! # Rejections (typed: [`StepRejection`])
//! - no edge in most lines (flat terrace), or the edge too near the border;
//! - a second edge beside the first (multiple steps in the window);
//! - a height that is a multiple of the monatomic one (a double step) or far from it;
//! - a tip change: the per-line heights jump part-way through the scan;
//! - defects: too many lines whose height is far from the others.

use spm_hal::{CountPoint, Counts, HeightMap};

/// Settings of the step finder.
#[derive(Clone, Debug, PartialEq)]
pub struct StepConfig {
    /// Expected height of one monatomic step, Z counts (the standard's height over the
    /// nominal Kz).
    pub nominal_height_counts: f64,
    /// A step is monatomic when its height is within this fraction of the nominal (the
    /// nominal Kz is only approximate), e.g. 0.3.
    pub height_tolerance_fraction: f64,
    /// Half-width of the band around the edge left out of the terrace fit, pixels.
    pub edge_mask_px: f64,
    /// Half-width of the box averages that locate the edge in a line, pixels (≥ 2).
    pub smoothing_px: usize,
    /// Fewest pixels of each terrace in a line for the line to count.
    pub min_terrace_px: usize,
    /// Fewest lines crossing the edge.
    pub min_lines: usize,
    /// A jump of the per-line heights larger than this many standard errors (and 2 % of the
    /// height) is a tip change.
    pub tip_change_sigma: f64,
    /// Largest fraction of lines rejected as outliers (defects) before the scan is rejected.
    pub max_outlier_fraction: f64,
}

impl StepConfig {
    /// Settings for a monatomic step of `nominal_height_counts` in a scan whose edge band
    /// (transition + lag) is `edge_mask_px` pixels.
    pub fn monatomic(nominal_height_counts: f64, edge_mask_px: f64) -> Self {
        Self {
            nominal_height_counts,
            height_tolerance_fraction: 0.3,
            edge_mask_px,
            smoothing_px: 4,
            min_terrace_px: 6,
            min_lines: 8,
            tip_change_sigma: 8.0,
            max_outlier_fraction: 0.25,
        }
    }
}

/// A measured step.
#[derive(Clone, Debug, PartialEq)]
pub struct StepMeasurement {
    /// Step height, Z counts (> 0).
    pub height_counts: f64,
    /// Standard uncertainty of the height, Z counts.
    pub u_height_counts: f64,
    /// A point of the edge (the middle line's crossing), commanded counts.
    pub edge_point: CountPoint,
    /// Z of the lower terrace at the edge point, counts (mean line offset).
    pub lower_terrace_z_counts: f64,
    /// Lines used.
    pub lines_used: usize,
    /// Lines left out as outliers (defects).
    pub lines_rejected: usize,
    /// The upper terrace lies towards +i (along the lines) from the edge.
    pub upper_towards_positive: bool,
}

/// Why a scan gave no step height.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum StepRejection {
    /// No edge: fewer than `min_lines` lines show a jump of at least half a step.
    #[error("no step edge: {lines_with_edge} of {lines} lines show a jump (need {needed})")]
    NoEdge {
        /// Lines with a jump.
        lines_with_edge: usize,
        /// Lines in the scan.
        lines: usize,
        /// Lines needed.
        needed: usize,
    },
    /// The edge is too near the scan's border for both terraces to be fitted.
    #[error("the step edge is too near the scan border ({lines_usable} usable lines)")]
    EdgeNearBorder {
        /// Lines with both terraces wide enough.
        lines_usable: usize,
    },
    /// Several edges in the window.
    #[error("several step edges in the window ({lines_with_second_edge} lines show a second jump)")]
    MultipleEdges {
        /// Lines with a second jump.
        lines_with_second_edge: usize,
    },
    /// The height is a multiple of the monatomic step.
    #[error("a {layers}-layer step ({height_counts:.1} counts), not a monatomic one")]
    DoubleStep {
        /// Layers.
        layers: u32,
        /// Measured height, counts.
        height_counts: f64,
    },
    /// The height is far from any multiple of the monatomic step.
    #[error("step height {height_counts:.1} counts is {ratio:.2} × the nominal monatomic height")]
    ImplausibleHeight {
        /// Measured height, counts.
        height_counts: f64,
        /// Height over the nominal.
        ratio: f64,
    },
    /// The per-line heights jump part-way through the scan.
    #[error("tip change at line {line}: the step height jumps by {jump_fraction:.1}%")]
    TipChange {
        /// First line after the jump.
        line: usize,
        /// Relative size of the jump, %.
        jump_fraction: f64,
    },
    /// Too many outlier lines (vacancies, adsorbates, a ragged edge).
    #[error("defects: {rejected} of {lines} lines are outliers")]
    Defects {
        /// Outlier lines.
        rejected: usize,
        /// Lines crossing the edge.
        lines: usize,
    },
    /// The map is unusable (too small, non-finite values, bad settings).
    #[error("unusable scan: {0}")]
    Unusable(String),
}

impl StepRejection {
    /// A short machine-readable kind (`no_edge`, `double_step`, …) for records.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::NoEdge { .. } => "no_edge",
            Self::EdgeNearBorder { .. } => "edge_near_border",
            Self::MultipleEdges { .. } => "multiple_edges",
            Self::DoubleStep { .. } => "double_step",
            Self::ImplausibleHeight { .. } => "implausible_height",
            Self::TipChange { .. } => "tip_change",
            Self::Defects { .. } => "defects",
            Self::Unusable(_) => "unusable",
        }
    }
}

/// The workspace's median ([`spm_regression::median`]); NaN when empty.
fn median(v: &mut [f64]) -> f64 {
    spm_regression::median(v).unwrap_or(f64::NAN)
}

/// Position and signed size of the largest box-average jump of a line.
fn strongest_jump(line: &[f64], w: usize) -> Option<(usize, f64)> {
    let n = line.len();
    if n < 2 * w + 2 {
        return None;
    }
    let mut prefix = Vec::with_capacity(n + 1);
    prefix.push(0.0);
    for &z in line {
        prefix.push(prefix.last().copied().unwrap_or(0.0) + z);
    }
    let mean = |a: usize, b: usize| (prefix[b] - prefix[a]) / (b - a) as f64;
    let mut best: Option<(usize, f64)> = None;
    // Jump between pixel i−1 and i: mean of [i, i+w) minus mean of [i−w, i).
    for i in w..=n - w {
        let d = mean(i, i + w) - mean(i - w, i);
        if best.is_none_or(|(_, b)| d.abs() > b.abs()) {
            best = Some((i, d));
        }
    }
    best
}

/// Measures one step in a height map (lines along x). See the module docs.
///
/// # Errors
/// [`StepRejection`] naming why the scan gives no monatomic step height.
pub fn measure_step(
    map: &HeightMap,
    config: &StepConfig,
) -> Result<StepMeasurement, StepRejection> {
    let nx = map.columns;
    let ny = map.rows;
    let w = config.smoothing_px.max(2);
    if !(config.nominal_height_counts.is_finite() && config.nominal_height_counts > 0.0) {
        return Err(StepRejection::Unusable(format!(
            "nominal height {} counts must be > 0",
            config.nominal_height_counts
        )));
    }
    if nx < 2 * (config.min_terrace_px + w) + 2 || ny < config.min_lines.max(3) {
        return Err(StepRejection::Unusable(format!(
            "{nx}×{ny} pixels is too small for a step fit"
        )));
    }
    if map.z_counts.len() != nx * ny || map.z_counts.iter().any(|z| !z.is_finite()) {
        return Err(StepRejection::Unusable(
            "heights missing or not finite".into(),
        ));
    }
    let threshold = 0.5 * config.nominal_height_counts;
    // 1. The edge in every line.
    let (detected, upper_towards_positive) = detect_edge(map, config, w, threshold)?;
    // 2. A straight edge i = a + b·j through the detections, outliers left out.
    let (a, b) = straight_edge(&detected, w);
    // 3. Per-line terrace sums with the edge band masked; lines crossing the edge only.
    let edge = Edge {
        map,
        a,
        b,
        mask: config.edge_mask_px.max(1.0),
        upper_towards_positive,
        min_terrace_px: config.min_terrace_px,
    };
    let no_exclusion = |_: usize| false;
    let mut lines: Vec<Line> = (0..ny)
        .filter_map(|j| edge.terraces(j, &no_exclusion))
        .collect();
    if lines.len() < config.min_lines {
        return Err(StepRejection::EdgeNearBorder {
            lines_usable: lines.len(),
        });
    }
    // 4. Common slope and per-line heights, with per-line offsets eliminated.
    let (mut g, mut heights) = solve_lines(&lines);
    // 5. Pixel outliers (vacancies, adsorbates): residuals beyond 6 robust σ, one pass.
    drop_pixel_outliers(&edge, config, &mut lines, &mut g, &mut heights);
    // 6. Outlier lines (defects, a ragged edge).
    let med = median(&mut heights.clone());
    let mad = median(&mut heights.iter().map(|h| (h - med).abs()).collect::<Vec<_>>());
    let limit = (5.0 * 1.4826 * mad).max(0.02 * med.abs());
    let keep: Vec<bool> = heights.iter().map(|h| (h - med).abs() <= limit).collect();
    let rejected = keep.iter().filter(|k| !**k).count();
    if rejected as f64 > config.max_outlier_fraction * lines.len() as f64 {
        return Err(StepRejection::Defects {
            rejected,
            lines: lines.len(),
        });
    }
    let kept: Vec<(usize, f64)> = lines
        .iter()
        .zip(&heights)
        .zip(&keep)
        .filter(|(_, k)| **k)
        .map(|((l, h), _)| (l.j, *h))
        .collect();
    if kept.len() < config.min_lines {
        return Err(StepRejection::EdgeNearBorder {
            lines_usable: kept.len(),
        });
    }
    let n = kept.len() as f64;
    let mean = kept.iter().map(|(_, h)| h).sum::<f64>() / n;
    let var = kept.iter().map(|(_, h)| (h - mean).powi(2)).sum::<f64>() / (n - 1.0);
    let sd = var.sqrt();
    // 8. A second edge: a jump of half a step in the residual of many lines.
    let second = second_edges(&edge, &lines, g, mean, w, threshold);
    if second as f64 > 0.3 * lines.len() as f64 {
        return Err(StepRejection::MultipleEdges {
            lines_with_second_edge: second,
        });
    }
    // 7. Tip change: the largest two-sample jump of the per-line heights in scan order.
    tip_change(&kept, mean, config)?;
    // 9. Monatomic?
    let ratio = mean / config.nominal_height_counts;
    let layers = ratio.round();
    let tol = config.height_tolerance_fraction;
    if layers >= 2.0 && (ratio - layers).abs() <= tol {
        return Err(StepRejection::DoubleStep {
            layers: layers as u32,
            height_counts: mean,
        });
    }
    if (ratio - 1.0).abs() > tol {
        return Err(StepRejection::ImplausibleHeight {
            height_counts: mean,
            ratio,
        });
    }
    let j_mid = 0.5 * (ny as f64 - 1.0);
    let i_mid = a + b * j_mid;
    let offsets: Vec<f64> = lines
        .iter()
        .map(|l| (l.lo[2] - g * l.lo[1]) / l.lo[0] + g * i_mid)
        .collect();
    let lower = offsets.iter().sum::<f64>() / offsets.len() as f64;
    Ok(StepMeasurement {
        height_counts: mean,
        u_height_counts: sd / n.sqrt(),
        edge_point: map.position(i_mid, j_mid),
        lower_terrace_z_counts: lower,
        lines_used: kept.len(),
        lines_rejected: rejected,
        upper_towards_positive,
    })
}

/// Step 1 of [`measure_step`]: the strongest jump of every line, the edge's sign by majority,
/// and the lines whose jump has that sign and at least half a step (line, position between
/// pixels); whether the upper terrace lies towards +i.
fn detect_edge(
    map: &HeightMap,
    config: &StepConfig,
    w: usize,
    threshold: f64,
) -> Result<(Vec<(usize, f64)>, bool), StepRejection> {
    let (nx, ny) = (map.columns, map.rows);
    let line = |j: usize| &map.z_counts[j * nx..(j + 1) * nx];
    let jumps: Vec<Option<(usize, f64)>> = (0..ny).map(|j| strongest_jump(line(j), w)).collect();
    let positive = jumps
        .iter()
        .flatten()
        .filter(|(_, d)| *d >= threshold)
        .count();
    let negative = jumps
        .iter()
        .flatten()
        .filter(|(_, d)| *d <= -threshold)
        .count();
    let upper_towards_positive = positive >= negative;
    let detected: Vec<(usize, f64)> = jumps
        .iter()
        .enumerate()
        .filter_map(|(j, jump)| {
            let (i, d) = (*jump)?;
            let ok = if upper_towards_positive {
                d >= threshold
            } else {
                d <= -threshold
            };
            ok.then_some((j, i as f64 - 0.5))
        })
        .collect();
    if detected.len() < config.min_lines.max(ny / 3) {
        return Err(StepRejection::NoEdge {
            lines_with_edge: detected.len(),
            lines: ny,
            needed: config.min_lines.max(ny / 3),
        });
    }
    Ok((detected, upper_towards_positive))
}

/// Step 2 of [`measure_step`]: the straight edge `i = a + b·j` through the detections, three
/// passes leaving out detections further than `max(2w, 3)` pixels from the last line.
fn straight_edge(detected: &[(usize, f64)], w: usize) -> (f64, f64) {
    let mut inliers: Vec<(usize, f64)> = detected.to_vec();
    let (mut a, mut b) = (0.0, 0.0);
    for _ in 0..3 {
        let n = inliers.len() as f64;
        let mj = inliers.iter().map(|(j, _)| *j as f64).sum::<f64>() / n;
        let mi = inliers.iter().map(|(_, i)| *i).sum::<f64>() / n;
        let sjj: f64 = inliers.iter().map(|(j, _)| (*j as f64 - mj).powi(2)).sum();
        let sji: f64 = inliers
            .iter()
            .map(|(j, i)| (*j as f64 - mj) * (i - mi))
            .sum();
        b = if sjj > 0.0 { sji / sjj } else { 0.0 };
        a = mi - b * mj;
        let tolerance = (2.0 * w as f64).max(3.0);
        let kept: Vec<(usize, f64)> = detected
            .iter()
            .copied()
            .filter(|(j, i)| (i - (a + b * *j as f64)).abs() <= tolerance)
            .collect();
        if kept.len() < 3 {
            break;
        }
        inliers = kept;
    }
    (a, b)
}

/// One line crossing the edge: the lower and upper terrace's sums.
struct Line {
    j: usize,
    // Lower and upper terrace: count, Σi, Σz, Σi², Σi·z.
    lo: [f64; 5],
    hi: [f64; 5],
}

/// The straight edge `i = a + b·j` of a map and its masked band: how a line splits into the
/// two terraces.
struct Edge<'m> {
    map: &'m HeightMap,
    a: f64,
    b: f64,
    /// Half-width of the band around the edge left out, pixels.
    mask: f64,
    upper_towards_positive: bool,
    min_terrace_px: usize,
}

impl Edge<'_> {
    /// The heights of line `j`.
    fn line(&self, j: usize) -> &[f64] {
        let nx = self.map.columns;
        &self.map.z_counts[j * nx..(j + 1) * nx]
    }

    /// Step 3 of [`measure_step`]: the terrace sums of line `j`, the masked band and the
    /// pixels `exclude` names left out; `None` when a terrace has too few pixels.
    fn terraces(&self, j: usize, exclude: &dyn Fn(usize) -> bool) -> Option<Line> {
        let edge = self.a + self.b * j as f64;
        let mut lo = [0.0; 5];
        let mut hi = [0.0; 5];
        for (i, &z) in self.line(j).iter().enumerate() {
            let d = i as f64 - edge;
            if d.abs() < self.mask || exclude(i) {
                continue;
            }
            let upper = (d > 0.0) == self.upper_towards_positive;
            let t = if upper { &mut hi } else { &mut lo };
            let x = i as f64;
            t[0] += 1.0;
            t[1] += x;
            t[2] += z;
            t[3] += x * x;
            t[4] += x * z;
        }
        let min = self.min_terrace_px as f64;
        (lo[0] >= min && hi[0] >= min).then_some(Line { j, lo, hi })
    }
}

/// Step 4 of [`measure_step`]: the common slope `g` and each line's height, with per-line
/// offsets eliminated. Within a line: z − z̄ = g (i − ī) + H (u − ū); normal equations pooled.
/// The least squares of z = c_line + g·i + H·u computed streaming from each line's sums (no
/// pixel kept), not a second solver: the test `solve_lines_is_the_kernel_least_squares`
/// checks it against [`spm_regression::least_squares`] on the dense design.
fn solve_lines(lines: &[Line]) -> (f64, Vec<f64>) {
    let (mut sgg, mut sgh, mut shh, mut sgz, mut shz) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for l in lines {
        let n = l.lo[0] + l.hi[0];
        let si = l.lo[1] + l.hi[1];
        let sz = l.lo[2] + l.hi[2];
        let sii = l.lo[3] + l.hi[3];
        let siz = l.lo[4] + l.hi[4];
        let su = l.hi[0];
        sgg += sii - si * si / n;
        sgh += l.hi[1] - si * su / n;
        shh += su - su * su / n;
        sgz += siz - si * sz / n;
        shz += l.hi[2] - su * sz / n;
    }
    let det = sgg * shh - sgh * sgh;
    let g = if det.abs() > 0.0 {
        (shh * sgz - sgh * shz) / det
    } else {
        0.0
    };
    let heights = lines
        .iter()
        .map(|l| {
            let (ml, mh) = (l.lo[2] / l.lo[0], l.hi[2] / l.hi[0]);
            let (il, ih) = (l.lo[1] / l.lo[0], l.hi[1] / l.hi[0]);
            (mh - ml) - g * (ih - il)
        })
        .collect();
    (g, heights)
}

/// Step 5 of [`measure_step`]: pixels whose residual from the two-terrace model lies beyond
/// 6 robust σ (vacancies, adsorbates) are left out in one pass, and the lines solved again,
/// unless fewer than `min_lines` lines would remain.
fn drop_pixel_outliers(
    edge: &Edge<'_>,
    config: &StepConfig,
    lines: &mut Vec<Line>,
    g: &mut f64,
    heights: &mut Vec<f64>,
) {
    let h0 = median(&mut heights.clone());
    let mut residuals = Vec::new();
    let mut per_line = Vec::with_capacity(lines.len());
    for l in lines.iter() {
        let at = edge.a + edge.b * l.j as f64;
        let offset = (l.lo[2] - *g * l.lo[1]) / l.lo[0];
        let r: Vec<(usize, f64)> = edge
            .line(l.j)
            .iter()
            .enumerate()
            .filter_map(|(i, &z)| {
                let d = i as f64 - at;
                if d.abs() < edge.mask {
                    return None;
                }
                let upper = (d > 0.0) == edge.upper_towards_positive;
                let model = offset + *g * i as f64 + if upper { h0 } else { 0.0 };
                Some((i, z - model))
            })
            .collect();
        residuals.extend(r.iter().map(|(_, r)| *r));
        per_line.push(r);
    }
    let med = median(&mut residuals.clone());
    let mad = median(
        &mut residuals
            .iter()
            .map(|r| (r - med).abs())
            .collect::<Vec<_>>(),
    );
    let limit = 6.0 * 1.4826 * mad.max(1e-9);
    let any_outlier = per_line
        .iter()
        .any(|r| r.iter().any(|(_, v)| (v - med).abs() > limit));
    if any_outlier {
        let rebuilt: Vec<Line> = lines
            .iter()
            .zip(&per_line)
            .filter_map(|(l, r)| {
                let bad: Vec<usize> = r
                    .iter()
                    .filter(|(_, v)| (v - med).abs() > limit)
                    .map(|(i, _)| *i)
                    .collect();
                edge.terraces(l.j, &|i| bad.contains(&i))
            })
            .collect();
        if rebuilt.len() >= config.min_lines {
            *lines = rebuilt;
            (*g, *heights) = solve_lines(lines);
        }
    }
}

/// Step 8 of [`measure_step`]: the lines whose residual from the model (slope `g`, step
/// `mean`) jumps by at least `threshold` on either side of the masked band — a second edge.
fn second_edges(
    edge: &Edge<'_>,
    lines: &[Line],
    g: f64,
    mean: f64,
    w: usize,
    threshold: f64,
) -> usize {
    let nx = edge.map.columns;
    let mut second = 0usize;
    for l in lines {
        let at = edge.a + edge.b * l.j as f64;
        let offset = (l.lo[2] - g * l.lo[1]) / l.lo[0];
        let residual: Vec<f64> = edge
            .line(l.j)
            .iter()
            .enumerate()
            .map(|(i, &z)| {
                let d = i as f64 - at;
                let upper = (d > 0.0) == edge.upper_towards_positive;
                z - offset - g * i as f64 - if upper { mean } else { 0.0 }
            })
            .collect();
        // Look on each side of the masked band separately.
        let cut_lo = (at - edge.mask).floor().max(0.0) as usize;
        let cut_hi = ((at + edge.mask).ceil().max(0.0) as usize).min(nx);
        for part in [&residual[..cut_lo.min(nx)], &residual[cut_hi..]] {
            if let Some((_, d)) = strongest_jump(part, w)
                && d.abs() >= threshold
            {
                second += 1;
                break;
            }
        }
    }
    second
}

/// Step 7 of [`measure_step`]: a tip change, the largest two-sample jump of the kept lines'
/// heights in scan order (two-sample t with the pooled within-part spread, since a jump
/// inflates the overall one), refused beyond `tip_change_sigma` and 2 % of the step.
fn tip_change(kept: &[(usize, f64)], mean: f64, config: &StepConfig) -> Result<(), StepRejection> {
    let n = kept.len() as f64;
    let min_part = (config.min_lines / 2).max(3);
    if kept.len() >= 2 * min_part {
        let mut prefix = vec![0.0];
        let mut prefix2 = vec![0.0];
        for (_, h) in kept {
            let d = h - mean;
            prefix.push(prefix.last().copied().unwrap_or(0.0) + d);
            prefix2.push(prefix2.last().copied().unwrap_or(0.0) + d * d);
        }
        let total = prefix.last().copied().unwrap_or(0.0);
        let total2 = prefix2.last().copied().unwrap_or(0.0);
        let mut worst: Option<(usize, f64, f64)> = None;
        for k in min_part..=kept.len() - min_part {
            let (k1, k2) = (k as f64, n - k as f64);
            let m1 = prefix[k] / k1;
            let m2 = (total - prefix[k]) / k2;
            let ss = (prefix2[k] - k1 * m1 * m1) + (total2 - prefix2[k] - k2 * m2 * m2);
            let pooled = (ss.max(0.0) / (n - 2.0)).sqrt();
            let se = pooled * (1.0 / k1 + 1.0 / k2).sqrt();
            let t = (m2 - m1).abs() / se.max(1e-9 * mean.abs()).max(1e-12);
            if worst.is_none_or(|(_, wt, _)| t > wt) {
                worst = Some((k, t, (m2 - m1) / mean));
            }
        }
        if let Some((k, t, jump)) = worst
            && t > config.tip_change_sigma
            && jump.abs() > 0.02
        {
            return Err(StepRejection::TipChange {
                line: kept[k].0,
                jump_fraction: 100.0 * jump,
            });
        }
    }
    Ok(())
}

/// Measures a step in two scans of the same window (forward and backward traces, or a direct
/// and a counter scan): the mean of the two heights, which cancels a linear Z drift within
/// the lines and the feedback lag's asymmetry. The uncertainty is the larger of the combined
/// standard errors and half the two heights' difference.
///
/// # Errors
/// The first scan's rejection, else the second's.
pub fn measure_step_pair(
    first: &HeightMap,
    second: &HeightMap,
    config: &StepConfig,
) -> Result<StepMeasurement, StepRejection> {
    let a = measure_step(first, config)?;
    let b = measure_step(second, config)?;
    let height = 0.5 * (a.height_counts + b.height_counts);
    let u = (0.5 * (a.u_height_counts.powi(2) + b.u_height_counts.powi(2)).sqrt())
        .max(0.5 * (a.height_counts - b.height_counts).abs() / 3f64.sqrt());
    Ok(StepMeasurement {
        height_counts: height,
        u_height_counts: u,
        edge_point: CountPoint::new(
            Counts(0.5 * (a.edge_point.x.value() + b.edge_point.x.value())),
            Counts(0.5 * (a.edge_point.y.value() + b.edge_point.y.value())),
        ),
        lower_terrace_z_counts: 0.5 * (a.lower_terrace_z_counts + b.lower_terrace_z_counts),
        lines_used: a.lines_used + b.lines_used,
        lines_rejected: a.lines_rejected + b.lines_rejected,
        upper_towards_positive: a.upper_towards_positive,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// A synthetic map: terraces with a slope, a per-line offset (Z drift), a corrugation,
    /// and steps at the given edge positions (pixel, per-line slope) and heights.
    fn map(edges: &[(f64, f64, f64)], jump_at: Option<(usize, f64)>) -> HeightMap {
        let (nx, ny) = (64, 32);
        let mut z = Vec::with_capacity(nx * ny);
        for j in 0..ny {
            let scale = match jump_at {
                Some((line, f)) if j >= line => f,
                _ => 1.0,
            };
            for i in 0..nx {
                let noise = ((i * 7919 + j * 104_729) % 1000) as f64 / 1000.0 - 0.5;
                let mut h =
                    3.0 * j as f64 + 0.2 * i as f64 + 4.0 * (1.7 * i as f64).sin() + 2.0 * noise;
                for (e0, slope, height) in edges {
                    let d = i as f64 - (e0 + slope * j as f64);
                    h += scale * height * 0.5 * (1.0 + d / (d * d + 0.25).sqrt());
                }
                z.push(h);
            }
        }
        HeightMap {
            origin: CountPoint::from_counts(100.0, 200.0),
            pixel_step: Counts(10.0),
            columns: nx,
            rows: ny,
            z_counts: z,
            time_s: vec![0.0; nx * ny],
        }
    }

    fn check(edges: &[(f64, f64, f64)], jump: Option<(usize, f64)>, expected: Result<f64, &str>) {
        let c = StepConfig::monatomic(84.0, 4.0);
        match (measure_step(&map(edges, jump), &c), expected) {
            (Ok(m), Ok(h)) => assert!(
                (m.height_counts - h).abs() < 0.6 && m.u_height_counts < 1.0,
                "{m:?} vs {h}"
            ),
            (Err(e), Err(kind)) => assert_eq!(e.kind(), kind, "{e}"),
            (got, want) => panic!("{got:?} but expected {want:?}"),
        }
    }

    #[test]
    fn steps_are_measured_or_rejected_with_a_reason() {
        check(&[(30.0, 0.2, 84.0)], None, Ok(84.0));
        check(&[(30.0, -0.1, -80.0)], None, Ok(80.0));
        check(&[], None, Err("no_edge"));
        check(&[(30.0, 0.0, 168.0)], None, Err("double_step"));
        check(
            &[(30.0, 0.0, 84.0), (31.5, 0.0, 84.0)],
            None,
            Err("double_step"),
        );
        check(
            &[(18.0, 0.0, 84.0), (46.0, 0.0, 84.0)],
            None,
            Err("multiple_edges"),
        );
        check(&[(30.0, 0.0, 84.0)], Some((16, 1.3)), Err("tip_change"));
        check(&[(30.0, 0.0, 140.0)], None, Err("implausible_height"));
        check(&[(2.0, 0.0, 84.0)], None, Err("edge_near_border"));
    }

    /// The streamed solve is the kernel's least squares: on random lines, the common slope of
    /// z = c_line + g·i + H·u (one offset per line) from [`spm_regression::least_squares`] on
    /// the dense design, and each line's height from the kernel's fit of that line's
    /// z − g·i = c + H·u, equal [`solve_lines`] to 1e-9.
    #[test]
    fn solve_lines_is_the_kernel_least_squares() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(28);
        let n_lines = 7;
        let mut lines = Vec::new();
        let mut pixels: Vec<(usize, f64, f64, f64)> = Vec::new(); // (line, i, u, z)
        for j in 0..n_lines {
            let offset: f64 = rng.random_range(-5.0..5.0);
            let height: f64 = rng.random_range(1.0..3.0);
            let edge = rng.random_range(10..30);
            let (mut lo, mut hi) = ([0.0; 5], [0.0; 5]);
            for i in 0..40 {
                let x = f64::from(i);
                let u = if i >= edge { 1.0 } else { 0.0 };
                let z = offset + 0.03 * x + height * u + rng.random_range(-0.2..0.2);
                let t = if i >= edge { &mut hi } else { &mut lo };
                t[0] += 1.0;
                t[1] += x;
                t[2] += z;
                t[3] += x * x;
                t[4] += x * z;
                pixels.push((j, x, u, z));
            }
            lines.push(Line { j, lo, hi });
        }
        let (g, heights) = solve_lines(&lines);
        let rows: Vec<Vec<f64>> = pixels
            .iter()
            .map(|&(line, x, u, _)| {
                let mut row: Vec<f64> = (0..n_lines)
                    .map(|k| f64::from(u8::from(k == line)))
                    .collect();
                row.extend([x, u]);
                row
            })
            .collect();
        let rhs: Vec<f64> = pixels.iter().map(|p| p.3).collect();
        let fit = spm_regression::least_squares(&rows, &rhs, &vec![false; n_lines + 2]).unwrap();
        assert!(
            (g - fit.coefficients[n_lines]).abs() < 1e-9,
            "{g} vs {:?}",
            fit.coefficients
        );
        for (j, h) in heights.iter().enumerate() {
            let line: Vec<_> = pixels.iter().filter(|p| p.0 == j).collect();
            let rows: Vec<Vec<f64>> = line.iter().map(|p| vec![1.0, p.2]).collect();
            let rhs: Vec<f64> = line.iter().map(|p| p.3 - g * p.1).collect();
            let per_line = spm_regression::least_squares(&rows, &rhs, &[false, false]).unwrap();
            assert!((h - per_line.coefficients[1]).abs() < 1e-9, "line {j}: {h}");
        }
    }
}
