//! Running observation normalisation (rl_games `RunningMeanStd`,
//! Denys88/rl_games 1.1.4 `rl_games/algos_torch/running_mean_std.py`):
//! per-dimension mean and variance kept in `f64`, starting from mean 0,
//! variance 1, count 1, merged batch by batch with the parallel variance
//! formula (Chan et al.) using the *unbiased* batch variance, and applied as
//! `(x - mean) / sqrt(var + 1e-5)` clamped to `[-5, 5]`.

use anyhow::{ensure, Result};
use serde::{Deserialize, Serialize};

/// Added to the variance before the square root.
pub const NORM_EPS: f64 = 1e-5;
/// Normalised values are clamped to `[-NORM_CLIP, NORM_CLIP]`.
pub const NORM_CLIP: f64 = 5.0;

/// The moments of one batch ([`RunningNorm::batch_moments`]).
#[derive(Clone, Debug, PartialEq)]
pub struct BatchMoments {
    /// Mean per dimension.
    pub mean: Vec<f64>,
    /// Unbiased variance per dimension (0 for a batch of one row).
    pub var: Vec<f64>,
    /// Number of rows.
    pub count: f64,
}

/// Per-dimension running mean and variance with a sample count.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunningNorm {
    /// Running mean, one per dimension.
    pub mean: Vec<f64>,
    /// Running variance, one per dimension.
    pub var: Vec<f64>,
    /// Number of samples merged so far (including the prior's 1).
    pub count: f64,
}

impl RunningNorm {
    /// The rl_games start state: mean 0, variance 1, count 1.
    pub fn new(dim: usize) -> Self {
        RunningNorm {
            mean: vec![0.0; dim],
            var: vec![1.0; dim],
            count: 1.0,
        }
    }

    /// An empty state (count 0): after one merge it holds exactly that
    /// batch's mean and unbiased variance.
    pub fn empty(dim: usize) -> Self {
        RunningNorm {
            mean: vec![0.0; dim],
            var: vec![0.0; dim],
            count: 0.0,
        }
    }

    /// Number of dimensions.
    pub fn dim(&self) -> usize {
        self.mean.len()
    }

    /// Merge a batch of rows (`data.len() == rows * dim`). A batch of one row
    /// has no unbiased variance and is merged with batch variance 0.
    pub fn update(&mut self, data: &[f32]) -> Result<()> {
        if let Some(b) = self.batch_moments(data)? {
            self.merge(&b.mean, &b.var, b.count);
        }
        Ok(())
    }

    /// The mean and unbiased variance per dimension of the rows of `data`
    /// and their count (`None` for no row); what [`RunningNorm::update`]
    /// merges.
    ///
    /// # Errors
    /// When `data` is not whole rows of this normaliser's dimension.
    pub fn batch_moments(&self, data: &[f32]) -> Result<Option<BatchMoments>> {
        let d = self.dim();
        ensure!(
            d > 0 && data.len().is_multiple_of(d),
            "normaliser: {} values are not rows of {d}",
            data.len()
        );
        let n = data.len() / d;
        if n == 0 {
            return Ok(None);
        }
        let mut bmean = vec![0.0f64; d];
        for row in data.chunks_exact(d) {
            for (m, &x) in bmean.iter_mut().zip(row) {
                *m += x as f64;
            }
        }
        for m in &mut bmean {
            *m /= n as f64;
        }
        let mut bvar = vec![0.0f64; d];
        if n > 1 {
            for row in data.chunks_exact(d) {
                for ((v, &x), m) in bvar.iter_mut().zip(row).zip(&bmean) {
                    let e = x as f64 - m;
                    *v += e * e;
                }
            }
            for v in &mut bvar {
                *v /= (n - 1) as f64;
            }
        }
        Ok(Some(BatchMoments {
            mean: bmean,
            var: bvar,
            count: n as f64,
        }))
    }

    /// Merge batch moments (`bmean`, `bvar`) of `bcount` samples.
    pub fn merge(&mut self, bmean: &[f64], bvar: &[f64], bcount: f64) {
        let tot = self.count + bcount;
        for i in 0..self.dim() {
            let delta = bmean[i] - self.mean[i];
            let m2 = self.var[i] * self.count
                + bvar[i] * bcount
                + delta * delta * self.count * bcount / tot;
            self.mean[i] += delta * bcount / tot;
            self.var[i] = m2 / tot;
        }
        self.count = tot;
    }

    /// Normalise rows of `data` in place-free fashion: `(x - mean) /
    /// sqrt(var + 1e-5)`, clamped to `[-5, 5]`.
    pub fn normalize(&self, data: &[f32]) -> Vec<f32> {
        let d = self.dim();
        let inv: Vec<f64> = self
            .var
            .iter()
            .map(|v| 1.0 / (v + NORM_EPS).sqrt())
            .collect();
        data.iter()
            .enumerate()
            .map(|(k, &x)| {
                let i = k % d;
                ((x as f64 - self.mean[i]) * inv[i]).clamp(-NORM_CLIP, NORM_CLIP) as f32
            })
            .collect()
    }
}
