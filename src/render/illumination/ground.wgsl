// The ground's radiance under each cloud (docs/illumination.md §4, "The ground"): per texel of
// the cloud's ground map, reflectance / pi times the irradiance of its lights through its light
// volumes (its own shadow and those they hold) plus the sky's pi L_sky. Runs at the start of
// the scatter stage, for the clouds a ground lights; the sweep takes it in where a lattice line
// climbs into the grid. z workgroup i does slot `work[i]`.
#import bevy_particle_clouds::types::{CloudParams, LightParams, Slot, PI, GroundMap, GROUND_MAP_SIDE, flat_invocation, light_coords, clamped_lookup, clamped_corner, corner_weight, affine_point, affine_vector, ground_texel_centre}

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> lights: array<LightParams>;
@group(0) @binding(2) var<storage, read> optical_depth: array<f32>;
@group(0) @binding(3) var<storage, read_write> grounds: array<GroundMap>;
@group(0) @binding(4) var<storage, read> work: array<u32>;

@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn ground_radiance(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = work[id.z];
    let slot = slots[index];
    let cloud = slot.cloud;
    let texel = flat_invocation(id, groups);
    if texel >= GROUND_MAP_SIDE * GROUND_MAP_SIDE {
        return;
    }
    let plane = grounds[index].plane;
    let to_world = grounds[index].world_from_local;
    let xz = ground_texel_centre(plane, vec2(texel % GROUND_MAP_SIDE, texel / GROUND_MAP_SIDE));
    let p = affine_point(grounds[index].local_from_world, vec3(xz.x, plane.x, xz.y));
    var irradiance = PI * grounds[index].sky.xyz;
    for (var l = 0u; l < cloud.light_count; l++) {
        let light = lights[slot.lights + l];
        let cosine = -normalize(affine_vector(to_world, light.w)).y;
        if cosine <= 0.0 {
            continue;
        }
        let t = clamped_lookup(light_coords(cloud, light, p), cloud.light_n);
        let first = slot.optical_depth + light.offset;
        var tau = 0.0;
        for (var corner = 0u; corner < 8u; corner++) {
            tau += corner_weight(t, corner) * optical_depth[first + clamped_corner(t, corner, cloud.light_n)];
        }
        irradiance += light.irradiance * (cosine * exp(-tau));
    }
    grounds[index].radiance[texel] = vec4(grounds[index].reflectance.xyz / PI * irradiance, 0.0);
}
