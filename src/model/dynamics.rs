//! First-order Lagrangian dynamics C q̇ + K q = f_q (eq. 14) integrated by explicit Euler (eq. 15).
//!
//! # State
//! q = (q_c, q_θ, q_s, q_d): translation c, unit quaternion [s, v], the superquadric parameters
//! (a, a1, a2, a3, ε1, ε2) and one displacement d_i per FEM node, all in [`ModelState`]. A node's
//! world position is x_i = c + R (s_i + d_i) (eqs. 2, 3).
//!
//! # Forces
//! Every applied force reaches the model as a point force on the surface; [`NodalForces`] holds
//! them spread to the nodes with the shape functions N_i (eq. 22), together with each node's
//! *stiffness weight* κ_i: the spring constant of the forces acting there, Σ_p w_p N_i(u_p).
//! The generalized forces (eq. 33) are then sums over nodes:
//! f_c = Σ F_i, f_θ = Σ B_iᵀ F_i = Gᵀ Σ p_i × RᵀF_i, f_s = Σ J_iᵀ RᵀF_i, f_d,i = RᵀF_i.
//!
//! # Damping: the choice that makes motion independent of tessellation and data count
//! The paper's C is γ ∫ LᵀL du (eq. 28) with a damping density γ. We keep that form but take the
//! integral over the points where forces act, weighted by their stiffness, and split it in two blocks:
//!
//! * **Global block** (13 × 13): C_g = γ_g (Σ_i κ_i L_iᵀ L_i + λ diag(·) + ρ κ̄ D), with
//!   L_i = [I, B_i, R J_i] (eq. 11). Both C_g and f_g are sums over the same force points, so
//!   C_g⁻¹ f_g — and with it the motion — does not change when the points are duplicated or the
//!   surface is tessellated more finely. For range springs (f = w (r − x)) the step
//!   Δt C_g⁻¹ f_g is a damped Gauss–Newton (Levenberg–Marquardt) step on the spring energy with
//!   step fraction Δt/γ_g. λ (Marquardt) and ρ (a ridge scaled to the model size ℓ = a through
//!   D = diag(1, ℓ², 1, ℓ²) per column kind) keep C_g invertible along the two gauge
//!   directions: the quaternion's length (G q_θ = 0) and a·a_i's redundancy.
//! * **Local block** (diagonal, lumped): C_d,i = γ_d A_i with A_i = ∫ N_i du the nodal area in
//!   material coordinates. K q is the discretisation of −w1 Δd + w0 d times A_i, and range springs
//!   give each of the m points the weight β |Ω| / m (see `forces::range`), a force density that
//!   does not depend on m; so q̇_d approximates the same continuous flow for every k and m.
//!
//! # Stability
//! The local update is Euler on d with the membrane K explicit and the data springs κ_i implicit:
//! the springs, linearised about the start of the step (exact for springs attached to nodes), are
//! diagonal, so each node takes d_i ← d_i + h (f_i − κ_i (d_i − d_i⁰) − (K d)_i) / (γ_d A_i + h κ_i)
//! at no extra cost. Stiff data springs then cost nothing in stability: the step is stable when
//! Δt < Δt_crit = 2 γ_d / max_i (Σ_j |K_ij| / A_i) (Gershgorin bound on the largest eigenvalue of
//! C_d⁻¹K), a property of the membrane and the tessellation alone (with explicit springs, strong
//! image forces made the doll's parts take up to 64 sub-steps a step). [`step`] checks the bound
//! each step and sub-steps the local update instead of blowing up; beyond [`MAX_SUBSTEPS`] it
//! clamps the step and says so in the [`StepReport`]. Rest states are those of explicit Euler.
//! The global update is limited to a trust region (a quarter of the model size, a quarter radian,
//! a quarter of each aspect and exponent per step).

