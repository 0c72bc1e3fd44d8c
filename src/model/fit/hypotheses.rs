//! The states a fit starts from and the candidates it tries: the moments frame with each of its
//! axes as the model's z ([`initial_hypotheses`]; of the points that lie densely on a surface
//! too, `surface_starts`), and a fitted superquadric's similar shapes
//! (axis turns with swapped exponents, cross-section duals: [`similarity_candidates`],
//! [`cross_section_dual`]).

use super::context::Context;
use super::options::{FitOptions, Initialization};
use crate::model::init::{InitialPose, Normalization, initial_pose};
use crate::model::superquadric::SuperquadricParams;
use glam::DVec3;
use std::f64::consts::SQRT_2;

/// How far ε2 must be from 1 (an elliptic cross-section, its own dual) before
/// [`cross_section_dual`] offers a dual.
pub const DUAL_EPSILON_GAP: f64 = 0.5;

/// The cross-section dual of a fitted pose: the model turned 45° about its z axis, ε2 → 2 − ε2,
/// and both section semi-axes set to their mean times √2 (a square section's dual diamond reaches
/// its corners) or ÷ √2 (a diamond's dual square is inscribed). `None` when ε2 is within
/// [`DUAL_EPSILON_GAP`] of 1, where the section is nearly elliptic and turning it changes little.
pub fn cross_section_dual(pose: &InitialPose) -> Option<InitialPose> {
    let q = pose.shape;
    if (q.e2 - 1.0).abs() <= DUAL_EPSILON_GAP {
        return None;
    }
    Some(dual_about_z(
        pose,
        if q.e2 < 1.0 { SQRT_2 } else { 1.0 / SQRT_2 },
    ))
}

/// The pose with its axes permuted cyclically `turns` times ((x, y, z) → (y, z, x) for one), so
/// that another axis is the model's z, with the same semi-axes along the same world directions.
/// With `swap`, ε1 and ε2 trade places (EMS's axis-mismatch candidate: exact for ε1 = ε2 = 1,
/// and the nearest superquadric of the new frame when both exponents are alike).
pub(super) fn turned_axes(pose: &InitialPose, turns: usize, swap: bool) -> InitialPose {
    let m = glam::DMat3::from_quat(pose.rotation);
    let semi = pose.shape.semi_axes().to_array();
    let (cx, cy, cz) = (turns % 3, (turns + 1) % 3, (turns + 2) % 3);
    let frame = glam::DMat3::from_cols(m.col(cx), m.col(cy), m.col(cz));
    let a = semi[cx].max(semi[cy]).max(semi[cz]).max(f64::MIN_POSITIVE);
    let q = pose.shape;
    let (e1, e2) = if swap { (q.e2, q.e1) } else { (q.e1, q.e2) };
    InitialPose {
        translation: pose.translation,
        rotation: glam::DQuat::from_mat3(&frame).normalize(),
        shape: SuperquadricParams {
            a,
            a1: semi[cx] / a,
            a2: semi[cy] / a,
            a3: semi[cz] / a,
            e1,
            e2,
        },
    }
}

/// Bounds on the ratio of two semi-axes for [`similarity_candidates`] to offer the cross-section
/// dual about the third axis (EMS's: a square-ish section only).
pub const DUAL_AXES_RATIO: (f64, f64) = (0.6, 1.4);

/// The similarity candidates of a fitted pose (EMS's similarity switching, Liu et al. 2022): the
/// two other axes as the model's z axis with ε1 and ε2 swapped, then for each axis whose two
/// perpendicular semi-axes are within [`DUAL_AXES_RATIO`] of each other, that axis as z and the
/// cross-section dual about it (turned 45°, ε2 → 2 − ε2, the section rescaled as in
/// [`cross_section_dual`]). Each is a different local minimum near the same surface.
pub fn similarity_candidates(pose: &InitialPose) -> Vec<InitialPose> {
    let mut candidates = vec![turned_axes(pose, 1, true), turned_axes(pose, 2, true)];
    for turns in 0..3 {
        let along = turned_axes(pose, turns, turns != 0);
        let s = along.shape.semi_axes();
        let ratio = s.x / s.y;
        if ratio > DUAL_AXES_RATIO.0 && ratio < DUAL_AXES_RATIO.1 {
            // The section's scale goes linearly in ε2 from √2 (a square's dual diamond reaches its
            // corners) through 1 (a circle is its own dual) to 1/√2 (a diamond's dual square is
            // inscribed), as EMS scales its candidates.
            let e2 = along.shape.e2;
            let scale = if e2 <= 1.0 {
                (1.0 - SQRT_2) * e2 + SQRT_2
            } else {
                (0.5 * SQRT_2 - 1.0) * e2 + 2.0 - 0.5 * SQRT_2
            };
            candidates.push(dual_about_z(&along, scale));
        }
    }
    candidates
}

