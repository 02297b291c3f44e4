// Sky map (docs/illumination.md §10): over a horizontal plane under the clouds, the fraction of
// the sky's irradiance on an upward-facing surface that the clouds take away,
// 1 - (1/K) sum_k exp(-tau_k), tau_k the optical depth of every cloud along the k-th of K
// cosine-weighted directions up from the texel's point. `march_sky` adds the clouds of one pool
// to each (texel, direction)'s tau (one dispatch per pool they lie in; the first writes, the
// others add); `resolve_sky` then writes each texel's occlusion into the maps' buffer.
// Rust mirror: src/render/illumination/sky_map.rs; CPU reference: `reference::illumination::sky_occlusion_map`.
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
    // 0: this dispatch writes the optical depths, 1: it adds to them.
    accumulate: u32,
    // Tiles per side of the caster lists.
    tiles: u32,
}

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> casters: array<SkyCaster>;
// The pool's densities at binding 2 (density.wgsl).
@group(0) @binding(3) var<storage, read_write> sky_depth: array<f32>;
@group(0) @binding(4) var<storage, read> sky_map: SkyMapTarget;
@group(0) @binding(5) var<storage, read_write> maps: array<f32>;
// Per direction k and tile (a, b) of SKY_MAP_TILE² texels, the casters a ray may meet: list
// k tiles² + a + tiles b runs from entry `lists[i]` to `lists[i + 1]`, the entries after the
// DIRECTIONS tiles² + 1 offsets (`tile_lists` in sky_map.rs).
@group(0) @binding(6) var<storage, read> lists: array<u32>;

const DIRECTIONS: u32 = #{SKY_MAP_DIRECTIONS}u;
const TILE: u32 = #{SKY_MAP_TILE}u;
// An optical depth past which a direction's transmittance (below 6.2e-6) no longer matters: its
// march stops there, so a ray that has crossed one thick cloud marches no more.
const OPAQUE: f32 = 12.0;
const PI: f32 = 3.141592653589793;

// Direction k (world, upwards): cosine-weighted, on a Fibonacci spiral (`sky_direction` in
// src/shadow_maps.rs).
fn sky_direction(k: u32) -> vec3<f32> {
    let r = sqrt((f32(k) + 0.5) / f32(DIRECTIONS));
    let phi = f32(k) * PI * (3.0 - sqrt(5.0));
    return vec3(r * cos(phi), sqrt(max(1.0 - r * r, 0.0)), r * sin(phi));
}

// The optical depth of caster `c` along the world ray from `x` along `up`: its scattering grid's
// density marched through the cube around its voxels' centres widened by half a voxel, in
// ceil(chord / h - 0.001) equal steps sampled at their middles (`grid_optical_depth` on the CPU).
// The march stops once `before` (what the ray already crossed) and its own reach OPAQUE. The
// caster is read field by field: a ray that misses its sphere needs nothing else of it.
fn optical_depth_through(c: u32, x: vec3<f32>, up: vec3<f32>, before: f32) -> f32 {
    let oc = casters[c].centre - x;
    let radius = casters[c].radius;
    let b = dot(oc, up);
    if b < -radius || dot(oc, oc) - b * b > radius * radius {
        return 0.0;
    }
    let slot = slots[casters[c].slot];
    let grid = slot.cloud;
    let local_from_world = casters[c].local_from_world;
    let o = (local_from_world * vec4(x, 1.0)).xyz;
    let d = normalize((local_from_world * vec4(up, 0.0)).xyz);
    let lo = grid.grid_origin - 0.5 * grid.h;
    let hi = lo + f32(grid.n + 1u) * grid.h;
    // A ray parallel to a pair of faces crosses the slab between them everywhere, or nowhere.
    let flat = abs(d) < vec3(1e-12);
    if any(flat & ((o < lo) | (o > hi))) {
        return 0.0;
    }
    let safe = select(d, vec3(1.0), flat);
    let to_lo = (lo - o) / safe;
    let to_hi = (hi - o) / safe;
    let near = select(min(to_lo, to_hi), vec3(-3.4e38), flat);
    let far = select(max(to_lo, to_hi), vec3(3.4e38), flat);
    let t0 = max(max(near.x, near.y), max(near.z, 0.0));
    let t1 = min(min(far.x, far.y), far.z);
    if t1 <= t0 {
        return 0.0;
    }
    // A chord a rounding error over a whole number of voxels takes that number of steps.
    let steps = max(ceil((t1 - t0) / grid.h - 1e-3), 1.0);
    let dt = (t1 - t0) / steps;
    let per_density = grid.k_local * dt;
    let left = (OPAQUE - before) / per_density;
    var sum = 0.0;
    for (var s = 0u; s < u32(steps) && sum < left; s++) {
        sum += density_at(grid, slot.density, o + d * (t0 + (f32(s) + 0.5) * dt));
    }
    return per_density * sum;
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
    let k = i % DIRECTIONS;
    let column = vec2(texel % sky_map.size, texel / sky_map.size);
    let x = sky_map.origin + f32(column.x) * sky_map.step_x + f32(column.y) * sky_map.step_y;
    let up = sky_direction(k);
    var tau = 0.0;
    if sky_map.accumulate != 0u {
        tau = sky_depth[i];
    }
    let tile = column / TILE;
    let list = (k * sky_map.tiles + tile.y) * sky_map.tiles + tile.x;
    let entries = DIRECTIONS * sky_map.tiles * sky_map.tiles + 1u;
    for (var e = lists[list]; e < lists[list + 1u] && tau < OPAQUE; e++) {
        tau += optical_depth_through(lists[entries + e], x, up, tau);
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
