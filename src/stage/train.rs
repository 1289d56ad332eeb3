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
use crate::augment::ats::{Ats, AtsParams};
use crate::augment::stf::{StfParams, StfSampler};
use crate::motion::MotionLib;
use crate::reward::{DatasetKind, RewardOptions, Weights};
use crate::rl::humanoid::{EnvConfig, EnvParts, EpisodeRecord, HeRuntime, HumanoidEnv, Method};
use crate::rl::{collect, Agent, EpisodeTracker, StepResult, VecEnv};
use crate::sim::mjcf::Model;
use crate::sim::{objects, SimOptions};
use crate::stage::sample_stf::StfConfig;
use crate::table::train::{MetricRow, Metrics};
use crate::table::{self, train as mtable};
use anyhow::{bail, ensure, Context, Result};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Instant;

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

/// The trainer's state in a checkpoint beside the agent.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct TrainerState {
    format: u32,
    /// Hash of the resolved settings (without `samples`).
    settings_hash: String,
    iteration: u64,
    samples: u64,
    rng_seed: Vec<u8>,
    rng_stream: u64,
    rng_word_pos: String,
    tracker: EpisodeTracker,
    ats: Vec<(usize, usize, f64, u64)>,
    metrics: Vec<MetricRow>,
    episodes: Vec<EpisodeMeta>,
}

/// A running episode without its actions (those go to `episodes.bin`).
#[derive(Clone, Debug, Serialize, Deserialize)]
struct EpisodeMeta {
    traj: crate::augment::stf::Trajectory,
    ats_key: (usize, usize),
    actions: usize,
}

/// Everything the environment is built from, loaded once.
pub struct Setup {
    /// The motion library.
    pub lib: MotionLib,
    /// STG edges (empty without `stg`).
    pub edges: Vec<crate::augment::stg::Edge>,
    /// The humanoid model.
    pub model: Model,
    /// Objects of the trained clips.
    pub objects: Vec<crate::sim::ObjectSpec>,
    /// Physics settings.
    pub sim: SimOptions,
    /// STF parameters with the switches applied.
    pub stf: crate::augment::stf::StfParams,
    /// ATS exponents.
    pub ats_params: AtsParams,
    /// Clip ids being trained.
    pub clips: Vec<usize>,
    /// Whether perturbed starts need forward kinematics.
    pub fk: bool,
    /// Seam of every clip ([`crate::augment::seam`]).
    pub seams: Vec<Option<crate::augment::seam::Seam>>,
}

impl Setup {
    /// The trained skills, each once, in the library's clip order.
    pub fn skills(&self) -> Vec<String> {
        self.lib
            .skills()
            .into_iter()
            .filter(|sk| self.clips.iter().any(|c| self.lib.clips[*c].skill == *sk))
            .collect()
    }
}

/// Load the library and everything else the environment needs, with the
/// recipe's `[sample-stf]` settings.
pub fn setup(common: &Common, cfg: &TrainConfig) -> Result<Setup> {
    let stf_cfg: StfConfig = common.settings("sample-stf")?;
    setup_lib(
        table::load_library(common.input_dir())?,
        common,
        cfg,
        &stf_cfg,
    )
}

/// The STF parameters of `cfg`'s switches over the recipe's `base`.
pub fn start_params(cfg: &TrainConfig, base: &StfParams) -> StfParams {
    let mut stf = base.clone();
    stf.p_e = if cfg.stg { cfg.p_e } else { 0.0 };
    stf.p_n = if cfg.nsi || cfg.stf { cfg.p_n } else { 0.0 };
    stf.horizon = cfg.episode_length;
    if cfg.nsi && !cfg.stf {
        // ε-NSI follows the centroid's clip: no connection, so no start is
        // given up for lack of one (τ only decides STF connections)
        stf.tau = 0.0;
    }
    stf
}

