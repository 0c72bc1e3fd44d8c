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
//! - [`part_region`]: one part's silhouette and the ring around it: its area on and off the
//!   image, and its [`RegionModel`].

use super::fem::Tessellation;
use super::forces::image::{ImagePotential, RegionModel, for_each_outline_edge};
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
    let hi = DVec2::new((w - 1) as f64, (h - 1) as f64);
    for (tess, x) in parts {
        for t in tess.triangles() {
            let v = t.map(|i| potential.to_pixel(x[i as usize].truncate()));
            fill_triangle(v, DVec2::ZERO, hi, 1, |c, r| {
                mask[r as usize * w + c as usize] = true;
            });
        }
    }
    mask
}

/// Calls `f(column, row)` for every pixel centre inside the triangle `v` (pixel positions) and
/// within [lo, hi] whose column and row are multiples of `stride`; nothing for a degenerate or
/// non-finite triangle.
fn fill_triangle(
    v: [DVec2; 3],
    lo: DVec2,
    hi: DVec2,
    stride: usize,
    mut f: impl FnMut(isize, isize),
) {
    let area = (v[1] - v[0]).perp_dot(v[2] - v[0]);
    if area == 0.0 || !area.is_finite() {
        return;
    }
    let s = stride as f64;
    let from = (v[0].min(v[1]).min(v[2]).max(lo) / s).ceil() * s;
    let to = v[0].max(v[1]).max(v[2]).min(hi).floor();
    for r in (from.y as isize..=to.y as isize).step_by(stride) {
        for c in (from.x as isize..=to.x as isize).step_by(stride) {
            let p = DVec2::new(c as f64, r as f64);
            let s0 = (v[1] - v[0]).perp_dot(p - v[0]) / area;
            let s1 = (v[2] - v[1]).perp_dot(p - v[1]) / area;
            let s2 = (v[0] - v[2]).perp_dot(p - v[2]) / area;
            if s0 >= 0.0 && s1 >= 0.0 && s2 >= 0.0 {
                f(c, r);
            }
        }
    }
}

/// One part's silhouette and the ring around it ([`part_region`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PartRegion {
    /// Pixels inside the silhouette, on the image or off it (off it, counted up to one image
    /// size beyond each border); sampled, see [`part_region`].
    pub area: usize,
    /// Of those, the pixels on the image.
    pub on_image: usize,
    /// The part's [`RegionModel::from_samples`] of the luminance inside the silhouette and in
    /// the ring around it, on the image.
    pub model: Option<RegionModel>,
}

/// Samples of a part's spine ([`RegionModel::from_samples`]).
const SPINE_SAMPLES: usize = 32;

/// Samples taken of a part's region at most (about 128², whatever the part's size): enough for
/// means to a fraction of a grey level and an area to a percent.
const REGION_SAMPLES: f64 = 16384.0;

