//! A ReLU MLP's forward and backward passes on flat `f32` buffers, for the
//! PPO update on the CPU (`crate::rl::ppo`).
//!
//! Why not candle's autograd there: at the CPU preset's sizes (a 902-value
//! observation, 256-256 hidden layers, 2,048-row minibatches) the update
//! spent about as long outside the matrix products as in them. Every op
//! allocates a fresh output (and every backward step a zero buffer to add
//! the gradient into), so that a tenth of a `bench train` profile's samples
//! were the kernel faulting new pages in; the bias gradient is a strided
//! reduction; Adam is about ten element-wise passes per weight. Here the same products are gemm's
//! (the crate candle's CPU matmul calls, with the same kernels), into
//! buffers that live across minibatches, with the bias, the ReLU and its
//! mask fused into single passes. The arithmetic is the same as the
//! autograd's up to the order of float sums (unit tests below compare
//! them); measured in docs/training.md, "A learner that keeps up".
//!
//! Layout: the weights of all layers sit in one flat vector, layer `l`'s
//! weight `[out, in]` (row-major, as `candle_nn::Linear` holds it) and bias
//! `[out]` at offsets the caller gives, so that one vector can hold several
//! networks and their optimiser moments.

use anyhow::{ensure, Result};
use gemm::Parallelism;

/// Where one layer's weight `[out, in]` and bias `[out]` start in a flat
/// parameter vector.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LayerAt {
    /// Offset of the weight (row-major `[out, in]`).
    pub weight: usize,
    /// Offset of the bias.
    pub bias: usize,
}

/// A ReLU MLP (ReLU after every layer but the last) over a flat parameter
/// vector, keeping each layer's output of the last forward pass for the
/// backward pass.
pub struct DenseMlp {
    sizes: Vec<usize>,
    at: Vec<LayerAt>,
    rows: usize,
    /// `acts[l]`: layer `l`'s output `[rows, sizes[l + 1]]`, after the ReLU
    /// for hidden layers.
    acts: Vec<Vec<f32>>,
    g: Vec<f32>,
    g_prev: Vec<f32>,
}

/// `dst[m x n] (+)= lhs[m x k] · rhs[k x n]` with explicit element strides
/// (`rs` between rows, `cs` between columns); `dst` is row-major. With
/// `accumulate` the product is added to `dst`, else it overwrites it.
///
/// # Panics
/// When a stride would reach past a slice (checked before gemm runs).
#[allow(clippy::too_many_arguments)]
fn matmul(
    (m, n, k): (usize, usize, usize),
    dst: &mut [f32],
    accumulate: bool,
    lhs: &[f32],
    (lhs_rs, lhs_cs): (usize, usize),
    rhs: &[f32],
    (rhs_rs, rhs_cs): (usize, usize),
    par: Parallelism,
) {
    if m == 0 || n == 0 {
        return;
    }
    assert!(dst.len() >= m * n, "matmul: destination too short");
    if k > 0 {
        assert!(
            (m - 1) * lhs_rs + (k - 1) * lhs_cs < lhs.len(),
            "matmul: lhs too short"
        );
        assert!(
            (k - 1) * rhs_rs + (n - 1) * rhs_cs < rhs.len(),
            "matmul: rhs too short"
        );
    }
    // SAFETY: every index gemm reads or writes lies inside the slices
    // (asserted above); `dst` does not alias the inputs (a `&mut` borrow).
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            lhs.as_ptr(),
            lhs_cs as isize,
            lhs_rs as isize,
            rhs.as_ptr(),
            rhs_cs as isize,
            rhs_rs as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            par,
        );
    }
}

/// The parallelism candle's own CPU matmul uses (candle-core
/// `src/cpu_backend/mod.rs`, `MatMul`): the threads `RAYON_NUM_THREADS`
/// names (set from `--threads`), split on rayon.
pub fn parallelism() -> Parallelism {
    match candle_core::utils::get_num_threads() {
        0 | 1 => Parallelism::None,
        n => Parallelism::Rayon(n),
    }
}

impl DenseMlp {
    /// An MLP over layer `sizes` (input, hidden..., output) whose layer `l`
    /// lives at `at[l]` in the parameter vectors later passed in.
    ///
    /// # Errors
    /// When `at` does not have one entry per layer.
    pub fn new(sizes: &[usize], at: &[LayerAt]) -> Result<DenseMlp> {
        ensure!(
            sizes.len() >= 2 && at.len() + 1 == sizes.len(),
            "dense mlp: {} layer offsets for {} sizes",
            at.len(),
            sizes.len()
        );
        Ok(DenseMlp {
            sizes: sizes.to_vec(),
            at: at.to_vec(),
            rows: 0,
            acts: vec![Vec::new(); at.len()],
            g: Vec::new(),
            g_prev: Vec::new(),
        })
    }

