//! The paper's Figure 5: a snow bunny of about 1.2 million particles, lit by two lights, with 5
//! multiple-scattering steps. Its shape is a signed-distance function (`generators::bunny_sdf`)
//! filled by rejection sampling (`generators::from_sdf`) at start-up, with progress on stderr.
//! Beside it sits a small bunny of 3 000 particles loaded from `assets/bunny.ply` through the
//! `AssetServer` (the plugin registers a loader for `.ply` and `.csv` particle files).
//!
//! ```text
//! cargo run --example snow_bunny
//! cargo run --example snow_bunny -- --particles 50000 --frames 60     # lighter, for CI
//! cargo run --example snow_bunny -- --screenshot snow_bunny.png [--particles N]
//! ```
//!
//! `--particles N` (default 1 200 000) sets the big bunny's particle count; the particle radius
//! scales with `N^(-1/3)` so the bunny keeps its optical thickness.
//!
//! Controls: arrow keys turn the key light, J/L and I/K the rim light; drag or A/D/W/S to orbit;
//! wheel or +/- to zoom.

mod support;

use std::{process::ExitCode, time::Instant};

use bevy::prelude::*;
use bevy_particle_clouds::prelude::*;
use support::{Example, Hud, HudLines, KeyLight, Options, OrbitCamera};

const EXAMPLE: Example = Example {
    title: "bevy_particle_clouds: snow bunny (Figure 5)",
    controls: "arrows: key light | J/L, I/K: rim light | drag, A/D/W/S: orbit | wheel, +/-: zoom",
    steady: true,
};

/// The paper's particle count.
const DEFAULT_PARTICLES: usize = 1_200_000;
/// Particle radius at the default count, metres.
const RADIUS_AT_DEFAULT: f32 = 0.025;
/// The paper's multiple-scattering steps, the series alone (no coarse-grid cycles).
const SCATTER_STEPS: u32 = 5;

/// The big bunny's particles, generated before the app starts.
#[derive(Resource)]
struct BigBunny(Option<Particles>);

/// 1.2 million particles filling a bunny (the paper's Figure 5).
#[derive(clap::Parser)]
struct Args {
    #[command(flatten)]
    common: Options,
    /// Particles of the big bunny (the radius grows as N^(-1/3), keeping its optical thickness).
    #[arg(long, value_name = "N", default_value_t = DEFAULT_PARTICLES as u64,
          value_parser = clap::value_parser!(u64).range(1..=20_000_000))]
    particles: u64,
}

fn main() -> ExitCode {
    let args: Args = support::parse_args();
    let options = args.common;
    let count = args.particles as usize;
    let bunny = generate(count);
    support::run(EXAMPLE, options, move |app| {
        app.insert_resource(BigBunny(Some(bunny)))
            .add_systems(Startup, setup)
            .add_systems(Update, describe.in_set(HudLines));
    })
}

/// Fills the bunny in batches of 100 000, reporting progress on stderr.
fn generate(count: usize) -> Particles {
    let start = Instant::now();
    let radius = RADIUS_AT_DEFAULT * (DEFAULT_PARTICLES as f32 / count as f32).cbrt();
    let (lo, hi) = generators::BUNNY_BOUNDS;
    let mut all = Vec::with_capacity(count);
    let batch = 100_000;
    for (i, first) in (0..count).step_by(batch).enumerate() {
        let n = batch.min(count - first);
        all.extend(
            generators::from_sdf(generators::bunny_sdf, lo, hi, radius, n, 1000 + i as u64)
                .particles,
        );
        eprintln!(
            "snow_bunny: {:>8} / {count} particles ({:.0} %) in {:.1} s",
            all.len(),
            100.0 * all.len() as f64 / count as f64,
            start.elapsed().as_secs_f64()
        );
    }
    eprintln!("snow_bunny: particle radius {:.1} mm", radius * 1000.0);
    Particles::new(all)
}

fn setup(
    mut commands: Commands,
    mut bunny: ResMut<BigBunny>,
    mut particles: ResMut<Assets<Particles>>,
    asset_server: Res<AssetServer>,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
) {
    let big = particles.add(bunny.0.take().expect("generated in main"));
    commands.spawn((
        ParticleCloud::new(big).with_medium(Medium {
            extinction: 1.5,
            albedo: 0.99,
            ..Default::default()
        }),
        CloudQualitySettings {
            volume_resolution: 128,
            scatter_iterations: SCATTER_STEPS,
            scatter_coarse_cycles: 0,
            // A fine grid of 256: the default 4 would make it 512 (537 MB a light) where the
            // adapter's storage binding holds it.
            light_supersampling: 2,
            ..default()
        },
        Transform::default(),
    ));
    // The small bunny comes from a file, through the asset loader.
    let small: Handle<Particles> = asset_server.load("bunny.ply");
    commands.spawn((
        ParticleCloud::new(small).with_medium(Medium {
            extinction: 12.0,
            albedo: 0.99,
            ..Default::default()
        }),
        CloudQualitySettings {
            volume_resolution: 48,
            scatter_iterations: SCATTER_STEPS,
            scatter_coarse_cycles: 0,
            ..default()
        },
        Transform::from_xyz(1.5, 0.0, 1.0)
            .with_scale(Vec3::splat(0.4))
            .with_rotation(Quat::from_rotation_y(0.9)),
    ));
    commands.spawn(support::ground(
        &mut meshes,
        &mut materials,
        200.0,
        Color::linear_rgb(0.02, 0.025, 0.035),
    ));
    commands.spawn(support::key_light(
        KeyLight {
            name: "key light",
            azimuth: 60f32.to_radians(),
            elevation: 35f32.to_radians(),
            keys: KeyLight::ARROWS,
        },
        Color::linear_rgb(1.0, 0.86, 0.7),
        8_000.0,
    ));
    commands.spawn(support::key_light(
        KeyLight {
            name: "rim light",
            azimuth: 200f32.to_radians(),
            elevation: 25f32.to_radians(),
            keys: [KeyCode::KeyJ, KeyCode::KeyL, KeyCode::KeyK, KeyCode::KeyI],
        },
        Color::linear_rgb(0.55, 0.7, 1.0),
        6_000.0,
    ));
    let orbit = OrbitCamera {
        target: Vec3::new(0.4, 1.2, 0.4),
        distance: 5.4,
        yaw: 0.45,
        pitch: 0.15,
    };
    commands.spawn(support::camera(
        orbit,
        9.0,
        Color::linear_rgb(0.03, 0.05, 0.1),
    ));
}

fn describe(
    mut hud: ResMut<Hud>,
    clouds: Query<(&ParticleCloud, &CloudQualitySettings)>,
    particles: Res<Assets<Particles>>,
    asset_server: Res<AssetServer>,
    lights: Query<(&KeyLight, &DirectionalLight)>,
) {
    hud.lines.clear();
    for (cloud, quality) in &clouds {
        let name = asset_server
            .get_path(cloud.particles.id())
            .map_or("generated".to_string(), |p| p.to_string());
        let count = particles
            .get(&cloud.particles)
            .map_or("loading".to_string(), |p| p.particles.len().to_string());
        hud.lines.push(format!(
            "{name}: {count} particles, volume {}^3, {} scattering steps",
            quality.volume_resolution, quality.scatter_iterations
        ));
    }
    for (key, light) in &lights {
        hud.lines
            .push(format!("{}, {} lux", key.describe(), light.illuminance));
    }
}
