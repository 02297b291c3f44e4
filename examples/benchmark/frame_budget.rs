//! `frame-budget`: what three game-sized scenes cost per frame, pass by pass, beside each
//! pass's memory-bandwidth floor (issue #11's real-GPU table):
//!
//! - **paper 38k**: `paper_38k_5lights` (the paper's 38,000 particles, 128³ volumes, 5 lights)
//!   at 1920×1080, and again drawn at half size (`cloud_target_scale` 0.5);
//! - **snow bunny**: the paper's Figure 5, 1.2 million particles filling a bunny, 128³, 5
//!   scattering iterations, two lights, 1920×1080 (the `snow_bunny` example's big bunny);
//! - **cloudscape**: the `cloudscape` example's sky, 100 cumulus of 3,000 particles over a lit
//!   ground under a blue sky, 32³ × 8 iterations with level of detail (2 pixels per voxel),
//!   drawn at half size, at most 10 clouds re-lit a frame, 1920×1080.
//!
//! `--view WxH` measures them at another size; `--settings` replaces the chosen scenes' quality
//! settings, one row per `--settings`. The draw's fragments (the billboards' screen rectangles,
//! overlaps counted) give its time per fragment, a rate to hold against the adapter's.
//!
//! Re-lit: frames that rerun every pass for every cloud (the particles touched). Lights moving:
//! frames where every light turns by a degree, which rerun what a light's turn needs (shade,
//! gather, the scattering's warm restart) within the scene's re-light budget, and the draw.
//! Static: a frame where nothing changed, the draw only.
//!
//! The floor of a pass is the bytes it must at least read and write once, at `--bandwidth`
//! (default 4.8 TB/s, an H200's HBM3e), summed over the clouds at their chosen resolutions:
//! [`floor_bytes`] says what each pass counts. Writes `DIR/frame_budget.csv` and `.md`.

use std::fmt::Write as _;

use bevy_particle_clouds::{
    CloudLod, CloudRedraw, CloudRelightBudget, LightSample, Medium, scene::ResolvedCloud,
    scene::SceneCamera, scene::SceneObject, settings::COARSE_GRID_ORDERS,
};

use super::*;

/// Bytes of one particle as the shaders read it (`GpuParticle`: two vec4).
const PARTICLE_BYTES: f64 = 32.0;
/// Bytes of a pixel of the cloud target (`Rgba16Float`).
const PIXEL_BYTES: f64 = 8.0;
/// The frame goals of issue #11 for the paper's scene on a real GPU, ms.
const GOAL_RELIT_MS: f64 = 2.0;
const GOAL_STATIC_MS: f64 = 0.5;

/// One scene of the frame budget.
struct BudgetScene {
    name: &'static str,
    scene: Scene,
    /// Level of detail, pixels per scattering voxel.
    lod: Option<f32>,
    /// Clouds re-lit per frame (`CloudRelightBudget`); none: no limit.
    relight_budget: Option<u32>,
}

fn camera_at(position: Vec3, look_at: Vec3) -> SceneCamera {
    SceneCamera {
        position,
        look_at,
        up: Vec3::Y,
        vertical_fov_degrees: 40.0,
        width: 1920,
        height: 1080,
    }
}

/// The unit travel direction of a light at `azimuth` and `elevation` (degrees).
fn travel(azimuth: f32, elevation: f32) -> Vec3 {
    let (a, e) = (azimuth.to_radians(), elevation.to_radians());
    -Vec3::new(e.cos() * a.cos(), e.sin(), e.cos() * a.sin())
}

/// [`paper_38k`] drawn at half size (`cloud_target_scale` 0.5): the fill-rate saving.
fn paper_38k_half() -> Result<BudgetScene, String> {
    let mut b = paper_38k()?;
    b.scene.settings.cloud_target_scale = 0.5;
    b.name = "paper 38k, 5 lights, ½ target";
    Ok(b)
}

fn paper_38k() -> Result<BudgetScene, String> {
    let bench = SCENES
        .iter()
        .find(|s| s.name == "paper_38k_5lights")
        .ok_or("no paper_38k_5lights scene")?;
    let scene = load_scene(bench)?;
    Ok(BudgetScene {
        name: "paper 38k, 5 lights",
        scene,
        lod: None,
        relight_budget: None,
    })
}

