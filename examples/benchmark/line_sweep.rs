//! `line-sweep`: why the scattering's sweeps are slow on a GPU, and whether cutting each
//! lattice line into segments would help.
//!
//! The sweep (`scatter.wgsl`) gives each lattice line of an `n³` grid to one invocation, which
//! marches it voxel by voxel: the radiance at a voxel is the upwind voxel's, attenuated, plus the
//! segment's scattering, and each voxel's share is added to the next order (a read-modify-write).
//! At 128³ a direction has 16,384 to 65,025 lines: a few warps per multiprocessor of a large GPU,
//! each waiting on memory at every step. Here the same recurrence in plain wgpu, along x and
//! along z, three ways:
//! - **serial**: as the sweep does it (one invocation per line, read-modify-write deposits);
//! - **serial, overwrite**: the same with plain stores (what the read of each deposit costs);
//! - **segmented**: each line cut into `segments` pieces, one invocation each, in two
//!   dispatches: each piece's transfer (its transmittance and what it adds with nothing
//!   entering), then each piece composes the transfers upwind of it into the radiance entering
//!   it, and marches it, depositing. `segments` times the invocations, twice the reads.
//!
//! Every way deposits the same volume (checked: `max_difference`).

use std::{borrow::Cow, fmt::Write as _, path::Path};

use wgpu::util::DeviceExt as _;

use super::raster_vs_compute::{Gpu, gpu, max_difference};
use super::{Frames, write_report};

/// The options of `benchmark line-sweep`.
#[derive(clap::Args, Debug)]
pub(crate) struct LineSweepArgs {
    /// Voxels per side of the grid.
    #[arg(long, default_value_t = 128, value_parser = clap::value_parser!(u32).range(2..=512))]
    pub(crate) grid: u32,
    /// Segments per line.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub(crate) segments: u32,
    #[command(flatten)]
    pub(crate) frames: Frames,
}

/// `benchmark line-sweep`: 26 sweeps per timed submission (two iterations' worth); writes
/// `DIR/line_sweep.md`.
pub(crate) fn line_sweep_benchmark(args: &LineSweepArgs, out: &Path) -> Result<(), String> {
    eprintln!(
        "benchmark: line sweep, {}³, {} segments",
        args.grid, args.segments
    );
    let (adapter, results) = measure(args.grid, args.segments, 26, args.frames.count())?;
    let md = table(&adapter, args.grid, &results);
    write_report(out, "line_sweep.md", &md)
}

const SHADER: &str = r#"
// `overwrite`: plain stores instead of read-modify-write deposits.
struct Work { n: u32, axis: u32, segments: u32, overwrite: u32 }
@group(0) @binding(0) var<uniform> work: Work;
@group(0) @binding(1) var<storage, read> density: array<f32>;
@group(0) @binding(2) var<storage, read> s_in: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> s_out: array<vec4<f32>>;
// Per line and segment: what the segment adds with nothing entering (xyz), its transmittance (w).
@group(0) @binding(4) var<storage, read_write> transfers: array<vec4<f32>>;

fn invocation(id: vec3<u32>, groups: vec3<u32>) -> u32 {
    return id.x + id.y * groups.x * 64u;
}

// Voxel t of line `line` (the other two coordinates), the line along x (axis 0) or z.
fn voxel(line: u32, t: u32) -> u32 {
    let n = work.n;
    if work.axis == 0u {
        return t + n * line;
    }
    return line + n * n * t;
}

// The radiance after voxel i, `x` entering it: attenuated, plus the voxel's scattering.
fn step(x: vec3<f32>, i: u32) -> vec4<f32> {
    let a = exp(-0.05 * density[i]);
    return vec4(a * x + (1.0 - a) * s_in[i].xyz, a);
}

@compute @workgroup_size(64)
fn serial(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let line = invocation(id, groups);
    if line >= work.n * work.n {
        return;
    }
    var x = vec3(0.0);
    for (var t = 0u; t < work.n; t++) {
        let i = voxel(line, t);
        x = step(x, i).xyz;
        if work.overwrite != 0u {
            s_out[i] = vec4(x / 26.0, 0.0);
        } else {
            s_out[i] += vec4(x / 26.0, 0.0);
        }
    }
}

