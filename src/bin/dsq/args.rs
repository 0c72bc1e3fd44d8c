//! `dsq fit`'s options (clap's derive API) and their resolution into the fitter's settings.
//!
//! Where options overlap, the order is fixed, whatever the order on the command line: a
//! `--paper` experiment's settings first, then `--robust`, then every option given by itself.

use bevy_deformable_sq::io::{MAX_MESH_SAMPLES, MESH_SAMPLES};
use bevy_deformable_sq::model::fit::{
    CloudOptions, FitOptions, NoiseStiffness, Solver, Stiffness, k_for_nodes,
};
use bevy_deformable_sq::model::forces::image::DEFAULT_SIGMA;
use bevy_deformable_sq::model::image_fit::{ImageChoices, ImageFitOptions};
use bevy_deformable_sq::model::parts::{DEFAULT_MAX_PARTS, PartCount};
use bevy_deformable_sq::synthetic;
use bevy_deformable_sq::synthetic::{doll_experiment, pestle_experiment};
use clap::{Args as ClapArgs, ValueEnum};
use glam::{DVec2, DVec3};
use std::path::PathBuf;

/// One of the paper's experiments (section VI), on its rebuilt or stand-in data.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Paper {
    /// The egg range map (2603 nodes, 499 points).
    Egg,
    /// The mug range map (1683 nodes, 651 points).
    Mug,
    /// The pestle image experiment, on the shipped rocket image.
    Pestle,
    /// The doll image experiment (11 parts), on the shipped horse image.
    Doll,
}

/// How a point fit comes to rest (`--solver`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum SolverArg {
    /// Solved for (the default): the superquadric (with its tapering and bending) by
    /// Levenberg–Marquardt, the membrane by linear solves.
    #[value(alias = "lm")]
    Solved,
    /// The paper's explicit dynamics under range springs.
    Dynamics,
}

/// The membrane's w1: a number, or `auto` (chosen from the cloud's noise).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum W1 {
    /// From the noise the points show.
    Auto,
    /// As given.
    Value(f64),
}

/// `dsq fit`'s command line.
#[derive(ClapArgs, Debug)]
#[command(
    allow_negative_numbers = true,
    after_help = "\
A POINTS file is fitted by default with --solver solved --outliers 0.2 --plane --w1 auto, and \
with --robust when --global-only. --paper-forces starts from the paper's springs and stiffness \
instead; --solver dynamics runs the paper's explicit dynamics. Progress goes to stderr; stdout gets one JSON line per part and a summary line. Bad input \
exits with code 2 and a one-line message."
)]
pub struct FitArgs {
    /// The point cloud: an OBJ or PLY file, its vertices the points; a file with faces is a
    /// mesh, read as points spread uniformly by area over its surface (see --mesh-samples).
    /// Give several to fit them side by side over every core: a JSON line per file, in the
    /// order given.
    #[arg(value_name = "POINTS")]
    pub points: Vec<PathBuf>,
    /// How many points a mesh's surface is read as (default 10000; 1 to 10⁸).
    #[arg(long, value_name = "N")]
    pub mesh_samples: Option<usize>,
    /// Fit the parts of an image (PNG or JPEG) instead.
    #[arg(long, value_name = "IMAGE")]
    pub image: Option<PathBuf>,
    /// Run every part of a scene file (.dsq.ron) to rest with the scene's settings.
    #[arg(long, value_name = "FILE")]
    pub scene: Option<PathBuf>,
    /// Run one of the paper's experiments with its settings (other options override them).
    #[arg(long, value_enum, value_name = "EXPERIMENT")]
    pub paper: Option<Paper>,

