//! The finite-element discretisation of the local displacement d over material coordinates
//! u = (u, v) (section IV and Appendix B).
//!
//! **Tessellation** (Fig. 9): k latitude rings × k longitudes plus the two poles, k² + 2 nodes — the
//! paper's 963 / 1683 / 2603 / 5043 nodes are k = 31 / 41 / 51 / 71. Rings sit at
//! u_i = −π/2 + (i + 1) h_u with h_u = π/(k + 1), longitudes at v_j = −π + j h_v with h_v = 2π/k
//! (periodic). Node 0 is the south pole, node 1 + i k + j is ring i, longitude j, and node k² + 1 is
//! the north pole.
//!
//! **Elements**: bilinear quadrilaterals between rings (eqs. 48–52, 2×2 Gauss–Legendre) and, at the
//! two caps, the paper's right linear triangles (eqs. 53–68, Radau quadrature) in which the pole
//! takes the v of one of the other nodes.
//!
//! **Stiffness** (eqs. 13, 40–47): per displacement component, K^j = ∫ w1 ∇N ∇Nᵀ + w0 N Nᵀ du.
//! The paper's γ_i = [∂N_i/∂u, ∂N_i/∂v, 1]ᵀ after eq. (45) should read [.., .., N_i]ᵀ — the third
//! strain component is d_k = Σ N_i q_i — and is implemented so. K_dd is never assembled:
//! [`Tessellation::apply_stiffness`] adds K q without assembling K, as section IV prescribes.

use super::simd::with_avx2;
use super::superquadric::{SignedPowers, SuperquadricParams, Trig, spow};
use glam::DVec3;
use std::f64::consts::{FRAC_PI_2, PI, TAU};

mod bounds;
mod element;
pub use bounds::*;
pub use element::*;
#[cfg(test)]
mod tests;

/// A point inside an element: up to four nodes and their shape-function weights N_i
/// (unused slots have weight 0). Interpolates any nodal field: x(u) = Σ N_i x_i.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ElementPoint {
    /// Node indices of the element (the triangle's third node repeated in the fourth slot).
    pub nodes: [u32; 4],
    /// Shape-function values N_i at the point; they sum to 1.
    pub weights: [f64; 4],
    /// ∂N_i/∂u at the point.
    pub du: [f64; 4],
    /// ∂N_i/∂v at the point.
    pub dv: [f64; 4],
}

impl ElementPoint {
    /// A point sitting exactly on one node.
    pub fn at_node(node: u32) -> Self {
        Self {
            nodes: [node; 4],
            weights: [1.0, 0.0, 0.0, 0.0],
            du: [0.0; 4],
            dv: [0.0; 4],
        }
    }

    /// Σ N_i f(node_i) for a nodal field given by a lookup.
    #[inline]
    pub fn interpolate(&self, f: impl Fn(usize) -> DVec3) -> DVec3 {
        if self.weights[0] == 1.0 {
            // On a node (the paper's nearest-node springs): the other weights are 0.
            return f(self.nodes[0] as usize);
        }
        (0..4)
            .filter(|&i| self.weights[i] != 0.0)
            .map(|i| self.weights[i] * f(self.nodes[i] as usize))
            .sum()
    }
}

/// The tessellated material domain: node coordinates, elements and their matrices.
#[derive(Clone, Debug)]
pub struct Tessellation {
    /// Number of latitude rings and of longitudes.
    pub k: usize,
    /// Ring spacing h_u = π/(k + 1).
    pub h_u: f64,
    /// Longitude spacing h_v = 2π/k.
    pub h_v: f64,
    /// Material coordinates (u, v) of every node (the poles take v = 0).
    pub uv: Vec<[f64; 2]>,
    /// Trigonometric terms of every node, computed once (see [`Trig`]).
    pub trig: Vec<Trig>,
    /// Quadrilaterals, nodes ordered as in [`quad_element`].
    pub quads: Vec<[u32; 4]>,
    /// North-cap triangles (ring node, pole, next ring node), as in [`triangle_element`].
    pub north: Vec<[u32; 3]>,
    /// South-cap triangles (pole, ring node, next ring node), as in [`triangle_element`].
    pub south: Vec<[u32; 3]>,
    /// The shared matrices of every quadrilateral.
    pub quad_matrices: ElementMatrices<4>,
    /// The shared matrices of every north-cap triangle.
    pub north_matrices: ElementMatrices<3>,
    /// The shared matrices of every south-cap triangle.
    pub south_matrices: ElementMatrices<3>,
    /// The render triangulation (see [`Tessellation::triangles`]).
    pub tris: Vec<[u32; 3]>,
    /// Every edge of the render triangulation with the two triangles that share it:
    /// `[node a, node b, triangle 1, triangle 2]` (the surface is closed, so each edge has two).
    pub edges: Vec<[u32; 4]>,
    /// The render triangles round every node (see [`NodeTriangles`]).
    pub node_tris: NodeTriangles,
    /// Lumped nodal area A_i = ∫ N_i du (row sums of the mass matrices); Σ A_i is the area the
    /// elements cover in (u, v).
    pub node_area: Vec<f64>,
    /// |Ω| = Σ A_i, summed once (the range springs' weight β |Ω| / m needs it every step).
    pub area: f64,
}

