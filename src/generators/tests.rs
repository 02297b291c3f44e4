use bevy::prelude::{Cuboid, MeshBuilder, Meshable, Sphere, Torus};

use super::*;

fn positions(p: &Particles) -> Vec<Vec3> {
    p.particles.iter().map(|p| p.position).collect()
}

#[test]
fn sphere_fills_the_ball() {
    let p = sphere(2.0, 0.25, 1000, 3);
    assert_eq!(p.particles.len(), 1000);
    for q in &p.particles {
        assert!(
            q.position.length() + q.radius <= 2.0 + 1e-5,
            "{q:?} leaves the ball"
        );
        assert_eq!((q.radius, q.density), (0.25, 1.0));
    }
    // Uniform in volume: about (1/2)³ of the centres lie within half the inner radius.
    let inner = p
        .particles
        .iter()
        .filter(|q| q.position.length() < 0.875)
        .count();
    assert!(
        (80..=175).contains(&inner),
        "{inner} of 1000 in the inner half radius"
    );
    assert_eq!(p, sphere(2.0, 0.25, 1000, 3));
    assert_ne!(p, sphere(2.0, 0.25, 1000, 4));
}

#[test]
fn cuboid_fills_the_box() {
    let extents = Vec3::new(4.0, 1.0, 2.0);
    let p = cuboid(extents, 0.1, 800, 9);
    assert_eq!(p.particles.len(), 800);
    for q in &p.particles {
        assert!(
            (q.position.abs() + q.radius)
                .cmple(extents * 0.5 + 1e-5)
                .all(),
            "{q:?} leaves the box"
        );
    }
    let (lo, hi) = p.bounds().unwrap();
    // 800 uniform samples reach within 2 % of each face.
    assert!(
        lo.cmplt(-extents * 0.49).all() && hi.cmpgt(extents * 0.49).all(),
        "{lo} {hi}"
    );
    assert_eq!(p, cuboid(extents, 0.1, 800, 9));
    assert_ne!(p, cuboid(extents, 0.1, 800, 10));
}

#[test]
fn cumulus_is_a_flat_bottomed_heap() {
    let p = cumulus(2.5, 3000, 7);
    assert_eq!(p.particles.len(), 3000);
    for q in &p.particles {
        assert!(q.position.y >= -0.05 * 2.5 - 1e-6, "{q:?} below the base");
        assert!(q.position.length() < 2.5, "{q:?} far outside the heap");
        assert!((0.07 * 2.5 - 1e-5..=0.13 * 2.5 + 1e-5).contains(&q.radius));
        assert!((0.5..=1.0).contains(&q.density));
    }
    assert_eq!(p, cumulus(2.5, 3000, 7));
    assert_ne!(p, cumulus(2.5, 3000, 8));
}

#[test]
fn cloudscape_lays_out_equal_clouds_on_a_grid() {
    let sky = cloudscape(9, 900, 7);
    assert_eq!(sky.len(), 9);
    for (i, cloud) in sky.iter().enumerate() {
        assert_eq!(cloud.particles.particles.len(), 100);
        // Its grid cell (3 × 3, 80 m apart), jittered by at most 0.3 of a cell.
        let cell = Vec2::new((i % 3) as f32 - 1.0, (i / 3) as f32 - 1.0) * 80.0;
        let at = Vec2::new(cloud.translation.x, cloud.translation.z);
        assert!(
            (at - cell).abs().max_element() <= 24.0 + 1e-3,
            "{at} off {cell}"
        );
        assert!((70.0..=110.0).contains(&cloud.translation.y));
        // Extinction 20 / size for a size of 25–60 m; the particles within that size.
        let size = 20.0 / cloud.medium.extinction;
        assert!((25.0..=60.0).contains(&size), "size {size}");
        assert!(
            cloud
                .particles
                .particles
                .iter()
                .all(|p| p.position.length() < size)
        );
    }
    // The particles' turn keeps their distances from the cloud's origin.
    let turned = &sky[0].particles.particles;
    let size = 20.0 / sky[0].medium.extinction;
    let unturned = cumulus(size, 100, 1000);
    for (a, b) in turned.iter().zip(&unturned.particles) {
        assert!((a.position.length() - b.position.length()).abs() < 1e-4);
        assert!((a.position.y - b.position.y).abs() < 1e-4);
    }
    assert_eq!(sky[3].translation, cloudscape(9, 900, 7)[3].translation);
}

#[test]
fn from_sdf_fills_only_the_inside() {
    let ball = |p: Vec3| p.length() - 1.0;
    let p = from_sdf(ball, Vec3::splat(-1.5), Vec3::splat(1.5), 0.05, 10_000, 5);
    assert_eq!(p.particles.len(), 10_000);
    assert!(positions(&p).iter().all(|q| q.length() < 1.0));
    assert!(
        p.particles
            .iter()
            .all(|q| q.radius == 0.05 && q.density == 1.0)
    );
    // Uniform: the mean distance from the centre of a uniform unit ball is 3/4.
    let mean = positions(&p).iter().map(|q| q.length()).sum::<f32>() / 10_000.0;
    assert!((mean - 0.75).abs() < 0.01, "mean radius {mean}");
    // Deterministic per seed, also across chunk boundaries (10 000 > one chunk).
    assert_eq!(
        p,
        from_sdf(ball, Vec3::splat(-1.5), Vec3::splat(1.5), 0.05, 10_000, 5)
    );
    assert_ne!(
        p,
        from_sdf(ball, Vec3::splat(-1.5), Vec3::splat(1.5), 0.05, 10_000, 6)
    );
    // A prefix of a larger request is the same sample.
    let more = from_sdf(ball, Vec3::splat(-1.5), Vec3::splat(1.5), 0.05, 12_000, 5);
    assert_eq!(&more.particles[..CHUNK], &p.particles[..CHUNK]);
}

