// The paper's §4 fill-rate optimisation, second half: the clouds, drawn into a reduced-resolution
// target (premultiplied radiance, alpha = 1 - transmittance), are enlarged onto the view over what
// is behind them. The upsample is depth-aware (a joint bilateral filter): of the four target
// texels around a pixel, those whose depth sample lies on another surface than the pixel's own
// get no weight, so cloud edges neither bleed onto nearer objects nor leave halos around them.
// `reference::cloud_target::upsample` is the CPU reference of this shader.
#import bevy_core_pipeline::fullscreen_vertex_shader::FullscreenVertexOutput
#import bevy_particle_clouds::types::{CloudTargetParams, cloud_target_depth_pixel, relative_depth_difference}

@group(0) @binding(0) var<uniform> params: CloudTargetParams;
@group(0) @binding(1) var clouds: texture_2d<f32>;
#ifdef MULTISAMPLED
@group(0) @binding(2) var scene_depth: texture_depth_multisampled_2d;
#else
@group(0) @binding(2) var scene_depth: texture_depth_2d;
#endif

fn depth_at(pixel: vec2<u32>) -> f32 {
    return textureLoad(scene_depth, pixel, 0);
}

@fragment
fn composite(in: FullscreenVertexOutput) -> @location(0) vec4<f32> {
    let pixel = vec2<u32>(floor(in.position.xy));
    let depth = depth_at(pixel);
    // The pixel's centre in target texels, relative to texel centres.
    let u = (in.position.xy - vec2<f32>(params.viewport_origin)) * params.scale - 0.5;
    let base = vec2<i32>(floor(u));
    let f = u - floor(u);
    let last = vec2<i32>(params.target_size) - 1;
    var sum = vec4(0.0);
    var weight = 0.0;
    var nearest = vec4(0.0);
    var nearest_difference = 2.0;
    for (var corner = 0u; corner < 4u; corner++) {
        let o = vec2<u32>(corner & 1u, corner >> 1u);
        let t = vec2<u32>(clamp(base + vec2<i32>(o), vec2(0), last));
        let bilinear = select(1.0 - f, f, vec2<bool>(o));
        let texel_depth = depth_at(cloud_target_depth_pixel(params, t));
        let similarity = relative_depth_difference(depth, texel_depth) / params.depth_tolerance;
        let w = bilinear.x * bilinear.y * exp(-similarity * similarity);
        let colour = textureLoad(clouds, t, 0);
        sum += w * colour;
        weight += w;
        // Nearest in reverse-Z (inverse depth), which tells apart surfaces at any distance from
        // the sky, where the relative difference is 1 for all of them.
        if abs(depth - texel_depth) < nearest_difference {
            nearest_difference = abs(depth - texel_depth);
            nearest = colour;
        }
    }
    // No texel on this pixel's surface (a sliver thinner than a texel, such as sky between two
    // objects): the texel nearest in inverse depth.
    if weight < 1e-4 {
        return nearest;
    }
    return sum / weight;
}
