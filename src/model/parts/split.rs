//! A whole object split into parts by description length: the fewest pure superquadrics that
//! explain its points (beyond the paper, which places its parts by hand).
//!
//! **The cost.** A set of parts describes the points at a cost in nats,
//! L = Σ_i ρ(d_i) + ρ_s Σ_n A_n ρ(g_n − τ) + m · ½ P ln N. Each point at distance d_i from the union of
//! the parts (from the nearest surface, or, inside another part, at least its depth there)
//! costs ρ(d) = min(½ (d/τ)², C): its normal offset coded as a Gaussian of width τ or, when that
//! is dearer, as an outlier anywhere along the cloud's diagonal D (C = ln(D/τ), the code length
//! of a position to within τ out of D). Each node n of a part's surface outside the other parts,
//! standing for area A_n, costs as the ρ_s A_n points the data would have there (ρ_s: the
//! points per unit area of the one-part fit) at its gap g_n from the nearest point beyond τ
//! ([`Scale::gap_cost`]): a part that bulges where there is no data pays for it. On a one-view scan ([`ONE_VIEW`]) only the
//! surface facing the scanner had to show data, and only it pays. Each of the m parts costs the
//! BIC's ½ ln N for each of its P = 11 parameters. τ is the finest offset the data can show: the
//! larger of the points' spacing (the median distance from a point to its nearest neighbour)
//! and their noise ([`estimate_noise`]), floored at [`TOLERANCE`] of D, the finest a pure
//! superquadric is asked to follow (finer detail is the membrane's). A point is *explained*
//! when it lies within [`Scale::reach`] of the union, where coding it as an outlier would be
//! cheaper.
//!
//! **The search.** The parts are assembled bottom-up, which needs no guess of where a part ends
//! ([`super::merge`]): a cloud of more than [`WORK_POINTS`] is spread-sampled to that many, cut
//! into [`PATCHES`] small connected patches ([`super::patches`]), and touching pieces are merged
//! two at a time, the cheapest first, while a merge lowers L. A superquadric is convex, so the
//! merges stop at the concave creases where a person would name a new part: a limb on a body,
//! a head on a neck, a wheel on an axle. Then a part is removed while removing it raises the
//! points' cost by less than a part's price (none hides inside the others or exists only to
//! cover noise), every point goes to the part whose surface is nearest, each part is refitted
//! to its points while that lowers L, and a new part is fitted to each connected group of
//! points left unexplained while that lowers L.

use super::Whole;
use super::merge::{Assembly, PIECE_K};
use crate::model::distance::normal_distance;
use crate::model::dynamics::ModelState;
use crate::model::fem::Tessellation;
use crate::model::fit::spread_sample;
use crate::model::fit::{
    FitError, FitOptions, FitReport, Initialization, MIN_POINTS, bounding_diagonal, fit_lean,
    fit_on, validate_points,
};
use crate::model::init::InitialPose;
use crate::model::nearest::kd_tree;
use crate::model::noise::estimate_noise;
use crate::model::parallel::run_parallel;
use glam::DVec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use std::num::NonZeroUsize;

/// The parameters of a pure superquadric a part pays for: translation (3), rotation (3), the
/// three semi-axes and the two exponents.
pub const PART_PARAMETERS: f64 = 11.0;

/// The finest offset a pure part is asked to follow, as a fraction of the cloud's diagonal.
pub const TOLERANCE: f64 = 0.01;

/// The cap on [`super::PartCount::Auto`] that `dsq fit --parts auto` and Python's `fit_parts` use
/// unless given one: a bound on the time, above the parts an object's description length asks
/// for (at most 20 on the 29 meshes of the corpus, docs/results.md).
pub const DEFAULT_MAX_PARTS: usize = 24;

/// The most points the parts are searched on: a larger cloud is spread-sampled to this many,
/// and every point is given to its nearest part at the end.
pub const WORK_POINTS: usize = 4096;

/// The patches a cloud is first cut into (geodesic Voronoi cells): several for each part a person
/// would name on the richest objects.
pub const PATCHES: usize = 64;

