//! `sky-map`: what the sky map (docs/illumination.md §10) costs and how far it is from the
//! sky the clouds leave, on a scene with lit objects under a sky (default
//! `cloud_over_ground_sky`):
//!
//! - **error**, with the f64 CPU references (no adapter): `1 - V` along a line of ground points
//!   through the clouds' footprint, against 8192 directions through the fine density grid, for
//!   several direction counts, through the scattering grid (the map's) or the fine one, and read
//!   from maps of several sizes (bilinear between texels, as the surfaces read it);
//! - **cost**, on the adapter: the wall time of frames that move one cloud (which refills the
//!   maps) with the sky and under a black sky (no sky map), for the scene's cloud and for a field
//!   of 100 of them (16³, 4 iterations), two rounds each.

use std::{fmt::Write, path::Path};

use bevy::{math::DVec3, prelude::*};
use bevy_particle_clouds::{
    ParticleCloud,
    headless::{self, FrameRecorder},
    reference::{
        composite::CloudPlacement,
        illumination::{
            CloudIllumination, illuminate_scene, shadow_map_depth_at, sky_occlusion_at,
        },
    },
    scene::{ObjectShape, Scene},
    shadow_maps::{SKY_MAP_DIRECTIONS, ShadowMapPlacement},
};

use super::{named_scenes, write_report};

/// The options of `benchmark sky-map`.
#[derive(clap::Args, Debug)]
pub(crate) struct SkyMapArgs {
    /// Only these scenes (comma-separated names; default: `cloud_over_ground_sky`): scenes under a
    /// sky.
    #[arg(long, value_delimiter = ',')]
    pub(crate) scenes: Option<Vec<String>>,
}

/// `benchmark sky-map`: the sky map's error and cost on each chosen scene (default
/// `cloud_over_ground_sky`); writes `DIR/sky_map.md`.
pub(crate) fn sky_map_benchmark(args: &SkyMapArgs, out: &Path) -> Result<(), String> {
    let mut md = String::from(
        "# The sky map\n\nWhat the clouds hide of the sky from the ground (docs/illumination.md \
         §10), measured by `cargo run --example benchmark -- sky-map`.\n",
    );
    for (bench, scene) in named_scenes(args.scenes.as_deref(), "cloud_over_ground_sky")? {
        let name = bench.name;
        if scene.background == Vec3::ZERO {
            return Err(format!(
                "`{name}` has a black sky; sky-map takes a scene under a sky"
            ));
        }
        eprintln!("benchmark: {name}: the sky map's error (CPU)");
        md.push_str(&error(name, &scene, &scene.settings));
        eprintln!("benchmark: {name}: the sky map's cost");
        md.push_str(&cost(&scene)?);
    }
    write_report(out, "sky_map.md", &md)
}

/// Directions of the exact sky transmittance the others are held against.
const EXACT_DIRECTIONS: u32 = 8192;
/// Direction counts of the error table.
const DIRECTIONS: [u32; 4] = [32, 64, 128, 256];
/// Sky map sizes of the error table (texels per side).
const MAP_SIZES: [u32; 3] = [32, 64, 128];
/// Ground points along the line through the clouds' footprint.
const POINTS: usize = 41;

