//! The components a deformable superquadric is made of.
//!
//! Spawning `(GlobalShape { .. }, RigidState { .. })` makes a complete model: the other components
//! are required components with defaults. The state q of the paper is split as the users asked:
//! [`RigidState`] (q_c, q_θ), [`GlobalShape`] (q_s), [`LocalDofs`] (q_d), on the tessellation of
//! [`FemMesh`]. Every one of them may be changed from outside (an inspector); the next step reads
//! them as they are. What pulls on a model from outside (range data, an image, springs, joints)
//! is in components of its own ([`RangeData`], [`ImageData`], [`SpringForces`], [`PartJoint`]).

use crate::model::deform::GlobalDeformation;
use crate::model::dynamics::{
    DynamicsParams, FreeDofs, ModelState, ModelSurface, NodalForces, Workspace,
};
use crate::model::fem::Tessellation;
use crate::model::fit::FitOptions;
use crate::model::forces::image::ImageScratch;
use crate::model::inertia::{InertiaParams, InertiaWorkspace, Velocity};
use crate::model::superquadric::SuperquadricParams;
use bevy::math::{DQuat, DVec3};
use bevy::prelude::*;
use std::sync::Arc;

mod forces;
pub use forces::*;

/// The global deformation parameters q_s = (a, a1, a2, a3, ε1, ε2) of eq. (5), and the tapering
/// and bending q_T of [`crate::model::deform`] (zero for the paper's model).
#[derive(Component, Reflect, Clone, Copy, Debug, PartialEq)]
#[reflect(Component, Default, Debug, PartialEq)]
#[cfg_attr(feature = "serialize", derive(serde::Serialize, serde::Deserialize))]
#[require(
    RigidState,
    LocalDofs,
    FemMesh,
    ModelSettings,
    SimControl,
    Scratch,
    super::messages::Reported
)]
pub struct GlobalShape {
    /// Scale a.
    pub a: f64,
    /// Aspect ratio along x, 0 < a1 ≤ 1.
    pub a1: f64,
    /// Aspect ratio along y, 0 < a2 ≤ 1.
    pub a2: f64,
    /// Aspect ratio along z, 0 < a3 ≤ 1.
    pub a3: f64,
    /// Squareness ε1 (latitude profile).
    pub e1: f64,
    /// Squareness ε2 (longitude cross-section).
    pub e2: f64,
    /// Tapering (t_x, t_y) along z, each in [−1, 1] ([`GlobalDeformation::taper`]).
    #[cfg_attr(feature = "serialize", serde(default))]
    pub taper: [f64; 2],
    /// Bending (b_x, b_y): direction and angle of each end, radians ([`GlobalDeformation::bend`]).
    #[cfg_attr(feature = "serialize", serde(default))]
    pub bend: [f64; 2],
}

impl GlobalShape {
    /// The shape q_s with the tapering and bending q_T.
    pub fn new(shape: SuperquadricParams, deformation: GlobalDeformation) -> Self {
        Self {
            taper: deformation.taper,
            bend: deformation.bend,
            ..shape.into()
        }
    }

    /// The tapering and bending q_T.
    pub fn deformation(&self) -> GlobalDeformation {
        GlobalDeformation {
            taper: self.taper,
            bend: self.bend,
        }
    }
}

impl Default for GlobalShape {
    /// The unit sphere.
    fn default() -> Self {
        SuperquadricParams::default().into()
    }
}

impl From<SuperquadricParams> for GlobalShape {
    fn from(q: SuperquadricParams) -> Self {
        Self {
            a: q.a,
            a1: q.a1,
            a2: q.a2,
            a3: q.a3,
            e1: q.e1,
            e2: q.e2,
            taper: [0.0; 2],
            bend: [0.0; 2],
        }
    }
}

impl From<GlobalShape> for SuperquadricParams {
    fn from(g: GlobalShape) -> Self {
        Self {
            a: g.a,
            a1: g.a1,
            a2: g.a2,
            a3: g.a3,
            e1: g.e1,
            e2: g.e2,
        }
    }
}

/// The rigid coordinates q_c (translation c) and q_θ (unit quaternion) of the model frame, in
/// world space (eq. 2). Write-back copies them into the entity's [`Transform`].
#[derive(Component, Reflect, Clone, Copy, Debug, PartialEq)]
#[reflect(Component, Default, Debug, PartialEq)]
#[cfg_attr(feature = "serialize", derive(serde::Serialize, serde::Deserialize))]
#[require(Transform)]
pub struct RigidState {
    /// q_c: the model centre in world space.
    pub translation: DVec3,
    /// q_θ: the model frame's orientation.
    pub rotation: DQuat,
}

