//! `skillaug export --policy TRAIN_DIR --onnx FILE` (docs/export.md): tiny
//! policies trained on the real clips are exported, and ONNX Runtime, run in
//! Python on real observations of skillaug's own environment, gives the
//! actions skillaug's agent chooses deterministically (max |diff| <= 1e-5).
//! The ONNX checker validates the file. Bad policy folders are refused with
//! the missing file named and nothing written.

mod common;

use common::*;
use rand::SeedableRng;
use skillaug::rl::config::PolicyMeta;
use skillaug::rl::humanoid::HeRuntime;
use skillaug::rl::trainer::environment;
use skillaug::rl::{Agent, VecEnv};
use std::path::Path;

/// The agreement asked of ONNX Runtime and skillaug's agent.
const TOLERANCE: f64 = 1e-5;

/// `skillaug train` of a tiny policy ([`TINY_TRAIN`], 256 samples, warm start
/// on, so the policy mean is fitted to the reference and far from 0) from
/// run `from` into `out`, with `extra` flags.
fn tiny_train(from: &Path, out: &Path, extra: &[&str]) {
    let mut a = vec![
        "train",
        "--from",
        from.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "-q",
        "--threads",
        "2",
        "--set",
        "train.samples=256",
    ];
    a.extend_from_slice(TINY_TRAIN);
    a.extend_from_slice(extra);
    ok(&a);
}

/// `skillaug export --policy pol --onnx out`; returns what it printed.
fn export(pol: &Path, out: &Path) -> String {
    ok(&[
        "export",
        "--policy",
        pol.to_str().unwrap(),
        "--onnx",
        out.to_str().unwrap(),
    ])
}

/// Real observations and skillaug's deterministic actions: the policy in
/// `pol` drives `envs` environments built from run `run` as training builds
/// them (with the frozen history encoder when the policy has one) for
/// `steps` policy steps. Returns (observations `rows * obs_dim`, actions
/// `rows * act_dim`, obs_dim, act_dim).
fn record(run: &Path, pol: &Path, envs: usize, steps: usize) -> (Vec<f32>, Vec<f32>, usize, usize) {
    let meta: PolicyMeta =
        serde_json::from_slice(&std::fs::read(pol.join("policy.meta.json")).unwrap()).unwrap();
    let mut cfg = meta.train.clone();
    cfg.skills = meta.skills.clone();
    cfg.stg = false;
    let s = setup_for(run, &cfg);
    let dev = candle_core::Device::Cpu;
    let he = meta.he_dir.as_ref().map(|d| {
        let enc = skillaug::nn::he::load(Path::new(d), &dev).unwrap();
        HeRuntime::new(enc, &s.lib).unwrap()
    });
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut env = environment(&s, &cfg, he, envs, &[], &mut rng).unwrap();
    let agent = Agent::load(&pol.join("policy.safetensors"), &dev).unwrap();
    let (od, ad) = (env.obs_dim(), env.act_dim());
    assert_eq!((od, ad), (agent.obs_dim(), agent.act_dim()));
    let (mut obs, mut act) = (Vec::new(), Vec::new());
    for _ in 0..steps {
        let o = env.observe();
        let a = agent.act(&o, true, &mut rng).unwrap();
        env.step(&a.actions, &mut rng).unwrap();
        obs.extend_from_slice(&o);
        act.extend_from_slice(&a.actions);
    }
    (obs, act, od, ad)
}

/// Checks the model with the ONNX checker, runs it with ONNX Runtime on
/// `obs.f32` (all rows at once, then rows 0..7 as a second batch size) and
/// compares with `act.f32`; prints one JSON object.
const CHECK_PY: &str = r#"
import json, sys
import numpy as np
import onnx
import onnxruntime as ort

model, obs_path, act_path, od, ad = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5])
m = onnx.load(model)
onnx.checker.check_model(m, full_check=True)
obs = np.fromfile(obs_path, dtype="<f4").reshape(-1, od)
act = np.fromfile(act_path, dtype="<f4").reshape(-1, ad)
s = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
(out,) = s.run(["action"], {"obs": obs})
(few,) = s.run(["action"], {"obs": obs[:7]})
print(json.dumps({
    "rows": int(obs.shape[0]),
    "max_diff": float(np.abs(out.astype(np.float64) - act).max()),
    "max_diff_batch7": float(np.abs(few.astype(np.float64) - act[:7]).max()),
    "max_abs_action": float(np.abs(act).max()),
    "input": [s.get_inputs()[0].name, [str(d) for d in s.get_inputs()[0].shape]],
    "output": [s.get_outputs()[0].name, [str(d) for d in s.get_outputs()[0].shape]],
    "ir_version": m.ir_version,
    "opset": [o.version for o in m.opset_import if o.domain in ("", "ai.onnx")],
    "ops": [n.op_type for n in m.graph.node],
    "metadata": {p.key: p.value for p in m.metadata_props},
}))
"#;

fn f32_file(path: &Path, v: &[f32]) {
    let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
    std::fs::write(path, bytes).unwrap();
}

