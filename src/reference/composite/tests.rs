use super::*;
use crate::math::particle_optical_depth;
use crate::scene::ObjectShape;
use bevy::math::Vec3;

const W: u32 = 21;
const H: u32 = 15;

/// Camera at the origin looking down -Z, odd size so that the centre pixel looks exactly along -Z.
fn camera() -> PinholeCamera {
    PinholeCamera::looking_at(DVec3::ZERO, DVec3::NEG_Z, DVec3::Y, 40.0, W, H)
}

fn particle(p: DVec3, radius: f32, density: f32) -> Particle {
    Particle {
        position: p.as_vec3(),
        radius,
        density,
    }
}

fn pixel(image: &[[f32; 4]], px: u32, py: u32) -> DVec3 {
    let p = image[(py * W + px) as usize];
    assert_eq!(p[3], 1.0);
    DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64)
}

fn close(a: DVec3, b: DVec3) -> bool {
    (a - b).abs().max_element() < 2e-6 * (1.0 + b.abs().max_element())
}

fn cloud<'a>(
    particles: &'a [Particle],
    scattered: ScatteredLight<'a>,
    extinction: f32,
) -> BillboardCloud<'a> {
    BillboardCloud {
        particles,
        world_from_local: CloudPlacement::at(DVec3::ZERO),
        medium: Medium {
            extinction,
            albedo: 1.0,
            ..Default::default()
        },
        scattered,
        segments: 4,
        compositing: BillboardCompositing::Sorted,
        shading: BillboardShading::Chord,
    }
}

const WHITE: ScatteredLight = &|_, _| DVec3::ONE;

#[test]
fn single_particle_face_on_has_beer_lambert_alpha() {
    let cam = camera();
    // Local particle r = 0.5 scaled by 2 into the world: R = 1.
    let particles = [particle(DVec3::new(0.0, 0.0, -1.5), 0.5, 1.5)];
    let colours = [DVec3::new(0.5, 1.0, 2.0)];
    let uniform = |_, _| colours[0];
    let mut c = cloud(&particles, &uniform, 0.8);
    c.world_from_local = CloudPlacement {
        translation: DVec3::new(0.0, 0.0, -2.0),
        rotation: DQuat::IDENTITY,
        scale: 2.0,
    };
    let background = DVec3::new(0.1, 0.2, 0.3);
    let exposure = 0.5;
    let image = composite(&cam, background, &[], &[c], exposure);
    // Centre pixel: b = 0, tau = K eta R 16/15.
    let tau0 = 0.8 * 1.5 * 16.0 / 15.0;
    let alpha0 = 1.0 - f64::exp(-tau0);
    let expected = colours[0] * exposure * alpha0 + background * (1.0 - alpha0);
    assert!(close(pixel(&image, W / 2, H / 2), expected));
    // A pixel off to the side: b = |c| sin(angle between the ray and the centre direction).
    let (px, py) = (W / 2 + 2, H / 2 - 1);
    let w = cam.pixel_ray(px, py);
    let b = 5.0 * w.angle_between(DVec3::NEG_Z).sin();
    assert!(b > 0.2 && b < 1.0);
    let alpha = 1.0 - f64::exp(-particle_optical_depth(0.8, 1.5, 1.0, b));
    assert!(alpha < alpha0 && alpha > 0.0);
    let expected = colours[0] * exposure * alpha + background * (1.0 - alpha);
    assert!(close(pixel(&image, px, py), expected));
    // A corner pixel misses the particle and shows the background.
    assert!(close(pixel(&image, 0, 0), background));
}

#[test]
fn centre_shading_shows_the_light_at_the_centre_over_the_whole_billboard() {
    let cam = camera();
    let particles = [particle(DVec3::new(0.2, 0.0, -4.0), 1.0, 1.5)];
    // Brighter towards +x; the ray argument must be the direction to the centre.
    let field = |x: DVec3, ray: DVec3| DVec3::new(1.0, 0.5, 0.25) * (1.0 + x.x) * (1.0 - ray.z);
    let mut c = cloud(&particles, &field, 0.8);
    c.shading = BillboardShading::Centre;
    let image = composite(&cam, DVec3::ZERO, &[], &[c], 1.0);
    let centre = particles[0].position.as_dvec3();
    let shown = field(centre, centre.normalize());
    let mut covered = 0;
    for py in 0..H {
        for px in 0..W {
            let w = cam.pixel_ray(px, py);
            let b = (centre - w * centre.dot(w)).length();
            if b >= 1.0 {
                continue;
            }
            let alpha = 1.0 - f64::exp(-particle_optical_depth(0.8, 1.5, 1.0, b));
            assert!(close(pixel(&image, px, py), shown * alpha));
            covered += 1;
        }
    }
    assert!(covered > 10);
    // Along the chord, the side towards +x is brighter than the centre's light.
    c.shading = BillboardShading::Chord;
    let chord = composite(&cam, DVec3::ZERO, &[], &[c], 1.0);
    let (px, py) = (W / 2 + 3, H / 2);
    assert!(pixel(&chord, px, py).x > pixel(&image, px, py).x * 1.05);
}

