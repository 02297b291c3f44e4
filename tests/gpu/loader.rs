//! Particle files through Bevy's `AssetServer` (`loader::ParticlesLoader`, registered by the
//! plugin): PLY and CSV load into `Particles`; a malformed file produces an
//! `AssetLoadFailedEvent<Particles>` whose message names the file and the line.
//!
//! Also checks that `assets/bunny.ply` (the `snow_bunny` example's small bunny) is exactly what
//! [`bunny_ply_particles`] generates. To regenerate it after changing `generators::bunny_sdf`:
//! `WRITE_BUNNY_PLY=1 cargo test --test gpu loader::bunny_ply`.

use std::{path::Path, time::Duration};

use bevy::{
    asset::{AssetLoadFailedEvent, LoadState},
    prelude::*,
};
use bevy_particle_clouds::headless::{self, FrameRecorder, SceneTarget};
use bevy_particle_clouds::{
    Medium, Particle, ParticleCloud, Particles, generators,
    particle_files::{self, ParticleAttributes},
};

use crate::common;

/// The small bunny shipped as `assets/bunny.ply`: 3 000 particles of radius 0.1 m over
/// `generators::bunny_sdf`, seed 5 (binary PLY, 60 KB).
fn bunny_ply_particles() -> Particles {
    let (lo, hi) = generators::BUNNY_BOUNDS;
    generators::from_sdf(generators::bunny_sdf, lo, hi, 0.1, 3000, 5)
}

/// Loads `path` (under `assets/`) and updates until it has loaded or failed (at most ~10 s).
fn load(app: &mut App, path: &str) -> (Handle<Particles>, LoadState) {
    let handle: Handle<Particles> = app.world().resource::<AssetServer>().load(path.to_string());
    wait_for(app, handle, path)
}

/// Loads `path` with the loader settings `attributes` (the `AssetServer`'s load builder).
fn load_with(
    app: &mut App,
    path: &'static str,
    attributes: ParticleAttributes,
) -> (Handle<Particles>, LoadState) {
    let handle: Handle<Particles> = app
        .world()
        .resource::<AssetServer>()
        .load_builder()
        .with_settings(move |a: &mut ParticleAttributes| *a = attributes.clone())
        .load(path);
    wait_for(app, handle, path)
}

