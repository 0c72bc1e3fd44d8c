//! What the solved image fit ([`super::solved`]) reads from an image: the distance to its edges,
//! and the signed distance to the figure a part was placed on.
//!
//! **Edges** are Canny's: the potential P = ‖∇(G_σ ∗ I)‖ thinned to its maxima across the edge
//! (non-maximum suppression along ∇(G_σ ∗ I)), kept where P ≥ [`EDGE_LOW`] P_ref and connected to
//! a pixel with P ≥ [`EDGE_HIGH`] P_ref (hysteresis). [`edge_distance`] is the Euclidean distance
//! transform of that edge map (Felzenszwalb and Huttenlocher's exact one).
//!
//! **The figure is decided by what encloses what.** The image is split in two classes by Otsu's
//! threshold: the whole image's on a two-tone image, else the threshold of the placed outline's
//! pixels and a ring about it as large, applied to the whole image. Its 4-connected components are
//! ranked by depth: a component on the image's border has depth 0, and one met first across
//! another's boundary is one deeper (a breadth-first search over pixels, 0 inside a component
//! and 1 across a boundary). The part's object is the component that covers most of the placed
//! outline's pixels (ties: the deepest) and encloses something less than the whole image, so a
//! box on a white desk framed by dark clutter is the box, and a leg placed half off a horse is
//! the horse (the background around it encloses everything). The figure is the object with
//! everything it encloses (the flood from the border that never enters the object does not reach
//! it): a coin's dark relief is the coin.
//! [`figure_distance`] is the figure's signed distance, negative inside.

use super::super::forces::image::{ImagePotential, otsu_threshold};
use glam::DVec2;
use std::collections::VecDeque;

/// Hysteresis: an edge pixel is kept when it is connected to one with P at least this × P_ref.
pub const EDGE_HIGH: f64 = 0.2;
/// Hysteresis: no edge pixel has P below this × P_ref.
pub const EDGE_LOW: f64 = 0.1;

/// A field sampled at the pixel centres, read between them bilinearly (pixel coordinates:
/// column, row).
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Raster {
    width: usize,
    height: usize,
    values: Vec<f64>,
}

impl Raster {
    /// The pixels where the field is negative (a signed distance's inside).
    pub(crate) fn inside_count(&self) -> usize {
        self.values.iter().filter(|&&v| v < 0.0).count()
    }

    /// The value and gradient (per pixel, along column and row) at `p`, bilinear between the
    /// four pixels around it; a point off the image reads the nearest border cell.
    pub(crate) fn sample(&self, p: DVec2) -> (f64, DVec2) {
        let (w, h) = (self.width, self.height);
        let c = if p.x.is_finite() {
            p.x.clamp(0.0, (w - 1) as f64)
        } else {
            0.0
        };
        let r = if p.y.is_finite() {
            p.y.clamp(0.0, (h - 1) as f64)
        } else {
            0.0
        };
        let c0 = (c as usize).min(w - 2);
        let r0 = (r as usize).min(h - 2);
        let (s, t) = (c - c0 as f64, r - r0 as f64);
        let i = r0 * w + c0;
        let v = &self.values;
        let (f00, f10, f01, f11) = (v[i], v[i + 1], v[i + w], v[i + w + 1]);
        let value = (1.0 - t) * ((1.0 - s) * f00 + s * f10) + t * ((1.0 - s) * f01 + s * f11);
        let dc = (1.0 - t) * (f10 - f00) + t * (f11 - f01);
        let dr = (1.0 - s) * (f01 - f00) + s * (f11 - f10);
        (value, DVec2::new(dc, dr))
    }
}

/// A large finite stand-in for "no feature" in the distance transform.
const FAR: f64 = 1e20;

/// The exact squared Euclidean distance transform of one line `f` (0 at a feature, [`FAR`]
/// elsewhere) into `d` (Felzenszwalb and Huttenlocher, 2012).
fn transform_line(f: &[f64], d: &mut [f64], v: &mut [usize], z: &mut [f64]) {
    let n = f.len();
    let mut k = 0usize;
    v[0] = 0;
    z[0] = f64::NEG_INFINITY;
    z[1] = f64::INFINITY;
    for q in 1..n {
        let fq = f[q] + (q * q) as f64;
        let mut s;
        loop {
            let p = v[k];
            s = (fq - (f[p] + (p * p) as f64)) / (2.0 * (q as f64 - p as f64));
            if s <= z[k] && k > 0 {
                k -= 1;
            } else {
                break;
            }
        }
        if s <= z[k] {
            // k == 0 and the new parabola lies below the first everywhere it matters.
            v[0] = q;
            z[0] = f64::NEG_INFINITY;
            z[1] = f64::INFINITY;
            continue;
        }
        k += 1;
        v[k] = q;
        z[k] = s;
        z[k + 1] = f64::INFINITY;
    }
    k = 0;
    for (q, dq) in d.iter_mut().enumerate() {
        while z[k + 1] < q as f64 {
            k += 1;
        }
        let p = v[k];
        *dq = (q as f64 - p as f64).powi(2) + f[p];
    }
}

