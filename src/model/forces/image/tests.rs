use super::*;

/// A smooth image: a Gaussian blob of intensity, sampled at pixel centres.
fn blob(width: usize, height: usize, r: f64) -> Vec<f64> {
    let mut v = Vec::with_capacity(width * height);
    for row in 0..height {
        for col in 0..width {
            let x = col as f64 - width as f64 / 2.0;
            let y = row as f64 - height as f64 / 2.0;
            v.push((-(x * x + y * y) / (2.0 * r * r)).exp());
        }
    }
    v
}

/// A bright disc (0.9) of radius `r` pixels about pixel (⌊w/2⌋, ⌊h/2⌋) on a dark background
/// (0.1).
fn disc(width: usize, height: usize, r: f64) -> Vec<f64> {
    let centre = ((width / 2) as f64, (height / 2) as f64);
    (0..width * height)
        .map(|i| {
            let (c, row) = ((i % width) as f64 - centre.0, (i / width) as f64 - centre.1);
            if c * c + row * row < r * r { 0.9 } else { 0.1 }
        })
        .collect()
}

#[test]
fn otsu_splits_two_levels_between_them() {
    let lum: Vec<f64> = (0..100).map(|i| if i < 30 { 0.2 } else { 0.7 }).collect();
    let t = otsu_threshold(&lum);
    assert!(t > 0.2 && t < 0.7, "{t}");
}

#[test]
fn foreground_is_the_side_that_misses_the_border() {
    // A dark square on a bright background: the dark side is the foreground.
    let lum: Vec<f64> = (0..100)
        .map(|i| {
            if (3..7).contains(&(i % 10)) && (3..7).contains(&(i / 10)) {
                0.1
            } else {
                0.9
            }
        })
        .collect();
    let p = ImagePotential::new(10, 10, lum, 1.0, ImageFrame::default()).unwrap();
    assert_eq!(p.foreground().iter().filter(|&&f| f).count(), 16);
    assert!(p.in_foreground(p.to_plane(DVec2::new(4.0, 5.0))));
    assert!(!p.in_foreground(p.to_plane(DVec2::new(1.0, 5.0))));
    assert!(!p.in_foreground(DVec2::new(5.0, 5.0)));
}

#[test]
fn pixel_and_plane_coordinates_are_inverse_and_y_points_up() {
    let p = ImagePotential::new(
        40,
        20,
        vec![0.0; 800],
        1.0,
        ImageFrame {
            center: DVec2::new(0.3, -0.2),
            extent: 2.0,
        },
    )
    .unwrap();
    assert_eq!(p.pitch(), 0.05);
    let q = DVec2::new(3.25, 7.5);
    assert!((p.to_pixel(p.to_plane(q)) - q).length() < 1e-12);
    // The top-left pixel is up and left of the centre.
    let tl = p.to_plane(DVec2::ZERO);
    assert!(tl.x < 0.3 && tl.y > -0.2);
    assert!((tl - DVec2::new(0.3 - 0.975, -0.2 + 0.475)).length() < 1e-12);
    assert!(p.contains(DVec2::new(0.3 + 0.99, -0.2)));
    assert!(!p.contains(DVec2::new(0.3 + 1.01, -0.2)));
}

#[test]
fn potential_of_a_smoothed_step_edge_matches_the_analytic_one() {
    // A vertical step edge from 0 to 1 at column 50 (between pixels 49 and 50).
    let (w, h) = (100, 8);
    let lum: Vec<f64> = (0..w * h)
        .map(|i| if i % w >= 50 { 1.0 } else { 0.0 })
        .collect();
    let sigma = 3.0;
    let p = ImagePotential::new(w, h, lum, sigma, ImageFrame::default()).unwrap();
    // Plane units: pitch = 1/100; P = g_σ(x) (unit contrast), peak 1/(σ_w √(2π)).
    let sigma_w = sigma * p.pitch();
    let peak = 1.0 / (sigma_w * (2.0 * std::f64::consts::PI).sqrt());
    let at = |col: f64| p.potential_at(p.to_plane(DVec2::new(col, 4.0)));
    // Central differences over two pixels and sampling at pixel centres cost a few per cent.
    assert!(
        (at(49.5) - peak).abs() < 0.04 * peak,
        "{} vs {peak}",
        at(49.5)
    );
    let x = 4.0 * p.pitch();
    let expected = peak * (-(x * x) / (2.0 * sigma_w * sigma_w)).exp();
    assert!((at(45.5) - expected).abs() < 0.03 * peak);
    // ∇P points towards the edge from both sides, and vanishes far away.
    assert!(p.gradient_at(p.to_plane(DVec2::new(46.0, 4.0))).x > 0.0);
    assert!(p.gradient_at(p.to_plane(DVec2::new(53.0, 4.0))).x < 0.0);
    assert_eq!(
        p.gradient_at(p.to_plane(DVec2::new(10.0, 4.0))),
        DVec2::ZERO
    );
    // The 99th percentile sits on the ridge.
    assert!((p.p_ref() - at(49.5)).abs() < 0.05 * peak);
}

