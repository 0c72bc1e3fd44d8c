//! Property-based tests of the core (no Bevy): random and mutated point files (PLY ascii and
//! binary, OBJ), scene files and images give a value or a one-line error naming the file, never
//! a panic; fits of random superquadric clouds under random rigid motions and scales are the
//! same fit, transformed. Fixed seeds, so a failure repeats; no failure files are written.

use bevy_deformable_sq::io::{decode_luminance, decode_points};
use bevy_deformable_sq::model::fit::{FitOptions, FitReport, Solver, fit, surface_distances};
use bevy_deformable_sq::model::init::InitialPose;
use bevy_deformable_sq::model::superquadric::SuperquadricParams;
use bevy_deformable_sq::scene::{SceneData, SceneDef};
use bevy_deformable_sq::synthetic::superquadric_cloud;
use glam::{DQuat, DVec3};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngSeed};
use std::path::{Path, PathBuf};

/// `cases` cases from a fixed seed, without failure files.
fn config(cases: u32, seed: u64) -> Config {
    Config {
        cases,
        rng_seed: RngSeed::Fixed(seed),
        failure_persistence: None,
        max_shrink_iters: 256,
        ..Config::default()
    }
}

const ASCII_PLY: &str = "ply\nformat ascii 1.0\ncomment a tetrahedron\nelement vertex 4\n\
property float x\nproperty float y\nproperty float z\nelement face 1\n\
property list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n";

const OBJ: &str = "# a tetrahedron\nmtllib none.mtl\no t\nv 0 0 0\nv 1 0 0\nv 0 1 0\n\
v 0 0 1.5e0\nvn 0 0 1\nvt 0.5 0.5\nf 1 2 3\nf 1/1/1 2/1/1 4/1/1\nl 1 4\n";

/// A binary little-endian PLY of four vertices (f32 x y z, then a f64 confidence).
fn binary_ply() -> Vec<u8> {
    let mut out = b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\n\
property float y\nproperty float z\nproperty double confidence\nend_header\n"
        .to_vec();
    for (i, p) in [
        [0.0f32, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
    ]
    .iter()
    .enumerate()
    {
        for c in p {
            out.extend_from_slice(&c.to_le_bytes());
        }
        out.extend_from_slice(&(i as f64).to_le_bytes());
    }
    out
}

/// An 8×6 RGB PNG with a gradient.
fn png() -> Vec<u8> {
    let img =
        image::RgbImage::from_fn(8, 6, |x, y| image::Rgb([(x * 30) as u8, (y * 40) as u8, 7]));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png)
        .expect("encode");
    out.into_inner()
}

/// Tokens that break parsers in interesting ways.
const TOKENS: &[&str] = &[
    "nan",
    "inf",
    "-inf",
    "1e400",
    "-0",
    "99999999999999999999",
    "4294967295",
    "18446744073709551616",
    "\0",
    "\n",
    "\r\n",
    " ",
    "{",
    "}",
    "(",
    ")",
    "[",
    "]",
    ":",
    ",",
    "\"",
    "#",
    "é",
    "element vertex 4294967295\n",
    "property list uint uint vertex_indices\n",
    "format binary_big_endian 1.0\n",
    "end_header\n",
    "v 1 2\n",
    "v nan 0 0\n",
];

/// One edit of a file's bytes.
#[derive(Clone, Debug)]
enum Edit {
    /// Set the byte at (position mod length).
    Set(usize, u8),
    /// Insert a token of [`TOKENS`] at a position.
    Insert(usize, usize),
    /// Delete up to this many bytes from a position.
    Delete(usize, usize),
    /// Cut the file at a position.
    Truncate(usize),
    /// Copy a span to another place.
    Duplicate(usize, usize, usize),
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        (any::<usize>(), any::<u8>()).prop_map(|(i, b)| Edit::Set(i, b)),
        (any::<usize>(), 0..TOKENS.len()).prop_map(|(i, t)| Edit::Insert(i, t)),
        (any::<usize>(), 1usize..16).prop_map(|(i, n)| Edit::Delete(i, n)),
        any::<usize>().prop_map(Edit::Truncate),
        (any::<usize>(), 1usize..64, any::<usize>()).prop_map(|(i, n, j)| Edit::Duplicate(i, n, j)),
    ]
}

