//! PPO with a fixed-σ Gaussian policy, a separate value network, GAE, a
//! bounds loss and running observation normalisation, following SkillMimic
//! (Ingrid789/SkillMimic-V2 `skillmimic/data/cfg/train/rlg/skillmimic.yaml`,
//! `skillmimic/learning/skillmimic_network_builder.py`, `skillmimic_agent.py`
//! and `common_agent.py`, on Denys88/rl_games 1.1.4; defaults are its values):
//!
//! * policy mean and value: separate ReLU MLPs, hidden `[1024, 512, 512]`,
//!   linear heads; hidden layers use PyTorch's default `Linear` weight
//!   distribution `U(-1/sqrt(fan_in), 1/sqrt(fan_in))`, every bias is 0
//!   (`skillmimic_network_builder.py`; rl_games
//!   `rl_games/algos_torch/network_builder.py`). The policy head is drawn from
//!   `U(-0.01, 0.01)` by default so that first actions are near 0
//!   (`policy_out_bound`; `train.ppo.policy_out_bound = 0` gives SkillMimic's
//!   plain PyTorch default head).
//! * σ fixed: log σ = −2.9, σ ≈ 0.055 **standard deviation**. The paper calls
//!   0.055 a "variance"; the released code (`sigma_init` -2.9 with
//!   `fixed_sigma` in `skillmimic.yaml`) uses it as the std, and so do we by
//!   default. `sigma_is_variance: true` reads `sigma` as a variance
//!   (σ = sqrt(sigma)) for the paper's literal wording.
//! * γ 0.99, GAE λ 0.95, clip ε 0.2, Adam lr 2e-5 (paper Table 6; ε 1e-8, no
//!   weight decay, constant schedule), 6 mini-epochs, minibatch 16 384, critic
//!   coefficient 5, plain (unclipped) squared value error, bounds loss
//!   coefficient 10 on `Σ_d max(|μ_d| − 1, 0)²`, no entropy term, no gradient
//!   clipping (the `config` block of `skillmimic.yaml`; the loss in
//!   `common_agent.py`).
//! * advantages = GAE returns − values, normalised over the **whole batch**
//!   (zero mean, unit std + 1e-8) before the mini-epochs, as rl_games does.
//! * `done` (termination: no bootstrap) and `timeout` (truncation: bootstrap
//!   from V of the episode's last observation, which the caller supplies)
//!   are separate (`common_agent.py`).
//! * observation normalisation: the running statistics are merged once per
//!   update with the whole rollout batch, before the mini-epochs, and are
//!   frozen during rollouts. rl_games merges on every minibatch forward in
//!   train mode (24 merges of the same samples per epoch); one merge per
//!   batch gives the same mean and a variance weighted per sample rather
//!   than per pass, and keeps the normaliser fixed within an update.
//! * value normalisation (`normalize_value`; off by default, on in the
//!   reference configs through rl_games's `normalize_value`): the critic predicts
//!   returns standardised by a running mean and variance; rollout and
//!   bootstrap values are de-standardised (input clamped to ±5); before each
//!   update the statistics merge the stored values, then the returns, and the
//!   value loss is computed in standardised units (rl_games 1.1.4,
//!   `rl_games/common/a2c_common.py`).
//! * adaptive learning rate (`kl_threshold`, off by default): after every
//!   mini-epoch the mean approximate KL of its minibatches sets the rate,
//!   divided by 1.5 above twice the threshold and multiplied by 1.5 below
//!   half of it, kept within [`PpoConfig::lr_min`, `PpoConfig::lr_max`]
//!   (rl_games `AdaptiveScheduler`, `rl_games/common/schedulers.py`). The
//!   current rate is saved with the agent, so a resume continues with it.
//!
//! Adam is written here with explicit first/second-moment tensors and step
//! count because candle-nn's `AdamW` keeps its moments private, so they
//! could not be checkpointed for an exact resume. Every weight is drawn from
//! a seeded `ChaCha8Rng` (candle's own initialisers are unseeded), and all
//! sampling uses the caller's generator, so a run repeats bit for bit for
//! the same seed and thread count.

use super::comm::Comm;
use super::norm::RunningNorm;
use super::ppo_dense::{Batch, DenseUpdate, StepOut};
use crate::nn::{Mlp, MlpInit, Params};
use anyhow::{bail, ensure, Context, Result};
use candle_core::{Device, Tensor, Var, D};
use candle_nn::Module;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// PPO hyper-parameters (SkillMimic defaults).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PpoConfig {
    /// Hidden layer sizes of both the policy and the value MLP.
    pub hidden: Vec<usize>,
    /// Action noise: the std (default) or, with `sigma_is_variance`, the
    /// variance of the fixed Gaussian.
    pub sigma: f64,
    /// Read `sigma` as a variance instead of a standard deviation.
    pub sigma_is_variance: bool,
    /// Discount γ.
    pub gamma: f64,
    /// GAE λ.
    pub lambda: f64,
    /// PPO ratio clip ε.
    pub clip: f64,
    /// Adam learning rate.
    pub lr: f64,
    /// Adam ε.
    pub adam_eps: f64,
    /// Mini-epochs per update.
    pub epochs: usize,
    /// Minibatch size (capped at the batch size; a smaller last minibatch
    /// is used when it does not divide the batch).
    pub minibatch: usize,
    /// Weight of the value loss.
    pub critic_coef: f64,
    /// Clip the value prediction around the rollout value by ε (off in
    /// SkillMimic: plain squared error).
    pub clip_value: bool,
    /// Weight of the bounds loss on the policy mean.
    pub bounds_coef: f64,
    /// The soft bound on |μ| beyond which the bounds loss applies.
    pub bounds_soft: f64,
    /// Normalise observations with running statistics.
    pub normalize_obs: bool,
    /// Normalise advantages over the whole batch.
    pub normalize_advantages: bool,
    /// Merge the rollout into the observation statistics *after* the
    /// mini-epochs instead of before them, so the update sees the inputs the
    /// rollout's actions and log-probabilities were computed from (ratio 1
    /// at the first minibatch). rl_games merges before (during) the update.
    /// Off: on DF (`stages/df-run.toml`, seed 0, 512 x 32 batches) it removed
    /// the first update's KL jump (approximate KL 0.35 against 64) but
    /// reached 0.134 SM per step with 48 % falls over the 160k samples
    /// before 2M, against 0.129 and 27.5 %.
    pub norm_after_update: bool,
    /// Policy head weights drawn from `U(-b, b)`; `None`: PyTorch default.
    pub policy_out_bound: Option<f64>,
    /// Standardise the value targets with running statistics (see the
    /// module doc).
    pub normalize_value: bool,
    /// Adaptive learning rate around this KL (rl_games uses 0.008); `None`:
    /// constant `lr`.
    pub kl_threshold: Option<f64>,
    /// Lower bound of the adaptive rate.
    pub lr_min: f64,
    /// Upper bound of the adaptive rate.
    pub lr_max: f64,
    /// Correlation ρ in [0, 1) of the action noise between consecutive
    /// steps of one episode: the standard-normal noise z_t of μ + σ·z_t
    /// follows z_t = ρ·z_{t−1} + sqrt(1 − ρ²)·ξ_t with ξ_t independent
    /// (a discretised Ornstein-Uhlenbeck process, the exploration noise of
    /// DDPG, Lillicrap et al. 2016, Section 7; z_0 = ξ_0 at an episode's
    /// start), so every z_t is still N(0, 1) and the log-probabilities are
    /// the Gaussian policy's; the noise keeps a direction for about
    /// 1 / (1 − ρ) steps ([`collect`](super::collect)). 0 = independent
    /// noise at every step (SkillMimic's). Not written when 0.
    #[serde(skip_serializing_if = "is_zero")]
    pub noise_correlation: f64,
    /// `[act_dim]`, or empty for every dimension: the action dimensions
    /// whose noise follows [`PpoConfig::noise_correlation`]; the others get
    /// independent noise at every step. Either way each z_t is N(0, 1), so
    /// the log-probabilities stay the Gaussian policy's. Not written when
    /// empty.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub noise_correlated_dims: Vec<bool>,
    /// `[act_dim]`, or empty for every dimension: the action dimensions the
    /// Gaussian policy explores and is scored on. A dimension that is not
    /// free is taken at the mean μ with no noise and left out of the
    /// log-probability (so the ratio, the clip and the KL of the update see
    /// only the free dimensions, and μ there gets no policy gradient, only
    /// the bounds loss's). For action values that do not move the
    /// simulation (`train.residual_scale = 0` on some joints). Not written
    /// when empty.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub free_dims: Vec<bool>,
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

