// Types and small helpers shared by every pass of bevy_particle_clouds.
// The Rust mirrors are in src/render/plan/volumes.rs (`CloudParams`, `LightParams`, `SweepDirection`)
// and src/render/extract/particles.rs (`GpuParticle`). Discretization: docs/illumination.md.
#define_import_path bevy_particle_clouds::types

const PI: f32 = 3.141592653589793;
// Integral of the kernel (1 - u^2)^2 over the unit ball: 32 pi / 105.
const KERNEL_VOLUME: f32 = 0.9574532925;

struct Particle {
    // Cloud-local centre (xyz, metres) and radius (w, metres).
    position_radius: vec4<f32>,
    // Density in x.
    density: vec4<f32>,
}

struct CloudParams {
    // Voxels per side N of the density and scattering volumes.
    n: u32,
    particle_count: u32,
    // Voxels per side m of the fine density grid and of each light's optical-depth volume, over
    // the same cube as the scattering grid; any m >= N (the gather weighs overlaps).
    light_n: u32,
    // Lights in the `lights` array (and volumes in the optical-depth buffer).
    light_count: u32,
    // Corner of the density cube, cloud-local metres.
    grid_origin: vec3<f32>,
    // Voxel size, cloud-local metres.
    h: f32,
    grid_centre: vec3<f32>,
    // Extinction per cloud-local metre at density 1 (K times the cloud's scale).
    k_local: f32,
    albedo: f32,
    forward_scattering: f32,
    // Henyey-Greenstein g of the scattering towards the camera.
    anisotropy: f32,
    // The medium's delta-M transform (docs/illumination.md §4): the fraction of the
    // optical depths the light's beam and the multiple scattering see, 1 - albedo f ...
    depth_scale: f32,
    // 1 when a light or the sky reaches the cloud.
    lit: u32,
    // 1 when other clouds' media reach into its scattering grid (the sweep reads `foreign`).
    foreign: u32,
    // ... the transformed albedo, and the moments g' and chi'_2 of the P2 phase function, the
    // multiple scattering sweeps with.
    scatter_albedo: f32,
    scatter_anisotropy: f32,
    scatter_second_moment: f32,
    // 1 when the scattering volumes hold angular moments beside their means (an anisotropic
    // medium): the flux after the means, and in `multiple` the quadrupole after the flux.
    moments: u32,
}

struct LightParams {
    // Orthonormal light basis; w is the direction the light travels (cloud-local).
    u: vec3<f32>,
    h_u: f32,
    v: vec3<f32>,
    h_v: f32,
    w: vec3<f32>,
    h_w: f32,
    // Half-extents of the light box along u, v, w (centred on grid_centre).
    half_extents: vec3<f32>,
    // Extinction per local metre per unit density in the shading pass: k_local (1 - f albedo).
    sigma_scale: f32,
    // Linear RGB irradiance.
    irradiance: vec3<f32>,
    // First element of this light's volume in the shared optical-depth buffer.
    offset: u32,
}

// One cloud's place in the volume pool of its shape (src/render/plan/pools.rs; docs/illumination.md
// §9): its uniforms, and the first element of each of its volumes in the pool's buffers. The
// batched passes find it through their work list, one entry per z workgroup. Rust mirror: `Slot`.
struct Slot {
    // The scattering grid's uniform.
    cloud: CloudParams,
    // The fine grid's uniform (shade).
    fine: CloudParams,
    // First f32 of the fine density (its finest level) in `densities`.
    fine_density: u32,
    // First f32 of the scattering grid's density in `densities`.
    density: u32,
    // First f32 of the light volumes in `optical_depth`.
    optical_depth: u32,
    // First vec4 of the volume in `source` and `orders`.
    volume: u32,
    // First vec4 of the volume in `multiple`.
    multiple: u32,
    // First vec2 of the other clouds' media in `foreign`.
    foreign: u32,
    // First of the cloud's lights in the pool's light array.
    lights: u32,
    // Its element of the closure's `order_ratios`.
    ratio: u32,
    // 1 for a coarse grid's slot: its series sums a signed correction, which the closure does not
    // clamp at 0; else 0.
    coarse: u32,
}

// The density levels of a fine grid (docs/illumination.md §1). Rust mirror: `DensityLevels` in
// src/render/core/types.rs.
struct DensityLevels {
    // Per level, the fine grid first: voxels per side (x), first element in the density buffer
    // (y), first brick of voxelize's gather among a cloud's bricks (z), and bricks per side (w).
    size_offset: array<vec4<u32>, 8>,
    // Levels in use.
    count: u32,
    // The level an upsample dispatch enlarges into the one below it.
    upsample_from: u32,
    // Largest radius, in voxels of its level, of a particle deposited on a level.
    max_radius: f32,
    // On level l, a particle deposits a kernel of radius sqrt(r² - kernel_narrowing (h_l² - h²)).
    kernel_narrowing: f32,
}

