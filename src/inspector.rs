//! [`DeformableSqInspectorPlugin`] (feature `egui`): the modelling sandbox's panel for any app.
//!
//! One egui window lists every model and joint and shows the selected model's panel,
//! [`model_inspector_ui`]: sliders for the global shape and the dynamics, switches for what is
//! free, second-order dynamics, pause / step / reset, fit to convergence, export, and the plot of
//! the distance to the data. An app with its own egui UI can embed that panel instead: query
//! [`InspectedModel`] and call [`model_inspector_ui`].
//!
//! The plugin needs bevy_egui's `EguiPlugin` (added before or after it). Its window is drawn in
//! `EguiPrimaryContextPass`; the residual history ([`ResidualHistory`]) and the selection are kept
//! in `Update`, in [`InspectorSystems`]. With the `picking` feature a model grabbed by the mouse
//! spring becomes the selected one.

use crate::model::deform::{MAX_BEND, MAX_TAPER};
use crate::model::dynamics::ModelState;
use crate::model::fit::residuals;
use crate::model::superquadric::{LEAST_EPSILON, MAX_EPSILON};
use crate::plugin::{
    FemMesh, FitDriver, FitFinished, GlobalShape, ImageData, Inertia, LocalDofs, ModelFrozen,
    ModelSettings, PartJoint, RangeData, RigidState, SimControl,
};
use bevy::ecs::query::QueryData;
use bevy::prelude::*;
use bevy_egui::{EguiContexts, EguiPrimaryContextPass, egui};
use std::collections::VecDeque;
use std::path::PathBuf;

/// The inspector window: the models, the joints and the selected model's panel.
#[derive(Default)]
pub struct DeformableSqInspectorPlugin;

impl Plugin for DeformableSqInspectorPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<InspectorState>()
            .add_systems(
                Update,
                (select_new, track_residuals, report)
                    .chain()
                    .in_set(InspectorSystems),
            )
            // Where the simulation runs in `Update`, the residuals are sampled after its step.
            .configure_sets(
                Update,
                InspectorSystems.after(crate::plugin::DeformableSqSystems::WriteBack),
            )
            .add_systems(EguiPrimaryContextPass, inspector_window);
        #[cfg(feature = "picking")]
        app.add_systems(
            Update,
            select_grabbed
                .in_set(InspectorSystems)
                .before(select_new)
                .after(crate::picking::MouseSpringSystems)
                .run_if(resource_exists::<Messages<crate::picking::ModelGrabbed>>),
        );
    }

    fn finish(&self, app: &mut App) {
        if !app.is_plugin_added::<bevy_egui::EguiPlugin>() {
            warn!("DeformableSqInspectorPlugin needs bevy_egui's EguiPlugin: no window is drawn");
        }
    }
}

/// The set the inspector's `Update` systems run in (selection, residual history, messages).
#[derive(SystemSet, Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct InspectorSystems;

/// What the inspector window shows.
#[derive(Resource, Clone, Debug)]
pub struct InspectorState {
    /// The window is drawn (default true).
    pub open: bool,
    /// The model whose panel is shown.
    pub selected: Option<Entity>,
    /// Select the first model of this name when it appears (e.g. from a command line).
    pub select_name: Option<String>,
    /// The last thing that happened: an export, a fit that ended, a model that froze.
    pub message: String,
    /// Where "Export" writes `NAME.obj` and `NAME.json` (default the working directory).
    pub export_dir: PathBuf,
}

impl Default for InspectorState {
    fn default() -> Self {
        Self {
            open: true,
            selected: None,
            select_name: None,
            message: String::new(),
            export_dir: PathBuf::from("."),
        }
    }
}

/// The RMS distance from a model's range data to its surface (a fraction of the data's
/// bounding-box diagonal), sampled every `every` frames; the inspector plots it. The inspector
/// adds one to the model it selects; add one to any model with [`RangeData`] to track it.
#[derive(Component, Clone, Debug, PartialEq)]
pub struct ResidualHistory {
    /// The samples, oldest first (at most `capacity`).
    pub values: VecDeque<f32>,
    /// Frames between samples.
    pub every: u32,
    /// Samples kept.
    pub capacity: usize,
    frames: u32,
}

