//! Networks in candle: the layers, the history encoder and its
//! pre-training (`rl/` holds the PPO core; the evaluator and the ONNX export
//! load what these build). Layers are built with seeded, PyTorch-style initial weights
//! (uniform in +-1/sqrt(fan_in), biases too, unless [`MlpInit`] says
//! otherwise), because candle's own
//! initialisers draw from an unseeded generator and start far larger
//! (measured: saturated outputs), and runs must repeat for a seed.

pub mod dense;
pub mod he;
pub mod he_kernel;
pub mod he_train;

use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor, Var};
use candle_nn::{Conv1d, Conv1dConfig, Linear, Module};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeMap;

/// A compute device as the command line (`--device`) and the recipes
/// name it: `cpu`, or `cuda` / `cuda:N` (with the `cuda` feature).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DeviceName {
    /// The CPU.
    #[default]
    Cpu,
    /// A CUDA device: `cuda` (device 0) or `cuda:N`.
    Cuda(Option<usize>),
}

impl std::str::FromStr for DeviceName {
    type Err = anyhow::Error;

    fn from_str(name: &str) -> Result<DeviceName> {
        match name {
            "cpu" => Ok(DeviceName::Cpu),
            "cuda" => Ok(DeviceName::Cuda(None)),
            n => match n.strip_prefix("cuda:").map(str::parse) {
                Some(Ok(ordinal)) => Ok(DeviceName::Cuda(Some(ordinal))),
                _ => bail!("unknown device `{n}` (cpu, cuda, cuda:N)"),
            },
        }
    }
}

impl std::fmt::Display for DeviceName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DeviceName::Cpu => f.pad("cpu"),
            DeviceName::Cuda(None) => f.pad("cuda"),
            DeviceName::Cuda(Some(n)) => f.pad(&format!("cuda:{n}")),
        }
    }
}

/// In recipes and resolved settings a device is its name (`"cuda:1"`).
impl serde::Serialize for DeviceName {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> serde::Deserialize<'de> for DeviceName {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<DeviceName, D::Error> {
        let name = String::deserialize(d)?;
        name.parse().map_err(serde::de::Error::custom)
    }
}

impl DeviceName {
    /// The device; a CUDA one only in a build with the `cuda` feature.
    pub fn open(self) -> Result<Device> {
        match self {
            DeviceName::Cpu => Ok(Device::Cpu),
            DeviceName::Cuda(ordinal) => {
                if !cfg!(feature = "cuda") {
                    bail!(
                        "--device {self}: this build has no CUDA support (rebuild with --features cuda)"
                    );
                }
                Device::new_cuda(ordinal.unwrap_or(0))
                    // the driver's error, without the backtrace candle attaches
                    // under RUST_BACKTRACE (the message is the user's answer)
                    .map_err(|e| match e {
                        candle_core::Error::WithBacktrace { inner, .. } => *inner,
                        e => e,
                    })
                    .with_context(|| {
                        format!(
                            "--device {self}: no CUDA device could be opened \
                             (is the NVIDIA driver installed and a GPU visible?)"
                        )
                    })
            }
        }
    }
}

/// Named trainable variables, in a stable (sorted) order.
#[derive(Default)]
pub struct Params {
    vars: BTreeMap<String, Var>,
}

impl Params {
    /// A new variable `name` of `shape`, uniform in +-bound, drawn from `rng`.
    fn uniform(
        &mut self,
        name: String,
        shape: &[usize],
        bound: f64,
        rng: &mut ChaCha8Rng,
        dev: &Device,
    ) -> Result<Tensor> {
        let n: usize = shape.iter().product();
        // a zero bound gives zeros and draws nothing
        let data: Vec<f32> = if bound > 0.0 {
            (0..n)
                .map(|_| rng.random_range(-bound..bound) as f32)
                .collect()
        } else {
            vec![0.0; n]
        };
        let var = Var::from_tensor(&Tensor::from_vec(data, shape, dev)?)?;
        let t = var.as_tensor().clone();
        self.vars.insert(name, var);
        Ok(t)
    }

