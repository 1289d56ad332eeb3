//! `skillaug eval`: success rates of a trained policy (paper Section 5,
//! reference §11): SR, TSR, ε-NSR and NR, over trials run in parallel with
//! deterministic actions (σ = 0) and the frozen encoder.
//!
//! - SR: start at a random reference frame of skill A (frames [2, F − 2],
//!   uniform), condition = A, judged by A's rule ([`crate::eval::rules`])
//!   over a trial of the rule's length (600 policy steps = 10 s for
//!   BallPlay), no early termination.
//! - TSR: start at a frame of A, condition = B, B's rule (BallPlay pairs
//!   DL→DR, DF→DR, DF→Shot, Layup→DF; Locomotion Getup→Run, Run→Getup).
//! - ε-NSR: as SR from a start perturbed within the training ε
//!   (`[sample-stf]` radii of the policy), or for ParaHome the
//!   object-centric perturbation (yaw U[−45°, 45°], up to 10 cm).
//! - NR: mean SM reward per step from RSI starts until the reference clip
//!   ends, for every method (also DM-trained ones).
//!
//! Outputs: `eval_trials.parquet` (one row per trial) and
//! `eval_summary.parquet` (one row per cell with 95 % Wilson intervals),
//! and a printed table.

use super::train::{environment_with, setup_with, PolicyMeta, TrainConfig};
use super::Common;
use crate::eval::rules::{Judge, Rule};
use crate::motion::MotionLib;
use crate::reward::DatasetKind;
use crate::rl::humanoid::{EnvConfig, HeRuntime, MaskedReward};
use crate::rl::{Agent, VecEnv};
use crate::table::{self, eval as etable};
use anyhow::{bail, ensure, Context, Result};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Settings of the `[eval]` recipe table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EvalConfig {
    /// Trials per cell (the paper: 10,000).
    pub trials: usize,
    /// Environments run in parallel.
    pub envs: usize,
    /// Which metrics: any of "sr", "tsr", "nsr", "nr".
    pub metrics: Vec<String>,
    /// Trial length override, policy steps (0 = each rule's own: 600 for
    /// BallPlay, 200-400 for ParaHome).
    pub steps: usize,
    /// Row label of this policy in reports ("" = from its switches, e.g. "SM+STF").
    pub label: String,
}

impl Default for EvalConfig {
    fn default() -> Self {
        EvalConfig {
            trials: 100,
            envs: 50,
            metrics: vec!["sr".into(), "tsr".into(), "nsr".into(), "nr".into()],
            steps: 0,
            label: String::new(),
        }
    }
}

/// The transition pairs of Table 1 / Table 5 (from, to) present in `skills`.
pub fn tsr_pairs(kind: DatasetKind, skills: &[String]) -> Vec<(String, String)> {
    let all: &[(&str, &str)] = match kind {
        DatasetKind::BallPlay => &[
            ("lrun", "rrun"),
            ("run", "rrun"),
            ("run", "shot"),
            ("layup", "run"),
        ],
        DatasetKind::Locomotion => &[("getup", "run_no_object"), ("run_no_object", "getup")],
        DatasetKind::ParaHome => &[],
    };
    all.iter()
        .filter(|(a, b)| skills.iter().any(|s| s == a) && skills.iter().any(|s| s == b))
        .map(|(a, b)| (a.to_string(), b.to_string()))
        .collect()
}

/// The label of a policy from its switches: "SM", "DM+eNSI", "SM+STG+STF+ATS+HE", ...
pub fn method_label(t: &TrainConfig) -> String {
    let mut s = match t.method {
        crate::rl::humanoid::Method::Sm => "SM".to_string(),
        crate::rl::humanoid::Method::Dm => "DM".to_string(),
    };
    for (on, name) in [
        (t.nsi && !t.stf, "eNSI"),
        (t.stg, "STG"),
        (t.stf, "STF"),
        (t.ats, "ATS"),
        (t.he, "HE"),
    ] {
        if on {
            s.push('+');
            s.push_str(name);
        }
    }
    s
}

