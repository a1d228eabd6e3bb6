//! `spmcal`: the command-line program of the spmcal workspace (DESIGN §13).
//!
//! Exit codes: 0 success; 1 a run failed (instrument, numerical); 2 bad usage or
//! bad input, with a message on stderr naming the file, line or field; 3 `calibrate`
//! finished and wrote its report, but missed a target its plan declares
//! (`[plan.targets]`; `--no-targets` exits 0 instead). A panic (101) is always a bug.

mod calibrate_cmd;
mod cdb_cmd;
mod console;
mod correct_cmd;
mod crop_cmd;
mod dates;
mod diagnose_cmd;
mod error;
mod files;
mod fit_cmd;
mod info;
mod lattice_cmd;
#[cfg(feature = "sim")]
mod nanonis_sim_cmd;
mod report_cmd;
mod scan_cmd;
#[cfg(feature = "sim")]
mod simulate_cmd;

use clap::{Parser, Subcommand, ValueEnum};
use error::{CliError, EXIT_BAD_INPUT, EXIT_SUCCESS};
use std::io::Write;
use std::path::PathBuf;

/// `println!` that returns [`CliError::Stdout`] instead of panicking when stdout is closed.
macro_rules! outln {
    ($($arg:tt)*) => {
        $crate::files::stdout_line(format_args!($($arg)*))?
    };
}
pub(crate) use outln;

/// Distributed, drift-insensitive calibration of SPM scanners, and image correction.
/// The lattice a `correct --ruler` measures against.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum RulerStandard {
    /// HOPG: hexagonal, a = 0.246 nm.
    Hopg,
}

