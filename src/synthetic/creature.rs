//! Generated creatures: trees of 2 to 16 superquadrics, some tapered or bent, with thin and
//! thick limbs at random angles, sampled over the union's surface (a closed mesh's, by area) or
//! seen from one side; the true parts are what a split of them is pinned to.

use super::union::{one_view, thin};
use super::{Rng, unit_vector};
use crate::model::deform::GlobalDeformation;
use crate::model::fem::Tessellation;
use crate::model::init::InitialPose;
use crate::model::superquadric::{SuperquadricParams, inside_outside, shape_at};
use glam::{DQuat, DVec3};

/// One part of a creature: a superquadric and its tapering and bending.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CreaturePart {
    /// The superquadric's pose and shape.
    pub pose: InitialPose,
    /// Its tapering and bending (about the superquadric's z).
    pub deformation: GlobalDeformation,
}

impl CreaturePart {
    /// The world point of the model-frame superquadric point `s`, deformed.
    pub fn place(&self, s: DVec3) -> DVec3 {
        let height = self.pose.shape.semi_axes().z;
        self.pose.translation + self.pose.rotation * self.deformation.apply(s, height)
    }

    /// Whether the world point `x` lies inside the deformed superquadric: the deformation
    /// undone by Newton's method, then the inside–outside function below 1.
    pub fn contains(&self, x: DVec3) -> bool {
        let local = self.pose.rotation.inverse() * (x - self.pose.translation);
        let height = self.pose.shape.semi_axes().z;
        let mut s = local;
        if !self.deformation.is_identity() {
            for _ in 0..30 {
                let j = self.deformation.jacobian(s, height);
                let r = j.value - local;
                if r.length() < 1e-12 * (1.0 + local.length()) {
                    break;
                }
                let det = j.d_point.determinant();
                if !(det.abs() > 1e-12) {
                    return false;
                }
                s -= j.d_point.inverse() * r;
            }
            if !(self.deformation.apply(s, height) - local)
                .length()
                .is_finite()
                || (self.deformation.apply(s, height) - local).length()
                    > 1e-6 * (1.0 + local.length())
            {
                return false;
            }
        }
        inside_outside(&self.pose.shape, s) < 1.0
    }
}

/// A creature and points on its surface.
#[derive(Clone, Debug)]
pub struct Creature {
    /// The parts: the body first, then each limb after the part it grows from.
    pub parts: Vec<CreaturePart>,
    /// Which part each limb grows from (the body's entry is 0).
    pub parent: Vec<usize>,
    /// The points (with noise).
    pub points: Vec<DVec3>,
    /// The part each point was drawn from.
    pub owner: Vec<usize>,
}

/// A creature of `parts` parts (clamped to 1–16), about `points` points with Gaussian noise
/// `noise` (a fraction of the creature's diagonal), over the whole surface or, with `view`, as
/// a one-view scan from a random direction. Deterministic in `seed`.
///
/// The body's semi-axes are 1 × [0.4, 0.8] × [0.3, 0.6]. Each limb grows from a random part
/// already placed, at a random point of its surface, along the surface's outward direction
/// turned up to 40° at random, with a quarter to two fifths of its length inside that part; it
/// is thin (0.04–0.1 across) or thick (0.12–0.3) at even odds, and 0.3–1.0 long. Exponents
/// lie in [0.2, 1.8]; a limb is tapered (|t| ≤ 0.5) with odds 1 in 3 and bent (each end up to
/// 0.8 rad) with odds 1 in 4. A limb that would reach into a part other than the one it grows
/// from, or leave its outer half inside it, is drawn again.
pub fn creature(seed: u64, parts: usize, points: usize, noise: f64, view: bool) -> Creature {
    let mut rng = Rng::new(seed);
    let eps = |rng: &mut Rng| rng.range(0.2, 1.8);
    let body = CreaturePart {
        pose: InitialPose {
            translation: DVec3::ZERO,
            rotation: DQuat::IDENTITY,
            shape: shape(
                DVec3::new(1.0, rng.range(0.4, 0.8), rng.range(0.3, 0.6)),
                eps(&mut rng),
                eps(&mut rng),
            ),
        },
        deformation: GlobalDeformation::IDENTITY,
    };
    let mut out = vec![body];
    let mut parent = vec![0];
    let mut attempts = 0;
    while out.len() < parts.clamp(1, 16) && attempts < 400 {
        attempts += 1;
        let from = (rng.uniform() * out.len() as f64) as usize % out.len();
        if let Some(limb) = limb(&mut rng, &out, from) {
            out.push(limb);
            parent.push(from);
        }
    }
    // A random turn and place for the whole creature.
    let turn = DQuat::from_axis_angle(unit_vector(&mut rng), rng.range(0.0, std::f64::consts::TAU));
    let shift = DVec3::new(
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
    );
    for p in &mut out {
        p.pose.translation = shift + turn * p.pose.translation;
        p.pose.rotation = (turn * p.pose.rotation).normalize();
    }
    let (cloud, owner) = sample(&out, points, noise, view, &mut rng);
    Creature {
        parts: out,
        parent,
        points: cloud,
        owner,
    }
}