#[test]
fn opaque_object_in_front_hides_the_particle_and_behind_shows_through() {
    let cam = camera();
    let particles = [particle(DVec3::new(0.0, 0.0, -5.0), 1.0, 2.0)];
    let c = cloud(&particles, WHITE, 1.0);
    let object = |z: f32, color: Vec3| SceneObject {
        shape: ObjectShape::Sphere(0.3),
        translation: Vec3::new(0.0, 0.0, z),
        color,
        reflectance: Vec3::ZERO,
    };
    // In front (depth 2.7 < 5): exactly the object's radiance.
    let red = Vec3::new(0.9, 0.1, 0.0);
    let image = composite(&cam, DVec3::ZERO, &[object(-3.0, red)], &[c], 1.0);
    assert_eq!(pixel(&image, W / 2, H / 2), red.as_dvec3());
    // Behind (depth 7.7 > 5): the particle over the object.
    let image = composite(&cam, DVec3::ZERO, &[object(-8.0, red)], &[c], 1.0);
    let alpha = 1.0 - f64::exp(-2.0 * 16.0 / 15.0);
    assert!(close(
        pixel(&image, W / 2, H / 2),
        DVec3::ONE * alpha + red.as_dvec3() * (1.0 - alpha)
    ));
    // An object inside the sphere but nearer than its centre still hides the whole billboard.
    let image = composite(&cam, DVec3::ZERO, &[object(-4.2, red)], &[c], 1.0);
    assert_eq!(pixel(&image, W / 2, H / 2), red.as_dvec3());
}

#[test]
fn overlapping_particles_composite_back_to_front_in_any_input_order() {
    let cam = camera();
    let near = particle(DVec3::new(0.1, 0.0, -3.0), 0.8, 0.7);
    let far = particle(DVec3::new(-0.1, 0.05, -6.0), 1.5, 1.2);
    let (near_colour, far_colour) = (DVec3::new(1.0, 0.0, 0.0), DVec3::new(0.0, 0.0, 1.0));
    let field = |x: DVec3, _: DVec3| if x.z > -4.5 { near_colour } else { far_colour };
    let background = DVec3::new(0.0, 0.3, 0.0);
    let draw = |particles: &[Particle]| {
        let mut c = cloud(particles, &field, 1.3);
        c.segments = 1;
        composite(&cam, background, &[], &[c], 1.0)
    };
    let a = draw(&[near, far]);
    assert_eq!(a, draw(&[far, near]));
    let w = cam.pixel_ray(W / 2, H / 2);
    let alpha = |p: &Particle| {
        let c = p.position.as_dvec3();
        let bb = (c - w * c.dot(w)).length();
        1.0 - (-particle_optical_depth(1.3, p.density as f64, p.radius as f64, bb)).exp()
    };
    let mut expected = background;
    expected = far_colour * alpha(&far) + expected * (1.0 - alpha(&far));
    expected = near_colour * alpha(&near) + expected * (1.0 - alpha(&near));
    assert!(close(pixel(&a, W / 2, H / 2), expected));
    // The other order would give a visibly different colour.
    let mut wrong = background;
    wrong = near_colour * alpha(&near) + wrong * (1.0 - alpha(&near));
    wrong = far_colour * alpha(&far) + wrong * (1.0 - alpha(&far));
    assert!((wrong - expected).length() > 0.05);
}

#[test]
fn chord_segments_converge_to_the_integral_along_the_ray() {
    // A thick particle on the axis with scattered light rising linearly away from the camera:
    // the exact pixel is the integral of T(s) sigma(s) c(s) ds along the chord. One segment
    // takes c at the chord's middle; more segments converge to the integral, whose front (dark
    // here) weighs most.
    let cam = camera();
    let (k, eta, r) = (3.0, 1.0, 1.0);
    let particles = [particle(DVec3::new(0.0, 0.0, -5.0), r as f32, eta as f32)];
    let field = |x: DVec3, _: DVec3| DVec3::splat(-4.0 - x.z); // 0 at the front (z = -4), 2 at the back
    let steps = 100_000;
    let ds = 2.0 * r / steps as f64;
    let (mut exact, mut t) = (0.0, 1.0);
    for i in 0..steps {
        let s = -r + (i as f64 + 0.5) * ds;
        let sigma = k * eta * (1.0 - s * s) * (1.0 - s * s);
        exact += t * sigma * ds * (1.0 + s);
        t *= (-sigma * ds).exp();
    }
    let error = |segments: u32| {
        let mut c = cloud(&particles, &field, k as f32);
        c.segments = segments;
        let image = composite(&cam, DVec3::ZERO, &[], &[c], 1.0);
        (pixel(&image, W / 2, H / 2).x - exact).abs() / exact
    };
    let (one, four, sixteen) = (error(1), error(4), error(16));
    assert!(one > 0.2, "one segment sees the middle only: {one}");
    assert!(
        four < one / 4.0 && sixteen < four / 4.0,
        "{one} {four} {sixteen}"
    );
    assert!(sixteen < 0.01, "{sixteen}");
}

