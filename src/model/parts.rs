//! Several parts fitted to one range cloud (the paper's doll experiment, section VI-A, in 3D):
//! every data point pulls on the part whose surface lies nearest it.
//!
//! [`fit_parts`] with [`PartCount::Auto`] finds the parts by description length ([`split`]:
//! small patches of the cloud merged while a merge pays, parts added where points are left
//! unexplained). With [`PartCount::Exact`] it runs [`partition`]:
//!
//! The loop alternates two steps until no point changes part: fit every part to its points (each
//! part a global-only [`fit`], the parts in parallel), then give every point to the part whose
//! fitted surface is nearest. Then, if the options have local DOFs, each part is fitted once more
//! with them to its final points (fitting them in the rounds would let a part's membrane stretch
//! over its neighbour's points and keep them). The first partition is k-means on the points (k-means++-style farthest-point
//! seeding, deterministic), and the first fit of each part starts from the moments of its
//! cluster; later rounds start each part from its last fit.

use super::dynamics::ModelState;
use super::fem::Tessellation;
use super::fit::{
    FitError, FitOptions, FitReport, Initialization, MIN_POINTS, fit, point_distances,
    validate_points,
};
use super::init::InitialPose;
use super::parallel::run_parallel;
use glam::DVec3;

mod joints;
mod merge;
mod patches;
mod split;

use super::fit::spread_sample;
pub use joints::{PartJoint, joints};
pub use split::{
    DEFAULT_MAX_PARTS, PART_PARAMETERS, PATCHES, Scale, TOLERANCE, WORK_POINTS, split,
};

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

/// Rounds of fit-then-reassign that [`fit_parts`]'s callers use by default (`dsq fit`'s
/// `--parts`, scenes' shared sources): on the scans in `assets/` the partition has settled, or
/// moves a handful of points back and forth, by then.
pub const PARTITION_ROUNDS: u32 = 8;

/// What [`partition`] and [`fit_parts`] return.
#[derive(Clone, Debug)]
pub struct Partition {
    /// The fit of each part, in data units: from [`partition`], the last global-only fit; from
    /// [`fit_parts`], the final fit (with local DOFs when the options have them).
    pub fits: Vec<FitReport>,
    /// The part each data point belongs to (index into `fits`).
    pub owner: Vec<usize>,
    /// Rounds of fit-then-reassign taken.
    pub rounds: u32,
    /// True when the last round moved no point to another part.
    pub stable: bool,
    /// How many points the last round moved to another part.
    pub moved: usize,
}

/// How many parts [`fit_parts`] makes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PartCount {
    /// As many as lower the description length ([`split`]), at most this many.
    Auto(usize),
    /// Exactly this many ([`partition`] from k-means clusters).
    Exact(usize),
}

/// A whole object fitted as parts ([`split`], [`fit_parts`]).
#[derive(Clone, Debug)]
pub struct Whole {
    /// The fit of each part, in data units.
    pub fits: Vec<FitReport>,
    /// The part each data point belongs to (index into `fits`): the one whose surface is
    /// nearest.
    pub owner: Vec<usize>,
    /// The joints between the parts that touch.
    pub joints: Vec<PartJoint>,
    /// The description length's scale (see [`split`]).
    pub scale: Scale,
    /// The fraction of the points the parts explain: those within [`Scale::reach`] of the
    /// nearest part's surface.
    pub explained: f64,
    /// For each part, the fraction of its points (those nearest it) within [`Scale::reach`] of
    /// its surface.
    pub part_explained: Vec<f64>,
}

