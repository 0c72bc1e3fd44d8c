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

use crate::io::{decode_luminance, decode_points};
use crate::model::deform::{GlobalDeformation, MAX_BEND, MAX_BEND_WIDTH, MAX_TAPER};
use crate::model::dynamics::{DynamicsParams, FreeDofs, ModelState, StepError};
use crate::model::fem::{MIN_K, Tessellation};
use crate::model::fit::{FitError, FitOptions, FitReport, Initialization, fit};
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

/// The file extension of scene files (`egg.dsq.ron`), registered with the asset loader.
pub const SCENE_EXTENSION: &str = "dsq.ron";

/// Largest tessellation a scene may ask for (k² + 2 = 250 002 nodes).
pub const MAX_K: usize = 500;

/// A scene: data sources by name, parts, and optionally a camera.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneDef {
    /// Data sources by name; parts refer to them from their [`Forces`].
    #[serde(default)]
    pub data: BTreeMap<String, DataSource>,
    /// The models.
    #[serde(default)]
    pub parts: Vec<PartDef>,
    /// Point-to-point joints between parts ([`crate::model::joint`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub joints: Vec<JointDef>,
    /// Where to look from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraDef>,
}

/// A joint between two parts' surfaces: `(parts: (0, 1), ends: ((u: 0.0, v: 0.0), (u: 0.0,
/// v: 3.14159)))`, with an optional stabilising constant (`stiffness`, default
/// [`crate::model::joint::Joint::DEFAULT_STIFFNESS`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JointDef {
    /// Indices of the two parts in `parts`.
    pub parts: [usize; 2],
    /// The material point (u, v) on each.
    pub ends: [JointEnd; 2],
    /// κ, the stabilising spring constant (> 0).
    #[serde(default = "default_joint_stiffness")]
    pub stiffness: f64,
}

fn default_joint_stiffness() -> f64 {
    crate::model::joint::Joint::DEFAULT_STIFFNESS
}

/// Where a scene's data come from. Paths are relative to the scene file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum DataSource {
    /// A point cloud: the vertices of an OBJ file or a PLY file, placed in the world.
    Points {
        /// The file, relative to the scene.
        path: String,
        /// File coordinates → world: x ↦ translation + rotation · (scale · x).
        #[serde(default)]
        placement: Placement,
    },
    /// A cloud made by [`crate::synthetic`]: the paper's range data, rebuilt.
    Generated(Generated),
    /// A PNG or JPEG image in the world x–y plane (y up), the source of an image potential.
    Image {
        /// The file, relative to the scene.
        path: String,
        /// Gaussian width σ in pixels (eq. 20).
        #[serde(default = "default_sigma")]
        sigma: f64,
        /// World (x, y) of the image's centre.
        #[serde(default)]
        center: [f64; 2],
        /// World length of the image's longer side.
        #[serde(default = "one")]
        extent: f64,
    },
}

/// The generated clouds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Generated {
    /// [`crate::synthetic::egg`]: the paper's egg, 499 points.
    Egg,
    /// [`crate::synthetic::mug`]: the paper's mug, 651 points.
    Mug,
    /// [`crate::synthetic::Banana::default`]: a curved, tapered tube, 2000 points with noise 0.002
    /// (seed 7), in its model frame (the arc bends towards +x, thicker towards +z).
    Banana,
}

/// A rigid placement with uniform scale.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Placement {
    /// World translation.
    pub translation: [f64; 3],
    /// Rotation.
    pub rotation: Rotation,
    /// Uniform scale, applied first.
    pub scale: f64,
}

impl Default for Placement {
    fn default() -> Self {
        Self {
            translation: [0.0; 3],
            rotation: Rotation::default(),
            scale: 1.0,
        }
    }
}

/// A rotation, as a quaternion or an axis and an angle.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum Rotation {
    /// A quaternion in glam's order (x, y, z, w); normalised on load when it is not of unit
    /// length.
    Quat(f64, f64, f64, f64),
    /// A turn of `degrees` about `axis` (any length but zero).
    AxisAngle {
        /// The axis.
        axis: [f64; 3],
        /// The angle, right-handed, in degrees.
        degrees: f64,
    },
}

impl Default for Rotation {
    fn default() -> Self {
        Rotation::Quat(0.0, 0.0, 0.0, 1.0)
    }
}

impl Rotation {
    /// The unit quaternion, or why there is none. A quaternion within 1e-12 of unit length is
    /// taken as it is (bit for bit), so saved states load back unchanged.
    pub fn to_quat(&self) -> Result<DQuat, String> {
        match *self {
            Rotation::Quat(x, y, z, w) => {
                let q = DQuat::from_xyzw(x, y, z, w);
                let n2 = q.length_squared();
                if !q.is_finite() {
                    Err("the quaternion has a NaN or infinite component".into())
                } else if !(n2 > 1e-20) {
                    Err("the quaternion is zero".into())
                } else if (n2 - 1.0).abs() > 1e-12 {
                    Ok(q.normalize())
                } else {
                    Ok(q)
                }
            }
            Rotation::AxisAngle { axis, degrees } => {
                let axis = DVec3::from_array(axis);
                if !(axis.is_finite() && degrees.is_finite()) {
                    Err("the axis or angle is NaN or infinite".into())
                } else if !(axis.length_squared() > 1e-20) {
                    Err("the axis is zero".into())
                } else {
                    Ok(DQuat::from_axis_angle(
                        axis.normalize(),
                        degrees.to_radians(),
                    ))
                }
            }
        }
    }

    /// The quaternion as written in a scene.
    pub fn from_quat(q: DQuat) -> Self {
        Rotation::Quat(q.x, q.y, q.z, q.w)
    }
}