#[test]
fn gradient_is_the_central_difference_at_pixels_and_bilinear_between() {
    let (w, h) = (30, 24);
    let p = ImagePotential::new(w, h, blob(w, h, 5.0), 1.5, ImageFrame::default()).unwrap();
    let pot = p.potential();
    let (col, row) = (9usize, 14usize);
    let expected = DVec2::new(
        pot[row * w + col + 1] - pot[row * w + col - 1],
        pot[(row - 1) * w + col] - pot[(row + 1) * w + col],
    ) / (2.0 * p.pitch());
    let at = |c: f64, r: f64| p.gradient_at(p.to_plane(DVec2::new(c, r)));
    assert!((at(9.0, 14.0) - expected).length() < 1e-9 * expected.length());
    // Halfway between four pixels: their mean.
    let mean = (at(9.0, 14.0) + at(10.0, 14.0) + at(9.0, 15.0) + at(10.0, 15.0)) / 4.0;
    assert!((at(9.5, 14.5) - mean).length() < 1e-9 * mean.length());
}

#[test]
fn lookups_at_pixel_centres_read_each_pixels_own_potential_and_foreground() {
    // A bright disc on a dark background: foreground and background pixels both.
    let (w, h) = (23, 17);
    let p = ImagePotential::new(w, h, disc(w, h, 5.0), 1.0, ImageFrame::default()).unwrap();
    let mut foreground = 0;
    for row in 0..h {
        for col in 0..w {
            let i = row * w + col;
            let x = p.to_plane(DVec2::new(col as f64, row as f64));
            let expected = p.potential()[i];
            assert!(
                (p.potential_at(x) - expected).abs() <= 1e-12 * p.p_ref(),
                "P at pixel ({col}, {row})"
            );
            assert_eq!(
                p.in_foreground(x),
                p.foreground()[i],
                "pixel ({col}, {row})"
            );
            foreground += usize::from(p.foreground()[i]);
        }
    }
    assert!(foreground > 50 && foreground < w * h - 50, "{foreground}");
}

#[test]
fn gradient_and_potential_from_one_lookup_equal_the_two_lookups_to_the_bit() {
    let (w, h) = (30, 24);
    let p = ImagePotential::new(w, h, blob(w, h, 5.0), 1.5, ImageFrame::default()).unwrap();
    let mut inside = 0;
    // Pixel centres, points between them, the last row and column, and points off the image.
    for c in [
        -3.0, -0.4, 0.0, 0.25, 9.0, 9.5, 17.3, 28.9, 29.0, 29.6, 35.0,
    ] {
        for r in [-2.0, 0.0, 0.7, 14.0, 14.5, 22.2, 23.0, 23.5, 30.0] {
            let x = p.to_plane(DVec2::new(c, r));
            let (g, pot) = p.gradient_and_potential_at(x);
            assert_eq!(g, p.gradient_at(x), "∇P at pixel ({c}, {r})");
            assert_eq!(pot, p.potential_at(x), "P at pixel ({c}, {r})");
            inside += usize::from(pot != 0.0);
        }
    }
    assert!(inside > 20, "only {inside} points had a potential");
}

