//! A trained policy as an ONNX model (`skillaug export --policy TRAIN_DIR
//! --onnx FILE`): the deterministic action of [`Agent::act`] (the policy
//! mean μ, what `skillaug eval` runs) for a batch of raw observations, with
//! the observation normaliser inside the graph, so that a consumer feeds the
//! observation of [`crate::rl::humanoid::write_observation`] as it is.
//!
//! Graph (opset 17, IR version 8), input `obs` float32 `[N, obs_dim]`,
//! output `action` float32 `[N, act_dim]`, `N` dynamic:
//!
//! ```text
//! obs -Cast(double)-> Sub(norm.mean) -> Mul(norm.inv_std) -> Clip(-5, 5) -Cast(float)->
//!     Gemm(pi.0.weight, pi.0.bias, transB=1) -> Relu -> ... -> Gemm(pi.L.weight, pi.L.bias, transB=1) -> action
//! ```
//!
//! The normaliser ([`RunningNorm::normalize`]: `(x - mean) / sqrt(var +
//! 1e-5)` clamped to ±5, [`NORM_EPS`], [`NORM_CLIP`]) is computed in
//! float64 with the checkpoint's float64 statistics and `1 / sqrt(var +
//! eps)` computed here exactly as the Rust code computes it, then rounded
//! to float32, as skillaug does; so the MLP sees bit-identical inputs and
//! the only differences left are the float32 matrix products' summation
//! order. It is not folded into the first Gemm: the clamp sits between.
//! Without `normalize_obs` the five normaliser nodes are left out. The
//! layers are the checkpoint's `pi.K.weight` `[out, in]` and `pi.K.bias`
//! `[out]` (candle `Linear`: `y = x W^T + b`), ReLU between them and none
//! after the last ([`crate::nn::Mlp`]). No clamp follows: [`Agent::act`]
//! returns μ unclamped; the simulator clamps each component to [-1, 1] and
//! multiplies it by π to get the PD target exp-map ([`World::apply_action`]),
//! which the model's metadata (`action_doc`) describes.
//!
//! Metadata (`metadata_props`) records what a consumer needs: the
//! observation layout as a JSON list of `[name, start, length]`
//! ([`observation_layout`]), the action layout ([`action_layout`]), obs_dim,
//! act_dim, skeleton, dataset, skills, clips and their condition classes,
//! the body names, the skillaug version, the normaliser, and for a policy
//! trained with the history encoder (`--he`) that the last `he_dim`
//! observation entries are its embedding, which the model takes as input
//! and does not compute; for a policy trained on a stiffer character
//! (`train.pd_stiffness_scale` other than 1) that factor on kp, and for
//! one trained with other ball physics (`train.object_density`,
//! `train.ball_inertia`, `train.object_angular_damping`) or contacts
//! (`train.contact_recycling` off) those settings.
//!
//! Encoding: the ONNX messages ([`proto`]) are declared here by hand with
//! `prost` derive macros and the field numbers of `onnx/onnx.proto` of the
//! ONNX specification (github.com/onnx/onnx). The maintained protobuf
//! runtime is `prost`; the crates that ship ONNX types either generate them
//! at build time with `prost-build`, which needs a `protoc` binary that CI
//! does not have (`candle-onnx`, `onnx-pb`; the latter last released in
//! 2020 on prost 0.6), or bring a second protobuf runtime (`onnx-protobuf`,
//! rust-protobuf 3, MPL-2.0, one maintainer). Ten small messages, only the
//! fields written, are lighter than either.

use crate::motion::{library::CONDITION_SLOTS, Skeleton};
use crate::rl::config::PolicyMeta;
use crate::rl::humanoid::{fingertips, obs_dim};
use crate::rl::norm::{NORM_CLIP, NORM_EPS};
use crate::rl::Agent;
#[cfg(doc)]
use crate::rl::RunningNorm;
#[cfg(doc)]
use crate::sim::World;
use anyhow::{bail, ensure, Context, Result};
use prost::Message;
use std::path::Path;

/// ONNX messages, declared by hand for [`prost`] with the field numbers of
/// the ONNX specification's `onnx/onnx.proto` (github.com/onnx/onnx; the
/// numbers are stable across its releases). Only the fields this exporter
/// writes are declared; a reader skips none of them. `proto2` `optional`
/// scalars are `Option`s, so a set zero is still written; repeated
/// integers are unpacked, as `proto2` declares them. The `oneof`s of
/// `TypeProto` and `TensorShapeProto.Dimension` are written as their
/// members (one set at a time), which is the same wire format.
pub mod proto {
    /// `ModelProto`: the file's top-level message.
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct ModelProto {
        /// IR version of the format (8: ONNX 1.10–1.12, opset ≤ 17).
        #[prost(int64, optional, tag = "1")]
        pub ir_version: Option<i64>,
        /// Tool that wrote the model.
        #[prost(string, optional, tag = "2")]
        pub producer_name: Option<String>,
        /// Its version.
        #[prost(string, optional, tag = "3")]
        pub producer_version: Option<String>,
        /// Reverse-domain namespace of the model.
        #[prost(string, optional, tag = "4")]
        pub domain: Option<String>,
        /// Version of the model.
        #[prost(int64, optional, tag = "5")]
        pub model_version: Option<i64>,
        /// Human-readable description.
        #[prost(string, optional, tag = "6")]
        pub doc_string: Option<String>,
        /// The graph.
        #[prost(message, optional, tag = "7")]
        pub graph: Option<GraphProto>,
        /// Operator sets the graph uses.
        #[prost(message, repeated, tag = "8")]
        pub opset_import: Vec<OperatorSetIdProto>,
        /// Named metadata (distinct keys).
        #[prost(message, repeated, tag = "14")]
        pub metadata_props: Vec<StringStringEntryProto>,
    }

