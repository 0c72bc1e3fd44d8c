//! Second-order dynamics: the full equations of motion M q̈ + C q̇ + K q = g_q + f_q (eq. 12,
//! Appendix A), which the paper derives but does not simulate (section VII lists them as work in
//! progress). A model with mass swings, overshoots and settles like a physical object.
//!
//! # Mass
//! The kinetic energy is eq. (24) with the mass lumped at the nodes: node i carries
//! m_i = μ A_i (A_i its area in material coordinates, as for the damping of `dynamics`), so
//! T = ½ Σ m_i |ẋ_i|² = ½ q̇ᵀ M q̇ with M = Σ m_i L_iᵀ L_i. Lumped like this M is singular: the
//! 3n node velocities cannot determine the 3n local and the global velocities together (the
//! local displacements alone can make any motion of the nodes). We add an inertia of the
//! deformation coordinates themselves, ½ Σ m_d,i |ḋ_i|² with m_d,i = λ m_i (λ =
//! [`InertiaParams::local_inertia`]): it makes M positive definite, it is invariant under
//! translations and rotations of the whole model (so momentum and angular momentum are still
//! conserved, and a force F still accelerates the centre of mass by F / Σ m_i), and it decides how
//! a motion of the nodes is shared between the global and local coordinates.
//!
//! # Coordinates
//! The velocity is v = (ċ, Ω, Ȧ, ε̇, q̇_T, ḋ): Ω the angular velocity in world space (the
//! quaternion's four rates have a gauge direction that carries no motion), Ȧ the rates of the
//! semi-axes A = a·(a1, a2, a3) (a and a_i are redundant: only their products move the surface),
//! then the exponents', the tapering and bending rates ([`super::deform`]) and the local ones.
//! Node i's velocity is ẋ_i = ċ + Ω × r_i + R (P_i q̇_g + ḋ_i), r_i = R p_i, P_i = ∂p_i/∂(A, ε, q_T):
//! the columns of L_i (eq. 11) in these coordinates.
//!
//! # Equations
//! Kane's form of eqs. (34)–(36): Σ_i L_iᵀ (m_i ẍ_i − F_i) + (ghost and elastic terms) = 0 with
//! ẍ_i = L_i v̇ + a_i, where the velocity-product term
//! a_i = Ω × (Ω × r_i) + 2 Ω × R u_i + R D²p_i[q̇_g, q̇_g], u_i = P_i q̇_g + ḋ_i,
//! carries the centrifugal and Coriolis forces g_q = −Σ m_i L_iᵀ a_i of eq. (36). The local rows
//! are eliminated node by node (M_dd is diagonal), leaving a 15 × 15 system for the global
//! accelerations with S = Σ m_i m_d,i / (m_i + m_d,i) L_g,iᵀ L_g,i.
//!
//! # Damping and integration
//! Damping is mass-proportional (C = β M, eq. 28 with γ = β μ): it takes energy at the rate
//! 2βT and leaves the motion's shape alone. Integration is semi-implicit (symplectic) Euler,
//! v ← v + h v̇(q, v), then q ← q ⊕ h v, sub-stepped within the explicit stability bound of the
//! membrane and the springs on the lightest node. With β = 0 and no forces, energy, momentum and
//! angular momentum are conserved to O(h) (tested).

use super::deform::GlobalDeformation;
use super::dynamics::{DynamicsParams, FreeDofs, ModelState, NodalForces, StepError, StepReport};
use super::fem::{GridPowers, Tessellation};
use super::frame::rotation_matrix;
use super::linalg::cholesky_solve;
use super::superquadric::{
    MAX_EPSILON, MIN_ASPECT, MIN_EPSILON, SuperquadricParams, epsilon_floor,
};
use glam::{DMat3, DQuat, DVec3};

#[cfg(test)]
mod tests;

/// Number of global velocity coordinates: ċ (3), Ω (3), Ȧ (3), ε̇ (2), q̇_T (4).
pub const NUM_GLOBAL_VELOCITY: usize = 15;
/// Number of shape velocity coordinates in q̇_g: Ȧ (3), ε̇ (2), q̇_T (4).
const NUM_SHAPE_VELOCITY: usize = 9;
/// Most sub-steps one [`step`] takes before it clamps the step.
pub const MAX_SUBSTEPS: u32 = 256;

