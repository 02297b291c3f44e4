//! `illumination`: every illumination pass's GPU time, incremental against brute-force shading.

use super::*;

/// What a measured frame changes, and so which passes rerun.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Change {
    /// Nothing: the draw only.
    Nothing,
    /// The cloud's albedo (by one part in 10⁶): scatter and the particle colours.
    Albedo,
    /// The first light's illuminance (by one part in 10⁶): gather, scatter, colours.
    Irradiance,
    /// Every light's direction (by ~10⁻⁴ rad): shade (every light), gather, scatter, colours.
    Direction,
    /// The camera (by 10⁻⁴ m): the view pass (the view volume, or the sort).
    Camera,
    /// The particles (touched): everything (upload, voxelize, shade, gather, scatter, sort).
    Particles,
}

impl Bench {
    /// Applies `change` for frame number `i` (alternating up and down, so nothing drifts).
    pub(crate) fn change(&mut self, change: Change, i: usize) {
        let sign = if i.is_multiple_of(2) { 1.0 } else { -1.0 };
        let world = self.app.world_mut();
        match change {
            Change::Nothing => {}
            Change::Albedo => {
                for mut cloud in world.query::<&mut ParticleCloud>().iter_mut(world) {
                    cloud.albedo *= 1.0 - sign * 1e-6;
                }
            }
            Change::Irradiance => {
                if let Some(mut light) = world
                    .query::<&mut DirectionalLight>()
                    .iter_mut(world)
                    .next()
                {
                    light.illuminance *= 1.0 + sign * 1e-6;
                }
            }
            Change::Direction => {
                for mut t in world
                    .query_filtered::<&mut Transform, With<DirectionalLight>>()
                    .iter_mut(world)
                {
                    t.rotate_y(sign * 1e-4);
                }
            }
            Change::Camera => {
                for mut t in world
                    .query_filtered::<&mut Transform, With<Camera3d>>()
                    .iter_mut(world)
                {
                    t.translation.x += sign * 1e-4;
                }
            }
            Change::Particles => self.touch_particles(),
        }
    }

    /// Median wall time of `frames` frames that each apply `change`, and the frames.
    pub(crate) fn wall_of(&mut self, change: Change, frames: usize) -> (f64, Vec<FrameStats>) {
        self.frame(); // settle
        let mut ids = Vec::new();
        for i in 0..frames {
            self.change(change, i);
            ids.push(self.frame());
        }
        if frames % 2 == 1 {
            self.change(change, frames); // undo the odd change
            self.frame();
        }
        for _ in 0..4 {
            self.recorder
                .drain(&mut self.app)
                .expect("the benchmark scene renders");
        }
        let stats: Vec<FrameStats> = ids
            .iter()
            .map(|&i| self.recorder.frames[i].clone())
            .collect();
        (median(stats.iter().map(|f| f.wall_ms).collect()), stats)
    }
}

/// Per-pass cost from wall-time differences of frames that rerun nested sets of passes (reliable
/// on every adapter, and the only per-pass figure that means something on llvmpipe).
#[derive(Clone, Debug, Default)]
pub(crate) struct WallPasses {
    /// voxelize (with the particles' upload), shade, gather, scatter (with colours), sort, draw
    /// (static frame, with Bevy's per-frame overhead).
    pub(crate) pass_ms: [f64; PASSES],
}

/// Or why the cloud was not drawn (it warns why: e.g. its volumes past the adapter's limit).
pub(crate) fn wall_passes(b: &mut Bench, frames: usize) -> Result<(WallPasses, Timing), String> {
    let (_, timing) = b.try_measure(frames)?;
    let (w0, _) = b.wall_of(Change::Nothing, frames);
    let (wa, _) = b.wall_of(Change::Albedo, frames);
    let (wi, _) = b.wall_of(Change::Irradiance, frames);
    let (wd, _) = b.wall_of(Change::Direction, frames);
    let (wc, _) = b.wall_of(Change::Camera, frames);
    let (wp, _) = b.wall_of(Change::Particles, frames);
    // The camera's move reruns the view pass: the sort or the view volume, whichever runs.
    let view = wc - w0;
    let pass_ms = [wp - wd - view, wd - wi, wi - wa, wa - w0, view, 0.0, w0];
    Ok((WallPasses { pass_ms }, timing))
}