    /// A linear layer `prefix.weight` `[out, in]`, `prefix.bias` `[out]`.
    pub fn linear(
        &mut self,
        prefix: &str,
        inp: usize,
        out: usize,
        rng: &mut ChaCha8Rng,
        dev: &Device,
    ) -> Result<Linear> {
        let b = 1.0 / (inp as f64).sqrt();
        self.linear_init(prefix, inp, out, [b, b], rng, dev)
    }

    /// A linear layer with weights in `U(-bounds[0], bounds[0])` and biases
    /// in `U(-bounds[1], bounds[1])` (a zero bound: zeros, nothing drawn).
    pub fn linear_init(
        &mut self,
        prefix: &str,
        inp: usize,
        out: usize,
        bounds: [f64; 2],
        rng: &mut ChaCha8Rng,
        dev: &Device,
    ) -> Result<Linear> {
        let w = self.uniform(format!("{prefix}.weight"), &[out, inp], bounds[0], rng, dev)?;
        let bias = self.uniform(format!("{prefix}.bias"), &[out], bounds[1], rng, dev)?;
        Ok(Linear::new(w, Some(bias)))
    }

    /// A 1-D convolution `[out, in, kernel]` with zero padding `pad`.
    // The layer's sizes, the generator and the device are all needed here;
    // a parameter struct would only rename them.
    #[allow(clippy::too_many_arguments)]
    pub fn conv1d(
        &mut self,
        prefix: &str,
        inp: usize,
        out: usize,
        kernel: usize,
        pad: usize,
        rng: &mut ChaCha8Rng,
        dev: &Device,
    ) -> Result<Conv1d> {
        let b = 1.0 / ((inp * kernel) as f64).sqrt();
        let w = self.uniform(format!("{prefix}.weight"), &[out, inp, kernel], b, rng, dev)?;
        let bias = self.uniform(format!("{prefix}.bias"), &[out], b, rng, dev)?;
        let cfg = Conv1dConfig {
            padding: pad,
            ..Default::default()
        };
        Ok(Conv1d::new(w, Some(bias), cfg))
    }

    /// Every variable with its name, in name order.
    pub fn named(&self) -> Vec<(String, Var)> {
        self.vars
            .iter()
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect()
    }

    /// Every variable, in name order (for the optimiser).
    pub fn all(&self) -> Vec<Var> {
        self.vars.values().cloned().collect()
    }

    /// Variables whose names start with `prefix`, as named tensors.
    pub fn tensors(&self, prefix: &str) -> Vec<(String, Tensor)> {
        self.vars
            .iter()
            .filter(|(k, _)| k.starts_with(prefix))
            .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
            .collect()
    }

    /// Overwrite every variable with the tensor of the same name.
    pub fn load(&self, named: &std::collections::HashMap<String, Tensor>) -> Result<()> {
        for (k, v) in &self.vars {
            match named.get(k) {
                Some(t) if t.dims() == v.dims() => v.set(t)?,
                Some(t) => bail!(
                    "weights `{k}`: shape {:?}, expected {:?}",
                    t.dims(),
                    v.dims()
                ),
                None => bail!("weights `{k}` missing"),
            }
        }
        Ok(())
    }
}

/// A ReLU MLP: linear layers with ReLU between them, none after the last.
pub struct Mlp {
    layers: Vec<Linear>,
}

impl Mlp {
    /// Layers `prefix.0`, `prefix.1`, ... of sizes `inp -> hidden... -> out`.
    pub fn new(
        p: &mut Params,
        prefix: &str,
        inp: usize,
        hidden: &[usize],
        out: usize,
        rng: &mut ChaCha8Rng,
        dev: &Device,
    ) -> Result<Mlp> {
        let mut sizes = vec![inp];
        sizes.extend_from_slice(hidden);
        sizes.push(out);
        Mlp::with_init(p, prefix, &sizes, MlpInit::default(), rng, dev)
    }

