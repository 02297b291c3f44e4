//! `still-view`: what a still frame costs when the view keeps its clouds
//! (`CloudRedraw::WhenChanged`, the default) against drawing them again (`EveryFrame`, which the
//! other modes' static frames measure), at default settings, and how far the kept image is
//! from the drawn one.
//!
//! Cost: the draw's GPU time (the depth comparison, the splat's workgroups that leave at once,
//! the resolve and the composite when kept) and the frame's wall time, medians over
//! [`ROUNDS`] rounds that alternate the two, so that a drift of the machine favours neither.

use bevy_particle_clouds::CloudRedraw;

use super::*;

/// Rounds of static frames per mode, alternating.
const ROUNDS: usize = 4;

/// The scenes measured unless `--scenes` names others.
const DEFAULT_SCENES: [&str; 4] = ["paper_3100", "paper_38k_5lights", "cumulus", "thin_smoke"];

struct StillRow {
    scene: &'static str,
    /// Draw GPU ms and wall ms: drawn, kept.
    draw_ms: [f64; 2],
    wall_ms: [f64; 2],
    /// The largest difference of a channel between the kept and the drawn image, over the
    /// drawn image's peak.
    worst: f32,
}

const MODES: [CloudRedraw; 2] = [CloudRedraw::EveryFrame, CloudRedraw::WhenChanged];

/// The options of `benchmark still-view`.
#[derive(clap::Args, Debug)]
pub(crate) struct StillViewArgs {
    /// Only these scenes (comma-separated names; default: `paper_3100`, `paper_38k_5lights`,
    /// `cumulus`, `thin_smoke`).
    #[arg(long, value_delimiter = ',')]
    pub(crate) scenes: Option<Vec<String>>,
    #[command(flatten)]
    pub(crate) frames: Frames,
}

pub(crate) fn still_view_benchmark(args: &StillViewArgs, out: &Path) -> Result<(), String> {
    let mut rows = Vec::new();
    let mut adapter = String::new();
    for bench in chosen_scenes(args.scenes.as_deref(), &DEFAULT_SCENES) {
        let scene = load_scene(bench)?;
        let mut b = Bench::new(&scene);
        adapter = b.adapter.clone();
        let drawn = b.image();
        let mut times = [(); 2].map(|_| (Vec::new(), Vec::new()));
        for _ in 0..ROUNDS {
            for (i, mode) in MODES.into_iter().enumerate() {
                b.app.insert_resource(mode);
                let (draw, wall) = b.static_frames(args.frames.count());
                times[i].0.extend(draw);
                times[i].1.extend(wall);
            }
        }
        let kept = b.image();
        let [(d0, w0), (d1, w1)] = times;
        let row = StillRow {
            scene: bench.name,
            draw_ms: [median(d0), median(d1)],
            wall_ms: [median(w0), median(w1)],
            worst: kept.worst_difference(&drawn),
        };
        eprintln!(
            "benchmark: {}: still frame drawn {:.2} ms GPU ({:.0} ms wall), kept {:.2} ms ({:.0} ms); kept image within {:.1e} of the peak",
            row.scene, row.draw_ms[0], row.wall_ms[0], row.draw_ms[1], row.wall_ms[1], row.worst
        );
        rows.push(row);
    }
    write_report(
        out,
        "still_view.md",
        &table(&adapter, &rows, args.frames.count()),
    )
}

fn table(adapter: &str, rows: &[StillRow], frames: usize) -> String {
    let mut md = format!(
        "Adapter: `{adapter}`. Default settings, a frame in which nothing changed. Draw: GPU \
         time of the cloud target's draw and composite, median of {ROUNDS} rounds of {frames} \
         frames alternating the two modes; wall: the frame's, Bevy's per-frame work included. \
         Kept image: the largest difference of a channel from the drawn image, over its peak.\n\n\
         | scene | draw, drawn (ms) | draw, kept (ms) | kept / drawn | wall, drawn (ms) | wall, kept (ms) | kept image |\n\
         |---|---:|---:|---:|---:|---:|---:|\n"
    );
    for r in rows {
        let _ = writeln!(
            md,
            "| {} | {:.2} | {:.2} | {:.3} | {:.0} | {:.0} | {:.1e} |",
            r.scene,
            r.draw_ms[0],
            r.draw_ms[1],
            r.draw_ms[1] / r.draw_ms[0],
            r.wall_ms[0],
            r.wall_ms[1],
            r.worst
        );
    }
    md
}
