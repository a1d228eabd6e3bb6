//! The lattice of a standard surveyed over one image: measured on the whole image and in
//! each cell of a `grid` × `grid` division of its scanned region, by this crate's extraction
//! and baseline fit (what `spmcal diagnose` reports); the survey `spmcal lattice` prints.

use crate::{
    ExtractOptions, FeatureObservation, FeatureSet, LatticeSpec, Options, diagnose_features,
    extract_features,
};
use serde::Serialize;
use spm_formats::{Channel, SpmFile};

/// Why a lattice survey cannot be made.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum SurveyError {
    /// The channel states no pixel size (features cannot be placed in the image).
    #[error("the channel states no pixel size")]
    NoPixelSize,
}

/// The lattice in one part of an image as `spmcal diagnose`'s baseline measures it
/// (spm-modelcheck: the cell-template localiser for Si 7×7, the plain one for atoms; a
/// lattice indexed and fitted with scales, obliquity, rotation and drift).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PartLattice {
    /// Scale along x: true over apparent lattice length, i.e. the image's true nm per
    /// nominal nm (K̄x/K; 1 = correct, 0.68 = the lattice looks 1/0.68 times too long).
    pub scale_x: f64,
    /// Scale along y, as `scale_x`.
    pub scale_y: f64,
    /// Obliquity, degrees (0 = orthogonal axes).
    pub obliquity_deg: f64,
    /// One-sigma uncertainty of `scale_x` (the fit's covariance scaled by its residual
    /// variance: the part's own localisation scatter over its extent).
    pub scale_x_sigma: f64,
    /// One-sigma uncertainty of `scale_y`.
    pub scale_y_sigma: f64,
    /// One-sigma uncertainty of `obliquity_deg`, degrees.
    pub obliquity_sigma_deg: f64,
    /// Features used.
    pub features: usize,
    /// Features of the part left out as not lattice sites (a cell whose fit left residuals
    /// above [`ROBUST_CELL_RESIDUAL_FACTOR`] times the typical cell's).
    pub features_left_out: usize,
}

/// The lattice measured in one cell of a grid over an image.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CellLattice {
    /// Cell column (0 = left).
    pub column: usize,
    /// Cell row (0 = top of the display).
    pub row: usize,
    /// The lattice found, or `None` when the cell holds too few features.
    pub lattice: Option<PartLattice>,
}

/// The part of an image that holds data: for each display row, the span of columns from its
/// first to its last finite pixel, and the first and last rows that hold any. A corrected
/// image is a parallelogram (or a curved quadrilateral) inside its bounding box, with NaN
/// beyond the raster; the grid of [`survey_channel`] divides this scanned region, not the
/// box, so that every cell is a part of the field the raster covered (a cell of the box at a
/// sheared image's side is half NaN and holds too few features to measure).
#[derive(Debug, Clone, PartialEq)]
struct ScannedRegion {
    /// Per display row, the first and one-past-the-last column of its data (`None`: no data).
    spans: Vec<Option<(usize, usize)>>,
    /// The first and one-past-the-last row with data.
    rows: Option<(usize, usize)>,
}

impl ScannedRegion {
    /// The region of `data` (display order, `nx` × `ny`).
    fn of(data: &[f64], nx: usize, ny: usize) -> Self {
        let spans: Vec<Option<(usize, usize)>> = (0..ny)
            .map(|r| {
                let line = data.get(r * nx..(r + 1) * nx)?;
                let first = line.iter().position(|v| v.is_finite())?;
                let last = line.iter().rposition(|v| v.is_finite())?;
                Some((first, last + 1))
            })
            .collect();
        let rows = spans
            .iter()
            .position(Option::is_some)
            .zip(spans.iter().rposition(Option::is_some))
            .map(|(a, b)| (a, b + 1));
        Self { spans, rows }
    }

    /// The cell (column, row) of a `grid` × `grid` division of the region that holds the
    /// place (`column`, `row`) in display pixels: rows divide the rows with data, and
    /// within its row a place's column is its fraction of that row's span. `None` outside.
    fn cell_of(&self, column: f64, row: f64, grid: usize) -> Option<(usize, usize)> {
        let (r0, r1) = self.rows?;
        if !(row >= r0 as f64 && row < r1 as f64) {
            return None;
        }
        let (c0, c1) = (*self.spans.get(row as usize)?)?;
        if !(column >= c0 as f64 && column < c1 as f64) {
            return None;
        }
        let fraction = |v: f64, a: usize, b: usize| (v - a as f64) / (b - a) as f64;
        let index = |f: f64| ((f * grid as f64) as usize).min(grid - 1);
        Some((
            index(fraction(column, c0, c1)),
            index(fraction(row, r0, r1)),
        ))
    }
}

