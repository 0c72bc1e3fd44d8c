//! One part: its checks, and the dynamics, fit and image options its settings give.

use super::*;

impl PartDef {
    /// A part with no data and every setting at its default, a unit sphere at the origin.
    pub fn new(name: impl Into<String>) -> Self {
        Self {
            name: name.into(),
            placement: PartPlacement::Pose {
                translation: [0.0; 3],
                rotation: Rotation::default(),
                shape: SuperquadricParams::default(),
            },
            k: default_k(),
            w0: default_w0(),
            w1: default_w1(),
            stiffness_from_noise: false,
            damping: Damping::default(),
            dt: default_dt(),
            reassign_every: default_reassign(),
            free: Freedoms::default(),
            forces: Forces::Free,
            fit: FitSettings::default(),
            local: None,
            deformation: GlobalDeformation::IDENTITY,
            inertia: None,
        }
    }

    /// Tapering and bending within their bounds ([`GlobalDeformation::clamped`]); with a `Pose`
    /// placement the bend must also keep the shape's widest section on the near side of the
    /// centre of curvature.
    fn validate_deformation(
        &self,
        file: &Path,
        f: &dyn Fn(&str) -> String,
    ) -> Result<(), SceneError> {
        let d = &self.deformation;
        check_finite(file, &f("deformation.taper"), &d.taper)?;
        check_finite(file, &f("deformation.bend"), &d.bend)?;
        if d.taper.iter().any(|t| t.abs() > MAX_TAPER) {
            return Err(SceneError::at_field(
                file,
                f("deformation.taper"),
                format!(
                    "each of t_x, t_y must lie in [-{MAX_TAPER}, {MAX_TAPER}], found {:?}",
                    d.taper
                ),
            ));
        }
        let axes = match &self.placement {
            PartPlacement::Pose { shape, .. } => shape.semi_axes(),
            // The shape comes from the data: only the bend's own bound can be checked here.
            _ => DVec3::new(0.0, 0.0, f64::INFINITY),
        };
        let limit = d.clamped(axes).bend;
        if d.bend != limit {
            return Err(SceneError::at_field(
                file,
                f("deformation.bend"),
                format!(
                    "|b| = {} is beyond its bound {} (at most {MAX_BEND} rad, and at most \
                     {MAX_BEND_WIDTH} × the z semi-axis over the widest tapered section)",
                    d.bend[0].hypot(d.bend[1]),
                    limit[0].hypot(limit[1])
                ),
            ));
        }
        Ok(())
    }

