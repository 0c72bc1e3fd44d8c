//! Several parts fitted to one range cloud (the paper's doll experiment, section VI-A, in 3D):
//! every data point pulls on the part whose surface lies nearest it.
//!
//! The loop alternates two steps until no point changes part: fit every part to its points (each
//! part a global-only [`fit`], the parts in parallel), then give every point to the part whose
//! fitted surface is nearest. Then, if the options have local DOFs, each part is fitted once more
//! with them to its final points (fitting them in the rounds would let a part's membrane stretch
//! over its neighbour's points and keep them). The first partition is k-means on the points (k-means++-style farthest-point
//! seeding, deterministic), and the first fit of each part starts from the moments of its
//! cluster; later rounds start each part from its last fit.

use super::fit::{
    FitError, FitOptions, FitReport, Initialization, MIN_POINTS, fit, point_distances, run_parallel,
};
use super::init::InitialPose;
use bevy::math::DVec3;

/// What [`fit_parts`] returns.
#[derive(Clone, Debug)]
pub struct PartsReport {
    /// The fit of each part, in data units.
    pub parts: Vec<FitReport>,
    /// The part each data point belongs to (index into `parts`).
    pub owner: Vec<usize>,
    /// Rounds of fit-then-reassign taken.
    pub rounds: u32,
    /// True when the last round moved no point to another part.
    pub stable: bool,
}

