//! Numerical stress: extreme inputs render finite, non-negative images within the documented
//! bound (docs/illumination.md §4), and nothing panics or hangs.
//!
//! Bound: compositing is a convex blend, so every pixel lies between the background and the
//! brightest particle colour, `albedo * max A <= albedo * sum(E) / (4 pi) * (M + 1)`.

use std::f32::consts::PI;

use bevy::prelude::*;
use bevy_particle_clouds::headless::{self, FrameRecorder, SceneTarget};
use bevy_particle_clouds::{
    CloudPass, CloudQualitySettings, CloudSkyLight, LightSample, Medium, Particle, ParticleCloud,
    Particles, generators, image_io::LinearImage,
};

use crate::common;

struct Case {
    particles: Vec<Particle>,
    medium: Medium,
    lights: Vec<LightSample>,
    settings: CloudQualitySettings,
    eye: Vec3,
    look_at: Vec3,
}

impl Case {
    fn new(particles: Vec<Particle>) -> Self {
        Self {
            particles,
            medium: Medium {
                extinction: 5.0,
                albedo: 0.9,
                ..Default::default()
            },
            lights: vec![LightSample {
                direction: Vec3::new(-0.4, -1.0, -0.3),
                irradiance: Vec3::ONE,
            }],
            settings: common::quality(16, 4),
            eye: Vec3::new(0.0, 0.3, 5.0),
            look_at: Vec3::ZERO,
        }
    }
}

const BACKGROUND: Vec3 = Vec3::new(0.1, 0.2, 0.3);

fn ball() -> Vec<Particle> {
    generators::sphere(1.0, 0.3, 60, 3).particles
}

/// Renders the case; returns the image and whether the cloud was drawn in the final frame.
fn render(case: &Case) -> (LinearImage, u32) {
    let mut app = common::headless_app();
    common::draw_every_frame(&mut app);
    let image = headless::float_target(&mut app, 32, 24);
    let camera = headless::spawn_linear_camera(
        &mut app,
        image.clone(),
        Transform::from_translation(case.eye).looking_at(case.look_at, Vec3::Y),
        50.0,
        BACKGROUND,
    );
    for light in &case.lights {
        headless::spawn_light(&mut app, light.direction, light.irradiance);
    }
    headless::spawn_cloud(
        &mut app,
        case.particles.clone(),
        case.medium,
        case.settings,
        Transform::IDENTITY,
    );
    let target = SceneTarget {
        image,
        width: 32,
        height: 24,
        camera,
        drawable_clouds: 0,
    };
    let mut frames = FrameRecorder::default();
    for _ in 0..4 {
        frames.frame(&mut app).unwrap();
    }
    let image = headless::capture(&mut app, &mut frames, &target.image).unwrap();
    let drawn = frames.frames.last().unwrap().runs(CloudPass::Draw);
    (image, drawn)
}

fn assert_bounded(case: &Case, what: &str) -> (LinearImage, u32) {
    let (image, drawn) = render(case);
    let irradiance: f32 = case.lights.iter().map(|l| l.irradiance.max_element()).sum();
    let bound = BACKGROUND.max_element().max(
        case.medium.albedo * irradiance / (4.0 * PI)
            * (case.settings.scatter_iterations + 1) as f32,
    ) * 1.01
        + 1e-3;
    for (i, p) in image.pixels.iter().enumerate() {
        for &v in &p[..3] {
            assert!(
                v.is_finite() && v >= 0.0 && v <= bound,
                "{what}: pixel {i} = {p:?} outside [0, {bound}]"
            );
        }
    }
    (image, drawn)
}

fn differs_from_background(image: &LinearImage) -> bool {
    image
        .pixels
        .iter()
        .any(|p| (p[0] - BACKGROUND.x).abs() > 1e-3 || (p[2] - BACKGROUND.z).abs() > 1e-3)
}

#[test]
fn albedo_one_with_a_thousand_iterations_stays_bounded() {
    let mut case = Case::new(ball());
    case.medium = Medium {
        extinction: 20.0,
        albedo: 1.0,
        ..Default::default()
    };
    case.settings = common::quality(16, 1000);
    let (image, drawn) = assert_bounded(&case, "albedo 1");
    assert_eq!(drawn, 1);
    assert!(differs_from_background(&image));
}

#[test]
fn extinction_of_ten_thousand() {
    let mut case = Case::new(ball());
    case.medium.extinction = 1e4;
    let (image, _) = assert_bounded(&case, "extinction 1e4");
    assert!(
        differs_from_background(&image),
        "an opaque cloud covers the background"
    );
}