/// The `snow_bunny` example's big bunny: 1.2 million particles of radius 25 mm.
fn snow_bunny() -> BudgetScene {
    const COUNT: usize = 1_200_000;
    let (lo, hi) = generators::BUNNY_BOUNDS;
    let batch = 100_000;
    let particles = (0..COUNT / batch)
        .flat_map(|i| {
            eprintln!(
                "benchmark: frame budget, bunny particles {} / {COUNT}",
                i * batch
            );
            generators::from_sdf(generators::bunny_sdf, lo, hi, 0.025, batch, 1000 + i as u64)
                .particles
        })
        .collect();
    BudgetScene {
        name: "snow bunny, 1.2M",
        scene: Scene {
            camera: camera_at(Vec3::new(2.7, 2.0, 5.4), Vec3::new(0.4, 1.0, 0.4)),
            background: Vec3::new(0.03, 0.05, 0.1),
            lights: vec![
                LightSample {
                    direction: travel(60.0, 35.0),
                    irradiance: Vec3::new(3.0, 2.6, 2.1),
                },
                LightSample {
                    direction: travel(200.0, 25.0),
                    irradiance: Vec3::new(1.1, 1.4, 2.0),
                },
            ],
            clouds: vec![ResolvedCloud {
                translation: Vec3::ZERO,
                medium: Medium {
                    extinction: 1.5,
                    albedo: 0.99,
                    ..Default::default()
                },
                particles,
            }],
            objects: Vec::new(),
            fog: None,
            shadow_map_resolution: bevy_particle_clouds::scene::DEFAULT_SHADOW_MAP_RESOLUTION,
            settings: CloudQualitySettings {
                volume_resolution: 128,
                scatter_iterations: 5,
                scatter_coarse_cycles: 0,
                // The fine grid of 256 the H200 tables were measured with (the default 4 would
                // be 512 there).
                light_supersampling: 2,
                ..default()
            },
        },
        lod: None,
        relight_budget: None,
    }
}

/// The `cloudscape` example's sky and settings, seen from its camera's starting place.
fn cloudscape() -> BudgetScene {
    let clouds = generators::cloudscape(100, 300_000, 7)
        .into_iter()
        .map(|c| ResolvedCloud {
            translation: c.translation,
            medium: c.medium,
            particles: c.particles.particles,
        })
        .collect();
    let ground = SceneObject {
        shape: bevy_particle_clouds::scene::ObjectShape::Cuboid(Vec3::new(5000.0, 1.0, 5000.0)),
        translation: Vec3::new(0.0, -0.5, 0.0),
        color: Vec3::ZERO,
        reflectance: Vec3::new(0.03, 0.055, 0.02),
    };
    let target = Vec3::new(0.0, 90.0, 0.0);
    let offset = Quat::from_euler(EulerRot::YXZ, 0.3, -0.12, 0.0) * Vec3::Z * 420.0;
    BudgetScene {
        name: "cloudscape, 100 clouds",
        scene: Scene {
            camera: camera_at(target + offset, target),
            background: Vec3::new(0.2, 0.35, 0.6),
            lights: vec![LightSample {
                direction: travel(30.0, 30.0),
                irradiance: Vec3::new(3.0, 2.9, 2.7),
            }],
            clouds,
            objects: vec![ground],
            fog: None,
            shadow_map_resolution: bevy_particle_clouds::scene::DEFAULT_SHADOW_MAP_RESOLUTION,
            settings: CloudQualitySettings {
                volume_resolution: 32,
                scatter_iterations: 8,
                scatter_coarse_cycles: 0,
                light_supersampling: 2,
                cloud_target_scale: 0.5,
                ..default()
            },
        },
        lod: Some(2.0),
        relight_budget: Some(10),
    }
}

/// What one cloud holds, for the floor.
#[derive(Clone, Copy, Debug)]
struct CloudShape {
    particles: f64,
    /// Voxels per side of the scattering grid and of the fine grid (each light volume).
    n: f64,
    m: f64,
    /// vec4 per voxel of a scattering order: 4 with angular moments (an anisotropic medium).
    order_vec4: f64,
}