    /// Node count k² + 2 (e.g. 963, 1683, 2603, 5043).
    #[arg(long, value_name = "N", conflicts_with = "k", help_heading = "Model")]
    pub nodes: Option<usize>,
    /// Tessellation: k latitude rings × k longitudes + 2 poles (k in [3, 836]: the largest takes
    /// about 1 GB).
    #[arg(long, value_name = "K", help_heading = "Model")]
    pub k: Option<u32>,
    /// Membrane stiffness w0 (≥ 0).
    #[arg(long, value_name = "F", value_parser = non_negative, help_heading = "Model")]
    pub w0: Option<f64>,
    /// Membrane stiffness w1 (≥ 0), or `auto` to choose it (and w0) from the cloud's noise.
    #[arg(long, value_name = "F|auto", value_parser = w1, help_heading = "Model")]
    pub w1: Option<W1>,
    /// Data-spring strength β (> 0).
    #[arg(long, value_name = "F", value_parser = positive, help_heading = "Model")]
    pub beta: Option<f64>,
    /// Step cap (per part for scenes and images; at least 1).
    #[arg(long, value_name = "N", help_heading = "Model")]
    pub max_steps: Option<u32>,

    /// Write the fitted mesh (OBJ).
    #[arg(long, value_name = "FILE.obj", help_heading = "Output")]
    pub out_mesh: Option<PathBuf>,
    /// Write the fitted parameters (JSON).
    #[arg(long, value_name = "FILE.json", help_heading = "Output")]
    pub out_params: Option<PathBuf>,
    /// Write each cloud's mesh and parameters into DIR (created if missing) as STEM.obj and
    /// STEM.json, STEM being the file's name without its extension.
    #[arg(long, value_name = "DIR", help_heading = "Output")]
    pub out_dir: Option<PathBuf>,
    /// No progress lines on stderr.
    #[arg(long, help_heading = "Output")]
    pub quiet: bool,

    /// A pure superquadric: the local DOFs stay frozen (for an image, each part's global
    /// stage only).
    #[arg(long, help_heading = "Point clouds")]
    pub global_only: bool,
    /// Start from the paper's forces and stiffness (equal weights, nearest-node springs,
    /// w0 = 1e-3, w1 = 0.1) instead of the data-driven defaults.
    #[arg(long, help_heading = "Point clouds")]
    pub paper_forces: bool,
    /// How the fit comes to rest: `solved` (the default; `lm` is the same): the superquadric
    /// solved for by Levenberg–Marquardt and, with local DOFs, the membrane by linear solves; or
    /// `dynamics`: the paper's explicit steps.
    #[arg(long, value_enum, help_heading = "Point clouds")]
    pub solver: Option<SolverArg>,
    /// Point-to-plane springs in the global stage.
    #[arg(long, help_heading = "Point clouds")]
    pub plane: bool,
    /// Prior fraction of outliers for the robust spring weights, in [0, 1).
    #[arg(long, value_name = "F", value_parser = fraction, help_heading = "Point clouds")]
    pub outliers: Option<f64>,
    /// Also try the cross-section dual of the chosen hypothesis.
    #[arg(long, help_heading = "Point clouds")]
    pub switch: bool,
    /// Also try the fit's similarity candidates.
    #[arg(long, help_heading = "Point clouds")]
    pub similar: bool,
    /// --outliers 0.2 --plane --switch --similar: the most accurate pure superquadric on
    /// partial or outlier-ridden clouds.
    #[arg(long, help_heading = "Point clouds")]
    pub robust: bool,
    /// Points of influence migrate over the surface (the paper's Fig. 3).
    #[arg(long, help_heading = "Point clouds")]
    pub migrate: bool,
    /// Reattach the points every N steps (the paper: 200; at least 1).
    #[arg(long, value_name = "N", help_heading = "Point clouds")]
    pub reassign: Option<u32>,
    /// Split a cloud into parts: `auto` (as many as its description length asks, see
    /// --max-parts) or exactly N; an image: its N largest blobs (at least 1).
    #[arg(long, value_name = "auto|N", value_parser = parts_arg, help_heading = "Point clouds")]
    pub parts: Option<PartsArg>,
    /// With --parts auto: at most N parts (default 12, `model::parts::DEFAULT_MAX_PARTS`).
    #[arg(long, value_name = "N", help_heading = "Point clouds")]
    pub max_parts: Option<usize>,
    /// Run the fit through the Bevy plugin in a headless app (needs the `bevy` feature).
    #[arg(long, help_heading = "Point clouds")]
    pub app: bool,
    /// Free the global tapering.
    #[arg(long, help_heading = "Point clouds")]
    pub taper: bool,
    /// Free the global bending.
    #[arg(long, help_heading = "Point clouds")]
    pub bend: bool,
    /// The membrane's update as one backward-Euler step solved by conjugate gradients, with
    /// local damping γ_d = GAMMA (> 0, e.g. 0.01).
    #[arg(long, value_name = "GAMMA", value_parser = positive, help_heading = "Point clouds")]
    pub implicit_local: Option<f64>,

