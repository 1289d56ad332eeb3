//! A vectorised environment: N independent worlds stepped in parallel with
//! rayon (measured 1.96x on two threads with this humanoid,
//! docs/simulation.md). Each world is deterministic on its own, so the
//! results do not depend on the thread count.

use super::mjcf::Model;
use super::objects::ObjectSpec;
use super::world::{SimOptions, World};
use crate::motion::state::State;
use anyhow::Result;
use rayon::prelude::*;

/// N worlds built from one model.
pub struct VecEnv {
    /// The worlds, in environment order.
    pub worlds: Vec<World>,
}

impl VecEnv {
    /// Build `n` identical worlds.
    pub fn new(
        model: &Model,
        objects: &[ObjectSpec],
        opts: &SimOptions,
        n: usize,
    ) -> Result<VecEnv> {
        let worlds = (0..n)
            .into_par_iter()
            .map(|_| World::new(model, objects, opts))
            .collect::<Result<Vec<_>>>()?;
        Ok(VecEnv { worlds })
    }

    /// Number of worlds.
    pub fn len(&self) -> usize {
        self.worlds.len()
    }

    /// True when there are no worlds.
    pub fn is_empty(&self) -> bool {
        self.worlds.is_empty()
    }

    /// Action width (3 per joint).
    pub fn action_dim(&self) -> usize {
        self.worlds.first().map_or(0, |w| 3 * w.n_joints())
    }

    /// Apply one action per world (`actions` is `[N * action_dim]`) and
    /// advance every world one policy step, in parallel.
    pub fn step(&mut self, actions: &[f32]) {
        let a = self.action_dim();
        assert_eq!(actions.len(), a * self.len(), "one action per world");
        self.worlds
            .par_iter_mut()
            .zip(actions.par_chunks_exact(a))
            .for_each(|(w, act)| {
                w.apply_action(act);
                w.step();
            });
    }

    /// Run `f` on every world in parallel.
    pub fn for_each(&mut self, f: impl Fn(usize, &mut World) + Sync) {
        self.worlds
            .par_iter_mut()
            .enumerate()
            .for_each(|(i, w)| f(i, w));
    }

    /// The state of every world.
    pub fn states(&self) -> Vec<State> {
        self.worlds.par_iter().map(World::get_state).collect()
    }
}
