//! Large least squares, nalgebra beside faer (issue 17, item 8): the reduction that
//! `spm_regression::fit` runs over 10⁶ weighted records — a streaming Householder QR — with
//! nalgebra (the library's choice) and with faer (the same streaming QR, and one QR of the whole
//! augmented matrix), for a degree-3 and a degree-6 surface. Every kernel's coefficients are
//! checked against the library's; the figure is the best of a few runs, one thread.
//!
//! faer is compiled only with xtask's `faer` feature, which the `cargo xtask` alias turns on
//! (`.cargo/config.toml`): it stays out of `cargo test --workspace`, whose build it would
//! lengthen by minutes of CPU for a comparison the tests never run (issue 28, item 7). Built
//! without it, the section is recorded as not measured, with that reason.

use super::{Context, Section};
use crate::XtaskError;
use serde::Serialize;
#[cfg(feature = "faer")]
use spm_regression::bench_support::{LeastSquaresKernel, Records, reduce};
use std::fmt::Write as _;
#[cfg(feature = "faer")]
use std::time::Instant;

/// One kernel on one problem.
#[derive(Debug, Serialize)]
pub struct KernelTime {
    /// Kernel name (`nalgebra_streaming_qr`, `faer_streaming_qr`, `faer_dense_qr`).
    pub kernel: String,
    /// Best wall time over the repeats, ms.
    pub best_ms: f64,
    /// Largest |coefficient − nalgebra's| ÷ largest |coefficient|.
    pub max_relative_difference: f64,
}

/// One problem size.
#[derive(Debug, Serialize)]
pub struct LinalgCase {
    /// Polynomial degree of the surface.
    pub degree: u32,
    /// Terms of the surface (columns of the design matrix).
    pub terms: usize,
    /// Every kernel.
    pub kernels: Vec<KernelTime>,
    /// Fastest faer kernel's time ÷ nalgebra's (> 1: nalgebra is faster).
    pub faer_over_nalgebra: f64,
}

/// The section's figures.
#[derive(Debug, Serialize)]
pub struct LinalgResults {
    /// Records per fit.
    pub records: usize,
    /// Timed runs per kernel (the best counts).
    pub repeats: usize,
    /// Per degree.
    pub cases: Vec<LinalgCase>,
}

/// Without the `faer` feature: not measured, and why.
#[cfg(not(feature = "faer"))]
pub fn run(_ctx: &Context) -> Result<LinalgResults, XtaskError> {
    Err(XtaskError::step(
        "linalg",
        "not run: xtask was built without its `faer` feature (the `cargo xtask` alias turns it on; \
         `cargo run -p xtask --release --features faer -- bench`)",
    ))
}

/// Every kernel on a degree-3 and a degree-6 surface.
#[cfg(feature = "faer")]
pub fn run(ctx: &Context) -> Result<LinalgResults, XtaskError> {
    let (records, repeats) = if ctx.quick {
        (100_000, 1)
    } else {
        (1_000_000, 3)
    };
    let mut cases = Vec::new();
    for degree in [3, 6] {
        let data = Records::synthetic(records, degree);
        let mut reference: Option<Vec<f64>> = None;
        let mut kernels = Vec::new();
        for kernel in LeastSquaresKernel::ALL {
            let mut best_ms = f64::INFINITY;
            let mut coefficients = Vec::new();
            for _ in 0..repeats {
                let started = Instant::now();
                coefficients = reduce(&data, kernel)
                    .map_err(|e| XtaskError::step(format!("linalg {}", kernel.name()), e))?;
                best_ms = best_ms.min(started.elapsed().as_secs_f64() * 1e3);
            }
            let reference = reference.get_or_insert_with(|| coefficients.clone());
            let scale = reference.iter().fold(0.0_f64, |a, c| a.max(c.abs()));
            let max_relative_difference = coefficients
                .iter()
                .zip(reference.iter())
                .fold(0.0_f64, |a, (c, r)| a.max((c - r).abs()))
                / scale;
            kernels.push(KernelTime {
                kernel: kernel.name().to_owned(),
                best_ms,
                max_relative_difference,
            });
        }
        let nalgebra = kernels
            .iter()
            .find(|k| k.kernel == LeastSquaresKernel::NalgebraStreaming.name())
            .map_or(f64::NAN, |k| k.best_ms);
        let faer = kernels
            .iter()
            .filter(|k| k.kernel.starts_with("faer"))
            .fold(f64::INFINITY, |a, k| a.min(k.best_ms));
        let case = LinalgCase {
            degree,
            terms: spm_regression::n_terms(degree),
            faer_over_nalgebra: faer / nalgebra,
            kernels,
        };
        println!(
            "   linalg: degree {degree}, {records} records: nalgebra {nalgebra:.0} ms, faer best \
             {faer:.0} ms (faer/nalgebra {:.2})",
            case.faer_over_nalgebra
        );
        cases.push(case);
    }
    Ok(LinalgResults {
        records,
        repeats,
        cases,
    })
}

/// The section of `RESULTS.md`.
pub fn markdown(md: &mut String, section: &Section<LinalgResults>) {
    let _ = writeln!(md, "## Large least squares: nalgebra beside faer\n");
    match section {
        Section::Measured(r) => {
            let _ = writeln!(
                md,
                "The reduction of `spm_regression::fit` (R and Qᵀb of the weighted design matrix, \
                 then back substitution) over {} weighted records, one thread, best of {}. \
                 Streaming: blocks of rows stacked under the running triangular factor (what the \
                 library runs, O(terms²) memory); dense: one QR of the whole augmented matrix. \
                 The library keeps the faster one (nalgebra while faer/nalgebra > 1). \
                 Command: `cargo xtask bench` (criterion: `cargo bench -p spm-regression \
                 --features test-support --bench linalg`).\n",
                r.records, r.repeats
            );
            let _ = writeln!(
                md,
                "| degree (terms) | kernel | best ms | max rel. diff. to nalgebra |\n|---|---|---|---|"
            );
            for case in &r.cases {
                for k in &case.kernels {
                    let _ = writeln!(
                        md,
                        "| {} ({}) | {} | {:.0} | {:.1e} |",
                        case.degree, case.terms, k.kernel, k.best_ms, k.max_relative_difference
                    );
                }
            }
            let ratios: Vec<String> = r
                .cases
                .iter()
                .map(|c| format!("degree {}: {:.2}", c.degree, c.faer_over_nalgebra))
                .collect();
            let _ = writeln!(
                md,
                "\nfaer (fastest kernel) ÷ nalgebra: {}.\n",
                ratios.join(", ")
            );
        }
        Section::Missing { missing } => {
            let _ = writeln!(md, "Not measured in this run: {missing}\n");
        }
    }
}
