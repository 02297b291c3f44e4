//! The illumination passes (the paper's Algorithm 1, lines 2–6), recorded once per frame in the
//! `RenderGraph` schedule before any camera: voxelize, shade per light, gather and multiple
//! scattering. Only the stages planned by `prepare_cloud_volumes` run.

use bevy::{
    prelude::*,
    render::{
        render_asset::RenderAssets,
        render_resource::{
            BindGroup, BindGroupEntries, BindGroupEntry, Buffer, BufferBinding, ComputePass,
            PipelineCache, ShaderType,
        },
        renderer::RenderContext,
    },
};

use super::{
    extract::ExtractedCloud,
    gpu::record_stage,
    particles::GpuParticles,
    pipelines::{
        ComputeStage, IlluminationPipelines, ReadyPipelines, SWEEP_DIRECTION_STRIDE,
        SweepDirection, sweep_directions, sweep_lines,
    },
    plan::CloudIllumination,
    volumes::CloudVolumes,
    workgroups::{self, dispatch_columns, dispatch_linear, dispatch_volume},
};
use crate::{
    settings::{ScatterStencil, ShadingMethod},
    stats::{CloudPass, CloudPassCounters},
};

/// Records every planned illumination stage of every cloud.
pub(crate) fn illuminate_clouds(
    mut ctx: RenderContext,
    mut clouds: Query<(&ExtractedCloud, &CloudVolumes, &mut CloudIllumination)>,
    particles: Res<RenderAssets<GpuParticles>>,
    pipelines: Option<Res<IlluminationPipelines>>,
    pipeline_cache: Res<PipelineCache>,
    counters: Res<CloudPassCounters>,
    shading: Option<Res<ShadingMethod>>,
) {
    let Some(pipelines) = pipelines else { return };
    if clouds.iter().all(|(_, _, s)| s.plan.is_empty()) {
        return;
    }
    let brute_force = shading.is_some_and(|s| *s == ShadingMethod::BruteForce);
    let shade_stage = if brute_force {
        &pipelines.shade_brute_force
    } else {
        &pipelines.shade
    };
    let (Some(ready), Some(shade)) = (
        pipelines.ready(&pipeline_cache),
        shade_stage.get(&pipeline_cache),
    ) else {
        // Not compiled yet: forget the plan so that the next frame does all of it.
        clouds.iter_mut().for_each(|(_, _, mut s)| s.invalidate());
        return;
    };
    let device = ctx.render_device().clone();
    let recorder = ctx.diagnostic_recorder();
    let bind = |stage: &ComputeStage, entries: &[BindGroupEntry]| -> BindGroup {
        device.create_bind_group(
            None,
            &pipeline_cache.get_bind_group_layout(&stage.layout),
            entries,
        )
    };
    let clouds: Vec<_> = clouds
        .iter_mut()
        .filter(|(_, _, s)| !s.plan.is_empty())
        .filter_map(|(cloud, v, s)| Some((particles.get(cloud.particles)?, v, s)))
        .collect();

    // Voxelize (docs/illumination.md §1): clear, then every particle deposits its mass into the
    // fine grid, one row of its support per invocation: the kernel's sums, then the deposit.
    let voxelizing: Vec<_> = clouds.iter().filter(|(_, _, s)| s.plan.voxelize).collect();
    if !voxelizing.is_empty() {
        for (_, v, _) in &voxelizing {
            ctx.command_encoder().clear_buffer(&v.fine_density, 0, None);
            ctx.command_encoder().clear_buffer(&v.kernel_sums, 0, None);
        }
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Voxelize,
            |pass| {
                let groups: Vec<_> = voxelizing
                    .iter()
                    .map(|(gpu, v, _)| {
                        let group = bind(
                            &pipelines.voxelize,
                            &BindGroupEntries::sequential((
                                v.fine_params_buffer.as_entire_binding(),
                                gpu.buffer.as_entire_binding(),
                                v.fine_density.as_entire_binding(),
                                v.kernel_sums.as_entire_binding(),
                            )),
                        );
                        let rows = v.fine_params.rows;
                        (
                            group,
                            [gpu.count.div_ceil(workgroups::LINEAR).max(1), rows, rows],
                        )
                    })
                    .collect();
                for pipeline in [ready.kernel_sums, ready.voxelize] {
                    pass.set_pipeline(pipeline);
                    for (group, [x, y, z]) in &groups {
                        pass.set_bind_group(0, group, &[]);
                        pass.dispatch_workgroups(*x, *y, *z);
                    }
                }
                voxelizing.len() as u32
            },
        );
    }

    // Shade (§2): one column per invocation, marching slice by slice away from the light (or, with
    // `ShadingMethod::BruteForce`, one voxel per invocation marching all the way to the light).
    if clouds.iter().any(|(_, _, s)| !s.plan.shade.is_empty()) {
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Shade,
            |pass| {
                pass.set_pipeline(shade);
                let mut runs = 0;
                for (_, v, s) in &clouds {
                    let m = v.params.light_n;
                    for &i in &s.plan.shade {
                        let group = bind(
                            shade_stage,
                            &BindGroupEntries::sequential((
                                v.fine_params_buffer.as_entire_binding(),
                                v.lights[i].params.as_entire_binding(),
                                v.fine_density.as_entire_binding(),
                                v.optical_depth.as_entire_binding(),
                            )),
                        );
                        pass.set_bind_group(0, &group, &[]);
                        if brute_force {
                            dispatch_volume(pass, m);
                        } else {
                            dispatch_columns(pass, m);
                        }
                        runs += 1;
                    }
                }
                runs
            },
        );
    }

    // Gather (§1, §3): the scattering grid's density, and every light's single scattering into
    // its source S_0.
    if clouds.iter().any(|(_, _, s)| s.plan.gather) {
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Gather,
            |pass| {
                pass.set_pipeline(ready.gather);
                let mut runs = 0;
                for (_, v, _) in clouds.iter().filter(|(_, _, s)| s.plan.gather) {
                    let group = bind(
                        &pipelines.gather,
                        &BindGroupEntries::sequential((
                            v.params_buffer.as_entire_binding(),
                            v.light_array.as_entire_binding(),
                            v.optical_depth.as_entire_binding(),
                            v.fine_density.as_entire_binding(),
                            v.density.as_entire_binding(),
                            v.source.as_entire_binding(),
                        )),
                    );
                    pass.set_bind_group(0, &group, &[]);
                    dispatch_volume(pass, v.params.n);
                    runs += 1;
                }
                runs
            },
        );
    }

    // Multiple scattering (§4): the iterations, then the series' closure.
    let scattering: Vec<_> = clouds
        .iter()
        .filter(|(_, _, s)| s.plan.scatter.is_some())
        .collect();
    for (_, v, _) in clouds
        .iter()
        .filter(|(_, _, s)| s.plan.scatter.is_some() || s.plan.unlit)
    {
        ctx.command_encoder().clear_buffer(&v.multiple, 0, None);
    }
    if !scattering.is_empty() {
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Scatter,
            |pass| {
                let mut runs = 0;
                for (_, v, s) in &scattering {
                    let iterations = s.plan.scatter.unwrap_or(0);
                    let sweep = s.plan.stencil == ScatterStencil::DiscreteOrdinates;
                    scatter_cloud(pass, &pipelines, &ready, &bind, v, iterations, sweep);
                    runs += iterations;
                }
                runs
            },
        );
    }
    drop(scattering);

    for (_, _, mut s) in clouds {
        s.ready |= s.plan.scatter.is_some() || s.plan.unlit;
        s.plan = default();
    }
}