/// Each cloud of the bench as the floors count it, from its own entity: its particles and
/// medium, at the resolution its level of detail chose (else `settings`').
fn cloud_shapes(bench: &mut Bench, settings: &CloudQualitySettings) -> Vec<CloudShape> {
    let world = bench.app.world_mut();
    let clouds: Vec<(ParticleCloud, Option<u32>)> = world
        .query::<(&ParticleCloud, Option<&CloudLod>)>()
        .iter(world)
        .map(|(c, lod)| (c.clone(), lod.map(|l| l.resolution)))
        .collect();
    let assets = world.resource::<Assets<Particles>>();
    clouds
        .iter()
        .map(|(cloud, chosen)| {
            let settings = CloudQualitySettings {
                volume_resolution: chosen.unwrap_or(settings.volume_resolution),
                ..*settings
            };
            CloudShape {
                particles: assets
                    .get(&cloud.particles)
                    .map_or(0, |p| p.particles.len()) as f64,
                n: settings.volume_resolution as f64,
                m: settings.light_resolution() as f64,
                order_vec4: if cloud.anisotropy != 0.0 { 4.0 } else { 1.0 },
            }
        })
        .collect()
}

/// The bytes `pass` must at least read and write once in a re-lit frame (the draw: a static
/// frame's), given every cloud's shape, `lights`, each cloud's scattering sweeps (its iterations,
/// and its coarse-grid cycles' sweeps, a coarse one counted an eighth) and the cloud target's
/// pixels:
///
/// - voxelize: the particles read, the fine and the scattering grid's density written;
/// - shade: the fine density read, one optical depth per light written (4 B a voxel each);
/// - gather: each light's optical depth read at the scattering grid's voxels, its density
///   read, the source written;
/// - scatter: per sweep the previous order and the density read, the next order written;
/// - sort: the particles read, their order written; view volume: the density read, the
///   optical depth from the camera written;
/// - draw: the particles read, every target pixel read and written once.
fn floor_bytes(
    pass: CloudPass,
    clouds: &[CloudShape],
    lights: f64,
    sweeps: f64,
    pixels: f64,
) -> f64 {
    let per_cloud = |c: &CloudShape| {
        let (n3, m3) = (c.n.powi(3), c.m.powi(3));
        match pass {
            CloudPass::Voxelize => c.particles * PARTICLE_BYTES + 4.0 * (m3 + n3),
            CloudPass::Shade => 4.0 * m3 * (1.0 + lights),
            CloudPass::Gather => n3 * (4.0 * lights + 4.0 + 16.0 * c.order_vec4),
            CloudPass::Scatter => sweeps * n3 * (32.0 * c.order_vec4 + 4.0),
            CloudPass::Sort => c.particles * (PARTICLE_BYTES + 4.0),
            CloudPass::ViewVolume => n3 * 8.0,
            CloudPass::Draw => c.particles * PARTICLE_BYTES,
        }
    };
    let sum: f64 = clouds.iter().map(per_cloud).sum();
    if pass == CloudPass::Draw {
        sum + 2.0 * PIXEL_BYTES * pixels
    } else {
        sum
    }
}

/// The pixels the particles' billboards cover in a target of `scale` times the view's size,
/// overlaps counted each time: the draw's fragments, about (each billboard's quad as the vertex
/// stage draws it, [`quad_fragments`]).
fn billboard_fragments(scene: &Scene, scale: f32) -> f64 {
    let camera = &scene.camera;
    let forward = (camera.look_at - camera.position).normalize();
    let right = forward.cross(camera.up).normalize();
    let target = Target {
        basis: [right, right.cross(forward), forward],
        width: camera.width as f32 * scale,
        height: camera.height as f32 * scale,
        vertical_fov: camera.vertical_fov_degrees.to_radians(),
        near: PerspectiveProjection::default().near,
    };
    scene
        .clouds
        .iter()
        .flat_map(|c| {
            c.particles
                .iter()
                .map(|p| (c.translation + p.position, p.radius))
        })
        .map(|(centre, radius)| quad_fragments(&target, centre - camera.position, radius))
        .sum()
}

/// A view's target, as [`quad_fragments`] sees it.
struct Target {
    /// The view's right, up and forward axes (unit).
    basis: [Vec3; 3],
    /// Pixels.
    width: f32,
    height: f32,
    /// Radians.
    vertical_fov: f32,
    /// The near plane's depth, metres.
    near: f32,
}

