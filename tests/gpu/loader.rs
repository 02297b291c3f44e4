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
use bevy_particle_clouds::headless;
use bevy_particle_clouds::{
    Particle, Particles, generators,
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
        csv.contains("bad_value.csv: line 3: column `z` is `oops`, which is not a number"),
        "{csv}"
    );
    let ply = message("truncated.ply");
    assert!(
        ply.contains("truncated.ply: line 12: vertex 2: the line ends before property `density`"),
        "{ply}"
    );
    let invalid = message("negative_radius.csv");
    assert!(
        invalid.contains("particle 1: `radius` is -0.5; it must be finite and > 0"),
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
