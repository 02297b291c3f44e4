//! The paper's Figure 2: one cloud lit blue from one side and red from the other. Each light
//! shades its own light-aligned volume; the gather pass adds them; multiple scattering mixes the
//! colours inside the cloud.
//!
//! ```text
//! cargo run --example multiple_lights
//! cargo run --example multiple_lights -- --frames 120
//! cargo run --example multiple_lights -- --screenshot multiple_lights.png
//! ```
//!
//! Controls: arrow keys turn the blue light, J/L and I/K the red one; drag or A/D/W/S to orbit;
//! wheel or +/- to zoom. Turning a light reruns only that light's shade pass, the gather and the
//! scattering (see the pass counters on screen).

mod support;

use std::process::ExitCode;

use bevy::prelude::*;
use bevy_particle_clouds::prelude::*;
use support::{Example, Hud, HudLines, KeyLight, Options, OrbitCamera};

const EXAMPLE: Example = Example {
    title: "bevy_particle_clouds: two coloured lights (Figure 2)",
    controls: "arrows: blue light | J/L, I/K: red light | drag, A/D/W/S: orbit | wheel, +/-: zoom",
    steady: true,
};

/// Illuminance of each light, lux.
const LUX: f32 = 10_000.0;

/// One cloud lit blue from one side and red from the other (the paper's Figure 2).
#[derive(clap::Parser)]
struct Args {
    #[command(flatten)]
    common: Options,
}

fn main() -> ExitCode {
    let args: Args = support::parse_args();
    let options = args.common;
    support::run(EXAMPLE, options, |app| {
        app.add_systems(Startup, setup)
            .add_systems(Update, describe.in_set(HudLines));
    })
}

fn setup(mut commands: Commands, mut particles: ResMut<Assets<Particles>>) {
    let cloud = particles.add(generators::cumulus(2.5, 4000, 7));
    commands.spawn((
        ParticleCloud::new(cloud).with_medium(Medium {
            extinction: 8.0,
            albedo: 0.99,
            ..Default::default()
        }),
        CloudQualitySettings {
            volume_resolution: 64,
            scatter_iterations: 16,
            ..default()
        },
        Transform::from_xyz(0.0, -0.4, 0.0),
    ));
    // Blue from the left, red from the right, both a little above and in front.
    commands.spawn(support::key_light(
        KeyLight {
            name: "blue",
            azimuth: 160f32.to_radians(),
            elevation: 20f32.to_radians(),
            keys: KeyLight::ARROWS,
        },
        Color::linear_rgb(0.15, 0.35, 1.0),
        LUX,
    ));
    commands.spawn(support::key_light(
        KeyLight {
            name: "red",
            azimuth: 20f32.to_radians(),
            elevation: 20f32.to_radians(),
            keys: [KeyCode::KeyJ, KeyCode::KeyL, KeyCode::KeyK, KeyCode::KeyI],
        },
        Color::linear_rgb(1.0, 0.2, 0.08),
        LUX,
    ));
    let orbit = OrbitCamera {
        target: Vec3::new(0.0, 0.75, 0.0),
        distance: 6.0,
        yaw: 0.0,
        pitch: 0.1,
    };
    commands.spawn(support::camera(
        orbit,
        9.5,
        Color::linear_rgb(0.01, 0.01, 0.015),
    ));
}

fn describe(mut hud: ResMut<Hud>, lights: Query<(&KeyLight, &DirectionalLight)>) {
    hud.lines.clear();
    hud.lines
        .push("cumulus, 4000 particles, volume 64^3, 16 scatter iterations".into());
    for (key, light) in &lights {
        let c = light.color.to_linear();
        hud.lines.push(format!(
            "{}, {} lux, colour ({:.2}, {:.2}, {:.2})",
            key.describe(),
            light.illuminance,
            c.red,
            c.green,
            c.blue
        ));
    }
}
