//! Reading point clouds and writing fitted models.
//!
//! * [`load_points`]: an OBJ file (vertices parsed by `tobj`) or a PLY file (ascii or binary,
//!   `x y z` vertex properties; parsed by `ply-rs-bw`). A file with faces is a mesh, read as
//!   [`MESH_SAMPLES`] points spread uniformly by area over its surface ([`sample_surface`]); a
//!   file without is a point cloud, read as its vertices.
//! * [`write_obj`]: a closed triangle mesh.
//! * [`load_depth_png`], [`load_intrinsics`]: a depth video's frames (16-bit PNG) and its
//!   camera (Open3D's intrinsics JSON).
//!
//! Every error names the file and says what is wrong, with the line where there is one.

use crate::model::dynamics::ModelState;
use crate::model::fem::Tessellation;
use glam::DVec3;
use std::fmt;
use std::path::{Path, PathBuf};

mod depth;
mod surface;
mod track;
pub use depth::{
    PRIMESENSE_DEFAULT, decode_depth_png, load_depth_png, load_intrinsics, parse_intrinsics,
    write_depth_png, write_track_png,
};
pub use surface::{MAX_MESH_SAMPLES, MESH_SAMPLES, sample_surface};
pub use track::{pose_from_json, track_line};

/// A file that could not be read as points, or written.
#[derive(Debug, Clone, PartialEq)]
pub struct IoError {
    /// The file.
    pub path: PathBuf,
    /// What is wrong, with the line number where one applies.
    pub message: String,
}

impl fmt::Display for IoError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.path.display(), self.message)
    }
}

impl std::error::Error for IoError {}

/// An error on one line: parser messages that span lines are folded with "; ".
fn err(path: &Path, message: impl Into<String>) -> IoError {
    let message: String = message.into();
    let one_line = message
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect::<Vec<_>>()
        .join("; ");
    IoError {
        path: path.to_path_buf(),
        message: one_line,
    }
}

/// Reads a point cloud from an `.obj` or `.ply` file (by extension, case-insensitive): its
/// vertices, or, when it has faces, [`MESH_SAMPLES`] points spread by area over them
/// ([`load_points_sampled`] takes another count). Fails on a missing file, a directory, an
/// unreadable or empty file, text that is not numbers, NaN or infinite coordinates, a face
/// whose indices are not the file's vertices, and faces without area.
pub fn load_points(path: &Path) -> Result<Vec<DVec3>, IoError> {
    load_points_sampled(path, MESH_SAMPLES)
}

/// [`load_points`], a mesh read as `samples` points (1 to [`MAX_MESH_SAMPLES`]).
pub fn load_points_sampled(path: &Path, samples: usize) -> Result<Vec<DVec3>, IoError> {
    if path.is_dir() {
        return Err(err(path, "is a directory, not a point file"));
    }
    let bytes = std::fs::read(path).map_err(|e| err(path, format!("cannot read: {e}")))?;
    decode_points_sampled(path, &bytes, samples)
}

/// Parses the bytes of an `.obj` or `.ply` point file (the format by `path`'s extension, which
/// also names the source in errors); see [`load_points`].
pub fn decode_points(path: &Path, bytes: &[u8]) -> Result<Vec<DVec3>, IoError> {
    decode_points_sampled(path, bytes, MESH_SAMPLES)
}

/// [`decode_points`], a mesh read as `samples` points (1 to [`MAX_MESH_SAMPLES`]).
pub fn decode_points_sampled(
    path: &Path,
    bytes: &[u8],
    samples: usize,
) -> Result<Vec<DVec3>, IoError> {
    if !(1..=MAX_MESH_SAMPLES).contains(&samples) {
        return Err(err(
            path,
            format!("mesh samples = {samples} is out of range [1, {MAX_MESH_SAMPLES}]"),
        ));
    }
    if bytes.iter().all(|b| b.is_ascii_whitespace()) {
        return Err(err(path, "the file is empty"));
    }
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let (points, triangles) = match ext.as_str() {
        "obj" => load_obj(path, bytes)?,
        "ply" => load_ply(path, bytes)?,
        _ => {
            return Err(err(
                path,
                format!("unsupported extension {ext:?}: expected .obj or .ply"),
            ));
        }
    };
    if points.is_empty() {
        return Err(err(path, "contains no points"));
    }
    if triangles.is_empty() {
        return Ok(points);
    }
    sample_surface(&points, &triangles, samples)
        .ok_or_else(|| err(path, format!("its {} faces have no area", triangles.len())))
}

