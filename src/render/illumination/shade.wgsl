// Shade: the optical depth towards one light in a light-aligned volume of m^3 voxels, computed
// incrementally slice by slice (the paper's Algorithm 4; docs/illumination.md §2). One invocation
// per column along the light; each slice is the previous one plus this step's optical depth.
// Every (cloud, light) of a volume pool in one dispatch: z workgroup i shades `work[i]`.
// The cloud's own optical depth goes to `own_depth`, which other clouds' casts read, and to
// `optical_depth`, which gather and the billboards read (cast.wgsl adds other clouds' shadows).
#import bevy_particle_clouds::types::{LightParams, Slot, voxel_index, flat_invocation, light_voxel_centre}
#import bevy_particle_clouds::density::density_at

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> lights: array<LightParams>;
// Every light volume of every slot; a light's starts at slot.optical_depth + light.offset.
@group(0) @binding(3) var<storage, read_write> optical_depth: array<f32>;
// The same, never shadowed by other clouds.
@group(0) @binding(4) var<storage, read_write> own_depth: array<f32>;
// (slot, light) per z workgroup.
@group(0) @binding(5) var<storage, read> work: array<vec2<u32>>;

var<private> slot: Slot;
var<private> light: LightParams;

fn begin(item: u32) {
    let w = work[item];
    slot = slots[w.x];
    light = lights[slot.lights + w.y];
}

fn sigma_at(v: vec3<u32>) -> f32 {
    let p = light_voxel_centre(slot.fine, light, v);
    return light.sigma_scale * density_at(slot.fine, slot.fine_density, p);
}

fn store(v: vec3<u32>, tau: f32) {
    let i = slot.optical_depth + light.offset + voxel_index(v, slot.fine.n);
    optical_depth[i] = tau;
    own_depth[i] = tau;
}

@compute @workgroup_size(#{SLICE_WORKGROUP}, #{SLICE_WORKGROUP}, 1)
fn shade(@builtin(global_invocation_id) id: vec3<u32>) {
    begin(id.z);
    let m = slot.fine.n;
    if id.x >= m || id.y >= m {
        return;
    }
    // sigma of the previous slice; 0 before the first, so slice 0 gets half a voxel of its own.
    var previous_sigma = 0.0;
    var tau = 0.0;
    for (var c = 0u; c < m; c++) {
        let sigma = sigma_at(vec3(id.xy, c));
        tau += 0.5 * (previous_sigma + sigma) * light.h_w;
        store(vec3(id.xy, c), tau);
        previous_sigma = sigma;
    }
}

// The same optical depth with every voxel marching to the light on its own: the brute force
// the incremental pass replaces (benchmarks only). One invocation per voxel.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn shade_brute_force(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    begin(id.z);
    let m = slot.fine.n;
    let i = flat_invocation(id, groups);
    if i >= m * m * m {
        return;
    }
    let v = vec3(i % m, (i / m) % m, i / (m * m));
    var previous_sigma = 0.0;
    var tau = 0.0;
    for (var c = 0u; c <= v.z; c++) {
        let sigma = sigma_at(vec3(v.xy, c));
        tau += 0.5 * (previous_sigma + sigma) * light.h_w;
        previous_sigma = sigma;
    }
    store(v, tau);
}
