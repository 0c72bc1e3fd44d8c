//! The states a fit starts from and the candidates it tries: the moments frame with each of its
//! axes as the model's z ([`initial_hypotheses`]), and a fitted superquadric's similar shapes
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

/// The moments frame with each principal axis in turn as the model's z axis: the superquadric's
/// z is special (ε1 shapes its profile), and which data axis it belongs on is not always the one
/// of largest spread (a squat mug's axis is its smallest).
fn axis_hypotheses(pose: &InitialPose) -> [InitialPose; 3] {
    // Cyclic permutation keeps the frame right-handed: (x, y, z) → (y, z, x) → (z, x, y).
    std::array::from_fn(|i| turned_axes(pose, i, false))
}
