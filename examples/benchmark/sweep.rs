//! The settings swept, and the real-time measurements: GPU and wall time per frame, images.

use super::*;

/// The default settings before the view transmittance became the default: sorted compositing,
/// 16 iterations, light supersampling 2, 4 chord segments.
pub(crate) const PREVIOUS_DEFAULT: CloudQualitySettings = CloudQualitySettings {
    volume_resolution: 48,
    scatter_iterations: 16,
    warm_scatter_iterations: 0,
    scatter_coarse_cycles: 0,
    forward_scattering: 0.0,
    scatter_stencil: ScatterStencil::DiscreteOrdinates,
    scatter_directions: SweepDirections::Lattice26,
    light_supersampling: 2,
    chord_segments: 4,
    compositing: Compositing::Sorted,
    billboard_shading: BillboardShading::Chord,
    cloud_target_scale: 1.0,
    draw_method: DrawMethod::Raster,
};

/// The scattering of the defaults before the coarse-grid cycles: the series of 32 orders.
pub(crate) const SERIES_DEFAULT: CloudQualitySettings = CloudQualitySettings {
    scatter_iterations: 32,
    scatter_coarse_cycles: 0,
    ..CloudQualitySettings::DEFAULT
};

/// The quality settings of a sweep: the defaults, then each knob varied on its own around them
/// (so every knob's cost and error are measured), plus the paper's stencil.
pub(crate) fn sweep(quick: bool) -> Vec<CloudQualitySettings> {
    let base = CloudQualitySettings::default();
    let (resolutions, iterations, segments, supersampling): (&[u32], &[u32], &[u32], &[u32]) =
        if quick {
            (&[32, 48, 64], &[0, 16], &[1, 4], &[1, 2])
        } else {
            (
                &[16, 24, 32, 48, 64, 96, 128],
                &[0, 1, 2, 4, 8, 16, 32, 64],
                &[1, 2, 4, 8],
                &[1, 2, 3, 4],
            )
        };
    let cycles: &[u32] = if quick { &[0] } else { &[0, 1, 2, 4] };
    let mut settings = vec![base];
    let mut add = |s: CloudQualitySettings| {
        if !settings.contains(&s) {
            settings.push(s);
        }
    };
    for &volume_resolution in resolutions {
        add(CloudQualitySettings {
            volume_resolution,
            ..base
        });
    }
    for &scatter_iterations in iterations {
        add(CloudQualitySettings {
            scatter_iterations,
            ..base
        });
    }
    for &scatter_coarse_cycles in cycles {
        add(CloudQualitySettings {
            scatter_coarse_cycles,
            ..base
        });
    }
    // The series alone, the default before the cycles.
    add(SERIES_DEFAULT);
    for &chord_segments in segments {
        add(CloudQualitySettings {
            chord_segments,
            ..base
        });
    }
    for &light_supersampling in supersampling {
        add(CloudQualitySettings {
            light_supersampling,
            ..base
        });
    }
    // Resolution and iterations together, where the front is expected.
    if !quick {
        for volume_resolution in [32, 48, 64] {
            for scatter_iterations in [4, 8, 16, 32] {
                add(CloudQualitySettings {
                    volume_resolution,
                    scatter_iterations,
                    ..base
                });
            }
        }
    }
    // The paper's compositing, sorted particles, at the default and the finest grid, and the
    // defaults of 0.1 (sorted, 16 iterations, supersampling 2, 4 chord segments).
    let sorted: &[u32] = if quick { &[48] } else { &[48, 128] };
    for &volume_resolution in sorted {
        add(CloudQualitySettings {
            volume_resolution,
            compositing: Compositing::Sorted,
            ..base
        });
    }
    add(PREVIOUS_DEFAULT);
    // The rasterised draw, the default before 2026-11-28: its blend rounds after every particle.
    add(CloudQualitySettings {
        draw_method: DrawMethod::Raster,
        ..base
    });
    let paper: &[u32] = if quick { &[48] } else { &[32, 48, 128] };
    for &volume_resolution in paper {
        add(CloudQualitySettings {
            volume_resolution,
            scatter_stencil: ScatterStencil::Paper,
            ..base
        });
    }
    settings
}

