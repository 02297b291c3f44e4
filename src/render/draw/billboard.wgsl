// The final render (the paper's Algorithm 3): each particle a camera-facing billboard in the
// Transparent3d phase. Alpha is exact per pixel: the optical depth of the view ray through the
// particle's kernel. The colour is the light scattered along that chord, cut into `segments`
// pieces (PHYSICS.md; docs/illumination.md §5). Two compositings:
// - VIEW_TRANSMITTANCE: `attenuate` multiplies what is behind by each particle's transmittance,
//   then `emit` adds each particle's light, seen through the optical depth towards the camera of
//   the cloud and of every cloud that may lie in front of it (view_volume.wgsl); both are
//   order-independent, so clouds that overlap on screen draw all their `attenuate`s first;
// - otherwise `fragment` blends particles whole, back to front in the sorted order.
#import bevy_render::view::View
//
// CLOUD_TARGET: drawn into the view's reduced-resolution cloud target, which has no depth
// attachment; each fragment is depth-tested here against the view pixel its texel stands for
// (cloud_target.wgsl enlarges the target onto the view).
//
// COMPUTE_DRAW (with CLOUD_TARGET and VIEW_TRANSMITTANCE): no rasteriser. `splat` evaluates the
// particles' fragments in a compute shader, over the target texels whose centres their
// rectangles cover, and adds their light and optical depth into per-texel sums; `resolve_splats` writes
// the sums into the cloud target as `accumulate`'s blending would have left it. Same image, but
// fragment shaders run this work many times slower on some GPUs (docs/performance.md, "On a real GPU").
//
// DISTANCE_FOG: every piece of every chord is fogged at its own distance (fog.wgsl).
#import bevy_particle_clouds::fog::{CloudFog, fog_colour, fogged}
#import bevy_particle_clouds::types::{Particle, CloudParams, LightParams, ViewVolumeParams, CloudTargetParams, grid_coords, henyey_greenstein, flux_element, quadrupole_element, phase_on_moments, light_coords, clamped_lookup, clamped_corner, corner_weight, opacity, voxel_index, view_volume_coords, front_map_index, view_columns, column_corner, cloud_target_depth_pixel}

struct DrawParams {
    world_from_local: mat4x4<f32>,
    local_from_world: mat4x4<f32>,
    // Uniform scale of the cloud (world metres per local metre).
    scale: f32,
    // Extinction K per world metre at density 1.
    extinction: f32,
    // Segments of each chord at which the illumination is evaluated.
    segments: u32,
    // 1: the illumination is evaluated once per particle, at its centre (the vertex shader's).
    centre_shading: u32,
}

@group(0) @binding(0) var<uniform> view: View;
#ifdef CLOUD_TARGET
@group(0) @binding(1) var<uniform> cloud_target: CloudTargetParams;
#ifdef MULTISAMPLED
@group(0) @binding(2) var scene_depth: texture_depth_multisampled_2d;
#else
@group(0) @binding(2) var scene_depth: texture_depth_2d;
#endif
@group(0) @binding(3) var<uniform> fog: CloudFog;
#ifdef COMPUTE_DRAW
// Per target texel: the light (r, g, b) and the particles' own optical depth, f32 bits.
@group(0) @binding(4) var<storage, read_write> sums: array<atomic<u32>>;
#ifdef BLENDED_CLOUD_TARGET
@group(0) @binding(5) var target_texels: texture_storage_2d<rgba32float, write>;
#else
@group(0) @binding(5) var target_texels: texture_storage_2d<rgba16float, write>;
#endif
// What decides whether this frame draws (`CloudRedraw`): [0] is non-zero when it does (1 when
// the CPU cannot rule out a change, else set by `compare_depth`); [1 + i] is the depth that
// target texel i's particles were last tested against, f32 bits.
@group(0) @binding(6) var<storage, read_write> still: array<atomic<u32>>;
#endif
#else
@group(0) @binding(1) var<uniform> fog: CloudFog;
#endif
// Where a cloud's elements start in the arrays below: 0 when the arrays are the cloud's own
// ranges (the rasterised draw binds them so); a batch's clouds share whole buffers.
struct CloudBases {
    lights: u32,
    optical_depth: u32,
    multiple: u32,
}
var<private> bases: CloudBases;
#ifdef COMPUTE_DRAW
// One cloud of a splat batch (splat.rs, `SplatCloud`): every cloud of one volume pool and medium
// that a view splats, in one dispatch. `load_splat_cloud` sets the private copies of its uniforms.
struct SplatCloud {
    draw: DrawParams,
    cloud: CloudParams,
    // Its particles start at `first_group * SPLAT_PARTICLES` of `particles`.
    first_group: u32,
    particle_count: u32,
    // Its element of `view_volumes`.
    view_volume: u32,
    bases: CloudBases,
}
@group(1) @binding(0) var<storage, read> splat_clouds: array<SplatCloud>;
var<private> params: DrawParams;
var<private> cloud: CloudParams;
var<private> view_volume: ViewVolumeParams;
#else
@group(1) @binding(0) var<uniform> params: DrawParams;
@group(1) @binding(1) var<uniform> cloud: CloudParams;
#endif
@group(1) @binding(2) var<storage, read> particles: array<Particle>;
#ifdef VIEW_TRANSMITTANCE
#ifndef COMPUTE_DRAW
@group(1) @binding(3) var<uniform> view_volume: ViewVolumeParams;
#endif
#else
// Particle indices, back to front for this view.
@group(1) @binding(3) var<storage, read> order: array<u32>;
#endif
@group(1) @binding(4) var<storage, read> lights: array<LightParams>;
@group(1) @binding(5) var<storage, read> optical_depth: array<f32>;
// Multiple scattering S_m per voxel of the density grid (its means; with moments, then its flux
// and its quadrupole); through the view transmittance, an anisotropic cloud's S_m seen from the
// camera instead, the view's volumes of them from `view_volume.seen_offset` (view_volume.wgsl).
@group(1) @binding(6) var<storage, read> multiple: array<vec4<f32>>;
#ifdef VIEW_TRANSMITTANCE
// Optical depth from the camera at the nodes of every view volume of this view, each from its
// `offset`; the volumes themselves; and the neighbour lists (indices into `view_volumes`).
@group(1) @binding(7) var<storage, read> view_optical_depth: array<f32>;
@group(1) @binding(8) var<storage, read> view_volumes: array<ViewVolumeParams>;
@group(1) @binding(9) var<storage, read> neighbours: array<u32>;
#endif
// The spread of the delta-M beam's excess relative to the phase function,
// BEAM_PHASE_ANGLES x BEAM_PHASE_DEPTHS, angle-major (src/beam_phase.rs); one element when the
// medium has no excess.
#ifdef VIEW_TRANSMITTANCE
@group(1) @binding(10) var<storage, read> beam_phase: array<f32>;
#else
@group(1) @binding(7) var<storage, read> beam_phase: array<f32>;
#endif