impl Default for ResidualHistory {
    fn default() -> Self {
        Self {
            values: VecDeque::new(),
            every: 10,
            capacity: 300,
            frames: 0,
        }
    }
}

/// What [`model_inspector_ui`] shows and edits of one model.
#[derive(QueryData)]
#[query_data(mutable)]
pub struct InspectedModel {
    /// The model.
    pub entity: Entity,
    /// Its name, shown as the panel's title.
    pub name: Option<&'static Name>,
    /// Edited by the shape sliders.
    pub shape: &'static mut GlobalShape,
    /// Edited by the dynamics sliders and switches.
    pub settings: &'static mut ModelSettings,
    /// Pause, step and reset.
    pub control: &'static mut SimControl,
    /// Second-order dynamics, switched on and off by the panel.
    pub inertia: Option<&'static mut Inertia>,
    /// Exported with the shape.
    pub rigid: &'static RigidState,
    /// Exported with the shape.
    pub local: &'static LocalDofs,
    /// Exported with the shape.
    pub fem: &'static FemMesh,
    /// Only models with range or image data are fitted to convergence.
    pub range: Has<RangeData>,
    /// Image data: fitted to convergence by the solved image fit.
    pub image: Has<ImageData>,
    /// A fit in progress.
    pub driver: Option<&'static FitDriver>,
    /// Plotted when present.
    pub residual: Option<&'static ResidualHistory>,
}

/// The selected model's panel, for any egui UI: the global shape, the dynamics, what is free,
/// inertia, pause / step / reset, fit to convergence (models with range or image data), export
/// to `export_dir` and the residual plot. Returns a line to show the user when a button did something.
pub fn model_inspector_ui(
    ui: &mut egui::Ui,
    model: &mut InspectedModelItem,
    export_dir: &std::path::Path,
    commands: &mut Commands,
) -> Option<String> {
    let mut said = None;
    if let Some(name) = model.name {
        ui.strong(name.as_str());
    }
    shape_sliders(ui, &mut model.shape);
    dynamics_controls(ui, &mut model.settings);
    let mut second_order = model.inertia.is_some();
    if ui
        .checkbox(&mut second_order, "inertia (second order)")
        .changed()
    {
        if second_order {
            commands.entity(model.entity).insert(Inertia::default());
        } else {
            commands.entity(model.entity).remove::<Inertia>();
        }
    }
    if let Some(inertia) = model.inertia.as_mut() {
        let p = &mut inertia.params;
        ui.add(
            edit_slider(&mut p.mass_density, 0.01..=100.0)
                .logarithmic(true)
                .text("mass density μ"),
        );
        ui.add(edit_slider(&mut p.damping, 0.0..=10.0).text("damping β"));
    }
    let control = &mut *model.control;
    ui.horizontal(|ui| {
        ui.checkbox(&mut control.paused, "paused");
        if ui.button("Step").clicked() {
            control.paused = true;
            control.step_requests += 1;
        }
        if ui.button("Reset").clicked() {
            control.reset_requested = true;
        }
    });
    let (mut fit, mut export_now) = (false, false);
    ui.horizontal(|ui| {
        fit = (model.range || model.image) && ui.button("Fit to convergence").clicked();
        export_now = ui.button("Export OBJ").clicked();
    });
    if fit {
        commands
            .entity(model.entity)
            .insert(FitDriver::for_model(&model.settings));
        said = Some("fitting to convergence".to_string());
    }
    if export_now {
        said = Some(match export(model, export_dir) {
            Ok(done) => done,
            Err(e) => format!("export failed: {e}"),
        });
    }
    let control = &*model.control;
    ui.label(format!("{} steps", control.steps));
    if let Some(err) = &control.error {
        ui.colored_label(egui::Color32::LIGHT_RED, err);
    }
    if let Some(d) = model.driver {
        match d.error() {
            Some(e) => ui.colored_label(egui::Color32::LIGHT_RED, format!("fit failed: {e}")),
            None => ui.label(match (d.is_done(), d.converged()) {
                (false, _) => "fitting…",
                (true, true) => "fit at rest",
                (true, false) => "fit stopped at its step cap",
            }),
        };
    }
    if let Some(history) = model.residual {
        ui.label("RMS distance to the data (fraction of the diagonal)");
        plot(ui, &history.values);
    }
    said
}