    /// Gaussian blur σ of the image potential, pixels (> 0).
    #[arg(long, value_name = "PX", value_parser = positive, help_heading = "Images")]
    pub sigma: Option<f64>,
    /// Half-width of the band |x3| < F in which image forces act (> 0).
    #[arg(long, value_name = "F", value_parser = positive, help_heading = "Images")]
    pub band: Option<f64>,
    /// Region (balloon) force fraction (≥ 0).
    #[arg(long, value_name = "F", value_parser = non_negative, help_heading = "Images")]
    pub region: Option<f64>,
    /// The paper's image forces on every node in the band, not only the projected outline.
    #[arg(long, help_heading = "Images")]
    pub paper_band: bool,
    /// Let the parts move in depth too.
    #[arg(long, help_heading = "Images")]
    pub free_depth: bool,
    /// Hold the squareness ε1 = ε2 = 1, as the paper does for the pestle and the doll: every
    /// part an ellipsoid.
    #[arg(long, help_heading = "Images")]
    pub fix_epsilon: bool,
    /// Place a part by four pixel points: both ends of the major axis, then of the minor axis.
    #[arg(long, value_name = "x0,y0,x1,y1,x2,y2,x3,y3", value_parser = part, help_heading = "Images")]
    pub part: Vec<[DVec2; 4]>,
    /// Draw the fitted outlines over the image (PNG).
    #[arg(long, value_name = "FILE.png", help_heading = "Images")]
    pub out_overlay: Option<PathBuf>,

    /// Write the scene back with every part's fitted state.
    #[arg(long, value_name = "FILE.dsq.ron", help_heading = "Scenes")]
    pub out_scene: Option<PathBuf>,
}

fn number(v: &str) -> Result<f64, String> {
    v.trim()
        .parse()
        .map_err(|_| format!("cannot read {v:?} as a number"))
}

fn non_negative(v: &str) -> Result<f64, String> {
    let x = number(v)?;
    if x.is_finite() && x >= 0.0 {
        Ok(x)
    } else {
        Err(format!("{x} must be a finite number ≥ 0"))
    }
}

/// `--parts`: `auto` or a count.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PartsArg {
    /// As many as the cloud's description length asks.
    Auto,
    /// Exactly this many.
    Count(usize),
}

fn parts_arg(v: &str) -> Result<PartsArg, String> {
    if v == "auto" {
        return Ok(PartsArg::Auto);
    }
    v.parse::<usize>()
        .map(PartsArg::Count)
        .map_err(|_| format!("{v:?} is neither `auto` nor a whole number of parts"))
}

fn positive(v: &str) -> Result<f64, String> {
    let x = number(v)?;
    if x.is_finite() && x > 0.0 {
        Ok(x)
    } else {
        Err(format!("{x} must be a finite number > 0"))
    }
}

fn fraction(v: &str) -> Result<f64, String> {
    let x = number(v)?;
    if (0.0..1.0).contains(&x) {
        Ok(x)
    } else {
        Err(format!("{x}: expected a fraction in [0, 1)"))
    }
}

fn w1(v: &str) -> Result<W1, String> {
    if v == "auto" {
        Ok(W1::Auto)
    } else {
        non_negative(v).map(W1::Value)
    }
}

