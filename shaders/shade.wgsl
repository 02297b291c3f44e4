// Shade: the transmittance towards one light in a light-aligned volume, computed incrementally
// slice by slice (the paper's Algorithm 4; docs/illumination.md §2). One invocation per column
// along the light; each slice is the previous one times this step's attenuation.
#import bevy_particle_clouds::types::{CloudParams, LightParams, voxel_index}

@group(0) @binding(0) var<uniform> cloud: CloudParams;
@group(0) @binding(1) var<uniform> light: LightParams;
@group(0) @binding(2) var<storage, read> density: array<f32>;
@group(0) @binding(3) var<storage, read_write> transmittance: array<f32>;

// Density at a cloud-local point: trilinear between voxel centres, zero outside the grid.
fn density_at(p: vec3<f32>) -> f32 {
    let n = i32(cloud.n);
    let g = (p - cloud.grid_origin) / cloud.h - 0.5;
    let base = vec3<i32>(floor(g));
    let f = g - floor(g);
    var sum = 0.0;
    for (var corner = 0u; corner < 8u; corner++) {
        let o = vec3<u32>(corner & 1u, (corner >> 1u) & 1u, corner >> 2u);
        let v = base + vec3<i32>(o);
        if all(v >= vec3(0)) && all(v < vec3(n)) {
            let w = select(1.0 - f, f, vec3<bool>(o));
            sum += w.x * w.y * w.z * density[voxel_index(vec3<u32>(v), cloud.n)];
        }
    }
    return sum;
}

// Centre of light-volume voxel (a, b, c) in cloud-local space.
fn light_voxel_centre(v: vec3<u32>) -> vec3<f32> {
    let h = vec3(light.h_u, light.h_v, light.h_w);
    let xi = -light.half_extents + (vec3<f32>(v) + 0.5) * h;
    return cloud.grid_centre + xi.x * light.u + xi.y * light.v + xi.z * light.w;
}

@compute @workgroup_size(8, 8, 1)
fn shade(@builtin(global_invocation_id) id: vec3<u32>) {
    let n = cloud.n;
    if id.x >= n || id.y >= n {
        return;
    }
    // sigma of the previous slice; 0 before the first, so slice 0 gets half a voxel of its own.
    var previous_sigma = 0.0;
    var t = 1.0;
    for (var c = 0u; c < n; c++) {
        let sigma = light.sigma_scale * density_at(light_voxel_centre(vec3(id.xy, c)));
        t *= exp(-0.5 * (previous_sigma + sigma) * light.h_w);
        transmittance[voxel_index(vec3(id.xy, c), n)] = t;
        previous_sigma = sigma;
    }
}

// The same transmittance with every voxel marching to the light on its own: the brute force
// the incremental pass replaces (benchmarks only).
@compute @workgroup_size(4, 4, 4)
fn shade_brute_force(@builtin(global_invocation_id) id: vec3<u32>) {
    let n = cloud.n;
    if any(id >= vec3(n)) {
        return;
    }
    var previous_sigma = 0.0;
    var depth = 0.0;
    for (var c = 0u; c <= id.z; c++) {
        let sigma = light.sigma_scale * density_at(light_voxel_centre(vec3(id.xy, c)));
        depth += 0.5 * (previous_sigma + sigma) * light.h_w;
        previous_sigma = sigma;
    }
    transmittance[voxel_index(id, n)] = exp(-depth);
}