/// Target ball height of a shot: the reference ball height at the highest
/// frame of the skill's first clip (reference §11.1).
fn shot_target(lib: &MotionLib, skill: &str) -> f32 {
    let Some(&c) = lib.clips_of(skill).first() else {
        return 0.0;
    };
    let f = &lib.frames[c];
    (0..f.frames)
        .filter(|i| f.valid[*i] && f.n_objects > 0)
        .map(|i| f.obj_pos[3 * f.n_objects * i + 2])
        .fold(f32::NEG_INFINITY, f32::max)
}

/// Wilson score interval of `k` successes in `n` trials at 95 %.
pub fn wilson(k: usize, n: usize) -> (f64, f64) {
    if n == 0 {
        return (f64::NAN, f64::NAN);
    }
    let z = 1.959_963_984_540_054_f64;
    let (n, p) = (n as f64, k as f64 / n as f64);
    let d = 1.0 + z * z / n;
    let c = (p + z * z / (2.0 * n)) / d;
    let h = z * ((p * (1.0 - p) / n + z * z / (4.0 * n * n)).sqrt()) / d;
    // exact ends (rounding would leave p = 1 just outside its own interval)
    ((c - h).clamp(0.0, p), (c + h).clamp(p, 1.0))
}

/// One evaluation cell.
struct Cell {
    metric: &'static str,
    from: String,
    to: String,
}

/// Run the cells of one kind: `trials` episodes of the environment built
/// with `env_cfg` from the clips of `from`, judged by `rule` (None: NR,
/// mean SM reward per unmasked step).
#[allow(clippy::too_many_arguments)]
fn run_cell(
    common: &Common,
    meta: &PolicyMeta,
    agent: &Agent,
    he: Option<&Path>,
    cell: &Cell,
    rule: Option<Rule>,
    env_cfg: EnvConfig,
    cfg: &EvalConfig,
    seed: u64,
) -> Result<Vec<etable::TrialRow>> {
    let mut tcfg = meta.train.clone();
    tcfg.skills = vec![cell.from.clone()];
    tcfg.stg = false;
    let noised = cell.metric == "nsr" && !env_cfg.object_perturb;
    tcfg.nsi = noised;
    tcfg.stf = false;
    tcfg.p_n = 1.0;
    tcfg.episode_length = 100_000; // follow the reference to its end
    let s = setup_with(common, &tcfg, &meta.stf)?;
    let he_rt = match he {
        Some(dir) => {
            let dev = candle_core::Device::Cpu;
            Some(HeRuntime::new(
                crate::nn::he::load(dir, &dev)?,
                &s.lib,
                &dev,
            )?)
        }
        None => None,
    };
    let n = cfg.envs.min(cfg.trials).max(1);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut env_cfg = env_cfg;
    env_cfg.nsi_follow = noised;
    let mut env = environment_with(&s, env_cfg.clone(), he_rt, n, &mut rng)?;
    ensure!(
        env.obs_dim() == agent.obs_dim(),
        "the policy takes {} observation values; this environment gives {}",
        agent.obs_dim(),
        env.obs_dim()
    );
    let mut rows = Vec::with_capacity(cfg.trials);
    let mut judges: Vec<Option<Judge>> = (0..n).map(|_| rule.map(Judge::new)).collect();
    let mut sums = vec![(0.0f64, 0usize, 0usize); n];
    // each environment runs trials in turn until `trials` are done
    let mut started = 0usize;
    let mut active = vec![true; n];
    started += n;
    while active.iter().any(|a| *a) {
        let obs = env.observe();
        let act = agent.act(&obs, true, &mut rng)?;
        let r = env.try_step(&act.actions, &mut rng)?;
        for e in 0..n {
            if !active[e] {
                continue;
            }
            if let Some(j) = judges[e].as_mut() {
                j.update(&env.probes()[e]);
            }
            sums[e].2 += 1;
            if let Some(sm) = env.sm_rewards()[e] {
                sums[e].0 += sm;
                sums[e].1 += 1;
            }
            if r.terminated[e] || r.truncated[e] {
                let p = &env.probes()[e];
                rows.push(etable::TrialRow {
                    metric: cell.metric.to_string(),
                    from: cell.from.clone(),
                    to: cell.to.clone(),
                    trial: rows.len() as u32,
                    success: judges[e].as_ref().map(Judge::success),
                    steps: sums[e].2 as u32,
                    mean_sm: if sums[e].1 > 0 {
                        sums[e].0 / sums[e].1 as f64
                    } else {
                        f64::NAN
                    },
                    final_root_z: p.root[2],
                });
                sums[e] = (0.0, 0, 0);
                judges[e] = rule.map(Judge::new);
                if started < cfg.trials {
                    started += 1;
                } else {
                    active[e] = false;
                }
            }
        }
    }
    Ok(rows)
}

