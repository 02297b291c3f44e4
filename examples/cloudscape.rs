//! A sky full of clouds: 100 cumulus (300,000 particles) over a ground plane that takes their
//! shadows (Bevy's `StandardMaterial`, extended: `CloudShadowedMaterial`), under a sun that
//! moves, seen from a camera that flies around them. Level of detail lowers the resolution of the
//! clouds that are small on screen, and the clouds are drawn at half the window's size.
//!
//! ```text
//! cargo run --example cloudscape                              # a window
//! cargo run --example cloudscape -- --clouds 400 --particles 1200000
//! cargo run --example cloudscape -- --screenshot cloudscape.png [--size 800x450] [--frames N]
//! ```
//!
//! The on-screen text shows the frame time, the passes run in the last frame (and their GPU
//! times), and how many clouds are at each level of detail. Controls: Space stops or starts the
//! sun, F the flight; arrows turn the sun by hand; drag or A/D/W/S orbit; wheel or +/- zoom;
//! L cycles the level of detail (2, 4 pixels per voxel, off, 1), B the re-light budget (10
//! clouds per frame, 25, no limit), R the draw method (rasterised, or computed: the same image,
//! `DrawMethod::Compute`).
//!
//! With the sun still and the camera still, no cloud is re-lit: a frame only draws. With the
//! camera flying and the sun still, clouds are not re-lit either: a level change waits for the
//! next re-lighting. With the sun moving, the clouds take turns: at most `CloudRelightBudget`
//! clouds are re-lit per frame, the others keep their previous lighting until their turn, and a
//! re-lit cloud restarts its scattering from its previous solution (`warm_scatter_iterations`,
//! 4 iterations instead of the 8 of a full solve). Shade, gather and scatter take the same
//! dispatches for all the clouds of a resolution (the on-screen dispatch count).

mod support;

use std::process::ExitCode;

use bevy::{platform::collections::HashMap, prelude::*};
use bevy_particle_clouds::{cloud_shadowed_material::CloudShadowedMaterial, headless, prelude::*};
use support::{Example, Hud, HudLines, KeyLight, Options, OrbitCamera, PassCounts};

const EXAMPLE: Example = Example {
    title: "bevy_particle_clouds: a cloudscape",
    controls: "Space: sun on/off | F: flight on/off | L: level of detail | B: re-light budget | R: raster/compute | arrows: sun | drag, A/D/W/S: orbit | wheel, +/-: zoom",
    steady: false,
};

/// The sun's azimuth rate while it moves, radians per second.
const SUN_RATE: f32 = 0.05;
/// The camera's orbit rate while it flies, radians per second.
const FLIGHT_RATE: f32 = 0.04;
/// The level-of-detail settings L cycles through, pixels per scattering voxel (0: off).
const PIXELS_PER_VOXEL: [f32; 4] = [2.0, 4.0, 0.0, 1.0];
/// The re-light budgets B cycles through, clouds per frame (0: no limit).
const BUDGETS: [u32; 3] = [10, 25, 0];

/// A sky full of cumulus over a ground plane, under a moving sun.
#[derive(clap::Parser)]
struct Args {
    #[command(flatten)]
    common: Options,
    /// Clouds, on a jittered grid.
    #[arg(long, default_value_t = 100, value_parser = clap::value_parser!(u32).range(1..=1000))]
    clouds: u32,
    /// Particles in all the clouds together.
    #[arg(long, default_value_t = 300_000, value_parser = clap::value_parser!(u32).range(1000..=5_000_000))]
    particles: u32,
}

/// Whether the sun moves and the camera flies.
#[derive(Resource, Clone, Copy)]
struct Motion {
    sun: bool,
    flight: bool,
}

fn main() -> ExitCode {
    let args: Args = support::parse_args();
    let (clouds, particles) = (args.clouds, args.particles);
    // The turning-sun picture turns the sun itself, step by step, from a still camera.
    let moving = args.common.sun_turn_gif.is_none();
    support::run(EXAMPLE, args.common, move |app| {
        // The ground takes the clouds' shadows of the sun through a 1024² map (1 m texels over
        // the 800 m the clouds span).
        headless::enable_cloud_shadow_maps(app, 1024, 1);
        app.insert_resource(DefaultCloudQuality(CloudQualitySettings {
            volume_resolution: 32,
            // The series alone: a sky of small clouds spends its budget on re-lighting more of
            // them, not on the deep orders of each.
            scatter_iterations: 8,
            scatter_coarse_cycles: 0,
            light_supersampling: 2,
            ..default()
        }))
        .insert_resource(CloudLevelOfDetail {
            pixels_per_voxel: PIXELS_PER_VOXEL[0],
            min_resolution: 12,
        })
        .insert_resource(CloudRelightBudget(BUDGETS[0]))
        .insert_resource(Motion {
            sun: moving,
            flight: moving,
        })
        .add_systems(
            Startup,
            move |commands: Commands, assets: ResMut<Assets<Particles>>| {
                spawn_clouds(commands, assets, clouds, particles)
            },
        )
        .add_systems(Startup, setup)
        .add_systems(Update, (controls, move_sun, fly))
        .add_systems(Update, describe.in_set(HudLines));
    })
}

/// The clouds of [`generators::cloudscape`]: `clouds` cumulus of `particles / clouds` particles
/// each, 25–60 m across, their bases at 70–110 m, on a jittered grid 80 m apart.
fn spawn_clouds(
    mut commands: Commands,
    mut assets: ResMut<Assets<Particles>>,
    clouds: u32,
    particles: u32,
) {
    for cloud in generators::cloudscape(clouds, particles, 7) {
        let handle = assets.add(cloud.particles);
        commands.spawn((
            ParticleCloud::new(handle).with_medium(cloud.medium),
            Transform::from_translation(cloud.translation),
        ));
    }
}

