//! Side by side with EMS (Liu et al., CVPR 2022) on its six published clouds: the point-to-surface
//! residuals of ours and, given EMS's fits, of EMS's, and the recovered parameters.
//!
//! ```text
//! cargo bench --bench compare_ems [-- DIR] [--ems FILE]
//! ```
//!
//! DIR holds the clouds (`*.ply`; default `../shared/data/ems/single_superquadric`, EMS's clouds
//! kept beside the crate, never in it). `--ems FILE` reads EMS's fits of them, made by running
//! EMS outside the crate (JSON lines with `cloud`, `shape`, `scale`, `translation` and `rot`).
//! `cargo test` runs it on six generated clouds instead, and fails when a figure is not a finite
//! number.
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
use glam::DVec3;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[path = "../tests/support/clouds.rs"]
mod clouds;
#[path = "common/ems.rs"]
mod ems;
#[path = "common/mode.rs"]
mod mode;

/// The clouds to fit: `DIR/*.ply` by name when benched, else six generated clouds.
fn clouds_from(dir: Option<&Path>) -> Result<Vec<(String, Vec<DVec3>)>, String> {
    let Some(dir) = dir else {
        return Ok((1..=3)
            .flat_map(|i| {
                [
                    (format!("noisy_{i}"), clouds::noisy(i).points),
                    (format!("partial_{i}"), clouds::partial(i).points),
                ]
            })
            .collect());
    };
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| format!("{}: {e}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "ply"))
        .collect();
    files.sort();
    files
        .iter()
        .map(|f| {
            let name = f
                .file_stem()
                .unwrap_or_default()
                .to_string_lossy()
                .into_owned();
            load_points(f).map(|p| (name, p)).map_err(|e| e.to_string())
        })
        .collect()
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
    format!("{:.5} / {:.5}", r.mean, r.p95)
}

fn main() -> ExitCode {
    let benched = mode::benched();
    let mut dir =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/ems/single_superquadric");
    let mut ems_file = None;
    let mut args = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .filter(|_| benched);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--ems" => ems_file = args.next().map(PathBuf::from),
            _ => dir = PathBuf::from(a),
        }
    }
    let results = match ems::read_results(ems_file.as_deref()) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::from(2);
        }
    };
    let clouds = match clouds_from(benched.then_some(dir.as_path())) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::from(2);
        }
    };
    println!(
        "| cloud | EMS | ours, global only | ours, global only, `--robust` | ours, with local DOFs | EMS ε1, ε2 / semi-axes | ours `--robust` | ours, global only |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for (name, points) in &clouds {
        let ems = results.iter().find(|f| &f.cloud == name);
        let fine = Tessellation::new(151);
        // A pure superquadric's residuals, on the fine tessellation.
        let exact = |translation, rotation, shape| {
            let state = ModelState::new(&fine, translation, rotation, shape);
            let mut x = Vec::new();
            state.node_positions(&fine, &mut x);
            residuals(&fine, &x, points)
        };
        let theirs = ems.map(|e| {
            let InitialPose {
                translation,
                rotation,
                shape,
            } = e.pose();
            (exact(translation, rotation, shape), shape)
        });
        let run = |global_only: bool, robust: bool| -> Result<FitReport, String> {
            let mut opts = FitOptions {
                global_only,
                ..Default::default()
            };
            if robust {
                opts = opts.robust();
            }
            fit(points, &opts, |_| {}).map_err(|e| format!("{name}: {e}"))
        };
        let fits = (run(true, false), run(true, true), run(false, false));
        let (Ok(global), Ok(robust), Ok(local)) = fits else {
            eprintln!("a fit of {name} failed");
            return ExitCode::from(2);
        };
        let ours =
            [&global, &robust].map(|r| exact(r.state.translation, r.state.rotation, r.state.shape));
        let figures = [&ours[0], &ours[1], &local.residuals].map(|r| [r.mean, r.p95]);
        if let Err(e) = mode::check_finite(name, figures.as_flattened()) {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
        println!(
            "| {} | {} | {} | {} | {} | {} | {} | {} |",
            name,
            theirs.map_or("–".into(), |t| pair(&t.0)),
            pair(&ours[0]),
            pair(&ours[1]),
            pair(&local.residuals),
            theirs.map_or("–".into(), |t| describe(&t.1)),
            describe(&robust.state.shape),
            describe(&global.state.shape),
        );
    }
    ExitCode::SUCCESS
}
