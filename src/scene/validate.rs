//! A scene's values checked against what the renderer accepts: every error names the field, its
//! value and what is allowed.

use super::*;

pub(super) fn invalid(
    path: impl Into<String>,
    value: impl std::fmt::Display,
    allowed: impl Into<String>,
) -> SceneError {
    SceneError::Invalid {
        path: path.into(),
        value: value.to_string(),
        allowed: allowed.into(),
    }
}

/// `(x, y, z)` with Rust's shortest round-tripping float formatting.
pub(super) fn fmt_vec3(v: Vec3) -> String {
    format!("({}, {}, {})", v.x, v.y, v.z)
}

pub(super) fn check_finite(path: &str, v: Vec3) -> Result<(), SceneError> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(invalid(
            path,
            fmt_vec3(v),
            "every coordinate must be finite",
        ))
    }
}

pub(super) fn check_radiance(path: &str, v: Vec3) -> Result<(), SceneError> {
    if v.is_finite() && v.cmpge(Vec3::ZERO).all() {
        Ok(())
    } else {
        Err(invalid(
            path,
            fmt_vec3(v),
            "every component must be finite and >= 0",
        ))
    }
}

/// Maps a medium or particle error of cloud `cloud` to its field path; `note` (e.g. the particle
/// file) is appended to the message.
pub(super) fn medium_error(cloud: usize, error: InvalidMedium, note: &str) -> SceneError {
    let p = format!("clouds[{cloud}]");
    match error {
        InvalidMedium::Position { index, value } => invalid(
            format!("{p}.particles[{index}].position"),
            fmt_vec3(value),
            format!("every coordinate must be finite and within ±{MAX_PARTICLE_EXTENT:e} m{note}"),
        ),
        InvalidMedium::Radius { index, value } => invalid(
            format!("{p}.particles[{index}].radius"),
            value,
            format!("it must be > 0 and at most {MAX_PARTICLE_EXTENT:e} m{note}"),
        ),
        InvalidMedium::Density { index, value } => invalid(
            format!("{p}.particles[{index}].density"),
            value,
            format!("it must be finite and >= 0{note}"),
        ),
        InvalidMedium::Extinction(value) => invalid(
            format!("{p}.medium.extinction"),
            value,
            "it must be finite and >= 0",
        ),
        InvalidMedium::Albedo(value) => {
            invalid(format!("{p}.medium.albedo"), value, "it must lie in [0, 1]")
        }
        InvalidMedium::Anisotropy(value) => invalid(
            format!("{p}.medium.anisotropy"),
            value,
            "it must lie in (-1, 1)",
        ),
    }
}

/// Sets one field of `settings` from a `field=value` assignment written as in a scene file's
/// `settings` (for example `volume_resolution=64` or `compositing=Sorted`), as the tools' `--set`
/// does, then checks every knob's range.
pub fn apply_setting(
    settings: &mut CloudQualitySettings,
    assignment: &str,
) -> Result<(), SceneError> {
    use bevy::reflect::GetPath;
    let Some((field, value)) = assignment.split_once('=') else {
        return Err(invalid(
            "--set",
            assignment,
            "it must be field=value, e.g. volume_resolution=64",
        ));
    };
    let field = field.trim();
    // RON checks the field's name and the value's type, with the scene file's messages.
    let parsed: CloudQualitySettings = ron::from_str(&format!("({field}: {})", value.trim()))
        .map_err(|error| SceneError::Parse {
            origin: format!("--set {assignment}"),
            error: Box::new(error),
        })?;
    let unknown = || invalid("--set", assignment, "the field is not a settings field");
    let source = parsed.reflect_path(field).map_err(|_| unknown())?;
    settings
        .reflect_path_mut(field)
        .map_err(|_| unknown())?
        .apply(source);
    settings.validate().map_err(SceneError::Settings)
}

pub(super) fn validate_shadow_map_resolution(resolution: u32) -> Result<(), SceneError> {
    if SHADOW_MAP_RESOLUTIONS.contains(&resolution) {
        return Ok(());
    }
    let (lo, hi) = (SHADOW_MAP_RESOLUTIONS.start(), SHADOW_MAP_RESOLUTIONS.end());
    Err(invalid(
        "shadow_map_resolution",
        resolution,
        format!("allowed: {lo}..={hi}"),
    ))
}

pub(super) fn validate_fog(fog: Option<&Fog>) -> Result<(), SceneError> {
    fog.map_or(Ok(()), |f| {
        f.validate()
            .map_err(|e| invalid(format!("fog.{}", e.field), e.value, e.allowed))
    })
}