/// The free dimensions of `free` ([`PpoConfig::free_dims`]; all `d` when
/// it is empty).
pub(super) fn free_count(free: &[bool], d: usize) -> usize {
    if free.is_empty() {
        d
    } else {
        free.iter().filter(|&&f| f).count()
    }
}

/// log((2π)^(d/2) σ^d): the normaliser of a d-dimensional Gaussian with
/// standard deviation σ in every dimension.
pub(super) fn log_normaliser(d: usize, std: f64) -> f64 {
    let d = d as f64;
    0.5 * d * std::f64::consts::TAU.ln() + d * std.ln()
}

impl Default for PpoConfig {
    fn default() -> Self {
        PpoConfig {
            hidden: vec![1024, 512, 512],
            sigma: 0.055,
            sigma_is_variance: false,
            gamma: 0.99,
            lambda: 0.95,
            clip: 0.2,
            lr: 2e-5,
            adam_eps: 1e-8,
            epochs: 6,
            minibatch: 16384,
            critic_coef: 5.0,
            clip_value: false,
            bounds_coef: 10.0,
            bounds_soft: 1.0,
            normalize_obs: true,
            normalize_advantages: true,
            norm_after_update: false,
            policy_out_bound: Some(0.01),
            normalize_value: false,
            kl_threshold: None,
            lr_min: 1e-6,
            lr_max: 1e-2,
            noise_correlation: 0.0,
            noise_correlated_dims: Vec::new(),
            free_dims: Vec::new(),
        }
    }
}

impl PpoConfig {
    /// The action standard deviation σ.
    pub fn std(&self) -> f64 {
        if self.sigma_is_variance {
            self.sigma.sqrt()
        } else {
            self.sigma
        }
    }

    fn validate(&self) -> Result<()> {
        ensure!(self.sigma > 0.0, "ppo: sigma must be > 0");
        ensure!(
            (0.0..1.0).contains(&self.noise_correlation),
            "ppo: noise_correlation must be in [0, 1), got {}",
            self.noise_correlation
        );
        ensure!(
            self.epochs > 0 && self.minibatch > 0,
            "ppo: epochs and minibatch must be > 0"
        );
        ensure!(self.lr > 0.0 && self.lr.is_finite(), "ppo: lr must be > 0");
        if let Some(k) = self.kl_threshold {
            ensure!(k > 0.0 && k.is_finite(), "ppo: kl_threshold must be > 0");
            ensure!(
                self.lr_min > 0.0 && self.lr_min <= self.lr_max && self.lr_max.is_finite(),
                "ppo: need 0 < lr_min <= lr_max"
            );
        }
        ensure!(
            self.hidden.iter().all(|&h| h > 0),
            "ppo: hidden sizes must be > 0"
        );
        Ok(())
    }
}

/// Adam's β1 and β2 (PyTorch's defaults), for both update paths.
pub(super) const ADAM_BETAS: (f64, f64) = (0.9, 0.999);

/// Adam (PyTorch formula, no weight decay) with its state in the open so
/// it can be checkpointed: candle-nn's `AdamW` keeps its moments private.
/// The update on flat buffers (`ppo_dense.rs`) applies the same rule.
struct Adam {
    m: Vec<Tensor>,
    v: Vec<Tensor>,
    step: u64,
}

impl Adam {
    fn new(vars: &[(String, Var)]) -> Result<Adam> {
        let zeros = |var: &Var| var.as_tensor().zeros_like();
        Ok(Adam {
            m: vars
                .iter()
                .map(|(_, v)| zeros(v))
                .collect::<candle_core::Result<_>>()?,
            v: vars
                .iter()
                .map(|(_, v)| zeros(v))
                .collect::<candle_core::Result<_>>()?,
            step: 0,
        })
    }

    fn apply(
        &mut self,
        vars: &[(String, Var)],
        grads: &[Option<Tensor>],
        lr: f64,
        eps: f64,
        skip_missing: bool,
    ) -> Result<()> {
        let (b1, b2) = ADAM_BETAS;
        self.step += 1;
        let t = self.step as i32;
        let bc1 = 1.0 - b1.powi(t);
        let bc2 = 1.0 - b2.powi(t);
        for (k, (name, var)) in vars.iter().enumerate() {
            let Some(g) = &grads[k] else {
                if skip_missing {
                    continue;
                }
                bail!("ppo: no gradient for `{name}`");
            };
            self.m[k] = (self.m[k].affine(b1, 0.0)? + g.affine(1.0 - b1, 0.0)?)?;
            self.v[k] = (self.v[k].affine(b2, 0.0)? + g.sqr()?.affine(1.0 - b2, 0.0)?)?;
            let denom = self.v[k].sqrt()?.affine(1.0 / bc2.sqrt(), eps)?;
            let upd = self.m[k].div(&denom)?.affine(lr / bc1, 0.0)?;
            var.set(&var.as_tensor().sub(&upd)?)?;
        }
        Ok(())
    }
}