/// The pose turned 45° about its z axis with ε2 → 2 − ε2 and both section semi-axes set to their
/// mean times `scale`.
fn dual_about_z(pose: &InitialPose, scale: f64) -> InitialPose {
    let q = pose.shape;
    let section = 0.5 * (q.a1 + q.a2) * scale;
    let rotation =
        (pose.rotation * glam::DQuat::from_rotation_z(std::f64::consts::FRAC_PI_4)).normalize();
    let shape = SuperquadricParams {
        a1: section,
        a2: section,
        e2: 2.0 - q.e2,
        ..q
    };
    InitialPose {
        translation: pose.translation,
        rotation,
        shape: shape.normalized(),
    }
}

/// The initial states a fit of `points` with `opts` tries (data frame): the three axis
/// hypotheses of the moments frame, or the one explicit pose.
pub fn initial_hypotheses(points: &[DVec3], opts: &FitOptions) -> Vec<InitialPose> {
    let norm = Normalization::of(points);
    if !(norm.scale > 0.0) {
        return match opts.init {
            Initialization::Moments => axis_hypotheses(&initial_pose(points)).to_vec(),
            Initialization::Explicit(pose) => vec![pose],
        };
    }
    let unit: Vec<DVec3> = points.iter().map(|p| norm.unit_point(*p)).collect();
    unit_hypotheses(&unit, &norm, opts)
        .iter()
        .map(|h| norm.pose_from_unit(h))
        .collect()
}

/// [`initial_hypotheses`] of a fit's context, in its unit frame: the moments are taken there
/// (squared coordinates of a cloud at 10³⁰⁰ would overflow).
pub(super) fn starts(ctx: &Context) -> Vec<InitialPose> {
    unit_hypotheses(&ctx.unit, &ctx.norm, &ctx.opts)
}

/// The hypotheses of the points `unit` (normalised by `norm`) in the unit frame.
fn unit_hypotheses(unit: &[DVec3], norm: &Normalization, opts: &FitOptions) -> Vec<InitialPose> {
    match opts.init {
        Initialization::Moments => axis_hypotheses(&initial_pose(unit)).to_vec(),
        Initialization::Explicit(pose) => vec![norm.pose_to_unit(&pose)],
    }
}

/// More starts of a fit's context (unit frame): the moments frames of its [`surface_points`],
/// when they are not all of them and the fit starts from moments (none for an explicit pose).
/// Outliers scattered about an object pull the moments of all the points (and the starts of
/// [`starts`]) far from it; these are not.
pub(super) fn surface_starts(ctx: &Context) -> Vec<InitialPose> {
    match (ctx.opts.init, surface_points(&ctx.unit)) {
        (Initialization::Moments, Some(dense)) => axis_hypotheses(&initial_pose(&dense)).to_vec(),
        _ => Vec::new(),
    }
}

/// The neighbour whose distance measures a point's local density in [`surface_points`].
const DENSITY_NEIGHBOURS: usize = 8;

/// EM rounds of [`surface_points`]' two-component mixture.
const DENSITY_EM_ROUNDS: usize = 30;

/// The points of a spread sample of `unit` ([`coarse_sample`]) that lie densely, as on a sampled
/// surface, rather than sparsely, as outliers scattered through a volume do; `None` when that
/// is all of them or too few to take moments of. A surface sampled with density ρ has its k-th
/// neighbour at r ∝ (k/ρ)^½, outliers in a volume at r ∝ (k/ρ)^⅓ and far sparser: the log
/// distances to the [`DENSITY_NEIGHBOURS`]-th neighbour are split by a two-component Gaussian
/// mixture (EM), and a point is dense when the nearer component explains it better. The
/// moments of all the points are pulled by outliers far from the object; these are not.
pub(super) fn surface_points(unit: &[DVec3]) -> Option<Vec<DVec3>> {
    use crate::model::nearest::kd_tree;
    use kiddo::SquaredEuclidean;
    let sample = super::search::coarse_sample(unit);
    if sample.len() <= 4 * DENSITY_NEIGHBOURS {
        return None;
    }
    let tree = kd_tree(&sample)?;
    let k = std::num::NonZeroUsize::new(DENSITY_NEIGHBOURS + 1)?;
    let log_r: Vec<f64> = sample
        .iter()
        .map(|p| {
            let near = tree
                .query(&p.to_array())
                .nearest_n::<SquaredEuclidean<f64>>(k)
                .execute();
            0.5 * near.last().map_or(0.0, |n| n.distance).max(1e-300).ln()
        })
        .collect();
    let dense = two_component_split(&log_r)?;
    let points: Vec<DVec3> = sample
        .iter()
        .zip(&dense)
        .filter(|(_, d)| **d)
        .map(|(p, _)| *p)
        .collect();
    (points.len() >= 4 * DENSITY_NEIGHBOURS && points.len() < sample.len()).then_some(points)
}