/// Mass, damping and the inertia of the deformation coordinates.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct InertiaParams {
    /// Mass density μ per unit material area (node i weighs μ A_i).
    pub mass_density: f64,
    /// Ratio λ of the deformation coordinates' own inertia to the node mass, m_d,i = λ m_i (> 0).
    pub local_inertia: f64,
    /// Damping rate β (1/time): C = β M. 0 conserves energy.
    pub damping: f64,
}

impl Default for InertiaParams {
    /// μ = 0.01, λ = 1, β = 0.5. The material area of a whole model is π · 2π ≈ 19.7, so a
    /// model weighs about 0.2 whatever its size: the sandbox's mouse spring (constant about
    /// 2 w1 = 0.2) then swings it with a period of a few seconds, and it overshoots once or twice
    /// before it settles.
    fn default() -> Self {
        Self {
            mass_density: 0.01,
            local_inertia: 1.0,
            damping: 0.5,
        }
    }
}

/// The generalized velocity v of a model (see the module docs).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Velocity {
    /// ċ, world.
    pub linear: DVec3,
    /// Ω, world.
    pub angular: DVec3,
    /// Ȧ: rates of the semi-axes a·(a1, a2, a3).
    pub axes: DVec3,
    /// ε̇1, ε̇2.
    pub epsilon: [f64; 2],
    /// Rates of (t_x, t_y, b_x, b_y).
    pub deformation: [f64; 4],
    /// ḋ_i, model frame, one per node (missing ones count as zero).
    pub local: Vec<DVec3>,
}

impl Velocity {
    /// At rest on `n` nodes.
    pub fn zero(n: usize) -> Self {
        Self {
            local: vec![DVec3::ZERO; n],
            ..Self::default()
        }
    }

    /// True when every component is finite.
    pub fn is_finite(&self) -> bool {
        self.global().iter().all(|x| x.is_finite()) && self.local.iter().all(|d| d.is_finite())
    }

    /// The global part (ċ, Ω, Ȧ, ε̇, q̇_T).
    pub fn global(&self) -> [f64; NUM_GLOBAL_VELOCITY] {
        let mut g = [0.0; NUM_GLOBAL_VELOCITY];
        g[..3].copy_from_slice(&self.linear.to_array());
        g[3..6].copy_from_slice(&self.angular.to_array());
        g[6..9].copy_from_slice(&self.axes.to_array());
        g[9..11].copy_from_slice(&self.epsilon);
        g[11..].copy_from_slice(&self.deformation);
        g
    }

    fn set_global(&mut self, g: &[f64; NUM_GLOBAL_VELOCITY]) {
        self.linear = DVec3::new(g[0], g[1], g[2]);
        self.angular = DVec3::new(g[3], g[4], g[5]);
        self.axes = DVec3::new(g[6], g[7], g[8]);
        self.epsilon = [g[9], g[10]];
        self.deformation = [g[11], g[12], g[13], g[14]];
    }

    /// ḋ_i (zero where missing).
    fn local_at(&self, i: usize) -> DVec3 {
        self.local.get(i).copied().unwrap_or_default()
    }
}

/// What one node contributes: its world position r_i relative to c, and the model-frame shape
/// columns P_i, rate P_i q̇_g and second derivative D²p_i[q̇_g, q̇_g].
struct NodeKinematics {
    r: DVec3,
    p_cols: [DVec3; NUM_SHAPE_VELOCITY],
    shape_rate: DVec3,
    curvature: DVec3,
}

