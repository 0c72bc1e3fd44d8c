//! Loading a scene's data (point files, generated clouds, images, the split of shared sources)
//! and running its parts to rest.

use super::*;

/// A scene's data, loaded: point clouds (placed in the world) and image potentials, by source
/// name. Cheap to clone (shared).
#[derive(Clone, Debug, Default)]
pub struct SceneData {
    /// World points of every point source.
    pub points: HashMap<String, Arc<Vec<DVec3>>>,
    /// The potential of every image source.
    pub images: HashMap<String, Arc<ImagePotential>>,
    /// How each source shared by two or more parts was split among them, by source name.
    pub splits: HashMap<String, Split>,
    /// The noise of the range points of each part whose stiffness comes from it
    /// ([`PartDef::stiffness_from_noise`]), by part index.
    pub noise: HashMap<usize, NoiseEstimate>,
}

/// How a shared source's points were split among its parts ([`crate::model::parts::partition`]).
#[derive(Clone, Debug)]
pub struct Split {
    /// The scene index of the part each of the source's points pulls on.
    pub owner: Arc<Vec<usize>>,
    /// Rounds of fit-then-reassign taken.
    pub rounds: u32,
    /// True when the last round moved no point.
    pub stable: bool,
    /// How many points the last round moved to another part.
    pub moved: usize,
}

impl SceneData {
    /// Loads every data source of `def`; `read` returns the bytes of a path relative to the scene
    /// (`file`, which names the scene in errors).
    pub fn resolve(
        def: &SceneDef,
        file: &Path,
        mut read: impl FnMut(&str) -> Result<Vec<u8>, String>,
    ) -> Result<Self, SceneError> {
        let mut out = SceneData::default();
        for (name, source) in &def.data {
            let at = format!("data.{name}.path");
            match source {
                DataSource::Points { path, placement } => {
                    let bytes = read(path).map_err(|m| SceneError::at_field(file, &at, m))?;
                    let raw = decode_points(Path::new(path), &bytes)
                        .map_err(|e| SceneError::at_field(file, &at, e.to_string()))?;
                    let placed = raw.iter().map(|p| placement.place(*p)).collect();
                    out.points.insert(name.clone(), Arc::new(placed));
                }
                DataSource::Generated(g) => {
                    let pts = match g {
                        Generated::Egg => crate::synthetic::egg(),
                        Generated::Mug => crate::synthetic::mug(),
                        Generated::Banana => {
                            crate::synthetic::Banana::default().points(2000, 0.002, 7)
                        }
                    };
                    out.points.insert(name.clone(), Arc::new(pts));
                }
                DataSource::Image {
                    path,
                    sigma,
                    center,
                    extent,
                } => {
                    let bytes = read(path).map_err(|m| SceneError::at_field(file, &at, m))?;
                    let (w, h, lum, rgb) = decode_image(Path::new(path), &bytes)
                        .map_err(|e| SceneError::at_field(file, &at, e.to_string()))?;
                    let frame = ImageFrame {
                        center: DVec2::from_array(*center),
                        extent: *extent,
                    };
                    let potential = ImagePotential::new(w, h, lum, *sigma, frame)
                        .and_then(|p| p.with_colour(rgb))
                        .map_err(|e| SceneError::at_field(file, &at, format!("{path}: {e}")))?;
                    out.images.insert(name.clone(), Arc::new(potential));
                }
            }
        }
        for (source, group) in def.shared_groups() {
            if group.len() < 2 {
                continue;
            }
            let split = out.split(def, source, &group).map_err(|m| {
                SceneError::at_field(file, format!("parts[{}].forces", group[0]), m)
            })?;
            out.splits.insert(source.to_string(), split);
        }
        for (i, part) in def.parts.iter().enumerate() {
            if let Forces::Range { .. } = part.forces {
                let points = out.range_points(def, i).unwrap_or_default();
                let n = points.len();
                if n < crate::model::fit::MIN_POINTS {
                    return Err(SceneError::at_field(
                        file,
                        format!("parts[{i}].forces"),
                        format!(
                            "{n} data points act on this part (after any crop); a fit needs at least {}",
                            crate::model::fit::MIN_POINTS
                        ),
                    ));
                }
                if part.stiffness_from_noise {
                    let noise = estimate_noise(&points).ok_or_else(|| {
                        SceneError::at_field(
                            file,
                            format!("parts[{i}].stiffness_from_noise"),
                            format!(
                                "cannot estimate the noise of the part's {n} data points (it needs \
                                 at least {NOISE_NEIGHBOURS} points spread in space)"
                            ),
                        )
                    })?;
                    out.noise.insert(i, noise);
                }
            }
        }
        Ok(out)
    }

