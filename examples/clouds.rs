//! A field of cumulus clouds over a ground plane, under a sun you can turn.
//!
//! ```text
//! cargo run --example clouds                         # a window
//! cargo run --example clouds -- --frames 120         # exits after 120 frames (CI, under Xvfb)
//! cargo run --example clouds -- --screenshot clouds.png [--size 800x450]   # headless picture
//! cargo run --example clouds -- --sun 200,12 --screenshot backlit.png   # the sun behind a cloud
//! cargo run --example clouds -- --visibility 0       # no haze
//! ```
//!
//! The clouds scatter forward (Henyey–Greenstein g = 0.6), so with the sun behind one (turn it
//! with the arrow keys, or start there with `--sun`) its thin edges glow: the silver lining. A
//! blue sky lights them too (`CloudSkyLight`), which tints their shadowed sides, and the grass
//! lights their undersides a little (`CloudGround`). They shadow the ground (its material takes
//! the `CloudShadowMaps`), and a haze (Bevy's `DistanceFog`, 1500 m
//! visibility) fogs the clouds and the ground alike, fading into the sky.
//!
//! Controls: arrow keys turn the sun (azimuth, elevation); drag with the left mouse button or
//! A/D/W/S to orbit; wheel or +/- to zoom; [ and ] change the multiple-scattering iterations,
//! V the volume resolution (both through the `DefaultCloudQuality` resource), C the camera's
//! `CloudTargetScale` (1, 1/2, 1/4: the clouds drawn at that fraction of the window's size and
//! enlarged; 1/2 to start with, as a game would).
//!
//! Exposure: the sun's illuminance is E = 10 000 lux. The lit sides of these clouds (albedo 0.99,
//! 8 scattering iterations) come out at roughly E / (4π) ≈ 800 (judged from the rendered
//! pictures; less than the E / (4π) × 3 of fully converged multiple scattering), so the camera's
//! exposure factor
//! 1 / (1.2 · 2^ev100) = 1 / 750 (ev100 = 9.3) maps them to about 1: white after ACES tonemapping,
//! not grey. The ground (albedo ≈ 0.05) stays darker than the clouds, as it should.

mod support;

use std::process::ExitCode;

use bevy::prelude::*;
use bevy_particle_clouds::{headless, lit_object::LitObjectMaterial, prelude::*};
use support::{Example, Hud, HudLines, KeyLight, Options, OrbitCamera, SUN_LUX};

const EXAMPLE: Example = Example {
    title: "bevy_particle_clouds: a field of cumulus",
    controls: "arrows: sun | drag, A/D/W/S: orbit | wheel, +/-: zoom | [ ]: scatter iterations | V: volume resolution | C: cloud target scale",
    steady: true,
};

/// A field of cumulus over a ground plane under a sun turned with the arrow keys.
#[derive(clap::Parser)]
struct Args {
    #[command(flatten)]
    common: Options,
    /// The sun's azimuth and elevation to start with, degrees (the azimuth from +X around +Y, of
    /// the direction the light comes from; elevation in -90..=90).
    #[arg(long, value_name = "AZ,EL", value_parser = parse_sun, default_value = "30,25")]
    sun: (f32, f32),
    /// The haze's visibility, metres (`FogFalloff::from_visibility`); 0 for none.
    #[arg(long, value_name = "M", value_parser = parse_visibility, default_value = "1500")]
    visibility: f32,
}

fn parse_visibility(text: &str) -> Result<f32, String> {
    text.parse::<f32>()
        .ok()
        .filter(|v| v.is_finite() && *v >= 0.0)
        .ok_or(format!(
            "--visibility is {text}; it must be a number of metres >= 0"
        ))
}

fn parse_sun(text: &str) -> Result<(f32, f32), String> {
    text.split_once(',')
        .and_then(|(a, e)| Some((a.trim().parse::<f32>().ok()?, e.trim().parse::<f32>().ok()?)))
        .filter(|(a, e)| a.is_finite() && (-90.0..=90.0).contains(e))
        .map(|(a, e)| (a.to_radians(), e.to_radians()))
        .ok_or(format!(
            "--sun is {text}; it must be AZ,EL in degrees, the elevation in -90..=90"
        ))
}

/// The sun the scene starts with (radians), and the haze's visibility (metres, 0 for none).
#[derive(Resource)]
struct Start {
    sun: (f32, f32),
    visibility: f32,
}

fn main() -> ExitCode {
    let args: Args = support::parse_args();
    let options = args.common;
    support::run(EXAMPLE, options, |app| {
        // The ground takes the clouds' shadows of the sun through a 1024² map.
        headless::enable_cloud_shadow_maps(app, 1024, 1);
        app.insert_resource(Start {
            sun: args.sun,
            visibility: args.visibility,
        });
        app.insert_resource(DefaultCloudQuality(CloudQualitySettings {
            volume_resolution: 48,
            scatter_iterations: 8,
            ..default()
        }))
        .add_systems(Startup, setup)
        .add_systems(Update, (change_quality, describe).chain().in_set(HudLines));
    })
}