/// Refits of every part to the points nearest it, at most, after the parts are assembled.
const REFINE_ROUNDS: usize = 2;

/// The scale the cost measures offsets in (module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scale {
    /// τ, data units.
    pub tau: f64,
    /// C, the cost of an outlier, nats.
    pub outlier: f64,
    /// ½ P ln N, the cost of a part, nats.
    pub part: f64,
}

impl Scale {
    /// The scale of `points` (module docs).
    pub fn of(points: &[DVec3]) -> Self {
        let diagonal = bounding_diagonal(points);
        let noise = estimate_noise(points).map_or(0.0, |n| n.sigma);
        let tau = median_spacing(points)
            .max(noise)
            .max(TOLERANCE * diagonal)
            .max(f64::MIN_POSITIVE);
        Self {
            tau,
            outlier: (diagonal / tau).ln().max(1.0),
            part: 0.5 * PART_PARAMETERS * (points.len().max(2) as f64).ln(),
        }
    }

    /// ρ(d): the cost of a point at distance `d` from the nearest part.
    pub fn point_cost(&self, d: f64) -> f64 {
        let r = d / self.tau;
        (0.5 * r * r).min(self.outlier)
    }

    /// What a node of a part's surface costs, a point's worth of its area, at its gap `g` from
    /// the nearest data point: [`Self::point_cost`] of the gap beyond τ. Points at the data's
    /// spacing and noise leave every surface a gap of up to about τ from them, so that much
    /// says nothing against it; charging it would make every surface hidden inside another
    /// part cheaper than a surface shown, and pay parts for overlapping.
    pub fn gap_cost(&self, g: f64) -> f64 {
        self.point_cost((g - self.tau).max(0.0))
    }

    /// The distance beyond which a point costs as an outlier, τ √(2C): the points within it are
    /// the ones a fit explains.
    pub fn reach(&self) -> f64 {
        self.tau * (2.0 * self.outlier).sqrt()
    }
}

