//! The GPU illumination volumes against the f64 CPU reference (docs/illumination.md), voxel by
//! voxel: the fine and the scattering grid's density, each light's optical depth, the scattering
//! source, the closure's order ratio and the multiple scattering.
//!
//! Storage is 32-bit float everywhere (RGBA32F / R32F buffers). The GPU sums in f32 with float
//! atomics in arbitrary order and multiplies `n` slice attenuations, so its error relative to the
//! volume's maximum stays within ~`n * 2^-23`; the tests allow 2e-4 of the maximum.

use bevy::{math::DVec3, prelude::*, render::renderer::RenderDevice};
use bevy_particle_clouds::headless::{self, FrameRecorder, SceneTarget};
use bevy_particle_clouds::{
    CloudQualitySettings, CloudSkyLight, LightSample, Medium, Particle, ScatterStencil,
    generators::SplitMix64,
    reference::{
        illumination::{LocalLight, SeriesClosure, illuminate_at_light_resolution},
        metrics::max_relative_difference,
    },
    render::{
        pools::{VolumePools, VolumeShape},
        volumes::CloudVolumes,
    },
};

use crate::common;

pub(crate) const TOLERANCE: f64 = 2e-4;

/// Largest difference of the series closure's coefficients, relative to the largest.
const CLOSURE_TOLERANCE: f64 = 1e-2;

struct Case {
    particles: Vec<Particle>,
    medium: Medium,
    lights: Vec<LightSample>,
    transform: Transform,
    settings: CloudQualitySettings,
}

/// A CPU volume of RGB as flat floats, like [`rgb`]'s.
pub(crate) fn flat(v: &[bevy::math::DVec3]) -> Vec<f64> {
    v.iter().flat_map(|c| c.to_array()).collect()
}

/// A CPU volume of per-voxel moments (a flux, a quadrupole) as flat floats, laid out like the
/// GPU's: voxel by voxel, entry by entry, RGB.
pub(crate) fn flat_entries<const K: usize>(v: &[[bevy::math::DVec3; K]]) -> Vec<f64> {
    v.iter().flatten().flat_map(|c| c.to_array()).collect()
}

pub(crate) fn random_particles(seed: u64, count: usize) -> Vec<Particle> {
    let mut rng = SplitMix64::new(seed);
    (0..count)
        .map(|_| Particle {
            position: rng.in_unit_ball() * Vec3::new(1.0, 0.6, 0.8),
            radius: 0.05 + 0.35 * rng.next_f32(),
            density: 0.2 + rng.next_f32(),
        })
        .collect()
}

fn random_direction(rng: &mut SplitMix64) -> Vec3 {
    rng.in_unit_ball().try_normalize().unwrap_or(Vec3::NEG_Y)
}

/// The RGB of an RGBA f32 volume.
pub(crate) fn rgb(bytes: &[u8]) -> Vec<f64> {
    headless::floats(bytes)
        .chunks_exact(4)
        .flat_map(|c| [c[0], c[1], c[2]])
        .map(f64::from)
        .collect()
}