/// The triangles round every node of a triangulation, as one list with offsets: node n's are
/// `incident[first[n]..first[n + 1]]`, in ascending order of triangle.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NodeTriangles {
    /// Where each node's triangles start in `incident` (one entry per node, and the end).
    pub first: Vec<u32>,
    /// The triangles' indices, node after node.
    pub incident: Vec<u32>,
}

impl NodeTriangles {
    /// The triangles of `tris` round each of `nodes` nodes (a corner at or past `nodes` is
    /// left out).
    pub fn of(tris: &[[u32; 3]], nodes: usize) -> Self {
        let mut first = vec![0u32; nodes + 1];
        for &n in tris.iter().flatten() {
            if let Some(count) = first.get_mut(n as usize + 1) {
                *count += 1;
            }
        }
        for n in 0..nodes {
            first[n + 1] += first[n];
        }
        let mut fill = first.clone();
        let mut incident = vec![0u32; first[nodes] as usize];
        for (t, tri) in tris.iter().enumerate() {
            for &n in tri.iter().filter(|&&n| (n as usize) < nodes) {
                let at = &mut fill[n as usize];
                incident[*at as usize] = t as u32;
                *at += 1;
            }
        }
        Self { first, incident }
    }

    /// The triangles round node `n` (none past the last node).
    pub fn of_node(&self, n: usize) -> &[u32] {
        match (self.first.get(n), self.first.get(n + 1)) {
            (Some(&a), Some(&b)) => &self.incident[a as usize..b as usize],
            _ => &[],
        }
    }
}

/// Signed powers of a superquadric on the tessellation's grid. Node (ring i, longitude j) has
/// cos^ε1 u, sin^ε1 u from ring i and cos^ε2 v, sin^ε2 v from longitude j, so a whole model needs
/// only O(k) powers instead of O(k²).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GridPowers {
    /// (cos^ε1 u, sin^ε1 u) of the south pole, the k rings, and the north pole (k + 2 entries).
    pub rings: Vec<[f64; 2]>,
    /// (cos^ε2 v, sin^ε2 v) of the k longitudes.
    pub longitudes: Vec<[f64; 2]>,
    /// (cos^ε2 v, sin^ε2 v) of the south and north pole (their v is 0).
    pub poles: [[f64; 2]; 2],
}

impl GridPowers {
    /// The signed powers of node `i` of `tess`.
    #[inline]
    pub fn at(&self, tess: &Tessellation, i: usize) -> SignedPowers {
        let (r, j) = tess.grid_index(i);
        let [cu, su] = self.rings[r];
        let [cv, sv] = match j {
            Some(j) => self.longitudes[j],
            None => self.poles[usize::from(r != 0)],
        };
        SignedPowers { cu, su, cv, sv }
    }

    /// The (cos^ε2 v, sin^ε2 v) of the nodes of ring `ring` as [`Tessellation::grid_ring`]
    /// numbers them: the k longitudes, or a pole's own entry.
    pub fn ring_longitudes(&self, ring: usize) -> &[[f64; 2]] {
        match ring {
            0 => &self.poles[..1],
            r if r > self.longitudes.len() => &self.poles[1..],
            _ => &self.longitudes,
        }
    }
}

/// Adds K_e q_e of every element in `elems` (all sharing the matrix `k`) to `out`.
fn apply_elements<const N: usize>(
    elems: &[[u32; N]],
    k: &[[f64; N]; N],
    q: &[DVec3],
    out: &mut [DVec3],
) {
    for e in elems {
        let qe: [DVec3; N] = std::array::from_fn(|j| q[e[j] as usize]);
        for i in 0..N {
            let mut acc = DVec3::ZERO;
            for j in 0..N {
                acc += k[i][j] * qe[j];
            }
            out[e[i] as usize] += acc;
        }
    }
}