use super::deform::{GlobalDeformation, NUM_DEFORM};
use super::fem::{CgScratch, ElementPoint, GridPowers, Tessellation};
use super::frame::{g_matrix, quat_from_paper, quat_to_paper, rotation_matrix};
use super::linalg::cholesky_solve;
use super::simd::with_avx2;
use super::superquadric::{NUM_SHAPE, SignedPowers, SuperquadricParams, Trig, shape_from_powers};
use glam::{DMat3, DQuat, DVec3};

mod global;
mod step;
use global::*;
pub use global::{generalized_global_forces, generalized_local_forces};
pub use step::{IMPLICIT_LOCAL_MAX_ITERATIONS, IMPLICIT_LOCAL_TOLERANCE, step, step_prepared};
#[cfg(test)]
pub(crate) mod tests;

/// Number of global degrees of freedom: q_c (3) + q_θ (4) + q_s (6) + q_T (4, tapering and
/// bending: [`super::deform`], frozen unless [`FreeDofs::taper`] / [`FreeDofs::bend`]).
pub const NUM_GLOBAL: usize = 13 + NUM_DEFORM;
/// Index of the first deformation coordinate q_T in the global vector.
const DEFORM_START: usize = 7 + NUM_SHAPE;
/// Most local sub-steps one [`step`] takes before it clamps Δt.
pub const MAX_SUBSTEPS: u32 = 64;

/// The full state q of one deformable superquadric.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelState {
    /// q_c: the model frame's origin c in world space.
    pub translation: DVec3,
    /// q_θ: the model frame's orientation as a unit quaternion.
    pub rotation: DQuat,
    /// q_s: the global deformation parameters.
    pub shape: SuperquadricParams,
    /// q_T: tapering and bending applied to the superquadric before the local displacement
    /// ([`super::deform`]); the identity for the paper's model.
    pub deformation: GlobalDeformation,
    /// q_d: the local displacement d_i of every node, in the model frame.
    pub displacement: Vec<DVec3>,
}

impl ModelState {
    /// A model with zero local displacement on `tess`.
    pub fn new(
        tess: &Tessellation,
        translation: DVec3,
        rotation: DQuat,
        shape: SuperquadricParams,
    ) -> Self {
        Self {
            translation,
            rotation,
            shape,
            deformation: GlobalDeformation::IDENTITY,
            displacement: vec![DVec3::ZERO; tess.node_count()],
        }
    }

    /// True when every coordinate is finite.
    pub fn is_finite(&self) -> bool {
        self.translation.is_finite()
            && self.rotation.is_finite()
            && self.shape.is_finite()
            && self.deformation.is_finite()
            && all_finite(&self.displacement)
    }

    /// The continuous surface of this state ([`ModelSurface`]).
    pub fn surface(&self) -> ModelSurface<'_> {
        ModelSurface::new(
            self.translation,
            self.rotation,
            self.shape,
            self.deformation,
            &self.displacement,
        )
    }

    /// World positions x_i = c + R p_i of every node (eq. 2).
    pub fn node_positions(&self, tess: &Tessellation, out: &mut Vec<DVec3>) {
        node_positions(
            tess,
            self.translation,
            self.rotation,
            &self.shape,
            &self.deformation,
            &self.displacement,
            out,
        );
    }
}

/// True when every coordinate of `v` is finite. A fold over the flat coordinates without an
/// early exit, so that it vectorises: a step checks every displacement it writes.
fn all_finite(v: &[DVec3]) -> bool {
    bytemuck::cast_slice::<DVec3, f64>(v)
        .iter()
        .fold(true, |ok, x| ok & x.is_finite())
}

