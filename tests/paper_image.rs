//! The paper's image experiments (section VI-A) on the shipped stand-in images, and image forces
//! driven through `DeformableSqPlugin`.
//!
//! The measure of a fit is the mean of P / P_ref along the parts' projected outlines (1 on a
//! typical strong edge, 0 in flat regions) and, for the silhouette image, the IoU of the parts'
//! projected silhouettes with the thresholded foreground. Both must clearly improve from the
//! crude initial placement to the fitted state.

use bevy::prelude::*;
use bevy::time::TimeUpdateStrategy;
use bevy_deformable_sq::io::load_luminance;
use bevy_deformable_sq::model::dynamics::{ModelState, NodalForces, Workspace, step};
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::forces::image::{ImageForces, ImageFrame, ImagePotential};
use bevy_deformable_sq::model::image_fit::{
    ImageExperiment, ImageFitOptions, ImagePartFit, PartAxes, PartSilhouette, doll_experiment,
    fit_image, outline_potential, part_silhouette, parts_on, pestle_experiment, silhouette_iou,
};
use bevy_deformable_sq::plugin::ImageData;
use bevy_deformable_sq::prelude::*;
use glam::{DVec2, DVec3};
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

struct Outcome {
    outline: (f64, f64),
    iou: (f64, f64),
    fits: Vec<ImagePartFit>,
    /// Each part's silhouette after the fit.
    parts: Vec<PartSilhouette>,
}

/// Runs an experiment with a step cap per part.
fn run(e: &ImageExperiment, max_steps: usize) -> Outcome {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(e.image);
    let (w, h, lum) = load_luminance(&path).unwrap();
    let potential =
        Arc::new(ImagePotential::new(w, h, lum, e.sigma, ImageFrame::default()).unwrap());
    let placed: Vec<PartAxes> = e
        .parts
        .iter()
        .map(|(_, p)| PartAxes::from_points(&potential, *p).unwrap())
        .collect();
    let mut opts = e.options;
    opts.max_steps = max_steps;
    let fits = fit_image(potential.clone(), &placed, &opts).unwrap();
    let tess = Tessellation::new(opts.k);
    let xs = |states: Vec<ModelState>| -> Vec<Vec<DVec3>> {
        states
            .iter()
            .map(|s| {
                let mut x = Vec::new();
                s.node_positions(&tess, &mut x);
                x
            })
            .collect()
    };
    let before = xs(placed.iter().map(|p| p.state(&tess)).collect());
    let after = xs(fits.iter().map(|f| f.state.clone()).collect());
    let outline = (
        outline_potential(&potential, &parts_on(&tess, &before)),
        outline_potential(&potential, &parts_on(&tess, &after)),
    );
    let iou = (
        silhouette_iou(&potential, &parts_on(&tess, &before)),
        silhouette_iou(&potential, &parts_on(&tess, &after)),
    );
    let parts = after
        .iter()
        .map(|x| part_silhouette(&potential, &tess, x))
        .collect();
    Outcome {
        outline,
        iou,
        fits,
        parts,
    }
}

#[test]
fn pestle_outline_moves_onto_the_rockets_edges() {
    let e = pestle_experiment();
    assert_eq!(Tessellation::new(e.options.k).node_count(), 5043);
    let o = run(&e, 800);
    let f = &o.fits[0];
    assert!(f.state.is_finite());
    // ε stays fixed at 1, the part stays in the image plane.
    assert_eq!((f.state.shape.e1, f.state.shape.e2), (1.0, 1.0));
    assert_eq!(f.state.translation.z, 0.0);
    assert!(
        o.outline.1 > 0.9 && o.outline.1 > o.outline.0 + 0.3,
        "outline P/P_ref {:.3} -> {:.3}",
        o.outline.0,
        o.outline.1
    );
}

#[test]
fn doll_parts_move_onto_the_horses_silhouette() {
    let e = doll_experiment();
    assert_eq!(e.parts.len(), 11);
    assert_eq!(Tessellation::new(e.options.k).node_count(), 963);
    let o = run(&e, e.options.max_steps);
    assert!(o.fits.iter().all(|f| f.state.is_finite()));
    assert!(
        o.outline.1 > 0.8 && o.outline.1 > o.outline.0 + 0.4,
        "outline P/P_ref {:.3} -> {:.3}",
        o.outline.0,
        o.outline.1
    );
    assert!(
        o.iou.1 > 0.85 && o.iou.1 > o.iou.0 + 0.15,
        "silhouette IoU {:.3} -> {:.3}",
        o.iou.0,
        o.iou.1
    );
    // Most parts individually end on edges.
    let on_edges = o.fits.iter().filter(|f| f.outline_after > 0.75).count();
    assert!(on_edges >= 8, "{on_edges} of 11 parts end on edges");
    // The union covers the horse, and no part is a sliver or off the horse (issue 44's targets).
    assert!(o.iou.1 >= 0.92, "silhouette IoU {:.3}", o.iou.1);
    for ((name, _), s) in e.parts.iter().zip(&o.parts) {
        assert!(
            s.area >= 150 && s.width >= 5.0 && s.on_foreground >= 0.9,
            "{name}: {s:?}"
        );
    }
}

