//! The history encoder's forward pass one window position at a time, for
//! the environments' per-step embeddings.
//!
//! The policy's history window moves by one frame per policy step, and
//! a 1-D convolution with stride 1 gives most of the new window's
//! activations already: a position whose inputs are the previous window's
//! inputs one position later has the previous window's value one position
//! later. Only the positions next to the window's two ends (3, 5 and 7 of
//! the 60 in the three layers of kernel 3) need computing again, about
//! 1/17 of the arithmetic of the whole window (`docs/training.md`,
//! "The full method's speed").
//!
//! candle has no such incremental convolution, and its `conv1d` (an
//! unfolding and a blocked matrix product) sums each output in an order of
//! its own that a single position cannot reproduce; this module's own
//! loops compute every output from its inputs in one fixed order, so a
//! reused value and a recomputed one have the same bits, and an embedding
//! does not depend on what was cached (resume after a checkpoint rebuilds
//! the caches and stays bit-exact). The values agree with
//! [`HistoryEncoder::encode`] up to float rounding (tested).

use super::he::HistoryEncoder;
use anyhow::{ensure, Result};
use wide::f32x8;

/// One convolution layer with its weight laid out as `[out][tap][in]`.
#[derive(Clone, Debug)]
struct ConvLayer {
    /// `[out * kernel * inp]`: `w[(o * kernel + j) * inp + i]` is candle's
    /// `weight[o][i][j]`.
    w: Vec<f32>,
    /// `[out]`.
    b: Vec<f32>,
    inp: usize,
    out: usize,
    /// The positions of a window shifted by one frame that are not the
    /// previous window's values one position later.
    recompute: Vec<usize>,
}

/// The encoder theta of [`HistoryEncoder`] as plain weights: convolutions
/// (kernel `K`, zero padding `K / 2`, ReLU) over a `[k, C]` window, then a
/// linear layer from the channel-major flattened last activation to the
/// embedding `[mu]`.
#[derive(Clone, Debug)]
pub struct EncoderKernel {
    layers: Vec<ConvLayer>,
    /// `[mu][k][c_last]` (candle's `[mu][c_last * k]` read as `c * k + t`).
    fc_w: Vec<f32>,
    /// `[mu]`.
    fc_b: Vec<f32>,
    k: usize,
    c: usize,
    kernel: usize,
    /// `0..k`.
    all: Vec<usize>,
}

/// How [`EncoderKernel::encode_cached`] used its cache.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reuse {
    /// The window was the cached one (and not also the cached one moved
    /// on by a frame, as a constant window is): no convolution computed.
    Same,
    /// The window was the cached one moved on by a frame: only the
    /// positions next to its ends computed.
    Shifted,
    /// Every position computed.
    Full,
}

/// What one environment's last embedding computed: the window and every
/// layer's activations (`[k][out]` per layer). Empty until first used.
#[derive(Clone, Debug, Default)]
pub struct EncoderCache {
    window: Vec<f32>,
    acts: Vec<Vec<f32>>,
}

impl EncoderKernel {
    /// Copy the weights of `enc` (on any device).
    ///
    /// Errors: an even kernel (the padding `K / 2` would not centre it).
    pub fn new(enc: &HistoryEncoder) -> Result<EncoderKernel> {
        let cfg = &enc.cfg;
        let (k, kernel) = (cfg.history, cfg.kernel);
        ensure!(
            kernel % 2 == 1,
            "history encoder kernel {kernel}: only odd kernels are supported"
        );
        let pad = kernel / 2;
        let mut layers = Vec::new();
        // the input window shifted by one frame: slot p is old slot p + 1,
        // except the newest
        let mut prev: Vec<bool> = (0..k).map(|p| p + 1 < k).collect();
        for conv in enc.convs() {
            let (out, inp, kk) = conv.weight().dims3()?;
            ensure!(
                kk == kernel,
                "history encoder: conv kernel {kk} != {kernel}"
            );
            let wt = conv.weight().flatten_all()?.to_vec1::<f32>()?;
            let mut w = vec![0f32; out * kernel * inp];
            for o in 0..out {
                for i in 0..inp {
                    for j in 0..kernel {
                        w[(o * kernel + j) * inp + i] = wt[(o * inp + i) * kernel + j];
                    }
                }
            }
            let b = match conv.bias() {
                Some(b) => b.to_vec1::<f32>()?,
                None => vec![0.0; out],
            };
            // reuse[p]: position p of a window shifted by one frame equals
            // position p + 1 of the window before
            let reuse: Vec<bool> = (0..k)
                .map(|p| {
                    p + 1 < k
                        && (0..kernel).all(|j| {
                            let q = p as isize + j as isize - pad as isize;
                            let new_in = (0..k as isize).contains(&q);
                            let old_in = (0..k as isize).contains(&(q + 1));
                            match (new_in, old_in) {
                                (true, true) => prev[q as usize],
                                (false, false) => true,
                                _ => false,
                            }
                        })
                })
                .collect();
            let recompute = (0..k).filter(|p| !reuse[*p]).collect();
            prev = reuse;
            layers.push(ConvLayer {
                w,
                b,
                inp,
                out,
                recompute,
            });
        }
        let c_last = layers.last().map_or(cfg.channels, |l| l.out);
        let (mu, fan_in) = enc.fc().weight().dims2()?;
        ensure!(
            fan_in == c_last * k,
            "history encoder: fc takes {fan_in} values, expected {c_last} x {k}"
        );
        let ft = enc.fc().weight().flatten_all()?.to_vec1::<f32>()?;
        let mut fc_w = vec![0f32; mu * k * c_last];
        for e in 0..mu {
            for c in 0..c_last {
                for t in 0..k {
                    fc_w[(e * k + t) * c_last + c] = ft[e * fan_in + c * k + t];
                }
            }
        }
        let fc_b = match enc.fc().bias() {
            Some(b) => b.to_vec1::<f32>()?,
            None => vec![0.0; mu],
        };
        Ok(EncoderKernel {
            layers,
            fc_w,
            fc_b,
            k,
            c: cfg.channels,
            kernel,
            all: (0..k).collect(),
        })
    }

