// Sky map (docs/illumination.md §10): over a horizontal plane under the clouds, the fraction of
// the sky's irradiance on an upward-facing surface that the clouds take away,
// 1 - (1/K) sum_k exp(-tau_k), tau_k the optical depth of every cloud along the k-th of K
// cosine-weighted directions up from the texel's point. `march_sky` adds the clouds of one pool
// to each (texel, direction)'s tau (one dispatch per pool they lie in; the first writes, the
// others add); `resolve_sky` then writes each texel's occlusion into the maps' buffer.
// Rust mirror: src/render/sky_map.rs; CPU reference: `reference::illumination::sky_occlusion_map`.
#import bevy_particle_clouds::types::{Slot, flat_invocation}
#import bevy_particle_clouds::density::density_at

// Rust mirror: `SkyCaster` in sky_map.rs.
struct SkyCaster {
    local_from_world: mat4x4<f32>,
    // The world sphere that holds its density (culls the rays that miss it).
    centre: vec3<f32>,
    radius: f32,
    // Its slot in the pool bound.
    slot: u32,
}

// Rust mirror: `SkyMapTarget` in sky_map.rs.
struct SkyMapTarget {
    // Texel (0, 0)'s point on the plane, and the map's first element in `maps`.
    origin: vec3<f32>,
    first: u32,
    step_x: vec3<f32>,
    size: u32,
    step_y: vec3<f32>,
    casters: u32,
    // 0: this dispatch writes the optical depths, 1: it adds to them.
    accumulate: u32,
}

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> casters: array<SkyCaster>;
// The pool's densities at binding 2 (density.wgsl).
@group(0) @binding(3) var<storage, read_write> sky_depth: array<f32>;
@group(0) @binding(4) var<storage, read> sky_map: SkyMapTarget;
@group(0) @binding(5) var<storage, read_write> maps: array<f32>;

const DIRECTIONS: u32 = #{SKY_MAP_DIRECTIONS}u;
const PI: f32 = 3.141592653589793;

// Direction k (world, upwards): cosine-weighted, on a Fibonacci spiral (`sky_direction` in
// src/shadow_maps.rs).
fn sky_direction(k: u32) -> vec3<f32> {
    let r = sqrt((f32(k) + 0.5) / f32(DIRECTIONS));
    let phi = f32(k) * PI * (3.0 - sqrt(5.0));
    return vec3(r * cos(phi), sqrt(max(1.0 - r * r, 0.0)), r * sin(phi));
}

// The optical depth of `caster` along the world ray from `x` along `up`: its scattering grid's
// density marched through the cube around its voxels' centres widened by half a voxel, in
// ceil(chord / h - 0.001) equal steps sampled at their middles (`grid_optical_depth` on the CPU).
fn optical_depth_through(caster: SkyCaster, x: vec3<f32>, up: vec3<f32>) -> f32 {
    let oc = caster.centre - x;
    let b = dot(oc, up);
    if b < -caster.radius || dot(oc, oc) - b * b > caster.radius * caster.radius {
        return 0.0;
    }
    let slot = slots[caster.slot];
    let grid = slot.cloud;
    let o = (caster.local_from_world * vec4(x, 1.0)).xyz;
    let d = normalize((caster.local_from_world * vec4(up, 0.0)).xyz);
    let lo = grid.grid_origin - 0.5 * grid.h;
    let hi = lo + f32(grid.n + 1u) * grid.h;
    // A ray parallel to a pair of faces crosses the slab between them everywhere, or nowhere.
    let flat = abs(d) < vec3(1e-12);
    if any(flat & ((o < lo) | (o > hi))) {
        return 0.0;
    }
    let safe = select(d, vec3(1.0), flat);
    let a = (lo - o) / safe;
    let c = (hi - o) / safe;
    let near = select(min(a, c), vec3(-3.4e38), flat);
    let far = select(max(a, c), vec3(3.4e38), flat);
    let t0 = max(max(near.x, near.y), max(near.z, 0.0));
    let t1 = min(min(far.x, far.y), far.z);
    if t1 <= t0 {
        return 0.0;
    }
    // A chord a rounding error over a whole number of voxels takes that number of steps.
    let steps = max(ceil((t1 - t0) / grid.h - 1e-3), 1.0);
    let dt = (t1 - t0) / steps;
    var sum = 0.0;
    for (var s = 0u; s < u32(steps); s++) {
        sum += density_at(grid, slot.density, o + d * (t0 + (f32(s) + 0.5) * dt));
    }
    return grid.k_local * sum * dt;
}

// One invocation per (texel, direction), element texel * DIRECTIONS + k of `sky_depth`.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn march_sky(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = flat_invocation(id, groups);
    let texels = sky_map.size * sky_map.size;
    if i >= texels * DIRECTIONS {
        return;
    }
    let texel = i / DIRECTIONS;
    let x = sky_map.origin + f32(texel % sky_map.size) * sky_map.step_x + f32(texel / sky_map.size) * sky_map.step_y;
    let up = sky_direction(i % DIRECTIONS);
    var tau = 0.0;
    for (var c = 0u; c < sky_map.casters; c++) {
        tau += optical_depth_through(casters[c], x, up);
    }
    if sky_map.accumulate != 0u {
        tau += sky_depth[i];
    }
    sky_depth[i] = tau;
}

// One invocation per texel: the occlusion 1 - mean_k exp(-tau_k).
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn resolve_sky(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let texel = flat_invocation(id, groups);
    if texel >= sky_map.size * sky_map.size {
        return;
    }
    var visible = 0.0;
    for (var k = 0u; k < DIRECTIONS; k++) {
        visible += exp(-sky_depth[texel * DIRECTIONS + k]);
    }
    maps[sky_map.first + texel] = 1.0 - visible / f32(DIRECTIONS);
}
