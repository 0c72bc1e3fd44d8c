//! Each model drawn as a dynamic [`Mesh3d`]: the k² + 2 model-frame points p_i = s_i + d_i as
//! vertices (fixed count), the tessellation's quads and polar fans as triangles, and smooth normals
//! from the mesh (analytic normals are infinite on the edges of square superquadrics, ε < 1). The
//! entity's `Transform` carries c and R. Positions and normals are rewritten in place whenever the
//! shape or the local DOFs change. Nothing here runs without `Assets<Mesh>` (headless apps).

use crate::model::dynamics::node_positions;
use crate::plugin::scene::SceneImage;
use crate::plugin::{FemMesh, GlobalShape, LocalDofs};
use bevy::asset::RenderAssetUsages;
use bevy::math::{DQuat, DVec3};
use bevy::mesh::{Indices, PrimitiveTopology, VertexAttributeValues};
use bevy::prelude::*;

/// The dynamic mesh the render systems keep in step with a model.
#[derive(Component, Clone, Debug)]
pub struct ModelMesh(pub Handle<Mesh>);

pub use crate::plugin::components::{ModelColor, PALETTE};

/// Draws every model as a dynamic [`Mesh3d`] whose vertices follow its surface, and a scene's
/// image as a backdrop (in [`PostUpdate`], where [`Assets<Mesh>`] exists: with the render
/// plugins; without them it does nothing). Part of [`crate::DeformableSqPlugins`].
#[derive(Default)]
pub struct DeformableSqRenderPlugin;

impl Plugin for DeformableSqRenderPlugin {
    fn build(&self, app: &mut App) {
        build(app);
    }
}

fn build(app: &mut App) {
    app.register_type::<ModelColor>().add_systems(
        PostUpdate,
        (
            attach_meshes,
            write_meshes,
            refresh_image_backdrops,
            attach_image_backdrops,
        )
            .chain()
            .run_if(resource_exists::<Assets<Mesh>>),
    );
}

/// The image of a [`SceneImage`] as an sRGB texture (its luminance as grey, row 0 at the top),
/// or with `show_potential` its potential P as grey (white at P_ref and above).
pub fn backdrop_texture(
    potential: &crate::model::forces::image::ImagePotential,
    show_potential: bool,
) -> bevy::image::Image {
    use bevy::render::render_resource::{Extent3d, TextureDimension, TextureFormat};
    let p_ref = potential.p_ref().max(f64::MIN_POSITIVE);
    let values: Vec<f64> = if show_potential {
        potential.potential().iter().map(|p| p / p_ref).collect()
    } else {
        potential.luminance().to_vec()
    };
    let data: Vec<u8> = values
        .iter()
        .flat_map(|l| {
            let g = (l.clamp(0.0, 1.0) * 255.0).round() as u8;
            [g, g, g, 255]
        })
        .collect();
    bevy::image::Image::new(
        Extent3d {
            width: potential.width() as u32,
            height: potential.height() as u32,
            depth_or_array_layers: 1,
        },
        TextureDimension::D2,
        data,
        TextureFormat::Rgba8UnormSrgb,
        RenderAssetUsages::RENDER_WORLD,
    )
}

/// A [`SceneImage`] whose display changed is drawn anew (its quad and texture rebuilt).
pub fn refresh_image_backdrops(
    mut commands: Commands,
    changed: Query<Entity, (Changed<SceneImage>, With<Mesh3d>)>,
) {
    for e in &changed {
        commands
            .entity(e)
            .remove::<(Mesh3d, MeshMaterial3d<StandardMaterial>)>();
    }
}

/// Draws every [`SceneImage`] that has no mesh yet as an unlit textured quad covering the image's
/// world rectangle (see [`ImageFrame`](crate::model::forces::image::ImageFrame)).
pub fn attach_image_backdrops(
    mut commands: Commands,
    mut meshes: ResMut<Assets<Mesh>>,
    textures: Option<ResMut<Assets<bevy::image::Image>>>,
    materials: Option<ResMut<Assets<StandardMaterial>>>,
    images: Query<(Entity, &SceneImage), Without<Mesh3d>>,
) {
    let (Some(mut textures), Some(mut materials)) = (textures, materials) else {
        return;
    };
    for (entity, image) in &images {
        let p = &image.potential;
        let frame = p.frame();
        let pitch = frame.extent / p.width().max(p.height()) as f64;
        let size = Vec2::new(p.width() as f32, p.height() as f32) * pitch as f32;
        let texture = textures.add(backdrop_texture(p, image.show_potential));
        commands.entity(entity).insert((
            Mesh3d(meshes.add(Rectangle::from_size(size))),
            MeshMaterial3d(materials.add(StandardMaterial {
                base_color_texture: Some(texture),
                unlit: true,
                cull_mode: None,
                ..default()
            })),
            Transform::from_translation(frame.center.as_vec2().extend(0.0)),
        ));
    }
}