    /// `OperatorSetIdProto`: an operator set and its version.
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct OperatorSetIdProto {
        /// Domain ("" = the default ONNX operators).
        #[prost(string, optional, tag = "1")]
        pub domain: Option<String>,
        /// Opset version.
        #[prost(int64, optional, tag = "2")]
        pub version: Option<i64>,
    }

    /// `StringStringEntryProto`: one key-value pair.
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct StringStringEntryProto {
        /// Key.
        #[prost(string, optional, tag = "1")]
        pub key: Option<String>,
        /// Value.
        #[prost(string, optional, tag = "2")]
        pub value: Option<String>,
    }

    /// `GraphProto`: nodes in topological order, constants, inputs, outputs.
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct GraphProto {
        /// Nodes, sorted topologically.
        #[prost(message, repeated, tag = "1")]
        pub node: Vec<NodeProto>,
        /// Graph name.
        #[prost(string, optional, tag = "2")]
        pub name: Option<String>,
        /// Named constant tensors.
        #[prost(message, repeated, tag = "5")]
        pub initializer: Vec<TensorProto>,
        /// Human-readable description.
        #[prost(string, optional, tag = "10")]
        pub doc_string: Option<String>,
        /// Graph inputs.
        #[prost(message, repeated, tag = "11")]
        pub input: Vec<ValueInfoProto>,
        /// Graph outputs.
        #[prost(message, repeated, tag = "12")]
        pub output: Vec<ValueInfoProto>,
    }

    /// `NodeProto`: one operator call.
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct NodeProto {
        /// Input value names.
        #[prost(string, repeated, tag = "1")]
        pub input: Vec<String>,
        /// Output value names.
        #[prost(string, repeated, tag = "2")]
        pub output: Vec<String>,
        /// Node name.
        #[prost(string, optional, tag = "3")]
        pub name: Option<String>,
        /// Operator, e.g. `Gemm`.
        #[prost(string, optional, tag = "4")]
        pub op_type: Option<String>,
        /// Attributes.
        #[prost(message, repeated, tag = "5")]
        pub attribute: Vec<AttributeProto>,
        /// Human-readable description.
        #[prost(string, optional, tag = "6")]
        pub doc_string: Option<String>,
        /// Operator set domain ("" = default).
        #[prost(string, optional, tag = "7")]
        pub domain: Option<String>,
    }

    /// `AttributeProto.AttributeType` values used here.
    pub mod attribute_type {
        /// A single float (`f`).
        pub const FLOAT: i32 = 1;
        /// A single integer (`i`).
        pub const INT: i32 = 2;
    }

    /// `AttributeProto`: a named attribute of a node.
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct AttributeProto {
        /// Name.
        #[prost(string, optional, tag = "1")]
        pub name: Option<String>,
        /// Float value.
        #[prost(float, optional, tag = "2")]
        pub f: Option<f32>,
        /// Integer value.
        #[prost(int64, optional, tag = "3")]
        pub i: Option<i64>,
        /// Which value field is set ([`attribute_type`]).
        #[prost(int32, optional, tag = "20")]
        pub r#type: Option<i32>,
    }

    /// `TensorProto.DataType` values used here.
    pub mod data_type {
        /// float32.
        pub const FLOAT: i32 = 1;
        /// float64.
        pub const DOUBLE: i32 = 11;
    }

    /// `TensorProto`: a constant tensor (row-major, little-endian raw data).
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct TensorProto {
        /// Shape.
        #[prost(int64, repeated, packed = "false", tag = "1")]
        pub dims: Vec<i64>,
        /// Element type ([`data_type`]).
        #[prost(int32, optional, tag = "2")]
        pub data_type: Option<i32>,
        /// Name (the value it defines).
        #[prost(string, optional, tag = "8")]
        pub name: Option<String>,
        /// Elements, fixed-width little-endian.
        #[prost(bytes = "vec", optional, tag = "9")]
        pub raw_data: Option<Vec<u8>>,
        /// Human-readable description.
        #[prost(string, optional, tag = "12")]
        pub doc_string: Option<String>,
    }

    /// `ValueInfoProto`: name and type of a graph input or output.
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct ValueInfoProto {
        /// Value name.
        #[prost(string, optional, tag = "1")]
        pub name: Option<String>,
        /// Type.
        #[prost(message, optional, tag = "2")]
        pub r#type: Option<TypeProto>,
        /// Human-readable description.
        #[prost(string, optional, tag = "3")]
        pub doc_string: Option<String>,
    }

    /// `TypeProto` with its `tensor_type` member (field 1 of the `value`
    /// oneof).
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct TypeProto {
        /// A tensor type.
        #[prost(message, optional, tag = "1")]
        pub tensor_type: Option<TypeProtoTensor>,
    }