/// The GPU volumes of `case` under a sky of radiance `sky` against the CPU reference.
fn check(case: Case, sky: Vec3) {
    let mut app = common::headless_app();
    app.insert_resource(CloudSkyLight::from_radiance(sky));
    let image = headless::float_target(&mut app, 16, 16);
    let camera = headless::spawn_linear_camera(
        &mut app,
        image.clone(),
        Transform::from_translation(case.transform.translation + Vec3::new(0.0, 0.0, 6.0))
            .looking_at(case.transform.translation, Vec3::Y),
        60.0,
        Vec3::ZERO,
    );
    for light in &case.lights {
        headless::spawn_light(&mut app, light.direction, light.irradiance);
    }
    headless::spawn_cloud(
        &mut app,
        case.particles.clone(),
        case.medium,
        case.settings,
        case.transform,
    );
    let target = SceneTarget {
        image,
        width: 16,
        height: 16,
        camera,
        drawable_clouds: 1,
    };
    headless::render_until_steady(
        &mut app,
        &mut FrameRecorder::default(),
        target.drawable_clouds,
        20,
    )
    .unwrap();

    let (m, max_binding) = common::with_render_world(&mut app, |world| {
        let volumes = world.query::<&CloudVolumes>().single(world).unwrap();
        let limits = world.resource::<RenderDevice>().limits();
        (
            volumes.params.light_n,
            limits.max_storage_buffer_binding_size,
        )
    });
    let settings = case.settings;
    assert_eq!(
        m,
        expected_light_resolution(&case, max_binding),
        "the fine grid in effect, under a storage binding of {max_binding} bytes"
    );
    let (fine_density, density, depths, source, ratio, multiple) =
        common::with_render_world(&mut app, |world| {
            let volumes = world
                .query::<&CloudVolumes>()
                .single(world)
                .expect("one cloud's volumes");
            let pool = world.resource::<VolumePools>().pool(&volumes.slot);
            let slot = volumes.slot.index;
            (
                pool.fine_density(slot),
                pool.density(slot),
                pool.optical_depth(slot),
                pool.source(slot),
                pool.order_ratio(slot),
                pool.multiple(slot),
            )
        });
    let read_f64 = |app: &mut App, range| -> Vec<f64> {
        headless::floats(&headless::read_buffer_range(app, range).unwrap())
            .into_iter()
            .map(f64::from)
            .collect()
    };
    let gpu_fine_density = read_f64(&mut app, &fine_density);
    let gpu_density = read_f64(&mut app, &density);
    let gpu_depths = read_f64(&mut app, &depths);
    let gpu_source = rgb(&headless::read_buffer_range(&mut app, &source).unwrap());
    let gpu_ratio = rgb(&headless::read_buffer_range(&mut app, &ratio).unwrap());
    let gpu_multiple = rgb(&headless::read_buffer_range(&mut app, &multiple).unwrap());

    let rotation = case.transform.rotation.as_dquat();
    let lights: Vec<LocalLight> = case
        .lights
        .iter()
        .map(|l| LocalLight::from_world(l, rotation))
        .collect();
    let scale = case.transform.scale.max_element() as f64;
    let cpu = illuminate_at_light_resolution(
        &case.particles,
        &case.medium,
        scale,
        &lights,
        sky.as_dvec3(),
        &settings,
        m,
    )
    .expect("a cloud with density");

    // The CPU's orders closed with the GPU's coefficients: those are checked on their own
    // below, and a difference within their tolerance would move the sum by up to the tail's
    // share of it (0.2 % of its maximum seen on an NVIDIA H200).
    let gpu_closure = SeriesClosure {
        last: DVec3::new(gpu_ratio[0], gpu_ratio[1], gpu_ratio[2]),
        before: DVec3::new(gpu_ratio[3], gpu_ratio[4], gpu_ratio[5]),
    };
    let cpu_total = cpu
        .multiple
        .total_closed_with(&gpu_closure)
        .unwrap_or_else(|| cpu.multiple.total.clone());
    let n3 = (settings.volume_resolution as usize).pow(3);
    let m3 = (m as usize).pow(3);
    let cpu_depths: Vec<f64> = cpu
        .lights
        .iter()
        .flat_map(|(v, _)| v.optical_depth.iter().copied())
        .collect();
    let mut errors = vec![
        (
            "fine density",
            max_relative_difference(&gpu_fine_density[..m3], &cpu.fine.rho),
        ),
        (
            "density",
            max_relative_difference(&gpu_density[..n3], &cpu.grid.rho),
        ),
        (
            "optical depth",
            max_relative_difference(&gpu_depths[..m3 * cpu.lights.len()], &cpu_depths),
        ),
        (
            "source",
            max_relative_difference(&gpu_source[..3 * n3], &flat(&cpu.source.mean)),
        ),
        (
            "multiple",
            max_relative_difference(&gpu_multiple[..3 * n3], &flat(&cpu_total)),
        ),
    ];
    if settings.scatter_iterations > 0 {
        // The tail's coefficients of S_M and S_{M-1}. A two-mode fit takes differences of the
        // orders' size ratios, which f32 orders move: measured up to 0.4 % in these cases.
        let closure = cpu.multiple.closure;
        let coefficients = [closure.last.to_array(), closure.before.to_array()].concat();
        let error = max_relative_difference(&gpu_ratio[..6], &coefficients);
        assert!(
            error <= CLOSURE_TOLERANCE,
            "closure: GPU {:?} against the CPU's {closure:?}",
            &gpu_ratio[..6]
        );
    }
    // An anisotropic medium's moments: after the n³ means, 3 vec4 of flux per voxel, then 5 of
    // quadrupole, in the source as in `multiple`.
    let moments = case.medium.anisotropy != 0.0;
    assert_eq!(
        (gpu_multiple.len() == 27 * n3, gpu_source.len() == 27 * n3),
        (moments, moments),
        "moments held for anisotropic media only"
    );
    if moments {
        let (flux, quadrupole) = (3 * n3..12 * n3, 12 * n3..27 * n3);
        let m = &cpu.multiple;
        errors.extend([
            (
                "source flux",
                max_relative_difference(&gpu_source[flux.clone()], &flat_entries(&cpu.source.flux)),
            ),
            (
                "source quadrupole",
                max_relative_difference(
                    &gpu_source[quadrupole.clone()],
                    &flat_entries(&cpu.source.quadrupole),
                ),
            ),
            (
                "multiple flux",
                max_relative_difference(&gpu_multiple[flux], &flat_entries(&m.flux)),
            ),
            (
                "multiple quadrupole",
                max_relative_difference(&gpu_multiple[quadrupole], &flat_entries(&m.quadrupole)),
            ),
        ]);
        assert!(
            m.quadrupole.iter().flatten().any(|q| q.max_element() > 0.0),
            "the multiply scattered light is not isotropic"
        );
    }
    // The two-mode tail a S_M + b S_{M-1} is a difference of terms up to (|a| + |b|) / (a + b)
    // times its size, and carries its coefficients' error that much larger.
    let closure = cpu.multiple.closure;
    let amplification = (0..3)
        .map(|c| {
            let (a, b) = (closure.last[c], closure.before[c]);
            if a + b > 0.0 {
                (a.abs() + b.abs()) / (a + b)
            } else {
                1.0
            }
        })
        .fold(1.0, f64::max);
    for (name, error) in errors {
        let tolerance = if name.starts_with("multiple") {
            TOLERANCE * amplification
        } else {
            TOLERANCE
        };
        assert!(
            error <= tolerance,
            "{name}: GPU differs from the CPU reference by {error:e} of its maximum"
        );
    }
    assert!(
        cpu.multiple.total.iter().any(|s| s.max_element() > 0.0),
        "the case scatters light more than once"
    );
}

