//! Global parameters as part descriptors: fits a small library of parts, then finds the nearest
//! library part for query parts that are the same objects seen differently (turned, scaled, or a
//! second instance), by `model::descriptor::ShapeDescriptor::distance`.
//!
//! ```text
//! cargo run --release --example index [-- --with-size]
//! ```
//!
//! Library: the cow scene's body, head, back leg 1 and fore leg 1 (`assets/scenes/cow.dsq.ron`),
//! the paper's egg and mug clouds (`synthetic`), and three generated one-view clouds (noise-free
//! points on 40–60 % of a random superquadric, `synthetic::ground_truth_cloud`). Queries: the cow's
//! other two legs, and a second "scan" of every other library cloud: half its points, with noise
//! of 1 % of its size, turned by 90° about a tilted axis and scaled ×3 (×1 with `--with-size`). Descriptors are
//! scale-free unless `--with-size`. Prints one line per query: the nearest part, its distance and
//! the runner-up's, and how many queries found their own object. (The one-view clouds show one
//! side of their object: half of them, with noise, can fit a noticeably different superquadric,
//! so the descriptor of a one-view fit is only as determined as the view.)

use bevy_deformable_sq::model::descriptor::{ShapeDescriptor, nearest_part};
use bevy_deformable_sq::model::fit::{FitOptions, fit};
use bevy_deformable_sq::scene::{PartRun, SceneDef, run_scene};
use bevy_deformable_sq::synthetic;
use glam::{DQuat, DVec3};
use std::path::Path;
use std::process::ExitCode;

/// Length of the bounding-box diagonal of `points`.
fn bbox_diagonal(points: &[DVec3]) -> f64 {
    let (lo, hi) = points.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    (hi - lo).length()
}

fn main() -> ExitCode {
    let with_size = std::env::args().any(|a| a == "--with-size");
    let describe = |shape: &bevy_deformable_sq::model::superquadric::SuperquadricParams| {
        let d = ShapeDescriptor::new(shape);
        if with_size { d } else { d.scale_free() }
    };
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    // The cow's parts, fitted by the scene runner.
    let (def, data) = match SceneDef::load_file(&root.join("assets/scenes/cow.dsq.ron")) {
        Ok(x) => x,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::from(2);
        }
    };
    let mut cow = Vec::new();
    for (part, run) in def.parts.iter().zip(run_scene(&def, &data, None)) {
        match run {
            Ok(PartRun::Range(report)) => cow.push((part.name.clone(), report.state.shape)),
            Ok(_) => {}
            Err(e) => {
                eprintln!("{}: {e}", part.name);
                return ExitCode::from(2);
            }
        }
    }
    // Point clouds fitted here, as they are and turned + scaled.
    let turn = DQuat::from_axis_angle(DVec3::new(1.0, 1.0, 0.3).normalize(), 90f64.to_radians());
    // Scale-free descriptors do not see size; with size, the queries keep theirs.
    let scale = if with_size { 1.0 } else { 3.0 };
    let mut clouds: Vec<(String, Vec<DVec3>)> = vec![
        ("egg".into(), synthetic::egg()),
        ("mug".into(), synthetic::mug()),
    ];
    for n in 1..=3u64 {
        let recipe = synthetic::CloudRecipe {
            surface_points: [150, 750, 220][n as usize - 1],
            kept: [0.5, 0.6, 0.4][n as usize - 1],
            noise: 0.0,
            outliers: 0.0,
            ..synthetic::CloudRecipe::default()
        };
        let cloud = synthetic::ground_truth_cloud(500 + n, &recipe);
        clouds.push((format!("one-view cloud {n}"), cloud.points));
    }
    let opts = FitOptions {
        global_only: true,
        ..Default::default()
    };
    let mut library: Vec<(String, ShapeDescriptor)> = Vec::new();
    let mut queries: Vec<(String, String, ShapeDescriptor)> = Vec::new();
    for (name, shape) in &cow {
        let d = describe(shape);
        if name.ends_with('2') {
            let own = name.trim_end_matches('2').to_string() + "1";
            queries.push((format!("cow {name}"), format!("cow {own}"), d));
        } else {
            library.push((format!("cow {name}"), d));
        }
    }
    for (name, points) in &clouds {
        // Another scan of the object: every other point, turned, scaled, with noise of 1 % of
        // its size.
        let size = bbox_diagonal(points);
        let mut seed = 7u64;
        let mut noise = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.02 * size
        };
        let moved: Vec<DVec3> = points
            .iter()
            .skip(1)
            .step_by(2)
            .map(|p| scale * (turn * (*p + DVec3::new(noise(), noise(), noise()))))
            .collect();
        for (pts, is_query) in [(points, false), (&moved, true)] {
            match fit(pts, &opts, |_| {}) {
                Ok(r) if is_query => queries.push((
                    format!("{name}, rescanned ×{scale}"),
                    name.clone(),
                    describe(&r.state.shape),
                )),
                Ok(r) => library.push((name.clone(), describe(&r.state.shape))),
                Err(e) => {
                    eprintln!("{name}: {e}");
                    return ExitCode::from(2);
                }
            }
        }
    }
    let descriptors: Vec<ShapeDescriptor> = library.iter().map(|(_, d)| *d).collect();
    println!(
        "library of {} parts ({} descriptors)",
        library.len(),
        if with_size { "with size" } else { "scale-free" }
    );
    let mut right_count = 0;
    for (query, own, d) in &queries {
        let Some((i, dist)) = nearest_part(&descriptors, d) else {
            continue;
        };
        let runner_up = descriptors
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != i)
            .map(|(_, e)| d.distance(e))
            .fold(f64::INFINITY, f64::min);
        let right = library[i].0 == *own;
        right_count += usize::from(right);
        println!(
            "{query:42} → {:30} distance {dist:.3} (next {runner_up:.3}){}",
            library[i].0,
            if right { "" } else { "  (not its own object)" }
        );
    }
    println!(
        "{right_count} of {} queries found their own object",
        queries.len()
    );
    ExitCode::SUCCESS
}
