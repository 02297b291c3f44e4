//! Every stage for one cloud, several clouds or a scene, and section 5: the illumination at a
//! shading point.

use bevy::math::{DQuat, DVec3};
use rayon::prelude::*;

use super::coarse_cycles::{CoarseCycles, scatter_cycles_through};
use super::gather::{
    Moments, flux_along, gather_source, quadrupole_along, single_scattering_towards,
};
use super::interpolation::unravel;
use super::scatter::{Boundary, MultipleScattering, SweptMedium, scatter_through};
use super::shade::{LightVolume, ShadeInputs, shade};
use super::voxelize::{DensityGrid, voxelize};
use crate::beam_phase::BeamPhase;
use crate::ground::CloudGround;
use crate::particle::{DeltaM, LightSample, Medium, Particle};
use crate::reference::composite::CloudPlacement;
use crate::reference::ground::GroundLight;
use crate::settings::{COARSE_GRID_ORDERS, CloudQualitySettings, Compositing};

/// A directional light in the cloud's local space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalLight {
    /// Direction the light travels, local space; any non-zero length.
    pub direction: DVec3,
    /// Linear RGB irradiance `E` perpendicular to the direction.
    pub irradiance: DVec3,
}

impl LocalLight {
    /// The local light of a world light for a cloud with rotation `rotation`: direction
    /// `normalize(R^-1 d)` (zero if `d` is zero), irradiance unchanged.
    pub fn from_world(light: &LightSample, rotation: DQuat) -> Self {
        Self {
            direction: (rotation.inverse() * light.direction.as_dvec3()).normalize_or_zero(),
            irradiance: light.irradiance.as_dvec3(),
        }
    }
}

/// Everything [`illuminate`] computed for one cloud.
#[derive(Clone, Debug, PartialEq)]
pub struct CloudIllumination {
    /// The scattering grid's density (section 1), `volume_resolution` voxels per side.
    pub grid: DensityGrid,
    /// The fine density grid the lights are shaded through (section 1), `light_resolution()`
    /// voxels per side (or the side [`illuminate_at_light_resolution`] was given).
    pub fine: DensityGrid,
    /// Local extinction `K_local = K s` used, 1/local metre.
    pub k_local: f64,
    /// The medium's albedo used.
    pub albedo: f64,
    /// The medium's Henyey–Greenstein `g`.
    pub anisotropy: f64,
    /// Each shaded light's volume with its irradiance (section 2), in input order, with the
    /// shadows of the clouds illuminated with it; lights with zero irradiance or zero direction
    /// are left out.
    pub lights: Vec<(LightVolume, DVec3)>,
    /// The same light volumes before other clouds' shadows: the cloud's own optical depth, what
    /// it casts on others and on the shadow maps.
    pub own_lights: Vec<LightVolume>,
    /// The multiple-scattering source `S_0` per voxel (section 3): its mean, and its flux for
    /// an anisotropic medium.
    pub source: Moments,
    /// Multiple scattering per voxel (section 4).
    pub multiple: MultipleScattering,
    /// How the camera sees the δ-M beam's excess (section 5); `None` for a medium the
    /// transform does not truncate.
    pub beam: Option<BeamPhase>,
}

/// [`illuminate_under_sky`] under a black sky.
pub fn illuminate(
    particles: &[Particle],
    medium: &Medium,
    scale: f64,
    lights_local: &[LocalLight],
    settings: &CloudQualitySettings,
) -> Option<CloudIllumination> {
    illuminate_under_sky(
        particles,
        medium,
        scale,
        lights_local,
        DVec3::ZERO,
        settings,
    )
}

/// Runs every stage of the contract for one cloud, under a uniform sky of radiance `sky` (linear
/// RGB, the units of `E` per steradian; section 4).
///
/// `scale`: the cloud's uniform world scale `s > 0` (so `K_local = medium.extinction * s`);
/// `lights_local`: directions already in local space (see [`LocalLight::from_world`]). Lights with
/// zero irradiance, or a zero / non-finite direction, are skipped. Returns `None` when no particle
/// has `density > 0`. With no lights everything is zero; with zero extinction `T = 1` everywhere.
pub fn illuminate_under_sky(
    particles: &[Particle],
    medium: &Medium,
    scale: f64,
    lights_local: &[LocalLight],
    sky: DVec3,
    settings: &CloudQualitySettings,
) -> Option<CloudIllumination> {
    let m = settings.light_resolution();
    illuminate_at_light_resolution(particles, medium, scale, lights_local, sky, settings, m)
}

