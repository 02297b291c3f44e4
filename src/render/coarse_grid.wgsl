// The coarse-grid cycles of the multiple scattering (docs/illumination.md §4, "Coarse-grid
// cycles"): the fine grid's residual averaged onto the grid of half the side, and the correction
// solved there added back. Every cloud of a volume pool in one dispatch: z workgroup i takes
// slot `work[i]`, its fine grid in `slots` and its coarse grid in `coarse_slots`.
// With angular moments (shader def MOMENTS) every entry of a voxel (mean, flux, quadrupole) alike.
#import bevy_particle_clouds::types::{Slot, clamped_lookup, corner_weight, flat_invocation, flux_element, quadrupole_element, voxel_index}

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> coarse_slots: array<Slot>;
// The fine grids' density.
@group(0) @binding(2) var<storage, read> densities: array<f32>;
// The fine grids' residual r = K (S_0 + S) + b - S.
@group(0) @binding(3) var<storage, read> residual: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> coarse_densities: array<f32>;
// The coarse series' start: the residual, restricted.
@group(0) @binding(5) var<storage, read_write> coarse_source: array<vec4<f32>>;
// The coarse series' sum past its start: the correction (zeroed with the restriction).
@group(0) @binding(6) var<storage, read_write> correction: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read_write> multiple: array<vec4<f32>>;
// A slot per z workgroup.
@group(0) @binding(8) var<storage, read> work: array<u32>;

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

// One invocation per coarse voxel: its density, the mean of its 8 fine voxels', and its start,
// their residual weighted by their density (a coarse voxel scatters what the fine ones do;
// where they hold none, 0); its correction zeroed for the series to sum into.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn restrict_residual(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let fine = slots[work[id.z]];
    let coarse = coarse_slots[work[id.z]];
    let n = fine.cloud.n;
    let nc = coarse.cloud.n;
    let c = flat_invocation(id, groups);
    if c >= nc * nc * nc {
        return;
    }
    let at = vec3(c % nc, (c / nc) % nc, c / (nc * nc));
    var children: array<u32, 8>;
    var rho: array<f32, 8>;
    var mass = 0.0;
    for (var k = 0u; k < 8u; k++) {
        let v = 2u * at + vec3(k & 1u, (k >> 1u) & 1u, k >> 2u);
        children[k] = voxel_index(v, n);
        rho[k] = densities[fine.density + children[k]];
        mass += rho[k];
    }
    coarse_densities[coarse.density + c] = mass / 8.0;
    let weight = select(0.0, 1.0 / mass, mass > 0.0);
    for (var e = 0u; e < ENTRIES; e++) {
        var sum = vec4(0.0);
        for (var k = 0u; k < 8u; k++) {
            sum += rho[k] * residual[element(fine.volume, n, children[k], e)];
        }
        coarse_source[element(coarse.volume, nc, c, e)] = sum * weight;
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