/// The median distance from a point to its nearest neighbour (over at most 2000 of them).
fn median_spacing(points: &[DVec3]) -> f64 {
    let Some(tree) = kd_tree(points) else {
        return 0.0;
    };
    let Some(two) = NonZeroUsize::new(2) else {
        return 0.0;
    };
    let stride = points.len().div_ceil(2000).max(1);
    let mut d: Vec<f64> = points
        .iter()
        .step_by(stride)
        .filter_map(|p| {
            tree.query(&p.to_array())
                .nearest_n::<SquaredEuclidean<f64>>(two)
                .execute()
                .get(1)
                .map(|r| r.distance.sqrt())
        })
        .collect();
    if d.is_empty() {
        return 0.0;
    }
    let mid = d.len() / 2;
    *d.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// The area each of a surface's `nodes` (on `tess`) stands for (a third of each triangle it is
/// a corner of), and its outward normal (away from `centre` over the whole surface).
fn node_areas(tess: &Tessellation, nodes: &[DVec3], centre: DVec3) -> (Vec<f64>, Vec<DVec3>) {
    let mut area = vec![0.0; nodes.len()];
    let mut normal = vec![DVec3::ZERO; nodes.len()];
    for t in tess.triangles() {
        let [a, b, c] = t.map(|i| nodes[i as usize]);
        let cross = (b - a).cross(c - a);
        let third = cross.length() / 6.0;
        for &i in t {
            area[i as usize] += third;
            normal[i as usize] += cross;
        }
    }
    let outward: f64 = normal
        .iter()
        .zip(nodes)
        .map(|(n, x)| n.dot(*x - centre))
        .sum();
    let sign = if outward < 0.0 { -1.0 } else { 1.0 };
    let normal = normal
        .iter()
        .map(|n| (*n * sign).normalize_or_zero())
        .collect();
    (area, normal)
}

/// A superquadric's surface as the cost sees it: node positions on [`PIECE_K`]'s tessellation,
/// the area each stands for, its outward normal, and its gap from the nearest data point.
pub(super) struct Surface {
    pub nodes: Vec<DVec3>,
    pub area: Vec<f64>,
    pub normal: Vec<DVec3>,
    pub gap: Vec<f64>,
}

/// The cloud as the cost sees it: its points' tree and their density on the surface.
pub(super) struct Data {
    tree: Option<ImmutableKdTree<f64, 3>>,
    tess: Tessellation,
    /// Points per unit of area.
    pub density: f64,
    /// Where a one-view scan was seen from (unit), when the points are one ([`view_of`]): only
    /// the surface facing it had to show data.
    pub view: Option<DVec3>,
}

impl Data {
    /// The surface of `pose` measured against the data.
    pub fn surface(&self, pose: &InitialPose) -> Surface {
        let state = ModelState::new(&self.tess, pose.translation, pose.rotation, pose.shape);
        let mut nodes = Vec::new();
        state.node_positions(&self.tess, &mut nodes);
        let (area, normal) = node_areas(&self.tess, &nodes, pose.translation);
        let gap = match &self.tree {
            Some(tree) => nodes
                .iter()
                .map(|n| {
                    tree.query(&n.to_array())
                        .nearest_one::<SquaredEuclidean<f64>>()
                        .execute()
                        .distance
                        .sqrt()
                })
                .collect(),
            None => vec![0.0; nodes.len()],
        };
        Surface {
            nodes,
            area,
            normal,
            gap,
        }
    }

    /// Whether a node with outward normal `normal` faces away from a one-view scan's viewer.
    pub fn unseen(&self, normal: DVec3) -> bool {
        self.view.is_some_and(|v| normal.dot(v) <= 0.0)
    }
}

/// One part while the object is split: its superquadric, its points, its surface, and every
/// data point's signed distance from it (negative inside, along the normal to first order:
/// [`normal_distance`]).
pub(super) struct Part {
    pub pose: InitialPose,
    pub members: Vec<usize>,
    surface: Surface,
    dist: Vec<f64>,
}

impl Part {
    /// The part `pose` owning `members`, measured against every point of `points`.
    pub fn new(points: &[DVec3], data: &Data, pose: InitialPose, members: Vec<usize>) -> Self {
        Self {
            surface: data.surface(&pose),
            dist: points.iter().map(|p| normal_distance(&pose, *p)).collect(),
            pose,
            members,
        }
    }
}

/// The cost (nats) of describing the points `which` (indices; all of them when `None`) by
/// `parts` (module docs), without the parts' price: the points' part (each at its distance from
/// the union: from the nearest surface, or at least its depth inside a part) and the surfaces'
/// part (each node not inside another of `parts`, and seen, at its gap from the data).
pub(super) fn cost_of(
    parts: &[&Part],
    which: Option<&[usize]>,
    data: &Data,
    scale: &Scale,
) -> (f64, f64) {
    let union = |i: usize| {
        let mut near = f64::INFINITY;
        let mut depth: f64 = 0.0;
        for q in parts {
            let d = q.dist[i];
            near = near.min(d.abs());
            if parts.len() > 1 && d < 0.0 {
                depth = depth.max(-d);
            }
        }
        scale.point_cost(near.max(depth))
    };
    let points = match which {
        Some(w) => w.iter().map(|&i| union(i)).sum(),
        None => (0..parts.first().map_or(0, |p| p.dist.len()))
            .map(union)
            .sum(),
    };
    let mut surface = 0.0;
    for (j, q) in parts.iter().enumerate() {
        let s = &q.surface;
        for (((x, a), g), normal) in s.nodes.iter().zip(&s.area).zip(&s.gap).zip(&s.normal) {
            let hidden = data.unseen(*normal)
                || parts
                    .iter()
                    .enumerate()
                    .any(|(k, o)| k != j && o.pose.contains(*x));
            if !hidden {
                surface += data.density * a * scale.gap_cost(*g);
            }
        }
    }
    (points, surface)
}

/// The cost (nats) of describing every point by `parts` (module docs), the parts' own price
/// included.
fn cost(parts: &[&Part], data: &Data, scale: &Scale) -> f64 {
    let (points, surface) = cost_of(parts, None, data, scale);
    points + surface + parts.len() as f64 * scale.part
}

/// Splits `points` into parts by description length (module docs), each part a pure
/// superquadric fitted with `opts` (made global-only), and joins the parts that touch
/// ([`joints`](fn@super::joints), within τ). Errors: bad points or options, fewer than [`MIN_POINTS`] points, or
/// a `max_parts` of 0. A cap above what the points allow ([`MIN_POINTS`] a part) is lowered to
/// it.
pub fn split(points: &[DVec3], max_parts: usize, opts: &FitOptions) -> Result<Whole, FitError> {
    validate_points(points)?;
    // At least one part and the points for it; a larger cap is only a bound.
    super::check_parts(points.len(), max_parts.min(1))?;
    let pure = FitOptions {
        global_only: true,
        init: Initialization::Moments,
        ..*opts
    };
    let work = spread_sample(points, WORK_POINTS);
    let cap = max_parts.min(work.len() / MIN_POINTS).max(1);
    let scale = Scale::of(&work);
    let mut data = Data {
        tree: kd_tree(&work),
        tess: Tessellation::new(PIECE_K),
        density: 0.0,
        view: None,
    };
    let one_pose = fit_lean(&work, &pure)?;
    let all: Vec<usize> = (0..work.len()).collect();
    let area: f64 = data.surface(&one_pose).area.iter().sum();
    data.density = work.len() as f64 / area.max(f64::MIN_POSITIVE);
    data.view = view_of(&work, one_pose.translation);
    if data.view.is_some() {
        // Only the seen half of a closed surface carries the points.
        data.density *= 2.0;
    }
    let one = Part::new(&work, &data, one_pose, all);
    let mut graph = super::patches::neighbourhood_graph(&work);
    super::patches::connect(&work, &mut graph);
    let mut parts = if cap > 1 && work.len() >= 2 * MIN_POINTS {
        let count = PATCHES.min(work.len() / MIN_POINTS);
        let label = super::patches::patches(&work, &graph, count);
        let adjacent = super::patches::adjacency(&graph, &label, count);
        Assembly::new(&work, &data, &scale, &pure).merge(&label, &adjacent, cap)?
    } else {
        Vec::new()
    };
    prune(&mut parts, &data, &scale);
    let total = |parts: &[Part]| cost(&parts.iter().collect::<Vec<_>>(), &data, &scale);
    if parts.is_empty() || total(&parts) >= total(std::slice::from_ref(&one)) {
        parts = vec![one];
    }
    refine(&work, &mut parts, &data, &scale, &pure)?;
    for _ in 0..RECOVER_ROUNDS {
        if parts.len() >= cap || !recover(&work, &graph, &mut parts, &data, &scale, &pure)? {
            break;
        }
        refine(&work, &mut parts, &data, &scale, &pure)?;
        prune(&mut parts, &data, &scale);
    }
    // Every point to the part whose surface is nearest; each part's report on its points.
    let poses: Vec<InitialPose> = parts.iter().map(|p| p.pose).collect();
    let owner = nearest_part(points, &poses);
    let members = super::members_of(points, &owner, poses.len());
    let jobs: Vec<(&Vec<DVec3>, &InitialPose)> = members.iter().zip(&poses).collect();
    let fits = run_parallel(
        &jobs,
        |(m, pose), _| {
            // A part left without points (all nearer another) is reported on all of them.
            let on = if m.len() >= MIN_POINTS {
                &m[..]
            } else {
                points
            };
            fit_on(on, pose, &pure)
        },
        &mut |_: &()| {},
    )
    .into_iter()
    .collect::<Result<Vec<FitReport>, FitError>>()?;
    // A part left with fewer points than a fit needs is dropped, its points to the others: a
    // scene that shares the cloud among the parts splits it the same way, and each part must
    // be fittable there.
    let mut fits = fits;
    loop {
        let whole = Whole::of(points, fits, scale);
        let counts = whole
            .owner
            .iter()
            .fold(vec![0usize; whole.fits.len()], |mut c, &o| {
                c[o] += 1;
                c
            });
        let Some(few) = (0..counts.len()).find(|&j| counts[j] < MIN_POINTS) else {
            return Ok(whole);
        };
        fits = whole.fits;
        fits.remove(few);
    }
}

/// The part whose surface is nearest each of `points` (by [`normal_distance`]).
fn nearest_part(points: &[DVec3], poses: &[InitialPose]) -> Vec<usize> {
    points
        .iter()
        .map(|p| {
            (0..poses.len())
                .min_by(|&a, &b| {
                    normal_distance(&poses[a], *p)
                        .abs()
                        .total_cmp(&normal_distance(&poses[b], *p).abs())
                })
                .unwrap_or(0)
        })
        .collect()
}

/// Removes, one at a time, the part that explains least, while one does not pay for itself:
/// a part is kept only when removing it (its points then described by the others) would raise
/// the points' cost by more than a part's price. Only the points judge a part here: a part
/// hidden in the others that hides an unsupported piece of their surface in turn lowers the
/// surfaces' cost, and would otherwise pay for itself without explaining anything.
fn prune(parts: &mut Vec<Part>, data: &Data, scale: &Scale) {
    while parts.len() > 1 {
        let all: Vec<&Part> = parts.iter().collect();
        let with = cost_of(&all, None, data, scale).0;
        let rise: Vec<f64> = (0..parts.len())
            .map(|j| {
                let rest: Vec<&Part> = (0..parts.len())
                    .filter(|&k| k != j)
                    .map(|k| &parts[k])
                    .collect();
                cost_of(&rest, None, data, scale).0 - with
            })
            .collect();
        let Some((j, r)) = rise
            .iter()
            .copied()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(&b.1))
        else {
            return;
        };
        if r >= scale.part {
            return;
        }
        parts.remove(j);
    }
}