/// Per-node kinematics of `state` moving at `v`, in node order.
fn node_kinematics(
    tess: &Tessellation,
    state: &ModelState,
    v: &Velocity,
    grid: &mut GridPowers,
    mut visit: impl FnMut(usize, &NodeKinematics),
) {
    let q = &state.shape;
    tess.grid_powers(q, grid);
    let axes = q.semi_axes();
    let rot = rotation_matrix(state.rotation);
    let deformation = state.deformation;
    let deformed = !deformation.is_identity() || v.deformation != [0.0; 4];
    let global = v.global();
    let shape_rate: [f64; NUM_SHAPE_VELOCITY] = std::array::from_fn(|k| global[6 + k]);
    let deformation_q = deformation.to_array();
    let grid = &*grid;
    tess.for_each_grid_node(|i, ring, lon| {
        let [cu, su] = grid.rings[ring];
        let [cv, sv] = lon.map_or(grid.poles[usize::from(ring != 0)], |j| grid.longitudes[j]);
        let ([ln_cu, ln_su], [ln_cv, ln_sv]) = tess.grid_logs(ring, lon);
        let base = DVec3::new(cu * cv, cu * sv, su);
        // ∂base/∂ε1, ∂base/∂ε2 (base_c φ_c, see `dynamics`).
        let d_e1 = base * DVec3::new(ln_cu, ln_cu, ln_su);
        let d_e2 = base * DVec3::new(ln_cv, ln_sv, 0.0);
        let s = axes * base;
        // Superquadric columns ∂s/∂(A, ε) and the second derivative of s along (Ȧ, ε̇):
        // s_c = A_c base_c(ε) with ∂base_c/∂ε = base_c φ_c, so
        // D²s_c = 2 Ȧ_c base_c (φ_c·ε̇) + A_c base_c (φ_c·ε̇)².
        let s_cols = [
            DVec3::new(base.x, 0.0, 0.0),
            DVec3::new(0.0, base.y, 0.0),
            DVec3::new(0.0, 0.0, base.z),
            axes * d_e1,
            axes * d_e2,
        ];
        let (ad, ed) = (v.axes, v.epsilon);
        let phi_e = DVec3::new(
            ln_cu * ed[0] + ln_cv * ed[1],
            ln_cu * ed[0] + ln_sv * ed[1],
            ln_su * ed[0],
        );
        let d2s = 2.0 * ad * base * phi_e + axes * base * phi_e * phi_e;
        let ds: DVec3 = (0..5).map(|k| shape_rate[k] * s_cols[k]).sum();
        let d = state.displacement.get(i).copied().unwrap_or_default();
        let (p, p_cols, curvature) = if deformed {
            let t = deformation.jacobian(s, axes.z);
            let mut cols = [DVec3::ZERO; NUM_SHAPE_VELOCITY];
            for k in 0..5 {
                cols[k] = t.d_point * s_cols[k];
            }
            cols[2] += t.d_height;
            cols[5..].copy_from_slice(&t.d_params);
            // D²(T∘s): T_s D²s plus T's own second derivative along w = (ṡ, Ȧ_z, q̇_T), by a
            // central difference of T's first derivative along w.
            let tau = 1e-5;
            let along = |sign: f64| {
                let moved = GlobalDeformation::from_array(std::array::from_fn(|k| {
                    deformation_q[k] + sign * tau * v.deformation[k]
                }));
                let j = moved.jacobian(s + sign * tau * ds, axes.z + sign * tau * ad.z);
                j.d_point * ds
                    + j.d_height * ad.z
                    + (0..4)
                        .map(|k| v.deformation[k] * j.d_params[k])
                        .sum::<DVec3>()
            };
            let d2t = (along(1.0) - along(-1.0)) / (2.0 * tau);
            (t.value + d, cols, t.d_point * d2s + d2t)
        } else {
            let mut cols = [DVec3::ZERO; NUM_SHAPE_VELOCITY];
            cols[..5].copy_from_slice(&s_cols);
            (s + d, cols, d2s)
        };
        let shape_rate = p_cols.iter().zip(&shape_rate).map(|(c, x)| *x * *c).sum();
        visit(
            i,
            &NodeKinematics {
                r: rot * p,
                p_cols,
                shape_rate,
                curvature,
            },
        );
    });
}

/// The velocity-product acceleration a_i = Ω × (Ω × r_i) + 2 Ω × R u_i + R D²p_i[q̇_g, q̇_g]
/// of a node (ẍ_i = L_i v̇ + a_i), and u_i = P_i q̇_g + ḋ_i.
fn velocity_product(rot: &DMat3, v: &Velocity, i: usize, k: &NodeKinematics) -> DVec3 {
    let omega = v.angular;
    let u = shape_velocity(v, i, k);
    omega.cross(omega.cross(k.r)) + 2.0 * omega.cross(*rot * u) + *rot * k.curvature
}

/// u_i = P_i q̇_g + ḋ_i: the node's velocity relative to the model frame, in that frame.
fn shape_velocity(v: &Velocity, i: usize, k: &NodeKinematics) -> DVec3 {
    k.shape_rate + v.local_at(i)
}

/// Which global velocity coordinates move under `free`.
fn free_global(free: &FreeDofs) -> [bool; NUM_GLOBAL_VELOCITY] {
    std::array::from_fn(|k| match k {
        0 | 1 => free.translation,
        2 => free.translation && !free.planar,
        3 | 4 => free.rotation && !free.planar,
        5 => free.rotation,
        // Semi-axis A_k moves with its aspect ratio (planar motion holds the depth's, a2).
        6..=8 => free.shape[k - 5],
        9 => free.shape[4],
        10 => free.shape[5],
        11 | 12 => free.taper,
        _ => free.bend,
    })
}

