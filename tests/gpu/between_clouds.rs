//! What clouds give each other (docs/illumination.md §2 and §4): a cloud's light volumes take the
//! optical depth of every cloud between it and the light (their shadows), and its multiple
//! scattering goes through the media of the clouds that overlap it. Against the CPU reference,
//! voxel by voxel and image by image, with casters in the receiver's volume pool and in another;
//! and the cast reruns only when what it reads changes.

use bevy::{prelude::*, render::sync_world::RenderEntity};
use bevy_particle_clouds::headless::{self, FrameRecorder};
use bevy_particle_clouds::{
    CloudPass, LightSample, Medium, Particle, ParticleCloud,
    reference::{
        composite::CloudPlacement,
        illumination::{CloudIllumination, PlacedCloud, illuminate_clouds_under_sky},
        metrics::{max_relative_difference, relative_rmse},
    },
    render::{
        pools::{BufferRange, VolumePool, VolumePools},
        volumes::CloudVolumes,
    },
};

use crate::common;
use crate::draw::{
    Setup, SetupCloud, assert_images_match, cloud_setup, reference, reference_of_clouds,
    spawn_clouds,
};
use crate::illumination::{TOLERANCE, flat};

/// A cloud under a high sun, seen from the side; two more clouds above it, out of view, one of
/// them at another volume resolution (another pool).
fn stacked() -> (Setup, [Vec<Particle>; 2]) {
    let camera = Transform::from_xyz(0.2, 0.2, 4.0).looking_at(Vec3::ZERO, Vec3::Y);
    let mut setup = cloud_setup(31, camera);
    setup.transform = Transform::IDENTITY;
    setup.lights = vec![LightSample {
        direction: Vec3::new(-0.15, -1.0, -0.1),
        irradiance: Vec3::new(2.0, 1.8, 1.5),
    }];
    let casters = [
        cloud_setup(32, camera).particles,
        cloud_setup(33, camera).particles,
    ];
    (setup, casters)
}

fn caster(particles: &[Particle], at: Vec3, volume_resolution: u32) -> SetupCloud<'_> {
    SetupCloud {
        particles,
        medium: Medium {
            extinction: 2.5,
            albedo: 0.9,
            ..Default::default()
        },
        transform: Transform::from_translation(at).with_rotation(Quat::from_rotation_x(0.5)),
        settings: Some(common::quality(volume_resolution, 4)),
    }
}

/// The stacked clouds: the receiver, a caster of its shape above it, and one of another shape
/// above that.
fn clouds<'a>(setup: &'a Setup, casters: &'a [Vec<Particle>; 2]) -> [SetupCloud<'a>; 3] {
    [
        setup.cloud(),
        caster(&casters[0], Vec3::new(0.3, 3.2, 0.2), 16),
        caster(&casters[1], Vec3::new(1.3, 9.0, 0.3), 12),
    ]
}

/// The light volumes of the cloud at `translation`, as the GPU holds them.
fn light_volumes(app: &mut App, translation: Vec3) -> Vec<f64> {
    slot_volume(app, translation, |pool, slot| pool.optical_depth(slot))
}

/// The multiple scattering of the cloud at `translation` (RGB), as the GPU holds it.
fn multiple_scattering(app: &mut App, translation: Vec3) -> Vec<f64> {
    let rgba = slot_volume(app, translation, |pool, slot| pool.multiple(slot));
    rgba.chunks_exact(4)
        .flat_map(|c| [c[0], c[1], c[2]])
        .collect()
}

/// The f32 volume `range` picks in the slot of the cloud at `translation`.
fn slot_volume(
    app: &mut App,
    translation: Vec3,
    range: impl FnOnce(&VolumePool, u32) -> BufferRange,
) -> Vec<f64> {
    let cloud = cloud_at(app, translation);
    let render = app.world().get::<RenderEntity>(cloud).unwrap().id();
    let range = common::with_render_world(app, |world| {
        let volumes = world.get::<CloudVolumes>(render).expect("its volumes");
        range(
            world.resource::<VolumePools>().pool(&volumes.slot),
            volumes.slot.index,
        )
    });
    let bytes = headless::read_buffer_range(app, &range).unwrap();
    headless::floats(&bytes)
        .into_iter()
        .map(f64::from)
        .collect()
}