/// Model-frame vertex positions and smooth (area-weighted) normals of a model.
pub fn surface_vertices(
    fem: &FemMesh,
    shape: &GlobalShape,
    local: &LocalDofs,
    points: &mut Vec<DVec3>,
) -> Option<(Vec<[f32; 3]>, Vec<[f32; 3]>)> {
    let tess = fem.get()?;
    node_positions(
        tess,
        DVec3::ZERO,
        DQuat::IDENTITY,
        &(*shape).into(),
        &shape.deformation(),
        &local.displacement,
        points,
    );
    let mut normals = Vec::new();
    tess.vertex_normals(points, &mut normals);
    let pos = points.iter().map(|p| p.as_vec3().to_array()).collect();
    let nor = normals
        .iter()
        .map(|n| n.try_normalize().unwrap_or(DVec3::Z).as_vec3().to_array())
        .collect();
    Some((pos, nor))
}

fn build_mesh(positions: Vec<[f32; 3]>, normals: Vec<[f32; 3]>, fem: &FemMesh) -> Mesh {
    let indices = fem
        .get()
        .map(|t| t.triangles().iter().flatten().copied().collect())
        .unwrap_or_default();
    Mesh::new(
        PrimitiveTopology::TriangleList,
        RenderAssetUsages::default(),
    )
    .with_inserted_attribute(Mesh::ATTRIBUTE_POSITION, positions)
    .with_inserted_attribute(Mesh::ATTRIBUTE_NORMAL, normals)
    .with_inserted_indices(Indices::U32(indices))
}

/// Gives every model that has none a [`Mesh3d`] and, when materials exist, a coloured
/// [`StandardMaterial`].
pub fn attach_meshes(
    mut commands: Commands,
    mut meshes: ResMut<Assets<Mesh>>,
    materials: Option<ResMut<Assets<StandardMaterial>>>,
    models: Query<
        (
            Entity,
            &FemMesh,
            &GlobalShape,
            &LocalDofs,
            Option<&ModelColor>,
        ),
        Without<ModelMesh>,
    >,
    mut next_colour: Local<usize>,
    mut points: Local<Vec<DVec3>>,
) {
    let mut materials = materials;
    for (entity, fem, shape, local, colour) in &models {
        let Some((pos, nor)) = surface_vertices(fem, shape, local, &mut points) else {
            continue;
        };
        let handle = meshes.add(build_mesh(pos, nor, fem));
        let mut e = commands.entity(entity);
        e.insert((ModelMesh(handle.clone()), Mesh3d(handle)));
        if let Some(materials) = materials.as_mut() {
            let colour = colour.map(|c| c.0).unwrap_or_else(|| {
                *next_colour += 1;
                PALETTE[(*next_colour - 1) % PALETTE.len()]
            });
            e.insert(MeshMaterial3d(materials.add(StandardMaterial {
                base_color: colour,
                perceptual_roughness: 0.6,
                ..default()
            })));
        }
    }
}

/// Rewrites positions and normals in place (same vertex count), or the whole mesh when the
/// tessellation changed.
pub fn write_meshes(
    mut meshes: ResMut<Assets<Mesh>>,
    models: Query<
        (&FemMesh, &GlobalShape, &LocalDofs, &ModelMesh),
        Or<(Changed<LocalDofs>, Changed<GlobalShape>, Changed<FemMesh>)>,
    >,
    mut points: Local<Vec<DVec3>>,
) {
    for (fem, shape, local, handle) in &models {
        let Some((pos, nor)) = surface_vertices(fem, shape, local, &mut points) else {
            continue;
        };
        let Some(mut mesh) = meshes.get_mut(&handle.0) else {
            continue;
        };
        let same_count = matches!(mesh.attribute(Mesh::ATTRIBUTE_POSITION), Some(VertexAttributeValues::Float32x3(v)) if v.len() == pos.len());
        if !same_count {
            *mesh = build_mesh(pos, nor, fem);
            continue;
        }
        if let Some(VertexAttributeValues::Float32x3(v)) =
            mesh.attribute_mut(Mesh::ATTRIBUTE_POSITION)
        {
            v.copy_from_slice(&pos);
        }
        if let Some(VertexAttributeValues::Float32x3(v)) =
            mesh.attribute_mut(Mesh::ATTRIBUTE_NORMAL)
        {
            v.copy_from_slice(&nor);
        }
    }
}