/// The model's continuous surface x(u, v) = c + R (T(s(u, v)) + d(u, v)) (eqs. 2, 3): the exact
/// superquadric s of eq. (4) under the global deformation T, plus the local displacement d
/// interpolated by the shape functions (eq. 7). It agrees with the nodes' positions at the
/// nodes; between them it is the paper's surface, where the triangles of the mesh are chords of
/// it. Migrating points of influence sit on it (`forces::range`).
#[derive(Clone, Copy, Debug)]
pub struct ModelSurface<'a> {
    translation: DVec3,
    rotation: DMat3,
    shape: SuperquadricParams,
    deformation: GlobalDeformation,
    displacement: &'a [DVec3],
}

impl<'a> ModelSurface<'a> {
    /// The surface of a model with these parts (as [`node_positions`] takes them).
    pub fn new(
        translation: DVec3,
        rotation: DQuat,
        shape: SuperquadricParams,
        deformation: GlobalDeformation,
        displacement: &'a [DVec3],
    ) -> Self {
        Self {
            translation,
            rotation: rotation_matrix(rotation),
            shape,
            deformation,
            displacement,
        }
    }

    /// x(u, v) at material coordinates (u, v) that lie at `at` of their element.
    pub fn at(&self, u: f64, v: f64, at: &ElementPoint) -> DVec3 {
        self.at_terms(&Trig::new(u, v), at)
    }

    /// [`Self::at`] from the [`Trig`] terms of (u, v), which a caller may keep across steps: the
    /// surface then costs four `exp` ([`SignedPowers::from_logs`]) and no sine or cosine.
    pub fn at_terms(&self, t: &Trig, at: &ElementPoint) -> DVec3 {
        let mut s = shape_from_powers(&self.shape, &SignedPowers::from_logs(&self.shape, t));
        if !self.deformation.is_identity() {
            s = self.deformation.apply(s, self.shape.semi_axes().z);
        }
        self.placed(s, at)
    }

    /// The local displacement d_k of node k (zero past the end of the displacements).
    fn displacement(&self, k: usize) -> DVec3 {
        self.displacement.get(k).copied().unwrap_or_default()
    }

    /// c + R (t + d(u)) for the deformed superquadric point t at `at`.
    fn placed(&self, t: DVec3, at: &ElementPoint) -> DVec3 {
        self.translation + self.rotation * (t + at.interpolate(|k| self.displacement(k)))
    }

    /// x(u, v) and its tangents ∂x/∂u, ∂x/∂v, or the tangents `None` on the coordinate lines
    /// through the axes (cos or sin of u or v zero), where the signed powers' derivatives are
    /// infinite or undefined for exponents below 1. From eq. (4): d/du sgn(c)|c|^ε with c = cos u
    /// is −ε (sin u / cos u) C_u^ε, and likewise for the other three powers; T's Jacobian and the
    /// shape functions' derivatives carry them through the deformation and the displacement.
    pub fn with_tangents(
        &self,
        u: f64,
        v: f64,
        at: &ElementPoint,
    ) -> (DVec3, Option<(DVec3, DVec3)>) {
        self.with_tangents_terms(&Trig::new(u, v), at)
    }

    /// [`Self::with_tangents`] from the [`Trig`] terms of (u, v) (see [`Self::at_terms`]).
    pub fn with_tangents_terms(
        &self,
        t: &Trig,
        at: &ElementPoint,
    ) -> (DVec3, Option<(DVec3, DVec3)>) {
        let q = &self.shape;
        let p = SignedPowers::from_logs(q, t);
        let s = shape_from_powers(q, &p);
        let (cu, su, cv, sv) = (t.cu, t.su, t.cv, t.sv);
        let regular = [cu, su, cv, sv].iter().all(|t| t.abs() >= 1e-9);
        let scaled = q.a * DVec3::new(q.a1, q.a2, q.a3);
        let ds = regular.then(|| {
            let dcu = -q.e1 * su / cu * p.cu;
            let dsu = q.e1 * cu / su * p.su;
            let dcv = -q.e2 * sv / cv * p.cv;
            let dsv = q.e2 * cv / sv * p.sv;
            (
                scaled * DVec3::new(dcu * p.cv, dcu * p.sv, dsu),
                scaled * DVec3::new(p.cu * dcv, p.cu * dsv, 0.0),
            )
        });
        let (t, ds) = if self.deformation.is_identity() {
            (s, ds)
        } else {
            let jac = self.deformation.jacobian(s, q.semi_axes().z);
            (
                jac.value,
                ds.map(|(a, b)| (jac.d_point * a, jac.d_point * b)),
            )
        };
        let tangents = ds.map(|(a, b)| {
            let derivative = |dn: &[f64; 4]| -> DVec3 {
                (0..4)
                    .map(|k| dn[k] * self.displacement(at.nodes[k] as usize))
                    .sum()
            };
            (
                self.rotation * (a + derivative(&at.du)),
                self.rotation * (b + derivative(&at.dv)),
            )
        });
        (self.placed(t, at), tangents)
    }
}