impl Default for RigidState {
    fn default() -> Self {
        Self {
            translation: DVec3::ZERO,
            rotation: DQuat::IDENTITY,
        }
    }
}

/// The local displacement d_i of every node, in the model frame (q_d, eq. 7). Empty or wrongly
/// sized vectors are reset to zero displacement on the next step.
#[derive(Component, Reflect, Clone, Debug, Default, PartialEq)]
#[reflect(Component, Default, Debug, PartialEq)]
#[cfg_attr(feature = "serialize", derive(serde::Serialize, serde::Deserialize))]
pub struct LocalDofs {
    /// One displacement per node of the model's [`FemMesh`].
    pub displacement: Vec<DVec3>,
}

/// The tessellation (k rings × k longitudes + 2 poles) and what the element-by-element stiffness
/// needs. Models of the same k share one [`Tessellation`] through the [`FemMeshCache`].
#[derive(Component, Reflect, Clone, Debug)]
#[reflect(Component, Default, Debug)]
pub struct FemMesh {
    /// Rings and longitudes; change it and the model is re-tessellated (its local DOFs carried
    /// onto the new mesh, [`Tessellation::prolong`]).
    pub k: usize,
    /// The tessellation for `k`, filled in on the first step.
    #[reflect(ignore)]
    pub tessellation: Option<Arc<Tessellation>>,
}

impl Default for FemMesh {
    /// k = 31: the paper's 963 nodes.
    fn default() -> Self {
        Self::new(31)
    }
}

impl FemMesh {
    /// A mesh of k rings × k longitudes, tessellated on first use.
    pub fn new(k: usize) -> Self {
        Self {
            k,
            tessellation: None,
        }
    }

    /// The tessellation, if it is built and matches `k`.
    pub fn get(&self) -> Option<&Arc<Tessellation>> {
        self.tessellation
            .as_ref()
            .filter(|t| t.k == self.k.max(crate::model::fem::MIN_K))
    }
}

/// Shared tessellations by k, so that models of the same resolution share one.
#[derive(Resource, Default)]
pub struct FemMeshCache(pub std::collections::HashMap<usize, Arc<Tessellation>>);

impl FemMeshCache {
    /// The tessellation for k, built once.
    pub fn get(&mut self, k: usize) -> Arc<Tessellation> {
        let k = k.max(crate::model::fem::MIN_K);
        self.0
            .entry(k)
            .or_insert_with(|| Arc::new(Tessellation::new(k)))
            .clone()
    }
}

/// How a model simulates: stiffness, damping, time step and reattachment interval.
#[derive(Component, Reflect, Clone, Copy, Debug, PartialEq)]
#[reflect(Component, Default, Debug, PartialEq)]
#[cfg_attr(feature = "serialize", derive(serde::Serialize, serde::Deserialize))]
pub struct ModelSettings {
    /// Membrane stiffness on |d|² (eq. 13).
    pub w0: f64,
    /// Membrane stiffness on |∂d/∂u|² + |∂d/∂v|² (eq. 13).
    pub w1: f64,
    /// Euler time step Δt (eq. 15) per simulation step.
    pub dt: f64,
    /// Global damping density γ_g (Δt/γ_g is the Gauss–Newton step fraction).
    pub gamma_global: f64,
    /// Local damping density γ_d.
    pub gamma_local: f64,
    /// Reattach range points to their nearest nodes every this many steps (the paper: 200).
    pub reassign_every: u32,
    /// Freeze the local DOFs (a pure superquadric).
    pub global_only: bool,
    /// Hold the local DOFs for the first this many steps after spawn or reset, so that the
    /// superquadric captures what it can before the membrane takes the rest (the fitter's
    /// "global first"); 0 lets both move from the start, as in the paper.
    pub hold_local_steps: u64,
    /// Freeze ε1 and ε2 (the paper's image experiments).
    pub fix_epsilon: bool,
    /// Freeze the whole superquadric shape (a, a1..a3, ε1, ε2): the model moves as a rigid
    /// body (with its membrane unless `global_only`), e.g. the links of a jointed figure. The
    /// paper's shape has no stiffness (K_ss = 0), so a free one pulled by a spring or a joint
    /// stretches instead of moving.
    #[cfg_attr(feature = "serialize", serde(default))]
    pub fix_shape: bool,
    /// Freeze the model's translation and rotation: with `fix_shape`, the global DOFs held while
    /// the membrane alone moves (a fit's joint stage on a finer tessellation,
    /// [`FitOptions::k_from_data`]).
    #[cfg_attr(feature = "serialize", serde(default))]
    pub fix_pose: bool,
    /// Image-plane motion only, with the depth ratio a2 held (see
    /// [`FreeDofs::planar`](crate::model::dynamics::FreeDofs::planar)): for parts fitted to an
    /// image.
    #[cfg_attr(feature = "serialize", serde(default))]
    pub planar: bool,
    /// Let the tapering coordinates of [`GlobalShape::taper`] move (beyond the paper).
    #[cfg_attr(feature = "serialize", serde(default))]
    pub taper: bool,
    /// Let the bending coordinates of [`GlobalShape::bend`] move (beyond the paper).
    #[cfg_attr(feature = "serialize", serde(default))]
    pub bend: bool,
    /// Take the membrane's update implicitly, stable at any Δt
    /// ([`DynamicsParams::implicit_local`], beyond the paper). First-order dynamics only: a model
    /// with [`Inertia`] takes the second-order step, which has no implicit membrane, and ignores
    /// this.
    #[cfg_attr(feature = "serialize", serde(default))]
    pub implicit_local: bool,
}

