// Gather: one light's shaded volume resampled into the cloud's single-scattering source
// S_0 = (1 / 4 pi) sum_l E_l T_l (docs/illumination.md §3). Dispatched once per light.
#import bevy_particle_clouds::types::{CloudParams, LightParams, PI, voxel_index, clamp_trilinear}

@group(0) @binding(0) var<uniform> cloud: CloudParams;
@group(0) @binding(1) var<uniform> light: LightParams;
@group(0) @binding(2) var<storage, read> transmittance: array<f32>;
@group(0) @binding(3) var<storage, read_write> source: array<vec4<f32>>;

// Transmittance at a cloud-local point: trilinear in the light box, clamped to its edge voxels.
fn transmittance_at(p: vec3<f32>) -> f32 {
    let n = cloud.n;
    let d = p - cloud.grid_centre;
    let xi = vec3(dot(d, light.u), dot(d, light.v), dot(d, light.w));
    let g = (xi + light.half_extents) / vec3(light.h_u, light.h_v, light.h_w) - 0.5;
    let c = clamp_trilinear(g, n);
    var sum = 0.0;
    for (var corner = 0u; corner < 8u; corner++) {
        let o = vec3<u32>(corner & 1u, (corner >> 1u) & 1u, corner >> 2u);
        let w = select(1.0 - c.f, c.f, vec3<bool>(o));
        sum += w.x * w.y * w.z * transmittance[voxel_index(min(c.base + o, vec3(n - 1u)), n)];
    }
    return sum;
}

@compute @workgroup_size(4, 4, 4)
fn gather(@builtin(global_invocation_id) id: vec3<u32>) {
    let n = cloud.n;
    if any(id >= vec3(n)) {
        return;
    }
    let x = cloud.grid_origin + (vec3<f32>(id) + 0.5) * cloud.h;
    let s = light.irradiance * (transmittance_at(x) / (4.0 * PI));
    let i = voxel_index(id, n);
    if light.accumulate != 0u {
        source[i] += vec4(s, 0.0);
    } else {
        source[i] = vec4(s, 0.0);
    }
}