/// The gradient of every variable of `vars` (`None` where the loss does not
/// depend on it), averaged over the ranks of `comm`: one all-reduce of the
/// concatenated gradients per minibatch, as MPI Adam does (see
/// [`super::comm`]). With one rank the gradients are returned untouched.
fn rank_mean_grads(
    vars: &[(String, Var)],
    grads: &candle_core::backprop::GradStore,
    comm: &dyn Comm,
) -> Result<Vec<Option<Tensor>>> {
    let mut gs: Vec<Option<Tensor>> = vars
        .iter()
        .map(|(_, v)| grads.get(v.as_tensor()).cloned())
        .collect();
    if comm.size() > 1 {
        let mut flat = Vec::new();
        for g in gs.iter().flatten() {
            flat.extend(g.flatten_all()?.to_vec1::<f32>()?);
        }
        comm.sum_f32(&mut flat)?;
        let inv = 1.0 / comm.size() as f32;
        let mut at = 0;
        for t in gs.iter_mut().flatten() {
            let n = t.elem_count();
            let v: Vec<f32> = flat[at..at + n].iter().map(|x| x * inv).collect();
            *t = Tensor::from_vec(v, t.shape(), t.device())?;
            at += n;
        }
    }
    Ok(gs)
}

/// How [`Agent::update_with`] takes its minibatch steps: on flat buffers
/// (the CPU) or on candle's autograd over the batch's tensors (normalised
/// observations, actions, old log-probabilities, old values, advantages,
/// return targets).
enum Stepper {
    Dense(Box<DenseUpdate>),
    Autograd([Tensor; 6]),
}

/// Merge the batch `data` (rows of `norm.dim()`) of every rank into `norm`,
/// in rank order, so that every rank holds the same statistics. With one
/// rank this is [`RunningNorm::update`]. The moments travel as raw `f64`
/// bytes: nothing is rounded on the way.
fn merge_ranks(norm: &mut RunningNorm, data: &[f32], comm: &dyn Comm) -> Result<()> {
    if comm.size() == 1 {
        return norm.update(data);
    }
    let d = norm.dim();
    let mut bytes = Vec::new();
    if let Some(b) = norm.batch_moments(data)? {
        for x in std::iter::once(&b.count).chain(&b.mean).chain(&b.var) {
            bytes.extend_from_slice(&x.to_le_bytes());
        }
    }
    for b in comm.all_gather(&bytes)? {
        if b.is_empty() {
            continue;
        }
        ensure!(
            b.len() == 8 * (1 + 2 * d),
            "normaliser: another rank sent {} bytes for {d} dimensions",
            b.len()
        );
        let x: Vec<f64> = b
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect();
        norm.merge(&x[1..1 + d], &x[1 + d..], x[0]);
    }
    Ok(())
}

/// What [`Agent::act`] returns for a batch of `N` observations.
#[derive(Clone, Debug, PartialEq)]
pub struct ActOut {
    /// Actions, `N * act_dim` (the mean when deterministic).
    pub actions: Vec<f32>,
    /// log π(a | s) of each action under the current policy.
    pub logp: Vec<f32>,
    /// V(s) of each observation.
    pub values: Vec<f32>,
}

/// The losses and diagnostics of one [`Agent::update`], averaged over its
/// minibatches.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct UpdateStats {
    /// Clipped surrogate loss.
    pub policy_loss: f64,
    /// Value loss (squared error, before `critic_coef`).
    pub value_loss: f64,
    /// Bounds loss (before `bounds_coef`).
    pub bounds_loss: f64,
    /// Total loss.
    pub total_loss: f64,
    /// Fraction of samples with |ratio − 1| > ε.
    pub clip_frac: f64,
    /// Approximate KL(old ‖ new), `mean(½ (log r)²)`.
    pub approx_kl: f64,
    /// Mean GAE advantage before normalisation.
    pub adv_mean: f64,
    /// Mean return target.
    pub return_mean: f64,
    /// Number of gradient steps taken.
    pub steps: usize,
    /// Learning rate after the update (the adaptive rate when on).
    pub lr: f64,
}

/// One step of `N` environments, as pushed into a [`Rollout`]. Slices are
/// per env (`N` long) or per env and dimension (`N * dim`).
pub struct Transition<'a> {
    /// Observations the actions were chosen from (raw, unnormalised).
    pub obs: &'a [f32],
    /// Actions taken.
    pub actions: &'a [f32],
    /// log π of the actions at collection time.
    pub logp: &'a [f32],
    /// V(obs) at collection time.
    pub values: &'a [f32],
    /// Rewards received.
    pub rewards: &'a [f32],
    /// Episode ended by termination (no bootstrap).
    pub terminated: &'a [bool],
    /// Episode ended by a time limit (bootstrap from `bootstrap_values`).
    pub truncated: &'a [bool],
    /// V of the true last observation of episodes that were truncated at
    /// this step; read only where `truncated` (and not `terminated`).
    pub bootstrap_values: &'a [f32],
}

/// A rollout buffer `[T steps][N envs]`, stored step-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Rollout {
    num_envs: usize,
    obs_dim: usize,
    act_dim: usize,
    obs: Vec<f32>,
    actions: Vec<f32>,
    logp: Vec<f32>,
    values: Vec<f32>,
    rewards: Vec<f32>,
    terminated: Vec<bool>,
    truncated: Vec<bool>,
    bootstrap: Vec<f32>,
    last_values: Option<Vec<f32>>,
}

impl Rollout {
    /// An empty buffer for `num_envs` environments.
    pub fn new(num_envs: usize, obs_dim: usize, act_dim: usize) -> Self {
        Rollout {
            num_envs,
            obs_dim,
            act_dim,
            obs: Vec::new(),
            actions: Vec::new(),
            logp: Vec::new(),
            values: Vec::new(),
            rewards: Vec::new(),
            terminated: Vec::new(),
            truncated: Vec::new(),
            bootstrap: Vec::new(),
            last_values: None,
        }
    }

    /// Number of steps `T` pushed.
    pub fn steps(&self) -> usize {
        self.rewards.len() / self.num_envs.max(1)
    }

    /// Number of environments `N`.
    pub fn num_envs(&self) -> usize {
        self.num_envs
    }

    /// Append one step.
    pub fn push(&mut self, t: &Transition<'_>) -> Result<()> {
        let n = self.num_envs;
        ensure!(self.last_values.is_none(), "rollout: push after finish");
        ensure!(t.obs.len() == n * self.obs_dim, "rollout: obs length");
        ensure!(
            t.actions.len() == n * self.act_dim,
            "rollout: actions length"
        );
        for (name, len) in [
            ("logp", t.logp.len()),
            ("values", t.values.len()),
            ("rewards", t.rewards.len()),
            ("terminated", t.terminated.len()),
            ("truncated", t.truncated.len()),
            ("bootstrap_values", t.bootstrap_values.len()),
        ] {
            ensure!(len == n, "rollout: {name} has {len} entries, expected {n}");
        }
        self.obs.extend_from_slice(t.obs);
        self.actions.extend_from_slice(t.actions);
        self.logp.extend_from_slice(t.logp);
        self.values.extend_from_slice(t.values);
        self.rewards.extend_from_slice(t.rewards);
        self.terminated.extend_from_slice(t.terminated);
        self.truncated.extend_from_slice(t.truncated);
        self.bootstrap.extend_from_slice(t.bootstrap_values);
        Ok(())
    }

    /// Close the buffer with V of the observations after the last step.
    pub fn finish(&mut self, last_values: &[f32]) -> Result<()> {
        ensure!(
            last_values.len() == self.num_envs,
            "rollout: last_values length"
        );
        self.last_values = Some(last_values.to_vec());
        Ok(())
    }