#[test]
fn interpolated_gradient_agrees_with_central_differences_of_the_potential() {
    // On a smooth, finely sampled potential the interpolated ∇P is the derivative of P.
    let (w, h) = (120, 120);
    let p = ImagePotential::new(w, h, blob(w, h, 25.0), 2.0, ImageFrame::default()).unwrap();
    let step = p.pitch();
    for &(c, r) in &[(40.3, 61.7), (75.6, 30.2), (60.0, 88.9)] {
        let x = p.to_plane(DVec2::new(c, r));
        let g = p.gradient_at(x);
        let fd = DVec2::new(
            p.potential_at(x + DVec2::X * step) - p.potential_at(x - DVec2::X * step),
            p.potential_at(x + DVec2::Y * step) - p.potential_at(x - DVec2::Y * step),
        ) / (2.0 * step);
        assert!(
            (g - fd).length() < 0.03 * g.length().max(1e-9),
            "at ({c},{r}): {g} vs {fd}"
        );
    }
}

#[test]
fn bad_images_and_sigmas_are_refused() {
    let f = ImageFrame::default();
    assert_eq!(
        ImagePotential::new(1, 1, vec![0.5], 1.0, f),
        Err(ImageError::TooSmall {
            width: 1,
            height: 1
        })
    );
    assert!(matches!(
        ImagePotential::new(4, 4, vec![0.5; 15], 1.0, f),
        Err(ImageError::WrongSize { .. })
    ));
    let mut nan = vec![0.5; 16];
    nan[5] = f64::NAN;
    assert_eq!(
        ImagePotential::new(4, 4, nan, 1.0, f),
        Err(ImageError::NonFinite { index: 5 })
    );
    for s in [0.0, -1.0, 0.2, 2.0, f64::NAN, f64::INFINITY] {
        assert!(matches!(
            ImagePotential::new(4, 4, vec![0.5; 16], s, f),
            Err(ImageError::BadSigma { .. })
        ));
    }
    let bad = ImageFrame {
        center: DVec2::ZERO,
        extent: 0.0,
    };
    assert_eq!(
        ImagePotential::new(4, 4, vec![0.5; 16], 1.0, bad),
        Err(ImageError::BadFrame)
    );
}

#[test]
fn nearest_index_is_round_clamped_at_zero_for_every_kind_of_value() {
    let mut values = vec![
        f64::NEG_INFINITY,
        -1e300,
        -2.5,
        -0.5,
        -0.49999999999999994,
        -0.0,
        0.0,
        f64::MIN_POSITIVE,
        0.49999999999999994,
        0.5,
        0.5000000000000001,
        1.5,
        2.4999999999999996,
        2.5,
        399.5,
        327.49999999999994,
        1e15 + 0.5,
        4_503_599_627_370_495.5,
        4_503_599_627_370_496.0,
        4_503_599_627_370_497.0,
        1e19,
        1e300,
        f64::INFINITY,
        f64::NAN,
    ];
    // Quarter and half pixels, and values just either side of each half.
    for i in -8..1700 {
        let p = i as f64 * 0.25;
        values.extend([p, p.next_down(), p.next_up()]);
    }
    for p in values {
        assert_eq!(nearest_index(p), p.round().max(0.0) as usize, "p = {p:e}");
    }
}

