//! Clouds under Bevy's `Atmosphere` (`src/atmosphere.rs`): the sun reaches each cloud through the
//! atmosphere's transmittance, as it reaches Bevy's meshes. Against the same cloud without an
//! atmosphere, its lights' colours multiplied by that transmittance on the CPU, and against the
//! CPU billboard reference of that.

use bevy::{
    light::{Atmosphere, SunDisk, atmosphere::ScatteringMedium},
    prelude::*,
};
use bevy_particle_clouds::{
    atmosphere::AtmosphereTransmittance,
    headless::{self, FrameRecorder},
    image_io::LinearImage,
    reference::metrics::max_relative_difference,
};

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
    // The same passes on the same numbers, but for the order of voxelize's atomic adds.
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
