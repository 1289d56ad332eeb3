//! `skillaug train`: PPO ([`crate::rl`]) on the rapier3d humanoid
//! ([`crate::rl::humanoid`]) with the SM or DM reward and every component of
//! the method as a switch (`--nsi --stg --stf --ats --he`), so the baselines
//! and the ablations of Tables 1 and 3 are one program with different
//! recipes.
//!
//! Sizes come from a preset that explicit keys override: `preset = "cpu"`
//! (default: 128 environments x 32 steps = 4,096 samples per iteration,
//! two 256-256 networks, minibatch 2,048, lr 1e-4, measured to learn on two
//! cores: on the DF clips, seed 0, the mean SM reward per step at 2M
//! samples was 0.129 with 512 x 32 / minibatch 4,096, 0.149 with 256 x 32,
//! and 0.187 with 128 x 32 / minibatch 2,048, the last at about the same
//! samples/s; `stages/df-run.toml`) or `"paper"` (Table 6 and the configs of
//! Ingrid789/SkillMimic-V2, `skillmimic/data/cfg/skillmimic.yaml` and
//! `skillmimic/data/cfg/train/rlg/skillmimic.yaml`: 2,048 x 32 = 65,536
//! samples, 1024-512-512 networks, minibatch 16,384, lr 2e-5). Both use 6
//! mini-epochs, γ 0.99, λ 0.95, clip 0.2 and the fixed σ 0.055.
//!
//! The neighbourhood radii, τ, N_max, the ATS exponents and the other STF
//! settings are read from the recipe's `[sample-stf]` table (one recipe
//! drives both stages); the switches set p_e (`--stg`) and p_n (`--nsi`,
//! `--stf`), from `train.p_e` / `train.p_n` (Table 7: 0.1 each).
//!
//! Outputs in `--out`: `train_metrics.parquet` (one row per iteration,
//! `skillaug schema train_metrics`), `policy.safetensors` + `policy.json`
//! (the final agent), `train.resolved.toml`, and `checkpoint/` (agent,
//! optimiser moments, normaliser, RNG state, ATS table, episode tracker,
//! metrics so far and the running episodes as start + actions), written
//! every `checkpoint_every` iterations by write-then-rename. `--resume`
//! continues from it and gives the same iterations as an uninterrupted run
//! with the same seed and thread count.

use super::Common;
use crate::rl::comm::{Comm, Solo};
use crate::rl::humanoid::{HeRuntime, Method};
use crate::rl::trainer::{Setup, Trainer};
use crate::rl::VecEnv;
use crate::table::{self, train::MetricRow};
use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};

pub use crate::rl::config::{PolicyMeta, PpoOverrides, Preset, TrainConfig};

/// Command-line switches of `skillaug train` (each, when given, overrides
/// the recipe).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Switches {
    /// `--method`.
    pub method: Option<Method>,
    /// `--nsi`.
    pub nsi: bool,
    /// `--stg`.
    pub stg: bool,
    /// `--stf`.
    pub stf: bool,
    /// `--ats`.
    pub ats: bool,
    /// `--he`.
    pub he: bool,
    /// `--device`.
    pub device: Option<String>,
    /// `--resume`.
    pub resume: bool,
}

/// Load the library of `common`'s input folder and everything else the
/// environment needs, with the recipe's `[sample-stf]` settings.
pub fn setup(common: &Common, cfg: &TrainConfig) -> Result<Setup> {
    Setup::load(
        common.input_dir(),
        common.args.data_root.as_deref(),
        cfg,
        &common.settings("sample-stf")?,
    )
}

/// The ranks of this process: MPI when a launcher started it and the `mpi`
/// feature is built, else one process.
fn ranks() -> Result<Box<dyn Comm>> {
    let launched = crate::rl::comm::launcher_size();
    refuse_launch(launched, cfg!(feature = "mpi"))?;
    #[cfg(feature = "mpi")]
    if launched.is_some() {
        return Ok(Box::new(crate::rl::comm::Mpi::init()?));
    }
    Ok(Box::new(Solo))
}