/// The pixels of `target` that the billboard of a particle of `radius` at `to_centre` (from the
/// eye) covers, as `billboard.wgsl`'s vertex stage draws it: the rectangle of the screen that
/// the sphere's part beyond the near plane covers ([`screen_span`] per axis, 0.1 % to spare
/// either side); nothing when it lies behind the near plane.
fn quad_fragments(target: &Target, to_centre: Vec3, radius: f32) -> f64 {
    let [right, up, forward] = target.basis;
    let depth = to_centre.dot(forward);
    if depth + radius <= target.near {
        return 0.0;
    }
    // Pixels per unit of (lateral offset ÷ depth).
    let focal = 0.5 * target.height / (0.5 * target.vertical_fov).tan();
    let pixels = |offset: f32, extent: f32| {
        let screen = 1.01 * 0.5 * extent / focal;
        let (lo, hi) = screen_span(offset, depth, radius, target.near, screen);
        let pad = 0.001 * (hi - lo);
        let to_pixel = |slope: f32| (0.5 * extent + focal * slope).clamp(0.0, extent);
        (to_pixel(hi + pad) - to_pixel(lo - pad)).max(0.0)
    };
    (pixels(to_centre.dot(right), target.width) * pixels(to_centre.dot(up), target.height)) as f64
}

/// The extent, in units of lateral offset ÷ depth, of the part beyond the near plane (depth
/// `near`) of a sphere of radius `r` centred at lateral offset `x` and depth `z` along one
/// screen axis, clamped to `±screen`: `screen_span` of `billboard.wgsl`.
fn screen_span(x: f32, z: f32, r: f32, near: f32, screen: f32) -> (f32, f32) {
    let d2 = x * x + z * z;
    let (mut lo, mut hi) = (screen, -screen);
    if d2 > r * r {
        let t = (d2 - r * r).sqrt();
        for side in [-1.0, 1.0] {
            let (px, pz) = (t * x - side * r * z, t * z + side * r * x);
            if pz * t / d2 >= near {
                (lo, hi) = (lo.min(px / pz), hi.max(px / pz));
            }
        }
    }
    let h = r * r - (near - z) * (near - z);
    if h > 0.0 {
        let e = h.sqrt();
        (lo, hi) = (lo.min((x - e) / near), hi.max((x + e) / near));
    }
    (lo.clamp(-screen, screen), hi.max(lo).clamp(-screen, screen))
}

/// One measured scene.
struct BudgetRow {
    name: String,
    timing: Timing,
    /// Per pass, GPU ms of a frame where every light turned (median), and that frame's total.
    moving_ms: [f64; PASSES],
    moving_total_ms: f64,
    /// GPU ms of the draw in a static frame when the view keeps its clouds
    /// (`CloudRedraw::WhenChanged`, the default; `timing`'s static frame draws them again).
    kept_ms: f64,
    runs: [u32; PASSES],
    dispatches: [u32; PASSES],
    floor_ms: [f64; PASSES],
    particles: usize,
    resolutions: String,
    /// The draw's fragments in a static frame, about ([`billboard_fragments`]).
    fragments: f64,
    /// The cloud target's size over the view's.
    target_scale: f32,
}

/// Every light turns by a degree each frame (a moving sun): the median GPU ms of each pass over
/// `frames` such frames, after two that settle into it, and of their totals. What reruns is what a
/// light's turn needs (shade, gather, the scattering's warm restart, the draw); with a re-light
/// budget, only that many clouds a frame.
fn moving_lights(bench: &mut Bench, frames: usize) -> ([f64; PASSES], f64) {
    let mut ids = Vec::new();
    for k in 0..frames + 2 {
        bench.turn_lights(1.0);
        let i = bench.frame();
        if k >= 2 {
            ids.push(i);
        }
    }
    for _ in 0..4 {
        bench
            .recorder
            .drain(&mut bench.app)
            .expect("the benchmark scene renders"); // late GPU timestamps
    }
    let stats: Vec<&FrameStats> = ids.iter().map(|&i| &bench.recorder.frames[i]).collect();
    let ms = |f: &FrameStats, p: CloudPass| f.gpu_ms.get(&p).copied().unwrap_or(0.0);
    let per_pass = CloudPass::ALL.map(|p| median(stats.iter().map(|f| ms(f, p)).collect()));
    let totals = stats
        .iter()
        .map(|f| CloudPass::ALL.iter().map(|&p| ms(f, p)).sum())
        .collect();
    (per_pass, median(totals))
}

