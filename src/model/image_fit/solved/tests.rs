use super::*;
use crate::model::fem::Tessellation;
use crate::model::image_fit::evidence;
use crate::model::image_fit::{ImageFitOptions, fit_parts_together};

/// `o` with unknown `k` of (cx, cy, θ, r1, r3, ε1) moved by `s`.
fn shifted(o: Outline, k: usize, s: f64) -> Outline {
    let mut m = o;
    match k {
        0 => m.c.x += s,
        1 => m.c.y += s,
        2 => m.theta += s,
        3 => m.r[0] += s,
        4 => m.r[1] += s,
        _ => m.eps += s,
    }
    m
}

#[test]
fn the_outline_jacobian_is_the_central_difference() {
    let o = Outline {
        c: DVec2::new(40.0, 30.0),
        theta: 0.7,
        r: [12.0, 25.0],
        eps: 0.6,
    };
    let h = 1e-6;
    for eta in [0.3, 1.9, 3.5, 5.0] {
        let (_, jac) = o.point_jacobian(eta);
        for (k, d) in jac.iter().enumerate() {
            let shift = |s: f64| shifted(o, k, s).point(eta);
            let fd = (shift(h) - shift(-h)) / (2.0 * h);
            assert!(
                (fd - *d).length() < 1e-6,
                "η {eta} unknown {k}: {fd} vs {d}"
            );
        }
    }
}

#[test]
fn the_radial_distance_and_its_gradient_are_right() {
    let o = Outline {
        c: DVec2::new(40.0, 30.0),
        theta: -0.4,
        r: [12.0, 25.0],
        eps: 0.7,
    };
    // On the outline the distance is 0; along a ray it grows as the distance from the outline.
    for eta in [0.2, 2.0, 4.4] {
        let p = o.point(eta);
        assert!(o.radial(p).unwrap().0.abs() < 1e-9);
        let out = o.c + (p - o.c) * 1.5;
        let d = o.radial(out).unwrap().0;
        assert!((d - 0.5 * (p - o.c).length()).abs() < 1e-9, "{d}");
    }
    let h = 1e-6;
    for q in [
        DVec2::new(55.0, 20.0),
        DVec2::new(30.0, 45.0),
        DVec2::new(41.0, 31.0),
    ] {
        let (_, grad) = o.radial(q).unwrap();
        for (k, g) in grad.iter().enumerate() {
            let shift = |s: f64| shifted(o, k, s).radial(q).unwrap().0;
            let fd = (shift(h) - shift(-h)) / (2.0 * h);
            assert!(
                (fd - g).abs() < 1e-6 * (1.0 + g.abs()),
                "{q} unknown {k}: {fd} vs {g}"
            );
        }
    }
}

/// A dark superellipse on a light ground: the image and its truth.
pub(in crate::model::image_fit) fn blob() -> (ImagePotential, Outline) {
    let truth = Outline {
        c: DVec2::new(82.0, 57.0),
        theta: 0.5,
        r: [18.0, 34.0],
        eps: 0.5,
    };
    let (w, h) = (160, 120);
    let lum = (0..w * h)
        .map(|i| {
            let q = DVec2::new((i % w) as f64, (i / w) as f64);
            if truth.contains(q) { 0.2 } else { 0.8 }
        })
        .collect();
    let frame = crate::model::forces::image::ImageFrame::default();
    (ImagePotential::new(w, h, lum, 2.0, frame).unwrap(), truth)
}

/// The ellipse placed off [`blob`]'s truth: shifted, turned, of the wrong size.
fn placed_off(truth: &Outline) -> Outline {
    Outline {
        c: truth.c + DVec2::new(6.0, -4.0),
        theta: 0.3,
        r: [13.0, 27.0],
        eps: 1.0,
    }
}

/// A part placed off [`blob`]'s truth.
pub(in crate::model::image_fit) fn part_on<'a>(
    pot: &ImagePotential,
    edges: Option<&'a Raster>,
) -> Part<'a> {
    let (_, truth) = blob();
    let tess = Tessellation::new(3);
    let start = placed_off(&truth).state(pot, 13.0 * pot.pitch(), 1.0, 0.0, &tess);
    Part::new(pot, edges, &pot.relief(), &start)
}

#[test]
fn the_global_gradient_is_the_central_difference() {
    let (pot, truth) = blob();
    let edges = evidence::edge_distance(&pot);
    let part = part_on(&pot, edges.as_ref());
    let area = part.area(&[]);
    let fields = part.fields();
    let problem = part.problem(&fields, area.as_ref(), false);
    // Between the placement and the truth, where every residual has a slope.
    let o = Outline {
        c: truth.c + DVec2::new(2.3, -1.7),
        theta: 0.43,
        r: [16.2, 31.1],
        eps: 0.73,
    };
    let (e0, _) = problem.evaluate(&o, &[]);
    let h = 1e-6;
    let mut checked = 0;
    for i in (0..problem.len()).step_by(5) {
        let Some((r, g)) = problem.gradient(&o, i, None) else {
            continue;
        };
        assert!((r - e0[i]).abs() < 1e-12, "residual {i}");
        for (k, gk) in g.iter().enumerate() {
            let at = |s: f64| problem.evaluate(&shifted(o, k, s), &[]).0[i];
            let fd = (at(h) - at(-h)) / (2.0 * h);
            assert!(
                (fd - gk).abs() < 1e-4 * (1.0 + gk.abs()),
                "residual {i} unknown {k}: {fd} vs {gk}"
            );
        }
        checked += usize::from(g.iter().any(|g| g.abs() > 1e-3));
    }
    assert!(checked > 100, "{checked} residuals with a slope");
}

#[test]
fn a_solved_part_lowers_its_energy_stays_finite_and_comes_to_rest_on_its_truth() {
    let (pot, truth) = blob();
    let edges = evidence::edge_distance(&pot);
    let tess = Tessellation::new(15);
    let start = placed_off(&truth).state(&pot, 13.0 * pot.pitch(), 1.0, 0.0, &tess);
    let part = Part::new(&pot, edges.as_ref(), &pot.relief(), &start);
    let area = part.area(&[]);
    let fields = part.fields();
    let problem = part.problem(&fields, area.as_ref(), false);
    let cost = |o: &Outline| {
        problem
            .evaluate(o, &[])
            .0
            .iter()
            .map(|e| e * e)
            .sum::<f64>()
    };
    let (o, _, at_rest, _) = part.solve_global(part.start(), area.as_ref(), false);
    assert!(
        cost(&o) < 0.2 * cost(&part.start()),
        "{} → {}",
        cost(&part.start()),
        cost(&o)
    );
    assert!(at_rest);
    assert!(o.c.distance(truth.c) < 1.0, "{o:?}");
    assert!(
        (o.r[0] - truth.r[0]).abs() < 1.5 && (o.r[1] - truth.r[1]).abs() < 1.5,
        "{o:?}"
    );
    assert!((o.eps - truth.eps).abs() < 0.2, "{o:?}");
    // Solved again from where it ended, it stays: a rest, not a stop.
    let (again, _, _, moved) = part.solve_global(o, area.as_ref(), false);
    assert!(moved < REST_PX, "{o:?} → {again:?}");
    // With the contour: finite, at rest, and its outline still on the truth.
    let solved = &fit_parts_together(&tess, &pot, &[start], &ImageFitOptions::default())[0];
    assert!(solved.state.is_finite() && solved.converged);
}
