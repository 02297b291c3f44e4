//! Quality knobs of the real-time renderer.
//!
//! Every knob lives in [`CloudQualitySettings`], a component on a [`ParticleCloud`](crate::ParticleCloud)
//! entity; clouds without it use the [`DefaultCloudQuality`] resource. Scene files carry the same
//! struct under `settings`. The cost and error of each knob are measured by the time–error
//! benchmark (see the README).

use bevy::{
    prelude::*,
    render::{extract_component::ExtractComponent, extract_resource::ExtractResource},
};
use serde::Deserialize;

/// How one multiple-scattering iteration carries light between voxels (docs/illumination.md §4).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect, Deserialize)]
#[reflect(Default, Debug, PartialEq)]
pub enum ScatterStencil {
    /// A discrete-ordinates sweep: along each of the 26 lattice directions, the radiance arriving
    /// at every voxel is marched from upwind to downwind through the whole grid, attenuated and
    /// fed by the scattering of every segment it crosses (with `S` linear along each segment).
    /// Light passes through many voxels in one iteration, so no order is lost to the voxel size,
    /// and the result converges to the transport solution as the resolution grows. The default.
    #[default]
    DiscreteOrdinates,
    /// The paper's Algorithm 2: every one of the 26 neighbours weighted by the voxel's own
    /// opacity, `albedo / 26 * (1 - exp(-sigma_t h)) * S_j`. Kept for comparison: it loses energy
    /// at every order, more the finer the grid.
    Paper,
}

/// The directions along which the discrete-ordinates sweep carries radiance between voxels
/// (docs/illumination.md §4, "Detail finer than a mean free path"). More directions resolve the
/// angular detail of the radiance that a fine grid's sharp source casts (fewer ray effects), for
/// more sweep work: one dispatch per direction pair, each marching every voxel twice.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect, Deserialize)]
#[reflect(Default, Debug, PartialEq)]
pub enum SweepDirections {
    /// The 26 directions to a voxel's neighbours (components in {-1, 0, 1}), equally weighted
    /// in each order's mean: 13 dispatches per iteration. The default.
    #[default]
    Lattice26,
    /// The 98 primitive lattice directions with components in `-2..=2`, each weighted by the
    /// solid angle nearest it: 49 dispatches per iteration, 3.6x the re-lit frame of the
    /// `cumulus` benchmark scene at 96³ on llvmpipe. For scattering grids of optically thin
    /// voxels: there it removes the ray effects that made 128³ read worse than 96³ (`cumulus`
    /// at 96³ 0.0110 -> 0.0065, at 128³ 0.0058). Its steps of up to 3 voxels err on coarse
    /// grids (at 48³ `cumulus` reads worse), and the albedo-1 `albedo_one` reads worse with it
    /// (0.0134 -> 0.0156 at 96³; docs/performance.md, "Sweep directions").
    Lattice98,
}

/// How a cloud's billboards are composited over what is behind them (docs/illumination.md §5).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect, Deserialize)]
#[reflect(Default, Debug, PartialEq)]
pub enum Compositing {
    /// The paper's compositing: particles sorted back to front by centre depth (on the GPU, once
    /// per view change) and blended whole over each other, each with its exact alpha. The cloud is
    /// drawn whole, ordered by its centre against other clouds. Exact for
    /// particles that do not overlap along a ray; optically thick particles that interpenetrate
    /// hide each other's light as whole discs, so it errs where they do (0.069 on the
    /// benchmark's `albedo_one` cloud, growing with the resolution), but it draws each particle
    /// once and shades fewer points.
    Sorted,
    /// Every piece of a particle's chord is seen through the whole cloud's optical depth towards
    /// the camera, read from a per-view volume marched through the fine density grid once per view
    /// change, and through the volumes of the other such clouds that overlap it on screen. Each
    /// particle's light is added and the background is multiplied by every particle's
    /// transmittance, so no order is needed: interpenetrating particles, and interpenetrating
    /// clouds, hide each other's light only where they overlap. The volume blurs the other particles' shadows by about a fine
    /// voxel, so it wants a fine grid (`light_supersampling` 3 or more) and 8 chord segments. The
    /// default: with those it is within the accuracy goals on every benchmark scene, and
    /// `Sorted` reads worse on five of seven (twice the error where optically thick particles
    /// interpenetrate; docs/accuracy.md, "Compositing").
    #[default]
    ViewTransmittance,
}

