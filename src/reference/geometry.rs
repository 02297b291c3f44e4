//! Ray intersection with the opaque objects of a scene, and their surface normals.

use bevy::math::DVec3;

use crate::scene::{ObjectShape, SceneObject};

/// Distance `t > 0` along the ray `origin + t * dir` to the first hit of `object`, if any.
pub fn intersect_object(object: &SceneObject, origin: DVec3, dir: DVec3) -> Option<f64> {
    let centre = object.translation.as_dvec3();
    match object.shape {
        ObjectShape::Sphere(radius) => intersect_sphere(centre, radius as f64, origin, dir),
        ObjectShape::Cuboid(extents) => {
            intersect_box(centre, extents.as_dvec3() * 0.5, origin, dir)
        }
    }
}

/// The outward unit normal of `object` at its surface point `x`: for a box, that of the face `x`
/// lies on (the axis where `x` is nearest the box's extent).
pub fn object_normal(object: &SceneObject, x: DVec3) -> DVec3 {
    let offset = x - object.translation.as_dvec3();
    match object.shape {
        ObjectShape::Sphere(_) => offset.normalize_or_zero(),
        ObjectShape::Cuboid(extents) => {
            let q = offset / (extents.as_dvec3() * 0.5);
            let a = q.abs();
            let axis = if a.x >= a.y && a.x >= a.z {
                DVec3::X
            } else if a.y >= a.z {
                DVec3::Y
            } else {
                DVec3::Z
            };
            axis * q.dot(axis).signum()
        }
    }
}

/// The nearest object hit along a ray: `(t, object index)`.
pub fn nearest_object(objects: &[SceneObject], origin: DVec3, dir: DVec3) -> Option<(f64, usize)> {
    objects
        .iter()
        .enumerate()
        .filter_map(|(i, o)| intersect_object(o, origin, dir).map(|t| (t, i)))
        .min_by(|a, b| a.0.total_cmp(&b.0))
}

/// First positive hit of a ray with a sphere.
pub fn intersect_sphere(centre: DVec3, radius: f64, origin: DVec3, dir: DVec3) -> Option<f64> {
    let oc = origin - centre;
    let b = oc.dot(dir);
    let c = oc.length_squared() - radius * radius;
    let disc = b * b - c * dir.length_squared();
    if disc < 0.0 {
        return None;
    }
    let a = dir.length_squared();
    let sq = disc.sqrt();
    let t0 = (-b - sq) / a;
    let t1 = (-b + sq) / a;
    if t0 > 0.0 {
        Some(t0)
    } else if t1 > 0.0 {
        Some(t1)
    } else {
        None
    }
}

/// First positive hit of a ray with an axis-aligned box (slab method); inside the box, the exit.
pub fn intersect_box(centre: DVec3, half: DVec3, origin: DVec3, dir: DVec3) -> Option<f64> {
    let inv = dir.recip();
    let t_a = (centre - half - origin) * inv;
    let t_b = (centre + half - origin) * inv;
    let t_near = t_a.min(t_b).max_element();
    let t_far = t_a.max(t_b).min_element();
    if t_far < t_near.max(0.0) {
        return None;
    }
    Some(if t_near > 0.0 { t_near } else { t_far })
}

/// Range `[t0, t1]` (clipped to `t >= 0`) where a ray is inside a box, if any.
pub fn box_interval(lo: DVec3, hi: DVec3, origin: DVec3, dir: DVec3) -> Option<(f64, f64)> {
    let inv = dir.recip();
    let t_a = (lo - origin) * inv;
    let t_b = (hi - origin) * inv;
    let t0 = t_a.min(t_b).max_element().max(0.0);
    let t1 = t_a.max(t_b).min_element();
    (t1 > t0).then_some((t0, t1))
}