fn cloud_at(app: &mut App, translation: Vec3) -> Entity {
    let mut clouds = app
        .world_mut()
        .query_filtered::<(Entity, &Transform), With<ParticleCloud>>();
    clouds
        .iter(app.world())
        .find(|(_, t)| t.translation == translation)
        .map(|(e, _)| e)
        .expect("a cloud there")
}

/// The CPU reference's illumination of the first of `clouds`, illuminated together.
fn cpu_illumination(setup: &Setup, clouds: &[SetupCloud]) -> CloudIllumination {
    let placed: Vec<PlacedCloud> = clouds
        .iter()
        .map(|c| PlacedCloud {
            particles: c.particles,
            medium: c.medium,
            placement: CloudPlacement {
                translation: c.transform.translation.as_dvec3(),
                rotation: c.transform.rotation.as_dquat(),
                scale: c.transform.scale.x as f64,
            },
            settings: c.settings.unwrap_or(setup.settings),
        })
        .collect();
    let cpu = illuminate_clouds_under_sky(&placed, &setup.lights, setup.sky.as_dvec3());
    cpu.into_iter()
        .next()
        .unwrap()
        .expect("a cloud with density")
}

/// The CPU reference's light volumes of the first of `clouds`, illuminated together.
fn cpu_light_volumes(setup: &Setup, clouds: &[SetupCloud]) -> Vec<f64> {
    cpu_illumination(setup, clouds)
        .lights
        .iter()
        .flat_map(|(v, _)| v.optical_depth.iter().copied())
        .collect()
}

fn render(app: &mut App, recorder: &mut FrameRecorder, clouds: u32) {
    headless::render_until_steady(app, recorder, clouds, 20).unwrap();
}

#[test]
fn a_cloud_in_the_shadow_of_two_others_equals_the_cpu_reference() {
    let (setup, casters) = stacked();
    let clouds = clouds(&setup, &casters);
    let (mut app, target) = spawn_clouds(&setup, &clouds);
    common::draw_every_frame(&mut app);
    let mut recorder = FrameRecorder::default();
    render(&mut app, &mut recorder, 1);
    // The casters are out of view, yet illuminated for their shadow; only the receiver is drawn.
    let last = recorder.frames.last().unwrap();
    assert_eq!(last.runs(CloudPass::Draw), 1);
    // Shade: one dispatch per pool; cast: one per pair of the receivers' and the casters'
    // pools (the receiver's casters lie in both, the middle one's in the top one's).
    let frames = &recorder.frames;
    let shade = |count: &dyn Fn(&headless::FrameStats) -> u32| frames.iter().map(count).sum();
    let runs: u32 = shade(&|f| f.runs(CloudPass::Shade));
    let dispatches: u32 = shade(&|f| f.dispatches(CloudPass::Shade));
    assert_eq!((runs, dispatches), (3, 2 + 2));

    let gpu = light_volumes(&mut app, Vec3::ZERO);
    let cpu = cpu_light_volumes(&setup, &clouds);
    let error = max_relative_difference(&gpu[..cpu.len()], &cpu);
    assert!(error <= TOLERANCE, "light volume: {error:e} of its maximum");
    // The shadow is real: the casters hold most of the receiver's optical depth.
    let own = cpu_light_volumes(&setup, &clouds[..1]);
    let ratio = cpu.iter().sum::<f64>() / own.iter().sum::<f64>();
    // Measured 3.4.
    eprintln!("optical depth with the casters / alone: {ratio}");
    assert!(ratio > 2.0, "the casters add too little: {ratio}");

    let image = headless::capture(&mut app, &mut recorder, &target.image).unwrap();
    assert_images_match(&image, &reference_of_clouds(&setup, &clouds), "shadowed");
    // Against the receiver lit alone (over the same background), the image changes a lot:
    // measured 0.29.
    let rgb = |p: &[[f32; 4]]| {
        p.iter()
            .map(|c| [c[0], c[1], c[2], 1.0])
            .collect::<Vec<_>>()
    };
    let darkening = relative_rmse(&rgb(&reference(&setup)), &rgb(&image.pixels));
    assert!(darkening > 0.2, "shadowed against alone: {darkening}");
}

