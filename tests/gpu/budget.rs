//! The re-light budget on the GPU: under a light that turns every frame, a budget of one
//! re-lights one cloud per frame, in turn, and the others catch up once the light stops.

use bevy::prelude::*;
use bevy_particle_clouds::headless::{self, FrameRecorder};
use bevy_particle_clouds::settings::CloudRelightBudget;
use bevy_particle_clouds::{CloudPass, Medium, Particle};

use crate::common;

/// Three small clouds side by side, a light across the row (no cloud shadows another), and the
/// light's entity.
fn three_clouds(budget: u32) -> (App, Entity) {
    let mut app = common::headless_app();
    app.insert_resource(CloudRelightBudget(budget));
    let image = headless::float_target(&mut app, 64, 32);
    let eye = Transform::from_xyz(0.0, 0.0, 14.0).looking_at(Vec3::ZERO, Vec3::Y);
    headless::spawn_linear_camera(&mut app, image, eye, 40.0, Vec3::ZERO);
    let light = headless::spawn_light(&mut app, Vec3::new(0.0, -1.0, -0.4), Vec3::ONE);
    for x in [-4.0, 0.0, 4.0] {
        let particles = (0..12)
            .map(|i| Particle {
                position: Vec3::new((i % 3) as f32 - 1.0, (i / 3) as f32 * 0.4 - 0.6, 0.0) * 0.6,
                radius: 0.5,
                density: 1.0,
            })
            .collect();
        headless::spawn_cloud(
            &mut app,
            particles,
            Medium {
                extinction: 3.0,
                albedo: 0.9,
                ..Default::default()
            },
            common::quality(12, 4),
            Transform::from_xyz(x, 0.0, 0.0),
        );
    }
    (app, light)
}

/// Shade runs in each of `frames` frames, turning the light before each when `turning`.
fn shade_runs(
    app: &mut App,
    recorder: &mut FrameRecorder,
    light: Entity,
    frames: usize,
    turning: bool,
) -> Vec<u32> {
    (0..frames)
        .map(|_| {
            if turning {
                app.world_mut()
                    .get_mut::<Transform>(light)
                    .unwrap()
                    .rotate_y(0.05);
            }
            recorder.frame(app).unwrap().runs(CloudPass::Shade)
        })
        .collect()
}

#[test]
fn a_budget_of_one_relights_one_cloud_per_frame_in_turn() {
    let (mut app, light) = three_clouds(1);
    let mut recorder = FrameRecorder::default();
    // New clouds are illuminated at once, whatever the budget.
    headless::render_until_steady(&mut app, &mut recorder, 3, 20).unwrap();
    assert_eq!(
        recorder
            .frames
            .iter()
            .map(|f| f.runs(CloudPass::Shade))
            .sum::<u32>(),
        3
    );
    // The light turns every frame: one cloud (one light) is shaded per frame.
    assert_eq!(shade_runs(&mut app, &mut recorder, light, 6, true), [1; 6]);
    // It stops: the two clouds not re-lit in the last frame catch up, one per frame, then
    // nothing runs.
    assert_eq!(
        shade_runs(&mut app, &mut recorder, light, 4, false),
        [1, 1, 0, 0]
    );
}

#[test]
fn without_a_budget_every_cloud_is_relit_every_frame() {
    let (mut app, light) = three_clouds(0);
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 3, 20).unwrap();
    assert_eq!(shade_runs(&mut app, &mut recorder, light, 3, true), [3; 3]);
    assert_eq!(shade_runs(&mut app, &mut recorder, light, 2, false), [0; 2]);
}
