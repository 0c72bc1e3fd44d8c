//! Global tapering and bending (`model::deform`, beyond the paper) against the plain
//! superquadric, in global-only fits of curved, tapered objects.
//!
//! `cargo run --release --example deform [-- --robust]`
//!
//! Objects: a synthetic banana (`synthetic::Banana::default()`: an arc of radius 3 turning ±0.6 rad,
//! round sections of radius 0.4 growing by ±40 % along it, flat ends; 2000 points, noise 0.002,
//! turned and moved off the axes) and the tail of CGAL's cow (`assets/data/cow.obj`, the vertices
//! in the box x < −0.425, y ∈ [−0.17, 0.15], |z| < 0.04: a thin tail hanging from the rump, curving
//! out and thickening into its tuft). For each, four fits: plain, `--taper`, `--bend`, both.
//! Columns: steps, wall time, mean and p95 distance of the points to the fitted surface over the
//! bounding-box diagonal, and the recovered taper (t_x, t_y) and bend (b_x, b_y). `--robust` runs
//! every fit with `FitOptions::robust()`.
use bevy_deformable_sq::io::load_points;
use bevy_deformable_sq::model::fit::{FitOptions, fit};
use bevy_deformable_sq::synthetic::Banana;
use glam::{DQuat, DVec3};
use std::path::Path;

/// The cow's tail: the mesh vertices in its box.
fn cow_tail() -> Result<Vec<DVec3>, String> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/data/cow.obj");
    let all = load_points(&path).map_err(|e| e.to_string())?;
    Ok(all
        .into_iter()
        .filter(|p| p.x < -0.425 && (-0.17..=0.15).contains(&p.y) && p.z.abs() < 0.04)
        .collect())
}

fn main() -> Result<(), String> {
    let robust = std::env::args().any(|a| a == "--robust");
    let turn = DQuat::from_axis_angle(DVec3::new(0.3, 1.0, -0.5).normalize(), 0.9);
    let banana: Vec<DVec3> = Banana::default()
        .points(2000, 0.002, 7)
        .into_iter()
        .map(|p| turn * p + DVec3::new(0.5, -1.0, 2.0))
        .collect();
    let objects = [("banana (synthetic)", banana), ("cow's tail", cow_tail()?)];
    println!("| object | points | free | steps | wall ms | mean | p95 | taper | bend |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for (name, points) in &objects {
        for (taper, bend) in [(false, false), (true, false), (false, true), (true, true)] {
            let mut o = FitOptions {
                global_only: true,
                ..FitOptions::default()
            };
            if robust {
                o = o.robust();
            }
            o.dynamics.free.taper = taper;
            o.dynamics.free.bend = bend;
            let start = std::time::Instant::now();
            let r = fit(points, &o, |_| {}).map_err(|e| format!("{name}: {e}"))?;
            let wall = start.elapsed().as_secs_f64() * 1e3;
            let free = match (taper, bend) {
                (false, false) => "superquadric",
                (true, false) => "taper",
                (false, true) => "bend",
                (true, true) => "taper + bend",
            };
            let d = r.state.deformation;
            println!(
                "| {name} | {} | {free} | {} | {wall:.0} | {:.4} | {:.4} | {:.2}, {:.2} | {:.2}, {:.2} |",
                points.len(),
                r.steps,
                r.residuals.mean,
                r.residuals.p95,
                d.taper[0],
                d.taper[1],
                d.bend[0],
                d.bend[1],
            );
        }
    }
    Ok(())
}