/// World positions x_i = c + R (T(s_i) + d_i) of every node (eqs. 2, 3, with the global
/// deformation T of [`super::deform`]) from the parts of a state. Displacements missing at the
/// end of `displacement` count as zero.
pub fn node_positions(
    tess: &Tessellation,
    translation: DVec3,
    rotation: DQuat,
    shape_q: &SuperquadricParams,
    deformation: &GlobalDeformation,
    displacement: &[DVec3],
    out: &mut Vec<DVec3>,
) {
    let r = rotation_matrix(rotation);
    out.clear();
    for_each_model_point(
        tess,
        shape_q,
        deformation,
        &mut GridPowers::default(),
        displacement,
        |_, p| out.push(translation + r * p),
    );
}

/// Calls `visit(i, p_i)` with the model-frame point p_i = T(s_i) + d_i of every node in index
/// order, computing the signed powers once per ring and longitude into `grid`. Displacements
/// missing at the end of `displacement` count as zero.
fn for_each_model_point(
    tess: &Tessellation,
    q: &SuperquadricParams,
    deformation: &GlobalDeformation,
    grid: &mut GridPowers,
    displacement: &[DVec3],
    visit: impl FnMut(usize, DVec3),
) {
    tess.grid_powers(q, grid);
    let axes = q.semi_axes();
    let grid = &*grid;
    // One loop per case, so that the paper's model pays nothing for T.
    if deformation.is_identity() {
        visit_points(tess, grid, axes, displacement, |s| s, visit);
    } else {
        visit_points(
            tess,
            grid,
            axes,
            displacement,
            |s| deformation.apply(s, axes.z),
            visit,
        );
    }
}

/// The loop of [`for_each_model_point`], with the deformation `deform` applied to each s_i.
#[inline(always)]
fn visit_points(
    tess: &Tessellation,
    grid: &GridPowers,
    axes: DVec3,
    displacement: &[DVec3],
    deform: impl Fn(DVec3) -> DVec3,
    mut visit: impl FnMut(usize, DVec3),
) {
    // Ring by ring over slices (the poles are rings of one node): no per-node grid walk, and
    // the displacements read by slice where they are all present.
    for ring in 0..tess.k + 2 {
        let (nodes, _) = tess.grid_ring(ring);
        let [cu, su] = grid.rings[ring];
        let longitudes = grid.ring_longitudes(ring);
        let s = |[cv, sv]: &[f64; 2]| deform(axes * DVec3::new(cu * cv, cu * sv, su));
        match displacement.get(nodes.clone()) {
            Some(d) => {
                for ((i, lon), d) in nodes.zip(longitudes).zip(d) {
                    visit(i, s(lon) + *d);
                }
            }
            None => {
                for (i, lon) in nodes.zip(longitudes) {
                    visit(i, s(lon) + displacement.get(i).copied().unwrap_or_default());
                }
            }
        }
    }
}

