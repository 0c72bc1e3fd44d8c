//! A starting tapering and bending read off the data's centreline (beyond the paper).
//!
//! A fit that frees tapering and bending ([`super::deform`]) would otherwise start them at zero,
//! from a straight superquadric boxing a curved cloud, and the dynamics then often settle in the
//! nearer local minimum of a longer, rounder, over-bent model. The cloud shows its curvature and
//! its taper before any fitting: sliced across the hypothesis's z axis, the slices' centroids trace
//! the axis, and their spreads trace the cross-section's size along it.
//!
//! [`seed_deformation`] fits a circle to the slice centroids in the plane they bend in (an arc of
//! half-angle φ and radius R gives the bend |b| = φ and the half-length A = Rφ), and a line to the
//! slice spreads (the taper t = slope · A / r0, r0 the spread at the middle; each spread a high
//! quantile of the slice's distances from its centre, [`SPREAD_QUANTILE`]). The pose moves to the
//! arc's middle and the section semi-axes become the middle spreads.

use super::deform::GlobalDeformation;
use super::fem::Tessellation;
use super::init::InitialPose;
use super::linalg::cholesky_solve;
use glam::{DMat3, DVec2, DVec3};

/// Slices along the hypothesis's z axis.
pub const SEED_SLICES: usize = 12;

/// The bend (radians, from the parabola through the slice centroids) from which the centreline is
/// taken as a circle's arc rather than a parabola's.
pub const CIRCLE_FROM: f64 = 0.15;

/// Fewest points a slice needs to count.
const MIN_SLICE_POINTS: usize = 5;

/// A slice across z: its count, mean z, centroid (x, y) and the indices of its points.
#[derive(Clone, Default)]
struct Slice {
    n: f64,
    z: f64,
    centre: DVec2,
    members: Vec<u32>,
}

/// The quantile of a slice's points' distances from its centre, along x and along y, taken as the
/// section's semi-axes there: near the largest distance on a tube's ring, and on an end cap's disk
/// too (where a spread from the variance would be too small by √2).
pub const SPREAD_QUANTILE: f64 = 0.9;

/// The normal equations Σ w φ φᵀ c = Σ w φ y of a weighted least-squares fit over
/// `(w, φ, y)` samples with three basis values φ each.
fn normal_equations(
    samples: impl Iterator<Item = (f64, [f64; 3], f64)>,
) -> ([[f64; 3]; 3], [f64; 3]) {
    let mut a = [[0.0; 3]; 3];
    let mut b = [0.0; 3];
    for (w, basis, y) in samples {
        for i in 0..3 {
            b[i] += w * basis[i] * y;
            for j in 0..3 {
                a[i][j] += w * basis[i] * basis[j];
            }
        }
    }
    (a, b)
}

/// Weighted least squares of `y ≈ c0 + c1 x + c2 x²` over `(w, x, y)` (or of a line when
/// `quadratic` is false, with c2 = 0).
fn polyfit(samples: &[(f64, f64, f64)], quadratic: bool) -> Option<[f64; 3]> {
    let (mut a, mut b) = normal_equations(
        samples
            .iter()
            .map(|&(w, x, y)| (w, [1.0, x, if quadratic { x * x } else { 0.0 }], y)),
    );
    if !quadratic {
        // c2 is pinned to 0.
        a[2] = [0.0, 0.0, 1.0];
        b[2] = 0.0;
    }
    cholesky_solve(&a, &b).filter(|c| c.iter().all(|v| v.is_finite()))
}

/// The circle through weighted points (z, w) by the algebraic fit z² + w² + D z + E w + F = 0:
/// its centre and radius.
fn circle_fit(samples: &[(f64, f64, f64)]) -> Option<(DVec2, f64)> {
    let (a, b) = normal_equations(
        samples
            .iter()
            .map(|&(weight, z, w)| (weight, [z, w, 1.0], -(z * z + w * w))),
    );
    let [d, e, f] = cholesky_solve(&a, &b)?;
    let centre = DVec2::new(-0.5 * d, -0.5 * e);
    let r2 = centre.length_squared() - f;
    (r2 > 0.0 && r2.is_finite()).then(|| (centre, r2.sqrt()))
}

