//! `replot` and `replot-scale`: redraw `pareto.png` from `results.csv` and `scale.png` from
//! `scale.csv` (e.g. after changing the plot, `plot.rs`), without measuring anything.

use super::*;

/// The options of `benchmark replot` and `benchmark replot-scale`.
#[derive(clap::Args, Debug)]
pub(crate) struct ReplotArgs {
    #[command(flatten)]
    pub(crate) plot: PlotFont,
}

/// A CSV file the benchmark wrote, opened for a replot.
pub(crate) struct CsvTable {
    pub(crate) reader: csv::Reader<std::fs::File>,
    header: csv::StringRecord,
    pub(crate) path: PathBuf,
}

impl CsvTable {
    pub(crate) fn open(path: PathBuf) -> Result<Self, String> {
        let mut reader = csv::Reader::from_path(&path)
            .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
        let header = reader
            .headers()
            .map_err(|e| format!("cannot read {}: {e}", path.display()))?
            .clone();
        Ok(Self {
            reader,
            header,
            path,
        })
    }

    /// The index of column `name`.
    pub(crate) fn column(&self, name: &str) -> Result<usize, String> {
        self.header
            .iter()
            .position(|h| h == name)
            .ok_or(format!("{}: no column {name}", self.path.display()))
    }
}

/// `benchmark replot`: redraws `DIR/pareto.png` from `DIR/results.csv` (e.g. after changing the
/// plot).
pub(crate) fn replot(args: &ReplotArgs, out: &Path) -> Result<(), String> {
    let mut table = CsvTable::open(out.join("results.csv"))?;
    let path = table.path.clone();
    let cannot_read = |e: csv::Error| format!("cannot read {}: {e}", path.display());
    let column = |name: &str| table.column(name);
    let [
        adapter,
        scene,
        res,
        iters,
        stencil,
        fwd,
        segments,
        supersampling,
        compositing,
        gpu,
        wall,
        rmse,
        noise,
        spp,
        pareto,
        axis,
    ] = [
        "adapter",
        "scene",
        "volume_resolution",
        "scatter_iterations",
        "stencil",
        "forward_scattering",
        "chord_segments",
        "light_supersampling",
        "compositing",
        "gpu_ms_total",
        "wall_ms",
        "rel_rmse",
        "reference_noise",
        "reference_spp",
        "pareto",
        "pareto_time_axis",
    ]
    .map(column);
    let (adapter, scene, res, iters, stencil, fwd, segments, supersampling) = (
        adapter?,
        scene?,
        res?,
        iters?,
        stencil?,
        fwd?,
        segments?,
        supersampling?,
    );
    // Results written before the compositing knob existed were all sorted, and before the
    // billboard shading knob all shaded along the chord.
    let compositing = compositing.ok();
    let shading = table.column("billboard_shading").ok();
    // Written before the coarse-grid cycles existed: none.
    let cycles = table.column("scatter_coarse_cycles").ok();
    // Written before the draw method was recorded: rasterised (the default then).
    let draw_method = table.column("draw_method").ok();
    // Written before the sweep's directions were a knob: the 26.
    let directions = table.column("scatter_directions").ok();
    let (gpu, wall, rmse, noise, spp, pareto, axis) =
        (gpu?, wall?, rmse?, noise?, spp?, pareto?, axis?);
    let mut rows = Vec::new();
    let mut order: Vec<&'static str> = Vec::new();
    let mut adapter_name = String::new();
    for record in table.reader.records() {
        let record = record.map_err(cannot_read)?;
        let f = |i: usize| record.get(i).unwrap_or_default();
        let num = |i: usize| f(i).parse::<f64>().unwrap_or(f64::NAN);
        adapter_name = f(adapter).to_string();
        let _ = WALL_AXIS.set(f(axis) == "wall_ms");
        let name: &'static str = match order.iter().find(|n| **n == f(scene)) {
            Some(n) => n,
            None => {
                let n: &'static str = Box::leak(f(scene).to_string().into_boxed_str());
                order.push(n);
                n
            }
        };
        let settings = CloudQualitySettings {
            volume_resolution: num(res) as u32,
            scatter_iterations: num(iters) as u32,
            forward_scattering: num(fwd) as f32,
            scatter_stencil: match f(stencil) {
                "Paper" => ScatterStencil::Paper,
                _ => ScatterStencil::DiscreteOrdinates,
            },
            chord_segments: num(segments) as u32,
            light_supersampling: num(supersampling) as u32,
            compositing: match compositing.map(f) {
                Some("ViewTransmittance") => Compositing::ViewTransmittance,
                _ => Compositing::Sorted,
            },
            billboard_shading: match shading.map(f) {
                Some("Centre") => BillboardShading::Centre,
                _ => BillboardShading::Chord,
            },
            // The sweep draws at full size; `cloud-target` measures the scales.
            cloud_target_scale: 1.0,
            draw_method: match draw_method.map(f) {
                Some("Compute") => DrawMethod::Compute,
                _ => DrawMethod::Raster,
            },
            // The sweep's frames are still; `warm-start` measures the warm restart.
            warm_scatter_iterations: 0,
            scatter_coarse_cycles: cycles.map_or(0, |c| num(c) as u32),
            scatter_directions: match directions.map(f) {
                Some("Lattice98") => SweepDirections::Lattice98,
                _ => SweepDirections::Lattice26,
            },
        };
        let timing = Timing {
            gpu_ms_total: num(gpu),
            wall_ms: num(wall),
            ..default()
        };
        rows.push(Row {
            scene: name,
            particles: 0,
            lights: 0,
            size: (0, 0),
            error_size: (0, 0),
            settings,
            cost_ms: if wall_axis() {
                timing.wall_ms
            } else {
                timing.gpu_ms_total
            },
            timing,
            rel_rmse: num(rmse),
            rel_rmse_box4: f64::NAN,
            rel_mse: f64::NAN,
            mae: f64::NAN,
            reference_spp: num(spp) as u32,
            reference_noise: num(noise),
            reference_noise_box4: f64::NAN,
            pareto: f(pareto) == "true",
        });
    }
    let png = out.join("pareto.png");
    plot(&png, &args.plot.font, &adapter_name, &rows, &order)?;
    eprintln!("benchmark: wrote {}", png.display());
    Ok(())
}

