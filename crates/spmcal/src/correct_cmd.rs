//! `spmcal correct IMAGE... --calibration FILE (--out OUT.gwy|OUT.gsf | --out-dir DIR)`.
//!
//! Reads, writes and reports; what is corrected and how is `spm_apply` (the file's own
//! raster, the guard rails, one map for every channel, NaN where no data lies, provenance).

use crate::error::CliError;
use crate::{OutFormat, RasterDirection};
use spm_apply::history::ScanHistory;
use spm_apply::{ApplyError, ApplyOptions, ChannelSelection, Corrected, OutputKind, RasterPath};
use spm_correction::SurfaceSet;
use spm_formats::{Direction, ScanDir};
use std::path::{Path, PathBuf};

/// Largest calibration file read, bytes.
const MAX_CALIBRATION_BYTES: u64 = 64 << 20;

/// The command's arguments.
pub struct CorrectArgs<'a> {
    pub images: &'a [PathBuf],
    pub calibration: &'a Path,
    pub out: Option<&'a Path>,
    pub out_dir: Option<&'a Path>,
    pub format: OutFormat,
    pub channel: Option<&'a str>,
    pub direction: Option<RasterDirection>,
    pub nominal_nm_per_count: Option<f64>,
    pub z_counts: Option<f64>,
    pub scanner: Option<&'a str>,
    pub allow_extrapolation: bool,
    pub static_only: bool,
    pub ruler: Option<spm_apply::ruler::LatticeRuler>,
    /// `--counter FILE`.
    pub counter: Option<&'a Path>,
    /// `--counter-delay S`.
    pub counter_delay_s: Option<f64>,
    /// `--feature-nm NM`.
    pub feature_nm: Option<f64>,
}

fn apply_error(error: ApplyError, calibration: &Path) -> CliError {
    let text = match &error {
        ApplyError::Calibration { .. } => format!("{}: {error}", calibration.display()),
        _ => error.to_string(),
    };
    if error.is_bad_input() {
        CliError::BadInput(text)
    } else {
        CliError::RunFailed(text)
    }
}

/// Reads a calibration file (format 2, or a version-1 surfaces.json).
fn read_calibration(path: &Path) -> Result<SurfaceSet, CliError> {
    let bytes = crate::files::read_limited(path, "calibration file", MAX_CALIBRATION_BYTES)?;
    let text = String::from_utf8(bytes)
        .map_err(|_| CliError::BadInput(format!("{}: not UTF-8 text", path.display())))?;
    SurfaceSet::from_json_str(&text)
        .map_err(|e| CliError::BadInput(format!("{}: {e}", path.display())))
}

/// Where each image's output goes, checked before anything is read or written.
fn outputs(args: &CorrectArgs<'_>) -> Result<Vec<(PathBuf, OutputKind)>, CliError> {
    let bad = |e: ApplyError| CliError::BadInput(e.to_string());
    match (args.out, args.out_dir) {
        (Some(out), None) => {
            if args.images.len() != 1 {
                return Err(CliError::BadInput(format!(
                    "--out {}: {} images given; use --out-dir DIR for more than one",
                    out.display(),
                    args.images.len()
                )));
            }
            // An output that is an input is refused first: that is the worse mistake.
            let mut inputs: Vec<&Path> = args.images.iter().map(PathBuf::as_path).collect();
            inputs.push(args.calibration);
            crate::files::check_output(out, "--out", &inputs)?;
            let kind = OutputKind::of_path(out).map_err(bad)?;
            Ok(vec![(out.to_path_buf(), kind)])
        }
        (None, Some(dir)) => {
            let meta = std::fs::metadata(dir).map_err(|e| CliError::io(dir, e))?;
            if !meta.is_dir() {
                return Err(CliError::BadInput(format!(
                    "--out-dir {}: not a directory",
                    dir.display()
                )));
            }
            let (kind, ext) = match args.format {
                OutFormat::Gwy => (OutputKind::Gwy, "gwy"),
                OutFormat::Gsf => (OutputKind::Gsf, "gsf"),
            };
            let mut seen = std::collections::HashSet::new();
            args.images
                .iter()
                .map(|image| {
                    let stem = image
                        .file_stem()
                        .map_or_else(|| "image".into(), |s| s.to_string_lossy().into_owned());
                    let out = dir.join(format!("{stem}.corrected.{ext}"));
                    if !seen.insert(out.clone()) {
                        return Err(CliError::BadInput(format!(
                            "{}: two images would be written to {}; correct them into \
                             different directories",
                            image.display(),
                            out.display()
                        )));
                    }
                    Ok((out, kind))
                })
                .collect()
        }
        _ => Err(CliError::BadInput(
            "give --out FILE (one image) or --out-dir DIR".to_owned(),
        )),
    }
}

