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
//! that bulges where there is no data pays for it. Each of the m parts costs the BIC's ½ ln N
//! for each of its P = 11 parameters. τ is the finest offset the data can show: the larger of the points'
//! spacing (the median distance from a point to its nearest neighbour) and their noise
//! ([`estimate_noise`]), floored at [`TOLERANCE`] of D, the finest a pure superquadric is asked
//! to follow (finer detail is the membrane's).
//!
//! **The search.** Start from one part fitted to every point. Each part is offered two cuts of
//! its points: the spectral bisection of their neighbourhood graph (the least normalised cut,
//! across a narrow neck: [`super::spectral`]), and the largest connected set of the points it
//! leaves unexplained (farther than where a point costs as an outlier: a limb a robust fit
//! passes by) against the rest. Each side is fitted from its moments; the better cut of each
//! part is settled (its points given to the nearer of the two surfaces, both refitted). The
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
use crate::model::superquadric::inside_outside;
use glam::DVec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use std::num::NonZeroUsize;

/// The parameters of a pure superquadric a part pays for: translation (3), rotation (3), the
/// three semi-axes and the two exponents.
pub const PART_PARAMETERS: f64 = 11.0;

/// The finest offset a pure part is asked to follow, as a fraction of the cloud's diagonal.
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
    /// Node positions, and the area each node stands for.
    nodes: Vec<DVec3>,
    area: Vec<f64>,
    /// Each node's distance to the nearest data point.
    gap: Vec<f64>,
}

impl Part {
    fn new(
        points: &[DVec3],
        data: &Data,
        members: Vec<usize>,
        opts: &FitOptions,
    ) -> Result<Self, FitError> {
        let own = gather(points, &members);
        let fit = fit(&own, opts, |_| {})?;
        let mut nodes = Vec::new();
        fit.state.node_positions(&fit.tess, &mut nodes);
        let mut area = vec![0.0; nodes.len()];
        for t in fit.tess.triangles() {
            let [a, b, c] = t.map(|i| nodes[i as usize]);
            let third = (b - a).cross(c - a).length() / 6.0;
            for &i in t {
                area[i as usize] += third;
            }
        }
        let gap = data.gaps(&nodes);
        Ok(Self {
            pose: InitialPose::of(&fit.state),
            fit,
            members,
            nodes,
            area,
            gap,
        })
    }

    /// The distance of each of `points` to this part's surface.
    fn distances(&self, points: &[DVec3]) -> Vec<f64> {
        point_distances(&self.fit.tess, &self.nodes, points)
    }

