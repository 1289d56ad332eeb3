//! The History Encoder (paper Section 4.6, Appendix B.5, Eqs. 21-23; the
//! reference code is Ingrid789/SkillMimic-V2
//! `skillmimic/utils/history_encoder.py` (network),
//! `skillmimic/utils/state_prediction_ballplay.py` (pre-training) and
//! `skillmimic/env/tasks/skillmimic1_hist.py` (use in the policy)).
//!
//! * Per-frame feature (`skillmimic1_hist.py`): root height (1); positions of
//!   bodies 1..B-1 relative to the root, turned into the heading frame
//!   (3(B-1)); joint exp-maps (3J); each object's position in the heading frame
//!   with absolute height (3 per object). BallPlay: 1 + 156 + 156 + 3 = 316
//!   channels. The heading is the true quaternion heading everywhere (the
//!   reference pre-training, `state_prediction_ballplay.py`, passes an exp-map
//!   where a quaternion belongs, a bug not copied here). ParaHome uses its 60
//!   simulated bodies (the reference's 70 data slots include ten empty ones):
//!   1 + 180 + 180 + 3. Features are standardised per channel with the mean
//!   and standard deviation of the training frames; both travel in the config.
//! * Encoder theta (`history_encoder.py`): three 1-D convolutions over the
//!   last k = 60 frames (C -> 128 -> 64 -> 32 channels, kernel 3, zero
//!   padding 1, ReLU), flattened channel-major (32 x 60), then a linear layer
//!   to mu = 3.
//! * Predictor psi: an MLP (1024-512-512, ReLU) from [c (64-slot one-hot), s_t,
//!   h_t] to s_{t+1} (Eq. 22; this project's sizes: the policy's MLP shape).
//! * Loss, Eq. 23: lambda_a * MSE(s_{t+1}, predicted) + lambda_b * mean |h|^2,
//!   lambda_a = 1, lambda_b = 1e-5 (the reference code has no regulariser).
//! * Windows (as in `state_prediction_ballplay.py`): for frame t, history =
//!   frames [t-60, t); slots before the clip's start, and missing frames, are
//!   zeros (in standardised units, i.e. the mean frame).

use super::{Mlp, Params};
use crate::motion::{quat, MotionLib, Skeleton, State};
use anyhow::{bail, Result};
use candle_core::{Device, Tensor, D};
use candle_nn::{Conv1d, Linear, Module};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Everything needed to rebuild the encoder without the recipe
/// (`he.config.json` beside `he.safetensors`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HeConfig {
    /// Layout version of this file.
    pub version: u32,
    /// Skeleton of the features.
    pub skeleton: String,
    /// Objects in the feature (0, 1 or 2).
    pub n_objects: usize,
    /// Channels C per frame.
    pub channels: usize,
    /// History length k, frames.
    pub history: usize,
    /// Embedding size mu.
    pub embedding: usize,
    /// Convolution output channels.
    pub conv: Vec<usize>,
    /// Convolution kernel.
    pub kernel: usize,
    /// Predictor hidden sizes.
    pub predictor_hidden: Vec<usize>,
    /// Condition slots (one-hot of the class id).
    pub condition_slots: usize,
    /// Human description of the channel layout.
    pub feature_layout: String,
    /// Per-channel mean of the raw features.
    pub mean: Vec<f32>,
    /// Per-channel standard deviation (floored at 1e-3).
    pub std: Vec<f32>,
    /// The ingest run whose clips it was trained on
    /// ([`crate::table::ingest_id`]; absent in files of older versions).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ingest_id: Option<String>,
}

/// Channels of the per-frame feature.
pub fn channels(sk: Skeleton, n_objects: usize) -> usize {
    1 + 3 * (sk.n_bodies() - 1) + 3 * sk.n_joints() + 3 * n_objects
}

/// The raw (unstandardised) feature of one state; objects beyond those the
/// state has are zeros.
pub fn feature(s: &State, sk: Skeleton, n_objects: usize) -> Vec<f32> {
    let inv = quat::from_expmap([0.0, 0.0, -quat::heading(s.root_rot)]);
    let r = [
        s.root_pos[0] as f64,
        s.root_pos[1] as f64,
        s.root_pos[2] as f64,
    ];
    let mut v = Vec::with_capacity(channels(sk, n_objects));
    v.push(s.root_pos[2]);
    for b in s.body_pos.chunks_exact(3).skip(1) {
        let d = quat::rotate(
            inv,
            [b[0] as f64 - r[0], b[1] as f64 - r[1], b[2] as f64 - r[2]],
        );
        v.extend(d.map(|x| x as f32));
    }
    v.extend_from_slice(&s.joint_rot);
    for k in 0..n_objects {
        match s.obj_pos.get(3 * k..3 * k + 3) {
            Some(o) => {
                let d = quat::rotate(inv, [o[0] as f64 - r[0], o[1] as f64 - r[1], 0.0]);
                v.extend([d[0] as f32, d[1] as f32, o[2]]);
            }
            None => v.extend([0.0; 3]),
        }
    }
    v
}

