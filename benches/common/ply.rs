//! Generated clouds written for other fitters: an ASCII PLY of the points and a JSON line of the
//! truth, shared by the measurement programs that export their clouds.

use bevy_deformable_sq::model::init::InitialPose;
use glam::DVec3;
use std::io::Write;
use std::path::Path;

/// Writes `points` to `path` as an ASCII PLY with x, y, z vertices.
pub fn write_ascii(path: &Path, points: &[DVec3]) -> std::io::Result<()> {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
    writeln!(f, "ply\nformat ascii 1.0\nelement vertex {}", points.len())?;
    writeln!(
        f,
        "property float x\nproperty float y\nproperty float z\nend_header"
    )?;
    for p in points {
        writeln!(f, "{} {} {}", p.x, p.y, p.z)?;
    }
    f.flush()
}

/// One JSON line naming `cloud` and giving its true pose and shape.
pub fn truth_line(cloud: &str, t: &InitialPose) -> String {
    format!(
        "{{\"cloud\":\"{cloud}\",\"translation\":{:?},\"rotation_xyzw\":{:?},\"semi_axes\":{:?},\"epsilon\":[{},{}]}}\n",
        t.translation.to_array(),
        t.rotation.to_array(),
        t.shape.semi_axes().to_array(),
        t.shape.e1,
        t.shape.e2
    )
}
