//! The series' closure: the tail past the last computed order, from the orders' ratio (one
//! geometric mode, or two).

use super::*;

/// Largest per-order ratio `lambda` the series closure assumes.
pub const MAX_ORDER_RATIO: f64 = 0.995;

/// The two-mode closure's slower ratio must leave at least this many times the faster one's
/// distance to 1: nearer, its coefficients cancel so strongly that the tail follows the last two
/// orders' differences rather than their sum, and the geometric closure is taken instead. The
/// two-mode tail takes its full weight from [`MODE_SEPARATION_FULL`] on.
pub const MODE_SEPARATION: f64 = 1.5;

/// The modes' separation from which the two-mode tail takes its full weight.
pub const MODE_SEPARATION_FULL: f64 = 2.0;

/// The two-mode fit divides by `det = N_{M-2}^2 - N_{M-1} N_{M-3}`, which vanishes as the faster
/// mode dies out, and its tail grows as `1 / (1 - r1)`: a relative change `e` of the sizes (their
/// f32 rounding, the order of a GPU's atomic adds, a particle that moved) moves the tail by
/// about `e / y`, `y = |det| / N_{M-2}^2 (1 - r1)` (measured on thick, bright clouds). Below
/// this `y` the geometric closure is taken, which the two-mode tail has come close to by then
/// (within 3 % at `y` = 6e-6 on such clouds). The two-mode tail takes its full weight from
/// [`CONDITIONING_FULL`] on, log-linearly between: an `e` of 1e-7 then moves the tail by at
/// most 1e-3.
pub const CONDITIONING: f64 = 1e-5;

/// The conditioning `y` from which the two-mode tail takes its full weight.
pub const CONDITIONING_FULL: f64 = 1e-4;

/// The ratio of the slower mode from which (down) the two-mode tail takes its full weight; it
/// takes none at [`MAX_ORDER_RATIO`].
pub const ORDER_RATIO_FULL: f64 = 0.99;

/// The ratio of the faster mode from which (up) the two-mode tail takes its full weight; it
/// takes none at 0 (an alternating mode).
pub const FAST_RATIO_FULL: f64 = 0.02;

/// An order's size for the closure, per channel: `sum rho |S_k|` over the voxels. The orders of
/// the full series are never negative; those of a warm restart's correction may be, and their
/// absolute values keep the ratio from cancelling.
pub fn order_size(grid: &DensityGrid, order: &[DVec3]) -> DVec3 {
    grid.rho
        .iter()
        .zip(order)
        .fold(DVec3::ZERO, |acc, (rho, s)| acc + s.abs() * *rho)
}

/// The per-order ratio of the last two orders, per channel: `lambda = |S_M| / |S_{M-1}|`
/// ([`order_size`]), clamped to `[0, MAX_ORDER_RATIO]` (0 where the earlier order carries
/// nothing).
pub fn order_ratio(grid: &DensityGrid, last: &[DVec3], before: &[DVec3]) -> DVec3 {
    let (num, den) = (order_size(grid, last), order_size(grid, before));
    DVec3::from_array(std::array::from_fn(|c| geometric_ratio(num[c], den[c])))
}

pub(super) fn geometric_ratio(last: f64, before: f64) -> f64 {
    if before > 0.0 {
        (last / before).clamp(0.0, MAX_ORDER_RATIO)
    } else {
        0.0
    }
}

/// How the scattering series is closed past its last order `S_M` (docs/illumination.md §4): the
/// orders left over sum to `last S_M + before S_{M-1}`, per channel.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SeriesClosure {
    /// The coefficient of `S_M`.
    pub last: DVec3,
    /// The coefficient of `S_{M-1}`.
    pub before: DVec3,
}

impl SeriesClosure {
    /// The orders past `S_M` taken as geometric with the ratio of the last two order sizes:
    /// `S_M lambda / (1 - lambda)`. `sizes` ends with `|S_{M-1}|, |S_M|`.
    pub fn geometric(sizes: &[DVec3]) -> Self {
        let mut closure = Self::default();
        if let [.., before, last] = sizes {
            for c in 0..3 {
                let lambda = geometric_ratio(last[c], before[c]);
                closure.last[c] = lambda / (1.0 - lambda);
            }
        }
        closure
    }

    /// The orders past `S_M` taken as the sum of two geometric modes, `A r1^k + B r2^k` per
    /// voxel, whose ratios fit the last four order sizes exactly (`sizes` ends with
    /// `|S_{M-3}|, ..., |S_M|`). Their sizes obey `N_{k+2} = p N_{k+1} - q N_k`
    /// (`p = r1 + r2`, `q = r1 r2`), so the tail is `((p - q) S_M - q S_{M-1}) / (1 - p + q)`.
    /// The per-order ratio still rises after the first orders (light reaching the cloud's
    /// inside); one geometric mode holds it at its last value, and shapes the tail like the
    /// last order. Per channel, the two-mode tail is blended with the geometric one by
    /// [`two_mode_weight`], which falls continuously to 0 where the fit stops being two
    /// well-conditioned modes with `0 <= r2 < r1 <= MAX_ORDER_RATIO`, so that the tail never
    /// jumps as the sizes change a little; every channel is closed geometrically where `sizes`
    /// holds fewer than four.
    pub fn two_mode(sizes: &[DVec3]) -> Self {
        let mut closure = Self::geometric(sizes);
        let [.., n0, n1, n2, n3] = sizes else {
            return closure;
        };
        for c in 0..3 {
            if let Some(fit) = TwoModes::fit([n0[c], n1[c], n2[c], n3[c]]) {
                let w = fit.weight;
                closure.last[c] = w * fit.last + (1.0 - w) * closure.last[c];
                closure.before[c] = w * fit.before;
            }
        }
        closure
    }

