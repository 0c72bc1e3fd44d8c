//! Global tapering and bending (`model::deform`, beyond the paper) in whole fits: on a curved,
//! tapered object they capture what the plain superquadric cannot.

use bevy_deformable_sq::model::fit::{FitOptions, FitReport, fit};
use bevy_deformable_sq::synthetic::Banana;
use glam::{DMat3, DQuat, DVec3};

fn banana_fit(points: &[DVec3], taper: bool, bend: bool) -> FitReport {
    let mut o = FitOptions {
        global_only: true,
        ..FitOptions::default()
    };
    o.dynamics.free.taper = taper;
    o.dynamics.free.bend = bend;
    fit(points, &o, |_| {}).expect("the fit runs")
}

#[test]
fn taper_and_bend_fit_a_banana_that_a_superquadric_cannot() {
    // Default banana: arc radius 3, ends turned ±0.6 rad, radius 0.4 growing by 40 % towards the
    // +z end; turned and moved off the axes.
    let banana = Banana::default();
    let turn = DQuat::from_axis_angle(DVec3::new(0.3, 1.0, -0.5).normalize(), 0.9);
    let offset = DVec3::new(0.5, -1.0, 2.0);
    let points: Vec<DVec3> = banana
        .points(2000, 0.002, 7)
        .into_iter()
        .map(|p| turn * p + offset)
        .collect();
    let plain = banana_fit(&points, false, false);
    let both = banana_fit(&points, true, true);
    assert!(plain.state.deformation.is_identity());
    assert!(
        both.residuals.mean < 0.65 * plain.residuals.mean,
        "plain {:?} vs tapered and bent {:?}",
        plain.residuals,
        both.residuals
    );
    // The recovered coordinates mean what the banana is: each end turned by 0.6 rad towards the
    // arc's centre, the section growing by 40 % towards the +z end.
    let d = both.state.deformation;
    let r = DMat3::from_quat(both.state.rotation);
    let bend = d.bend[0].hypot(d.bend[1]);
    assert!((bend - 0.6).abs() < 0.1, "bend {d:?}");
    let towards = (r * DVec3::new(d.bend[0], d.bend[1], 0.0)).normalize();
    assert!(
        towards.dot(turn * DVec3::X) > 0.95,
        "bends towards {towards}"
    );
    for t in d.taper {
        assert!((t.abs() - 0.4).abs() < 0.1, "taper {d:?}");
    }
    // Thicker towards the banana's +z end: sign(t) × the model's z axis.
    let thick_end = d.taper[0].signum() * (r * DVec3::Z);
    assert!(
        thick_end.dot(turn * DVec3::Z) > 0.9,
        "thick end {thick_end}"
    );
    assert_eq!(d.taper[0].signum(), d.taper[1].signum());
    // Round sections of radius ≈ 0.4: semi-axes x, y within 15 %.
    let axes = both.state.shape.semi_axes();
    for a in [axes.x, axes.y] {
        assert!((a - 0.4).abs() < 0.06, "semi-axes {axes}");
    }
}

/// Seen whole, a cone and a banana bent through 120° keep their taper and bend: the fit starts
/// from the centreline (`model::centreline`) and keeps the coverage springs on, so the cone's tip
/// does not grow round nor the banana run on past its ends.
#[test]
fn a_cone_and_a_120_degree_banana_keep_their_taper_and_bend() {
    let turn = DQuat::from_axis_angle(DVec3::new(-0.4, 0.8, 0.3).normalize(), 2.1);
    for (shape, taper, bend) in [
        (Banana::cone(1.5, 0.5, 1.0), 1.0, 0.0),
        (
            Banana::bent(2.0, 120.0, 0.3, 0.0),
            0.0,
            120f64.to_radians() / 2.0,
        ),
    ] {
        let points: Vec<DVec3> = shape
            .points(2000, 0.01 * shape.radius, 11)
            .into_iter()
            .map(|p| turn * p + DVec3::new(1.0, 0.5, -2.0))
            .collect();
        let options = |deform| {
            let mut o = FitOptions {
                global_only: true,
                ..FitOptions::default()
            };
            o.dynamics.free.taper = deform;
            o.dynamics.free.bend = deform;
            o.for_data()
        };
        let plain = fit(&points, &options(false), |_| {}).expect("the fit runs");
        let both = fit(&points, &options(true), |_| {}).expect("the fit runs");
        let d = both.state.deformation;
        assert!(
            both.residuals.mean < 0.5 * plain.residuals.mean,
            "plain {:?} vs deformed {:?} ({d:?})",
            plain.residuals,
            both.residuals
        );
        for t in d.taper {
            assert!((t.abs() - taper).abs() <= 0.2 * taper.max(0.5), "{d:?}");
        }
        let fitted = d.bend[0].hypot(d.bend[1]);
        assert!((fitted - bend).abs() <= 0.2 * bend.max(0.5), "{d:?}");
    }
}
