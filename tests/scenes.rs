//! Scene files: every shipped scene loads and runs headless; scenes load through the asset
//! loader into entities and despawn with their root; a saved scene loads back bit for bit; every
//! kind of bad scene gives an error naming the file and the line or field.

use bevy::asset::AssetPlugin;
use bevy::prelude::*;
use bevy_deformable_sq::model::dynamics::ModelState;
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::fit::{
    FitOptions, MIN_POINTS, Residuals, bounding_diagonal, fit, point_distances, residuals,
};
use bevy_deformable_sq::model::image_fit::PartAxes;
use bevy_deformable_sq::plugin::FitDriver;
use bevy_deformable_sq::plugin::scene::{SceneImage, save_scene};
use bevy_deformable_sq::prelude::*;
use bevy_deformable_sq::scene::{PartRun, SceneDef, SceneError, run_scene};
use bevy_deformable_sq::synthetic;
use bevy_deformable_sq::synthetic::{doll_experiment, pestle_experiment};
use glam::{DQuat, DVec2, DVec3};
use std::path::{Path, PathBuf};

#[path = "support/scene_app.rs"]
mod scene_app;
use scene_app::{Step, load, parts, scene_app};

const SHIPPED: [(&str, usize); 9] = [
    ("egg", 1),
    ("mug", 1),
    ("pestle", 1),
    ("doll", 11),
    ("bunny", 1),
    ("hippo1", 1),
    ("cow", 6),
    ("ant_scan", 9),
    ("cow_scan", 6),
];

fn shipped(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("assets/scenes")
        .join(format!("{name}.dsq.ron"))
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("bdsq-scenes-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn node_positions(k: usize, s: &ModelState) -> (Tessellation, Vec<DVec3>) {
    let tess = Tessellation::new(k);
    let mut x = Vec::new();
    s.node_positions(&tess, &mut x);
    (tess, x)
}

#[test]
fn every_shipped_scene_loads_and_runs_headless() {
    for (name, parts) in SHIPPED {
        let (def, data) = SceneDef::load_file(&shipped(name)).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(def.parts.len(), parts, "{name}");
        // A few hundred steps each: every part must be pulled towards its data.
        let runs = run_scene(&def, &data, Some(600));
        for (i, run) in runs.into_iter().enumerate() {
            let run = run.unwrap_or_else(|e| panic!("{name}: {e}"));
            let part = &def.parts[i];
            let start = data.initial_state(&def, i).unwrap();
            assert!(run.state().is_finite(), "{name} part {i}");
            match run {
                PartRun::Range(report) => {
                    let pts = data.range_points(&def, i).unwrap();
                    let (tess, x0) = node_positions(part.k, &start);
                    let before = residuals(&tess, &x0, &pts).rms;
                    assert!(
                        report.residuals.rms < 0.9 * before,
                        "{name} part {i}: rms {before} -> {}",
                        report.residuals.rms
                    );
                }
                PartRun::Image(f) => assert!(
                    f.outline_after > f.outline_before + 0.1,
                    "{name} part {i} ({}): outline {} -> {}",
                    part.name,
                    f.outline_before,
                    f.outline_after
                ),
                PartRun::Free(_) => panic!("{name}: shipped parts all have data"),
            }
        }
    }
}

#[test]
fn egg_and_mug_scenes_run_the_papers_experiments_to_rest() {
    for (name, (points, options)) in [
        ("egg", synthetic::egg_experiment()),
        ("mug", synthetic::mug_experiment()),
    ] {
        let (def, data) = SceneDef::load_file(&shipped(name)).unwrap();
        let part = &def.parts[0];
        let start = data.initial_state(&def, 0).unwrap();
        assert_eq!(data.range_points(&def, 0).unwrap(), points, "{name}");
        // The same options bit for bit, hence the same fit as `dsq fit --paper egg|mug`.
        assert_eq!(part.fit_options(&start), options, "{name}");
        let run = run_scene(&def, &data, None).remove(0).unwrap();
        let PartRun::Range(report) = run else {
            panic!("{name}: not a range part")
        };
        assert!(report.converged, "{name} did not come to rest");
        assert!(
            report.residuals.rms < 0.01,
            "{name}: {:?}",
            report.residuals
        );
    }
}

#[test]
fn pestle_and_doll_scenes_are_the_papers_image_experiments() {
    for (name, experiment) in [("pestle", pestle_experiment()), ("doll", doll_experiment())] {
        let (def, data) = SceneDef::load_file(&shipped(name)).unwrap();
        assert_eq!(def.parts.len(), experiment.parts.len());
        let potential = data.images.values().next().unwrap();
        for (i, (part, (part_name, px))) in def.parts.iter().zip(&experiment.parts).enumerate() {
            assert_eq!(&part.name, part_name);
            assert_eq!(
                part.image_options(),
                experiment.options,
                "{name} {part_name}"
            );
            let axes = PartAxes::from_points(potential, *px).unwrap();
            let tess = Tessellation::new(part.k);
            assert_eq!(
                data.initial_state(&def, i).unwrap(),
                axes.state(&tess),
                "{name} {part_name}"
            );
        }
    }
}

#[test]
fn a_saved_scene_parses_back_to_the_same_state_bit_for_bit() {
    let (mut def, data) = SceneDef::load_file(&shipped("mug")).unwrap();
    let k = def.parts[0].k;
    // Awkward values: not exactly representable decimals, subnormals, signed zero, extremes.
    let odd = [
        0.1 + 0.2,
        1e-300,
        -0.0,
        5e-324,
        1.0 / 3.0,
        -2.5e17,
        f64::EPSILON,
    ];
    let displacement: Vec<DVec3> = (0..k * k + 2)
        .map(|i| {
            DVec3::new(
                odd[i % odd.len()] * (i as f64).sqrt(),
                odd[(i + 3) % odd.len()],
                (i as f64 * 0.37).sin() * 1e-3,
            )
        })
        .collect();
    let state = ModelState {
        translation: DVec3::new(0.1 + 0.2, -1.0 / 7.0, 1e-17),
        rotation: DQuat::from_euler(EulerRot::XYZ, 0.3, -1.2, 2.9),
        shape: bevy_deformable_sq::model::superquadric::SuperquadricParams {
            a: 0.712_345_678_901_234_5,
            a1: 1.0,
            a2: 0.3 + 1e-16,
            a3: 2.0 / 3.0,
            e1: 0.1 + 0.7,
            e2: 1.999_999_999_999_999_8,
        },
        deformation: bevy_deformable_sq::model::deform::GlobalDeformation {
            taper: [odd[0], -1.0 / 3.0],
            bend: [1e-300, -0.0],
        },
        displacement,
    };
    def.set_state(0, &state, true);
    let text = def.to_ron().unwrap();
    let back = SceneDef::parse(&text, Path::new("saved.dsq.ron")).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(back, def);
    let loaded = data.initial_state(&back, 0).unwrap();
    assert_eq!(
        loaded.translation.to_array().map(f64::to_bits),
        state.translation.to_array().map(f64::to_bits)
    );
    assert_eq!(
        loaded.rotation.to_array().map(f64::to_bits),
        state.rotation.to_array().map(f64::to_bits)
    );
    assert_eq!(
        loaded.shape.to_array().map(f64::to_bits),
        state.shape.to_array().map(f64::to_bits)
    );
    assert_eq!(
        loaded.deformation.to_array().map(f64::to_bits),
        state.deformation.to_array().map(f64::to_bits)
    );
    let bits = |d: &[DVec3]| -> Vec<[u64; 3]> {
        d.iter().map(|v| v.to_array().map(f64::to_bits)).collect()
    };
    assert_eq!(bits(&loaded.displacement), bits(&state.displacement));
    // Without the local displacements they are dropped, and load as zero.
    def.set_state(0, &state, false);
    let back = SceneDef::parse(&def.to_ron().unwrap(), Path::new("saved.dsq.ron")).unwrap();
    assert!(back.parts[0].local.is_none());
    assert!(
        data.initial_state(&back, 0)
            .unwrap()
            .displacement
            .iter()
            .all(|d| *d == DVec3::ZERO)
    );
}

// ---------------------------------------------------------------------------------------------
// Errors

const GOOD_PART: &str = r#"(
        name: "p",
        placement: Pose(translation: (0.0, 0.0, 0.0), shape: (a: 1.0, a1: 1.0, a2: 1.0, a3: 1.0, e1: 1.0, e2: 1.0)),
        k: 5,
        w0: 0.001,
        w1: 0.1,
        forces: Range(data: "pts"),
    )"#;