pub(crate) fn median(mut values: Vec<f64>) -> f64 {
    values.retain(|v| v.is_finite());
    if values.is_empty() {
        return f64::NAN;
    }
    values.sort_by(f64::total_cmp);
    let n = values.len();
    if n % 2 == 1 {
        values[n / 2]
    } else {
        0.5 * (values[n / 2 - 1] + values[n / 2])
    }
}

/// Median timings of a setting.
#[derive(Clone, Debug, Default)]
pub(crate) struct Timing {
    /// Per pass (CloudPass::ALL order, draw from the transparent pass), frames where all rerun.
    pub(crate) pass_ms: [f64; PASSES],
    /// GPU time of a frame where every pass runs: median of the per-frame sums.
    pub(crate) gpu_ms_total: f64,
    /// GPU time of a static frame (the draw only).
    pub(crate) gpu_ms_static: f64,
    pub(crate) wall_ms: f64,
    pub(crate) wall_ms_static: f64,
}

/// A running app with one scene, for measuring many settings.
pub(crate) struct Bench {
    pub(crate) app: App,
    pub(crate) target: headless::SceneTarget,
    pub(crate) recorder: FrameRecorder,
    pub(crate) clouds: Vec<(Entity, Handle<Particles>)>,
    pub(crate) draw_seen: [Option<bevy::platform::time::Instant>; 2],
    pub(crate) adapter: String,
}

impl Bench {
    pub(crate) fn new(scene: &Scene) -> Bench {
        Self::with_shadow_maps(scene, None)
    }

    /// A bench of `scene` whose lit objects take shadow maps of `resolution` texels per side
    /// (else the headless renderer's default).
    pub(crate) fn with_shadow_maps(scene: &Scene, resolution: Option<u32>) -> Bench {
        let mut app = headless::app_with(headless::plugins().disable::<bevy::winit::WinitPlugin>());
        // A static frame measures the draw (`benchmark still-view` measures what keeping it saves).
        app.insert_resource(bevy_particle_clouds::CloudRedraw::EveryFrame);
        if let Some(resolution) = resolution {
            app.insert_resource(bevy_particle_clouds::CloudShadowMaps::with_resolution(
                resolution,
            ));
        }
        let adapter = headless::adapter_name(&mut app);
        let target = headless::spawn_scene(&mut app, scene);
        let clouds = app
            .world_mut()
            .query::<(Entity, &ParticleCloud)>()
            .iter(app.world())
            .map(|(e, c)| (e, c.particles.clone()))
            .collect();
        Bench {
            app,
            target,
            recorder: FrameRecorder::default(),
            clouds,
            draw_seen: [None; 2],
            adapter,
        }
    }

    pub(crate) fn set_quality(&mut self, settings: CloudQualitySettings) {
        for &(entity, _) in &self.clouds {
            self.app.world_mut().entity_mut(entity).insert(settings);
        }
    }

    /// The camera's distance fog: `fog`, or none.
    pub(crate) fn set_fog(&mut self, fog: Option<&Fog>) {
        let mut camera = self.app.world_mut().entity_mut(self.target.camera);
        match fog {
            Some(fog) => camera.insert(bevy_particle_clouds::render::fog::distance_fog(fog)),
            None => camera.remove::<bevy::pbr::DistanceFog>(),
        };
    }

    /// No cloud shadows another (`NotShadowCaster` on every cloud).
    pub(crate) fn without_cloud_shadows(&mut self) {
        for &(entity, _) in &self.clouds {
            let mut cloud = self.app.world_mut().entity_mut(entity);
            cloud.insert(bevy::light::NotShadowCaster);
        }
    }

    /// No ground lights the clouds (`CloudGround` removed).
    pub(crate) fn without_ground(&mut self) {
        let world = self.app.world_mut();
        world.remove_resource::<bevy_particle_clouds::CloudGround>();
    }

