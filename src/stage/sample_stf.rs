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

use super::{Common, Outputs};
use crate::augment::ats::{Ats, AtsParams, Update};
use crate::augment::stf::{Connect, Eps, Noise, Order, Search, StfParams, StfSampler, Trajectory};
use crate::augment::MaskRule;
use crate::motion::Skeleton;
use crate::reward::{DatasetKind, Weights};
use crate::table;
use anyhow::{bail, Context, Result};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

/// Settings of the `[sample-stf]` recipe table (defaults: Table 7, BallPlay).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StfConfig {
    /// Trajectories to sample.
    pub trajectories: u32,
    /// Move the bodies of perturbed starts by forward kinematics of the MJCF
    /// humanoid (data root `assets/mjcf/`); false = rigidly with the root only.
    pub fk: bool,
    /// Policy steps per trajectory at most (episode length T, Table 6).
    pub horizon: u32,
    /// Probability of an external (STG) start; must be 0 for ParaHome.
    pub p_e: f64,
    /// Probability of an ε-neighbourhood start.
    pub p_n: f64,
    /// ATS frame-level exponent lambda_s (Eq. 8).
    pub lambda_s: f64,
    /// ATS inter-class exponent lambda_c.
    pub lambda_c: f64,
    /// ATS intra-class clip exponent: 0 = uniform within a class (paper), 5 = reference code.
    pub lambda_i: f64,
    /// Neighbourhood radii per group.
    pub eps: Eps,
    /// Per-class radii replacing `eps` (key: class id). Giving this table
    /// replaces the default, which holds class 0 (Getup: root_pos = root_vel = 1.0).
    pub eps_class: BTreeMap<String, Eps>,
    /// "uniform" in [-ε, ε] (paper) or "gaussian" with σ = ε (reference code).
    pub noise: Noise,
    /// Similarity threshold tau.
    pub tau: f64,
    /// Maximum masked states N_max.
    pub n_max: u32,
    /// Eq. 20 as printed ("paper", ceil) or the reference code's floor rule ("reference").
    pub mask_rule: MaskRule,
    /// "paper" (Algorithm 1: switch, then noise on top) or "reference" (noise or switch, never both).
    pub order: Order,
    /// "paper" (Eq. 7: start, N masked, ŝ_j, ...) or "reference" (the start stands for ŝ_j).
    pub connect: Connect,
    /// Frames Eq. 6 searches: "skill" (every clip of A) or "clip" (the centroid's clip, reference code).
    pub search: Search,
    /// Target skills (empty = all).
    pub skills: Vec<String>,
    /// ATS rewards table (Parquet: clip_id, frame, mean_reward); "" = none (uniform).
    pub rewards: String,
}

impl crate::config::Validate for StfConfig {
    fn validate(&self, stage: &str) -> Result<()> {
        let c = crate::config::Check::new(stage);
        c.count("trajectories", self.trajectories as u64, 1, u32::MAX as u64)?;
        c.count("horizon", self.horizon as u64, 1, 1 << 20)?;
        c.range("p_e", self.p_e, 0.0, 1.0)?;
        c.range("p_n", self.p_n, 0.0, 1.0)?;
        c.range("lambda_s", self.lambda_s, 0.0, 1e3)?;
        c.range("lambda_c", self.lambda_c, 0.0, 1e3)?;
        c.range("lambda_i", self.lambda_i, 0.0, 1e3)?;
        c.range("tau", self.tau, 0.0, 1.0)?;
        c.count("n_max", self.n_max as u64, 0, 10_000)?;
        let check_eps = |name: &str, e: &Eps| -> Result<()> {
            for (k, v) in [
                ("root_pos", e.root_pos),
                ("root_vel", e.root_vel),
                ("root_rot", e.root_rot),
                ("root_rot_vel", e.root_rot_vel),
                ("dof", e.dof),
                ("dof_vel", e.dof_vel),
                ("obj_pos", e.obj_pos),
                ("obj_vel", e.obj_vel),
                ("obj_rot", e.obj_rot),
                ("obj_rot_vel", e.obj_rot_vel),
            ] {
                c.range(&format!("{name}.{k}"), v, 0.0, 1e3)?;
            }
            Ok(())
        };
        check_eps("eps", &self.eps)?;
        for (k, e) in &self.eps_class {
            c.holds(k.parse::<u32>().is_ok(), || {
                format!("eps_class.{k}: the key must be a class id (an integer)")
            })?;
            check_eps(&format!("eps_class.{k}"), e)?;
        }
        Ok(())
    }
}

