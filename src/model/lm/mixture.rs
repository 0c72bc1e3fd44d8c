//! The outlier model of a fit (EMS's, Liu et al. 2022): inliers lie a Gaussian distance from
//! the surface, outliers anywhere in the data's bounding box. It weighs the points of every
//! Levenberg–Marquardt round ([`Mixture::inlier`]) and ranks competing fits by how well they
//! explain the points ([`Mixture::score`]).

/// The Gaussian–uniform mixture that weighs the points: inliers lie a Gaussian distance from the
/// surface, outliers anywhere in the data's bounding box with prior probability `outlier_ratio`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Mixture {
    /// Prior fraction of outliers w_o in [0, 1); 0 weighs every point 1.
    pub outlier_ratio: f64,
    /// The outliers' uniform density 1/V, V the volume of the data's bounding box.
    pub outlier_density: f64,
    /// Least σ² of the inliers' distance per coordinate.
    pub sigma2_floor: f64,
}

impl Mixture {
    /// The posterior inlier probability of a point `distance` from the surface when the inliers'
    /// variance per coordinate is `sigma2`.
    pub fn inlier(&self, distance: f64, sigma2: f64) -> f64 {
        if self.outlier_ratio <= 0.0 {
            return 1.0;
        }
        let gauss = (2.0 * std::f64::consts::PI * sigma2).powf(-1.5);
        let c = self.outlier_ratio * self.outlier_density / (gauss * (1.0 - self.outlier_ratio));
        let e = (-0.5 * distance * distance / sigma2).exp();
        let p = e / (c + e);
        if p.is_finite() { p } else { 0.0 }
    }

    /// How well points at signed `distances` from a surface fit it under this mixture: the
    /// negative log-likelihood per point, at the inliers' variance σ² that maximises it (EM on σ²
    /// alone, from every point an inlier). Less is better; comparable between surfaces, where a
    /// plain mean distance would let a surface that passes through the outliers win.
    pub fn score(&self, distances: &[f64]) -> f64 {
        let n = distances.len().max(1) as f64;
        let spread = distances.iter().map(|d| d * d).sum::<f64>() / (3.0 * n);
        let sigma2 = self.fitted_sigma2(distances, spread);
        let (w, density) = (self.outlier_ratio, self.outlier_density);
        let norm = (2.0 * std::f64::consts::PI * sigma2).powf(-1.5);
        let nll: f64 = distances
            .iter()
            .map(|&d| {
                let gauss = (1.0 - w) * norm * (-0.5 * d * d / sigma2).exp();
                -(gauss + w * density).max(f64::MIN_POSITIVE).ln()
            })
            .sum();
        nll / n
    }
}

impl Mixture {
    /// The inliers' variance σ² per coordinate that maximises the likelihood of points at signed
    /// `distances` from a surface held where it is: EM on σ² alone from `from` (at least the
    /// floor), to the nearest fixed point. From the points' whole spread (every point an
    /// inlier) it is the widest explanation the surface has; `from` itself without an outlier
    /// model.
    pub fn fitted_sigma2(&self, distances: &[f64], from: f64) -> f64 {
        let floor = self.sigma2_floor.max(f64::MIN_POSITIVE);
        let mut sigma2 = from.max(floor);
        if self.outlier_ratio <= 0.0 {
            return sigma2;
        }
        for _ in 0..SCORE_EM_ROUNDS {
            let (mut wd, mut w) = (0.0, 0.0);
            for &d in distances {
                let p = self.inlier(d, sigma2);
                wd += p * d * d;
                w += p;
            }
            let next = if w > 0.0 {
                (wd / (3.0 * w)).max(floor)
            } else {
                floor
            };
            let done = (next - sigma2).abs() <= 1e-6 * sigma2;
            sigma2 = next;
            if done {
                break;
            }
        }
        sigma2
    }
}

/// Most EM rounds [`Mixture::score`] takes to find its σ².
const SCORE_EM_ROUNDS: u32 = 50;