fn segment_span(segment: u32) -> vec2<u32> {
    let length = (work.n + work.segments - 1u) / work.segments;
    return vec2(min(segment * length, work.n), min((segment + 1u) * length, work.n));
}

@compute @workgroup_size(64)
fn segment_transfer(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let k = invocation(id, groups);
    let line = k / work.segments;
    if line >= work.n * work.n {
        return;
    }
    let span = segment_span(k % work.segments);
    var added = vec3(0.0);
    var transmittance = 1.0;
    for (var t = span.x; t < span.y; t++) {
        let s = step(added, voxel(line, t));
        added = s.xyz;
        transmittance *= s.w;
    }
    transfers[k] = vec4(added, transmittance);
}

@compute @workgroup_size(64)
fn segment_march(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let k = invocation(id, groups);
    let line = k / work.segments;
    if line >= work.n * work.n {
        return;
    }
    let segment = k % work.segments;
    var x = vec3(0.0);
    for (var upwind = 0u; upwind < segment; upwind++) {
        let transfer = transfers[line * work.segments + upwind];
        x = transfer.w * x + transfer.xyz;
    }
    let span = segment_span(segment);
    for (var t = span.x; t < span.y; t++) {
        let i = voxel(line, t);
        x = step(x, i).xyz;
        s_out[i] += vec4(x / 26.0, 0.0);
    }
}
"#;

/// One way's time per direction dispatch (two for the segmented way), and what it deposited.
pub(crate) struct Swept {
    pub(crate) name: String,
    pub(crate) axis: u32,
    /// Median over the repetitions, wall ms per sweep of all the lines (its dispatches).
    pub(crate) ms: f64,
    pub(crate) volume: Vec<f32>,
}

/// The three ways along x and along z on an `n³` grid, `repeats` timed submissions of
/// `sweeps` sweeps each.
pub(crate) fn measure(
    n: u32,
    segments: u32,
    sweeps: u32,
    repeats: usize,
) -> Result<(String, Vec<Swept>), String> {
    let gpu = gpu()?;
    let device = &gpu.device;
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("line_sweep"),
        source: wgpu::ShaderSource::Wgsl(Cow::Borrowed(SHADER)),
    });
    let voxels = (n as usize).pow(3);
    let density: Vec<f32> = (0..voxels)
        .map(|i| ((i * 7919) % 101) as f32 / 10.0)
        .collect();
    let s_in: Vec<f32> = (0..4 * voxels)
        .map(|i| ((i * 104729) % 97) as f32 / 97.0)
        .collect();
    let storage = |label, contents: &[u8]| {
        device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        })
    };
    let density = storage("density", bytemuck::cast_slice(&density));
    let s_in = storage("s_in", bytemuck::cast_slice(&s_in));
    let s_out = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("s_out"),
        size: 16 * voxels as u64,
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let transfers = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("transfers"),
        size: 16 * (n * n * segments) as u64,
        usage: wgpu::BufferUsages::STORAGE,
        mapped_at_creation: false,
    });
    let entries: Vec<wgpu::BindGroupLayoutEntry> = (0..5)
        .map(|binding| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: match binding {
                    0 => wgpu::BufferBindingType::Uniform,
                    1 | 2 => wgpu::BufferBindingType::Storage { read_only: true },
                    _ => wgpu::BufferBindingType::Storage { read_only: false },
                },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        })
        .collect();
    let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: None,
        entries: &entries,
    });
    let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: None,
        bind_group_layouts: &[Some(&layout)],
        immediate_size: 0,
    });
    let pipeline = |entry: &str| {
        device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(entry),
            layout: Some(&pipeline_layout),
            module: &module,
            entry_point: Some(entry),
            compilation_options: Default::default(),
            cache: None,
        })
    };
    let [serial, transfer, march] = ["serial", "segment_transfer", "segment_march"].map(pipeline);
    let mut results = Vec::new();
    for axis in [0, 2] {
        // Each way: its name, its dispatches, invocations per line, and whether it overwrites.
        let ways: [(String, Vec<&wgpu::ComputePipeline>, u32, u32); 3] = [
            ("serial".into(), vec![&serial], 1, 0),
            ("serial, overwrite".into(), vec![&serial], 1, 1),
            (
                format!("segmented ×{segments}"),
                vec![&transfer, &march],
                segments,
                0,
            ),
        ];
        for (name, stages, per_line, overwrite) in ways {
            let work = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("work"),
                contents: bytemuck::cast_slice(&[n, axis, segments, overwrite]),
                usage: wgpu::BufferUsages::UNIFORM,
            });
            let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &layout,
                entries: &[&work, &density, &s_in, &s_out, &transfers]
                    .iter()
                    .enumerate()
                    .map(|(i, b)| wgpu::BindGroupEntry {
                        binding: i as u32,
                        resource: b.as_entire_binding(),
                    })
                    .collect::<Vec<_>>(),
            });
            let invocations = n * n * per_line;
            let groups = invocations.div_ceil(64);
            let (x, y) = (groups.min(65535), groups.div_ceil(65535));
            let record = |count: u32| {
                let mut encoder = device.create_command_encoder(&Default::default());
                encoder.clear_buffer(&s_out, 0, None);
                {
                    let mut pass = encoder.begin_compute_pass(&Default::default());
                    pass.set_bind_group(0, &group, &[]);
                    for _ in 0..count {
                        for stage in &stages {
                            pass.set_pipeline(stage);
                            pass.dispatch_workgroups(x, y, 1);
                        }
                    }
                }
                encoder
            };
            // One sweep for the volume it deposits; a warm-up; then the timed ones.
            gpu.run(record(1))?;
            let volume = read_back(&gpu, &s_out, voxels)?;
            gpu.run(record(sweeps))?;
            let mut times = Vec::new();
            for _ in 0..repeats {
                times.push(gpu.run(record(sweeps))? / sweeps as f64);
            }
            times.sort_by(f64::total_cmp);
            results.push(Swept {
                name,
                axis,
                ms: times[times.len() / 2],
                volume,
            });
        }
    }
    Ok((gpu.adapter, results))
}

