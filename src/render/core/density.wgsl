// The density grids a march samples: shade (towards each light) and view_volume (towards the
// camera), each over every cloud of a pool, bind the pool's densities at group 0, binding 2.
#define_import_path bevy_particle_clouds::density
#import bevy_particle_clouds::types::{CloudParams, grid_coords, zero_border_lookup, corner_weight, corner_voxel}

@group(0) @binding(2) var<storage, read> density: array<f32>;

// Density at a cloud-local point of the grid `grid` whose first voxel is element `first`:
// trilinear between voxel centres, zero outside the grid.
fn density_at(grid: CloudParams, first: u32, p: vec3<f32>) -> f32 {
    let t = zero_border_lookup(grid_coords(grid, p));
    var sum = 0.0;
    for (var corner = 0u; corner < 8u; corner++) {
        let i = corner_voxel(t, corner, grid.n);
        if i >= 0 {
            sum += corner_weight(t, corner) * density[first + u32(i)];
        }
    }
    return sum;
}
