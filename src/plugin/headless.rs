//! Fitting through the plugin in a headless app (`MinimalPlugins`): the command-line fitter's
//! `--app` mode. One model with the points as its [`RangeData`] and a [`FitDriver`], updated until
//! the driver is done; the report is the driver's with the state read back from the model's
//! components, so what `dsq fit --app` writes is what the plugin wrote into the model.

use super::{
    DeformableSqPlugin, FemMesh, FitDriver, GlobalShape, LocalDofs, RangeData, RigidState,
    model_state,
};
use crate::model::fem::Tessellation;
use crate::model::fit::{FitError, FitOptions, FitReport, validate_options, validate_points};
use bevy::math::DVec3;
use bevy::prelude::*;

/// Fits `points` through [`DeformableSqPlugin`] in a headless app; see the module docs.
pub fn fit_headless(points: &[DVec3], opts: &FitOptions) -> Result<FitReport, FitError> {
    validate_points(points)?;
    validate_options(opts)?;
    let mut app = App::new();
    app.add_plugins((MinimalPlugins, DeformableSqPlugin::in_schedule(Update)));
    let e = app
        .world_mut()
        .spawn((
            GlobalShape::default(),
            RangeData::new(points.to_vec()),
            FitDriver::new(*opts),
        ))
        .id();
    loop {
        app.update();
        let driver = app
            .world()
            .get::<FitDriver>(e)
            .ok_or(FitError::Degenerate)?;
        if let Some(error) = driver.error() {
            return Err(error.clone());
        }
        if driver.is_done() {
            break;
        }
        // The fit runs on another thread: wait for it without spinning a core.
        std::thread::sleep(std::time::Duration::from_micros(200));
    }
    let world = app.world();
    let report = world
        .get::<FitDriver>(e)
        .and_then(FitDriver::report)
        .ok_or(FitError::Degenerate)?;
    let (Some(rigid), Some(shape), Some(local), Some(fem)) = (
        world.get::<RigidState>(e),
        world.get::<GlobalShape>(e),
        world.get::<LocalDofs>(e),
        world.get::<FemMesh>(e),
    ) else {
        return Err(FitError::Degenerate);
    };
    Ok(FitReport {
        state: model_state(rigid, shape, local),
        tess: Tessellation::new(fem.k),
        ..report.clone()
    })
}