#[derive(Debug, Parser)]
#[command(name = "spmcal", version, about, long_about = None)]
struct Cli {
    /// Write tracing logs to this file (default: warnings to stderr).
    #[arg(long, global = true, value_name = "FILE")]
    log: Option<PathBuf>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the calibration plan of a config on the backend it names; append to the CDB.
    Calibrate {
        /// The job config (TOML): `[backend]` and `[plan]`.
        #[arg(
            long,
            value_name = "FILE",
            required_unless_present = "virtual_image",
            conflicts_with = "virtual_image"
        )]
        config: Option<PathBuf>,
        /// Virtual calibration mode: calibrate on this stored image of a standard (any format
        /// spmcal reads) instead of an instrument; the plan is built for the image.
        #[arg(long = "virtual", value_name = "IMAGE", requires = "standard")]
        virtual_image: Option<PathBuf>,
        /// With --virtual: the standard the image shows, hopg (atoms, a = 0.2461 nm) or
        /// si7x7 (corner holes, a = 2.688 nm).
        #[arg(long, value_name = "hopg|si7x7", requires = "virtual_image")]
        standard: Option<spm_calibration::StandardName>,
        /// With --virtual: the height channel (default Z, else Topography, else the first in m).
        #[arg(long, value_name = "NAME", requires = "virtual_image")]
        channel: Option<String>,
        /// With --virtual: nodes per side of the net (default 5).
        #[arg(
            long,
            value_name = "N",
            requires = "virtual_image",
            default_value_t = 5
        )]
        nodes: u32,
        /// With --virtual: repeats l of the net (default 1: a stored image does not change,
        /// so a repeat returns the same coefficients).
        #[arg(
            long,
            value_name = "L",
            requires = "virtual_image",
            default_value_t = 1
        )]
        repeats: u32,
        /// With --virtual: the virtual scanner's nominal sensitivity, nm per count (default:
        /// the image's pixel size / 10).
        #[arg(long, value_name = "NM", requires = "virtual_image")]
        nominal_nm_per_count: Option<f64>,
        /// With --virtual: the pixel size, nm, for files that state none (raw).
        #[arg(long, value_name = "NM", requires = "virtual_image")]
        pixel_nm: Option<f64>,
        /// With --virtual: a consecutive frame of the same area scanned the other way,
        /// served for counter scans.
        #[arg(long, value_name = "IMAGE", requires = "virtual_image")]
        counter_image: Option<PathBuf>,
        /// With --virtual: smooth the image by a Gaussian this many lattice constants wide
        /// (default 0.05 for hopg, 0.15 for si7x7).
        #[arg(long, value_name = "LATTICE", requires = "virtual_image")]
        smooth: Option<f64>,
        /// With --virtual: accepted LCS angle deviation, degrees.
        #[arg(
            long,
            value_name = "DEG",
            requires = "virtual_image",
            default_value_t = 20.0
        )]
        angle_tolerance_deg: f64,
        /// With --virtual: accepted relative deviation of LCS sides.
        #[arg(
            long,
            value_name = "FRACTION",
            requires = "virtual_image",
            default_value_t = 0.35
        )]
        length_tolerance: f64,
        /// The calibration database: a file (created when missing; default OUT/cdb.sqlite)
        /// or a shared PostgreSQL database, postgres://USER@HOST:PORT/DB (the schema is
        /// created when missing).
        #[arg(long, value_name = "PATH|URL")]
        cdb: Option<PathBuf>,
        /// Resume the unfinished run in the CDB instead of starting a new one.
        #[arg(long)]
        resume: bool,
        /// Folder for the run's report and plots.
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
        /// After the run, take the test images of the image benchmark on the simulated
        /// instrument (moves, pauses, direct and counter rasters) and judge every correction
        /// method on them (report.json `images`; simulated backends only; adds minutes).
        #[arg(long)]
        image_benchmark: bool,
        /// A reduced report (a coarser accuracy grid; with --image-benchmark, 2 sizes and 1
        /// dwell instead of 3 and 2): seconds instead of minutes, for smoke runs.
        #[arg(long)]
        quick: bool,
        /// Do not fail the run on a missed target: print the verdicts of the plan's
        /// `[plan.targets]` and exit 0 (without it, a FAIL exits with code 3).
        #[arg(long)]
        no_targets: bool,
    },
    /// Fit regression surfaces through the CDB's coefficients.
    Fit {
        /// The calibration database: a file or postgres://USER@HOST:PORT/DB.
        #[arg(long, value_name = "PATH|URL")]
        cdb: PathBuf,
        /// Only records of this scanner.
        #[arg(long, value_name = "ID")]
        scanner: Option<String>,
        /// Only records at or after this UTC date-time (RFC 3339 or YYYY-MM-DD).
        #[arg(long, value_name = "DATE")]
        since: Option<String>,
        /// Only records at or before this UTC date-time (RFC 3339 or YYYY-MM-DD).
        #[arg(long, value_name = "DATE")]
        until: Option<String>,
        /// Where to write the surfaces (JSON).
        #[arg(long, value_name = "FILE")]
        out: PathBuf,
        /// Leave out records whose K̄x, K̄y or α lies beyond this many robust standard
        /// deviations from their plane's surfaces (refitted until none does; never below
        /// half the records), e.g. 3 for a calibration on a measured image whose
        /// recognition accepted some wrong structures. Default: every record is fitted.
        #[arg(long, value_name = "SIGMAS")]
        reject_outliers: Option<f64>,
        /// How K̄x and the product surfaces K̄yx, K̄yy are fitted: one by one, as the
        /// derivatives of two potentials (an exact form), or per plane the one with the lower
        /// BIC.
        #[arg(long, value_enum, default_value_t = FormArg::Auto)]
        form: FormArg,
    },
    /// Regenerate the report (report.json, report.html, surfaces.json, figures) of a
    /// finished run from the CDB alone, e.g. after the report failed; what only the running
    /// instrument had (the oracle's accuracy, the image benchmark, drift) is not regenerated,
    /// and the report says so. An unfinished run is continued with `calibrate --resume`.
    Report {
        /// The calibration database: a file or postgres://USER@HOST:PORT/DB.
        #[arg(long, value_name = "PATH|URL")]
        cdb: PathBuf,
        /// The run's id (as `calibrate` printed it; `spmcal cdb export` lists them).
        #[arg(long, value_name = "ID")]
        run: String,
        /// Folder of the report (created when missing; its report files are replaced).
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
    },
    /// Correct image files with a calibration file (`spmcal fit`): the file's own raster
    /// (size, offset, angle, slow direction, both halves), every channel by one map, NaN
    /// where no data lies, the source header and the calibration's provenance kept.
    Correct {
        /// The image files (any format spmcal reads).
        #[arg(required = true)]
        images: Vec<PathBuf>,
        /// The calibration file written by `spmcal fit` (a version-1 surfaces.json too).
        #[arg(long, visible_alias = "surfaces", value_name = "CALIBRATION.json")]
        calibration: PathBuf,
        /// Output file for one image: .gwy (every channel and the metadata) or .gsf (one
        /// channel per file: the height channel, or with `--channel` several files named
        /// OUT.CHANNEL.DIRECTION.gsf).
        #[arg(long, value_name = "OUT.gwy|OUT.gsf", conflicts_with = "out_dir")]
        out: Option<PathBuf>,
        /// Output directory for any number of images: IMAGE-STEM.corrected.gwy (or .gsf with
        /// `--format gsf`).
        #[arg(long, value_name = "DIR")]
        out_dir: Option<PathBuf>,
        /// Format of the files written into `--out-dir`.
        #[arg(long, value_enum, default_value_t = OutFormat::Gwy, requires = "out_dir")]
        format: OutFormat,
        /// Channels to correct: a channel name (both halves) or `all`. Default: every channel
        /// into a .gwy, the forward height channel into a .gsf.
        #[arg(long, value_name = "NAME|all")]
        channel: Option<String>,
        /// Override the file's raster path: `direct` (+x lines, slow axis up) or `counter`
        /// (−x lines from the far corner, slow axis down). Default: as the file records it.
        #[arg(long, value_enum)]
        direction: Option<RasterDirection>,
        /// The controller's nominal sensitivity, nm per count, for files that do not
        /// record their raster in scanner counts.
        #[arg(long, value_name = "K")]
        nominal_nm_per_count: Option<f64>,
        /// Z level of the image (its mean Z reading, counts): the lateral field is blended
        /// between the calibrated Z planes bracketing it (the Z⇒X/Y change of the lateral
        /// sensitivities). Default: the plane nearest z = 0.
        #[arg(long, value_name = "Z", allow_hyphen_values = true)]
        z_counts: Option<f64>,
        /// The scanner the images were taken with (checked against the calibration when the
        /// file does not name its scanner).
        #[arg(long, value_name = "ID")]
        scanner: Option<String>,
        /// Correct an image that reaches beyond the calibrated region (the surfaces are
        /// extrapolated there; the output is marked `spmcal_extrapolated`).
        #[arg(long)]
        allow_extrapolation: bool,
        /// Apply the static field only, even when the calibration file holds the scanner's
        /// dynamics (the raster's hysteresis and creep are then not corrected).
        #[arg(long = "static")]
        static_only: bool,
        /// Measure the approach move's creep, the drift and what the calibration left along the
        /// lines against the standard's lattice in each image (atomic resolution, ≥ 4 pixels
        /// per lattice constant; each half on its own atoms) and remove them too — for files
        /// corrected along their own raster, without a recorded history. `hopg`: hexagonal,
        /// a = 0.246 nm.
        #[arg(long, value_name = "STANDARD")]
        ruler: Option<RulerStandard>,
        /// The image's counter-scanned partner: the same place scanned right before or after it
        /// with the slow axis the other way. The drift, and the part of the approach move's
        /// creep the two frames tell apart, are measured between them feature by feature (no
        /// lattice assumed) and removed — for one image corrected along its own raster, without
        /// a recorded history. Features are matched at `--feature-nm`, or the `--ruler`
        /// standard's lattice constant.
        #[arg(long, value_name = "FILE")]
        counter: Option<PathBuf>,
        /// With --counter: time from the image's first line to the partner's, s (negative when
        /// the partner came first). Default: from the files' time stamps, at least the earlier
        /// frame's duration.
        #[arg(long, value_name = "S", allow_negative_numbers = true)]
        counter_delay: Option<f64>,
        /// With --counter: the spacing of the sample's features, nm (the detector's scale and
        /// the match radius).
        #[arg(long, value_name = "NM")]
        feature_nm: Option<f64>,
    },
    /// Take one image through a job's backend and keep the command history it was taken with
    /// (IMAGE.sxm or IMAGE.gsf, and IMAGE.….history.json): `spmcal correct` then corrects the
    /// creep of the approach move and the raster's dynamics with the calibration's dynamics.
    Scan(scan_cmd::ScanArgs),
    /// Describe SPM files: format, pixels, size, offset, scan angle, direction, line time, date,
    /// channels (several files: one line each).
    Info {
        /// The files: one gets a full description, several a one-line-per-file table.
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Cut a part of an image file (every channel) and write it as .gwy or .gsf, its raster
    /// carried over: the centre moved along the scan angle, size, line time, slow direction
    /// and the source header. For a held-out part (calibrate in virtual mode on one half,
    /// correct the other), or to leave out a step or a defect.
    Crop {
        /// The image file.
        image: PathBuf,
        /// Display columns A..B (0 = left, B excluded; default all).
        #[arg(long, value_name = "A..B", value_parser = crop_cmd::parse_range)]
        columns: Option<std::ops::Range<usize>>,
        /// Display rows A..B (0 = top, B excluded; default all).
        #[arg(long, value_name = "A..B", value_parser = crop_cmd::parse_range)]
        rows: Option<std::ops::Range<usize>>,
        /// The output: OUT.gwy (every channel) or OUT.gsf (one file per channel).
        #[arg(long, value_name = "FILE")]
        out: PathBuf,
    },
    /// Measure the lattice of a standard on image files (before or after `spmcal correct`):
    /// lattice constant and angle over the whole image and in a grid of cells.
    Lattice {
        /// The image files.
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// The standard the images show: hopg or si7x7.
        #[arg(long, value_name = "hopg|si7x7")]
        standard: spm_calibration::StandardName,
        /// Cells per side of the grid (default 4).
        #[arg(long, value_name = "N", default_value_t = 4)]
        grid: usize,
        /// The height channel (default Z, else Topography, else the first in m).
        #[arg(long, value_name = "NAME")]
        channel: Option<String>,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Compare measured images with the simulation: what it gets wrong and why.
    Diagnose {
        /// Image files (frames of one area).
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// The sample's lattice: hopg | si7x7 | hex:A_NM | square:A_NM.
        #[arg(long, value_name = "LATTICE")]
        lattice: String,
        /// Where to write the diagnosis (JSON).
        #[arg(long, value_name = "OUT")]
        json: PathBuf,
        /// Also draw the residual figure.
        #[arg(long, value_name = "OUT.png")]
        png: Option<PathBuf>,
    },
    /// Run a measured file's scan program on the simulated microscope and write it as .sxm.
    #[cfg(feature = "sim")]
    Simulate {
        /// The measured file whose scan program (size, pixels, line time,
        /// directions, slow-axis direction, date) is copied.
        #[arg(long, value_name = "FILE")]
        like: PathBuf,
        /// The simulated microscope (spm-sim TOML), e.g. from the diagnosis' sim patch.
        #[arg(long, value_name = "SIM.toml")]
        config: PathBuf,
        /// Where to write the simulated scan (Nanonis .sxm).
        #[arg(long, value_name = "OUT.sxm")]
        out: PathBuf,
        /// The calibration the instrument's software believes, nm per count
        /// (default: the config's x sensitivity).
        #[arg(long, value_name = "NM")]
        nominal_nm_per_count: Option<f64>,
    },
    /// Serve the Nanonis TCP protocol over the simulated microscope (for `[backend] kind =
    /// "nanonis"` without hardware); runs until killed.
    #[cfg(feature = "sim")]
    NanonisSim(nanonis_sim_cmd::NanonisSimArgs),
    /// Calibration-database maintenance.
    Cdb {
        #[command(subcommand)]
        command: CdbCommand,
    },
}

#[derive(Debug, Subcommand)]
enum CdbCommand {
    /// Check the database's integrity (exit 1 when it fails).
    Check {
        /// The database: a file or postgres://USER@HOST:PORT/DB.
        #[arg(value_name = "PATH|URL")]
        path: PathBuf,
    },
    /// Export every record.
    Export {
        /// The database: a file or postgres://USER@HOST:PORT/DB.
        #[arg(value_name = "PATH|URL")]
        path: PathBuf,
        /// CSV output file.
        #[arg(long, value_name = "OUT")]
        csv: PathBuf,
    },
    /// Copy a SQLite CDB to a new file, consistently also while a run writes (SQLite's
    /// online backup API); the copy's integrity is checked. Restore: see README.
    Backup {
        /// The database file to copy.
        #[arg(value_name = "SRC")]
        src: PathBuf,
        /// The new file (refused if it exists).
        #[arg(value_name = "DEST")]
        dest: PathBuf,
    },
    /// Coefficients against date (age dynamics).
    Trend {
        /// The database: a file or postgres://USER@HOST:PORT/DB.
        #[arg(value_name = "PATH|URL")]
        path: PathBuf,
        /// Also draw the history as a PNG: K̄x and K̄y of every scanner per run, % change
        /// from its first run with ± the standard uncertainty, against time (a new file).
        #[arg(long, value_name = "OUT.png")]
        png: Option<PathBuf>,
    },
}

/// Format of the corrected files written into a directory.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum OutFormat {
    /// Gwyddion native: every channel and the metadata in one file.
    Gwy,
    /// Gwyddion Simple Field: one file per channel.
    Gsf,
}

