//! Depth video frames: 16-bit PNG depth images and Open3D's camera intrinsics JSON.

use super::{IoError, err};
use crate::model::init::InitialPose;
use crate::model::track::{DepthFrame, Intrinsics};
use std::path::Path;

/// Open3D's `PinholeCameraIntrinsicParameters.PrimeSenseDefault`: 640×480, f = 525,
/// c = (319.5, 239.5), the camera a depth image is taken to come from when none is given.
pub const PRIMESENSE_DEFAULT: Intrinsics = Intrinsics {
    width: 640,
    height: 480,
    fx: 525.0,
    fy: 525.0,
    cx: 319.5,
    cy: 239.5,
};

/// Reads the JSON Open3D writes for a `PinholeCameraIntrinsic`: `width`, `height` and
/// `intrinsic_matrix`, the 3×3 matrix K in column-major order (`f_x = m[0]`, `f_y = m[4]`,
/// `c_x = m[6]`, `c_y = m[7]`). The message names the field that is missing or wrong.
pub fn load_intrinsics(path: &Path) -> Result<Intrinsics, IoError> {
    if path.is_dir() {
        return Err(err(path, "is a directory, not camera intrinsics"));
    }
    let text = std::fs::read_to_string(path).map_err(|e| err(path, format!("cannot read: {e}")))?;
    parse_intrinsics(&text).map_err(|m| err(path, m))
}

/// Parses Open3D intrinsics JSON text (see [`load_intrinsics`]).
pub fn parse_intrinsics(text: &str) -> Result<Intrinsics, String> {
    let v: serde_json::Value =
        serde_json::from_str(text).map_err(|e| format!("not JSON camera intrinsics: {e}"))?;
    let size = |name: &str| -> Result<u32, String> {
        v.get(name)
            .and_then(serde_json::Value::as_u64)
            .and_then(|n| u32::try_from(n).ok())
            .filter(|&n| n > 0)
            .ok_or_else(|| format!("`{name}` is missing or not a positive whole number"))
    };
    let (width, height) = (size("width")?, size("height")?);
    let m: Vec<f64> = v
        .get("intrinsic_matrix")
        .and_then(serde_json::Value::as_array)
        .map(|a| a.iter().filter_map(serde_json::Value::as_f64).collect())
        .unwrap_or_default();
    if m.len() != 9 {
        return Err("`intrinsic_matrix` must be 9 numbers (the 3×3 K, column-major)".to_string());
    }
    let c = Intrinsics {
        width,
        height,
        fx: m[0],
        fy: m[4],
        cx: m[6],
        cy: m[7],
    };
    c.validate()
        .map_err(|e| format!("`intrinsic_matrix`: {e}"))?;
    Ok(c)
}

/// Decodes a 16-bit single-channel PNG depth image: width, height and the raw units, row-major
/// (0 = no depth). An 8-bit or colour image is an error: its values are not depths.
pub fn decode_depth_png(path: &Path, bytes: &[u8]) -> Result<(u32, u32, Vec<u16>), IoError> {
    let img = image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
        .map_err(|e| err(path, format!("cannot decode the PNG: {e}")))?;
    match img {
        image::DynamicImage::ImageLuma16(g) => {
            let (w, h) = g.dimensions();
            Ok((w, h, g.into_raw()))
        }
        other => Err(err(
            path,
            format!(
                "is a {:?} PNG; a depth frame is a 16-bit single-channel (grey) PNG",
                other.color()
            ),
        )),
    }
}

/// Reads a depth frame from a 16-bit PNG at `scale` metres per unit, taken by the camera
/// `intrinsics` ([`PRIMESENSE_DEFAULT`] when `None`). Errors name the file: missing,
/// unreadable, not 16-bit grey, or not the intrinsics' size.
pub fn load_depth_png(
    path: &Path,
    intrinsics: Option<&Intrinsics>,
    scale: f64,
) -> Result<DepthFrame, IoError> {
    if !(scale.is_finite() && scale > 0.0) {
        return Err(err(
            path,
            format!("depth scale {scale} must be a positive number of metres per unit"),
        ));
    }
    if path.is_dir() {
        return Err(err(path, "is a directory, not a depth image"));
    }
    let bytes = std::fs::read(path).map_err(|e| err(path, format!("cannot read: {e}")))?;
    let (w, h, raw) = decode_depth_png(path, &bytes)?;
    let camera = intrinsics.copied().unwrap_or(PRIMESENSE_DEFAULT);
    if (w, h) != (camera.width, camera.height) {
        let whose = if intrinsics.is_some() {
            "the intrinsics"
        } else {
            "the default camera (give --intrinsics)"
        };
        return Err(err(
            path,
            format!(
                "is {w}×{h} pixels; {whose} are {}×{}",
                camera.width, camera.height
            ),
        ));
    }
    DepthFrame::from_raw(camera, &raw, scale).map_err(|m| err(path, m))
}