fn part(v: &str) -> Result<[DVec2; 4], String> {
    let n: Vec<f64> = v
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("{v:?}: expected 8 numbers x0,y0,x1,y1,x2,y2,x3,y3 (pixels)"))?;
    if n.len() != 8 || !n.iter().all(|x| x.is_finite()) {
        return Err(format!(
            "{v:?}: expected 8 finite numbers x0,y0,x1,y1,x2,y2,x3,y3 (pixels)"
        ));
    }
    Ok([0, 2, 4, 6].map(|i| DVec2::new(n[i], n[i + 1])))
}

/// Where the data come from.
pub enum Source {
    /// A point file.
    File(PathBuf),
    /// Point files fitted side by side (several, or any with `--out-dir`).
    Files(Vec<PathBuf>),
    /// The paper's egg or mug range experiment.
    Paper(&'static str),
    /// An image, its parts placed by `--part` or found as blobs.
    Image(PathBuf),
    /// A scene file.
    Scene(PathBuf),
}

/// Image-fit settings.
pub struct ImageArgs {
    /// The fit's options.
    pub options: ImageFitOptions,
    /// Blur of the potential, pixels.
    pub sigma: f64,
    /// Parts placed by four points.
    pub parts: Vec<[DVec2; 4]>,
    /// Parts to place automatically (the largest blobs).
    pub auto_parts: usize,
    /// Where to draw the overlay.
    pub overlay: Option<PathBuf>,
}

impl Default for ImageArgs {
    /// The image fit's defaults: one part, the default potential width, no overlay.
    fn default() -> Self {
        Self {
            options: ImageFitOptions::default(),
            sigma: DEFAULT_SIGMA,
            parts: Vec::new(),
            auto_parts: 1,
            overlay: None,
        }
    }
}

/// A fit's resolved settings.
pub struct Args {
    /// The data.
    pub source: Source,
    /// The range fit's settings.
    pub options: FitOptions,
    /// The image fit's settings.
    pub image: ImageArgs,
    /// `--out-mesh`.
    pub out_mesh: Option<PathBuf>,
    /// `--out-params`.
    pub out_params: Option<PathBuf>,
    /// `--out-dir`.
    pub out_dir: Option<PathBuf>,
    /// `--quiet`.
    pub quiet: bool,
    /// `--app`.
    pub app: bool,
    /// `--out-scene`.
    pub out_scene: Option<PathBuf>,
    /// `--max-steps` as given (a scene caps each part with it).
    pub max_steps_override: Option<u32>,
    /// `--parts` on a cloud: how many parts to split it into (`None`: one).
    pub cloud_parts: Option<PartCount>,
    /// `--mesh-samples`: the points a mesh file is read as.
    pub mesh_samples: usize,
}

/// A paper experiment's settings: the point fit's options and points, or the image's.
struct PaperBase {
    options: FitOptions,
    points: Option<(&'static str, Vec<DVec3>)>,
    image: Option<(PathBuf, ImageArgs)>,
}

impl FitArgs {
    /// The fitter's settings, and the paper experiment's points for `--paper egg|mug`; an error
    /// names the option that is wrong or out of place.
    pub fn resolve(mut self) -> Result<(Args, Option<Vec<DVec3>>), String> {
        let base = self.paper_base()?;
        let k = match (self.nodes, self.k) {
            (Some(n), _) => Some(k_for_nodes(n)?),
            (None, k) => k.map(|k| k as usize),
        };
        let (image_path, mut image) = match base.image {
            Some((path, image)) => (Some(path), image),
            None => (self.image.take(), ImageArgs::default()),
        };
        image.overlay = self.out_overlay.take();
        let cloud_parts = match (self.parts, self.max_parts) {
            (Some(PartsArg::Count(0)), _) => {
                return Err("parts = 0 is out of range: it must be at least 1".into());
            }
            (_, Some(0)) => {
                return Err("max-parts = 0 is out of range: it must be at least 1".into());
            }
            (Some(PartsArg::Count(n)), None) => {
                image.auto_parts = n;
                (n > 1).then_some(PartCount::Exact(n))
            }
            (Some(PartsArg::Auto), cap) => Some(PartCount::Auto(cap.unwrap_or(DEFAULT_MAX_PARTS))),
            (_, Some(_)) => return Err("--max-parts caps --parts auto; give --parts auto".into()),
            (None, None) => None,
        };
        if !self.part.is_empty() {
            image.parts = std::mem::take(&mut self.part);
        }
        let source = self.source(base.points.as_ref().map(|p| p.0), image_path)?;
        let is_file = matches!(source, Source::File(_) | Source::Files(_));
        if matches!(source, Source::Image(_)) {
            (image.options, image.sigma) =
                self.image_choices(k).resolve(image.options, image.sigma)?;
        }
        if self.solver.is_some() && !is_file && !matches!(source, Source::Image(_)) {
            return Err("--solver acts on POINTS and image fits".into());
        }
        let options = self
            .cloud_options(k)
            .resolve(base.options, is_file)
            .map_err(|e| e.to_string())?;
        self.check_places(&source, &options)?;
        let args = Args {
            source,
            options,
            image,
            out_mesh: self.out_mesh,
            out_params: self.out_params,
            out_dir: self.out_dir,
            quiet: self.quiet,
            app: self.app,
            out_scene: self.out_scene,
            max_steps_override: self.max_steps,
            cloud_parts,
            mesh_samples: self.mesh_samples.unwrap_or(MESH_SAMPLES),
        };
        Ok((args, base.points.map(|(_, pts)| pts)))
    }