/// Rounds of [`recover`] at most, each followed by [`refine`] and [`prune`].
const RECOVER_ROUNDS: usize = 4;

/// A part added where the parts leave points unexplained: for each connected set (in `graph`)
/// of at least [`MIN_POINTS`] points farther than [`Scale::reach`] from the union, the largest
/// first, a part fitted to them, kept when it lowers the whole cost. Whether one was kept.
fn recover(
    points: &[DVec3],
    graph: &[Vec<usize>],
    parts: &mut Vec<Part>,
    data: &Data,
    scale: &Scale,
    pure: &FitOptions,
) -> Result<bool, FitError> {
    let reach = scale.reach();
    let unexplained: Vec<bool> = (0..points.len())
        .map(|i| {
            let mut near = f64::INFINITY;
            let mut depth: f64 = 0.0;
            for q in parts.iter() {
                near = near.min(q.dist[i].abs());
                if parts.len() > 1 && q.dist[i] < 0.0 {
                    depth = depth.max(-q.dist[i]);
                }
            }
            near.max(depth) > reach
        })
        .collect();
    let mut sets = super::patches::components_where(graph, &unexplained);
    sets.retain(|s| s.len() >= MIN_POINTS);
    sets.sort_by_key(|s| std::cmp::Reverse(s.len()));
    let total = |parts: &[&Part]| cost(parts, data, scale);
    let mut before = total(&parts.iter().collect::<Vec<_>>());
    let mut kept = false;
    for set in sets.into_iter().take(4) {
        let own: Vec<DVec3> = set.iter().map(|&i| points[i]).collect();
        let part = Part::new(points, data, fit_lean(&own, pure)?, set);
        let mut with: Vec<&Part> = parts.iter().collect();
        with.push(&part);
        let after = total(&with);
        if after < before {
            before = after;
            parts.push(part);
            kept = true;
        }
    }
    Ok(kept)
}