/// Fewest features a part's lattice is fitted to (its fit then states its own uncertainty: on
/// Si_7x7_028 and 032 corrected, side cells of 10–11 corner holes read ±0.2–0.6 % and
/// ±0.2–0.5°, one of six ±4 % and ±3°).
pub const MIN_PART_FEATURES: usize = 9;

/// A cell of [`survey_channel`]'s grid whose fit leaves an RMS residual above this many
/// times the median cell's holds features that are not lattice sites. On Si_7x7_032 corrected,
/// the cells' residuals are 23–44 pm, and two odd cells' 210 and 224 pm.
pub const ROBUST_CELL_RESIDUAL_FACTOR: f64 = 3.0;

/// Measures the lattice of `spec` on `channel` of `file`, whole and in a `grid` × `grid`
/// partition of its scanned region, by this crate's extraction and baseline fit (what
/// `spmcal diagnose` reports); pixels without data (a corrected image's corners) are left
/// out by the extraction. Returns the whole image's lattice and the cells, row by row (a
/// lattice is `None` where the part holds fewer than [`MIN_PART_FEATURES`] features or the
/// fit finds none; all are `None` when the extraction fails). A `grid` of 0 is taken as 1.
///
/// # Errors
/// [`SurveyError::NoPixelSize`] when the channel states no pixel size.
pub fn survey_channel(
    file: &SpmFile,
    channel: &Channel,
    spec: &LatticeSpec,
    grid: usize,
) -> Result<(Option<PartLattice>, Vec<CellLattice>), SurveyError> {
    let (Some(pixel_x_nm), Some(pixel_y_nm)) = (channel.pixel_x_nm(), channel.pixel_y_nm()) else {
        return Err(SurveyError::NoPixelSize);
    };
    let (nx, ny) = (channel.nx(), channel.ny());
    let extract = ExtractOptions {
        channel: Some(channel.name().to_owned()),
        ..ExtractOptions::default()
    };
    let options = Options {
        effects: Vec::new(),
        max_findings: 0,
        ..Options::default()
    };
    // The features are extracted once, on the whole image: a cell's own spectrum holds a
    // few lattice constants only, too few for the cell-template localiser's lattice and
    // template (Si 7×7 at 13.8 pixels per cell: 8 of 16 cells found that way, 14 with the
    // whole image's features). A part is then the features whose centre lies in it.
    let whole_file = SpmFile {
        channels: vec![channel.clone()],
        ..file.clone()
    };
    let all = extract_features(&[(whole_file, None)], spec, &extract).ok();
    let region = ScannedRegion::of(channel.data(), nx, ny);
    let grid = grid.max(1);
    let (whole, cells) = match all {
        Some(all) => {
            let fit = |features| fit_part(&all, features, spec, &options);
            // A feature's place in display pixels (column from the left, row from the top;
            // pixel c covers [c, c + 1)). Feature coordinates are nm from the frame centre,
            // y up.
            let place = |f: &FeatureObservation| {
                (
                    f.x_nm / pixel_x_nm + 0.5 * nx as f64,
                    0.5 * ny as f64 - f.y_nm / pixel_y_nm,
                )
            };
            let in_cell = |c: (usize, usize)| -> Vec<FeatureObservation> {
                all.features
                    .iter()
                    .filter(|f| {
                        let (column, row) = place(f);
                        region.cell_of(column, row, grid) == Some(c)
                    })
                    .cloned()
                    .collect()
            };
            let whole = fit(all.features.clone()).map(|(l, _)| l);
            (whole, grid_cells(grid, &in_cell, &fit))
        }
        None => (
            None,
            (0..grid * grid)
                .map(|i| CellLattice {
                    column: i % grid,
                    row: i / grid,
                    lattice: None,
                })
                .collect(),
        ),
    };
    Ok((whole, cells))
}