/// A file's vertices and its faces' triangles (none for a point cloud).
type Parsed = (Vec<DVec3>, Vec<[u32; 3]>);

/// Parses OBJ vertices with tobj, and faces ([`surface`]). tobj only returns vertices that
/// elements reference, so every `v` line is followed by a one-vertex element `l -1` that
/// references it; faces are left out of what tobj reads.
fn load_obj(path: &Path, bytes: &[u8]) -> Result<Parsed, IoError> {
    let text =
        std::str::from_utf8(bytes).map_err(|e| err(path, format!("not UTF-8 text ({e})")))?;
    let mut augmented = String::with_capacity(text.len() * 2);
    let mut vertex_lines = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => {
                let coords: Vec<&str> = words.collect();
                let numeric =
                    coords.len() >= 3 && coords[..3].iter().all(|w| w.parse::<f64>().is_ok());
                if !numeric {
                    return Err(err(
                        path,
                        format!(
                            "line {}: expected `v x y z` with three numbers, found {:?}",
                            n + 1,
                            line.trim()
                        ),
                    ));
                }
                vertex_lines.push(n + 1);
                augmented.push_str(line);
                augmented.push_str("\nl -1\n");
            }
            // Faces, lines, groups and materials are not points: leave them out.
            Some("f" | "l" | "p" | "mtllib" | "usemtl") => {}
            _ => {
                augmented.push_str(line);
                augmented.push('\n');
            }
        }
    }
    if vertex_lines.is_empty() {
        return Err(err(path, "contains no `v` vertex lines"));
    }
    let options = tobj::LoadOptions {
        single_index: true,
        ignore_points: false,
        ignore_lines: false,
        ..Default::default()
    };
    let (models, _) = tobj::load_obj_buf(&mut augmented.as_bytes(), &options, |_| {
        Err(tobj::LoadError::OpenFileFailed)
    })
    .map_err(|e| err(path, format!("OBJ parse error: {e}")))?;
    let positions: Vec<f64> = models.into_iter().flat_map(|m| m.mesh.positions).collect();
    let points: Vec<DVec3> = positions
        .chunks_exact(3)
        .map(|c| DVec3::new(c[0], c[1], c[2]))
        .collect();
    if points.len() != vertex_lines.len() {
        return Err(err(
            path,
            format!("read {} of {} vertices", points.len(), vertex_lines.len()),
        ));
    }
    if let Some(i) = points.iter().position(|p| !p.is_finite()) {
        return Err(err(
            path,
            format!(
                "line {}: vertex {} has a NaN or infinite coordinate",
                vertex_lines[i],
                i + 1
            ),
        ));
    }
    let triangles = surface::obj_faces(path, text, points.len())?;
    Ok((points, triangles))
}

/// The PLY parser's error in one short line: its first sentence ("Line 9: Couldn't read element
/// line.") and the offending text, cut to 60 printable characters, without the parser's internals.
fn ply_message(raw: &str) -> String {
    let first = raw
        .lines()
        .next()
        .unwrap_or(raw)
        .trim()
        .trim_end_matches('.');
    let quoted = raw
        .split_once("String: '")
        .map(|(_, rest)| rest.split('\'').next().unwrap_or(rest))
        .map(|text| {
            let clean: String = text
                .trim()
                .chars()
                .map(|c| if c.is_control() { ' ' } else { c })
                .take(60)
                .collect();
            format!(" (`{clean}`)")
        })
        .unwrap_or_default();
    match first.strip_prefix("Line ") {
        Some(rest) => format!("PLY line {rest}{quoted}"),
        None => format!("PLY parse error: {first}{quoted}"),
    }
}