    /// Splits the points of `source` among the parts `group` (scene indices) that share it.
    fn split(&self, def: &SceneDef, source: &str, group: &[usize]) -> Result<Split, String> {
        let points = self
            .points
            .get(source)
            .ok_or_else(|| format!("the data {source:?} are not loaded"))?;
        let opts: Vec<FitOptions> = group
            .iter()
            .map(|&i| {
                let part = &def.parts[i];
                let placed = match part.placement {
                    PartPlacement::Auto => None,
                    _ => self.initial_state(def, i),
                };
                let init = placed.map_or(Initialization::Moments, |s| {
                    Initialization::Explicit(InitialPose::of(&s))
                });
                part.fit_options_from(init)
            })
            .collect();
        let p = partition(points, &opts, PARTITION_ROUNDS)
            .map_err(|e| format!("splitting {source:?} among parts {group:?}: {e}"))?;
        Ok(Split {
            owner: Arc::new(p.owner.iter().map(|&j| group[j]).collect()),
            rounds: p.rounds,
            stable: p.stable,
            moved: p.moved,
        })
    }

    /// The world points that pull on part `index`, if it has range forces: its source's points
    /// inside its crop box, or, from a shared source, the points the split gave it.
    pub fn range_points(&self, def: &SceneDef, index: usize) -> Option<Vec<DVec3>> {
        let Forces::Range {
            data, crop, shared, ..
        } = &def.parts.get(index)?.forces
        else {
            return None;
        };
        let pts = self.points.get(data)?;
        Some(match (crop, self.splits.get(data)) {
            (_, Some(split)) if *shared => pts
                .iter()
                .zip(split.owner.iter())
                .filter(|(_, o)| **o == index)
                .map(|(p, _)| *p)
                .collect(),
            (Some(b), _) => pts.iter().copied().filter(|p| b.contains(*p)).collect(),
            _ => pts.to_vec(),
        })
    }

    /// The image forces on `part`, if it has image forces.
    pub fn image_forces(&self, part: &PartDef) -> Option<ImageForces> {
        let Forces::Image { data, .. } = &part.forces else {
            return None;
        };
        Some(part.image_options().forces(self.images.get(data)?.clone()))
    }

    /// Part `index`'s state as the scene places it: pose, global shape and local displacements
    /// (zero when the scene gives none).
    pub fn initial_state(&self, def: &SceneDef, index: usize) -> Option<ModelState> {
        let part = def.parts.get(index)?;
        let tess_nodes = part.k * part.k + 2;
        let mut state = match part.placement {
            PartPlacement::Pose {
                translation,
                rotation,
                shape,
            } => ModelState {
                translation: DVec3::from_array(translation),
                rotation: rotation.to_quat().ok()?,
                shape,
                deformation: part.deformation,
                displacement: vec![DVec3::ZERO; tess_nodes],
            },
            PartPlacement::Axes { major, minor } => {
                let Forces::Image { data, .. } = &part.forces else {
                    return None;
                };
                let potential = self.images.get(data)?;
                let pts = [major[0], major[1], minor[0], minor[1]].map(DVec2::from_array);
                let (translation, rotation, shape) =
                    PartAxes::from_points(potential, pts).ok()?.pose();
                ModelState {
                    translation,
                    rotation,
                    shape,
                    deformation: part.deformation,
                    displacement: vec![DVec3::ZERO; tess_nodes],
                }
            }
            PartPlacement::Auto => {
                let pose = initial_pose(&self.range_points(def, index)?);
                ModelState {
                    translation: pose.translation,
                    rotation: pose.rotation,
                    shape: pose.shape,
                    deformation: part.deformation,
                    displacement: vec![DVec3::ZERO; tess_nodes],
                }
            }
        };
        if let Some(local) = &part.local {
            state.displacement = local.iter().map(|d| DVec3::from_array(*d)).collect();
        }
        Some(state)
    }
}

/// What running a part to rest gave.
#[derive(Clone, Debug)]
pub enum PartRun {
    /// A range fit (see [`fit`]).
    Range(Box<FitReport>),
    /// An image fit (see [`fit_part`]).
    Image(ImagePartFit),
    /// A part with no data: nothing moves it without a user.
    Free(ModelState),
}