/// [`illuminate_under_sky`] on a fine grid of `light_resolution` voxels per side (at least
/// `settings.volume_resolution`) instead of the settings' own: what the renderer shades a cloud
/// on where the adapter's storage binding lowers its fine grid.
pub fn illuminate_at_light_resolution(
    particles: &[Particle],
    medium: &Medium,
    scale: f64,
    lights_local: &[LocalLight],
    sky: DVec3,
    settings: &CloudQualitySettings,
    light_resolution: u32,
) -> Option<CloudIllumination> {
    let m = light_resolution.max(settings.volume_resolution);
    shade_cloud(particles, medium, scale, lights_local, (settings, m))
        .map(|shaded| shaded.finish((sky, None), settings, None))
}

/// One of several clouds illuminated together ([`illuminate_clouds_under_sky`]).
#[derive(Clone, Copy)]
pub struct PlacedCloud<'a> {
    /// Particles in cloud-local space.
    pub particles: &'a [Particle],
    /// The cloud's medium.
    pub medium: Medium,
    /// Its transform: lights are taken to its local space, and other clouds' points too.
    pub placement: CloudPlacement,
    /// Its quality knobs (clouds may differ, as in a game).
    pub settings: CloudQualitySettings,
}

/// Runs every stage of the contract for clouds that shadow each other, under the world `lights`
/// and a uniform sky `sky`, each cloud at its own settings: each cloud's light volumes take,
/// beside its own optical depth, the optical depth every other cloud casts on it (section 2,
/// [`LightVolume::cast_depth_at`]), before its single and multiple scattering are gathered and
/// scattered. One entry per cloud, `None` for a cloud without density. A cloud alone is
/// [`illuminate_under_sky`] exactly.
pub fn illuminate_clouds_under_sky(
    clouds: &[PlacedCloud],
    lights: &[LightSample],
    sky: DVec3,
) -> Vec<Option<CloudIllumination>> {
    illuminate_clouds_over_ground(clouds, lights, sky, None)
}

/// [`illuminate_clouds_under_sky`] over `ground` (section 4, "The ground"): each cloud's
/// multiple scattering takes the ground's radiance in on the lattice lines that climb into its
/// grid ([`GroundLight`], from its light volumes once the other clouds' shadows are in them),
/// the sky's on the others. `None`: no ground, the sky's from every side.
pub fn illuminate_clouds_over_ground(
    clouds: &[PlacedCloud],
    lights: &[LightSample],
    sky: DVec3,
    ground: Option<&CloudGround>,
) -> Vec<Option<CloudIllumination>> {
    let mut shaded: Vec<Option<ShadedCloud>> = clouds
        .iter()
        .map(|cloud| {
            let rotation = cloud.placement.rotation;
            let local: Vec<LocalLight> = lights
                .iter()
                .map(|l| LocalLight::from_world(l, rotation))
                .collect();
            let scale = cloud.placement.scale;
            let m = cloud.settings.light_resolution();
            shade_cloud(
                cloud.particles,
                &cloud.medium,
                scale,
                &local,
                (&cloud.settings, m),
            )
        })
        .collect();
    let placements: Vec<CloudPlacement> = clouds.iter().map(|c| c.placement).collect();
    cast_shadows(&mut shaded, &placements);
    let foreign = foreign_media(&shaded, &placements);
    shaded
        .into_iter()
        .zip(clouds)
        .zip(&foreign)
        .map(|((s, cloud), foreign)| {
            let boundary = (sky, ground.map(|g| (g, cloud.placement)));
            s.map(|s| s.finish(boundary, &cloud.settings, foreign.as_deref()))
        })
        .collect()
}

