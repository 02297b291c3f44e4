// Back-to-front particle sort on the GPU: keys from view depth, then an LSD radix sort of 32-bit
// keys in four 8-bit passes (count per tile, one global scan, stable scatter per tile).
// Each invocation owns a tile of TILE consecutive elements and walks it in order, which keeps
// the scatter stable without workgroup-level ranking.
#import bevy_particle_clouds::types::{Particle, flat_invocation}

const TILE: u32 = #{SORT_TILE}u;
const RADIX: u32 = 256u;

struct SortParams {
    // Row of view_from_local giving view-space z: z = dot(depth_row, vec4(p, 1)).
    depth_row: vec4<f32>,
    count: u32,
    tiles: u32,
    shift: u32,
    _padding: u32,
}

@group(0) @binding(0) var<uniform> params: SortParams;
@group(0) @binding(1) var<storage, read> particles: array<Particle>;
@group(0) @binding(2) var<storage, read_write> keys_in: array<u32>;
@group(0) @binding(3) var<storage, read_write> values_in: array<u32>;
@group(0) @binding(4) var<storage, read_write> keys_out: array<u32>;
@group(0) @binding(5) var<storage, read_write> values_out: array<u32>;
// Digit-major: histogram[digit * tiles + tile].
@group(0) @binding(6) var<storage, read_write> histogram: array<u32>;

// A float as a u32 whose unsigned order is the float's order; NaN sorts last.
fn sortable(z: f32) -> u32 {
    if z != z {
        return 0xffffffffu;
    }
    let bits = bitcast<u32>(z);
    return bits ^ select(0x80000000u, 0xffffffffu, (bits >> 31u) == 1u);
}

// View-space z grows towards the camera, so ascending z is back to front.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn depth_keys(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = flat_invocation(id, groups);
    if i >= params.count {
        return;
    }
    let p = particles[i].position_radius.xyz;
    keys_in[i] = sortable(dot(params.depth_row, vec4(p, 1.0)));
    values_in[i] = i;
}

@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn count_digits(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let tile = flat_invocation(id, groups);
    if tile >= params.tiles {
        return;
    }
    var counts: array<u32, 256>;
    let end = min((tile + 1u) * TILE, params.count);
    for (var e = tile * TILE; e < end; e++) {
        let digit = (keys_in[e] >> params.shift) & (RADIX - 1u);
        counts[digit] += 1u;
    }
    for (var d = 0u; d < RADIX; d++) {
        histogram[d * params.tiles + tile] = counts[d];
    }
}

var<workgroup> chunk_sums: array<u32, 256>;

// Exclusive prefix sum over the whole digit-major histogram: afterwards histogram[d * tiles + t]
// is where tile t's first element of digit d goes. One workgroup; each invocation owns a chunk.
@compute @workgroup_size(256)
fn scan_digits(@builtin(local_invocation_index) lane: u32) {
    let total = RADIX * params.tiles;
    let chunk = (total + 255u) / 256u;
    let begin = min(lane * chunk, total);
    let end = min(begin + chunk, total);
    var sum = 0u;
    for (var i = begin; i < end; i++) {
        sum += histogram[i];
    }
    chunk_sums[lane] = sum;
    workgroupBarrier();
    if lane == 0u {
        var running = 0u;
        for (var l = 0u; l < 256u; l++) {
            let s = chunk_sums[l];
            chunk_sums[l] = running;
            running += s;
        }
    }
    workgroupBarrier();
    var running = chunk_sums[lane];
    for (var i = begin; i < end; i++) {
        let c = histogram[i];
        histogram[i] = running;
        running += c;
    }
}

@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn scatter_digits(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let tile = flat_invocation(id, groups);
    if tile >= params.tiles {
        return;
    }
    var offsets: array<u32, 256>;
    for (var d = 0u; d < RADIX; d++) {
        offsets[d] = histogram[d * params.tiles + tile];
    }
    let end = min((tile + 1u) * TILE, params.count);
    for (var e = tile * TILE; e < end; e++) {
        let key = keys_in[e];
        let digit = (key >> params.shift) & (RADIX - 1u);
        let destination = offsets[digit];
        offsets[digit] = destination + 1u;
        keys_out[destination] = key;
        values_out[destination] = values_in[e];
    }
}
