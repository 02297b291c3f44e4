//! `accuracy`, the time–error benchmark: every chosen scene at every setting of the sweep (or at
//! each `--settings`), its GPU and wall time per frame and its error against the path-traced
//! reference. Writes `DIR/results.csv`, `DIR/results.md` and `DIR/pareto.png`, and each scene's
//! default image (`DIR/NAME-default.png`) beside its reference (`DIR/NAME-compare.png`).

use super::*;

/// The options of `benchmark accuracy`.
#[derive(clap::Args, Debug)]
pub(crate) struct AccuracyArgs {
    /// A short sweep (fewer settings and scenes, a quarter of the reference samples) for a quick
    /// look.
    #[arg(long)]
    pub(crate) quick: bool,
    /// Only these scenes (comma-separated names); default: all (with --quick, the quick ones).
    #[arg(long, value_delimiter = ',')]
    pub(crate) scenes: Option<Vec<String>>,
    /// Measure only these settings (RON, as a scene file's `settings`) instead of the sweep.
    /// Repeatable.
    #[arg(long = "settings", value_name = "RON", value_parser = parse_settings)]
    pub(crate) settings: Vec<CloudQualitySettings>,
    #[command(flatten)]
    pub(crate) frames: Frames,
    #[command(flatten)]
    pub(crate) reference: ReferenceSpp,
    /// Clouds do not shadow each other (every cloud `NotShadowCaster`): what the cast of their
    /// shadows costs and what its absence does to the error.
    #[arg(long)]
    pub(crate) no_cloud_shadows: bool,
    /// No ground lights the clouds from below (no `CloudGround`, though the scene has lit
    /// objects): what the ground's light costs and what its absence does to the error.
    #[arg(long)]
    pub(crate) no_ground: bool,
    /// Texels per side of the cloud shadow maps of scenes with lit objects (default: each
    /// scene's `shadow_map_resolution`).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=4096))]
    pub(crate) shadow_map_resolution: Option<u32>,
    #[command(flatten)]
    pub(crate) plot: PlotFont,
}

