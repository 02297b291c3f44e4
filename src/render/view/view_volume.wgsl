// View transmittance: a cloud's optical depth from the camera, marched through its fine density
// grid along n x n view rays and stored at n view depths (docs/illumination.md §5). One
// invocation per ray; tau_k = tau_{k-1} + K (rho_{k-1} + rho_k) / 2 * dz sqrt(1 + u^2 + v^2).
// The billboards read it to see each piece of a particle through every particle in front of it,
// of this cloud and of the clouds that overlap it, so every view volume of a view sits in one
// buffer (the view's atlas), each from its `offset`.
// Then `sum_front` fills each volume's front map: at each of its columns, the optical depth along
// the column's ray of the neighbours wholly in front of it, the same for every point of the
// volume, so the billboards read it once per pixel instead of walking those neighbours.
// For an anisotropic cloud, `see_multiple` evaluates its S_m towards the camera at every voxel of
// its scattering grid (the phase function on its moments), which the billboards then read like
// an isotropic cloud's mean instead of the moments at every chord point.
// Every volume of one view whose cloud is in one volume pool in one dispatch: z workgroup i
// marches (or sees) `work[i]`.
#import bevy_particle_clouds::types::{Slot, ViewVolumeParams, voxel_index, front_map_index, view_columns, column_corner, flux_element, quadrupole_element, phase_on_moments}
#import bevy_particle_clouds::density::density_at

// The pool's slots; the atlas's volumes; the pool's densities at binding 2 (density.wgsl).
@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> volumes: array<ViewVolumeParams>;
@group(0) @binding(3) var<storage, read_write> view_optical_depth: array<f32>;
// (atlas volume, slot) per z workgroup (`sum_front`: the slot unused).
@group(0) @binding(4) var<storage, read> work: array<vec2<u32>>;
// The neighbour lists (`sum_front` only).
@group(0) @binding(5) var<storage, read> neighbours: array<u32>;
// The pool's multiple scattering with its moments, and the view's S_m seen from the camera
// (`see_multiple` only).
@group(0) @binding(6) var<storage, read> multiple: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read_write> seen_multiple: array<vec4<f32>>;

@compute @workgroup_size(#{SLICE_WORKGROUP}, #{SLICE_WORKGROUP}, 1)
fn march(@builtin(global_invocation_id) id: vec3<u32>) {
    let item = work[id.z];
    let volume = volumes[item.x];
    let slot = slots[item.y];
    let n = volume.n;
    if id.x >= n || id.y >= n {
        return;
    }
    let node = vec2<f32>(id.xy) / f32(n - 1u);
    let uv = mix(volume.rect.xz, volume.rect.yw, node);
    let dz = (volume.depth.y - volume.depth.x) / f32(n - 1u);
    let step = 0.5 * volume.extinction * dz * sqrt(1.0 + dot(uv, uv));
    var before = 0.0;
    var tau = 0.0;
    for (var k = 0u; k < n; k++) {
        let z = volume.depth.x + dz * f32(k);
        let local = (volume.local_from_view * vec4(uv * z, -z, 1.0)).xyz;
        let here = density_at(slot.fine, slot.fine_density, local);
        if k > 0u {
            tau += (before + here) * step;
        }
        view_optical_depth[volume.offset + voxel_index(vec3(id.xy, k), n)] = tau;
        before = here;
    }
}

// Optical depth along the whole ray of tangent `uv` through volume `k`: bilinear in its last
// slice; none off its rectangle of rays.
fn along(k: u32, uv: vec2<f32>) -> f32 {
    let volume = volumes[k];
    if any(uv < volume.rect.xz) || any(uv > volume.rect.yw) {
        return 0.0;
    }
    let n = volume.n;
    let columns = view_columns(volume, uv);
    var tau = 0.0;
    for (var c = 0u; c < 4u; c++) {
        let corner = column_corner(columns, c);
        tau += corner.weight * view_optical_depth[volume.offset + voxel_index(vec3(corner.column, n - 1u), n)];
    }
    return tau;
}

@compute @workgroup_size(#{SLICE_WORKGROUP}, #{SLICE_WORKGROUP}, 1)
fn sum_front(@builtin(global_invocation_id) id: vec3<u32>) {
    let volume = volumes[work[id.z].x];
    let n = volume.n;
    if id.x >= n || id.y >= n {
        return;
    }
    let uv = mix(volume.rect.xz, volume.rect.yw, vec2<f32>(id.xy) / f32(n - 1u));
    var tau = 0.0;
    for (var i = 0u; i < volume.front_count; i++) {
        tau += along(neighbours[volume.first_neighbour + i], uv);
    }
    view_optical_depth[front_map_index(volume, id.xy)] = tau;
}

// S_m of each voxel of the scattering grid towards the camera: max(mean + 3 g F . u + (15/2) g^2
// u^T Q u, 0), u the unit direction from the voxel's centre to the camera (the mean alone where
// the camera is at the centre). One invocation per column of the grid.
@compute @workgroup_size(#{SLICE_WORKGROUP}, #{SLICE_WORKGROUP}, 1)
fn see_multiple(@builtin(global_invocation_id) id: vec3<u32>) {
    let item = work[id.z];
    let volume = volumes[item.x];
    let slot = slots[item.y];
    let n = slot.cloud.n;
    if id.x >= n || id.y >= n {
        return;
    }
    let camera = (volume.local_from_view * vec4(0.0, 0.0, 0.0, 1.0)).xyz;
    let first = slot.multiple;
    for (var z = 0u; z < n; z++) {
        let v = vec3(id.xy, z);
        let i = voxel_index(v, n);
        let towards = camera - (slot.cloud.grid_origin + (vec3<f32>(v) + 0.5) * slot.cloud.h);
        let u = select(vec3(0.0), normalize(towards), dot(towards, towards) > 0.0);
        var flux = array<vec3<f32>, 3>();
        for (var axis = 0u; axis < 3u; axis++) {
            flux[axis] = multiple[flux_element(first, n, i, axis)].xyz;
        }
        var quadrupole = array<vec3<f32>, 5>();
        for (var c = 0u; c < 5u; c++) {
            quadrupole[c] = multiple[quadrupole_element(first, n, i, c)].xyz;
        }
        let s_m = multiple[first + i].xyz + phase_on_moments(slot.cloud.anisotropy, u, flux, quadrupole);
        seen_multiple[volume.seen_offset + i] = vec4(max(s_m, vec3(0.0)), 0.0);
    }
}
