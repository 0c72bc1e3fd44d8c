//! Scene files: parts, their data and their settings in one human-editable RON file.
//!
//! A scene ([`SceneDef`]) names its data sources (point files, generated clouds, images) and lists
//! its parts, each with its initial placement, tessellation, stiffness, damping, time step,
//! reattachment interval, the forces that act on it and how it is fitted. Paths are relative to the
//! scene file. This module is pure: parsing and checking ([`SceneDef::parse`]), loading the data
//! ([`SceneData::resolve`]), running every part to rest ([`run_part`]) and writing the scene back
//! with the parts' current state ([`SceneDef::set_state`], [`SceneDef::to_ron`]). The plugin loads
//! scenes as Bevy assets (`plugin::scene`, feature `bevy`) and `dsq fit --scene` runs them headless.
//!
//! Every error ([`SceneError`]) names the file and the line and column (syntax, unknown fields,
//! wrong types) or the field (`parts[1].w0`, out-of-range values, missing data).
//!
//! ```ron
//! #![enable(implicit_some)]
//! (
//!     data: {
//!         "scan": Points(path: "../data/bunny_scan.obj", placement: (scale: 0.1)),
//!     },
//!     parts: [
//!         (
//!             name: "bunny",
//!             placement: Pose(
//!                 translation: (0.0, 0.5, 0.0),
//!                 rotation: Quat(0.0, 0.0, 0.0, 1.0),
//!                 shape: (a: 0.5, a1: 1.0, a2: 1.0, a3: 1.0, e1: 1.0, e2: 1.0),
//!             ),
//!             forces: Range(data: "scan"),
//!         ),
//!     ],
//! )
//! ```

use crate::io::{decode_image, decode_points};
use crate::model::deform::{GlobalDeformation, MAX_BEND, MAX_BEND_WIDTH, MAX_TAPER};
use crate::model::dynamics::{DynamicsParams, FreeDofs, ModelState, StepError};
use crate::model::fem::{MIN_K, Tessellation};
use crate::model::fit::{FitError, FitOptions, FitReport, Initialization, Solver, fit};
use crate::model::forces::image::{
    DEFAULT_BAND, DEFAULT_IMAGE_BETA, DEFAULT_SIGMA, ImageForces, ImageFrame, ImagePotential,
};
use crate::model::forces::range::{DEFAULT_COVERAGE, InfluenceMode};
use crate::model::image_fit::{ImageFitOptions, ImagePartFit, PartAxes, fit_part};
use crate::model::inertia::InertiaParams;
use crate::model::init::{InitialPose, initial_pose};
use crate::model::joint::JointEnd;
use crate::model::noise::{NOISE_NEIGHBOURS, NoiseEstimate, estimate_noise, stiffness_for_noise};
use crate::model::parts::{PARTITION_ROUNDS, partition};
use crate::model::superquadric::{LEAST_EPSILON, MAX_EPSILON, SuperquadricParams};
use glam::{DQuat, DVec2, DVec3};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::fmt;
use std::path::{Component, Path, PathBuf};
use std::sync::Arc;

mod format;
mod load;
mod part;
mod validate;
mod whole;
pub use format::*;
pub use load::*;
#[cfg(feature = "bevy")]
pub(crate) use validate::relative_path;

/// The file extension of scene files (`egg.dsq.ron`), registered with the asset loader.
pub const SCENE_EXTENSION: &str = "dsq.ron";

/// Largest tessellation a scene may ask for: the fitter's ([`crate::model::fem::MAX_K`]).
pub use crate::model::fem::MAX_K;

/// A scene that could not be read, checked, loaded or written.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneError {
    /// The scene file.
    pub file: PathBuf,
    /// Line and column (1-based), where the parser knows them.
    pub position: Option<(usize, usize)>,
    /// The field, as a path from the top (`parts[1].w0`, `data.scan.path`).
    pub field: Option<String>,
    /// What is wrong.
    pub message: String,
}

impl SceneError {
    fn at_field(file: &Path, field: impl Into<String>, message: impl Into<String>) -> Self {
        Self {
            file: file.to_path_buf(),
            position: None,
            field: Some(field.into()),
            message: message.into(),
        }
    }
}

impl fmt::Display for SceneError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file.display())?;
        if let Some((line, col)) = self.position {
            write!(f, ":{line}:{col}")?;
        }
        if let Some(field) = &self.field {
            write!(f, ": {field}")?;
        }
        write!(f, ": {}", self.message)
    }
}

impl std::error::Error for SceneError {}

/// Checks a number, naming the field: finite and at least (or above) a bound.
fn check(file: &Path, field: &str, v: f64, min: f64, strict: bool) -> Result<(), SceneError> {
    let ok = v.is_finite() && if strict { v > min } else { v >= min };
    if ok {
        Ok(())
    } else {
        let rel = if strict { ">" } else { "≥" };
        Err(SceneError::at_field(
            file,
            field,
            format!("must be a finite number {rel} {min}, found {v}"),
        ))
    }
}

fn check_finite(file: &Path, field: &str, v: &[f64]) -> Result<(), SceneError> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(SceneError::at_field(
            file,
            field,
            format!("must be finite, found {v:?}"),
        ))
    }
}