/// One model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PartDef {
    /// A name for the part (shown by tools, given to the entity).
    #[serde(default)]
    pub name: String,
    /// Where the part starts.
    pub placement: PartPlacement,
    /// Tessellation: k rings × k longitudes + 2 poles (k ≥ 3).
    #[serde(default = "default_k")]
    pub k: usize,
    /// Membrane stiffness on |d|² (eq. 13), ≥ 0.
    #[serde(default = "default_w0")]
    pub w0: f64,
    /// Membrane stiffness on the first derivatives of d (eq. 13), ≥ 0.
    #[serde(default = "default_w1")]
    pub w1: f64,
    /// Choose `w0` and `w1` from the noise of the part's range points when the scene loads,
    /// replacing the values written: w1 grows with the noise over the cloud's size and w0 =
    /// w1 / 100 ([`crate::model::noise`]; the command-line fitter's `--w1 auto`). Needs range
    /// forces; a part sharing its source is judged on its share.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub stiffness_from_noise: bool,
    /// Damping densities.
    #[serde(default)]
    pub damping: Damping,
    /// Euler time step Δt.
    #[serde(default = "default_dt")]
    pub dt: f64,
    /// Reattach range points to their nearest nodes every this many steps (the paper: 200).
    #[serde(default = "default_reassign")]
    pub reassign_every: u32,
    /// Which degrees of freedom move.
    #[serde(default)]
    pub free: Freedoms,
    /// The forces that act on the part.
    #[serde(default)]
    pub forces: Forces,
    /// How the part is run to rest.
    #[serde(default)]
    pub fit: FitSettings,
    /// Local displacements d_i, one per node (k² + 2), in the model frame; absent: zero.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub local: Option<Vec<[f64; 3]>>,
    /// Tapering and bending of the superquadric ([`crate::model::deform`]), whatever the
    /// placement: `(taper: (t_x, t_y), bend: (b_x, b_y))`; absent: none. They move only when
    /// `free.taper` / `free.bend` say so.
    #[serde(default, skip_serializing_if = "GlobalDeformation::is_identity")]
    pub deformation: GlobalDeformation,
    /// Second-order dynamics with mass ([`crate::model::inertia`]): `inertia: (mass_density: 0.01,
    /// local_inertia: 1.0, damping: 0.5)`; absent: the paper's first-order fitting dynamics.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub inertia: Option<InertiaParams>,
}

/// Where a part starts.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum PartPlacement {
    /// An explicit pose and global shape, in world space.
    Pose {
        /// q_c.
        translation: [f64; 3],
        /// q_θ.
        #[serde(default)]
        rotation: Rotation,
        /// q_s.
        shape: SuperquadricParams,
    },
    /// An ellipsoid placed on the part's image from four pixel points, as a user does in the
    /// paper's Fig. 6(a): both ends of the major axis, then both ends of the minor axis. Needs
    /// [`Forces::Image`].
    Axes {
        /// Both ends of the major axis, in pixels.
        major: [[f64; 2]; 2],
        /// Both ends of the minor axis, in pixels.
        minor: [[f64; 2]; 2],
    },
    /// The automatic initialisation: an ellipsoid boxing the part's range points in their
    /// principal frame ([`crate::model::init::initial_pose`]); with a `shared` source, the points
    /// the part gets when the source is split among its parts. Needs [`Forces::Range`].
    Auto,
}

/// Damping densities γ_g (global) and γ_d (local).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Damping {
    /// γ_g: Δt/γ_g is the fraction of a Gauss–Newton step the global DOFs take. Unset: the
    /// range fitter's γ_g = Δt (a whole step, [`FitOptions::default`]) on range parts, the
    /// interactive half step ([`DynamicsParams::default`]) on the others.
    pub global: Option<f64>,
    /// γ_d.
    pub local: f64,
}

impl Default for Damping {
    fn default() -> Self {
        Self {
            global: None,
            local: DynamicsParams::default().gamma_local,
        }
    }
}

/// Which degrees of freedom move. Unset flags take the default of the part's forces: parts on an
/// image move in the image plane with ε fixed (as in the paper's image experiments); the others
/// move freely.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Freedoms {
    /// Freeze the local DOFs: a pure superquadric.
    pub global_only: bool,
    /// Hold ε1 and ε2.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fix_epsilon: Option<bool>,
    /// Image-plane motion only, depth ratio held.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub planar: Option<bool>,
    /// Hold the whole superquadric shape: the part moves as a rigid body (see
    /// `ModelSettings::fix_shape` of the plugin).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub fix_shape: bool,
    /// Let the tapering coordinates move ([`crate::model::deform`]; beyond the paper).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub taper: bool,
    /// Let the bending coordinates move ([`crate::model::deform`]; beyond the paper).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub bend: bool,
}

/// The forces on a part. β is per unit material area in both cases.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum Forces {
    /// No data: the part moves only under user springs.
    #[default]
    Free,
    /// Range points pulling on their points of influence (eq. 22).
    Range {
        /// The [`DataSource::Points`] or [`DataSource::Generated`] source.
        data: String,
        /// Spring strength β.
        #[serde(default = "default_range_beta")]
        beta: f64,
        /// Density of the model-to-data coverage springs that place the part, as a fraction of β
        /// (0: the paper's forces only).
        #[serde(default = "default_coverage")]
        coverage: f64,
        /// Nearest node (the paper) or migrating points of influence (Fig. 3).
        #[serde(default)]
        influence: InfluenceMode,
        /// Prior fraction of outliers in [0, 1) for outlier-robust spring weights
        /// (`forces::range::Robust`; 0: the paper's equal weights).
        #[serde(default)]
        outliers: f64,
        /// Only the source's points inside this world box pull on this part (a part of a
        /// multi-part object).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        crop: Option<Aabb>,
        /// Share the source's points with the other parts on it that set `shared`: each point
        /// pulls only on the part whose surface is nearest (the paper's doll experiment, in 3D).
        /// The split is made when the scene loads ([`SceneData::resolve`]) by alternating
        /// global-only fits of the parts and reassignment ([`crate::model::parts::partition`]);
        /// the parts sharing a source must all be placed `Auto` or all be placed explicitly.
        #[serde(default)]
        shared: bool,
    },
    /// An image potential pulling on the part's projected outline (eq. 23).
    Image {
        /// The [`DataSource::Image`] source.
        data: String,
        /// Force strength β.
        #[serde(default = "default_image_beta")]
        beta: f64,
        /// Band half-width on |x3| (the nodes near the image plane that feel the image).
        #[serde(default = "default_band")]
        band: f64,
        /// Pull only the projected outline (false: the paper's forces on every node in the band).
        #[serde(default = "yes")]
        outline_only: bool,
        /// Region (balloon) force fraction; 0: the paper's forces.
        #[serde(default)]
        region: f64,
    },
}

