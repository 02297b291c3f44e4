// Gather: the multiple-scattering source S_0 of every density voxel, the density-weighted mean of
// the single scattering S_1 = (1 / 4 pi) sum_l E_l exp(-tau_l) over the voxel's f^3 sub-points,
// all lights in one dispatch (docs/illumination.md §3).
#import bevy_particle_clouds::types::{CloudParams, LightParams, PI, voxel_index, grid_coords, light_coords, clamped_lookup, clamped_corner, zero_border_lookup, corner_weight, corner_voxel}

@group(0) @binding(0) var<uniform> cloud: CloudParams;
@group(0) @binding(1) var<storage, read> lights: array<LightParams>;
@group(0) @binding(2) var<storage, read> optical_depth: array<f32>;
@group(0) @binding(3) var<storage, read> density: array<f32>;
@group(0) @binding(4) var<storage, read_write> source: array<vec4<f32>>;

// S_1 at a cloud-local point. (billboard.wgsl evaluates the same sum at its shading points.)
fn single_scattering_at(p: vec3<f32>) -> vec3<f32> {
    var sum = vec3(0.0);
    for (var l = 0u; l < cloud.light_count; l++) {
        let light = lights[l];
        let t = clamped_lookup(light_coords(cloud, light, p), cloud.light_n);
        var tau = 0.0;
        for (var corner = 0u; corner < 8u; corner++) {
            tau += corner_weight(t, corner) * optical_depth[light.offset + clamped_corner(t, corner, cloud.light_n)];
        }
        sum += light.irradiance * exp(-tau);
    }
    return sum / (4.0 * PI);
}

fn density_at(p: vec3<f32>) -> f32 {
    let t = zero_border_lookup(grid_coords(cloud, p));
    var sum = 0.0;
    for (var corner = 0u; corner < 8u; corner++) {
        let i = corner_voxel(t, corner, cloud.n);
        if i >= 0 {
            sum += corner_weight(t, corner) * density[i];
        }
    }
    return sum;
}

@compute @workgroup_size(4, 4, 4)
fn gather(@builtin(global_invocation_id) id: vec3<u32>) {
    let n = cloud.n;
    if any(id >= vec3(n)) {
        return;
    }
    let f = cloud.supersampling;
    let centre = cloud.grid_origin + (vec3<f32>(id) + 0.5) * cloud.h;
    var weighted = vec3(0.0);
    var mass = 0.0;
    var plain = vec3(0.0);
    for (var s = 0u; s < f * f * f; s++) {
        let sub = vec3(s % f, (s / f) % f, s / (f * f));
        let p = centre + ((vec3<f32>(sub) + 0.5) / f32(f) - 0.5) * cloud.h;
        let scattered = single_scattering_at(p);
        let rho = density_at(p);
        weighted += rho * scattered;
        mass += rho;
        plain += scattered;
    }
    let mean = select(plain / f32(f * f * f), weighted / mass, mass > 0.0);
    source[voxel_index(id, n)] = vec4(mean, 0.0);
}