/// Extinctions up to f32's limit, where `σ_t ρ h` and the optical depths overflow to infinity:
/// finite, bounded, and opaque (docs/limitations.md: such media draw dark, with a warning).
#[test]
fn extinctions_at_the_limit_of_f32() {
    for extinction in [1e30, f32::MAX] {
        let mut case = Case::new(ball());
        case.medium.extinction = extinction;
        let what = format!("extinction {extinction:e}");
        let (image, drawn) = assert_bounded(&case, &what);
        assert_eq!(drawn, 1, "{what}");
        assert!(
            differs_from_background(&image),
            "{what}: covers the background"
        );
    }
}

#[test]
fn tiny_and_huge_particles() {
    let tiny = Case {
        eye: Vec3::new(0.0, 0.0, 0.5),
        ..Case::new(vec![
            Particle {
                position: Vec3::ZERO,
                radius: 1e-4,
                density: 1.0
            };
            3
        ])
    };
    assert_bounded(&tiny, "radius 1e-4");
    let huge = Case {
        eye: Vec3::new(0.0, 0.0, 5e4),
        ..Case::new(vec![
            Particle {
                position: Vec3::ZERO,
                radius: 1e4,
                density: 1.0,
            },
            Particle {
                position: Vec3::new(5e3, 0.0, 0.0),
                radius: 1e4,
                density: 0.5,
            },
        ])
    };
    let (image, _) = assert_bounded(
        &Case {
            medium: Medium {
                extinction: 1e-3,
                albedo: 0.9,
                ..Default::default()
            },
            ..huge
        },
        "radius 1e4",
    );
    assert!(differs_from_background(&image));
}

#[test]
fn five_thousand_particles_at_one_point() {
    let case = Case::new(vec![
        Particle {
            position: Vec3::new(0.1, 0.2, 0.3),
            radius: 0.5,
            density: 1.0
        };
        5000
    ]);
    let (image, _) = assert_bounded(&case, "5000 coincident particles");
    assert!(differs_from_background(&image));
}

#[test]
fn lights_along_axes_the_view_and_from_below() {
    let directions = [
        Vec3::NEG_Y,
        Vec3::Y,
        Vec3::X,
        Vec3::NEG_X,
        Vec3::Z,
        Vec3::NEG_Z,
        Vec3::new(0.0, -0.3, -5.0),
    ];
    let mut case = Case::new(ball());
    case.lights = directions
        .iter()
        .map(|&d| LightSample {
            direction: d,
            irradiance: Vec3::splat(0.3),
        })
        .collect();
    assert_bounded(&case, "axis lights");
    for direction in directions {
        case.lights = vec![LightSample {
            direction,
            irradiance: Vec3::ONE,
        }];
        let (image, _) = assert_bounded(&case, &format!("light {direction}"));
        assert!(differs_from_background(&image));
    }
}

#[test]
fn sixteen_lights() {
    let mut rng = generators::SplitMix64::new(16);
    let mut case = Case::new(ball());
    case.lights = (0..16)
        .map(|_| LightSample {
            direction: rng.in_unit_ball() + Vec3::new(0.0, -0.1, 0.0),
            irradiance: Vec3::splat(0.2),
        })
        .collect();
    let (_, drawn) = assert_bounded(&case, "16 lights");
    assert_eq!(drawn, 1);
}

#[test]
fn no_lights_empty_clouds_and_a_single_particle() {
    let mut dark = Case::new(ball());
    dark.lights.clear();
    let (image, drawn) = assert_bounded(&dark, "no lights");
    assert_eq!(drawn, 1, "an unlit cloud still absorbs the background");
    assert!(
        image.pixels.iter().any(|p| p[2] < BACKGROUND.z - 0.01),
        "the cloud darkens the background"
    );

    for (what, particles) in [
        ("no particles", vec![]),
        (
            "zero density",
            vec![Particle {
                position: Vec3::ZERO,
                radius: 1.0,
                density: 0.0,
            }],
        ),
    ] {
        let (image, drawn) = assert_bounded(&Case::new(particles), what);
        assert_eq!(drawn, 0, "{what}: nothing to draw");
        assert!(!differs_from_background(&image), "{what}: transparent");
    }
    let mut transparent = Case::new(ball());
    transparent.medium.extinction = 0.0;
    let (image, drawn) = assert_bounded(&transparent, "zero extinction");
    assert_eq!(drawn, 0);
    assert!(!differs_from_background(&image));

    let (image, drawn) = assert_bounded(
        &Case::new(vec![Particle {
            position: Vec3::ZERO,
            radius: 0.8,
            density: 1.0,
        }]),
        "one particle",
    );
    assert_eq!(drawn, 1);
    assert!(differs_from_background(&image));
}

