//! Clouds under Bevy's `Atmosphere` (`src/atmosphere.rs`): the sun reaches each cloud through the
//! atmosphere's transmittance, as it reaches Bevy's meshes. Against the same cloud without an
//! atmosphere, its lights' colours multiplied by that transmittance on the CPU, and against the
//! CPU billboard reference of that.

use bevy::{
    core_pipeline::{
        core_3d::{main_opaque_pass_3d, main_transparent_pass_3d},
        schedule::Core3d,
    },
    light::{Atmosphere, SunDisk, atmosphere::ScatteringMedium},
    pbr::main_transmissive_pass_3d,
    prelude::*,
    render::RenderApp,
};
use bevy_particle_clouds::render::cloud_target::draw_cloud_target;
use bevy_particle_clouds::{
    atmosphere::AtmosphereTransmittance,
    headless::{self, FrameRecorder},
    image_io::LinearImage,
    reference::metrics::max_relative_difference,
};
use std::any::TypeId;

use crate::draw::{Setup, assert_images_match, cloud_setup, reference, spawn};

/// Earth's radius, where Bevy places the planet's centre below the origin by default.
const EARTH: f32 = 6_360_000.0;

fn render(setup: &Setup, atmosphere: Option<ScatteringMedium>) -> LinearImage {
    let (mut app, target) = spawn(setup);
    if let Some(medium) = atmosphere {
        let world = app.world_mut();
        let medium = world.resource_mut::<Assets<ScatteringMedium>>().add(medium);
        world.spawn(Atmosphere::earth(medium));
    }
    let mut frames = FrameRecorder::default();
    // Steady means frames with no illumination work: under the atmosphere too, a still scene
    // re-lights nothing once lit (its transmittances are not integrated again).
    headless::render_until_steady(&mut app, &mut frames, target.drawable_clouds, 20).unwrap();
    headless::capture(&mut app, &mut frames, &target.image).unwrap()
}

#[test]
fn a_cloud_under_an_atmosphere_takes_the_sun_through_it() {
    let camera = Transform::from_xyz(0.3, 0.4, 4.0).looking_at(Vec3::ZERO, Vec3::Y);
    let mut setup = cloud_setup(21, camera);
    // A low sun, about 5.5° up, and a high one.
    setup.lights[0].direction = Vec3::new(-1.0, -0.1, -0.3);
    setup.lights[1].direction = Vec3::new(0.1, -1.0, 0.2);
    let medium = ScatteringMedium::earth(256, 256);
    let planet = GlobalTransform::from_translation(-Vec3::Y * EARTH);
    let air = AtmosphereTransmittance::new(&Atmosphere::earth(default()), &planet, &medium);
    let disk = SunDisk::EARTH.angular_size;
    let centre = setup.transform.translation;
    let tints: Vec<Vec3> = setup
        .lights
        .iter()
        .map(|l| air.towards_light(centre, l.direction.normalize(), disk))
        .collect();
    eprintln!(
        "transmittance to the low sun {}, to the high one {}",
        tints[0], tints[1]
    );
    // The low sun reaches the cloud red, the high one nearly white.
    assert!(
        tints[0].z < 0.3 * tints[0].x && tints[0].x < 0.9,
        "{}",
        tints[0]
    );
    assert!(tints[1].min_element() > 0.6, "{}", tints[1]);
    let under_air = render(&setup, Some(medium));
    for (light, tint) in setup.lights.iter_mut().zip(&tints) {
        light.irradiance *= *tint;
    }
    let tinted = render(&setup, None);
    // The same passes on the same numbers, but for the order of the computed draw's atomic adds
    // (voxelize sums in a fixed order).
    let channels = |image: &LinearImage| -> Vec<f64> {
        image.pixels.iter().flatten().map(|&v| v as f64).collect()
    };
    let difference = max_relative_difference(&channels(&under_air), &channels(&tinted));
    assert!(
        difference <= 1e-4,
        "under the atmosphere and with tinted lights: {difference} of the brightest channel apart"
    );
    assert_images_match(&under_air, &reference(&setup), "under the atmosphere");
}

/// `Core3d`'s systems in the order its built schedule runs them (its executor is single-threaded),
/// by type.
fn core_3d_order(app: &App) -> Vec<TypeId> {
    let schedules = app.sub_app(RenderApp).world().resource::<Schedules>();
    let core_3d = schedules.get(Core3d).expect("the Core3d schedule");
    core_3d
        .systems()
        .expect("Core3d has run")
        .map(|(_, system)| system.system_type())
        .collect()
}

/// Bevy draws its sky (`render_sky`, for a camera with `AtmosphereSettings`) between the opaque
/// and the transparent passes, where the computed draw composites the clouds too: the sky adds
/// its light over the background and multiplies what is there by the atmosphere's
/// transmittance, so clouds composited before it would be covered by the sky. Nothing but the
/// schedule's unspecified order separated the two (and the plugin's systems, added after Bevy's,
/// tend to run first); the plugin's build pass runs the composite after every system placed
/// between the two passes but the transmissive pass, which it precedes (`render/after_sky.rs`).
/// `render_sky` is private and systems are unnamed without Bevy's `debug` feature, so this
/// checks the composite against every system the schedule runs between the two passes, of which
/// the sky is one. (Rendering Bevy's atmosphere itself crashes Debian 12's lavapipe, Mesa
/// 22.3.6, inside the driver, with or without clouds, so the order is checked in the schedule,
/// not in an image.)
#[test]
fn the_clouds_are_composited_after_bevys_sky() {
    let camera = Transform::from_xyz(0.0, 0.3, 4.0).looking_at(Vec3::ZERO, Vec3::Y);
    let setup = cloud_setup(21, camera);
    let (mut app, target) = spawn(&setup);
    let mut frames = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut frames, target.drawable_clouds, 20).unwrap();
    let order = core_3d_order(&app);
    let at = |ty: TypeId, name: &str| {
        order
            .iter()
            .position(|&t| t == ty)
            .unwrap_or_else(|| panic!("no {name} in Core3d"))
    };
    let opaque = at(main_opaque_pass_3d.system_type_id(), "opaque pass");
    let transparent = at(
        main_transparent_pass_3d.system_type_id(),
        "transparent pass",
    );
    let composite = at(draw_cloud_target.system_type_id(), "cloud composite");
    let transmissive = at(
        main_transmissive_pass_3d.system_type_id(),
        "transmissive pass",
    );
    let others: Vec<usize> = (opaque + 1..transparent)
        .filter(|&i| i != composite && i != transmissive)
        .collect();
    eprintln!(
        "Core3d: opaque {opaque}, others {others:?}, composite {composite}, transmissive \
         {transmissive}, transparent {transparent}"
    );
    assert!(
        !others.is_empty(),
        "no system between the opaque and transparent passes but ours and the transmissive one: \
         where is Bevy's sky?"
    );
    assert!(
        others.iter().all(|&i| i < composite) && composite < transmissive,
        "Core3d runs the cloud composite (system {composite}) before systems {others:?} between \
         the opaque ({opaque}) and the transparent ({transparent}) passes, or after the \
         transmissive pass ({transmissive})"
    );
}
