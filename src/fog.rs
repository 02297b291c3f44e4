//! Distance fog over the clouds (docs/physics.md, "Fog"): Bevy's `DistanceFog`, as the billboards,
//! the CPU reference and the path tracer evaluate it.
//!
//! Bevy fogs an opaque fragment at distance `d` from the camera as `c' = c V(d) + A(d) F`, and a
//! premultiplied transparent one (coverage `α`) as `c' = c V(d) + α A(d) F`: `V` is what the fog
//! lets through, `A` how much of its colour `F` it adds, `F` the fog's colour plus the
//! directional lights' glow towards the ray. A cloud is fogged piece by piece the same way: each
//! piece of each chord at its own distance, with the share of the view it covers as `α`. Summed
//! along a ray, that is the exact fog of a volume the fog permeates (docs/physics.md).

use bevy::math::{DVec3, Vec3};
use bevy::reflect::Reflect;
use serde::Deserialize;

/// How the fog thickens with distance; the variants and formulas of Bevy's `FogFalloff`.
#[derive(Clone, Copy, Debug, PartialEq, Deserialize, Reflect)]
pub enum Falloff {
    /// None before `start`, all of it after `end`, linear between (metres, `start < end`).
    Linear {
        /// Distance where the fog starts, metres.
        start: f32,
        /// Distance where the fog hides everything, metres.
        end: f32,
    },
    /// `1 - exp(-density d)` of the fog colour; `density` per metre, >= 0.
    Exponential {
        /// Per metre.
        density: f32,
    },
    /// `1 - exp(-(density d)²)` of the fog colour; `density` per metre, >= 0.
    ExponentialSquared {
        /// Per metre.
        density: f32,
    },
    /// Separate extinction and in-scattering per channel: what is behind keeps
    /// `1 - α (1 - exp(-extinction d))`, and `α (1 - exp(-inscattering d))` of the fog colour is
    /// added; both per metre, >= 0.
    Atmospheric {
        /// Per metre, linear RGB.
        extinction: Vec3,
        /// Per metre, linear RGB.
        inscattering: Vec3,
    },
}

/// Distance fog: Bevy's `DistanceFog` (its colours in linear RGB), and a scene file's `fog`.
#[derive(Clone, Copy, Debug, PartialEq, Deserialize, Reflect)]
#[serde(deny_unknown_fields)]
pub struct Fog {
    /// The fog's colour, linear RGB radiance (at exposure 1), each >= 0.
    pub color: Vec3,
    /// How much fog: the `DistanceFog` colour's alpha, in `[0, 1]`; default 1.
    #[serde(default = "one")]
    pub alpha: f32,
    /// How the fog thickens with distance.
    pub falloff: Falloff,
    /// Added to the colour where the ray looks towards a directional light, times that light's
    /// irradiance (linear RGB, each >= 0, its alpha multiplied in); default black (no glow).
    #[serde(default)]
    pub directional_light_color: Vec3,
    /// Sharpness of that glow: `max(cos θ, 0)^exponent` about each light; > 0, default 8.
    #[serde(default = "eight")]
    pub directional_light_exponent: f32,
}

fn one() -> f32 {
    1.0
}

fn eight() -> f32 {
    8.0
}

/// A fog value out of range: `fog.FIELD is VALUE; ALLOWED`.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("fog.{field} is {value}; {allowed}")]
pub struct InvalidFog {
    /// The field, e.g. `falloff.density`.
    pub field: &'static str,
    /// Its value as written.
    pub value: String,
    /// What is allowed.
    pub allowed: &'static str,
}

/// What the fog does at one distance: `c' = c transmitted + α inscattered F`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FogAt {
    /// The share of the radiance behind that reaches the camera, per channel.
    pub transmitted: DVec3,
    /// The share of the fog colour added (per unit coverage), per channel.
    pub inscattered: DVec3,
}

