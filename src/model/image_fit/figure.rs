//! The figure a part was placed on, and its signed distance.
//!
//! **The figure on a photo is what the clicks lie on, bounded by edges** (the [`watershed`]).
//! The placed outline shrunk to half is the object's seed, and all beyond it grown 1.75 times is
//! its surroundings' seed. Both flood the image's relief (‖∇(G_σ ∗ I)‖ over the colour channels,
//! [`ImagePotential::relief`]) as its level rises, and they meet on the strongest edge between
//! them. So the faces of a box stay one figure however they differ in brightness, and a face as
//! bright as the desk is bounded by whatever edge it has. The figure is the object's flood with
//! what it encloses.
//!
//! **On a silhouette, what encloses what.** When the image is two-toned and so are the part's
//! surroundings (Otsu's two classes hold 90 % of the variance, [`crate::model::forces::image::TWO_TONE`]), the figure is the
//! component of the image's two classes that covers most of the placed outline and encloses
//! something less than the whole image, with everything it encloses: a leg placed half off a
//! horse is the horse (the background around it encloses everything), and a body's limb lies on
//! the body's figure, which reaches past the limb's surroundings.
//! [`figure_distance`] is the figure's signed distance, negative inside.

use super::evidence::{Raster, signed_distance};
use super::outline::{Area, MAX_GROWTH, Outline};
use crate::model::forces::image::{ImagePotential, two_toned};
use glam::DVec2;
use std::collections::VecDeque;

/// A figure covering more than this share of the pixels a part can reach is no figure of the
/// part: it fills its reach, so it cannot tell where the part ends (nothing bounded it). Nor is, on a photo (not two-tone), a figure larger than the
/// part may grow ([`MAX_GROWTH`] times its placed area). The part is then fitted to the edges
/// alone.
pub const FILLED: f64 = 0.9;

/// The object's seed for its figure on a photo: the placed outline shrunk by this factor. Swept
/// over 0.4–0.8 on the generated photos and the coins (docs/results.md): the largest that keeps
/// every coin clicked up to half a radius off on its coin (at 0.8 one is seeded past its rim).
pub const CORE: f64 = 0.7;

/// The surroundings' seed for a part's figure on a photo: all outside the placed outline grown
/// by this factor, past where a box's corners reach from its placement (√2 × its axes' 2σ ends,
/// less a quarter off).
pub const GROUND: f64 = 1.75;

