// The coarse-grid cycles of the multiple scattering (docs/illumination.md §4, "Coarse-grid
// cycles"): the fine grid's media and residual averaged onto the grid of half the side, and the
// correction solved there added back. Every cloud of a volume pool in one dispatch: z workgroup i takes
// slot `work[i]`, its fine grid in `slots` and its coarse grid in `coarse_slots`.
// With angular moments (shader def MOMENTS) every entry of a voxel (mean, flux, quadrupole) alike.
#import bevy_particle_clouds::types::{Slot, clamped_lookup, corner_weight, flat_invocation, flux_element, quadrupole_element, voxel_index}

// Three entry points, each binding what it reads (no more storage buffers than the adapter
// check asks for): `restrict_media` 0-3, 7, 8; `restrict_residual` 0-7; `prolong_correction`
// 0, 1, 6, 7, 9.
@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> coarse_slots: array<Slot>;
// The fine grids' density.
@group(0) @binding(2) var<storage, read> densities: array<f32>;
// The fine grids' other clouds' media (overlap.wgsl).
@group(0) @binding(3) var<storage, read> foreign: array<vec2<f32>>;
// The fine grids' residual r = K (S_0 + S) + b - S.
@group(0) @binding(4) var<storage, read> residual: array<vec4<f32>>;
// The coarse series' start: the residual, restricted.
@group(0) @binding(5) var<storage, read_write> coarse_source: array<vec4<f32>>;
// The coarse series' sum past its start: the correction (zeroed with the restriction).
@group(0) @binding(6) var<storage, read_write> correction: array<vec4<f32>>;
// A slot per z workgroup.
@group(0) @binding(7) var<storage, read> work: array<u32>;
// The coarse grids' media: each slot's density, then its other clouds' media (the vec2 at
// `foreign`, as the sweep binds this buffer a second time).
@group(0) @binding(8) var<storage, read_write> coarse_media: array<f32>;
@group(0) @binding(9) var<storage, read_write> multiple: array<vec4<f32>>;

#ifdef MOMENTS
const ENTRIES: u32 = 9u;
#else
const ENTRIES: u32 = 1u;
#endif

// Entry e (0: the mean, 1-3: the flux, 4-8: the quadrupole) of voxel i in a volume whose means
// start at `first`.
fn element(first: u32, n: u32, i: u32, e: u32) -> u32 {
    if e == 0u {
        return first + i;
    }
    if e < 4u {
        return flux_element(first, n, i, e - 1u);
    }
    return quadrupole_element(first, n, i, e - 4u);
}

// Fine voxel k of the 8 that coarse voxel `at` holds.
fn child(at: vec3<u32>, k: u32, n: u32) -> u32 {
    return voxel_index(2u * at + vec3(k & 1u, (k >> 1u) & 1u, k >> 2u), n);
}

// The coarse voxel of invocation `id`, or `NONE` past the grid.
const NONE: u32 = 0xffffffffu;
fn coarse_voxel(id: vec3<u32>, groups: vec3<u32>) -> u32 {
    let nc = coarse_slots[work[id.z]].cloud.n;
    let c = flat_invocation(id, groups);
    return select(NONE, c, c < nc * nc * nc);
}

// Once before a batch's cycles, one invocation per coarse voxel: its medium, the mean of its 8
// fine voxels' (the density, and other clouds' extinction and scattering).
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn restrict_media(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let c = coarse_voxel(id, groups);
    if c == NONE {
        return;
    }
    let fine = slots[work[id.z]];
    let coarse = coarse_slots[work[id.z]];
    let nc = coarse.cloud.n;
    let at = vec3(c % nc, (c / nc) % nc, c / (nc * nc));
    var mass = 0.0;
    var media = vec2(0.0);
    for (var k = 0u; k < 8u; k++) {
        let i = child(at, k, fine.cloud.n);
        mass += densities[fine.density + i];
        if fine.cloud.foreign != 0u {
            media += foreign[fine.foreign + i];
        }
    }
    coarse_media[coarse.density + c] = mass / 8.0;
    if coarse.cloud.foreign != 0u {
        coarse_media[2u * (coarse.foreign + c)] = media.x / 8.0;
        coarse_media[2u * (coarse.foreign + c) + 1u] = media.y / 8.0;
    }
}

// The scattering coefficient of fine voxel i, in units of the cloud's extinction at density 1:
// its own and other clouds' (the sweep's `medium`, times its albedo).
fn scattering(fine: Slot, i: u32) -> f32 {
    var s = fine.cloud.scatter_albedo * fine.cloud.depth_scale * densities[fine.density + i];
    if fine.cloud.foreign != 0u {
        s += foreign[fine.foreign + i].y;
    }
    return s;
}

// Each cycle, one invocation per coarse voxel: its start, the residual of its 8 fine voxels
// weighted by what they scatter (a coarse voxel scatters what the fine ones do; where they
// scatter nothing, 0), and its correction zeroed for the series to sum into.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn restrict_residual(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let c = coarse_voxel(id, groups);
    if c == NONE {
        return;
    }
    let fine = slots[work[id.z]];
    let coarse = coarse_slots[work[id.z]];
    let n = fine.cloud.n;
    let nc = coarse.cloud.n;
    let at = vec3(c % nc, (c / nc) % nc, c / (nc * nc));
    var children: array<u32, 8>;
    var weights: array<f32, 8>;
    var total = 0.0;
    for (var k = 0u; k < 8u; k++) {
        children[k] = child(at, k, n);
        weights[k] = scattering(fine, children[k]);
        total += weights[k];
    }
    let normal = select(0.0, 1.0 / total, total > 0.0);
    for (var e = 0u; e < ENTRIES; e++) {
        var sum = vec4(0.0);
        for (var k = 0u; k < 8u; k++) {
            sum += weights[k] * residual[element(fine.volume, n, children[k], e)];
        }
        coarse_source[element(coarse.volume, nc, c, e)] = sum * normal;
        correction[element(coarse.multiple, nc, c, e)] = vec4(0.0);
    }
}

// One invocation per fine voxel: the correction, trilinear between the coarse voxels' centres
// (clamped at the edges), added to the solution.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn prolong_correction(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let fine = slots[work[id.z]];
    let coarse = coarse_slots[work[id.z]];
    let n = fine.cloud.n;
    let nc = coarse.cloud.n;
    let v = flat_invocation(id, groups);
    if v >= n * n * n {
        return;
    }
    let at = vec3(v % n, (v / n) % n, v / (n * n));
    // Fine voxel i's centre lies at coarse coordinate (i + 1/2) / 2 - 1/2.
    let lookup = clamped_lookup(0.5 * vec3<f32>(at) - 0.25, nc);
    var corners: array<u32, 8>;
    var weights: array<f32, 8>;
    for (var k = 0u; k < 8u; k++) {
        corners[k] = voxel_index(vec3<u32>(lookup.base) + vec3(k & 1u, (k >> 1u) & 1u, k >> 2u), nc);
        weights[k] = corner_weight(lookup, k);
    }
    for (var e = 0u; e < ENTRIES; e++) {
        var sum = vec4(0.0);
        for (var k = 0u; k < 8u; k++) {
            sum += weights[k] * correction[element(coarse.multiple, nc, corners[k], e)];
        }
        multiple[element(fine.multiple, n, v, e)] += sum;
    }
}