    /// Positions of a shifted window that each layer computes again.
    pub fn recomputed_positions(&self) -> Vec<usize> {
        self.layers.iter().map(|l| l.recompute.len()).collect()
    }

    /// The embedding `[mu]` of one `[k * C]` window (row-major `[k, C]`),
    /// computed from scratch.
    pub fn encode(&self, window: &[f32]) -> Vec<f32> {
        self.encode_cached(window, &mut EncoderCache::default()).0
    }

    /// The embedding `[mu]` of `window`, reusing `cache`: one position
    /// later where the window is the cached one moved on by a frame,
    /// unchanged if it is the cached one, from scratch otherwise. The result
    /// has the same bits as [`EncoderKernel::encode`] either way; `cache`
    /// then holds this window.
    ///
    /// Panics if `window` is not `k * C` long.
    pub fn encode_cached(&self, window: &[f32], cache: &mut EncoderCache) -> (Vec<f32>, Reuse) {
        let (k, c) = (self.k, self.c);
        assert_eq!(window.len(), k * c, "history window of {} values", k * c);
        let same_shape = cache.window.len() == window.len()
            && cache.acts.len() == self.layers.len()
            && cache
                .acts
                .iter()
                .zip(&self.layers)
                .all(|(a, l)| a.len() == k * l.out);
        // a step's window is the cached one moved on: test that first, so
        // the steps do not also compare the whole window
        let shifted = same_shape && bits_equal(&window[..(k - 1) * c], &cache.window[c..]);
        let reuse = if shifted {
            Reuse::Shifted
        } else if same_shape && bits_equal(window, &cache.window) {
            Reuse::Same
        } else {
            Reuse::Full
        };
        if reuse != Reuse::Same {
            // no window names the activations while they change
            cache.window.clear();
            if !same_shape {
                cache.acts = self.layers.iter().map(|l| vec![0.0; k * l.out]).collect();
            }
            for li in 0..self.layers.len() {
                let (done, rest) = cache.acts.split_at_mut(li);
                let input: &[f32] = match done.last() {
                    Some(a) => a,
                    None => window,
                };
                let layer = &self.layers[li];
                let acts = &mut rest[0];
                if shifted {
                    acts.copy_within(layer.out.., 0);
                }
                let todo = if shifted { &layer.recompute } else { &self.all };
                conv_positions(layer, self.kernel, k, input, todo, acts);
            }
            cache.window.extend_from_slice(window);
        }
        let last: &[f32] = cache.acts.last().map_or(window, |a| a);
        let n = last.len();
        let emb = self
            .fc_b
            .iter()
            .enumerate()
            .map(|(e, b)| b + dot(&self.fc_w[e * n..(e + 1) * n], last))
            .collect();
        (emb, reuse)
    }
}