struct VertexOutput {
    @builtin(position) clip_position: vec4<f32>,
    @location(0) world_position: vec3<f32>,
    // World centre (xyz) and world radius (w).
    @location(1) @interpolate(flat) centre_radius: vec4<f32>,
    @location(2) @interpolate(flat) density: f32,
    // 1 when the billboard sits on the near plane (the particle reaches it).
    @location(3) @interpolate(flat) on_near_plane: u32,
    // With centre shading: albedo (S_1 + S_m) at the particle's centre towards the camera.
    @location(4) @interpolate(flat) centre_light: vec3<f32>,
}

fn near_plane() -> f32 {
    return view.clip_from_view[3][2];
}

// The extent, in units of lateral offset / depth, of the part beyond the near plane of a sphere
// of radius `r` whose centre lies at lateral offset `x` and depth `z` along one screen axis:
// the sphere projected on that axis's plane with the view direction is the disc of (x, z), and
// x / z is extreme on that disc's part beyond the near plane where the eye's tangents touch it
// or where its edge crosses the near plane (there alone when the eye lies within the disc).
// Clamped to `screen`, the view's half-extent.
fn screen_span(x: f32, z: f32, r: f32, screen: f32) -> vec2<f32> {
    let near = near_plane();
    let d2 = x * x + z * z;
    var span = vec2(screen, -screen);
    if d2 > r * r {
        // The tangent points, scaled by d2 / t: (t x -+ r z, t z +- r x).
        let t = sqrt(d2 - r * r);
        for (var side = -1.0; side <= 1.0; side += 2.0) {
            let p = vec2(t * x - side * r * z, t * z + side * r * x);
            if p.y * t / d2 >= near {
                span = vec2(min(span.x, p.x / p.y), max(span.y, p.x / p.y));
            }
        }
    }
    // Where the disc's edge crosses the near plane.
    let h = r * r - (near - z) * (near - z);
    if h > 0.0 {
        let e = sqrt(h);
        span = vec2(min(span.x, (x - e) / near), max(span.y, (x + e) / near));
    }
    // Nothing found (only by rounding): an empty span, not an inverted one.
    return clamp(vec2(span.x, max(span.x, span.y)), vec2(-screen), vec2(screen));
}

// A particle's billboard in this view: the rectangle of the screen that the part of its sphere
// beyond the near plane covers (0.1 % of it to spare either side for rounding), in units of
// lateral offset / depth along the view's right (`span_x`) and up (`span_y`) axes.
struct Billboard {
    centre: vec3<f32>,
    radius: f32,
    density: f32,
    // Along the view direction, from the eye to the centre.
    depth: f32,
    span_x: vec2<f32>,
    span_y: vec2<f32>,
    // Entirely behind the near plane: nothing to draw.
    behind: bool,
    // Reaches the near plane (or holds the camera): the billboard lies on the near plane, and
    // the fragments integrate only the part of each ray's chord beyond it.
    on_near_plane: bool,
}

