// Distance fog (docs/physics.md, "Fog"): what Bevy's `DistanceFog` does to a mesh fragment, done
// to each piece of a chord: light c covering alpha of the view at distance d becomes
// c V(d) + alpha A(d) F, F the fog's colour plus its glow about the lights. Summed along a ray,
// that is the fog of a medium the fog permeates. The falloff is a shader def (`FOG_*`).
// Rust mirror: src/render/draw/fog.rs (`CloudFogParams`), src/fog.rs (the CPU model).
#define_import_path bevy_particle_clouds::fog

struct CloudFog {
    color: vec4<f32>,
    directional_light_color: vec3<f32>,
    directional_light_exponent: f32,
    // Linear: (start, end, 0) metres; the exponentials: (density, 0, 0) per metre; Atmospheric:
    // extinction per metre.
    falloff: vec3<f32>,
    light_count: u32,
    // Atmospheric: in-scattering per metre.
    inscattering: vec3<f32>,
    _padding: u32,
    to_light: array<vec4<f32>, 10>,
    irradiance: array<vec4<f32>, 10>,
}

// F along the world unit ray w; the glow scales with the view's exposure, as Bevy's does.
fn fog_colour(fog: CloudFog, w: vec3<f32>, exposure: f32) -> vec3<f32> {
    var glow = vec3(0.0);
    for (var l = 0u; l < fog.light_count; l++) {
        let cosine = max(dot(w, fog.to_light[l].xyz), 0.0);
        glow += pow(cosine, fog.directional_light_exponent) * fog.irradiance[l].xyz;
    }
    return fog.color.rgb + fog.directional_light_color * glow * exposure;
}

// 1 - exp(-x), x >= 0.
fn thickening(x: vec3<f32>) -> vec3<f32> {
    return vec3(1.0) - exp(-x);
}

// Light c (premultiplied) covering `coverage` of the view at distance d, fogged with colour f.
fn fogged(fog: CloudFog, c: vec3<f32>, coverage: f32, d: f32, f: vec3<f32>) -> vec3<f32> {
    let alpha = fog.color.a;
#ifdef FOG_ATMOSPHERIC
    let transmitted = vec3(1.0) - alpha * thickening(d * fog.falloff);
    let inscattered = alpha * thickening(d * fog.inscattering);
    return c * transmitted + coverage * inscattered * f;
#else
    var amount = 0.0;
#ifdef FOG_LINEAR
    let start = fog.falloff.x;
    let end = fog.falloff.y;
    amount = 1.0 - clamp((end - d) / (end - start), 0.0, 1.0);
#endif
#ifdef FOG_EXPONENTIAL
    amount = thickening(vec3(d * fog.falloff.x)).x;
#endif
#ifdef FOG_EXPONENTIAL_SQUARED
    let x = d * fog.falloff.x;
    amount = thickening(vec3(x * x)).x;
#endif
    amount *= alpha;
    return c * (1.0 - amount) + coverage * amount * f;
#endif
}
