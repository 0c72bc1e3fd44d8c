//! The fit's plan: the dynamics' [`Stage`]s and the clock that ends each ([`StageClock`]), the
//! hypotheses a fit starts from (axis turns, duals, similarity candidates), and the membrane's
//! tessellation chosen from the data ([`joint_k`]).

use super::*;

/// Which degrees of freedom the loop is moving, and with which forces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// Global DOFs only, with the model-to-data coverage springs on (placing the model).
    Cover,
    /// Global DOFs only (local held), the paper's forces.
    Global,
    /// Global and local DOFs together.
    Joint,
}

/// The bookkeeping of one stage of the dynamics: how the forces and free DOFs are set, when
/// points are reattached and when the model is at rest.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct StageClock {
    /// The stage being run.
    pub stage: Stage,
    /// Steps since the last reattachment.
    pub since_reassign: u32,
}

impl StageClock {
    /// A clock at the start of `stage`.
    pub fn new(stage: Stage) -> Self {
        Self {
            stage,
            since_reassign: 0,
        }
    }

    /// Whether the local DOFs move in this stage.
    pub fn local_free(&self, opts: &FitOptions) -> bool {
        opts.dynamics.free.local && self.stage == Stage::Joint
    }

    /// Whether the range springs are point-to-plane in this stage (the global stage, when
    /// `point_to_plane` is set).
    pub fn plane(&self, opts: &FitOptions) -> bool {
        opts.point_to_plane && self.stage == Stage::Global
    }

    /// Coverage-spring density in this stage: the placing stage has them, and with
    /// `global_coverage` (a tapered or bent fit of data that surrounds the model, beyond the
    /// paper) the global stage too.
    pub fn coverage(&self, opts: &FitOptions, global_coverage: bool) -> f64 {
        if self.stage == Stage::Cover || (global_coverage && self.stage == Stage::Global) {
            opts.coverage
        } else {
            0.0
        }
    }

    /// After a step whose largest node motion was `motion`: reattaches through `reassign` (which
    /// returns how many springs changed) when `reassign_every` steps have passed or the model is
    /// at rest, and returns true when the stage is over: at rest right after a reattachment that
    /// changed at most `settle_fraction` of the `points`, and never fewer than one. (A point
    /// midway between two nodes can flip from one to the other at every rest for ever; below 500
    /// points the default 0.2 % rounds to none, and such a stage ran to its step cap.)
    pub fn after_step(
        &mut self,
        motion: f64,
        opts: &FitOptions,
        points: usize,
        reassign: impl FnOnce() -> usize,
    ) -> bool {
        self.since_reassign += 1;
        let at_rest = motion < opts.tolerance;
        if self.since_reassign < opts.reassign_every && !at_rest {
            return false;
        }
        let changed = reassign();
        self.since_reassign = 0;
        at_rest && changed as f64 <= (opts.settle_fraction * points as f64).max(1.0)
    }
}

/// The step budget of each similarity candidate ([`FitOptions::similarity_switch`]) when `spent`
/// of the fit's `max_steps` are used: an equal share of the rest, as the hypotheses share the
/// whole, so that the candidates can run side by side and the fit stays within its cap.
pub(crate) fn similarity_share(max_steps: u32, spent: u32, candidates: usize) -> u32 {
    max_steps.saturating_sub(spent) / candidates.max(1) as u32
}

/// The stages a fit runs before choosing among initial hypotheses: placing (when `coverage` > 0)
/// and the global stage (unless the local DOFs move from the start).
pub(crate) fn global_stages(opts: &FitOptions) -> Vec<Stage> {
    let mut stages = Vec::new();
    if opts.coverage > 0.0 {
        stages.push(Stage::Cover);
    }
    if opts.global_first || opts.global_only || !opts.dynamics.free.local {
        stages.push(Stage::Global);
    }
    stages
}