/// How `spmcal fit` fits K̄x and the product surfaces (`spm_correction::SurfaceForm`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum FormArg {
    /// Per plane, the form with the lower BIC.
    Auto,
    /// Each surface by itself (eqs. 2 and 11).
    Independent,
    /// The derivatives of two potentials x̄(x, y), ȳ(y): a correction that does not depend
    /// on the raster's path, and a y scale with no x term to extrapolate.
    Exact,
}

impl FormArg {
    fn form(self) -> Option<spm_correction::SurfaceForm> {
        match self {
            Self::Auto => None,
            Self::Independent => Some(spm_correction::SurfaceForm::Independent),
            Self::Exact => Some(spm_correction::SurfaceForm::Exact),
        }
    }
}

/// Raster direction of an image to correct.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum RasterDirection {
    /// +x lines stepping +y.
    Direct,
    /// −x lines stepping −y from the far corner.
    Counter,
}

fn main() {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(error) => {
            let code = if error.use_stderr() {
                EXIT_BAD_INPUT
            } else {
                EXIT_SUCCESS
            };
            // clap prints help/version to stdout and usage errors to stderr.
            let _ = error.print();
            std::process::exit(code);
        }
    };
    if let Some(log) = &cli.log {
        if let Err(error) = check_log(log, &cli.command) {
            let _ = writeln!(std::io::stderr(), "spmcal: error: {error}");
            std::process::exit(error.exit_code());
        }
        files::set_log(log);
    }
    let _guard = install_subscriber(cli.log.as_deref(), &cli.command);
    let code = match run(cli.command) {
        Ok(()) => EXIT_SUCCESS,
        Err(error) => {
            // A reader that went away (closed pipe) gets no message; anything else does.
            if !error.is_closed_stdout() {
                let _ = writeln!(std::io::stderr(), "spmcal: error: {error}");
            }
            error.exit_code()
        }
    };
    std::process::exit(code);
}