/// A PLY vertex as the parser reads it: its x, y and z when they are scalars, every other
/// property ignored (no map a vertex, so a million-point cloud reads in tens of megabytes).
struct PlyVertex([Option<f64>; 3]);

impl ply_rs_bw::ply::PropertyAccess for PlyVertex {
    fn new() -> Self {
        Self([None; 3])
    }

    fn set_property(
        &mut self,
        name: &str,
        property: ply_rs_bw::ply::Property,
    ) -> ply_rs_bw::ply::PropertyAccessResult {
        use ply_rs_bw::ply::{Property, PropertyAccessResult};
        let Some(k) = ["x", "y", "z"].iter().position(|n| *n == name) else {
            return PropertyAccessResult::Ignored;
        };
        let value = match property {
            Property::Char(v) => v as f64,
            Property::UChar(v) => v as f64,
            Property::Short(v) => v as f64,
            Property::UShort(v) => v as f64,
            Property::Int(v) => v as f64,
            Property::UInt(v) => v as f64,
            Property::Float(v) => v as f64,
            Property::Double(v) => v,
            _ => return PropertyAccessResult::Ignored,
        };
        self.0[k] = Some(value);
        PropertyAccessResult::Set
    }
}

/// An element of a PLY file that is not the vertices: read past, kept nowhere.
struct PlySkipped;

impl ply_rs_bw::ply::PropertyAccess for PlySkipped {
    fn new() -> Self {
        Self
    }
}

fn load_ply(path: &Path, bytes: &[u8]) -> Result<Parsed, IoError> {
    use ply_rs_bw::parser::{Parser, Reader};
    let bad = |e: ply_rs_bw::parser::ParseError| err(path, ply_message(&e.to_string()));
    let mut reader = Reader::new(std::io::Cursor::new(bytes));
    let header = Parser::<PlySkipped>::new()
        .read_header(&mut reader)
        .map_err(bad)?;
    let mut vertices = None;
    let mut faces = Vec::new();
    // Elements are read in the header's order; the vertices and the faces are usually first,
    // and nothing after them is needed.
    for def in header.elements.values() {
        if def.name == "vertex" {
            let parser = Parser::<PlyVertex>::new();
            vertices = Some(
                parser
                    .read_payload_for_element(&mut reader, def, &header)
                    .map_err(bad)?,
            );
        } else if def.name == "face" {
            faces = Parser::<surface::PlyFace>::new()
                .read_payload_for_element(&mut reader, def, &header)
                .map_err(bad)?;
        } else {
            Parser::<PlySkipped>::new()
                .read_payload_for_element(&mut reader, def, &header)
                .map_err(bad)?;
        }
        if vertices.is_some() && (!faces.is_empty() || !header.elements.contains_key("face")) {
            break;
        }
    }
    let Some(vertices) = vertices else {
        return Err(err(path, "has no `vertex` element"));
    };
    let mut points = Vec::with_capacity(vertices.len());
    for (i, v) in vertices.iter().enumerate() {
        let mut c = [0.0; 3];
        for (k, name) in ["x", "y", "z"].iter().enumerate() {
            c[k] = v.0[k].ok_or_else(|| {
                err(
                    path,
                    format!("vertex {}: no scalar property `{name}`", i + 1),
                )
            })?;
        }
        let p = DVec3::from_array(c);
        if !p.is_finite() {
            return Err(err(
                path,
                format!("vertex {} has a NaN or infinite coordinate", i + 1),
            ));
        }
        points.push(p);
    }
    let triangles = surface::ply_faces(path, &faces, points.len())?;
    Ok((points, triangles))
}