/// Rounds of: every point given to the part whose surface is nearest, and each part refitted to
/// its points from where it is; a round is kept when it lowers the whole cost, and the rounds
/// end when one does not (or after [`REFINE_ROUNDS`]).
fn refine(
    points: &[DVec3],
    parts: &mut Vec<Part>,
    data: &Data,
    scale: &Scale,
    pure: &FitOptions,
) -> Result<(), FitError> {
    let total = |parts: &[Part]| cost(&parts.iter().collect::<Vec<_>>(), data, scale);
    let mut before = total(parts);
    for _ in 0..REFINE_ROUNDS {
        let poses: Vec<InitialPose> = parts.iter().map(|p| p.pose).collect();
        let owner = nearest_part(points, &poses);
        let jobs: Vec<(Vec<usize>, InitialPose)> = (0..parts.len())
            .map(|j| {
                let m: Vec<usize> = (0..points.len()).filter(|&i| owner[i] == j).collect();
                (m, poses[j])
            })
            .collect();
        let refit = run_parallel(
            &jobs,
            |(m, pose), _| -> Result<Part, FitError> {
                if m.len() < MIN_POINTS {
                    return Ok(Part::new(points, data, *pose, m.clone()));
                }
                let own: Vec<DVec3> = m.iter().map(|&i| points[i]).collect();
                let opts = FitOptions {
                    init: Initialization::Explicit(*pose),
                    ..*pure
                };
                Ok(Part::new(points, data, fit_lean(&own, &opts)?, m.clone()))
            },
            &mut |_: &()| {},
        )
        .into_iter()
        .collect::<Result<Vec<Part>, FitError>>()?;
        let after = total(&refit);
        if !(after < before) {
            break;
        }
        *parts = refit;
        before = after;
    }
    Ok(())
}