/// Point forces spread to the nodes, with the stiffness weight κ_i of the springs among them.
///
/// `force`/`stiffness` act on every degree of freedom. `shape_force`/`shape_stiffness` act on the
/// global DOFs (c, θ, q_s) only: forces that should place and shape the superquadric but not bend
/// the membrane, such as the weak model-to-data springs of `forces::range`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NodalForces {
    /// World-space force F_i on each node.
    pub force: Vec<DVec3>,
    /// Stiffness weight κ_i ≥ 0 of each node (0 where no spring acts).
    pub stiffness: Vec<f64>,
    /// World-space force on each node that acts on the global DOFs only.
    pub shape_force: Vec<DVec3>,
    /// Stiffness weight of the springs in `shape_force`.
    pub shape_stiffness: Vec<f64>,
    /// Stiffness of point-to-plane springs at each node: springs whose force (in `shape_force`)
    /// acts along the surface normal `plane_normal` only. They add ρ_i (L_iᵀ n_i)(L_iᵀ n_i)ᵀ to
    /// the global damping block instead of the isotropic κ_i L_iᵀ L_i, so that the global step is
    /// a Gauss–Newton step on the point-to-plane distances (see `forces::range`).
    pub plane_stiffness: Vec<f64>,
    /// Unit world-space surface normal n_i where `plane_stiffness` is non-zero.
    pub plane_normal: Vec<DVec3>,
}

impl NodalForces {
    /// Zero forces on `n` nodes.
    pub fn new(n: usize) -> Self {
        let mut f = Self::default();
        f.clear(n);
        f
    }

    /// Whether any point-to-plane spring acts: some ρ_i in `plane_stiffness` is non-zero.
    pub fn has_plane_springs(&self) -> bool {
        self.plane_stiffness.iter().any(|&rho| rho != 0.0)
    }

    /// Resets to zero forces on `n` nodes, keeping the allocation.
    pub fn clear(&mut self, n: usize) {
        for v in [
            &mut self.force,
            &mut self.shape_force,
            &mut self.plane_normal,
        ] {
            v.clear();
            v.resize(n, DVec3::ZERO);
        }
        for v in [
            &mut self.stiffness,
            &mut self.shape_stiffness,
            &mut self.plane_stiffness,
        ] {
            v.clear();
            v.resize(n, 0.0);
        }
    }

    /// Adds a world force `f` acting at a point inside an element, spread as f_i = N_i f (eq. 22),
    /// with spring stiffness `kappa` spread the same way.
    #[inline]
    pub fn add(&mut self, at: &ElementPoint, f: DVec3, kappa: f64) {
        if at.weights[0] == 1.0 {
            let n = at.nodes[0] as usize;
            self.force[n] += f;
            self.stiffness[n] += kappa;
            return;
        }
        for i in 0..4 {
            let w = at.weights[i];
            if w != 0.0 {
                let n = at.nodes[i] as usize;
                self.force[n] += w * f;
                self.stiffness[n] += w * kappa;
            }
        }
    }
}

/// Which degrees of freedom move. Frozen ones keep their value (the pestle experiment fixes ε).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FreeDofs {
    /// q_c moves.
    pub translation: bool,
    /// q_θ moves.
    pub rotation: bool,
    /// Each of (a, a1, a2, a3, ε1, ε2) moves.
    pub shape: [bool; NUM_SHAPE],
    /// q_d moves (false: a pure superquadric, "global only").
    pub local: bool,
    /// Image-plane motion only: the model translates in world x–y and turns about world z; the
    /// depth c_z and the out-of-plane turns are held (a monocular image does not observe them).
    #[serde(default)]
    pub planar: bool,
    /// The tapering coordinates (t_x, t_y) of [`super::deform`] move (beyond the paper).
    #[serde(default)]
    pub taper: bool,
    /// The bending coordinates (b_x, b_y) of [`super::deform`] move (beyond the paper).
    #[serde(default)]
    pub bend: bool,
}