fn billboard(index: u32) -> Billboard {
    let particle = particles[index];
    var b: Billboard;
    b.centre = (params.world_from_local * vec4(particle.position_radius.xyz, 1.0)).xyz;
    b.radius = particle.position_radius.w * params.scale;
    b.density = particle.density.x;
    let to_centre = b.centre - view.world_position;
    b.depth = dot(to_centre, -view.world_from_view[2].xyz);
    b.behind = b.depth + b.radius <= near_plane();
    b.on_near_plane = b.depth - b.radius < near_plane();
    let screen = 1.01 / vec2(view.clip_from_view[0][0], view.clip_from_view[1][1]);
    let span_x = screen_span(dot(to_centre, view.world_from_view[0].xyz), b.depth, b.radius, screen.x);
    let span_y = screen_span(dot(to_centre, view.world_from_view[1].xyz), b.depth, b.radius, screen.y);
    let pad = 0.001 * vec2(span_x.y - span_x.x, span_y.y - span_y.x);
    b.span_x = span_x + vec2(-pad.x, pad.x);
    b.span_y = span_y + vec2(-pad.y, pad.y);
    return b;
}

// The billboard's world point at `slope` (lateral offset / depth along right and up): in the
// plane at the particle's depth, or on the near plane.
fn billboard_point(b: Billboard, slope: vec2<f32>) -> vec3<f32> {
    let along = -view.world_from_view[2].xyz + slope.x * view.world_from_view[0].xyz
        + slope.y * view.world_from_view[1].xyz;
    return view.world_position + select(b.depth, near_plane(), b.on_near_plane) * along;
}

// The billboard's depth in the depth buffer's terms (reverse Z) at world point `world`.
fn billboard_depth(b: Billboard, world: vec3<f32>) -> f32 {
    if b.on_near_plane {
        return 1.0;
    }
    let clip = view.clip_from_world * vec4(world, 1.0);
    return clip.z / clip.w;
}

// What every fragment of a particle's billboard shares but its centre's light.
fn flat_output_unshaded(b: Billboard) -> VertexOutput {
    var out: VertexOutput;
    out.centre_radius = vec4(b.centre, b.radius);
    out.density = b.density;
    out.on_near_plane = u32(b.on_near_plane);
    out.centre_light = vec3(0.0);
    return out;
}

// What every fragment of a particle's billboard shares.
fn flat_output(index: u32, b: Billboard) -> VertexOutput {
    var out = flat_output_unshaded(b);
#ifndef ALPHA_ONLY
    if params.centre_shading != 0u {
        let local = particles[index].position_radius.xyz;
        let ray = normalize((params.local_from_world * vec4(b.centre - view.world_position, 0.0)).xyz);
        out.centre_light = scattered_at(local, ray);
    }
#endif
    return out;
}

@vertex
fn vertex(@builtin(vertex_index) vertex_index: u32, @builtin(instance_index) instance_index: u32) -> VertexOutput {
    // A four-vertex triangle strip per instance: (-1,-1), (1,-1), (-1,1), (1,1).
    let corner = vec2(f32(vertex_index & 1u), f32(vertex_index >> 1u));
#ifdef VIEW_TRANSMITTANCE
    let index = instance_index;
#else
    let index = order[instance_index];
#endif
    let b = billboard(index);
    var out = flat_output(index, b);
    if b.behind {
        // A degenerate triangle, culled before rasterisation.
        out.clip_position = vec4(2.0, 2.0, 2.0, 1.0);
        out.world_position = b.centre;
        return out;
    }
    let slope = vec2(mix(b.span_x.x, b.span_x.y, corner.x), mix(b.span_y.x, b.span_y.y, corner.y));
    out.world_position = billboard_point(b, slope);
    let clip = view.clip_from_world * vec4(out.world_position, 1.0);
    if b.on_near_plane {
        out.clip_position = vec4(clip.xy / clip.w, 1.0, 1.0);
    } else {
        out.clip_position = clip;
    }
    return out;
}

// Integral of (q - s^2/R^2)^2 ds: the kernel along the ray, s from the closest point.
fn chord_integral(s: f32, q: f32, r: f32) -> f32 {
    let x = s / r;
    return r * (q * q * x - 2.0 * q * x * x * x / 3.0 + x * x * x * x * x / 5.0);
}