fn setup(
    mut commands: Commands,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<CloudShadowedMaterial>>,
) {
    let orbit = OrbitCamera {
        target: Vec3::new(0.0, 90.0, 0.0),
        distance: 420.0,
        yaw: 0.3,
        pitch: 0.12,
    };
    let sun = (30f32.to_radians(), 30f32.to_radians());
    let albedo = support::GROUND_ALBEDO;
    // A game's `StandardMaterial` ground, extended to take the clouds' shadows.
    let ground = support::cloud_shadowed_ground(
        &mut meshes,
        &mut materials,
        5000.0,
        Color::linear_rgb(albedo.x, albedo.y, albedo.z),
    );
    support::spawn_outdoor(&mut commands, ground, sun, orbit);
    // The cloud shadows are lit by the sky, as on a Lambertian ground.
    commands.insert_resource(support::sky_ambient_on_rough_ground());
}

fn controls(
    keys: Res<ButtonInput<KeyCode>>,
    mut motion: ResMut<Motion>,
    mut lod: ResMut<CloudLevelOfDetail>,
    mut budget: ResMut<CloudRelightBudget>,
    mut quality: ResMut<DefaultCloudQuality>,
) {
    if keys.just_pressed(KeyCode::KeyR) {
        quality.draw_method = match quality.draw_method {
            DrawMethod::Raster => DrawMethod::Compute,
            DrawMethod::Compute => DrawMethod::Raster,
        };
    }
    if keys.just_pressed(KeyCode::KeyB) {
        let at = BUDGETS.iter().position(|&b| b == budget.0).unwrap_or(0);
        budget.0 = BUDGETS[(at + 1) % BUDGETS.len()];
    }
    if keys.just_pressed(KeyCode::Space) {
        motion.sun = !motion.sun;
    }
    if keys.just_pressed(KeyCode::KeyF) {
        motion.flight = !motion.flight;
    }
    if keys.just_pressed(KeyCode::KeyL) {
        let at = PIXELS_PER_VOXEL
            .iter()
            .position(|&p| p == lod.pixels_per_voxel)
            .unwrap_or(0);
        lod.pixels_per_voxel = PIXELS_PER_VOXEL[(at + 1) % PIXELS_PER_VOXEL.len()];
    }
}

fn move_sun(time: Res<Time>, motion: Res<Motion>, mut sun: Query<(&mut KeyLight, &mut Transform)>) {
    if !motion.sun {
        return;
    }
    for (mut light, mut transform) in &mut sun {
        light.azimuth += SUN_RATE * time.delta_secs();
        *transform = light.transform();
    }
}

fn fly(
    time: Res<Time>,
    motion: Res<Motion>,
    mut camera: Query<(&mut OrbitCamera, &mut Transform)>,
) {
    if !motion.flight {
        return;
    }
    for (mut orbit, mut transform) in &mut camera {
        orbit.yaw += FLIGHT_RATE * time.delta_secs();
        *transform = orbit.transform();
    }
}

fn describe(
    mut hud: ResMut<Hud>,
    (motion, lod, budget): (
        Res<Motion>,
        Res<CloudLevelOfDetail>,
        Res<CloudRelightBudget>,
    ),
    (quality, counts): (Res<DefaultCloudQuality>, Res<PassCounts>),
    sun: Query<&KeyLight>,
    clouds: Query<(&ParticleCloud, Option<&CloudLod>)>,
    particles: Res<Assets<Particles>>,
) {
    hud.lines.clear();
    let count: usize = clouds
        .iter()
        .filter_map(|(c, _)| particles.get(&c.particles))
        .map(|p| p.particles.len())
        .sum();
    hud.lines.push(format!(
        "{} clouds, {count} particles, at most {}^3 voxels, {} scatter iterations ({} warm), drawn by {:?}",
        clouds.iter().len(),
        quality.volume_resolution,
        quality.scatter_iterations,
        quality.warm_scatter_iterations,
        quality.draw_method
    ));
    let mut levels: HashMap<u32, usize> = HashMap::default();
    for (_, l) in &clouds {
        let resolution = l
            .filter(|_| lod.enabled())
            .map_or(quality.volume_resolution, |l| l.resolution);
        *levels.entry(resolution).or_default() += 1;
    }
    let mut levels: Vec<(u32, usize)> = levels.into_iter().collect();
    levels.sort();
    let levels: Vec<String> = levels.iter().map(|(r, n)| format!("{r}^3 x{n}")).collect();
    let mode = if lod.enabled() {
        format!("{} pixels per voxel", lod.pixels_per_voxel)
    } else {
        "off".into()
    };
    hud.lines.push(format!(
        "level of detail {mode}: {} (a change waits until the cloud is re-lit)",
        levels.join(", ")
    ));
    let budget = match budget.0 {
        0 => "re-light budget: none (every cloud re-lit when the sun moves)".into(),
        n => format!("re-light budget: {n} clouds per frame (the others wait their turn)"),
    };
    hud.lines.push(format!(
        "{budget}; {} compute dispatches last frame",
        counts.dispatches_last
    ));
    for light in &sun {
        hud.lines.push(format!(
            "{}, {}; camera {}",
            light.describe(),
            if motion.sun { "moving" } else { "still" },
            if motion.flight { "flying" } else { "still" }
        ));
    }
}
