//! Local shift between the trace and the retrace of the same lines: where the retrace shows
//! what the trace showed at each column (the raster's hysteresis, creep and signal lag
//! separate the two; issue 23's dynamics stage measures them from these shifts).
//!
//! Both halves in scanner geometry (columns increasing with x), row-major. Each row is
//! levelled (its mean removed). In windows of `window_px` columns every `step_px`, the
//! normalised cross-correlation over all rows is maximised over integer shifts around a
//! prediction and refined by a parabola through the peak and its neighbours. On a periodic
//! standard a shift is ambiguous modulo the lattice period, so windows are tracked from the
//! first column (where trace and retrace meet after the previous line's retrace) with the
//! prediction extrapolated linearly from the two previous windows, searched ±`search_px`.
//!
//! Pure: no IO, no clock.

use crate::error::FeatureError;

/// Parameters of [`trace_retrace_shifts`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShiftConfig {
    /// Window width, pixels (≥ 4). Default 16.
    pub window_px: usize,
    /// Distance between window centres, pixels (≥ 1). Default 4.
    pub step_px: usize,
    /// Search half-width around the prediction, pixels (≥ 1). Default 1.
    pub search_px: usize,
    /// Windows with a smaller peak correlation are reported but not used for prediction.
    /// Default 0.5.
    pub min_correlation: f64,
}

impl Default for ShiftConfig {
    fn default() -> Self {
        Self {
            window_px: 16,
            step_px: 4,
            search_px: 1,
            min_correlation: 0.5,
        }
    }
}

/// The shift at one window.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColumnShift {
    /// Window centre, trace column (pixels, fractional).
    pub column: f64,
    /// The retrace shows at `column + shift_px` what the trace shows at `column`, pixels.
    pub shift_px: f64,
    /// Peak normalised correlation, [−1, 1].
    pub correlation: f64,
}

/// Tracks the trace → retrace shift along the lines from both ends (module docs): from the
/// first column rightwards and from the last column leftwards (both ends are reversal points,
/// where the branches meet). A window is returned only where both trackings agree to within
/// 0.5 pixel (`AGREEMENT_PX`); one that slipped a lattice period disagrees from the slip on.
/// Returns the agreeing windows and how many windows disagreed.
///
/// # Errors
/// As the one-way tracking: [`FeatureError::InconsistentMap`], [`FeatureError::NonFinite`],
/// [`FeatureError::MapTooSmall`], [`FeatureError::InvalidConfig`].
pub fn trace_retrace_shifts(
    trace: &[f64],
    retrace: &[f64],
    columns: usize,
    rows: usize,
    config: &ShiftConfig,
) -> Result<(Vec<ColumnShift>, usize), FeatureError> {
    let forward = track_one_way(trace, retrace, columns, rows, config)?;
    let mirror = |img: &[f64]| -> Vec<f64> {
        img.chunks(columns)
            .flat_map(|row| row.iter().rev().copied())
            .collect()
    };
    let backward = track_one_way(&mirror(trace), &mirror(retrace), columns, rows, config)?;
    let last = (columns - 1) as f64;
    // The right-to-left tracking in trace columns, increasing.
    let mut other: Vec<(f64, f64)> = backward
        .iter()
        .map(|b| (last - b.column, -b.shift_px))
        .collect();
    other.sort_by(|p, q| p.0.total_cmp(&q.0));
    let mut agreeing = Vec::new();
    let mut disagreeing = 0;
    for a in &forward {
        let k = other.partition_point(|p| p.0 < a.column);
        let (Some(lo), Some(hi)) = (k.checked_sub(1).and_then(|i| other.get(i)), other.get(k))
        else {
            continue;
        };
        if hi.0 - lo.0 > 2.0 * config.step_px as f64 {
            continue;
        }
        let f = if hi.0 > lo.0 {
            (a.column - lo.0) / (hi.0 - lo.0)
        } else {
            0.0
        };
        let b_shift = lo.1 + f * (hi.1 - lo.1);
        if (a.shift_px - b_shift).abs() <= AGREEMENT_PX {
            agreeing.push(ColumnShift {
                column: a.column,
                shift_px: 0.5 * (a.shift_px + b_shift),
                correlation: a.correlation,
            });
        } else {
            disagreeing += 1;
        }
    }
    Ok((agreeing, disagreeing))
}