fn scene_text(part: &str, data: &str) -> String {
    format!(
        "#![enable(implicit_some)]\n(\n    data: {{ {data} }},\n    parts: [\n    {part}\n    ],\n)\n"
    )
}

fn parse_err(text: &str) -> SceneError {
    SceneDef::parse(text, Path::new("bad.dsq.ron")).expect_err("the scene should be refused")
}

fn assert_names(e: &SceneError, field: Option<&str>, line: Option<usize>, what: &str) {
    let s = e.to_string();
    assert!(s.contains("bad.dsq.ron"), "{s}");
    if let Some(f) = field {
        assert_eq!(e.field.as_deref(), Some(f), "{s}");
    }
    if let Some(l) = line {
        assert_eq!(e.position.map(|p| p.0), Some(l), "{s}");
    }
    assert!(s.to_lowercase().contains(what), "{s} does not say {what:?}");
}

const PTS: &str = r#""pts": Generated(Egg)"#;

#[test]
fn a_good_scene_text_parses() {
    let def = SceneDef::parse(&scene_text(GOOD_PART, PTS), Path::new("good.dsq.ron")).unwrap();
    assert_eq!(def.parts[0].k, 5);
    assert_eq!(def.parts[0].dt, 0.05, "defaults fill what is left out");
}

#[test]
fn unknown_field_names_the_line_and_field() {
    let text = scene_text(
        &GOOD_PART.replace("k: 5,", "k: 5,\n        stiffnes: 3.0,"),
        PTS,
    );
    let e = parse_err(&text);
    // Line 1 is the extension, 2 `(`, 3 data, 4 `parts: [`, 5 `(`, 6 name, 7 placement, 8 k.
    assert_names(&e, Some("parts[0].stiffnes"), Some(9), "unexpected field");
}

#[test]
fn wrong_type_names_the_line_and_field() {
    let e = parse_err(&scene_text(&GOOD_PART.replace("k: 5", "k: \"five\""), PTS));
    assert_names(&e, Some("parts[0].k"), Some(8), "expected");
}

#[test]
fn nan_is_refused_with_the_field() {
    let e = parse_err(&scene_text(&GOOD_PART.replace("w1: 0.1", "w1: NaN"), PTS));
    assert_names(&e, Some("parts[0].w1"), None, "finite");
}

#[test]
fn negative_stiffness_is_refused_with_the_field() {
    let e = parse_err(&scene_text(
        &GOOD_PART.replace("w0: 0.001", "w0: -1.0"),
        PTS,
    ));
    assert_names(&e, Some("parts[0].w0"), None, "-1");
}

