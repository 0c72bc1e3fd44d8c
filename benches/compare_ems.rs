//! Side by side with EMS (Liu et al., CVPR 2022) on its six published clouds: the point-to-surface
//! residuals of EMS's fits (`assets/data/ems/ems_results.jsonl`, computed by running EMS; see
//! `assets/data/ATTRIBUTION.md`) and of ours, and the recovered parameters.
//!
//! ```text
//! cargo bench --bench compare_ems
//! ```
//!
//! `cargo test` runs it too, and fails when a figure is not a finite number.
//!
//! Residuals: mean / p95 distance of all the cloud's points (outliers included) to the fitted
//! surface, as fractions of the cloud's bounding-box diagonal (`model::fit::residuals`). Pure
//! superquadrics (EMS's and our global-only fits) are tessellated at k = 151 (22 803 nodes) to
//! measure them; our fit with local DOFs is measured on its own 963-node surface. "robust" is
//! `--robust` of `dsq fit`: outlier-robust weights (0.2), point-to-plane springs, the
//! refining stage and the cross-section switch. Semi-axes are listed largest first. Prints a
//! Markdown table.

use bevy_deformable_sq::io::load_points;
use bevy_deformable_sq::model::dynamics::ModelState;
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::fit::{FitOptions, FitReport, Residuals, fit, residuals};
use bevy_deformable_sq::model::init::InitialPose;
use bevy_deformable_sq::model::superquadric::SuperquadricParams;
use std::path::Path;
use std::process::ExitCode;

#[path = "common/ems.rs"]
mod ems;
// It runs whole under `cargo test` too, so it has no use for `mode::benched`.
#[allow(dead_code)]
#[path = "common/mode.rs"]
mod mode;

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
    format!("{:.5} / {:.5}", r.mean, r.p95)
}

fn main() -> ExitCode {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/data/ems");
    let results = match ems::read_results(&root.join("ems_results.jsonl")) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::from(2);
        }
    };
    println!(
        "| cloud | EMS | ours, global only | ours, global only, `--robust` | ours, with local DOFs | EMS ε1, ε2 / semi-axes | ours `--robust` | ours, global only |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for ems in &results {
        let points = match load_points(&root.join(format!("{}.ply", ems.cloud))) {
            Ok(p) => p,
            Err(e) => {
                eprintln!("{e}");
                return ExitCode::from(2);
            }
        };
        let InitialPose {
            translation,
            rotation,
            shape,
        } = ems.pose();
        let fine = Tessellation::new(151);
        // A pure superquadric's residuals, on the fine tessellation.
        let exact = |translation, rotation, shape| {
            let state = ModelState::new(&fine, translation, rotation, shape);
            let mut x = Vec::new();
            state.node_positions(&fine, &mut x);
            residuals(&fine, &x, &points)
        };
        let theirs = exact(translation, rotation, shape);
        let run = |global_only: bool, robust: bool| -> Result<FitReport, String> {
            let mut opts = FitOptions {
                global_only,
                ..Default::default()
            };
            if robust {
                opts = opts.robust();
            }
            fit(&points, &opts, |_| {}).map_err(|e| format!("{}: {e}", ems.cloud))
        };
        let fits = (run(true, false), run(true, true), run(false, false));
        let (Ok(global), Ok(robust), Ok(local)) = fits else {
            eprintln!("a fit of {} failed", ems.cloud);
            return ExitCode::from(2);
        };
        let ours =
            [&global, &robust].map(|r| exact(r.state.translation, r.state.rotation, r.state.shape));
        let figures = [&theirs, &ours[0], &ours[1], &local.residuals].map(|r| [r.mean, r.p95]);
        if let Err(e) = mode::check_finite(&ems.cloud, figures.as_flattened()) {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
        println!(
            "| {} | {} | {} | {} | {} | {} | {} | {} |",
            ems.cloud,
            pair(&theirs),
            pair(&ours[0]),
            pair(&ours[1]),
            pair(&local.residuals),
            describe(&shape),
            describe(&robust.state.shape),
            describe(&global.state.shape),
        );
    }
    ExitCode::SUCCESS
}