fn setup(
    mut commands: Commands,
    start: Res<Start>,
    mut particles: ResMut<Assets<Particles>>,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<LitObjectMaterial>>,
    shadow_maps: Res<CloudShadowMaps>,
) {
    // Eight cumulus of different sizes on a loose ring, their bases at 6–9 m.
    let mut rng = generators::SplitMix64::new(2024);
    for i in 0..8u64 {
        let size = 5.0 + 7.0 * rng.next_f32();
        let count = (600.0 * size) as usize;
        let angle = i as f32 / 8.0 * std::f32::consts::TAU + 0.5 * rng.next_f32();
        let radius = if i == 0 {
            0.0
        } else {
            18.0 + 14.0 * rng.next_f32()
        };
        let position = Vec3::new(
            angle.cos() * radius,
            6.0 + 3.0 * rng.next_f32(),
            angle.sin() * radius,
        );
        let handle = particles.add(generators::cumulus(size, count, 100 + i));
        commands.spawn((
            // Optical thickness independent of size: extinction ∝ 1 / size.
            ParticleCloud::new(handle).with_medium(Medium {
                extinction: 20.0 / size,
                albedo: 0.99,
                anisotropy: 0.6,
            }),
            Transform::from_translation(position).with_rotation(Quat::from_rotation_y(angle)),
        ));
    }
    let orbit = OrbitCamera {
        target: Vec3::new(0.0, 8.0, 0.0),
        distance: 55.0,
        yaw: 0.3,
        pitch: 0.12,
    };
    let ground = support::shadowed_ground(
        &mut meshes,
        &mut materials,
        &shadow_maps,
        1000.0,
        support::GROUND_ALBEDO,
    );
    let camera = support::spawn_outdoor(&mut commands, ground, start.sun, orbit);
    if start.visibility > 0.0 {
        commands.entity(camera).insert(DistanceFog {
            color: support::sky_color(),
            // The sun's glow in the haze: its colour times the exposed illuminance (13 here).
            directional_light_color: Color::linear_rgba(1.0, 0.9, 0.7, 0.02),
            directional_light_exponent: 16.0,
            falloff: FogFalloff::from_visibility(start.visibility),
        });
    }
}

fn change_quality(
    keys: Res<ButtonInput<KeyCode>>,
    mut quality: ResMut<DefaultCloudQuality>,
    mut target: Query<&mut CloudTargetScale>,
) {
    if keys.just_pressed(KeyCode::KeyC) {
        for mut scale in &mut target {
            scale.0 = if scale.0 <= 0.25 { 1.0 } else { scale.0 / 2.0 };
        }
    }
    if keys.just_pressed(KeyCode::BracketRight) {
        quality.scatter_iterations = (quality.scatter_iterations * 2).clamp(1, 64);
    }
    if keys.just_pressed(KeyCode::BracketLeft) {
        quality.scatter_iterations /= 2;
    }
    if keys.just_pressed(KeyCode::KeyV) {
        quality.volume_resolution = match quality.volume_resolution {
            0..=32 => 48,
            33..=48 => 64,
            65.. => 32,
            _ => 96,
        };
    }
}

fn describe(
    mut hud: ResMut<Hud>,
    quality: Res<DefaultCloudQuality>,
    sun: Query<&KeyLight>,
    camera: Query<(&OrbitCamera, &bevy::camera::Exposure, &CloudTargetScale)>,
    clouds: Query<&ParticleCloud>,
    particles: Res<Assets<Particles>>,
) {
    hud.lines.clear();
    let count: usize = clouds
        .iter()
        .filter_map(|c| particles.get(&c.particles))
        .map(|p| p.particles.len())
        .sum();
    hud.lines
        .push(format!("{} clouds, {count} particles", clouds.iter().len()));
    hud.lines.push(format!(
        "volume {}^3, {} scatter iterations + {} coarse-grid cycles, stencil {:?}",
        quality.volume_resolution,
        quality.scatter_iterations,
        quality.coarse_cycles(),
        quality.scatter_stencil
    ));
    for light in &sun {
        hud.lines
            .push(format!("{}, {SUN_LUX} lux", light.describe()));
    }
    for (orbit, exposure, target) in &camera {
        hud.lines.push(format!(
            "camera {:.0} m from the centre, exposure ev100 {}, clouds drawn at {} of its size",
            orbit.distance, exposure.ev100, target.0
        ));
    }
}