impl Fog {
    /// Checks every value; the message names the field, its value and what is allowed.
    pub fn validate(&self) -> Result<(), InvalidFog> {
        let invalid = |field, value: String, allowed| InvalidFog {
            field,
            value,
            allowed,
        };
        let colour = |field, c: Vec3| {
            (c.is_finite() && c.min_element() >= 0.0)
                .then_some(())
                .ok_or_else(|| invalid(field, format!("{c}"), "each must be finite and >= 0"))
        };
        colour("color", self.color)?;
        colour("directional_light_color", self.directional_light_color)?;
        if !(0.0..=1.0).contains(&self.alpha) {
            return Err(invalid("alpha", self.alpha.to_string(), "allowed: [0, 1]"));
        }
        let exponent = self.directional_light_exponent;
        if !(exponent.is_finite() && exponent > 0.0) {
            return Err(invalid(
                "directional_light_exponent",
                exponent.to_string(),
                "must be finite and > 0",
            ));
        }
        match self.falloff {
            Falloff::Linear { start, end } => {
                if !(start.is_finite() && end.is_finite() && start < end) {
                    return Err(invalid(
                        "falloff",
                        format!("Linear(start: {start}, end: {end})"),
                        "start and end must be finite, start < end",
                    ));
                }
            }
            Falloff::Exponential { density } | Falloff::ExponentialSquared { density } => {
                if !(density.is_finite() && density >= 0.0) {
                    return Err(invalid(
                        "falloff.density",
                        density.to_string(),
                        "must be finite and >= 0",
                    ));
                }
            }
            Falloff::Atmospheric {
                extinction,
                inscattering,
            } => {
                colour("falloff.extinction", extinction)?;
                colour("falloff.inscattering", inscattering)?;
            }
        }
        Ok(())
    }

    /// The fog at `distance` metres from the camera.
    pub fn at(&self, distance: f64) -> FogAt {
        let alpha = self.alpha as f64;
        // Bevy's `1 - 1 / exp(x)`, without its overflow for large x.
        let thickening = |x: f64| -(-x).exp_m1();
        let amount = match self.falloff {
            Falloff::Linear { start, end } => {
                let (start, end) = (start as f64, end as f64);
                1.0 - ((end - distance) / (end - start)).clamp(0.0, 1.0)
            }
            Falloff::Exponential { density } => thickening(distance * density as f64),
            Falloff::ExponentialSquared { density } => {
                thickening((distance * density as f64).powi(2))
            }
            Falloff::Atmospheric {
                extinction,
                inscattering,
            } => {
                let per_channel =
                    |k: Vec3| k.as_dvec3().to_array().map(|k| thickening(distance * k));
                return FogAt {
                    transmitted: DVec3::ONE - DVec3::from(per_channel(extinction)) * alpha,
                    inscattered: DVec3::from(per_channel(inscattering)) * alpha,
                };
            }
        };
        FogAt {
            transmitted: DVec3::splat(1.0 - alpha * amount),
            inscattered: DVec3::splat(alpha * amount),
        }
    }

    /// The fog's colour `F` seen along the unit ray `ray`: its colour plus each light's glow,
    /// `directional_light_color × max(ray · to_light, 0)^exponent × E`; `lights` are
    /// `(unit direction towards the light, irradiance)`.
    pub fn colour_towards(
        &self,
        ray: DVec3,
        lights: impl IntoIterator<Item = (DVec3, DVec3)>,
    ) -> DVec3 {
        let glow: DVec3 = lights
            .into_iter()
            .map(|(to_light, irradiance)| {
                let cosine = ray.dot(to_light).max(0.0);
                irradiance * cosine.powf(self.directional_light_exponent as f64)
            })
            .sum();
        self.color.as_dvec3() + self.directional_light_color.as_dvec3() * glow
    }