/// The lattice of a set of features (`all`'s frames), with the fit's residual RMS (pm);
/// `None` below [`MIN_PART_FEATURES`] or when the fit finds no lattice.
fn fit_part(
    all: &FeatureSet,
    features: Vec<FeatureObservation>,
    spec: &LatticeSpec,
    options: &Options,
) -> Option<(PartLattice, f64)> {
    if features.len() < MIN_PART_FEATURES {
        return None;
    }
    let set = FeatureSet {
        features,
        frames: all.frames.clone(),
        warnings: all.warnings.clone(),
    };
    let d = diagnose_features(&set, spec, options).ok()?;
    let p = |key: &str| d.baseline.parameters.get(key).copied();
    let (x, y, o) = (p("scale_x")?, p("scale_y")?, p("obliquity_deg")?);
    let lattice = PartLattice {
        scale_x: x.value,
        scale_y: y.value,
        obliquity_deg: o.value,
        scale_x_sigma: x.sigma,
        scale_y_sigma: y.sigma,
        obliquity_sigma_deg: o.sigma,
        features: set.features.len(),
        features_left_out: 0,
    };
    Some((lattice, d.baseline.rms_pm))
}

/// The cells of a `grid` × `grid` division, row by row: each cell's features (`in_cell`)
/// fitted (`fit`); a cell whose fit leaves residuals far above the typical cell's holds
/// features that are not lattice sites (a defect's, or a hole misplaced beside one), and they
/// are left out ([`leave_out_non_sites`], above [`ROBUST_CELL_RESIDUAL_FACTOR`] × the median
/// cell's residual).
fn grid_cells(
    grid: usize,
    in_cell: &dyn Fn((usize, usize)) -> Vec<FeatureObservation>,
    fit: &dyn Fn(Vec<FeatureObservation>) -> Option<(PartLattice, f64)>,
) -> Vec<CellLattice> {
    let places: Vec<(usize, usize)> = (0..grid * grid).map(|i| (i % grid, i / grid)).collect();
    let features: Vec<Vec<FeatureObservation>> = places.iter().map(|&c| in_cell(c)).collect();
    let mut fitted: Vec<Option<(PartLattice, f64)>> =
        features.iter().map(|f| fit(f.clone())).collect();
    let mut residuals: Vec<f64> = fitted.iter().flatten().map(|(_, rms)| *rms).collect();
    if let Some(typical) = spm_regression::median(&mut residuals) {
        let bound = ROBUST_CELL_RESIDUAL_FACTOR * typical;
        for (slot, cell) in fitted.iter_mut().zip(features) {
            if let Some(first) = *slot
                && first.1 > bound
            {
                let (lattice, rms, left_out) =
                    leave_out_non_sites(cell, first, bound, MIN_PART_FEATURES, fit);
                *slot = Some((
                    PartLattice {
                        features_left_out: left_out,
                        ..lattice
                    },
                    rms,
                ));
            }
        }
    }
    places
        .iter()
        .zip(fitted)
        .map(|(&(column, row), f)| CellLattice {
            column,
            row,
            lattice: f.map(|(l, _)| l),
        })
        .collect()
}

/// Leaves features out of a part whose fit `first` (its result and residual RMS) is above
/// `bound`: one at a time, each time the one whose removal lowers the residual most, while
/// the part is above the bound, the removal lowers its residual by a fifth at least, and
/// more than `min` features remain. Returns the last fit, its residual and how many
/// features were left out.
fn leave_out_non_sites<T: Clone, L: Copy>(
    mut features: Vec<T>,
    first: (L, f64),
    bound: f64,
    min: usize,
    fit: &dyn Fn(Vec<T>) -> Option<(L, f64)>,
) -> (L, f64, usize) {
    let (mut best, mut rms) = first;
    let mut left_out = 0;
    while rms > bound && features.len() > min {
        let trial = (0..features.len())
            .filter_map(|i| {
                let mut rest = features.clone();
                rest.remove(i);
                fit(rest).map(|(l, r)| (i, l, r))
            })
            .min_by(|p, q| p.2.total_cmp(&q.2));
        match trial {
            Some((i, l, r)) if r < 0.8 * rms => {
                features.remove(i);
                best = l;
                rms = r;
                left_out += 1;
            }
            _ => break,
        }
    }
    (best, rms, left_out)
}