impl Whole {
    /// The whole object of `fits` on `points` at `scale`: every point given to the part whose
    /// surface is nearest, the parts that touch joined, and what the parts explain.
    pub fn of(points: &[DVec3], fits: Vec<FitReport>, scale: Scale) -> Self {
        let (owner, distance) = nearest_surface(points, fits.iter().map(|f| (&f.tess, &f.state)));
        let reach = scale.reach();
        let mut within = vec![(0usize, 0usize); fits.len()];
        for (&j, &d) in owner.iter().zip(&distance) {
            within[j].1 += 1;
            if d <= reach {
                within[j].0 += 1;
            }
        }
        let explained =
            within.iter().map(|w| w.0).sum::<usize>() as f64 / points.len().max(1) as f64;
        Self {
            joints: joints(&fits, scale.tau),
            part_explained: within
                .iter()
                .map(|&(k, n)| if n == 0 { 1.0 } else { k as f64 / n as f64 })
                .collect(),
            fits,
            owner,
            scale,
            explained,
        }
    }
}

/// Checks that `n` points can be split into `parts`: at least one part, and [`MIN_POINTS`] points
/// a part.
fn check_parts(n: usize, parts: usize) -> Result<(), FitError> {
    if parts == 0 || n < parts.saturating_mul(MIN_POINTS) {
        return Err(FitError::BadOption(format!(
            "parts = {parts} is out of range [1, {}]: each part needs {MIN_POINTS} points and the cloud has {n}",
            n / MIN_POINTS
        )));
    }
    Ok(())
}

/// Splits `points` among parts, one per entry of `opts` (each part's own tessellation, stiffness
/// and forces): at most `rounds` rounds of global-only fits, each followed by giving every point
/// to the part whose fitted surface is nearest (see the module docs).
///
/// The first split: when every part starts from [`Initialization::Moments`], k-means on the
/// points, and each part's first fit starts from its cluster's moments; when every part starts
/// from an [`Initialization::Explicit`] pose, each point goes to the part whose initial surface
/// is nearest. Later rounds start each part from its last fit; a round that would leave a part
/// fewer than [`MIN_POINTS`] points is not taken, and the partition ends unsettled with the
/// points each part was last fitted to.
///
/// Errors: a mix of the two kinds of start, fewer than [`MIN_POINTS`] points for some part in
/// the first split (named), or a part's fit failing.
pub fn partition(
    points: &[DVec3],
    opts: &[FitOptions],
    rounds: u32,
) -> Result<Partition, FitError> {
    super::fit::validate_points(points)?;
    let k = opts.len();
    check_parts(points.len(), k)?;
    let explicit: Vec<Option<InitialPose>> = opts
        .iter()
        .map(|o| match o.init {
            Initialization::Explicit(pose) => Some(pose),
            Initialization::Moments => None,
        })
        .collect();
    let mut owner = if explicit.iter().all(Option::is_none) {
        kmeans(points, k, 50)
    } else if let Some(poses) = explicit.iter().copied().collect::<Option<Vec<_>>>() {
        let surfaces: Vec<(Tessellation, ModelState)> = poses
            .iter()
            .zip(opts)
            .map(|(pose, o)| {
                let tess = Tessellation::new(o.k);
                let state = ModelState::new(
                    &tess,
                    pose.translation,
                    pose.rotation,
                    pose.shape.normalized(),
                );
                (tess, state)
            })
            .collect();
        nearest_surface(points, surfaces.iter().map(|(t, s)| (t, s))).0
    } else {
        return Err(FitError::BadOption(
            "the parts must all start from the moments of their points or all from explicit poses"
                .into(),
        ));
    };
    // The partition rounds fit pure superquadrics: a membrane would stretch each part over its
    // neighbour's points and keep them. The local DOFs come in once the partition has settled.
    let mut global: Vec<FitOptions> = opts
        .iter()
        .map(|o| FitOptions {
            global_only: true,
            ..*o
        })
        .collect();
    let mut fits: Vec<FitReport> = Vec::new();
    let mut taken = 0;
    let mut moved = 0;
    // The ownership the last fits were fitted to.
    let mut last: Option<Vec<usize>> = None;
    for _ in 0..rounds.max(1) {
        let members = members_of(points, &owner, k);
        if let Some((j, m)) = members
            .iter()
            .enumerate()
            .find(|(_, m)| m.len() < MIN_POINTS)
        {
            // A later round that would leave a part too few points to fit is not taken: the
            // last round's fits stand, each with the points it was fitted to, unsettled.
            if let Some(fitted) = last.take() {
                owner = fitted;
                break;
            }
            return Err(FitError::BadOption(format!(
                "part {j} was left with {} points (fewer than {MIN_POINTS}); try fewer parts",
                m.len()
            )));
        }
        fits = fit_each(&members, &global)?;
        taken += 1;
        let next = nearest_surface(points, fits.iter().map(|f| (&f.tess, &f.state))).0;
        for (o, f) in global.iter_mut().zip(&fits) {
            o.init = Initialization::Explicit(InitialPose::of(&f.state));
        }
        moved = next.iter().zip(&owner).filter(|(a, b)| a != b).count();
        last = Some(std::mem::replace(&mut owner, next));
        if moved == 0 {
            break;
        }
    }
    // The last round's nearest surfaces, when they leave a part too few points, give way to
    // the points it was fitted to, as above.
    let mut count = vec![0usize; k];
    owner.iter().for_each(|&j| count[j] += 1);
    if count.iter().any(|&c| c < MIN_POINTS)
        && let Some(fitted) = last
    {
        owner = fitted;
    }
    Ok(Partition {
        fits,
        owner,
        rounds: taken,
        stable: moved == 0,
        moved,
    })
}