impl Command {
    /// Every file the command names (inputs and outputs), for the `--log` check.
    fn paths(&self) -> Vec<PathBuf> {
        let mut paths = Vec::new();
        match self {
            Self::Calibrate {
                config,
                virtual_image,
                counter_image,
                cdb,
                out,
                ..
            } => {
                if let Some(config) = config {
                    paths.push(config.clone());
                    paths.extend(spmcal::job::Job::referenced_files(config));
                }
                paths.extend(virtual_image.iter().cloned());
                paths.extend(counter_image.iter().cloned());
                let out = out
                    .clone()
                    .unwrap_or_else(|| PathBuf::from(calibrate_cmd::DEFAULT_OUT));
                paths.push(cdb.clone().unwrap_or_else(|| out.join("cdb.sqlite")));
                for name in calibrate_cmd::OUTPUT_FILES {
                    paths.push(out.join(name));
                }
            }
            Self::Fit { cdb, out, .. } => paths.extend([cdb.clone(), out.clone()]),
            Self::Report { cdb, out, .. } => {
                paths.push(cdb.clone());
                for name in calibrate_cmd::OUTPUT_FILES {
                    paths.push(out.join(name));
                }
            }
            Self::Scan(args) => {
                paths.push(args.config.clone());
                paths.extend(spmcal::job::Job::referenced_files(&args.config));
                paths.push(args.out.clone());
                paths.push(spm_apply::history::sidecar_of(&args.out));
            }
            Self::Correct {
                images,
                calibration,
                out,
                out_dir,
                ..
            } => {
                paths.extend(images.iter().cloned());
                paths.push(calibration.clone());
                paths.extend(out.iter().cloned());
                paths.extend(out_dir.iter().cloned());
            }
            Self::Crop { image, out, .. } => paths.extend([image.clone(), out.clone()]),
            Self::Info { files, .. } | Self::Lattice { files, .. } => {
                paths.extend(files.iter().cloned());
            }
            Self::Diagnose {
                files, json, png, ..
            } => {
                paths.extend(files.iter().cloned());
                paths.push(json.clone());
                paths.extend(png.iter().cloned());
            }
            #[cfg(feature = "sim")]
            Self::Simulate {
                like, config, out, ..
            } => {
                paths.extend([like.clone(), config.clone(), out.clone()]);
            }
            #[cfg(feature = "sim")]
            Self::NanonisSim(args) => paths.push(args.config.clone()),
            Self::Cdb { command } => match command {
                CdbCommand::Check { path } => paths.push(path.clone()),
                CdbCommand::Trend { path, png } => {
                    paths.push(path.clone());
                    paths.extend(png.iter().cloned());
                }
                CdbCommand::Export { path, csv } => paths.extend([path.clone(), csv.clone()]),
                CdbCommand::Backup { src, dest } => paths.extend([src.clone(), dest.clone()]),
            },
        }
        paths
    }
}