impl Default for ModelSettings {
    /// The fitter's defaults (w0 = 1e-3, w1 = 0.1, Δt = 0.05, γ_d = 1, reattachment every 200
    /// steps) with the interactive global damping of [`DynamicsParams::default`], γ_g = 0.1: half
    /// a Gauss–Newton step per step, so a model dragged or edited moves smoothly instead of
    /// jumping (the fitter takes whole steps, γ_g = Δt).
    fn default() -> Self {
        Self {
            gamma_global: DynamicsParams::default().gamma_global,
            ..Self::from_fit(&FitOptions::default())
        }
    }
}

impl ModelSettings {
    /// The settings a fit with `opts` steps with (its damping, stiffness and time step).
    pub fn from_fit(opts: &FitOptions) -> Self {
        let d = &opts.dynamics;
        Self {
            w0: d.w0,
            w1: d.w1,
            dt: d.dt,
            gamma_global: d.gamma_global,
            gamma_local: d.gamma_local,
            reassign_every: opts.reassign_every,
            global_only: !d.free.local,
            hold_local_steps: 0,
            fix_epsilon: !(d.free.shape[4] || d.free.shape[5]),
            fix_shape: !d.free.shape.iter().any(|&f| f),
            fix_pose: !d.free.translation && !d.free.rotation,
            planar: d.free.planar,
            taper: d.free.taper,
            bend: d.free.bend,
            implicit_local: d.implicit_local,
        }
    }

    /// The core's dynamics parameters at step number `step` (see `hold_local_steps`).
    pub fn dynamics_at(&self, step: u64) -> DynamicsParams {
        let mut d = self.dynamics();
        d.free.local &= step >= self.hold_local_steps;
        d
    }

    /// The core's dynamics parameters.
    pub fn dynamics(&self) -> DynamicsParams {
        let mut free = FreeDofs::with(!self.global_only, self.planar, self.fix_epsilon)
            .beyond_the_paper(self.fix_shape, self.taper, self.bend);
        free.translation &= !self.fix_pose;
        free.rotation &= !self.fix_pose;
        DynamicsParams {
            w0: self.w0,
            w1: self.w1,
            dt: self.dt,
            gamma_global: self.gamma_global,
            gamma_local: self.gamma_local,
            free,
            implicit_local: self.implicit_local,
            ..DynamicsParams::default()
        }
    }
}

/// Second-order dynamics for this model (eq. 12 with mass, [`crate::model::inertia`]) instead of
/// the paper's first-order fitting dynamics: a pulled model swings, overshoots and settles. Add it
/// to a model to switch, remove it to switch back; the integrate stage keeps the velocity here.
/// Reset zeroes it; Δt, w0, w1 and the free DOFs still come from [`ModelSettings`].
#[derive(Component, Clone, Debug, PartialEq)]
pub struct Inertia {
    /// Mass density, the deformation coordinates' own inertia and the damping rate.
    pub params: InertiaParams,
    /// The generalized velocity, sized to the mesh on the next step.
    pub velocity: Velocity,
}