impl Default for StfConfig {
    fn default() -> Self {
        let p = StfParams::default();
        let a = AtsParams::default();
        StfConfig {
            trajectories: 1000,
            fk: true,
            horizon: p.horizon as u32,
            p_e: p.p_e,
            p_n: p.p_n,
            lambda_s: a.lambda_s,
            lambda_c: a.lambda_c,
            lambda_i: a.lambda_i,
            eps: p.eps,
            eps_class: p
                .eps_class
                .iter()
                .map(|(k, v)| (k.to_string(), *v))
                .collect(),
            noise: p.noise,
            tau: p.tau,
            n_max: p.n_max,
            mask_rule: p.mask_rule,
            order: p.order,
            connect: p.connect,
            search: p.search,
            skills: Vec::new(),
            rewards: String::new(),
        }
    }
}

impl StfConfig {
    /// Build the library parameters (the ranges are checked by
    /// [`crate::config::Validate`] when the settings are resolved).
    pub fn params(&self) -> Result<(StfParams, AtsParams)> {
        let mut eps_class = BTreeMap::new();
        for (k, e) in &self.eps_class {
            let class: u32 = k.parse().with_context(|| {
                format!("sample-stf.eps_class.{k}: the key must be a class id (an integer)")
            })?;
            eps_class.insert(class, *e);
        }
        Ok((
            StfParams {
                p_e: self.p_e,
                p_n: self.p_n,
                eps: self.eps,
                eps_class,
                noise: self.noise,
                tau: self.tau,
                n_max: self.n_max,
                mask_rule: self.mask_rule,
                order: self.order,
                connect: self.connect,
                search: self.search,
                horizon: self.horizon as usize,
            },
            AtsParams {
                lambda_s: self.lambda_s,
                lambda_c: self.lambda_c,
                lambda_i: self.lambda_i,
                update: Update::Mean,
            },
        ))
    }
}

/// Read and check the STG edges of `input` against its clips.
pub(crate) fn load_edges(
    input: &Path,
    lib: &crate::motion::MotionLib,
    p_e: f64,
) -> Result<Vec<crate::augment::stg::Edge>> {
    let path = input.join("stg_edges.parquet");
    if !path.is_file() {
        bail!(
            "{} does not exist: p_e = {p_e} starts trajectories from the Stitched Trajectory Graph; \
             run `skillaug build-stg --out {}` first (or set sample-stf.p_e=0)",
            path.display(),
            input.display()
        );
    }
    let edges = table::stg::read(&path)?;
    table::check_ingest_id(
        &path,
        &table::ingest_id(&input.join("clips.parquet"))?,
        "build-stg",
    )?;
    for (i, e) in edges.iter().enumerate() {
        let ok = |c: u32, f: u32| {
            lib.frames
                .get(c as usize)
                .is_some_and(|cf| (f as usize) < cf.frames)
        };
        if !ok(e.src_clip, e.src_frame)
            || !ok(e.dst_clip, e.dst_frame)
            || lib.clips[e.dst_clip as usize].skill != e.target_skill
        {
            bail!(
                "{}: row {i} (clip {} frame {} -> clip {} frame {}, skill {}) does not match the clips of {}: \
                 run `skillaug build-stg` again",
                path.display(),
                e.src_clip,
                e.src_frame,
                e.dst_clip,
                e.dst_frame,
                e.target_skill,
                input.display()
            );
        }
    }
    Ok(edges)
}