/// Adds to every cloud's light volumes the optical depth the other clouds cast on it (contract
/// section 2): at each voxel centre `p` of cloud `a`'s volume of light `l`,
/// `tau += sum_b cast_b,l(p)` over the other clouds `b`, with [`LightVolume::cast_depth_at`] of
/// `b`'s *own* volume of light `l` at `p` taken to `b`'s local space. Optical depths add along a
/// line, so this is the optical depth of all the clouds, each sampled on its own light box. The
/// clouds' light lists must match (the same lights in the same order), as the scene's lights do.
fn cast_shadows(clouds: &mut [Option<ShadedCloud>], placements: &[CloudPlacement]) {
    let own: Vec<Option<Vec<LightVolume>>> = clouds
        .iter()
        .map(|c| c.as_ref().map(|c| c.own.clone()))
        .collect();
    for (a, cloud) in clouds.iter_mut().enumerate() {
        let Some(cloud) = cloud else { continue };
        for (l, (volume, _)) in cloud.lights.iter_mut().enumerate() {
            let casters: Vec<(&LightVolume, &CloudPlacement)> = own
                .iter()
                .zip(placements)
                .enumerate()
                .filter(|&(b, _)| b != a)
                .filter_map(|(_, (volumes, placement))| {
                    Some((volumes.as_ref()?.get(l)?, placement))
                })
                .collect();
            if casters.is_empty() {
                continue;
            }
            let receiver = own[a].as_ref().map(|v| &v[l]).expect("a shaded cloud");
            let n = receiver.n;
            volume
                .optical_depth
                .par_iter_mut()
                .enumerate()
                .for_each(|(idx, tau)| {
                    let (i, j, k) = unravel(idx, n);
                    let world = placements[a].world_point(receiver.voxel_centre(i, j, k));
                    *tau += casters
                        .iter()
                        .map(|(v, placement)| v.cast_depth_at(placement.local_point(world)))
                        .sum::<f64>();
                });
        }
    }
}

/// Per voxel of every cloud's scattering grid, the other clouds' media there (section 4,
/// "Clouds that overlap"): at the voxel's centre, `sum_c c_c K_c rho_c / K` and
/// `sum_c c_c albedo'_c K_c rho_c / K`, `rho_c` trilinear in cloud `c`'s scattering grid (zero
/// outside it), `K` the world extinctions and `c_c`, `albedo'_c` cloud `c`'s δ-M
/// transform (1 and its albedo for an isotropic medium). `None` for a cloud no other cloud's
/// medium reaches.
fn foreign_media(
    clouds: &[Option<ShadedCloud>],
    placements: &[CloudPlacement],
) -> Vec<Option<Vec<[f64; 2]>>> {
    let world_extinction = |c: &ShadedCloud, p: &CloudPlacement| c.inputs.k_local / p.scale;
    clouds
        .iter()
        .zip(placements)
        .enumerate()
        .map(|(a, (cloud, placement))| {
            let cloud = cloud.as_ref()?;
            let extinction = world_extinction(cloud, placement);
            if extinction <= 0.0 {
                return None;
            }
            let others: Vec<(&ShadedCloud, &CloudPlacement)> = clouds
                .iter()
                .zip(placements)
                .enumerate()
                .filter(|&(b, _)| b != a)
                .filter_map(|(_, (c, p))| Some((c.as_ref()?, p)))
                .collect();
            let media: Vec<[f64; 2]> = (0..cloud.grid.len())
                .into_par_iter()
                .map(|i| {
                    let world = placement.world_point(cloud.grid.voxel_centre_linear(i));
                    others.iter().fold([0.0; 2], |[t, s], (c, p)| {
                        let delta = c.delta();
                        let sigma = delta.depth_scale * world_extinction(c, p) / extinction
                            * c.grid.sample(p.local_point(world));
                        [t + sigma, s + delta.albedo * sigma]
                    })
                })
                .collect();
            media.iter().any(|m| m[0] > 0.0).then_some(media)
        })
        .collect()
}

/// A cloud's density grids and light volumes (sections 1 and 2), before the other clouds cast
/// their shadows on it and its scattering is gathered.
struct ShadedCloud {
    fine: DensityGrid,
    grid: DensityGrid,
    inputs: ShadeInputs,
    anisotropy: f64,
    lights: Vec<(LightVolume, DVec3)>,
    /// The light volumes before other clouds' shadows.
    own: Vec<LightVolume>,
}