/// The log file must be a regular file or new, and none of the command's files.
fn check_log(log: &std::path::Path, command: &Command) -> Result<(), error::CliError> {
    let paths = command.paths();
    let refs: Vec<&std::path::Path> = paths.iter().map(PathBuf::as_path).collect();
    if paths.iter().any(|p| p == log) {
        return Err(error::CliError::BadInput(format!(
            "--log {}: is also a file of the command; refusing to overwrite it",
            log.display()
        )));
    }
    files::check_output(log, "--log", &refs)
}

/// Logs go to a file when asked (or, for `calibrate`, to `OUT/calibrate.log`), otherwise
/// warnings and errors go to stderr ([`console`]).
fn install_subscriber(log: Option<&std::path::Path>, command: &Command) -> Option<()> {
    let to = match (log, command) {
        (Some(path), _) => console::LogTo::File(path),
        (None, Command::Calibrate { .. }) => console::LogTo::Deferred,
        (None, _) => console::LogTo::Console,
    };
    console::install(to);
    Some(())
}

fn run(command: Command) -> Result<(), CliError> {
    match command {
        Command::Info { files, json } => info::run(&files, json),
        Command::Crop {
            image,
            columns,
            rows,
            out,
        } => crop_cmd::run(&image, columns, rows, &out),
        Command::Scan(args) => scan_cmd::run(&args),
        Command::Lattice {
            files,
            standard,
            grid,
            channel,
            json,
        } => lattice_cmd::run(&files, standard, grid, channel.as_deref(), json),
        Command::Fit {
            cdb,
            scanner,
            since,
            until,
            out,
            reject_outliers,
            form,
        } => fit_cmd::run(
            &cdb,
            scanner.as_deref(),
            since.as_deref(),
            until.as_deref(),
            &out,
            reject_outliers,
            form.form(),
        ),
        Command::Report { cdb, run, out } => report_cmd::run(&cdb, &run, &out),
        Command::Cdb { command } => match command {
            CdbCommand::Check { path } => cdb_cmd::check(&path),
            CdbCommand::Export { path, csv } => cdb_cmd::export(&path, &csv),
            CdbCommand::Trend { path, png } => cdb_cmd::trend(&path, png.as_deref()),
            CdbCommand::Backup { src, dest } => cdb_cmd::backup(&src, &dest),
        },
        Command::Calibrate {
            config,
            virtual_image,
            standard,
            channel,
            nodes,
            repeats,
            nominal_nm_per_count,
            pixel_nm,
            counter_image,
            smooth,
            angle_tolerance_deg,
            length_tolerance,
            cdb,
            resume,
            out,
            image_benchmark,
            quick,
            no_targets,
        } => calibrate_cmd::run(
            &match (config, virtual_image, standard) {
                (_, Some(image), Some(standard)) => calibrate_cmd::JobSource::Virtual(
                    image,
                    spmcal::virtual_mode::VirtualRunOptions {
                        standard,
                        channel,
                        nominal_nm_per_count,
                        nodes_per_side: nodes,
                        repeats,
                        pixel_nm,
                        counter_image,
                        smoothing_sigma_lattice: smooth,
                        angle_tolerance_deg,
                        length_tolerance_fraction: length_tolerance,
                    },
                ),
                (Some(config), _, _) => calibrate_cmd::JobSource::Config(config),
                _ => {
                    return Err(CliError::BadInput(
                        "calibrate: give --config FILE, or --virtual IMAGE --standard hopg|si7x7"
                            .into(),
                    ));
                }
            },
            cdb.as_deref(),
            resume,
            out.as_deref(),
            calibrate_cmd::ReportOptions {
                image_benchmark,
                quick,
                enforce_targets: !no_targets,
            },
        ),
        Command::Correct {
            images,
            calibration,
            out,
            out_dir,
            format,
            channel,
            direction,
            nominal_nm_per_count,
            z_counts,
            scanner,
            allow_extrapolation,
            static_only,
            ruler,
            counter,
            counter_delay,
            feature_nm,
        } => correct_cmd::run(&correct_cmd::CorrectArgs {
            images: &images,
            calibration: &calibration,
            out: out.as_deref(),
            out_dir: out_dir.as_deref(),
            format,
            channel: channel.as_deref(),
            direction,
            nominal_nm_per_count,
            z_counts,
            scanner: scanner.as_deref(),
            allow_extrapolation,
            static_only,
            ruler: ruler.map(|r| match r {
                RulerStandard::Hopg => spm_apply::ruler::LatticeRuler::hopg(),
            }),
            counter: counter.as_deref(),
            counter_delay_s: counter_delay,
            feature_nm,
        }),
        Command::Diagnose {
            files,
            lattice,
            json,
            png,
        } => diagnose_cmd::run(&files, &lattice, &json, png.as_deref()),
        #[cfg(feature = "sim")]
        Command::Simulate {
            like,
            config,
            out,
            nominal_nm_per_count,
        } => simulate_cmd::run(&like, &config, &out, nominal_nm_per_count),
        #[cfg(feature = "sim")]
        Command::NanonisSim(args) => nanonis_sim_cmd::run(&args),
    }
}

/// Writes `bytes` to a temporary file beside `path`, then renames it into place.
fn write_atomically(path: &std::path::Path, bytes: &[u8]) -> Result<(), CliError> {
    files::write_atomically(path, bytes)
}
