//! The billboards' bind groups (made in `PrepareBindGroups`): each cloud's particles, sort,
//! volumes, uniforms and beam-phase table, and each view's group 0.

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_asset::RenderAssets,
        render_resource::{
            BindGroup, BindGroupEntries, BindGroupLayout, BindingResource, Buffer,
            BufferInitDescriptor, BufferUsages, PipelineCache,
        },
        renderer::RenderDevice,
        view::{RetainedViewEntity, ViewUniforms},
    },
};

use crate::beam_phase::BeamPhase;

use crate::render::{
    core::gpu::uniform_bytes,
    core::key_of,
    draw::fog::CloudFogUniforms,
    extract::ExtractedCloud,
    extract::particles::GpuParticles,
    plan::pools::{BufferRange, VolumePools},
    plan::volumes::CloudVolumes,
    view::sort::CloudSorts,
    view::view_atlas::ViewVolumeAtlases,
    view::view_volume::CloudViewVolumes,
};
use crate::settings::Compositing;

use crate::render::draw::billboards::*;

/// Per cloud: the draw uniform and one bind group per view (each view has its own sort order or
/// view volume). Rebuilt only when one of their inputs changes.
#[derive(Component)]
pub struct CloudDrawBindGroups {
    key: u64,
    _params: Buffer,
    /// The cloud's [`BeamPhase`] table (one element for a medium without one).
    beam_phase: Buffer,
    /// Group 1 of the billboard pipeline, per view.
    pub groups: HashMap<RetainedViewEntity, BindGroup>,
}

impl CloudDrawBindGroups {
    /// Its buffers (the memory census).
    pub(crate) fn buffers(&self) -> [&Buffer; 2] {
        [&self._params, &self.beam_phase]
    }

    /// The cloud's [`BeamPhase`] table.
    pub fn beam_phase(&self) -> &Buffer {
        &self.beam_phase
    }
}

/// The view bind group of the billboard pipeline.
#[derive(Resource)]
pub struct BillboardViewBindGroup(pub(crate) BindGroup);

/// Per view, the buffers that make a cloud's group 1 differ between views: the sorted order, or
/// the view volume's uniform and the view's atlas (optical depths, volumes, neighbour lists,
/// and for an anisotropic cloud its multiple scattering seen from the camera).
struct PerView<'a> {
    view: RetainedViewEntity,
    buffers: [&'a Buffer; 4],
    seen_multiple: Option<&'a Buffer>,
}

fn per_view_buffers<'a>(
    sorts: Option<&'a CloudSorts>,
    view_volumes: Option<&'a CloudViewVolumes>,
    atlases: &'a ViewVolumeAtlases,
    compositing: Compositing,
) -> Vec<PerView<'a>> {
    match compositing {
        Compositing::Sorted => sorts
            .into_iter()
            .flat_map(|s| &s.0)
            .map(|(view, sort)| PerView {
                view: *view,
                buffers: [sort.buffers.sorted_values(); 4],
                seen_multiple: None,
            })
            .collect(),
        Compositing::ViewTransmittance => view_volumes
            .into_iter()
            .flat_map(|v| &v.0)
            .filter_map(|(view, volume)| {
                let atlas = atlases.0.get(view)?;
                let buffers = [&atlas.optical_depth, &atlas.volumes, &atlas.neighbours];
                Some(PerView {
                    view: *view,
                    buffers: [&volume.params, buffers[0], buffers[1], buffers[2]],
                    seen_multiple: volume.sees_multiple().then_some(&atlas.seen_multiple),
                })
            })
            .collect(),
    }
}

/// Each anisotropy's [`BeamPhase`] table on the GPU, built once while some cloud has that
/// medium (building one sums a Legendre series per entry).
#[derive(Default)]
pub(crate) struct BeamPhaseBuffers(HashMap<u32, Buffer>);

impl BeamPhaseBuffers {
    /// Drops the tables no cloud of `anisotropies` uses.
    fn keep_only(&mut self, anisotropies: impl Iterator<Item = f32>) {
        let used: Vec<u32> = anisotropies.map(f32::to_bits).collect();
        self.0.retain(|g, _| used.contains(g));
    }

    /// The table of anisotropy `g` (one element where the medium has none).
    fn get(&mut self, device: &RenderDevice, g: f32) -> Buffer {
        let buffer = self.0.entry(g.to_bits()).or_insert_with(|| {
            let ratios = BeamPhase::new(g as f64).map_or(vec![1.0], |t| t.ratios);
            device.create_buffer_with_data(&BufferInitDescriptor {
                label: Some("particle_clouds_beam_phase"),
                contents: bytemuck::cast_slice(&ratios),
                usage: BufferUsages::STORAGE,
            })
        });
        buffer.clone()
    }
}

/// What the billboards of one cloud bind: its volumes and its per-view sorts or view volumes.
type BillboardSources = (
    Entity,
    &'static ExtractedCloud,
    &'static CloudVolumes,
    Option<&'static CloudSorts>,
    Option<&'static CloudViewVolumes>,
    Option<&'static CloudDrawBindGroups>,
);

