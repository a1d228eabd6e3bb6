//! `spmcal crop IMAGE --columns A..B --rows A..B --out OUT.gwy|OUT.gsf`: a part of an image
//! file, every channel, its raster carried over (`spm_apply::crop`).

use crate::error::CliError;
use spm_apply::OutputKind;
use std::ops::Range;
use std::path::Path;

/// A pixel range `A..B` (B excluded) as given on the command line.
pub fn parse_range(text: &str) -> Result<Range<usize>, String> {
    let (a, b) = text
        .split_once("..")
        .ok_or_else(|| format!("{text:?}: give a range A..B (B excluded), e.g. 0..256"))?;
    let number = |s: &str| {
        s.trim()
            .parse::<usize>()
            .map_err(|_| format!("{text:?}: {s:?} is not a pixel index"))
    };
    Ok(number(a)?..number(b)?)
}

pub fn run(
    image: &Path,
    columns: Option<Range<usize>>,
    rows: Option<Range<usize>>,
    out: &Path,
) -> Result<(), CliError> {
    crate::files::check_input(image, "image")?;
    crate::files::check_output(out, "--out", &[image])?;
    let kind = OutputKind::of_path(out).map_err(|e| CliError::BadInput(e.to_string()))?;
    let file = spm_formats::read_any(image).map_err(|e| CliError::BadInput(e.to_string()))?;
    let [nx, ny] = file.pixels().unwrap_or([0, 0]);
    let part = spm_apply::crop::crop_file(&file, columns.unwrap_or(0..nx), rows.unwrap_or(0..ny))
        .map_err(|e| CliError::BadInput(e.to_string()))?;
    let written =
        crate::correct_cmd::write_channels(&part.channels, &part.metadata, out, kind, &[image])?;
    for path in written {
        crate::outln!("{}", path.display());
    }
    Ok(())
}
