//! A scene made from a whole object's fit ([`SceneDef::of_whole`]): `dsq fit POINTS --parts
//! auto --out-scene`, which the sandbox opens as one jointed model on its data.

use super::validate::{lexical_absolute, relative_path};
use super::*;
use crate::model::parts::Whole;

impl SceneDef {
    /// The scene, to be written at `scene_file`, of a whole object fitted as parts: the cloud
    /// `points_file` (referred to relative to the scene's folder) as the source `"cloud"`, shared
    /// by every part; each part at its fitted state (with its local displacements),
    /// tessellation, stiffness and the fit's outlier prior; the parts' joints.
    pub fn of_whole(points_file: &Path, scene_file: &Path, whole: &Whole) -> Self {
        let dir = lexical_absolute(scene_file.parent().unwrap_or(Path::new("")));
        let path = relative_path(&lexical_absolute(points_file), &dir)
            .to_string_lossy()
            .replace('\\', "/");
        let data = BTreeMap::from([(
            "cloud".to_string(),
            DataSource::Points {
                path,
                placement: Placement::default(),
            },
        )]);
        let mut scene = SceneDef {
            data,
            parts: Vec::new(),
            joints: whole
                .joints
                .iter()
                .map(|j| JointDef {
                    parts: j.parts,
                    ends: j.ends,
                    stiffness: default_joint_stiffness(),
                })
                .collect(),
            camera: None,
        };
        for (j, f) in whole.fits.iter().enumerate() {
            let o = &f.options;
            let forces = Forces::Range {
                data: "cloud".into(),
                beta: o.beta,
                coverage: o.coverage,
                influence: o.influence,
                outliers: o.outlier_ratio,
                crop: None,
                shared: true,
            };
            let mut part = PartDef::new(format!("part {j}"));
            part.forces = forces;
            part.k = f.tess.k;
            part.w0 = o.dynamics.w0;
            part.w1 = o.dynamics.w1;
            part.free.global_only = o.global_only;
            scene.parts.push(part);
            scene.set_state(j, &f.state, true);
        }
        scene
    }
}