/// The accelerations v̇ = (global, local) of `state` moving at `v` under `forces` (eq. 12 in
/// Kane's form, see the module docs), with the membrane of `params` (w0, w1) and its free DOFs.
/// Mass-proportional damping is not included. With `origin` (the node positions the forces were
/// computed at), each node's springs are linearised about it, F − κ (x − x⁰), as the
/// first-order step does: sub-steps then follow stiff springs instead of holding their force.
pub fn accelerations(
    tess: &Tessellation,
    state: &ModelState,
    v: &Velocity,
    forces: &NodalForces,
    params: &DynamicsParams,
    inertia: &InertiaParams,
    origin: Option<&[DVec3]>,
) -> Result<([f64; NUM_GLOBAL_VELOCITY], Vec<DVec3>), StepError> {
    let mut buffers = AccelerationBuffers::default();
    let global = accelerations_in(
        &mut buffers,
        tess,
        state,
        v,
        forces,
        params,
        inertia,
        origin,
    )?;
    Ok((global, buffers.d_acc))
}

/// Reusable buffers for [`step`], and the membrane's row bounds cached by (w0, w1, mesh), so that a
/// step allocates nothing after the first and recomputes only what changed.
#[derive(Clone, Debug, Default)]
pub struct InertiaWorkspace {
    /// The node positions at the step's start, about which the springs are linearised.
    origin: Vec<DVec3>,
    rows: Vec<f64>,
    rows_key: Option<(f64, f64, usize)>,
    acc: AccelerationBuffers,
}

/// The buffers of one evaluation of the accelerations.
#[derive(Clone, Debug, Default)]
struct AccelerationBuffers {
    grid: GridPowers,
    kd: Vec<DVec3>,
    /// [Rᵀ(F − m a) − K d] / (m + m_d) per node, model frame.
    local_rhs: Vec<DVec3>,
    /// The world columns of L_g,i per node.
    cols: Vec<[DVec3; NUM_GLOBAL_VELOCITY]>,
    /// The local accelerations d̈_i.
    d_acc: Vec<DVec3>,
    /// When set, the next [`accelerations_in`] also gathers the springs' stiffness on the
    /// global coordinates and leaves in `global_rate` the bound on their ω² (see
    /// [`global_rate_bound`]); cleared by that call.
    rate_wanted: bool,
    /// ω² bound of the global modes from the last call that wanted it.
    global_rate: f64,
}

impl InertiaWorkspace {
    /// Σ_j |K_ij| per node for (w0, w1), computed when they or the mesh change.
    fn row_bounds(&mut self, tess: &Tessellation, w0: f64, w1: f64) -> &[f64] {
        let key = (w0, w1, tess.node_count());
        if self.rows_key != Some(key) {
            self.rows = tess.stiffness_row_bounds(w0, w1);
            self.rows_key = Some(key);
        }
        &self.rows
    }
}