/// Where a billboard evaluates the light its particle scatters towards the camera
/// (docs/illumination.md §5).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect, Deserialize)]
#[reflect(Default, Debug, PartialEq)]
pub enum BillboardShading {
    /// At `chord_segments` points along each pixel's chord through the particle: a big particle
    /// shows its lit and its dark side. Each point reads every light's optical depth and the
    /// multiple scattering. The default.
    #[default]
    Chord,
    /// Once per particle, at its centre towards the camera (the paper's): every pixel of the
    /// billboard takes that light, so the pixels read no illumination volume and the draw costs
    /// a fraction of `Chord`'s; a particle large against the light's variation shows one tone.
    /// Alpha stays exact, and the view transmittance still weighs each chord segment.
    Centre,
}

/// How a view's billboards become pixels (docs/illumination.md §6). The image is the same, up to
/// the rounding of the rasteriser's blend.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect, Deserialize)]
#[reflect(Default, Debug, PartialEq)]
pub enum DrawMethod {
    /// The GPU's rasteriser draws a quad per particle in Bevy's `Transparent3d` phase, and a
    /// fragment shader shades each pixel of it, blended into the view's target after every
    /// particle. For views that interleave clouds with transparent meshes. The blend rounds
    /// after each particle into the target's f16: on llvmpipe, whose conversion to f16 rounds
    /// towards zero, that darkens the image by 0.1-1.3 % of its energy (its relative RMSE
    /// against the path tracer +0.0027 on the `cumulus` benchmark scene, +0.0149 on
    /// `thin_smoke`; docs/performance.md, "The draw's rounding").
    Raster,
    /// A compute shader evaluates the same pixels of every view-transmittance cloud and sums
    /// their light and optical depth per pixel of a cloud target (at `cloud_target_scale`, full
    /// size included) in f32, which is then composited onto the view, between the opaque and the
    /// transparent passes. The default: exact, and the faster draw of the paper's scene on both
    /// adapters measured (0.032× the rasterised draw's time on an NVIDIA H200, 0.57× on
    /// llvmpipe; docs/performance.md, "On a real GPU"). `Sorted` clouds are still rasterised, into the
    /// same target, over the computed ones; where the adapter cannot compute the draw (a target
    /// above its storage binding, fewer than 11 storage buffers per stage), the view is
    /// rasterised.
    #[default]
    Compute,
}

