//! The clouds are composited after Bevy's sky. Under a camera that renders Bevy's `Atmosphere`
//! (`AtmosphereSettings`), `bevy_pbr` draws the sky between the opaque and the transparent
//! passes (its `render_sky`): over the background it adds the sky's light and multiplies what is
//! there by the atmosphere's transmittance. The computed draw composites its clouds between the
//! same two passes, and clouds composited first would have the sky drawn over them. Both systems
//! are ordered only against those passes, so the schedule's unspecified order decided. `render_sky`
//! is private to `bevy_pbr` (it cannot be named in `.after()`), and without Bevy's `debug` feature
//! systems have no names, so this build pass orders the composite after every system that is
//! placed only between the two passes, whoever added it, except those it must precede
//! (the transmissive pass, which samples the view with the clouds in it).

use std::any::TypeId;

use bevy::{
    core_pipeline::core_3d::{main_opaque_pass_3d, main_transparent_pass_3d},
    ecs::schedule::{
        FlattenedDependencies, NodeId, ScheduleBuildError, ScheduleBuildPass, ScheduleGraph,
        SystemKey, SystemSetKey,
        graph::{DiGraph, Direction},
    },
    platform::{collections::HashSet, hash::FixedHasher},
    prelude::*,
};
use indexmap::IndexSet;

/// Orders `last` after every other system whose only place is between `after` and `before`
/// (direct edges from `after` and to `before`), but for those already ordered after it, and
/// before those in `precedes`. Systems are told apart by their type.
#[derive(Debug, Clone)]
pub(crate) struct LastBetween {
    after: TypeId,
    before: TypeId,
    last: TypeId,
    precedes: Vec<TypeId>,
}

impl LastBetween {
    /// The cloud composite last between Bevy's opaque and transparent passes, before the
    /// transmissive pass where `bevy_pbr` is linked.
    pub(crate) fn cloud_composite() -> Self {
        Self {
            after: main_opaque_pass_3d.system_type_id(),
            before: main_transparent_pass_3d.system_type_id(),
            last: crate::render::draw::cloud_target::draw_cloud_target.system_type_id(),
            #[cfg(any(feature = "distance_fog", feature = "lit_object"))]
            precedes: vec![bevy::pbr::main_transmissive_pass_3d.system_type_id()],
            #[cfg(not(any(feature = "distance_fog", feature = "lit_object")))]
            precedes: vec![],
        }
    }

    /// Its anchors given by type (the unit tests' own systems).
    #[cfg(test)]
    fn new(after: TypeId, before: TypeId, last: TypeId, precedes: Vec<TypeId>) -> Self {
        Self {
            after,
            before,
            last,
            precedes,
        }
    }

    /// The edges to add to `dependencies`: (system, `last`) for each system it must follow,
    /// (`last`, system) for each in `precedes`. None where an anchor is not in the schedule.
    fn edges(
        &self,
        graph: &ScheduleGraph,
        dependencies: &DiGraph<SystemKey>,
    ) -> Vec<(SystemKey, SystemKey)> {
        let key = |ty: TypeId| {
            graph
                .systems
                .iter()
                .find_map(|(key, system, _)| (system.system_type() == ty).then_some(key))
        };
        let (Some(after), Some(before), Some(last)) =
            (key(self.after), key(self.before), key(self.last))
        else {
            return vec![];
        };
        let precedes: Vec<SystemKey> = self.precedes.iter().filter_map(|&ty| key(ty)).collect();
        let following = successors(dependencies, last);
        let follows = dependencies
            .neighbors_directed(after, Direction::Outgoing)
            .filter(|&x| {
                x != last
                    && dependencies.contains_edge(x, before)
                    && !precedes.contains(&x)
                    && !following.contains(&x)
            })
            .map(|x| (x, last));
        follows.chain(precedes.iter().map(|&x| (last, x))).collect()
    }
}