/// The Euclidean distance (pixels) from every pixel to the nearest pixel where `feature` holds;
/// [`FAR`] everywhere when there is none.
fn distance_transform(width: usize, height: usize, feature: impl Fn(usize) -> bool) -> Vec<f64> {
    let n = width.max(height);
    let (mut v, mut z) = (vec![0usize; n], vec![0.0; n + 1]);
    let mut f = vec![0.0; n];
    let mut d = vec![0.0; n];
    let mut grid: Vec<f64> = (0..width * height)
        .map(|i| if feature(i) { 0.0 } else { FAR })
        .collect();
    for col in 0..width {
        for row in 0..height {
            f[row] = grid[row * width + col];
        }
        transform_line(&f[..height], &mut d[..height], &mut v, &mut z);
        for row in 0..height {
            grid[row * width + col] = d[row];
        }
    }
    for row in 0..height {
        f[..width].copy_from_slice(&grid[row * width..(row + 1) * width]);
        transform_line(&f[..width], &mut d[..width], &mut v, &mut z);
        grid[row * width..(row + 1) * width].copy_from_slice(&d[..width]);
    }
    grid.iter_mut().for_each(|g| *g = g.min(FAR).sqrt());
    grid
}

/// The image's edge map (see the module docs).
pub(crate) fn edges(pot: &ImagePotential) -> Vec<bool> {
    let (w, h) = (pot.width(), pot.height());
    let p = pot.potential();
    let (low, high) = (EDGE_LOW * pot.p_ref(), EDGE_HIGH * pot.p_ref());
    let mut kind = vec![0u8; w * h]; // 0 none, 1 weak, 2 strong
    for row in 1..h.saturating_sub(1) {
        for col in 1..w.saturating_sub(1) {
            let i = row * w + col;
            if !(p[i] >= low) || p[i] <= 0.0 {
                continue;
            }
            let g = pot.brightening_at_pixel(i);
            // Along the gradient in pixel steps (rows grow downwards, y upwards).
            let (gx, gy) = (g.x, -g.y);
            let angle = gy.atan2(gx).rem_euclid(std::f64::consts::PI);
            let step: isize = match (angle / (std::f64::consts::PI / 8.0)) as usize {
                0 | 7 => 1,
                1 | 2 => w as isize + 1,
                3 | 4 => w as isize,
                _ => w as isize - 1,
            };
            let (a, b) = (
                p[(i as isize + step) as usize],
                p[(i as isize - step) as usize],
            );
            if p[i] >= a && p[i] >= b {
                kind[i] = if p[i] >= high { 2 } else { 1 };
            }
        }
    }
    let mut stack: Vec<usize> = (0..w * h).filter(|&i| kind[i] == 2).collect();
    let mut edge: Vec<bool> = kind.iter().map(|&k| k == 2).collect();
    while let Some(i) = stack.pop() {
        let (col, row) = ((i % w) as isize, (i / w) as isize);
        for dr in -1..=1 {
            for dc in -1..=1 {
                let (c, r) = (col + dc, row + dr);
                if c < 0 || r < 0 || c >= w as isize || r >= h as isize {
                    continue;
                }
                let j = r as usize * w + c as usize;
                if kind[j] == 1 && !edge[j] {
                    edge[j] = true;
                    stack.push(j);
                }
            }
        }
    }
    edge
}

/// The distance (pixels) from every pixel to the image's nearest edge ([`edges`]); `None` on an
/// image without one.
pub(crate) fn edge_distance(pot: &ImagePotential) -> Option<Raster> {
    let edge = edges(pot);
    edge.iter().any(|&e| e).then(|| Raster {
        width: pot.width(),
        height: pot.height(),
        values: distance_transform(pot.width(), pot.height(), |i| edge[i]),
    })
}

