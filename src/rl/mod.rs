//! Reinforcement learning core: PPO as SkillMimic trains its skill policies
//! ([`ppo`]), running observation normalisation ([`norm`]), an
//! environment-agnostic vectorised environment interface ([`VecEnv`]) with a
//! rollout collector ([`collect`]), and a small control task to test the
//! learner on ([`pointmass`]); the trainer ([`trainer`]) and its timing
//! ([`mod@bench`]).
//!
//! Reference facts followed (SkillMimic / SkillMimic-V2 released code:
//! Ingrid789/SkillMimic-V2 `skillmimic/data/cfg/train/rlg/skillmimic.yaml` and
//! `skillmimic/learning/`, on Denys88/rl_games 1.1.4): γ 0.99, GAE λ 0.95,
//! clip 0.2, Adam lr 2e-5 (paper Table 6), fixed action std σ = e^−2.9 ≈ 0.055
//! (the paper's "variance 0.055" is the std in the code; the code is followed,
//! `sigma_is_variance` gives the paper's reading), separate `[1024, 512, 512]`
//! ReLU MLPs for policy and value, bounds loss (coefficient 10, soft bound 1),
//! critic coefficient 5, running observation normalisation clamped to ±5, and
//! timeouts bootstrapped from the value of the episode's last state while
//! terminations are not.

pub mod bench;
pub mod comm;
pub mod config;
pub mod humanoid;
pub mod norm;
pub mod pointmass;
pub mod ppo;
mod ppo_dense;
pub mod trainer;

pub use norm::RunningNorm;
pub use ppo::{gae, ActOut, Agent, GaeInput, PpoConfig, Rollout, Transition, UpdateStats};

use anyhow::{ensure, Result};
use rand_chacha::ChaCha8Rng;

/// What one step of a [`VecEnv`] reports, per environment.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StepResult {
    /// Reward of the step.
    pub rewards: Vec<f32>,
    /// The episode ended by termination (failure): no bootstrap.
    pub terminated: Vec<bool>,
    /// The episode ended by its time limit: bootstrap from `final_obs`.
    pub truncated: Vec<bool>,
    /// `N * obs_dim`: for environments whose episode ended at this step,
    /// the true last observation (before the automatic reset); rows of the
    /// other environments are not read.
    pub final_obs: Vec<f32>,
}

/// `N` environments stepped together, each reset automatically when its
/// episode ends (so [`VecEnv::observe`] after a step shows the new
/// episode's first observation for those).
pub trait VecEnv {
    /// Number of environments `N`.
    fn num_envs(&self) -> usize;
    /// Observation size.
    fn obs_dim(&self) -> usize;
    /// Action size.
    fn act_dim(&self) -> usize;
    /// The current observations, `N * obs_dim`.
    fn observe(&self) -> Vec<f32>;
    /// Apply `N * act_dim` actions; `rng` drives any randomness (resets).
    /// An error is a failure of the environment itself (a world that
    /// cannot be rebuilt), not an episode outcome.
    fn step(&mut self, actions: &[f32], rng: &mut ChaCha8Rng) -> Result<StepResult>;
}

/// Running per-environment episode returns and the returns of finished
/// episodes; with correlated action noise
/// ([`PpoConfig::noise_correlation`]) also each running episode's last
/// noise, so a rollout continues it where the last one stopped (and a
/// checkpoint keeps it).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EpisodeTracker {
    running: Vec<f64>,
    lengths: Vec<usize>,
    /// Returns of episodes finished since the last [`EpisodeTracker::take`].
    pub finished: Vec<f64>,
    /// Lengths of those episodes.
    pub finished_lengths: Vec<usize>,
    /// `[N * act_dim]`: the standard-normal action noise of each
    /// environment's last step (empty until correlated noise is used).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    noise: Vec<f64>,
    /// `[N]`: whether that noise belongs to the running episode (false at
    /// an episode's start, where the noise starts afresh).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    noise_live: Vec<bool>,
}

impl EpisodeTracker {
    /// A tracker for `n` environments.
    pub fn new(n: usize) -> Self {
        EpisodeTracker {
            running: vec![0.0; n],
            lengths: vec![0; n],
            ..Default::default()
        }
    }

    /// Record one step's rewards and episode ends.
    pub fn record(&mut self, s: &StepResult) {
        for e in 0..self.running.len() {
            self.running[e] += s.rewards[e] as f64;
            self.lengths[e] += 1;
            if s.terminated[e] || s.truncated[e] {
                self.finished.push(self.running[e]);
                self.finished_lengths.push(self.lengths[e]);
                self.running[e] = 0.0;
                self.lengths[e] = 0;
            }
        }
    }