/// An axis-aligned box.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Aabb {
    /// Lower corner.
    pub min: [f64; 3],
    /// Upper corner.
    pub max: [f64; 3],
}

impl Aabb {
    /// True when `p` lies inside or on the box.
    pub fn contains(&self, p: DVec3) -> bool {
        p.cmpge(DVec3::from_array(self.min)).all() && p.cmple(DVec3::from_array(self.max)).all()
    }
}

/// How a part is run to rest (by the headless runner, and by the plugin's fit driver for range
/// parts).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FitSettings {
    /// Rest threshold on the largest node motion in a step (range: × the data's RMS radius;
    /// image: × the image extent); unset: 1e-5 (both).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tolerance: Option<f64>,
    /// Step cap; unset: 20 000 (range), 3 000 (image).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_steps: Option<u32>,
    /// Run the global DOFs to rest before freeing the local ones.
    pub global_first: bool,
}

impl Default for FitSettings {
    fn default() -> Self {
        Self {
            tolerance: None,
            max_steps: None,
            global_first: true,
        }
    }
}

/// A camera looking from `eye` at `target`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraDef {
    /// Camera position.
    pub eye: [f64; 3],
    /// The point looked at.
    pub target: [f64; 3],
    /// Up direction.
    #[serde(default = "y_up")]
    pub up: [f64; 3],
}

fn default_sigma() -> f64 {
    DEFAULT_SIGMA
}
fn one() -> f64 {
    1.0
}
fn yes() -> bool {
    true
}
fn y_up() -> [f64; 3] {
    [0.0, 1.0, 0.0]
}
fn default_k() -> usize {
    FitOptions::default().k
}
fn default_w0() -> f64 {
    DynamicsParams::default().w0
}
fn default_w1() -> f64 {
    DynamicsParams::default().w1
}
fn default_dt() -> f64 {
    DynamicsParams::default().dt
}
fn default_reassign() -> u32 {
    FitOptions::default().reassign_every
}
fn default_range_beta() -> f64 {
    FitOptions::default().beta
}
fn default_coverage() -> f64 {
    DEFAULT_COVERAGE
}
fn default_image_beta() -> f64 {
    DEFAULT_IMAGE_BETA
}
fn default_band() -> f64 {
    DEFAULT_BAND
}

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

impl SceneDef {
    /// Parses and checks a scene's text; `file` names it in errors.
    pub fn parse(text: &str, file: &Path) -> Result<Self, SceneError> {
        let options = ron::Options::default()
            .with_default_extension(ron::extensions::Extensions::IMPLICIT_SOME);
        let spanned = |e: ron::error::SpannedError, field: Option<String>| SceneError {
            file: file.to_path_buf(),
            position: Some((e.span.start.line, e.span.start.col)),
            field,
            message: e.code.to_string(),
        };
        let mut de = ron::Deserializer::from_str_with_options(text, &options)
            .map_err(|e| spanned(e, None))?;
        let def: SceneDef = match serde_path_to_error::deserialize(&mut de) {
            Ok(def) => def,
            Err(e) => {
                let path = e.path().to_string();
                let field = (path != ".").then_some(path);
                let code = e.into_inner();
                return Err(spanned(de.span_error(code), field));
            }
        };
        de.end()
            .map_err(|code| spanned(de.span_error(code), None))?;
        def.validate(file)?;
        Ok(def)
    }

    /// Checks every value and reference, naming the first bad field.
    pub fn validate(&self, file: &Path) -> Result<(), SceneError> {
        for (name, source) in &self.data {
            let at = |f: &str| format!("data.{name}.{f}");
            match source {
                DataSource::Points { path, placement } => {
                    if path.trim().is_empty() {
                        return Err(SceneError::at_field(file, at("path"), "is empty"));
                    }
                    check_finite(file, &at("placement.translation"), &placement.translation)?;
                    check(file, &at("placement.scale"), placement.scale, 0.0, true)?;
                    placement
                        .rotation
                        .to_quat()
                        .map_err(|m| SceneError::at_field(file, at("placement.rotation"), m))?;
                }
                DataSource::Generated(_) => {}
                DataSource::Image {
                    path,
                    sigma,
                    center,
                    extent,
                } => {
                    if path.trim().is_empty() {
                        return Err(SceneError::at_field(file, at("path"), "is empty"));
                    }
                    check(file, &at("sigma"), *sigma, 0.0, true)?;
                    check_finite(file, &at("center"), center)?;
                    check(file, &at("extent"), *extent, 0.0, true)?;
                }
            }
        }
        for (i, part) in self.parts.iter().enumerate() {
            part.validate(file, &format!("parts[{i}]"), &self.data)?;
        }
        for (i, joint) in self.joints.iter().enumerate() {
            let at = |f: &str| format!("joints[{i}].{f}");
            let [a, b] = joint.parts;
            if a == b || a >= self.parts.len() || b >= self.parts.len() {
                return Err(SceneError::at_field(
                    file,
                    at("parts"),
                    format!(
                        "must name two different parts of the {} in `parts`, found ({a}, {b})",
                        self.parts.len()
                    ),
                ));
            }
            for (k, end) in joint.ends.iter().enumerate() {
                if !(end.u.is_finite()
                    && end.v.is_finite()
                    && end.u.abs() <= std::f64::consts::FRAC_PI_2)
                {
                    return Err(SceneError::at_field(
                        file,
                        at(&format!("ends[{k}]")),
                        format!(
                            "u must lie in [-π/2, π/2] and v be finite, found ({}, {})",
                            end.u, end.v
                        ),
                    ));
                }
            }
            check(file, &at("stiffness"), joint.stiffness, 0.0, true)?;
        }
        for (source, group) in self.shared_groups() {
            let auto = |&i: &usize| matches!(self.parts[i].placement, PartPlacement::Auto);
            if group.iter().any(auto) && !group.iter().all(auto) {
                let odd = group.iter().find(|i| !auto(i)).copied().unwrap_or(group[0]);
                return Err(SceneError::at_field(
                    file,
                    format!("parts[{odd}].placement"),
                    format!(
                        "the parts sharing {source:?} ({group:?}) must all be placed Auto or all explicitly"
                    ),
                ));
            }
        }
        if let Some(c) = &self.camera {
            check_finite(file, "camera.eye", &c.eye)?;
            check_finite(file, "camera.target", &c.target)?;
            check_finite(file, "camera.up", &c.up)?;
            let (eye, target, up) = (
                DVec3::from_array(c.eye),
                DVec3::from_array(c.target),
                DVec3::from_array(c.up),
            );
            if !((target - eye).length() > 1e-12) || !((target - eye).cross(up).length() > 1e-12) {
                return Err(SceneError::at_field(
                    file,
                    "camera",
                    "eye and target must differ, and up must not lie along the view",
                ));
            }
        }
        Ok(())
    }

