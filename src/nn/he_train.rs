//! Pre-training of the history encoder by behaviour cloning on the reference
//! clips (paper Appendix B.5, Eq. 23; reference code: Ingrid789/SkillMimic-V2
//! `skillmimic/utils/state_prediction_ballplay.py`; networks in [`super::he`]):
//! the `[pretrain-he]` settings, the minibatches of history windows, the
//! training loop and the skill-separation diagnostic.

use super::he::{self, HeConfig, HistoryEncoder, Predictor};
use super::Params;
use crate::motion::MotionLib;
use crate::table::he::LossRow;
use anyhow::{bail, Result};
use candle_core::{Device, Tensor};
use candle_nn::{AdamW, Optimizer, ParamsAdamW};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Settings of the `[pretrain-he]` recipe table.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HeSettings {
    /// Optimiser steps.
    pub steps: usize,
    /// Windows per minibatch.
    pub batch_size: usize,
    /// Adam learning rate (no weight decay).
    pub lr: f64,
    /// Weight of the prediction term (Eq. 23).
    pub lambda_a: f64,
    /// Weight of the embedding regulariser (Eq. 23).
    pub lambda_b: f64,
    /// History length k, frames.
    pub history: usize,
    /// Embedding size mu.
    pub embedding: usize,
    /// Convolution channels.
    pub conv: Vec<usize>,
    /// Convolution kernel.
    pub kernel: usize,
    /// Predictor hidden sizes.
    pub predictor_hidden: Vec<usize>,
    /// `cpu`, or `cuda` / `cuda:N` (cargo feature `cuda`).
    pub device: super::DeviceName,
    /// Print a plain progress line every this many steps when stderr is not a terminal.
    pub log_every: usize,
}

impl crate::config::Validate for HeSettings {
    fn validate(&self, stage: &str) -> Result<()> {
        let c = crate::config::Check::new(stage);
        c.count("steps", self.steps as u64, 1, u32::MAX as u64)?;
        c.count("batch_size", self.batch_size as u64, 1, 1 << 20)?;
        c.positive("lr", self.lr)?;
        c.non_negative("lambda_a", self.lambda_a)?;
        c.non_negative("lambda_b", self.lambda_b)?;
        c.count("history", self.history as u64, 1, 10_000)?;
        c.holds(self.embedding == 3, || {
            format!(
                "embedding = {}: only mu = 3 is supported (Table 6)",
                self.embedding
            )
        })?;
        c.count("kernel", self.kernel as u64, 1, self.history as u64)?;
        c.holds(
            !self.conv.is_empty() && self.conv.iter().all(|&n| n > 0),
            || {
                format!(
                    "conv = {:?}: needs at least one layer, every size > 0",
                    self.conv
                )
            },
        )?;
        c.holds(self.predictor_hidden.iter().all(|&n| n > 0), || {
            format!(
                "predictor_hidden = {:?}: every size must be > 0",
                self.predictor_hidden
            )
        })?;
        c.count("log_every", self.log_every as u64, 1, u64::MAX)
    }
}

impl Default for HeSettings {
    fn default() -> Self {
        HeSettings {
            steps: 600,
            batch_size: 128,
            lr: 1e-3,
            lambda_a: 1.0,
            lambda_b: 1e-5,
            history: 60,
            embedding: 3,
            conv: vec![128, 64, 32],
            kernel: 3,
            predictor_hidden: vec![1024, 512, 512],
            device: super::DeviceName::Cpu,
            log_every: 100,
        }
    }
}

/// Training windows: (clip, frame t) with frames t and t+1 present.
fn samples(feats: &[Vec<Option<Vec<f32>>>]) -> Vec<(usize, usize)> {
    let mut v = Vec::new();
    for (c, f) in feats.iter().enumerate() {
        for t in 0..f.len().saturating_sub(1) {
            if f[t].is_some() && f[t + 1].is_some() {
                v.push((c, t));
            }
        }
    }
    v
}

struct Batch {
    windows: Tensor,
    current: Tensor,
    target: Tensor,
    cond: Tensor,
}