/// Fill `ats` from the rewards table at `path`.
fn load_rewards(path: &Path, lib: &crate::motion::MotionLib, ats: &mut Ats) -> Result<usize> {
    let rows = table::stf::read_rewards(path)
        .context("sample-stf.rewards: cannot use the ATS rewards table")?;
    let mut seen = std::collections::BTreeSet::new();
    for (i, (c, f, r)) in rows.iter().enumerate() {
        let Some(cf) = lib.frames.get(*c as usize) else {
            bail!(
                "{}: row {i}: clip_id {c} is not a clip of this run ({} clips)",
                path.display(),
                lib.clips.len()
            );
        };
        if *f as usize >= cf.frames {
            bail!(
                "{}: row {i}: frame {f} is outside clip {c} ({} frames)",
                path.display(),
                cf.frames
            );
        }
        if !seen.insert((*c, *f)) {
            bail!(
                "{}: row {i}: a second row for clip {c}, frame {f}",
                path.display()
            );
        }
        ats.set_mean(*c as usize, *f as usize, *r);
    }
    Ok(rows.len())
}

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
    let mut ats = Ats::new(&lib);
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
        for c in 0..lib.clips.len() {
            if !cfg.skills.contains(&lib.clips[c].skill) {
                ats.disable_clip(c);
            }
        }
    }
    let edges = if cfg.p_e > 0.0 {
        load_edges(input, &lib, cfg.p_e)?
    } else {
        Vec::new()
    };
    let n_rewards = if cfg.rewards.is_empty() {
        0
    } else {
        load_rewards(Path::new(&cfg.rewards), &lib, &mut ats)?
    };
    let weights = Weights::sm(DatasetKind::of_library(&lib));
    let mut sampler = StfSampler::new(&lib, &edges, weights);
    if cfg.fk && cfg.p_n > 0.0 {
        let root = crate::dataset::data_root(common.args.data_root.as_deref())?;
        let path = root
            .join("assets/mjcf")
            .join(format!("{}.xml", lib.skeleton.name()));
        let model = crate::sim::mjcf::Model::load(&path).map_err(|e| {
            anyhow::anyhow!("{e:#} (needed for the forward kinematics of perturbed starts; --set sample-stf.fk=false moves bodies rigidly instead)")
        })?;
        sampler = sampler.with_model(model);
    }
    let aw = ats.weights(&ats_params);
    let seed = common.args.seed;
    let trajs: Vec<Trajectory> = (0..cfg.trajectories)
        .into_par_iter()
        .map(|i| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            rng.set_stream(i as u64);
            sampler.sample(&aw, &params, &mut rng)
        })
        .collect::<Option<Vec<_>>>()
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
        print!("{}", summary(&trajs, &lib.skills()));
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

/// The summary table: per target skill, trajectories per start kind, mean N
/// and mean length (policy steps).
pub fn summary(trajs: &[Trajectory], skills: &[String]) -> String {
    const KINDS: [&str; 4] = ["rsi", "rsi+noise", "stg", "stg+noise"];
    let mut s = format!(
        "{:<14} {:>5} {:>6} {:>6} {:>9} {:>6} {:>9} {:>8} {:>6} {:>10}\n",
        "target skill",
        "class",
        "trajs",
        "rsi",
        "rsi+noise",
        "stg",
        "stg+noise",
        "fallback",
        "mean N",
        "mean steps"
    );
    let row = |name: &str, class: String, v: &[&Trajectory]| -> String {
        let n = v.len().max(1) as f64;
        let count = |k: &str| v.iter().filter(|t| t.kind_label() == k).count();
        let mean_n = v.iter().map(|t| t.n_masked as f64).sum::<f64>() / n;
        let mean_len = v.iter().map(|t| t.policy_steps() as f64).sum::<f64>() / n;
        format!(
            "{:<14} {:>5} {:>6} {:>6} {:>9} {:>6} {:>9} {:>8} {:>6.2} {:>10.1}\n",
            name,
            class,
            v.len(),
            count(KINDS[0]),
            count(KINDS[1]),
            count(KINDS[2]),
            count(KINDS[3]),
            v.iter().filter(|t| t.fallback).count(),
            mean_n,
            mean_len
        )
    };
    for sk in skills {
        let v: Vec<&Trajectory> = trajs.iter().filter(|t| &t.target_skill == sk).collect();
        if let Some(t) = v.first() {
            s += &row(sk, t.condition.to_string(), &v);
        }
    }
    s += &row("all", String::new(), &trajs.iter().collect::<Vec<_>>());
    s
}
