//! The warm restart of the scattering on the GPU against the f64 CPU reference: when only the
//! light moves, the scattering restarts from the solution the volumes hold
//! (`warm_scatter_iterations`), and the first frame the light stays still settles it with the
//! full series. Under a black sky and under a blue one, which enters the restart's first sweep.

use bevy::prelude::*;
use bevy_particle_clouds::headless::{self, FrameRecorder};
use bevy_particle_clouds::{
    CloudPass, CloudQualitySettings, CloudSkyLight, Medium, ScatterStencil,
    reference::{
        illumination::{LocalLight, illuminate_under_sky, scatter_warm},
        metrics::max_relative_difference,
    },
    render::{pools::VolumePools, volumes::CloudVolumes},
};

// The illumination tests' tolerance: f32 storage and arbitrary summation order.
use crate::{
    common,
    illumination::{TOLERANCE, flat, random_particles, rgb},
};

fn gpu_multiple(app: &mut App) -> Vec<f64> {
    let range = common::with_render_world(app, |world| {
        let volumes = world
            .query::<&CloudVolumes>()
            .single(world)
            .expect("one cloud's volumes");
        let pool = world.resource::<VolumePools>().pool(&volumes.slot);
        pool.volume(&pool.multiple, volumes.slot.index)
    });
    rgb(&headless::read_buffer_range(app, &range).unwrap())
}

#[test]
fn a_moving_light_restarts_warm_and_a_still_one_settles() {
    check_warm_restart(Vec3::ZERO);
    check_warm_restart(Vec3::new(0.1, 0.2, 0.4));
}

fn check_warm_restart(sky: Vec3) {
    let particles = random_particles(3, 60);
    let medium = Medium {
        extinction: 8.0,
        albedo: 0.95,
        ..Default::default()
    };
    let settings = CloudQualitySettings {
        warm_scatter_iterations: 3,
        ..common::quality(16, 8)
    };
    let (a, b) = (Vec3::new(0.2, -1.0, 0.1), Vec3::new(0.5, -0.9, 0.1));
    let irradiance = Vec3::new(1.0, 0.9, 0.8);

    let mut app = common::headless_app();
    app.insert_resource(CloudSkyLight::from_radiance(sky));
    let image = headless::float_target(&mut app, 16, 16);
    let eye = Transform::from_xyz(0.0, 0.0, 6.0).looking_at(Vec3::ZERO, Vec3::Y);
    headless::spawn_linear_camera(&mut app, image, eye, 60.0, Vec3::ZERO);
    let light = headless::spawn_light(&mut app, a, irradiance);
    headless::spawn_cloud(
        &mut app,
        particles.clone(),
        medium,
        settings,
        Transform::IDENTITY,
    );
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 1, 20).unwrap();

    // The light turns: one frame shades, gathers and restarts warm (3 iterations).
    *app.world_mut().get_mut::<Transform>(light).unwrap() =
        Transform::default().looking_to(b, Vec3::Y);
    let warm_frame = recorder.frame(&mut app).unwrap().clone();
    assert_eq!(warm_frame.runs(CloudPass::Shade), 1);
    assert_eq!(warm_frame.runs(CloudPass::Scatter), 3);
    // The warm start, the not-accumulating sweep and the correction add 2 dispatches.
    assert_eq!(warm_frame.dispatches(CloudPass::Scatter), 3 * 13 + 2 + 2);
    let warm = gpu_multiple(&mut app);

    let cpu = |direction: Vec3| {
        let light = LocalLight {
            direction: direction.as_dvec3(),
            irradiance: irradiance.as_dvec3(),
        };
        illuminate_under_sky(
            &particles,
            &medium,
            1.0,
            &[light],
            sky.as_dvec3(),
            &settings,
        )
        .unwrap()
    };
    let (before, after) = (cpu(a), cpu(b));
    let restarted = scatter_warm(
        &after.grid,
        after.k_local,
        after.albedo,
        ScatterStencil::DiscreteOrdinates,
        &after.source,
        &before.multiple.total,
        sky.as_dvec3(),
        3,
    );
    let error = max_relative_difference(&warm, &flat(&restarted.total));
    assert!(error <= TOLERANCE, "warm restart: GPU differs by {error:e}");
    // It is not the full series' result (else this test could not tell them apart) ...
    let full = flat(&after.multiple.total);
    let apart = max_relative_difference(&flat(&restarted.total), &full);
    assert!(
        apart > 10.0 * TOLERANCE,
        "warm and full differ by {apart:e} only"
    );
    // ... but far closer to it than where it started. (Under the sky, whose light did not move,
    // less so: the correction's closure also extrapolates what is left of the sky's series.)
    let moved = max_relative_difference(&flat(&before.multiple.total), &full);
    let bound = if sky == Vec3::ZERO { 0.25 } else { 0.5 };
    assert!(apart < bound * moved, "warm {apart:e}, start {moved:e}");

    // The light stays: the full series settles it, then nothing runs.
    let settle = recorder.frame(&mut app).unwrap().clone();
    assert_eq!(
        (
            settle.runs(CloudPass::Shade),
            settle.runs(CloudPass::Scatter)
        ),
        (0, 8)
    );
    let settled = gpu_multiple(&mut app);
    let error = max_relative_difference(&settled, &full);
    assert!(error <= TOLERANCE, "settled: GPU differs by {error:e}");
    assert_eq!(recorder.frame(&mut app).unwrap().work(), 0);
}