/// [`accelerations`] into `buffers`: returns the global part, leaves the local one in
/// `buffers.d_acc`.
#[allow(clippy::too_many_arguments)]
fn accelerations_in(
    buffers: &mut AccelerationBuffers,
    tess: &Tessellation,
    state: &ModelState,
    v: &Velocity,
    forces: &NodalForces,
    params: &DynamicsParams,
    inertia: &InertiaParams,
    origin: Option<&[DVec3]>,
) -> Result<[f64; NUM_GLOBAL_VELOCITY], StepError> {
    let n = tess.node_count();
    let rot = rotation_matrix(state.rotation);
    let rt = rot.transpose();
    let local = params.free.local;
    let AccelerationBuffers {
        grid,
        kd,
        local_rhs,
        cols: cols_store,
        d_acc,
        rate_wanted,
        global_rate,
    } = buffers;
    let want_rate = std::mem::take(rate_wanted);
    let mut k_mat = [[0.0; NUM_GLOBAL_VELOCITY]; NUM_GLOBAL_VELOCITY];
    kd.clear();
    kd.resize(n, DVec3::ZERO);
    if local {
        tess.apply_stiffness(params.w0, params.w1, &state.displacement, kd);
    }
    let lambda = inertia.local_inertia;
    // Per node: the world columns of L_g,i (15), the terms of the global right-hand side, and
    // what the local row needs afterwards.
    let mut s_mat = [[0.0; NUM_GLOBAL_VELOCITY]; NUM_GLOBAL_VELOCITY];
    let mut rhs = [0.0; NUM_GLOBAL_VELOCITY];
    local_rhs.clear();
    local_rhs.resize(n, DVec3::ZERO);
    cols_store.clear();
    node_kinematics(tess, state, v, grid, |i, k| {
        let m = inertia.mass_density * tess.node_area[i];
        // ρ = m / (m + m_d) with the local coordinates free; 0 when they are held.
        let rho = if local { 1.0 / (1.0 + lambda) } else { 0.0 };
        let a = velocity_product(&rot, v, i, k);
        let moved = origin
            .and_then(|x0| x0.get(i))
            .map_or(DVec3::ZERO, |x0| state.translation + k.r - *x0);
        let f = forces.force[i] - forces.stiffness[i] * moved;
        let f_global = forces.shape_force[i] - forces.shape_stiffness[i] * moved;
        let mut cols = [DVec3::ZERO; NUM_GLOBAL_VELOCITY];
        cols[0] = DVec3::X;
        cols[1] = DVec3::Y;
        cols[2] = DVec3::Z;
        // Ω × r = −r × Ω: column j is e_j × r.
        cols[3] = DVec3::X.cross(k.r);
        cols[4] = DVec3::Y.cross(k.r);
        cols[5] = DVec3::Z.cross(k.r);
        for (c, p) in cols[6..].iter_mut().zip(&k.p_cols) {
            *c = rot * *p;
        }
        let w = m * (1.0 - rho);
        let g = (1.0 - rho) * (f - m * a) + f_global + rho * (rot * kd[i]);
        for x in 0..NUM_GLOBAL_VELOCITY {
            rhs[x] += cols[x].dot(g);
            for y in x..NUM_GLOBAL_VELOCITY {
                s_mat[x][y] += w * cols[x].dot(cols[y]);
            }
        }
        // The springs' stiffness on the global coordinates, as the right-hand side feels it.
        let kappa = (1.0 - rho) * forces.stiffness[i] + forces.shape_stiffness[i];
        if want_rate && kappa > 0.0 {
            for x in 0..NUM_GLOBAL_VELOCITY {
                for y in x..NUM_GLOBAL_VELOCITY {
                    k_mat[x][y] += kappa * cols[x].dot(cols[y]);
                }
            }
        }
        if local {
            local_rhs[i] = (rt * (f - m * a) - kd[i]) / (m * (1.0 + lambda));
        }
        cols_store.push(cols);
    });
    let free = free_global(&params.free);
    let scale = s_mat
        .iter()
        .enumerate()
        .map(|(i, r)| r[i])
        .fold(0.0, f64::max)
        .max(1e-300);
    for x in 0..NUM_GLOBAL_VELOCITY {
        for y in 0..x {
            s_mat[x][y] = s_mat[y][x];
        }
    }
    for x in 0..NUM_GLOBAL_VELOCITY {
        if !free[x] {
            hold(&mut s_mat, &mut rhs, x);
        } else {
            // A node set with no extent along a direction (e.g. ε at a sphere's axes) leaves a
            // tiny pivot; a relative ridge keeps the solve finite.
            s_mat[x][x] += 1e-12 * scale;
        }
    }
    if !rhs.iter().all(|x| x.is_finite()) {
        return Err(StepError::NonFinite("generalized force f_q"));
    }
    if want_rate {
        *global_rate = global_rate_bound(&s_mat, k_mat, &free);
    }
    let singular = StepError::NonFinite("mass matrix M (Schur block)");
    let mut global = cholesky_solve(&s_mat, &rhs).ok_or(singular.clone())?;
    // A coordinate at its bound that the solve pushes through it is held there, and the rest
    // solved again: clipped after the fact (`advance`), its share of the coupled motion would
    // go to the coordinates it is coupled with through M, and pump them without bound.
    let pushed = pushed_at_bounds(state, v, &global);
    if pushed.iter().any(|&p| p) {
        for x in (0..NUM_GLOBAL_VELOCITY).filter(|&x| pushed[x]) {
            hold(&mut s_mat, &mut rhs, x);
        }
        global = cholesky_solve(&s_mat, &rhs).ok_or(singular)?;
    }
    d_acc.clear();
    d_acc.resize(n, DVec3::ZERO);
    if local {
        let rho = 1.0 / (1.0 + lambda);
        for i in 0..n {
            let lg: DVec3 = (0..NUM_GLOBAL_VELOCITY)
                .map(|x| global[x] * cols_store[i][x])
                .sum();
            d_acc[i] = local_rhs[i] - rho * (rt * lg);
        }
    }
    Ok(global)
}