/// A decoded image as row-major luminance in [0, 1] (row 0 at the top): width, height, values.
pub type Luminance = (usize, usize, Vec<f64>);

/// An image as width, height, luminance in [0, 1] and its RGB in [0, 1], row-major.
pub type Pixels = (usize, usize, Vec<f64>, Vec<[f32; 3]>);

/// Decodes PNG or JPEG bytes (format sniffed from the contents) to luminance (Rec. 709 weights;
/// alpha ignored) and RGB. `path` only names the source in errors.
pub fn decode_image(path: &Path, bytes: &[u8]) -> Result<Pixels, IoError> {
    let img = image::load_from_memory(bytes)
        .map_err(|e| err(path, format!("cannot decode the image: {e}")))?;
    let rgb = img.to_rgb32f();
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    if w < 2 || h < 2 {
        return Err(err(
            path,
            format!("image is {w}×{h} pixels; the potential needs at least 2×2"),
        ));
    }
    let colour: Vec<[f32; 3]> = rgb.pixels().map(|p| p.0).collect();
    let lum = colour
        .iter()
        .map(|p| crate::model::forces::image::luminance_of(p.map(f64::from)))
        .collect();
    Ok((w, h, lum, colour))
}

/// Decodes PNG or JPEG bytes to luminance (see [`decode_image`]).
pub fn decode_luminance(path: &Path, bytes: &[u8]) -> Result<Luminance, IoError> {
    decode_image(path, bytes).map(|(w, h, lum, _)| (w, h, lum))
}

/// Reads a PNG or JPEG image file as luminance and RGB (see [`decode_image`]).
pub fn load_image(path: &Path) -> Result<Pixels, IoError> {
    if path.is_dir() {
        return Err(err(path, "is a directory, not an image"));
    }
    let bytes = std::fs::read(path).map_err(|e| err(path, format!("cannot read: {e}")))?;
    decode_image(path, &bytes)
}

/// Reads a PNG or JPEG image file as luminance (see [`decode_image`]).
pub fn load_luminance(path: &Path) -> Result<Luminance, IoError> {
    load_image(path).map(|(w, h, lum, _)| (w, h, lum))
}

/// Writes the image (dimmed luminance) with the projected outlines of models drawn over it, one
/// colour per model, as a PNG: a picture of an image fit.
pub fn write_overlay_png(
    path: &Path,
    potential: &crate::model::forces::image::ImagePotential,
    outlines: &[Vec<[glam::DVec2; 2]>],
) -> Result<(), IoError> {
    const COLOURS: [[u8; 3]; 6] = [
        [255, 60, 40],
        [40, 200, 255],
        [255, 210, 0],
        [90, 255, 90],
        [255, 80, 255],
        [255, 150, 40],
    ];
    let (w, h) = (potential.width() as u32, potential.height() as u32);
    let mut img = image::RgbImage::from_fn(w, h, |c, r| {
        let v = (potential.luminance()[(r * w + c) as usize] * 160.0 + 40.0).clamp(0.0, 255.0);
        image::Rgb([v as u8; 3])
    });
    for (m, segments) in outlines.iter().enumerate() {
        let colour = image::Rgb(COLOURS[m % COLOURS.len()]);
        for [a, b] in segments {
            let (pa, pb) = (potential.to_pixel(*a), potential.to_pixel(*b));
            let n = ((pb - pa).length().ceil() as usize * 2).max(1);
            for s in 0..=n {
                let p = (pa + (pb - pa) * (s as f64 / n as f64)).round();
                if p.x >= 0.0 && p.y >= 0.0 && p.x < w as f64 && p.y < h as f64 {
                    img.put_pixel(p.x as u32, p.y as u32, colour);
                }
            }
        }
    }
    img.save_with_format(path, image::ImageFormat::Png)
        .map_err(|e| err(path, format!("cannot write: {e}")))
}