/// Sections 1 and 2 for one cloud (see [`illuminate_under_sky`] for the arguments) on a fine
/// grid of `m` voxels per side.
fn shade_cloud(
    particles: &[Particle],
    medium: &Medium,
    scale: f64,
    lights_local: &[LocalLight],
    (settings, m): (&CloudQualitySettings, u32),
) -> Option<ShadedCloud> {
    let fine = voxelize(particles, m as usize)?;
    let grid = fine.averaged_onto(settings.volume_resolution as usize);
    let inputs = ShadeInputs {
        k_local: medium.extinction as f64 * scale,
        albedo: medium.albedo as f64,
        forward_scattering: settings.forward_scattering as f64,
        resolution: m as usize,
    };
    let lights: Vec<(LightVolume, DVec3)> = lights_local
        .iter()
        .filter(|l| l.irradiance != DVec3::ZERO && l.direction.try_normalize().is_some())
        .map(|l| (shade(&fine, &inputs, l.direction), l.irradiance))
        .collect();
    Some(ShadedCloud {
        fine,
        grid,
        inputs,
        anisotropy: medium.anisotropy as f64,
        own: lights.iter().map(|(v, _)| v.clone()).collect(),
        lights,
    })
}

impl ShadedCloud {
    /// The δ-M transform of its medium.
    pub(super) fn delta(&self) -> DeltaM {
        DeltaM::new(self.inputs.albedo, self.anisotropy)
    }

    /// Sections 3 and 4: the source gathered from the light volumes, and its multiple scattering
    /// under the sky `sky` and, with a ground, over it (the cloud placed by the placement given),
    /// and with `foreign`, other clouds' media in the scattering grid (section 4).
    fn finish(
        self,
        (sky, ground): (DVec3, Option<(&CloudGround, CloudPlacement)>),
        settings: &CloudQualitySettings,
        foreign: Option<&[[f64; 2]]>,
    ) -> CloudIllumination {
        let ground = ground
            .map(|(g, placement)| GroundLight::new(g, placement, &self.grid, &self.lights, sky));
        let boundary = Boundary {
            sky,
            ground: ground.as_ref(),
        };
        let delta = self.delta();
        let source = gather_source(&self.grid, &self.fine, &self.lights, delta);
        let medium = SweptMedium {
            grid: &self.grid,
            k_local: self.inputs.k_local,
            albedo: self.inputs.albedo,
            delta,
            foreign,
            directions: settings.scatter_directions,
        };
        let stencil = settings.scatter_stencil;
        let iterations = settings.scatter_iterations;
        let multiple = match settings.coarse_cycles() {
            0 => scatter_through(medium, stencil, &source, boundary, iterations),
            cycles => {
                let schedule = CoarseCycles {
                    fine_orders: iterations,
                    cycles,
                    coarse_orders: COARSE_GRID_ORDERS,
                };
                scatter_cycles_through(medium, &source, boundary, schedule)
            }
        };
        CloudIllumination {
            grid: self.grid,
            fine: self.fine,
            k_local: self.inputs.k_local,
            albedo: self.inputs.albedo,
            anisotropy: self.anisotropy,
            lights: self.lights,
            own_lights: self.own,
            source,
            multiple,
            beam: BeamPhase::new(self.anisotropy),
        }
    }
}

/// Cloud `index` of `scene` as [`illuminate_clouds_under_sky`] illuminates it among the scene's
/// other clouds (their shadows included), with the scene's lights and its background as the sky.
/// Scene clouds are translated only, so local and world directions agree.
pub fn illuminate_scene_cloud(
    scene: &crate::scene::Scene,
    index: usize,
    settings: &CloudQualitySettings,
) -> Option<CloudIllumination> {
    illuminate_scene(scene, settings).swap_remove(index)
}

/// Every cloud of `scene`, illuminated together ([`illuminate_clouds_over_ground`]), with the
/// scene's lights, its background as the sky and its ground ([`Scene::cloud_ground`](crate::scene::Scene::cloud_ground)).
pub fn illuminate_scene(
    scene: &crate::scene::Scene,
    settings: &CloudQualitySettings,
) -> Vec<Option<CloudIllumination>> {
    let clouds: Vec<PlacedCloud> = scene
        .clouds
        .iter()
        .map(|c| PlacedCloud {
            particles: &c.particles,
            medium: c.medium,
            placement: CloudPlacement::at(c.translation.as_dvec3()),
            settings: *settings,
        })
        .collect();
    let sky = scene.background.as_dvec3();
    let ground = scene.cloud_ground();
    illuminate_clouds_over_ground(&clouds, &scene.lights, sky, ground.as_ref())
}

