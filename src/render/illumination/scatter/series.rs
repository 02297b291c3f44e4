//! The scattering series (docs/illumination.md §4): the orders `S_0 → a → b → a …` a batch of
//! clouds sweeps, with the volumes each order reads and writes and the passes that record them.
//! The full grids' series and the coarse grids' ([`coarse_grid`](super::coarse_grid)) share it.

use std::num::NonZeroU64;

use bevy::{
    prelude::*,
    render::render_resource::{
        BindGroup, BindGroupEntries, BindGroupEntry, Buffer, BufferBinding, ComputePipeline,
    },
};

use crate::render::{
    core::gpu::{StagePass, WorkList},
    core::workgroups::{dispatch_linear, dispatch_rows},
    illumination::pipelines::{
        ComputeStage, IlluminationPipelines, ReadyPipelines, SWEEP_DIRECTIONS_BINDING,
        sweep_direction_offset, sweep_lines,
    },
    plan::pools::VolumePool,
};
use crate::settings::SweepDirections;

/// The volumes a scattering series reads and writes: a pool's own, or its coarse grids'
/// ([`CoarseGrids`](crate::render::plan::pools::CoarseGrids)), laid out alike.
pub(crate) struct SeriesVolumes<'a> {
    pub(crate) slots: &'a Buffer,
    pub(crate) densities: &'a Buffer,
    /// `S_0`, the series' start.
    pub(crate) source: &'a Buffer,
    /// The two order volumes, alternating.
    pub(crate) orders: &'a [Buffer; 2],
    pub(crate) multiple: &'a Buffer,
    pub(crate) order_ratios: &'a Buffer,
    /// Other clouds' media, where each slot's `foreign` points.
    pub(crate) foreign: &'a Buffer,
    /// Each direction pair's share of an order, for one dispatch per order
    /// ([`SweepDispatch::PerOrder`]), where it is asked for and fits.
    pub(crate) pair_volumes: Option<&'a Buffer>,
}

/// The bind groups of one dispatch per order for an order pair: the sweep, writing every pair's
/// share into the pair volumes, and their sum, reading those into the next order.
pub(crate) struct PerOrderGroups {
    sweep: BindGroup,
    sum: BindGroup,
}

/// A series' three order pairs (`S_0 → a`, `a → b`, `b → a`) as the sweep binds them.
pub(crate) struct OrderPairs {
    /// For one dispatch per direction pair (and the other stencils and passes on an order pair).
    per_pair: [BindGroup; 3],
    /// For one dispatch per order, where the pool has pair volumes.
    per_order: Option<[PerOrderGroups; 3]>,
}

impl OrderPairs {
    /// Order pair `i` ([`scatter_group`]).
    pub(crate) fn pair(&self, i: usize) -> OrderPair<'_> {
        OrderPair {
            per_pair: &self.per_pair[i],
            per_order: self.per_order.as_ref().map(|g| &g[i]),
        }
    }
}

/// One order pair's bind groups ([`OrderPairs::pair`]).
#[derive(Clone, Copy)]
pub(crate) struct OrderPair<'a> {
    per_pair: &'a BindGroup,
    per_order: Option<&'a PerOrderGroups>,
}

impl<'a> SeriesVolumes<'a> {
    pub(crate) fn of_pool(pool: &'a VolumePool) -> Self {
        Self {
            slots: &pool.slots,
            densities: &pool.densities,
            source: &pool.source,
            orders: &pool.orders,
            multiple: &pool.multiple,
            order_ratios: &pool.order_ratios,
            foreign: &pool.foreign,
            pair_volumes: None,
        }
    }

