//! The standard's lattice as the ruler of one image (issue 23, `spmcal correct --ruler`): the
//! creep of the move that brought the probe there and the drift, estimated from the image
//! alone.
//!
//! A file says nothing of the probe's history before its frame, so its dynamic correction
//! ([`crate::dynamic::dynamic_map`]) starts settled. What it leaves is a function of time only:
//!
//! `e(t) = A·g(t + t_m) + v·t`, `g(t) = w·Σₖ e^{−t/τₖ}`
//!
//! (`e` the corrected position minus the true one, nm; `g` the creep still to come `t` after a
//! unit step, of the calibration's own law; `t_m` the time from the end of the approach move
//! to the frame's first pixel; `A` the move's creep amplitude, nm; `v` the drift, nm/s). Every
//! atom of the image is seen at its own time, so the atoms of a known lattice (HOPG: hexagonal,
//! a = 0.246 nm) sit at `O + R(θ)·B·n + e(t)`, n the atom's lattice index. The image's
//! atoms are indexed by growing from the atom seen at the median time, neighbour by neighbour,
//! with the apparent basis of the atoms seen around that time (a step between neighbours is
//! never ambiguous, however far the frame is sheared; a frame the index does not span is
//! straightened by the drift of the indexed patch and indexed again, as long as the index
//! grows), and
//! `O`, the rotation `δθ` about the apparent one, `A` and `v` follow by linear least squares
//! for each `t_m` of a log-spaced ladder; the `t_m` of the least residual is kept. Any `(A, t_m,
//! v)` that fits the atoms gives the same `e` over the frame, so that `A` and `v` trade off for
//! a late `t_m` does not matter.
//!
//! A static error of the calibration along the slow axis (K̄y, α) is a constant rate of `e`
//! along y, so the time terms remove it too. What a function of time cannot hold (a line takes
//! no time) is what depends on the place `u` along the line (−½ … ½ of the line's length from
//! its middle): the fast axis's scale and nonlinearity left by the calibration, and the
//! trace's own hysteresis. The fit carries them as `x·u, x·u², x·u³, y·u², y·u³` (a term
//! `y·u` is a rotation plus the shear the drift already carries); they must stay within 15 %
//! of the line's length anywhere along it. A half's hysteresis is mirrored in the other half,
//! so each half is fitted on its own atoms. A constant offset is invisible to the lattice: the
//! correction leaves the frame's middle where the map put it.
//!
//! Images whose lattice is not resolved (fewer than `min_pixels_per_constant` pixels per
//! lattice constant), whose index spans less than 70 % of the atoms, or whose atoms stay more
//! than a quarter lattice constant RMS off the fitted lattice (a wrong index: a correct one
//! leaves 0.01–0.04 nm on the benchmark's images) are refused, not guessed.

use spm_correction::dynamics::CreepLaw;
use spm_correction::{CoordinateMap, CorrectionError, YCoordinates};
use spm_features::{DetectionConfig, Feature, LatticeConfig, detect, lattice_vectors};
use spm_hal::{CountPoint, Counts, HeightMap};

/// Fewest atoms indexed, as a fraction of those located, for a fit that spans the frame.
const MIN_INDEXED_FRACTION: f64 = 0.7;
/// Atoms indexed, as a fraction of those located, beyond which the index is not straightened
/// further.
const COMPLETE_FRACTION: f64 = 0.95;
/// Most straightening passes (drift fit, straighten, index again) of a strained frame.
const MAX_STRAIGHTENING_PASSES: usize = 8;
/// Largest RMS distance of the atoms from the fitted lattice, in lattice constants.
const MAX_RESIDUAL_FRACTION: f64 = 0.25;
/// Largest displacement the fast-axis terms may make anywhere along a line, in line lengths.
/// A calibrated map is off along its lines by a few per cent (13 % on the worst simulated
/// scanner, file alone); terms beyond that fit something else (two grains, a wrong index).
const MAX_FAST_AXIS_FRACTION: f64 = 0.15;

/// The lattice a ruler measures against.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LatticeRuler {
    /// Nearest-neighbour distance of the hexagonal lattice, nm (HOPG 0.246).
    pub constant_nm: f64,
    /// Fewest pixels per lattice constant for the atoms to be located (default 4).
    pub min_pixels_per_constant: f64,
}

impl LatticeRuler {
    /// HOPG's surface lattice: hexagonal, a = 0.246 nm.
    #[must_use]
    pub fn hopg() -> Self {
        Self {
            constant_nm: 0.246,
            min_pixels_per_constant: 4.0,
        }
    }
}

