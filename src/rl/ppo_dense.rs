//! The PPO minibatch step on the CPU without autograd: the losses of
//! [`super::ppo::Agent::update_with`] differentiated by hand, the networks'
//! passes on [`crate::nn::dense::DenseMlp`], and Adam as one fused pass
//! over flat weight and moment vectors. Why: docs/training.md, "A learner
//! that keeps up". The autograd path stays for other devices, and
//! `the_update_on_flat_buffers_takes_the_autograds_step` (tests/rl_ppo.rs)
//! holds the two to the same step and the same optimiser moments.
//!
//! The derivatives (per row i of a minibatch of B rows; μ the policy
//! mean, σ its fixed standard deviation, A the advantage):
//! - surrogate `L_π = -mean_i min(r_i A_i, clip(r_i, 1-ε, 1+ε) A_i)`,
//!   `r_i = exp(log π(a_i) - log π_old(a_i))`, `log π = -½|z|² - c`,
//!   `z = (a - μ)/σ`: `∂L_π/∂μ_ij = -(A_i/B) r_i z_ij/σ` where the
//!   unclipped term is the minimum (ties included), else 0, and 0 where
//!   the log ratio is clamped at ±20;
//! - bounds loss `mean_i Σ_j max(μ_ij - s, 0)² + max(-μ_ij - s, 0)²`:
//!   `2(max(μ - s, 0) - max(-μ - s, 0))/B`;
//! - value loss `mean_i (v_i - R_i)²`: `2(v_i - R_i)/B`; clipped
//!   (`clip_value`), `mean_i max((v_i - R_i)², (v̂_i - R_i)²)` with
//!   `v̂ = v_old + clip(v - v_old, -ε, ε)`: the derivative of the larger
//!   term, the clipped one's only where `|v - v_old| < ε`, half of each
//!   where the two are equal (as candle's `maximum` splits a tie).

use super::comm::Comm;
use super::ppo::PpoConfig;
use crate::nn::dense::{parallelism, DenseMlp, LayerAt};
use anyhow::{ensure, Context, Result};
use candle_core::{Tensor, Var};

/// One minibatch step's loss values and per-row log ratios.
pub(super) struct StepOut {
    pub pl: f64,
    pub vl: f64,
    pub bl: f64,
    pub total: f64,
    pub log_ratio: Vec<f32>,
}

/// The update's working copy of the weights, Adam's moments and the
/// batch, as flat vectors (variables in the agent's name order).
pub(super) struct DenseUpdate {
    /// `(offset, length, is_policy)` of every variable.
    spans: Vec<(usize, usize, bool)>,
    params: Vec<f32>,
    m: Vec<f32>,
    v: Vec<f32>,
    grads: Vec<f32>,
    pi: DenseMlp,
    vf: DenseMlp,
    obs_dim: usize,
    act_dim: usize,
    // minibatch scratch
    x: Vec<f32>,
    g_mu: Vec<f32>,
    g_v: Vec<f32>,
}

/// The batch one update works on (normalised observations `[B, obs]`,
/// actions `[B, act]`, per-row old log-probabilities, old values,
/// advantages and return targets, the last two already normalised as
/// configured).
pub(super) struct Batch<'a> {
    pub obs: &'a [f32],
    pub act: &'a [f32],
    pub old_logp: &'a [f32],
    pub old_v: &'a [f32],
    pub adv: &'a [f32],
    pub ret: &'a [f32],
}

/// The layers of the MLP `prefix` among `vars` (`prefix.L.weight`
/// `[out, in]`, `prefix.L.bias`): their sizes and where they sit.
fn layers_of(
    vars: &[(String, Var)],
    spans: &[(usize, usize, bool)],
    prefix: &str,
) -> Result<(Vec<usize>, Vec<LayerAt>)> {
    let find = |name: &str| -> Option<(usize, &Var)> {
        vars.iter()
            .position(|(k, _)| k == name)
            .map(|i| (spans[i].0, &vars[i].1))
    };
    let mut sizes = Vec::new();
    let mut at = Vec::new();
    for l in 0.. {
        let Some((w_off, w)) = find(&format!("{prefix}.{l}.weight")) else {
            break;
        };
        let (b_off, _) = find(&format!("{prefix}.{l}.bias"))
            .with_context(|| format!("ppo: `{prefix}.{l}.bias` missing"))?;
        let &[out, inp] = w.dims() else {
            anyhow::bail!("ppo: `{prefix}.{l}.weight` is not a matrix");
        };
        if l == 0 {
            sizes.push(inp);
        }
        ensure!(
            sizes.last() == Some(&inp),
            "ppo: `{prefix}.{l}.weight` takes {inp} inputs"
        );
        sizes.push(out);
        at.push(LayerAt {
            weight: w_off,
            bias: b_off,
        });
    }
    ensure!(!at.is_empty(), "ppo: no layers named `{prefix}.*`");
    Ok((sizes, at))
}

