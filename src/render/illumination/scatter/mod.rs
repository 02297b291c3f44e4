//! Multiple scattering (the paper's Algorithm 1, line 6; docs/illumination.md §4): the sweep
//! (`sweep.wgsl`), its closure (`closure.wgsl`), the coarse scattering grid (`coarse_grid`) and
//! the media of overlapping clouds (`overlap.wgsl`).

pub mod coarse_grid;
pub mod overlap;
pub mod series;
pub mod sweep;

use bevy::render::render_resource::{BindGroup, BindGroupEntry, Buffer};

use crate::render::{
    core::gpu::{StagePass, WorkList},
    illumination::pipelines::{ComputeStage, IlluminationPipelines, ReadyPipelines},
    illumination::scatter::coarse_grid::CycleBatch,
    illumination::scatter::series::{OrderPairs, SeriesPasses, SeriesVolumes, scatter_group},
    plan::pools::VolumePool,
};
use crate::settings::SweepDirections;

/// The scattering of a pool's clouds that share an iteration count, a stencil (with its sweep
/// directions) and whether they restart warm.
pub(crate) struct ScatterBatch {
    pub(crate) iterations: u32,
    /// The discrete-ordinates sweep's directions, or `None` for the paper's stencil.
    pub(crate) sweep: Option<SweepDirections>,
    /// A warm restart from the solution `multiple` holds (docs/illumination.md §4).
    pub(crate) warm: bool,
    /// The iterations' three order pairs: `S_0 → a`, `a → b`, `b → a`.
    pub(crate) orders: OrderPairs,
    /// `S_0 → b`, a warm restart's start.
    pub(crate) restart: BindGroup,
    /// The closure, reading the last two orders.
    pub(crate) closure: BindGroup,
    pub(crate) work: WorkList,
    /// The coarse-grid cycles after the series, if any.
    pub(crate) cycles: Option<CycleBatch>,
}

/// The bind groups of `iterations` of scattering for the slots of `work`, in `pool` (the
/// discrete-ordinates stencil along the 26 directions, full series: set `sweep` and `warm` for
/// the others).
pub(crate) fn scatter_batch(
    bind: &impl Fn(&ComputeStage, &[BindGroupEntry]) -> BindGroup,
    pipelines: &IlluminationPipelines,
    (pool, pair_volumes): (&VolumePool, Option<&Buffer>),
    iterations: u32,
    work: WorkList,
) -> ScatterBatch {
    let volumes = SeriesVolumes {
        pair_volumes,
        ..SeriesVolumes::of_pool(pool)
    };
    let orders = volumes.iteration_groups(bind, pipelines, pool, &work);
    let restart = (&pool.source, &pool.orders[1]);
    let restart = volumes.order_pair(bind, pipelines, pool, restart, &work);
    let closure = volumes.closure(bind, pipelines, iterations, &work);
    ScatterBatch {
        iterations,
        sweep: Some(SweepDirections::Lattice26),
        warm: false,
        orders,
        restart,
        closure,
        work,
        cycles: None,
    }
}

/// Records a batch's scattering iterations (the discrete-ordinates `sweep`, else the paper's
/// stencil) on its clouds' `n³` grids, the closure (§4), then its coarse-grid cycles. A warm
/// restart's first iteration scatters `S_0` plus the solution held, and turns it into the
/// correction's first order.
pub(crate) fn scatter_batch_passes(
    pass: &mut StagePass,
    ready: &ReadyPipelines,
    batch: &ScatterBatch,
    n: u32,
    moments: bool,
) {
    let variant = moments as usize;
    let series = SeriesPasses {
        ready,
        sweep: batch.sweep,
        n,
        variant,
    };
    for (work, items) in batch.work.chunks() {
        let first = if batch.warm {
            series.restart_sweep(pass, (&batch.orders, &batch.restart), work, items);
            1
        } else {
            0
        };
        series.set_stencil(pass);
        for k in first..batch.iterations {
            let pair = batch.orders.pair(scatter_group(k));
            series.iterate(pass, pair, (work, items), k == 0);
            // Orders M - 2 and M - 3 lie where the closure reads M and M - 1 (the two order
            // volumes alternate): their sizes, for a two-mode closure of the full series.
            if !batch.warm && batch.iterations >= 4 && k + 3 == batch.iterations {
                series.order_sizes(pass, &batch.closure, work, items);
            }
        }
    }
    for (work, items) in batch.work.chunks() {
        series.close(pass, &batch.closure, work, items);
    }
    if let Some(cycles) = &batch.cycles {
        for (work, items) in batch.work.chunks() {
            cycles.record(
                pass,
                &series,
                (&batch.orders, &batch.restart),
                (work, items),
            );
        }
    }
}