pub(super) fn validate_camera(c: &SceneCamera) -> Result<(), SceneError> {
    check_finite("camera.position", c.position)?;
    check_finite("camera.look_at", c.look_at)?;
    check_finite("camera.up", c.up)?;
    let view = c.look_at.as_dvec3() - c.position.as_dvec3();
    if view == DVec3::ZERO {
        return Err(invalid(
            "camera.look_at",
            fmt_vec3(c.look_at),
            format!(
                "it must differ from camera.position {}",
                fmt_vec3(c.position)
            ),
        ));
    }
    let up = c.up.as_dvec3();
    if up == DVec3::ZERO {
        return Err(invalid("camera.up", fmt_vec3(c.up), "it must not be zero"));
    }
    // sine of the angle between `up` and the viewing direction
    let sine = view.normalize().cross(up.normalize()).length();
    if sine.is_nan() || sine <= 1e-6 {
        return Err(invalid(
            "camera.up",
            fmt_vec3(c.up),
            format!(
                "it must not be parallel to the viewing direction look_at - position = {}",
                fmt_vec3(view.as_vec3())
            ),
        ));
    }
    let fov = c.vertical_fov_degrees;
    if !(fov > 0.0 && fov < 180.0) {
        return Err(invalid(
            "camera.vertical_fov_degrees",
            fov,
            "it must lie in (0, 180)",
        ));
    }
    for (name, v) in [("camera.width", c.width), ("camera.height", c.height)] {
        if !(1..=MAX_IMAGE_SIZE).contains(&v) {
            return Err(invalid(
                name,
                v,
                format!("it must be > 0 and <= {MAX_IMAGE_SIZE}"),
            ));
        }
    }
    Ok(())
}

pub(super) fn validate_object(i: usize, o: &SceneObject) -> Result<(), SceneError> {
    match o.shape {
        ObjectShape::Cuboid(e) => {
            if !(e.is_finite() && e.cmpgt(Vec3::ZERO).all()) {
                return Err(invalid(
                    format!("objects[{i}].shape"),
                    format!("Cuboid({})", fmt_vec3(e)),
                    "every extent must be finite and > 0",
                ));
            }
        }
        ObjectShape::Sphere(r) => {
            if !(r.is_finite() && r > 0.0) {
                return Err(invalid(
                    format!("objects[{i}].shape"),
                    format!("Sphere({r})"),
                    "the radius must be finite and > 0",
                ));
            }
        }
    }
    check_finite(&format!("objects[{i}].translation"), o.translation)?;
    check_radiance(&format!("objects[{i}].color"), o.color)?;
    let r = o.reflectance;
    if !(r.is_finite() && r.cmpge(Vec3::ZERO).all() && r.cmple(Vec3::ONE).all()) {
        return Err(invalid(
            format!("objects[{i}].reflectance"),
            fmt_vec3(r),
            "every component must lie in [0, 1]",
        ));
    }
    Ok(())
}

/// Everything but the clouds.
pub(super) fn validate_globals(
    camera: &SceneCamera,
    background: Vec3,
    lights: &[LightSample],
    objects: &[SceneObject],
    settings: &CloudQualitySettings,
) -> Result<(), SceneError> {
    validate_camera(camera)?;
    check_radiance("background", background)?;
    for (i, l) in lights.iter().enumerate() {
        let path = format!("lights[{i}].direction");
        check_finite(&path, l.direction)?;
        if l.direction == Vec3::ZERO {
            return Err(invalid(path, fmt_vec3(l.direction), "it must not be zero"));
        }
        check_radiance(&format!("lights[{i}].irradiance"), l.irradiance)?;
    }
    for (i, o) in objects.iter().enumerate() {
        validate_object(i, o)?;
    }
    settings.validate().map_err(SceneError::Settings)
}

/// A cloud's translation and medium.
pub(super) fn validate_cloud_header(
    i: usize,
    translation: Vec3,
    medium: &Medium,
) -> Result<(), SceneError> {
    check_finite(&format!("clouds[{i}].translation"), translation)?;
    medium.validate().map_err(|e| medium_error(i, e, ""))
}

pub(super) fn validate_particles(
    i: usize,
    particles: &[Particle],
    note: &str,
) -> Result<(), SceneError> {
    particles
        .iter()
        .enumerate()
        .try_for_each(|(j, p)| p.validate(j))
        .map_err(|e| medium_error(i, e, note))
}
