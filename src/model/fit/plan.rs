//! The fit's plan: its [`Stage`]s and the clock that ends each ([`StageClock`]), the refining
//! stage's tests, and the hypotheses a fit starts from (axis turns, duals, similarity candidates,
//! extended squareness).

use super::*;

/// Migration rate of the refining stage ([`Stage::Refine`]): each step moves a point of influence
/// the whole Gauss–Newton way to the foot of its datum (at most one element).
pub const REFINE_RATE: f64 = 1.0;

/// Step budget of the refining stage. A refinement that is not at rest by then, or that leaves
/// the points farther from the surface than the global stage did, is undone: on noisy clouds with
/// outliers, points near a cylinder's rim can let its length run away (each cap point's closest
/// surface point slides onto the side wall), a minimum of the one-sided distance that is no fit.
pub const REFINE_MAX_STEPS: u32 = 3000;

/// The refining stage is checked every this many steps ([`REFINE_GIVE_UP`], [`refine_stalled`]).
pub const REFINE_CHECK_EVERY: u32 = 250;

/// A refinement whose mean point-to-surface distance, checked every [`REFINE_CHECK_EVERY`] steps,
/// exceeds this multiple of the least distance it has had (the global stage's at first) is given
/// up and undone at once instead of at the end of its [`REFINE_MAX_STEPS`]. On scans of objects
/// that are no superquadric, the outlier weights let it drop whole limbs (the bunny's ears) and
/// the one-sided distance it minimises keeps falling while the model runs off; on a cylinder with
/// outliers (EMS's `noisy_pointCloud_example_2`), projected onto the mesh's chords, it first came
/// closer, then its length ran away.
pub const REFINE_GIVE_UP: f64 = 1.01;

/// A refinement is also given up, after any step, when the superquadric's longest semi-axis has
/// grown past this multiple of its length at the start of the stage ([`refine_overgrown`]). The
/// refinement polishes a fit that the global stage has placed and sized; a model that grows by
/// half again is the other way a cylinder's length runs away with its rim points, the mean
/// distance still falling as it goes (on EMS's `noisy_pointCloud_example_3`, two similarity
/// candidates grew 3× in 3000 steps).
pub const REFINE_MAX_GROWTH: f64 = 1.5;

/// The refining stage's check every [`REFINE_CHECK_EVERY`] steps, shared by [`fit`] and the
/// plugin's fit: given the mean `distance` of the points now and the `least` seen before, returns
/// the new least, or `None` to give the refinement up ([`REFINE_GIVE_UP`]).
pub fn refine_check(distance: f64, least: f64) -> Option<f64> {
    (distance <= REFINE_GIVE_UP * least).then(|| least.min(distance))
}

/// Whether a refinement has run off in length: its longest semi-axis `longest` is past
/// [`REFINE_MAX_GROWTH`] times `start`, its length at the start of the stage. One number, so
/// [`fit`] and the plugin's fit ask after every step of the stage that did not end it: a model
/// that runs off in length goes on running off, and was given up only at the next check of
/// [`REFINE_CHECK_EVERY`] (on EMS's `partial_pointCloud_example_1`
/// had one similarity candidate 2.2 times as long 65 steps into its refinement and 62 times at
/// the check 215 steps in).
pub fn refine_overgrown(longest: f64, start: f64) -> bool {
    longest > REFINE_MAX_GROWTH * start
}

/// A refinement whose inlier-weighted mean point-to-surface distance ([`refine_distances`], with
/// the robust weights of the moment), checked every [`REFINE_CHECK_EVERY`] steps, fell by less
/// than this fraction since the previous check is given up ([`refine_stalled`]): it is circling,
/// not converging. On EMS's `partial_pointCloud_example_3` one similarity candidate's refinement
/// went round a cycle of states (the largest node motion steady at 2.6e-3 of the RMS radius a
/// step) to its [`REFINE_MAX_STEPS`] and was undone; it is now undone 920 steps sooner. The
/// weights matter: with 20 % outliers the plain mean distance wanders by more than this while a
/// fit still converges (a rule on it lost one of the 20 ground-truth clouds).
pub const REFINE_MIN_PROGRESS: f64 = 1e-3;

/// A similarity candidate ([`FitOptions::similarity_switch`]) goes on to the refining stage only
/// when its global stage ended no farther from the points than this multiple of the chosen fit's
/// global stage (both by the chosen fit's inlier-weighted mean distance,
/// [`weighted_mean_distance`]): the two stages ran on the same forces, so the comparison is
/// like for like, and a candidate that placed much worse has not been seen to refine past the
/// chosen fit. On the eight shipped clouds and the 20 ground-truth clouds (`cargo bench --bench
/// ground_truth`) the candidates that won did so from ratios of 0.39 to 1.89, and
/// those that lost reached 4.5; at 2.5 the fits and the ground-truth table are what refining
/// every candidate gives, and EMS's `partial_pointCloud_example_1`, `_2` and `_3` skip
/// refinements that took 25 %, 31 % and 40 % of their steps.
pub const SIMILARITY_REFINE_MARGIN: f64 = 2.5;

