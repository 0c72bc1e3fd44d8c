//! The generated sets the single fit is swept on (`cargo bench --bench sweep`): clouds of random
//! superquadrics with known truth, each set a different way of being hard.

use super::{CloudRecipe, GroundTruthCloud, OutlierSpread, Rng, ground_truth_cloud};
use crate::model::deform::{GlobalDeformation, MAX_TAPER};
use crate::model::superquadric::SuperquadricParams;

/// A generated set of clouds ([`set_cloud`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SweepSet {
    /// Every outlier fraction, noise level, view and spread interleaved ([`sweep_cloud`]).
    Mixed,
    /// 40 % outliers in a Gaussian as wide as the object about it, 60 % of the surface seen,
    /// noise 2 %.
    Outliers,
    /// 20 % outliers in a Gaussian about the object, 40 % of the surface seen, noise 1 %.
    Partial,
    /// Tapered (and, every other cloud, bent) truths, 60 % seen, noise 1 %, 10 % outliers.
    Deformed,
}

impl SweepSet {
    /// Every set, in the order the bench reports them.
    pub const ALL: [SweepSet; 4] = [Self::Mixed, Self::Outliers, Self::Partial, Self::Deformed];

    /// The set's name on the command line (`--set NAME`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Mixed => "mixed",
            Self::Outliers => "outliers",
            Self::Partial => "partial",
            Self::Deformed => "deformed",
        }
    }

    /// The set named `name`.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|s| s.name() == name)
    }
}

/// Cloud `i` of the mixed set the fitter's defaults are swept on, with its recipe: 2000 surface
/// points; four outlier fractions (0, 10, 20 and 40 %), four noise levels (0, 1, 3 and 5 % of the
/// largest semi-axis), three views (the whole surface, 60 % and 40 % of it) and both outlier
/// spreads, interleaved so that any 32 consecutive clouds meet every outlier fraction with every
/// noise level and spread, and any 12 every outlier fraction with every view; exponents over
/// [0.1, 1.9].
pub fn sweep_cloud(i: u64) -> (CloudRecipe, GroundTruthCloud) {
    const OUTLIERS: [f64; 4] = [0.0, 0.1, 0.2, 0.4];
    const NOISE: [f64; 4] = [0.0, 0.01, 0.03, 0.05];
    const KEPT: [f64; 3] = [1.0, 0.6, 0.4];
    let recipe = CloudRecipe {
        surface_points: 2000,
        kept: KEPT[(i % 3) as usize],
        noise: NOISE[((i / 4) % 4) as usize],
        outliers: OUTLIERS[(i % 4) as usize],
        outlier_spread: if (i / 16).is_multiple_of(2) {
            OutlierSpread::Uniform
        } else {
            OutlierSpread::Gaussian
        },
        epsilon: [0.1, 1.9],
        deformation: GlobalDeformation::default(),
    };
    (recipe, ground_truth_cloud(1000 + i, &recipe))
}

/// Cloud `i` (from 1) of `set`, with its recipe. The sets other than [`SweepSet::Mixed`] cycle
/// through 500, 1000 and 2000 surface points, draw exponents over [0.1, 1.9], and are seeded
/// apart from each other and from the tests' clouds.
pub fn set_cloud(set: SweepSet, i: u64) -> (CloudRecipe, GroundTruthCloud) {
    let base = CloudRecipe {
        surface_points: [500, 1000, 2000][(i % 3) as usize],
        outlier_spread: OutlierSpread::Gaussian,
        epsilon: [0.1, 1.9],
        ..CloudRecipe::default()
    };
    let (recipe, seed) = match set {
        SweepSet::Mixed => return sweep_cloud(i),
        SweepSet::Outliers => (
            CloudRecipe {
                kept: 0.6,
                noise: 0.02,
                outliers: 0.4,
                ..base
            },
            20_000 + i,
        ),
        SweepSet::Partial => (
            CloudRecipe {
                kept: 0.4,
                noise: 0.01,
                outliers: 0.2,
                ..base
            },
            30_000 + i,
        ),
        SweepSet::Deformed => (
            CloudRecipe {
                kept: 0.6,
                noise: 0.01,
                outliers: 0.1,
                deformation: deformation(i),
                ..base
            },
            40_000 + i,
        ),
    };
    let cloud = ground_truth_cloud(seed, &recipe);
    // The deformation is drawn before the shape is known: clamp it to what the shape allows.
    let shape: &SuperquadricParams = &cloud.truth.shape;
    let allowed = recipe.deformation.clamped(shape.semi_axes());
    if allowed == recipe.deformation {
        return (recipe, cloud);
    }
    let recipe = CloudRecipe {
        deformation: allowed,
        ..recipe
    };
    (recipe, ground_truth_cloud(seed, &recipe))
}

/// The tapering (and, for even `i`, bending) of [`SweepSet::Deformed`]'s cloud `i`: each taper
/// uniform in ±0.8 of [`MAX_TAPER`], each bend in ±1.5.
fn deformation(i: u64) -> GlobalDeformation {
    let mut rng = Rng::new(90_000 + i);
    let taper = [(); 2].map(|_| rng.range(-0.8, 0.8) * MAX_TAPER);
    let bend = [(); 2].map(|_| rng.range(-1.5, 1.5));
    GlobalDeformation {
        taper,
        bend: if i.is_multiple_of(2) { bend } else { [0.0; 2] },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_set_follows_its_recipe() {
        for set in SweepSet::ALL {
            assert_eq!(SweepSet::from_name(set.name()), Some(set));
            for i in 1..=3 {
                let (r, c) = set_cloud(set, i);
                assert_eq!(c.points.len() - c.outliers, r.surface_points);
                assert_eq!(c.deformation, r.deformation);
                assert!(c.points.iter().all(|p| p.is_finite()));
                let expected = r.outliers / (1.0 - r.outliers) * r.surface_points as f64;
                assert!((c.outliers as f64 - expected).abs() <= 1.0);
            }
        }
        let (r, _) = set_cloud(SweepSet::Deformed, 2);
        assert!(r.deformation.bend != [0.0; 2] && r.deformation.taper != [0.0; 2]);
        assert_eq!(set_cloud(SweepSet::Mixed, 5), sweep_cloud(5));
    }
}
