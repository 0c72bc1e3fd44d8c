//! How parts fitted to an image sit on it: their projected outlines and silhouettes, and the
//! measures [`crate::model::image_fit`] reports.
//!
//! - [`outline_potential`]: the mean of P / P_ref along the parts' projected outlines (the edges
//!   between triangles that face the camera and triangles that face away): 1 on a typical strong
//!   edge, near 0 in flat regions.
//! - [`silhouette_iou`]: the union of the parts' projected silhouettes against the thresholded
//!   foreground.
//! - [`part_silhouette`]: one part's silhouette on its own: its area and width in pixels and the
//!   share of it on the foreground, which tell a part that keeps its shape from a sliver.

use super::fem::Tessellation;
use super::forces::image::{ImagePotential, for_each_outline_edge};
use glam::{DVec2, DVec3};

/// The projected outline of a model (see [`for_each_outline_edge`]) as plane segments.
pub fn outline_segments(tess: &Tessellation, x: &[DVec3]) -> Vec<[DVec2; 2]> {
    let mut out = Vec::new();
    for_each_outline_edge(tess, x, |a, b| {
        out.push([x[a as usize].truncate(), x[b as usize].truncate()])
    });
    out
}

/// Pairs each part's node positions with their shared tessellation, as the measures take them.
pub fn parts_on<'a>(
    tess: &'a Tessellation,
    xs: &'a [Vec<DVec3>],
) -> Vec<(&'a Tessellation, &'a [DVec3])> {
    xs.iter().map(|x| (tess, x.as_slice())).collect()
}

/// Mean of P / P_ref along the projected outlines of `parts` (each a tessellation and its node
/// world positions), weighted by length; 0 when there is no outline or the image is flat.
pub fn outline_potential(potential: &ImagePotential, parts: &[(&Tessellation, &[DVec3])]) -> f64 {
    let (mut sum, mut len) = (0.0, 0.0);
    for (tess, x) in parts {
        for [a, b] in outline_segments(tess, x) {
            let l = (b - a).length();
            // Sample each segment at a pixel's spacing (at least its midpoint).
            let n = ((l / potential.pitch()).ceil() as usize).max(1);
            for s in 0..n {
                let p = a + (b - a) * ((s as f64 + 0.5) / n as f64);
                sum += potential.potential_at(p) * l / n as f64;
            }
            len += l;
        }
    }
    if len > 0.0 && potential.p_ref() > 0.0 {
        sum / len / potential.p_ref()
    } else {
        0.0
    }
}

/// The pixels (row-major) whose centres lie inside the projection of any of `parts`.
pub fn silhouette_mask(
    potential: &ImagePotential,
    parts: &[(&Tessellation, &[DVec3])],
) -> Vec<bool> {
    let (w, h) = (potential.width(), potential.height());
    let mut mask = vec![false; w * h];
    for (tess, x) in parts {
        for t in tess.triangles() {
            let v = t.map(|i| potential.to_pixel(x[i as usize].truncate()));
            let lo = v[0].min(v[1]).min(v[2]).ceil().max(DVec2::ZERO);
            let hi = v[0].max(v[1]).max(v[2]).floor();
            let area = (v[1] - v[0]).perp_dot(v[2] - v[0]);
            if area == 0.0 || !area.is_finite() {
                continue;
            }
            let (c1, r1) = (
                (hi.x.min((w - 1) as f64)) as isize,
                (hi.y.min((h - 1) as f64)) as isize,
            );
            for r in lo.y as isize..=r1 {
                for c in lo.x as isize..=c1 {
                    let p = DVec2::new(c as f64, r as f64);
                    let s0 = (v[1] - v[0]).perp_dot(p - v[0]) / area;
                    let s1 = (v[2] - v[1]).perp_dot(p - v[1]) / area;
                    let s2 = (v[0] - v[2]).perp_dot(p - v[2]) / area;
                    if s0 >= 0.0 && s1 >= 0.0 && s2 >= 0.0 {
                        mask[r as usize * w + c as usize] = true;
                    }
                }
            }
        }
    }
    mask
}

/// Intersection over union of two masks (1 when both are empty).
pub fn iou(a: &[bool], b: &[bool]) -> f64 {
    let (mut inter, mut union) = (0usize, 0usize);
    for (x, y) in a.iter().zip(b) {
        inter += (*x && *y) as usize;
        union += (*x || *y) as usize;
    }
    if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    }
}

/// IoU of the union of the parts' silhouettes with the image's thresholded foreground.
pub fn silhouette_iou(potential: &ImagePotential, parts: &[(&Tessellation, &[DVec3])]) -> f64 {
    iou(&silhouette_mask(potential, parts), potential.foreground())
}

/// One part's projected silhouette, measured in pixels (see [`part_silhouette`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PartSilhouette {
    /// Pixels whose centres lie inside the silhouette.
    pub area: usize,
    /// Width in pixels: √12 √λ_min of the covariance of the silhouette's pixels, the width of a
    /// bar with the same second moment across it (a leg's width; 0.87 × the minor axis of a
    /// filled ellipse). 0 for an empty silhouette.
    pub width: f64,
    /// Share of the silhouette's pixels on the image's foreground (0 for an empty silhouette).
    pub on_foreground: f64,
}

