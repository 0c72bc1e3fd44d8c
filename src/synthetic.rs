//! Deterministic synthetic data: the paper's range experiments (section VI-B), whose NRCC range
//! maps are not public, rebuilt from their description, and clouds sampled from superquadrics
//! with known parameters.
//!
//! * [`egg`]: 499 points from the upper half of an egg, as a range camera looking down −z sees it
//!   (an orthographic grid of rays, first hit).
//! * [`mug`]: 651 points from the upper part of an upright mug whose wall has pits.
//! * [`superquadric_cloud`]: points on a superquadric with known pose and parameters.

use crate::model::fit::{FitOptions, Initialization};
use crate::model::init::{InitialPose, moments};
use crate::model::superquadric::{SuperquadricParams, shape_at};
use bevy::math::{DQuat, DVec3};
use std::f64::consts::{FRAC_PI_2, PI};

/// A small deterministic generator (SplitMix64), so data and tests are the same on every machine.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    /// A generator from a seed.
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }
    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }
    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = self.uniform().max(1e-300);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (2.0 * PI * u2).cos()
    }
    /// Picks `n` of `items` without replacement, keeping their order.
    pub fn choose<T: Clone>(&mut self, items: &[T], n: usize) -> Vec<T> {
        let mut idx: Vec<usize> = (0..items.len()).collect();
        for i in 0..n.min(idx.len()) {
            let j = i + (self.next_u64() % (idx.len() - i) as u64) as usize;
            idx.swap(i, j);
        }
        let mut chosen: Vec<usize> = idx.into_iter().take(n).collect();
        chosen.sort_unstable();
        chosen.into_iter().map(|i| items[i].clone()).collect()
    }
}

/// Semi-length of the synthetic egg along its long (x) axis.
pub const EGG_HALF_LENGTH: f64 = 0.75;
/// Equatorial radius of the synthetic egg.
pub const EGG_RADIUS: f64 = 0.55;

/// Radius of the egg's cross-section at x (an egg: fatter towards +x), 0 outside |x| ≤ half length.
pub fn egg_radius(x: f64) -> f64 {
    let c = (x / EGG_HALF_LENGTH).clamp(-1.0, 1.0);
    EGG_RADIUS * (1.0 - c * c).max(0.0).sqrt() * (1.0 + 0.18 * c)
}

/// The paper's egg data: 499 points on the upper half (z ≥ 0) of an egg lying along x, sampled by
/// a range camera looking down −z on a regular grid, then thinned to 499 at random.
pub fn egg() -> Vec<DVec3> {
    let h = 0.045;
    let mut pts = Vec::new();
    let n = (EGG_HALF_LENGTH / h).ceil() as i32 + 1;
    for i in -n..=n {
        for j in -n..=n {
            let (x, y) = (i as f64 * h, j as f64 * h);
            let r = egg_radius(x);
            if y.abs() < r {
                pts.push(DVec3::new(x, y, (r * r - y * y).sqrt()));
            }
        }
    }
    Rng::new(233).choose(&pts, 499)
}

/// Mug radius.
pub const MUG_RADIUS: f64 = 0.5;
/// Mug half height.
pub const MUG_HALF_HEIGHT: f64 = 0.8;
/// Depth of each pit in the mug's wall.
pub const MUG_PIT_DEPTH: f64 = 0.07;
/// Radius of each pit on the wall.
pub const MUG_PIT_RADIUS: f64 = 0.16;

/// Centres of the mug's pits as (azimuth, height).
pub fn mug_pits() -> Vec<(f64, f64)> {
    let mut rng = Rng::new(251);
    (0..10)
        .map(|i| {
            (
                -PI + (i as f64 + rng.range(0.2, 0.8)) * 2.0 * PI / 10.0,
                rng.range(0.2, 0.6),
            )
        })
        .collect()
}

/// Inward depth of the pitted wall at (azimuth, height): smooth spherical-cap dents.
pub fn mug_pit_depth(azimuth: f64, z: f64) -> f64 {
    mug_pits()
        .iter()
        .map(|&(a, h)| {
            let da = (azimuth - a + PI).rem_euclid(2.0 * PI) - PI;
            let d2 = (da * MUG_RADIUS).powi(2) + (z - h).powi(2);
            let t = 1.0 - d2 / (MUG_PIT_RADIUS * MUG_PIT_RADIUS);
            if t > 0.0 { MUG_PIT_DEPTH * t * t } else { 0.0 }
        })
        .fold(0.0, f64::max)
}