// The element of entry `axis` of voxel i's flux in a volume whose means start at `first`
// (docs/illumination.md §9): the n^3 means, then 3 vec4 (x, y, z: RGB) per voxel.
fn flux_element(first: u32, n: u32, i: u32, axis: u32) -> u32 {
    return first + n * n * n + 3u * i + axis;
}

// The element of entry `c` (xx, yy, xy, xz, yz) of voxel i's quadrupole in a volume whose means
// start at `first`: after the means and the flux, 5 vec4 (RGB) per voxel.
fn quadrupole_element(first: u32, n: u32, i: u32, c: u32) -> u32 {
    return first + 4u * n * n * n + 5u * i + c;
}

// The entries of w w^T - I/3 at xx, yy, xy, xz, yz, for unit w; and the weights of those entries
// in w^T Q w (zz = -xx - yy).
fn quadrupole_basis(w: vec3<f32>) -> array<f32, 5> {
    return array(w.x * w.x - 1.0 / 3.0, w.y * w.y - 1.0 / 3.0, w.x * w.y, w.x * w.z, w.y * w.z);
}

fn quadrupole_weights(w: vec3<f32>) -> array<f32, 5> {
    return array(w.x * w.x - w.z * w.z, w.y * w.y - w.z * w.z, 2.0 * w.x * w.y, 2.0 * w.x * w.z, 2.0 * w.y * w.z);
}

// What the Henyey-Greenstein phase function of anisotropy g adds to the mean of S_m towards the
// unit direction w, from its flux F (per axis) and quadrupole Q (xx, yy, xy, xz, yz):
// 3 g F . w + (15/2) g^2 w^T Q w, its Legendre expansion to second order (docs/illumination.md
// §5). Zero for w = 0.
fn phase_on_moments(g: f32, w: vec3<f32>, flux: array<vec3<f32>, 3>, quadrupole: array<vec3<f32>, 5>) -> vec3<f32> {
    let q = quadrupole_weights(w);
    let along = w.x * flux[0] + w.y * flux[1] + w.z * flux[2];
    let spread = q[0] * quadrupole[0] + q[1] * quadrupole[1] + q[2] * quadrupole[2] + q[3] * quadrupole[3] + q[4] * quadrupole[4];
    return 3.0 * g * along + 7.5 * g * g * spread;
}

// Linear index of voxel `v` in an n^3 volume.
fn voxel_index(v: vec3<u32>, n: u32) -> u32 {
    return v.x + n * (v.y + n * v.z);
}

// The density kernel k(u) of the squared argument u^2.
fn kernel(u2: f32) -> f32 {
    let a = max(1.0 - u2, 0.0);
    return a * a;
}

// Index of a 1D invocation dispatched as a 2D grid of 64-wide workgroups
// (more than 65535 workgroups do not fit in one dimension).
fn flat_invocation(id: vec3<u32>, groups: vec3<u32>) -> u32 {
    return id.x + id.y * groups.x * #{LINEAR_WORKGROUP}u;
}

// A trilinear lookup: the base voxel and the fractions towards the next one per axis.
struct Trilinear {
    base: vec3<i32>,
    f: vec3<f32>,
}

// Continuous voxel coordinate `g` (voxel i's centre at g = i) clamped to an n^3 volume: the
// edge voxels extend to the border.
fn clamped_lookup(g: vec3<f32>, n: u32) -> Trilinear {
    let gc = clamp(g, vec3(0.0), vec3(f32(n) - 1.0));
    let base = min(vec3<i32>(floor(gc)), vec3(i32(max(n, 2u)) - 2));
    return Trilinear(base, gc - vec3<f32>(base));
}

// `g` with voxels outside the volume counting as 0 (the caller skips them: see `corner_voxel`).
fn zero_border_lookup(g: vec3<f32>) -> Trilinear {
    let base = vec3<i32>(floor(g));
    return Trilinear(base, g - floor(g));
}

// Weight of corner `corner` (0..8, bits x y z) of a lookup.
fn corner_weight(t: Trilinear, corner: u32) -> f32 {
    let o = vec3<u32>(corner & 1u, (corner >> 1u) & 1u, corner >> 2u);
    let w = select(1.0 - t.f, t.f, vec3<bool>(o));
    return w.x * w.y * w.z;
}

