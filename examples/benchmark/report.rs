//! Results: rows, the Pareto front, `results.csv` and `results.md`; and `write_report`, which
//! writes a subcommand's Markdown table.

use super::*;

#[derive(Clone)]
pub(crate) struct Row {
    pub(crate) scene: &'static str,
    pub(crate) particles: usize,
    pub(crate) lights: usize,
    pub(crate) size: (u32, u32),
    pub(crate) error_size: (u32, u32),
    pub(crate) settings: CloudQualitySettings,
    pub(crate) timing: Timing,
    /// The time axis of the Pareto front: `gpu_ms_total`, or `wall_ms` on llvmpipe (see [`wall_axis`]).
    pub(crate) cost_ms: f64,
    pub(crate) rel_rmse: f64,
    /// The relative RMSE after a 4×4 box filter of both images (noise averages out, bias does not).
    pub(crate) rel_rmse_box4: f64,
    pub(crate) rel_mse: f64,
    pub(crate) mae: f64,
    pub(crate) reference_spp: u32,
    pub(crate) reference_noise: f64,
    /// The reference's noise after the same 4×4 box filter.
    pub(crate) reference_noise_box4: f64,
    pub(crate) pareto: bool,
}

/// An error with the reference's own noise removed in quadrature (0 when the noise explains it all).
pub(crate) fn denoised(error: f64, noise: f64) -> f64 {
    (error * error - noise * noise).max(0.0).sqrt()
}

pub(crate) fn stencil_name(s: ScatterStencil) -> &'static str {
    match s {
        ScatterStencil::DiscreteOrdinates => "DiscreteOrdinates",
        ScatterStencil::Paper => "Paper",
    }
}

pub(crate) fn setting_label(s: &CloudQualitySettings) -> String {
    let stencil = match s.scatter_stencil {
        ScatterStencil::DiscreteOrdinates => "D",
        ScatterStencil::Paper => "P",
    };
    let compositing = match s.compositing {
        Compositing::ViewTransmittance => "",
        Compositing::Sorted => " sorted",
    };
    let shading = match s.billboard_shading {
        BillboardShading::Chord => "",
        BillboardShading::Centre => " centre",
    };
    let target = if s.cloud_target_scale < 1.0 {
        format!(" target ×{}", s.cloud_target_scale)
    } else {
        String::new()
    };
    let method = match s.draw_method {
        DrawMethod::Raster => " raster",
        DrawMethod::Compute => "",
    };
    let cycles = match s.scatter_coarse_cycles {
        0 => String::new(),
        c => format!(" +{c} cycles"),
    };
    let directions = match s.scatter_directions {
        SweepDirections::Lattice26 => "",
        SweepDirections::Lattice98 => " 98 dirs",
    };
    format!(
        "{}³ ×{}{cycles} {stencil}{directions} K{} L{}{compositing}{shading}{target}{method}",
        s.volume_resolution, s.scatter_iterations, s.chord_segments, s.light_supersampling
    )
}

pub(crate) static WALL_AXIS: std::sync::OnceLock<bool> = std::sync::OnceLock::new();

/// Whether the Pareto front uses wall time instead of GPU time: on llvmpipe (lavapipe), where a
/// timestamp is only taken when the driver flushes, so a pass of one dispatch reads ~0 ms and the
/// first dispatch of every pass is missed; the GPU is the CPU there, and the wall time of a frame
/// is its cost (plus a constant per-frame overhead, which does not change which settings dominate).
pub(crate) fn wall_axis() -> bool {
    *WALL_AXIS.get().unwrap_or(&false)
}

pub(crate) fn cost_name() -> &'static str {
    if wall_axis() {
        "wall ms per frame"
    } else {
        "GPU ms per frame"
    }
}

/// Marks the rows of one scene on the Pareto front of (GPU time, relative RMSE): no other row is
/// at least as fast and at least as accurate, and strictly better in one.
pub(crate) fn mark_pareto(rows: &mut [Row]) {
    let points: Vec<(f64, f64)> = rows.iter().map(|r| (r.cost_ms, r.rel_rmse)).collect();
    for (i, row) in rows.iter_mut().enumerate() {
        let (t, e) = points[i];
        row.pareto = t.is_finite()
            && !points
                .iter()
                .any(|&(t2, e2)| t2 <= t && e2 <= e && (t2 < t || e2 < e));
    }
}