/// Per-cloud quality knobs. Missing fields in scene files take these defaults.
#[derive(Component, Clone, Copy, Debug, PartialEq, Reflect, Deserialize)]
#[serde(default, deny_unknown_fields)]
#[reflect(Component, Default, Debug, PartialEq)]
pub struct CloudQualitySettings {
    /// Voxels per side `N` of the cloud's density and multiple-scattering volumes. Allowed:
    /// `MIN_VOLUME_RESOLUTION..=MAX_VOLUME_RESOLUTION`. Default 48, chosen from the time–error
    /// benchmark (docs/benchmarking.md): the cheapest resolution at which every
    /// benchmark scene is within its accuracy goal. The image's error follows the fine grid
    /// (`volume_resolution * light_supersampling`) more than this: raise `light_supersampling`
    /// first (docs/performance.md, "The fine grid, not the scattering grid, sets the error").
    /// Past 96 the error does not fall on every benchmark scene (on the cumulus scenes and
    /// `albedo_one` 128 reads up to 0.0005 above 96; docs/performance.md, "Results").
    pub volume_resolution: u32,
    /// Multiple-scattering iterations `M` (scattering orders computed beyond the first); the
    /// orders past `M` are estimated from the last four (two geometric modes), then
    /// `scatter_coarse_cycles` correct the sum. 0 = single scattering only. Allowed:
    /// `0..=MAX_SCATTER_ITERATIONS`. Default 8, with 2 coarse-grid cycles: the deep orders of
    /// thick clouds of albedo near 1 (20 % of their light lies past order 16) are the cycles'
    /// work. Without cycles, 32 or more: more iterations converge to the grid's own solution,
    /// whose error is set by `volume_resolution`; the series' closure is ill-conditioned on
    /// thick albedo-1 clouds, where it falls back to one mode and converges slowly (16, 32 and
    /// 64 orders: 0.056, 0.047, 0.036 on the benchmark's `albedo_one`; README,
    /// "Limitations").
    pub scatter_iterations: u32,
    /// Multiple-scattering iterations when only the lights changed since the last solve (a
    /// moving sun): the scattering restarts from the solution the cloud holds, and computes the
    /// correction's series in this many iterations, closed like `scatter_iterations`' series
    /// (docs/illumination.md §4). The first frame the lights stay still, the full series settles
    /// it. 0 = always the full series. Allowed: 0 or `2..=MAX_SCATTER_ITERATIONS`. Default 4: in
    /// the benchmark, a sun that jumps 5° between solves gives an image within 0.0030 (relative
    /// RMSE) of the full solve's, for 0.07–0.16 of its scattering cost on lavapipe
    /// (docs/performance.md, "Warm restart under a moving sun").
    pub warm_scatter_iterations: u32,
    /// Two-grid cycles after the full series' `scatter_iterations` orders (docs/illumination.md
    /// §4, "Coarse-grid cycles"): each sweeps the grid for the residual of the solution, solves
    /// for its smooth part in [`COARSE_GRID_ORDERS`] orders on a grid of half the resolution,
    /// adds it, and sweeps once more. They converge to the grid's own solution, which thick,
    /// bright clouds reach only after hundreds of orders; a cycle costs about 6 sweeps of the
    /// grid (2 fine, and 32 of an eighth of the voxels). With the discrete-ordinates stencil
    /// only (the paper's ignores it); an odd `volume_resolution` has no coarse grid, and its
    /// cycles only sweep. Not in a warm restart. 0 = off (the series alone). Allowed:
    /// `0..=MAX_SCATTER_COARSE_CYCLES`. Default 2, after 8 iterations: in the benchmark they
    /// reach the grid's converged solution (on the thick, albedo-1 `albedo_one` 0.020 relative
    /// RMSE after a 4×4 box, where 32 iterations of the series read 0.025), and its error falls
    /// as `volume_resolution` rises, at 0.6–0.93× the series' wall time on lavapipe
    /// (docs/performance.md, "Coarse-grid cycles").
    pub scatter_coarse_cycles: u32,
    /// Fraction `f` in `[0, 1]` of scattered light treated as continuing forward in the shading
    /// pass (the paper's forward scattering): light attenuates with `sigma_t * (1 - f * albedo)`.
    /// Default 0, which is exactly the isotropic model of docs/physics.md.
    pub forward_scattering: f32,
    /// The multiple-scattering stencil. Default [`ScatterStencil::DiscreteOrdinates`].
    pub scatter_stencil: ScatterStencil,
    /// The directions the discrete-ordinates sweep carries radiance along (the paper's stencil
    /// ignores it). Default [`SweepDirections::Lattice26`].
    pub scatter_directions: SweepDirections,
    /// The density the lights shine through and each light's optical-depth volume have
    /// `volume_resolution * light_supersampling` voxels per side, at most
    /// [`MAX_LIGHT_RESOLUTION`] (see [`Self::light_resolution`]); this fine grid need not be a
    /// whole multiple of the scattering grid. Single scattering, which the billboards evaluate
    /// straight from these volumes, is then sharper than the multiple-scattering grid. Allowed:
    /// `1..=MAX_LIGHT_SUPERSAMPLING`. Default 4: the fine grid sets the error more than the
    /// scattering grid does, and 48³ at 4 beats 48³ at 3 on 18 of the 20 benchmark scenes, for
    /// 0.89–1.61× a re-lit frame's wall time on lavapipe (docs/performance.md, "Supersampling 4,
    /// the default"). Where one cloud's light volumes (4 bytes a voxel, per light) would not fit
    /// the adapter's storage binding (128 MiB on lavapipe and WebGPU's default: 5 lights at the
    /// default 48³ need 142 MB), the renderer shades that cloud on the largest fine grid that
    /// fits (5 lights: 188³), at least `volume_resolution`, and says so once.
    pub light_supersampling: u32,
    /// Segments `K` of each pixel's chord through a particle at which the billboard evaluates the
    /// illumination (a big particle shows its lit and its dark side). Alpha is exact whatever
    /// `K`. Allowed: `1..=MAX_CHORD_SEGMENTS`. Default 8.
    pub chord_segments: u32,
    /// How the billboards are composited. Default [`Compositing::ViewTransmittance`].
    pub compositing: Compositing,
    /// Where the billboards evaluate the scattered light: along each pixel's chord, or once per
    /// particle at its centre. Default [`BillboardShading::Chord`].
    pub billboard_shading: BillboardShading,
    /// The billboards are drawn into a target of this fraction of the view's size per axis, then
    /// enlarged onto the view with a depth-aware upsample (the paper's §4 fill-rate
    /// optimisation; docs/illumination.md §6). A view draws all its clouds at one scale: its
    /// camera's [`CloudTargetScale`] if it has one, else the largest scale any cloud it sees
    /// asks for. Allowed: `MIN_CLOUD_TARGET_SCALE..=1`. Default 1 (full size).
    pub cloud_target_scale: f32,
    /// How the billboards become pixels. A view computes its clouds' pixels when any cloud it
    /// sees asks for [`DrawMethod::Compute`], so a view is rasterised when every cloud it sees
    /// asks for [`DrawMethod::Raster`] (set it in [`DefaultCloudQuality`]).
    /// Default [`DrawMethod::Compute`].
    pub draw_method: DrawMethod,
}