/// The global shape: a, the aspect ratios, the squareness, tapering and bending.
fn shape_sliders(ui: &mut egui::Ui, g: &mut GlobalShape) {
    ui.add(edit_slider(&mut g.a, 0.05..=3.0).text("a"));
    ui.add(edit_slider(&mut g.a1, 0.05..=1.0).text("a1"));
    ui.add(edit_slider(&mut g.a2, 0.05..=1.0).text("a2"));
    ui.add(edit_slider(&mut g.a3, 0.05..=1.0).text("a3"));
    // Down to the least ε a shape may hold; the step keeps one set below 0.1 there.
    let e_range = LEAST_EPSILON..=MAX_EPSILON;
    ui.add(edit_slider(&mut g.e1, e_range.clone()).text("ε1"));
    ui.add(edit_slider(&mut g.e2, e_range).text("ε2"));
    // The step keeps tapering and bending within their bounds for the shape.
    ui.add(edit_slider(&mut g.taper[0], -MAX_TAPER..=MAX_TAPER).text("taper x"));
    ui.add(edit_slider(&mut g.taper[1], -MAX_TAPER..=MAX_TAPER).text("taper y"));
    ui.add(edit_slider(&mut g.bend[0], -MAX_BEND..=MAX_BEND).text("bend x"));
    ui.add(edit_slider(&mut g.bend[1], -MAX_BEND..=MAX_BEND).text("bend y"));
}

/// The membrane's stiffness, the damping, the step and what is free.
fn dynamics_controls(ui: &mut egui::Ui, s: &mut ModelSettings) {
    let log = |ui: &mut egui::Ui, v: &mut f64, range, text| {
        ui.add(edit_slider(v, range).logarithmic(true).text(text));
    };
    log(ui, &mut s.w0, 0.0..=0.1, "w0");
    log(ui, &mut s.w1, 0.0..=2.0, "w1");
    log(ui, &mut s.gamma_global, 0.01..=10.0, "γ global");
    log(ui, &mut s.gamma_local, 0.01..=10.0, "γ local");
    log(ui, &mut s.dt, 0.001..=0.2, "Δt");
    ui.add(edit_slider(&mut s.reassign_every, 1..=1000).text("reassign every"));
    ui.horizontal(|ui| {
        ui.checkbox(&mut s.global_only, "global only");
        ui.checkbox(&mut s.implicit_local, "implicit membrane")
            .on_hover_text(
                "one backward-Euler solve of the local DOFs a step: stable at any Δt \
                 (first-order dynamics; ignored with inertia)",
            );
    });
    ui.horizontal(|ui| {
        ui.checkbox(&mut s.fix_epsilon, "fix ε");
        ui.checkbox(&mut s.fix_shape, "fix shape (rigid)");
        ui.checkbox(&mut s.fix_pose, "fix pose");
    });
    ui.horizontal(|ui| {
        ui.checkbox(&mut s.taper, "free taper");
        ui.checkbox(&mut s.bend, "free bend");
    });
}

/// Writes the model as `NAME.obj` (its mesh) and `NAME.json` (its parameters) in `dir`.
fn export(model: &InspectedModelItem, dir: &std::path::Path) -> Result<String, String> {
    let tess = model.fem.get().ok_or("the model has no mesh yet")?;
    let state = ModelState {
        translation: model.rigid.translation,
        rotation: model.rigid.rotation,
        shape: (*model.shape).into(),
        deformation: model.shape.deformation(),
        displacement: model.local.displacement.clone(),
    };
    let name = model
        .name
        .map(|n| n.as_str().replace(|c: char| !c.is_alphanumeric(), "_"))
        .unwrap_or_else(|| "model".into());
    let (obj, json) = (
        dir.join(format!("{name}.obj")),
        dir.join(format!("{name}.json")),
    );
    crate::io::write_model_obj(&obj, tess, &state).map_err(|e| e.to_string())?;
    let params = serde_json::json!({
        "translation": state.translation.to_array(),
        "rotation_xyzw": state.rotation.to_array(),
        "shape": state.shape,
        "taper": model.shape.taper,
        "bend": model.shape.bend,
        "nodes": tess.node_count(),
    });
    std::fs::write(&json, params.to_string()).map_err(|e| format!("{}: {e}", json.display()))?;
    Ok(format!("wrote {} and {}", obj.display(), json.display()))
}

