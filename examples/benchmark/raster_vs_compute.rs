//! `raster-vs-compute`: does the adapter run the draw's kind of per-pixel work slower in a
//! fragment shader than in a compute shader, and is it the work or the fragments?
//!
//! The same synthetic work, in plain wgpu outside Bevy: `layers` billboards over every pixel of
//! the view (the paper's scene covers each 1080p pixel 13 times), each evaluating `points` chord
//! points that read the optical depth of `volumes` volumes of 128³ trilinearly from storage
//! buffers (the default draw: 9 points, 5 lights and the multiple scattering). Three ways:
//! - **raster, layered**: one full-view quad per layer, blended additively into Rgba16Float
//!   (the draw's structure);
//! - **raster, looped**: one quad, each fragment looping over the layers (the same shading, one
//!   fragment and one blend per pixel);
//! - **compute**: one invocation per pixel looping over the layers, one store per pixel.
//!
//! All three write the same image (checked: `max_difference`), so they do the same work.

use std::{borrow::Cow, fmt::Write as _, path::Path, time::Instant};

use wgpu::util::DeviceExt as _;

use super::{Frames, parse_view, write_report};

/// The options of `benchmark raster-vs-compute`.
#[derive(clap::Args, Debug)]
pub(crate) struct RasterVsComputeArgs {
    /// The view's size, pixels.
    #[arg(long, default_value = "1920x1080", value_parser = parse_view)]
    pub(crate) view: (u32, u32),
    /// Billboards over each pixel (the paper's scene: 13 at 1080p).
    #[arg(long, default_value_t = 13, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub(crate) layers: u32,
    #[command(flatten)]
    pub(crate) frames: Frames,
}

/// `benchmark raster-vs-compute`: the default draw's per-pixel work (9 chord points, 5 lights and
/// the multiple scattering) and the bare fragments (no chord point), three ways each; writes
/// `DIR/raster_vs_compute.md`.
pub(crate) fn raster_vs_compute_benchmark(
    args: &RasterVsComputeArgs,
    out: &Path,
) -> Result<(), String> {
    let (width, height) = args.view;
    let mut md = String::new();
    for points in [9, 0] {
        let work = Workload {
            width,
            height,
            layers: args.layers,
            points,
            volumes: 6,
            n: 128,
        };
        eprintln!("benchmark: raster vs compute, {points} points");
        let (adapter, results) = measure(work, args.frames.count())?;
        md.push_str(&table(&adapter, work, &results));
        md.push('\n');
    }
    write_report(out, "raster_vs_compute.md", &md)
}

/// The synthetic draw: view size, billboards per pixel, chord points, volumes and their size.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Workload {
    pub(crate) width: u32,
    pub(crate) height: u32,
    pub(crate) layers: u32,
    pub(crate) points: u32,
    pub(crate) volumes: u32,
    pub(crate) n: u32,
}

impl Workload {
    /// Pixel-layer pairs: the fragments of the layered raster.
    pub(crate) fn fragments(&self) -> f64 {
        self.width as f64 * self.height as f64 * self.layers as f64
    }
}

const SHADER: &str = r#"
struct Work { width: u32, height: u32, layers: u32, points: u32, volumes: u32, n: u32 }
@group(0) @binding(0) var<uniform> work: Work;
@group(0) @binding(1) var<storage, read> volume: array<f32>;

fn trilinear(k: u32, x: vec3<f32>) -> f32 {
    let n = work.n;
    let base = min(vec3<u32>(floor(x)), vec3(n - 2u));
    let f = x - vec3<f32>(base);
    var sum = 0.0;
    for (var c = 0u; c < 8u; c++) {
        let o = vec3<u32>(c & 1u, (c >> 1u) & 1u, c >> 2u);
        let w = select(1.0 - f, f, vec3<bool>(o));
        let i = base + o;
        sum += w.x * w.y * w.z * volume[k * n * n * n + (i.z * n + i.y) * n + i.x];
    }
    return sum;
}

// One billboard's light at one pixel: a chord of `points` points through the volumes.
fn shade(pixel: vec2<u32>, layer: u32) -> vec4<f32> {
    let uv = (vec2<f32>(pixel) + 0.5) / vec2<f32>(f32(work.width), f32(work.height));
    let extent = f32(work.n - 1u);
    var light = 0.001 * f32(layer + 1u);
    for (var i = 0u; i < work.points; i++) {
        let depth = (f32(layer) + (f32(i) + 0.5) / f32(work.points)) / f32(work.layers);
        let x = clamp(vec3(uv, depth), vec3(0.0), vec3(1.0)) * extent;
        var tau = 0.0;
        for (var k = 0u; k < work.volumes; k++) {
            tau += trilinear(k, x);
        }
        light += exp(-tau) / f32(work.points);
    }
    return vec4(light, 0.5 * light, 0.25 * light, 0.0);
}