/// Holds global coordinate `x` in the solve S v̇ = rhs: its row and column become the identity's
/// and its force zero, so that its acceleration is 0 and the others are solved without it.
fn hold(
    s_mat: &mut [[f64; NUM_GLOBAL_VELOCITY]; NUM_GLOBAL_VELOCITY],
    rhs: &mut [f64; NUM_GLOBAL_VELOCITY],
    x: usize,
) {
    for y in 0..NUM_GLOBAL_VELOCITY {
        s_mat[x][y] = 0.0;
        s_mat[y][x] = 0.0;
    }
    s_mat[x][x] = 1.0;
    rhs[x] = 0.0;
}

/// The coordinates at a bound of `advance` that are not moving away from it and that the
/// accelerations `acc` would push through it: semi-axes at [`MIN_ASPECT`] of the largest,
/// exponents at [`MAX_EPSILON`] or at or below [`MIN_EPSILON`] (where a step may not lower
/// them), and tapering and bending at the bounds of [`GlobalDeformation::clamped`].
fn pushed_at_bounds(
    state: &ModelState,
    v: &Velocity,
    acc: &[f64; NUM_GLOBAL_VELOCITY],
) -> [bool; NUM_GLOBAL_VELOCITY] {
    let shape = &state.shape;
    let mut out = [false; NUM_GLOBAL_VELOCITY];
    let axes = shape.semi_axes().to_array();
    let min_axis = MIN_ASPECT * shape.a * (1.0 + 1e-9);
    for k in 0..3 {
        out[6 + k] = axes[k] <= min_axis && v.axes[k] <= 0.0 && acc[6 + k] < 0.0;
    }
    for (k, e) in [shape.e1, shape.e2].into_iter().enumerate() {
        let (rate, a) = (v.epsilon[k], acc[9 + k]);
        out[9 + k] = (e >= MAX_EPSILON && rate >= 0.0 && a > 0.0)
            || (e <= MIN_EPSILON && rate <= 0.0 && a < 0.0);
    }
    let q = state.deformation.to_array();
    for k in 0..4 {
        let a = acc[11 + k];
        if a == 0.0 || v.deformation[k] * a < 0.0 {
            continue;
        }
        let mut moved = q;
        moved[k] += 1e-9 * (1.0 + q[k].abs()) * a.signum();
        let kept = GlobalDeformation::from_array(moved).clamped(shape.semi_axes());
        out[11 + k] = kept.to_array()[k] != moved[k];
    }
    out
}

/// An upper bound on ω² of the global modes: the largest eigenvalue of S⁻¹ K_g, with S the
/// global coordinates' mass and K_g = Σ κ_i L_g,iᵀ L_g,i the springs' stiffness on them (upper
/// triangle), bounded by its trace Σ_j (S⁻¹ K_g)_jj, since every eigenvalue is ≥ 0. A spring
/// on one node may move a coordinate whose share of the mass is small (an exponent, a semi-axis
/// at the node's end), so the whole model's mass alone misjudges it. ∞ when S is not positive
/// definite, so that the step then takes its most sub-steps.
fn global_rate_bound(
    s_mat: &[[f64; NUM_GLOBAL_VELOCITY]; NUM_GLOBAL_VELOCITY],
    mut k_mat: [[f64; NUM_GLOBAL_VELOCITY]; NUM_GLOBAL_VELOCITY],
    free: &[bool; NUM_GLOBAL_VELOCITY],
) -> f64 {
    for x in 0..NUM_GLOBAL_VELOCITY {
        for y in 0..x {
            k_mat[x][y] = k_mat[y][x];
        }
    }
    let mut trace = 0.0;
    for j in (0..NUM_GLOBAL_VELOCITY).filter(|&j| free[j] && k_mat[j][j] > 0.0) {
        let column: [f64; NUM_GLOBAL_VELOCITY] =
            std::array::from_fn(|x| if free[x] { k_mat[x][j] } else { 0.0 });
        match cholesky_solve(s_mat, &column) {
            Some(z) => trace += z[j].max(0.0),
            None => return f64::INFINITY,
        }
    }
    trace
}

/// The kinetic energy T = ½ Σ m_i |ẋ_i|² + ½ Σ λ m_i |ḋ_i|² of `state` moving at `v`.
pub fn kinetic_energy(
    tess: &Tessellation,
    state: &ModelState,
    v: &Velocity,
    inertia: &InertiaParams,
) -> f64 {
    let mut t = 0.0;
    for_each_node_velocity(tess, state, v, |i, _, xdot| {
        let m = inertia.mass_density * tess.node_area[i];
        t += 0.5
            * m
            * (xdot.length_squared() + inertia.local_inertia * v.local_at(i).length_squared());
    });
    t
}