/// Runs [`CHECK_PY`] on `model` with the recorded rows; returns its report.
fn onnxruntime_check(
    model: &Path,
    obs: &[f32],
    act: &[f32],
    od: usize,
    ad: usize,
) -> serde_json::Value {
    let dir = tempfile::tempdir().unwrap();
    let (op, ap, sp) = (
        dir.path().join("obs.f32"),
        dir.path().join("act.f32"),
        dir.path().join("check.py"),
    );
    f32_file(&op, obs);
    f32_file(&ap, act);
    std::fs::write(&sp, CHECK_PY).unwrap();
    let o = std::process::Command::new(python_with(&["onnx", "onnxruntime", "numpy"]))
        .arg(&sp)
        .arg(model)
        .arg(&op)
        .arg(&ap)
        .arg(od.to_string())
        .arg(ad.to_string())
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "ONNX check failed:\n{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).unwrap()
}

/// Export `pol`, record 1,000 observations (8 envs x 125 steps) and check
/// ONNX Runtime against skillaug; returns the report.
fn export_and_compare(run: &Path, pol: &Path, model: &Path) -> serde_json::Value {
    let printed = export(pol, model);
    assert!(
        printed.contains("wrote") && printed.contains(".onnx"),
        "{printed}"
    );
    let (obs, act, od, ad) = record(run, pol, 8, 125);
    assert_eq!(obs.len(), 1000 * od);
    let r = onnxruntime_check(model, &obs, &act, od, ad);
    eprintln!(
        "{}: {} bytes, max |diff| {:e} over {} rows (batch of 7: {:e}), max |action| {}",
        model.display(),
        std::fs::metadata(model).unwrap().len(),
        r["max_diff"].as_f64().unwrap(),
        r["rows"],
        r["max_diff_batch7"].as_f64().unwrap(),
        r["max_abs_action"]
    );
    assert_eq!(r["rows"], 1000);
    assert!(r["max_diff"].as_f64().unwrap() <= TOLERANCE, "{r}");
    assert!(r["max_diff_batch7"].as_f64().unwrap() <= TOLERANCE, "{r}");
    // the warm-started mean is far from 0, so the comparison means something
    assert!(r["max_abs_action"].as_f64().unwrap() > 0.1, "{r}");
    assert_eq!(
        r["input"],
        serde_json::json!(["obs", ["N", od.to_string()]])
    );
    assert_eq!(
        r["output"],
        serde_json::json!(["action", ["N", ad.to_string()]])
    );
    assert_eq!(r["ir_version"], 8);
    assert_eq!(r["opset"], serde_json::json!([17]));
    let md = &r["metadata"];
    assert_eq!(md["obs_dim"], od.to_string());
    assert_eq!(md["act_dim"], ad.to_string());
    assert_eq!(md["skillaug_version"], env!("CARGO_PKG_VERSION"));
    // the layout is a list of [name, start, length] covering the observation
    let layout: Vec<(String, usize, usize)> =
        serde_json::from_str(md["observation_layout"].as_str().unwrap()).unwrap();
    let mut next = 0;
    for (_, start, len) in &layout {
        assert_eq!(*start, next);
        next += len;
    }
    assert_eq!(next, od);
    let actions: Vec<(String, usize, usize)> =
        serde_json::from_str(md["action_layout"].as_str().unwrap()).unwrap();
    assert_eq!(actions.len() * 3, ad);
    r
}