/// The options of `benchmark illumination`.
#[derive(clap::Args, Debug)]
pub(crate) struct IlluminationArgs {
    /// Only these scenes (comma-separated): `paper_38k_1light`, `paper_38k_5lights` (default:
    /// both).
    #[arg(long, value_delimiter = ',')]
    pub(crate) scenes: Option<Vec<String>>,
    /// The view's size, pixels (default: the scenes' own 640x480).
    #[arg(long, value_parser = parse_view)]
    pub(crate) view: Option<(u32, u32)>,
    #[command(flatten)]
    pub(crate) frames: Frames,
}

pub(crate) fn illumination_benchmark(args: &IlluminationArgs, out: &Path) -> Result<(), String> {
    let mut csv = String::from(
        "adapter,scene,lights,volume_resolution,light_resolution,shading,gpu_ms_voxelize,gpu_ms_shade,gpu_ms_gather,gpu_ms_scatter,\
         gpu_ms_view,gpu_ms_draw,gpu_ms_total,wall_ms,wall_ms_voxelize,wall_ms_shade,wall_ms_gather,wall_ms_scatter,\
         wall_ms_view,wall_ms_static\n",
    );
    let mut adapter = String::new();
    let mut view = (0, 0);
    // Configurations whose cloud the renderer refused on this adapter.
    let mut refused = Vec::new();
    let mut lines: Vec<(usize, u32, u32, String, Timing, WallPasses)> = Vec::new();
    let mut ratios = Vec::new();
    let wanted = |name: &&str| {
        let names = args.scenes.as_ref();
        names.is_none_or(|names| names.iter().any(|n| n == name))
    };
    for name in ["paper_38k_1light", "paper_38k_5lights"]
        .into_iter()
        .filter(wanted)
    {
        let bench = SCENES.iter().find(|s| s.name == name).expect("scene");
        let mut scene = load_scene(bench)?;
        let own = (scene.camera.width, scene.camera.height);
        (scene.camera.width, scene.camera.height) = args.view.unwrap_or(own);
        view = (scene.camera.width, scene.camera.height);
        let mut b = Bench::new(&scene);
        adapter = b.adapter.clone();
        // Density grids of 32³ and 64³; the light volumes `light_supersampling` times finer.
        for n in [32u32, 64] {
            let mut shade = HashMap::new();
            for method in [ShadingMethod::Incremental, ShadingMethod::BruteForce] {
                b.app.insert_resource(method);
                b.set_quality(CloudQualitySettings {
                    volume_resolution: n,
                    ..default()
                });
                eprintln!("benchmark: {name} {n}³ {method:?}…");
                let method_name = format!("{method:?}");
                let (w, t) = match wall_passes(&mut b, args.frames.count()) {
                    Ok(measured) => measured,
                    Err(e) => {
                        eprintln!("benchmark: {name} {n}³ {method_name} not measured: {e}");
                        refused.push(format!(
                            "{} light(s), {n}³, {method_name}",
                            scene.lights.len()
                        ));
                        continue;
                    }
                };
                eprintln!(
                    "benchmark: {name} {n}³ {method_name}: shade GPU {:.2} ms, wall {:.1} ms; GPU total {:.2} ms, wall {:.1} ms",
                    t.pass_ms[1], w.pass_ms[1], t.gpu_ms_total, t.wall_ms
                );
                // Lower than the settings' where the renderer lowered the supersampling to fit.
                let m = b.light_resolution().unwrap_or(0);
                let p = &t.pass_ms;
                let q = &w.pass_ms;
                let _ = writeln!(
                    csv,
                    "\"{adapter}\",{name},{},{n},{m},{method_name},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3}",
                    scene.lights.len(),
                    p[0],
                    p[1],
                    p[2],
                    p[3],
                    p[4] + p[5],
                    p[6],
                    t.gpu_ms_total,
                    t.wall_ms,
                    q[0],
                    q[1],
                    q[2],
                    q[3],
                    q[4] + q[5],
                    q[6]
                );
                shade.insert(method, (t.pass_ms[1], w.pass_ms[1]));
                lines.push((scene.lights.len(), n, m, method_name, t, w));
            }
            if let (Some((gi, wi)), Some((gb, wb))) = (
                shade.get(&ShadingMethod::Incremental),
                shade.get(&ShadingMethod::BruteForce),
            ) {
                ratios.push((scene.lights.len(), n, gb / gi, wb / wi));
            }
        }
        b.app.insert_resource(ShadingMethod::Incremental);
    }
    let mut table = format!(
        "Adapter: `{adapter}`. The 38,000-particle cloud (benchmarks/scenes/paper_38k_*.ron, {}×{}), \
         the default knobs ({} scattering iterations, light volumes up to {}× the density grid's resolution) but \
         the density grid's resolution (`grid`); `light volumes`: their voxels per side, lower where the \
         renderer lowered the supersampling to fit the adapter's storage binding. GPU: per-pass timestamps, median of {} frames in which \
         every pass reruns. Wall: per-pass cost from wall-time differences of frames that rerun nested sets of \
         passes (scatter: albedo changed; + gather: irradiance changed; + shade: light directions changed; \
         + voxelize: particles changed, including their upload; view pass (the view volume, or the sort when \
         sorted): camera moved; static: nothing changed, \
         the draw plus Bevy's per-frame work).\n\n",
        view.0,
        view.1,
        CloudQualitySettings::default().scatter_iterations,
        CloudQualitySettings::default().light_supersampling,
        args.frames.count()
    );
    table.push_str("| lights | grid | light volumes | shading | GPU: voxelize | shade | gather | scatter | view pass | draw | total | wall: voxelize | shade | gather | scatter | view pass | static frame | all passes |\n");
    table.push_str(
        "|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for (lights, n, m, method, t, w) in &lines {
        let p = &t.pass_ms;
        let q = &w.pass_ms;
        let _ = writeln!(
            table,
            "| {lights} | {n}³ | {m}³ | {method} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} |",
            p[0],
            p[1],
            p[2],
            p[3],
            p[4] + p[5],
            p[6],
            t.gpu_ms_total,
            q[0],
            q[1],
            q[2],
            q[3],
            q[4] + q[5],
            q[6],
            t.wall_ms
        );
    }
    if !refused.is_empty() {
        let _ = writeln!(
            table,
            "\nNot measured: the renderer refused the cloud on this adapter, with a warning that \
             says why (e.g. its volumes past the adapter's storage buffer limit): {}.",
            refused.join("; ")
        );
    }
    table.push_str("\nShade cost of the brute-force march (every voxel marching to the light) over the incremental pass:\n\n");
    table.push_str(
        "| lights | grid | ratio (GPU timestamps) | ratio (wall time) |\n|---:|---:|---:|---:|\n",
    );
    for (lights, n, g, w) in &ratios {
        let _ = writeln!(table, "| {lights} | {n}³ | {g:.1}× | {w:.1}× |");
    }
    let csv_path = out.join("illumination.csv");
    std::fs::write(&csv_path, csv)
        .map_err(|e| format!("cannot write {}: {e}", csv_path.display()))?;
    let md_path = out.join("illumination.md");
    std::fs::write(&md_path, &table)
        .map_err(|e| format!("cannot write {}: {e}", md_path.display()))?;
    println!("{table}");
    eprintln!(
        "benchmark: wrote {} and {}",
        csv_path.display(),
        md_path.display()
    );
    Ok(())
}