/// The part placed as `placed`: its figure's signed distance ([`figure_distance`]) and its area
/// term's pixels ([`Area`]), seeded by the placed outline shrunk by [`CORE`] and all beyond it
/// grown by [`GROUND`]; `None` without a figure, or with one that fills the part's reach
/// ([`FILLED`]) or, on a photo, is larger than the part may grow.
pub(super) fn part_figure(
    pot: &ImagePotential,
    relief: &[f64],
    placed: &Outline,
) -> Option<(Raster, Area)> {
    let sigma = pot.sigma();
    let scaled = |k: f64| Outline {
        r: placed.r.map(|r| r * k),
        ..*placed
    };
    let (core, reach) = (scaled(CORE), scaled(GROUND));
    figure_distance(
        pot,
        relief,
        |q| placed.contains(q),
        |q| core.contains(q),
        |q| !reach.contains(q),
    )
    .map(|f| {
        let a = Area::about(placed, &f, sigma, (pot.width(), pot.height()));
        (f, a)
    })
    .filter(|(f, a)| {
        // A figure that fills the part's whole reach cannot tell where it ends; on a photo,
        // neither can one larger than the part may grow.
        let n = a.membership.len().max(1) as f64;
        let placed_area = std::f64::consts::PI * placed.r[0] * placed.r[1];
        a.membership.iter().sum::<f64>() / n < FILLED
            && (pot.two_tone().is_some() || (f.inside_count() as f64) <= MAX_GROWTH * placed_area)
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

/// The figure a part placed over the pixels where `placed` holds belongs to (see the module
/// docs), as a mask; `None` when it would be the whole image or nothing. On a two-tone image it
/// is what encloses what among the image's two classes; on a photo, the [`watershed`] of the
/// image's `relief` ([`ImagePotential::relief`]) from the seeds `core` (the object's) and
/// `ground` (its surroundings').
pub(crate) fn figure(
    pot: &ImagePotential,
    relief: &[f64],
    placed: impl Fn(DVec2) -> bool,
    core: impl Fn(DVec2) -> bool,
    ground: impl Fn(DVec2) -> bool,
) -> Option<Vec<bool>> {
    let (w, h) = (pot.width(), pot.height());
    let at = |i: usize| DVec2::new((i % w) as f64, (i / w) as f64);
    // A silhouette is two tones about the part as well as on the whole image; a photo with a
    // plain ground may be two tones on the whole, and many about an object of several faces.
    let lum = pot.luminance();
    let about: Vec<f64> = (0..w * h)
        .filter(|&i| !ground(at(i)))
        .map(|i| lum[i])
        .collect();
    if pot.two_tone().is_none() || !two_toned(&about) {
        let seeds: Vec<u8> = (0..w * h)
            .map(|i| {
                let p = at(i);
                if core(p) {
                    OBJECT_LABEL
                } else if ground(p) {
                    GROUND_LABEL
                } else {
                    0
                }
            })
            .collect();
        if !seeds.contains(&OBJECT_LABEL) || !seeds.contains(&GROUND_LABEL) {
            return None;
        }
        let label = watershed(w, h, relief, seeds);
        // The object's pixels with what they enclose.
        let class: Vec<u32> = label
            .iter()
            .map(|&l| u32::from(l == OBJECT_LABEL))
            .collect();
        return enclosed_by(w, h, &class, 1);
    }
    let inside: Vec<usize> = (0..w * h).filter(|&i| placed(at(i))).collect();
    if inside.is_empty() {
        return None;
    }
    let class = pot.foreground().to_vec();
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

/// A watershed label: the object's.
const OBJECT_LABEL: u8 = 1;
/// A watershed label: the surroundings'.
const GROUND_LABEL: u8 = 2;

/// Meyer's seeded watershed: every pixel not labelled in `label` (0) takes the label of the seed
/// whose flood reaches it first as the level rises over `relief`, so two labels meet along the
/// highest ridge between them: the strongest edge that separates the seeds, however bright
/// either side is.
fn watershed(w: usize, h: usize, relief: &[f64], mut label: Vec<u8>) -> Vec<u8> {
    use std::cmp::Reverse;
    use std::collections::BinaryHeap;
    // Levels are non-negative, so their bits order as the levels do; ties go first in, first out.
    let mut heap = BinaryHeap::new();
    let mut order = 0u64;
    for i in (0..w * h).filter(|&i| label[i] != 0) {
        for j in neighbours(w, h, i) {
            if label[j] == 0 {
                heap.push(Reverse((relief[j].max(0.0).to_bits(), order, j, label[i])));
                order += 1;
            }
        }
    }
    while let Some(Reverse((_, _, i, l))) = heap.pop() {
        if label[i] != 0 {
            continue;
        }
        label[i] = l;
        for j in neighbours(w, h, i) {
            if label[j] == 0 {
                heap.push(Reverse((relief[j].max(0.0).to_bits(), order, j, l)));
                order += 1;
            }
        }
    }
    label
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

/// The signed distance to the figure a part placed over `placed` belongs to ([`figure`],
/// [`signed_distance`]).
pub(crate) fn figure_distance(
    pot: &ImagePotential,
    relief: &[f64],
    placed: impl Fn(DVec2) -> bool,
    core: impl Fn(DVec2) -> bool,
    ground: impl Fn(DVec2) -> bool,
) -> Option<Raster> {
    figure(pot, relief, placed, core, ground)
        .map(|f| signed_distance(pot.width(), pot.height(), &f))
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let f = figure(&pot, &pot.relief(), placed, |_| false, |_| false).expect("a figure");
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
        let r = |q: DVec2| (q - DVec2::splat(30.0)).length();
        let f = figure(
            &pot,
            &pot.relief(),
            |q| r(q) < 9.0,
            |q| r(q) < 4.5,
            |q| r(q) > 16.0,
        )
        .expect("a figure");
        assert!((0..w * h).all(|i| f[i] == inside(i)));
    }

    #[test]
    fn faces_as_bright_as_the_ground_belong_to_the_figure_the_seeds_lie_on() {
        // A square (columns and rows 20..60) of three faces, 0.15, 0.35 and 0.58, on a ground of
        // 0.6 (the third face 2 % of the range from it, the faces 20 % from each other), and a
        // darker square elsewhere on the ground. One threshold joins the third face to the
        // ground; the watershed keeps the square whole.
        let (w, h) = (100, 80);
        let lum: Vec<f64> = (0..w * h)
            .map(|i| {
                let (c, r) = (i % w, i / w);
                match ((20..60).contains(&c), (20..60).contains(&r)) {
                    (true, true) if r < 40 => 0.58,
                    (true, true) if c < 40 => 0.15,
                    (true, true) => 0.35,
                    _ if (75..90).contains(&c) && (30..45).contains(&r) => 0.3,
                    _ if (70..95).contains(&c) && (55..75).contains(&r) => 0.95,
                    _ if (70..95).contains(&c) && (3..20).contains(&r) => 0.02,
                    _ => 0.6,
                }
            })
            .collect();
        let pot = potential(w, h, lum);
        assert!(pot.two_tone().is_none());
        let r = |q: DVec2| (q - DVec2::new(41.0, 39.0)).length();
        let f = figure(
            &pot,
            &pot.relief(),
            |q| r(q) < 20.0,
            |q| r(q) < 9.0,
            |q| r(q) > 33.0,
        )
        .expect("a figure");
        let wrong = (0..w * h)
            .filter(|&i| f[i] != ((20..60).contains(&(i % w)) && (20..60).contains(&(i / w))))
            .count();
        assert!(
            wrong <= 80,
            "{wrong} pixels on the wrong side (the square has 1600)"
        );
    }
}