/// The feature layout text recorded in the config.
pub fn layout_text(sk: Skeleton, n_objects: usize) -> String {
    format!(
        "root height (1); bodies 1..{} relative to the root in the heading frame ({}); joint exp-maps ({}); object positions in the heading frame, absolute height ({})",
        sk.n_bodies() - 1,
        3 * (sk.n_bodies() - 1),
        3 * sk.n_joints(),
        3 * n_objects
    )
}

/// The feature of `s` standardised with `cfg`'s per-channel mean and std.
pub fn standardised_feature(s: &State, sk: Skeleton, cfg: &HeConfig) -> Vec<f32> {
    feature(s, sk, cfg.n_objects)
        .iter()
        .zip(cfg.mean.iter().zip(&cfg.std))
        .map(|(x, (m, sd))| (x - m) / sd)
        .collect()
}

/// Standardised features of every frame of every clip (`None` = missing).
pub fn clip_features(lib: &MotionLib, cfg: &HeConfig) -> Vec<Vec<Option<Vec<f32>>>> {
    let sk = lib.skeleton;
    lib.frames
        .iter()
        .map(|c| {
            (0..c.frames)
                .map(|i| c.state(i).map(|s| standardised_feature(&s, sk, cfg)))
                .collect()
        })
        .collect()
}

/// Per-channel mean and standard deviation over every valid frame.
pub fn standardisation(lib: &MotionLib, n_objects: usize) -> (Vec<f32>, Vec<f32>) {
    let sk = lib.skeleton;
    let c = channels(sk, n_objects);
    let (mut sum, mut sq, mut n) = (vec![0f64; c], vec![0f64; c], 0f64);
    for clip in &lib.frames {
        for i in 0..clip.frames {
            if let Some(s) = clip.state(i) {
                for (k, x) in feature(&s, sk, n_objects).iter().enumerate() {
                    sum[k] += *x as f64;
                    sq[k] += (*x as f64) * (*x as f64);
                }
                n += 1.0;
            }
        }
    }
    let n = n.max(1.0);
    let mean: Vec<f32> = sum.iter().map(|s| (s / n) as f32).collect();
    let std = sum
        .iter()
        .zip(&sq)
        .map(|(s, q)| ((q / n - (s / n).powi(2)).max(0.0).sqrt().max(1e-3)) as f32)
        .collect();
    (mean, std)
}

/// The history window of frame `t` of a clip: `[k, C]` row-major, zeros for
/// slots before the clip's start and for missing frames.
pub fn window(feats: &[Option<Vec<f32>>], t: usize, k: usize, c: usize) -> Vec<f32> {
    let mut w = vec![0f32; k * c];
    for slot in 0..k {
        let idx = t as isize - k as isize + slot as isize;
        if idx >= 0 {
            if let Some(f) = &feats[idx as usize] {
                w[slot * c..(slot + 1) * c].copy_from_slice(f);
            }
        }
    }
    w
}

/// Encoder theta (cloning shares the weights).
#[derive(Clone)]
pub struct HistoryEncoder {
    convs: Vec<Conv1d>,
    fc: Linear,
    /// Its configuration.
    pub cfg: HeConfig,
}

impl HistoryEncoder {
    /// Build with seeded initial weights, registering them in `p` as `encoder.*`.
    pub fn new(cfg: HeConfig, p: &mut Params, rng: &mut ChaCha8Rng, dev: &Device) -> Result<Self> {
        let mut convs = Vec::new();
        let mut inp = cfg.channels;
        for (i, out) in cfg.conv.iter().enumerate() {
            convs.push(p.conv1d(
                &format!("encoder.conv{i}"),
                inp,
                *out,
                cfg.kernel,
                cfg.kernel / 2,
                rng,
                dev,
            )?);
            inp = *out;
        }
        let fc = p.linear("encoder.fc", inp * cfg.history, cfg.embedding, rng, dev)?;
        Ok(HistoryEncoder { convs, fc, cfg })
    }

    /// The convolutions, input first (weights `[out, in, kernel]`).
    pub fn convs(&self) -> &[Conv1d] {
        &self.convs
    }

    /// The linear layer from the flattened last activation (`[mu, c * k]`).
    pub fn fc(&self) -> &Linear {
        &self.fc
    }

