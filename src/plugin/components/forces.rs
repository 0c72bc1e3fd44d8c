//! The components that pull on a model from outside: range data (eq. 22), an image (eqs. 20–23),
//! user springs, and joints between parts.

use super::ModelSettings;
use crate::model::fem::Tessellation;
use crate::model::forces::range::{InfluenceMode, RangeForces};
use crate::model::joint::{Joint, JointEnd};
use bevy::math::DVec3;
use bevy::prelude::*;

/// An image pulling on a model (eqs. 20–23): the potential (shared by every part fitted to the
/// same image, through its `Arc`), β, the band and the beyond-the-paper options of
/// [`ImageForces`](crate::model::forces::image::ImageForces). Pair it with
/// [`ModelSettings::planar`] and `fix_epsilon`, as the image experiments do.
#[derive(Component, Clone, Debug)]
pub struct ImageData {
    /// The forces, applied at the gather stage.
    pub forces: crate::model::forces::image::ImageForces,
}

impl ImageData {
    /// Image forces of `potential` with the default β, band and outline-only pull.
    pub fn new(potential: std::sync::Arc<crate::model::forces::image::ImagePotential>) -> Self {
        Self {
            forces: crate::model::forces::image::ImageForces::new(potential),
        }
    }

    /// The image settings of an image fit.
    pub fn with_options(self, opts: &crate::model::image_fit::ImageFitOptions) -> Self {
        Self {
            forces: opts.forces(self.forces.potential),
        }
    }
}

/// Range data attached to a model: points in world space pulling on their points of influence
/// (eq. 22). `forces.influence()` gives the current point → node (or element) attachment, readable
/// by other systems.
#[derive(Component, Clone, Debug)]
pub struct RangeData {
    /// The springs: points, strength β, influence mode and the current attachments.
    pub forces: RangeForces,
    /// Reattachments done so far.
    pub reassignments: u64,
}

impl RangeData {
    /// Range data with strength β = 4, the paper's nearest-node attachment and no coverage
    /// springs (the paper's forces).
    pub fn new(points: Vec<DVec3>) -> Self {
        let mut forces = RangeForces::new(points, 4.0, InfluenceMode::NearestNode);
        forces.coverage = 0.0;
        Self {
            forces,
            reassignments: 0,
        }
    }

    /// The same with model-to-data coverage springs of density `coverage` × β (see
    /// [`crate::model::forces::range`]; [`DEFAULT_COVERAGE`](crate::model::forces::range::DEFAULT_COVERAGE) is what the fit loop places with).
    pub fn with_coverage(mut self, coverage: f64) -> Self {
        self.forces.coverage = coverage;
        self
    }

    /// The same with points of influence migrating over the surface (Fig. 3).
    pub fn migrating(mut self) -> Self {
        self.forces.mode = InfluenceMode::Migrating { rate: 0.5 };
        self
    }

    /// The same with strength β.
    pub fn with_beta(mut self, beta: f64) -> Self {
        self.forces.beta = beta;
        self
    }

    /// The node each data point is attached to (the first node of its element when it lies
    /// inside one); empty before the first reattachment.
    pub fn attached_nodes(&self) -> impl Iterator<Item = u32> + '_ {
        self.forces.influence().iter().map(|i| i.at.nodes[0])
    }
}

/// A spring from a material point on the model's surface to a world-space anchor (a mouse spring).
/// Several may act on one model.
#[derive(Reflect, Clone, Copy, Debug, PartialEq)]
pub struct Spring {
    /// Material latitude u of the grabbed surface point.
    pub u: f64,
    /// Material longitude v of the grabbed surface point.
    pub v: f64,
    /// World-space anchor.
    pub anchor: DVec3,
    /// Spring constant (force per unit length).
    pub stiffness: f64,
    /// The spring reshapes the superquadric too (the paper's Fig. 1 pull: a, a1..a3, ε1, ε2 and
    /// the tapering and bending move under it). False (a grab): while the spring acts, the
    /// model's global shape is held, so it moves, turns and dents its membrane where it is
    /// pulled, and a pull at one point cannot stretch it into a slab or square its section.
    pub reshape: bool,
}