/// Smallest allowed `volume_resolution`.
pub const MIN_VOLUME_RESOLUTION: u32 = 4;
/// Largest allowed `volume_resolution` (a 256³ RGBA f32 volume is 256 MiB), and the largest
/// resolution of a light's volume.
pub const MAX_VOLUME_RESOLUTION: u32 = 256;
/// Largest allowed `scatter_iterations`.
pub const MAX_SCATTER_ITERATIONS: u32 = 4096;
/// Largest allowed `scatter_coarse_cycles`.
pub const MAX_SCATTER_COARSE_CYCLES: u32 = 64;
/// Orders of the series each coarse-grid cycle sums on the grid of half the resolution, closed
/// with two modes (docs/illumination.md §4, "Coarse-grid cycles").
pub const COARSE_GRID_ORDERS: u32 = 32;
/// Largest allowed `light_supersampling`.
pub const MAX_LIGHT_SUPERSAMPLING: u32 = 4;
/// Largest side of the fine density grid and of a light's optical-depth volume (`512³` f32 is
/// 512 MiB): [`CloudQualitySettings::light_resolution`] is `volume_resolution` times
/// `light_supersampling`, at most this. Twice `MAX_VOLUME_RESOLUTION`, so that the fine grid
/// rises with `volume_resolution` to 128 at any `light_supersampling`, and never falls after (an
/// adapter's storage binding may still lower it sooner).
pub const MAX_LIGHT_RESOLUTION: u32 = 512;
/// Largest allowed `chord_segments`.
pub const MAX_CHORD_SEGMENTS: u32 = 16;
/// Smallest allowed `cloud_target_scale` (an eighth of the view's size per axis).
pub const MIN_CLOUD_TARGET_SCALE: f32 = 0.125;

impl Default for CloudQualitySettings {
    fn default() -> Self {
        Self::DEFAULT
    }
}