    /// `[batch, k, C]` windows to `[batch, mu]` embeddings.
    pub fn encode(&self, windows: &Tensor) -> candle_core::Result<Tensor> {
        let mut h = windows.transpose(1, 2)?.contiguous()?; // [batch, C, k]
        for c in &self.convs {
            h = c.forward(&h)?.relu()?;
        }
        let h = h.flatten_from(1)?; // channel-major: channel * k + time
        self.fc.forward(&h)
    }
}

/// Predictor psi.
pub struct Predictor {
    mlp: Mlp,
}

impl Predictor {
    /// Build with seeded initial weights, registered as `predictor.*`.
    pub fn new(cfg: &HeConfig, p: &mut Params, rng: &mut ChaCha8Rng, dev: &Device) -> Result<Self> {
        let inp = cfg.condition_slots + cfg.channels + cfg.embedding;
        Ok(Predictor {
            mlp: Mlp::new(
                p,
                "predictor",
                inp,
                &cfg.predictor_hidden,
                cfg.channels,
                rng,
                dev,
            )?,
        })
    }

    /// `[c, s_t, h_t]` to the predicted `s_{t+1}`.
    pub fn predict(&self, cond: &Tensor, s: &Tensor, h: &Tensor) -> candle_core::Result<Tensor> {
        self.mlp.forward(&Tensor::cat(&[cond, s, h], D::Minus1)?)
    }
}

/// One-hot condition rows `[n, slots]` of class ids.
pub fn one_hot(classes: &[u32], slots: usize, dev: &Device) -> Result<Tensor> {
    let mut v = vec![0f32; classes.len() * slots];
    for (i, c) in classes.iter().enumerate() {
        if *c as usize >= slots {
            bail!("class {c} does not fit the {slots} condition slots");
        }
        v[i * slots + *c as usize] = 1.0;
    }
    Ok(Tensor::from_vec(v, (classes.len(), slots), dev)?)
}

/// A frozen encoder loaded from a folder holding `he.safetensors` and
/// `he.config.json`.
pub fn load(dir: &std::path::Path, dev: &Device) -> Result<HistoryEncoder> {
    use anyhow::Context;
    use rand::SeedableRng;
    let cp = dir.join("he.config.json");
    let cfg: HeConfig = serde_json::from_str(&std::fs::read_to_string(&cp).with_context(|| {
        format!(
            "cannot read {}: run `skillaug pretrain-he` first",
            cp.display()
        )
    })?)
    .with_context(|| format!("{} is not a history-encoder config", cp.display()))?;
    let wp = dir.join("he.safetensors");
    let named = candle_core::safetensors::load(&wp, dev)
        .with_context(|| format!("cannot read {}", wp.display()))?;
    let mut p = Params::default();
    let enc = HistoryEncoder::new(cfg, &mut p, &mut ChaCha8Rng::seed_from_u64(0), dev)?;
    p.load(&named)
        .with_context(|| format!("{}", wp.display()))?;
    Ok(enc)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn channel_counts_match_the_reference() {
        assert_eq!(channels(Skeleton::MocapHumanoid, 1), 316);
        assert_eq!(channels(Skeleton::ParaHome, 1), 1 + 180 + 180 + 3);
        let s = State {
            root_pos: [1.0, 2.0, 0.9],
            root_rot: [0.0, 0.0, 0.0, 1.0],
            joint_rot: vec![0.1; 156],
            body_pos: (0..159).map(|i| i as f32 * 0.01).collect(),
            obj_pos: vec![1.5, 2.0, 0.3],
            ..State::default()
        };
        let f = feature(&s, Skeleton::MocapHumanoid, 1);
        assert_eq!(f.len(), 316);
        assert_eq!(f[0], 0.9);
        // body 1 relative to the root, heading 0: (0.03, 0.04, 0.05) - (1, 2, 0.9)
        assert!((f[1] - (0.03 - 1.0)).abs() < 1e-6 && (f[3] - (0.05 - 0.9)).abs() < 1e-6);
        // object: heading-frame x, y relative to the root, absolute z
        assert!((f[313] - 0.5).abs() < 1e-6 && f[314].abs() < 1e-6 && f[315] == 0.3);
    }

    #[test]
    fn windows_are_zero_padded_before_the_start_and_at_missing_frames() {
        let feats: Vec<Option<Vec<f32>>> = vec![Some(vec![1.0, 1.0]), None, Some(vec![3.0, 3.0])];
        let w = window(&feats, 3, 4, 2);
        assert_eq!(w, [0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 3.0, 3.0]);
        assert!(one_hot(&[64], 64, &Device::Cpu).is_err());
    }
}
