//! The dynamics stage (issue 23): trace/retrace rasters of the standard at a ladder of line
//! lengths and two line rates, at a few places in the field, through any [`Microscope`].
//! The standard's lattice is the only ruler: what the trace shows at one column the retrace
//! shows elsewhere, by the raster's hysteresis, its creep and the signal's lag, which
//! `spm_correction::hysteresis::fit_dynamics` separates (amplitude dependent, rate
//! independent: hysteresis; rate dependent: creep and lag).
//!
//! The stage only scans; the frames go to the caller with the run's command log.

use serde::{Deserialize, Serialize};
use spm_hal::{
    Capabilities, CountPoint, Counts, CountsPerSecond, Frame, Microscope, MoveRequest,
    ScanDirection, ScanRequest, Seconds,
};

use crate::config::StandardConfig;

/// The dynamics stage of a plan (`[dynamics]`); absent in a plan file = the defaults, so old
/// plans stay valid and gain the stage. `enabled = false` skips it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DynamicsConfig {
    /// Run the stage. Default true.
    pub enabled: bool,
    /// Line lengths of the ladder, counts (≥ 3 sizes spanning ≥ 10×). Default
    /// [512, 2048, 8192, 16384]; each is cut to what the instrument's pixels per line allow
    /// (16384 becomes 12285 at 4096 pixels of 3 counts).
    pub ladder_counts: Vec<f64>,
    /// Pixels per lattice constant along the lines (sets the pixel step from the standard's
    /// lattice constant and nominal sensitivity). Default 4.
    pub pixels_per_lattice_constant: f64,
    /// Lines per frame (trace + retrace each; the first, which follows the approach, is not
    /// used). Default 8: with fewer, lines of thousands of pixels lose the lattice's phase
    /// between trace and retrace somewhere (sim-hopg, 3 counts per pixel).
    pub lines: u32,
    /// Pixel dwells, s: two line rates. Default [1e-4, 4e-4].
    pub pixel_dwells_s: Vec<f64>,
    /// Places, as fractions (−1…1) of the net's half-extent from its centre. Default the
    /// centre and two opposite diagonal points at ±0.5.
    pub places: Vec<[f64; 2]>,
    /// Wait at each frame's centre before scanning it, s: the creep of the move there must
    /// not shift the retrace against the trace by a lattice period. Default 10.
    pub settle_s: f64,
    /// Speed of the move to each frame, counts/s. Default 20 000.
    pub move_speed_counts_per_s: f64,
    /// Counter-scanned pairs for the slow axis: at each place and ladder length, a tall frame
    /// of [`Self::slow_axis_columns`] columns whose lines step +y over the length, then at once
    /// the same frame stepping −y. A sample point is seen on the way up and on the way down,
    /// so the pair shows the slow axis's hysteresis loop (issue 23). Default true.
    pub slow_axis_pairs: bool,
    /// Pixels per line of the slow-axis frames (≥ 2). Default 4: narrow and fast, so the
    /// drift between a point's two sightings stays under a pixel. A count the controller
    /// cannot scan as asked at its pixels-per-line granularity is rounded up to one it can,
    /// at the same line time ([`slow_axis_raster`]); 4 is scanned as asked by every backend
    /// (a Nanonis controller samples each line 16 times and averages each pixel's 4).
    pub slow_axis_columns: u32,
    /// Pixel dwell of the slow-axis frames, s. Default 5e-5.
    pub slow_axis_dwell_s: f64,
    /// The slow-axis pairs are scanned at the first this many [`Self::places`] (≥ 1); absent:
    /// at every place. The slow axis's loop is one operator for the whole field; more places
    /// average its tracking, fewer save their scans (a smoke plan scans them at one).
    pub slow_axis_pair_places: Option<usize>,
}

impl Default for DynamicsConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            ladder_counts: vec![512.0, 2048.0, 8192.0, 16384.0],
            pixels_per_lattice_constant: 4.0,
            lines: 8,
            pixel_dwells_s: vec![1e-4, 4e-4],
            places: vec![[0.0, 0.0], [-0.5, 0.5], [0.5, -0.5]],
            settle_s: 10.0,
            move_speed_counts_per_s: 20_000.0,
            slow_axis_pairs: true,
            slow_axis_columns: 4,
            slow_axis_dwell_s: 5e-5,
            slow_axis_pair_places: None,
        }
    }
}