/// A superquadric of semi-axes `axes` and exponents `e1`, `e2`.
fn shape(axes: DVec3, e1: f64, e2: f64) -> SuperquadricParams {
    let a = axes.max_element();
    SuperquadricParams {
        a,
        a1: axes.x / a,
        a2: axes.y / a,
        a3: axes.z / a,
        e1,
        e2,
    }
}

/// A limb grown from `parts[from]` (see [`creature`]), or `None` when the draw collides.
fn limb(rng: &mut Rng, parts: &[CreaturePart], from: usize) -> Option<CreaturePart> {
    let host = &parts[from];
    let (u, v) = (
        rng.range(-1.4, 1.4),
        rng.range(-std::f64::consts::PI, std::f64::consts::PI),
    );
    let s = shape_at(&host.pose.shape, u, v);
    let at = host.place(s);
    let out = (host.place(s * 1.01) - at).normalize_or_zero();
    if out == DVec3::ZERO {
        return None;
    }
    let side = out
        .cross(unit_vector(rng))
        .normalize_or(out.any_orthonormal_vector());
    let tilt = DQuat::from_axis_angle(side, rng.range(0.0, 40f64.to_radians()));
    let axis = (tilt * out).normalize_or_zero();
    if axis == DVec3::ZERO {
        return None;
    }
    let thick = if rng.uniform() < 0.5 {
        rng.range(0.04, 0.1)
    } else {
        rng.range(0.12, 0.3)
    };
    let length = rng.range(0.3, 1.0);
    let inside = rng.range(0.25, 0.4) * length;
    let centre = at + axis * (0.5 * length - inside);
    let (e1, e2) = (rng.range(0.2, 1.8), rng.range(0.2, 1.8));
    let mut deformation = GlobalDeformation::IDENTITY;
    if rng.uniform() < 1.0 / 3.0 {
        deformation.taper = [rng.range(-0.5, 0.5), rng.range(-0.5, 0.5)];
    }
    if rng.uniform() < 0.25 {
        let angle = rng.range(0.2, 0.8);
        let dir = rng.range(0.0, std::f64::consts::TAU);
        deformation.bend = [angle * dir.cos(), angle * dir.sin()];
    }
    let axes = DVec3::new(thick * rng.range(0.7, 1.0), thick, 0.5 * length);
    let limb = CreaturePart {
        pose: InitialPose {
            translation: centre,
            rotation: DQuat::from_rotation_arc(DVec3::Z, axis),
            shape: shape(axes, e1, e2),
        },
        deformation: deformation.clamped(axes),
    };
    // Its axis, sampled: the outer half clear of its host, all of it clear of the others.
    let half = 0.5 * length;
    for k in 0..=20 {
        let z = -half + length * k as f64 / 20.0;
        let x = limb.place(DVec3::new(0.0, 0.0, z));
        let outer = z > 0.0;
        for (j, p) in parts.iter().enumerate() {
            if p.contains(x) && (j != from || outer) {
                return None;
            }
        }
    }
    Some(limb)
}