/// Pairs the triangles of a closed triangulation across their shared edges, in the order of the
/// triangles: each edge when its second triangle is reached, oriented as that triangle has it.
///
/// The edges still waiting for their second triangle are kept in a list per lower node index
/// (each a few entries long; a pole's up to k). It replaced a `HashMap` keyed by the node pair,
/// whose SipHash hashing and removals took a third of the time of measuring a fit's residuals on
/// the 22 803-node tessellation ([`crate::model::fit::fit_residuals`]); the edges are the same, in the same order.
fn edge_faces(tris: &[[u32; 3]]) -> Vec<[u32; 4]> {
    const END: u32 = u32::MAX;
    let nodes = tris.iter().flatten().max().map_or(0, |&n| n as usize + 1);
    // `head[lo]`: the first waiting edge whose lower node is `lo`; `waiting[e]`: its higher node,
    // its first triangle and the next waiting edge of the same `lo`.
    let mut head = vec![END; nodes];
    let mut waiting: Vec<(u32, u32, u32)> = Vec::with_capacity(tris.len() * 3 / 2);
    let mut out = Vec::with_capacity(tris.len() * 3 / 2);
    for (ti, t) in tris.iter().enumerate() {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            let (lo, hi) = (a.min(b) as usize, a.max(b));
            let (mut prev, mut e) = (END, head[lo]);
            while e != END && waiting[e as usize].0 != hi {
                (prev, e) = (e, waiting[e as usize].2);
            }
            if e == END {
                waiting.push((hi, ti as u32, head[lo]));
                head[lo] = (waiting.len() - 1) as u32;
                continue;
            }
            let (_, other, next) = waiting[e as usize];
            match prev {
                END => head[lo] = next,
                p => waiting[p as usize].2 = next,
            }
            out.push([a, b, other, ti as u32]);
        }
    }
    debug_assert!(
        head.iter().all(|&e| e == END),
        "the triangulation is not closed"
    );
    out
}

impl Tessellation {
    /// Builds the k² + 2 node tessellation. `k` below [`MIN_K`] is raised to it, and above
    /// [`MAX_K`] held to it.
    pub fn new(k: usize) -> Self {
        let k = k.clamp(MIN_K, MAX_K);
        let h_u = PI / (k as f64 + 1.0);
        let h_v = TAU / k as f64;
        let ring = |i: usize, j: usize| (1 + i * k + (j % k)) as u32;
        let north_pole = (k * k + 1) as u32;
        let mut uv = Vec::with_capacity(k * k + 2);
        uv.push([-FRAC_PI_2, 0.0]);
        for i in 0..k {
            for j in 0..k {
                uv.push([-FRAC_PI_2 + (i as f64 + 1.0) * h_u, -PI + j as f64 * h_v]);
            }
        }
        uv.push([FRAC_PI_2, 0.0]);
        let trig = uv.iter().map(|&[u, v]| Trig::new(u, v)).collect();
        let mut quads = Vec::with_capacity((k - 1) * k);
        for i in 0..k - 1 {
            for j in 0..k {
                quads.push([
                    ring(i, j),
                    ring(i + 1, j),
                    ring(i + 1, j + 1),
                    ring(i, j + 1),
                ]);
            }
        }
        let north = (0..k)
            .map(|j| [ring(k - 1, j), north_pole, ring(k - 1, j + 1)])
            .collect();
        let south = (0..k).map(|j| [0, ring(0, j), ring(0, j + 1)]).collect();
        let mut t = Self {
            k,
            h_u,
            h_v,
            uv,
            trig,
            quads,
            north,
            south,
            quad_matrices: quad_element(h_u, h_v),
            north_matrices: triangle_element(Cap::North, h_u, h_v),
            south_matrices: triangle_element(Cap::South, h_u, h_v),
            node_area: Vec::new(),
            area: 0.0,
            tris: Vec::new(),
            edges: Vec::new(),
            node_tris: NodeTriangles::default(),
        };
        t.tris = t.build_triangles();
        t.edges = edge_faces(&t.tris);
        t.node_tris = NodeTriangles::of(&t.tris, t.node_count());
        let mut area = vec![0.0; t.node_count()];
        t.for_each_element(|nodes, grad_mass| {
            for (a, &n) in nodes.iter().enumerate() {
                area[n as usize] += grad_mass.1[a].iter().sum::<f64>();
            }
        });
        t.area = area.iter().sum();
        t.node_area = area;
        t
    }