/// Every system ordered after `key`, directly or not.
fn successors(dependencies: &DiGraph<SystemKey>, key: SystemKey) -> HashSet<SystemKey> {
    let mut seen = HashSet::default();
    let mut stack = vec![key];
    while let Some(k) = stack.pop() {
        for next in dependencies.neighbors_directed(k, Direction::Outgoing) {
            if seen.insert(next) {
                stack.push(next);
            }
        }
    }
    seen
}

impl ScheduleBuildPass for LastBetween {
    type EdgeOptions = ();

    fn add_dependency(&mut self, _: NodeId, _: NodeId, _: Option<&Self::EdgeOptions>) {}

    fn collapse_set(
        &mut self,
        _: SystemSetKey,
        _: &IndexSet<SystemKey, FixedHasher>,
        _: &DiGraph<NodeId>,
    ) -> impl Iterator<Item = (NodeId, NodeId)> {
        std::iter::empty()
    }

    fn build(
        &mut self,
        _: &mut World,
        graph: &mut ScheduleGraph,
        mut dependencies: FlattenedDependencies<'_>,
    ) -> Result<(), ScheduleBuildError> {
        for (first, then) in self.edges(graph, dependencies.graph()) {
            dependencies.add_edge(first, then);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::ecs::schedule::{Schedule, ScheduleLabel, SingleThreadedExecutor};
    use std::sync::Mutex;

    #[derive(ScheduleLabel, Debug, Clone, PartialEq, Eq, Hash)]
    struct Passes;

    /// The order the systems ran in.
    #[derive(Resource, Default)]
    struct Ran(Mutex<Vec<&'static str>>);

    /// One system per name, each of its own type, recording that it ran.
    macro_rules! recording_systems {
        ($($name:ident),*) => {$(
            fn $name(ran: Res<Ran>) {
                ran.0.lock().unwrap().push(stringify!($name));
            }
        )*};
    }
    recording_systems!(opaque, sky, other, composite, later, glass, transparent);

    /// Runs the passes, with or without the build pass. `composite` is added after `sky`, as the
    /// plugin's systems after Bevy's (an unordered schedule then runs it first), `later` is
    /// ordered after it, and `glass` added last.
    fn run(with_pass: bool) -> Vec<&'static str> {
        let mut world = World::new();
        world.init_resource::<Ran>();
        let mut schedule = Schedule::new(Passes);
        schedule.set_executor(SingleThreadedExecutor::new());
        schedule.add_systems((opaque, transparent).chain());
        schedule.add_systems((sky, other).after(opaque).before(transparent));
        schedule.add_systems(
            (composite, later.after(composite))
                .after(opaque)
                .before(transparent),
        );
        schedule.add_systems(glass.after(opaque).before(transparent));
        if with_pass {
            schedule.add_build_pass(LastBetween::new(
                opaque.system_type_id(),
                transparent.system_type_id(),
                composite.system_type_id(),
                vec![glass.system_type_id()],
            ));
        }
        schedule.run(&mut world);
        world.resource::<Ran>().0.lock().unwrap().clone()
    }

    fn at(order: &[&str], name: &str) -> usize {
        order.iter().position(|n| *n == name).unwrap()
    }

    /// With the pass the composite follows every system placed only between the two passes, and
    /// precedes the one ordered after it and the one it is told to precede (`glass`, added
    /// last); without it nothing orders it after the sky.
    #[test]
    fn the_composite_follows_everything_between_the_passes() {
        let order = run(true);
        assert_eq!(order.len(), 7, "{order:?}");
        for before in ["opaque", "sky", "other"] {
            assert!(at(&order, before) < at(&order, "composite"), "{order:?}");
        }
        for after in ["later", "glass"] {
            assert!(at(&order, "composite") < at(&order, after), "{order:?}");
        }
        assert_eq!(order.last(), Some(&"transparent"), "{order:?}");
        let unordered = run(false);
        assert!(
            at(&unordered, "composite") < at(&unordered, "sky"),
            "the test's schedule ran the composite after the sky without the pass, so it shows \
             nothing: {unordered:?}"
        );
    }
}
