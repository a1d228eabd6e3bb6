//! Prints the extracted features and the lattice indexing of one or more files.
//! `cargo run -p spm-modelcheck --example debug_index -- LATTICE RELATIVE_PATH… [--plain|--cells]`
//! (paths relative to `../shared/data/measured/`).
#![allow(clippy::unwrap_used)]
use spm_modelcheck::{
    ExtractOptions, LatticeSpec, LineDirection, Localiser, extract_features, index_features,
};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let lattice = LatticeSpec::parse(&args[0]).unwrap();
    let mut ex = ExtractOptions::default();
    let mut files = Vec::new();
    for a in &args[1..] {
        match a.as_str() {
            "--plain" => ex.localiser = Localiser::Features,
            "--cells" => ex.localiser = Localiser::Cells,
            p => files.push((
                spm_formats::read_any(spmcal_tests::measured_file(p)).unwrap(),
                None,
            )),
        }
    }
    let set = match extract_features(&files, &lattice, &ex) {
        Ok(s) => s,
        Err(e) => {
            println!("extraction refused: {e}");
            return;
        }
    };
    println!(
        "{} features; warnings {:?}",
        set.features.len(),
        set.warnings
    );
    for (k, frame) in set.frames.iter().enumerate() {
        for dir in [LineDirection::Forward, LineDirection::Backward] {
            let mut sig: Vec<f64> = set
                .features
                .iter()
                .filter(|f| f.frame_index == k && f.direction == dir)
                .filter_map(|f| f.sigma_nm)
                .collect();
            sig.sort_by(f64::total_cmp);
            if sig.is_empty() {
                continue;
            }
            println!(
                "frame {k} {:?} {dir:?}: {} features, median σ {:.1} pm, pixel {:?} nm",
                frame.label,
                sig.len(),
                1000.0 * sig[sig.len() / 2],
                frame.pixel_nm
            );
        }
    }
    // Trace − retrace: each backward feature against the nearest forward one of its frame.
    for k in 0..set.frames.len() {
        let fw: Vec<_> = set
            .features
            .iter()
            .filter(|f| f.frame_index == k && f.direction == LineDirection::Forward)
            .collect();
        let (mut sum, mut n) = ([0.0, 0.0], 0usize);
        for b in set
            .features
            .iter()
            .filter(|f| f.frame_index == k && f.direction == LineDirection::Backward)
        {
            let near = fw.iter().min_by(|p, q| {
                (p.x_nm - b.x_nm)
                    .hypot(p.y_nm - b.y_nm)
                    .total_cmp(&(q.x_nm - b.x_nm).hypot(q.y_nm - b.y_nm))
            });
            if let Some(f) = near
                && (f.x_nm - b.x_nm).hypot(f.y_nm - b.y_nm) < 0.3 * lattice.a_nm()
            {
                sum[0] += f.x_nm - b.x_nm;
                sum[1] += f.y_nm - b.y_nm;
                n += 1;
            }
        }
        if n > 0 {
            println!(
                "frame {k}: forward − backward mean ({:.1}, {:.1}) pm over {n} pairs",
                1000.0 * sum[0] / n as f64,
                1000.0 * sum[1] / n as f64
            );
        }
    }
    match index_features(&set, &lattice) {
        Ok(idx) => {
            let b = &idx.basis;
            let len = |v: [f64; 2]| v[0].hypot(v[1]);
            println!(
                "basis b1 {:?} ({:.4} nm), b2 {:?} ({:.4} nm); warnings {:?}",
                b.b1_nm,
                len(b.b1_nm),
                b.b2_nm,
                len(b.b2_nm),
                idx.warnings
            );
            let n = idx.sites.iter().filter(|s| s.is_some()).count();
            println!("indexed {n} of {}", set.features.len());
        }
        Err(e) => println!("index error: {e}"),
    }
}