/// The case's fine grid, lowered while its volumes pass one storage binding of `max_binding`
/// bytes: the renderer's rule, checked here on whichever adapter runs the test (its unit tests
/// check the sides it picks).
fn expected_light_resolution(case: &Case, max_binding: u64) -> u32 {
    let lights = case.lights.len() as u32;
    let moments = case.medium.anisotropy != 0.0;
    VolumeShape::fitting_light_resolution(&case.settings, lights, moments, max_binding)
        .expect("the case's volumes fit at the scattering grid's side")
}

#[test]
fn one_light_straight_down() {
    check(
        Case {
            particles: random_particles(1, 60),
            medium: Medium {
                extinction: 6.0,
                albedo: 0.9,
                ..Default::default()
            },
            lights: vec![LightSample {
                direction: Vec3::NEG_Y,
                irradiance: Vec3::new(1.0, 0.9, 0.8),
            }],
            transform: Transform::IDENTITY,
            settings: common::quality(16, 4),
        },
        Vec3::ZERO,
    );
}

/// The sky enters the grid in the first iteration of the series: with a light, and alone (a
/// cloud no directional light reaches is still lit).
#[test]
fn a_sky_lights_the_cloud_with_and_without_a_light() {
    let case = |lights: Vec<LightSample>| Case {
        particles: random_particles(3, 60),
        medium: Medium {
            extinction: 6.0,
            albedo: 0.9,
            ..Default::default()
        },
        lights,
        transform: Transform::from_rotation(Quat::from_rotation_y(0.3)),
        settings: common::quality(16, 4),
    };
    let sun = LightSample {
        direction: Vec3::new(0.3, -1.0, 0.2),
        irradiance: Vec3::new(1.0, 0.9, 0.8),
    };
    let sky = Vec3::new(0.2, 0.3, 0.5);
    check(case(vec![sun]), sky);
    check(case(vec![]), sky);
}

