//! Per-cloud GPU volumes and the decision of which illumination stages must run this frame.
//!
//! Every stage's output is cached with a key of its inputs; a stage runs only when its key
//! changes (docs/illumination.md; the `--stats` counters show it). The density grid lives in
//! cloud-local space, so moving or rotating a cloud never re-voxelizes it: rotation only
//! re-shades (the lights' local directions change) and scale only changes the extinction.

use bevy::{
    prelude::*,
    render::{
        render_asset::RenderAssets,
        render_resource::{Buffer, BufferDescriptor, BufferUsages, ShaderType, encase},
        renderer::{RenderDevice, RenderQueue},
    },
};

use super::{
    extract::{ExtractedCloud, ExtractedCloudLights},
    key_of,
    particles::{CloudBounds, GpuParticles},
};
use crate::{reference::illumination::light_basis, settings::ScatterStencil};

/// Mirror of `CloudParams` in `shaders/types.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct CloudParams {
    /// Voxels per side.
    pub n: u32,
    /// Particles in the cloud.
    pub particle_count: u32,
    /// 0: transmittance stencil, 1: the paper's, 2: free-path hops.
    pub stencil: u32,
    /// Uniform-buffer padding.
    pub _padding: u32,
    /// Corner of the density cube, cloud-local metres.
    pub grid_origin: Vec3,
    /// Voxel size, cloud-local metres.
    pub h: f32,
    /// Centre of the density cube, cloud-local metres.
    pub grid_centre: Vec3,
    /// Extinction per cloud-local metre at density 1 (`K` times the cloud's scale).
    pub k_local: f32,
    /// Single-scattering albedo.
    pub albedo: f32,
    /// Forward-scattering fraction of the shading pass.
    pub forward_scattering: f32,
}

/// Mirror of `LightParams` in `shaders/types.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct LightParams {
    /// First axis across the light, cloud-local.
    pub u: Vec3,
    /// Voxel size along `u`, local metres.
    pub h_u: f32,
    /// Second axis across the light.
    pub v: Vec3,
    /// Voxel size along `v`.
    pub h_v: f32,
    /// The direction the light travels, cloud-local.
    pub w: Vec3,
    /// Voxel size along `w` (the slice thickness).
    pub h_w: f32,
    /// Half-extents of the light box along `u`, `v`, `w`.
    pub half_extents: Vec3,
    /// Extinction per local metre per unit density in the shading pass, `k_local (1 - f albedo)`.
    pub sigma_scale: f32,
    /// Linear RGB irradiance.
    pub irradiance: Vec3,
    /// Gather: 0 writes, 1 adds.
    pub accumulate: u32,
}

impl LightParams {
    /// The light box of a light travelling along `direction_local` (docs/illumination.md §2).
    pub fn new(
        cloud: &CloudParams,
        direction_local: Vec3,
        irradiance: Vec3,
        accumulate: bool,
    ) -> Self {
        let [u, v, w] = light_basis(direction_local.as_dvec3().normalize()).map(|a| a.as_vec3());
        let side = cloud.h * cloud.n as f32;
        let half_extents = 0.5
            * side
            * Vec3::new(
                u.abs().element_sum(),
                v.abs().element_sum(),
                w.abs().element_sum(),
            );
        let h = 2.0 * half_extents / cloud.n as f32;
        Self {
            u,
            h_u: h.x,
            v,
            h_v: h.y,
            w,
            h_w: h.z,
            half_extents,
            sigma_scale: cloud.k_local * (1.0 - cloud.forward_scattering * cloud.albedo),
            irradiance,
            accumulate: accumulate as u32,
        }
    }
}

/// One light's shaded volume inside a cloud.
pub struct LightVolume {
    /// Its `LightParams` uniform.
    pub params: Buffer,
    /// `n³` f32 transmittance towards the light.
    pub transmittance: Buffer,
    /// Key of (density, light direction, extinction) the volume was shaded with.
    pub key: u64,
}

/// What the illumination system must do for one cloud this frame.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct WorkPlan {
    /// Rebuild the density grid.
    pub voxelize: bool,
    /// Indices into `CloudVolumes::lights` to shade.
    pub shade: Vec<usize>,
    /// Gather every light into `S_0`.
    pub gather: bool,
    /// Restart the accumulation from `S_0`, run the scattering iterations, then compute the
    /// particles' colours.
    pub scatter: Option<u32>,
    /// No light reaches the cloud: its colours are zeroed instead of computed.
    pub unlit: bool,
}

impl WorkPlan {
    /// Nothing to do.
    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }
}