/// Updates until `handle` has loaded or failed (at most ~10 s).
fn wait_for(
    app: &mut App,
    handle: Handle<Particles>,
    path: &str,
) -> (Handle<Particles>, LoadState) {
    for _ in 0..1000 {
        headless::update(app).unwrap();
        let state = app.world().resource::<AssetServer>().load_state(&handle);
        if matches!(state, LoadState::Loaded | LoadState::Failed(_)) {
            return (handle, state);
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    panic!("{path} neither loaded nor failed within 1000 updates");
}

/// Every `AssetLoadFailedEvent<Particles>` seen, as (path, error text), collected each frame
/// (messages live only two updates).
#[derive(Resource, Default)]
struct Failures(Vec<(String, String)>);

fn collect_failures(
    mut events: MessageReader<AssetLoadFailedEvent<Particles>>,
    mut failures: ResMut<Failures>,
) {
    failures.0.extend(
        events
            .read()
            .map(|e| (e.path.to_string(), e.error.to_string())),
    );
}

fn app() -> App {
    let mut app = common::headless_app();
    app.init_resource::<Failures>()
        .add_systems(Update, collect_failures);
    app
}

fn failures(app: &App) -> Vec<(String, String)> {
    app.world().resource::<Failures>().0.clone()
}

fn particle(x: f32, y: f32, z: f32, radius: f32, density: f32) -> Particle {
    Particle {
        position: Vec3::new(x, y, z),
        radius,
        density,
    }
}

#[test]
fn loads_csv_and_ply_files() {
    let mut app = app();
    let (csv, state) = load(&mut app, "test_files/puffs.csv");
    assert!(matches!(state, LoadState::Loaded), "{state:?}");
    let (ply, state) = load(&mut app, "test_files/pair.ply");
    assert!(matches!(state, LoadState::Loaded), "{state:?}");
    let assets = app.world().resource::<Assets<Particles>>();
    assert_eq!(
        assets.get(&csv).unwrap().particles,
        vec![
            particle(0.0, 0.0, 0.0, 0.5, 1.0),
            particle(1.5, 0.25, -2.0, 0.75, 0.5),
            particle(-1.0, 2.0, 3.0, 1.0, 2.0)
        ]
    );
    assert_eq!(
        assets.get(&ply).unwrap().particles,
        vec![
            particle(0.0, 0.0, 0.0, 0.5, 1.0),
            particle(1.0, 2.0, 3.0, 0.25, 0.5)
        ]
    );
    assert!(failures(&app).is_empty());
}

#[test]
fn the_shipped_bunny_loads_through_the_asset_server() {
    let mut app = app();
    let (handle, state) = load(&mut app, "bunny.ply");
    assert!(matches!(state, LoadState::Loaded), "{state:?}");
    let bunny = app
        .world()
        .resource::<Assets<Particles>>()
        .get(&handle)
        .unwrap()
        .clone();
    assert_eq!(bunny.particles.len(), 3000);
    assert!(
        bunny
            .particles
            .iter()
            .all(|p| generators::bunny_sdf(p.position) < 0.0
                && p.radius == 0.1
                && p.density == 1.0)
    );
    let (lo, hi) = bunny.bounds().unwrap();
    // Feet on the ground, ears about 2 m up, about 1.9 m from tail to nose.
    assert!(
        lo.y > -0.2 && lo.y < 0.0 && hi.y > 1.9 && hi.y < 2.1,
        "bounds {lo} {hi}"
    );
    assert!(hi.x - lo.x > 1.7 && hi.x - lo.x < 2.2, "bounds {lo} {hi}");
}

#[test]
fn bunny_ply_is_the_generated_bunny() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/bunny.ply");
    let expected = bunny_ply_particles();
    if std::env::var_os("WRITE_BUNNY_PLY").is_some() {
        particle_files::write_ply_binary(&path, &expected.particles).unwrap();
    }
    let shipped = particle_files::read_ply(&path).unwrap();
    assert_eq!(shipped.len(), 3000);
    assert!(
        shipped == expected.particles,
        "assets/bunny.ply differs from the generator: run `WRITE_BUNNY_PLY=1 cargo test --test gpu loader::bunny_ply`"
    );
    let bytes = std::fs::metadata(&path).unwrap().len();
    assert_eq!(
        bytes,
        3000 * 20 + 202,
        "a small binary file: 20 bytes per particle plus the header"
    );
}

#[test]
fn malformed_files_fail_with_the_line() {
    let mut app = app();
    let (csv, state) = load(&mut app, "test_files/bad_value.csv");
    assert!(matches!(state, LoadState::Failed(_)), "{state:?}");
    let (ply, state) = load(&mut app, "test_files/truncated.ply");
    assert!(matches!(state, LoadState::Failed(_)), "{state:?}");
    let (invalid, state) = load(&mut app, "test_files/negative_radius.csv");
    assert!(matches!(state, LoadState::Failed(_)), "{state:?}");
    let assets = app.world().resource::<Assets<Particles>>();
    assert!(
        assets.get(&csv).is_none() && assets.get(&ply).is_none() && assets.get(&invalid).is_none()
    );

    let failures = failures(&app);
    assert_eq!(failures.len(), 3, "{failures:#?}");
    let message = |name: &str| {
        failures
            .iter()
            .find(|(path, _)| path.ends_with(name))
            .map(|(_, e)| e.clone())
            .unwrap_or_else(|| panic!("no failure for {name}: {failures:#?}"))
    };
    let csv = message("bad_value.csv");
    assert!(
        csv.contains("bad_value.csv: line 3: column `z` is not a number; found `oops`"),
        "{csv}"
    );
    let ply = message("truncated.ply");
    assert!(
        ply.contains("truncated.ply: line 12: vertex 2: the line ends before property `density`"),
        "{ply}"
    );
    let invalid = message("negative_radius.csv");
    assert!(
        invalid.contains("particle 1: `radius` is -0.5; it must be > 0 and at most 1e15 m"),
        "{invalid}"
    );
}

/// Houdini-style points (centimetres, `pscale`, no density, extra columns with quoted commas)
/// load through the loader's settings.
#[test]
fn loader_settings_map_attributes_and_scale() {
    let mut app = app();
    let houdini = ParticleAttributes {
        radius: "pscale".into(),
        default_density: Some(0.8),
        scale: 0.01,
        ..default()
    };
    let (handle, state) = load_with(&mut app, "test_files/houdini_points.csv", houdini);
    assert!(matches!(state, LoadState::Loaded), "{state:?}");
    let assets = app.world().resource::<Assets<Particles>>();
    let particle = |x: f32, y: f32, radius: f32| Particle {
        position: Vec3::new(x, y, 0.0),
        radius,
        density: 0.8,
    };
    let got = &assets.get(&handle).unwrap().particles;
    assert_eq!(got.len(), 2);
    for (a, b) in got
        .iter()
        .zip([particle(0.1, 0.0, 0.5), particle(-0.1, 0.2, 0.25)])
    {
        assert!((a.position - b.position).length() < 1e-6 && (a.radius - b.radius).abs() < 1e-6);
        assert_eq!(a.density, b.density);
    }
}

/// A 32×24 view of a cloud loaded from `path` under the app's asset folder, lit from above-left.
fn view_of_loaded_cloud(app: &mut App, handle: Handle<Particles>) -> SceneTarget {
    let image = headless::float_target(app, 32, 24);
    let camera = headless::spawn_linear_camera(
        app,
        image.clone(),
        Transform::from_xyz(0.0, 0.3, 5.0).looking_at(Vec3::ZERO, Vec3::Y),
        50.0,
        Vec3::ZERO,
    );
    headless::spawn_light(app, Vec3::new(-0.4, -1.0, -0.3), Vec3::ONE);
    app.world_mut().spawn((
        ParticleCloud::new(handle).with_medium(Medium {
            extinction: 5.0,
            albedo: 0.9,
            ..default()
        }),
        common::quality(16, 4),
        Transform::IDENTITY,
    ));
    SceneTarget {
        image,
        width: 32,
        height: 24,
        camera,
        drawable_clouds: 1,
    }
}

fn steady_image(app: &mut App, target: &SceneTarget) -> Vec<[f32; 4]> {
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(app, &mut recorder, 1, 100).unwrap();
    headless::capture(app, &mut recorder, &target.image)
        .unwrap()
        .pixels
}

/// Updates until `done`, at most about 10 s.
fn update_until(app: &mut App, what: &str, done: impl Fn(&App) -> bool) {
    for _ in 0..1000 {
        headless::update(app).unwrap();
        if done(app) {
            return;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    panic!("{what} did not happen within 1000 updates");
}

/// A particle file replaced while the app runs, reloaded as Bevy's file watcher reloads it
/// (`AssetServer::reload`): a malformed replacement fails with a message naming the file and its
/// line, and the cloud keeps its last good particles on screen; a valid one is picked up.
#[test]
fn a_replaced_file_reloads_and_a_malformed_one_keeps_the_last_good_particles() {
    let dir = std::env::temp_dir().join(format!("bpc_reload_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("cloud.csv");
    let ball = generators::sphere(1.0, 0.3, 60, 3).particles;
    particle_files::write_csv(&file, &ball).unwrap();
    let mut app = common::headless_app_with(headless::plugins().set(AssetPlugin {
        file_path: dir.display().to_string(),
        ..default()
    }));
    app.init_resource::<Failures>()
        .add_systems(Update, collect_failures);
    let (handle, state) = load(&mut app, "cloud.csv");
    assert!(matches!(state, LoadState::Loaded), "{state:?}");
    let target = view_of_loaded_cloud(&mut app, handle.clone());
    let first = steady_image(&mut app, &target);
    assert!(
        first.iter().any(|p| p[0] > 1e-3),
        "the cloud covers some of the black background"
    );
    let particles = |app: &App| {
        app.world()
            .resource::<Assets<Particles>>()
            .get(&handle)
            .map(|p| p.particles.clone())
    };

    std::fs::write(&file, "x,y,z,radius,density\n0,0,oops,1,1\n").unwrap();
    app.world().resource::<AssetServer>().reload("cloud.csv");
    update_until(&mut app, "the malformed file's failure", |app| {
        !failures(app).is_empty()
    });
    for (path, error) in failures(&app) {
        assert!(path.ends_with("cloud.csv"), "{path}");
        assert!(
            error.contains("cloud.csv: line 2: column `z` is not a number"),
            "{error}"
        );
    }
    assert_eq!(
        particles(&app),
        Some(ball.clone()),
        "the last good particles stay"
    );
    let kept = steady_image(&mut app, &target);
    let largest_change = first
        .iter()
        .zip(&kept)
        .map(|(a, b)| (a[0] - b[0]).abs().max((a[2] - b[2]).abs()))
        .fold(0.0f32, f32::max);
    assert!(
        largest_change < 1e-5,
        "the cloud on screen changed by {largest_change}"
    );

    let smaller: Vec<Particle> = ball
        .iter()
        .map(|p| Particle {
            position: p.position * 0.5 + Vec3::X,
            ..*p
        })
        .collect();
    particle_files::write_csv(&file, &smaller).unwrap();
    let failed = failures(&app).len();
    app.world().resource::<AssetServer>().reload("cloud.csv");
    update_until(&mut app, "the valid replacement's load", |app| {
        particles(app).as_ref() == Some(&smaller)
    });
    let replaced = steady_image(&mut app, &target);
    let largest_change = first
        .iter()
        .zip(&replaced)
        .map(|(a, b)| (a[0] - b[0]).abs())
        .fold(0.0f32, f32::max);
    assert!(
        largest_change > 1e-2,
        "the new particles are drawn: {largest_change}"
    );
    assert_eq!(failures(&app).len(), failed, "{:#?}", failures(&app));
}
