//! The scene file's format: the types a `.dsq.ron` file deserialises into, with their defaults.
//! The reference for users is docs/scene-format.md.

use super::*;

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

pub(super) fn default_joint_stiffness() -> f64 {
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

impl Placement {
    /// The world position of the file point `p`: translation + rotation · (scale · p).
    pub fn place(&self, p: DVec3) -> DVec3 {
        let q = self.rotation.to_quat().unwrap_or(DQuat::IDENTITY);
        DVec3::from_array(self.translation) + q * (self.scale * p)
    }

    /// The placement that scales `points` (file coordinates) uniformly, without turning them, so
    /// that their centroid lands at `at` and their RMS distance from it is `radius`: their first
    /// two moments. `None` for no points, non-finite ones, or points that all coincide.
    pub fn framing(points: &[DVec3], at: DVec3, radius: f64) -> Option<Self> {
        if points.is_empty() || !at.is_finite() || !(radius > 0.0 && radius.is_finite()) {
            return None;
        }
        let n = points.len() as f64;
        let centroid = points.iter().copied().sum::<DVec3>() / n;
        let rms = (points
            .iter()
            .map(|p| p.distance_squared(centroid))
            .sum::<f64>()
            / n)
            .sqrt();
        if !(rms > 0.0 && rms.is_finite()) {
            return None;
        }
        let scale = radius / rms;
        Some(Self {
            translation: (at - scale * centroid).to_array(),
            rotation: Rotation::default(),
            scale,
        })
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

impl Forces {
    /// Range forces from the points of source `data`, with every other setting at its default
    /// (as a scene that writes only `Range(data: "…")`).
    pub fn range(data: impl Into<String>) -> Self {
        Forces::Range {
            data: data.into(),
            beta: default_range_beta(),
            coverage: default_coverage(),
            influence: InfluenceMode::default(),
            outliers: 0.0,
            crop: None,
            shared: false,
        }
    }
}

impl Forces {
    /// Image forces from source `data`, with every other setting at its default (as a scene that
    /// writes only `Image(data: "…")`).
    pub fn image(data: impl Into<String>) -> Self {
        Forces::Image {
            data: data.into(),
            beta: default_image_beta(),
            band: default_band(),
            outline_only: yes(),
            region: 0.0,
        }
    }
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
    /// Run the global DOFs to rest before freeing the local ones (the dynamics).
    pub global_first: bool,
    /// How a part's fit to its data comes to rest: `Solved` (absent: the default) or `Dynamics`
    /// (the paper's explicit steps, as the paper's experiments run).
    #[serde(default, skip_serializing_if = "is_solved")]
    pub solver: Solver,
}

/// True for the default solver (not written to a saved scene).
fn is_solved(solver: &Solver) -> bool {
    *solver == Solver::Solved
}

impl Default for FitSettings {
    fn default() -> Self {
        Self {
            tolerance: None,
            max_steps: None,
            global_first: true,
            solver: Solver::Solved,
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

pub(super) fn default_sigma() -> f64 {
    DEFAULT_SIGMA
}
pub(super) fn one() -> f64 {
    1.0
}
pub(super) fn yes() -> bool {
    true
}
pub(super) fn y_up() -> [f64; 3] {
    [0.0, 1.0, 0.0]
}
pub(super) fn default_k() -> usize {
    FitOptions::default().k
}
pub(super) fn default_w0() -> f64 {
    DynamicsParams::default().w0
}
pub(super) fn default_w1() -> f64 {
    DynamicsParams::default().w1
}
pub(super) fn default_dt() -> f64 {
    DynamicsParams::default().dt
}
pub(super) fn default_reassign() -> u32 {
    FitOptions::default().reassign_every
}
pub(super) fn default_range_beta() -> f64 {
    FitOptions::default().beta
}
pub(super) fn default_coverage() -> f64 {
    DEFAULT_COVERAGE
}
pub(super) fn default_image_beta() -> f64 {
    DEFAULT_IMAGE_BETA
}
pub(super) fn default_band() -> f64 {
    DEFAULT_BAND
}