/// Writes `frame` as a 16-bit grey PNG at `scale` metres per unit (depths rounded to the unit,
/// clamped to 65535; no depth stays 0).
pub fn write_depth_png(path: &Path, frame: &DepthFrame, scale: f64) -> Result<(), IoError> {
    let c = &frame.intrinsics;
    let raw: Vec<u16> = frame
        .depth
        .iter()
        .map(|&z| {
            if z > 0.0 {
                (z as f64 / scale).round().clamp(1.0, 65535.0) as u16
            } else {
                0
            }
        })
        .collect();
    let img = image::ImageBuffer::<image::Luma<u16>, _>::from_raw(c.width, c.height, raw)
        .ok_or_else(|| err(path, "the frame's pixels are not its intrinsics' size"))?;
    img.save_with_format(path, image::ImageFormat::Png)
        .map_err(|e| err(path, format!("cannot write: {e}")))
}

/// Writes a picture of a tracked frame: the depth as grey (near is bright, over a metre about
/// the model; no depth black)
/// with the model of `pose` drawn over it as red dots of the surface that faces the camera.
pub fn write_track_png(path: &Path, frame: &DepthFrame, pose: &InitialPose) -> Result<(), IoError> {
    use crate::model::superquadric::{SignedPowers, Trig, shape_from_powers};
    let c = &frame.intrinsics;
    // Grey over half a metre either side of the model.
    let near = (pose.translation.z - 0.5) as f32;
    let span = 1.0f32;
    let mut img = image::RgbImage::from_fn(c.width, c.height, |u, v| {
        let z = frame.depth[(v * c.width + u) as usize];
        let g = if z > 0.0 {
            (230.0 - 190.0 * ((z - near) / span).clamp(0.0, 1.0)) as u8
        } else {
            0
        };
        image::Rgb([g; 3])
    });
    let (rings, longitudes) = (256, 512);
    let mut dots = Vec::with_capacity(rings * longitudes);
    for i in 0..=rings {
        let u = -std::f64::consts::FRAC_PI_2 + std::f64::consts::PI * i as f64 / rings as f64;
        for j in 0..longitudes {
            let v =
                -std::f64::consts::PI + 2.0 * std::f64::consts::PI * j as f64 / longitudes as f64;
            let at = |u: f64, v: f64| {
                let t = Trig::new(u, v);
                pose.translation
                    + pose.rotation
                        * shape_from_powers(&pose.shape, &SignedPowers::new(&pose.shape, &t))
            };
            let p = at(u, v);
            // The outward normal from neighbouring points of the grid.
            let (du, dv) = (1e-3, 1e-3);
            let n = (at(u + du, v) - at(u - du, v)).cross(at(u, v + dv) - at(u, v - dv));
            let outward = if n.dot(p - pose.translation) >= 0.0 {
                n
            } else {
                -n
            };
            let front = outward.dot(p) < 0.0;
            dots.push((p, front));
        }
    }
    for (p, front) in dots {
        if !front {
            continue;
        }
        let Some(px) = c.project(p) else { continue };
        let (x, y) = (px.x.round(), px.y.round());
        if x >= 0.0 && y >= 0.0 && x < c.width as f64 && y < c.height as f64 {
            img.put_pixel(x as u32, y as u32, image::Rgb([255, 40, 30]));
        }
    }
    img.save_with_format(path, image::ImageFormat::Png)
        .map_err(|e| err(path, format!("cannot write: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn open3d_intrinsics_are_read_column_major() {
        let c = parse_intrinsics(
            r#"{"width": 640, "height": 480,
                "intrinsic_matrix": [600.0, 0.0, 0.0, 0.0, 610.0, 0.0, 320.5, 241.0, 1.0]}"#,
        )
        .unwrap();
        assert_eq!((c.width, c.height), (640, 480));
        assert_eq!((c.fx, c.fy, c.cx, c.cy), (600.0, 610.0, 320.5, 241.0));
    }

    #[test]
    fn a_track_picture_draws_the_model_where_it_projects() {
        use crate::model::superquadric::SuperquadricParams;
        let camera = Intrinsics {
            width: 64,
            height: 48,
            fx: 60.0,
            fy: 60.0,
            cx: 31.5,
            cy: 23.5,
        };
        let frame = DepthFrame {
            intrinsics: camera,
            depth: vec![2.0; 64 * 48],
        };
        let pose = InitialPose {
            translation: glam::DVec3::new(0.2, 0.0, 1.0),
            rotation: glam::DQuat::IDENTITY,
            shape: SuperquadricParams {
                a: 0.1,
                a1: 1.0,
                a2: 1.0,
                a3: 1.0,
                e1: 1.0,
                e2: 1.0,
            },
        };
        let path = std::env::temp_dir().join(format!("dsq-track-png-{}.png", std::process::id()));
        write_track_png(&path, &frame, &pose).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        std::fs::remove_file(&path).ok();
        assert_eq!(img.dimensions(), (64, 48));
        // The sphere of radius 0.1 m at (0.2, 0, 1) covers u ∈ 31.5 + 60·[0.1, 0.3] (about).
        let red: Vec<(u32, u32)> = img
            .enumerate_pixels()
            .filter(|(_, _, p)| p.0 == [255, 40, 30])
            .map(|(u, v, _)| (u, v))
            .collect();
        assert!(red.len() > 50, "{} red pixels", red.len());
        assert!(
            red.iter()
                .all(|&(u, v)| (36..=51).contains(&u) && (16..=31).contains(&v))
        );
    }

    #[test]
    fn bad_intrinsics_name_the_field() {
        let e = parse_intrinsics(r#"{"width": 640, "intrinsic_matrix": []}"#).unwrap_err();
        assert!(e.contains("`height`"), "{e}");
        let e = parse_intrinsics(r#"{"width": 640, "height": 480, "intrinsic_matrix": [1, 2]}"#)
            .unwrap_err();
        assert!(e.contains("`intrinsic_matrix`"), "{e}");
        let e = parse_intrinsics(
            r#"{"width": 4, "height": 4, "intrinsic_matrix": [0, 0, 0, 0, 5, 0, 2, 2, 1]}"#,
        )
        .unwrap_err();
        assert!(e.contains("fx"), "{e}");
    }

    #[test]
    fn depth_png_round_trips_at_the_unit() {
        let dir = std::env::temp_dir().join(format!("dsq-depth-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let camera = Intrinsics {
            width: 4,
            height: 3,
            fx: 5.0,
            fy: 5.0,
            cx: 1.5,
            cy: 1.0,
        };
        let depth = vec![
            0.0, 1.2344, 0.5, 65.0, 0.0, 0.0, 2.0, 0.001, 0.0004, 3.0, 1.0, 0.25,
        ];
        let frame = DepthFrame {
            intrinsics: camera,
            depth: depth.clone(),
        };
        let path = dir.join("d.png");
        write_depth_png(&path, &frame, 0.001).unwrap();
        let back = load_depth_png(&path, Some(&camera), 0.001).unwrap();
        for (a, b) in depth.iter().zip(&back.depth) {
            let expect = if *a > 0.0 {
                ((*a as f64 / 0.001).round().clamp(1.0, 65535.0) * 0.001) as f32
            } else {
                0.0
            };
            assert!((b - expect).abs() < 1e-6, "{a} → {b}");
        }
        // The wrong size, a bad scale and an 8-bit image are errors naming the file.
        let e = load_depth_png(&path, None, 0.001).unwrap_err().to_string();
        assert!(e.contains("d.png") && e.contains("4×3"), "{e}");
        for scale in [0.0, -1.0, f64::NAN] {
            let e = load_depth_png(&path, Some(&camera), scale).unwrap_err();
            assert!(e.message.contains("depth scale"), "{e}");
        }
        let grey8 = dir.join("g.png");
        image::GrayImage::new(4, 3).save(&grey8).unwrap();
        let e = load_depth_png(&grey8, Some(&camera), 0.001).unwrap_err();
        assert!(e.message.contains("16-bit"), "{e}");
        let e = load_depth_png(&dir.join("missing.png"), Some(&camera), 0.001).unwrap_err();
        assert!(e.message.contains("cannot read"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