/// `benchmark accuracy`: the sweep (or `--settings`) on every chosen scene against its
/// path-traced reference.
pub(crate) fn accuracy_benchmark(args: &AccuracyArgs, out: &Path) -> Result<(), String> {
    let start = Instant::now();
    let chosen = sweep_scenes(args.scenes.as_deref(), !args.quick)?;
    let settings = if args.settings.is_empty() {
        sweep(args.quick)
    } else {
        args.settings.clone()
    };
    let mut rows = Vec::new();
    let mut adapter = String::new();
    let csv = out.join("results.csv");
    for bench in &chosen {
        let scene = load_scene(bench)?;
        let spp = args
            .reference
            .spp
            .unwrap_or(if args.quick { bench.spp / 4 } else { bench.spp });
        let fog_effect = FogEffect::new(&scene, bench, spp, out)?;
        let reference = reference(&scene, bench, spp, out)?;
        let mut b = Bench::with_shadow_maps(&scene, args.shadow_map_resolution);
        if args.no_cloud_shadows {
            b.without_cloud_shadows();
        }
        if args.no_ground {
            b.without_ground();
        }
        adapter = b.adapter.clone();
        let _ = WALL_AXIS.set(adapter.contains("llvmpipe"));
        eprintln!(
            "benchmark: {}: adapter {adapter}; reference {} spp, noise {:.4}; {} settings",
            bench.name,
            reference.spp,
            reference.noise,
            settings.len()
        );
        let mut scene_rows = Vec::new();
        let bar = ProgressBar::new(settings.len() as u64).with_style(
            ProgressStyle::with_template(&format!(
                "{} {{bar:40}} {{pos}}/{{len}} settings, {{eta}} left",
                bench.name
            ))
            .expect("progress template"),
        );
        for s in &settings {
            let t0 = Instant::now();
            b.set_quality(*s);
            let (image, timing) = match b.try_measure(args.frames.count()) {
                Ok(measured) => measured,
                Err(why) => {
                    bar.suspend(|| {
                        eprintln!(
                            "benchmark: {} {}: skipped, not measured: {why}",
                            bench.name,
                            setting_label(s)
                        )
                    });
                    bar.inc(1);
                    continue;
                }
            };
            let image = downsample(&image, bench.error_downsample);
            assert_eq!(
                (image.width, image.height),
                (reference.width, reference.height)
            );
            // Under a sky, over the pixels where the cloud changes it.
            let sky = scene.background;
            let (seen, truth) = (
                cloud_pixels(&image.pixels, &reference.image, sky),
                cloud_pixels(&reference.image, &reference.image, sky),
            );
            let (rel_rmse, rel_mse_, mae) = (
                relative_rmse(&seen, &truth),
                rel_mse(&seen, &truth),
                mean_absolute_error(&seen, &truth),
            );
            let reference_image = LinearImage {
                width: reference.width,
                height: reference.height,
                pixels: reference.image.clone(),
            };
            let boxed_truth = downsample(&reference_image, 4).pixels;
            let rel_rmse_box4 = relative_rmse(
                &cloud_pixels(&downsample(&image, 4).pixels, &boxed_truth, sky),
                &cloud_pixels(&boxed_truth, &boxed_truth, sky),
            );
            if std::env::var_os("BENCHMARK_DEBUG").is_some() {
                let sum =
                    |p: &[[f32; 4]]| p.iter().map(|v| (v[0] + v[1] + v[2]) as f64).sum::<f64>();
                eprintln!(
                    "  mean ratio real-time / reference: {:.4}",
                    sum(&image.pixels) / sum(&reference.image)
                );
            }
            if *s == CloudQualitySettings::default() {
                let mut shown = image.clone();
                shown.pixels.iter_mut().for_each(|p| p[3] = 1.0);
                let _ = write_png(&shown, &out.join(format!("{}-default.png", bench.name)));
                let _ = write_png(
                    &side_by_side(&shown, &reference_image),
                    &out.join(format!("{}-compare.png", bench.name)),
                );
            }
            // Scenes with fog: the error of what the fog changes (the same frame without it).
            if let Some(effect) = &fog_effect {
                b.set_fog(None);
                let clear = downsample(&b.image(), bench.error_downsample);
                let (clear_draw, clear_wall) = b.static_frames(args.frames.count());
                b.set_fog(scene.fog.as_ref());
                b.image();
                let (fog_draw, fog_wall) = b.static_frames(args.frames.count());
                bar.suspend(|| {
                    eprintln!(
                        "benchmark: {} {}: static frame with fog / without: draw {:.1} / {:.1} ms, wall {:.1} / {:.1} ms",
                        bench.name,
                        setting_label(s),
                        median(fog_draw),
                        median(clear_draw),
                        median(fog_wall),
                        median(clear_wall)
                    )
                });
                let (error, inherited) =
                    effect.error(&image.pixels, &clear.pixels, &reference, &scene);
                let noise = effect.noise(&reference);
                bar.suspend(|| {
                    eprintln!(
                        "benchmark: {} {}: the fog's effect: rel. RMSE {error:.4} (denoised {:.4}; noise {noise:.4}); the clear cloud's error through the fog alone would make it about {inherited:.4}",
                        bench.name,
                        setting_label(s),
                        denoised(error, noise)
                    )
                });
            }
            // Scenes with lit objects: the error over the pixels that see one (the ground and
            // the clouds' shadows on it).
            if let Some((mask, noise)) = &reference.ground {
                let error = relative_rmse(
                    &masked(&image.pixels, mask),
                    &masked(&reference.image, mask),
                );
                bar.suspend(|| {
                    eprintln!(
                        "benchmark: {} {}: over the lit objects' pixels rel. RMSE {error:.4} (denoised {:.4}; noise {noise:.4})",
                        bench.name,
                        setting_label(s),
                        denoised(error, *noise)
                    )
                });
            }
            // Above the bar on a terminal; plain lines in a log.
            bar.inc(1);
            bar.suspend(|| eprintln!(
                "benchmark: {} {:<16} GPU {:8.2} ms (static {:6.2}), wall {:8.1} ms; rel. RMSE {:.4} (denoised {:.4}, 4x4 box {:.4}) relMSE {:.5} MAE {:.5} ({:.1} s)",
                bench.name,
                setting_label(s),
                timing.gpu_ms_total,
                timing.gpu_ms_static,
                timing.wall_ms,
                rel_rmse,
                denoised(rel_rmse, reference.noise),
                denoised(rel_rmse_box4, reference.noise_box4),
                rel_mse_,
                mae,
                t0.elapsed().as_secs_f64()
            ));
            scene_rows.push(Row {
                scene: bench.name,
                particles: scene.clouds.iter().map(|c| c.particles.len()).sum(),
                lights: scene.lights.len(),
                size: (scene.camera.width, scene.camera.height),
                error_size: (reference.width, reference.height),
                settings: *s,
                cost_ms: if wall_axis() {
                    timing.wall_ms
                } else {
                    timing.gpu_ms_total
                },
                timing,
                rel_rmse,
                rel_rmse_box4,
                rel_mse: rel_mse_,
                mae,
                reference_spp: reference.spp,
                reference_noise: reference.noise,
                reference_noise_box4: reference.noise_box4,
                pareto: false,
            });
        }
        bar.finish_and_clear();
        mark_pareto(&mut scene_rows);
        rows.extend(scene_rows);
        drop(b);
        // After every scene, so that a sweep stopped part way keeps the scenes it finished.
        write_csv_results(&csv, &adapter, &rows)
            .map_err(|e| format!("cannot write {}: {e}", csv.display()))?;
    }
    let order: Vec<&'static str> = chosen.iter().map(|s| s.name).collect();
    let md = markdown(&adapter, &rows, &order);
    let md_path = out.join("results.md");
    std::fs::write(&md_path, &md)
        .map_err(|e| format!("cannot write {}: {e}", md_path.display()))?;
    println!("{md}");
    for name in &order {
        let scene_rows: Vec<Row> = rows.iter().filter(|r| r.scene == *name).cloned().collect();
        let dom = dominating(&scene_rows);
        if dom.is_empty() {
            eprintln!("benchmark: {name}: the default settings are on the Pareto front");
        } else {
            let names: Vec<_> = dom.iter().map(|r| setting_label(&r.settings)).collect();
            eprintln!(
                "benchmark: {name}: the default settings are dominated by {}",
                names.join(", ")
            );
        }
    }
    let png = out.join("pareto.png");
    plot(&png, &args.plot.font, &adapter, &rows, &order)?;
    eprintln!(
        "benchmark: wrote {}, {} and {} in {:.0} s",
        csv.display(),
        md_path.display(),
        png.display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}