/// Linear momentum Σ m_i ẋ_i and angular momentum Σ m_i x_i × ẋ_i about the world origin.
pub fn momentum(
    tess: &Tessellation,
    state: &ModelState,
    v: &Velocity,
    inertia: &InertiaParams,
) -> (DVec3, DVec3) {
    let (mut p, mut l) = (DVec3::ZERO, DVec3::ZERO);
    for_each_node_velocity(tess, state, v, |i, x, xdot| {
        let m = inertia.mass_density * tess.node_area[i];
        p += m * xdot;
        l += m * x.cross(xdot);
    });
    (p, l)
}

/// Calls `visit(i, x_i, ẋ_i)` for every node.
fn for_each_node_velocity(
    tess: &Tessellation,
    state: &ModelState,
    v: &Velocity,
    mut visit: impl FnMut(usize, DVec3, DVec3),
) {
    let rot = rotation_matrix(state.rotation);
    node_kinematics(tess, state, v, &mut GridPowers::default(), |i, k| {
        let xdot = v.linear + v.angular.cross(k.r) + rot * shape_velocity(v, i, k);
        visit(i, state.translation + k.r, xdot);
    });
}

/// The stability bound on h of the explicit step: 2 / ω_max, with ω_max² the larger of the
/// local bound — Gershgorin's on the membrane and the node's springs over its lightest effective
/// mass m λ / (1 + λ) — and the global one: the larger of four times all the springs over the
/// model's mass (the factor covers the lever arm of a turn) and `global_rate`, the bound of
/// [`global_rate_bound`] on the global modes.
fn critical_step(
    ws: &mut InertiaWorkspace,
    tess: &Tessellation,
    forces: &NodalForces,
    params: &DynamicsParams,
    inertia: &InertiaParams,
    global_rate: f64,
) -> f64 {
    let local = if params.free.local {
        let rows = ws.row_bounds(tess, params.w0, params.w1);
        let share = inertia.local_inertia / (1.0 + inertia.local_inertia);
        (0..tess.node_count())
            .map(|i| {
                let m = inertia.mass_density * tess.node_area[i] * share;
                (rows[i] + forces.stiffness[i]) / m
            })
            .fold(0.0, f64::max)
    } else {
        0.0
    };
    let mass = inertia.mass_density * tess.area;
    let springs: f64 =
        forces.stiffness.iter().sum::<f64>() + forces.shape_stiffness.iter().sum::<f64>();
    let omega2 = local.max(4.0 * springs / mass).max(global_rate);
    if omega2 > 0.0 {
        2.0 / omega2.sqrt()
    } else {
        f64::INFINITY
    }
}

