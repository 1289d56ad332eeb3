//! The settings of the `[build-stg]` recipe table ([`StgConfig`]) and of
//! the `[sample-stf]` table ([`StfConfig`]), which both `skillaug
//! sample-stf` and the trainer's STF starts read (one recipe drives both),
//! and their translation into the library's parameters. The
//! trainer takes p_e, p_n and the trajectory length T from its own table
//! instead (`train.p_e`, `train.p_n`, `train.episode_length`, with the
//! switches; `crate::rl::trainer::start_params`): there `sample-stf.p_e`,
//! `p_n` and `horizon` have no effect.

use crate::augment::ats::{AtsParams, Update};
use crate::augment::stf::{Connect, Eps, Noise, Order, Search, StfParams};
use crate::augment::stg::StgParams;
use crate::augment::MaskRule;
use crate::reward::Align;
use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Settings of the `[build-stg]` recipe table.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StgConfig {
    /// Similarity threshold tau (Table 7).
    pub tau: f64,
    /// Maximum masked states N_max (Table 7).
    pub n_max: u32,
    /// Eq. 20 as printed ("paper", ceil) or the reference code's floor rule ("reference").
    pub mask_rule: MaskRule,
    /// Align the start state's heading too, not only its root x, y (reference code; paper: x, y only).
    pub align_yaw: bool,
    /// The reference code's direction: for each frame of A, the best state of each other skill.
    pub per_target: bool,
}

impl crate::config::Validate for StgConfig {
    fn validate(&self, stage: &str) -> Result<()> {
        let c = crate::config::Check::new(stage);
        c.range("tau", self.tau, 0.0, 1.0)?;
        c.count("n_max", self.n_max as u64, 0, 10_000)
    }
}

impl Default for StgConfig {
    fn default() -> Self {
        StgConfig {
            tau: 1e-10,
            n_max: 10,
            mask_rule: MaskRule::Paper,
            align_yaw: true,
            per_target: false,
        }
    }
}

impl StgConfig {
    /// The library's parameters ([`crate::augment::stg::build`]): root x, y
    /// always aligned, the heading when `align_yaw`.
    pub fn params(&self) -> StgParams {
        StgParams {
            tau: self.tau,
            n_max: self.n_max,
            mask_rule: self.mask_rule,
            align: Align {
                xy: true,
                yaw: self.align_yaw,
            },
            per_target: self.per_target,
        }
    }
}

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