    /// `TypeProto.Tensor`: element type and shape.
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct TypeProtoTensor {
        /// Element type ([`data_type`]).
        #[prost(int32, optional, tag = "1")]
        pub elem_type: Option<i32>,
        /// Shape.
        #[prost(message, optional, tag = "2")]
        pub shape: Option<TensorShapeProto>,
    }

    /// `TensorShapeProto`: a list of dimensions.
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct TensorShapeProto {
        /// Dimensions.
        #[prost(message, repeated, tag = "1")]
        pub dim: Vec<Dimension>,
    }

    /// `TensorShapeProto.Dimension`: a size or a symbolic name (one of the
    /// two, the `value` oneof).
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct Dimension {
        /// A fixed size.
        #[prost(int64, optional, tag = "1")]
        pub dim_value: Option<i64>,
        /// A symbolic (dynamic) size.
        #[prost(string, optional, tag = "2")]
        pub dim_param: Option<String>,
    }
}

use proto::*;

/// ONNX IR version written (8: ONNX 1.10–1.12; supports opset 17).
pub const IR_VERSION: i64 = 8;
/// Version of the default ONNX operator set the graph uses.
pub const OPSET: i64 = 17;
/// Name of the graph input: raw observations, float32 `[N, obs_dim]`.
pub const INPUT: &str = "obs";
/// Name of the graph output: deterministic actions, float32 `[N, act_dim]`.
pub const OUTPUT: &str = "action";

/// One named segment of a flat vector: `len` entries from `start`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Segment {
    /// Segment name (`body_pos`, `object0_rot`, `skill_condition`, ...).
    pub name: String,
    /// First index.
    pub start: usize,
    /// Number of entries.
    pub len: usize,
}

fn segments(parts: &[(String, usize)]) -> Vec<Segment> {
    let mut start = 0;
    parts
        .iter()
        .map(|(name, len)| {
            let s = Segment {
                name: name.clone(),
                start,
                len: *len,
            };
            start += len;
            s
        })
        .collect()
}

/// The segments of the policy observation, in the order
/// [`crate::rl::humanoid::write_observation`] writes them (the reference code's
/// order: Ingrid789/SkillMimic-V2 `skillmimic/env/tasks/humanoid_task.py`,
/// `humanoid_object_task.py`, `skillmimic1.py`, `skillmimic1_hist.py`); their
/// lengths add up to [`obs_dim`]`(sk, n_objects, he_dim)` (902 for BallPlay,
/// one object, no encoder). "Heading frame": world frame turned about the
/// vertical by minus the root's heading.
///
/// - `root_height` (1): root z, m.
/// - `body_pos` (3 per body 1..): body position minus root position, heading frame, m.
/// - `body_rot` (6 per body): tangent (rotated x) and normal (rotated z) of the body rotation in the heading frame.
/// - `body_linvel`, `body_angvel` (3 per body): heading frame, m/s and rad/s.
/// - `fingertip_force` (3 per fingertip, ten): net contact force on each fingertip body ([`fingertips`]), world frame, N (0 right after a reset).
/// - per object `k`: `object{k}_pos` (heading-frame x, y offset from the root and absolute height, m), `object{k}_rot` (6, tan-norm), `object{k}_linvel`, `object{k}_angvel` (heading frame).
/// - `skill_condition` ([`CONDITION_SLOTS`] = 64): one-hot of the skill's class id.
/// - `history_embedding` (`he_dim`, only with the history encoder): the frozen encoder's embedding of the past feature frames.
pub fn observation_layout(sk: Skeleton, n_objects: usize, he_dim: usize) -> Vec<Segment> {
    let b = sk.n_bodies();
    let mut parts: Vec<(String, usize)> = vec![
        ("root_height".into(), 1),
        ("body_pos".into(), 3 * (b - 1)),
        ("body_rot".into(), 6 * b),
        ("body_linvel".into(), 3 * b),
        ("body_angvel".into(), 3 * b),
        ("fingertip_force".into(), 3 * fingertips(sk).len()),
    ];
    for k in 0..n_objects {
        parts.push((format!("object{k}_pos"), 3));
        parts.push((format!("object{k}_rot"), 6));
        parts.push((format!("object{k}_linvel"), 3));
        parts.push((format!("object{k}_angvel"), 3));
    }
    parts.push(("skill_condition".into(), CONDITION_SLOTS));
    if he_dim > 0 {
        parts.push(("history_embedding".into(), he_dim));
    }
    segments(&parts)
}

/// The segments of the action: three entries per joint, named after the
/// body the joint drives (joint `j` drives body `j + 1`), `3 *
/// sk.n_joints()` in all (156 for `mocap_humanoid`).
pub fn action_layout(sk: Skeleton) -> Vec<Segment> {
    let parts: Vec<(String, usize)> = sk.body_names()[1..]
        .iter()
        .map(|n| (n.to_string(), 3))
        .collect();
    segments(&parts)
}

fn layout_json(segs: &[Segment]) -> String {
    let v: Vec<serde_json::Value> = segs
        .iter()
        .map(|s| serde_json::json!([s.name, s.start, s.len]))
        .collect();
    serde_json::Value::Array(v).to_string()
}