    pub(super) fn validate(
        &self,
        file: &Path,
        at: &str,
        data: &BTreeMap<String, DataSource>,
    ) -> Result<(), SceneError> {
        let f = |name: &str| format!("{at}.{name}");
        match &self.placement {
            PartPlacement::Pose {
                translation,
                rotation,
                shape,
            } => {
                check_finite(file, &f("placement.translation"), translation)?;
                rotation
                    .to_quat()
                    .map_err(|m| SceneError::at_field(file, f("placement.rotation"), m))?;
                check(file, &f("placement.shape.a"), shape.a, 0.0, true)?;
                for (n, v) in [("a1", shape.a1), ("a2", shape.a2), ("a3", shape.a3)] {
                    check(file, &f(&format!("placement.shape.{n}")), v, 0.0, true)?;
                }
                for (n, v) in [("e1", shape.e1), ("e2", shape.e2)] {
                    if !(LEAST_EPSILON..=MAX_EPSILON).contains(&v) {
                        return Err(SceneError::at_field(
                            file,
                            f(&format!("placement.shape.{n}")),
                            format!("must lie in [{LEAST_EPSILON}, {MAX_EPSILON}], found {v}"),
                        ));
                    }
                }
            }
            PartPlacement::Axes { major, minor } => {
                check_finite(file, &f("placement.major"), major.as_flattened())?;
                check_finite(file, &f("placement.minor"), minor.as_flattened())?;
                if !matches!(self.forces, Forces::Image { .. }) {
                    return Err(SceneError::at_field(
                        file,
                        f("placement"),
                        "Axes places a part on its image: the part needs `forces: Image(..)`",
                    ));
                }
            }
            PartPlacement::Auto => {
                if !matches!(self.forces, Forces::Range { .. }) {
                    return Err(SceneError::at_field(
                        file,
                        f("placement"),
                        "Auto places a part on its range points: the part needs `forces: Range(..)`",
                    ));
                }
            }
        }
        self.validate_deformation(file, &f)?;
        if let Some(i) = &self.inertia {
            check(file, &f("inertia.mass_density"), i.mass_density, 0.0, true)?;
            check(
                file,
                &f("inertia.local_inertia"),
                i.local_inertia,
                0.0,
                true,
            )?;
            check(file, &f("inertia.damping"), i.damping, 0.0, false)?;
        }
        if !(MIN_K..=MAX_K).contains(&self.k) {
            return Err(SceneError::at_field(
                file,
                f("k"),
                format!(
                    "must lie in [{MIN_K}, {MAX_K}] (the largest takes about 1 GB), found {}",
                    self.k
                ),
            ));
        }
        check(file, &f("w0"), self.w0, 0.0, false)?;
        check(file, &f("w1"), self.w1, 0.0, false)?;
        if self.stiffness_from_noise && !matches!(self.forces, Forces::Range { .. }) {
            return Err(SceneError::at_field(
                file,
                f("stiffness_from_noise"),
                "the stiffness comes from the noise of the part's range points: the part needs \
                 `forces: Range(..)`",
            ));
        }
        check(file, &f("dt"), self.dt, 0.0, true)?;
        if let Some(g) = self.damping.global {
            check(file, &f("damping.global"), g, 0.0, true)?;
        }
        check(file, &f("damping.local"), self.damping.local, 0.0, true)?;
        if self.reassign_every == 0 {
            return Err(SceneError::at_field(
                file,
                f("reassign_every"),
                "must be at least 1, found 0",
            ));
        }
        let source = |name: &str| {
            data.get(name).ok_or_else(|| {
                let known: Vec<&str> = data.keys().map(String::as_str).collect();
                SceneError::at_field(
                    file,
                    f("forces.data"),
                    format!("no data source named {name:?} (the scene has {known:?})"),
                )
            })
        };
        match &self.forces {
            Forces::Free => {}
            Forces::Range {
                data: name,
                beta,
                coverage,
                influence,
                crop,
                outliers,
                shared,
            } => {
                if *shared && crop.is_some() {
                    return Err(SceneError::at_field(
                        file,
                        f("forces.crop"),
                        "a shared source is split among its parts by nearness; drop the crop or `shared`",
                    ));
                }
                if !(0.0..1.0).contains(outliers) {
                    return Err(SceneError::at_field(
                        file,
                        f("forces.outliers"),
                        format!("must lie in [0, 1), found {outliers}"),
                    ));
                }
                if matches!(source(name)?, DataSource::Image { .. }) {
                    return Err(SceneError::at_field(
                        file,
                        f("forces.data"),
                        format!("{name:?} is an image; Range forces need points"),
                    ));
                }
                check(file, &f("forces.beta"), *beta, 0.0, true)?;
                check(file, &f("forces.coverage"), *coverage, 0.0, false)?;
                if let InfluenceMode::Migrating { rate } = influence
                    && !(*rate > 0.0 && *rate <= 1.0)
                {
                    return Err(SceneError::at_field(
                        file,
                        f("forces.influence.rate"),
                        format!("must lie in (0, 1], found {rate}"),
                    ));
                }
                if let Some(b) = crop {
                    check_finite(file, &f("forces.crop"), &[b.min, b.max].concat())?;
                    if (0..3).any(|i| b.min[i] > b.max[i]) {
                        return Err(SceneError::at_field(
                            file,
                            f("forces.crop"),
                            "min must not exceed max",
                        ));
                    }
                }
            }
            Forces::Image {
                data: name,
                beta,
                band,
                region,
                ..
            } => {
                if !matches!(source(name)?, DataSource::Image { .. }) {
                    return Err(SceneError::at_field(
                        file,
                        f("forces.data"),
                        format!("{name:?} is not an image; Image forces need one"),
                    ));
                }
                check(file, &f("forces.beta"), *beta, 0.0, true)?;
                check(file, &f("forces.band"), *band, 0.0, true)?;
                check(file, &f("forces.region"), *region, 0.0, false)?;
            }
        }
        if let Some(t) = self.fit.tolerance {
            check(file, &f("fit.tolerance"), t, 0.0, true)?;
        }
        if self.fit.max_steps == Some(0) {
            return Err(SceneError::at_field(
                file,
                f("fit.max_steps"),
                "must be at least 1, found 0",
            ));
        }
        if let Some(local) = &self.local {
            let n = self.k * self.k + 2;
            if local.len() != n {
                return Err(SceneError::at_field(
                    file,
                    f("local"),
                    format!(
                        "has {} displacements; k = {} has {n} nodes",
                        local.len(),
                        self.k
                    ),
                ));
            }
            if let Some(i) = local.iter().position(|d| !d.iter().all(|x| x.is_finite())) {
                return Err(SceneError::at_field(
                    file,
                    format!("{at}.local[{i}]"),
                    "has a NaN or infinite component",
                ));
            }
        }
        Ok(())
    }