/// The approach creep and drift the ruler found (see the module doc).
#[derive(Debug, Clone, PartialEq)]
pub struct RulerEstimate {
    /// A, nm per axis.
    pub amplitude_nm: [f64; 2],
    /// t_m, s.
    pub since_move_s: f64,
    /// v, nm/s per axis.
    pub drift_nm_per_s: [f64; 2],
    /// The fast axis's terms along the line (see `fast_axis_terms`), nm: x·u, x·u², x·u³,
    /// y·u², y·u³, u the place along the line in line lengths from its middle (−½ … ½).
    pub fast_axis_nm: [f64; FAST_TERMS],
    /// e at the frame's middle (the median pixel time, the middle of the line), nm: what
    /// [`Self::error_at_nm`] leaves in place. A constant offset is not seen by the lattice
    /// (the fit's offset takes it), so the correction moves the frame's middle nowhere.
    pub reference_nm: [f64; 2],
    /// Atoms located.
    pub atoms: usize,
    /// Atoms indexed and fitted.
    pub indexed: usize,
    /// RMS distance of the atoms from the lattice before the fit (offset and rotation
    /// removed), nm.
    pub before_rms_nm: f64,
    /// RMS residual after it, nm.
    pub residual_rms_nm: f64,
    law: CreepLaw,
}

impl RulerEstimate {
    /// g(t).
    fn to_come(law: &CreepLaw, t_s: f64) -> f64 {
        law.still_to_come(t_s)
    }

    /// e at time `t_s` and place `u` along the line (−½ … ½, line lengths from its middle),
    /// less its value at the frame's middle ([`Self::reference_nm`]), nm.
    #[must_use]
    pub fn error_at_nm(&self, t_s: f64, u: f64) -> [f64; 2] {
        let (e, f) = (self.error_nm(t_s), fast_axis_nm(&self.fast_axis_nm, u));
        [
            e[0] + f[0] - self.reference_nm[0],
            e[1] + f[1] - self.reference_nm[1],
        ]
    }

    /// The part of e that is a function of time alone (approach creep and drift), nm.
    #[must_use]
    pub fn error_nm(&self, t_s: f64) -> [f64; 2] {
        let g = Self::to_come(&self.law, t_s + self.since_move_s);
        [
            self.amplitude_nm[0] * g + self.drift_nm_per_s[0] * t_s,
            self.amplitude_nm[1] * g + self.drift_nm_per_s[1] * t_s,
        ]
    }

    /// `map` with e(t) of every pixel removed (`times_s` per pixel, the map's order).
    ///
    /// # Errors
    /// [`CorrectionError::SizeMismatch`]; as [`CoordinateMap::new`].
    pub fn corrected(
        &self,
        map: &CoordinateMap,
        times_s: &[f64],
    ) -> Result<CoordinateMap, CorrectionError> {
        let nx = map.columns();
        without_error(map, times_s, |t, column| {
            self.error_at_nm(t, along_line(column as f64, nx))
        })
    }
}

/// `map` with `error(t, column)` (nm) of every pixel removed, `times_s` per pixel in the map's
/// order: what the ruler and the counter partner ([`crate::counter`]) estimated.
///
/// # Errors
/// [`CorrectionError::SizeMismatch`]; as [`CoordinateMap::new`].
pub(crate) fn without_error(
    map: &CoordinateMap,
    times_s: &[f64],
    error: impl Fn(f64, usize) -> [f64; 2],
) -> Result<CoordinateMap, CorrectionError> {
    let (nx, ny) = (map.columns(), map.rows());
    if times_s.len() != nx * ny {
        return Err(CorrectionError::SizeMismatch {
            what: "pixel times",
            expected: nx * ny,
            got: times_s.len(),
        });
    }
    let mut x = Vec::with_capacity(nx * ny);
    let mut y = Vec::with_capacity(nx * ny);
    for (i, &t) in times_s.iter().enumerate() {
        let e = error(t, i % nx);
        let p = map
            .point(i % nx, i / nx)
            .ok_or(CorrectionError::Empty("map pixel"))?;
        x.push(p.x.value() - e[0]);
        y.push(p.y.value() - e[1]);
    }
    CoordinateMap::new(nx, ny, x, YCoordinates::PerPixel(y))
}

/// An atom: corrected position (nm) and time (s), and its detection with the position
/// replaced by the corrected one (what the lattice estimator reads).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Atom {
    pub(crate) p: [f64; 2],
    pub(crate) t: f64,
    /// Where along the line the atom was seen: its column's distance from the middle of the
    /// line, in line lengths (−½ … ½).
    u: f64,
    feature: Feature,
}

/// The image's atoms at their corrected positions and times.
pub(crate) fn atoms(
    heights: &[f64],
    map: &CoordinateMap,
    times_s: &[f64],
    ruler: &LatticeRuler,
) -> Result<Vec<Atom>, CorrectionError> {
    let (nx, ny) = (map.columns(), map.rows());
    let (x0, x1, _, _) = map.bounds_nm();
    let nm_per_px = (x1 - x0) / (nx.max(2) - 1) as f64;
    let per_constant = ruler.constant_nm / nm_per_px;
    if per_constant.is_nan() || per_constant < ruler.min_pixels_per_constant {
        return Err(CorrectionError::InvalidArgument(format!(
            "the lattice ruler needs ≥ {} pixels per lattice constant; this image has {per_constant:.2} \
             ({nm_per_px:.4} nm per pixel, a = {} nm)",
            ruler.min_pixels_per_constant, ruler.constant_nm
        )));
    }
    let height_map = HeightMap {
        origin: CountPoint::from_counts(0.0, 0.0),
        pixel_step: Counts(1.0),
        columns: nx,
        rows: ny,
        z_counts: heights
            .iter()
            .map(|v| if v.is_finite() { *v } else { 0.0 })
            .collect(),
        time_s: times_s.to_vec(),
    };
    let config = DetectionConfig {
        min_separation_px: 0.35 * per_constant,
        ..DetectionConfig::default()
    };
    let found = detect(&height_map, &config)
        .map_err(|e| CorrectionError::InvalidArgument(format!("lattice ruler: {e}")))?;
    Ok(found
        .features
        .iter()
        .filter_map(|f: &Feature| {
            let p = map.interpolate(f.column, f.row)?;
            Some(Atom {
                p: [p.x.value(), p.y.value()],
                t: f.time.value(),
                u: along_line(f.column, nx),
                feature: Feature {
                    position: CountPoint::from_counts(p.x.value(), p.y.value()),
                    ..*f
                },
            })
        })
        .collect())
}

