//! A whole object split into parts by description length: the fewest pure superquadrics that
//! explain its points (beyond the paper, which places its parts by hand).
//!
//! **The cost.** A set of parts describes the points at a cost in nats,
//! L = Σ_i ρ(d_i) + ρ_s Σ_n A_n ρ(g_n) + m · ½ P ln N. Each point at distance d_i from the union of
//! the parts (from the nearest surface, or, inside another part, at least its depth there)
//! costs ρ(d) = min(½ (d/τ)², C): its normal offset coded as a Gaussian of width τ or, when that
//! is dearer, as an outlier anywhere along the cloud's diagonal D (C = ln(D/τ), the code length
//! of a position to within τ out of D). Each node n of a part's surface outside the other parts,
//! standing for area A_n, costs as the ρ_s A_n points the data would have there (ρ_s: the
//! points per unit area of the one-part fit) at its gap g_n from the nearest point: a part
//! that bulges where there is no data pays for it. On a one-view scan ([`ONE_VIEW`]) only the
//! surface facing the scanner had to show data, and only it pays. Each of the m parts costs the BIC's ½ ln N
//! for each of its P = 11 parameters. τ is the finest offset the data can show: the larger of the points'
//! spacing (the median distance from a point to its nearest neighbour) and their noise
//! ([`estimate_noise`]), floored at [`TOLERANCE`] of D, the finest a pure superquadric is asked
//! to follow (finer detail is the membrane's).
//!
//! **The search.** Start from one part fitted to every point. Each part is offered two cuts of
//! its points: the spectral bisection of their neighbourhood graph (the least normalised cut,
//! across a narrow neck: [`super::spectral`]), and the largest connected set of the points it
//! leaves unexplained (farther than where a point costs as an outlier: a limb a robust fit
//! passes by) against the rest. Each side is closed over the cut ([`cap`]) and fitted from its
//! moments; the better cut of each part is settled (its points given to the nearer of the two
//! surfaces, both refitted to their points alone). The
//! split that lowers L the most is taken, and again, until no split lowers L or the cap is met.
//! Then a part whose removal lowers L is removed (none hides inside the others or exists only
//! to cover noise), and every point goes to the part whose surface is nearest.

use super::{Whole, joints, nearest_surface};
use crate::model::fit::{
    FitError, FitOptions, FitReport, Initialization, MIN_POINTS, bounding_diagonal, fit,
    point_distances, validate_points,
};
use crate::model::forces::nearest::kd_tree;
use crate::model::init::InitialPose;
use crate::model::noise::estimate_noise;
use crate::model::parallel::run_parallel;
use glam::DVec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use std::num::NonZeroUsize;

/// The parameters of a pure superquadric a part pays for: translation (3), rotation (3), the
/// three semi-axes and the two exponents.
pub const PART_PARAMETERS: f64 = 11.0;

/// The finest offset a pure part is asked to follow, as a fraction of the cloud's diagonal:
/// swept over 0.005, 0.01 and 0.02 on the generated unions of `tests/parts.rs` (whole and seen
/// from one side: the true count 21, 22 and 24 times of 30) and on the meshes and scans of
/// docs/results.md, where 0.01 is the only value good on both.
pub const TOLERANCE: f64 = 0.01;

/// The cap on [`super::PartCount::Auto`] that `dsq fit --parts auto` and Python's `fit_parts` use
/// unless given one: a bound on the time, well above the parts an object's description length
/// asks for.
pub const DEFAULT_MAX_PARTS: usize = 12;

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

/// One part while the object is split: its fit, the indices of its points, and what the cost
/// needs of its surface.
#[derive(Clone)]
struct Part {
    fit: FitReport,
    members: Vec<usize>,
    pose: InitialPose,
    /// Node positions, the area each node stands for, and its outward normal.
    nodes: Vec<DVec3>,
    area: Vec<f64>,
    normal: Vec<DVec3>,
    /// Each node's distance to the nearest data point.
    gap: Vec<f64>,
    /// Every data point's distance to this part's surface, and whether it lies inside it.
    dist: Vec<f64>,
    inside: Vec<bool>,
}