// Linear index of corner `corner` of a lookup in an n^3 volume, or -1 outside it.
fn corner_voxel(t: Trilinear, corner: u32, n: u32) -> i32 {
    let v = t.base + vec3<i32>(vec3<u32>(corner & 1u, (corner >> 1u) & 1u, corner >> 2u));
    if any(v < vec3(0)) || any(v >= vec3(i32(n))) {
        return -1;
    }
    return i32(voxel_index(vec3<u32>(v), n));
}

// Continuous density-grid coordinate of cloud-local point `p`.
fn grid_coords(cloud: CloudParams, p: vec3<f32>) -> vec3<f32> {
    return (p - cloud.grid_origin) / cloud.h - 0.5;
}

// Continuous coordinate of cloud-local point `p` in a light's box of m voxels per side.
fn light_coords(cloud: CloudParams, light: LightParams, p: vec3<f32>) -> vec3<f32> {
    let d = p - cloud.grid_centre;
    let xi = vec3(dot(d, light.u), dot(d, light.v), dot(d, light.w));
    return (xi + light.half_extents) / vec3(light.h_u, light.h_v, light.h_w) - 0.5;
}

// Centre of voxel `v` of a light's box (centred on the fine grid's cube) in cloud-local space.
fn light_voxel_centre(fine: CloudParams, light: LightParams, v: vec3<u32>) -> vec3<f32> {
    let h = vec3(light.h_u, light.h_v, light.h_w);
    let xi = -light.half_extents + (vec3<f32>(v) + 0.5) * h;
    return fine.grid_centre + xi.x * light.u + xi.y * light.v + xi.z * light.w;
}

// Linear index of corner `corner` of a clamped lookup in an n^3 volume.
fn clamped_corner(t: Trilinear, corner: u32, n: u32) -> u32 {
    let o = vec3<u32>(corner & 1u, (corner >> 1u) & 1u, corner >> 2u);
    return voxel_index(min(vec3<u32>(t.base) + o, vec3(n - 1u)), n);
}

// The Henyey-Greenstein phase function (1/sr) of anisotropy g at the cosine between the light's
// travel direction and the scattered direction; 1 / (4 pi) for g = 0.
fn henyey_greenstein(g: f32, cos_theta: f32) -> f32 {
    let d = 1.0 + g * g - 2.0 * g * cos_theta;
    return (1.0 - g * g) / (4.0 * PI * d * sqrt(d));
}

// Opacity 1 - exp(-tau), without f32 cancellation for thin segments (series below 0.02).
fn opacity(tau: f32) -> f32 {
    if tau < 0.02 {
        return tau * (1.0 - tau * (0.5 - tau / 6.0));
    }
    return 1.0 - exp(-tau);
}

// A cloud's view transmittance volume (docs/illumination.md §5): optical depth from the camera
// at n x n rays by n slices. Rust mirror: `ViewVolumeParams` in src/render/view/view_volume.rs.
struct ViewVolumeParams {
    // Cloud-local from view space.
    local_from_view: mat4x4<f32>,
    // Tangent rectangle of the rays (u0, u1, v0, v1): u = x / depth, v = y / depth in view space.
    rect: vec4<f32>,
    // View depths of the first and last slice, metres.
    depth: vec2<f32>,
    // Extinction K per world metre at density 1.
    extinction: f32,
    // Rays per side and slices, n.
    n: u32,
    // First element of this volume in its view's optical-depth buffer.
    offset: u32,
    // This volume's range in its view's neighbour list: the volumes (its own among them) whose
    // clouds may lie in front of some point of this cloud (docs/illumination.md §5).
    first_neighbour: u32,
    neighbour_count: u32,
    // The first `front_count` neighbours lie wholly in front of this volume (their last slice
    // before its first): their optical depth is summed into this volume's front map.
    front_count: u32,
    // First vec4 of the cloud's multiple scattering seen from the camera in its view's
    // `seen_multiple` (an anisotropic cloud's), and that volume's voxels per side (the
    // scattering grid's N; 0: none, the billboards read the mean S_m).
    seen_offset: u32,
    seen_n: u32,
}

// Element of column (i, j) of a view volume's front map: after its n^3 optical depths, n^2
// sums of the optical depth of the neighbours wholly in front of it (src/render/view/view_volume.rs,
// `view_volume_len`).
fn front_map_index(volume: ViewVolumeParams, column: vec2<u32>) -> u32 {
    let n = volume.n;
    return volume.offset + n * n * n + column.x + n * column.y;
}

// The ray of tangent `uv` among a view volume's columns: the lower column of the four about it
// and the bilinear weights' fractions, clamped to the volume's rectangle of rays.
struct ViewColumns {
    base: vec2<u32>,
    f: vec2<f32>,
}

