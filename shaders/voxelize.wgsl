// Voxelize: every particle deposits its mass into the cloud's density grid
// (docs/illumination.md §1). One invocation per particle; float atomics by compare-exchange.
#import bevy_particle_clouds::types::{Particle, CloudParams, KERNEL_VOLUME, kernel, voxel_index, flat_invocation, zero_border_lookup, corner_weight, corner_voxel}

@group(0) @binding(0) var<uniform> cloud: CloudParams;
@group(0) @binding(1) var<storage, read> particles: array<Particle>;
// f32 bits; cleared to zero before this pass.
@group(0) @binding(2) var<storage, read_write> density: array<atomic<u32>>;

fn atomic_add_density(i: u32, value: f32) {
    var old = atomicLoad(&density[i]);
    loop {
        let result = atomicCompareExchangeWeak(&density[i], old, bitcast<u32>(bitcast<f32>(old) + value));
        if result.exchanged {
            break;
        }
        old = result.old_value;
    }
}

// Sub-voxel particle: its whole mass goes to the 8 voxel centres around it, trilinearly,
// renormalised over the ones inside the grid so no mass is lost at the border.
fn splat(g: vec3<f32>, density_per_voxel: f32) {
    let t = zero_border_lookup(g);
    var inside = 0.0;
    for (var corner = 0u; corner < 8u; corner++) {
        if corner_voxel(t, corner, cloud.n) >= 0 {
            inside += corner_weight(t, corner);
        }
    }
    if inside <= 0.0 {
        return;
    }
    for (var corner = 0u; corner < 8u; corner++) {
        let i = corner_voxel(t, corner, cloud.n);
        if i >= 0 {
            atomic_add_density(u32(i), density_per_voxel * corner_weight(t, corner) / inside);
        }
    }
}

@compute @workgroup_size(64)
fn deposit(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = flat_invocation(id, groups);
    if index >= cloud.particle_count {
        return;
    }
    let particle = particles[index];
    let centre = particle.position_radius.xyz;
    let radius = particle.position_radius.w;
    let eta = particle.density.x;
    if eta <= 0.0 {
        return;
    }
    let h = cloud.h;
    let r_voxels = radius / h;
    // Mass / voxel volume, in density units; (r/h)^3 avoids overflow for huge particles.
    let density_per_voxel = KERNEL_VOLUME * eta * r_voxels * r_voxels * r_voxels;
    let g = (centre - cloud.grid_origin) / h - 0.5;
    if radius < h {
        splat(g, density_per_voxel);
        return;
    }
    let n = i32(cloud.n);
    let lo = max(vec3<i32>(ceil(g - r_voxels)), vec3(0));
    let hi = min(vec3<i32>(floor(g + r_voxels)), vec3(n - 1));
    let inv_r2 = 1.0 / (r_voxels * r_voxels);
    // First the kernel's sum over the voxel centres, so the deposit conserves mass exactly.
    var total = 0.0;
    for (var z = lo.z; z <= hi.z; z++) {
        for (var y = lo.y; y <= hi.y; y++) {
            for (var x = lo.x; x <= hi.x; x++) {
                let d = vec3<f32>(f32(x), f32(y), f32(z)) - g;
                total += kernel(dot(d, d) * inv_r2);
            }
        }
    }
    if total <= 0.0 {
        splat(g, density_per_voxel);
        return;
    }
    let scale = density_per_voxel / total;
    for (var z = lo.z; z <= hi.z; z++) {
        for (var y = lo.y; y <= hi.y; y++) {
            for (var x = lo.x; x <= hi.x; x++) {
                let d = vec3<f32>(f32(x), f32(y), f32(z)) - g;
                let w = kernel(dot(d, d) * inv_r2);
                if w > 0.0 {
                    atomic_add_density(voxel_index(vec3<u32>(vec3(x, y, z)), cloud.n), w * scale);
                }
            }
        }
    }
}