/// The shift along the slow axis between the two frames of a counter-scanned pair: `up`
/// (lines stepping +y) and `down` (the same region at once stepping −y), both in scanner
/// geometry (`columns` × `rows`, row-major, row index growing with y). Returns per window of
/// rows: the `up` row at the window's centre (`column` of the result, in rows) and where
/// `down` shows what `up` shows there (`shift_px`, rows). Tracked from the top row down
/// (where the two frames meet in time, so the shift starts near zero), each column of the
/// frames a profile along y ([`track_one_way`] on the transposed frames).
///
/// # Errors
/// As [`track_one_way`].
pub fn counter_pair_shifts(
    up: &[f64],
    down: &[f64],
    columns: usize,
    rows: usize,
    config: &ShiftConfig,
) -> Result<Vec<ColumnShift>, FeatureError> {
    if up.len() != columns * rows || down.len() != columns * rows {
        return Err(FeatureError::InconsistentMap {
            columns,
            rows,
            z_len: up.len().min(down.len()),
            time_len: columns * rows,
        });
    }
    // Transposed and reversed along y: profile c, sample k = row (rows − 1 − k).
    let profiles = |img: &[f64]| -> Vec<f64> {
        (0..columns)
            .flat_map(|c| (0..rows).rev().map(move |r| img[r * columns + c]))
            .collect()
    };
    let tracked = track_one_way(&profiles(up), &profiles(down), rows, columns, config)?;
    let last = (rows - 1) as f64;
    Ok(tracked
        .into_iter()
        .map(|t| ColumnShift {
            column: last - t.column,
            shift_px: -t.shift_px,
            correlation: t.correlation,
        })
        .collect())
}

/// Largest difference of the two trackings' shifts at one window, pixels.
pub const AGREEMENT_PX: f64 = 0.5;

