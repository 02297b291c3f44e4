// Lit objects (docs/physics.md, "Lit objects"; docs/illumination.md §10): a Lambertian surface
// shows its colour plus reflectance / pi times the irradiance of the lights, through the clouds'
// shadow maps, and of the sky, through the sky map; fogged by the view's `DistanceFog` like any
// mesh.
// Rust mirror: src/lit_object.rs; the lights and maps: cloud_shadow_maps.wgsl.
#import bevy_pbr::{forward_io::VertexOutput, mesh_view_bindings::view}
#import bevy_particle_clouds::cloud_shadow_maps::{lights, cloud_transmittance, sky_visibility}
#ifdef DISTANCE_FOG
#import bevy_pbr::{mesh_view_bindings::fog, pbr_functions::apply_fog}
#endif

const PI: f32 = 3.141592653589793;

struct LitSurface {
    color: vec3<f32>,
    reflectance: vec3<f32>,
}

@group(#{MATERIAL_BIND_GROUP}) @binding(0) var<uniform> surface: LitSurface;

@fragment
fn fragment(in: VertexOutput) -> @location(0) vec4<f32> {
    let n = normalize(in.world_normal);
    let x = in.world_position.xyz;
    var irradiance = PI * lights.sky * sky_visibility(x);
    for (var l = 0u; l < lights.count; l++) {
        let light = lights.lights[l];
        let cosine = dot(n, light.to_light);
        if cosine <= 0.0 {
            continue;
        }
        irradiance += light.irradiance * (cosine * cloud_transmittance(l, x));
    }
    let radiance = surface.color + surface.reflectance * irradiance / PI;
    let colour = vec4(radiance * view.exposure, 1.0);
#ifdef DISTANCE_FOG
    // Fogged as Bevy fogs its own meshes.
    return apply_fog(fog, colour, x, view.world_position, in.position.xy);
#else
    return colour;
#endif
}