    /// A finished buffer of `T` steps of `N` environments as little-endian
    /// bytes, for a checkpoint: the `f32` arrays obs `[T][N][obs_dim]`,
    /// actions `[T][N][act_dim]`, logp, values, rewards and bootstrap
    /// values `[T][N]` each, last values `[N]`, then the flags terminated
    /// and truncated `[T][N]`, one byte each: `4 (T N (obs_dim + act_dim +
    /// 4) + N) + 2 T N` bytes. [`Rollout::from_le_bytes`] reads them back
    /// exactly.
    ///
    /// # Errors
    /// When the buffer is not finished.
    pub fn to_le_bytes(&self) -> Result<Vec<u8>> {
        let last = self.last_values.as_ref().context("rollout: not finished")?;
        let mut b = Vec::new();
        for a in [
            &self.obs,
            &self.actions,
            &self.logp,
            &self.values,
            &self.rewards,
            &self.bootstrap,
            last,
        ] {
            for x in a {
                b.extend_from_slice(&x.to_le_bytes());
            }
        }
        b.extend(self.terminated.iter().map(|&t| t as u8));
        b.extend(self.truncated.iter().map(|&t| t as u8));
        Ok(b)
    }

    /// Read back the bytes of [`Rollout::to_le_bytes`] of a finished buffer
    /// of `steps` steps of `num_envs` environments.
    ///
    /// # Errors
    /// Bytes of another length, or a flag byte that is neither 0 nor 1.
    pub fn from_le_bytes(
        num_envs: usize,
        obs_dim: usize,
        act_dim: usize,
        steps: usize,
        bytes: &[u8],
    ) -> Result<Rollout> {
        let tn = steps * num_envs;
        let floats = [tn * obs_dim, tn * act_dim, tn, tn, tn, tn, num_envs];
        let want = 4 * floats.iter().sum::<usize>() + 2 * tn;
        ensure!(
            bytes.len() == want,
            "rollout: {} bytes, expected {want} for {steps} steps of {num_envs} environments",
            bytes.len()
        );
        let mut at = 0;
        let mut arrays = floats.iter().map(|&len| {
            let v: Vec<f32> = bytes[at..at + 4 * len]
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            at += 4 * len;
            v
        });
        let mut next = || arrays.next().expect("seven arrays");
        let (obs, actions, logp, values, rewards, bootstrap, last) =
            (next(), next(), next(), next(), next(), next(), next());
        let flags = &bytes[bytes.len() - 2 * tn..];
        ensure!(
            flags.iter().all(|&f| f <= 1),
            "rollout: a flag byte is neither 0 nor 1"
        );
        let flag = |s: &[u8]| s.iter().map(|&f| f == 1).collect::<Vec<bool>>();
        Ok(Rollout {
            num_envs,
            obs_dim,
            act_dim,
            obs,
            actions,
            logp,
            values,
            rewards,
            terminated: flag(&flags[..tn]),
            truncated: flag(&flags[tn..]),
            bootstrap,
            last_values: Some(last),
        })
    }

    /// GAE advantages and returns (`T * N`, step-major).
    pub fn advantages(&self, gamma: f64, lambda: f64) -> Result<(Vec<f32>, Vec<f32>)> {
        let last = self
            .last_values
            .as_ref()
            .context("rollout: finish() was not called")?;
        Ok(gae(
            &GaeInput {
                rewards: &self.rewards,
                values: &self.values,
                terminated: &self.terminated,
                truncated: &self.truncated,
                bootstrap: &self.bootstrap,
                last_values: last,
                num_envs: self.num_envs,
            },
            gamma,
            lambda,
        ))
    }
}

/// Inputs of [`gae`], step-major `[T][N]` slices.
pub struct GaeInput<'a> {
    /// r_t.
    pub rewards: &'a [f32],
    /// V(s_t).
    pub values: &'a [f32],
    /// Episode terminated at t (next value 0).
    pub terminated: &'a [bool],
    /// Episode truncated at t (next value `bootstrap`).
    pub truncated: &'a [bool],
    /// V of the truncated episode's last observation.
    pub bootstrap: &'a [f32],
    /// V(s_T) after the last step, `N` long.
    pub last_values: &'a [f32],
    /// N.
    pub num_envs: usize,
}

/// Generalised advantage estimation (Ingrid789/SkillMimic-V2
/// `skillmimic/learning/common_agent.py`):
/// `next_v = 0` if terminated, the supplied bootstrap value if truncated,
/// `V(s_{t+1})` otherwise; `δ_t = r_t + γ next_v − V_t`;
/// `A_t = δ_t + γλ (1 − done_t) A_{t+1}` with `done = terminated ∨
/// truncated`; returns `A + V`. Computed in `f64`.
pub fn gae(inp: &GaeInput<'_>, gamma: f64, lambda: f64) -> (Vec<f32>, Vec<f32>) {
    let n = inp.num_envs;
    let len = inp.rewards.len();
    let t_len = len / n;
    let mut adv = vec![0f32; len];
    let mut ret = vec![0f32; len];
    for e in 0..n {
        let mut a_next = 0.0f64;
        for t in (0..t_len).rev() {
            let k = t * n + e;
            let v = inp.values[k] as f64;
            let next_v = if inp.terminated[k] {
                0.0
            } else if inp.truncated[k] {
                inp.bootstrap[k] as f64
            } else if t + 1 == t_len {
                inp.last_values[e] as f64
            } else {
                inp.values[k + n] as f64
            };
            let done = inp.terminated[k] || inp.truncated[k];
            let delta = inp.rewards[k] as f64 + gamma * next_v - v;
            let a = delta + if done { 0.0 } else { gamma * lambda * a_next };
            adv[k] = a as f32;
            ret[k] = (a + v) as f32;
            a_next = a;
        }
    }
    (adv, ret)
}

/// Scalars of a checkpoint (the JSON sidecar).
#[derive(Serialize, Deserialize)]
struct Sidecar {
    format: u32,
    obs_dim: usize,
    act_dim: usize,
    config: PpoConfig,
    adam_step: u64,
    norm_count: f64,
    /// Learning rate in use (the adaptive rate); absent in older files.
    #[serde(default)]
    lr_now: Option<f64>,
    /// Value normaliser (mean, var, count); absent without it.
    #[serde(default)]
    value_norm: Option<(f64, f64, f64)>,
}

/// The PPO learner: policy and value networks, optimiser and normaliser.
pub struct Agent {
    cfg: PpoConfig,
    obs_dim: usize,
    act_dim: usize,
    std: f64,
    pi: Mlp,
    vf: Mlp,
    /// Every weight by name (the optimiser's and the checkpoint's order).
    vars: Vec<(String, Var)>,
    adam: Adam,
    norm: RunningNorm,
    /// Running statistics of the value targets (used with `normalize_value`).
    vnorm: RunningNorm,
    /// The learning rate in use (adapted with `kl_threshold`).
    lr_now: f64,
    dev: Device,
    /// Minibatch steps on candle's autograd even on the CPU
    /// ([`Agent::use_autograd`]).
    autograd: bool,
    /// `[1, act_dim]`: 1 on a free dimension, 0 elsewhere
    /// ([`PpoConfig::free_dims`]); `None` when every one is free. Built
    /// once for the autograd step's likelihood.
    free_mask: Option<Tensor>,
}

