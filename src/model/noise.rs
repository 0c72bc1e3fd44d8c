//! The noise in a range cloud, estimated from the points alone, and the membrane stiffness it
//! calls for (beyond the paper, which fits clean synthetic data with hand-picked w0 and w1).
//!
//! **Estimate.** Around each of up to [`NOISE_SAMPLES`] points (evenly spread through the cloud)
//! its k nearest points (k = n / 100 clamped to [[`NOISE_NEIGHBOURS`], [`MAX_NEIGHBOURS`]], so that
//! a neighbourhood stays wider than the noise in dense clouds) are expressed in their principal
//! frame and fitted by a quadratic height field h = c0 + c1 a + c2 b + c3 a² + c4 ab + c5 b² (least squares). The
//! quadratic takes up the surface's curvature, so what is left is the noise along the normal: with
//! Gaussian noise of standard deviation σ per coordinate, the residual sum of squares is
//! σ² χ²(k − 6). The estimate is the median over the samples of that per-neighbourhood variance,
//! divided by the median of χ²(k − 6)/(k − 6) (Wilson–Hilferty): the median ignores
//! neighbourhoods across edges, creases and outliers. It is reported in data units and relative to
//! the cloud's RMS radius, the unit in which [`super::fit::fit`] works, so it is scale-free.
//!
//! **Stiffness.** The fit normalises the data to unit RMS radius, so w0 and w1 act on the same
//! scale whatever the data's units; only the noise relative to that scale matters. The membrane
//! must not follow the noise: [`stiffness_for_noise`] keeps the paper's w1 = 0.1 on clean data and
//! raises w1 in proportion to the relative noise above a threshold, a rule fitted to the sweep of
//! `benches/noise.rs` (docs/results.md, "Noise and the membrane's stiffness").

use super::init::{Moments, Normalization, moments};
use super::linalg::{cholesky_solve, symmetric_eigen3};
use crate::model::nearest::kd_tree;
use glam::DVec3;
use kiddo::SquaredEuclidean;
use std::num::NonZeroUsize;

/// Fewest neighbours of each sampled point in the local quadratic fit.
pub const NOISE_NEIGHBOURS: usize = 20;

/// Most neighbours of each sampled point in the local quadratic fit.
pub const MAX_NEIGHBOURS: usize = 64;

/// Largest number of points whose neighbourhoods are fitted (the estimate's cost is bounded).
pub const NOISE_SAMPLES: usize = 1000;

/// The noise of a cloud ([`estimate_noise`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoiseEstimate {
    /// Standard deviation of the noise along the surface normal, in data units.
    pub sigma: f64,
    /// `sigma` over the cloud's RMS radius about its centroid.
    pub relative: f64,
}

/// Estimates the noise of `points` (see the module docs). `None` when there are fewer than
/// [`NOISE_NEIGHBOURS`] finite points or the cloud has no extent.
pub fn estimate_noise(points: &[DVec3]) -> Option<NoiseEstimate> {
    let k = (points.len() / 100).clamp(NOISE_NEIGHBOURS, MAX_NEIGHBOURS);
    if points.len() < k || !points.iter().all(|p| p.is_finite()) {
        return None;
    }
    let norm = Normalization::of(points);
    let scale = norm.scale;
    if !(scale > 0.0) {
        return None;
    }
    // Measured in the unit frame (squared distances of a cloud at 1e300 would overflow), then
    // scaled back.
    let unit: Vec<DVec3> = points.iter().map(|p| norm.unit_point(*p)).collect();
    let points = &unit[..];
    let tree = kd_tree(points)?;
    let stride = points.len().div_ceil(NOISE_SAMPLES).max(1);
    let mut variances: Vec<f64> = points
        .iter()
        .step_by(stride)
        .filter_map(|p| {
            let near: Vec<DVec3> = tree
                .query(&p.to_array())
                .nearest_n::<SquaredEuclidean<f64>>(NonZeroUsize::new(k)?)
                .execute()
                .into_iter()
                .map(|r| points[r.item as usize])
                .collect();
            quadric_residual_variance(&near)
        })
        .collect();
    if variances.is_empty() {
        return None;
    }
    variances.sort_by(f64::total_cmp);
    let median = variances[variances.len() / 2];
    // Median of χ²(ν)/ν by Wilson–Hilferty, ν = k − 6.
    let nu = (k - 6) as f64;
    let chi_median = (1.0 - 2.0 / (9.0 * nu)).powi(3);
    let relative = (median / chi_median).sqrt();
    Some(NoiseEstimate {
        sigma: relative * scale,
        relative,
    })
}