/// A forward-scattering medium (docs/illumination.md §4): its source's and its multiple
/// scattering's moments too, under a sun and a sky, on a rotated, scaled cloud; and a backward
/// one (no δ-Eddington truncation, flux only from `g`).
#[test]
fn anisotropic_media_with_their_moments() {
    let case = |anisotropy: f32| Case {
        particles: random_particles(6, 70),
        medium: Medium {
            extinction: 6.0,
            albedo: 0.95,
            anisotropy,
        },
        lights: vec![LightSample {
            direction: Vec3::new(0.3, -1.0, 0.2),
            irradiance: Vec3::new(1.0, 0.9, 0.8),
        }],
        transform: Transform::from_xyz(0.2, 0.1, -0.3)
            .with_rotation(Quat::from_euler(EulerRot::YXZ, 0.4, 0.2, -0.3))
            .with_scale(Vec3::splat(1.3)),
        settings: common::quality(16, 5),
    };
    check(case(0.7), Vec3::new(0.2, 0.3, 0.5));
    check(case(-0.4), Vec3::ZERO);
}

#[test]
fn three_lights_along_axes_on_a_rotated_scaled_cloud() {
    let mut rng = SplitMix64::new(7);
    check(
        Case {
            particles: random_particles(2, 120),
            medium: Medium {
                extinction: 3.0,
                albedo: 0.99,
                ..Default::default()
            },
            lights: vec![
                LightSample {
                    direction: Vec3::X,
                    irradiance: Vec3::new(0.2, 0.4, 1.0),
                },
                LightSample {
                    direction: Vec3::NEG_Z,
                    irradiance: Vec3::new(1.0, 0.3, 0.2),
                },
                LightSample {
                    direction: random_direction(&mut rng),
                    irradiance: Vec3::splat(0.5),
                },
            ],
            transform: Transform::from_xyz(0.5, -0.2, 0.3)
                .with_rotation(Quat::from_euler(EulerRot::YXZ, 0.7, -0.3, 0.2))
                .with_scale(Vec3::splat(1.5)),
            settings: common::quality(24, 6),
        },
        Vec3::ZERO,
    );
}

#[test]
fn eight_random_lights_with_the_paper_stencil() {
    let mut rng = SplitMix64::new(11);
    check(
        Case {
            particles: random_particles(3, 40),
            medium: Medium {
                extinction: 10.0,
                albedo: 0.8,
                ..Default::default()
            },
            lights: (0..8)
                .map(|i| LightSample {
                    direction: random_direction(&mut rng),
                    irradiance: Vec3::splat(0.1 + 0.1 * i as f32),
                })
                .collect(),
            transform: Transform::IDENTITY,
            settings: CloudQualitySettings {
                scatter_stencil: ScatterStencil::Paper,
                ..common::quality(8, 3)
            },
        },
        Vec3::ZERO,
    );
}

#[test]
fn forward_scattering_supersampling_3_and_a_light_along_the_view() {
    check(
        Case {
            particles: random_particles(4, 80),
            medium: Medium {
                extinction: 5.0,
                albedo: 0.95,
                ..Default::default()
            },
            lights: vec![LightSample {
                direction: Vec3::NEG_Z,
                irradiance: Vec3::ONE,
            }],
            transform: Transform::IDENTITY,
            settings: CloudQualitySettings {
                forward_scattering: 0.5,
                light_supersampling: 3,
                ..common::quality(20, 2)
            },
        },
        Vec3::ZERO,
    );
}

#[test]
fn thick_cloud_at_albedo_one_with_many_iterations_and_no_supersampling() {
    check(
        Case {
            particles: random_particles(5, 90),
            medium: Medium {
                extinction: 20.0,
                albedo: 1.0,
                ..Default::default()
            },
            lights: vec![LightSample {
                direction: Vec3::new(0.3, -1.0, 0.2),
                irradiance: Vec3::new(1.0, 0.9, 0.8),
            }],
            transform: Transform::from_rotation(Quat::from_rotation_z(0.3))
                .with_scale(Vec3::splat(0.7)),
            settings: CloudQualitySettings {
                light_supersampling: 1,
                ..common::quality(20, 24)
            },
        },
        Vec3::ZERO,
    );
}