impl DynamicsConfig {
    /// Checks the values; the error names the field.
    ///
    /// # Errors
    /// `(field, reason)`.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if self
            .ladder_counts
            .iter()
            .any(|l| !(l.is_finite() && *l > 0.0))
        {
            return Err(("dynamics.ladder_counts", "lengths must be > 0".into()));
        }
        if self.enabled {
            let (lo, hi) = self
                .ladder_counts
                .iter()
                .fold((f64::INFINITY, 0.0_f64), |(lo, hi), &l| {
                    (lo.min(l), hi.max(l))
                });
            if self.ladder_counts.len() < 3 || hi < 10.0 * lo {
                return Err((
                    "dynamics.ladder_counts",
                    "at least 3 sizes spanning at least 10× are needed".into(),
                ));
            }
            if self.pixel_dwells_s.len() < 2 {
                return Err((
                    "dynamics.pixel_dwells_s",
                    "two line rates are needed".into(),
                ));
            }
        }
        if !(self.pixels_per_lattice_constant.is_finite()
            && self.pixels_per_lattice_constant >= 2.5)
        {
            return Err((
                "dynamics.pixels_per_lattice_constant",
                "must be ≥ 2.5 (the lattice must be resolved)".into(),
            ));
        }
        if !(self.settle_s.is_finite() && self.settle_s >= 0.0) {
            return Err(("dynamics.settle_s", "must be ≥ 0".into()));
        }
        if !(self.move_speed_counts_per_s.is_finite() && self.move_speed_counts_per_s > 0.0) {
            return Err(("dynamics.move_speed_counts_per_s", "must be > 0".into()));
        }
        if self.lines == 0 {
            return Err(("dynamics.lines", "must be ≥ 1".into()));
        }
        if self.slow_axis_columns < 2 {
            return Err(("dynamics.slow_axis_columns", "must be ≥ 2".into()));
        }
        if !(self.slow_axis_dwell_s.is_finite() && self.slow_axis_dwell_s > 0.0) {
            return Err(("dynamics.slow_axis_dwell_s", "must be > 0".into()));
        }
        if self.slow_axis_pair_places == Some(0) {
            return Err(("dynamics.slow_axis_pair_places", "must be ≥ 1".into()));
        }
        if self
            .pixel_dwells_s
            .iter()
            .any(|d| !(d.is_finite() && *d > 0.0))
        {
            return Err(("dynamics.pixel_dwells_s", "dwells must be > 0".into()));
        }
        if self
            .places
            .iter()
            .any(|p| !(p[0].abs() <= 1.0 && p[1].abs() <= 1.0))
        {
            return Err(("dynamics.places", "fractions must lie in [−1, 1]".into()));
        }
        Ok(())
    }

    /// The pixel step for a standard, counts (≥ 1).
    #[must_use]
    pub fn pixel_step_counts(&self, standard: &StandardConfig) -> f64 {
        (standard.lattice_constant_nm
            / standard.nominal_nm_per_count
            / self.pixels_per_lattice_constant)
            .floor()
            .max(1.0)
    }
}

/// One ladder raster as scanned.
#[derive(Debug, Clone, PartialEq)]
pub struct LadderFrame {
    /// Place index in the config.
    pub place: usize,
    /// Line length (a slow-axis frame: its height), counts.
    pub length_counts: f64,
    /// The frame (forward and backward halves).
    pub frame: Frame,
    /// `None` for a fast-axis frame (long lines along x); for a slow-axis frame, which half
    /// of its counter-scanned pair it is.
    pub slow_axis: Option<ScanDirection>,
}

/// Attempts per ladder frame: a transient failure (timeout, lost communication, feedback
/// loss) is retried, as the net's visits are.
pub const FRAME_ATTEMPTS: u32 = 3;

/// The ladder as scanned, and the frames that could not be taken.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct LadderScan {
    /// The frames taken.
    pub frames: Vec<LadderFrame>,
    /// Why each frame that is missing is missing (the backend's error).
    pub failures: Vec<String>,
}

