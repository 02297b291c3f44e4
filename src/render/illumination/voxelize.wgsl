// Voxelize: every particle deposits its mass into its cloud's (fine) density grid
// (docs/illumination.md §1). A particle wider than 32 voxels deposits on a coarser density level
// instead, so that none visits more than 65³ voxels; the levels are then enlarged into the fine
// grid, coarsest first. One invocation per row of voxels of a particle's support, in two passes
// (the kernel's sum over the support, then the deposit); float atomics by compare-exchange.
// Every cloud of a volume pool in one dispatch: z workgroup i voxelizes `work[i]`, whose particles
// were copied into `particles` from element `work[i].y` on.
#import bevy_particle_clouds::types::{Particle, CloudParams, DensityLevels, Slot, KERNEL_VOLUME, kernel, voxel_index, zero_border_lookup, corner_weight, corner_voxel}

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
// The particles of every cloud voxelized this frame, one after the other.
@group(0) @binding(1) var<storage, read> particles: array<Particle>;
// Every slot's density levels, f32 bits, the fine grid first; a slot's are cleared to zero before
// the passes.
@group(0) @binding(2) var<storage, read_write> density: array<atomic<u32>>;
// Per particle of `particles`, the kernel's sum over the voxel centres in its support (f32 bits);
// cleared to zero before the passes.
@group(0) @binding(3) var<storage, read_write> totals: array<atomic<u32>>;
// The levels' sizes (the same for every slot of a pool); `upsample_from` differs per upsample
// dispatch (a dynamic offset).
@group(0) @binding(4) var<uniform> levels: DensityLevels;
// (slot, first particle) per z workgroup.
@group(0) @binding(5) var<storage, read> work: array<vec2<u32>>;

// The fine grid's uniform of the item's cloud, and the first element of its levels in `density`.
var<private> cloud: CloudParams;
var<private> first_density: u32;

fn begin(item: u32) {
    let slot = slots[work[item].x];
    cloud = slot.fine;
    first_density = slot.fine_density;
}

// One density level: voxels per side, its first element in `density`, and its voxel size.
struct Level {
    n: u32,
    offset: u32,
    h: f32,
}

fn level_at(l: u32) -> Level {
    let size = levels.size_offset[l];
    return Level(size.x, first_density + size.y, cloud.h * f32(1u << l));
}

// The finest level on which a particle of radius `r` spans at most `max_radius` voxels, else the
// coarsest (`density_level` in src/math.rs).
fn particle_level(r: f32) -> u32 {
    var l = 0u;
    while l + 1u < levels.count && r > levels.max_radius * level_at(l).h {
        l++;
    }
    return l;
}

fn add_density(i: u32, value: f32) {
    var old = atomicLoad(&density[i]);
    loop {
        let result = atomicCompareExchangeWeak(&density[i], old, bitcast<u32>(bitcast<f32>(old) + value));
        if result.exchanged {
            break;
        }
        old = result.old_value;
    }
}

fn add_total(i: u32, value: f32) {
    var old = atomicLoad(&totals[i]);
    loop {
        let result = atomicCompareExchangeWeak(&totals[i], old, bitcast<u32>(bitcast<f32>(old) + value));
        if result.exchanged {
            break;
        }
        old = result.old_value;
    }
}

// Sub-voxel particle: its whole mass goes to the 8 voxel centres around it, trilinearly,
// renormalised over the ones inside the grid so no mass is lost at the border.
fn splat(f: Footprint, density_per_voxel: f32) {
    let t = zero_border_lookup(f.g);
    var inside = 0.0;
    for (var corner = 0u; corner < 8u; corner++) {
        if corner_voxel(t, corner, f.level.n) >= 0 {
            inside += corner_weight(t, corner);
        }
    }
    if inside <= 0.0 {
        return;
    }
    for (var corner = 0u; corner < 8u; corner++) {
        let i = corner_voxel(t, corner, f.level.n);
        if i >= 0 {
            add_density(f.level.offset + u32(i), density_per_voxel * corner_weight(t, corner) / inside);
        }
    }
}

// A particle's footprint on its level: its centre in voxel coordinates, its radius in voxels (for
// its mass), the radius of the kernel it deposits with (narrower on a coarse level, by what the
// upsampling spreads: `level_kernel_radius` in src/math.rs), and the range of voxels inside that
// kernel's support.
struct Footprint {
    level: Level,
    g: vec3<f32>,
    r_voxels: f32,
    kernel_voxels: f32,
    lo: vec3<i32>,
    hi: vec3<i32>,
}

fn footprint(particle: Particle) -> Footprint {
    let r = particle.position_radius.w;
    let l = particle_level(r);
    let level = level_at(l);
    let g = (particle.position_radius.xyz - cloud.grid_origin) / level.h - 0.5;
    let narrowing = levels.kernel_narrowing * (level.h * level.h - cloud.h * cloud.h);
    let kernel_voxels = select(sqrt(max(r * r - narrowing, 0.0)), r, l == 0u) / level.h;
    let lo = max(vec3<i32>(ceil(g - kernel_voxels)), vec3(0));
    let hi = min(vec3<i32>(floor(g + kernel_voxels)), vec3(i32(level.n) - 1));
    return Footprint(level, g, r / level.h, kernel_voxels, lo, hi);
}

// The row (y, z) of a particle's support that invocation `id` handles: each invocation handles
// one row of one particle, so no invocation loops over more than a row (software rasterisers
// such as lavapipe cut loops off after 65535 iterations per invocation). `id.y` counts the rows
// of the cloud's largest support, `cloud.rows` per axis; the dispatch covers the pool's largest.
fn row(id: vec3<u32>, f: Footprint) -> vec2<i32> {
    return f.lo.yz + vec2<i32>(vec2(id.y % cloud.rows, id.y / cloud.rows));
}