impl CloudQualitySettings {
    /// The defaults ([`Default`]), usable in constants.
    pub const DEFAULT: Self = Self {
        volume_resolution: 48,
        scatter_iterations: 8,
        warm_scatter_iterations: 4,
        scatter_coarse_cycles: 2,
        forward_scattering: 0.0,
        scatter_stencil: ScatterStencil::DiscreteOrdinates,
        scatter_directions: SweepDirections::Lattice26,
        light_supersampling: 4,
        chord_segments: 8,
        compositing: Compositing::ViewTransmittance,
        billboard_shading: BillboardShading::Chord,
        cloud_target_scale: 1.0,
        draw_method: DrawMethod::Compute,
    };

    /// Voxels per side of the fine density grid and of each light's optical-depth volume:
    /// `volume_resolution * light_supersampling`, at most [`MAX_LIGHT_RESOLUTION`] (and at least
    /// `volume_resolution`). It never falls as either knob rises.
    pub fn light_resolution(&self) -> u32 {
        let wanted = self
            .volume_resolution
            .saturating_mul(self.light_supersampling.max(1));
        wanted.min(MAX_LIGHT_RESOLUTION).max(self.volume_resolution)
    }

    /// Whether `light_supersampling` is the default's. The renderer and the `render` tool lower
    /// the default's fine grid to what the adapter binds as documented behaviour (info), and
    /// any other's with a warning or a refusal.
    pub fn light_supersampling_is_default(&self) -> bool {
        self.light_supersampling == Self::DEFAULT.light_supersampling
    }

    /// The coarse-grid cycles the full series is followed by: `scatter_coarse_cycles` with the
    /// discrete-ordinates stencil and at least one iteration, else 0.
    pub fn coarse_cycles(&self) -> u32 {
        let sweeps = self.scatter_stencil == ScatterStencil::DiscreteOrdinates;
        if sweeps && self.scatter_iterations > 0 {
            self.scatter_coarse_cycles
        } else {
            0
        }
    }

    /// Whether the scattering grid has a coarse grid of half its side for the cycles: they run,
    /// and `volume_resolution` is even.
    pub fn has_coarse_grid(&self) -> bool {
        self.coarse_cycles() > 0 && self.volume_resolution.is_multiple_of(2)
    }
}

/// Why a settings value is refused; each variant names the field, its value and what is allowed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("`{}` is {}; {}", self.field(), self.value(), self.allowed())]
pub enum InvalidSettings {
    /// `volume_resolution` outside `MIN_VOLUME_RESOLUTION..=MAX_VOLUME_RESOLUTION`.
    VolumeResolution(u32),
    /// `scatter_iterations` above `MAX_SCATTER_ITERATIONS`.
    ScatterIterations(u32),
    /// `warm_scatter_iterations` 1 or above `MAX_SCATTER_ITERATIONS`.
    WarmScatterIterations(u32),
    /// `scatter_coarse_cycles` above `MAX_SCATTER_COARSE_CYCLES`.
    ScatterCoarseCycles(u32),
    /// `forward_scattering` outside `[0, 1]` (or NaN).
    ForwardScattering(f32),
    /// `light_supersampling` outside `1..=MAX_LIGHT_SUPERSAMPLING`.
    LightSupersampling(u32),
    /// `chord_segments` outside `1..=MAX_CHORD_SEGMENTS`.
    ChordSegments(u32),
    /// `cloud_target_scale` outside `[MIN_CLOUD_TARGET_SCALE, 1]` (or NaN).
    CloudTargetScale(f32),
}