    /// `radiance` (premultiplied, covering `coverage` of the view) fogged at `distance` with the
    /// fog colour `colour` ([`Self::colour_towards`]).
    pub fn apply(&self, radiance: DVec3, coverage: f64, distance: f64, colour: DVec3) -> DVec3 {
        let at = self.at(distance);
        radiance * at.transmitted + at.inscattered * colour * coverage
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fog(falloff: Falloff) -> Fog {
        Fog {
            color: Vec3::new(0.5, 0.6, 0.7),
            alpha: 1.0,
            falloff,
            directional_light_color: Vec3::ZERO,
            directional_light_exponent: 8.0,
        }
    }

    #[test]
    fn falloffs_follow_bevys_formulas() {
        let d = 30.0;
        let linear = fog(Falloff::Linear {
            start: 10.0,
            end: 50.0,
        });
        assert!((linear.at(d).inscattered.x - 0.5).abs() < 1e-12);
        assert_eq!(linear.at(5.0).transmitted, DVec3::ONE);
        assert_eq!(linear.at(80.0).transmitted, DVec3::ZERO);
        let exponential = fog(Falloff::Exponential { density: 0.02 });
        assert!((exponential.at(d).transmitted.x - (-0.6f64).exp()).abs() < 1e-7);
        let squared = fog(Falloff::ExponentialSquared { density: 0.02 });
        assert!((squared.at(d).transmitted.y - (-0.36f64).exp()).abs() < 1e-7);
        let mut atmospheric = fog(Falloff::Atmospheric {
            extinction: Vec3::new(0.01, 0.02, 0.03),
            inscattering: Vec3::new(0.03, 0.02, 0.01),
        });
        atmospheric.alpha = 0.5;
        let at = atmospheric.at(d);
        assert!((at.transmitted.z - (1.0 - 0.5 * (1.0 - (-0.9f64).exp()))).abs() < 1e-7);
        assert!((at.inscattered.x - 0.5 * (1.0 - (-0.9f64).exp())).abs() < 1e-7);
        // Far enough, the exponential fogs hide everything, without overflow.
        assert_eq!(exponential.at(1e9).transmitted, DVec3::ZERO);
    }

    #[test]
    fn an_opaque_fragment_mixes_towards_the_fog_colour_and_glows_towards_lights() {
        let mut f = fog(Falloff::Exponential { density: 0.1 });
        f.directional_light_color = Vec3::new(1.0, 0.5, 0.0);
        f.directional_light_exponent = 2.0;
        let lights = [(DVec3::Z, DVec3::splat(2.0))];
        // Away from the light: the fog colour alone.
        assert_eq!(f.colour_towards(-DVec3::Z, lights), f.color.as_dvec3());
        // 60° off the light: cos² = 1/4 of the irradiance, times the glow colour.
        let ray = DVec3::new(0.75f64.sqrt(), 0.0, 0.5);
        let colour = f.colour_towards(ray, lights);
        assert!(
            (colour - DVec3::new(1.0, 0.85, 0.7)).length() < 1e-6,
            "{colour}"
        );
        let c = f.apply(DVec3::ONE, 1.0, 10.0, colour);
        let v = (-1.0f64).exp();
        assert!((c - (DVec3::ONE * v + colour * (1.0 - v))).length() < 1e-7);
    }

    #[test]
    fn bad_values_name_their_field() {
        let mut f = fog(Falloff::Exponential { density: -1.0 });
        assert_eq!(
            f.validate().unwrap_err().to_string(),
            "fog.falloff.density is -1; must be finite and >= 0"
        );
        f.falloff = Falloff::Linear {
            start: 5.0,
            end: 5.0,
        };
        assert!(
            f.validate()
                .unwrap_err()
                .to_string()
                .starts_with("fog.falloff is Linear")
        );
        f.falloff = Falloff::ExponentialSquared { density: 0.1 };
        f.alpha = 1.5;
        assert_eq!(f.validate().unwrap_err().field, "alpha");
        f.alpha = 1.0;
        f.color = Vec3::new(f32::NAN, 0.0, 0.0);
        assert_eq!(f.validate().unwrap_err().field, "color");
        f.color = Vec3::ONE;
        f.directional_light_exponent = 0.0;
        assert_eq!(
            f.validate().unwrap_err().field,
            "directional_light_exponent"
        );
        f.directional_light_exponent = 8.0;
        assert_eq!(f.validate(), Ok(()));
    }
}
