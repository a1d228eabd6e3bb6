//! Indexing that survives large distortions (issue 29 item 3): grown from the least
//! distorted part of a group outwards, the distortion model and the indexing iterated.
//!
//! The neighbour walk indexes a step by rounding the step in units of *one* basis for the
//! whole group, and the structure-factor registration by one phase: both slip by a site
//! where the local lattice in the image departs from that basis by a sizeable fraction of a
//! cell — the ends of a sinusoidally driven fast axis (stretched up to 1/cos β in the
//! image), the edges of a cubic of several lattice constants. The site of a feature is a
//! smooth function of its commanded position, (i, j) = F(ξx, ξy), whatever the scanner
//! does: F is fitted (two total-degree polynomials, spm-regression's least squares) to the
//! sites the walk gave in the central square |ξ| ≤ 0.4, where every odd distortion of the
//! fast axis and every frame-edge distortion is smallest, and every feature within a
//! radius growing by 0.1 is then indexed as round(F) when F lies within 0.3 of a site; F is
//! refitted on those and its degree raised (3 → 5, 7 once everything is in) as the region
//! grows.

use spm_regression::{FitOptions, Observations, Polynomial2};

/// The central square the growth starts from, in half-sizes.
const SEED_RADIUS: f64 = 0.4;
/// A feature is on a site when F lies within this of it (both indices) while growing.
const TOLERANCE: f64 = 0.3;
/// The same for the final assignment on the converged map, which follows the atoms to a
/// few pm: off-lattice features (adsorbates, noise peaks) fall within 0.3 of a site in
/// a third of cases (0.6²), within 0.2 in a sixth.
const FINAL_TOLERANCE: f64 = 0.2;
/// The grown sites replace the walk's only where F departs from an affine map by more
/// than this (cells) somewhere in the group: below it one basis or one phase is within
/// half a cell everywhere, and the walk and the phase (0.3-tolerant) stand.
const NONLINEAR_CELLS: f64 = 0.5;

/// The site map F: the (i, j) surfaces over (ξx, ξy).
type SiteMap = [Polynomial2; 2];

/// Chebyshev radius of a normalised position.
fn radius(xi: [f64; 2]) -> f64 {
    xi[0].abs().max(xi[1].abs())
}

/// The polynomial degree of F for a region of radius `r` (half-sizes).
fn degree_for(r: f64) -> u32 {
    if r <= 0.55 {
        3
    } else if r <= 1.05 {
        5
    } else {
        7
    }
}

/// F fitted to the indexed features, at `degree` or the highest lower degree the points
/// support (a surface needs three points per term here).
fn fit_map(xi: &[[f64; 2]], sites: &[Option<[i64; 2]>], degree: u32) -> Option<SiteMap> {
    let (mut x, mut y, mut i, mut j) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for (p, s) in xi.iter().zip(sites) {
        if let Some(s) = s {
            x.push(p[0]);
            y.push(p[1]);
            i.push(s[0] as f64);
            j.push(s[1] as f64);
        }
    }
    let options = FitOptions::default();
    (1..=degree).rev().find_map(|d| {
        if x.len() < 3 * spm_regression::n_terms(d) {
            return None;
        }
        let fi = spm_regression::fit(&Observations::new(&x, &y, &i), d, &options).ok()?;
        let fj = spm_regression::fit(&Observations::new(&x, &y, &j), d, &options).ok()?;
        Some([fi.surface, fj.surface])
    })
}

/// round(F(ξ)) for every feature within `r` whose F lies within the tolerance of a site.
fn assign(map: &SiteMap, xi: &[[f64; 2]], r: f64, tolerance: f64) -> Vec<Option<[i64; 2]>> {
    xi.iter()
        .map(|&p| {
            if radius(p) > r {
                return None;
            }
            let [fi, fj] = Polynomial2::evaluate_each([&map[0], &map[1]], p[0], p[1]);
            let (ri, rj) = (fi.round(), fj.round());
            ((fi - ri).abs() < tolerance && (fj - rj).abs() < tolerance)
                .then_some([ri as i64, rj as i64])
        })
        .collect()
}

/// How many indexed features a smooth site map keeps on their sites: F fitted to `sites` at
/// `degree`, the features whose F lies within [`FINAL_TOLERANCE`] of their own site.
fn on_site(xi: &[[f64; 2]], sites: &[Option<[i64; 2]>], degree: u32) -> Option<usize> {
    let map = fit_map(xi, sites, degree)?;
    Some(
        xi.iter()
            .zip(sites)
            .filter(|(p, s)| {
                s.is_some_and(|s| {
                    let [fi, fj] = Polynomial2::evaluate_each([&map[0], &map[1]], p[0], p[1]);
                    (fi - s[0] as f64).abs() < FINAL_TOLERANCE
                        && (fj - s[1] as f64).abs() < FINAL_TOLERANCE
                })
            })
            .count(),
    )
}

