//! CPU ground-truth volumetric path tracer for exactly the model of docs/physics.md.
//!
//! What it computes, per camera ray `x_t = o + t w`:
//!
//! ```text
//! L = ∫ T(0,t) σ_s(x_t) S(x_t) dt + T(0,∞) L_background
//! S = (1/4π) ( Σ_l E_l T_l(x) + ∫ L(x, w') dw' )
//! ```
//!
//! with the exact particle kernel, Henyey–Greenstein scattering (isotropic by default), all
//! scattering orders, opaque unlit objects
//! ending rays (camera, scattered and shadow rays alike) and the constant background radiance seen by
//! every ray that escapes.
//!
//! How it estimates it (each step unbiased):
//!
//! - **Free flights** by delta tracking against a piecewise-constant majorant: a uniform grid over
//!   the clouds stores, per cell, an upper bound of `σ_t` and the list of particles overlapping the
//!   cell; rays walk the grid with a 3D DDA. A real collision at `x` happens with density
//!   `T(0,t) σ_t(x_t)`, so weighting by `σ_s/σ_t` turns it into an estimate of the first integral.
//! - **Next-event estimation** at every real collision: each directional light adds
//!   `(σ_s/σ_t) · E_l T_l(x) p(x, cos θ_l)`, `p` the phase function of the media at `x` (where
//!   clouds of different anisotropies overlap, the mixture of theirs weighted by their `σ_s`) and
//!   `θ_l` the angle between the light's travel direction and the way back along the path.
//!   `T_l` is computed *exactly*: the optical depth of one particle
//!   along a straight segment is a polynomial integral, so summing it over the particles of the cells
//!   the shadow ray crosses gives `T_l` without noise ([`Media::optical_depth`]). Shadow rays hitting
//!   an opaque object carry nothing (objects are unlit and block the light, which comes from infinity).
//!   [`transmittance`] (ratio tracking) is the stochastic alternative, kept for media without a
//!   closed form and for tests.
//! - **Multiple scattering**: the `∫ p L dw'` term is estimated by continuing the path in a
//!   direction sampled from the phase function itself (so the weight is 1): uniformly for the
//!   isotropic medium, by inverting the Henyey–Greenstein distribution otherwise, the component
//!   of a mixture chosen in proportion to its `σ_s`. Russian roulette with survival
//!   probability `σ_s/σ_t` replaces the albedo weight, so every path has weight 1 and ends by
//!   absorption, by escaping (adding `L_background`) or by hitting an object (adding its `color`).
//!   Directional lights are delta distributions: an escaping ray never "sees" them, so there is no
//!   double counting with next-event estimation.
//!
//! Transport is grey (the albedo is a scalar per cloud), so paths carry a scalar weight and colour
//! only enters through `E_l`, `L_background` and the objects' `color` and `reflectance`.
//!
//! Lit objects (a `reflectance`) reflect, as Lambertian surfaces, the irradiance of the lights
//! (shadow rays, blocked by objects and attenuated by the clouds with the exact transmittance)
//! and of the sky (one cosine-distributed direction per path, blocked or attenuated alike);
//! light the clouds scatter onto them is not part of the model (docs/physics.md).
//!
//! Camera rays start at the eye (`t = 0`, as in docs/physics.md), not at Bevy's near plane.

// One file per part of the estimate: the media it walks, the estimators, the images.
mod estimators;
mod images;
mod media;
#[cfg(test)]
mod tests;

pub use estimators::{
    DENSE_SEGMENT, DirectionalLight, Lighting, radiance, radiance_by_order, sample_free_flight,
    transmittance,
};
pub use images::{
    PathTracerSettings, Progress, noise_level, render, render_media, render_media_orders,
    render_orders, render_within_limit,
};
pub use media::{Coefficients, Media, ParticleMedia, Segment};

/// Safety cap on real scattering events per path. It is the only source of bias: paths are cut
/// after this many events. With Russian roulette on the albedo a path of albedo `ω < 1` has
/// `ω/(1-ω)` events on average (99 for `ω = 0.99`); at `ω = 1` paths end by escaping, after about
/// `τ²` events in a medium of optical radius `τ`, so the cap only matters for `τ ≳ 300`.
pub const MAX_SCATTER_EVENTS: u32 = 100_000;