/// The lattice index of every atom reachable from the median-time atom by neighbour steps,
/// and the apparent basis used: per atom its lattice index (when reached), and the apparent
/// basis, nm.
pub type Indexing = (Vec<Option<[i64; 2]>>, [[f64; 2]; 2]);

/// The apparent basis and nearest-neighbour distance of the atoms seen around the median
/// time: creep and drift strain a frame differently at each time, so the atoms of a short
/// time window (the third of them nearest the median time, then two thirds, then all) show one
/// lattice where the whole frame may show none.
fn apparent_basis(atoms: &[Atom]) -> Result<([[f64; 2]; 2], f64), CorrectionError> {
    let mut by_time: Vec<&Atom> = atoms.iter().collect();
    by_time.sort_by(|a, b| a.t.total_cmp(&b.t));
    let mut last = CorrectionError::InvalidArgument("lattice ruler: no atoms".into());
    for fraction in [1.0 / 3.0, 2.0 / 3.0, 1.0] {
        let take = ((by_time.len() as f64 * fraction).ceil() as usize).min(by_time.len());
        if take < 12 && fraction < 1.0 {
            continue;
        }
        let from = (by_time.len() - take) / 2;
        let window: Vec<Feature> = by_time[from..from + take]
            .iter()
            .map(|a| a.feature)
            .collect();
        let lattice = match lattice_vectors(&window, &LatticeConfig::default()) {
            Ok(l) => l,
            Err(e) => {
                last = CorrectionError::InvalidArgument(format!("lattice ruler: {e}"));
                continue;
            }
        };
        let Some((b1, b2)) = lattice.basis() else {
            last = CorrectionError::InvalidArgument(
                "lattice ruler: fewer than two lattice directions".into(),
            );
            continue;
        };
        return Ok((
            [
                [b1.vector.x.value(), b1.vector.y.value()],
                [b2.vector.x.value(), b2.vector.y.value()],
            ],
            lattice.nearest_neighbour.value(),
        ));
    }
    Err(last)
}

fn index(atoms: &[Atom]) -> Result<Indexing, CorrectionError> {
    let (basis, nn) = apparent_basis(atoms)?;
    let det = basis[0][0] * basis[1][1] - basis[1][0] * basis[0][1];
    if det == 0.0 || !det.is_finite() {
        return Err(CorrectionError::InvalidArgument(
            "lattice ruler: collinear lattice directions".into(),
        ));
    }
    let reach = 1.3 * nn;
    // The lattice step (k₁, k₂) that displacement `d` is in the basis `b`, when it is one to
    // 0.3 nearest-neighbour distances, and how far off it is.
    let step_of = |b: &[[f64; 2]; 2], d: [f64; 2]| -> Option<([i64; 2], f64)> {
        let det = b[0][0] * b[1][1] - b[1][0] * b[0][1];
        if det == 0.0 || !det.is_finite() {
            return None;
        }
        let k1 = (d[0] * b[1][1] - d[1] * b[1][0]) / det;
        let k2 = (b[0][0] * d[1] - b[0][1] * d[0]) / det;
        let k = [k1.round(), k2.round()];
        let r = [
            d[0] - k[0] * b[0][0] - k[1] * b[1][0],
            d[1] - k[0] * b[0][1] - k[1] * b[1][1],
        ];
        let off = r[0].hypot(r[1]);
        (off < 0.3 * nn).then_some(([k[0] as i64, k[1] as i64], off))
    };
    // The basis a newly indexed atom carries on: its parent's, with the vector of the step just
    // taken when that step was one basis vector (so that the basis follows a strain that changes
    // across the frame, as creep's does).
    let carried = |b: &[[f64; 2]; 2], k: [i64; 2], d: [f64; 2]| -> [[f64; 2]; 2] {
        let mut out = *b;
        match k {
            [1, 0] => out[0] = d,
            [-1, 0] => out[0] = [-d[0], -d[1]],
            [0, 1] => out[1] = d,
            [0, -1] => out[1] = [-d[0], -d[1]],
            _ => {}
        }
        out
    };
    // Grow from the atom seen at the median time; a seed that is no lattice site (a defect,
    // noise) reaches few atoms, so the next seeds in time from the median are tried until one
    // component holds half the atoms.
    let mut by_time: Vec<usize> = (0..atoms.len()).collect();
    by_time.sort_by(|&a, &b| atoms[a].t.total_cmp(&atoms[b].t));
    let median_t = atoms[by_time[by_time.len() / 2]].t;
    let mut seeds = by_time;
    seeds.sort_by(|&a, &b| {
        (atoms[a].t - median_t)
            .abs()
            .total_cmp(&(atoms[b].t - median_t).abs())
    });
    let grow = |seed: usize| -> (Vec<Option<[i64; 2]>>, usize) {
        let mut n: Vec<Option<[i64; 2]>> = vec![None; atoms.len()];
        let mut local = vec![basis; atoms.len()];
        n[seed] = Some([0, 0]);
        let mut reached = 1;
        let mut queue = std::collections::VecDeque::from([seed]);
        while let Some(i) = queue.pop_front() {
            let Some(ni) = n[i] else { continue };
            let b = local[i];
            for (j, a) in atoms.iter().enumerate() {
                if n[j].is_some() {
                    continue;
                }
                let d = [a.p[0] - atoms[i].p[0], a.p[1] - atoms[i].p[1]];
                if d[0].hypot(d[1]) > reach {
                    continue;
                }
                if let Some((k, off)) = step_of(&b, d) {
                    n[j] = Some([ni[0] + k[0], ni[1] + k[1]]);
                    // Only a clean step (a tenth of a neighbour distance) teaches the basis: a
                    // defect near a site must not bend it.
                    local[j] = if off < 0.1 * nn { carried(&b, k, d) } else { b };
                    reached += 1;
                    queue.push_back(j);
                }
            }
        }
        (n, reached)
    };
    let mut n = Vec::new();
    let mut best = 0;
    for &seed in seeds.iter().take(20) {
        let (component, reached) = grow(seed);
        if reached > best {
            best = reached;
            n = component;
        }
        if 2 * best >= atoms.len() {
            break;
        }
    }
    Ok((n, basis))
}