/// Layer `layer` (kernel `kernel`, window `k`) at the window positions
/// `positions`, into `acts` (`[k][out]`): `acts[p][o] = relu(sum over taps
/// j of w[o][j] . input[p + j - K/2] + b[o])`, taps outside the window being
/// zeros and the taps summed in order. Four output channels at a time, so
/// that four independent sums are in flight (the eight-lane sums of one
/// channel alone wait on each other's additions).
fn conv_positions(
    layer: &ConvLayer,
    kernel: usize,
    k: usize,
    input: &[f32],
    positions: &[usize],
    acts: &mut [f32],
) {
    let pad = kernel / 2;
    let (inp, out) = (layer.inp, layer.out);
    let row = |o: usize, j: usize| &layer.w[(o * kernel + j) * inp..(o * kernel + j + 1) * inp];
    // the input row of tap j at position p, if inside the window
    let tap = |p: usize, j: usize| {
        (p + j >= pad && p + j - pad < k)
            .then(|| &input[(p + j - pad) * inp..(p + j - pad + 1) * inp])
    };
    let mut sums = vec![[0f32; 4]; positions.len()];
    let mut o = 0;
    while o < out {
        let width = (out - o).min(4);
        sums.fill([0.0; 4]);
        for j in 0..kernel {
            for (s, &p) in sums.iter_mut().zip(positions) {
                let Some(x) = tap(p, j) else { continue };
                if width == 4 {
                    let d = dot4_lanes([row(o, j), row(o + 1, j), row(o + 2, j), row(o + 3, j)], x);
                    for i in 0..4 {
                        s[i] += d[i];
                    }
                } else {
                    for (i, si) in s.iter_mut().enumerate().take(width) {
                        *si += dot(row(o + i, j), x);
                    }
                }
            }
        }
        for (s, &p) in sums.iter().zip(positions) {
            for i in 0..width {
                acts[p * out + o + i] = (s[i] + layer.b[o + i]).max(0.0);
            }
        }
        o += width;
    }
}

/// `a . b` summed in one fixed order: eight running sums (one `f32x8`:
/// separate multiplications and additions, never fused, so the bits are
/// those of eight scalar sums on any CPU) over blocks of eight, the tail
/// added lane by lane, then the sums pairwise.
#[inline(always)]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let (ac, at) = a.as_chunks::<8>();
    let (bc, bt) = b.as_chunks::<8>();
    let mut acc = f32x8::ZERO;
    for (x, y) in ac.iter().zip(bc) {
        acc += f32x8::new(*x) * f32x8::new(*y);
    }
    reduce8(add_tail(acc, at, bt))
}

/// Four dot products `rows[i] . x` with [`dot`]'s order each (the
/// same bits as four calls of it), computed together.
#[inline(always)]
fn dot4_lanes(rows: [&[f32]; 4], x: &[f32]) -> [f32; 4] {
    let (xc, xt) = x.as_chunks::<8>();
    let (r0, t0) = rows[0].as_chunks::<8>();
    let (r1, t1) = rows[1].as_chunks::<8>();
    let (r2, t2) = rows[2].as_chunks::<8>();
    let (r3, t3) = rows[3].as_chunks::<8>();
    let mut a = [f32x8::ZERO; 4];
    for ((((x, w0), w1), w2), w3) in xc.iter().zip(r0).zip(r1).zip(r2).zip(r3) {
        let x = f32x8::new(*x);
        a[0] += f32x8::new(*w0) * x;
        a[1] += f32x8::new(*w1) * x;
        a[2] += f32x8::new(*w2) * x;
        a[3] += f32x8::new(*w3) * x;
    }
    [
        reduce8(add_tail(a[0], t0, xt)),
        reduce8(add_tail(a[1], t1, xt)),
        reduce8(add_tail(a[2], t2, xt)),
        reduce8(add_tail(a[3], t3, xt)),
    ]
}

/// The lanes of `acc` with the products of the tails (fewer than eight
/// values) added lane by lane.
#[inline(always)]
fn add_tail(acc: f32x8, a: &[f32], b: &[f32]) -> [f32; 8] {
    let mut acc = acc.to_array();
    for (l, (x, y)) in a.iter().zip(b).enumerate() {
        acc[l] += x * y;
    }
    acc
}

#[inline(always)]
fn reduce8(acc: [f32; 8]) -> f32 {
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]))
}