/// A dark ellipse on white, 120×120.
fn ellipse_potential() -> Arc<ImagePotential> {
    let (w, h) = (120usize, 120usize);
    let lum = (0..w * h)
        .map(|i| {
            let d = DVec2::new((i % w) as f64 - 60.0, (i / w) as f64 - 60.0);
            if (d.x / 38.0).powi(2) + (d.y / 18.0).powi(2) <= 1.0 {
                0.1
            } else {
                0.9
            }
        })
        .collect();
    Arc::new(ImagePotential::new(w, h, lum, 2.0, ImageFrame::default()).unwrap())
}

#[test]
fn image_forces_through_the_plugin_equal_the_core_step_for_step() {
    let potential = ellipse_potential();
    let start = PartAxes {
        center: DVec2::new(0.02, -0.01),
        major: DVec2::new(0.27, 0.03),
        minor: 0.12,
    };
    let k = 12;
    let tess = Tessellation::new(k);
    let (c, r, s) = start.pose();
    let settings = ModelSettings {
        planar: true,
        fix_epsilon: true,
        ..default()
    };
    let mut app = App::new();
    app.add_plugins(MinimalPlugins)
        .add_plugins(DeformableSqPlugin::default());
    app.insert_resource(TimeUpdateStrategy::ManualDuration(Duration::from_secs_f64(
        1.0 / 64.0,
    )));
    let e = app
        .world_mut()
        .spawn((
            GlobalShape::from(s),
            RigidState {
                translation: c,
                rotation: r,
            },
            FemMesh::new(k),
            settings,
            ImageData::new(potential.clone()),
        ))
        .id();
    let steps = 60;
    for _ in 0..steps * 4 {
        app.update();
        if app.world().get::<SimControl>(e).unwrap().steps >= steps {
            break;
        }
    }
    assert_eq!(app.world().get::<SimControl>(e).unwrap().steps, steps);
    // The same steps in the core.
    let forces = ImageForces::new(potential.clone());
    let mut state = ModelState::new(&tess, c, r, s);
    let params = settings.dynamics();
    let (mut ws, mut nf, mut x) = (Workspace::default(), NodalForces::default(), Vec::new());
    let mut x0 = Vec::new();
    state.node_positions(&tess, &mut x0);
    for _ in 0..steps {
        state.node_positions(&tess, &mut x);
        nf.clear(tess.node_count());
        forces.accumulate(&tess, &x, &mut nf);
        step(&tess, &mut state, &nf, &params, &mut ws).unwrap();
    }
    let w = app.world();
    assert_eq!(
        w.get::<RigidState>(e).unwrap().translation,
        state.translation
    );
    assert_eq!(w.get::<RigidState>(e).unwrap().rotation, state.rotation);
    assert_eq!(
        w.get::<LocalDofs>(e).unwrap().displacement,
        state.displacement
    );
    state.node_positions(&tess, &mut x);
    let (before, after) = (
        outline_potential(&potential, &[(&tess, &x0)]),
        outline_potential(&potential, &[(&tess, &x)]),
    );
    assert!(after > before + 0.2, "outline {before:.3} -> {after:.3}");
}

/// A label image shipped beside a photo (`assets/data/*_mask.png`, 8-bit gray): 0 is background,
/// k the k-th object's pixels. Returns the labels, row-major.
fn load_labels(name: &str) -> (usize, usize, Vec<u8>) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("assets/data")
        .join(name);
    let (w, h, lum) = load_luminance(&path).unwrap();
    (
        w,
        h,
        lum.iter().map(|l| (l * 255.0).round() as u8).collect(),
    )
}