/// The window: every model, every joint, and the selected model's panel.
fn inspector_window(
    mut contexts: EguiContexts,
    mut state: ResMut<InspectorState>,
    mut models: Query<InspectedModel>,
    joints: Query<(Entity, &PartJoint)>,
    #[cfg(feature = "debug_render")] debug: Option<ResMut<crate::debug_render::DebugRenderConfig>>,
    mut commands: Commands,
) -> Result {
    if !state.open {
        return Ok(());
    }
    let ctx = contexts.ctx_mut()?;
    let state = &mut *state;
    egui::Window::new("Deformable superquadrics")
        .default_pos([10.0, 10.0])
        .default_width(300.0)
        // The selected model's controls run past a small window's bottom: scroll to them.
        .vscroll(true)
        .default_height(690.0)
        .show(ctx, |ui| {
            #[cfg(feature = "debug_render")]
            if let Some(mut debug) = debug {
                ui.horizontal(|ui| {
                    ui.checkbox(&mut debug.points, "points");
                    ui.checkbox(&mut debug.data_springs, "data springs");
                    ui.checkbox(&mut debug.user_springs, "mouse springs");
                });
            }
            if !state.message.is_empty() {
                ui.label(&state.message);
            }
            ui.weak("scroll down for fit to convergence, export and the residual plot");
            ui.separator();
            ui.label("Models");
            let mut list: Vec<(Entity, String)> = models
                .iter()
                .map(|m| (m.entity, label(m.entity, m.name)))
                .collect();
            list.sort_by(|a, b| a.1.cmp(&b.1));
            for (e, name) in &list {
                if ui
                    .selectable_label(state.selected == Some(*e), name)
                    .clicked()
                {
                    state.selected = Some(*e);
                }
            }
            if !joints.is_empty() {
                ui.separator();
                ui.label("Joints (gap, force carried)");
                for (e, j) in &joints {
                    let name = |m: Entity| {
                        list.iter()
                            .find(|(e, _)| *e == m)
                            .map_or_else(|| format!("{m}"), |(_, n)| n.clone())
                    };
                    ui.horizontal(|ui| {
                        ui.label(format!(
                            "{} ↔ {}: {:.1e}, {:.2}",
                            name(j.a),
                            name(j.b),
                            j.gap.length(),
                            j.joint.multiplier.length()
                        ));
                        if ui.small_button("remove").clicked() {
                            commands.entity(e).despawn();
                        }
                    });
                }
            }
            let Some(mut model) = state.selected.and_then(|e| models.get_mut(e).ok()) else {
                return;
            };
            ui.separator();
            if let Some(said) = model_inspector_ui(ui, &mut model, &state.export_dir, &mut commands)
            {
                state.message = said;
            }
        });
    Ok(())
}

/// A model's name, or its entity when it has none.
fn label(e: Entity, name: Option<&Name>) -> String {
    name.map_or_else(|| format!("{e}"), |n| n.to_string())
}

/// Selects the model named by `select_name` when it appears, gives the selected range model a
/// [`ResidualHistory`], and forgets a selected model that is gone.
fn select_new(
    mut state: ResMut<InspectorState>,
    models: Query<(Entity, Option<&Name>, Has<RangeData>, Has<ResidualHistory>), With<GlobalShape>>,
    mut commands: Commands,
) {
    if let Some(e) = state.selected
        && !models.contains(e)
    {
        state.selected = None;
    }
    if state.selected.is_none()
        && let Some(want) = &state.select_name
        && let Some((e, ..)) = models
            .iter()
            .find(|(_, n, ..)| n.is_some_and(|n| n.as_str() == want))
    {
        state.selected = Some(e);
        state.select_name = None;
    }
    if let Some(Ok((e, _, true, false))) = state.selected.map(|e| models.get(e)) {
        commands.entity(e).insert(ResidualHistory::default());
    }
}