fn view_columns(volume: ViewVolumeParams, uv: vec2<f32>) -> ViewColumns {
    let n = volume.n;
    let g = clamp((uv - volume.rect.xz) / (volume.rect.yw - volume.rect.xz), vec2(0.0), vec2(1.0)) * f32(n - 1u);
    let base = min(vec2<u32>(floor(g)), vec2(n - 2u));
    return ViewColumns(base, g - vec2<f32>(base));
}

// Corner `c` (0..4: x in bit 0, y in bit 1) of the four columns about a ray, and its bilinear
// weight.
struct ColumnCorner {
    column: vec2<u32>,
    weight: f32,
}

fn column_corner(columns: ViewColumns, c: u32) -> ColumnCorner {
    let o = vec2<u32>(c & 1u, c >> 1u);
    let w = select(1.0 - columns.f, columns.f, vec2<bool>(o));
    return ColumnCorner(columns.base + o, w.x * w.y);
}

// Continuous node coordinates of view-space point `p` (view looks down -z), clamped to the volume.
fn view_volume_coords(volume: ViewVolumeParams, p: vec3<f32>) -> vec3<f32> {
    let depth = -p.z;
    let uv = p.xy / depth;
    let t = vec3(
        (uv - volume.rect.xz) / (volume.rect.yw - volume.rect.xz),
        (depth - volume.depth.x) / (volume.depth.y - volume.depth.x),
    );
    return clamp(t, vec3(0.0), vec3(1.0)) * f32(volume.n - 1u);
}

// A view's reduced-resolution cloud target (src/render/draw/cloud_target.rs; docs/illumination.md §6).
struct CloudTargetParams {
    // The view's viewport in its target: corner and size, pixels.
    viewport_origin: vec2<u32>,
    viewport_size: vec2<u32>,
    // Texels per side of the cloud target.
    target_size: vec2<u32>,
    // Cloud-target texels per view pixel, per axis.
    scale: f32,
    // Relative depth difference at which an upsampling weight falls to 1/e.
    depth_tolerance: f32,
}

// The view pixel whose depth cloud-target texel `t` stands for: the one under the texel's centre.
// The billboards are depth-tested against it, and the upsample compares it with each pixel's own.
fn cloud_target_depth_pixel(params: CloudTargetParams, t: vec2<u32>) -> vec2<u32> {
    let p = vec2<u32>((vec2<f32>(t) + 0.5) / params.scale);
    return params.viewport_origin + min(p, params.viewport_size - 1u);
}

// |a - b| / max(a, b) for reverse-Z depths: the relative difference of the view depths, measured
// from the farther one; 0 for equal depths, 1 between the sky (0) and any surface.
fn relative_depth_difference(a: f32, b: f32) -> f32 {
    let far = max(a, b);
    if far <= 0.0 {
        return 0.0;
    }
    return abs(a - b) / far;
}

// Texels per side of a cloud's ground map (Rust: `ground::GROUND_MAP_SIDE`).
const GROUND_MAP_SIDE: u32 = 32u;

// A cloud's ground (docs/illumination.md §4, "The ground"): where the plane under it lies, and
// per texel of a map of it the radiance it reflects. The CPU writes the frame, the ground pass
// the radiance. Rust mirror of the frame: `GroundFrame` in src/render/plan/ground.rs.
struct GroundMap {
    // Rows of the cloud's world-from-local affine map (translation in w), and of its inverse.
    world_from_local: array<vec4<f32>, 3>,
    local_from_world: array<vec4<f32>, 3>,
    // The plane's world height (x); the map's centre, world x and z (y, z); its half-width (w).
    // Metres.
    plane: vec4<f32>,
    // Lambertian reflectance (xyz); w: 1 when a ground lights the cloud, else 0.
    reflectance: vec4<f32>,
    // The sky's radiance (xyz), which the ground reflects.
    sky: vec4<f32>,
    // Texel i + GROUND_MAP_SIDE j (i along world x, j along z): the ground's radiance (xyz).
    radiance: array<vec4<f32>, 1024>,
}

fn affine_point(rows: array<vec4<f32>, 3>, p: vec3<f32>) -> vec3<f32> {
    let q = vec4(p, 1.0);
    return vec3(dot(rows[0], q), dot(rows[1], q), dot(rows[2], q));
}

fn affine_vector(rows: array<vec4<f32>, 3>, v: vec3<f32>) -> vec3<f32> {
    return vec3(dot(rows[0].xyz, v), dot(rows[1].xyz, v), dot(rows[2].xyz, v));
}

// World (x, z) of texel (i, j)'s centre.
fn ground_texel_centre(plane: vec4<f32>, texel: vec2<u32>) -> vec2<f32> {
    let size = 2.0 * plane.w / f32(GROUND_MAP_SIDE);
    return plane.yz - vec2(plane.w) + (vec2<f32>(texel) + 0.5) * size;
}
