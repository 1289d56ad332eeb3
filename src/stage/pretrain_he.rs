//! `skillaug pretrain-he`: pre-train the history encoder by behaviour cloning
//! on the ingested reference clips ([`crate::nn::he_train`]; paper Appendix
//! B.5, Eq. 23) and write `he.safetensors`, `he.config.json`,
//! `he_loss.parquet` and `he_embeddings.parquet`.

use super::Common;
use crate::nn::he_train::{pretrain, HeSettings};
use crate::table::io::Outputs;
use crate::{nn, progress, table};
use anyhow::{Context, Result};
use std::io::IsTerminal;
use std::time::Instant;

/// Run the stage; `device_flag` is `--device`.
pub fn run(common: &Common, device_flag: Option<nn::DeviceName>) -> Result<()> {
    let started = Instant::now();
    let mut set: HeSettings = common.settings("pretrain-he")?;
    if let Some(d) = device_flag {
        set.device = d;
    }
    let _lock = common.lock_output("pretrain-he")?;
    let dev = set.device.open()?;
    let lib = table::load_library(common.input_dir())?;
    let ingest_id = Some(table::ingest_id(&common.input_dir().join("clips.parquet"))?)
        .filter(|id| !id.is_empty());
    let quiet = common.args.quiet;
    let bar = progress::bar(set.steps as u64, "pretrain-he", quiet);
    let plain = !quiet && !std::io::stderr().is_terminal();
    let p = pretrain(
        &lib,
        common.input_dir(),
        &set,
        ingest_id,
        common.args.seed,
        &dev,
        |step, row| {
            bar.set_message(format!("loss {:.4}", row.total));
            bar.inc(1);
            if plain && (step % set.log_every.max(1) == 0 || step + 1 == set.steps) {
                eprintln!(
                    "pretrain-he step {step:>6}/{}: loss {:.5} (prediction {:.5})",
                    set.steps, row.total, row.prediction
                );
            }
        },
    )?;
    bar.finish_and_clear();
    let (cfg, curve, trained) = (&p.cfg, &p.curve, &p.trained);
    let (sep_before, sep_after) = (p.separation_untrained, p.separation_trained);
    let secs = started.elapsed().as_secs_f64();

    // Outputs.
    let resolved = common.resolved_toml("pretrain-he", &set)?;
    let first = curve[0].prediction;
    let tail = &curve[curve.len().saturating_sub(50)..];
    let last = tail.iter().map(|r| r.prediction).sum::<f64>() / tail.len() as f64;
    let meta = table::Meta::new(&lib.clips[0].dataset, &resolved)
        .with("seed", common.args.seed.to_string())
        .with("separation_untrained", format!("{sep_before:.6}"))
        .with("separation_trained", format!("{sep_after:.6}"));
    let emb_rows: Vec<table::he::EmbeddingRow> = trained
        .iter()
        .map(|e| table::he::EmbeddingRow {
            clip_id: e.clip as u32,
            frame: e.frame as u32,
            skill: lib.clips[e.clip].skill.clone(),
            h: e.h,
        })
        .collect();
    let mut out = Outputs::new(&common.args.out)?;
    out.with_path("he.safetensors", |path| {
        candle_core::safetensors::save(&p.named, path).context("writing he.safetensors")
    })?;
    out.text("he.config.json", &serde_json::to_string_pretty(cfg)?)?;
    out.parquet(
        "he_loss.parquet",
        &table::he::loss_batch(curve)?,
        &meta.table("he_loss"),
    )?;
    out.parquet(
        "he_embeddings.parquet",
        &table::he::embedding_batch(&emb_rows)?,
        &meta.table("he_embeddings"),
    )?;
    out.text("pretrain-he.resolved.toml", &resolved)?;
    out.commit()?;

    if !quiet {
        println!(
            "pretrain-he: {} steps x {} windows of {} frames x {} channels on {} in {secs:.1} s",
            set.steps, set.batch_size, cfg.history, cfg.channels, set.device
        );
        println!(
            "prediction loss {first:.4} -> {last:.4} (mean of the last {} steps; {:.1}x lower)",
            tail.len(),
            first / last.max(1e-30)
        );
        println!("skill separation (between / within variance of h): untrained {sep_before:.3}, trained {sep_after:.3}");
    }
    Ok(())
}
