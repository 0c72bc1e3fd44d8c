//! A scene as a whole: parsing and checking it, its shared sources, and writing it back.

use super::*;

impl SceneDef {
    /// Parses and checks a scene's text; `file` names it in errors.
    pub fn parse(text: &str, file: &Path) -> Result<Self, SceneError> {
        let options = ron::Options::default()
            .with_default_extension(ron::extensions::Extensions::IMPLICIT_SOME);
        let spanned = |e: ron::error::SpannedError, field: Option<String>| SceneError {
            file: file.to_path_buf(),
            position: Some((e.span.start.line, e.span.start.col)),
            field,
            message: e.code.to_string(),
        };
        let mut de = ron::Deserializer::from_str_with_options(text, &options)
            .map_err(|e| spanned(e, None))?;
        let def: SceneDef = match serde_path_to_error::deserialize(&mut de) {
            Ok(def) => def,
            Err(e) => {
                let path = e.path().to_string();
                let field = (path != ".").then_some(path);
                let code = e.into_inner();
                return Err(spanned(de.span_error(code), field));
            }
        };
        de.end()
            .map_err(|code| spanned(de.span_error(code), None))?;
        def.validate(file)?;
        Ok(def)
    }

    /// Checks every value and reference, naming the first bad field.
    pub fn validate(&self, file: &Path) -> Result<(), SceneError> {
        for (name, source) in &self.data {
            let at = |f: &str| format!("data.{name}.{f}");
            match source {
                DataSource::Points { path, placement } => {
                    if path.trim().is_empty() {
                        return Err(SceneError::at_field(file, at("path"), "is empty"));
                    }
                    check_finite(file, &at("placement.translation"), &placement.translation)?;
                    check(file, &at("placement.scale"), placement.scale, 0.0, true)?;
                    placement
                        .rotation
                        .to_quat()
                        .map_err(|m| SceneError::at_field(file, at("placement.rotation"), m))?;
                }
                DataSource::Generated(_) => {}
                DataSource::Image {
                    path,
                    sigma,
                    center,
                    extent,
                } => {
                    if path.trim().is_empty() {
                        return Err(SceneError::at_field(file, at("path"), "is empty"));
                    }
                    check(file, &at("sigma"), *sigma, 0.0, true)?;
                    check_finite(file, &at("center"), center)?;
                    check(file, &at("extent"), *extent, 0.0, true)?;
                }
            }
        }
        for (i, part) in self.parts.iter().enumerate() {
            part.validate(file, &format!("parts[{i}]"), &self.data)?;
            if part.fit.solver != Solver::Solved && matches!(part.forces, Forces::Free) {
                return Err(SceneError::at_field(
                    file,
                    format!("parts[{i}].fit.solver"),
                    "chooses how a fit to data comes to rest; this part has no data",
                ));
            }
        }
        for (i, joint) in self.joints.iter().enumerate() {
            let at = |f: &str| format!("joints[{i}].{f}");
            let [a, b] = joint.parts;
            if a == b || a >= self.parts.len() || b >= self.parts.len() {
                return Err(SceneError::at_field(
                    file,
                    at("parts"),
                    format!(
                        "must name two different parts of the {} in `parts`, found ({a}, {b})",
                        self.parts.len()
                    ),
                ));
            }
            for (k, end) in joint.ends.iter().enumerate() {
                if !(end.u.is_finite()
                    && end.v.is_finite()
                    && end.u.abs() <= std::f64::consts::FRAC_PI_2)
                {
                    return Err(SceneError::at_field(
                        file,
                        at(&format!("ends[{k}]")),
                        format!(
                            "u must lie in [-π/2, π/2] and v be finite, found ({}, {})",
                            end.u, end.v
                        ),
                    ));
                }
            }
            check(file, &at("stiffness"), joint.stiffness, 0.0, true)?;
        }
        for (source, group) in self.shared_groups() {
            let auto = |&i: &usize| matches!(self.parts[i].placement, PartPlacement::Auto);
            if group.iter().any(auto) && !group.iter().all(auto) {
                let odd = group.iter().find(|i| !auto(i)).copied().unwrap_or(group[0]);
                return Err(SceneError::at_field(
                    file,
                    format!("parts[{odd}].placement"),
                    format!(
                        "the parts sharing {source:?} ({group:?}) must all be placed Auto or all explicitly"
                    ),
                ));
            }
        }
        if let Some(c) = &self.camera {
            check_finite(file, "camera.eye", &c.eye)?;
            check_finite(file, "camera.target", &c.target)?;
            check_finite(file, "camera.up", &c.up)?;
            let (eye, target, up) = (
                DVec3::from_array(c.eye),
                DVec3::from_array(c.target),
                DVec3::from_array(c.up),
            );
            if !((target - eye).length() > 1e-12) || !((target - eye).cross(up).length() > 1e-12) {
                return Err(SceneError::at_field(
                    file,
                    "camera",
                    "eye and target must differ, and up must not lie along the view",
                ));
            }
        }
        Ok(())
    }

    /// The parts that share each source (`Range(shared: true)`), by source name, in part order.
    pub fn shared_groups(&self) -> BTreeMap<&str, Vec<usize>> {
        let mut groups: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
        for (i, part) in self.parts.iter().enumerate() {
            if let Forces::Range {
                data, shared: true, ..
            } = &part.forces
            {
                groups.entry(data.as_str()).or_default().push(i);
            }
        }
        groups
    }