    /// The number of parameters the layers span (the largest end offset).
    pub fn param_end(&self) -> usize {
        self.at
            .iter()
            .zip(self.sizes.windows(2))
            .map(|(a, s)| (a.weight + s[0] * s[1]).max(a.bias + s[1]))
            .max()
            .unwrap_or(0)
    }

    /// The output `[rows, out]` for the input `x` (`[rows, in]`, row-major)
    /// under the weights in `params`; every layer's output is kept for
    /// [`DenseMlp::backward`].
    ///
    /// # Panics
    /// When `x` is not `rows` rows of the input size or `params` is shorter
    /// than [`DenseMlp::param_end`].
    pub fn forward(&mut self, params: &[f32], x: &[f32], rows: usize, par: Parallelism) -> &[f32] {
        assert_eq!(x.len(), rows * self.sizes[0], "dense mlp: input size");
        assert!(params.len() >= self.param_end(), "dense mlp: parameters");
        self.rows = rows;
        let last = self.at.len() - 1;
        for l in 0..self.at.len() {
            let (inp, out) = (self.sizes[l], self.sizes[l + 1]);
            let at = self.at[l];
            let w = &params[at.weight..at.weight + out * inp];
            let b = &params[at.bias..at.bias + out];
            let mut z = std::mem::take(&mut self.acts[l]);
            z.resize(rows * out, 0.0);
            for row in z.chunks_exact_mut(out) {
                row.copy_from_slice(b);
            }
            let prev: &[f32] = if l == 0 { x } else { &self.acts[l - 1] };
            // z += prev · Wᵀ: Wᵀ's (i, o) element is W[o * in + i]
            matmul(
                (rows, out, inp),
                &mut z,
                true,
                prev,
                (inp, 1),
                w,
                (1, inp),
                par,
            );
            if l < last {
                for v in &mut z {
                    *v = v.max(0.0);
                }
            }
            self.acts[l] = z;
        }
        &self.acts[last]
    }