#[test]
fn a_caster_that_moves_recasts_the_receiver_and_a_still_sky_does_nothing() {
    let (setup, casters) = stacked();
    let [receiver, above, _] = clouds(&setup, &casters);
    let (mut app, _) = spawn_clouds(&setup, &[receiver, above]);
    let mut recorder = FrameRecorder::default();
    render(&mut app, &mut recorder, 1);

    // Both move together: nothing is re-lit.
    for cloud in [Vec3::ZERO, above.transform.translation] {
        let entity = cloud_at(&mut app, cloud);
        let mut transform = app.world_mut().get_mut::<Transform>(entity).unwrap();
        transform.translation += Vec3::new(0.5, 0.0, 0.0);
    }
    let first = recorder.frames.len();
    render(&mut app, &mut recorder, 1);
    let work: u32 = recorder.frames[first..]
        .iter()
        .map(|f| f.runs(CloudPass::Shade) + f.runs(CloudPass::Gather))
        .sum();
    assert_eq!(work, 0, "moving both clouds together re-lit one");

    // The caster moves out of the light's path: the receiver's volume is recast (its own optical
    // depth again, no shading), gathered and scattered; the caster does nothing.
    let moved = above.transform.translation + Vec3::new(0.5, 0.0, 0.0);
    let entity = cloud_at(&mut app, moved);
    app.world_mut()
        .get_mut::<Transform>(entity)
        .unwrap()
        .translation += Vec3::X * 6.0;
    let first = recorder.frames.len();
    render(&mut app, &mut recorder, 1);
    let frames = &recorder.frames[first..];
    let runs = |pass| frames.iter().map(|f| f.runs(pass)).sum::<u32>();
    assert_eq!(
        [
            runs(CloudPass::Voxelize),
            runs(CloudPass::Shade),
            runs(CloudPass::Gather)
        ],
        [0, 0, 1],
        "no shading, one gather"
    );
    // The cast is shade's one dispatch.
    let shade_dispatches: u32 = frames.iter().map(|f| f.dispatches(CloudPass::Shade)).sum();
    assert_eq!(shade_dispatches, 1);
    let gpu = light_volumes(&mut app, Vec3::new(0.5, 0.0, 0.0));
    let alone = cpu_light_volumes(&setup, &[receiver]);
    let error = max_relative_difference(&gpu[..alone.len()], &alone);
    assert!(
        error <= TOLERANCE,
        "unshadowed again: {error:e} of its maximum"
    );
}

/// Bevy's `NotShadowCaster` and `NotShadowReceiver` opt clouds out, as they do meshes.
#[test]
fn not_shadow_caster_and_not_shadow_receiver_opt_clouds_out() {
    use bevy::light::{NotShadowCaster, NotShadowReceiver};
    let (setup, casters) = stacked();
    let [receiver, above, _] = clouds(&setup, &casters);
    let alone = cpu_light_volumes(&setup, &[receiver]);
    let above_at = above.transform.translation;
    for opt_out in ["caster", "receiver"] {
        let (mut app, _) = spawn_clouds(&setup, &[receiver, above]);
        let (cloud, marker) = match opt_out {
            "caster" => (cloud_at(&mut app, above_at), true),
            _ => (cloud_at(&mut app, Vec3::ZERO), false),
        };
        let mut entity = app.world_mut().entity_mut(cloud);
        if marker {
            entity.insert(NotShadowCaster);
        } else {
            entity.insert(NotShadowReceiver);
        }
        let mut recorder = FrameRecorder::default();
        render(&mut app, &mut recorder, 1);
        let gpu = light_volumes(&mut app, Vec3::ZERO);
        let error = max_relative_difference(&gpu[..alone.len()], &alone);
        assert!(error <= TOLERANCE, "not shadow {opt_out}: {error:e}");
        // The caster, out of view, shadows no cloud that takes shadows: it is not illuminated.
        let shaded = recorder.total(CloudPass::Shade);
        assert_eq!(shaded, 1, "not shadow {opt_out}");
    }
}