/// One step of Δt = `params.dt` of the second-order dynamics (module docs): symplectic Euler,
/// sub-stepped within a quarter of the stability bound. On error `state` and `v` are untouched.
/// `ws` keeps the buffers from one step to the next (any workspace will do).
pub fn step(
    tess: &Tessellation,
    state: &mut ModelState,
    v: &mut Velocity,
    forces: &NodalForces,
    params: &DynamicsParams,
    inertia: &InertiaParams,
    ws: &mut InertiaWorkspace,
) -> Result<StepReport, StepError> {
    let n = tess.node_count();
    assert!(
        forces.force.len() == n && forces.shape_force.len() == n,
        "NodalForces sized for another tessellation"
    );
    if !(inertia.mass_density > 0.0 && inertia.local_inertia > 0.0 && inertia.damping >= 0.0) {
        return Err(StepError::Invalid(
            "inertia parameters: μ and λ must be > 0 and β ≥ 0",
        ));
    }
    state.node_positions(tess, &mut ws.origin);
    let mut new_state = state.clone();
    let mut new_v = v.clone();
    new_v.local.resize(n, DVec3::ZERO);
    // A coordinate held since the last step (its DOF switched off) keeps no rate: it stays put.
    let free = free_global(&params.free);
    let mut g = new_v.global();
    for (x, rate) in g.iter_mut().enumerate() {
        if !free[x] {
            *rate = 0.0;
        }
    }
    new_v.set_global(&g);
    let accelerations =
        |acc: &mut AccelerationBuffers, at: &ModelState, v: &Velocity, x0: &[DVec3]| {
            accelerations_in(acc, tess, at, v, forces, params, inertia, Some(x0))
        };
    // The first sub-step's accelerations, which also bound the global modes' rate.
    ws.acc.rate_wanted = true;
    let first = accelerations(&mut ws.acc, &new_state, &new_v, &ws.origin)?;
    let global_rate = ws.acc.global_rate;
    let dt_critical = critical_step(ws, tess, forces, params, inertia, global_rate);
    // A quarter of the bound (ω h ≤ ½): symplectic Euler is stable to ω h < 2, but its energy
    // wobbles by O(ω h), and a stiff spring should not pump a visible swing.
    let safe = 0.25 * dt_critical;
    let mut substeps = if params.dt <= safe {
        1
    } else {
        (params.dt / safe).ceil() as u32
    };
    let mut h = params.dt / substeps as f64;
    let mut clamped = false;
    if substeps > MAX_SUBSTEPS {
        substeps = MAX_SUBSTEPS;
        h = safe;
        clamped = true;
    }
    for sub in 0..substeps {
        let g_acc = if sub == 0 {
            first
        } else {
            accelerations(&mut ws.acc, &new_state, &new_v, &ws.origin)?
        };
        let decay = 1.0 / (1.0 + h * inertia.damping);
        let mut g = new_v.global();
        for x in 0..NUM_GLOBAL_VELOCITY {
            g[x] = (g[x] + h * g_acc[x]) * decay;
        }
        new_v.set_global(&g);
        if params.free.local {
            for (dv, a) in new_v.local.iter_mut().zip(&ws.acc.d_acc) {
                *dv = (*dv + h * *a) * decay;
            }
        } else {
            new_v.local.iter_mut().for_each(|d| *d = DVec3::ZERO);
        }
        advance(&mut new_state, &mut new_v, h);
    }
    if !(new_state.is_finite() && new_v.is_finite()) {
        return Err(StepError::NonFinite("state after the second-order step"));
    }
    *state = new_state;
    *v = new_v;
    Ok(StepReport {
        substeps,
        dt_critical,
        clamped,
        trust_limited: false,
        local_iterations: 0,
    })
}

/// q ← q ⊕ h v; a coordinate stopped by its bound loses its rate (an inelastic stop).
fn advance(state: &mut ModelState, v: &mut Velocity, h: f64) {
    state.translation += h * v.linear;
    state.rotation = (DQuat::from_scaled_axis(h * v.angular) * state.rotation).normalize();
    let axes = state.shape.semi_axes() + h * v.axes;
    let a = axes.max_element().max(f64::MIN_POSITIVE);
    let min_axis = MIN_ASPECT * a;
    let mut axes_rate = v.axes.to_array();
    let axes = axes.to_array().map(|x| x.max(min_axis));
    for (k, x) in axes.iter().enumerate() {
        if *x == min_axis && axes_rate[k] < 0.0 {
            axes_rate[k] = 0.0;
        }
    }
    v.axes = DVec3::from_array(axes_rate);
    let e = [
        state.shape.e1 + h * v.epsilon[0],
        state.shape.e2 + h * v.epsilon[1],
    ];
    // An exponent set below MIN_EPSILON may stay down there (`normalized_keeping`).
    let floor = [state.shape.e1, state.shape.e2].map(epsilon_floor);
    let e: [f64; 2] = std::array::from_fn(|k| e[k].clamp(floor[k], MAX_EPSILON));
    for k in 0..2 {
        if e[k] == floor[k] || e[k] == MAX_EPSILON {
            v.epsilon[k] = 0.0;
        }
    }
    state.shape = SuperquadricParams {
        a,
        // Clamped again: (MIN_ASPECT a) / a may round below MIN_ASPECT.
        a1: (axes[0] / a).clamp(MIN_ASPECT, 1.0),
        a2: (axes[1] / a).clamp(MIN_ASPECT, 1.0),
        a3: (axes[2] / a).clamp(MIN_ASPECT, 1.0),
        e1: e[0],
        e2: e[1],
    };
    let wanted: [f64; 4] =
        std::array::from_fn(|k| state.deformation.to_array()[k] + h * v.deformation[k]);
    let kept = GlobalDeformation::from_array(wanted).clamped(state.shape.semi_axes());
    for (k, (w, got)) in wanted.iter().zip(kept.to_array()).enumerate() {
        if *w != got {
            v.deformation[k] = 0.0;
        }
    }
    state.deformation = kept;
    let n = state.displacement.len();
    for (d, dv) in state.displacement.iter_mut().zip(v.local.iter().take(n)) {
        *d += h * *dv;
    }
}