    /// The settings `--paper` starts from: an image experiment's image and parts, or a range
    /// experiment's points and options; the defaults without it.
    fn paper_base(&self) -> Result<PaperBase, String> {
        let mut base = PaperBase {
            options: FitOptions::default(),
            points: None,
            image: None,
        };
        match self.paper {
            Some(p @ (Paper::Pestle | Paper::Doll)) => {
                if self.image.is_some() {
                    return Err("give one of POINTS, --paper, --image or --scene".into());
                }
                let e = if p == Paper::Pestle {
                    pestle_experiment()
                } else {
                    doll_experiment()
                };
                let image = ImageArgs {
                    options: e.options,
                    sigma: e.sigma,
                    parts: e.parts.iter().map(|p| p.1).collect(),
                    ..ImageArgs::default()
                };
                let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(e.image);
                base.image = Some((path, image));
            }
            Some(p @ (Paper::Egg | Paper::Mug)) => {
                let ((pts, opts), name) = if p == Paper::Egg {
                    (synthetic::egg_experiment(), "egg")
                } else {
                    (synthetic::mug_experiment(), "mug")
                };
                base.points = Some((name, pts));
                base.options = opts;
            }
            None => {}
        }
        Ok(base)
    }

    /// The image fit's flags, tessellation `k`.
    fn image_choices(&self, k: Option<usize>) -> ImageChoices {
        ImageChoices {
            global_only: self.global_only,
            paper_band: self.paper_band,
            free_depth: self.free_depth,
            fix_epsilon: self.fix_epsilon,
            sigma: self.sigma,
            band: self.band,
            region: self.region,
            k,
            w0: self.w0,
            w1: match self.w1 {
                Some(W1::Value(w1)) => Some(w1),
                _ => None,
            },
            beta: self.beta,
            max_steps: self.max_steps.map(|n| n as usize),
            solver: self.solver.map(|s| match s {
                SolverArg::Solved => Solver::Solved,
                SolverArg::Dynamics => Solver::Dynamics,
            }),
        }
    }

