// Lit objects (docs/physics.md, "Lit objects"; docs/illumination.md §10): a Lambertian surface
// shows its colour plus reflectance / pi times the irradiance of the lights, through the clouds'
// shadow maps, and of the sky; fogged by the view's `DistanceFog` like any mesh.
// Rust mirrors: src/lit_object.rs, src/shadow_maps.rs.
#import bevy_pbr::{forward_io::VertexOutput, mesh_view_bindings::view}
#ifdef DISTANCE_FOG
#import bevy_pbr::{mesh_view_bindings::fog, pbr_functions::apply_fog}
#endif

const PI: f32 = 3.141592653589793;

struct ShadowMapPlacement {
    u: vec3<f32>,
    texel: f32,
    v: vec3<f32>,
    w_begin: f32,
    d: vec3<f32>,
    w_end: f32,
    corner: vec2<f32>,
    size: u32,
    first: u32,
}

struct LitSurface {
    color: vec3<f32>,
    reflectance: vec3<f32>,
}

struct LitLight {
    to_light: vec3<f32>,
    mapped: u32,
    irradiance: vec3<f32>,
    map: ShadowMapPlacement,
}

struct LitObjectLights {
    sky: vec3<f32>,
    count: u32,
    lights: array<LitLight, 8>,
}

@group(#{MATERIAL_BIND_GROUP}) @binding(0) var<uniform> surface: LitSurface;
@group(#{MATERIAL_BIND_GROUP}) @binding(1) var<uniform> lights: LitObjectLights;
@group(#{MATERIAL_BIND_GROUP}) @binding(2) var<storage, read> shadow_maps: array<f32>;

// Texel (i, j) of a map; 0 outside it (no cloud's column there).
fn texel(map: ShadowMapPlacement, i: i32, j: i32) -> f32 {
    let n = i32(map.size);
    if i < 0 || j < 0 || i >= n || j >= n {
        return 0.0;
    }
    return shadow_maps[map.first + u32(i + n * j)];
}

// The optical depth of every cloud between world point `x` and the light of `map`: bilinear
// between texel centres; 0 before the first cloud along the light.
fn cloud_optical_depth(map: ShadowMapPlacement, x: vec3<f32>) -> f32 {
    if dot(x, map.d) < map.w_begin {
        return 0.0;
    }
    let g = (vec2(dot(x, map.u), dot(x, map.v)) - map.corner) / map.texel - 0.5;
    let base = vec2<i32>(floor(g));
    let f = g - floor(g);
    let bottom = mix(texel(map, base.x, base.y), texel(map, base.x + 1, base.y), f.x);
    let top = mix(texel(map, base.x, base.y + 1), texel(map, base.x + 1, base.y + 1), f.x);
    return mix(bottom, top, f.y);
}

@fragment
fn fragment(in: VertexOutput) -> @location(0) vec4<f32> {
    let n = normalize(in.world_normal);
    let x = in.world_position.xyz;
    var irradiance = PI * lights.sky;
    for (var l = 0u; l < lights.count; l++) {
        let light = lights.lights[l];
        let cosine = dot(n, light.to_light);
        if cosine <= 0.0 {
            continue;
        }
        var tau = 0.0;
        if light.mapped != 0u {
            tau = cloud_optical_depth(light.map, x);
        }
        irradiance += light.irradiance * (cosine * exp(-tau));
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