    /// The gradient of a loss with respect to every weight and bias, from its
    /// gradient `g_out` (`[rows, out]`) with respect to the output of the
    /// last [`DenseMlp::forward`] on `x`: written (not added) into `grads` at
    /// the layers' offsets. The input's gradient is not computed.
    ///
    /// # Panics
    /// When the sizes do not match the last forward pass.
    pub fn backward(
        &mut self,
        params: &[f32],
        x: &[f32],
        g_out: &[f32],
        grads: &mut [f32],
        par: Parallelism,
    ) {
        let rows = self.rows;
        let n = self.at.len();
        assert_eq!(
            g_out.len(),
            rows * self.sizes[n],
            "dense mlp: output gradient"
        );
        assert_eq!(x.len(), rows * self.sizes[0], "dense mlp: input size");
        assert!(
            grads.len() >= self.param_end(),
            "dense mlp: gradient buffer"
        );
        let mut g = std::mem::take(&mut self.g);
        let mut g_prev = std::mem::take(&mut self.g_prev);
        g.clear();
        g.extend_from_slice(g_out);
        for l in (0..n).rev() {
            let (inp, out) = (self.sizes[l], self.sizes[l + 1]);
            let at = self.at[l];
            let prev: &[f32] = if l == 0 { x } else { &self.acts[l - 1] };
            // dW = gᵀ · prev: gᵀ's (o, r) element is g[r * out + o]
            matmul(
                (out, inp, rows),
                &mut grads[at.weight..at.weight + out * inp],
                false,
                &g,
                (1, out),
                prev,
                (inp, 1),
                par,
            );
            let db = &mut grads[at.bias..at.bias + out];
            db.fill(0.0);
            for row in g.chunks_exact(out) {
                for (d, v) in db.iter_mut().zip(row) {
                    *d += v;
                }
            }
            if l > 0 {
                // g_prev = (g · W) masked where the ReLU was off
                g_prev.resize(rows * inp, 0.0);
                let w = &params[at.weight..at.weight + out * inp];
                matmul(
                    (rows, inp, out),
                    &mut g_prev,
                    false,
                    &g,
                    (out, 1),
                    w,
                    (inp, 1),
                    par,
                );
                for (d, a) in g_prev.iter_mut().zip(&self.acts[l - 1]) {
                    if *a <= 0.0 {
                        *d = 0.0;
                    }
                }
                std::mem::swap(&mut g, &mut g_prev);
            }
        }
        self.g = g;
        self.g_prev = g_prev;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::{Mlp, MlpInit, Params};
    use candle_core::{Device, Tensor};
    use candle_nn::Module;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The flat vector and offsets of an [`Mlp`]'s variables (name order).
    fn flatten(p: &Params, prefix: &str, layers: usize) -> (Vec<f32>, Vec<LayerAt>) {
        let named = p.named();
        let mut flat = Vec::new();
        let mut offsets = std::collections::HashMap::new();
        for (k, v) in &named {
            offsets.insert(k.clone(), flat.len());
            flat.extend(
                v.as_tensor()
                    .flatten_all()
                    .unwrap()
                    .to_vec1::<f32>()
                    .unwrap(),
            );
        }
        let at = (0..layers)
            .map(|l| LayerAt {
                weight: offsets[&format!("{prefix}.{l}.weight")],
                bias: offsets[&format!("{prefix}.{l}.bias")],
            })
            .collect();
        (flat, at)
    }

    #[test]
    fn forward_and_gradients_agree_with_candles_autograd() {
        let dev = Device::Cpu;
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut p = Params::default();
        let sizes = [37, 64, 48, 11];
        let init = MlpInit {
            out_bound: None,
            zero_bias: false,
        };
        let mlp = Mlp::with_init(&mut p, "net", &sizes, init, &mut rng, &dev).unwrap();
        let rows = 53;
        let x: Vec<f32> = (0..rows * sizes[0])
            .map(|_| rng.random_range(-2.0..2.0))
            .collect();
        // a loss with a non-trivial output gradient: sum(c ⊙ out²) / 2
        let c: Vec<f32> = (0..rows * sizes[3])
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let xt = Tensor::from_slice(&x, (rows, sizes[0]), &dev).unwrap();
        let ct = Tensor::from_slice(&c, (rows, sizes[3]), &dev).unwrap();
        let out = mlp.forward(&xt).unwrap();
        let loss = (out.sqr().unwrap() * &ct)
            .unwrap()
            .sum_all()
            .unwrap()
            .affine(0.5, 0.0)
            .unwrap();
        let grads = loss.backward().unwrap();

        let (params, at) = flatten(&p, "net", 3);
        let mut net = DenseMlp::new(&sizes, &at).unwrap();
        assert_eq!(net.param_end(), params.len());
        let dense_out = net.forward(&params, &x, rows, parallelism()).to_vec();
        let want_out = out.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let max_out = want_out.iter().fold(0f32, |m, v| m.max(v.abs()));
        for (a, b) in dense_out.iter().zip(&want_out) {
            assert!(
                (a - b).abs() <= 1e-5 * max_out.max(1.0),
                "output {a} vs {b}"
            );
        }
        let g_out: Vec<f32> = dense_out.iter().zip(&c).map(|(o, c)| o * c).collect();
        let mut g = vec![f32::NAN; params.len()];
        net.backward(&params, &x, &g_out, &mut g, parallelism());
        let mut compared = 0;
        for (k, v) in p.named() {
            let want = grads
                .get(v.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            let off = if k.ends_with("weight") {
                at[k.split('.').nth(1).unwrap().parse::<usize>().unwrap()].weight
            } else {
                at[k.split('.').nth(1).unwrap().parse::<usize>().unwrap()].bias
            };
            let scale = want.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-3);
            for (i, w) in want.iter().enumerate() {
                let d = g[off + i];
                assert!((d - w).abs() <= 1e-4 * scale, "{k}[{i}]: {d} vs {w}");
                compared += 1;
            }
        }
        assert_eq!(compared, params.len());
    }

    #[test]
    fn a_second_pass_reuses_its_buffers_and_gives_the_same_bits() {
        let sizes = [5, 8, 3];
        let at = [
            LayerAt {
                weight: 0,
                bias: 40,
            },
            LayerAt {
                weight: 48,
                bias: 72,
            },
        ];
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let params: Vec<f32> = (0..75).map(|_| rng.random_range(-1.0..1.0)).collect();
        let x: Vec<f32> = (0..4 * 5).map(|_| rng.random_range(-1.0..1.0)).collect();
        let mut net = DenseMlp::new(&sizes, &at).unwrap();
        assert_eq!(net.param_end(), 75);
        let first = net.forward(&params, &x, 4, Parallelism::None).to_vec();
        let mut g1 = vec![0.0; 75];
        net.backward(&params, &x, &first, &mut g1, Parallelism::None);
        // a different batch in between must not leak into the next pass
        let other: Vec<f32> = (0..7 * 5).map(|i| i as f32).collect();
        net.forward(&params, &other, 7, Parallelism::None);
        let again = net.forward(&params, &x, 4, Parallelism::None).to_vec();
        let mut g2 = vec![0.0; 75];
        net.backward(&params, &x, &again, &mut g2, Parallelism::None);
        assert_eq!(first, again);
        assert_eq!(g1, g2);
        assert!(g1.iter().any(|v| *v != 0.0));
    }
}
