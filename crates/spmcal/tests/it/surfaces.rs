//! `spmcal fit`'s command line: a bad outlier threshold is refused before the CDB is opened
//! (the fit itself is `spm-correction`'s, tested there: `cargo test -p spm-correction --test
//! it fit::`).
#![allow(clippy::unwrap_used)]

#[test]
fn a_rejection_threshold_below_one_sigma_is_bad_input() {
    for bad in ["0.5", "-3", "nan", "inf"] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_spmcal"))
            .args(["fit", "--cdb", "/no/such.sqlite", "--out", "/no/such.json"])
            .arg(format!("--reject-outliers={bad}"))
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{bad}: {stderr}");
        assert!(stderr.contains("--reject-outliers"), "{bad}: {stderr}");
    }
}