    /// The orders past `last` (`S_M`; `before`: `S_{M-1}`): `last S_M + before S_{M-1}`, every
    /// moment alike. Where a channel has two modes, its mean is kept between 0 and
    /// `MAX_ORDER_RATIO / (1 - MAX_ORDER_RATIO) S_M`, the tails of one geometric mode from
    /// ratio 0 to the largest, so that no fit can take the solution past the energy bound
    /// ([`energy_bound`]); a geometric tail lies there already, so the bound does not jump as a
    /// channel's two-mode weight reaches 0. `zero`: moments of zeros shaped like the orders.
    pub(super) fn tail(&self, zero: &Moments, last: &Moments, before: &Moments) -> Moments {
        let mut tail = zero.plus(last, self.last).plus(before, self.before);
        let most = MAX_ORDER_RATIO / (1.0 - MAX_ORDER_RATIO);
        for (t, s) in tail.mean.iter_mut().zip(&last.mean) {
            for c in 0..3 {
                if self.before[c] != 0.0 {
                    let bound = most * s[c];
                    t[c] = t[c].clamp(bound.min(0.0), bound.max(0.0));
                }
            }
        }
        tail
    }
}

/// A two-mode fit of one channel's last four order sizes: the tail's coefficients of `S_M` and
/// `S_{M-1}`, and the weight in `(0, 1]` the closure gives them (the geometric tail the rest).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TwoModes {
    /// The coefficient of `S_M`: `(p - q) / (1 - p + q)`.
    pub last: f64,
    /// The coefficient of `S_{M-1}`: `-q / (1 - p + q)`.
    pub before: f64,
    /// [`two_mode_weight`] of the fit.
    pub weight: f64,
}

impl TwoModes {
    /// The fit of the sizes `[N_{M-3}, N_{M-2}, N_{M-1}, N_M]`, or `None` where its weight is 0.
    pub fn fit([n0, n1, n2, n3]: [f64; 4]) -> Option<Self> {
        // N_M = p N_{M-1} - q N_{M-2} and N_{M-1} = p N_{M-2} - q N_{M-3}.
        let det = n1 * n1 - n2 * n0;
        let p = (n1 * n2 - n3 * n0) / det;
        let q = (n2 * n2 - n1 * n3) / det;
        let disc = p * p - 4.0 * q;
        // No real modes (or no fit: NaN).
        if disc.is_nan() || disc < 0.0 {
            return None;
        }
        let (r1, r2) = ((p + disc.sqrt()) / 2.0, (p - disc.sqrt()) / 2.0);
        let weight = two_mode_weight(det.abs() / (n1 * n1), r1, r2);
        let d = 1.0 - p + q;
        (weight > 0.0).then(|| Self {
            last: (p - q) / d,
            before: -q / d,
            weight,
        })
    }
}

/// How much the closure trusts a two-mode fit with `x = |det| / N_{M-2}^2` and ratios
/// `r1 >= r2`: 1 for two well-separated, well-conditioned modes with
/// `FAST_RATIO_FULL <= r2`, `r1 <= ORDER_RATIO_FULL`, `1 - r2 >= MODE_SEPARATION_FULL (1 - r1)`
/// and `x (1 - r1) >= CONDITIONING_FULL`; 0 past `MAX_ORDER_RATIO`, `MODE_SEPARATION` or
/// `CONDITIONING`; a product of ramps between. A switch between the two tails would let a tiny
/// change of the orders (f32 rounding, the order of a GPU's atomic adds) move a bright, thick
/// cloud's light by a few per cent (docs/illumination.md §4).
pub fn two_mode_weight(x: f64, r1: f64, r2: f64) -> f64 {
    let ramp = |v: f64, zero: f64, one: f64| ((v - zero) / (one - zero)).clamp(0.0, 1.0);
    let conditioning = x * (1.0 - r1);
    if !(r1 < 1.0 && conditioning > CONDITIONING) {
        return 0.0;
    }
    ramp(conditioning.ln(), CONDITIONING.ln(), CONDITIONING_FULL.ln())
        * ramp(
            (1.0 - r2) / (1.0 - r1),
            MODE_SEPARATION,
            MODE_SEPARATION_FULL,
        )
        * ramp(r1, MAX_ORDER_RATIO, ORDER_RATIO_FULL)
        * ramp(r2, 0.0, FAST_RATIO_FULL)
}