/// The lattice index of atoms whose `position` is in nm (and `time` their sighting), grown
/// neighbour by neighbour from the atom seen at the median time as the ruler does (see the
/// module doc): per atom its index `[n₁, n₂]` when reached, and the apparent basis (nm) used.
/// For per-image methods that measure against a known lattice (the image benchmark's
/// competitors) without repeating the ruler's indexing.
///
/// # Errors
/// [`CorrectionError::InvalidArgument`] when no lattice is found among the atoms.
pub fn index_lattice(features: &[Feature]) -> Result<Indexing, CorrectionError> {
    let atoms: Vec<Atom> = features
        .iter()
        .map(|f| Atom {
            p: [f.position.x.value(), f.position.y.value()],
            t: f.time.value(),
            u: 0.0,
            feature: *f,
        })
        .collect();
    if atoms.is_empty() {
        return Err(CorrectionError::InvalidArgument(
            "lattice index: no atoms".into(),
        ));
    }
    index(&atoms)
}

/// The true hexagonal basis of lattice constant `constant_nm` at the orientation of an
/// `apparent` basis ([`index_lattice`]): b₁ along the apparent first vector, b₂ at 60° or 120°
/// on the side of the apparent second, as the apparent pair is.
#[must_use]
pub fn hexagonal_basis(apparent: &[[f64; 2]; 2], constant_nm: f64) -> [[f64; 2]; 2] {
    true_basis(apparent, constant_nm)
}

/// The atoms that were indexed, with their indices.
fn indexed(atoms: &[Atom], n: &[Option<[i64; 2]>]) -> Vec<(Atom, [i64; 2])> {
    atoms
        .iter()
        .zip(n)
        .filter_map(|(a, n)| n.map(|n| (*a, n)))
        .collect()
}

/// The true basis (lattice constant `a`) at the apparent orientation: b₁ along the apparent
/// first vector, b₂ at 60° or 120° on the side of the apparent second, as the apparent pair is.
fn true_basis(apparent: &[[f64; 2]; 2], a: f64) -> [[f64; 2]; 2] {
    let theta = apparent[0][1].atan2(apparent[0][0]);
    let side = (apparent[0][0] * apparent[1][1] - apparent[0][1] * apparent[1][0]).signum();
    let angle2 = theta
        + side
            * if (apparent[0][0] * apparent[1][0] + apparent[0][1] * apparent[1][1]) >= 0.0 {
                std::f64::consts::FRAC_PI_3
            } else {
                2.0 * std::f64::consts::FRAC_PI_3
            };
    [
        [a * theta.cos(), a * theta.sin()],
        [a * angle2.cos(), a * angle2.sin()],
    ]
}

/// Columns of the fast-axis terms: per axis, what each of the [`FAST_TERMS`] coefficients
/// adds at `u` (the place along the line, −½ … ½). Along x a scale and its quadratic and cubic
/// companions (the fast axis's scale and nonlinearity left by the calibration, and the trace's
/// hysteresis); along y the quadratic and cubic (a linear one is a rotation plus a shear the
/// drift already carries).
fn fast_axis_terms(u: f64) -> [[f64; FAST_TERMS]; 2] {
    let (u2, u3) = (u * u, u * u * u);
    [[u, u2, u3, 0.0, 0.0], [0.0, 0.0, 0.0, u2, u3]]
}