// A full-view quad per instance.
@vertex
fn vertex(@builtin(vertex_index) v: u32, @builtin(instance_index) layer: u32) -> @builtin(position) vec4<f32> {
    let corner = vec2(f32(v & 1u), f32(v >> 1u)) * 2.0 - 1.0;
    return vec4(corner, 0.5, 1.0);
}

// Blended additively: one layer each; the instance is recovered from the draw's uniform below.
@group(0) @binding(2) var<uniform> layer_of_draw: vec4<u32>;

@fragment
fn layered(@builtin(position) p: vec4<f32>) -> @location(0) vec4<f32> {
    return shade(vec2<u32>(p.xy), layer_of_draw.x);
}

@fragment
fn looped(@builtin(position) p: vec4<f32>) -> @location(0) vec4<f32> {
    var sum = vec4(0.0);
    for (var l = 0u; l < work.layers; l++) {
        sum += shade(vec2<u32>(p.xy), l);
    }
    return sum;
}

@group(0) @binding(3) var image: texture_storage_2d<rgba16float, write>;

@compute @workgroup_size(8, 8, 1)
fn compute(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= work.width || id.y >= work.height {
        return;
    }
    var sum = vec4(0.0);
    for (var l = 0u; l < work.layers; l++) {
        sum += shade(id.xy, l);
    }
    textureStore(image, id.xy, sum);
}
"#;

/// What one way of drawing took and wrote.
pub(crate) struct Measured {
    pub(crate) name: &'static str,
    /// Median over the repetitions, milliseconds of wall time (one submission each).
    pub(crate) ms: f64,
    pub(crate) image: Vec<f32>,
}

/// A plain wgpu device on the Vulkan adapter Bevy would pick.
pub(crate) struct Gpu {
    pub(crate) device: wgpu::Device,
    pub(crate) queue: wgpu::Queue,
    pub(crate) adapter: String,
}

impl Gpu {
    /// Submits `encoder` and waits for it: wall milliseconds.
    pub(crate) fn run(&self, encoder: wgpu::CommandEncoder) -> Result<f64, String> {
        let start = Instant::now();
        self.queue.submit([encoder.finish()]);
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| e.to_string())?;
        Ok(start.elapsed().as_secs_f64() * 1e3)
    }
}

pub(crate) fn gpu() -> Result<Gpu, String> {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::VULKAN;
    desc.flags = wgpu::InstanceFlags::default().with_env();
    let instance = wgpu::Instance::new(desc);
    let adapter = pollster(instance.request_adapter(&wgpu::RequestAdapterOptions {
        power_preference: wgpu::PowerPreference::HighPerformance,
        force_fallback_adapter: false,
        compatible_surface: None,
    }))
    .map_err(|e| format!("no Vulkan adapter ({e}): install mesa-vulkan-drivers or a GPU driver"))?;
    let name = adapter.get_info().name;
    let (device, queue) = pollster(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("raster_vs_compute"),
        required_limits: adapter.limits(),
        ..Default::default()
    }))
    .map_err(|e| format!("cannot open {name}: {e}"))?;
    Ok(Gpu {
        device,
        queue,
        adapter: name,
    })
}

fn pollster<F: std::future::Future>(f: F) -> F::Output {
    bevy::tasks::block_on(f)
}