/// `benchmark replot-scale`: redraws `DIR/scale.png` from `DIR/scale.csv`.
pub(crate) fn replot_scale(args: &ReplotArgs, out: &Path) -> Result<(), String> {
    let mut table = CsvTable::open(out.join("scale.csv"))?;
    let path = table.path.clone();
    let cannot_read = |e: csv::Error| format!("cannot read {}: {e}", path.display());
    let column = |name: &str| table.column(name);
    let passes: Vec<usize> = CloudPass::ALL
        .iter()
        .map(|p| column(&format!("gpu_ms_{}", p.name())))
        .collect::<Result<_, _>>()?;
    let [adapter, sweep, label, x, total] =
        ["adapter", "sweep", "label", "x", "gpu_ms_total"].map(column);
    let (adapter, sweep, label, x, total) = (adapter?, sweep?, label?, x?, total?);
    // Absent from the files written before the computed draw: rasterised.
    let method = table.column("draw_method").ok();
    let number = |record: &csv::StringRecord, i: usize| -> Result<f64, String> {
        record[i]
            .parse()
            .map_err(|_| format!("{}: `{}` is not a number", path.display(), &record[i]))
    };
    let mut rows = Vec::new();
    let mut adapter_name = String::new();
    for record in table.reader.records() {
        let record = record.map_err(cannot_read)?;
        adapter_name = format!(
            "{}, drawn by {}",
            &record[adapter],
            method.map_or("Raster", |m| &record[m])
        );
        let sweep = ["particles", "clouds", "clouds, level of detail", "view"]
            .into_iter()
            .find(|s| *s == &record[sweep])
            .ok_or(format!(
                "{}: unknown sweep `{}`",
                path.display(),
                &record[sweep]
            ))?;
        let mut timing = Timing {
            gpu_ms_total: number(&record, total)?,
            ..default()
        };
        for (ms, &i) in timing.pass_ms.iter_mut().zip(&passes) {
            *ms = number(&record, i)?;
        }
        rows.push(ScaleRow {
            sweep,
            label: record[label].to_string(),
            x: number(&record, x)?,
            timing,
            runs: [0; PASSES],
            dispatches: [0; PASSES],
        });
    }
    let png = out.join("scale.png");
    plot_scale(&png, &args.plot.font, &adapter_name, &rows)?;
    eprintln!("benchmark: wrote {}", png.display());
    Ok(())
}