/// The GPU volumes of one cloud (render world component).
#[derive(Component)]
pub struct CloudVolumes {
    /// The current uniform values.
    pub params: CloudParams,
    /// The `CloudParams` uniform.
    pub params_buffer: Buffer,
    /// `n³` f32 density (written as atomic u32 bits by voxelize).
    pub density: Buffer,
    /// `n³` vec4 single-scattering source `S_0`.
    pub source: Buffer,
    /// `n³` vec4 ping-pong scattering orders.
    pub orders: [Buffer; 2],
    /// `n³` vec4 accumulated `S`.
    pub accumulated: Buffer,
    /// One vec4 per particle: `albedo * S(c_i)`, what the billboards draw.
    pub colours: Buffer,
    /// One shaded volume per light, in the order of `ExtractedCloudLights`.
    pub lights: Vec<LightVolume>,
    density_key: u64,
    gather_key: u64,
    scatter_key: u64,
    /// This frame's work, consumed by `illuminate_clouds`.
    pub plan: WorkPlan,
    /// Colours hold a finished illumination: the cloud may be drawn.
    pub ready: bool,
}

fn bits(v: Vec3) -> [u32; 3] {
    v.to_array().map(f32::to_bits)
}

/// A storage buffer of at least 16 bytes (bindings may not be empty) that can be cleared, copied and read back.
pub(crate) fn storage(device: &RenderDevice, label: &'static str, size: u64) -> Buffer {
    device.create_buffer(&BufferDescriptor {
        label: Some(label),
        size: size.max(16),
        usage: BufferUsages::STORAGE | BufferUsages::COPY_DST | BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    })
}