    /// Whether `p` lies inside this part's pure superquadric.
    fn contains(&self, p: DVec3) -> bool {
        let local = self.pose.rotation.inverse() * (p - self.pose.translation);
        inside_outside(&self.pose.shape, local) < 1.0
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

/// The cost (nats) of describing the points `idx` by `parts` (module docs): each point at its
/// distance from the union of the parts, each part's surface outside the others at its gap
/// from the data, weighted by the data's density.
fn cost(points: &[DVec3], idx: &[usize], parts: &[&Part], data: &Data, scale: &Scale) -> f64 {
    let own = gather(points, idx);
    let dist: Vec<Vec<f64>> = parts.iter().map(|p| p.distances(&own)).collect();
    let mut total = 0.0;
    for (i, p) in own.iter().enumerate() {
        let mut near = f64::INFINITY;
        let mut depth: f64 = 0.0;
        for (j, q) in parts.iter().enumerate() {
            let d = dist[j][i];
            near = near.min(d);
            if parts.len() > 1 && q.contains(*p) {
                depth = depth.max(d);
            }
        }
        total += scale.point_cost(near.max(depth));
    }
    for (j, q) in parts.iter().enumerate() {
        for ((n, a), g) in q.nodes.iter().zip(&q.area).zip(&q.gap) {
            let hidden = parts
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
fn cuts(own: &[DVec3], p: &Part, scale: &Scale) -> Vec<Vec<bool>> {
    let Some(graph) = super::spectral::neighbourhood_graph(own) else {
        return Vec::new();
    };
    let mut out: Vec<Vec<bool>> = super::spectral::bisect_graph(own, &graph)
        .into_iter()
        .collect();
    let reach = scale.tau * (2.0 * scale.outlier).sqrt();
    let unexplained: Vec<bool> = p.distances(own).iter().map(|&d| d > reach).collect();
    if let Some(set) = super::spectral::largest_component(&graph, &unexplained) {
        out.push(set);
    }
    out
}

/// The split of `p` along `side`: each side's pure superquadric fitted from its moments, or
/// `None` when a side is too small to fit.
fn try_cut(
    points: &[DVec3],
    data: &Data,
    p: &Part,
    side: &[bool],
    opts: &FitOptions,
    scale: &Scale,
) -> Result<Option<Proposal>, FitError> {
    let [a, b] = halves(&p.members, side);
    if a.len() < MIN_POINTS || b.len() < MIN_POINTS {
        return Ok(None);
    }
    let moments = pure(opts, Initialization::Moments);
    let pair = [
        Part::new(points, data, a, &moments)?,
        Part::new(points, data, b, &moments)?,
    ];
    Ok(Some(Proposal::new(points, data, p, pair, scale)))
}

/// `p`'s members split by `side` (`true`: the second).
fn halves(members: &[usize], side: &[bool]) -> [Vec<usize>; 2] {
    let mut h = [Vec::new(), Vec::new()];
    for (&i, &l) in members.iter().zip(side) {
        h[usize::from(l)].push(i);
    }
    h
}

/// `proposal` for `p` settled: each of `p`'s points given to the nearer of the two surfaces and
/// both refitted from where they are (unchanged when no point moves).
fn settle(
    points: &[DVec3],
    data: &Data,
    p: &Part,
    proposal: Proposal,
    opts: &FitOptions,
    scale: &Scale,
) -> Result<Proposal, FitError> {
    let own = gather(points, &p.members);
    let pair = &proposal.parts;
    let near: Vec<bool> = nearest_surface(&own, pair.iter().map(|q| (&q.fit.tess, &q.fit.state)))
        .iter()
        .map(|&j| j == 1)
        .collect();
    let [a, b] = halves(&p.members, &near);
    if a == pair[0].members || a.len() < MIN_POINTS || b.len() < MIN_POINTS {
        return Ok(proposal);
    }
    let again = |q: &Part, members| {
        let o = pure(opts, Initialization::Explicit(q.pose));
        Part::new(points, data, members, &o)
    };
    let settled = [again(&pair[0], a)?, again(&pair[1], b)?];
    Ok(Proposal::new(points, data, p, settled, scale))
}

impl Proposal {
    /// `p` split into `pair`, with its gain.
    fn new(points: &[DVec3], data: &Data, p: &Part, pair: [Part; 2], scale: &Scale) -> Self {
        let before = cost(points, &p.members, &[p], data, scale);
        let after = cost(points, &p.members, &[&pair[0], &pair[1]], data, scale);
        Self {
            parts: pair,
            gain: before - after - scale.part,
        }
    }
}

/// The best split of each of `parts` (by index `todo`) among its candidate cuts ([`cuts`]),
/// settled ([`settle`]); `None` for a part no cut of which can be fitted. The cuts are fitted
/// side by side, then the best of each part settled side by side.
fn propose(
    points: &[DVec3],
    data: &Data,
    parts: &[Part],
    todo: &[usize],
    opts: &FitOptions,
    scale: &Scale,
) -> Result<Vec<Option<Proposal>>, FitError> {
    let mut jobs: Vec<(usize, Vec<bool>)> = Vec::new();
    for &j in todo {
        let own = gather(points, &parts[j].members);
        jobs.extend(cuts(&own, &parts[j], scale).into_iter().map(|c| (j, c)));
    }
    let tried = run_parallel(
        &jobs,
        |(j, side), _| try_cut(points, data, &parts[*j], side, opts, scale),
        &mut |_: &()| {},
    );
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
                parts: [q.parts[0].clone(), q.parts[1].clone()],
                gain: q.gain,
            };
            settle(points, data, &parts[*j], q, opts, scale).map(Some)
        },
        &mut |_: &()| {},
    );
    settled.into_iter().collect()
}

/// Splits `points` into parts by description length (module docs), each part a pure
/// superquadric fitted with `opts` (made global-only), and joins the parts that touch
/// ([`joints`], within τ). Errors: bad points or options, fewer
/// than [`MIN_POINTS`] points, or a `max_parts` of 0.
pub fn split(points: &[DVec3], max_parts: usize, opts: &FitOptions) -> Result<Whole, FitError> {
    validate_points(points)?;
    let cap = max_parts;
    super::check_parts(points.len(), cap)?;
    let scale = Scale::of(points);
    let mut data = Data {
        tree: kd_tree(points),
        density: 0.0,
    };
    let all: Vec<usize> = (0..points.len()).collect();
    let mut parts = vec![Part::new(
        points,
        &data,
        all,
        &pure(opts, Initialization::Moments),
    )?];
    data.density = points.len() as f64 / parts[0].total_area().max(f64::MIN_POSITIVE);
    let mut proposals: Vec<Option<Proposal>> = vec![None];
    let mut tried = vec![false];
    while parts.len() < cap {
        let todo: Vec<usize> = (0..parts.len()).filter(|&j| !tried[j]).collect();
        let fresh = propose(points, &data, &parts, &todo, opts, &scale)?;
        for (&j, proposal) in todo.iter().zip(fresh) {
            proposals[j] = proposal;
            tried[j] = true;
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
    prune(points, &mut parts, &data, &scale);
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
fn prune(points: &[DVec3], parts: &mut Vec<Part>, data: &Data, scale: &Scale) {
    let all: Vec<usize> = (0..points.len()).collect();
    while parts.len() > 1 {
        let whole = cost(points, &all, &parts.iter().collect::<Vec<_>>(), data, scale);
        let without: Vec<f64> = (0..parts.len())
            .map(|j| {
                let rest: Vec<&Part> = (0..parts.len())
                    .filter(|&k| k != j)
                    .map(|k| &parts[k])
                    .collect();
                cost(points, &all, &rest, data, scale) - scale.part
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