/// Residual variance (per degree of freedom) of the least-squares quadratic height field through
/// `near` in its principal frame; `None` when the fit is singular.
fn quadric_residual_variance(near: &[DVec3]) -> Option<f64> {
    let n = near.len();
    if n <= 6 {
        return None;
    }
    let Moments {
        centroid: c,
        covariance,
    } = moments(near);
    let (spread, frame) = symmetric_eigen3(&covariance);
    // Columns ascending: the normal first, then the two tangents.
    let (normal, t1, t2) = (frame.col(0), frame.col(1), frame.col(2));
    // The neighbourhood's size along its widest tangent, to keep the normal equations well scaled.
    let size = spread.z.max(0.0).sqrt();
    if !(size > 0.0) {
        return None;
    }
    let rows: Vec<([f64; 6], f64)> = near
        .iter()
        .map(|p| {
            let d = (*p - c) / size;
            let (a, b) = (d.dot(t1), d.dot(t2));
            ([1.0, a, b, a * a, a * b, b * b], d.dot(normal))
        })
        .collect();
    let mut ata = [[0.0; 6]; 6];
    let mut atb = [0.0; 6];
    for (r, h) in &rows {
        for i in 0..6 {
            atb[i] += r[i] * h;
            for j in 0..6 {
                ata[i][j] += r[i] * r[j];
            }
        }
    }
    let coef = cholesky_solve(&ata, &atb)?;
    let ss: f64 = rows
        .iter()
        .map(|(r, h)| {
            let fit: f64 = r.iter().zip(&coef).map(|(x, c)| x * c).sum();
            (h - fit).powi(2)
        })
        .sum();
    Some(ss * size * size / (n - 6) as f64)
}

/// w1 of [`stiffness_for_noise`] at a relative noise of [`REFERENCE_NOISE`].
pub const REFERENCE_W1: f64 = 0.025;
/// The relative noise at which [`stiffness_for_noise`] gives [`REFERENCE_W1`].
pub const REFERENCE_NOISE: f64 = 0.04;
/// How fast w1 grows with the noise: w1 ∝ (σ / RMS radius)^this.
pub const NOISE_EXPONENT: f64 = 1.6;
/// The softest membrane [`stiffness_for_noise`] gives (clean data).
pub const MIN_W1: f64 = 0.003;
/// The stiffest membrane [`stiffness_for_noise`] gives.
pub const MAX_W1: f64 = 1.0;