/// How far the points' mean outward normal must reach for them to be one view of a surface:
/// over a closed surface the outward normals cancel (0, up to sampling), over the half a scanner
/// sees they do not (1/2 for a sphere sampled uniformly by area, 2/3 by a scanner's pixel grid).
pub const ONE_VIEW: f64 = 0.25;

/// The direction a one-view scan was seen from, or `None` for points all round a surface: the
/// mean of the points' normals (each the least principal axis of its neighbourhood) turned away
/// from `centre`, when it reaches [`ONE_VIEW`].
fn view_of(points: &[DVec3], centre: DVec3) -> Option<DVec3> {
    let graph = super::patches::neighbourhood_graph(points);
    if graph.is_empty() {
        return None;
    }
    let mut sum = DVec3::ZERO;
    for (i, near) in graph.iter().enumerate() {
        if near.len() < 3 {
            continue;
        }
        let mean = near.iter().map(|&j| points[j]).sum::<DVec3>() / near.len() as f64;
        let mut m = glam::DMat3::ZERO;
        for &j in near {
            let d = points[j] - mean;
            m += glam::DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        }
        let (_, axes) = crate::model::linalg::symmetric_eigen3(&m);
        let n = axes.col(0);
        sum += if n.dot(points[i] - centre) < 0.0 {
            -n
        } else {
            n
        };
    }
    let mean = sum / points.len().max(1) as f64;
    (mean.length() >= ONE_VIEW).then(|| mean.normalize())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::superquadric::SuperquadricParams;
    use crate::synthetic::superquadric_cloud;
    use glam::DQuat;

    #[test]
    fn a_one_view_scan_is_told_from_a_closed_surface_and_its_view_found() {
        let q = SuperquadricParams {
            a: 1.0,
            a1: 1.0,
            a2: 0.7,
            a3: 0.5,
            e1: 0.8,
            e2: 1.0,
        };
        let all = superquadric_cloud(&q, DVec3::ZERO, DQuat::IDENTITY, 3000, 0.0, 9);
        assert_eq!(view_of(&all, DVec3::ZERO), None);
        let view = DVec3::new(0.3, -0.4, 0.866).normalize();
        let seen: Vec<DVec3> = all.iter().copied().filter(|p| p.dot(view) > 0.0).collect();
        let found = view_of(&seen, DVec3::ZERO).expect("a one-view scan");
        assert!(found.dot(view) > 0.9, "{found}");
    }
}