    /// The scene as RON text, every field written (what [`SceneDef::parse`] reads back to the same
    /// value, bit for bit: numbers are written in their shortest round-tripping form).
    pub fn to_ron(&self) -> Result<String, ron::Error> {
        let config = ron::ser::PrettyConfig::new()
            .extensions(ron::extensions::Extensions::IMPLICIT_SOME)
            .struct_names(false);
        ron::Options::default().to_string_pretty(self, config)
    }

    /// Records `state` as part `index`'s placement (pose and global shape) and, when
    /// `include_local`, its local displacements (otherwise they are dropped).
    pub fn set_state(&mut self, index: usize, state: &ModelState, include_local: bool) {
        let Some(part) = self.parts.get_mut(index) else {
            return;
        };
        part.placement = PartPlacement::Pose {
            translation: state.translation.to_array(),
            rotation: Rotation::from_quat(state.rotation),
            shape: state.shape,
        };
        part.deformation = state.deformation;
        part.local = (include_local && !state.displacement.is_empty())
            .then(|| state.displacement.iter().map(|d| d.to_array()).collect());
    }

    /// Rewrites the relative data paths of a scene read from directory `from` so that they point
    /// at the same files from directory `to` (where the scene is about to be written).
    pub fn rebase(&mut self, from: &Path, to: &Path) {
        for source in self.data.values_mut() {
            if let DataSource::Points { path, .. } | DataSource::Image { path, .. } = source
                && Path::new(path.as_str()).is_relative()
            {
                let target = lexical_absolute(&from.join(path.as_str()));
                *path = relative_path(&target, &lexical_absolute(to))
                    .to_string_lossy()
                    .replace('\\', "/");
            }
        }
    }

    /// Sets `w0` and `w1` of every part whose stiffness comes from its data's noise
    /// ([`PartDef::stiffness_from_noise`]) from the estimate in `data` (made by
    /// [`SceneData::resolve`]). [`SceneDef::load_file`] and the asset loader do this.
    pub fn apply_noise_stiffness(&mut self, data: &SceneData) {
        for (&i, noise) in &data.noise {
            if let Some(part) = self.parts.get_mut(i)
                && part.stiffness_from_noise
            {
                (part.w0, part.w1) = stiffness_for_noise(noise.relative);
            }
        }
    }

    /// Reads and checks a scene file, loads its data from the files next to it and sets the
    /// stiffness of parts that take it from their data's noise.
    pub fn load_file(file: &Path) -> Result<(SceneDef, SceneData), SceneError> {
        let text = std::fs::read_to_string(file).map_err(|e| SceneError {
            file: file.to_path_buf(),
            position: None,
            field: None,
            message: format!("cannot read: {e}"),
        })?;
        let mut def = SceneDef::parse(&text, file)?;
        let dir = file.parent().unwrap_or(Path::new("")).to_path_buf();
        let data = SceneData::resolve(&def, file, |rel| {
            std::fs::read(dir.join(rel)).map_err(|e| format!("cannot read {rel:?}: {e}"))
        })?;
        def.apply_noise_stiffness(&data);
        Ok((def, data))
    }

    /// Writes the scene to `file` (see [`SceneDef::to_ron`]).
    pub fn save(&self, file: &Path) -> Result<(), SceneError> {
        let fail = |message: String| SceneError {
            file: file.to_path_buf(),
            position: None,
            field: None,
            message,
        };
        let text = self
            .to_ron()
            .map_err(|e| fail(format!("cannot write the scene as RON: {e}")))?;
        std::fs::write(file, text).map_err(|e| fail(format!("cannot write: {e}")))
    }

    /// The relative paths of the files the scene's data come from, by source name.
    pub fn data_files(&self) -> Vec<(&str, &str)> {
        self.data
            .iter()
            .filter_map(|(name, s)| match s {
                DataSource::Points { path, .. } | DataSource::Image { path, .. } => {
                    Some((name.as_str(), path.as_str()))
                }
                DataSource::Generated(_) => None,
            })
            .collect()
    }
}

/// `p` made absolute against the working directory, with `.` and `..` resolved lexically.
pub(super) fn lexical_absolute(p: &Path) -> PathBuf {
    let joined = if p.is_absolute() {
        p.to_path_buf()
    } else {
        std::env::current_dir().unwrap_or_default().join(p)
    };
    let mut out = PathBuf::new();
    for c in joined.components() {
        match c {
            Component::ParentDir => {
                out.pop();
            }
            Component::CurDir => {}
            c => out.push(c),
        }
    }
    out
}

/// The path from directory `base` to `target` (both absolute and lexically normal).
pub(crate) fn relative_path(target: &Path, base: &Path) -> PathBuf {
    let t: Vec<_> = target.components().collect();
    let b: Vec<_> = base.components().collect();
    let common = t.iter().zip(&b).take_while(|(x, y)| x == y).count();
    let mut out = PathBuf::new();
    for _ in common..b.len() {
        out.push("..");
    }
    for c in &t[common..] {
        out.push(c);
    }
    out
}
