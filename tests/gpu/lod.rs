//! Level of detail on the GPU: a cloud's volume resolution follows its projected size, and a
//! change waits until the cloud is re-lit, so it never pops on a still sky.

use bevy::prelude::*;
use bevy_particle_clouds::headless::{self, FrameRecorder};
use bevy_particle_clouds::{
    CloudLevelOfDetail, CloudLod, CloudPass, render::volumes::CloudVolumes,
};

use crate::common;

/// The plugin tests' small cloud (bounding sphere radius ~1.3 m) at the origin, at most 32³.
fn spawn_cloud(app: &mut App) -> Entity {
    let cloud = crate::plugin::small_cloud(app, 0.9, Vec3::ZERO);
    app.world_mut()
        .entity_mut(cloud)
        .insert(common::quality(32, 4));
    cloud
}

/// The volume resolution the cloud's volumes hold.
fn held(app: &mut App) -> u32 {
    common::with_render_world(app, |world| {
        world
            .query::<&CloudVolumes>()
            .single(world)
            .expect("one cloud's volumes")
            .params
            .n
    })
}

fn frames(app: &mut App, recorder: &mut FrameRecorder, count: usize) -> usize {
    (0..count)
        .map(|_| recorder.frame(app).unwrap().runs(CloudPass::Voxelize) as usize)
        .sum()
}

#[test]
fn resolution_follows_the_projected_size_once_the_cloud_is_relit() {
    let mut app = common::headless_app();
    app.insert_resource(CloudLevelOfDetail {
        pixels_per_voxel: 2.0,
        min_resolution: 8,
    });
    let image = headless::float_target(&mut app, 64, 48);
    let far = Transform::from_xyz(0.0, 0.0, 40.0).looking_at(Vec3::ZERO, Vec3::Y);
    let camera = headless::spawn_linear_camera(&mut app, image, far, 40.0, Vec3::ZERO);
    let light = headless::spawn_light(&mut app, Vec3::new(-1.0, -1.0, -0.5), Vec3::ONE);
    let cloud = spawn_cloud(&mut app);
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 1, 20).unwrap();

    // 40 m away, about 4 pixels across at 2 pixels per voxel: the coarsest level, 8³.
    let lod = *app
        .world()
        .get::<CloudLod>(cloud)
        .expect("a level of detail");
    assert!(
        (3.0..6.0).contains(&lod.projected_pixels),
        "{}",
        lod.projected_pixels
    );
    assert_eq!((lod.level, lod.resolution), (4, 8));
    assert_eq!(held(&mut app), 8);

    // Close: the level asks for all 32³, but nothing needs re-lighting, so the volumes hold.
    app.world_mut()
        .entity_mut(camera)
        .insert(Transform::from_xyz(0.0, 0.0, 3.0).looking_at(Vec3::ZERO, Vec3::Y));
    assert_eq!(frames(&mut app, &mut recorder, 4), 0, "no re-lighting");
    let lod = *app.world().get::<CloudLod>(cloud).unwrap();
    assert_eq!((lod.level, lod.resolution), (0, 32));
    assert_eq!(held(&mut app), 8, "held until re-lit");

    // The light turns: the cloud is re-lit, at the resolution its level asks for.
    app.world_mut()
        .entity_mut(light)
        .get_mut::<Transform>()
        .unwrap()
        .rotate_y(0.3);
    assert_eq!(
        frames(&mut app, &mut recorder, 4),
        1,
        "voxelized once, at 32³"
    );
    assert_eq!(held(&mut app), 32);
}

#[test]
fn level_of_detail_is_off_by_default() {
    let mut app = common::headless_app();
    let image = headless::float_target(&mut app, 64, 48);
    let far = Transform::from_xyz(0.0, 0.0, 40.0).looking_at(Vec3::ZERO, Vec3::Y);
    headless::spawn_linear_camera(&mut app, image, far, 40.0, Vec3::ZERO);
    headless::spawn_light(&mut app, Vec3::NEG_Y, Vec3::ONE);
    let cloud = spawn_cloud(&mut app);
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 1, 20).unwrap();
    assert!(app.world().get::<CloudLod>(cloud).is_none());
    assert_eq!(held(&mut app), 32);
}

/// Without level of detail, a new `volume_resolution` on a still cloud applies at once: only
/// the level of detail's own changes wait for a re-light. (The benchmark's sweeps captured the
/// previous setting's image while it waited too.)
#[test]
fn a_new_volume_resolution_applies_at_once_without_level_of_detail() {
    let mut app = common::headless_app();
    let image = headless::float_target(&mut app, 64, 48);
    let near = Transform::from_xyz(0.0, 0.0, 6.0).looking_at(Vec3::ZERO, Vec3::Y);
    headless::spawn_linear_camera(&mut app, image, near, 40.0, Vec3::ZERO);
    headless::spawn_light(&mut app, Vec3::NEG_Y, Vec3::ONE);
    let cloud = spawn_cloud(&mut app);
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 1, 20).unwrap();
    assert_eq!(held(&mut app), 32);
    app.world_mut()
        .entity_mut(cloud)
        .insert(common::quality(16, 4));
    let voxelized = frames(&mut app, &mut recorder, 3);
    assert_eq!(held(&mut app), 16);
    assert_eq!(voxelized, 1, "voxelized once at the new resolution");
}
