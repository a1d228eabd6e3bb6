//! An image-level generator independent of spm-sim and of the feature-level
//! generator: a cosine (graphite-like) lattice point-sampled at the true tip
//! position of every pixel, pixels equidistant in time along each line, trace
//! and retrace, written as Nanonis `.sxm` through spm-formats' writer and read
//! back by the diagnosis like any instrument file. Pixel locking of the
//! localiser, file timing and direction conventions are all exercised.
#![allow(dead_code, clippy::unwrap_used)]

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use spm_formats::{DateTime, ScanDir, SxmChannel, SxmScan, encode_sxm};
use std::f64::consts::PI;
use std::path::PathBuf;

/// What the generator hides (one effect per case, or none).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Hidden {
    None,
    /// Rate-independent trace/retrace separation along x, largest mid-line
    /// (cos(πξ/2) shape, not the library's polynomial): half-separation at
    /// mid-line, nm.
    Hysteresis {
        half_separation_nm: f64,
    },
    /// Drift acceleration (x, y), nm/s².
    DriftAcceleration {
        a_nm_per_s2: [f64; 2],
    },
    /// Lateral jump (x, y) at a time (s from the first frame's start).
    TipChange {
        time_s: f64,
        jump_nm: [f64; 2],
    },
    /// Sinusoidal vibration: amplitudes (x, y) nm, frequency Hz.
    Vibration {
        amplitude_nm: [f64; 2],
        frequency_hz: f64,
    },
    /// First-order Z feedback filtering the measured height along the line:
    /// per-pixel decay d (the measured height keeps d of its previous value).
    FeedbackFilter {
        decay: f64,
    },
    /// Quadratic + cubic nonlinearity of the x axis at the frame edge
    /// (fractions of the half-width).
    Nonlinearity {
        quadratic: f64,
        cubic: f64,
    },
    /// Piezo creep after the move to each frame's start: input displacement
    /// c·lg(1 + t′/τ) per axis (nominal nm per decade), t′ since the frame
    /// start.
    Creep {
        nm_per_decade: [f64; 2],
        time_constant_s: f64,
    },
    /// Quadratic crosstalk (guidance bow): input x += b_x·H·η², y += b_y·W·ξ².
    Bow {
        x_from_y: f64,
        y_from_x: f64,
    },
    /// Obliquity varying over the field: input x += g_x·W·ξη, y += g_y·H·ξη.
    ShearGradient {
        x: f64,
        y: f64,
    },
    /// Backward lines shifted along y (interlace), nm.
    Interlace {
        dy_nm: f64,
    },
    /// Fast axis driven sinusoidally in time (fast SPM), pixels equidistant
    /// in time: true x = W·sin(βξ)/sin β for the commanded ξ.
    SineDrive {
        beta_rad: f64,
    },
    /// The drift + hysteresis + creep model of a peer (Yothers, Browder &
    /// Bumm, Rev. Sci. Instrum. 88, 013708 (2017)), implemented from its
    /// equations: the drift *velocity* of each axis is v + b·t + c/(t′ + t₀)
    /// (t′ since the frame start: creep after the move to the frame, which
    /// integrates to c·ln(1 + t′/t₀)), and the fast axis's local scale after
    /// each turnaround grows as a power of the time since the line start, so
    /// a line reaches x = −W + 2W·τ^(1+p) (τ the fraction of the line time;
    /// retrace mirrored). The trace/retrace separation is largest mid-line
    /// and vanishes at the line ends, but is not the library's polynomial.
    PeerDriftHysteresisCreep {
        acceleration_nm_per_s2: [f64; 2],
        creep_nm: [f64; 2],
        creep_time_constant_s: f64,
        hysteresis_exponent: f64,
    },
}

