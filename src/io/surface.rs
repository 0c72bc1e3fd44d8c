//! A mesh read as its surface: the faces of an OBJ or PLY file, and points spread uniformly by
//! area over them ([`sample_surface`]). A mesh's vertices crowd where its modeller added detail
//! (a head, a hand) and thin out over large flat faces; a fit to them would weigh the detail
//! many times over. Samples by area weigh every part of the surface by how much of it there is.

use super::{IoError, err};
use glam::DVec3;
use std::path::Path;

/// How many points a mesh's surface is read as, unless a caller asks for another count: enough
/// that a limb a hundredth of the surface still carries a hundred points.
pub const MESH_SAMPLES: usize = 10_000;

/// The most points a mesh may be sampled to (8 bytes × 3 a point: 2.4 GB).
pub const MAX_MESH_SAMPLES: usize = 100_000_000;

/// The triangles of an OBJ file's `f` lines (polygons fanned from their first corner), as
/// 0-based indices into its `vertices` `v` lines. `f` corners are `i`, `i/t`, `i//n` or `i/t/n`;
/// a negative `i` counts back from the last vertex read before its line. Errors name the line.
pub(super) fn obj_faces(
    path: &Path,
    text: &str,
    vertices: usize,
) -> Result<Vec<[u32; 3]>, IoError> {
    let mut seen = 0usize;
    let mut triangles = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => seen += 1,
            Some("f") => {
                let corners = words
                    .map(|w| obj_index(w, seen, vertices))
                    .collect::<Option<Vec<u32>>>()
                    .filter(|c| c.len() >= 3)
                    .ok_or_else(|| {
                        err(
                            path,
                            format!(
                                "line {}: expected `f i j k` with at least three vertex indices in [1, {vertices}] (or negative, counting back), found {:?}",
                                n + 1,
                                line.trim()
                            ),
                        )
                    })?;
                for k in 1..corners.len() - 1 {
                    triangles.push([corners[0], corners[k], corners[k + 1]]);
                }
            }
            _ => {}
        }
    }
    Ok(triangles)
}

/// One `f` corner's vertex (0-based), or `None` when it is not an index of the file's vertices.
fn obj_index(word: &str, seen: usize, vertices: usize) -> Option<u32> {
    let i: i64 = word.split('/').next()?.parse().ok()?;
    let zero_based = match i {
        0 => return None,
        i if i > 0 => i - 1,
        i => seen as i64 + i,
    };
    (0..vertices as i64)
        .contains(&zero_based)
        .then(|| u32::try_from(zero_based).ok())
        .flatten()
}

/// A PLY face as the parser reads it: its `vertex_indices` (or `vertex_index`) list.
pub(super) struct PlyFace(pub(super) Option<Vec<i64>>);

impl ply_rs_bw::ply::PropertyAccess for PlyFace {
    fn new() -> Self {
        Self(None)
    }

    fn set_property(
        &mut self,
        name: &str,
        property: ply_rs_bw::ply::Property,
    ) -> ply_rs_bw::ply::PropertyAccessResult {
        use ply_rs_bw::ply::{Property, PropertyAccessResult};
        if name != "vertex_indices" && name != "vertex_index" {
            return PropertyAccessResult::Ignored;
        }
        let list: Vec<i64> = match property {
            Property::ListChar(v) => v.into_iter().map(i64::from).collect(),
            Property::ListUChar(v) => v.into_iter().map(i64::from).collect(),
            Property::ListShort(v) => v.into_iter().map(i64::from).collect(),
            Property::ListUShort(v) => v.into_iter().map(i64::from).collect(),
            Property::ListInt(v) => v.into_iter().map(i64::from).collect(),
            Property::ListUInt(v) => v.into_iter().map(i64::from).collect(),
            _ => return PropertyAccessResult::Ignored,
        };
        self.0 = Some(list);
        PropertyAccessResult::Set
    }
}

/// The triangles of a PLY file's faces (fanned), checked against its `vertices`. Errors name
/// the face.
pub(super) fn ply_faces(
    path: &Path,
    faces: &[PlyFace],
    vertices: usize,
) -> Result<Vec<[u32; 3]>, IoError> {
    let mut triangles = Vec::new();
    for (f, face) in faces.iter().enumerate() {
        let corners: Option<Vec<u32>> = face.0.as_ref().and_then(|list| {
            list.iter()
                .map(|&i| {
                    (0..vertices as i64)
                        .contains(&i)
                        .then(|| u32::try_from(i).ok())
                        .flatten()
                })
                .collect::<Option<Vec<u32>>>()
                .filter(|c| c.len() >= 3)
        });
        let Some(corners) = corners else {
            return Err(err(
                path,
                format!(
                    "face {}: expected a `vertex_indices` list of at least three indices in [0, {}]",
                    f + 1,
                    vertices.saturating_sub(1)
                ),
            ));
        };
        for k in 1..corners.len() - 1 {
            triangles.push([corners[0], corners[k], corners[k + 1]]);
        }
    }
    Ok(triangles)
}