/// Coefficients of the fast-axis terms ([`fast_axis_terms`]): x·u, x·u², x·u³, y·u², y·u³.
const FAST_TERMS: usize = 5;

/// The place `u` along a line of `columns` pixels of (fractional) column `column`: its
/// distance from the line's middle in line lengths (−½ … ½).
fn along_line(column: f64, columns: usize) -> f64 {
    (column - 0.5 * (columns as f64 - 1.0)) / (columns.max(2) - 1) as f64
}

/// The displacement the fast-axis terms of coefficients `c` (nm) make at `u`, nm.
fn fast_axis_nm(c: &[f64; FAST_TERMS], u: f64) -> [f64; 2] {
    let f = fast_axis_terms(u);
    let along = |row: &[f64; FAST_TERMS]| -> f64 { row.iter().zip(c).map(|(a, b)| a * b).sum() };
    [along(&f[0]), along(&f[1])]
}

/// The largest displacement the fast-axis terms `c` make anywhere along a line, nm.
fn fast_axis_reach_nm(c: &[f64; FAST_TERMS]) -> f64 {
    (0..=64)
        .map(|k| {
            let d = fast_axis_nm(c, f64::from(k) / 64.0 - 0.5);
            d[0].hypot(d[1])
        })
        .fold(0.0, f64::max)
}

/// The least-squares problem of the atoms against the lattice `b`, two rows per atom. Columns:
/// O_x, O_y, δθ, then A_x, A_y (with `since_move_s`), then v_x, v_y, then the
/// [`FAST_TERMS`] fast-axis coefficients.
fn design(
    used: &[(Atom, [i64; 2])],
    b: &[[f64; 2]; 2],
    law: &CreepLaw,
    since_move_s: Option<f64>,
) -> (Vec<Vec<f64>>, Vec<f64>) {
    let mut rows = Vec::with_capacity(2 * used.len());
    let mut rhs = Vec::with_capacity(2 * used.len());
    for (atom, n) in used {
        let (n1, n2) = (n[0] as f64, n[1] as f64);
        let l = [n1 * b[0][0] + n2 * b[1][0], n1 * b[0][1] + n2 * b[1][1]];
        let (mut x, mut y) = (vec![1.0, 0.0, -l[1]], vec![0.0, 1.0, l[0]]);
        if let Some(tm) = since_move_s {
            let g = RulerEstimate::to_come(law, atom.t + tm);
            x.extend([g, 0.0]);
            y.extend([0.0, g]);
        }
        x.extend([atom.t, 0.0]);
        y.extend([0.0, atom.t]);
        let f = fast_axis_terms(atom.u);
        x.extend(f[0]);
        y.extend(f[1]);
        rows.push(x);
        rhs.push(atom.p[0] - l[0]);
        rows.push(y);
        rhs.push(atom.p[1] - l[1]);
    }
    (rows, rhs)
}

