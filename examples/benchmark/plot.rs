//! Every plot the benchmark draws: the Pareto plot of `accuracy` (`pareto.png`) and the cost
//! panels of `scale` (`scale.png`), each also redrawn from its CSV by `replot` and `replot-scale`.

use super::*;

/// Registers the TTF `font` as plotters' "sans-serif".
pub(crate) fn register_font(font: &Path) -> Result<(), String> {
    use plotters::prelude::FontStyle;
    let bytes = std::fs::read(font).map_err(|e| {
        format!(
            "cannot read the plot's font {}: {e}; install it with `apt-get install fonts-dejavu-core` or pass --font FILE.ttf",
            font.display()
        )
    })?;
    let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
    plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
        .map_err(|_| format!("{} is not a TrueType/OpenType font", font.display()))
}

/// The Pareto plot: each scene's cost against its relative RMSE, one panel per scene.
pub(crate) fn plot(
    path: &Path,
    font: &Path,
    adapter: &str,
    rows: &[Row],
    scene_order: &[&'static str],
) -> Result<(), String> {
    use plotters::prelude::*;
    register_font(font)?;

    let scenes: Vec<&str> = scene_order
        .iter()
        .copied()
        .filter(|n| rows.iter().any(|r| r.scene == *n))
        .collect();
    let cols = scenes.len().clamp(1, 3) as u32;
    let rows_n = (scenes.len() as u32).div_ceil(cols).max(1);
    let (w, h) = (420 * cols, 330 * rows_n + 64);
    let mut buffer = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let (title, body) = root.split_vertically(64);
        title
            .draw_text(
                &format!(
                    "{} (every pass reruns) vs. relative RMSE, {adapter}",
                    cost_name()
                ),
                &("sans-serif", 18).into_font().color(&BLACK),
                (10, 12),
            )
            .map_err(|e| e.to_string())?;
        let panels = body.split_evenly((rows_n as usize, cols as usize));
        for (panel, name) in panels.iter().zip(&scenes) {
            let pts: Vec<&Row> = rows
                .iter()
                .filter(|r| r.scene == *name && r.cost_ms.is_finite())
                .collect();
            let (t_lo, t_hi) = pts.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
                (lo.min(r.cost_ms), hi.max(r.cost_ms))
            });
            let (e_lo, e_hi) = pts.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
                (lo.min(r.rel_rmse), hi.max(r.rel_rmse))
            });
            let noise = pts.first().map_or(0.0, |r| r.reference_noise);
            let mut chart = ChartBuilder::on(panel)
                .caption(
                    format!("{name} (ref. noise {noise:.3})"),
                    ("sans-serif", 15),
                )
                .margin(8)
                .x_label_area_size(32)
                .y_label_area_size(52)
                .build_cartesian_2d(
                    ((t_lo * 0.8).max(1e-3)..t_hi * 1.25).log_scale(),
                    (e_lo * 0.9).max(1e-4)..e_hi * 1.08,
                )
                .map_err(|e| e.to_string())?;
            chart
                .configure_mesh()
                .x_desc(cost_name())
                .y_desc("relative RMSE")
                .label_style(("sans-serif", 11))
                .axis_desc_style(("sans-serif", 12))
                .x_labels(8)
                .y_labels(6)
                .x_label_formatter(&|v| {
                    if *v >= 10.0 {
                        format!("{v:.0}")
                    } else {
                        format!("{v:.1}")
                    }
                })
                .y_label_formatter(&|v| format!("{v:.2}"))
                .light_line_style(WHITE)
                .draw()
                .map_err(|e| e.to_string())?;
            if noise > e_lo * 0.9 {
                chart
                    .draw_series(LineSeries::new(
                        [(t_lo * 0.8, noise), (t_hi * 1.25, noise)],
                        ShapeStyle::from(&RGBColor(160, 160, 160)).stroke_width(1),
                    ))
                    .map_err(|e| e.to_string())?;
            }
            let mut front: Vec<(f64, f64)> = pts
                .iter()
                .filter(|r| r.pareto)
                .map(|r| (r.cost_ms, r.rel_rmse))
                .collect();
            front.sort_by(|a, b| a.0.total_cmp(&b.0));
            chart
                .draw_series(LineSeries::new(
                    front.clone(),
                    ShapeStyle::from(&BLACK).stroke_width(2),
                ))
                .map_err(|e| e.to_string())?
                .label("Pareto front")
                .legend(|(x, y)| {
                    PathElement::new(vec![(x, y), (x + 14, y)], BLACK.stroke_width(2))
                });
            let res_colour = |n: u32| match n {
                ..=24 => RGBColor(120, 120, 120),
                32 => RGBColor(230, 159, 0),
                48 => RGBColor(86, 180, 233),
                64 => RGBColor(0, 158, 115),
                96 => RGBColor(0, 114, 178),
                _ => RGBColor(213, 94, 0),
            };
            for stencil in [ScatterStencil::DiscreteOrdinates, ScatterStencil::Paper] {
                let series: Vec<&&Row> = pts
                    .iter()
                    .filter(|r| r.settings.scatter_stencil == stencil)
                    .collect();
                if series.is_empty() {
                    continue;
                }
                let drawn = chart
                    .draw_series(series.iter().map(|r| {
                        let c = res_colour(r.settings.volume_resolution);
                        let p = (r.cost_ms, r.rel_rmse);
                        match stencil {
                            ScatterStencil::DiscreteOrdinates => {
                                Circle::new(p, 3, c.filled()).into_dyn()
                            }
                            ScatterStencil::Paper => {
                                TriangleMarker::new(p, 4, c.stroke_width(1)).into_dyn()
                            }
                        }
                    }))
                    .map_err(|e| e.to_string())?;
                match stencil {
                    ScatterStencil::DiscreteOrdinates => drawn
                        .label("DiscreteOrdinates stencil")
                        .legend(|(x, y)| Circle::new((x + 7, y), 3, BLACK.filled())),
                    ScatterStencil::Paper => drawn
                        .label("Paper stencil")
                        .legend(|(x, y)| TriangleMarker::new((x + 7, y), 4, BLACK.stroke_width(1))),
                };
            }
            if let Some(d) = pts
                .iter()
                .find(|r| r.settings == CloudQualitySettings::default())
            {
                chart
                    .draw_series([Cross::new(
                        (d.cost_ms, d.rel_rmse),
                        7,
                        ShapeStyle::from(&RED).stroke_width(2),
                    )])
                    .map_err(|e| e.to_string())?
                    .label("default settings")
                    .legend(|(x, y)| Cross::new((x + 7, y), 5, RED.stroke_width(2)));
            }
        }
        // Markers, once: stencil shapes, the default, the front.
        let text = ("sans-serif", 14).into_font().color(&BLACK);
        let y = 46;
        let t = |e: DrawingAreaErrorKind<_>| e.to_string();
        title
            .draw(&Circle::new((16, y), 4, BLACK.filled()))
            .map_err(t)?;
        title
            .draw_text("DiscreteOrdinates stencil", &text, (26, y - 7))
            .map_err(t)?;
        title
            .draw(&TriangleMarker::new((200, y), 5, BLACK.stroke_width(1)))
            .map_err(t)?;
        title
            .draw_text("Paper stencil", &text, (210, y - 7))
            .map_err(t)?;
        title
            .draw(&Cross::new((480, y), 6, RED.stroke_width(2)))
            .map_err(t)?;
        title
            .draw_text("default settings", &text, (492, y - 7))
            .map_err(t)?;
        title
            .draw(&PathElement::new(
                vec![(630, y), (654, y)],
                BLACK.stroke_width(2),
            ))
            .map_err(t)?;
        title
            .draw_text(
                "Pareto front; grey line: reference noise",
                &text,
                (660, y - 7),
            )
            .map_err(t)?;
        // Resolution colours, once.
        let legend = ["32³", "48³", "64³", "96³", "128³"];
        let colours = [
            (230, 159, 0),
            (86, 180, 233),
            (0, 158, 115),
            (0, 114, 178),
            (213, 94, 0),
        ];
        for (i, (l, c)) in legend.iter().zip(colours).enumerate() {
            let x = w as i32 - 330 + 64 * i as i32;
            title
                .draw(&Circle::new((x, 20), 5, RGBColor(c.0, c.1, c.2).filled()))
                .map_err(|e| e.to_string())?;
            title
                .draw_text(
                    l,
                    &("sans-serif", 14).into_font().color(&BLACK),
                    (x + 8, 13),
                )
                .map_err(|e| e.to_string())?;
        }
        root.present().map_err(|e| e.to_string())?;
    }
    save_plot(buffer, (w, h), path)
}