fn uniform(device: &RenderDevice, label: &'static str, size: u64) -> Buffer {
    device.create_buffer(&BufferDescriptor {
        label: Some(label),
        size,
        usage: BufferUsages::UNIFORM | BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// Encodes a `ShaderType` value as uniform-buffer bytes.
pub fn uniform_bytes<T: ShaderType + encase::internal::WriteInto>(value: &T) -> Vec<u8> {
    let mut buffer = encase::UniformBuffer::new(Vec::new());
    buffer
        .write(value)
        .expect("uniform encoding cannot fail for plain structs");
    buffer.into_inner()
}

impl CloudVolumes {
    fn new(device: &RenderDevice, n: u32, particle_count: u32) -> Self {
        let voxels = (n as u64).pow(3);
        Self {
            params: CloudParams::default(),
            params_buffer: uniform(
                device,
                "particle_clouds_params",
                CloudParams::min_size().get(),
            ),
            density: storage(device, "particle_clouds_density", voxels * 4),
            source: storage(device, "particle_clouds_source", voxels * 16),
            orders: [
                storage(device, "particle_clouds_order_a", voxels * 16),
                storage(device, "particle_clouds_order_b", voxels * 16),
            ],
            accumulated: storage(device, "particle_clouds_accumulated", voxels * 16),
            colours: storage(
                device,
                "particle_clouds_colours",
                particle_count as u64 * 16,
            ),
            lights: Vec::new(),
            density_key: 0,
            gather_key: 0,
            scatter_key: 0,
            plan: WorkPlan::default(),
            ready: false,
        }
    }

    /// Forgets every cached stage, so that the next frame redoes all of them (used when the work
    /// of a frame could not be recorded, e.g. while pipelines compile).
    pub fn invalidate(&mut self) {
        self.density_key = 0;
        self.gather_key = 0;
        self.scatter_key = 0;
        self.lights.iter_mut().for_each(|l| l.key = 0);
        self.plan = WorkPlan::default();
    }

    fn fits(&self, n: u32, particle_count: u32) -> bool {
        self.params.n == n && self.params.particle_count == particle_count
    }
}

/// The gather key of a cloud that no light reaches.
const UNLIT: u64 = 1;

/// Bytes of the volumes of one cloud at resolution `n` (for the adapter-limit check).
pub fn largest_binding(n: u32) -> u64 {
    (n as u64).pow(3) * 16
}

/// Decides each visible cloud's work for this frame and writes the uniforms it needs.
pub(crate) fn prepare_cloud_volumes(
    mut commands: Commands,
    mut clouds: Query<(Entity, &ExtractedCloud, Option<&mut CloudVolumes>)>,
    lights: Res<ExtractedCloudLights>,
    particles: Res<RenderAssets<GpuParticles>>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
) {
    let max_binding = device.limits().max_storage_buffer_binding_size as u64;
    for (entity, cloud, volumes) in &mut clouds {
        let Some(gpu) = particles.get(cloud.particles) else {
            continue;
        };
        let Some(bounds) = gpu.bounds else {
            commands.entity(entity).remove::<CloudVolumes>();
            continue;
        };
        let n = cloud.settings.volume_resolution;
        if largest_binding(n) > max_binding || gpu.count as u64 * 32 > max_binding {
            warn_once!(
                "particle cloud: `volume_resolution` {n} or {} particles exceed this adapter's storage \
                 buffer limit of {max_binding} bytes; the cloud is not drawn",
                gpu.count
            );
            continue;
        }
        if !cloud.visible || cloud.extinction <= 0.0 {
            continue; // cached volumes stay; no work for clouds nobody sees or that are transparent
        }
        match volumes {
            Some(mut v) if v.fits(n, gpu.count) => {
                plan_cloud(&mut v, cloud, gpu, bounds, &lights, &device, &queue)
            }
            _ => {
                let mut v = CloudVolumes::new(&device, n, gpu.count);
                plan_cloud(&mut v, cloud, gpu, bounds, &lights, &device, &queue);
                commands.entity(entity).insert(v);
            }
        }
    }
}

/// Compares every stage's key with the cached one and records the stages to run.
fn plan_cloud(
    volumes: &mut CloudVolumes,
    cloud: &ExtractedCloud,
    gpu: &GpuParticles,
    bounds: CloudBounds,
    lights: &ExtractedCloudLights,
    device: &RenderDevice,
    queue: &RenderQueue,
) {
    let params = cloud_params(cloud, gpu, bounds);
    let n = params.n;
    let mut plan = WorkPlan::default();
    if lights.0.is_empty() {
        // Nothing lights the cloud: it only absorbs. Zero its colours once; no pass runs.
        if volumes.gather_key != UNLIT {
            volumes.gather_key = UNLIT;
            volumes.scatter_key = 0;
            plan.unlit = true;
        }
        volumes.plan = plan;
        return;
    }

    let density_key = key_of((gpu.generation, n));
    if density_key != volumes.density_key {
        plan.voxelize = true;
        volumes.density_key = density_key;
    }

    // Slot i shades the i-th light, in the cloud's local frame.
    let to_local = cloud.rotation().inverse();
    volumes.lights.truncate(lights.0.len());
    while volumes.lights.len() < lights.0.len() {
        volumes.lights.push(LightVolume {
            params: uniform(
                device,
                "particle_clouds_light_params",
                LightParams::min_size().get(),
            ),
            transmittance: storage(
                device,
                "particle_clouds_transmittance",
                (n as u64).pow(3) * 4,
            ),
            key: 0,
        });
    }
    let light_params: Vec<LightParams> = lights
        .0
        .iter()
        .enumerate()
        .map(|(i, l)| {
            LightParams::new(
                &params,
                (to_local * l.direction).normalize(),
                l.irradiance,
                i > 0,
            )
        })
        .collect();
    let mut gather_inputs = Vec::with_capacity(light_params.len());
    for (i, (light, slot)) in light_params.iter().zip(&mut volumes.lights).enumerate() {
        let key = key_of((density_key, bits(light.w), light.sigma_scale.to_bits()));
        if key != slot.key {
            plan.shade.push(i);
            slot.key = key;
        }
        gather_inputs.push((key, bits(light.irradiance)));
    }

    let gather_key = key_of((&gather_inputs, density_key));
    if gather_key != volumes.gather_key {
        volumes.gather_key = gather_key;
        plan.gather = true;
    }
    let scatter_key = key_of((
        gather_key,
        params.k_local.to_bits(),
        params.albedo.to_bits(),
        params.stencil,
        cloud.settings.scatter_iterations,
    ));
    if scatter_key != volumes.scatter_key {
        volumes.scatter_key = scatter_key;
        plan.scatter = Some(cloud.settings.scatter_iterations);
    }

    if !plan.is_empty() {
        if params != volumes.params {
            queue.write_buffer(&volumes.params_buffer, 0, &uniform_bytes(&params));
            volumes.params = params;
        }
        for (light, slot) in light_params.iter().zip(&volumes.lights) {
            queue.write_buffer(&slot.params, 0, &uniform_bytes(light));
        }
    }
    volumes.plan = plan;
}

/// The uniform of a cloud's illumination passes.
fn cloud_params(cloud: &ExtractedCloud, gpu: &GpuParticles, bounds: CloudBounds) -> CloudParams {
    let n = cloud.settings.volume_resolution;
    CloudParams {
        n,
        particle_count: gpu.count,
        stencil: match cloud.settings.scatter_stencil {
            ScatterStencil::Transmittance => 0,
            ScatterStencil::Paper => 1,
            ScatterStencil::FreePath => 2,
        },
        _padding: 0,
        grid_origin: bounds.centre - bounds.side * 0.5,
        h: bounds.side / n as f32,
        grid_centre: bounds.centre,
        k_local: cloud.extinction * cloud.scale(),
        albedo: cloud.albedo,
        forward_scattering: cloud.settings.forward_scattering,
    }
}