/// The largest departure (cells) of F from its best affine fit over the features.
fn nonlinear_departure(map: &SiteMap, xi: &[[f64; 2]]) -> f64 {
    let x: Vec<f64> = xi.iter().map(|p| p[0]).collect();
    let y: Vec<f64> = xi.iter().map(|p| p[1]).collect();
    let options = FitOptions::default();
    let mut worst = 0.0_f64;
    for surface in map {
        let f: Vec<f64> = xi.iter().map(|p| surface.evaluate(p[0], p[1])).collect();
        let Ok(affine) = spm_regression::fit(&Observations::new(&x, &y, &f), 1, &options) else {
            return f64::INFINITY;
        };
        for (p, v) in xi.iter().zip(&f) {
            worst = worst.max((v - affine.surface.evaluate(p[0], p[1])).abs());
        }
    }
    worst
}

/// The group's sites regrown from its centre (`local`: the walk's or the phase's, whose
/// central sites seed the growth and fix the index convention), or `None` when the group
/// is too small or F is nearly affine (then `local` stands). `pts` in nominal nm from the
/// frame centre, `half_nm` the frame's half-sizes.
pub(crate) fn grow_from_centre(
    pts: &[[f64; 2]],
    local: &[Option<[i64; 2]>],
    half_nm: [f64; 2],
) -> Option<Vec<Option<[i64; 2]>>> {
    if !(half_nm[0] > 0.0 && half_nm[1] > 0.0) {
        return None;
    }
    let xi: Vec<[f64; 2]> = pts
        .iter()
        .map(|p| [p[0] / half_nm[0], p[1] / half_nm[1]])
        .collect();
    let mut sites: Vec<Option<[i64; 2]>> = local
        .iter()
        .zip(&xi)
        .map(|(s, p)| s.filter(|_| radius(*p) <= SEED_RADIUS))
        .collect();
    // The seed re-indexed on its own affine map twice (a slipped or off-lattice seed
    // feature — an adsorbate the walk stepped through — is dropped), then grown by 0.1
    // half-sizes, then twice over everything (features beyond the nominal frame and the
    // refit with all).
    for _ in 0..2 {
        let affine = fit_map(&xi, &sites, 1)?;
        sites = assign(&affine, &xi, SEED_RADIUS, TOLERANCE);
    }
    let mut map = fit_map(&xi, &sites, degree_for(SEED_RADIUS))?;
    let steps = [
        0.4,
        0.5,
        0.6,
        0.7,
        0.8,
        0.9,
        1.0,
        f64::INFINITY,
        f64::INFINITY,
    ];
    for r in steps {
        sites = assign(&map, &xi, r, TOLERANCE);
        map = fit_map(&xi, &sites, degree_for(r))?;
    }
    sites = assign(&map, &xi, f64::INFINITY, FINAL_TOLERANCE);
    if nonlinear_departure(&map, &xi) <= NONLINEAR_CELLS {
        return None;
    }
    // By evidence: the grown sites replace the walk's only when a smooth map of the same
    // degree, fitted to each, keeps more features on their sites (within the final
    // tolerance). A walk that slipped a site leaves those features a cell off any smooth map;
    // on a real frame whose map the growth cannot follow (a step, a superstructure, the
    // terrace's drift) the walk keeps more (the HOPG terrace's right half: the grown sites
    // kept 427 features, the walk's 618, and `spmcal lattice` found no lattice with them).
    let degree = degree_for(f64::INFINITY);
    if let (Some(walked), Some(grown)) = (on_site(&xi, local, degree), on_site(&xi, &sites, degree))
        && walked >= grown
    {
        return None;
    }
    // Where the smooth map places no feature but F is nearest the walk's site (a feature
    // pulled off its site by a neighbour, a region the map follows less well), the walk's
    // site stands; where F is nearest another site, the walk slipped and the feature is
    // left out.
    Some(
        sites
            .iter()
            .zip(local)
            .zip(&xi)
            .map(|((grown, walked), p)| {
                grown.or_else(|| {
                    let [fi, fj] = Polynomial2::evaluate_each([&map[0], &map[1]], p[0], p[1]);
                    walked.filter(|w| w[0] == fi.round() as i64 && w[1] == fj.round() as i64)
                })
            })
            .collect(),
    )
}