fn batch(
    idx: &[(usize, usize)],
    feats: &[Vec<Option<Vec<f32>>>],
    lib: &MotionLib,
    cfg: &HeConfig,
    dev: &Device,
) -> Result<Batch> {
    let (k, c, n) = (cfg.history, cfg.channels, idx.len());
    let mut w = Vec::with_capacity(n * k * c);
    let mut cur = Vec::with_capacity(n * c);
    let mut tgt = Vec::with_capacity(n * c);
    let mut classes = Vec::with_capacity(n);
    for &(clip, t) in idx {
        w.extend(he::window(&feats[clip], t, k, c));
        // `samples` only lists t where frames t and t + 1 are both present.
        cur.extend_from_slice(feats[clip][t].as_ref().expect("sample frame present"));
        tgt.extend_from_slice(feats[clip][t + 1].as_ref().expect("next frame present"));
        classes.push(lib.clips[clip].class as u32);
    }
    Ok(Batch {
        windows: Tensor::from_vec(w, (n, k, c), dev)?,
        current: Tensor::from_vec(cur, (n, c), dev)?,
        target: Tensor::from_vec(tgt, (n, c), dev)?,
        cond: he::one_hot(&classes, cfg.condition_slots, dev)?,
    })
}

/// The embedding h_t of one reference frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameEmbedding {
    /// Clip of the motion library.
    pub clip: usize,
    /// Frame t (h is computed from the frames before it).
    pub frame: usize,
    /// h_t.
    pub h: [f32; 3],
}

/// Embeddings of every present frame.
fn embed_all(
    enc: &HistoryEncoder,
    feats: &[Vec<Option<Vec<f32>>>],
    dev: &Device,
) -> Result<Vec<FrameEmbedding>> {
    let frames: Vec<(usize, usize)> = feats
        .iter()
        .enumerate()
        .flat_map(|(c, f)| {
            (0..f.len())
                .filter(move |t| f[*t].is_some())
                .map(move |t| (c, t))
        })
        .collect();
    let (k, ch) = (enc.cfg.history, enc.cfg.channels);
    let mut out = Vec::with_capacity(frames.len());
    for chunk in frames.chunks(256) {
        let mut w = Vec::with_capacity(chunk.len() * k * ch);
        for &(c, t) in chunk {
            w.extend(he::window(&feats[c], t, k, ch));
        }
        let h = enc
            .encode(&Tensor::from_vec(w, (chunk.len(), k, ch), dev)?)?
            .to_vec2::<f32>()?;
        for (&(c, t), row) in chunk.iter().zip(h) {
            let mut a = [0f32; 3];
            for (d, x) in a.iter_mut().zip(row.iter()) {
                *d = *x;
            }
            out.push(FrameEmbedding {
                clip: c,
                frame: t,
                h: a,
            });
        }
    }
    Ok(out)
}

/// Between-skill over within-skill variance of embeddings (larger = the
/// skills are better separated).
pub fn separation(emb: &[FrameEmbedding], lib: &MotionLib) -> f64 {
    let skills = lib.skills();
    let mut sums = vec![([0f64; 3], 0f64); skills.len()];
    let mut all = [0f64; 3];
    let skill_of = |c: usize| {
        skills
            .iter()
            .position(|s| *s == lib.clips[c].skill)
            .unwrap_or(0)
    };
    for FrameEmbedding { clip, h, .. } in emb {
        let s = &mut sums[skill_of(*clip)];
        for d in 0..3 {
            s.0[d] += h[d] as f64;
            all[d] += h[d] as f64;
        }
        s.1 += 1.0;
    }
    let n = emb.len().max(1) as f64;
    let mean = all.map(|x| x / n);
    let means: Vec<[f64; 3]> = sums
        .iter()
        .map(|(s, m)| s.map(|x| x / m.max(1.0)))
        .collect();
    let between: f64 = sums
        .iter()
        .zip(&means)
        .map(|((_, m), mu)| m * (0..3).map(|d| (mu[d] - mean[d]).powi(2)).sum::<f64>())
        .sum::<f64>()
        / n;
    let within: f64 = emb
        .iter()
        .map(|FrameEmbedding { clip, h, .. }| {
            let mu = means[skill_of(*clip)];
            (0..3).map(|d| (h[d] as f64 - mu[d]).powi(2)).sum::<f64>()
        })
        .sum::<f64>()
        / n;
    between / within.max(1e-30)
}