/// Labels the 4-connected components of equal `class`; returns the label of every pixel and the
/// number of components.
fn components<T: PartialEq>(width: usize, height: usize, class: &[T]) -> (Vec<u32>, usize) {
    let mut label = vec![u32::MAX; width * height];
    let mut next = 0u32;
    let mut stack = Vec::new();
    for start in 0..width * height {
        if label[start] != u32::MAX {
            continue;
        }
        label[start] = next;
        stack.push(start);
        while let Some(i) = stack.pop() {
            for j in neighbours(width, height, i) {
                if label[j] == u32::MAX && class[j] == class[i] {
                    label[j] = next;
                    stack.push(j);
                }
            }
        }
        next += 1;
    }
    (label, next as usize)
}

/// The 4-neighbours of pixel `i` on the image.
fn neighbours(width: usize, height: usize, i: usize) -> impl Iterator<Item = usize> {
    let (c, r) = (i % width, i / width);
    [
        (c > 0).then(|| i - 1),
        (c + 1 < width).then(|| i + 1),
        (r > 0).then(|| i - width),
        (r + 1 < height).then(|| i + width),
    ]
    .into_iter()
    .flatten()
}

/// Two classes of a colour image: 2-means in RGB over the pixels `samples`, started from the
/// split `start` (or, when it leaves a class empty, from the samples' mean and the sample
/// farthest from it), then every pixel in the class of the nearer mean.
fn colour_classes(
    rgb: &[[f32; 3]],
    samples: impl Iterator<Item = usize>,
    start: impl Fn(usize) -> bool,
) -> Vec<bool> {
    let samples: Vec<usize> = samples.collect();
    let colour = |i: usize| rgb[i].map(f64::from);
    let means_of = |class: &[bool]| {
        let mut sums = [[0.0f64; 3]; 2];
        let mut counts = [0usize; 2];
        for (&i, &c) in samples.iter().zip(class) {
            let p = colour(i);
            for k in 0..3 {
                sums[usize::from(c)][k] += p[k];
            }
            counts[usize::from(c)] += 1;
        }
        (!counts.contains(&0)).then(|| [0, 1].map(|c| sums[c].map(|v| v / counts[c] as f64)))
    };
    let mut class: Vec<bool> = samples.iter().map(|&i| start(i)).collect();
    let mut means = means_of(&class).unwrap_or_else(|| {
        let n = samples.len().max(1) as f64;
        let mean = samples.iter().fold([0.0; 3], |a, &i| {
            let p = colour(i);
            [a[0] + p[0] / n, a[1] + p[1] / n, a[2] + p[2] / n]
        });
        let d = |p: [f64; 3]| (0..3).map(|k| (p[k] - mean[k]).powi(2)).sum::<f64>();
        let far = samples
            .iter()
            .map(|&i| colour(i))
            .max_by(|a, b| d(*a).total_cmp(&d(*b)))
            .unwrap_or(mean);
        [mean, far]
    });
    for _ in 0..20 {
        let next: Vec<bool> = samples
            .iter()
            .map(|&i| nearer_second(&means, rgb[i]))
            .collect();
        if next == class {
            break;
        }
        class = next;
        match means_of(&class) {
            Some(m) => means = m,
            None => break,
        }
    }
    rgb.iter().map(|&p| nearer_second(&means, p)).collect()
}

/// True when colour `p` lies nearer the second mean than the first.
fn nearer_second(means: &[[f64; 3]; 2], p: [f32; 3]) -> bool {
    let d = |m: &[f64; 3]| {
        (0..3)
            .map(|k| (f64::from(p[k]) - m[k]).powi(2))
            .sum::<f64>()
    };
    d(&means[1]) < d(&means[0])
}

/// Every component's depth: 0 on the image's border, else the fewest component boundaries
/// crossed on a way from the border (a 0–1 breadth-first search over pixels).
fn depths(width: usize, height: usize, label: &[u32], count: usize) -> Vec<u32> {
    let mut pixel = vec![u32::MAX; width * height];
    let mut queue = VecDeque::new();
    for i in 0..width * height {
        let (c, r) = (i % width, i / width);
        if c == 0 || r == 0 || c + 1 == width || r + 1 == height {
            pixel[i] = 0;
            queue.push_back(i);
        }
    }
    while let Some(i) = queue.pop_front() {
        for j in neighbours(width, height, i) {
            let cross = u32::from(label[j] != label[i]);
            if pixel[i] + cross < pixel[j] {
                pixel[j] = pixel[i] + cross;
                if cross == 0 {
                    queue.push_front(j);
                } else {
                    queue.push_back(j);
                }
            }
        }
    }
    let mut depth = vec![u32::MAX; count];
    for (i, &l) in label.iter().enumerate() {
        depth[l as usize] = depth[l as usize].min(pixel[i]);
    }
    depth
}