/// Estimates the approach creep and drift of one image from its lattice (see the module doc).
/// `heights`, `map` and `times_s` in the map's order; `law` the calibration's creep law.
///
/// # Errors
/// [`CorrectionError::InvalidArgument`] for an image whose lattice is not resolved or not
/// found, indexed on less than 70 % of its atoms, or left more than a quarter lattice constant off (RMS) by
/// the fit; [`CorrectionError::Empty`] with fewer than 12 indexed atoms.
pub fn estimate_from_lattice(
    heights: &[f64],
    map: &CoordinateMap,
    times_s: &[f64],
    law: &CreepLaw,
    ruler: &LatticeRuler,
) -> Result<RulerEstimate, CorrectionError> {
    let n_px = map.columns() * map.rows();
    for (what, len) in [("heights", heights.len()), ("pixel times", times_s.len())] {
        if len != n_px {
            return Err(CorrectionError::SizeMismatch {
                what,
                expected: n_px,
                got: len,
            });
        }
    }
    let located = atoms(heights, map, times_s, ruler)?;
    let mut atoms = located.clone();
    let (mut n, mut apparent) = index(&atoms)?;
    // A frame strained too much for the index to span it: the drift fitted on the indexed patch
    // (a linear function of time extrapolates mildly) straightens the atoms, and the index is
    // grown again from them, as long as it grows. Each fit is on the located positions, with
    // the indices the last straightening found, so its drift is the whole one.
    let mut pre_drift = [0.0; 2];
    let mut pre_fast = [0.0; FAST_TERMS];
    for _ in 0..MAX_STRAIGHTENING_PASSES {
        let reached = n.iter().flatten().count();
        if reached < 12 || reached as f64 >= COMPLETE_FRACTION * located.len() as f64 {
            break;
        }
        let patch = indexed(&located, &n);
        let b = true_basis(&apparent, ruler.constant_nm);
        let (rows, rhs) = design(&patch, &b, law, None);
        let Ok(fit) = spm_regression::least_squares(&rows, &rhs, &[false; 5 + FAST_TERMS]) else {
            break;
        };
        let drift = [fit.coefficients[3], fit.coefficients[4]];
        let mut fast = [0.0; FAST_TERMS];
        fast.copy_from_slice(&fit.coefficients[5..5 + FAST_TERMS]);
        let straightened: Vec<Atom> = located
            .iter()
            .map(|a| {
                let f = fast_axis_nm(&fast, a.u);
                let p = [
                    a.p[0] - drift[0] * a.t - f[0],
                    a.p[1] - drift[1] * a.t - f[1],
                ];
                Atom {
                    p,
                    feature: Feature {
                        position: CountPoint::from_counts(p[0], p[1]),
                        ..a.feature
                    },
                    ..*a
                }
            })
            .collect();
        let Ok((grown, basis)) = index(&straightened) else {
            break;
        };
        if grown.iter().flatten().count() <= reached {
            break;
        }
        (atoms, n, apparent, pre_drift, pre_fast) = (straightened, grown, basis, drift, fast);
    }
    let used = indexed(&atoms, &n);
    if used.len() < 12 {
        return Err(CorrectionError::Empty("indexed atoms (fewer than 12)"));
    }
    // A fit on a patch extrapolates wildly across the frame: the index must span it.
    if (used.len() as f64) < MIN_INDEXED_FRACTION * atoms.len() as f64 {
        return Err(CorrectionError::InvalidArgument(format!(
            "lattice ruler: only {} of {} atoms could be indexed from one another (the image is \
             too distorted, or not one lattice)",
            used.len(),
            atoms.len()
        )));
    }
    let b = true_basis(&apparent, ruler.constant_nm);
    let design = |tm: f64| design(&used, &b, law, Some(tm));
    let (rows, rhs) = design(1.0);
    let rigid: Vec<Vec<f64>> = rows.iter().map(|r| r[..3].to_vec()).collect();
    let before = spm_regression::least_squares(&rigid, &rhs, &[false; 3])
        .map_err(|e| CorrectionError::InvalidArgument(format!("lattice ruler: {e}")))?;
    let (from, to, per_decade) = (0.1_f64, 1e4_f64, 8_u32);
    let steps = ((to / from).log10() * f64::from(per_decade)).ceil() as usize;
    let mut best: Option<(f64, Vec<f64>, f64)> = None;
    for k in 0..=steps {
        let tm = from * 10f64.powf(k as f64 / f64::from(per_decade));
        let (rows, rhs) = design(tm);
        if let Ok(fit) = spm_regression::least_squares(&rows, &rhs, &[false; 7 + FAST_TERMS])
            && best.as_ref().is_none_or(|b| fit.residual_rms < b.2)
        {
            best = Some((tm, fit.coefficients, fit.residual_rms));
        }
    }
    let (since_move_s, c, residual_rms_nm) = best.ok_or_else(|| {
        CorrectionError::InvalidArgument(
            "lattice ruler: the atoms do not determine the approach creep and drift".into(),
        )
    })?;
    if residual_rms_nm > MAX_RESIDUAL_FRACTION * ruler.constant_nm {
        return Err(CorrectionError::InvalidArgument(format!(
            "lattice ruler: the atoms stay {residual_rms_nm:.3} nm RMS off the lattice after the \
             fit (more than {MAX_RESIDUAL_FRACTION} a): the image's distortion is not a function \
             of time alone"
        )));
    }
    // The fast-axis terms' largest displacement along a line, against the line's length.
    let fast: [f64; FAST_TERMS] = std::array::from_fn(|k| c[7 + k] + pre_fast[k]);
    let fast_nm = fast_axis_reach_nm(&fast);
    let line_nm = {
        let (x0, x1, _, _) = map.bounds_nm();
        x1 - x0
    };
    if fast_nm.is_nan() || fast_nm > MAX_FAST_AXIS_FRACTION * line_nm {
        return Err(CorrectionError::InvalidArgument(format!(
            "lattice ruler: the fit moves atoms by {fast_nm:.3} nm along the lines, more than \
             {MAX_FAST_AXIS_FRACTION} of their {line_nm:.3} nm: not one lattice, or a map far \
             off the image"
        )));
    }
    let mut middle_times = times_s.to_vec();
    let middle_s = spm_regression::median(&mut middle_times).unwrap_or(0.0);
    let mut estimate = RulerEstimate {
        amplitude_nm: [c[3], c[4]],
        since_move_s,
        drift_nm_per_s: [c[5] + pre_drift[0], c[6] + pre_drift[1]],
        fast_axis_nm: fast,
        reference_nm: [0.0; 2],
        atoms: atoms.len(),
        indexed: used.len(),
        before_rms_nm: before.residual_rms,
        residual_rms_nm,
        law: law.clone(),
    };
    estimate.reference_nm = estimate.error_at_nm(middle_s, 0.0);
    Ok(estimate)
}