#[test]
fn camera_inside_a_particle_sees_the_partial_chord() {
    // Camera 0.5 m from the centre of a particle of radius 2, looking away from it... and through it.
    let cam = PinholeCamera::looking_at(
        DVec3::new(0.0, 0.0, 0.5),
        DVec3::new(0.0, 0.0, -1.0),
        DVec3::Y,
        40.0,
        W,
        H,
    );
    let (k, eta, r) = (1.5, 0.8, 2.0);
    let particles = [particle(DVec3::ZERO, r as f32, eta as f32)];
    let image = composite(
        &cam,
        DVec3::ZERO,
        &[],
        &[cloud(&particles, WHITE, k as f32)],
        1.0,
    );
    assert!(image.iter().flatten().all(|v| v.is_finite()));
    // Centre ray: b = 0, the chord runs from the near plane (s = 0.1 - 0.5 = -0.4) to s = 2.
    // Integrate the density along it numerically (midpoint rule).
    let steps = 200_000;
    let (s0, s1) = (cam.near - 0.5, r);
    let ds = (s1 - s0) / steps as f64;
    let tau: f64 = (0..steps)
        .map(|i| {
            let s = s0 + (i as f64 + 0.5) * ds;
            let u2 = s * s / (r * r);
            k * eta * (1.0 - u2) * (1.0 - u2) * ds
        })
        .sum();
    let full = particle_optical_depth(k, eta, r, 0.0);
    assert!(tau < full && tau > 0.5 * full);
    let got = pixel(&image, W / 2, H / 2).x;
    assert!(
        (got - (1.0 - (-tau).exp())).abs() < 1e-6,
        "{got} vs {}",
        1.0 - (-tau).exp()
    );
    // An opaque object between the near plane and the particle centre does not hide it: the
    // billboard sits on the near plane, so the whole partial chord composites over the object.
    let obj = SceneObject {
        shape: ObjectShape::Sphere(0.01),
        translation: Vec3::ZERO,
        color: Vec3::X,
        reflectance: Vec3::ZERO,
    };
    let clouds = [cloud(&particles, WHITE, k as f32)];
    let image = composite(&cam, DVec3::ZERO, &[obj], &clouds, 1.0);
    let alpha = 1.0 - (-tau).exp();
    let expected = DVec3::ONE * alpha + DVec3::X * (1.0 - alpha);
    assert!(close(pixel(&image, W / 2, H / 2), expected));
}

#[test]
fn near_plane_rule_is_continuous_and_ignores_particles_behind_the_camera() {
    let cam = camera();
    let draw = |z: f64| {
        let particles = [particle(DVec3::new(0.0, 0.0, z), 1.0, 1.0)];
        composite(
            &cam,
            DVec3::ZERO,
            &[],
            &[cloud(&particles, WHITE, 2.0)],
            1.0,
        )
    };
    // Just beyond and just within the switch (z_c - R = near): the same image to f32 precision.
    let eps = 1e-9;
    let (a, b) = (draw(-(1.1 + eps)), draw(-(1.1 - eps)));
    for (p, q) in a.iter().zip(&b) {
        assert!((p[0] - q[0]).abs() < 1e-6);
    }
    // Wholly behind the camera: nothing.
    assert!(draw(2.0).iter().all(|p| p[0] == 0.0));
}

