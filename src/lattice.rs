//! The lattice directions of the discrete-ordinates sweep (docs/illumination.md §4) and their
//! quadrature weights, shared by the real-time renderer and its CPU reference.
//!
//! A direction `o` is a primitive integer vector: radiance travels from voxel `v + o` to `v`
//! along a lattice line, so the sweep needs no interpolation. Each set is closed under the
//! octahedral group, so odd moments vanish, and the weights depend only on the orbit of
//! `(|o_x|, |o_y|, |o_z|)` sorted.

use std::sync::OnceLock;

use crate::settings::SweepDirections;

/// One direction of a sweep set with its two quadrature weights (each set's sum to 1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LatticeDirection {
    /// The lattice step, components in `-2..=2`.
    pub o: [i32; 3],
    /// Its weight in the order's mean and flux: `1/26` in the 26-direction set, the solid angle
    /// nearest `o` over `4π` in the 98-direction set (the sphere's Voronoi cell of `o`).
    pub mean: f64,
    /// Its weight in the order's quadrupole: a rule exact to degree 7 (the 26-point Lebedev
    /// rule; for 98 directions, the solid angles corrected to integrate degrees 4 and 6
    /// exactly). Gathering a P2 radiance's quadrupole integrates degree 4, which the mean's
    /// weights miss.
    pub quadrupole: f64,
}

/// Per orbit (sorted absolute components): the solid angle of one direction's Voronoi cell over
/// `4π` (counted on a 400,000-point Fibonacci sphere; the test recounts it), and the degree-7
/// rule's weight: the smallest relative change to those that integrates `1`, `x⁴ + y⁴ + z⁴`,
/// `x⁶ + y⁶ + z⁶` and `x²y²z²` exactly.
const ORBITS_98: [([i32; 3], f64, f64); 6] = [
    ([0, 0, 1], 0.016735, 0.021212966641714),
    ([0, 1, 1], 0.0086237, 0.008612871237129),
    ([0, 1, 2], 0.012817, 0.013747285049890),
    ([1, 1, 1], 0.0062881, 0.005399712655794),
    ([1, 1, 2], 0.010302, 0.009387400609362),
    ([1, 2, 2], 0.0079564, 0.007122399509824),
];

/// The 26-point Lebedev rule's weight by non-zero components: 1/21 along an axis, 4/105 along a
/// face diagonal, 9/280 along a body diagonal.
fn lebedev_26(o: [i32; 3]) -> f64 {
    match o.iter().filter(|&&c| c != 0).count() {
        1 => 1.0 / 21.0,
        2 => 4.0 / 105.0,
        _ => 9.0 / 280.0,
    }
}

fn orbit(o: [i32; 3]) -> [i32; 3] {
    let mut a = o.map(i32::abs);
    a.sort_unstable();
    a
}

fn gcd(a: i32, b: i32) -> i32 {
    if b == 0 { a.abs() } else { gcd(b, a % b) }
}

impl SweepDirections {
    /// The largest absolute component of the set's directions.
    pub fn reach(self) -> i32 {
        match self {
            Self::Lattice26 => 1,
            Self::Lattice98 => 2,
        }
    }

    /// Its directions, `z`, then `y`, then `x` ascending.
    pub fn directions(self) -> Vec<LatticeDirection> {
        let r = self.reach();
        let range = move || -r..=r;
        let mean_26 = 1.0 / 26.0;
        range()
            .flat_map(|z| range().flat_map(move |y| range().map(move |x| [x, y, z])))
            .filter(|o| *o != [0; 3] && gcd(gcd(o[0], o[1]), o[2]) == 1)
            .map(|o| match self {
                Self::Lattice26 => LatticeDirection {
                    o,
                    mean: mean_26,
                    quadrupole: lebedev_26(o),
                },
                Self::Lattice98 => {
                    let (_, cell, rule) = ORBITS_98
                        .into_iter()
                        .find(|(k, ..)| *k == orbit(o))
                        .expect("every primitive vector up to 2 lies in an orbit");
                    // The rounded cells sum to 1.0000088: normalised, a constant stays exact.
                    LatticeDirection {
                        o,
                        mean: cell / 1.000_008_8,
                        quadrupole: rule,
                    }
                }
            })
            .collect()
    }

