//! The edges the solved image fit reads: where they are, and the distance to them.
//!
//! **Edges** are Canny's: the potential P = ‖∇(G_σ ∗ I)‖ thinned to its maxima across the edge
//! (non-maximum suppression along ∇(G_σ ∗ I)), kept where P ≥ [`EDGE_LOW`] P_ref and connected to
//! a pixel with P ≥ [`EDGE_HIGH`] P_ref (hysteresis). [`edge_distance`] is the Euclidean distance
//! transform of that edge map (Felzenszwalb and Huttenlocher's exact one).
//!

use crate::model::forces::image::ImagePotential;
use glam::DVec2;

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
}