#[test]
fn from_sdf_of_an_empty_shape_gives_nothing() {
    let p = from_sdf(|_| 1.0, Vec3::ZERO, Vec3::ONE, 0.1, 3, 1);
    assert_eq!(p.particles.len(), 0);
    assert_eq!(
        from_sdf(|_| -1.0, Vec3::ZERO, Vec3::ONE, 0.1, 0, 1)
            .particles
            .len(),
        0
    );
}

#[test]
fn bunny_is_inside_its_bounds_and_has_its_parts() {
    let (lo, hi) = BUNNY_BOUNDS;
    let p = from_sdf(bunny_sdf, lo, hi, 0.02, 20_000, 11);
    assert_eq!(p.particles.len(), 20_000);
    assert!(positions(&p).iter().all(|&q| bunny_sdf(q) < 0.0));
    // The box contains the whole shape: its faces are outside the bunny.
    for i in 0..=41 {
        for j in 0..=41 {
            let (a, b) = (i as f32 / 41.0, j as f32 / 41.0);
            for q in [
                Vec3::new(lo.x, lo.y + a * (hi.y - lo.y), lo.z + b * (hi.z - lo.z)),
                Vec3::new(hi.x, lo.y + a * (hi.y - lo.y), lo.z + b * (hi.z - lo.z)),
                Vec3::new(lo.x + a * (hi.x - lo.x), lo.y, lo.z + b * (hi.z - lo.z)),
                Vec3::new(lo.x + a * (hi.x - lo.x), hi.y, lo.z + b * (hi.z - lo.z)),
                Vec3::new(lo.x + a * (hi.x - lo.x), lo.y + b * (hi.y - lo.y), lo.z),
                Vec3::new(lo.x + a * (hi.x - lo.x), lo.y + b * (hi.y - lo.y), hi.z),
            ] {
                assert!(
                    bunny_sdf(q) > 0.0,
                    "the bunny pokes out of BUNNY_BOUNDS at {q}"
                );
            }
        }
    }
    // Parts: ears above the head, a tail behind, symmetric in z.
    assert!(bunny_sdf(Vec3::new(0.38, 1.75, 0.18)) < 0.0, "ear");
    assert!(
        bunny_sdf(Vec3::new(0.38, 1.75, 0.0)) > 0.0,
        "gap between the ears"
    );
    assert!(bunny_sdf(Vec3::new(-0.9, 0.5, 0.0)) < 0.0, "tail");
    assert!(bunny_sdf(Vec3::new(0.6, 1.1, 0.0)) < 0.0, "head");
    let left = p.particles.iter().filter(|q| q.position.z > 0.0).count();
    assert!(
        (9_700..=10_300).contains(&left),
        "{left} of 20 000 on one side"
    );
}

#[test]
fn from_mesh_volume_fills_a_box_mesh() {
    let mesh = Cuboid::new(2.0, 1.0, 0.5).mesh().build();
    let p = from_mesh_volume(&mesh, 0.05, 2000, 4).unwrap();
    assert_eq!(p.particles.len(), 2000);
    let half = Vec3::new(1.0, 0.5, 0.25);
    assert!(positions(&p).iter().all(|q| q.abs().cmple(half).all()));
    let (lo, hi) = p.bounds().unwrap();
    assert!(
        (lo + 0.05).cmplt(-half + 0.05).all() && (hi - 0.05).cmpgt(half - 0.05).all(),
        "{lo} {hi}"
    );
    assert_eq!(p, from_mesh_volume(&mesh, 0.05, 2000, 4).unwrap());
    assert_ne!(p, from_mesh_volume(&mesh, 0.05, 2000, 5).unwrap());
}

#[test]
fn from_mesh_volume_respects_concavity() {
    // A torus (ring radius 1, tube radius 0.25): its hole must stay empty.
    let mesh = Torus::new(0.75, 1.25).mesh().build();
    let p = from_mesh_volume(&mesh, 0.05, 3000, 2).unwrap();
    assert_eq!(p.particles.len(), 3000);
    for q in positions(&p) {
        // The tessellated tube (32 × 24 segments) departs from the true one by under 4 mm.
        let tube = (Vec3::new(q.x, 0.0, q.z).length() - 1.0).hypot(q.y);
        assert!(
            tube <= 0.25 + 0.005,
            "{q} is outside the torus (tube distance {tube})"
        );
    }
    // And fills it: particles reach most of the way around the ring in every quadrant.
    for (sx, sz) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
        let n = p
            .particles
            .iter()
            .filter(|q| q.position.x * sx > 0.0 && q.position.z * sz > 0.0)
            .count();
        assert!(
            (650..=850).contains(&n),
            "{n} of 3000 in quadrant ({sx}, {sz})"
        );
    }
    let ball = Sphere::new(1.0).mesh().ico(3).unwrap();
    let b = from_mesh_volume(&ball, 0.05, 1000, 2).unwrap();
    assert!(positions(&b).iter().all(|q| q.length() <= 1.0 + 1e-5));
}

#[test]
fn from_mesh_volume_refuses_a_mesh_without_triangles() {
    use bevy::{
        asset::RenderAssetUsages,
        mesh::{Indices, PrimitiveTopology},
    };
    let points = Mesh::new(PrimitiveTopology::PointList, RenderAssetUsages::default())
        .with_inserted_attribute(Mesh::ATTRIBUTE_POSITION, vec![[0.0f32, 0.0, 0.0]])
        .with_inserted_indices(Indices::U32(vec![0]));
    assert!(matches!(
        from_mesh_volume(&points, 0.1, 10, 1),
        Err(MeshTrianglesError::WrongTopology)
    ));
}
