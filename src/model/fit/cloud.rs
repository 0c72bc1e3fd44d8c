//! A fit to a user's point cloud as `dsq fit POINTS`, the Python package and the plugin's
//! [`FitDriver::for_model`](crate::plugin::FitDriver) take it: the options a user gives
//! ([`CloudOptions`]), resolved once into the fitter's settings ([`CloudOptions::resolve`]).
//! Every front end goes through here, so that one cloud fits the same from each.

use super::options::{FitError, FitOptions, NoiseStiffness, Solver, validate_options};
use crate::model::fem::check_k;
use crate::model::forces::range::InfluenceMode;

/// The membrane's stiffness w1 as a user gives it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Stiffness {
    /// From the noise the points show (w0 with it; [`FitOptions::with_stiffness_from_noise`]).
    FromNoise,
    /// As given.
    Value(f64),
}

/// What a user can set for a fit to a point cloud; `None` and `false` leave the default for a
/// cloud: the solved fit, outlier-robust weights (0.2), point-to-plane springs, the membrane's
/// stiffness from the noise and a tessellation from the data ([`FitOptions::for_data`]), with
/// `robust`'s switches when `global_only`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CloudOptions {
    /// A pure superquadric: the local DOFs stay frozen.
    pub global_only: bool,
    /// How the fit comes to rest (solved unless given).
    pub solver: Option<Solver>,
    /// Start from the paper's forces and stiffness instead of the defaults for a cloud.
    pub paper_forces: bool,
    /// [`FitOptions::robust`].
    pub robust: bool,
    /// Point-to-plane springs in the global stage.
    pub plane: bool,
    /// Try the cross-section dual.
    pub switch: bool,
    /// Try the similarity candidates.
    pub similar: bool,
    /// Points of influence migrate over the surface (the paper's Fig. 3).
    pub migrate: bool,
    /// Free the global tapering.
    pub taper: bool,
    /// Free the global bending.
    pub bend: bool,
    /// The prior outlier fraction in [0, 1).
    pub outliers: Option<f64>,
    /// Tessellation: k latitude rings × k longitudes + 2 poles; given, every stage keeps it.
    pub k: Option<usize>,
    /// Membrane stiffness w0 ≥ 0.
    pub w0: Option<f64>,
    /// Membrane stiffness w1.
    pub w1: Option<Stiffness>,
    /// Data-spring strength β > 0.
    pub beta: Option<f64>,
    /// Step cap (at least 1).
    pub max_steps: Option<u32>,
    /// Reattach the points every N steps (at least 1).
    pub reassign: Option<u32>,
    /// The membrane's update as one backward-Euler step with this local damping γ_d > 0.
    pub implicit_local: Option<f64>,
}

impl CloudOptions {
    /// Checks what a user gave, by the names of `dsq fit`'s flags and the Python keywords: an
    /// error of one line with the name, the value and its range. `k` lies in
    /// [[`MIN_K`](crate::model::fem::MIN_K), [`MAX_K`](crate::model::fem::MAX_K)] (what the
    /// memory allows), `max_steps` and `reassign` are at least 1, `outliers`
    /// in [0, 1), `w0` and `w1` at least 0, `beta` and `implicit_local` above 0, all finite.
    fn check(&self) -> Result<(), FitError> {
        if let Some(k) = self.k {
            check_k("k", k).map_err(FitError::BadOption)?;
        }
        for (name, n) in [("max_steps", self.max_steps), ("reassign", self.reassign)] {
            if n == Some(0) {
                return Err(FitError::BadOption(format!(
                    "{name} = 0 is out of range: it must be at least 1"
                )));
            }
        }
        let w1 = match self.w1 {
            Some(Stiffness::Value(w)) => Some(w),
            _ => None,
        };
        for (name, value, range, ok) in [
            (
                "outliers",
                self.outliers,
                "[0, 1)",
                (|x| (0.0..1.0).contains(&x)) as fn(f64) -> bool,
            ),
            ("w0", self.w0, "[0, ∞)", |x| x >= 0.0),
            ("w1", w1, "[0, ∞)", |x| x >= 0.0),
            ("beta", self.beta, "(0, ∞)", |x| x > 0.0),
            ("implicit_local", self.implicit_local, "(0, ∞)", |x| {
                x > 0.0
            }),
        ] {
            if let Some(x) = value
                && !(x.is_finite() && ok(x))
            {
                return Err(FitError::BadOption(format!(
                    "{name} = {x:?} is out of range {range}"
                )));
            }
        }
        Ok(())
    }
}

/// The tessellation parameter k of a node count k² + 2 (k ≥ 3); an error names the nearest.
pub fn k_for_nodes(n: usize) -> Result<usize, String> {
    let k = (n.saturating_sub(2) as f64).sqrt().round() as usize;
    if k < 3 || k * k + 2 != n {
        return Err(format!(
            "--nodes {n}: a node count is k² + 2 with k ≥ 3 (e.g. 963, 1683, 2603, 5043); nearest is {}",
            k.max(3) * k.max(3) + 2
        ));
    }
    Ok(k)
}

