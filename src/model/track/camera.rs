//! A pinhole depth camera: its intrinsics, a depth frame, and the rays between them.
//!
//! The camera frame is OpenCV's (and Open3D's): x right, y down, z forward, so a pixel (u, v)
//! of depth z back-projects to z·((u − c_x)/f_x, (v − c_y)/f_y, 1). Pixel centres sit at whole
//! coordinates.

use glam::{DVec2, DVec3};

/// A pinhole camera's intrinsics: the image size and the focal lengths and principal point, in
/// pixels.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Intrinsics {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
}

impl Intrinsics {
    /// Checks that the size is at least one pixel and the focal lengths and principal point are
    /// finite with positive focal lengths; the message names the first field that is not.
    pub fn validate(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!(
                "the image size {}×{} has no pixels",
                self.width, self.height
            ));
        }
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} is {v}; a focal length must be positive"));
            }
        }
        for (name, v) in [("cx", self.cx), ("cy", self.cy)] {
            if !v.is_finite() {
                return Err(format!("{name} is {v}; it must be finite"));
            }
        }
        Ok(())
    }

    /// The camera-frame point of pixel (u, v) at depth `z`.
    pub fn back_project(&self, u: f64, v: f64, z: f64) -> DVec3 {
        DVec3::new((u - self.cx) / self.fx * z, (v - self.cy) / self.fy * z, z)
    }

    /// The pixel position of a camera-frame point in front of the camera (`None` behind it).
    pub fn project(&self, p: DVec3) -> Option<DVec2> {
        (p.z > 0.0)
            .then(|| DVec2::new(self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy))
    }

    /// The ray of pixel (u, v) scaled to unit depth: the points z·ray.
    pub fn ray(&self, u: f64, v: f64) -> DVec3 {
        self.back_project(u, v, 1.0)
    }
}

/// A depth image in metres: `depth[v·width + u]`, 0 where the sensor saw nothing.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthFrame {
    /// The camera.
    pub intrinsics: Intrinsics,
    /// Depth along z per pixel, metres; 0 for no depth.
    pub depth: Vec<f32>,
}

impl DepthFrame {
    /// A frame of raw sensor units `raw` (row-major, 0 = no depth) at `scale` metres per unit.
    /// Errors when the pixel count is not the intrinsics' size.
    pub fn from_raw(intrinsics: Intrinsics, raw: &[u16], scale: f64) -> Result<Self, String> {
        let expected = intrinsics.width as usize * intrinsics.height as usize;
        if raw.len() != expected {
            return Err(format!(
                "the frame has {} pixels, the intrinsics {}×{} = {expected}",
                raw.len(),
                intrinsics.width,
                intrinsics.height
            ));
        }
        let depth = raw.iter().map(|&d| (d as f64 * scale) as f32).collect();
        Ok(Self { intrinsics, depth })
    }

    /// A frame rendered from camera-frame `points` by a z-buffer: each point lands on its
    /// nearest pixel, the nearest point wins, pixels no point reaches have no depth.
    pub fn from_points(intrinsics: Intrinsics, points: &[DVec3]) -> Self {
        let (w, h) = (intrinsics.width as usize, intrinsics.height as usize);
        let mut depth = vec![0.0f32; w * h];
        for p in points {
            let Some(px) = intrinsics.project(*p) else {
                continue;
            };
            let (u, v) = (px.x.round(), px.y.round());
            if u < 0.0 || v < 0.0 || u >= w as f64 || v >= h as f64 {
                continue;
            }
            let slot = &mut depth[v as usize * w + u as usize];
            let z = p.z as f32;
            if *slot == 0.0 || z < *slot {
                *slot = z;
            }
        }
        Self { intrinsics, depth }
    }

    /// The depth at pixel (u, v), metres (0: none, or outside the image).
    pub fn at(&self, u: usize, v: usize) -> f64 {
        let w = self.intrinsics.width as usize;
        if u >= w || v >= self.intrinsics.height as usize {
            return 0.0;
        }
        self.depth[v * w + u] as f64
    }

    /// Every pixel with depth inside the pixel box [u0, u1) × [v0, v1) (clipped to the image),
    /// taken every `stride` pixels, as camera-frame points with their pixel.
    pub fn points_in(
        &self,
        (u0, v0, u1, v1): (usize, usize, usize, usize),
        stride: usize,
    ) -> Vec<(DVec3, [u32; 2])> {
        let (w, h) = (
            self.intrinsics.width as usize,
            self.intrinsics.height as usize,
        );
        let stride = stride.max(1);
        let mut out = Vec::new();
        for v in (v0.min(h)..v1.min(h)).step_by(stride) {
            for u in (u0.min(w)..u1.min(w)).step_by(stride) {
                let z = self.depth[v * w + u] as f64;
                if z > 0.0 && z.is_finite() {
                    out.push((
                        self.intrinsics.back_project(u as f64, v as f64, z),
                        [u as u32, v as u32],
                    ));
                }
            }
        }
        out
    }

    /// How many pixels have depth.
    pub fn valid_pixels(&self) -> usize {
        self.depth.iter().filter(|&&d| d > 0.0).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> Intrinsics {
        Intrinsics {
            width: 64,
            height: 48,
            fx: 60.0,
            fy: 58.0,
            cx: 31.5,
            cy: 23.5,
        }
    }

    #[test]
    fn projection_inverts_back_projection() {
        let c = camera();
        let p = c.back_project(10.0, 40.0, 1.7);
        let px = c.project(p).unwrap();
        assert!((px - DVec2::new(10.0, 40.0)).length() < 1e-12);
        assert!(c.project(DVec3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn a_z_buffer_keeps_the_nearest_point() {
        let c = camera();
        let far = c.back_project(5.0, 6.0, 2.0);
        let near = c.back_project(5.0, 6.0, 1.0);
        let f = DepthFrame::from_points(c, &[far, near, DVec3::new(0.0, 0.0, -1.0)]);
        assert_eq!(f.at(5, 6), 1.0);
        assert_eq!(f.valid_pixels(), 1);
        let pts = f.points_in((0, 0, 64, 48), 1);
        assert_eq!(pts.len(), 1);
        assert!((pts[0].0 - near).length() < 1e-6);
    }

    #[test]
    fn bad_intrinsics_and_sizes_are_named() {
        let mut c = camera();
        c.fx = 0.0;
        assert!(c.validate().unwrap_err().contains("fx"));
        let e = DepthFrame::from_raw(camera(), &[0; 10], 0.001).unwrap_err();
        assert!(e.contains("10 pixels"), "{e}");
    }
}