impl PartRun {
    /// The part's state at the end.
    pub fn state(&self) -> &ModelState {
        match self {
            PartRun::Range(r) => &r.state,
            PartRun::Image(f) => &f.state,
            PartRun::Free(s) => s,
        }
    }
}

/// Runs part `index` of a loaded scene to rest (or its step cap), without a window: range parts
/// through [`fit`] from the scene's placement (the local displacements start at zero), image parts
/// through [`fit_part`] from their placement and displacements. `max_steps` overrides the part's cap.
pub fn run_part(
    def: &SceneDef,
    data: &SceneData,
    index: usize,
    max_steps: Option<u32>,
) -> Result<PartRun, String> {
    let part = def
        .parts
        .get(index)
        .ok_or_else(|| format!("the scene has no part {index}"))?;
    let state = data
        .initial_state(def, index)
        .ok_or_else(|| format!("parts[{index}]: cannot place the part"))?;
    match &part.forces {
        Forces::Free => Ok(PartRun::Free(state)),
        Forces::Range { .. } => {
            let points = data
                .range_points(def, index)
                .ok_or_else(|| format!("parts[{index}]: its data are not loaded"))?;
            let mut opts = part.fit_options(&state);
            if let Some(m) = max_steps {
                opts.max_steps = m;
            }
            let report = fit(&points, &opts, |_| {})
                .map_err(|e: FitError| format!("parts[{index}]: {e}"))?;
            Ok(PartRun::Range(Box::new(report)))
        }
        Forces::Image { .. } => {
            let forces = data
                .image_forces(part)
                .ok_or_else(|| format!("parts[{index}]: its image is not loaded"))?;
            let mut opts = part.image_options();
            if let Some(m) = max_steps {
                opts.max_steps = m as usize;
            }
            let tess = Tessellation::new(part.k);
            let fitted = fit_part(&tess, &forces, state, &opts)
                .map_err(|e: StepError| format!("parts[{index}]: {e}"))?;
            Ok(PartRun::Image(fitted))
        }
    }
}

/// Runs every part of a scene (in parallel threads), in order. Image parts solved for their rest
/// on one image with the same options are solved together
/// ([`fit_parts_together`](crate::model::image_fit::fit_parts_together)): what one covers, the
/// others neither gain nor lose.
pub fn run_scene(
    def: &SceneDef,
    data: &SceneData,
    max_steps: Option<u32>,
) -> Vec<Result<PartRun, String>> {
    let mut groups: Vec<(&str, ImageFitOptions, Vec<usize>)> = Vec::new();
    for (i, part) in def.parts.iter().enumerate() {
        let Forces::Image { data: image, .. } = &part.forces else {
            continue;
        };
        let opts = part.image_options();
        if opts.solver != Solver::Solved {
            continue;
        }
        match groups
            .iter_mut()
            .find(|(d, o, _)| *d == image.as_str() && *o == opts)
        {
            Some((_, _, members)) => members.push(i),
            None => groups.push((image.as_str(), opts, vec![i])),
        }
    }
    groups.retain(|(_, _, members)| members.len() > 1);
    let together: Vec<usize> = groups.iter().flat_map(|g| g.2.iter().copied()).collect();
    let mut runs: Vec<Option<Result<PartRun, String>>> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..def.parts.len())
            .map(|i| {
                (!together.contains(&i))
                    .then(|| scope.spawn(move || run_part(def, data, i, max_steps)))
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.map(|h| {
                    h.join()
                        .unwrap_or_else(|_| Err("the part's thread panicked".into()))
                })
            })
            .collect()
    });
    for (image, opts, members) in &groups {
        let Some(potential) = data.images.get(*image) else {
            for &i in members {
                runs[i] = Some(Err(format!("parts[{i}]: its image is not loaded")));
            }
            continue;
        };
        let states: Option<Vec<ModelState>> = members
            .iter()
            .map(|&i| data.initial_state(def, i))
            .collect();
        let Some(states) = states else {
            for &i in members {
                runs[i] = Some(Err(format!("parts[{i}]: cannot place the part")));
            }
            continue;
        };
        let tess = Tessellation::new(opts.k);
        let fits = crate::model::image_fit::fit_parts_together(&tess, potential, &states, opts);
        for (&i, fit) in members.iter().zip(fits) {
            runs[i] = Some(Ok(PartRun::Image(fit)));
        }
    }
    runs.into_iter()
        .map(|r| r.unwrap_or_else(|| Err("the part was not run".into())))
        .collect()
}
