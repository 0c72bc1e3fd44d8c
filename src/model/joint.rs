//! Point-to-point joints between the surfaces of two models (beyond the paper: section VII lists
//! "constraints among models" as work in progress).
//!
//! A joint ties a material point u_a = (u, v) on model a to a point u_b on model b: the
//! constraint is g = x_b(u_b) − x_a(u_a) = 0. It is solved by an augmented Lagrangian in the
//! models' own equations of motion: the constraint force on a is F = λ + κ g (and −F on b), where
//! λ is the Lagrange multiplier and κ g the stabilising term (Baumgarte's, at the position level).
//! Each step λ ← λ + η κ g, so at equilibrium g = 0 exactly and λ is the force the joint
//! transmits, whatever else pulls on the parts; while the parts move, κ g closes the gap.
//!
//! On a model of the first-order dynamics the force acts on the global coordinates only
//! ([`JointLoad::Global`], a `shape_force`): a joint holds the parts together as superquadrics
//! and does not raise a spike in either membrane. On a model with mass it acts on the end's
//! nodes ([`JointLoad::Nodal`]): with inertia a force on the global coordinates alone is taken
//! up by the membrane's own inertia, which moves the nodes back as the frame moves on, so the
//! gap never closes and the model runs away while its membrane stretches behind. Each model
//! is stepped on its own with the other held, so each weighs the joint as a spring of 2κ to the
//! gap's midpoint (2κ in its global damping weight, and in the springs the second-order step
//! linearises): each closes half the gap, and the pair closes it without overshooting. With the
//! κ-weighted global damping of `dynamics` that is a Gauss–Newton step, so κ only sets how much
//! the joint weighs against the parts' data, not the step's stability.

use super::dynamics::NodalForces;
use super::fem::{ElementPoint, Tessellation};
use glam::DVec3;

/// The multiplier's step η for the first-order dynamics: λ gains η κ g per step.
pub const MULTIPLIER_RATE: f64 = 0.2;

/// The longest gap a joint's stabilising term pulls with, in units of the smaller part's scale
/// a (the `reach` of [`Joint::apply`]; the plugin's mouse springs stretch as far). A joint made
/// between parts far apart then pulls them together with a bounded force instead of flinging
/// the lighter one.
pub const MAX_REACH: f64 = 1.5;

/// The multiplier's step η for a joint on models with mass ([`super::inertia`]) and damping rate
/// β, stepping by Δt. With inertia the multiplier is an integral term on an oscillator
/// (m s³ + βm s² + κ s + ηκ/Δt), stable only while ηκ/Δt < βκ (Routh–Hurwitz): η = ½ β Δt,
/// and 0 (a plain stabilising spring) without damping.
pub fn inertial_multiplier_rate(damping: f64, dt: f64) -> f64 {
    (0.5 * damping * dt).clamp(0.0, MULTIPLIER_RATE)
}

/// How a joint's force enters one model's equations (module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JointLoad {
    /// On the global coordinates only: for the first-order dynamics.
    Global,
    /// On the end's nodes, global and local coordinates both: for a model with mass.
    Nodal,
}

impl JointLoad {
    /// [`JointLoad::Nodal`] for a model with mass, else [`JointLoad::Global`].
    pub fn for_model(with_mass: bool) -> Self {
        if with_mass { Self::Nodal } else { Self::Global }
    }
}

/// A point on a model's surface by its material coordinates.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JointEnd {
    /// Latitude u ∈ [−π/2, π/2].
    pub u: f64,
    /// Longitude v ∈ [−π, π).
    pub v: f64,
}

impl JointEnd {
    /// The end's world position on a model with tessellation `tess` and node positions `x`
    /// (bilinear within its element, as the paper places points of influence, eq. 22).
    pub fn position(&self, tess: &Tessellation, x: &[DVec3]) -> DVec3 {
        tess.locate(self.u, self.v).interpolate(|k| x[k])
    }

    /// The end at the node of `x` nearest to `point` (how the sandbox picks one).
    pub fn nearest(tess: &Tessellation, x: &[DVec3], point: DVec3) -> Option<Self> {
        let node = (0..x.len().min(tess.node_count())).min_by(|&i, &j| {
            x[i].distance_squared(point)
                .total_cmp(&x[j].distance_squared(point))
        })?;
        let [u, v] = tess.uv[node];
        Some(Self { u, v })
    }
}