impl Default for FreeDofs {
    fn default() -> Self {
        Self {
            translation: true,
            rotation: true,
            shape: [true; NUM_SHAPE],
            local: true,
            planar: false,
            taper: false,
            bend: false,
        }
    }
}

impl FreeDofs {
    /// Everything free except: the local DOFs unless `local`; with `planar`, motion in the
    /// image plane only, and the depth ratio a2 and ε2 held (one image cannot observe them: the
    /// outline seen along the model's y axis is its x–z section, |x/a1|^(2/ε1) + |z/a3|^(2/ε1)
    /// = 1, in which neither appears); with `fix_epsilon`, ε1 and ε2 held.
    pub fn with(local: bool, planar: bool, fix_epsilon: bool) -> Self {
        let mut shape = [true; NUM_SHAPE];
        shape[2] = !planar;
        shape[4] = !fix_epsilon;
        shape[5] = !fix_epsilon && !planar;
        Self {
            shape,
            local,
            planar,
            ..Self::default()
        }
    }

    /// These freedoms with the switches beyond the paper: `fix_shape` holds all of q_s (a rigid
    /// superquadric), `taper` and `bend` free q_T ([`super::deform`]).
    pub fn beyond_the_paper(mut self, fix_shape: bool, taper: bool, bend: bool) -> Self {
        if fix_shape {
            self.shape = [false; NUM_SHAPE];
        }
        self.taper = taper;
        self.bend = bend;
        self
    }
}

/// Physical and numerical parameters of the first-order dynamics.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DynamicsParams {
    /// Membrane stiffness w0 on |d|² (eq. 13).
    pub w0: f64,
    /// Membrane stiffness w1 on |∂d/∂u|² + |∂d/∂v|² (eq. 13).
    pub w1: f64,
    /// Time step Δt (eq. 15).
    pub dt: f64,
    /// Global damping density γ_g; Δt/γ_g is the Gauss–Newton step fraction.
    pub gamma_global: f64,
    /// Local damping density γ_d.
    pub gamma_local: f64,
    /// Marquardt factor λ added to the diagonal of the global damping block.
    pub marquardt: f64,
    /// Ridge ρ that keeps the global damping block invertible when few forces act.
    pub ridge: f64,
    /// Which degrees of freedom move.
    pub free: FreeDofs,
    /// Take the local block of eq. (15) as one backward-Euler step, (γ_d A/Δt + κ + K) d⁺ =
    /// (γ_d A/Δt + κ) d + f, solved by conjugate gradients ([`Tessellation::solve_shifted`]) after the global
    /// update, with the nodal forces moved to the new pose (F_i − κ_i Δx_i, exact for springs on
    /// nodes): stable at any Δt, and with a small γ_d close to the membrane's rest in one step
    /// (beyond the paper). Taken after the global update, not beside it, because the two blocks
    /// answer the same spring forces: side by side (as the explicit update does) a large local
    /// step would add to the global one and overshoot. False: the paper's explicit update,
    /// sub-stepped within its stability bound. The first-order [`step`] only; the second-order
    /// dynamics of `inertia` keep their explicit update.
    pub implicit_local: bool,
}

impl Default for DynamicsParams {
    /// w0 = 1e-3, w1 = 0.1 (the doll experiment's values), Δt = 0.05, γ_g = 0.1 (so the global
    /// step is half a Gauss–Newton step), γ_d = 1.
    fn default() -> Self {
        Self {
            w0: 1e-3,
            w1: 0.1,
            dt: 0.05,
            gamma_global: 0.1,
            gamma_local: 1.0,
            marquardt: 1e-3,
            ridge: 1e-6,
            free: FreeDofs::default(),
            implicit_local: false,
        }
    }
}

