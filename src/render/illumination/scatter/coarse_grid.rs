//! The coarse-grid cycles of the multiple scattering (docs/illumination.md §4, "Coarse-grid
//! cycles"), after a batch's full series. First each cloud's media (its density and other
//! clouds') are averaged onto its grid of half the side
//! ([`CoarseGrids`](crate::render::plan::pools::CoarseGrids)). Each cycle sweeps the fine grids for their
//! residual `r = K (S_0 + S) + b - S` (adding it to `S`), averages it onto the coarse grid
//! weighted by what each voxel scatters, sums the series of [`COARSE_GRID_ORDERS`] orders from it
//! there and closes it, adds that correction back trilinearly, and sweeps the fine grids once
//! more. A pool without coarse grids (an odd side) only sweeps. The CPU reference is
//! `reference::illumination::scatter_coarse_cycles` (feature `reference`).

use bevy::render::render_resource::{BindGroup, BindGroupEntries, BindGroupEntry, Buffer};

use crate::render::{
    core::gpu::{StagePass, WorkList},
    core::workgroups::dispatch_linear,
    illumination::pipelines::{ComputeStage, IlluminationPipelines},
    illumination::scatter::series::{OrderPairs, SeriesPasses, SeriesVolumes, scatter_group},
    plan::pools::VolumePool,
};
use crate::settings::COARSE_GRID_ORDERS;

/// A scattering batch's coarse-grid cycles.
pub(crate) struct CycleBatch {
    cycles: u32,
    /// The coarse grids' passes; `None` in a pool without them.
    coarse: Option<CoarseBatch>,
}

/// The bind groups of the coarse series and of the transfers between the grids.
struct CoarseBatch {
    /// The coarse series' order pairs: its start → a, a → b, b → a.
    sweeps: OrderPairs,
    /// Its closure, reading its last two orders.
    closure: BindGroup,
    /// The transfers between the grids (`coarse_grid.wgsl`): the media's restriction, the
    /// residual's, and the correction's prolongation.
    media: BindGroup,
    residual: BindGroup,
    prolongation: BindGroup,
}

impl CycleBatch {
    /// `cycles` cycles for the slots of `work` in `pool`, whose `pair_volumes` (where it has
    /// them) the coarse series sweeps into too.
    pub(crate) fn new(
        bind: &impl Fn(&ComputeStage, &[BindGroupEntry]) -> BindGroup,
        pipelines: &IlluminationPipelines,
        (pool, pair_volumes): (&VolumePool, Option<&Buffer>),
        work: &WorkList,
        cycles: u32,
    ) -> Self {
        let coarse = pool.coarse.as_ref().map(|coarse| {
            let moments = pool.shape().moments;
            let volumes = SeriesVolumes {
                slots: &coarse.slots,
                densities: &coarse.densities,
                source: &coarse.source,
                orders: &coarse.orders,
                multiple: &coarse.multiple,
                order_ratios: &coarse.order_ratios,
                // Behind each slot's density in the same buffer (`Slot::foreign`).
                foreign: &coarse.densities,
                pair_volumes,
            };
            // The sweep binds the pool's ground maps, unread: no light enters a coarse grid.
            let sweeps = volumes.iteration_groups(bind, pipelines, pool, work);
            let closure = volumes.closure(bind, pipelines, COARSE_GRID_ORDERS, work);
            let media = bind(
                &pipelines.restrict_media,
                &BindGroupEntries::with_indices((
                    (0, pool.slots.as_entire_binding()),
                    (1, coarse.slots.as_entire_binding()),
                    (2, pool.densities.as_entire_binding()),
                    (3, pool.foreign.as_entire_binding()),
                    (7, work.binding()),
                    (8, coarse.densities.as_entire_binding()),
                )),
            );
            let residual = bind(
                pipelines.restrict_residual.stage(moments),
                &BindGroupEntries::sequential((
                    pool.slots.as_entire_binding(),
                    coarse.slots.as_entire_binding(),
                    pool.densities.as_entire_binding(),
                    pool.foreign.as_entire_binding(),
                    // Where the residual sweep leaves the residual (order a).
                    pool.orders[0].as_entire_binding(),
                    coarse.source.as_entire_binding(),
                    coarse.multiple.as_entire_binding(),
                    work.binding(),
                )),
            );
            let prolongation = bind(
                pipelines.prolong_correction.stage(moments),
                &BindGroupEntries::with_indices((
                    (0, pool.slots.as_entire_binding()),
                    (1, coarse.slots.as_entire_binding()),
                    (6, coarse.multiple.as_entire_binding()),
                    (7, work.binding()),
                    (9, pool.multiple.as_entire_binding()),
                )),
            );
            CoarseBatch {
                sweeps,
                closure,
                media,
                residual,
                prolongation,
            }
        });
        Self { cycles, coarse }
    }

    /// Records the cycles of the chunk `(work, items)` of the batch whose fine series `series`
    /// records, with its order pairs and restart `groups`.
    pub(crate) fn record(
        &self,
        pass: &mut StagePass,
        series: &SeriesPasses,
        groups: (&OrderPairs, &BindGroup),
        (work, items): (u32, u32),
    ) {
        let ready = series.ready;
        let n = series.n;
        let coarse_series = SeriesPasses {
            n: n / 2,
            ..*series
        };
        if let Some(coarse) = self.coarse.as_ref().filter(|_| self.cycles > 0) {
            pass.set_pipeline(ready.restrict_media);
            pass.set_bind_group(0, &coarse.media, &[work]);
            dispatch_linear(pass, (n / 2).pow(3), items);
        }
        for _ in 0..self.cycles {
            // S += r, r left in order a.
            series.restart_sweep(pass, groups, work, items);
            if let Some(coarse) = &self.coarse {
                pass.set_pipeline(ready.restrict_residual[series.variant]);
                pass.set_bind_group(0, &coarse.residual, &[work]);
                dispatch_linear(pass, (n / 2).pow(3), items);
                coarse_series.set_stencil(pass);
                for k in 0..COARSE_GRID_ORDERS {
                    let group = coarse.sweeps.pair(scatter_group(k));
                    coarse_series.iterate(pass, group, (work, items), false);
                    if k + 3 == COARSE_GRID_ORDERS {
                        coarse_series.order_sizes(pass, &coarse.closure, work, items);
                    }
                }
                coarse_series.close(pass, &coarse.closure, work, items);
                pass.set_pipeline(ready.prolong_correction[series.variant]);
                pass.set_bind_group(0, &coarse.prolongation, &[work]);
                dispatch_linear(pass, n.pow(3), items);
            }
            // The smoothing sweep: S <- K (S_0 + S) + b.
            series.restart_sweep(pass, groups, work, items);
        }
    }
}