impl CloudOptions {
    /// These options over `base` (the defaults, or a paper experiment's settings). For a user's
    /// cloud (`users_cloud`) and without `paper_forces`, the defaults for a cloud come on top
    /// ([`FitOptions::for_data`]), less what was given. An error names an option out of range.
    pub fn resolve(&self, base: FitOptions, users_cloud: bool) -> Result<FitOptions, FitError> {
        self.check()?;
        let mut o = base;
        if self.robust {
            o = o.robust();
        }
        if let Some(k) = self.k {
            o.k = k;
        }
        if let Some(w0) = self.w0 {
            o.dynamics.w0 = w0;
        }
        let asked = self.w1 == Some(Stiffness::FromNoise);
        if let Some(Stiffness::Value(w1)) = self.w1 {
            o.dynamics.w1 = w1;
        }
        let stiffness_given = self.w0.is_some() || matches!(self.w1, Some(Stiffness::Value(_)));
        if let Some(beta) = self.beta {
            o.beta = beta;
        }
        if let Some(max_steps) = self.max_steps {
            o.max_steps = max_steps;
        }
        if let Some(n) = self.reassign {
            o.reassign_every = n;
        }
        o.global_only |= self.global_only;
        o.dynamics.free.taper |= self.taper;
        o.dynamics.free.bend |= self.bend;
        o.point_to_plane |= self.plane;
        o.switch_cross_section |= self.switch;
        o.similarity_switch |= self.similar;
        if let Some(f) = self.outliers {
            o.outlier_ratio = f;
        }
        if self.migrate {
            o.influence = InfluenceMode::Migrating { rate: 0.5 };
        }
        if let Some(gamma) = self.implicit_local {
            o.dynamics.implicit_local = true;
            o.dynamics.gamma_local = gamma;
        }
        let mut from_noise = asked;
        if users_cloud && !self.paper_forces {
            // The defaults for a user's cloud (docs/cli.md): outlier-robust weights,
            // point-to-plane springs in the global stage and the membrane's stiffness from the
            // noise.
            let given = o;
            o = o.for_data();
            if self.outliers.is_some() {
                o.outlier_ratio = given.outlier_ratio;
            }
            // A tessellation given is kept for every stage.
            o.k_from_data &= self.k.is_none();
            // (w0 and w1 act on the local DOFs only.)
            from_noise |= !stiffness_given && !o.global_only;
        }
        if let Some(solver) = self.solver {
            o.solver = solver;
        }
        o.noise_stiffness = if asked {
            NoiseStiffness::Required
        } else if from_noise {
            NoiseStiffness::WhenMeasurable
        } else {
            NoiseStiffness::Off
        };
        validate_options(&o)?;
        Ok(o)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_users_cloud_gets_the_data_defaults_less_what_was_given() {
        let o = CloudOptions {
            outliers: Some(0.05),
            k: Some(41),
            ..CloudOptions::default()
        }
        .resolve(FitOptions::default(), true)
        .unwrap();
        assert_eq!(o.outlier_ratio, 0.05);
        assert_eq!(o.k, 41);
        assert!(!o.k_from_data && o.point_to_plane);
        assert_eq!(o.noise_stiffness, NoiseStiffness::WhenMeasurable);
        assert_eq!(o.solver, Solver::Solved);
        // The paper's forces, or a stiffness given, keep the stiffness as it is.
        for c in [
            CloudOptions {
                paper_forces: true,
                ..CloudOptions::default()
            },
            CloudOptions {
                w1: Some(Stiffness::Value(0.2)),
                ..CloudOptions::default()
            },
        ] {
            let o = c.resolve(FitOptions::default(), true).unwrap();
            assert_eq!(o.noise_stiffness, NoiseStiffness::Off, "{c:?}");
        }
    }

    #[test]
    fn an_option_out_of_range_is_named() {
        for (c, name) in [
            (
                CloudOptions {
                    outliers: Some(1.5),
                    ..CloudOptions::default()
                },
                "outliers = 1.5 is out of range [0, 1)",
            ),
            (
                CloudOptions {
                    beta: Some(f64::NAN),
                    ..CloudOptions::default()
                },
                "beta",
            ),
            (
                CloudOptions {
                    k: Some(2),
                    ..CloudOptions::default()
                },
                "k = 2",
            ),
        ] {
            let e = c.resolve(FitOptions::default(), true).unwrap_err();
            assert!(e.to_string().contains(name), "{e}");
        }
        assert_eq!(k_for_nodes(963), Ok(31));
        assert!(k_for_nodes(964).unwrap_err().contains("nearest is 963"));
    }
}
