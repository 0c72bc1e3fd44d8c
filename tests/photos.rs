//! Photos fitted from a user's four clicks per object, scored by IoU against masks made for the
//! tests (`assets/data/*_mask.png`; see `assets/data/ATTRIBUTION.md`), in every documented image
//! mode.

use bevy_deformable_sq::io::{load_image, load_luminance};
use bevy_deformable_sq::model::dynamics::ModelState;
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::fit::Solver;
use bevy_deformable_sq::model::forces::image::{ImageFrame, ImagePotential};
use bevy_deformable_sq::model::image_fit::{
    ImageFitOptions, PartAxes, fit_image, part_silhouette, parts_on, silhouette_iou,
};
use bevy_deformable_sq::model::image_measure::mask_axis_ends;
use bevy_deformable_sq::synthetic::doll_experiment;
use glam::DVec2;
use std::path::Path;
use std::sync::Arc;

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
    let object: Vec<bool> = labels.iter().map(|&l| l == k).collect();
    mask_axis_ends(w, &object)
        .expect("every label has pixels")
        .map(|p| p.round())
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
    // As `dsq fit --image` reads a photo: its luminance and its colour.
    let (w, h, lum, rgb) = load_image(&path).unwrap();
    let potential = Arc::new(
        ImagePotential::new(w, h, lum, 2.0, ImageFrame::default())
            .unwrap()
            .with_colour(rgb)
            .unwrap(),
    );
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
fn coins_fitted_by_the_papers_dynamics_with_a_region_force_come_to_rest() {
    // The 24 coins of a real photo (assets/data/coins.png; masks made for this test, see
    // ATTRIBUTION.md), each placed from four clicks up to half its radius off, fitted as pure
    // superquadrics by the paper's dynamics with the region force. Measured: IoU with the masks 0.51–0.91 (mean 0.72) as
    // placed, 0.934–0.965 (mean 0.950) fitted with ε1 free (0.931–0.963 with ε held), every part at
    // rest.
    let opts = ImageFitOptions {
        local: false,
        region: 0.04,
        solver: Solver::Dynamics,
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

/// Every documented image mode of the solved fit: the default (local DOFs), `--global-only`, and
/// `--global-only --fix-epsilon`.
fn solved_modes() -> [(&'static str, ImageFitOptions); 3] {
    let d = ImageFitOptions::default();
    [
        ("default", d),
        ("global only", ImageFitOptions { local: false, ..d }),
        (
            "global only, ε held",
            ImageFitOptions {
                local: false,
                fix_epsilon: true,
                ..d
            },
        ),
    ]
}

#[test]
fn coins_come_to_rest_on_their_outlines_in_every_solved_mode() {
    // Measured (release): least IoU 0.929 / 0.932 / 0.929, 24 of 24
    // at rest in each mode (IoU 0.51–0.91 as placed).
    for (mode, opts) in solved_modes() {
        let coins = photo_fits("coins.png", "coins_mask.png", &opts, 0.5);
        assert_eq!(coins.len(), 24);
        for (i, &(before, after, at_rest)) in coins.iter().enumerate() {
            assert!(at_rest, "{mode}: coin {} not at rest", i + 1);
            assert!(
                after >= 0.9,
                "{mode}: coin {}: IoU {before:.3} → {after:.3}",
                i + 1
            );
        }
    }
}

#[test]
fn the_crema_and_the_spoon_of_a_colour_photo_come_to_rest_in_every_solved_mode() {
    // scikit-image's coffee photo (CC0), masks drawn by hand (assets/data/coffee_mask.png: 1 the
    // crema, 2 the spoon's bowl). The crema's figure is the watershed's from its clicks, bounded
    // by the cup's rim. The reflective bowl's figure runs up its neck to the cup's dark foot,
    // and its outline follows it there (docs/results.md).
    // Measured (release): crema 0.83 as placed → 0.895 / 0.902 / 0.900, spoon 0.71 → 0.720 /
    // 0.689 / 0.721, at rest.
    for (mode, opts) in solved_modes() {
        let fits = photo_fits("coffee.png", "coffee_mask.png", &opts, 0.5);
        assert_eq!(fits.len(), 2);
        for (k, &(before, after, at_rest)) in fits.iter().enumerate() {
            assert!(at_rest, "{mode}: object {} not at rest", k + 1);
            let least = [0.88, 0.65][k];
            assert!(
                after >= least,
                "{mode}: object {}: IoU {before:.3} → {after:.3}",
                k + 1
            );
        }
    }
}

#[test]
fn the_dolls_eleven_parts_come_to_rest_on_the_horse() {
    // The paper's doll experiment (its placements on assets/data/horse.png), solved: every part
    // at rest, the union's IoU with the horse at least 0.93, no part under 5 px wide or 150 px,
    // each at least 90 % on the horse. Measured (release): IoU 0.959, widths ≥ 9.3 px, areas ≥
    // 366 px, each ≥ 92.1 % on the horse.
    let e = doll_experiment();
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(e.image);
    let (w, h, lum) = load_luminance(&path).unwrap();
    let potential =
        Arc::new(ImagePotential::new(w, h, lum, e.sigma, ImageFrame::default()).unwrap());
    let placed: Vec<PartAxes> = e
        .parts
        .iter()
        .map(|(_, p)| PartAxes::from_points(&potential, *p).unwrap())
        .collect();
    let fits = fit_image(potential.clone(), &placed, &e.options).unwrap();
    let tess = Tessellation::new(e.options.k);
    let xs: Vec<Vec<glam::DVec3>> = fits
        .iter()
        .map(|f| {
            let mut x = Vec::new();
            f.state.node_positions(&tess, &mut x);
            x
        })
        .collect();
    let iou = silhouette_iou(&potential, &parts_on(&tess, &xs));
    assert!(iou >= 0.93, "union IoU {iou:.3}");
    for (((name, _), f), x) in e.parts.iter().zip(&fits).zip(&xs) {
        let s = part_silhouette(&potential, &tess, x);
        assert!(f.state.is_finite() && f.converged, "{name}: not at rest");
        assert!(
            s.width >= 5.0 && s.area >= 150 && s.on_foreground >= 0.8,
            "{name}: {s:?}"
        );
    }
}

#[test]
fn the_doll_scene_solves_its_parts_together_as_dsq_fit_paper_doll_does() {
    use bevy_deformable_sq::scene::{PartRun, SceneDef, run_scene};
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/scenes/doll.dsq.ron");
    let (def, data) = SceneDef::load_file(&file).unwrap();
    let runs = run_scene(&def, &data, None);
    let e = doll_experiment();
    let potential = data.images.values().next().unwrap().clone();
    let placed: Vec<PartAxes> = e
        .parts
        .iter()
        .map(|(_, p)| PartAxes::from_points(&potential, *p).unwrap())
        .collect();
    let fits = fit_image(potential, &placed, &e.options).unwrap();
    assert_eq!(runs.len(), fits.len());
    for (run, fit) in runs.iter().zip(&fits) {
        let Ok(PartRun::Image(run)) = run else {
            panic!("not an image part: {run:?}")
        };
        assert_eq!(run.state, fit.state);
        assert!(run.converged);
    }
}

#[test]
fn generated_photos_objects_whose_faces_differ_are_found_whole_in_every_solved_mode() {
    // Generated photos with a known truth (synthetic::photo), each object with a face within 3 %
    // of the desk's luminance: seed 3, a box and a cylinder on a cluttered desk, blurred and
    // noisy; seed 54, a box on a grained desk with noise 0.03; seed 87, a cylinder and a box on
    // a grained desk. Clicks up to a quarter of the size off. One threshold of the placement
    // joined the bright faces to the desk (seed 54: IoU 0.29–0.33, seed 87's cylinder
    // 0.79–0.89); the watershed from the clicks keeps them. Measured (release): 0.866–0.945.
    use bevy_deformable_sq::model::image_measure::{iou, silhouette_mask};
    use bevy_deformable_sq::synthetic::{PHOTO_HEIGHT, PHOTO_WIDTH, photo};
    for seed in [3, 54, 87] {
        let p = photo(seed);
        let pot = Arc::new(
            ImagePotential::new(
                PHOTO_WIDTH,
                PHOTO_HEIGHT,
                p.luminance(),
                2.0,
                ImageFrame::default(),
            )
            .unwrap()
            .with_colour(p.rgb.clone())
            .unwrap(),
        );
        let placed: Vec<PartAxes> = p
            .objects
            .iter()
            .map(|o| PartAxes::from_points(&pot, o.clicks).unwrap())
            .collect();
        for (mode, opts) in solved_modes() {
            let tess = Tessellation::new(opts.k);
            let fits = fit_image(pot.clone(), &placed, &opts).unwrap();
            for (f, o) in fits.iter().zip(&p.objects) {
                let mut x = Vec::new();
                f.state.node_positions(&tess, &mut x);
                let score = iou(&silhouette_mask(&pot, &[(&tess, &x)]), &o.mask);
                assert!(
                    f.converged,
                    "photo {seed}, {mode}: the {} not at rest",
                    o.kind
                );
                assert!(
                    score >= 0.85,
                    "photo {seed}, {mode}: the {}: IoU {score:.3}",
                    o.kind
                );
            }
        }
    }
}
