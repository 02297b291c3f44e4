//! Particles that move every frame: a stream of puffs born small upwind, drifting with the wind,
//! swirling and growing, fading out downwind — next to a cloud that does not move. The moving
//! cloud's `Particles` asset is rewritten every frame (`Assets::get_mut`), so its passes rerun
//! every frame; the still cloud is only drawn (and re-sorted when the camera moves). The on-screen
//! counters (`CloudPassCounters::take()` each frame) show it.
//!
//! ```text
//! cargo run --example animated
//! cargo run --example animated -- --frames 120
//! cargo run --example animated -- --screenshot animated.png
//! ```
//!
//! Controls: Space pauses the wind (then no illumination pass runs at all); arrow keys turn the
//! sun; drag or A/D/W/S to orbit; wheel or +/- to zoom.

mod support;

use std::process::ExitCode;

use bevy::prelude::*;
use bevy_particle_clouds::{CloudPass, prelude::*};
use support::{Example, Hud, HudLines, KeyLight, Options, OrbitCamera, PassCounts};

const EXAMPLE: Example = Example {
    title: "bevy_particle_clouds: particles moving every frame",
    controls: "Space: pause the wind | arrows: sun | drag, A/D/W/S: orbit | wheel, +/-: zoom",
    steady: false,
};

/// Particles of the moving stream.
const COUNT: usize = 2500;
/// The stream runs from x = −LENGTH/2 to +LENGTH/2, metres.
const LENGTH: f32 = 7.0;
/// Wind speed along +x, m/s.
const WIND: f32 = 0.6;
/// Radius at birth and at the end of the stream, metres.
const RADIUS: (f32, f32) = (0.12, 0.4);

/// The moving stream: its asset, per-particle phases, the random source for rebirths.
#[derive(Resource)]
struct Stream {
    handle: Handle<Particles>,
    phases: Vec<f32>,
    rng: generators::SplitMix64,
    paused: bool,
    time: f32,
}

/// Particles moving every frame beside a still cloud.
#[derive(clap::Parser)]
struct Args {
    #[command(flatten)]
    common: Options,
}

fn main() -> ExitCode {
    let args: Args = support::parse_args();
    let options = args.common;
    let fixed_step = options.screenshot.is_some();
    support::run(EXAMPLE, options, move |app| {
        app.add_systems(Startup, setup).add_systems(
            Update,
            (
                move |keys: Res<ButtonInput<KeyCode>>,
                      time: Res<Time>,
                      stream: ResMut<Stream>,
                      assets: ResMut<Assets<Particles>>| {
                    // Headless frames take as long as the software renderer needs: step a fixed
                    // 1/30 s so the picture does not depend on the machine.
                    let dt = if fixed_step {
                        1.0 / 30.0
                    } else {
                        time.delta_secs().min(0.1)
                    };
                    blow(&keys, dt, stream, assets);
                },
                describe.in_set(HudLines),
            ),
        );
    })
}

/// Where along the stream `x` lies, 0 (birth) to 1 (end).
fn progress(x: f32) -> f32 {
    (x / LENGTH + 0.5).clamp(0.0, 1.0)
}

/// A particle at stream position `x` (cross-section offset `y`, `z`): it grows along the way and
/// fades in and out at the ends.
fn particle_at(position: Vec3) -> Particle {
    let t = progress(position.x);
    let fade = (t / 0.15).min((1.0 - t) / 0.15).clamp(0.0, 1.0);
    Particle {
        position,
        radius: RADIUS.0 + (RADIUS.1 - RADIUS.0) * t,
        density: fade * fade * (3.0 - 2.0 * fade),
    }
}

fn birth(rng: &mut generators::SplitMix64, x: f32) -> Vec3 {
    let p = rng.in_unit_ball();
    Vec3::new(x, 0.35 * p.y, 0.5 * p.z)
}