/// Log–log panels of each pass's GPU time against the sweep's variable.
pub(crate) fn plot_scale(
    path: &Path,
    font: &Path,
    adapter: &str,
    rows: &[ScaleRow],
) -> Result<(), String> {
    use plotters::prelude::*;
    register_font(font)?;
    let sweeps = [
        ("particles", "particles"),
        ("clouds", "clouds (38,400 particles in all)"),
        ("view", "view pixels"),
    ];
    let (w, h) = (1260u32, 420u32);
    let mut buffer = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let (title, body) = root.split_vertically(40);
        title
            .draw_text(
                &format!("GPU ms per pass (frames that rerun every pass; draw: static), {adapter}"),
                &("sans-serif", 16).into_font().color(&BLACK),
                (10, 10),
            )
            .map_err(|e| e.to_string())?;
        let panels = body.split_evenly((1, sweeps.len()));
        for (panel, (sweep, axis)) in panels.iter().zip(sweeps) {
            let pts: Vec<&ScaleRow> = rows.iter().filter(|r| r.sweep == sweep).collect();
            let series: Vec<(String, Vec<(f64, f64)>)> = CloudPass::ALL
                .iter()
                .enumerate()
                .filter(|(i, _)| pts.iter().any(|r| r.timing.pass_ms[*i] > 0.0))
                .map(|(i, p)| {
                    let line = pts
                        .iter()
                        .filter(|r| r.timing.pass_ms[i] > 0.0)
                        .map(|r| (r.x, r.timing.pass_ms[i]))
                        .collect();
                    (p.name().to_string(), line)
                })
                .chain(std::iter::once((
                    "total".to_string(),
                    pts.iter().map(|r| (r.x, r.timing.gpu_ms_total)).collect(),
                )))
                .collect();
            let all = series.iter().flat_map(|(_, s)| s.iter());
            let (x_lo, x_hi, y_lo, y_hi) = all.fold(
                (f64::INFINITY, 0.0f64, f64::INFINITY, 0.0f64),
                |(a, b, c, d), &(x, y)| (a.min(x), b.max(x), c.min(y), d.max(y)),
            );
            if !x_lo.is_finite() || !y_lo.is_finite() {
                continue;
            }
            let mut chart = ChartBuilder::on(panel)
                .margin(10)
                .x_label_area_size(36)
                .y_label_area_size(50)
                .build_cartesian_2d(
                    (x_lo * 0.8..x_hi * 1.25).log_scale(),
                    (y_lo * 0.5..y_hi * 2.0).log_scale(),
                )
                .map_err(|e| e.to_string())?;
            chart
                .configure_mesh()
                .x_desc(axis)
                .y_desc("GPU ms")
                .x_labels(6)
                .x_label_formatter(&|x| short_number(*x))
                .y_label_formatter(&|y| short_number(*y))
                .draw()
                .map_err(|e| e.to_string())?;
            for (i, (name, line)) in series.iter().enumerate() {
                let color = Palette99::pick(i).to_rgba();
                chart
                    .draw_series(LineSeries::new(line.iter().copied(), color.stroke_width(2)))
                    .map_err(|e| e.to_string())?
                    .label(name.as_str())
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], color));
                chart
                    .draw_series(line.iter().map(|&p| Circle::new(p, 3, color.filled())))
                    .map_err(|e| e.to_string())?;
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperLeft)
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()
                .map_err(|e| e.to_string())?;
        }
        root.present().map_err(|e| e.to_string())?;
    }
    save_plot(buffer, (w, h), path)
}

/// `1.2M`, `38k`, `720`, `0.5`: an axis label.
fn short_number(v: f64) -> String {
    match v {
        v if v >= 1e6 => format!("{}M", (v / 1e5).round() / 10.0),
        v if v >= 1e4 => format!("{}k", (v / 1e3).round()),
        v if v >= 1.0 => format!("{}", v.round()),
        v => format!("{}", (v * 100.0).round() / 100.0),
    }
}

/// Writes a plot's RGB `buffer` of `(w, h)` pixels as PNG.
pub(crate) fn save_plot(buffer: Vec<u8>, (w, h): (u32, u32), path: &Path) -> Result<(), String> {
    let image = image::RgbImage::from_raw(w, h, buffer).expect("buffer size");
    image
        .save_with_format(path, image::ImageFormat::Png)
        .map_err(|e| format!("cannot write {}: {e}", path.display()))
}