/// [`setup`] on a library already loaded from `common`'s input folder and
/// explicit STF settings (evaluation checks the library against the policy
/// first and uses the policy's STF settings).
pub fn setup_lib(
    lib: MotionLib,
    common: &Common,
    cfg: &TrainConfig,
    stf_cfg: &StfConfig,
) -> Result<Setup> {
    let (base, ats_params) = stf_cfg.params()?;
    let input = common.input_dir();
    let all = lib.skills();
    for s in &cfg.skills {
        if !all.contains(s) {
            bail!(
                "train.skills: no skill `{s}` in {} (skills: {})",
                input.display(),
                all.join(", ")
            );
        }
    }
    let clips: Vec<usize> = (0..lib.clips.len())
        .filter(|c| cfg.skills.is_empty() || cfg.skills.contains(&lib.clips[*c].skill))
        .collect();
    let stf = start_params(cfg, &base);
    if cfg.stg && DatasetKind::of_library(&lib) == DatasetKind::ParaHome {
        bail!("train --stg: ParaHome has no Stitched Trajectory Graph (Table 7); leave --stg off");
    }
    let edges = if cfg.stg {
        super::sample_stf::load_edges(input, &lib, cfg.p_e)?
    } else {
        Vec::new()
    };
    let root = crate::dataset::data_root(common.args.data_root.as_deref())?;
    let model = Model::for_skeleton(&root, lib.skeleton)?;
    let first = &lib.clips[clips[0]];
    for &c in &clips {
        let row = &lib.clips[c];
        if row.objects != first.objects {
            bail!(
                "train: clips `{}` (objects {:?}) and `{}` (objects {:?}) need different worlds; \
                 train them separately (train.skills)",
                first.name,
                first.objects,
                row.name,
                row.objects
            );
        }
    }
    let objects = objects::load_all(&first.objects, &root)?;
    let sim = SimOptions::for_fps(first.fps as f64);
    let min_loop = (cfg.seam_min_loop_s * first.fps as f64).ceil() as usize;
    let seams = crate::augment::seam::seams(
        &lib,
        &Weights::sm(DatasetKind::of_library(&lib)),
        min_loop.max(1),
    );
    Ok(Setup {
        seams,
        fk: stf_cfg.fk,
        lib,
        edges,
        model,
        objects,
        sim,
        stf,
        ats_params,
        clips,
    })
}

/// Build the environment of `setup` with `n` worlds.
pub fn environment<'a>(
    s: &'a Setup,
    cfg: &TrainConfig,
    he: Option<HeRuntime>,
    n: usize,
    rng: &mut ChaCha8Rng,
) -> Result<HumanoidEnv<'a>> {
    let env_cfg = EnvConfig {
        early_termination: cfg.early_termination,
        fall_height: cfg.fall_height,
        collapse_reward: cfg.collapse_reward,
        masked_reward: cfg.masked_reward,
        reward: RewardOptions {
            contacts: cfg.contacts,
            contact_detect: cfg.contact_detect,
            contact_radius: cfg.contact_radius,
            root_rot: cfg.root_rot,
            smoothness: cfg.smoothness,
        },
        continue_steps: if cfg.continuation {
            cfg.episode_length
        } else {
            0
        },
        term_key_distance: cfg.term_key_distance,
        term_object_distance: cfg.term_object_distance,
        fall_height_by_skill: cfg.fall_height_by_skill.clone(),
        seam_masked_min: cfg.seam_masked_min,
        nsi_follow: cfg.nsi && !cfg.stf,
        ats: cfg.ats,
        ats_params: s.ats_params,
        ats_update: cfg.ats_update,
        ..EnvConfig::training(cfg.method)
    };
    environment_with(s, &s.clips, s.stf.clone(), env_cfg, he, n, rng)
}

/// Build an environment of `n` worlds over `setup`'s library that starts
/// in `clips` with `stf`, with explicit settings (evaluation).
pub fn environment_with<'a>(
    s: &'a Setup,
    clips: &[usize],
    stf: StfParams,
    env_cfg: EnvConfig,
    he: Option<HeRuntime>,
    n: usize,
    rng: &mut ChaCha8Rng,
) -> Result<HumanoidEnv<'a>> {
    let mut ats = Ats::new(&s.lib);
    for c in 0..s.lib.clips.len() {
        if !clips.contains(&c) {
            ats.disable_clip(c);
        }
    }
    let weights = Weights::sm(DatasetKind::of_library(&s.lib));
    let mut sampler = StfSampler::new(&s.lib, &s.edges, weights);
    if s.fk && stf.p_n > 0.0 {
        sampler = sampler.with_model(s.model.clone());
    }
    HumanoidEnv::new(
        EnvParts {
            lib: &s.lib,
            sampler,
            stf,
            ats,
            model: s.model.clone(),
            objects: s.objects.clone(),
            sim: s.sim.clone(),
            cfg: env_cfg,
            he,
            seams: s.seams.clone(),
        },
        n,
        rng,
    )
}

