//! The per-frame re-light budget: which clouds with pending illumination work do it this frame
//! ([`CloudRelightBudget`](crate::settings::CloudRelightBudget); docs/illumination.md §8).
//! A pure function of the candidates, tested on the CPU.

use bevy::prelude::*;

/// A cloud with illumination work pending this frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RelightCandidate {
    /// Its render-world entity.
    pub entity: Entity,
    /// It has no finished illumination yet, so it cannot be drawn until it gets one: it always
    /// goes first.
    pub first: bool,
    /// Frames its work has been put off.
    pub waited: u32,
}

/// The candidates that do their work this frame: all of them when `budget` is 0, else the
/// `budget` first in order of (never illuminated, longest waited, entity), plus every cloud never
/// illuminated beyond the budget (so a new cloud is drawn on its first frame).
pub fn relit_this_frame(mut candidates: Vec<RelightCandidate>, budget: u32) -> Vec<Entity> {
    if budget == 0 {
        return candidates.iter().map(|c| c.entity).collect();
    }
    candidates.sort_by_key(|c| (!c.first, std::cmp::Reverse(c.waited), c.entity));
    let firsts = candidates.iter().filter(|c| c.first).count();
    candidates
        .iter()
        .take((budget as usize).max(firsts))
        .map(|c| c.entity)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn candidate(index: u32, first: bool, waited: u32) -> RelightCandidate {
        RelightCandidate {
            entity: Entity::from_raw_u32(index).unwrap(),
            first,
            waited,
        }
    }

    fn indices(entities: Vec<Entity>) -> Vec<u32> {
        entities.iter().map(|e| e.index_u32()).collect()
    }

    fn sorted(mut indices: Vec<u32>) -> Vec<u32> {
        indices.sort();
        indices
    }

    #[test]
    fn no_budget_relights_everything() {
        let all = vec![
            candidate(1, false, 0),
            candidate(2, true, 0),
            candidate(3, false, 5),
        ];
        assert_eq!(sorted(indices(relit_this_frame(all, 0))), [1, 2, 3]);
    }

    #[test]
    fn the_longest_waiting_go_first_and_new_clouds_always() {
        let all = vec![
            candidate(1, false, 0),
            candidate(2, false, 3),
            candidate(3, false, 1),
            candidate(4, true, 0),
        ];
        assert_eq!(indices(relit_this_frame(all.clone(), 2)), [4, 2]);
        assert_eq!(indices(relit_this_frame(all.clone(), 3)), [4, 2, 3]);
        // Three new clouds and a budget of one: all three, nothing else.
        let new = vec![
            candidate(5, true, 0),
            candidate(6, true, 0),
            candidate(1, false, 9),
            candidate(7, true, 0),
        ];
        assert_eq!(sorted(indices(relit_this_frame(new, 1))), [5, 6, 7]);
    }

    /// Under a sun that moves every frame, a budget of `b` re-lights each of `n` clouds every
    /// `ceil(n / b)` frames: nobody starves.
    #[test]
    fn round_robin_under_a_moving_sun() {
        let (n, budget) = (5u32, 2u32);
        let mut waited = vec![0u32; n as usize];
        let mut last_relit = vec![0usize; n as usize];
        for frame in 1..=20 {
            let all = (0..n)
                .map(|i| candidate(i, false, waited[i as usize]))
                .collect();
            let relit = indices(relit_this_frame(all, budget));
            assert_eq!(relit.len(), budget as usize);
            for i in 0..n as usize {
                if relit.contains(&(i as u32)) {
                    assert!(
                        frame - last_relit[i] <= n.div_ceil(budget) as usize,
                        "cloud {i} starved"
                    );
                    last_relit[i] = frame;
                    waited[i] = 0;
                } else {
                    waited[i] += 1;
                }
            }
        }
    }
}
