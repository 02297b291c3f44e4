// What a surface under the clouds reads of them (docs/illumination.md §10): the cloud-lighting
// lights and the sky, bound at 100, and the cloud shadow maps and the sky map, bound at 101, of a
// material's bind group; the clouds' transmittance between a world point and a light, and the
// part of the sky they leave it. Imported by
// `lit_object.wgsl` and `cloud_shadowed_material.wgsl`.
// Rust mirrors: src/lit_object.rs, src/shadow_maps.rs.
#define_import_path bevy_particle_clouds::cloud_shadow_maps

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

struct LitLight {
    to_light: vec3<f32>,
    mapped: u32,
    irradiance: vec3<f32>,
    map: ShadowMapPlacement,
}

struct LitObjectLights {
    sky: vec3<f32>,
    count: u32,
    // Its `size` is 0 without a sky map.
    sky_map: ShadowMapPlacement,
    lights: array<LitLight, 8>,
}

@group(#{MATERIAL_BIND_GROUP}) @binding(100) var<uniform> lights: LitObjectLights;
@group(#{MATERIAL_BIND_GROUP}) @binding(101) var<storage, read> shadow_maps: array<f32>;

// Texel (i, j) of a map; 0 outside it (no cloud's column there).
fn texel(map: ShadowMapPlacement, i: i32, j: i32) -> f32 {
    let n = i32(map.size);
    if i < 0 || j < 0 || i >= n || j >= n {
        return 0.0;
    }
    return shadow_maps[map.first + u32(i + n * j)];
}

// What `map` holds at world point `x` (for a light's map, the optical depth of every cloud
// between `x` and the light; for the sky map, the part of the sky they hide): bilinear between
// texel centres; 0 outside the map and before its first cloud along its direction.
fn map_value(map: ShadowMapPlacement, x: vec3<f32>) -> f32 {
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

// The clouds' transmittance between `x` and light `l`: 1 without a map.
fn cloud_transmittance(l: u32, x: vec3<f32>) -> f32 {
    let light = lights.lights[l];
    if light.mapped == 0u {
        return 1.0;
    }
    return exp(-map_value(light.map, x));
}

// The part of the sky's irradiance on an upward-facing surface at `x` that the clouds leave,
// `V`: read at `x`'s horizontal position from the sky map, made on its plane; 1 without one.
fn sky_visibility(x: vec3<f32>) -> f32 {
    if lights.sky_map.size == 0u {
        return 1.0;
    }
    return 1.0 - map_value(lights.sky_map, x);
}