    /// k² + 2.
    pub fn node_count(&self) -> usize {
        self.uv.len()
    }

    /// The signed powers sgn(c)|c|^ε of eqs. (4, 5) for shape `q` on the grid (see
    /// [`GridPowers`]): 2k + 4 `powf`s, where
    /// evaluating [`SignedPowers::new`] at every node would take 4(k² + 2).
    pub fn grid_powers(&self, q: &SuperquadricParams, out: &mut GridPowers) {
        let k = self.k;
        let ring = |t: &Trig| [spow(t.cu, q.e1), spow(t.su, q.e1)];
        out.rings.clear();
        out.rings.push(ring(&self.trig[0]));
        out.rings
            .extend((0..k).map(|i| ring(&self.trig[1 + i * k])));
        out.rings.push(ring(&self.trig[self.north_pole()]));
        out.longitudes.clear();
        out.longitudes.extend(
            self.trig[1..=k]
                .iter()
                .map(|t| [spow(t.cv, q.e2), spow(t.sv, q.e2)]),
        );
        let pole = |t: &Trig| [spow(t.cv, q.e2), spow(t.sv, q.e2)];
        out.poles = [pole(&self.trig[0]), pole(&self.trig[self.north_pole()])];
    }

    /// The grid position of node `i`: (ring index into [`GridPowers::rings`], longitude index), or
    /// `None` for the longitude of a pole (which has its own, [`GridPowers::poles`]).
    #[inline]
    pub fn grid_index(&self, i: usize) -> (usize, Option<usize>) {
        if i == 0 {
            (0, None)
        } else if i == self.north_pole() {
            (self.k + 1, None)
        } else {
            ((i - 1) / self.k + 1, Some((i - 1) % self.k))
        }
    }

    /// The nodes of ring `ring` (0 the south pole, 1..=k the rings, k + 1 the north pole, as
    /// [`Tessellation::for_each_grid_node`] numbers them) and the [`Trig`] terms of their
    /// longitudes, in node order (a pole's own terms, at v = 0).
    pub fn grid_ring(&self, ring: usize) -> (std::ops::Range<usize>, &[Trig]) {
        let k = self.k;
        match ring {
            0 => (0..1, &self.trig[..1]),
            r if r > k => {
                let np = self.north_pole();
                (np..np + 1, &self.trig[np..np + 1])
            }
            r => (1 + (r - 1) * k..1 + r * k, &self.trig[1..=k]),
        }
    }

    /// Calls `visit(node, ring, longitude)` for every node in index order, with the indices of
    /// [`GridPowers`] (`None` for a pole's longitude): the grid walk without a division per node.
    #[inline(always)]
    pub fn for_each_grid_node(&self, mut visit: impl FnMut(usize, usize, Option<usize>)) {
        // One call site, so the visitor is inlined into the loop.
        let (k, n) = (self.k, self.node_count());
        let (mut ring, mut j) = (0, 0);
        for i in 0..n {
            let lon = (ring != 0 && ring <= k).then_some(j);
            visit(i, ring, lon);
            if ring == 0 || j + 1 == k {
                ring += 1;
                j = 0;
            } else {
                j += 1;
            }
        }
    }

    /// The [`Trig`] terms of ring `ring` and longitude `longitude` as indexed by
    /// [`Tessellation::for_each_grid_node`]: (ln|cos u|, ln|sin u|) and (ln|cos v|, ln|sin v|).
    #[inline]
    pub fn grid_logs(&self, ring: usize, longitude: Option<usize>) -> ([f64; 2], [f64; 2]) {
        let t = match ring {
            0 => &self.trig[0],
            r if r > self.k => &self.trig[self.north_pole()],
            r => &self.trig[1 + (r - 1) * self.k],
        };
        let l = longitude.map_or(t, |j| &self.trig[1 + j]);
        ([t.ln_cu, t.ln_su], [l.ln_cv, l.ln_sv])
    }