/// The model the mouse spring grabbed becomes the selected one.
#[cfg(feature = "picking")]
fn select_grabbed(
    mut state: ResMut<InspectorState>,
    mut grabbed: MessageReader<crate::picking::ModelGrabbed>,
) {
    if let Some(g) = grabbed.read().last() {
        state.selected = Some(g.model);
    }
}

/// Samples every [`ResidualHistory`]: the RMS distance of the model's points to its surface,
/// from the model's components (so that a fit's state is sampled while the model is paused).
fn track_residuals(
    mut models: Query<(
        &FemMesh,
        &RigidState,
        &GlobalShape,
        &LocalDofs,
        &RangeData,
        &mut ResidualHistory,
    )>,
    mut x: Local<Vec<bevy::math::DVec3>>,
) {
    for (fem, rigid, shape, local, range, mut history) in &mut models {
        history.frames += 1;
        if history.frames < history.every.max(1) {
            continue;
        }
        let Some(tess) = fem.get() else { continue };
        if local.displacement.len() != tess.node_count() {
            continue;
        }
        history.frames = 0;
        crate::plugin::world_positions(tess, rigid, shape, local, &mut x);
        let rms = residuals(tess, &x, range.forces.points()).rms as f32;
        history.values.push_back(rms);
        while history.values.len() > history.capacity {
            history.values.pop_front();
        }
    }
}

/// The simulation's messages about the selected model, as the window's message line.
fn report(
    mut state: ResMut<InspectorState>,
    mut fits: MessageReader<FitFinished>,
    mut frozen: MessageReader<ModelFrozen>,
) {
    for f in fits.read() {
        if state.selected == Some(f.model) {
            state.message = match f.at_rest {
                true => format!("fit at rest after {} steps", f.steps),
                false => format!("fit stopped at its step cap ({} steps)", f.steps),
            };
        }
    }
    for f in frozen.read() {
        if state.selected == Some(f.model) {
            state.message = format!("frozen: {}", f.error);
        }
    }
}

/// A line plot of `values` with its last value.
fn plot(ui: &mut egui::Ui, values: &VecDeque<f32>) {
    let (rect, _) = ui.allocate_exact_size(egui::vec2(280.0, 80.0), egui::Sense::hover());
    let painter = ui.painter_at(rect);
    painter.rect_filled(rect, 2.0, egui::Color32::from_gray(30));
    let Some(max) = values.iter().copied().reduce(f32::max).filter(|m| *m > 0.0) else {
        return;
    };
    let n = values.len().max(2) as f32 - 1.0;
    let points: Vec<egui::Pos2> = values
        .iter()
        .enumerate()
        .map(|(i, v)| {
            egui::pos2(
                rect.left() + rect.width() * i as f32 / n,
                rect.bottom() - rect.height() * (v / max) * 0.95,
            )
        })
        .collect();
    painter.add(egui::Shape::line(
        points,
        egui::Stroke::new(1.5, egui::Color32::LIGHT_GREEN),
    ));
    if let Some(last) = values.back() {
        painter.text(
            rect.right_top() + egui::vec2(-4.0, 4.0),
            egui::Align2::RIGHT_TOP,
            format!("{last:.4} (max {max:.4})"),
            egui::FontId::proportional(11.0),
            egui::Color32::WHITE,
        );
    }
}

/// A slider that clamps what the user enters to `range` but leaves values outside it alone (egui
/// clamps every shown value by default, which would silently change a model the inspector shows).
pub fn edit_slider<Num: egui::emath::Numeric>(
    value: &mut Num,
    range: std::ops::RangeInclusive<Num>,
) -> egui::Slider<'_> {
    egui::Slider::new(value, range).clamping(egui::SliderClamping::Edits)
}
