//! The image fit swept over generated photos whose truth is known (`synthetic::photo`: shaded
//! superquadrics, faces as bright as the desk, textures, clutter, shadows, blur, noise, clicks up
//! to a quarter of the size off).
//!
//! ```text
//! cargo bench --bench photos [-- --photos N] [--first S] [--write DIR]
//! ```
//!
//! Each photo is fitted as `dsq fit --image` fits a colour photo from four clicks per object, in
//! every solved mode (default, `--global-only`, `--global-only --fix-epsilon`), and each object
//! is scored by the IoU of its part's silhouette with its mask. Prints a row per photo, then per
//! mode the least and median IoU, the objects under 0.85 and the parts not at rest. `--photos N`
//! (default 120) photos from seed `--first S` (default 0). `--write DIR` writes each photo as
//! `DIR/photo_S.png` and its default fit's overlay as `DIR/photo_S_fit.png`.

use bevy_deformable_sq::io::write_overlay_png;
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::forces::image::{ImageFrame, ImagePotential};
use bevy_deformable_sq::model::image_fit::{
    ImageFitOptions, PartAxes, fit_image, iou, outline_segments, silhouette_mask,
};
use bevy_deformable_sq::synthetic::{PHOTO_HEIGHT, PHOTO_WIDTH, photo};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

#[path = "common/mode.rs"]
mod mode;

struct Args {
    photos: u64,
    first: u64,
    write: Option<PathBuf>,
}

fn parse(benched: bool) -> Result<Args, String> {
    let mut a = Args {
        photos: if benched { 120 } else { 2 },
        first: 0,
        write: None,
    };
    let mut args = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .filter(|_| benched);
    while let Some(flag) = args.next() {
        let mut number = |name: &str| {
            args.next()
                .and_then(|n| n.parse::<u64>().ok())
                .ok_or(format!("{name}: expected a whole number"))
        };
        match flag.as_str() {
            "--photos" => a.photos = number("--photos")?,
            "--first" => a.first = number("--first")?,
            "--write" => {
                a.write = Some(args.next().ok_or("--write: expected a folder")?.into());
            }
            other => return Err(format!("unknown argument {other:?}")),
        }
    }
    Ok(a)
}

fn modes() -> [(&'static str, ImageFitOptions); 3] {
    let d = ImageFitOptions::default();
    [
        ("default", d),
        ("global-only", ImageFitOptions { local: false, ..d }),
        (
            "global-only, ε held",
            ImageFitOptions {
                local: false,
                fix_epsilon: true,
                ..d
            },
        ),
    ]
}

fn run(a: &Args) -> Result<(), String> {
    let (w, h) = (PHOTO_WIDTH, PHOTO_HEIGHT);
    // Per mode: every object's IoU (with its photo and kind), parts not at rest.
    let mut scores: Vec<Vec<(f64, u64, String)>> = vec![Vec::new(); 3];
    let mut restless = [0usize; 3];
    if let Some(dir) = &a.write {
        std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    }
    for seed in a.first..a.first + a.photos {
        let p = photo(seed);
        let pot = Arc::new(
            ImagePotential::new(w, h, p.luminance(), 2.0, ImageFrame::default())
                .and_then(|pot| pot.with_colour(p.rgb.clone()))
                .map_err(|e| format!("photo {seed}: {e}"))?,
        );
        let placed: Vec<PartAxes> = p
            .objects
            .iter()
            .map(|o| PartAxes::from_points(&pot, o.clicks))
            .collect::<Result<_, _>>()
            .map_err(|e| format!("photo {seed}: {e}"))?;
        let mut row = format!("photo {seed:3} ({}):", p.description);
        for (m, (name, opts)) in modes().iter().enumerate() {
            let fits = fit_image(pot.clone(), &placed, opts).map_err(|e| format!("{e}"))?;
            let tess = Tessellation::new(opts.k);
            let mut outlines = Vec::new();
            for (f, o) in fits.iter().zip(&p.objects) {
                let mut x = Vec::new();
                f.state.node_positions(&tess, &mut x);
                let score = iou(&silhouette_mask(&pot, &[(&tess, &x)]), &o.mask);
                mode::check_finite("IoU", &[score])?;
                scores[m].push((score, seed, o.kind.clone()));
                restless[m] += usize::from(!f.converged);
                row += &format!(
                    " {name} {score:.3}{}",
                    if f.converged { "" } else { " (moving)" }
                );
                outlines.push(outline_segments(&tess, &x));
            }
            if let (Some(dir), 0) = (&a.write, m) {
                let fit = dir.join(format!("photo_{seed}_fit.png"));
                write_overlay_png(&fit, &pot, &outlines).map_err(|e| e.to_string())?;
                let bytes: Vec<u8> = p
                    .rgb
                    .iter()
                    .flat_map(|c| c.map(|v| (v * 255.0).round() as u8))
                    .collect();
                let shot = dir.join(format!("photo_{seed}.png"));
                image::save_buffer(&shot, &bytes, w as u32, h as u32, image::ColorType::Rgb8)
                    .map_err(|e| format!("{}: {e}", shot.display()))?;
            }
        }
        println!(
            "{row}  [{}]",
            p.objects
                .iter()
                .map(|o| o.kind.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    for (m, (name, _)) in modes().iter().enumerate() {
        let s = &mut scores[m];
        s.sort_by(|x, y| x.0.total_cmp(&y.0));
        let (least, seed, kind) = &s[0];
        let median = s[s.len() / 2].0;
        let under = s.iter().filter(|x| x.0 < 0.85).count();
        println!(
            "{name}: {} objects, least IoU {least:.3} (photo {seed}, {kind}), median {median:.3}, \
             {under} under 0.85, {} not at rest",
            s.len(),
            restless[m]
        );
    }
    Ok(())
}

fn main() -> ExitCode {
    match parse(mode::benched()).and_then(|a| run(&a)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("photos: {e}");
            ExitCode::FAILURE
        }
    }
}