    /// The point fit's flags, tessellation `k`.
    fn cloud_options(&self, k: Option<usize>) -> CloudOptions {
        CloudOptions {
            global_only: self.global_only,
            solver: self.solver.map(|s| match s {
                SolverArg::Solved => Solver::Solved,
                SolverArg::Dynamics => Solver::Dynamics,
            }),
            paper_forces: self.paper_forces,
            robust: self.robust,
            plane: self.plane,
            switch: self.switch,
            similar: self.similar,
            migrate: self.migrate,
            taper: self.taper,
            bend: self.bend,
            outliers: self.outliers,
            k,
            w0: self.w0,
            w1: self.w1.map(|w| match w {
                W1::Auto => Stiffness::FromNoise,
                W1::Value(v) => Stiffness::Value(v),
            }),
            beta: self.beta,
            max_steps: self.max_steps,
            reassign: self.reassign,
            implicit_local: self.implicit_local,
        }
    }

    /// The one input given: POINTS files, the paper experiment `paper`, an image or a scene.
    fn source(
        &mut self,
        paper: Option<&'static str>,
        image: Option<PathBuf>,
    ) -> Result<Source, String> {
        let points = &mut self.points;
        Ok(match (points.len(), paper, image, self.scene.take()) {
            (1, None, None, None) if self.out_dir.is_none() => Source::File(points.remove(0)),
            (1.., None, None, None) => Source::Files(std::mem::take(points)),
            (0, Some(name), None, None) => Source::Paper(name),
            (0, None, Some(p), None) => Source::Image(p),
            (0, None, None, Some(p)) => Source::Scene(p),
            (0, None, None, None) => {
                return Err("no POINTS file given (dsq fit --help lists the inputs)".into());
            }
            _ => return Err("give one of POINTS, --paper, --image or --scene".into()),
        })
    }

    /// Refuses a flag given where `source` cannot honour it.
    fn check_places(&self, source: &Source, options: &FitOptions) -> Result<(), String> {
        let is_file = matches!(source, Source::File(_) | Source::Files(_));
        let refused = |why: &str| Err(why.to_string());
        if let Some(n) = self.mesh_samples {
            if !is_file {
                return refused("--mesh-samples acts on POINTS files");
            }
            if !(1..=MAX_MESH_SAMPLES).contains(&n) {
                return Err(format!(
                    "mesh-samples = {n} is out of range [1, {MAX_MESH_SAMPLES}]"
                ));
            }
        }
        if let Source::Files(_) = source {
            if self.out_mesh.is_some() || self.out_params.is_some() {
                return refused(
                    "--out-mesh and --out-params write one fit; with several POINTS files give --out-dir",
                );
            }
            if self.app {
                return refused("--app fits one POINTS file at a time");
            }
            if self.parts.is_some_and(|p| p != PartsArg::Count(1)) {
                return refused("--parts splits one POINTS file at a time");
            }
        } else if self.out_dir.is_some() {
            return refused("--out-dir acts on POINTS files");
        }
        let image_or_scene = matches!(source, Source::Image(_) | Source::Scene(_));
        if self.paper_forces && !is_file {
            return refused(
                "--paper-forces acts on POINTS fits (--paper, --image and --scene keep their own settings)",
            );
        }
        let split = self.parts.is_some_and(|p| p != PartsArg::Count(1));
        if self.parts == Some(PartsArg::Auto) && image_or_scene {
            return refused("--parts auto splits a point cloud; an image takes a count of blobs");
        }
        if self.parts.is_some() && matches!(source, Source::Scene(_)) {
            return refused("--parts acts on a POINTS file or an image; a scene lists its parts");
        }
        if self.out_scene.is_some()
            && !(matches!(source, Source::Scene(_)) || (split && !image_or_scene))
        {
            return refused("--out-scene needs --scene, or --parts on a POINTS file");
        }
        if (self.taper || self.bend) && image_or_scene {
            return refused(
                "--taper and --bend act on point fits; a scene part frees them with free: (taper: true, bend: true)",
            );
        }
        if options.noise_stiffness != NoiseStiffness::Off && image_or_scene {
            return refused(
                "--w1 auto reads the noise of a point cloud; give w1 a number for images and scenes",
            );
        }
        if self.app && !cfg!(feature = "bevy") {
            return refused(
                "--app runs the fit through the Bevy plugin: build dsq with the `bevy` feature",
            );
        }
        Ok(())
    }
}