fn options(args: &CorrectArgs<'_>, kind: OutputKind) -> ApplyOptions {
    let channels = match args.channel {
        Some(name) if name.eq_ignore_ascii_case("all") => ChannelSelection::All,
        Some(name) => ChannelSelection::Named(name.to_owned()),
        None => match kind {
            OutputKind::Gwy => ChannelSelection::All,
            OutputKind::Gsf => ChannelSelection::Height,
        },
    };
    ApplyOptions {
        channels,
        nominal_nm_per_count: args.nominal_nm_per_count,
        z_counts: args.z_counts,
        allow_extrapolation: args.allow_extrapolation,
        scanner_id: args.scanner.map(str::to_owned),
        path: args.direction.map(|d| match d {
            RasterDirection::Direct => RasterPath::Trace(ScanDir::Up),
            RasterDirection::Counter => RasterPath::Counter,
        }),
        static_only: args.static_only,
        history: None,
        interpolation: spm_correction::Interpolation::Bilinear,
        ruler: args.ruler,
        counter: None,
    }
}

/// The counter-scanned partner of `--counter`, read and checked (one image per call).
fn counter_partner(args: &CorrectArgs<'_>) -> Result<Option<spm_apply::CounterPartner>, CliError> {
    let Some(path) = args.counter else {
        if args.counter_delay_s.is_some() || args.feature_nm.is_some() {
            return Err(CliError::BadInput(
                "--counter-delay and --feature-nm go with --counter FILE".to_owned(),
            ));
        }
        return Ok(None);
    };
    if args.images.len() != 1 {
        return Err(CliError::BadInput(format!(
            "--counter {}: one image per call has a counter partner ({} given)",
            path.display(),
            args.images.len()
        )));
    }
    if args.static_only {
        return Err(CliError::BadInput(format!(
            "--counter {}: the partner measures what the dynamics leave; not with --static",
            path.display()
        )));
    }
    if let Some(d) = args.counter_delay_s
        && !d.is_finite()
    {
        return Err(CliError::BadInput(format!(
            "--counter-delay {d}: must be a number"
        )));
    }
    let spacing = match (args.feature_nm, args.ruler) {
        (Some(nm), _) if nm.is_finite() && nm > 0.0 => spm_apply::ruler::LatticeRuler {
            constant_nm: nm,
            ..spm_apply::ruler::LatticeRuler::hopg()
        },
        (Some(nm), _) => {
            return Err(CliError::BadInput(format!(
                "--feature-nm {nm}: must be a number > 0"
            )));
        }
        (None, Some(ruler)) => ruler,
        (None, None) => {
            return Err(CliError::BadInput(format!(
                "--counter {}: give the spacing of the sample's features (--feature-nm NM) or \
                 its standard (--ruler)",
                path.display()
            )));
        }
    };
    crate::files::check_input(path, "counter partner")?;
    let file = spm_formats::read_any(path).map_err(|e| CliError::BadInput(e.to_string()))?;
    Ok(Some(spm_apply::CounterPartner {
        file,
        delay_s: args.counter_delay_s,
        spacing,
    }))
}

/// The command history an image was taken with: `IMAGE.history.json` beside it, written by
/// `spmcal scan` (none with `--static`).
fn history_of(image: &Path, args: &CorrectArgs<'_>) -> Result<Option<ScanHistory>, CliError> {
    let path = spm_apply::history::sidecar_of(image);
    if args.static_only || !path.is_file() {
        return Ok(None);
    }
    let bytes =
        crate::files::read_limited(&path, "history", spm_apply::history::MAX_HISTORY_BYTES)?;
    let text = String::from_utf8(bytes)
        .map_err(|_| CliError::BadInput(format!("{}: not UTF-8 text", path.display())))?;
    ScanHistory::from_json(&text, &path.display().to_string())
        .map(Some)
        .map_err(|e| CliError::BadInput(e.to_string()))
}

/// The file a channel of a multi-channel .gsf output goes to: OUT.CHANNEL.DIRECTION.gsf.
fn gsf_name(out: &Path, channel: &spm_formats::Channel) -> PathBuf {
    let stem = out
        .file_stem()
        .map_or_else(|| "out".into(), |s| s.to_string_lossy().into_owned());
    let name: String = channel
        .name()
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    let dir = match channel.direction() {
        Direction::Forward => "forward",
        Direction::Backward => "backward",
    };
    out.with_file_name(format!("{stem}.{name}.{dir}.gsf"))
}

/// Writes one corrected image; returns the files written.
fn write(
    corrected: &Corrected,
    out: &Path,
    kind: OutputKind,
    calibration: &Path,
    inputs: &[&Path],
) -> Result<Vec<PathBuf>, CliError> {
    let mut metadata = corrected.metadata.clone();
    metadata.insert(
        1,
        (
            "spmcal_calibration_file".to_owned(),
            calibration.display().to_string(),
        ),
    );
    write_channels(&corrected.channels, &metadata, out, kind, inputs)
}

