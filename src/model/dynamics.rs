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
    /// image plane only and the depth ratio a2 held (one image cannot observe it); with
    /// `fix_epsilon`, ε1 and ε2 held.
    pub fn with(local: bool, planar: bool, fix_epsilon: bool) -> Self {
        let mut shape = [true; NUM_SHAPE];
        shape[2] = !planar;
        if fix_epsilon {
            shape[4] = false;
            shape[5] = false;
        }
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

/// The generalized forces of eq. (33) for the 13 global DOFs, in the order (c, θ, s).
pub fn generalized_global_forces(
    tess: &Tessellation,
    state: &ModelState,
    forces: &NodalForces,
) -> [f64; NUM_GLOBAL] {
    let mut ws = Workspace::default();
    ws.prepare(tess, state);
    global_system_general(tess, state, &ws, forces).1
}

/// f_d,i = Sᵀ Rᵀ f: for nodal basis functions the local generalized force is RᵀF_i (eq. 33).
pub fn generalized_local_forces(state: &ModelState, forces: &NodalForces) -> Vec<DVec3> {
    let rt = rotation_matrix(state.rotation).transpose();
    forces.force.iter().map(|f| rt * *f).collect()
}

/// The structure of J that [`global_system`] sums over: component c of column b is
/// J_b,c = base_c (α_c,b · φ_c), with base = (X, Y, Z) = (cos^ε1 u cos^ε2 v, cos^ε1 u sin^ε2 v,
/// sin^ε1 u), the log features φ_x = (1, ln|cos u|, ln|cos v|), φ_y = (1, ln|cos u|, ln|sin v|),
/// φ_z = (1, ln|sin u|, 0), and constant coefficients α (eq. 10 as corrected in `superquadric`).
/// Returns α indexed [c][b].
fn jacobian_coefficients(q: &SuperquadricParams) -> [[[f64; 3]; NUM_SHAPE]; 3] {
    let a = q.a;
    let z = [0.0; 3];
    [
        [
            [q.a1, 0.0, 0.0],
            [a, 0.0, 0.0],
            z,
            z,
            [0.0, a * q.a1, 0.0],
            [0.0, 0.0, a * q.a1],
        ],
        [
            [q.a2, 0.0, 0.0],
            z,
            [a, 0.0, 0.0],
            z,
            [0.0, a * q.a2, 0.0],
            [0.0, 0.0, a * q.a2],
        ],
        [
            [q.a3, 0.0, 0.0],
            z,
            z,
            [a, 0.0, 0.0],
            [0.0, a * q.a3, 0.0],
            z,
        ],
    ]
}

/// The log features φ_c of one node (see [`jacobian_coefficients`]).
#[cfg(test)]
fn log_features(t: &super::superquadric::Trig) -> [[f64; 3]; 3] {
    [
        [1.0, t.ln_cu, t.ln_cv],
        [1.0, t.ln_cu, t.ln_sv],
        [1.0, t.ln_su, 0.0],
    ]
}

fn dot3(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// What the global system reads at a node where a force acts.
#[derive(Clone, Copy)]
struct ForcedNode {
    /// Node index.
    i: usize,
    /// Force on every DOF plus force on the global DOFs only (world).
    f: DVec3,
    /// Stiffness weight of both.
    kappa: f64,
    /// Point-to-plane stiffness (0 without).
    rho: f64,
    /// Model-frame point p_i.
    p: DVec3,
    /// (X, Y, Z): the unit-scale superquadric point (see [`jacobian_coefficients`]).
    base: [f64; 3],
    /// The log features φ_x, φ_y, φ_z.
    phi: [[f64; 3]; 3],
}

/// Calls `visit` for every node with a force, spring or plane spring on it, with the terms of
/// the node's row of J (signed powers from the workspace's grid, logs from the tessellation).
#[inline(always)]
fn for_each_forced_node(
    tess: &Tessellation,
    ws: &Workspace,
    forces: &NodalForces,
    mut visit: impl FnMut(&ForcedNode),
) {
    let (points, grid) = (&ws.points, &ws.grid);
    let plane = forces.plane_stiffness.len() == forces.force.len();
    tess.for_each_grid_node(|i, ring, lon| {
        let f = forces.force[i] + forces.shape_force[i];
        let kappa = forces.stiffness[i] + forces.shape_stiffness[i];
        let rho = if plane {
            forces.plane_stiffness[i]
        } else {
            0.0
        };
        if kappa == 0.0 && rho == 0.0 && f == DVec3::ZERO {
            return;
        }
        let [cu, su] = grid.rings[ring];
        let [cv, sv] = lon.map_or(grid.poles[usize::from(ring != 0)], |j| grid.longitudes[j]);
        let ([ln_cu, ln_su], [ln_cv, ln_sv]) = tess.grid_logs(ring, lon);
        visit(&ForcedNode {
            i,
            f,
            kappa,
            rho,
            p: points[i],
            base: [cu * cv, cu * sv, su],
            phi: [[1.0, ln_cu, ln_cv], [1.0, ln_cu, ln_sv], [1.0, ln_su, 0.0]],
        });
    });
}

/// The stiffness-weighted Gram matrix Σ κ_i L_iᵀ L_i (plus the point-to-plane terms), the
/// generalized forces Σ L_iᵀ F_i and the total stiffness weight: through the superquadric's
/// moments ([`global_system_superquadric`]) when the model is a plain superquadric whose
/// tapering and bending are held, and column by column ([`global_system_general`]) otherwise.
fn global_system(
    tess: &Tessellation,
    state: &ModelState,
    ws: &Workspace,
    forces: &NodalForces,
    free: &FreeDofs,
) -> ([[f64; NUM_GLOBAL]; NUM_GLOBAL], [f64; NUM_GLOBAL], f64) {
    if state.deformation.is_identity() && !free.taper && !free.bend {
        global_system_superquadric(tess, state, ws, forces)
    } else {
        global_system_general(tess, state, ws, forces)
    }
}

/// [`global_system`] for any T: each node's 14 model-frame columns of L (rotation, q_s, q_T) are
/// built explicitly, L_iᵀ L_i summed from them (about 700 flops a node, 4–5 times the moments).
/// Model-frame columns: G_j × p for q_θ (so that R times it is B's column, eq. 17), and
/// ∂T/∂s J_b + ∂T/∂A ∂A/∂q_b for q_s (A = a·a3), ∂T/∂q_T for q_T; the translation columns are
/// the world axes.
fn global_system_general(
    tess: &Tessellation,
    state: &ModelState,
    ws: &Workspace,
    forces: &NodalForces,
) -> ([[f64; NUM_GLOBAL]; NUM_GLOBAL], [f64; NUM_GLOBAL], f64) {
    const M: usize = NUM_GLOBAL - 3;
    let r = rotation_matrix(state.rotation);
    let rt = r.transpose();
    let g = g_matrix(state.rotation);
    let q = &state.shape;
    let alpha = jacobian_coefficients(q);
    let axes = q.semi_axes();
    // ∂A/∂q_s for A = a·a3.
    let mut d_height = [0.0; NUM_SHAPE];
    d_height[0] = q.a3;
    d_height[3] = q.a;
    let mut gram = [[0.0; M]; M]; // Σ κ colᵀcol + Σ ρ (col·m)(col·m), upper triangle
    let mut k_col = [DVec3::ZERO; M]; // Σ κ col (model frame)
    let mut rho_n_col = [DVec3::ZERO; M]; // Σ ρ n (col·m) (world n)
    let mut rho_nn = DMat3::ZERO; // Σ ρ n nᵀ
    let mut f_model = [0.0; M];
    let mut f_c = DVec3::ZERO;
    let (mut kappa_sum, mut plane_sum) = (0.0, 0.0);
    for_each_forced_node(tess, ws, forces, |node| {
        let s = axes * DVec3::from_array(node.base);
        let t = state.deformation.jacobian(s, axes.z);
        let mut cols = [DVec3::ZERO; M];
        for j in 0..4 {
            cols[j] = g[j].cross(node.p);
        }
        for b in 0..NUM_SHAPE {
            let jb = DVec3::new(
                node.base[0] * dot3(&alpha[0][b], &node.phi[0]),
                node.base[1] * dot3(&alpha[1][b], &node.phi[1]),
                node.base[2] * dot3(&alpha[2][b], &node.phi[2]),
            );
            cols[4 + b] = t.d_point * jb + d_height[b] * t.d_height;
        }
        cols[4 + NUM_SHAPE..].copy_from_slice(&t.d_params);
        let fm = rt * node.f;
        f_c += node.f;
        for (fa, col) in f_model.iter_mut().zip(&cols) {
            *fa += col.dot(fm);
        }
        let n = if node.rho != 0.0 {
            forces.plane_normal[node.i]
        } else {
            DVec3::ZERO
        };
        let m = rt * n;
        let along: [f64; M] = std::array::from_fn(|a| cols[a].dot(m));
        for a in 0..M {
            k_col[a] += node.kappa * cols[a];
            rho_n_col[a] += node.rho * along[a] * n;
            for b in a..M {
                gram[a][b] += node.kappa * cols[a].dot(cols[b]) + node.rho * along[a] * along[b];
            }
        }
        rho_nn += node.rho * DMat3::from_cols(n.x * n, n.y * n, n.z * n);
        kappa_sum += node.kappa;
        plane_sum += node.rho;
    });
    let mut c = [[0.0; NUM_GLOBAL]; NUM_GLOBAL];
    for k in 0..3 {
        for l in 0..3 {
            c[k][l] = rho_nn.col(l)[k] + if k == l { kappa_sum } else { 0.0 };
        }
    }
    for a in 0..M {
        // c–(θ, s, T): e_kᵀ (Σ κ R col + Σ ρ n (col·m)).
        let col = r * k_col[a] + rho_n_col[a];
        for k in 0..3 {
            c[k][3 + a] = col[k];
        }
        for b in a..M {
            c[3 + a][3 + b] = gram[a][b];
        }
    }
    for i in 0..NUM_GLOBAL {
        for j in 0..i {
            c[i][j] = c[j][i];
        }
    }
    let mut f = [0.0; NUM_GLOBAL];
    f[..3].copy_from_slice(&f_c.to_array());
    f[3..].copy_from_slice(&f_model);
    (c, f, kappa_sum + plane_sum)
}

/// Sums over the nodes of one ring of the stiffness and force terms whose longitude factors
/// (cos^ε2 v, sin^ε2 v and their logs) vary along the ring; the ring's own factors multiply them
/// once when the ring is folded into the moments ([`RingSums::fold`]).
#[derive(Default)]
struct RingSums {
    /// Σ κ, and Σ κ p.
    k: f64,
    kp: DVec3,
    /// Σ κ C, Σ κ C ln|C|, Σ κ C², Σ κ C² ln|C|, Σ κ C² ln²|C| for C = cos^ε2 v ([0]) and
    /// C = sin^ε2 v ([1]).
    kc: [[f64; 5]; 2],
    /// Σ κ C p and Σ κ C ln|C| p, for the same two C.
    kcp: [[DVec3; 2]; 2],
    /// Σ C (RᵀF)_x, Σ C ln|C| (RᵀF)_x for C = cos^ε2 v; the same for sin^ε2 v and (RᵀF)_y;
    /// and Σ (RᵀF)_z.
    fc: [[f64; 2]; 2],
    fz: f64,
}

/// The moments of the global system that [`global_system_superquadric`] assembles the 13 × 13
/// system from, per J component c: `mm[c]` = Σ κ base_c² φ_c φ_cᵀ (packed xx, xy, xz, yy, yz,
/// zz), `v[c]` = Σ κ base_c φ_c, `w[c][d]` = Σ κ p_d base_c φ_c, `fs[c]` = Σ base_c (RᵀF)_c φ_c.
#[derive(Default)]
struct Moments {
    mm: [[f64; 6]; 3],
    v: [[f64; 3]; 3],
    w: [[[f64; 3]; 3]; 3],
    fs: [[f64; 3]; 3],
}

impl RingSums {
    /// Adds this ring's sums to `m`, for a ring with (cos^ε1 u, sin^ε1 u) = `(cu, su)` and logs
    /// `(ln_cu, ln_su)`. Components x and y have base cu C and φ = (1, ln|cos u|, ln|C|);
    /// component z has base su and φ = (1, ln|sin u|, 0).
    fn fold(&self, [cu, su]: [f64; 2], [ln_cu, ln_su]: [f64; 2], m: &mut Moments) {
        for c in 0..2 {
            let [s1, s1l, s2, s2l, s2ll] = self.kc[c];
            let cu2 = cu * cu;
            add(&mut m.v[c], cu, [s1, ln_cu * s1, s1l]);
            add(
                &mut m.mm[c],
                cu2,
                [s2, ln_cu * s2, s2l, ln_cu * ln_cu * s2, ln_cu * s2l, s2ll],
            );
            let [p1, p1l] = self.kcp[c];
            for d in 0..3 {
                add(&mut m.w[c][d], cu, [p1[d], ln_cu * p1[d], p1l[d]]);
            }
            let [f1, f1l] = self.fc[c];
            add(&mut m.fs[c], cu, [f1, ln_cu * f1, f1l]);
        }
        let k = self.k;
        add(&mut m.v[2], su, [k, ln_su * k, 0.0]);
        add(
            &mut m.mm[2],
            su * su,
            [k, ln_su * k, 0.0, ln_su * ln_su * k, 0.0, 0.0],
        );
        for d in 0..3 {
            let p = self.kp[d];
            add(&mut m.w[2][d], su, [p, ln_su * p, 0.0]);
        }
        add(&mut m.fs[2], su, [self.fz, ln_su * self.fz, 0.0]);
    }
}

/// `acc += scale · terms`, element by element.
#[inline(always)]
fn add<const N: usize>(acc: &mut [f64; N], scale: f64, terms: [f64; N]) {
    for (a, t) in acc.iter_mut().zip(terms) {
        *a += scale * t;
    }
}

/// Accumulates the stiffness-weighted Gram matrix Σ κ_i L_iᵀ L_i (the global damping block) and
/// the generalized forces Σ L_iᵀ F_i (eq. 33) of a plain superquadric (q_T = 0), using the block structure of L = [I, −R p̃ G, R J] and the per-component structure
/// of J ([`jacobian_coefficients`]). The x and y components of J's columns are products of a
/// ring's factor (cos^ε1 u and its log) and a longitude's (cos^ε2 v or sin^ε2 v and its log), the
/// z components depend on the ring alone; so each node adds to the 31 sums of its ring
/// ([`RingSums`]) and to the 12 moments of the rigid block Σ κ p pᵀ, Σ F, Σ p × RᵀF (about 100
/// flops a node, 130 before the ring sums), each ring's sums become the moments of J
/// ([`Moments`]) once, and the 13 × 13 system is assembled from the moments once. The
/// point-to-plane springs add ρ g gᵀ node by node.
fn global_system_superquadric(
    tess: &Tessellation,
    state: &ModelState,
    ws: &Workspace,
    forces: &NodalForces,
) -> ([[f64; NUM_GLOBAL]; NUM_GLOBAL], [f64; NUM_GLOBAL], f64) {
    let r = rotation_matrix(state.rotation);
    let rt = r.transpose();
    let g = g_matrix(state.rotation);
    let alpha = jacobian_coefficients(&state.shape);
    let mut kappa_sum = 0.0;
    let mut kp = DVec3::ZERO; // Σ κ p
    let mut kpp = [0.0; 6]; // Σ κ p pᵀ, packed (xx, xy, xz, yy, yz, zz)
    let mut f_c = DVec3::ZERO;
    let mut torque = DVec3::ZERO; // Σ p × RᵀF (model frame)
    let mut moments = Moments::default();
    let (k, grid) = (tess.k, &ws.grid);
    // Ring by ring (the poles are rings of one node): the terms that vary along a ring are
    // summed over it, and its cos^ε1 u, sin^ε1 u and their logs multiply the sums once.
    for ring in 0..k + 2 {
        // The ring's nodes, and their longitudes' powers and logs (a pole's own, at v = 0).
        let (nodes, lon_trig) = tess.grid_ring(ring);
        let lon_powers = grid.ring_longitudes(ring);
        let mut sums = RingSums::default();
        let node_terms = forces.force[nodes.clone()]
            .iter()
            .zip(&forces.shape_force[nodes.clone()])
            .zip(&forces.stiffness[nodes.clone()])
            .zip(&forces.shape_stiffness[nodes.clone()])
            .zip(&ws.points[nodes])
            .zip(lon_powers.iter().zip(lon_trig));
        for (((((f, shape_f), kappa), shape_kappa), p), ([cv, sv], t)) in node_terms {
            let (f, kappa, p) = (*f + *shape_f, kappa + shape_kappa, *p);
            let fm = rt * f;
            f_c += f;
            torque += p.cross(fm);
            let kp_i = kappa * p;
            add(
                &mut kpp,
                1.0,
                [
                    kp_i.x * p.x,
                    kp_i.x * p.y,
                    kp_i.x * p.z,
                    kp_i.y * p.y,
                    kp_i.y * p.z,
                    kp_i.z * p.z,
                ],
            );
            sums.k += kappa;
            sums.kp += kp_i;
            for (c, (lon_c, ln_c, fm_c)) in [(*cv, t.ln_cv, fm.x), (*sv, t.ln_sv, fm.y)]
                .into_iter()
                .enumerate()
            {
                let kc = kappa * lon_c;
                let kcl = kc * ln_c;
                let kccl = kcl * lon_c;
                add(
                    &mut sums.kc[c],
                    1.0,
                    [kc, kcl, kc * lon_c, kccl, kccl * ln_c],
                );
                sums.kcp[c][0] += kc * p;
                sums.kcp[c][1] += kcl * p;
                let fc = lon_c * fm_c;
                add(&mut sums.fc[c], 1.0, [fc, fc * ln_c]);
            }
            sums.fz += fm.z;
        }
        sums.fold(grid.rings[ring], tess.grid_logs(ring, None).0, &mut moments);
        kappa_sum += sums.k;
        kp += sums.kp;
    }
    // Point-to-plane springs: ρ g gᵀ for g = L_iᵀ n = (n, Gᵀ (p × Rᵀn), Jᵀ Rᵀn), upper triangle.
    let mut plane_gram = [[0.0; NUM_GLOBAL]; NUM_GLOBAL];
    let mut plane_sum = 0.0;
    if forces.has_plane_springs() {
        for_each_forced_node(tess, ws, forces, |node| {
            let ForcedNode {
                i,
                rho,
                p,
                base,
                phi,
                ..
            } = *node;
            if rho == 0.0 {
                return;
            }
            let n = forces.plane_normal[i];
            let m = rt * n;
            let pm = p.cross(m);
            let ma = m.to_array();
            let mut gv = [0.0; NUM_GLOBAL];
            gv[..3].copy_from_slice(&n.to_array());
            for j in 0..4 {
                gv[3 + j] = g[j].dot(pm);
            }
            for b in 0..NUM_SHAPE {
                gv[7 + b] = (0..3)
                    .map(|c| base[c] * ma[c] * dot3(&alpha[c][b], &phi[c]))
                    .sum();
            }
            for a in 0..DEFORM_START {
                let ra = rho * gv[a];
                for b in a..DEFORM_START {
                    plane_gram[a][b] += ra * gv[b];
                }
            }
            plane_sum += rho;
        });
    }
    let Moments { mm, v, w, fs } = moments;
    let k_j: [DVec3; NUM_SHAPE] = std::array::from_fn(|b| {
        DVec3::new(
            dot3(&alpha[0][b], &v[0]),
            dot3(&alpha[1][b], &v[1]),
            dot3(&alpha[2][b], &v[2]),
        )
    }); // Σ κ J_b
    let k_pj: [DVec3; NUM_SHAPE] = std::array::from_fn(|b| {
        // Σ κ p × J_b, with Σ κ p_d J_b,c = α_c,b · w[c][d].
        let pj = |c: usize, d: usize| dot3(&alpha[c][b], &w[c][d]);
        DVec3::new(
            pj(2, 1) - pj(1, 2),
            pj(0, 2) - pj(2, 0),
            pj(1, 0) - pj(0, 1),
        )
    });
    let unpack = |m: &[f64; 6]| [[m[0], m[1], m[2]], [m[1], m[3], m[4]], [m[2], m[4], m[5]]];
    let moments = mm.map(|m| unpack(&m));
    let gram = |a: usize, b: usize| -> f64 {
        // Σ κ J_a · J_b = Σ_c α_c,aᵀ M_c α_c,b
        (0..3)
            .map(|c| {
                let mb = moments[c].map(|row| dot3(&row, &alpha[c][b]));
                dot3(&alpha[c][a], &mb)
            })
            .sum()
    };
    let p2 = kpp[0] + kpp[3] + kpp[5];
    let ppt = unpack(&kpp);
    let inertia = DMat3::from_cols_array_2d(&std::array::from_fn(|col| {
        std::array::from_fn(|row| (if row == col { p2 } else { 0.0 }) - ppt[row][col])
    })); // Σ κ (|p|² I − p pᵀ)
    let mut m = [[0.0; NUM_GLOBAL]; NUM_GLOBAL];
    // c–c
    for (k, row) in m.iter_mut().enumerate().take(3) {
        row[k] = kappa_sum;
    }
    // c–θ: column j is R (G_j × Σκp); c–s: column b is R Σκ J_b
    for j in 0..4 {
        let col = r * g[j].cross(kp);
        for k in 0..3 {
            m[k][3 + j] = col[k];
        }
    }
    for b in 0..NUM_SHAPE {
        let col = r * k_j[b];
        for k in 0..3 {
            m[k][7 + b] = col[k];
        }
    }
    // θ–θ: G_aᵀ I G_b; θ–s: G_a · Σκ p × J_b
    for a in 0..4 {
        for b in a..4 {
            m[3 + a][3 + b] = g[a].dot(inertia * g[b]);
        }
        for b in 0..NUM_SHAPE {
            m[3 + a][7 + b] = g[a].dot(k_pj[b]);
        }
    }
    for a in 0..NUM_SHAPE {
        for b in a..NUM_SHAPE {
            m[7 + a][7 + b] = gram(a, b);
        }
    }
    for (row, plane_row) in m.iter_mut().zip(&plane_gram) {
        for (x, p) in row.iter_mut().zip(plane_row) {
            *x += p;
        }
    }
    for i in 0..NUM_GLOBAL {
        for j in 0..i {
            m[i][j] = m[j][i];
        }
    }
    let mut f = [0.0; NUM_GLOBAL];
    f[..3].copy_from_slice(&f_c.to_array());
    for j in 0..4 {
        f[3 + j] = g[j].dot(torque);
    }
    for b in 0..NUM_SHAPE {
        f[7 + b] = (0..3).map(|c| dot3(&alpha[c][b], &fs[c])).sum();
    }
    (m, f, kappa_sum + plane_sum)
}

/// Relative residual at which the implicit local solve stops ([`DynamicsParams::implicit_local`]):
/// each component's |b − M d⁺| at most this times its |b|.
pub const IMPLICIT_LOCAL_TOLERANCE: f64 = 1e-6;

/// Conjugate-gradient iterations the implicit local solve takes at most.
pub const IMPLICIT_LOCAL_MAX_ITERATIONS: u32 = 2000;

/// The local block of eq. (15) as one backward-Euler step ([`DynamicsParams::implicit_local`]),
/// from `displacement` into `ws.new_d` (its warm start), at the pose of `rotation`. With
/// `before`, the nodes have moved from there to `ws.world` since the forces were gathered, and
/// each node's force is moved with them: F_i − κ_i Δx_i. Returns the solver's iterations.
fn implicit_local_step(
    tess: &Tessellation,
    displacement: &[DVec3],
    (forces, rotation, before): (&NodalForces, DQuat, Option<&[DVec3]>),
    params: &DynamicsParams,
    ws: &mut Workspace,
) -> u32 {
    let n = tess.node_count();
    let rt = rotation_matrix(rotation).transpose();
    ws.local_force.clear();
    ws.local_force.extend((0..n).map(|i| {
        let moved = before.map_or(DVec3::ZERO, |b| ws.world[i] - b[i]);
        rt * (forces.force[i] - forces.stiffness[i] * moved)
    }));
    let (w0, w1) = (params.w0, params.w1);
    let key = (w0, w1, n);
    if ws.k_diagonal_key != Some(key) {
        ws.k_diagonal = tess.stiffness_diagonal(w0, w1);
        ws.k_diagonal_key = Some(key);
    }
    let damping = params.gamma_local / params.dt;
    ws.shift.clear();
    ws.shift
        .extend((0..n).map(|i| damping * tess.node_area[i] + forces.stiffness[i]));
    for i in 0..n {
        ws.local_force[i] += ws.shift[i] * displacement[i];
    }
    tess.solve_shifted(
        (w0, w1),
        &ws.shift,
        &ws.k_diagonal,
        &ws.local_force,
        &mut ws.new_d,
        (IMPLICIT_LOCAL_TOLERANCE, IMPLICIT_LOCAL_MAX_ITERATIONS),
        &mut ws.cg,
    )
}

/// The global block of one Euler step: δq_g = Δt C_g⁻¹ f_g (eq. 15), frozen DOFs removed.
fn global_increment(
    tess: &Tessellation,
    state: &ModelState,
    ws: &Workspace,
    forces: &NodalForces,
    params: &DynamicsParams,
) -> Result<[f64; NUM_GLOBAL], StepError> {
    let (mut c, mut f, kappa_sum) = global_system(tess, state, ws, forces, &params.free);
    let ell = state.shape.a.max(1e-12);
    // Units of each column of L, squared: lengths (ℓ²) except for c and a (dimensionless).
    let scale: [f64; NUM_GLOBAL] =
        std::array::from_fn(|i| if i < 3 || i == 7 { 1.0 } else { ell * ell });
    let weight = kappa_sum
        .max(f.iter().map(|x| x.abs()).fold(0.0, f64::max) / ell)
        .max(1e-300);
    for i in 0..NUM_GLOBAL {
        c[i][i] += params.marquardt * c[i][i] + params.ridge * weight * scale[i];
    }
    let free = params.free;
    // Planar motion: rotate the quaternion block into a basis whose first vector is the turn
    // about world z, and hold the other three (and c_z) below.
    let basis = free.planar.then(|| planar_rotation_basis(state.rotation));
    if let Some(e) = &basis {
        change_rotation_basis(&mut c, &mut f, e);
    }
    for i in 0..NUM_GLOBAL {
        let is_free = match i {
            0 | 1 => free.translation,
            2 => free.translation && !free.planar,
            3 => free.rotation,
            4..=6 => free.rotation && !free.planar,
            7..DEFORM_START => free.shape[i - 7],
            _ if i < DEFORM_START + 2 => free.taper,
            _ => free.bend,
        };
        if !is_free {
            for j in 0..NUM_GLOBAL {
                c[i][j] = 0.0;
                c[j][i] = 0.0;
            }
            c[i][i] = 1.0;
            f[i] = 0.0;
        }
        for row in c.iter_mut() {
            row[i] *= params.gamma_global;
        }
    }
    if f.iter().all(|&x| x == 0.0) {
        return Ok([0.0; NUM_GLOBAL]);
    }
    if !f.iter().all(|x| x.is_finite()) {
        return Err(StepError::NonFinite("generalized force f_q"));
    }
    let mut x = cholesky_solve(&c, &f).ok_or(StepError::NonFinite("global damping matrix C_g"))?;
    if let Some(e) = &basis {
        let xi = [x[3], x[4], x[5], x[6]];
        for j in 0..4 {
            x[3 + j] = (0..4).map(|k| e[k][j] * xi[k]).sum();
        }
    }
    Ok(x.map(|v| v * params.dt))
}

/// An orthonormal basis of quaternion increments (paper order) whose first vector is the turn
/// about world z, dq/dφ = ½ (0, ẑ) ⊗ q.
fn planar_rotation_basis(q: DQuat) -> [[f64; 4]; 4] {
    let t = DQuat::from_xyzw(0.0, 0.0, 0.5, 0.0) * q;
    let mut basis: Vec<[f64; 4]> = Vec::with_capacity(4);
    let candidates = [
        [t.w, t.x, t.y, t.z],
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    for mut v in candidates {
        for b in &basis {
            let d: f64 = (0..4).map(|k| v[k] * b[k]).sum();
            (0..4).for_each(|k| v[k] -= d * b[k]);
        }
        let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        if n > 0.3 && basis.len() < 4 {
            basis.push(v.map(|x| x / n));
        }
    }
    [basis[0], basis[1], basis[2], basis[3]]
}

/// C ← Qᵀ C Q and f ← Qᵀ f for Q = diag(I₃, E, I₆), E's columns the rows of `e`.
fn change_rotation_basis(
    c: &mut [[f64; NUM_GLOBAL]; NUM_GLOBAL],
    f: &mut [f64; NUM_GLOBAL],
    e: &[[f64; 4]; 4],
) {
    for row in c.iter_mut() {
        // C Q, row by row.
        let r: [f64; 4] = std::array::from_fn(|j| row[3 + j]);
        for k in 0..4 {
            row[3 + k] = (0..4).map(|j| e[k][j] * r[j]).sum();
        }
    }
    for col in 0..NUM_GLOBAL {
        let column: [f64; 4] = std::array::from_fn(|j| c[3 + j][col]);
        for k in 0..4 {
            c[3 + k][col] = (0..4).map(|j| e[k][j] * column[j]).sum();
        }
    }
    let fr: [f64; 4] = std::array::from_fn(|j| f[3 + j]);
    for k in 0..4 {
        f[3 + k] = (0..4).map(|j| e[k][j] * fr[j]).sum();
    }
}

/// Cuts a global increment back to the trust region; returns true when it did.
fn limit_global(delta: &mut [f64; NUM_GLOBAL], state: &ModelState) -> bool {
    const TRUST: f64 = 0.25;
    let ell = state.shape.a.max(1e-12);
    let dc = DVec3::new(delta[0], delta[1], delta[2]).length() / ell;
    let dq = delta[3..7].iter().map(|x| x * x).sum::<f64>().sqrt() * 2.0; // ≈ rotation angle
    let da = (delta[7] / ell).abs();
    // Aspects and exponents, and the dimensionless taper and bend (radians) alike.
    let rest = delta[8..].iter().fold(0.0_f64, |m, x| m.max(x.abs()));
    let worst = dc.max(dq).max(da).max(rest);
    if worst > TRUST {
        let s = TRUST / worst;
        delta.iter_mut().for_each(|x| *x *= s);
        true
    } else {
        false
    }
}

/// One explicit Euler step of eq. (15), q ← q + Δt C⁻¹ (f_q − K q), with the damping of the
/// module docs. Renormalises the quaternion, moves the largest a_i into a and clamps a_i, ε to
/// their bounds. On error the state is untouched: a step never writes a non-finite value.
pub fn step(
    tess: &Tessellation,
    state: &mut ModelState,
    forces: &NodalForces,
    params: &DynamicsParams,
    ws: &mut Workspace,
) -> Result<StepReport, StepError> {
    ws.prepare(tess, state);
    step_prepared(tess, state, forces, params, ws)
}

/// [`step`] for a state that [`Workspace::prepare`] was last called on, so a loop that needs the
/// node positions for its forces computes them once per step: `prepare` → forces from
/// [`Workspace::world_positions`] → `step_prepared` → `prepare` the new state → …
/// Given a workspace prepared for another state, the step uses that state's node points. After
/// the step the workspace must be prepared again before its positions are read.
pub fn step_prepared(
    tess: &Tessellation,
    state: &mut ModelState,
    forces: &NodalForces,
    params: &DynamicsParams,
    ws: &mut Workspace,
) -> Result<StepReport, StepError> {
    with_avx2!({ step_prepared_body(tess, state, forces, params, ws) })
}

/// [`step_prepared`]'s body, inlined into both of its builds.
#[inline(always)]
fn step_prepared_body(
    tess: &Tessellation,
    state: &mut ModelState,
    forces: &NodalForces,
    params: &DynamicsParams,
    ws: &mut Workspace,
) -> Result<StepReport, StepError> {
    let n = tess.node_count();
    assert!(
        forces.force.len() == n && forces.shape_force.len() == n,
        "NodalForces sized for another tessellation"
    );
    let mut report = StepReport {
        substeps: 0,
        dt_critical: f64::INFINITY,
        clamped: false,
        trust_limited: false,
        local_iterations: 0,
    };
    assert!(
        ws.points.len() == n,
        "Workspace not prepared for this tessellation"
    );
    let mut delta = global_increment(tess, state, ws, forces, params)?;
    report.trust_limited = limit_global(&mut delta, state);

    // Local block, explicit Euler with the checked stability bound.
    ws.new_d.clear();
    ws.new_d.extend_from_slice(&state.displacement);
    let implicit = params.free.local && params.implicit_local;
    if implicit {
        // Solved after the global update, at the new pose (below).
        report.substeps = 1;
    } else if params.free.local {
        let (w0, w1, gamma) = (params.w0, params.w1, params.gamma_local);
        let lambda_max = ws.max_rate(tess, w0, w1) / gamma;
        report.dt_critical = if lambda_max > 0.0 {
            2.0 / lambda_max
        } else {
            f64::INFINITY
        };
        let safe = 0.9 * report.dt_critical;
        let mut substeps = if params.dt <= safe {
            1
        } else {
            (params.dt / safe).ceil() as u32
        };
        let mut h = params.dt / substeps as f64;
        if substeps > MAX_SUBSTEPS {
            substeps = MAX_SUBSTEPS;
            h = safe;
            report.clamped = true;
        }
        report.substeps = substeps;
        // Data springs linearised about the start of the step, F(d) = F(d⁰) − κ (d − d⁰), and
        // taken implicitly (they are diagonal): d += h (f − κ (d − d⁰) − K d) / (γ A + h κ).
        let rt = rotation_matrix(state.rotation).transpose();
        ws.local_force.clear();
        ws.local_force.extend(forces.force.iter().map(|f| rt * *f));
        // As one pass over two slices, so that the divisions vectorise.
        ws.substep_scale.clear();
        ws.substep_scale.extend(
            tess.node_area
                .iter()
                .zip(&forces.stiffness)
                .map(|(a, kappa)| h / (gamma * a + h * kappa)),
        );
        for _ in 0..substeps {
            ws.kd.clear();
            ws.kd.resize(n, DVec3::ZERO);
            tess.apply_stiffness(w0, w1, &ws.new_d, &mut ws.kd);
            let nodes = ws
                .new_d
                .iter_mut()
                .zip(&state.displacement)
                .zip(forces.stiffness.iter().zip(&ws.substep_scale))
                .zip(ws.local_force.iter().zip(&ws.kd));
            for (((d, d0), (kappa, scale)), (f, kd)) in nodes {
                let spring = *kappa * (*d - *d0);
                *d += *scale * (*f - spring - *kd);
            }
        }
    }

    if implicit && delta.iter().all(|&x| x == 0.0) {
        report.local_iterations = implicit_local_step(
            tess,
            &state.displacement,
            (forces, state.rotation, None),
            params,
            ws,
        );
    }
    if delta.iter().all(|&x| x == 0.0) {
        // No global force: the global DOFs stay exactly where they are (no renormalisation drift).
        let displacement = std::mem::take(&mut ws.new_d);
        if !all_finite(&displacement) {
            ws.new_d = displacement;
            return Err(StepError::NonFinite(
                "local displacement after the Euler step",
            ));
        }
        ws.new_d = std::mem::replace(&mut state.displacement, displacement);
        return Ok(report);
    }
    let q = quat_to_paper(state.rotation);
    let rotation = quat_from_paper(std::array::from_fn(|j| q[j] + delta[3 + j]));
    if !(rotation.length() > 0.0) {
        return Err(StepError::NonFinite("rotation quaternion"));
    }
    let shape_q = state.shape.to_array();
    let shape = SuperquadricParams::from_array(std::array::from_fn(|j| shape_q[j] + delta[7 + j]))
        .normalized_keeping(&state.shape);
    let deform_q = state.deformation.to_array();
    let deformation = GlobalDeformation::from_array(std::array::from_fn(|j| {
        deform_q[j] + delta[DEFORM_START + j]
    }))
    .clamped(shape.semi_axes());
    let mut new = ModelState {
        translation: state.translation + DVec3::new(delta[0], delta[1], delta[2]),
        rotation: rotation.normalize(),
        shape,
        deformation,
        displacement: std::mem::take(&mut ws.new_d),
    };
    if implicit {
        // Gauss–Seidel: the membrane solved at the new pose, the springs' forces moved there.
        // The positions before go into `kd`, which only the explicit update uses.
        let mut before = std::mem::take(&mut ws.kd);
        before.clear();
        before.extend_from_slice(&ws.world);
        ws.prepare(tess, &new);
        ws.new_d = std::mem::take(&mut new.displacement);
        report.local_iterations = implicit_local_step(
            tess,
            &state.displacement,
            (forces, new.rotation, Some(&before)),
            params,
            ws,
        );
        ws.kd = before;
        new.displacement = std::mem::take(&mut ws.new_d);
    }
    if !new.is_finite() {
        ws.new_d = new.displacement;
        return Err(StepError::NonFinite("state after the Euler step"));
    }
    ws.new_d = std::mem::take(&mut state.displacement);
    *state = new;
    Ok(report)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::model::frame::quat_from_paper;
    use crate::model::superquadric::jacobian;

    /// A posed, non-trivial superquadric with a small displacement at every node.
    pub(crate) fn test_state(tess: &Tessellation) -> ModelState {
        let mut s = ModelState::new(
            tess,
            DVec3::new(0.3, -0.2, 0.5),
            DQuat::from_axis_angle(DVec3::new(0.2, 1.0, -0.4).normalize(), 0.7),
            SuperquadricParams {
                a: 1.3,
                a1: 0.8,
                a2: 1.0,
                a3: 0.6,
                e1: 0.8,
                e2: 1.2,
            },
        );
        for (i, d) in s.displacement.iter_mut().enumerate() {
            *d = 0.01
                * DVec3::new(
                    (i as f64 * 0.7).sin(),
                    (i as f64 * 1.3).cos(),
                    (i as f64 * 0.4).sin(),
                );
        }
        s
    }

    /// [`test_state`] tapered and bent.
    fn deformed_state(tess: &Tessellation) -> ModelState {
        ModelState {
            deformation: GlobalDeformation {
                taper: [0.3, -0.2],
                bend: [0.4, 0.25],
            },
            ..test_state(tess)
        }
    }

    fn test_forces(tess: &Tessellation) -> NodalForces {
        let mut f = NodalForces::new(tess.node_count());
        for (i, at) in [
            (0.3, 0.4),
            (-0.9, 2.5),
            (1.2, -2.0),
            (1.5, 0.1),
            (-1.5, 1.0),
        ]
        .iter()
        .enumerate()
        {
            let p = tess.locate(at.0, at.1);
            f.add(&p, DVec3::new(1.0 - i as f64, 0.5 * i as f64, 0.3), 0.0);
        }
        f
    }

    /// Potential of constant point forces: V(q) = −Σ_p f_p · x_p(q). Its negative gradient is f_q.
    fn potential(tess: &Tessellation, state: &ModelState, forces: &NodalForces) -> f64 {
        let mut x = Vec::new();
        state.node_positions(tess, &mut x);
        -forces
            .force
            .iter()
            .zip(&x)
            .map(|(f, x)| f.dot(*x))
            .sum::<f64>()
    }

    /// `all_finite` finds a NaN or an infinity in any coordinate of any vector, and passes
    /// finite ones (and none).
    #[test]
    fn all_finite_finds_every_non_finite_coordinate() {
        assert!(all_finite(&[]));
        let finite: Vec<DVec3> = (0..37)
            .map(|i| DVec3::new(i as f64, -1e300, f64::MIN_POSITIVE))
            .collect();
        assert!(all_finite(&finite));
        for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            for i in [0, 1, 17, 36] {
                for c in 0..3 {
                    let mut v = finite.clone();
                    v[i][c] = bad;
                    assert!(!all_finite(&v), "{bad} at vector {i}, coordinate {c}");
                }
            }
        }
    }

    #[test]
    fn prepare_gives_the_node_walks_positions_to_the_bit() {
        // Plain, deformed, and with displacements missing at the end (the ring walk's slice
        // and per-node paths), against `node_positions`.
        for k in [3, 8, 31] {
            let tess = Tessellation::new(k);
            let mut short = test_state(&tess);
            short.displacement.truncate(tess.node_count() - k - 1);
            for state in [test_state(&tess), deformed_state(&tess), short] {
                let mut expected = Vec::new();
                state.node_positions(&tess, &mut expected);
                let mut ws = Workspace::default();
                assert_eq!(ws.prepare(&tess, &state), &expected[..], "k = {k}");
                let rt = rotation_matrix(state.rotation).transpose();
                for (p, x) in ws.points.iter().zip(&expected) {
                    assert!((*p - rt * (*x - state.translation)).length() < 1e-12);
                }
            }
        }
    }

    #[test]
    fn the_continuous_surface_passes_through_the_nodes_and_lies_on_the_superquadric_between() {
        let tess = Tessellation::new(9);
        // Through the nodes, tapered, bent and displaced.
        let state = deformed_state(&tess);
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        let surface = state.surface();
        for (i, [u, v]) in tess.uv.iter().enumerate() {
            let at = ElementPoint::at_node(i as u32);
            let d = surface.at(*u, *v, &at).distance(x[i]);
            assert!(d < 1e-12, "node {i} at ({u}, {v}) is {d} off the surface");
        }
        // Between the nodes, undeformed and undisplaced: on the superquadric (F = 1) and outside
        // the mesh's chords.
        let state = ModelState::new(&tess, state.translation, state.rotation, state.shape);
        state.node_positions(&tess, &mut x);
        let (surface, r) = (state.surface(), rotation_matrix(state.rotation));
        let mut bulge: f64 = 0.0;
        for i in 0..40 {
            let (u, v) = (
                -1.5 + 3.0 * (i as f64 + 0.37) / 40.0,
                -3.1 + 0.155 * i as f64,
            );
            let at = tess.locate(u, v);
            let p = surface.at(u, v, &at);
            let local = r.transpose() * (p - state.translation);
            let f = crate::model::superquadric::inside_outside(&state.shape, local);
            assert!((f - 1.0).abs() < 1e-9, "F = {f} at ({u}, {v})");
            bulge = bulge.max(p.distance(at.interpolate(|k| x[k])));
        }
        assert!(bulge > 1e-3, "the mesh's chords are the surface: {bulge}");
    }

    #[test]
    fn the_continuous_surfaces_tangents_match_central_differences() {
        let tess = Tessellation::new(9);
        for state in [test_state(&tess), deformed_state(&tess)] {
            let surface = state.surface();
            let x = |u: f64, v: f64| surface.at(u, v, &tess.locate(u, v));
            let h = 1e-6;
            for i in 0..25 {
                // Points inside elements, off the coordinate lines through the axes.
                let (u, v) = (
                    -1.4 + 2.8 * (i as f64 + 0.31) / 25.0,
                    -3.0 + 0.2437 * i as f64,
                );
                let at = tess.locate(u, v);
                let (p, tangents) = surface.with_tangents(u, v, &at);
                assert!(p.distance(x(u, v)) < 1e-12);
                let (tu, tv) = tangents.expect("regular point");
                let fu = (x(u + h, v) - x(u - h, v)) / (2.0 * h);
                let fv = (x(u, v + h) - x(u, v - h)) / (2.0 * h);
                let scale = 1.0 + fu.length().max(fv.length());
                assert!(
                    (tu - fu).length() < 1e-6 * scale,
                    "∂x/∂u {tu} vs {fu} at ({u}, {v})"
                );
                assert!(
                    (tv - fv).length() < 1e-6 * scale,
                    "∂x/∂v {tv} vs {fv} at ({u}, {v})"
                );
            }
            // On the coordinate lines through the axes the tangents are not given.
            let at = tess.locate(0.3, 0.0);
            assert!(surface.with_tangents(0.3, 0.0, &at).1.is_none());
        }
    }

    #[test]
    fn global_generalized_forces_match_central_differences() {
        // Every global DOF, tapering and bending included, for the plain superquadric (at q_T = 0)
        // and a tapered, bent one.
        let tess = Tessellation::new(6);
        let forces = test_forces(&tess);
        for state in [test_state(&tess), deformed_state(&tess)] {
            let fq = generalized_global_forces(&tess, &state, &forces);
            let h = 1e-6;
            for j in 0..NUM_GLOBAL {
                let perturbed = |sign: f64| {
                    let mut s = state.clone();
                    match j {
                        0..=2 => s.translation[j] += sign * h,
                        3..=6 => {
                            let mut q = quat_to_paper(s.rotation);
                            q[j - 3] += sign * h;
                            s.rotation = quat_from_paper(q).normalize();
                        }
                        7..DEFORM_START => {
                            let mut a = s.shape.to_array();
                            a[j - 7] += sign * h;
                            s.shape = SuperquadricParams::from_array(a);
                        }
                        _ => {
                            let mut t = s.deformation.to_array();
                            t[j - DEFORM_START] += sign * h;
                            s.deformation = GlobalDeformation::from_array(t);
                        }
                    }
                    potential(&tess, &s, &forces)
                };
                let fd = -(perturbed(1.0) - perturbed(-1.0)) / (2.0 * h);
                assert!(
                    (fd - fq[j]).abs() < 1e-6 * (1.0 + fd.abs()),
                    "dof {j} at {:?}: f_q {} vs fd {fd}",
                    state.deformation,
                    fq[j]
                );
            }
        }
    }

    #[test]
    fn local_generalized_forces_match_central_differences_inside_elements() {
        let tess = Tessellation::new(6);
        let state = test_state(&tess);
        let forces = test_forces(&tess);
        let fd_local = generalized_local_forces(&state, &forces);
        let h = 1e-6;
        for node in [0usize, 5, 17, tess.north_pole(), 30] {
            for c in 0..3 {
                let v = |sign: f64| {
                    let mut s = state.clone();
                    s.displacement[node][c] += sign * h;
                    potential(&tess, &s, &forces)
                };
                let fd = -(v(1.0) - v(-1.0)) / (2.0 * h);
                assert!(
                    (fd - fd_local[node][c]).abs() < 1e-7,
                    "node {node} comp {c}: {} vs {fd}",
                    fd_local[node][c]
                );
            }
        }
    }

    #[test]
    fn jacobian_structure_reproduces_the_jacobian() {
        // J_b,c = base_c (α_c,b · φ_c) is the same J as `superquadric::jacobian`.
        let tess = Tessellation::new(9);
        let state = test_state(&tess);
        let alpha = jacobian_coefficients(&state.shape);
        let mut powers = Vec::new();
        tess.signed_powers(&state.shape, &mut powers);
        for (t, pw) in tess.trig.iter().zip(&powers) {
            let jac = jacobian(&state.shape, t);
            let base = [pw.cu * pw.cv, pw.cu * pw.sv, pw.su];
            let phi = log_features(t);
            for b in 0..NUM_SHAPE {
                for c in 0..3 {
                    let rebuilt = base[c] * dot3(&alpha[c][b], &phi[c]);
                    assert!((rebuilt - jac[b][c]).abs() <= 1e-14 * (1.0 + jac[b][c].abs()));
                }
            }
        }
    }

    /// Σ κ L_iᵀ L_i + Σ ρ (L_iᵀ n_i)(L_iᵀ n_i)ᵀ and Σ L_iᵀ F_i built from explicit world columns
    /// L_i = [I, B_i, R (∂T/∂s J + ∂T/∂A ∂A/∂q_s), R ∂T/∂q_T].
    fn explicit_system(
        tess: &Tessellation,
        state: &ModelState,
        forces: &NodalForces,
    ) -> ([[f64; NUM_GLOBAL]; NUM_GLOBAL], [f64; NUM_GLOBAL]) {
        let mut ws = Workspace::default();
        ws.prepare(tess, state);
        let r = rotation_matrix(state.rotation);
        let q = &state.shape;
        let axes = q.semi_axes();
        let mut gram = [[0.0; NUM_GLOBAL]; NUM_GLOBAL];
        let mut f = [0.0; NUM_GLOBAL];
        for i in 0..tess.node_count() {
            let b = crate::model::frame::b_matrix(&r, state.rotation, ws.points[i]);
            let jac = jacobian(q, &tess.trig[i]);
            let s = crate::model::superquadric::shape(q, &tess.trig[i]);
            let t = state.deformation.jacobian(s, axes.z);
            let d_height = [q.a3, 0.0, 0.0, q.a, 0.0, 0.0];
            let cols: Vec<DVec3> = [DVec3::X, DVec3::Y, DVec3::Z]
                .into_iter()
                .chain(b)
                .chain((0..NUM_SHAPE).map(|k| r * (t.d_point * jac[k] + d_height[k] * t.d_height)))
                .chain(t.d_params.iter().map(|c| r * *c))
                .collect();
            let n = forces.plane_normal[i];
            let force = forces.force[i] + forces.shape_force[i];
            let kappa = forces.stiffness[i] + forces.shape_stiffness[i];
            for a in 0..NUM_GLOBAL {
                f[a] += cols[a].dot(force);
                for bb in 0..NUM_GLOBAL {
                    gram[a][bb] += kappa * cols[a].dot(cols[bb])
                        + forces.plane_stiffness[i] * cols[a].dot(n) * cols[bb].dot(n);
                }
            }
        }
        (gram, f)
    }

    #[test]
    fn gram_matrix_equals_explicit_lt_l_sum() {
        // The Gram matrix and forces through the superquadric's moments (plain model, q_T held)
        // and column by column (tapered and bent, or q_T free) equal the sums built from explicit
        // columns; the two paths agree on the plain model.
        let tess = Tessellation::new(5);
        let mut forces = test_forces(&tess);
        for i in 0..tess.node_count() {
            forces.stiffness[i] = 0.1 + (i % 3) as f64;
            forces.shape_stiffness[i] = 0.05 * (i % 2) as f64;
            forces.shape_force[i] = DVec3::new(0.1, -0.2 * (i % 3) as f64, 0.05);
            if i % 4 == 1 {
                // Point-to-plane springs on some nodes, with any unit normal.
                forces.plane_stiffness[i] = 0.5 + (i % 5) as f64;
                forces.plane_normal[i] =
                    DVec3::new((i as f64).sin(), 0.3, (0.7 * i as f64).cos()).normalize();
            }
        }
        let held = FreeDofs::default();
        let free = FreeDofs {
            taper: true,
            bend: true,
            ..held
        };
        for (state, dofs) in [
            (test_state(&tess), held),
            (test_state(&tess), free),
            (deformed_state(&tess), held),
            (deformed_state(&tess), free),
        ] {
            let mut ws = Workspace::default();
            ws.prepare(&tess, &state);
            let (m, f, _) = global_system(&tess, &state, &ws, &forces, &dofs);
            let (explicit, explicit_f) = explicit_system(&tess, &state, &forces);
            // The moments path leaves the q_T rows empty: they are held.
            let rows = if state.deformation.is_identity() && !dofs.taper {
                DEFORM_START
            } else {
                NUM_GLOBAL
            };
            for a in 0..rows {
                let tol = |x: f64| 1e-9 * (1.0 + x.abs());
                assert!((f[a] - explicit_f[a]).abs() < tol(explicit_f[a]), "f {a}");
                for b in 0..rows {
                    assert!(
                        (m[a][b] - explicit[a][b]).abs() < tol(explicit[a][b]),
                        "({a},{b}) at {:?}, free {dofs:?}",
                        state.deformation
                    );
                }
            }
        }
    }

    /// Relaxes a displaced model with no external force for `steps` steps at Δt far beyond the
    /// explicit bound, checking that the strain energy never rises, the quaternion stays unit and
    /// the global DOFs stay where they are; returns the final energy over the first and the
    /// step reports.
    fn relax_unforced(implicit_local: bool, steps: usize) -> (f64, Vec<StepReport>) {
        let tess = Tessellation::new(12);
        let mut state = test_state(&tess);
        for (i, d) in state.displacement.iter_mut().enumerate() {
            *d = 0.2
                * DVec3::new(
                    (i as f64 * 2.7).sin(),
                    (i as f64 * 0.3).cos(),
                    (i as f64).sin(),
                );
        }
        let params = DynamicsParams {
            dt: 5.0,
            w0: 0.01,
            w1: 0.5,
            implicit_local,
            ..Default::default()
        };
        let forces = NodalForces::new(tess.node_count());
        let mut ws = Workspace::default();
        let start = tess.strain_energy(params.w0, params.w1, &state.displacement);
        let mut energy = start;
        let before = state.clone();
        let mut reports = Vec::new();
        for _ in 0..steps {
            reports.push(step(&tess, &mut state, &forces, &params, &mut ws).expect("finite"));
            assert!(state.displacement.iter().all(|d| d.is_finite()));
            let e = tess.strain_energy(params.w0, params.w1, &state.displacement);
            assert!(e <= energy * (1.0 + 1e-12), "energy rose: {energy} -> {e}");
            energy = e;
            assert!((state.rotation.length() - 1.0).abs() < 1e-12);
        }
        // No external force: the global DOFs do not move.
        assert_eq!(state.translation, before.translation);
        assert_eq!(state.rotation, before.rotation);
        (energy / start, reports)
    }

    #[test]
    fn free_model_relaxes_with_falling_energy_and_unit_quaternion() {
        // The explicit update must sub-step, not explode.
        let (ratio, reports) = relax_unforced(false, 200);
        assert!(reports.iter().all(|r| r.substeps > 1));
        assert!(ratio < 1e-3, "{ratio}");
    }

    #[test]
    fn implicit_local_step_is_stable_far_beyond_the_explicit_bound() {
        // One solve a step, and ten steps where the explicit update needs hundreds of sub-steps.
        let (ratio, reports) = relax_unforced(true, 10);
        assert!(
            reports
                .iter()
                .all(|r| r.substeps == 1 && r.local_iterations > 0)
        );
        assert!(ratio < 1e-3, "{ratio}");
    }

    #[test]
    fn implicit_local_step_with_little_damping_reaches_the_springs_equilibrium() {
        // Global DOFs held, κ = 1 springs from every node to a displaced copy of the model:
        // with γ_d → 0 one implicit step is the static equilibrium (I + K) d = Rᵀ(t − c) − s.
        let tess = Tessellation::new(10);
        let state0 = test_state(&tess);
        let mut target_state = state0.clone();
        for (i, d) in target_state.displacement.iter_mut().enumerate() {
            *d += 0.05 * DVec3::new((i as f64).cos(), (i as f64 * 0.5).sin(), 0.3);
        }
        let mut target = Vec::new();
        target_state.node_positions(&tess, &mut target);
        let (forces, _) = springs_to(&tess, &state0, &target);
        let params = DynamicsParams {
            implicit_local: true,
            gamma_local: 1e-12,
            w0: 0.01,
            w1: 0.5,
            free: FreeDofs {
                translation: false,
                rotation: false,
                shape: [false; NUM_SHAPE],
                ..Default::default()
            },
            ..Default::default()
        };
        let mut state = state0.clone();
        step(
            &tess,
            &mut state,
            &forces,
            &params,
            &mut Workspace::default(),
        )
        .expect("finite");
        let d = &state.displacement;
        let mut lhs = d.clone();
        tess.apply_stiffness(params.w0, params.w1, d, &mut lhs);
        // Rᵀ(t − c) − s = d_target, the target's own displacement (same pose and shape).
        let worst = lhs
            .iter()
            .zip(&target_state.displacement)
            .map(|(l, t)| (*l - *t).length())
            .fold(0.0, f64::max);
        assert!(worst < 1e-5, "equilibrium residual {worst}");
        assert!(state.displacement != state0.displacement);
    }

    #[test]
    fn implicit_local_joint_steps_bring_node_springs_to_rest_with_falling_energy() {
        // Global and local DOFs free, springs to a moved, reshaped and displaced copy: the global
        // Gauss–Newton step and the implicit membrane after it (Gauss–Seidel) must not overshoot.
        let tess = Tessellation::new(10);
        let mut target_state = test_state(&tess);
        target_state.translation += DVec3::new(0.05, -0.03, 0.02);
        target_state.shape.a1 *= 1.1;
        for (i, d) in target_state.displacement.iter_mut().enumerate() {
            *d += 0.03 * DVec3::new((i as f64 * 0.9).cos(), (i as f64 * 0.5).sin(), 0.1);
        }
        let mut target = Vec::new();
        target_state.node_positions(&tess, &mut target);
        let params = DynamicsParams {
            implicit_local: true,
            gamma_local: 0.01,
            gamma_global: 0.05,
            w0: 0.01,
            w1: 0.1,
            ..Default::default()
        };
        let mut state = test_state(&tess);
        let mut ws = Workspace::default();
        let total = |state: &ModelState| {
            springs_to(&tess, state, &target).1
                + tess.strain_energy(params.w0, params.w1, &state.displacement)
        };
        let start = total(&state);
        let mut energy = start;
        for _ in 0..40 {
            let (forces, _) = springs_to(&tess, &state, &target);
            step(&tess, &mut state, &forces, &params, &mut ws).expect("finite");
            assert!(state.is_finite());
            let e = total(&state);
            assert!(e <= energy * (1.0 + 1e-9), "energy rose: {energy} -> {e}");
            energy = e;
        }
        assert!(energy < 0.05 * start, "{energy} of {start}");
    }

    /// Springs κ = 1 from every node to where the same node of `target` is, and their energy.
    fn springs_to(tess: &Tessellation, state: &ModelState, target: &[DVec3]) -> (NodalForces, f64) {
        let mut x = Vec::new();
        state.node_positions(tess, &mut x);
        let mut f = NodalForces::new(tess.node_count());
        let mut energy = 0.0;
        for i in 0..x.len() {
            f.force[i] = target[i] - x[i];
            f.stiffness[i] = 1.0;
            energy += 0.5 * (target[i] - x[i]).length_squared();
        }
        (f, energy)
    }

    #[test]
    fn free_taper_and_bend_recover_a_deformed_target_with_falling_energy() {
        // Node springs to a tapered, bent copy of the model: the global step (Gauss–Newton on
        // the springs) must bring q_T from 0 to the target's, the energy falling every step.
        let tess = Tessellation::new(10);
        // Elongated along z, so that the target's bend is well inside its bound.
        let start = ModelState {
            shape: SuperquadricParams {
                a: 1.5,
                a1: 0.5,
                a2: 0.4,
                a3: 1.0,
                e1: 0.8,
                e2: 1.2,
            },
            displacement: vec![DVec3::ZERO; tess.node_count()],
            ..test_state(&tess)
        };
        let truth = ModelState {
            deformation: GlobalDeformation {
                taper: [0.35, -0.25],
                bend: [0.5, 0.3],
            },
            ..start.clone()
        };
        let mut target = Vec::new();
        truth.node_positions(&tess, &mut target);
        let mut params = DynamicsParams::default();
        params.free.local = false;
        params.free.taper = true;
        params.free.bend = true;
        let mut state = start.clone();
        let mut ws = Workspace::default();
        let (_, mut energy) = springs_to(&tess, &state, &target);
        let first = energy;
        for _ in 0..300 {
            let (forces, e) = springs_to(&tess, &state, &target);
            // (Once at rounding level, the energy only wanders there.)
            assert!(
                e <= energy * (1.0 + 1e-9) + 1e-24 * first,
                "energy rose: {energy} -> {e}"
            );
            energy = e;
            step(&tess, &mut state, &forces, &params, &mut ws).expect("finite");
        }
        assert!(energy < 1e-10 * first, "energy {first} -> {energy}");
        for (got, want) in state
            .deformation
            .to_array()
            .iter()
            .zip(truth.deformation.to_array())
        {
            assert!((got - want).abs() < 1e-5, "{:?}", state.deformation);
        }
        // Held, the same springs leave q_T at 0.
        params.free.taper = false;
        params.free.bend = false;
        let mut held = start.clone();
        for _ in 0..20 {
            let (forces, _) = springs_to(&tess, &held, &target);
            step(&tess, &mut held, &forces, &params, &mut ws).expect("finite");
        }
        assert!(held.deformation.is_identity());
    }

    /// Unit-stiffness forces on every node, `force(along)` from its coordinate along the model's
    /// z axis.
    fn axial_pull(
        tess: &Tessellation,
        state: &ModelState,
        force: impl Fn(f64) -> DVec3,
    ) -> NodalForces {
        let mut x = Vec::new();
        state.node_positions(tess, &mut x);
        let mut forces = NodalForces::new(tess.node_count());
        let axis = rotation_matrix(state.rotation) * DVec3::Z;
        for i in 0..x.len() {
            forces.force[i] = force((x[i] - state.translation).dot(axis));
            forces.stiffness[i] = 1.0;
        }
        forces
    }

    #[test]
    fn taper_and_bend_stay_within_bounds_under_any_pull() {
        // Huge opposite pulls on the two ends, sideways: the state stays finite and q_T within
        // its bounds (no point crosses the centre of curvature).
        let tess = Tessellation::new(8);
        let mut state = ModelState {
            displacement: vec![DVec3::ZERO; tess.node_count()],
            ..test_state(&tess)
        };
        let mut params = DynamicsParams::default();
        params.free.taper = true;
        params.free.bend = true;
        let mut ws = Workspace::default();
        for k in 0..200 {
            let side = rotation_matrix(state.rotation) * DVec3::X;
            let forces = axial_pull(&tess, &state, |along| {
                1e4 * along.signum() * side * if k % 50 < 25 { 1.0 } else { -3.0 }
            });
            step(&tess, &mut state, &forces, &params, &mut ws).expect("finite");
            assert!(state.is_finite());
            assert_eq!(
                state.deformation,
                state.deformation.clamped(state.shape.semi_axes())
            );
        }
        assert!(!state.deformation.is_identity());
    }

    #[test]
    fn an_exponent_set_below_the_bound_neither_jumps_to_it_nor_sinks_further() {
        // A box-like shape with ε1 = 0.03 (as the squareness extension leaves one), squeezed and
        // then stretched along z: ε1 may rise, fall back to 0.03, never below it, and does not
        // jump to MIN_EPSILON at the first step.
        use crate::model::superquadric::MIN_EPSILON;
        let tess = Tessellation::new(8);
        let mut state = test_state(&tess);
        state.shape.e1 = 0.03;
        let params = DynamicsParams::default();
        let mut ws = Workspace::default();
        let mut seen = Vec::new();
        for k in 0..60 {
            let axis = rotation_matrix(state.rotation) * DVec3::Z;
            let forces = axial_pull(&tess, &state, |along| {
                along * axis * if k < 30 { -5.0 } else { 5.0 }
            });
            step(&tess, &mut state, &forces, &params, &mut ws).expect("finite");
            assert!(
                state.is_finite() && state.shape.e1 >= 0.03,
                "{:?}",
                state.shape
            );
            seen.push(state.shape.e1);
        }
        assert!(seen[0] < MIN_EPSILON, "{seen:?}");
        assert!(seen.iter().any(|&e| e != 0.03), "ε1 never moved: {seen:?}");
    }

    #[test]
    fn non_finite_force_leaves_state_untouched() {
        let tess = Tessellation::new(5);
        let mut state = test_state(&tess);
        let before = state.clone();
        let mut forces = NodalForces::new(tess.node_count());
        forces.force[3] = DVec3::new(f64::NAN, 0.0, 0.0);
        forces.stiffness[3] = 1.0;
        let err = step(
            &tess,
            &mut state,
            &forces,
            &DynamicsParams::default(),
            &mut Workspace::default(),
        );
        assert!(err.is_err());
        assert_eq!(state, before);
    }

    #[test]
    fn planar_motion_holds_depth_and_turns_only_about_z() {
        let tess = Tessellation::new(8);
        let mut state = test_state(&tess);
        let mut forces = test_forces(&tess);
        for k in forces.stiffness.iter_mut() {
            *k = 1.0;
        }
        let mut params = DynamicsParams::default();
        params.free.planar = true;
        let before = state.clone();
        let mut ws = Workspace::default();
        for _ in 0..5 {
            step(&tess, &mut state, &forces, &params, &mut ws).unwrap();
        }
        assert_eq!(state.translation.z, before.translation.z);
        assert!((state.translation - before.translation).truncate().length() > 1e-6);
        // The relative turn is about world z: it maps ẑ to itself.
        let turn = state.rotation * before.rotation.inverse();
        assert!((turn * DVec3::Z - DVec3::Z).length() < 1e-9, "{turn:?}");
        assert!(turn.to_axis_angle().1.abs() > 1e-6);
        // Without the constraint the same forces turn the model out of the plane.
        let mut free = before.clone();
        params.free.planar = false;
        step(&tess, &mut free, &forces, &params, &mut ws).unwrap();
        let turn = free.rotation * before.rotation.inverse();
        assert!((turn * DVec3::Z - DVec3::Z).length() > 1e-6);
    }
}
