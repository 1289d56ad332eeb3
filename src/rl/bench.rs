//! Speed of whole PPO iterations for `skillaug bench train`.
//!
//! The benchmark runs iterations of `skillaug train` on the Dribble-Forward
//! clips with the CPU preset (128 environments x 32 steps = 4,096 samples
//! per iteration, 256-256 networks, minibatch 2,048) and with the paper's
//! networks (1024-512-512, minibatch 16,384; 512 environments x 32 steps,
//! the paper's 2,048 being too slow to time on two cores), and reports
//! end-to-end samples per second split into simulation (physics,
//! observation, reward, resets), inference and the PPO update, beside the
//! simulation-only bound measured in the same iterations (samples per
//! second of the environments' steps alone) and the share of it reached
//! ([`time_iterations`]); each also with the next rollout collected during
//! the update ([`Timing::Overlapped`]).

use crate::rl::config::TrainConfig;
use crate::rl::trainer::{environment, gather, gather_during, update_stream, Setup};
use crate::rl::{Agent, EpisodeTracker, VecEnv as _};
use crate::sim::bench::median;
use anyhow::Result;
use rand::SeedableRng;
use std::time::Instant;

/// Medians of the timed iterations of [`time_iterations`], seconds per
/// iteration.
#[derive(Clone, Copy, Debug)]
pub struct IterationTimes {
    /// Samples per iteration (environments × steps).
    pub samples: f64,
    /// The environments' steps alone (physics, observation, reward, resets).
    pub sim: f64,
    /// The rest of the rollout (policy inference, bookkeeping).
    pub act: f64,
    /// The PPO update.
    pub update: f64,
    /// The whole iteration.
    pub total: f64,
}

impl IterationTimes {
    /// End-to-end samples per second.
    pub fn samples_per_s(&self) -> f64 {
        self.samples / self.total
    }

    /// The simulation-only bound: samples per second if the environments'
    /// steps, timed inside the same iterations, were all an iteration did.
    pub fn bound(&self) -> f64 {
        self.samples / self.sim
    }

    /// Microseconds per sample of `secs` per iteration.
    pub fn us_per_sample(&self, secs: f64) -> f64 {
        1e6 * secs / self.samples
    }
}

/// How [`time_iterations`] runs an iteration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Timing {
    /// Collect, then update; the update on flat buffers on the CPU
    /// (candle's autograd on other devices).
    Flat,
    /// Collect, then update on candle's autograd ([`Agent::use_autograd`]).
    Autograd,
    /// As [`Timing::Flat`], but the next rollout is collected on a second
    /// thread by a copy of the policy while the update runs
    /// (`train.overlap_rollout`); the update has its own generator.
    Overlapped,
}

/// Time `repeat` PPO iterations (rollout and update, seed 0) of `cfg` on
/// `s`'s clips, networks on `dev`, after one untimed iteration that warms
/// caches and the allocator. With [`Timing::Overlapped`] the simulation
/// and inference times are those of the rollout collected during the
/// timed iteration's update, and the whole iteration is the wall time of
/// both.
///
/// # Errors
/// As [`environment`], [`Agent::new`], [`crate::rl::collect`] and [`Agent::update`].
pub fn time_iterations(
    s: &Setup,
    cfg: &TrainConfig,
    repeat: usize,
    timing: Timing,
    dev: &candle_core::Device,
) -> Result<IterationTimes> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let pushes = super::trainer::feed_forward_pushes(s, cfg, 0)?;
    let mut env = environment(s, cfg, None, cfg.envs(), &pushes, &mut rng)?;
    let mut agent = Agent::new(env.obs_dim(), env.act_dim(), &cfg.ppo_config(), 0, dev)?;
    agent.use_autograd(timing == Timing::Autograd);
    let mut tracker = EpisodeTracker::new(cfg.envs());
    let (mut sim, mut act, mut upd, mut total) = (vec![], vec![], vec![], vec![]);
    let steps = cfg.steps();
    let mut urng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    urng.set_stream(update_stream(0));
    let mut actor = agent.actor_copy()?;
    let mut pending = None;
    for i in 0..=repeat.max(1) {
        let t0 = Instant::now();
        let (sim_s, c, update_s) = if timing == Timing::Overlapped {
            let ro = match pending.take() {
                Some(ro) => ro,
                None => gather(&agent, &mut env, steps, &mut tracker, &mut rng)?.0,
            };
            agent.copy_into(&mut actor)?;
            let ag = &mut agent;
            let (_, update_s, (ro, sim_s, c)) =
                gather_during(&actor, &mut env, steps, &mut tracker, &mut rng, || {
                    ag.update(&ro, &mut urng)
                })?;
            pending = Some(ro);
            (sim_s, c, update_s)
        } else {
            let (ro, sim_s, c) = gather(&agent, &mut env, steps, &mut tracker, &mut rng)?;
            let t1 = Instant::now();
            agent.update(&ro, &mut rng)?;
            (sim_s, c, t1.elapsed().as_secs_f64())
        };
        if i > 0 {
            upd.push(update_s);
            sim.push(sim_s);
            act.push(c - sim_s);
            total.push(t0.elapsed().as_secs_f64());
        }
    }
    Ok(IterationTimes {
        samples: (cfg.envs() * cfg.steps()) as f64,
        sim: median(sim),
        act: median(act),
        update: median(upd),
        total: median(total),
    })
}