    /// The parts that share each source (`Range(shared: true)`), by source name, in part order.
    pub fn shared_groups(&self) -> BTreeMap<&str, Vec<usize>> {
        let mut groups: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
        for (i, part) in self.parts.iter().enumerate() {
            if let Forces::Range {
                data, shared: true, ..
            } = &part.forces
            {
                groups.entry(data.as_str()).or_default().push(i);
            }
        }
        groups
    }

    /// The scene as RON text, every field written (what [`SceneDef::parse`] reads back to the same
    /// value, bit for bit: numbers are written in their shortest round-tripping form).
    pub fn to_ron(&self) -> Result<String, ron::Error> {
        let config = ron::ser::PrettyConfig::new()
            .extensions(ron::extensions::Extensions::IMPLICIT_SOME)
            .struct_names(false);
        ron::Options::default().to_string_pretty(self, config)
    }

    /// Records `state` as part `index`'s placement (pose and global shape) and, when
    /// `include_local`, its local displacements (otherwise they are dropped).
    pub fn set_state(&mut self, index: usize, state: &ModelState, include_local: bool) {
        let Some(part) = self.parts.get_mut(index) else {
            return;
        };
        part.placement = PartPlacement::Pose {
            translation: state.translation.to_array(),
            rotation: Rotation::from_quat(state.rotation),
            shape: state.shape,
        };
        part.deformation = state.deformation;
        part.local = (include_local && !state.displacement.is_empty())
            .then(|| state.displacement.iter().map(|d| d.to_array()).collect());
    }

    /// Rewrites the relative data paths of a scene read from directory `from` so that they point
    /// at the same files from directory `to` (where the scene is about to be written).
    pub fn rebase(&mut self, from: &Path, to: &Path) {
        for source in self.data.values_mut() {
            if let DataSource::Points { path, .. } | DataSource::Image { path, .. } = source
                && Path::new(path.as_str()).is_relative()
            {
                let target = lexical_absolute(&from.join(path.as_str()));
                *path = relative_path(&target, &lexical_absolute(to))
                    .to_string_lossy()
                    .replace('\\', "/");
            }
        }
    }

    /// Sets `w0` and `w1` of every part whose stiffness comes from its data's noise
    /// ([`PartDef::stiffness_from_noise`]) from the estimate in `data` (made by
    /// [`SceneData::resolve`]). [`SceneDef::load_file`] and the asset loader do this.
    pub fn apply_noise_stiffness(&mut self, data: &SceneData) {
        for (&i, noise) in &data.noise {
            if let Some(part) = self.parts.get_mut(i)
                && part.stiffness_from_noise
            {
                (part.w0, part.w1) = stiffness_for_noise(noise.relative);
            }
        }
    }

    /// Reads and checks a scene file, loads its data from the files next to it and sets the
    /// stiffness of parts that take it from their data's noise.
    pub fn load_file(file: &Path) -> Result<(SceneDef, SceneData), SceneError> {
        let text = std::fs::read_to_string(file).map_err(|e| SceneError {
            file: file.to_path_buf(),
            position: None,
            field: None,
            message: format!("cannot read: {e}"),
        })?;
        let mut def = SceneDef::parse(&text, file)?;
        let dir = file.parent().unwrap_or(Path::new("")).to_path_buf();
        let data = SceneData::resolve(&def, file, |rel| {
            std::fs::read(dir.join(rel)).map_err(|e| format!("cannot read {rel:?}: {e}"))
        })?;
        def.apply_noise_stiffness(&data);
        Ok((def, data))
    }

    /// Writes the scene to `file` (see [`SceneDef::to_ron`]).
    pub fn save(&self, file: &Path) -> Result<(), SceneError> {
        let fail = |message: String| SceneError {
            file: file.to_path_buf(),
            position: None,
            field: None,
            message,
        };
        let text = self
            .to_ron()
            .map_err(|e| fail(format!("cannot write the scene as RON: {e}")))?;
        std::fs::write(file, text).map_err(|e| fail(format!("cannot write: {e}")))
    }

    /// The relative paths of the files the scene's data come from, by source name.
    pub fn data_files(&self) -> Vec<(&str, &str)> {
        self.data
            .iter()
            .filter_map(|(name, s)| match s {
                DataSource::Points { path, .. } | DataSource::Image { path, .. } => {
                    Some((name.as_str(), path.as_str()))
                }
                DataSource::Generated(_) => None,
            })
            .collect()
    }
}

/// `p` made absolute against the working directory, with `.` and `..` resolved lexically.
fn lexical_absolute(p: &Path) -> PathBuf {
    let joined = if p.is_absolute() {
        p.to_path_buf()
    } else {
        std::env::current_dir().unwrap_or_default().join(p)
    };
    let mut out = PathBuf::new();
    for c in joined.components() {
        match c {
            Component::ParentDir => {
                out.pop();
            }
            Component::CurDir => {}
            c => out.push(c),
        }
    }
    out
}

