//! `--demo-drag [--demo-part NAME]` (for the sandbox's render test): once the part (default the
//! cylinder) has taken 20 steps, moves the real cursor onto it, presses the left button as the
//! windowing system would report it, drags about 175 pixels to the upper right over 40 frames and
//! holds, then prints how far the part moved and how much its shape changed. Picking, the grab,
//! the drag and the spring all run as they do for a user.
use bevy::input::ButtonState;
use bevy::input::mouse::MouseButtonInput;
use bevy::prelude::*;
use bevy::window::WindowEvent;
use bevy_deformable_sq::prelude::*;
use glam::DVec3;

/// The part to drag.
#[derive(Resource)]
struct DemoPart(String);

/// Adds the scripted drag when the command line asks for it.
pub fn maybe_add(app: &mut App, args: &[String]) {
    if !args.iter().any(|a| a == "--demo-drag") {
        return;
    }
    let part = args
        .iter()
        .position(|a| a == "--demo-part")
        .and_then(|i| args.get(i + 1).cloned())
        .unwrap_or_else(|| "cylinder".into());
    app.insert_resource(DemoPart(part))
        .add_systems(Update, demo_drag.before(MouseSpringSystems));
}

fn demo_drag(
    mut frame: Local<u32>,
    mut start: Local<Option<(Vec2, DVec3, GlobalShape)>>,
    part: Res<DemoPart>,
    mouse: Res<MouseSpring>,
    mut window: Single<(Entity, &mut Window)>,
    camera: Single<(&Camera, &GlobalTransform)>,
    parts: Query<(&Name, &RigidState, &GlobalShape, &SimControl)>,
    mut buttons: MessageWriter<MouseButtonInput>,
    mut events: MessageWriter<WindowEvent>,
) {
    let Some((name, rigid, shape, control)) = parts.iter().find(|(n, ..)| n.as_str() == part.0)
    else {
        return;
    };
    if control.steps < 20 {
        return;
    }
    let (camera, cam_tf) = *camera;
    let (window_entity, window) = &mut *window;
    let Some((p0, c0, shape0)) = *start else {
        let Ok(p) = camera.world_to_viewport(cam_tf, rigid.translation.as_vec3()) else {
            return;
        };
        window.set_cursor_position(Some(p));
        *start = Some((p, rigid.translation, *shape));
        return;
    };
    *frame += 1;
    match *frame {
        1..=2 => {}
        3 => {
            let press = MouseButtonInput {
                button: MouseButton::Left,
                state: ButtonState::Pressed,
                window: *window_entity,
            };
            buttons.write(press);
            events.write(WindowEvent::MouseButtonInput(press));
        }
        4..=43 => {
            let step = (*frame - 3) as f32;
            window.set_cursor_position(Some(p0 + Vec2::new(3.6, -2.4) * step));
        }
        44 => {
            let axes = |s: &GlobalShape| [s.a * s.a1, s.a * s.a2, s.a * s.a3];
            let (before, after) = (axes(&shape0), axes(shape));
            let stretch = (0..3)
                .map(|i| (after[i] / before[i]).max(before[i] / after[i]))
                .fold(0.0, f64::max);
            let eps = (shape.e1 - shape0.e1)
                .abs()
                .max((shape.e2 - shape0.e2).abs());
            println!(
                "demo drag: {} grabbed: {}, semi-axes within {:.3}x, epsilon within {:.3}, moved by {:.3} (x {:.3})",
                name,
                mouse.model.is_some(),
                stretch,
                eps,
                (rigid.translation - c0).length(),
                rigid.translation.x - c0.x
            );
        }
        _ => {}
    }
}