impl DenseUpdate {
    /// Copies of the weights in `vars` and of Adam's moments `m`, `v` (one
    /// tensor per variable, in the same order).
    pub fn new(vars: &[(String, Var)], m: &[Tensor], v: &[Tensor]) -> Result<DenseUpdate> {
        let mut spans = Vec::with_capacity(vars.len());
        let (mut params, mut mm, mut vv) = (Vec::new(), Vec::new(), Vec::new());
        for (k, (name, var)) in vars.iter().enumerate() {
            let w = var.as_tensor().flatten_all()?.to_vec1::<f32>()?;
            spans.push((params.len(), w.len(), name.starts_with("pi.")));
            params.extend(w);
            mm.extend(m[k].flatten_all()?.to_vec1::<f32>()?);
            vv.extend(v[k].flatten_all()?.to_vec1::<f32>()?);
        }
        ensure!(
            mm.len() == params.len() && vv.len() == params.len(),
            "ppo: optimiser moments do not match the weights"
        );
        let (pi_sizes, pi_at) = layers_of(vars, &spans, "pi")?;
        let (vf_sizes, vf_at) = layers_of(vars, &spans, "vf")?;
        ensure!(
            vf_sizes.last() == Some(&1) && vf_sizes[0] == pi_sizes[0],
            "ppo: the value network does not map observations to one value"
        );
        Ok(DenseUpdate {
            grads: vec![0.0; params.len()],
            spans,
            params,
            m: mm,
            v: vv,
            obs_dim: pi_sizes[0],
            act_dim: *pi_sizes.last().expect("sizes"),
            pi: DenseMlp::new(&pi_sizes, &pi_at)?,
            vf: DenseMlp::new(&vf_sizes, &vf_at)?,
            x: Vec::new(),
            g_mu: Vec::new(),
            g_v: Vec::new(),
        })
    }

    /// Write the weights and moments back into `vars`, `m` and `v`.
    pub fn write_back(
        &self,
        vars: &[(String, Var)],
        m: &mut [Tensor],
        v: &mut [Tensor],
    ) -> Result<()> {
        for (k, (_, var)) in vars.iter().enumerate() {
            let (off, len, _) = self.spans[k];
            let shape = var.as_tensor().shape().clone();
            let dev = var.as_tensor().device().clone();
            var.set(&Tensor::from_slice(
                &self.params[off..off + len],
                &shape,
                &dev,
            )?)?;
            m[k] = Tensor::from_slice(&self.m[off..off + len], &shape, &dev)?;
            v[k] = Tensor::from_slice(&self.v[off..off + len], &shape, &dev)?;
        }
        Ok(())
    }

