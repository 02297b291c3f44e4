//! The phase function through which the camera sees the δ-M beam's excess
//! (docs/illumination.md §5, "The beam's excess").
//!
//! An anisotropic medium's beam is attenuated by `c = 1 - albedo f` of the optical depth: the
//! fraction `f = g³` of each scattering ([`peak_fraction`]), the forward peak, is taken as not
//! scattered at all. So at optical depth `tau` the beam holds `exp(-c tau)`, of which
//! `exp(-tau)` never scattered and the *excess* `exp(-c tau) - exp(-tau)` went through `k >= 1`
//! scatterings in the peak (Poisson, mean `m = albedo f tau`). Those scatterings spread the
//! light about the beam's direction: the peak, `(p_g - (1 - f) p') / f` with `p'` the
//! remainder the sweep scatters through (its moments `1, g', chi'_2`, nothing past them), has
//! the Legendre moments `chi_l = (g^l - (1 - f) chi'_l) / f`: 1 up to `l = 3` (it keeps the
//! light, its flux and its quadrupole, as the transform assumes) and `g^(l - 3)` past them (it
//! spreads the light). After `k` of them the light's `l`-th moment is `chi_l^k`, and the camera
//! sees it through `p_g`, whose moments are `g^l`. Summed over the Poisson weights:
//!
//! `excess(mu) = exp(-tau) sum_l (2l + 1) / 4π g^l P_l(mu) (exp(m chi_l) - 1)`,
//!
//! clamped at 0 (the peak is not a positive distribution: its moments are the transform's,
//! not a phase function's). Without the spread (`chi_l = 1`) this is
//! `(exp(-c tau) - exp(-tau)) p_g(mu)`, what the beam showed before.
//!
//! [`BeamPhase`] tabulates its ratio to that, `excess / ((exp(-c tau) - exp(-tau)) p_g)`, over
//! the angle and `m`; the billboards (billboard.wgsl) and the CPU reference read it alike.

use crate::{
    math::{INV_4PI, henyey_greenstein},
    particle::{DeltaM, peak_fraction},
};

/// Samples of the table along the angle: `x = sqrt((1 - mu) / 2)`, `sin(θ/2)`, uniform in
/// `[0, 1]` (dense where the forward peak is narrow).
pub const BEAM_PHASE_ANGLES: u32 = 128;
/// Samples along the mean number of peak scatterings: `y = m / (m + 1)`, uniform in `[0, 1]`
/// (`y = 1`: `m` without bound).
pub const BEAM_PHASE_DEPTHS: u32 = 32;

/// The excess's phase function relative to `p_g`, tabulated for one anisotropy `g > 0`.
#[derive(Clone, Debug, PartialEq)]
pub struct BeamPhase {
    /// `BEAM_PHASE_ANGLES x BEAM_PHASE_DEPTHS` ratios, angle-major, each `>= 0`.
    pub ratios: Vec<f32>,
}

impl BeamPhase {
    /// The table of a medium of anisotropy `g`; `None` where the transform truncates nothing
    /// (`g <= 0`: the beam has no excess).
    pub fn new(g: f64) -> Option<Self> {
        if g <= 0.0 {
            return None;
        }
        let (na, nd) = (BEAM_PHASE_ANGLES, BEAM_PHASE_DEPTHS);
        let ratios = (0..na)
            .flat_map(|i| {
                let x = i as f64 / (na - 1) as f64;
                let cos = 1.0 - 2.0 * x * x;
                (0..nd).map(move |j| {
                    let y = j as f64 / (nd - 1) as f64;
                    let m = if j == nd - 1 {
                        f64::INFINITY
                    } else {
                        y / (1.0 - y)
                    };
                    (spread_excess(g, m, cos) / henyey_greenstein(g, cos)) as f32
                })
            })
            .collect();
        Some(Self { ratios })
    }

    /// The ratio at the cosine `cos` between the light's travel direction and the direction
    /// towards the camera, `m = albedo f tau` peak scatterings on average: bilinear in the
    /// table, as the billboards read it.
    pub fn ratio(&self, cos: f64, m: f64) -> f64 {
        let (na, nd) = (BEAM_PHASE_ANGLES as usize, BEAM_PHASE_DEPTHS as usize);
        let x = (0.5 - 0.5 * cos).max(0.0).sqrt().min(1.0) * (na - 1) as f64;
        let m = m.clamp(0.0, 1e20);
        let y = m / (m + 1.0) * (nd - 1) as f64;
        let (i, j) = ((x as usize).min(na - 2), (y as usize).min(nd - 2));
        let (fx, fy) = (x - i as f64, y - j as f64);
        let at = |a: usize, d: usize| self.ratios[a * nd + d] as f64;
        (at(i, j) * (1.0 - fy) + at(i, j + 1) * fy) * (1.0 - fx)
            + (at(i + 1, j) * (1.0 - fy) + at(i + 1, j + 1) * fy) * fx
    }
}