/// Fits a whole object: `points` split into parts, each a pure superquadric fitted with `opts`;
/// then, when `opts` has local DOFs, each part fitted once more with them to its points, from
/// its pure fit; and the parts that touch joined ([`joints`]). [`PartCount::Auto`]: by
/// description length ([`split`]); [`PartCount::Exact`]: the [`partition`] of that many parts
/// from k-means clusters, [`PARTITION_ROUNDS`] rounds at most. Errors as theirs.
pub fn fit_parts(points: &[DVec3], count: PartCount, opts: &FitOptions) -> Result<Whole, FitError> {
    let mut whole = match count {
        PartCount::Auto(cap) => split(points, cap, opts)?,
        PartCount::Exact(k) => {
            validate_points(points)?;
            check_parts(points.len(), k)?;
            let each = vec![
                FitOptions {
                    init: Initialization::Moments,
                    ..*opts
                };
                k
            ];
            let p = partition(points, &each, PARTITION_ROUNDS)?;
            Whole::of(
                points,
                p.fits,
                Scale::of(&spread_sample(points, WORK_POINTS)),
            )
        }
    };
    if super::fit::has_joint_stage(opts) {
        // Each part fitted once more with the local DOFs, from its pure superquadric, to the
        // points nearest it.
        let members = members_of(points, &whole.owner, whole.fits.len());
        let jobs: Vec<(&Vec<DVec3>, FitOptions)> = members
            .iter()
            .zip(&whole.fits)
            .map(|(m, f)| {
                let init = Initialization::Explicit(InitialPose::of(&f.state));
                (m, FitOptions { init, ..*opts })
            })
            .collect();
        let local = run_parallel(
            &jobs,
            |(m, o), _| fit(if m.len() >= MIN_POINTS { m } else { points }, o, |_| {}),
            &mut |_: &()| {},
        );
        let fits = local.into_iter().collect::<Result<Vec<_>, _>>()?;
        whole = Whole::of(points, fits, whole.scale);
    }
    Ok(whole)
}

