//! Mutation test: flipped, truncated or inserted bytes in every real file never panic.
//!
//! The reader must return either a file or a typed error; mutations are biased towards the
//! header (the first 4 KiB and the RHK page tables), where a wrong byte changes sizes and
//! offsets, but also hit the data.

#![allow(clippy::unwrap_used)]

use std::path::Path;
use std::sync::OnceLock;

use proptest::prelude::*;
use spm_formats::read_bytes;
use spmcal_tests::measured_file;

const FILES: &[&str] = &[
    "si7x7-nanonis/Si_7x7_012.sxm",
    "si7x7-nanonis/Si_7x7_028.sxm",
    "si7x7-nanonis/Si_7x7_032.sxm",
    "si7x7-nanonis/Si_7x7_051.sxm",
    "graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4",
    "hopg-terrace-iso28600/graphiteterrace.spm",
    "si7x7-raw/image_with_defects.dat",
    "si7x7-raw/image_with_step_edge.dat",
    "si7x7-raw/image_with_step_edge_and_atoms.dat",
];

/// The real files, and a `.gwy` as spmcal writes it (no real file is one): two channels,
/// one with holes (masked), and metadata.
fn originals() -> &'static Vec<(String, Vec<u8>)> {
    static DATA: OnceLock<Vec<(String, Vec<u8>)>> = OnceLock::new();
    DATA.get_or_init(|| {
        let mut files: Vec<(String, Vec<u8>)> = FILES
            .iter()
            .map(|rel| {
                let path = measured_file(rel);
                let name = path.file_name().unwrap().to_string_lossy().into_owned();
                (name, std::fs::read(&path).unwrap())
            })
            .collect();
        let (nx, ny) = (32, 24);
        let data = |hole: bool| -> Vec<f64> {
            (0..nx * ny)
                .map(|i| {
                    if hole && i % 37 == 0 {
                        f64::NAN
                    } else {
                        1e-10 * (i as f64).sin()
                    }
                })
                .collect()
        };
        let channel = |direction, hole| {
            spm_formats::Channel::new("Z", direction, "m", nx, ny, data(hole))
                .unwrap()
                .with_size_nm(3.2, 2.4)
                .with_center_nm(1.0, -2.0)
        };
        let gwy = spm_formats::encode_gwy(
            &[
                channel(spm_formats::Direction::Forward, false),
                channel(spm_formats::Direction::Backward, true),
            ],
            &[("spmcal_scan_angle_ccw_deg".to_owned(), "10".to_owned())],
        )
        .unwrap();
        files.push(("written.gwy".to_owned(), gwy));
        files
    })
}

#[derive(Debug, Clone)]
enum Mutation {
    /// Set byte at position (fraction of the header window or of the file) to a value.
    Set { at: Pos, value: u8 },
    /// XOR a 4-byte little-endian word with a mask (changes sizes and offsets).
    Word { at: Pos, mask: u32 },
    /// Cut the file at a position.
    Truncate { at: Pos },
    /// Insert bytes at a position.
    Insert { at: Pos, bytes: Vec<u8> },
    /// Remove a run of bytes.
    Remove { at: Pos, len: usize },
}

#[derive(Debug, Clone, Copy)]
enum Pos {
    /// Within the first 4 KiB (text headers, RHK file and page index headers).
    Head(usize),
    /// Within the RHK page header/string region (bytes 5000–6100) or anywhere for others.
    Tables(usize),
    /// Anywhere in the file.
    Anywhere(usize),
}

impl Pos {
    fn resolve(self, len: usize) -> usize {
        if len == 0 {
            return 0;
        }
        match self {
            Pos::Head(k) => k % len.min(4096),
            Pos::Tables(k) => (5000 + k % 1100) % len,
            Pos::Anywhere(k) => k % len,
        }
    }
}

fn pos() -> impl Strategy<Value = Pos> {
    prop_oneof![
        4 => any::<usize>().prop_map(Pos::Head),
        2 => any::<usize>().prop_map(Pos::Tables),
        2 => any::<usize>().prop_map(Pos::Anywhere),
    ]
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        3 => (pos(), any::<u8>()).prop_map(|(at, value)| Mutation::Set { at, value }),
        3 => (pos(), any::<u32>()).prop_map(|(at, mask)| Mutation::Word { at, mask }),
        2 => pos().prop_map(|at| Mutation::Truncate { at }),
        1 => (pos(), proptest::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(at, bytes)| Mutation::Insert { at, bytes }),
        1 => (pos(), 1usize..64).prop_map(|(at, len)| Mutation::Remove { at, len }),
    ]
}

fn apply(bytes: &mut Vec<u8>, m: &Mutation) {
    let len = bytes.len();
    match m {
        Mutation::Set { at, value } => {
            if len > 0 {
                let i = at.resolve(len);
                bytes[i] = *value;
            }
        }
        Mutation::Word { at, mask } => {
            let i = at.resolve(len);
            for (k, b) in mask.to_le_bytes().iter().enumerate() {
                if let Some(x) = bytes.get_mut(i + k) {
                    *x ^= b;
                }
            }
        }
        Mutation::Truncate { at } => bytes.truncate(at.resolve(len)),
        Mutation::Insert { at, bytes: ins } => {
            let i = at.resolve(len);
            bytes.splice(i..i, ins.iter().copied());
        }
        Mutation::Remove { at, len: n } => {
            let i = at.resolve(len);
            let end = (i + n).min(len);
            bytes.drain(i..end);
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn mutated_files_never_panic(
        file in 0..=FILES.len(),
        mutations in proptest::collection::vec(mutation(), 1..4),
    ) {
        let (name, original) = &originals()[file];
        let mut bytes = original.clone();
        for m in &mutations {
            apply(&mut bytes, m);
        }
        // Either a file or a typed error; the test fails on a panic.
        match read_bytes(&bytes, Path::new(name)) {
            Ok(f) => {
                for c in &f.channels {
                    prop_assert_eq!(c.data().len(), c.nx() * c.ny());
                }
                let _ = f.info();
            }
            Err(e) => {
                prop_assert!(e.to_string().contains(name.as_str()));
            }
        }
    }
}

/// Deterministic companion: cutting any real file anywhere in its header region (and at a
/// spread of data offsets) gives a typed error.
#[test]
fn truncation_anywhere_is_a_typed_error() {
    for (name, bytes) in originals() {
        let len = bytes.len();
        let head = (0..len.min(6200)).step_by(7);
        let body = (0..64).map(|k| k * (len / 64));
        for cut in head.chain(body).filter(|&c| c < len) {
            let e = read_bytes(&bytes[..cut], Path::new(name));
            assert!(e.is_err(), "{name} cut at {cut} read without error");
        }
    }
}