#[test]
fn forces_with_kept_buffers_equal_the_forces_from_every_nodes_normals_to_the_bit() {
    use crate::model::dynamics::ModelState;
    use crate::model::superquadric::SuperquadricParams;
    // A bright disc on a dark background, and models that straddle its edge, so that the
    // region force pushes some acting nodes out and pulls others in.
    let (w, h) = (90, 90);
    let potential =
        Arc::new(ImagePotential::new(w, h, disc(w, h, 20.0), 2.0, ImageFrame::default()).unwrap());
    let shape = SuperquadricParams {
        a: 0.3,
        a1: 1.0,
        a2: 0.5,
        a3: 0.7,
        e1: 0.6,
        e2: 1.3,
    };
    // One scratch for every model and option: a kept buffer from a larger model must not
    // leak into a smaller one's forces.
    let mut scratch = ImageScratch::default();
    // How many cases took the node-by-node normals and the one-pass normals.
    let mut paths = [0; 2];
    // The disc's own grey levels, as the part would measure them, and a model that puts the
    // boundary off the disc's edge, so that the region force's sign varies between nodes.
    let models = [
        RegionModel {
            inside: 0.9,
            outside: 0.1,
        },
        RegionModel {
            inside: 0.7,
            outside: 0.3,
        },
    ];
    for (k, outline_only, region, model, oriented) in [
        (20, true, 0.05, models[0], false),
        (9, true, 0.05, models[1], false),
        (12, false, 0.2, models[0], true),
    ] {
        let forces = ImageForces {
            potential: potential.clone(),
            beta: 1.5,
            band: 0.3,
            outline_only,
            region,
            region_model: Some(model),
            oriented,
        };
        let tess = Tessellation::new(k);
        let state = ModelState::new(
            &tess,
            DVec3::new(0.12, -0.05, 0.02),
            glam::DQuat::from_rotation_x(0.7) * glam::DQuat::from_rotation_z(0.4),
            shape,
        );
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        let mut fast = NodalForces::new(tess.node_count());
        forces.accumulate_with(&tess, &x, &mut fast, &mut scratch);
        // The reference: every node's normal from `vertex_normals`, the region force in a
        // pass of its own before the edge force, as the forces were first written.
        let mut reference = NodalForces::new(tess.node_count());
        let mut acting = Vec::new();
        forces.acting_nodes(&tess, &x, &mut acting);
        let mut normals = Vec::new();
        tess.vertex_normals(&x, &mut normals);
        let sigma_w = potential.sigma() * potential.pitch();
        let push = region * forces.beta * potential.p_ref() / sigma_w;
        let (mut pushed, mut pulled) = (0, 0);
        for (i, &xi) in x.iter().enumerate() {
            let n = normals[i].truncate().normalize_or_zero();
            if acting[i] && n != DVec2::ZERO {
                let sign = potential
                    .luminance_at(xi.truncate())
                    .map_or(-1.0, |lum| model.membership(lum));
                (pushed, pulled) = (
                    pushed + usize::from(sign > 0.0),
                    pulled + usize::from(sign < 0.0),
                );
                reference.force[i] += (sign * push * tess.node_area[i] * n).extend(0.0);
            }
        }
        let kappa = forces.beta * potential.curvature_scale();
        for (i, &xi) in x.iter().enumerate().filter(|(i, _)| acting[*i]) {
            let (g, p) = potential.gradient_and_potential_at(xi.truncate());
            let a = tess.node_area[i];
            let near_edge = (p / potential.p_ref()).clamp(0.0, 1.0);
            let n = normals[i].truncate().normalize_or_zero();
            let facing = match oriented {
                true => potential.edge_facing(xi.truncate(), n, model.polarity()),
                false => 1.0,
            };
            reference.force[i] += facing * forces.beta * a * DVec3::new(g.x, g.y, 0.0);
            reference.stiffness[i] += kappa * a * (FLAT_WEIGHT + (1.0 - FLAT_WEIGHT) * near_edge);
        }
        assert!(
            pushed > 0 && pulled > 0,
            "k = {k}: {pushed} pushed, {pulled} pulled"
        );
        let count = acting.iter().filter(|&&a| a).count();
        paths[usize::from(normals_in_one_pass(count, x.len()))] += 1;
        assert_eq!(fast.force, reference.force, "k = {k}");
        assert_eq!(fast.stiffness, reference.stiffness, "k = {k}");
        // And the convenience form, which allocates its buffers afresh.
        let mut fresh = NodalForces::new(tess.node_count());
        forces.accumulate(&tess, &x, &mut fresh);
        assert_eq!(fresh.force, reference.force, "k = {k}");
    }
    assert!(
        paths[0] > 0 && paths[1] > 0,
        "both ways to the normals: {paths:?}"
    );
}

