// Multiple scattering: one iteration of the isotropic 26-neighbour stencil (the paper's
// Algorithm 2 with coefficients derived from transport; docs/illumination.md §4).
// Reads S_n, writes S_{n+1} and adds it to the accumulation volume.
#import bevy_particle_clouds::types::{CloudParams, voxel_index}

@group(0) @binding(0) var<uniform> cloud: CloudParams;
@group(0) @binding(1) var<storage, read> density: array<f32>;
@group(0) @binding(2) var<storage, read> s_in: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> s_out: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> accumulated: array<vec4<f32>>;

@compute @workgroup_size(4, 4, 4)
fn scatter(@builtin(global_invocation_id) id: vec3<u32>) {
    let n = cloud.n;
    if any(id >= vec3(n)) {
        return;
    }
    let i = voxel_index(id, n);
    let rho = density[i];
    // The paper weighs every neighbour by the voxel's own opacity.
    let own_opacity = 1.0 - exp(-cloud.k_local * rho * cloud.h);
    var sum = vec3(0.0);
    for (var z = -1; z <= 1; z++) {
        for (var y = -1; y <= 1; y++) {
            for (var x = -1; x <= 1; x++) {
                let o = vec3(x, y, z);
                let v = vec3<i32>(id) + o;
                if all(o == vec3(0)) || any(v < vec3(0)) || any(v >= vec3(i32(n))) {
                    continue;
                }
                let j = voxel_index(vec3<u32>(v), n);
                // Optical depth between the two voxel centres (trapezoid).
                let tau = cloud.k_local * 0.5 * (rho + density[j]) * cloud.h * length(vec3<f32>(o));
                let opacity = select(1.0 - exp(-tau), own_opacity, cloud.stencil == 1u);
                sum += opacity * s_in[j].xyz;
            }
        }
    }
    let s = sum * (cloud.albedo / 26.0);
    s_out[i] = vec4(s, 0.0);
    accumulated[i] += vec4(s, 0.0);
}
