// The final render (the paper's Algorithm 3): each particle a camera-facing billboard, drawn back
// to front in the Transparent3d phase. Alpha is exact per pixel: the optical depth of the view
// ray through the particle's kernel. The colour is the light scattered along that chord, taken at
// `segments` points (PHYSICS.md; docs/illumination.md §5).
#import bevy_render::view::View
#import bevy_particle_clouds::types::{Particle, CloudParams, LightParams, PI, grid_coords, light_coords, clamped_lookup, clamped_corner, corner_weight, opacity}

struct DrawParams {
    world_from_local: mat4x4<f32>,
    local_from_world: mat4x4<f32>,
    // Uniform scale of the cloud (world metres per local metre).
    scale: f32,
    // Extinction K per world metre at density 1.
    extinction: f32,
    // Segments of each chord at which the illumination is evaluated.
    segments: u32,
    _padding: u32,
}

@group(0) @binding(0) var<uniform> view: View;
@group(1) @binding(0) var<uniform> params: DrawParams;
@group(1) @binding(1) var<uniform> cloud: CloudParams;
@group(1) @binding(2) var<storage, read> particles: array<Particle>;
// Particle indices, back to front for this view.
@group(1) @binding(3) var<storage, read> order: array<u32>;
@group(1) @binding(4) var<storage, read> lights: array<LightParams>;
@group(1) @binding(5) var<storage, read> optical_depth: array<f32>;
// Multiple scattering S_m per voxel of the density grid.
@group(1) @binding(6) var<storage, read> multiple: array<vec4<f32>>;

struct VertexOutput {
    @builtin(position) clip_position: vec4<f32>,
    @location(0) world_position: vec3<f32>,
    // World centre (xyz) and world radius (w).
    @location(1) @interpolate(flat) centre_radius: vec4<f32>,
    @location(2) @interpolate(flat) density: f32,
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
    let centre = (params.world_from_local * vec4(particle.position_radius.xyz, 1.0)).xyz;
    let radius = particle.position_radius.w * params.scale;
    let eye = view.world_position;
    let forward = -view.world_from_view[2].xyz;
    let right = view.world_from_view[0].xyz;
    let up = view.world_from_view[1].xyz;
    let to_centre = centre - eye;
    let depth = dot(to_centre, forward);

    var out: VertexOutput;
    out.centre_radius = vec4(centre, radius);
    out.density = particle.density.x;
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

// S_1 at a cloud-local point, straight from the light volumes (as gather.wgsl computes it).
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

// albedo (S_1 + S_m) at a cloud-local point.
fn scattered_at(p: vec3<f32>) -> vec3<f32> {
    let t = clamped_lookup(grid_coords(cloud, p), cloud.n);
    var s_m = vec3(0.0);
    for (var corner = 0u; corner < 8u; corner++) {
        s_m += corner_weight(t, corner) * multiple[clamped_corner(t, corner, cloud.n)].xyz;
    }
    return cloud.albedo * (single_scattering_at(p) + s_m);
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
    var s0 = -s1;
    if in.on_near_plane != 0u {
        let forward = -view.world_from_view[2].xyz;
        s0 = max(-s1, near_plane() / dot(w, forward) - t_c);
        if s0 >= s1 {
            discard;
        }
    }
    // The chord in equal segments, front to back: each adds its opacity times the light it
    // scatters, seen through the segments in front of it.
    let sigma = params.extinction * in.density;
    let ds = (s1 - s0) / f32(params.segments);
    var colour = vec3(0.0);
    var transmittance = 1.0;
    var depth_before = chord_integral(s0, q, radius);
    for (var k = 1u; k <= params.segments; k++) {
        let end = s0 + ds * f32(k);
        let depth_after = chord_integral(end, q, radius);
        let segment = opacity(max(sigma * (depth_after - depth_before), 0.0));
        let x = eye + (t_c + end - 0.5 * ds) * w;
        let local = (params.local_from_world * vec4(x, 1.0)).xyz;
        colour += transmittance * segment * scattered_at(local);
        transmittance *= 1.0 - segment;
        depth_before = depth_after;
    }
    let alpha = 1.0 - transmittance;
    return vec4(colour * view.exposure, alpha);
}