/// What one [`step`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepReport {
    /// Local sub-steps taken (1 when Δt is within the stability bound).
    pub substeps: u32,
    /// The stability bound Δt_crit of the local update this step (∞ when nothing is stiff).
    pub dt_critical: f64,
    /// True when Δt was beyond [`MAX_SUBSTEPS`] × Δt_crit and was clamped.
    pub clamped: bool,
    /// True when the global increment was cut back to the trust region.
    pub trust_limited: bool,
    /// Conjugate-gradient iterations of the implicit local solve
    /// ([`DynamicsParams::implicit_local`]); 0 for the explicit update.
    pub local_iterations: u32,
}

/// Why a step was refused; the state is left unchanged.
#[derive(Clone, Debug, PartialEq)]
pub enum StepError {
    /// A force or the computed update was not finite; names what.
    NonFinite(&'static str),
    /// A parameter is out of range; says which and what it must be.
    Invalid(&'static str),
}

impl std::fmt::Display for StepError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            StepError::NonFinite(what) => write!(f, "non-finite {what}; the step was not applied"),
            StepError::Invalid(what) => write!(f, "{what}; the step was not applied"),
        }
    }
}

impl std::error::Error for StepError {}

/// Reusable buffers and caches for [`step`], so a step allocates nothing.
#[derive(Clone, Debug, Default)]
pub struct Workspace {
    grid: GridPowers,
    points: Vec<DVec3>,
    world: Vec<DVec3>,
    kd: Vec<DVec3>,
    local_force: Vec<DVec3>,
    new_d: Vec<DVec3>,
    /// Each node's sub-step factor h / (γ A_i + h κ_i), so a sub-step divides nothing.
    substep_scale: Vec<f64>,
    /// max_i Σ_j |K_ij| / A_i (Gershgorin) for the stiffness weights and node count of the key.
    max_rate: f64,
    max_rate_key: Option<(f64, f64, usize)>,
    k_diagonal: Vec<f64>,
    k_diagonal_key: Option<(f64, f64, usize)>,
    shift: Vec<f64>,
    cg: CgScratch,
}

impl Workspace {
    /// Computes, once per step, the signed powers of `state`'s shape on the grid, the model-frame
    /// points p_i = s_i + d_i and the world positions x_i = c + R p_i (eqs. 2, 3), and returns the
    /// world positions (also [`Workspace::world_positions`] until the next call).
    pub fn prepare(&mut self, tess: &Tessellation, state: &ModelState) -> &[DVec3] {
        with_avx2!({ self.prepare_body(tess, state) });
        &self.world
    }

    /// [`Self::prepare`]'s body, inlined into both of its builds.
    #[inline(always)]
    fn prepare_body(&mut self, tess: &Tessellation, state: &ModelState) {
        let r = rotation_matrix(state.rotation);
        let c = state.translation;
        self.points.clear();
        self.world.clear();
        let points = &mut self.points;
        for_each_model_point(
            tess,
            &state.shape,
            &state.deformation,
            &mut self.grid,
            &state.displacement,
            |_, p| points.push(p),
        );
        // The world positions in a pass of their own: a loop that pushed both took 6 % longer
        // at 5043 nodes.
        self.world.extend(self.points.iter().map(|p| c + r * *p));
    }

    /// The world node positions of the state last given to [`Workspace::prepare`].
    pub fn world_positions(&self) -> &[DVec3] {
        &self.world
    }

    /// The largest eigenvalue bound of the lumped membrane A⁻¹K, max_i Σ_j |K_ij| / A_i,
    /// computed once per tessellation and stiffness weights.
    fn max_rate(&mut self, tess: &Tessellation, w0: f64, w1: f64) -> f64 {
        let key = (w0, w1, tess.node_count());
        if self.max_rate_key != Some(key) {
            let rows = tess.stiffness_row_bounds(w0, w1);
            self.max_rate = rows
                .iter()
                .zip(&tess.node_area)
                .map(|(r, a)| r * (1.0 / a))
                .fold(0.0_f64, f64::max);
            self.max_rate_key = Some(key);
        }
        self.max_rate
    }
}
