//! EMS's fits of clouds, read from a file made by running EMS outside the crate (JSON lines with
//! `cloud`, `shape`, `scale`, `translation` and `rot`), shared by the measurement programs that
//! compare with it.

use bevy_deformable_sq::model::init::InitialPose;
use bevy_deformable_sq::model::superquadric::SuperquadricParams;
use glam::{DMat3, DQuat, DVec3};
use std::path::Path;

/// One line of an EMS results file.
#[derive(serde::Deserialize)]
pub struct EmsFit {
    /// Which cloud (a file stem).
    pub cloud: String,
    /// ε1, ε2.
    pub shape: [f64; 2],
    /// Semi-axes along the model's x, y, z.
    pub scale: [f64; 3],
    /// Centre.
    pub translation: [f64; 3],
    /// Rotation matrix, row-major (model frame → world).
    pub rot: [f64; 9],
}

impl EmsFit {
    /// The fit as a pose and shape of ours.
    pub fn pose(&self) -> InitialPose {
        let r = self.rot;
        let rotation = DQuat::from_mat3(&DMat3::from_cols_array(&[
            r[0], r[3], r[6], r[1], r[4], r[7], r[2], r[5], r[8],
        ]))
        .normalize();
        let a = self.scale.iter().copied().fold(0.0, f64::max);
        InitialPose {
            translation: DVec3::from_array(self.translation),
            rotation,
            shape: SuperquadricParams {
                a,
                a1: self.scale[0] / a,
                a2: self.scale[1] / a,
                a3: self.scale[2] / a,
                e1: self.shape[0],
                e2: self.shape[1],
            },
        }
    }
}

/// Every line of the results file `path` (`--ems FILE`), none without one; errors name the
/// file and line.
pub fn read_results(path: Option<&Path>) -> Result<Vec<EmsFit>, String> {
    let Some(path) = path else {
        return Ok(Vec::new());
    };
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    text.lines()
        .enumerate()
        .map(|(n, line)| {
            serde_json::from_str(line).map_err(|e| format!("{}:{}: {e}", path.display(), n + 1))
        })
        .collect()
}