/// The excess's phase function (per steradian, integrating to 1 where not clamped) at the cosine
/// `cos`, `m` peak scatterings on average (given at least one):
/// `sum_l (2l + 1) / 4π g^l P_l(cos) (exp(m chi_l) - 1) / (exp(m) - 1)`, clamped at 0.
pub fn spread_excess(g: f64, m: f64, cos: f64) -> f64 {
    let f = peak_fraction(g);
    let delta = DeltaM::new(1.0, g);
    // The remainder's moments: what the sweep's P2 source holds, nothing past it.
    let remainder = [1.0, delta.anisotropy, delta.second_moment];
    // (exp(m chi) - 1) / (exp(m) - 1) without overflow; chi itself for m -> 0; [chi = 1] for m
    // without bound.
    let weight = |chi: f64| {
        if m < 1e-9 {
            chi
        } else if m.is_infinite() {
            if chi >= 1.0 - 1e-12 { 1.0 } else { 0.0 }
        } else {
            ((m * (chi - 1.0)).exp() - (-m).exp()) / -(-m).exp_m1()
        }
    };
    let (mut before, mut legendre) = (0.0, 1.0);
    let mut g_l = 1.0;
    let mut sum = 0.0;
    for l in 0..10_000u32 {
        if l > 0 {
            // Bonnet's recursion: P_l from P_{l-1} (legendre) and P_{l-2} (before).
            let next = if l == 1 {
                cos
            } else {
                ((2 * l - 1) as f64 * cos * legendre - (l - 1) as f64 * before) / l as f64
            };
            before = legendre;
            legendre = next;
            g_l *= g;
        }
        let rest_l = remainder.get(l as usize).copied().unwrap_or(0.0);
        let chi = ((g_l - (1.0 - f) * rest_l) / f).min(1.0);
        sum += (2 * l + 1) as f64 * INV_4PI * g_l * legendre * weight(chi);
        // The terms fall as g^(2l).
        if l > 2 && (2 * l + 1) as f64 * g_l * g_l < 1e-12 * g * g {
            break;
        }
    }
    sum.max(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `2π ∫ f(cos) d cos` by the midpoint rule.
    fn over_sphere(f: impl Fn(f64) -> f64) -> f64 {
        let n = 20_000;
        (0..n)
            .map(|i| {
                let cos = -1.0 + (i as f64 + 0.5) * 2.0 / n as f64;
                f(cos) * 2.0 / n as f64
            })
            .sum::<f64>()
            * std::f64::consts::TAU
    }

    #[test]
    fn a_single_peak_scattering_conserves_the_light_and_its_flux() {
        // For few peak scatterings the sum integrates to 1, and its mean cosine is g (the
        // peak's first moment is 1). Up to g = 1/2 it is positive everywhere, so unclamped;
        // past that the clamp at 0 adds a little (0.6 % at g = 0.85).
        for (g, within) in [(0.3, 1e-3), (0.5, 1e-3), (0.7, 5e-3), (0.85, 1e-2)] {
            let m = 0.05;
            let energy = over_sphere(|c| spread_excess(g, m, c));
            let flux = over_sphere(|c| c * spread_excess(g, m, c));
            assert!((energy - 1.0).abs() < within, "g {g}: energy {energy}");
            assert!((flux - g).abs() < within, "g {g}: mean cosine {flux}");
        }
    }

    #[test]
    fn the_spread_moves_light_from_the_peak_to_the_angles_beside_it() {
        // Seen straight along the beam the excess is dimmer than p_g, at 45° brighter.
        for g in [0.5, 0.7, 0.85] {
            let table = BeamPhase::new(g).unwrap();
            let along = table.ratio(1.0, 0.5);
            let beside = table.ratio(45f64.to_radians().cos(), 0.5);
            assert!(along < 0.9, "g {g}: along {along}");
            assert!(beside > 1.04, "g {g}: at 45° {beside}");
        }
    }

    #[test]
    fn the_table_reads_the_sum_at_its_nodes_and_between_them() {
        let g = 0.7;
        let table = BeamPhase::new(g).unwrap();
        for (cos, m) in [(1.0, 0.0), (0.5, 1.0), (-1.0, 3.0), (0.9, 0.2), (0.0, 0.7)] {
            let exact = spread_excess(g, m, cos) / henyey_greenstein(g, cos);
            let read = table.ratio(cos, m);
            assert!(
                (read - exact).abs() < 0.02 * exact.max(0.1),
                "cos {cos}, m {m}: table {read}, sum {exact}"
            );
        }
        // Past the last sample of m: the limit, finite.
        assert!(table.ratio(0.3, f64::INFINITY).is_finite());
        assert!(table.ratios.iter().all(|r| r.is_finite() && *r >= 0.0));
    }

    #[test]
    fn an_untruncated_medium_has_no_table() {
        assert!(BeamPhase::new(0.0).is_none());
        assert!(BeamPhase::new(-0.4).is_none());
    }
}