/// The silhouette of one part on `potential`'s pixel grid, and the ring around it: the
/// silhouette scaled by √2 about the nodes' mean, less the silhouette itself, which makes the
/// ring as large as the silhouette (the inside and the surroundings weigh the same). The
/// spine is sampled between the projections of the poles (the tessellation's first and last
/// nodes).
///
/// The pixels are sampled every `s` columns and rows, with `s` the least that keeps the samples
/// of the ring's bounding box within 16384, and each sample counts for s² pixels of area. Only
/// triangles that face the camera are filled: on a closed surface they cover the silhouette.
pub fn part_region(potential: &ImagePotential, tess: &Tessellation, x: &[DVec3]) -> PartRegion {
    let (w, h) = (potential.width() as isize, potential.height() as isize);
    let empty = PartRegion {
        area: 0,
        on_image: 0,
        model: None,
    };
    if x.len() < 2 {
        return empty;
    }
    let centre = x.iter().map(|p| p.truncate()).sum::<DVec2>() / x.len().max(1) as f64;
    let ring_scale = std::f64::consts::SQRT_2;
    let pixel = |p: DVec3| potential.to_pixel(p.truncate());
    let grown = |p: DVec3| potential.to_pixel(centre + (p.truncate() - centre) * ring_scale);
    // The pixels either shape covers, clipped to one image size beyond each border.
    let (mut lo, mut hi) = (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY));
    for &p in x {
        for q in [pixel(p), grown(p)] {
            if q.is_finite() {
                (lo, hi) = (lo.min(q), hi.max(q));
            }
        }
    }
    let lo = lo.ceil().max(DVec2::new(-w as f64, -h as f64));
    let hi = hi
        .floor()
        .min(DVec2::new((2 * w - 1) as f64, (2 * h - 1) as f64));
    if !(lo.x <= hi.x && lo.y <= hi.y) {
        return empty;
    }
    let box_area = (hi.x - lo.x + 1.0) * (hi.y - lo.y + 1.0);
    let stride = (box_area / REGION_SAMPLES).sqrt().ceil().max(1.0) as usize;
    let s = stride as f64;
    // The sample grid: multiples of the stride within [lo, hi].
    let (lo, hi) = ((lo / s).ceil() * s, (hi / s).floor() * s);
    if !(lo.x <= hi.x && lo.y <= hi.y) {
        return empty;
    }
    let cols = ((hi.x - lo.x) / s) as usize + 1;
    let rows = ((hi.y - lo.y) / s) as usize + 1;
    let (c0, r0) = (lo.x as isize, lo.y as isize);
    // Bit 1: inside the silhouette; bit 2: inside the grown silhouette.
    let mut cover = vec![0u8; cols * rows];
    for t in tess.triangles() {
        let v = t.map(|i| pixel(x[i as usize]));
        // Pixel rows run down: a triangle facing the camera (+z) turns clockwise here.
        if (v[1] - v[0]).perp_dot(v[2] - v[0]) >= 0.0 {
            continue;
        }
        let g = t.map(|i| grown(x[i as usize]));
        for (bit, v) in [(1u8, v), (2, g)] {
            fill_triangle(v, lo, hi, stride, |c, r| {
                let (i, j) = ((c - c0) as usize / stride, (r - r0) as usize / stride);
                cover[j * cols + i] |= bit;
            });
        }
    }
    let lum = potential.luminance();
    let (mut area, mut on_image) = (0, 0);
    let (mut inside, mut ring) = (Vec::new(), Vec::new());
    let weight = stride * stride;
    for (i, &bits) in cover.iter().enumerate().filter(|(_, b)| **b != 0) {
        let (c, r) = (
            c0 + ((i % cols) * stride) as isize,
            r0 + ((i / cols) * stride) as isize,
        );
        let is_inside = bits & 1 != 0;
        area += usize::from(is_inside) * weight;
        if c < 0 || r < 0 || c >= w || r >= h {
            continue;
        }
        let v = lum[(r * w + c) as usize];
        if is_inside {
            on_image += weight;
            inside.push(v);
        } else {
            ring.push(v);
        }
    }
    // The spine: the middle 80 % of the segment between the poles' projections, 32 samples.
    let (south, north) = (x[0].truncate(), x[x.len() - 1].truncate());
    let spine: Vec<f64> = (0..SPINE_SAMPLES)
        .filter_map(|i| {
            let t = 0.1 + 0.8 * (i as f64 + 0.5) / SPINE_SAMPLES as f64;
            potential.luminance_at(south.lerp(north, t))
        })
        .collect();
    PartRegion {
        area,
        on_image,
        model: RegionModel::from_samples(&inside, &ring, &spine),
    }
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

/// Both ends of the major axis, then both ends of the minor axis, of pixels with centroid
/// `centroid` and covariance `covariance` (pixels, rows downwards): each 2σ from the centroid
/// along its principal axis, the semi-axes of a filled ellipse with those moments.
pub fn axis_ends(centroid: DVec2, covariance: [[f64; 2]; 2]) -> [DVec2; 4] {
    let [[sxx, sxy], [_, syy]] = covariance;
    let mean = 0.5 * (sxx + syy);
    let spread = (0.25 * (sxx - syy).powi(2) + sxy * sxy).sqrt();
    let (l1, l2) = (mean + spread, (mean - spread).max(0.0));
    let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let e1 = DVec2::new(angle.cos(), angle.sin());
    let (a, b) = (2.0 * l1.sqrt() * e1, 2.0 * l2.sqrt() * e1.perp());
    [centroid - a, centroid + a, centroid - b, centroid + b]
}

/// [`axis_ends`] of the pixels where `mask` holds (row-major, `width` pixels a row): where a
/// user would click to place a part on them. `None` for an empty mask.
pub fn mask_axis_ends(width: usize, mask: &[bool]) -> Option<[DVec2; 4]> {
    let mut moments = PixelMoments::default();
    for i in (0..mask.len()).filter(|&i| mask[i]) {
        moments.add(DVec2::new((i % width) as f64, (i / width) as f64));
    }
    let (centroid, covariance) = moments.mean_and_covariance()?;
    Some(axis_ends(centroid, covariance))
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