/// `count` points spread uniformly by area over the triangles `triangles` of `vertices`, or
/// `None` when the triangles have no area (all degenerate). Deterministic: the triangles are
/// chosen by systematic sampling of their cumulative area (sample s at (s + ½)/count of it, so
/// a triangle with a share a of the area gets ⌊a · count⌋ or one more), and the place within a
/// triangle by the plastic-number (R2) low-discrepancy sequence, warped to be uniform by area.
pub fn sample_surface(
    vertices: &[DVec3],
    triangles: &[[u32; 3]],
    count: usize,
) -> Option<Vec<DVec3>> {
    let corners = |t: &[u32; 3]| t.map(|i| vertices[i as usize]);
    let mut cumulative = Vec::with_capacity(triangles.len());
    let mut total = 0.0;
    for t in triangles {
        let [a, b, c] = corners(t);
        total += 0.5 * (b - a).cross(c - a).length();
        cumulative.push(total);
    }
    if !(total > 0.0 && total.is_finite()) || count == 0 {
        return None;
    }
    // R2: the additive recurrence on 1/φ₂ and 1/φ₂² (φ₂ the plastic number).
    const G: f64 = 1.324_717_957_244_746;
    let (r1, r2) = (1.0 / G, 1.0 / (G * G));
    let mut out = Vec::with_capacity(count);
    let mut t = 0;
    for s in 0..count {
        let at = (s as f64 + 0.5) / count as f64 * total;
        while t + 1 < cumulative.len() && cumulative[t] < at {
            t += 1;
        }
        let [a, b, c] = corners(&triangles[t]);
        let u = (0.5 + r1 * s as f64).fract();
        let v = (0.5 + r2 * s as f64).fract();
        let su = u.sqrt();
        out.push(a * (1.0 - su) + b * (su * (1.0 - v)) + c * (su * v));
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_spread_by_area_not_by_vertex() {
        // Two squares side by side, the right one 3× as wide, and the left one cut into many
        // small triangles: its vertices crowd, its area does not.
        let mut v = vec![];
        let mut t = vec![];
        let n = 10;
        for i in 0..=n {
            for j in 0..=n {
                v.push(DVec3::new(i as f64 / n as f64, j as f64 / n as f64, 0.0));
            }
        }
        for i in 0..n {
            for j in 0..n {
                let k = (i * (n + 1) + j) as u32;
                let s = (n + 1) as u32;
                t.push([k, k + s, k + 1]);
                t.push([k + 1, k + s, k + s + 1]);
            }
        }
        let base = v.len() as u32;
        v.extend([
            DVec3::new(1.0, 0.0, 0.0),
            DVec3::new(4.0, 0.0, 0.0),
            DVec3::new(4.0, 1.0, 0.0),
            DVec3::new(1.0, 1.0, 0.0),
        ]);
        t.push([base, base + 1, base + 2]);
        t.push([base, base + 2, base + 3]);
        let p = sample_surface(&v, &t, 4000).expect("area");
        assert_eq!(p.len(), 4000);
        let left = p.iter().filter(|q| q.x < 1.0).count();
        assert!(
            (left as i64 - 1000).abs() <= 2,
            "{left} of 4000 on a quarter of the area"
        );
        // Uniform within the wide square too: each of its three unit cells gets a third.
        for cell in 1..4 {
            let c = p
                .iter()
                .filter(|q| q.x >= cell as f64 && q.x < cell as f64 + 1.0)
                .count();
            assert!((c as i64 - 1000).abs() < 40, "cell {cell}: {c}");
        }
        assert!(p.iter().all(|q| q.y >= 0.0 && q.y <= 1.0 && q.z == 0.0));
        // The same input gives the same points.
        assert_eq!(p, sample_surface(&v, &t, 4000).expect("area"));
        // No area: none.
        assert_eq!(sample_surface(&v, &[[0, 0, 1]], 10), None);
    }

    #[test]
    fn obj_faces_take_every_corner_form_and_name_a_bad_line() {
        let path = Path::new("m.obj");
        let text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1/1 2//3 3/4/5 -1\n";
        let t = obj_faces(path, text, 4).expect("faces");
        assert_eq!(t, vec![[0, 1, 2], [0, 2, 3]]);
        for bad in ["f 1 2 9", "f 1 2", "f 0 1 2", "f a b c", "f -5 1 2"] {
            let text = format!("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n{bad}\n");
            let e = obj_faces(path, &text, 4).unwrap_err().to_string();
            assert!(e.starts_with("m.obj: line 5: expected `f i j k`"), "{e}");
            assert_eq!(e.lines().count(), 1);
        }
    }
}
