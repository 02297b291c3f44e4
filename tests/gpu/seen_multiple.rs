//! An anisotropic cloud composited through the view transmittance: its multiple scattering is
//! evaluated towards the camera once per voxel of its scattering grid, into its view's atlas
//! (docs/illumination.md §5), instead of from its moments at every chord point. Against the CPU
//! reference voxel by voxel, evaluated again only when the camera or the light moved, and never
//! for an isotropic cloud.

use bevy::prelude::*;
use bevy_particle_clouds::headless::{self, FrameRecorder, FrameStats};
use bevy_particle_clouds::{
    CloudPass, Medium,
    reference::{
        illumination::{CloudIllumination, LocalLight, illuminate},
        metrics::max_relative_difference,
    },
    render::{pools::BufferRange, view_atlas::ViewVolumeAtlases, view_volume::CloudViewVolumes},
};

use crate::{
    common,
    illumination::{TOLERANCE, flat, random_particles, rgb},
};

const IRRADIANCE: Vec3 = Vec3::new(1.0, 0.9, 0.8);

struct Scene {
    app: App,
    recorder: FrameRecorder,
    camera: Entity,
    light: Entity,
}

fn scene(anisotropy: f32, eye: Vec3, light: Vec3) -> Scene {
    let mut app = common::headless_app();
    let image = headless::float_target(&mut app, 16, 16);
    let camera = headless::spawn_linear_camera(
        &mut app,
        image,
        Transform::from_translation(eye).looking_at(Vec3::ZERO, Vec3::Y),
        60.0,
        Vec3::ZERO,
    );
    let light = headless::spawn_light(&mut app, light, IRRADIANCE);
    headless::spawn_cloud(
        &mut app,
        random_particles(3, 60),
        medium(anisotropy),
        common::quality(12, 6),
        Transform::IDENTITY,
    );
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 1, 20).unwrap();
    Scene {
        app,
        recorder,
        camera,
        light,
    }
}

fn medium(anisotropy: f32) -> Medium {
    Medium {
        extinction: 6.0,
        albedo: 0.95,
        anisotropy,
    }
}

/// The CPU reference of the cloud lit along `light`.
fn cpu(light: Vec3) -> CloudIllumination {
    let light = LocalLight {
        direction: light.normalize().as_dvec3(),
        irradiance: IRRADIANCE.as_dvec3(),
    };
    illuminate(
        &random_particles(3, 60),
        &medium(0.7),
        1.0,
        &[light],
        &common::quality(12, 6),
    )
    .unwrap()
}

/// The one view's multiple scattering seen from the camera (RGB per voxel), if the cloud has it.
fn gpu_seen(app: &mut App) -> Option<Vec<f64>> {
    let range = common::with_render_world(app, |world| {
        let volume = world
            .query::<&CloudViewVolumes>()
            .single(world)
            .expect("one cloud's view volumes");
        let (view, volume) = volume.0.iter().next().expect("one view");
        let params = volume.uniform().filter(|_| volume.sees_multiple())?;
        let atlas = &world.resource::<ViewVolumeAtlases>().0[view];
        Some(BufferRange {
            buffer: atlas.seen_multiple.clone(),
            offset: params.seen_offset as u64 * 16,
            size: (params.seen_n as u64).pow(3) * 16,
        })
    })?;
    Some(rgb(&headless::read_buffer_range(app, &range).unwrap()))
}

/// The GPU's volume against the CPU's seen from `eye`, relative to its maximum.
fn check_seen(app: &mut App, eye: Vec3, light: Vec3, what: &str) {
    let gpu = gpu_seen(app).expect("an anisotropic cloud's multiple scattering seen");
    let cpu = cpu(light)
        .multiple_seen_from(eye.as_dvec3())
        .expect("moments");
    let error = max_relative_difference(&gpu, &flat(&cpu));
    assert!(error <= TOLERANCE, "{what}: GPU differs by {error:e}");
}

/// The view-volume stage's (runs, dispatches) in the next frame.
fn next_frame(s: &mut Scene) -> (u32, u32) {
    let frame: FrameStats = s.recorder.frame(&mut s.app).unwrap().clone();
    (
        frame.runs(CloudPass::ViewVolume),
        frame.dispatches(CloudPass::ViewVolume),
    )
}

#[test]
fn an_anisotropic_clouds_multiple_scattering_is_seen_from_the_camera() {
    let (eye, light) = (Vec3::new(0.5, 0.3, 4.0), Vec3::new(0.3, -0.4, -1.0));
    let mut s = scene(0.7, eye, light);
    check_seen(&mut s.app, eye, light, "first frame");
    // A still scene evaluates nothing again.
    assert_eq!(next_frame(&mut s), (0, 0));

    // The light moves: the scattering reruns, and the volume is seen again (one dispatch), but
    // the view volume's optical depth is not marched.
    let turned = Vec3::new(-0.6, -0.5, 0.4);
    *s.app.world_mut().get_mut::<Transform>(s.light).unwrap() =
        Transform::default().looking_to(turned, Vec3::Y);
    assert_eq!(next_frame(&mut s), (1, 1));
    // The warm restart's frame is settled by the full series in the next: seen once more.
    assert_eq!(next_frame(&mut s), (1, 1));
    check_seen(&mut s.app, eye, turned, "after the light moved");
    assert_eq!(next_frame(&mut s), (0, 0));

    // The camera moves: the march and the new sight, one dispatch each.
    let moved = Vec3::new(-2.0, 1.0, 3.0);
    *s.app.world_mut().get_mut::<Transform>(s.camera).unwrap() =
        Transform::from_translation(moved).looking_at(Vec3::ZERO, Vec3::Y);
    assert_eq!(next_frame(&mut s), (1, 2));
    check_seen(&mut s.app, moved, turned, "after the camera moved");

    // Seen from elsewhere, the light scattered towards the camera differs: the volume is not
    // the mean.
    let other = cpu(turned).multiple_seen_from(eye.as_dvec3()).unwrap();
    let gpu = gpu_seen(&mut s.app).unwrap();
    assert!(max_relative_difference(&gpu, &flat(&other)) > 100.0 * TOLERANCE);
}

#[test]
fn an_isotropic_cloud_reads_its_mean_multiple_scattering() {
    let (eye, light) = (Vec3::new(0.5, 0.3, 4.0), Vec3::new(0.3, -0.4, -1.0));
    let mut s = scene(0.0, eye, light);
    assert!(gpu_seen(&mut s.app).is_none());
    // The camera moves: the march alone.
    *s.app.world_mut().get_mut::<Transform>(s.camera).unwrap() =
        Transform::from_xyz(-2.0, 1.0, 3.0).looking_at(Vec3::ZERO, Vec3::Y);
    assert_eq!(next_frame(&mut s), (1, 1));
}