/// Runs the three ways `repeats` times each on the adapter; returns its name and the results.
pub(crate) fn measure(work: Workload, repeats: usize) -> Result<(String, Vec<Measured>), String> {
    let gpu = gpu()?;
    let device = &gpu.device;
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("raster_vs_compute"),
        source: wgpu::ShaderSource::Wgsl(Cow::Borrowed(SHADER)),
    });
    let uniform = |label, contents: &[u32]| {
        device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents: bytemuck::cast_slice(contents),
            usage: wgpu::BufferUsages::UNIFORM,
        })
    };
    let work_buffer = uniform(
        "work",
        &[
            work.width,
            work.height,
            work.layers,
            work.points,
            work.volumes,
            work.n,
            0,
            0,
        ],
    );
    let volume = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("volumes"),
        contents: bytemuck::cast_slice(&volumes(work)),
        usage: wgpu::BufferUsages::STORAGE,
    });
    let layers: Vec<wgpu::Buffer> = (0..work.layers)
        .map(|l| uniform("layer", &[l, 0, 0, 0]))
        .collect();
    let extent = wgpu::Extent3d {
        width: work.width,
        height: work.height,
        depth_or_array_layers: 1,
    };
    let target = device.create_texture(&wgpu::TextureDescriptor {
        label: Some("target"),
        size: extent,
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: wgpu::TextureFormat::Rgba16Float,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT
            | wgpu::TextureUsages::STORAGE_BINDING
            | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    });
    let target_view = target.create_view(&Default::default());
    let layout = bind_group_layout(device);
    let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: None,
        bind_group_layouts: &[Some(&layout)],
        immediate_size: 0,
    });
    let bind_groups: Vec<wgpu::BindGroup> = layers
        .iter()
        .map(|layer| {
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &layout,
                entries: &[
                    entry(0, work_buffer.as_entire_binding()),
                    entry(1, volume.as_entire_binding()),
                    entry(2, layer.as_entire_binding()),
                    entry(3, wgpu::BindingResource::TextureView(&target_view)),
                ],
            })
        })
        .collect();
    // The storage binding and the attachment are the same texture: the raster passes use a
    // second view-sized texture as attachment, so no binding aliases it.
    let attachment = device.create_texture(&wgpu::TextureDescriptor {
        label: Some("attachment"),
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        ..target_descriptor(extent)
    });
    let attachment_view = attachment.create_view(&Default::default());
    let raster = |entry: &str| raster_pipeline(device, &pipeline_layout, &module, entry);
    let layered = raster("layered");
    let looped = raster("looped");
    let compute = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some("compute"),
        layout: Some(&pipeline_layout),
        module: &module,
        entry_point: Some("compute"),
        compilation_options: Default::default(),
        cache: None,
    });
    let draw = |encoder: &mut wgpu::CommandEncoder, way: usize| {
        if way == 2 {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&compute);
            pass.set_bind_group(0, &bind_groups[0], &[]);
            pass.dispatch_workgroups(work.width.div_ceil(8), work.height.div_ceil(8), 1);
            return;
        }
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: None,
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &attachment_view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        if way == 0 {
            pass.set_pipeline(&layered);
            for group in &bind_groups {
                pass.set_bind_group(0, group, &[]);
                pass.draw(0..4, 0..1);
            }
        } else {
            pass.set_pipeline(&looped);
            pass.set_bind_group(0, &bind_groups[0], &[]);
            pass.draw(0..4, 0..1);
        }
    };
    let names = ["raster, layered", "raster, looped", "compute"];
    let mut results = Vec::new();
    for (way, name) in names.into_iter().enumerate() {
        let source = if way == 2 { &target } else { &attachment };
        let mut times = Vec::new();
        // One warm-up submission (pipeline compilation, first touch), then the timed ones.
        for _ in 0..=repeats {
            let mut encoder = device.create_command_encoder(&Default::default());
            draw(&mut encoder, way);
            times.push(gpu.run(encoder).map_err(|e| format!("{name}: {e}"))?);
        }
        times.remove(0);
        times.sort_by(f64::total_cmp);
        let image = read_back(&gpu, source, work)?;
        results.push(Measured {
            name,
            ms: times[times.len() / 2],
            image,
        });
    }
    Ok((gpu.adapter, results))
}

fn target_descriptor(size: wgpu::Extent3d) -> wgpu::TextureDescriptor<'static> {
    wgpu::TextureDescriptor {
        label: None,
        size,
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: wgpu::TextureFormat::Rgba16Float,
        usage: wgpu::TextureUsages::empty(),
        view_formats: &[],
    }
}

fn entry(binding: u32, resource: wgpu::BindingResource<'_>) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry { binding, resource }
}

fn bind_group_layout(device: &wgpu::Device) -> wgpu::BindGroupLayout {
    let all = wgpu::ShaderStages::VERTEX_FRAGMENT | wgpu::ShaderStages::COMPUTE;
    let buffer = |binding, ty| wgpu::BindGroupLayoutEntry {
        binding,
        visibility: all,
        ty: wgpu::BindingType::Buffer {
            ty,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    };
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: None,
        entries: &[
            buffer(0, wgpu::BufferBindingType::Uniform),
            buffer(1, wgpu::BufferBindingType::Storage { read_only: true }),
            buffer(2, wgpu::BufferBindingType::Uniform),
            wgpu::BindGroupLayoutEntry {
                binding: 3,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::StorageTexture {
                    access: wgpu::StorageTextureAccess::WriteOnly,
                    format: wgpu::TextureFormat::Rgba16Float,
                    view_dimension: wgpu::TextureViewDimension::D2,
                },
                count: None,
            },
        ],
    })
}