/// Writes a triangle mesh as OBJ (`v` lines, then 1-based `f` lines) with a comment header.
pub fn write_obj(
    path: &Path,
    vertices: &[DVec3],
    triangles: &[[u32; 3]],
    comment: &str,
) -> Result<(), IoError> {
    use std::fmt::Write as _;
    let mut s = String::with_capacity(vertices.len() * 40 + triangles.len() * 24);
    for line in comment.lines() {
        let _ = writeln!(s, "# {line}");
    }
    push_mesh(&mut s, vertices, triangles, 1);
    std::fs::write(path, s).map_err(|e| err(path, format!("cannot write: {e}")))
}

/// Appends `vertices` as `v` lines and `triangles` as `f` lines numbered from `first` (the OBJ
/// index of the first of these vertices).
fn push_mesh(s: &mut String, vertices: &[DVec3], triangles: &[[u32; 3]], first: u32) {
    use std::fmt::Write as _;
    for v in vertices {
        let _ = writeln!(s, "v {} {} {}", v.x, v.y, v.z);
    }
    for t in triangles {
        let _ = writeln!(s, "f {} {} {}", t[0] + first, t[1] + first, t[2] + first);
    }
}

/// Writes a model's closed surface x_i (in world units) as a triangle OBJ.
pub fn write_model_obj(
    path: &Path,
    tess: &Tessellation,
    state: &ModelState,
) -> Result<(), IoError> {
    write_models_obj(path, &[(tess, state)])
}