fn read_back(gpu: &Gpu, buffer: &wgpu::Buffer, voxels: usize) -> Result<Vec<f32>, String> {
    let staging = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("read back"),
        size: 16 * voxels as u64,
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let mut encoder = gpu.device.create_command_encoder(&Default::default());
    encoder.copy_buffer_to_buffer(buffer, 0, &staging, 0, None);
    gpu.run(encoder)?;
    staging.slice(..).map_async(wgpu::MapMode::Read, |_| {});
    gpu.device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| format!("read back: {e}"))?;
    let bytes = staging.slice(..).get_mapped_range();
    Ok(bytemuck::cast_slice::<u8, f32>(&bytes).to_vec())
}

/// The table: ms per sweep, and each way against the serial one of its axis.
pub(crate) fn table(adapter: &str, n: u32, results: &[Swept]) -> String {
    let mut md = format!(
        "`line-sweep` on {adapter}: one sweep of every lattice line along an axis of a {n}³ \
         grid (wall ms per sweep, median of the repetitions)\n\n| lines along | way | ms | × \
         serial | volume differs from serial's by |\n|---|---|---:|---:|---:|\n"
    );
    for r in results {
        let base = results
            .iter()
            .find(|b| b.axis == r.axis)
            .expect("a serial way per axis");
        let _ = writeln!(
            md,
            "| {} | {} | {:.3} | {:.3} | {:.1e} |",
            ["x", "y", "z"][r.axis as usize],
            r.name,
            r.ms,
            r.ms / base.ms,
            max_difference(&base.volume, &r.volume)
        );
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Cutting the lines into segments deposits what marching them whole does.
    #[test]
    fn segmented_lines_deposit_what_whole_lines_do() {
        let (_, results) = measure(12, 5, 1, 1).expect("an adapter");
        for r in &results {
            let base = results.iter().find(|b| b.axis == r.axis).unwrap();
            let peak = base.volume.iter().fold(0f32, |m, v| m.max(*v));
            assert!(peak > 0.001, "the sweep deposits: peak {peak}");
            let d = max_difference(&base.volume, &r.volume);
            assert!(d < 1e-5, "{} along axis {} differs by {d}", r.name, r.axis);
        }
    }
}