/// The scan program and the instrument's linear part.
#[derive(Clone, Debug)]
pub struct Program {
    pub a_nm: f64,
    pub pixels: usize,
    pub size_nm: f64,
    pub line_time_s: f64,
    /// Slow-axis direction of each frame.
    pub frames: Vec<ScanDir>,
    /// Pause between the end of one frame and the start of the next, s.
    pub gap_s: f64,
    pub corrugation_nm: f64,
    pub z_noise_nm: f64,
    pub scale: [f64; 2],
    pub obliquity_rad: f64,
    pub rotation_rad: f64,
    pub drift_nm_per_s: [f64; 2],
    /// Adsorbates per lattice site: Gaussian blobs (σ = 0.3 a, twice the corrugation) at
    /// random places on the sample, off the lattice sites (0: none, and the images are the
    /// same as without the field).
    pub adsorbates_per_site: f64,
}

impl Default for Program {
    fn default() -> Self {
        Self {
            a_nm: 0.2461,
            pixels: 96,
            size_nm: 4.8,
            line_time_s: 0.08,
            frames: vec![ScanDir::Down, ScanDir::Up],
            gap_s: 28.0,
            corrugation_nm: 0.03,
            z_noise_nm: 0.002,
            scale: [1.03, 0.98],
            obliquity_rad: 0.015,
            rotation_rad: 0.25,
            drift_nm_per_s: [0.004, -0.003],
            adsorbates_per_site: 0.0,
        }
    }
}

/// The adsorbates' places on the sample (lattice frame, nm): uniform over a square of twice
/// the frame's size (what the rotated, drifting frame sees), from their own random stream
/// (the Z noise of the images stays that of a program without them).
fn adsorbates(program: &Program, seed: u64) -> Vec<[f64; 2]> {
    if program.adsorbates_per_site <= 0.0 {
        return Vec::new();
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_ad50);
    let side = 2.0 * program.size_nm;
    let site_area = 0.75f64.sqrt() * program.a_nm * program.a_nm;
    let n = (program.adsorbates_per_site * side * side / site_area).round() as usize;
    let uniform = rand_distr::Uniform::new(-0.5 * side, 0.5 * side).unwrap();
    (0..n)
        .map(|_| [uniform.sample(&mut rng), uniform.sample(&mut rng)])
        .collect()
}

fn date_plus(seconds: u64) -> DateTime {
    let s = 12 * 3600 + seconds;
    DateTime::new(
        2024,
        3,
        5,
        (s / 3600) as u8,
        ((s / 60) % 60) as u8,
        (s % 60) as u8,
    )
    .unwrap()
}

/// The instrument's linear map J = R(θ)·M from the commanded position (nominal nm)
/// to the lattice frame (nm), M = [[k_x, k_y sin α], [0, k_y cos α]].
pub fn instrument_map(program: &Program) -> [[f64; 2]; 2] {
    let (so, co) = program.obliquity_rad.sin_cos();
    let (sr, cr) = program.rotation_rad.sin_cos();
    let m = [
        [program.scale[0], program.scale[1] * so],
        [0.0, program.scale[1] * co],
    ];
    [
        [cr * m[0][0] - sr * m[1][0], cr * m[0][1] - sr * m[1][1]],
        [sr * m[0][0] + cr * m[1][0], sr * m[0][1] + cr * m[1][1]],
    ]
}

/// Amplitudes along the image axes (the library reports tip–sample displacements along
/// the scan axes) of the generator's lattice-frame vibration (x: A_x cos ωt, y: A_y cos(ωt + 1)).
pub fn vibration_image_amplitudes(program: &Program, a: [f64; 2]) -> [f64; 2] {
    let (s, c) = program.rotation_rad.sin_cos();
    let (s1, c1) = 1f64.sin_cos();
    // Complex amplitudes: x → a0, y → a1·e^{i}.
    let x = [c * a[0] + s * a[1] * c1, s * a[1] * s1];
    let y = [-s * a[0] + c * a[1] * c1, c * a[1] * s1];
    [x[0].hypot(x[1]), y[0].hypot(y[1])]
}

/// The vibration frequency whose phase advances `advance` cycles per line period (trace
/// and retrace) on top of `whole` cycles, Hz.
pub fn frequency_for_advance(program: &Program, whole: f64, advance: f64) -> f64 {
    (whole + advance) / (2.0 * program.line_time_s)
}

/// Where the lattice's sites sit in the lattice frame (the hills' offset), nm.
fn site_offset(program: &Program, seed: u64) -> [f64; 2] {
    [
        0.031 * seed as f64 % program.a_nm,
        0.017 * seed as f64 % program.a_nm,
    ]
}