/// Read a `skillaug train --out DIR` folder: its `policy.meta.json` and the
/// agent of `policy.safetensors` + `policy.json`, on the CPU. Each missing
/// file is named in the error; sizes that disagree between the two are
/// refused.
pub fn load_policy(dir: &Path) -> Result<(PolicyMeta, Agent)> {
    if !dir.is_dir() {
        bail!(
            "--policy {}: no such folder (give the output folder of `skillaug train`)",
            dir.display()
        );
    }
    let mp = dir.join("policy.meta.json");
    let wp = dir.join("policy.safetensors");
    let sp = Agent::sidecar_path(&wp);
    for p in [&mp, &wp, &sp] {
        if !p.is_file() {
            bail!(
                "{} not found: --policy needs the output folder of a finished `skillaug train` \
                 (policy.safetensors, policy.json and policy.meta.json)",
                p.display()
            );
        }
    }
    let meta: PolicyMeta = serde_json::from_slice(
        &std::fs::read(&mp).with_context(|| format!("cannot read {}", mp.display()))?,
    )
    .with_context(|| format!("{} is not a skillaug policy description", mp.display()))?;
    let agent = Agent::load(&wp, &candle_core::Device::Cpu)
        .with_context(|| format!("cannot load the policy {}", wp.display()))?;
    ensure!(
        agent.obs_dim() == meta.obs_dim && agent.act_dim() == meta.act_dim,
        "{} has a policy of {} observation and {} action values, {} says {} and {}",
        wp.display(),
        agent.obs_dim(),
        agent.act_dim(),
        mp.display(),
        meta.obs_dim,
        meta.act_dim
    );
    Ok((meta, agent))
}

fn dims(v: &[usize]) -> Vec<i64> {
    v.iter().map(|&d| d as i64).collect()
}

fn f32_tensor(name: &str, shape: &[usize], data: &[f32], doc: &str) -> TensorProto {
    TensorProto {
        dims: dims(shape),
        data_type: Some(data_type::FLOAT),
        name: Some(name.into()),
        raw_data: Some(data.iter().flat_map(|x| x.to_le_bytes()).collect()),
        doc_string: Some(doc.into()),
    }
}

fn f64_tensor(name: &str, shape: &[usize], data: &[f64], doc: &str) -> TensorProto {
    TensorProto {
        dims: dims(shape),
        data_type: Some(data_type::DOUBLE),
        name: Some(name.into()),
        raw_data: Some(data.iter().flat_map(|x| x.to_le_bytes()).collect()),
        doc_string: Some(doc.into()),
    }
}

fn node(
    op: &str,
    name: &str,
    inputs: &[&str],
    output: &str,
    attrs: Vec<AttributeProto>,
) -> NodeProto {
    NodeProto {
        input: inputs.iter().map(|s| s.to_string()).collect(),
        output: vec![output.into()],
        name: Some(name.into()),
        op_type: Some(op.into()),
        attribute: attrs,
        doc_string: None,
        domain: Some(String::new()),
    }
}

fn int_attr(name: &str, v: i64) -> AttributeProto {
    AttributeProto {
        name: Some(name.into()),
        f: None,
        i: Some(v),
        r#type: Some(attribute_type::INT),
    }
}

/// A float32 `[N, width]` value with a dynamic first dimension `N`.
fn batch_value(name: &str, width: usize, doc: &str) -> ValueInfoProto {
    ValueInfoProto {
        name: Some(name.into()),
        r#type: Some(TypeProto {
            tensor_type: Some(TypeProtoTensor {
                elem_type: Some(data_type::FLOAT),
                shape: Some(TensorShapeProto {
                    dim: vec![
                        Dimension {
                            dim_value: None,
                            dim_param: Some("N".into()),
                        },
                        Dimension {
                            dim_value: Some(width as i64),
                            dim_param: None,
                        },
                    ],
                }),
            }),
        }),
        doc_string: Some(doc.into()),
    }
}

