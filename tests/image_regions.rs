//! Image fits on a photo-like image: each part's figure is its own (what encloses what), never
//! the image's one threshold. The solved fit (the default) keeps a part within its reach; the
//! paper's dynamics with a region force stop a part that grows without bound, and say so. On a
//! generated desk scene whose truth is known.

use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::fit::Solver;
use bevy_deformable_sq::model::forces::image::{ImageFrame, ImagePotential};
use bevy_deformable_sq::model::image_fit::{
    ImageFitOptions, MAX_GROWTH, PartAxes, fit_image, iou, silhouette_mask,
};
use glam::DVec2;
use std::sync::Arc;

const W: usize = 240;
const H: usize = 180;

/// Ellipse of the scene: centre and semi-axes in pixels, and its grey level.
struct Object {
    centre: DVec2,
    radii: DVec2,
    grey: f64,
}

const OBJECTS: [Object; 2] = [
    // A dark tube standing on the desk, seen from above the table: an upright ellipse.
    Object {
        centre: DVec2::new(165.0, 90.0),
        radii: DVec2::new(22.0, 36.0),
        grey: 0.2,
    },
    // A mid-grey can, seen from its side a little above: a wide ellipse.
    Object {
        centre: DVec2::new(72.0, 95.0),
        radii: DVec2::new(30.0, 20.0),
        grey: 0.5,
    },
];

fn inside(o: &Object, c: usize, r: usize) -> bool {
    let d = (DVec2::new(c as f64, r as f64) - o.centre) / o.radii;
    d.length_squared() <= 1.0
}

/// A white desk sheet with two objects on it, framed by dark, textured clutter: the image's
/// border is dark, so one threshold of the whole image takes the desk for the foreground.
fn desk() -> Vec<f64> {
    let mut lum = Vec::with_capacity(W * H);
    for r in 0..H {
        for c in 0..W {
            let on_desk = (22..W - 22).contains(&c) && (18..H - 18).contains(&r);
            let mut v = if on_desk {
                0.92
            } else {
                // Clutter: stripes between 0.05 and 0.65.
                0.35 + 0.3 * ((c as f64 * 0.45).sin() * (r as f64 * 0.3).cos())
            };
            for o in &OBJECTS {
                if inside(o, c, r) {
                    v = o.grey;
                }
            }
            lum.push(v);
        }
    }
    lum
}

fn potential() -> Arc<ImagePotential> {
    Arc::new(ImagePotential::new(W, H, desk(), 2.0, ImageFrame::default()).unwrap())
}

/// Four clicks a little off each object's axes (both ends of the major axis, then the minor).
fn clicks(o: &Object) -> [DVec2; 4] {
    let (c, r) = (o.centre, o.radii * 0.85);
    let off = DVec2::new(3.0, -2.0);
    if r.y > r.x {
        [
            c + off + DVec2::new(0.0, -r.y),
            c + off + DVec2::new(0.0, r.y),
            c + off + DVec2::new(-r.x, 0.0),
            c + off + DVec2::new(r.x, 0.0),
        ]
    } else {
        [
            c + off + DVec2::new(-r.x, 0.0),
            c + off + DVec2::new(r.x, 0.0),
            c + off + DVec2::new(0.0, -r.y),
            c + off + DVec2::new(0.0, r.y),
        ]
    }
}

#[test]
fn parts_on_a_white_desk_settle_on_their_objects_not_on_the_desk() {
    let p = potential();
    // The premise: the whole image's threshold calls the desk the foreground, and the image is
    // no silhouette, so every part measures its own region.
    let desk_pixel = 40 * W + 120;
    assert!(
        p.foreground()[desk_pixel],
        "the desk is the global foreground"
    );
    assert_eq!(p.two_tone(), None);
    let placed: Vec<PartAxes> = OBJECTS
        .iter()
        .map(|o| PartAxes::from_points(&p, clicks(o)).unwrap())
        .collect();
    let opts = ImageFitOptions {
        local: false,
        ..ImageFitOptions::default()
    };
    let fits = fit_image(p.clone(), &placed, &opts).unwrap();
    let tess = Tessellation::new(opts.k);
    for ((o, f), axes) in OBJECTS.iter().zip(&fits).zip(&placed) {
        let truth: Vec<bool> = (0..W * H).map(|i| inside(o, i % W, i / W)).collect();
        let overlap = |state: &bevy_deformable_sq::model::dynamics::ModelState| {
            let mut x = Vec::new();
            state.node_positions(&tess, &mut x);
            iou(&silhouette_mask(&p, &[(&tess, &x)]), &truth)
        };
        let (before, after) = (overlap(&axes.state(&tess)), overlap(&f.state));
        assert!(f.state.is_finite());
        assert_eq!(f.stopped, None, "grey {}", o.grey);
        assert!(f.converged, "grey {}: not at rest", o.grey);
        assert!(
            after >= 0.9 && after > before,
            "grey {}: IoU {before:.3} → {after:.3}",
            o.grey
        );
    }
}