fn measure(
    (b, dispatch): (&BudgetScene, SweepDispatch),
    frames: usize,
    bandwidth: f64,
    adapter: &mut String,
) -> BudgetRow {
    let mut bench = Bench::new(&b.scene);
    bench.app.insert_resource(dispatch);
    *adapter = bench.adapter.clone();
    if let Some(pixels_per_voxel) = b.lod {
        bench.set_level_of_detail(pixels_per_voxel, 12);
    }
    let (_, timing) = bench.measure(frames);
    bench.app.insert_resource(CloudRedraw::WhenChanged);
    let (kept, _) = bench.static_frames(frames);
    bench.app.insert_resource(CloudRedraw::EveryFrame);
    let (runs, dispatches) = bench.relit_counts();
    // A game's moving sun: the clouds take turns within the re-light budget.
    if let Some(clouds) = b.relight_budget {
        bench.app.insert_resource(CloudRelightBudget(clouds));
    }
    let (moving_ms, moving_total_ms) = moving_lights(&mut bench, frames);
    let settings = b.scene.settings;
    let shapes = cloud_shapes(&mut bench, &settings);
    let scale = settings.cloud_target_scale as f64;
    let pixels = (b.scene.camera.width * b.scene.camera.height) as f64 * scale * scale;
    let clouds = shapes.len().max(1) as f64;
    let lights = b.scene.lights.len() as f64;
    let iterations = settings.scatter_iterations as f64;
    // A coarse-grid cycle moves the bytes of two orders, and of its coarse orders at an eighth.
    let cycles = settings.coarse_cycles() as f64;
    let sweeps = iterations + cycles * (2.0 + COARSE_GRID_ORDERS as f64 / 8.0);
    let floor_ms = CloudPass::ALL.map(|p| {
        let bytes = floor_bytes(p, &shapes, lights, sweeps, pixels);
        // The share of the clouds' work that ran: the clouds in view for the view passes,
        // those re-lit and their iterations for the others.
        let all_runs = match p {
            CloudPass::Shade => clouds * lights,
            CloudPass::Scatter => clouds * iterations,
            _ => clouds,
        };
        let share = match p {
            CloudPass::Draw => 1.0,
            _ => (runs[p as usize] as f64 / all_runs.max(1.0)).min(1.0),
        };
        1e3 * bytes * share / bandwidth
    });
    let mut resolutions: Vec<u32> = shapes.iter().map(|s| s.n as u32).collect();
    resolutions.sort_unstable();
    resolutions.dedup();
    BudgetRow {
        name: b.name.to_string(),
        timing,
        moving_ms,
        moving_total_ms,
        kept_ms: median(kept),
        runs,
        dispatches,
        floor_ms,
        particles: b.scene.clouds.iter().map(|c| c.particles.len()).sum(),
        fragments: billboard_fragments(&b.scene, settings.cloud_target_scale),
        target_scale: settings.cloud_target_scale,
        resolutions: resolutions
            .iter()
            .map(|r| format!("{r}³"))
            .collect::<Vec<_>>()
            .join(", "),
    }
}

/// Makes one of the scenes (the paper's reads its particle file).
type SceneBuilder = fn() -> Result<BudgetScene, String>;

/// The options of `benchmark frame-budget`.
#[derive(clap::Args, Debug)]
pub(crate) struct FrameBudgetArgs {
    /// Only these scenes (comma-separated): `paper`, `paper-half` (drawn at half size), `snow`,
    /// `cloudscape` (default: all four).
    #[arg(long, value_delimiter = ',')]
    pub(crate) scenes: Option<Vec<String>>,
    /// The view's size, pixels.
    #[arg(long, default_value = "1920x1080", value_parser = parse_view)]
    pub(crate) view: (u32, u32),
    /// Measure the chosen scenes at these settings (RON, as a scene file's `settings`) instead
    /// of their own, one row each. Repeatable.
    #[arg(long = "settings", value_name = "RON", value_parser = parse_settings)]
    pub(crate) settings: Vec<CloudQualitySettings>,
    /// How the billboards are drawn, each in turn (comma-separated: `raster`, `compute`).
    #[arg(long, value_delimiter = ',', default_value = "raster", value_parser = parse_draw_method)]
    pub(crate) draw_methods: Vec<DrawMethod>,
    /// How the scattering sweep dispatches an order's direction pairs, each in turn
    /// (comma-separated: `per-pair`, the default, and `per-order`; `SweepDispatch`).
    #[arg(long, value_delimiter = ',', default_value = "per-pair", value_parser = parse_sweep_dispatch)]
    pub(crate) sweep_dispatches: Vec<SweepDispatch>,
    /// The memory bandwidth the floors are computed at, TB/s (default: an H200's HBM3e).
    #[arg(long, default_value_t = 4.8)]
    pub(crate) bandwidth: f64,
    #[command(flatten)]
    pub(crate) frames: Frames,
}