/// Scans the ladder at every place and dwell (place, dwell, size order), centred on
/// `centre ± fraction·half_extent`, clipped to the instrument's pixels per line. A frame that
/// fails [`FRAME_ATTEMPTS`] times, or once with a lasting error (out of range), is skipped and
/// named in [`LadderScan::failures`]; the stage goes on.
pub fn scan_ladder<M: Microscope>(
    microscope: &mut M,
    config: &DynamicsConfig,
    standard: &StandardConfig,
    centre: CountPoint,
    half_extent_counts: [f64; 2],
) -> LadderScan {
    let step = config.pixel_step_counts(standard);
    let caps = microscope.capabilities();
    let max_pixels = caps.max_pixels_per_line.max(2);
    let mut out = LadderScan::default();
    for (place, fraction) in config.places.iter().enumerate() {
        let at = [
            centre.x.value() + fraction[0] * half_extent_counts[0],
            centre.y.value() + fraction[1] * half_extent_counts[1],
        ];
        for &dwell in &config.pixel_dwells_s {
            for &length in &config.ladder_counts {
                let pixels = ((length / step).round() as u32 + 1).clamp(2, max_pixels);
                let length = step * f64::from(pixels - 1);
                let request = ScanRequest {
                    origin: CountPoint::from_counts(
                        (at[0] - 0.5 * length).round(),
                        (at[1] - 0.5 * step * f64::from(config.lines)).round(),
                    ),
                    pixel_step: Counts(step),
                    pixels_per_line: pixels,
                    lines: config.lines,
                    direction: ScanDirection::Direct,
                    pixel_dwell: Seconds(dwell),
                    record_backward: true,
                };
                // Settled at the frame's centre, the raster's mean position: creep then has
                // little to relax towards during the frame (settled at a corner, it creeps
                // back towards the centre by counts per second through the first lines, a
                // trace/retrace shift of more than a lattice period at the line's start).
                let settle = MoveRequest {
                    target: CountPoint::from_counts(at[0].round(), at[1].round()),
                    speed: CountsPerSecond(config.move_speed_counts_per_s),
                    settle: Seconds(config.settle_s),
                };
                match with_attempts(|| {
                    microscope
                        .move_to(settle)
                        .and_then(|()| microscope.scan(&request))
                }) {
                    Ok(frame) => out.frames.push(LadderFrame {
                        place,
                        length_counts: length,
                        frame,
                        slow_axis: None,
                    }),
                    Err((e, attempt)) => out.failures.push(format!(
                        "place {place}, {length} counts at {dwell} s per pixel: {e} \
                         (attempt {attempt})"
                    )),
                }
            }
        }
        if config.slow_axis_pairs && config.slow_axis_pair_places.is_none_or(|n| place < n) {
            scan_slow_axis_pairs(microscope, config, step, place, at, &mut out);
        }
    }
    out
}

/// `take` until it succeeds, at most [`FRAME_ATTEMPTS`] times while its error is transient;
/// the lasting or last error with the attempt it ended.
fn with_attempts<T, E: spm_hal::Error>(
    mut take: impl FnMut() -> Result<T, E>,
) -> Result<T, (E, u32)> {
    let mut attempt = 0;
    loop {
        attempt += 1;
        match take() {
            Ok(value) => return Ok(value),
            Err(e) if e.kind().is_transient() && attempt < FRAME_ATTEMPTS => {}
            Err(e) => return Err((e, attempt)),
        }
    }
}

/// The slow-axis frames' pixels per line and pixel dwell, s, on an instrument of `caps`:
/// [`DynamicsConfig::slow_axis_columns`] at [`DynamicsConfig::slow_axis_dwell_s`] (within the
/// instrument's pixels per line and shortest dwell), rounded up to the next count the
/// controller scans as asked at its granularity
/// ([`Capabilities::honours_pixels_per_line`]: 4 of a Nanonis controller's 16 is scanned in
/// its own frame and line time, 3 would be padded to 16 at 3's step and dwell, 5.3 times the
/// line time), the dwell divided so that the line time stays the configured one. At the
/// default 4 columns nothing changes at granularity 1 or 16: the frame, its width in counts
/// and its line time are the same on every backend, and so is the physics it measures.
#[must_use]
pub fn slow_axis_raster(config: &DynamicsConfig, caps: &Capabilities) -> (u32, f64) {
    let max_pixels = caps.max_pixels_per_line.max(2);
    let asked = config.slow_axis_columns.min(max_pixels);
    let columns = (asked..=max_pixels)
        .find(|&c| caps.honours_pixels_per_line(c))
        .unwrap_or(asked);
    let line_s = f64::from(asked) * config.slow_axis_dwell_s;
    let dwell_s = (line_s / f64::from(columns)).max(caps.min_pixel_dwell.value());
    (columns, dwell_s)
}