    /// One minibatch step on the rows `idx` of `batch`: losses, gradients
    /// (averaged over the ranks of `comm`) and Adam at rate `lr` with
    /// `adam_step` the step's number (1 for the first). With `critic_only`
    /// only the value network's weights move (the policy's losses are still
    /// reported).
    #[allow(clippy::too_many_arguments)]
    pub fn step(
        &mut self,
        cfg: &PpoConfig,
        std: f64,
        batch: &Batch<'_>,
        idx: &[u32],
        critic_only: bool,
        lr: f64,
        adam_step: u64,
        comm: &dyn Comm,
    ) -> Result<StepOut> {
        let (od, ad) = (self.obs_dim, self.act_dim);
        let rows = idx.len();
        ensure!(rows > 0, "ppo: empty minibatch");
        let par = parallelism();
        self.x.clear();
        for &i in idx {
            let i = i as usize;
            self.x.extend_from_slice(&batch.obs[i * od..(i + 1) * od]);
        }
        let inv_b = 1.0 / rows as f32;
        let inv_std = (1.0 / std) as f32;
        let free = &cfg.free_dims;
        let logc = super::ppo::log_normaliser(super::ppo::free_count(free, ad), std) as f32;
        let eps = cfg.clip as f32;
        let soft = cfg.bounds_soft as f32;
        let bcoef = cfg.bounds_coef as f32;
        let ccoef = cfg.critic_coef as f32;

        // the policy's losses and their gradient with respect to μ
        let mu_all = self.pi.forward(&self.params, &self.x, rows, par);
        self.g_mu.resize(rows * ad, 0.0);
        let mut log_ratio = Vec::with_capacity(rows);
        let (mut pl_sum, mut bl_sum) = (0f64, 0f64);
        for (r, &i) in idx.iter().enumerate() {
            let i = i as usize;
            let mu = &mu_all[r * ad..(r + 1) * ad];
            let a = &batch.act[i * ad..(i + 1) * ad];
            let g = &mut self.g_mu[r * ad..(r + 1) * ad];
            let mut sq = 0f32;
            for j in 0..ad {
                // a dimension that is not free is out of the likelihood
                let z = if free.is_empty() || free[j] {
                    (a[j] - mu[j]) * inv_std
                } else {
                    0.0
                };
                g[j] = z;
                sq += z * z;
            }
            let logp = -0.5 * sq - logc;
            let raw = logp - batch.old_logp[i];
            let lr_i = raw.clamp(-20.0, 20.0);
            log_ratio.push(lr_i);
            let ratio = lr_i.exp();
            let adv = batch.adv[i];
            let s1 = ratio * adv;
            let s2 = ratio.clamp(1.0 - eps, 1.0 + eps) * adv;
            pl_sum += s1.min(s2) as f64;
            let g_ratio = if s1 <= s2 { -adv * inv_b } else { 0.0 };
            let g_lr = if raw > -20.0 && raw < 20.0 {
                g_ratio * ratio
            } else {
                0.0
            };
            for j in 0..ad {
                let hi = (mu[j] - soft).max(0.0);
                let lo = (-mu[j] - soft).max(0.0);
                bl_sum += (hi * hi + lo * lo) as f64;
                g[j] = g_lr * g[j] * inv_std + bcoef * inv_b * 2.0 * (hi - lo);
            }
        }
        if !critic_only {
            self.pi
                .backward(&self.params, &self.x, &self.g_mu, &mut self.grads, par);
        }

        // the value loss and its gradient with respect to v
        let v = self.vf.forward(&self.params, &self.x, rows, par);
        self.g_v.resize(rows, 0.0);
        let mut vl_sum = 0f64;
        for (r, &i) in idx.iter().enumerate() {
            let i = i as usize;
            let (v, ret, ov) = (v[r], batch.ret[i], batch.old_v[i]);
            let e = v - ret;
            let (l, dl) = if cfg.clip_value {
                let dv = v - ov;
                let inside = dv > -eps && dv < eps;
                let ec = ov + dv.clamp(-eps, eps) - ret;
                let (l1, l2) = (e * e, ec * ec);
                let d1 = 2.0 * e;
                let d2 = if inside { 2.0 * ec } else { 0.0 };
                if l1 > l2 {
                    (l1, d1)
                } else if l2 > l1 {
                    (l2, d2)
                } else {
                    (l1, 0.5 * (d1 + d2))
                }
            } else {
                (e * e, 2.0 * e)
            };
            vl_sum += l as f64;
            self.g_v[r] = ccoef * inv_b * dl;
        }
        self.vf
            .backward(&self.params, &self.x, &self.g_v, &mut self.grads, par);

        // every rank's mean gradient, then Adam on the variables that moved
        // (a critic-only update never writes the policy's gradients, which
        // stay at the zeros `new` made: the sum carries them unchanged)
        if comm.size() > 1 {
            comm.sum_f32(&mut self.grads)?;
            let inv = 1.0 / comm.size() as f32;
            for g in &mut self.grads {
                *g *= inv;
            }
        }
        self.adam(lr, cfg.adam_eps, adam_step, critic_only);

        let b = rows as f64;
        let (pl, vl, bl) = (-pl_sum / b, vl_sum / b, bl_sum / b);
        let total = if critic_only {
            cfg.critic_coef * vl
        } else {
            pl + cfg.critic_coef * vl + cfg.bounds_coef * bl
        };
        Ok(StepOut {
            pl,
            vl,
            bl,
            total,
            log_ratio,
        })
    }

    /// Adam (β = 0.9, 0.999) in one pass per variable: the same update as
    /// `Adam::apply` in `ppo.rs`, `p -= lr/(1-β1^t) · m / (sqrt(v)/sqrt(1-β2^t) + eps)`.
    fn adam(&mut self, lr: f64, eps: f64, t: u64, critic_only: bool) {
        let (b1, b2) = super::ppo::ADAM_BETAS;
        let t = t as i32;
        let bc1 = 1.0 - b1.powi(t);
        let bc2 = 1.0 - b2.powi(t);
        let (c1, c2) = ((1.0 - b1) as f32, (1.0 - b2) as f32);
        let (b1, b2) = (b1 as f32, b2 as f32);
        let inv_sqrt_bc2 = (1.0 / bc2.sqrt()) as f32;
        let eps = eps as f32;
        let step = (lr / bc1) as f32;
        for &(off, len, is_pi) in &self.spans {
            if critic_only && is_pi {
                continue;
            }
            let r = off..off + len;
            for (((p, m), v), g) in self.params[r.clone()]
                .iter_mut()
                .zip(&mut self.m[r.clone()])
                .zip(&mut self.v[r.clone()])
                .zip(&self.grads[r])
            {
                *m = b1 * *m + c1 * g;
                *v = b2 * *v + c2 * (g * g);
                *p -= step * (*m / (v.sqrt() * inv_sqrt_bc2 + eps));
            }
        }
    }
}
