//! The ground lights the clouds from below (docs/illumination.md §4, "The ground"): the map of
//! the light it reflects under a cloud, and the multiple scattering that takes it in, against
//! the CPU reference voxel by voxel and image by image; and its cost, one dispatch.

use bevy::prelude::*;
use bevy_particle_clouds::headless;
use bevy_particle_clouds::{
    CloudGround, CloudPass,
    reference::{
        ground::GroundLight,
        illumination::{CloudIllumination, PlacedCloud, illuminate_clouds_over_ground},
        metrics::max_relative_difference,
    },
    render::{pools::VolumePools, volumes::CloudVolumes},
};

use crate::common;
use crate::draw::{Setup, assert_images_match, cloud_setup, placement, reference, render};
use crate::illumination::{TOLERANCE, flat};

/// The draw tests' cloud (turned, two lights) under a blue sky, over a ground 1.5 m below it,
/// seen from slightly below.
fn ground_setup() -> Setup {
    let camera = Transform::from_xyz(0.3, -0.6, 4.0).looking_at(Vec3::ZERO, Vec3::Y);
    let mut setup = cloud_setup(21, camera);
    setup.sky = Vec3::new(0.1, 0.15, 0.3);
    setup.background = setup.sky;
    setup.ground = Some(CloudGround {
        height: -1.5,
        reflectance: Vec3::new(0.6, 0.45, 0.3),
    });
    setup
}

fn cpu_illumination(setup: &Setup, ground: Option<&CloudGround>) -> CloudIllumination {
    let cloud = PlacedCloud {
        particles: &setup.particles,
        medium: setup.medium,
        placement: placement(&setup.transform),
        settings: setup.settings,
    };
    let sky = setup.sky.as_dvec3();
    illuminate_clouds_over_ground(&[cloud], &setup.lights, sky, ground)
        .remove(0)
        .expect("a cloud with density")
}

/// The RGB of each texel of a GPU ground map (after its frame of 9 vec4).
fn map_radiance(floats: &[f32]) -> Vec<f64> {
    floats[9 * 4..]
        .chunks_exact(4)
        .flat_map(|c| [c[0], c[1], c[2]])
        .map(f64::from)
        .collect()
}

#[test]
fn a_cloud_over_a_lit_ground_equals_the_cpu_reference() {
    let setup = ground_setup();
    let (mut app, _, gpu) = render(&setup);
    assert_images_match(&gpu.image, &reference(&setup), "over a lit ground");

    let (map, multiple) = common::with_render_world(&mut app, |world| {
        let volumes = world
            .query::<&CloudVolumes>()
            .single(world)
            .expect("one cloud's volumes");
        let pool = world.resource::<VolumePools>().pool(&volumes.slot);
        (
            pool.ground(volumes.slot.index),
            pool.multiple(volumes.slot.index),
        )
    });
    let gpu_map = headless::floats(&headless::read_buffer_range(&mut app, &map).unwrap());
    let gpu_multiple =
        crate::illumination::rgb(&headless::read_buffer_range(&mut app, &multiple).unwrap());

    let ground = setup.ground.as_ref();
    let cpu = cpu_illumination(&setup, ground);
    let cpu_map = GroundLight::new(
        ground.unwrap(),
        placement(&setup.transform),
        &cpu.grid,
        &cpu.lights,
        setup.sky.as_dvec3(),
    );
    let map_error = max_relative_difference(&map_radiance(&gpu_map), &flat(&cpu_map.radiance));
    let n3 = cpu.grid.len();
    let error = max_relative_difference(&gpu_multiple[..3 * n3], &flat(&cpu.multiple.total));
    eprintln!("over a ground: map {map_error:e}, multiple scattering {error:e} of the maximum");
    assert!(map_error <= TOLERANCE, "ground map: {map_error:e}");
    assert!(error <= TOLERANCE, "multiple scattering: {error:e}");

    // The ground's light is real: it changes the multiple scattering by a good part of its
    // maximum (the underside, lit by the ground instead of the sky).
    let skylit = cpu_illumination(&setup, None);
    let change = max_relative_difference(&flat(&skylit.multiple.total), &flat(&cpu.multiple.total));
    eprintln!("the ground changes the multiple scattering by {change} of its maximum");
    assert!(change > 0.1, "the ground changes little: {change}");
}

/// The ground costs one dispatch per pool in each scattering stage, and nothing without it.
#[test]
fn the_ground_adds_one_dispatch_per_scattering() {
    let scatter = |ground: Option<CloudGround>| {
        let setup = Setup {
            ground,
            ..ground_setup()
        };
        let (_, _, gpu) = render(&setup);
        let frames = &gpu.frames.frames;
        let dispatches: u32 = frames
            .iter()
            .map(|f| f.dispatches(CloudPass::Scatter))
            .sum();
        let scattering = frames
            .iter()
            .filter(|f| f.dispatches(CloudPass::Scatter) > 0)
            .count();
        (dispatches, scattering as u32)
    };
    let (without, runs) = scatter(None);
    let (with, runs_with) = scatter(ground_setup().ground);
    assert!(runs > 0);
    assert_eq!(runs, runs_with, "frames that scatter");
    assert_eq!(
        with,
        without + runs,
        "scatter dispatches with a ground and without"
    );
}
