//! The evaluator of `skillaug eval`: success rates of a trained policy
//! (paper Section 5; reference code: Ingrid789/SkillMimic-V2
//! `skillmimic/learning/skillmimic_players.py` and `skillmimic/metric/`):
//! SR, TSR, ε-NSR and NR, over trials run in parallel with deterministic
//! actions (σ = 0) and the frozen encoder.
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

use crate::augment::stf::StfParams;
use crate::eval::rules::{Judge, Rule};
use crate::motion::MotionLib;
use crate::reward::DatasetKind;
use crate::rl::config::{PolicyMeta, TrainConfig};
use crate::rl::humanoid::{EnvConfig, HeRuntime, MaskedReward};
use crate::rl::trainer::{environment_with, start_params, Setup};
use crate::rl::{Agent, VecEnv};
use crate::table::eval::{self as etable, Metric};
use crate::table::rollout::RolloutStep;
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
    /// Trial length override of the sr, nsr and tsr trials, policy steps
    /// (0 = each rule's own: 600 for BallPlay, 200-400 for ParaHome); nr
    /// trials follow their reference to its end whatever this says.
    pub steps: usize,
    /// Row label of this policy in reports ("" = from its switches, e.g. "SM+STF").
    pub label: String,
    /// Keep the first `record` finished trials of each cell step by step in
    /// `eval_rollouts.parquet` (for `skillaug view --rollouts`); 0: none.
    pub record: usize,
}

impl crate::config::Validate for EvalConfig {
    fn validate(&self, stage: &str) -> Result<()> {
        let c = crate::config::Check::new(stage);
        c.count("trials", self.trials as u64, 1, 1 << 32)?;
        c.count("envs", self.envs as u64, 1, 1 << 20)?;
        c.count("steps", self.steps as u64, 0, 1 << 24)?;
        c.count("record", self.record as u64, 0, self.trials as u64)?;
        c.holds(!self.metrics.is_empty(), || {
            "metrics = []: give at least one of sr, tsr, nsr, nr".into()
        })?;
        for m in &self.metrics {
            c.holds(Metric::from_name(m).is_some(), || {
                format!("metrics: unknown metric `{m}` (sr, tsr, nsr, nr)")
            })?;
        }
        Ok(())
    }
}

