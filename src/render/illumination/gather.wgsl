// Gather: for every voxel of the scattering grid, its density (the mean of the fine grid over its
// cube, each fine voxel weighed by its overlap with it, docs/illumination.md §1) and its
// multiple-scattering source S_0, the density-weighted mean over those fine voxels of the beams'
// radiance (1 / 4 pi) sum_l E_l exp(-c tau_l), c the delta-M depth scale (1 for an isotropic
// medium), and for an anisotropic medium (shader def MOMENTS) of their flux
// (1 / 4 pi) sum_l E_l exp(-c tau_l) d_l and quadrupole (1 / 4 pi) sum_l E_l exp(-c tau_l) (d_l d_l^T - I/3);
// all lights in one dispatch (§3). Every cloud of a volume pool in that dispatch: z workgroup i
// gathers slot `work[i]`.
#import bevy_particle_clouds::types::{CloudParams, LightParams, Slot, PI, voxel_index, flat_invocation, light_coords, clamped_lookup, clamped_corner, corner_weight, flux_element, quadrupole_element, quadrupole_basis}

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> lights: array<LightParams>;
@group(0) @binding(2) var<storage, read> optical_depth: array<f32>;
// Per slot, the fine density grid (light_n^3 voxels and its levels), then the scattering grid's.
@group(0) @binding(3) var<storage, read_write> densities: array<f32>;
@group(0) @binding(4) var<storage, read_write> source: array<vec4<f32>>;
// A slot per z workgroup.
@group(0) @binding(5) var<storage, read> work: array<u32>;

var<private> slot: Slot;
var<private> cloud: CloudParams;

// The beams' mean radiance, flux (x, y, z) and quadrupole (xx, yy, xy, xz, yz) at a
// cloud-local point. (billboard.wgsl evaluates the same optical depths at its shading points.)
struct Beams {
    mean: vec3<f32>,
    flux: array<vec3<f32>, 3>,
    quadrupole: array<vec3<f32>, 5>,
}

fn beams_at(p: vec3<f32>) -> Beams {
    var beams: Beams;
    for (var l = 0u; l < cloud.light_count; l++) {
        let light = lights[slot.lights + l];
        let t = clamped_lookup(light_coords(cloud, light, p), cloud.light_n);
        let first = slot.optical_depth + light.offset;
        var tau = 0.0;
        for (var corner = 0u; corner < 8u; corner++) {
            tau += corner_weight(t, corner) * optical_depth[first + clamped_corner(t, corner, cloud.light_n)];
        }
        let radiance = light.irradiance * (exp(-tau * cloud.depth_scale) / (4.0 * PI));
        beams.mean += radiance;
#ifdef MOMENTS
        for (var axis = 0u; axis < 3u; axis++) {
            beams.flux[axis] += radiance * light.w[axis];
        }
        let q = quadrupole_basis(light.w);
        for (var c = 0u; c < 5u; c++) {
            beams.quadrupole[c] += radiance * q[c];
        }
#endif
    }
    return beams;
}

// The fine voxels of a grid of m per side that overlap scattering voxel `voxel` of a grid of N
// over the same cube: per axis the first, and one past the last. In units of 1 / N of a fine
// voxel the scattering voxel v spans [v m, (v + 1) m) and fine voxel j spans [j N, (j + 1) N),
// so integers decide every overlap exactly (with m = f N, the f^3 children, each whole).
fn fine_first(voxel: vec3<u32>, n: u32, m: u32) -> vec3<u32> {
    return voxel * m / n;
}

fn fine_end(voxel: vec3<u32>, n: u32, m: u32) -> vec3<u32> {
    return ((voxel + 1u) * m + n - 1u) / n;
}

// The part of fine voxel `child` inside scattering voxel `voxel`, in fine voxels (1 when whole).
fn overlap(child: vec3<u32>, voxel: vec3<u32>, n: u32, m: u32) -> f32 {
    let lo = max(child * n, voxel * m);
    let hi = min((child + 1u) * n, (voxel + 1u) * m);
    let w = vec3<f32>(hi - lo) / f32(n);
    return w.x * w.y * w.z;
}

@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn gather(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    slot = slots[work[id.z]];
    cloud = slot.cloud;
    let n = cloud.n;
    let i = flat_invocation(id, groups);
    if i >= n * n * n {
        return;
    }
    let voxel = vec3(i % n, (i / n) % n, i / (n * n));
    let m = cloud.light_n;
    let fine_h = cloud.h * f32(n) / f32(m);
    let first = fine_first(voxel, n, m);
    let span = fine_end(voxel, n, m) - first;
    var weighted: Beams;
    var mass = 0.0;
    var plain: Beams;
    for (var s = 0u; s < span.x * span.y * span.z; s++) {
        let child = first + vec3(s % span.x, (s / span.x) % span.y, s / (span.x * span.y));
        let w = overlap(child, voxel, n, m);
        let p = cloud.grid_origin + (vec3<f32>(child) + 0.5) * fine_h;
        let beams = beams_at(p);
        let rho = w * densities[slot.fine_density + voxel_index(child, m)];
        weighted.mean += rho * beams.mean;
        plain.mean += w * beams.mean;
#ifdef MOMENTS
        for (var axis = 0u; axis < 3u; axis++) {
            weighted.flux[axis] += rho * beams.flux[axis];
            plain.flux[axis] += w * beams.flux[axis];
        }
        for (var c = 0u; c < 5u; c++) {
            weighted.quadrupole[c] += rho * beams.quadrupole[c];
            plain.quadrupole[c] += w * beams.quadrupole[c];
        }
#endif
        mass += rho;
    }
    // The overlaps sum to (m / N)^3 fine voxels: the voxel's volume.
    let ratio = f32(m) / f32(n);
    let children = ratio * ratio * ratio;
    densities[slot.density + i] = mass / children;
    let filled = mass > 0.0;
    let count = select(children, mass, filled);
    source[slot.volume + i] = vec4(select(plain.mean, weighted.mean, filled) / count, 0.0);
#ifdef MOMENTS
    for (var axis = 0u; axis < 3u; axis++) {
        let flux = select(plain.flux[axis], weighted.flux[axis], filled) / count;
        source[flux_element(slot.volume, n, i, axis)] = vec4(flux, 0.0);
    }
    for (var c = 0u; c < 5u; c++) {
        let q = select(plain.quadrupole[c], weighted.quadrupole[c], filled) / count;
        source[quadrupole_element(slot.volume, n, i, c)] = vec4(q, 0.0);
    }
#endif
}
