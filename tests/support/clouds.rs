//! Generated clouds with known truth, written as ASCII PLY files for the tests that run `dsq`:
//! the crate ships no third party's test clouds, and these stand where EMS's published ones
//! stood (three clean one-view clouds and three noisy clouds with outliers).
#![allow(dead_code)]

use bevy_deformable_sq::synthetic::{CloudRecipe, GroundTruthCloud, ground_truth_cloud};
use glam::DVec3;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Clean one-view clouds: 150–750 points on 40–60 % of a random superquadric, no noise.
pub fn partial(i: u64) -> GroundTruthCloud {
    ground_truth_cloud(
        500 + i,
        &CloudRecipe {
            surface_points: [150, 750, 220][(i as usize - 1) % 3],
            kept: [0.5, 0.6, 0.4][(i as usize - 1) % 3],
            noise: 0.0,
            outliers: 0.0,
            ..CloudRecipe::default()
        },
    )
}

/// Noisy clouds: 450–1000 surface points, noise 1–2 % of the largest semi-axis, 10–20 %
/// outliers, the whole surface or most of it.
pub fn noisy(i: u64) -> GroundTruthCloud {
    ground_truth_cloud(
        600 + i,
        &CloudRecipe {
            surface_points: [1000, 450, 400][(i as usize - 1) % 3],
            kept: [1.0, 0.8, 1.0][(i as usize - 1) % 3],
            noise: [0.01, 0.02, 0.01][(i as usize - 1) % 3],
            outliers: [0.2, 0.1, 0.15][(i as usize - 1) % 3],
            ..CloudRecipe::default()
        },
    )
}

/// Writes `points` to `path` as an ASCII PLY of x, y, z vertices, whole or not at all (through
/// a file of its own renamed into place, so that tests running side by side never read half a
/// file).
pub fn write_ply(path: &Path, points: &[DVec3]) {
    let part = path.with_extension(format!("{:?}.part", std::thread::current().id()));
    write_ply_to(&part, points);
    std::fs::rename(&part, path).expect("a scratch file renamed");
}

fn write_ply_to(path: &Path, points: &[DVec3]) {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).expect("a scratch file"));
    writeln!(f, "ply\nformat ascii 1.0\nelement vertex {}", points.len()).unwrap();
    writeln!(
        f,
        "property double x\nproperty double y\nproperty double z\nend_header"
    )
    .unwrap();
    for p in points {
        writeln!(f, "{:?} {:?} {:?}", p.x, p.y, p.z).unwrap();
    }
    f.flush().unwrap();
}

/// The file `DIR/partial_I.ply` of [`partial`]`(i)`, written when it is not there yet.
pub fn partial_file(dir: &Path, i: u64) -> PathBuf {
    let path = dir.join(format!("partial_{i}.ply"));
    if !path.exists() {
        write_ply(&path, &partial(i).points);
    }
    path
}

/// The file `DIR/noisy_I.ply` of [`noisy`]`(i)`, written when it is not there yet.
pub fn noisy_file(dir: &Path, i: u64) -> PathBuf {
    let path = dir.join(format!("noisy_{i}.ply"));
    if !path.exists() {
        write_ply(&path, &noisy(i).points);
    }
    path
}

/// A folder for generated clouds that every test of a binary shares.
pub fn cloud_dir() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("bdsq_clouds_{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("a scratch folder");
    dir
}
