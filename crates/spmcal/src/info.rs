//! `spmcal info FILE... [--json]`: one file in full, several as a one-line-per-file table.

use crate::error::CliError;
use std::path::{Path, PathBuf};

/// A number with `significant` significant digits ([`spmcal::html::significant_text`]) and no
/// trailing zeros (`1 nm`, not `0.9999999717180685 nm`).
fn human(value: f64, significant: usize) -> String {
    let text = spmcal::html::significant_text(value, significant);
    let (mantissa, exponent) = match text.split_once('e') {
        Some((m, e)) => (m.to_owned(), format!("e{e}")),
        None => (text, String::new()),
    };
    let mantissa = if mantissa.contains('.') {
        mantissa
            .trim_end_matches('0')
            .trim_end_matches('.')
            .to_owned()
    } else {
        mantissa
    };
    let mantissa = if mantissa == "-0" {
        "0".to_owned()
    } else {
        mantissa
    };
    format!("{mantissa}{exponent}")
}

/// The geometry of the file's first channel: (offset x, y nm; angle degrees).
fn geometry(spm: &spm_formats::SpmFile) -> (Option<[f64; 2]>, Option<f64>) {
    let Some(c) = spm.channels.first() else {
        return (None, None);
    };
    let offset = match (c.center_x_nm(), c.center_y_nm()) {
        (Some(x), Some(y)) => Some([x, y]),
        _ => None,
    };
    (offset, c.angle_deg())
}

fn read(file: &Path) -> Result<spm_formats::SpmFile, CliError> {
    crate::files::check_input(file, "file")?;
    spm_formats::read_any(file).map_err(|e| CliError::BadInput(e.to_string()))
}

pub fn run(files: &[PathBuf], json: bool) -> Result<(), CliError> {
    let read_all: Vec<spm_formats::SpmFile> =
        files.iter().map(|f| read(f)).collect::<Result<_, _>>()?;
    if json {
        let infos: Vec<spm_formats::Info> = read_all.iter().map(|f| f.info()).collect();
        let text = match infos.as_slice() {
            [one] => serde_json::to_string_pretty(one),
            many => serde_json::to_string_pretty(many),
        }
        .map_err(|e| CliError::RunFailed(format!("cannot encode JSON: {e}")))?;
        crate::outln!("{text}");
        return Ok(());
    }
    match read_all.as_slice() {
        [one] => full(&files[0], one),
        many => table(files, many),
    }
}

fn full(file: &Path, spm: &spm_formats::SpmFile) -> Result<(), CliError> {
    let info = spm.info();
    crate::outln!("file:      {}", file.display());
    crate::outln!("format:    {}", info.format);
    if let Some([nx, ny]) = info.pixels {
        crate::outln!("pixels:    {nx} × {ny}");
    }
    if let Some([x, y]) = info.size_nm {
        crate::outln!("size:      {} nm × {} nm", human(x, 6), human(y, 6));
    }
    let (offset, angle) = geometry(spm);
    if let Some([x, y]) = offset {
        crate::outln!("offset:    ({} nm, {} nm)", human(x, 6), human(y, 6));
    }
    if let Some(a) = angle {
        crate::outln!("angle:     {}°", human(a, 4));
    }
    if let Some(dir) = &info.scan_dir {
        crate::outln!("scan dir:  {dir}");
    }
    if let Some(t) = info.line_time_s {
        crate::outln!("line time: {} s", human(t, 4));
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

fn table(files: &[PathBuf], spms: &[spm_formats::SpmFile]) -> Result<(), CliError> {
    let mut rows = vec![[
        "file".to_owned(),
        "format".to_owned(),
        "pixels".to_owned(),
        "size nm".to_owned(),
        "offset nm".to_owned(),
        "angle °".to_owned(),
        "dir".to_owned(),
        "line s".to_owned(),
        "recorded".to_owned(),
        "channels".to_owned(),
    ]];
    let dash = || "–".to_owned();
    for (file, spm) in files.iter().zip(spms) {
        let info = spm.info();
        let (offset, angle) = geometry(spm);
        rows.push([
            file.file_name().map_or_else(
                || file.display().to_string(),
                |n| n.to_string_lossy().into_owned(),
            ),
            info.format.to_string(),
            info.pixels.map_or_else(dash, |[x, y]| format!("{x}×{y}")),
            info.size_nm
                .map_or_else(dash, |[x, y]| format!("{}×{}", human(x, 6), human(y, 6))),
            offset.map_or_else(dash, |[x, y]| format!("{}, {}", human(x, 4), human(y, 4))),
            angle.map_or_else(dash, |a| human(a, 4)),
            info.scan_dir.clone().unwrap_or_else(dash),
            info.line_time_s.map_or_else(dash, |t| human(t, 4)),
            info.recorded.clone().unwrap_or_else(dash),
            info.channels.len().to_string(),
        ]);
    }
    let widths: Vec<usize> = (0..10)
        .map(|i| rows.iter().map(|r| r[i].chars().count()).max().unwrap_or(0))
        .collect();
    for row in rows {
        let line: Vec<String> = row
            .iter()
            .zip(&widths)
            .map(|(cell, w)| format!("{cell:<w$}"))
            .collect();
        crate::outln!("{}", line.join("  ").trim_end());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::human;

    #[test]
    fn numbers_read_as_a_person_writes_them() {
        for (value, digits, expect) in [
            (0.999_999_971_718_068_5, 6, "1"),
            (11.4807, 6, "11.4807"),
            (-12.814_022_731_788_555, 4, "-12.81"),
            (0.256, 4, "0.256"),
            (2.5e-10, 3, "2.5e-10"),
            (50.0, 5, "50"),
            (0.0, 4, "0"),
        ] {
            assert_eq!(human(value, digits), expect, "{value} to {digits} digits");
        }
    }
}