/// The silhouette of one part (a tessellation and its node world positions) on `potential`'s
/// pixel grid: area, width and share on the foreground.
pub fn part_silhouette(
    potential: &ImagePotential,
    tess: &Tessellation,
    x: &[DVec3],
) -> PartSilhouette {
    let mask = silhouette_mask(potential, &[(tess, x)]);
    let w = potential.width();
    let fg = potential.foreground();
    let (mut moments, mut on) = (PixelMoments::default(), 0usize);
    for (i, _) in mask.iter().enumerate().filter(|(_, m)| **m) {
        moments.add(DVec2::new((i % w) as f64, (i / w) as f64));
        on += fg[i] as usize;
    }
    let Some((_, [[sxx, sxy], [_, syy]])) = moments.mean_and_covariance() else {
        return PartSilhouette {
            area: 0,
            width: 0.0,
            on_foreground: 0.0,
        };
    };
    let lambda_min = 0.5 * (sxx + syy) - (0.25 * (sxx - syy).powi(2) + sxy * sxy).sqrt();
    PartSilhouette {
        area: moments.count(),
        width: (12.0 * lambda_min.max(0.0)).sqrt(),
        on_foreground: on as f64 / moments.count() as f64,
    }
}

/// Running sums of pixel positions: the count, mean and covariance of a set of pixels.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct PixelMoments {
    n: usize,
    sum: DVec2,
    /// Σx², Σxy, Σy².
    squares: [f64; 3],
}

impl PixelMoments {
    /// Adds the pixel at `p` (column, row).
    pub(crate) fn add(&mut self, p: DVec2) {
        self.n += 1;
        self.sum += p;
        self.squares[0] += p.x * p.x;
        self.squares[1] += p.x * p.y;
        self.squares[2] += p.y * p.y;
    }

    /// Pixels added.
    pub(crate) fn count(&self) -> usize {
        self.n
    }

    /// The mean position and the covariance [[σxx, σxy], [σxy, σyy]] (pixels², rows downwards)
    /// of the pixels, each a unit square with its own variance 1/12 per axis; `None` when empty.
    pub(crate) fn mean_and_covariance(&self) -> Option<(DVec2, [[f64; 2]; 2])> {
        if self.n == 0 {
            return None;
        }
        let n = self.n as f64;
        let m = self.sum / n;
        let sxx = self.squares[0] / n - m.x * m.x + 1.0 / 12.0;
        let sxy = self.squares[1] / n - m.x * m.y;
        let syy = self.squares[2] / n - m.y * m.y + 1.0 / 12.0;
        Some((m, [[sxx, sxy], [sxy, syy]]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::dynamics::ModelState;
    use crate::model::forces::image::ImageFrame;
    use crate::model::superquadric::SuperquadricParams;
    use glam::DQuat;

    /// A dark `w0`-pixel-wide vertical bar on white, `w`×`h`.
    fn bar(w: usize, h: usize, w0: usize) -> ImagePotential {
        let lum = (0..w * h)
            .map(|i| {
                if (i % w).abs_diff(w / 2) * 2 < w0 {
                    0.1
                } else {
                    0.9
                }
            })
            .collect();
        ImagePotential::new(w, h, lum, 2.0, ImageFrame::default()).unwrap()
    }

    #[test]
    fn outline_of_a_sphere_is_its_equator_and_its_silhouette_is_a_disc() {
        let (w, h) = (100, 100);
        let pot = ImagePotential::new(w, h, vec![0.5; w * h], 2.0, ImageFrame::default()).unwrap();
        // Odd k puts a ring on the equator, which is then the outline seen along z.
        let tess = Tessellation::new(15);
        let state = ModelState::new(
            &tess,
            DVec3::ZERO,
            DQuat::IDENTITY,
            SuperquadricParams {
                a: 0.25,
                ..Default::default()
            },
        );
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        let segs = outline_segments(&tess, &x);
        assert_eq!(segs.len(), 15);
        for [a, b] in &segs {
            assert!((a.length() - 0.25).abs() < 1e-9 && (b.length() - 0.25).abs() < 1e-9);
        }
        let mask = silhouette_mask(&pot, &[(&tess, &x)]);
        let area = mask.iter().filter(|&&m| m).count() as f64;
        // A 15-gon of circumradius 25 px: area (15/2) r² sin(2π/15) ≈ 1907 px².
        let expected = 7.5 * 625.0 * (2.0 * std::f64::consts::PI / 15.0).sin();
        assert!(
            (area - expected).abs() < 0.03 * expected,
            "{area} vs {expected}"
        );
    }

    #[test]
    fn a_box_over_a_bar_measures_its_area_width_and_share_on_the_foreground() {
        let pot = bar(100, 100, 20);
        let tess = Tessellation::new(31);
        // A squarish box (ε = 0.1) 30 px wide and 60 px tall: half of it over the 20-px bar.
        let px = pot.pitch();
        // The model's z axis (its long one) along the image's y.
        let state = ModelState::new(
            &tess,
            DVec3::ZERO,
            DQuat::from_rotation_x(std::f64::consts::FRAC_PI_2),
            SuperquadricParams {
                a: 30.0 * px,
                a1: 0.5,
                a2: 0.5,
                a3: 1.0,
                e1: 0.1,
                e2: 0.1,
            },
        );
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        let s = part_silhouette(&pot, &tess, &x);
        assert!((s.area as f64 - 1800.0).abs() < 0.05 * 1800.0, "{s:?}");
        assert!((s.width - 30.0).abs() < 1.5, "{s:?}");
        assert!((s.on_foreground - 20.0 / 30.0).abs() < 0.05, "{s:?}");
        let none = part_silhouette(&pot, &tess, &vec![DVec3::splat(5.0); x.len()]);
        assert_eq!((none.area, none.width, none.on_foreground), (0, 0.0, 0.0));
    }
}