pub(crate) fn frame_budget_benchmark(args: &FrameBudgetArgs, out: &Path) -> Result<(), String> {
    let bandwidth = args.bandwidth * 1e12;
    let wanted = |key: &str| {
        args.scenes
            .as_ref()
            .is_none_or(|names| names.iter().any(|n| n == key))
    };
    let builders: [(&str, SceneBuilder); 4] = [
        ("paper", paper_38k),
        ("paper-half", paper_38k_half),
        ("snow", || Ok(snow_bunny())),
        ("cloudscape", || Ok(cloudscape())),
    ];
    let mut adapter = String::new();
    let mut rows = Vec::new();
    for (key, build) in builders {
        if !wanted(key) {
            continue;
        }
        let mut scene = build()?;
        (scene.scene.camera.width, scene.scene.camera.height) = args.view;
        // `--settings`: each replaces the scene's own, one row each.
        let variants: Vec<Option<CloudQualitySettings>> = if args.settings.is_empty() {
            vec![None]
        } else {
            args.settings.iter().copied().map(Some).collect()
        };
        let methods = args.draw_methods.iter().copied();
        let dispatches = &args.sweep_dispatches;
        for ((settings, method), dispatch) in variants
            .into_iter()
            .flat_map(|s| methods.clone().map(move |m| (s, m)))
            .flat_map(|v| dispatches.iter().map(move |&d| (v, d)))
        {
            // `--draw-methods`: each scene (each variant) drawn each way, labelled when
            // computed.
            let mut label = scene.name.to_string();
            if let Some(settings) = settings {
                scene.scene.settings = settings;
            }
            scene.scene.settings.draw_method = method;
            if settings.is_some() {
                label = format!("{label}: {}", setting_label(&scene.scene.settings));
            } else if method == DrawMethod::Compute {
                label = format!("{label}, compute");
            }
            if dispatch == SweepDispatch::PerOrder {
                label = format!("{label}, per order");
            }
            eprintln!("benchmark: frame budget, {label}");
            let mut row = measure(
                (&scene, dispatch),
                args.frames.count(),
                bandwidth,
                &mut adapter,
            );
            row.name = label;
            eprintln!(
                "benchmark: frame budget, {}: re-lit {:.2} ms, static {:.2} ms (GPU)",
                row.name, row.timing.gpu_ms_total, row.timing.gpu_ms_static
            );
            rows.push(row);
        }
    }
    write_frame_budget(args, out, &adapter, &rows)
}