impl Part {
    fn new(
        points: &[DVec3],
        data: &Data,
        members: Vec<usize>,
        cap: &[DVec3],
        opts: &FitOptions,
    ) -> Result<Self, FitError> {
        let mut own = gather(points, &members);
        own.extend_from_slice(cap);
        let fit = fit(&own, opts, |_| {})?;
        let mut nodes = Vec::new();
        fit.state.node_positions(&fit.tess, &mut nodes);
        let mut area = vec![0.0; nodes.len()];
        let mut normal = vec![DVec3::ZERO; nodes.len()];
        for t in fit.tess.triangles() {
            let [a, b, c] = t.map(|i| nodes[i as usize]);
            let cross = (b - a).cross(c - a);
            let third = cross.length() / 6.0;
            for &i in t {
                area[i as usize] += third;
                normal[i as usize] += cross;
            }
        }
        // Outward: the side away from the centre, over the whole surface.
        let centre = fit.state.translation;
        let outward: f64 = normal
            .iter()
            .zip(&nodes)
            .map(|(n, x)| n.dot(*x - centre))
            .sum();
        let sign = if outward < 0.0 { -1.0 } else { 1.0 };
        let normal = normal
            .iter()
            .map(|n| (*n * sign).normalize_or_zero())
            .collect();
        let gap = data.gaps(&nodes);
        let pose = InitialPose::of(&fit.state);
        let dist = point_distances(&fit.tess, &nodes, points);
        let inside = points.iter().map(|p| pose.contains(*p)).collect();
        Ok(Self {
            pose,
            fit,
            members,
            nodes,
            area,
            normal,
            gap,
            dist,
            inside,
        })
    }

    /// Whether `p` lies inside this part's pure superquadric.
    fn contains(&self, p: DVec3) -> bool {
        self.pose.contains(p)
    }

    /// The total area of the surface.
    fn total_area(&self) -> f64 {
        self.area.iter().sum()
    }
}

/// The cloud as the cost sees it: its points' tree and their density on the surface.
struct Data {
    tree: Option<ImmutableKdTree<f64, 3>>,
    /// Points per unit of area.
    density: f64,
    /// Where a one-view scan was seen from (unit), when the points are one ([`view_of`]): only
    /// the surface facing it had to show data.
    view: Option<DVec3>,
}

impl Data {
    /// The distance from each of `nodes` to its nearest data point.
    fn gaps(&self, nodes: &[DVec3]) -> Vec<f64> {
        let Some(tree) = &self.tree else {
            return vec![0.0; nodes.len()];
        };
        nodes
            .iter()
            .map(|n| {
                tree.query(&n.to_array())
                    .nearest_one::<SquaredEuclidean<f64>>()
                    .execute()
                    .distance
                    .sqrt()
            })
            .collect()
    }
}

/// The cost (nats) of describing every point by `parts` (module docs): each point at its
/// distance from the union of the parts, each part's surface outside the others at its gap
/// from the data, weighted by the data's density; without the parts' own price.
fn cost(parts: &[&Part], data: &Data, scale: &Scale) -> f64 {
    let n = parts.first().map_or(0, |p| p.dist.len());
    let mut total = 0.0;
    for i in 0..n {
        let mut near = f64::INFINITY;
        let mut depth: f64 = 0.0;
        for q in parts {
            let d = q.dist[i];
            near = near.min(d);
            if parts.len() > 1 && q.inside[i] {
                depth = depth.max(d);
            }
        }
        total += scale.point_cost(near.max(depth));
    }
    for (j, q) in parts.iter().enumerate() {
        for (((n, a), g), normal) in q.nodes.iter().zip(&q.area).zip(&q.gap).zip(&q.normal) {
            let unseen = data.view.is_some_and(|v| normal.dot(v) <= 0.0);
            let hidden = unseen
                || parts
                    .iter()
                    .enumerate()
                    .any(|(k, o)| k != j && o.contains(*n));
            if !hidden {
                total += data.density * a * scale.point_cost(*g);
            }
        }
    }
    total
}

/// A part's best split into two.
struct Proposal {
    parts: [Part; 2],
    /// How much it lowers the cost (nats), the new part's price paid.
    gain: f64,
}