impl Spring {
    /// Spring constant of a mouse spring per unit of the membrane stiffness w1 (see
    /// [`Self::mouse_stiffness`]).
    pub const GAIN: f64 = 2.0;
    /// Longest a mouse spring may stretch, in units of the model's scale a.
    pub const MAX_STRETCH: f64 = 1.5;

    /// The constant of a mouse spring on a model: [`Self::GAIN`] × (w1 + w0 a²). A point force
    /// f raises a spike of height about f / w1 in the membrane (and f / (w0 a²) where w0
    /// dominates), so a spring scaled to the stiffness deforms every model visibly without
    /// tearing it into a spike that the global DOFs then chase.
    pub fn mouse_stiffness(settings: &ModelSettings, a: f64) -> f64 {
        Self::GAIN * (settings.w1 + settings.w0 * a * a).max(1e-6)
    }

    /// A grab ([`Self::reshape`] false) of constant `stiffness` on the node nearest `hit` (world
    /// space) of a model whose world node positions are `node_x`, anchored at that node.
    pub fn grab(tess: &Tessellation, node_x: &[DVec3], hit: DVec3, stiffness: f64) -> Option<Self> {
        if node_x.len() != tess.node_count() || !hit.is_finite() || !(stiffness > 0.0) {
            return None;
        }
        let node = (0..node_x.len()).min_by(|&i, &j| {
            node_x[i]
                .distance_squared(hit)
                .total_cmp(&node_x[j].distance_squared(hit))
        })?;
        let [u, v] = tess.uv[node];
        Some(Self {
            u,
            v,
            anchor: node_x[node],
            stiffness,
            reshape: false,
        })
    }

    /// Moves the anchor to `target`, but no further than [`Self::MAX_STRETCH`] a from the grabbed
    /// surface point: the force stays below GAIN · MAX_STRETCH · a³ however far the cursor goes,
    /// so no drag can blow the simulation up.
    pub fn pull_towards(&mut self, tess: &Tessellation, node_x: &[DVec3], target: DVec3, a: f64) {
        if node_x.len() != tess.node_count() || !target.is_finite() {
            return;
        }
        let at = tess.locate(self.u, self.v).interpolate(|k| node_x[k]);
        self.anchor = at + (target - at).clamp_length_max(Self::MAX_STRETCH * a.max(0.0));
    }
}

/// User springs acting on a model. While one that does not [`Spring::reshape`] acts, the model's
/// global shape is held.
#[derive(Component, Reflect, Clone, Debug, Default, PartialEq)]
#[reflect(Component, Default, Debug, PartialEq)]
pub struct SpringForces(pub Vec<Spring>);

/// A point-to-point joint between the surfaces of two models ([`crate::model::joint`]): put it
/// on an entity of its own. Each step it adds its constraint force (multiplier plus stabilising
/// spring) to both models' global coordinates; `joint.multiplier` is the force it transmits to
/// `a`, and `gap` the distance between its ends at the last step. A joint whose models are gone
/// or not yet tessellated does nothing.
#[derive(Component, Clone, Debug, PartialEq)]
pub struct PartJoint {
    /// Model a.
    pub a: Entity,
    /// Model b.
    pub b: Entity,
    /// The ends, the stabilising constant and the multiplier.
    pub joint: Joint,
    /// x_b − x_a at the last step.
    pub gap: DVec3,
}

impl PartJoint {
    /// A joint between `a` at `end_a` and `b` at `end_b`, with the default constant
    /// ([`PartJoint::STIFFNESS`]).
    pub fn new(a: Entity, end_a: JointEnd, b: Entity, end_b: JointEnd) -> Self {
        Self {
            a,
            b,
            joint: Joint::new(end_a, end_b, Self::STIFFNESS),
            gap: DVec3::ZERO,
        }
    }

    /// The default stabilising constant κ ([`Joint::DEFAULT_STIFFNESS`]).
    pub const STIFFNESS: f64 = Joint::DEFAULT_STIFFNESS;
}
