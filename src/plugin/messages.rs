//! Messages the simulation sends that an app can react to: a fit ended ([`FitFinished`]) and a
//! model froze ([`ModelFrozen`]). Both are written in [`DeformableSqSystems::WriteBack`]
//! (super::DeformableSqSystems), once per event: read them with a `MessageReader` in any later
//! system.

use super::components::SimControl;
use super::fit_driver::FitDriver;
use bevy::prelude::*;

/// Sent once when a model's [`FitDriver`] ends: the fit came to rest, stopped at its step cap, or
/// failed ([`FitDriver::error`]).
#[derive(Message, Clone, Copy, Debug, PartialEq)]
pub struct FitFinished {
    /// The model.
    pub model: Entity,
    /// True when the fit ended at rest; false when its step cap ended it, or it failed.
    pub at_rest: bool,
    /// The fit's steps ([`crate::model::fit::FitReport::steps`]; 0 when it failed).
    pub steps: u64,
}

/// Sent once when a model freezes: a step was refused, or its state was made non-finite from
/// outside. The model takes no steps until it is reset ([`SimControl::reset_requested`]).
#[derive(Message, Clone, Debug, PartialEq)]
pub struct ModelFrozen {
    /// The model.
    pub model: Entity,
    /// Why it froze ([`SimControl::error`]).
    pub error: String,
}

/// What was last reported for a model, so that each event is sent once.
#[derive(Component, Clone, Copy, Debug, Default)]
pub(crate) struct Reported {
    frozen: bool,
    fit_done: bool,
}

/// Stage `WriteBack`: sends [`FitFinished`] and [`ModelFrozen`] for the models whose fit ended
/// or that froze since the last run.
pub(crate) fn send_messages(
    mut models: Query<(
        Entity,
        Ref<SimControl>,
        Option<Ref<FitDriver>>,
        &mut Reported,
    )>,
    mut fits: MessageWriter<FitFinished>,
    mut frozen: MessageWriter<ModelFrozen>,
) {
    for (model, control, driver, mut reported) in &mut models {
        let driver_changed = driver.as_ref().is_some_and(|d| d.is_changed());
        if !(control.is_changed() || driver_changed) {
            continue;
        }
        if control.frozen && !reported.frozen {
            frozen.write(ModelFrozen {
                model,
                error: control.error.clone().unwrap_or_default(),
            });
        }
        reported.frozen = control.frozen;
        let fit_done = driver.as_ref().is_some_and(|d| d.is_done());
        if fit_done
            && !reported.fit_done
            && let Some(d) = &driver
        {
            fits.write(FitFinished {
                model,
                at_rest: d.converged(),
                steps: d.steps(),
            });
        }
        reported.fit_done = fit_done;
    }
}