/// Run the stage. `policy` is a `skillaug train` output folder.
pub fn run(common: &Common, policy: &Path) -> Result<()> {
    let cfg: EvalConfig = common.settings("eval")?;
    ensure!(
        cfg.trials > 0 && cfg.envs > 0,
        "eval.trials and eval.envs must be > 0"
    );
    for m in &cfg.metrics {
        ensure!(
            ["sr", "tsr", "nsr", "nr"].contains(&m.as_str()),
            "eval.metrics: unknown metric `{m}` (sr, tsr, nsr, nr)"
        );
    }
    let mp = policy.join("policy.meta.json");
    let meta: PolicyMeta = serde_json::from_slice(&std::fs::read(&mp).with_context(|| {
        format!(
            "cannot read {}: give the output folder of `skillaug train` (--policy)",
            mp.display()
        )
    })?)
    .with_context(|| format!("{} is not a skillaug policy description", mp.display()))?;
    let agent = Agent::load(
        &policy.join("policy.safetensors"),
        &candle_core::Device::Cpu,
    )?;
    let input = common.input_dir();
    let lib = table::load_library(input)?;
    let dataset = &lib.clips[0].dataset;
    if *dataset != meta.dataset || lib.skeleton.name() != meta.skeleton {
        bail!(
            "the policy in {} was trained on dataset `{}` ({}); {} holds `{}` ({})",
            policy.display(),
            meta.dataset,
            meta.skeleton,
            input.display(),
            dataset,
            lib.skeleton.name()
        );
    }
    for c in &meta.clips {
        if !lib.clips.iter().any(|r| &r.name == c) {
            bail!(
                "the policy was trained on clip `{c}`, which {} does not hold (its skills: {})",
                input.display(),
                lib.skills().join(", ")
            );
        }
    }
    let he_dir = match &meta.he_dir {
        Some(d) => {
            let p = PathBuf::from(d);
            if !p.join("he.safetensors").is_file() {
                bail!(
                    "the policy uses a history encoder, expected at {}/he.safetensors: not found \
                     (run `skillaug pretrain-he --out {d}`, or keep the training run folder)",
                    p.display()
                );
            }
            Some(p)
        }
        None => None,
    };
    let kind = DatasetKind::of_library(&lib);
    let label = if cfg.label.is_empty() {
        method_label(&meta.train)
    } else {
        cfg.label.clone()
    };
    let base = EnvConfig {
        early_termination: false,
        masked_reward: MaskedReward::Zero,
        ..EnvConfig::training(meta.train.method)
    };
    let class_of = |skill: &str| -> u32 {
        lib.clips
            .iter()
            .find(|c| c.skill == skill)
            .map_or(0, |c| c.class as u32)
    };
    let want = |m: &str| cfg.metrics.iter().any(|x| x == m);
    let mut rows = Vec::new();
    let mut k = 0u64;
    let mut next_seed = || {
        k += 1;
        common.args.seed.wrapping_mul(1_000_003).wrapping_add(k)
    };
    let he = he_dir.as_deref();
    for skill in &meta.skills {
        let rule = Rule::of_skill(skill, shot_target(&lib, skill));
        let steps = |r: Rule| {
            if cfg.steps > 0 {
                cfg.steps
            } else {
                r.trial_steps()
            }
        };
        if let Some(r) = rule {
            if want("sr") {
                let cell = Cell {
                    metric: "sr",
                    from: skill.clone(),
                    to: skill.clone(),
                };
                let ec = EnvConfig {
                    fixed_length: Some(steps(r)),
                    ..base.clone()
                };
                rows.extend(run_cell(
                    common,
                    &meta,
                    &agent,
                    he,
                    &cell,
                    Some(r),
                    ec,
                    &cfg,
                    next_seed(),
                )?);
            }
            if want("nsr") {
                let cell = Cell {
                    metric: "nsr",
                    from: skill.clone(),
                    to: skill.clone(),
                };
                let ec = EnvConfig {
                    fixed_length: Some(steps(r)),
                    object_perturb: kind == DatasetKind::ParaHome,
                    ..base.clone()
                };
                rows.extend(run_cell(
                    common,
                    &meta,
                    &agent,
                    he,
                    &cell,
                    Some(r),
                    ec,
                    &cfg,
                    next_seed(),
                )?);
            }
        }
        if want("nr") {
            let cell = Cell {
                metric: "nr",
                from: skill.clone(),
                to: skill.clone(),
            };
            rows.extend(run_cell(
                common,
                &meta,
                &agent,
                he,
                &cell,
                None,
                base.clone(),
                &cfg,
                next_seed(),
            )?);
        }
    }
    if want("tsr") {
        for (a, b) in tsr_pairs(kind, &meta.skills) {
            let Some(r) = Rule::of_skill(&b, shot_target(&lib, &b)) else {
                continue;
            };
            let cell = Cell {
                metric: "tsr",
                from: a.clone(),
                to: b.clone(),
            };
            let ec = EnvConfig {
                fixed_length: Some(if cfg.steps > 0 {
                    cfg.steps
                } else {
                    r.trial_steps()
                }),
                condition: Some(class_of(&b)),
                ..base.clone()
            };
            rows.extend(run_cell(
                common,
                &meta,
                &agent,
                he,
                &cell,
                Some(r),
                ec,
                &cfg,
                next_seed(),
            )?);
        }
    }
    let summary = etable::summarise(&label, &rows)?;
    let resolved = common.resolved_toml("eval", &cfg)?;
    let tmeta = table::Meta::new(dataset, &resolved)
        .with("label", label.clone())
        .with("policy", policy.display().to_string());
    let mut out = super::Outputs::new(&common.args.out)?;
    out.parquet(
        "eval_trials.parquet",
        &etable::trials_batch(&label, &rows)?,
        &tmeta.table("eval_trials"),
    )?;
    out.parquet(
        "eval_summary.parquet",
        &etable::summary_batch(&summary)?,
        &tmeta.table("eval_summary"),
    )?;
    out.text("eval.resolved.toml", &resolved)?;
    out.commit()?;
    if !common.args.quiet {
        println!("{}", etable::render(&summary));
        println!(
            "wrote {}",
            common.args.out.join("eval_summary.parquet").display()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wilson_intervals_match_known_values() {
        let (lo, hi) = wilson(8, 10);
        assert!(
            (lo - 0.4902).abs() < 1e-3 && (hi - 0.9433).abs() < 1e-3,
            "{lo} {hi}"
        );
        let (lo, hi) = wilson(0, 8);
        assert!(lo == 0.0 && (hi - 0.3244).abs() < 1e-3);
        assert!(wilson(0, 0).0.is_nan());
    }

    #[test]
    fn labels_and_pairs_follow_the_tables() {
        let mut t = TrainConfig::default();
        assert_eq!(method_label(&t), "SM");
        t.nsi = true;
        assert_eq!(method_label(&t), "SM+eNSI");
        t.stf = true;
        t.stg = true;
        t.ats = true;
        t.he = true;
        assert_eq!(method_label(&t), "SM+STG+STF+ATS+HE");
        let skills: Vec<String> = ["layup", "lrun", "rrun", "run", "shot"]
            .map(String::from)
            .to_vec();
        assert_eq!(tsr_pairs(DatasetKind::BallPlay, &skills).len(), 4);
        assert_eq!(tsr_pairs(DatasetKind::BallPlay, &skills[..2]).len(), 0);
    }
}
