//! `spmcal info FILE [--json]`.

use crate::error::CliError;
use std::path::Path;

pub fn run(file: &Path, json: bool) -> Result<(), CliError> {
    crate::files::check_input(file, "file")?;
    let spm = spm_formats::read_any(file).map_err(|e| CliError::BadInput(e.to_string()))?;
    let info = spm.info();
    if json {
        let text = serde_json::to_string_pretty(&info)
            .map_err(|e| CliError::RunFailed(format!("cannot encode JSON: {e}")))?;
        crate::outln!("{text}");
        return Ok(());
    }
    crate::outln!("file:      {}", file.display());
    crate::outln!("format:    {}", info.format);
    if let Some([nx, ny]) = info.pixels {
        crate::outln!("pixels:    {nx} × {ny}");
    }
    if let Some([x, y]) = info.size_nm {
        crate::outln!("size:      {x} nm × {y} nm");
    }
    if let Some(dir) = &info.scan_dir {
        crate::outln!("scan dir:  {dir}");
    }
    if let Some(t) = info.line_time_s {
        crate::outln!("line time: {t} s");
    }
    if let Some(recorded) = &info.recorded {
        crate::outln!("recorded:  {recorded}");
    }
    crate::outln!("channels:");
    for channel in &info.channels {
        crate::outln!(
            "  {:<24} {:<9} [{}]",
            channel.name,
            channel.direction,
            channel.unit
        );
    }
    crate::outln!("header:    {} entries", info.header.len());
    Ok(())
}