/// The path from directory `base` to `target` (both absolute and lexically normal).
fn relative_path(target: &Path, base: &Path) -> PathBuf {
    let t: Vec<_> = target.components().collect();
    let b: Vec<_> = base.components().collect();
    let common = t.iter().zip(&b).take_while(|(x, y)| x == y).count();
    let mut out = PathBuf::new();
    for _ in common..b.len() {
        out.push("..");
    }
    for c in &t[common..] {
        out.push(c);
    }
    out
}

impl PartDef {
    /// A part with no data and every setting at its default, a unit sphere at the origin.
    pub fn new(name: impl Into<String>) -> Self {
        Self {
            name: name.into(),
            placement: PartPlacement::Pose {
                translation: [0.0; 3],
                rotation: Rotation::default(),
                shape: SuperquadricParams::default(),
            },
            k: default_k(),
            w0: default_w0(),
            w1: default_w1(),
            stiffness_from_noise: false,
            damping: Damping::default(),
            dt: default_dt(),
            reassign_every: default_reassign(),
            free: Freedoms::default(),
            forces: Forces::Free,
            fit: FitSettings::default(),
            local: None,
            deformation: GlobalDeformation::IDENTITY,
            inertia: None,
        }
    }

    /// Tapering and bending within their bounds ([`GlobalDeformation::clamped`]); with a `Pose`
    /// placement the bend must also keep the shape's widest section on the near side of the
    /// centre of curvature.
    fn validate_deformation(
        &self,
        file: &Path,
        f: &dyn Fn(&str) -> String,
    ) -> Result<(), SceneError> {
        let d = &self.deformation;
        check_finite(file, &f("deformation.taper"), &d.taper)?;
        check_finite(file, &f("deformation.bend"), &d.bend)?;
        if d.taper.iter().any(|t| t.abs() > MAX_TAPER) {
            return Err(SceneError::at_field(
                file,
                f("deformation.taper"),
                format!(
                    "each of t_x, t_y must lie in [-{MAX_TAPER}, {MAX_TAPER}], found {:?}",
                    d.taper
                ),
            ));
        }
        let axes = match &self.placement {
            PartPlacement::Pose { shape, .. } => shape.semi_axes(),
            // The shape comes from the data: only the bend's own bound can be checked here.
            _ => DVec3::new(0.0, 0.0, f64::INFINITY),
        };
        let limit = d.clamped(axes).bend;
        if d.bend != limit {
            return Err(SceneError::at_field(
                file,
                f("deformation.bend"),
                format!(
                    "|b| = {} is beyond its bound {} (at most {MAX_BEND} rad, and at most \
                     {MAX_BEND_WIDTH} × the z semi-axis over the widest tapered section)",
                    d.bend[0].hypot(d.bend[1]),
                    limit[0].hypot(limit[1])
                ),
            ));
        }
        Ok(())
    }