/// The policy of `agent` (trained as `meta` describes) as an ONNX model:
/// the graph of the module doc and its metadata. Weights are copied as
/// float32, the normaliser statistics as float64.
pub fn policy_model(meta: &PolicyMeta, agent: &Agent) -> Result<ModelProto> {
    let sk = Skeleton::from_name(&meta.skeleton)
        .with_context(|| format!("policy.meta.json: unknown skeleton `{}`", meta.skeleton))?;
    let (od, ad) = (agent.obs_dim(), agent.act_dim());
    ensure!(
        od == meta.obs_dim && ad == meta.act_dim,
        "the agent's sizes ({od}, {ad}) differ from the description's ({}, {})",
        meta.obs_dim,
        meta.act_dim
    );
    ensure!(
        ad == 3 * sk.n_joints(),
        "the policy has {ad} action values; skeleton {} has {} joints of 3",
        sk.name(),
        sk.n_joints()
    );
    ensure!(
        !meta.train.residual_action && !meta.train.reference_obs,
        "the policy was trained with {}: it needs its reference motion at every step, which \
         this export does not carry; export a policy trained without them",
        if meta.train.residual_action {
            "train.residual_action"
        } else {
            "train.reference_obs"
        }
    );
    let n_objects = meta.objects.len();
    let base = obs_dim(sk, n_objects, 0);
    let he_dim = od.checked_sub(base).with_context(|| {
        format!(
            "the policy takes {od} observation values; skeleton {} with {n_objects} object(s) gives {base}",
            sk.name()
        )
    })?;
    match (&meta.he_dir, he_dim) {
        (None, 0) | (Some(_), 1..) => {}
        (None, _) => bail!(
            "the policy takes {od} observation values, {he_dim} more than skeleton {} with \
             {n_objects} object(s) gives, and has no history encoder: cannot describe them",
            sk.name()
        ),
        (Some(_), 0) => bail!(
            "the policy was trained with a history encoder but its observation has no embedding"
        ),
    }
    let obs_layout = observation_layout(sk, n_objects, he_dim);
    debug_assert_eq!(obs_layout.iter().map(|s| s.len).sum::<usize>(), od);

    let cfg = agent.config();
    let weights: std::collections::HashMap<String, Vec<f32>> =
        agent.weights()?.into_iter().collect();
    let mut sizes = vec![od];
    sizes.extend_from_slice(&cfg.hidden);
    sizes.push(ad);

    let mut nodes = Vec::new();
    let mut inits = Vec::new();
    let mut x = INPUT.to_string();
    if cfg.normalize_obs {
        let norm = agent.normalizer();
        ensure!(norm.dim() == od, "normaliser of {} values", norm.dim());
        // exactly RunningNorm::normalize's factor
        let inv: Vec<f64> = norm
            .var
            .iter()
            .map(|v| 1.0 / (v + NORM_EPS).sqrt())
            .collect();
        inits.push(f64_tensor(
            "norm.mean",
            &[od],
            &norm.mean,
            "running mean of the observations (norm.mean of policy.safetensors)",
        ));
        inits.push(f64_tensor(
            "norm.inv_std",
            &[od],
            &inv,
            "1 / sqrt(norm.var + 1e-5) of policy.safetensors",
        ));
        inits.push(f64_tensor(
            "norm.clip_min",
            &[],
            &[-NORM_CLIP],
            "lower clamp",
        ));
        inits.push(f64_tensor(
            "norm.clip_max",
            &[],
            &[NORM_CLIP],
            "upper clamp",
        ));
        let to = |t: i32| vec![int_attr("to", t as i64)];
        nodes.push(node(
            "Cast",
            "obs_to_double",
            &[INPUT],
            "obs_f64",
            to(data_type::DOUBLE),
        ));
        nodes.push(node(
            "Sub",
            "norm_sub",
            &["obs_f64", "norm.mean"],
            "obs_centred",
            vec![],
        ));
        nodes.push(node(
            "Mul",
            "norm_scale",
            &["obs_centred", "norm.inv_std"],
            "obs_scaled",
            vec![],
        ));
        nodes.push(node(
            "Clip",
            "norm_clip",
            &["obs_scaled", "norm.clip_min", "norm.clip_max"],
            "obs_clipped",
            vec![],
        ));
        nodes.push(node(
            "Cast",
            "obs_to_float",
            &["obs_clipped"],
            "obs_norm",
            to(data_type::FLOAT),
        ));
        x = "obs_norm".into();
    }
    let layers = sizes.len() - 1;
    for (k, w) in sizes.windows(2).enumerate() {
        let (inp, out) = (w[0], w[1]);
        let get = |name: &str, len: usize| -> Result<Vec<f32>> {
            let v = weights
                .get(name)
                .with_context(|| format!("the checkpoint has no `{name}`"))?;
            ensure!(
                v.len() == len,
                "`{name}` has {} values, expected {len}",
                v.len()
            );
            Ok(v.clone())
        };
        let (wn, bn) = (format!("pi.{k}.weight"), format!("pi.{k}.bias"));
        inits.push(f32_tensor(
            &wn,
            &[out, inp],
            &get(&wn, out * inp)?,
            "policy layer weight [out, in]",
        ));
        inits.push(f32_tensor(
            &bn,
            &[out],
            &get(&bn, out)?,
            "policy layer bias",
        ));
        let last = k + 1 == layers;
        let y = if last {
            OUTPUT.to_string()
        } else {
            format!("pi.{k}.linear")
        };
        nodes.push(node(
            "Gemm",
            &format!("pi_{k}_gemm"),
            &[&x, &wn, &bn],
            &y,
            vec![int_attr("transB", 1)],
        ));
        x = y;
        if !last {
            let r = format!("pi.{k}.relu");
            nodes.push(node("Relu", &format!("pi_{k}_relu"), &[&x], &r, vec![]));
            x = r;
        }
    }

    let obs_doc = format!(
        "raw observation, float32 [N, {od}]: the vector skillaug's humanoid environment writes \
         (rl::humanoid::write_observation), layout in metadata `observation_layout`{}",
        if he_dim > 0 {
            format!(
                "; entries {}..{od} are the history encoder's embedding, an input of this model",
                od - he_dim
            )
        } else {
            String::new()
        }
    );
    let act_doc = format!(
        "deterministic action (policy mean), float32 [N, {ad}]: PD target of joint j = pi * \
         clamp(action[3j..3j+3], -1, 1) as an exp-map, rad"
    );
    let graph = GraphProto {
        node: nodes,
        name: Some("skillaug_policy".into()),
        initializer: inits,
        doc_string: Some(
            "observation normaliser (float64) then the policy-mean ReLU MLP of skillaug's PPO agent".into(),
        ),
        input: vec![batch_value(INPUT, od, &obs_doc)],
        output: vec![batch_value(OUTPUT, ad, &act_doc)],
    };
    let props = metadata(meta, agent, sk, &obs_layout, he_dim)?;
    Ok(ModelProto {
        ir_version: Some(IR_VERSION),
        producer_name: Some("skillaug".into()),
        producer_version: Some(env!("CARGO_PKG_VERSION").into()),
        domain: Some("skillaug".into()),
        model_version: Some(1),
        doc_string: Some(format!(
            "skillaug policy ({}, dataset {}, skills {}): deterministic action of a raw observation; \
             see metadata_props",
            crate::eval::method_label(&meta.train),
            meta.dataset,
            meta.skills.join(", ")
        )),
        graph: Some(graph),
        opset_import: vec![OperatorSetIdProto {
            domain: Some(String::new()),
            version: Some(OPSET),
        }],
        metadata_props: props
            .into_iter()
            .map(|(k, v)| StringStringEntryProto {
                key: Some(k.into()),
                value: Some(v),
            })
            .collect(),
    })
}

