//! The illumination passes (the paper's Algorithm 1, lines 2–6): voxelize, shade per light,
//! gather and multiple scattering. Only the stages planned for this frame run
//! ([`plan`](super::plan)). Their bind groups are made in `PrepareBindGroups`; the system in the
//! `RenderGraph` schedule, once per frame before any camera, only records.

use bevy::{
    prelude::*,
    render::{
        render_asset::RenderAssets,
        render_resource::{
            BindGroup, BindGroupEntries, BindGroupEntry, Buffer, BufferBinding, ComputePass,
            PipelineCache, ShaderType,
        },
        renderer::{RenderContext, RenderDevice},
    },
};

use super::{
    extract::ExtractedCloud,
    gpu::{DYNAMIC_UNIFORM_STRIDE, record_stage},
    particles::GpuParticles,
    pipelines::{
        ComputeStage, IlluminationPipelines, ReadyPipelines, SweepDirection, sweep_directions,
        sweep_lines,
    },
    plan::CloudIllumination,
    volumes::{CloudVolumes, DensityLevels},
    workgroups::{self, dispatch_columns, dispatch_linear, dispatch_volume},
};
use crate::{
    settings::{ScatterStencil, ShadingMethod},
    stats::{CloudPass, CloudPassCounters},
};

/// The bind groups of one cloud's planned stages this frame (render world component).
#[derive(Component, Default)]
pub struct IlluminationBindGroups {
    /// Voxelize (all three of its entry points).
    voxelize: Option<BindGroup>,
    /// Shade, per planned light slot.
    shade: Vec<(usize, BindGroup)>,
    /// Gather.
    gather: Option<BindGroup>,
    /// The scattering iterations' three order pairs: `S_0 → a`, `a → b`, `b → a`.
    scatter: Option<[BindGroup; 3]>,
    /// The closure, reading the last two orders.
    closure: Option<BindGroup>,
}

/// `S_0` for `k = 0`, else the order written by iteration `k - 1` (the two order volumes alternate).
fn order(v: &CloudVolumes, k: u32) -> &Buffer {
    if k == 0 {
        &v.source
    } else {
        &v.orders[(k as usize - 1) % 2]
    }
}

/// Which of [`IlluminationBindGroups::scatter`] iteration `k` reads and writes with.
fn scatter_group(k: u32) -> usize {
    match k {
        0 => 0,
        k if k % 2 == 1 => 1,
        _ => 2,
    }
}

/// Makes the bind groups of every cloud's planned stages.
pub(crate) fn prepare_illumination_bind_groups(
    mut commands: Commands,
    clouds: Query<(Entity, &ExtractedCloud, &CloudVolumes, &CloudIllumination)>,
    particles: Res<RenderAssets<GpuParticles>>,
    pipelines: Option<Res<IlluminationPipelines>>,
    pipeline_cache: Res<PipelineCache>,
    device: Res<RenderDevice>,
) {
    let Some(pipelines) = pipelines else { return };
    let bind = |stage: &ComputeStage, entries: &[BindGroupEntry]| -> BindGroup {
        let layout = pipeline_cache.get_bind_group_layout(&stage.layout);
        device.create_bind_group(None, &layout, entries)
    };
    for (entity, cloud, v, state) in &clouds {
        let plan = &state.plan;
        let Some(gpu) = particles.get(cloud.particles).filter(|_| !plan.is_empty()) else {
            continue;
        };
        let voxelize = plan.voxelize.then(|| {
            bind(
                &pipelines.voxelize,
                &BindGroupEntries::sequential((
                    v.fine_params_buffer.as_entire_binding(),
                    gpu.buffer.as_entire_binding(),
                    v.fine_density.as_entire_binding(),
                    v.kernel_sums.as_entire_binding(),
                    BufferBinding {
                        buffer: &v.density_levels,
                        offset: 0,
                        size: Some(DensityLevels::min_size()),
                    },
                )),
            )
        });
        let shade = plan
            .shade
            .iter()
            .map(|&i| {
                let entries = BindGroupEntries::sequential((
                    v.fine_params_buffer.as_entire_binding(),
                    v.lights[i].params.as_entire_binding(),
                    v.fine_density.as_entire_binding(),
                    v.optical_depth.as_entire_binding(),
                ));
                (i, bind(&pipelines.shade, &entries))
            })
            .collect();
        let gather = plan.gather.then(|| {
            bind(
                &pipelines.gather,
                &BindGroupEntries::sequential((
                    v.params_buffer.as_entire_binding(),
                    v.light_array.as_entire_binding(),
                    v.optical_depth.as_entire_binding(),
                    v.fine_density.as_entire_binding(),
                    v.density.as_entire_binding(),
                    v.source.as_entire_binding(),
                )),
            )
        });
        let iterations = plan.scatter.unwrap_or(0);
        let sweep = |k: u32| {
            bind(
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
            )
        };
        let scatter = (iterations > 0).then(|| [sweep(0), sweep(1), sweep(2)]);
        let closure = (iterations > 0).then(|| {
            bind(
                &pipelines.order_ratio,
                &BindGroupEntries::sequential((
                    v.params_buffer.as_entire_binding(),
                    v.density.as_entire_binding(),
                    order(v, iterations).as_entire_binding(),
                    order(v, iterations - 1).as_entire_binding(),
                    v.multiple.as_entire_binding(),
                    v.order_ratio.as_entire_binding(),
                )),
            )
        });
        commands.entity(entity).insert(IlluminationBindGroups {
            voxelize,
            shade,
            gather,
            scatter,
            closure,
        });
    }
}