    fn validate(
        &self,
        file: &Path,
        at: &str,
        data: &BTreeMap<String, DataSource>,
    ) -> Result<(), SceneError> {
        let f = |name: &str| format!("{at}.{name}");
        match &self.placement {
            PartPlacement::Pose {
                translation,
                rotation,
                shape,
            } => {
                check_finite(file, &f("placement.translation"), translation)?;
                rotation
                    .to_quat()
                    .map_err(|m| SceneError::at_field(file, f("placement.rotation"), m))?;
                check(file, &f("placement.shape.a"), shape.a, 0.0, true)?;
                for (n, v) in [("a1", shape.a1), ("a2", shape.a2), ("a3", shape.a3)] {
                    check(file, &f(&format!("placement.shape.{n}")), v, 0.0, true)?;
                }
                for (n, v) in [("e1", shape.e1), ("e2", shape.e2)] {
                    if !(LEAST_EPSILON..=MAX_EPSILON).contains(&v) {
                        return Err(SceneError::at_field(
                            file,
                            f(&format!("placement.shape.{n}")),
                            format!("must lie in [{LEAST_EPSILON}, {MAX_EPSILON}], found {v}"),
                        ));
                    }
                }
            }
            PartPlacement::Axes { major, minor } => {
                check_finite(file, &f("placement.major"), major.as_flattened())?;
                check_finite(file, &f("placement.minor"), minor.as_flattened())?;
                if !matches!(self.forces, Forces::Image { .. }) {
                    return Err(SceneError::at_field(
                        file,
                        f("placement"),
                        "Axes places a part on its image: the part needs `forces: Image(..)`",
                    ));
                }
            }
            PartPlacement::Auto => {
                if !matches!(self.forces, Forces::Range { .. }) {
                    return Err(SceneError::at_field(
                        file,
                        f("placement"),
                        "Auto places a part on its range points: the part needs `forces: Range(..)`",
                    ));
                }
            }
        }
        self.validate_deformation(file, &f)?;
        if let Some(i) = &self.inertia {
            check(file, &f("inertia.mass_density"), i.mass_density, 0.0, true)?;
            check(
                file,
                &f("inertia.local_inertia"),
                i.local_inertia,
                0.0,
                true,
            )?;
            check(file, &f("inertia.damping"), i.damping, 0.0, false)?;
        }
        if !(MIN_K..=MAX_K).contains(&self.k) {
            return Err(SceneError::at_field(
                file,
                f("k"),
                format!("must lie in [{MIN_K}, {MAX_K}], found {}", self.k),
            ));
        }
        check(file, &f("w0"), self.w0, 0.0, false)?;
        check(file, &f("w1"), self.w1, 0.0, false)?;
        if self.stiffness_from_noise && !matches!(self.forces, Forces::Range { .. }) {
            return Err(SceneError::at_field(
                file,
                f("stiffness_from_noise"),
                "the stiffness comes from the noise of the part's range points: the part needs \
                 `forces: Range(..)`",
            ));
        }
        check(file, &f("dt"), self.dt, 0.0, true)?;
        if let Some(g) = self.damping.global {
            check(file, &f("damping.global"), g, 0.0, true)?;
        }
        check(file, &f("damping.local"), self.damping.local, 0.0, true)?;
        if self.reassign_every == 0 {
            return Err(SceneError::at_field(
                file,
                f("reassign_every"),
                "must be at least 1, found 0",
            ));
        }
        let source = |name: &str| {
            data.get(name).ok_or_else(|| {
                let known: Vec<&str> = data.keys().map(String::as_str).collect();
                SceneError::at_field(
                    file,
                    f("forces.data"),
                    format!("no data source named {name:?} (the scene has {known:?})"),
                )
            })
        };
        match &self.forces {
            Forces::Free => {}
            Forces::Range {
                data: name,
                beta,
                coverage,
                influence,
                crop,
                outliers,
                shared,
            } => {
                if *shared && crop.is_some() {
                    return Err(SceneError::at_field(
                        file,
                        f("forces.crop"),
                        "a shared source is split among its parts by nearness; drop the crop or `shared`",
                    ));
                }
                if !(0.0..1.0).contains(outliers) {
                    return Err(SceneError::at_field(
                        file,
                        f("forces.outliers"),
                        format!("must lie in [0, 1), found {outliers}"),
                    ));
                }
                if matches!(source(name)?, DataSource::Image { .. }) {
                    return Err(SceneError::at_field(
                        file,
                        f("forces.data"),
                        format!("{name:?} is an image; Range forces need points"),
                    ));
                }
                check(file, &f("forces.beta"), *beta, 0.0, true)?;
                check(file, &f("forces.coverage"), *coverage, 0.0, false)?;
                if let InfluenceMode::Migrating { rate } = influence
                    && !(*rate > 0.0 && *rate <= 1.0)
                {
                    return Err(SceneError::at_field(
                        file,
                        f("forces.influence.rate"),
                        format!("must lie in (0, 1], found {rate}"),
                    ));
                }
                if let Some(b) = crop {
                    check_finite(file, &f("forces.crop"), &[b.min, b.max].concat())?;
                    if (0..3).any(|i| b.min[i] > b.max[i]) {
                        return Err(SceneError::at_field(
                            file,
                            f("forces.crop"),
                            "min must not exceed max",
                        ));
                    }
                }
            }
            Forces::Image {
                data: name,
                beta,
                band,
                region,
                ..
            } => {
                if !matches!(source(name)?, DataSource::Image { .. }) {
                    return Err(SceneError::at_field(
                        file,
                        f("forces.data"),
                        format!("{name:?} is not an image; Image forces need one"),
                    ));
                }
                check(file, &f("forces.beta"), *beta, 0.0, true)?;
                check(file, &f("forces.band"), *band, 0.0, true)?;
                check(file, &f("forces.region"), *region, 0.0, false)?;
            }
        }
        if let Some(t) = self.fit.tolerance {
            check(file, &f("fit.tolerance"), t, 0.0, true)?;
        }
        if self.fit.max_steps == Some(0) {
            return Err(SceneError::at_field(
                file,
                f("fit.max_steps"),
                "must be at least 1, found 0",
            ));
        }
        if let Some(local) = &self.local {
            let n = self.k * self.k + 2;
            if local.len() != n {
                return Err(SceneError::at_field(
                    file,
                    f("local"),
                    format!(
                        "has {} displacements; k = {} has {n} nodes",
                        local.len(),
                        self.k
                    ),
                ));
            }
            if let Some(i) = local.iter().position(|d| !d.iter().all(|x| x.is_finite())) {
                return Err(SceneError::at_field(
                    file,
                    format!("{at}.local[{i}]"),
                    "has a NaN or infinite component",
                ));
            }
        }
        Ok(())
    }

    /// True when the part is pulled by an image.
    pub fn on_image(&self) -> bool {
        matches!(self.forces, Forces::Image { .. })
    }

    /// Whether ε1, ε2 are held (set, or by default on image parts).
    pub fn fix_epsilon(&self) -> bool {
        self.free.fix_epsilon.unwrap_or(self.on_image())
    }

    /// Whether the part moves in the image plane only (set, or by default on image parts).
    pub fn planar(&self) -> bool {
        self.free.planar.unwrap_or(self.on_image())
    }

    /// The part's dynamics parameters (stiffness, Δt, damping, free DOFs).
    pub fn dynamics(&self) -> DynamicsParams {
        let f = &self.free;
        let free = FreeDofs::with(!f.global_only, self.planar(), self.fix_epsilon())
            .beyond_the_paper(f.fix_shape, f.taper, f.bend);
        DynamicsParams {
            w0: self.w0,
            w1: self.w1,
            dt: self.dt,
            gamma_global: self.damping.global.unwrap_or(match self.forces {
                Forces::Range { .. } => FitOptions::default().dynamics.gamma_global,
                _ => DynamicsParams::default().gamma_global,
            }),
            gamma_local: self.damping.local,
            free,
            ..DynamicsParams::default()
        }
    }

    /// The options of a range fit of this part from `start` (in world space).
    pub fn fit_options(&self, start: &ModelState) -> FitOptions {
        self.fit_options_from(Initialization::Explicit(InitialPose::of(start)))
    }

    /// The options of a range fit of this part, started as `init` says.
    fn fit_options_from(&self, init: Initialization) -> FitOptions {
        let defaults = FitOptions::default();
        let (beta, coverage, influence, outlier_ratio) = match &self.forces {
            Forces::Range {
                beta,
                coverage,
                influence,
                outliers,
                ..
            } => (*beta, *coverage, *influence, *outliers),
            _ => (
                defaults.beta,
                defaults.coverage,
                defaults.influence,
                defaults.outlier_ratio,
            ),
        };
        FitOptions {
            k: self.k,
            dynamics: self.dynamics(),
            beta,
            influence,
            coverage,
            outlier_ratio,
            reassign_every: self.reassign_every,
            max_steps: self.fit.max_steps.unwrap_or(defaults.max_steps),
            tolerance: self.fit.tolerance.unwrap_or(defaults.tolerance),
            global_first: self.fit.global_first,
            global_only: self.free.global_only,
            init,
            ..defaults
        }
    }