fn gather(points: &[DVec3], idx: &[usize]) -> Vec<DVec3> {
    idx.iter().map(|&i| points[i]).collect()
}

fn pure(opts: &FitOptions, init: Initialization) -> FitOptions {
    FitOptions {
        global_only: true,
        init,
        ..*opts
    }
}

/// The candidate cuts of a part's points (`true`: the second side): the spectral bisection of
/// their neighbourhood graph, and the largest connected set of the points the part leaves
/// unexplained (farther than the distance at which a point costs as an outlier) against the
/// rest.
fn cuts(own: &[DVec3], p: &Part, scale: &Scale) -> Vec<Cut> {
    let Some(graph) = super::spectral::neighbourhood_graph(own) else {
        return Vec::new();
    };
    let mut sides: Vec<Vec<bool>> = super::spectral::bisect_graph(own, &graph)
        .into_iter()
        .collect();
    let reach = scale.tau * (2.0 * scale.outlier).sqrt();
    let unexplained: Vec<bool> = p.members.iter().map(|&i| p.dist[i] > reach).collect();
    if let Some(set) = super::spectral::largest_component(&graph, &unexplained) {
        sides.push(set);
    }
    sides
        .into_iter()
        .map(|side| Cut {
            caps: [false, true].map(|s| cap(own, &graph, &side, s, scale.tau)),
            side,
        })
        .collect()
}

/// A cut of a part's points: the side of each (`true`: the second), and for each side the
/// points that close it over the cut ([`cap`]).
struct Cut {
    side: Vec<bool>,
    caps: [Vec<DVec3>; 2],
}

/// Points that close the side `which` of `side` over its cut: the side's rim (its points with
/// a neighbour on the other side, in `graph`) joined to the rim's centroid by a fan of points
/// spaced about `spacing` apart, as a disc over the hole. A pure superquadric fitted to an open
/// piece of a surface bulges or flattens past the opening; closed, it fits the piece.
fn cap(
    own: &[DVec3],
    graph: &[Vec<usize>],
    side: &[bool],
    which: bool,
    spacing: f64,
) -> Vec<DVec3> {
    let rim: Vec<DVec3> = (0..own.len())
        .filter(|&i| side[i] == which && graph[i].iter().any(|&j| side[j] != which))
        .map(|i| own[i])
        .collect();
    if rim.len() < 3 {
        return Vec::new();
    }
    let centre = rim.iter().copied().sum::<DVec3>() / rim.len() as f64;
    let mut out = vec![centre];
    for r in &rim {
        let steps = (r.distance(centre) / spacing.max(f64::MIN_POSITIVE)).floor() as usize;
        out.extend((1..steps.min(64)).map(|k| centre + (*r - centre) * (k as f64 / steps as f64)));
    }
    out
}

/// What a split's proposals are made and judged against: the points, the options, the scale,
/// the parts so far and their whole cost.
struct Round<'a> {
    points: &'a [DVec3],
    data: &'a Data,
    opts: &'a FitOptions,
    scale: &'a Scale,
    parts: &'a [Part],
    before: f64,
}

