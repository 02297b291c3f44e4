//! Run to run: the same scene, rendered by fresh apps, draws the same image up to the order in
//! which the GPU's threads add floats. Two passes add floats with atomics in an order the
//! hardware chooses: the voxelization's density (and each particle's kernel total), and the
//! computed draw's sums of light and optical depth per pixel. Everything else is a fixed order.
//! README "Limitations" states the bound asserted here.

use bevy::prelude::*;
use bevy_particle_clouds::headless::{self, FrameRecorder};
use bevy_particle_clouds::{
    CloudQualitySettings, Medium, generators, reference::metrics::relative_rmse,
};

use crate::common;

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