fn raster_pipeline(
    device: &wgpu::Device,
    layout: &wgpu::PipelineLayout,
    module: &wgpu::ShaderModule,
    fragment: &str,
) -> wgpu::RenderPipeline {
    let add = wgpu::BlendComponent {
        src_factor: wgpu::BlendFactor::One,
        dst_factor: wgpu::BlendFactor::One,
        operation: wgpu::BlendOperation::Add,
    };
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(fragment),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module,
            entry_point: Some("vertex"),
            compilation_options: Default::default(),
            buffers: &[],
        },
        primitive: wgpu::PrimitiveState {
            topology: wgpu::PrimitiveTopology::TriangleStrip,
            ..Default::default()
        },
        depth_stencil: None,
        multisample: Default::default(),
        fragment: Some(wgpu::FragmentState {
            module,
            entry_point: Some(fragment),
            compilation_options: Default::default(),
            targets: &[Some(wgpu::ColorTargetState {
                format: wgpu::TextureFormat::Rgba16Float,
                blend: Some(wgpu::BlendState {
                    color: add,
                    alpha: add,
                }),
                write_mask: wgpu::ColorWrites::ALL,
            })],
        }),
        multiview_mask: None,
        cache: None,
    })
}

/// Smooth optical depths, 0–0.3 per volume, different in each.
fn volumes(work: Workload) -> Vec<f32> {
    let n = work.n as usize;
    let mut data = Vec::with_capacity(work.volumes as usize * n * n * n);
    for k in 0..work.volumes as usize {
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let phase = (x + 2 * y + 3 * z + 17 * k) as f32 / n as f32;
                    data.push(0.15 + 0.15 * (std::f32::consts::TAU * phase).sin());
                }
            }
        }
    }
    data
}

fn read_back(gpu: &Gpu, texture: &wgpu::Texture, work: Workload) -> Result<Vec<f32>, String> {
    let row = (work.width * 8).next_multiple_of(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT);
    let buffer = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("read back"),
        size: row as u64 * work.height as u64,
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let mut encoder = gpu.device.create_command_encoder(&Default::default());
    encoder.copy_texture_to_buffer(
        texture.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row),
                rows_per_image: None,
            },
        },
        texture.size(),
    );
    gpu.queue.submit([encoder.finish()]);
    buffer.slice(..).map_async(wgpu::MapMode::Read, |_| {});
    gpu.device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| format!("read back: {e}"))?;
    let bytes = buffer.slice(..).get_mapped_range();
    let mut image = Vec::with_capacity((work.width * work.height * 3) as usize);
    for y in 0..work.height as usize {
        for x in 0..work.width as usize {
            let at = y * row as usize + x * 8;
            for c in 0..3 {
                let bits = u16::from_le_bytes([bytes[at + 2 * c], bytes[at + 2 * c + 1]]);
                image.push(f16_to_f32(bits));
            }
        }
    }
    Ok(image)
}

/// IEEE half to single (finite values and zero; the images hold nothing else).
fn f16_to_f32(bits: u16) -> f32 {
    let sign = if bits & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exponent = ((bits >> 10) & 0x1f) as i32;
    let mantissa = (bits & 0x3ff) as f32;
    let magnitude = match exponent {
        0 => mantissa * 2f32.powi(-24),
        _ => (1.0 + mantissa / 1024.0) * 2f32.powi(exponent - 15),
    };
    sign * magnitude
}

/// Largest difference between two images relative to the largest value of the first.
pub(crate) fn max_difference(a: &[f32], b: &[f32]) -> f32 {
    let peak = a.iter().fold(0f32, |m, v| m.max(v.abs()));
    let worst = a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
    worst / peak.max(f32::MIN_POSITIVE)
}

/// The table of one workload's three ways, ns per fragment and each way's time over the layered
/// raster's.
pub(crate) fn table(adapter: &str, work: Workload, results: &[Measured]) -> String {
    let mut md = format!(
        "`raster-vs-compute` on {adapter}: {}×{}, {} layers, {} points × {} volumes of {}³ \
         (wall ms, median of the repetitions)\n\n| way | ms | ns per fragment | × layered | \
         image differs from layered by |\n|---|---:|---:|---:|---:|\n",
        work.width, work.height, work.layers, work.points, work.volumes, work.n
    );
    let base = &results[0];
    for r in results {
        let _ = writeln!(
            md,
            "| {} | {:.2} | {:.3} | {:.3} | {:.1e} |",
            r.name,
            r.ms,
            r.ms * 1e6 / work.fragments(),
            r.ms / base.ms,
            max_difference(&base.image, &r.image)
        );
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The three ways draw the same image: the comparison times the same work.
    #[test]
    fn the_three_ways_draw_the_same_image() {
        let work = Workload {
            width: 48,
            height: 40,
            layers: 3,
            points: 2,
            volumes: 2,
            n: 16,
        };
        let (_, results) = measure(work, 1).expect("an adapter");
        let peak = results[0].image.iter().fold(0f32, |m, v| m.max(*v));
        assert!(peak > 0.01, "the image holds light: peak {peak}");
        for r in &results[1..] {
            let d = max_difference(&results[0].image, &r.image);
            assert!(
                d < 4e-3,
                "{} differs from the layered raster by {d}",
                r.name
            );
        }
    }
}