    /// The options of an image fit of this part.
    pub fn image_options(&self) -> ImageFitOptions {
        let defaults = ImageFitOptions::default();
        let (beta, band, outline_only, region) = match &self.forces {
            Forces::Image {
                beta,
                band,
                outline_only,
                region,
                ..
            } => (*beta, *band, *outline_only, *region),
            _ => (
                defaults.beta,
                defaults.band,
                defaults.outline_only,
                defaults.region,
            ),
        };
        ImageFitOptions {
            k: self.k,
            // The fit sets the free DOFs per stage from `planar` and `fix_epsilon`.
            dynamics: DynamicsParams {
                free: FreeDofs::default(),
                ..self.dynamics()
            },
            beta,
            band,
            outline_only,
            region,
            planar: self.planar(),
            fix_epsilon: self.fix_epsilon(),
            global_first: self.fit.global_first,
            tolerance: self.fit.tolerance.unwrap_or(defaults.tolerance),
            max_steps: self
                .fit
                .max_steps
                .map_or(defaults.max_steps, |m| m as usize),
        }
    }
}

/// A scene's data, loaded: point clouds (placed in the world) and image potentials, by source
/// name. Cheap to clone (shared).
#[derive(Clone, Debug, Default)]
pub struct SceneData {
    /// World points of every point source.
    pub points: HashMap<String, Arc<Vec<DVec3>>>,
    /// The potential of every image source.
    pub images: HashMap<String, Arc<ImagePotential>>,
    /// How each source shared by two or more parts was split among them, by source name.
    pub splits: HashMap<String, Split>,
    /// The noise of the range points of each part whose stiffness comes from it
    /// ([`PartDef::stiffness_from_noise`]), by part index.
    pub noise: HashMap<usize, NoiseEstimate>,
}

/// How a shared source's points were split among its parts ([`crate::model::parts::partition`]).
#[derive(Clone, Debug)]
pub struct Split {
    /// The scene index of the part each of the source's points pulls on.
    pub owner: Arc<Vec<usize>>,
    /// Rounds of fit-then-reassign taken.
    pub rounds: u32,
    /// True when the last round moved no point.
    pub stable: bool,
    /// How many points the last round moved to another part.
    pub moved: usize,
}

impl SceneData {
    /// Loads every data source of `def`; `read` returns the bytes of a path relative to the scene
    /// (`file`, which names the scene in errors).
    pub fn resolve(
        def: &SceneDef,
        file: &Path,
        mut read: impl FnMut(&str) -> Result<Vec<u8>, String>,
    ) -> Result<Self, SceneError> {
        let mut out = SceneData::default();
        for (name, source) in &def.data {
            let at = format!("data.{name}.path");
            match source {
                DataSource::Points { path, placement } => {
                    let bytes = read(path).map_err(|m| SceneError::at_field(file, &at, m))?;
                    let raw = decode_points(Path::new(path), &bytes)
                        .map_err(|e| SceneError::at_field(file, &at, e.to_string()))?;
                    let q = placement.rotation.to_quat().unwrap_or(DQuat::IDENTITY);
                    let t = DVec3::from_array(placement.translation);
                    let placed = raw.iter().map(|p| t + q * (placement.scale * *p)).collect();
                    out.points.insert(name.clone(), Arc::new(placed));
                }
                DataSource::Generated(g) => {
                    let pts = match g {
                        Generated::Egg => crate::synthetic::egg(),
                        Generated::Mug => crate::synthetic::mug(),
                        Generated::Banana => {
                            crate::synthetic::Banana::default().points(2000, 0.002, 7)
                        }
                    };
                    out.points.insert(name.clone(), Arc::new(pts));
                }
                DataSource::Image {
                    path,
                    sigma,
                    center,
                    extent,
                } => {
                    let bytes = read(path).map_err(|m| SceneError::at_field(file, &at, m))?;
                    let (w, h, lum) = decode_luminance(Path::new(path), &bytes)
                        .map_err(|e| SceneError::at_field(file, &at, e.to_string()))?;
                    let frame = ImageFrame {
                        center: DVec2::from_array(*center),
                        extent: *extent,
                    };
                    let potential = ImagePotential::new(w, h, lum, *sigma, frame)
                        .map_err(|e| SceneError::at_field(file, &at, format!("{path}: {e}")))?;
                    out.images.insert(name.clone(), Arc::new(potential));
                }
            }
        }
        for (source, group) in def.shared_groups() {
            if group.len() < 2 {
                continue;
            }
            let split = out.split(def, source, &group).map_err(|m| {
                SceneError::at_field(file, format!("parts[{}].forces", group[0]), m)
            })?;
            out.splits.insert(source.to_string(), split);
        }
        for (i, part) in def.parts.iter().enumerate() {
            if let Forces::Range { .. } = part.forces {
                let points = out.range_points(def, i).unwrap_or_default();
                let n = points.len();
                if n < crate::model::fit::MIN_POINTS {
                    return Err(SceneError::at_field(
                        file,
                        format!("parts[{i}].forces"),
                        format!(
                            "{n} data points act on this part (after any crop); a fit needs at least {}",
                            crate::model::fit::MIN_POINTS
                        ),
                    ));
                }
                if part.stiffness_from_noise {
                    let noise = estimate_noise(&points).ok_or_else(|| {
                        SceneError::at_field(
                            file,
                            format!("parts[{i}].stiffness_from_noise"),
                            format!(
                                "cannot estimate the noise of the part's {n} data points (it needs \
                                 at least {NOISE_NEIGHBOURS} points spread in space)"
                            ),
                        )
                    })?;
                    out.noise.insert(i, noise);
                }
            }
        }
        Ok(out)
    }

    /// Splits the points of `source` among the parts `group` (scene indices) that share it.
    fn split(&self, def: &SceneDef, source: &str, group: &[usize]) -> Result<Split, String> {
        let points = self
            .points
            .get(source)
            .ok_or_else(|| format!("the data {source:?} are not loaded"))?;
        let opts: Vec<FitOptions> = group
            .iter()
            .map(|&i| {
                let part = &def.parts[i];
                let placed = match part.placement {
                    PartPlacement::Auto => None,
                    _ => self.initial_state(def, i),
                };
                let init = placed.map_or(Initialization::Moments, |s| {
                    Initialization::Explicit(InitialPose::of(&s))
                });
                part.fit_options_from(init)
            })
            .collect();
        let p = partition(points, &opts, PARTITION_ROUNDS)
            .map_err(|e| format!("splitting {source:?} among parts {group:?}: {e}"))?;
        Ok(Split {
            owner: Arc::new(p.owner.iter().map(|&j| group[j]).collect()),
            rounds: p.rounds,
            stable: p.stable,
            moved: p.moved,
        })
    }