/// Tracks the trace → retrace shift along the lines in one direction (module docs).
///
/// # Errors
/// [`FeatureError::InconsistentMap`] for arrays that do not match the size,
/// [`FeatureError::NonFinite`] for NaN/∞ heights, [`FeatureError::MapTooSmall`] when fewer
/// columns than two windows, [`FeatureError::InvalidConfig`] for a bad config.
pub fn track_one_way(
    trace: &[f64],
    retrace: &[f64],
    columns: usize,
    rows: usize,
    config: &ShiftConfig,
) -> Result<Vec<ColumnShift>, FeatureError> {
    let n = columns * rows;
    if n == 0 {
        return Err(FeatureError::MapTooSmall {
            columns,
            rows,
            min: 1,
        });
    }
    if trace.len() != n || retrace.len() != n {
        return Err(FeatureError::InconsistentMap {
            columns,
            rows,
            z_len: trace.len().min(retrace.len()),
            time_len: n,
        });
    }
    if let Some(index) = trace.iter().chain(retrace).position(|v| !v.is_finite()) {
        let index = index % n;
        return Err(FeatureError::NonFinite {
            what: "height",
            column: index % columns,
            row: index / columns,
        });
    }
    if config.window_px < 4 || config.step_px == 0 || config.search_px == 0 {
        return Err(FeatureError::InvalidConfig {
            field: "shift",
            reason: "window_px ≥ 4, step_px ≥ 1 and search_px ≥ 1 are required",
        });
    }
    if rows == 0 || columns < 2 * config.window_px + 2 * config.search_px {
        return Err(FeatureError::MapTooSmall {
            columns,
            rows,
            min: 2 * config.window_px + 2 * config.search_px,
        });
    }
    let level = |img: &[f64]| -> Vec<f64> {
        img.chunks(columns)
            .flat_map(|row| {
                let m = row.iter().sum::<f64>() / columns as f64;
                row.iter().map(move |v| v - m)
            })
            .collect()
    };
    let (a, b) = (level(trace), level(retrace));
    let w = config.window_px;
    // Correlation of the trace window at `start` with the retrace sampled at
    // x + shift + slope·(x − centre) (linear interpolation): the local stretch between the
    // branches is followed, so narrow periods stay in phase across the window.
    let correlation = |start: usize, shift: f64, slope: f64| -> Option<f64> {
        let centre = start as f64 + 0.5 * (w as f64 - 1.0);
        let (mut ab, mut aa, mut bb, mut sa, mut sb) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for r in 0..rows {
            let rb = &b[r * columns..(r + 1) * columns];
            for k in start..start + w {
                let x = k as f64;
                let p = x + shift + slope * (x - centre);
                if p < 0.0 || p > (columns - 1) as f64 {
                    return None;
                }
                let i = (p.floor() as usize).min(columns - 2);
                let f = p - i as f64;
                let y = rb[i] * (1.0 - f) + rb[i + 1] * f;
                let xv = a[r * columns + k];
                ab += xv * y;
                aa += xv * xv;
                bb += y * y;
                sa += xv;
                sb += y;
            }
        }
        let m = (rows * w) as f64;
        let cov = ab - sa * sb / m;
        let va = aa - sa * sa / m;
        let vb = bb - sb * sb / m;
        (va > 0.0 && vb > 0.0).then(|| cov / (va * vb).sqrt())
    };
    let mut out = Vec::new();
    let mut history: Vec<(f64, f64)> = Vec::new(); // (column, shift) of trusted windows
    let mut start = 0;
    // Sub-pixel search grid: quarter pixels.
    const SUB: f64 = 0.25;
    const SLOPE_STEP: f64 = 0.01;
    const MAX_SLOPE_STEPS: i64 = 25;
    while start + w <= columns {
        let column = start as f64 + 0.5 * (w as f64 - 1.0);
        let (predicted, slope) = match history.as_slice() {
            [] => (0.0, 0.0),
            [(_, p)] => (*p, 0.0),
            [.., (c2, p2), (c1, p1)] => {
                let d = (p1 - p2) / (c1 - c2);
                (p1 + d * (column - c1), d)
            }
        };
        let steps = (config.search_px as f64 / SUB).round() as i64;
        // Until two windows are trusted, the local stretch is searched too.
        let slopes: Vec<f64> = if history.len() < 2 {
            (-MAX_SLOPE_STEPS..=MAX_SLOPE_STEPS)
                .map(|j| slope + j as f64 * SLOPE_STEP)
                .collect()
        } else {
            vec![slope]
        };
        let mut best: Option<(i64, f64)> = None;
        let mut slope = slope;
        for &trial in &slopes {
            for k in -steps..=steps {
                if let Some(c) = correlation(start, predicted + k as f64 * SUB, trial)
                    && best.is_none_or(|(_, b)| c > b)
                {
                    best = Some((k, c));
                    slope = trial;
                }
            }
        }
        if let Some((k, c)) = best {
            let at = |j: i64| correlation(start, predicted + j as f64 * SUB, slope);
            let refined = match (at(k - 1), at(k + 1)) {
                (Some(l), Some(r)) => {
                    let d = l - 2.0 * c + r;
                    if d < 0.0 {
                        (0.5 * (l - r) / d).clamp(-0.5, 0.5)
                    } else {
                        0.0
                    }
                }
                _ => 0.0,
            };
            let shift_px = predicted + (k as f64 + refined) * SUB;
            out.push(ColumnShift {
                column,
                shift_px,
                correlation: c,
            });
            if c >= config.min_correlation {
                history.push((column, shift_px));
            }
        }
        start += config.step_px;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// A counter-scanned pair: `down` shows at row y + s(y) what `up` shows at y, s growing
    /// from 0 at the top (the pair's turning point) to 9 rows at the bottom; the tracked
    /// shifts follow it in `up`'s rows.
    #[test]
    fn a_counter_pair_shift_is_tracked_from_the_top() {
        let (columns, rows) = (4, 900);
        let truth = |y: f64| 9.0 * ((rows - 1) as f64 - y) / (rows - 1) as f64;
        let pattern = |y: f64, c: usize| {
            (2.0 * std::f64::consts::PI * y / 3.4 + 0.9 * c as f64).cos()
                + 0.3 * (y * 0.41 + c as f64).sin()
        };
        let mut up = Vec::new();
        let mut down = Vec::new();
        for r in 0..rows {
            for c in 0..columns {
                let y = r as f64;
                up.push(pattern(y, c));
                let mut y0 = y;
                for _ in 0..60 {
                    y0 = y - truth(y0);
                }
                down.push(pattern(y0, c));
            }
        }
        let shifts =
            counter_pair_shifts(&up, &down, columns, rows, &ShiftConfig::default()).unwrap();
        assert!(shifts.len() > 150, "{}", shifts.len());
        for s in &shifts {
            assert!(
                (s.shift_px - truth(s.column)).abs() < 0.15,
                "row {}: {} vs {}",
                s.column,
                s.shift_px,
                truth(s.column)
            );
        }
        assert!(shifts.iter().any(|s| s.shift_px > 8.0));
    }

    /// A pattern of period 3.1 px sampled at a known, smoothly growing shift s(x) (up to many
    /// periods): the tracked shifts follow it.
    #[test]
    fn a_growing_shift_is_tracked_beyond_the_period() {
        let (columns, rows) = (1200, 3);
        let truth = |x: f64| 40.0 * (std::f64::consts::PI * x / 1200.0).sin(); // 0 → 40 → 0 px
        let pattern = |x: f64, r: usize| {
            (2.0 * std::f64::consts::PI * x / 3.1).cos() + 0.4 * (x * 0.37 + r as f64).sin()
        };
        let mut trace = Vec::new();
        let mut retrace = Vec::new();
        for r in 0..rows {
            for c in 0..columns {
                let x = c as f64;
                trace.push(pattern(x, r));
                // The retrace shows at column x + s(x) what the trace shows at x.
                // Invert x' = x + s(x) by fixed point.
                let mut x0 = x;
                for _ in 0..50 {
                    x0 = x - truth(x0);
                }
                retrace.push(pattern(x0, r));
            }
        }
        let (shifts, disagreeing) =
            trace_retrace_shifts(&trace, &retrace, columns, rows, &ShiftConfig::default()).unwrap();
        assert_eq!(disagreeing, 0);
        assert!(shifts.len() > 100);
        let mut worst: f64 = 0.0;
        for s in shifts
            .iter()
            .filter(|s| s.column + s.shift_px + 12.0 < columns as f64)
        {
            worst = worst.max((s.shift_px - truth(s.column)).abs());
        }
        assert!(worst < 0.25, "worst {worst}");
    }

    #[test]
    fn bad_input_is_refused() {
        let cfg = ShiftConfig::default();
        assert!(trace_retrace_shifts(&[0.0; 10], &[0.0; 9], 10, 1, &cfg).is_err());
        assert!(trace_retrace_shifts(&[0.0; 10], &[0.0; 10], 10, 1, &cfg).is_err());
        let mut t = vec![0.0; 100];
        t[3] = f64::NAN;
        assert!(trace_retrace_shifts(&t, &[0.0; 100], 100, 1, &cfg).is_err());
    }
}