/// The slices of `local` (points in the hypothesis's frame) across z from `lo` to `hi`.
fn slices(local: &[DVec3], lo: f64, hi: f64) -> Vec<Slice> {
    let width = (hi - lo) / SEED_SLICES as f64;
    let mut cuts = vec![Slice::default(); SEED_SLICES];
    for (i, p) in local.iter().enumerate() {
        let k = ((p.z - lo) / width).floor();
        if !(0.0..SEED_SLICES as f64).contains(&k) {
            continue;
        }
        let cut = &mut cuts[k as usize];
        cut.n += 1.0;
        cut.z += p.z;
        cut.centre += DVec2::new(p.x, p.y);
        cut.members.push(i as u32);
    }
    cuts.into_iter()
        .filter(|c| c.n >= MIN_SLICE_POINTS as f64)
        .map(|c| Slice {
            z: c.z / c.n,
            centre: c.centre / c.n,
            ..c
        })
        .collect()
}

/// The `q` quantile of `values`, sorted in place ([`super::init`]'s quantile).
fn quantile(values: &mut [f64], q: f64) -> f64 {
    values.sort_by(f64::total_cmp);
    super::init::quantile(values, q)
}

/// A start for a fit that frees tapering (`taper`) and/or bending (`bend`): the hypothesis `pose`
/// moved to the middle of the `points`' centreline, its semi-axes set to the centreline's length
/// and the slices' spread, with the tapering and bending they show (within
/// [`GlobalDeformation::clamped`]'s bounds). `None` when the points give too few slices to read a
/// centreline from, or when neither is free.
pub fn seed_deformation(
    points: &[DVec3],
    pose: &InitialPose,
    taper: bool,
    bend: bool,
) -> Option<(InitialPose, GlobalDeformation)> {
    if !(taper || bend) || points.len() < MIN_SLICE_POINTS * 4 {
        return None;
    }
    let frame = DMat3::from_quat(pose.rotation);
    let to_local = frame.transpose();
    let local: Vec<DVec3> = points
        .iter()
        .map(|p| to_local * (*p - pose.translation))
        .collect();
    let mut z: Vec<f64> = local.iter().map(|p| p.z).collect();
    z.sort_by(f64::total_cmp);
    let (lo, hi) = (
        super::init::quantile(&z, 0.01),
        super::init::quantile(&z, 0.99),
    );
    let half_chord = 0.5 * (hi - lo);
    if !(half_chord > 0.0 && half_chord.is_finite()) {
        return None;
    }
    let mid = 0.5 * (lo + hi);
    let cuts = slices(&local, lo, hi);
    if cuts.len() < 4 {
        return None;
    }
    // The centreline: a parabola in each of x and y about the chord's middle.
    let fit_axis = |k: usize| {
        let samples: Vec<_> = cuts.iter().map(|s| (s.n, s.z - mid, s.centre[k])).collect();
        polyfit(&samples, true)
    };
    let (cx, cy) = (fit_axis(0)?, fit_axis(1)?);
    let curvature = DVec2::new(2.0 * cx[2], 2.0 * cy[2]);
    // The bending plane's in-plane direction (towards the centre of curvature), the arc's radius
    // and half-angle, and the z of its middle (where its tangent is along z).
    let (toward, arc, z_mid) = match curvature.try_normalize() {
        Some(u) if bend => {
            let samples: Vec<_> = cuts
                .iter()
                .map(|s| (s.n, s.z - mid, s.centre.dot(u)))
                .collect();
            // The circle's centre must lie on the concave side. A nearly straight centreline
            // (the parabola turning its ends by less than [`CIRCLE_FROM`]) keeps the parabola's
            // curvature and the chord's middle: a circle through nearly collinear points fits
            // their noise.
            let (radius, z_mid) = match circle_fit(&samples) {
                Some((centre, r))
                    if curvature.length() * half_chord >= CIRCLE_FROM && centre.y > 0.0 =>
                {
                    (r, centre.x.clamp(-0.5 * half_chord, 0.5 * half_chord))
                }
                _ => (1.0 / curvature.length(), 0.0),
            };
            let phi = (half_chord / radius).min(1.0).asin();
            (u, Some((radius, phi)), z_mid)
        }
        _ => (DVec2::X, None, 0.0),
    };
    let at = |c: [f64; 3]| c[0] + c[1] * z_mid + c[2] * z_mid * z_mid;
    let middle = DVec3::new(at(cx), at(cy), mid + z_mid);
    let (half_length, angle) = match arc {
        Some((radius, phi)) if phi > 1e-6 => (radius * phi, phi),
        _ => (half_chord, 0.0),
    };
    // The sections' spread along x and y; a slice cut obliquely through a bent tube is widened
    // along the bend by 1 / cos of the axis's tilt there, which is taken out first.
    let perpendicular = DVec2::new(-toward.y, toward.x);
    let spreads: Vec<(f64, f64, [f64; 2])> = cuts
        .iter()
        .map(|s| {
            let tilt = match arc {
                Some((radius, _)) => ((s.z - mid - z_mid) / radius).clamp(-1.0, 1.0).asin(),
                None => 0.0,
            };
            let mut offsets: [Vec<f64>; 2] = [Vec::new(), Vec::new()];
            for &i in &s.members {
                let p = local[i as usize];
                let o = DVec2::new(p.x, p.y) - s.centre;
                let o = o.dot(toward) * tilt.cos() * toward + o.dot(perpendicular) * perpendicular;
                offsets[0].push(o.x.abs());
                offsets[1].push(o.y.abs());
            }
            let r = offsets.map(|mut v| quantile(&mut v, SPREAD_QUANTILE));
            (s.n, s.z - mid - z_mid, r)
        })
        .collect();
    let mut section = [0.0; 2];
    let mut tapers = [0.0; 2];
    for k in 0..2 {
        let samples: Vec<_> = spreads.iter().map(|&(n, z, r)| (n, z, r[k])).collect();
        let line = polyfit(&samples, false)?;
        let r0 = line[0].max(1e-3 * half_length);
        section[k] = r0;
        tapers[k] = if taper {
            line[1] * half_length / r0
        } else {
            0.0
        };
    }
    let semi = DVec3::new(section[0], section[1], half_length);
    let a = semi.max_element();
    if !(a > 0.0 && a.is_finite()) {
        return None;
    }
    let shape = super::superquadric::SuperquadricParams {
        a,
        a1: semi.x / a,
        a2: semi.y / a,
        a3: semi.z / a,
        ..pose.shape
    }
    .normalized();
    let deformation = GlobalDeformation {
        taper: tapers,
        bend: (toward * angle).to_array(),
    }
    .clamped(shape.semi_axes());
    let seeded = InitialPose {
        translation: pose.translation + frame * middle,
        rotation: pose.rotation,
        shape,
    };
    (seeded.translation.is_finite() && deformation.is_finite()).then_some((seeded, deformation))
}