fn write_frame_budget(
    args: &FrameBudgetArgs,
    out: &Path,
    adapter: &str,
    rows: &[BudgetRow],
) -> Result<(), String> {
    let mut csv = String::from(
        "adapter,scene,particles,resolutions,pass,gpu_ms,floor_ms,runs,dispatches,gpu_ms_relit,gpu_ms_static,gpu_ms_moving,gpu_ms_moving_frame,gpu_ms_static_kept\n",
    );
    let mut md = format!(
        "Adapter: `{adapter}`, {}×{}. GPU ms: median of {} frames that rerun every pass (the \
         draw: a static frame's). Floor: the bytes the pass must at least read and write once, \
         at {} TB/s. Runs and dispatches: in a re-lit frame.\n\n\
         | scene | pass | GPU ms | floor ms | GPU ÷ floor | runs | dispatches | lights moving, GPU ms |\n\
         |---|---|---:|---:|---:|---:|---:|---:|\n",
        args.view.0,
        args.view.1,
        args.frames.count(),
        args.bandwidth
    );
    for r in rows {
        for (i, pass) in CloudPass::ALL.iter().enumerate() {
            let (ms, floor) = (r.timing.pass_ms[i], r.floor_ms[i]);
            let _ = writeln!(
                csv,
                "\"{adapter}\",\"{}\",{},\"{}\",{},{ms:.4},{floor:.4},{},{},{:.4},{:.4},{:.4},{:.4},{:.4}",
                r.name,
                r.particles,
                r.resolutions,
                pass.name(),
                r.runs[i],
                r.dispatches[i],
                r.timing.gpu_ms_total,
                r.timing.gpu_ms_static,
                r.moving_ms[i],
                r.moving_total_ms,
                r.kept_ms
            );
            if r.runs[i] == 0 && *pass != CloudPass::Draw {
                continue;
            }
            let ratio = if floor > 0.0 {
                format!("{:.0}×", ms / floor)
            } else {
                "–".into()
            };
            let _ = writeln!(
                md,
                "| {} | {} | {ms:.3} | {floor:.3} | {ratio} | {} | {} | {:.3} |",
                r.name,
                pass.name(),
                r.runs[i],
                r.dispatches[i],
                r.moving_ms[i]
            );
        }
        let floor: f64 = r.floor_ms.iter().sum();
        let _ = writeln!(
            md,
            "| **{}** ({} particles, {}) | **re-lit frame** | **{:.3}** | {floor:.3} | {:.0}× | | | **{:.3}** |",
            r.name,
            r.particles,
            r.resolutions,
            r.timing.gpu_ms_total,
            r.timing.gpu_ms_total / floor.max(1e-9),
            r.moving_total_ms
        );
        let _ = writeln!(
            md,
            "| **{}** | **static frame** | **{:.3}** | {:.3} | | | | |",
            r.name, r.timing.gpu_ms_static, r.floor_ms[6]
        );
        let _ = writeln!(
            md,
            "| **{}** | **static frame, view kept** | **{:.3}** | | | | | |",
            r.name, r.kept_ms
        );
    }
    // The draw per fragment: a rate to hold against the adapter's fill rate.
    let _ = writeln!(
        md,
        "\nBillboard fragments of a static frame (each billboard's screen rectangle as the vertex stage draws it, overlaps \
         counted) and the draw's time per fragment:\n\n\
         | scene | fragments (millions) | per pixel of the target | draw ns per fragment |\n\
         |---|---:|---:|---:|"
    );
    for r in rows {
        let draw_ms = r.timing.pass_ms[CloudPass::Draw as usize];
        let scale = r.target_scale as f64;
        let (width, height) = args.view;
        let pixels = (width * height) as f64 * scale * scale;
        let _ = writeln!(
            md,
            "| {} | {:.1} | {:.1} | {:.2} |",
            r.name,
            r.fragments / 1e6,
            r.fragments / pixels,
            1e6 * draw_ms / r.fragments.max(1.0)
        );
    }
    if let Some(paper) = rows.iter().find(|r| r.name.starts_with("paper")) {
        let mark = |ok: bool| if ok { "✓" } else { "✗" };
        let _ = writeln!(
            md,
            "\nThe paper's scene against issue #11's goals: its 5 lights moving {:.3} ms and everything \
             re-lit {:.3} ms (goal ≤ {GOAL_RELIT_MS}) {}, static {:.3} ms with the view kept (the \
             default; goal ≤ {GOAL_STATIC_MS}) {}, {:.3} ms drawn again {}.",
            paper.moving_total_ms,
            paper.timing.gpu_ms_total,
            mark(paper.timing.gpu_ms_total.max(paper.moving_total_ms) <= GOAL_RELIT_MS),
            paper.kept_ms,
            mark(paper.kept_ms <= GOAL_STATIC_MS),
            paper.timing.gpu_ms_static,
            mark(paper.timing.gpu_ms_static <= GOAL_STATIC_MS)
        );
    }
    std::fs::create_dir_all(out).map_err(|e| format!("cannot create {}: {e}", out.display()))?;
    for (name, text) in [("frame_budget.csv", &csv), ("frame_budget.md", &md)] {
        let path = out.join(name);
        std::fs::write(&path, text).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    }
    println!("{md}");
    eprintln!(
        "benchmark: wrote frame_budget.csv and frame_budget.md in {}",
        out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 400×300 target, 90° vertical field of view (150 pixels per unit of offset ÷ depth),
    /// looking along -z.
    fn target() -> Target {
        Target {
            basis: [Vec3::X, Vec3::Y, Vec3::NEG_Z],
            width: 400.0,
            height: 300.0,
            vertical_fov: std::f32::consts::FRAC_PI_2,
            near: 0.1,
        }
    }

    #[test]
    fn a_billboard_covers_its_quad_as_the_vertex_stage_draws_it() {
        let t = target();
        // On the axis, 10 m away, r = 0.5: the tangents' slopes are ±r / sqrt(z² - r²), 0.1 %
        // to spare either side.
        let side = 1.002 * 2.0 * 150.0 * 0.5 / (100.0f64 - 0.25).sqrt();
        let on_axis = quad_fragments(&t, Vec3::new(0.0, 0.0, -10.0), 0.5);
        assert!(
            (on_axis - side * side).abs() < 1e-2 * on_axis,
            "{on_axis} against {}",
            side * side
        );
        // Off the axis the silhouette stretches; across the right edge, a part of it is drawn.
        let at_edge = Vec3::new(200.0 / 15.0, 0.0, -10.0);
        let wide = Target {
            width: 1200.0,
            ..target()
        };
        let whole = quad_fragments(&wide, at_edge, 0.5);
        let edge = quad_fragments(&t, at_edge, 0.5);
        assert!(whole > on_axis, "{whole} against {on_axis}");
        assert!(
            0.3 * whole < edge && edge < 0.7 * whole,
            "{edge} against {whole}"
        );
        assert_eq!(quad_fragments(&t, Vec3::new(30.0, 0.0, -10.0), 0.5), 0.0);
        // Behind the near plane nothing; holding the eye, the whole target; reaching the near
        // plane beside the eye, a part of it.
        assert_eq!(quad_fragments(&t, Vec3::new(0.0, 0.0, 1.0), 0.5), 0.0);
        assert_eq!(
            quad_fragments(&t, Vec3::new(0.0, 0.0, -0.3), 0.5),
            400.0 * 300.0
        );
        let beside = quad_fragments(&t, Vec3::new(0.8, 0.0, -0.3), 0.5);
        assert!(beside > 0.0 && beside < 0.5 * 400.0 * 300.0, "{beside}");
    }

    /// The span holds every point of the sphere beyond the near plane, and its ends are reached.
    #[test]
    fn a_screen_span_bounds_the_sphere_beyond_the_near_plane_tightly() {
        let near = 0.1;
        for (x, z, r) in [
            (0.0, 10.0, 0.5),
            (8.0, 10.0, 0.5),
            (-3.0, 2.0, 1.5),
            (1.0, 0.3, 0.5),
            (-0.6, 0.05, 0.7),
        ] {
            let (lo, hi) = screen_span(x, z, r, near, 1e3);
            let (mut seen_lo, mut seen_hi) = (f32::INFINITY, f32::NEG_INFINITY);
            // The disc of (x, z) beyond the near plane, sampled densely: boundary and inside.
            for i in 0..2000 {
                let a = i as f32 / 2000.0 * std::f32::consts::TAU;
                for k in 0..=20 {
                    let (px, pz) = (
                        x + r * k as f32 / 20.0 * a.cos(),
                        z + r * k as f32 / 20.0 * a.sin(),
                    );
                    if pz < near {
                        continue;
                    }
                    let slope = px / pz;
                    assert!(
                        slope >= lo - 1e-4 * (1.0 + lo.abs())
                            && slope <= hi + 1e-4 * (1.0 + hi.abs()),
                        "({x}, {z}, {r}): {slope} outside {lo}..{hi}"
                    );
                    (seen_lo, seen_hi) = (seen_lo.min(slope), seen_hi.max(slope));
                }
            }
            // And where the disc crosses the near plane.
            let h = r * r - (near - z) * (near - z);
            for k in 0..=2000 {
                let px = x + h.max(0.0).sqrt() * (k as f32 / 1000.0 - 1.0);
                if h > 0.0 {
                    (seen_lo, seen_hi) = (seen_lo.min(px / near), seen_hi.max(px / near));
                }
            }
            let width = hi - lo;
            assert!(
                seen_lo - lo < 1e-3 * width && hi - seen_hi < 1e-3 * width,
                "({x}, {z}, {r}): {lo}..{hi}, reached {seen_lo}..{seen_hi}"
            );
        }
        // The eye within the sphere: the whole screen.
        assert_eq!(screen_span(0.02, 0.15, 0.5, near, 2.0), (-2.0, 2.0));
    }
}