/// What [`pretrain`] made: the encoder's description, the named weights of
/// the encoder and the predictor, the loss per step, the embedding of every
/// frame after training and the skill separation before and after.
pub struct Pretrained {
    /// `he.config.json`.
    pub cfg: HeConfig,
    /// `encoder.*` and `predictor.*` tensors (`he.safetensors`).
    pub named: std::collections::HashMap<String, Tensor>,
    /// One row per optimiser step.
    pub curve: Vec<LossRow>,
    /// The embedding of every frame with a history, after training.
    pub trained: Vec<FrameEmbedding>,
    /// Between- over within-skill variance of h before training.
    pub separation_untrained: f64,
    /// The same after training.
    pub separation_trained: f64,
}

/// Pre-train the history encoder on `lib` with `set` by behaviour cloning
/// of the next state (Eq. 23): minibatches of `set.batch_size` windows drawn
/// with `seed`, Adam without weight decay on `dev`. `ingest_id` is recorded
/// in the description; `step` is called after every step with its losses.
///
/// # Errors
/// A library without a pair of consecutive frames (`input` names it), a
/// network that cannot be built, or a loss that is not finite (the error
/// says to lower `pretrain-he.lr`).
pub fn pretrain(
    lib: &MotionLib,
    input: &Path,
    set: &HeSettings,
    ingest_id: Option<String>,
    seed: u64,
    dev: &Device,
    mut step_done: impl FnMut(usize, &LossRow),
) -> Result<Pretrained> {
    let n_objects = lib.frames.iter().map(|f| f.n_objects).max().unwrap_or(0);
    let (mean, std) = he::standardisation(lib, n_objects);
    let cfg = HeConfig {
        version: 1,
        skeleton: lib.skeleton.name().into(),
        n_objects,
        channels: he::channels(lib.skeleton, n_objects),
        history: set.history,
        embedding: set.embedding,
        conv: set.conv.clone(),
        kernel: set.kernel,
        predictor_hidden: set.predictor_hidden.clone(),
        condition_slots: crate::motion::library::CONDITION_SLOTS,
        feature_layout: he::layout_text(lib.skeleton, n_objects),
        mean,
        std,
        ingest_id,
    };
    let feats = he::clip_features(lib, &cfg);
    let samples = samples(&feats);
    if samples.is_empty() {
        bail!(
            "{}: no pair of consecutive frames to learn from",
            input.display()
        );
    }

    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut params = Params::default();
    let enc = HistoryEncoder::new(cfg.clone(), &mut params, &mut rng, dev)?;
    let pred = Predictor::new(&cfg, &mut params, &mut rng, dev)?;
    let untrained = embed_all(&enc, &feats, dev)?;
    let sep_before = separation(&untrained, lib);
    let mut opt = AdamW::new(
        params.all(),
        ParamsAdamW {
            lr: set.lr,
            weight_decay: 0.0,
            ..Default::default()
        },
    )?;
    let mut curve = Vec::with_capacity(set.steps);
    for step in 0..set.steps {
        let idx: Vec<(usize, usize)> = (0..set.batch_size)
            .map(|_| samples[rng.random_range(0..samples.len())])
            .collect();
        let b = batch(&idx, &feats, lib, &cfg, dev)?;
        let h = enc.encode(&b.windows)?;
        let predicted = pred.predict(&b.cond, &b.current, &h)?;
        let prediction = (predicted - &b.target)?.sqr()?.mean_all()?;
        let reg = h.sqr()?.sum(1)?.mean_all()?;
        let total = ((&prediction * set.lambda_a)? + (&reg * set.lambda_b)?)?;
        opt.backward_step(&total)?;
        let row = LossRow {
            step: step as u32,
            total: total.to_scalar::<f32>()? as f64,
            prediction: prediction.to_scalar::<f32>()? as f64,
            regulariser: reg.to_scalar::<f32>()? as f64,
        };
        if !row.total.is_finite() {
            bail!(
                "pretrain-he diverged at step {step} (loss {}); lower pretrain-he.lr",
                row.total
            );
        }
        step_done(step, &row);
        curve.push(row);
    }
    let trained = embed_all(&enc, &feats, dev)?;
    let sep_after = separation(&trained, lib);
    let named = params
        .tensors("encoder.")
        .into_iter()
        .chain(params.tensors("predictor."))
        .collect();
    Ok(Pretrained {
        cfg,
        named,
        curve,
        trained,
        separation_untrained: sep_before,
        separation_trained: sep_after,
    })
}