#[test]
fn an_outlier_fraction_of_one_or_more_is_refused_and_a_valid_one_reaches_the_fit() {
    let e = parse_err(&scene_text(
        &GOOD_PART.replace(
            r#"Range(data: "pts")"#,
            r#"Range(data: "pts", outliers: 1.5)"#,
        ),
        PTS,
    ));
    assert_names(&e, Some("parts[0].forces.outliers"), None, "found 1.5");
    let def = SceneDef::parse(
        &scene_text(
            &GOOD_PART.replace(
                r#"Range(data: "pts")"#,
                r#"Range(data: "pts", outliers: 0.2)"#,
            ),
            PTS,
        ),
        Path::new("good.dsq.ron"),
    )
    .unwrap();
    let part = &def.parts[0];
    let start = bevy_deformable_sq::model::dynamics::ModelState::new(
        &bevy_deformable_sq::model::fem::Tessellation::new(part.k),
        DVec3::ZERO,
        DQuat::IDENTITY,
        Default::default(),
    );
    assert_eq!(part.fit_options(&start).outlier_ratio, 0.2);
}

#[test]
fn an_exponent_below_the_least_is_refused_and_one_a_fit_can_write_is_read() {
    // A pure superquadric fit may end with an exponent below the dynamics' bound (the squareness
    // extension, down to LEAST_EPSILON = 0.01): its scene must load.
    let e = parse_err(&scene_text(&GOOD_PART.replace("e1: 1.0", "e1: 0.005"), PTS));
    assert_names(
        &e,
        Some("parts[0].placement.shape.e1"),
        None,
        "must lie in [0.01, 2], found 0.005",
    );
    let text = scene_text(&GOOD_PART.replace("e2: 1.0", "e2: 0.01"), PTS);
    assert!(SceneDef::parse(&text, Path::new("good.dsq.ron")).is_ok());
}

#[test]
fn k_below_3_is_refused_with_the_field() {
    let e = parse_err(&scene_text(&GOOD_PART.replace("k: 5", "k: 2"), PTS));
    assert_names(&e, Some("parts[0].k"), None, "found 2");
}

#[test]
fn tapering_and_bending_are_read_freed_and_bounded() {
    let part = GOOD_PART.replace(
        "k: 5,",
        "k: 5, deformation: (taper: (0.25, -0.5), bend: (0.3, 0.0)), free: (taper: true, bend: true),",
    );
    let def = SceneDef::parse(&scene_text(&part, PTS), Path::new("good.dsq.ron")).unwrap();
    let p = &def.parts[0];
    assert_eq!(p.deformation.taper, [0.25, -0.5]);
    assert_eq!(p.deformation.bend, [0.3, 0.0]);
    let free = p.dynamics().free;
    assert!(free.taper && free.bend);
    // Written back only when set.
    assert!(def.to_ron().unwrap().contains("taper"));
    let plain = SceneDef::parse(&scene_text(GOOD_PART, PTS), Path::new("good.dsq.ron")).unwrap();
    assert!(!plain.to_ron().unwrap().contains("taper"));
    assert!(!plain.parts[0].dynamics().free.taper);
    // Out of bounds: a taper beyond 1, a bend past the centre of curvature of a unit sphere
    // (|b| ≤ 0.9 × 1 / 1), a non-finite bend.
    for (deformation, field, what) in [
        (
            "(taper: (1.5, 0.0))",
            "parts[0].deformation.taper",
            "[-1, 1]",
        ),
        (
            "(bend: (0.0, 1.2))",
            "parts[0].deformation.bend",
            "beyond its bound 0.9",
        ),
        ("(bend: (inf, 0.0))", "parts[0].deformation.bend", "finite"),
    ] {
        let part = GOOD_PART.replace("k: 5,", &format!("k: 5, deformation: {deformation},"));
        let e = parse_err(&scene_text(&part, PTS));
        assert_names(&e, Some(field), None, what);
    }
}