// The spread of the beam's excess at cosine `cos` between the light's travel direction and the
// direction towards the camera, `m` peak scatterings on average: bilinear in the table, sampled
// at sin(theta / 2) and m / (m + 1) (BeamPhase::ratio).
fn beam_spread(cos: f32, m: f32) -> f32 {
    let x = min(sqrt(max(0.5 - 0.5 * cos, 0.0)), 1.0) * f32(#{BEAM_PHASE_ANGLES}u - 1u);
    let depth = clamp(m, 0.0, 1e20);
    let y = depth / (depth + 1.0) * f32(#{BEAM_PHASE_DEPTHS}u - 1u);
    let i = min(u32(x), #{BEAM_PHASE_ANGLES}u - 2u);
    let j = min(u32(y), #{BEAM_PHASE_DEPTHS}u - 2u);
    let f = vec2(x - f32(i), y - f32(j));
    let row = i * #{BEAM_PHASE_DEPTHS}u + j;
    let near = mix(beam_phase[row], beam_phase[row + 1u], f.y);
    let far = mix(beam_phase[row + #{BEAM_PHASE_DEPTHS}u], beam_phase[row + #{BEAM_PHASE_DEPTHS}u + 1u], f.y);
    return mix(near, far, f.x);
}

// S_1 at a cloud-local point towards the camera, straight from the light volumes: each light's
// share weighted by the phase function between its travel direction and -ray, `ray` the view
// ray's cloud-local unit direction. Its beam goes through `depth_scale` of the optical depth
// (the delta-M beam; 1 for an isotropic medium), and the excess over the light that
// never scattered is seen spread by the peak scatterings it took (docs/illumination.md §5).
fn single_scattering_at(p: vec3<f32>, ray: vec3<f32>) -> vec3<f32> {
    var sum = vec3(0.0);
    for (var l = 0u; l < cloud.light_count; l++) {
        let light = lights[bases.lights + l];
        let t = clamped_lookup(light_coords(cloud, light, p), cloud.light_n);
        let first = bases.optical_depth + light.offset;
        var tau = 0.0;
        for (var corner = 0u; corner < 8u; corner++) {
            tau += corner_weight(t, corner) * optical_depth[first + clamped_corner(t, corner, cloud.light_n)];
        }
        let cos = -dot(light.w, ray);
        let phase = henyey_greenstein(cloud.anisotropy, cos);
        var beam = exp(-tau);
        if cloud.depth_scale < 1.0 {
            let excess = exp(-tau * cloud.depth_scale) - beam;
            beam += excess * beam_spread(cos, tau * (1.0 - cloud.depth_scale));
        }
        sum += light.irradiance * (beam * phase);
    }
    return sum;
}

// Whether `multiple` holds the cloud's S_m seen from the camera (docs/illumination.md §5), and
// its first element.
#ifdef VIEW_TRANSMITTANCE
fn seen_from_camera() -> bool {
    return view_volume.seen_n > 0u;
}

fn first_multiple() -> u32 {
    return select(bases.multiple, view_volume.seen_offset, seen_from_camera());
}
#else
fn seen_from_camera() -> bool {
    return false;
}

fn first_multiple() -> u32 {
    return bases.multiple;
}
#endif

// S_m at a cloud-local point towards the unit direction w: its mean, and with moments the
// Henyey-Greenstein phase function on its first three angular moments,
// max(mean + 3 g F . w + (15/2) g^2 w^T Q w, 0) (docs/illumination.md §5); all trilinear. Seen
// from the camera, the volume holds that towards the camera already.
fn multiple_towards(p: vec3<f32>, w: vec3<f32>) -> vec3<f32> {
    let t = clamped_lookup(grid_coords(cloud, p), cloud.n);
    let n = cloud.n;
    let first = first_multiple();
    var s_m = vec3(0.0);
    for (var corner = 0u; corner < 8u; corner++) {
        s_m += corner_weight(t, corner) * multiple[first + clamped_corner(t, corner, n)].xyz;
    }
    // The cycles' last sweep may leave S_m a relative 1e-4 below 0 beside a sharp edge of the
    // light; summed in f32 over thousands of particles that would show as a negative pixel.
    if cloud.moments == 0u || seen_from_camera() {
        return max(s_m, vec3(0.0));
    }
    var flux = array<vec3<f32>, 3>();
    var quadrupole = array<vec3<f32>, 5>();
    for (var corner = 0u; corner < 8u; corner++) {
        let i = clamped_corner(t, corner, n);
        let weight = corner_weight(t, corner);
        for (var axis = 0u; axis < 3u; axis++) {
            flux[axis] += weight * multiple[flux_element(first, n, i, axis)].xyz;
        }
        for (var c = 0u; c < 5u; c++) {
            quadrupole[c] += weight * multiple[quadrupole_element(first, n, i, c)].xyz;
        }
    }
    return max(s_m + phase_on_moments(cloud.anisotropy, w, flux, quadrupole), vec3(0.0));
}

// albedo (S_1 + S_m) at a cloud-local point, seen along `ray`.
fn scattered_at(p: vec3<f32>, ray: vec3<f32>) -> vec3<f32> {
    return cloud.albedo * (single_scattering_at(p, ray) + multiple_towards(p, -ray));
}

// albedo (S_1 + S_m) for chord point s: evaluated there, or with centre shading the particle's
// (BillboardShading::Centre; a uniform branch).
fn shading_point(in: VertexOutput, c: Chord, s: f32, ray: vec3<f32>) -> vec3<f32> {
    if params.centre_shading != 0u {
        return in.centre_light;
    }
    return scattered_at(local_at(c, s), ray);
}

// The chord's ray direction in cloud-local space (unit).
fn local_ray(c: Chord) -> vec3<f32> {
    return normalize((params.local_from_world * vec4(c.w, 0.0)).xyz);
}

// The visible part of a pixel's ray through a particle: s runs along the unit ray w from the
// point closest to the centre (at ray parameter t_c), the chord covers s0..s1, q = 1 - b^2/R^2.
struct Chord {
    w: vec3<f32>,
    t_c: f32,
    q: f32,
    s0: f32,
    s1: f32,
    radius: f32,
    // Extinction per world metre inside the particle at its peak.
    sigma: f32,
    // False when the ray misses the particle or sees none of it beyond the near plane.
    seen: bool,
}

// Whether opaque geometry hides the fragment (reverse Z: nearer is greater); the depth
// attachment does this test when drawing at full size.
fn occluded(position: vec4<f32>) -> bool {
#ifdef CLOUD_TARGET
    let pixel = cloud_target_depth_pixel(cloud_target, vec2<u32>(floor(position.xy)));
    return position.z < textureLoad(scene_depth, pixel, 0);
#else
    return false;
#endif
}

fn chord(in: VertexOutput) -> Chord {
    var c: Chord;
    let eye = view.world_position;
    c.w = normalize(in.world_position - eye);
    c.radius = in.centre_radius.w;
    c.sigma = params.extinction * in.density;
    let to_centre = in.centre_radius.xyz - eye;
    c.t_c = dot(to_centre, c.w);
    let closest = to_centre - c.t_c * c.w;
    c.q = 1.0 - dot(closest, closest) / (c.radius * c.radius);
    c.seen = c.q > 0.0 && !occluded(in.clip_position);
    c.s1 = c.radius * sqrt(max(c.q, 0.0));
    c.s0 = -c.s1;
    if in.on_near_plane != 0u {
        let forward = -view.world_from_view[2].xyz;
        c.s0 = max(-c.s1, near_plane() / dot(c.w, forward) - c.t_c);
        c.seen = c.seen && c.s0 < c.s1;
    }
    return c;
}

// The particle's own optical depth along the chord from s0 to s.
fn own_depth(c: Chord, s: f32) -> f32 {
    return max(c.sigma * (chord_integral(s, c.q, c.radius) - chord_integral(c.s0, c.q, c.radius)), 0.0);
}

fn world_at(c: Chord, s: f32) -> vec3<f32> {
    return view.world_position + (c.t_c + s) * c.w;
}

fn local_at(c: Chord, s: f32) -> vec3<f32> {
    return (params.local_from_world * vec4(world_at(c, s), 1.0)).xyz;
}

// The fog's colour along the chord's ray (unused without fog).
fn ray_fog_colour(c: Chord) -> vec3<f32> {
#ifdef DISTANCE_FOG
    return fog_colour(fog, c.w, view.exposure);
#else
    return vec3(0.0);
#endif
}

// A piece of the chord's light as the image shows it: `light` (premultiplied, before exposure)
// covering `coverage` of the view at chord parameter s, exposed, then fogged at its distance
// with the fog colour `f`.
fn shown(c: Chord, light: vec3<f32>, coverage: f32, s: f32, f: vec3<f32>) -> vec3<f32> {
#ifdef DISTANCE_FOG
    return fogged(fog, light * view.exposure, coverage, c.t_c + s, f);
#else
    return light * view.exposure;
#endif
}

#ifdef VIEW_TRANSMITTANCE
// Optical depth from the camera to view-space point `p` through view volume `k`: trilinear,
// clamped to the volume. None in front of its first slice (which holds 0) or off its rectangle of
// rays (whose edges only graze its cloud's cube): most neighbours of most pixels are skipped
// after reading those two fields.
fn optical_depth_through(k: u32, p: vec3<f32>) -> f32 {
    let depth = -p.z;
    let rect = view_volumes[k].rect;
    let uv = p.xy / depth;
    if depth <= view_volumes[k].depth.x || any(uv < rect.xz) || any(uv > rect.yw) {
        return 0.0;
    }
    let volume = view_volumes[k];
    let n = volume.n;
    let g = view_volume_coords(volume, p);
    let base = min(vec3<u32>(floor(g)), vec3(n - 2u));
    let f = g - vec3<f32>(base);
    var tau = 0.0;
    for (var corner = 0u; corner < 8u; corner++) {
        let o = vec3<u32>(corner & 1u, (corner >> 1u) & 1u, corner >> 2u);
        let w = select(1.0 - f, f, vec3<bool>(o));
        tau += w.x * w.y * w.z * view_optical_depth[volume.offset + voxel_index(base + o, n)];
    }
    return tau;
}

// Optical depth along the whole ray of tangent `uv` through view volume `k`: bilinear in its
// last slice; none off its rectangle of rays.
fn optical_depth_along(k: u32, uv: vec2<f32>) -> f32 {
    let rect = view_volumes[k].rect;
    if any(uv < rect.xz) || any(uv > rect.yw) {
        return 0.0;
    }
    let volume = view_volumes[k];
    let n = volume.n;
    let columns = view_columns(volume, uv);
    var tau = 0.0;
    for (var c = 0u; c < 4u; c++) {
        let corner = column_corner(columns, c);
        tau += corner.weight * view_optical_depth[volume.offset + voxel_index(vec3(corner.column, n - 1u), n)];
    }
    return tau;
}

// Optical depth along the ray of tangent `uv` of the neighbours wholly in front of this cloud's
// volume: its front map (view_volume.wgsl, `sum_front`), bilinear.
fn front_optical_depth(uv: vec2<f32>) -> f32 {
    if view_volume.front_count == 0u {
        return 0.0;
    }
    let columns = view_columns(view_volume, uv);
    var tau = 0.0;
    for (var c = 0u; c < 4u; c++) {
        let corner = column_corner(columns, c);
        tau += corner.weight * view_optical_depth[front_map_index(view_volume, corner.column)];
    }
    return tau;
}

// What the cloud's neighbours hold along one pixel's chord: `front`, the optical depth of those
// wholly in front of the chord (the front map's, for those in front of the whole volume; then
// those whose last slice lies before the chord's near end: all of their depth along the ray is
// in front of every point of it), and `mask`, bit j set for the j-th other neighbour (j < 32)
// that overlaps the chord in depth and holds some optical depth along the ray (those past 32 are
// always looked up). A column of nodes' optical depth grows with depth, so one that is 0 at the
// last slice is 0 all along: what is left out adds exactly nothing. So each chord point looks up
// only the clouds that interpenetrate it, and the others cost at most one bilinear read per pixel.
struct RayNeighbours {
    front: f32,
    mask: u32,
}

fn neighbours_along(c: Chord) -> RayNeighbours {
    let near = (view.view_from_world * vec4(world_at(c, c.s0), 1.0)).xyz;
    let far = -(view.view_from_world * vec4(world_at(c, c.s1), 1.0)).z;
    let uv = near.xy / -near.z;
    var r = RayNeighbours(front_optical_depth(uv), 0u);
    let others = view_volume.neighbour_count - view_volume.front_count;
    for (var j = 0u; j < min(others, 32u); j++) {
        let k = neighbours[view_volume.first_neighbour + view_volume.front_count + j];
        let depth = view_volumes[k].depth;
        if depth.x >= far {
            continue;
        }
        let along = optical_depth_along(k, uv);
        if along <= 0.0 {
            continue;
        }
        if depth.y <= -near.z {
            r.front += along;
        } else {
            r.mask |= 1u << j;
        }
    }
    return r;
}

// Optical depth from the camera to a world point of a chord: through this cloud and every cloud
// that may be in front of it (its neighbours, this cloud's own volume among them), as
// `neighbours_along` sorted them for the chord.
fn view_optical_depth_at(x: vec3<f32>, r: RayNeighbours) -> f32 {
    let p = (view.view_from_world * vec4(x, 1.0)).xyz;
    var tau = r.front;
    let others = view_volume.neighbour_count - view_volume.front_count;
    for (var j = 0u; j < others; j++) {
        if j < 32u && (r.mask & (1u << j)) == 0u {
            continue;
        }
        tau += optical_depth_through(neighbours[view_volume.first_neighbour + view_volume.front_count + j], p);
    }
    return tau;
}

// (1 - exp(-x)) / x, 1 at 0: the mean of exp(-x t) over t in [0, 1].
fn mean_attenuation(x: f32) -> f32 {
    if abs(x) < 1e-3 {
        return 1.0 - 0.5 * x;
    }
    return -expm1_neg(x) / x;
}

// exp(-x) - 1 without cancellation for small x.
fn expm1_neg(x: f32) -> f32 {
    if abs(x) < 0.02 {
        return -x * (1.0 - x * (0.5 - x / 6.0));
    }
    return exp(-x) - 1.0;
}

// Mean of S over a segment of optical depth tau, log-linear from a to b, weighted by what each of
// its points shows through the segment: a g(tau + beta) / g(tau), beta = ln(a / b), per channel;
// a channel zero at either end is taken linear.
fn segment_mean(a: vec3<f32>, b: vec3<f32>, tau: f32) -> vec3<f32> {
    let g = mean_attenuation(tau);
    let far = select((1.0 / g - 1.0) / tau, 0.5, tau < 1e-3);
    var mean = a + (b - a) * far;
    for (var i = 0u; i < 3u; i++) {
        if a[i] > 0.0 && b[i] > 0.0 {
            let beta = clamp(log(a[i] / b[i]), -40.0, 40.0);
            mean[i] = a[i] * mean_attenuation(tau + beta) / g;
        }
    }
    return mean;
}

// Multiplies what is behind by the particle's transmittance.
@fragment
fn attenuate(in: VertexOutput) -> @location(0) vec4<f32> {
    let c = chord(in);
    if !c.seen {
        discard;
    }
    return vec4(0.0, 0.0, 0.0, opacity(own_depth(c, c.s1)));
}

// Adds the particle's light.
@fragment
fn emit(in: VertexOutput) -> @location(0) vec4<f32> {
    let c = chord(in);
    if !c.seen {
        discard;
    }
    return vec4(emitted(in, c), 0.0);
}

// Into a cloud target, which holds only clouds (cleared to no cloud), both at once: the light
// adds up, the alpha channel accumulates 1 - the product of the transmittances (see
// `BillboardBlend::Accumulate`). One draw instead of two.
@fragment
fn accumulate(in: VertexOutput) -> @location(0) vec4<f32> {
    let c = chord(in);
    if !c.seen {
        discard;
    }
    return vec4(emitted(in, c), opacity(own_depth(c, c.s1)));
}

// The particle's light as the image shows it: piece k of the chord adds
// mean S * tau_k / tau_all * exp(-tau_view(a_k)) * (1 - exp(-tau_all)), tau_all the piece's
// optical depth with every particle (the view volume's, at least the particle's own tau_k),
// exposed and fogged at its midpoint.
fn emitted(in: VertexOutput, c: Chord) -> vec3<f32> {
    let ds = (c.s1 - c.s0) / f32(params.segments);
    var light = vec3(0.0);
    var own_before = 0.0;
    let ray = neighbours_along(c);
    var view_before = view_optical_depth_at(world_at(c, c.s0), ray);
    let direction = local_ray(c);
    var s_before = shading_point(in, c, c.s0, direction);
    let f = ray_fog_colour(c);
    for (var k = 1u; k <= params.segments; k++) {
        let end = c.s0 + ds * f32(k);
        let own_after = own_depth(c, end);
        let tau = max(own_after - own_before, 0.0);
        let view_after = view_optical_depth_at(world_at(c, end), ray);
        let s_after = shading_point(in, c, end, direction);
        let all = max(view_after - view_before, tau);
        let coverage = tau * exp(-view_before) * mean_attenuation(all);
        let piece = segment_mean(s_before, s_after, all) * coverage;
        light += shown(c, piece, coverage, end - 0.5 * ds, f);
        own_before = own_after;
        view_before = view_after;
        s_before = s_after;
    }
    return light;
}
#else
// Blends the particle whole: the chord in equal segments, front to back, each adds its opacity
// times the light it scatters at its midpoint, seen through the segments in front of it.
@fragment
fn fragment(in: VertexOutput) -> @location(0) vec4<f32> {
    let c = chord(in);
    if !c.seen {
        discard;
    }
    let ds = (c.s1 - c.s0) / f32(params.segments);
    var colour = vec3(0.0);
    var transmittance = 1.0;
    var depth_before = 0.0;
    let direction = local_ray(c);
    let f = ray_fog_colour(c);
    for (var k = 1u; k <= params.segments; k++) {
        let end = c.s0 + ds * f32(k);
        let middle = end - 0.5 * ds;
        let depth_after = own_depth(c, end);
        let coverage = transmittance * opacity(max(depth_after - depth_before, 0.0));
        let piece = coverage * shading_point(in, c, middle, direction);
        colour += shown(c, piece, coverage, middle, f);
        transmittance -= coverage;
        depth_before = depth_after;
    }
    let alpha = 1.0 - transmittance;
    return vec4(colour, alpha);
}
#endif

#ifdef COMPUTE_DRAW
// Adds `v` to the f32 whose bits `sums[i]` holds (WGSL has no float atomics): retried until no
// other invocation wrote in between. The same loop as voxelize's `add_density`: one function
// taking the atomic by pointer would serve both, but naga_oil rejects a storage pointer as a
// parameter of a shared module's function.
fn add_to_sum(i: u32, v: f32) {
    if v == 0.0 {
        return;
    }
    var old = atomicLoad(&sums[i]);
    loop {
        let swap = atomicCompareExchangeWeak(&sums[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if swap.exchanged {
            break;
        }
        old = swap.old_value;
    }
}

// The target texels whose centres the billboard's rectangle covers, as a rasteriser takes them:
// (first x, first y, last x, last y), empty where a last is below its first.
fn covered_texels(b: Billboard) -> vec4<i32> {
    let size = vec2<f32>(cloud_target.target_size);
    let ndc_x = b.span_x * view.clip_from_view[0][0];
    let ndc_y = b.span_y * view.clip_from_view[1][1];
    // Texel t's centre lies at ndc x = 2 (t + 0.5) / size - 1, and y the other way up.
    let x = (ndc_x + 1.0) * 0.5 * size.x - 0.5;
    let y = (1.0 - ndc_y.yx) * 0.5 * size.y - 0.5;
    let first = max(vec2<i32>(ceil(vec2(x.x, y.x))), vec2(0));
    let last = min(vec2<i32>(floor(vec2(x.y, y.y))), vec2<i32>(size) - 1);
    return vec4(first, last);
}

// Texel t's centre in units of lateral offset / depth.
fn texel_slope(t: vec2<i32>) -> vec2<f32> {
    let ndc = (vec2<f32>(t) + 0.5) / vec2<f32>(cloud_target.target_size) * vec2(2.0, -2.0) + vec2(-1.0, 1.0);
    return ndc / vec2(view.clip_from_view[0][0], view.clip_from_view[1][1]);
}

// Particles per splat workgroup, one per invocation (`workgroups::LINEAR` in Rust).
const SPLAT_PARTICLES: u32 = #{LINEAR_WORKGROUP}u;

// `still[0]` as the splat's workgroup reads it once.
var<workgroup> redraw: u32;

// Per particle of the workgroup: the texels it covers, and after the scan the running count of
// texels up to and including it; its light with centre shading.
var<workgroup> covered: array<vec4<i32>, SPLAT_PARTICLES>;
var<workgroup> texels_through: array<u32, SPLAT_PARTICLES>;
var<workgroup> centre_lights: array<vec3<f32>, SPLAT_PARTICLES>;

// The workgroup's particle whose texels hold pair `k`: the first whose running count exceeds it.
fn particle_of_pair(k: u32) -> u32 {
    var lo = 0u;
    var hi = SPLAT_PARTICLES - 1u;
    while lo < hi {
        let mid = (lo + hi) / 2u;
        if texels_through[mid] > k {
            hi = mid;
        } else {
            lo = mid + 1u;
        }
    }
    return lo;
}

// Makes the batch's cloud that workgroup `g` draws the one the shading functions read (the last
// whose first workgroup is at most `g`), and returns the end of its particles.
fn load_splat_cloud(g: u32) -> u32 {
    var lo = 0u;
    var hi = arrayLength(&splat_clouds) - 1u;
    while lo < hi {
        let mid = (lo + hi + 1u) / 2u;
        if splat_clouds[mid].first_group <= g {
            lo = mid;
        } else {
            hi = mid - 1u;
        }
    }
    let c = splat_clouds[lo];
    params = c.draw;
    cloud = c.cloud;
    view_volume = view_volumes[c.view_volume];
    bases = c.bases;
    return c.first_group * SPLAT_PARTICLES + c.particle_count;
}

// One workgroup per SPLAT_PARTICLES particles of a cloud and z slice (a workgroup never holds two
// clouds' particles). Each invocation finds its particle's
// texels; a scan of their counts lays every (particle, texel) pair of the workgroup end to end,
// and the invocations take the pairs 64 at a time, dealt out over the slices: small particles
// fill the invocations as well as large ones. Each pair is shaded as `accumulate` would shade it.
@compute @workgroup_size(SPLAT_PARTICLES)
fn splat(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    if lane == 0u {
        redraw = atomicLoad(&still[0]);
    }
    // A still view keeps its target: every workgroup leaves at once.
    if workgroupUniformLoad(&redraw) == 0u {
        return;
    }
    let g = group.x + group.y * groups.x;
    let end = load_splat_cloud(g);
    let first = g * SPLAT_PARTICLES;
    let index = first + lane;
    var rect = vec4(0, 0, -1, -1);
    var count = 0u;
    if index < end {
        let b = billboard(index);
        let texels = covered_texels(b);
        if !b.behind && all(texels.zw >= texels.xy) {
            rect = texels;
            let extent = vec2<u32>(texels.zw - texels.xy) + 1u;
            count = extent.x * extent.y;
            centre_lights[lane] = flat_output(index, b).centre_light;
        }
    }
    covered[lane] = rect;
    texels_through[lane] = count;
    // Inclusive scan of the counts (Hillis-Steele).
    for (var offset = 1u; offset < SPLAT_PARTICLES; offset *= 2u) {
        workgroupBarrier();
        let before = select(0u, texels_through[max(lane, offset) - offset], lane >= offset);
        workgroupBarrier();
        texels_through[lane] += before;
    }
    workgroupBarrier();
    let total = texels_through[SPLAT_PARTICLES - 1u];
    for (var k = group.z * SPLAT_PARTICLES + lane; k < total; k += groups.z * SPLAT_PARTICLES) {
        let p = particle_of_pair(k);
        let r = covered[p];
        let start = select(0u, texels_through[max(p, 1u) - 1u], p > 0u);
        let width = u32(r.z - r.x) + 1u;
        let t = r.xy + vec2<i32>(vec2((k - start) % width, (k - start) / width));
        let b = billboard(first + p);
        var in = flat_output_unshaded(b);
        in.centre_light = centre_lights[p];
        in.world_position = billboard_point(b, texel_slope(t));
        in.clip_position = vec4(vec2<f32>(t) + 0.5, billboard_depth(b, in.world_position), 1.0);
        let c = chord(in);
        if !c.seen {
            continue;
        }
        let light = emitted(in, c);
        let i = 4u * (u32(t.y) * cloud_target.target_size.x + u32(t.x));
        add_to_sum(i, light.r);
        add_to_sum(i + 1u, light.g);
        add_to_sum(i + 2u, light.b);
        add_to_sum(i + 3u, own_depth(c, c.s1));
    }
}

// Before the splat: the depth each target texel's particles are tested against (`occluded`),
// kept for the next frame; where it differs from the last frame's, this frame draws.
@compute @workgroup_size(#{SLICE_WORKGROUP}, #{SLICE_WORKGROUP}, 1)
fn compare_depth(@builtin(global_invocation_id) id: vec3<u32>) {
    if any(id.xy >= cloud_target.target_size) {
        return;
    }
    let depth = textureLoad(scene_depth, cloud_target_depth_pixel(cloud_target, id.xy), 0);
    let i = 1u + id.y * cloud_target.target_size.x + id.x;
    if atomicExchange(&still[i], bitcast<u32>(depth)) != bitcast<u32>(depth) {
        atomicStore(&still[0], 1u);
    }
}

// The sums into the cloud target: the light, and 1 - the product of the transmittances. The
// sums are left at zero for the next frame's splat.
@compute @workgroup_size(#{SLICE_WORKGROUP}, #{SLICE_WORKGROUP}, 1)
fn resolve_splats(@builtin(global_invocation_id) id: vec3<u32>) {
    if any(id.xy >= cloud_target.target_size) || atomicLoad(&still[0]) == 0u {
        return;
    }
    let i = 4u * (id.y * cloud_target.target_size.x + id.x);
    var sum: array<f32, 4>;
    for (var k = 0u; k < 4u; k++) {
        sum[k] = bitcast<f32>(atomicExchange(&sums[i + k], 0u));
    }
    let light = vec3(sum[0], sum[1], sum[2]);
    textureStore(target_texels, id.xy, vec4(light, opacity(sum[3])));
}
#endif
