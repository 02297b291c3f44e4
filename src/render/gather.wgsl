// Gather: for every voxel of the scattering grid, its density (the mean of its f^3 children in
// the fine grid, docs/illumination.md §1) and its multiple-scattering source S_0, the
// density-weighted mean over those children of the single scattering
// S_1 = (1 / 4 pi) sum_l E_l exp(-tau_l), all lights in one dispatch (§3).
#import bevy_particle_clouds::types::{CloudParams, LightParams, PI, voxel_index, light_coords, clamped_lookup, clamped_corner, corner_weight}

@group(0) @binding(0) var<uniform> cloud: CloudParams;
@group(0) @binding(1) var<storage, read> lights: array<LightParams>;
@group(0) @binding(2) var<storage, read> optical_depth: array<f32>;
// The fine density grid, light_n^3 voxels.
@group(0) @binding(3) var<storage, read> fine_density: array<f32>;
@group(0) @binding(4) var<storage, read_write> density: array<f32>;
@group(0) @binding(5) var<storage, read_write> source: array<vec4<f32>>;

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

@compute @workgroup_size(#{VOXEL_WORKGROUP}, #{VOXEL_WORKGROUP}, #{VOXEL_WORKGROUP})
fn gather(@builtin(global_invocation_id) id: vec3<u32>) {
    let n = cloud.n;
    if any(id >= vec3(n)) {
        return;
    }
    let f = cloud.supersampling;
    let fine_h = cloud.h / f32(f);
    var weighted = vec3(0.0);
    var mass = 0.0;
    var plain = vec3(0.0);
    for (var s = 0u; s < f * f * f; s++) {
        let child = id * f + vec3(s % f, (s / f) % f, s / (f * f));
        let p = cloud.grid_origin + (vec3<f32>(child) + 0.5) * fine_h;
        let scattered = single_scattering_at(p);
        let rho = fine_density[voxel_index(child, cloud.light_n)];
        weighted += rho * scattered;
        mass += rho;
        plain += scattered;
    }
    let children = f32(f * f * f);
    let i = voxel_index(id, n);
    density[i] = mass / children;
    source[i] = vec4(select(plain / children, weighted / mass, mass > 0.0), 0.0);
}