/// Whether a fit goes on to the joint stage after the global ones.
pub fn has_joint_stage(opts: &FitOptions) -> bool {
    !opts.global_only && opts.dynamics.free.local
}

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
pub(super) fn dual_about_z(pose: &InitialPose, scale: f64) -> InitialPose {
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

/// The initial states a fit tries: the three axis hypotheses of the moments frame, or the one
/// explicit pose.
pub fn initial_hypotheses(points: &[DVec3], opts: &FitOptions) -> Vec<InitialPose> {
    match opts.init {
        Initialization::Moments => {
            // The moments are taken in the unit frame: squared coordinates of a cloud at 1e300
            // would overflow.
            let norm = Normalization::of(points);
            if !(norm.scale > 0.0) {
                return axis_hypotheses(&initial_pose(points)).to_vec();
            }
            let unit: Vec<DVec3> = points.iter().map(|p| norm.unit_point(*p)).collect();
            axis_hypotheses(&initial_pose(&unit))
                .iter()
                .map(|h| norm.pose_from_unit(h))
                .collect()
        }
        Initialization::Explicit(pose) => vec![pose],
    }
}

/// The moments frame with each principal axis in turn as the model's z axis: the superquadric's
/// z is special (ε1 shapes its profile), and which data axis it belongs on is not always the one
/// of largest spread (a squat mug's axis is its smallest).
pub(super) fn axis_hypotheses(pose: &InitialPose) -> [InitialPose; 3] {
    // Cyclic permutation keeps the frame right-handed: (x, y, z) → (y, z, x) → (z, x, y).
    std::array::from_fn(|i| turned_axes(pose, i, false))
}

/// The finest tessellation [`joint_k`] chooses: k = 101 (10 203 nodes).
pub const MAX_JOINT_K: usize = 101;

/// Data points per covered node that [`joint_k`] aims at. On the five one-view scans of
/// docs/results.md (3000–6100 points, 16–35 % of the model's surface covered) 2 gives k = 75–96;
/// 3 gave 4–30 % larger mean residuals, 1 (k up to 136) from 10 % larger to 29 % smaller at 1.5×
/// the time.
pub const POINTS_PER_COVERED_NODE: f64 = 2.0;

/// [`joint_k`] keeps the given tessellation unless the data asks for at least this many times its
/// nodes: a second joint stage on a barely finer mesh costs steps and gains nothing measurable.
pub const MIN_JOINT_REFINEMENT: f64 = 1.5;

/// The joint stage's tessellation (k) chosen from the data's density and extent, given the
/// model's nodes `x` on `tess` after the global stages and the data `points`: a node is covered
/// when it is some point's nearest, so with c of the n nodes covered the data spans about c/n of
/// the surface, and k grows until that share of the nodes is one per
/// [`POINTS_PER_COVERED_NODE`] points. A dense scan of a small part of the surface gets nodes
/// where its detail is; a sparse cloud keeps `min_k`, and so does one that asks for fewer than
/// [`MIN_JOINT_REFINEMENT`] times its nodes. At most [`MAX_JOINT_K`].
pub fn joint_k(tess: &Tessellation, x: &[DVec3], points: &[DVec3], min_k: usize) -> usize {
    let Some(grid) = crate::model::forces::nearest::NodeGrid::new(x) else {
        return min_k;
    };
    let mut covered = vec![false; x.len()];
    for i in grid.nearest_each(points) {
        covered[i as usize] = true;
    }
    let count = covered.iter().filter(|&&c| c).count().max(1);
    let share = count as f64 / tess.node_count() as f64;
    let nodes = points.len() as f64 / (POINTS_PER_COVERED_NODE * share);
    if nodes < MIN_JOINT_REFINEMENT * (min_k * min_k + 2) as f64 {
        return min_k;
    }
    let k = (nodes - 2.0).max(0.0).sqrt().round() as usize;
    k.clamp(min_k, MAX_JOINT_K.max(min_k))
}
