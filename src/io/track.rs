//! A track's poses as JSON: the lines `dsq track` prints and the poses it starts from.

use crate::model::frame::{quat_from_paper, quat_to_paper};
use crate::model::init::InitialPose;
use crate::model::superquadric::SuperquadricParams;
use crate::model::track::TrackedFrame;
use glam::DVec3;
use serde_json::{Value, json};

/// Frame `index`'s line of a track: the pose and shape as `dsq fit` gives them (`translation`,
/// `rotation` [s, v1, v2, v3], `a`, `a1`, `a2`, `a3`, `e1`, `e2`) and the frame's figures.
pub fn track_line(index: usize, out: &TrackedFrame) -> Value {
    let p = &out.pose;
    let s = &p.shape;
    json!({
        "frame": index,
        "translation": p.translation.to_array(), "rotation": quat_to_paper(p.rotation),
        "a": s.a, "a1": s.a1, "a2": s.a2, "a3": s.a3, "e1": s.e1, "e2": s.e2,
        "lost": out.lost, "points": out.points, "inliers": out.inliers,
        "free_rays": out.free_rays, "rms": out.rms, "iterations": out.iterations,
    })
}

/// The pose in a JSON object with `translation`, `rotation` ([s, v1, v2, v3]) and the shape
/// `a`, `a1`, `a2`, `a3`, `e1`, `e2`: a `dsq fit --out-params` file or a track's line. The
/// message names the field that is missing or wrong.
pub fn pose_from_json(v: &Value) -> Result<InitialPose, String> {
    let numbers = |name: &str, n: usize| -> Result<Vec<f64>, String> {
        let field = v.get(name).ok_or_else(|| format!("no `{name}`"))?;
        let list: Vec<f64> = match field.as_array() {
            Some(a) => a.iter().filter_map(Value::as_f64).collect(),
            None => field.as_f64().into_iter().collect(),
        };
        if list.len() != n || list.iter().any(|x| !x.is_finite()) {
            return Err(format!("`{name}` must be {n} finite number(s)"));
        }
        Ok(list)
    };
    let t = numbers("translation", 3)?;
    let q = numbers("rotation", 4)?;
    let one = |name: &str| numbers(name, 1).map(|x| x[0]);
    let shape = SuperquadricParams {
        a: one("a")?,
        a1: one("a1")?,
        a2: one("a2")?,
        a3: one("a3")?,
        e1: one("e1")?,
        e2: one("e2")?,
    };
    let rotation = quat_from_paper([q[0], q[1], q[2], q[3]]);
    if rotation.length() < 1e-9 {
        return Err("`rotation` is not a rotation".into());
    }
    Ok(InitialPose {
        translation: DVec3::new(t[0], t[1], t[2]),
        rotation: rotation.normalize(),
        shape,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;

    #[test]
    fn a_line_reads_back_as_its_pose() {
        let out = TrackedFrame {
            pose: InitialPose {
                translation: DVec3::new(0.1, -0.2, 0.9),
                rotation: DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.2, 1.0),
                shape: SuperquadricParams {
                    a: 0.07,
                    a1: 1.0,
                    a2: 0.8,
                    a3: 0.6,
                    e1: 0.3,
                    e2: 0.9,
                },
            },
            lost: false,
            points: 300,
            inliers: 290.5,
            free_rays: 400,
            rms: 0.002,
            iterations: 4,
            energy: [2.0, 1.0],
        };
        let line = track_line(3, &out);
        let text = line.to_string();
        let back = pose_from_json(&serde_json::from_str(&text).unwrap()).unwrap();
        assert_eq!(back.translation, out.pose.translation);
        assert_eq!(back.shape, out.pose.shape);
        assert!(back.rotation.angle_between(out.pose.rotation) < 1e-6);
        let e = pose_from_json(&json!({"translation": [0, 0], "rotation": [1, 0, 0, 0]}));
        assert!(e.unwrap_err().contains("`translation`"));
    }
}