/// `S_0` for `k = 0`, else the order written by iteration `k - 1` (the two order volumes alternate).
fn order(v: &CloudVolumes, k: u32) -> &Buffer {
    if k == 0 {
        &v.source
    } else {
        &v.orders[(k as usize - 1) % 2]
    }
}

/// Records one cloud's scattering iterations (the discrete-ordinates `sweep`, else the paper's
/// stencil) and the closure (§4).
fn scatter_cloud(
    pass: &mut ComputePass,
    pipelines: &IlluminationPipelines,
    ready: &ReadyPipelines,
    bind: &impl Fn(&ComputeStage, &[BindGroupEntry]) -> BindGroup,
    v: &CloudVolumes,
    iterations: u32,
    sweep: bool,
) {
    let n = v.params.n;
    pass.set_pipeline(if sweep {
        ready.sweep
    } else {
        ready.scatter_paper
    });
    for k in 0..iterations {
        let group = bind(
            &pipelines.sweep,
            &BindGroupEntries::sequential((
                v.params_buffer.as_entire_binding(),
                BufferBinding {
                    buffer: &pipelines.sweep_directions,
                    offset: 0,
                    size: Some(SweepDirection::min_size()),
                },
                v.density.as_entire_binding(),
                order(v, k).as_entire_binding(),
                order(v, k + 1).as_entire_binding(),
                v.multiple.as_entire_binding(),
            )),
        );
        if sweep {
            // One dispatch per direction pair: the lines of one direction partition the grid.
            for (i, o) in sweep_directions().enumerate() {
                pass.set_bind_group(0, &group, &[i as u32 * SWEEP_DIRECTION_STRIDE]);
                dispatch_linear(pass, sweep_lines(o, n));
            }
        } else {
            pass.set_bind_group(0, &group, &[0]);
            dispatch_volume(pass, n);
        }
    }
    if iterations == 0 {
        return;
    }
    let group = bind(
        &pipelines.order_ratio,
        &BindGroupEntries::sequential((
            v.params_buffer.as_entire_binding(),
            v.density.as_entire_binding(),
            order(v, iterations).as_entire_binding(),
            order(v, iterations - 1).as_entire_binding(),
            v.multiple.as_entire_binding(),
            v.order_ratio.as_entire_binding(),
        )),
    );
    pass.set_bind_group(0, &group, &[]);
    pass.set_pipeline(ready.order_ratio);
    pass.dispatch_workgroups(1, 1, 1);
    pass.set_pipeline(ready.extrapolate);
    dispatch_linear(pass, n.pow(3));
}