    /// The signed powers of every node for shape `q`: what [`SignedPowers::new`] gives for each
    /// entry of `trig`, bit for bit, from [`Tessellation::grid_powers`].
    pub fn signed_powers(&self, q: &SuperquadricParams, out: &mut Vec<SignedPowers>) {
        let mut grid = GridPowers::default();
        self.grid_powers(q, &mut grid);
        out.clear();
        out.extend((0..self.node_count()).map(|i| grid.at(self, i)));
    }

    /// Index of the north pole node.
    pub fn north_pole(&self) -> usize {
        self.k * self.k + 1
    }

    /// Visits every element with its node list and (grad, mass) matrices as row slices.
    fn for_each_element(&self, mut visit: impl FnMut(&[u32], (&[&[f64]], &[&[f64]]))) {
        let q = &self.quad_matrices;
        let (qg, qm): ([&[f64]; 4], [&[f64]; 4]) = (
            q.grad.each_ref().map(|r| &r[..]),
            q.mass.each_ref().map(|r| &r[..]),
        );
        for e in &self.quads {
            visit(e, (&qg, &qm));
        }
        for (tris, m) in [
            (&self.north, &self.north_matrices),
            (&self.south, &self.south_matrices),
        ] {
            let (g, mm): ([&[f64]; 3], [&[f64]; 3]) = (
                m.grad.each_ref().map(|r| &r[..]),
                m.mass.each_ref().map(|r| &r[..]),
            );
            for e in tris {
                visit(e, (&g, &mm));
            }
        }
    }

    /// Adds K_dd q to `out` (section IV: K is never assembled), for scalar stiffnesses w0, w1.
    /// The three displacement components share the same element matrix (eq. 47), so the product
    /// works on whole [`DVec3`]s. Every quadrilateral has the same matrix, so the quad band is
    /// applied as the 3 × 3 stencil it sums to, ring by ring; the cap triangles element by
    /// element. Equal to [`Tessellation::apply_stiffness_by_element`] up to rounding (tested).
    pub fn apply_stiffness(&self, w0: f64, w1: f64, q: &[DVec3], out: &mut [DVec3]) {
        with_avx2!({ self.apply_stiffness_body(w0, w1, q, out) })
    }

    /// [`Self::apply_stiffness`]'s body, inlined into both of its builds.
    #[inline(always)]
    fn apply_stiffness_body(&self, w0: f64, w1: f64, q: &[DVec3], out: &mut [DVec3]) {
        let kq = self.quad_matrices.stiffness(w0, w1);
        // A node is corner 0 of quad (i, j) and corner 3 of quad (i, j − 1) in the band above
        // it, corner 1 of quad (i − 1, j) and corner 2 of quad (i − 1, j − 1) in the band below.
        // Each band sums to weights on the node's ring at (j − 1, j, j + 1) and the same on the
        // band's other ring.
        let above_own = [kq[3][0], kq[0][0] + kq[3][3], kq[0][3]];
        let above_ring = [kq[3][1], kq[0][1] + kq[3][2], kq[0][2]];
        let below_own = [kq[2][1], kq[1][1] + kq[2][2], kq[1][2]];
        let below_ring = [kq[2][0], kq[1][0] + kq[2][3], kq[1][3]];
        let both_own: [f64; 3] = std::array::from_fn(|a| above_own[a] + below_own[a]);
        let k = self.k;
        let row = |i: usize| &q[1 + i * k..1 + (i + 1) * k];
        for i in 0..k {
            let o = &mut out[1 + i * k..1 + (i + 1) * k];
            let up = (i + 1 < k).then(|| (above_ring, row(i + 1)));
            let down = (i > 0).then(|| (below_ring, row(i - 1)));
            match (up, down) {
                (Some(a), Some(b)) => add_ring_stencils([(both_own, row(i)), a, b], o),
                (Some(a), None) => add_ring_stencils([(above_own, row(i)), a], o),
                (None, Some(b)) => add_ring_stencils([(below_own, row(i)), b], o),
                (None, None) => add_ring_stencils([(below_own, row(i))], o),
            }
        }
        apply_elements(&self.north, &self.north_matrices.stiffness(w0, w1), q, out);
        apply_elements(&self.south, &self.south_matrices.stiffness(w0, w1), q, out);
    }

