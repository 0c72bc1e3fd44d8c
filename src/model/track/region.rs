//! The object inside a user's pixel box: the surface the box is drawn around.
//!
//! A box drawn around an object also holds what lies behind it and beside it (a second object, a
//! wall, the floor). The object is the piece of surface that fills the box's middle: the box's
//! pixels are split into pieces of continuous depth (4-neighbours whose depths differ by less
//! than a jump), and the piece with the most pixels in the box's central half is kept.

use super::camera::DepthFrame;
use glam::DVec3;

/// The camera-frame points of the piece of continuous surface that fills the middle of the box
/// [u0, u1) × [v0, v1) (clipped to the image): pixels with depth for which `keep` holds, joined
/// to a 4-neighbour when their depths differ by less than `jump(z)` metres at depth z.
pub fn object_region(
    frame: &DepthFrame,
    (u0, v0, u1, v1): (usize, usize, usize, usize),
    keep: impl Fn(DVec3) -> bool,
    jump: impl Fn(f64) -> f64,
) -> Vec<DVec3> {
    let c = &frame.intrinsics;
    let (u1, v1) = (u1.min(c.width as usize), v1.min(c.height as usize));
    if u0 >= u1 || v0 >= v1 {
        return Vec::new();
    }
    let (w, h) = (u1 - u0, v1 - v0);
    // Each kept pixel's point; None for no depth or not kept.
    let points: Vec<Option<DVec3>> = (0..w * h)
        .map(|k| {
            let (u, v) = (u0 + k % w, v0 + k / w);
            let z = frame.at(u, v);
            (z > 0.0 && z.is_finite())
                .then(|| c.back_project(u as f64, v as f64, z))
                .filter(|p| keep(*p))
        })
        .collect();
    // Pieces by flood fill over 4-neighbours of continuous depth.
    let mut label = vec![usize::MAX; w * h];
    let mut pieces: Vec<Vec<usize>> = Vec::new();
    let mut stack = Vec::new();
    for seed in 0..w * h {
        if points[seed].is_none() || label[seed] != usize::MAX {
            continue;
        }
        let id = pieces.len();
        let mut piece = Vec::new();
        label[seed] = id;
        stack.push(seed);
        while let Some(k) = stack.pop() {
            piece.push(k);
            let z = points[k].map_or(0.0, |p| p.z);
            let (x, y) = (k % w, k / w);
            let neighbours = [
                (x > 0).then(|| k - 1),
                (x + 1 < w).then_some(k + 1),
                (y > 0).then(|| k - w),
                (y + 1 < h).then_some(k + w),
            ];
            for n in neighbours.into_iter().flatten() {
                if label[n] == usize::MAX
                    && let Some(q) = points[n]
                    && (q.z - z).abs() < jump(z.min(q.z))
                {
                    label[n] = id;
                    stack.push(n);
                }
            }
        }
        pieces.push(piece);
    }
    // The piece with the most pixels in the central half of the box.
    let central = |k: &usize| {
        let (x, y) = (k % w, k / w);
        4 * x >= w && 4 * x < 3 * w && 4 * y >= h && 4 * y < 3 * h
    };
    let best = pieces.iter().enumerate().max_by_key(|(i, p)| {
        (
            p.iter().filter(|k| central(k)).count(),
            p.len(),
            usize::MAX - i,
        )
    });
    best.map(|(_, p)| p.iter().filter_map(|&k| points[k]).collect())
        .unwrap_or_default()
}

/// The depth noise σ the box shows, metres: from the median step between horizontal
/// neighbours with depth (1.4826·median|Δz|/√2; a surface's slope adds to it). 0 for none.
pub fn step_noise(frame: &DepthFrame, (u0, v0, u1, v1): (usize, usize, usize, usize)) -> f64 {
    let c = &frame.intrinsics;
    let (u1, v1) = (u1.min(c.width as usize), v1.min(c.height as usize));
    let mut steps = Vec::new();
    for v in v0..v1 {
        for u in u0..u1.saturating_sub(1) {
            let (a, b) = (frame.at(u, v), frame.at(u + 1, v));
            if a > 0.0 && b > 0.0 {
                steps.push((a - b).abs());
            }
        }
    }
    if steps.is_empty() {
        return 0.0;
    }
    let mid = steps.len() / 2;
    let median = *steps.select_nth_unstable_by(mid, f64::total_cmp).1;
    1.4826 * median / std::f64::consts::SQRT_2
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::track::Intrinsics;

    #[test]
    fn the_piece_in_the_middle_is_kept_and_the_one_behind_dropped() {
        let camera = Intrinsics {
            width: 40,
            height: 30,
            fx: 50.0,
            fy: 50.0,
            cx: 19.5,
            cy: 14.5,
        };
        // A wall at 2 m, a block at 1 m over the middle, a sloping ramp at the top rows.
        let mut depth = vec![2.0f32; 40 * 30];
        for v in 8..22 {
            for u in 12..28 {
                depth[v * 40 + u] = 1.0 + 0.005 * u as f32;
            }
        }
        for u in 0..40 {
            depth[u] = 0.0;
        }
        let frame = DepthFrame {
            intrinsics: camera,
            depth,
        };
        let region = object_region(&frame, (5, 3, 35, 27), |_| true, |z| 0.05 * z);
        assert_eq!(region.len(), 14 * 16);
        assert!(region.iter().all(|p| p.z < 1.2));
        // Pixels that `keep` refuses are not part of any piece.
        let none = object_region(&frame, (5, 3, 35, 27), |p| p.z > 1.5, |z| 0.05 * z);
        assert!(none.iter().all(|p| p.z > 1.5));
        // A box outside the image holds nothing.
        assert!(object_region(&frame, (50, 40, 60, 50), |_| true, |_| 1.0).is_empty());
    }
}
