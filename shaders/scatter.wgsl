// Multiple scattering: one iteration of the isotropic 26-neighbour stencil (the paper's
// Algorithm 2 with coefficients derived from transport; docs/illumination.md §4).
// Reads S_n, writes S_{n+1} and adds it to the accumulation volume.
#import bevy_particle_clouds::types::{CloudParams, voxel_index}

@group(0) @binding(0) var<uniform> cloud: CloudParams;
@group(0) @binding(1) var<storage, read> density: array<f32>;
@group(0) @binding(2) var<storage, read> s_in: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> s_out: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> accumulated: array<vec4<f32>>;

// Hops along offset `o` from voxel `v` that stay inside the grid.
fn hops_inside(v: vec3<i32>, o: vec3<i32>, n: i32) -> i32 {
    var hops = n;
    for (var a = 0; a < 3; a++) {
        if o[a] > 0 {
            hops = min(hops, n - 1 - v[a]);
        } else if o[a] < 0 {
            hops = min(hops, v[a]);
        }
    }
    return hops;
}

@compute @workgroup_size(4, 4, 4)
fn scatter(@builtin(global_invocation_id) id: vec3<u32>) {
    let n = cloud.n;
    if any(id >= vec3(n)) {
        return;
    }
    let i = voxel_index(id, n);
    let rho = density[i];
    let sigma = cloud.k_local * rho;
    // The paper weighs every neighbour by the voxel's own opacity.
    let own_opacity = 1.0 - exp(-sigma * cloud.h);
    var sum = vec3(0.0);
    for (var z = -1; z <= 1; z++) {
        for (var y = -1; y <= 1; y++) {
            for (var x = -1; x <= 1; x++) {
                let o = vec3(x, y, z);
                let reach = hops_inside(vec3<i32>(id), o, i32(n));
                if all(o == vec3(0)) || reach < 1 {
                    continue;
                }
                let step = cloud.h * length(vec3<f32>(o));
                // Free-path hops: about one mean free path, whole voxels, at least one.
                var hops = 1;
                if cloud.stencil == 2u {
                    let per_hop = sigma * step;
                    let free = select(f32(reach), floor(1.0 / per_hop), per_hop * f32(reach) > 1.0);
                    hops = clamp(i32(free), 1, reach);
                }
                let j = voxel_index(vec3<u32>(vec3<i32>(id) + hops * o), n);
                // Optical depth between the two voxel centres (trapezoid).
                let tau = cloud.k_local * 0.5 * (rho + density[j]) * step * f32(hops);
                var opacity = 1.0 - exp(-tau);
                if cloud.stencil == 1u {
                    opacity = own_opacity;
                } else if cloud.stencil == 2u {
                    // The sample stands for the segment twice as long (midpoint rule), cut at the
                    // grid's edge: beyond it there is no medium to scatter.
                    opacity = 1.0 - exp(-tau * min(2.0, f32(reach) / f32(hops)));
                }
                sum += opacity * s_in[j].xyz;
            }
        }
    }
    let s = sum * (cloud.albedo / 26.0);
    s_out[i] = vec4(s, 0.0);
    accumulated[i] += vec4(s, 0.0);
}