    /// Mean return of the finished episodes (None if there are none).
    pub fn mean_return(&self) -> Option<f64> {
        (!self.finished.is_empty())
            .then(|| self.finished.iter().sum::<f64>() / self.finished.len() as f64)
    }

    /// Take and clear the finished returns.
    pub fn take(&mut self) -> Vec<f64> {
        self.finished_lengths.clear();
        std::mem::take(&mut self.finished)
    }
}

/// Run `steps` steps of `env` with stochastic actions from `agent`, and
/// return the finished [`Rollout`]. Values of truncated episodes' last
/// observations are computed for the bootstrap; `rng` drives both action
/// noise and the environment.
pub fn collect<E: VecEnv + ?Sized>(
    agent: &Agent,
    env: &mut E,
    steps: usize,
    tracker: &mut EpisodeTracker,
    rng: &mut ChaCha8Rng,
) -> Result<Rollout> {
    let (n, od, ad) = (env.num_envs(), env.obs_dim(), env.act_dim());
    ensure!(
        od == agent.obs_dim() && ad == agent.act_dim(),
        "collect: environment sizes ({od}, {ad}) differ from the agent's ({}, {})",
        agent.obs_dim(),
        agent.act_dim()
    );
    let mut ro = Rollout::new(n, od, ad);
    let mut obs = env.observe();
    let rho = agent.noise_correlation();
    if rho > 0.0 && tracker.noise.len() != n * ad {
        tracker.noise = vec![0.0; n * ad];
        tracker.noise_live = vec![false; n];
    }
    let mut xi = vec![0f64; n * ad];
    for _ in 0..steps {
        // ξ from `rng` as for independent noise; correlated noise
        // continues each running episode's last z
        crate::random::fill_normal(&mut xi, rng);
        if rho > 0.0 {
            let keep = (1.0 - rho * rho).sqrt();
            let dims = agent.noise_correlated_dims();
            for e in 0..n {
                let (z, x) = (
                    &mut tracker.noise[e * ad..(e + 1) * ad],
                    &xi[e * ad..(e + 1) * ad],
                );
                if tracker.noise_live[e] {
                    for (k, (z, x)) in z.iter_mut().zip(x).enumerate() {
                        *z = if dims.is_empty() || dims[k] {
                            rho * *z + keep * x
                        } else {
                            *x
                        };
                    }
                } else {
                    z.copy_from_slice(x);
                }
            }
        }
        let z = if rho > 0.0 { &tracker.noise } else { &xi };
        let out = agent.act_with_noise(&obs, z)?;
        let s = env.step(&out.actions, rng)?;
        if rho > 0.0 {
            for e in 0..n {
                tracker.noise_live[e] = !(s.terminated[e] || s.truncated[e]);
            }
        }
        ensure!(
            s.rewards.len() == n && s.final_obs.len() == n * od,
            "collect: environment step sizes"
        );
        let mut boot = vec![0f32; n];
        let idx: Vec<usize> = (0..n)
            .filter(|&e| s.truncated[e] && !s.terminated[e])
            .collect();
        if !idx.is_empty() {
            let rows: Vec<f32> = idx
                .iter()
                .flat_map(|&e| s.final_obs[e * od..(e + 1) * od].iter().copied())
                .collect();
            for (&e, v) in idx.iter().zip(agent.values(&rows)?) {
                boot[e] = v;
            }
        }
        ro.push(&Transition {
            obs: &obs,
            actions: &out.actions,
            logp: &out.logp,
            values: &out.values,
            rewards: &s.rewards,
            terminated: &s.terminated,
            truncated: &s.truncated,
            bootstrap_values: &boot,
        })?;
        tracker.record(&s);
        obs = env.observe();
    }
    ro.finish(&agent.values(&obs)?)?;
    Ok(ro)
}

/// Mean undiscounted return of `episodes` full episodes per environment
/// with deterministic (mean) actions; the environment is stepped until each
/// environment has finished that many episodes.
pub fn evaluate<E: VecEnv + ?Sized>(
    agent: &Agent,
    env: &mut E,
    episodes: usize,
    rng: &mut ChaCha8Rng,
) -> Result<f64> {
    let n = env.num_envs();
    let mut done = vec![0usize; n];
    let mut running = vec![0f64; n];
    let mut sum = 0.0;
    let mut count = 0usize;
    while done.iter().any(|&d| d < episodes) {
        let obs = env.observe();
        let a = agent.act(&obs, true, rng)?;
        let s = env.step(&a.actions, rng)?;
        for e in 0..n {
            running[e] += s.rewards[e] as f64;
            if s.terminated[e] || s.truncated[e] {
                if done[e] < episodes {
                    sum += running[e];
                    count += 1;
                }
                done[e] += 1;
                running[e] = 0.0;
            }
        }
    }
    Ok(sum / count as f64)
}
