//! Whole objects with known parts: unions of superquadrics, a body with limbs, sampled over the
//! union's surface or seen from one side, the truth a test pins [`crate::model::parts`] to.

use super::{Rng, area_uniform, unit_vector};
use crate::model::init::InitialPose;
use crate::model::superquadric::SuperquadricParams;
use glam::{DQuat, DVec3};

/// A union of superquadrics and points on its surface.
#[derive(Clone, Debug)]
pub struct UnionCloud {
    /// The parts: the body first, then the limbs.
    pub parts: Vec<InitialPose>,
    /// The points (with noise).
    pub points: Vec<DVec3>,
    /// The part each point was drawn from.
    pub owner: Vec<usize>,
}

/// A body (semi-axes in [0.8, 1.2] × [0.5, 0.8] × [0.4, 0.6]) with `parts − 1` limbs (at most
/// five, one along each of ±x, ±y and +z of the body, in a random order), each limb a
/// superquadric 0.6–1.0 long and 0.15–0.3 thick whose inner third lies inside the body; exponents
/// in [0.3, 1.7]; turned and moved at random. About `points` points drawn uniformly by area
/// over the union's surface (none inside another part), with Gaussian noise `noise` (data
/// units); with `view`, only the points nearest the viewer along that direction in each cell of
/// a grid across it (a one-view scan). Deterministic in `seed`.
pub fn union_cloud(seed: u64, parts: usize, points: usize, noise: f64, view: bool) -> UnionCloud {
    let mut rng = Rng::new(seed);
    let eps = |rng: &mut Rng| rng.range(0.3, 1.7);
    let body_axes = DVec3::new(
        rng.range(0.8, 1.2),
        rng.range(0.5, 0.8),
        rng.range(0.4, 0.6),
    );
    let shape = |axes: DVec3, e1: f64, e2: f64| {
        let a = axes.max_element();
        SuperquadricParams {
            a,
            a1: axes.x / a,
            a2: axes.y / a,
            a3: axes.z / a,
            e1,
            e2,
        }
    };
    let (e1, e2) = (eps(&mut rng), eps(&mut rng));
    let mut local = vec![(DVec3::ZERO, DQuat::IDENTITY, shape(body_axes, e1, e2))];
    let mut dirs = vec![DVec3::X, -DVec3::X, DVec3::Y, -DVec3::Y, DVec3::Z];
    for _ in 1..parts.clamp(1, 6) {
        let d = dirs.remove((rng.uniform() * dirs.len() as f64) as usize % dirs.len());
        let length = rng.range(0.3, 0.5);
        let thick = rng.range(0.15, 0.3);
        let reach = body_axes.dot(d.abs());
        let centre = d * (reach + length / 3.0);
        let turn = DQuat::from_rotation_arc(DVec3::Z, d);
        let (e1, e2) = (eps(&mut rng), eps(&mut rng));
        local.push((
            centre,
            turn,
            shape(DVec3::new(thick, thick, length), e1, e2),
        ));
    }
    let rotation =
        DQuat::from_axis_angle(unit_vector(&mut rng), rng.range(0.0, std::f64::consts::TAU))
            .normalize();
    let translation = DVec3::new(
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
    );
    let poses: Vec<InitialPose> = local
        .iter()
        .map(|(c, q, s)| InitialPose {
            translation: translation + rotation * *c,
            rotation: (rotation * *q).normalize(),
            shape: *s,
        })
        .collect();
    // Area-uniform samples of each part, as many as its share of the area, kept where no other
    // part covers them.
    let drawn = if view { points * 6 } else { points * 2 };
    let areas: Vec<f64> = poses.iter().map(|p| area(&p.shape)).collect();
    let total: f64 = areas.iter().sum();
    let mut cloud = Vec::new();
    for (j, pose) in poses.iter().enumerate() {
        let n = ((drawn as f64) * areas[j] / total).ceil() as usize;
        for p in area_uniform(&pose.shape, n, &mut rng) {
            let x = pose.translation + pose.rotation * p;
            if poses
                .iter()
                .enumerate()
                .all(|(k, o)| k == j || !o.contains(x))
            {
                cloud.push((x, j));
            }
        }
    }
    if view {
        cloud = one_view(cloud, unit_vector(&mut rng), points);
    }
    let (points, owner) = thin(&cloud, points, noise, &mut rng);
    UnionCloud {
        parts: poses,
        points,
        owner,
    }
}

/// An even thinning of `cloud` (points and their parts) to about `count`, each point moved by
/// Gaussian noise `sigma` (data units): the points and their parts.
pub(super) fn thin(
    cloud: &[(DVec3, usize)],
    count: usize,
    sigma: f64,
    rng: &mut Rng,
) -> (Vec<DVec3>, Vec<usize>) {
    let stride = (cloud.len() as f64 / count as f64).max(1.0);
    let (mut points, mut owner) = (Vec::new(), Vec::new());
    let mut at = 0.0;
    while (at as usize) < cloud.len() {
        let (x, j) = cloud[at as usize];
        points.push(x + sigma * DVec3::new(rng.normal(), rng.normal(), rng.normal()));
        owner.push(j);
        at += stride;
    }
    (points, owner)
}

/// The surface area of `shape`, from a k = 41 tessellation.
fn area(shape: &SuperquadricParams) -> f64 {
    let tess = crate::model::fem::Tessellation::new(41);
    let x: Vec<DVec3> = tess
        .uv
        .iter()
        .map(|&[u, v]| crate::model::superquadric::shape_at(shape, u, v))
        .collect();
    tess.triangles()
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| x[i as usize]);
            0.5 * (b - a).cross(c - a).length()
        })
        .sum()
}

/// The points of `cloud` a viewer looking along −`d` sees: in each cell of a grid across `d`
/// (sized for about `points` cells covered), the point nearest the viewer, and any within a
/// cell's width of it in depth.
pub(super) fn one_view(cloud: Vec<(DVec3, usize)>, d: DVec3, points: usize) -> Vec<(DVec3, usize)> {
    use std::collections::HashMap;
    let (e1, e2) = d.any_orthonormal_pair();
    let (lo, hi) = cloud.iter().fold(
        (
            glam::DVec2::splat(f64::INFINITY),
            glam::DVec2::splat(f64::NEG_INFINITY),
        ),
        |(lo, hi), (x, _)| {
            let q = glam::DVec2::new(x.dot(e1), x.dot(e2));
            (lo.min(q), hi.max(q))
        },
    );
    let extent = hi - lo;
    let cell = (extent.x * extent.y / (points as f64 * 1.5))
        .sqrt()
        .max(f64::MIN_POSITIVE);
    let key = |x: DVec3| {
        (
            ((x.dot(e1) - lo.x) / cell) as i64,
            ((x.dot(e2) - lo.y) / cell) as i64,
        )
    };
    let mut front: HashMap<(i64, i64), f64> = HashMap::new();
    for (x, _) in &cloud {
        let depth = x.dot(d);
        let f = front.entry(key(*x)).or_insert(f64::NEG_INFINITY);
        *f = f.max(depth);
    }
    cloud
        .into_iter()
        .filter(|(x, _)| front.get(&key(*x)).is_some_and(|&f| x.dot(d) >= f - cell))
        .collect()
}