/// Writes several models' closed surfaces (world units) into one triangle OBJ, each its own
/// object (`o part_J`) and its own connected mesh.
pub fn write_models_obj(
    path: &Path,
    models: &[(&Tessellation, &ModelState)],
) -> Result<(), IoError> {
    use std::fmt::Write as _;
    let mut s = String::new();
    let nodes: usize = models.iter().map(|(t, _)| t.node_count()).sum();
    let _ = writeln!(
        s,
        "# {} deformable superquadric{}: {nodes} nodes, written by bevy_deformable_sq",
        models.len(),
        if models.len() == 1 { "" } else { "s" }
    );
    let mut x = Vec::new();
    let mut base = 1;
    for (j, (tess, state)) in models.iter().enumerate() {
        state.node_positions(tess, &mut x);
        if models.len() > 1 {
            let _ = writeln!(s, "o part_{j}");
        }
        push_mesh(&mut s, &x, tess.triangles(), base);
        base += x.len() as u32;
    }
    std::fs::write(path, s).map_err(|e| err(path, format!("cannot write: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(name: &str, contents: &[u8]) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("bdsq-io-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join(name);
        std::fs::write(&p, contents).unwrap();
        p
    }

    #[test]
    fn images_decode_to_luminance_and_bad_images_are_refused() {
        let mut png = Vec::new();
        image::RgbImage::from_fn(3, 2, |c, _| {
            image::Rgb(if c == 0 { [255; 3] } else { [0, 255, 0] })
        })
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
        let (w, h, lum) = load_luminance(&temp("ok.png", &png)).unwrap();
        assert_eq!((w, h), (3, 2));
        assert!((lum[0] - 1.0).abs() < 1e-6 && (lum[1] - 0.7152).abs() < 1e-6);
        let mut tiny = Vec::new();
        image::GrayImage::new(1, 1)
            .write_to(
                &mut std::io::Cursor::new(&mut tiny),
                image::ImageFormat::Png,
            )
            .unwrap();
        let e = load_luminance(&temp("tiny.png", &tiny)).unwrap_err();
        assert!(
            e.to_string().contains("tiny.png") && e.message.contains("1×1"),
            "{e}"
        );
        let e = load_luminance(&temp("corrupt.png", b"\x89PNG not really")).unwrap_err();
        assert!(
            e.to_string().contains("corrupt.png") && e.message.contains("decode"),
            "{e}"
        );
        let e = load_luminance(Path::new("/nonexistent/missing.png")).unwrap_err();
        assert!(
            e.to_string().contains("missing.png") && e.message.contains("cannot read"),
            "{e}"
        );
    }

    #[test]
    fn several_models_are_written_as_one_object_each_with_their_own_vertices() {
        let tess = Tessellation::new(4);
        let a = ModelState::new(
            &tess,
            DVec3::ZERO,
            glam::DQuat::IDENTITY,
            Default::default(),
        );
        let b = ModelState::new(
            &tess,
            DVec3::X * 3.0,
            glam::DQuat::IDENTITY,
            Default::default(),
        );
        let path = temp("two.obj", b"");
        write_models_obj(&path, &[(&tess, &a), (&tess, &b)]).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let n = tess.node_count();
        assert_eq!(text.lines().filter(|l| l.starts_with("o part_")).count(), 2);
        assert_eq!(text.lines().filter(|l| l.starts_with("v ")).count(), 2 * n);
        // Read back as a surface: on the two coarse unit spheres, half on each.
        let back = load_points(&path).unwrap();
        assert!(back.iter().all(|p| {
            let r = p.length().min(p.distance(DVec3::X * 3.0));
            (0.5..=1.0 + 1e-9).contains(&r)
        }));
        assert_eq!(back.iter().filter(|p| p.x < 1.5).count(), MESH_SAMPLES / 2);
        // The second object's faces index its own vertices, after the first's.
        let faces: Vec<Vec<usize>> = text
            .lines()
            .filter(|l| l.starts_with("f "))
            .map(|l| l[2..].split(' ').map(|i| i.parse().unwrap()).collect())
            .collect();
        let half = faces.len() / 2;
        assert!(
            faces[..half]
                .iter()
                .flatten()
                .all(|&i| (1..=n).contains(&i))
        );
        assert!(
            faces[half..]
                .iter()
                .flatten()
                .all(|&i| (n + 1..=2 * n).contains(&i))
        );
    }

    #[test]
    fn obj_vertices_are_points_and_a_mesh_is_its_surface() {
        let p = temp("a.obj", b"# c\nv 1 2 3\nv 4 5 6\nv 7 8 9.5\n");
        let pts = load_points(&p).unwrap();
        assert_eq!(
            pts,
            vec![
                DVec3::new(1.0, 2.0, 3.0),
                DVec3::new(4.0, 5.0, 6.0),
                DVec3::new(7.0, 8.0, 9.5)
            ]
        );
        // With a face, the points lie on it, spread over it.
        let p = temp("f.obj", b"v 0 0 0\nv 2 0 0\nv 0 2 0\nf 1 2 3\n");
        let pts = load_points_sampled(&p, 500).unwrap();
        assert_eq!(pts.len(), 500);
        assert!(
            pts.iter()
                .all(|q| q.z == 0.0 && q.x >= 0.0 && q.y >= 0.0 && q.x + q.y <= 2.0 + 1e-12)
        );
        let near_corner = pts.iter().filter(|q| q.x + q.y < 1.0).count();
        assert!(
            (near_corner as i64 - 125).abs() < 10,
            "{near_corner} of 500 on a quarter"
        );
        assert_eq!(load_points(&p).unwrap().len(), MESH_SAMPLES);
        // Bad faces and counts are refused in one line naming the file.
        let p = temp("g.obj", b"v 0 0 0\nv 2 0 0\nv 0 2 0\nf 1 2 4\n");
        let e = load_points(&p).unwrap_err().to_string();
        assert!(e.contains("g.obj: line 4: expected `f i j k`"), "{e}");
        let p = temp("h.obj", b"v 0 0 0\nv 2 0 0\nv 4 0 0\nf 1 2 3\n");
        let e = load_points(&p).unwrap_err().to_string();
        assert!(e.ends_with("h.obj: its 1 faces have no area"), "{e}");
        let e = load_points_sampled(&p, 0).unwrap_err().to_string();
        assert!(e.contains("mesh samples = 0 is out of range"), "{e}");
    }

    #[test]
    fn ply_faces_make_a_mesh_read_as_its_surface() {
        let text = b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n";
        let p = temp("q.ply", text);
        let pts = load_points_sampled(&p, 100).unwrap();
        assert_eq!(pts.len(), 100);
        assert!(pts.iter().all(|q| q.z == 0.0 && (0.0..=1.0).contains(&q.x)));
        let bad = String::from_utf8_lossy(text).replace("4 0 1 2 3", "3 0 1 7");
        let p = temp("r.ply", bad.as_bytes());
        let e = load_points(&p).unwrap_err().to_string();
        assert!(
            e.contains("r.ply: face 1: expected a `vertex_indices` list"),
            "{e}"
        );
    }

    #[test]
    fn obj_errors_name_the_line() {
        let p = temp("bad.obj", b"v 1 2 3\nv 1 x 3\n");
        let e = load_points(&p).unwrap_err();
        assert!(
            e.to_string().contains("bad.obj") && e.message.contains("line 2"),
            "{e}"
        );
        let p = temp("nan.obj", b"v 1 2 3\nv 1 nan 3\n");
        let e = load_points(&p).unwrap_err();
        assert!(
            e.message.contains("line 2") && e.message.contains("NaN"),
            "{e}"
        );
    }

    #[test]
    fn ply_errors_are_one_short_line_naming_the_line() {
        let header = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
        let bad_value = temp(
            "value.ply",
            format!("{header}1 2 3\n4 5 abc\n7 8 9\n").as_bytes(),
        );
        let bad_type = temp("type.ply", header.replace("float y", "floot y").as_bytes());
        let binary = header.replace("ascii", "binary_little_endian") + "abcdefgh";
        let short = temp("short.ply", binary.as_bytes());
        for (p, line, text) in [
            (bad_value, "line 9", "`4 5 abc`"),
            (bad_type, "line 5", "`property floot y`"),
            (short, "line 8", "end of file"),
        ] {
            let e = load_points(&p).unwrap_err();
            let m = e.to_string();
            assert!(
                m.contains(p.file_name().unwrap().to_str().unwrap())
                    && m.contains(line)
                    && m.contains(text),
                "{m}"
            );
            assert!(!m.contains('\n') && m.len() < 200, "{m}");
        }
    }

    #[test]
    fn ply_vertices_are_read_past_other_elements_and_properties() {
        // An edge element before the vertices, and normals and colours beside x, y, z.
        let text = "ply\nformat ascii 1.0\nelement edge 1\nproperty list uchar int vertex_indices\n\
            element vertex 2\nproperty float nx\nproperty double x\nproperty float y\n\
            property uchar red\nproperty int z\nend_header\n3 0 1 0\n0.5 1.25 2 255 3\n0 -1 0.5 7 -2\n";
        let points = load_points(&temp("mixed.ply", text.as_bytes())).unwrap();
        assert_eq!(
            points,
            vec![DVec3::new(1.25, 2.0, 3.0), DVec3::new(-1.0, 0.5, -2.0)]
        );
        let no_z = text.replace("property int z", "property int w");
        let e = load_points(&temp("no_z.ply", no_z.as_bytes())).unwrap_err();
        assert!(
            e.to_string().contains("vertex 1: no scalar property `z`"),
            "{e}"
        );
    }

    #[test]
    fn ply_ascii_and_binary_read_the_same_points() {
        let ascii = b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n-1 0.5 2\n";
        let p = temp("a.ply", ascii);
        let a = load_points(&p).unwrap();
        let mut bin = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty double x\nproperty double y\nproperty double z\nend_header\n".to_vec();
        for v in [1.0f64, 2.0, 3.0, -1.0, 0.5, 2.0] {
            bin.extend_from_slice(&v.to_le_bytes());
        }
        let b = load_points(&temp("b.ply", &bin)).unwrap();
        assert_eq!(a, b);
        assert_eq!(a[1], DVec3::new(-1.0, 0.5, 2.0));
    }
}