    /// The world points that pull on part `index`, if it has range forces: its source's points
    /// inside its crop box, or, from a shared source, the points the split gave it.
    pub fn range_points(&self, def: &SceneDef, index: usize) -> Option<Vec<DVec3>> {
        let Forces::Range {
            data, crop, shared, ..
        } = &def.parts.get(index)?.forces
        else {
            return None;
        };
        let pts = self.points.get(data)?;
        Some(match (crop, self.splits.get(data)) {
            (_, Some(split)) if *shared => pts
                .iter()
                .zip(split.owner.iter())
                .filter(|(_, o)| **o == index)
                .map(|(p, _)| *p)
                .collect(),
            (Some(b), _) => pts.iter().copied().filter(|p| b.contains(*p)).collect(),
            _ => pts.to_vec(),
        })
    }

    /// The image forces on `part`, if it has image forces.
    pub fn image_forces(&self, part: &PartDef) -> Option<ImageForces> {
        let Forces::Image { data, .. } = &part.forces else {
            return None;
        };
        Some(part.image_options().forces(self.images.get(data)?.clone()))
    }

    /// Part `index`'s state as the scene places it: pose, global shape and local displacements
    /// (zero when the scene gives none).
    pub fn initial_state(&self, def: &SceneDef, index: usize) -> Option<ModelState> {
        let part = def.parts.get(index)?;
        let tess_nodes = part.k * part.k + 2;
        let mut state = match part.placement {
            PartPlacement::Pose {
                translation,
                rotation,
                shape,
            } => ModelState {
                translation: DVec3::from_array(translation),
                rotation: rotation.to_quat().ok()?,
                shape,
                deformation: part.deformation,
                displacement: vec![DVec3::ZERO; tess_nodes],
            },
            PartPlacement::Axes { major, minor } => {
                let Forces::Image { data, .. } = &part.forces else {
                    return None;
                };
                let potential = self.images.get(data)?;
                let pts = [major[0], major[1], minor[0], minor[1]].map(DVec2::from_array);
                let (translation, rotation, shape) =
                    PartAxes::from_points(potential, pts).ok()?.pose();
                ModelState {
                    translation,
                    rotation,
                    shape,
                    deformation: part.deformation,
                    displacement: vec![DVec3::ZERO; tess_nodes],
                }
            }
            PartPlacement::Auto => {
                let pose = initial_pose(&self.range_points(def, index)?);
                ModelState {
                    translation: pose.translation,
                    rotation: pose.rotation,
                    shape: pose.shape,
                    deformation: part.deformation,
                    displacement: vec![DVec3::ZERO; tess_nodes],
                }
            }
        };
        if let Some(local) = &part.local {
            state.displacement = local.iter().map(|d| DVec3::from_array(*d)).collect();
        }
        Some(state)
    }
}

/// What running a part to rest gave.
#[derive(Clone, Debug)]
pub enum PartRun {
    /// A range fit (see [`fit`]).
    Range(Box<FitReport>),
    /// An image fit (see [`fit_part`]).
    Image(ImagePartFit),
    /// A part with no data: nothing moves it without a user.
    Free(ModelState),
}

impl PartRun {
    /// The part's state at the end.
    pub fn state(&self) -> &ModelState {
        match self {
            PartRun::Range(r) => &r.state,
            PartRun::Image(f) => &f.state,
            PartRun::Free(s) => s,
        }
    }
}

/// Runs part `index` of a loaded scene to rest (or its step cap), without a window: range parts
/// through [`fit`] from the scene's placement (the local displacements start at zero), image parts
/// through [`fit_part`] from their placement and displacements. `max_steps` overrides the part's cap.
pub fn run_part(
    def: &SceneDef,
    data: &SceneData,
    index: usize,
    max_steps: Option<u32>,
) -> Result<PartRun, String> {
    let part = def
        .parts
        .get(index)
        .ok_or_else(|| format!("the scene has no part {index}"))?;
    let state = data
        .initial_state(def, index)
        .ok_or_else(|| format!("parts[{index}]: cannot place the part"))?;
    match &part.forces {
        Forces::Free => Ok(PartRun::Free(state)),
        Forces::Range { .. } => {
            let points = data
                .range_points(def, index)
                .ok_or_else(|| format!("parts[{index}]: its data are not loaded"))?;
            let mut opts = part.fit_options(&state);
            if let Some(m) = max_steps {
                opts.max_steps = m;
            }
            let report = fit(&points, &opts, |_| {})
                .map_err(|e: FitError| format!("parts[{index}]: {e}"))?;
            Ok(PartRun::Range(Box::new(report)))
        }
        Forces::Image { .. } => {
            let forces = data
                .image_forces(part)
                .ok_or_else(|| format!("parts[{index}]: its image is not loaded"))?;
            let mut opts = part.image_options();
            if let Some(m) = max_steps {
                opts.max_steps = m as usize;
            }
            let tess = Tessellation::new(part.k);
            let fitted = fit_part(&tess, &forces, state, &opts)
                .map_err(|e: StepError| format!("parts[{index}]: {e}"))?;
            Ok(PartRun::Image(fitted))
        }
    }
}

/// Runs every part of a scene (in parallel threads), in order.
pub fn run_scene(
    def: &SceneDef,
    data: &SceneData,
    max_steps: Option<u32>,
) -> Vec<Result<PartRun, String>> {
    std::thread::scope(|scope| {
        let handles: Vec<_> = (0..def.parts.len())
            .map(|i| scope.spawn(move || run_part(def, data, i, max_steps)))
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err("the part's thread panicked".into()))
            })
            .collect()
    })
}
