#![allow(clippy::unwrap_used)]
use spm_hal::{CountPoint, Counts, Microscope, ScanRequest, Seconds, TraceHalf};
use spm_features::{detect, DetectionConfig, Polarity};
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let std: spm_calibration::StandardName = args[2].parse().unwrap();
    let size_a: f64 = args[3].parse().unwrap();
    let px: u32 = args[4].parse().unwrap();
    let mut opts = spmcal::virtual_mode::VirtualRunOptions::new(std); opts.smoothing_sigma_lattice = std::env::var("VSMOOTH").ok().and_then(|s| s.parse().ok());
    let (_, backend, plan) = spmcal::virtual_mode::virtual_job(std::path::Path::new(&args[1]), &opts).unwrap();
    let mut m = backend.microscope().unwrap();
    let caps = m.capabilities();
    let a_c = plan.standard.lattice_constant_nm / plan.standard.nominal_nm_per_count;
    let size = size_a * a_c;
    let step = size / f64::from(px - 1);
    let mut hit = 0; let mut total = 0; let mut nfeat = 0;
    for (fx, fy) in (0..100).map(|i| (0.32 + 0.04 * f64::from(i % 10) + 0.0123, 0.32 + 0.04 * f64::from(i / 10) + 0.0071)) {
        let c = CountPoint::from_counts(caps.field_min.x.value() + fx * (caps.field_max.x - caps.field_min.x).value(), caps.field_min.y.value() + fy * (caps.field_max.y - caps.field_min.y).value());
        let req = ScanRequest::centred_square(c, Counts(step), px, Seconds(1e-4));
        let f = m.scan(&req).unwrap();
        let map = f.height_map(TraceHalf::Forward).unwrap();
        let pol = if matches!(plan.standard.feature, spm_calibration::FeaturePolarity::Pits) { Polarity::Pit } else { Polarity::Hill };
        let snr: f64 = std::env::var("SNR").map(|s| s.parse().unwrap()).unwrap_or(4.0); let cfg = DetectionConfig { polarity: pol, min_snr: snr, min_separation_px: (0.5 * a_c / step).max(1.5), ..DetectionConfig::default() }; println!("noise {}", 0);
        let d = detect(&map, &cfg).unwrap();
        total += 1; nfeat += d.features.len(); if d.nearest(c).map_or(false, |f| f.position.distance(c).value() < 0.6 * a_c) { hit += 1; }
        if total > 3 { continue; }
        println!("at ({fx},{fy}) step {step:.2} counts: {} features, {} rejected, noise {}", d.features.len(), d.rejected.len(), d.noise_sigma_z_counts);
        let mut reasons = std::collections::BTreeMap::new();
        for r in &d.rejected { *reasons.entry(format!("{:?}", r.reason)).or_insert(0) += 1; }
        println!("  rejections {reasons:?}");
        for f in d.features.iter().take(4) { println!("  {:?} w {:?}", f.position, f.width); }
    }
    println!("windows {total}: with a feature within 0.6 a of the centre {hit}; features per window {}", nfeat as f64 / total as f64);
    println!("plan attach {:?} aperture {:?}", plan.attach, plan.aperture);
}