/// The error tables, markdown.
pub(crate) fn error(
    name: &str,
    scene: &Scene,
    settings: &bevy_particle_clouds::CloudQualitySettings,
) -> String {
    let lit = illuminate_scene(scene, settings);
    let placed: Vec<(&CloudIllumination, CloudPlacement)> = lit
        .iter()
        .zip(&scene.clouds)
        .filter_map(|(c, cloud)| {
            Some((
                c.as_ref()?,
                CloudPlacement::at(cloud.translation.as_dvec3()),
            ))
        })
        .collect();
    // The CPU reference marches the scattering grid, as the map does; the same clouds with their
    // fine grids in its place are the finer view.
    let fine: Vec<CloudIllumination> = placed
        .iter()
        .map(|(c, _)| CloudIllumination {
            grid: c.fine.clone(),
            ..(*c).clone()
        })
        .collect();
    let fine: Vec<_> = fine
        .iter()
        .zip(&placed)
        .map(|(c, (_, p))| (c, *p))
        .collect();
    let height = scene.cloud_ground().map_or(0.0, |g| g.height);
    let spheres = spheres(&placed);
    let Some(map) = ShadowMapPlacement::sky(&spheres, height, 64, 0) else {
        return format!("\n`{name}`: no cloud above the ground, no sky map.\n");
    };
    let points = ground_line(&map, &spheres);
    let exact: Vec<f64> = points
        .iter()
        .map(|&x| sky_occlusion_at(&fine, x, EXACT_DIRECTIONS))
        .collect();
    let largest = exact.iter().copied().fold(0.0, f64::max);
    let stats = |f: &dyn Fn(DVec3) -> f64| {
        let d: Vec<f64> = points.iter().zip(&exact).map(|(&x, &o)| f(x) - o).collect();
        let max = d.iter().map(|v| v.abs()).fold(0.0, f64::max);
        let rms = (d.iter().map(|v| v * v).sum::<f64>() / d.len() as f64).sqrt();
        format!("{max:.4} / {rms:.4}")
    };
    let mut md = String::new();
    let _ = writeln!(
        md,
        "\n## `{name}`\n\nThe clouds' occlusion of the sky `1 - V` at {POINTS} ground points on a \
         line through their footprint (the largest {largest:.3}), against {EXACT_DIRECTIONS} \
         directions through the fine grid; max / RMS of the difference, in fractions of the \
         sky's irradiance. The map takes {SKY_MAP_DIRECTIONS} directions through the scattering \
         grid.\n\n| directions | through the fine grid | through the scattering grid |\n|---:|---:|---:|"
    );
    for k in DIRECTIONS {
        let through_fine = stats(&|x| sky_occlusion_at(&fine, x, k));
        let through_grid = stats(&|x| sky_occlusion_at(&placed, x, k));
        let _ = writeln!(md, "| {k} | {through_fine} | {through_grid} |");
    }
    let _ = writeln!(
        md,
        "\nRead from a map (bilinear between texels, as the surfaces read it), through the \
         scattering grid:\n\n| texels per side | texel (m) | {} |\n|---:|---:|{}",
        DIRECTIONS.map(|k| format!("{k} directions")).join(" | "),
        "---:|".repeat(DIRECTIONS.len())
    );
    for size in MAP_SIZES {
        let map = ShadowMapPlacement::sky(&spheres, height, size, 0).expect("clouds above");
        let row: Vec<String> = DIRECTIONS
            .iter()
            .map(|&k| {
                let n = map.size;
                let values: Vec<f64> = (0..n * n)
                    .map(|t| sky_occlusion_at(&placed, map.texel_point(t % n, t / n).as_dvec3(), k))
                    .collect();
                stats(&|x| shadow_map_depth_at(&map, &values, x))
            })
            .collect();
        let _ = writeln!(md, "| {size} | {:.3} | {} |", map.texel, row.join(" | "));
    }
    md
}

/// The clouds' world spheres, as the main world places the map from them.
fn spheres(placed: &[(&CloudIllumination, CloudPlacement)]) -> Vec<(Vec3, f32)> {
    placed
        .iter()
        .map(|(c, p)| {
            let centre = p.world_point(c.fine.centre).as_vec3();
            (centre, (0.5 * 3f64.sqrt() * c.fine.side * p.scale) as f32)
        })
        .collect()
}

/// [`POINTS`] points of the map's plane on a slanting line through the clouds' footprint, from
/// one side of the map's middle half to the other.
fn ground_line(map: &ShadowMapPlacement, spheres: &[(Vec3, f32)]) -> Vec<DVec3> {
    let centre = spheres.iter().map(|(c, _)| *c).sum::<Vec3>() / spheres.len() as f32;
    let half = 0.25 * map.texel * map.size as f32;
    let along = Vec2::new(1.0, 0.33).normalize();
    (0..POINTS)
        .map(|i| {
            let s = -half + 2.0 * half * i as f32 / (POINTS - 1) as f32;
            let xz = centre.xz() + along * s;
            DVec3::new(xz.x as f64, -map.w_end as f64, xz.y as f64)
        })
        .collect()
}

/// The cost table, markdown: per cloud count and shadow map resolution, the median and fastest
/// frame that moves one cloud, with and without the sky, two rounds.
pub(crate) fn cost(scene: &Scene) -> Result<String, String> {
    let mut md = String::from(
        "\n| clouds | light maps | sky map | frame moving a cloud, sky (ms) | black sky (ms) | the sky map |\n\
         |---:|---:|---:|---:|---:|---:|\n",
    );
    let mut adapter = String::new();
    for (clouds, resolution) in [(1, 512), (1, 1024), (100, 1024)] {
        let mut rounds = Vec::new();
        for _ in 0..2 {
            for sky in [true, false] {
                let (name, ms) = moving_frames(&field(scene, clouds, resolution, sky))?;
                adapter = name;
                rounds.push((sky, ms));
            }
        }
        let median = |sky: bool| {
            let mut all: Vec<f64> = rounds
                .iter()
                .filter(|r| r.0 == sky)
                .flat_map(|r| r.1.clone())
                .collect();
            all.sort_by(f64::total_cmp);
            all[all.len() / 2]
        };
        let (with, without) = (median(true), median(false));
        let size = bevy_particle_clouds::shadow_maps::sky_map_size(resolution);
        let _ = writeln!(
            md,
            "| {clouds} | {resolution}² | {size}² | {with:.0} | {without:.0} | {:+.0} ms |",
            with - without
        );
    }
    Ok(format!(
        "\nCost on `{adapter}` (wall time, medians of two rounds of 6 frames each):\n{md}"
    ))
}