#[test]
fn forces_act_in_the_band_parallel_to_the_plane_and_follow_the_energy() {
    use crate::model::dynamics::{ModelState, generalized_global_forces};
    use crate::model::superquadric::SuperquadricParams;
    let (w, h) = (160, 160);
    let pot =
        Arc::new(ImagePotential::new(w, h, blob(w, h, 30.0), 3.0, ImageFrame::default()).unwrap());
    let forces = ImageForces {
        potential: pot,
        beta: 2.0,
        band: 0.05,
        outline_only: false,
        region: 0.0,
        region_model: None,
        oriented: false,
    };
    let tess = Tessellation::new(12);
    let shape = SuperquadricParams {
        a: 0.2,
        a1: 1.0,
        a2: 0.8,
        a3: 0.6,
        e1: 0.8,
        e2: 1.0,
    };
    let state = ModelState::new(
        &tess,
        DVec3::new(0.03, -0.02, 0.01),
        glam::DQuat::from_rotation_x(0.3).normalize(),
        shape,
    );
    let mut x = Vec::new();
    state.node_positions(&tess, &mut x);
    let mut nf = NodalForces::new(tess.node_count());
    forces.accumulate(&tess, &x, &mut nf);
    let mut acted = 0;
    for (i, xi) in x.iter().enumerate() {
        assert_eq!(nf.force[i].z, 0.0);
        if xi.z.abs() >= 0.05 {
            assert_eq!(nf.force[i], DVec3::ZERO);
            assert_eq!(nf.stiffness[i], 0.0);
        } else {
            acted += 1;
            assert!(nf.stiffness[i] > 0.0);
        }
    }
    assert!(acted > 10 && acted < tess.node_count());
    // Translation in x and y: f_c ≈ −∂E/∂c (central differences, nodes kept in the band).
    let fq = generalized_global_forces(&tess, &state, &nf);
    let energy = |dc: DVec3| {
        let mut s = state.clone();
        s.translation += dc;
        let mut xs = Vec::new();
        s.node_positions(&tess, &mut xs);
        // Same band membership as at the base state.
        let shifted: Vec<DVec3> = xs
            .iter()
            .zip(&x)
            .map(|(a, b)| DVec3::new(a.x, a.y, b.z))
            .collect();
        forces.energy(&tess, &shifted)
    };
    let hstep = 1e-4;
    for (k, dir) in [DVec3::X, DVec3::Y].into_iter().enumerate() {
        let fd = -(energy(dir * hstep) - energy(-dir * hstep)) / (2.0 * hstep);
        assert!(
            (fq[k] - fd).abs()
                < 0.02
                    * fq[k]
                        .abs()
                        .max(1e-3 * fq[..2].iter().map(|v| v.abs()).sum::<f64>()),
            "f_c[{k}] = {} vs −∂E/∂c = {fd}",
            fq[k]
        );
    }
}

#[test]
fn edges_face_out_of_the_part_whichever_side_is_brighter() {
    // A bright disc on dark (the disc is the part's inside) and its negative, a dark disc on
    // bright; the polarity is the part's region model's.
    let (w, h, r) = (80, 80, 20.0);
    for (lum, model) in [
        (disc(w, h, r), (0.9, 0.1)),
        (disc(w, h, r).iter().map(|v| 1.0 - v).collect(), (0.1, 0.9)),
    ] {
        let polarity = RegionModel {
            inside: model.0,
            outside: model.1,
        }
        .polarity();
        let p = ImagePotential::new(w, h, lum, 2.0, ImageFrame::default()).unwrap();
        let centre = DVec2::new(40.0, 40.0);
        for angle in [0.0, 1.0, 2.5, 4.0] {
            let out = DVec2::from_angle(angle);
            // On the rim, in plane coordinates (y up: the pixel row is flipped).
            let rim = p.to_plane(centre + DVec2::new(out.x, -out.y) * r);
            let facing_out = p.edge_facing(rim, out, polarity);
            assert!(facing_out > 0.95, "angle {angle}: {facing_out}");
            assert_eq!(p.edge_facing(rim, -out, polarity), 0.0, "angle {angle}");
            // Across the edge's direction: half-way.
            let across = p.edge_facing(rim, (out + out.perp()).normalize(), polarity);
            assert!(
                (across - 0.5f64.sqrt()).abs() < 0.05,
                "angle {angle}: {across}"
            );
        }
        // Flat image far from the edge, and off the image: no edge to face.
        assert_eq!(
            p.edge_facing(p.to_plane(DVec2::new(2.0, 2.0)), DVec2::X, polarity),
            0.0
        );
        assert_eq!(p.edge_facing(DVec2::new(9.0, 9.0), DVec2::X, polarity), 0.0);
        // Without a polarity, no edge faces anywhere.
        assert_eq!(
            p.edge_facing(p.to_plane(DVec2::new(60.0, 40.0)), DVec2::X, 0.0),
            0.0
        );
    }
}