    /// K_dd q element by element over every element: the reference [`Tessellation::apply_stiffness`]
    /// is checked against.
    pub fn apply_stiffness_by_element(&self, w0: f64, w1: f64, q: &[DVec3], out: &mut [DVec3]) {
        apply_elements(&self.quads, &self.quad_matrices.stiffness(w0, w1), q, out);
        apply_elements(&self.north, &self.north_matrices.stiffness(w0, w1), q, out);
        apply_elements(&self.south, &self.south_matrices.stiffness(w0, w1), q, out);
    }

    /// The strain energy ½ qᵀ K_dd q (eq. 29, the q_d block).
    pub fn strain_energy(&self, w0: f64, w1: f64, q: &[DVec3]) -> f64 {
        let mut kq = vec![DVec3::ZERO; q.len()];
        self.apply_stiffness(w0, w1, q, &mut kq);
        0.5 * q.iter().zip(&kq).map(|(a, b)| a.dot(*b)).sum::<f64>()
    }

    /// Gershgorin bound on each row of K_dd: Σ_j |K_ij|. The largest eigenvalue of the lumped
    /// system A⁻¹K is at most max_i of this over A_i, which bounds the explicit Euler step.
    pub fn stiffness_row_bounds(&self, w0: f64, w1: f64) -> Vec<f64> {
        let mut rows = vec![0.0; self.node_count()];
        self.for_each_element(|nodes, (g, m)| {
            for (a, &n) in nodes.iter().enumerate() {
                rows[n as usize] += (0..nodes.len())
                    .map(|b| (w1 * g[a][b] + w0 * m[a][b]).abs())
                    .sum::<f64>();
            }
        });
        rows
    }

    /// The diagonal of K_dd: K_ii for every node.
    pub fn stiffness_diagonal(&self, w0: f64, w1: f64) -> Vec<f64> {
        let mut diag = vec![0.0; self.node_count()];
        self.for_each_element(|nodes, (g, m)| {
            for (a, &n) in nodes.iter().enumerate() {
                diag[n as usize] += w1 * g[a][a] + w0 * m[a][a];
            }
        });
        diag
    }

    /// Solves (diag(`shift`) + K_dd) x = b for the three displacement components at once by
    /// conjugate gradients preconditioned with the diagonal (`shift` + `k_diagonal`, the latter
    /// from [`Tessellation::stiffness_diagonal`]), from the `x` given (a warm start) until each
    /// component's residual is at most `tolerance` times its |b|, or `max_iterations`. The matrix
    /// is symmetric positive definite when w0 > 0 or some shift is positive. Returns the
    /// iterations taken.
    #[allow(clippy::too_many_arguments)]
    pub fn solve_shifted(
        &self,
        (w0, w1): (f64, f64),
        shift: &[f64],
        k_diagonal: &[f64],
        b: &[DVec3],
        x: &mut [DVec3],
        (tolerance, max_iterations): (f64, u32),
        cg: &mut CgScratch,
    ) -> u32 {
        let n = self.node_count();
        let apply = |v: &[DVec3], out: &mut Vec<DVec3>| {
            out.clear();
            out.extend(v.iter().zip(shift).map(|(v, s)| *s * *v));
            self.apply_stiffness(w0, w1, v, out);
        };
        let sum = |a: &[DVec3], b: &[DVec3]| a.iter().zip(b).map(|(a, b)| *a * *b).sum::<DVec3>();
        cg.inv_p.clear();
        cg.inv_p.extend(
            shift
                .iter()
                .zip(k_diagonal)
                .map(|(s, k)| if s + k > 0.0 { 1.0 / (s + k) } else { 0.0 }),
        );
        let inv_p = &cg.inv_p;
        let bound = tolerance * tolerance * sum(b, b);
        apply(&*x, &mut cg.ap);
        cg.r.clear();
        cg.r.extend(b.iter().zip(&cg.ap).map(|(b, a)| *b - *a));
        cg.z.clear();
        cg.z.extend(cg.r.iter().zip(inv_p).map(|(r, p)| *p * *r));
        cg.p.clear();
        cg.p.extend_from_slice(&cg.z);
        let mut rz = sum(&cg.r, &cg.z);
        let mut iterations = 0;
        while iterations < max_iterations {
            let rr = sum(&cg.r, &cg.r);
            if rr.cmple(bound).all() {
                break;
            }
            iterations += 1;
            apply(&cg.p, &mut cg.ap);
            let pap = sum(&cg.p, &cg.ap);
            let alpha = DVec3::select(pap.cmpgt(DVec3::ZERO), rz / pap, DVec3::ZERO);
            for i in 0..n {
                x[i] += alpha * cg.p[i];
                cg.r[i] -= alpha * cg.ap[i];
                cg.z[i] = inv_p[i] * cg.r[i];
            }
            let rz_new = sum(&cg.r, &cg.z);
            let beta = DVec3::select(rz.cmpgt(DVec3::ZERO), rz_new / rz, DVec3::ZERO);
            rz = rz_new;
            for (p, z) in cg.p.iter_mut().zip(&cg.z) {
                *p = *z + beta * *p;
            }
        }
        iterations
    }