/// Two clouds that interpenetrate, under a sky alone (so that neither shadows the other): each
/// one's multiple scattering goes through both media, as the CPU reference's does; alone, a cloud
/// scatters far more where the other, darker one stands.
/// Clouds that interpenetrate along the light cast on each other both ways: a column of one lies
/// partly before, inside and past the other, which is looked up point by point there (and once
/// per column where the column lies wholly past it). Both light volumes equal the CPU's.
#[test]
fn interpenetrating_clouds_cast_on_each_other_point_by_point() {
    let (setup, casters) = stacked();
    let at = Vec3::new(0.3, 0.9, 0.2);
    let clouds = [setup.cloud(), caster(&casters[0], at, 16)];
    let (mut app, _) = spawn_clouds(&setup, &clouds);
    render(&mut app, &mut FrameRecorder::default(), 2);
    let swapped = [clouds[1], clouds[0]];
    for (translation, clouds) in [(Vec3::ZERO, &clouds), (at, &swapped)] {
        let gpu = light_volumes(&mut app, translation);
        let cpu = cpu_light_volumes(&setup, clouds);
        let error = max_relative_difference(&gpu[..cpu.len()], &cpu);
        assert!(
            error <= TOLERANCE,
            "light volume at {translation}: {error:e}"
        );
        let own = cpu_light_volumes(&setup, &clouds[..1]);
        let ratio = cpu.iter().sum::<f64>() / own.iter().sum::<f64>();
        assert!(
            ratio > 1.2,
            "at {translation}, the other casts too little: {ratio}"
        );
    }
}

#[test]
fn interpenetrating_clouds_scatter_through_each_others_media() {
    check_scattering_through_each_other(0);
}

/// As above, with coarse-grid cycles: the receiver's coarse grid takes the other's medium,
/// restricted like its own density (`coarse_grid.wgsl`, `restrict_media`).
#[test]
fn coarse_grid_cycles_scatter_through_each_others_media() {
    check_scattering_through_each_other(2);
}

fn check_scattering_through_each_other(cycles: u32) {
    let (mut setup, casters) = stacked();
    setup.lights.clear();
    setup.sky = Vec3::new(0.4, 0.6, 1.0);
    setup.medium.albedo = 0.99;
    setup.settings.scatter_coarse_cycles = cycles;
    let mut other = caster(&casters[0], Vec3::new(0.4, 0.3, -0.2), 12);
    other.medium.albedo = 0.5;
    let clouds = [setup.cloud(), other];
    let (mut app, _) = spawn_clouds(&setup, &clouds);
    render(&mut app, &mut FrameRecorder::default(), 2);
    let gpu = multiple_scattering(&mut app, Vec3::ZERO);
    let cpu = flat(&cpu_illumination(&setup, &clouds).multiple.total);
    let error = max_relative_difference(&gpu[..cpu.len()], &cpu);
    assert!(
        error <= TOLERANCE,
        "multiple scattering: {error:e} of its maximum"
    );
    let alone = flat(&cpu_illumination(&setup, &[setup.cloud()]).multiple.total);
    let change = max_relative_difference(&alone, &cpu);
    eprintln!("multiple scattering with the other's medium against alone: {change}");
    assert!(
        change > 0.1,
        "the other's medium changes too little: {change}"
    );
}