fn apply(mut bytes: Vec<u8>, edits: &[Edit]) -> Vec<u8> {
    for e in edits {
        let len = bytes.len().max(1);
        match *e {
            Edit::Set(i, b) => {
                if !bytes.is_empty() {
                    bytes[i % len] = b;
                }
            }
            Edit::Insert(i, t) => {
                let at = i % (bytes.len() + 1);
                bytes.splice(at..at, TOKENS[t].bytes());
            }
            Edit::Delete(i, n) => {
                let at = i % len;
                let end = (at + n).min(bytes.len());
                bytes.drain(at.min(end)..end);
            }
            Edit::Truncate(i) => bytes.truncate(i % len),
            Edit::Duplicate(i, n, j) => {
                let at = i % len;
                let end = (at + n).min(bytes.len());
                let span: Vec<u8> = bytes[at.min(end)..end].to_vec();
                let to = j % (bytes.len() + 1);
                bytes.splice(to..to, span);
            }
        }
    }
    bytes
}

/// An error message is one line that starts with the file it is about.
fn one_line_naming(message: &str, file: &Path) -> Result<(), TestCaseError> {
    prop_assert!(!message.contains('\n'), "more than one line: {message:?}");
    prop_assert!(
        message.starts_with(&file.display().to_string()),
        "does not name {}: {message:?}",
        file.display()
    );
    prop_assert!(message.len() < 400, "too long: {message:?}");
    Ok(())
}

/// Points decoded from any bytes are finite and not empty, or the error is one line.
fn check_points(name: &str, bytes: &[u8]) -> Result<(), TestCaseError> {
    let file = PathBuf::from(name);
    match decode_points(&file, bytes) {
        Ok(points) => {
            prop_assert!(!points.is_empty());
            prop_assert!(points.iter().all(|p| p.is_finite()), "{points:?}");
        }
        Err(e) => one_line_naming(&e.to_string(), &file)?,
    }
    Ok(())
}

#[test]
fn the_seed_files_decode() {
    // The binary PLY is a cloud: its four vertices.
    let points = decode_points(Path::new("t.ply"), &binary_ply()).expect("binary");
    assert_eq!(points.len(), 4);
    assert!(points.contains(&DVec3::new(0.0, 0.0, 1.0)));
    // The other two have faces: their surfaces, sampled, on the tetrahedron's faces.
    for (name, bytes) in [
        ("t.ply", ASCII_PLY.as_bytes().to_vec()),
        ("t.obj", OBJ.as_bytes().to_vec()),
    ] {
        let points = decode_points(Path::new(name), &bytes).expect(name);
        assert_eq!(points.len(), bevy_deformable_sq::io::MESH_SAMPLES, "{name}");
        assert!(
            points
                .iter()
                .all(|p| p.min_element() >= 0.0 && p.x + p.y + p.z / 1.5 <= 1.0 + 1e-9),
            "{name}"
        );
    }
    let (w, h, lum) = decode_luminance(Path::new("t.png"), &png()).expect("png");
    assert_eq!((w, h, lum.len()), (8, 6, 48));
}