#[cfg(test)]
mod tests {
    use super::{ScannedRegion, leave_out_non_sites};

    /// A 12 × 8 image whose rows hold data from column `row` to column `row + 8` (a
    /// parallelogram sheared by one column per row, NaN beside it, as a corrected image is).
    fn sheared() -> ScannedRegion {
        let (nx, ny) = (16, 8);
        let data: Vec<f64> = (0..nx * ny)
            .map(|i| {
                let (r, c) = (i / nx, i % nx);
                if (r..r + 8).contains(&c) {
                    1.0
                } else {
                    f64::NAN
                }
            })
            .collect();
        ScannedRegion::of(&data, nx, ny)
    }

    #[track_caller]
    fn check(
        region: &ScannedRegion,
        place: (f64, f64),
        grid: usize,
        expected: Option<(usize, usize)>,
    ) {
        assert_eq!(
            region.cell_of(place.0, place.1, grid),
            expected,
            "place {place:?}"
        );
    }

    #[test]
    fn the_grid_divides_each_row_of_the_scanned_region_not_the_box() {
        let region = sheared();
        // Row 0 spans columns 0..8, row 7 spans 7..15: a cell's columns follow the shear.
        check(&region, (0.5, 0.5), 2, Some((0, 0)));
        check(&region, (7.5, 0.5), 2, Some((1, 0)));
        check(&region, (7.5, 7.5), 2, Some((0, 1)));
        check(&region, (14.9, 7.5), 2, Some((1, 1)));
        // In the box's left half but right of the sheared row's middle.
        check(&region, (7.2, 6.5), 2, Some((0, 1)));
        check(&region, (11.5, 6.5), 2, Some((1, 1)));
        // NaN beside the data, and beyond the image.
        check(&region, (0.5, 7.5), 2, None);
        check(&region, (15.5, 0.5), 2, None);
        check(&region, (3.0, 8.5), 2, None);
        check(&region, (3.0, -0.5), 2, None);
    }

    #[test]
    fn an_image_without_nan_is_divided_as_its_box() {
        let region = ScannedRegion::of(&[0.0; 8 * 4], 8, 4);
        for (place, expected) in [
            ((0.0, 0.0), (0, 0)),
            ((1.99, 0.5), (0, 0)),
            ((2.0, 0.5), (1, 0)),
            ((7.99, 3.99), (3, 3)),
            ((4.5, 2.0), (2, 2)),
        ] {
            check(&region, place, 4, Some(expected));
        }
        assert_eq!(
            ScannedRegion::of(&[f64::NAN; 4], 2, 2).cell_of(0.5, 0.5, 2),
            None
        );
    }

    /// `leave_out_non_sites` on values whose "fit" is their mean and RMS deviation: the
    /// values far from the rest are left out one by one, the part's residual then within
    /// the bound; a clean part and one at its minimum size are left as they are.
    #[test]
    fn features_that_are_not_lattice_sites_are_left_out_of_a_part() {
        let fit = |v: Vec<f64>| -> Option<(f64, f64)> {
            let mean = v.iter().sum::<f64>() / v.len() as f64;
            let rms = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / v.len() as f64).sqrt();
            Some((mean, rms))
        };
        let check = |values: &[f64], min: usize, expected_left_out: usize, expected_mean: f64| {
            let first = fit(values.to_vec()).unwrap();
            let (mean, rms, left_out) = leave_out_non_sites(values.to_vec(), first, 0.5, min, &fit);
            assert_eq!(left_out, expected_left_out, "{values:?}");
            assert!((mean - expected_mean).abs() < 1e-9, "{values:?}: {mean}");
            assert!(left_out == 0 || rms <= 0.5, "{values:?}: rms {rms}");
        };
        let clean = [0.1, -0.2, 0.3, 0.0, -0.1, 0.2, -0.3, 0.0];
        check(&clean, 4, 0, 0.0);
        let mut one = clean.to_vec();
        one.push(9.0);
        check(&one, 4, 1, 0.0);
        let mut two = clean.to_vec();
        two.extend([7.0, -6.0]);
        check(&two, 4, 2, 0.0);
        // At its minimum size nothing is left out.
        check(&[0.0, 0.1, 9.0], 3, 0, 9.1 / 3.0);
    }
}