/// k-means clusters of `points`: the cluster of each point. Seeds: the point farthest from the
/// centroid, then repeatedly the point farthest from every seed so far; then `iterations` Lloyd
/// steps. Deterministic.
pub fn kmeans(points: &[DVec3], k: usize, iterations: u32) -> Vec<usize> {
    if points.is_empty() || k == 0 {
        return vec![0; points.len()];
    }
    let centroid = points.iter().copied().sum::<DVec3>() / points.len() as f64;
    let far_from = |seeds: &[DVec3]| {
        points
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let d = seeds
                    .iter()
                    .map(|s| s.distance_squared(*p))
                    .fold(f64::INFINITY, f64::min);
                (i, d)
            })
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .map_or(0, |(i, _)| i)
    };
    let mut centres = vec![points[far_from(&[centroid])]];
    while centres.len() < k.min(points.len()) {
        centres.push(points[far_from(&centres)]);
    }
    let nearest = |p: &DVec3, centres: &[DVec3]| {
        centres
            .iter()
            .enumerate()
            .map(|(j, c)| (j, c.distance_squared(*p)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map_or(0, |(j, _)| j)
    };
    let mut label: Vec<usize> = points.iter().map(|p| nearest(p, &centres)).collect();
    for _ in 0..iterations {
        let mut sum = vec![DVec3::ZERO; centres.len()];
        let mut count = vec![0usize; centres.len()];
        for (p, &l) in points.iter().zip(&label) {
            sum[l] += *p;
            count[l] += 1;
        }
        for j in 0..centres.len() {
            if count[j] > 0 {
                centres[j] = sum[j] / count[j] as f64;
            }
        }
        let next: Vec<usize> = points.iter().map(|p| nearest(p, &centres)).collect();
        if next == label {
            break;
        }
        label = next;
    }
    label
}

/// Fits `k` parts to `points` (see the module docs), at most `rounds` rounds. Each part is fitted
/// with `opts` (its `init` is replaced: moments of the cluster first, then the last fit).
/// Errors: fewer than [`MIN_POINTS`] points per part, or a part's fit failing (named).
pub fn fit_parts(
    points: &[DVec3],
    k: usize,
    rounds: u32,
    opts: &FitOptions,
) -> Result<PartsReport, FitError> {
    super::fit::validate_points(points)?;
    if k == 0 || points.len() < k * MIN_POINTS {
        return Err(FitError::BadOption(format!(
            "{k} parts need at least {} points ({MIN_POINTS} each); the cloud has {}",
            k.max(1) * MIN_POINTS,
            points.len()
        )));
    }
    let mut owner = kmeans(points, k, 50);
    // The partition rounds fit pure superquadrics: a membrane would stretch each part over its
    // neighbour's points and keep them. The local DOFs come in once the partition has settled.
    let global = FitOptions {
        global_only: true,
        ..*opts
    };
    let mut starts: Vec<Initialization> = vec![Initialization::Moments; k];
    let mut parts: Vec<FitReport> = Vec::new();
    let mut stable = false;
    let mut taken = 0;
    for _ in 0..rounds.max(1) {
        taken += 1;
        let members = members_of(points, &owner, k);
        if let Some((j, m)) = members
            .iter()
            .enumerate()
            .find(|(_, m)| m.len() < MIN_POINTS)
        {
            return Err(FitError::BadOption(format!(
                "part {j} was left with {} points (fewer than {MIN_POINTS}); try fewer parts",
                m.len()
            )));
        }
        parts = fit_each(&members, &starts, &global)?;
        // Every point to the part whose surface is nearest.
        let mut best = vec![(f64::INFINITY, 0usize); points.len()];
        for (j, part) in parts.iter().enumerate() {
            let mut x = Vec::new();
            part.state.node_positions(&part.tess, &mut x);
            for (i, d) in point_distances(&part.tess, &x, points)
                .into_iter()
                .enumerate()
            {
                if d < best[i].0 {
                    best[i] = (d, j);
                }
            }
        }
        let next: Vec<usize> = best.into_iter().map(|(_, j)| j).collect();
        starts = parts
            .iter()
            .map(|p| {
                Initialization::Explicit(InitialPose {
                    translation: p.state.translation,
                    rotation: p.state.rotation,
                    shape: p.state.shape,
                })
            })
            .collect();
        if next == owner {
            stable = true;
            break;
        }
        owner = next;
    }
    if super::fit::has_joint_stage(opts) {
        let members = members_of(points, &owner, k);
        parts = fit_each(&members, &starts, opts)?;
    }
    Ok(PartsReport {
        parts,
        owner,
        rounds: taken,
        stable,
    })
}

/// The points of each of `k` parts.
fn members_of(points: &[DVec3], owner: &[usize], k: usize) -> Vec<Vec<DVec3>> {
    (0..k)
        .map(|j| {
            points
                .iter()
                .zip(owner)
                .filter(|(_, o)| **o == j)
                .map(|(p, _)| *p)
                .collect()
        })
        .collect()
}

/// Fits every part to its points from its start, the parts spread over the cores.
fn fit_each(
    members: &[Vec<DVec3>],
    starts: &[Initialization],
    opts: &FitOptions,
) -> Result<Vec<FitReport>, FitError> {
    let jobs: Vec<(&Vec<DVec3>, Initialization)> =
        members.iter().zip(starts.iter().copied()).collect();
    run_parallel(
        &jobs,
        |(m, init), _| {
            let o = FitOptions {
                init: *init,
                ..*opts
            };
            fit(m, &o, |_| {})
        },
        &mut |_| {},
    )
    .into_iter()
    .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::superquadric::SuperquadricParams;
    use crate::synthetic::superquadric_cloud;
    use bevy::math::DQuat;

    #[test]
    fn two_touching_parts_are_separated_and_each_fitted() {
        // A squat box and a tall cylinder side by side, 1 % noise.
        let body = SuperquadricParams {
            a: 1.0,
            a1: 1.0,
            a2: 0.6,
            a3: 0.4,
            e1: 0.3,
            e2: 0.3,
        };
        let post = SuperquadricParams {
            a: 1.0,
            a1: 0.3,
            a2: 0.3,
            a3: 1.0,
            e1: 0.2,
            e2: 1.0,
        };
        let c_body = DVec3::ZERO;
        let c_post = DVec3::new(1.45, 0.0, 0.6);
        let mut points = superquadric_cloud(&body, c_body, DQuat::IDENTITY, 600, 0.01, 3);
        let n_body = points.len();
        points.extend(superquadric_cloud(
            &post,
            c_post,
            DQuat::IDENTITY,
            500,
            0.01,
            4,
        ));
        let report = fit_parts(&points, 2, 6, &FitOptions::default()).expect("fit");
        assert_eq!(report.owner.len(), points.len());
        assert!(report.owner.iter().all(|&o| o < 2));
        // Each true object ends up (almost) all in one part, a different one for each.
        let share = |range: std::ops::Range<usize>, part: usize| {
            range.clone().filter(|&i| report.owner[i] == part).count() as f64 / range.len() as f64
        };
        let body_part = usize::from(share(0..n_body, 1) > 0.5);
        let post_part = 1 - body_part;
        let (b, p) = (
            share(0..n_body, body_part),
            share(n_body..points.len(), post_part),
        );
        assert!(b > 0.95 && p > 0.95, "body {b:.3}, post {p:.3}");
        for (j, part) in report.parts.iter().enumerate() {
            assert!(part.state.is_finite());
            assert!(part.residuals.mean < 0.01, "part {j}: {:?}", part.residuals);
        }
        // The post's part is centred on the post.
        let post_fit = &report.parts[post_part].state;
        assert!(post_fit.translation.distance(c_post) < 0.1, "{post_fit:?}");
    }

    #[test]
    fn too_many_parts_for_the_points_is_an_error() {
        let points = superquadric_cloud(
            &SuperquadricParams::default(),
            DVec3::ZERO,
            DQuat::IDENTITY,
            25,
            0.0,
            1,
        );
        let e = fit_parts(&points, 3, 2, &FitOptions::default()).unwrap_err();
        assert!(
            e.to_string().contains("3 parts need at least 30 points"),
            "{e}"
        );
    }

    #[test]
    fn kmeans_splits_two_blobs() {
        let mut points: Vec<DVec3> = (0..50).map(|i| DVec3::splat(i as f64 * 1e-3)).collect();
        points.extend((0..50).map(|i| DVec3::new(5.0, 0.0, 0.0) + DVec3::splat(i as f64 * 1e-3)));
        let l = kmeans(&points, 2, 10);
        assert!(l[..50].iter().all(|&x| x == l[0]));
        assert!(l[50..].iter().all(|&x| x == l[50]));
        assert_ne!(l[0], l[50]);
    }
}