/// Whether a similarity candidate whose global stage ended `candidate` from the points is
/// refined, when the chosen fit's global stage ended `chosen` from them
/// ([`SIMILARITY_REFINE_MARGIN`]). Shared by [`fit`] and the plugin's fit.
pub fn refine_candidate(candidate: f64, chosen: f64) -> bool {
    candidate <= SIMILARITY_REFINE_MARGIN * chosen
}

/// Whether a refinement has stalled: its inlier-weighted distance `weighted` at a check is more
/// than 1 − [`REFINE_MIN_PROGRESS`] times the one at the `previous` check of the stage (none at
/// the first). Shared by [`fit`] and the plugin's fit.
pub fn refine_stalled(weighted: f64, previous: Option<f64>) -> bool {
    previous.is_some_and(|p| weighted > (1.0 - REFINE_MIN_PROGRESS) * p)
}

/// The refining stage's two measures at a check, from one pass over the point distances: the
/// mean distance of `range`'s points to the surface through `node_x` ([`refine_check`]) and the
/// same weighted by each point's [`RangeForces::relative_weight`] ([`refine_stalled`]).
pub fn refine_distances(tess: &Tessellation, node_x: &[DVec3], range: &RangeForces) -> (f64, f64) {
    let d = point_distances(tess, node_x, range.points());
    let mean = d.iter().sum::<f64>() / d.len().max(1) as f64;
    let (mut total, mut weighted) = (0.0, 0.0);
    for (i, d) in d.iter().enumerate() {
        let w = range.relative_weight(i);
        total += w;
        weighted += w * d;
    }
    (mean, weighted / total.max(f64::MIN_POSITIVE))
}

/// Which degrees of freedom the loop is moving, and with which forces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// Global DOFs only, with the model-to-data coverage springs on (placing the model).
    Cover,
    /// Global DOFs only (local held), the paper's forces.
    Global,
    /// Global DOFs only, after the hypothesis is chosen, with each point's point of influence
    /// migrating to its closest point on the surface (the paper's Fig. 3) and point-to-plane
    /// springs: the superquadric fitted to the points themselves instead of to the nodes they
    /// chose (beyond the paper's experiments; [`FitOptions::refine`]). [`fit`] and
    /// `plugin::headless::fit_headless` undo it when it does not pay; the plugin's `FitDriver` alone
    /// runs it to rest or to its budget.
    Refine,
    /// Global and local DOFs together.
    Joint,
}

/// The bookkeeping of one stage of a fit: how the forces and free DOFs are set, when points are
/// reattached and when the model is at rest. [`fit`] and the plugin's fit driver share it, so a fit
/// takes the same steps either way.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StageClock {
    /// The stage being run.
    pub stage: Stage,
    /// Steps since the last reattachment.
    pub since_reassign: u32,
    /// Signatures ([`RangeForces::signature`]) of the springs that the last
    /// [`REST_CYCLE_MEMORY`] unsettled reattachments at rest gave, newest at
    /// `rests % REST_CYCLE_MEMORY`.
    pub rest_signatures: [u64; REST_CYCLE_MEMORY],
    /// How many unsettled reattachments at rest this stage has had.
    pub rests: u32,
}

/// How many of its last rests a stage remembers to tell a cycle of rests
/// ([`StageClock::after_step`]).
pub const REST_CYCLE_MEMORY: usize = 4;

impl StageClock {
    /// A clock at the start of `stage`.
    pub fn new(stage: Stage) -> Self {
        Self {
            stage,
            since_reassign: 0,
            rest_signatures: [0; REST_CYCLE_MEMORY],
            rests: 0,
        }
    }

    /// Whether the local DOFs move in this stage.
    pub fn local_free(&self, opts: &FitOptions) -> bool {
        opts.dynamics.free.local && self.stage == Stage::Joint
    }

    /// Whether the range springs are point-to-plane in this stage (the global stages, when
    /// `point_to_plane` is set).
    pub fn plane(&self, opts: &FitOptions) -> bool {
        (opts.point_to_plane && self.stage == Stage::Global) || self.stage == Stage::Refine
    }

