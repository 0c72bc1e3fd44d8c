//! Placing a part on an image (section VI-A): from the paper's four clicks
//! ([`PartAxes::from_points`]) or, with no user, from the image's blobs ([`segment`]).

use crate::model::dynamics::ModelState;
use crate::model::fem::Tessellation;
use crate::model::forces::image::ImagePotential;
use crate::model::image_measure::{PixelMoments, axis_ends};
use crate::model::superquadric::SuperquadricParams;
use glam::{DMat3, DQuat, DVec2, DVec3};

/// A part's placement in the image plane: centre, major semi-axis (a vector) and minor semi-axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PartAxes {
    /// Centre in plane coordinates.
    pub center: DVec2,
    /// Major semi-axis as a plane vector (direction and length).
    pub major: DVec2,
    /// Minor semi-axis length (in the plane, perpendicular to `major`; also the depth).
    pub minor: f64,
}

/// Why a part could not be placed.
#[derive(Clone, Debug, PartialEq)]
pub enum PlacementError {
    /// The part's centre is not on the image.
    OutsideImage {
        /// Centre in pixels.
        center: DVec2,
    },
    /// An axis has zero or non-finite length.
    DegenerateAxis,
}

impl std::fmt::Display for PlacementError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PlacementError::OutsideImage { center } => write!(
                f,
                "the part's centre ({:.1}, {:.1}) px is outside the image",
                center.x, center.y
            ),
            PlacementError::DegenerateAxis => {
                write!(f, "an axis of the part has zero or non-finite length")
            }
        }
    }
}

impl std::error::Error for PlacementError {}

impl PartAxes {
    /// From four pixel positions: both ends of the major axis, then both ends of the minor axis.
    pub fn from_points(
        potential: &ImagePotential,
        pixels: [DVec2; 4],
    ) -> Result<Self, PlacementError> {
        if !pixels.iter().all(|p| p.is_finite()) {
            return Err(PlacementError::DegenerateAxis);
        }
        let center_px = (pixels[0] + pixels[1] + pixels[2] + pixels[3]) / 4.0;
        let x = pixels.map(|p| potential.to_plane(p));
        let axes = Self {
            center: potential.to_plane(center_px),
            major: (x[1] - x[0]) / 2.0,
            minor: (x[3] - x[2]).length() / 2.0,
        };
        axes.check(potential)
    }

    /// From a blob's pixel moments.
    pub fn from_blob(potential: &ImagePotential, blob: &Blob) -> Result<Self, PlacementError> {
        let c = blob.centroid;
        let [_, major_end, _, minor_end] = axis_ends(c, blob.covariance);
        let center = potential.to_plane(c);
        let axes = Self {
            center,
            major: potential.to_plane(major_end) - center,
            minor: (minor_end - c).length() * potential.pitch(),
        };
        axes.check(potential)
    }

    fn check(self, potential: &ImagePotential) -> Result<Self, PlacementError> {
        if !(self.major.is_finite() && self.minor.is_finite() && self.center.is_finite())
            || self.major.length() <= 0.0
            || self.minor <= 0.0
        {
            return Err(PlacementError::DegenerateAxis);
        }
        if !potential.contains(self.center) {
            return Err(PlacementError::OutsideImage {
                center: potential.to_pixel(self.center),
            });
        }
        Ok(self)
    }

    /// The pose and shape this placement gives: the model's z axis along the major axis, its
    /// x axis along the minor one, its y axis out of the image; ε1 = ε2 = 1.
    pub fn pose(&self) -> (DVec3, DQuat, SuperquadricParams) {
        ellipsoid_pose(
            self.center.extend(0.0),
            self.major.extend(0.0),
            self.minor,
            DVec3::Z,
        )
    }

    /// A model in this placement with zero local displacement.
    pub fn state(&self, tess: &Tessellation) -> ModelState {
        let (c, r, s) = self.pose();
        ModelState::new(tess, c, r, s)
    }
}

/// The ellipsoid a user places as in the paper's Fig. 6(a), in any plane: centred on `center`,
/// its model z axis along `major` (the half-axis vector, in the plane), its x axis along the minor
/// axis of half-length `minor`, its y axis along the plane's unit `normal`; the depth semi-axis is
/// the minor one, ε1 = ε2 = 1.
pub fn ellipsoid_pose(
    center: DVec3,
    major: DVec3,
    minor: f64,
    normal: DVec3,
) -> (DVec3, DQuat, SuperquadricParams) {
    let ez = major.normalize();
    let ex = normal.cross(ez);
    let ey = ez.cross(ex);
    let rotation = DQuat::from_mat3(&DMat3::from_cols(ex, ey, ez)).normalize();
    let major = major.length();
    let minor = minor.min(major);
    let shape = SuperquadricParams {
        a: major,
        a1: minor / major,
        a2: minor / major,
        a3: 1.0,
        e1: 1.0,
        e2: 1.0,
    }
    .normalized();
    (center, rotation, shape)
}

/// The placement of [`ellipsoid_pose`] from four points in a plane: both ends of the major axis,
/// then both ends of the minor axis (projected into the plane through their mean with unit
/// `normal`); `None` when an axis has no length.
pub fn ellipsoid_from_points(
    points: [DVec3; 4],
    normal: DVec3,
) -> Option<(DVec3, DQuat, SuperquadricParams)> {
    let flat = |v: DVec3| v - normal * v.dot(normal);
    let center = (points[0] + points[1] + points[2] + points[3]) / 4.0;
    let major = flat(points[1] - points[0]) / 2.0;
    let minor = flat(points[3] - points[2]).length() / 2.0;
    let ok = major.is_finite() && minor.is_finite() && major.length() > 1e-9 && minor > 1e-9;
    ok.then(|| ellipsoid_pose(center, major, minor, normal.normalize()))
}

/// A 4-connected region of foreground pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct Blob {
    /// Pixel count.
    pub area: usize,
    /// Mean pixel position (column, row).
    pub centroid: DVec2,
    /// Covariance of the pixel positions [[σxx, σxy], [σxy, σyy]] (pixels², rows downwards).
    pub covariance: [[f64; 2]; 2],
}

/// The foreground's 4-connected blobs of at least `min_area` pixels, largest first.
pub fn segment(potential: &ImagePotential, min_area: usize) -> Vec<Blob> {
    let (w, h) = (potential.width(), potential.height());
    let mask = potential.foreground();
    let mut seen = vec![false; w * h];
    let mut blobs = Vec::new();
    let mut stack = Vec::new();
    for start in 0..w * h {
        if !mask[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let mut moments = PixelMoments::default();
        while let Some(i) = stack.pop() {
            let (c, r) = (i % w, i / w);
            moments.add(DVec2::new(c as f64, r as f64));
            let mut visit = |j: usize| {
                if mask[j] && !seen[j] {
                    seen[j] = true;
                    stack.push(j);
                }
            };
            if c > 0 {
                visit(i - 1);
            }
            if c + 1 < w {
                visit(i + 1);
            }
            if r > 0 {
                visit(i - w);
            }
            if r + 1 < h {
                visit(i + w);
            }
        }
        if moments.count() >= min_area.max(1)
            && let Some((centroid, covariance)) = moments.mean_and_covariance()
        {
            blobs.push(Blob {
                area: moments.count(),
                centroid,
                covariance,
            });
        }
    }
    blobs.sort_by_key(|b| std::cmp::Reverse(b.area));
    blobs
}