/// The figure a part placed over the pixels where `placed` holds, with the ring `ring` about
/// it, belongs to (see the module docs), as a mask; `None` when it would be the whole image or
/// nothing.
pub(crate) fn figure(
    pot: &ImagePotential,
    placed: impl Fn(DVec2) -> bool,
    ring: impl Fn(DVec2) -> bool,
) -> Option<Vec<bool>> {
    let (w, h) = (pot.width(), pot.height());
    let lum = pot.luminance();
    let inside: Vec<usize> = (0..w * h)
        .filter(|&i| placed(DVec2::new((i % w) as f64, (i / w) as f64)))
        .collect();
    if inside.is_empty() {
        return None;
    }
    let class: Vec<bool> = if pot.two_tone().is_some() {
        pot.foreground().to_vec()
    } else {
        // Otsu's threshold of the placed outline's pixels and of a ring about it as large.
        let window: Vec<f64> = (0..w * h)
            .filter(|&i| ring(DVec2::new((i % w) as f64, (i / w) as f64)))
            .map(|i| lum[i])
            .chain(inside.iter().map(|&i| lum[i]))
            .collect();
        let t = otsu_threshold(&window);
        match pot.colour() {
            Some(rgb) => {
                let samples = (0..w * h)
                    .filter(|&i| ring(DVec2::new((i % w) as f64, (i / w) as f64)))
                    .chain(inside.iter().copied());
                colour_classes(rgb, samples, |i| lum[i] > t)
            }
            None => lum.iter().map(|&v| v > t).collect(),
        }
    };
    let (label, count) = components(w, h, &class);
    let depth = depths(w, h, &label, count);
    let mut cover = std::collections::HashMap::<u32, usize>::new();
    for &i in &inside {
        *cover.entry(label[i]).or_default() += 1;
    }
    // The components covering the placement most first; among those covering about as much,
    // the deepest. The first that encloses something less than the whole image is the object.
    let mut order: Vec<(u32, usize)> = cover.into_iter().collect();
    order.sort_by_key(|&(l, n)| {
        (
            std::cmp::Reverse(n),
            std::cmp::Reverse(depth[l as usize]),
            l,
        )
    });
    order
        .into_iter()
        .find_map(|(object, _)| enclosed_by(w, h, &label, object))
}

/// The pixels component `object` encloses, itself included: those the flood from the border
/// that never enters it does not reach; `None` when that is the whole image or nothing.
fn enclosed_by(w: usize, h: usize, label: &[u32], object: u32) -> Option<Vec<bool>> {
    let mut ground = vec![false; w * h];
    let mut stack: Vec<usize> = (0..w * h)
        .filter(|&i| {
            let (c, r) = (i % w, i / w);
            (c == 0 || r == 0 || c + 1 == w || r + 1 == h) && label[i] != object
        })
        .collect();
    stack.iter().for_each(|&i| ground[i] = true);
    while let Some(i) = stack.pop() {
        for j in neighbours(w, h, i) {
            if !ground[j] && label[j] != object {
                ground[j] = true;
                stack.push(j);
            }
        }
    }
    let figure: Vec<bool> = ground.iter().map(|g| !g).collect();
    (figure.iter().any(|&f| f) && ground.iter().any(|&g| g)).then_some(figure)
}

/// The signed distance (pixels) to the boundary of `figure`, negative inside: half a pixel at
/// the pixels on either side of it.
pub(crate) fn signed_distance(width: usize, height: usize, figure: &[bool]) -> Raster {
    let to_figure = distance_transform(width, height, |i| figure[i]);
    let to_ground = distance_transform(width, height, |i| !figure[i]);
    let values = (0..width * height)
        .map(|i| {
            if figure[i] {
                0.5 - to_ground[i]
            } else {
                to_figure[i] - 0.5
            }
        })
        .collect();
    Raster {
        width,
        height,
        values,
    }
}