    /// Wraps any (u, v) onto the domain u ∈ [−π/2, π/2], v ∈ [−π, π): a u past a pole comes back
    /// on the other side of it, half a turn round in v.
    pub fn wrap(u: f64, v: f64) -> (f64, f64) {
        let mut u = period(u + FRAC_PI_2) - FRAC_PI_2; // u ∈ [−π/2, 3π/2)
        let mut v = v;
        if u > FRAC_PI_2 {
            u = PI - u;
            v += PI;
        }
        (u, period(v + PI) - PI)
    }

    /// Locates material point (u, v) in its element and returns the shape functions there
    /// (eq. 22's N_i). In a cap cell the collapsed coordinates t (towards the pole) and s (along v)
    /// give N_pole = t, N_j = (1 − t)(1 − s), N_{j+1} = (1 − t) s: the same linear triangle, now
    /// covering the whole cell.
    pub fn locate(&self, u: f64, v: f64) -> ElementPoint {
        let (u, v) = Self::wrap(u, v);
        let k = self.k;
        let sv = (v + PI) / self.h_v;
        // sv ≥ 0 after the wrap, so truncation is the floor (without a libm call: `floor` is
        // not an instruction on the default x86-64 target).
        let j = (sv as usize).min(k - 1);
        let s = (sv - j as f64).clamp(0.0, 1.0);
        // Longitude j + 1 wraps to 0 at the seam (j < k): no integer division on this path.
        let next = if j + 1 == k { 0 } else { j + 1 };
        let ring = |i: usize, j: usize| (1 + i * k + j) as u32;
        let su = (u + FRAC_PI_2) / self.h_u - 1.0; // ring coordinate: ring i at su = i
        if su < 0.0 || su >= (k - 1) as f64 {
            let (pole, i, t, sign) = if su < 0.0 {
                (0u32, 0, -su, -1.0)
            } else {
                (self.north_pole() as u32, k - 1, su - (k - 1) as f64, 1.0)
            };
            let t = t.clamp(0.0, 1.0);
            let (hu, hv) = (sign / self.h_u, 1.0 / self.h_v);
            return ElementPoint {
                nodes: [pole, ring(i, j), ring(i, next), ring(i, next)],
                weights: [t, (1.0 - t) * (1.0 - s), (1.0 - t) * s, 0.0],
                du: [hu, -hu * (1.0 - s), -hu * s, 0.0],
                dv: [0.0, -hv * (1.0 - t), hv * (1.0 - t), 0.0],
            };
        }
        let i = (su as usize).min(k - 2); // su ≥ 0 here: truncation is the floor
        let r = su - i as f64;
        let (hu, hv) = (1.0 / self.h_u, 1.0 / self.h_v);
        ElementPoint {
            nodes: [ring(i, j), ring(i + 1, j), ring(i + 1, next), ring(i, next)],
            weights: [(1.0 - r) * (1.0 - s), r * (1.0 - s), r * s, (1.0 - r) * s],
            du: [-hu * (1.0 - s), hu * (1.0 - s), hu * s, -hu * s],
            dv: [-hv * (1.0 - r), -hv * r, hv * r, hv * (1.0 - r)],
        }
    }

    /// A nodal field on `coarse` carried onto this tessellation: each node takes the field's
    /// interpolation at its material point (u, v) in `coarse`'s element there (eq. 22's N_i).
    pub fn prolong(&self, coarse: &Tessellation, field: &[DVec3]) -> Vec<DVec3> {
        self.uv
            .iter()
            .map(|&[u, v]| coarse.locate(u, v).interpolate(|i| field[i]))
            .collect()
    }

