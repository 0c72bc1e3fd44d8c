//! What a user sets for an image fit (`dsq fit --image`'s flags, the Python package's keywords),
//! resolved once into [`ImageFitOptions`] and the potential's σ, so that every front end fits an
//! image the same way.

use super::options::ImageFitOptions;
use crate::model::fit::Solver;

/// A user's settings for an image fit; `None` and `false` keep the base's (the defaults, or a
/// paper experiment's).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ImageChoices {
    /// Each part's global stage only (no membrane).
    pub global_only: bool,
    /// The paper's forces on every node in the band, not the projected outline only.
    pub paper_band: bool,
    /// Let the parts move in depth too.
    pub free_depth: bool,
    /// Hold ε1 = ε2 = 1.
    pub fix_epsilon: bool,
    /// Gaussian width σ of the potential, pixels (> 0).
    pub sigma: Option<f64>,
    /// Band half-width on |x3| (> 0).
    pub band: Option<f64>,
    /// Region (balloon) force fraction (≥ 0).
    pub region: Option<f64>,
    /// Tessellation k (in [[`MIN_K`](crate::model::fem::MIN_K),
    /// [`MAX_K`](crate::model::fem::MAX_K)]).
    pub k: Option<usize>,
    /// Membrane stiffness w0 (≥ 0).
    pub w0: Option<f64>,
    /// Membrane stiffness w1 (≥ 0).
    pub w1: Option<f64>,
    /// Force strength β (> 0).
    pub beta: Option<f64>,
    /// Step cap per part (at least 1; the dynamics).
    pub max_steps: Option<usize>,
    /// How the parts come to rest: solved (the default) or the paper's dynamics.
    pub solver: Option<Solver>,
}

impl ImageChoices {
    /// These settings over `base` and its potential width `sigma`; an error names a value out of
    /// range.
    pub fn resolve(
        &self,
        base: ImageFitOptions,
        sigma: f64,
    ) -> Result<(ImageFitOptions, f64), String> {
        let mut o = base;
        let sigma = self.sigma.unwrap_or(sigma);
        o.local &= !self.global_only;
        o.outline_only &= !self.paper_band;
        o.planar &= !self.free_depth;
        o.fix_epsilon |= self.fix_epsilon;
        o.band = self.band.unwrap_or(o.band);
        o.region = self.region.unwrap_or(o.region);
        o.k = self.k.unwrap_or(o.k);
        o.dynamics.w0 = self.w0.unwrap_or(o.dynamics.w0);
        o.dynamics.w1 = self.w1.unwrap_or(o.dynamics.w1);
        o.beta = self.beta.unwrap_or(o.beta);
        o.max_steps = self.max_steps.unwrap_or(o.max_steps);
        o.solver = self.solver.unwrap_or(o.solver);
        if o.solver == Solver::Solved {
            let dynamics_only = [
                ("paper_band", self.paper_band),
                ("free_depth", self.free_depth),
                ("band", self.band.is_some()),
                ("region", self.region.is_some()),
                ("w0", self.w0.is_some()),
                ("w1", self.w1.is_some()),
                ("beta", self.beta.is_some()),
                ("max_steps", self.max_steps.is_some()),
            ];
            if let Some((name, _)) = dynamics_only.iter().find(|(_, given)| *given) {
                return Err(format!(
                    "{name} sets the paper's dynamics: it acts with solver dynamics, not with the \
                     solved fit (the default)"
                ));
            }
        }
        for (name, x, ok) in [
            ("sigma", sigma, sigma > 0.0),
            ("band", o.band, o.band > 0.0),
            ("region", o.region, o.region >= 0.0),
            ("w0", o.dynamics.w0, o.dynamics.w0 >= 0.0),
            ("w1", o.dynamics.w1, o.dynamics.w1 >= 0.0),
            ("beta", o.beta, o.beta > 0.0),
        ] {
            if !(ok && x.is_finite()) {
                return Err(format!("{name} = {x:?} is out of range"));
            }
        }
        crate::model::fem::check_k("k", o.k)?;
        if o.max_steps == 0 {
            return Err("max_steps = 0 is out of range: it must be at least 1".into());
        }
        Ok((o, sigma))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn choices_override_the_base_and_a_value_out_of_range_is_named() {
        let base = ImageFitOptions::default();
        let (o, sigma) = ImageChoices {
            global_only: true,
            fix_epsilon: true,
            region: Some(0.04),
            solver: Some(Solver::Dynamics),
            ..ImageChoices::default()
        }
        .resolve(base, 2.0)
        .unwrap();
        assert!(!o.local && o.fix_epsilon && o.planar && o.outline_only);
        assert_eq!((o.region, o.k, sigma), (0.04, base.k, 2.0));
        for (c, name) in [
            (
                ImageChoices {
                    sigma: Some(0.0),
                    ..ImageChoices::default()
                },
                "sigma",
            ),
            (
                ImageChoices {
                    band: Some(f64::NAN),
                    solver: Some(Solver::Dynamics),
                    ..ImageChoices::default()
                },
                "band = NaN",
            ),
            (
                ImageChoices {
                    region: Some(0.04),
                    ..ImageChoices::default()
                },
                "region sets the paper's dynamics",
            ),
            (
                ImageChoices {
                    k: Some(2),
                    ..ImageChoices::default()
                },
                "k = 2 is out of range",
            ),
        ] {
            let e = c.resolve(base, 2.0).unwrap_err();
            assert!(e.starts_with(name), "{e}");
        }
    }
}