impl Round<'_> {
    /// A part fitted to the points `members` and `cap` with the pure options and `init`.
    fn part(
        &self,
        members: Vec<usize>,
        cap: &[DVec3],
        init: Initialization,
    ) -> Result<Part, FitError> {
        Part::new(self.points, self.data, members, cap, &pure(self.opts, init))
    }

    /// Part `j` split into `pair`, with its gain.
    fn proposal(&self, j: usize, pair: [Part; 2]) -> Proposal {
        let mut after: Vec<&Part> = self
            .parts
            .iter()
            .enumerate()
            .filter(|(k, _)| *k != j)
            .map(|(_, q)| q)
            .collect();
        after.extend(pair.iter());
        let gain = self.before - cost(&after, self.data, self.scale) - self.scale.part;
        Proposal { parts: pair, gain }
    }

    /// The split of part `j` along `side`: each side's pure superquadric fitted from its
    /// moments, or `None` when a side is too small to fit.
    fn try_cut(&self, j: usize, cut: &Cut) -> Result<Option<Proposal>, FitError> {
        let [a, b] = halves(&self.parts[j].members, &cut.side);
        if a.len() < MIN_POINTS || b.len() < MIN_POINTS {
            return Ok(None);
        }
        let pair = [
            self.part(a, &cut.caps[0], Initialization::Moments)?,
            self.part(b, &cut.caps[1], Initialization::Moments)?,
        ];
        Ok(Some(self.proposal(j, pair)))
    }

    /// `proposal` for part `j` settled: each of its points given to the nearer of the two
    /// surfaces and both refitted from where they are, to their points alone (without the
    /// caps that closed the cut).
    fn settle(&self, j: usize, proposal: Proposal) -> Result<Proposal, FitError> {
        let p = &self.parts[j];
        let pair = &proposal.parts;
        let near: Vec<bool> = p
            .members
            .iter()
            .map(|&i| pair[1].dist[i] < pair[0].dist[i])
            .collect();
        let [mut a, mut b] = halves(&p.members, &near);
        if a.len() < MIN_POINTS || b.len() < MIN_POINTS {
            // Keep the cut's own sides; the refit below still drops the caps.
            a = pair[0].members.clone();
            b = pair[1].members.clone();
        }
        let settled = [
            self.part(a, &[], Initialization::Explicit(pair[0].pose))?,
            self.part(b, &[], Initialization::Explicit(pair[1].pose))?,
        ];
        Ok(self.proposal(j, settled))
    }

    /// The best split of each part of `todo` among its candidate cuts ([`cuts`]), settled;
    /// `None` for a part no cut of which can be fitted. The cuts are fitted side by side, then
    /// the best of each part settled side by side.
    fn propose(&self, todo: &[usize]) -> Result<Vec<Option<Proposal>>, FitError> {
        let mut jobs: Vec<(usize, Cut)> = Vec::new();
        for &j in todo {
            let p = &self.parts[j];
            let own = gather(self.points, &p.members);
            jobs.extend(cuts(&own, p, self.scale).into_iter().map(|c| (j, c)));
        }
        let tried = run_parallel(&jobs, |(j, cut), _| self.try_cut(*j, cut), &mut |_: &()| {});
        let mut best: Vec<Option<Proposal>> = todo.iter().map(|_| None).collect();
        for ((j, _), proposal) in jobs.iter().zip(tried) {
            let slot = &mut best[todo.iter().position(|t| t == j).unwrap_or(0)];
            if let Some(q) = proposal?
                && slot.as_ref().is_none_or(|b| q.gain > b.gain)
            {
                *slot = Some(q);
            }
        }
        let settle_jobs: Vec<(usize, Option<Proposal>)> = todo.iter().copied().zip(best).collect();
        let settled = run_parallel(
            &settle_jobs,
            |(j, proposal), _| -> Result<Option<Proposal>, FitError> {
                let Some(q) = proposal else { return Ok(None) };
                let q = Proposal {
                    parts: q.parts.clone(),
                    gain: q.gain,
                };
                self.settle(*j, q).map(Some)
            },
            &mut |_: &()| {},
        );
        settled.into_iter().collect()
    }
}

/// `members` split by `side` (`true`: the second).
fn halves(members: &[usize], side: &[bool]) -> [Vec<usize>; 2] {
    let mut h = [Vec::new(), Vec::new()];
    for (&i, &l) in members.iter().zip(side) {
        h[usize::from(l)].push(i);
    }
    h
}

