// Voxelize: every particle deposits its mass into the cloud's (fine) density grid
// (docs/illumination.md §1). One invocation per row of voxels of a particle's support, in two
// passes (the kernel's sum over the support, then the deposit); float atomics by
// compare-exchange.
#import bevy_particle_clouds::types::{Particle, CloudParams, KERNEL_VOLUME, kernel, voxel_index, zero_border_lookup, corner_weight, corner_voxel}

@group(0) @binding(0) var<uniform> cloud: CloudParams;
@group(0) @binding(1) var<storage, read> particles: array<Particle>;
// f32 bits; cleared to zero before the passes.
@group(0) @binding(2) var<storage, read_write> density: array<atomic<u32>>;
// Per particle, the kernel's sum over the voxel centres in its support (f32 bits); cleared to
// zero before the passes.
@group(0) @binding(3) var<storage, read_write> totals: array<atomic<u32>>;

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
fn splat(g: vec3<f32>, density_per_voxel: f32) {
    let t = zero_border_lookup(g);
    var inside = 0.0;
    for (var corner = 0u; corner < 8u; corner++) {
        if corner_voxel(t, corner, cloud.n) >= 0 {
            inside += corner_weight(t, corner);
        }
    }
    if inside <= 0.0 {
        return;
    }
    for (var corner = 0u; corner < 8u; corner++) {
        let i = corner_voxel(t, corner, cloud.n);
        if i >= 0 {
            add_density(u32(i), density_per_voxel * corner_weight(t, corner) / inside);
        }
    }
}

// A particle's footprint in the grid: its centre in voxel coordinates, its radius in voxels
// and the range of voxels inside its support.
struct Footprint {
    g: vec3<f32>,
    r_voxels: f32,
    lo: vec3<i32>,
    hi: vec3<i32>,
}

fn footprint(particle: Particle) -> Footprint {
    let g = (particle.position_radius.xyz - cloud.grid_origin) / cloud.h - 0.5;
    let r_voxels = particle.position_radius.w / cloud.h;
    let lo = max(vec3<i32>(ceil(g - r_voxels)), vec3(0));
    let hi = min(vec3<i32>(floor(g + r_voxels)), vec3(i32(cloud.n) - 1));
    return Footprint(g, r_voxels, lo, hi);
}

// The row (y, z) of a particle's support that invocation `id` handles: each invocation handles
// one row of one particle, so no invocation loops over more than a row (software rasterisers
// such as lavapipe cut loops off after 65535 iterations per invocation).
fn row(id: vec3<u32>, f: Footprint) -> vec2<i32> {
    return f.lo.yz + vec2<i32>(id.yz);
}

// Kernel weight of voxel x of a row.
fn row_weight(f: Footprint, x: i32, yz: vec2<i32>) -> f32 {
    let d = vec3<f32>(vec3(x, yz)) - f.g;
    return kernel(dot(d, d) / (f.r_voxels * f.r_voxels));
}

// Pass 1: every row adds its kernel sum to its particle's total W (the normalisation that makes
// the deposit mass-exact).
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn kernel_sums(@builtin(global_invocation_id) id: vec3<u32>) {
    let index = id.x;
    if index >= cloud.particle_count {
        return;
    }
    let particle = particles[index];
    let f = footprint(particle);
    let yz = row(id, f);
    if particle.density.x <= 0.0 || particle.position_radius.w < cloud.h || any(yz > f.hi.yz) {
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
    let index = id.x;
    if index >= cloud.particle_count {
        return;
    }
    let particle = particles[index];
    let eta = particle.density.x;
    let f = footprint(particle);
    if eta <= 0.0 {
        return;
    }
    // Mass / voxel volume, in density units; (r/h)^3 avoids overflow for huge particles.
    let density_per_voxel = KERNEL_VOLUME * eta * f.r_voxels * f.r_voxels * f.r_voxels;
    let total = bitcast<f32>(atomicLoad(&totals[index]));
    if particle.position_radius.w < cloud.h || total <= 0.0 {
        if all(id.yz == vec2(0u)) {
            splat(f.g, density_per_voxel);
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
            add_density(voxel_index(vec3<u32>(vec3(x, yz)), cloud.n), w * scale);
        }
    }
}