    /// An MLP over layer `sizes` (input, hidden..., output) started as
    /// `init` says.
    pub fn with_init(
        p: &mut Params,
        prefix: &str,
        sizes: &[usize],
        init: MlpInit,
        rng: &mut ChaCha8Rng,
        dev: &Device,
    ) -> Result<Mlp> {
        let n = sizes.len() - 1;
        let layers = sizes
            .windows(2)
            .enumerate()
            .map(|(i, w)| {
                let default = 1.0 / (w[0] as f64).sqrt();
                let weight = match init.out_bound {
                    Some(b) if i + 1 == n => b,
                    _ => default,
                };
                let bias = if init.zero_bias { 0.0 } else { default };
                p.linear_init(
                    &format!("{prefix}.{i}"),
                    w[0],
                    w[1],
                    [weight, bias],
                    rng,
                    dev,
                )
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Mlp { layers })
    }
}

/// How an [`Mlp`] starts. The default is PyTorch's: weights and biases in
/// `U(+-1/sqrt(fan_in))`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MlpInit {
    /// Output-layer weights in `U(-b, b)` instead of the default.
    pub out_bound: Option<f64>,
    /// All biases 0.
    pub zero_bias: bool,
}

impl Mlp {
    /// The same outputs as [`Module::forward`], bit for bit, for an input
    /// `x` (`[B, in]`) that needs no gradient (observations): the first
    /// layer's product goes through `ConstInputMatmul`, whose backward
    /// pass gives the weight's gradient only. candle's matmul backward
    /// always computes the gradient of both operands (candle-core
    /// `src/backprop.rs`, `Op::Matmul`), and for the first layer the input's
    /// (`[B, in]` from `[B, out] x [out, in]`) is a quarter of the PPO
    /// update's arithmetic with a 902-value observation, thrown away.
    /// Falls back to [`Module::forward`] off the CPU.
    pub fn forward_const_input(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let Some(first) = self.layers.first() else {
            return Ok(x.clone());
        };
        if !x.device().is_cpu() || x.rank() != 2 {
            return self.forward(x);
        }
        let mut h =
            first
                .weight()
                .apply_op1_arc(std::sync::Arc::new(Box::new(ConstInputMatmul {
                    x: x.clone(),
                })))?;
        if let Some(b) = first.bias() {
            h = h.broadcast_add(b)?;
        }
        for l in &self.layers[1..] {
            h = h.relu()?;
            h = l.forward(&h)?;
        }
        Ok(h)
    }
}

/// `x · Wᵀ` as an operation of the weight `W` (`[out, in]`) alone, with
/// `x` (`[B, in]`) a constant: the forward pass is candle's own
/// `x.matmul(W.t())` (the same bits as `candle_nn::Linear`), the backward
/// pass `(xᵀ · g)ᵀ`, the gradient candle's matmul and transpose give `W`,
/// without the gradient of `x` nobody reads (see [`Mlp::forward_const_input`]).
struct ConstInputMatmul {
    x: Tensor,
}

impl candle_core::CustomOp1 for ConstInputMatmul {
    fn name(&self) -> &'static str {
        "const-input-matmul"
    }

    fn cpu_fwd(
        &self,
        storage: &candle_core::CpuStorage,
        layout: &candle_core::Layout,
    ) -> candle_core::Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let data = storage.as_slice::<f32>()?;
        let w = match layout.contiguous_offsets() {
            Some((a, b)) => Tensor::from_slice(&data[a..b], layout.shape(), &Device::Cpu)?,
            None => candle_core::bail!("const-input-matmul: the weight is not contiguous"),
        };
        let y = self.x.matmul(&w.t()?)?.contiguous()?;
        let shape = y.shape().clone();
        let (st, l) = y.storage_and_layout();
        let out = match &*st {
            candle_core::Storage::Cpu(c) => match l.contiguous_offsets() {
                Some((0, n)) if n == c.as_slice::<f32>()?.len() => c.clone(),
                Some((a, b)) => candle_core::CpuStorage::F32(c.as_slice::<f32>()?[a..b].to_vec()),
                None => candle_core::bail!("const-input-matmul: a strided product"),
            },
            _ => candle_core::bail!("const-input-matmul: the product left the CPU"),
        };
        Ok((out, shape))
    }

    fn bwd(
        &self,
        _w: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<Option<Tensor>> {
        Ok(Some(self.x.t()?.matmul(grad)?.t()?))
    }
}