#[cfg(test)]
pub(crate) mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// A HOPG-like surface: Gaussian atoms on a hexagonal lattice (a = 0.246 nm) rotated by
    /// `angle`.
    pub(crate) fn surface(x: f64, y: f64, angle: f64) -> f64 {
        let a = 0.246;
        let (s, c) = angle.sin_cos();
        let b1 = [a * c, a * s];
        let b2 = [
            a * (c * 0.5 - s * 0.75f64.sqrt()),
            a * (s * 0.5 + c * 0.75f64.sqrt()),
        ];
        let det = b1[0] * b2[1] - b1[1] * b2[0];
        let (k1, k2) = ((x * b2[1] - y * b2[0]) / det, (b1[0] * y - b1[1] * x) / det);
        let mut z = 0.0;
        for d1 in -1..=2 {
            for d2 in -1..=2 {
                let (n1, n2) = (k1.floor() + f64::from(d1), k2.floor() + f64::from(d2));
                let (px, py) = (n1 * b1[0] + n2 * b2[0], n1 * b1[1] + n2 * b2[1]);
                z += (-((x - px).powi(2) + (y - py).powi(2)) / (2.0 * 0.045f64.powi(2))).exp();
            }
        }
        z
    }

    fn hidden_error(
        law: &CreepLaw,
        amplitude_nm: [f64; 2],
        since_move_s: f64,
        drift_nm_per_s: [f64; 2],
    ) -> RulerEstimate {
        RulerEstimate {
            amplitude_nm,
            since_move_s,
            drift_nm_per_s,
            fast_axis_nm: [0.0; FAST_TERMS],
            reference_nm: [0.0; 2],
            atoms: 0,
            indexed: 0,
            before_rms_nm: 0.0,
            residual_rms_nm: 0.0,
            law: law.clone(),
        }
    }

    /// The place along the line of pixel `i` of a 129-pixel line (−½ … ½).
    fn along(i: usize) -> f64 {
        along_line((i % 129) as f64, 129)
    }

    /// RMS over the frame's pixels of `f(t, u)` (pixel time, place along the line), its mean (a
    /// rigid offset) removed, nm.
    fn spread(times: &[f64], f: &dyn Fn(f64, f64) -> [f64; 2]) -> f64 {
        let v: Vec<[f64; 2]> = times
            .iter()
            .enumerate()
            .map(|(i, &t)| f(t, along(i)))
            .collect();
        spread_of(&v)
    }

    /// What `estimate` leaves of `hidden`'s e over the frame's pixels, its mean removed, nm.
    fn left_of(times: &[f64], hidden: &RulerEstimate, estimate: &RulerEstimate) -> f64 {
        spread(times, &|t, u| {
            let (e, f) = (hidden.error_at_nm(t, u), estimate.error_at_nm(t, u));
            [e[0] - f[0], e[1] - f[1]]
        })
    }

    /// RMS length of displacements `v` about their mean (a rigid offset removed), nm.
    pub(crate) fn spread_of(v: &[[f64; 2]]) -> f64 {
        let m = [
            v.iter().map(|p| p[0]).sum::<f64>() / v.len() as f64,
            v.iter().map(|p| p[1]).sum::<f64>() / v.len() as f64,
        ];
        (v.iter()
            .map(|p| (p[0] - m[0]).powi(2) + (p[1] - m[1]).powi(2))
            .sum::<f64>()
            / v.len() as f64)
            .sqrt()
    }

    /// A 129² frame of a hexagonal lattice at 0.02 nm per pixel, lines of `line_s` trace and
    /// retrace, every pixel seen displaced by `hidden`'s e(t), with `extra(sample point)` added to
    /// the heights: heights, the file-alone map (the commanded grid) and the pixel times.
    fn strained_frame(
        hidden: &RulerEstimate,
        line_s: f64,
        extra: &dyn Fn(f64, f64) -> f64,
    ) -> (Vec<f64>, CoordinateMap, Vec<f64>) {
        let (n, step) = (129, 0.02);
        let dwell = line_s / n as f64;
        let mut times = vec![0.0; n * n];
        let mut heights = vec![0.0; n * n];
        let mut x = vec![0.0; n * n];
        let mut y = vec![0.0; n * n];
        for row in 0..n {
            for col in 0..n {
                let i = row * n + col;
                let t = 2.0 * line_s * row as f64 + (col as f64 + 0.5) * dwell;
                let p = [col as f64 * step, row as f64 * step];
                let e = hidden.error_at_nm(t, along(i));
                times[i] = t;
                x[i] = p[0];
                y[i] = p[1];
                let (sx, sy) = (p[0] - e[0], p[1] - e[1]);
                heights[i] = surface(sx, sy, 0.3) + extra(sx, sy);
            }
        }
        let map = CoordinateMap::new(n, n, x, YCoordinates::PerPixel(y)).unwrap();
        (heights, map, times)
    }

    /// A strongly strained frame: the approach creep of a long move seen from 0.3 s after it,
    /// most of it in the first lines, and a drift of 0.02–0.03 nm/s move the atoms by more than
    /// a tenth of the side. The index must span 90 % of the atoms, and the ruler take out 90 %
    /// of e.
    #[test]
    fn a_strongly_strained_frame_is_indexed_by_straightening_and_growing_again() {
        let law = CreepLaw::log_spaced(0.0055, 0.01, 1e4, 3).unwrap();
        let hidden = hidden_error(&law, [-25.0, 40.0], 0.3, [0.02, -0.03]);
        let (heights, map, times) = strained_frame(&hidden, 0.1, &|_, _| 0.0);
        let before = spread(&times, &|t, u| hidden.error_at_nm(t, u));
        assert!(before > 0.25, "the hidden e is {before} nm RMS");
        let estimate =
            estimate_from_lattice(&heights, &map, &times, &law, &LatticeRuler::hopg()).unwrap();
        let after = left_of(&times, &hidden, &estimate);
        assert!(
            after < 0.1 * before,
            "left of e: {before} nm → {after} nm; {estimate:?}"
        );
        assert!(
            estimate.indexed as f64 >= 0.9 * estimate.atoms as f64,
            "{estimate:?}"
        );
    }

    /// The fast axis's scale (2 % of the line), its quadratic and cubic, and a bow of the lines
    /// along y, hidden beside the approach creep and drift: what a line's own place along it
    /// explains, which a function of time alone cannot (a line takes no time). The ruler must
    /// take out 90 % of the whole, and find the scale to a tenth.
    #[test]
    fn the_lattice_finds_the_fast_axis_scale_and_nonlinearity() {
        let law = CreepLaw::log_spaced(0.0055, 0.01, 1e4, 3).unwrap();
        let mut hidden = hidden_error(&law, [-6.0, 4.0], 2.0, [0.002, -0.001]);
        hidden.fast_axis_nm = [0.05, 0.06, 0.12, 0.03, 0.05];
        let (heights, map, times) = strained_frame(&hidden, 0.1, &|_, _| 0.0);
        let fast = spread(&times, &|_, u| fast_axis_nm(&hidden.fast_axis_nm, u));
        assert!(fast > 0.015, "the hidden fast-axis part is {fast} nm RMS");
        let before = spread(&times, &|t, u| hidden.error_at_nm(t, u));
        let estimate =
            estimate_from_lattice(&heights, &map, &times, &law, &LatticeRuler::hopg()).unwrap();
        let after = left_of(&times, &hidden, &estimate);
        assert!(
            after < 0.1 * before && after < 0.2 * fast,
            "left of e: {before} nm → {after} nm (fast-axis part {fast} nm); {estimate:?}"
        );
        assert!(
            (estimate.fast_axis_nm[0] - 0.05).abs() < 0.005,
            "scale along the line {} nm, hidden 0.05 nm",
            estimate.fast_axis_nm[0]
        );
    }

    /// A 129² frame of a hexagonal lattice, corrected as a file alone is: every pixel seen
    /// displaced by a hidden e(t) (approach creep and drift, ≈ 8 % of the side over the
    /// frame), with a defect off the lattice where the frame's median time is. The ruler must
    /// take out 90 % of it, and refuse a frame whose lattice is not resolved.
    #[test]
    fn the_lattice_finds_a_hidden_approach_creep_and_drift() {
        let n = 129;
        let step = 0.02;
        let line_s = 0.1;
        let law = CreepLaw::log_spaced(0.0055, 0.01, 1e4, 3).unwrap();
        let hidden = hidden_error(&law, [-8.0, 5.0], 2.0, [0.003, -0.002]);
        // Defects off the lattice along the rows seen at the median time: growing the index
        // from one of them alone would reach no other atom.
        let defects = |sx: f64, sy: f64| -> f64 {
            (0..9)
                .map(|k| {
                    let (dx, dy) = (sx - 0.15 - 0.27 * f64::from(k), sy - 1.29);
                    2.0 * (-(dx * dx + dy * dy) / (2.0 * 0.04f64.powi(2))).exp()
                })
                .sum()
        };
        let (heights, map, times) = strained_frame(&hidden, line_s, &defects);
        let estimate =
            estimate_from_lattice(&heights, &map, &times, &law, &LatticeRuler::hopg()).unwrap();
        // What is left of e over the frame, its mean (a rigid offset) removed.
        let before = spread(&times, &|t, u| hidden.error_at_nm(t, u));
        let after = left_of(&times, &hidden, &estimate);
        assert!(
            after < 0.1 * before,
            "left of e: {before} nm → {after} nm; {estimate:?}"
        );
        assert!(estimate.indexed > 80, "{estimate:?}");
        // Two pixels per lattice constant: refused, naming the need.
        let coarse = CoordinateMap::new(
            n,
            n,
            (0..n * n).map(|i| (i % n) as f64 * 0.12).collect(),
            YCoordinates::PerPixel((0..n * n).map(|i| (i / n) as f64 * 0.12).collect()),
        )
        .unwrap();
        let refused = estimate_from_lattice(&heights, &coarse, &times, &law, &LatticeRuler::hopg())
            .unwrap_err()
            .to_string();
        assert!(refused.contains("pixels per lattice constant"), "{refused}");
        // Two grains (the upper half's lattice turned by 20°): no single lattice fits the
        // frame, so it is refused — either no index spans it, or the index the straightening
        // grew across the boundary leaves the atoms far off, or the fit bends the lines by
        // far more than a calibrated map can be off — and no fit extrapolates from one grain
        // across the other.
        let grains: Vec<f64> = (0..n * n)
            .map(|i| {
                let (px, py) = ((i % n) as f64 * step, (i / n) as f64 * step);
                surface(px, py, if i / n < n / 2 { 0.3 } else { 0.65 })
            })
            .collect();
        let refused = estimate_from_lattice(&grains, &map, &times, &law, &LatticeRuler::hopg())
            .unwrap_err()
            .to_string();
        assert!(
            refused.contains("could be indexed")
                || refused.contains("off the lattice")
                || refused.contains("along the lines"),
            "{refused}"
        );
    }
}