/// The rows that dominate the default settings of a scene.
pub(crate) fn dominating(rows: &[Row]) -> Vec<&Row> {
    let Some(d) = rows
        .iter()
        .find(|r| r.settings == CloudQualitySettings::default())
    else {
        return vec![];
    };
    let (t, e) = (d.cost_ms, d.rel_rmse);
    rows.iter()
        .filter(|r| {
            let (t2, e2) = (r.cost_ms, r.rel_rmse);
            t2 <= t && e2 <= e && (t2 < t || e2 < e)
        })
        .collect()
}

/// One line of `results.csv`; the field names are the header.
#[derive(serde::Serialize)]
struct CsvRow<'a> {
    adapter: &'a str,
    scene: &'a str,
    particles: usize,
    lights: usize,
    width: u32,
    height: u32,
    error_width: u32,
    error_height: u32,
    volume_resolution: u32,
    scatter_iterations: u32,
    stencil: &'static str,
    forward_scattering: f32,
    chord_segments: u32,
    light_supersampling: u32,
    compositing: String,
    billboard_shading: String,
    draw_method: String,
    scatter_coarse_cycles: u32,
    is_default: bool,
    gpu_ms_total: f64,
    gpu_ms_voxelize: f64,
    gpu_ms_shade: f64,
    gpu_ms_gather: f64,
    gpu_ms_scatter: f64,
    gpu_ms_view: f64,
    gpu_ms_draw: f64,
    gpu_ms_static: f64,
    wall_ms: f64,
    wall_ms_static: f64,
    rel_rmse: f64,
    rel_mse: f64,
    mae: f64,
    reference_spp: u32,
    reference_noise: f64,
    pareto: bool,
    pareto_time_axis: &'static str,
    rel_rmse_denoised: f64,
    rel_rmse_box4: f64,
    reference_noise_box4: f64,
    rel_rmse_box4_denoised: f64,
    scatter_directions: String,
}

impl<'a> CsvRow<'a> {
    fn new(adapter: &'a str, r: &'a Row) -> Self {
        let (t, s) = (&r.timing, &r.settings);
        CsvRow {
            adapter,
            scene: r.scene,
            particles: r.particles,
            lights: r.lights,
            width: r.size.0,
            height: r.size.1,
            error_width: r.error_size.0,
            error_height: r.error_size.1,
            volume_resolution: s.volume_resolution,
            scatter_iterations: s.scatter_iterations,
            stencil: stencil_name(s.scatter_stencil),
            forward_scattering: s.forward_scattering,
            chord_segments: s.chord_segments,
            light_supersampling: s.light_supersampling,
            compositing: format!("{:?}", s.compositing),
            billboard_shading: format!("{:?}", s.billboard_shading),
            draw_method: format!("{:?}", s.draw_method),
            scatter_coarse_cycles: s.scatter_coarse_cycles,
            is_default: *s == CloudQualitySettings::default(),
            gpu_ms_total: t.gpu_ms_total,
            gpu_ms_voxelize: t.pass_ms[0],
            gpu_ms_shade: t.pass_ms[1],
            gpu_ms_gather: t.pass_ms[2],
            gpu_ms_scatter: t.pass_ms[3],
            gpu_ms_view: t.pass_ms[4] + t.pass_ms[5],
            gpu_ms_draw: t.pass_ms[6],
            gpu_ms_static: t.gpu_ms_static,
            wall_ms: t.wall_ms,
            wall_ms_static: t.wall_ms_static,
            rel_rmse: r.rel_rmse,
            rel_mse: r.rel_mse,
            mae: r.mae,
            reference_spp: r.reference_spp,
            reference_noise: r.reference_noise,
            pareto: r.pareto,
            pareto_time_axis: if wall_axis() {
                "wall_ms"
            } else {
                "gpu_ms_total"
            },
            rel_rmse_denoised: denoised(r.rel_rmse, r.reference_noise),
            rel_rmse_box4: r.rel_rmse_box4,
            reference_noise_box4: r.reference_noise_box4,
            rel_rmse_box4_denoised: denoised(r.rel_rmse_box4, r.reference_noise_box4),
            scatter_directions: format!("{:?}", s.scatter_directions),
        }
    }
}