    /// Level of detail at `pixels_per_voxel`, no coarser than `min_resolution` voxels per side.
    pub(crate) fn set_level_of_detail(&mut self, pixels_per_voxel: f32, min_resolution: u32) {
        self.app.insert_resource(CloudLevelOfDetail {
            pixels_per_voxel,
            min_resolution,
        });
    }

    /// Each pass's runs and compute dispatches in a frame where every pass reruns (the
    /// particles touched).
    pub(crate) fn relit_counts(&mut self) -> ([u32; PASSES], [u32; PASSES]) {
        self.touch_particles();
        let i = self.frame();
        let frame = &self.recorder.frames[i];
        (
            CloudPass::ALL.map(|p| frame.runs(p)),
            CloudPass::ALL.map(|p| frame.dispatches(p)),
        )
    }

    /// Turns every light of the scene by `degrees` about the world's vertical.
    pub(crate) fn turn_lights(&mut self, degrees: f32) {
        let turn = Quat::from_rotation_y(degrees.to_radians());
        let mut lights = self
            .app
            .world_mut()
            .query_filtered::<&mut Transform, With<DirectionalLight>>();
        for mut transform in lights.iter_mut(self.app.world_mut()) {
            transform.rotation = turn * transform.rotation;
        }
    }

    /// Marks every cloud's particles changed: the next frame reruns every pass.
    pub(crate) fn touch_particles(&mut self) {
        for (_, handle) in &self.clouds {
            let mut assets = self.app.world_mut().resource_mut::<Assets<Particles>>();
            assets.get_mut(handle).expect("particles").into_inner();
        }
    }

    /// The draw's GPU time measured since the last call, if a new one arrived: the transparent
    /// pass (the billboards at full size) plus the cloud target's draw and composite.
    pub(crate) fn new_draw_time(&mut self) -> Option<f64> {
        let store = self.app.world().get_resource::<DiagnosticsStore>()?;
        let mut total = None;
        for (i, path) in draw_diagnostics().iter().enumerate() {
            let m = store.get(path).and_then(|d| d.measurement());
            if let Some(m) = m
                && self.draw_seen[i] != Some(m.time)
            {
                self.draw_seen[i] = Some(m.time);
                total = Some(total.unwrap_or(0.0) + m.value);
            }
        }
        total
    }

    pub(crate) fn frame(&mut self) -> usize {
        self.recorder
            .frame(&mut self.app)
            .expect("the benchmark scene renders");
        self.recorder.frames.len() - 1
    }

    /// The draw's GPU time and the wall time of `frames` static frames (nothing changed: the
    /// draw only), after two that warm up.
    pub(crate) fn static_frames(&mut self, frames: usize) -> (Vec<f64>, Vec<f64>) {
        for _ in 0..2 {
            self.frame();
            self.new_draw_time();
        }
        let (mut draw, mut wall) = (Vec::new(), Vec::new());
        for _ in 0..frames {
            let i = self.frame();
            wall.push(self.recorder.frames[i].wall_ms);
            draw.extend(self.new_draw_time());
        }
        (draw, wall)
    }

    /// The clouds that hold volumes in the render world: a cloud the renderer refused (e.g. past
    /// the adapter's storage limit) holds none.
    fn clouds_with_volumes(&mut self) -> u32 {
        let world = self.app.sub_app_mut(bevy::render::RenderApp).world_mut();
        let mut query = world.query::<&bevy_particle_clouds::render::volumes::CloudVolumes>();
        query.iter(world).count() as u32
    }

    /// The largest light volume's voxels per side among the clouds that hold volumes: the
    /// settings' `volume_resolution × light_supersampling`, or less where the renderer lowered the
    /// supersampling to fit the adapter's storage binding.
    pub(crate) fn light_resolution(&mut self) -> Option<u32> {
        let world = self.app.sub_app_mut(bevy::render::RenderApp).world_mut();
        let mut query = world.query::<&bevy_particle_clouds::render::volumes::CloudVolumes>();
        query.iter(world).map(|v| v.params.light_n).max()
    }

    /// Renders the finished image of the current settings.
    pub(crate) fn image(&mut self) -> LinearImage {
        headless::render_until_steady(
            &mut self.app,
            &mut self.recorder,
            self.target.drawable_clouds,
            200,
        )
        .expect("the benchmark scene renders");
        headless::capture(&mut self.app, &mut self.recorder, &self.target.image)
            .expect("the benchmark scene renders")
    }