/// About `count` points over the union of `parts` (each part's surface by area, a point kept
/// where no other part covers it), with noise `noise` of the diagonal; with `view`, those a
/// one-view scan from a random direction sees. The part of each point.
fn sample(
    parts: &[CreaturePart],
    count: usize,
    noise: f64,
    view: bool,
    rng: &mut Rng,
) -> (Vec<DVec3>, Vec<usize>) {
    let tess = Tessellation::new(41);
    let meshes: Vec<Vec<DVec3>> = parts
        .iter()
        .map(|p| {
            tess.uv
                .iter()
                .map(|&[u, v]| p.place(shape_at(&p.pose.shape, u, v)))
                .collect()
        })
        .collect();
    let area = |x: &[DVec3], t: &[u32; 3]| {
        let [a, b, c] = t.map(|i| x[i as usize]);
        0.5 * (b - a).cross(c - a).length()
    };
    let totals: Vec<f64> = meshes
        .iter()
        .map(|x| tess.triangles().iter().map(|t| area(x, t)).sum())
        .collect();
    let all: f64 = totals.iter().sum();
    let drawn = if view { count * 6 } else { count * 2 };
    let mut cloud: Vec<(DVec3, usize)> = Vec::new();
    for (j, x) in meshes.iter().enumerate() {
        let n = ((drawn as f64) * totals[j] / all).ceil() as usize;
        let mut cumulative = Vec::with_capacity(tess.triangles().len());
        let mut total = 0.0;
        for t in tess.triangles() {
            total += area(x, t);
            cumulative.push(total);
        }
        for _ in 0..n {
            let pick = rng.uniform() * total;
            let i = cumulative
                .partition_point(|&c| c < pick)
                .min(cumulative.len() - 1);
            let [a, b, c] = tess.triangles()[i].map(|k| x[k as usize]);
            let (r1, r2) = (rng.uniform().sqrt(), rng.uniform());
            let p = a * (1.0 - r1) + b * (r1 * (1.0 - r2)) + c * (r1 * r2);
            if parts
                .iter()
                .enumerate()
                .all(|(k, o)| k == j || !o.contains(p))
            {
                cloud.push((p, j));
            }
        }
    }
    if view {
        cloud = one_view(cloud, unit_vector(rng), count);
    }
    let (lo, hi) = cloud.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), (x, _)| (lo.min(*x), hi.max(*x)),
    );
    thin(&cloud, count, noise * (hi - lo).length(), rng)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn creatures_have_their_parts_each_on_their_surface() {
        for (seed, parts) in [(1, 2), (2, 6), (3, 16)] {
            let c = creature(seed, parts, 3000, 0.0, false);
            assert_eq!(c.parts.len(), parts, "seed {seed}");
            assert_eq!(c.points.len(), c.owner.len());
            assert!(
                (2500..=3500).contains(&c.points.len()),
                "{}",
                c.points.len()
            );
            // Every part shows some of its surface, and no point lies inside another part.
            for j in 0..parts {
                assert!(c.owner.contains(&j), "seed {seed}: part {j} hidden");
            }
            for (p, &j) in c.points.iter().zip(&c.owner) {
                for (k, q) in c.parts.iter().enumerate() {
                    assert!(k == j || !q.contains(*p));
                }
            }
            // The same seed gives the same creature.
            assert_eq!(c.points, creature(seed, parts, 3000, 0.0, false).points);
        }
    }

    #[test]
    fn a_deformed_part_contains_what_its_surface_bounds() {
        let part = CreaturePart {
            pose: InitialPose {
                translation: DVec3::new(0.3, 0.1, -0.2),
                rotation: DQuat::from_rotation_x(0.4),
                shape: shape(DVec3::new(0.2, 0.15, 0.8), 0.7, 1.2),
            },
            deformation: GlobalDeformation {
                taper: [0.4, -0.2],
                bend: [0.3, 0.5],
            },
        };
        for (u, v) in [(0.3, 0.2), (-1.0, 2.0), (1.2, -2.5), (0.0, 1.0)] {
            let s = shape_at(&part.pose.shape, u, v);
            assert!(part.contains(part.place(s * 0.95)), "({u}, {v}) inside");
            assert!(!part.contains(part.place(s * 1.05)), "({u}, {v}) outside");
        }
    }
}