/// The index of the surface nearest each point, among `surfaces` (tessellation and state), and
/// the point's distance from it.
fn nearest_surface<'a>(
    points: &[DVec3],
    surfaces: impl Iterator<Item = (&'a Tessellation, &'a ModelState)>,
) -> (Vec<usize>, Vec<f64>) {
    let mut best = vec![(f64::INFINITY, 0usize); points.len()];
    let mut x = Vec::new();
    for (j, (tess, state)) in surfaces.enumerate() {
        state.node_positions(tess, &mut x);
        for (b, d) in best.iter_mut().zip(point_distances(tess, &x, points)) {
            if d < b.0 {
                *b = (d, j);
            }
        }
    }
    best.into_iter().map(|(d, j)| (j, d)).unzip()
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

/// Fits every part to its points with its options, the parts side by side ([`run_parallel`]).
fn fit_each(members: &[Vec<DVec3>], opts: &[FitOptions]) -> Result<Vec<FitReport>, FitError> {
    let jobs: Vec<(&Vec<DVec3>, &FitOptions)> = members.iter().zip(opts).collect();
    run_parallel(&jobs, |(m, o), _| fit(m, o, |_| {}), &mut |_: &()| {})
        .into_iter()
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::superquadric::SuperquadricParams;
    use crate::synthetic::superquadric_cloud;
    use glam::DQuat;

    /// Points on two superquadrics (shape, centre, count), with noise; and how many are on the first.
    fn two_clouds(
        a: (&SuperquadricParams, DVec3, usize),
        b: (&SuperquadricParams, DVec3, usize),
        noise: f64,
    ) -> (Vec<DVec3>, usize) {
        let mut points = superquadric_cloud(a.0, a.1, DQuat::IDENTITY, a.2, noise, 3);
        let n = points.len();
        points.extend(superquadric_cloud(b.0, b.1, DQuat::IDENTITY, b.2, noise, 4));
        (points, n)
    }

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
        let (points, n_body) = two_clouds((&body, c_body, 600), (&post, c_post, 500), 0.01);
        let report = fit_parts(
            &points,
            PartCount::Exact(2),
            &FitOptions::default().for_data(),
        )
        .expect("fit");
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
        for (j, part) in report.fits.iter().enumerate() {
            assert!(part.state.is_finite());
            assert!(part.residuals.mean < 0.01, "part {j}: {:?}", part.residuals);
        }
        // The post's part is centred on the post.
        let post_fit = &report.fits[post_part].state;
        assert!(post_fit.translation.distance(c_post) < 0.1, "{post_fit:?}");
    }

    #[test]
    fn explicit_starts_split_by_the_nearest_initial_surface_and_mixed_starts_are_refused() {
        // Two unit spheres 4 apart; each part starts as a small sphere near one of them.
        let sphere = SuperquadricParams::default();
        let (c0, c1) = (DVec3::ZERO, DVec3::new(4.0, 0.0, 0.0));
        let (points, n0) = two_clouds((&sphere, c0, 300), (&sphere, c1, 300), 0.0);
        let small = SuperquadricParams { a: 0.5, ..sphere };
        let at = |c: DVec3| FitOptions {
            k: 11,
            init: Initialization::Explicit(InitialPose {
                translation: c + DVec3::splat(0.2),
                rotation: DQuat::IDENTITY,
                shape: small,
            }),
            ..FitOptions::default()
        };
        // Listed far sphere first: the split follows the starts, not the order of the points.
        let p = partition(&points, &[at(c1), at(c0)], 4).expect("partition");
        assert!(p.owner[..n0].iter().all(|&o| o == 1), "first sphere");
        assert!(p.owner[n0..].iter().all(|&o| o == 0), "second sphere");
        assert!(p.stable && p.moved == 0, "{} moved", p.moved);
        assert!(p.fits[0].state.translation.distance(c1) < 0.05);
        assert!((p.fits[1].state.shape.a - 1.0).abs() < 0.05);
        let moments = FitOptions {
            init: Initialization::Moments,
            ..at(c0)
        };
        let e = partition(&points, &[at(c1), moments], 4).unwrap_err();
        assert!(e.to_string().contains("all start from"), "{e}");
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
        for parts in [3, 0, usize::MAX] {
            let e =
                fit_parts(&points, PartCount::Exact(parts), &FitOptions::default()).unwrap_err();
            assert!(
                e.to_string()
                    .contains(&format!("parts = {parts} is out of range [1, 2]")),
                "{e}"
            );
        }
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