/// Which of the values `x` the lower component of a two-component 1-D Gaussian mixture fitted by
/// EM (from the quartiles) explains better; `None` when the values do not spread, or when the
/// two components do not describe them better than one Gaussian by the Bayesian information
/// criterion (three more parameters, each at ½ ln n): one population, nothing to split.
fn two_component_split(x: &[f64]) -> Option<Vec<bool>> {
    let n = x.len();
    let mut sorted = x.to_vec();
    sorted.sort_by(f64::total_cmp);
    let (q1, q3) = (sorted[n / 4], sorted[3 * n / 4]);
    let var0 = ((q3 - q1) / 2.0).powi(2);
    if !(var0 > 0.0) {
        return None;
    }
    let gauss = |v: f64, mean: f64, var: f64| {
        (-0.5 * (v - mean).powi(2) / var).exp() / (2.0 * std::f64::consts::PI * var).sqrt()
    };
    let one_mean = x.iter().sum::<f64>() / n as f64;
    let one_var = x.iter().map(|v| (v - one_mean).powi(2)).sum::<f64>() / n as f64;
    let one: f64 = x.iter().map(|&v| gauss(v, one_mean, one_var).ln()).sum();
    let (mut mean, mut var, mut weight) = ([q1, q3], [var0; 2], [0.5; 2]);
    let mut low = vec![0.0; n];
    let mut two = f64::NEG_INFINITY;
    for _ in 0..DENSITY_EM_ROUNDS {
        two = 0.0;
        for (l, &v) in low.iter_mut().zip(x) {
            let a = weight[0] * gauss(v, mean[0], var[0]);
            let b = weight[1] * gauss(v, mean[1], var[1]);
            *l = if a + b > 0.0 {
                a / (a + b)
            } else {
                f64::from(v < mean[1])
            };
            two += (a + b).max(f64::MIN_POSITIVE).ln();
        }
        for c in 0..2 {
            let r = |l: f64| if c == 0 { l } else { 1.0 - l };
            let w: f64 = low.iter().map(|&l| r(l)).sum();
            if !(w > 1.0) {
                return None;
            }
            mean[c] = low.iter().zip(x).map(|(&l, &v)| r(l) * v).sum::<f64>() / w;
            var[c] = (low
                .iter()
                .zip(x)
                .map(|(&l, &v)| r(l) * (v - mean[c]).powi(2))
                .sum::<f64>()
                / w)
                .max(1e-6 * var0);
            weight[c] = w / n as f64;
        }
    }
    if two - one <= 1.5 * (n as f64).ln() {
        return None;
    }
    Some(low.iter().map(|&l| l > 0.5).collect())
}

/// The moments frame with each principal axis in turn as the model's z axis: the superquadric's
/// z is special (ε1 shapes its profile), and which data axis it belongs on is not always the one
/// of largest spread (a squat mug's axis is its smallest).
fn axis_hypotheses(pose: &InitialPose) -> [InitialPose; 3] {
    // Cyclic permutation keeps the frame right-handed: (x, y, z) → (y, z, x) → (z, x, y).
    std::array::from_fn(|i| turned_axes(pose, i, false))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::{Rng, SweepSet, set_cloud};

    #[test]
    fn two_populations_are_split_and_one_is_not() {
        let mut rng = Rng::new(3);
        let one: Vec<f64> = (0..600).map(|_| rng.normal()).collect();
        assert_eq!(two_component_split(&one), None);
        let two: Vec<f64> = (0..600)
            .map(|i| rng.normal() * 0.3 + if i % 3 == 0 { 4.0 } else { 0.0 })
            .collect();
        let split = two_component_split(&two).expect("two populations");
        let right = split
            .iter()
            .enumerate()
            .filter(|(i, low)| **low == (i % 3 != 0))
            .count();
        assert!(right >= 590, "{right} of 600 assigned right");
        assert_eq!(two_component_split(&[1.0; 100]), None);
    }

    #[test]
    fn surface_points_leave_scattered_outliers_out() {
        // 40 % outliers in a Gaussian about the object: the dense points are nearly all on it.
        let (_, c) = set_cloud(SweepSet::Outliers, 4);
        let inliers = c.points.len() - c.outliers;
        let dense = surface_points(&c.points).expect("outliers to leave out");
        let on_surface = dense
            .iter()
            .filter(|p| c.points[..inliers].contains(p))
            .count();
        assert!(
            on_surface as f64 >= 0.85 * dense.len() as f64,
            "{on_surface} of {} dense points on the surface",
            dense.len()
        );
        // Most of the sample's surface points are kept (the sample holds 60 % of them).
        let sample = crate::model::fit::coarse_sample(&c.points).len();
        assert!(
            on_surface as f64 >= 0.8 * 0.6 * sample as f64,
            "{on_surface} of {sample}"
        );
    }
}