    /// True when the part is pulled by an image.
    pub fn on_image(&self) -> bool {
        matches!(self.forces, Forces::Image { .. })
    }

    /// Whether ε1, ε2 are held (false unless set).
    pub fn fix_epsilon(&self) -> bool {
        self.free.fix_epsilon.unwrap_or(false)
    }

    /// Whether the part moves in the image plane only (set, or by default on image parts).
    pub fn planar(&self) -> bool {
        self.free.planar.unwrap_or(self.on_image())
    }

    /// The part's dynamics parameters (stiffness, Δt, damping, free DOFs).
    pub fn dynamics(&self) -> DynamicsParams {
        let f = &self.free;
        let free = FreeDofs::with(!f.global_only, self.planar(), self.fix_epsilon())
            .beyond_the_paper(f.fix_shape, f.taper, f.bend);
        DynamicsParams {
            w0: self.w0,
            w1: self.w1,
            dt: self.dt,
            gamma_global: self.damping.global.unwrap_or(match self.forces {
                Forces::Range { .. } => FitOptions::default().dynamics.gamma_global,
                _ => DynamicsParams::default().gamma_global,
            }),
            gamma_local: self.damping.local,
            free,
            ..DynamicsParams::default()
        }
    }

    /// The options of a range fit of this part from `start` (in world space).
    pub fn fit_options(&self, start: &ModelState) -> FitOptions {
        self.fit_options_from(Initialization::Explicit(InitialPose::of(start)))
    }

    /// The options of a range fit of this part, started as `init` says.
    pub(super) fn fit_options_from(&self, init: Initialization) -> FitOptions {
        let defaults = FitOptions::default();
        let (beta, coverage, influence, outlier_ratio) = match &self.forces {
            Forces::Range {
                beta,
                coverage,
                influence,
                outliers,
                ..
            } => (*beta, *coverage, *influence, *outliers),
            _ => (
                defaults.beta,
                defaults.coverage,
                defaults.influence,
                defaults.outlier_ratio,
            ),
        };
        FitOptions {
            k: self.k,
            dynamics: self.dynamics(),
            beta,
            influence,
            coverage,
            outlier_ratio,
            reassign_every: self.reassign_every,
            max_steps: self.fit.max_steps.unwrap_or(defaults.max_steps),
            tolerance: self.fit.tolerance.unwrap_or(defaults.tolerance),
            global_first: self.fit.global_first,
            solver: self.fit.solver,
            global_only: self.free.global_only,
            init,
            ..defaults
        }
    }

    /// The options of an image fit of this part.
    pub fn image_options(&self) -> ImageFitOptions {
        let defaults = ImageFitOptions::default();
        let (beta, band, outline_only, region) = match &self.forces {
            Forces::Image {
                beta,
                band,
                outline_only,
                region,
                ..
            } => (*beta, *band, *outline_only, *region),
            _ => (
                defaults.beta,
                defaults.band,
                defaults.outline_only,
                defaults.region,
            ),
        };
        ImageFitOptions {
            k: self.k,
            // The fit sets the free DOFs per stage from `planar` and `fix_epsilon`.
            dynamics: DynamicsParams {
                free: FreeDofs::default(),
                ..self.dynamics()
            },
            beta,
            band,
            outline_only,
            region,
            planar: self.planar(),
            fix_epsilon: self.fix_epsilon(),
            global_first: self.fit.global_first,
            local: !self.free.global_only,
            tolerance: self.fit.tolerance.unwrap_or(defaults.tolerance),
            max_steps: self
                .fit
                .max_steps
                .map_or(defaults.max_steps, |m| m as usize),
            solver: self.fit.solver,
        }
    }
}