fn setup(
    mut commands: Commands,
    mut particles: ResMut<Assets<Particles>>,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
) {
    let mut rng = generators::SplitMix64::new(5);
    let stream: Vec<Particle> = (0..COUNT)
        .map(|i| {
            let x = (i as f32 + 0.5) / COUNT as f32 * LENGTH - LENGTH / 2.0;
            let mut p = particle_at(birth(&mut rng, x));
            // Further along, the stream has spread out.
            p.position.y *= 1.0 + progress(x);
            p.position.z *= 1.0 + progress(x);
            p
        })
        .collect();
    let phases = (0..COUNT)
        .map(|_| rng.next_f32() * std::f32::consts::TAU)
        .collect();
    let handle = particles.add(Particles::new(stream));
    commands.spawn((
        ParticleCloud::new(handle.clone()).with_medium(Medium {
            extinction: 6.0,
            albedo: 0.99,
            ..Default::default()
        }),
        CloudQualitySettings {
            volume_resolution: 48,
            scatter_iterations: 8,
            ..default()
        },
        Transform::from_xyz(0.0, 3.0, 0.0),
    ));
    commands.insert_resource(Stream {
        handle,
        phases,
        rng,
        paused: false,
        time: 0.0,
    });

    let still = particles.add(generators::cumulus(2.2, 2500, 3));
    commands.spawn((
        ParticleCloud::new(still).with_medium(Medium {
            extinction: 9.0,
            albedo: 0.99,
            ..Default::default()
        }),
        CloudQualitySettings {
            volume_resolution: 48,
            scatter_iterations: 8,
            ..default()
        },
        Transform::from_xyz(-2.2, 0.5, 1.5),
    ));
    commands.spawn(support::ground(
        &mut meshes,
        &mut materials,
        200.0,
        Color::linear_rgb(0.03, 0.055, 0.02),
    ));
    commands.spawn(support::key_light(
        KeyLight {
            name: "sun",
            azimuth: 40f32.to_radians(),
            elevation: 35f32.to_radians(),
            keys: KeyLight::ARROWS,
        },
        Color::WHITE,
        10_000.0,
    ));
    let orbit = OrbitCamera {
        target: Vec3::new(0.0, 2.6, 0.0),
        distance: 11.0,
        yaw: 0.25,
        pitch: 0.1,
    };
    commands.spawn(support::camera(
        orbit,
        9.5,
        Color::linear_rgb(0.22, 0.38, 0.75),
    ));
}

/// Moves every particle of the stream by `dt` seconds of wind: drift along +x, a swirl across,
/// growth; particles past the end are reborn at the start.
fn blow(
    keys: &ButtonInput<KeyCode>,
    dt: f32,
    mut stream: ResMut<Stream>,
    mut assets: ResMut<Assets<Particles>>,
) {
    if keys.just_pressed(KeyCode::Space) {
        stream.paused = !stream.paused;
    }
    if stream.paused {
        return; // The asset is untouched: no pass but the draw reruns.
    }
    stream.time += dt;
    let Stream {
        handle,
        phases,
        rng,
        time,
        ..
    } = &mut *stream;
    // `get_mut` marks the asset modified: it is re-uploaded and re-voxelized this frame.
    let Some(mut particles) = assets.get_mut(&*handle) else {
        return;
    };
    for (p, &phase) in particles.particles.iter_mut().zip(phases.iter()) {
        let q = p.position;
        let swirl = Vec3::new(
            0.0,
            0.12 * (1.7 * q.x - 0.9 * *time + phase).sin(),
            0.15 * (1.3 * q.x + 0.7 * *time + 2.0 * phase).cos(),
        );
        // The stream widens as it goes: drift away from its axis.
        let spread = Vec3::new(0.0, q.y, q.z) * 0.08;
        let mut next = q + (Vec3::X * WIND + swirl + spread) * dt;
        if next.x > LENGTH / 2.0 {
            next = birth(rng, next.x - LENGTH);
        }
        *p = particle_at(next);
    }
}

fn describe(
    mut hud: ResMut<Hud>,
    stream: Res<Stream>,
    counts: Res<PassCounts>,
    lights: Query<&KeyLight>,
) {
    hud.lines.clear();
    hud.lines.push(format!(
        "moving cloud: {COUNT} particles, wind {WIND} m/s{}; still cloud: 2500 particles",
        if stream.paused { " (paused)" } else { "" }
    ));
    for light in &lights {
        hud.lines.push(format!("{}, 10000 lux", light.describe()));
    }
    let frames = counts.frames.max(1) as f64;
    let per_frame: Vec<String> = CloudPass::ALL
        .iter()
        .map(|&p| {
            format!(
                "{} {:.1}",
                p.name(),
                counts.total[p as usize] as f64 / frames
            )
        })
        .collect();
    hud.lines.push(format!(
        "runs per frame, mean over {} frames: {}",
        counts.frames,
        per_frame.join(", ")
    ));
    hud.lines
        .push("each frame: voxelize 1 (only the moving cloud), draw 2 (both clouds)".into());
}