// The item's particle that invocation `id` handles, or none (-1).
fn particle_index(id: vec3<u32>) -> i32 {
    begin(id.z);
    if id.x >= cloud.particle_count || id.y >= cloud.rows * cloud.rows {
        return -1;
    }
    return i32(work[id.z].y + id.x);
}

// Kernel weight of voxel x of a row.
fn row_weight(f: Footprint, x: i32, yz: vec2<i32>) -> f32 {
    let d = vec3<f32>(vec3(x, yz)) - f.g;
    return kernel(dot(d, d) / (f.kernel_voxels * f.kernel_voxels));
}

// Pass 1: every row adds its kernel sum to its particle's total W (the normalisation that makes
// the deposit mass-exact).
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn kernel_sums(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = particle_index(id);
    if i < 0 {
        return;
    }
    let index = u32(i);
    let particle = particles[index];
    let f = footprint(particle);
    let yz = row(id, f);
    if particle.density.x <= 0.0 || f.r_voxels < 1.0 || any(yz > f.hi.yz) {
        return;
    }
    var sum = 0.0;
    for (var x = f.lo.x; x <= f.hi.x; x++) {
        sum += row_weight(f, x, yz);
    }
    if sum > 0.0 {
        add_total(index, sum);
    }
}

// Pass 2: every row deposits its share of the particle's mass; a sub-voxel particle (or one whose
// support holds no voxel centre) is splatted by its first row.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn deposit(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = particle_index(id);
    if i < 0 {
        return;
    }
    let index = u32(i);
    let particle = particles[index];
    let eta = particle.density.x;
    let f = footprint(particle);
    if eta <= 0.0 {
        return;
    }
    // Mass / the level's voxel volume, in density units; (r/h)^3 avoids overflow for huge
    // particles.
    let density_per_voxel = KERNEL_VOLUME * eta * f.r_voxels * f.r_voxels * f.r_voxels;
    let total = bitcast<f32>(atomicLoad(&totals[index]));
    if f.r_voxels < 1.0 || total <= 0.0 {
        if id.y == 0u {
            splat(f, density_per_voxel);
        }
        return;
    }
    let yz = row(id, f);
    if any(yz > f.hi.yz) {
        return;
    }
    let scale = density_per_voxel / total;
    for (var x = f.lo.x; x <= f.hi.x; x++) {
        let w = row_weight(f, x, yz);
        if w > 0.0 {
            add_density(f.level.offset + voxel_index(vec3<u32>(vec3(x, yz)), f.level.n), w * scale);
        }
    }
}

// The density weights of fine voxel `i` on the coarse voxels (i >> 1) - 1 + t, t = 0, 1, 2, one
// axis of a level of `fine_n` voxels under one of `coarse_n`. Coarse voxel J gives 1/8, 3/8, 3/8
// and 1/8 of its mass to fine voxels 2J - 1 ..= 2J + 2; a share that would leave the level goes to
// its edge voxel, so no mass is lost. Density weights are twice the shares (a fine voxel is half
// as wide); inside, they are trilinear interpolation's.
fn prolongation(i: u32, fine_n: u32, coarse_n: u32) -> vec3<f32> {
    var w = vec3(0.0);
    for (var t = 0; t < 3; t++) {
        let j = i32(i >> 1u) - 1 + t;
        if j < 0 || j >= i32(coarse_n) {
            continue;
        }
        for (var d = -1; d <= 2; d++) {
            if clamp(2 * j + d, 0, i32(fine_n) - 1) == i32(i) {
                w[t] += select(0.75, 0.25, d == -1 || d == 2);
            }
        }
    }
    return w;
}

// Pass 3, once per coarse level, coarsest first: level `upsample_from` enlarged by
// `prolongation` on every axis is added to the level below. One invocation per column of the
// level below, whose voxels only it writes; z workgroup i enlarges `work[i]`'s levels.
@compute @workgroup_size(#{SLICE_WORKGROUP}, #{SLICE_WORKGROUP}, 1)
fn upsample(@builtin(global_invocation_id) id: vec3<u32>) {
    begin(id.z);
    let coarse = level_at(levels.upsample_from);
    let fine = level_at(levels.upsample_from - 1u);
    if any(id.xy >= vec2(fine.n)) {
        return;
    }
    let wx = prolongation(id.x, fine.n, coarse.n);
    let wy = prolongation(id.y, fine.n, coarse.n);
    for (var z = 0u; z < fine.n; z++) {
        let v = vec3(id.xy, z);
        let wz = prolongation(z, fine.n, coarse.n);
        let base = vec3<i32>(v >> vec3(1u)) - 1;
        var sum = 0.0;
        for (var c = 0; c < 3; c++) {
            for (var b = 0; b < 3; b++) {
                for (var a = 0; a < 3; a++) {
                    let weight = wx[a] * wy[b] * wz[c];
                    if weight > 0.0 {
                        let j = vec3<u32>(base + vec3(a, b, c));
                        sum += weight * bitcast<f32>(atomicLoad(&density[coarse.offset + voxel_index(j, coarse.n)]));
                    }
                }
            }
        }
        let i = fine.offset + voxel_index(v, fine.n);
        atomicStore(&density[i], bitcast<u32>(bitcast<f32>(atomicLoad(&density[i])) + sum));
    }
}
