// Gather: for every voxel of the scattering grid, its density (the mean of its f^3 children in
// the fine grid, docs/illumination.md §1) and its multiple-scattering source S_0, the
// density-weighted mean over those children of the beams' radiance
// (1 / 4 pi) sum_l E_l exp(-c tau_l), c the delta-M depth scale (1 for an isotropic
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
    let f = cloud.supersampling;
    let fine_h = cloud.h / f32(f);
    var weighted: Beams;
    var mass = 0.0;
    var plain: Beams;
    for (var s = 0u; s < f * f * f; s++) {
        let child = voxel * f + vec3(s % f, (s / f) % f, s / (f * f));
        let p = cloud.grid_origin + (vec3<f32>(child) + 0.5) * fine_h;
        let beams = beams_at(p);
        let rho = densities[slot.fine_density + voxel_index(child, cloud.light_n)];
        weighted.mean += rho * beams.mean;
        plain.mean += beams.mean;
#ifdef MOMENTS
        for (var axis = 0u; axis < 3u; axis++) {
            weighted.flux[axis] += rho * beams.flux[axis];
            plain.flux[axis] += beams.flux[axis];
        }
        for (var c = 0u; c < 5u; c++) {
            weighted.quadrupole[c] += rho * beams.quadrupole[c];
            plain.quadrupole[c] += beams.quadrupole[c];
        }
#endif
        mass += rho;
    }
    let children = f32(f * f * f);
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