    /// Smooth vertex normals of the surface through node positions `x`: the area-weighted sum of
    /// the normals of the render triangles round each node, normalised (zero where they cancel).
    /// Outward on a superquadric.
    pub fn vertex_normals(&self, x: &[DVec3], out: &mut Vec<DVec3>) {
        out.clear();
        out.resize(x.len(), DVec3::ZERO);
        for &[a, b, c] in &self.tris {
            let (pa, pb, pc) = (x[a as usize], x[b as usize], x[c as usize]);
            let n = (pb - pa).cross(pc - pa);
            for i in [a, b, c] {
                out[i as usize] += n;
            }
        }
        for n in out.iter_mut() {
            *n = n.normalize_or_zero();
        }
    }

    /// The smooth normal of node `i` alone: [`Self::vertex_normals`]' entry `i`, to the bit (the
    /// same triangles' normals added in the same order), for a caller that needs only a few
    /// nodes' normals.
    pub fn vertex_normal(&self, x: &[DVec3], i: usize) -> DVec3 {
        let mut n = DVec3::ZERO;
        for &t in self.node_tris.of_node(i) {
            let [a, b, c] = self.tris[t as usize];
            let (pa, pb, pc) = (x[a as usize], x[b as usize], x[c as usize]);
            n += (pb - pa).cross(pc - pa);
        }
        n.normalize_or_zero()
    }

    /// The render triangulation: each quad split in two and a fan at each pole, wound so that
    /// (B − A) × (C − A) points outward on a superquadric. 2k² triangles.
    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.tris
    }

    fn build_triangles(&self) -> Vec<[u32; 3]> {
        let mut out = Vec::with_capacity(2 * self.quads.len() + 2 * self.k);
        for &[n00, n10, n11, n01] in &self.quads {
            out.push([n00, n01, n11]);
            out.push([n00, n11, n10]);
        }
        for &[a, pole, b] in &self.north {
            out.push([a, b, pole]);
        }
        for &[pole, a, b] in &self.south {
            out.push([pole, b, a]);
        }
        out
    }
}

/// The work vectors of [`Tessellation::solve_shifted`], kept between solves.
#[derive(Clone, Debug, Default)]
pub struct CgScratch {
    inv_p: Vec<f64>,
    r: Vec<DVec3>,
    z: Vec<DVec3>,
    p: Vec<DVec3>,
    ap: Vec<DVec3>,
}

/// Adds Σ_r (w_r,₋ x_r,j−1 + w_r,0 x_r,j + w_r,₊ x_r,j+1) to `out[j]` round one ring (j ± 1
/// wrapping), the rows r = (w_r, x_r) taken in the order given: the ring's own row of
/// [`Tessellation::apply_stiffness`]'s 9-point stencil, then the ring above's and the ring
/// below's where there are such rings. Each row's three terms are added to `out[j]` as one sum,
/// row after row, so the result is the same to the bit as one pass a row. Between the ring's
/// first and last node the rings are read as flat arrays of coordinates, where a node's
/// neighbours are three entries away, so that the loop vectorises; the two nodes where the ring
/// closes are added as vectors.
#[inline(always)]
fn add_ring_stencils<const R: usize>(rows: [([f64; 3], &[DVec3]); R], out: &mut [DVec3]) {
    // A ring has k ≥ MIN_K = 3 nodes.
    let k = out.len();
    for (w, x) in &rows {
        out[0] += w[0] * x[k - 1] + w[1] * x[0] + w[2] * x[1];
        out[k - 1] += w[0] * x[k - 2] + w[1] * x[k - 1] + w[2] * x[0];
    }
    // Nodes 1..k − 1: coordinates 3..3k − 3, whose neighbours lie at m − 3 and m + 3.
    let flat: &mut [f64] = bytemuck::cast_slice_mut(out);
    let n = 3 * (k - 2);
    let o = &mut flat[3..3 + n];
    let rows = rows.map(|(w, x)| {
        let x: &[f64] = bytemuck::cast_slice(x);
        (w, &x[..n], &x[3..3 + n], &x[6..6 + n])
    });
    for m in 0..n {
        let mut v = o[m];
        for (w, before, at, after) in &rows {
            v += w[0] * before[m] + w[1] * at[m] + w[2] * after[m];
        }
        o[m] = v;
    }
}

/// `x` reduced to [0, 2π): `x.rem_euclid(2π)`, bit for bit, without the `fmod` call when `x` is
/// already there (a point of influence almost always is: it moves less than an element a step).
#[inline]
fn period(x: f64) -> f64 {
    if (0.0..TAU).contains(&x) {
        x
    } else {
        x.rem_euclid(TAU)
    }
}
