//! Renders every channel of the given files to PNG files in the output folder.
//!
//! `cargo run -p spm-plot --example render_all -- OUT_DIR FILE...`

use spm_formats::read_any;
use spm_plot::{PngOptions, write_png};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let out = std::path::PathBuf::from(args.next().ok_or("usage: render_all OUT_DIR FILE...")?);
    for file in args {
        let f = read_any(&file)?;
        let stem = std::path::Path::new(&file)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        for c in &f.channels {
            let name = format!(
                "{stem}_{}_{}.png",
                c.name().replace(' ', "_"),
                c.direction()
            );
            write_png(out.join(&name), c, &PngOptions::default())?;
            println!("{name}");
        }
    }
    Ok(())
}