/// The rotation θ that puts the lattice's rows (its a₁ direction) at `angle_rad` from
/// the fast axis in the image, through the program's scales and obliquity: J·(cos, sin)
/// of that angle lies along the lattice frame's x.
pub fn rotation_for_row_angle(program: &Program, angle_rad: f64) -> f64 {
    let (so, co) = program.obliquity_rad.sin_cos();
    let (s, c) = angle_rad.sin_cos();
    let m = [
        program.scale[0] * c + program.scale[1] * so * s,
        program.scale[1] * co * s,
    ];
    -m[1].atan2(m[0])
}

/// The generator's truth for a clean program (`Hidden::None`): the commanded position
/// (nominal nm, centred, y up) at which the tip met the lattice site nearest to a
/// feature reported at `u_nm` and time `t_s` (the time axis of the first frame's start).
pub fn true_site_position(program: &Program, seed: u64, u_nm: [f64; 2], t_s: f64) -> [f64; 2] {
    let j = instrument_map(program);
    let offset = site_offset(program, seed);
    let d = [
        program.drift_nm_per_s[0] * t_s,
        program.drift_nm_per_s[1] * t_s,
    ];
    let q = [
        j[0][0] * u_nm[0] + j[0][1] * u_nm[1] + d[0] - offset[0],
        j[1][0] * u_nm[0] + j[1][1] * u_nm[1] + d[1] - offset[1],
    ];
    // Lattice basis a₁ = (a, 0), a₂ = (a/2, a√3/2): fractional coordinates, rounded.
    let a = program.a_nm;
    let h = 0.75f64.sqrt() * a;
    let fj = (q[1] / h).round();
    let fi = ((q[0] - 0.5 * a * fj) / a).round();
    let site = [
        fi * a + 0.5 * a * fj + offset[0] - d[0],
        fj * h + offset[1] - d[1],
    ];
    let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
    [
        (j[1][1] * site[0] - j[0][1] * site[1]) / det,
        (-j[1][0] * site[0] + j[0][0] * site[1]) / det,
    ]
}