/// The `metadata_props` of [`policy_model`], as (key, value) pairs.
fn metadata(
    meta: &PolicyMeta,
    agent: &Agent,
    sk: Skeleton,
    obs_layout: &[Segment],
    he_dim: usize,
) -> Result<Vec<(&'static str, String)>> {
    let cfg = agent.config();
    let json = |v: serde_json::Value| v.to_string();
    let (od, ad) = (agent.obs_dim(), agent.act_dim());
    // class id of each trained clip: the number of its first three characters
    // (the rule of manifests and plain folders, crate::dataset::class_of)
    let classes: serde_json::Map<String, serde_json::Value> = meta
        .clips
        .iter()
        .filter_map(|c| crate::dataset::class_of(c).map(|k| (c.clone(), k.into())))
        .collect();
    let tips: Vec<&str> = fingertips(sk).iter().map(|&b| sk.body_names()[b]).collect();
    let norm = agent.normalizer();
    let mut v: Vec<(&'static str, String)> =
        vec![
        ("format", "skillaug-policy-onnx 1".into()),
        ("skillaug_version", env!("CARGO_PKG_VERSION").into()),
        ("input", INPUT.into()),
        ("output", OUTPUT.into()),
        ("obs_dim", od.to_string()),
        ("act_dim", ad.to_string()),
        ("skeleton", sk.name().into()),
        ("dataset", meta.dataset.clone()),
        ("skills", json(serde_json::json!(meta.skills))),
        ("clips", json(serde_json::json!(meta.clips))),
        ("clip_classes", serde_json::Value::Object(classes).to_string()),
        ("objects", json(serde_json::json!(meta.objects))),
        ("method", crate::eval::method_label(&meta.train)),
        ("iterations", meta.iterations.to_string()),
        ("samples", meta.samples.to_string()),
        ("hidden", json(serde_json::json!(cfg.hidden))),
        ("activation", "relu".into()),
        ("observation_layout", layout_json(obs_layout)),
        (
            "observation_doc",
            "Segments [name, start, length] of the raw observation, written by \
             skillaug::rl::humanoid::write_observation. Heading frame: the world frame turned \
             about the vertical (z up) by minus the root's heading. root_height: root z, m. \
             body_pos: bodies 1.. (order of `bodies`) minus the root position, heading frame, m. \
             body_rot: per body the tangent (rotated x axis) and normal (rotated z axis) of its \
             rotation in the heading frame. body_linvel, body_angvel: per body, heading frame, \
             m/s and rad/s. fingertip_force: net contact force on each of `fingertip_bodies` \
             during the last policy step, world frame, N (0 right after a reset). objectK_pos: \
             heading-frame x, y offset of object K (order of `objects`) from the root and its \
             absolute height, m; objectK_rot: tangent and normal, heading frame; objectK_linvel, \
             objectK_angvel: heading frame. skill_condition: one-hot of the skill's class id \
             (slot = class id; see `clip_classes`). history_embedding (only when \
             `history_encoder` is not none): the frozen history encoder's embedding of the 60 \
             feature frames before the current one."
                .into(),
        ),
        ("bodies", json(serde_json::json!(sk.body_names()))),
        ("fingertip_bodies", json(serde_json::json!(tips))),
        ("action_layout", layout_json(&action_layout(sk))),
        (
            "action_doc",
            "The deterministic action: the policy mean mu, unclamped, as skillaug's Agent::act \
             returns it with deterministic = true (skillaug eval). Three entries per joint; joint \
             j drives body j + 1 (`action_layout` names it). The simulator sets joint j's PD \
             target to the exp-map (rotation vector, rad) pi * clamp(action[3j..3j+3], -1, 1) \
             (skillaug::sim::World::apply_action), one action per policy step (60 Hz for the \
             60 fps BallPlay and Locomotion clips, 30 Hz for ParaHome)."
                .into(),
        ),
        (
            "normalization",
            if cfg.normalize_obs {
                format!(
                    "inside the model: (obs - mean) / sqrt(var + {NORM_EPS:e}) clamped to \
                     [-{NORM_CLIP}, {NORM_CLIP}], in float64, from running statistics over {} \
                     observations (initializers norm.mean, norm.inv_std); feed raw observations",
                    norm.count
                )
            } else {
                "none (trained without observation normalisation)".into()
            },
        ),
        ("policy_std", format!("{}", cfg.std())),
    ];
    v.push((
        "history_encoder",
        match &meta.he_dir {
            Some(d) => format!(
                "the observation's last {he_dim} entries (history_embedding, {}..{od}) are the \
                 embedding of the frozen history encoder ({d}/he.safetensors); this model takes \
                 them as input and does not compute them",
                od - he_dim
            ),
            None => "none".into(),
        },
    ));
    if meta.train.pd_stiffness_scale != 1.0 {
        // the policy was trained on a stiffer character: a consumer must
        // drive the joints with the same kp to reproduce it
        v.push((
            "pd_stiffness_scale",
            format!(
                "{}: trained and evaluated with every joint's kp (the MJCF joint stiffness) \
                 multiplied by this factor and kd unchanged (train.pd_stiffness_scale)",
                meta.train.pd_stiffness_scale
            ),
        ));
    }
    if let Some(d) = meta.train.object_density {
        // the policy was trained on objects of another mass: a consumer
        // must simulate them with the same density to reproduce it
        v.push((
            "object_density",
            format!(
                "{d}: trained and evaluated with every object's density set to this many \
                 kg/m^3 in place of its own (train.object_density)"
            ),
        ));
    }
    if let Some(d) = meta.train.object_angular_damping {
        // the policy was trained on objects whose spin dies away faster: a
        // consumer must simulate them the same way to reproduce it
        v.push((
            "object_angular_damping",
            format!(
                "{d}: trained and evaluated with every object's angular velocity damping set \
                 to this many 1/s in place of its own (train.object_angular_damping)"
            ),
        ));
    }
    if meta.train.ball_inertia == crate::sim::objects::BallInertia::Shell {
        // the policy was trained on a ball that spins more easily: a
        // consumer must simulate it the same way to reproduce it
        v.push((
            "ball_inertia",
            "shell: trained and evaluated with the ball's rotational inertia that of a thin \
             shell of the same mass, 2/3 m r^2 instead of a solid sphere's 2/5 m r^2 \
             (train.ball_inertia)"
                .to_string(),
        ));
    }
    if !meta.train.contact_recycling {
        // the policy was trained with contacts recomputed at every physics
        // step: a consumer on rapier must turn its recycling off too
        v.push((
            "contact_recycling",
            "false: trained and evaluated with rapier's contact recycling off, every contact \
             pair recomputed at every physics step (train.contact_recycling)"
                .to_string(),
        ));
    }
    Ok(v)
}

/// The ONNX model bytes of the policy in `policy_dir` (a `skillaug train
/// --out` folder): [`load_policy`], [`policy_model`], protobuf-encoded.
pub fn policy_to_onnx(policy_dir: &Path) -> Result<Vec<u8>> {
    let (meta, agent) = load_policy(policy_dir)?;
    Ok(policy_model(&meta, &agent)?.encode_to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::augment::settings::StfConfig;
    use crate::rl::config::TrainConfig;
    use crate::rl::PpoConfig;
    use candle_core::Device;

    fn meta(sk: Skeleton, objects: &[&str], he: bool, od: usize) -> PolicyMeta {
        PolicyMeta {
            format: 1,
            dataset: "ballplay".into(),
            skeleton: sk.name().into(),
            skills: vec!["run".into()],
            clips: vec!["013_018pickle_run2_5".into()],
            objects: objects.iter().map(|s| s.to_string()).collect(),
            obs_dim: od,
            act_dim: 3 * sk.n_joints(),
            he_dir: he.then(|| "he".into()),
            train: TrainConfig::default(),
            stf: StfConfig::default(),
            iterations: 0,
            samples: 0,
            ranks: 1,
            push_feed_forward: Vec::new(),
            reference_flights: Vec::new(),
        }
    }

    fn agent(od: usize, ad: usize, hidden: &[usize], normalize_obs: bool) -> Agent {
        let cfg = PpoConfig {
            hidden: hidden.to_vec(),
            normalize_obs,
            ..PpoConfig::default()
        };
        Agent::new(od, ad, &cfg, 1, &Device::Cpu).unwrap()
    }

    /// The value of metadata entry `key` of `m`, if it has one.
    fn prop(m: &ModelProto, key: &str) -> Option<String> {
        m.metadata_props
            .iter()
            .find(|e| e.key.as_deref() == Some(key))
            .and_then(|e| e.value.clone())
    }

    #[test]
    fn the_layouts_cover_the_observation_and_the_action() {
        for (sk, objects) in [(Skeleton::MocapHumanoid, 1), (Skeleton::ParaHome, 2)] {
            for he in [0, 3] {
                let l = observation_layout(sk, objects, he);
                assert_eq!(
                    l.iter().map(|s| s.len).sum::<usize>(),
                    obs_dim(sk, objects, he)
                );
                for w in l.windows(2) {
                    assert_eq!(w[0].start + w[0].len, w[1].start);
                }
                assert_eq!(l.last().unwrap().name == "history_embedding", he > 0);
            }
            let a = action_layout(sk);
            assert_eq!(a.len(), sk.n_joints());
            assert_eq!(a.last().unwrap().start + 3, 3 * sk.n_joints());
        }
        assert_eq!(obs_dim(Skeleton::MocapHumanoid, 1, 0), 902);
        let l = observation_layout(Skeleton::MocapHumanoid, 1, 0);
        let cond = l.iter().find(|s| s.name == "skill_condition").unwrap();
        assert_eq!((cond.start, cond.len), (902 - 64, 64));
    }

    #[test]
    fn the_model_decodes_with_its_graph_and_metadata() {
        let sk = Skeleton::MocapHumanoid;
        let od = obs_dim(sk, 1, 0);
        for norm in [true, false] {
            let a = agent(od, 3 * sk.n_joints(), &[8, 4], norm);
            let bytes = policy_model(&meta(sk, &["ball"], false, od), &a)
                .unwrap()
                .encode_to_vec();
            let m = ModelProto::decode(bytes.as_slice()).unwrap();
            let g = m.graph.as_ref().unwrap();
            let ops: Vec<&str> = g
                .node
                .iter()
                .map(|n| n.op_type.as_deref().unwrap())
                .collect();
            let mlp = ["Gemm", "Relu", "Gemm", "Relu", "Gemm"];
            if norm {
                assert_eq!(ops[..5], ["Cast", "Sub", "Mul", "Clip", "Cast"]);
                assert_eq!(ops[5..], mlp);
            } else {
                assert_eq!(ops, mlp);
            }
            assert_eq!(g.node.last().unwrap().output, [OUTPUT]);
            assert_eq!(g.input[0].name.as_deref(), Some(INPUT));
            let key = |k: &str| prop(&m, k).unwrap();
            assert_eq!(key("obs_dim"), "902");
            assert_eq!(key("act_dim"), "156");
            assert_eq!(key("history_encoder"), "none");
            assert_eq!(key("clip_classes"), r#"{"013_018pickle_run2_5":13}"#);
            assert_eq!(
                prop(&m, "pd_stiffness_scale"),
                None,
                "the model's gains need no entry"
            );
            let w = g
                .initializer
                .iter()
                .find(|t| t.name.as_deref() == Some("pi.0.weight"))
                .unwrap();
            assert_eq!(w.dims, [8, od as i64]);
            assert_eq!(w.raw_data.as_ref().unwrap().len(), 4 * 8 * od);
        }
    }

    #[test]
    fn a_policy_of_a_stiffer_character_or_another_ball_says_so() {
        let sk = Skeleton::MocapHumanoid;
        let od = obs_dim(sk, 1, 0);
        let a = agent(od, 156, &[4], true);
        let mut stiff = meta(sk, &["ball"], false, od);
        stiff.train.pd_stiffness_scale = 4.0;
        // each setting is absent from the metadata until it is set, then
        // declared with its value first, in one-space sentences
        let declared = |meta: &PolicyMeta, key: &str, value: &str| {
            let v = prop(&policy_model(meta, &a).unwrap(), key).unwrap();
            assert!(v.starts_with(&format!("{value}: ")), "{key}: {v}");
            assert!(!v.contains("  "), "one space between words: {v}");
        };
        declared(&stiff, "pd_stiffness_scale", "4");
        let absent = |meta: &PolicyMeta, key: &str| {
            assert_eq!(prop(&policy_model(meta, &a).unwrap(), key), None, "{key}");
        };
        // a lighter ball is declared too
        absent(&stiff, "object_density");
        stiff.train.object_density = Some(83.0);
        declared(&stiff, "object_density", "83");
        // and a ball with a shell's inertia
        absent(&stiff, "ball_inertia");
        stiff.train.ball_inertia = crate::sim::objects::BallInertia::Shell;
        declared(&stiff, "ball_inertia", "shell");
        // and a ball whose spin dies away
        absent(&stiff, "object_angular_damping");
        stiff.train.object_angular_damping = Some(10.0);
        declared(&stiff, "object_angular_damping", "10");
        // and contacts recomputed at every step
        absent(&stiff, "contact_recycling");
        stiff.train.contact_recycling = false;
        declared(&stiff, "contact_recycling", "false");
    }

    #[test]
    fn an_encoder_policy_declares_its_embedding_and_a_mismatch_is_refused() {
        let sk = Skeleton::MocapHumanoid;
        let od = obs_dim(sk, 1, 3);
        let a = agent(od, 156, &[4], true);
        let m = policy_model(&meta(sk, &["ball"], true, od), &a).unwrap();
        let he = prop(&m, "history_encoder").unwrap();
        assert!(he.contains("last 3 entries"), "{he}");
        // the same observation without an encoder in the description
        let e = policy_model(&meta(sk, &["ball"], false, od), &a).unwrap_err();
        assert!(e.to_string().contains("no history encoder"), "{e}");
        let e = policy_model(&meta(sk, &[], false, od), &a).unwrap_err();
        assert!(e.to_string().contains("cannot describe"), "{e}");
    }
}