proptest! {
    #![proptest_config(config(384, 0x5eed_0001))]

    #[test]
    fn mutated_ascii_ply_gives_points_or_a_one_line_error(edits in prop::collection::vec(edit(), 1..8)) {
        check_points("mutated.ply", &apply(ASCII_PLY.as_bytes().to_vec(), &edits))?;
    }

    #[test]
    fn mutated_binary_ply_gives_points_or_a_one_line_error(edits in prop::collection::vec(edit(), 1..8)) {
        check_points("mutated.ply", &apply(binary_ply(), &edits))?;
    }

    #[test]
    fn mutated_obj_gives_points_or_a_one_line_error(edits in prop::collection::vec(edit(), 1..8)) {
        check_points("mutated.obj", &apply(OBJ.as_bytes().to_vec(), &edits))?;
    }

    #[test]
    fn mutated_png_gives_an_image_or_a_one_line_error(edits in prop::collection::vec(edit(), 1..6)) {
        let file = PathBuf::from("mutated.png");
        match decode_luminance(&file, &apply(png(), &edits)) {
            Ok((w, h, lum)) => {
                prop_assert!(w >= 2 && h >= 2 && lum.len() == w * h);
                prop_assert!(lum.iter().all(|l| (0.0..=1.0).contains(l)));
            }
            Err(e) => one_line_naming(&e.to_string(), &file)?,
        }
    }

    #[test]
    fn random_bytes_give_a_value_or_a_one_line_error(bytes in prop::collection::vec(any::<u8>(), 0..512)) {
        check_points("random.ply", &bytes)?;
        check_points("random.obj", &bytes)?;
        let mut ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty double x\n\
property double y\nproperty double z\nend_header\n".to_vec();
        ply.extend_from_slice(&bytes);
        check_points("random_body.ply", &ply)?;
        let file = PathBuf::from("random.png");
        if let Err(e) = decode_luminance(&file, &bytes) {
            one_line_naming(&e.to_string(), &file)?;
        }
    }
}

/// The shipped scenes, the seeds of the scene mutations.
fn scene_texts() -> Vec<(PathBuf, String)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/scenes");
    let mut out: Vec<(PathBuf, String)> = std::fs::read_dir(&dir)
        .expect("assets/scenes")
        .map(|e| e.expect("entry").path())
        .filter(|p| p.to_string_lossy().ends_with(".dsq.ron"))
        .map(|p| {
            let text = std::fs::read_to_string(&p).expect("scene");
            (p, text)
        })
        .collect();
    out.sort();
    assert!(out.len() >= 10, "{} scenes", out.len());
    out
}

/// A mutated scene parses and resolves its data, giving a start state for every part, or fails
/// with one line naming the scene file.
fn check_scene(file: &Path, text: &str) -> Result<(), TestCaseError> {
    let def = match SceneDef::parse(text, file) {
        Ok(def) => def,
        Err(e) => return one_line_naming(&e.to_string(), file),
    };
    let dir = file.parent().expect("scene dir").to_path_buf();
    let data = SceneData::resolve(&def, file, |rel| {
        // Only files that exist under assets/: a mutated path never reads elsewhere.
        let path = dir.join(rel);
        let assets = dir.parent().expect("assets");
        match path.canonicalize() {
            Ok(p) if p.starts_with(assets.canonicalize().expect("assets")) && p.is_file() => {
                std::fs::read(p).map_err(|e| format!("cannot read {rel:?}: {e}"))
            }
            _ => Err(format!("cannot read {rel:?}: not a file under assets/")),
        }
    });
    match data {
        Ok(data) => {
            for i in 0..def.parts.len() {
                if let Some(s) = data.initial_state(&def, i) {
                    prop_assert!(s.is_finite(), "part {i}: {s:?}");
                }
            }
        }
        Err(e) => one_line_naming(&e.to_string(), file)?,
    }
    Ok(())
}

#[test]
fn every_shipped_scene_parses_and_resolves() {
    for (file, text) in scene_texts() {
        let def = SceneDef::parse(&text, &file).unwrap_or_else(|e| panic!("{e}"));
        check_scene(&file, &text).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
        assert!(!def.parts.is_empty(), "{}", file.display());
    }
}