    /// `S_0` for `k = 0`, else the order written by iteration `k - 1`.
    pub(crate) fn order(&self, k: u32) -> &'a Buffer {
        if k == 0 {
            self.source
        } else {
            &self.orders[(k as usize - 1) % 2]
        }
    }

    /// The sweep's bind group reading `from` and writing `to`, for the slots of `work` in
    /// `pool` (whose ground maps the sweep reads).
    pub(crate) fn order_pair(
        &self,
        bind: &impl Fn(&ComputeStage, &[BindGroupEntry]) -> BindGroup,
        pipelines: &IlluminationPipelines,
        pool: &VolumePool,
        (from, to): (&Buffer, &Buffer),
        work: &WorkList,
    ) -> BindGroup {
        bind(
            pipelines.sweep[0].stage(pool.shape().moments),
            &BindGroupEntries::sequential((
                self.slots.as_entire_binding(),
                BufferBinding {
                    buffer: &pipelines.sweep_directions,
                    offset: 0,
                    size: NonZeroU64::new(SWEEP_DIRECTIONS_BINDING),
                },
                self.densities.as_entire_binding(),
                from.as_entire_binding(),
                to.as_entire_binding(),
                self.multiple.as_entire_binding(),
                work.binding(),
                self.foreign.as_entire_binding(),
                pool.ground.as_entire_binding(),
            )),
        )
    }

    /// The order pairs of [`scatter_group`]'s iterations (`S_0 → a`, `a → b`, `b → a`), and
    /// where the pair volumes exist, their groups for one dispatch per order: the sweep writes
    /// the pair volumes (bound as its `s_out`), the sum reads them (as its `s_in`).
    pub(crate) fn iteration_groups(
        &self,
        bind: &impl Fn(&ComputeStage, &[BindGroupEntry]) -> BindGroup,
        pipelines: &IlluminationPipelines,
        pool: &VolumePool,
        work: &WorkList,
    ) -> OrderPairs {
        let pairs = [0, 1, 2].map(|k| (self.order(k), self.order(k + 1)));
        let group = |pair| self.order_pair(bind, pipelines, pool, pair, work);
        OrderPairs {
            per_pair: pairs.map(group),
            per_order: self.pair_volumes.map(|volumes| {
                pairs.map(|(from, to)| PerOrderGroups {
                    sweep: group((from, volumes)),
                    sum: group((volumes, to)),
                })
            }),
        }
    }

    /// The closure's bind group after `iterations` orders (it reads the last two).
    pub(crate) fn closure(
        &self,
        bind: &impl Fn(&ComputeStage, &[BindGroupEntry]) -> BindGroup,
        pipelines: &IlluminationPipelines,
        iterations: u32,
        work: &WorkList,
    ) -> BindGroup {
        bind(
            &pipelines.order_ratio,
            &BindGroupEntries::sequential((
                self.slots.as_entire_binding(),
                self.densities.as_entire_binding(),
                self.order(iterations).as_entire_binding(),
                self.order(iterations - 1).as_entire_binding(),
                self.multiple.as_entire_binding(),
                self.order_ratios.as_entire_binding(),
                work.binding(),
            )),
        )
    }
}

/// Which of a series' iteration groups ([`ScatterBatch::groups`]) iteration `k` reads and writes
/// with.
pub(crate) fn scatter_group(k: u32) -> usize {
    match k {
        0 => 0,
        k if k % 2 == 1 => 1,
        _ => 2,
    }
}

/// Records the passes of a scattering series on a pool's `n³` grids (or on its coarse grids).
pub(crate) struct SeriesPasses<'a> {
    pub(crate) ready: &'a ReadyPipelines<'a>,
    /// The discrete-ordinates sweep's directions, else (`None`) the paper's stencil.
    pub(crate) sweep: Option<SweepDirections>,
    /// Voxels per side of the grids.
    pub(crate) n: u32,
    /// 1 for the pipelines with angular moments, else 0.
    pub(crate) variant: usize,
}

