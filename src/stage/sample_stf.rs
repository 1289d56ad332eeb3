//! `skillaug sample-stf`: trajectories sampled from the State Transition Field
//! with Adaptive Trajectory Sampling (paper Sections 4.3-4.5, Algorithm 1,
//! Table 7; reference code: Ingrid789/SkillMimic-V2
//! `skillmimic/env/tasks/skillmimic1_rand.py` and `skillmimic1_reweight.py`),
//! written to `stf_samples.parquet` so that a user can inspect what the trainer
//! will see. The algorithm lives in [`crate::augment::stf`] and
//! [`crate::augment::ats`]; the trainer calls the same code online.
//!
//! Each trajectory gets its own ChaCha8 stream (seed = `--seed`, stream =
//! trajectory id), so the output depends only on the inputs, the settings and
//! the seed, not on the thread count.

use super::Common;
use crate::augment::ats::Ats;
use crate::augment::settings::StfConfig;
use crate::augment::stf::{StfSampler, Trajectory};
use crate::motion::Skeleton;
use crate::reward::{DatasetKind, Weights};
use crate::table;
use crate::table::io::Outputs;
use anyhow::{bail, Context, Result};
use std::path::Path;
use std::time::Instant;

/// Run the stage.
pub fn run(common: &Common) -> Result<()> {
    let started = Instant::now();
    let cfg: StfConfig = common.settings("sample-stf")?;
    let _lock = common.lock_output("sample-stf")?;
    let (params, ats_params) = cfg.params()?;
    let input = common.input_dir();
    let lib = table::load_library(input)?;
    if lib.skeleton == Skeleton::ParaHome && cfg.p_e > 0.0 {
        bail!(
            "sample-stf: {} holds ParaHome clips, which have no Stitched Trajectory Graph \
             (Table 7: p_e = -, one policy per clip); set p_e = 0 (--set sample-stf.p_e=0)",
            input.display()
        );
    }
    if !cfg.skills.is_empty() {
        let all = lib.skills();
        for s in &cfg.skills {
            if !all.contains(s) {
                bail!(
                    "sample-stf.skills: no skill `{s}` in {} (skills: {})",
                    input.display(),
                    all.join(", ")
                );
            }
        }
    }
    let mut ats = Ats::for_clips(&lib, |c| {
        cfg.skills.is_empty() || cfg.skills.contains(&lib.clips[c].skill)
    });
    let edges = if cfg.p_e > 0.0 {
        table::stg::load_edges(input, &lib, cfg.p_e)?
    } else {
        Vec::new()
    };
    let n_rewards = if cfg.rewards.is_empty() {
        0
    } else {
        let path = Path::new(&cfg.rewards);
        let rows = table::stf::read_rewards(path)
            .context("sample-stf.rewards: cannot use the ATS rewards table")?;
        table::stf::check_rewards(path, &rows, &lib)?;
        for r in &rows {
            ats.set_mean(r.clip_id as usize, r.frame as usize, r.mean_reward);
        }
        rows.len()
    };
    let weights = Weights::sm(DatasetKind::of_library(&lib));
    let mut sampler = StfSampler::new(&lib, &edges, weights);
    if cfg.fk && cfg.p_n > 0.0 {
        let root = crate::dataset::data_root(common.args.data_root.as_deref())?;
        let model = crate::sim::mjcf::Model::for_skeleton(&root, lib.skeleton).map_err(|e| {
            anyhow::anyhow!("{e:#} (needed for the forward kinematics of perturbed starts; --set sample-stf.fk=false moves bodies rigidly instead)")
        })?;
        sampler = sampler.with_model(model);
    }
    let aw = ats.weights(&ats_params);
    let seed = common.args.seed;
    let trajs: Vec<Trajectory> = sampler
        .sample_many(&aw, &params, cfg.trajectories as usize, seed)
        .with_context(|| {
            format!(
                "sample-stf: no clip of {} has a start frame",
                input.display()
            )
        })?;
    let secs = started.elapsed().as_secs_f64();

    let resolved = common.resolved_toml("sample-stf", &cfg)?;
    let meta = table::Meta::new(&lib.clips[0].dataset, &resolved)
        .with("ingest_id", table::ingest_id(&input.join("clips.parquet"))?)
        .with("skeleton", lib.skeleton.name())
        .with("seed", seed.to_string())
        .with("stg_edges", edges.len().to_string())
        .with("rewards", cfg.rewards.clone())
        .with("weights", serde_json::to_string(&weights)?);
    let batch = table::stf::batch(&trajs)?;
    let mut out = Outputs::new(&common.args.out)?;
    out.parquet("stf_samples.parquet", &batch, &meta.table("stf_samples"))?;
    out.text("sample-stf.resolved.toml", &resolved)?;
    out.commit()?;

    if !common.args.quiet {
        print!("{}", crate::augment::stf::summary(&trajs, &lib.skills()));
        if n_rewards > 0 {
            println!("ATS rewards: {n_rewards} rows from {}", cfg.rewards);
        }
        println!(
            "sampled {} trajectories ({} rows) into {} in {secs:.2} s",
            trajs.len(),
            batch.num_rows(),
            common.args.out.join("stf_samples.parquet").display()
        );
    }
    Ok(())
}