proptest! {
    #![proptest_config(config(256, 0x5eed_0002))]

    #[test]
    fn mutated_scenes_give_a_scene_or_a_one_line_error(
        which in any::<usize>(),
        edits in prop::collection::vec(edit(), 1..6),
    ) {
        let scenes = scene_texts();
        let (file, text) = &scenes[which % scenes.len()];
        let bytes = apply(text.as_bytes().to_vec(), &edits);
        check_scene(file, &String::from_utf8_lossy(&bytes))?;
    }
}

/// A random superquadric in the range a recogniser meets.
fn shape() -> impl Strategy<Value = SuperquadricParams> {
    (0.35f64..1.0, 0.35f64..1.0, 0.3f64..1.7, 0.3f64..1.7).prop_map(|(a1, a2, e1, e2)| {
        SuperquadricParams {
            a: 1.0,
            a1,
            a2,
            a3: 1.0,
            e1,
            e2,
        }
    })
}

/// A random rotation: a unit quaternion from four normal-ish coordinates.
fn rotation() -> impl Strategy<Value = DQuat> {
    (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0)
        .prop_filter("not near zero", |(x, y, z, w)| {
            x * x + y * y + z * z + w * w > 0.05
        })
        .prop_map(|(x, y, z, w)| DQuat::from_xyzw(x, y, z, w).normalize())
}

/// Node positions of a fitted model.
fn nodes(r: &FitReport) -> Vec<DVec3> {
    let mut x = Vec::new();
    r.state.node_positions(&r.tess, &mut x);
    x
}

proptest! {
    #![proptest_config(config(6, 0x5eed_0003))]

    #[test]
    fn fits_of_moved_and_scaled_clouds_are_the_same_fit_transformed(
        truth in shape(),
        (seed, motion, shift) in (any::<u64>(), rotation(), prop::array::uniform3(-1e3f64..1e3)),
        log_scale in -12.0f64..12.0,
        lm in any::<bool>(),
    ) {
        let points = superquadric_cloud(&truth, DVec3::ZERO, DQuat::IDENTITY, 300, 0.01, seed);
        let opts = if lm {
            FitOptions { global_only: true, solver: Solver::Solved, ..Default::default() }
                .for_data()
        } else {
            FitOptions { global_only: true, k: 15, max_steps: 1500, ..Default::default() }
        };
        let scale = 10f64.powf(log_scale);
        let shift = DVec3::from_array(shift);
        let moved: Vec<DVec3> = points.iter().map(|p| scale * (motion * *p + shift)).collect();
        let base = fit(&points, &opts, |_| {}).expect("fit");
        let r = fit(&moved, &opts, |_| {}).map_err(|e| TestCaseError::fail(e.to_string()))?;
        prop_assert!(r.state.is_finite());
        prop_assert!(r.state.rotation.length() - 1.0 < 1e-12);
        // The same surface, transformed: B's nodes, moved back, lie on A's superquadric (and the
        // nodes match one for one when both fits took the same path).
        let back: Vec<DVec3> = nodes(&r)
            .iter()
            .map(|x| motion.inverse() * (*x / scale - shift))
            .collect();
        let off = surface_distances(&InitialPose::of(&base.state), &back)
            .into_iter()
            .fold(0.0, f64::max);
        let size = base.residuals.diagonal;
        prop_assert!(off < 1e-5 * size, "B's surface is {off} off A's (diagonal {size})");
        let worst = nodes(&base)
            .iter()
            .zip(&back)
            .map(|(a, b)| a.distance(*b))
            .fold(0.0, f64::max);
        prop_assert!(
            worst < 1e-5 * size || truth.a1.max(truth.a2) > 0.9 || (truth.a1 - truth.a2).abs() < 0.1,
            "nodes differ by {worst} (diagonal {size})"
        );
        // Mean distances in the data's units (the bounding box turns with the data).
        let (ma, mb) = (
            base.residuals.mean * base.residuals.diagonal,
            r.residuals.mean * r.residuals.diagonal / scale,
        );
        prop_assert!((ma - mb).abs() <= 1e-5 * ma.max(1e-12 * size), "mean distance {mb} vs {ma}");
    }
}