/// A point-to-point joint between model a and model b, and its multiplier.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Joint {
    /// The point on model a.
    pub a: JointEnd,
    /// The point on model b.
    pub b: JointEnd,
    /// κ: the stabilising spring constant (and the joint's weight in the global damping).
    pub stiffness: f64,
    /// λ: the Lagrange multiplier, the force the joint transmits to a (world).
    pub multiplier: DVec3,
}

impl Joint {
    /// The default stabilising constant κ: ten times the range springs' β per unit area, so that
    /// a joint outweighs a part's data while the multiplier builds up.
    pub const DEFAULT_STIFFNESS: f64 = 40.0;

    /// A joint between `a` and `b` with stabilising constant `stiffness` and λ = 0.
    pub fn new(a: JointEnd, b: JointEnd, stiffness: f64) -> Self {
        Self {
            a,
            b,
            stiffness,
            multiplier: DVec3::ZERO,
        }
    }

    /// One step's constraint forces: updates λ by `rate` × κ g from the gap g = x_b − x_a
    /// ([`MULTIPLIER_RATE`], or [`inertial_multiplier_rate`] when a model has mass), then adds
    /// F = λ + κ g at a's end and −F at b's to the two models' forces, each as its
    /// [`JointLoad`] says. Both terms use g clamped to the length `reach` (the plugin passes
    /// [`MAX_REACH`] × the smaller scale; `f64::INFINITY` for none). Returns g, unclamped. A
    /// non-finite gap adds nothing and leaves λ alone.
    pub fn apply(
        &mut self,
        rate: f64,
        reach: f64,
        (tess_a, x_a, forces_a, load_a): (&Tessellation, &[DVec3], &mut NodalForces, JointLoad),
        (tess_b, x_b, forces_b, load_b): (&Tessellation, &[DVec3], &mut NodalForces, JointLoad),
    ) -> DVec3 {
        let (at_a, at_b) = (
            tess_a.locate(self.a.u, self.a.v),
            tess_b.locate(self.b.u, self.b.v),
        );
        let gap = at_b.interpolate(|k| x_b[k]) - at_a.interpolate(|k| x_a[k]);
        if !gap.is_finite() || !(self.stiffness > 0.0) {
            return gap;
        }
        let pull = gap.clamp_length_max(reach.max(0.0));
        self.multiplier += rate * self.stiffness * pull;
        let force = self.multiplier + self.stiffness * pull;
        // Each model is stepped on its own, with the other held where it is: weighed as 2κ (a
        // spring of 2κ to the gap's midpoint), each closes half the gap, and together they close
        // it without overshooting (with κ each would close all of it, and the pair would swing).
        add(forces_a, &at_a, force, 2.0 * self.stiffness, load_a);
        add(forces_b, &at_b, -force, 2.0 * self.stiffness, load_b);
        gap
    }
}