impl InvalidSettings {
    /// The refused field's name, as in [`CloudQualitySettings`] and scene files.
    pub fn field(&self) -> &'static str {
        match self {
            Self::VolumeResolution(_) => "volume_resolution",
            Self::ScatterIterations(_) => "scatter_iterations",
            Self::WarmScatterIterations(_) => "warm_scatter_iterations",
            Self::ScatterCoarseCycles(_) => "scatter_coarse_cycles",
            Self::ForwardScattering(_) => "forward_scattering",
            Self::LightSupersampling(_) => "light_supersampling",
            Self::ChordSegments(_) => "chord_segments",
            Self::CloudTargetScale(_) => "cloud_target_scale",
        }
    }

    /// The refused value, as written.
    pub fn value(&self) -> String {
        match self {
            Self::VolumeResolution(v)
            | Self::ScatterIterations(v)
            | Self::WarmScatterIterations(v)
            | Self::ScatterCoarseCycles(v)
            | Self::LightSupersampling(v)
            | Self::ChordSegments(v) => v.to_string(),
            Self::ForwardScattering(v) | Self::CloudTargetScale(v) => v.to_string(),
        }
    }

    /// What is allowed.
    pub fn allowed(&self) -> String {
        match self {
            Self::VolumeResolution(_) => {
                format!("allowed is {MIN_VOLUME_RESOLUTION}..={MAX_VOLUME_RESOLUTION}")
            }
            Self::ScatterIterations(_) => format!("allowed is 0..={MAX_SCATTER_ITERATIONS}"),
            Self::WarmScatterIterations(_) => {
                format!("allowed is 0 (off) or 2..={MAX_SCATTER_ITERATIONS}")
            }
            Self::ScatterCoarseCycles(_) => format!("allowed is 0..={MAX_SCATTER_COARSE_CYCLES}"),
            Self::ForwardScattering(_) => "it must lie in [0, 1]".into(),
            Self::LightSupersampling(_) => format!("allowed is 1..={MAX_LIGHT_SUPERSAMPLING}"),
            Self::ChordSegments(_) => format!("allowed is 1..={MAX_CHORD_SEGMENTS}"),
            Self::CloudTargetScale(_) => {
                format!("it must lie in [{MIN_CLOUD_TARGET_SCALE}, 1]")
            }
        }
    }
}

impl CloudQualitySettings {
    /// Checks every knob's range.
    pub fn validate(&self) -> Result<(), InvalidSettings> {
        if !(MIN_VOLUME_RESOLUTION..=MAX_VOLUME_RESOLUTION).contains(&self.volume_resolution) {
            return Err(InvalidSettings::VolumeResolution(self.volume_resolution));
        }
        if self.scatter_iterations > MAX_SCATTER_ITERATIONS {
            return Err(InvalidSettings::ScatterIterations(self.scatter_iterations));
        }
        let warm = self.warm_scatter_iterations;
        if warm == 1 || warm > MAX_SCATTER_ITERATIONS {
            return Err(InvalidSettings::WarmScatterIterations(warm));
        }
        if self.scatter_coarse_cycles > MAX_SCATTER_COARSE_CYCLES {
            return Err(InvalidSettings::ScatterCoarseCycles(
                self.scatter_coarse_cycles,
            ));
        }
        if !(0.0..=1.0).contains(&self.forward_scattering) {
            return Err(InvalidSettings::ForwardScattering(self.forward_scattering));
        }
        if !(1..=MAX_LIGHT_SUPERSAMPLING).contains(&self.light_supersampling) {
            return Err(InvalidSettings::LightSupersampling(
                self.light_supersampling,
            ));
        }
        if !(1..=MAX_CHORD_SEGMENTS).contains(&self.chord_segments) {
            return Err(InvalidSettings::ChordSegments(self.chord_segments));
        }
        if !(MIN_CLOUD_TARGET_SCALE..=1.0).contains(&self.cloud_target_scale) {
            return Err(InvalidSettings::CloudTargetScale(self.cloud_target_scale));
        }
        Ok(())
    }
}

/// A camera's cloud target scale: its clouds are drawn into a target of this fraction of its
/// size per axis, then enlarged onto it with a depth-aware upsample. Overrides the
/// `cloud_target_scale` of the clouds it sees. Allowed: `MIN_CLOUD_TARGET_SCALE..=1`; a value
/// outside is clamped into it, NaN draws at full size, with a warning naming the camera.
#[derive(Component, Clone, Copy, Debug, PartialEq, Reflect, Deref, ExtractComponent)]
#[reflect(Component, Default, Debug, PartialEq)]
pub struct CloudTargetScale(pub f32);

