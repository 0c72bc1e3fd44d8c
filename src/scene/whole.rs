//! A scene made from a whole object's fit ([`SceneDef::of_whole`]): `dsq fit POINTS --parts
//! auto --out-scene`, which the sandbox opens as one jointed model on its data.

use super::validate::{lexical_absolute, relative_path};
use super::*;
use crate::model::parts::Whole;

impl SceneDef {
    /// The scene, to be written at `scene_file`, of a whole object fitted as parts: the cloud
    /// `points_file` (referred to relative to the scene's folder) as the source `"cloud"`, and
    /// the parts on it ([`SceneDef::add_whole`]).
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
            joints: Vec::new(),
            camera: None,
        };
        scene.add_whole("cloud", whole);
        scene
    }

    /// Appends the parts of `whole`, fitted to the scene's source `source`, which they share:
    /// named "`source` 1", "`source` 2", …, each at its fitted state (with its local
    /// displacements) with its fit's tessellation, stiffness, range forces' settings and
    /// freedoms; and their joints. Gives the index of the first part.
    pub fn add_whole(&mut self, source: &str, whole: &Whole) -> usize {
        let base = self.parts.len();
        for (j, f) in whole.fits.iter().enumerate() {
            let o = &f.options;
            let mut part = PartDef::new(format!("{source} {}", j + 1));
            part.forces = Forces::Range {
                data: source.into(),
                beta: o.beta,
                coverage: o.coverage,
                influence: o.influence,
                outliers: o.outlier_ratio,
                crop: None,
                shared: true,
            };
            part.k = f.tess.k;
            part.w0 = o.dynamics.w0;
            part.w1 = o.dynamics.w1;
            part.free.global_only = o.global_only;
            self.parts.push(part);
            self.set_state(base + j, &f.state, true);
        }
        self.joints.extend(whole.joints.iter().map(|j| JointDef {
            parts: [base + j.parts[0], base + j.parts[1]],
            ends: j.ends,
            stiffness: default_joint_stiffness(),
        }));
        base
    }
}
