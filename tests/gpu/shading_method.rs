//! `ShadingMethod::BruteForce` (every voxel marches to the light) against the incremental shade
//! pass (each slice is the previous one times one step): the same trapezoid sums, so the light
//! volumes and everything computed from them agree up to f32 rounding.

use bevy::prelude::*;
use bevy_particle_clouds::headless::{self, FrameRecorder, SceneTarget};
use bevy_particle_clouds::{
    CloudPass, CloudQualitySettings, LightSample, Medium, Particle, ParticleCloud, Particles,
    generators::SplitMix64,
    reference::metrics::max_relative_difference,
    render::{pools::VolumePools, volumes::CloudVolumes},
    settings::ShadingMethod,
};

use crate::common;

/// Largest allowed difference, relative to the volume's largest value.
const TOLERANCE: f64 = 1e-5;

fn particles() -> Vec<Particle> {
    let mut rng = SplitMix64::new(5);
    (0..150)
        .map(|_| Particle {
            position: rng.in_unit_ball() * Vec3::new(1.0, 0.7, 0.9),
            radius: 0.1 + 0.3 * rng.next_f32(),
            density: 0.3 + rng.next_f32(),
        })
        .collect()
}

struct Volumes {
    /// One optical-depth volume per light.
    optical_depth: Vec<Vec<f64>>,
    /// Multiple scattering, RGBA.
    multiple: Vec<f64>,
    /// The series closure's coefficients of `S_M` and `S_{M-1}`, RGBA each.
    closure: Vec<f64>,
    shade_runs: u32,
}

impl Volumes {
    /// How much the two-mode tail `a S_M + b S_{M-1}` magnifies a relative difference of the
    /// orders: `(|a| + |b|) / (a + b)`, at least 1.
    fn amplification(&self) -> f64 {
        (0..3)
            .map(|c| {
                let (a, b) = (self.closure[c], self.closure[4 + c]);
                if a + b > 0.0 {
                    (a.abs() + b.abs()) / (a + b)
                } else {
                    1.0
                }
            })
            .fold(1.0, f64::max)
    }
}

fn render(
    method: ShadingMethod,
    settings: CloudQualitySettings,
    lights: &[LightSample],
) -> Volumes {
    let mut app = common::headless_app();
    app.insert_resource(method);
    let image = headless::float_target(&mut app, 16, 16);
    let camera = headless::spawn_linear_camera(
        &mut app,
        image.clone(),
        Transform::from_xyz(0.0, 0.0, 6.0).looking_at(Vec3::ZERO, Vec3::Y),
        60.0,
        Vec3::ZERO,
    );
    for light in lights {
        headless::spawn_light(&mut app, light.direction, light.irradiance);
    }
    let handle = app
        .world_mut()
        .resource_mut::<Assets<Particles>>()
        .add(Particles::new(particles()));
    app.world_mut().spawn((
        ParticleCloud::new(handle).with_medium(Medium {
            extinction: 12.0,
            albedo: 0.95,
            ..Default::default()
        }),
        settings,
        Transform::IDENTITY,
    ));
    let target = SceneTarget {
        image,
        width: 16,
        height: 16,
        camera,
        drawable_clouds: 1,
    };
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, target.drawable_clouds, 20).unwrap();
    let shade_runs = recorder
        .frames
        .iter()
        .map(|f| f.runs(CloudPass::Shade))
        .sum();
    let (depths, multiple, closure) = common::with_render_world(&mut app, |world| {
        let volumes = world
            .query::<&CloudVolumes>()
            .single(world)
            .expect("one cloud's volumes");
        let pool = world.resource::<VolumePools>().pool(&volumes.slot);
        let slot = volumes.slot.index;
        (
            pool.optical_depth(slot),
            pool.multiple(slot),
            pool.order_ratio(slot),
        )
    });
    let n3 = (settings.volume_resolution as usize).pow(3);
    let m3 = (settings.light_resolution() as usize).pow(3);
    let read = |app: &mut App, range| -> Vec<f64> {
        headless::floats(&headless::read_buffer_range(app, range).unwrap())
            .into_iter()
            .map(f64::from)
            .collect()
    };
    let optical_depth = read(&mut app, &depths)
        .chunks_exact(m3)
        .take(lights.len())
        .map(<[f64]>::to_vec)
        .collect();
    let multiple = read(&mut app, &multiple)[..4 * n3].to_vec();
    let closure = read(&mut app, &closure);
    Volumes {
        optical_depth,
        multiple,
        closure,
        shade_runs,
    }
}

#[test]
fn brute_force_and_incremental_shading_agree() {
    let lights = [
        LightSample {
            direction: Vec3::new(-0.5, -0.8, -0.35),
            irradiance: Vec3::new(1.0, 0.9, 0.8),
        },
        LightSample {
            direction: Vec3::new(0.9, 0.1, 0.3),
            irradiance: Vec3::new(0.2, 0.3, 1.0),
        },
    ];
    // The series alone, whose closure's amplification sets the tolerance below (the coarse
    // grid's closure would amplify the shading's differences its own way: tested apart, in
    // coarse_cycles.rs).
    let settings = CloudQualitySettings {
        volume_resolution: 40,
        scatter_iterations: 4,
        scatter_coarse_cycles: 0,
        ..default()
    };
    let incremental = render(ShadingMethod::Incremental, settings, &lights);
    let brute_force = render(ShadingMethod::BruteForce, settings, &lights);
    assert_eq!(incremental.shade_runs, 2);
    assert_eq!(brute_force.shade_runs, 2);
    assert_eq!(incremental.optical_depth.len(), 2);
    for (i, (b, inc)) in brute_force
        .optical_depth
        .iter()
        .zip(&incremental.optical_depth)
        .enumerate()
    {
        // The light must be attenuated somewhere, or the comparison proves nothing.
        let max = inc.iter().copied().fold(0.0, f64::max);
        assert!(
            max > 3.0,
            "light {i}: the cloud barely shadows (max optical depth {max})"
        );
        let error = max_relative_difference(b, inc);
        assert!(
            error <= TOLERANCE,
            "light {i}: optical depth differs by {error:e} of its maximum"
        );
    }
    assert!(
        incremental.multiple.iter().any(|&s| s > 0.0),
        "no multiple scattering"
    );
    // The orders differ by the light volumes' rounding; the two-mode tail magnifies that (1.3e-5
    // of the maximum seen on an NVIDIA H200, while voxelize still summed the density with float
    // atomics in an order the GPU chose; it sums in a fixed order now).
    let amplification = incremental.amplification();
    let error = max_relative_difference(&brute_force.multiple, &incremental.multiple);
    assert!(
        error <= TOLERANCE * amplification,
        "multiple scattering differs by {error:e} of its maximum (tail amplification \
         {amplification})"
    );
}