#[test]
fn a_ballplay_policy_runs_in_onnx_runtime_as_in_skillaug() {
    let (dir, run) = ingested("ballplay");
    let pol = dir.path().join("pol");
    tiny_train(&run, &pol, &[]);
    let model = dir.path().join("policy.onnx");
    let r = export_and_compare(&run, &pol, &model);
    let md = &r["metadata"];
    assert_eq!(md["skeleton"], "mocap_humanoid");
    assert_eq!(md["dataset"], "ballplay");
    assert_eq!(md["history_encoder"], "none");
    assert_eq!(md["hidden"], "[16]");
    let skills: Vec<String> = serde_json::from_str(md["skills"].as_str().unwrap()).unwrap();
    assert_eq!(skills, ["layup", "lrun", "rrun", "run", "shot"]);
    assert!(md["observation_layout"]
        .as_str()
        .unwrap()
        .contains(r#"["skill_condition",838,64]"#));
    assert!(md["action_doc"].as_str().unwrap().contains("pi * clamp"));
    assert_eq!(
        r["ops"],
        serde_json::json!(["Cast", "Sub", "Mul", "Clip", "Cast", "Gemm", "Relu", "Gemm"])
    );
}

#[test]
fn a_history_encoder_policy_takes_the_embedding_as_input() {
    let (dir, run) = ingested("ballplay");
    tiny_encoder(run.to_str().unwrap(), 3);
    let pol = dir.path().join("pol-he");
    tiny_train(&run, &pol, &["--he", "--set", "train.skills=[\"run\"]"]);
    let model = dir.path().join("he.onnx");
    let r = export_and_compare(&run, &pol, &model);
    let md = &r["metadata"];
    // 902 + the 3-D embedding (Ingrid789/SkillMimic-V2
    // `skillmimic/env/tasks/skillmimic1_hist.py`)
    assert_eq!(md["obs_dim"], "905");
    let he = md["history_encoder"].as_str().unwrap();
    assert!(
        he.contains("last 3 entries") && he.contains("he.safetensors"),
        "{he}"
    );
    assert!(md["observation_layout"]
        .as_str()
        .unwrap()
        .ends_with(r#"["history_embedding",902,3]]"#));
}

#[test]
fn a_parahome_policy_runs_in_onnx_runtime_as_in_skillaug() {
    let (dir, run) = ingested("parahome");
    let pol = dir.path().join("pol");
    tiny_train(&run, &pol, &["--set", "train.skills=[\"place_book\"]"]);
    let model = dir.path().join("parahome.onnx");
    let r = export_and_compare(&run, &pol, &model);
    let md = &r["metadata"];
    assert_eq!(md["skeleton"], "mocap_parahome_boxhand");
    assert_eq!(md["act_dim"], "180");
}

#[test]
fn a_folder_without_its_files_is_refused_and_nothing_is_written() {
    let (dir, run) = ingested("ballplay");
    let pol = dir.path().join("pol");
    tiny_train(&run, &pol, &["--set", "train.skills=[\"run\"]"]);
    let out_dir = dir.path().join("out");
    std::fs::create_dir(&out_dir).unwrap();
    let out = out_dir.join("p.onnx");
    let refused = |policy: &Path, file: &str| {
        let e = fails(&[
            "export",
            "--policy",
            policy.to_str().unwrap(),
            "--onnx",
            out.to_str().unwrap(),
        ]);
        assert!(e.contains(file), "expected `{file}` in: {e}");
        assert!(!out.exists(), "{} was written", out.display());
        assert!(entries(&out_dir).is_empty(), "{:?}", entries(&out_dir));
    };
    for missing in ["policy.meta.json", "policy.safetensors", "policy.json"] {
        let copy = dir.path().join(format!("without-{missing}"));
        std::fs::create_dir(&copy).unwrap();
        for f in ["policy.meta.json", "policy.safetensors", "policy.json"] {
            if f != missing {
                std::fs::copy(pol.join(f), copy.join(f)).unwrap();
            }
        }
        refused(&copy, missing);
    }
    refused(&dir.path().join("nothing"), "nothing");
    // a description that is not one
    let bad = dir.path().join("bad-meta");
    std::fs::create_dir(&bad).unwrap();
    for f in ["policy.safetensors", "policy.json"] {
        std::fs::copy(pol.join(f), bad.join(f)).unwrap();
    }
    std::fs::write(bad.join("policy.meta.json"), "{\"format\": 1}").unwrap();
    refused(&bad, "policy.meta.json");
    // the whole folder exports
    export(&pol, &out);
    assert_eq!(entries(&out_dir), ["p.onnx"]);
}

/// The figures of docs/export.md: file size, export time and max |diff| for the
/// CPU preset's hidden sizes [256, 256] and the paper's [1024, 512, 512]
/// (tiny training budgets, warm start shortened). Slow: `cargo test
/// --release --test export_onnx -- --ignored --nocapture`.
#[test]
#[ignore]
fn measure_export_of_the_preset_sizes() {
    let (dir, run) = ingested("ballplay");
    for hidden in ["[256, 256]", "[1024, 512, 512]"] {
        let pol = dir.path().join(format!("pol-{}", hidden.len()));
        let h = format!("train.ppo.hidden={hidden}");
        ok(&[
            "train",
            "--from",
            run.to_str().unwrap(),
            "--out",
            pol.to_str().unwrap(),
            "-q",
            "--set",
            "train.num_envs=8",
            "--set",
            "train.horizon=8",
            "--set",
            &h,
            "--set",
            "train.ppo.minibatch=64",
            "--set",
            "train.samples=256",
            "--set",
            "train.warm_start_epochs=5",
            "--set",
            "train.skills=[\"run\"]",
        ]);
        let model = dir.path().join(format!("m-{}.onnx", hidden.len()));
        let t = std::time::Instant::now();
        let r = export_and_compare(&run, &pol, &model);
        eprintln!(
            "hidden {hidden}: {} bytes (policy.safetensors {} bytes), export + comparison {:.2} s, \
             max |diff| {:e}",
            std::fs::metadata(&model).unwrap().len(),
            std::fs::metadata(pol.join("policy.safetensors")).unwrap().len(),
            t.elapsed().as_secs_f64(),
            r["max_diff"].as_f64().unwrap()
        );
        let t = std::time::Instant::now();
        export(&pol, &model);
        eprintln!(
            "hidden {hidden}: `skillaug export` alone {:.2} s",
            t.elapsed().as_secs_f64()
        );
    }
}