/// Spreads a force over an element's nodes (eq. 22), on the coordinates `load` names.
fn add(out: &mut NodalForces, at: &ElementPoint, f: DVec3, kappa: f64, load: JointLoad) {
    if load == JointLoad::Nodal {
        out.add(at, f, kappa);
        return;
    }
    for (n, w) in at.nodes.iter().zip(&at.weights) {
        if *w != 0.0 {
            out.shape_force[*n as usize] += *w * f;
            out.shape_stiffness[*n as usize] += *w * kappa;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::dynamics::{DynamicsParams, ModelState, Workspace, step};
    use crate::model::forces::range::{InfluenceMode, RangeForces};
    use crate::model::superquadric::SuperquadricParams;
    use crate::synthetic::superquadric_cloud;
    use glam::DQuat;

    /// The node positions of a pair of models, and empty forces for each.
    fn positions_and_no_forces(
        tess: &Tessellation,
        states: &[ModelState; 2],
    ) -> ([Vec<DVec3>; 2], [NodalForces; 2]) {
        let x = states.each_ref().map(|s| {
            let mut x = Vec::new();
            s.node_positions(tess, &mut x);
            x
        });
        (
            x,
            std::array::from_fn(|_| NodalForces::new(tess.node_count())),
        )
    }

    fn ball(tess: &Tessellation, at: DVec3) -> ModelState {
        ModelState::new(
            tess,
            at,
            DQuat::IDENTITY,
            SuperquadricParams {
                a: 0.5,
                ..SuperquadricParams::default()
            },
        )
    }

    #[test]
    fn an_end_picked_near_a_point_sits_on_the_nearest_node() {
        // How the sandbox makes a joint end from a click: the node nearest the hit, whose
        // position the end then follows as the model moves.
        let tess = Tessellation::new(9);
        let mut state = ball(&tess, DVec3::new(1.0, 2.0, 3.0));
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        let hit = DVec3::new(1.0, 2.0, 3.0) + DVec3::new(0.1, 0.45, 0.2).normalize() * 0.52;
        let end = JointEnd::nearest(&tess, &x, hit).expect("a node");
        let nearest = x
            .iter()
            .copied()
            .min_by(|a, b| a.distance(hit).total_cmp(&b.distance(hit)))
            .unwrap();
        assert!((end.position(&tess, &x) - nearest).length() < 1e-12);
        state.translation += DVec3::X;
        state.node_positions(&tess, &mut x);
        assert!((end.position(&tess, &x) - (nearest + DVec3::X)).length() < 1e-12);
        assert!(JointEnd::nearest(&tess, &[], hit).is_none());
    }

    #[test]
    fn a_joint_holds_two_parts_together_against_their_data() {
        // Two balls, each fitted (global only) to its own cloud; the clouds are 1.6 apart, so
        // each part's data pulls it away from the joint between a's +x pole region and b's −x.
        // With the joint the gap closes to nothing while both still fit their data as far as the
        // joint lets them; without it they part.
        let tess = Tessellation::new(9);
        let params = DynamicsParams {
            dt: 0.05,
            free: crate::model::dynamics::FreeDofs {
                local: false,
                ..Default::default()
            },
            ..Default::default()
        };
        let cloud = |centre: DVec3, seed| {
            let shape = SuperquadricParams {
                a: 0.5,
                ..SuperquadricParams::default()
            };
            superquadric_cloud(&shape, centre, DQuat::IDENTITY, 300, 0.0, seed)
        };
        let run = |jointed: bool| {
            let mut states = [
                ball(&tess, DVec3::new(-0.5, 0.0, 0.0)),
                ball(&tess, DVec3::new(0.5, 0.0, 0.0)),
            ];
            let mut ranges = [
                RangeForces::new(
                    cloud(DVec3::new(-0.8, 0.0, 0.0), 1),
                    4.0,
                    InfluenceMode::NearestNode,
                ),
                RangeForces::new(
                    cloud(DVec3::new(0.8, 0.0, 0.0), 2),
                    4.0,
                    InfluenceMode::NearestNode,
                ),
            ];
            let mut joint = Joint::new(
                JointEnd { u: 0.0, v: 0.0 },
                JointEnd {
                    u: 0.0,
                    v: std::f64::consts::PI - 1e-9,
                },
                50.0,
            );
            let mut ws = [Workspace::default(), Workspace::default()];
            let mut gap = DVec3::ZERO;
            for k in 0..1500 {
                let (x, mut forces) = positions_and_no_forces(&tess, &states);
                for p in 0..2 {
                    if k % 50 == 0 {
                        ranges[p].reassign(&tess, &x[p]);
                    }
                    ranges[p].accumulate(&tess, &x[p], &mut forces[p]);
                }
                if jointed {
                    let [fa, fb] = &mut forces;
                    let g = JointLoad::Global;
                    gap = joint.apply(
                        MULTIPLIER_RATE,
                        f64::INFINITY,
                        (&tess, &x[0], fa, g),
                        (&tess, &x[1], fb, g),
                    );
                }
                for p in 0..2 {
                    step(&tess, &mut states[p], &forces[p], &params, &mut ws[p]).expect("finite");
                }
            }
            (states, gap, joint.multiplier)
        };
        let (free, _, _) = run(false);
        let free_gap = (free[1].translation - free[0].translation).length() - 1.0;
        assert!(
            free_gap > 0.5,
            "unjointed parts should follow their data apart: {free_gap}"
        );
        let (held, gap, lambda) = run(true);
        assert!(gap.length() < 1e-6, "gap {gap}");
        // The joint transmits a finite pull, nearly along the line between the parts (the two
        // random clouds are not quite mirror images): a is pulled towards b (+x), against its data.
        assert!(
            lambda.x > 0.0 && lambda.y.abs().max(lambda.z.abs()) < 0.05 * lambda.x,
            "λ {lambda}"
        );
        // The parts sit between where the joint and their data want them.
        assert!(held[0].translation.x < -0.5 && held[1].translation.x > 0.5);
    }

    /// Two balls with mass, jointed where they touch and pulled apart by constant forces on
    /// their far sides, rigid or with free membranes, the joint's force entering as `load`:
    /// (largest gap over the last second, whether any step failed).
    fn pulled_apart_with_mass(rate: f64, membrane: bool, load: JointLoad) -> (f64, bool) {
        use crate::model::inertia::{
            InertiaParams, InertiaWorkspace, Velocity, step as inertia_step,
        };
        let tess = Tessellation::new(7);
        let mut params = DynamicsParams {
            dt: 0.05,
            ..Default::default()
        };
        params.free.local = membrane;
        params.free.shape = [false; 6];
        let inertia = InertiaParams {
            damping: 1.0,
            ..Default::default()
        };
        let mut states = [
            ball(&tess, DVec3::new(-0.5, 0.0, 0.0)),
            ball(&tess, DVec3::new(0.5, 0.0, 0.0)),
        ];
        let mut ws = [InertiaWorkspace::default(), InertiaWorkspace::default()];
        let mut v = [
            Velocity::zero(tess.node_count()),
            Velocity::zero(tess.node_count()),
        ];
        let mut joint = Joint::new(
            JointEnd { u: 0.0, v: 0.0 },
            JointEnd {
                u: 0.0,
                v: std::f64::consts::PI,
            },
            40.0,
        );
        let far = [
            tess.locate(0.0, std::f64::consts::PI),
            tess.locate(0.0, 0.0),
        ];
        let mut worst = 0.0_f64;
        for k in 0..400 {
            let (x, mut forces) = positions_and_no_forces(&tess, &states);
            for p in 0..2 {
                let pull = if p == 0 { -DVec3::X } else { DVec3::X };
                forces[p].add(&far[p], pull, 0.0);
            }
            let [fa, fb] = &mut forces;
            let gap = joint.apply(
                rate,
                f64::INFINITY,
                (&tess, &x[0], fa, load),
                (&tess, &x[1], fb, load),
            );
            if k >= 380 {
                worst = worst.max(gap.length());
            }
            for p in 0..2 {
                if inertia_step(
                    &tess,
                    &mut states[p],
                    &mut v[p],
                    &forces[p],
                    &params,
                    &inertia,
                    &mut ws[p],
                )
                .is_err()
                {
                    return (f64::INFINITY, true);
                }
            }
        }
        (worst, false)
    }

    #[test]
    fn with_mass_the_multiplier_rate_must_respect_the_damping() {
        // At η = ½ β Δt the jointed pair settles with the joint closed; at the first-order rate
        // (0.2 > β Δt = 0.05) the multiplier's integral action outruns the damping and the gap
        // grows without bound (Routh–Hurwitz, see `inertial_multiplier_rate`).
        let nodal = JointLoad::Nodal;
        let (gap, failed) =
            pulled_apart_with_mass(inertial_multiplier_rate(1.0, 0.05), false, nodal);
        assert!(!failed && gap < 1e-3, "stable rate: gap {gap}");
        let (gap, failed) = pulled_apart_with_mass(MULTIPLIER_RATE, false, nodal);
        assert!(
            failed || gap > 1.0,
            "the first-order rate should be unstable with mass: gap {gap}"
        );
    }

    #[test]
    fn with_mass_and_free_membranes_the_joint_holds() {
        let rate = inertial_multiplier_rate(1.0, 0.05);
        let (gap, failed) = pulled_apart_with_mass(rate, true, JointLoad::Nodal);
        assert!(!failed && gap < 0.05, "gap {gap}");
    }

    #[test]
    fn a_joint_holds_a_model_with_mass_to_one_without() {
        // The plugin's case that tests/plugin_properties.rs found: a ball with mass and a free
        // membrane jointed to a first-order ball, each end loaded as the plugin loads it. With
        // the force on the massive ball's global coordinates alone (and its semi-axes clipped
        // at their bound after each sub-step) its frame ran away, to 6e18 in 300 steps.
        use crate::model::inertia::{
            InertiaParams, InertiaWorkspace, Velocity, step as inertia_step,
        };
        let tess = Tessellation::new(7);
        let params = DynamicsParams {
            dt: 0.05,
            ..Default::default()
        };
        let inertia = InertiaParams::default();
        let run = |load: JointLoad| -> f64 {
            let mut states = [
                ball(&tess, DVec3::new(-0.5, 0.0, 0.0)),
                ball(&tess, DVec3::new(1.5, 0.3, -0.4)),
            ];
            let (mut ws, mut iws) = (Workspace::default(), InertiaWorkspace::default());
            let mut v = Velocity::zero(tess.node_count());
            let mut joint = Joint::new(
                JointEnd { u: 0.0, v: 0.0 },
                JointEnd {
                    u: 0.3,
                    v: std::f64::consts::PI,
                },
                Joint::DEFAULT_STIFFNESS,
            );
            let rate = inertial_multiplier_rate(inertia.damping, params.dt);
            let mut worst = 0.0_f64;
            for k in 0..300 {
                let (x, mut forces) = positions_and_no_forces(&tess, &states);
                let [fa, fb] = &mut forces;
                let global = JointLoad::Global;
                let gap = joint.apply(
                    rate,
                    f64::INFINITY,
                    (&tess, &x[0], fa, global),
                    (&tess, &x[1], fb, load),
                );
                if k >= 250 {
                    worst = worst.max(gap.length());
                }
                step(&tess, &mut states[0], &forces[0], &params, &mut ws).expect("first order");
                if inertia_step(
                    &tess,
                    &mut states[1],
                    &mut v,
                    &forces[1],
                    &params,
                    &inertia,
                    &mut iws,
                )
                .is_err()
                {
                    return f64::INFINITY;
                }
            }
            let far = states
                .iter()
                .map(|s| s.translation.length())
                .fold(0.0, f64::max);
            worst.max(if far > 10.0 { far } else { 0.0 })
        };
        let held = run(JointLoad::for_model(true));
        assert!(held < 0.05, "gap {held}");
    }

    #[test]
    fn a_joint_made_across_a_wide_gap_pulls_within_reach() {
        // The plugin's case that tests/plugin_properties.rs found: a stiff joint (κ = 775) made
        // between a ball and a light ball with mass 9 scales away. With the whole gap in the
        // stabilising term the first step grew the light ball's scale from 0.5 to 2.7; within
        // reach the force is bounded as a mouse spring's is, and inside reach nothing changes.
        use crate::model::inertia::{
            InertiaParams, InertiaWorkspace, Velocity, step as inertia_step,
        };
        let tess = Tessellation::new(7);
        let (params, inertia) = (DynamicsParams::default(), InertiaParams::default());
        let rate = inertial_multiplier_rate(inertia.damping, params.dt);
        let facing = (
            JointEnd { u: 0.0, v: 0.0 },
            JointEnd {
                u: 0.0,
                v: std::f64::consts::PI,
            },
        );
        let loads = (JointLoad::Global, JointLoad::Nodal);
        // The light ball's scale after one step, and the largest nodal force the joint added.
        let first_step = |at: f64, reach: f64| -> (f64, f64) {
            let mut states = [ball(&tess, DVec3::ZERO), ball(&tess, DVec3::X * at)];
            let mut v = Velocity::zero(tess.node_count());
            let mut joint = Joint::new(facing.0, facing.1, 775.0);
            let (x, mut f) = positions_and_no_forces(&tess, &states);
            let [fa, fb] = &mut f;
            joint.apply(
                rate,
                reach,
                (&tess, &x[0], fa, loads.0),
                (&tess, &x[1], fb, loads.1),
            );
            let pull = f[1].force.iter().fold(DVec3::ZERO, |s, f| s + *f).length();
            let mut iws = InertiaWorkspace::default();
            let p = (&params, &inertia, &mut iws);
            inertia_step(&tess, &mut states[1], &mut v, &f[1], p.0, p.1, p.2).expect("a step");
            (states[1].shape.a, pull)
        };
        let reach = MAX_REACH * 0.5;
        let (flung, _) = first_step(10.0, f64::INFINITY);
        assert!(
            flung > 2.0,
            "the whole gap no longer flings the ball: a = {flung}"
        );
        let (a, pull) = first_step(10.0, reach);
        assert!(
            (a - 0.5).abs() < 0.15,
            "one step took the ball's scale to {a}"
        );
        assert!(
            pull <= (1.0 + rate) * 775.0 * reach * (1.0 + 1e-12),
            "pull {pull}"
        );
        // Within reach (a gap of 0.2) the clamp changes nothing.
        assert_eq!(first_step(1.2, reach), first_step(1.2, f64::INFINITY));
    }
}