impl Default for CloudTargetScale {
    fn default() -> Self {
        Self(1.0)
    }
}

impl CloudTargetScale {
    /// The scale in effect: clamped into `MIN_CLOUD_TARGET_SCALE..=1`, full size for NaN.
    pub fn effective(self) -> f32 {
        if self.0.is_nan() {
            1.0
        } else {
            self.0.clamp(MIN_CLOUD_TARGET_SCALE, 1.0)
        }
    }
}

/// The settings of clouds that have no [`CloudQualitySettings`] component.
#[derive(Resource, Clone, Copy, Debug, Default, PartialEq, Reflect, Deref, DerefMut)]
#[reflect(Resource, Default, Debug, PartialEq)]
pub struct DefaultCloudQuality(pub CloudQualitySettings);

/// The most clouds re-lit in one frame (a resource; docs/illumination.md §8).
///
/// When the sun moves every frame, every visible cloud must be re-lit every frame. With a budget
/// of `n`, only the `n` clouds that have waited longest do their illumination work this frame;
/// the others keep drawing with their previous illumination (the sun where it was when they were
/// last re-lit) until their turn, so a frame re-lights at most `n` clouds and each cloud is
/// re-lit at least every `ceil(clouds / n)` frames. A cloud that has never been illuminated is
/// always illuminated at once (it could not be drawn otherwise). A still sky re-lights nothing,
/// whatever the budget. `0`, the default, means no limit.
#[derive(Resource, ExtractResource, Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect)]
#[reflect(Resource, Default, Debug, PartialEq)]
pub struct CloudRelightBudget(pub u32);

/// When a computing view draws its clouds again (a resource; docs/illumination.md §6, "A still
/// view keeps its image").
///
/// The computed draw (`DrawMethod::Compute`) leaves a view's clouds in its cloud target, which
/// is composited onto the view every frame. Where nothing the target shows can have changed
/// since the view last drew it, drawing it again gives the same texels, so by default the view
/// keeps it.
#[derive(Resource, ExtractResource, Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect)]
#[reflect(Resource, Default, Debug, PartialEq)]
pub enum CloudRedraw {
    /// Draw only when something the target shows may have changed: the camera (its transform,
    /// projection, viewport, exposure) or its fog, which clouds it splats and their uniforms, any
    /// illumination or view-volume pass having run since, the texture handed to the target, or
    /// (checked on the GPU, per target texel) the opaque depth its particles are tested against.
    /// A view that also rasterises `Sorted` clouds into its target draws every frame.
    #[default]
    WhenChanged,
    /// Draw every frame. For measuring the draw itself (the benchmark's static frames).
    EveryFrame,
}

/// How the scattering sweep marches each lattice line (docs/illumination.md §4, "The march").
///
/// A resource of the main world, extracted to the render world. Both marches compute the same
/// arithmetic in the same order, so the same volumes; they differ in when each step loads its
/// inputs, which suits one kind of adapter or the other (docs/performance.md, "On a real GPU").
#[derive(Resource, ExtractResource, Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect)]
#[reflect(Resource, Default, Debug, PartialEq)]
pub enum SweepMarch {
    /// [`SweepMarch::Serial`] on a CPU adapter (llvmpipe), else [`SweepMarch::ReadAhead`].
    #[default]
    Auto,
    /// Each step loads what it needs as it needs it. On llvmpipe the scattering takes
    /// 0.6–0.9× the read-ahead march's time.
    Serial,
    /// Each step loads the voxel two ahead and the next voxel's sum so far, so that its own
    /// arithmetic hides their latency: on an NVIDIA H200 the scattering takes 0.81× the serial
    /// march's time.
    ReadAhead,
}