fn bits_equal(a: &[f32], b: &[f32]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::he::HeConfig;
    use crate::nn::Params;
    use candle_core::{Device, Tensor};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn encoder(channels: usize, history: usize, conv: &[usize], kernel: usize) -> HistoryEncoder {
        let cfg = HeConfig {
            version: 1,
            skeleton: "mocap_humanoid".into(),
            n_objects: 1,
            channels,
            history,
            embedding: 3,
            conv: conv.to_vec(),
            kernel,
            predictor_hidden: vec![8],
            condition_slots: 64,
            feature_layout: String::new(),
            mean: vec![0.0; channels],
            std: vec![1.0; channels],
            ingest_id: None,
        };
        let mut p = Params::default();
        HistoryEncoder::new(cfg, &mut p, &mut ChaCha8Rng::seed_from_u64(3), &Device::Cpu).unwrap()
    }

    #[test]
    fn positions_agree_with_candle_and_shifted_windows_reuse_their_cache_bit_for_bit() {
        // kernel 3, padding 1: the two window ends, plus one more per side
        // and layer; 6 channels leave a group of two beside the groups of
        // four output channels
        shifted_windows_match(&[16, 6, 4], 3, &[3, 5, 7]);
        // kernel 5, padding 2: two more per side and layer
        shifted_windows_match(&[8, 5], 5, &[5, 9]);
    }

    fn shifted_windows_match(conv: &[usize], kernel: usize, recomputed: &[usize]) {
        let (c, k) = (13, 20);
        let enc = encoder(c, k, conv, kernel);
        let kern = EncoderKernel::new(&enc).unwrap();
        assert_eq!(kern.recomputed_positions(), recomputed);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        // a stream of frames; window t holds frames t-15 .. t+4, so the
        // first 15 windows start with zero slots (a clip's start); frame 30
        // is missing (zeros)
        let frames: Vec<Vec<f32>> = (0..60)
            .map(|f| {
                if f == 30 {
                    vec![0.0; c]
                } else {
                    (0..c).map(|_| rng.random_range(-2.0..2.0)).collect()
                }
            })
            .collect();
        let window_at = |t: usize| -> Vec<f32> {
            let mut w = vec![0f32; k * c];
            for slot in 0..k {
                let idx = t as isize - k as isize + slot as isize + 5;
                if idx >= 0 {
                    w[slot * c..(slot + 1) * c].copy_from_slice(&frames[idx as usize]);
                }
            }
            w
        };
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let mut cache = EncoderCache::default();
        for t in 0..40 {
            let w = window_at(t);
            let fresh = kern.encode(&w);
            let (cached, reuse) = kern.encode_cached(&w, &mut cache);
            let expected = if t == 0 { Reuse::Full } else { Reuse::Shifted };
            assert_eq!(reuse, expected, "window {t}, kernel {kernel}");
            assert_eq!(bits(&fresh), bits(&cached), "window {t}, kernel {kernel}");
            // the same window again comes from the cache unchanged
            let (again, reuse) = kern.encode_cached(&w, &mut cache);
            assert_eq!((bits(&again), reuse), (bits(&fresh), Reuse::Same));
            let theirs = enc
                .encode(&Tensor::from_vec(w.clone(), (1, k, c), &Device::Cpu).unwrap())
                .unwrap()
                .to_vec2::<f32>()
                .unwrap();
            for (a, b) in fresh.iter().zip(&theirs[0]) {
                assert!(
                    (a - b).abs() <= 1e-4 * (1.0 + b.abs()),
                    "window {t}: {a} vs candle {b}"
                );
            }
        }
        // an unrelated window is computed from scratch, not shifted
        let mut other = window_at(10);
        other[0] += 1.0;
        let (emb, reuse) = kern.encode_cached(&other, &mut cache);
        assert_eq!(
            (bits(&emb), reuse),
            (bits(&kern.encode(&other)), Reuse::Full)
        );
    }

    #[test]
    fn four_dot_products_at_once_have_the_bits_of_one_at_a_time() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        for n in [0, 1, 7, 8, 9, 64, 316, 1000] {
            let mut v = || {
                (0..n)
                    .map(|_| rng.random_range(-3.0..3.0))
                    .collect::<Vec<f32>>()
            };
            let x = v();
            let rows = [v(), v(), v(), v()];
            let four = dot4_lanes([&rows[0], &rows[1], &rows[2], &rows[3]], &x);
            for (r, d) in rows.iter().zip(four) {
                let one = dot(r, &x);
                assert_eq!(d.to_bits(), one.to_bits(), "n = {n}");
                // eight scalar running sums in the same order: the same bits
                let mut lanes = [0f32; 8];
                for (i, (a, b)) in r.iter().zip(&x).enumerate() {
                    lanes[i % 8] += a * b;
                }
                assert_eq!(reduce8(lanes).to_bits(), one.to_bits(), "n = {n}");
                let exact: f64 = r.iter().zip(&x).map(|(a, b)| *a as f64 * *b as f64).sum();
                assert!(
                    (one as f64 - exact).abs() <= 1e-4 * (1.0 + exact.abs()),
                    "n = {n}"
                );
            }
        }
    }
}