#[test]
fn rotated_and_scaled_cloud_and_row_culling_match_brute_force() {
    // Many particles; every pixel compared with a direct evaluation without row culling.
    let cam =
        PinholeCamera::looking_at(DVec3::new(1.0, 2.0, 6.0), DVec3::ZERO, DVec3::Y, 50.0, W, H);
    let mut seed = 12345u64;
    let mut rnd = || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let particles: Vec<Particle> = (0..60)
        .map(|_| {
            particle(
                DVec3::new(rnd(), rnd(), rnd()) * 2.0 - 1.0,
                0.1 + 0.3 * rnd() as f32,
                rnd() as f32,
            )
        })
        .collect();
    let field = |x: DVec3, _: DVec3| DVec3::new(x.x.sin() + 1.0, x.y.cos() + 1.0, x.z * x.z);
    let mut c = cloud(&particles, &field, 3.0);
    c.world_from_local = CloudPlacement {
        translation: DVec3::new(0.2, 0.0, -0.5),
        rotation: DQuat::from_rotation_y(0.7),
        scale: 1.3,
    };
    let image = composite(&cam, DVec3::splat(0.05), &[], &[c], 2.0);
    let sorted = [sort_cloud(&cam, &c)];
    let all: Vec<(&SortedCloud, Vec<&Billboard>)> = sorted
        .iter()
        .map(|s| (s, s.billboards.iter().collect()))
        .collect();
    let mut covered = 0;
    for py in 0..H {
        for px in 0..W {
            let direct = shade_ray(
                &cam,
                cam.pixel_ray(px, py),
                DVec3::splat(0.05),
                &[],
                &all,
                &Seen {
                    exposure: 2.0,
                    fog: None,
                },
            );
            assert!(close(pixel(&image, px, py), direct));
            covered += (direct.x != 0.05) as usize;
        }
    }
    assert!(covered > 20);
}

/// The cloud of `particles` composited through its view transmittance, on an `n³` fine grid.
fn through_view(
    particles: &[Particle],
    scattered: ScatteredLight,
    n: usize,
    segments: u32,
    background: DVec3,
) -> Vec<[f32; 4]> {
    let fine = crate::reference::illumination::voxelize(particles, n).unwrap();
    let mut c = cloud(particles, scattered, 1.5);
    c.compositing = BillboardCompositing::ViewTransmittance(&fine);
    c.segments = segments;
    composite(&camera(), background, &[], &[c], 1.0)
}

#[test]
fn view_transmittance_of_one_particle_approaches_its_exact_light() {
    // Alone, a particle's light is its own chord's (the sorted compositing is exact then);
    // the view volume only blurs its own density, less the finer its grid.
    let particles = [particle(DVec3::new(0.1, 0.0, -4.0), 1.0, 1.2)];
    let field = |x: DVec3, _: DVec3| DVec3::new(1.0, 0.5, 0.25) * (2.0 * (x.x + 1.0)).exp();
    let mut c = cloud(&particles, &field, 1.5);
    c.segments = 16;
    let exact = composite(&camera(), DVec3::ZERO, &[], &[c], 1.0);
    let background = DVec3::new(0.2, 0.1, 0.0);
    let error = |n: usize| {
        let image = through_view(&particles, &field, n, 16, DVec3::ZERO);
        let worst = (0..W * H)
            .map(|i| (image[i as usize][0] - exact[i as usize][0]).abs())
            .fold(0.0f32, f32::max);
        worst / exact.iter().map(|p| p[0]).fold(0.0, f32::max)
    };
    let (coarse, fine) = (error(32), error(128));
    assert!(fine < 0.02 && fine < coarse, "{coarse} -> {fine}");
    // The background is dimmed by exactly the particle's own transmittance.
    let dark = |_: DVec3, _: DVec3| DVec3::ZERO;
    let image = through_view(&particles, &dark, 32, 4, background);
    let w = camera().pixel_ray(W / 2, H / 2);
    let c = particles[0].position.as_dvec3();
    let tau = particle_optical_depth(1.5, 1.2, 1.0, (c - w * c.dot(w)).length());
    assert!(close(
        pixel(&image, W / 2, H / 2),
        background * (-tau).exp()
    ));
}

#[test]
fn view_transmittance_shares_light_between_interpenetrating_particles() {
    // Two thick particles at the same place: a constant S must show as S (1 - T) of their
    // summed optical depth, whatever the order, as the medium itself would.
    let a = particle(DVec3::new(0.0, 0.0, -4.0), 0.8, 2.0);
    let b = particle(DVec3::new(0.05, 0.0, -4.02), 0.8, 2.0);
    let image = through_view(&[a, b], WHITE, 128, 8, DVec3::ZERO);
    assert_eq!(image, through_view(&[b, a], WHITE, 128, 8, DVec3::ZERO));
    let w = camera().pixel_ray(W / 2, H / 2);
    let tau: f64 = [a, b]
        .iter()
        .map(|p| {
            let c = p.position.as_dvec3();
            let impact = (c - w * c.dot(w)).length();
            particle_optical_depth(1.5, 2.0, 0.8, impact)
        })
        .sum();
    let expected = 1.0 - (-tau).exp();
    let got = pixel(&image, W / 2, H / 2).x;
    assert!(
        (got - expected).abs() < 0.02 * expected,
        "{got} vs {expected}"
    );
}
