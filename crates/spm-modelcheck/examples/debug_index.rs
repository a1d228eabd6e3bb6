//! Prints the extracted features and the lattice indexing of one file.
//! `cargo run -p spm-modelcheck --example debug_index -- RELATIVE_PATH LATTICE`
#![allow(clippy::unwrap_used)]
use spm_modelcheck::{ExtractOptions, LatticeSpec, extract_features, index_features};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let path = spmcal_tests::measured_file(&args[0]);
    let lattice = LatticeSpec::parse(&args[1]).unwrap();
    let file = spm_formats::read_any(&path).unwrap();
    let set = extract_features(&[(file, None)], &lattice, &ExtractOptions::default()).unwrap();
    println!("{} features; frame {:?}", set.features.len(), set.frames[0]);
    let idx = index_features(&set, &lattice).unwrap();
    println!("basis {:?}", idx.basis);
    let n = idx.sites.iter().filter(|s| s.is_some()).count();
    println!("indexed {n}");
    for (f, s) in set.features.iter().zip(&idx.sites).take(40) {
        println!(
            "{:8.3} {:8.3} {:?} {:?} line {}",
            f.x_nm, f.y_nm, f.direction, s, f.line_index
        );
    }
}