/// Refuse a launch as one of several processes (`launched`, from
/// [`crate::rl::comm::launcher_size`]) by a build without MPI: each process
/// would train alone and all would write the same folder.
fn refuse_launch(launched: Option<usize>, built_with_mpi: bool) -> Result<()> {
    if let Some(n) = launched.filter(|n| *n > 1 && !built_with_mpi) {
        bail!(
            "train: started as one of {n} processes (mpirun or srun), but this skillaug was \
             built without MPI; build it with `cargo build --release --features mpi` \
             (README, \"Training on a cluster\") or start one process"
        );
    }
    Ok(())
}

fn write_metrics(out: &Path, rows: &[MetricRow], resolved: &str, dataset: &str) -> Result<()> {
    let meta = table::Meta::new(dataset, resolved);
    let mut o = super::Outputs::new(out)?;
    o.parquet(
        "train_metrics.parquet",
        &table::train::batch(rows)?,
        &meta.table("train_metrics"),
    )?;
    o.commit()
}

/// The history encoder of `cfg.he`: from `train.he_dir`, else from the
/// input folder, whose clips it must have been pre-trained on.
fn history_encoder(
    common: &Common,
    cfg: &TrainConfig,
    s: &Setup,
    dev: &candle_core::Device,
) -> Result<Option<(HeRuntime, String)>> {
    if !cfg.he {
        return Ok(None);
    }
    let dir = if cfg.he_dir.is_empty() {
        common.input_dir().to_path_buf()
    } else {
        PathBuf::from(&cfg.he_dir)
    };
    let enc = crate::nn::he::load(&dir, dev)?;
    // an encoder in the input folder was made from its clips; one from
    // another folder (`he_dir`) is the user's choice
    if cfg.he_dir.is_empty() {
        let id = table::ingest_id(&common.input_dir().join("clips.parquet"))?;
        if let Some(e) = enc
            .cfg
            .ingest_id
            .as_ref()
            .filter(|e| table::ingest_ids_differ(e, &id))
        {
            bail!(
                "{}/he.config.json: the history encoder was pre-trained on other clips \
                 (ingest id {e}) than {} holds now ({id}): run `skillaug pretrain-he` again",
                dir.display(),
                common.input_dir().display()
            );
        }
    }
    Ok(Some((
        HeRuntime::new(enc, &s.lib, dev)?,
        dir.display().to_string(),
    )))
}

/// Run the stage.
pub fn run(common: &Common, sw: &Switches) -> Result<()> {
    let comm = ranks()?;
    let r = run_ranks(common, sw, comm.as_ref());
    if let Err(e) = &r {
        comm.abort_on_error(e);
    }
    r
}

