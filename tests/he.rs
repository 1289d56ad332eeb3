//! `skillaug pretrain-he` on the real BallPlay clips, with small networks.

mod common;

use arrow::array::AsArray;
use arrow::datatypes::Float64Type;
use common::*;
use skillaug::table::io::read_parquet;
use std::path::Path;

const SMALL: [&str; 8] = [
    "--set",
    "pretrain-he.conv=[16, 16, 8]",
    "--set",
    "pretrain-he.predictor_hidden=[64]",
    "--set",
    "pretrain-he.batch_size=32",
    "--set",
    "pretrain-he.log_every=1000",
];

fn pretrain(out: &Path, steps: usize, seed: &str) -> String {
    let mut args = vec![
        "pretrain-he".to_string(),
        "--out".into(),
        out.to_str().unwrap().into(),
        "--seed".into(),
        seed.into(),
        "--threads".into(),
        "2".into(),
        "--set".into(),
        format!("pretrain-he.steps={steps}"),
    ];
    args.extend(SMALL.iter().map(|s| s.to_string()));
    let a: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
    ok(&a)
}

#[test]
fn pretraining_learns_and_writes_every_output() {
    let (_dir, out) = ingested("ballplay");
    let stdout = pretrain(&out, 200, "1");
    assert!(stdout.contains("prediction loss"), "{stdout}");
    for f in [
        "he.safetensors",
        "he.config.json",
        "he_loss.parquet",
        "he_embeddings.parquet",
        "pretrain-he.resolved.toml",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("he.config.json")).unwrap())
            .unwrap();
    assert_eq!(cfg["channels"], 316);
    assert_eq!(cfg["mean"].as_array().unwrap().len(), 316);
    let loss = read_parquet(&out.join("he_loss.parquet")).unwrap();
    assert_eq!(loss.rows(), 200);
    let pred: Vec<f64> = loss.batches[0]
        .column_by_name("prediction")
        .unwrap()
        .as_primitive::<Float64Type>()
        .values()
        .to_vec();
    let first = pred[0];
    let last = pred[180..].iter().sum::<f64>() / 20.0;
    assert!(
        last < first / 3.0,
        "prediction loss {first} -> {last}: did not learn"
    );
    let emb = read_parquet(&out.join("he_embeddings.parquet")).unwrap();
    assert_eq!(emb.rows(), 796);
}

#[test]
fn same_seed_same_bytes_and_the_frozen_encoder_repeats() {
    let (dir, out) = ingested("ballplay");
    pretrain(&out, 5, "7");
    let w1 = std::fs::read(out.join("he.safetensors")).unwrap();
    let e1 = std::fs::read(out.join("he_embeddings.parquet")).unwrap();
    pretrain(&out, 5, "7");
    assert!(
        w1 == std::fs::read(out.join("he.safetensors")).unwrap(),
        "weights differ for one seed"
    );
    assert!(e1 == std::fs::read(out.join("he_embeddings.parquet")).unwrap());
    pretrain(&out, 5, "8");
    assert!(
        w1 != std::fs::read(out.join("he.safetensors")).unwrap(),
        "the seed has no effect"
    );

    // Load the frozen encoder and run it twice on the same windows.
    let dev = candle_core::Device::Cpu;
    let enc = skillaug::nn::he::load(&out, &dev).unwrap();
    let lib = skillaug::table::load_library(&out).unwrap();
    let feats = skillaug::nn::he::clip_features(&lib, &enc.cfg);
    let (k, c) = (enc.cfg.history, enc.cfg.channels);
    let mut w = Vec::new();
    for t in [0usize, 30, 70, 100] {
        w.extend(skillaug::nn::he::window(&feats[0], t, k, c));
    }
    let x = candle_core::Tensor::from_vec(w, (4, k, c), &dev).unwrap();
    let a = enc.encode(&x).unwrap().to_vec2::<f32>().unwrap();
    let b = enc.encode(&x).unwrap().to_vec2::<f32>().unwrap();
    assert_eq!(a, b);

    let err = fails(&[
        "pretrain-he",
        "--out",
        dir.path().join("none").to_str().unwrap(),
    ]);
    assert!(err.contains("clips.parquet"), "{err}");
    assert!(skillaug::nn::he::load(&dir.path().join("none"), &dev).is_err());
}
