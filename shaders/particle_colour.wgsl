// Per-particle colour: albedo times the accumulated illumination at the particle's centre
// (clamped trilinear; docs/illumination.md §5). What the billboards draw.
#import bevy_particle_clouds::types::{Particle, CloudParams, voxel_index, clamp_trilinear, flat_invocation}

@group(0) @binding(0) var<uniform> cloud: CloudParams;
@group(0) @binding(1) var<storage, read> particles: array<Particle>;
@group(0) @binding(2) var<storage, read> accumulated: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> colours: array<vec4<f32>>;

@compute @workgroup_size(64)
fn colour(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = flat_invocation(id, groups);
    if index >= cloud.particle_count {
        return;
    }
    let n = cloud.n;
    let g = (particles[index].position_radius.xyz - cloud.grid_origin) / cloud.h - 0.5;
    let c = clamp_trilinear(g, n);
    var sum = vec3(0.0);
    for (var corner = 0u; corner < 8u; corner++) {
        let o = vec3<u32>(corner & 1u, (corner >> 1u) & 1u, corner >> 2u);
        let w = select(1.0 - c.f, c.f, vec3<bool>(o));
        sum += w.x * w.y * w.z * accumulated[voxel_index(min(c.base + o, vec3(n - 1u)), n)].xyz;
    }
    colours[index] = vec4(cloud.albedo * sum, 0.0);
}