impl Agent {
    /// A fresh agent; weights drawn from `ChaCha8Rng::seed_from_u64(seed)`
    /// (policy layers first, then value layers).
    pub fn new(
        obs_dim: usize,
        act_dim: usize,
        cfg: &PpoConfig,
        seed: u64,
        dev: &Device,
    ) -> Result<Agent> {
        cfg.validate()?;
        ensure!(
            obs_dim > 0 && act_dim > 0,
            "ppo: empty observation or action"
        );
        ensure!(
            cfg.noise_correlated_dims.is_empty() || cfg.noise_correlated_dims.len() == act_dim,
            "ppo: noise_correlated_dims has {} entries for {act_dim} action dimensions",
            cfg.noise_correlated_dims.len()
        );
        ensure!(
            cfg.free_dims.is_empty()
                || (cfg.free_dims.len() == act_dim && cfg.free_dims.iter().any(|&f| f)),
            "ppo: free_dims has {} entries ({} free) for {act_dim} action dimensions",
            cfg.free_dims.len(),
            cfg.free_dims.iter().filter(|&&f| f).count()
        );
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut sizes = vec![obs_dim];
        sizes.extend_from_slice(&cfg.hidden);
        sizes.push(act_dim);
        let mut params = Params::default();
        let init = MlpInit {
            out_bound: cfg.policy_out_bound,
            zero_bias: true,
        };
        let pi = Mlp::with_init(&mut params, "pi", &sizes, init, &mut rng, dev)?;
        *sizes.last_mut().expect("sizes") = 1;
        let init = MlpInit {
            out_bound: None,
            zero_bias: true,
        };
        let vf = Mlp::with_init(&mut params, "vf", &sizes, init, &mut rng, dev)?;
        let vars = params.named();
        let adam = Adam::new(&vars)?;
        let free_mask = if cfg.free_dims.is_empty() {
            None
        } else {
            let m: Vec<f32> = cfg.free_dims.iter().map(|&f| f as u8 as f32).collect();
            Some(Tensor::from_vec(m, (1, act_dim), dev)?)
        };
        Ok(Agent {
            std: cfg.std(),
            cfg: cfg.clone(),
            obs_dim,
            act_dim,
            pi,
            vf,
            vars,
            adam,
            norm: RunningNorm::new(obs_dim),
            vnorm: RunningNorm::new(1),
            lr_now: cfg.lr,
            dev: dev.clone(),
            autograd: false,
            free_mask,
        })
    }

    /// The learning rate the next update uses.
    pub fn learning_rate(&self) -> f64 {
        self.lr_now
    }

    /// Critic outputs to values in return units.
    fn denorm_values(&self, v: Vec<f32>) -> Vec<f32> {
        if !self.cfg.normalize_value {
            return v;
        }
        let (m, sd) = (
            self.vnorm.mean[0],
            (self.vnorm.var[0] + super::norm::NORM_EPS).sqrt(),
        );
        v.into_iter()
            .map(|x| {
                ((x as f64).clamp(-super::norm::NORM_CLIP, super::norm::NORM_CLIP) * sd + m) as f32
            })
            .collect()
    }

    /// The configuration.
    pub fn config(&self) -> &PpoConfig {
        &self.cfg
    }

