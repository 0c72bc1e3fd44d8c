//! The global block of the damping and the step: the generalized forces of eq. (33), the
//! stiffness-weighted Gram matrix C_g and the trust-region-limited increment Δt C_g⁻¹ f_g.

use super::*;

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
pub(super) fn jacobian_coefficients(q: &SuperquadricParams) -> [[[f64; 3]; NUM_SHAPE]; 3] {
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
pub(super) fn log_features(t: &Trig) -> [[f64; 3]; 3] {
    [
        [1.0, t.ln_cu, t.ln_cv],
        [1.0, t.ln_cu, t.ln_sv],
        [1.0, t.ln_su, 0.0],
    ]
}

pub(super) fn dot3(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// What the global system reads at a node where a force acts.
#[derive(Clone, Copy)]
pub(super) struct ForcedNode {
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
pub(super) fn for_each_forced_node(
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
pub(super) fn global_system(
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
pub(super) fn global_system_general(
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
pub(super) struct RingSums {
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
pub(super) struct Moments {
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
pub(super) fn add<const N: usize>(acc: &mut [f64; N], scale: f64, terms: [f64; N]) {
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
pub(super) fn global_system_superquadric(
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

/// The global block of one Euler step: δq_g = Δt C_g⁻¹ f_g (eq. 15), frozen DOFs removed.
pub(super) fn global_increment(
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
pub(super) fn planar_rotation_basis(q: DQuat) -> [[f64; 4]; 4] {
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
pub(super) fn change_rotation_basis(
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
pub(super) fn limit_global(delta: &mut [f64; NUM_GLOBAL], state: &ModelState) -> bool {
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