/// A deformed fit counts as seeing its object whole when at least this fraction of its middle
/// nodes ([`MIDDLE_LATITUDE`]) has a data point within reach ([`seen_whole`]).
pub const SEEN_WHOLE: f64 = 0.85;

/// The reach of [`seen_whole`]: this fraction of the model's smallest semi-axis, plus twice the
/// points' typical spacing (the median distance from a point to its nearest neighbour), so that a
/// sparse cloud still covers the nodes between its points. On a tube seen from one side, the nodes
/// more than some 30° past the silhouette are out of reach of every point, so only some 70 % of
/// the middle nodes count (38–68 % on the one-view clouds of `cargo bench --bench deformed`).
pub const SURROUND_REACH: f64 = 0.2;

/// The latitude |u| below which [`seen_whole`] looks at the nodes: the middle of the model, whose
/// sides data that surrounds the object covers however far a model's ends have run past it.
pub const MIDDLE_LATITUDE: f64 = std::f64::consts::FRAC_PI_6;

/// Points whose nearest neighbour [`seen_whole`] measures for the spacing.
const SPACING_SAMPLE: usize = 256;

/// Whether `points` surround the model whose nodes (of `tess`) are at `node_x` and whose smallest
/// semi-axis is `smallest`: at least [`SEEN_WHOLE`] of the nodes within [`MIDDLE_LATITUDE`] of
/// the equator have a point within reach ([`SURROUND_REACH`]). A one-view scan does not: its
/// unseen side has no data near it.
pub fn seen_whole(tess: &Tessellation, node_x: &[DVec3], points: &[DVec3], smallest: f64) -> bool {
    use kiddo::SquaredEuclidean;
    if node_x.is_empty() || points.len() < 2 {
        return false;
    }
    let Some(tree) = crate::model::nearest::kd_tree(points) else {
        return false;
    };
    let stride = (points.len() / SPACING_SAMPLE).max(1);
    let mut gaps: Vec<f64> = points
        .iter()
        .step_by(stride)
        .filter_map(|p| {
            let two = tree
                .query(&p.to_array())
                .nearest_n::<SquaredEuclidean<f64>>(std::num::NonZero::new(2)?)
                .execute();
            two.get(1).map(|n| n.distance.sqrt())
        })
        .collect();
    if gaps.is_empty() {
        return false;
    }
    let spacing = quantile(&mut gaps, 0.5);
    let reach = SURROUND_REACH * smallest + 2.0 * spacing;
    let middle: Vec<DVec3> = tess
        .uv
        .iter()
        .zip(node_x)
        .filter(|(uv, _)| uv[0].abs() < MIDDLE_LATITUDE)
        .map(|(_, x)| *x)
        .collect();
    let seen = middle
        .iter()
        .filter(|x| {
            let nearest = tree
                .query(&x.to_array())
                .nearest_one::<SquaredEuclidean<f64>>()
                .execute();
            nearest.distance <= reach * reach
        })
        .count();
    !middle.is_empty() && seen as f64 >= SEEN_WHOLE * middle.len() as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::Banana;
    use glam::DQuat;

    /// A banana turned and moved, with a hypothesis whose z axis is along its chord.
    fn banana_case(banana: &Banana) -> (Vec<DVec3>, InitialPose) {
        let turn = DQuat::from_axis_angle(DVec3::new(0.2, -1.0, 0.4).normalize(), 1.1);
        let offset = DVec3::new(1.0, 2.0, -0.5);
        let points: Vec<DVec3> = banana
            .points(3000, 0.002, 3)
            .into_iter()
            .map(|p| turn * p + offset)
            .collect();
        let pose = crate::model::init::initial_pose(&points);
        (points, pose)
    }

    #[test]
    fn a_bananas_bend_and_taper_are_read_off_its_centreline() {
        for (half_angle, taper) in [(0.3, 0.0), (0.6, 0.4), (1.0, 0.2)] {
            let banana = Banana {
                arc_radius: 1.8 / half_angle,
                half_angle,
                radius: 0.35,
                taper,
            };
            let (points, pose) = banana_case(&banana);
            let (seeded, d) = seed_deformation(&points, &pose, true, true).expect("a seed");
            let bend = d.bend[0].hypot(d.bend[1]);
            assert!(
                (bend - half_angle).abs() < 0.2 * half_angle,
                "φ {half_angle}: bend {d:?}"
            );
            // A start, not a fit: the taper within 0.2.
            for t in d.taper {
                assert!((t.abs() - taper).abs() < 0.2, "taper {taper}: {d:?}");
            }
            let axes = seeded.shape.semi_axes();
            assert!((axes.z - 1.8).abs() < 0.36, "φ {half_angle}: axes {axes}");
            for r in [axes.x, axes.y] {
                assert!((r - 0.35).abs() < 0.08, "φ {half_angle}: axes {axes}");
            }
        }
    }

    #[test]
    fn a_straight_cylinder_gets_no_bend_and_nothing_is_seeded_when_nothing_is_free() {
        let (points, pose) = banana_case(&Banana {
            arc_radius: 1e4,
            half_angle: 1.5e-4,
            radius: 0.4,
            taper: 0.0,
        });
        let (_, d) = seed_deformation(&points, &pose, true, true).expect("a seed");
        assert!(d.bend[0].hypot(d.bend[1]) < 0.05, "{d:?}");
        assert!(d.taper.iter().all(|t| t.abs() < 0.05), "{d:?}");
        assert!(seed_deformation(&points, &pose, false, false).is_none());
        assert!(seed_deformation(&points[..10], &pose, true, true).is_none());
    }

    #[test]
    fn a_tube_is_seen_whole_from_all_round_and_not_from_one_side() {
        let banana = Banana::default();
        let all: Vec<(DVec3, DVec3)> = banana.oriented_points(3000, 0.002, 5);
        let view = DVec3::new(0.0, 1.0, 0.2).normalize();
        let whole: Vec<DVec3> = all.iter().map(|(p, _)| *p).collect();
        let one_view: Vec<DVec3> = all
            .iter()
            .filter(|(_, n)| n.dot(view) > 0.0)
            .map(|(p, _)| *p)
            .collect();
        let tess = Tessellation::new(21);
        for (points, expected) in [(&whole, true), (&one_view, false)] {
            let pose = crate::model::init::initial_pose(points);
            let (start, d) = seed_deformation(points, &pose, true, true).expect("a seed");
            let mut state = crate::model::dynamics::ModelState::new(
                &tess,
                start.translation,
                start.rotation,
                start.shape,
            );
            state.deformation = d;
            let mut x = Vec::new();
            state.node_positions(&tess, &mut x);
            let smallest = start.shape.semi_axes().min_element();
            assert_eq!(seen_whole(&tess, &x, points, smallest), expected);
        }
    }
}
