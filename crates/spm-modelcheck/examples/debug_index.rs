//! Prints the extracted features and the lattice indexing of one file.
//! `cargo run -p spm-modelcheck --example debug_index -- RELATIVE_PATH LATTICE`
#![allow(clippy::unwrap_used)]
use spm_modelcheck::{
    ExtractOptions, LatticeSpec, LineDirection, extract_features, index_features,
};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let path = spmcal_tests::measured_file(&args[0]);
    let lattice = LatticeSpec::parse(&args[1]).unwrap();
    let file = spm_formats::read_any(&path).unwrap();
    if let Some(out) = args.get(2) {
        let opts = spm_plot::PngOptions {
            zoom: 2,
            ..Default::default()
        };
        spm_plot::write_png(out, &file.channels[0], &opts).unwrap();
    }
    let set = extract_features(&[(file, None)], &lattice, &ExtractOptions::default()).unwrap();
    println!("{} features; frame {:?}", set.features.len(), set.frames[0]);
    // Nearest-neighbour vectors of the forward features (folded to x ≥ 0), binned.
    let pts: Vec<[f64; 2]> = set
        .features
        .iter()
        .filter(|f| f.direction == LineDirection::Forward)
        .map(|f| [f.x_nm, f.y_nm])
        .collect();
    let mut bins = std::collections::BTreeMap::new();
    for (i, p) in pts.iter().enumerate() {
        let mut best = (f64::INFINITY, [0.0, 0.0]);
        for (j, q) in pts.iter().enumerate() {
            let d = [q[0] - p[0], q[1] - p[1]];
            let l = d[0].hypot(d[1]);
            if i != j && l < best.0 {
                best = (l, d);
            }
        }
        let mut d = best.1;
        if d[0] < 0.0 {
            d = [-d[0], -d[1]];
        }
        let key = ((d[0] / 0.25).round() as i64, (d[1] / 0.25).round() as i64);
        *bins.entry(key).or_insert(0) += 1;
    }
    let mut v: Vec<_> = bins.into_iter().collect();
    v.sort_by_key(|b| std::cmp::Reverse(b.1));
    for ((x, y), n) in v.iter().take(15) {
        println!(
            "nn ({:.2}, {:.2}) nm × {n}",
            *x as f64 * 0.25,
            *y as f64 * 0.25
        );
    }
    match index_features(&set, &lattice) {
        Ok(idx) => {
            println!("basis {:?}", idx.basis);
            let n = idx.sites.iter().filter(|s| s.is_some()).count();
            println!("indexed {n}");
        }
        Err(e) => println!("index error: {e}"),
    }
}