/// Membrane stiffness (w0, w1) for a cloud whose noise along the normal is `relative` times its
/// RMS radius: w1 = [`REFERENCE_W1`] · (relative / [`REFERENCE_NOISE`])^[`NOISE_EXPONENT`], clamped
/// to [[`MIN_W1`], [`MAX_W1`]], and w0 = w1 / 100. Fitted to `benches/noise.rs`'s sweep (a ridged
/// egg, 500–8000 points, noise 0–8 % of the RMS radius), where it lands within 5 % of the best
/// swept w1's error at every noise level; a non-finite `relative` counts as clean.
pub fn stiffness_for_noise(relative: f64) -> (f64, f64) {
    let r = if relative.is_finite() {
        relative.max(0.0)
    } else {
        0.0
    };
    let w1 = (REFERENCE_W1 * (r / REFERENCE_NOISE).powf(NOISE_EXPONENT)).clamp(MIN_W1, MAX_W1);
    (w1 / 100.0, w1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::superquadric::SuperquadricParams;
    use crate::synthetic::superquadric_cloud;
    use glam::DQuat;

    #[test]
    fn recovers_the_noise_added_to_a_curved_surface_at_any_scale() {
        let shape = SuperquadricParams {
            a: 1.0,
            a1: 1.0,
            a2: 0.6,
            a3: 0.8,
            e1: 0.6,
            e2: 1.0,
        };
        for (sigma, scale) in [(0.005, 1.0), (0.02, 1.0), (0.02, 250.0)] {
            let pts: Vec<DVec3> =
                superquadric_cloud(&shape, DVec3::ZERO, DQuat::IDENTITY, 4000, sigma, 7)
                    .into_iter()
                    .map(|p| p * scale)
                    .collect();
            let e = estimate_noise(&pts).unwrap();
            let got = e.sigma / scale;
            assert!(
                (got - sigma).abs() < 0.25 * sigma,
                "σ {sigma} × {scale}: estimated {got}"
            );
            let rms = Normalization::of(&pts).scale;
            assert!((e.relative - e.sigma / rms).abs() < 1e-12);
        }
        // Clean points: the estimate is far below any of those noise levels.
        let clean = superquadric_cloud(&shape, DVec3::ZERO, DQuat::IDENTITY, 4000, 0.0, 7);
        let e = estimate_noise(&clean).unwrap();
        assert!(e.sigma < 1e-3, "{e:?}");
        assert!(estimate_noise(&clean[..5]).is_none());
    }

    #[test]
    fn stiffness_grows_with_the_noise_between_its_bounds() {
        assert_eq!(stiffness_for_noise(0.0), (MIN_W1 / 100.0, MIN_W1));
        assert_eq!(stiffness_for_noise(f64::NAN), stiffness_for_noise(0.0));
        assert_eq!(stiffness_for_noise(10.0).1, MAX_W1);
        let (w0, w1) = stiffness_for_noise(REFERENCE_NOISE);
        assert!((w1 - REFERENCE_W1).abs() < 1e-15 && (w0 - w1 / 100.0).abs() < 1e-18);
        let mut last = 0.0;
        for i in 0..200 {
            let w1 = stiffness_for_noise(i as f64 * 1e-3).1;
            assert!(w1 >= last, "w1 falls at noise {}", i as f64 * 1e-3);
            last = w1;
        }
    }

    #[test]
    fn the_chosen_stiffness_keeps_a_noisy_fit_closer_to_the_clean_surface_than_the_papers() {
        use crate::model::dynamics::DynamicsParams;
        use crate::model::fit::{FitOptions, fit, point_distances};
        use crate::synthetic::{Rng, ridged_egg};
        // The ridged egg, 1500 points with noise 2 % of the RMS radius (benches/noise.rs).
        let clean = ridged_egg(1500, 2);
        let scale = Normalization::of(&clean).scale;
        let mut rng = Rng::new(3);
        let noisy: Vec<DVec3> = clean
            .iter()
            .map(|p| *p + 0.02 * scale * DVec3::new(rng.normal(), rng.normal(), rng.normal()))
            .collect();
        let truth = ridged_egg(3000, 1);
        let error = |opts: &FitOptions| {
            let r = fit(&noisy, opts, |_| {}).unwrap();
            let mut x = Vec::new();
            r.state.node_positions(&r.tess, &mut x);
            let d = point_distances(&r.tess, &x, &truth);
            d.iter().sum::<f64>() / d.len() as f64 / scale
        };
        let paper = FitOptions {
            k: 21,
            dynamics: DynamicsParams {
                w0: 1e-3,
                w1: 0.1,
                ..FitOptions::default().dynamics
            },
            ..FitOptions::default()
        };
        let (auto, noise) = paper.with_stiffness_from_noise(&noisy);
        let noise = noise.unwrap();
        assert!((noise.relative - 0.02).abs() < 0.005, "{noise:?}");
        assert!(auto.dynamics.w1 < 0.05, "w1 {}", auto.dynamics.w1);
        let (e_paper, e_auto) = (error(&paper), error(&auto));
        assert!(
            e_auto < 0.8 * e_paper,
            "clean-surface error: chosen {e_auto:.5} vs the paper's w1 {e_paper:.5}"
        );
    }
}