fn run_ranks(common: &Common, sw: &Switches, comm: &dyn Comm) -> Result<()> {
    let mut cfg: TrainConfig = common.settings("train")?;
    if let Some(m) = sw.method {
        cfg.method = m;
    }
    cfg.nsi |= sw.nsi;
    cfg.stg |= sw.stg;
    cfg.stf |= sw.stf;
    cfg.ats |= sw.ats;
    cfg.he |= sw.he;
    let root = comm.is_root();
    let _lock = if root {
        Some(common.lock_output("train")?)
    } else {
        None
    };
    let dev = crate::nn::device(sw.device.as_deref().unwrap_or("cpu"))?;
    let stf_cfg = common.settings("sample-stf")?;
    let s = Setup::load(
        common.input_dir(),
        common.args.data_root.as_deref(),
        &cfg,
        &stf_cfg,
    )?;
    let (he, he_dir) = match history_encoder(common, &cfg, &s, &dev)? {
        Some((h, d)) => (Some(h), Some(d)),
        None => (None, None),
    };
    let out = common.args.out.clone();
    if root {
        std::fs::create_dir_all(&out)
            .with_context(|| format!("cannot create the output folder {}", out.display()))?;
    }
    let resolved = common.resolved_toml("train", &cfg)?;
    let seed = common.args.seed;
    let quiet = common.args.quiet || !root;
    let mut t = if sw.resume {
        Trainer::resume(&s, &cfg, &stf_cfg, he, seed, &dev, comm, &out)?
    } else {
        Trainer::start(&s, &cfg, &stf_cfg, he, seed, &dev, comm)?
    };
    if !quiet {
        if let Some(w) = &t.warm_start {
            println!(
                "train: warm start on {} states, {} epochs: action error (mse) {:.4} -> {:.4} ({:.1} s)",
                w.states, cfg.warm_start_epochs, w.mse.0, w.mse.1, w.secs
            );
        }
        println!(
            "train: {:?} on {} ({} clips), {} envs x {} steps{}, obs {} act {}, nets {:?}, lr {}, switches nsi={} stg={} stf={} ats={} he={}{}",
            cfg.method,
            s.skills().join(", "),
            s.clips.len(),
            cfg.envs(),
            cfg.steps(),
            if comm.size() > 1 {
                format!(" over {} ranks", comm.size())
            } else {
                String::new()
            },
            t.env().obs_dim(),
            t.env().act_dim(),
            t.agent().config().hidden,
            t.agent().config().lr,
            cfg.nsi,
            cfg.stg,
            cfg.stf,
            cfg.ats,
            cfg.he,
            if sw.resume {
                format!(
                    ", resumed at iteration {} ({} samples)",
                    t.iteration(),
                    t.samples()
                )
            } else {
                String::new()
            }
        );
    }
    let dataset = s.lib.clips[0].dataset.clone();
    let bar = crate::progress::bar(cfg.samples, "train", quiet);
    bar.set_position(t.samples().min(cfg.samples));
    while !t.done() {
        let row = t.iterate()?.clone();
        let m = &row.metrics;
        bar.set_position(row.samples.min(cfg.samples));
        bar.set_message(format!(
            "{:.0} samples/s  reward {:.3}  sm {:.3}  len {:.1}  falls {:.0}%",
            m.samples_per_s,
            m.mean_reward,
            m.mean_sm_reward,
            m.mean_episode_length,
            100.0 * m.fall_rate
        ));
        // without a terminal (logs), one line per iteration instead of the bar
        if !quiet && bar.is_hidden() {
            println!(
                "iter {:>5} samples {:>9} reward {:.4} sm {:.4} len {:5.1} falls {:5.1}% {:.0} samples/s (sim {:.1} s, act {:.1} s, update {:.1} s)",
                row.iteration,
                row.samples,
                m.mean_reward,
                m.mean_sm_reward,
                m.mean_episode_length,
                100.0 * m.fall_rate,
                m.samples_per_s,
                m.sim_s,
                m.act_s,
                m.update_s
            );
        }
        if row.iteration % cfg.checkpoint_every == 0 || t.done() {
            t.checkpoint(&out)?;
            if root {
                write_metrics(&out, t.metrics(), &resolved, &dataset)?;
            }
        }
    }
    bar.finish_and_clear();
    if !root {
        return Ok(());
    }
    t.agent().save(&out.join("policy.safetensors"))?;
    let meta = t.policy_meta(&stf_cfg, he_dir);
    write_metrics(&out, t.metrics(), &resolved, &dataset)?;
    let mut o = super::Outputs::new(&out)?;
    o.text("policy.meta.json", &serde_json::to_string_pretty(&meta)?)?;
    o.text("train.resolved.toml", &resolved)?;
    o.commit()?;
    if !quiet {
        if let Some(r) = t.metrics().last() {
            println!(
                "trained {} iterations, {} samples{}: last mean reward {:.4}, SM {:.4}, falls {:.1}%; wrote {}",
                r.iteration,
                r.samples,
                if comm.size() > 1 {
                    format!(
                        " on {} ranks (weights identical on every rank after every update)",
                        comm.size()
                    )
                } else {
                    String::new()
                },
                r.get("mean_reward").unwrap_or(f64::NAN),
                r.get("mean_sm_reward").unwrap_or(f64::NAN),
                100.0 * r.get("fall_rate").unwrap_or(f64::NAN),
                out.join("train_metrics.parquet").display()
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::refuse_launch;

    #[test]
    fn a_parallel_launch_of_a_build_without_mpi_is_refused() {
        let e = refuse_launch(Some(4), false).unwrap_err().to_string();
        assert!(e.contains("one of 4 processes"), "{e}");
        assert!(e.contains("--features mpi"), "{e}");
        refuse_launch(Some(4), true).unwrap();
        refuse_launch(Some(1), false).unwrap();
        refuse_launch(None, false).unwrap();
    }
}