#[test]
fn camera_inside_the_cloud() {
    let case = Case {
        eye: Vec3::new(0.0, 0.0, 0.1),
        look_at: Vec3::new(0.0, 0.0, -1.0),
        ..Case::new(ball())
    };
    let (image, drawn) = assert_bounded(&case, "camera inside");
    assert_eq!(drawn, 1);
    assert!(differs_from_background(&image));
}

#[test]
fn invalid_values_through_the_api_are_refused_and_others_render() {
    let mut app = common::headless_app();
    common::draw_every_frame(&mut app);
    let image = headless::float_target(&mut app, 16, 16);
    headless::spawn_linear_camera(
        &mut app,
        image.clone(),
        Transform::from_xyz(0.0, 0.0, 8.0).looking_at(Vec3::ZERO, Vec3::Y),
        60.0,
        BACKGROUND,
    );
    headless::spawn_light(&mut app, Vec3::NEG_Y, Vec3::ONE);
    let spawn = |app: &mut App, particles: Vec<Particle>, medium: Medium, x: f32| {
        let handle = app
            .world_mut()
            .resource_mut::<Assets<Particles>>()
            .add(Particles::new(particles));
        app.world_mut().spawn((
            ParticleCloud::new(handle).with_medium(medium),
            Transform::from_xyz(x, 0.0, 0.0),
        ));
    };
    let good = Particle {
        position: Vec3::ZERO,
        radius: 0.5,
        density: 1.0,
    };
    spawn(
        &mut app,
        vec![Particle {
            position: Vec3::new(f32::NAN, 0.0, 0.0),
            ..good
        }],
        Medium::default(),
        -2.0,
    );
    spawn(
        &mut app,
        vec![Particle {
            radius: -1.0,
            ..good
        }],
        Medium::default(),
        -1.0,
    );
    spawn(
        &mut app,
        vec![good],
        Medium {
            extinction: 1.0,
            albedo: 2.0,
            ..Default::default()
        },
        0.0,
    );
    spawn(
        &mut app,
        vec![good],
        Medium {
            extinction: f32::INFINITY,
            albedo: 0.5,
            ..Default::default()
        },
        1.0,
    );
    spawn(
        &mut app,
        vec![good],
        Medium {
            extinction: 1.0,
            albedo: 0.5,
            anisotropy: 1.0,
        },
        3.0,
    );
    spawn(
        &mut app,
        vec![good],
        Medium {
            extinction: 1.0,
            albedo: 0.5,
            ..Default::default()
        },
        2.0,
    );
    // A sky that is not finite is refused (taken as black), and so is a ground beyond the
    // range (taken as none): the valid cloud still renders.
    app.insert_resource(CloudSkyLight::from_radiance(Vec3::new(0.1, f32::NAN, -1.0)));
    app.insert_resource(bevy_particle_clouds::CloudGround {
        height: f32::NEG_INFINITY,
        reflectance: Vec3::new(0.3, 2.0, f32::NAN),
    });
    let mut frames = FrameRecorder::default();
    for _ in 0..5 {
        frames.frame(&mut app).unwrap();
    }
    assert_eq!(
        frames.frames.last().unwrap().runs(CloudPass::Draw),
        1,
        "only the valid cloud is drawn"
    );
    let shot = headless::capture(&mut app, &mut frames, &image).unwrap();
    assert!(
        shot.pixels.iter().flatten().all(|v| v.is_finite()),
        "a refused sky or ground leaves no NaN"
    );
}

/// A light whose irradiance is negative in one channel or NaN is refused (with a warning naming
/// the field) and lights nothing: the image is the one without it, and the valid light still
/// lights the cloud.
#[test]
fn a_broken_light_is_skipped_and_the_valid_one_still_lights_the_cloud() {
    let valid = Case::new(ball());
    let mut broken = Case::new(ball());
    broken.lights.extend([
        LightSample {
            direction: Vec3::new(0.5, -1.0, 0.2),
            irradiance: Vec3::new(1.0, -0.5, 1.0),
        },
        LightSample {
            direction: Vec3::X,
            irradiance: Vec3::new(f32::NAN, 1.0, 1.0),
        },
    ]);
    let (expected, _) = render(&valid);
    let (image, drawn) = assert_bounded(&broken, "broken lights");
    assert_eq!(drawn, 1);
    assert!(differs_from_background(&image));
    for (i, (p, q)) in image.pixels.iter().zip(&expected.pixels).enumerate() {
        for c in 0..3 {
            assert!(
                (p[c] - q[c]).abs() <= 1e-4 * q[c].abs().max(1e-2),
                "pixel {i}: {p:?} with the broken lights, {q:?} without"
            );
        }
    }
}