/// Times the environment's steps (the simulation share of an iteration).
pub struct Timed<'e, E: VecEnv> {
    /// The wrapped environment.
    pub env: &'e mut E,
    /// Seconds spent in `step`.
    pub secs: f64,
}

impl<E: VecEnv> VecEnv for Timed<'_, E> {
    fn num_envs(&self) -> usize {
        self.env.num_envs()
    }
    fn obs_dim(&self) -> usize {
        self.env.obs_dim()
    }
    fn act_dim(&self) -> usize {
        self.env.act_dim()
    }
    fn observe(&self) -> Vec<f32> {
        self.env.observe()
    }
    fn step(&mut self, actions: &[f32], rng: &mut ChaCha8Rng) -> Result<StepResult> {
        let t = Instant::now();
        let r = self.env.step(actions, rng);
        self.secs += t.elapsed().as_secs_f64();
        r
    }
}

fn settings_hash(cfg: &TrainConfig, stf_cfg: &StfConfig, seed: u64) -> Result<String> {
    let mut c = cfg.clone();
    c.samples = 0;
    let text = format!(
        "{}\n{}\nseed={seed}",
        toml::to_string(&c)?,
        toml::to_string(stf_cfg)?,
    );
    Ok(crate::config::hash_text(&text))
}

fn ckpt_dir(out: &Path) -> PathBuf {
    out.join("checkpoint")
}

/// Write a checkpoint: into `checkpoint.tmp/`, then swapped into place.
fn save_checkpoint(
    out: &Path,
    agent: &Agent,
    st: &TrainerState,
    recs: &[EpisodeRecord],
) -> Result<()> {
    let tmp = out.join("checkpoint.tmp");
    let old = out.join("checkpoint.old");
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp)?;
    }
    std::fs::create_dir_all(&tmp)?;
    agent.save(&tmp.join("agent.safetensors"))?;
    let mut bytes = Vec::new();
    for r in recs {
        for a in &r.actions {
            bytes.extend_from_slice(&a.to_le_bytes());
        }
    }
    std::fs::write(tmp.join("episodes.bin"), bytes)?;
    std::fs::write(tmp.join("state.json"), serde_json::to_vec(st)?)?;
    let dir = ckpt_dir(out);
    if dir.exists() {
        if old.exists() {
            std::fs::remove_dir_all(&old)?;
        }
        std::fs::rename(&dir, &old)?;
    }
    std::fs::rename(&tmp, &dir)?;
    if old.exists() {
        std::fs::remove_dir_all(&old)?;
    }
    Ok(())
}

/// Load a checkpoint (`checkpoint/`, or `checkpoint.old/` when a swap was
/// interrupted).
fn load_checkpoint(
    out: &Path,
    dev: &candle_core::Device,
) -> Result<(Agent, TrainerState, Vec<EpisodeRecord>)> {
    let mut dir = ckpt_dir(out);
    if !dir.join("state.json").is_file() {
        dir = out.join("checkpoint.old");
    }
    ensure!(
        dir.join("state.json").is_file(),
        "--resume: no checkpoint in {} (train without --resume to start)",
        out.display()
    );
    let sp = dir.join("state.json");
    let st: TrainerState = serde_json::from_slice(&std::fs::read(&sp)?)
        .with_context(|| format!("{} is not a skillaug training checkpoint", sp.display()))?;
    ensure!(
        st.format == 1,
        "{}: checkpoint format {}",
        sp.display(),
        st.format
    );
    let agent = Agent::load(&dir.join("agent.safetensors"), dev)?;
    let bytes = std::fs::read(dir.join("episodes.bin"))?;
    let total: usize = st.episodes.iter().map(|e| e.actions).sum();
    ensure!(
        bytes.len() == 4 * total,
        "{}: episodes.bin holds {} bytes, expected {}",
        dir.display(),
        bytes.len(),
        4 * total
    );
    let mut at = 0;
    let mut recs = Vec::with_capacity(st.episodes.len());
    for e in &st.episodes {
        let actions = bytes[4 * at..4 * (at + e.actions)]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        at += e.actions;
        recs.push(EpisodeRecord {
            traj: e.traj.clone(),
            ats_key: e.ats_key,
            actions,
        });
    }
    Ok((agent, st, recs))
}

