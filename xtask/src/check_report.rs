//! `cargo xtask check-report`: renders a `report.html` in headless Chromium (the
//! distribution's `chromium` package) and writes a screenshot, so that a person can look at
//! the page as a browser draws it. Checks on the way that the page is self-contained (no
//! script, no network resource) and that the screenshot is a PNG that is not blank.

use crate::XtaskError;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Where Chromium is looked for, in order (the Debian package installs /usr/bin/chromium).
const CHROMIUM: [&str; 3] = [
    "/usr/bin/chromium",
    "/usr/bin/chromium-browser",
    "/usr/bin/google-chrome",
];

/// The longest a render may take.
const RENDER_TIMEOUT: Duration = Duration::from_secs(120);

/// Renders `report` into the PNG `out` (1280 px wide, 4000 px tall window).
pub fn run(report: &Path, out: &Path) -> Result<(), XtaskError> {
    let html = std::fs::read_to_string(report)
        .map_err(|e| XtaskError::step(format!("reading {}", report.display()), e))?;
    self_contained(&html).map_err(|e| XtaskError::step(report.display().to_string(), e))?;
    let chromium = CHROMIUM
        .iter()
        .map(PathBuf::from)
        .find(|p| p.is_file())
        .ok_or_else(|| {
            XtaskError::step(
                "finding Chromium",
                format!(
                    "none of {} exists; install the distribution's package \
                     (Debian: apt-get install -y chromium)",
                    CHROMIUM.join(", ")
                ),
            )
        })?;
    let report = std::fs::canonicalize(report)
        .map_err(|e| XtaskError::step(format!("resolving {}", report.display()), e))?;
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .map_err(|e| XtaskError::step(format!("creating {}", parent.display()), e))?;
    }
    let _ = std::fs::remove_file(out);
    let profile = std::env::temp_dir().join(format!("xtask-chromium-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&profile);
    std::fs::create_dir_all(&profile)
        .map_err(|e| XtaskError::step(format!("creating {}", profile.display()), e))?;
    let started = Instant::now();
    let result = render(&chromium, &profile, &report, out);
    let _ = std::fs::remove_dir_all(&profile);
    result?;
    let png = std::fs::read(out).map_err(|e| {
        XtaskError::step(
            format!("reading the screenshot {}", out.display()),
            format!("{e} (Chromium wrote none)"),
        )
    })?;
    let (width, height) = not_blank(&png)
        .map_err(|e| XtaskError::step(format!("screenshot {}", out.display()), e))?;
    println!(
        "rendered {} in {:.1} s with {}: screenshot {} ({width}×{height} px)",
        report.display(),
        started.elapsed().as_secs_f64(),
        chromium.display(),
        out.display()
    );
    Ok(())
}

fn render(chromium: &Path, profile: &Path, report: &Path, out: &Path) -> Result<(), XtaskError> {
    let mut child = Command::new(chromium)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(format!("--screenshot={}", out.display()))
        .arg("--window-size=1280,4000")
        .arg(format!("file://{}", report.display()))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| XtaskError::step(format!("starting {}", chromium.display()), e))?;
    let deadline = Instant::now() + RENDER_TIMEOUT;
    loop {
        match child.try_wait() {
            Ok(Some(status)) if status.success() => return Ok(()),
            Ok(Some(status)) => {
                let mut stderr = String::new();
                if let Some(mut e) = child.stderr.take() {
                    let _ = std::io::Read::read_to_string(&mut e, &mut stderr);
                }
                let tail: Vec<&str> = stderr.lines().rev().take(5).collect();
                return Err(XtaskError::step(
                    format!("{} --screenshot", chromium.display()),
                    format!("exited with {status}: {}", tail.join(" | ")),
                ));
            }
            Ok(None) if Instant::now() > deadline => {
                let _ = child.kill();
                let _ = child.wait();
                return Err(XtaskError::step(
                    format!("{} --screenshot", chromium.display()),
                    format!("no result within {} s", RENDER_TIMEOUT.as_secs()),
                ));
            }
            Ok(None) => std::thread::sleep(Duration::from_millis(100)),
            Err(e) => return Err(XtaskError::step("waiting for Chromium", e)),
        }
    }
}

/// The page needs nothing from outside: no script, no stylesheet link, no http(s) resource.
fn self_contained(html: &str) -> Result<(), String> {
    let lower = html.to_ascii_lowercase();
    for needle in [
        "<script",
        "<link",
        "src=\"http",
        "src='http",
        "url(http",
        "@import",
    ] {
        if lower.contains(needle) {
            return Err(format!("not self-contained: contains {needle:?}"));
        }
    }
    Ok(())
}

/// The screenshot's size, when it is a PNG with more than one colour.
fn not_blank(png_bytes: &[u8]) -> Result<(u32, u32), String> {
    let decoder = png::Decoder::new(png_bytes);
    let mut reader = decoder.read_info().map_err(|e| e.to_string())?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| e.to_string())?;
    buf.truncate(info.buffer_size());
    let channels = info.color_type.samples();
    let first = buf.get(..channels).unwrap_or(&[]).to_vec();
    if buf.chunks_exact(channels).all(|p| p == first.as_slice()) {
        return Err("the page rendered blank (one colour)".to_owned());
    }
    Ok((info.width, info.height))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check(html: &str, ok: bool) {
        assert_eq!(self_contained(html).is_ok(), ok, "{html}");
    }

    #[test]
    fn external_resources_are_refused() {
        check("<p>ok</p><img src=\"data:image/png;base64,AA==\">", true);
        check("<script>1</script>", false);
        check("<img src=\"https://example.invalid/x.png\">", false);
        check("<link rel=stylesheet href=x.css>", false);
        check("<style>@import 'x.css';</style>", false);
    }
}