#[test]
fn unknown_data_source_is_refused_with_the_field() {
    let e = parse_err(&scene_text(GOOD_PART, r#""other": Generated(Mug)"#));
    assert_names(&e, Some("parts[0].forces.data"), None, "\"pts\"");
}

/// A scene in a fresh directory whose single data source is `data`, with `files` beside it.
fn scene_dir_with(name: &str, data: &str, files: &[(&str, &[u8])]) -> PathBuf {
    let dir = scratch(name);
    for (f, bytes) in files {
        std::fs::write(dir.join(f), bytes).unwrap();
    }
    let file = dir.join("bad.dsq.ron");
    std::fs::write(&file, scene_text(GOOD_PART, data)).unwrap();
    file
}

fn load_err(file: &Path) -> SceneError {
    SceneDef::load_file(file).expect_err("the scene should be refused")
}

#[test]
fn missing_data_file_names_the_source() {
    let file = scene_dir_with(
        "missing",
        r#""pts": Points(path: "nowhere/cloud.ply")"#,
        &[],
    );
    let e = load_err(&file);
    assert_names(&e, Some("data.pts.path"), None, "cannot read");
    assert!(e.to_string().contains("cloud.ply"), "{e}");
}

#[test]
fn empty_point_file_names_the_source() {
    let file = scene_dir_with(
        "empty",
        r#""pts": Points(path: "empty.obj")"#,
        &[("empty.obj", b"\n")],
    );
    let e = load_err(&file);
    assert_names(&e, Some("data.pts.path"), None, "empty");
}

#[test]
fn unreadable_image_names_the_source() {
    let part = GOOD_PART.replace(r#"Range(data: "pts")"#, r#"Image(data: "img")"#);
    let dir = scratch("image");
    std::fs::write(dir.join("broken.png"), b"\x89PNG but not really").unwrap();
    let file = dir.join("bad.dsq.ron");
    std::fs::write(
        &file,
        scene_text(&part, r#""img": Image(path: "broken.png")"#),
    )
    .unwrap();
    let e = load_err(&file);
    assert_names(&e, Some("data.img.path"), None, "decode");
    assert!(e.to_string().contains("broken.png"), "{e}");
}

#[test]
fn a_crop_that_leaves_too_few_points_is_refused() {
    let part = GOOD_PART.replace(
        r#"Range(data: "pts")"#,
        r#"Range(data: "pts", crop: (min: (5.0, 5.0, 5.0), max: (6.0, 6.0, 6.0)))"#,
    );
    let dir = scratch("crop");
    let file = dir.join("bad.dsq.ron");
    std::fs::write(&file, scene_text(&part, PTS)).unwrap();
    let e = load_err(&file);
    assert_names(&e, Some("parts[0].forces"), None, "0 data points");
}

/// A scene (in its own scratch directory) with one range part on a ridged egg with Gaussian
/// noise of `sigma` along every axis, written as an OBJ; `flag` is written into the part.
fn noisy_egg_scene(name: &str, sigma: f64, flag: &str) -> PathBuf {
    let mut rng = synthetic::Rng::new(11);
    let mut obj = String::new();
    for p in synthetic::ridged_egg(2000, 5) {
        let q = p + sigma * DVec3::new(rng.normal(), rng.normal(), rng.normal());
        obj.push_str(&format!("v {} {} {}\n", q.x, q.y, q.z));
    }
    let dir = scratch(name);
    std::fs::write(dir.join("egg.obj"), obj).unwrap();
    let part = GOOD_PART.replace("w1: 0.1,", &format!("w1: 0.1,{flag}"));
    let file = dir.join("noisy.dsq.ron");
    std::fs::write(
        &file,
        scene_text(&part, r#""pts": Points(path: "egg.obj")"#),
    )
    .unwrap();
    file
}

#[test]
fn stiffness_from_noise_sets_w0_w1_from_the_parts_data_and_is_saved() {
    use bevy_deformable_sq::model::noise::{estimate_noise, stiffness_for_noise};
    let load = |file: &Path| SceneDef::load_file(file).unwrap_or_else(|e| panic!("{e}"));
    let mut w1 = Vec::new();
    for (i, sigma) in [0.002, 0.03].into_iter().enumerate() {
        let file = noisy_egg_scene(&format!("noise{i}"), sigma, " stiffness_from_noise: true,");
        let (def, data) = load(&file);
        let part = &def.parts[0];
        let noise = estimate_noise(&data.range_points(&def, 0).unwrap()).unwrap();
        assert_eq!(data.noise.get(&0), Some(&noise));
        assert_eq!((part.w0, part.w1), stiffness_for_noise(noise.relative));
        assert_ne!(part.w1, 0.1, "the written w1 is replaced");
        assert!(part.stiffness_from_noise);
        // The flag is saved, so the stiffness is chosen again from the data when reloaded.
        let text = def.to_ron().unwrap();
        assert!(text.contains("stiffness_from_noise: true"), "{text}");
        w1.push(part.w1);
    }
    assert!(w1[1] > 2.0 * w1[0], "more noise, stiffer membrane: {w1:?}");
    // Without the flag the scene's own values stand, and no estimate is made.
    let (def, data) = load(&noisy_egg_scene("noise-off", 0.03, ""));
    assert_eq!((def.parts[0].w0, def.parts[0].w1), (0.001, 0.1));
    assert!(data.noise.is_empty());
    assert!(!def.to_ron().unwrap().contains("stiffness_from_noise"));
}

#[test]
fn stiffness_from_noise_needs_range_forces() {
    let part = GOOD_PART.replace(
        r#"forces: Range(data: "pts"),"#,
        "forces: Free, stiffness_from_noise: true,",
    );
    let e = parse_err(&scene_text(&part, PTS));
    assert_names(
        &e,
        Some("parts[0].stiffness_from_noise"),
        None,
        "needs `forces: range",
    );
}

#[test]
fn a_shared_scan_is_split_so_every_point_pulls_on_one_part_and_the_parts_fit_closer_than_one() {
    let (def, data) = SceneDef::load_file(&shipped("cow_scan")).unwrap_or_else(|e| panic!("{e}"));
    let cloud = data.points["cow"].clone();
    let split = &data.splits["cow"];
    assert_eq!(split.owner.len(), cloud.len());
    // Every point belongs to exactly one part: the parts' points are disjoint and cover the scan.
    let mut seen = 0;
    for i in 0..def.parts.len() {
        let mine = data.range_points(&def, i).unwrap();
        assert!(mine.len() >= MIN_POINTS, "part {i}: {} points", mine.len());
        assert_eq!(
            mine.len(),
            split.owner.iter().filter(|&&o| o == i).count(),
            "part {i}"
        );
        seen += mine.len();
    }
    assert_eq!(seen, cloud.len());
    // Auto placement: each part starts boxing its own points.
    let start = data.initial_state(&def, 2).unwrap();
    let mine = data.range_points(&def, 2).unwrap();
    let centroid = mine.iter().copied().sum::<DVec3>() / mine.len() as f64;
    assert!(
        start.translation.distance(centroid) < start.shape.a,
        "{start:?}"
    );
    // The parts, each on its points, lie closer to the scan than one part fitted to all of it.
    let runs = run_scene(&def, &data, None);
    let mut d = Vec::new();
    for (i, run) in runs.iter().enumerate() {
        let run = run.as_ref().unwrap_or_else(|e| panic!("{e}"));
        let (tess, x) = node_positions(def.parts[i].k, run.state());
        d.extend(point_distances(
            &tess,
            &x,
            &data.range_points(&def, i).unwrap(),
        ));
    }
    let parts = Residuals::of(d, bounding_diagonal(&cloud)).mean;
    let one = fit(
        &cloud,
        &FitOptions {
            k: 21,
            ..FitOptions::default()
        },
        |_| {},
    )
    .unwrap()
    .residuals
    .mean;
    assert!(
        parts < 0.5 * one,
        "six parts {parts:.5} vs one part {one:.5}"
    );
}

#[test]
fn shared_sources_refuse_crops_and_mixed_placements_and_auto_needs_range_forces() {
    let shared = GOOD_PART.replace(
        r#"Range(data: "pts")"#,
        r#"Range(data: "pts", shared: true)"#,
    );
    let cropped = shared.replace(
        "shared: true",
        "shared: true, crop: (min: (0.0, 0.0, 0.0), max: (1.0, 1.0, 1.0))",
    );
    let e = parse_err(&scene_text(&cropped, PTS));
    assert_names(&e, Some("parts[0].forces.crop"), None, "shared");
    let auto = shared.replace(
        &shared[shared.find("placement:").unwrap()..shared.find("k: 5").unwrap()],
        "placement: Auto,\n        ",
    );
    let e = parse_err(&scene_text(&format!("{auto},\n    {shared}"), PTS));
    assert_names(&e, Some("parts[1].placement"), None, "all be placed auto");
    let free = auto.replace(r#"forces: Range(data: "pts", shared: true),"#, "");
    let e = parse_err(&scene_text(&free, PTS));
    assert_names(&e, Some("parts[0].placement"), None, "range");
    // Two Auto parts on the egg: loads, and splits the egg between them.
    let dir = scratch("shared");
    let file = dir.join("two.dsq.ron");
    std::fs::write(&file, scene_text(&format!("{auto},\n    {auto}"), PTS)).unwrap();
    let (def, data) = SceneDef::load_file(&file).unwrap_or_else(|e| panic!("{e}"));
    let n: Vec<usize> = (0..2)
        .map(|i| data.range_points(&def, i).unwrap().len())
        .collect();
    assert_eq!(n[0] + n[1], data.points["pts"].len(), "{n:?}");
}

// ---------------------------------------------------------------------------------------------
// Through the plugin

fn shipped_assets() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("assets")
}

#[test]
fn the_asset_loader_sets_the_stiffness_from_the_datas_noise() {
    let file = noisy_egg_scene("noise-app", 0.03, " stiffness_from_noise: true,");
    let (def, _) = SceneDef::load_file(&file).unwrap_or_else(|e| panic!("{e}"));
    let mut app = scene_app(file.parent().unwrap());
    let root = load(&mut app, "noisy.dsq.ron");
    let instance = app.world().get::<SceneInstance>(root).unwrap();
    assert!(instance.error.is_none(), "{:?}", instance.error);
    let settings = app
        .world()
        .get::<ModelSettings>(parts(&app, root)[0])
        .unwrap();
    assert_eq!(
        (settings.w0, settings.w1),
        (def.parts[0].w0, def.parts[0].w1)
    );
    assert_ne!(settings.w1, 0.1);
}

#[test]
fn a_scene_parts_outlier_fraction_reaches_its_fit_through_the_plugin() {
    let file = noisy_egg_scene("outliers-app", 0.01, "");
    let text = std::fs::read_to_string(&file).unwrap();
    let text = text.replace(
        r#"Range(data: "pts")"#,
        r#"Range(data: "pts", outliers: 0.2)"#,
    );
    std::fs::write(&file, text).unwrap();
    let mut app = scene_app(file.parent().unwrap());
    let root = load(&mut app, "noisy.dsq.ron");
    let part = parts(&app, root)[0];
    app.world_mut().run_schedule(Step);
    let driver = app
        .world()
        .get::<FitDriver>(part)
        .expect("a range part is fitted");
    assert_eq!(driver.options().outlier_ratio, 0.2);
    // The options are the core scene runner's, so the fit is `dsq fit --scene`'s.
    let (def, data) = SceneDef::load_file(&file).unwrap();
    let start = data.initial_state(&def, 0).unwrap();
    assert_eq!(*driver.options(), def.parts[0].fit_options(&start));
}

#[test]
fn shipped_scenes_spawn_entities_that_simulate_and_despawn_with_the_root() {
    let mut app = scene_app(&shipped_assets());
    for (name, n) in SHIPPED {
        let root = load(&mut app, &format!("scenes/{name}.dsq.ron"));
        let instance = app.world().get::<SceneInstance>(root).unwrap();
        assert!(instance.error.is_none(), "{name}: {:?}", instance.error);
        let ps = parts(&app, root);
        assert_eq!(ps.len(), n, "{name}");
        let (def, data) = SceneDef::load_file(&shipped(name)).unwrap();
        let images = app
            .world()
            .get::<SceneInstance>(root)
            .unwrap()
            .images
            .clone();
        assert_eq!(
            images.len(),
            data.images.len(),
            "{name}: one backdrop per image"
        );
        for &e in &images {
            let image = app.world().get::<SceneImage>(e).unwrap();
            let source = &data.images[&image.name];
            assert_eq!(image.potential.luminance(), source.luminance(), "{name}");
        }
        for (&e, part) in ps.iter().zip(&def.parts) {
            let w = app.world();
            assert_eq!(w.get::<Name>(e).unwrap().as_str(), part.name);
            assert_eq!(w.get::<FemMesh>(e).unwrap().k, part.k);
            assert_eq!(w.get::<ChildOf>(e).unwrap().parent(), root);
            let image = part.on_image();
            assert_eq!(w.get::<ImageData>(e).is_some(), image, "{name}");
            assert_eq!(w.get::<RangeData>(e).is_some(), !image, "{name}");
            assert_eq!(w.get::<FitDriver>(e).is_some(), !image, "{name}");
            assert_eq!(w.get::<ModelSettings>(e).unwrap().planar, image);
        }
        for _ in 0..5 {
            app.world_mut().run_schedule(Step);
        }
        for (&e, part) in ps.iter().zip(&def.parts) {
            let w = app.world();
            let c = w.get::<SimControl>(e).unwrap();
            // A range part is paused while its fit (on another thread) moves it.
            let steps = if part.on_image() { 5 } else { 0 };
            assert_eq!((c.steps, c.frozen), (steps, false), "{name}");
            let shape = w.get::<GlobalShape>(e).unwrap();
            assert!(shape.a.is_finite() && w.get::<RigidState>(e).unwrap().translation.is_finite());
        }
        app.world_mut().entity_mut(root).despawn();
        app.update();
        for &e in ps.iter().chain(&images) {
            assert!(
                app.world().get_entity(e).is_err(),
                "{name}: part outlived its root"
            );
        }
    }
}

#[test]
fn a_scene_saved_from_the_app_loads_back_bit_for_bit() {
    // The egg scene's data are generated: it can move to a scratch asset folder as it is.
    let dir = scratch("roundtrip");
    std::fs::copy(shipped("egg"), dir.join("egg.dsq.ron")).unwrap();
    let mut app = scene_app(&dir);
    let root = load(&mut app, "egg.dsq.ron");
    let e = parts(&app, root)[0];
    // The part's fit runs on another thread: until it is done.
    for _ in 0..200_000 {
        app.world_mut().run_schedule(Step);
        if app
            .world()
            .get::<FitDriver>(e)
            .is_some_and(FitDriver::is_done)
        {
            break;
        }
        std::thread::sleep(std::time::Duration::from_micros(200));
    }
    assert!(app.world().get::<FitDriver>(e).unwrap().converged());
    // The fit holds the local DOFs at first: give them values as an inspector would.
    for (i, d) in app
        .world_mut()
        .get_mut::<LocalDofs>(e)
        .unwrap()
        .displacement
        .iter_mut()
        .enumerate()
    {
        *d = DVec3::new((i as f64 * 0.1).sin(), 1.0 / (i as f64 + 3.0), -0.0) * 1e-3;
    }
    for _ in 0..5 {
        app.world_mut().run_schedule(Step);
    }
    let local = app.world().get::<LocalDofs>(e).unwrap().clone();
    assert!(
        local
            .displacement
            .iter()
            .filter(|d| **d != DVec3::ZERO)
            .count()
            > 100
    );
    save_scene(app.world(), root, &dir.join("saved.dsq.ron"), &dir, true).unwrap();

    let mut again = scene_app(&dir);
    let root2 = load(&mut again, "saved.dsq.ron");
    let e2 = parts(&again, root2)[0];
    let (a, b) = (app.world(), again.world());
    let rigid = |w: &World, e| *w.get::<RigidState>(e).unwrap();
    let shape = |w: &World, e| *w.get::<GlobalShape>(e).unwrap();
    let bits = |r: RigidState, s: GlobalShape| {
        let mut v: Vec<u64> = r
            .translation
            .to_array()
            .iter()
            .map(|x| x.to_bits())
            .collect();
        v.extend(r.rotation.to_array().iter().map(|x| x.to_bits()));
        v.extend(
            [s.a, s.a1, s.a2, s.a3, s.e1, s.e2]
                .iter()
                .map(|x| x.to_bits()),
        );
        v
    };
    assert_eq!(
        bits(rigid(a, e), shape(a, e)),
        bits(rigid(b, e2), shape(b, e2))
    );
    let moved = rigid(a, e).translation
        != DVec3::new(
            0.04364729458917831,
            0.013887775551102207,
            0.3739771742297049,
        );
    assert!(moved, "the fit did not move the model");
    let local2 = b.get::<LocalDofs>(e2).unwrap();
    let dbits = |d: &[DVec3]| -> Vec<[u64; 3]> {
        d.iter().map(|v| v.to_array().map(f64::to_bits)).collect()
    };
    assert_eq!(dbits(&local2.displacement), dbits(&local.displacement));
    assert_eq!(b.get::<ModelSettings>(e2), a.get::<ModelSettings>(e));
}

#[test]
fn a_model_added_under_the_root_is_saved_as_a_new_part() {
    let dir = scratch("added");
    std::fs::copy(shipped("mug"), dir.join("mug.dsq.ron")).unwrap();
    let mut app = scene_app(&dir);
    let root = load(&mut app, "mug.dsq.ron");
    let rigid = RigidState {
        translation: DVec3::new(0.1 + 0.2, -2.0, 1.0 / 3.0),
        rotation: DQuat::from_rotation_y(0.7),
    };
    let shape = GlobalShape {
        a: 0.4,
        a1: 1.0,
        a2: 0.5,
        a3: 0.25,
        e1: 0.3,
        e2: 1.9,
        taper: [0.1, -0.2],
        bend: [0.15, -0.05],
    };
    app.world_mut().spawn((
        Name::new("placed"),
        shape,
        ModelSettings {
            taper: true,
            bend: true,
            ..Default::default()
        },
        rigid,
        FemMesh::new(7),
        ChildOf(root),
    ));
    for _ in 0..3 {
        app.world_mut().run_schedule(Step);
    }
    save_scene(app.world(), root, &dir.join("more.dsq.ron"), &dir, false).unwrap();
    let (def, _) = SceneDef::load_file(&dir.join("more.dsq.ron")).unwrap();
    assert_eq!(def.parts.len(), 2);
    assert_eq!(def.parts[1].name, "placed");
    assert_eq!(def.parts[1].k, 7);
    assert_eq!(def.parts[1].forces, bevy_deformable_sq::scene::Forces::Free);
    assert!(def.parts[1].free.taper && def.parts[1].free.bend);
    let mut again = scene_app(&dir);
    let root2 = load(&mut again, "more.dsq.ron");
    let e = parts(&again, root2)[1];
    // A part with no forces keeps its pose and shape bit for bit.
    assert_eq!(*again.world().get::<RigidState>(e).unwrap(), rigid);
    assert_eq!(*again.world().get::<GlobalShape>(e).unwrap(), shape);
}

#[test]
fn a_bad_scene_is_logged_and_the_app_keeps_running() {
    let dir = scratch("badapp");
    std::fs::write(
        dir.join("bad.dsq.ron"),
        scene_text(&GOOD_PART.replace("k: 5", "k: 1"), PTS),
    )
    .unwrap();
    std::fs::copy(shipped("mug"), dir.join("mug.dsq.ron")).unwrap();
    let mut app = scene_app(&dir);
    let bad = load(&mut app, "bad.dsq.ron");
    let error = app.world().get::<SceneInstance>(bad).unwrap().error.clone();
    let error = error.expect("the failure is recorded");
    assert!(
        error.contains("bad.dsq.ron") && error.contains("parts[0].k"),
        "{error}"
    );
    assert!(parts(&app, bad).is_empty());
    // The app goes on: another scene still loads and simulates.
    let good = load(&mut app, "mug.dsq.ron");
    assert_eq!(parts(&app, good).len(), 1);
    app.world_mut().run_schedule(Step);
    app.update();
    let e = parts(&app, good)[0];
    let c = app.world().get::<SimControl>(e).unwrap();
    assert!(c.paused && !c.frozen, "{c:?}");
    assert!(app.world().get::<FitDriver>(e).is_some());
}

#[test]
fn a_changed_scene_asset_respawns_its_parts() {
    let mut app = scene_app(&shipped_assets());
    let root = load(&mut app, "scenes/mug.dsq.ron");
    let before = parts(&app, root);
    let id = app.world().get::<DeformableSceneRoot>(root).unwrap().0.id();
    app.world_mut()
        .resource_mut::<Assets<DeformableScene>>()
        .get_mut(id)
        .unwrap()
        .def
        .parts[0]
        .k = 9;
    app.update();
    app.update();
    let after = parts(&app, root);
    assert_eq!(after.len(), 1);
    assert_ne!(after, before, "the part was not respawned");
    assert!(app.world().get_entity(before[0]).is_err());
    assert_eq!(app.world().get::<FemMesh>(after[0]).unwrap().k, 9);
}

#[test]
fn axes_placement_matches_the_image_fitters() {
    // A part placed by four pixel points sits where `PartAxes` puts it: centre of the major axis.
    let (def, data) = SceneDef::load_file(&shipped("pestle")).unwrap();
    let potential = data.images["rocket"].clone();
    let s = data.initial_state(&def, 0).unwrap();
    let centre = potential.to_plane(DVec2::new(322.0, 265.0));
    assert!(
        (s.translation.truncate() - centre).length() < 1e-12,
        "{:?} vs {centre:?}",
        s.translation
    );
}

#[test]
fn the_documented_example_scene_parses_and_loads() {
    let readme =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/scene-format.md"))
            .unwrap();
    let start = readme
        .find("```ron\n")
        .expect("docs/scene-format.md has a ron block")
        + "```ron\n".len();
    let text = &readme[start..start + readme[start..].find("```").unwrap()];
    // Its paths are written as from `assets/scenes/`.
    let file = shipped("readme-example");
    let def = SceneDef::parse(text, &file).unwrap_or_else(|e| panic!("{e}"));
    let dir = file.parent().unwrap().to_path_buf();
    let data = bevy_deformable_sq::scene::SceneData::resolve(&def, &file, |rel| {
        std::fs::read(dir.join(rel)).map_err(|e| e.to_string())
    })
    .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(def.parts.len(), 2);
    assert_eq!(
        data.range_points(&def, 0).unwrap().len(),
        3029,
        "the crop keeps the whole bunny"
    );
    assert!(data.initial_state(&def, 1).is_some());
}

#[test]
fn a_parts_inertia_is_read_spawned_saved_and_checked() {
    // `inertia: (..)` gives the spawned part an Inertia component (second-order dynamics) with
    // those parameters (the rest default), and saving the scene writes it back; a bad value is
    // refused naming the field.
    let dir = scratch("inertia");
    let part = GOOD_PART.replace("k: 5,", "k: 5, inertia: (damping: 2.0),");
    std::fs::write(dir.join("mass.dsq.ron"), scene_text(&part, PTS)).unwrap();
    let mut app = scene_app(&dir);
    let root = load(&mut app, "mass.dsq.ron");
    let e = parts(&app, root)[0];
    let inertia = app.world().get::<Inertia>(e).expect("the part has inertia");
    assert_eq!(inertia.params.damping, 2.0);
    assert_eq!(
        inertia.params.mass_density,
        bevy_deformable_sq::model::inertia::InertiaParams::default().mass_density
    );
    for _ in 0..3 {
        app.world_mut().run_schedule(Step);
    }
    assert!(!app.world().get::<SimControl>(e).unwrap().frozen);
    save_scene(app.world(), root, &dir.join("saved.dsq.ron"), &dir, false).unwrap();
    let (def, _) = SceneDef::load_file(&dir.join("saved.dsq.ron")).unwrap();
    assert_eq!(def.parts[0].inertia.map(|i| i.damping), Some(2.0));
    // A part without it has none, and none is written.
    let plain = SceneDef::parse(&scene_text(GOOD_PART, PTS), Path::new("good.dsq.ron")).unwrap();
    assert!(plain.parts[0].inertia.is_none());
    assert!(!plain.to_ron().unwrap().contains("inertia"));
    for (value, field) in [
        ("(mass_density: 0.0)", "parts[0].inertia.mass_density"),
        ("(local_inertia: -1.0)", "parts[0].inertia.local_inertia"),
        ("(damping: inf)", "parts[0].inertia.damping"),
    ] {
        let part = GOOD_PART.replace("k: 5,", &format!("k: 5, inertia: {value},"));
        let e = parse_err(&scene_text(&part, PTS));
        assert_names(&e, Some(field), None, "finite number");
    }
}

#[test]
fn a_scenes_joints_hold_a_pulled_chain_together_and_are_saved() {
    // The shipped chain: four links jointed pole to pole. A spring pulls the last link up and
    // away; the joints spawn between the right parts, keep every gap closed, and the first link
    // follows. Saving writes the joints back.
    let mut app = scene_app(&shipped_assets());
    let root = load(&mut app, "scenes/chain.dsq.ron");
    let links = parts(&app, root);
    assert_eq!(links.len(), 4);
    let mut q = app.world_mut().query::<&PartJoint>();
    let joints: Vec<PartJoint> = q.iter(app.world()).cloned().collect();
    assert_eq!(joints.len(), 3);
    for (i, j) in joints.iter().enumerate() {
        assert!(
            links.contains(&j.a) && links.contains(&j.b) && j.a != j.b,
            "joint {i}"
        );
    }
    let start = app.world().get::<RigidState>(links[0]).unwrap().translation;
    app.world_mut()
        .entity_mut(links[3])
        .insert(SpringForces(vec![Spring {
            u: std::f64::consts::FRAC_PI_2,
            v: 0.0,
            anchor: DVec3::new(3.5, 2.0, 0.0),
            stiffness: 2.0,
            reshape: true,
        }]));
    for _ in 0..600 {
        app.world_mut().run_schedule(Step);
    }
    let mut q = app.world_mut().query::<&PartJoint>();
    for j in q.iter(app.world()) {
        assert!(
            j.gap.length() < 0.01,
            "a joint opened by {}",
            j.gap.length()
        );
    }
    let moved = app.world().get::<RigidState>(links[0]).unwrap().translation - start;
    assert!(
        moved.length() > 0.3,
        "the first link stayed behind: {moved}"
    );
    for &e in &links {
        assert!(!app.world().get::<SimControl>(e).unwrap().frozen);
    }
    let dir = scratch("chain");
    save_scene(
        app.world(),
        root,
        &dir.join("chain.dsq.ron"),
        &shipped_assets().join("scenes"),
        false,
    )
    .unwrap();
    let (def, _) = SceneDef::load_file(&dir.join("chain.dsq.ron")).unwrap();
    assert_eq!(def.joints.len(), 3);
    assert_eq!(def.joints[0].parts, [0, 1]);
}

#[test]
fn a_bad_joint_is_refused_naming_the_field() {
    let two = format!("{GOOD_PART},\n    {}", GOOD_PART.replace("\"p\"", "\"q\""));
    for (joints, field, what) in [
        (
            "[(parts: (0, 0), ends: ((u: 0.0, v: 0.0), (u: 0.0, v: 0.0)))]",
            "joints[0].parts",
            "two different parts",
        ),
        (
            "[(parts: (0, 5), ends: ((u: 0.0, v: 0.0), (u: 0.0, v: 0.0)))]",
            "joints[0].parts",
            "found (0, 5)",
        ),
        (
            "[(parts: (0, 1), ends: ((u: 2.0, v: 0.0), (u: 0.0, v: 0.0)))]",
            "joints[0].ends[0]",
            "[-π/2, π/2]",
        ),
        (
            "[(parts: (0, 1), ends: ((u: 0.0, v: 0.0), (u: 0.0, v: 0.0)), stiffness: 0.0)]",
            "joints[0].stiffness",
            "> 0",
        ),
    ] {
        let text = scene_text(&two, PTS).replace("\n)\n", &format!("\n    joints: {joints},\n)\n"));
        let e = parse_err(&text);
        assert_names(&e, Some(field), None, what);
    }
}

/// The plugin group added before Bevy's `AssetPlugin` still loads scene files: the loader is
/// registered when the app's plugins are finished, not when the group is added.
#[test]
fn scenes_load_whichever_order_the_plugins_are_added_in() {
    let assets = shipped_assets();
    let mut app = App::new();
    app.add_plugins((
        MinimalPlugins,
        DeformableSqPlugins::in_schedule(Step),
        AssetPlugin {
            file_path: assets.display().to_string(),
            ..default()
        },
    ));
    app.init_schedule(Step);
    // What `App::run` does before its first update.
    app.finish();
    app.cleanup();
    let root = load(&mut app, "scenes/egg.dsq.ron");
    let instance = app.world().get::<SceneInstance>(root).unwrap();
    assert!(instance.error.is_none(), "{:?}", instance.error);
    assert_eq!(parts(&app, root).len(), 1);
}
