// Types and small helpers shared by every pass of bevy_particle_clouds.
// The Rust mirrors are in src/render/illumination.rs (`CloudParams`, `LightParams`)
// and src/render/particles.rs (`GpuParticle`). Discretization: docs/illumination.md.
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
    // Voxels per side of every volume.
    n: u32,
    particle_count: u32,
    // 0: transmittance stencil, 1: the paper's stencil, 2: free-path hops.
    stencil: u32,
    _padding: u32,
    // Corner of the density cube, cloud-local metres.
    grid_origin: vec3<f32>,
    // Voxel size, cloud-local metres.
    h: f32,
    grid_centre: vec3<f32>,
    // Extinction per cloud-local metre at density 1 (K times the cloud's scale).
    k_local: f32,
    albedo: f32,
    forward_scattering: f32,
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
    // Gather: 0 writes the light's contribution, 1 adds it.
    accumulate: u32,
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
    return id.x + id.y * groups.x * 64u;
}

// Trilinear weights and base voxel of continuous voxel coordinate `g`, clamped to the volume
// (the edge voxels extend to the border): returns base in xyz-ints and the fractions.
struct Clamped {
    base: vec3<u32>,
    f: vec3<f32>,
}

fn clamp_trilinear(g: vec3<f32>, n: u32) -> Clamped {
    let top = f32(n) - 1.0;
    let gc = clamp(g, vec3(0.0), vec3(top));
    let base = min(vec3<u32>(floor(gc)), vec3(max(n, 2u) - 2u));
    return Clamped(base, gc - vec3<f32>(base));
}