impl CloudIllumination {
    /// What a particle scatters towards the camera at local point `p` along the view ray's unit
    /// local direction `ray` (section 5): `albedo (S_1(p, ray) + S_m(p))`, `S_1` from the light
    /// volumes with the phase function towards the camera and `S_m` the multiple scattering,
    /// trilinear and clamped to the edge. Radiance in the units of `E`.
    pub fn scattered_at(&self, p: DVec3, ray: DVec3) -> DVec3 {
        let medium = (self.albedo, self.anisotropy);
        let single = single_scattering_towards(&self.lights, p, medium, ray, self.beam.as_ref());
        (single + self.multiple_towards(p, -ray)) * self.albedo
    }

    /// The multiple scattering at local point `p` scattered towards the unit direction `w`
    /// (section 5): `max(S_m(p), 0)`, and for an anisotropic medium the Henyey–Greenstein phase
    /// function applied to its first three angular moments,
    /// `max(mean + 3 g F . w + (15/2) g² w^T Q w, 0)`; all trilinear and clamped to the edge.
    /// The cycles' last sweep may leave `S_m` a relative 1e-4 below 0 beside a sharp edge of the
    /// light; radiance is not negative.
    pub fn multiple_towards(&self, p: DVec3, w: DVec3) -> DVec3 {
        let m = &self.multiple;
        let mean = self.grid.sample_clamped(&m.total, p);
        if m.flux.is_empty() {
            return mean.max(DVec3::ZERO);
        }
        let g = self.anisotropy;
        let flux = self.grid.sample_clamped_array(&m.flux, p);
        let quadrupole = self.grid.sample_clamped_array(&m.quadrupole, p);
        (mean + flux_along(&flux, w) * (3.0 * g) + quadrupole_along(&quadrupole, w) * (7.5 * g * g))
            .max(DVec3::ZERO)
    }

    /// `S_m` of every voxel of the scattering grid scattered towards a camera at local point
    /// `camera` (section 5, "An anisotropic cloud seen from the camera"):
    /// [`multiple_towards`](Self::multiple_towards) at the voxel's centre, towards the camera
    /// (the mean alone where the camera is at the centre). `None` for an isotropic medium, whose
    /// `S_m` is the same in every direction.
    pub fn multiple_seen_from(&self, camera: DVec3) -> Option<Vec<DVec3>> {
        if self.multiple.flux.is_empty() {
            return None;
        }
        let seen = (0..self.multiple.total.len()).into_par_iter().map(|i| {
            let centre = self.grid.voxel_centre_linear(i);
            self.multiple_towards(centre, (camera - centre).normalize_or_zero())
        });
        Some(seen.collect())
    }

    /// What the billboards of this cloud see from a camera at local point `camera` with
    /// `compositing`: through the view transmittance, an anisotropic cloud's `S_m` comes from
    /// [`multiple_seen_from`](Self::multiple_seen_from), as on the GPU; otherwise the light is
    /// [`scattered_at`](Self::scattered_at).
    pub fn seen_from(&self, camera: DVec3, compositing: Compositing) -> SeenIllumination<'_> {
        let seen = match compositing {
            Compositing::ViewTransmittance => self.multiple_seen_from(camera),
            Compositing::Sorted => None,
        };
        SeenIllumination {
            illumination: self,
            multiple: seen,
        }
    }
}

/// A cloud's illumination as the billboards of one camera see it
/// ([`CloudIllumination::seen_from`]).
pub struct SeenIllumination<'a> {
    illumination: &'a CloudIllumination,
    /// `S_m` per voxel towards the camera, where the billboards read it from a volume.
    multiple: Option<Vec<DVec3>>,
}

impl SeenIllumination<'_> {
    /// [`CloudIllumination::scattered_at`], with `S_m` trilinear in the volume seen from the
    /// camera where there is one.
    pub fn scattered_at(&self, p: DVec3, ray: DVec3) -> DVec3 {
        let ill = self.illumination;
        let Some(multiple) = &self.multiple else {
            return ill.scattered_at(p, ray);
        };
        let medium = (ill.albedo, ill.anisotropy);
        let single = single_scattering_towards(&ill.lights, p, medium, ray, ill.beam.as_ref());
        (single + ill.grid.sample_clamped(multiple, p)) * ill.albedo
    }
}

#[cfg(test)]
mod tests;