    /// How points of influence are chosen in this stage: migrating in the refining stage, the
    /// options' mode otherwise.
    pub fn influence(&self, opts: &FitOptions) -> InfluenceMode {
        if self.stage == Stage::Refine {
            InfluenceMode::Migrating { rate: REFINE_RATE }
        } else {
            opts.influence
        }
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
    /// returns how many springs changed and the springs' [`RangeForces::signature`]) when
    /// `reassign_every` steps have passed or the model is at rest, and returns true when the stage
    /// is over: at rest right after a reattachment that changed at most `settle_fraction` of the
    /// `points`, or at rest right after one that gave springs this stage has already had at one of
    /// its last [`REST_CYCLE_MEMORY`] rests. That is a cycle of rests: with nearest-node springs a
    /// point midway between two nodes can flip from one to the other at each rest for ever (on
    /// EMS's `partial_pointCloud_example_3` with `--outliers 0.05`, one point of 216 — more than
    /// the 0.2 % it may — every 3 steps, until the fit's 20 000-step cap). A reattachment that
    /// changed every spring (the robust weights still sharpening) starts no cycle.
    pub fn after_step(
        &mut self,
        motion: f64,
        opts: &FitOptions,
        points: usize,
        reassign: impl FnOnce() -> (usize, u64),
    ) -> bool {
        self.since_reassign += 1;
        let at_rest = motion < opts.tolerance;
        if self.since_reassign < opts.reassign_every && !at_rest {
            return false;
        }
        let (changed, signature) = reassign();
        self.since_reassign = 0;
        if !at_rest {
            return false;
        }
        if changed as f64 <= opts.settle_fraction * points as f64 {
            return true;
        }
        if changed >= points {
            return false;
        }
        let seen = self.rest_signatures[..(self.rests as usize).min(REST_CYCLE_MEMORY)]
            .contains(&signature);
        self.rest_signatures[self.rests as usize % REST_CYCLE_MEMORY] = signature;
        self.rests += 1;
        seen
    }
}

/// The step budget of each similarity candidate ([`FitOptions::similarity_switch`]) when `spent`
/// of the fit's `max_steps` are used: an equal share of the rest, as the hypotheses share the
/// whole, so that the candidates can run side by side and the fit stays within its cap.
pub fn similarity_share(max_steps: u32, spent: u32, candidates: usize) -> u32 {
    max_steps.saturating_sub(spent) / candidates.max(1) as u32
}

/// The exponents [`extend_squareness`] tries below [`MIN_EPSILON`], largest first.
pub const EXTENDED_EPSILONS: [f64; 4] = [0.05, 0.03, 0.02, LEAST_EPSILON];

/// The squareness extension of a pure superquadric fit (beyond the paper). The dynamics hold ε1
/// and ε2 at [`MIN_EPSILON`] or above, because below it eq. (4) crowds a flat face into a sliver
/// of (u, v) at the pole that the points of influence cannot migrate onto; a fit that ends with an
/// exponent at that bound is asking for a squarer shape. Each such exponent (ε1, then ε2 with ε1's
/// outcome) is tried at each of [`EXTENDED_EPSILONS`], every other parameter held, and set to the
/// trial whose surface lies closest to `points` weighted by `weights` (the similarity switch's
/// score, [`weighted_mean_distance`], measured over every core) if it is closer than the fit's.
/// The shape when an exponent moved, `None` otherwise.
///
/// EMS's noisy cylinder (`noisy_pointCloud_example_2`), whose robust fit came to rest at ε1 =
/// 0.1, is the case: the extension takes ε1 to 0.01 and the mean distance of the points to the
/// surface from 0.01485 to 0.01468 of the diagonal, EMS's own fit (ε1 = 0.01) lying 0.01473
/// from them (docs/results.md, "Side by side with EMS").
pub fn extend_squareness(
    tess: &Tessellation,
    state: &ModelState,
    points: &[DVec3],
    weights: &[f64],
) -> Option<SuperquadricParams> {
    let mut x = Vec::new();
    let mut distance = |shape: &SuperquadricParams| {
        node_positions(
            tess,
            state.translation,
            state.rotation,
            shape,
            &state.deformation,
            &state.displacement,
            &mut x,
        );
        // The extension runs alone at the end of a fit: its distances use every core.
        weighted_mean(&point_distances_parallel(tess, &x, points), weights)
    };
    let mut best = state.shape;
    let mut least = None;
    for k in 0..2 {
        let with = |q: SuperquadricParams, e: f64| {
            if k == 0 {
                SuperquadricParams { e1: e, ..q }
            } else {
                SuperquadricParams { e2: e, ..q }
            }
        };
        if [best.e1, best.e2][k] != MIN_EPSILON {
            continue;
        }
        let mut here = *least.get_or_insert_with(|| distance(&best));
        let mut moved = None;
        for e in EXTENDED_EPSILONS {
            let trial = with(best, e);
            let d = distance(&trial);
            if d < here {
                (here, moved) = (d, Some(trial));
            }
        }
        if let Some(shape) = moved {
            (best, least) = (shape, Some(here));
        }
    }
    (best != state.shape).then_some(best)
}

/// The stages a fit runs before choosing among initial hypotheses: placing (when `coverage` > 0)
/// and the global stage (unless the local DOFs move from the start).
pub fn global_stages(opts: &FitOptions) -> Vec<Stage> {
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