impl SweepMarch {
    /// Whether the sweep reads ahead, on an adapter that is a CPU (`cpu`) or not.
    pub fn reads_ahead(self, cpu: bool) -> bool {
        match self {
            Self::Auto => !cpu,
            Self::Serial => false,
            Self::ReadAhead => true,
        }
    }
}

/// How the scattering sweep dispatches an order's direction pairs (docs/illumination.md §4,
/// "One dispatch per order").
///
/// A resource of the main world, extracted to the render world. The pairs of an order are
/// independent: each reads the order `S_n` and adds its share to `S_{n+1}`. One dispatch per pair
/// adds into `S_{n+1}` in place, so the pairs run one after another; one dispatch per order runs
/// them side by side, each into a volume of its own, then sums those in the pairs' order. Both
/// give the same volumes up to f32 rounding. On a GPU whose sweeps are too few lattice lines to
/// fill it (a sweep's time follows its lines' length, not its voxels: docs/performance.md, "On a
/// real GPU"), one dispatch per order gives it 13 (or 49) times the lines at once; it has not
/// been measured on one yet.
#[derive(Resource, ExtractResource, Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect)]
#[reflect(Resource, Default, Debug, PartialEq)]
pub enum SweepDispatch {
    /// One dispatch per direction pair, each adding its share into the next order in place.
    #[default]
    PerPair,
    /// One dispatch per order for every pair, each into a volume of its own (13 or 49 times a
    /// pool's order volume of GPU memory, kept while the pool lives), then one that sums them.
    /// A pool whose pair volumes would not fit one storage binding sweeps per pair.
    PerOrder,
}

/// How the shade pass computes each light's transmittance volume (docs/illumination.md §2).
///
/// A resource of the main world, extracted to the render world. Both methods give the same
/// volume (up to f32 rounding); the brute force exists to measure what the incremental pass saves
/// (`cargo run --example benchmark -- illumination`). A change takes effect the next time a
/// light is shaded (when a light, the density or the extinction changes).
#[derive(Resource, ExtractResource, Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect)]
#[reflect(Resource, Default, Debug, PartialEq)]
pub enum ShadingMethod {
    /// The paper's Algorithm 4: one invocation per column along the light, each slice the
    /// previous one times one step's attenuation: `n²` invocations of `n` steps.
    #[default]
    Incremental,
    /// Every voxel marches to the light on its own: `n³` invocations of up to `n` steps.
    BruteForce,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Raising `volume_resolution` or `light_supersampling` never shrinks the fine grid, which
    /// sets the error: it rises with `volume_resolution` until it reaches `MAX_LIGHT_RESOLUTION`,
    /// which it never passes (at 96³ × 4 the former cap of 256 gave 192, 64³'s 256; a factor
    /// lowered to a whole number gave 160³ × 4 a grid of 480).
    #[test]
    fn the_fine_grid_grows_with_volume_resolution() {
        let fine = |volume_resolution, light_supersampling| {
            CloudQualitySettings {
                volume_resolution,
                light_supersampling,
                ..CloudQualitySettings::DEFAULT
            }
            .light_resolution()
        };
        for l in 1..=MAX_LIGHT_SUPERSAMPLING {
            for n in MIN_VOLUME_RESOLUTION..MAX_VOLUME_RESOLUTION {
                let (here, next) = (fine(n, l), fine(n + 1, l));
                assert!(next >= here, "L{l}: {n} -> {}", n + 1);
                assert!(next > here || here == MAX_LIGHT_RESOLUTION, "L{l}: {n}");
                assert!(next <= MAX_LIGHT_RESOLUTION && here >= n);
                if l < MAX_LIGHT_SUPERSAMPLING {
                    assert!(fine(n, l + 1) >= here, "L{l} -> L{}: {n}", l + 1);
                }
            }
        }
        assert_eq!(fine(128, 4), 512);
        assert_eq!(fine(160, 4), 512);
        assert_eq!(fine(256, 1), 256);
        assert_eq!(CloudQualitySettings::DEFAULT.light_resolution(), 192);
    }
}