    /// Observation size.
    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }

    /// Action size.
    pub fn act_dim(&self) -> usize {
        self.act_dim
    }

    /// The observation normaliser.
    pub fn normalizer(&self) -> &RunningNorm {
        &self.norm
    }

    /// Number of optimiser steps taken.
    pub fn optimizer_steps(&self) -> u64 {
        self.adam.step
    }

    /// Every weight, by name, as flat `f32` vectors (stable order).
    pub fn weights(&self) -> Result<Vec<(String, Vec<f32>)>> {
        self.vars
            .iter()
            .map(|(k, v)| Ok((k.clone(), v.as_tensor().flatten_all()?.to_vec1::<f32>()?)))
            .collect()
    }

    /// A copy of this agent that acts as it does ([`Agent::act`],
    /// [`Agent::values`] give the same outputs, bit for bit) and shares no
    /// storage with it, so it can act on another thread while this agent
    /// updates; its optimiser moments are fresh (an actor never updates).
    ///
    /// # Errors
    /// A failure to allocate or copy a weight on the agent's device.
    pub fn actor_copy(&self) -> Result<Agent> {
        let mut actor = Agent::new(self.obs_dim, self.act_dim, &self.cfg, 0, &self.dev)?;
        self.copy_into(&mut actor)?;
        Ok(actor)
    }

    /// Overwrite `actor`'s weights and normalisers with this agent's (an
    /// actor made by [`Agent::actor_copy`]), copying the values into its own
    /// storage.
    ///
    /// # Errors
    /// An `actor` of other sizes or settings, or a failed copy.
    pub fn copy_into(&self, actor: &mut Agent) -> Result<()> {
        ensure!(
            actor.cfg == self.cfg && actor.vars.len() == self.vars.len(),
            "ppo: the actor was made for other settings"
        );
        for ((k, from), (k2, to)) in self.vars.iter().zip(&actor.vars) {
            ensure!(k == k2, "ppo: the actor's weight {k2} is not {k}");
            to.set(from.as_tensor())?;
        }
        actor.std = self.std;
        actor.norm = self.norm.clone();
        actor.vnorm = self.vnorm.clone();
        actor.lr_now = self.lr_now;
        Ok(())
    }

    /// The observations `obs` (raw, rows of `obs_dim`) as the networks see
    /// them: normalised when `normalize_obs` is on.
    fn normalized_obs(&self, obs: &[f32]) -> Result<Vec<f32>> {
        ensure!(
            obs.len().is_multiple_of(self.obs_dim),
            "ppo: {} observation values are not rows of {}",
            obs.len(),
            self.obs_dim
        );
        Ok(if self.cfg.normalize_obs {
            self.norm.normalize(obs)
        } else {
            obs.to_vec()
        })
    }

    fn obs_tensor(&self, obs: &[f32]) -> Result<Tensor> {
        let x = self.normalized_obs(obs)?;
        let rows = x.len() / self.obs_dim;
        Ok(Tensor::from_vec(x, (rows, self.obs_dim), &self.dev)?)
    }

    /// V(s) for a batch of raw observations.
    pub fn values(&self, obs: &[f32]) -> Result<Vec<f32>> {
        let x = self.obs_tensor(obs)?;
        Ok(self.denorm_values(self.vf.forward(&x)?.flatten_all()?.to_vec1::<f32>()?))
    }

    /// The policy mean μ(s) for a batch of raw observations.
    pub fn mean_action(&self, obs: &[f32]) -> Result<Vec<f32>> {
        let x = self.obs_tensor(obs)?;
        Ok(self.pi.forward(&x)?.flatten_all()?.to_vec1::<f32>()?)
    }

    /// Actions for a batch of raw observations (`N * obs_dim`): μ when
    /// `deterministic`, else μ + σ·z with z drawn from `rng`; with their
    /// log-probabilities and the state values.
    pub fn act<R: Rng + ?Sized>(
        &self,
        obs: &[f32],
        deterministic: bool,
        rng: &mut R,
    ) -> Result<ActOut> {
        let mut z = vec![0f64; obs.len() / self.obs_dim.max(1) * self.act_dim];
        if !deterministic {
            crate::random::fill_normal(&mut z, rng);
        }
        self.act_with_noise(obs, &z)
    }

    /// Actions μ + σ·z for a batch of raw observations (`N * obs_dim`) with
    /// the given standard-normal noise `z` (`N * act_dim`), with their
    /// log-probabilities under the Gaussian policy and the state values.
    ///
    /// # Errors
    /// When `z` does not have one value per action, or the networks fail.
    pub fn act_with_noise(&self, obs: &[f32], z: &[f64]) -> Result<ActOut> {
        let x = self.obs_tensor(obs)?;
        let mu = self.pi.forward(&x)?.flatten_all()?.to_vec1::<f32>()?;
        ensure!(
            z.len() == mu.len(),
            "ppo: {} noise values for {} actions",
            z.len(),
            mu.len()
        );
        let values = self.denorm_values(self.vf.forward(&x)?.flatten_all()?.to_vec1::<f32>()?);
        let d = self.act_dim;
        let free = &self.cfg.free_dims;
        let is_free = |k: usize| free.is_empty() || free[k];
        let actions: Vec<f32> = mu
            .iter()
            .zip(z)
            .enumerate()
            .map(|(i, (&m, &z))| {
                if is_free(i % d) {
                    (m as f64 + self.std * z) as f32
                } else {
                    m
                }
            })
            .collect();
        let c = log_normaliser(self.free_count(), self.std);
        let logp = actions
            .chunks_exact(d)
            .zip(mu.chunks_exact(d))
            .map(|(a, m)| {
                let q: f64 = a
                    .iter()
                    .zip(m)
                    .enumerate()
                    .filter(|(k, _)| is_free(*k))
                    .map(|(_, (&a, &m))| ((a as f64 - m as f64) / self.std).powi(2))
                    .sum();
                (-0.5 * q - c) as f32
            })
            .collect();
        Ok(ActOut {
            actions,
            logp,
            values,
        })
    }

    /// How many action dimensions the Gaussian policy explores and scores
    /// ([`PpoConfig::free_dims`]; every one when it is empty).
    pub fn free_count(&self) -> usize {
        free_count(&self.cfg.free_dims, self.act_dim)
    }

    /// Correlation of the action noise between steps
    /// ([`PpoConfig::noise_correlation`]).
    pub fn noise_correlation(&self) -> f64 {
        self.cfg.noise_correlation
    }

    /// The action dimensions the correlation applies to
    /// ([`PpoConfig::noise_correlated_dims`]; empty = all).
    pub fn noise_correlated_dims(&self) -> &[bool] {
        &self.cfg.noise_correlated_dims
    }

    /// One PPO update on a finished rollout; the minibatch permutations are
    /// drawn from `rng`.
    pub fn update<R: Rng + ?Sized>(&mut self, ro: &Rollout, rng: &mut R) -> Result<UpdateStats> {
        self.update_with(ro, rng, false, &super::comm::Solo)
    }

    /// [`Agent::update`]; with `critic_only` the policy loss and the bounds
    /// loss are left out, so only the value network learns (the critic
    /// warm-up after a behaviour-cloned start). With several ranks in
    /// `comm`, `ro` is this rank's share of the batch: the advantage
    /// statistics, the normalisers, every minibatch's gradient (this rank's
    /// `minibatch / ranks` rows) and the KL of the adaptive rate are
    /// combined over the ranks, so every rank applies the same steps; the
    /// returned statistics are the ranks' means.
    ///
    /// # Errors
    /// When `ro` does not fit the agent, is empty, or a collective fails.
    pub fn update_with<R: Rng + ?Sized>(
        &mut self,
        ro: &Rollout,
        rng: &mut R,
        critic_only: bool,
        comm: &dyn Comm,
    ) -> Result<UpdateStats> {
        ensure!(
            ro.obs_dim == self.obs_dim && ro.act_dim == self.act_dim,
            "ppo: rollout sizes differ from the agent's"
        );
        let (mut adv, ret) = ro.advantages(self.cfg.gamma, self.cfg.lambda)?;
        let b = adv.len();
        ensure!(b > 0, "ppo: empty rollout");
        // sums over every rank's rows (one rank: this batch)
        let mut sums = [
            adv.iter().map(|&a| a as f64).sum::<f64>(),
            ret.iter().map(|&a| a as f64).sum::<f64>(),
            b as f64,
        ];
        comm.sum_f64(&mut sums)?;
        let b_all = sums[2];
        let mut stats = UpdateStats {
            adv_mean: sums[0] / b_all,
            return_mean: sums[1] / b_all,
            ..Default::default()
        };
        if self.cfg.normalize_advantages {
            let m = stats.adv_mean;
            let mut sq = [adv.iter().map(|&a| (a as f64 - m).powi(2)).sum::<f64>()];
            comm.sum_f64(&mut sq)?;
            let var = sq[0] / (b_all.max(2.0) - 1.0);
            let s = var.sqrt() + 1e-8;
            for a in &mut adv {
                *a = ((*a as f64 - m) / s) as f32;
            }
        }
        if self.cfg.normalize_obs && !self.cfg.norm_after_update {
            merge_ranks(&mut self.norm, &ro.obs, comm)?;
        }
        let dev = self.dev.clone();
        let (old_v, ret) = if self.cfg.normalize_value {
            merge_ranks(&mut self.vnorm, &ro.values, comm)?;
            merge_ranks(&mut self.vnorm, &ret, comm)?;
            (self.vnorm.normalize(&ro.values), self.vnorm.normalize(&ret))
        } else {
            (ro.values.clone(), ret)
        };
        ensure!(
            self.cfg.minibatch.is_multiple_of(comm.size()),
            "ppo: minibatch {} is not a multiple of the {} ranks",
            self.cfg.minibatch,
            comm.size()
        );
        let mb = (self.cfg.minibatch / comm.size()).min(b);
        let eps = self.cfg.clip;
        // On the CPU the step runs on flat buffers (`ppo_dense`), elsewhere
        // (and with `use_autograd`) on candle's autograd.
        let obs = self.normalized_obs(&ro.obs)?;
        let mut stepper = if dev.is_cpu() && !self.autograd {
            Stepper::Dense(Box::new(DenseUpdate::new(
                &self.vars,
                &self.adam.m,
                &self.adam.v,
            )?))
        } else {
            Stepper::Autograd([
                Tensor::from_slice(&obs, (b, self.obs_dim), &dev)?,
                Tensor::from_slice(&ro.actions, (b, self.act_dim), &dev)?,
                Tensor::from_slice(&ro.logp, b, &dev)?,
                Tensor::from_slice(&old_v, b, &dev)?,
                Tensor::from_slice(&adv, b, &dev)?,
                Tensor::from_slice(&ret, b, &dev)?,
            ])
        };
        let batch = Batch {
            obs: &obs,
            act: &ro.actions,
            old_logp: &ro.logp,
            old_v: &old_v,
            adv: &adv,
            ret: &ret,
        };
        let mut perm: Vec<u32> = (0..b as u32).collect();
        for _ in 0..self.cfg.epochs {
            perm.shuffle(rng);
            let (mut epoch_kl, mut epoch_n) = (0.0, 0usize);
            for chunk in perm.chunks(mb) {
                let out = match &mut stepper {
                    Stepper::Dense(d) => {
                        self.adam.step += 1;
                        d.step(
                            &self.cfg,
                            self.std,
                            &batch,
                            chunk,
                            critic_only,
                            self.lr_now,
                            self.adam.step,
                            comm,
                        )?
                    }
                    Stepper::Autograd(t) => self.step_autograd(t, chunk, critic_only, comm)?,
                };
                let lr_v = &out.log_ratio;
                let n = lr_v.len() as f64;
                stats.clip_frac += lr_v
                    .iter()
                    .filter(|&&l| ((l as f64).exp() - 1.0).abs() > eps)
                    .count() as f64
                    / n;
                let kl = lr_v.iter().map(|&l| 0.5 * (l as f64).powi(2)).sum::<f64>() / n;
                stats.approx_kl += kl;
                epoch_kl += kl;
                epoch_n += 1;
                stats.policy_loss += out.pl;
                stats.value_loss += out.vl;
                stats.bounds_loss += out.bl;
                stats.total_loss += out.total;
                stats.steps += 1;
            }
            if let (Some(k), false) = (self.cfg.kl_threshold, critic_only) {
                let mut kn = [epoch_kl, epoch_n as f64];
                comm.sum_f64(&mut kn)?;
                let kl = kn[0] / kn[1].max(1.0);
                if kl > 2.0 * k {
                    self.lr_now = (self.lr_now / 1.5).max(self.cfg.lr_min);
                } else if kl < 0.5 * k {
                    self.lr_now = (self.lr_now * 1.5).min(self.cfg.lr_max);
                }
            }
        }
        if let Stepper::Dense(d) = &stepper {
            d.write_back(&self.vars, &mut self.adam.m, &mut self.adam.v)?;
        }
        if self.cfg.normalize_obs && self.cfg.norm_after_update {
            merge_ranks(&mut self.norm, &ro.obs, comm)?;
        }
        let k = stats.steps as f64;
        stats.clip_frac /= k;
        stats.approx_kl /= k;
        stats.policy_loss /= k;
        stats.value_loss /= k;
        stats.bounds_loss /= k;
        stats.total_loss /= k;
        if comm.size() > 1 {
            let mut m = [
                stats.clip_frac,
                stats.approx_kl,
                stats.policy_loss,
                stats.value_loss,
                stats.bounds_loss,
                stats.total_loss,
            ];
            comm.sum_f64(&mut m)?;
            let r = comm.size() as f64;
            stats.clip_frac = m[0] / r;
            stats.approx_kl = m[1] / r;
            stats.policy_loss = m[2] / r;
            stats.value_loss = m[3] / r;
            stats.bounds_loss = m[4] / r;
            stats.total_loss = m[5] / r;
        }
        stats.lr = self.lr_now;
        Ok(stats)
    }

    /// One minibatch step of [`Agent::update_with`] on candle's autograd:
    /// `t` holds the batch's normalised observations, actions, old
    /// log-probabilities, old values, advantages and return targets; `chunk`
    /// the minibatch's rows.
    fn step_autograd(
        &mut self,
        t: &[Tensor; 6],
        chunk: &[u32],
        critic_only: bool,
        comm: &dyn Comm,
    ) -> Result<StepOut> {
        let [obs, act, old_logp, old_v, adv, ret] = t;
        let logc = log_normaliser(self.free_count(), self.std);
        let eps = self.cfg.clip;
        let idx = Tensor::from_slice(chunk, chunk.len(), &self.dev)?;
        let x = obs.index_select(&idx, 0)?;
        let a = act.index_select(&idx, 0)?;
        let olp = old_logp.index_select(&idx, 0)?;
        let ov = old_v.index_select(&idx, 0)?;
        let ad = adv.index_select(&idx, 0)?;
        let rt = ret.index_select(&idx, 0)?;
        let mu = self.pi.forward_const_input(&x)?;
        let mut z = (a - &mu)?.affine(1.0 / self.std, 0.0)?;
        if let Some(m) = &self.free_mask {
            z = z.broadcast_mul(m)?;
        }
        let logp = z.sqr()?.sum(D::Minus1)?.affine(-0.5, -logc)?;
        let log_ratio = (logp - &olp)?.clamp(-20f32, 20f32)?;
        let ratio = log_ratio.exp()?;
        let s1 = ratio.mul(&ad)?;
        let s2 = ratio.clamp(1.0 - eps, 1.0 + eps)?.mul(&ad)?;
        let pl = s1.minimum(&s2)?.mean_all()?.neg()?;
        let v = self.vf.forward_const_input(&x)?.squeeze(D::Minus1)?;
        let vl = if self.cfg.clip_value {
            let vc = (&ov + (&v - &ov)?.clamp(-eps, eps)?)?;
            (&v - &rt)?
                .sqr()?
                .maximum(&(vc - &rt)?.sqr()?)?
                .mean_all()?
        } else {
            (&v - &rt)?.sqr()?.mean_all()?
        };
        let soft = self.cfg.bounds_soft;
        let hi = mu.affine(1.0, -soft)?.relu()?.sqr()?;
        let lo = mu.affine(-1.0, -soft)?.relu()?.sqr()?;
        let bl = (hi + lo)?.sum(D::Minus1)?.mean_all()?;
        let total = if critic_only {
            vl.affine(self.cfg.critic_coef, 0.0)?
        } else {
            ((&pl + vl.affine(self.cfg.critic_coef, 0.0)?)?
                + bl.affine(self.cfg.bounds_coef, 0.0)?)?
        };
        let grads = rank_mean_grads(&self.vars, &total.backward()?, comm)?;
        self.adam.apply(
            &self.vars,
            &grads,
            self.lr_now,
            self.cfg.adam_eps,
            critic_only,
        )?;
        Ok(StepOut {
            pl: pl.to_scalar::<f32>()? as f64,
            vl: vl.to_scalar::<f32>()? as f64,
            bl: bl.to_scalar::<f32>()? as f64,
            total: total.to_scalar::<f32>()? as f64,
            log_ratio: log_ratio.to_vec1::<f32>()?,
        })
    }

    /// Run [`Agent::update`]'s minibatch steps on candle's autograd even on
    /// the CPU (for comparisons: `skillaug bench train`, tests); off, the
    /// CPU runs them on flat buffers (`src/rl/ppo_dense.rs`).
    pub fn use_autograd(&mut self, on: bool) {
        self.autograd = on;
    }

    /// Behaviour cloning of the policy mean: merge `obs` (raw, `N *
    /// obs_dim`) into the observation statistics, then fit μ(obs) to
    /// `targets` (`N * act_dim`) by mean squared error over `epochs` passes
    /// of shuffled minibatches with a separate Adam at rate `lr` (the PPO
    /// optimiser's moments stay untouched). Returns the mean squared error
    /// per action value before and after, on this rank's rows.
    ///
    /// With several ranks in `comm`, each rank fits its own rows (the same
    /// number on every rank): the statistics merge every rank's rows and
    /// each step averages the ranks' gradients of `minibatch` rows each.
    ///
    /// # Errors
    /// When the rows do not fit the agent, or the ranks hold different
    /// numbers of rows.
    #[allow(clippy::too_many_arguments)]
    pub fn fit_mean<R: Rng + ?Sized>(
        &mut self,
        obs: &[f32],
        targets: &[f32],
        epochs: usize,
        minibatch: usize,
        lr: f64,
        rng: &mut R,
        comm: &dyn Comm,
    ) -> Result<(f64, f64)> {
        let n = obs.len() / self.obs_dim;
        ensure!(
            n > 0 && obs.len() == n * self.obs_dim && targets.len() == n * self.act_dim,
            "fit_mean: {} observation and {} target values do not make rows",
            obs.len(),
            targets.len()
        );
        // every rank must take the same number of steps
        comm.check_identical(n as u64, "fit_mean: the numbers of rows")?;
        if self.cfg.normalize_obs {
            merge_ranks(&mut self.norm, obs, comm)?;
        }
        let dev = self.dev.clone();
        let x = self.obs_tensor(obs)?;
        let y = Tensor::from_slice(targets, (n, self.act_dim), &dev)?;
        let mse = |agent: &Agent| -> Result<f64> {
            let mu = agent.pi.forward(&x)?;
            Ok((mu - &y)?.sqr()?.mean_all()?.to_scalar::<f32>()? as f64)
        };
        let before = mse(self)?;
        let mut adam = Adam::new(&self.vars)?;
        let mut perm: Vec<u32> = (0..n as u32).collect();
        for _ in 0..epochs {
            perm.shuffle(rng);
            for chunk in perm.chunks(minibatch.max(1)) {
                let idx = Tensor::from_slice(chunk, chunk.len(), &dev)?;
                let mu = self.pi.forward_const_input(&x.index_select(&idx, 0)?)?;
                let loss = (mu - y.index_select(&idx, 0)?)?.sqr()?.mean_all()?;
                let grads = rank_mean_grads(&self.vars, &loss.backward()?, comm)?;
                adam.apply(&self.vars, &grads, lr, self.cfg.adam_eps, true)?;
            }
        }
        Ok((before, mse(self)?))
    }

    /// The JSON sidecar's path for checkpoint `path`: `path` with extension
    /// `json` (`ckpt.safetensors` → `ckpt.json`).
    pub fn sidecar_path(path: &Path) -> PathBuf {
        path.with_extension("json")
    }

    /// Save weights, Adam moments, normaliser statistics (safetensors at
    /// `path`) and scalars with the config (JSON sidecar, see
    /// [`Agent::sidecar_path`]); each file is written to a temporary name
    /// and renamed into place.
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut staged = crate::table::io::Staged::new();
        self.stage(&mut staged, path)?;
        staged.commit()
    }

    /// Stage the files of [`Agent::save`] at `path` into `staged`, to be
    /// moved into place with the other outputs staged there.
    pub fn stage(&self, staged: &mut crate::table::io::Staged, path: &Path) -> Result<()> {
        let mut map: HashMap<String, Tensor> = HashMap::new();
        for (k, (name, var)) in self.vars.iter().enumerate() {
            map.insert(name.clone(), var.as_tensor().clone());
            map.insert(format!("adam.m.{name}"), self.adam.m[k].clone());
            map.insert(format!("adam.v.{name}"), self.adam.v[k].clone());
        }
        map.insert(
            "norm.mean".into(),
            Tensor::from_slice(&self.norm.mean, self.obs_dim, &Device::Cpu)?,
        );
        map.insert(
            "norm.var".into(),
            Tensor::from_slice(&self.norm.var, self.obs_dim, &Device::Cpu)?,
        );
        let side = Sidecar {
            format: 1,
            obs_dim: self.obs_dim,
            act_dim: self.act_dim,
            config: self.cfg.clone(),
            adam_step: self.adam.step,
            norm_count: self.norm.count,
            lr_now: Some(self.lr_now),
            value_norm: self
                .cfg
                .normalize_value
                .then(|| (self.vnorm.mean[0], self.vnorm.var[0], self.vnorm.count)),
        };
        let sp = Self::sidecar_path(path);
        staged.with_path(path, |tmp| {
            candle_core::safetensors::save(&map, tmp)
                .with_context(|| format!("writing {}", path.display()))
        })?;
        staged.text(&sp, &serde_json::to_string_pretty(&side)?)
    }

    /// Load a checkpoint written by [`Agent::save`] onto `dev`.
    pub fn load(path: &Path, dev: &Device) -> Result<Agent> {
        let sp = Self::sidecar_path(path);
        let side: Sidecar = serde_json::from_slice(
            &std::fs::read(&sp).with_context(|| format!("reading {}", sp.display()))?,
        )
        .with_context(|| format!("parsing {}", sp.display()))?;
        ensure!(
            side.format == 1,
            "checkpoint format {} unknown",
            side.format
        );
        let map = candle_core::safetensors::load(path, dev)
            .with_context(|| format!("reading {}", path.display()))?;
        let mut agent = Agent::new(side.obs_dim, side.act_dim, &side.config, 0, dev)?;
        let get = |k: &str| {
            map.get(k)
                .with_context(|| format!("{}: tensor `{k}` missing", path.display()))
        };
        for (k, (name, var)) in agent.vars.iter().enumerate() {
            let w = get(name)?;
            ensure!(
                w.dims() == var.dims(),
                "{}: tensor `{name}` has shape {:?}, but {} (obs_dim {}, act_dim {}, hidden {:?}) \
                 needs {:?}",
                path.display(),
                w.dims(),
                sp.display(),
                side.obs_dim,
                side.act_dim,
                side.config.hidden,
                var.dims()
            );
            var.set(w)?;
            agent.adam.m[k] = get(&format!("adam.m.{name}"))?.clone();
            agent.adam.v[k] = get(&format!("adam.v.{name}"))?.clone();
        }
        agent.adam.step = side.adam_step;
        agent.norm = RunningNorm {
            mean: get("norm.mean")?.to_vec1::<f64>()?,
            var: get("norm.var")?.to_vec1::<f64>()?,
            count: side.norm_count,
        };
        ensure!(
            agent.norm.dim() == side.obs_dim,
            "checkpoint: normaliser size"
        );
        if let Some(lr) = side.lr_now {
            agent.lr_now = lr;
        }
        if let Some((m, v, c)) = side.value_norm {
            agent.vnorm = RunningNorm {
                mean: vec![m],
                var: vec![v],
                count: c,
            };
        }
        Ok(agent)
    }
}