/// The paper's mug data: 651 points on the upper part of an upright mug (axis z): its closed top
/// and its wall down to mid-height, the wall dented by pits ([`mug_pits`]).
pub fn mug() -> Vec<DVec3> {
    let mut rng = Rng::new(251_1683);
    let wall_area = 2.0 * PI * MUG_RADIUS * MUG_HALF_HEIGHT;
    let top_area = PI * MUG_RADIUS * MUG_RADIUS;
    (0..651)
        .map(|_| {
            if rng.uniform() < wall_area / (wall_area + top_area) {
                let az = rng.range(-PI, PI);
                let z = rng.range(0.0, MUG_HALF_HEIGHT);
                let r = MUG_RADIUS - mug_pit_depth(az, z);
                DVec3::new(r * az.cos(), r * az.sin(), z)
            } else {
                let r = MUG_RADIUS * rng.uniform().sqrt();
                let az = rng.range(-PI, PI);
                DVec3::new(r * az.cos(), r * az.sin(), MUG_HALF_HEIGHT)
            }
        })
        .collect()
}

/// `n` points on the superquadric `shape` placed at (`translation`, `rotation`), at material
/// coordinates drawn so that a sphere would be sampled uniformly (u = asin(2r − 1)), with
/// Gaussian noise of standard deviation `noise` (data units) added to each coordinate.
pub fn superquadric_cloud(
    shape: &SuperquadricParams,
    translation: DVec3,
    rotation: DQuat,
    n: usize,
    noise: f64,
    seed: u64,
) -> Vec<DVec3> {
    let mut rng = Rng::new(seed);
    (0..n)
        .map(|_| {
            let u = (2.0 * rng.uniform() - 1.0)
                .asin()
                .clamp(-FRAC_PI_2, FRAC_PI_2);
            let v = rng.range(-PI, PI);
            let p = translation + rotation * shape_at(shape, u, v);
            p + noise * DVec3::new(rng.normal(), rng.normal(), rng.normal())
        })
        .collect()
}

/// A paper experiment: its data and the fit options the paper gives.
fn paper_experiment(
    points: Vec<DVec3>,
    k: usize,
    w0: f64,
    w1: f64,
    shape: SuperquadricParams,
) -> (Vec<DVec3>, FitOptions) {
    let mut o = FitOptions {
        k,
        ..Default::default()
    };
    o.dynamics.w0 = w0;
    o.dynamics.w1 = w1;
    o.init = Initialization::Explicit(InitialPose {
        translation: moments(&points).centroid,
        rotation: DQuat::IDENTITY,
        shape,
    });
    (points, o)
}

/// The paper's third experiment: [`egg`] data, 2603 nodes (k = 51), w0 = 1e-6, w1 = 0.1, and the
/// initial sphere at the data's centre of gravity, a = 1.2, a1 = a2 = a3 = 0.5, ε1 = ε2 = 1.
pub fn egg_experiment() -> (Vec<DVec3>, FitOptions) {
    let sphere = SuperquadricParams {
        a: 1.2,
        a1: 0.5,
        a2: 0.5,
        a3: 0.5,
        e1: 1.0,
        e2: 1.0,
    };
    paper_experiment(egg(), 51, 1e-6, 0.1, sphere)
}

/// The paper's fourth experiment: [`mug`] data, 1683 nodes (k = 41), w0 = 0.01, w1 = 0.1, and the
/// "tubular" initial state a = 1.5, a1 = a2 = 0.3, a3 = 0.8, ε1 = 0.7, ε2 = 1.0, upright at the
/// data's centroid.
pub fn mug_experiment() -> (Vec<DVec3>, FitOptions) {
    let tube = SuperquadricParams {
        a: 1.5,
        a1: 0.3,
        a2: 0.3,
        a3: 0.8,
        e1: 0.7,
        e2: 1.0,
    };
    paper_experiment(mug(), 41, 0.01, 0.1, tube)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn egg_and_mug_have_the_papers_point_counts() {
        let e = egg();
        assert_eq!(e.len(), 499);
        assert!(e.iter().all(|p| p.z >= 0.0));
        let m = mug();
        assert_eq!(m.len(), 651);
        assert!(
            m.iter()
                .all(|p| p.z >= 0.0 && p.z <= MUG_HALF_HEIGHT + 1e-12)
        );
        // Some wall points lie in pits.
        assert!(
            m.iter()
                .filter(|p| p.z < MUG_HALF_HEIGHT && MUG_RADIUS - p.truncate().length() > 0.02)
                .count()
                > 20
        );
    }

    #[test]
    fn generator_is_deterministic() {
        assert_eq!(egg(), egg());
        assert_eq!(Rng::new(7).next_u64(), Rng::new(7).next_u64());
    }
}