/// Splits `points` into parts by description length (module docs), each part a pure
/// superquadric fitted with `opts` (made global-only), and joins the parts that touch
/// ([`joints`], within τ). Errors: bad points or options, fewer
/// than [`MIN_POINTS`] points, or a `max_parts` of 0. A cap above what the points allow
/// ([`MIN_POINTS`] a part) is lowered to it.
pub fn split(points: &[DVec3], max_parts: usize, opts: &FitOptions) -> Result<Whole, FitError> {
    validate_points(points)?;
    // At least one part and the points for it; a larger cap is only a bound.
    super::check_parts(points.len(), max_parts.min(1))?;
    let cap = max_parts.min(points.len() / MIN_POINTS);
    let scale = Scale::of(points);
    let mut data = Data {
        tree: kd_tree(points),
        density: 0.0,
        view: None,
    };
    let all: Vec<usize> = (0..points.len()).collect();
    let mut parts = vec![Part::new(
        points,
        &data,
        all,
        &[],
        &pure(opts, Initialization::Moments),
    )?];
    data.density = points.len() as f64 / parts[0].total_area().max(f64::MIN_POSITIVE);
    data.view = view_of(points, parts[0].fit.state.translation);
    if data.view.is_some() {
        // Only the seen half of a closed surface carries the points.
        data.density *= 2.0;
    }
    let mut proposals: Vec<Option<Proposal>> = vec![None];
    let mut tried = vec![false];
    while parts.len() < cap {
        let todo: Vec<usize> = (0..parts.len()).filter(|&j| !tried[j]).collect();
        let round = Round {
            points,
            data: &data,
            opts,
            scale: &scale,
            parts: &parts,
            before: cost(&parts.iter().collect::<Vec<_>>(), &data, &scale),
        };
        let fresh = round.propose(&todo)?;
        for (&j, proposal) in todo.iter().zip(fresh) {
            proposals[j] = proposal;
            tried[j] = true;
        }
        // The other parts' proposals were judged against the parts as they were: judge them
        // again against the parts as they are (their fits stand).
        for (j, slot) in proposals.iter_mut().enumerate() {
            if !todo.contains(&j)
                && let Some(q) = slot.take()
            {
                *slot = Some(round.proposal(j, q.parts));
            }
        }
        let best = proposals
            .iter()
            .enumerate()
            .filter_map(|(j, p)| p.as_ref().map(|p| (j, p.gain)))
            .max_by(|a, b| a.1.total_cmp(&b.1));
        let Some((j, gain)) = best else { break };
        if gain <= 0.0 {
            break;
        }
        let Some(Proposal { parts: [a, b], .. }) = proposals[j].take() else {
            break;
        };
        parts[j] = a;
        parts.push(b);
        tried[j] = false;
        tried.push(false);
        proposals.push(None);
    }
    prune(&mut parts, &data, &scale);
    let fits: Vec<FitReport> = parts.into_iter().map(|p| p.fit).collect();
    let owner = nearest_surface(points, fits.iter().map(|f| (&f.tess, &f.state)));
    Ok(Whole {
        joints: joints(&fits, scale.tau),
        fits,
        owner,
        scale,
    })
}

/// Removes, one at a time, the part whose removal lowers the whole cost the most (its points
/// then described by the others), while one does: a part hidden inside the others, or one that
/// exists only to cover a few points, costs more than it saves.
fn prune(parts: &mut Vec<Part>, data: &Data, scale: &Scale) {
    while parts.len() > 1 {
        let whole = cost(&parts.iter().collect::<Vec<_>>(), data, scale);
        let without: Vec<f64> = (0..parts.len())
            .map(|j| {
                let rest: Vec<&Part> = (0..parts.len())
                    .filter(|&k| k != j)
                    .map(|k| &parts[k])
                    .collect();
                cost(&rest, data, scale) - scale.part
            })
            .collect();
        let Some((j, c)) = without
            .iter()
            .copied()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(&b.1))
        else {
            return;
        };
        if c >= whole {
            return;
        }
        parts.remove(j);
    }
}

/// How far the points' mean outward normal must reach for them to be one view of a surface:
/// over a closed surface the outward normals cancel (0, up to sampling), over the half a scanner
/// sees they do not (1/2 for a sphere sampled uniformly by area, 2/3 by a scanner's pixel grid).
pub const ONE_VIEW: f64 = 0.25;

/// The direction a one-view scan was seen from, or `None` for points all round a surface: the
/// mean of the points' normals (each the least principal axis of its neighbourhood) turned away
/// from `centre`, when it reaches [`ONE_VIEW`].
fn view_of(points: &[DVec3], centre: DVec3) -> Option<DVec3> {
    let graph = super::spectral::neighbourhood_graph(points)?;
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
