//! Speed measurements of the simulation for `skillaug bench sim` (the
//! accuracy beside them is [`super::checks`]).
//!
//! The benchmark steps the rapier3d humanoid (with the ball and contacts) on
//! one thread and on every thread of the pool, for the full 53-body model
//! and for a 23-body variant without finger bodies, and reports physics
//! steps per second per core and in total, and the scaling. The worlds
//! start from a Dribble-Forward frame and follow its pose with small action
//! noise, reset every 60 policy steps (a training episode) and whenever the
//! root drops below 0.5 m (early termination), so contacts are those of
//! training rather than of a humanoid lying on the ground or standing still
//! ([`sim_rate`]).

use super::mjcf::Model;
use super::objects::ObjectSpec;
use super::vec_env::VecEnv;
use super::SimOptions;
use crate::motion::state::State;
use anyhow::Result;
use std::time::Instant;

/// The median of `v` (the upper one of an even count); `v` must not be empty.
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// Physics steps per second of `worlds` worlds of `model` stepped for
/// `policy_steps` policy steps on a pool of `threads` threads. The worlds
/// start from `start` and follow its pose (PD targets e / π) with uniform
/// action noise of ±0.1; they restart every 60 policy steps (a training
/// episode) and whenever the root drops below 0.5 m (early termination),
/// so contacts are those of training.
///
/// # Errors
/// When the pool or the worlds cannot be built.
pub fn sim_rate(
    model: &Model,
    opts: &SimOptions,
    start: &State,
    threads: usize,
    worlds: usize,
    policy_steps: usize,
) -> Result<f64> {
    use rand::{Rng, SeedableRng};
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    pool.install(|| -> Result<f64> {
        let mut env = VecEnv::new(model, &[ObjectSpec::ball()], opts, worlds)?;
        let a = env.action_dim();
        let base: Vec<f32> = start.joint_rot[..a]
            .iter()
            .map(|v| v / std::f32::consts::PI)
            .collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let t = Instant::now();
        for step in 0..policy_steps {
            if step % 60 == 0 {
                env.for_each(|_, w| w.set_state(start).expect("state fits the model"));
            }
            let actions: Vec<f32> = (0..worlds * a)
                .map(|k| base[k % a] + rng.random_range(-0.1..0.1))
                .collect();
            env.step(&actions);
            // early termination, as in training: a fallen world restarts
            env.for_each(|_, w| {
                if w.root_height() < 0.5 {
                    w.set_state(start).expect("state fits the model");
                }
            });
        }
        let steps = (worlds * policy_steps * opts.substeps) as f64;
        Ok(steps / t.elapsed().as_secs_f64())
    })
}

/// Medians over `repeat` rounds of [`sim_rate`] on one thread and on
/// `threads` threads (one of each per round), in that order.
///
/// # Errors
/// As [`sim_rate`].
pub fn sim_rates(
    model: &Model,
    opts: &SimOptions,
    start: &State,
    threads: usize,
    worlds: usize,
    policy_steps: usize,
    repeat: usize,
) -> Result<(f64, f64)> {
    let mut one = Vec::new();
    let mut all = Vec::new();
    for _ in 0..repeat {
        one.push(sim_rate(model, opts, start, 1, worlds, policy_steps)?);
        all.push(sim_rate(model, opts, start, threads, worlds, policy_steps)?);
    }
    Ok((median(one), median(all)))
}

/// The models `bench sim` times: `full` ("full (with fingers)") and
/// `full` without the bodies below the hands ("without fingers"), each
/// with the indices of its bodies in `full`.
pub fn with_and_without_fingers(full: &Model) -> Vec<(&'static str, Model, Vec<usize>)> {
    let hands = super::world::hand_bodies(full);
    let (no_fingers, kept) = full.without(|b| b.parent.is_some_and(|p| hands[p]));
    vec![
        (
            "full (with fingers)",
            full.clone(),
            (0..full.bodies.len()).collect(),
        ),
        ("without fingers", no_fingers, kept),
    ]
}

/// `s` restricted to the bodies `bodies` (indices into the full model,
/// root first) of a reduced model: their joints' rotations and velocities.
pub fn state_of_bodies(s: &State, bodies: &[usize]) -> State {
    let joints = |v: &[f32]| -> Vec<f32> {
        bodies[1..]
            .iter()
            .flat_map(|&b| v[3 * (b - 1)..3 * b].to_vec())
            .collect()
    };
    State {
        joint_rot: joints(&s.joint_rot),
        joint_vel: joints(&s.joint_vel),
        ..s.clone()
    }
}

/// The `[sim]` keys of `opts` whose values differ from the defaults, as
/// `sim.KEY=VALUE` separated by spaces ("the defaults" when none does).
///
/// # Errors
/// When the options do not serialise.
pub fn settings_changed(opts: &SimOptions) -> Result<String> {
    let now = toml::Table::try_from(opts)?;
    let default = toml::Table::try_from(SimOptions::default())?;
    let changed: Vec<String> = now
        .iter()
        .filter(|(k, v)| default.get(*k) != Some(*v))
        .map(|(k, v)| match v {
            // the options are f32: print them as such, not widened to f64
            toml::Value::Float(f) => format!("sim.{k}={}", *f as f32),
            v => format!("sim.{k}={v}"),
        })
        .collect();
    Ok(if changed.is_empty() {
        "the defaults".to_string()
    } else {
        changed.join(" ")
    })
}