/// The signed distance to the figure a part placed over `placed` belongs to ([`figure`],
/// [`signed_distance`]).
pub(crate) fn figure_distance(
    pot: &ImagePotential,
    placed: impl Fn(DVec2) -> bool,
    ring: impl Fn(DVec2) -> bool,
) -> Option<Raster> {
    figure(pot, placed, ring).map(|f| signed_distance(pot.width(), pot.height(), &f))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_distance_transform_is_the_brute_force_distance() {
        let (w, h) = (13, 9);
        let feature = |i: usize| [5, 40, 41, 100].contains(&i);
        let d = distance_transform(w, h, feature);
        for i in 0..w * h {
            let p = DVec2::new((i % w) as f64, (i / w) as f64);
            let brute = [5usize, 40, 41, 100]
                .iter()
                .map(|&j| p.distance(DVec2::new((j % w) as f64, (j / w) as f64)))
                .fold(f64::INFINITY, f64::min);
            assert!((d[i] - brute).abs() < 1e-9, "{i}: {} vs {brute}", d[i]);
        }
    }

    #[test]
    fn the_raster_gradient_is_the_central_difference_between_pixels() {
        let r = Raster {
            width: 3,
            height: 3,
            values: vec![0.0, 1.0, 4.0, 2.0, 3.0, 7.0, 1.0, 5.0, 6.0],
        };
        let p = DVec2::new(0.7, 1.3);
        let (_, g) = r.sample(p);
        let h = 1e-6;
        let fd = |e: DVec2| (r.sample(p + e * h).0 - r.sample(p - e * h).0) / (2.0 * h);
        assert!((g.x - fd(DVec2::X)).abs() < 1e-6 && (g.y - fd(DVec2::Y)).abs() < 1e-6);
    }

    #[test]
    fn depth_counts_the_boundaries_crossed_from_the_border() {
        // A ring of 1s inside 0s, holding a 0 hole with a 1 dot: depths 0, 1, 2, 3.
        let (w, h) = (9, 9);
        let class: Vec<bool> = (0..w * h)
            .map(|i| {
                let (c, r) = ((i % w) as i32 - 4, (i / w) as i32 - 4);
                let m = c.abs().max(r.abs());
                m == 3 || m == 0
            })
            .collect();
        let (label, n) = components(w, h, &class);
        let d = depths(w, h, &label, n);
        let at = |c: usize, r: usize| d[label[r * w + c] as usize];
        assert_eq!((at(0, 0), at(1, 4), at(2, 4), at(4, 4)), (0, 1, 2, 3));
    }

    fn potential(w: usize, h: usize, lum: Vec<f64>) -> ImagePotential {
        ImagePotential::new(
            w,
            h,
            lum,
            1.0,
            crate::model::forces::image::ImageFrame::default(),
        )
        .unwrap()
    }

    #[test]
    fn the_figure_is_what_the_placement_lies_on_with_what_it_encloses() {
        // A dark square (columns and rows 20..60) with a light hole (35..45) on a light ground;
        // a placement half on the square, half on the ground.
        let (w, h) = (80, 80);
        let dark = |c: usize, r: usize| {
            let sq = (20..60).contains(&c) && (20..60).contains(&r);
            let hole = (35..45).contains(&c) && (35..45).contains(&r);
            sq && !hole
        };
        let lum = (0..w * h)
            .map(|i| if dark(i % w, i / w) { 0.1 } else { 0.9 })
            .collect();
        let pot = potential(w, h, lum);
        let placed = |q: DVec2| (q - DVec2::new(20.0, 40.0)).length() < 10.0;
        let ring = |q: DVec2| {
            let d = (q - DVec2::new(20.0, 40.0)).length();
            (10.0..14.2).contains(&d)
        };
        let f = figure(&pot, placed, ring).expect("a figure");
        for i in 0..w * h {
            let (c, r) = (i % w, i / w);
            let square = (20..60).contains(&c) && (20..60).contains(&r);
            assert_eq!(f[i], square, "pixel ({c}, {r})");
        }
    }

    #[test]
    fn colour_tells_apart_what_luminance_joins() {
        // A red disc on a grey ground of the same luminance.
        let (w, h) = (60, 60);
        let red = [0.8f32, 0.2, 0.2];
        let l = crate::model::forces::image::luminance_of(red.map(f64::from)) as f32;
        let inside = |i: usize| {
            (DVec2::new((i % w) as f64, (i / w) as f64) - DVec2::splat(30.0)).length() < 12.0
        };
        let rgb: Vec<[f32; 3]> = (0..w * h)
            .map(|i| if inside(i) { red } else { [l; 3] })
            .collect();
        let lum = rgb
            .iter()
            .map(|p| crate::model::forces::image::luminance_of(p.map(f64::from)))
            .collect();
        let grey = potential(w, h, lum);
        assert!(
            grey.clone()
                .with_colour(vec![[0.5; 3]; w * h])
                .unwrap()
                .colour()
                .is_none()
        );
        let pot = grey.with_colour(rgb).unwrap();
        let placed = |q: DVec2| (q - DVec2::splat(30.0)).length() < 9.0;
        let ring = |q: DVec2| (9.0..12.7).contains(&(q - DVec2::splat(30.0)).length());
        let f = figure(&pot, placed, ring).expect("a figure");
        assert!((0..w * h).all(|i| f[i] == inside(i)));
    }
}