impl SeriesPasses<'_> {
    pub(crate) fn stencil(&self) -> &ComputePipeline {
        if self.sweep.is_some() {
            self.ready.sweep[self.variant]
        } else {
            self.ready.scatter_paper
        }
    }

    pub(crate) fn set_stencil(&self, pass: &mut StagePass) {
        pass.set_pipeline(self.stencil());
    }

    /// One iteration with the stencil set: with `accumulate`, its order goes into `multiple`;
    /// with `boundary`, the light entering the grid comes in.
    pub(crate) fn pass_once(
        &self,
        pass: &mut StagePass,
        group: OrderPair,
        (work, items): (u32, u32),
        accumulate: bool,
        boundary: bool,
    ) {
        let n = self.n;
        let Some(directions) = self.sweep else {
            // The paper's stencil reads only the pair's `accumulate`.
            let direction =
                sweep_direction_offset(SweepDirections::Lattice26, 0, accumulate, boundary);
            pass.set_bind_group(0, group.per_pair, &[direction, work]);
            dispatch_linear(pass, n.pow(3), items);
            return;
        };
        if let (Some(groups), Some(per_order)) = (group.per_order, self.ready.per_order) {
            // Every pair at once, each into its own volume; then their sum (and into `multiple`).
            let direction = sweep_direction_offset(directions, 0, accumulate, boundary);
            let lines = directions
                .pairs()
                .iter()
                .map(|d| sweep_lines(IVec3::from_array(d.o), n));
            let pairs = directions.pairs().len() as u32;
            pass.set_pipeline(per_order.sweep[self.variant]);
            pass.set_bind_group(0, &groups.sweep, &[direction, work]);
            dispatch_rows(pass, lines.max().unwrap_or(0), pairs, items);
            pass.set_pipeline(per_order.sum_pairs[self.variant]);
            pass.set_bind_group(0, &groups.sum, &[direction, work]);
            dispatch_linear(pass, n.pow(3), items);
            pass.set_pipeline(self.stencil());
            return;
        }
        let group = group.per_pair;
        // One dispatch per direction pair: the lines of one direction partition the grid.
        for (i, d) in directions.pairs().iter().enumerate() {
            let direction = sweep_direction_offset(directions, i, accumulate, boundary);
            pass.set_bind_group(0, group, &[direction, work]);
            dispatch_linear(pass, sweep_lines(IVec3::from_array(d.o), n), items);
        }
        // The order into `multiple` once, not in each direction's dispatch.
        if accumulate {
            pass.set_pipeline(self.ready.accumulate_order[self.variant]);
            dispatch_linear(pass, n.pow(3), items);
            pass.set_pipeline(self.stencil());
        }
    }

    /// An accumulating iteration of the series, the first (`boundary`) bringing the light
    /// entering the grid in (§4).
    pub(crate) fn iterate(
        &self,
        pass: &mut StagePass,
        group: OrderPair,
        work: (u32, u32),
        boundary: bool,
    ) {
        self.pass_once(pass, group, work, true, boundary);
    }

    /// `S <- K (S_0 + S) + b` on what `multiple` holds, the change `K (S_0 + S) + b - S` left in
    /// order a: a warm restart's first order, and a coarse-grid cycle's residual and smoothing
    /// sweeps. `S_0 + S` goes into b, is scattered into a without accumulating, then
    /// `multiple` takes a and a the change. Leaves the stencil set.
    /// `orders` are the series' order pairs, `restart` its `S_0 → b`.
    pub(crate) fn restart_sweep(
        &self,
        pass: &mut StagePass,
        (orders, restart): (&OrderPairs, &BindGroup),
        work: u32,
        items: u32,
    ) {
        let n3 = self.n.pow(3);
        pass.set_pipeline(self.ready.warm_start[self.variant]);
        pass.set_bind_group(0, restart, &[0, work]);
        dispatch_linear(pass, n3, items);
        self.set_stencil(pass);
        self.pass_once(pass, orders.pair(2), (work, items), false, true);
        pass.set_pipeline(self.ready.warm_correction[self.variant]);
        pass.set_bind_group(0, &orders.per_pair[2], &[0, work]);
        dispatch_linear(pass, n3, items);
        self.set_stencil(pass);
    }

    /// The sizes of orders `M - 3` and `M - 2` (the full series' two-mode closure), from the
    /// closure's bindings while they hold them; leaves the stencil set.
    pub(crate) fn order_sizes(
        &self,
        pass: &mut StagePass,
        closure: &BindGroup,
        work: u32,
        items: u32,
    ) {
        pass.set_bind_group(0, closure, &[work]);
        pass.set_pipeline(self.ready.order_sizes);
        pass.dispatch(1, 1, items);
        self.set_stencil(pass);
    }

    /// The closure: the tail's coefficients, then the tail added to `multiple`.
    pub(crate) fn close(&self, pass: &mut StagePass, closure: &BindGroup, work: u32, items: u32) {
        pass.set_bind_group(0, closure, &[work]);
        pass.set_pipeline(self.ready.order_ratio);
        pass.dispatch(1, 1, items);
        pass.set_pipeline(self.ready.extrapolate[self.variant]);
        dispatch_linear(pass, self.n.pow(3), items);
    }
}
