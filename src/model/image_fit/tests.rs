use super::dynamics::RestCheck;
use super::*;
use glam::{DVec2, DVec3};

#[test]
fn four_points_on_the_ground_place_the_ellipsoid_they_span() {
    // Major axis along x (length 4), minor along z (length 1), on the ground y = 0.
    let pts = [
        DVec3::new(-2.0, 0.0, 0.0),
        DVec3::new(2.0, 0.0, 0.0),
        DVec3::new(0.0, 0.0, -0.5),
        DVec3::new(0.0, 0.0, 0.5),
    ];
    let (c, r, s) = ellipsoid_from_points(pts, DVec3::Y).unwrap();
    assert!(c.length() < 1e-12);
    assert!(
        (r * DVec3::Z - DVec3::X).length() < 1e-12,
        "model z along the major axis"
    );
    assert!(
        (r * DVec3::Y - DVec3::Y).length() < 1e-12,
        "model y along the normal"
    );
    let semi = s.semi_axes();
    assert!(
        (semi - DVec3::new(0.5, 0.5, 2.0)).length() < 1e-12,
        "{semi:?}"
    );
    assert!(ellipsoid_from_points([pts[0]; 4], DVec3::Y).is_none());
}
use crate::model::forces::image::ImageFrame;

/// A dark filled ellipse on a white background.
fn ellipse_image(w: usize, h: usize, c: DVec2, a: f64, b: f64, angle: f64) -> Vec<f64> {
    let (s, co) = angle.sin_cos();
    (0..w * h)
        .map(|i| {
            let d = DVec2::new((i % w) as f64, (i / w) as f64) - c;
            let (u, v) = (co * d.x + s * d.y, -s * d.x + co * d.y);
            if (u / a).powi(2) + (v / b).powi(2) <= 1.0 {
                0.1
            } else {
                0.9
            }
        })
        .collect()
}

fn potential(lum: Vec<f64>, w: usize, h: usize) -> Arc<ImagePotential> {
    Arc::new(ImagePotential::new(w, h, lum, 2.0, ImageFrame::default()).unwrap())
}

#[test]
fn blobs_of_a_dark_ellipse_give_its_centre_and_axes() {
    let (w, h) = (200, 160);
    let c = DVec2::new(90.0, 70.0);
    let lum = ellipse_image(w, h, c, 60.0, 25.0, 0.5);
    let pot = potential(lum, w, h);
    let blobs = segment(&pot, 20);
    assert_eq!(blobs.len(), 1);
    let axes = PartAxes::from_blob(&pot, &blobs[0]).unwrap();
    assert!((pot.to_pixel(axes.center) - c).length() < 0.5);
    let major_px = axes.major.length() / pot.pitch();
    assert!((major_px - 60.0).abs() < 1.0, "{major_px}");
    assert!((axes.minor / pot.pitch() - 25.0).abs() < 1.0);
    // Rows grow downwards, so a positive image angle is clockwise in the plane.
    let angle = axes.major.y.atan2(axes.major.x);
    let expected = -0.5;
    let diff = (angle - expected).rem_euclid(std::f64::consts::PI);
    assert!(diff.min(std::f64::consts::PI - diff) < 0.02, "{angle}");
}

#[test]
fn four_points_place_a_part_and_outside_points_are_refused() {
    let (w, h) = (100, 80);
    let pot = potential(vec![0.5; w * h], w, h);
    let px = [
        DVec2::new(20.0, 40.0),
        DVec2::new(80.0, 40.0),
        DVec2::new(50.0, 30.0),
        DVec2::new(50.0, 50.0),
    ];
    let axes = PartAxes::from_points(&pot, px).unwrap();
    assert!((pot.to_pixel(axes.center) - DVec2::new(50.0, 40.0)).length() < 1e-9);
    assert!((axes.major.length() - 0.3).abs() < 1e-12);
    assert!((axes.minor - 0.1).abs() < 1e-12);
    let (c, r, s) = axes.pose();
    // The model's z axis lies along the major axis; its semi-axes are 0.3 and 0.1.
    assert!(
        (r * DVec3::Z - DVec3::X).length() < 1e-12 || (r * DVec3::Z + DVec3::X).length() < 1e-12
    );
    assert!((s.a * s.a3 - 0.3).abs() < 1e-12 && (s.a * s.a1 - 0.1).abs() < 1e-12);
    assert_eq!(c.z, 0.0);
    let outside = px.map(|p| p + DVec2::new(500.0, 0.0));
    assert!(matches!(
        PartAxes::from_points(&pot, outside),
        Err(PlacementError::OutsideImage { .. })
    ));
    let flat = [px[0], px[0], px[2], px[3]];
    assert_eq!(
        PartAxes::from_points(&pot, flat),
        Err(PlacementError::DegenerateAxis)
    );
}