/// Writes the frames as `.sxm` files in a fresh directory; returns their paths.
pub fn write_frames(program: &Program, hidden: Hidden, seed: u64, tag: &str) -> Vec<PathBuf> {
    let dir = std::env::temp_dir().join(format!(
        "spm-modelcheck-image-{}-{tag}-{seed}",
        std::process::id()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let noise = Normal::new(0.0, program.z_noise_nm.max(1e-12)).unwrap();
    let n = program.pixels;
    let p = program.size_nm / n as f64;
    let half = 0.5 * program.size_nm;
    let j = instrument_map(program);
    // Reciprocal vectors of the triangular lattice (hills on the sites).
    let g = 4.0 * PI / (3f64.sqrt() * program.a_nm);
    let gs: Vec<[f64; 2]> = (0..3)
        .map(|k| {
            let phi = PI / 6.0 + k as f64 * 2.0 * PI / 3.0;
            [g * phi.cos(), g * phi.sin()]
        })
        .collect();
    let offset = site_offset(program, seed);
    let blobs = adsorbates(program, seed);
    let blob_sigma = 0.3 * program.a_nm;
    let height = |r: [f64; 2]| {
        program.corrugation_nm / 3.0
            * gs.iter()
                .map(|gk| (gk[0] * (r[0] - offset[0]) + gk[1] * (r[1] - offset[1])).cos())
                .sum::<f64>()
            + blobs
                .iter()
                .map(|b| {
                    let d2 = (r[0] - b[0]).powi(2) + (r[1] - b[1]).powi(2);
                    if d2 < 16.0 * blob_sigma * blob_sigma {
                        2.0 * program.corrugation_nm * (-0.5 * d2 / (blob_sigma * blob_sigma)).exp()
                    } else {
                        0.0
                    }
                })
                .sum::<f64>()
    };
    let period = 2.0 * program.line_time_s;
    let duration = period * n as f64;
    let mut paths = Vec::new();
    let mut start = 0.0_f64;
    for (f, &dir_y) in program.frames.iter().enumerate() {
        let mut images = [vec![0.0; n * n], vec![0.0; n * n]];
        for (h, image) in images.iter_mut().enumerate() {
            let s = if h == 0 { 1.0 } else { -1.0 };
            for r in 0..n {
                let y_row = match dir_y {
                    ScanDir::Down => (0.5 * (n as f64 - 1.0) - r as f64) * p,
                    ScanDir::Up => (r as f64 - 0.5 * (n as f64 - 1.0)) * p,
                };
                let mut z_meas = None::<f64>;
                for k in 0..n {
                    let c = if s > 0.0 { k } else { n - 1 - k };
                    let mut u = [(c as f64 - 0.5 * (n as f64 - 1.0)) * p, y_row];
                    let t = start
                        + r as f64 * period
                        + if s > 0.0 { 0.0 } else { program.line_time_s }
                        + (k as f64 + 0.5) * program.line_time_s / n as f64;
                    let xi = u[0] / half;
                    let mut d = [program.drift_nm_per_s[0] * t, program.drift_nm_per_s[1] * t];
                    let mut decay = 0.0;
                    match hidden {
                        Hidden::None => {}
                        Hidden::Hysteresis { half_separation_nm } => {
                            u[0] -= s * half_separation_nm * (0.5 * PI * xi).cos();
                        }
                        Hidden::DriftAcceleration { a_nm_per_s2 } => {
                            d[0] += 0.5 * a_nm_per_s2[0] * t * t;
                            d[1] += 0.5 * a_nm_per_s2[1] * t * t;
                        }
                        Hidden::TipChange { time_s, jump_nm } => {
                            if t >= time_s {
                                d[0] += jump_nm[0];
                                d[1] += jump_nm[1];
                            }
                        }
                        Hidden::Vibration {
                            amplitude_nm,
                            frequency_hz,
                        } => {
                            let w = 2.0 * PI * frequency_hz * t;
                            d[0] += amplitude_nm[0] * w.cos();
                            d[1] += amplitude_nm[1] * (w + 1.0).cos();
                        }
                        Hidden::FeedbackFilter { decay: dd } => decay = dd,
                        Hidden::Nonlinearity { quadratic, cubic } => {
                            u[0] += half * (quadratic * xi * xi + cubic * xi.powi(3));
                        }
                        Hidden::SineDrive { beta_rad } => {
                            u[0] = half * (beta_rad * xi).sin() / beta_rad.sin();
                        }
                        Hidden::Creep {
                            nm_per_decade,
                            time_constant_s,
                        } => {
                            let g = (1.0 + (t - start) / time_constant_s).log10();
                            u[0] += nm_per_decade[0] * g;
                            u[1] += nm_per_decade[1] * g;
                        }
                        Hidden::Bow { x_from_y, y_from_x } => {
                            let eta = u[1] / half;
                            u[0] += x_from_y * half * eta * eta;
                            u[1] += y_from_x * half * xi * xi;
                        }
                        Hidden::ShearGradient { x, y } => {
                            let eta = u[1] / half;
                            u[0] += x * half * xi * eta;
                            u[1] += y * half * xi * eta;
                        }
                        Hidden::Interlace { dy_nm } => {
                            if s < 0.0 {
                                u[1] += dy_nm;
                            }
                        }
                        Hidden::PeerDriftHysteresisCreep {
                            acceleration_nm_per_s2,
                            creep_nm,
                            creep_time_constant_s,
                            hysteresis_exponent,
                        } => {
                            let tau_line = (k as f64 + 0.5) / n as f64;
                            let reach = 2.0 * tau_line.powf(1.0 + hysteresis_exponent) - 1.0;
                            u[0] = s * half * reach;
                            let t_frame = t - start;
                            let log = (1.0 + t_frame / creep_time_constant_s).ln();
                            for a in 0..2 {
                                d[a] += 0.5 * acceleration_nm_per_s2[a] * t * t + creep_nm[a] * log;
                            }
                        }
                    }
                    let q = [
                        j[0][0] * u[0] + j[0][1] * u[1] + d[0],
                        j[1][0] * u[0] + j[1][1] * u[1] + d[1],
                    ];
                    let z_true = height(q);
                    let z = match z_meas {
                        Some(prev) if decay > 0.0 => decay * prev + (1.0 - decay) * z_true,
                        _ => z_true,
                    };
                    z_meas = Some(z);
                    // Stored in acquisition (time) order: column k of line r.
                    image[r * n + k] = (z + noise.sample(&mut rng)) * 1e-9;
                }
            }
        }
        let [fwd, bwd] = images;
        let scan = SxmScan {
            pixels: [n, n],
            size_nm: [program.size_nm, program.size_nm],
            centre_nm: [0.0, 0.0],
            angle_deg: 0.0,
            line_time_s: [program.line_time_s, program.line_time_s],
            scan_dir: dir_y,
            recorded: date_plus(start.floor() as u64),
            bias_v: 0.1,
            comment: format!("image-level generator, hidden {hidden:?}"),
            extra_header: Vec::new(),
            channels: vec![SxmChannel {
                name: "Z".into(),
                unit: "m".into(),
                forward: fwd,
                backward: Some(bwd),
            }],
        };
        let path = dir.join(format!("frame{f}.sxm"));
        std::fs::write(&path, encode_sxm(&scan, &path).unwrap()).unwrap();
        paths.push(path);
        // Whole seconds between frames with a pause (stamps are exact);
        // back to back without one (a movie: stamps truncate).
        start = if program.gap_s > 0.0 {
            (start + duration + program.gap_s).round()
        } else {
            start + duration
        };
    }
    paths
}

/// A frame of white noise or of random blobs (no lattice), as `.sxm`.
pub fn write_no_lattice(program: &Program, blobs: bool, seed: u64, tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "spm-modelcheck-image-{}-{tag}-{seed}",
        std::process::id()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let n = program.pixels;
    let p = program.size_nm / n as f64;
    let unit: Normal<f64> = Normal::new(0.0, 1.0).unwrap();
    let centres: Vec<[f64; 2]> = (0..(n * n / 40))
        .map(|_| {
            [
                (unit.sample(&mut rng) * 0.3 + 0.5).rem_euclid(1.0) * program.size_nm,
                (unit.sample(&mut rng) * 0.3 + 0.5).rem_euclid(1.0) * program.size_nm,
            ]
        })
        .collect();
    let mut image = vec![0.0; n * n];
    for r in 0..n {
        for c in 0..n {
            let v = if blobs {
                let x = [c as f64 * p, r as f64 * p];
                centres
                    .iter()
                    .map(|b| {
                        let d2 = (x[0] - b[0]).powi(2) + (x[1] - b[1]).powi(2);
                        0.05 * (-d2 / (2.0 * (0.35 * program.a_nm).powi(2))).exp()
                    })
                    .sum::<f64>()
                    + 0.001 * unit.sample(&mut rng)
            } else {
                0.01 * unit.sample(&mut rng)
            };
            image[r * n + c] = v * 1e-9;
        }
    }
    let backward: Vec<f64> = image.clone();
    let scan = SxmScan {
        pixels: [n, n],
        size_nm: [program.size_nm, program.size_nm],
        centre_nm: [0.0, 0.0],
        angle_deg: 0.0,
        line_time_s: [program.line_time_s, program.line_time_s],
        scan_dir: ScanDir::Down,
        recorded: date_plus(0),
        bias_v: 0.1,
        comment: String::new(),
        extra_header: Vec::new(),
        channels: vec![SxmChannel {
            name: "Z".into(),
            unit: "m".into(),
            forward: image,
            backward: Some(backward),
        }],
    };
    let path = dir.join(format!("{}.sxm", if blobs { "blobs" } else { "noise" }));
    std::fs::write(&path, encode_sxm(&scan, &path).unwrap()).unwrap();
    path
}

/// The written frames as diagnose's inputs (times from the files).
pub fn inputs(paths: &[std::path::PathBuf]) -> Vec<spm_modelcheck::ImageInput> {
    paths
        .iter()
        .map(|p| spm_modelcheck::ImageInput {
            path: p.clone(),
            start_time_s: None,
        })
        .collect()
}