impl Default for EvalConfig {
    fn default() -> Self {
        EvalConfig {
            trials: 100,
            envs: 50,
            metrics: vec!["sr".into(), "tsr".into(), "nsr".into(), "nr".into()],
            steps: 0,
            label: String::new(),
            record: 0,
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

/// Target ball height of a shot: the reference ball height at the highest
/// frame of the skill's first clip (the `layup_target` of
/// Ingrid789/SkillMimic-V2 `skillmimic/env/tasks/skillmimic1.py`).
pub fn shot_target(lib: &MotionLib, skill: &str) -> f32 {
    let Some(&c) = lib.clips_of(skill).first() else {
        return 0.0;
    };
    let f = &lib.frames[c];
    (0..f.frames)
        .filter(|i| f.valid[*i] && f.n_objects > 0)
        .map(|i| f.obj_pos[3 * f.n_objects * i + 2])
        .fold(f32::NEG_INFINITY, f32::max)
}

/// One evaluation cell: its metric, start and target skills, rule (None:
/// NR, the mean SM reward per unmasked step) and environment settings.
pub struct Cell {
    /// Its metric.
    pub metric: Metric,
    /// The skill whose clips the trials start in.
    pub from: String,
    /// The skill the policy is asked for and judged by.
    pub to: String,
    /// The success rule (None: NR).
    pub rule: Option<Rule>,
    /// The environment of the trials.
    pub env: EnvConfig,
}

/// What every cell of one evaluation shares.
pub struct Evaluator<'a> {
    /// The library and worlds (the policy's skills, no STG).
    pub setup: Setup,
    /// The policy's `[sample-stf]` parameters (the ε radii of ε-NSR).
    pub base_stf: StfParams,
    /// The policy's training settings.
    pub train: &'a TrainConfig,
    /// The policy.
    pub agent: &'a Agent,
    /// The policy's frozen history encoder.
    pub he: Option<HeRuntime>,
    /// The `[eval]` settings.
    pub cfg: &'a EvalConfig,
}

impl Evaluator<'_> {
    /// `trials` episodes of the environment of `cell`, started in the clips
    /// of `cell.from`, with deterministic actions: one row per trial and
    /// the steps of the first `record` finished trials.
    ///
    /// # Errors
    /// An environment that cannot be built or does not fit the policy.
    pub fn run_cell(
        &self,
        cell: &Cell,
        seed: u64,
    ) -> Result<(Vec<etable::TrialRow>, Vec<RolloutStep>)> {
        let s = &self.setup;
        let metric = cell.metric;
        let clips: Vec<usize> = s
            .clips
            .iter()
            .copied()
            .filter(|c| s.lib.clips[*c].skill == cell.from)
            .collect();
        let mut tcfg = self.train.clone();
        tcfg.stg = false;
        tcfg.stf = false;
        tcfg.nsi = cell.env.nsi_follow;
        tcfg.p_n = 1.0;
        tcfg.episode_length = 100_000; // follow the reference to its end
        let stf = start_params(&tcfg, &self.base_stf);
        let (cfg, n) = (self.cfg, self.cfg.envs.min(self.cfg.trials).max(1));
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut env = environment_with(
            s,
            &clips,
            stf,
            cell.env.clone(),
            self.he.clone(),
            n,
            &mut rng,
        )?;
        ensure!(
            env.obs_dim() == self.agent.obs_dim(),
            "the policy takes {} observation values; this environment gives {}",
            self.agent.obs_dim(),
            env.obs_dim()
        );
        let mut recording = cfg.record > 0;
        env.set_recording(recording);
        let mut rows = Vec::with_capacity(cfg.trials);
        let mut recorded = Vec::new();
        let mut running: Vec<Vec<RolloutStep>> = vec![Vec::new(); n];
        let mut judges: Vec<Option<Judge>> = (0..n).map(|_| cell.rule.map(Judge::new)).collect();
        let mut sums = vec![(0.0f64, 0usize, 0usize); n];
        // object 0's height over each running trial's last steps
        let mut late_z: Vec<std::collections::VecDeque<f32>> =
            vec![std::collections::VecDeque::with_capacity(etable::LATE_APEX_STEPS); n];
        // each environment runs trials in turn until `trials` have started
        let mut started = n;
        let mut active = vec![true; n];
        while active.iter().any(|a| *a) {
            let obs = env.observe();
            let act = self.agent.act(&obs, true, &mut rng)?;
            let r = env.step(&act.actions, &mut rng)?;
            let mut recs = env.take_recorded();
            for e in 0..n {
                if !active[e] {
                    continue;
                }
                if let Some(j) = judges[e].as_mut() {
                    j.update(&env.probes()[e]);
                }
                sums[e].2 += 1;
                if late_z[e].len() == etable::LATE_APEX_STEPS {
                    late_z[e].pop_front();
                }
                late_z[e].push_back(env.probes()[e].obj.first().map_or(f32::NAN, |o| o[2]));
                if let Some(sm) = env.sm_rewards()[e] {
                    sums[e].0 += sm;
                    sums[e].1 += 1;
                }
                if let Some(rec) = recs.get_mut(e).and_then(Option::take) {
                    running[e].push(RolloutStep {
                        metric: cell.metric.as_str().to_string(),
                        from: cell.from.clone(),
                        to: cell.to.clone(),
                        trial: 0,
                        step: sums[e].2 as u32,
                        reference: rec.reference,
                        masked: rec.reference.is_none(),
                        sm_reward: env.sm_rewards()[e],
                        posture: rec.posture,
                        hand_ball_distance: rec.hand_ball_distance,
                        hand_ball_touch: rec.hand_ball_touch,
                        hand_target_distance: rec.hand_target_distance,
                        hand_target: rec.hand_target,
                        hand_target_posed: rec.hand_target_posed,
                        hand_target_applied: rec.hand_target_applied,
                        pushing_hand_pos: rec.pushing_hand_pos,
                    });
                }
                if r.terminated[e] || r.truncated[e] {
                    let trial = rows.len() as u32;
                    let steps = std::mem::take(&mut running[e]);
                    if (trial as usize) < cfg.record {
                        recorded.extend(steps.into_iter().map(|s| RolloutStep { trial, ..s }));
                    }
                    rows.push(etable::TrialRow {
                        metric,
                        from: cell.from.clone(),
                        to: cell.to.clone(),
                        trial,
                        success: judges[e].as_ref().map(Judge::success),
                        steps: sums[e].2 as u32,
                        mean_sm: if sums[e].1 > 0 {
                            sums[e].0 / sums[e].1 as f64
                        } else {
                            f64::NAN
                        },
                        final_root_z: env.probes()[e].root[2],
                        down_step: judges[e]
                            .as_ref()
                            .and_then(Judge::down_step)
                            .map(|d| d as u32),
                        late_obj_apex: std::mem::take(&mut late_z[e])
                            .into_iter()
                            .fold(f32::NAN, f32::max),
                    });
                    sums[e] = (0.0, 0, 0);
                    judges[e] = cell.rule.map(Judge::new);
                    if started < cfg.trials {
                        started += 1;
                    } else {
                        active[e] = false;
                    }
                }
            }
            // trial numbers follow the finishing order: once `record`
            // trials have finished, no running trial will be kept
            if recording && rows.len() >= cfg.record {
                recording = false;
                env.set_recording(false);
                running.iter_mut().for_each(Vec::clear);
            }
        }
        Ok((rows, recorded))
    }
}

/// Read a `skillaug train` output folder `policy` (its `policy.meta.json`
/// and `policy.safetensors`) and check it against the clips of `lib`
/// (read from `input`): dataset, skeleton and every trained clip. Returns
/// the description, the agent and the history encoder's folder.
///
/// # Errors
/// A missing or unreadable policy, one of another dataset or of clips the
/// library lacks, or a history encoder that is not where it says.
pub fn load_policy(
    policy: &Path,
    lib: &MotionLib,
    input: &Path,
) -> Result<(PolicyMeta, Agent, Option<PathBuf>)> {
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
    let on = meta.train.push_feed_forward != crate::rl::config::PushJoints::Off;
    if on && meta.push_feed_forward.is_empty() {
        bail!(
            "{}: train.push_feed_forward is on but the description holds no push_feed_forward \
             offsets (keep the file `skillaug train` wrote)",
            mp.display()
        );
    }
    for (i, p) in meta.push_feed_forward.iter().enumerate() {
        let at = format!(
            "{}: push_feed_forward[{i}] (clip `{}`, frames {}..{})",
            mp.display(),
            p.clip,
            p.start,
            p.release
        );
        let Some(c) = lib.clips.iter().position(|r| r.name == p.clip) else {
            bail!("{at}: {} holds no such clip", input.display());
        };
        let n = lib.frames[c].frames;
        if !(p.start < p.release && p.release < n) {
            bail!("{at}: the clip has frames 0..{n} in {}", input.display());
        }
        if p.offset.len() != meta.act_dim || p.offset.iter().any(|x| !x.is_finite()) {
            bail!(
                "{at}: the offset needs {} finite values (one per action), it has {}",
                meta.act_dim,
                p.offset.len()
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
    Ok((meta, agent, he_dir))
}

/// The cells of an evaluation of the policy `meta` on `lib` with `cfg`, in
/// order (per skill: SR, ε-NSR, NR; then TSR per pair), and a warning for
/// every target skill whose trials `eval.steps` makes shorter than its rule
/// needs.
pub fn plan_cells(
    cfg: &EvalConfig,
    meta: &PolicyMeta,
    lib: &MotionLib,
) -> (Vec<Cell>, Vec<String>) {
    let kind = DatasetKind::of_library(lib);
    let t = &meta.train;
    let base = EnvConfig {
        early_termination: false,
        masked_reward: MaskedReward::Zero,
        reward: crate::reward::RewardOptions {
            contacts: t.contacts,
            contact_detect: t.contact_detect,
            contact_radius: t.contact_radius,
            root_rot: t.root_rot,
            smoothness: t.smoothness,
            // trials are scored with the paper's weights, whatever
            // `train.reward_weights` trained the policy on
            weights: Default::default(),
        },
        residual_action: t.residual_action,
        reference_obs: t.reference_obs,
        feed_forward_lead: t.feed_forward_lead,
        velocity_feed_forward: t.velocity_feed_forward,
        velocity_feed_forward_joints: t.velocity_feed_forward_joints,
        residual_scale: t.residual_scale as f32,
        residual_scale_joints: t.residual_scale_joints,
        seam_blend_steps: t.seam_blend_steps,
        seam_masked_min: t.seam_masked_min,
        seam_match: t.seam_match,
        ball_clock_frames: t.ball_clock_frames,
        // the clips are checked by `load_policy`
        push_feed_forward: meta
            .push_feed_forward
            .iter()
            .filter_map(|p| {
                let clip = lib.clips.iter().position(|c| c.name == p.clip)?;
                Some(crate::rl::humanoid::PushFeedForward {
                    clip,
                    frames: p.start..p.release,
                    offset: p.offset.clone(),
                })
            })
            .collect(),
        ..EnvConfig::training(t.method)
    };
    let class_of = |skill: &str| -> u32 {
        lib.clips
            .iter()
            .find(|c| c.skill == skill)
            .map_or(0, |c| c.class as u32)
    };
    let steps = |r: Rule| {
        if cfg.steps > 0 {
            cfg.steps
        } else {
            r.trial_steps()
        }
    };
    let want = |m: Metric| cfg.metrics.iter().any(|x| x == m.as_str());
    let cell = |metric: Metric, from: &str, to: &str, rule: Option<Rule>, env: EnvConfig| Cell {
        metric,
        from: from.to_string(),
        to: to.to_string(),
        rule,
        env,
    };
    let mut cells = Vec::new();
    for skill in &meta.skills {
        let rule = Rule::of_skill(skill, shot_target(lib, skill));
        if let Some(r) = rule {
            let trial = EnvConfig {
                fixed_length: Some(steps(r)),
                ..base.clone()
            };
            let trial = EnvConfig {
                continue_steps: if t.residual_action || t.reference_obs {
                    steps(r)
                } else {
                    0
                },
                ..trial
            };
            if want(Metric::Sr) {
                cells.push(cell(Metric::Sr, skill, skill, rule, trial.clone()));
            }
            if want(Metric::Nsr) {
                let parahome = kind == DatasetKind::ParaHome;
                let env = EnvConfig {
                    object_perturb: parahome,
                    nsi_follow: !parahome,
                    ..trial
                };
                cells.push(cell(Metric::Nsr, skill, skill, rule, env));
            }
        }
        if want(Metric::Nr) {
            cells.push(cell(Metric::Nr, skill, skill, None, base.clone()));
        }
    }
    if want(Metric::Tsr) {
        for (a, b) in tsr_pairs(kind, &meta.skills) {
            let Some(r) = Rule::of_skill(&b, shot_target(lib, &b)) else {
                continue;
            };
            // a policy that needs its reference follows the first skill's,
            // continued, while the condition asks for the second
            let env = EnvConfig {
                fixed_length: Some(steps(r)),
                condition: Some(class_of(&b)),
                continue_steps: if t.residual_action || t.reference_obs {
                    steps(r)
                } else {
                    0
                },
                ..base.clone()
            };
            cells.push(cell(Metric::Tsr, &a, &b, Some(r), env));
        }
    }
    let mut warned = std::collections::BTreeSet::new();
    let mut warnings = Vec::new();
    for c in &cells {
        if let (Some(r), Some(n)) = (c.rule, c.env.fixed_length) {
            if n < r.min_steps() && warned.insert(c.to.clone()) {
                warnings.push(format!(
                    "eval.steps = {n}: {} trials are shorter than its success rule \
                     needs ({} steps; its own length is {}): every one is scored as a failure",
                    c.to,
                    r.min_steps(),
                    r.trial_steps()
                ));
            }
        }
    }
    (cells, warnings)
}

impl Evaluator<'_> {
    /// Every cell in turn, cell k with seed `seed * 1_000_003 + k + 1`:
    /// the trial rows and recorded steps of all of them.
    ///
    /// # Errors
    /// As [`Evaluator::run_cell`].
    pub fn run_all(
        &self,
        cells: &[Cell],
        seed: u64,
    ) -> Result<(Vec<etable::TrialRow>, Vec<RolloutStep>)> {
        let mut rows = Vec::new();
        let mut recorded = Vec::new();
        for (k, c) in cells.iter().enumerate() {
            let seed = seed.wrapping_mul(1_000_003).wrapping_add(k as u64 + 1);
            let (r, rec) = self.run_cell(c, seed)?;
            rows.extend(r);
            recorded.extend(rec);
        }
        Ok((rows, recorded))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::method_label;

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