    /// The set's direction pairs `(o, -o)`, each by its `o` whose first non-zero component is
    /// positive: one sweep dispatch each (13 or 49). Built once per set, since every recorded
    /// sweep dispatch asks for them.
    pub fn pairs(self) -> &'static [LatticeDirection] {
        static PAIRS_26: OnceLock<Vec<LatticeDirection>> = OnceLock::new();
        static PAIRS_98: OnceLock<Vec<LatticeDirection>> = OnceLock::new();
        let pairs = match self {
            Self::Lattice26 => &PAIRS_26,
            Self::Lattice98 => &PAIRS_98,
        };
        pairs.get_or_init(|| {
            self.directions()
                .into_iter()
                .filter(|d| d.o.into_iter().find(|&c| c != 0) > Some(0))
                .collect()
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(o: [i32; 3]) -> [f64; 3] {
        let o = o.map(f64::from);
        let len = (o[0] * o[0] + o[1] * o[1] + o[2] * o[2]).sqrt();
        o.map(|c| c / len)
    }

    /// `sum_o w_o f(o)` over a set.
    fn integral(
        set: SweepDirections,
        weight: fn(&LatticeDirection) -> f64,
        f: fn([f64; 3]) -> f64,
    ) -> f64 {
        set.directions()
            .iter()
            .map(|d| weight(d) * f(unit(d.o)))
            .sum()
    }

    #[test]
    fn the_sets_hold_26_and_98_directions_in_13_and_49_pairs() {
        assert_eq!(SweepDirections::Lattice26.directions().len(), 26);
        assert_eq!(SweepDirections::Lattice98.directions().len(), 98);
        assert_eq!(SweepDirections::Lattice26.pairs().len(), 13);
        assert_eq!(SweepDirections::Lattice98.pairs().len(), 49);
    }

    /// Both weights sum to 1; the quadrupole's integrate the even polynomials up to degree 6 over
    /// the sphere exactly (their means: x⁴ 1/5, x⁶ 1/7, x²y²z² 1/105).
    #[test]
    fn the_quadrupole_rules_are_exact_to_degree_7() {
        for set in [SweepDirections::Lattice26, SweepDirections::Lattice98] {
            assert!(
                (integral(set, |d| d.mean, |_| 1.0) - 1.0).abs() < 1e-12,
                "{set:?}"
            );
            let q = |f| integral(set, |d| d.quadrupole, f);
            assert!((q(|_| 1.0) - 1.0).abs() < 1e-12, "{set:?}");
            assert!((q(|u| u[0].powi(4)) - 0.2).abs() < 1e-12, "{set:?}");
            assert!((q(|u| u[1].powi(6)) - 1.0 / 7.0).abs() < 1e-12, "{set:?}");
            let xyz = q(|u| (u[0] * u[1] * u[2]).powi(2));
            assert!((xyz - 1.0 / 105.0).abs() < 1e-12, "{set:?}");
        }
    }

    /// The 98 mean weights are the solid angles of the directions' Voronoi cells: recounted on a
    /// 20,000-point Fibonacci sphere, each orbit's cell within 1.5 % (the count's noise is about
    /// 0.5 %).
    #[test]
    fn the_98_mean_weights_are_the_directions_solid_angles() {
        let directions = SweepDirections::Lattice98.directions();
        let units: Vec<[f64; 3]> = directions.iter().map(|d| unit(d.o)).collect();
        let points = 20_000;
        let mut counts = vec![0usize; units.len()];
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        for k in 0..points {
            let z = 1.0 - 2.0 * (k as f64 + 0.5) / points as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * k as f64;
            let p = [r * phi.cos(), r * phi.sin(), z];
            let dot = |u: &[f64; 3]| u[0] * p[0] + u[1] * p[1] + u[2] * p[2];
            let nearest = (0..units.len())
                .max_by(|&a, &b| dot(&units[a]).total_cmp(&dot(&units[b])))
                .unwrap();
            counts[nearest] += 1;
        }
        for (k, _, _) in ORBITS_98 {
            let members: Vec<usize> = (0..directions.len())
                .filter(|&i| orbit(directions[i].o) == k)
                .collect();
            let counted: usize = members.iter().map(|&i| counts[i]).sum();
            let measured = counted as f64 / points as f64 / members.len() as f64;
            let weight = directions[members[0]].mean;
            assert!(
                (measured / weight - 1.0).abs() < 0.015,
                "{k:?}: {measured} vs {weight}"
            );
        }
    }
}
