// Shade: the optical depth towards one light in a light-aligned volume of m^3 voxels, computed
// incrementally slice by slice (the paper's Algorithm 4; docs/illumination.md §2). One invocation
// per column along the light; each slice is the previous one plus this step's optical depth.
// Every (cloud, light) of a volume pool in one dispatch: z workgroup i shades `work[i]`.
#import bevy_particle_clouds::types::{LightParams, Slot, voxel_index, flat_invocation}
#import bevy_particle_clouds::density::density_at

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> lights: array<LightParams>;
// Every light volume of every slot; a light's starts at slot.optical_depth + light.offset.
@group(0) @binding(3) var<storage, read_write> optical_depth: array<f32>;
// (slot, light) per z workgroup.
@group(0) @binding(4) var<storage, read> work: array<vec2<u32>>;

var<private> slot: Slot;
var<private> light: LightParams;

fn begin(item: u32) {
    let w = work[item];
    slot = slots[w.x];
    light = lights[slot.lights + w.y];
}

// Centre of light-volume voxel (a, b, c) in cloud-local space.
fn light_voxel_centre(v: vec3<u32>) -> vec3<f32> {
    let h = vec3(light.h_u, light.h_v, light.h_w);
    let xi = -light.half_extents + (vec3<f32>(v) + 0.5) * h;
    return slot.fine.grid_centre + xi.x * light.u + xi.y * light.v + xi.z * light.w;
}

fn sigma_at(v: vec3<u32>) -> f32 {
    return light.sigma_scale * density_at(slot.fine, slot.fine_density, light_voxel_centre(v));
}

fn store(v: vec3<u32>, tau: f32) {
    optical_depth[slot.optical_depth + light.offset + voxel_index(v, slot.fine.n)] = tau;
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