    /// Renders the finished image of the current settings and measures it.
    ///
    /// # Panics
    /// If no measured frame reran every pass, a refused cloud included.
    pub(crate) fn measure(&mut self, frames: usize) -> (LinearImage, Timing) {
        self.try_measure(frames).unwrap_or_else(|e| panic!("{e}"))
    }

    /// [`Bench::measure`], or, where a cloud the renderer refused (it warns why, e.g. volumes
    /// past the adapter's storage limit) kept every frame from rerunning its passes, how many.
    ///
    /// # Panics
    /// If no measured frame reran every pass although every cloud holds its volumes.
    pub(crate) fn try_measure(&mut self, frames: usize) -> Result<(LinearImage, Timing), String> {
        let image = self.image();
        // Static frames: nothing changed, only the draw runs.
        let (draw, static_wall) = self.static_frames(frames);
        // Frames where everything reruns.
        let mut dynamic = Vec::new();
        for _ in 0..frames {
            self.touch_particles();
            dynamic.push(self.frame());
        }
        for _ in 0..4 {
            self.recorder
                .drain(&mut self.app)
                .expect("the benchmark scene renders"); // late GPU timestamps
        }
        let frames_of = |ids: &[usize]| -> Vec<FrameStats> {
            ids.iter()
                .map(|&i| self.recorder.frames[i].clone())
                .collect()
        };
        // Every illumination pass and the view pass (the sort or the view volume).
        let reran = |f: &FrameStats| {
            [CloudPass::Voxelize, CloudPass::Shade, CloudPass::Gather]
                .iter()
                .all(|&p| f.runs(p) > 0)
                && f.runs(CloudPass::Sort) + f.runs(CloudPass::ViewVolume) > 0
        };
        let dynamics: Vec<FrameStats> = frames_of(&dynamic).into_iter().filter(reran).collect();
        if std::env::var_os("BENCHMARK_DEBUG").is_some() {
            for f in frames_of(&dynamic) {
                eprintln!(
                    "  frame: wall {:.1} ms, runs {:?}, gpu {:?}",
                    f.wall_ms, f.passes, f.gpu_ms
                );
            }
        }
        if dynamics.is_empty() {
            // Only a cloud the renderer refused (it holds no volumes) is skipped; anything else
            // is a bug in the renderer or the benchmark.
            let refused = self.target.drawable_clouds - self.clouds_with_volumes();
            assert!(
                refused > 0,
                "none of the {frames} measured frames reran every pass"
            );
            return Err(format!(
                "the renderer refused {refused} cloud(s) (its warning above says why)"
            ));
        }
        let draw_ms = median(draw);
        let mut pass_ms = [0.0; PASSES];
        for (i, pass) in CloudPass::ALL.iter().enumerate() {
            pass_ms[i] = if *pass == CloudPass::Draw {
                draw_ms
            } else {
                median(
                    dynamics
                        .iter()
                        .map(|f| {
                            f.gpu_ms
                                .get(pass)
                                .copied()
                                .unwrap_or(if f.runs(*pass) == 0 { 0.0 } else { f64::NAN })
                        })
                        .collect(),
                )
            };
        }
        let gpu_ms_total = median(
            dynamics
                .iter()
                .map(|f| {
                    CloudPass::ALL
                        .iter()
                        .filter(|&&p| p != CloudPass::Draw)
                        .map(|p| {
                            f.gpu_ms.get(p).copied().unwrap_or(if f.runs(*p) == 0 {
                                0.0
                            } else {
                                f64::NAN
                            })
                        })
                        .sum::<f64>()
                        + draw_ms
                })
                .collect(),
        );
        let timing = Timing {
            pass_ms,
            gpu_ms_total,
            gpu_ms_static: draw_ms,
            wall_ms: median(dynamics.iter().map(|f| f.wall_ms).collect()),
            wall_ms_static: median(static_wall),
        };
        Ok((image, timing))
    }
}
