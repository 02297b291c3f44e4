// The final render (the paper's Algorithm 3): each particle a camera-facing billboard, drawn back
// to front in the Transparent3d phase. Alpha is exact per pixel: the optical depth of the view
// ray through the particle's kernel (PHYSICS.md, docs/illumination.md "Draw").
#import bevy_render::view::View
#import bevy_particle_clouds::types::Particle

struct DrawParams {
    world_from_local: mat4x4<f32>,
    // Uniform scale of the cloud (world metres per local metre).
    scale: f32,
    // Extinction K per world metre at density 1.
    extinction: f32,
    _padding: vec2<f32>,
}

@group(0) @binding(0) var<uniform> view: View;
@group(1) @binding(0) var<uniform> cloud: DrawParams;
@group(1) @binding(1) var<storage, read> particles: array<Particle>;
@group(1) @binding(2) var<storage, read> colours: array<vec4<f32>>;
// Particle indices, back to front for this view.
@group(1) @binding(3) var<storage, read> order: array<u32>;

struct VertexOutput {
    @builtin(position) clip_position: vec4<f32>,
    @location(0) world_position: vec3<f32>,
    // World centre (xyz) and world radius (w).
    @location(1) @interpolate(flat) centre_radius: vec4<f32>,
    // albedo * S (rgb) and density (w).
    @location(2) @interpolate(flat) colour_density: vec4<f32>,
    // 1 when the billboard sits on the near plane (the particle reaches it).
    @location(3) @interpolate(flat) on_near_plane: u32,
}

fn near_plane() -> f32 {
    return view.clip_from_view[3][2];
}

@vertex
fn vertex(@builtin(vertex_index) vertex_index: u32, @builtin(instance_index) instance_index: u32) -> VertexOutput {
    var corners = array<vec2<f32>, 6>(
        vec2(-1.0, -1.0), vec2(1.0, -1.0), vec2(1.0, 1.0),
        vec2(-1.0, -1.0), vec2(1.0, 1.0), vec2(-1.0, 1.0),
    );
    let corner = corners[vertex_index];
    let index = order[instance_index];
    let particle = particles[index];
    let centre = (cloud.world_from_local * vec4(particle.position_radius.xyz, 1.0)).xyz;
    let radius = particle.position_radius.w * cloud.scale;
    let eye = view.world_position;
    let forward = -view.world_from_view[2].xyz;
    let right = view.world_from_view[0].xyz;
    let up = view.world_from_view[1].xyz;
    let to_centre = centre - eye;
    let depth = dot(to_centre, forward);

    var out: VertexOutput;
    out.centre_radius = vec4(centre, radius);
    out.colour_density = vec4(colours[index].xyz, particle.density.x);
    if depth + radius <= near_plane() {
        // Entirely behind the near plane: a degenerate triangle, culled before rasterisation.
        out.clip_position = vec4(2.0, 2.0, 2.0, 1.0);
        out.world_position = centre;
        out.on_near_plane = 0u;
    } else if depth - radius >= near_plane() {
        // A quad in the plane at the particle's depth covering the sphere's silhouette: for a
        // sphere seen at angle theta off-axis, its silhouette cone (half-angle alpha) cuts that
        // plane within R / cos(theta + alpha) of the centre.
        let distance = length(to_centre);
        let sin_alpha = min(radius / distance, 1.0);
        let cos_alpha = sqrt(1.0 - sin_alpha * sin_alpha);
        let cos_theta = depth / distance;
        let sin_theta = sqrt(max(1.0 - cos_theta * cos_theta, 0.0));
        let half_size = radius / max(cos_theta * cos_alpha - sin_theta * sin_alpha, 1e-4);
        let world = centre + (corner.x * right + corner.y * up) * half_size;
        out.world_position = world;
        out.clip_position = view.clip_from_world * vec4(world, 1.0);
        out.on_near_plane = 0u;
    } else {
        // The particle reaches the near plane (or holds the camera): cover the screen on the near
        // plane and integrate only the part of each ray's chord beyond it.
        out.clip_position = vec4(corner, 1.0, 1.0);
        let world = view.world_from_clip * vec4(corner, 1.0, 1.0);
        out.world_position = world.xyz / world.w;
        out.on_near_plane = 1u;
    }
    return out;
}

// Integral of (q - s^2/R^2)^2 ds: the kernel along the ray, s from the closest point.
fn chord_integral(s: f32, q: f32, r: f32) -> f32 {
    let x = s / r;
    return r * (q * q * x - 2.0 * q * x * x * x / 3.0 + x * x * x * x * x / 5.0);
}

@fragment
fn fragment(in: VertexOutput) -> @location(0) vec4<f32> {
    let eye = view.world_position;
    let w = normalize(in.world_position - eye);
    let centre = in.centre_radius.xyz;
    let radius = in.centre_radius.w;
    let to_centre = centre - eye;
    let t_c = dot(to_centre, w);
    let closest = to_centre - t_c * w;
    let q = 1.0 - dot(closest, closest) / (radius * radius);
    if q <= 0.0 {
        discard;
    }
    let s1 = radius * sqrt(q);
    var depth_units: f32;
    if in.on_near_plane == 0u {
        // The whole chord: tau_i(b) / (K eta) = R 16/15 q^(5/2).
        depth_units = radius * (16.0 / 15.0) * q * q * sqrt(q);
    } else {
        let forward = -view.world_from_view[2].xyz;
        let s0 = max(-s1, near_plane() / dot(w, forward) - t_c);
        if s0 >= s1 {
            discard;
        }
        depth_units = chord_integral(s1, q, radius) - chord_integral(s0, q, radius);
    }
    let tau = cloud.extinction * in.colour_density.w * depth_units;
    let alpha = 1.0 - exp(-tau);
    let colour = in.colour_density.xyz * view.exposure;
    return vec4(colour * alpha, alpha);
}