impl Default for Inertia {
    /// [`InertiaParams::default`], at rest.
    fn default() -> Self {
        Self::new(InertiaParams::default())
    }
}

impl Inertia {
    /// At rest, with `params`.
    pub fn new(params: InertiaParams) -> Self {
        Self {
            params,
            velocity: Velocity::default(),
        }
    }
}

/// Pause, single-step and reset, and what the simulation did.
#[derive(Component, Reflect, Clone, Debug, Default, PartialEq)]
#[reflect(Component, Default, Debug, PartialEq)]
pub struct SimControl {
    /// No steps while paused.
    pub paused: bool,
    /// Take this many steps even while paused (single-stepping), then stay paused.
    pub step_requests: u32,
    /// Return to the state the model was spawned with on the next step.
    pub reset_requested: bool,
    /// Steps taken since spawn or reset.
    pub steps: u64,
    /// Set when a step was refused (non-finite); the model no longer steps until reset.
    pub frozen: bool,
    /// Why the model froze.
    pub error: Option<String>,
    /// Sub-steps the last step took for stability (1 when within the bound).
    pub last_substeps: u32,
}

/// Per-model buffers reused every step (forces, workspace, node positions, the image forces'
/// buffers) and the state at spawn for reset.
#[derive(Component, Clone, Debug, Default)]
pub(crate) struct Scratch {
    pub(crate) forces: NodalForces,
    pub(crate) workspace: Workspace,
    pub(crate) node_x: Vec<DVec3>,
    pub(crate) inertia_workspace: InertiaWorkspace,
    pub(crate) image: ImageScratch,
    pub(crate) initial: Option<(RigidState, GlobalShape, LocalDofs)>,
    /// The entity and the change ticks of its [`FemMesh`], [`RigidState`], [`GlobalShape`] and
    /// [`LocalDofs`] ([`StateTicks`]) when `integrate` last left `workspace` prepared for the
    /// state it wrote; `None` when the workspace holds no current positions. While the ticks are
    /// unchanged nothing has written the state since, so the workspace's node positions are the
    /// state's and the systems reuse them instead of computing them again.
    pub(crate) prepared: Option<(Entity, StateTicks)>,
}

/// The change ticks of a model's [`FemMesh`], [`RigidState`], [`GlobalShape`] and [`LocalDofs`]:
/// any write to one of them (a step, a reset, an inspector's edit, a new mesh) changes its tick.
pub(crate) type StateTicks = [bevy::ecs::change_detection::Tick; 4];

/// A model's mesh and state as the systems that only read them see them, with their change
/// ticks (`Scratch::current_positions`).
#[derive(bevy::ecs::query::QueryData)]
pub(crate) struct ModelStateRef {
    /// The model's entity.
    pub entity: Entity,
    /// Its mesh.
    pub fem: Ref<'static, FemMesh>,
    /// Its pose.
    pub rigid: Ref<'static, RigidState>,
    /// Its global shape.
    pub shape: Ref<'static, GlobalShape>,
    /// Its local displacements.
    pub local: Ref<'static, LocalDofs>,
}

impl ModelStateRefItem<'_, '_> {
    /// The components' [`StateTicks`].
    pub(crate) fn ticks(&self) -> StateTicks {
        state_ticks(&self.fem, &self.rigid, &self.shape, &self.local)
    }

    /// The model's continuous surface ([`model_surface`]).
    pub fn surface(&self) -> ModelSurface<'_> {
        model_surface(&self.rigid, &self.shape, &self.local)
    }
}

/// The [`StateTicks`] of a model's components as a system sees them.
pub(crate) fn state_ticks(
    fem: &impl DetectChanges,
    rigid: &impl DetectChanges,
    shape: &impl DetectChanges,
    local: &impl DetectChanges,
) -> StateTicks {
    [
        fem.last_changed(),
        rigid.last_changed(),
        shape.last_changed(),
        local.last_changed(),
    ]
}

impl Scratch {
    /// World node positions as of the last step.
    pub(crate) fn node_positions(&self) -> &[DVec3] {
        &self.node_x
    }

    /// True when `workspace` holds the node positions of `entity`'s state as its components
    /// now stand (`ticks`), on a mesh of `n` nodes.
    pub(crate) fn workspace_current(&self, entity: Entity, ticks: StateTicks, n: usize) -> bool {
        self.prepared == Some((entity, ticks)) && self.workspace.world_positions().len() == n
    }

