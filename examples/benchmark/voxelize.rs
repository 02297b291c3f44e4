//! `voxelize`: the voxelize pass's GPU time against particle size and placement, at a fixed
//! particle count.
//!
//! [`PARTICLES`] particles of radius `r`, chosen so that `r / h` (the radius in fine voxels of
//! the default settings) takes each value of [`RADII_IN_VOXELS`]: spread, with centres in a unit
//! cube; and piled, every centre on one point but for one at each corner of the cube (so that
//! the grid, and `r / h`, are the same).
//! Every measured frame touches the particles, so every pass reruns; the voxelize pass's GPU
//! time is the median over [`ROUNDS`] rounds of `--frames` frames, each round visiting every size. Depositing a particle's kernel on every fine voxel
//! of its support costs `(r / h)³`; docs/illumination.md §1 says how the coarse density levels
//! bound it.

use super::*;

/// Particles in every measured cloud.
const PARTICLES: usize = 1000;

/// Rounds over the sizes.
const ROUNDS: usize = 3;

/// The particles' radius in fine voxels, `r / h`.
const RADII_IN_VOXELS: [f32; 7] = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0];

/// A 64×64 view of a cloud of [`PARTICLES`] particles of `r / h = q` at `settings`, holding about
/// the same optical thickness whatever `q`.
fn scene(q: f32, piled: bool, settings: CloudQualitySettings) -> Scene {
    let m = settings.light_resolution() as f32;
    // The grid's side is the centres' unit cube plus one radius each side: h = (1 + 2r) / m.
    let r = q / (m - 2.0 * q);
    let side = 1.0 + 2.0 * r;
    // Total mass ≈ side³, so the mean density, and the cloud's look, hardly change with `q`.
    let density = side.powi(3) / (PARTICLES as f32 * r.powi(3) * 0.957);
    let mut rng = SplitMix64::new(7);
    let particles = (0..PARTICLES)
        .map(|i| {
            let spread = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) - 0.5;
            let corner = Vec3::new((i & 1) as f32, (i >> 1 & 1) as f32, (i >> 2 & 1) as f32) - 0.5;
            Particle {
                position: match (piled, i < 8) {
                    (false, _) => spread,
                    (true, true) => corner,
                    (true, false) => Vec3::splat(0.1),
                },
                radius: r,
                density,
            }
        })
        .collect();
    let medium = bevy_particle_clouds::Medium {
        extinction: 2.0,
        albedo: 0.9,
        ..Default::default()
    };
    let light = Vec3::new(-0.5, -1.0, -0.3);
    one_cloud_scene(3.0 * side, 40.0, light, medium, particles, settings)
}

/// A 64×64 view, from `distance` metres along +z with a vertical field of view of `fov` degrees,
/// of one cloud at the origin of `medium` and `particles`, lit by one light of irradiance 1
/// travelling along `light`, over black, at `settings`.
pub(crate) fn one_cloud_scene(
    distance: f32,
    fov: f32,
    light: Vec3,
    medium: bevy_particle_clouds::Medium,
    particles: Vec<Particle>,
    settings: CloudQualitySettings,
) -> Scene {
    Scene {
        camera: bevy_particle_clouds::scene::SceneCamera {
            position: Vec3::new(0.0, 0.0, distance),
            look_at: Vec3::ZERO,
            up: Vec3::Y,
            vertical_fov_degrees: fov,
            width: 64,
            height: 64,
        },
        background: Vec3::ZERO,
        lights: vec![bevy_particle_clouds::LightSample {
            direction: light.normalize(),
            irradiance: Vec3::ONE,
        }],
        clouds: vec![bevy_particle_clouds::scene::ResolvedCloud {
            translation: Vec3::ZERO,
            medium,
            particles,
        }],
        objects: Vec::new(),
        fog: None,
        shadow_map_resolution: bevy_particle_clouds::scene::DEFAULT_SHADOW_MAP_RESOLUTION,
        settings,
    }
}

/// The options of `benchmark voxelize`.
#[derive(clap::Args, Debug)]
pub(crate) struct VoxelizeArgs {
    #[command(flatten)]
    pub(crate) frames: Frames,
}

pub(crate) fn voxelize_benchmark(args: &VoxelizeArgs, out: &Path) -> Result<(), String> {
    let settings = CloudQualitySettings::default();
    let cases: Vec<(f32, bool)> = RADII_IN_VOXELS
        .iter()
        .flat_map(|&q| [(q, false), (q, true)])
        .collect();
    let mut benches: Vec<Bench> = cases
        .iter()
        .map(|&(q, piled)| Bench::new(&scene(q, piled, settings)))
        .collect();
    let adapter = benches[0].adapter.clone();
    // Rounds that visit every case in turn, so that a slow drift of the machine favours none.
    let mut times = vec![Vec::new(); cases.len()];
    for round in 0..ROUNDS {
        for ((&(q, piled), b), times) in cases.iter().zip(&mut benches).zip(&mut times) {
            let (_, timing) = b.measure(args.frames.count());
            eprintln!(
                "benchmark: voxelize, round {round}, r/h = {q}, piled {piled}: {:.2} ms (GPU)",
                timing.pass_ms[0]
            );
            times.push(timing.pass_ms[0]);
        }
    }
    let ms: Vec<f64> = times.into_iter().map(median).collect();
    let base = ms[0];
    let mut table = format!(
        "Adapter: `{adapter}`. {PARTICLES} particles of radius `r`, default settings (fine grid \
         {m}³), spread over a unit cube or piled on one point. The voxelize pass's GPU time (all \
         of its dispatches), median of {} rounds × {} frames that each re-voxelize, the rounds \
         visiting the cases in turn.\n\n\
         | r / h | support voxels per particle (4π/3 (r/h)³) | spread, ms | / r = h | piled, ms | piled / spread |\n\
         |---:|---:|---:|---:|---:|---:|\n",
        ROUNDS,
        args.frames.count(),
        m = settings.light_resolution(),
    );
    for (&q, pair) in RADII_IN_VOXELS.iter().zip(ms.chunks(2)) {
        let support = 4.0 / 3.0 * std::f32::consts::PI * q.powi(3);
        let _ = writeln!(
            table,
            "| {q} | {support:.0} | {:.2} | {:.1}× | {:.2} | {:.2}× |",
            pair[0],
            pair[0] / base,
            pair[1],
            pair[1] / pair[0]
        );
    }
    let path = out.join("voxelize.md");
    std::fs::write(&path, &table).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    println!("{table}");
    eprintln!("benchmark: wrote {}", path.display());
    Ok(())
}