/// Writes `results.csv`: one row per scene and setting (the `csv` crate quotes what needs it).
pub(crate) fn write_csv_results(path: &Path, adapter: &str, rows: &[Row]) -> csv::Result<()> {
    let mut writer = csv::Writer::from_path(path)?;
    for r in rows {
        writer.serialize(CsvRow::new(adapter, r))?;
    }
    writer.flush()?;
    Ok(())
}

pub(crate) fn markdown(adapter: &str, rows: &[Row], scene_order: &[&'static str]) -> String {
    let mut s = format!(
        "Adapter: `{adapter}`. GPU ms: sum of the per-pass GPU times of a frame in which every pass reruns \
         (voxelize + shade + gather + scatter + sort + draw), median; static: a frame with nothing changed (draw only). \
         Wall ms: the frame's wall time (update + GPU wait). Errors against the path-traced reference \
         (relative RMSE, relMSE, mean absolute error); ★ = on the Pareto front of ({}, relative RMSE), \
         **bold** = the default settings (`CloudQualitySettings::default()`). Settings: `N³ ×M stencil Kk Lf` = volume_resolution, \
         scatter_iterations, stencil (D = DiscreteOrdinates, P = Paper), chord_segments, light_supersampling; \
         forward_scattering 0.\n",
        if wall_axis() {
            "wall ms: on llvmpipe the timestamps miss single-dispatch passes"
        } else {
            "GPU ms"
        }
    );
    for &name in scene_order {
        let scene_rows: Vec<&Row> = rows.iter().filter(|r| r.scene == name).collect();
        let Some(first) = scene_rows.first() else {
            continue;
        };
        let _ = write!(
            s,
            "\n### {name}\n\n{} particles, {} light(s), rendered at {}×{}, errors at {}×{}; reference: {} spp, noise {:.4} (relative RMSE; {:.4} after a 4×4 box filter)\n\n",
            first.particles,
            first.lights,
            first.size.0,
            first.size.1,
            first.error_size.0,
            first.error_size.1,
            first.reference_spp,
            first.reference_noise,
            first.reference_noise_box4
        );
        s.push_str("| setting | GPU ms | voxelize | shade | gather | scatter | sort | draw | static GPU ms | wall ms | static wall ms | rel. RMSE | denoised | 4×4 box, denoised | relMSE | MAE | front |\n");
        s.push_str(
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|:---:|\n",
        );
        let mut sorted = scene_rows.clone();
        sorted.sort_by(|a, b| a.cost_ms.total_cmp(&b.cost_ms));
        for r in sorted {
            let t = &r.timing;
            let label = setting_label(&r.settings);
            let label = if r.settings == CloudQualitySettings::default() {
                format!("**{label}**")
            } else {
                label
            };
            let _ = writeln!(
                s,
                "| {label} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.0} | {:.0} | {:.4} | {:.4} | {:.4} | {:.5} | {:.5} | {} |",
                t.gpu_ms_total,
                t.pass_ms[0],
                t.pass_ms[1],
                t.pass_ms[2],
                t.pass_ms[3],
                t.pass_ms[4] + t.pass_ms[5],
                t.pass_ms[6],
                t.gpu_ms_static,
                t.wall_ms,
                t.wall_ms_static,
                r.rel_rmse,
                denoised(r.rel_rmse, r.reference_noise),
                denoised(r.rel_rmse_box4, r.reference_noise_box4),
                r.rel_mse,
                r.mae,
                if r.pareto { "★" } else { "" }
            );
        }
        let dom = dominating(
            &rows
                .iter()
                .filter(|r| r.scene == name)
                .cloned()
                .collect::<Vec<_>>(),
        )
        .iter()
        .map(|r| setting_label(&r.settings))
        .collect::<Vec<_>>();
        if dom.is_empty() {
            s.push_str("\nThe default settings are on the Pareto front.\n");
        } else {
            let _ = writeln!(
                s,
                "\nThe default settings are dominated by: {}.",
                dom.join(", ")
            );
        }
    }
    s
}

/// Writes `md` to `DIR/file` and prints it.
pub(crate) fn write_report(out: &Path, file: &str, md: &str) -> Result<(), String> {
    let path = out.join(file);
    std::fs::write(&path, md).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    println!("{md}");
    Ok(())
}