/// Records every planned illumination stage of every cloud.
pub(crate) fn illuminate_clouds(
    mut ctx: RenderContext,
    mut clouds: Query<(
        &ExtractedCloud,
        &CloudVolumes,
        &mut CloudIllumination,
        Option<&IlluminationBindGroups>,
    )>,
    particles: Res<RenderAssets<GpuParticles>>,
    pipelines: Option<Res<IlluminationPipelines>>,
    pipeline_cache: Res<PipelineCache>,
    counters: Res<CloudPassCounters>,
    shading: Option<Res<ShadingMethod>>,
) {
    let Some(pipelines) = pipelines else { return };
    if clouds.iter().all(|(_, _, s, _)| s.plan.is_empty()) {
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
        clouds
            .iter_mut()
            .for_each(|(_, _, mut s, _)| s.invalidate());
        return;
    };
    let recorder = ctx.diagnostic_recorder();
    let clouds: Vec<_> = clouds
        .iter_mut()
        .filter(|(_, _, s, _)| !s.plan.is_empty())
        .filter_map(|(cloud, v, s, groups)| Some((particles.get(cloud.particles)?, v, s, groups?)))
        .collect();

    // Voxelize (docs/illumination.md §1): clear, then every particle deposits its mass on its
    // density level, one row of its support per invocation: the kernel's sums, then the deposit.
    // Then the coarse levels are enlarged into the fine grid, coarsest first.
    let voxelizing: Vec<_> = clouds
        .iter()
        .filter_map(|(gpu, v, _, g)| Some((gpu, v, g.voxelize.as_ref()?)))
        .collect();
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
                for pipeline in [ready.kernel_sums, ready.voxelize] {
                    pass.set_pipeline(pipeline);
                    for (gpu, v, group) in &voxelizing {
                        let rows = v.fine_params.rows;
                        pass.set_bind_group(0, *group, &[0]);
                        pass.dispatch_workgroups(
                            gpu.count.div_ceil(workgroups::LINEAR).max(1),
                            rows,
                            rows,
                        );
                    }
                }
                pass.set_pipeline(ready.upsample);
                for (_, v, group) in &voxelizing {
                    for coarse in (1..v.levels_in_use).rev() {
                        pass.set_bind_group(0, *group, &[coarse as u32 * DYNAMIC_UNIFORM_STRIDE]);
                        dispatch_volume(pass, v.level_sizes[coarse - 1]);
                    }
                }
                voxelizing.len() as u32
            },
        );
    }

    // Shade (§2): one column per invocation, marching slice by slice away from the light (or, with
    // `ShadingMethod::BruteForce`, one voxel per invocation marching all the way to the light).
    if clouds.iter().any(|(_, _, _, g)| !g.shade.is_empty()) {
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Shade,
            |pass| {
                pass.set_pipeline(shade);
                let mut runs = 0;
                for (_, v, _, g) in &clouds {
                    for (_, group) in &g.shade {
                        pass.set_bind_group(0, group, &[]);
                        if brute_force {
                            dispatch_volume(pass, v.params.light_n);
                        } else {
                            dispatch_columns(pass, v.params.light_n);
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
    if clouds.iter().any(|(_, _, _, g)| g.gather.is_some()) {
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Gather,
            |pass| {
                pass.set_pipeline(ready.gather);
                let mut runs = 0;
                for (_, v, _, g) in &clouds {
                    if let Some(group) = &g.gather {
                        pass.set_bind_group(0, group, &[]);
                        dispatch_volume(pass, v.params.n);
                        runs += 1;
                    }
                }
                runs
            },
        );
    }

    // Multiple scattering (§4): the iterations, then the series' closure.
    for (_, v, s, _) in &clouds {
        if s.plan.scatter.is_some() || s.plan.unlit {
            ctx.command_encoder().clear_buffer(&v.multiple, 0, None);
        }
    }
    if clouds.iter().any(|(_, _, s, _)| s.plan.scatter.is_some()) {
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Scatter,
            |pass| {
                let mut runs = 0;
                for (_, v, s, g) in &clouds {
                    let Some(iterations) = s.plan.scatter else {
                        continue;
                    };
                    let sweep = s.plan.stencil == ScatterStencil::DiscreteOrdinates;
                    scatter_cloud(pass, &ready, g, v.params.n, iterations, sweep);
                    runs += iterations;
                }
                runs
            },
        );
    }

    for (_, _, mut s, _) in clouds {
        s.ready |= s.plan.scatter.is_some() || s.plan.unlit;
        s.plan = default();
    }
}

/// Records one cloud's scattering iterations (the discrete-ordinates `sweep`, else the paper's
/// stencil) on its `n³` grid, and the closure (§4).
fn scatter_cloud(
    pass: &mut ComputePass,
    ready: &ReadyPipelines,
    groups: &IlluminationBindGroups,
    n: u32,
    iterations: u32,
    sweep: bool,
) {
    let (Some(scatter), Some(closure)) = (&groups.scatter, &groups.closure) else {
        return;
    };
    pass.set_pipeline(if sweep {
        ready.sweep
    } else {
        ready.scatter_paper
    });
    for k in 0..iterations {
        let group = &scatter[scatter_group(k)];
        if sweep {
            // One dispatch per direction pair: the lines of one direction partition the grid.
            for (i, o) in sweep_directions().enumerate() {
                pass.set_bind_group(0, group, &[i as u32 * DYNAMIC_UNIFORM_STRIDE]);
                dispatch_linear(pass, sweep_lines(o, n));
            }
        } else {
            pass.set_bind_group(0, group, &[0]);
            dispatch_volume(pass, n);
        }
    }
    pass.set_bind_group(0, closure, &[]);
    pass.set_pipeline(ready.order_ratio);
    pass.dispatch_workgroups(1, 1, 1);
    pass.set_pipeline(ready.extrapolate);
    dispatch_linear(pass, n.pow(3));
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The three bind groups cover every iteration's (read, write) pair of order volumes.
    #[test]
    fn scatter_groups_alternate_like_the_orders() {
        // (read, write) of iteration k, as indices: 0 = S_0, 1 = a, 2 = b.
        let order = |k: u32| if k == 0 { 0 } else { 1 + (k - 1) % 2 };
        let pairs = [(0, 1), (1, 2), (2, 1)];
        for k in 0..10 {
            assert_eq!(
                pairs[scatter_group(k)],
                (order(k), order(k + 1)),
                "iteration {k}"
            );
        }
    }
}