/// The counter-scanned pairs of one place ([`DynamicsConfig::slow_axis_pairs`]): settled at
/// the frame's centre, the frame stepping +y, then at once the frame stepping −y. A pair
/// with a failed half is dropped whole (and named).
fn scan_slow_axis_pairs<M: Microscope>(
    microscope: &mut M,
    config: &DynamicsConfig,
    step: f64,
    place: usize,
    at: [f64; 2],
    out: &mut LadderScan,
) {
    let caps = microscope.capabilities();
    if !caps.counter_scan {
        out.failures.push(format!(
            "place {place}: no slow-axis pairs (the instrument cannot scan a counter raster)"
        ));
        return;
    }
    let (columns, dwell_s) = slow_axis_raster(config, &caps);
    for &length in &config.ladder_counts {
        let lines = ((length / step).round() as u32 + 1).clamp(2, caps.max_lines.max(2));
        let length = step * f64::from(lines - 1);
        let request = |direction| ScanRequest {
            origin: CountPoint::from_counts(
                (at[0] - 0.5 * step * f64::from(columns - 1)).round(),
                (at[1] - 0.5 * length).round(),
            ),
            pixel_step: Counts(step),
            pixels_per_line: columns,
            lines,
            direction,
            pixel_dwell: Seconds(dwell_s),
            record_backward: true,
        };
        let settle = MoveRequest {
            target: CountPoint::from_counts(at[0].round(), at[1].round()),
            speed: CountsPerSecond(config.move_speed_counts_per_s),
            settle: Seconds(config.settle_s),
        };
        let taken = with_attempts(|| {
            microscope.move_to(settle)?;
            let up = microscope.scan(&request(ScanDirection::Direct))?;
            let down = microscope.scan(&request(ScanDirection::Counter))?;
            Ok::<_, M::Error>((up, down))
        });
        match taken {
            Ok((up, down)) => {
                for (frame, direction) in
                    [(up, ScanDirection::Direct), (down, ScanDirection::Counter)]
                {
                    out.frames.push(LadderFrame {
                        place,
                        length_counts: length,
                        frame,
                        slow_axis: Some(direction),
                    });
                }
            }
            Err((e, attempt)) => out.failures.push(format!(
                "place {place}, slow-axis pair of {length} counts: {e} (attempt {attempt})"
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// Three short ladder lines at one dwell, at the field's centre, 2 lines per frame.
    fn small_ladder() -> DynamicsConfig {
        DynamicsConfig {
            ladder_counts: vec![64.0, 128.0, 256.0],
            pixel_dwells_s: vec![1e-4],
            places: vec![[0.0, 0.0]],
            lines: 2,
            ..DynamicsConfig::default()
        }
    }

    /// [`scan_ladder`] of the small HOPG plan's standard around the origin.
    fn scan_small<M: Microscope>(microscope: &mut M, config: &DynamicsConfig) -> LadderScan {
        let standard = crate::PlanConfig::hopg_small_net().standard;
        scan_ladder(
            microscope,
            config,
            &standard,
            CountPoint::from_counts(0.0, 0.0),
            [1000.0, 1000.0],
        )
    }

    /// Transient failures are retried up to FRAME_ATTEMPTS; a lasting one skips the frame and
    /// is named; the stage goes on either way.
    #[test]
    fn transient_failures_are_retried_and_lasting_ones_skip_the_frame() {
        use spm_hal::ErrorKind;
        use spm_hal::mock::{Expectation, Operation, ScriptedMicroscope};
        let mut mock = ScriptedMicroscope::new(ScriptedMicroscope::default_capabilities())
            .lenient_moves_and_waits(true);
        mock.expect_all([
            Expectation::fault(Operation::Scan, ErrorKind::Timeout),
            Expectation::fault(Operation::Scan, ErrorKind::Communication),
            Expectation::scan(|_, _| Counts(0.0)),
            Expectation::fault(Operation::Scan, ErrorKind::OutOfRange),
            Expectation::fault(Operation::Scan, ErrorKind::Timeout),
            Expectation::fault(Operation::Scan, ErrorKind::Timeout),
            Expectation::fault(Operation::Scan, ErrorKind::Timeout),
        ]);
        let config = DynamicsConfig {
            slow_axis_pairs: false,
            ..small_ladder()
        };
        let scan = scan_small(&mut mock, &config);
        assert_eq!(scan.frames.len(), 1, "{:?}", scan.failures);
        // 64 counts at the 3-count step (4 pixels per HOPG lattice constant): 21 steps.
        assert_eq!(scan.frames[0].length_counts, 63.0);
        assert_eq!(scan.failures.len(), 2, "{:?}", scan.failures);
        assert!(
            scan.failures[0].contains("attempt 1"),
            "{:?}",
            scan.failures
        );
        assert!(
            scan.failures[1].contains("attempt 3"),
            "{:?}",
            scan.failures
        );
        mock.done().unwrap();
    }

    /// Each place's slow-axis pairs follow its fast-axis frames: per length, the frame
    /// stepping +y then the one stepping −y over the same region (tall: the length over the
    /// lines, `slow_axis_columns` wide, at the slow-axis dwell); a pair with a failed half is
    /// dropped whole and named.
    #[test]
    fn slow_axis_pairs_scan_the_same_tall_region_up_then_down() {
        use spm_hal::ErrorKind;
        use spm_hal::mock::{Expectation, Operation, ScriptedMicroscope};
        let mut mock = ScriptedMicroscope::new(ScriptedMicroscope::default_capabilities())
            .lenient_moves_and_waits(true);
        let ok = || Expectation::scan(|_, _| Counts(0.0));
        mock.expect_all([
            ok(),
            ok(),
            ok(),
            ok(),
            ok(),
            ok(),
            Expectation::fault(Operation::Scan, ErrorKind::OutOfRange),
            ok(),
            ok(),
        ]);
        let config = small_ladder();
        let scan = scan_small(&mut mock, &config);
        assert_eq!(scan.failures.len(), 1, "{:?}", scan.failures);
        assert!(
            scan.failures[0].contains("slow-axis pair of 129"),
            "{:?}",
            scan.failures
        );
        let slow: Vec<&LadderFrame> = scan
            .frames
            .iter()
            .filter(|f| f.slow_axis.is_some())
            .collect();
        assert_eq!(scan.frames.len() - slow.len(), 3);
        assert_eq!(slow.len(), 4);
        for pair in slow.chunks(2) {
            let (up, down) = (&pair[0], &pair[1]);
            assert_eq!(up.slow_axis, Some(ScanDirection::Direct));
            assert_eq!(down.slow_axis, Some(ScanDirection::Counter));
            assert_eq!(up.frame.request.direction, ScanDirection::Direct);
            assert_eq!(down.frame.request.direction, ScanDirection::Counter);
            for f in [up, down] {
                let r = &f.frame.request;
                assert_eq!(r.pixels_per_line, 4);
                assert_eq!(r.pixel_dwell, Seconds(5e-5));
                // The height spans the length: lines − 1 steps of 3 counts.
                assert_eq!(
                    f64::from(r.lines - 1) * r.pixel_step.value(),
                    f.length_counts
                );
                assert_eq!(r.origin, up.frame.request.origin);
            }
        }
        assert_eq!(slow[0].length_counts, 63.0);
        assert_eq!(slow[2].length_counts, 255.0);
    }

    /// The tall frames of each pair at a controller granularity of 16 pixels per line (a
    /// Nanonis controller's) against granularity 1 (the simulator's, the virtual
    /// backend's): the controller acquires a multiple of 16 pixels per line, and scans the
    /// frames as asked (no padding), with the frame's width in counts, its line time and its
    /// pixel centres those of granularity 1. A count it would pad (3) is rounded up to one it
    /// scans as asked (4), at the configured line time.
    #[test]
    fn at_a_granularity_of_16_the_tall_frames_keep_their_width_and_line_time() {
        use spm_hal::mock::{Expectation, ScriptedMicroscope};
        let tall_frames = |multiple: u32, columns: u32| -> Vec<ScanRequest> {
            let caps = Capabilities {
                pixels_per_line_multiple: multiple,
                ..ScriptedMicroscope::default_capabilities()
            };
            let mut mock = ScriptedMicroscope::new(caps).lenient_moves_and_waits(true);
            mock.expect_all((0..9).map(|_| Expectation::scan(|_, _| Counts(0.0))));
            let config = DynamicsConfig {
                slow_axis_columns: columns,
                ..small_ladder()
            };
            let scan = scan_small(&mut mock, &config);
            assert!(scan.failures.is_empty(), "{:?}", scan.failures);
            mock.done().unwrap();
            scan.frames
                .into_iter()
                .filter(|f| f.slow_axis.is_some())
                .map(|f| f.frame.request)
                .collect()
        };
        let line_s = |r: &ScanRequest| f64::from(r.pixels_per_line) * r.pixel_dwell.value();
        let width_counts =
            |r: &ScanRequest| f64::from(r.pixels_per_line - 1) * r.pixel_step.value();
        let nanonis = Capabilities {
            pixels_per_line_multiple: 16,
            ..ScriptedMicroscope::default_capabilities()
        };
        let (one, sixteen) = (tall_frames(1, 4), tall_frames(16, 4));
        assert_eq!(one.len(), 6);
        assert_eq!(sixteen.len(), one.len());
        for (a, b) in one.iter().zip(&sixteen) {
            assert!(
                nanonis
                    .acquired_pixels_per_line(b.pixels_per_line)
                    .is_multiple_of(16)
            );
            assert!(nanonis.honours_pixels_per_line(b.pixels_per_line), "{b:?}");
            assert_eq!(line_s(b), line_s(a));
            assert_eq!(width_counts(b), width_counts(a));
            assert_eq!(b, a);
        }
        // 3 columns: padded to 16 they would take 16/3 of the line time.
        assert!(!nanonis.honours_pixels_per_line(3));
        let (one, sixteen) = (tall_frames(1, 3), tall_frames(16, 3));
        for (a, b) in one.iter().zip(&sixteen) {
            assert_eq!(a.pixels_per_line, 3);
            assert_eq!(b.pixels_per_line, 4);
            assert!(nanonis.honours_pixels_per_line(b.pixels_per_line));
            assert!((line_s(b) - line_s(a)).abs() <= 1e-15, "{b:?} {a:?}");
            assert_eq!((b.lines, b.pixel_step), (a.lines, a.pixel_step));
        }
    }

    /// `slow_axis_pair_places = 1`: the pairs at the first place only, the fast-axis frames at
    /// every place.
    #[test]
    fn slow_axis_pairs_can_be_limited_to_the_first_places() {
        use spm_hal::mock::{Expectation, ScriptedMicroscope};
        let mut mock = ScriptedMicroscope::new(ScriptedMicroscope::default_capabilities())
            .lenient_moves_and_waits(true);
        mock.expect_all((0..12).map(|_| Expectation::scan(|_, _| Counts(0.0))));
        let config = DynamicsConfig {
            ladder_counts: vec![64.0, 128.0, 256.0],
            pixel_dwells_s: vec![1e-4],
            places: vec![[0.0, 0.0], [0.5, 0.5]],
            lines: 2,
            slow_axis_pair_places: Some(1),
            ..small_ladder()
        };
        let scan = scan_small(&mut mock, &config);
        assert!(scan.failures.is_empty(), "{:?}", scan.failures);
        let fast: Vec<usize> = scan
            .frames
            .iter()
            .filter(|f| f.slow_axis.is_none())
            .map(|f| f.place)
            .collect();
        let slow: Vec<usize> = scan
            .frames
            .iter()
            .filter(|f| f.slow_axis.is_some())
            .map(|f| f.place)
            .collect();
        assert_eq!(fast, vec![0, 0, 0, 1, 1, 1]);
        assert_eq!(slow, vec![0; 6]);
    }

    #[test]
    fn the_defaults_validate_and_bad_ladders_are_refused() {
        DynamicsConfig::default().validate().unwrap();
        let short = DynamicsConfig {
            ladder_counts: vec![512.0, 1024.0, 2048.0],
            ..DynamicsConfig::default()
        };
        assert_eq!(short.validate().unwrap_err().0, "dynamics.ladder_counts");
        let one_rate = DynamicsConfig {
            pixel_dwells_s: vec![1e-4],
            ..DynamicsConfig::default()
        };
        assert_eq!(
            one_rate.validate().unwrap_err().0,
            "dynamics.pixel_dwells_s"
        );
        let off = DynamicsConfig {
            enabled: false,
            pixel_dwells_s: vec![1e-4],
            ..DynamicsConfig::default()
        };
        off.validate().unwrap();
        let one_column = DynamicsConfig {
            slow_axis_columns: 1,
            ..DynamicsConfig::default()
        };
        assert_eq!(
            one_column.validate().unwrap_err().0,
            "dynamics.slow_axis_columns"
        );
        let no_places = DynamicsConfig {
            slow_axis_pair_places: Some(0),
            ..DynamicsConfig::default()
        };
        assert_eq!(
            no_places.validate().unwrap_err().0,
            "dynamics.slow_axis_pair_places"
        );
        let no_dwell = DynamicsConfig {
            slow_axis_dwell_s: 0.0,
            ..DynamicsConfig::default()
        };
        assert_eq!(
            no_dwell.validate().unwrap_err().0,
            "dynamics.slow_axis_dwell_s"
        );
    }
}
