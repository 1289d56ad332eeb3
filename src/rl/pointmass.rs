//! A vectorised 2-D point mass reaching a random target: a small control
//! task to test the PPO core on.
//!
//! State: position `p` and velocity `v` in the plane, target `g`. An action
//! `a ∈ R²` (clipped to `[-1, 1]²`) drives the velocity: `v ← 0.8 v + 0.2 a`,
//! then `p ← p + 0.5 v`. Reward `exp(-2 |g − p|)` per
//! step (in `(0, 1]`). The episode is *terminated* (failure, no bootstrap)
//! when the mass leaves the box `|p|_∞ > 2`, and *truncated* after
//! `episode_len` steps. Observation: `(g − p, v, p)` (6 numbers). Starts and
//! targets are uniform in `[-1, 1]²`.

use super::{StepResult, VecEnv};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Observation size.
pub const OBS_DIM: usize = 6;
/// Action size.
pub const ACT_DIM: usize = 2;
/// Half-width of the box whose exit terminates an episode.
pub const BOX: f32 = 2.0;

/// `N` point-mass environments.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PointMass {
    pos: Vec<[f32; 2]>,
    vel: Vec<[f32; 2]>,
    goal: Vec<[f32; 2]>,
    t: Vec<usize>,
    episode_len: usize,
}

impl PointMass {
    /// `n` environments with episodes of `episode_len` steps, reset from
    /// `rng`. With `stagger` the episode clocks start at random steps so
    /// that episodes do not all end together (for training; the first
    /// episodes are then shorter); without, all start at step 0 (for
    /// evaluation).
    pub fn new(n: usize, episode_len: usize, stagger: bool, rng: &mut ChaCha8Rng) -> Self {
        let mut env = PointMass {
            pos: vec![[0.0; 2]; n],
            vel: vec![[0.0; 2]; n],
            goal: vec![[0.0; 2]; n],
            t: vec![0; n],
            episode_len: episode_len.max(1),
        };
        for e in 0..n {
            env.reset(e, rng);
            if stagger {
                env.t[e] = rng.random_range(0..env.episode_len);
            }
        }
        env
    }

    fn reset(&mut self, e: usize, rng: &mut ChaCha8Rng) {
        self.pos[e] = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
        self.goal[e] = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
        self.vel[e] = [0.0; 2];
        self.t[e] = 0;
    }

    fn obs_row(&self, e: usize, out: &mut Vec<f32>) {
        let (p, v, g) = (self.pos[e], self.vel[e], self.goal[e]);
        out.extend_from_slice(&[g[0] - p[0], g[1] - p[1], v[0], v[1], p[0], p[1]]);
    }
}

impl VecEnv for PointMass {
    fn num_envs(&self) -> usize {
        self.pos.len()
    }

    fn obs_dim(&self) -> usize {
        OBS_DIM
    }

    fn act_dim(&self) -> usize {
        ACT_DIM
    }

    fn observe(&self) -> Vec<f32> {
        let mut o = Vec::with_capacity(self.num_envs() * OBS_DIM);
        for e in 0..self.num_envs() {
            self.obs_row(e, &mut o);
        }
        o
    }

    fn step(&mut self, actions: &[f32], rng: &mut ChaCha8Rng) -> anyhow::Result<StepResult> {
        let n = self.num_envs();
        let mut s = StepResult {
            rewards: vec![0.0; n],
            terminated: vec![false; n],
            truncated: vec![false; n],
            final_obs: Vec::with_capacity(n * OBS_DIM),
        };
        for e in 0..n {
            for k in 0..2 {
                let a = actions[e * ACT_DIM + k].clamp(-1.0, 1.0);
                self.vel[e][k] = 0.8 * self.vel[e][k] + 0.2 * a;
                self.pos[e][k] += 0.5 * self.vel[e][k];
            }
            let d = ((self.goal[e][0] - self.pos[e][0]).powi(2)
                + (self.goal[e][1] - self.pos[e][1]).powi(2))
            .sqrt();
            s.rewards[e] = (-2.0 * d).exp();
            self.t[e] += 1;
            s.terminated[e] = self.pos[e].iter().any(|p| p.abs() > BOX);
            s.truncated[e] = !s.terminated[e] && self.t[e] >= self.episode_len;
            self.obs_row(e, &mut s.final_obs);
            if s.terminated[e] || s.truncated[e] {
                self.reset(e, rng);
            }
        }
        Ok(s)
    }
}
