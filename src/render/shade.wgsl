// Shade: the optical depth towards one light in a light-aligned volume of m^3 voxels, computed
// incrementally slice by slice (the paper's Algorithm 4; docs/illumination.md §2). One invocation
// per column along the light; each slice is the previous one plus this step's optical depth.
#import bevy_particle_clouds::types::{LightParams, voxel_index}
#import bevy_particle_clouds::density::{cloud, density_at}

@group(0) @binding(1) var<uniform> light: LightParams;
// Every light's volume of the cloud; this light's starts at light.offset.
@group(0) @binding(3) var<storage, read_write> optical_depth: array<f32>;

// Centre of light-volume voxel (a, b, c) in cloud-local space.
fn light_voxel_centre(v: vec3<u32>) -> vec3<f32> {
    let h = vec3(light.h_u, light.h_v, light.h_w);
    let xi = -light.half_extents + (vec3<f32>(v) + 0.5) * h;
    return cloud.grid_centre + xi.x * light.u + xi.y * light.v + xi.z * light.w;
}

fn sigma_at(v: vec3<u32>) -> f32 {
    return light.sigma_scale * density_at(light_voxel_centre(v));
}

@compute @workgroup_size(#{SLICE_WORKGROUP}, #{SLICE_WORKGROUP}, 1)
fn shade(@builtin(global_invocation_id) id: vec3<u32>) {
    let m = cloud.light_n;
    if id.x >= m || id.y >= m {
        return;
    }
    // sigma of the previous slice; 0 before the first, so slice 0 gets half a voxel of its own.
    var previous_sigma = 0.0;
    var tau = 0.0;
    for (var c = 0u; c < m; c++) {
        let sigma = sigma_at(vec3(id.xy, c));
        tau += 0.5 * (previous_sigma + sigma) * light.h_w;
        optical_depth[light.offset + voxel_index(vec3(id.xy, c), m)] = tau;
        previous_sigma = sigma;
    }
}

// The same optical depth with every voxel marching to the light on its own: the brute force
// the incremental pass replaces (benchmarks only).
@compute @workgroup_size(#{VOXEL_WORKGROUP}, #{VOXEL_WORKGROUP}, #{VOXEL_WORKGROUP})
fn shade_brute_force(@builtin(global_invocation_id) id: vec3<u32>) {
    let m = cloud.light_n;
    if any(id >= vec3(m)) {
        return;
    }
    var previous_sigma = 0.0;
    var tau = 0.0;
    for (var c = 0u; c <= id.z; c++) {
        let sigma = sigma_at(vec3(id.xy, c));
        tau += 0.5 * (previous_sigma + sigma) * light.h_w;
        previous_sigma = sigma;
    }
    optical_depth[light.offset + voxel_index(id, m)] = tau;
}
