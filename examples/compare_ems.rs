//! Side by side with EMS (Liu et al., CVPR 2022) on its six published clouds: the point-to-surface
//! residuals of EMS's fits (`assets/data/ems/ems_results.jsonl`, computed by running EMS; see
//! `assets/data/ATTRIBUTION.md`) and of ours, and the recovered parameters.
//!
//! ```text
//! cargo run --release --example compare_ems
//! ```
//!
//! Residuals: mean / p95 distance of all the cloud's points (outliers included) to the fitted
//! surface, as fractions of the cloud's bounding-box diagonal (`model::fit::residuals`). EMS's
//! superquadric is tessellated at k = 151 (22 803 nodes) to measure it; ours is measured on its
//! own 963-node surface. Semi-axes are listed largest first. Prints a Markdown table.

use bevy::math::{DMat3, DQuat, DVec3};
use bevy_deformable_sq::io::load_points;
use bevy_deformable_sq::model::dynamics::ModelState;
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::fit::{FitOptions, FitReport, Residuals, fit, residuals};
use bevy_deformable_sq::model::superquadric::SuperquadricParams;
use std::path::Path;
use std::process::ExitCode;

/// One line of `ems_results.jsonl`.
#[derive(serde::Deserialize)]
struct EmsFit {
    cloud: String,
    shape: [f64; 2],
    scale: [f64; 3],
    translation: [f64; 3],
    /// Rotation matrix, row-major (model frame → world).
    rot: [f64; 9],
}

/// ε1, ε2 and the semi-axes largest first.
fn describe(q: &SuperquadricParams) -> String {
    let s = q.semi_axes();
    let mut axes = [s.x, s.y, s.z];
    axes.sort_by(|a, b| b.total_cmp(a));
    format!(
        "{:.2}, {:.2} / {:.2}, {:.2}, {:.2}",
        q.e1, q.e2, axes[0], axes[1], axes[2]
    )
}

fn pair(r: &Residuals) -> String {
    format!("{:.4} / {:.4}", r.mean, r.p95)
}

fn main() -> ExitCode {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/data/ems");
    let text = match std::fs::read_to_string(root.join("ems_results.jsonl")) {
        Ok(t) => t,
        Err(e) => {
            eprintln!("{}: {e}", root.join("ems_results.jsonl").display());
            return ExitCode::from(2);
        }
    };
    println!(
        "| cloud | EMS | ours, global only | ours, global only, `--outliers 0.2 --plane` | ours, with local DOFs | EMS ε1, ε2 / semi-axes | ours `--outliers 0.2 --plane` | ours, global only |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for (n, line) in text.lines().enumerate() {
        let ems: EmsFit = match serde_json::from_str(line) {
            Ok(v) => v,
            Err(e) => {
                eprintln!("ems_results.jsonl:{}: {e}", n + 1);
                return ExitCode::from(2);
            }
        };
        let points = match load_points(&root.join(format!("{}.ply", ems.cloud))) {
            Ok(p) => p,
            Err(e) => {
                eprintln!("{e}");
                return ExitCode::from(2);
            }
        };
        let r = ems.rot;
        let rotation = DQuat::from_mat3(&DMat3::from_cols_array(&[
            r[0], r[3], r[6], r[1], r[4], r[7], r[2], r[5], r[8],
        ]))
        .normalize();
        let a = ems.scale.iter().copied().fold(0.0, f64::max);
        let shape = SuperquadricParams {
            a,
            a1: ems.scale[0] / a,
            a2: ems.scale[1] / a,
            a3: ems.scale[2] / a,
            e1: ems.shape[0],
            e2: ems.shape[1],
        };
        let tess = Tessellation::new(151);
        let state = ModelState::new(&tess, DVec3::from_array(ems.translation), rotation, shape);
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        let theirs = residuals(&tess, &x, &points);
        let run = |global_only: bool, robust: bool| -> Result<FitReport, String> {
            let opts = FitOptions {
                global_only,
                point_to_plane: robust,
                outlier_ratio: if robust { 0.2 } else { 0.0 },
                ..Default::default()
            };
            fit(&points, &opts, |_| {}).map_err(|e| format!("{}: {e}", ems.cloud))
        };
        let fits = (run(true, false), run(true, true), run(false, false));
        let (Ok(global), Ok(robust), Ok(local)) = fits else {
            eprintln!("a fit of {} failed", ems.cloud);
            return ExitCode::from(2);
        };
        println!(
            "| {} | {} | {} | {} | {} | {} | {} | {} |",
            ems.cloud,
            pair(&theirs),
            pair(&global.residuals),
            pair(&robust.residuals),
            pair(&local.residuals),
            describe(&shape),
            describe(&robust.state.shape),
            describe(&global.state.shape),
        );
    }
    ExitCode::SUCCESS
}