/// `scene` with `clouds` copies of its first cloud (a 10-wide field, 12 m apart, 10 m up, at 16³
/// and 4 iterations, beyond one), its maps at `resolution`, with its sky or a black one.
fn field(scene: &Scene, clouds: usize, resolution: u32, sky: bool) -> Scene {
    let mut scene = scene.clone();
    scene.shadow_map_resolution = resolution;
    if !sky {
        scene.background = Vec3::ZERO;
    }
    if clouds > 1 {
        scene.settings.volume_resolution = 16;
        scene.settings.scatter_iterations = 4;
        scene.camera.position = Vec3::new(0.0, 40.0, 160.0);
        scene.camera.look_at = Vec3::ZERO;
        let first = scene.clouds[0].clone();
        scene.clouds = (0..clouds)
            .map(|i| {
                let mut c = first.clone();
                let (a, b) = ((i % 10) as f32, (i / 10) as f32);
                c.translation = Vec3::new(a * 12.0 - 54.0, 10.0, b * 12.0 - 54.0);
                c
            })
            .collect();
        for object in &mut scene.objects {
            if let ObjectShape::Cuboid(extents) = &mut object.shape {
                *extents = Vec3::new(400.0, extents.y, 400.0);
            }
        }
    }
    scene
}

/// The adapter, and the wall times of 6 frames that each move one cloud by 1 cm (another each
/// frame where there are several), once the scene is steady.
fn moving_frames(scene: &Scene) -> Result<(String, Vec<f64>), String> {
    let mut app = headless::app_with(headless::plugins().disable::<bevy::winit::WinitPlugin>());
    let adapter = headless::adapter_name(&mut app);
    let target = headless::spawn_scene(&mut app, scene);
    let mut recorder = FrameRecorder::default();
    let fail = |e: headless::HeadlessError| e.to_string();
    headless::render_until_steady(&mut app, &mut recorder, target.drawable_clouds, 60)
        .map_err(fail)?;
    let mut ms = Vec::new();
    for i in 0..6 {
        let mut clouds = app
            .world_mut()
            .query_filtered::<&mut Transform, With<ParticleCloud>>();
        let count = scene.clouds.len();
        if let Some(mut t) = clouds.iter_mut(app.world_mut()).nth(i * 7 % count) {
            t.translation.x += if i % 2 == 0 { 0.01 } else { -0.01 };
        }
        ms.push(recorder.frame(&mut app).map_err(fail)?.wall_ms);
    }
    Ok((adapter, ms))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The error's ground points lie on the map's plane, across the clouds' footprint and within
    /// the map.
    #[test]
    fn the_ground_line_crosses_the_clouds_on_the_plane() {
        let spheres = [
            (Vec3::new(2.0, 6.0, -1.0), 1.5),
            (Vec3::new(6.0, 7.0, 3.0), 1.0),
        ];
        let map = ShadowMapPlacement::sky(&spheres, 0.5, 64, 0).unwrap();
        let line = ground_line(&map, &spheres);
        assert_eq!(line.len(), POINTS);
        let middle = line[POINTS / 2];
        assert!(
            (middle.x - 4.0).abs() < 1e-4 && (middle.z - 1.0).abs() < 1e-4,
            "{middle}"
        );
        for x in line {
            assert!((x.y - 0.5).abs() < 1e-6);
            let a = (x.x as f32 - map.corner.x) / map.texel;
            let b = (x.z as f32 - map.corner.y) / map.texel;
            assert!(
                (0.0..64.0).contains(&a) && (0.0..64.0).contains(&b),
                "{a} {b}"
            );
        }
    }

    /// The field of the cost table: 100 copies 12 m apart at 16³, the lit ground widened under
    /// them; one cloud and a black sky otherwise as the scene.
    #[test]
    fn the_cost_field_copies_the_scenes_cloud() {
        let scene = Scene::from_ron_str(
            "(camera: (position: (0.0, 1.0, 8.0), look_at: (0.0, 1.0, 0.0), vertical_fov_degrees: 40.0, \
             width: 16, height: 12), background: (0.1, 0.2, 0.3), \
             lights: [(direction: (0.0, -1.0, 0.0), irradiance: (1.0, 1.0, 1.0))], \
             clouds: [(translation: (0.0, 3.0, 0.0), medium: (extinction: 2.0, albedo: 0.9), particles: Inline([(position: (0.0, 0.0, 0.0), radius: 1.0, density: 1.0)]))], \
             objects: [(shape: Cuboid((10.0, 1.0, 10.0)), translation: (0.0, -0.5, 0.0), color: (0.0, 0.0, 0.0), reflectance: (0.3, 0.3, 0.3))])",
            std::path::Path::new("."),
        )
        .unwrap();
        let many = field(&scene, 100, 1024, true);
        assert_eq!(
            (many.clouds.len(), many.settings.volume_resolution),
            (100, 16)
        );
        assert_eq!(many.clouds[11].translation, Vec3::new(-42.0, 10.0, -42.0));
        assert_eq!(
            many.objects[0].shape,
            ObjectShape::Cuboid(Vec3::new(400.0, 1.0, 400.0))
        );
        let one = field(&scene, 1, 512, false);
        assert_eq!(
            (one.clouds.len(), one.background, one.shadow_map_resolution),
            (1, Vec3::ZERO, 512)
        );
        assert_eq!(one.clouds[0].translation, scene.clouds[0].translation);
    }
}
