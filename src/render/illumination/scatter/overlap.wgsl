// Overlap: the media of other clouds in a cloud's scattering grid (docs/illumination.md §4,
// "Clouds that overlap"). One invocation per voxel of a slot's grid: each neighbour's
// scattering-grid density at the voxel's centre (trilinear, zero outside its grid), as extinction
// and scattering in units of the slot's own extinction. Z workgroup i does slot `work[i]` with
// its neighbours in the pool bound as `neighbour_densities` (one dispatch per pool they lie in).
#import bevy_particle_clouds::types::{Slot, flat_invocation, zero_border_lookup, corner_weight, corner_voxel}

// Rust mirror: `Neighbour` in overlap.rs.
struct Neighbour {
    // The neighbour's scattering-grid voxel coordinates (voxel i's centre at i) of a
    // receiver-local point.
    coords_from_receiver: mat4x4<f32>,
    // First element of its density in `neighbour_densities`, and voxels per side.
    first: u32,
    n: u32,
    // Its extinction over the receiver's, and its albedo, both as the sweep takes them:
    // delta-M transformed (docs/illumination.md §4).
    extinction: f32,
    albedo: f32,
}

// Rust mirror: `OverlapItem` in overlap.rs.
struct OverlapItem {
    slot: u32,
    first_neighbour: u32,
    neighbours: u32,
    // 0: `foreign` becomes these neighbours' media; 1: they are added to it.
    accumulate: u32,
}

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> neighbours: array<Neighbour>;
@group(0) @binding(2) var<storage, read> neighbour_densities: array<f32>;
// Per voxel: the neighbours' extinction (x) and scattering (y), in units of the slot's own
// extinction at density 1.
@group(0) @binding(3) var<storage, read_write> foreign: array<vec2<f32>>;
@group(0) @binding(4) var<storage, read> work: array<OverlapItem>;

// A neighbour's density at receiver-local point `p`.
fn neighbour_density(neighbour: Neighbour, p: vec3<f32>) -> f32 {
    let t = zero_border_lookup((neighbour.coords_from_receiver * vec4(p, 1.0)).xyz);
    var rho = 0.0;
    for (var corner = 0u; corner < 8u; corner++) {
        let v = corner_voxel(t, corner, neighbour.n);
        if v >= 0 {
            rho += corner_weight(t, corner) * neighbour_densities[neighbour.first + u32(v)];
        }
    }
    return rho;
}

@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn overlap_media(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let item = work[id.z];
    let cloud = slots[item.slot].cloud;
    let n = cloud.n;
    let i = flat_invocation(id, groups);
    if i >= n * n * n {
        return;
    }
    let v = vec3(i % n, (i / n) % n, i / (n * n));
    let p = cloud.grid_origin + (vec3<f32>(v) + 0.5) * cloud.h;
    var media = vec2(0.0);
    for (var k = 0u; k < item.neighbours; k++) {
        let neighbour = neighbours[item.first_neighbour + k];
        let sigma = neighbour.extinction * neighbour_density(neighbour, p);
        media += vec2(sigma, sigma * neighbour.albedo);
    }
    let at = slots[item.slot].foreign + i;
    foreign[at] = select(vec2(0.0), foreign[at], item.accumulate != 0u) + media;
}