fn write_metrics(out: &Path, rows: &[MetricRow], resolved: &str, dataset: &str) -> Result<()> {
    let meta = table::Meta::new(dataset, resolved);
    let mut o = super::Outputs::new(out)?;
    o.parquet(
        "train_metrics.parquet",
        &mtable::batch(rows)?,
        &meta.table("train_metrics"),
    )?;
    o.commit()
}

/// Run the stage.
pub fn run(common: &Common, sw: &Switches) -> Result<()> {
    let mut cfg: TrainConfig = common.settings("train")?;
    if let Some(m) = sw.method {
        cfg.method = m;
    }
    cfg.nsi |= sw.nsi;
    cfg.stg |= sw.stg;
    cfg.stf |= sw.stf;
    cfg.ats |= sw.ats;
    cfg.he |= sw.he;
    let _lock = common.lock_output("train")?;
    let dev = crate::nn::device(sw.device.as_deref().unwrap_or("cpu"))?;
    let stf_cfg: StfConfig = common.settings("sample-stf")?;
    let s = setup_lib(
        table::load_library(common.input_dir())?,
        common,
        &cfg,
        &stf_cfg,
    )?;
    let he = if cfg.he {
        let dir = if cfg.he_dir.is_empty() {
            common.input_dir().to_path_buf()
        } else {
            PathBuf::from(&cfg.he_dir)
        };
        let enc = crate::nn::he::load(&dir, &dev)?;
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
        Some(HeRuntime::new(enc, &s.lib, &dev)?)
    } else {
        None
    };
    let out = common.args.out.clone();
    std::fs::create_dir_all(&out)
        .with_context(|| format!("cannot create the output folder {}", out.display()))?;
    let resolved = common.resolved_toml("train", &cfg)?;
    let hash = settings_hash(&cfg, &stf_cfg, common.args.seed)?;
    let seed = common.args.seed;
    let ppo = cfg.ppo_config();
    let n = cfg.envs();
    let steps = cfg.steps();

    let (mut agent, mut rng, mut env, mut tracker, mut metrics, mut iteration, mut samples);
    if sw.resume {
        let (a, st, recs) = load_checkpoint(&out, &dev)?;
        ensure!(
            st.settings_hash == hash,
            "--resume: the settings differ from those of the checkpoint in {} \
             (only train.samples may change); start a new --out instead",
            out.display()
        );
        let mut throwaway = ChaCha8Rng::seed_from_u64(seed);
        env = environment(&s, &cfg, he, n, &mut throwaway)?;
        env.restore(recs)?;
        let mut ats = env.ats().clone();
        for (c, f, m, v) in &st.ats {
            ats.restore_stat(*c, *f, *m, *v);
        }
        env.set_ats(ats);
        env.take_stats();
        let mut seed32 = [0u8; 32];
        ensure!(st.rng_seed.len() == 32, "checkpoint: RNG seed");
        seed32.copy_from_slice(&st.rng_seed);
        let mut r = ChaCha8Rng::from_seed(seed32);
        r.set_stream(st.rng_stream);
        r.set_word_pos(
            st.rng_word_pos
                .parse::<u128>()
                .context("checkpoint: RNG position")?,
        );
        rng = r;
        agent = a;
        ensure!(
            agent.obs_dim() == env.obs_dim() && agent.act_dim() == env.act_dim(),
            "--resume: the checkpoint's agent does not fit this environment"
        );
        tracker = st.tracker;
        metrics = st.metrics;
        iteration = st.iteration;
        samples = st.samples;
    } else {
        rng = ChaCha8Rng::seed_from_u64(seed);
        env = environment(&s, &cfg, he, n, &mut rng)?;
        env.take_stats();
        agent = Agent::new(env.obs_dim(), env.act_dim(), &ppo, seed, &dev)?;
        if cfg.warm_start_epochs > 0 {
            let t = Instant::now();
            let (obs, targets) = env.warm_start_data(&s.clips, cfg.warm_start_copies, &mut rng)?;
            let (before, after) = agent.fit_mean(
                &obs,
                &targets,
                cfg.warm_start_epochs,
                // 512 for the presets; tiny test minibatches would make thousands of steps
                ppo.minibatch.clamp(256, 512),
                cfg.warm_start_lr,
                &mut rng,
            )?;
            if !common.args.quiet {
                println!(
                    "train: warm start on {} states, {} epochs: action error (mse) {before:.4} -> {after:.4} ({:.1} s)",
                    obs.len() / env.obs_dim(),
                    cfg.warm_start_epochs,
                    t.elapsed().as_secs_f64()
                );
            }
        }
        tracker = EpisodeTracker::new(n);
        metrics = Vec::new();
        iteration = 0;
        samples = 0;
    }
    let quiet = common.args.quiet;
    if !quiet {
        let skills = s.skills();
        println!(
            "train: {:?} on {} ({} clips), {} envs x {} steps, obs {} act {}, nets {:?}, lr {}, switches nsi={} stg={} stf={} ats={} he={}{}",
            cfg.method,
            skills.join(", "),
            s.clips.len(),
            n,
            steps,
            env.obs_dim(),
            env.act_dim(),
            agent.config().hidden,
            agent.config().lr,
            cfg.nsi,
            cfg.stg,
            cfg.stf,
            cfg.ats,
            cfg.he,
            if sw.resume {
                format!(", resumed at iteration {iteration} ({samples} samples)")
            } else {
                String::new()
            }
        );
    }
    let dataset = s.lib.clips[0].dataset.clone();
    let bar = crate::progress::bar(cfg.samples, "train", quiet);
    bar.set_position(samples.min(cfg.samples));
    while samples < cfg.samples {
        let t0 = Instant::now();
        let mut timed = Timed {
            env: &mut env,
            secs: 0.0,
        };
        let ro = collect(&agent, &mut timed, steps, &mut tracker, &mut rng)?;
        let sim_s = timed.secs;
        let collect_s = t0.elapsed().as_secs_f64();
        let st = env.take_stats();
        env.refresh_ats();
        let t1 = Instant::now();
        let up = agent.update_with(&ro, &mut rng, iteration < cfg.critic_warmup_iters)?;
        let update_s = t1.elapsed().as_secs_f64();
        let total_s = t0.elapsed().as_secs_f64();
        iteration += 1;
        samples += (n * steps) as u64;
        let returns = tracker.take();
        let mean_return = if returns.is_empty() {
            f64::NAN
        } else {
            returns.iter().sum::<f64>() / returns.len() as f64
        };
        // start fractions are NaN when no episode started in the iteration
        metrics.push(MetricRow {
            iteration,
            samples,
            metrics: Metrics {
                mean_reward: st.mean_reward(),
                mean_sm_reward: st.mean_sm(),
                fall_rate: st.fall_rate(),
                episodes: st.episodes as f64,
                mean_episode_length: st.mean_length(),
                mean_return,
                masked_frac: st.masked as f64 / st.steps.max(1) as f64,
                stg_start_frac: st.starts.stg_frac(),
                noised_start_frac: st.starts.noised_frac(),
                mean_n_masked: st.n_masked_sum as f64 / st.start_count() as f64,
                policy_loss: up.policy_loss,
                value_loss: up.value_loss,
                bounds_loss: up.bounds_loss,
                clip_frac: up.clip_frac,
                approx_kl: up.approx_kl,
                lr: up.lr,
                mean_sm_body: st.mean_sm_factor(0),
                mean_sm_object: st.mean_sm_factor(1),
                mean_sm_rel: st.mean_sm_factor(2),
                mean_sm_contact: st.mean_sm_factor(3),
                lost_rate: st.lost_rate(),
                lost_object_rate: st.lost_object_rate(),
                continued_frac: if st.episodes > 0 {
                    st.continuations as f64 / st.episodes as f64
                } else {
                    f64::NAN
                },
                samples_per_s: (n * steps) as f64 / total_s,
                sim_s,
                act_s: collect_s - sim_s,
                update_s,
            },
        });
        bar.set_position(samples.min(cfg.samples));
        bar.set_message(format!(
            "{:.0} samples/s  reward {:.3}  sm {:.3}  len {:.1}  falls {:.0}%",
            (n * steps) as f64 / total_s,
            st.mean_reward(),
            st.mean_sm(),
            st.mean_length(),
            100.0 * st.fall_rate()
        ));
        // without a terminal (logs), one line per iteration instead of the bar
        if !quiet && bar.is_hidden() {
            println!(
                    "iter {iteration:>5} samples {samples:>9} reward {:.4} sm {:.4} len {:5.1} falls {:5.1}% {:.0} samples/s (sim {:.1} s, act {:.1} s, update {:.1} s)",
                    st.mean_reward(),
                    st.mean_sm(),
                    st.mean_length(),
                    100.0 * st.fall_rate(),
                    (n * steps) as f64 / total_s,
                    sim_s,
                    collect_s - sim_s,
                    update_s
                );
        }
        let last = samples >= cfg.samples;
        if iteration % cfg.checkpoint_every == 0 || last {
            let recs = env.snapshot();
            let (seed_bytes, stream, pos) = (rng.get_seed(), rng.get_stream(), rng.get_word_pos());
            let state = TrainerState {
                format: 1,
                settings_hash: hash.clone(),
                iteration,
                samples,
                rng_seed: seed_bytes.to_vec(),
                rng_stream: stream,
                rng_word_pos: pos.to_string(),
                tracker: tracker.clone(),
                ats: env.ats().visited(),
                metrics: metrics.clone(),
                episodes: recs
                    .iter()
                    .map(|r| EpisodeMeta {
                        traj: r.traj.clone(),
                        ats_key: r.ats_key,
                        actions: r.actions.len(),
                    })
                    .collect(),
            };
            save_checkpoint(&out, &agent, &state, &recs)?;
            write_metrics(&out, &metrics, &resolved, &dataset)?;
        }
    }
    bar.finish_and_clear();
    agent.save(&out.join("policy.safetensors"))?;
    let meta = PolicyMeta {
        format: 1,
        dataset: dataset.clone(),
        skeleton: s.lib.skeleton.name().to_string(),
        skills: s.skills(),
        clips: s
            .clips
            .iter()
            .map(|c| s.lib.clips[*c].name.clone())
            .collect(),
        objects: s.lib.clips[s.clips[0]].objects.clone(),
        obs_dim: env.obs_dim(),
        act_dim: env.act_dim(),
        he_dir: cfg.he.then(|| {
            if cfg.he_dir.is_empty() {
                common.input_dir().display().to_string()
            } else {
                cfg.he_dir.clone()
            }
        }),
        train: cfg.clone(),
        stf: stf_cfg,
        iterations: iteration,
        samples,
    };
    write_metrics(&out, &metrics, &resolved, &dataset)?;
    let mut o = super::Outputs::new(&out)?;
    o.text("policy.meta.json", &serde_json::to_string_pretty(&meta)?)?;
    o.text("train.resolved.toml", &resolved)?;
    o.commit()?;
    if !quiet {
        if let Some(r) = metrics.last() {
            println!(
                "trained {} iterations, {} samples: last mean reward {:.4}, SM {:.4}, falls {:.1}%; wrote {}",
                r.iteration,
                r.samples,
                r.get("mean_reward").unwrap_or(f64::NAN),
                r.get("mean_sm_reward").unwrap_or(f64::NAN),
                100.0 * r.get("fall_rate").unwrap_or(f64::NAN),
                out.join("train_metrics.parquet").display()
            );
        }
    }
    Ok(())
}
