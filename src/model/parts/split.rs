//! A whole object split into parts by description length: the fewest pure superquadrics that
//! explain its points (beyond the paper, which places its parts by hand).
//!
//! **The cost.** A set of parts describes the points at a cost in nats,
//! L = Σ_i ρ(d_i) + m · ½ P ln N: each point at distance d_i from the nearest part's surface
//! costs ρ(d) = min(½ (d/τ)², C), its normal offset coded as a Gaussian of width τ or, when that
//! is dearer, as an outlier anywhere along the cloud's diagonal D (C = ln(D/τ), the code length
//! of a position to within τ out of D); each of the m parts costs the BIC's ½ ln N for each of
//! its P = 11 parameters. τ is the finest offset the data can show: the larger of the points'
//! spacing (the median distance from a point to its nearest neighbour) and their noise
//! ([`estimate_noise`]), floored at [`TOLERANCE`] of D, the finest a pure superquadric is asked
//! to follow (finer detail is the membrane's).
//!
//! **The search.** Start from one part fitted to every point. Each part's best split is two
//! parts fitted to the two k-means clusters of its points, then its points given to the nearer
//! of the two surfaces and both refitted. The split that lowers L the most is taken, and again,
//! until no split lowers L (or the cap is met; with an exact count, until the count is met).
//! Then a part whose removal costs its points less than its own ½ P ln N is removed (none hides
//! inside the others or exists only to cover noise), and every point goes to the part whose
//! surface is nearest.

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

/// The cap on [`PartCount::Auto`] that `dsq fit --parts auto` and Python's `fit_parts` use
/// unless given one: a bound on the time, well above the parts an object's description length
/// asks for.
pub const DEFAULT_MAX_PARTS: usize = 12;

/// How many parts [`split`] stops at, at most.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PartCount {
    /// As many as lower the description length, at most this many.
    Auto(usize),
    /// Exactly this many.
    Exact(usize),
}

impl PartCount {
    fn cap(self) -> usize {
        match self {
            Self::Auto(n) | Self::Exact(n) => n,
        }
    }
}

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

/// The best split of `p` (module docs), or `None` when a cluster is too small to fit.
fn propose(
    points: &[DVec3],
    data: &Data,
    p: &Part,
    opts: &FitOptions,
    scale: &Scale,
) -> Result<Option<Proposal>, FitError> {
    let own = gather(points, &p.members);
    let Some(side) = super::spectral::bisect(&own) else {
        return Ok(None);
    };
    let label: Vec<usize> = side.iter().map(|&s| usize::from(s)).collect();
    let halves = |label: &[usize]| -> [Vec<usize>; 2] {
        let mut h = [Vec::new(), Vec::new()];
        for (&i, &l) in p.members.iter().zip(label) {
            h[l.min(1)].push(i);
        }
        h
    };
    let [a, b] = halves(&label);
    if a.len() < MIN_POINTS || b.len() < MIN_POINTS {
        return Ok(None);
    }
    let moments = pure(opts, Initialization::Moments);
    let mut pair = [
        Part::new(points, data, a, &moments)?,
        Part::new(points, data, b, &moments)?,
    ];
    // Each point to the nearer of the two surfaces, and both refitted from where they are.
    let near = nearest_surface(&own, pair.iter().map(|q| (&q.fit.tess, &q.fit.state)));
    let [a, b] = halves(&near);
    if near != label && a.len() >= MIN_POINTS && b.len() >= MIN_POINTS {
        let again = |q: &Part, members| {
            let o = pure(opts, Initialization::Explicit(q.pose));
            Part::new(points, data, members, &o)
        };
        pair = [again(&pair[0], a)?, again(&pair[1], b)?];
    }
    let before = cost(points, &p.members, &[p], data, scale);
    let after = cost(points, &p.members, &[&pair[0], &pair[1]], data, scale);

    Ok(Some(Proposal {
        parts: pair,
        gain: before - after - scale.part,
    }))
}

/// Splits `points` into parts by description length (module docs), each part a pure
/// superquadric fitted with `opts` (made global-only), and joins the parts that touch
/// ([`joints`], within τ). Errors: bad points or options, fewer
/// than [`MIN_POINTS`] points, or an exact count the points cannot be split into.
pub fn split(points: &[DVec3], count: PartCount, opts: &FitOptions) -> Result<Whole, FitError> {
    validate_points(points)?;
    let cap = count.cap();
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
        let fresh = run_parallel(
            &todo,
            |&j, _| propose(points, &data, &parts[j], opts, &scale),
            &mut |_: &()| {},
        );
        for (&j, proposal) in todo.iter().zip(fresh) {
            proposals[j] = proposal?;
            tried[j] = true;
        }
        let best = proposals
            .iter()
            .enumerate()
            .filter_map(|(j, p)| p.as_ref().map(|p| (j, p.gain)))
            .max_by(|a, b| a.1.total_cmp(&b.1));
        let Some((j, gain)) = best else { break };
        if matches!(count, PartCount::Auto(_)) && gain <= 0.0 {
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
    if let PartCount::Exact(n) = count
        && parts.len() < n
    {
        return Err(FitError::BadOption(format!(
            "parts = {n}: the points split into only {} parts of at least {MIN_POINTS} points",
            parts.len()
        )));
    }
    if matches!(count, PartCount::Auto(_)) {
        prune(points, &mut parts, &data, &scale);
    }
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