    /// The world node positions of `model`'s state into the buffer `which` picks: copied from
    /// the workspace when it holds them ([`Self::workspace_current`]), computed by
    /// [`world_positions`] otherwise. Both give the same values to the bit.
    pub(crate) fn current_positions(
        &mut self,
        which: fn(&mut Self) -> &mut Vec<DVec3>,
        model: &ModelStateRefItem,
        tess: &Tessellation,
    ) {
        let current = self.workspace_current(model.entity, model.ticks(), tess.node_count());
        let mut out = std::mem::take(which(self));
        if current {
            out.clear();
            out.extend_from_slice(self.workspace.world_positions());
        } else {
            world_positions(tess, &model.rigid, &model.shape, &model.local, &mut out);
        }
        *which(self) = out;
    }
}

/// The world node positions of `entity`'s model as its components stand now
/// ([`world_positions`]); `None` when it is not a model or its mesh is not built yet.
pub fn model_node_positions(world: &World, entity: Entity) -> Option<Vec<DVec3>> {
    let model = world.get_entity(entity).ok()?;
    let tess = model.get::<FemMesh>()?.get()?;
    let mut out = Vec::new();
    world_positions(tess, model.get()?, model.get()?, model.get()?, &mut out);
    Some(out)
}

/// World node positions x_i = c + R (T(s_i) + d_i) of a model, from its components.
pub fn world_positions(
    tess: &Tessellation,
    rigid: &RigidState,
    shape: &GlobalShape,
    local: &LocalDofs,
    out: &mut Vec<DVec3>,
) {
    crate::model::dynamics::node_positions(
        tess,
        rigid.translation,
        rigid.rotation,
        &(*shape).into(),
        &shape.deformation(),
        &local.displacement,
        out,
    );
}

/// The model's continuous surface ([`ModelSurface`]) from its components.
pub fn model_surface<'a>(
    rigid: &RigidState,
    shape: &GlobalShape,
    local: &'a LocalDofs,
) -> ModelSurface<'a> {
    ModelSurface::new(
        rigid.translation,
        rigid.rotation,
        (*shape).into(),
        shape.deformation(),
        &local.displacement,
    )
}

/// The core's [`ModelState`] of a model's components, as they are.
pub fn model_state(rigid: &RigidState, shape: &GlobalShape, local: &LocalDofs) -> ModelState {
    ModelState {
        translation: rigid.translation,
        rotation: rigid.rotation,
        shape: (*shape).into(),
        deformation: shape.deformation(),
        displacement: local.displacement.clone(),
    }
}

/// Assembles the core's [`ModelState`] from the components (moving the displacement out).
pub(crate) fn take_state(
    rigid: &RigidState,
    shape: &GlobalShape,
    local: &mut LocalDofs,
) -> ModelState {
    ModelState {
        translation: rigid.translation,
        rotation: rigid.rotation,
        shape: (*shape).into(),
        // Brought within bounds here, so that a value set from outside (an inspector) can never
        // turn the surface inside out.
        deformation: shape
            .deformation()
            .clamped(SuperquadricParams::from(*shape).semi_axes()),
        displacement: std::mem::take(&mut local.displacement),
    }
}

/// Writes the core's state back into the components, only where values changed (so change
/// detection stays meaningful).
pub(crate) fn put_state(
    state: ModelState,
    rigid: &mut Mut<RigidState>,
    shape: &mut Mut<GlobalShape>,
    local: &mut Mut<LocalDofs>,
) {
    let new_rigid = RigidState {
        translation: state.translation,
        rotation: state.rotation,
    };
    rigid.set_if_neq(new_rigid);
    shape.set_if_neq(GlobalShape::new(state.shape, state.deformation));
    local.displacement = state.displacement;
}

/// The colour a model is drawn in (otherwise one from a palette is chosen at spawn).
#[derive(Component, Reflect, Clone, Copy, Debug, PartialEq)]
#[reflect(Component, Debug, PartialEq)]
pub struct ModelColor(pub Color);

/// Readable, distinct part colours.
pub const PALETTE: [Color; 8] = [
    Color::srgb(0.90, 0.45, 0.20),
    Color::srgb(0.25, 0.55, 0.90),
    Color::srgb(0.35, 0.75, 0.35),
    Color::srgb(0.85, 0.30, 0.55),
    Color::srgb(0.95, 0.80, 0.25),
    Color::srgb(0.55, 0.40, 0.85),
    Color::srgb(0.30, 0.80, 0.80),
    Color::srgb(0.70, 0.70, 0.70),
];
