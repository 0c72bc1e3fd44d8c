//! [`FitDriver`]: a whole fit of a model's range data, or of its image, run in the background and
//! written into the model's components.
//!
//! The fit is the core's, [`crate::model::fit::fit_watched`] for range data, the same plan
//! `dsq fit` runs, and [`crate::model::image_fit::fit_part`] solved for its rest for an image: a
//! fit through the plugin ends in the same state, bit for bit. It runs on Bevy's
//! [`AsyncComputeTaskPool`], so a long fit never holds up a frame; while it runs, the state it
//! has reached (the chosen superquadric) is written into the model as it arrives, and when it
//! ends the fitted state, on the tessellation it ended on. The model is paused as soon as the
//! driver is inserted (the fit, not the per-frame simulation, moves it) and stays paused at the
//! fitted rest.
//! Removing the driver abandons the fit: the model keeps the state last written.

use super::components::{
    FemMesh, GlobalShape, ImageData, LocalDofs, ModelSettings, RangeData, RigidState, SimControl,
    model_state,
};
use crate::model::dynamics::ModelState;
use crate::model::fem::Tessellation;
use crate::model::fit::{
    CloudOptions, FitError, FitOptions, FitProgress, FitReport, Solver, fit_watched,
};
use crate::model::image_fit::{ImageFitOptions, ImagePartFit, fit_part};
use bevy::prelude::*;
use bevy::tasks::{AsyncComputeTaskPool, Task, block_on, poll_once};
use std::sync::{Arc, Mutex};

/// A fit to convergence of the model's [`RangeData`] with [`FitOptions`]: insert it on a model
/// with range data and the fit starts at the next run of the plugin's schedule, from the options'
/// initialisation (the data's moments by default, so it does not depend on where the model has
/// been). On a model with [`ImageData`] instead, the image fit solved for its rest
/// ([`fit_part`] with [`Solver::Solved`]) runs from where the model is, on its tessellation, a
/// pure superquadric when the options say `global_only`. [`FitFinished`](super::FitFinished) is
/// sent when it ends. Every option means what it means for [`crate::model::fit::fit`]; a model
/// with neither gets the error "no range or image data" ([`FitDriver::error`]).
#[derive(Component)]
#[component(on_insert = pause_for_the_fit)]
pub struct FitDriver {
    options: FitOptions,
    run: Run,
}

/// Where a driver's fit is.
enum Run {
    /// Not started yet.
    Waiting,
    /// Running: the task, and the latest state and progress it has handed over.
    Running {
        task: Task<Result<Fitted, FitError>>,
        latest: Arc<Mutex<Latest>>,
    },
    /// Ended: the fit, or why it failed.
    Ended(Box<Result<Fitted, FitError>>),
}

/// What a driver's fit gave.
enum Fitted {
    /// A range fit's report.
    Range(Box<FitReport>),
    /// An image part's fit, on a tessellation with this k.
    Image(Box<ImagePartFit>, usize),
}

/// What a running fit has handed over and the app has not read yet.
#[derive(Default)]
struct Latest {
    state: Option<(usize, ModelState)>,
    progress: Option<FitProgress>,
}

impl FitDriver {
    /// A fit to convergence with `options` (see the type's docs).
    pub fn new(options: FitOptions) -> Self {
        Self {
            options,
            run: Run::Waiting,
        }
    }

    /// [`FitDriver::new`].
    pub fn to_convergence(options: FitOptions) -> Self {
        Self::new(options)
    }

    /// The fit `dsq fit` runs on a user's cloud ([`CloudOptions`] resolved for a cloud: the
    /// membrane's stiffness chosen from the cloud's noise when the fit starts), with what the
    /// model's `settings` free: a pure superquadric when they say `global_only`, tapering and
    /// bending when they free them. The inspector's and the sandbox's fit to convergence.
    pub fn for_model(settings: &ModelSettings) -> Self {
        let cloud = CloudOptions {
            global_only: settings.global_only,
            taper: settings.taper,
            bend: settings.bend,
            ..CloudOptions::default()
        };
        // Switches alone cannot be out of range: the defaults stand in for an impossible error.
        Self::new(
            cloud
                .resolve(FitOptions::default(), true)
                .unwrap_or_default(),
        )
    }

    /// The fit's options.
    pub fn options(&self) -> &FitOptions {
        &self.options
    }

    /// True when the fit has ended (at rest, at its step cap, or with an error).
    pub fn is_done(&self) -> bool {
        matches!(self.run, Run::Ended(_))
    }

    /// True when the fit ended at rest.
    pub fn converged(&self) -> bool {
        match self.fitted() {
            Some(Fitted::Range(r)) => r.converged,
            Some(Fitted::Image(f, _)) => f.converged,
            None => false,
        }
    }

    /// Steps (or solver iterations) the ended fit took; 0 before it ends or when it failed.
    pub fn steps(&self) -> u64 {
        match self.fitted() {
            Some(Fitted::Range(r)) => r.steps as u64,
            Some(Fitted::Image(f, _)) => f.steps as u64,
            None => 0,
        }
    }

    fn fitted(&self) -> Option<&Fitted> {
        match &self.run {
            Run::Ended(outcome) => outcome.as_ref().as_ref().ok(),
            _ => None,
        }
    }