/// Four pixel points on an object's mask as a user would click them: both ends of its major
/// axis, then both ends of its minor axis, each 2σ from the centroid along the axis (a disc's
/// radius), rounded to whole pixels.
fn four_points(w: usize, labels: &[u8], k: u8) -> [DVec2; 4] {
    let pixels: Vec<DVec2> = (0..labels.len())
        .filter(|&i| labels[i] == k)
        .map(|i| DVec2::new((i % w) as f64, (i / w) as f64))
        .collect();
    let n = pixels.len() as f64;
    let c = pixels.iter().copied().sum::<DVec2>() / n;
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for p in &pixels {
        let d = *p - c;
        (sxx, sxy, syy) = (
            sxx + d.x * d.x / n,
            sxy + d.x * d.y / n,
            syy + d.y * d.y / n,
        );
    }
    let mean = (sxx + syy) / 2.0;
    let spread = (((sxx - syy) / 2.0).powi(2) + sxy * sxy).sqrt();
    let (l1, l2) = (mean + spread, (mean - spread).max(0.0));
    let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let e1 = DVec2::new(angle.cos(), angle.sin());
    let (a, b) = (2.0 * l1.sqrt() * e1, 2.0 * l2.sqrt() * e1.perp());
    [c - a, c + a, c - b, c + b].map(|p| p.round())
}

/// `points` as a hurried user clicks them: each off by up to `slop` × the minor semi-axis in x
/// and in y (deterministic), rounded to whole pixels.
fn clicked(
    points: [DVec2; 4],
    slop: f64,
    rng: &mut bevy_deformable_sq::synthetic::Rng,
) -> [DVec2; 4] {
    let radius = (points[3] - points[2]).length() / 2.0;
    points.map(|p| {
        (p + slop * radius * DVec2::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0))).round()
    })
}

/// Fits every object of a photo from its four points and returns, per object, the IoU of the
/// part's silhouette with the object's mask and whether the part came to rest.
fn photo_fits(image: &str, mask: &str, opts: &ImageFitOptions, slop: f64) -> Vec<(f64, f64, bool)> {
    use bevy_deformable_sq::model::image_measure::{iou, silhouette_mask};
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("assets/data")
        .join(image);
    let (w, h, lum) = load_luminance(&path).unwrap();
    let potential = Arc::new(ImagePotential::new(w, h, lum, 2.0, ImageFrame::default()).unwrap());
    let (mw, mh, labels) = load_labels(mask);
    assert_eq!((mw, mh), (w, h));
    let objects = *labels.iter().max().unwrap();
    let mut rng = bevy_deformable_sq::synthetic::Rng::new(5);
    let placed: Vec<PartAxes> = (1..=objects)
        .map(|k| {
            let points = clicked(four_points(w, &labels, k), slop, &mut rng);
            PartAxes::from_points(&potential, points).unwrap()
        })
        .collect();
    let fits = fit_image(potential.clone(), &placed, opts).unwrap();
    let tess = Tessellation::new(opts.k);
    let overlap = |state: &ModelState, k: u8| {
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        let part = silhouette_mask(&potential, &[(&tess, &x)]);
        let object: Vec<bool> = labels.iter().map(|&l| l == k).collect();
        iou(&part, &object)
    };
    fits.iter()
        .zip(&placed)
        .zip(1..=objects)
        .map(|((f, p), k)| {
            (
                overlap(&p.state(&tess), k),
                overlap(&f.state, k),
                f.converged,
            )
        })
        .collect()
}

#[test]
fn coins_placed_by_rough_clicks_fit_their_outlines_and_come_to_rest() {
    // The 24 coins of a real photo (assets/data/coins.png; masks made for this test, see
    // ATTRIBUTION.md), each placed from four clicks up to half its radius off, fitted as pure
    // superquadrics with the region force. Measured: IoU with the masks 0.51–0.91 (mean 0.72) as
    // placed, 0.934–0.965 (mean 0.950) fitted with ε1 free (0.931–0.963 with ε held), every part at
    // rest.
    let opts = ImageFitOptions {
        local: false,
        region: 0.04,
        ..ImageFitOptions::default()
    };
    let coins = photo_fits("coins.png", "coins_mask.png", &opts, 0.5);
    assert_eq!(coins.len(), 24);
    let placed = coins.iter().map(|c| c.0).fold(1.0, f64::min);
    assert!(
        placed < 0.6,
        "the clicks are rough: least IoU as placed {placed}"
    );
    for (i, &(before, after, at_rest)) in coins.iter().enumerate() {
        assert!(at_rest, "coin {}: not at rest", i + 1);
        assert!(after >= 0.9, "coin {}: IoU {before:.3} → {after:.3}", i + 1);
    }
}