/// Writes channels with their header: one `.gwy`, or one `.gsf` per channel (OUT.gsf for
/// one, OUT.CHANNEL.DIRECTION.gsf for several); returns the files written.
pub(crate) fn write_channels(
    channels: &[spm_formats::Channel],
    metadata: &[(String, String)],
    out: &Path,
    kind: OutputKind,
    inputs: &[&Path],
) -> Result<Vec<PathBuf>, CliError> {
    let targets: Vec<(PathBuf, Vec<&spm_formats::Channel>)> = match kind {
        OutputKind::Gwy => vec![(out.to_path_buf(), channels.iter().collect())],
        OutputKind::Gsf if channels.len() == 1 => {
            vec![(out.to_path_buf(), channels.iter().collect())]
        }
        OutputKind::Gsf => channels
            .iter()
            .map(|c| (gsf_name(out, c), vec![c]))
            .collect(),
    };
    for (path, _) in &targets {
        crate::files::check_output(path, "--out", inputs)?;
    }
    let mut written = Vec::new();
    for (path, channels) in targets {
        let bytes = match kind {
            OutputKind::Gwy => {
                let owned: Vec<spm_formats::Channel> = channels.into_iter().cloned().collect();
                spm_formats::encode_gwy(&owned, metadata)
            }
            OutputKind::Gsf => {
                let extra: Vec<(&str, &str)> = metadata
                    .iter()
                    .map(|(k, v)| (k.as_str(), v.as_str()))
                    .collect();
                match channels.first() {
                    Some(channel) => spm_formats::encode_gsf(channel, &extra),
                    None => continue,
                }
            }
        }
        .map_err(|e| CliError::RunFailed(format!("{}: {e}", path.display())))?;
        crate::files::write_atomically(&path, &bytes)?;
        written.push(path);
    }
    Ok(written)
}

pub fn run(args: &CorrectArgs<'_>) -> Result<(), CliError> {
    if let Some(k) = args.nominal_nm_per_count
        && !(k.is_finite() && k > 0.0)
    {
        return Err(CliError::BadInput(format!(
            "--nominal-nm-per-count {k}: must be a number > 0"
        )));
    }
    let outs = outputs(args)?;
    for image in args.images {
        crate::files::check_input(image, "image")?;
    }
    let counter = counter_partner(args)?;
    // Read once, after the first image (whose errors are reported first).
    let mut calibration: Option<SurfaceSet> = None;
    for (image, (out, kind)) in args.images.iter().zip(&outs) {
        let mut inputs: Vec<&Path> = args.images.iter().map(PathBuf::as_path).collect();
        inputs.push(args.calibration);
        inputs.extend(args.counter);
        crate::files::check_output(out, "--out", &inputs)?;
        let file = spm_formats::read_any(image).map_err(|e| CliError::BadInput(e.to_string()))?;
        let set = match calibration.take() {
            Some(set) => set,
            None => read_calibration(args.calibration)?,
        };
        let mut options = ApplyOptions {
            history: history_of(image, args)?,
            ..options(args, *kind)
        };
        if counter.is_some() {
            // With a partner the standard only names the feature spacing.
            options.ruler = None;
            options.counter.clone_from(&counter);
        }
        let corrected = spm_apply::correct_file(&file, &set, &options)
            .map_err(|e| apply_error(e, args.calibration))?;
        if file.header_value(spm_apply::KEY_SCANNER).is_none() && args.scanner.is_none() {
            use std::io::Write as _;
            let _ = writeln!(
                std::io::stderr(),
                "spmcal: warning: {}: the file does not name its scanner, so it was not checked \
                 against the calibration's ({:?}); give --scanner ID to check it",
                image.display(),
                set.provenance.scanner_id
            );
        }
        calibration = Some(set);
        let written = write(&corrected, out, *kind, args.calibration, &inputs)?;
        let first = corrected.channels.first();
        crate::outln!(
            "{} → {} ({} channel(s), {}×{} px of {:.4} nm; {} pixels without data are NaN; \
             expected error {:.3} nm; dynamics: {}{})",
            image.display(),
            written
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", "),
            corrected.channels.len(),
            first.map_or(0, |c| c.nx()),
            first.map_or(0, |c| c.ny()),
            corrected.step_nm,
            corrected.unknown_pixels,
            corrected.expected_error_nm,
            match corrected.dynamics {
                spm_apply::DynamicsUsed::None => "none (static field)",
                spm_apply::DynamicsUsed::NoLineTime =>
                    "none: the file states no line time (static field)",
                spm_apply::DynamicsUsed::Raster =>
                    "the raster's hysteresis and creep (approach creep unknown)",
                spm_apply::DynamicsUsed::Recorded =>
                    "the recorded history's hysteresis and creep (IMAGE.history.json)",
                spm_apply::DynamicsUsed::RasterRuler =>
                    "the raster's hysteresis and creep; approach creep and drift from the lattice",
                spm_apply::DynamicsUsed::RasterCounter =>
                    "the raster's hysteresis and creep; drift from the counter-scanned partner",
            },
            if corrected.extrapolated_counts.is_some() {
                "; EXTRAPOLATED beyond the calibrated region"
            } else {
                ""
            }
        );
    }
    Ok(())
}
