//! `spmcal info FILE [--json]`.

use crate::error::CliError;
use std::path::Path;

pub fn run(file: &Path, json: bool) -> Result<(), CliError> {
    let spm = spm_formats::read_any(file).map_err(|e| CliError::BadInput(e.to_string()))?;
    let info = spm.info();
    if json {
        let text = serde_json::to_string_pretty(&info)
            .map_err(|e| CliError::RunFailed(format!("cannot encode JSON: {e}")))?;
        println!("{text}");
        return Ok(());
    }
    println!("file:      {}", file.display());
    println!("format:    {}", info.format);
    if let Some([nx, ny]) = info.pixels {
        println!("pixels:    {nx} × {ny}");
    }
    if let Some([x, y]) = info.size_nm {
        println!("size:      {x} nm × {y} nm");
    }
    if let Some(dir) = &info.scan_dir {
        println!("scan dir:  {dir}");
    }
    if let Some(t) = info.line_time_s {
        println!("line time: {t} s");
    }
    if let Some(recorded) = &info.recorded {
        println!("recorded:  {recorded}");
    }
    println!("channels:");
    for channel in &info.channels {
        println!(
            "  {:<24} {:<9} [{}]",
            channel.name, channel.direction, channel.unit
        );
    }
    println!("header:    {} entries", info.header.len());
    Ok(())
}
