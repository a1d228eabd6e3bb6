//! Nanonis `.sxm` writer (the layout [`crate::read_sxm`] reads): for simulated
//! scans that must look like an instrument's files (`spmcal simulate`, the
//! image-level tests of spm-modelcheck).

use std::fmt::Write as _;
use std::path::Path;

use crate::error::{FormatError, Result};
use crate::model::{DateTime, ScanDir};

/// One channel of a scan to write: images in acquisition order (line 0 = the
/// first line acquired; backward lines in time order, right to left), each
/// `nx·ny` values in the channel's unit.
#[derive(Clone, Debug, PartialEq)]
pub struct SxmChannel {
    /// Channel name (e.g. `Z`).
    pub name: String,
    /// Unit (e.g. `m`).
    pub unit: String,
    /// Forward image, acquisition order.
    pub forward: Vec<f64>,
    /// Backward image, acquisition (time) order; `None` = forward only.
    pub backward: Option<Vec<f64>>,
}

/// A scan to write as `.sxm`.
#[derive(Clone, Debug, PartialEq)]
pub struct SxmScan {
    /// Pixels per line, lines.
    pub pixels: [usize; 2],
    /// Scan range (x, y), nm.
    pub size_nm: [f64; 2],
    /// Frame centre, nm.
    pub centre_nm: [f64; 2],
    /// Scan angle, degrees.
    pub angle_deg: f64,
    /// Forward and backward line time, s.
    pub line_time_s: [f64; 2],
    /// Slow-axis direction.
    pub scan_dir: ScanDir,
    /// Record date and time (start of the scan).
    pub recorded: DateTime,
    /// Bias, V (written as `BIAS`).
    pub bias_v: f64,
    /// Free text for `COMMENT`.
    pub comment: String,
    /// Channels (at least one).
    pub channels: Vec<SxmChannel>,
    /// Further header tags `(name, value)`, written after `COMMENT` as `:name:` sections (the
    /// reader keeps every tag): what a controller adds, or spmcal's raster in counts. Names
    /// and values are kept on one line (`:`, newlines, tabs and NUL become spaces).
    pub extra_header: Vec<(String, String)>,
}

fn invalid(path: &Path, reason: String) -> FormatError {
    crate::error::Ctx::new(path).invalid_input(reason)
}

/// Encodes a scan as `.sxm` bytes (big-endian float32). `path` names the
/// file in errors only.
pub fn encode_sxm(scan: &SxmScan, path: &Path) -> Result<Vec<u8>> {
    let [nx, ny] = scan.pixels;
    let n = nx.checked_mul(ny).unwrap_or(0);
    if n == 0 {
        return Err(invalid(path, format!("pixels {nx}×{ny}")));
    }
    if scan.channels.is_empty() {
        return Err(invalid(path, "no channels".to_owned()));
    }
    let finite = scan
        .size_nm
        .iter()
        .chain(&scan.centre_nm)
        .chain(&scan.line_time_s);
    if !finite.into_iter().all(|v| v.is_finite()) || scan.line_time_s[0] <= 0.0 {
        return Err(invalid(
            path,
            "size, centre and line times must be finite, line time > 0".to_owned(),
        ));
    }
    let one_line = |s: &str| s.replace(['\n', '\r', '\0', '\t', ':'], " ");
    let mut h = String::new();
    let mut tag = |t: &str, v: &str| {
        let _ = write!(h, ":{t}:\n{v}\n");
    };
    let d = scan.recorded;
    tag("NANONIS_VERSION", "2");
    tag("SCANIT_TYPE", "              FLOAT            MSBFIRST");
    tag(
        "REC_DATE",
        &format!(" {:02}.{:02}.{:04}", d.day, d.month, d.year),
    );
    tag(
        "REC_TIME",
        &format!("{:02}:{:02}:{:02}", d.hour, d.minute, d.second),
    );
    tag("SCAN_PIXELS", &format!("       {nx}       {ny}"));
    tag(
        "SCAN_TIME",
        &format!(
            "             {:.6E}             {:.6E}",
            scan.line_time_s[0], scan.line_time_s[1]
        ),
    );
    tag(
        "SCAN_RANGE",
        &format!(
            "           {:.9E}           {:.9E}",
            scan.size_nm[0] * 1e-9,
            scan.size_nm[1] * 1e-9
        ),
    );
    tag(
        "SCAN_OFFSET",
        &format!(
            "             {:.9E}         {:.9E}",
            scan.centre_nm[0] * 1e-9,
            scan.centre_nm[1] * 1e-9
        ),
    );
    tag("SCAN_ANGLE", &format!("            {:.3E}", scan.angle_deg));
    tag("SCAN_DIR", scan.scan_dir.as_str());
    tag("BIAS", &format!("            {:.3E}", scan.bias_v));
    tag("COMMENT", &one_line(&scan.comment));
    for (name, value) in &scan.extra_header {
        let name = one_line(name).trim().replace(' ', "_");
        if name.is_empty() {
            return Err(invalid(
                path,
                "an extra header tag without a name".to_owned(),
            ));
        }
        tag(&name, &one_line(value));
    }
    let mut info = String::from("\tChannel\tName\tUnit\tDirection\tCalibration\tOffset");
    for (i, c) in scan.channels.iter().enumerate() {
        let dir = if c.backward.is_some() {
            "both"
        } else {
            "forward"
        };
        let _ = write!(
            info,
            "\n\t{i}\t{}\t{}\t{dir}\t1.000E+0\t0.000E+0",
            one_line(&c.name).replace(' ', "_"),
            one_line(&c.unit).replace(' ', "_")
        );
    }
    tag("DATA_INFO", &(info + "\n"));
    let mut out = h.into_bytes();
    out.extend_from_slice(b":SCANIT_END:\n\n\n");
    out.extend_from_slice(&[0x1A, 0x04]);
    for c in &scan.channels {
        for image in std::iter::once(&c.forward).chain(c.backward.as_ref()) {
            if image.len() != n {
                return Err(invalid(
                    path,
                    format!(
                        "channel {}: {} values for {nx}×{ny} pixels",
                        c.name,
                        image.len()
                    ),
                ));
            }
            for &v in image {
                out.extend_from_slice(&(v as f32).to_be_bytes());
            }
        }
    }
    Ok(out)
}

/// Writes a scan as a `.sxm` file (see [`encode_sxm`]).
pub fn write_sxm(path: impl AsRef<Path>, scan: &SxmScan) -> Result<()> {
    let path = path.as_ref();
    let bytes = encode_sxm(scan, path)?;
    std::fs::write(path, bytes).map_err(|source| FormatError::Io {
        path: path.to_path_buf(),
        action: "cannot write",
        source,
    })
}
