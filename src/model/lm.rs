//! The global DOFs' rest state solved for directly (beyond the paper).
//!
//! A pure superquadric fit comes to rest where the range springs' generalized force on the
//! global DOFs vanishes. The explicit dynamics of [`super::fit`] reach that state in hundreds to
//! thousands of small steps; this module reaches it in tens of Levenberg–Marquardt iterations,
//! the way EMS (Liu et al., CVPR 2022) does, then goes on where EMS stops:
//!
//! - one engine (`engine`) takes the damped Gauss–Newton steps over any residual, with outlier
//!   weights from a Gaussian–uniform [`Mixture`] refreshed between rounds (an EM alternation),
//!   and holds an unknown on its bound while a step would push it past;
//! - its problems: the plain superquadric's eleven unknowns ([`fit_em`]: the semi-axes a·a_i,
//!   the exponents ε1 and ε2, the translation, and a rotation increment about the current
//!   orientation), and the tapered and bent one's fifteen ([`fit_deformed`]); their Jacobians are
//!   analytic, tested against central differences;
//! - the distance is the radial one, its projection on the normal, or the exact distance to the
//!   closest surface point ([`Metric`]); the last keeps each point's foot between evaluations,
//!   so that its search starts where it ended ([`super::distance::closest_point_from`]);
//! - the coverage term ([`Coverage`]) can be added, to place a model over the whole cloud;
//! - the search that runs it from many starts lives with the fit that calls it
//!   ([`crate::model::fit::solve`]).
//!
//! [`super::fit::fit`] uses it by default ([`super::fit::Solver::Solved`]); the paper's
//! dynamics stay available as [`super::fit::Solver::Dynamics`], and the plugin's per-frame
//! simulation is the dynamics.

pub use super::distance::{Distance, Metric, NUM_UNKNOWNS, radial, radial_distance};

mod coverage;
mod deformed;
mod engine;
mod mixture;
mod plain;
pub use coverage::{COVERAGE_K, Coverage};
pub use deformed::{
    DeformedFit, DeformedPose, NUM_DEFORMED, SEED_RAYS, deformed_distances, fit_deformed,
};
pub use engine::LmOptions;
pub(crate) use engine::{Normal, Problem, normal_equations, solve_em};
pub use mixture::Mixture;
pub(crate) use plain::Plain;
pub use plain::{LmFit, apply_increment, bounded_increment, fit_em, fit_em_with, weighted_cost};
#[cfg(test)]
pub(crate) mod tests;