    /// The range fit's report, once it has ended without an error.
    pub fn report(&self) -> Option<&FitReport> {
        match self.fitted() {
            Some(Fitted::Range(r)) => Some(r),
            _ => None,
        }
    }

    /// The image fit, once it has ended without an error.
    pub fn image_fit(&self) -> Option<&ImagePartFit> {
        match self.fitted() {
            Some(Fitted::Image(f, _)) => Some(f),
            _ => None,
        }
    }

    /// Why the fit failed, when it did.
    pub fn error(&self) -> Option<&FitError> {
        match &self.run {
            Run::Ended(outcome) => outcome.as_ref().as_ref().err(),
            _ => None,
        }
    }

    /// The last progress the running fit reported.
    pub fn progress(&self) -> Option<FitProgress> {
        match &self.run {
            Run::Running { latest, .. } => lock(latest).progress,
            _ => None,
        }
    }
}

/// A model gets a [`FitDriver`]: it is paused at once, so that the per-frame simulation takes no
/// step of its own before the fit moves it.
fn pause_for_the_fit(
    mut world: bevy::ecs::world::DeferredWorld,
    context: bevy::ecs::lifecycle::HookContext,
) {
    if let Some(mut control) = world.get_mut::<SimControl>(context.entity) {
        control.paused = true;
    }
}

/// The lock of `latest`, whether or not a fit thread panicked while holding it.
fn lock(latest: &Mutex<Latest>) -> std::sync::MutexGuard<'_, Latest> {
    latest.lock().unwrap_or_else(|e| e.into_inner())
}

/// Writes `state`, on a tessellation with `k`, into a model's components.
fn write_state(
    (rigid, shape, local, fem): (
        &mut RigidState,
        &mut GlobalShape,
        &mut LocalDofs,
        &mut FemMesh,
    ),
    k: usize,
    state: &ModelState,
) {
    *rigid = RigidState {
        translation: state.translation,
        rotation: state.rotation,
    };
    *shape = GlobalShape::new(state.shape, state.deformation);
    local.displacement.clone_from(&state.displacement);
    if fem.k != k {
        // The plugin re-tessellates at its next step; the displacements are already the new
        // mesh's, so nothing is carried over.
        fem.k = k;
    }
}

/// Stage `Converge`: starts the fits of new drivers on the async compute pool (pausing their
/// models), writes what running fits have handed over into their models, and ends the fits whose
/// task is done, writing the fitted state.
pub(crate) fn drive_fits(
    mut models: Query<(
        &mut FitDriver,
        (Option<&RangeData>, Option<&ImageData>),
        &mut SimControl,
        &mut RigidState,
        &mut GlobalShape,
        &mut LocalDofs,
        &mut FemMesh,
    )>,
) {
    for (mut driver, (range, image), mut control, mut rigid, mut shape, mut local, mut fem) in
        &mut models
    {
        let driver = &mut *driver;
        match &mut driver.run {
            Run::Waiting => {
                control.paused = true;
                let latest = Arc::new(Mutex::new(Latest::default()));
                let shared = latest.clone();
                let options = driver.options;
                let task = if let Some(range) = range {
                    let points = range.forces.points().to_vec();
                    AsyncComputeTaskPool::get().spawn(async move {
                        let progress = |p: &FitProgress| lock(&shared).progress = Some(*p);
                        let watch = |tess: &Tessellation, state: &ModelState| {
                            lock(&shared).state = Some((tess.k, state.clone()));
                        };
                        fit_watched(&points, &options, progress, watch)
                            .map(|r| Fitted::Range(Box::new(r)))
                    })
                } else if let Some(image) = image {
                    let forces = image.forces.clone();
                    let start = model_state(&rigid, &shape, &local);
                    let opts = ImageFitOptions {
                        k: fem.k,
                        local: !options.global_only,
                        solver: Solver::Solved,
                        ..ImageFitOptions::default()
                    };
                    AsyncComputeTaskPool::get().spawn(async move {
                        let tess = Tessellation::new(opts.k);
                        fit_part(&tess, &forces, start, &opts)
                            .map(|f| Fitted::Image(Box::new(f), opts.k))
                            .map_err(FitError::Step)
                    })
                } else {
                    let error = FitError::BadOption("no range or image data to fit".into());
                    driver.run = Run::Ended(Box::new(Err(error)));
                    continue;
                };
                driver.run = Run::Running { task, latest };
            }
            Run::Running { task, latest } => {
                if let Some((k, state)) = lock(latest).state.take() {
                    write_state((&mut rigid, &mut shape, &mut local, &mut fem), k, &state);
                }
                if let Some(outcome) = block_on(poll_once(task)) {
                    let fitted = match &outcome {
                        Ok(Fitted::Range(report)) => Some((report.tess.k, &report.state)),
                        Ok(Fitted::Image(fit, k)) => Some((*k, &fit.state)),
                        Err(_) => None,
                    };
                    if let Some((k, state)) = fitted {
                        write_state((&mut rigid, &mut shape, &mut local, &mut fem), k, state);
                    }
                    driver.run = Run::Ended(Box::new(outcome));
                    control.paused = true;
                }
            }
            Run::Ended(_) => {}
        }
    }
}
