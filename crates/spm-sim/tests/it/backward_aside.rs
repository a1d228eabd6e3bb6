//! The backward halves recorded aside (`Simulator::record_backward_aside`): every scan returns
//! its retrace, and the forward data, the instrument's state and its random streams go on bit
//! for bit as without them (the image benchmark's other methods keep their figures).
#![allow(clippy::unwrap_used)]

use spm_hal::{CountPoint, Counts, Microscope, ScanDirection, ScanRequest, Seconds, TraceHalf};
use spm_sim::{SimConfig, Simulator};
use std::path::PathBuf;

fn hopg() -> Simulator {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../configs/sim-hopg.toml");
    Simulator::new(SimConfig::from_file(path).unwrap()).unwrap()
}

/// Two identical instruments take the same direct and counter frames, one with the retraces
/// aside: the forward halves are bit-identical, and so is a later frame taken with the aside
/// off; the aside retraces are there, on the trace's pixels (the same atoms: correlated with
/// the trace well above chance), with times inside each line's second half.
#[test]
fn the_backward_half_aside_changes_nothing_the_forward_half_measures() {
    let mut plain = hopg();
    let mut aside = plain.clone();
    aside.record_backward_aside(true);
    let request = ScanRequest::centred_square(
        CountPoint::from_counts(100.0, -50.0),
        Counts(1.0),
        65,
        Seconds(2e-4),
    );
    for direction in [ScanDirection::Direct, ScanDirection::Counter] {
        let r = request.clone().with_direction(direction);
        let a = plain.scan(&r).unwrap();
        let b = aside.scan(&r).unwrap();
        assert!(a.backward.is_none());
        assert_eq!(a.forward, b.forward, "{direction:?}: forward data moved");
        let trace = b.height_map(TraceHalf::Forward).unwrap();
        let retrace = b.height_map(TraceHalf::Backward).unwrap();
        // Each retrace pixel is seen after the trace pixel of the same line, within one line.
        let line_s = 2.0 * 65.0 * 2e-4;
        for (t, r) in trace.time_s.iter().zip(&retrace.time_s) {
            assert!(*r > *t && *r - *t < line_s, "trace {t} s, retrace {r} s");
        }
        let corr = correlation(&trace.z_counts, &retrace.z_counts);
        assert!(
            corr > 0.5,
            "{direction:?}: trace/retrace correlation {corr}"
        );
    }
    aside.record_backward_aside(false);
    let later = request.clone();
    let a = plain.scan(&later).unwrap();
    let b = aside.scan(&later).unwrap();
    assert_eq!(
        a, b,
        "a later frame differs: the state or a random stream moved"
    );
}

fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    sab / (saa * sbb).sqrt()
}