impl Module for Mlp {
    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let mut h = x.clone();
        for (i, l) in self.layers.iter().enumerate() {
            h = l.forward(&h)?;
            if i + 1 < self.layers.len() {
                h = h.relu()?;
            }
        }
        Ok(h)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// The PPO update relies on `forward_const_input` giving the same bits
    /// as `forward`, for the outputs and for every weight's gradient.
    #[test]
    fn forward_const_input_matches_forward_bit_for_bit() {
        let dev = Device::Cpu;
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut p = Params::default();
        let mlp = Mlp::new(&mut p, "pi", 37, &[19, 11], 5, &mut rng, &dev).unwrap();
        let x: Vec<f32> = (0..23 * 37).map(|_| rng.random_range(-2.0..2.0)).collect();
        let x = Tensor::from_vec(x, (23, 37), &dev).unwrap();
        let (a, b) = (
            mlp.forward(&x).unwrap(),
            mlp.forward_const_input(&x).unwrap(),
        );
        let bits = |t: &Tensor| -> Vec<u32> {
            t.flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
                .iter()
                .map(|v| v.to_bits())
                .collect()
        };
        assert_eq!(bits(&a), bits(&b));
        let (ga, gb) = (
            a.sqr().unwrap().sum_all().unwrap().backward().unwrap(),
            b.sqr().unwrap().sum_all().unwrap().backward().unwrap(),
        );
        let vars = p.named();
        assert_eq!(vars.len(), 6);
        for (name, v) in &vars {
            let (x, y) = (ga.get(v.as_tensor()), gb.get(v.as_tensor()));
            assert_eq!(
                bits(x.unwrap()),
                bits(y.unwrap()),
                "gradient of {name} differs"
            );
        }
        // candle's matmul computes the input's gradient; this one does not
        assert!(ga.get(&x).is_some());
        assert!(gb.get(&x).is_none());
    }

    #[test]
    fn device_names_parse_and_print_back() {
        for n in ["cpu", "cuda", "cuda:3"] {
            assert_eq!(n.parse::<DeviceName>().unwrap().to_string(), n);
        }
        for n in ["gpu", "cuda:", "cuda:x", "CPU"] {
            let e = n.parse::<DeviceName>().unwrap_err().to_string();
            assert_eq!(e, format!("unknown device `{n}` (cpu, cuda, cuda:N)"));
        }
        assert!(DeviceName::Cpu.open().unwrap().is_cpu());
        if !cfg!(feature = "cuda") {
            let e = DeviceName::Cuda(Some(1)).open().unwrap_err().to_string();
            assert!(
                e.contains("--device cuda:1: this build has no CUDA support"),
                "{e}"
            );
        }
        // in recipes: the name, checked when the recipe is read
        #[derive(serde::Deserialize, serde::Serialize)]
        struct Holder {
            device: DeviceName,
        }
        let h: Holder = toml::from_str("device = \"cuda:2\"").unwrap();
        assert_eq!(h.device, DeviceName::Cuda(Some(2)));
        assert_eq!(toml::to_string(&h).unwrap().trim(), "device = \"cuda:2\"");
        let e = toml::from_str::<Holder>("device = \"tpu\"").err().unwrap();
        assert!(e.to_string().contains("unknown device `tpu`"), "{e}");
    }
}
