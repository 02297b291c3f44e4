//! The warm restart of the scattering on the GPU against the f64 CPU reference: when only the
//! light moves, the scattering restarts from the solution the volumes hold
//! (`warm_scatter_iterations`), and the first frame the light stays still settles it with the
//! full series. Under a black sky and under a blue one, which enters the restart's first sweep;
//! and for an anisotropic medium, whose volumes hold angular moments beside their means.

use bevy::prelude::*;
use bevy_particle_clouds::headless::{self, FrameRecorder};
use bevy_particle_clouds::{
    CloudPass, CloudQualitySettings, CloudSkyLight, Medium, Particle, ScatterStencil,
    reference::{
        illumination::{LocalLight, MultipleScattering, illuminate_under_sky, scatter_warm_medium},
        metrics::max_relative_difference,
    },
    render::{pools::VolumePools, volumes::CloudVolumes},
};

// The illumination tests' tolerance: f32 storage and arbitrary summation order.
use crate::{
    common,
    illumination::{TOLERANCE, flat, flat_entries, random_particles, rgb},
};

/// Each part of a multiple-scattering volume the GPU holds (the means, and with moments the
/// flux and the quadrupole) against the CPU's, relative to its own maximum: the largest.
pub(crate) fn difference(gpu: &[f64], cpu: &MultipleScattering) -> f64 {
    let mut parts = vec![flat(&cpu.total)];
    if !cpu.flux.is_empty() {
        parts.extend([flat_entries(&cpu.flux), flat_entries(&cpu.quadrupole)]);
    }
    assert_eq!(gpu.len(), parts.iter().map(Vec::len).sum::<usize>());
    let mut at = 0;
    parts
        .iter()
        .map(|part| {
            at += part.len();
            max_relative_difference(&gpu[at - part.len()..at], part)
        })
        .fold(0.0, f64::max)
}

/// The one cloud's `multiple` volume as the GPU holds it, its moments included.
pub(crate) fn gpu_multiple(app: &mut App) -> Vec<f64> {
    let range = common::with_render_world(app, |world| {
        let volumes = world
            .query::<&CloudVolumes>()
            .single(world)
            .expect("one cloud's volumes");
        let pool = world.resource::<VolumePools>().pool(&volumes.slot);
        pool.multiple(volumes.slot.index)
    });
    rgb(&headless::read_buffer_range(app, &range).unwrap())
}

/// One cloud at the origin, lit by one light (its travel direction and irradiance) under the
/// sky `sky`, seen by a 16×16 camera 6 m away: the app, and the light's entity.
pub(crate) fn lit_cloud_app(
    sky: Vec3,
    (direction, irradiance): (Vec3, Vec3),
    (particles, medium, settings): (&[Particle], Medium, CloudQualitySettings),
) -> (App, Entity) {
    let mut app = common::headless_app();
    app.insert_resource(CloudSkyLight::from_radiance(sky));
    let image = headless::float_target(&mut app, 16, 16);
    let eye = Transform::from_xyz(0.0, 0.0, 6.0).looking_at(Vec3::ZERO, Vec3::Y);
    headless::spawn_linear_camera(&mut app, image, eye, 60.0, Vec3::ZERO);
    let light = headless::spawn_light(&mut app, direction, irradiance);
    let cloud = particles.to_vec();
    headless::spawn_cloud(&mut app, cloud, medium, settings, Transform::IDENTITY);
    (app, light)
}

#[test]
fn a_moving_light_restarts_warm_and_a_still_one_settles() {
    let turn = Vec3::new(0.5, -0.9, 0.1);
    check_warm_restart(Vec3::ZERO, 0.0, turn);
    check_warm_restart(Vec3::new(0.1, 0.2, 0.4), 0.0, turn);
}

#[test]
fn an_anisotropic_medium_restarts_warm_with_its_moments() {
    // The transformed medium is thinner and its series shorter: a larger turn, so that the
    // warm frame is not yet the full series' result.
    check_warm_restart(Vec3::new(0.1, 0.2, 0.4), 0.6, Vec3::new(1.0, -0.3, 0.6));
}

/// The light turns from straight down-ish to `turn`.
fn check_warm_restart(sky: Vec3, anisotropy: f32, turn: Vec3) {
    let particles = random_particles(3, 60);
    let medium = Medium {
        extinction: 8.0,
        albedo: 0.95,
        anisotropy,
    };
    let settings = CloudQualitySettings {
        warm_scatter_iterations: 3,
        ..common::quality(16, 8)
    };
    let (a, b) = (Vec3::new(0.2, -1.0, 0.1), turn);
    let irradiance = Vec3::new(1.0, 0.9, 0.8);

    let (mut app, light) = lit_cloud_app(sky, (a, irradiance), (&particles, medium, settings));
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 1, 20).unwrap();

    // The light turns: one frame shades, gathers and restarts warm (3 iterations).
    *app.world_mut().get_mut::<Transform>(light).unwrap() =
        Transform::default().looking_to(b, Vec3::Y);
    let warm_frame = recorder.frame(&mut app).unwrap().clone();
    assert_eq!(warm_frame.runs(CloudPass::Shade), 1);
    assert_eq!(warm_frame.runs(CloudPass::Scatter), 3);
    // 3 iterations of 13 sweeps, the two accumulating ones followed by their accumulation, the
    // closure's two; the warm start and the correction around the first, not-accumulating one.
    assert_eq!(
        warm_frame.dispatches(CloudPass::Scatter),
        3 * 13 + 2 + 2 + 2
    );
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
    let restarted = scatter_warm_medium(
        &after.grid,
        after.k_local,
        (after.albedo, after.anisotropy),
        ScatterStencil::DiscreteOrdinates,
        &after.source,
        &before.multiple.moments(),
        sky.as_dvec3(),
        3,
    );
    let error = difference(&warm, &restarted);
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
    let error = difference(&settled, &after.multiple);
    assert!(error <= TOLERANCE, "settled: GPU differs by {error:e}");
    assert_eq!(recorder.frame(&mut app).unwrap().work(), 0);
}