#[test]
fn a_part_fitted_to_an_ellipse_image_puts_its_outline_on_the_edge() {
    let (w, h) = (160, 160);
    let c = DVec2::new(80.0, 80.0);
    let lum = ellipse_image(w, h, c, 50.0, 22.0, 0.3);
    let pot = potential(lum, w, h);
    // A crude start: centre off by 6 px, axes 20 % off, rotated by 0.2 rad.
    let start = PartAxes {
        center: pot.to_plane(c + DVec2::new(6.0, -4.0)),
        major: DVec2::from_angle(-0.1) * 40.0 * pot.pitch(),
        minor: 26.0 * pot.pitch(),
    };
    let opts = ImageFitOptions {
        k: 16,
        ..Default::default()
    };
    let fits = fit_image(pot.clone(), &[start], &opts).unwrap();
    let f = &fits[0];
    assert!(f.state.is_finite());
    assert!(
        f.outline_after > 0.8 && f.outline_after > f.outline_before + 0.2,
        "outline P/P_ref {} -> {}",
        f.outline_before,
        f.outline_after
    );
    let tess = Tessellation::new(16);
    let mut x0 = Vec::new();
    start.state(&tess).node_positions(&tess, &mut x0);
    let mut x1 = Vec::new();
    f.state.node_positions(&tess, &mut x1);
    let (before, after) = (
        silhouette_iou(&pot, &[(&tess, &x0)]),
        silhouette_iou(&pot, &[(&tess, &x1)]),
    );
    assert!(
        after > 0.9 && after > before + 0.1,
        "IoU {before} -> {after}"
    );
}

#[test]
fn without_the_local_stage_a_part_stays_a_superquadric() {
    let (w, h) = (160, 160);
    let pot = potential(
        ellipse_image(w, h, DVec2::new(80.0, 80.0), 50.0, 22.0, 0.3),
        w,
        h,
    );
    let start = PartAxes {
        center: pot.to_plane(DVec2::new(86.0, 76.0)),
        major: DVec2::from_angle(-0.1) * 40.0 * pot.pitch(),
        minor: 26.0 * pot.pitch(),
    };
    let opts = |local| ImageFitOptions {
        k: 16,
        local,
        ..Default::default()
    };
    let global = &fit_image(pot.clone(), &[start], &opts(false)).unwrap()[0];
    assert_eq!(global.steps, global.global_steps);
    assert!(global.state.displacement.iter().all(|d| *d == DVec3::ZERO));
    assert!(global.outline_after > global.outline_before + 0.2);
    let both = &fit_image(pot.clone(), &[start], &opts(true)).unwrap()[0];
    assert!(both.steps > both.global_steps);
    assert!(both.state.displacement.iter().any(|d| *d != DVec3::ZERO));
}

#[test]
fn a_part_jittering_in_place_is_at_rest_and_one_creeping_is_not() {
    let rest = 1e-3;
    let base = vec![DVec3::ZERO; 4];
    // Each step moves a node by 10 × rest, back and forth, or back and forth with a drift.
    let at = |step: usize, drift: f64| -> Vec<DVec3> {
        let mut x = base.clone();
        x[2].x = if step.is_multiple_of(2) {
            0.0
        } else {
            10.0 * rest
        } + drift * step as f64;
        x
    };
    for (drift, expected) in [(0.0, Some(2 * REST_WINDOW)), (0.05 * rest, None)] {
        let mut check = RestCheck::new(rest);
        let first =
            (1..=10 * REST_WINDOW).find(|&s| check.after_step(&at(s - 1, drift), &at(s, drift)));
        assert_eq!(first, expected, "drift {drift}");
    }
    // A step that moves nothing by more than `rest` is rest at once.
    assert!(RestCheck::new(rest).after_step(&base, &base));
}

#[test]
fn a_part_placed_across_one_edge_of_a_bar_fills_the_bar_instead_of_flattening_onto_the_edge() {
    // A dark vertical bar 24 px wide on white; the part is centred on its left edge, half of
    // it on the background, as a crude placement of a leg would be. Without oriented edges
    // in the global stage, both sides of the part settle on that one edge (area 0).
    let (w, h) = (160, 160);
    let lum = (0..w * h)
        .map(|i| {
            if (72..96).contains(&(i % w)) {
                0.1
            } else {
                0.9
            }
        })
        .collect();
    let pot = potential(lum, w, h);
    let start = PartAxes {
        center: pot.to_plane(DVec2::new(72.0, 80.0)),
        major: DVec2::new(0.0, 40.0 * pot.pitch()),
        minor: 8.0 * pot.pitch(),
    };
    let opts = ImageFitOptions {
        k: 16,
        region: 0.1,
        max_steps: 1500,
        solver: Solver::Dynamics,
        ..Default::default()
    };
    let fit = &fit_image(pot.clone(), &[start], &opts).unwrap()[0];
    assert!(fit.state.is_finite());
    let tess = Tessellation::new(16);
    let mut x = Vec::new();
    fit.state.node_positions(&tess, &mut x);
    let s = part_silhouette(&pot, &tess, &x);
    assert!((s.width - 24.0).abs() < 2.0, "{s:?}");
    assert!(s.on_foreground > 0.9, "{s:?}");
}
