//! Run to run: the same scene, rendered by fresh apps, draws the same image up to the order in
//! which the GPU's threads add floats. One pass still adds floats with atomics in an order the
//! hardware chooses: the computed draw's sums of light and optical depth per pixel. Voxelize is a
//! gather in a fixed order, so the density is the same bit for bit, even where thousands of
//! particles pile on one voxel. README "Limitations" states the bound asserted here.

use bevy::prelude::*;
use bevy_particle_clouds::headless::{self, FrameRecorder};
use bevy_particle_clouds::{
    CloudQualitySettings, Medium, Particle,
    generators::{self, SplitMix64},
    reference::{
        illumination::voxelize,
        metrics::{max_relative_difference, relative_rmse},
    },
};

use crate::{batching::fine_density, common};

/// The largest relative RMSE between two runs' images that README "Limitations" allows for
/// this scene (llvmpipe measured 1.1e-5).
const RUN_TO_RUN: f64 = 1e-4;

/// An albedo-1 cumulus at the defaults, lit by two suns, 64×40: the medium whose scattering
/// amplifies the last bits of its density the most (docs/performance.md, "The closure's weight").
fn render_once() -> Vec<[f32; 4]> {
    let mut app = common::headless_app();
    let image = headless::float_target(&mut app, 64, 40);
    headless::spawn_linear_camera(
        &mut app,
        image.clone(),
        Transform::from_xyz(0.0, 0.4, 6.0).looking_at(Vec3::new(0.0, 0.3, 0.0), Vec3::Y),
        40.0,
        Vec3::new(0.1, 0.2, 0.3),
    );
    headless::spawn_light(&mut app, Vec3::new(-0.6, -0.5, -0.6), Vec3::splat(3.0));
    headless::spawn_light(
        &mut app,
        Vec3::new(0.8, -0.2, 0.3),
        Vec3::new(0.5, 0.6, 1.2),
    );
    headless::spawn_cloud(
        &mut app,
        generators::cumulus(2.5, 1500, 11).particles,
        Medium {
            extinction: 12.0,
            albedo: 1.0,
            ..default()
        },
        CloudQualitySettings::default(),
        Transform::IDENTITY,
    );
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 1, 100).unwrap();
    headless::capture(&mut app, &mut recorder, &image)
        .unwrap()
        .pixels
}

#[test]
fn the_same_scene_draws_the_same_image_run_to_run_within_the_stated_bound() {
    let first = render_once();
    assert!(first.iter().all(|p| p.iter().all(|v| v.is_finite())));
    let mut largest = 0.0f64;
    for run in 2..=3 {
        let again = render_once();
        let difference = relative_rmse(&again, &first);
        eprintln!("run {run} against run 1: relative RMSE {difference:.3e}");
        largest = largest.max(difference);
    }
    assert!(
        largest <= RUN_TO_RUN,
        "runs differ by {largest:.3e} rel. RMSE, above the stated {RUN_TO_RUN:e}"
    );
}

/// 3,000 particles of radius 0.05 m piled on one point, beside 1,000 spread over a ball of
/// radius 0.5 m (its grid's voxel is about 1 cm at 96³).
fn piled_particles() -> Vec<Particle> {
    let mut rng = SplitMix64::new(17);
    (0..4000)
        .map(|i| Particle {
            position: if i < 3000 {
                Vec3::new(0.1, -0.05, 0.2)
            } else {
                rng.in_unit_ball() * 0.5
            },
            radius: if i < 3000 {
                0.05
            } else {
                0.03 + 0.05 * rng.next_f32()
            },
            density: 0.1 + rng.next_f32(),
        })
        .collect()
}

/// The fine density a fresh app voxelizes from `particles` at `settings`.
fn voxelize_once(particles: &[Particle], settings: CloudQualitySettings) -> Vec<f32> {
    let mut app = common::headless_app();
    let image = headless::float_target(&mut app, 32, 32);
    let eye = Transform::from_xyz(0.0, 0.0, 4.0).looking_at(Vec3::ZERO, Vec3::Y);
    headless::spawn_linear_camera(&mut app, image, eye, 40.0, Vec3::ZERO);
    headless::spawn_light(&mut app, Vec3::new(0.0, -1.0, -0.4), Vec3::ONE);
    let cloud = headless::spawn_cloud(
        &mut app,
        particles.to_vec(),
        Medium::default(),
        settings,
        Transform::IDENTITY,
    );
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 1, 20).unwrap();
    fine_density(&mut app, cloud, settings.light_resolution() as usize)
}

#[test]
fn voxelize_writes_the_same_density_bit_for_bit_even_where_particles_pile_up() {
    let particles = piled_particles();
    // A fine grid of 96³.
    let settings = CloudQualitySettings {
        light_supersampling: 4,
        ..common::quality(24, 1)
    };
    let first = voxelize_once(&particles, settings);
    let again = voxelize_once(&particles, settings);
    let differing = first
        .iter()
        .zip(&again)
        .filter(|(a, b)| a.to_bits() != b.to_bits())
        .count();
    assert_eq!(differing, 0, "{differing} voxels differ between two runs");
    // And it is the right density: the CPU reference's, voxel by voxel.
    let cpu = voxelize(&particles, 96).expect("density");
    let gpu: Vec<f64> = first.iter().map(|&v| f64::from(v)).collect();
    let difference = max_relative_difference(&gpu, &cpu.rho);
    assert!(difference < 2e-4, "{difference}");
}

/// On an 8³ grid (one brick) every particle is binned in the same brick: lists just longer than
/// one invocation sorts (32) are sorted by the workgroup, and the density is still the CPU
/// reference's. (Lavapipe crashed on such lists while the count of long lists was left in
/// workgroup memory uncleared.)
#[test]
fn lists_just_past_one_invocation_are_sorted_by_the_workgroup() {
    let settings = CloudQualitySettings {
        volume_resolution: 8,
        light_supersampling: 1,
        ..default()
    };
    for count in [32, 33, 45, 64, 65, 100] {
        let particles = generators::sphere(0.6, 0.2, count, 3).particles;
        let gpu: Vec<f64> = voxelize_once(&particles, settings)
            .into_iter()
            .map(f64::from)
            .collect();
        let cpu = voxelize(&particles, 8).expect("density");
        let difference = max_relative_difference(&gpu, &cpu.rho);
        assert!(difference < 2e-4, "{count} particles: {difference}");
    }
}