#[test]
fn a_part_placed_on_the_desk_itself_is_stopped_and_says_why() {
    let p = potential();
    // Clicks on the desk beside the tube, the major axis ending on its edge: the part's spine
    // is desk, its ring takes in the tube, so the desk is the part's object, and nothing on the
    // open desk stops it.
    let axes = PartAxes::from_points(
        &p,
        [
            DVec2::new(118.0, 90.0),
            DVec2::new(148.0, 90.0),
            DVec2::new(133.0, 80.0),
            DVec2::new(133.0, 100.0),
        ],
    )
    .unwrap();
    let opts = ImageFitOptions {
        local: false,
        region: 0.04,
        solver: Solver::Dynamics,
        ..ImageFitOptions::default()
    };
    let fit = &fit_image(p.clone(), &[axes], &opts).unwrap()[0];
    assert!(fit.state.is_finite());
    assert!(!fit.converged);
    let why = fit.stopped.as_deref().expect("stopped");
    assert!(
        why.starts_with(&format!("grew past {MAX_GROWTH}× its placed area")),
        "{why}"
    );
    assert!(fit.steps < opts.max_steps, "{} steps", fit.steps);
    // Solved, the same part comes to rest within its reach: at most MAX_GROWTH times its
    // placed area.
    let solved = &fit_image(p.clone(), &[axes], &ImageFitOptions::default()).unwrap()[0];
    let tess = Tessellation::new(ImageFitOptions::default().k);
    let area = |state: &bevy_deformable_sq::model::dynamics::ModelState| {
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        silhouette_mask(&p, &[(&tess, &x)])
            .iter()
            .filter(|&&b| b)
            .count() as f64
    };
    assert!(solved.state.is_finite() && solved.converged && solved.stopped.is_none());
    let (before, after) = (area(&axes.state(&tess)), area(&solved.state));
    assert!(
        after <= 1.05 * MAX_GROWTH * before,
        "{before} px → {after} px"
    );
}

/// A dark box (a rectangle, half-sizes 30 × 14 px) on the desk below the tube and the can.
fn box_on_desk() -> Vec<f64> {
    let mut lum = desk();
    for r in 0..H {
        for c in 0..W {
            if in_box(c, r) {
                lum[r * W + c] = 0.25;
            }
        }
    }
    lum
}

fn in_box(c: usize, r: usize) -> bool {
    (c as f64 - 110.0).abs() <= 30.0 && (r as f64 - 140.0).abs() <= 14.0
}

#[test]
fn a_box_is_fitted_as_a_box_unless_its_squareness_is_held() {
    let p = Arc::new(ImagePotential::new(W, H, box_on_desk(), 2.0, ImageFrame::default()).unwrap());
    let truth: Vec<bool> = (0..W * H).map(|i| in_box(i % W, i / W)).collect();
    // Clicks a little off the box's axes, 85 % of the way to its sides.
    assert_eq!(p.two_tone(), None);
    let (c, off) = (DVec2::new(110.0, 140.0), DVec2::new(2.0, -1.0));
    let axes = PartAxes::from_points(
        &p,
        [
            c + off + DVec2::new(-25.5, 0.0),
            c + off + DVec2::new(25.5, 0.0),
            c + off + DVec2::new(0.0, -11.9),
            c + off + DVec2::new(0.0, 11.9),
        ],
    )
    .unwrap();
    let tess = Tessellation::new(ImageFitOptions::default().k);
    let fit = |fix_epsilon: bool| {
        let opts = ImageFitOptions {
            local: false,
            fix_epsilon,
            ..ImageFitOptions::default()
        };
        let f = fit_image(p.clone(), &[axes], &opts).unwrap().remove(0);
        let mut x = Vec::new();
        f.state.node_positions(&tess, &mut x);
        let overlap = iou(&silhouette_mask(&p, &[(&tess, &x)]), &truth);
        (f, overlap)
    };
    let (free, free_iou) = fit(false);
    let (held, held_iou) = fit(true);
    assert!(free.state.is_finite() && held.state.is_finite());
    assert!(
        free.converged,
        "ε free: not at rest in {} steps",
        free.steps
    );
    // ε1 shapes the outline (the x–z section); ε2 lies across the view and is held.
    assert!(free.state.shape.e1 < 0.5, "ε1 = {}", free.state.shape.e1);
    assert_eq!(free.state.shape.e2, 1.0);
    assert_eq!((held.state.shape.e1, held.state.shape.e2), (1.0, 1.0));
    // No ellipse covers a rectangle with IoU above about 0.9; a superquadric can.
    assert!(free_iou >= 0.95, "IoU with ε free {free_iou:.3}");
    assert!(
        free_iou > held_iou + 0.03,
        "IoU {free_iou:.3} free against {held_iou:.3} held"
    );
}