#[allow(clippy::too_many_arguments)]
pub(crate) fn prepare_billboard_bind_groups(
    mut commands: Commands,
    pipeline: Option<Res<BillboardPipeline>>,
    pipeline_cache: Res<PipelineCache>,
    device: Res<RenderDevice>,
    view_uniforms: Res<ViewUniforms>,
    fog_uniforms: Res<CloudFogUniforms>,
    clouds: Query<BillboardSources>,
    particles: Res<RenderAssets<GpuParticles>>,
    pools: Res<VolumePools>,
    atlases: Res<ViewVolumeAtlases>,
    mut beam_phases: Local<BeamPhaseBuffers>,
) {
    let Some(pipeline) = pipeline else { return };
    beam_phases.keep_only(clouds.iter().map(|c| c.1.anisotropy));
    let (Some(view_binding), Some(fog_binding)) =
        (view_uniforms.uniforms.binding(), fog_uniforms.0.binding())
    else {
        return;
    };
    commands.insert_resource(BillboardViewBindGroup(device.create_bind_group(
        "particle_clouds_view_bind_group",
        &pipeline_cache.get_bind_group_layout(&pipeline.view_layout),
        &BindGroupEntries::sequential((view_binding, fog_binding)),
    )));
    for (entity, cloud, volumes, sorts, view_volumes, existing) in &clouds {
        let Some(gpu) = particles.get(cloud.particles) else {
            continue;
        };
        let compositing = cloud.settings.compositing;
        let pool = pools.pool(&volumes.slot);
        let optical_depth = pool.optical_depth(volumes.slot.index);
        let multiple = pool.multiple(volumes.slot.index);
        let lights = pool.lights(volumes.slot.index);
        let layout = pipeline_cache.get_bind_group_layout(pipeline.cloud_layout(compositing));
        let params = draw_params(cloud);
        let per_view = per_view_buffers(sorts, view_volumes, &atlases, compositing);
        // Order-independent over the views (a hash map's order is arbitrary).
        let views = per_view
            .iter()
            .map(|p| {
                let seen = p.seen_multiple.map(|b| b.id());
                key_of((p.view, p.buffers.map(|b| b.id()), seen))
            })
            .fold(0, |a, h| a ^ h);
        // The whole uniform, so that no field of it can be left out of the key.
        let params_bytes = uniform_bytes(&params);
        let key = key_of((
            &params_bytes,
            gpu.buffer.id(),
            volumes.params_buffer.id(),
            [&lights, &optical_depth, &multiple].map(|r| (r.buffer.id(), r.offset)),
            views,
            compositing,
            cloud.anisotropy.to_bits(),
        ));
        if existing.is_some_and(|e| e.key == key) {
            continue;
        }
        let beam_phase = beam_phases.get(&device, cloud.anisotropy);
        let params = device.create_buffer_with_data(&BufferInitDescriptor {
            label: Some("particle_clouds_draw_params"),
            contents: &params_bytes,
            usage: BufferUsages::UNIFORM,
        });
        let shared = SharedBindings {
            params: &params,
            cloud_params: &volumes.params_buffer,
            particles: &gpu.buffer,
            lights: &lights,
            optical_depth: &optical_depth,
            multiple: &multiple,
            beam_phase: &beam_phase,
        };
        let groups = per_view
            .into_iter()
            .map(|p| {
                (
                    p.view,
                    billboard_group(&device, &layout, compositing, &shared, &p),
                )
            })
            .collect();
        commands.entity(entity).insert(CloudDrawBindGroups {
            key,
            _params: params,
            beam_phase,
            groups,
        });
    }
}

/// What a cloud's billboard bind group binds whatever the view.
struct SharedBindings<'a> {
    params: &'a Buffer,
    cloud_params: &'a Buffer,
    particles: &'a Buffer,
    lights: &'a BufferRange,
    optical_depth: &'a BufferRange,
    multiple: &'a BufferRange,
    beam_phase: &'a Buffer,
}

/// A cloud's billboard bind group for one view (group 1 of `billboard.wgsl`): its buffers, the
/// view's sorted order or view volume, and through the view transmittance the view's atlas.
fn billboard_group(
    device: &RenderDevice,
    layout: &BindGroupLayout,
    compositing: Compositing,
    shared: &SharedBindings,
    view: &PerView,
) -> BindGroup {
    let [a, atlas_depth, atlas_volumes, atlas_neighbours] = view.buffers;
    let multiple = match view.seen_multiple {
        Some(seen) => seen.as_entire_binding(),
        None => BindingResource::Buffer(shared.multiple.binding()),
    };
    let (p, c, g, a, l, o) = (
        shared.params.as_entire_binding(),
        shared.cloud_params.as_entire_binding(),
        shared.particles.as_entire_binding(),
        a.as_entire_binding(),
        shared.lights.binding(),
        shared.optical_depth.binding(),
    );
    let b = shared.beam_phase.as_entire_binding();
    let label = "particle_clouds_billboard_bind_group";
    match compositing {
        Compositing::Sorted => device.create_bind_group(
            label,
            layout,
            &BindGroupEntries::sequential((p, c, g, a, l, o, multiple, b)),
        ),
        Compositing::ViewTransmittance => device.create_bind_group(
            label,
            layout,
            &BindGroupEntries::sequential((
                p,
                c,
                g,
                a,
                l,
                o,
                multiple,
                atlas_depth.as_entire_binding(),
                atlas_volumes.as_entire_binding(),
                atlas_neighbours.as_entire_binding(),
                b,
            )),
        ),
    }
}