/// Five lights at 64³ × 3 hold 5 × 192³ floats (141 MB), past a 128 MiB storage binding
/// (lavapipe's, and WebGPU's default): the cloud is shaded on a fine grid of 188³ (132.9 MB)
/// instead of being refused, 2.94 fine voxels per scattering voxel, so the gather weighs fine
/// voxels it shares between scattering voxels by their overlap; it matches the CPU reference on
/// that grid. Where the adapter's binding holds them, on 192³.
#[test]
fn light_volumes_past_the_storage_binding_are_shaded_on_a_smaller_fine_grid() {
    let directions = [
        Vec3::new(0.3, -1.0, 0.2),
        Vec3::new(-1.0, -0.5, 0.1),
        Vec3::new(0.2, 0.4, -1.0),
        Vec3::new(0.9, -0.1, 0.8),
        Vec3::new(-0.2, 1.0, 0.3),
    ];
    check(
        Case {
            particles: random_particles(11, 40),
            medium: Medium {
                extinction: 4.0,
                albedo: 0.8,
                ..Default::default()
            },
            lights: directions
                .iter()
                .map(|d| LightSample {
                    direction: d.normalize(),
                    irradiance: Vec3::new(1.0, 0.8, 0.6),
                })
                .collect(),
            transform: Transform::IDENTITY,
            settings: CloudQualitySettings {
                light_supersampling: 3,
                ..common::quality(64, 2)
            },
        },
        Vec3::ZERO,
    );
}

#[test]
fn one_particle_filling_a_fine_grid_of_256_cubed() {
    // Every voxel of the grid in one particle's support, 256³ fine voxels, 128³ scattering
    // voxels: voxelize splits the support into rows and the closure's sums stay short, so no
    // invocation loops past what software rasterisers allow (lavapipe stops at 65535 iterations).
    check(
        Case {
            particles: vec![Particle {
                position: Vec3::ZERO,
                radius: 1.0,
                density: 1.0,
            }],
            medium: Medium {
                extinction: 6.0,
                albedo: 0.9,
                ..Default::default()
            },
            lights: vec![LightSample {
                direction: Vec3::new(0.3, -1.0, 0.2),
                irradiance: Vec3::new(1.0, 0.9, 0.8),
            }],
            transform: Transform::IDENTITY,
            settings: common::quality(128, 2),
        },
        Vec3::ZERO,
    );
}

/// A fine grid past the former cap of 256: 72³ × 4 = 288³ fine voxels (one light's volume,
/// 96 MB, fits a 128 MiB binding), so that raising `volume_resolution` never shrinks it.
#[test]
fn a_fine_grid_of_288_cubed() {
    check(
        Case {
            particles: random_particles(23, 40),
            medium: Medium {
                extinction: 5.0,
                albedo: 0.9,
                ..Default::default()
            },
            lights: vec![LightSample {
                direction: Vec3::new(-0.4, -1.0, 0.3),
                irradiance: Vec3::new(1.0, 0.9, 0.8),
            }],
            transform: Transform::IDENTITY,
            settings: CloudQualitySettings {
                light_supersampling: 4,
                ..common::quality(72, 2)
            },
        },
        Vec3::ZERO,
    );
}

#[test]
fn large_particles_on_coarse_density_levels_of_odd_sizes() {
    // A fine grid of 135³: its density levels are 135, 68, 34, 17, 9, 5 voxels per side, so the
    // upsampling meets levels of both parities. Radii up to ~36 fine voxels put particles on
    // levels 0, 1 and 2.
    let mut rng = SplitMix64::new(21);
    let particles = (0..60)
        .map(|i| Particle {
            position: rng.in_unit_ball(),
            radius: [0.03, 0.2, 0.6, 1.2][i % 4] * (0.8 + 0.2 * rng.next_f32()),
            density: 0.2 + rng.next_f32(),
        })
        .collect();
    check(
        Case {
            particles,
            medium: Medium {
                extinction: 2.0,
                albedo: 0.9,
                ..Default::default()
            },
            lights: vec![LightSample {
                direction: Vec3::new(-0.4, -1.0, 0.3),
                irradiance: Vec3::ONE,
            }],
            transform: Transform::IDENTITY,
            settings: CloudQualitySettings {
                light_supersampling: 3,
                ..common::quality(45, 2)
            },
        },
        Vec3::ZERO,
    );
}
